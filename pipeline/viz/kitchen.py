"""Rerun recordings of deployed episodes in the Franka kitchen (`pipeline.envs.kitchen`).

An episode's recording: a 3-D view of the robot and the kitchen as a skeleton of body origins
(MuJoCo's kinematics of the observed joints; metres, z up) at every step, the kettle's goal
position when the kettle is a subtask, and the path of the robot's hand so far; on the right the
outcome in words (each subtask's first completion, D4RL's score), each subtask's distance to its
goal in units of the env's threshold (0.3: below 1 is complete) with the threshold line, the
number of subtasks completed so far, the plan cost at each replan and the actions. Timelines
`step` and `sim_time`, as the other envs' recordings. The run overview is the manipulation
envs' (`pipeline.viz.manip.write_manip_overview`): success table and bars per task.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.envs.kitchen import BONUS_THRESH, OBS_ELEMENT_INDICES, KitchenSpec
from pipeline.evaluation.episodes import EpisodeResult
from pipeline.io import atomic_path
from pipeline.viz.deploy import ACTION_COLORS, RADIUS_LINE, application_id, recording_name
from pipeline.viz.maze import GOAL, LLP_PLAN, PATH, PLAN

BODY = (90, 90, 100)
HAND_BODY = "panda0_link7"  # the last arm link: the hand's path
SUBTASK_COLORS = [(50, 100, 200), (230, 130, 20), (20, 150, 60), (200, 30, 170), (120, 120, 120),
                  (150, 80, 200), (0, 170, 200)]  # fmt: skip


def _times(steps: np.ndarray, dt: float) -> list[rr.TimeColumn]:
    return [rr.TimeColumn("step", sequence=steps), rr.TimeColumn("sim_time", duration=steps * dt)]


def body_positions(spec: KitchenSpec, states: np.ndarray) -> np.ndarray:
    """`[n, nbody, 3]` every body's origin (m) in observations `[n, 59]` (MuJoCo kinematics)."""
    data = mujoco.MjData(spec.model)
    out = np.empty((len(states), spec.model.nbody, 3))
    for i, state in enumerate(np.asarray(states, dtype=np.float64)):
        spec.set_observation(data, state)
        mujoco.mj_kinematics(spec.model, data)
        out[i] = data.xpos
    return out


