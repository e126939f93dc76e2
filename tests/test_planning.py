"""The planner: CEM on known problems, batch independence, the goal cost, skill rollouts, MPC,
the counter-based noise streams, and the compiled planner against eager."""

import numpy as np
import pytest
import torch
from factories import planner_config, small_skill_model

from pipeline.errors import UserError
from pipeline.model import SkillModel
from pipeline.model.rollout import rollout_skills
from pipeline.planning import (
    CEM,
    CEMConfig,
    GoalCost,
    SkillPlanner,
    problem_keys,
    shift_plan,
    substream,
)
from pipeline.planning.fused import PlannerNets
from pipeline.planning.mpc import SkillMPC
from pipeline.planning.noise import normal

CENTRES = torch.tensor([[[1.0, -2.0, 0.5], [0.0, 3.0, -1.0]], [[-4.0, 0.0, 2.0], [1.0, 1.0, 1.0]]])


def quadratic(centres: torch.Tensor, calls: list | None = None):
    """Cost sum((x - c_b)^2) of candidates `[B, K, 2, 3]`; extras: the candidates' first row."""

    def cost(x: torch.Tensor) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        if calls is not None:
            calls.append(x.shape[0])
        return (x - centres[:, None]).pow(2).sum(dim=(-1, -2)), (x[:, :, 0],)

    return cost


def test_cem_finds_the_minimum_of_a_quadratic():
    cem = CEM(CEMConfig(candidates=64, elites=8, iterations=40, min_std=0.0, stop_cost=None))
    mean = torch.zeros(2, 2, 3)
    result = cem.minimize(quadratic(CENTRES), mean, 2.0, problem_keys([0, 1], "cpu"))
    assert torch.allclose(result.best, CENTRES, atol=0.05)
    assert torch.equal(result.extras[0], result.best[:, 0])  # the best candidate's extras
    assert torch.allclose(result.mean, CENTRES, atol=0.05)
    assert (result.cost < 0.01).all() and (result.iterations == 40).all()
    # The returned cost is the returned candidate's.
    assert torch.allclose(result.cost, (result.best - CENTRES).pow(2).sum(dim=(1, 2)))


def test_cem_problems_planned_together_equal_planned_apart():
    # Early stop: problem 0 starts at its optimum and stops after one iteration, problem 1 runs on.
    centres = CENTRES.clone()
    cfg = CEMConfig(candidates=32, elites=6, iterations=15, min_std=0.0, stop_cost=0.05)
    mean = torch.stack([centres[0], torch.zeros(2, 3)])
    std = torch.stack([torch.full((2, 3), 0.01), torch.ones(2, 3)])
    calls: list = []
    keys = problem_keys([7, 8], "cpu")
    together = CEM(cfg).minimize(quadratic(centres, calls), mean, std, keys)
    assert together.iterations[0] == 1 < together.iterations[1] == len(calls)
    assert set(calls) == {2}  # fixed shapes: a stopped problem is frozen, not removed
    for b in range(2):
        alone = CEM(cfg).minimize(
            quadratic(centres[b : b + 1]), mean[b : b + 1], std[b : b + 1], keys[b : b + 1]
        )
        assert torch.equal(alone.best[0], together.best[b])
        assert torch.equal(alone.cost[0], together.cost[b])
        assert torch.equal(alone.mean[0], together.mean[b])
        assert alone.iterations[0] == together.iterations[b]


def test_cem_ignores_nan_costs_and_rejects_bad_settings():
    def cost(x):
        c = x.pow(2).sum(-1)
        return torch.where(x[..., 0] > 0, torch.nan, c), ()  # NaN on half of the space

    result = CEM(CEMConfig(32, 4, 10, 0.0, None)).minimize(
        cost, torch.zeros(1, 2), 1.0, problem_keys([0], "cpu")
    )
    assert torch.isfinite(result.cost).all() and result.best[0, 0] <= 0
    with pytest.raises(UserError, match="elites"):
        CEMConfig(candidates=10, elites=11, iterations=1, min_std=0.0, stop_cost=None)


