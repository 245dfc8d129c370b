"""The hydrosoft-stack command line: help texts, the demo, and the services' own command lines."""

import importlib
import subprocess
import sys

import pytest

from hydrosoft.services.commands.cli import COMMANDS, GROUPS, main


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    for command in ("demo", "bench", "simulate", "calibrate"):
        assert command in out
    for group, commands in (("bench", ("model", "control", "tradeoff", "bus", "tracker")),
                            ("simulate", ("ur", "ft300")), ("calibrate", ("camera",))):
        with pytest.raises(SystemExit):
            main([group, "--help"])
        out = capsys.readouterr().out
        for command in commands:
            assert command in out


def test_no_command_prints_help(capsys):
    assert main([]) == 0
    assert "usage: hydrosoft-stack" in capsys.readouterr().out


def test_demo_pushes_the_cube_forward(capsys):
    assert main(["demo", "--steps", "6", "--speed", "3"]) == 0
    out = capsys.readouterr().out
    last = [line for line in out.splitlines() if line.strip().startswith("6 ")][0].split()
    assert float(last[1]) == pytest.approx(18.0)  # bubble x in mm
    assert 0.5 < float(last[2]) < 18.0  # the object followed, with slip


def test_unknown_model_is_rejected_with_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["demo", "--model", "rigid"])
    assert exit_info.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_console_script_entry_point_runs():
    result = subprocess.run([sys.executable, "-m", "hydrosoft.services.commands.cli", "--help"], capture_output=True, text=True)
    assert result.returncode == 0 and "hydrosoft-stack" in result.stdout


@pytest.mark.parametrize("module", ["sim_world", "tag_tracker", "planner", "arm_commander", "ft_reader",
                                    "bubble_camera"])
def test_every_service_refuses_a_missing_config_with_exit_code_2(module, tmp_path, capsys):
    service = importlib.import_module(f"hydrosoft.services.{module}")
    assert service.main([str(tmp_path / "missing.toml")]) == 2
    assert "missing.toml does not exist" in capsys.readouterr().err


@pytest.mark.parametrize("command", [[name] for name in COMMANDS] + [["demo"]] + [[group] for group in GROUPS]
                         + [[group, name] for group, (_, names) in GROUPS.items() for name in names],
                         ids=lambda command: " ".join(command))
def test_every_commands_help_prints_and_exits_0(command, capsys):
    """argparse formats help texts with %: a bare "95 %" in one breaks that command's --help."""
    with pytest.raises(SystemExit) as exit_info:
        main([*command, "--help"])
    assert exit_info.value.code == 0 and "usage: hydrosoft-stack" in capsys.readouterr().out
