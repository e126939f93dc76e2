"""Waypoints from the graph of the data's skills (`deploy.subgoals`): round a wall the way the
demonstrations went, the goal itself once it is within reach, and wired into the skill MPC."""

import numpy as np
import pytest
import torch
from factories import make_info, make_skill_episodes, planner_config, skill_model_config

from pipeline.model import SkillModel
from pipeline.planning import SkillPlanner
from pipeline.planning.mpc import SkillMPC
from pipeline.planning.subgoals import StuckWatch, SubgoalGraph
from pipeline.segments import build_segments


def _u_corridor(step: float = 0.1) -> np.ndarray:
    """Positions along a U: up the left leg x = 0, across y = 4, down the right leg x = 4 (a
    wall between the legs below y = 4), there and back."""
    up = np.stack([np.zeros(41), np.arange(41) * step], axis=1)
    across = np.stack([np.arange(1, 41) * step, np.full(40, 4.0)], axis=1)
    down = np.stack([np.full(40, 4.0), 4.0 - np.arange(1, 41) * step], axis=1)
    path = np.concatenate([up, across, down])
    return np.concatenate([path, path[::-1]])


def _graph(reach: int = 5, window: int = 5) -> SubgoalGraph:
    points = _u_corridor()
    first = np.arange(len(points) - window)
    return SubgoalGraph.from_windows(
        points, first, first + window, cell=0.25, reach=reach, line_of_sight=False
    )


def test_waypoint_leads_round_the_wall_and_is_the_goal_once_within_reach():
    graph = _graph()
    # Nodes are cells of the corridor; a skill spans 0.5 m, so the far leg is ~24 skills away.
    assert graph.nodes.shape[1] == 2 and torch.isfinite(graph.hops).all()
    assert torch.equal(graph.hops, graph.hops.T)
    positions = torch.tensor([[0.0, 0.0], [4.0, 2.0], [2.0, 4.0]])
    goals = torch.tensor([[4.0, 0.0], [4.0, 0.0], [4.0, 0.0]])
    targets = graph.waypoints(positions, goals)
    # From the left leg's foot: up the left leg (towards the goal would be into the wall).
    x, y = targets[0].tolist()
    assert abs(x) < 0.3 and 1.5 < y < 3.2
    # Within reach (2 m = 4 skills down the right leg): the goal itself.
    torch.testing.assert_close(targets[1], goals[1])
    # From the top: along the top towards the right leg, no further than reach skills.
    x, y = targets[2].tolist()
    assert 3.0 < x <= 4.2 and y > 3.0


def test_windows_with_a_jump_are_no_edges():
    """A teleport in the data (one step from the left leg's foot to the right one's) links
    nothing: the feet stay the whole U apart, in skills, as without it."""
    u = _u_corridor()
    hop = np.concatenate([u[:20][::-1], u[120:140]])  # down the left leg, then a jump right
    points = np.concatenate([u, hop])
    first = np.concatenate([np.arange(len(u) - 5), len(u) + np.arange(len(hop) - 5)])
    graph = SubgoalGraph.from_windows(
        points, first, first + 5, cell=0.25, reach=5, line_of_sight=False
    )
    feet = torch.tensor([[0.0, 0.0], [4.0, 0.0]])
    a, b = graph.nearest(feet)
    plain = _graph()
    c, d = plain.nearest(feet)
    assert graph.hops[a, b] == plain.hops[c, d] > 20  # round the U (as an edge: 1 skill)
    smooth = np.concatenate([u, u[:40]])  # the same windows without a jump: no change
    first = np.concatenate([np.arange(len(u) - 5), len(u) + np.arange(35)])
    assert torch.equal(
        SubgoalGraph.from_windows(
            smooth, first, first + 5, cell=0.25, reach=5, line_of_sight=False
        ).hops,
        _graph().hops,
    )


def test_unreachable_goal_and_single_skill_reach():
    points = np.concatenate([_u_corridor(), [[10.0, 10.0], [10.0, 10.1]]])  # an island
    first = np.arange(len(points) - 7)
    graph = SubgoalGraph.from_windows(
        points, first, first + 5, cell=0.25, reach=1, line_of_sight=False
    )
    goals = torch.tensor([[10.0, 10.0], [4.0, 0.0]])
    targets = graph.waypoints(torch.tensor([[0.0, 0.0], [0.0, 0.0]]), goals)
    torch.testing.assert_close(targets[0], goals[0])  # not connected: the goal itself
    step = torch.linalg.vector_norm(targets[1] - torch.tensor([0.0, 0.0]))
    assert 0.2 < step < 0.8  # one skill (0.5 m) up the left leg
    with pytest.raises(ValueError, match="cell"):
        SubgoalGraph.from_windows(points, first, first + 5, cell=0.0, reach=1, line_of_sight=False)


