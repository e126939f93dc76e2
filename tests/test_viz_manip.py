"""The manipulation views (OGBench's cube-single and scene): the arm drawn from MuJoCo's
kinematics, cubes and their goals, the legend, the framing, the dataset view and the success bars,
read back from the recordings. (What they look like is checked by eye: scripts/screenshots.py.)"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from factories import make_info
from rerun.chunk import RrdReader
from test_viz_views import _entities, _values, _verify, _views

from pipeline.dataset import Episode
from pipeline.envs.manipspace.env import SUCCESS_TOLERANCE, manipspace_spec, reference_env
from pipeline.evaluation.episodes import EpisodeResult, EpisodeTrace
from pipeline.evaluation.tasks import EpisodeSpec
from pipeline.recording import write_dataset
from pipeline.viz import manip_scene
from pipeline.viz.dataset import write_dataset_view
from pipeline.viz.manip import write_manip_episode_recording, write_manip_overview

STEPS = 12


def _rollout(env_id: str, steps: int = STEPS, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Observations `[steps + 1, state_dim]` and actions `[steps, 5]` of a real episode from the
    reference env's reset state (no second env to build) driven by random actions in MuJoCo."""
    spec = manipspace_spec(env_id)
    data = mujoco.MjData(spec.model)
    spec.set_physics_state(data, spec.state_of_env(reference_env(env_id)))
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, size=(steps, 5))
    obs = [spec.observe(data)]
    for a in actions:
        spec.control_step(spec.model, data, a)
        obs.append(spec.observe(data))
    return np.array(obs), actions


@pytest.fixture(scope="module")
def cube():
    return manipspace_spec("cube-single-v0"), *_rollout("cube-single-v0")


def _result(spec, obs, actions, task="ogbench-task1", index=0, success=False, plans=True):
    goal = np.array(
        [0.3, 0.5, 0.2] * spec.n_cubes + [0.0] * (len(spec.goal_dims) - 3 * spec.n_cubes)
    )
    trace = EpisodeTrace(states=list(obs), actions=list(actions))
    if plans:
        trace.replan_steps = [0, 6]
        trace.plans = [obs[[t, t + 2, t + 4]] for t in (0, 6)]
        trace.plan_costs = [3.0, 2.0]
    result = EpisodeResult(EpisodeSpec(task, index, obs[0], goal, 5), agent="oposm")
    result.steps, result.replans, result.trace = len(actions), len(trace.plans), trace
    result.steps_to_goal = 10 if success else None
    result.min_distance = result.final_distance = 0.5 if success else 6.0
    return result


def test_the_arm_follows_mujocos_kinematics_of_the_observed_joints(cube):
    """The drawn arm ends where the observation says the pinch site is: the joint angles went
    into the right joints (the pinch reading lags the joints by one physics step: < 1 cm)."""
    spec, obs, _ = cube
    poser = manip_scene.ArmPoses(spec)
    poses = poser(obs)
    assert poses.arm.shape == (len(obs), len(manip_scene.ARM_BODIES) + 1, 3)
    assert np.allclose(poses.arm[:, 0], 0.0)  # the UR5e's base stands at the world origin
    site = spec._ids["pinch"]
    qpos = poser.joint_positions(obs)
    for t in (0, len(obs) - 1):
        poser.data.qpos[:] = qpos[t]
        mujoco.mj_kinematics(spec.model, poser.data)
        observed = manip_scene.to_metres(obs[t, manip_scene.PINCH])
        assert np.linalg.norm(poser.data.site_xpos[site] - observed) < 0.01
    # The gripper's base is a few centimetres above the pinch site, the pads beside it.
    assert 0.05 < np.linalg.norm(poses.arm[-1, -2] - poses.arm[-1, -1]) < 0.25
    pads = poses.fingers[:, :, -1]  # [n, 2, 3]
    assert np.all(np.linalg.norm(pads[:, 0] - pads[:, 1], axis=-1) < 0.12)
    assert np.ptp(poses.arm[:, 3:], axis=0).max() > 0.005  # random actions move the arm


