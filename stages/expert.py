"""Expert stage: train the direction-commanded ant expert (resumable), ship its actor, check it.

`train` runs or resumes SAC in a scratch folder (`scratch_dir`, outside the work tree); when the
run reaches `sac.total_steps` it ships the actor to `experts/<robot>/actor.safetensors` +
`actor.json` (committed, small) and checks it, writing the measured quality into that JSON.
`check` measures any exported actor (an intermediate one too) and writes a report.
"""

from __future__ import annotations

import logging
import os
import shlex
import sys
from pathlib import Path
from typing import Any

from pipeline.ant_expert.actor import load_actor, save_actor, update_info
from pipeline.ant_expert.config import AntExpertParams, check_robot
from pipeline.errors import UserError
from pipeline.io import write_json

log = logging.getLogger(__name__)


def scratch_dir(robot: str) -> Path:
    """`$XDG_CACHE_HOME/oposm/experts/<robot>/` (default `~/.cache/...`): resume checkpoints, the
    latest actor export, progress log, check report.

    Outside the work tree on purpose: training takes several sessions, and a session may get a
    freshly laid checkout (without git-ignored `data/`) but the same machine.
    """
    cache = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(cache) / "oposm" / "experts" / robot


def ship_dir(robot: str) -> Path:
    """`experts/<robot>/`: the committed actor and the params that produced it."""
    return Path("experts") / robot


def train(
    params: AntExpertParams, robot: str, out: Path, ship: Path | None, params_file: Path
) -> dict[str, Any]:
    """Train or resume; ship and check the actor once `total_steps` are done. Returns a summary."""
    from pipeline.ant_expert.training import ACTOR_FILE, train_direction_expert

    check_robot(robot)
    command = "oposm " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    info = {"command": command, "params_file": str(params_file)}
    summary = train_direction_expert(params.sac, out, info=info)
    result = {
        "steps": summary.steps,
        "total_steps": params.sac.total_steps,
        "finished": summary.finished,
        "steps_per_s": round(summary.steps_per_s, 2),
        "scratch": str(out),
    }
    log.info(
        "%s at step %d / %d (%.1f steps/s this run)",
        "finished" if summary.finished else "stopped",
        summary.steps,
        params.sac.total_steps,
        summary.steps_per_s,
    )
    if summary.finished and ship is not None:
        shipped = ship / ACTOR_FILE
        save_actor(load_actor(out / ACTOR_FILE), shipped)
        log.info("shipped the actor to %s; checking it", shipped)
        result["shipped"] = str(shipped)
        result["check"] = check(params, robot, shipped, out / "check.json")
    return result


def check(params: AntExpertParams, robot: str, actor_path: Path, report: Path) -> dict[str, Any]:
    """Measure an exported actor; write `report` and the actor JSON's `quality` entry."""
    from pipeline.ant_expert.check import check_direction_actor

    check_robot(robot)
    if not actor_path.exists():
        raise UserError(
            f"actor {actor_path} not found; train first (oposm expert train {robot}) or pass "
            f"--actor {scratch_dir(robot)}/actor.safetensors for the latest checkpoint's actor"
        )
    actor = load_actor(actor_path)
    quality = check_direction_actor(actor, params.check)
    quality["actor"] = str(actor_path)
    quality["actor_steps"] = actor.spec.info.get("steps")
    quality["command"] = "oposm " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    write_json(report, quality)
    update_info(actor_path, quality=quality)
    return quality
