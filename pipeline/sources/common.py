"""Helpers shared by the importers: the dataset clock, numeric checks, maze metadata, progress.

Every importer returns an `ImportedDataset`: a `DatasetInfo` and a lazy stream of `Episode`s in
the conventions of `pipeline/dataset.py` (N observations and N actions per episode, `time` on one
clock). Everything that can be checked without reading the frames is checked when the source is
opened, so a bad input fails before any file is created.
"""

from __future__ import annotations

import importlib.metadata
import logging
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from tqdm import tqdm

from pipeline.dataset import DatasetInfo, Episode
from pipeline.envs.maze.env import SUPPORTED_ENVS, make_maze_env, maze_layout, point_env
from pipeline.envs.maze.generate import ACTION_NAMES, ACTION_UNITS, STATE_NAMES, STATE_UNITS
from pipeline.envs.physics import PHYSICS_SPEC
from pipeline.errors import UserError

log = logging.getLogger(__name__)

# The point-mass state and action of a PointMaze, as the built-in expert records them.
MAZE_STATE_NAMES, MAZE_STATE_UNITS = list(STATE_NAMES), list(STATE_UNITS)
MAZE_ACTION_NAMES, MAZE_ACTION_UNITS = list(ACTION_NAMES), list(ACTION_UNITS)


@dataclass
class ImportedDataset:
    """What an importer produces: metadata and a one-shot stream of episodes.

    Attributes:
        info: The dataset's metadata (`source` is "lerobot", "d4rl" or "minari").
        episodes: Episodes 0, 1, 2, ... in order; consumed once.
        frames: Total number of steps the stream will yield (for progress and throughput).
    """

    info: DatasetInfo
    episodes: Iterator[Episode]
    frames: int


class Clock:
    """The dataset clock: step k of the whole dataset is at `k * dt` seconds.

    Episode k + 1 starts one control period after episode k ended (see `pipeline/dataset.py`).
    Times are computed from an integer step count, so they do not drift over long datasets.
    """

    def __init__(self, dt: float) -> None:
        self.dt = float(dt)
        self.steps = 0

    def next(self, n: int) -> np.ndarray:
        """Times `[n]` of the next episode's n steps; advances the clock past them."""
        times = (self.steps + np.arange(n, dtype=np.float64)) * self.dt
        self.steps += n
        return times


def numeric(values: Any, what: str, dims: int = 2) -> np.ndarray:
    """`values` as a float64 array of `dims` dimensions (`[N]` or `[N, d]`).

    A `[N]` array is accepted where `[N, d]` is wanted (it becomes `[N, 1]`).

    Raises:
        UserError: the values are not numbers (strings, objects, images) or have another rank.
    """
    array = np.asarray(values)
    if array.dtype.kind not in "biuf":
        raise UserError(f"{what} is not numeric (dtype {array.dtype}); pick a numeric feature")
    if dims == 2 and array.ndim == 1:
        array = array[:, None]
    if array.ndim != dims:
        shape = "[N]" if dims == 1 else "[N, dim]"
        raise UserError(f"{what} has shape {array.shape}; expected {shape}")
    return array.astype(np.float64, copy=False)


def missing(kind: str, key: str, available: Iterable[str], where: str) -> UserError:
    """The error for a key the user named that the source does not have."""
    names = ", ".join(sorted(available)) or "(none)"
    return UserError(f"{where} has no {kind} {key!r}; available: {names}")


def same_lengths(lengths: dict[str, int], where: str) -> None:
    """Raise `UserError` unless all named arrays have the same length."""
    if len(set(lengths.values())) > 1:
        shown = ", ".join(f"{k}: {v}" for k, v in lengths.items())
        raise UserError(f"{where}: arrays have different lengths ({shown}); the file is malformed")


def vector_names(prefix: str, dim: int, names: Sequence[str] | None = None) -> list[str]:
    """Names of a vector's components: the given ones, or `prefix[0]`, `prefix[1]`, ..."""
    if names is not None and len(names) == dim:
        return [str(n) for n in names]
    return [f"{prefix}[{i}]" for i in range(dim)]


def unique_names(groups: list[tuple[str, list[str]]]) -> list[str]:
    """Concatenate per-feature component names, prefixing them with the feature if they clash."""
    flat = [name for _, names in groups for name in names]
    if len(set(flat)) == len(flat):
        return flat
    return [f"{feature}.{name}" for feature, names in groups for name in names]


def physics_state(time: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """The MuJoCo full-physics vector `[N, 1 + nq + nv]` = `[time, qpos, qvel]` per step.

    For models without actuator activations, mocap bodies or user data (the PointMaze point mass,
    the D4RL locomotion robots) this is exactly `mjSTATE_FULLPHYSICS`, which `set_physics_state`
    restores. The recorded time is the dataset clock.
    """
    return np.column_stack([time, qpos, qvel])


def is_point_maze(env_id: str) -> bool:
    """Whether `env_id` is a PointMaze the pipeline can simulate (`SUPPORTED_ENVS`)."""
    return env_id in SUPPORTED_ENVS


def is_simulated_maze(info: DatasetInfo) -> bool:
    """Whether a dataset lives in a PointMaze we simulate and has the point-mass state first.

    Such datasets get the maze checks (walls, bounds, jumps, physics) after import.
    """
    return is_point_maze(info.env_id) and info.state_names[:4] == MAZE_STATE_NAMES


def maze_metadata(env_id: str, maze_map: list[list[int | str]] | None = None) -> dict[str, Any]:
    """`maze_layout` and control period of a PointMaze, for `DatasetInfo`.

    Returns:
        {"maze_layout": ..., "control_period": dt in s, "physics_dim": len of the physics state}.
    """
    env = make_maze_env(env_id, maze_map)
    try:
        pe = point_env(env)
        return {
            "maze_layout": maze_layout(env),
            "control_period": float(pe.dt),
            "physics_dim": int(mujoco.mj_stateSize(pe.model, PHYSICS_SPEC)),
        }
    finally:
        env.close()


def versions(*packages: str) -> dict[str, str]:
    """Installed versions of the packages that read the source (for provenance)."""
    out = {}
    for name in ("numpy", *packages):
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    return out


def with_progress(
    episodes: Iterator[Episode], total: int, desc: str, enabled: bool
) -> Iterator[Episode]:
    """Pass episodes through, advancing a tqdm bar over `total` frames."""
    with tqdm(total=total, disable=not enabled, unit="frame", desc=desc) as bar:
        for episode in episodes:
            bar.update(len(episode))
            yield episode


def check_control_period(value: float | None, where: str) -> float:
    """A positive control period, or a `UserError` telling the user which key to set."""
    if value is None or not np.isfinite(value) or value <= 0:
        raise UserError(
            f"the control period of this dataset is unknown; set {where} (seconds per step)"
        )
    return float(value)
