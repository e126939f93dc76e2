"""Deploy: tasks, batched simulators, success statistics, failure isolation, and the real
`oposm deploy` of all four agents (oposm, llp, gcbc, expert) on tiny trained models with its report
and Rerun recordings read back."""

import json
import shutil

import gymnasium as gym
import numpy as np
import pytest
import torch
import yaml
from factories import planner_config, skill_model_config
from rerun.chunk import RrdReader
from typer.testing import CliRunner

from cli import app
from pipeline.envs.batch import BatchSim
from pipeline.envs.maze.env import layout_cell, make_maze_env
from pipeline.envs.spec import PointMazeSpec
from pipeline.errors import UserError
from pipeline.evaluation.episodes import EpisodeResult, RunConfig, run_episodes
from pipeline.evaluation.proportions import wilson_interval
from pipeline.evaluation.report import format_summary
from pipeline.evaluation.stats import latency_summary, task_summary
from pipeline.evaluation.tasks import EpisodeSpec, MazeTasks, check_goal
from pipeline.model import SkillModel, load_model, save_model
from pipeline.planning import SkillPlanner
from pipeline.planning.mpc import SkillMPC

ENV_ID = "PointMaze_Medium-v3"
runner = CliRunner()


@pytest.fixture(scope="module")
def spec():
    return PointMazeSpec.create(ENV_ID)


@pytest.fixture(scope="module")
def layout(spec):
    return spec.layout


def test_wilson_interval_known_values():
    lo, hi = wilson_interval(95, 100)
    assert (round(lo, 4), round(hi, 4)) == (0.8882, 0.9785)  # statsmodels: (0.88825, 0.97846)
    lo, hi = wilson_interval(100, 100)
    assert round(lo, 4) == 0.9630 and hi == 1.0
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_tasks_follow_their_definitions(layout):
    locations = np.array([[1.5, -0.4], [-2.6, 2.4], [0.2, 0.6]])
    tasks = MazeTasks(layout, locations, start_noise=0.1, seed=3)
    corners = tasks.episodes("corners", 3)
    for spec in corners:  # medium: cell (1, 1) -> cell (6, 6), D4RL's goal
        assert np.allclose(spec.goal, [2.5, -2.5])
        assert np.all(np.abs(spec.start[:2] - [-2.5, 2.5]) <= 0.1)
        assert np.array_equal(spec.start[2:], [0.0, 0.0])
    assert len({s.seed for s in corners}) == 3
    randoms = tasks.episodes("random_goal", 40)
    for spec in randoms:
        assert any(np.array_equal(spec.goal, loc) for loc in locations)
        start_cell = layout_cell(layout, *spec.start[:2])
        assert start_cell != layout_cell(layout, *spec.goal)
        assert list(start_cell) in layout["free_cells"]
    # An episode is the same whatever the number drawn (its seed comes from its index).
    again = tasks.episodes("random_goal", 5)
    assert all(np.array_equal(a.start, b.start) for a, b in zip(again, randoms, strict=False))


def test_bad_goals_and_task_names_are_user_errors(layout):
    with pytest.raises(UserError, match="outside the maze"):
        check_goal(layout, np.array([9.0, 0.0]))
    with pytest.raises(UserError, match="inside a wall"):
        check_goal(layout, np.array([0.0, 3.5]))  # cell (0, 4): the outer wall
    with pytest.raises(UserError, match="unknown task 'fly'"):
        MazeTasks(layout, np.zeros((1, 2))).episodes("fly", 1)
    with pytest.raises(UserError, match="outside the maze"):
        MazeTasks(layout, np.zeros((1, 2)), goal=np.array([0.0, -7.0]))


