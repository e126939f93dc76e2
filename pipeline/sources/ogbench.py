"""OGBench point-maze data: generated with OGBench's own recipe, or imported from its `.npz` files.

**Generate** (`generate_ogbench`), following `data_gen_scripts/generate_locomaze.py` of OGBench's
repository (read for its facts; the loop is written here because the script needs OGBench's
training code, absl and a saved agent):

- each episode resets the real env (`terminate_at_goal=False`) with `task_info = (init_ij,
  goal_ij)`: the start cell uniform over all free cells; the goal cell uniform over the "vertex"
  cells (free cells that are not straight hallways) for `navigate` and `explore`, and uniform over
  the cells exactly 4 BFS steps from the start for `stitch`; OGBench's reset adds its +-1 noise;
- the point's action is the unit direction to the BFS oracle subgoal (`explore`: a random unit
  direction, redrawn every 10 steps) plus N(0, noise^2), clipped to [-1, 1]; noise 0.5
  (navigate, stitch) or 1.0 (explore);
- `navigate` draws a new vertex goal (`set_goal(goal_ij)`, with noise) whenever the current one is
  reached (within 1.0, after the step);
- OGBench's sizes: navigate 1000 episodes x 1001 steps (giant: 500 x 2001), stitch 5000 x 201,
  explore 10000 x 501, each plus a 10 % validation file. Here the sizes are params; the
  validation share comes from the segment stage's split instead of a second file.

OGBench draws its reset and goal noise from numpy's global generator: each episode runs under
`global_seed` of its own seed, so a dataset is a function of `ingest.seed`. Recorded per step:
the observation `[x, y]`, the action sent, the goal pursued, whether the step reached it, and the
exact MuJoCo state before the step (`[time, qpos, qvel]`, time on the dataset clock).

**Import** (`read_ogbench`): an OGBench dataset file (`observations`, `actions`, `terminals`,
optional `qpos` / `qvel`) and, when present, its `-val.npz` companion (appended as later
episodes; `generator["files"]` says which). An episode ends after a step whose `terminals` is set.
`write_ogbench_npz` writes our episodes in that layout (float32, as OGBench's files).
"""

from __future__ import annotations

import importlib.metadata
import logging
import re
import zipfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import mujoco
import numpy as np

from pipeline.dataset import DatasetInfo, Episode
from pipeline.envs.ant import global_seed
from pipeline.envs.checks import DatasetReport
from pipeline.envs.checks import _Walls as MazeWalls  # the maze checks' wall geometry
from pipeline.envs.maze import PHYSICS_SPEC
from pipeline.envs.ogbench import (
    OGBENCH_MAZES,
    OGBenchMazeSpec,
    check_ogbench_id,
    make_ogbench_env,
)
from pipeline.envs.ogbench_oracle import BFSOracle
from pipeline.envs.spec import make_env_spec
from pipeline.errors import UserError
from pipeline.sources.common import (
    Clock,
    ImportedDataset,
    missing,
    numeric,
    physics_state,
    same_lengths,
    with_progress,
)

log = logging.getLogger(__name__)

DATASET_TYPES = ("navigate", "stitch", "explore")
# OGBench's point action noise per dataset type (`commands.sh`).
POINT_NOISE = {"navigate": 0.5, "stitch": 0.5, "explore": 1.0}
# `stitch` goals lie this many BFS steps from the start cell.
STITCH_CELLS = 4
# `explore` redraws its direction every this many steps.
EXPLORE_EVERY = 10
REQUIRED = ("observations", "actions", "terminals")
OPTIONAL = ("qpos", "qvel")
# `pointmaze-medium-navigate-v0.npz` -> maze `pointmaze-medium-v0`.
_FILE_NAME = re.compile(r"^((?:point|ant)maze-[a-z]+)-(?:[a-z]+)-v0(?:-val)?\.npz$")


def _point_only(env_id: str) -> OGBenchMazeSpec:
    spec = _spec(env_id)
    if spec.loco != "point":
        raise UserError(
            f"generating {env_id} data needs OGBench's trained {spec.loco} policy, which this "
            "project does not have yet (issue 19); use a point maze or import an .npz file"
        )
    return spec


def _spec(env_id: str) -> OGBenchMazeSpec:
    spec = make_env_spec(env_id)
    assert isinstance(spec, OGBenchMazeSpec)
    return spec


