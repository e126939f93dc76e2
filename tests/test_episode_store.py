"""Finished episodes written and read back exactly (`pipeline.evaluation.episode_store`): what a
killed deploy resumes from."""

import json

import numpy as np
import pytest

from pipeline.evaluation.episode_store import load_episodes, save_episodes
from pipeline.evaluation.episodes import EpisodeResult, EpisodeTrace, PlanCall
from pipeline.evaluation.tasks import EpisodeSpec


def _episode(rng: np.random.Generator, index: int, physics: bool, ragged: bool) -> EpisodeResult:
    n = int(rng.integers(3, 9))
    spec = EpisodeSpec(
        "ogbench-task2", index, rng.normal(size=4), rng.normal(size=2), int(rng.integers(1e9)),
        rng.normal(size=7) if physics else None,
    )  # fmt: skip
    plans = [rng.normal(size=(4 - (k % 2 if ragged else 0), 4)) for k in range(3)]
    trace = EpisodeTrace(
        states=[rng.normal(size=4) for _ in range(n + 1)],
        actions=[rng.normal(size=2).astype(np.float32) for _ in range(n)],
        replan_steps=[0, 2, 4],
        plans=plans,
        plan_costs=[float(c) for c in rng.normal(size=3)],
        plan_targets=[] if ragged else [rng.normal(size=2) for _ in range(3)],
    )
    return EpisodeResult(
        spec, steps=n, steps_to_goal=None if ragged else n, steps_to_goal_gym=None,
        min_distance=np.float64(rng.random()), final_distance=float("inf"), fell_at=2,
        replans=3, plan_seconds=0.1 + rng.random(), error="ValueError: x" if ragged else None,
        subtasks_done=[3, None] if physics else None, agent="oposm", trace=trace,
    )  # fmt: skip


def _same(a, b) -> None:
    """Equal values, with arrays of the same dtype and shape, bit for bit."""
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape
        assert a.tobytes() == b.tobytes()
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _same(x, y)
    elif isinstance(a, float) and np.isnan(a):
        assert np.isnan(b)
    else:
        assert a == b and (a is None) == (b is None)


def test_episodes_read_back_bit_for_bit(tmp_path):
    rng = np.random.default_rng(0)
    results = [_episode(rng, i, physics=i % 2 == 0, ragged=i == 1) for i in range(4)]
    calls = [PlanCall(0.123456789, 2), PlanCall(1e-7, 1)]
    save_episodes(tmp_path / "job", results, calls, 12.5)

    read, read_calls, seconds = load_episodes(tmp_path / "job")
    assert seconds == 12.5 and read_calls == calls and len(read) == len(results)
    for a, b in zip(results, read, strict=True):
        for field in ("task", "index", "seed", "start", "goal", "physics"):
            _same(getattr(a.spec, field), getattr(b.spec, field))
        for field in ("steps", "steps_to_goal", "steps_to_goal_gym", "min_distance",
                      "final_distance", "fell_at", "replans", "plan_seconds", "error",
                      "subtasks_done", "agent"):  # fmt: skip
            _same(getattr(a, field), getattr(b, field))
        for field in ("states", "actions", "replan_steps", "plans", "plan_costs", "plan_targets"):
            _same(getattr(a.trace, field), getattr(b.trace, field))
        assert json.dumps(a.to_json()) == json.dumps(b.to_json())


@pytest.mark.parametrize("damage", ["truncate arrays", "other format", "no episodes file"])
def test_a_damaged_or_foreign_folder_reads_as_nothing_to_resume(tmp_path, damage):
    rng = np.random.default_rng(1)
    folder = tmp_path / "job"
    save_episodes(folder, [_episode(rng, 0, physics=True, ragged=False)], [], 1.0)
    if damage == "truncate arrays":
        data = (folder / "arrays.safetensors").read_bytes()
        (folder / "arrays.safetensors").write_bytes(data[: len(data) // 2])
    elif damage == "other format":
        meta = json.loads((folder / "episodes.json").read_text())
        (folder / "episodes.json").write_text(json.dumps({**meta, "format": 99}))
    else:
        (folder / "episodes.json").unlink()
    assert load_episodes(folder) is None
    assert load_episodes(tmp_path / "never-written") is None
