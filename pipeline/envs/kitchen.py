"""gymnasium-robotics' Franka kitchen (`FrankaKitchen-v1`, the refactored D4RL kitchen) behind the
`EnvSpec` interface, with D4RL's task sets, the env's success rule and a Minari writer.

What the env really is (read from `gymnasium_robotics/envs/franka_kitchen/{kitchen_env,
franka_env}.py` and gymnasium's `MujocoEnv` of the installed gymnasium-robotics 1.4.2, and checked
step for step against `env.step` in tests/test_kitchen.py):

- **Model**: a 9-dof Franka Panda (7 hinge joints, 2 finger slides; position actuators, ctrl
  clamped to their ctrl ranges by MuJoCo) in a kitchen of 14 object joints (4 burner knobs and
  4 burners, light switch and light, slide cabinet, two hinge cabinets, microwave door) and a free
  kettle: nq = 30, nv = 29. Physics steps of 0.002 s (Newton solver), `frame_skip` 40 per control
  step: `dt` = 0.08 s (12.5 Hz). An episode lasts at most 280 steps (the registered limit).
- **Action** `[9]` in [-1, 1]: normalized joint *velocities*, turned into position targets
  (`FrankaRobot.step`): clip to [-1, 1], times 2 (`act_rng`; so at most 2 rad/s or m/s, well
  inside the config's velocity bounds of +-10, which are applied all the same), `target = q_obs
  + v * dt`, clipped to the config's joint position bounds (`franka_config.xml`), written to
  `ctrl`; then 40 `mj_step`s and `mj_rnePostConstraint`. **`q_obs` is the robot qpos of the last
  observation, not of the state** (the env's own comment: "this breaks MDP assumptions", kept from
  D4RL): with observation noise the next state depends on the noise drawn at the last step.
- **Observation** (`observation` of the dict, 59 float64): robot qpos (9), robot qvel (9), object
  qpos (21: full qpos 9..29), object qvel (20: full qvel 9..28); i.e. exactly qpos and qvel,
  robot part first. By default it is noisy: uniform noise in [-1, 1] times `robot_noise_ratio`
  (default 0.01) times the config's per-joint amplitudes (0.1 for the robot) on the robot part,
  and times `object_noise_ratio` (default 0.0005) on the objects' part (whose position noise
  reads the amplitudes one joint off: `robot_pos_noise_amp[8:]`). The dict's `achieved_goal` /
  `desired_goal` hold, per subtask of `tasks_to_complete`, the element's true (noise-free) qpos
  and its goal (`OBS_ELEMENT_INDICES` index the *full* qpos: observation dim = index + 9).
- **Reset**: deterministic up to the noise: `mj_resetData`, the env's fixed `init_qpos`, zero
  velocity (so zero warm start, time 0). The seed only draws the observation noise.
- **Success** (`KitchenEnv.compute_reward`): a subtask is complete when
  `norm(qpos[OBS_ELEMENT_INDICES[t]] - OBS_ELEMENT_GOALS[t]) < BONUS_THRESH` (0.3; the kettle's
  norm is over its position *and* quaternion). The reward is the number of remaining subtasks
  complete after a step; completed ones are removed (`remove_task_when_completed`) and the
  episode ends when all are done. D4RL's score is the number of subtasks completed during an
  episode over 4 (`completion_count`).

**The spec is noise-free.** It simulates `make_kitchen_env(robot_noise_ratio=0,
object_noise_ratio=0)`: then the observation is exactly `[qpos, qvel]` and the last observed robot
qpos is `qpos[:9]`, so the control law is a function of the state and the physics state needs no
user data. A state (`physics_dim` = 89) is `mjSTATE_FULLPHYSICS | mjSTATE_WARMSTART`: time, qpos,
qvel and the Newton solver's warm start (`qacc_warmstart`), without which a restored state's next
step differs in contacts (measured: up to 2e-6 in the observation after one step); with it
`set_physics_state` + `control_step` is `env.step` bit for bit. Data recorded with noise (the
env's default) are not replayed exactly: there the env's targets start from the noisy observed
qpos (+-0.001 rad), and the observations are not the states. An observation is a full state, so
`set_observation` writes it (warm start zero, as after a reset).

**Tasks.** A spec is made for the env's `tasks_to_complete` (default: all seven subtasks); its
`subtasks` are these in `OBS_ELEMENT_INDICES` order and its `goal_dims` their observation dims.
D4RL's task sets (`KITCHEN_TASK_SETS`): `kitchen-complete` and `kitchen-partial` (microwave,
kettle, light switch, slide cabinet), `kitchen-mixed` (microwave, kettle, bottom burner, light
switch), and `kitchen-all` (the env's default, all seven): `KitchenSpec.for_task_set`.

`make_kitchen_env` applies a compatibility shim first (`patch_mujoco_utils`): without it
`gymnasium.make("FrankaKitchen-v1")` fails with MuJoCo 4 (see there).
"""

from __future__ import annotations