def _names(spec: OGBenchMazeSpec) -> tuple[list[str], list[str], list[str], list[str]]:
    """State names and units, action names and units of the point or the ant."""
    if spec.loco == "point":
        return ["x", "y"], ["m", "m"], ["dx", "dy"], ["0.2 m", "0.2 m"]
    nq, nv = spec.model.nq, spec.model.nv
    states = ["x", "y", *(f"qpos[{i}]" for i in range(2, nq)), *(f"qvel[{i}]" for i in range(nv))]
    units = ["m", "m", *([""] * (nq - 2 + nv))]
    actions = [f"torque[{i}]" for i in range(spec.action_dim)]
    return states, units, actions, ["1"] * spec.action_dim


def _versions() -> dict[str, str]:
    names = ("ogbench", "gymnasium", "mujoco", "numpy")
    return {n: importlib.metadata.version(n) for n in names}


def _info(
    spec: OGBenchMazeSpec,
    name: str,
    seed: int | None,
    generator: dict[str, Any],
    goal_dim: int,
) -> DatasetInfo:
    states, state_units, actions, action_units = _names(spec)
    return DatasetInfo(
        name=name,
        source="ogbench",
        env_id=spec.env_id,
        state_names=states,
        action_names=actions,
        state_units=state_units,
        action_units=action_units,
        control_period=spec.dt,
        physics_dim=spec.physics_dim,
        goal_dim=goal_dim,
        seed=seed,
        env_kwargs={},
        generator={**generator, "maze_layout": spec.layout},
        versions=_versions(),
    )


# --- generate ---------------------------------------------------------------------------------


def maze_cells(maze_map: np.ndarray) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """OGBench's start and goal cell pools: all free cells, and the "vertex" cells, the free
    cells that are not a straight hallway (free above and below with walls left and right, or
    free left and right with walls above and below)."""
    free, vertex = [], []
    m = maze_map
    for (i, j), value in np.ndenumerate(m):
        if value != 0:
            continue
        free.append((i, j))
        vertical = m[i - 1, j] == 0 and m[i + 1, j] == 0 and m[i, j - 1] == 1 and m[i, j + 1] == 1
        across = m[i, j - 1] == 0 and m[i, j + 1] == 0 and m[i - 1, j] == 1 and m[i + 1, j] == 1
        if not (vertical or across):
            vertex.append((i, j))
    return free, vertex


def cells_at_distance(maze_map: np.ndarray, start: tuple[int, int], steps: int) -> list:
    """Free cells exactly `steps` BFS moves (4-neighbour) from `start`, in BFS order."""
    distance = {start: 0}
    queue, found = [start], []
    while queue:
        i, j = queue.pop(0)
        for di, dj in ((-1, 0), (0, -1), (1, 0), (0, 1)):
            cell = (i + di, j + dj)
            inside = 0 <= cell[0] < maze_map.shape[0] and 0 <= cell[1] < maze_map.shape[1]
            if inside and maze_map[cell] == 0 and cell not in distance:
                distance[cell] = distance[(i, j)] + 1
                queue.append(cell)
                if distance[cell] == steps:
                    found.append(cell)
    return found


@dataclass(frozen=True)
class Recipe:
    """One OGBench dataset recipe: type, sizes, noise."""

    env_id: str
    dataset_type: str
    episodes: int
    episode_steps: int
    noise: float
    seed: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "recipe": "OGBench data_gen_scripts/generate_locomaze.py",
            "dataset_type": self.dataset_type,
            "n_episodes": self.episodes,
            "episode_steps": self.episode_steps,
            "noise": self.noise,
            "continuous": False,
        }


def make_recipe(
    env_id: str,
    dataset_type: str,
    episodes: int,
    episode_steps: int,
    seed: int,
    noise: float | None = None,
) -> Recipe:
    """Checked recipe; `noise` None: OGBench's for the dataset type."""
    check_ogbench_id(env_id)
    if dataset_type not in DATASET_TYPES:
        raise UserError(
            f"unknown OGBench dataset type {dataset_type!r}; use one of: {', '.join(DATASET_TYPES)}"
        )
    if episodes < 1 or episode_steps < 2:
        raise UserError(
            f"need episodes >= 1 and episode_steps >= 2, got {episodes}, {episode_steps}"
        )
    noise = POINT_NOISE[dataset_type] if noise is None else float(noise)
    return Recipe(env_id, dataset_type, int(episodes), int(episode_steps), noise, int(seed))


def generate_ogbench(recipe: Recipe, name: str, progress: bool = False) -> ImportedDataset:
    """The dataset `recipe` describes, as a lazy stream (see the module docstring)."""
    spec = _point_only(recipe.env_id)
    info = _info(spec, name, recipe.seed, recipe.to_dict(), goal_dim=2)
    frames = recipe.episodes * recipe.episode_steps
    stream = _generate(recipe, spec)
    return ImportedDataset(info, with_progress(stream, frames, name, progress), frames)


