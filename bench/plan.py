"""Planning benchmark (`oposm bench plan`): time and FLOPs per replan of OPOSM's skill planner and
of LLP's low-level planner, at this repository's settings and at the paper's.

Configurations: OPOSM with `deploy.planner` ("oposm") and the paper's table 14 ("oposm_table14":
L 10, K 100, N_keep 50, N_iters 100); LLP with `deploy.llp` ("llp": the paper code's L 20, K 100,
keep 20 %, 5 iterations) and its timing figure's L 400, 100 iterations ("llp_figure", one
environment only: a batched call would take minutes). LLP is timed when its models exist
(`oposm dynamics`, `oposm bc`).

All configurations run in one process on the same threads, interleaved (repeat r of every
configuration before repeat r + 1 of any), so a change in machine load hits them alike. Start
states and goals are training-data positions (at rest). The first call of each is a warm-up.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from pipeline.config import Params
from pipeline.devices import resolve_device
from pipeline.envs.spec import make_env_spec
from pipeline.evaluation.tasks import train_locations
from pipeline.model.checkpoint import load_dynamics, load_model, load_policy
from pipeline.paths import Paths
from pipeline.planning import CEMConfig, GoalCost, PlannerConfig, SkillPlanner, problem_generators
from pipeline.planning.llp import LowLevelPlanner
from pipeline.segments import load_segments
from stages.deploy import llp_config, planner_config

log = logging.getLogger(__name__)

Planner = SkillPlanner | LowLevelPlanner


def _plan_call(planner: Planner, s0: torch.Tensor, goals: torch.Tensor, seed: int) -> Callable:
    def call() -> None:
        gens = problem_generators(range(seed, seed + len(s0)), s0.device)
        planner.plan(s0, GoalCost(goals), gens)
        if s0.device.type == "cuda":
            torch.cuda.synchronize()

    return call


def _seconds(call: Callable) -> float:
    start = time.perf_counter()
    call()
    return time.perf_counter() - start


def _planners(params: Params, paths: Paths, device: torch.device) -> dict[str, tuple]:
    """label -> (planner, time batched too); LLP only when its models exist."""
    cfg, name = params.deploy, params.ingest.name
    model, _ = load_model(paths.existing(paths.model(name)), device=device)
    table14 = PlannerConfig(10, CEMConfig(100, 50, 100, stop_cost=cfg.planner.stop_cost))
    out = {
        "oposm": (SkillPlanner(model, planner_config(cfg.planner)), True),
        "oposm_table14": (SkillPlanner(model, table14), True),
    }
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
    params: Params, paths: Paths, envs: int = 64, repeats: int = 10, batch_repeats: int = 3
) -> dict[str, float]:
    """Per configuration: one-environment replan p50 / p95 (s), batched replan of `envs`
    environments per environment (s), plans/s, and FLOPs of one replan (matrix products, counted
    by `FlopCounterMode`); `llp_over_oposm_*` ratios; the machine's load average."""
    cfg, name = params.deploy, params.ingest.name
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    device = resolve_device(cfg.device, "deploy.device")
    log.info("loading the models and the training data's locations (%s)", name)
    planners = _planners(params, paths, device)
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
    out["load_1min_before"] = os.getloadavg()[0]
    single: dict[str, list[float]] = {label: [] for label in planners}
    batch: dict[str, list[float]] = {label: [] for label, (_, b) in planners.items() if b}
    for label, (planner, _) in planners.items():
        _plan_call(planner, s0[:1], goals[:1], 0)()  # warm-up
        with FlopCounterMode(display=False) as counter:
            _plan_call(planner, s0[:1], goals[:1], 0)()
        out[f"{label}_flops_per_replan"] = float(counter.get_total_flops())
    log.info("timing %s: %d replans of 1 env each, interleaved", ", ".join(planners), repeats)
    for r in range(repeats):  # a different start and goal each time
        for label, (planner, _) in planners.items():
            single[label].append(_seconds(_plan_call(planner, s0[r : r + 1], goals[r : r + 1], r)))
    log.info("timing %s: %d replans of %d envs each", ", ".join(batch), batch_repeats, envs)
    for r in range(batch_repeats):
        for label in batch:
            call = _plan_call(planners[label][0], s0[:envs], goals[:envs], 10_000 + r * envs)
            batch[label].append(_seconds(call))
    out["load_1min_after"] = os.getloadavg()[0]
    for label in planners:
        out[f"{label}_replan_1env_p50_s"] = float(np.percentile(single[label], 50))
        out[f"{label}_replan_1env_p95_s"] = float(np.percentile(single[label], 95))
    for label, seconds in batch.items():
        out[f"{label}_replan_{envs}envs_per_env_s"] = float(np.median(seconds)) / envs
        out[f"{label}_plans_per_s_{envs}envs"] = envs / float(np.median(seconds))
    if "llp" in planners:
        for label in ("oposm", "oposm_table14"):
            for other in ("llp", "llp_figure"):
                key = f"{other}_over_{label}_1env_p50"
                out[key] = out[f"{other}_replan_1env_p50_s"] / out[f"{label}_replan_1env_p50_s"]
    return out
