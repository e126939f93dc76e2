"""OGBench's manipulation envs through the pipeline: the batched simulator on their exact states,
the goal cost with per-dim scales, OGBench's five tasks from exact starts, the refusals of maze
tasks, and a tiny end to end run on cube-single (ingest -> segment -> train -> validate ->
deploy, real physics and random small models)."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from factories import one_line_error

from pipeline.config import load_params
from pipeline.envs.batch import BatchSim
from pipeline.envs.manipspace.env import READINGS, manipspace_spec
from pipeline.envs.spec import PointMazeSpec, make_env_spec
from pipeline.evaluation.goals import GoalRule
from pipeline.evaluation.tasks import check_manipulation_tasks, manipulation_episodes
from pipeline.paths import Paths
from pipeline.planning.costs import GoalCost
from pipeline.recording import read_info

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cube():
    return manipspace_spec("cube-single-v0")


# --- the simulator ---------------------------------------------------------------------------


def test_make_env_spec_builds_the_manipulation_specs_and_the_mazes_keep_theirs():
    spec = make_env_spec("cube-single-v0")
    assert spec is manipspace_spec("cube-single-v0")
    assert spec.state_spec == mujoco.mjtState.mjSTATE_FULLPHYSICS | (
        mujoco.mjtState.mjSTATE_WARMSTART | mujoco.mjtState.mjSTATE_USERDATA
    )
    maze = make_env_spec("PointMaze_UMaze-v3")
    assert isinstance(maze, PointMazeSpec)
    assert maze.state_spec == mujoco.mjtState.mjSTATE_FULLPHYSICS and maze.physics_dim == 5


def test_batch_sim_restores_and_steps_a_manipulation_state_as_control_step(cube):
    """Two slots from two task starts: restored, their observations are the env's reset ones;
    stepped through the batch, the states are `control_step`'s on a lone MjData, bit for bit."""
    starts = [cube.task_start(1, seed=3), cube.task_start(4, seed=4)]
    sim = BatchSim(cube, 2)
    sim.set_state(np.stack([s.physics for s in starts]))
    assert np.array_equal(sim.observe(), np.stack([s.observation for s in starts]))
    assert np.array_equal(sim.get_state(), np.stack([s.physics for s in starts]))
    lone = [mujoco.MjData(cube.model) for _ in starts]
    for data, s in zip(lone, starts, strict=True):
        cube.set_physics_state(data, s.physics)
    rng = np.random.default_rng(0)
    for _ in range(5):
        actions = rng.uniform(-1, 1, (2, cube.action_dim))
        assert sim.step(actions) == {}
        for data, action in zip(lone, actions, strict=True):
            cube.control_step(cube.model, data, action)
    assert np.array_equal(sim.get_state(), np.stack([cube.physics_state(d) for d in lone]))
    assert np.array_equal(sim.observe(), np.stack([cube.observe(d) for d in lone]))


def test_scene_slots_sharing_a_model_stay_independent():
    """The scene's step writes the drawer damping its button implies into the shared model:
    a slot with the drawer unlocked and one with it locked, both with the drawer moving, step
    together exactly as each does alone (and differently from each other)."""
    scene = manipspace_spec("scene-v0")
    base = scene.task_start(1, seed=0).physics.copy()
    drawer_vel = 1 + scene.model.nq + scene._ids["drawer_dof"]
    base[drawer_vel] = 0.5
    button0 = 1 + scene.model.nq + 2 * scene.model.nv + READINGS  # drawer lock in user data
    states = np.stack([base, base])
    states[0, button0], states[1, button0] = 1.0, 0.0  # unlocked, locked
    actions = np.zeros((2, scene.action_dim))

    together = BatchSim(scene, 2)
    together.set_state(states)
    alone = [BatchSim(scene, 1) for _ in range(2)]
    for sim, state in zip(alone, states, strict=True):
        sim.set_state(state[None])
    for _ in range(3):
        together.step(actions)
        for sim, action in zip(alone, actions, strict=True):
            sim.step(action[None])
    ends = together.get_state()
    assert np.array_equal(ends, np.concatenate([sim.get_state() for sim in alone]))
    drawer_pos = 1 + scene._ids["drawer_qpos"]
    moved = np.abs(ends[:, drawer_pos] - base[drawer_pos])
    assert moved[0] > 10 * moved[1]  # the unlocked drawer slides on, the locked one stops


# --- goals -----------------------------------------------------------------------------------