import contextlib
import functools
import importlib.metadata
import json
import os
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import gymnasium
import mujoco
import numpy as np

from pipeline.envs.physics import PHYSICS_SPEC, register_envs
from pipeline.errors import UserError

KITCHEN_ENV_ID = "FrankaKitchen-v1"
KITCHEN_ENVS: tuple[str, ...] = (KITCHEN_ENV_ID,)
EPISODE_STEPS = 280  # the registered `max_episode_steps` (also D4RL's)

# What a state is (module docstring): full physics and the solver's warm start.
KITCHEN_STATE_SPEC = PHYSICS_SPEC | mujoco.mjtState.mjSTATE_WARMSTART

# gymnasium-robotics' constants (`kitchen_env.py`), copied so that this module's import does not
# import gymnasium-robotics; `test_constants_are_the_envs` holds them equal to the env's.
OBS_ELEMENT_INDICES: dict[str, tuple[int, ...]] = {  # into the full qpos
    "bottom burner": (11, 12),
    "top burner": (15, 16),
    "light switch": (17, 18),
    "slide cabinet": (19,),
    "hinge cabinet": (20, 21),
    "microwave": (22,),
    "kettle": (23, 24, 25, 26, 27, 28, 29),
}
OBS_ELEMENT_GOALS: dict[str, tuple[float, ...]] = {
    "bottom burner": (-0.88, -0.01),
    "top burner": (-0.92, -0.01),
    "light switch": (-0.69, -0.05),
    "slide cabinet": (0.37,),
    "hinge cabinet": (0.0, 1.45),
    "microwave": (-0.75,),
    "kettle": (-0.23, 0.75, 1.62, 0.99, 0.0, 0.0, -0.06),
}
BONUS_THRESH = 0.3  # a subtask is complete when its element is closer than this to its goal
SUBTASKS: tuple[str, ...] = tuple(OBS_ELEMENT_INDICES)  # canonical order: by qpos index

# Observation layout (module docstring): robot qpos, robot qvel, object qpos, object qvel.
ROBOT_DOF = 9
STATE_DIM = 59
# Observation dim of full-qpos index i >= ROBOT_DOF (an object joint): i + ROBOT_DOF, the robot's
# 9 velocities coming before the objects' positions.
OBJECT_OBS_OFFSET = ROBOT_DOF

# The kettle's position (x, y, z of its free joint, m) in the observation: the one 3-D position an
# observation holds (validate's recording draws it).
KETTLE_POSITION_DIMS: tuple[int, ...] = tuple(
    i + OBJECT_OBS_OFFSET for i in OBS_ELEMENT_INDICES["kettle"][:3]
)

# D4RL's kitchen task sets (the paper's kitchen-partial / -complete / -mixed), plus the env's
# default set of all seven subtasks.
KITCHEN_TASK_SETS: dict[str, tuple[str, ...]] = {
    "kitchen-partial": ("microwave", "kettle", "light switch", "slide cabinet"),
    "kitchen-complete": ("microwave", "kettle", "light switch", "slide cabinet"),
    "kitchen-mixed": ("microwave", "kettle", "bottom burner", "light switch"),
    "kitchen-all": SUBTASKS,
}
CUSTOM_TASK = "kitchen-custom"  # the task of a spec whose subtasks are no named set

# --- compatibility shim ------------------------------------------------------------------------

_HINGE_OR_SLIDE = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
_FREE, _BALL = int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL)


def _joint(model: mujoco.MjModel, name: str) -> tuple[int, int]:
    """`(joint id, joint type as int)` of joint `name`; an AssertionError if absent (upstream)."""
    joint_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
    assert joint_id != -1, f"Joint with name '{name}' is not part of the model!"
    joint_type = int(model.jnt_type[joint_id])
    assert joint_type in (_FREE, _BALL, *_HINGE_OR_SLIDE), f"unknown joint type {joint_type}"
    return joint_id, joint_type


def get_joint_qpos(model: mujoco.MjModel, data: mujoco.MjData, name: str) -> np.ndarray:
    """gymnasium-robotics' `mujoco_utils.get_joint_qpos` comparing joint types as ints: a copy
    of the joint's qpos (7 numbers for a free joint, 4 for a ball, 1 for a hinge or slide)."""
    joint_id, joint_type = _joint(model, name)
    size = 7 if joint_type == _FREE else 4 if joint_type == _BALL else 1
    start = int(model.jnt_qposadr[joint_id])
    return data.qpos[start : start + size].copy()


def get_joint_qvel(model: mujoco.MjModel, data: mujoco.MjData, name: str) -> np.ndarray:
    """gymnasium-robotics' `mujoco_utils.get_joint_qvel` comparing joint types as ints: a copy
    of the joint's qvel (6 for a free joint, 1 for a hinge or slide; 4 for a ball joint, as
    upstream returns, though a ball has 3 dofs: the shim changes nothing but the comparison)."""
    joint_id, joint_type = _joint(model, name)
    size = 6 if joint_type == _FREE else 4 if joint_type == _BALL else 1
    start = int(model.jnt_dofadr[joint_id])
    return data.qvel[start : start + size].copy()


