"""One object of a manipulation goal at a time (`deploy.object_subtasks`): which object is
active, what each replan aims at, the spec's objects, and the skill MPC planning to them."""

import numpy as np
import pytest
import torch
from factories import planner_config, skill_model_config

from pipeline.model import SkillModel
from pipeline.planning import SkillPlanner
from pipeline.planning.mpc import SkillMPC
from pipeline.planning.subtasks import ObjectSubtasks

CUBES = ((0, 1, 2), (3, 4, 5))
SCALE = (0.4,) * 6  # a cube's 0.04 m in observation units


def test_the_first_object_not_within_its_tolerance_is_active_and_the_rest_wait():
    subtasks = ObjectSubtasks(CUBES, SCALE)
    goals = torch.tensor([[1.0, 0.0, 0.0, -1.0, 0.0, 0.0]]).repeat(4, 1)
    current = torch.tensor([
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],  # both cubes off: the first is active
        [0.9, 0.1, 0.0, 0.0, 0.0, 0.0],  # the first within 0.4 (distance 0.14): the second
        [0.0, 0.0, 0.0, -1.0, 0.0, 0.3],  # the second done, the first not: the first
        [1.0, 0.0, 0.0, -1.2, 0.2, 0.0],  # both within their tolerance: none
    ])  # fmt: skip
    assert subtasks.done(current, goals).tolist() == [
        [False, False], [True, False], [False, True], [True, True],
    ]  # fmt: skip
    assert subtasks.active(current, goals).tolist() == [0, 1, 0, 2]
    targets = subtasks.targets(current, goals)
    # The active cube and every cube done aim at the goal; a cube still to come stays put.
    assert targets[0].tolist() == [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert targets[1].tolist() == goals[1].tolist()
    assert targets[2].tolist() == goals[2].tolist()  # the second is done: held at its goal
    assert targets[3].tolist() == goals[3].tolist()


def test_a_distance_of_exactly_one_tolerance_counts_as_done():
    subtasks = ObjectSubtasks(((0,), (1,)), (0.5, 0.5))
    goals = torch.tensor([[1.0, 1.0]])
    assert subtasks.done(torch.tensor([[0.5, 0.49]]), goals).tolist() == [[True, False]]


@pytest.mark.parametrize(
    ("objects", "scale"),
    [(((0, 1),), (1.0, 1.0, 1.0)), (((0, 1), (1, 2)), (1.0, 1.0, 1.0)), ((), ()),
     (((0,), ()), (1.0,)), (((0,),), (0.0,))],
)  # fmt: skip
def test_objects_must_cover_the_goal_once_with_positive_tolerances(objects, scale):
    with pytest.raises(ValueError):
        ObjectSubtasks(objects, scale)


@pytest.mark.parametrize(
    ("env_id", "objects"),
    [("cube-double-v0", 2), ("scene-v0", 1 + 2 + 2), ("puzzle-3x3-v0", 9)],
)
def test_a_manipulation_goal_splits_into_its_objects(env_id, objects):
    from pipeline.envs.manipspace.env import ManipSpaceSpec

    spec = ManipSpaceSpec.create(env_id)
    assert len(spec.goal_objects) == objects
    assert sorted(i for obj in spec.goal_objects for i in obj) == list(range(len(spec.goal_dims)))
    ObjectSubtasks(spec.goal_objects, spec.goal_scale)  # accepted as they are


def test_the_mpc_plans_to_the_active_object_exactly_as_to_that_target():
    """With object subtasks a replan is the plan to `targets(...)` as the goal (same noise)."""
    torch.manual_seed(0)
    model = SkillModel(skill_model_config(8, 2, z_dim=3, hidden=16)).eval()
    planner = planner_config(horizon=2, candidates=16, elites=4, iterations=2)
    dims = (2, 3, 4, 5, 6, 7)
    subtasks = ObjectSubtasks(CUBES, SCALE)
    states = np.random.default_rng(0).normal(size=(3, 8))
    goals = states[:, list(dims)].copy()
    goals[:, 0] += 1.0  # row 0, 1: the first cube off; row 2: only the second
    goals[2, 0] -= 1.0
    goals[2, 4] += 2.0
    goals[1, 3] -= 1.0
    with_subtasks = SkillMPC(
        model, SkillPlanner(model, planner), False, dims, goal_scale=SCALE, subtasks=subtasks
    )
    with_subtasks.reset(goals, seeds=[1, 2, 3])
    got = with_subtasks.replan(np.arange(3), states)
    targets = subtasks.targets(
        torch.as_tensor(states[:, list(dims)]).float(), torch.as_tensor(goals).float()
    ).numpy()
    assert targets[1, 3] == pytest.approx(states[1, 5])  # the second cube waits in row 1
    assert targets[2, 4] == pytest.approx(goals[2, 4])  # and is the active one in row 2
    plain = SkillMPC(model, SkillPlanner(model, planner), False, dims, goal_scale=SCALE)
    plain.reset(targets, seeds=[1, 2, 3])
    want = plain.replan(np.arange(3), states)
    torch.testing.assert_close(got.eps, want.eps)
    torch.testing.assert_close(got.cost, want.cost)


def test_subgoals_and_subtasks_do_not_go_together():
    from pipeline.planning.subgoals import SubgoalGraph

    model = SkillModel(skill_model_config(8, 2, z_dim=3, hidden=16)).eval()
    points = np.stack([np.linspace(0, 1, 20), np.zeros(20)], axis=1)
    graph = SubgoalGraph.from_windows(
        points, np.arange(10), np.arange(10) + 5, cell=0.25, reach=2, line_of_sight=False
    )
    planner = SkillPlanner(model, planner_config(horizon=2, candidates=8, elites=2, iterations=1))
    with pytest.raises(ValueError, match="not both"):
        SkillMPC(model, planner, False, subgoals=graph, subtasks=ObjectSubtasks(CUBES, SCALE))
