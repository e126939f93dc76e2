"""OGBench's oracles on its evaluation tasks (`pipeline/envs/manipspace/solver.py`, `oposm
oracle`): the subtask order on hand-made states, real episodes in OGBench's env from the agents'
starts, and the stage's report as the manipulation report reads it; the puzzles' exact Lights Out
solver and its presses in OGBench's env."""

from __future__ import annotations

import numpy as np
import pytest
from factories import one_line_error

from pipeline.envs.manipspace.env import (
    EPISODE_STEPS,
    ObjectConfig,
    make_manipspace_env,
    manipspace_spec,
)
from pipeline.envs.manipspace.solver import (
    Subtask,
    episode_seeds,
    in_drawer_goal,
    lights_out_presses,
    next_subtask,
    run_episode,
    run_puzzle_episode,
    toggle_matrix,
)
from pipeline.evaluation.tasks import manipulation_episodes

AXIS = np.array([0.0, -1.0, 0.0])  # the scene's drawer opens toward +y (joint positions < 0)
IN_DRAWER = np.array([[0.33, -0.356, 0.066]])  # scene task 4's cube goal (drawer closed)


def _info(cubes, buttons=(0, 0), drawer=0.0, window=0.0) -> dict:
    info = {f"privileged/block_{i}_pos": np.array(c, dtype=float) for i, c in enumerate(cubes)}
    info |= {f"privileged/button_{b}_state": s for b, s in enumerate(buttons)}
    return info | {"privileged/drawer_pos": np.array([drawer]),
                   "privileged/window_pos": np.array([window])}  # fmt: skip


def _scene_goal(cube, buttons=(1, 0), drawer=0.0, window=0.0) -> ObjectConfig:
    return ObjectConfig(np.array(cube, dtype=float), np.array(buttons), drawer, window)


def test_a_cube_goes_into_the_drawer_after_unlocking_and_opening_it_then_it_closes():
    goal = _scene_goal(IN_DRAWER)
    steps = [
        (_info([[0.35, 0.05, 0.02]]), Subtask("button", 0, 1)),
        (_info([[0.35, 0.05, 0.02]], buttons=(1, 0)), Subtask("drawer")),
    ]
    for info, expected in steps:
        assert next_subtask(info, goal, True, AXIS) == expected
    opened = _info([[0.35, 0.05, 0.02]], buttons=(1, 0), drawer=-0.16)
    sub = next_subtask(opened, goal, True, AXIS)
    assert sub.kind == "cube" and np.allclose(sub.target, IN_DRAWER[0] + [0, 0.16, 0])
    placed = _info([in_drawer_goal(goal, 0, -0.16, AXIS)], buttons=(1, 0), drawer=-0.16)
    assert next_subtask(placed, goal, True, AXIS) == Subtask("drawer", 0, 0.0)
    closed = _info(IN_DRAWER, buttons=(1, 0))
    assert next_subtask(closed, goal, True, AXIS) is None


def test_the_window_is_unlocked_before_it_moves_and_buttons_are_set_last():
    goal = _scene_goal([[0.4, 0.15, 0.02]], buttons=(0, 0), window=0.2)
    at = [[0.4, 0.15, 0.02]]
    assert next_subtask(_info(at), goal, True, AXIS) == Subtask("button", 1, 1)
    assert next_subtask(_info(at, (0, 1)), goal, True, AXIS) == Subtask("window", 0, 0.2)
    done = _info(at, (0, 1), window=0.2)
    assert next_subtask(done, goal, True, AXIS) == Subtask("button", 1, 0)


def test_a_stack_is_built_from_its_base_and_a_swap_sets_one_cube_aside():
    stack = ObjectConfig(np.array([[0.425, 0.0, 0.02], [0.425, 0.0, 0.06]]))
    apart = [[0.425, -0.2, 0.02], [0.425, 0.2, 0.02]]
    for order in (apart, apart[::-1]):  # the base first, whichever cube is listed first
        sub = next_subtask(_info(order), stack, False)
        assert sub == Subtask("cube", 0, sub.target) and np.allclose(sub.target, [0.425, 0, 0.02])
    swap = ObjectConfig(np.array([[0.425, 0.1, 0.02], [0.425, -0.1, 0.02]]))
    sub = next_subtask(_info([[0.425, -0.1, 0.02], [0.425, 0.1, 0.02]]), swap, False)
    assert sub.kind == "cube" and np.linalg.norm(sub.target[:2] - [0.425, 0.1]) > 0.1
    assert np.linalg.norm(sub.target[:2] - [0.425, -0.1]) > 0.1  # neither cube's place