def patch_mujoco_utils() -> bool:
    """Replace `get_joint_qpos` and `get_joint_qvel` of `gymnasium_robotics.utils.mujoco_utils`
    with this module's versions, once (idempotent). Returns whether this call patched them.

    Why: upstream's functions end in `assert joint_type in (mjtJoint.mjJNT_HINGE,
    mjtJoint.mjJNT_SLIDE)` with `joint_type = model.jnt_type[id]`, a numpy int32. Tuple
    containment compares `enum == np.int32`, and the enums of MuJoCo 4.0's bindings (pybind11
    native enums) answer False there (`np.int32 == enum` is True), so every hinge or slide joint
    fails the assert: `FrankaKitchen-v1` cannot even be constructed (its `__init__` reads the
    robot's joints through `robot_get_obs`). The replacements compare `int(joint_type)` and are
    otherwise the same.

    Where: only the module attributes need replacing. `robot_get_obs` (imported by name into
    `franka_env`) looks both functions up in `mujoco_utils`' globals at call time; the other
    users (the shadow hand, Fetch) call them as `mujoco_utils.<name>`; no module of
    gymnasium-robotics 1.4.2 imports them by name. (`set_joint_qpos` / `set_joint_qvel` have the
    same assert; the kitchen does not use them, so they are left alone.)

    When to remove: once gymnasium-robotics compares joint types in a way MuJoCo's enums answer
    (a release after 1.4.2; none is available here), or once MuJoCo's enums compare equal to
    numpy ints again (`mujoco.mjtJoint.mjJNT_HINGE == np.int32(3)` is True);
    `test_shim_is_needed` in tests/test_kitchen.py skips with a notice when it no longer is.
    """
    from gymnasium_robotics.utils import mujoco_utils

    if mujoco_utils.get_joint_qpos is get_joint_qpos and mujoco_utils.get_joint_qvel is (
        get_joint_qvel
    ):
        return False
    mujoco_utils.get_joint_qpos = get_joint_qpos
    mujoco_utils.get_joint_qvel = get_joint_qvel
    return True


# --- the env -----------------------------------------------------------------------------------


def is_kitchen(env_id: str) -> bool:
    """Whether `env_id` is the kitchen this module simulates."""
    return env_id in KITCHEN_ENVS


def check_subtasks(subtasks: Sequence[str], where: str = "tasks_to_complete") -> tuple[str, ...]:
    """`subtasks` in canonical order (`SUBTASKS`), duplicates dropped.

    Raises:
        UserError: an unknown subtask, or none.
    """
    if isinstance(subtasks, str):
        subtasks = [subtasks]
    unknown = [t for t in subtasks if t not in OBS_ELEMENT_INDICES]
    if unknown:
        raise UserError(
            f"{where}: unknown kitchen subtask(s) {unknown}; use some of: {', '.join(SUBTASKS)}"
        )
    if not subtasks:
        raise UserError(f"{where} is empty; name at least one of: {', '.join(SUBTASKS)}")
    return tuple(t for t in SUBTASKS if t in set(subtasks))


def make_kitchen_env(**kwargs: Any) -> gymnasium.Env:
    """`gymnasium.make("FrankaKitchen-v1", **kwargs)`, after registering gymnasium-robotics and
    applying `patch_mujoco_utils` (without which it fails under MuJoCo 4).

    Useful kwargs: `tasks_to_complete` (subtask names), `robot_noise_ratio=0.0,
    object_noise_ratio=0.0` (the noise-free env `KitchenSpec` simulates), `max_episode_steps`,
    `terminate_on_tasks_completed`, `remove_task_when_completed`.

    Raises:
        UserError: an unknown subtask in `tasks_to_complete`.
    """
    if "tasks_to_complete" in kwargs:
        kwargs["tasks_to_complete"] = list(check_subtasks(kwargs["tasks_to_complete"]))
    register_envs()
    patch_mujoco_utils()
    return gymnasium.make(KITCHEN_ENV_ID, **kwargs)


def noise_free_kwargs(env_kwargs: dict[str, Any] | None) -> dict[str, Any]:
    """`env_kwargs` with both observation noise ratios 0 (the env `KitchenSpec` simulates)."""
    return {**(env_kwargs or {}), "robot_noise_ratio": 0.0, "object_noise_ratio": 0.0}


@functools.cache
def _reference_env(key: str) -> gymnasium.Env:
    """One noise-free env per kwargs (`key`: their JSON) for the spec's model and constants,
    and for `KitchenSpec.task_start`'s resets (which write only its `MjData`). Never step it."""
    env = make_kitchen_env(**json.loads(key))
    env.reset(seed=0)
    return env


def reference_env(env_kwargs: dict[str, Any] | None = None) -> gymnasium.Env:
    """The shared noise-free env of `env_kwargs` (see `_reference_env`)."""
    return _reference_env(json.dumps(noise_free_kwargs(env_kwargs), sort_keys=True))


