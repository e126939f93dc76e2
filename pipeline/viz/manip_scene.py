"""What every 3-D view of OGBench's manipulation envs shares: the robot, the table, the objects
and their goals, a legend and a camera that frames the workspace.

The robot is drawn from MuJoCo's own kinematics: an observation holds the arm's six joint angles
and the gripper's opening, so `ArmPoses` puts them into the env's model (`ManipSpaceSpec.model`)
and runs `mj_kinematics`; the arm is a thick line through its link bodies (base, shoulder, upper
arm, forearm, the three wrist links, the gripper's base), the two fingers thinner lines through
theirs. The gripper's other joints follow the opening by a fixed coupling (`_finger_joints`):
close to the real linkage, which MuJoCo solves only by simulating it. The scene's buttons,
drawer and window, and a puzzle's buttons, are the bounding boxes of their geoms in each body's
frame, moved by a per-step transform of the body; their joints come from the observation too.

A cube is a solid box in its colour (its orientation from the observation); its goal a wire box
of the success tolerance in the same colour with a label, joined to the cube by a thin line, so
which cube goes where reads at a glance. A puzzle's button caps are solid boxes in their state's
colour at every step (OGBench's: red 0, blue 1); a button's goal state is a wire box around its
cap in the goal state's colour, so a cap whose colour is not its box's is still wrong. The legend
is a small 2-D view of its own: Rerun's 3-D views have none.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.envs.manipspace.env import (
    BUTTON_DIM,
    BUTTON_SCALE,
    CUBE_DIM,
    DRAWER_SCALE,
    GRIPPER_OPEN_QPOS,
    GRIPPER_SCALE,
    PROPRIO_DIM,
    SUCCESS_TOLERANCE,
    WINDOW_SCALE,
    WORKSPACE_BOUNDS,
    XYZ_CENTER,
    XYZ_SCALE,
    ManipSpaceSpec,
)
from pipeline.viz.maze import AGENT, Color, text_color

ARM_BODIES = (
    "ur5e/base", "ur5e/shoulder_link", "ur5e/upper_arm_link", "ur5e/forearm_link",
    "ur5e/wrist_1_link", "ur5e/wrist_2_link", "ur5e/wrist_3_link", "ur5e/robotiq/base",
)  # fmt: skip
FINGER_BODIES = tuple(
    tuple(f"ur5e/robotiq/{side}_{part}" for part in ("driver", "follower", "pad"))
    for side in ("right", "left")
)
# The scene's moving and fixed parts (bodies with geoms; the drawer's virtual handles have none).
SCENE_BODIES = ("buttonbox_0", "button_0", "buttonbox_1", "button_1", "drawer_base",
                "drawer_link", "window", "windowb_a", "windowb_b")  # fmt: skip
# Button states' colours as OGBench draws them: red 0, then blue 1 on a puzzle (`PuzzleEnv`) and
# white 1 in the scene (`SceneEnv`, where 0 locks the drawer or window).
BUTTON_OFF: Color = (245, 66, 84)
BUTTON_ON: Color = (89, 140, 232)
SCENE_BUTTON_ON: Color = (240, 240, 240)
BUTTON_CAP = np.array([0.018, 0.018, 0.005])  # half sizes of a drawn cap (radius 0.0172 m)
BUTTON_GOAL = np.array([0.026, 0.026, 0.012])  # half sizes of a goal state's wire box
ARM = (70, 75, 90)
JOINT = (40, 40, 48)
TABLE = (205, 200, 188)
TABLE_MIN = np.array([-0.15, -0.55])  # the table reaches past the arm's base and the drawer
WALL = (150, 150, 150)
WORKSPACE = (120, 150, 200)
FIXTURE = (150, 135, 115)
CUBE_COLORS: list[Color] = [(0, 150, 200), (150, 70, 200)]  # not the pinch site's orange
CUBE_HALF = 0.02  # OGBench's cubes are 4 cm
PINCH = slice(12, 15)  # the pinch site's position in the observation (scaled as the cubes)
OPENING = 17  # the gripper's opening in the observation (0 open .. 3 closed)


def to_metres(observed: np.ndarray) -> np.ndarray:
    """Positions `[..., 3]` in observation units (`(p - [0.425, 0, 0]) * 10`) -> metres."""
    return XYZ_CENTER + np.asarray(observed, dtype=np.float64) / XYZ_SCALE


def cube_color(i: int) -> Color:
    return CUBE_COLORS[i % len(CUBE_COLORS)]


def button_on_color(spec: ManipSpaceSpec) -> Color:
    """The colour of a button in state 1: the scene's white, a puzzle's blue."""
    return SCENE_BUTTON_ON if spec.scene else BUTTON_ON


def button_colors(states: np.ndarray, on_color: Color = BUTTON_ON) -> np.ndarray:
    """`[..., 3]` uint8 colours of button states `[...]` (0 or 1; a prediction is rounded)."""
    on = np.asarray(states, dtype=np.float64) >= 0.5
    return np.where(on[..., None], on_color, BUTTON_OFF).astype(np.uint8)


def scene_bodies(spec: ManipSpaceSpec) -> tuple[str, ...]:
    """The bodies of the env's parts besides the robot and the cubes: the scene's, or each
    puzzle button's box and button."""
    if spec.scene:
        return SCENE_BODIES
    return tuple(f"{part}_{i}" for i in range(spec.n_buttons) for part in ("buttonbox", "button"))


