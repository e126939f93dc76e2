"""Export an oposm MCAP dataset as a LeRobot v3.0 dataset, written by LeRobot's own writer.

Features: `observation.state` and `action` (float32, LeRobot's convention, named after our state
and action names), `observation.goal` (float32) and `observation.physics` (float64: it holds the
simulated time, which float32 would round) when the dataset has them, and `next.reward`,
`next.done`, `next.success` for rewards, terminals and goal_reached. `LeRobotDataset.create` +
`add_frame` + `save_episode` + `finalize` write it (timestamps = frame_index / fps, the dataset's
fps = 1 / control_period); our `DatasetInfo` goes to `meta/oposm.json`, which LeRobot ignores and
`oposm ingest` with `source: lerobot` reads back. The folder appears only when complete.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.dataset import DatasetInfo, Episode
from pipeline.errors import UserError
from pipeline.io import atomic_dir
from pipeline.recording import iter_episodes, read_info, summarize
from pipeline.recording.metadata import encode_info
from pipeline.sources.common import with_progress
from pipeline.sources.lerobot_import import GOAL_FEATURE, PHYSICS_FEATURE, SIDECAR


@dataclass(frozen=True)
class ExportSummary:
    """What `export_lerobot` wrote: the folder, its repo id, episodes, frames and fps."""

    root: Path
    repo_id: str
    episodes: int
    frames: int
    fps: int


def _fps(info: DatasetInfo) -> int:
    fps = 1.0 / info.control_period
    if abs(fps - round(fps)) > 1e-6 * fps:
        raise UserError(
            f"LeRobot needs an integer fps; {info.name} has a control period of "
            f"{info.control_period} s ({fps:.4f} Hz)"
        )
    return int(round(fps))


def _features(info: DatasetInfo, first: Episode) -> dict[str, dict[str, Any]]:
    """LeRobot feature specs for what the dataset has (optional flags seen on its first episode)."""

    def vector(dtype: str, dim: int, names: list[str] | None) -> dict[str, Any]:
        return {"dtype": dtype, "shape": (dim,), "names": names}

    features = {
        "observation.state": vector("float32", info.state_dim, list(info.state_names)),
        "action": vector("float32", info.action_dim, list(info.action_names)),
    }
    if info.goal_dim:
        features[GOAL_FEATURE] = vector("float32", info.goal_dim, None)
    if info.physics_dim:
        features[PHYSICS_FEATURE] = vector("float64", info.physics_dim, None)
    for key, field, dtype in (
        ("next.reward", "rewards", "float32"),
        ("next.done", "terminals", "bool"),
        ("next.success", "goal_reached", "bool"),
    ):
        if getattr(first, field) is not None:
            features[key] = vector(dtype, 1, None)
    return features


def _frames(ep: Episode, features: dict[str, dict[str, Any]], task: str) -> Any:
    """The frames of one episode as `add_frame` dicts, cast to the declared dtypes."""
    columns = {
        "observation.state": ep.observations,
        "action": ep.actions,
        GOAL_FEATURE: ep.goals,
        PHYSICS_FEATURE: ep.physics,
        "next.reward": None if ep.rewards is None else ep.rewards[:, None],
        "next.done": None if ep.terminals is None else ep.terminals[:, None],
        "next.success": None if ep.goal_reached is None else ep.goal_reached[:, None],
    }
    cast = {}
    for key, spec in features.items():
        if columns[key] is None:
            raise UserError(f"episode {ep.index} has no {key} but earlier episodes do")
        cast[key] = np.ascontiguousarray(columns[key], dtype=spec["dtype"])
    for t in range(len(ep)):
        frame = {key: values[t] for key, values in cast.items()}
        frame["task"] = task
        yield frame


def export_lerobot(
    mcap: str | Path,
    root: str | Path,
    repo_id: str | None = None,
    task: str | None = None,
    overwrite: bool = False,
    progress: bool = False,
) -> ExportSummary:
    """Write the MCAP dataset `mcap` as a LeRobot v3.0 dataset in the folder `root`.

    Args:
        mcap: An oposm MCAP dataset.
        root: Destination folder (must not exist, unless `overwrite`).
        repo_id: LeRobot repo id; default `local/<dataset name>`.
        task: The task string of every frame; default "reach goals in <env id>" or the name.
        overwrite: Replace an existing `root`.
        progress: Show a progress bar.
    """
    import datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    info = read_info(mcap)
    root, fps = Path(root), _fps(info)
    if root.exists() and any(root.iterdir()) and not overwrite:
        raise UserError(f"{root} already exists; pass --overwrite to replace it")
    repo_id = repo_id or f"local/{info.name}"
    task = task or (f"reach goals in {info.env_id}" if info.env_id else info.name)
    stream = iter_episodes(mcap)
    first = next(stream)
    features = _features(info, first)
    bars = datasets.is_progress_bar_enabled()
    datasets.disable_progress_bars()  # one "Map" bar per saved episode otherwise
    episodes = frames = 0
    try:
        with atomic_dir(root) as tmp:
            tmp.rmdir()  # LeRobotDataset.create makes the folder itself
            ds = LeRobotDataset.create(
                repo_id,
                fps=fps,
                features=features,
                root=tmp,
                use_videos=False,
                video_backend="pyav",
            )
            total = int(summarize(mcap)["steps"])
            for ep in with_progress(itertools.chain([first], stream), total, "export", progress):
                for frame in _frames(ep, features, task):
                    ds.add_frame(frame)
                ds.save_episode()
                episodes, frames = episodes + 1, frames + len(ep)
            ds.finalize()
            sidecar = {"dataset": encode_info(info), "exported_from": str(Path(mcap).resolve())}
            (tmp / SIDECAR).write_text(json.dumps(sidecar, indent=2) + "\n")
    finally:
        if bars:
            datasets.enable_progress_bars()
    return ExportSummary(root, repo_id, episodes, frames, fps)
