"""``hydrosoft-stack bench bus`` runs briefly, measures every row and prints them as JSON or a table."""

import argparse
import json

from loopback import free_loopback_address

import numpy as np

from hydrosoft.services.benchmarks import bus as bench
from hydrosoft.services.benchmarks import bus_tail

ROW_KEYS = {"payload", "transport", "p50_us", "p99_us", "msgs_per_s"}


def test_bench_prints_every_row_as_json(capsys):
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    assert bench.run(parser.parse_args(["--seconds", "0.5", "--json"])) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    assert {(row["payload"], row["transport"]) for row in rows} == {
        (payload, transport) for payload in bench.RATES_HZ for transport in bench.TRANSPORTS}
    for row in rows:
        assert ROW_KEYS <= set(row)
        assert 0 < row["p50_us"] <= row["p99_us"] < 1e6  # under a second even on two busy cores
        assert row["received"] > 0.5 * row["sent"] > 0  # the subscriber kept up with the paced publisher
        assert row["msgs_per_s"] == round(row["received"] / 0.5, 1)


def test_tcp_peer_measures_the_other_hosts_address_without_and_with_curve(capsys):
    peer = free_loopback_address(21, 39, ())
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    assert bench.run(parser.parse_args(["--seconds", "0.5", "--json", "--tcp-peer", peer])) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    assert {(row["payload"], row["transport"]) for row in rows} == {
        (payload, transport) for payload in bench.RATES_HZ for transport in bench.PEER_TRANSPORTS}
    for row in rows:
        assert 0 < row["p50_us"] <= row["p99_us"] < 1e6
        assert row["received"] > 0.5 * row["sent"] > 0  # CURVE admitted the bench's own key


def test_table_has_a_line_per_row():
    rows = [bench.Row(payload="wrench", transport="ipc", p50_us=40.0, p99_us=90.5, msgs_per_s=1000.0,
                      rate_hz=1000.0, sent=500, received=500, samples=480)]
    lines = bench.format_table(rows).splitlines()
    assert lines[0].split()[:2] == ["payload", "transport"]
    assert lines[1].split()[:4] == ["wrench", "ipc", "40.0", "90.5"]


def test_non_positive_seconds_are_refused(capsys):
    assert bench.run(argparse.Namespace(seconds=0.0, json=True)) == 2
    assert "--seconds must be > 0" in capsys.readouterr().err


def test_a_message_in_flight_during_a_collection_is_told_apart():
    """``overlaps``: a message ``(stamp_ns, received_ns)`` overlaps a collection that ran at any time between the
    two, also one that began before it was sent; not one that ended before or began after."""
    samples = np.array([[0, 10], [20, 30], [40, 50], [60, 70]])
    pauses = [(5, 7, 0), (31, 39, 1), (35, 42, 0), (55, 80, 2)]
    assert bus_tail.overlaps(samples, pauses).tolist() == [True, False, True, True]
    assert bus_tail.overlaps(samples, []).tolist() == [False] * 4


def test_tail_compares_every_receive_path_with_raw_pyzmq_in_one_run(capsys):
    """``bench bus --tail``: one row per variant and transport, each round's p99 and its ratio to raw pyzmq's in
    the same round (1 for raw itself), the collections of both processes, the sender's pacing, the load average."""
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    assert bench.run(parser.parse_args(["--tail", "--seconds", "0.3", "--rounds", "1", "--json"])) == 0
    report = json.loads(capsys.readouterr().out)
    rows = report["tail"]
    assert [(r["variant"], r["transport"]) for r in rows] == [
        (variant, transport) for transport in bus_tail.TRANSPORTS for variant in bus_tail.VARIANTS]
    for row in rows:
        assert row["samples"] > 0 and 0 < row["p50_us"] <= row["p99_us"] <= row["max_us"] < 1e6
        assert len(row["round_p99_us"]) == 1 and len(row["gc_per_s"]) == 3
        assert 0 <= row["over_1ms_in_gc"] <= row["over_1ms_count"]
        assert row["receiver_cpu_us_per_msg"] > 0 and row["sender_cpu_us_per_msg"] > 0
        assert row["p99_vs_raw"] == 1.0 if row["variant"] == "raw" else row["p99_vs_raw"] > 0
    assert len(report["load_average"]["before"]) == len(report["load_average"]["after"]) == 3
    assert bench.run(parser.parse_args(["--tail", "--rounds", "0"])) == 2
