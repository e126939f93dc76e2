"""gymnasium-robotics' FrankaKitchen-v1 (`pipeline.envs.kitchen`): the compatibility shim, the
spec against the real noise-free env bit for bit, tasks and success against the env's own
`info`, and a Minari dataset written by Minari's `DataCollector` and read by our importer. Real
physics, no mocks."""

from __future__ import annotations

import importlib.util

import mujoco
import numpy as np
import pytest

from pipeline.envs.batch import BatchSim
from pipeline.envs.kitchen import (
    BONUS_THRESH,
    KITCHEN_STATE_SPEC,
    KITCHEN_TASK_SETS,
    OBS_ELEMENT_GOALS,
    OBS_ELEMENT_INDICES,
    SUBTASKS,
    KitchenGoal,
    KitchenSpec,
    get_joint_qpos,
    get_joint_qvel,
    is_kitchen,
    kitchen_spec,
    make_kitchen_env,
    patch_mujoco_utils,
    write_kitchen_minari,
)
from pipeline.envs.physics import PHYSICS_SPEC
from pipeline.errors import UserError

# gymnasium's passive checker warns that `desired_goal` is the same dict at every step (it is).
pytestmark = pytest.mark.filterwarnings("ignore:.*share an object:UserWarning")


@pytest.fixture(scope="module")
def spec() -> KitchenSpec:
    """The spec of the env's default task (all seven subtasks)."""
    return kitchen_spec()


@pytest.fixture(scope="module")
def env():
    """The noise-free env with all seven subtasks, never removed (so `step_task_completions` is
    every subtask complete after the step)."""
    env = make_kitchen_env(
        robot_noise_ratio=0.0, object_noise_ratio=0.0, remove_task_when_completed=False
    )
    yield env
    env.close()


def _copy_of(spec: KitchenSpec, env) -> mujoco.MjData:
    """A fresh `MjData` in the env's exact state, through `physics_state` / `set_physics_state`."""
    data = mujoco.MjData(spec.model)
    spec.set_physics_state(data, spec.state_of_env(env))
    return data


# --- the shim ------------------------------------------------------------------------------------


def test_shim_is_needed_and_idempotent(spec: KitchenSpec) -> None:
    """Upstream's functions (a fresh copy of the module) fail on a hinge joint under this MuJoCo;
    the shim's agree with upstream on the joint types upstream handles (the free kettle)."""
    from gymnasium_robotics.utils import mujoco_utils

    path = mujoco_utils.__file__
    upstream_spec = importlib.util.spec_from_file_location("upstream_mujoco_utils", path)
    upstream = importlib.util.module_from_spec(upstream_spec)
    upstream_spec.loader.exec_module(upstream)
    model, data = spec.model, mujoco.MjData(spec.model)
    mujoco.mj_resetData(model, data)
    data.qpos[:] = np.arange(model.nq)
    data.qvel[:] = np.arange(model.nv)
    try:
        upstream.get_joint_qpos(model, data, "microwave")
    except AssertionError:
        pass
    else:
        pytest.skip("upstream's get_joint_qpos works here: patch_mujoco_utils can be removed")
    np.testing.assert_array_equal(get_joint_qpos(model, data, "microwave"), [22.0])
    np.testing.assert_array_equal(get_joint_qvel(model, data, "microwave"), [22.0])
    for ours, theirs in ((get_joint_qpos, upstream.get_joint_qpos), (get_joint_qvel,
                         upstream.get_joint_qvel)):  # fmt: skip
        np.testing.assert_array_equal(ours(model, data, "kettle"), theirs(model, data, "kettle"))
    assert patch_mujoco_utils() is False  # make_kitchen_env patched already: nothing to do
    assert mujoco_utils.get_joint_qpos is get_joint_qpos
    assert mujoco_utils.get_joint_qvel is get_joint_qvel
    qpos, qvel = mujoco_utils.robot_get_obs(
        model, data, [model.joint(i).name for i in range(model.njnt)]
    )
    np.testing.assert_array_equal(qpos, np.arange(9))
    np.testing.assert_array_equal(qvel, np.arange(9))