def observed_buttons(spec: ManipSpaceSpec, observations: np.ndarray) -> np.ndarray:
    """`[..., n_buttons]` the button states observations `[..., state_dim]` show."""
    base = PROPRIO_DIM + CUBE_DIM * spec.n_cubes
    cols = [base + BUTTON_DIM * b + 1 for b in range(spec.n_buttons)]
    return np.asarray(observations)[..., cols]


def _finger_joints(model: mujoco.MjModel) -> list[tuple[int, float]]:
    """(qpos address, gain on the driver angle) of each gripper joint: the spring links turn with
    the driver, the followers against it (keeping the pads parallel), the couplers stay near 0."""
    out = []
    for side in ("right", "left"):
        for part, gain in (("driver", 1.0), ("spring_link", 1.0), ("follower", -1.0)):
            out.append((int(model.joint(f"ur5e/robotiq/{side}_{part}_joint").qposadr[0]), gain))
    return out


@dataclass
class Poses:
    """Where the robot and the scene's parts are at each of `n` steps (metres, world frame).

    Attributes:
        arm: `[n, len(ARM_BODIES) + 1, 3]`: the link bodies, then the pinch site.
        fingers: `[n, 2, 4, 3]`: per finger the gripper base, then `FINGER_BODIES`.
        bodies: `scene_bodies` name -> (position `[n, 3]`, quaternion `[n, 4]` x y z w).
        button_tops: `[n, n_buttons, 3]`: each button's top (site `btntop_<i>`) as pressed.
    """

    arm: np.ndarray
    fingers: np.ndarray
    bodies: dict[str, tuple[np.ndarray, np.ndarray]]
    button_tops: np.ndarray | None = None


