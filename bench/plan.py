"""Planning benchmark (`oposm bench plan`): latency per replan and plans/s, deploy vs table 14."""

from __future__ import annotations

import logging
import time

import numpy as np
import torch

from pipeline.config import Params
from pipeline.devices import resolve_device
from pipeline.envs.spec import make_env_spec
from pipeline.evaluation.tasks import train_locations
from pipeline.model import load_model
from pipeline.paths import Paths
from pipeline.planning import CEMConfig, GoalCost, PlannerConfig, SkillPlanner, problem_generators
from pipeline.segments import load_segments
from stages.deploy import planner_config

log = logging.getLogger(__name__)


def _time_plans(planner, s0, goals, seed: int, repeats: int) -> list[float]:
    """Wall seconds of `repeats` planning calls for the batch `s0 [B, sd]`, `goals [B, G]`."""
    seconds = []
    for r in range(repeats):
        gens = problem_generators(range(seed + r * len(s0), seed + (r + 1) * len(s0)), s0.device)
        start = time.perf_counter()
        planner.plan(s0, GoalCost(goals), gens)
        if s0.device.type == "cuda":
            torch.cuda.synchronize()
        seconds.append(time.perf_counter() - start)
    return seconds


def bench_plan(
    params: Params, paths: Paths, envs: int = 64, repeats: int = 10, batch_repeats: int = 3
) -> dict[str, float]:
    """Planning latency of one replan (one env) and plans/s with `envs` envs planned at once.

    For `deploy.planner` ("default") and the paper's table 14 (L 10, K 100, N_keep 50, N_iters
    100; same `stop_cost`, the paper's threshold is not given). Start states and goals are
    training-data positions of the trained model's dataset (at rest), so early stopping behaves as
    in deploy. The first call of each configuration is a warm-up, not timed.
    """
    cfg, name = params.deploy, params.ingest.name
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    device = resolve_device(cfg.device, "deploy.device")
    log.info("loading the model and the training data's locations (%s)", name)
    model, _ = load_model(paths.model(name), device=device)
    segments = load_segments(paths.segments(name))
    dims = list(make_env_spec(segments.info.env_id, segments.info.env_kwargs).goal_dims)
    locations = train_locations(segments, tuple(dims))
    rng = np.random.default_rng(cfg.seed)
    n = max(envs, repeats)
    s0 = np.zeros((n, model.config.state_dim))  # at rest at a training-data position
    s0[:, dims] = locations[rng.integers(len(locations), size=n)]
    s0 = torch.as_tensor(s0, dtype=torch.float32, device=device)
    goals = torch.as_tensor(
        locations[rng.integers(len(locations), size=n)], dtype=torch.float32, device=device
    )
    table14 = PlannerConfig(10, CEMConfig(100, 50, 100, stop_cost=cfg.planner.stop_cost))
    out: dict[str, float] = {"envs": float(envs), "threads": float(torch.get_num_threads())}
    for label, config in (("default", planner_config(cfg.planner)), ("table14", table14)):
        planner = SkillPlanner(model, config)
        log.info(
            "timing %s (L %d, K %d, %d iterations): %d replans of 1 env, %d of %d envs",
            label,
            config.horizon,
            config.cem.population,
            config.cem.iterations,
            repeats,
            batch_repeats,
            envs,
        )
        _time_plans(planner, s0[:1], goals[:1], 0, 1)  # warm-up
        single = []
        for r in range(repeats):  # a different start and goal each time
            single += _time_plans(planner, s0[r : r + 1], goals[r : r + 1], r, 1)
        batch = _time_plans(planner, s0[:envs], goals[:envs], 10_000, batch_repeats)
        out[f"{label}_replan_1env_p50_s"] = float(np.percentile(single, 50))
        out[f"{label}_replan_1env_p95_s"] = float(np.percentile(single, 95))
        out[f"{label}_replan_{envs}envs_p50_s"] = float(np.percentile(batch, 50))
        out[f"{label}_plans_per_s_{envs}envs"] = envs / float(np.median(batch))
    return out
