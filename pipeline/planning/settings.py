"""`deploy.planner` and `deploy.llp` params -> the planners' configs (shared by the deploy stage,
the planning benchmark and the tests, which must not need the stage's recording dependencies).

The planners' configs have no defaults of their own: every value comes from the params models
(`pipeline.config`), the one source of defaults (`planner_config(PlannerParams())`: the
pipeline's planner).
"""

from __future__ import annotations

from pipeline.config import LLPParams, PlannerParams
from pipeline.planning.cem import CEMConfig
from pipeline.planning.llp import LLPConfig
from pipeline.planning.skills import PlannerConfig


def cem_config(p: PlannerParams | LLPParams) -> CEMConfig:
    """The CEM settings of `deploy.planner` or `deploy.llp`."""
    return CEMConfig(
        candidates=p.candidates,
        elites=p.elites,
        iterations=p.iterations,
        min_std=p.min_std,
        stop_cost=p.stop_cost,
    )


def planner_config(p: PlannerParams) -> PlannerConfig:
    """`deploy.planner` params -> the skill planner's config."""
    return PlannerConfig(
        horizon=p.horizon,
        cem=cem_config(p),
        init_std=p.init_std,
        prior_weight=p.prior_weight,
        skill_penalty=p.skill_penalty,
        fall_penalty=p.fall_penalty,
        uncertainty_weight=p.uncertainty_weight,
        warm_start=p.warm_start,
        compile=p.compile,
        dtype=p.dtype,
        kernel=p.kernel,
        support_weight=p.support_weight,
        data_skills=p.data_skills,
    )


def llp_config(p: LLPParams) -> LLPConfig:
    """`deploy.llp` params -> the low-level planner's config."""
    return LLPConfig(
        horizon=p.horizon,
        execute=p.execute,
        cem=cem_config(p),
        init_std=p.init_std,
        l2_penalty=p.l2_penalty,
        plan_from=p.plan_from,
        warm_start=p.warm_start,
    )