def test_the_oracle_starts_where_the_agents_start_and_solves_cube_single():
    spec = manipspace_spec("cube-single-v0")
    env = make_manipspace_env(spec.env_id, max_episode_steps=EPISODE_STEPS[spec.env_id])
    starts = manipulation_episodes(spec, ["ogbench"], 2, seed=3)
    for task_id in (1, 4):
        for k in range(2):
            episode_seed, reset_seed = episode_seeds(3, task_id, k)
            observation, _ = env.reset(seed=reset_seed, options={"task_id": task_id})
            expected = starts[f"ogbench-task{task_id}"][k]
            assert episode_seed == expected.seed
            assert np.array_equal(observation, expected.start)
            episode = run_episode(env, task_id, reset_seed, episode_seed, scene=False)
            assert episode.success and 40 < episode.steps < 120 and episode.subtasks == 1


@pytest.mark.slow
def test_the_oracle_puts_the_scene_cube_in_the_drawer():
    env = make_manipspace_env("scene-v0", max_episode_steps=EPISODE_STEPS["scene-v0"])
    episode = run_episode(env, 4, reset_seed=5, seed=5, scene=True)  # task4_put_in_drawer
    assert episode.success and episode.subtasks >= 4  # button, drawer, cube, drawer


# --- the puzzles ("Lights Out") ------------------------------------------------------------------


def _all_presses(n: int) -> np.ndarray:
    """`[2^n, n]` every set of presses of n buttons."""
    return (np.arange(2**n)[:, None] >> np.arange(n) & 1).astype(np.int64)


@pytest.mark.parametrize("env_id", ["puzzle-3x3-v0", "puzzle-4x4-v0"])
def test_the_presses_solve_each_task_exactly_and_are_the_fewest(env_id):
    """Over GF(2), against every one of the 2^n press sets: the presses turn each task's init
    states into its goal states, and no other set that does so is smaller (4x4 has 16 that do)."""
    spec = manipspace_spec(env_id)
    matrix = toggle_matrix(*spec.grid).astype(np.int64)
    every = _all_presses(spec.n_buttons)
    for task in spec.tasks():
        init, goal = task.init.button_states, task.goal.button_states
        presses = lights_out_presses(spec.grid, init, goal).astype(np.int64)
        assert np.array_equal((init + matrix @ presses) % 2, goal), task.name
        solving = every[((init + every @ matrix.T) % 2 == goal).all(axis=1)]
        assert len(solving) == (1 if env_id == "puzzle-3x3-v0" else 16)
        assert presses.sum() == solving.sum(axis=1).min(), task.name


def test_an_unreachable_puzzle_goal_is_a_one_line_error():
    """4x4 Lights Out is singular: one light on from all off cannot be reached."""
    goal = np.zeros(16, dtype=np.int64)
    goal[5] = 1
    message = one_line_error(lambda: lights_out_presses((4, 4), np.zeros(16), goal))
    assert "no button presses turn the 4x4 puzzle's states" in message
    assert lights_out_presses((3, 3), np.zeros(9), np.eye(9, dtype=int)[5]).sum() > 0


def test_the_oracle_solves_every_puzzle_3x3_task_from_the_agents_starts():
    """OGBench's button plan oracle, pressing the buttons the solver picks, reaches OGBench's
    success on all five tasks of puzzle-3x3 within its 500 steps, from the starts of the agents'
    episodes (measured: 46 to 269 steps, 2 to 9 presses)."""
    spec = manipspace_spec("puzzle-3x3-v0")
    env = make_manipspace_env(spec.env_id, max_episode_steps=EPISODE_STEPS[spec.env_id])
    starts = manipulation_episodes(spec, ["ogbench"], 1, seed=0)
    for task in spec.tasks():
        episode_seed, reset_seed = episode_seeds(0, task.task_id, 0)
        observation, _ = env.reset(seed=reset_seed, options={"task_id": task.task_id})
        assert np.array_equal(observation, starts[f"ogbench-task{task.task_id}"][0].start)
        episode = run_puzzle_episode(env, task.task_id, reset_seed, episode_seed)
        presses = lights_out_presses(spec.grid, task.init.button_states, task.goal.button_states)
        assert episode.success, task.name
        assert episode.steps < EPISODE_STEPS[spec.env_id] and episode.subtasks == presses.sum()
