"""The single-step dynamics model p(s_{t+1} | s_t, a_t): the paper's low-level (LLP) baseline.

§4.1 and appendix D compare the temporally abstract world model with "a single-timestep
low-level dynamics model" rolled forward step by step. This is that model: a `GaussianMLP` (the
same 2-layer ReLU trunk and Gaussian heads as the skill model, appendix C) that predicts the
normalized state change `(s_{t+1} - s_t - delta_mean) / delta_std` from normalized `(s_t, a_t)`,
trained by Gaussian maximum likelihood on the train split's transitions. Predicting the change
rather than the next state is the usual parameterization (mbrl-lib, PETS): at dt = 0.01 s the
change is tiny next to the state, so a network predicting s_{t+1} directly would spend its
capacity on the identity.

Checkpoints follow the skill model's contract: safetensors weights + a JSON config, no pickle.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from pipeline.errors import UserError
from pipeline.io import atomic_path
from pipeline.model.networks import GaussianMLP
from pipeline.model.skill_model import diag_normal
from pipeline.segments import Segments

log = logging.getLogger(__name__)

WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
FORMAT = "oposm-dynamics-model"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class DynamicsConfig:
    """Everything needed to rebuild a `DynamicsModel`.

    Attributes:
        state_dim: Size of a state vector.
        action_dim: Size of an action vector.
        hidden: Width of every hidden layer.
        min_std: Floor added to the predicted std (normalized units).
    """

    state_dim: int
    action_dim: int
    hidden: int = 128
    min_std: float = 1e-4


class DynamicsModel(nn.Module):
    """p(s_{t+1} | s_t, a_t) = N(s_t + delta_mean + delta_std * mu, (delta_std * sigma)^2).

    Holds the train-split normalization statistics as buffers, so its public methods take and
    return raw environment units.
    """

    def __init__(self, config: DynamicsConfig):
        super().__init__()
        self.config = config
        sd, ad = config.state_dim, config.action_dim
        self.net = GaussianMLP(sd + ad, config.hidden, sd, min_std=config.min_std)
        for name, dim in (("state", sd), ("action", ad), ("delta", sd)):
            self.register_buffer(f"{name}_mean", torch.zeros(dim))
            self.register_buffer(f"{name}_std", torch.ones(dim))

    def set_normalization(self, stats: dict[str, np.ndarray]) -> None:
        """Copy `{state,action,delta}_{mean,std}` arrays into the buffers."""
        for name, value in stats.items():
            buffer = getattr(self, name)
            buffer.copy_(torch.as_tensor(value, dtype=buffer.dtype))

    def dist(self, s: torch.Tensor, a: torch.Tensor):
        """Distribution of the normalized change, from raw `s [..., sd]`, `a [..., ad]`."""
        x = torch.cat(
            [(s - self.state_mean) / self.state_std, (a - self.action_mean) / self.action_std], -1
        )
        return diag_normal(*self.net(x))

    def nll(self, s: torch.Tensor, a: torch.Tensor, s_next: torch.Tensor) -> torch.Tensor:
        """Negative log-likelihood `[B]` of raw `s_next` (normalized change units, nats)."""
        target = (s_next - s - self.delta_mean) / self.delta_std
        return -self.dist(s, a).log_prob(target)

    @torch.no_grad()
    def predict(self, s: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw `s [..., sd]`, `a [..., ad]` -> mean, std of s_{t+1} in raw units `[..., sd]`."""
        d = self.dist(s, a).base_dist
        return s + self.delta_mean + d.loc * self.delta_std, d.scale * self.delta_std

    @torch.no_grad()
    def rollout(self, s0: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Mean rollout: raw `s0 [B, sd]`, `actions [B, T, ad]` -> states `[B, T + 1, sd]`.

        Each step feeds the previous predicted mean back in (what an LLP planner does with an
        open-loop action sequence), so errors compound over the T steps.
        """
        states = [s0]
        for t in range(actions.shape[1]):
            states.append(self.predict(states[-1], actions[:, t])[0])
        return torch.stack(states, dim=1)


def transition_index(segments: Segments, split: str) -> np.ndarray:
    """Global step indices t of `split`'s episodes whose successor t + 1 is in the same episode."""
    offsets = segments.episode_offsets
    parts = [np.arange(offsets[e], offsets[e + 1] - 1) for e in segments.episodes_in(split)]
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def normalization(segments: Segments, train_idx: np.ndarray) -> dict[str, np.ndarray]:
    """Train statistics: the segments' state/action stats plus those of the change s_{t+1} - s_t."""
    delta = segments.states[train_idx + 1].astype(np.float64) - segments.states[train_idx]
    st = segments.stats
    return {
        "state_mean": st.state_mean,
        "state_std": st.state_std,
        "action_mean": st.action_mean,
        "action_std": st.action_std,
        "delta_mean": delta.mean(0),
        "delta_std": np.maximum(delta.std(0), 1e-8),
    }


@dataclass
class FitConfig:
    """Optimization of `fit_dynamics` (the `dynamics` section of params.yaml)."""

    batch_size: int = 256
    lr: float = 1e-3
    max_steps: int = 10000
    eval_every: int = 1000
    val_transitions: int = 5000
    seed: int = 0


def _transitions(segments: Segments, idx: np.ndarray, device: torch.device) -> tuple:
    return tuple(
        torch.as_tensor(x, dtype=torch.float32, device=device)
        for x in (segments.states[idx], segments.actions[idx], segments.states[idx + 1])
    )


@torch.no_grad()
def evaluate(model: DynamicsModel, s, a, s_next) -> dict[str, float]:
    """Mean NLL and one-step position/state RMSE (raw units) over given transitions `[N, ...]`."""
    mean, _ = model.predict(s, a)
    return {
        "nll": float(model.nll(s, a, s_next).mean()),
        "rmse": float((mean - s_next).square().sum(-1).mean().sqrt()),
    }


def fit_dynamics(
    segments: Segments, model_config: DynamicsConfig, cfg: FitConfig, device: torch.device
) -> tuple[DynamicsModel, dict[str, float]]:
    """Train a `DynamicsModel` on train-split transitions by Adam on the Gaussian NLL.

    Keeps the parameters with the best validation NLL (evaluated every `eval_every` steps on a
    fixed subset of `val_transitions` validation-split transitions, and at the end).

    Returns:
        The best model (eval mode) and its metrics: `val_nll`, `val_rmse`, `best_step`, ...

    Raises:
        UserError: no train or validation transitions, or the loss became NaN/inf.
    """
    train_idx = transition_index(segments, "train")
    val_idx = transition_index(segments, "validation")
    if train_idx.size == 0 or val_idx.size == 0:
        raise UserError("the dynamics model needs train and validation episodes; see segment.split")
    rng = np.random.default_rng(cfg.seed)
    if val_idx.size > cfg.val_transitions:
        val_idx = np.sort(rng.choice(val_idx, cfg.val_transitions, replace=False))
    torch.manual_seed(cfg.seed)
    model = DynamicsModel(model_config)
    model.set_normalization(normalization(segments, train_idx))
    model.to(device)
    train, val = _transitions(segments, train_idx, device), _transitions(segments, val_idx, device)
    optimizer = torch.optim.Adam(model.net.parameters(), lr=cfg.lr)
    generator = torch.Generator().manual_seed(cfg.seed)
    best: dict[str, Any] = {"val_nll": float("inf")}
    state = None
    started = time.monotonic()
    for step in range(1, cfg.max_steps + 1):
        batch = torch.randint(train_idx.size, (cfg.batch_size,), generator=generator).to(device)
        loss = model.nll(*(x[batch] for x in train)).mean()
        if not torch.isfinite(loss):
            raise UserError(f"dynamics training diverged at step {step}; lower dynamics.lr")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if step % cfg.eval_every == 0 or step == cfg.max_steps:
            metrics = evaluate(model.eval(), *val)
            model.train()
            log.info("dynamics step %d: val NLL %.3f, RMSE %.2e", step, *metrics.values())
            if state is None or metrics["nll"] < best["val_nll"]:
                state = {k: v.detach().clone() for k, v in model.state_dict().items()}
                best = {"val_nll": metrics["nll"], "val_rmse": metrics["rmse"], "best_step": step}
    model.load_state_dict(state)
    best |= {
        "steps": cfg.max_steps,
        "train_transitions": int(train_idx.size),
        "wall_s": time.monotonic() - started,
    }
    return model.eval(), best


def save_dynamics(model: DynamicsModel, directory: str | Path, extra: dict[str, Any]) -> None:
    """Write `model.safetensors` then `config.json` (config + `extra`, e.g. dataset info)."""
    directory = Path(directory)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    with atomic_path(directory / WEIGHTS_FILE) as tmp:
        save_file(state, tmp, metadata={"format": FORMAT})
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "model": asdict(model.config)}
    with atomic_path(directory / CONFIG_FILE) as tmp:
        tmp.write_text(json.dumps(meta | extra, indent=2) + "\n")


def load_dynamics(
    directory: str | Path, device: str | torch.device = "cpu"
) -> tuple[DynamicsModel, dict[str, Any]]:
    """Rebuild a `DynamicsModel` (eval mode) and return it with its config.json dict.

    Raises:
        UserError: missing, corrupt or outdated files.
    """
    directory = Path(directory)
    path = directory / CONFIG_FILE
    if not path.exists():
        raise UserError(f"no dynamics model in {directory}; run `oposm dynamics` first")
    try:
        meta = json.loads(path.read_text())
        config = DynamicsConfig(**meta["model"])
        state = load_file(directory / WEIGHTS_FILE, device=str(device))
    except (OSError, ValueError, KeyError, TypeError, SafetensorError) as exc:
        raise UserError(f"{directory}: dynamics model is unreadable ({exc}); re-run it") from exc
    if meta.get("format") != FORMAT or meta.get("format_version") != FORMAT_VERSION:
        raise UserError(f"{path}: not a current dynamics model; re-run `oposm dynamics`")
    model = DynamicsModel(config).to(device)
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        raise UserError(f"{directory}: weights do not match the config; re-run it") from exc
    return model.eval(), meta
