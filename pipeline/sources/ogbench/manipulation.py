"""OGBench's manipulation datasets (cube-single, cube-double, scene, the puzzles; `play` or
`noisy`) as an ingest source, and the checks of what the ingest stage wrote.

Generation is `pipeline.envs.manipspace.data` (OGBench's scripted oracles, its recipe); this
module turns its episodes into the dataset conventions (`pipeline/dataset.py`) and back:

- an episode of `episode_steps` N is generated with N actions (N + 1 states); the last state,
  the result of the last action, is dropped (as Minari's final observation), so step t holds
  the observation before action t and the exact physics state it was observed in
  (`ManipSpaceSpec.physics_state`: full physics, the solver's warm start, OGBench's readings; its
  time column on the dataset clock, which MuJoCo's dynamics never read);
- `goal_reached` marks the steps at which the oracle finished its subtask with the subtask
  achieved (OGBench's `info['success']` at the step its oracle says it is done): completions;
- every generated episode is checked (`manipspace_data.check`: shapes, cubes inside the
  workspace, observations holding their states' cube positions and button states, the scene's
  health rule) before it is written; a failing one stops the ingest with the check's first
  problems.

OGBench's sizes: 1000 episodes x 1001 steps per dataset (`ingest.episodes`, `ingest.episode_steps`);
`ingest.ogbench.workers` processes generate them (each episode a function of its own seed, so the
same data for any number).

OGBench's downloaded manipulation `.npz` files import with `path` (`manip_npz.py`): the same
episodes and metadata, with each step's state restored from the file's `qpos` / `qvel` /
`button_states` (not bit for bit: a step from one lands on average ~1e-4 observation units from
the recorded next observation) and no
completions (the file does not say when its oracle finished a subtask); the check reads the
restore error back.
"""

from __future__ import annotations

import functools
import multiprocessing
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from pipeline.dataset import DatasetInfo, Episode
from pipeline.envs.manipspace.data import (
    NOISE,
    RECIPES,
    check,
    check_sizes,
    episode_seeds,
    generate_episode,
    leaves_table,
    observed_buttons,
    out_of_bounds,
    state_buttons,
)
from pipeline.envs.manipspace.env import (
    BUTTON_DIM,
    CUBE_DIM,
    PROPRIO_DIM,
    XYZ_CENTER,
    XYZ_SCALE,
    ManipSpaceSpec,
    manipspace_spec,
)
from pipeline.envs.maze.checks import DatasetReport
from pipeline.errors import UserError
from pipeline.sources.common import Clock, ImportedDataset, with_progress
from pipeline.sources.episode_cache import cache_folder, cached_episodes
from pipeline.sources.ogbench.info import versions
from pipeline.sources.ogbench.manip_npz import (
    FLOAT32_TOLERANCE,
    load_manipulation_files,
    manipulation_episodes,
    restore_errors,
)
from pipeline.sources.ogbench.npz import describe_files

# The read-back check restores the recorded state every this many steps (and the last one).
RESTORE_EVERY = 50
# ... and, for an imported file, steps a restored state every this many steps (at 1001 steps
# per episode: 5 per episode, ~7 ms each).
STEP_EVERY = 200


@dataclass
class ManipulationReport(DatasetReport):
    """`DatasetReport` without the maze's geometry (steps, speeds, walls), which a manipulation
    dataset does not have; `n_outside_bounds` counts steps with a cube out of the workspace.
    An imported file's (`manip_npz.py`) adds how far its restored states are from what it
    recorded, in observation units (max over dims; None for generated data, restored exactly)."""

    restore_observation_error_max: float | None = None
    """Largest gap of a restored state's observation to the recorded one (float32 rounding)."""
    restore_next_error_max: float | None = None
    """Largest gap of the observation after one step from a restored state, with the recorded
    action, to the recorded next observation."""
    restore_next_error_mean: float | None = None
    """Its mean over the stepped steps."""
    restore_steps: int | None = None
    """Restored states stepped (every `STEP_EVERY`-th step of each episode)."""

    MAZE_ONLY = ("max_step_distance", "max_axis_speed", "min_wall_clearance", "n_in_wall")

    def metrics(self) -> dict[str, float]:
        return {k: v for k, v in super().metrics().items() if k not in self.MAZE_ONLY}


