"""The deploy baselines on small real things: BC / GCBC policies (hindsight goals, a few-step fit,
checkpoints), the low-level planner (LLP) on tiny random models, the expert agent reaching goals
through the episode runner, FLOPs counted around one replan."""

import numpy as np
import pytest
import torch
from factories import dynamics_config, llp_config, make_info, make_skill_episodes, policy_config

from pipeline.config import BCParams, GCBCParams, LLPParams
from pipeline.envs.batch import BatchSim
from pipeline.envs.maze.expert import ExpertConfig
from pipeline.envs.spec import PointMazeSpec
from pipeline.errors import UserError
from pipeline.evaluation.episodes import RunConfig, run_episodes
from pipeline.evaluation.flops import replan_flops
from pipeline.evaluation.tasks import MazeTasks
from pipeline.model.checkpoint import load_policy, save_policy
from pipeline.model.dynamics import DynamicsModel
from pipeline.model.policy import GaussianPolicy
from pipeline.planning.agents import ExpertAgent, PolicyAgent
from pipeline.planning.costs import GoalCost
from pipeline.planning.llp import LowLevelMPC, LowLevelPlanner
from pipeline.planning.noise import problem_keys
from pipeline.segments import build_segments
from pipeline.sources.ogbench import generate_ogbench, make_recipe
from pipeline.training.bc import episode_ends, fit_policy, hindsight_goals

ENV_ID = "PointMaze_Medium-v3"
SPLIT = {"train": 0.6, "validation": 0.2, "test": 0.2}


@pytest.fixture(scope="module")
def segments():
    episodes = make_skill_episodes(10, 60, seed=0)
    return build_segments(episodes, make_info("skills", physics_dim=0), 11, 1, SPLIT, seed=0)


def test_hindsight_goals_are_later_states_of_the_same_episode(segments):
    offsets = segments.episode_offsets
    steps = np.arange(offsets[-1])
    goals = hindsight_goals(segments, steps, np.random.default_rng(0))
    last = episode_ends(segments, steps)
    assert np.all(goals <= last) and np.all(goals >= np.minimum(steps + 1, last))
    assert np.array_equal(goals[last == steps], steps[last == steps])  # an episode's last step
    episode_of = np.searchsorted(offsets, steps, "right")
    assert np.array_equal(np.searchsorted(offsets, goals, "right"), episode_of)
    # Uniform over the rest of the episode: from the first step, goals spread over all of it.
    first = np.full(4000, offsets[0])
    spread = hindsight_goals(segments, first, np.random.default_rng(1)) - offsets[0]
    assert spread.min() == 1 and spread.max() == last[0] - offsets[0]
    assert abs(spread.mean() - (1 + last[0] - offsets[0]) / 2) < 1.5


@pytest.mark.parametrize("params", [BCParams, GCBCParams])
def test_a_few_fitting_steps_lower_the_nll_and_the_checkpoint_round_trips(
    segments, params, tmp_path
):
    cfg = params(hidden=16, max_steps=60, eval_every=30, batch_size=64, val_transitions=100)
    goal_dims = (0, 1) if params is GCBCParams else ()
    torch.manual_seed(0)
    untrained = GaussianPolicy(
        policy_config(4, 2, goal_dims, hidden=16, learned_std=cfg.learned_std)
    )
    policy, metrics = fit_policy(segments, cfg, torch.device("cpu"), goal_dims)
    assert policy.goal_conditioned == bool(goal_dims) and metrics["best_step"] in (30, 60)
    s = torch.as_tensor(segments.states[:50])
    a = torch.as_tensor(segments.actions[:50])
    g = s[:, :2] if goal_dims else None
    untrained.set_normalization({"action_std": policy.action_std.numpy()})
    assert policy.nll(s, a, g).mean() < untrained.nll(s, a, g).mean()
    if not cfg.learned_std:  # OGBench's constant std: 1 in normalized units
        assert torch.allclose(policy.normalized(s, g)[1], torch.ones(50, 2))
    kind = "gcbc" if goal_dims else "bc"
    save_policy(policy, tmp_path / kind, kind, {"dataset": "skills"})
    loaded, meta = load_policy(tmp_path / kind, kind)
    assert meta["kind"] == kind and loaded.config == policy.config
    assert torch.equal(loaded.action_stats(s, g)[0], policy.action_stats(s, g)[0])
    other = "bc" if kind == "gcbc" else "gcbc"
    with pytest.raises(UserError, match=f"not {other}; run `oposm {other}`"):
        load_policy(tmp_path / kind, other)
    with pytest.raises(UserError, match="run `oposm bc` first"):
        load_policy(tmp_path / "missing", "bc")


