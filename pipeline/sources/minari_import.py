"""Import a local Minari dataset through the `minari` library.

Minari stores N + 1 observations per episode (the last one after the last action) and N actions,
rewards, terminations and truncations; the final observation is dropped (`pipeline/dataset.py`).
Observations may be dicts, as PointMaze's `observation` / `achieved_goal` / `desired_goal`: the
state is the concatenation of `state_keys` (default `observation`), the goal `goal_key` when the
dict has it. Per-step `infos` also have N + 1 entries, aligned with the observations.

When the dataset's environment spec is a PointMaze we simulate, the spec's id and kwargs (the maze
map, ...) become `env_id` / `env_kwargs`, the state is named `x, y, vx, vy` and the full physics
state `[time, qpos, qvel]` is taken from `infos["qpos"]` / `infos["qvel"]` when recorded, else
from the observation, which for PointMaze is exactly qpos and qvel.

gymnasium-robotics' Franka kitchen (`FrankaKitchen-v1`, D4RL's kitchen: Minari's
`D4RL/kitchen/{complete,partial,mixed}-v2`) is simulated too (`pipeline.envs.kitchen`): its
subtasks are the keys of the observations' `desired_goal` dict (else the env's
`tasks_to_complete`) and must be one of D4RL's task sets, recorded as `env_kwargs
["tasks_to_complete"]` and `generator["kitchen_task_set"]`; the goal is the `desired_goal` dict's
subtask goals concatenated in the spec's order (its `goal_vector`); states and actions get the
model's joint names; the physics state is `infos["physics"]` where recorded (the exact state,
`write_kitchen_minari`), else made from the observation (qpos and qvel, warm start zero: exact
only for noise-free data, which D4RL's are not).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from pipeline.dataset import DatasetInfo, Episode
from pipeline.envs.kitchen import (
    STATE_DIM,
    SUBTASKS,
    check_subtasks,
    dataset_task_set,
    is_kitchen,
    kitchen_action_names,
    kitchen_spec,
    observation_names,
    physics_from_observations,
)
from pipeline.errors import UserError
from pipeline.sources.common import (
    MAZE_ACTION_NAMES,
    MAZE_ACTION_UNITS,
    MAZE_STATE_NAMES,
    MAZE_STATE_UNITS,
    Clock,
    ImportedDataset,
    check_control_period,
    is_point_maze,
    maze_metadata,
    missing,
    numeric,
    physics_state,
    same_lengths,
    unique_names,
    vector_names,
    versions,
    with_progress,
)

log = logging.getLogger(__name__)


def _data_dir(dataset_id: str | None, path: str | Path | None) -> Path:
    """The Minari `data/` directory (holding metadata.json) of a dataset id or path."""
    import minari
    from minari.storage.datasets_root_dir import get_dataset_path

    if path:
        root = Path(path)
        if not root.is_dir():
            raise UserError(f"Minari dataset folder {root} does not exist")
        for candidate in (root / "data", root):
            if (candidate / "metadata.json").is_file():
                return candidate
        raise UserError(f"{root} is not a Minari dataset (no data/metadata.json)")
    if not dataset_id:
        raise UserError("set ingest.minari.dataset_id (or ingest.minari.path) to import Minari")
    data = get_dataset_path(dataset_id) / "data"
    if not (data / "metadata.json").is_file():
        local = ", ".join(sorted(minari.list_local_datasets())) or "(none)"
        raise UserError(
            f"Minari dataset {dataset_id!r} not found under {get_dataset_path()} "
            f"(MINARI_DATASETS_PATH); local datasets: {local}; "
            f"fetch it with `minari download {dataset_id}`"
        )
    return data


def _box(space: gym.Space, what: str) -> int:
    """Size of a flat numeric Box space (error for anything else)."""
    if not isinstance(space, gym.spaces.Box) or space.dtype.kind not in "biuf":
        raise UserError(f"{what} is a {type(space).__name__}, not a numeric Box; pick another key")
    return int(np.prod(space.shape, dtype=np.int64))


def _pick(space: gym.Space, keys: list[str], what: str, param: str) -> list[tuple[str, int]]:
    """(key, size) of the parts of `space` named by `keys` ([] = the whole array space)."""
    if isinstance(space, gym.spaces.Dict):
        if not keys:
            raise UserError(f"{what}s are dicts: set {param} to some of: {', '.join(space)}")
        for key in keys:
            if key not in space.spaces:
                raise missing(f"{what} key", key, space.spaces, f"the {what} space")
        return [(key, _box(space[key], f"{what} key {key!r}")) for key in keys]
    if keys:
        raise UserError(f"{what}s are arrays, not dicts: set {param} to null/[] (got {keys})")
    return [("", _box(space, what))]


def _env(dataset: Any) -> tuple[str, dict[str, Any], dict[str, Any]]:
    """(env_id, env_kwargs, generator extras) from the dataset's environment spec, if any."""
    spec = dataset.env_spec
    if spec is None:
        return "", {}, {}
    extras: dict[str, Any] = {"max_episode_steps": spec.max_episode_steps}
    try:
        extras["env_spec"] = spec.to_json()
        kwargs = json.loads(json.dumps(spec.kwargs))
    except (TypeError, ValueError):
        log.warning("the env spec of %s has kwargs that are not JSON; not recorded", spec.id)
        kwargs = {}
    return spec.id, kwargs, extras


