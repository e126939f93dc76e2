"""The goal-conditioned value network and its checkpoint.

V(s, g) is the discounted return of reward -1 per step until the goal is reached (0 once it is),
so `-1 / (1 - discount) <= V <= 0` and the steps to go follow from it:
`d(s, g) = log(1 + (1 - discount) V) / log(discount)` (`GoalValue.steps_to_go`), the temporal
distance GCIVL, HIQL and GAS learn from the same kind of data. An ensemble of `heads`
independent MLPs (LayerNorm + GELU after every hidden layer, as OGBench's value networks) over the
normalized state and goal; the goal is the environment's goal dims, normalized with the states'
own statistics. Training is `pipeline.value.fit`; the stage is `stages/value.py`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, Field
from torch import nn

# The checkpoint helpers every model kind shares (weights file, atomic writes, error messages).
from pipeline.errors import UserError
from pipeline.model.checkpoint import CONFIG_FILE, FORMAT_VERSION, _load_weights, _read_meta, _write
from pipeline.readback import READBACK_CONFIG, Count, Size, validated

VALUE_FORMAT = "oposm-goal-value"
COMMAND = "oposm value"


@dataclass(frozen=True)
class ValueConfig:
    """Everything needed to rebuild a `GoalValue` (defaults: `pipeline.config.ValueParams`).

    Attributes:
        state_dim: Size of a state vector.
        goal_dims: The state dims a goal gives.
        hidden: Width of every hidden layer.
        layers: Hidden layers per head.
        heads: Independent value networks (their mean is V; the target takes their minimum).
        discount: The discount the values are learned with (sets the steps-to-go scale).
    """

    state_dim: int
    goal_dims: tuple[int, ...]
    hidden: int
    layers: int
    heads: int
    discount: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "goal_dims", tuple(int(d) for d in self.goal_dims))
        if not self.goal_dims or any(not 0 <= d < self.state_dim for d in self.goal_dims):
            raise ValueError(f"goal_dims {list(self.goal_dims)} must be state dims")
        if not 0 < self.discount < 1:
            raise ValueError(f"discount must be in (0, 1), got {self.discount}")


def _head(inputs: int, hidden: int, layers: int) -> nn.Sequential:
    parts: list[nn.Module] = []
    for i in range(layers):
        parts += [nn.Linear(inputs if i == 0 else hidden, hidden), nn.LayerNorm(hidden), nn.GELU()]
    parts.append(nn.Linear(hidden, 1))
    return nn.Sequential(*parts)


class GoalValue(nn.Module):
    """V(s, g) for raw states `[..., sd]` and goals `[..., G]`; normalization lives in buffers."""

    def __init__(self, config: ValueConfig):
        super().__init__()
        self.config = config
        sd, g = config.state_dim, len(config.goal_dims)
        self.heads = nn.ModuleList(
            _head(sd + g, config.hidden, config.layers) for _ in range(config.heads)
        )
        self.register_buffer("state_mean", torch.zeros(sd))
        self.register_buffer("state_std", torch.ones(sd))
        self.register_buffer("goal_index", torch.tensor(config.goal_dims, dtype=torch.long))

    def set_normalization(self, state_mean: np.ndarray, state_std: np.ndarray) -> None:
        """The train split's state statistics (the goal dims' serve the goals)."""
        self.state_mean.copy_(torch.as_tensor(state_mean, dtype=torch.float32))
        self.state_std.copy_(torch.as_tensor(state_std, dtype=torch.float32))

    def heads_values(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """`[..., heads]`: each head's V of raw `states [..., sd]` and `goals [..., G]`."""
        s = (states - self.state_mean) / self.state_std
        mean, std = self.state_mean[self.goal_index], self.state_std[self.goal_index]
        x = torch.cat([s, ((goals - mean) / std).expand(*s.shape[:-1], -1)], dim=-1)
        return torch.cat([head(x) for head in self.heads], dim=-1)

    def forward(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """`[...]`: V, the heads' mean."""
        return self.heads_values(states, goals).mean(dim=-1)

    def steps_to_go(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """`[...]` the temporal distance V stands for, in environment steps (0 at the goal,
        at most `log(1e-6) / log(discount)` where V says "never")."""
        gamma = self.config.discount
        fraction = (1 + (1 - gamma) * self(states, goals)).clamp(1e-6, 1.0)
        return torch.log(fraction) / math.log(gamma)


class _ValueModel(BaseModel):
    model_config = READBACK_CONFIG
    state_dim: Size
    goal_dims: list[Count] = Field(min_length=1)
    hidden: Size
    layers: Size
    heads: Size
    discount: float = Field(gt=0, lt=1)


class _ValueCheckpoint(BaseModel):
    """What is read from a value checkpoint's config.json."""

    format: str
    format_version: int
    model: _ValueModel


def save_value(value: GoalValue, directory: str | Path, extra: dict[str, Any]) -> None:
    """Write the value network: weights and `config.json` (config + `extra`)."""
    meta = {"format": VALUE_FORMAT, "format_version": FORMAT_VERSION}
    _write(value, directory, VALUE_FORMAT, meta | {"model": asdict(value.config)} | extra)


def load_value(
    directory: str | Path, device: str | torch.device = "cpu"
) -> tuple[GoalValue, dict[str, Any]]:
    """Rebuild the value network in `directory` (eval mode) with its config.json.

    Raises:
        UserError: missing, corrupt or outdated files, or another kind of checkpoint.
    """
    meta = _read_meta(directory, "goal-value network", COMMAND)
    path = Path(directory) / CONFIG_FILE
    if meta.get("format") != VALUE_FORMAT or meta.get("format_version") != FORMAT_VERSION:
        raise UserError(f"{path}: not a current goal-value checkpoint; re-run `{COMMAND}`")
    model = validated(_ValueCheckpoint, meta, path, f"re-run `{COMMAND}`").model
    config = ValueConfig(**model.model_dump())
    return _load_weights(GoalValue(config), directory, device, COMMAND), meta