def state_names(spec: ManipSpaceSpec) -> tuple[list[str], list[str]]:
    """Names and units of the observation's dims (`pipeline.envs.manipspace.env`'s layout)."""
    names = [f"arm_qpos[{i}]" for i in range(6)] + [f"arm_qvel[{i}]" for i in range(6)]
    units = ["rad"] * 6 + ["rad/s"] * 6
    names += [
        "pinch_x",
        "pinch_y",
        "pinch_z",
        "pinch_cos_yaw",
        "pinch_sin_yaw",
        "gripper_opening",
        "gripper_contact",
    ]
    units += ["0.1 m"] * 3 + ["1"] * 4
    for c in range(spec.n_cubes):
        names += [
            f"cube{c}_{k}" for k in ("x", "y", "z", "qw", "qx", "qy", "qz", "cos_yaw", "sin_yaw")
        ]
        units += ["0.1 m"] * 3 + ["1"] * 6
    for b in range(spec.n_buttons):  # the scene's 2, a puzzle's rows x cols (row-major)
        names += [f"button{b}_off", f"button{b}_on", f"button{b}_pos", f"button{b}_vel"]
        units += ["1", "1", "1/120 m", "m/s"]
    if spec.scene:
        names += ["drawer_pos", "drawer_vel", "window_pos", "window_vel"]
        units += ["1/18 m", "m/s", "1/15 m", "m/s"]
    expected = PROPRIO_DIM + CUBE_DIM * spec.n_cubes + BUTTON_DIM * spec.n_buttons + 4 * spec.scene
    assert len(names) == len(units) == spec.state_dim == expected
    return names, units


def manipulation_info(
    spec: ManipSpaceSpec, name: str, seed: int | None, generator: dict
) -> DatasetInfo:
    """`DatasetInfo` of a manipulation dataset (seed None: imported); `generator` gets the
    workspace."""
    names, units = state_names(spec)
    return DatasetInfo(
        name=name,
        source="ogbench",
        env_id=spec.env_id,
        state_names=names,
        action_names=["dx", "dy", "dz", "dyaw", "dgrip"],
        state_units=units,
        action_units=["0.05 m", "0.05 m", "0.05 m", "0.3 rad", "1"],
        control_period=spec.dt,
        physics_dim=spec.physics_dim,
        goal_dim=0,
        seed=seed,
        env_kwargs={},
        generator={**generator, "layout": spec.layout, "goal_dims": list(spec.goal_dims)},
        versions=versions(),
    )


def open_manipulation(
    env_id: str,
    dataset_type: str,
    episodes: int,
    episode_steps: int,
    seed: int,
    name: str,
    noise: float | None = None,
    path: str | None = None,
    progress: bool = False,
    workers: int = 1,
    include_val: bool = True,
    cache_root: Path | None = None,
) -> ImportedDataset:
    """OGBench's `dataset_type` data of `env_id`, generated lazily (module docstring), or its
    file `path` imported (with its `-val.npz` if `include_val`; the sizes, seed, noise and
    dataset type are then the file's).

    With `workers` > 1, episodes are generated by that many processes and streamed in order:
    each episode is a function of its own seed alone, so the data do not depend on `workers`.
    With a `cache_root`, generated episodes are kept there in chunks as they are made, and a run
    killed on the way resumes from them (`pipeline.sources.episode_cache`).

    Raises:
        UserError: a dataset type that is not a manipulation recipe; a file that is missing,
            damaged, foreign or of another env (`manip_npz.load_manipulation_files`).
    """
    if path:
        return _import(Path(path).expanduser(), env_id, name, include_val, progress)
    if dataset_type not in RECIPES:
        raise UserError(
            f"ingest.ogbench.dataset_type {dataset_type!r} is a maze recipe; {env_id} has "
            f"OGBench's manipulation recipes: {', '.join(RECIPES)}"
        )
    check_sizes(env_id, dataset_type, episodes, episode_steps)
    spec = manipspace_spec(env_id)
    noise = NOISE if noise is None else float(noise)
    generator: dict[str, Any] = {
        "recipe": "OGBench data_gen_scripts/generate_manipspace.py",
        "dataset_type": dataset_type,
        "n_episodes": episodes,
        "episode_steps": episode_steps,
        "noise": noise,
        "continuous": False,
    }
    info = manipulation_info(spec, name, seed, generator)
    frames = episodes * episode_steps
    cache = None if cache_root is None else cache_folder(cache_root, info)
    stream = _episodes(spec, dataset_type, episodes, episode_steps, seed, noise, workers, cache)
    return ImportedDataset(info, with_progress(stream, frames, name, progress), frames)


