"""OGBench's `.npz` dataset files: import them as episodes (`read_ogbench`), write ours in their
layout (`write_ogbench_npz`).

An OGBench dataset file holds `observations`, `actions`, `terminals` and optionally `qpos` /
`qvel` (the state before each step); its `-val.npz` companion, when present, is appended as later
episodes (`generator["files"]` says which). An episode ends after a step whose `terminals` is set.
"""

from __future__ import annotations

import logging
import re
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipeline.dataset import DatasetInfo, Episode
from pipeline.envs.ogbench import OGBENCH_MAZES, OGBenchMazeSpec, check_ogbench_id
from pipeline.errors import UserError
from pipeline.io import atomic_path
from pipeline.sources.common import (
    Clock,
    ImportedDataset,
    missing,
    numeric,
    physics_state,
    same_lengths,
    with_progress,
)
from pipeline.sources.ogbench.info import dataset_info, ogbench_spec

log = logging.getLogger(__name__)

REQUIRED = ("observations", "actions", "terminals")
OPTIONAL = ("qpos", "qvel")
# `pointmaze-medium-navigate-v0.npz` -> maze `pointmaze-medium-v0`.
_FILE_NAME = re.compile(r"^((?:point|ant)maze-[a-z]+)-(?:[a-z]+)-v0(?:-val)?\.npz$")


def maze_of_file(path: Path) -> str | None:
    """The env id an OGBench file name names (`pointmaze-medium-navigate-v0.npz` ->
    `pointmaze-medium-v0`), or None for another name."""
    match = _FILE_NAME.match(path.name)
    return f"{match.group(1)}-v0" if match else None


_NOT_NPZ = "an OGBench dataset is a .npz: a zip of numpy arrays"


