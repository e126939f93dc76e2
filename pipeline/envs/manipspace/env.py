"""OGBench's manipulation tasks (`ogbench.manipspace`): `cube-single-v0`, `cube-double-v0`,
`scene-v0` and the puzzles `puzzle-3x3-v0` ... `puzzle-4x6-v0` behind the `EnvSpec` interface,
with their evaluation tasks and success rule.

What OGBench's ManipSpace really is (read from `ogbench/manipspace/envs/{env,manipspace_env,
cube_env,scene_env,puzzle_env}.py` and `controllers/diff_ik.py` of the installed ogbench 1.2.2,
and checked step for step against the gymnasium env in tests/test_manipspace.py):

- **Robot** (generic): a UR5e arm (6 hinge joints, PD position actuators with OGBench's gains)
  and a Robotiq 2F-85 gripper (8 coupled joints, one actuator). Physics steps of 0.002 s
  (implicitfast, Newton solver), 25 per control step: `dt` = 0.05 s.
- **Action** (generic) `[dx, dy, dz, dyaw, dgrip]` in [-1, 1], scaled by `[0.05, 0.05, 0.05,
  0.3, 1.0]`: a displacement of the pinch site, a yaw increment and a gripper-opening increment.
  Each control step turns it into joint targets (`ManipSpaceEnv.set_control`): the target pinch
  position (clipped to the workspace bounds), a downward orientation with the new yaw, solved by
  OGBench's own `DiffIKController` (20 damped least-squares iterations on a separate UR5e model,
  stateless between calls), and `255 * opening` for the gripper. The env itself does not clip
  actions; OGBench's evaluation and data generation clip them to [-1, 1], and so does
  `control_step` (a no-op in range).
- **Observation** (generic part, 19 dims): arm joint positions (6) and velocities (6), pinch site
  position `(p - [0.425, 0, 0]) * 10` (3), cos and sin of its yaw (2), gripper opening
  `clip(q_driver / 0.8, 0, 1) * 3` (1), gripper contact `clip(|cfrc_ext(right pad)| / 50, 0, 1)`
  (1). Per cube (per-env): position (scaled as above, 3), quaternion (4), cos and sin of its yaw
  (2). Scene and puzzle: per button a one-hot state (2), joint position * 120 and velocity (the
  scene's 2 buttons, a puzzle's rows x cols in row-major order); scene only: drawer position * 18
  and velocity; window position * 15 and velocity.
- **Puzzle** ("Lights Out"): a button pressed down (its joint crossing -0.02 going down) toggles
  its own state and those of its 4 grid neighbours; a puzzle has no cube (`n_cubes` 0).
- **Goal** (`goal_dims`, per-env): the observation dims of each cube's position; for the scene
  and the puzzles also each button's state (the "on" dim of its one-hot), for the scene the
  drawer and the window position: OGBench's own "oracle goal representation"
  (`compute_oracle_observation`) in observation units.
- **Success** (per-env, `ManipSpaceSpec.success`): every cube within 0.04 m of its goal position;
  scene also every button in its goal state and drawer and window within 0.04 of their goal
  positions; a puzzle every button in its goal state. The registered ids judge it after the step
  (`success_timing='post'`); an evaluation episode lasts at most 200 (cube-single), 500
  (cube-double, puzzle-3x3, puzzle-4x4), 750 (scene), 1000 (puzzle-4x5, puzzle-4x6) steps.

**Why the physics state is more than `mjSTATE_FULLPHYSICS`.** Restoring `[time, qpos, qvel]`
and stepping does not reproduce the env, for three reasons, so a state here (`physics_dim`) is
`mjSTATE_FULLPHYSICS | mjSTATE_WARMSTART | mjSTATE_USERDATA` of `ManipSpaceSpec.model`, the env's
model recompiled with room for user data (every physics parameter copied and checked equal):

1. The solver's warm start (`qacc_warmstart`) changes the Newton solver's answer in the last
   bits; it is part of the state.
2. OGBench reads the pinch site's pose (for the observation and for the next action's target)
   and the pad's contact force (`cfrc_ext`, observation) from `MjData` as the step leaves it:
   `mj_step` computes them *before* the last integration, so in the cube envs they lag `qpos` by
   one physics step (in the scene a post-step `mj_forward` refreshes the pose, not the force).
   They are not functions of `qpos`, so the state keeps these "readings" (pinch position 3,
   orientation matrix 9, pad force 6) in `MjData.userdata`, where `control_step` leaves them.
3. The button states of the scene (which toggle when a button is pressed down past -0.02 and
   lock the drawer or window by a joint damping of 1e6 instead of 2) and of a puzzle live in the
   env object, not in `MjData`; they are kept in user data too, and `control_step` writes the
   damping the scene's imply into the model before stepping (so slots sharing one model stay
   independent).

So `set_physics_state` + `observe` returns the env's observation bit for bit, and
`control_step` the env's next state and observation bit for bit. Not reproduced: the scene env's
task-mode "numerical instability" reset (a cube beyond the workspace bounds +- 0.2 m is put back
at a random place with the env's generator; OGBench's data generation does not use it and
`manipspace_data.check` flags such states instead), and the colours OGBench paints on its model
(visual only: the buttons' state colours too). An observation is not a full state (the gripper's
7 coupled joints and the objects' velocities are missing), so `set_observation` refuses: start
from a physics state (`task_start`, or a dataset's recorded states).
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium
import mujoco
import numpy as np

from pipeline.envs.ids import MANIPSPACE_ENVS, PUZZLE_ENVS
from pipeline.envs.physics import PHYSICS_SPEC
from pipeline.errors import UserError

# Cubes per id (`MANIPSPACE_ENVS`; the scene has one cube, two buttons, a drawer, a window; a
# puzzle none, and rows x cols buttons: `PUZZLE_GRIDS`).
_CUBES = {"cube-single-v0": 1, "cube-double-v0": 2, "scene-v0": 1} | dict.fromkeys(PUZZLE_ENVS, 0)
# puzzle-RxC-v0 -> (R, C)
PUZZLE_GRIDS: dict[str, tuple[int, int]] = {e: (int(e[7]), int(e[9])) for e in PUZZLE_ENVS}
# Step limit of an evaluation episode (the registered `max_episode_steps` of these ids).
EPISODE_STEPS = {"cube-single-v0": 200, "cube-double-v0": 500, "scene-v0": 750,
                 "puzzle-3x3-v0": 500, "puzzle-4x4-v0": 500, "puzzle-4x5-v0": 1000,
                 "puzzle-4x6-v0": 1000}  # fmt: skip

# What a state is (module docstring): full physics, the solver's warm start, the readings.
# The env's own model has no user data: its part of a state is the rest.
ENV_STATE_SPEC = PHYSICS_SPEC | mujoco.mjtState.mjSTATE_WARMSTART
MANIP_STATE_SPEC = ENV_STATE_SPEC | mujoco.mjtState.mjSTATE_USERDATA
# User data: pinch site position (3) and orientation matrix (9), right pad's cfrc_ext (6), then
# the button states (the scene's 2, a puzzle's rows x cols: `ManipSpaceSpec.n_buttons`).
READING_POS = slice(0, 3)
READING_MAT = slice(3, 12)
READING_FORCE = slice(12, 18)
READINGS = 18
BUTTONS = 2  # the scene's

# OGBench's constants (`ManipSpaceEnv`, `SceneEnv`, `PuzzleEnv`).
ACTION_SCALE = np.array([0.05, 0.05, 0.05, 0.3, 1.0])  # action [-1, 1] -> m, m, m, rad, opening
WORKSPACE_BOUNDS = np.array([[0.25, -0.35, 0.02], [0.6, 0.35, 0.35]])  # pinch target clip, m
XYZ_CENTER = np.array([0.425, 0.0, 0.0])
XYZ_SCALE = 10.0
GRIPPER_SCALE = 3.0
BUTTON_SCALE = 120.0
DRAWER_SCALE = 18.0
WINDOW_SCALE = 15.0
CONTACT_FORCE_SCALE = 50.0  # N for a contact reading of 1
GRIPPER_OPEN_QPOS = 0.8  # driver joint angle of a fully open gripper (opening 1)
GRIPPER_CTRL = 255.0  # actuator command of opening 1
SUCCESS_TOLERANCE = 0.04  # m (cubes) or joint units (drawer, window)
BUTTON_PRESSED = -0.02  # a button toggles when its joint crosses this going down
# A pressed puzzle button toggles itself and its grid neighbours (row, col offsets).
PUZZLE_NEIGHBOURS = ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1))
# The goal cost's scale of a button-state dim (`ManipSpaceSpec.goal_scale`): the states are 0 or 1,
# so a predicted state half-way between counts as one tolerance off, a wrong one as two.
BUTTON_GOAL_SCALE = 0.5
LOCKED_DAMPING = 1e6  # drawer / window joint damping while its button is off (0)
UNLOCKED_DAMPING = 2.0
HEALTHY_MARGIN = 0.2  # the scene's instability test: cube beyond workspace bounds +- this
# The pinch frame's downward orientation (`_effector_down_rotation`) as a quaternion, w x y z.
EFFECTOR_DOWN_WXYZ = (0.0, 1.0, 0.0, 0.0)

# Observation layout (module docstring): proprioception, then 9 per cube, then the buttons, then
# the scene's drawer and window.
PROPRIO_DIM = 19
PINCH_DIMS = slice(12, 15)  # the pinch site's position in the proprioception (scaled as a cube's)
CUBE_DIM = 9
BUTTON_DIM = 4  # one-hot (2), position, velocity


def puzzle_toggles(rows: int, cols: int) -> list[list[int]]:
    """Per button of a rows x cols puzzle (row-major), the buttons a press of it toggles: itself
    and its grid neighbours (OGBench's `PuzzleEnv.post_step`)."""
    out = []
    for i in range(rows * cols):
        x, y = divmod(i, cols)
        near = [(x + dx, y + dy) for dx, dy in PUZZLE_NEIGHBOURS]
        out.append([r * cols + c for r, c in near if 0 <= r < rows and 0 <= c < cols])
    return out


def is_manipspace(env_id: str) -> bool:
    """Whether `env_id` is an OGBench manipulation env this module simulates."""
    return env_id in MANIPSPACE_ENVS


def check_manipspace_id(env_id: str) -> None:
    """A one-line `UserError` for an id this module does not simulate."""
    if env_id not in MANIPSPACE_ENVS:
        raise UserError(
            f"unsupported OGBench manipulation env id {env_id!r}; use one of: "
            f"{', '.join(MANIPSPACE_ENVS)}"
        )


def make_manipspace_env(env_id: str, **kwargs: Any) -> gymnasium.Env:
    """`gymnasium.make(env_id, **kwargs)` of a supported id, reset once (so its model exists).

    `import ogbench.manipspace` registers the ids; `ogbench.make_env_and_datasets` is not used
    (it needs the dataset files). Useful kwargs: `mode='data_collection'` (OGBench's data
    generation), `terminate_at_goal=False`, `max_episode_steps`.
    """
    check_manipspace_id(env_id)
    import ogbench.manipspace  # noqa: F401  (registers the ids)

    env = gymnasium.make(env_id, **kwargs)
    env.reset(seed=0)
    return env


@functools.cache
def reference_env(env_id: str) -> gymnasium.Env:
    """One shared task-mode env per id for its read-only parts (model, IK controller, tasks).

    Never step or reset it: `ManipSpaceSpec` holds its IK controller and pinch-to-flange pose.
    """
    return make_manipspace_env(env_id)


@functools.cache
def evaluation_env(env_id: str) -> gymnasium.Env:
    """The task-mode env `ManipSpaceSpec.task_start` resets (OGBench's evaluation env)."""
    return make_manipspace_env(env_id)


@dataclass(frozen=True, eq=False)
class ObjectConfig:
    """Where a task's objects are: cube positions `[n_cubes, 3]` (m; `[0, 3]` in a puzzle); the
    button states `[n_buttons]` (the scene's 0 locks the drawer / window; a puzzle's, row-major),
    the scene's drawer and window joint positions (else None)."""

    block_xyzs: np.ndarray
    button_states: np.ndarray | None = None
    drawer_pos: float | None = None
    window_pos: float | None = None

    @classmethod
    def from_task_part(cls, part: dict[str, Any]) -> ObjectConfig:
        """From a scene task's `init` / `goal` dict (cube tasks: `{'block_xyzs': ...}`; puzzles:
        `{'button_states': ...}`)."""
        buttons = part.get("button_states")
        return cls(
            block_xyzs=np.array(part.get("block_xyzs", np.zeros((0, 3))), dtype=np.float64),
            button_states=None if buttons is None else np.array(buttons, dtype=np.int64),
            drawer_pos=None if "drawer_pos" not in part else float(part["drawer_pos"]),
            window_pos=None if "window_pos" not in part else float(part["window_pos"]),
        )


@dataclass(frozen=True, eq=False)
class ManipTask:
    """One of OGBench's five evaluation tasks (`task_infos[task_id - 1]`)."""

    task_id: int
    name: str
    init: ObjectConfig
    goal: ObjectConfig


@dataclass(frozen=True, eq=False)
class TaskStart:
    """An evaluation episode's start as OGBench's `reset(options={'task_id': ...})` leaves it.

    Attributes:
        task: The task.
        physics: The exact start state `[physics_dim]`.
        observation: The env's reset observation `[state_dim]`.
        goal: The goal this episode is judged against (cubes in the order the reset permuted
            them to: OGBench permutes which cube goes where, `permute_blocks=True`).
        goal_observation: OGBench's goal observation `[state_dim]` (`info['goal']`): the goal
            scene after two random actions, which OGBench draws from an unseeded action space,
            so its arm part (and the start's warm start and time) are not a function of the seed.
    """

    task: ManipTask
    physics: np.ndarray
    observation: np.ndarray
    goal: ObjectConfig
    goal_observation: np.ndarray


def _so3():
    from ogbench.manipspace import lie

    return lie


def _yaw_of_matrix(mat9: np.ndarray) -> float:
    """OGBench's effector yaw: `SO3.from_matrix(m).compute_yaw_radians()`."""
    lie = _so3()
    return lie.SO3.from_matrix(np.array(mat9).reshape(3, 3)).compute_yaw_radians()


def _with_user_data(env: gymnasium.Env, size: int) -> mujoco.MjModel:
    """The env's model compiled again with `size` user-data numbers, OGBench's post-compilation
    changes (PD gains) copied, and every other array checked equal to the env's."""
    from ogbench.manipspace import mjcf_utils

    u = env.unwrapped
    root = ET.fromstring(mjcf_utils.to_string(u.mjcf_model))
    ET.SubElement(root, "size").set("nuserdata", str(size))
    model = mujoco.MjModel.from_xml_string(
        xml=ET.tostring(root, encoding="unicode"), assets=mjcf_utils.get_assets(u.mjcf_model)
    )
    source = u.model
    model.opt.timestep = source.opt.timestep
    # Copied: OGBench's gains, its colours (visual) and what the scene's reset sets on the model
    # (target site positions: visual; damping: rewritten from the button states every step).
    for name in ("actuator_gainprm", "actuator_biasprm", "geom_rgba", "mat_rgba", "site_pos",
                 "dof_damping"):  # fmt: skip
        getattr(model, name)[:] = getattr(source, name)
    differ = [
        name
        for name in dir(source)
        if not name.startswith("_")
        and isinstance(value := getattr(source, name), np.ndarray)
        and not np.array_equal(value, getattr(model, name), equal_nan=True)
    ]
    if differ or model.nq != source.nq or model.nv != source.nv or model.nu != source.nu:
        raise RuntimeError(
            f"{env.spec.id}: the recompiled model differs from OGBench's in {differ}"
        )
    return model


@dataclass(frozen=True, eq=False)
class ManipSpaceSpec:
    """An OGBench manipulation env (`EnvSpec`; see the module docstring for what is generic
    and what is per-env). Build it with `ManipSpaceSpec.create(env_id)`.

    Attributes (besides `EnvSpec`'s):
        n_cubes: Cubes in the scene.
        scene: Whether the env has the scene's buttons, drawer and window.
        layout: The workspace (`workspace_bounds`, OGBench's object and target sampling bounds;
            a puzzle's `grid`, rows and cols), not a maze.
        n_buttons: Buttons (the scene's 2, a puzzle's rows x cols; the cube envs' 0).
        grid: A puzzle's (rows, cols); None for the other envs.
    """

    env_id: str
    model: mujoco.MjModel
    dt: float
    state_dim: int
    action_dim: int
    max_episode_steps: int
    goal_dims: tuple[int, ...]
    n_cubes: int
    scene: bool
    layout: dict[str, Any]
    _ids: dict[str, Any]
    _ik: Any
    _pinch_to_flange: Any
    n_buttons: int = 0
    grid: tuple[int, int] | None = None
    state_spec: ClassVar[int] = MANIP_STATE_SPEC

    @classmethod
    def create(cls, env_id: str) -> ManipSpaceSpec:
        """The spec of OGBench's `env_id` (`cube-single-v0`, `cube-double-v0`, `scene-v0`,
        `puzzle-3x3-v0`, ...)."""
        check_manipspace_id(env_id)
        env = reference_env(env_id)
        u = env.unwrapped
        scene = env_id == "scene-v0"
        grid = PUZZLE_GRIDS.get(env_id)
        n_buttons = BUTTONS if scene else 0 if grid is None else grid[0] * grid[1]
        model = _with_user_data(env, READINGS + n_buttons)
        n_cubes = _CUBES[env_id]
        for mask in (mujoco.mjtState.mjSTATE_PLUGIN, mujoco.mjtState.mjSTATE_ACT):
            if mujoco.mj_stateSize(model, mask):  # state layout below assumes none
                raise RuntimeError(f"{env_id}: unexpected plugin or actuator state")
        joint = model.joint
        ids: dict[str, Any] = {
            "arm_qpos": np.array([model.jnt_qposadr[j] for j in u._arm_joint_ids]),
            "arm_dof": np.array([model.jnt_dofadr[j] for j in u._arm_joint_ids]),
            "arm_act": np.array(u._arm_actuator_ids),
            "grip_act": np.array(u._gripper_actuator_ids),
            "grip_qpos": int(model.jnt_qposadr[u._gripper_opening_joint_id]),
            "pinch": int(u._pinch_site_id),
            "pad": int(model.body("ur5e/robotiq/right_pad").id),
            "cube_qpos": [int(joint(f"object_joint_{i}").qposadr[0]) for i in range(n_cubes)],
        }
        goal_dims = [PROPRIO_DIM + CUBE_DIM * i + k for i in range(n_cubes) for k in range(3)]
        buttons = range(n_buttons)
        base = PROPRIO_DIM + CUBE_DIM * n_cubes
        if n_buttons:
            ids["button_qpos"] = [int(joint(f"buttonbox_joint_{i}").qposadr[0]) for i in buttons]
            ids["button_dof"] = [int(joint(f"buttonbox_joint_{i}").dofadr[0]) for i in buttons]
            # what a press of each button toggles: the scene's itself, a puzzle's its neighbours
            ids["toggles"] = [[i] for i in buttons] if grid is None else puzzle_toggles(*grid)
            goal_dims += [base + BUTTON_DIM * i + 1 for i in buttons]  # each button's "on" dim
        if scene:
            for part in ("drawer", "window"):
                ids[f"{part}_qpos"] = int(joint(f"{part}_slide").qposadr[0])
                ids[f"{part}_dof"] = int(joint(f"{part}_slide").dofadr[0])
            after = base + BUTTON_DIM * n_buttons
            goal_dims += [after, after + 2]  # drawer, window
        layout = {
            "kind": "manipspace",
            "workspace_bounds": WORKSPACE_BOUNDS.tolist(),
            "object_sampling_bounds": np.asarray(u._object_sampling_bounds).tolist(),
            "target_sampling_bounds": np.asarray(u._target_sampling_bounds).tolist(),
        }
        if grid is not None:
            layout["grid"] = list(grid)
        return cls(
            env_id=env_id,
            model=model,
            dt=float(u._control_timestep),
            state_dim=int(env.observation_space.shape[0]),
            action_dim=int(env.action_space.shape[0]),
            max_episode_steps=EPISODE_STEPS[env_id],
            goal_dims=tuple(goal_dims),
            n_cubes=n_cubes,
            scene=scene,
            layout=layout,
            _ids=ids,
            _ik=u._ik,
            _pinch_to_flange=u._T_pa,
            n_buttons=n_buttons,
            grid=grid,
        )

    # State ------------------------------------------------------------------------------------

    @property
    def physics_dim(self) -> int:
        """`[time, qpos, qvel, qacc_warmstart, readings (18), button states (n_buttons)]`: 80
        (cube-single), 99 (cube-double), 94 (scene), 97 (puzzle-3x3), 125 (puzzle-4x4)."""
        return int(mujoco.mj_stateSize(self.model, MANIP_STATE_SPEC))

    def physics_state(self, data: mujoco.MjData) -> np.ndarray:
        """The exact state `[physics_dim]` of `data` (of `self.model`; for an OGBench env's own
        data use `state_of_env`)."""
        if data.userdata.shape[0] != self.model.nuserdata:
            raise ValueError("data is not of this spec's model; use state_of_env for an env")
        out = np.empty(self.physics_dim)
        mujoco.mj_getState(self.model, data, out, MANIP_STATE_SPEC)
        return out

    def set_physics_state(
        self, data: mujoco.MjData, state: np.ndarray, model: mujoco.MjModel | None = None
    ) -> None:
        """Put `data` (of `model`: this spec's model, by default, or a variant of it) exactly in
        `state [physics_dim]`: reset, restore, the scene's locks written into `model`, and a
        forward pass for the derived quantities nothing here reads (rendering, sites)."""
        model = self.model if model is None else model
        state = np.asarray(state, dtype=np.float64)
        if state.shape != (self.physics_dim,):
            raise ValueError(f"physics state {state.shape} != ({self.physics_dim},)")
        mujoco.mj_resetData(model, data)
        mujoco.mj_setState(model, data, state, MANIP_STATE_SPEC)
        self._apply_locks(model, data)
        mujoco.mj_forward(model, data)

    def cold(self, state: np.ndarray) -> np.ndarray:
        """`state [physics_dim]` with the solver's warm start zeroed, as after a reset (the rest
        exactly as it was): what an evaluation start keeps of OGBench's reset, whose warm start
        comes from two actions drawn from an unseeded action space (`TaskStart`)."""
        data = mujoco.MjData(self.model)
        self.set_physics_state(data, state)
        data.qacc_warmstart[:] = 0.0
        return self.physics_state(data)

    def state_of_env(self, env: gymnasium.Env) -> np.ndarray:
        """The exact state `[physics_dim]` an OGBench env of this id is in (its own `MjData`
        has no user data: the readings are taken from its data, the button states from the
        env object), in the layout of `physics_state`."""
        u = env.unwrapped
        model, data = u.model, u.data
        core = np.empty(mujoco.mj_stateSize(model, ENV_STATE_SPEC))
        mujoco.mj_getState(model, data, core, ENV_STATE_SPEC)
        parts = [core, self._readings(data)]
        if self.n_buttons:
            parts.append(np.asarray(u._cur_button_states, dtype=np.float64))
        return np.concatenate(parts)

    def _readings(self, data: mujoco.MjData) -> np.ndarray:
        """`[18]`: what OGBench reads from `data` besides the state (module docstring, 2)."""
        i = self._ids
        return np.concatenate(
            [data.site_xpos[i["pinch"]], data.site_xmat[i["pinch"]], data.cfrc_ext[i["pad"]]]
        )

    def button_states(self, data: mujoco.MjData) -> np.ndarray:
        """The button states `[n_buttons]` (int) kept in `data.userdata`."""
        return data.userdata[READINGS : READINGS + self.n_buttons].astype(np.int64)

    def _apply_locks(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """The scene: the drawer (button 0) and window (button 1) damping the buttons imply."""
        if not self.scene:
            return
        for button, part in enumerate(("drawer", "window")):
            on = data.userdata[READINGS + button] != 0
            model.dof_damping[self._ids[f"{part}_dof"]] = UNLOCKED_DAMPING if on else LOCKED_DAMPING

    def cube_positions(self, physics: np.ndarray) -> np.ndarray:
        """`[..., n_cubes, 3]` cube positions (m) from states `[..., physics_dim]`."""
        physics = np.asarray(physics)
        cols = [1 + adr + k for adr in self._ids["cube_qpos"] for k in range(3)]  # 1: time
        return physics[..., cols].reshape(*physics.shape[:-1], self.n_cubes, 3)

    # Observation ------------------------------------------------------------------------------

    def observed_cubes(self, observations: np.ndarray) -> np.ndarray:
        """`[..., n_cubes, 3]` cube positions (m) read from observations `[..., state_dim]` (or
        predicted ones): the inverse of the observation's `(p - [0.425, 0, 0]) * 10`."""
        cols = [PROPRIO_DIM + CUBE_DIM * i + k for i in range(self.n_cubes) for k in range(3)]
        cubes = np.asarray(observations, dtype=np.float64)[..., cols]
        return XYZ_CENTER + cubes.reshape(*cubes.shape[:-1], self.n_cubes, 3) / XYZ_SCALE

    def observed_pinch(self, observations: np.ndarray) -> np.ndarray:
        """`[..., 3]` the pinch site's position (m) read from observations `[..., state_dim]`."""
        pinch = np.asarray(observations, dtype=np.float64)[..., PINCH_DIMS]
        return XYZ_CENTER + pinch / XYZ_SCALE

    def observe(self, data: mujoco.MjData) -> np.ndarray:
        """OGBench's observation `[state_dim]` (float64) of `data` (of `self.model`), bit for bit
        what the env returns in the same state."""
        lie = _so3()
        i, qpos, qvel, user = self._ids, data.qpos, data.qvel, data.userdata
        yaw = np.array([_yaw_of_matrix(user[READING_MAT])])
        opening = np.array(np.clip([qpos[i["grip_qpos"]] / GRIPPER_OPEN_QPOS], 0, 1))
        force = np.array(user[READING_FORCE])
        contact = np.array([np.clip(np.linalg.norm(force) / CONTACT_FORCE_SCALE, 0, 1)])
        ob = [
            qpos[i["arm_qpos"]],
            qvel[i["arm_dof"]],
            (np.array(user[READING_POS]) - XYZ_CENTER) * XYZ_SCALE,
            np.cos(yaw),
            np.sin(yaw),
            opening * GRIPPER_SCALE,
            contact,
        ]
        for adr in i["cube_qpos"]:
            quat = qpos[adr + 3 : adr + 7].copy()
            cube_yaw = np.array([lie.SO3(wxyz=quat).compute_yaw_radians()])
            ob += [(qpos[adr : adr + 3] - XYZ_CENTER) * XYZ_SCALE, quat]
            ob += [np.cos(cube_yaw), np.sin(cube_yaw)]
        if self.n_buttons:
            states = self.button_states(data)
            for b in range(self.n_buttons):
                ob += [
                    np.eye(2)[states[b]],
                    qpos[i["button_qpos"][b] : i["button_qpos"][b] + 1] * BUTTON_SCALE,
                    qvel[i["button_dof"][b] : i["button_dof"][b] + 1].copy(),
                ]
        if self.scene:
            for part, scale in (("drawer", DRAWER_SCALE), ("window", WINDOW_SCALE)):
                ob += [
                    qpos[i[f"{part}_qpos"] : i[f"{part}_qpos"] + 1] * scale,
                    qvel[i[f"{part}_dof"] : i[f"{part}_dof"] + 1].copy(),
                ]
        return np.concatenate(ob)

    def start_observation(self, xy: np.ndarray) -> np.ndarray:
        raise UserError(f"{self.env_id} has no start position in a plane; use task_start")

    def set_observation(self, data: mujoco.MjData, observation: np.ndarray) -> None:
        raise UserError(
            f"an observation of {self.env_id} is not a full state (gripper joints and object "
            "velocities are missing); restore a physics state (set_physics_state) instead"
        )

    # Dynamics ---------------------------------------------------------------------------------

    def joint_targets(self, data: mujoco.MjData, action: np.ndarray) -> None:
        """`ManipSpaceEnv.set_control`: `data.ctrl` from `action [5]` (already clipped), the
        pinch readings and the arm's joint positions (module docstring)."""
        lie = _so3()
        i = self._ids
        action = 0.5 * (action + 1) * (ACTION_SCALE - -ACTION_SCALE) + -ACTION_SCALE
        down = lie.SO3(np.asarray(EFFECTOR_DOWN_WXYZ))
        user = data.userdata
        effector_pos = np.array(user[READING_POS])
        effector_yaw = _yaw_of_matrix(user[READING_MAT])
        opening = np.array(np.clip([data.qpos[i["grip_qpos"]] / GRIPPER_OPEN_QPOS], 0, 1))
        target_pos = effector_pos + action[:3]
        target_rot = (
            lie.SO3.from_z_radians(action[3])
            @ lie.SO3.from_z_radians(effector_yaw)
            @ down.inverse()
        )
        target_opening = opening + action[4]
        np.clip(target_pos, *WORKSPACE_BOUNDS, out=target_pos)
        yaw = np.clip(target_rot.compute_yaw_radians(), -np.pi, np.pi)
        target_rot = lie.SO3.from_z_radians(yaw) @ down
        target_opening = np.clip(target_opening, 0.0, 1.0)
        pose = lie.SE3.from_rotation_and_translation(rotation=target_rot, translation=target_pos)
        flange = pose @ self._pinch_to_flange
        qpos_target = self._ik.solve(
            pos=flange.translation(),
            quat=flange.rotation().wxyz,
            curr_qpos=data.qpos[i["arm_qpos"]],
        )
        data.ctrl[i["arm_act"]] = qpos_target
        data.ctrl[i["grip_act"]] = GRIPPER_CTRL * target_opening

    def control_step(self, model: mujoco.MjModel, data: mujoco.MjData, action: np.ndarray) -> None:
        """One control step of `action [5]`, bit for bit `env.step` after OGBench's evaluation
        clip to [-1, 1]: joint targets, 25 MuJoCo steps, `mj_rnePostConstraint`; the button
        toggles (a puzzle's press toggles the grid neighbours too), the scene's locks and the
        forward pass; the new readings into user data.

        `model` is this spec's model or a copy of it (its drawer / window damping is written)."""
        action = np.clip(np.array(action), -1, 1)
        self._apply_locks(model, data)
        self.joint_targets(data, action)
        if self.n_buttons:
            pressed_before = [data.qpos[a] for a in self._ids["button_qpos"]]
        mujoco.mj_step(model, data, nstep=round(self.dt / model.opt.timestep))
        mujoco.mj_rnePostConstraint(model, data)
        if self.n_buttons:
            for b, adr in enumerate(self._ids["button_qpos"]):
                if pressed_before[b] > BUTTON_PRESSED and data.qpos[adr] <= BUTTON_PRESSED:
                    for toggled in self._ids["toggles"][b]:
                        k = READINGS + toggled
                        data.userdata[k] = (data.userdata[k] + 1) % 2
            self._apply_locks(model, data)
            mujoco.mj_forward(model, data)
        data.userdata[:READINGS] = self._readings(data)

    # Tasks and success ------------------------------------------------------------------------

    def tasks(self) -> list[ManipTask]:
        """OGBench's five evaluation tasks of this env (`task_infos`), ids 1 to 5."""
        out = []
        for k, info in enumerate(reference_env(self.env_id).unwrapped.task_infos, start=1):
            if self.scene:
                init, goal = info["init"], info["goal"]
            elif self.grid is not None:
                init = {"button_states": info["init_button_states"]}
                goal = {"button_states": info["goal_button_states"]}
            else:
                init, goal = {"block_xyzs": info["init_xyzs"]}, {"block_xyzs": info["goal_xyzs"]}
            out.append(
                ManipTask(
                    task_id=k,
                    name=str(info["task_name"]),
                    init=ObjectConfig.from_task_part(init),
                    goal=ObjectConfig.from_task_part(goal),
                )
            )
        return out

    def task_start(self, task_id: int, seed: int) -> TaskStart:
        """Start task `task_id` (1 to 5) as OGBench's evaluation does: `env.reset(seed=seed,
        options={'task_id': task_id})` (random arm pose, cube positions +-0.01 m and random yaw,
        drawer / window +-0.01; a puzzle's buttons exactly the task's), captured exactly (see
        `TaskStart` for what the seed leaves out).
        """
        task = self.tasks()[int(task_id) - 1]
        env = evaluation_env(self.env_id)
        observation, info = env.reset(seed=int(seed), options={"task_id": int(task_id)})
        u = env.unwrapped
        if self.grid is not None:  # no cubes: the goal is the button states
            goal = ObjectConfig(np.zeros((0, 3)), np.array(u._target_button_states, np.int64))
        else:
            targets = np.array([u.data.mocap_pos[m] for m in u._cube_target_mocap_ids])
            goal = ObjectConfig(targets)
            if self.scene:
                goal = ObjectConfig(
                    targets,
                    np.array(u._target_button_states, dtype=np.int64),
                    float(u._target_drawer_pos),
                    float(u._target_window_pos),
                )
        return TaskStart(
            task=task,
            physics=self.state_of_env(env),
            observation=np.array(observation),
            goal=goal,
            goal_observation=np.array(info["goal"]),
        )

    def success(self, data: mujoco.MjData, goal: ObjectConfig) -> bool:
        """OGBench's success (`_compute_successes`, all of them) of state `data` (of
        `self.model`) for `goal`: each cube's position within 0.04 of its goal; the buttons (the
        scene's, a puzzle's) in their goal states; the scene's drawer and window within 0.04 of
        theirs."""
        i = self._ids
        for adr, target in zip(i["cube_qpos"], goal.block_xyzs, strict=True):
            if not np.linalg.norm(data.qpos[adr : adr + 3] - target) <= SUCCESS_TOLERANCE:
                return False
        if self.n_buttons:
            assert goal.button_states is not None
            if not np.array_equal(self.button_states(data), goal.button_states):
                return False
        if not self.scene:
            return True
        drawer = np.abs(data.qpos[i["drawer_qpos"]] - goal.drawer_pos) <= SUCCESS_TOLERANCE
        window = np.abs(data.qpos[i["window_qpos"]] - goal.window_pos) <= SUCCESS_TOLERANCE
        return bool(drawer and window)

    def goal_vector(self, goal: ObjectConfig) -> np.ndarray:
        """`[len(goal_dims)]`: `goal` in observation units at `goal_dims` (cube positions scaled
        as observed; scene and puzzle: button states 0 / 1; scene: drawer * 18, window * 15)."""
        parts = [((np.asarray(goal.block_xyzs) - XYZ_CENTER) * XYZ_SCALE).ravel()]
        if self.n_buttons:
            assert goal.button_states is not None
            parts.append(np.asarray(goal.button_states, dtype=np.float64))
        if self.scene:
            parts.append(np.array([goal.drawer_pos * DRAWER_SCALE, goal.window_pos * WINDOW_SCALE]))
        return np.concatenate(parts)

    @property
    def goal_scale(self) -> tuple[float, ...]:
        """Per goal dim, its success tolerance in observation units, what planners divide the
        distance to a goal by (`GoalCost`): cube positions 0.04 m x 10 = 0.4; button states (the
        scene's, a puzzle's) 0.5 (`BUTTON_GOAL_SCALE`); the scene's drawer 0.04 x 18 = 0.72,
        window 0.04 x 15 = 0.6."""
        scale = [SUCCESS_TOLERANCE * XYZ_SCALE] * (3 * self.n_cubes)
        scale += [BUTTON_GOAL_SCALE] * self.n_buttons
        if self.scene:
            scale += [SUCCESS_TOLERANCE * DRAWER_SCALE, SUCCESS_TOLERANCE * WINDOW_SCALE]
        return tuple(scale)

    @property
    def goal_objects(self) -> tuple[tuple[int, ...], ...]:
        """The goal vector's indices of each object, in its order (`goal_vector`): each cube's
        position (3), each button's state, the scene's drawer, its window (1 each); what
        `deploy.object_subtasks` plans to one at a time, with the tolerances of `goal_scale`."""
        cubes = [(3 * i, 3 * i + 1, 3 * i + 2) for i in range(self.n_cubes)]
        singles = range(3 * self.n_cubes, len(self.goal_dims))
        return (*cubes, *((i,) for i in singles))

    def goal_reached(self, observations: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """`[...]` bool: `success` judged from observations `[..., state_dim]` and goal vectors
        `[..., G]` (`goal_vector`) instead of states, for planners and batched evaluation. The
        tolerances are scaled to observation units, so it agrees with `success` except within
        round-off of a threshold."""
        observations = np.asarray(observations)
        at = observations[..., list(self.goal_dims)]
        goals = np.asarray(goals)
        n = 3 * self.n_cubes
        cubes = (at[..., :n] - goals[..., :n]).reshape(*at.shape[:-1], self.n_cubes, 3)
        ok = (np.linalg.norm(cubes, axis=-1) <= SUCCESS_TOLERANCE * XYZ_SCALE).all(-1)
        b = n + self.n_buttons  # the buttons' dims are n .. b - 1, the scene's drawer b
        if self.n_buttons:
            ok &= (at[..., n:b] == goals[..., n:b]).all(-1)
        if self.scene:
            ok &= np.abs(at[..., b] - goals[..., b]) <= SUCCESS_TOLERANCE * DRAWER_SCALE
            ok &= np.abs(at[..., b + 1] - goals[..., b + 1]) <= SUCCESS_TOLERANCE * WINDOW_SCALE
        return ok


@functools.cache
def manipspace_spec(env_id: str) -> ManipSpaceSpec:
    """One shared `ManipSpaceSpec` per id (creating one compiles a model: about a second)."""
    return ManipSpaceSpec.create(env_id)