def _import(
    path: Path, env_id: str, name: str, include_val: bool, progress: bool
) -> ImportedDataset:
    """OGBench's manipulation file(s) as a dataset (`manip_npz.py`)."""
    dataset_type, files, loaded = load_manipulation_files(path, env_id, include_val)
    spec = manipspace_spec(env_id)
    described = describe_files(files, loaded)
    generator: dict[str, Any] = {
        "recipe": "OGBench data_gen_scripts/generate_manipspace.py",
        "dataset_type": dataset_type,
        "files": described,
        "physics_from": "qpos, qvel, button_states; pinch pose and contact from observations; "
        "warm start zero",
        "continuous": False,
    }
    info = manipulation_info(spec, name, None, generator)
    stream, frames = manipulation_episodes(loaded, spec, name, progress)
    return ImportedDataset(info, stream, frames)


def _generated(
    env_id: str,
    recipe: str,
    steps: int,
    noise: float,
    seeds: list[np.random.SeedSequence],
    indices: Sequence[int],
    workers: int,
) -> Iterator[dict[str, Any]]:
    """The generator's episodes `indices` in order, made here or by `workers` processes."""
    one = functools.partial(generate_episode, env_id, recipe, steps, noise=noise)
    chosen = [seeds[k] for k in indices]
    if workers <= 1:
        yield from map(one, chosen)
        return
    # spawn: each worker builds its own env (MuJoCo and OGBench's models do not cross a fork
    # cleanly) and is stopped with the stream.
    pool = multiprocessing.get_context("spawn").Pool(min(workers, len(chosen)))
    try:
        yield from pool.imap(one, chosen)
    finally:
        pool.terminate()


def _episodes(
    spec: ManipSpaceSpec,
    recipe: str,
    episodes: int,
    steps: int,
    seed: int,
    noise: float,
    workers: int = 1,
    cache: Path | None = None,
) -> Iterator[Episode]:
    clock = Clock(spec.dt)
    make = functools.partial(
        _generated, spec.env_id, recipe, steps, noise, episode_seeds(seed, episodes),
        workers=workers,
    )  # fmt: skip
    for k, ep in enumerate(cached_episodes(make, episodes, cache)):
        report = check([ep], spec)
        if not report["ok"]:
            raise UserError(
                f"generated {spec.env_id} {recipe} episode {k} failed its checks: "
                + "; ".join(report["problems"][:3])
            )
        time = clock.next(steps)
        physics = ep["physics"][:-1].copy()
        physics[:, 0] = time
        yield Episode(
            index=k,
            observations=ep["observations"][:-1],
            actions=ep["actions"],
            time=time,
            physics=physics,
            goal_reached=ep["subtask_done"] & ep["success"],
        )


