"""Tests for pipeline/envs: PointMaze helpers, the scripted expert, generation and checks."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from pipeline.dataset import Episode
from pipeline.envs.maze.checks import check_maze_dataset, raise_for_problems
from pipeline.envs.maze.env import (
    SUPPORTED_ENVS,
    cell_to_xy,
    free_cells,
    get_physics_state,
    make_maze_env,
    max_episode_steps,
    maze_layout,
    maze_of,
    set_physics_state,
    xy_to_cell,
)
from pipeline.envs.maze.expert import ExpertConfig
from pipeline.envs.maze.generate import dataset_info, generate_episodes
from pipeline.errors import UserError

ENV_ID = "PointMaze_Medium-v3"
SEED = 7
N_EPISODES = 5
EPISODE_STEPS = 1000

# Restoring `mjSTATE_FULLPHYSICS` loses the constraint solver's warm start, so on steps where the
# ball presses on a wall the solver converges from another starting point and the next state
# differs at round-off (measured: up to 2.2e-14 m or m/s). 1e-12 is ~50x that and 1e9x below any
# physical effect; steps without wall contact match exactly.
RESTORE_ATOL = 1e-12

# Two cells joined by one corridor: the smallest maze the expert can shuttle in.
TINY_MAP = [
    [1, 1, 1, 1],
    [1, 0, 0, 1],
    [1, 1, 1, 1],
]


@pytest.fixture(scope="module")
def episodes() -> list[Episode]:
    """5 x 1000 steps of the default (noisy, D4RL-like) expert in Medium."""
    return list(generate_episodes(ENV_ID, N_EPISODES, EPISODE_STEPS, SEED, ExpertConfig(), False))


@pytest.fixture(scope="module")
def info():
    return dataset_info(ENV_ID, "test", SEED, ExpertConfig(), N_EPISODES, EPISODE_STEPS)


def _fresh_env():
    env = make_maze_env(ENV_ID, max_episode_steps=10**9)
    env.reset(seed=123)  # a different start: everything must come from the restored state
    return env


def test_bad_env_id_is_a_user_error() -> None:
    with pytest.raises(UserError, match="PointMaze_Medium-v3"):
        make_maze_env("PointMaze_Huge-v3")
    with pytest.raises(UserError, match="unsupported"):
        generate_episodes("AntMaze_Medium-v4", 1, 10, 0, ExpertConfig())
    with pytest.raises(UserError):
        max_episode_steps("maze2d-medium-v1")


def test_bad_params_are_user_errors() -> None:
    with pytest.raises(UserError, match="action_noise"):
        ExpertConfig(action_noise=-1.0)
    with pytest.raises(UserError, match="goal_radius"):
        ExpertConfig(goal_radius=0.0)
    with pytest.raises(UserError, match="episode_steps"):
        generate_episodes(ENV_ID, 1, 0, 0, ExpertConfig())
    with pytest.raises(UserError, match="maze_map"):
        make_maze_env(ENV_ID, maze_map=[[1, 1], [1]])


def test_supported_envs_and_layout() -> None:
    assert SUPPORTED_ENVS == {
        "PointMaze_UMaze-v3": 300,
        "PointMaze_Medium-v3": 600,
        "PointMaze_Large-v3": 800,
    }
    env = make_maze_env(ENV_ID)
    maze = maze_of(env)
    cells = free_cells(maze)
    assert len(cells) == 26
    for cell in cells:
        assert xy_to_cell(maze, cell_to_xy(maze, cell) + 0.3) == cell
    layout = maze_layout(env)
    assert json.loads(json.dumps(layout)) == layout
    assert layout["maze_map"][1][1] == 0 and layout["bounds"] == [-4.0, 4.0, -4.0, 4.0]
    # The layout is enough to rebuild the same maze.
    rebuilt = maze_layout(make_maze_env(ENV_ID, maze_map=layout["maze_map"]))
    assert rebuilt == layout


def test_episode_shapes_and_info(episodes: list[Episode], info) -> None:
    assert [ep.index for ep in episodes] == list(range(N_EPISODES))
    for ep in episodes:
        assert len(ep) == EPISODE_STEPS
        assert ep.observations.shape == (EPISODE_STEPS, 4)
        assert ep.actions.shape == (EPISODE_STEPS, 2)
        assert ep.physics.shape == (EPISODE_STEPS, info.physics_dim) == (EPISODE_STEPS, 5)
        assert ep.goals.shape == (EPISODE_STEPS, info.goal_dim) == (EPISODE_STEPS, 2)
        assert ep.goal_reached.dtype == bool and ep.rewards is None and ep.terminals is None
        assert np.abs(ep.actions).max() <= 1.0
    assert info.control_period == 0.01 and info.state_dim == 4 and info.action_dim == 2
    assert info.env_kwargs["maze_map"] == maze_layout(make_maze_env(ENV_ID))["maze_map"]
    assert info.generator["expert"] == dataclasses.asdict(ExpertConfig())
    assert set(info.versions) == {"gymnasium", "gymnasium_robotics", "mujoco", "numpy"}
    json.dumps(dataclasses.asdict(info))


def test_generator_dynamics_are_gymnasiums(episodes: list[Episode]) -> None:
    """Replaying the recorded actions through the wrapped gymnasium env gives the same states,
    bit for bit: the generator's fast stepping is exactly `PointMazeEnv.step`."""
    env = make_maze_env(ENV_ID, max_episode_steps=10**9)
    obs, _ = env.reset(seed=SEED)
    states = np.concatenate([ep.observations for ep in episodes])
    actions = np.concatenate([ep.actions for ep in episodes])
    replay = [obs["observation"]]
    for action in actions[:-1]:
        replay.append(env.step(action)[0]["observation"])
    np.testing.assert_array_equal(np.array(replay), states)


