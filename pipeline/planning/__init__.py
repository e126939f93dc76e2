"""Batched CEM in whitened skill space, task costs and the model-predictive control agent."""

from pipeline.planning.cem import CEM, CEMConfig, CEMResult
from pipeline.planning.costs import GoalCost
from pipeline.planning.noise import problem_keys, substream
from pipeline.planning.skills import Plan, PlannerConfig, SkillPlanner, shift_plan

__all__ = [
    "CEM",
    "CEMConfig",
    "CEMResult",
    "GoalCost",
    "Plan",
    "PlannerConfig",
    "SkillPlanner",
    "problem_keys",
    "shift_plan",
    "substream",
]
