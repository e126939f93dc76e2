"""B MuJoCo simulators of one environment stepped together: the simulator of deploy and validate.

Every slot has its own `MjData`; each may run its own `MjModel` (a model variant, e.g. another
mass), otherwise all share the spec's nominal model. The environment-specific parts (observation,
one control step, what a physics state is and how it is restored) come from the `EnvSpec`, so for
PointMaze a step is `step_point_mass`, bit for bit gymnasium's `env.step` (tests/test_envs.py,
tests/test_deploy.py), and for OGBench's manipulation envs `ManipSpaceSpec.control_step`, bit for
bit theirs. A spec's step may write into the model it is given (the scene writes the drawer and
window damping its button states imply): it writes them before every step, from the slot's own
state, so slots sharing one model stay independent (tests/test_manip_pipeline.py).

Stepping is a Python loop over slots: one point-mass step costs microseconds (about 60k steps/s on
one loaded core), far below a planner call, so threads or batching in C would not change the deploy
or validate wall time.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from pipeline.envs.disturbance import Pushes, draw_force, push_rng, pushed_step
from pipeline.envs.spec import EnvSpec

# MuJoCo warnings after which it has reset the simulation: the slot's state is no longer real.
_FATAL_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQACC,
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    mujoco.mjtWarning.mjWARN_BADCTRL,
)

Rows = Sequence[int] | np.ndarray | None


class BatchSim:
    """B simulators of `spec`'s environment.

    Args:
        spec: The environment.
        n: Number of slots B.
        models: Per-slot model variants `[B]` (sharing the nominal model's state layout); the
            spec's nominal model in every slot if None. A variant made by editing a copy's
            fields (e.g. `body_mass`) needs `mujoco.mj_setConst` afterwards: MuJoCo caches
            derived constants such as a constant mass matrix.
        pushes: Random external pushes in every slot (`pipeline.envs.disturbance`), each slot
            drawing from the generator `seed_slots` gave it; None: none. The spec's own random
            events (OGBench's teleports: `OGBenchMazeSpec.teleport`) draw from it too.
    """

    def __init__(
        self,
        spec: EnvSpec,
        n: int,
        models: Sequence[mujoco.MjModel] | None = None,
        pushes: Pushes | None = None,
    ):
        self.spec = spec
        self.pushes = pushes if pushes is not None and pushes.active else None
        self._push_rngs: list[np.random.Generator | None] = [None] * n
        self.models = [spec.model] * n if models is None else list(models)
        if len(self.models) != n:
            raise ValueError(f"need one model per slot: {len(self.models)} != {n}")
        layout = (spec.model.nq, spec.model.nv, spec.model.nu)
        if any((m.nq, m.nv, m.nu) != layout for m in self.models):
            raise ValueError("every slot's model must have the nominal model's nq, nv and nu")
        self.datas = [mujoco.MjData(m) for m in self.models]
        self.physics_dim = spec.physics_dim
        # OGBench's teleport: a step that ends at an inbound teleport moves the agent before the
        # next step (`OGBenchMazeSpec.teleport`); a reset there does not.
        self._teleports = getattr(spec, "teleports", None)
        self._teleport_pending = np.zeros(n, dtype=bool)

    def __len__(self) -> int:
        return len(self.datas)

    def _rows(self, rows: Rows) -> Sequence[int]:
        return range(len(self)) if rows is None else [int(i) for i in rows]

    def reset(self, observations: np.ndarray, rows: Rows = None) -> None:
        """Start slots `rows [A]` (all if None) at `observations [A, state_dim]`, as a fresh
        gymnasium reset would (time 0, zeroed solver warm start)."""
        for i, obs in zip(self._rows(rows), np.asarray(observations), strict=True):
            model, data = self.models[i], self.datas[i]
            mujoco.mj_resetData(model, data)
            self.spec.set_observation(data, obs)
            mujoco.mj_forward(model, data)
            self._teleport_pending[i] = False

    def seed_slots(self, seeds: Sequence[int], rows: Rows = None) -> None:
        """Give slots `rows` the generators of episodes with these seeds, for their random
        events (pushes, teleports): a slot's then depend on its episode only, not on the batch."""
        for i, seed in zip(self._rows(rows), seeds, strict=True):
            self._push_rngs[i] = push_rng(seed)

    def set_state(self, physics: np.ndarray, rows: Rows = None) -> None:
        """Put slots `rows [A]` in exact physics states `[A, physics_dim]` (the spec's
        `state_spec`, as recorded with each dataset step), with `EnvSpec.set_physics_state`.

        The mazes' state (`mjSTATE_FULLPHYSICS`) leaves out the solver's warm start; it is zeroed
        (as after a reset), so stepping on reproduces the recording exactly away from walls and
        to round-off at them (`pipeline.envs.maze.env.set_physics_state`). The manipulation envs'
        state holds everything (`pipeline.envs.manipspace.env`): stepping on is bit for bit.
        """
        physics = np.asarray(physics, dtype=np.float64)
        ids = self._rows(rows)
        if physics.shape != (len(ids), self.physics_dim):
            raise ValueError(f"physics states {physics.shape} != ({len(ids)}, {self.physics_dim})")
        for i, state in zip(ids, physics, strict=True):
            self.spec.set_physics_state(self.datas[i], state, self.models[i])
            self._teleport_pending[i] = self._at_teleport(self.datas[i])  # a state a step led to

    def get_state(self, rows: Rows = None) -> np.ndarray:
        """Physics states `[A, physics_dim]` of slots `rows` (all if None)."""
        ids = self._rows(rows)
        out = np.empty((len(ids), self.physics_dim))
        for j, i in enumerate(ids):
            mujoco.mj_getState(self.models[i], self.datas[i], out[j], self.spec.state_spec)
        return out

    def observe(self, rows: Rows = None) -> np.ndarray:
        """Observations `[A, state_dim]` (float64) of slots `rows` (all if None)."""
        ids = self._rows(rows)
        if not ids:
            return np.empty((0, self.spec.state_dim))
        return np.stack([self.spec.observe(self.datas[i]) for i in ids])

    def step(self, actions: np.ndarray, rows: Rows = None) -> dict[int, str]:
        """Apply `actions [A, action_dim]` to slots `rows` (all if None) for one control step.

        A slot fails, and is left as it is, on a non-finite action or a MuJoCo instability (after
        which MuJoCo silently resets it, which must not count as the agent's motion); the others
        step on.

        Returns:
            `{slot: what failed}` for the slots that failed (empty when all stepped).
        """
        actions = np.asarray(actions, dtype=np.float64)
        finite = np.isfinite(actions).all(axis=-1)
        failed: dict[int, str] = {}
        for i, action, ok in zip(self._rows(rows), actions, finite, strict=True):
            if not ok:
                failed[i] = f"non-finite action {action.tolist()}"
                continue
            data = self.datas[i]
            force = None
            if self.pushes is not None:
                force = draw_force(self.pushes, self._slot_rng(i), self.spec.dt)
            if self._teleport_pending[i]:  # the last step's teleport, deferred
                self.spec.teleport(self.models[i], data, self._slot_rng(i))
            try:
                pushed_step(self.spec.control_step, self.models[i], data, action, force)
                self._teleport_pending[i] = self._at_teleport(data)
            except Exception as exc:  # one slot's failure must not stop the others
                failed[i] = f"{type(exc).__name__}: {exc}".splitlines()[0]
                continue
            for w in _FATAL_WARNINGS:
                if data.warning[w].number:
                    failed[i] = f"MuJoCo instability ({w.name}) at t = {data.time:.2f} s"
                    break
        return failed

    def _at_teleport(self, data: mujoco.MjData) -> bool:
        return self._teleports is not None and bool(self._teleports.inside(data.qpos[:2]))

    def _slot_rng(self, i: int) -> np.random.Generator:
        rng = self._push_rngs[i]
        if rng is None:
            raise RuntimeError(
                f"slot {i} draws random events (pushes, teleports) but has no generator: call "
                "seed_slots first"
            )
        return rng
