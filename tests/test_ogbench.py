"""OGBench mazes: the spec against the real gymnasium env, layout, tasks, oracle, source, import."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
import yaml
from factories import one_line_error
from typer.testing import CliRunner

from cli import app
from pipeline.envs.batch import BatchSim
from pipeline.envs.maze.env import layout_cell
from pipeline.envs.ogbench import (
    OGBENCH_MAZES,
    make_ogbench_env,
    ogbench_cell,
    ogbench_cell_xy,
    ogbench_tasks,
)
from pipeline.envs.ogbench_oracle import BFSOracle, OGBenchOracleAgent
from pipeline.envs.physics import PHYSICS_SPEC
from pipeline.envs.spec import make_env_spec
from pipeline.errors import UserError
from pipeline.evaluation.episodes import RunConfig, run_episodes
from pipeline.evaluation.tasks import MazeTasks
from pipeline.recording import read_info
from pipeline.sources.ogbench import (
    check_ogbench_dataset,
    generate_ogbench,
    make_recipe,
    read_ogbench,
    write_ogbench_npz,
)
from pipeline.viz.dataset import write_dataset_view

POINT = "pointmaze-medium-v0"
ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()


def _walk_into_walls(rng: np.random.Generator, n: int) -> np.ndarray:
    """`[n, 2]` actions that push in one direction for 20 steps at a time (so into walls),
    with a few out of [-1, 1] (the spec clips them as OGBench's evaluation does)."""
    directions = rng.uniform(-1, 1, (n // 20 + 1, 2))
    actions = np.repeat(directions, 20, axis=0)[:n] + rng.normal(0, 0.2, (n, 2))
    actions[::50] *= 3.0
    return actions


@pytest.mark.parametrize("env_id", ["pointmaze-medium-v0", "pointmaze-giant-v0"])
def test_point_spec_steps_bit_for_bit_like_the_gymnasium_env(env_id: str) -> None:
    """From the env's reset observation, `BatchSim` (set_observation + control_step + observe)
    reproduces `env.step` exactly over 3000 steps that press on walls again and again."""
    spec = make_env_spec(env_id)
    env = make_ogbench_env(env_id, max_episode_steps=10**6, terminate_at_goal=False)
    ob, _ = env.reset(seed=3, options={"task_id": 1})
    sim = BatchSim(spec, 1)
    sim.reset(ob[None])
    rng = np.random.default_rng(0)
    blocked = 0
    for action in _walk_into_walls(rng, 3000):
        before = ob
        ob, *_ = env.step(np.clip(action, -1, 1))  # OGBench's evaluation clips, the env does not
        assert sim.step(action[None]) == {}
        np.testing.assert_array_equal(sim.observe()[0], ob)
        free = before + 0.2 * np.clip(action, -1, 1)
        blocked += not np.allclose(ob, free, atol=1e-9)
    assert blocked > 100  # the walls really were hit (the contact path is covered)
    assert spec.state_dim == 2 and spec.action_dim == 2 and spec.physics_dim == 5
    assert spec.dt == pytest.approx(0.1) and spec.max_episode_steps == 1000
    assert spec.goal_dims == (0, 1) and spec.goal_tolerance == 1.0


def test_point_moves_by_a_fifth_of_the_action_in_free_space() -> None:
    spec = make_env_spec(POINT)
    sim = BatchSim(spec, 1)
    start = ogbench_cell_xy((3, 3))  # the centre of a free cell: 2 m from any wall
    sim.reset(start[None])
    sim.step(np.array([[0.5, -1.0]]))
    np.testing.assert_allclose(sim.observe()[0], start + [0.1, -0.2], atol=1e-12)


def test_ant_spec_steps_bit_for_bit_like_the_gymnasium_env() -> None:
    spec = make_env_spec("antmaze-medium-v0")
    env = make_ogbench_env("antmaze-medium-v0", max_episode_steps=10**6, terminate_at_goal=False)
    ob, _ = env.reset(seed=1, options={"task_id": 2})
    sim = BatchSim(spec, 1)
    sim.reset(ob[None])
    rng = np.random.default_rng(1)
    for _ in range(300):
        action = rng.uniform(-1, 1, 8)
        ob, *_ = env.step(action)
        sim.step(action[None])
        np.testing.assert_array_equal(sim.observe()[0], ob)
    assert (spec.state_dim, spec.action_dim, spec.physics_dim) == (29, 8, 30)
    assert spec.goal_tolerance == 0.5


class _StillAgent:
    """Zero torques: an upright ant stays up, an upside-down one stays down."""

    name = "still"

    def reset(self, goals, seeds) -> None:
        pass

    def act(self, rows, states):
        return np.zeros((len(rows), 8))


def test_deploy_reports_the_step_an_ant_fell_at() -> None:
    """Episodes record the first step the ant is fallen (upside down or torso out of OGBench's
    healthy height), and the task summary counts them; an upright ant is never counted."""
    from pipeline.evaluation.stats import task_summary
    from pipeline.evaluation.tasks import EpisodeSpec

    spec = make_env_spec("antmaze-medium-v0")
    upright = spec.start_observation(ogbench_cell_xy((1, 1)))
    flipped = upright.copy()
    flipped[2], flipped[3:7] = 0.6, [0.0, 1.0, 0.0, 0.0]  # 180 degrees about x
    assert spec.fallen(np.stack([upright, flipped])).tolist() == [False, True]
    both = torch.tensor(np.stack([upright, flipped]), dtype=torch.float32)[None]  # [1, 2, 29]
    assert spec.fallen(both).tolist() == [[False, True]]  # predicted states, for the planner
    low = upright.copy()
    low[2] = 0.1
    assert spec.fallen(low[None]).tolist() == [True]
    goal = ogbench_cell_xy((6, 6))
    specs = [EpisodeSpec("goal", i, s, goal, i) for i, s in enumerate([upright, flipped])]
    results, _ = run_episodes(_StillAgent(), BatchSim(spec, 2), specs, RunConfig(20, None, 0.5))
    assert [r.fell_at for r in results] == [None, 1]
    assert [r.to_json()["fell_at"] for r in results] == [None, 1]
    assert task_summary(results, spec.dt)["fallen"] == 1
    assert not hasattr(make_env_spec(POINT), "fallen")  # the point cannot fall


def test_layout_matches_ogbench_cells_and_walls() -> None:
    """Every OGBench cell's centre falls in the layout cell of the same kind (free / wall), so
    views, tasks and checks see OGBench's maze; `ogbench_cell` inverts `ogbench_cell_xy`."""
    for env_id in ("pointmaze-medium-v0", "pointmaze-large-v0", "pointmaze-giant-v0"):
        spec = make_env_spec(env_id)
        layout = spec.layout
        maze_map = np.asarray(make_ogbench_env(env_id).unwrapped.maze_map)
        assert layout["ogbench_maze_map"] == maze_map.tolist()
        assert len(layout["free_cells"]) == int((maze_map == 0).sum())
        for (i, j), value in np.ndenumerate(maze_map):
            xy = ogbench_cell_xy((i, j))
            row, col = layout_cell(layout, *xy)
            assert layout["maze_map"][row][col] == value
            assert ogbench_cell(xy) == (i, j)
        xmin, xmax, ymin, ymax = layout["bounds"]
        assert (xmin, ymin) == (-6.0, -6.0)
        assert (xmax, ymax) == (4 * maze_map.shape[1] - 6, 4 * maze_map.shape[0] - 6)


def test_unsupported_ids_are_one_line_user_errors() -> None:
    for bad in ("pointmaze-huge-v0", "humanoidmaze-medium-v0"):
        with pytest.raises(UserError) as err:
            make_env_spec(bad)
        message = str(err.value)
        assert "\n" not in message and "pointmaze-medium-v0" in message
    assert set(OGBENCH_MAZES) >= {
        f"{loco}maze-{size}-v0"
        for loco in ("point", "ant")
        for size in ("medium", "large", "giant", "teleport")
    }


class _NumpyLegacy:
    """A slot generator drawing as `np.random.randint` does (OGBench's teleport draw)."""

    def __init__(self, seed: int):
        self.state = np.random.RandomState(seed)

    def integers(self, n: int) -> int:
        return int(self.state.randint(n))


def _drive_into_teleports(env, spec) -> None:
    """Step OGBench's env and a `BatchSim` slot side by side into each inbound teleport in
    turn (8 times, from a cell beside it), checking every observation."""
    maze = env.unwrapped
    sim = BatchSim(spec, 1)
    sim.seed_slots([0])
    sim._push_rngs[0] = _NumpyLegacy(7)
    oracle = BFSOracle("pointmaze-teleport-v0")
    beside = [np.array([20.0, 8.0]), np.array([0.0, 12.0])]  # a cell next to each inbound
    landed = []
    for trial in range(8):
        maze.set_xy(beside[trial % 2])
        state = np.empty(spec.physics_dim)
        mujoco.mj_getState(maze.model, maze.data, state, PHYSICS_SPEC)
        sim.set_state(state[None])
        ob = maze.get_xy()
        for _ in range(60):
            direction = oracle.direction(maze.get_xy(), spec.teleports.inbound[trial % 2])
            before = ob
            ob, *_ = env.step(direction)
            assert sim.step(direction[None]) == {}
            np.testing.assert_array_equal(sim.observe()[0], ob)
            if np.linalg.norm(ob - before) > 1.0:  # moved: the step after the teleport
                landed.append(int(np.argmin(np.linalg.norm(spec.teleports.outbound - ob, axis=1))))
                break
    assert len(landed) == 8 and set(landed) == {0, 1, 2}


def test_teleport_maze_steps_bit_for_bit_like_ogbench_with_the_same_draws() -> None:
    """pointmaze-teleport-v0: driven into an inbound teleport again and again, `BatchSim` (its
    teleport deferred to the next step, drawing from the slot's generator) gives OGBench's
    observations exactly when both generators are seeded alike; every outbound is reached."""
    spec = make_env_spec("pointmaze-teleport-v0")
    assert spec.teleports is not None and spec.teleports.reach == 1.5
    env = make_ogbench_env("pointmaze-teleport-v0", max_episode_steps=10**6)
    env.reset(seed=3, options={"task_id": 1})
    previous = np.random.get_state()  # OGBench draws the destination from numpy's global
    np.random.seed(7)  # generator (restored after: other tests' resets draw from it)
    try:
        _drive_into_teleports(env, spec)
    finally:
        np.random.set_state(previous)
    unseeded = BatchSim(spec, 1)
    unseeded.reset(spec.teleports.inbound[:1])
    assert unseeded.step(np.zeros((1, 2))) == {}  # a reset at a teleport moves nothing ...
    with pytest.raises(RuntimeError, match="seed_slots"):  # ... a step that ends there does
        unseeded.step(np.zeros((1, 2)))


def test_teleport_data_passes_the_checks_and_replays() -> None:
    """Generated teleport-maze data: teleport steps are exempt from the jump check (the same
    jump elsewhere is not), recorded states hold their observations and replay exactly."""
    env_id = "pointmaze-teleport-v0"
    data = generate_ogbench(make_recipe(env_id, "navigate", 8, 501, seed=5), "gen")
    episodes = list(data.episodes)
    spec = make_env_spec(env_id)
    report = check_ogbench_dataset(episodes, data.info)
    assert report.problems == [] and report.max_step_distance < 1.0
    ep = episodes[1]  # starts at an inbound teleport (a reset there moves nothing) ...
    at = np.flatnonzero(spec.teleports.inside(ep.observations[:-1]))
    assert at[0] == 0 and np.linalg.norm(ep.observations[1] - ep.observations[0]) < 0.3
    t = int(at[1])  # ... then a step ends at one: the next step starts at an outbound
    assert np.linalg.norm(ep.observations[t + 1] - ep.observations[t]) > 3.0
    sim = BatchSim(spec, len(ep) - 1)
    sim.reset(ep.observations[:1], [0])
    sim.set_state(ep.physics[1:-1], range(1, len(ep) - 1))  # states a step led to
    sim.seed_slots(range(len(ep) - 1))
    assert sim.step(ep.actions[:-1]) == {}
    got = sim.observe()
    moved = at[1:]  # each lands a step from an outbound teleport (the slot's own draw) ...
    to_out = np.linalg.norm(got[moved, None] - spec.teleports.outbound, axis=-1).min(axis=1)
    assert (to_out < 0.3).all()
    rest = np.setdiff1d(np.arange(len(ep) - 1), moved)  # ... every other step as recorded
    np.testing.assert_array_equal(got[rest], ep.observations[1:][rest])
    jumped = [dataclasses.replace(ep, observations=ep.observations.copy(), physics=None)]
    jumped[0].observations[t + 2 :] += 8.0  # the same kind of jump, not from a teleport
    assert any("jumps" in p for p in check_ogbench_dataset(jumped, data.info).problems)


def test_tasks_are_ogbenchs() -> None:
    tasks = ogbench_tasks(POINT)
    assert [t["name"] for t in tasks] == [f"task{k}" for k in range(1, 6)]
    assert tasks[0]["init_ij"] == (1, 1) and tasks[0]["goal_ij"] == (6, 6)
    np.testing.assert_array_equal(tasks[0]["goal_xy"], [20.0, 20.0])


# --- tasks and the oracle -------------------------------------------------------------------


def _tasks(env_id: str = POINT, seed: int = 0) -> MazeTasks:
    spec = make_env_spec(env_id)
    return MazeTasks(spec.layout, np.zeros((0, 2)), 0.1, None, seed, spec.start_observation, env_id)


def test_ogbench_task_episodes_follow_ogbenchs_cells_and_noise() -> None:
    specs = _tasks().expand(["ogbench"], 40)
    assert list(specs) == [f"ogbench-task{k}" for k in range(1, 6)]
    for info, (name, episodes) in zip(ogbench_tasks(POINT), specs.items(), strict=True):
        starts = np.stack([e.start for e in episodes])
        goals = np.stack([e.goal for e in episodes])
        assert starts.shape == (40, 2) and goals.shape == (40, 2)  # the point's state is x, y
        assert np.abs(starts - info["init_xy"]).max() <= 1.0  # OGBench's add_noise: +-1
        assert np.abs(goals - info["goal_xy"]).max() <= 1.0
        assert np.abs(goals - info["goal_xy"]).max() > 0.8  # the noise is really there
        assert all(e.task == name for e in episodes)
    again = _tasks().expand(["ogbench"], 3)["ogbench-task2"]
    np.testing.assert_array_equal(again[2].start, specs["ogbench-task2"][2].start)
    other = _tasks(seed=1).expand(["ogbench"], 3)["ogbench-task2"]
    assert not np.array_equal(other[2].start, again[2].start)


def test_ogbench_task_outside_an_ogbench_maze_is_a_user_error() -> None:
    spec = make_env_spec("PointMaze_Medium-v3")
    tasks = MazeTasks(spec.layout, np.zeros((0, 2)), 0.1, None, 0, spec.start_observation, "")
    with pytest.raises(UserError, match="OGBench maze"):
        tasks.expand(["ogbench"], 2)


def test_oracle_memo_agrees_with_ogbenchs_bfs_everywhere() -> None:
    """The memoized subgoal equals OGBench's `get_oracle_subgoal` at random free positions."""
    spec = make_env_spec("pointmaze-large-v0")
    oracle = BFSOracle("pointmaze-large-v0")
    maze = make_ogbench_env("pointmaze-large-v0").unwrapped
    centers = np.asarray(spec.layout["free_cell_centers"])
    rng = np.random.default_rng(0)
    for _ in range(400):
        xy = centers[rng.integers(len(centers))] + rng.uniform(-1.9, 1.9, 2)
        goal = centers[rng.integers(len(centers))] + rng.uniform(-1.9, 1.9, 2)
        expected, _ = maze.get_oracle_subgoal(xy, goal)
        np.testing.assert_array_equal(oracle.subgoal(xy, goal), expected)
        d = oracle.direction(xy, goal)
        assert np.linalg.norm(d) == pytest.approx(1.0, abs=1e-5) or np.allclose(d, 0, atol=1e-5)


def test_oracle_agent_solves_the_ogbench_tasks() -> None:
    """OGBench's data-generating oracle (noise 0.5) reaches the goal in (nearly) every episode
    of the medium maze's five tasks within 1000 steps, judged within 1.0 as OGBench does."""
    spec = make_env_spec(POINT)
    specs = [e for eps in _tasks().expand(["ogbench"], 4).values() for e in eps]
    agent = OGBenchOracleAgent(POINT, noise=0.5)
    results, _ = run_episodes(agent, BatchSim(spec, len(specs)), specs, RunConfig(1000, None, 1.0))
    assert sum(r.success for r in results) >= 19
    assert all(r.error is None for r in results)
    with pytest.raises(UserError, match="ant expert"):
        OGBenchOracleAgent("antmaze-medium-v0")


# --- the ogbench source: generation, .npz import, bad input ---------------------------------


@pytest.fixture(scope="module")
def generated():
    """4 navigate episodes x 301 steps in the medium maze, by OGBench's recipe."""
    recipe = make_recipe(POINT, "navigate", 4, 301, seed=5)
    data = generate_ogbench(recipe, "gen")
    return data.info, list(data.episodes)


def test_generated_data_follows_the_recipe(generated) -> None:
    info, episodes = generated
    assert info.source == "ogbench" and info.env_id == POINT and info.state_names == ["x", "y"]
    assert info.generator["noise"] == 0.5 and info.generator["dataset_type"] == "navigate"
    assert [len(e) for e in episodes] == [301] * 4
    report = check_ogbench_dataset(episodes, info)
    assert report.problems == [] and report.n_steps == 4 * 301
    assert report.goals_reached >= 4  # navigate: the oracle reaches goal after goal ...
    for ep in episodes:
        assert np.abs(ep.actions).max() <= 1.0
        for t in np.flatnonzero(ep.goal_reached[:-1]):  # ... and then pursues a new one
            assert not np.array_equal(ep.goals[t + 1], ep.goals[t])
            assert np.linalg.norm(ep.observations[t + 1] - ep.goals[t]) <= 1.0
    again = list(generate_ogbench(make_recipe(POINT, "navigate", 4, 301, seed=5), "gen").episodes)
    assert all(np.array_equal(a.physics, b.physics) for a, b in zip(again, episodes, strict=True))


def test_recorded_physics_replays_exactly(generated) -> None:
    """Each recorded state, restored into the batched simulator and stepped with the recorded
    action, gives the next recorded observation (validate relies on it)."""
    info, episodes = generated
    spec = make_env_spec(info.env_id)
    sim = BatchSim(spec, 300)
    for ep in episodes[:2]:
        sim.set_state(ep.physics[:-1])
        assert sim.step(ep.actions[:-1]) == {}
        np.testing.assert_allclose(sim.observe(), ep.observations[1:], rtol=0, atol=1e-12)


def test_npz_round_trip_with_its_val_companion(generated, tmp_path) -> None:
    """Our episodes written in OGBench's layout load with OGBench's own loader, and import back
    (train file then -val file) with the same values and their provenance."""
    from ogbench.utils import load_dataset

    info, episodes = generated
    path = tmp_path / "pointmaze-medium-navigate-v0.npz"
    assert write_ogbench_npz(path, episodes[:3]) == 3 * 301
    write_ogbench_npz(tmp_path / "pointmaze-medium-navigate-v0-val.npz", episodes[3:])
    theirs = load_dataset(str(path), compact_dataset=True, add_info=True)
    assert theirs["observations"].shape == (903, 2) and theirs["qpos"].shape == (903, 2)
    data = read_ogbench(path, "imported")  # env id from the file name
    imported = list(data.episodes)
    assert data.info.env_id == POINT and data.frames == 4 * 301 and len(imported) == 4
    assert [f["episodes"] for f in data.info.generator["files"]] == [3, 1]
    assert data.info.generator["files"][1]["path"].endswith("-val.npz")
    for ours, back in zip(episodes, imported, strict=True):
        np.testing.assert_allclose(back.observations, ours.observations, atol=1e-5)
        np.testing.assert_allclose(back.actions, ours.actions, atol=1e-6)
        np.testing.assert_allclose(back.physics[:, 1:], ours.physics[:, 1:], atol=1e-5)
        assert back.terminals[-1] and not back.terminals[:-1].any()
    assert check_ogbench_dataset(imported, data.info).problems == []
    assert len(list(read_ogbench(path, "x", POINT, include_val=False).episodes)) == 3


def _npz(path, **arrays) -> None:
    np.savez(path, **arrays)


def test_bad_npz_inputs_are_one_line_errors(generated, tmp_path) -> None:
    ok = {"observations": np.zeros((5, 2)), "actions": np.zeros((5, 2)), "terminals": np.ones(5)}
    _npz(tmp_path / "missing.npz", observations=ok["observations"], actions=ok["actions"])
    message = one_line_error(lambda: read_ogbench(tmp_path / "missing.npz", "x", POINT))
    assert "terminals" in message and "actions, observations" in message  # what it has
    _npz(tmp_path / "lengths.npz", **{**ok, "actions": np.zeros((4, 2))})
    assert "different lengths" in one_line_error(
        lambda: read_ogbench(tmp_path / "lengths.npz", "x", POINT)
    )
    assert "pointmaze-medium-v0" in one_line_error(
        lambda: read_ogbench(tmp_path / "lengths.npz", "x", "pointmaze-huge-v0")
    )
    # medium-maze data read as the large maze: its positions lie in the large maze's walls
    _, episodes = generated
    write_ogbench_npz(tmp_path / "data.npz", episodes)
    message = one_line_error(lambda: read_ogbench(tmp_path / "data.npz", "x", "pointmaze-large-v0"))
    assert "set ingest.ogbench.env_id=pointmaze-medium-v0" in message  # the maze they fit
    # ... or the file name says which maze it is
    write_ogbench_npz(tmp_path / "pointmaze-medium-stitch-v0.npz", episodes[:1])
    assert "make them agree" in one_line_error(
        lambda: read_ogbench(tmp_path / "pointmaze-medium-stitch-v0.npz", "x", "pointmaze-giant-v0")
    )
    _npz(tmp_path / "ant.npz", **{**ok, "observations": np.zeros((5, 29))})
    assert "29 values" in one_line_error(lambda: read_ogbench(tmp_path / "ant.npz", "x", POINT))
    (tmp_path / "text.npz").write_text("not a zip")
    text = tmp_path / "text.npz"
    assert "not a .npz file" in one_line_error(lambda: read_ogbench(text, "x", POINT))
    assert "not found" in one_line_error(lambda: read_ogbench(tmp_path / "nope.npz", "x", POINT))
    assert "dataset type" in one_line_error(lambda: make_recipe(POINT, "path", 1, 10, 0))
    message = one_line_error(lambda: make_recipe("antmaze-medium-v0", "navigate", 1, 10, 0))
    assert "ingest.ogbench.expert" in message


def test_cli_ingest_ogbench_import_and_a_bad_file_leaves_nothing(generated, tmp_path) -> None:
    _, episodes = generated
    write_ogbench_npz(tmp_path / "pointmaze-medium-navigate-v0.npz", episodes[:2])
    params = {
        "ingest": {
            "name": "og",
            "source": "ogbench",
            "ogbench": {"path": str(tmp_path / "pointmaze-medium-navigate-v0.npz")},
        }
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    common = ["--params", str(tmp_path / "params.yaml"), "--data", str(tmp_path / "data")]
    result = runner.invoke(app, ["ingest", *common])
    assert result.exit_code == 0, result.output
    assert read_info(tmp_path / "data/demos/og.mcap").env_id == POINT
    report = json.loads((tmp_path / "data/reports/ingest/report.json").read_text())
    assert report["n_problems"] == 0 and report["steps"] == 2 * 301
    shown = runner.invoke(app, ["inspect", str(tmp_path / "data/demos/og.mcap")])
    assert shown.exit_code == 0 and "x [m], y [m]" in shown.output
    view = write_dataset_view(tmp_path / "data/demos/og.mcap", tmp_path / "og.rrd")
    assert view == {"episodes": 2, "total": 2} and (tmp_path / "og.rrd").stat().st_size > 0
    _npz(tmp_path / "bad.npz", observations=np.zeros((3, 2)), actions=np.zeros((3, 2)))
    params["ingest"]["name"] = "bad"
    params["ingest"]["ogbench"]["path"] = str(tmp_path / "bad.npz")
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    result = runner.invoke(app, ["ingest", *common])
    assert result.exit_code == 1
    assert len(result.stderr.strip().splitlines()) == 1 and "terminals" in result.stderr
    assert not (tmp_path / "data/demos/bad.mcap").exists()
    assert sorted(p.name for p in (tmp_path / "data/demos").iterdir()) == ["og.mcap"]


def test_deploy_refuses_another_success_radius_and_pools_the_five_tasks() -> None:
    from pipeline.config import DeployParams
    from pipeline.evaluation.episodes import EpisodeResult
    from stages.deploy import _check_ogbench_radius, _ogbench_overall

    spec = make_env_spec(POINT)
    message = one_line_error(lambda: _check_ogbench_radius(DeployParams(tasks=["ogbench"]), spec))
    assert "deploy.success_radius: 1" in message
    _check_ogbench_radius(DeployParams(tasks=["ogbench"], success_radius=1.0), spec)
    _check_ogbench_radius(DeployParams(tasks=["corners"]), spec)  # its own radius is the user's
    specs = _tasks().expand(["ogbench"], 2)
    results = {
        task: [EpisodeResult(s, steps_to_goal=10 if task.endswith("1") else None) for s in eps]
        for task, eps in specs.items()
    }
    pooled = _ogbench_overall(results, 0.1, [])["ogbench"]
    assert (pooled["episodes"], pooled["successes"]) == (10, 2)
    assert _ogbench_overall({"corners": results["ogbench-task1"]}, 0.1, []) == {}


def test_an_ant_maze_npz_imports_with_its_physics(tmp_path) -> None:
    """An OGBench ant file (29-dim observations, qpos 15, qvel 14: what issue 19 builds on)
    imports with exact physics: restoring a recorded state and stepping the recorded action
    gives the next recorded observation."""
    env = make_ogbench_env("antmaze-medium-v0", max_episode_steps=10**6, terminate_at_goal=False)
    rng = np.random.default_rng(0)
    columns: dict[str, list] = {
        k: [] for k in ("observations", "actions", "terminals", "qpos", "qvel")
    }
    for task in (1, 2):
        ob, _ = env.reset(seed=task, options={"task_id": task})
        for t in range(30):
            action = rng.uniform(-1, 1, 8)
            columns["observations"].append(ob)
            columns["actions"].append(action)
            columns["terminals"].append(t == 29)
            ob, _, _, _, info = env.step(action)
            columns["qpos"].append(info["prev_qpos"])
            columns["qvel"].append(info["prev_qvel"])
    np.savez(
        tmp_path / "antmaze-medium-navigate-v0.npz", **{k: np.array(v) for k, v in columns.items()}
    )
    data = read_ogbench(tmp_path / "antmaze-medium-navigate-v0.npz", "ant")
    episodes = list(data.episodes)
    assert data.info.env_id == "antmaze-medium-v0" and data.info.state_dim == 29
    assert data.info.physics_dim == 30 and [len(e) for e in episodes] == [30, 30]
    # random torques flip the ant within ~15 steps: no demonstrator, so its falls are accepted
    report = check_ogbench_dataset(episodes, data.info, max_fallen_share=1.0)
    assert report.problems == [] and report.fallen_episodes >= 1
    sim = BatchSim(make_env_spec("antmaze-medium-v0"), 29)
    sim.set_state(episodes[0].physics[:-1])
    sim.step(episodes[0].actions[:-1])
    np.testing.assert_allclose(sim.observe(), episodes[0].observations[1:], atol=1e-9)


@pytest.mark.parametrize("size", ["medium", "large", "giant"])
def test_ogbench_params_run_ogbenchs_gcbc(size) -> None:
    """`impls/agents/gcbc.py`: 3 x 512 MLP, constant std, lr 3e-4, raw inputs, final parameters;
    evaluated with its mean action. Only the batch (1024) and the steps (1M) are CPU-sized."""
    from pipeline.config import load_params

    params = load_params(ROOT / f"params-ogbench-pointmaze-{size}.yaml")
    gcbc = params.gcbc
    assert (gcbc.hidden, gcbc.lr, gcbc.learned_std) == (512, 3e-4, False)
    assert (gcbc.normalize, gcbc.keep) == (False, "last")
    assert not params.deploy.gcbc.sample_actions
