"""The planning benchmark's reference (the paper's procedure, one environment at a time) and the
matmul roofline: the reference optimizes the same objective as the batched planner."""

import time
from pathlib import Path

import pytest
import torch
from factories import (
    make_info,
    make_skill_episodes,
    planner_config,
    small_skill_model,
)

from bench.reference import ReferencePlanner
from bench.roofline import matmul_gflops
from bench.train import bench_train, bench_train_dtypes
from pipeline.config import load_params
from pipeline.model.rollout import rollout_skills
from pipeline.paths import Paths
from pipeline.planning import GoalCost, SkillPlanner, problem_keys
from pipeline.segments import build_segments, save_segments


def test_reference_returns_its_plans_objective_and_matches_the_batched_planner():
    model = small_skill_model()
    config = planner_config(horizon=3, candidates=64, elites=8, iterations=8, prior_weight=0.5)
    s0, goals = torch.randn(3, 4), torch.randn(3, 2)
    reference = ReferencePlanner(model, config)
    batched = SkillPlanner(model, config).plan(s0, GoalCost(goals), problem_keys([1, 2, 3], "cpu"))
    for b in range(3):
        eps, cost = reference.plan_one(s0[b], goals[b], torch.Generator().manual_seed(b))
        states = rollout_skills(model, s0[b : b + 1], eps=eps[None]).states
        task = GoalCost(goals[b : b + 1])(states[:, None])[0, 0]
        assert abs(cost - float(task + 0.5 * eps.pow(2).mean())) < 1e-4
        # Same objective, other noise: both searches end near the same cost (and improve on
        # the prior's mean skills).
        zeros = rollout_skills(model, s0[b : b + 1], eps=torch.zeros(1, 3, 3)).states
        start = GoalCost(goals[b : b + 1])(zeros[:, None])[0, 0]
        assert cost <= start + 1e-4 and float(batched.objective[b]) <= start + 1e-4
        assert abs(cost - float(batched.objective[b])) < 0.1 * max(cost, 0.1)
    assert len(reference.plan(s0, goals, seed=0)) == 3


def test_matmul_roofline_is_the_products_flops_over_their_time():
    """The GFLOP/s reported are the FLOPs torch's profiler counts in the products that were run
    (less the 3 warm-up products) over a time that is at least the budget and at most the call's
    wall time: a miscounted product (a lost factor 2) or a wrong clock falls outside."""
    m, k, n, budget = 64, 48, 32, 0.05
    with torch.profiler.profile(
        activities=[torch.profiler.ProfilerActivity.CPU], with_flops=True, acc_events=True
    ) as prof:
        start = time.perf_counter()
        got = matmul_gflops(torch.device("cpu"), m, k, n, seconds=budget)
        wall = time.perf_counter() - start
    counted = sum(e.flops for e in prof.key_averages() if e.key == "aten::mm")
    per_product = 2 * m * k * n
    assert counted % per_product == 0 and counted // per_product > 3
    timed = counted - 3 * per_product
    assert budget <= timed / (got * 1e9) <= wall


ROOT = Path(__file__).resolve().parents[1]


def _tiny_training(tmp_path: Path, *overrides: str):
    """Params of a tiny skill model (batch 8) and `Paths` under `tmp_path` holding its segments."""
    episodes = make_skill_episodes(n_episodes=10, length=60, seed=0)
    split = {"train": 0.8, "validation": 0.1, "test": 0.1}
    segments = build_segments(episodes, make_info("skills", physics_dim=0), 11, 1, split, seed=0)
    params = load_params(
        ROOT / "params.yaml",
        ["ingest.name=tiny", "train.device=cpu", "train.hidden=16", "train.z_dim=4",
         "train.batch_size=8", *overrides],
    )  # fmt: skip
    paths = Paths(tmp_path)
    save_segments(segments, paths.segments("tiny"))
    return params, paths


def test_bench_train_times_steps_of_the_params_model_with_threads_auto(tmp_path):
    """`oposm bench train` with the params' defaults (`train.threads: auto`) on saved segments."""
    params, paths = _tiny_training(tmp_path)
    assert params.train.threads == "auto"
    got = bench_train(params, paths, steps=3, warmup=1)
    assert got["windows_per_s"] == 8 * got["steps_per_s"] > 0
    assert got["flops_per_step"] > 0 and 0 < got["roofline_fraction"] < 1
    # the paper's procedure beside it: a 4-layer encoder, so more products per step
    assert got["reference/flops_per_step"] > got["flops_per_step"]
    ratio = got["steps_per_s"] / got["reference/steps_per_s"]
    assert got["speedup_over_reference"] == pytest.approx(ratio)


def test_the_papers_em_step_learns_and_moves_only_what_each_half_updates():
    """THE REFERENCE of `oposm bench train` (`bench/reference_em.py`) is a real EM step: on one
    fixed batch its losses fall; the E-step moves the encoder only, the M-step the rest."""
    from bench.reference_em import ReferenceEM
    from pipeline.training.data import WindowBatch

    torch.manual_seed(0)
    batch = WindowBatch(torch.randn(8, 6, 4), torch.randn(8, 5, 2))
    ref = ReferenceEM(4, 2, z_dim=3, hidden=16, lr=1e-2)
    before = {n: p.detach().clone() for n, p in ref.named_parameters()}
    ref.e_optimizer.step = lambda: None  # an M-step alone: the encoder must stay
    ref.m_optimizer.step, m_step = (lambda: None), ref.m_optimizer.step
    first = ref.step(batch)
    assert all(torch.equal(p, before[n]) for n, p in ref.named_parameters())  # both stubbed
    ref.m_optimizer.step = m_step
    ref.step(batch)
    moved = {n.split(".")[0] for n, p in ref.named_parameters() if not torch.equal(p, before[n])}
    assert moved == {"prior", "policy", "tawm"}
    del ref.e_optimizer.step  # the real E-step again
    for _ in range(30):
        last = ref.step(batch)
    assert last["e_loss"] < first["e_loss"] and last["m_loss"] < first["m_loss"]


def test_bench_train_times_each_dtype_and_their_ratio(tmp_path):
    """`oposm bench train --dtypes float32,bfloat16`: both precisions timed, each against its
    own roofline, and the ratio of their steps/s."""
    params, paths = _tiny_training(tmp_path, "train.threads=1")
    got = bench_train_dtypes(params, paths, steps=2, dtypes=["float32", "bfloat16"])
    for dtype in ("float32", "bfloat16"):
        assert got[f"{dtype}/steps_per_s"] > 0 and got[f"{dtype}/roofline_gflops"] > 0
    ratio = got["bfloat16/steps_per_s"] / got["float32/steps_per_s"]
    assert got["bfloat16_over_float32"] == pytest.approx(ratio)
