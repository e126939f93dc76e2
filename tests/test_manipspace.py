"""OGBench manipulation (cube-single, cube-double, scene, the puzzles): the spec against the real
gymnasium env, bit for bit; tasks and success; the play / noisy generator and its check. Real
physics, no mocks."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from pipeline.envs.manipspace.data import (
    SUBTASKS,
    check,
    collection_env,
    default_p_random_action,
    generate,
)
from pipeline.envs.manipspace.env import (
    MANIPSPACE_ENVS,
    READINGS,
    ManipSpaceSpec,
    evaluation_env,
    is_manipspace,
    manipspace_spec,
    puzzle_toggles,
)
from pipeline.envs.manipspace.solver import Subtask, oracle_info
from pipeline.envs.physics import PHYSICS_SPEC
from pipeline.errors import UserError


@pytest.fixture(scope="module", params=MANIPSPACE_ENVS)
def spec(request: pytest.FixtureRequest) -> ManipSpaceSpec:
    return manipspace_spec(request.param)


@pytest.fixture(scope="module")
def scene_play() -> list[dict]:
    """One 300-step scene play episode: it moves the cube three times and presses a button."""
    return generate("scene-v0", "play", episodes=1, episode_steps=300, seed=0)


def _random_state(spec: ManipSpaceSpec, seed: int):
    """The data-collection env after a seeded reset and 10 random steps, and its RNG."""
    env = collection_env(spec.env_id)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(10):
        env.step(rng.uniform(-1, 1, spec.action_dim))
    return env, rng


def test_sizes_and_ids(spec: ManipSpaceSpec) -> None:
    n_cubes, state_dim, limit = {
        "cube-single-v0": (1, 28, 200),
        "cube-double-v0": (2, 37, 500),
        "scene-v0": (1, 40, 750),
        "puzzle-3x3-v0": (0, 19 + 4 * 9, 500),  # OGBench's registered max_episode_steps
        "puzzle-4x4-v0": (0, 19 + 4 * 16, 500),
        "puzzle-4x5-v0": (0, 19 + 4 * 20, 1000),
        "puzzle-4x6-v0": (0, 19 + 4 * 24, 1000),
    }[spec.env_id]
    model = spec.model
    puzzle = 0 if spec.grid is None else spec.grid[0] * spec.grid[1]  # its buttons
    assert spec.n_buttons == (2 if spec.scene else puzzle)
    extra = READINGS + (2 if spec.scene else 0) + puzzle
    full = mujoco.mj_stateSize(model, PHYSICS_SPEC)
    assert full == 1 + model.nq + model.nv
    assert spec.physics_dim == full + model.nv + extra  # + warm start + user data
    assert (spec.n_cubes, spec.state_dim, spec.action_dim) == (n_cubes, state_dim, 5)
    assert (spec.dt, spec.max_episode_steps) == (0.05, limit)
    assert len(spec.goal_dims) == 3 * n_cubes + (4 if spec.scene else 0) + puzzle
    assert is_manipspace(spec.env_id) and not is_manipspace("pointmaze-medium-v0")
    with pytest.raises(UserError, match="not a full state"):
        spec.set_observation(mujoco.MjData(model), np.zeros(spec.state_dim))


def test_physics_state_round_trip(spec: ManipSpaceSpec) -> None:
    """A state taken from the env, restored into fresh data: the env's observation bit for bit."""
    env, _ = _random_state(spec, seed=1)
    ob, *_ = env.step(np.zeros(5))
    state = spec.state_of_env(env)
    data = mujoco.MjData(spec.model)
    spec.set_physics_state(data, state)
    assert np.array_equal(spec.observe(data), ob)
    assert np.array_equal(spec.physics_state(data), state)
    if spec.n_cubes:
        assert np.array_equal(spec.cube_positions(state)[0], data.qpos[14:17])
    assert np.array_equal(
        spec.button_states(data), getattr(env.unwrapped, "_cur_button_states", [])
    )