def test_batch_sim_steps_exactly_like_gymnasium(spec):
    env = make_maze_env(ENV_ID, continuing_task=True, max_episode_steps=10**6)
    env.reset(seed=0)
    pe = env.unwrapped.point_env
    start = np.array([-2.4, 2.3, 0.5, -0.2])
    pe.set_state(start[:2], start[2:])
    batch = BatchSim(spec, 3)
    batch.reset(start[None], rows=[1])
    actions = np.random.default_rng(0).uniform(-1.5, 1.5, size=(300, 2))  # some beyond the clip
    for a in actions:
        obs = env.step(a)[0]["observation"]
        assert batch.step(a[None], rows=[1]) == {}
        assert np.array_equal(batch.observe([1])[0], obs)
    assert np.array_equal(batch.observe([0]), np.zeros((1, 4)))  # other slots untouched
    # One slot's bad action fails that slot only; the state round-trips exactly.
    state = batch.get_state([1])
    bad = np.array([[np.nan, 0.0], [0.3, 0.1]])
    assert list(batch.step(bad, rows=[0, 2])) == [0]
    assert "non-finite action" in batch.step(bad, rows=[0, 2])[0]
    assert not np.array_equal(batch.observe([2]), np.zeros((1, 4)))
    batch.set_state(state, rows=[2])
    assert np.array_equal(batch.get_state([2]), state)
    assert np.array_equal(batch.observe([2]), batch.observe([1]))
    assert isinstance(env, gym.Env)


@pytest.fixture(scope="module")
def small_model() -> SkillModel:
    torch.manual_seed(0)
    model = SkillModel(skill_model_config(4, 2, z_dim=3, hidden=16))
    model.set_normalization([0.0, 0.0, 0.0, 0.0], [2.0, 2.0, 2.0, 2.0], [0.0, 0.0], [0.5, 0.5])
    return model.eval()


def _specs(n: int, layout) -> list[EpisodeSpec]:
    return MazeTasks(layout, np.array([[1.5, -0.4]]), seed=0).episodes("random_goal", n)


def test_a_failing_episode_ends_alone_and_others_are_unchanged(small_model, spec, layout):
    config = planner_config(horizon=3, candidates=8, elites=2, iterations=2, prior_weight=0.0)
    agent = SkillMPC(small_model, SkillPlanner(small_model, config), sample_actions=False)
    run_cfg = RunConfig(max_steps=30, replan_every=10)
    specs = _specs(3, layout)
    clean, _ = run_episodes(agent, BatchSim(spec, 3), specs, run_cfg)
    # A fourth episode whose start velocity is NaN: its planning and simulation cannot go on.
    bad = EpisodeSpec("random_goal", 99, np.array([0.5, 0.5, np.nan, 0.0]), specs[0].goal, 5)
    mixed, calls = run_episodes(agent, BatchSim(spec, 2), [*specs, bad], run_cfg)
    assert [c.envs for c in calls][:2] == [2, 2]  # waves of two environments
    assert mixed[3].error is not None and "non-finite" in mixed[3].error
    for a, b in zip(clean, mixed[:3], strict=True):
        assert a.error is None and b.error is None
        assert a.steps == b.steps == 30
        assert np.allclose(np.array(a.trace.states), np.array(b.trace.states), atol=1e-6)


TINY = {
    "ingest": {"name": "tiny", "episodes": 6, "episode_steps": 150, "seed": 1},
    "segment": {"window": 11},
    "train": {"z_dim": 4, "hidden": 32, "batch_size": 32, "max_steps": 30, "eval_every": 10},
    "dynamics": {"hidden": 16, "max_steps": 30, "eval_every": 15, "val_transitions": 200},
    "bc": {"hidden": 16, "max_steps": 30, "eval_every": 15, "val_transitions": 200},
    "gcbc": {"hidden": 16, "max_steps": 30, "eval_every": 15, "val_transitions": 200},
    "deploy": {
        "agents": ["oposm", "llp", "gcbc", "expert"],
        "tasks": ["random_goal", "corners"],
        "episodes": 3,
        "num_envs": 2,
        "max_steps": 40,
        "record_episodes": 2,
        "planner": {"horizon": 3, "candidates": 16, "elites": 4, "iterations": 3},
        "llp": {"horizon": 6, "execute": 3, "candidates": 16, "elites": 4, "iterations": 2},
    },
}
AGENTS = TINY["deploy"]["agents"]


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """Tiny real data, tiny trained models and a deploy run, all through the real CLI."""
    root = tmp_path_factory.mktemp("deploy")
    (root / "params.yaml").write_text(yaml.safe_dump(TINY))
    common = ["--params", str(root / "params.yaml"), "--data", str(root / "data")]
    # One torch thread: on a loaded 2-core machine, 2 intra-op threads made this 20x slower.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for command in ("ingest", "segment", "train", "dynamics", "bc", "gcbc", "deploy"):
            result = runner.invoke(app, [command, *common])
            assert result.exit_code == 0, result.output
    finally:
        torch.set_num_threads(threads)
    return root, common, result.output