def test_constants_are_the_envs() -> None:
    from gymnasium_robotics.envs.franka_kitchen import kitchen_env

    assert list(OBS_ELEMENT_INDICES) == list(kitchen_env.OBS_ELEMENT_INDICES)
    for t in SUBTASKS:
        np.testing.assert_array_equal(OBS_ELEMENT_INDICES[t], kitchen_env.OBS_ELEMENT_INDICES[t])
        np.testing.assert_array_equal(OBS_ELEMENT_GOALS[t], kitchen_env.OBS_ELEMENT_GOALS[t])
    assert BONUS_THRESH == kitchen_env.BONUS_THRESH
    assert all(set(s) <= set(SUBTASKS) for s in KITCHEN_TASK_SETS.values())


# --- the spec ------------------------------------------------------------------------------------


def test_sizes_and_layout(spec: KitchenSpec) -> None:
    model = spec.model
    assert (model.nq, model.nv, model.nu) == (30, 29, 9)
    assert (spec.env_id, spec.state_dim, spec.action_dim) == ("FrankaKitchen-v1", 59, 9)
    assert spec.physics_dim == mujoco.mj_stateSize(model, PHYSICS_SPEC) + model.nv == 89
    assert spec.state_spec == KITCHEN_STATE_SPEC
    assert (spec.dt, spec.frame_skip, spec.max_episode_steps) == (0.08, 40, 280)
    assert spec.subtasks == SUBTASKS and spec.layout == {"kind": "kitchen", "subtasks": [*SUBTASKS]}
    assert len(spec.goal_dims) == len(spec.goal_scale) == 17
    assert is_kitchen("FrankaKitchen-v1") and not is_kitchen("PointMaze_UMaze-v3")
    assert kitchen_spec() is spec  # shared
    with pytest.raises(UserError, match="no start position"):
        spec.start_observation(np.zeros(2))


def test_control_step_is_env_step_bit_for_bit(spec: KitchenSpec, env) -> None:
    """50 random actions (some beyond [-1, 1]) from a reset: every observation and the whole
    exact state equal the env's."""
    env.reset(seed=0)
    data = _copy_of(spec, env)
    rng = np.random.default_rng(0)
    for k in range(50):
        action = rng.uniform(-1.3, 1.3, 9)
        obs = env.step(action)[0]["observation"]
        spec.control_step(spec.model, data, action)
        assert np.array_equal(spec.observe(data), obs), f"step {k}"
    np.testing.assert_array_equal(spec.physics_state(data), spec.state_of_env(env))


def test_exact_state_needs_the_warm_start(spec: KitchenSpec, env) -> None:
    """Restored anywhere along a random run, the state (full physics + warm start) steps on as
    the env does; full physics alone does not (the Newton solver starts elsewhere)."""
    env.reset(seed=0)
    rng = np.random.default_rng(1)
    cold_differs = 0
    for _ in range(30):
        action = rng.uniform(-1, 1, 9)
        exact, cold = _copy_of(spec, env), mujoco.MjData(spec.model)
        full = np.empty(mujoco.mj_stateSize(spec.model, PHYSICS_SPEC))
        mujoco.mj_getState(spec.model, env.unwrapped.data, full, PHYSICS_SPEC)
        mujoco.mj_setState(spec.model, cold, full, PHYSICS_SPEC)
        obs = env.step(action)[0]["observation"]
        for data in (exact, cold):
            spec.control_step(spec.model, data, action)
        assert np.array_equal(spec.observe(exact), obs)
        cold_differs += not np.array_equal(spec.observe(cold), obs)
    assert cold_differs > 0


