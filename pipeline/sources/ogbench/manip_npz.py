"""OGBench's manipulation `.npz` files: read them (`load_manipulation_files`,
`manipulation_episodes`; `open_manipulation` imports them), each step's state restored from the
file; write our generated episodes in their layout (`write_manipulation_npz`).

An OGBench manipulation file (`data_gen_scripts/generate_manipspace.py`; e.g.
`cube-single-play-v0.npz`, 1000 episodes of 1001 steps, and `cube-single-play-v0-val.npz`, 100
more) holds per step `observations`, `actions`, `terminals` (set on each episode's last step),
`qpos` and `qvel` (float32: the physics before the step) and, in the scene and the puzzles
(`puzzle-3x3-play-v0.npz`, ...), `button_states` (int64; 2 in the scene, rows x cols in a
puzzle). The `-val.npz` companion, when present, is appended as later episodes.

**Restoring a state.** A state here (`ManipSpaceSpec.physics_state`) also holds the solver's
warm start and the "readings" OGBench computes the observation and the next action from (the
pinch site's pose and the pad's contact force, one physics step stale in the cube envs). The file
has neither, so `restore_physics` takes:

- `qpos`, `qvel` and the button states from the file (float32, as stored);
- the warm start zero, as after a reset (it changes the solver's answer in the last bits);
- the pinch position and yaw from the step's own observation, the pose matrix pointing down
  with that yaw, and a pad force whose norm gives the observed contact: what the observation
  and the next action read of them (a pose recomputed from `qpos` is one physics step newer
  than OGBench's: it moves the next observation by up to ~2e-2, this by ~2e-4).

So `observe` of a restored state is the recorded observation to float32 rounding, and one
`control_step` with the recorded action lands within `restore_errors` of the recorded next
observation (the ingest check measures it and reports `restore_next_error_max` / `_mean`; on
files OGBench's script made, docs/manipulation.md: median ~1e-6, mean < 1e-4, rare steps up to
~0.04). After a subtask switch in a cube env the file holds the observation from before
`set_new_target` refreshed the pinch pose while the env acted from the fresh one: such a step
restores the pose the file shows.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable, Iterator
from pathlib import Path

import mujoco
import numpy as np

from pipeline.dataset import Episode
from pipeline.envs.manipspace.env import (
    CONTACT_FORCE_SCALE,
    CUBE_DIM,
    EFFECTOR_DOWN_WXYZ,
    MANIPSPACE_ENVS,
    PROPRIO_DIM,
    READINGS,
    XYZ_CENTER,
    XYZ_SCALE,
    ManipSpaceSpec,
    check_manipspace_id,
    manipspace_spec,
)
from pipeline.errors import UserError
from pipeline.io import atomic_path
from pipeline.sources.common import Clock, missing, same_lengths, with_progress
from pipeline.sources.ogbench.npz import episode_ends, load_npz, maze_of_file, with_val_file

log = logging.getLogger(__name__)

REQUIRED = ("observations", "actions", "terminals", "qpos", "qvel")
# Observation columns of the readings (`pipeline.envs.manipspace.env`'s layout).
PINCH = slice(12, 15)
COS_YAW, SIN_YAW, CONTACT = 15, 16, 18
YAW_IN_CUBE = (7, 8)  # a cube's cos / sin of yaw, after its position (3) and quaternion (4)
# Largest gap between a restored state's observation (or a state's cube positions) and the
# recorded one, in observation units, that float32 storage explains: values up to ~10 carry
# ~1e-6 of rounding. A file whose observations are not its states' is off by far more.
FLOAT32_TOLERANCE = 1e-4
# `cube-double-noisy-v0.npz` -> (`cube-double-v0`, `noisy`); every manipulation file OGBench
# publishes has this form (puzzle-3x3 ... 4x6, cube-single ... quadruple, scene).
_FILE_NAME = re.compile(r"^(cube-[a-z]+|scene|puzzle-\d+x\d+)-(play|noisy)-v0(?:-val)?\.npz$")


def manipulation_of_file(path: Path) -> tuple[str, str] | None:
    """The env id and dataset type an OGBench manipulation file name names
    (`scene-play-v0-val.npz` -> (`scene-v0`, `play`)), or None for another name."""
    match = _FILE_NAME.match(path.name)
    return (f"{match.group(1)}-v0", match.group(2)) if match else None


def _env_of(path: Path, env_id: str) -> tuple[str, str | None]:
    """`env_id` checked against what the file name says; its dataset type (None: unnamed)."""
    maze = maze_of_file(path)
    if maze is not None:
        raise UserError(
            f"{path} is OGBench's {maze} maze data, but ingest.ogbench.env_id is {env_id}; "
            f"set ingest.ogbench.env_id={maze}"
        )
    if path.name.startswith("visual-"):
        raise UserError(
            f"{path} is one of OGBench's visual datasets (64 x 64 images, no states to "
            f"simulate); import its state-based file {path.name.removeprefix('visual-')}"
        )
    named = manipulation_of_file(path)
    if named is None:
        return env_id, None
    file_env, dataset_type = named
    if file_env not in MANIPSPACE_ENVS:
        raise UserError(
            f"{path} is OGBench's {file_env} data, an env not simulated here; importable: "
            f"{', '.join(MANIPSPACE_ENVS)}"
        )
    if file_env != env_id:
        raise UserError(
            f"{path} is a {file_env} dataset, but ingest.ogbench.env_id is {env_id}; "
            f"set ingest.ogbench.env_id={file_env}"
        )
    return env_id, dataset_type


def _sizes(spec: ManipSpaceSpec) -> dict[str, int]:
    """Values per step of each array an OGBench file of `spec`'s env holds."""
    sizes = {
        "observations": spec.state_dim,
        "actions": spec.action_dim,
        "qpos": spec.model.nq,
        "qvel": spec.model.nv,
    }
    if spec.n_buttons:
        sizes["button_states"] = spec.n_buttons
    return sizes