def test_deploy_writes_a_valid_report_and_prints_a_summary(project):
    root, _, output = project
    report = json.loads((root / "data/reports/deploy/report.json").read_text())
    assert report["episodes"] == 24 and report["tasks"] == ["random_goal", "corners"]
    assert report["agents"] == AGENTS and list(report["by_agent"]) == AGENTS
    for agent in AGENTS:
        assert f"  {agent} (" in output
        for task in ("random_goal", "corners"):
            t = report["by_agent"][agent][task]
            assert t["episodes"] == 3 and t["errors"] == 0
            assert 0 <= t["success_ci95_low"] <= t["success_rate"] <= t["success_ci95_high"] <= 1
            assert t["success_rate_r045"] <= t["success_rate"]
    oposm, llp = report["by_agent"]["oposm"], report["by_agent"]["llp"]
    # Waves of 2 envs; replan every T = 10 steps (window 11) for 40 steps: 4 replans per wave;
    # LLP every `execute` = 3 steps: 14 per wave. Static agents never plan.
    assert oposm["replan_every"] == 10 and oposm["planning"]["calls"] >= 4
    assert llp["replan_every"] == 3 and llp["planning"]["calls"] >= 14
    timings = json.loads((root / "data/timings/deploy.json").read_text())["by_agent"]
    for agent, r in (("oposm", oposm), ("llp", llp)):  # wall-clock: beside the report, not in it
        latency = timings[agent]["planning"]["per_env_latency_s"]
        assert 0 < latency["p50"] <= latency["p95"] and r["flops_per_replan"] > 0
        assert "per_env_latency_s" not in r["planning"] and "wall_s" not in r
    # LLP: 2 iterations x 16 candidates x 6 steps of BC + dynamics; OPOSM: 3 x 16 x 3 skills.
    assert llp["flops_per_replan"] != oposm["flops_per_replan"]
    for agent in ("gcbc", "expert"):
        assert report["by_agent"][agent]["planning"]["calls"] == 0
        assert report["by_agent"][agent]["flops_per_replan"] is None
        assert report["by_agent"][agent]["optimism_gap"] is None
    # Optimism gap after one skill (OPOSM: plan state 1, 10 steps) or 3 actions (LLP: state 3).
    assert oposm["optimism_gap"]["corners"]["steps_ahead"] == 10
    assert llp["optimism_gap"]["random_goal"]["plan_state"] == 3
    assert oposm["optimism_gap"]["corners"]["position_error_m"]["mean"] > 0
    assert "optimism" in output and report["disturbance"] == {"probability": 0.0, "impulse": 0.0}
    compared = report["oposm_vs_llp"]
    assert "corners" in compared and "replan_s_p50" not in compared
    assert (
        timings
        and json.loads((root / "data/timings/deploy.json").read_text())["oposm_vs_llp"][
            "replan_s_p50"
        ]["llp_over_oposm"]
        > 0
    )
    rows = json.loads((root / "data/reports/deploy/episodes.json").read_text())
    assert len(rows) == 24 and {r["agent"] for r in rows} == set(AGENTS)
    assert not any("plan_seconds" in r for r in rows)
    # Every agent ran the same episodes: same starts, goals and seeds.
    by_agent = {a: [(r["task"], r["seed"], r["start"], r["goal"]) for r in rows if r["agent"] == a]
                for a in AGENTS}  # fmt: skip
    assert all(by_agent[a] == by_agent["oposm"] for a in AGENTS)
    assert "recordings" in output and "95 % CI" in output and "oposm vs llp" in output
    headline = json.loads((root / "metrics/deploy.json").read_text())
    assert set(headline) == set(AGENTS) and "success" in headline["llp"]["corners"]
    assert "plan_s_p50" not in headline["oposm"]