class ArmPoses:
    """MuJoCo's forward kinematics of observations of one env (module docstring)."""

    def __init__(self, spec: ManipSpaceSpec) -> None:
        self.spec, self.model = spec, spec.model
        self.data = mujoco.MjData(self.model)
        body = self.model.body
        self.arm_ids = [body(n).id for n in ARM_BODIES]
        self.finger_ids = [[body(n).id for n in finger] for finger in FINGER_BODIES]
        self.scene_ids = {n: body(n).id for n in scene_bodies(spec)}
        self.top_ids = [self.model.site(f"btntop_{i}").id for i in range(spec.n_buttons)]
        self.fingers = _finger_joints(self.model)
        self.arm_qpos = spec._ids["arm_qpos"]

    def joint_positions(self, observations: np.ndarray) -> np.ndarray:
        """`qpos [n, nq]` of observations `[n, state_dim]`: the arm, the gripper (coupled to its
        opening), the cubes, the buttons and the scene's joints, all at once."""
        spec, obs = self.spec, np.asarray(observations, dtype=np.float64)
        qpos = np.tile(self.model.qpos0, (len(obs), 1))
        qpos[:, self.arm_qpos] = obs[:, :6]
        driver = np.clip(obs[:, OPENING] / GRIPPER_SCALE, 0, 1) * GRIPPER_OPEN_QPOS
        for adr, gain in self.fingers:
            qpos[:, adr] = gain * driver
        for i, adr in enumerate(spec._ids["cube_qpos"]):
            at = PROPRIO_DIM + CUBE_DIM * i
            qpos[:, adr : adr + 3] = to_metres(obs[:, at : at + 3])
            qpos[:, adr + 3 : adr + 7] = obs[:, at + 3 : at + 7]
        base = PROPRIO_DIM + CUBE_DIM * spec.n_cubes
        for b, adr in enumerate(spec._ids.get("button_qpos", [])):
            qpos[:, adr] = obs[:, base + BUTTON_DIM * b + 2] / BUTTON_SCALE
        if spec.scene:
            after = base + BUTTON_DIM * spec.n_buttons
            qpos[:, spec._ids["drawer_qpos"]] = obs[:, after] / DRAWER_SCALE
            qpos[:, spec._ids["window_qpos"]] = obs[:, after + 2] / WINDOW_SCALE
        return qpos

    def __call__(self, observations: np.ndarray) -> Poses:
        """The poses at each observation `[n, state_dim]`: one `mj_kinematics` a step, the
        rest batched."""
        observations = np.asarray(observations, dtype=np.float64)
        qpos = self.joint_positions(observations)
        n, nbody = len(observations), self.model.nbody
        xpos, xquat = np.empty((n, nbody, 3)), np.empty((n, nbody, 4))
        tops = np.empty((n, len(self.top_ids), 3))
        for t in range(n):
            self.data.qpos[:] = qpos[t]
            mujoco.mj_kinematics(self.model, self.data)
            xpos[t], xquat[t] = self.data.xpos, self.data.xquat
            tops[t] = self.data.site_xpos[self.top_ids]
        pinch = to_metres(observations[:, PINCH])[:, None]
        arm = np.concatenate([xpos[:, self.arm_ids], pinch], axis=1)
        base = np.broadcast_to(xpos[:, self.arm_ids[-1], None], (n, 1, 3))
        fingers = np.stack(
            [np.concatenate([base, xpos[:, ids]], axis=1) for ids in self.finger_ids], axis=1
        )
        bodies = {  # MuJoCo's quaternions are w x y z, Rerun's x y z w
            name: (xpos[:, b], xquat[:, b][:, [1, 2, 3, 0]]) for name, b in self.scene_ids.items()
        }
        return Poses(arm, fingers, bodies, tops)


def _geom_boxes(model: mujoco.MjModel, body: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The body's geoms as boxes in its frame: centres `[g, 3]`, half sizes `[g, 3]`,
    quaternions `[g, 4]` (x y z w), from each geom's bounding box (`geom_aabb`)."""
    ids = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body]
    centres, halves, quats = [], [], []
    for g in ids:
        rot = np.empty(9)
        mujoco.mju_quat2Mat(rot, model.geom_quat[g])
        centres.append(model.geom_pos[g] + rot.reshape(3, 3) @ model.geom_aabb[g, :3])
        halves.append(model.geom_aabb[g, 3:])
        quats.append(model.geom_quat[g][[1, 2, 3, 0]])
    return np.array(centres), np.array(halves), np.array(quats)


