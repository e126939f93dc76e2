"""Uncontrolled stochasticity: random external pushes on the agent (paper §2.1, appendix B).

The paper's case for EM over naive VI is that a skill learned with VI also "explains" state
changes the agent did not cause, so the world model becomes overconfident. PointMaze has no such
changes (all its randomness is in the recorded actions); `Pushes` adds them. At each control step,
with probability `probability`, the agent's root body gets an impulse of `impulse` N·s in a
uniformly random direction of the maze plane: a force `impulse / dt` through MuJoCo's
`xfrc_applied` for that one step. For the point (4.19 kg) 4.2 N·s changes its velocity by 1 m/s.

The same process runs where the agent acts in the simulator: ingest (recorded in the dataset's
metadata, `generator["disturbance"]`), validate and deploy (read from there). Each episode (or
simulator slot) draws from its own generator, seeded from the episode's seed, so pushes do not
depend on which episodes share a batch. Nothing is drawn when the pushes are off, so data made
without them is bit for bit what it was before they existed.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import mujoco
import numpy as np

from pipeline.errors import UserError

AGENT_BODY = 1  # the first body after the world: PointMaze's particle, the ant's torso
_STREAM = 0x9E3779B9  # mixed into episode seeds: the push stream is not the agent's


@dataclass(frozen=True)
class Pushes:
    """Random pushes: `probability` per control step, `impulse` N·s each (0, 0: none)."""

    probability: float = 0.0
    impulse: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.probability <= 1.0:
            raise UserError(f"disturbance.probability: {self.probability} is not in [0, 1]")
        if not self.impulse >= 0.0:
            raise UserError(f"disturbance.impulse: {self.impulse} N s is negative")

    @property
    def active(self) -> bool:
        return self.probability > 0.0 and self.impulse > 0.0

    def to_dict(self) -> dict[str, float]:
        return asdict(self)

    @classmethod
    def of_dataset(cls, generator: dict[str, Any] | None) -> Pushes:
        """The pushes a dataset was recorded under (`DatasetInfo.generator`); none if it says
        nothing (every dataset made before they existed, and imported ones)."""
        recorded = (generator or {}).get("disturbance") or {}
        return cls(**recorded)


def push_rng(seed: int) -> np.random.Generator:
    """The push generator of an episode (or data stream) with seed `seed`."""
    return np.random.default_rng([int(seed), _STREAM])


def draw_force(pushes: Pushes, rng: np.random.Generator, dt: float) -> tuple[float, float] | None:
    """This step's push as a force `(fx, fy)` in N, or None (no push, nothing drawn if off)."""
    if not pushes.active or rng.random() >= pushes.probability:
        return None
    angle = rng.uniform(0.0, 2.0 * math.pi)
    force = pushes.impulse / dt
    return force * math.cos(angle), force * math.sin(angle)


def pushed_step(step, model: mujoco.MjModel, data: mujoco.MjData, action, force) -> None:
    """`step(model, data, action)` (one control step) with `force` on the agent's root body."""
    if force is None:
        step(model, data, action)
        return
    data.xfrc_applied[AGENT_BODY, 0] = force[0]
    data.xfrc_applied[AGENT_BODY, 1] = force[1]
    try:
        step(model, data, action)
    finally:
        data.xfrc_applied[AGENT_BODY, :] = 0.0
