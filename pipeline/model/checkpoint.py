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
from typing import Annotated, Any

import torch
from pydantic import BaseModel, Field
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from pipeline.errors import UserError
from pipeline.io import atomic_path
from pipeline.model.dynamics import DynamicsConfig, DynamicsModel
from pipeline.model.policy import GaussianPolicy, PolicyConfig
from pipeline.model.skill_model import SkillModel, SkillModelConfig
from pipeline.readback import READBACK_CONFIG, Count, read_json, validated

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


class _TrainedOn(BaseModel):
    """A checkpoint's `info`: the dataset it was trained on, as far as the checks read it."""

    model_config = READBACK_CONFIG
    name: str | None = None
    env_id: str | None = None
    env_kwargs: dict[str, Any] | None = None
    state_names: list[str] | None = None
    action_names: list[str] | None = None


class _SkillCheckpoint(BaseModel):
    """What is read from a skill model's config.json."""

    model_config = READBACK_CONFIG
    model: SkillModelConfig
    window: Annotated[int, Field(ge=2)] | None = None
    step: Count | None = None
    info: _TrainedOn | None = None


class _DynamicsCheckpoint(BaseModel):
    model_config = READBACK_CONFIG
    model: DynamicsConfig
    info: _TrainedOn | None = None


class _PolicyCheckpoint(BaseModel):
    model_config = READBACK_CONFIG
    model: PolicyConfig
    info: _TrainedOn | None = None


# What each checkpoint format is, and the command that writes it (for "holds X, not Y").
_KINDS = {
    None: ("a skill model", "oposm train"),
    DYNAMICS_FORMAT: ("a single-step dynamics model", "oposm dynamics"),
    POLICY_FORMAT: ("a behaviour-cloning policy", "oposm bc / oposm gcbc"),
}


def _not_a_checkpoint(directory: Path, what: str, command: str) -> UserError:
    """Why `directory` holds no checkpoint config, in words: missing, a file, or the folder of
    something else (segments, a resume state)."""
    if directory.is_file():
        return UserError(
            f"{directory} is a file, not a {what} folder; pass the folder `{command}` writes "
            f"(it holds {CONFIG_FILE} and {WEIGHTS_FILE})"
        )
    if (directory / "segments.json").exists():
        return UserError(
            f"{directory} holds segments (what `oposm segment` writes), not a {what}; pass the "
            f"folder `{command}` writes, e.g. data/models/<name>"
        )
    if (directory / "state.json").exists():
        return UserError(
            f"{directory} holds a training resume state, not a {what}; pass the folder "
            f"`{command}` writes, e.g. data/models/<name>"
        )
    if not directory.exists():
        return UserError(f"no {what} in {directory} (no such folder); run `{command}` first")
    return UserError(f"no {what} in {directory} (no {CONFIG_FILE}); run `{command}` first")


def _read_meta(directory: str | Path, what: str, command: str) -> dict[str, Any]:
    """config.json of the checkpoint in `directory` (`what` and `command` name it in errors)."""
    directory = Path(directory)
    path = directory / CONFIG_FILE
    if not path.is_file():
        raise _not_a_checkpoint(directory, what, command)
    meta = read_json(path, f"re-run `{command}`")
    if not isinstance(meta, dict):
        raise UserError(f"{path} is not a JSON object; it is damaged: re-run `{command}`")
    return meta


def _check_kind(meta: dict[str, Any], path: Path, fmt: str | None, what: str, command: str):
    """Refuse the config of another kind of checkpoint, saying which one it is."""
    found = meta.get("format")
    model = meta.get("model")
    if found is None and not (isinstance(model, dict) and "z_dim" in model):
        return  # not recognizably a skill model either: the checks that follow say what is off
    if found != fmt and found in _KINDS:
        kind, writer = _KINDS[found]
        raise UserError(
            f"{path.parent} holds {kind} (what `{writer}` writes), not {what}; pass the folder "
            f"`{command}` writes"
        )


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
    meta = _read_meta(directory, "skill model checkpoint", "oposm train")
    _check_kind(meta, Path(directory) / CONFIG_FILE, None, "a skill model", "oposm train")
    if meta.get("format_version") != FORMAT_VERSION:
        raise UserError(
            f"{Path(directory) / CONFIG_FILE}: checkpoint format is outdated; re-run `oposm train`"
        )
    return meta


def skill_horizon(meta: dict[str, Any], directory: str | Path) -> int:
    """T, the actions per skill, of a skill model's config.json (`load_model`'s `meta`): its
    training window less one."""
    window = meta.get("window")
    if not isinstance(window, int) or window < 2:
        raise UserError(
            f"{Path(directory) / CONFIG_FILE} has no 'window' entry (the states per skill it was "
            "trained on); re-run `oposm train`"
        )
    return window - 1


def config_differences(a: SkillModelConfig, b: SkillModelConfig) -> list[str]:
    """`field: a != b` for each field where the two configs differ."""
    da, db = asdict(a), asdict(b)
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
    path = Path(directory) / CONFIG_FILE
    config = validated(_SkillCheckpoint, meta, path, "re-run `oposm train`").model
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
    _check_kind(meta, path, DYNAMICS_FORMAT, "a dynamics model", "oposm dynamics")
    if meta.get("format") != DYNAMICS_FORMAT or meta.get("format_version") != FORMAT_VERSION:
        raise UserError(f"{path}: not a current dynamics model; re-run `oposm dynamics`")
    config = validated(_DynamicsCheckpoint, meta, path, "re-run `oposm dynamics`").model
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
    _check_kind(meta, path, POLICY_FORMAT, f"a {kind} policy", command)
    if meta.get("format") != POLICY_FORMAT or meta.get("format_version") != FORMAT_VERSION:
        raise UserError(f"{path}: not a current policy; re-run `{command}`")
    if meta.get("kind") != kind:
        raise UserError(f"{path} holds a {meta.get('kind')} policy, not {kind}; run `{command}`")
    config = validated(_PolicyCheckpoint, meta, path, f"re-run `{command}`").model
    return _load_weights(GaussianPolicy(config), directory, device, command), meta
