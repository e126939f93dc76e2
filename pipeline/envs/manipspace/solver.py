"""OGBench's own oracles on its evaluation tasks: the scripted reference of results/manipulation.

OGBench's plan oracles (`ogbench.manipspace.oracles.plan`, the same that make the `play` data
here) each do one subtask (move a cube, press a button, slide the drawer or the window) toward a
target that OGBench's data-collection mode puts in `info`. An evaluation task is a goal for all
the objects at once, so `next_subtask` decides, from the env's `info`, which subtask comes next:

- a cube whose goal is in the drawer: the drawer open first (its button unlocked), then the cube
  placed where its goal is with the drawer as it now stands (the cube rides with the drawer);
- the drawer, then the window, to their goals, each unlocked by its button first;
- the cubes on the table, bottom ones first (a stack's base before its top); a cube whose goal
  another cube occupies waits, and when every wrong cube waits (a swap) one is set aside first;
- the buttons to their goal states last.

An oracle runs its plan to the end before the next subtask is chosen. The plans are noise-free
(OGBench's `play` data adds noise; the reference is the clean script). Episodes start from the
reset seeds the agents' episodes use (`pipeline.evaluation.tasks.manipulation_episodes`) and end
at OGBench's success or its step limit, as OGBench's evaluation does.

A puzzle ("Lights Out") has one kind of subtask, a button press (OGBench's button plan oracle,
the gripper kept closed as in its puzzle data). Which buttons to press is solved exactly: a press
of button j flips every button it toggles (`puzzle_toggles`), so the presses x (one or none per
button) that turn the current states c into the goal g solve A x = g - c over GF(2), A the
toggle matrix; `lights_out_presses` solves it by Gaussian elimination and, where A is singular
(4x4: 4 free presses), takes the solution with the fewest presses. After every press the system
is solved again from the states the env reports (a press that failed or landed twice is made
good), and the next press is the one nearest the gripper.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.envs.ids import OGBENCH_PREFIX, TASKS
from pipeline.envs.manipspace.env import (
    EPISODE_STEPS,
    SUCCESS_TOLERANCE,
    ManipSpaceSpec,
    ObjectConfig,
    make_manipspace_env,
    puzzle_toggles,
)
from pipeline.errors import UserError

# A cube counts as placed within half OGBench's tolerance (the subtask is redone otherwise).
PLACED = SUCCESS_TOLERANCE / 2
DRAWER_OPEN = -0.12  # OGBench's data puts cubes in the drawer only when it is open past this
TABLE_Z = 0.04  # a cube goal above this is on another cube or in the drawer
STACKED_XY = 0.02  # two cubes this close in x-y are stacked (OGBench's `top_blocks` test)
OCCUPIED = 0.05  # a goal this close to another cube's position is taken
# Where a cube is set aside when every wrong cube's goal is taken (x-y, m; the table's middle band).
ASIDE = np.array([[0.5, -0.2], [0.35, -0.2], [0.5, 0.2], [0.35, 0.2], [0.5, 0.0], [0.35, 0.0]])
# The most free presses whose combinations `lights_out_presses` tries for the fewest presses
# (2^this solutions; OGBench's grids have at most 4).
MAX_FREE_PRESSES = 16


@dataclass(frozen=True)
class Subtask:
    """One oracle run: `kind` (cube, button, drawer, window), which object, and its target (a cube's
    position; a joint position; a button's next state)."""

    kind: str
    index: int = 0
    target: Any = None


def _cubes(info: dict[str, Any], n: int) -> np.ndarray:
    return np.array([info[f"privileged/block_{i}_pos"] for i in range(n)])


def _drawer_goal_cube(goal: ObjectConfig, i: int) -> bool:
    """Cube `i`'s goal is in the drawer: off the table and not on another cube's goal."""
    xyz = goal.block_xyzs[i]
    if xyz[2] <= TABLE_Z:
        return False
    others = np.delete(goal.block_xyzs, i, axis=0)
    return not any(np.linalg.norm(o[:2] - xyz[:2]) < STACKED_XY for o in others)


def in_drawer_goal(goal: ObjectConfig, i: int, drawer: float, axis: np.ndarray) -> np.ndarray:
    """Cube `i`'s goal with the drawer at `drawer` instead of its goal position (the cube rides
    with the drawer, whose slide joint moves along world `axis`)."""
    return goal.block_xyzs[i] + axis * (drawer - goal.drawer_pos)


def next_subtask(
    info: dict[str, Any], goal: ObjectConfig, scene: bool, drawer_axis: np.ndarray | None = None
) -> Subtask | None:
    """What the oracle does next toward `goal` from the state in `info` (module docstring);
    None when nothing is left. `drawer_axis`: the scene's drawer slide axis (world)."""
    n = len(goal.block_xyzs)
    cubes = _cubes(info, n)
    goals = goal.block_xyzs.copy()
    if scene:
        assert goal.button_states is not None and drawer_axis is not None
        drawer = float(info["privileged/drawer_pos"][0])
        for i in range(n):
            if _drawer_goal_cube(goal, i):
                goals[i] = in_drawer_goal(goal, i, drawer, drawer_axis)
    wrong = [i for i in range(n) if np.linalg.norm(cubes[i] - goals[i]) > PLACED]
    if scene:
        window = float(info["privileged/window_pos"][0])
        buttons = [int(info[f"privileged/button_{b}_state"]) for b in range(2)]
        for i in wrong:
            if _drawer_goal_cube(goal, i):
                if drawer > DRAWER_OPEN:
                    return Subtask("button", 0, 1) if buttons[0] == 0 else Subtask("drawer")
                return Subtask("cube", i, goals[i])
        for b, (kind, now, target) in enumerate(
            (("drawer", drawer, goal.drawer_pos), ("window", window, goal.window_pos))
        ):
            if abs(now - target) > PLACED:
                return Subtask("button", b, 1) if buttons[b] == 0 else Subtask(kind, 0, target)
        wrong = [i for i in wrong if not _drawer_goal_cube(goal, i)]
    cube = _next_cube(cubes, goal.block_xyzs, wrong)
    if cube is not None:
        return cube
    if scene:
        for b in range(2):
            if buttons[b] != goal.button_states[b]:
                return Subtask("button", b, int(goal.button_states[b]))
    return None


def _next_cube(cubes: np.ndarray, goals: np.ndarray, wrong: list[int]) -> Subtask | None:
    """The first wrong cube that can go to its goal now, else one set aside (a swap)."""

    def free(i: int) -> bool:
        goal = goals[i]
        on_it = any(  # a cube on top of cube i: that one moves first
            j != i and cubes[j][2] > cubes[i][2] and np.linalg.norm(cubes[j][:2] - cubes[i][:2])
            < STACKED_XY for j in range(len(cubes))
        )  # fmt: skip
        taken = any(  # another cube where this one goes (a cube below it is its base)
            j != i and np.linalg.norm(cubes[j] - goal) < OCCUPIED
            and abs(cubes[j][2] - goal[2]) < STACKED_XY for j in range(len(cubes))
        )  # fmt: skip
        base_missing = goal[2] > TABLE_Z and any(  # its goal is on a cube not there yet
            j != i and np.linalg.norm(goals[j][:2] - goal[:2]) < STACKED_XY
            and np.linalg.norm(cubes[j] - goals[j]) > PLACED for j in range(len(cubes))
        )  # fmt: skip
        return not on_it and not taken and not base_missing

    for i in wrong:
        if free(i):
            return Subtask("cube", i, goals[i])
    if not wrong:
        return None
    i = wrong[0]
    busy = np.concatenate([cubes, goals])[:, :2]
    spot = max(ASIDE, key=lambda p: np.min(np.linalg.norm(busy - p, axis=1)))
    return Subtask("cube", i, np.array([spot[0], spot[1], 0.02]))


def drawer_axis(env: Any) -> np.ndarray:
    """The scene's drawer slide axis in world coordinates."""
    u = env.unwrapped
    return u._data.xaxis[u._model.joint("drawer_slide").id].copy()


def _axis_target(env: Any, joint: str, site: str, target: float) -> np.ndarray:
    """Where site `site` is when slide joint `joint` is at `target` (world, m)."""
    u = env.unwrapped
    j = u._model.joint(joint).id
    now = u._data.qpos[u._model.jnt_qposadr[j]]
    return u._data.site(site).xpos + u._data.xaxis[j] * (target - now)


def oracle_info(env: Any, info: dict[str, Any], sub: Subtask) -> dict:
    """`info` with the data-collection keys the subtask's plan oracle reads."""
    out = dict(info)
    u = env.unwrapped
    if sub.kind == "cube":
        out["privileged/target_block"] = sub.index
        out["privileged/target_block_pos"] = np.asarray(sub.target, dtype=np.float64)
        out["privileged/target_block_yaw"] = np.zeros(1)
    elif sub.kind == "button":
        out["privileged/target_button"] = sub.index
        out["privileged/target_button_top_pos"] = u._data.site(f"btntop_{sub.index}").xpos.copy()
    elif sub.kind == "drawer":
        target = -0.16 if sub.target is None else sub.target
        out["privileged/target_drawer_handle_pos"] = _axis_target(
            env, "drawer_slide", "drawer_handle_center", target
        )
    else:
        out["privileged/target_window_handle_pos"] = _axis_target(
            env, "window_slide", "window_handle_center", sub.target
        )
    return out


def toggle_matrix(rows: int, cols: int) -> np.ndarray:
    """`[n, n]` (uint8) over GF(2): entry (i, j) is 1 when a press of button j flips button i."""
    n = rows * cols
    matrix = np.zeros((n, n), dtype=np.uint8)
    for j, flipped in enumerate(puzzle_toggles(rows, cols)):
        matrix[flipped, j] = 1
    return matrix


def lights_out_presses(grid: tuple[int, int], current: Any, goal: Any) -> np.ndarray:
    """The buttons to press once each (`[n]` bool, row-major) that turn button states `current`
    into `goal` in a rows x cols puzzle, with the fewest presses (module docstring).

    Raises:
        UserError: no presses do it (Lights Out on a singular grid, e.g. 4x4, has unreachable
            state pairs).
    """
    rows, cols = grid
    current = np.asarray(current, dtype=np.int64).ravel()
    goal = np.asarray(goal, dtype=np.int64).ravel()
    n = rows * cols
    if current.shape != (n,) or goal.shape != (n,):
        raise ValueError(f"button states of a {rows}x{cols} puzzle have {n} entries")
    system = np.concatenate([toggle_matrix(rows, cols), ((goal - current) % 2)[:, None]], axis=1)
    system = system.astype(np.uint8)
    pivots: list[int] = []
    for col in range(n):  # reduced row echelon form over GF(2)
        below = np.flatnonzero(system[len(pivots) :, col])
        if not below.size:
            continue
        row = len(pivots) + int(below[0])
        system[[len(pivots), row]] = system[[row, len(pivots)]]
        others = np.flatnonzero(system[:, col])
        others = others[others != len(pivots)]
        system[others] ^= system[len(pivots)]
        pivots.append(col)
    if system[len(pivots) :, n].any():
        raise UserError(
            f"no button presses turn the {rows}x{cols} puzzle's states "
            f"{current.tolist()} into {goal.tolist()}: Lights Out on this grid cannot reach "
            "that goal from there"
        )
    free = [c for c in range(n) if c not in pivots]
    if len(free) > MAX_FREE_PRESSES:
        raise ValueError(f"{len(free)} free presses: too many solutions to search")
    base = np.zeros(n, dtype=np.uint8)
    base[pivots] = system[: len(pivots), n]
    kernel = []
    for f in free:  # with free press f alone, each pivot press becomes its row's entry
        v = np.zeros(n, dtype=np.uint8)
        v[f] = 1
        v[pivots] = system[: len(pivots), f]
        kernel.append(v)
    best = base
    for mask in range(1, 2 ** len(free)):
        x = base.copy()
        for k, v in enumerate(kernel):
            if mask >> k & 1:
                x ^= v
        if x.sum() < best.sum():
            best = x
    return best.astype(bool)


def next_press(info: dict[str, Any], goal: np.ndarray, grid: tuple[int, int]) -> Subtask | None:
    """The press the oracle makes next toward the puzzle's `goal` button states from the state
    in `info` (a task-mode env's): of the presses `lights_out_presses` finds, the button whose
    top is nearest the gripper; None when the states are the goal's."""
    n = grid[0] * grid[1]
    states = [int(info[f"privileged/button_{i}_state"]) for i in range(n)]
    presses = np.flatnonzero(lights_out_presses(grid, states, goal))
    if not presses.size:
        return None
    effector = np.asarray(info["proprio/effector_pos"])
    tops = np.array([info[f"privileged/button_{i}_top_pos"] for i in presses])
    return Subtask("button", int(presses[np.argmin(np.linalg.norm(tops - effector, axis=1))]))


def _plan_oracles(env: Any) -> dict[str, Any]:
    from ogbench.manipspace.oracles.plan.button_plan import ButtonPlanOracle
    from ogbench.manipspace.oracles.plan.cube_plan import CubePlanOracle
    from ogbench.manipspace.oracles.plan.drawer_plan import DrawerPlanOracle
    from ogbench.manipspace.oracles.plan.window_plan import WindowPlanOracle

    kinds = {"cube": CubePlanOracle, "button": ButtonPlanOracle, "drawer": DrawerPlanOracle,
             "window": WindowPlanOracle}  # fmt: skip
    return {k: cls(env=env, noise=0.0) for k, cls in kinds.items()}


@contextmanager
def _numpy_seeded(seed: int) -> Iterator[None]:
    """The plan oracles draw from numpy's global generator: seeded here, restored after."""
    saved = np.random.get_state()
    np.random.seed(seed % 2**32)
    try:
        yield
    finally:
        np.random.set_state(saved)


def _goal_of(env: Any, scene: bool) -> ObjectConfig:
    """The goal OGBench's task reset set (as `ManipSpaceSpec.task_start` reads it)."""
    u = env.unwrapped
    cubes = np.array([u._data.mocap_pos[m] for m in u._cube_target_mocap_ids])
    if not scene:
        return ObjectConfig(cubes)
    return ObjectConfig(cubes, np.array(u._target_button_states, dtype=np.int64),
                        float(u._target_drawer_pos), float(u._target_window_pos))  # fmt: skip


@dataclass(frozen=True)
class OracleEpisode:
    success: bool
    steps: int  # steps taken (to the goal, or the limit)
    subtasks: int  # oracle runs started


def run_episode(env: Any, task_id: int, reset_seed: int, seed: int, scene: bool) -> OracleEpisode:
    """One evaluation episode of task `task_id` from `env.reset(seed=reset_seed, ...)` (a
    task-mode env with OGBench's step limit), the oracles' randomness from `seed`."""
    observation, info = env.reset(seed=int(reset_seed), options={"task_id": int(task_id)})
    goal = _goal_of(env, scene)
    axis = drawer_axis(env) if scene else None
    oracles = _plan_oracles(env)
    steps = subtasks = 0
    with _numpy_seeded(seed):
        while True:
            sub = next_subtask(info, goal, scene, axis)
            if sub is None:  # all placed, but not within OGBench's tolerance: wait it out
                sub = Subtask("cube", 0, goal.block_xyzs[0])
            oracle = oracles[sub.kind]
            observation, info, ran, ended = _run_plan(env, oracle, observation, info, sub)
            steps, subtasks = steps + ran, subtasks + 1
            if ended:
                return OracleEpisode(bool(info["success"]), steps, subtasks)


def _run_plan(
    env: Any, oracle: Any, observation: Any, info: dict[str, Any], sub: Any
) -> tuple[Any, dict[str, Any], int, bool]:
    """One oracle's plan for subtask `sub`, run to its end: the last observation and info, the
    steps taken, and whether the episode ended (OGBench's success, termination or step limit)."""
    sub_info = oracle_info(env, info, sub)
    oracle.reset(observation, sub_info)
    steps = 0
    while not oracle.done:
        action = oracle.select_action(observation, sub_info)
        observation, _, terminated, truncated, info = env.step(action)
        steps += 1
        if info["success"] or terminated or truncated:
            return observation, info, steps, True
        sub_info = oracle_info(env, info, sub)
    return observation, info, steps, False


def run_puzzle_episode(env: Any, task_id: int, reset_seed: int, seed: int) -> OracleEpisode:
    """`run_episode` in a puzzle: OGBench's button plan oracle (noise-free, gripper closed)
    pressing the buttons `next_press` picks, one plan at a time, until OGBench's success or
    step limit."""
    from ogbench.manipspace.oracles.plan.button_plan import ButtonPlanOracle

    observation, info = env.reset(seed=int(reset_seed), options={"task_id": int(task_id)})
    u = env.unwrapped
    grid = (int(u._num_rows), int(u._num_cols))
    goal = np.array(u._target_button_states, dtype=np.int64)
    oracle = ButtonPlanOracle(env=env, noise=0.0, gripper_always_closed=True)
    steps = subtasks = 0
    with _numpy_seeded(seed):
        while True:
            sub = next_press(_with_button_tops(env, info), goal, grid)
            if sub is None:  # unreachable: the env ends the episode at the goal states
                raise RuntimeError(f"{env.spec.id}: at the goal states without OGBench's success")
            observation, info, ran, ended = _run_plan(env, oracle, observation, info, sub)
            steps, subtasks = steps + ran, subtasks + 1
            if ended:
                return OracleEpisode(bool(info["success"]), steps, subtasks)


def _with_button_tops(env: Any, info: dict[str, Any]) -> dict[str, Any]:
    """`info` with each puzzle button's top position (`privileged/button_<i>_top_pos`)."""
    u = env.unwrapped
    tops = {f"privileged/button_{i}_top_pos": u._data.site(f"btntop_{i}").xpos.copy()
            for i in range(u._num_buttons)}  # fmt: skip
    return info | tops


def episode_seeds(seed: int, task_id: int, k: int) -> tuple[int, int]:
    """(episode seed, reset seed) of episode `k` of task `task_id`: those of
    `pipeline.evaluation.tasks.manipulation_episodes`, so the oracle starts where the agents do
    (tests/test_manipspace_oracle.py holds them equal)."""
    seq = np.random.SeedSequence([seed, TASKS.index("ogbench"), task_id, k])
    episode_seed, reset_seed = (int(v) for v in seq.generate_state(2))
    return episode_seed, reset_seed


def evaluate(spec: ManipSpaceSpec, episodes: int, seed: int) -> dict[str, list[OracleEpisode]]:
    """`episodes` per OGBench task, `{"ogbench-task1": [...], ...}`, on the agents' starts."""
    env = make_manipspace_env(spec.env_id, max_episode_steps=EPISODE_STEPS[spec.env_id])
    out: dict[str, list[OracleEpisode]] = {}
    for task in spec.tasks():
        runs = []
        for k in range(episodes):
            episode_seed, reset_seed = episode_seeds(seed, task.task_id, k)
            if spec.grid is not None:
                runs.append(run_puzzle_episode(env, task.task_id, reset_seed, episode_seed))
            else:
                runs.append(run_episode(env, task.task_id, reset_seed, episode_seed, spec.scene))
        out[f"{OGBENCH_PREFIX}task{task.task_id}"] = runs
    return out
