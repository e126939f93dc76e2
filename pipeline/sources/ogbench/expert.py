"""Who acts in OGBench's recipe: the point's oracle direction itself, or the ant expert walking it.

`generate_locomaze.py` turns a unit direction (to the BFS oracle's subgoal, or `explore`'s random
one) into an action with an `actor_fn`: for the point the direction is the action; for the ant a
trained direction-commanded policy gets the ant's state without its x-y position followed by the
direction (`[qpos[2:], qvel, direction]`, 29 numbers) and acts deterministically (its
`temperature=0`). Gaussian noise and the clip to the action bounds come after, in the caller.

Here the ant's policy is our own `DirectionActor` (`pipeline.ant_expert.actor`, issue 19 §1), read
from safetensors + JSON, never from a pickle; its file's sha256 and its JSON's `info` (command,
seed, steps, measured quality) go into the dataset's metadata.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.ant_expert.actor import DirectionActor, json_path, load_actor
from pipeline.envs.ant import expert_observation
from pipeline.envs.ogbench import OGBenchMazeSpec
from pipeline.errors import UserError

Controller = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(observation `[state_dim]`, unit direction `[2]`) -> action before noise `[action_dim]`."""


def point_controller(observation: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The point's action is the direction (`actor_fn` returns `ob[-2:]`)."""
    return direction


def ant_controller(actor: DirectionActor) -> Controller:
    """The ant expert walking the direction: `actor([qpos[2:], qvel, direction])`, float64."""

    def act(observation: np.ndarray, direction: np.ndarray) -> np.ndarray:
        return actor.act(expert_observation(observation, direction)).astype(np.float64)

    return act


def sha256(path: Path) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def load_ant_expert(path: str | Path, spec: OGBenchMazeSpec) -> tuple[DirectionActor, dict]:
    """The ant expert at `path` (`ingest.ogbench.expert`) and its provenance for the metadata.

    Returns:
        The actor (eval mode) and `{"path", "sha256", "json_sha256", "obs_dim", "hidden",
        "activation", "info"}`.

    Raises:
        UserError: the file or its JSON is missing or unreadable, or the actor does not fit the
            maze's ant (observation `state_dim` = 29, `action_dim` = 8, robot "ant").
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(
            f"ant expert {path} not found (ingest.ogbench.expert); point it at an actor "
            "(experts/ant/actor.safetensors) or make one with `oposm expert train ant`"
        )
    try:
        actor = load_actor(path)
    except UserError as exc:
        raise UserError(f"ingest.ogbench.expert: {exc}") from exc
    actor_spec = actor.spec
    # The expert sees the state without x-y, plus the 2 numbers of the direction.
    wanted = (spec.state_dim, spec.action_dim)
    robot = actor_spec.info.get("robot", "ant")
    if (actor_spec.obs_dim, actor_spec.action_dim) != wanted or robot != "ant":
        raise UserError(
            f"{path} is a {robot} actor with {actor_spec.obs_dim} observations and "
            f"{actor_spec.action_dim} actions; {spec.env_id}'s ant expert needs {wanted[0]} and "
            f"{wanted[1]} (set ingest.ogbench.expert to an ant actor)"
        )
    provenance: dict[str, Any] = {
        "path": str(path),
        "sha256": sha256(path),
        "json_sha256": sha256(json_path(path)),
        "obs_dim": actor_spec.obs_dim,
        "hidden": list(actor_spec.hidden),
        "activation": actor_spec.activation,
        "info": actor_spec.info,
    }
    return actor, provenance