def test_an_episode_shows_arm_table_cubes_goals_and_a_legend(tmp_path, cube):
    spec, obs, actions = cube
    path = tmp_path / "oposm-ogbench-task1-0000.rrd"
    write_manip_episode_recording(path, _result(spec, obs, actions), spec)
    _verify(path)
    entities = _entities(path)
    for entity in (
        "/world/arm/links", "/world/arm/fingers", "/world/arm/joints", "/world/arm/pinch",
        "/world/table", "/world/walls", "/world/workspace", "/world/cubes", "/world/goals",
        "/world/to_goal", "/world/pinch_path", "/world/plan/cubes", "/summary",
    ):  # fmt: skip
        assert entity in entities, entity
    links = _values(path, "/world/arm/links", "strips")
    assert len(links) >= len(obs)  # one arm per step (and the static style row)
    # Cubes are solid boxes labelled "cube i"; goals wire boxes of the tolerance, "goal of ...",
    # in the same colour, so which cube goes where reads at a glance.
    assert _values(path, "/world/cubes", "labels")[0] == ["cube 0"]
    assert _values(path, "/world/cubes", "fill_mode")[0] == [3]  # Solid
    assert _values(path, "/world/goals", "labels")[0] == ["goal of cube 0"]
    assert np.allclose(_values(path, "/world/goals", "half_sizes")[0], [[SUCCESS_TOLERANCE] * 3])
    assert _values(path, "/world/goals", "colors")[0] == _values(path, "/world/cubes", "colors")[0]
    assert _values(path, "/world/goals", "fill_mode") in ([], [None], [[]])  # wire (default)
    # The legend names the arm, the cubes, their goals and the plans.
    labels = [
        label
        for e in sorted(entities)
        if e.startswith("/legend/") and e.endswith("/label")
        for label in _values(path, e, "labels")[0]
    ]
    assert {"arm (UR5e links)", "pinch site", "cube 0", "goal of cube 0"} <= set(labels)
    assert "TAWM: predicted cubes" in labels
    views = _views(path)
    assert views["workspace (m, z up)"] == "3D" and views["legend"] == "2D"
    ((text,),) = _values(path, "/summary", "text")
    assert text.startswith("### oposm: did not reach the goal in 12 steps")
    assert "cube 0 ends" in text


def test_the_camera_frames_the_table_and_the_arm(cube):
    """The 3-D view looks at the workspace from outside it, z up, with the arm's base (the world
    origin) and the far corner of the table both in front of the camera."""
    view = manip_scene.workspace_view("w", "/world/**")
    eye = view.properties["EyeControls3D"]
    pos = np.array(eye.position.as_arrow_array().to_pylist()[0])
    target = np.array(eye.look_target.as_arrow_array().to_pylist()[0])
    forward = (target - pos) / np.linalg.norm(target - pos)
    low, high = manip_scene.WORKSPACE_BOUNDS
    for point in (np.zeros(3), low, high, np.array([high[0], low[1], 0.0])):
        to = point - pos
        cos = to @ forward / np.linalg.norm(to)
        assert cos > np.cos(np.radians(35)), point  # within a 70-degree field of view


