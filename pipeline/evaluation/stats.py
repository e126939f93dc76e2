"""Success rates with Wilson score intervals (`proportions`), steps-to-goal and planning latency
summaries of deploy episodes."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pipeline.evaluation.episodes import EpisodeResult, PlanCall
from pipeline.evaluation.proportions import wilson_interval


def _quantiles(values: list[float] | np.ndarray) -> dict[str, float | None]:
    if len(values) == 0:
        return {"mean": None, "p50": None, "p95": None, "max": None}
    v = np.asarray(values, dtype=np.float64)
    return {
        "mean": float(v.mean()),
        "p50": float(np.percentile(v, 50)),
        "p95": float(np.percentile(v, 95)),
        "max": float(v.max()),
    }


def success_within(results: list[EpisodeResult], limit: int) -> dict:
    """Success within the first `limit` steps (e.g. D4RL's 600 in a 2000-step run), with its 95 %
    Wilson interval. An episode runs the same up to `limit` whatever its own step limit, so one
    long run gives the success rate of every shorter limit."""
    n = len(results)
    wins = sum(r.steps_to_goal is not None and r.steps_to_goal <= limit for r in results)
    lo, hi = wilson_interval(wins, n)
    return {
        "successes": wins,
        "success_rate": wins / n if n else 0.0,
        "success_ci95_low": lo,
        "success_ci95_high": hi,
    }


def task_summary(results: list[EpisodeResult], dt: float, limits: Sequence[int] = ()) -> dict:
    """Success (paper's and gymnasium's radius) with 95 % Wilson intervals, steps, planning time
    per episode, errors and episodes in which the agent fell (the ant); success within each of
    the shorter step `limits` as well."""
    n = len(results)
    wins = sum(r.success for r in results)
    wins_gym = sum(r.steps_to_goal_gym is not None for r in results)
    steps = [r.steps_to_goal for r in results if r.steps_to_goal is not None]
    lo, hi = wilson_interval(wins, n)
    lo_g, hi_g = wilson_interval(wins_gym, n)
    return {
        "episodes": n,
        "successes": wins,
        "success_rate": wins / n if n else 0.0,
        "success_ci95_low": lo,
        "success_ci95_high": hi,
        "success_rate_r045": wins_gym / n if n else 0.0,
        "success_r045_ci95_low": lo_g,
        "success_r045_ci95_high": hi_g,
        "steps_to_goal": _quantiles(steps),
        "seconds_to_goal_mean": float(np.mean(steps)) * dt if steps else None,
        "replans_mean": float(np.mean([r.replans for r in results])) if n else 0.0,
        "plan_seconds_per_episode": _quantiles([r.plan_seconds for r in results]),
        "final_distance_mean": float(np.mean([r.final_distance for r in results])) if n else 0.0,
        "errors": sum(r.error is not None for r in results),
        "fallen": sum(r.fell_at is not None for r in results),
        "within_steps": {str(k): success_within(results, k) for k in limits},
        **_score(results),
    }


def _score(results: list[EpisodeResult]) -> dict:
    """D4RL's kitchen score where the goals have subtasks (`EpisodeResult.score`): the mean share
    of subtasks completed per episode, and how many episodes completed each number of them."""
    scores = [r.score for r in results if r.score is not None]
    if not scores:
        return {}
    total = len(results[0].subtasks_done or [])
    counts = [round(s * total) for s in scores]
    return {
        "score_mean": float(np.mean(scores)),
        "subtasks_completed": {str(k): counts.count(k) for k in range(total + 1)},
    }


def latency_summary(calls: list[PlanCall]) -> dict:
    """Per planning call (one batched call per replan) and per environment planned for."""
    per_call = [c.seconds for c in calls]
    per_env = [c.seconds / c.envs for c in calls if c.envs]
    total_s = sum(per_call)
    planned = sum(c.envs for c in calls)
    return {
        "calls": len(calls),
        "plans": planned,
        "envs_per_call_mean": planned / len(calls) if calls else 0.0,
        "call_latency_s": _quantiles(per_call),
        "per_env_latency_s": _quantiles(per_env),
        "plans_per_s": planned / total_s if total_s > 0 else 0.0,
        "total_s": total_s,
    }


def optimism_gap(
    results: list[EpisodeResult],
    state_steps: int,
    every: int,
    goal_dims: Sequence[int],
    scale: Sequence[float] | None = None,
) -> dict:
    """How much closer to the goal each plan said its executed part would get than it did.

    At every replan at step t the chosen plan predicts where the agent will be after the part
    that runs before the next replan: plan state k = `every // state_steps` (one per skill for
    OPOSM, one per action for LLP), at step t + k * `state_steps`. The gap is the real distance
    to the goal there minus the predicted one (positive: the plan was optimistic, the paper's
    warning about naive VI), and the position error is how far the prediction was off. Replans
    whose step is past the episode's end are left out. Means with 95 % intervals over episodes
    (an episode's replans are not independent).

    Args:
        state_steps: Environment steps per predicted plan state (the skill length T, or 1).
        every: Steps between replans.
        goal_dims: The state dims a goal refers to.
        scale: Per goal dim, what distances are divided by (the spec's `goal_scale`: success
            tolerances in OGBench's manipulation envs); None: raw units (m in the mazes).
    """
    k = max(1, every // state_steps)
    dims = list(goal_dims)
    divide = 1.0 if scale is None else np.asarray(scale, dtype=np.float64)
    gaps, errors, count = [], [], 0
    for r in results:
        states, goal = r.trace.states, r.spec.goal
        ep_gaps, ep_errors = [], []
        for t, plan in zip(r.trace.replan_steps, r.trace.plans, strict=True):
            end = t + k * state_steps
            if end >= len(states) or k >= len(plan):
                continue
            real, predicted = states[end][dims], plan[k][dims]
            if scale is not None:
                real, predicted, goal = real / divide, predicted / divide, r.spec.goal / divide
            ep_gaps.append(np.linalg.norm(real - goal) - np.linalg.norm(predicted - goal))
            ep_errors.append(np.linalg.norm(real - predicted))
        if ep_gaps:
            gaps.append(float(np.mean(ep_gaps)))
            errors.append(float(np.mean(ep_errors)))
            count += len(ep_gaps)

    def mean_ci(values: list[float]) -> dict:
        if not values:
            return {"mean": None, "ci95": None}
        v = np.asarray(values)
        half = 1.96 * v.std(ddof=1) / np.sqrt(len(v)) if len(v) > 1 else float("inf")
        return {"mean": float(v.mean()), "ci95": [float(v.mean() - half), float(v.mean() + half)]}

    return {
        "plan_state": k,
        "steps_ahead": k * state_steps,
        "replans": count,
        "episodes": len(gaps),
        "distance_gap_m": mean_ci(gaps),
        "position_error_m": mean_ci(errors),
    }