def subtask_distances(spec: KitchenSpec, states: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """`[n, K]` each subtask's element distance to its goal over the env's threshold (0.3)."""
    diff = np.asarray(states)[:, list(spec.goal_dims)] - np.asarray(goal)
    out, start = [], 0
    for t in spec.subtasks:
        width = len(OBS_ELEMENT_INDICES[t])
        out.append(np.linalg.norm(diff[:, start : start + width], axis=1) / BONUS_THRESH)
        start += width
    return np.stack(out, axis=1)


def _summary(result: EpisodeResult, spec: KitchenSpec) -> str:
    r, s = result, result.spec
    if r.error is not None:
        outcome = f"failed after {r.steps} steps"
    elif r.success:
        outcome = f"completed every subtask in {r.steps_to_goal} steps"
    else:
        outcome = f"did not complete every subtask in {r.steps} steps"
    done = r.subtasks_done or [None] * len(spec.subtasks)
    lines = [
        f"### {r.agent + ': ' if r.agent else ''}{outcome}",
        "",
        f"- {spec.env_id} **{s.task}**, episode {s.index}, seed {s.seed}, {r.replans} replans",
        f"- D4RL score: {r.score if r.score is not None else 0.0:.2f} "
        f"({sum(d is not None for d in done)} of {len(done)} subtasks)",
    ]
    if r.error is not None:
        lines.append(f"- error: {r.error}")
    for t, step in zip(spec.subtasks, done, strict=True):
        lines.append(f"- {t}: " + (f"complete at step {step}" if step else "not completed"))
    return "\n".join(lines) + "\n"


def _blueprint(plans: bool) -> rrb.Blueprint:
    def linked(name: str, contents: str | list[str]) -> rrb.TimeSeriesView:
        return rrb.TimeSeriesView(
            name=name,
            contents=contents,
            axis_x=rrb.TimeAxis(link="LinkToGlobal"),
            plot_legend=rrb.PlotLegend(corner="RightTop"),
        )

    plots = [
        rrb.TextDocumentView(name="outcome", contents="/summary"),
        linked("distance to goal (thresholds: < 1 is complete)", "/metrics/distance/**"),
        linked("subtasks completed", "/metrics/completed"),
        *([linked("plan cost at each replan", "/metrics/plan_cost")] if plans else []),
        linked("actions", "/metrics/action/**"),
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="kitchen (m, z up)", origin="/world", contents="/world/**"),
            rrb.Vertical(*plots, row_shares=[3] + [2] * (len(plots) - 1)),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="sim_time", play_state="following", state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


def _log_states(rec: rr.RecordingStream, result: EpisodeResult, spec: KitchenSpec) -> None:
    states = np.asarray(result.trace.states)  # [n + 1, 59]
    steps = np.arange(len(states))
    times = _times(steps, spec.dt)
    model = spec.model
    xpos = body_positions(spec, states)
    links = [(int(model.body_parentid[b]), b) for b in range(1, model.nbody)]
    links = [(p, b) for p, b in links if p > 0]  # not from the world's origin
    rec.log("world/bodies", rr.LineStrips3D.from_fields(colors=BODY, radii=0.006), static=True)
    rec.send_columns(
        "world/bodies",
        indexes=times,
        columns=rr.LineStrips3D.columns(
            strips=[xpos[i, [p, b]] for i in range(len(states)) for p, b in links]
        ).partition([len(links)] * len(states)),
    )
    hand = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, HAND_BODY)
    if hand >= 0:
        path = xpos[:, hand]
        rec.log(
            "world/hand_path", rr.LineStrips3D.from_fields(colors=PATH, radii=0.004), static=True
        )
        rec.send_columns(
            "world/hand_path",
            indexes=times,
            columns=rr.LineStrips3D.columns(strips=[path[: t + 1] for t in steps]),
        )
    distances = subtask_distances(spec, states, result.spec.goal)
    for k, t in enumerate(spec.subtasks):
        entity = f"metrics/distance/{t.replace(' ', '_')}"
        color = SUBTASK_COLORS[k % len(SUBTASK_COLORS)]
        rec.log(entity, rr.SeriesLines(colors=color, names=t), static=True)
        rec.send_columns(entity, times, rr.Scalars.columns(scalars=distances[:, k]))
    rec.log("metrics/distance/threshold", rr.SeriesLines(colors=RADIUS_LINE, names="threshold"),
            static=True)  # fmt: skip
    rec.send_columns(
        "metrics/distance/threshold", times, rr.Scalars.columns(scalars=np.ones(len(steps)))
    )
    done = result.subtasks_done or []
    completed = np.array([sum(d is not None and d <= s for d in done) for s in steps], float)
    rec.log("metrics/completed", rr.SeriesLines(colors=GOAL, names="completed"), static=True)
    rec.send_columns("metrics/completed", times, rr.Scalars.columns(scalars=completed))
    if result.trace.actions:
        actions = np.asarray(result.trace.actions)
        for k in range(actions.shape[1]):
            entity = f"metrics/action/a{k}"
            style = rr.SeriesLines(colors=ACTION_COLORS[k % len(ACTION_COLORS)], names=f"a{k}")
            rec.log(entity, style, static=True)
            rec.send_columns(
                entity, _times(steps[:-1], spec.dt), rr.Scalars.columns(scalars=actions[:, k])
            )


def _log_plans(rec: rr.RecordingStream, result: EpisodeResult, spec: KitchenSpec) -> None:
    trace = result.trace
    if not trace.plans:
        return
    color = LLP_PLAN if result.agent == "llp" else PLAN
    rec.log(
        "metrics/plan_cost",
        rr.SeriesPoints(colors=color, names="predicted cost", markers="Circle", marker_sizes=4.0),
        static=True,
    )
    for t, cost in zip(trace.replan_steps, trace.plan_costs, strict=True):
        rec.set_time("step", sequence=t)
        rec.set_time("sim_time", duration=t * spec.dt)
        if np.isfinite(cost):
            rec.log("metrics/plan_cost", rr.Scalars(cost))


def write_kitchen_episode_recording(
    path: str | Path, result: EpisodeResult, spec: KitchenSpec
) -> None:
    """Write one kitchen episode's recording to `path`, atomically (module docstring)."""
    rec = rr.RecordingStream(application_id(result), recording_id=recording_name(result))
    with atomic_path(path) as tmp:
        try:  # the file is closed before it is renamed into place, or removed after an error
            rec.save(tmp, default_blueprint=_blueprint(bool(result.trace.plans)))
            rec.send_recording_name(recording_name(result))
            rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
            if "kettle" in spec.subtasks:  # its goal position (the free joint's x, y, z)
                start = sum(len(OBS_ELEMENT_INDICES[t]) for t in spec.subtasks[:-1])
                kettle = np.asarray(result.spec.goal)[start : start + 3]
                rec.log("world/kettle_goal", rr.Points3D([kettle], radii=0.03, colors=GOAL),
                        static=True)  # fmt: skip
            rec.log(
                "summary",
                rr.TextDocument(_summary(result, spec), media_type="text/markdown"),
                static=True,
            )
            _log_states(rec, result, spec)
            _log_plans(rec, result, spec)
            rec.flush()
        finally:
            rec.disconnect()