def _misfit(arrays: dict[str, np.ndarray], spec: ManipSpaceSpec) -> str | None:
    """Which array's size does not fit `spec`'s env (e.g. `qpos has 30 values per step,
    cube-single-v0 has 21`), or None."""
    for key, size in _sizes(spec).items():
        if key not in arrays:
            continue
        got = int(np.prod(arrays[key].shape[1:]))
        if got != size:
            return f"`{key}` has {got} values per step, {spec.env_id} has {size}"
    return None


def _check_arrays(arrays: dict[str, np.ndarray], where: str, spec: ManipSpaceSpec) -> None:
    """Keys, numeric types, lengths and sizes against the env: one-line `UserError`s."""
    needed = (*REQUIRED, "button_states") if spec.n_buttons else REQUIRED
    for key in needed:
        if key not in arrays:
            raise missing("array", key, arrays, f"{where} (not an OGBench {spec.env_id} file?)")
    for key in needed:
        if arrays[key].dtype.kind not in "biuf":
            raise UserError(f"{where}: `{key}` is not numeric (dtype {arrays[key].dtype})")
    same_lengths({k: int(arrays[k].shape[0]) for k in needed}, where)
    if arrays["observations"].shape[0] == 0:
        raise UserError(f"{where} holds no steps (empty dataset)")
    why = _misfit(arrays, spec)
    if why is not None:
        fit = next((e for e in MANIPSPACE_ENVS if _misfit(arrays, manipspace_spec(e)) is None),
                   None)  # fmt: skip
        hint = f"set ingest.ogbench.env_id={fit}" if fit else "it is not an OGBench file"
        raise UserError(f"{where}: {why}; {hint}")