def test_the_scene_moves_its_buttons_drawer_and_window(tmp_path):
    spec = manipspace_spec("scene-v0")
    obs, actions = _rollout("scene-v0", steps=4)
    poses = manip_scene.ArmPoses(spec)(obs)
    assert set(poses.bodies) == set(manip_scene.SCENE_BODIES)
    path = tmp_path / "scene.rrd"
    write_manip_episode_recording(path, _result(spec, obs, actions, plans=False), spec)
    entities = _entities(path)
    assert {"/world/scene/drawer_link", "/world/scene/window", "/world/arm/links"} <= entities
    assert len(_values(path, "/world/scene/drawer_link", "translation")) == len(obs)
    ((text,),) = _values(path, "/summary", "text")
    assert "drawer" in text and "plan cost at each replan" not in _views(path)
    # Its two buttons in their state's colours (OGBench's scene: red 0 locks, white 1), the
    # goal's button states (after the cube's 3 goal dims) as wire boxes.
    red, white = list(manip_scene.BUTTON_OFF), list(manip_scene.SCENE_BUTTON_ON)
    base = 19 + 9 * spec.n_cubes  # the proprio dims, then each cube's
    states = obs[:, base + 1 : base + 4 * 2 : 4]
    caps = [[_rgb(c) for c in row] for row in _values(path, "/world/buttons", "colors")]
    assert caps == [[white if s else red for s in row] for row in states]
    (goal_colors,) = _values(path, "/world/button_goals", "colors")
    assert [_rgb(c) for c in goal_colors] == [red, red]  # `_result`'s goal: 0 after the cube
    labels = {
        label
        for e in entities
        if e.startswith("/legend/") and e.endswith("/label")
        for label in _values(path, e, "labels")[0]
    }
    assert {"button locked (0)", "button unlocked (1)", "goal: unlocked"} <= labels


def test_a_manipulation_dataset_opens_in_3d(tmp_path, cube):
    """`oposm view` of a cube dataset no longer needs a maze: the arm on the dataset clock,
    every episode's cube and gripper paths, the summary and the actions."""
    spec, obs, actions = cube
    n = len(actions)
    info = make_info("cubes")
    info.env_id, info.source, info.goal_dim, info.physics_dim = "cube-single-v0", "ogbench", 0, 0
    info.state_names = [f"s{k}" for k in range(spec.state_dim)]
    info.state_units = ["1"] * spec.state_dim
    info.action_names = ["dx", "dy", "dz", "dyaw", "dgrip"]
    info.action_units = ["1"] * 5
    info.control_period = spec.dt
    episodes = [
        Episode(
            index=i, observations=obs[:n], actions=actions, time=spec.dt * (np.arange(n) + n * i)
        )
        for i in range(3)
    ]
    write_dataset(tmp_path / "cubes.mcap", info, episodes)
    path = tmp_path / "cubes.rrd"
    assert write_dataset_view(tmp_path / "cubes.mcap", path, max_episodes=2) == {
        "episodes": 2,
        "total": 3,
    }
    _verify(path)
    entities = _entities(path)
    for entity in (
        "/world/arm/links", "/world/cubes", "/world/table", "/world/paths/cubes",
        "/world/paths/gripper", "/world/current", "/actions/dgrip", "/summary",
    ):  # fmt: skip
        assert entity in entities, entity
    assert not any(e.startswith("/maze") for e in entities)
    assert len(_values(path, "/world/paths/cubes", "strips")[0]) == 2  # a cube path per episode
    assert len(_values(path, "/actions/dx", "scalars")) == 2 * n
    timelines = {c.name for c in RrdReader(path).store().schema().index_columns()}
    assert {"time", "episode"} <= timelines
    assert _views(path)["demonstrations (m, z up)"] == "3D"