def test_a_unit_scale_on_x_y_gives_the_maze_cost_bit_for_bit():
    g = torch.Generator().manual_seed(0)
    states = torch.randn(3, 5, 4, 4, generator=g) * 3
    goals = torch.randn(3, 2, generator=g)
    for dims in [(0, 1), (1, 2)]:
        plain = GoalCost(goals, dims, skill_penalty=0.3)
        unit = GoalCost(goals, dims, skill_penalty=0.3, scale=(1.0, 1.0))
        assert torch.equal(plain(states), unit(states))
    assert GoalCost(goals).key == ((0, 1), 0.0, 0.0, None)  # the mazes' key, as before
    with pytest.raises(ValueError, match="scale"):
        GoalCost(goals, scale=(1.0, 0.0))


def test_the_goal_cost_counts_a_manipulation_goal_in_success_tolerances(cube):
    """A predicted cube 0.04 m (one tolerance) from its goal along x costs 1; 0.08 m along the
    diagonal of x and y costs 2; the best of a plan's skills is taken."""
    start = cube.task_start(1, seed=0)
    goal = cube.goal_vector(start.goal)  # observation units
    dims = list(cube.goal_dims)
    s0 = torch.as_tensor(start.observation, dtype=torch.float64)
    states = s0.repeat(1, 2, 3, 1)  # [B=1, K=2, L+1=3, sd]
    states[0, 0, 1, dims] = torch.as_tensor(goal + [0.4, 0, 0])  # 0.04 m along x
    states[0, 0, 2, dims] = torch.as_tensor(goal + [1.0, 0, 0])  # further: not the best
    off = 0.8 / np.sqrt(2)
    states[0, 1, 1:, dims] = torch.as_tensor(goal + [off, off, 0])
    cost = GoalCost(torch.as_tensor(goal)[None], cube.goal_dims, scale=cube.goal_scale)
    assert torch.allclose(cost(states), torch.tensor([[1.0, 2.0]], dtype=torch.float64))
    assert cube.goal_scale == (0.4, 0.4, 0.4)
    scene = manipspace_spec("scene-v0")
    assert scene.goal_scale[3:] == (0.5, 0.5, 0.04 * 18, 0.04 * 15)


def test_the_goal_rule_is_ogbench_success_in_manipulation_and_the_radius_in_mazes(cube):
    start = cube.task_start(2, seed=1)
    goal = cube.goal_vector(start.goal)
    rule = GoalRule.of_spec(cube)
    at_goal = start.observation.copy()
    at_goal[list(cube.goal_dims)] = goal + [0.39, 0, 0]  # 0.039 m off: inside
    assert rule.distance(at_goal, goal) == pytest.approx(0.975)
    assert rule.success(at_goal, goal, rule.distance(at_goal, goal), radius=1e-9)  # radius unused
    at_goal[cube.goal_dims[1]] += 0.2  # now 0.044 m off: outside
    assert not rule.success(at_goal, goal, rule.distance(at_goal, goal), radius=10.0)
    assert not rule.success(start.observation, goal, 0.0, radius=10.0)  # the start is not solved
    maze = GoalRule.of_spec(make_env_spec("PointMaze_UMaze-v3"))
    state = np.array([1.0, 2.0, 0.5, 0.5])
    d = maze.distance(state, np.array([1.3, 2.4]))
    assert d == float(np.linalg.norm(state[[0, 1]] - np.array([1.3, 2.4])))  # the old formula
    assert maze.success(state, None, d, radius=0.5) and not maze.success(state, None, d, 0.4)


@pytest.mark.parametrize("env_id", ["cube-double-v0", "scene-v0"])
def test_a_state_at_the_goal_succeeds_and_one_object_off_fails(env_id):
    """Every task: the start is not at the goal; the start with its goal dims set to the goal
    is; then one object moved out of its tolerance (the last cube 0.05 m; the scene's window
    0.05 of its joint) is not."""
    spec = manipspace_spec(env_id)
    rule = GoalRule.of_spec(spec)
    for task in range(1, 6):
        start = spec.task_start(task, seed=task)
        goal = spec.goal_vector(start.goal)
        at_goal = start.observation.copy()
        at_goal[list(spec.goal_dims)] = goal
        assert rule.success(at_goal, goal, rule.distance(at_goal, goal), 0.0)
        assert rule.distance(at_goal, goal) == 0.0
        assert not rule.success(start.observation, goal, 1.0, radius=100.0)
        off = at_goal.copy()
        if spec.scene:
            off[spec.goal_dims[-1]] += 0.05 * 15  # window joint units in the observation
        else:
            off[spec.goal_dims[3 * spec.n_cubes - 3]] += 0.5  # 0.05 m along x
        assert rule.distance(off, goal) == pytest.approx(1.25)
        assert not rule.success(off, goal, rule.distance(off, goal), radius=100.0)


