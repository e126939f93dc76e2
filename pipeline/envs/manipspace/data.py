"""OGBench's manipulation datasets (`play`, `noisy`) generated with the package's own oracles,
and a check of what came out.

Follows `data_gen_scripts/generate_manipspace.py` of OGBench's repository (read for its facts; the
loop is written here, as the script needs absl and writes files):

- the env is made with `mode='data_collection'`, `terminate_at_goal=False`; each reset draws a
  random arm pose, random cube poses (scene: also button states, drawer and window positions;
  puzzle: random button states) and a first subtask ("target"): in the cube envs a cube to move
  to a random place, or (cube-double, probability `p_stack`) onto the other cube; in the scene one
  of cube / button / drawer / window (`SceneEnv.set_new_target`'s probabilities); in a puzzle a
  random button to press (`PuzzleEnv.set_new_target`: its state flipped is the target);
- one oracle per subtask kind drives the arm: `play` uses the plan oracles
  (`oracles/plan/*_plan.py`: keyframes interpolated, plus Gaussian noise `noise` x the action
  scale smoothed over time with `gaussian_filter1d(sigma=noise_smoothing)`); `noisy` the Markov
  oracles (`oracles/markov/*_markov.py`, `min_norm` 0.4) plus per-step Gaussian noise of std
  `xi x [1, 1, 1, 3, 10]`, `xi ~ U(0, noise)` drawn per episode, and with probability
  `p_random_action` (0.1; the puzzles' `commands.sh` lines 0.2) a uniform random action
  instead; actions are clipped to [-1, 1]. A puzzle has one kind, the button, and its oracle
  keeps the gripper closed (`gripper_always_closed=True`, the script's puzzle setting);
- when the oracle says it is done (plan oracles: the plan ran out; Markov oracles: the arm
  reached its random final pose, or its step limit passed: cube 200, button 100, drawer and
  window 75) the env draws the next subtask;
- `p_stack` is 0 for cube-single, U(0, 0.25) per episode for cube-double, 0.5 for the scene
  and the puzzles (which ignore it);
- scene episodes in which the cube leaves the visible table (y >= 0.29, or y <= -0.3 outside the
  drawer's height 0.06 - 0.08) are thrown away and redone;
- OGBench's sizes: 1000 episodes x 1001 steps, plus a 100-episode validation file, for each of
  cube-single, cube-double, scene, puzzle-3x3 and puzzle-4x4, play and noisy (puzzle-4x5: 3000,
  puzzle-4x6: 5000 episodes). Here the sizes are arguments with CPU-sized defaults.

Deterministic for a seed: each episode (and each redo) has its own `SeedSequence` child, which
seeds numpy's global generator (the oracles' and the script's source of randomness) and the
env's reset. OGBench draws its random actions from an unseeded `action_space.sample()`; here they
come from the same seeded global generator (float64, uniform in [-1, 1]).

Recorded per episode (T steps): `observations [T+1, state_dim]`, `actions [T, 5]`, exact
`physics [T+1, physics_dim]` states (`ManipSpaceSpec.physics_state`), and per step `success`
(the current subtask achieved after the step, the env's `info['success']`), `subtask_done` (the
oracle finished its subtask at this step; the next step pursues a new one) and `subtask` (the
kind pursued, an index into `SUBTASKS`). Every observation is `observe` of its state; it is the
env's own observation bit for bit except after a subtask switch in the cube envs, where
`set_new_target` refreshes the pinch site's pose (`mj_kinematics`) that the env's observation
had read one physics step stale: the recorded observation is the refreshed one, which is what
the next step acts from (so a state always holds its observation, and replaying the actions
through `control_step` reproduces the episode exactly). In the scene and the puzzles the env's
post-step forward pass has already refreshed it: there the two are the same.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from typing import Any

import gymnasium
import mujoco
import numpy as np

from pipeline.envs.ant import global_seed
from pipeline.envs.manipspace.env import (
    BUTTON_DIM,
    CUBE_DIM,
    HEALTHY_MARGIN,
    PROPRIO_DIM,
    WORKSPACE_BOUNDS,
    XYZ_CENTER,
    XYZ_SCALE,
    ManipSpaceSpec,
    check_manipspace_id,
    make_manipspace_env,
    manipspace_spec,
)
from pipeline.errors import UserError

RECIPES = ("play", "noisy")
SUBTASKS = ("cube", "button", "drawer", "window")
# OGBench's defaults (`generate_manipspace.py` flags, `commands.sh`).
NOISE = 0.1
NOISE_SMOOTHING = 0.5
MIN_NORM = 0.4
P_RANDOM_ACTION = {"play": 0.0, "noisy": 0.1}
PUZZLE_P_RANDOM_ACTION = {"play": 0.0, "noisy": 0.2}  # the puzzles' lines of `commands.sh`
MARKOV_NOISE_SHAPE = np.array([1.0, 1.0, 1.0, 3.0, 10.0])  # x xi per action dim
SCENE_P_STACK = 0.5
DOUBLE_P_STACK = (0.0, 0.25)
# The scene's health rule: where the cube is out of the camera's sight.
SCENE_FAR_RIGHT_Y = 0.29
SCENE_FAR_LEFT_Y = -0.3
DRAWER_Z = (0.06, 0.08)
MAX_ATTEMPTS = 20


@functools.cache
def collection_env(env_id: str) -> gymnasium.Env:
    """One data-collection env per id, reused: every episode starts with a seeded reset, which
    redraws everything an episode depends on. No time limit: episodes run as long as asked."""
    return make_manipspace_env(
        env_id, mode="data_collection", terminate_at_goal=False, max_episode_steps=10**9
    )


def subtask_kinds(spec: ManipSpaceSpec) -> tuple[str, ...]:
    """The subtask kinds (`SUBTASKS`) the env's data collection draws: the cube envs' cube, the
    scene's four, a puzzle's button."""
    if spec.scene:
        return SUBTASKS
    return ("button",) if spec.grid is not None else ("cube",)


def default_p_random_action(spec: ManipSpaceSpec, recipe: str) -> float:
    """The script's `p_random_action` for `recipe` in this env (`commands.sh`)."""
    return (PUZZLE_P_RANDOM_ACTION if spec.grid is not None else P_RANDOM_ACTION)[recipe]