@pytest.fixture(scope="module")
def ogbench_segments():
    """6 navigate episodes x 301 steps of OGBench's point-maze recipe, half of them validation."""
    data = generate_ogbench(make_recipe("pointmaze-medium-v0", "navigate", 6, 301, seed=5), "gen")
    split = {"train": 0.5, "validation": 0.5, "test": 0.0}
    return build_segments(list(data.episodes), data.info, 26, 1, split, seed=0)


def test_gcbc_as_ogbench_fits_in_raw_units_and_keeps_its_last_parameters(ogbench_segments):
    """OGBench's GCBC sees raw observations and goals, has std 1 in raw action units and is
    evaluated with its final parameters (`normalize: false`, `keep: last`)."""
    cpu = torch.device("cpu")
    common = dict(hidden=32, batch_size=64, val_transitions=300, lr=1e-2, max_steps=60)
    best, best_metrics = fit_policy(
        ogbench_segments, GCBCParams(**common, eval_every=10), cpu, (0, 1)
    )
    # This run's best validation NLL is before its end, so keeping the last parameters differs.
    assert best_metrics["best_step"] < 60 and best_metrics["normalized"]
    raw = GCBCParams(**common, eval_every=10, normalize=False, keep="last")
    last, metrics = fit_policy(ogbench_segments, raw, cpu, (0, 1))
    assert (metrics["best_step"], metrics["kept"], metrics["normalized"]) == (60, "last", False)
    # The same run validated only at its end (nothing else differs: validation draws no
    # training randomness) ends with the same parameters.
    once, _ = fit_policy(ogbench_segments, raw.model_copy(update={"eval_every": 60}), cpu, (0, 1))
    for (k, a), b in zip(last.state_dict().items(), once.state_dict().values(), strict=True):
        assert torch.equal(a, b), k
    for name in ("state_mean", "action_mean"):
        assert torch.equal(getattr(last, name), torch.zeros_like(getattr(last, name)))
    for name in ("state_std", "action_std"):
        assert torch.equal(getattr(last, name), torch.ones_like(getattr(last, name)))
    s = torch.as_tensor(ogbench_segments.states[:20])
    mean, std = last.action_stats(s, s)
    assert torch.equal(std, torch.ones(20, 2))  # const std: 1 raw action unit
    assert torch.equal(mean, last.net(torch.cat([s, s], -1))[0])  # raw inputs, raw actions
    assert not torch.equal(best.state_mean, last.state_mean)  # the default whitens


@pytest.fixture(scope="module")
def llp_models():
    torch.manual_seed(0)
    policy = GaussianPolicy(policy_config(4, 2, hidden=16)).eval()
    dynamics = DynamicsModel(dynamics_config(4, 2, hidden=16)).eval()
    dynamics.set_normalization({"delta_std": np.full(4, 0.05)})
    return policy, dynamics


def test_llp_plans_actions_along_its_predicted_states(llp_models):
    policy, dynamics = llp_models
    planner = LowLevelPlanner(
        policy, dynamics, llp_config(horizon=6, execute=3, candidates=16, elites=4, iterations=3)
    )
    s0 = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1.0, -1.0, 0.2, 0.0]])
    goals = torch.tensor([[1.0, 1.0], [-1.0, 0.5]])
    plan = planner.plan(s0, GoalCost(goals), problem_keys([1, 2], "cpu"))
    assert plan.eps.shape == (2, 6, 2) and plan.actions.shape == (2, 6, 2)
    assert plan.states.shape == (2, 7, 4) and torch.equal(plan.states[:, 0], s0)
    # The actions are the BC policy's whitened ones at the predicted states, and the states are
    # the single-step model's mean rollout of those actions (what the agent executes open loop).
    mean, std = policy.action_stats(plan.states[:, :-1])
    assert torch.allclose(plan.actions, mean + std * plan.eps, atol=1e-6)
    assert torch.allclose(dynamics.rollout(s0, plan.actions), plan.states, atol=1e-6)
    expected = torch.linalg.vector_norm(plan.states[:, 1:, :2] - goals[:, None], dim=-1).amin(-1)
    assert torch.allclose(plan.cost, expected)
    # One problem's plan does not depend on the other problems in the batch.
    alone = planner.plan(s0[1:], GoalCost(goals[1:]), problem_keys([2], "cpu"))
    assert torch.allclose(alone.eps[0], plan.eps[1], atol=1e-6)
    with pytest.raises(ValueError, match="p\\(a \\| s\\)"):
        LowLevelPlanner(
            GaussianPolicy(policy_config(4, 2, (0, 1), hidden=8)), dynamics, llp_config()
        )