def load_npz(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an OGBench `.npz` (never unpickled); a one-line `UserError` for a missing,
    damaged or foreign file."""
    if not path.is_file():
        raise UserError(f"OGBench file {path} not found (set ingest.ogbench.path)")
    with path.open("rb") as f:
        head = f.read(8)
    if head.startswith(b"\x89HDF"):
        raise UserError(
            f"{path} is an HDF5 file, not a .npz ({_NOT_NPZ}); a D4RL .hdf5 imports with "
            "ingest.source=d4rl"
        )
    if head.startswith(b"\x93NUMPY"):
        raise UserError(f"{path} is a single numpy array (.npy), not a .npz ({_NOT_NPZ})")
    if not head.startswith(b"PK"):
        raise UserError(f"{path} is not a .npz file ({_NOT_NPZ}); it is damaged or another kind")
    try:
        with np.load(path, allow_pickle=False) as f:
            return {k: f[k] for k in f.files}
    except ValueError as exc:  # numpy's text suggests allow_pickle: never pass it on
        raise UserError(
            f"{path} holds Python objects (pickled arrays), which OGBench data never does: it "
            "is not an OGBench dataset"
        ) from exc
    except (OSError, zipfile.BadZipFile, EOFError) as exc:
        raise UserError(f"{path} is a damaged or truncated .npz ({_NOT_NPZ})") from exc


def _misfit(arrays: dict[str, np.ndarray], spec: OGBenchMazeSpec) -> str | None:
    """Why the data cannot be from the maze of `spec` (observation or action size, positions in
    its walls), or None when they fit."""
    obs, actions = arrays["observations"], arrays["actions"]
    for key, values, size in (
        ("observation", obs, spec.state_dim),
        ("action", actions, spec.action_dim),
    ):
        got = int(np.prod(values.shape[1:]))
        if got != size:
            return f"{got} values per {key}, {spec.env_id} has {size}"
    try:
        _check_maze(np.asarray(obs, np.float64)[:, :2], "", spec)
    except UserError:
        return f"positions lie in walls of or outside {spec.env_id}"
    return None


def _check_unnamed(arrays: dict[str, np.ndarray], where: str, spec: OGBenchMazeSpec) -> None:
    """A file whose name names no maze is imported as `ingest.ogbench.env_id`: only if its data
    fit that maze; else the message names the mazes they fit."""
    usable = all(
        k in arrays and arrays[k].dtype.kind in "biuf" and arrays[k].ndim >= 1 and len(arrays[k])
        for k in ("observations", "actions")
    )
    if not usable:
        return  # `_check_arrays` says what is missing
    why = _misfit(arrays, spec)
    if why is None:
        log.info(
            "%s names no maze: imported as ingest.ogbench.env_id %s (its sizes and positions fit)",
            where,
            spec.env_id,
        )
        return
    fit = [
        m for m in OGBENCH_MAZES if m != spec.env_id and _misfit(arrays, ogbench_spec(m)) is None
    ]
    start = (
        f"{where}: its name names no maze, and its data are not from ingest.ogbench.env_id "
        f"{spec.env_id} ({why})"
    )
    if not fit:
        raise UserError(f"{start}; they fit none of {', '.join(OGBENCH_MAZES)}")
    choice = fit[0] if len(fit) == 1 else f"one of {', '.join(fit)}"
    raise UserError(f"{start}; they fit {choice}: set ingest.ogbench.env_id={fit[0]}")


def _check_arrays(arrays: dict[str, np.ndarray], where: str, spec: OGBenchMazeSpec) -> None:
    """Keys, numeric types, lengths and sizes against the env; raises one-line `UserError`s."""
    for key in REQUIRED:
        if key not in arrays:
            raise missing("array", key, arrays, f"{where} (not an OGBench dataset?)")
    present = [k for k in (*REQUIRED, *OPTIONAL) if k in arrays]
    for key in present:
        if arrays[key].dtype.kind not in "biuf":
            raise UserError(f"{where}: `{key}` is not numeric (dtype {arrays[key].dtype})")
    same_lengths({k: int(arrays[k].shape[0]) for k in present}, where)
    if arrays["observations"].shape[0] == 0:
        raise UserError(f"{where} holds no steps (empty dataset)")
    expected = {
        "observations": spec.state_dim,
        "actions": spec.action_dim,
        "qpos": spec.model.nq,
        "qvel": spec.model.nv,
    }
    for key, size in expected.items():
        if key in arrays and int(np.prod(arrays[key].shape[1:])) != size:
            raise UserError(
                f"{where}: `{key}` has {int(np.prod(arrays[key].shape[1:]))} values per step, "
                f"but {spec.env_id} has {size}; set ingest.ogbench.env_id to the file's maze"
            )


def _check_maze(positions: np.ndarray, where: str, spec: OGBenchMazeSpec) -> None:
    """Every position must lie in a free cell of the maze (the point cannot enter a wall)."""
    layout = spec.layout
    xmin, xmax, ymin, ymax = layout["bounds"]
    x, y = positions[:, 0], positions[:, 1]
    inside = (xmin < x) & (x < xmax) & (ymin < y) & (y < ymax)
    scale = float(layout["maze_size_scaling"])
    walls = np.asarray(layout["maze_map"]) == 1
    x, y = np.nan_to_num(x), np.nan_to_num(y)  # non-finite ones are already not inside
    rows = np.clip(np.floor((layout["y_map_center"] - y) / scale), 0, walls.shape[0] - 1)
    cols = np.clip(np.floor((x + layout["x_map_center"]) / scale), 0, walls.shape[1] - 1)
    wrong = ~inside | walls[rows.astype(int), cols.astype(int)]
    bad = int(wrong.sum())
    first = positions[np.argmax(wrong)] if bad else None
    if bad:
        raise UserError(
            f"{where}: {bad} of {len(positions)} positions (first {first[0]:.2f}, {first[1]:.2f}) "
            f"lie in walls or outside {spec.env_id}: the data is from another maze; set "
            "ingest.ogbench.env_id to the file's maze"
        )


def episode_ends(terminals: np.ndarray, where: str) -> np.ndarray:
    """`[E]` end indices (exclusive) of the episodes `terminals [N]` marks; trailing steps
    without a terminal are kept as a last episode (with a warning)."""
    ends = np.flatnonzero(np.asarray(terminals).reshape(-1) != 0) + 1
    n = len(terminals)
    if ends.size == 0 or ends[-1] != n:
        log.warning(
            "%s: the last %d steps have no terminal; kept as an episode",
            where,
            n - (int(ends[-1]) if ends.size else 0),
        )
        ends = np.append(ends, n)
    return ends


def with_val_file(path: Path, include_val: bool) -> list[Path]:
    """`[path]`, and its OGBench `-val.npz` companion beside it when `include_val` and it exists."""
    val = path.with_name(path.stem + "-val.npz")
    if include_val and val.is_file() and not path.stem.endswith("-val"):
        return [path, val]
    return [path]


def describe_files(
    files: list[Path], loaded: list[tuple[dict[str, np.ndarray], np.ndarray]]
) -> list[dict]:
    """What the dataset's provenance says of each imported file: path, steps, episodes, arrays."""
    return [
        {
            "path": str(f.resolve()),
            "steps": len(arrays["observations"]),
            "episodes": len(ends),
            "arrays": sorted(arrays),
        }
        for f, (arrays, ends) in zip(files, loaded, strict=True)
    ]


def read_ogbench(
    path: str | Path,
    name: str,
    env_id: str = "",
    include_val: bool = True,
    progress: bool = False,
) -> ImportedDataset:
    """Open an OGBench `.npz` (and its `-val.npz`, if `include_val` and present) as episodes.

    Args:
        path: The dataset file, e.g. `~/.ogbench/data/pointmaze-medium-navigate-v0.npz`.
        name: Dataset name.
        env_id: The OGBench maze; "" takes it from the file name.
        include_val: Append the episodes of the `-val.npz` companion next to it.

    Raises:
        UserError: missing file or arrays (lists those it has), arrays of different lengths, an
            unsupported env id, sizes or positions that do not fit the maze, no steps.
    """
    path = Path(path).expanduser()
    named = maze_of_file(path)
    if not env_id:
        if named is None:
            raise UserError(
                f"cannot tell the maze of {path.name}; set ingest.ogbench.env_id "
                f"(one of {', '.join(OGBENCH_MAZES)})"
            )
        env_id = named
    check_ogbench_id(env_id)
    if named is not None and named != env_id:
        raise UserError(
            f"{path.name} is a {named} dataset, but ingest.ogbench.env_id is {env_id}; "
            "make them agree"
        )
    spec = ogbench_spec(env_id)
    files = with_val_file(path, include_val)
    loaded = []
    for f in files:
        arrays = load_npz(f)
        if named is None:
            _check_unnamed(arrays, str(f), spec)
        _check_arrays(arrays, str(f), spec)
        _check_maze(np.asarray(arrays["observations"], np.float64)[:, :2], str(f), spec)
        loaded.append((arrays, episode_ends(arrays["terminals"], str(f))))
    described = describe_files(files, loaded)
    with_qpos = all("qpos" in a and "qvel" in a for a, _ in loaded)
    generator = {
        "files": described,
        "physics_from": "qpos, qvel" if with_qpos else _PHYSICS_FROM_OBSERVATIONS[spec.loco],
    }
    info = dataset_info(spec, name, None, generator, goal_dim=0)
    frames = sum(d["steps"] for d in described)
    stream = _imported_episodes(loaded, info, spec.model.nq, with_qpos)
    return ImportedDataset(info, with_progress(stream, frames, name, progress), frames)


_PHYSICS_FROM_OBSERVATIONS = {
    "point": "observations (the point's qpos; qvel 0, which its next step sets anyway)",
    "ant": "observations (the ant's observation is qpos, qvel)",
}


def _imported_episodes(
    loaded: list[tuple[dict[str, np.ndarray], np.ndarray]], info: DatasetInfo, nq: int, qpos: bool
) -> Iterator[Episode]:
    """The files' episodes in order, on one clock, with physics `[time, qpos, qvel]`."""
    clock = Clock(info.control_period)
    index = 0
    for arrays, ends in loaded:
        start = 0
        for end in ends.tolist():
            n = end - start
            time = clock.next(n)
            rows = {
                k: numeric(v[start:end].reshape(n, -1), k)
                for k, v in arrays.items()
                if k in ("observations", "actions", *OPTIONAL)
            }
            obs = rows["observations"]
            if qpos:
                physics = physics_state(time, rows["qpos"], rows["qvel"])
            elif nq == 2:  # the point: observation = qpos
                physics = physics_state(time, obs, np.zeros((n, 2)))
            else:
                physics = physics_state(time, obs[:, :nq], obs[:, nq:])
            terminals = np.asarray(arrays["terminals"][start:end]).reshape(n) != 0
            yield Episode(index, obs, rows["actions"], time, physics=physics, terminals=terminals)
            index += 1
            start = end


def write_ogbench_npz(path: str | Path, episodes: list[Episode], nq: int | None = None) -> int:
    """Write episodes in OGBench's file layout (float32 arrays, `terminals` on each episode's
    last step, `qpos` / `qvel` from the physics states `[time, qpos, qvel]`), atomically; returns
    the number of steps. `nq`: qpos size (the ant's 15); None: half the state (the point's 2)."""
    columns: dict[str, list[np.ndarray]] = {k: [] for k in (*REQUIRED, *OPTIONAL)}
    for ep in episodes:
        n = len(ep)
        terminals = np.zeros(n, dtype=bool)
        terminals[-1] = True
        columns["observations"].append(ep.observations.astype(np.float32))
        columns["actions"].append(ep.actions.astype(np.float32))
        columns["terminals"].append(terminals)
        if ep.physics is not None:
            split = 1 + ((ep.physics.shape[1] - 1) // 2 if nq is None else nq)
            columns["qpos"].append(ep.physics[:, 1:split].astype(np.float32))
            columns["qvel"].append(ep.physics[:, split:].astype(np.float32))
    arrays = {k: np.concatenate(v) for k, v in columns.items() if v}
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    return len(arrays["actions"])
