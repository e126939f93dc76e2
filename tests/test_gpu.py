"""CUDA gives what the CPU gives: the training objectives and their gradients, an EM step, the skill
rollout, and the skill MPC (warm start included) in closed loop. Skipped without a CUDA GPU
(`tests/conftest.py`). Random streams differ between devices, so comparisons use the same z / eps
on both; float32 throughout, as training and deployment run."""

import copy
from dataclasses import replace

import numpy as np
import pytest
import torch
from factories import planner_config, skill_model_config, train_updater

from pipeline.envs.batch import BatchSim
from pipeline.envs.spec import PointMazeSpec
from pipeline.evaluation.episodes import RunConfig, run_episodes
from pipeline.evaluation.tasks import EpisodeSpec
from pipeline.model import SkillModel
from pipeline.planning import GoalCost, PlannerConfig, SkillPlanner, problem_keys
from pipeline.planning.fused import PlannerNets
from pipeline.planning.mpc import SkillMPC
from pipeline.planning.triton_rollout import TritonNets
from pipeline.training.cuda_graphs import CudaGraphUpdater
from pipeline.training.data import WindowBatch
from pipeline.training.losses import e_objective, m_objective, vi_objective

pytestmark = pytest.mark.gpu
CLOSE = {"rtol": 1e-4, "atol": 1e-4}


def _model() -> SkillModel:
    torch.manual_seed(0)
    model = SkillModel(skill_model_config(4, 2, z_dim=8, hidden=64))
    model.set_normalization([0.5, -0.5, 0.0, 0.0], [2.0, 2.0, 1.0, 1.0], [0.0, 0.0], [0.5, 0.5])
    return model


def _objectives(model: SkillModel, batch: WindowBatch, z: torch.Tensor) -> dict:
    """The three objectives at fixed z, and the gradients of their sum in every parameter."""
    q = model.posterior_dist(batch.states[:, :-1], batch.actions)
    losses = {
        "e": e_objective(model, batch, q, z),
        "m": m_objective(model, batch, z)[0],
        "vi": vi_objective(model, batch, q, z)[0],
    }
    grads = torch.autograd.grad(sum(losses.values()), list(model.parameters()))
    return {k: v.detach().cpu() for k, v in losses.items()} | {
        f"grad{i}": g.cpu() for i, g in enumerate(grads)
    }


def check_training_matches_cpu(device: str) -> None:
    """Without TF32 in cuDNN's GRU (torch's default allows it) the gradients agree to 1e-4;
    with it they differ by up to 2e-3 (measured on an H100, `bench/gpu_profile.py`)."""
    previous = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = False
    try:
        _check_training_matches_cpu(device)
    finally:
        torch.backends.cudnn.allow_tf32 = previous


def _check_training_matches_cpu(device: str) -> None:
    g = torch.Generator().manual_seed(1)
    batch = WindowBatch(torch.randn(32, 11, 4, generator=g), torch.randn(32, 10, 2, generator=g))
    z = torch.randn(32, 8, generator=g)
    cpu = _model()
    dev = copy.deepcopy(cpu).to(device)
    want = _objectives(cpu, batch, z)
    dev_batch = WindowBatch(batch.states.to(device), batch.actions.to(device))
    got = _objectives(dev, dev_batch, z.to(device))
    for name in want:
        torch.testing.assert_close(got[name], want[name], **CLOSE, msg=name)
    # A whole EM step runs on the device and moves the weights (z noise differs by device).
    before = [p.detach().cpu().clone() for p in dev.parameters()]
    metrics = train_updater(dev, lr_e=1e-3, lr_m=1e-3, e_prior="current").step(dev_batch)
    assert all(bool(torch.isfinite(v)) for v in metrics.values())
    assert all(not torch.equal(b, p.cpu()) for b, p in zip(before, dev.parameters(), strict=True))


def check_compiled_training_step_matches_eager(device: str) -> None:
    """`train.compile`: EM and VI steps with compiled losses draw the same skills and end at the
    weights and metrics of eager steps (float rounding aside)."""
    g = torch.Generator().manual_seed(4)
    batch = WindowBatch(torch.randn(32, 11, 4, generator=g), torch.randn(32, 10, 2, generator=g))
    batch = WindowBatch(batch.states.to(device), batch.actions.to(device))
    for make in (
        lambda m, c: train_updater(m, lr_e=1e-3, lr_m=1e-3, e_prior="current", compile=c),
        lambda m, c: train_updater(m, method="vi", lr_m=1e-3, compile=c),
    ):
        runs = []
        graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
        for compile in (False, True):
            model = _model().to(device)
            updater = make(model, compile)
            torch.manual_seed(5)
            metrics = [updater.step(batch) for _ in range(3)]
            runs.append((model, metrics))
        (eager, want), (compiled, got) = runs
        assert torch._dynamo.utils.counters["stats"]["unique_graphs"] > graphs  # it compiled
        for w, c in zip(want, got, strict=True):
            assert w.keys() == c.keys()
            for name in w:
                torch.testing.assert_close(c[name], w[name], rtol=1e-3, atol=1e-3, msg=name)
        for w, c in zip(eager.parameters(), compiled.parameters(), strict=True):
            torch.testing.assert_close(c, w, rtol=1e-3, atol=1e-3)


