"""Training state for resume: model + optimizer + RNG states, written atomically as one unit.

`resume/` holds `model.safetensors`, `optim.pt` (optimizer and RNG states, loaded with
`torch.load(weights_only=True)`: tensors, numbers and containers only, never arbitrary objects)
and `state.json` (step, best metric, elapsed time, and the fingerprint of what was trained).
The directory is replaced as a whole, so a SIGKILL leaves either the previous or the new state.
"""

from __future__ import annotations

import json
import logging
import pickle  # only for its error type: torch.load(weights_only=True) on a bad file
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from pydantic import BaseModel, Field
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from pipeline.errors import UserError
from pipeline.io import atomic_dir, recover_dir
from pipeline.model.skill_model import SkillModel
from pipeline.readback import (
    READBACK_CONFIG,
    Count,
    Finite,
    NonNegativeFinite,
    read_json,
    validated,
)

log = logging.getLogger(__name__)


@dataclass
class Progress:
    """Where training stands.

    Attributes:
        step: Update steps done.
        elapsed_s: Training wall time over resumed runs.
        best: Per model-selection criterion (a validation metric, `SELECTION_CRITERIA`), the
            step and value of its best validation so far: `{"step": int, "value": float}`.
        evals_above_best: Consecutive validations, up to the last, whose watched metric was
            more than the divergence margin above its best (`loop.DivergenceCheck`).
        diverged_step: The step at which the run was found diverged; None while it is not.
    """

    step: int = 0
    elapsed_s: float = 0.0
    best: dict[str, dict[str, float]] = field(default_factory=dict)
    evals_above_best: int = 0
    diverged_step: int | None = None

    def best_of(self, criterion: str) -> tuple[int, float]:
        """(step, value) of `criterion`'s best validation; (-1, inf) before the first."""
        entry = self.best.get(criterion)
        return (-1, float("inf")) if entry is None else (int(entry["step"]), entry["value"])


class _SavedBest(BaseModel):
    step: Count
    value: Finite


class _SavedProgress(BaseModel):
    """`Progress` as state.json holds it (read back: checked before it is used)."""

    model_config = READBACK_CONFIG
    step: Count = 0
    elapsed_s: NonNegativeFinite = 0.0
    best: dict[str, _SavedBest] = Field(default_factory=dict)
    evals_above_best: Count = 0
    diverged_step: Count | None = None


class _SavedState(BaseModel):
    model_config = READBACK_CONFIG
    fingerprint: str
    progress: _SavedProgress


def save_state(
    directory: Path,
    model: SkillModel,
    optimizers: dict[str, torch.optim.Optimizer],
    generator: torch.Generator,
    progress: Progress,
    fingerprint: str,
    extra: dict[str, torch.nn.Module] | None = None,
) -> None:
    """Write the resume state of a run (replacing the previous one atomically); `extra`: other
    modules the run keeps (`EMUpdater.extra_state`), saved beside the optimizers."""
    model_state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    optim = {
        "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
        "extra": {k: m.state_dict() for k, m in (extra or {}).items()},
        "torch_rng": torch.get_rng_state(),
        "sampler_rng": generator.get_state(),
    }
    if torch.cuda.is_available():
        optim["cuda_rng"] = torch.cuda.get_rng_state_all()
    with atomic_dir(directory) as tmp:
        save_file(model_state, tmp / "model.safetensors")
        torch.save(optim, tmp / "optim.pt")
        meta = {"fingerprint": fingerprint, "progress": asdict(progress)}
        (tmp / "state.json").write_text(json.dumps(meta, indent=2) + "\n")


def _corrupt(directory: Path, what: str) -> UserError:
    return UserError(
        f"the training resume state in {directory} is unreadable ({what}); delete that folder "
        "to start over"
    )


def read_progress(directory: Path, fingerprint: str) -> Progress | None:
    """The progress saved in `directory`, or None if there is none or it is for other params.

    A state written for a different fingerprint (other model config, training params or data)
    is not an error: that run is simply not continued. An unreadable one is a `UserError`.
    """
    recover_dir(directory)
    meta_path = directory / "state.json"
    if not meta_path.exists():
        return None
    fix = f"delete {directory} to start over"
    meta: Any = read_json(meta_path, fix)
    if not isinstance(meta, dict):
        raise UserError(f"{meta_path} is not a JSON object; it is damaged: {fix}")
    if meta.get("fingerprint") != fingerprint:
        log.info("previous training state in %s is for other params; starting over", directory)
        return None
    saved = validated(_SavedState, meta, meta_path, fix).progress
    return Progress(**saved.model_dump())


def load_state(
    directory: Path,
    model: SkillModel,
    optimizers: dict[str, torch.optim.Optimizer],
    generator: torch.Generator,
    fingerprint: str,
    extra: dict[str, torch.nn.Module] | None = None,
) -> Progress | None:
    """Restore a previous run's state in place (and `extra`'s, as `save_state` wrote them);
    None if there is none or it is for other params."""
    progress = read_progress(directory, fingerprint)
    if progress is None:
        return None
    device = next(model.parameters()).device
    fix = f"delete {directory} to start over"
    weights_path, optim_path = directory / "model.safetensors", directory / "optim.pt"
    try:
        weights = load_file(weights_path, device=str(device))
    except (OSError, SafetensorError) as exc:
        raise UserError(f"{weights_path} is damaged or not a safetensors file; {fix}") from exc
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols before failing
            warnings.simplefilter("ignore")
            optim = torch.load(optim_path, weights_only=True, map_location=device)
    except (OSError, RuntimeError, ValueError, EOFError, pickle.UnpicklingError) as exc:
        # torch's own message suggests an unsafe load (weights_only=False): never pass it on.
        raise UserError(
            f"{optim_path} is damaged, or not the optimizer state `oposm train` writes (only "
            f"tensors and numbers); {fix}"
        ) from exc
    try:
        model.load_state_dict(weights)
        for name, optimizer in optimizers.items():
            _load_optimizer(optimizer, optim["optimizers"][name])
        for name, module in (extra or {}).items():
            module.load_state_dict(optim["extra"][name])
        torch.set_rng_state(optim["torch_rng"].cpu())
        generator.set_state(optim["sampler_rng"].cpu())
    except KeyError as exc:
        raise _corrupt(directory, f"optim.pt has no entry {exc}") from exc
    except (RuntimeError, ValueError, TypeError, AttributeError, IndexError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise _corrupt(directory, first) from exc
    if "cuda_rng" in optim and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in optim["cuda_rng"]])
    return progress


def _load_optimizer(optimizer: torch.optim.Optimizer, saved: dict) -> None:
    """`load_state_dict`, keeping this optimizer's `capturable` flag (a state saved by a
    CUDA-graph run, `train.cuda_graph`, resumes eagerly and the other way round): eager Adam
    counts its steps on the CPU, capturable Adam on the parameters' device."""
    capturable = [group.get("capturable", False) for group in optimizer.param_groups]
    optimizer.load_state_dict(saved)
    for group, flag in zip(optimizer.param_groups, capturable, strict=True):
        group["capturable"] = flag
        for p in group["params"]:
            state = optimizer.state.get(p)
            if state and "step" in state:
                device = p.device if flag else torch.device("cpu")
                state["step"] = state["step"].to(device, torch.float32)
