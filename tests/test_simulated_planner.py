"""The perfect-model planner (`pipeline.planning.simulated`, agent `oposm_sim`): its rollout is
the simulator executing the skills, so what it predicts is what happens."""

import numpy as np
import pytest
import torch

from pipeline.config import PlannerParams
from pipeline.envs.batch import BatchSim
from pipeline.envs.spec import make_env_spec
from pipeline.errors import UserError
from pipeline.evaluation.open_loop import execute_skills
from pipeline.model.skill_model import SkillModel, SkillModelConfig
from pipeline.planning.costs import GoalCost
from pipeline.planning.noise import problem_keys
from pipeline.planning.settings import planner_config
from pipeline.planning.simulated import SimulatedRollout, SimulatedSkillMPC, SimulatorPlanner

STEPS = 4  # simulator steps per skill


@pytest.fixture(scope="module")
def maze():
    """The point maze, a random-weight skill model (its actions are not tiny: the point moves),
    and three start states in the maze's open cells, as exact physics states."""
    spec = make_env_spec("PointMaze_Medium-v3")
    torch.manual_seed(0)
    config = SkillModelConfig(
        state_dim=spec.state_dim, action_dim=spec.action_dim, z_dim=3, hidden=16,
        tawm_shared_std=True, min_std=1e-4,
    )  # fmt: skip
    model = SkillModel(config).eval()
    model.set_normalization(np.zeros(4), np.ones(4), np.zeros(2), np.full(2, 0.5))
    sim = BatchSim(spec, 3)
    sim.reset(np.array([[1.0, 1.0, 0, 0], [-1.0, 0.0, 0.1, 0], [0.0, -1.0, 0, -0.2]]))
    return spec, model, sim.get_state(), sim.observe()


def test_the_rollout_is_the_simulator_executing_the_skills(maze):
    spec, model, physics, _ = maze
    rollout = SimulatedRollout(model, spec, spec.model, candidates=5, skill_steps=STEPS)
    eps = torch.randn(3, 5, 2, 3, generator=torch.Generator().manual_seed(1))
    states, z = rollout(eps, physics)
    assert states.shape == (3, 5, 3, 4) and z.shape == (3, 5, 2, 3)
    for p in range(3):  # the same skills, executed from the same state outside the planner
        sim = BatchSim(spec, 5)
        sim.set_state(np.repeat(physics[p][None], 5, axis=0))
        executed = execute_skills(model, sim, z[p], STEPS, sample_actions=False).states
        expected = torch.as_tensor(executed[:, ::STEPS], dtype=torch.float32)
        assert torch.equal(states[p], expected)
        assert (states[p, :, -1] - states[p, :, 0]).abs().max() > 1e-3  # the point moved
        # each skill is the prior's at the state the simulator reached, whitened by eps
        mu, sigma = model.skill_prior(states[p, :, 1])
        assert torch.equal(z[p, :, 1], torch.addcmul(mu, sigma, eps[p, :, 1]))


def test_a_plan_scored_in_the_simulator_predicts_what_executing_it_does(maze):
    spec, model, physics, observations = maze
    params = PlannerParams(horizon=2, candidates=6, elites=2, iterations=2, compile=False)
    config = planner_config(params)
    planner = SimulatorPlanner(model, config, SimulatedRollout(model, spec, spec.model, 6, STEPS))
    planner.starts = physics
    s0 = torch.as_tensor(observations, dtype=torch.float32)
    goals = torch.tensor([[3.0, 3.0], [-3.0, 3.0], [3.0, -3.0]])
    plan = planner.plan(s0, GoalCost(goals, (0, 1)), problem_keys([0, 1, 2], s0.device))
    sim = BatchSim(spec, 3)
    sim.set_state(physics)
    executed = execute_skills(model, sim, plan.z, STEPS, sample_actions=False).states
    # The same bits where MKL's products do not depend on how many rows a batch has (Intel's
    # AVX-512 branch); MKL's own path on AMD CPUs rounds the 18 scored rollouts and the 3
    # executed ones apart in the last bits (measured: 4e-9).
    executed = torch.as_tensor(executed[:, ::STEPS], dtype=torch.float32)
    torch.testing.assert_close(plan.states, executed, rtol=0, atol=1e-6)
    assert torch.equal(plan.cost, GoalCost(goals, (0, 1))(plan.states[:, None])[:, 0])


def test_the_agent_plans_from_the_slots_exact_states_and_refuses_what_it_cannot_do(maze):
    spec, model, physics, observations = maze
    config = planner_config(PlannerParams(horizon=2, candidates=4, elites=2, iterations=1))
    planner = SimulatorPlanner(model, config, SimulatedRollout(model, spec, spec.model, 4, STEPS))
    agent = SimulatedSkillMPC(model, planner, False, (0, 1))
    agent.reset(np.zeros((3, 2)), [0, 1, 2])
    with pytest.raises(RuntimeError, match="attach"):
        agent.replan(np.arange(3), observations)
    envs = BatchSim(spec, 3)
    envs.set_state(physics)
    agent.attach(envs)
    plan = agent.replan(np.array([0, 2]), observations[[0, 2]])
    assert np.array_equal(planner.starts, physics[[0, 2]])
    assert torch.equal(plan.states[:, 0], torch.as_tensor(observations[[0, 2]]).float())
    compiled = planner_config(PlannerParams(horizon=2, candidates=4, elites=2, compile=True))
    with pytest.raises(UserError, match="compile=false"):
        SimulatorPlanner(model, compiled, SimulatedRollout(model, spec, spec.model, 4, STEPS))
    uncertain = planner_config(
        PlannerParams(horizon=2, candidates=4, elites=2, uncertainty_weight=1.0)
    )
    with pytest.raises(UserError, match="uncertainty_weight=0"):
        SimulatorPlanner(model, uncertain, SimulatedRollout(model, spec, spec.model, 4, STEPS))
