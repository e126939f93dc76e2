"""The goal-conditioned value (`pipeline.value`): OGBench's value goals, the expectile loss, a
fit that learns steps to go on held-out episodes, the steps-to-go transform, the checkpoint, and
the planner's cost that adds it (`ValueGoalCost`), which is the paper's `GoalCost` at weight 0."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from factories import make_info, make_skill_episodes, one_line_error

from pipeline.config import ValueParams
from pipeline.planning.costs import GoalCost, ValueGoalCost
from pipeline.segments import build_segments
from pipeline.training.bc import episode_ends
from pipeline.value.fit import distance_samples, expectile_loss, fit_value, value_goals
from pipeline.value.network import GoalValue, ValueConfig, load_value, save_value

SPLIT = {"train": 0.7, "validation": 0.3, "test": 0.0}
RADIUS = 0.1


def near(states: np.ndarray, goals: np.ndarray) -> np.ndarray:
    return np.linalg.norm(states[:, :2] - goals, axis=-1) <= RADIUS


@pytest.fixture(scope="module")
def segments():
    episodes = make_skill_episodes(30, 80, seed=1)
    return build_segments(episodes, make_info("skills", physics_dim=0), 11, 1, SPLIT, seed=0)


def test_value_goals_are_the_step_a_later_step_of_its_episode_or_any_pool_step(segments):
    cfg = ValueParams(discount=0.9)
    steps = np.arange(segments.episode_offsets[-1] - 1)
    pool = np.arange(0, segments.episode_offsets[-1], 7)
    goals = value_goals(segments, np.repeat(steps, 20), pool, cfg, np.random.default_rng(0))
    repeated = np.repeat(steps, 20)
    current = goals == repeated
    ahead = (goals > repeated) & (goals <= episode_ends(segments, repeated))
    assert np.all(current | ahead | np.isin(goals, pool))
    assert abs(current.mean() - 0.2) < 0.03  # p_current (plus the rare pool hit on itself)
    gaps = (goals - repeated)[ahead & ~np.isin(goals, pool)]
    assert 5 < gaps.mean() < 12  # geometric with mean 1 / (1 - 0.9) = 10, cut at episode ends


def test_the_expectile_loss_weighs_positive_advantages_by_the_expectile():
    adv = torch.tensor([1.0, -1.0])
    diff = torch.tensor([2.0, 2.0])
    assert torch.allclose(expectile_loss(adv, diff, 0.9), torch.tensor([3.6, 0.4]))


def test_distance_samples_find_the_first_step_within_the_rule(segments):
    steps = np.arange(segments.episode_offsets[0], segments.episode_offsets[1] - 1)
    _, goals, took = distance_samples(segments, steps, (0, 1), near, 40, np.random.default_rng(0))
    for s, g, k in zip(steps, goals, took, strict=True):
        path = segments.states[s : s + k + 1, :2]
        hits = np.flatnonzero(np.linalg.norm(path - g, axis=-1) <= RADIUS)
        assert hits.size and hits[0] == k


def test_a_short_fit_learns_steps_to_go_on_held_out_episodes(segments):
    cfg = ValueParams(
        hidden=64, layers=2, discount=0.95, max_steps=600, eval_every=300, batch_size=128,
        lr=1e-3, val_transitions=400, eval_horizon=40,
    )  # fmt: skip
    value, metrics = fit_value(segments, cfg, torch.device("cpu"), (0, 1), near)
    first, last = metrics["history"][0], metrics["history"][-1]
    assert last["steps_to_go_spearman"] > 0.6, metrics["history"]
    assert last["steps_to_go_mae"] < first["steps_to_go_mae"]
    s = torch.as_tensor(segments.states[:5])
    at_goal = value.steps_to_go(s, s[:, :2])
    assert torch.all(at_goal < 3)  # the step itself is (nearly) reached
    again, _ = fit_value(segments, cfg.model_copy(update={"max_steps": 20}), "cpu", (0, 1), near)
    twice, _ = fit_value(segments, cfg.model_copy(update={"max_steps": 20}), "cpu", (0, 1), near)
    for a, b in zip(again.state_dict().values(), twice.state_dict().values(), strict=True):
        assert torch.equal(a, b)  # seeded: the same parameters


def _constant(value: GoalValue, v: float) -> GoalValue:
    """Every head outputs `v` (last layer's weights zero, bias v)."""
    with torch.no_grad():
        for head in value.heads:
            head[-1].weight.zero_()
            head[-1].bias.fill_(v)
    return value


def test_steps_to_go_inverts_the_discounted_return():
    value = GoalValue(ValueConfig(4, (0, 1), 8, 1, 2, 0.99))
    s = torch.randn(3, 4)
    for d in (0.0, 7.0, 150.0):
        v = -(1 - 0.99**d) / (1 - 0.99)
        assert torch.allclose(_constant(value, v).steps_to_go(s, s[:, :2]), torch.full((3,), d))
    never = _constant(value, -200.0).steps_to_go(s, s[:, :2])  # below -1/(1 - discount)
    assert torch.allclose(never, torch.full((3,), math.log(1e-6) / math.log(0.99)))


def test_the_checkpoint_round_trips_and_refuses_other_folders(tmp_path):
    torch.manual_seed(0)
    value = GoalValue(ValueConfig(4, (0, 1), 8, 2, 2, 0.99))
    value.set_normalization(np.arange(4.0), np.ones(4) * 2)
    save_value(value, tmp_path / "v", {"dataset": "skills"})
    loaded, meta = load_value(tmp_path / "v")
    s = torch.randn(6, 4)
    assert meta["dataset"] == "skills" and loaded.config == value.config
    assert torch.equal(loaded(s, s[:, :2]), value.eval()(s, s[:, :2]))
    assert "run `oposm value` first" in one_line_error(lambda: load_value(tmp_path / "none"))
    (tmp_path / "v" / "config.json").write_text('{"format": "oposm-policy"}')
    assert "re-run `oposm value`" in one_line_error(lambda: load_value(tmp_path / "v"))


def test_the_value_cost_is_the_goal_cost_at_weight_zero_and_adds_skills_to_go():
    torch.manual_seed(0)
    states = torch.randn(2, 5, 4, 3)  # B 2, K 5, L 3 skills (+ s_0), sd 3
    goals = torch.randn(2, 2)
    paper = GoalCost(goals, (0, 2), scale=(0.5, 2.0))

    def to_go(s, g):  # 10 steps per unit of distance
        return 10 * torch.linalg.vector_norm(s[..., [0, 2]] - g, dim=-1)

    zero = ValueGoalCost(goals, to_go, 0.0, 5, (0, 2), scale=(0.5, 2.0))
    assert torch.equal(zero(states), paper(states))
    cost = ValueGoalCost(goals, to_go, 0.5, 5, (0, 2), scale=(0.5, 2.0))
    per_skill = paper.per_skill(states)
    plain = torch.linalg.vector_norm(states[:, :, 1:, [0, 2]] - goals[:, None, None], dim=-1)
    expected = per_skill + 0.5 * (torch.arange(1.0, 4.0) + 10 * plain / 5)
    assert torch.allclose(cost(states), expected.amin(-1))
    moved = cost.with_goals(goals + 1)
    assert moved.key == cost.key and not torch.equal(moved(states), cost(states))