@pytest.mark.slow  # spawns worker processes, each loading torch and MuJoCo
def test_episodes_are_the_same_bytes_on_one_process_or_several(project, tmp_path):
    """deploy.workers only spreads the (agent, task) jobs over processes: one process and three
    (spawned, each building its own agents) write the reports the fixture's run wrote, byte for
    byte (the recordings are not compared: Rerun stamps each with its own id and time)."""
    root, _, _ = project
    written = ["reports/deploy/episodes.json", "reports/deploy/report.json"]  # DVC's outs
    for workers in (1, 3):
        data = tmp_path / f"data-{workers}"
        shutil.copytree(root / "data", data, ignore=shutil.ignore_patterns("recordings"))
        args = ["deploy", "--params", str(root / "params.yaml"), "--data", str(data),
                "-S", f"deploy.workers={workers}"]  # fmt: skip
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
        for name in written:  # the report names the data folder's models and recordings
            ours = (data / name).read_bytes().replace(bytes(data), bytes(root / "data"))
            assert ours == (root / "data" / name).read_bytes(), name


def test_a_killed_deploy_resumes_from_its_finished_jobs_with_the_same_bytes(
    project, tmp_path, monkeypatch
):
    """A deploy killed after three of its eight (agent, task) jobs, run again, runs only the
    five others and writes the reports the uninterrupted run wrote, byte for byte; once they
    are written, the finished jobs are deleted."""
    from stages.deploy_jobs import Runner

    root, _, _ = project
    assert not list((root / "data/scratch/deploy").glob("*")), "the fixture's run left jobs"
    data = tmp_path / "data"
    shutil.copytree(root / "data", data, ignore=shutil.ignore_patterns("recordings"))
    args = ["deploy", "--params", str(root / "params.yaml"), "--data", str(data),
            "-S", "deploy.workers=1"]  # fmt: skip
    ran = []
    real_run = Runner.run

    def run(self, job, progress, position=None):
        if len(ran) == 3 and kill:
            raise RuntimeError("killed")
        ran.append((job.agent, job.task))
        return real_run(self, job, progress, position)

    monkeypatch.setattr(Runner, "run", run)
    kill = True
    assert runner.invoke(app, args).exit_code != 0
    assert len(list((data / "scratch/deploy").iterdir())) == 3
    first = list(ran)
    kill, ran[:] = False, []
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert len(ran) == 5 and not set(ran) & set(first)
    for name in ("reports/deploy/episodes.json", "reports/deploy/report.json"):
        ours = (data / name).read_bytes().replace(bytes(data), bytes(root / "data"))
        assert ours == (root / "data" / name).read_bytes(), name
    assert not list((data / "scratch/deploy").iterdir())


def test_recordings_load_back_with_rerun(project):
    root, _, _ = project
    files = sorted((root / "data/recordings/deploy").glob("*.rrd"))
    assert (root / "data/recordings/deploy/overview.rrd") in files  # every agent's episodes
    assert [f.stem for f in files if f.stem != "overview"] == [
        f"{agent}-{task}-{k:04d}"
        for agent in sorted(AGENTS) for task in ("corners", "random_goal") for k in (0, 1)
    ]  # fmt: skip
    rows = {r["agent"] + r["task"] + str(r["episode"]): r for r in json.loads(
        (root / "data/reports/deploy/episodes.json").read_text())}  # fmt: skip
    reader = RrdReader(root / "data/recordings/deploy/oposm-corners-0000.rrd")
    assert [r.recording_id for r in reader.recordings()] == ["oposm-corners-0000"]
    assert len(reader.blueprints()) == 1  # the default layout travels with the file
    store = reader.store()
    schema = store.schema()
    entities = set(schema.entity_paths())
    for entity in (
        "/maze/walls", "/task/start", "/task/goal", "/agent/position", "/agent/path",
        "/plan/states", "/metrics/distance_to_goal", "/metrics/plan_cost", "/metrics/action/fx",
    ):  # fmt: skip
        assert entity in entities, entity
    assert {c.name for c in schema.index_columns()} >= {"step", "sim_time"}
    # One distance per state s_0..s_n, one plan per replan.
    chunks = list(store.stream())
    temporal = [c for c in chunks if not c.is_static]  # static rows: the series' colour, name
    distance_rows = sum(c.num_rows for c in temporal if c.entity_path.endswith("to_goal"))
    plan_rows = sum(c.num_rows for c in chunks if c.entity_path == "/plan/states")
    row = rows["oposmcorners0"]
    assert distance_rows == row["steps"] + 1 and plan_rows == row["replans"]
    # LLP's recording draws its predicted low-level path (one point per planned action).
    store = RrdReader(root / "data/recordings/deploy/llp-corners-0000.rrd").store()
    chunks = list(store.stream())
    plan_rows = sum(c.num_rows for c in chunks if c.entity_path == "/plan/path")
    assert plan_rows == rows["llpcorners0"]["replans"] > 0
    static = RrdReader(root / "data/recordings/deploy/gcbc-corners-0000.rrd").store()
    assert "/plan/path" not in set(static.schema().entity_paths())