@functools.cache
def _oracles(
    env: gymnasium.Env,
    kinds: tuple[str, ...],
    recipe: str,
    noise: float,
    smoothing: float,
    min_norm: float,
) -> dict[str, Any]:
    """The script's oracles: one per subtask kind the env draws (one set per process and
    settings: each episode resets the ones it uses). A puzzle's button oracle keeps the gripper
    closed, as the script's puzzle branch makes it."""
    puzzle = kinds == ("button",)
    if recipe == "play":
        from ogbench.manipspace.oracles.plan.button_plan import ButtonPlanOracle
        from ogbench.manipspace.oracles.plan.cube_plan import CubePlanOracle
        from ogbench.manipspace.oracles.plan.drawer_plan import DrawerPlanOracle
        from ogbench.manipspace.oracles.plan.window_plan import WindowPlanOracle

        plans = {"cube": CubePlanOracle, "button": ButtonPlanOracle,
                 "drawer": DrawerPlanOracle, "window": WindowPlanOracle}  # fmt: skip
        if puzzle:
            return {"button": ButtonPlanOracle(env=env, noise=noise, noise_smoothing=smoothing,
                                               gripper_always_closed=True)}  # fmt: skip
        return {k: plans[k](env=env, noise=noise, noise_smoothing=smoothing) for k in kinds}
    from ogbench.manipspace.oracles.markov.button_markov import ButtonMarkovOracle
    from ogbench.manipspace.oracles.markov.cube_markov import CubeMarkovOracle
    from ogbench.manipspace.oracles.markov.drawer_markov import DrawerMarkovOracle
    from ogbench.manipspace.oracles.markov.window_markov import WindowMarkovOracle

    markovs = {"cube": CubeMarkovOracle, "button": ButtonMarkovOracle,
               "drawer": DrawerMarkovOracle, "window": WindowMarkovOracle}  # fmt: skip
    if puzzle:
        return {"button": ButtonMarkovOracle(env=env, min_norm=min_norm,
                                             gripper_always_closed=True)}  # fmt: skip
    oracles = {k: markovs[k](env=env, min_norm=min_norm) for k in kinds}
    if kinds == SUBTASKS:  # the scene, as the script (though the oracle's reset sets its step
        # limit back to 200)
        oracles["cube"] = CubeMarkovOracle(env=env, min_norm=min_norm, max_step=100)
    return oracles


def generate(*args: Any, **kwargs: Any) -> list[dict[str, Any]]:
    """`iter_generate`'s episodes as a list (the same arguments)."""
    return list(iter_generate(*args, **kwargs))