def test_the_success_bars_read_0_to_100_percent_with_task_names(tmp_path, cube):
    """At 0 % success the chart still spans 0..100 % (fixed gridlines and bounds) and names
    every task under its bars; a bar's height is its rate."""
    spec, obs, actions = cube
    results = [
        _result(spec, obs, actions, "ogbench-task1", 0, False),
        _result(spec, obs, actions, "ogbench-task1", 1, True),
        _result(spec, obs, actions, "ogbench-task2", 0, False),
    ]
    path = tmp_path / "overview.rrd"
    write_manip_overview(path, results, spec)
    _verify(path)
    assert _values(path, "/success/axis", "labels")[0] == ["0 %", "25 %", "50 %", "75 %", "100 %"]
    assert _values(path, "/success/tasks", "labels")[0] == ["ogbench-task1", "ogbench-task2"]
    assert _values(path, "/success/oposm/counts", "labels")[0] == ["1/2", "0/1"]
    entities = _entities(path)
    assert "/success/oposm/0" in entities and "/success/oposm/1" not in entities  # 0 %: no bar
    grid = np.array(_values(path, "/success/grid", "strips")[0])  # [5, 2, 2]
    ((scale,),) = _values(path, "/success/oposm/0", "scale")
    assert np.isclose(2 * scale[1], 0.5 * np.ptp(grid[:, 0, 1]))  # 2 px: 50 % high
    assert _views(path)["success rate per task"] == "2D"


@pytest.mark.parametrize("env_id", ["pointmaze-medium-v0", "antmaze-medium-v0"])
def test_every_maze_domain_has_a_dataset_view(tmp_path, env_id):
    """OGBench's point and ant mazes open over their maze (the ant's 4 m cells scale the map)."""
    from pipeline.envs.spec import make_env_spec

    spec = make_env_spec(env_id)
    info = make_info("maze")
    info.env_id, info.source, info.physics_dim = env_id, "ogbench", 0
    info.state_names = [f"s{k}" for k in range(spec.state_dim)]
    info.state_units = ["1"] * spec.state_dim
    rng = np.random.default_rng(0)
    free = np.asarray(spec.layout["free_cell_centers"], dtype=float)[:20]
    obs = np.zeros((len(free), spec.state_dim))
    obs[:, :2] = free
    episode = Episode(index=0, observations=obs, actions=rng.uniform(-1, 1, (len(free), 2)),
                      time=0.1 * np.arange(len(free)), goals=free[::-1].copy())  # fmt: skip
    info.action_names, info.action_units, info.goal_dim = ["a0", "a1"], ["1", "1"], 2
    write_dataset(tmp_path / "maze.mcap", info, [episode])
    path = tmp_path / "maze.rrd"
    write_dataset_view(tmp_path / "maze.mcap", path)
    _verify(path)
    assert {"/maze/walls", "/demos/paths", "/demos/agent", "/legend/0"} <= _entities(path)
    ((scale,),) = _values(path, "/maze/walls", "scale")
    assert scale[0] == spec.layout["maze_size_scaling"]
    (paths,) = _values(path, "/demos/paths", "strips")
    assert np.allclose(paths[0], free * [1, -1])  # the right way up


# --- the puzzles ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def puzzle():
    """A puzzle-3x3 play episode of 60 steps: the button oracle presses buttons in it."""
    from pipeline.envs.manipspace.data import generate

    spec = manipspace_spec("puzzle-3x3-v0")
    ep = generate(spec.env_id, "play", episodes=1, episode_steps=60, seed=2)[0]
    return spec, ep["observations"], ep["actions"]


