"""Finished episodes written to a folder and read back exactly, so that a killed deploy resumes
from the jobs it had finished instead of from its first episode.

A folder holds `episodes.json` (each episode's outcome and spec scalars, its planning calls and
the job's wall time) and `arrays.safetensors` (the specs' and traces' arrays). JSON floats and
safetensors arrays round-trip bit for bit, so a report made from episodes read back is the one
made from the episodes in memory (`tests/test_episode_store.py`). Nothing is unpickled.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from safetensors import SafetensorError
from safetensors.numpy import load_file, save_file

from pipeline.evaluation.episodes import EpisodeResult, EpisodeTrace, PlanCall
from pipeline.evaluation.tasks import EpisodeSpec
from pipeline.io import atomic_dir

FORMAT = 1
_SCALARS = (
    "steps", "steps_to_goal", "steps_to_goal_gym", "min_distance", "final_distance", "fell_at",
    "replans", "plan_seconds", "error", "subtasks_done", "agent",
)  # fmt: skip
_ARRAY_LISTS = ("states", "actions", "plans", "plan_targets")  # EpisodeTrace's lists of arrays


def _plain(value: Any) -> Any:
    """NumPy scalars as Python numbers (JSON writes them, and reads back the same value)."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON")


def _put_list(arrays: dict[str, np.ndarray], key: str, items: list[np.ndarray]) -> str:
    """Store a list of arrays under `key`: stacked when they share shape and dtype ("stacked"),
    else one entry per item ("items"); an empty list stores nothing ("empty")."""
    if not items:
        return "empty"
    first = items[0]
    if all(a.shape == first.shape and a.dtype == first.dtype for a in items):
        arrays[key] = np.ascontiguousarray(np.stack(items))
        return "stacked"
    for k, a in enumerate(items):
        arrays[f"{key}.{k}"] = np.ascontiguousarray(a)
    return "items"


def _get_list(arrays: dict[str, np.ndarray], key: str, layout: str, count: int) -> list:
    if layout == "empty":
        return []
    if layout == "stacked":
        return list(arrays[key])
    return [arrays[f"{key}.{k}"] for k in range(count)]


def save_episodes(
    directory: Path, results: list[EpisodeResult], calls: list[PlanCall], seconds: float
) -> None:
    """Write `results` (traces included), `calls` and `seconds` to `directory`, atomically."""
    arrays: dict[str, np.ndarray] = {}
    rows = []
    for i, r in enumerate(results):
        s, t = r.spec, r.trace
        arrays[f"{i}.start"] = np.ascontiguousarray(s.start)
        arrays[f"{i}.goal"] = np.ascontiguousarray(s.goal)
        if s.physics is not None:
            arrays[f"{i}.physics"] = np.ascontiguousarray(s.physics)
        layouts = {f: _put_list(arrays, f"{i}.{f}", getattr(t, f)) for f in _ARRAY_LISTS}
        rows.append(
            {
                "spec": {"task": s.task, "index": s.index, "seed": s.seed},
                **{f: getattr(r, f) for f in _SCALARS},
                "trace": {
                    "layouts": layouts,
                    "counts": {f: len(getattr(t, f)) for f in _ARRAY_LISTS},
                    "replan_steps": t.replan_steps,
                    "plan_costs": t.plan_costs,
                },
            }
        )
    meta = {
        "format": FORMAT,
        "seconds": seconds,
        "calls": [[c.seconds, c.envs] for c in calls],
        "episodes": rows,
    }
    with atomic_dir(directory) as tmp:
        save_file(arrays, str(tmp / "arrays.safetensors"))
        (tmp / "episodes.json").write_text(json.dumps(meta, default=_plain))


def load_episodes(directory: Path) -> tuple[list[EpisodeResult], list[PlanCall], float] | None:
    """What `save_episodes` wrote to `directory`; None where it holds nothing complete and
    readable (never written, another format, damaged: the caller runs those episodes again)."""
    try:
        meta = json.loads((directory / "episodes.json").read_text())
        arrays = load_file(str(directory / "arrays.safetensors"))
        if meta.get("format") != FORMAT:
            return None
        results = [_episode(i, row, arrays) for i, row in enumerate(meta["episodes"])]
        calls = [PlanCall(float(seconds), int(envs)) for seconds, envs in meta["calls"]]
        return results, calls, float(meta["seconds"])
    except (OSError, ValueError, KeyError, TypeError, SafetensorError):
        return None


def _episode(i: int, row: dict, arrays: dict[str, np.ndarray]) -> EpisodeResult:
    s, t = row["spec"], row["trace"]
    spec = EpisodeSpec(
        s["task"], s["index"], arrays[f"{i}.start"], arrays[f"{i}.goal"], s["seed"],
        arrays.get(f"{i}.physics"),
    )  # fmt: skip
    lists = {
        f: _get_list(arrays, f"{i}.{f}", t["layouts"][f], t["counts"][f]) for f in _ARRAY_LISTS
    }
    trace = EpisodeTrace(
        replan_steps=list(t["replan_steps"]), plan_costs=list(t["plan_costs"]), **lists
    )
    return EpisodeResult(spec, **{f: row[f] for f in _SCALARS}, trace=trace)