def iter_generate(
    env_id: str,
    recipe: str,
    episodes: int = 2,
    episode_steps: int = 200,
    seed: int = 0,
    noise: float = NOISE,
    noise_smoothing: float = NOISE_SMOOTHING,
    min_norm: float = MIN_NORM,
    p_random_action: float | None = None,
) -> Iterator[dict[str, Any]]:
    """`episodes` episodes of `episode_steps` steps of OGBench's `recipe` data (module docstring),
    one at a time as they are made; the arguments are checked when the first one is asked for.

    Args:
        env_id: `cube-single-v0`, `cube-double-v0`, `scene-v0` or a puzzle (`puzzle-3x3-v0`, ...).
        recipe: "play" (plan oracles, smoothed noise) or "noisy" (Markov oracles, Gaussian noise).
        episodes, episode_steps: The size (OGBench: 1000 x 1001, plus 100 validation episodes).
        seed: Everything drawn is a function of it.
        noise: Play: the plan noise level; noisy: the maximum of the per-episode `xi`.
        noise_smoothing: Play: the noise's smoothing (Gaussian filter sigma, steps).
        min_norm: Noisy: the Markov oracles' minimum relative-position norm.
        p_random_action: Probability of a uniform random action (default play 0, noisy 0.1;
            the puzzles' noisy 0.2).

    Yields:
        One dict per episode: `observations [T+1, S]`, `actions [T, 5]`, `physics [T+1, P]`
        (float64), `success [T]`, `subtask_done [T]` (bool), `subtask [T]` (int8 index into
        `SUBTASKS`), and `attempts` (scene episodes redone for leaving the table, plus 1),
        `p_stack`, `xi` (noisy; else 0).

    Raises:
        UserError: an unknown env id or recipe, or a size below 1.
    """
    check_sizes(env_id, recipe, episodes, episode_steps)
    for episode_seed in episode_seeds(seed, episodes):
        yield generate_episode(
            env_id, recipe, episode_steps, episode_seed, noise, noise_smoothing, min_norm,
            p_random_action,
        )  # fmt: skip


def check_sizes(env_id: str, recipe: str, episodes: int, episode_steps: int) -> None:
    """A one-line `UserError` for an unknown env id or recipe, or a size below 1."""
    check_manipspace_id(env_id)
    if recipe not in RECIPES:
        raise UserError(f"unknown manipulation recipe {recipe!r}; use one of: {', '.join(RECIPES)}")
    if episodes < 1 or episode_steps < 1:
        raise UserError(f"episodes ({episodes}) and episode_steps ({episode_steps}) must be >= 1")


def episode_seeds(seed: int, episodes: int) -> list[np.random.SeedSequence]:
    """The seeds of a dataset's episodes: episode k is a function of `seed` and k alone."""
    return np.random.SeedSequence(seed).spawn(episodes)


def generate_episode(
    env_id: str,
    recipe: str,
    episode_steps: int,
    episode_seed: np.random.SeedSequence,
    noise: float = NOISE,
    noise_smoothing: float = NOISE_SMOOTHING,
    min_norm: float = MIN_NORM,
    p_random_action: float | None = None,
) -> dict[str, Any]:
    """One episode of `generate` (its `episode_seeds` entry), in this process's collection env.

    An episode does not depend on the ones generated before it in the same env (each starts
    with a seeded reset and fresh oracle resets; tests/test_manip_pipeline.py), so a dataset can
    be generated in several processes."""
    spec = manipspace_spec(env_id)
    env = collection_env(env_id)
    p_random = (
        default_p_random_action(spec, recipe) if p_random_action is None else float(p_random_action)
    )
    agents = _oracles(env, subtask_kinds(spec), recipe, noise, noise_smoothing, min_norm)
    return _healthy_episode(env, spec, agents, recipe, episode_steps, episode_seed, noise, p_random)


def _healthy_episode(
    env: gymnasium.Env,
    spec: ManipSpaceSpec,
    agents: dict[str, Any],
    recipe: str,
    steps: int,
    seed: np.random.SeedSequence,
    noise: float,
    p_random: float,
) -> dict[str, Any]:
    """The first of the episode's attempts that keeps the scene's cube on the table (OGBench's
    health rule on the states before each step; the cube envs take the first)."""
    for attempt, attempt_seed in enumerate(seed.spawn(MAX_ATTEMPTS), start=1):
        numpy_seed, reset_seed = (int(s) for s in attempt_seed.generate_state(2))
        with global_seed(numpy_seed):
            ep = _episode(env, spec, agents, recipe, steps, reset_seed, noise, p_random)
        if not spec.scene or not leaves_table(spec.cube_positions(ep["physics"][:-1])):
            ep["attempts"] = attempt
            return ep
    raise RuntimeError(f"{spec.env_id}: {MAX_ATTEMPTS} episodes in a row left the table")