def restore_physics(
    spec: ManipSpaceSpec,
    time: np.ndarray,
    observations: np.ndarray,
    qpos: np.ndarray,
    qvel: np.ndarray,
    button_states: np.ndarray | None = None,
) -> np.ndarray:
    """States `[N, physics_dim]` of N recorded steps (module docstring: qpos, qvel and button
    states as given, warm start zero, the readings from each step's observation).

    Args:
        time: `[N]` the dataset clock.
        observations: `[N, state_dim]`; qpos `[N, nq]`; qvel `[N, nv]`.
        button_states: `[N, n_buttons]` (the scene, a puzzle; else None).
    """
    n = len(observations)
    yaw = np.arctan2(observations[:, SIN_YAW], observations[:, COS_YAW])
    c, s, zero, one = np.cos(yaw), np.sin(yaw), np.zeros(n), np.ones(n)
    rz = np.stack([c, -s, zero, s, c, zero, zero, zero, one], axis=1).reshape(n, 3, 3)
    down = np.empty(9)
    mujoco.mju_quat2Mat(down, np.array(EFFECTOR_DOWN_WXYZ, dtype=np.float64))
    mat = (rz @ down.reshape(3, 3)).reshape(n, 9)
    force = np.zeros((n, 6))  # only its norm is read (the contact observation)
    force[:, 3] = observations[:, CONTACT] * CONTACT_FORCE_SCALE
    pinch = XYZ_CENTER + observations[:, PINCH] / XYZ_SCALE
    parts = [time[:, None], qpos, qvel, np.zeros_like(qvel), pinch, mat, force]
    if spec.n_buttons:
        assert button_states is not None
        parts.append(button_states)
    physics = np.concatenate(parts, axis=1).astype(np.float64)
    assert READINGS == 3 + 9 + 6 and physics.shape == (n, spec.physics_dim)
    return physics


def compared_dims(spec: ManipSpaceSpec) -> np.ndarray:
    """The observation dims a restore is judged on: all but each cube's cos / sin of yaw. Those
    are ill-conditioned where a cube stands on an edge (the yaw of a quaternion near its gimbal
    lock): float32 storage of the quaternion, itself compared, turns them by up to 2."""
    yaw = [PROPRIO_DIM + CUBE_DIM * i + k for i in range(spec.n_cubes) for k in YAW_IN_CUBE]
    return np.setdiff1d(np.arange(spec.state_dim), yaw)


def restore_errors(
    spec: ManipSpaceSpec, ep: Episode, every: int, step_every: int
) -> tuple[np.ndarray, np.ndarray]:
    """How far the episode's states, restored, are from what it recorded, in observation units
    (max over `compared_dims`): at every `every`-th step its own observation, and at every
    `step_every`-th step (a multiple of `every`) the observation one `control_step` with the
    recorded action leads to, against the recorded next one. The last step (no next one) is
    left out.

    Returns:
        `[k]` own-observation gaps and `[m]` next-observation gaps.
    """
    dims = compared_dims(spec)
    data = mujoco.MjData(spec.model)
    own, after = [], []
    for t in range(0, len(ep) - 1, every):
        spec.set_physics_state(data, ep.physics[t])
        own.append(np.abs(spec.observe(data) - ep.observations[t])[dims].max())
        if t % step_every == 0:
            spec.control_step(spec.model, data, ep.actions[t])
            after.append(np.abs(spec.observe(data) - ep.observations[t + 1])[dims].max())
    return np.array(own), np.array(after)


def _fits_observations(arrays: dict[str, np.ndarray], where: str, spec: ManipSpaceSpec) -> None:
    """The file's first step restored must observe as recorded: else its observations are not
    its states' (another env's layout, another model)."""
    ep = next(_episodes([(arrays, np.array([1]))], spec, Clock(spec.dt)))
    data = mujoco.MjData(spec.model)
    spec.set_physics_state(data, ep.physics[0])
    gap = float(np.abs(spec.observe(data) - ep.observations[0])[compared_dims(spec)].max())
    if not gap <= FLOAT32_TOLERANCE:
        raise UserError(
            f"{where}: its first observation is not that of its qpos / qvel in {spec.env_id} "
            f"(off by {gap:.3g}): not an OGBench {spec.env_id} file"
        )