def _control_period(env_id: str, dataset: Any, given: float | None) -> float:
    """Seconds per step: given, else the environment's `dt` (building the env from its spec)."""
    if given is not None or not env_id:
        return check_control_period(given, "ingest.minari.control_period")
    try:
        env = dataset.recover_environment()
    except Exception as exc:  # any env may fail to build; the user can still give the period
        raise UserError(
            f"cannot build {env_id} to read its time step ({exc}); set ingest.minari.control_period"
        ) from exc
    try:
        return check_control_period(
            getattr(env.unwrapped, "dt", None), "ingest.minari.control_period"
        )
    finally:
        env.close()


def read_minari(
    name: str,
    dataset_id: str | None = None,
    path: str | Path | None = None,
    state_keys: list[str] | None = None,
    action_key: str | None = None,
    goal_key: str | None = "desired_goal",
    control_period: float | None = None,
    progress: bool = False,
) -> ImportedDataset:
    """Open a local Minari dataset as a stream of episodes.

    Args:
        name: Dataset name for `DatasetInfo`.
        dataset_id: Minari id, looked up under `MINARI_DATASETS_PATH` (~/.minari/datasets).
        path: The dataset's folder (the one holding `data/`), instead of an id.
        state_keys: Observation dict keys concatenated, in this order, into the state; [] for
            array observations. Default `["observation"]`.
        action_key: Key of a dict action space; None for array actions.
        goal_key: Observation dict key recorded as the goal, if the dict has it; None for none.
        control_period: Seconds per step; default the environment's `dt`.
        progress: Show a progress bar while the episodes are read.
    """
    import minari

    state_keys = ["observation"] if state_keys is None else list(state_keys)
    data_dir = _data_dir(dataset_id, path)
    try:
        dataset = minari.MinariDataset(data_dir)
    except (ValueError, KeyError, OSError) as exc:
        raise UserError(f"{data_dir} is not a readable Minari dataset ({exc})") from exc
    if dataset.total_episodes == 0 or dataset.total_steps == 0:
        raise UserError(f"Minari dataset {dataset.id!r} holds no steps (empty dataset)")
    states = _pick(dataset.observation_space, state_keys, "observation", "ingest.minari.state_keys")
    actions = _pick(
        dataset.action_space,
        [action_key] if action_key else [],
        "action",
        "ingest.minari.action_key",
    )
    obs_space = dataset.observation_space
    env_id, env_kwargs, extras = _env(dataset)
    goal = None
    if is_kitchen(env_id):
        env_kwargs, goal = _kitchen(dataset, env_kwargs, extras, states, goal_key)
    elif goal_key and isinstance(obs_space, gym.spaces.Dict):
        if goal_key in obs_space.spaces:
            goal = (goal_key, _box(obs_space[goal_key], f"goal key {goal_key!r}"))
        else:
            log.info("observations have no %r key; no goals imported", goal_key)
    info = _info(name, dataset, env_id, env_kwargs, extras, states, actions, goal, control_period)
    info.generator.update(
        dataset_id=dataset.id,
        path=str(data_dir.resolve()),
        state_keys=state_keys,
        action_key=action_key,
        goal_key=goal[0] if goal else None,
    )
    episodes = _episodes(dataset, info, states, actions, goal)
    frames = int(dataset.total_steps)
    return ImportedDataset(info, with_progress(episodes, frames, name, progress), frames)