def test_control_step_is_the_env_step_bit_for_bit(spec: ManipSpaceSpec) -> None:
    """From a random state, random actions (some out of [-1, 1], one float32) give the env's
    observation and exact state after every step. Another slot's scene locks, left in the shared
    model, do not leak in (`control_step` rewrites them)."""
    env, rng = _random_state(spec, seed=2)
    data = mujoco.MjData(spec.model)
    spec.set_physics_state(data, spec.state_of_env(env))
    actions = [rng.uniform(-1.5, 1.5, 5) for _ in range(5)] + [rng.uniform(-1, 1, 5).astype("f4")]
    for action in actions:
        ob, *_ = env.step(np.clip(action, -1, 1))  # OGBench's evaluation clip
        if spec.scene:
            locks = [spec._ids["drawer_dof"], spec._ids["window_dof"]]
            spec.model.dof_damping[locks] = rng.choice([2.0, 1e6], 2)
        spec.control_step(spec.model, data, action)
        assert np.array_equal(spec.observe(data), ob)
        assert np.array_equal(spec.physics_state(data), spec.state_of_env(env))


def test_tasks_load_with_their_goals(spec: ManipSpaceSpec) -> None:
    """OGBench's five tasks; each start is exact, its goal is the task's (permuted), reached by
    the goal observation and not by the start."""
    tasks = spec.tasks()
    assert [t.task_id for t in tasks] == [1, 2, 3, 4, 5]
    assert all(t.name.split("_")[0] == f"task{t.task_id}" for t in tasks)
    data = mujoco.MjData(spec.model)
    for task in tasks:
        assert task.goal.block_xyzs.shape == task.init.block_xyzs.shape == (spec.n_cubes, 3)
        start = spec.task_start(task.task_id, seed=task.task_id)
        spec.set_physics_state(data, start.physics)
        assert np.array_equal(spec.observe(data), start.observation)
        rows = sorted(map(tuple, start.goal.block_xyzs))
        assert rows == sorted(map(tuple, task.goal.block_xyzs))
        if spec.scene:
            assert np.array_equal(start.goal.button_states, task.goal.button_states)
            assert (start.goal.drawer_pos, start.goal.window_pos) == (
                task.goal.drawer_pos, task.goal.window_pos)  # fmt: skip
            assert np.array_equal(spec.button_states(data), task.init.button_states)
        if spec.grid is not None:  # the buttons exactly the task's, the goal its goal states
            assert np.array_equal(spec.button_states(data), task.init.button_states)
            assert np.array_equal(start.goal.button_states, task.goal.button_states)
        goal = spec.goal_vector(start.goal)
        assert goal.shape == (len(spec.goal_dims),)
        assert spec.goal_reached(start.goal_observation, goal)
        assert not spec.goal_reached(start.observation, goal)
        assert not spec.success(data, start.goal)


def test_success_agrees_with_the_env(spec: ManipSpaceSpec) -> None:
    """`success` (and `goal_reached` on observations) is the env's `info['success']`, on a task
    start (not done) and with every object put at its goal (done)."""
    env = evaluation_env(spec.env_id)
    start = spec.task_start(1, seed=0)
    u = env.unwrapped
    data = mujoco.MjData(spec.model)
    goal = spec.goal_vector(start.goal)
    for done in (False, True):
        if done:
            qpos, qvel = u.data.qpos.copy(), np.zeros(spec.model.nv)
            for adr, xyz in zip(spec._ids["cube_qpos"], start.goal.block_xyzs, strict=True):
                qpos[adr : adr + 7] = [*xyz, 1, 0, 0, 0]
            if spec.scene:
                qpos[spec._ids["drawer_qpos"]] = start.goal.drawer_pos
                qpos[spec._ids["window_qpos"]] = start.goal.window_pos
                u.set_state(qpos, qvel, start.goal.button_states.copy())
            elif spec.grid is not None:
                u.set_state(qpos, qvel, start.goal.button_states.copy())
            else:
                u.set_state(qpos, qvel)
        ob, _, _, _, info = env.step(np.zeros(5))
        spec.set_physics_state(data, spec.state_of_env(env))
        assert info["success"] == done
        assert spec.success(data, start.goal) == done
        assert bool(spec.goal_reached(ob, goal)) == done