# --- tasks -------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class KitchenGoal:
    """Goal joint values per subtask, `{subtask: [k]}` (the env's: `KitchenGoal.of`), in
    canonical order (`SUBTASKS`)."""

    targets: dict[str, np.ndarray]

    @classmethod
    def of(cls, subtasks: Sequence[str]) -> KitchenGoal:
        """The env's goal (`OBS_ELEMENT_GOALS`) of `subtasks`."""
        return cls({t: np.array(OBS_ELEMENT_GOALS[t]) for t in check_subtasks(subtasks)})

    @property
    def subtasks(self) -> tuple[str, ...]:
        """The goal's subtasks, in canonical order."""
        return tuple(t for t in SUBTASKS if t in self.targets)


@dataclass(frozen=True, eq=False)
class KitchenTask:
    """A named task set of a spec (`KitchenSpec.tasks`): its 1-based id there, its name (a
    `KITCHEN_TASK_SETS` key or `CUSTOM_TASK`) and its goal. It starts from the env's reset."""

    task_id: int
    name: str
    goal: KitchenGoal


@dataclass(frozen=True, eq=False)
class KitchenTaskStart:
    """An evaluation episode's start as the noise-free env's reset leaves it.

    Attributes:
        task: The task.
        physics: The exact start state `[physics_dim]` (time 0, zero velocity and warm start).
        observation: The env's reset observation `[state_dim]`.
        goal: The goal the episode is judged against.
        goal_observation: The start observation with the goal at `goal_dims` (the env has no goal
            observation; this is the usual construction, for goal-conditioned models).
    """

    task: KitchenTask
    physics: np.ndarray
    observation: np.ndarray
    goal: KitchenGoal
    goal_observation: np.ndarray