def _generate(recipe: Recipe, spec: OGBenchMazeSpec) -> Iterator[Episode]:
    env = make_ogbench_env(
        recipe.env_id, terminate_at_goal=False, max_episode_steps=recipe.episode_steps
    )
    try:
        maze = env.unwrapped
        free, vertex = maze_cells(np.asarray(maze.maze_map))
        oracle = BFSOracle(recipe.env_id)
        clock = Clock(spec.dt)
        seeds = np.random.SeedSequence(recipe.seed).spawn(recipe.episodes)
        for k, seq in enumerate(seeds):
            rng = np.random.default_rng(seq)
            with global_seed(int(seq.generate_state(1)[0])):
                arrays = _episode(env, recipe, rng, free, vertex, oracle)
            time = clock.next(recipe.episode_steps)
            arrays["physics"][:, 0] = time
            yield Episode(index=k, time=time, **arrays)
    finally:
        env.close()


def _episode(
    env: gymnasium.Env,
    recipe: Recipe,
    rng: np.random.Generator,
    free: list,
    vertex: list,
    oracle: BFSOracle,
) -> dict[str, np.ndarray]:
    """One episode of `generate_locomaze.py`'s loop for the point."""
    maze = env.unwrapped
    maze_map = np.asarray(maze.maze_map)
    init_ij = free[rng.integers(len(free))]
    if recipe.dataset_type == "stitch":
        near = cells_at_distance(maze_map, init_ij, STITCH_CELLS)
        goal_ij = near[rng.integers(len(near))] if near else init_ij
    else:
        goal_ij = vertex[rng.integers(len(vertex))]
    ob, _ = env.reset(
        seed=int(rng.integers(2**31)),
        options={"task_info": {"init_ij": init_ij, "goal_ij": goal_ij}},
    )
    n = recipe.episode_steps
    physics = np.empty((n, mujoco.mj_stateSize(maze.model, PHYSICS_SPEC)))
    obs, actions, goals = np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 2))
    reached = np.zeros(n, dtype=bool)
    direction = np.zeros(2)
    for t in range(n):
        mujoco.mj_getState(maze.model, maze.data, physics[t], PHYSICS_SPEC)
        obs[t], goals[t] = ob, maze.cur_goal_xy
        if recipe.dataset_type == "explore":
            if t % EXPLORE_EVERY == 0:
                direction = rng.standard_normal(2)
                direction /= np.linalg.norm(direction) + 1e-6
        else:
            direction = oracle.direction(maze.get_xy(), maze.cur_goal_xy)
        action = np.clip(direction + rng.normal(0.0, recipe.noise, 2), -1.0, 1.0)
        actions[t] = action
        ob, _, _, _, step_info = env.step(action)
        reached[t] = bool(step_info["success"])
        if reached[t] and recipe.dataset_type == "navigate":
            maze.set_goal(vertex[rng.integers(len(vertex))])
    return {
        "observations": obs,
        "actions": actions,
        "physics": physics,
        "goals": goals,
        "goal_reached": reached,
    }


# --- import -----------------------------------------------------------------------------------


def maze_of_file(path: Path) -> str | None:
    """The env id an OGBench file name names (`pointmaze-medium-navigate-v0.npz` ->
    `pointmaze-medium-v0`), or None for another name."""
    match = _FILE_NAME.match(path.name)
    return f"{match.group(1)}-v0" if match else None