@pytest.mark.parametrize("recipe", ["play", "noisy"])
def test_generate_is_deterministic_for_a_seed(recipe: str) -> None:
    first = generate("cube-single-v0", recipe, episodes=2, episode_steps=30, seed=3)
    again = generate("cube-single-v0", recipe, episodes=2, episode_steps=30, seed=3)
    other = generate("cube-single-v0", recipe, episodes=2, episode_steps=30, seed=4)
    for a, b, c in zip(first, again, other, strict=True):
        for key in ("observations", "actions", "physics", "success", "subtask_done"):
            assert np.array_equal(a[key], b[key]), key
        assert not np.array_equal(a["actions"], c["actions"])
        assert a["observations"].shape == (31, 28) and a["physics"].shape == (31, 80)
    assert not np.array_equal(first[0]["actions"], first[1]["actions"])


def test_check_finds_the_oracle_completing_subtasks(scene_play: list[dict]) -> None:
    spec = manipspace_spec("scene-v0")
    report = check(scene_play, spec)
    assert report["ok"], report["problems"]
    assert report["succeeded"] >= 3 and report["finished"] >= report["succeeded"]
    assert report["by_subtask"]["cube"]["succeeded"] >= 1
    assert report["by_subtask"]["button"]["succeeded"] >= 1
    assert report["succeeded_per_1000_steps"] == pytest.approx(report["succeeded"] * 1000 / 300)
    assert set(report["by_subtask"]) == set(SUBTASKS)


def _replay_exactly(spec: ManipSpaceSpec, ep: dict) -> None:
    """Every recorded state and observation, from the first state and the actions alone."""
    data = mujoco.MjData(spec.model)
    spec.set_physics_state(data, ep["physics"][0])
    for t, action in enumerate(ep["actions"]):
        spec.control_step(spec.model, data, action)
        assert np.array_equal(spec.physics_state(data), ep["physics"][t + 1]), t
        assert np.array_equal(spec.observe(data), ep["observations"][t + 1]), t


def test_replaying_a_scene_episode_through_control_step_is_exact(scene_play: list[dict]) -> None:
    """The episode presses a button (a toggle and a drawer unlock), grasps and moves the cube."""
    ep = scene_play[0]
    buttons = ep["physics"][:, -2:]
    assert (buttons != buttons[0]).any()  # a button toggled
    _replay_exactly(manipspace_spec("scene-v0"), ep)


def test_replaying_a_cube_episode_across_a_subtask_switch_is_exact() -> None:
    """The recorded observation after a switch is the refreshed one the next step acts from."""
    ep = generate("cube-double-v0", "play", episodes=1, episode_steps=100, seed=0)[0]
    assert ep["subtask_done"].any()
    _replay_exactly(manipspace_spec("cube-double-v0"), ep)


def test_check_fails_an_episode_with_a_cube_out_of_the_workspace(scene_play: list[dict]) -> None:
    spec = manipspace_spec("scene-v0")
    ep = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in scene_play[0].items()}
    x_state = 1 + spec._ids["cube_qpos"][0]  # time, then qpos
    ep["physics"][100:110, x_state] = 2.0  # teleported 1.4 m beyond the workspace
    ep["observations"][100:110, 19] = (2.0 - 0.425) * 10
    report = check([scene_play[0], ep], spec)
    assert not report["ok"]
    assert len(report["problems"]) == 1 and report["problems"][0].startswith("episode 1:")
    assert "out of the workspace" in report["problems"][0]
    assert report["per_episode"][1]["out_of_bounds_steps"] == 10


def test_bad_input() -> None:
    with pytest.raises(UserError, match="unknown manipulation recipe"):
        generate("cube-single-v0", "expert")
    with pytest.raises(UserError, match="unsupported OGBench manipulation env"):
        generate("puzzle-5x5-v0", "play")
    with pytest.raises(UserError, match="unsupported OGBench manipulation env"):
        ManipSpaceSpec.create("cube-triple-v0")


# --- the puzzles ("Lights Out") -----------------------------------------------------------------