# --- the spec ----------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class KitchenSpec:
    """The noise-free `FrankaKitchen-v1` (`EnvSpec`; see the module docstring). Build it with
    `KitchenSpec.create(**env_kwargs)`, `KitchenSpec.for_task_set(name)` or `kitchen_spec`.

    Attributes (besides `EnvSpec`'s):
        subtasks: The env's `tasks_to_complete`, in canonical order; `goal_dims` are their
            elements' observation dims, in this order.
        frame_skip: MuJoCo steps per control step (40).
        env_kwargs: The kwargs the spec was made from (subtasks in canonical order; noise
            ratios as given: the spec ignores them).
        layout: `{"kind": "kitchen", "subtasks": [...]}`: no maze.
    """

    env_id: str
    model: mujoco.MjModel
    dt: float
    max_episode_steps: int
    goal_dims: tuple[int, ...]
    subtasks: tuple[str, ...]
    frame_skip: int
    env_kwargs: dict[str, Any]
    layout: dict[str, Any]
    _control: dict[str, np.ndarray]
    state_dim: int = STATE_DIM
    action_dim: int = ROBOT_DOF
    state_spec: ClassVar[int] = KITCHEN_STATE_SPEC

    @classmethod
    def create(cls, **env_kwargs: Any) -> KitchenSpec:
        """The spec of `make_kitchen_env(**env_kwargs)` made noise-free (`tasks_to_complete`
        decides `subtasks` and `goal_dims`; `max_episode_steps` the episode limit)."""
        subtasks = check_subtasks(env_kwargs.get("tasks_to_complete", SUBTASKS))
        kwargs = dict(env_kwargs)
        if "tasks_to_complete" in kwargs:
            kwargs["tasks_to_complete"] = list(subtasks)
        env = reference_env(kwargs)
        u = env.unwrapped
        robot = u.robot_env
        model = u.model
        names = [n for n in robot.model_names.joint_names if n.startswith("robot")]
        qadr = [int(model.joint(n).qposadr[0]) for n in names]
        dadr = [int(model.joint(n).dofadr[0]) for n in names]
        if qadr != list(range(ROBOT_DOF)) or dadr != list(range(ROBOT_DOF)):
            raise RuntimeError(f"{KITCHEN_ENV_ID}: robot joints at qpos {qadr}, dofs {dadr}")
        if (model.nq, model.nv, model.nu, model.na) != (30, 29, ROBOT_DOF, 0):
            raise RuntimeError(f"{KITCHEN_ENV_ID}: unexpected model sizes")
        if mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_PLUGIN):
            raise RuntimeError(f"{KITCHEN_ENV_ID}: unexpected plugin state")
        control = {
            "act_mid": np.array(robot.act_mid, dtype=np.float64),
            "act_rng": np.array(robot.act_rng, dtype=np.float64),
            "vel_low": robot.robot_vel_bound[:ROBOT_DOF, 0].copy(),
            "vel_high": robot.robot_vel_bound[:ROBOT_DOF, 1].copy(),
            "pos_low": robot.robot_pos_bound[:ROBOT_DOF, 0].copy(),
            "pos_high": robot.robot_pos_bound[:ROBOT_DOF, 1].copy(),
        }
        goal_dims = [i + OBJECT_OBS_OFFSET for t in subtasks for i in OBS_ELEMENT_INDICES[t]]
        return cls(
            env_id=KITCHEN_ENV_ID,
            model=model,
            dt=float(robot.dt),
            max_episode_steps=int(env.spec.max_episode_steps or EPISODE_STEPS),
            goal_dims=tuple(goal_dims),
            subtasks=subtasks,
            frame_skip=int(robot.frame_skip),
            env_kwargs=kwargs,
            layout={"kind": "kitchen", "subtasks": list(subtasks)},
            _control=control,
        )

    @classmethod
    def for_task_set(cls, name: str, **env_kwargs: Any) -> KitchenSpec:
        """The spec of a `KITCHEN_TASK_SETS` task set (e.g. `kitchen-mixed`).

        Raises:
            UserError: an unknown name.
        """
        return cls.create(tasks_to_complete=list(task_set(name)), **env_kwargs)

    # State ------------------------------------------------------------------------------------

    @property
    def physics_dim(self) -> int:
        """`[time, qpos (30), qvel (29), qacc_warmstart (29)]`: 89."""
        return int(mujoco.mj_stateSize(self.model, KITCHEN_STATE_SPEC))

    def physics_state(self, data: mujoco.MjData) -> np.ndarray:
        """The exact state `[physics_dim]` of `data` (of a kitchen model: the env's own too)."""
        out = np.empty(self.physics_dim)
        mujoco.mj_getState(self.model, data, out, KITCHEN_STATE_SPEC)
        return out

    def state_of_env(self, env: gymnasium.Env) -> np.ndarray:
        """The exact state `[physics_dim]` a (noise-free) kitchen env is in."""
        return self.physics_state(env.unwrapped.data)

    def set_physics_state(
        self, data: mujoco.MjData, state: np.ndarray, model: mujoco.MjModel | None = None
    ) -> None:
        """Put `data` (of `model`: this spec's model, by default, or a variant of it) exactly in
        `state [physics_dim]`: reset, restore, and a forward pass for the derived quantities
        (it leaves the restored warm start alone)."""
        model = self.model if model is None else model
        state = np.asarray(state, dtype=np.float64)
        if state.shape != (self.physics_dim,):
            raise ValueError(f"physics state {state.shape} != ({self.physics_dim},)")
        mujoco.mj_resetData(model, data)
        mujoco.mj_setState(model, data, state, KITCHEN_STATE_SPEC)
        mujoco.mj_forward(model, data)

    def cold(self, state: np.ndarray) -> np.ndarray:
        """`state [physics_dim]` with the solver's warm start zeroed, as after a reset (the
        kitchen's reset state already is: a no-op on `task_start`'s)."""
        out = np.array(state, dtype=np.float64)
        out[1 + self.model.nq + self.model.nv :] = 0.0
        return out

    # Observation ------------------------------------------------------------------------------

    def observe(self, data: mujoco.MjData) -> np.ndarray:
        """The noise-free observation `[59]`: robot qpos, robot qvel, object qpos, object qvel;
        bit for bit the env's `observation` in the same state."""
        qpos, qvel = data.qpos, data.qvel
        return np.concatenate(
            [qpos[:ROBOT_DOF], qvel[:ROBOT_DOF], qpos[ROBOT_DOF:], qvel[ROBOT_DOF:]]
        )

    def set_observation(self, data: mujoco.MjData, observation: np.ndarray) -> None:
        """qpos and qvel from a noise-free observation `[59]` (it is the whole of both), so that
        `observe` gives it back exactly."""
        obs = np.asarray(observation, dtype=np.float64)
        if obs.shape != (STATE_DIM,):
            raise ValueError(f"observation {obs.shape} != ({STATE_DIM},)")
        nq = self.model.nq
        data.qpos[:ROBOT_DOF] = obs[:ROBOT_DOF]
        data.qvel[:ROBOT_DOF] = obs[ROBOT_DOF : 2 * ROBOT_DOF]
        data.qpos[ROBOT_DOF:] = obs[2 * ROBOT_DOF : ROBOT_DOF + nq]
        data.qvel[ROBOT_DOF:] = obs[ROBOT_DOF + nq :]

    def start_observation(self, xy: np.ndarray) -> np.ndarray:
        """Refused: the kitchen has no start position in a plane (use `task_start`)."""
        raise UserError(f"{self.env_id} has no start position in a plane; use task_start")

    # Dynamics ---------------------------------------------------------------------------------

    def control_step(self, model: mujoco.MjModel, data: mujoco.MjData, action: np.ndarray) -> None:
        """One control step of `action [9]`, bit for bit the noise-free `env.step`: the joint
        velocities turned into position targets from the robot qpos (which noise-free is the
        last observed one), 40 MuJoCo steps, `mj_rnePostConstraint` (module docstring).

        `model` is this spec's model or a variant of it; its own time step sets the velocity's
        integration period, as in the env."""
        c = self._control
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        velocity = np.clip(c["act_mid"] + action * c["act_rng"], c["vel_low"], c["vel_high"])
        target = data.qpos[:ROBOT_DOF] + velocity * (model.opt.timestep * self.frame_skip)
        data.ctrl[:] = np.clip(target, c["pos_low"], c["pos_high"])
        mujoco.mj_step(model, data, nstep=self.frame_skip)
        mujoco.mj_rnePostConstraint(model, data)

    # Tasks and success ------------------------------------------------------------------------

    def tasks(self) -> list[KitchenTask]:
        """The task sets of this spec's subtasks: the `KITCHEN_TASK_SETS` with exactly these
        subtasks (kitchen-partial and kitchen-complete share theirs), else one `CUSTOM_TASK`;
        ids from 1."""
        names = [n for n, s in KITCHEN_TASK_SETS.items() if set(s) == set(self.subtasks)]
        goal = KitchenGoal.of(self.subtasks)
        return [KitchenTask(k, n, goal) for k, n in enumerate(names or [CUSTOM_TASK], start=1)]

    def task(self, task: str | int) -> KitchenTask:
        """One of `tasks()` by name or 1-based id.

        Raises:
            UserError: no such task for this spec's subtasks.
        """
        for t in self.tasks():
            if task in (t.name, t.task_id):
                return t
        have = ", ".join(f"{t.task_id}: {t.name}" for t in self.tasks())
        raise UserError(
            f"no kitchen task {task!r} for subtasks {list(self.subtasks)} (have {have}); make "
            "the spec with KitchenSpec.for_task_set(name) for another task set"
        )

    def task_start(self, task: str | int, seed: int) -> KitchenTaskStart:
        """Start `task` (a name or id of `tasks()`) as the noise-free env's `reset(seed=seed)`
        does, captured exactly. The seed changes nothing (it only draws observation noise)."""
        t = self.task(task)
        env = reference_env(self.env_kwargs)
        observation = np.array(env.reset(seed=int(seed))[0]["observation"])
        goal_observation = observation.copy()
        goal_observation[list(self.goal_dims)] = self.goal_vector(t.goal)
        return KitchenTaskStart(
            task=t,
            physics=self.state_of_env(env),
            observation=observation,
            goal=t.goal,
            goal_observation=goal_observation,
        )

    def completed(self, data: mujoco.MjData, goal: KitchenGoal) -> tuple[str, ...]:
        """The subtasks of `goal` complete in state `data` (the env's rule, `compute_reward`:
        `norm(qpos[OBS_ELEMENT_INDICES[t]] - target) < BONUS_THRESH`), in canonical order."""
        return tuple(
            t
            for t in goal.subtasks
            if np.linalg.norm(data.qpos[list(OBS_ELEMENT_INDICES[t])] - goal.targets[t])
            < BONUS_THRESH
        )

    def success(self, data: mujoco.MjData, goal: KitchenGoal) -> bool:
        """Whether every subtask of `goal` is complete in state `data` (`completed`)."""
        return len(self.completed(data, goal)) == len(goal.subtasks)

    def goal_vector(self, goal: KitchenGoal) -> np.ndarray:
        """`[len(goal_dims)]`: `goal`'s targets at `goal_dims` (observation units are the joint
        values themselves).

        Raises:
            UserError: `goal`'s subtasks are not this spec's.
        """
        if goal.subtasks != self.subtasks:
            raise UserError(
                f"kitchen goal of subtasks {list(goal.subtasks)} for a spec of "
                f"{list(self.subtasks)}; make the spec with tasks_to_complete="
                f"{list(goal.subtasks)}"
            )
        return np.concatenate(
            [np.asarray(goal.targets[t], dtype=np.float64) for t in goal.subtasks]
        )

    @property
    def goal_scale(self) -> tuple[float, ...]:
        """Per goal dim, `BONUS_THRESH` (0.3): in these units a subtask is complete when the norm
        of its dims' distance is below 1 (what planners divide by, `GoalCost`)."""
        return (BONUS_THRESH,) * len(self.goal_dims)

    def _groups(self) -> list[slice]:
        """Each subtask's slice of a goal vector."""
        out, start = [], 0
        for t in self.subtasks:
            out.append(slice(start, start + len(OBS_ELEMENT_INDICES[t])))
            start = out[-1].stop
        return out

    def subtasks_reached(self, observations: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """`[..., len(subtasks)]` bool: each subtask complete in observations `[..., 59]` (or
        predicted ones) against goal vectors `[..., G]` (`goal_vector`); noise-free observations
        hold the true joint values, so this is `completed` exactly."""
        diff = np.asarray(observations)[..., list(self.goal_dims)] - np.asarray(goals)
        return np.stack(
            [np.linalg.norm(diff[..., s], axis=-1) < BONUS_THRESH for s in self._groups()], axis=-1
        )

    def goal_reached(self, observations: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """`[...]` bool: every subtask complete (`subtasks_reached`), `success` from
        observations, for planners and batched evaluation."""
        return self.subtasks_reached(observations, goals).all(-1)

    def completion_count(self, observations: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """`[...]` int: subtasks complete at some step of episodes `[..., T, 59]` against their
        goals `[..., G]` (or `[..., T, G]`): the env's `episode_task_completions` count and the
        D4RL kitchen score's numerator (score = count / len(subtasks)). Pass the observations
        after each step (the env judges none at the reset)."""
        goals = np.asarray(goals)
        obs = np.asarray(observations)
        if goals.ndim == obs.ndim - 1:
            goals = goals[..., None, :]
        return self.subtasks_reached(obs, goals).any(-2).sum(-1)


def task_set(name: str) -> tuple[str, ...]:
    """The subtasks of a named task set (`KITCHEN_TASK_SETS`).

    Raises:
        UserError: an unknown name.
    """
    if name not in KITCHEN_TASK_SETS:
        raise UserError(
            f"unknown kitchen task set {name!r}; use one of: {', '.join(KITCHEN_TASK_SETS)}"
        )
    return KITCHEN_TASK_SETS[name]


@functools.cache
def _kitchen_spec(key: str) -> KitchenSpec:
    return KitchenSpec.create(**json.loads(key))


def kitchen_spec(env_kwargs: dict[str, Any] | None = None) -> KitchenSpec:
    """One shared `KitchenSpec` per `env_kwargs` (e.g. a dataset's `DatasetInfo.env_kwargs`)."""
    kwargs = dict(env_kwargs or {})
    if "tasks_to_complete" in kwargs:
        kwargs["tasks_to_complete"] = list(check_subtasks(kwargs["tasks_to_complete"]))
    return _kitchen_spec(json.dumps(kwargs, sort_keys=True))


# --- datasets ----------------------------------------------------------------------------------


def dataset_task_set(subtasks: Sequence[str], dataset_id: str = "") -> str:
    """The D4RL task set (`KITCHEN_TASK_SETS`) of a dataset's subtasks; kitchen-partial and
    kitchen-complete share theirs, so the dataset id decides between them (`D4RL/kitchen/
    partial-v2`), else the first.

    Raises:
        UserError: the subtasks are no named task set (one line).
    """
    subtasks = check_subtasks(subtasks, f"kitchen dataset {dataset_id or ''}".strip())
    names = [n for n, s in KITCHEN_TASK_SETS.items() if set(s) == set(subtasks)]
    if not names:
        known = "; ".join(f"{n}: {', '.join(s)}" for n, s in KITCHEN_TASK_SETS.items())
        raise UserError(
            f"kitchen dataset {dataset_id or '(no id)'}: subtasks {list(subtasks)} are no known "
            f"task set ({known}); import a dataset of one of these"
        )
    wanted = [n for n in names if n.removeprefix("kitchen-") in dataset_id.lower()]
    return (wanted or names)[0]


def observation_names(spec: KitchenSpec) -> tuple[list[str], list[str]]:
    """Names and units of the observation's 59 dims (the model's joints: robot qpos, robot qvel,
    object qpos, object qvel; the kettle's free joint as x, y, z, qw, qx, qy, qz and its velocity
    as vx, vy, vz, wx, wy, wz)."""
    model = spec.model
    qpos: list[tuple[int, str, str]] = []
    qvel: list[tuple[int, str, str]] = []
    for j in range(model.njnt):
        name, kind = model.joint(j).name or f"joint{j}", int(model.jnt_type[j])
        qadr, dadr = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
        if kind == _FREE:
            parts = [("x", "m"), ("y", "m"), ("z", "m"), ("qw", ""), ("qx", ""), ("qy", "")]
            qpos += [(qadr + k, f"{name}_{a}", u) for k, (a, u) in enumerate([*parts, ("qz", "")])]
            vel = [(f"v{a}", "m/s") for a in "xyz"] + [(f"w{a}", "rad/s") for a in "xyz"]
            qvel += [(dadr + k, f"{name}_{a}", u) for k, (a, u) in enumerate(vel)]
        elif kind in _HINGE_OR_SLIDE:
            unit = "rad" if kind == int(mujoco.mjtJoint.mjJNT_HINGE) else "m"
            qpos.append((qadr, name, unit))
            qvel.append((dadr, f"{name}_vel", f"{unit}/s"))
        else:
            raise RuntimeError(f"{KITCHEN_ENV_ID}: unexpected ball joint {name}")
    qpos.sort()
    qvel.sort()
    order = [*qpos[:ROBOT_DOF], *qvel[:ROBOT_DOF], *qpos[ROBOT_DOF:], *qvel[ROBOT_DOF:]]
    if len(order) != STATE_DIM or len({n for _, n, _ in order}) != STATE_DIM:
        raise RuntimeError(f"{KITCHEN_ENV_ID}: joints do not name the {STATE_DIM} observation dims")
    return [n for _, n, _ in order], [u for _, _, u in order]


def kitchen_action_names(spec: KitchenSpec) -> list[str]:
    """The 9 actions: each robot joint's normalized velocity in [-1, 1] (`<joint>_vel`)."""
    names, _ = observation_names(spec)
    return names[ROBOT_DOF : 2 * ROBOT_DOF]


def physics_from_observations(
    spec: KitchenSpec, observations: np.ndarray, time: np.ndarray
) -> np.ndarray:
    """`[N, physics_dim]` states from noise-free observations `[N, 59]` (which hold all of qpos
    and qvel) at `time [N]`, the solver's warm start zero (as after a reset): what data without
    recorded states (D4RL's, whose observations are noisy) can give."""
    obs = np.asarray(observations, dtype=np.float64)
    nq = spec.model.nq
    qpos = np.concatenate([obs[:, :ROBOT_DOF], obs[:, 2 * ROBOT_DOF : ROBOT_DOF + nq]], axis=1)
    qvel = np.concatenate([obs[:, ROBOT_DOF : 2 * ROBOT_DOF], obs[:, ROBOT_DOF + nq :]], axis=1)
    warm = np.zeros((len(obs), spec.model.nv))
    return np.column_stack([np.asarray(time, dtype=np.float64), qpos, qvel, warm])


# --- a Minari dataset --------------------------------------------------------------------------


@contextlib.contextmanager
def _minari_root(root: Path) -> Iterator[None]:
    """`MINARI_DATASETS_PATH` = `root` for the block (Minari's writer has no path argument)."""
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


def write_kitchen_minari(
    root: str | Path,
    dataset_id: str = "oposm/kitchen-random-v0",
    episode_steps: Sequence[int] = (12, 7, 9),
    seed: int = 0,
    **env_kwargs: Any,
) -> Path:
    """A small Minari dataset of seeded uniform random actions in the kitchen, written with
    Minari's own `DataCollector` around `make_kitchen_env(**env_kwargs)`, under `root`.

    Episode k resets with seed `seed + k` and runs `episode_steps[k]` steps (the env's step
    limit is the longest, so that one ends truncated by the limit, the others by the next
    reset). `env_kwargs` default to the noise-free env. Each step's infos hold `physics`, the
    spec's exact state `[89]` after it (`KITCHEN_STATE_SPEC`), N + 1 per episode like the
    observations; the env's own infos (lists of subtask names) are not recorded.

    Sets `MINARI_DATASETS_PATH` while it writes (not thread-safe).

    Returns:
        The dataset's folder (`root / dataset_id`, holding `data/`).

    Raises:
        UserError: the dataset exists already, or no episode steps.
    """
    import minari
    from minari.data_collector.callbacks import StepDataCallback

    root = Path(root)
    steps = [int(n) for n in episode_steps]
    if not steps or min(steps) < 1:
        raise UserError(f"episode_steps {steps}: give at least one episode of at least one step")
    if (root / dataset_id).exists():
        raise UserError(f"Minari dataset {root / dataset_id} exists; remove it or pick another id")
    kwargs = {"robot_noise_ratio": 0.0, "object_noise_ratio": 0.0, **env_kwargs}
    kwargs.setdefault("max_episode_steps", max(steps))
    if kwargs["max_episode_steps"] < max(steps):
        raise UserError(
            f"max_episode_steps {kwargs['max_episode_steps']} < the longest episode's "
            f"{max(steps)} steps; raise it or shorten episode_steps"
        )

    class PhysicsInfo(StepDataCallback):
        """Record the exact physics state as the step's only info."""

        def __call__(self, env: gymnasium.Env, **kw: Any) -> Any:
            data = super().__call__(env, **kw)
            u = env.unwrapped
            state = np.empty(mujoco.mj_stateSize(u.model, KITCHEN_STATE_SPEC))
            mujoco.mj_getState(u.model, u.data, state, KITCHEN_STATE_SPEC)
            data["info"] = {"physics": state}
            return data

    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    with _minari_root(root), warnings.catch_warnings():
        # Minari's advice to give an e-mail and a code link, and gymnasium's passive checker on
        # the env's `desired_goal`, which is the same dict object at every step.
        warnings.filterwarnings("ignore", message=".*(author_email|code_permalink).*")
        warnings.filterwarnings("ignore", message=".*share an object.*")
        env = minari.DataCollector(
            make_kitchen_env(**kwargs), step_data_callback=PhysicsInfo, record_infos=True
        )
        try:
            action_dim = env.action_space.shape[0]
            for k, n in enumerate(steps):
                env.reset(seed=seed + k)
                for _ in range(n):
                    env.step(rng.uniform(-1.0, 1.0, action_dim))
            env.create_dataset(
                dataset_id,
                eval_env=env.spec,
                algorithm_name=f"uniform random actions in [-1, 1] (numpy seed {seed})",
                author="oposm",
                description=(
                    f"{len(steps)} episodes of {steps} random steps in {KITCHEN_ENV_ID}, "
                    "infos['physics'] = the exact MuJoCo state (full physics + warm start)"
                ),
                requirements=[
                    f"{p}=={importlib.metadata.version(p)}"
                    for p in ("gymnasium-robotics", "mujoco", "minari")
                ],
            )
        finally:
            env.close()
    return root / dataset_id
