"""Checks on what goes into an MCAP dataset: `DatasetInfo` and each `Episode` against it.

Each check raises `ValueError` with a message naming the episode, field and step; the writer turns
it into a `UserError` that also names the file.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.dataset import DatasetInfo, Episode


def check_info(info: DatasetInfo) -> None:
    """Check that `info` is self-consistent (names vs units, dims, control period)."""
    if info.state_dim == 0 or info.action_dim == 0:
        raise ValueError("DatasetInfo needs at least one state name and one action name")
    if len(info.state_units) != info.state_dim:
        raise ValueError(
            f"DatasetInfo has {info.state_dim} state_names but {len(info.state_units)} state_units"
        )
    if len(info.action_units) != info.action_dim:
        raise ValueError(
            f"DatasetInfo has {info.action_dim} action_names "
            f"but {len(info.action_units)} action_units"
        )
    if not (math.isfinite(info.control_period) and info.control_period > 0):
        raise ValueError(f"DatasetInfo.control_period must be > 0, got {info.control_period}")
    if info.physics_dim < 0 or info.goal_dim < 0:
        raise ValueError("DatasetInfo.physics_dim and goal_dim must be >= 0")


def _array(
    episode: Episode, field: str, dtype: type, shape: tuple[int, ...], hint: str
) -> np.ndarray:
    value = np.asarray(getattr(episode, field), dtype=dtype)
    if value.shape != shape:
        raise ValueError(
            f"episode {episode.index}: `{field}` has shape {value.shape}, expected {shape} {hint}"
        )
    if dtype is np.float64 and not np.isfinite(value).all():
        bad = np.argwhere(~np.isfinite(value))[0]
        raise ValueError(
            f"episode {episode.index}, step {bad[0]}: `{field}` is {value[tuple(bad)]} "
            "(values must be finite)"
        )
    return value


def check_episode(episode: Episode, info: DatasetInfo, index: int, start_time: float) -> Episode:
    """Check one episode against `info` and return it with canonical dtypes.

    Args:
        episode: The episode to check.
        info: Dataset description giving state_dim, action_dim, physics_dim and goal_dim.
        index: The index this episode must have (episodes are numbered 0, 1, 2, ... in order).
        start_time: Time of the last step of the previous episode (0 for the first): times must be
            >= 0 and non-decreasing over the whole dataset (they become MCAP log times).

    Returns:
        The episode with float64 arrays and bool flags (optional arrays stay None).
    """
    if episode.index != index:
        raise ValueError(
            f"episode {episode.index} is at position {index}; number episodes 0, 1, 2, ... in order"
        )
    n = len(episode)
    if n == 0:
        raise ValueError(f"episode {index} is empty")
    f64, n_ = np.float64, (n,)
    obs = _array(episode, "observations", f64, (n, info.state_dim), "= [N, state_dim]")
    act = _array(episode, "actions", f64, (n, info.action_dim), "= [N, action_dim]")
    time = _array(episode, "time", f64, n_, "= [N]")
    steps_back = np.flatnonzero(np.diff(time, prepend=start_time) < 0)
    if steps_back.size:
        t = int(steps_back[0])
        raise ValueError(
            f"episode {index}, step {t}: time {time[t]} goes backwards; times must be >= 0 and "
            "non-decreasing on one dataset clock"
        )
    out = Episode(index=index, observations=obs, actions=act, time=time)
    for field, dim, name in (
        ("physics", info.physics_dim, "physics_dim"),
        ("goals", info.goal_dim, "goal_dim"),
    ):
        if (getattr(episode, field) is None) != (dim == 0):
            raise ValueError(
                f"episode {index}: `{field}` is {'missing' if dim else 'set'} but "
                f"DatasetInfo.{name} is {dim}"
            )
        if dim:
            setattr(out, field, _array(episode, field, f64, (n, dim), f"= [N, {name}]"))
    for field, dtype in (("goal_reached", bool), ("rewards", f64), ("terminals", bool)):
        if getattr(episode, field) is not None:
            setattr(out, field, _array(episode, field, dtype, n_, "= [N]"))
    return out
