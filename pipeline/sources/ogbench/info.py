"""What generated and imported OGBench datasets share: the maze spec, names and units, metadata."""

from __future__ import annotations

import importlib.metadata
from typing import Any

from pipeline.dataset import DatasetInfo
from pipeline.envs.ogbench import OGBenchMazeSpec
from pipeline.envs.spec import make_env_spec


def ogbench_spec(env_id: str) -> OGBenchMazeSpec:
    """The `OGBenchMazeSpec` of a supported OGBench maze id."""
    spec = make_env_spec(env_id)
    assert isinstance(spec, OGBenchMazeSpec)
    return spec


def names(spec: OGBenchMazeSpec) -> tuple[list[str], list[str], list[str], list[str]]:
    """State names and units, action names and units of the point or the ant."""
    if spec.loco == "point":
        return ["x", "y"], ["m", "m"], ["dx", "dy"], ["0.2 m", "0.2 m"]
    nq, nv = spec.model.nq, spec.model.nv
    states = ["x", "y", *(f"qpos[{i}]" for i in range(2, nq)), *(f"qvel[{i}]" for i in range(nv))]
    units = ["m", "m", *([""] * (nq - 2 + nv))]
    actions = [f"torque[{i}]" for i in range(spec.action_dim)]
    return states, units, actions, ["1"] * spec.action_dim


def versions() -> dict[str, str]:
    """Installed versions of what simulates OGBench's mazes (provenance)."""
    packages = ("ogbench", "gymnasium", "mujoco", "numpy")
    return {n: importlib.metadata.version(n) for n in packages}


def dataset_info(
    spec: OGBenchMazeSpec,
    name: str,
    seed: int | None,
    generator: dict[str, Any],
    goal_dim: int,
) -> DatasetInfo:
    """`DatasetInfo` of an OGBench dataset in `spec`'s maze; `generator` gets the maze layout."""
    states, state_units, actions, action_units = names(spec)
    return DatasetInfo(
        name=name,
        source="ogbench",
        env_id=spec.env_id,
        state_names=states,
        action_names=actions,
        state_units=state_units,
        action_units=action_units,
        control_period=spec.dt,
        physics_dim=spec.physics_dim,
        goal_dim=goal_dim,
        seed=seed,
        env_kwargs={},
        generator={**generator, "maze_layout": spec.layout},
        versions=versions(),
    )