def test_goal_cost_is_the_distance_of_the_nearest_predicted_state():
    # One problem, two candidates, L = 3 predicted states after s_0; goal at (1, 1).
    states = torch.zeros(1, 2, 4, 4)
    states[0, 0, :, :2] = torch.tensor([[1.0, 1.0], [4.0, 5.0], [1.0, 3.0], [7.0, 1.0]])
    states[0, 1, :, :2] = torch.tensor([[9.0, 9.0], [1.0, 1.5], [5.0, 5.0], [1.0, 1.0]])
    cost = GoalCost(torch.tensor([[1.0, 1.0]]))(states)
    # Candidate 0: s_0 is at the goal but is not a prediction; nearest predicted is 2.0 away.
    # Candidate 1: the last state reaches the goal exactly.
    assert torch.allclose(cost, torch.tensor([[2.0, 0.0]]))


def test_skill_penalty_prefers_the_plan_that_gets_there_sooner():
    # Two candidates reach the goal exactly, after skill 1 and after skill 3 (L = 3).
    states = torch.full((1, 2, 4, 2), 5.0)
    states[0, 0, 1] = states[0, 1, 3] = torch.tensor([1.0, 1.0])
    goal = torch.tensor([[1.0, 1.0]])
    assert torch.allclose(GoalCost(goal)(states), torch.tensor([[0.0, 0.0]]))  # the paper's
    late = GoalCost(goal, skill_penalty=0.5)
    assert torch.allclose(late(states), torch.tensor([[0.5, 1.5]]))
    # A nearer state later still wins when the penalty is smaller than what it gains.
    states[0, 1, 1] = torch.tensor([1.0, 3.0])  # 2 m away after skill 1: 2.5 against 1.5
    assert torch.allclose(late(states), torch.tensor([[0.5, 1.5]]))
    moved = late.with_goals(torch.tensor([[5.0, 5.0]]))
    assert moved.key == late.key == ((0, 1), 0.5, 0.0, None)
    with pytest.raises(ValueError, match="skill_penalty"):
        GoalCost(goal, skill_penalty=-1.0)


def test_fall_penalty_keeps_plans_from_predicted_falls():
    # Candidate 0 reaches the goal but its state after skill 2 is "fallen" (dim 2 below 0).
    states = torch.zeros(1, 2, 4, 3)
    states[0, 0, 1, :2] = torch.tensor([1.0, 1.0])
    states[0, 0, 2, 2] = -1.0
    states[0, 1, 3, :2] = torch.tensor([1.0, 2.0])  # 1 m short, upright throughout
    goal = torch.tensor([[1.0, 1.0]])

    def fallen(s: torch.Tensor) -> torch.Tensor:
        return s[..., 2] < 0

    assert torch.allclose(GoalCost(goal)(states), torch.tensor([[0.0, 1.0]]))
    cost = GoalCost(goal, fall_penalty=10.0, fallen=fallen)
    assert torch.allclose(cost(states), torch.tensor([[10.0, 1.0]]))
    assert cost.with_goals(goal).key == cost.key
    assert GoalCost(goal, fall_penalty=10.0).fall_penalty == 0.0  # nothing can fall


@pytest.fixture(scope="module")
def model() -> SkillModel:
    """A small skill model with random weights and non-trivial normalization."""
    return small_skill_model()


def test_rollout_chains_prior_and_tawm_means(model):
    s0 = torch.randn(2, 4)
    eps = torch.randn(2, 5, 3, 3)
    rollout = rollout_skills(model, s0[:, None], eps=eps)
    states, z = rollout.states, rollout.z
    assert states.shape == (2, 5, 4, 4) and z.shape == (2, 5, 3, 3)
    a, k = 1, 3  # one candidate by hand: z_i = mu(s_i) + sigma(s_i) eps_i, s_i+1 = TAWM mean
    s = s0[a]
    for i in range(3):
        mean, std = model.skill_prior(s)
        zi = mean + std * eps[a, k, i]
        assert torch.allclose(z[a, k, i], zi, atol=1e-6)
        s = model.predict_end(s, zi)[0]
        assert torch.allclose(states[a, k, i + 1], s, atol=1e-5)
    assert torch.equal(states[:, :, 0], s0[:, None].expand(2, 5, 4))
    # The same skills given directly chain to the same states (validate's posterior mode).
    again = rollout_skills(model, s0[:, None], z=z)
    torch.testing.assert_close(again.states, states, rtol=0, atol=0)
    torch.testing.assert_close(again.mean, states[:, :, 1:], rtol=0, atol=0)