def test_view_lists_the_recordings(project):
    root, _, _ = project
    result = runner.invoke(app, ["view", str(root / "data/recordings/deploy"), "--dry-run"])
    assert result.exit_code == 0 and result.output.count(".rrd") == 16 + 1  # and the overview
    assert "-m rerun" in result.output


def _one_line_error(result) -> str:
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    return lines[0]


def test_bad_deploy_inputs_are_one_line_errors(project, tmp_path):
    root, common, _ = project
    line = _one_line_error(runner.invoke(app, ["deploy", *common, "-S", "deploy.tasks=[fly]"]))
    assert "deploy.tasks" in line
    args = ["deploy", *common, "-S", "deploy.tasks=[goal]", "-S", "deploy.goal=[9.0, 0.0]"]
    assert "outside the maze" in _one_line_error(runner.invoke(app, args))
    assert "no recordings" in _one_line_error(runner.invoke(app, ["view", str(tmp_path)]))
    line = _one_line_error(runner.invoke(app, ["deploy", *common, "-S", "deploy.agents=[llm]"]))
    assert "deploy.agents" in line and "'oposm', 'oposm_sim', 'llp', 'gcbc' or 'expert'" in line
    args = ["deploy", *common, "-S", "deploy.device=cpu", "-S", "deploy.planner.kernel=triton"]
    assert "deploy.planner.kernel=torch" in _one_line_error(runner.invoke(app, args))
    args = ["deploy", *common, "-S", "deploy.object_subtasks=true"]
    assert "deploy.object_subtasks=false" in _one_line_error(runner.invoke(app, args))
    # A checkpoint whose states are not the maze's [x, y, vx, vy].
    model, meta = load_model(root / "data/models/tiny")
    wrong = SkillModel(skill_model_config(6, 2, z_dim=4, hidden=32))
    data = tmp_path / "data"
    save_model(wrong, data / "models/tiny", {k: v for k, v in meta.items() if k != "model"})
    (data / "segments").mkdir(parents=True)
    (data / "segments/tiny").symlink_to(root / "data/segments/tiny")
    line = _one_line_error(
        runner.invoke(app, ["deploy", "--params", str(root / "params.yaml"), "--data", str(data)])
    )
    assert "state_dim 6" in line


def test_model_from_another_maze_than_the_segments_is_a_one_line_error(project, tmp_path):
    """A model trained in UMaze with segments of Medium (same dataset name) must not run: goals
    drawn from Medium's data would lie inside UMaze's walls."""
    root, _, _ = project
    data = tmp_path / "data"
    shutil.copytree(root / "data/models", data / "models")
    (data / "segments").mkdir(parents=True)
    (data / "segments/tiny").symlink_to(root / "data/segments/tiny")
    config = data / "models/tiny/config.json"
    meta = json.loads(config.read_text())
    meta["info"]["env_id"] = "PointMaze_UMaze-v3"
    config.write_text(json.dumps(meta))
    args = ["deploy", "--params", str(root / "params.yaml"), "--data", str(data)]
    line = _one_line_error(runner.invoke(app, args))
    assert "trained on 'PointMaze_UMaze-v3'" in line and "PointMaze_Medium-v3" in line


def test_summary_without_any_success_says_so():
    spec = EpisodeSpec("corners", 0, np.zeros(4), np.ones(2), 0)
    failed = EpisodeResult(spec, steps=2000, min_distance=2.0, final_distance=2.5)
    agent = {"corners": task_summary([failed], 0.01, [600]), "planning": latency_summary([]),
             "wall_s": 1.0, "flops_per_replan": None}  # fmt: skip
    report = {
        "dataset": "d", "env_id": ENV_ID, "agents": ["gcbc"], "episodes": 1, "wall_s": 1.0,
        "max_steps": 2000, "device": "cpu", "tasks": ["corners"], "success_radius": 0.5,
        "by_agent": {"gcbc": agent}, "recordings": "data/recordings/deploy",
        "recorded_episodes": 0,
    }  # fmt: skip
    line = format_summary(report).splitlines()[2]
    assert "no episode reached the goal" in line and "None" not in line
    assert "0.0 % within 600 steps" in line
    assert "within 0.5 m" in line