def check_cuda_graph_training_matches_eager(device: str) -> None:
    """`train.cuda_graph`: EM and VI steps (and EM in bfloat16) replayed as CUDA graphs (step 1
    eager, capture on step 2) draw the same skills and end at eager's weights and metrics, batch
    after batch; a non-finite batch changes nothing."""
    g = torch.Generator().manual_seed(6)
    batches = [
        WindowBatch(
            torch.randn(32, 11, 4, generator=g).to(device),
            torch.randn(32, 10, 2, generator=g).to(device),
        )
        for _ in range(5)
    ]
    previous = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = False
    try:
        for make in (
            lambda m: train_updater(m, lr_e=1e-3, lr_m=1e-3, e_prior="current", grad_clip=1.0),
            lambda m: train_updater(m, method="vi", lr_m=1e-3),
            # train.dtype bfloat16: autocast inside the captured losses (no weight-cast cache)
            lambda m: train_updater(
                m, lr_e=1e-3, lr_m=1e-3, e_prior="current", grad_clip=1.0, dtype="bfloat16"
            ),
        ):
            runs = []
            for graphed in (False, True):
                model = _model().to(device)
                updater = CudaGraphUpdater(make(model)) if graphed else make(model)
                torch.manual_seed(5)
                metrics = [{k: v.clone() for k, v in updater.step(b).items()} for b in batches]
                runs.append((model, metrics, updater))
            (eager, want, _), (model, got, updater) = runs
            assert updater._captured is not None  # it replayed graphs
            for w, c in zip(want, got, strict=True):
                assert w.keys() == c.keys()
                for name in w:
                    torch.testing.assert_close(c[name], w[name], **CLOSE, msg=name)
            for w, c in zip(eager.parameters(), model.parameters(), strict=True):
                torch.testing.assert_close(c, w, **CLOSE)
            before = [p.detach().clone() for p in model.parameters()]
            bad = WindowBatch(batches[0].states.clone(), batches[0].actions)
            bad.states[0, 0, 0] = float("nan")
            metrics = updater.step(bad)
            assert not all(bool(torch.isfinite(v)) for v in metrics.values())
            for b, p in zip(before, model.parameters(), strict=True):
                assert torch.equal(b, p)
    finally:
        torch.backends.cudnn.allow_tf32 = previous