# --- tasks -----------------------------------------------------------------------------------


def test_ogbench_tasks_start_from_exact_seeded_states(cube):
    specs = manipulation_episodes(cube, ["ogbench"], 2, seed=7)
    assert list(specs) == [f"ogbench-task{k}" for k in range(1, 6)]
    tasks = cube.tasks()
    sim = BatchSim(cube, 1)
    for k, (name, episodes) in enumerate(specs.items()):
        assert [e.index for e in episodes] == [0, 1] and {e.task for e in episodes} == {name}
        first, second = episodes
        assert first.seed != second.seed and not np.array_equal(first.physics, second.physics)
        for e in episodes:
            sim.set_state(e.physics[None])
            assert np.array_equal(sim.observe()[0], e.start)
            # The goal is the task's (OGBench permutes cubes; one cube here), in obs units.
            expected = cube.goal_vector(tasks[k].goal)
            assert np.allclose(e.goal, expected, atol=0.0) and e.goal.shape == (3,)
    again = manipulation_episodes(cube, ["ogbench"], 2, seed=7)
    assert all(
        np.array_equal(a.physics, b.physics) and a.seed == b.seed
        for name in specs
        for a, b in zip(specs[name], again[name], strict=True)
    )


def test_maze_tasks_are_refused_on_a_manipulation_env_in_one_line():
    message = one_line_error(lambda: check_manipulation_tasks("cube-single-v0", ["random_goal"]))
    assert "random_goal" in message and "deploy.tasks=[ogbench]" in message
    check_manipulation_tasks("cube-single-v0", ["ogbench"])  # the one that fits


def test_manipulation_ingest_refuses_what_it_cannot_do(tmp_path):
    from stages import ingest

    base = ["ingest.source=ogbench", "ingest.ogbench.env_id=cube-single-v0"]
    paths = Paths(tmp_path / "data")
    cases = {
        "ingest.ogbench.dataset_type=navigate": "play, noisy",
        "ingest.ogbench.path=x.npz": "not found",
        "ingest.ogbench.expert=experts/ant/actor.safetensors": "ant mazes",
    }
    for override, expected in cases.items():
        params = load_params(ROOT / "params.yaml", [*base, override])
        assert expected in one_line_error(lambda p=params: ingest.run(p, paths, progress=False))
    assert not (tmp_path / "data/demos").exists() or not any((tmp_path / "data/demos").iterdir())


