"""``bench control --episodes FILE``: episodes are logged as they end and a later run reuses them."""

from __future__ import annotations

import argparse
import json

from hydrosoft.bench import control
from hydrosoft.bench.episode_log import EpisodeLog
from hydrosoft.tasks import evaluation


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    control.add_arguments(parser)
    return parser.parse_args(list(argv))


def quick_run(log_path, tmp_path, *extra: str) -> argparse.Namespace:
    return parse("--tasks", "rotation", "--models", "nh", "--plants", "same", "--quick", "--steps", "2",
                 "--goals", "2", "--rate-solves", "0", "--json", "--out", str(tmp_path), "--episodes",
                 str(log_path), *extra)


def count_episodes(monkeypatch) -> list[str]:
    """The loop of every episode run from now on, in order (``run_episode`` wrapped)."""
    ran = []
    real_episode = evaluation.run_episode

    def counted(setup, goal, loop, steps=None):
        ran.append(loop)
        return real_episode(setup, goal, loop, steps=steps)

    monkeypatch.setattr(evaluation, "run_episode", counted)
    return ran


def test_a_stopped_run_resumes_with_the_logged_episodes_and_runs_only_the_rest(tmp_path, capsys, monkeypatch):
    log_path = tmp_path / "episodes.jsonl"
    assert control.run(quick_run(log_path, tmp_path, "--loops", "closed")) == 0
    first = json.loads(capsys.readouterr().out)
    lines = log_path.read_text().splitlines()
    assert len(lines) == 2 and all(json.loads(line)["loop"] == "closed" for line in lines)

    ran = count_episodes(monkeypatch)
    assert control.run(quick_run(log_path, tmp_path)) == 0  # open and closed: only the open ones run
    out, err = capsys.readouterr()
    second = json.loads(out)
    assert ran == ["open", "open"]
    assert len(log_path.read_text().splitlines()) == 4
    closed = [row for row in second["rows"] if row["loop"] == "closed"][0]
    assert closed["errors_mm"] == first["rows"][0]["errors_mm"]  # reused, not re-run
    assert closed["episodes_wall_s"] == first["rows"][0]["episodes_wall_s"] > 0
    assert second["settings"]["episodes"]["reused"] == 2 and second["settings"]["episodes"]["ran"] == 2
    assert "(logged)" in err


def test_episodes_of_other_settings_and_broken_lines_are_counted_not_used(tmp_path, capsys, monkeypatch):
    log_path = tmp_path / "episodes.jsonl"
    assert control.run(quick_run(log_path, tmp_path, "--loops", "closed", "--goals", "1")) == 0
    capsys.readouterr()
    with log_path.open("a") as out:
        out.write('{"plant": "same", "task": "rot')  # a run killed while writing its line
    log = EpisodeLog(log_path, {"anything": "else"})
    assert (len(log.episodes), log.other_settings, log.malformed) == (0, 1, 1)

    ran = count_episodes(monkeypatch)
    assert control.run(quick_run(log_path, tmp_path, "--loops", "closed", "--goals", "1",
                                 "--pose-noise-mm", "0.5")) == 0  # other settings: runs again
    document = json.loads(capsys.readouterr().out)
    assert ran == ["closed"]
    assert document["settings"]["episodes"]["other_settings"] == 1
    assert document["settings"]["episodes"]["malformed"] == 1


def test_goals_split_over_runs_add_up_to_the_whole_run(tmp_path, capsys, monkeypatch):
    first, second = tmp_path / "first.jsonl", tmp_path / "second.jsonl"
    ran = count_episodes(monkeypatch)
    assert control.run(quick_run(first, tmp_path, "--loops", "closed", "--goal-indices", "1")) == 0
    part = json.loads(capsys.readouterr().out)
    assert ran == ["closed"] and part["rows"][0]["goals"] == 1 and part["settings"]["goal_indices"] == [1]
    assert [json.loads(line)["goal"] for line in first.read_text().splitlines()] == [1]
    assert control.run(quick_run(second, tmp_path, "--loops", "closed", "--goal-indices", "0")) == 0
    capsys.readouterr()

    whole = tmp_path / "whole.jsonl"
    whole.write_text(first.read_text() + second.read_text())
    ran.clear()
    assert control.run(quick_run(whole, tmp_path, "--loops", "closed")) == 0
    document = json.loads(capsys.readouterr().out)
    assert ran == []  # both goals come from the concatenated logs
    assert document["rows"][0]["goals"] == 2 and document["rows"][0]["errors_mm"][1] == part["rows"][0]["errors_mm"][0]


def test_goal_indices_outside_the_goals_are_refused(tmp_path, capsys):
    for bad in ("2", "0,0", "x"):
        assert control.run(quick_run(tmp_path / "log.jsonl", tmp_path, "--goal-indices", bad)) == 2
        assert "--goal-indices" in capsys.readouterr().err
