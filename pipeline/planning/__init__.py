"""Batched CEM in whitened skill space, task costs and the model-predictive control agent."""

from pipeline.planning.cem import CEM, CEMConfig, CEMResult, problem_generators
from pipeline.planning.costs import GoalCost
from pipeline.planning.skills import Plan, PlannerConfig, SkillPlanner, shift_plan

__all__ = [
    "CEM",
    "CEMConfig",
    "CEMResult",
    "GoalCost",
    "Plan",
    "PlannerConfig",
    "SkillPlanner",
    "problem_generators",
    "shift_plan",
]