def test_restore_into_fresh_env_reproduces_next_state(episodes: list[Episode], info) -> None:
    env = _fresh_env()
    ep = episodes[1]
    errors = []
    for t in range(len(ep) - 1):
        set_physics_state(env, ep.physics[t])
        np.testing.assert_array_equal(get_physics_state(env), ep.physics[t])
        obs = env.step(ep.actions[t])[0]["observation"]
        errors.append(np.abs(obs - ep.observations[t + 1]).max())
    errors = np.array(errors)
    assert errors.max() <= RESTORE_ATOL
    # Only steps in contact with a wall may differ at all.
    report = check_maze_dataset([dataclasses.replace(ep, index=0)], info)
    assert report.min_wall_clearance < 0.01  # this episode does touch walls
    assert np.mean(errors == 0.0) > 0.8
    # A brand-new env per restore, for a few steps.
    for t in (0, 500, 998):
        env = _fresh_env()
        set_physics_state(env, ep.physics[t])
        obs = env.step(ep.actions[t])[0]["observation"]
        np.testing.assert_allclose(obs, ep.observations[t + 1], rtol=0, atol=RESTORE_ATOL)


def test_episodes_are_continuous(episodes: list[Episode]) -> None:
    env = _fresh_env()
    for prev, nxt in zip(episodes, episodes[1:], strict=False):
        set_physics_state(env, prev.physics[-1])
        obs = env.step(prev.actions[-1])[0]["observation"]
        np.testing.assert_allclose(obs, nxt.observations[0], rtol=0, atol=RESTORE_ATOL)
        assert nxt.time[0] == pytest.approx(prev.time[-1] + 0.01, abs=1e-12)
    time = np.concatenate([ep.time for ep in episodes])
    np.testing.assert_allclose(time, np.arange(len(time)) * 0.01, rtol=0, atol=1e-12)


def test_states_stay_in_free_cells(episodes: list[Episode], info) -> None:
    report = check_maze_dataset(episodes, info)
    assert report.problems == []
    assert report.n_outside_bounds == 0 and report.n_in_wall == 0 and report.n_nonfinite == 0
    # Velocity is clipped to 5 m/s per axis, so a step moves at most ~0.074 m.
    assert report.max_step_distance < 0.08
    # Soft contacts let the 0.1 m ball overlap a wall a little, never by its radius.
    assert report.min_wall_clearance > -0.075
    maze = maze_of(make_maze_env(ENV_ID))
    free = set(free_cells(maze))
    pos = np.concatenate([ep.observations[:, :2] for ep in episodes])
    assert all(xy_to_cell(maze, p) in free for p in pos[::7])


def test_expert_reaches_goals(episodes: list[Episode], info) -> None:
    report = check_maze_dataset(episodes, info)
    # Measured over 40 seeds, 5000 steps of Medium with noise 0.5: 33 +- 4 goals (6.6 per 1000
    # steps, min 26). 20 leaves room for other seeds and library versions while still catching
    # an expert that wanders or gets stuck (a broken one reaches 0-5).
    assert report.goals_reached >= 20
    assert report.goals_per_1000_steps >= 4.0
    # D4RL gives an evaluation episode 600 steps in Medium; the expert needs at most ~350.
    assert report.longest_goal_segment <= 600
    goals = np.concatenate([ep.goals for ep in episodes])
    reached = np.concatenate([ep.goal_reached for ep in episodes])
    pos = np.concatenate([ep.observations[:, :2] for ep in episodes])
    # goal_reached marks the step whose action brought the ball within goal_radius of its goal.
    t = np.flatnonzero(reached[:-1])
    assert np.all(np.linalg.norm(pos[t + 1] - goals[t], axis=1) <= 0.5)
    assert np.all(np.any(goals[t + 1] != goals[t], axis=1))


