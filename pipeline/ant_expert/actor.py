"""The direction-commanded ant expert's actor: a plain torch module read from safetensors + JSON.

Loading needs neither the RL library that trained it nor any pickle: the weights are a safetensors
file and everything else (architecture, spaces, how it was made, its measured quality) a JSON file
beside it (`actor.safetensors` + `actor.json`).

The action is SAC's deterministic one: a = low + (tanh(mu(o)) + 1) / 2 * (high - low), with mu the
mean head of the squashed Gaussian policy (stable-baselines3's `predict(deterministic=True)`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from pydantic import ConfigDict, with_config
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from pipeline.errors import UserError
from pipeline.io import atomic_path, write_json
from pipeline.readback import Finite, Size, read_json, validated

FORMAT = "oposm-direction-actor"
VERSION = 1
_ACTIVATIONS: dict[str, type[nn.Module]] = {"gelu": nn.GELU, "relu": nn.ReLU}


@with_config(ConfigDict(extra="forbid"))  # read back from the JSON: an unknown key is an error
@dataclass
class ActorSpec:
    """Architecture and spaces of a `DirectionActor`; with `info` it is the actor's JSON file."""

    obs_dim: Size
    action_dim: Size
    hidden: list[Size]
    activation: Literal["gelu", "relu"]
    action_low: list[Finite]
    action_high: list[Finite]
    info: dict[str, Any] = field(default_factory=dict)
    """Provenance and quality: robot, observation layout, command, seed, steps, SAC params,
    measured quality (free-form JSON)."""

    def __post_init__(self) -> None:
        for name in ("action_low", "action_high"):
            if len(getattr(self, name)) != self.action_dim:
                raise ValueError(
                    f"{name} has {len(getattr(self, name))} values for {self.action_dim} dims"
                )
        if any(lo >= hi for lo, hi in zip(self.action_low, self.action_high, strict=True)):
            raise ValueError("every action_low must be below its action_high")


class DirectionActor(nn.Module):
    """MLP actor: [B, obs_dim] observation -> [B, action_dim] deterministic action."""

    def __init__(self, spec: ActorSpec) -> None:
        super().__init__()
        if spec.activation not in _ACTIVATIONS:
            raise ValueError(f"activation must be one of {sorted(_ACTIVATIONS)}")
        self.spec = spec
        layers: list[nn.Module] = []
        width = spec.obs_dim
        for h in spec.hidden:
            layers += [nn.Linear(width, h), _ACTIVATIONS[spec.activation]()]
            width = h
        self.trunk = nn.Sequential(*layers)
        self.mu = nn.Linear(width, spec.action_dim)
        self.log_std = nn.Linear(width, spec.action_dim)
        self.register_buffer("low", torch.tensor(spec.action_low, dtype=torch.float32))
        self.register_buffer("high", torch.tensor(spec.action_high, dtype=torch.float32))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        squashed = torch.tanh(self.mu(self.trunk(obs)))
        return self.low + 0.5 * (squashed + 1.0) * (self.high - self.low)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """[obs_dim] or [B, obs_dim] numpy observation -> float32 action(s) of the same rank.

        Under `inference_mode` (measured: half of `no_grad`'s ~190 us for one observation, which
        matters when the data generation calls it every step)."""
        with torch.inference_mode():
            x = torch.as_tensor(np.asarray(obs, dtype=np.float32))
            a = self(x.unsqueeze(0) if x.ndim == 1 else x)
            return (a[0] if x.ndim == 1 else a).numpy()


def weight_names(spec: ActorSpec) -> list[str]:
    """The tensors an actor file holds, in module order."""
    names = []
    for i in range(len(spec.hidden)):
        names += [f"trunk.{2 * i}.weight", f"trunk.{2 * i}.bias"]
    return [*names, "mu.weight", "mu.bias", "log_std.weight", "log_std.bias"]


def json_path(weights: Path) -> Path:
    """`actor.safetensors` -> `actor.json`."""
    return weights.with_suffix(".json")


def save_actor(actor: DirectionActor, path: str | Path) -> None:
    """Write `path` (safetensors) and its JSON, each atomically; the JSON last."""
    path = Path(path)
    state = {k: v.detach().cpu().contiguous() for k, v in actor.state_dict().items()}
    state = {k: state[k] for k in weight_names(actor.spec)}
    with atomic_path(path) as tmp:
        save_file(state, str(tmp), metadata={"format": FORMAT})
    write_json(json_path(path), {"format": FORMAT, "version": VERSION, **asdict(actor.spec)})


def read_spec(path: str | Path) -> ActorSpec:
    """The JSON of actor `path` (the .safetensors path or the .json path)."""
    path = Path(path)
    meta_path = path if path.suffix == ".json" else json_path(path)
    if not meta_path.exists():
        raise UserError(f"actor description {meta_path} not found (it goes beside the weights)")
    fix = "ship the actor again (`oposm expert train`) or restore the file"
    meta = read_json(meta_path, fix)
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise UserError(f"{meta_path} is not a direction-actor description (format {FORMAT!r})")
    if meta.get("version") != VERSION:
        raise UserError(f"{meta_path}: version {meta.get('version')!r}, this code reads {VERSION}")
    fields = {k: v for k, v in meta.items() if k not in ("format", "version")}
    return validated(ActorSpec, fields, meta_path, fix)


def load_actor(path: str | Path) -> DirectionActor:
    """Read actor weights (`.safetensors`) and their JSON into a `DirectionActor` in eval mode.

    Raises:
        UserError: a file is missing, corrupt, or the weights do not fit the description.
    """
    path = Path(path)
    if not path.exists():
        raise UserError(f"actor weights {path} not found")
    spec = read_spec(path)
    try:
        state = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as exc:
        raise UserError(f"{path} is not a readable safetensors file ({exc})") from exc
    actor = DirectionActor(spec)
    expected = set(weight_names(spec))
    if set(state) != expected:
        raise UserError(
            f"{path}: tensors {sorted(state)} do not match the description's {sorted(expected)}"
        )
    try:
        actor.load_state_dict(state, strict=False)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[-1].strip()
        raise UserError(f"{path}: weights do not fit the description ({first})") from exc
    return actor.eval()


def update_info(path: str | Path, **entries: Any) -> None:
    """Set entries of the actor's `info` (e.g. `quality`), rewriting its JSON atomically."""
    spec = read_spec(path)
    spec.info.update(entries)
    write_json(json_path(Path(path)), {"format": FORMAT, "version": VERSION, **asdict(spec)})
