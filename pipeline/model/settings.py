"""`train`, `dynamics`, `bc` and `gcbc` params -> the models' configs (shared by the stages, the
benchmarks and the tests).

The models' configs have no defaults of their own for what a params file sets: every value comes
from the params models (`pipeline.config`), the one source of defaults.
"""

from __future__ import annotations

from collections.abc import Sequence

from pipeline.config import DynamicsParams, PolicyParams, TrainParams
from pipeline.model.dynamics import DynamicsConfig
from pipeline.model.policy import PolicyConfig
from pipeline.model.skill_model import SkillModelConfig


def skill_model_config(
    cfg: TrainParams,
    state_dim: int,
    action_dim: int,
    action_low: Sequence[float] | None = None,
    action_high: Sequence[float] | None = None,
) -> SkillModelConfig:
    """`train` params -> the skill model's config; `action_low` / `action_high`: the data's action
    bounds where the policy's likelihood is censored (`train.action_likelihood: censored`)."""
    return SkillModelConfig(
        state_dim=state_dim,
        action_dim=action_dim,
        z_dim=cfg.z_dim,
        hidden=cfg.hidden,
        tawm_shared_std=cfg.tawm_shared_std,
        min_std=cfg.min_std,
        action_low=action_low,
        action_high=action_high,
        policy_layer_norm=cfg.policy_trunk == "layernorm_silu",
        policy_ignore_dims=tuple(cfg.policy_ignore_dims),
        tawm_components=cfg.tawm_components,
        encoder=cfg.encoder,
        tawm_residual=cfg.tawm_residual,
    )


def dynamics_config(cfg: DynamicsParams, state_dim: int, action_dim: int) -> DynamicsConfig:
    """`dynamics` params -> the single-step model's config."""
    return DynamicsConfig(state_dim, action_dim, cfg.hidden, cfg.min_std)


def policy_config(
    cfg: PolicyParams, state_dim: int, action_dim: int, goal_dims: Sequence[int] = ()
) -> PolicyConfig:
    """`bc` or `gcbc` params -> the policy's config; `goal_dims`: the state dimensions a goal
    gives (empty for p(a | s))."""
    return PolicyConfig(
        state_dim, action_dim, tuple(goal_dims), cfg.hidden, cfg.min_std, cfg.learned_std
    )