def _p_stack(env_id: str) -> float:
    if env_id == "cube-double-v0":
        return float(np.random.uniform(*DOUBLE_P_STACK))
    return 0.0 if env_id == "cube-single-v0" else SCENE_P_STACK


def _episode(
    env: gymnasium.Env,
    spec: ManipSpaceSpec,
    agents: dict[str, Any],
    recipe: str,
    steps: int,
    reset_seed: int,
    noise: float,
    p_random: float,
) -> dict[str, Any]:
    """One episode under the seeded global generator (the script's loop, recorded exactly)."""
    ob, info = env.reset(seed=reset_seed)
    p_stack = _p_stack(spec.env_id)
    xi = float(np.random.uniform(0, noise)) if recipe == "noisy" else 0.0
    kind = str(info["privileged/target_task"])
    agent = agents[kind]
    agent.reset(ob, info)

    scratch = mujoco.MjData(spec.model)
    observations = np.empty((steps + 1, spec.state_dim))
    physics = np.empty((steps + 1, spec.physics_dim))
    actions = np.empty((steps, spec.action_dim))
    success = np.zeros(steps, dtype=bool)
    done = np.zeros(steps, dtype=bool)
    subtask = np.zeros(steps, dtype=np.int8)

    def record(t: int, env_ob: np.ndarray, refreshed: bool) -> None:
        physics[t] = spec.state_of_env(env)
        spec.set_physics_state(scratch, physics[t])
        observations[t] = spec.observe(scratch)
        if not refreshed and not np.array_equal(observations[t], env_ob):
            raise RuntimeError(f"{spec.env_id}: observe(state) differs from the env's at step {t}")

    record(0, ob, refreshed=False)
    for t in range(steps):
        if np.random.rand() < p_random:
            action = np.random.uniform(-1.0, 1.0, spec.action_dim)
        else:
            action = np.array(agent.select_action(ob, info), dtype=np.float64)
            if recipe == "noisy":
                action = action + np.random.normal(0, xi * MARKOV_NOISE_SHAPE, action.shape)
        action = np.clip(action, -1, 1)
        ob, _, _, _, info = env.step(action)
        actions[t], success[t], subtask[t] = action, bool(info["success"]), SUBTASKS.index(kind)
        if agent.done:
            done[t] = True
            agent_ob, agent_info = env.unwrapped.set_new_target(p_stack=p_stack)
            kind = str(agent_info["privileged/target_task"])
            agent = agents[kind]
            agent.reset(agent_ob, agent_info)
        record(t + 1, ob, refreshed=done[t])
    return {
        "observations": observations,
        "actions": actions,
        "physics": physics,
        "success": success,
        "subtask_done": done,
        "subtask": subtask,
        "p_stack": p_stack,
        "xi": xi,
    }


def leaves_table(cubes: np.ndarray) -> bool:
    """OGBench's scene health rule on cube positions `[T, n, 3]` (module docstring): some cube
    off the visible table."""
    y, z = cubes[..., 1], cubes[..., 2]
    far_left = (y <= SCENE_FAR_LEFT_Y) & ((z < DRAWER_Z[0]) | (z > DRAWER_Z[1]))
    return bool((y >= SCENE_FAR_RIGHT_Y).any() or far_left.any())


def observed_buttons(spec: ManipSpaceSpec, observations: np.ndarray) -> np.ndarray:
    """`[T, n_buttons]` the button states observations `[T, state_dim]` show (the "on" dim of
    each one-hot; `[T, 0]` without buttons)."""
    base = PROPRIO_DIM + CUBE_DIM * spec.n_cubes
    return np.asarray(observations)[:, [base + BUTTON_DIM * b + 1 for b in range(spec.n_buttons)]]


def state_buttons(spec: ManipSpaceSpec, physics: np.ndarray) -> np.ndarray:
    """`[T, n_buttons]` the button states physics states `[T, physics_dim]` hold (their last
    `n_buttons` numbers, `ManipSpaceSpec.physics_state`)."""
    physics = np.asarray(physics)
    return physics[:, physics.shape[1] - spec.n_buttons :]


def out_of_bounds(cubes: np.ndarray) -> np.ndarray:
    """`[T]` bool per step of cube positions `[T, n, 3]`: some cube beyond OGBench's workspace
    bounds +- 0.2 m (the scene env's own test for a cube thrown out by an instability)."""
    low, high = WORKSPACE_BOUNDS[0] - HEALTHY_MARGIN, WORKSPACE_BOUNDS[1] + HEALTHY_MARGIN
    return ((cubes <= low) | (cubes >= high)).any(axis=(-1, -2))


