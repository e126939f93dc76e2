"""Planning benchmark (`oposm bench plan`): time, FLOPs and achieved GFLOP/s per replan of OPOSM's
skill planner against THE REFERENCE (`bench/reference.py`: a plain eager implementation of the
paper's procedure, one environment at a time), and of LLP's low-level planner.

Configurations: OPOSM with `deploy.planner` ("oposm") and the paper's table 14 ("oposm_table14":
L 10, K 100, N_keep 50, N_iters 100), each as the batched planner, the same compiled
(`--compiled`: `torch.compile`, CUDA graphs on GPU) and the reference; both batched planners in
`deploy.planner.dtype` (the reference always multiplies in float32, as the paper); LLP with
`deploy.llp` ("llp": the paper code's L 20, K 100, keep 20 %, 5 iterations) and its timing
figure's L 400, 100 iterations ("llp_figure", one environment only). LLP is timed when its
models exist (`oposm dynamics`, `oposm bc`).

All configurations run in one process on the same threads, interleaved (repeat r of every
configuration before repeat r + 1 of any), so a change in machine load hits them alike; compare
ratios, not seconds from different runs. Start states and goals are training-data positions (at
rest). The first call of each is a warm-up (compilation, graph capture). FLOPs are the matrix
products `FlopCounterMode` counts in one replan; GFLOP/s are set against a matrix-multiply
measurement of the same device (`bench/roofline.py`).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from bench.reference import ReferencePlanner
from bench.roofline import roofline
from pipeline.config import Params, PlannerParams
from pipeline.devices import resolve_device
from pipeline.envs.spec import make_env_spec
from pipeline.evaluation.tasks import train_locations
from pipeline.model.checkpoint import load_dynamics, load_model, load_policy
from pipeline.paths import Paths
from pipeline.planning import GoalCost, SkillPlanner, problem_keys
from pipeline.planning.llp import LowLevelPlanner
from pipeline.planning.settings import llp_config, planner_config
from pipeline.segments import load_segments

log = logging.getLogger(__name__)

Planner = SkillPlanner | LowLevelPlanner | ReferencePlanner


def _plan_call(planner: Planner, s0: torch.Tensor, goals: torch.Tensor, seed: int) -> Callable:
    def call() -> None:
        if isinstance(planner, ReferencePlanner):
            planner.plan(s0, goals, seed)
        else:
            planner.plan(s0, GoalCost(goals), problem_keys(range(seed, seed + len(s0)), s0.device))
        if s0.device.type == "cuda":
            torch.cuda.synchronize()

    return call


def _seconds(call: Callable) -> float:
    start = time.perf_counter()
    call()
    return time.perf_counter() - start


def _planners(
    params: Params,
    paths: Paths,
    device: torch.device,
    compiled: bool,
    triton: bool = False,
    reference: bool = True,
) -> dict:
    """label -> (planner, time batched too); LLP only when its models exist."""
    cfg, name = params.deploy, params.ingest.name
    model, _ = load_model(paths.existing(paths.model(name)), device=device)
    default = replace(planner_config(cfg.planner), compile=False)
    table14 = planner_config(  # the paper's CEM and cost, our arithmetic (deploy.planner.dtype)
        PlannerParams(
            horizon=10, candidates=100, elites=50, iterations=100, prior_weight=0.0,
            stop_cost=cfg.planner.stop_cost, dtype=default.dtype,
        )
    )  # fmt: skip
    out = {}
    for label, config in (("oposm", default), ("oposm_table14", table14)):
        out[label] = (SkillPlanner(model, config), True)
        if compiled:
            out[f"{label}_compiled"] = (SkillPlanner(model, replace(config, compile=True)), True)
        if triton:  # the fused rollout-and-cost kernel (`deploy.planner.kernel: triton`)
            fused = replace(config, kernel="triton")
            out[f"{label}_triton"] = (SkillPlanner(model, fused), True)
            if compiled:
                out[f"{label}_triton_compiled"] = (
                    SkillPlanner(model, replace(fused, compile=True)),
                    True,
                )
        if reference:
            out[f"{label}_reference"] = (ReferencePlanner(model, config), True)
    dyn_dir, bc_dir = paths.existing(paths.dynamics(name)), paths.existing(paths.policy(name, "bc"))
    if not (dyn_dir.exists() and bc_dir.exists()):
        log.info("LLP not timed: run `oposm dynamics` and `oposm bc` first")
        return out
    dynamics, _ = load_dynamics(dyn_dir, device=device)
    policy, _ = load_policy(bc_dir, "bc", device=device)
    figure = cfg.llp.model_copy(update={"horizon": 400, "iterations": 100})
    out["llp"] = (LowLevelPlanner(policy, dynamics, llp_config(cfg.llp)), True)
    out["llp_figure"] = (LowLevelPlanner(policy, dynamics, llp_config(figure)), False)
    return out


def bench_plan(
    params: Params,
    paths: Paths,
    envs: int = 64,
    repeats: int = 10,
    batch_repeats: int = 3,
    compiled: bool = False,
    reference_envs: int | None = None,
    triton: bool = False,
    reference: bool = True,
) -> dict[str, float]:
    """Per configuration: one-environment replan p50 / p95 (s), batched replan of `envs`
    environments per environment (s), plans/s, FLOPs of one replan, achieved GFLOP/s and its
    fraction of the measured matmul roofline; `*_speedup_*`: the reference's time over the
    planner's; `llp_over_oposm_*` ratios; the machine's load average before and after.
    `reference_envs`: time the reference's batch on this many environments (it plans one after
    the other, so its time per environment does not depend on how many; default `envs`)."""
    cfg, name = params.deploy, params.ingest.name
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    device = resolve_device(cfg.device, "deploy.device")
    log.info("loading the models and the training data's locations (%s)", name)
    planners = _planners(params, paths, device, compiled, triton, reference)
    segments = load_segments(paths.existing(paths.segments(name)))
    dims = list(make_env_spec(segments.info.env_id, segments.info.env_kwargs).goal_dims)
    locations = train_locations(segments, tuple(dims))
    rng = np.random.default_rng(cfg.seed)
    n = max(envs, repeats)
    s0 = np.zeros((n, segments.info.state_dim))  # at rest at a training-data position
    s0[:, dims] = locations[rng.integers(len(locations), size=n)]
    s0 = torch.as_tensor(s0, dtype=torch.float32, device=device)
    goals = torch.as_tensor(
        locations[rng.integers(len(locations), size=n)], dtype=torch.float32, device=device
    )
    out: dict[str, float] = {"envs": float(envs), "threads": float(torch.get_num_threads())}
    out["cuda"] = float(device.type == "cuda")
    out["load_1min_before"] = os.getloadavg()[0]
    hidden = planners["oposm"][0].model.config.hidden
    log.info("measuring the matmul roofline on %s", device)
    out.update(roofline(device, hidden))
    single: dict[str, list[float]] = {label: [] for label in planners}
    batch: dict[str, list[float]] = {label: [] for label, (_, b) in planners.items() if b}
    for label, (planner, batched) in planners.items():
        log.info("warming up %s", label)
        _plan_call(planner, s0[:1], goals[:1], 0)()
        if batched and not label.endswith("_reference"):  # its batch is one env at a time
            _plan_call(planner, s0[:envs], goals[:envs], 0)()
        eager = label.removesuffix("_compiled").removesuffix("_triton")
        if eager != label:  # the eager planner's arithmetic: a replayed CUDA graph dispatches
            out[f"{label}_flops_per_replan"] = out[f"{eager}_flops_per_replan"]  # no ops to
            continue  # count, and the counter does not see into the Triton kernel
        with FlopCounterMode(display=False) as counter:
            _plan_call(planner, s0[:1], goals[:1], 0)()
        out[f"{label}_flops_per_replan"] = float(counter.get_total_flops())
    log.info("timing %s: %d replans of 1 env each, interleaved", ", ".join(planners), repeats)
    for r in range(repeats):  # a different start and goal each time
        for label, (planner, _) in planners.items():
            single[label].append(_seconds(_plan_call(planner, s0[r : r + 1], goals[r : r + 1], r)))
    log.info("timing %s: %d replans of %d envs each", ", ".join(batch), batch_repeats, envs)
    sizes = {
        label: min(envs, reference_envs or envs) if label.endswith("_reference") else envs
        for label in batch
    }
    for r in range(batch_repeats):
        for label in batch:
            m = sizes[label]
            call = _plan_call(planners[label][0], s0[:m], goals[:m], 10_000 + r * envs)
            batch[label].append(_seconds(call) / m)
    out["load_1min_after"] = os.getloadavg()[0]
    for label in planners:
        p50 = float(np.percentile(single[label], 50))
        out[f"{label}_replan_1env_p50_s"] = p50
        out[f"{label}_replan_1env_p95_s"] = float(np.percentile(single[label], 95))
        out[f"{label}_gflops_1env"] = out[f"{label}_flops_per_replan"] / p50 / 1e9
    for label, seconds in batch.items():
        per_env = float(np.median(seconds))
        out[f"{label}_replan_{envs}envs_per_env_s"] = per_env
        out[f"{label}_plans_per_s_{envs}envs"] = 1.0 / per_env
        gflops = out[f"{label}_flops_per_replan"] / per_env / 1e9
        out[f"{label}_gflops_{envs}envs"] = gflops
        out[f"{label}_roofline_fraction_{envs}envs"] = gflops / out["roofline_gflops"]
    for label in ("oposm", "oposm_table14"):
        for suffix in ("", "_compiled", "_triton", "_triton_compiled"):
            variant = label + suffix
            if variant not in planners or f"{label}_reference" not in planners:
                continue
            ref = f"{label}_reference"
            out[f"{variant}_speedup_1env"] = (
                out[f"{ref}_replan_1env_p50_s"] / out[f"{variant}_replan_1env_p50_s"]
            )
            out[f"{variant}_speedup_{envs}envs"] = (
                out[f"{ref}_replan_{envs}envs_per_env_s"]
                / out[f"{variant}_replan_{envs}envs_per_env_s"]
            )
    if "llp" in planners:
        for label in ("oposm", "oposm_table14"):
            for other in ("llp", "llp_figure"):
                key = f"{other}_over_{label}_1env_p50"
                out[key] = out[f"{other}_replan_1env_p50_s"] / out[f"{label}_replan_1env_p50_s"]
    return out
