"""`deploy.planner.kernel: triton`: the fused rollout-and-cost kernel computes what the torch
rollout and `GoalCost` compute, and the planner built on it gives the torch planner's plans.

Without a GPU, Triton's interpreter runs the kernel on CPU tensors (NumPy, slow: small sizes);
with one, the same tests run the compiled kernel on CUDA. bfloat16 is checked on CUDA only
(tests/test_gpu.py): the interpreter has no bfloat16 arithmetic."""

import dataclasses

import pytest
import torch
from factories import planner_config, skill_model_config

from pipeline.model import SkillModel
from pipeline.planning import GoalCost, SkillPlanner, problem_keys
from pipeline.planning.fused import PlannerNets
from pipeline.planning.triton_rollout import TritonNets

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
CLOSE = {"rtol": 1e-5, "atol": 1e-5}


def _model(sd: int, z: int, hidden: int) -> SkillModel:
    torch.manual_seed(sd + z + hidden)
    model = SkillModel(skill_model_config(sd, 2, z_dim=z, hidden=hidden))
    for p in model.parameters():  # larger than the default init: states move well off s_0
        p.data.mul_(1.5)
    g = torch.Generator().manual_seed(1)
    mean, std = torch.randn(sd, generator=g), torch.rand(sd, generator=g) + 0.5
    model.set_normalization(mean.tolist(), std.tolist(), [0.0, 0.0], [1.0, 1.0])
    return model.to(DEVICE)


@pytest.mark.parametrize(
    ("sd", "z", "hidden", "dims", "penalty"),
    [
        (4, 8, 64, (0, 1), 0.0),  # the point maze's shapes, consecutive goal dims
        (29, 20, 40, (1, 0, 5), 0.1),  # all padded (29 -> 32, 20 -> 32, 40 -> 48), dims permuted
    ],
)
def test_kernel_equals_the_torch_rollout_and_goal_cost(sd, z, hidden, dims, penalty):
    model = _model(sd, z, hidden)
    planner = SkillPlanner(model, planner_config(horizon=4))  # its rollout only
    g = torch.Generator().manual_seed(2)
    b, k, n = 3, 21, 4  # 63 rows: the last program's tile is part padding
    eps = torch.randn(b, k, n, z, generator=g).to(DEVICE)
    s0 = torch.randn(b, sd, generator=g).to(DEVICE)
    goals = torch.randn(b, len(dims), generator=g).to(DEVICE)
    nets = PlannerNets(model)
    s0_n = model.norm_states(s0)
    prior0 = nets.prior(s0_n)
    states, skills, _ = planner._rollout(eps, nets, s0, s0_n, prior0)
    cost = GoalCost(goals, dims, skill_penalty=penalty)(states)
    fused = TritonNets(model)
    got = fused.rollout_cost(eps, s0, s0_n, prior0, fused.goal_inputs(goals, dims), penalty)
    assert states.abs().amax() > 1.0  # the rollout went somewhere
    for ours, theirs in zip(got, (states, skills, cost), strict=True):
        assert ours.shape == theirs.shape
        torch.testing.assert_close(ours, theirs, **CLOSE)


def test_planner_on_the_kernel_gives_the_torch_plans():
    model = _model(4, 8, 32)
    g = torch.Generator().manual_seed(3)
    s0, goals = torch.randn(2, 4, generator=g).to(DEVICE), torch.randn(2, 2, generator=g)
    keys = problem_keys([7, 8], DEVICE)
    config = planner_config(
        horizon=3, candidates=16, elites=4, iterations=3, prior_weight=0.5, skill_penalty=0.1
    )
    fused = SkillPlanner(model, dataclasses.replace(config, kernel="triton"))
    want = SkillPlanner(model, config).plan(s0, GoalCost(goals.to(DEVICE)), keys)
    got = fused.plan(s0, GoalCost(goals.to(DEVICE)), keys)
    for field in ("eps", "z", "states", "cost", "objective"):
        torch.testing.assert_close(getattr(got, field), getattr(want, field), **CLOSE)
    assert torch.equal(got.iterations, want.iterations)
    # A cost the kernel does not compute (a fall test) stays on the torch rollout.
    falls = GoalCost(goals.to(DEVICE), fall_penalty=5.0, fallen=lambda s: s[..., 2] > 0)
    assert fused._fused(GoalCost(goals)) and not fused._fused(falls)
    with pytest.raises(ValueError, match="kernel must be"):
        dataclasses.replace(planner_config(), kernel="cuda")