def log_table(rec: rr.RecordingStream, spec: ManipSpaceSpec, entity: str = "world") -> None:
    """The table (a slab under the arm's base and the scene), the outline of the env's walls on
    it (where the cubes stay), the pinch site's workspace (a faint wire box: where the gripper
    may go) and the scene's or a puzzle's parts in their own frames (static)."""
    model = spec.model
    walls = [g for g in range(model.ngeom) if model.geom(g).name.startswith("wall_")]
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    lo = np.min([data.geom_xpos[g] - model.geom_size[g] for g in walls], axis=0)
    hi = np.max([data.geom_xpos[g] + model.geom_size[g] for g in walls], axis=0)
    low = np.minimum(lo[:2], TABLE_MIN) - 0.04
    high = np.maximum(hi[:2], -TABLE_MIN) + 0.04
    rec.log(
        f"{entity}/table",
        rr.Boxes3D(
            centers=[[*(low + high) / 2, -0.0105]],
            half_sizes=[[*(high - low) / 2, 0.01]],
            colors=TABLE,
            fill_mode="solid",
        ),
        static=True,
    )
    corners = [[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]], [lo[0], lo[1]]]
    rec.log(
        f"{entity}/walls",
        rr.LineStrips3D([[[x, y, 0.0] for x, y in corners]], colors=WALL, radii=0.003),
        static=True,
    )
    low3, high3 = WORKSPACE_BOUNDS
    rec.log(
        f"{entity}/workspace",
        rr.Boxes3D(
            centers=[(low3 + high3) / 2],
            half_sizes=[(high3 - low3) / 2],
            colors=(*WORKSPACE, 110),
            radii=0.001,
        ),
        static=True,
    )
    for name in scene_bodies(spec):
        centres, halves, quats = _geom_boxes(model, model.body(name).id)
        rec.log(
            f"{entity}/scene/{name}",
            rr.Boxes3D(centers=centres, half_sizes=halves, quaternions=quats,
                       colors=FIXTURE, radii=0.001),
            static=True,
        )  # fmt: skip


def log_robot(
    rec: rr.RecordingStream, poses: Poses, times: list[rr.TimeColumn], entity: str = "world"
) -> None:
    """The arm, fingers, pinch site and the scene's moving parts at every step of `times`."""
    n = len(poses.arm)
    one = np.ones(n, dtype=int)
    rec.send_columns(f"{entity}/arm/links", times,
                     rr.LineStrips3D.columns(strips=list(poses.arm)).partition(one))  # fmt: skip
    rec.log(f"{entity}/arm/links", rr.LineStrips3D.from_fields(colors=ARM, radii=0.012),
            static=True)  # fmt: skip
    joints = poses.arm[:, 1:-1].reshape(-1, 3)
    rec.send_columns(f"{entity}/arm/joints", times, rr.Points3D.columns(
        positions=joints).partition(np.full(n, poses.arm.shape[1] - 2)))  # fmt: skip
    rec.log(f"{entity}/arm/joints", rr.Points3D.from_fields(colors=JOINT, radii=0.016),
            static=True)  # fmt: skip
    fingers = poses.fingers.reshape(-1, 4, 3)
    rec.send_columns(
        f"{entity}/arm/fingers",
        times,
        rr.LineStrips3D.columns(strips=list(fingers)).partition(np.full(n, 2)),
    )
    rec.log(f"{entity}/arm/fingers", rr.LineStrips3D.from_fields(colors=JOINT, radii=0.005),
            static=True)  # fmt: skip
    rec.send_columns(
        f"{entity}/arm/pinch", times, rr.Points3D.columns(positions=poses.arm[:, -1]).partition(one)
    )
    rec.log(f"{entity}/arm/pinch", rr.Points3D.from_fields(colors=AGENT, radii=0.009),
            static=True)  # fmt: skip
    for name, (pos, quat) in poses.bodies.items():
        rec.send_columns(f"{entity}/scene/{name}", times,
                         rr.Transform3D.columns(translation=pos, quaternion=quat))  # fmt: skip


