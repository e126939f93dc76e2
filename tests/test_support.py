"""The support distance of planned (state, skill) pairs (`deploy.planner.support_weight`): against
a float64 brute force, its bank from the segments, and what it adds to the planner's objective."""

import numpy as np
import pytest
import torch
from factories import (
    make_info,
    make_skill_episodes,
    planner_config,
    small_skill_model,
)

from pipeline.config import PlannerParams
from pipeline.model import SkillModel
from pipeline.planning import GoalCost, SkillPlanner, problem_keys
from pipeline.planning import support as support_module
from pipeline.planning.support import SkillSupport
from pipeline.segments import build_segments
from stages.deploy_agents import _planner_settings

SPLIT = {"train": 0.6, "validation": 0.2, "test": 0.2}


@pytest.fixture(scope="module")
def model() -> SkillModel:
    """A small skill model with random weights and non-trivial normalization."""
    return small_skill_model()


def brute_force(bank_s, bank_z, s, z):
    """The support distance in float64, pair by pair."""
    bank_s, bank_z, s, z = (t.double() for t in (bank_s, bank_z, s, z))
    scale = bank_z.std(dim=0)
    ds = (s[:, None] - bank_s[None]).pow(2).mean(dim=-1)
    dz = ((z[:, None] - bank_z[None]) / scale).pow(2).mean(dim=-1)
    return (ds + dz).amin(dim=1)


def test_the_distance_is_the_nearest_bank_pair_in_float64(monkeypatch):
    g = torch.Generator().manual_seed(1)
    bank_s, bank_z = torch.randn(50, 6, generator=g), 3.0 * torch.randn(50, 4, generator=g)
    support = SkillSupport(bank_s, bank_z)
    s, z = torch.randn(2, 5, 3, 6, generator=g), 3.0 * torch.randn(2, 5, 3, 4, generator=g)
    monkeypatch.setattr(support_module, "_ROWS", 7)  # blocks that do not divide the 30 pairs
    got = support.distance(s, z)
    assert got.shape == (2, 5, 3)
    want = brute_force(bank_s, bank_z, s.reshape(-1, 6), z.reshape(-1, 4)).reshape(2, 5, 3)
    torch.testing.assert_close(got.double(), want, atol=1e-5, rtol=1e-5)
    # A bank pair is at distance 0; the skill part does not depend on the skills' units.
    assert support.distance(bank_s[:3], bank_z[:3]).abs().max() < 1e-5
    rescaled = SkillSupport(bank_s, 10.0 * bank_z).distance(s, 10.0 * z)
    torch.testing.assert_close(rescaled, got, atol=1e-4, rtol=1e-4)


def test_the_bank_is_evenly_spaced_training_windows_and_their_posterior_skills(model):
    episodes = make_skill_episodes(6, 40, seed=0)
    segments = build_segments(episodes, make_info("skills", physics_dim=0), 11, 1, SPLIT, seed=0)
    total = len(segments.starts["train"])
    support = SkillSupport.from_segments(model, segments, windows=17, batch=5)
    assert len(support.bank) == 17 < total
    idx = np.unique(np.linspace(0, total - 1, 17).round().astype(np.int64))
    states, actions = (torch.as_tensor(x) for x in segments.windows("train", idx))
    skills, _ = model.infer_skill(states[:, :-1], actions)
    expected = SkillSupport(model.norm_states(states[:, 0]), skills)
    torch.testing.assert_close(support.bank, expected.bank)
    assert support.margin == 0.0  # no quantile: every distance pays
    # Asking for more windows than there are gives all of them.
    assert len(SkillSupport.from_segments(model, segments, windows=10 * total).bank) == total


def test_the_margin_is_a_quantile_of_the_windows_between_the_banks_and_only_beyond_it_pays(model):
    episodes = make_skill_episodes(6, 40, seed=0)
    segments = build_segments(episodes, make_info("skills", physics_dim=0), 11, 1, SPLIT, seed=0)
    total = len(segments.starts["train"])
    support = SkillSupport.from_segments(model, segments, windows=9, quantile=0.75)
    idx = np.unique(np.linspace(0, total - 1, 9).round().astype(np.int64))
    between = (idx[:-1] + idx[1:]) // 2
    assert not np.isin(between, idx).any()
    states, actions = (torch.as_tensor(x) for x in segments.windows("train", between))
    starts_n, skills = (
        model.norm_states(states[:, 0]),
        model.infer_skill(states[:, :-1], actions)[0],
    )
    own = support.distance(starts_n, skills)
    assert support.margin == pytest.approx(float(torch.quantile(own.double(), 0.75)))
    assert support.margin > 0 and (own > support.margin).sum() == 2  # 2 of the 8 pay
    excess = support.excess(starts_n, skills)
    torch.testing.assert_close(excess, (own - support.margin).clamp_min(0))
    assert (excess == 0).sum() == 6


