"""MuJoCo state shared by every environment: the physics state a dataset records per step, its
restore from a fresh reset, and gymnasium-robotics' registration (mazes and the kitchen)."""

from __future__ import annotations

import contextlib
import functools
import io
import warnings

import gymnasium as gym
import mujoco
import numpy as np

# MuJoCo state spec recorded per step: time, qpos, qvel (+ act, mocap, ...: empty here).
PHYSICS_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS


@functools.cache
def register_envs() -> None:
    """Import gymnasium-robotics and register its envs, once, without its import-time noise.

    gymnasium-robotics 1.4.2 prints an Adroit reward notice to stderr on import (via
    farama-notifications) that does not concern PointMaze; it is swallowed here.
    """
    with warnings.catch_warnings(), contextlib.redirect_stderr(io.StringIO()):
        warnings.simplefilter("ignore")
        import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)


def restore_physics(
    model: mujoco.MjModel, data: mujoco.MjData, state: np.ndarray, mask: int = PHYSICS_SPEC
) -> None:
    """Put `data` in `state` (the `mask` components, `mjSTATE_FULLPHYSICS` by default) from a
    fresh reset: everything the state leaves out (the solver's warm start, for the mazes) is as
    after `mj_resetData`; then a forward pass for the derived quantities."""
    mujoco.mj_resetData(model, data)
    mujoco.mj_setState(model, data, state, mask)
    mujoco.mj_forward(model, data)