def _load(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise UserError(f"OGBench file {path} not found (set ingest.ogbench.path)")
    try:
        with np.load(path) as f:
            return {k: f[k] for k in f.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise UserError(f"{path} is not a numpy .npz file ({exc})") from exc


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


def _episode_ends(terminals: np.ndarray, where: str) -> np.ndarray:
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
    spec = _spec(env_id)
    files = [path]
    val = path.with_name(path.stem + "-val.npz")
    if include_val and val.is_file() and not path.stem.endswith("-val"):
        files.append(val)
    loaded = []
    for f in files:
        arrays = _load(f)
        _check_arrays(arrays, str(f), spec)
        _check_maze(np.asarray(arrays["observations"], np.float64)[:, :2], str(f), spec)
        loaded.append((arrays, _episode_ends(arrays["terminals"], str(f))))
    described = [
        {
            "path": str(f.resolve()),
            "steps": len(a["observations"]),
            "episodes": len(ends),
            "arrays": sorted(a),
        }
        for f, (a, ends) in zip(files, loaded, strict=True)
    ]
    with_qpos = all("qpos" in a and "qvel" in a for a, _ in loaded)
    generator = {
        "files": described,
        "physics_from": "qpos, qvel" if with_qpos else _PHYSICS_FROM_OBSERVATIONS[spec.loco],
    }
    info = _info(spec, name, None, generator, goal_dim=0)
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


def write_ogbench_npz(path: str | Path, episodes: list[Episode]) -> int:
    """Write episodes in OGBench's file layout (float32 arrays, `terminals` on each episode's
    last step, `qpos` / `qvel` from the physics states); returns the number of steps."""
    columns: dict[str, list[np.ndarray]] = {k: [] for k in (*REQUIRED, *OPTIONAL)}
    for ep in episodes:
        n = len(ep)
        terminals = np.zeros(n, dtype=bool)
        terminals[-1] = True
        columns["observations"].append(ep.observations.astype(np.float32))
        columns["actions"].append(ep.actions.astype(np.float32))
        columns["terminals"].append(terminals)
        if ep.physics is not None:
            nq = (ep.physics.shape[1] - 1) // 2
            columns["qpos"].append(ep.physics[:, 1 : 1 + nq].astype(np.float32))
            columns["qvel"].append(ep.physics[:, 1 + nq :].astype(np.float32))
    arrays = {k: np.concatenate(v) for k, v in columns.items() if v}
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
    return len(arrays["actions"])


# --- checks -----------------------------------------------------------------------------------

# The point's command moves it at most 0.2 m per axis a step, and a wall contact can push it a
# little further (measured: up to 0.29 m in 200k generated steps); a hidden reset jumps cells.
_MAX_POINT_STEP = 1.0
# Recorded physics must equal the observations (float32 files leave ~1e-6 of room).
_PHYSICS_ATOL = 1e-4


def check_ogbench_dataset(episodes: Iterable[Episode], info: DatasetInfo) -> DatasetReport:
    """Checks of an OGBench point-maze dataset, one episode at a time: finite values, actions in
    [-1, 1], positions in the maze's free cells (and the body's smallest clearance to a wall,
    negative inside one), no jump beyond a step's reach (no hidden reset inside an episode),
    physics qpos equal to the observations; the goal-reach rate if recorded.
    """
    spec = _spec(info.env_id)
    walls = MazeWalls(spec.layout)
    report, problems = DatasetReport(), []
    reached, has_goals = 0, True
    for ep in episodes:
        report.n_episodes += 1
        report.n_steps += len(ep)
        arrays = [ep.observations, ep.actions] + [a for a in (ep.physics,) if a is not None]
        finite = np.all([np.isfinite(a).all(axis=1) for a in arrays], axis=0)
        if not finite.all():
            report.n_nonfinite += int((~finite).sum())
            problems.append(f"episode {ep.index}: NaN or inf values")
            continue
        if np.abs(ep.actions).max() > 1.0 + 1e-6:
            problems.append(f"episode {ep.index}: actions outside [-1, 1]")
        pos = ep.observations[:, :2]
        outside, in_wall, clearance = walls.measure(pos)
        report.n_outside_bounds += int(outside.sum())
        report.n_in_wall += int(in_wall.sum())
        report.min_wall_clearance = min(report.min_wall_clearance, float(clearance.min()))
        if outside.any() or in_wall.any():
            problems.append(f"episode {ep.index}: positions in walls or outside the maze")
        if spec.loco == "point" and len(ep) > 1:
            jump = float(np.linalg.norm(np.diff(pos, axis=0), axis=1).max())
            report.max_step_distance = max(report.max_step_distance, jump)
            if jump > _MAX_POINT_STEP:
                problems.append(f"episode {ep.index}: the point jumps {jump:.3f} m in one step")
        nq = spec.model.nq
        if ep.physics is not None and np.abs(ep.physics[:, 1 : 1 + 2] - pos).max() > _PHYSICS_ATOL:
            problems.append(f"episode {ep.index}: physics qpos differ from the observations")
        if ep.physics is not None and ep.physics.shape[1] != 1 + nq + spec.model.nv:
            problems.append(f"episode {ep.index}: physics states of the wrong size")
        if ep.goal_reached is None:
            has_goals = False
        else:
            reached += int(ep.goal_reached.sum())
    if report.n_episodes == 0:
        problems.append("the dataset has no episodes")
    if has_goals and report.n_steps:
        report.goals_reached = reached
        report.goals_per_1000_steps = 1000.0 * reached / report.n_steps
    report.problems = problems[:20]
    return report