def test_a_puzzle_episode_shows_its_buttons_in_their_states_colours_and_the_goal(tmp_path, puzzle):
    """No cube: the button caps at every step in their state's colour (OGBench's red 0, blue 1),
    each button's goal state a wire box in that state's colour, the grid's states in the text."""
    spec, obs, actions = puzzle
    goal = np.array([1, 1, 0, 1, 0, 1, 0, 1, 1], dtype=float)  # puzzle-3x3 task 1's
    result = _result(spec, obs, actions)
    result.spec = EpisodeSpec("ogbench-task1", 0, obs[0], goal, 5)
    path = tmp_path / "oposm-ogbench-task1-0000.rrd"
    write_manip_episode_recording(path, result, spec)
    _verify(path)
    entities = _entities(path)
    assert {"/world/buttons", "/world/button_goals", "/world/arm/links", "/summary"} <= entities
    assert "/world/scene/button_4" in entities and "/world/cubes" not in entities
    red, blue = list(manip_scene.BUTTON_OFF), list(manip_scene.BUTTON_ON)
    (goal_colors,) = _values(path, "/world/button_goals", "colors")
    assert [_rgb(c) for c in goal_colors] == [blue if g else red for g in goal]
    caps = [[_rgb(c) for c in row] for row in _values(path, "/world/buttons", "colors")]
    assert len(caps) == len(obs)  # a row per step
    states = obs[:, 19 + 1 : 19 + 4 * 9 : 4]  # each button's "on" dim
    assert caps == [[blue if s else red for s in row] for row in states]
    assert len({tuple(map(tuple, row)) for row in caps}) >= 2  # a press changed colours
    labels = [
        label
        for e in sorted(entities)
        if e.startswith("/legend/") and e.endswith("/label")
        for label in _values(path, e, "labels")[0]
    ]
    assert {"button off (0)", "button on (1)", "goal: on"} <= set(labels)
    assert "TAWM: predicted cubes" not in labels
    ((text,),) = _values(path, "/summary", "text")
    assert "goal 110 101 011" in text and "in their goal state" in text


def _rgb(packed: int) -> list[int]:
    """A colour as Rerun stores it (0xRRGGBBAA) -> [r, g, b]."""
    return [(packed >> shift) & 0xFF for shift in (24, 16, 8)]


def test_a_puzzle_dataset_and_its_validate_view_open(tmp_path, puzzle):
    """`oposm view` of a puzzle dataset: the buttons on the dataset clock, no cube paths; and
    validate's recording follows the gripper (no cube to follow)."""
    from pipeline.evaluation.open_loop import ModeResult, OpenLoopResult
    from pipeline.viz.manip_validate import tracked, write_validate_recording

    spec, obs, actions = puzzle
    n = len(actions)
    info = make_info("puzzle")
    info.env_id, info.source, info.goal_dim, info.physics_dim = spec.env_id, "ogbench", 0, 0
    info.state_names = [f"s{k}" for k in range(spec.state_dim)]
    info.state_units = ["1"] * spec.state_dim
    info.action_names = ["dx", "dy", "dz", "dyaw", "dgrip"]
    info.action_units = ["1"] * 5
    info.control_period = spec.dt
    episodes = [
        Episode(index=0, observations=obs[:n], actions=actions, time=spec.dt * np.arange(n))
    ]
    write_dataset(tmp_path / "puzzle.mcap", info, episodes)
    path = tmp_path / "puzzle.rrd"
    assert write_dataset_view(tmp_path / "puzzle.mcap", path) == {"episodes": 1, "total": 1}
    _verify(path)
    entities = _entities(path)
    assert {"/world/buttons", "/world/arm/links", "/world/paths/gripper"} <= entities
    assert len(_values(path, "/world/buttons", "colors")) == n
    rollouts = np.stack([obs[:21], obs[20:41]])  # [2, L H + 1, sd]: 2 rollouts, L 4 x H 5
    mode = ModeResult(real=rollouts, actions=np.stack([actions[:20], actions[20:40]]),
                      tawm_mean=rollouts[:, 5::5], pred_mean=rollouts[:, 5::5],
                      pred_std=np.ones_like(rollouts[:, 5::5]), single_step=rollouts)  # fmt: skip
    result = OpenLoopResult(5, np.array([0]), 2, {"prior": mode}, 80, 1.0)
    validate = tmp_path / "validate.rrd"
    write_validate_recording(validate, result, spec, n_starts=1)
    _verify(validate)
    (real,) = _values(validate, "/prior/start_0/real", "strips")
    assert np.allclose(real[0], tracked(spec, obs[:21]))  # the pinch site's path
    assert np.allclose(real[0], manip_scene.to_metres(obs[:21, manip_scene.PINCH]))
    ((text,),) = _values(validate, "/about", "text")
    assert "the gripper's (pinch site) real paths" in text