def test_determinism(episodes: list[Episode]) -> None:
    again = list(generate_episodes(ENV_ID, 2, EPISODE_STEPS, SEED, ExpertConfig(), False))
    other = list(generate_episodes(ENV_ID, 2, EPISODE_STEPS, SEED + 1, ExpertConfig(), False))
    for a, b, c in zip(episodes, again, other, strict=False):
        for name in ("observations", "actions", "time", "physics", "goals", "goal_reached"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert not np.array_equal(a.observations, c.observations)
        assert not np.array_equal(a.actions, c.actions)


def test_tiny_custom_maze() -> None:
    info = dataset_info(ENV_ID, "tiny", 0, ExpertConfig(), 2, 400, maze_map=TINY_MAP)
    eps = list(generate_episodes(ENV_ID, 2, 400, 0, ExpertConfig(), False, maze_map=TINY_MAP))
    assert info.env_kwargs == {"maze_map": TINY_MAP}
    report = check_maze_dataset(eps, info)
    assert report.problems == []
    # Two cells: the expert shuttles between them, reaching a goal every ~30-60 steps.
    assert report.goals_reached >= 8
    pos = np.concatenate([ep.observations[:, :2] for ep in eps])
    assert np.all(np.abs(pos[:, 1]) < 0.4) and np.all(np.abs(pos[:, 0]) < 0.9)


def test_checks_find_problems(episodes: list[Episode], info) -> None:
    bad = [dataclasses.replace(ep, observations=ep.observations.copy()) for ep in episodes[:2]]
    bad[0].observations[300, :2] += 0.6  # a teleport, and into a wall or another cell
    bad[1].observations[10, 0] = np.nan
    bad.append(dataclasses.replace(episodes[2], index=2, actions=episodes[2].actions[:-1]))
    report = check_maze_dataset(bad, info)
    text = " | ".join(report.problems)
    assert "jumps" in text and "NaN" in text and "shape" in text
    assert report.n_nonfinite == 1
    with pytest.raises(UserError, match="failed"):
        raise_for_problems(report, "bad")
    raise_for_problems(check_maze_dataset(episodes, info))  # a clean dataset passes
    # A wall position is caught even without a jump (a slow drift into the wall).
    walled = dataclasses.replace(episodes[0], observations=episodes[0].observations.copy())
    walled.observations[:, :2] = [-3.5, 3.5]  # centre of wall cell (0, 0)
    walled.physics = None
    report = check_maze_dataset([walled], dataclasses.replace(info, physics_dim=0))
    assert report.n_in_wall == EPISODE_STEPS
    assert any("inside a wall" in p for p in report.problems)


def test_batch_sim_runs_a_model_variant_per_slot() -> None:
    """Slots may run their own `MjModel` (e.g. twice the mass): same start and actions, the
    variant's slot moves half as far at first, the nominal slots stay identical."""
    import copy

    import mujoco

    from pipeline.envs.batch import BatchSim
    from pipeline.envs.spec import PointMazeSpec

    spec = PointMazeSpec.create("PointMaze_UMaze-v3")
    heavy = copy.copy(spec.model)
    heavy.body_mass[1] *= 2
    mujoco.mj_setConst(heavy, mujoco.MjData(heavy))  # MuJoCo 4 caches the constant mass matrix
    sim = BatchSim(spec, 3, models=[spec.model, heavy, spec.model])
    sim.reset(np.tile([0.0, 0.0, 0.0, 0.0], (3, 1)))
    for _ in range(5):
        assert sim.step(np.tile([0.5, 0.0], (3, 1))) == {}
    x = sim.observe()[:, 0]
    assert x[0] == x[2] and 0 < x[1] < 0.6 * x[0]
    with pytest.raises(ValueError, match="one model per slot"):
        BatchSim(spec, 2, models=[heavy])


def test_scale_mass_scales_every_body_and_leaves_the_nominal_model_alone():
    """`deploy.mass_scale` (paper fig. 5): mass and inertia x factor, the point moves as slowly
    as the factor says, the spec's model is untouched, and a non-positive factor is refused."""
    from pipeline.envs.batch import BatchSim
    from pipeline.envs.perturb import scale_mass
    from pipeline.envs.spec import PointMazeSpec
    from pipeline.errors import UserError

    spec = PointMazeSpec.create("PointMaze_UMaze-v3")
    nominal_mass = spec.model.body_mass.copy()
    light, heavy = scale_mass(spec.model, 0.5), scale_mass(spec.model, 4.0)
    assert np.array_equal(spec.model.body_mass, nominal_mass)
    assert np.allclose(heavy.body_mass[1:], 4 * nominal_mass[1:]) and heavy.body_mass[0] == 0
    assert np.allclose(heavy.body_inertia[1:], 4 * spec.model.body_inertia[1:])
    sim = BatchSim(spec, 3, models=[spec.model, light, heavy])
    sim.reset(np.zeros((3, 4)))
    for _ in range(3):
        sim.step(np.tile([0.2, 0.0], (3, 1)))
    x = sim.observe()[:, 0]
    assert x[1] > 1.8 * x[0] > 0 and 0 < x[2] < 0.3 * x[0]
    with pytest.raises(UserError, match="deploy.mass_scale"):
        scale_mass(spec.model, 0.0)