def test_llp_params_are_the_paper_codes_and_checked():
    cfg = llp_config()  # from LLPParams()
    assert (cfg.horizon, cfg.execute, cfg.l2_penalty, cfg.plan_from) == (20, 5, 0.01, "mean")
    assert (cfg.cem.candidates, cfg.cem.elites, cfg.cem.iterations) == (100, 20, 5)
    assert not cfg.warm_start
    with pytest.raises(ValueError, match="execute"):
        LLPParams(horizon=4, execute=5)


def test_llp_agent_executes_its_plan_then_replans(llp_models):
    policy, dynamics = llp_models
    agent = LowLevelMPC(
        LowLevelPlanner(
            policy, dynamics, llp_config(horizon=4, execute=2, candidates=8, elites=2, iterations=2)
        )
    )
    agent.reset(np.array([[1.0, 1.0], [0.0, 1.0], [2.0, 0.0]]), [5, 6, 7])
    rows, states = np.array([0, 2]), np.zeros((2, 4))
    plan = agent.replan(rows, states)
    first, second = agent.act(rows, states), agent.act(rows, states)
    np.testing.assert_allclose(first, plan.actions[:, 0].double().numpy())
    np.testing.assert_allclose(second, plan.actions[:, 1].double().numpy())
    assert replan_flops(agent, np.zeros(4), np.array([1.0, 1.0]), 3) > 0


def test_gcbc_agent_acts_towards_each_slots_goal():
    torch.manual_seed(0)
    policy = GaussianPolicy(policy_config(4, 2, (0, 1), hidden=16)).eval()
    agent = PolicyAgent(policy)
    goals = np.array([[1.0, 1.0], [-2.0, 0.5]])
    agent.reset(goals, [1, 2])
    states = np.zeros((2, 4))
    out = agent.act(np.array([1, 0]), states)
    expected = policy.action_stats(torch.zeros(2, 4), torch.as_tensor(goals[[1, 0]]).float())[0]
    np.testing.assert_allclose(out, expected.double().numpy(), rtol=1e-6)
    sampler = PolicyAgent(policy, sample_actions=True)
    sampler.reset(goals, [1, 2])
    a = sampler.act(np.array([0, 1]), states)
    sampler.reset(goals, [1, 2])
    np.testing.assert_array_equal(a, sampler.act(np.array([0, 1]), states))  # seeded per episode
    with pytest.raises(ValueError, match="goal-conditioned"):
        PolicyAgent(GaussianPolicy(policy_config(4, 2, hidden=8)))


def test_expert_agent_reaches_its_goals_through_the_episode_runner():
    spec = PointMazeSpec.create(ENV_ID)
    centers = np.asarray(spec.layout["free_cell_centers"])
    tasks = MazeTasks(spec.layout, centers, seed=0)
    specs = tasks.episodes("corners", 1) + tasks.episodes("random_goal", 5)
    agent = ExpertAgent(spec.layout, ExpertConfig())  # D4RL's gains and noise (0.5)
    results, calls = run_episodes(agent, BatchSim(spec, 3), specs, RunConfig(600, None))
    assert calls == []  # a static controller never plans
    assert all(r.success and r.error is None and r.agent == "expert" for r in results)
    assert all(r.replans == 0 and r.plan_seconds == 0.0 for r in results)
    assert results[0].steps_to_goal > 100  # corners: across the maze