def test_from_segments_and_the_mpc_aims_at_waypoints():
    episodes = make_skill_episodes(n_episodes=8, length=60, seed=0)
    split = {"train": 0.75, "validation": 0.125, "test": 0.125}
    segments = build_segments(episodes, make_info("skills", physics_dim=0), 11, 1, split, seed=0)
    graph = SubgoalGraph.from_segments(segments, (0, 1), cell=0.5, reach=2, line_of_sight=False)
    xy = segments.states[:, :2]
    assert (graph.nodes.numpy() >= xy.min(0) - 1e-5).all()
    assert (graph.nodes.numpy() <= xy.max(0) + 1e-5).all()

    torch.manual_seed(0)
    sd, ad = segments.info.state_dim, segments.info.action_dim
    model = SkillModel(skill_model_config(sd, ad, z_dim=4, hidden=16)).eval()
    planner = planner_config(horizon=2, candidates=16, elites=4, iterations=2, prior_weight=0.0)
    agent = SkillMPC(model, SkillPlanner(model, planner), False, goal_dims=(0, 1), subgoals=graph)
    far = graph.nodes[graph.hops[0].argmax()].numpy()
    agent.reset(far[None].astype(np.float64), seeds=[0])
    start = np.zeros((1, sd))
    start[0, :2] = graph.nodes[0].numpy()
    agent.replan(np.array([0]), start)
    want = graph.waypoints(torch.as_tensor(start[:, :2]).float(), torch.as_tensor(far[None]))
    torch.testing.assert_close(agent.targets, want)
    assert graph.hops[0, graph.nearest(agent.targets)].item() <= 2


def test_episodes_with_subgoals_record_one_waypoint_per_replan():
    from pipeline.envs.batch import BatchSim
    from pipeline.envs.spec import PointMazeSpec
    from pipeline.evaluation.episodes import RunConfig, run_episodes
    from pipeline.evaluation.tasks import EpisodeSpec

    # Data along Medium's top corridor (y = 2.5 m, x from -2.5 to 0.5: cells (1, 1) to (1, 4)).
    points = np.stack([np.linspace(-2.5, 0.5, 61), np.full(61, 2.5)], axis=1)
    points = np.concatenate([points, points[::-1]])
    first = np.arange(len(points) - 10)
    graph = SubgoalGraph.from_windows(
        points, first, first + 10, cell=0.25, reach=1, line_of_sight=False
    )
    torch.manual_seed(0)
    model = SkillModel(skill_model_config(4, 2, z_dim=4, hidden=16)).eval()
    planner = planner_config(horizon=2, candidates=16, elites=4, iterations=2, prior_weight=0.0)
    agent = SkillMPC(model, SkillPlanner(model, planner), False, goal_dims=(0, 1), subgoals=graph)
    spec = EpisodeSpec("goal", 0, np.array([-2.5, 2.5, 0.0, 0.0]), np.array([0.5, 2.5]), 3)
    (result,), _ = run_episodes(
        agent, BatchSim(PointMazeSpec.create("PointMaze_Medium-v3"), 1), [spec], RunConfig(20, 5)
    )
    trace = result.trace
    assert result.replans == 4 and len(trace.plan_targets) == 4
    first_target = trace.plan_targets[0]
    assert -2.5 < first_target[0] < 0.0 and abs(first_target[1] - 2.5) < 0.1  # 1 skill ahead


def _l_room(step: float = 0.1) -> np.ndarray:
    """Positions along an L round a wall block: right along y = 0 from x = 0 to 2, then up x = 2
    to y = 2, there and back. The block [0, 1.75) x [0.25, 2] is never visited."""
    right = np.stack([np.arange(21) * step, np.zeros(21)], axis=1)
    up = np.stack([np.full(20, 2.0), np.arange(1, 21) * step], axis=1)
    path = np.concatenate([right, up])
    return np.concatenate([path, path[::-1]])


