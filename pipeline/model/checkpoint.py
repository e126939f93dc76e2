"""Model checkpoints: safetensors weights + a JSON config that is enough to rebuild the model.

Loading never unpickles anything: weights come from safetensors, the config from JSON. The skill
model (`save_model` / `load_model`), the single-step model (`save_dynamics` / `load_dynamics`) and
the behaviour-cloning policies (`save_policy` / `load_policy`) share the format and the code; each
has its own format tag and the command that rebuilds it.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from pipeline.errors import UserError
from pipeline.io import atomic_path
from pipeline.model.dynamics import DynamicsConfig, DynamicsModel
from pipeline.model.policy import GaussianPolicy, PolicyConfig
from pipeline.model.skill_model import SkillModel, SkillModelConfig

WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
FORMAT_VERSION = 1
SKILL_FORMAT = "oposm-skill-model"
DYNAMICS_FORMAT = "oposm-dynamics-model"
POLICY_FORMAT = "oposm-policy"


def _write(module: nn.Module, directory: str | Path, weights_format: str, meta: dict) -> None:
    """Write `model.safetensors` then `config.json` (`meta`), each replaced atomically.

    The weights are written first, so a config always describes weights at least as new as itself.
    """
    directory = Path(directory)
    state = {k: v.detach().cpu().contiguous() for k, v in module.state_dict().items()}
    with atomic_path(directory / WEIGHTS_FILE) as tmp:
        save_file(state, tmp, metadata={"format": weights_format})
    with atomic_path(directory / CONFIG_FILE) as tmp:
        tmp.write_text(json.dumps(meta, indent=2) + "\n")


def _read_meta(directory: str | Path, what: str, command: str) -> dict[str, Any]:
    """config.json of the checkpoint in `directory` (`what` and `command` name it in errors)."""
    path = Path(directory) / CONFIG_FILE
    if not path.exists():
        raise UserError(f"no {what} in {directory}; run `{command}` first")
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise UserError(f"{path} is unreadable ({exc}); re-run `{command}`") from exc


def _load_weights(
    module: nn.Module, directory: str | Path, device: str | torch.device, command: str
) -> nn.Module:
    """Load `model.safetensors` into `module` (moved to `device`); return it in eval mode."""
    try:
        state = load_file(Path(directory) / WEIGHTS_FILE, device=str(device))
    except (OSError, SafetensorError) as exc:
        raise UserError(
            f"{directory}/{WEIGHTS_FILE} is unreadable ({exc}); re-run `{command}`"
        ) from exc
    module = module.to(device)
    try:
        module.load_state_dict(state)
    except RuntimeError as exc:
        first = str(exc).splitlines()[1].strip() if "\n" in str(exc) else str(exc)
        raise UserError(
            f"{directory}: weights do not match the config ({first}); re-run `{command}`"
        ) from exc
    return module.eval()


def save_model(model: SkillModel, directory: str | Path, extra: dict[str, Any]) -> None:
    """Write the skill model: weights and `config.json` (model config + `extra`, e.g. dataset
    info)."""
    meta = {"format_version": FORMAT_VERSION, "model": model.config.to_dict(), **extra}
    _write(model, directory, SKILL_FORMAT, meta)


def read_config(directory: str | Path) -> dict[str, Any]:
    """The skill model checkpoint's config.json as a dict.

    Raises:
        UserError: no checkpoint there, or an unreadable / outdated one.
    """
    meta = _read_meta(directory, "model checkpoint", "oposm train")
    if meta.get("format_version") != FORMAT_VERSION:
        raise UserError(
            f"{Path(directory) / CONFIG_FILE}: checkpoint format is outdated; re-run `oposm train`"
        )
    return meta


def config_differences(a: SkillModelConfig, b: SkillModelConfig) -> list[str]:
    """`field: a != b` for each field where the two configs differ."""
    da, db = a.to_dict(), b.to_dict()
    return [f"{k}: {da[k]!r} != {db[k]!r}" for k in da if da[k] != db[k]]


def load_model(
    directory: str | Path,
    expected: SkillModelConfig | None = None,
    device: str | torch.device = "cpu",
) -> tuple[SkillModel, dict[str, Any]]:
    """Rebuild a `SkillModel` from `directory`; return it (eval mode) and its config.json dict.

    Raises:
        UserError: missing or corrupt files, or a config that differs from `expected` (the
            message names every differing field).
    """
    meta = read_config(directory)
    try:
        config = SkillModelConfig(**meta["model"])
    except (KeyError, TypeError) as exc:
        raise UserError(f"{directory}/{CONFIG_FILE} has no valid model config ({exc})") from exc
    if expected is not None and (diff := config_differences(config, expected)):
        raise UserError(
            f"checkpoint in {directory} is for another model config ({'; '.join(diff)}); "
            "retrain or use matching params"
        )
    return _load_weights(SkillModel(config), directory, device, "oposm train"), meta


def save_dynamics(model: DynamicsModel, directory: str | Path, extra: dict[str, Any]) -> None:
    """Write the single-step model: weights and `config.json` (config + `extra`, e.g. dataset
    info)."""
    meta = {"format": DYNAMICS_FORMAT, "format_version": FORMAT_VERSION}
    _write(model, directory, DYNAMICS_FORMAT, meta | {"model": asdict(model.config)} | extra)


def load_dynamics(
    directory: str | Path, device: str | torch.device = "cpu"
) -> tuple[DynamicsModel, dict[str, Any]]:
    """Rebuild a `DynamicsModel` (eval mode) and return it with its config.json dict.

    Raises:
        UserError: missing, corrupt or outdated files.
    """
    meta = _read_meta(directory, "dynamics model", "oposm dynamics")
    path = Path(directory) / CONFIG_FILE
    if meta.get("format") != DYNAMICS_FORMAT or meta.get("format_version") != FORMAT_VERSION:
        raise UserError(f"{path}: not a current dynamics model; re-run `oposm dynamics`")
    try:
        config = DynamicsConfig(**meta["model"])
    except (KeyError, TypeError) as exc:
        raise UserError(
            f"{path} has no valid model config ({exc}); re-run `oposm dynamics`"
        ) from exc
    return _load_weights(DynamicsModel(config), directory, device, "oposm dynamics"), meta


def save_policy(
    policy: GaussianPolicy, directory: str | Path, kind: str, extra: dict[str, Any]
) -> None:
    """Write a BC policy (`kind`: the stage that made it, `bc` or `gcbc`): weights and
    `config.json` (config + `extra`, e.g. dataset info)."""
    meta = {"format": POLICY_FORMAT, "format_version": FORMAT_VERSION, "kind": kind}
    _write(policy, directory, POLICY_FORMAT, meta | {"model": asdict(policy.config)} | extra)


def load_policy(
    directory: str | Path, kind: str, device: str | torch.device = "cpu"
) -> tuple[GaussianPolicy, dict[str, Any]]:
    """Rebuild the `kind` (`bc` | `gcbc`) policy in `directory` (eval mode) with its config.json.

    Raises:
        UserError: missing, corrupt or outdated files, or a policy of another kind (the message
            names the command that makes the right one).
    """
    command = f"oposm {kind}"
    meta = _read_meta(directory, f"{kind} policy", command)
    path = Path(directory) / CONFIG_FILE
    if meta.get("format") != POLICY_FORMAT or meta.get("format_version") != FORMAT_VERSION:
        raise UserError(f"{path}: not a current policy; re-run `{command}`")
    if meta.get("kind") != kind:
        raise UserError(f"{path} holds a {meta.get('kind')} policy, not {kind}; run `{command}`")
    try:
        config = PolicyConfig(**meta["model"])
    except (KeyError, TypeError) as exc:
        raise UserError(f"{path} has no valid policy config ({exc}); re-run `{command}`") from exc
    return _load_weights(GaussianPolicy(config), directory, device, command), meta
