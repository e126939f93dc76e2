"""Model checkpoints: safetensors weights + a JSON config that is enough to rebuild the model.

Loading never unpickles anything: weights come from safetensors, the config from JSON.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from pipeline.errors import UserError
from pipeline.io import atomic_path
from pipeline.model.skill_model import SkillModel, SkillModelConfig

WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
FORMAT_VERSION = 1


def save_model(model: SkillModel, directory: str | Path, extra: dict[str, Any]) -> None:
    """Write `model.safetensors` and `config.json` (model config + `extra`, e.g. dataset info).

    Each file is replaced atomically; the weights are written first, so a config always
    describes weights at least as new as itself.
    """
    directory = Path(directory)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    with atomic_path(directory / WEIGHTS_FILE) as tmp:
        save_file(state, tmp, metadata={"format": "oposm-skill-model"})
    meta = {"format_version": FORMAT_VERSION, "model": model.config.to_dict(), **extra}
    with atomic_path(directory / CONFIG_FILE) as tmp:
        tmp.write_text(json.dumps(meta, indent=2) + "\n")


def read_config(directory: str | Path) -> dict[str, Any]:
    """The checkpoint's config.json as a dict.

    Raises:
        UserError: no checkpoint there, or an unreadable / outdated one.
    """
    path = Path(directory) / CONFIG_FILE
    if not path.exists():
        raise UserError(f"no model checkpoint in {directory}; run `oposm train` first")
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise UserError(f"{path} is unreadable ({exc}); re-run `oposm train`") from exc
    if meta.get("format_version") != FORMAT_VERSION:
        raise UserError(f"{path}: checkpoint format is outdated; re-run `oposm train`")
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
    try:
        state = load_file(Path(directory) / WEIGHTS_FILE, device=str(device))
    except (OSError, SafetensorError) as exc:
        raise UserError(f"{directory}/{WEIGHTS_FILE} is unreadable ({exc}); retrain") from exc
    model = SkillModel(config).to(device)
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        first = str(exc).splitlines()[1].strip() if "\n" in str(exc) else str(exc)
        raise UserError(f"{directory}: weights do not match the config ({first})") from exc
    return model.eval(), meta