def test_batched_planning_matches_planning_each_env_alone(model):
    planner = SkillPlanner(
        model, planner_config(horizon=3, candidates=24, elites=6, iterations=5, prior_weight=0.0)
    )
    s0, goals = torch.randn(3, 4), torch.randn(3, 2)
    seeds = [11, 12, 13]
    keys = problem_keys(seeds, "cpu")
    together = planner.plan(s0, GoalCost(goals), keys)
    for b in range(3):
        alone = planner.plan(s0[b : b + 1], GoalCost(goals[b : b + 1]), keys[b : b + 1])
        assert torch.allclose(alone.eps[0], together.eps[b], atol=1e-5)
        assert torch.allclose(alone.states[0], together.states[b], atol=1e-5)
        assert torch.allclose(alone.cost[0], together.cost[b], atol=1e-5)
    # The plan's states and skills, kept from the search, are the rollout of its eps from s_0.
    assert torch.equal(together.states[:, 0], s0)
    again = rollout_skills(model, s0, eps=together.eps)
    torch.testing.assert_close(together.states, again.states, rtol=0, atol=1e-5)
    torch.testing.assert_close(together.z, again.z, rtol=0, atol=1e-5)
    assert together.z.shape == (3, 3, 3)


def test_the_prior_penalty_keeps_plans_near_the_prior_mean(model):
    s0, goals = torch.randn(4, 4), 5 + torch.randn(4, 2)
    plans = {}
    for weight in (0.0, 100.0):
        config = planner_config(
            horizon=3, candidates=32, elites=8, iterations=5, prior_weight=weight
        )
        plans[weight] = SkillPlanner(model, config).plan(
            s0, GoalCost(goals), problem_keys(range(4), "cpu")
        )
    assert plans[100.0].eps.pow(2).mean() < 0.5 * plans[0.0].eps.pow(2).mean()
    # `cost` is the task cost of the returned plan; `objective` adds the penalty.
    for weight, plan in plans.items():
        task = GoalCost(goals)(plan.states[:, None])[:, 0]
        assert torch.allclose(plan.cost, task, atol=1e-5)
        penalty = weight * plan.eps.pow(2).mean(dim=(1, 2))
        assert torch.allclose(plan.objective, task + penalty, atol=1e-4)


def test_the_uncertainty_penalty_is_the_tawm_std_summed_over_the_plan(model):
    """`uncertainty_weight` adds w x the TAWM's std of each skill's outcome (the model's own
    `tawm_outcome`, normalized units, mean over dims), summed over the plan's skills."""
    s0, goals = torch.randn(3, 4), torch.randn(3, 2)
    keys = problem_keys(range(3), "cpu")
    plans = {}
    for weight in (0.0, 0.7):
        config = planner_config(
            horizon=3, candidates=16, elites=4, iterations=3, prior_weight=0.5,
            uncertainty_weight=weight,
        )  # fmt: skip
        plans[weight] = SkillPlanner(model, config).plan(s0, GoalCost(goals), keys)
    plan = plans[0.7]
    states_n = model.norm_states(plan.states)
    stds = model.tawm_outcome(states_n[:, :-1], plan.z)[1]  # each skill's outcome, [B, L, sd]
    uncertainty = stds.mean(dim=-1).sum(dim=-1)
    task = GoalCost(goals)(plan.states[:, None])[:, 0]
    prior = 0.5 * plan.eps.pow(2).mean(dim=(1, 2))
    torch.testing.assert_close(plan.objective, task + prior + 0.7 * uncertainty, atol=1e-4, rtol=0)
    assert uncertainty.min() > 0
    # Without the weight the objective has no uncertainty term.
    plain = plans[0.0]
    task = GoalCost(goals)(plain.states[:, None])[:, 0]
    torch.testing.assert_close(plain.objective, task + 0.5 * plain.eps.pow(2).mean(dim=(1, 2)),
                               atol=1e-5, rtol=0)  # fmt: skip


def test_mpc_warm_starts_from_the_shifted_plan_and_acts_with_the_policy(model):
    planner = SkillPlanner(
        model, planner_config(horizon=3, candidates=16, elites=4, iterations=3, prior_weight=0.0)
    )
    agent = SkillMPC(model, planner, sample_actions=False)
    agent.reset(np.zeros((2, 2)), seeds=[1, 2])
    states = np.random.default_rng(0).normal(size=(2, 4))
    first = agent.replan(np.array([0, 1]), states)
    expected = model.act(torch.as_tensor(states[1:], dtype=torch.float32), first.z[1:, 0])
    assert np.allclose(agent.act(np.array([1]), states[1:]), expected.numpy(), atol=1e-6)
    assert torch.equal(shift_plan(first.eps)[:, :2], first.eps[:, 1:])
    assert torch.equal(shift_plan(first.eps)[:, 2], torch.zeros(2, 3))
    # Sampled actions differ from the mean, reproducibly per episode seed.
    sampler = SkillMPC(model, planner, sample_actions=True)
    draws = []
    for _ in range(2):
        sampler.reset(np.zeros((2, 2)), seeds=[1, 2])
        sampler.replan(np.array([0, 1]), states)
        draws.append(sampler.act(np.array([0, 1]), states))
    assert np.array_equal(draws[0], draws[1])
    assert not np.allclose(draws[0], agent.act(np.array([0, 1]), states))