def test_observation_is_the_state(spec: KitchenSpec, env) -> None:
    """`set_observation` then `observe` is the identity, and `BatchSim` started from the reset
    observation steps as `env.reset` + `env.step`."""
    obs0 = env.reset(seed=0)[0]["observation"]
    rng = np.random.default_rng(2)
    for _ in range(5):
        obs = env.step(rng.uniform(-1, 1, 9))[0]["observation"]
    data = mujoco.MjData(spec.model)
    spec.set_observation(data, obs)
    assert np.array_equal(spec.observe(data), obs)
    np.testing.assert_array_equal(data.qpos, env.unwrapped.data.qpos)
    np.testing.assert_array_equal(data.qvel, env.unwrapped.data.qvel)

    sim = BatchSim(spec, 2)
    sim.reset(np.stack([obs0, obs0]))
    env.reset(seed=1)
    for _ in range(10):
        action = rng.uniform(-1, 1, 9)
        obs = env.step(action)[0]["observation"]
        assert not sim.step(np.stack([action, np.zeros(9)]))
        assert np.array_equal(sim.observe([0])[0], obs)
    np.testing.assert_array_equal(sim.get_state([0])[0], spec.state_of_env(env))


def test_goal_dims_are_the_achieved_goal(spec: KitchenSpec, env) -> None:
    """The env's `achieved_goal` (full qpos at `OBS_ELEMENT_INDICES`) is the observation at the
    spec's goal dims, subtask by subtask, after random steps."""
    env.reset(seed=0)
    rng = np.random.default_rng(3)
    for _ in range(5):
        obs = env.step(rng.uniform(-1, 1, 9))[0]
    at = obs["observation"][list(spec.goal_dims)]
    start = 0
    for t in SUBTASKS:
        n = len(OBS_ELEMENT_INDICES[t])
        assert np.array_equal(at[start : start + n], obs["achieved_goal"][t]), t
        start += n
    np.testing.assert_array_equal(spec.goal_vector(KitchenGoal.of(SUBTASKS)), np.concatenate(
        [OBS_ELEMENT_GOALS[t] for t in SUBTASKS]))  # fmt: skip
    mixed = KitchenSpec.for_task_set("kitchen-mixed")
    assert mixed.subtasks == ("bottom burner", "light switch", "microwave", "kettle")
    assert mixed.goal_dims == (20, 21, 26, 27, 31, *range(32, 39))


# --- tasks and success ---------------------------------------------------------------------------


def test_success_agrees_with_the_env(spec: KitchenSpec, env) -> None:
    """Each subtask's element put at its goal (via qpos), one step: the env's
    `step_task_completions` and the spec's `completed` (state) and `subtasks_reached`
    (observation) name the same subtasks; the reset state completes none."""
    u = env.unwrapped
    goal = KitchenGoal.of(SUBTASKS)
    gv = spec.goal_vector(goal)
    env.reset(seed=0)
    assert spec.completed(u.data, goal) == () and not spec.success(u.data, goal)
    obs, reward, *_, info = env.step(np.zeros(9))
    assert info["step_task_completions"] == [] and reward == 0.0
    assert spec.completed(u.data, goal) == ()
    assert not spec.subtasks_reached(obs["observation"], gv).any()
    for combo in [(t,) for t in SUBTASKS] + [("microwave", "light switch", "kettle")]:
        env.reset(seed=0)
        for t in combo:
            u.data.qpos[list(OBS_ELEMENT_INDICES[t])] = OBS_ELEMENT_GOALS[t]
        obs, reward, *_, info = env.step(np.zeros(9))
        done = spec.completed(u.data, goal)
        assert set(done) == set(info["step_task_completions"]) == set(combo), combo
        assert reward == len(done)
        reached = spec.subtasks_reached(obs["observation"], gv)
        assert tuple(t for t, r in zip(SUBTASKS, reached, strict=True) if r) == done
        assert spec.success(u.data, KitchenGoal.of(combo))
        assert not spec.goal_reached(obs["observation"], gv)


