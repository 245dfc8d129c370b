"""``hydrosoft-stack bench bus`` runs briefly, measures every row and prints them as JSON or a table."""

import argparse
import json

from loopback import free_loopback_address

from hydrosoft.services.benchmarks import bus as bench

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
