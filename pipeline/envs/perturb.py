"""Dynamics perturbations of an environment's MuJoCo model (robustness experiment, paper fig. 5).

The paper deploys its agents in an antmaze whose geoms' density it scales (×0.2 … ×5 of the
default) with every model left as trained. `scale_mass` does the same to any `EnvSpec`'s model:
every body but the world gets its mass and rotational inertia scaled by one factor, which is what a
uniform density change of all its geoms gives. For PointMaze that is the point's mass: the same
force accelerates it `1 / factor` as fast.
"""

from __future__ import annotations

import copy

import mujoco

from pipeline.errors import UserError


def scale_mass(model: mujoco.MjModel, factor: float) -> mujoco.MjModel:
    """A copy of `model` with the mass and inertia of every body (not the world) times `factor`.

    Raises:
        UserError: `factor` is not positive.
    """
    if not factor > 0:
        raise UserError(f"deploy.mass_scale: {factor} is not a positive factor; use e.g. 0.5 or 2")
    scaled = copy.copy(model)
    if factor != 1.0:
        scaled.body_mass[1:] *= factor
        scaled.body_inertia[1:] *= factor
        mujoco.mj_setConst(scaled, mujoco.MjData(scaled))  # cached constants: mass matrix, ...
    return scaled
