"""Import a D4RL hdf5 file (the classic flat layout), read with h5py.

Layout: `observations` `[N, obs_dim]`, `actions` `[N, act_dim]`, `rewards` `[N]`, `terminals`
`[N]`, `timeouts` `[N]` and optionally `infos/goal`, `infos/qpos`, `infos/qvel`, all steps of all
episodes concatenated; an episode ends after a step whose `terminals` or `timeouts` is set (steps
after the last such flag form a last, cut-off episode). Step t holds the observation before
`actions[t]`, as in our format.

With `env_id` set to a PointMaze id the file is read as D4RL maze2d for that maze: states, goals,
velocities and actions are converted to gymnasium-robotics coordinates (`maze2d.Maze2dMap`, the
mapping is recorded in `generator["coordinate_map"]`), and the full physics state
`[time, x, y, vx, vy]` is built from `infos/qpos` / `infos/qvel` (or from the observations, which
in maze2d are exactly qpos and qvel), so the data can be validated and deployed in our simulator.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from pipeline.dataset import DatasetInfo, Episode
from pipeline.errors import UserError
from pipeline.sources.common import (
    MAZE_ACTION_NAMES,
    MAZE_ACTION_UNITS,
    MAZE_STATE_NAMES,
    MAZE_STATE_UNITS,
    Clock,
    ImportedDataset,
    check_control_period,
    is_point_maze,
    maze_metadata,
    missing,
    numeric,
    physics_state,
    same_lengths,
    vector_names,
    versions,
    with_progress,
)
from pipeline.sources.maze2d import Maze2dMap

log = logging.getLogger(__name__)

OPTIONAL = ("rewards", "terminals", "timeouts", "infos/goal", "infos/qpos", "infos/qvel")
_MAZE2D_FILE = re.compile(r"maze2d", re.IGNORECASE)


@dataclass
class _Contents:
    """What `_inspect` found in the file (shapes and episode boundaries, no frames)."""

    keys: list[str]
    n: int
    ends: np.ndarray
    dims: dict[str, int] = field(default_factory=dict)
    n_terminals: int = 0
    n_timeouts: int = 0


def _datasets(f: h5py.File) -> dict[str, h5py.Dataset]:
    """All datasets of the file by path (`observations`, `infos/qpos`, ...)."""
    found: dict[str, h5py.Dataset] = {}

    def visit(name: str, obj: h5py.HLObject) -> None:  # returning non-None would stop the walk
        if isinstance(obj, h5py.Dataset):
            found[name] = obj

    f.visititems(visit)
    return found


def _inspect(f: h5py.File, where: str) -> _Contents:
    """Check keys, dtypes and lengths; find the episode boundaries."""
    data = _datasets(f)
    for key in ("observations", "actions"):
        if key not in data:
            raise missing("array", key, data, f"{where} (not a D4RL dataset?)")
    present = [k for k in ("observations", "actions", *OPTIONAL) if k in data]
    for key in present:
        if data[key].dtype.kind not in "biuf":
            raise UserError(f"{where}: `{key}` is not numeric (dtype {data[key].dtype})")
    same_lengths({k: int(data[k].shape[0]) for k in present}, where)
    n = int(data["observations"].shape[0])
    if n == 0:
        raise UserError(f"{where} holds no steps (empty dataset)")
    flags = [k for k in ("terminals", "timeouts") if k in data]
    if not flags:
        raise UserError(f"{where} has neither `terminals` nor `timeouts`; cannot split episodes")
    counts = {k: np.asarray(data[k][:], dtype=bool) for k in flags}
    done = np.logical_or.reduce(list(counts.values()))
    ends = np.flatnonzero(done) + 1
    if ends.size == 0 or ends[-1] != n:
        log.warning(
            "%s: the last %d steps end without a terminal or timeout; kept as an episode",
            where,
            n - (int(ends[-1]) if ends.size else 0),
        )
        ends = np.append(ends, n)
    dims = {k: int(np.prod(data[k].shape[1:], dtype=np.int64)) for k in present}
    return _Contents(
        keys=sorted(data),
        n=n,
        ends=ends,
        dims=dims,
        n_terminals=int(counts["terminals"].sum()) if "terminals" in counts else 0,
        n_timeouts=int(counts["timeouts"].sum()) if "timeouts" in counts else 0,
    )


def _open(path: Path) -> h5py.File:
    if not path.is_file():
        raise UserError(f"D4RL file {path} not found (set ingest.d4rl.path)")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise UserError(f"{path} is not an HDF5 file ({exc})") from exc


def read_d4rl(
    path: str | Path,
    name: str,
    env_id: str = "",
    control_period: float | None = None,
    progress: bool = False,
) -> ImportedDataset:
    """Open a D4RL hdf5 file as a stream of episodes (frames are read lazily, per episode).

    Args:
        path: The `.hdf5` file.
        name: Dataset name for `DatasetInfo`.
        env_id: A PointMaze id for maze2d files of that maze (coordinates converted), or "".
        control_period: Seconds per step; default the maze's dt for maze2d (required otherwise).
        progress: Show a progress bar while the episodes are read.

    Raises:
        UserError: missing file or arrays (lists the available ones), non-numeric arrays,
            arrays of different lengths, no steps, a non-maze2d file read as maze2d.
    """
    path = Path(path)
    with _open(path) as f:
        contents = _inspect(f, str(path))
    if env_id and not is_point_maze(env_id):
        raise UserError(f"ingest.d4rl.env_id {env_id!r} is not a PointMaze we simulate")
    if not env_id and _MAZE2D_FILE.search(path.name):
        log.warning(
            "%s looks like D4RL maze2d: set ingest.d4rl.env_id to its PointMaze id to "
            "convert coordinates and make it simulatable",
            path.name,
        )
    info, mapping = _info(path, name, env_id, control_period, contents)
    episodes = _episodes(path, contents, info, mapping)
    frames = contents.n
    return ImportedDataset(info, with_progress(episodes, frames, name, progress), frames)


def _info(
    path: Path, name: str, env_id: str, control_period: float | None, contents: _Contents
) -> tuple[DatasetInfo, Maze2dMap | None]:
    """`DatasetInfo` of the file, and the maze2d coordinate map (None for other files)."""
    dims = contents.dims
    generator: dict[str, Any] = {
        "path": str(path.resolve()),
        "arrays": contents.keys,
        "episode_ends": {"terminals": contents.n_terminals, "timeouts": contents.n_timeouts},
    }
    mapping = None
    env_kwargs: dict[str, Any] = {}
    if env_id:
        if dims["observations"] != 4 or dims["actions"] != 2:
            raise UserError(
                f"{path} is not a maze2d file: observations have {dims['observations']} values "
                f"and actions {dims['actions']} (expected 4 and 2); clear ingest.d4rl.env_id"
            )
        maze = maze_metadata(env_id)
        dt = maze["control_period"]
        if control_period is not None and abs(control_period - dt) > 1e-12:
            raise UserError(f"maze2d steps last {dt} s (the simulator's dt), not {control_period}")
        mapping = Maze2dMap.for_layout(maze["maze_layout"])
        env_kwargs = {"maze_map": maze["maze_layout"]["maze_map"]}
        generator.update(maze_layout=maze["maze_layout"], coordinate_map=mapping.to_dict())
        generator["physics_from"] = (
            "infos/qpos, infos/qvel"
            if _has_qpos(dims, 2)
            else "observations (maze2d observations are qpos, qvel)"
        )
        state = (MAZE_STATE_NAMES, MAZE_STATE_UNITS)
        action = (MAZE_ACTION_NAMES, MAZE_ACTION_UNITS)
        physics_dim, control_period = maze["physics_dim"], dt
    else:
        control_period = check_control_period(control_period, "ingest.d4rl.control_period")
        state = (vector_names("obs", dims["observations"]), [""] * dims["observations"])
        action = (vector_names("act", dims["actions"]), [""] * dims["actions"])
        nq, nv = dims.get("infos/qpos", 0), dims.get("infos/qvel", 0)
        physics_dim = 1 + nq + nv if nq and nv else 0
    info = DatasetInfo(
        name=name,
        source="d4rl",
        env_id=env_id,
        state_names=state[0],
        action_names=action[0],
        state_units=state[1],
        action_units=action[1],
        control_period=float(control_period),
        physics_dim=physics_dim,
        goal_dim=dims.get("infos/goal", 0),
        env_kwargs=env_kwargs,
        generator=generator,
        versions=versions("h5py"),
    )
    return info, mapping


def _has_qpos(dims: dict[str, int], n: int) -> bool:
    return dims.get("infos/qpos") == n and dims.get("infos/qvel") == n


def _episodes(
    path: Path, contents: _Contents, info: DatasetInfo, mapping: Maze2dMap | None
) -> Iterator[Episode]:
    """Read the file one episode at a time (the file stays open while the stream is consumed)."""
    clock = Clock(info.control_period)
    with h5py.File(path, "r") as f:
        data = _datasets(f)
        start = 0
        for index, end in enumerate(contents.ends.tolist()):
            rows = {
                k: data[k][start:end] for k in ("observations", "actions", *OPTIONAL) if k in data
            }
            yield _episode(index, rows, clock.next(end - start), info, mapping)
            start = end


def _episode(
    index: int,
    rows: dict[str, np.ndarray],
    time: np.ndarray,
    info: DatasetInfo,
    mapping: Maze2dMap | None,
) -> Episode:
    """One episode's arrays, converted to our conventions (and coordinates for maze2d)."""
    n = len(time)
    arrays = {k: numeric(v.reshape(n, -1), k) for k, v in rows.items()}
    obs, act = arrays["observations"], arrays["actions"]
    goal, qpos, qvel = (arrays.get(k) for k in ("infos/goal", "infos/qpos", "infos/qvel"))
    physics = None
    if mapping is not None:
        obs, act = mapping.states(obs), mapping.vectors(act)
        goal = None if goal is None else mapping.positions(goal)
        if info.generator["physics_from"].startswith("infos"):
            physics = physics_state(time, mapping.positions(qpos), mapping.vectors(qvel))
        else:
            physics = physics_state(time, obs[:, :2], obs[:, 2:])
    elif info.physics_dim:
        physics = physics_state(time, qpos, qvel)
    rewards, terminals = rows.get("rewards"), rows.get("terminals")
    return Episode(
        index=index,
        observations=obs,
        actions=act,
        time=time,
        physics=physics,
        goals=goal,
        rewards=None if rewards is None else rewards.reshape(n).astype(np.float64),
        terminals=None if terminals is None else terminals.reshape(n).astype(bool),
    )