def _kitchen(
    dataset: Any,
    env_kwargs: dict[str, Any],
    extras: dict[str, Any],
    states: list[tuple[str, int]],
    goal_key: str | None,
) -> tuple[dict[str, Any], tuple[str, int] | None]:
    """The kitchen's env kwargs (its subtasks as `tasks_to_complete`) and goal (`desired_goal`'s
    subtasks, concatenated), its D4RL task set into `extras` (module docstring).

    Raises:
        UserError: the state is not the 59-dim `observation`, or the subtasks are no D4RL task
            set.
    """
    if states != [("observation", STATE_DIM)]:
        raise UserError(
            f"{dataset.id}: the kitchen's state is its {STATE_DIM}-dim `observation` (qpos, "
            f"qvel); set ingest.minari.state_keys=[observation] (got {[k for k, _ in states]})"
        )
    space = dataset.observation_space
    desired = space.spaces.get("desired_goal") if isinstance(space, gym.spaces.Dict) else None
    if isinstance(desired, gym.spaces.Dict):
        subtasks = check_subtasks(list(desired.spaces), f"{dataset.id}: desired_goal")
    else:
        subtasks = check_subtasks(env_kwargs.get("tasks_to_complete", SUBTASKS))
    extras["kitchen_task_set"] = dataset_task_set(subtasks, str(dataset.id))
    extras["subtasks"] = list(subtasks)
    kwargs = {**env_kwargs, "tasks_to_complete": list(subtasks)}
    goal = None
    if goal_key and isinstance(space, gym.spaces.Dict) and goal_key in space.spaces:
        part = space[goal_key]
        if isinstance(part, gym.spaces.Dict):
            missing_tasks = [t for t in subtasks if t not in part.spaces]
            if missing_tasks:
                raise UserError(f"{dataset.id}: {goal_key} has no subtask(s) {missing_tasks}")
            size = sum(_box(part[t], f"{goal_key}[{t!r}]") for t in subtasks)
        else:
            size = _box(part, f"goal key {goal_key!r}")
        goal = (goal_key, size)
    return kwargs, goal


def _info(
    name: str,
    dataset: Any,
    env_id: str,
    env_kwargs: dict[str, Any],
    extras: dict[str, Any],
    states: list[tuple[str, int]],
    actions: list[tuple[str, int]],
    goal: tuple[str, int] | None,
    control_period: float | None,
) -> DatasetInfo:
    """`DatasetInfo` of the dataset: PointMaze names, layout and physics for simulated mazes."""
    maze = is_point_maze(env_id) and [k for k, _ in states] == ["observation"] and states[0][1] == 4
    generator: dict[str, Any] = dict(extras)
    if maze:
        meta = maze_metadata(env_id, env_kwargs.get("maze_map"))
        dt = meta["control_period"]
        if control_period is not None and abs(control_period - dt) > 1e-12:
            raise UserError(
                f"{env_id} steps last {dt} s (the simulator's dt), not {control_period}"
            )
        control_period = dt
        generator["maze_layout"] = meta["maze_layout"]
        generator["physics_from"] = (
            'infos["qpos"], infos["qvel"] if recorded, else the observation (qpos, qvel)'
        )
        state_names, state_units = MAZE_STATE_NAMES, MAZE_STATE_UNITS
        action_names, action_units = MAZE_ACTION_NAMES, MAZE_ACTION_UNITS
        physics_dim = meta["physics_dim"]
    elif is_kitchen(env_id):
        spec = kitchen_spec(env_kwargs)
        if control_period is not None and abs(control_period - spec.dt) > 1e-12:
            raise UserError(
                f"{env_id} steps last {spec.dt} s (the simulator's dt), not {control_period}"
            )
        control_period = spec.dt
        generator["physics_from"] = (
            'infos["physics"] if recorded (exact), else the observation (qpos, qvel; warm '
            "start zero)"
        )
        state_names, state_units = observation_names(spec)
        action_names = kitchen_action_names(spec)
        action_units = [""] * len(action_names)
        physics_dim = spec.physics_dim
    else:
        control_period = _control_period(env_id, dataset, control_period)
        state_names = unique_names([(k or "obs", vector_names(k or "obs", n)) for k, n in states])
        action_names = vector_names(actions[0][0] or "act", actions[0][1])
        state_units, action_units = [""] * len(state_names), [""] * len(action_names)
        physics_dim = 0
    return DatasetInfo(
        name=name,
        source="minari",
        env_id=env_id,
        state_names=list(state_names),
        action_names=list(action_names),
        state_units=list(state_units),
        action_units=list(action_units),
        control_period=float(control_period),
        physics_dim=physics_dim,
        goal_dim=goal[1] if goal else 0,
        env_kwargs=env_kwargs,
        generator=generator,
        versions=versions("minari", "gymnasium", "gymnasium_robotics"),
    )