def log_cubes(
    rec: rr.RecordingStream,
    spec: ManipSpaceSpec,
    observations: np.ndarray,
    times: list[rr.TimeColumn],
    entity: str = "world/cubes",
) -> np.ndarray:
    """Solid cubes, turned as observed, at every step; returns their centres `[n, n_cubes, 3]`."""
    k = spec.n_cubes
    obs = np.asarray(observations, dtype=np.float64)
    centres = spec.observed_cubes(obs)
    cols = [PROPRIO_DIM + CUBE_DIM * i + 3 + j for i in range(k) for j in (1, 2, 3, 0)]
    quats = obs[:, cols].reshape(-1, 4)  # w x y z -> x y z w
    rec.send_columns(
        entity,
        times,
        rr.Boxes3D.columns(centers=centres.reshape(-1, 3), quaternions=quats).partition(
            np.full(len(obs), k)
        ),
    )
    rec.log(entity, rr.Boxes3D.from_fields(
        half_sizes=[[CUBE_HALF] * 3] * k, colors=[cube_color(i) for i in range(k)],
        fill_mode="solid", labels=[f"cube {i}" for i in range(k)], show_labels=True,
    ), static=True)  # fmt: skip
    return centres


def log_goals(
    rec: rr.RecordingStream,
    goal_cubes: np.ndarray,
    entity: str = "world/goals",
    static: bool = True,
) -> None:
    """Each cube's goal `[n_cubes, 3]` (m) as a wire box of the success tolerance, its colour."""
    k = len(goal_cubes)
    rec.log(
        entity,
        rr.Boxes3D(
            centers=goal_cubes,
            half_sizes=[[SUCCESS_TOLERANCE] * 3] * k,
            colors=[cube_color(i) for i in range(k)],
            radii=0.0025,
            labels=[f"goal of cube {i}" for i in range(k)],
            show_labels=True,
        ),
        static=static,
    )


def log_to_goal(
    rec: rr.RecordingStream,
    cubes: np.ndarray,
    goal_cubes: np.ndarray,
    times: list[rr.TimeColumn],
    entity: str = "world/to_goal",
) -> None:
    """A thin line from each cube `[n, k, 3]` to its goal `[k, 3]` at every step."""
    n, k = cubes.shape[:2]
    strips = np.stack([cubes, np.broadcast_to(goal_cubes, cubes.shape)], axis=2)  # [n, k, 2, 3]
    rec.send_columns(entity, times, rr.LineStrips3D.columns(
        strips=list(strips.reshape(-1, 2, 3))).partition(np.full(n, k)))  # fmt: skip
    rec.log(entity, rr.LineStrips3D.from_fields(
        colors=[(*cube_color(i), 150) for i in range(k)], radii=0.0015), static=True)  # fmt: skip


def log_buttons(
    rec: rr.RecordingStream,
    spec: ManipSpaceSpec,
    observations: np.ndarray,
    tops: np.ndarray,
    times: list[rr.TimeColumn],
    entity: str = "world/buttons",
) -> None:
    """The buttons' caps (a puzzle's or the scene's) at every step: solid boxes at their tops
    `[n, n_buttons, 3]` (as pressed) in the colour of the state each observation shows."""
    n, k = tops.shape[:2]
    centres = tops - [0.0, 0.0, BUTTON_CAP[2]]
    colors = button_colors(observed_buttons(spec, observations), button_on_color(spec))
    rec.send_columns(
        entity,
        times,
        rr.Boxes3D.columns(centers=centres.reshape(-1, 3), colors=colors.reshape(-1, 3))
        .partition(np.full(n, k)),
    )  # fmt: skip
    rec.log(entity, rr.Boxes3D.from_fields(half_sizes=[BUTTON_CAP] * k, fill_mode="solid"),
            static=True)  # fmt: skip


def button_rest_tops(spec: ManipSpaceSpec) -> np.ndarray:
    """`[n_buttons, 3]` each button's top (site `btntop_<i>`) unpressed (m)."""
    data = mujoco.MjData(spec.model)
    mujoco.mj_kinematics(spec.model, data)
    return np.array([data.site_xpos[spec.model.site(f"btntop_{i}").id]
                     for i in range(spec.n_buttons)])  # fmt: skip