def write_d4rl(path: str | Path, episodes: Iterable[Episode], info: DatasetInfo) -> int:
    """Write episodes in D4RL's flat hdf5 layout (the inverse of `read_d4rl`); returns N.

    For a PointMaze dataset the states, goals and actions are converted back to D4RL maze2d
    coordinates and `infos/qpos` / `infos/qvel` are written; each episode ends with a timeout
    (or a terminal where the episode's last `terminals` flag is set). Used by `oposm bench import`
    to build large D4RL files from generated data.
    """
    mapping = None
    if is_point_maze(info.env_id):
        mapping = Maze2dMap.for_layout(maze_metadata(info.env_id)["maze_layout"])
    columns: dict[str, list[np.ndarray]] = {k: [] for k in ("observations", "actions", *OPTIONAL)}
    for ep in episodes:
        n = len(ep)
        obs, act = ep.observations, ep.actions
        goal = ep.goals
        if mapping is not None:
            obs, act = mapping.inverse_states(obs), mapping.inverse_vectors(act)
            goal = None if goal is None else mapping.inverse_positions(goal)
            columns["infos/qpos"].append(obs[:, :2].astype(np.float32))
            columns["infos/qvel"].append(obs[:, 2:4].astype(np.float32))
        terminals = np.zeros(n, bool) if ep.terminals is None else ep.terminals
        timeouts = np.zeros(n, bool)
        timeouts[-1] = not terminals[-1]
        columns["observations"].append(obs.astype(np.float32))
        columns["actions"].append(act.astype(np.float32))
        columns["rewards"].append(np.zeros(n) if ep.rewards is None else ep.rewards)
        columns["terminals"].append(terminals)
        columns["timeouts"].append(timeouts)
        if goal is not None:
            columns["infos/goal"].append(goal.astype(np.float32))
    with h5py.File(path, "w") as f:
        for key, parts in columns.items():
            if parts:
                f.create_dataset(key, data=np.concatenate(parts))
    return sum(len(p) for p in columns["actions"])