def test_summary_of_object_goals_speaks_in_success_tolerances():
    spec = EpisodeSpec("ogbench-task1", 0, np.zeros(4), np.ones(2), 0)
    won = EpisodeResult(spec, steps=90, min_distance=0.5, final_distance=0.5, steps_to_goal=90)
    gap = {"ogbench-task1": {"distance_gap_m": {"mean": 0.25, "ci95": [0.1, 0.4]}}}
    agent = {"ogbench-task1": task_summary([won], 0.05), "planning": latency_summary([]),
             "wall_s": 1.0, "flops_per_replan": None, "optimism_gap": gap}  # fmt: skip
    report = {
        "dataset": "d", "env_id": "cube-single-v0", "agents": ["oposm"], "episodes": 1,
        "wall_s": 1.0, "max_steps": 200, "device": "cpu", "tasks": ["ogbench-task1"],
        "success_radius": 0.5, "by_agent": {"oposm": agent}, "recordings": "r",
        "recorded_episodes": 0, "distance_unit": "success tolerances",
    }  # fmt: skip
    text = format_summary(report)
    assert "by the environment's success rule" in text and " m " not in text
    assert "+0.250 success tolerances [+0.100, +0.400]" in text


def test_an_agent_without_its_model_names_the_stage_to_run(project, tmp_path):
    root, _, _ = project
    data = tmp_path / "data"
    shutil.copytree(root / "data/models/tiny", data / "models/tiny")
    (data / "segments").mkdir(parents=True)
    (data / "segments/tiny").symlink_to(root / "data/segments/tiny")
    base = ["deploy", "--params", str(root / "params.yaml"), "--data", str(data), "-S"]
    line = _one_line_error(runner.invoke(app, [*base, "deploy.agents=[oposm,llp]"]))
    assert line.startswith("error: agent llp: no dynamics model") and "`oposm dynamics`" in line
    shutil.copytree(root / "data/models/tiny-dynamics", data / "models/tiny-dynamics")
    line = _one_line_error(runner.invoke(app, [*base, "deploy.agents=[llp]"]))
    assert "agent llp: no bc policy" in line and "run `oposm bc` first" in line
    line = _one_line_error(runner.invoke(app, [*base, "deploy.agents=[gcbc]"]))
    assert "agent gcbc: no gcbc policy" in line and "run `oposm gcbc` first" in line


def test_optimism_gap_is_real_minus_predicted_distance_where_the_executed_plan_ends():
    """Plans that predict the agent 0.3 m closer to the goal than it gets: gap +0.3 m; exact
    plans: 0; replans whose executed part runs past the episode's end are left out."""
    from pipeline.evaluation.episodes import EpisodeResult
    from pipeline.evaluation.stats import optimism_gap
    from pipeline.evaluation.tasks import EpisodeSpec

    def episode(offset: float, seed: int) -> EpisodeResult:
        goal = np.array([10.0, 0.0])
        r = EpisodeResult(EpisodeSpec("goal", seed, np.zeros(4), goal, seed))
        r.trace.states = [np.array([0.1 * t, 0.0, 0.0, 0.0]) for t in range(26)]  # 0.1 m/step
        for t in range(0, 26, 10):  # replans at 0, 10, 20; skills of 5 steps, 2 per replan
            plan = [np.array([0.1 * (t + 5 * k) + offset * (k > 0), 0.0, 0, 0]) for k in range(4)]
            r.trace.replan_steps.append(t)
            r.trace.plans.append(np.stack(plan))
        return r

    optimistic = optimism_gap([episode(0.3, 0), episode(0.3, 1)], 5, 10, (0, 1))
    assert optimistic["plan_state"] == 2 and optimistic["steps_ahead"] == 10
    assert optimistic["replans"] == 4  # the replan at 20 would end at step 30 > 25
    assert optimistic["distance_gap_m"]["mean"] == pytest.approx(0.3)
    assert optimistic["position_error_m"]["mean"] == pytest.approx(0.3)
    exact = optimism_gap([episode(0.0, 0), episode(0.0, 1)], 5, 10, (0, 1))
    assert exact["distance_gap_m"]["mean"] == pytest.approx(0.0, abs=1e-12)