def test_episode_completions_count_like_the_env(env) -> None:
    """An episode opens the microwave, closes it again and turns the light on: the env's
    `episode_task_completions` (microwave, light switch) is `completion_count`, though only the
    light is on at the end."""
    mixed = KitchenSpec.for_task_set("kitchen-mixed")
    gv = mixed.goal_vector(KitchenGoal.of(mixed.subtasks))
    ep_env = make_kitchen_env(
        robot_noise_ratio=0.0, object_noise_ratio=0.0, tasks_to_complete=list(mixed.subtasks)
    )
    u = ep_env.unwrapped
    ep_env.reset(seed=0)
    closed = u.data.qpos[22]
    observations = []
    for edit in ({22: -0.75}, {22: closed}, {17: -0.69, 18: -0.05}, {}):
        for i, v in edit.items():
            u.data.qpos[i] = v
        obs, *_, info = ep_env.step(np.zeros(9))
        observations.append(obs["observation"])
    ep_env.close()
    assert set(info["episode_task_completions"]) == {"microwave", "light switch"}
    assert mixed.completion_count(np.stack(observations), gv) == 2
    assert mixed.subtasks_reached(observations[-1], gv).sum() == 1
    batch = np.stack([np.stack(observations), np.stack(observations[1:2] * 4)])
    np.testing.assert_array_equal(mixed.completion_count(batch, np.stack([gv, gv])), [2, 0])


def test_task_sets_and_starts(spec: KitchenSpec, env) -> None:
    assert KITCHEN_TASK_SETS["kitchen-partial"] == KITCHEN_TASK_SETS["kitchen-complete"]
    partial = KitchenSpec.for_task_set("kitchen-partial")
    assert [t.name for t in partial.tasks()] == ["kitchen-partial", "kitchen-complete"]
    assert [t.name for t in spec.tasks()] == ["kitchen-all"]
    assert [t.name for t in kitchen_spec({"tasks_to_complete": ["kettle"]}).tasks()] == [
        "kitchen-custom"
    ]
    a, b = partial.task_start("kitchen-complete", seed=0), partial.task_start(2, seed=123)
    assert a.task.name == b.task.name == "kitchen-complete"
    np.testing.assert_array_equal(a.physics, b.physics)  # the seed only draws noise
    np.testing.assert_array_equal(a.physics, partial.cold(a.physics))  # reset: no warm start
    assert a.physics[0] == 0.0 and not a.physics[1 + 30 :].any()  # time 0, at rest
    reset_obs = env.reset(seed=0)[0]["observation"]
    np.testing.assert_array_equal(a.observation, reset_obs)
    data = mujoco.MjData(partial.model)
    partial.set_physics_state(data, a.physics)
    assert np.array_equal(partial.observe(data), a.observation)
    assert partial.completed(data, a.goal) == ()
    gv = partial.goal_vector(a.goal)
    np.testing.assert_array_equal(a.goal_observation[list(partial.goal_dims)], gv)
    assert partial.goal_reached(a.goal_observation, gv) and not partial.goal_reached(
        a.observation, gv
    )


def test_goal_scale_is_the_tolerance() -> None:
    """In `goal_scale` units a subtask is complete below 1: the microwave 0.29 off its goal is
    complete, 0.31 off is not."""
    micro = kitchen_spec({"tasks_to_complete": ["microwave"]})
    assert micro.goal_dims == (31,) and micro.goal_scale == (0.3,)
    gv = micro.goal_vector(KitchenGoal.of(["microwave"]))
    obs = np.zeros(59)
    for off, ok in ((0.29, True), (0.31, False)):
        obs[31] = gv[0] + off
        assert micro.goal_reached(obs, gv) == ok
        assert (abs(obs[31] - gv[0]) / micro.goal_scale[0] < 1) == ok