def _part(values: Any, key: str, n: int, order: Sequence[str] = ()) -> np.ndarray:
    """The first n rows of one key of the episode's (possibly dict) values, as `[n, d]`; a key
    holding a dict of arrays gives those of `order`, side by side."""
    array = values[key] if key else values
    if isinstance(array, dict):  # the kitchen's goals: one array per subtask, in `order`
        array = np.concatenate([np.asarray(array[k])[:n].reshape(n, -1) for k in order], axis=1)
    return numeric(np.asarray(array)[:n].reshape(n, -1), key or "value")


def _episodes(
    dataset: Any,
    info: DatasetInfo,
    states: list[tuple[str, int]],
    actions: list[tuple[str, int]],
    goal: tuple[str, int] | None,
) -> Iterator[Episode]:
    clock = Clock(info.control_period)
    subtasks = (info.generator or {}).get("subtasks", [])  # the kitchen's goal dict order
    for index, ep in enumerate(dataset.iterate_episodes()):
        first, act = states[0][0], actions[0][0]
        n = len(ep.actions[act] if act else ep.actions)
        n_obs = len(ep.observations[first] if first else ep.observations)
        same_lengths(
            {"observations - 1": n_obs - 1, "actions": n, "rewards": len(ep.rewards)},
            f"Minari episode {ep.id}",
        )
        time = clock.next(n)
        obs = np.concatenate([_part(ep.observations, k, n) for k, _ in states], axis=1)
        physics = None
        if info.physics_dim and is_kitchen(info.env_id):
            physics = _kitchen_physics(ep, info, obs, time)
        elif info.physics_dim:
            qpos, qvel = ep.infos.get("qpos"), ep.infos.get("qvel")
            if qpos is not None and qvel is not None:
                physics = physics_state(time, np.asarray(qpos)[:n], np.asarray(qvel)[:n])
            else:
                physics = physics_state(time, obs[:, :2], obs[:, 2:4])
        yield Episode(
            index=index,
            observations=obs,
            actions=_part(ep.actions, actions[0][0], n),
            time=time,
            physics=physics,
            goals=_part(ep.observations, goal[0], n, subtasks) if goal else None,
            rewards=numeric(ep.rewards, "rewards", dims=1),
            terminals=np.asarray(ep.terminations, dtype=bool),
        )


def _kitchen_physics(ep: Any, info: DatasetInfo, obs: np.ndarray, time: np.ndarray) -> np.ndarray:
    """The kitchen's states `[n, physics_dim]`: `infos["physics"]` where recorded (with the
    dataset clock's time), else made from the observations (module docstring)."""
    n = len(obs)
    recorded = ep.infos.get("physics") if isinstance(ep.infos, dict) else None
    if recorded is None:
        return physics_from_observations(kitchen_spec(info.env_kwargs), obs, time)
    physics = np.array(recorded, dtype=np.float64)
    if physics.ndim != 2 or physics.shape[0] < n or physics.shape[1] != info.physics_dim:
        raise UserError(
            f"Minari episode {ep.id}: infos['physics'] is {list(physics.shape)}, not "
            f"[{n + 1}, {info.physics_dim}] (the kitchen's exact state per observation)"
        )
    physics = physics[:n]
    physics[:, 0] = time
    return physics