def check(episodes: list[dict[str, Any]], spec: ManipSpaceSpec) -> dict[str, Any]:
    """What `generate`'s episodes hold, and whether they are sound.

    Counts per episode and in all: subtasks the oracle finished (`subtask_done`), those it
    finished with the subtask achieved (`success` at that step), per kind and per 1000 steps.
    Problems (each makes `ok` False): arrays of the wrong shapes; a cube out of bounds
    (`out_of_bounds`) in a recorded state or observation; an observation whose cube positions
    are not its state's (`(xyz - [0.425, 0, 0]) * 10`), or whose button states (the scene's, a
    puzzle's) are not its state's; for the scene, a cube off the table (OGBench's health rule,
    `generate` redoes such episodes).

    Returns:
        `{"ok", "problems": [str], "episodes", "steps", "finished", "succeeded",
        "finished_per_1000_steps", "succeeded_per_1000_steps", "by_subtask": {kind: {"finished",
        "succeeded"}}, "per_episode": [{"steps", "finished", "succeeded", "out_of_bounds_steps"}]}`.
    """
    problems: list[str] = []
    per_episode = []
    by_subtask = {k: {"finished": 0, "succeeded": 0} for k in SUBTASKS}
    cube_cols = [PROPRIO_DIM + CUBE_DIM * i + k for i in range(spec.n_cubes) for k in range(3)]
    drawn = subtask_kinds(spec)
    for e, ep in enumerate(episodes):
        obs, physics, actions = ep["observations"], ep["physics"], ep["actions"]
        steps = len(actions)
        expected = {
            "observations": (steps + 1, spec.state_dim),
            "physics": (steps + 1, spec.physics_dim),
            "actions": (steps, spec.action_dim),
            "success": (steps,),
            "subtask_done": (steps,),
            "subtask": (steps,),
        }
        wrong = [k for k, shape in expected.items() if np.shape(ep[k]) != shape]
        if wrong:
            problems.append(f"episode {e}: wrong shapes of {', '.join(wrong)}")
            per_episode.append({"steps": steps, "finished": 0, "succeeded": 0,
                                "out_of_bounds_steps": 0})  # fmt: skip
            continue
        cubes = spec.cube_positions(physics)
        observed = XYZ_CENTER + obs[:, cube_cols].reshape(steps + 1, spec.n_cubes, 3) / XYZ_SCALE
        outside = out_of_bounds(cubes) | out_of_bounds(observed)
        if outside.any():
            problems.append(
                f"episode {e}: a cube is out of the workspace bounds at {int(outside.sum())} "
                f"steps, first at step {int(np.argmax(outside))}"
            )
        if not np.array_equal(obs[:, cube_cols], ((cubes - XYZ_CENTER) * XYZ_SCALE).reshape(
                steps + 1, 3 * spec.n_cubes)):  # fmt: skip
            problems.append(f"episode {e}: observed cube positions differ from the states'")
        if not np.array_equal(observed_buttons(spec, obs), state_buttons(spec, physics)):
            problems.append(f"episode {e}: observed button states differ from the states'")
        if spec.scene and leaves_table(cubes):
            problems.append(f"episode {e}: the cube leaves the table (OGBench's health rule)")
        if np.abs(actions).max(initial=0.0) > 1.0:
            problems.append(f"episode {e}: actions outside [-1, 1]")
        done, success, kinds = ep["subtask_done"], ep["success"], ep["subtask"]
        for k, name in enumerate(SUBTASKS):
            of_kind = done & (kinds == k)
            by_subtask[name]["finished"] += int(of_kind.sum())
            by_subtask[name]["succeeded"] += int((of_kind & success).sum())
        per_episode.append({
            "steps": steps,
            "finished": int(done.sum()),
            "succeeded": int((done & success).sum()),
            "out_of_bounds_steps": int(outside.sum()),
        })  # fmt: skip
    steps = sum(p["steps"] for p in per_episode)
    finished = sum(p["finished"] for p in per_episode)
    succeeded = sum(p["succeeded"] for p in per_episode)
    per_1000 = 1000.0 / steps if steps else 0.0
    return {
        "ok": not problems,
        "problems": problems,
        "episodes": len(episodes),
        "steps": steps,
        "finished": finished,
        "succeeded": succeeded,
        "finished_per_1000_steps": finished * per_1000,
        "succeeded_per_1000_steps": succeeded * per_1000,
        "by_subtask": {k: v for k, v in by_subtask.items() if k in drawn},
        "per_episode": per_episode,
    }