def log_button_goals(
    rec: rr.RecordingStream,
    spec: ManipSpaceSpec,
    goal_states: np.ndarray,
    entity: str = "world/button_goals",
    static: bool = True,
) -> None:
    """Each button's goal state `[n_buttons]` as a wire box around its cap in the goal state's
    colour."""
    tops = button_rest_tops(spec)
    rec.log(
        entity,
        rr.Boxes3D(
            centers=tops - [0.0, 0.0, BUTTON_CAP[2]],
            half_sizes=[BUTTON_GOAL] * len(tops),
            colors=button_colors(goal_states, button_on_color(spec)),
            radii=0.002,
        ),
        static=static,
    )


def button_legend(spec: ManipSpaceSpec, goals: bool = True) -> list[tuple[str, Color, Any]]:
    """Legend items of the buttons (and their goal states), in the env's colours."""
    on = button_on_color(spec)
    off_label, on_label = ("locked", "unlocked") if spec.scene else ("off", "on")
    items: list[tuple[str, Color, Any]] = [(f"button {off_label} (0)", BUTTON_OFF, "dot"),
                                           (f"button {on_label} (1)", on, "dot")]  # fmt: skip
    if goals:
        items += [(f"goal: {off_label}", BUTTON_OFF, "ring"), (f"goal: {on_label}", on, "ring")]
    return items


LEGEND_STEP = 0.1  # between items, in the legend view's units (its bounds follow)


def log_manip_legend(
    rec: rr.RecordingStream, items: Sequence[tuple[str, Color, Any]], entity: str = "legend"
) -> None:
    """A column of `(label, colour, marker)` items ("dot", "line" or "ring") for `legend_view`,
    one entity `entity/<k>` each, its label just under it (Rerun centres a label on its point)."""
    r = 0.012
    for k, (label, color, marker) in enumerate(items):
        at = np.array([0.0, LEGEND_STEP * (k + 0.3)])
        if marker == "dot":
            item: Any = rr.Points2D([at], radii=r, colors=color)
        elif marker == "ring":
            item = rr.Ellipses2D(centers=[at], half_sizes=[[1.3 * r] * 2], colors=color,
                                 line_radii=0.3 * r)  # fmt: skip
        else:
            item = rr.LineStrips2D([[at - [3 * r, 0], at + [3 * r, 0]]], colors=color,
                                   radii=0.35 * r)  # fmt: skip
        rec.log(f"{entity}/{k}", item, static=True)
        rec.log(
            f"{entity}/{k}/label",
            rr.Points2D([at + [0, 0.027]], radii=1e-4, colors=text_color(color), labels=label,
                        show_labels=True),
            static=True,
        )  # fmt: skip


def legend_view(n_items: int, entity: str = "legend") -> rrb.Spatial2DView:
    """A narrow, tall 2-D view that holds just the legend (a column beside the 3-D view)."""
    return rrb.Spatial2DView(
        name="legend",
        origin="/",
        contents=[f"/{entity}/**"],
        visual_bounds=rrb.VisualBounds2D(
            x_range=[-0.1, 0.1], y_range=[0.0, LEGEND_STEP * max(n_items, 6)]
        ),
        background=(250, 250, 250),
    )


def robot_legend(n_cubes: int) -> list[tuple[str, Color, Any]]:
    """Legend items of the robot, the cubes and their goals."""
    items: list[tuple[str, Color, Any]] = [
        ("arm (UR5e links)", ARM, "line"),
        ("pinch site", AGENT, "dot"),
    ]
    for i in range(n_cubes):
        items += [(f"cube {i}", cube_color(i), "dot"), (f"goal of cube {i}", cube_color(i), "ring")]
    return items


def workspace_view(name: str, contents: Sequence[str] | str, origin: str = "/world"):
    """A 3-D view looking at the table from the front right, slightly above, the arm's base in
    the frame; z up."""
    return rrb.Spatial3DView(
        name=name,
        origin=origin,
        contents=contents,
        eye_controls=rrb.EyeControls3D(
            kind=rrb.Eye3DKind.Orbital,
            position=[1.25, -0.75, 0.75],
            look_target=[0.33, 0.0, 0.08],
            eye_up=[0.0, 0.0, 1.0],
        ),
        background=(235, 236, 240),
        line_grid=rrb.LineGrid3D(visible=False),
    )