def test_noise_rows_depend_only_on_their_key_and_look_standard_normal():
    keys = problem_keys([3, 1, 4, 1_000_000_007_000], "cpu")
    z = normal(keys, (500, 6))
    assert z.shape == (4, 500, 6) and z.dtype == torch.float32
    for b in range(4):  # any batch: the same row
        assert torch.equal(normal(keys[b : b + 1], (500, 6))[0], z[b])
    assert abs(z.mean()) < 0.03 and abs(z.std() - 1) < 0.03
    assert torch.corrcoef(z.reshape(4, -1)).sub(torch.eye(4)).abs().max() < 0.06
    # Substreams (replans, iterations) differ; int and tensor counters give the same keys.
    sub = substream(keys, 5)
    assert torch.equal(sub, substream(keys, torch.full((4,), 5)))
    assert not torch.equal(sub, substream(keys, 6)) and not torch.equal(sub, keys)
    assert (substream(keys, torch.arange(4)) == torch.stack(
        [substream(keys[i : i + 1], i)[0] for i in range(4)])).all()  # fmt: skip


def test_planner_nets_equal_the_models_prior_and_tawm_mean(model):
    nets = PlannerNets(model)
    s, z = torch.randn(7, 4), torch.randn(7, 3)
    for ours, theirs in zip(nets.prior(s), model.prior(s), strict=True):
        torch.testing.assert_close(ours, theirs, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(
        nets.tawm_mean(s, z), model.tawm(torch.cat([s, z], -1))[0], rtol=1e-5, atol=1e-6
    )


def test_bfloat16_planner_nets_and_plans_stay_near_float32(model):
    """`deploy.planner.dtype: bfloat16`: the networks within bf16 rounding of the model, float32
    out; a plan as good as the float32 one on the same problems."""
    nets = PlannerNets(model, torch.bfloat16)
    s, z = torch.randn(64, 4), torch.randn(64, 3)
    mean, std = nets.prior(s)
    assert mean.dtype == std.dtype == torch.float32
    for ours, theirs in zip((mean, std), model.prior(s), strict=True):
        torch.testing.assert_close(ours, theirs, rtol=3e-2, atol=3e-2)
    exact = model.tawm(torch.cat([s, z], -1))[0]
    torch.testing.assert_close(nets.tawm_mean(s, z), exact, rtol=3e-2, atol=3e-2)
    assert not torch.equal(nets.tawm_mean(s, z), exact)  # it really ran in bf16
    s0, goals = torch.randn(6, 4), torch.randn(6, 2)
    keys = problem_keys(range(6), "cpu")
    costs = {}
    for dtype in ("float32", "bfloat16"):
        config = planner_config(
            horizon=3, candidates=64, elites=8, iterations=6, dtype=dtype, prior_weight=0.0
        )
        plan = SkillPlanner(model, config).plan(s0, GoalCost(goals), keys)
        assert plan.states.dtype == torch.float32
        costs[dtype] = plan.cost
    assert costs["bfloat16"].mean() <= 1.1 * costs["float32"].mean() + 0.02


@pytest.mark.slow
def test_compiled_planner_gives_the_eager_plans(model):
    s0, goals = torch.randn(3, 4), torch.randn(3, 2)
    keys = problem_keys([5, 6, 7], "cpu")
    plans = {}
    for compiled in (False, True):
        config = planner_config(
            horizon=3, candidates=24, elites=6, iterations=4, prior_weight=0.5, compile=compiled
        )
        plans[compiled] = SkillPlanner(model, config).plan(s0, GoalCost(goals), keys)
    for field in ("eps", "z", "states", "cost", "objective"):
        eager, fast = getattr(plans[False], field), getattr(plans[True], field)
        torch.testing.assert_close(fast, eager, rtol=1e-4, atol=1e-4)
    assert torch.equal(plans[True].iterations, plans[False].iterations)
