"""An append-only log of finished benchmark episodes, so that a long ``bench control`` run can stop and resume.

Each line of the file is one JSON object: the episode's key (plant, task, model, loop, goal), the settings that
determine its outcome, the commit it ran at (``git describe``, or null outside a checkout), its wall time (s) and
its ``EpisodeResult`` without the tensors. A line is written and flushed as soon as its episode ends, so a run
that is stopped loses at most the episode in progress. A later run with the same file reuses the episodes whose
key and settings match its own and runs only the rest; lines with other settings are kept in the file and
counted, never used. Malformed lines (a run killed while writing) are counted and skipped.
"""

from __future__ import annotations

import json
import subprocess
from dataclasses import dataclass, fields
from pathlib import Path

from hydrosoft.tasks.evaluation import EpisodeResult

EpisodeKey = tuple[str, str, str, str, int]
"""(plant, task, model, loop, goal index)."""

_TENSOR_FIELDS = ("actions", "final_pose")


def current_commit(repo: Path | None = None) -> str | None:
    """``git describe --always --dirty`` of the checkout holding this package, or None when there is none."""
    where = repo or Path(__file__).resolve().parent
    try:
        done = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=where, capture_output=True,
                              text=True, timeout=10, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    if done.returncode != 0:
        return None
    return done.stdout.strip() or None


@dataclass
class LoggedEpisode:
    """One line of the log: the episode's result, its wall time (s) and the commit it ran at."""

    result: EpisodeResult
    wall_s: float
    commit: str | None


class EpisodeLog:
    """The episodes of ``path`` that match ``settings`` (a JSON-serialisable dict), and appending new ones.

    Attributes:
        episodes: the matching episodes by key (a key logged twice keeps its last line).
        other_settings: lines whose settings differ from ``settings`` (not used).
        malformed: lines that could not be read (not used).
    """

    def __init__(self, path: Path, settings: dict) -> None:
        self.path = Path(path)
        self.settings = json.loads(json.dumps(settings))  # the form a line's settings compare equal to
        self.episodes: dict[EpisodeKey, LoggedEpisode] = {}
        self.other_settings = 0
        self.malformed = 0
        self.commit = current_commit()
        if self.path.exists():
            for line in self.path.read_text().splitlines():
                if line.strip():
                    self._load(line)

    def _load(self, line: str) -> None:
        try:
            record = json.loads(line)
            key = (record["plant"], record["task"], record["model"], record["loop"], int(record["goal"]))
            names = {f.name for f in fields(EpisodeResult)} - set(_TENSOR_FIELDS)
            result = EpisodeResult(**{name: record["result"][name] for name in names})
            logged = LoggedEpisode(result, float(record["wall_s"]), record.get("commit"))
            settings = record["settings"]
        except (ValueError, KeyError, TypeError):
            self.malformed += 1
            return
        if settings != self.settings:
            self.other_settings += 1
            return
        self.episodes[key] = logged

    def get(self, key: EpisodeKey) -> LoggedEpisode | None:
        """The logged episode of ``key`` run with this log's settings, or None."""
        return self.episodes.get(key)

    def append(self, key: EpisodeKey, result: EpisodeResult, wall_s: float) -> None:
        """Write ``result`` of ``key`` (ran for ``wall_s`` seconds) as one line and flush it to disk."""
        plant, task, model, loop, goal = key
        stored = {f.name: getattr(result, f.name) for f in fields(result) if f.name not in _TENSOR_FIELDS}
        record = {"plant": plant, "task": task, "model": model, "loop": loop, "goal": goal, "wall_s": wall_s,
                  "commit": self.commit, "settings": self.settings, "result": stored}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.path.open("a") as out:
            out.write(json.dumps(record) + "\n")
            out.flush()
        self.episodes[key] = LoggedEpisode(result, wall_s, self.commit)

    def commits(self, keys: list[EpisodeKey]) -> list[str]:
        """The distinct commits the episodes of ``keys`` ran at, in first-seen order ("unknown" for none)."""
        seen: list[str] = []
        for key in keys:
            logged = self.episodes.get(key)
            commit = (logged.commit if logged else self.commit) or "unknown"
            if commit not in seen:
                seen.append(commit)
        return seen