def load_manipulation_files(
    path: Path, env_id: str, include_val: bool
) -> tuple[str | None, list[Path], list[tuple[dict[str, np.ndarray], np.ndarray]]]:
    """The file (and its `-val.npz`), checked: its dataset type (from the name; None if it
    names none), the files, and per file its arrays and episode ends.

    Raises:
        UserError: a missing, damaged or foreign file, a name naming another env, missing or
            misfit arrays, or observations that are not their states'.
    """
    env_id, dataset_type = _env_of(path, env_id)
    check_manipspace_id(env_id)
    spec = manipspace_spec(env_id)
    files = with_val_file(path, include_val)
    loaded = []
    for f in files:
        arrays = load_npz(f)
        if f != path and "observations" in arrays and not len(arrays["observations"]):
            # OGBench's script writes one with fewer than 10 episodes: nothing to add.
            log.warning("%s holds no steps: not imported", f)
            files.remove(f)
            continue
        _check_arrays(arrays, str(f), spec)
        _fits_observations(arrays, str(f), spec)
        loaded.append((arrays, episode_ends(arrays["terminals"], str(f))))
    return dataset_type, files, loaded


def _episodes(
    loaded: list[tuple[dict[str, np.ndarray], np.ndarray]], spec: ManipSpaceSpec, clock: Clock
) -> Iterator[Episode]:
    """The files' episodes in order, on one clock, with restored states."""
    index = 0
    for arrays, ends in loaded:
        start = 0
        for end in ends.tolist():
            n = end - start
            rows = {
                k: np.asarray(v[start:end], dtype=np.float64).reshape(n, -1)
                for k, v in arrays.items()
                if k in (*REQUIRED, "button_states")
            }
            time = clock.next(n)
            obs = rows["observations"]
            buttons = rows["button_states"] if spec.n_buttons else None
            physics = restore_physics(spec, time, obs, rows["qpos"], rows["qvel"], buttons)
            terminals = rows["terminals"].reshape(n) != 0
            yield Episode(index, obs, rows["actions"], time, physics=physics, terminals=terminals)
            index += 1
            start = end


def manipulation_episodes(
    loaded: list[tuple[dict[str, np.ndarray], np.ndarray]],
    spec: ManipSpaceSpec,
    name: str,
    progress: bool,
) -> tuple[Iterator[Episode], int]:
    """The loaded files' episodes (with progress) and their total steps."""
    frames = sum(len(arrays["observations"]) for arrays, _ in loaded)
    stream = _episodes(loaded, spec, Clock(spec.dt))
    return with_progress(stream, frames, name, progress), frames


def write_manipulation_npz(path: str | Path, episodes: Iterable[Episode], env_id: str) -> int:
    """Write episodes (with exact states, e.g. `open_manipulation`'s) in OGBench's file layout,
    atomically: float32 `observations`, `actions`, `qpos`, `qvel`; bool `terminals` on each
    episode's last step; the int64 `button_states` of the scene and the puzzles. Returns the
    number of steps."""
    spec = manipspace_spec(env_id)
    nq, nv = spec.model.nq, spec.model.nv
    buttons = 1 + nq + 2 * nv + READINGS  # time, qpos, qvel, warm start, readings
    columns: dict[str, list[np.ndarray]] = {k: [] for k in REQUIRED}
    columns["button_states"] = []
    for ep in episodes:
        terminals = np.zeros(len(ep), dtype=bool)
        terminals[-1] = True
        columns["observations"].append(ep.observations.astype(np.float32))
        columns["actions"].append(ep.actions.astype(np.float32))
        columns["terminals"].append(terminals)
        columns["qpos"].append(ep.physics[:, 1 : 1 + nq].astype(np.float32))
        columns["qvel"].append(ep.physics[:, 1 + nq : 1 + nq + nv].astype(np.float32))
        if spec.n_buttons:
            columns["button_states"].append(ep.physics[:, buttons : buttons + spec.n_buttons]
                                            .astype(np.int64))  # fmt: skip
    arrays = {k: np.concatenate(v) for k, v in columns.items() if v}
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    return len(arrays["actions"])