def test_the_planner_adds_the_weighted_support_excess_summed_over_its_skills(model):
    g = torch.Generator().manual_seed(2)
    support = SkillSupport(torch.randn(40, 4, generator=g), torch.randn(40, 3, generator=g))
    s0, goals = torch.randn(3, 4, generator=g), torch.randn(3, 2, generator=g)
    keys = problem_keys(range(3), "cpu")
    config = planner_config(
        horizon=3, candidates=16, elites=4, iterations=3, prior_weight=0.5, support_weight=0.7
    )
    plan = SkillPlanner(model, config, support).plan(s0, GoalCost(goals), keys)
    task = GoalCost(goals)(plan.states[:, None])[:, 0]
    prior = 0.5 * plan.eps.pow(2).mean(dim=(1, 2))
    distance = support.excess(model.norm_states(plan.states[:, :-1]), plan.z).sum(dim=-1)
    assert distance.min() > 0
    torch.testing.assert_close(plan.objective, task + prior + 0.7 * distance, atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="support"):
        SkillPlanner(model, config)


def test_a_heavy_support_weight_keeps_the_first_skill_near_the_data(model):
    """With one pair in the bank, the plans' first skills move towards its skill."""
    target = torch.tensor([[1.5, -1.0, 0.5]])
    s0 = torch.randn(4, 4, generator=torch.Generator().manual_seed(3))
    support = SkillSupport(model.norm_states(s0[:1]), target)
    keys = problem_keys(range(4), "cpu")
    gaps = {}
    for weight in (0.0, 50.0):
        config = planner_config(
            horizon=2, candidates=64, elites=8, iterations=12, prior_weight=0.0,
            support_weight=weight,
        )  # fmt: skip
        plan = SkillPlanner(model, config, support).plan(s0, GoalCost(torch.zeros(4, 2)), keys)
        gaps[weight] = (plan.z[:, 0] - target).norm(dim=-1)
    assert (gaps[50.0] < 0.5 * gaps[0.0]).all(), gaps


def test_the_report_names_the_support_settings_only_when_the_cost_uses_them():
    plain = _planner_settings(PlannerParams())
    assert not any(k.startswith(("support", "data_skills")) for k in plain)
    used = _planner_settings(PlannerParams(support_weight=2.0, support_windows=100))
    assert used["support_weight"] == 2.0 and used["support_windows"] == 100
    assert used["support_quantile"] == 0.9
    assert "data_skills" not in used
    assert _planner_settings(PlannerParams(data_skills=8))["data_skills"] == 8


def test_local_skills_are_those_of_the_nearest_starts_and_snap_picks_the_nearest_of_them():
    g = torch.Generator().manual_seed(5)
    starts, skills = torch.randn(30, 4, generator=g), 2.0 * torch.randn(30, 3, generator=g)
    support = SkillSupport(starts, skills)
    here = torch.randn(2, 4, generator=g)
    local = support.local_skills(here, 5)
    assert local.shape == (2, 5, 3)
    for b in range(2):  # brute force: the skills of the 5 nearest starts, nearest first
        order = (starts - here[b]).norm(dim=-1).argsort()[:5]
        assert torch.equal(local[b], skills[order])
    proposals = torch.randn(2, 7, 3, generator=g)
    snapped = support.snap(proposals, local)
    scale = skills.std(dim=0)
    for b in range(2):
        for k in range(7):
            nearest = ((local[b] - proposals[b, k]) / scale).norm(dim=-1).argmin()
            assert torch.equal(snapped[b, k], local[b, nearest])


def test_with_data_skills_every_plans_first_skill_is_one_of_the_data_skills_near_its_start(model):
    g = torch.Generator().manual_seed(6)
    support = SkillSupport(torch.randn(40, 4, generator=g), torch.randn(40, 3, generator=g))
    s0, goals = torch.randn(3, 4, generator=g), torch.randn(3, 2, generator=g)
    config = planner_config(horizon=3, candidates=16, elites=4, iterations=3, data_skills=4)
    plan = SkillPlanner(model, config, support).plan(
        s0, GoalCost(goals), problem_keys(range(3), "cpu")
    )
    local = support.local_skills(model.norm_states(s0), 4)
    for b in range(3):
        assert (plan.z[b, 0] == local[b]).all(dim=-1).any()  # the executed skill is a data skill
    # The later skills stay CEM's: the prior's at their states, not snapped.
    assert not (plan.z[:, 1:, None] == support.skills[None, None]).all(dim=-1).any()
    torch.testing.assert_close(
        plan.objective,
        GoalCost(goals)(plan.states[:, None])[:, 0] + 2.0 * plan.eps.pow(2).mean(dim=(1, 2)),
        atol=1e-4, rtol=0,
    )  # fmt: skip