def check_manipulation_dataset(
    episodes: Iterable[Episode], info: DatasetInfo
) -> ManipulationReport:
    """Check a manipulation dataset read back from its file, one episode at a time.

    Finite values; actions in [-1, 1]; no cube beyond the workspace bounds +- 0.2 m (in a state
    or an observation); observed cube positions and button states equal to their states'; the
    scene's cubes on the table; and every `RESTORE_EVERY`-th recorded state (and the last)
    restored gives its recorded observation bit for bit. Completions (`goal_reached`) are
    counted. An imported file's states (restored from its qpos / qvel, `manip_npz.py`) are held
    to float32 rounding (`FLOAT32_TOLERANCE`) instead, and stepped (`restore_errors`) for the
    report's restore gaps.

    Returns:
        The report; `report.problems` empty if all checks passed (at most 20 listed).
    """
    spec = manipspace_spec(info.env_id)
    imported = "files" in info.generator  # states restored from a file: not bit for bit
    report, problems = ManipulationReport(), []
    own: list[np.ndarray] = []
    after: list[np.ndarray] = []
    data = mujoco.MjData(spec.model)
    cube_cols = [PROPRIO_DIM + CUBE_DIM * i + k for i in range(spec.n_cubes) for k in range(3)]
    reached, reaching, with_goals = 0, 0, False
    for ep in episodes:
        report.n_episodes += 1
        report.n_steps += len(ep)
        if ep.physics is None or ep.physics.shape[1] != spec.physics_dim:
            problems.append(f"episode {ep.index}: no physics states of {spec.physics_dim} numbers")
            continue
        arrays = (ep.observations, ep.actions, ep.physics)
        finite = np.all([np.isfinite(a).all(axis=1) for a in arrays], axis=0)
        if not finite.all():
            report.n_nonfinite += int((~finite).sum())
            problems.append(f"episode {ep.index}: NaN or inf values")
            continue
        if np.abs(ep.actions).max() > 1.0:
            problems.append(f"episode {ep.index}: actions outside [-1, 1]")
        cubes = spec.cube_positions(ep.physics)
        observed_cubes = ep.observations[:, cube_cols].reshape(len(ep), spec.n_cubes, 3)
        observed = XYZ_CENTER + observed_cubes / XYZ_SCALE
        outside = out_of_bounds(cubes) | out_of_bounds(observed)
        report.n_outside_bounds += int(outside.sum())
        if outside.any():
            problems.append(
                f"episode {ep.index}: a cube is out of the workspace at "
                f"{int(outside.sum())} steps, first {int(np.argmax(outside))}"
            )
        expected = ((cubes - XYZ_CENTER) * XYZ_SCALE).reshape(len(ep), 3 * spec.n_cubes)
        gap = np.abs(ep.observations[:, cube_cols] - expected).max(initial=0.0)
        if not gap <= (FLOAT32_TOLERANCE if imported else 0.0):
            problems.append(f"episode {ep.index}: observed cube positions differ from the states'")
        if not np.array_equal(observed_buttons(spec, ep.observations),
                              state_buttons(spec, ep.physics)):  # fmt: skip
            problems.append(f"episode {ep.index}: observed button states differ from the states'")
        if spec.scene and leaves_table(cubes):
            problems.append(f"episode {ep.index}: the cube leaves the table (OGBench's rule)")
        if imported:
            gaps, stepped = restore_errors(spec, ep, RESTORE_EVERY, STEP_EVERY)
            own.append(gaps)
            after.append(stepped)
            if not gaps.max(initial=0.0) <= FLOAT32_TOLERANCE:
                problems.append(
                    f"episode {ep.index}: restored states observe up to {gaps.max():.3g} off "
                    "their recorded observations"
                )
        exact = [] if imported else {*range(0, len(ep), RESTORE_EVERY), len(ep) - 1}
        for t in sorted(exact):
            spec.set_physics_state(data, ep.physics[t])
            if not np.array_equal(spec.observe(data), ep.observations[t]):
                problems.append(
                    f"episode {ep.index}: the state at step {t} does not restore to "
                    "its recorded observation"
                )
                break
        if ep.goal_reached is not None:
            with_goals = True
            reached += int(ep.goal_reached.sum())
            reaching += int(ep.goal_reached.any())
    if report.n_episodes == 0:
        problems.append("the dataset has no episodes")
    if imported and own:
        own_all, after_all = np.concatenate(own), np.concatenate(after)
        report.restore_observation_error_max = float(own_all.max(initial=0.0))
        if after_all.size:
            report.restore_next_error_max = float(after_all.max())
            report.restore_next_error_mean = float(after_all.mean())
        report.restore_steps = int(after_all.size)
    if report.n_steps and with_goals:  # an imported file does not say when subtasks ended
        report.goals_reached = reached
        report.goals_per_1000_steps = 1000.0 * reached / report.n_steps
        report.episodes_reaching_goal = reaching
    report.problems = problems[:20]
    return report
