"""The skill MPC's warm start: each replan's CEM starts from the slot's previous plan shifted by one
skill, per slot, and a new episode starts from zeros (paper appendix C.6)."""

import numpy as np
import pytest
import torch
from factories import planner_config, skill_model_config

from pipeline.model import SkillModel
from pipeline.planning import SkillPlanner
from pipeline.planning.mpc import SkillMPC

L, Z = 3, 2


@pytest.fixture
def model() -> SkillModel:
    torch.manual_seed(0)
    m = SkillModel(skill_model_config(4, 2, z_dim=Z, hidden=8))
    m.set_normalization([0.5, -0.5, 0.0, 0.0], [2.0, 2.0, 1.0, 1.0], [0.0, 0.0], [0.5, 0.5])
    return m.eval()


def _spied_agent(model, warm_start=True):
    """An agent whose CEM records the initial mean it is started from at each call."""
    planner = SkillPlanner(
        model,
        planner_config(
            horizon=L, candidates=8, elites=2, iterations=2, warm_start=warm_start, prior_weight=0.0
        ),
    )
    starts: list[torch.Tensor] = []
    minimize = planner.cem.minimize

    def spy(cost_fn, mean, std, keys, step=None):
        starts.append(mean.clone())
        return minimize(cost_fn, mean, std, keys, step)

    planner.cem.minimize = spy
    return SkillMPC(model, planner, sample_actions=False), starts


def _shifted(eps: torch.Tensor) -> torch.Tensor:
    """`[L, z]` plan -> the next replan's start: drop the executed skill, append a zero skill."""
    return torch.cat([eps[1:], torch.zeros(1, eps.shape[-1])])


def test_each_replan_starts_cem_from_the_slots_previous_plan_shifted_by_one_skill(model):
    agent, starts = _spied_agent(model)
    rng = np.random.default_rng(0)
    agent.reset(rng.normal(size=(3, 2)), seeds=[1, 2, 3])

    first = agent.replan(np.array([0, 1, 2]), rng.normal(size=(3, 4)))
    assert torch.equal(starts[0], torch.zeros(3, L, Z))  # a new episode: the prior's mean skills
    assert first.eps.abs().min() > 0  # so a shifted plan cannot pass for zeros

    second = agent.replan(np.array([0, 1, 2]), rng.normal(size=(3, 4)))
    for b in range(3):
        torch.testing.assert_close(starts[1][b], _shifted(first.eps[b]), rtol=0, atol=0)

    # Slots replan on their own: slot 2 alone, then slots 0 and 2; each from its own last plan.
    third = agent.replan(np.array([2]), rng.normal(size=(1, 4)))
    torch.testing.assert_close(starts[2][0], _shifted(second.eps[2]), rtol=0, atol=0)
    agent.replan(np.array([0, 2]), rng.normal(size=(2, 4)))
    torch.testing.assert_close(starts[3][0], _shifted(second.eps[0]), rtol=0, atol=0)
    torch.testing.assert_close(starts[3][1], _shifted(third.eps[0]), rtol=0, atol=0)


def test_reset_clears_the_warm_start_and_warm_start_off_always_starts_from_zeros(model):
    agent, starts = _spied_agent(model)
    rng = np.random.default_rng(1)
    goals = rng.normal(size=(2, 2))
    agent.reset(goals, seeds=[1, 2])
    agent.replan(np.array([0, 1]), rng.normal(size=(2, 4)))
    agent.replan(np.array([0, 1]), rng.normal(size=(2, 4)))
    assert starts[1][:, :-1].abs().min() > 0  # warm within the episode
    agent.reset(goals, seeds=[3, 4])  # next episode, same number of slots
    agent.replan(np.array([1]), rng.normal(size=(1, 4)))
    agent.replan(np.array([0, 1]), rng.normal(size=(2, 4)))
    assert torch.equal(starts[2], torch.zeros(1, L, Z))
    assert torch.equal(starts[3][0], torch.zeros(L, Z))  # slot 0: first plan of this episode
    assert starts[3][1, :-1].abs().min() > 0  # slot 1: warm from this episode's plan

    cold, cold_starts = _spied_agent(model, warm_start=False)
    cold.reset(goals, seeds=[1, 2])
    for _ in range(2):
        cold.replan(np.array([0, 1]), rng.normal(size=(2, 4)))
    assert all(torch.equal(s, torch.zeros(2, L, Z)) for s in cold_starts)


def test_the_executed_skill_is_the_plans_first_per_slot(model):
    agent, _ = _spied_agent(model)
    rng = np.random.default_rng(2)
    agent.reset(rng.normal(size=(2, 2)), seeds=[1, 2])
    states = rng.normal(size=(2, 4))
    plan = agent.replan(np.array([0, 1]), states)
    later = agent.replan(np.array([1]), states[1:])  # slot 0 keeps executing its skill
    s = torch.as_tensor(states, dtype=torch.float32)
    want = torch.stack([model.act(s[0], plan.z[0, 0]), model.act(s[1], later.z[0, 0])])
    got = agent.act(np.array([0, 1]), states)
    np.testing.assert_allclose(got, want.double().numpy(), rtol=0, atol=1e-6)