def test_a_puzzle_press_toggles_the_button_and_its_grid_neighbours():
    assert puzzle_toggles(3, 3)[4] == [4, 7, 1, 5, 3]  # the centre: itself and 4 neighbours
    assert sorted(puzzle_toggles(3, 3)[0]) == [0, 1, 3]  # a corner: 2 neighbours
    assert sorted(puzzle_toggles(4, 6)[6]) == [0, 6, 7, 12]  # row 1, column 0: an edge
    spec = manipspace_spec("puzzle-4x4-v0")
    assert spec.grid == (4, 4) and spec._ids["toggles"] == puzzle_toggles(4, 4)


def test_pressing_puzzle_buttons_steps_bit_for_bit_with_the_env():
    """From an evaluation start of puzzle-3x3 task 1 (all off), OGBench's button plan oracle
    presses the centre button and then a corner; `control_step` follows the env step for step
    (observation and exact state), and the presses flip 5 buttons, then 3."""
    from ogbench.manipspace.oracles.plan.button_plan import ButtonPlanOracle

    spec = manipspace_spec("puzzle-3x3-v0")
    env = evaluation_env(spec.env_id)
    ob, info = env.reset(seed=7, options={"task_id": 1})
    data = mujoco.MjData(spec.model)
    spec.set_physics_state(data, spec.state_of_env(env))
    oracle = ButtonPlanOracle(env=env, noise=0.0, gripper_always_closed=True)
    flips = []
    assert spec.button_states(data).tolist() == [0] * 9
    for button in (4, 0):
        sub = Subtask("button", button)
        sub_info = oracle_info(env, info, sub)
        oracle.reset(ob, sub_info)
        while not oracle.done:
            before = spec.button_states(data)
            action = oracle.select_action(ob, sub_info)
            ob, _, _, _, info = env.step(action)
            spec.control_step(spec.model, data, action)
            assert np.array_equal(spec.observe(data), ob)
            assert np.array_equal(spec.physics_state(data), spec.state_of_env(env))
            if (changed := np.flatnonzero(spec.button_states(data) != before)).size:
                flips.append(sorted(changed.tolist()))
            sub_info = oracle_info(env, info, sub)
    assert flips == [[1, 3, 4, 5, 7], [0, 1, 3]]
    assert spec.button_states(data).tolist() == [1, 0, 0, 0, 1, 1, 0, 1, 0]


@pytest.mark.parametrize("recipe", ["play", "noisy"])
def test_puzzle_data_is_deterministic_and_replays_exactly(recipe: str) -> None:
    """OGBench's puzzle recipe: the button oracle presses random target buttons (each press
    flipping its neighbours too); the same seed makes the same episode, which replays through
    `control_step` bit for bit."""
    spec = manipspace_spec("puzzle-4x4-v0")
    first = generate(spec.env_id, recipe, episodes=1, episode_steps=120, seed=5)[0]
    again = generate(spec.env_id, recipe, episodes=1, episode_steps=120, seed=5)[0]
    for key in ("observations", "actions", "physics", "success", "subtask_done"):
        assert np.array_equal(first[key], again[key]), key
    report = check([first], spec)
    assert report["ok"], report["problems"]
    assert set(report["by_subtask"]) == {"button"}
    assert set(first["subtask"].tolist()) == {SUBTASKS.index("button")}
    buttons = first["physics"][:, -16:]
    flipped = np.abs(np.diff(buttons, axis=0)).sum(axis=1)
    if recipe == "play":  # the plan oracle presses a button every ~1.5 s
        assert report["succeeded"] >= 2 and (flipped >= 2).sum() >= 2
    _replay_exactly(spec, first)
    assert default_p_random_action(spec, "noisy") == 0.2  # the puzzles' commands.sh lines
    assert default_p_random_action(manipspace_spec("scene-v0"), "noisy") == 0.1


def test_check_fails_a_puzzle_episode_whose_observations_show_other_button_states() -> None:
    spec = manipspace_spec("puzzle-3x3-v0")
    ep = generate(spec.env_id, "play", episodes=1, episode_steps=20, seed=1)[0]
    assert check([ep], spec)["ok"]
    ep["observations"][5, 19:21] = ep["observations"][5, 19:21][::-1]  # button 0's one-hot flipped
    report = check([ep], spec)
    assert not report["ok"] and "observed button states differ" in report["problems"][0]