def _chain(model: SkillModel, s0: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """States `[B, L + 1, sd]` of whitened skills `eps [B, L, z]` chained through the prior and
    the TAWM mean, one skill at a time, with the model's raw-unit interface."""
    states = [s0]
    for k in range(eps.shape[1]):
        mean, std = model.skill_prior(states[-1])
        states.append(model.predict_end(states[-1], mean + std * eps[:, k])[0])
    return torch.stack(states, dim=1)


def check_planning_matches_cpu(device: str) -> None:
    cpu = _model().eval()
    dev = copy.deepcopy(cpu).to(device)
    g = torch.Generator().manual_seed(2)
    s0, eps = torch.randn(16, 4, generator=g), torch.randn(16, 4, 8, generator=g)
    got = _chain(dev, s0.to(device), eps.to(device))
    torch.testing.assert_close(got.cpu(), _chain(cpu, s0, eps), **CLOSE)

    # The MPC on the device, twice (the second replan warm-starts), then in closed loop.
    config = planner_config(horizon=4, candidates=32, elites=8, iterations=4, prior_weight=0.0)
    agent = SkillMPC(dev, SkillPlanner(dev, config), sample_actions=False)
    agent.reset(np.array([[1.0, 1.0], [-1.0, 0.5]]), seeds=[1, 2])
    states = np.array([[0.5, 0.5, 0.0, 0.0], [-0.5, 1.0, 0.1, -0.1]])
    for _ in range(2):
        plan = agent.replan(np.array([0, 1]), states)
    assert plan.eps.device.type == torch.device(device).type
    cpu_states = _chain(cpu, torch.as_tensor(states).float(), plan.eps.cpu())
    torch.testing.assert_close(plan.states.cpu(), cpu_states, **CLOSE)
    actions = agent.act(np.array([0, 1]), states)
    want = cpu.act(torch.as_tensor(states).float(), plan.z[:, 0].cpu()).double().numpy()
    np.testing.assert_allclose(actions, want, **CLOSE)

    specs = [
        EpisodeSpec("goal", i, np.array([x, y, 0.0, 0.0]), np.array([1.0, 1.0]), i)
        for i, (x, y) in enumerate([(-1.0, 1.0), (1.0, -1.0)])
    ]
    results, calls = run_episodes(
        agent, BatchSim(PointMazeSpec.create("PointMaze_Medium-v3"), 2), specs, RunConfig(30, 10)
    )
    assert all(r.error is None and r.steps == 30 and r.replans == 3 for r in results)
    assert [c.envs for c in calls] == [2, 2, 2]


def check_graphed_planner_matches_eager(device: str) -> None:
    """The compiled, CUDA-graph planner gives the eager plans on the device and on the CPU (the
    noise streams are the same on every device); padded batch sizes and a second replay too."""
    cpu = _model().eval()
    dev = copy.deepcopy(cpu).to(device)
    g = torch.Generator().manual_seed(3)
    s0, goals = torch.randn(3, 4, generator=g), torch.randn(3, 2, generator=g)
    config = planner_config(horizon=4, candidates=32, elites=8, iterations=6, prior_weight=0.5)
    graphed = SkillPlanner(dev, PlannerConfig(**{**config.__dict__, "compile": True}))
    for rows in (slice(0, 3), slice(1, 3), slice(0, 3)):  # 3 -> graph of 4, 2 -> graph of 2
        keys = problem_keys([7, 8, 9], "cpu")[rows]
        want = SkillPlanner(cpu, config).plan(s0[rows], GoalCost(goals[rows]), keys)
        for planner in (SkillPlanner(dev, config), graphed):
            got = planner.plan(
                s0[rows].to(device), GoalCost(goals[rows].to(device)), keys.to(device)
            )
            for field in ("eps", "states", "cost", "objective"):
                torch.testing.assert_close(
                    getattr(got, field).cpu(), getattr(want, field), rtol=1e-3, atol=1e-3
                )
    assert sorted(graphed._graphs) == [2, 4]


@torch.no_grad()
def check_triton_planner_matches_torch(device: str) -> None:
    """`deploy.planner.kernel: triton` on the GPU: eager, and compiled + CUDA graph, the torch
    planner's plans (float32, IEEE products in the kernel); in bfloat16, the torch bfloat16
    rollout within bf16 rounding."""
    model = _model().to(device)
    g = torch.Generator().manual_seed(5)
    s0, goals = torch.randn(3, 4, generator=g).to(device), torch.randn(3, 2, generator=g).to(device)
    keys = problem_keys([4, 5, 6], device)
    config = planner_config(
        horizon=4, candidates=100, elites=20, iterations=8, prior_weight=0.5, skill_penalty=0.05
    )
    want = SkillPlanner(model, config).plan(s0, GoalCost(goals), keys)
    for compile in (False, True):
        fused = replace(config, kernel="triton", compile=compile)
        for _ in range(2):  # the second: a replay
            got = SkillPlanner(model, fused).plan(s0, GoalCost(goals), keys)
            for field in ("eps", "states", "cost", "objective"):
                torch.testing.assert_close(getattr(got, field), getattr(want, field), **CLOSE)
    planner = SkillPlanner(model, config)
    eps = torch.randn(3, 50, 4, 8, generator=g).to(device)
    nets = PlannerNets(model, torch.bfloat16)
    s0_n = model.norm_states(s0)
    prior0 = nets.prior(s0_n)
    states, skills, _ = planner._rollout(eps, nets, s0, s0_n, prior0)
    bf16, fp32 = TritonNets(model, torch.bfloat16), TritonNets(model)
    got = bf16.rollout_cost(eps, s0, s0_n, prior0, bf16.goal_inputs(goals, (0, 1)), 0)
    torch.testing.assert_close(got[0], states, rtol=5e-2, atol=5e-2)
    torch.testing.assert_close(got[1], skills, rtol=5e-2, atol=5e-2)
    exact = fp32.rollout_cost(eps, s0, s0_n, prior0, fp32.goal_inputs(goals, (0, 1)), 0)
    assert not torch.equal(got[0], exact[0])  # it ran in bf16


def test_training_objectives_gradients_and_an_em_step_on_cuda_match_cpu():
    check_training_matches_cpu("cuda")


def test_compiled_training_step_on_cuda_matches_eager():
    check_compiled_training_step_matches_eager("cuda")


def test_cuda_graph_training_step_matches_eager():
    check_cuda_graph_training_matches_eager("cuda")


def test_skill_rollout_and_mpc_on_cuda_match_cpu():
    check_planning_matches_cpu("cuda")


def test_compiled_cuda_graph_planner_matches_eager_and_cpu():
    check_graphed_planner_matches_eager("cuda")


def test_triton_planner_matches_torch_on_cuda():
    check_triton_planner_matches_torch("cuda")
