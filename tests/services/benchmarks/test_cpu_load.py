import math
import signal
import subprocess
import sys
import time

import pytest

from hydrosoft.services.benchmarks.cpu_load import PERIOD_S, load_processes, main, spin_and_sleep


@pytest.mark.parametrize("cores, fractions", [(0.0, []), (0.3, [0.3]), (1.0, [1.0]), (1.5, [0.75, 0.75]),
                                              (2.0, [1.0, 1.0])])
def test_the_load_is_shared_equally_by_as_few_processes_as_can_take_it(cores, fractions):
    assert load_processes(cores) == pytest.approx(fractions)


@pytest.mark.parametrize("cores", [-0.1, math.nan, math.inf])
def test_a_load_that_is_not_a_number_of_cores_is_refused(cores):
    with pytest.raises(ValueError, match="number of cores"):
        load_processes(cores)


def test_a_process_spins_its_fraction_of_each_period_and_sleeps_the_rest():
    cycles, fraction = 30, 0.4
    start_s, start_cpu_s = time.monotonic(), time.thread_time()
    spin_and_sleep(fraction, cycles)
    wall_s, cpu_s = time.monotonic() - start_s, time.thread_time() - start_cpu_s
    # It never takes more than its fraction (a load that took a whole core would misstate the hour it stands for)...
    assert cpu_s <= fraction * cycles * PERIOD_S + 0.02
    # ... and it does spin: the cycles last their periods, and the spinning is CPU time, not sleep.
    assert wall_s >= (cycles - 1) * PERIOD_S
    assert cpu_s >= 0.1 * fraction * cycles * PERIOD_S


@pytest.mark.parametrize("fraction", [0.0, 1.5, -0.2, math.nan])
def test_a_fraction_outside_one_core_is_refused(fraction):
    with pytest.raises(ValueError, match="fraction of one core"):
        spin_and_sleep(fraction, 1)


@pytest.mark.parametrize("argv", [[], ["lots"], ["2"]])
def test_the_command_line_refuses_a_missing_or_bad_fraction(argv, capsys):
    assert main(argv) == 2
    assert "usage" in capsys.readouterr().err


def test_the_process_runs_until_interrupted_and_exits_cleanly():
    process = subprocess.Popen([sys.executable, "-m", "hydrosoft.services.benchmarks.cpu_load", "0.2"])
    try:
        time.sleep(1.0)
        assert process.poll() is None
        process.send_signal(signal.SIGINT)
        assert process.wait(10) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(10)