@pytest.mark.slow
def test_generating_in_two_processes_gives_the_same_dataset():
    """Each episode is a function of its own seed: workers (each episode after another one than
    in one process) change nothing."""
    from pipeline.sources.ogbench.manipulation import open_manipulation

    def episodes(workers: int):
        data = open_manipulation("cube-single-v0", "play", 3, 25, 4, "d", workers=workers)
        return list(data.episodes)

    one, two = episodes(1), episodes(2)
    assert len(one) == len(two) == 3
    for a, b in zip(one, two, strict=True):
        for name in ("observations", "actions", "physics", "time", "goal_reached"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert not np.array_equal(one[0].actions, one[1].actions)


# --- end to end ------------------------------------------------------------------------------

TRAINED = ("train", "dynamics", "bc", "gcbc")

TINY = [
    "deploy.subgoals.enabled=false",  # the subgoal graph is a maze's (the manipulation overlays)
    "ingest.name=cube",
    "ingest.source=ogbench",
    "ingest.ogbench.env_id=cube-single-v0",
    "ingest.ogbench.dataset_type=play",
    "ingest.episodes=3",
    "ingest.episode_steps=40",
    "segment.window=6",
    "segment.split.train=0.34",
    "segment.split.validation=0.33",
    "segment.split.test=0.33",
    *(f"{s}.{k}" for s in TRAINED for k in ("max_steps=3", "eval_every=3")),
    *(f"{s}.{k}" for s in TRAINED for k in ("hidden=16", "batch_size=8")),
    "train.z_dim=4",
    "train.val_windows=8",
    "train.checkpoint_every=3",
    "train.threads=1",
    *(f"{s}.val_transitions=8" for s in ("dynamics", "bc", "gcbc")),
    "validate.starts=2",
    "validate.skills=2",
    "validate.repeats=1",
    "validate.particles=4",
    "validate.record_starts=1",
    "deploy.tasks=[ogbench]",
    "deploy.agents=[oposm,llp,gcbc]",
    "deploy.episodes=1",
    "deploy.max_steps=6",
    "deploy.planner.horizon=2",
    "deploy.planner.candidates=8",
    "deploy.planner.elites=2",
    "deploy.planner.iterations=2",
    "deploy.llp.horizon=4",
    "deploy.llp.execute=2",
    "deploy.llp.candidates=8",
    "deploy.llp.elites=2",
    "deploy.llp.iterations=2",
    "deploy.record_episodes=1",
]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """Every stage on 3 x 40 steps of cube-single play data, models trained 3 steps; OPOSM, LLP
    and GCBC deployed on one 6-step episode of each task."""
    from stages import bc, deploy, dynamics, gcbc, ingest, segment, train, validate

    params = load_params(ROOT / "params.yaml", TINY)
    paths = Paths(tmp_path_factory.mktemp("manip") / "data")
    ingested = ingest.run(params, paths, progress=False)
    for stage in (segment, train, dynamics, bc, gcbc, validate):
        stage.run(params, paths)
    report = deploy.run(params, paths, progress=False)
    return params, paths, ingested, report


@pytest.mark.slow
def test_cube_single_runs_end_to_end(tiny_run, cube):
    params, paths, ingested, report = tiny_run
    info = read_info(paths.demos("cube"))
    assert (info.env_id, info.physics_dim, info.state_dim, info.action_dim) == (
        "cube-single-v0",
        cube.physics_dim,
        28,
        5,
    )
    assert info.state_names[19:22] == ["cube0_x", "cube0_y", "cube0_z"]
    assert ingested["steps"] == 120 and ingested["n_problems"] == 0
    assert "min_wall_clearance" not in ingested  # no maze geometry in a manipulation report
    validated = json.loads((paths.root / "reports/validate/report.json").read_text())
    assert "real_wall_crossing" not in validated and validated["prior"]["skills_2"]["steps"] == 10
    assert validated["position_unit"] == "observation units"
    assert (paths.root / "recordings/validate.rrd").stat().st_size > 0  # its 3-D view
    assert report["tasks"] == [*(f"ogbench-task{k}" for k in range(1, 6)), "ogbench"]
    assert report["distance_unit"] == "success tolerances" and report["max_steps"] == 6
    rows = json.loads((paths.root / "reports/deploy/episodes.json").read_text())
    assert len(rows) == 3 * 5 and all(r["error"] is None and r["steps"] == 6 for r in rows)
    starts = manipulation_episodes(cube, ["ogbench"], 1, params.deploy.seed)
    for r in rows:  # every agent starts each task from the same exact state
        expected = starts[r["task"]][0]
        assert np.array_equal(r["start"], expected.start) and r["seed"] == expected.seed
        assert np.allclose(r["goal"], expected.goal) and r["min_distance"] > 1.0
    oposm = [r for r in rows if r["agent"] == "oposm"]
    assert all(r["replans"] == 2 for r in oposm)  # tau = window - 1 = 5 steps: replans at 0, 5
    assert all(r["replans"] == 3 for r in rows if r["agent"] == "llp")  # every 2: 0, 2, 4
    recordings = sorted(p.name for p in (paths.root / "recordings/deploy").iterdir())
    assert "overview.rrd" in recordings and "oposm-ogbench-task3-0000.rrd" in recordings
    assert len(recordings) == 16


@pytest.mark.slow
def test_deploy_refuses_maze_only_settings_on_a_manipulation_env(tiny_run):
    from stages import deploy

    params, paths, _, _ = tiny_run
    cases = {
        "deploy.tasks=[ogbench,corners]": "maze tasks",
        "deploy.subgoals.enabled=true": "subgoal graph",
        "deploy.agents=[expert]": "no expert agent",
    }
    for override, expected in cases.items():
        changed = load_params(ROOT / "params.yaml", [*TINY, override])
        assert expected in one_line_error(lambda p=changed: deploy.run(p, paths, progress=False))


@pytest.mark.slow
def test_the_oracle_stage_writes_a_deploy_report_the_manipulation_report_reads(tiny_run):
    from pipeline.reporting.manipulation import collect
    from stages import oracle

    params, paths, _, _ = tiny_run
    run = Paths.for_run(paths.root, "oracle")
    report = oracle.run(params, run)
    assert report["tasks"] == [*(f"ogbench-task{k}" for k in range(1, 6)), "ogbench"]
    written = json.loads(run.report("deploy").read_text())  # no clock: the same bytes every run
    assert "wall_s" not in written and "wall_s" not in written["by_agent"]["oracle"]
    assert json.loads(run.timings("deploy").read_text())["wall_s"] == report["wall_s"]
    assert report["max_steps"] == 200 and report["episodes_per_task"] == 1
    rows = {a["agent"]: a for a in collect(paths.root)["agents"]}
    assert rows["oracle"]["tasks"]["ogbench"]["successes"] == 5  # cube-single: every task


@pytest.mark.slow
def test_the_perfect_model_agent_deploys_and_its_plans_come_true(tiny_run):
    """`oposm_sim` (CEM scored in the simulator) on the same episodes, mean actions: where
    each plan said its first skill would end is where the episode was (float32 rounding)."""
    from stages import deploy

    params, paths, _, _ = tiny_run
    run = Paths.for_run(paths.root, "oposm_sim")
    sim_params = load_params(
        ROOT / "params.yaml", [*TINY, "deploy.agents=[oposm_sim]", "deploy.sample_actions=false"]
    )
    report = deploy.run(sim_params, run, progress=False)
    section = report["by_agent"]["oposm_sim"]
    assert section["settings"]["scored_in"] == "simulator" and section["flops_per_replan"] is None
    for task in (f"ogbench-task{k}" for k in range(1, 6)):
        gap = section["optimism_gap"][task]
        assert gap["replans"] == 1 and gap["position_error_m"]["mean"] < 1e-5
    rows = json.loads((run.root / "reports/deploy/episodes.json").read_text())
    assert len(rows) == 5 and all(r["error"] is None and r["replans"] == 2 for r in rows)
    recordings = run.root / "recordings/deploy"
    assert (recordings / "oposm_sim-ogbench-task1-0000.rrd").stat().st_size > 0


@pytest.mark.slow
def test_oposm_plans_with_a_learned_value_once_oposm_value_has_run(tiny_run):
    """`value.weight > 0`: refused in one line until `oposm value` has written the value; then
    OPOSM's plans are scored with it on the same episodes, and the report says so."""
    from stages import deploy, value

    params, paths, _, _ = tiny_run
    weighted = load_params(
        ROOT / "params.yaml",
        [*TINY, "deploy.agents=[oposm]", "value.weight=0.5", "value.max_steps=4",
         "value.eval_every=2", "value.hidden=16", "value.val_transitions=8",
         "value.eval_horizon=10"],
    )  # fmt: skip
    run = Paths.for_run(paths.root, "valued")
    assert "run `oposm value` first" in one_line_error(
        lambda: deploy.run(weighted, run, progress=False)
    )
    fitted = value.run(weighted, paths)
    assert fitted["steps"] == 4 and len(fitted["history"]) == 2
    headline = json.loads(paths.metrics("value").read_text())
    assert set(headline) == {"val_steps_to_go_mae", "val_steps_to_go_spearman", "val_td_loss"}
    report = deploy.run(weighted, run, progress=False)
    settings = report["by_agent"]["oposm"]["settings"]
    assert settings["value_weight"] == 0.5 and settings["value_skill_steps"] == 5
    rows = json.loads((run.root / "reports/deploy/episodes.json").read_text())
    assert len(rows) == 5 and all(r["error"] is None and r["replans"] == 2 for r in rows)


@pytest.mark.slow
def test_oposm_plans_one_object_at_a_time_and_the_report_says_so(tiny_run):
    """`deploy.object_subtasks`: the same episodes run through, the settings name it, and with
    a single cube (one object) every plan is the one to the whole goal: the same episodes."""
    from stages import deploy

    params, paths, _, _ = tiny_run
    one = load_params(ROOT / "params.yaml", [*TINY, "deploy.agents=[oposm]"])
    split = load_params(
        ROOT / "params.yaml", [*TINY, "deploy.agents=[oposm]", "deploy.object_subtasks=true"]
    )
    whole = deploy.run(one, Paths.for_run(paths.root, "whole"), progress=False)
    report = deploy.run(split, Paths.for_run(paths.root, "objects"), progress=False)
    assert report["by_agent"]["oposm"]["settings"]["object_subtasks"] is True
    assert "object_subtasks" not in whole["by_agent"]["oposm"]["settings"]
    rows = {
        run: json.loads((paths.root / f"runs/{run}/reports/deploy/episodes.json").read_text())
        for run in ("whole", "objects")
    }
    assert len(rows["objects"]) == 5 and all(r["error"] is None for r in rows["objects"])
    assert [r["final_distance"] for r in rows["objects"]] == [
        r["final_distance"] for r in rows["whole"]
    ]
