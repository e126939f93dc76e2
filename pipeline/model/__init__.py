"""The skill model: posterior, prior, low-level policy and temporally abstract world model."""

from pipeline.model.checkpoint import load_model, save_model
from pipeline.model.networks import GaussianMLP
from pipeline.model.skill_model import SkillModel, SkillModelConfig, SkillPosterior

__all__ = [
    "GaussianMLP",
    "SkillModel",
    "SkillModelConfig",
    "SkillPosterior",
    "load_model",
    "save_model",
]
