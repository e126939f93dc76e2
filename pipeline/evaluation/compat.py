"""Checks that a trained model belongs to the dataset and environment it is evaluated in.

Deploy and validate rebuild the environment from the dataset's metadata and run a model trained on
some dataset in it; a model from another maze (or with other state/action spaces) would plan
through walls or fail deep inside a rollout, so both stages check first, with one-line errors.
"""

from __future__ import annotations

from typing import Any

from pipeline.dataset import DatasetInfo
from pipeline.envs.spec import EnvSpec
from pipeline.errors import UserError


def check_same_environment(data: DatasetInfo, checkpoint: dict[str, Any], what: str) -> None:
    """Raise `UserError` unless a checkpoint's config (`info`: the dataset it was trained on)
    describes the same environment, maze and state/action spaces as the dataset `data`."""
    info = checkpoint.get("info")
    if not isinstance(info, dict):
        raise UserError(f"{what} does not say which dataset it was trained on; retrain it")
    theirs = (info.get("env_id"), (info.get("env_kwargs") or {}).get("maze_map"))
    ours = (data.env_id, data.env_kwargs.get("maze_map"))
    if theirs[0] != ours[0]:
        raise UserError(
            f"{what} was trained on {theirs[0]!r} (dataset '{info.get('name')}'), but dataset "
            f"'{data.name}' is {ours[0]!r}; retrain it on this dataset or use its own dataset"
        )
    if theirs[1] != ours[1]:
        raise UserError(f"{what} was trained on another maze map than dataset '{data.name}'")
    for key in ("state_names", "action_names"):
        if info.get(key) != getattr(data, key):
            raise UserError(
                f"{what} has {key} {info.get(key)}, dataset '{data.name}' has "
                f"{getattr(data, key)}; retrain it on this dataset"
            )


def check_model_dims(state_dim: int, action_dim: int, spec: EnvSpec, what: str) -> None:
    """Raise `UserError` unless a model's state and action sizes are the environment's."""
    if (state_dim, action_dim) != (spec.state_dim, spec.action_dim):
        raise UserError(
            f"{what} has state_dim {state_dim} and action_dim {action_dim}, but {spec.env_id} "
            f"has {spec.state_dim} and {spec.action_dim}; retrain it on this environment's data"
        )