def test_line_of_sight_takes_the_corner_when_the_goal_within_reach_is_behind_a_wall():
    points = _l_room()
    first = np.arange(len(points) - 10)
    plain, sighted = (
        SubgoalGraph.from_windows(points, first, first + 10, cell=0.25, reach=4, line_of_sight=s)
        for s in (False, True)
    )
    start, goal = torch.tensor([[0.0, 0.0]]), torch.tensor([[2.0, 2.0]])
    # Four skills of 1 m apart: within reach, so the plain rule aims through the wall.
    assert plain.hops[plain.nearest(start), plain.nearest(goal)].item() == 4
    torch.testing.assert_close(plain.waypoints(start, goal), goal)
    # In sight of the start: along y = 0 only; the best of those nodes is at the corner.
    x, y = sighted.waypoints(start, goal)[0].tolist()
    assert 1.6 < x < 2.1 and abs(y) < 0.2
    # From the corner the goal is in sight: the goal itself.
    torch.testing.assert_close(sighted.waypoints(torch.tensor([[2.0, 0.1]]), goal), goal)
    # The line test itself: along the corridor clear, across the block not, outside the grid not.
    a = torch.tensor([[0.0, 0.0], [0.0, 0.0], [2.0, 0.0]])
    b = torch.tensor([[2.0, 0.0], [2.0, 2.0], [5.0, 0.0]])
    assert sighted.sight.clear(a, b).tolist() == [True, False, False]


def test_line_of_sight_changes_nothing_in_the_open():
    points = np.stack(np.meshgrid(np.arange(0, 3, 0.1), np.arange(0, 3, 0.1)), -1).reshape(-1, 2)
    first = np.arange(len(points) - 30)
    plain, sighted = (
        SubgoalGraph.from_windows(points, first, first + 30, cell=0.5, reach=1, line_of_sight=s)
        for s in (False, True)
    )
    gen = torch.Generator().manual_seed(0)
    positions, goals = (torch.rand(64, 2, generator=gen) * 2.9 for _ in range(2))
    want = plain.waypoints(positions, goals)
    torch.testing.assert_close(sighted.waypoints(positions, goals), want)


def test_stuck_watch_counts_replans_without_progress_and_latches():
    watch = StuckWatch(patience=2, progress=0.25)
    watch.reset(3, "cpu")
    rows = torch.tensor([0, 1, 2])
    # slot 0 closes in, slot 1 stalls (0.2 closer is not 0.25), slot 2 drifts away
    for distances in ([4.0, 4.0, 4.0], [3.5, 3.8, 4.5]):
        stuck = watch.update(rows, torch.tensor(distances))
        assert not stuck.any()
    stuck = watch.update(rows, torch.tensor([3.0, 3.9, 4.2]))
    assert stuck.tolist() == [False, True, True]
    # a stuck episode stays stuck, even once it gets closer; only slot 0's stall counts anew
    stuck = watch.update(rows, torch.tensor([3.0, 1.0, 1.0]))
    assert stuck.tolist() == [False, True, True]
    assert watch.update(rows[:1], torch.tensor([2.9])).tolist() == [True]
    watch.reset(3, "cpu")
    assert not watch.update(rows, torch.tensor([9.0, 9.0, 9.0])).any()
    with pytest.raises(ValueError, match="patience"):
        StuckWatch(0, 0.25)
    with pytest.raises(ValueError, match="progress"):
        StuckWatch(1, 0.0)


def test_mpc_aims_at_the_goal_until_the_episode_is_stuck_then_at_waypoints():
    """Two episodes from the left leg's foot to the right one's (a wall between): the one that
    stays put switches to the graph's waypoint (up the left leg) after `patience` replans; the one
    that keeps getting closer plans to the goal itself throughout."""
    graph = _graph(reach=5)
    torch.manual_seed(0)
    model = SkillModel(skill_model_config(4, 2, z_dim=4, hidden=16)).eval()
    planner = planner_config(horizon=5, candidates=16, elites=4, iterations=2, prior_weight=0.0)
    agent = SkillMPC(
        model, SkillPlanner(model, planner), False, goal_dims=(0, 1), subgoals=graph,
        stuck=StuckWatch(patience=2, progress=0.25),
    )  # fmt: skip
    goal = np.array([[4.0, 0.0], [4.0, 0.0]])
    agent.reset(goal, seeds=[0, 1])
    states = np.zeros((2, 4))
    rows = np.array([0, 1])
    for replan in range(4):
        agent.replan(rows, states)
        targets = agent.targets.numpy()
        torch.testing.assert_close(agent.targets[1], torch.tensor([4.0, 0.0]))
        if replan < 2:
            torch.testing.assert_close(agent.targets[0], torch.tensor([4.0, 0.0]))
        else:  # stuck: up the left leg, round the wall
            assert abs(targets[0, 0]) < 0.3 and targets[0, 1] > 1.0
        states[1, 0] += 0.5  # slot 1 gets closer each replan (through the wall: only a test)
    with pytest.raises(ValueError, match="give it subgoals"):
        SkillMPC(model, SkillPlanner(model, planner), False, stuck=StuckWatch(2, 0.25))