def test_user_errors(spec: KitchenSpec) -> None:
    with pytest.raises(UserError, match="unknown kitchen subtask"):
        make_kitchen_env(tasks_to_complete=["oven"])
    with pytest.raises(UserError, match="unknown kitchen task set 'kitchen-bogus'"):
        KitchenSpec.for_task_set("kitchen-bogus")
    with pytest.raises(UserError, match="no kitchen task 'kitchen-mixed'"):
        spec.task_start("kitchen-mixed", 0)
    with pytest.raises(UserError, match="make the spec with tasks_to_complete"):
        spec.goal_vector(KitchenGoal.of(["kettle"]))
    with pytest.raises(UserError, match="is empty"):
        kitchen_spec({"tasks_to_complete": []})


# --- a Minari dataset ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def minari_kitchen(tmp_path_factory):
    """3 episodes of 12, 7, 9 random steps (the longest cut by the time limit)."""
    return write_kitchen_minari(tmp_path_factory.mktemp("minari"), episode_steps=(12, 7, 9))


def test_minari_dataset_imports(spec: KitchenSpec, minari_kitchen) -> None:
    """Our importer reads the DataCollector's dataset: 59-dim states (`observation`), 9-dim
    actions, the right lengths; the recorded `infos['physics']` replay it bit for bit."""
    import minari

    from pipeline.sources import read_minari

    dataset = minari.MinariDataset(minari_kitchen / "data")
    imported = read_minari("kitchen", path=minari_kitchen, goal_key=None, control_period=spec.dt)
    info = imported.info
    assert info.env_id == "FrankaKitchen-v1" and info.env_kwargs["robot_noise_ratio"] == 0.0
    assert len(info.state_names) == 59 and len(info.action_names) == 9
    assert info.control_period == 0.08 and info.physics_dim == 89 and imported.frames == 28
    episodes = list(imported.episodes)
    assert [len(ep) for ep in episodes] == [12, 7, 9]
    data = mujoco.MjData(spec.model)
    for ep, raw in zip(episodes, dataset.iterate_episodes(), strict=True):
        n = len(ep)
        assert ep.observations.shape == (n, 59) and ep.actions.shape == (n, 9)
        np.testing.assert_array_equal(ep.observations, raw.observations["observation"][:n])
        np.testing.assert_array_equal(ep.actions, raw.actions)
        physics = raw.infos["physics"]
        assert physics.shape == (n + 1, spec.physics_dim)
        spec.set_physics_state(data, physics[0])
        for k in range(n):
            spec.control_step(spec.model, data, ep.actions[k])
            assert np.array_equal(spec.observe(data), raw.observations["observation"][k + 1])
        np.testing.assert_array_equal(spec.physics_state(data), physics[n])
    assert [bool(ep.terminals.any()) for ep in episodes] == [False] * 3
    assert list(dataset.iterate_episodes())[0].truncations[-1]


def test_minari_importer_reads_the_kitchen(spec: KitchenSpec, minari_kitchen) -> None:
    """With the importer's defaults: the control period is the spec's, the goal is
    `desired_goal`'s subtasks side by side (the spec's `goal_vector`), the task set is named,
    the physics states are the recorded ones on the dataset clock (from the observation where
    none are recorded: the same numbers but for the warm start, noise-free)."""
    from pipeline.envs.kitchen import physics_from_observations
    from pipeline.sources import read_minari

    imported = read_minari("kitchen", path=minari_kitchen)
    info = imported.info
    assert info.control_period == spec.dt and info.goal_dim == len(spec.goal_dims)
    assert info.generator["kitchen_task_set"] == "kitchen-all"
    assert info.env_kwargs["tasks_to_complete"] == list(spec.subtasks)
    goal = spec.goal_vector(spec.task("kitchen-all").goal)
    time = 0.0
    for ep in imported.episodes:
        n = len(ep)
        assert np.array_equal(ep.goals, np.tile(goal, (n, 1)))
        assert np.allclose(ep.physics[:, 0], time + spec.dt * np.arange(n))
        made = physics_from_observations(spec, ep.observations, ep.physics[:, 0])
        np.testing.assert_array_equal(made[:, : 1 + 30 + 29], ep.physics[:, : 1 + 30 + 29])
        time += spec.dt * n
