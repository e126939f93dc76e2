"""One Rerun recording (.rrd) per deployed episode: the maze, the task, the executed path, every
replan's skill sequence as the TAWM predicted it (paper fig. 10's green dots) and per-step scalars.

Timelines: `step` (control steps) and `sim_time` (simulated seconds). Per-step data goes in with
`send_columns`, one call per entity for the whole episode, so writing every episode stays cheap
(about 100 KB and a few ms each). The file embeds a default blueprint: the map on the left, distance
to goal / plan cost / actions plotted on the right.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.envs.spec import EnvSpec
from pipeline.evaluation.episodes import EpisodeResult
from pipeline.io import atomic_path
from pipeline.viz.maze import log_maze

APPLICATION_ID = "oposm-deploy"
START_COLOR = (70, 130, 255)
GOAL_COLOR = (230, 60, 60)
AGENT_COLOR = (250, 200, 40)
PATH_COLOR = (200, 40, 40)  # the executed path: fig. 10's red lines
PLAN_COLOR = (40, 200, 80)  # predicted states of the plan: fig. 10's green dots
LLP_PLAN_COLOR = (255, 80, 200)  # LLP's predicted low-level path: fig. 10's pink lines


def recording_name(result: EpisodeResult) -> str:
    """`<agent>-<task>-<episode>` (`<task>-<episode>` without an agent name), the recording id
    and file stem."""
    name = f"{result.spec.task}-{result.spec.index:04d}"
    return f"{result.agent}-{name}" if result.agent else name


def deploy_blueprint(layout: dict[str, Any]) -> rrb.Blueprint:
    """Map (3/5 of the width) beside three stacked plots, time panel on simulated seconds."""
    xmin, xmax, ymin, ymax = layout["bounds"]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(
                name="maze",
                origin="/",
                contents=["/maze/**", "/task/**", "/agent/**", "/plan/**"],
                visual_bounds=rrb.VisualBounds2D(x_range=[xmin, xmax], y_range=[ymin, ymax]),
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(
                    name="distance to goal (m)",
                    origin="/metrics",
                    contents=["/metrics/distance_to_goal", "/metrics/success_radius"],
                ),
                rrb.TimeSeriesView(
                    name="plan cost (predicted distance, m)", contents="/metrics/plan_cost"
                ),
                rrb.TimeSeriesView(name="actions", contents="/metrics/action/**"),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="sim_time"),
        collapse_panels=True,
    )


def _times(steps: np.ndarray, dt: float) -> list[rr.TimeColumn]:
    return [rr.TimeColumn("step", sequence=steps), rr.TimeColumn("sim_time", duration=steps * dt)]


def _log_task(
    rec: rr.RecordingStream, result: EpisodeResult, pos: list[int], radius: float
) -> None:
    spec = result.spec
    rec.log(
        "task/start", rr.Points2D([spec.start[pos]], radii=0.08, colors=START_COLOR), static=True
    )
    rec.log("task/goal", rr.Points2D([spec.goal], radii=0.08, colors=GOAL_COLOR), static=True)
    rec.log(
        "task/goal_region",
        rr.Points2D([spec.goal], radii=radius, colors=(*GOAL_COLOR, 50), draw_order=1.0),
        static=True,
    )


def _log_agent(
    rec: rr.RecordingStream, result: EpisodeResult, pos: list[int], dt: float, radius: float
) -> None:
    trace = result.trace
    states = np.asarray(trace.states)  # [n + 1, sd]
    steps = np.arange(len(states))
    positions = states[:, pos]
    rec.send_columns(
        "agent/position",
        indexes=_times(steps, dt),
        columns=rr.Points2D.columns(positions=positions, radii=np.full(len(steps), 0.1)),
    )
    rec.log("agent/position", rr.Points2D.from_fields(colors=AGENT_COLOR), static=True)
    distance = np.linalg.norm(positions - result.spec.goal, axis=1)
    rec.send_columns(
        "metrics/distance_to_goal", _times(steps, dt), rr.Scalars.columns(scalars=distance)
    )
    rec.send_columns(
        "metrics/success_radius",
        _times(steps, dt),
        rr.Scalars.columns(scalars=np.full(len(steps), radius)),
    )
    if trace.actions:
        actions = np.asarray(trace.actions)
        for k, name in enumerate(("fx", "fy")[: actions.shape[1]]):
            rec.send_columns(
                f"metrics/action/{name}",
                _times(steps[:-1], dt),
                rr.Scalars.columns(scalars=actions[:, k]),
            )
    # The path so far, at every replan and at the end (not every step: that would be O(n^2)).
    for t in [*trace.replan_steps, len(states) - 1]:
        rec.set_time("step", sequence=t)
        rec.set_time("sim_time", duration=t * dt)
        rec.log("agent/path", rr.LineStrips2D([positions[: t + 1]], colors=PATH_COLOR, radii=0.02))


def _log_plans(rec: rr.RecordingStream, result: EpisodeResult, pos: list[int], dt: float) -> None:
    trace = result.trace
    for t, plan, cost in zip(trace.replan_steps, trace.plans, trace.plan_costs, strict=True):
        rec.set_time("step", sequence=t)
        rec.set_time("sim_time", duration=t * dt)
        xy = plan[:, pos]
        # LLP predicts a state per action (dozens, close together), OPOSM one per skill.
        color, radius = (LLP_PLAN_COLOR, 0.03) if result.agent == "llp" else (PLAN_COLOR, 0.07)
        rec.log("plan/states", rr.Points2D(xy[1:], radii=radius, colors=color))
        rec.log("plan/path", rr.LineStrips2D([xy], radii=0.015, colors=(*color, 140)))
        if np.isfinite(cost):
            rec.log("metrics/plan_cost", rr.Scalars(cost))


def _summary(result: EpisodeResult, pos: list[int], dt: float) -> str:
    spec = result.spec
    if result.error is not None:
        outcome = f"failed: {result.error}"
    elif result.success:
        outcome = f"reached the goal in {result.steps_to_goal} steps"
        outcome += f" ({result.steps_to_goal * dt:.2f} s)"
    else:
        outcome = f"did not reach the goal in {result.steps} steps"
        outcome += f" (closest {result.min_distance:.2f} m)"
    return (
        (f"{result.agent}: " if result.agent else "")
        + f"task {spec.task}, episode {spec.index} (seed {spec.seed}): start "
        f"{np.round(spec.start[pos], 2).tolist()}, goal {np.round(spec.goal, 2).tolist()}; "
        f"{outcome}; {result.replans} replans"
    )


def write_episode_recording(
    path: str | Path,
    result: EpisodeResult,
    env: EnvSpec,
    success_radius: float = 0.5,
) -> None:
    """Write one episode's recording to `path` (atomically) with the deploy blueprint: the maze
    `env.layout`, positions = the state dims `env.goal_dims`, time in steps of `env.dt`."""
    pos, dt = list(env.goal_dims), env.dt
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_name(result))
    with atomic_path(path) as tmp:
        try:  # the file is closed before it is renamed into place, or removed after an error
            rec.save(tmp, default_blueprint=deploy_blueprint(env.layout))
            rec.send_recording_name(recording_name(result))
            log_maze(rec, env.layout)
            _log_task(rec, result, pos, success_radius)
            rec.log("summary", rr.TextDocument(_summary(result, pos, dt)), static=True)
            _log_agent(rec, result, pos, dt, success_radius)
            _log_plans(rec, result, pos, dt)
            rec.flush()
        finally:
            rec.disconnect()
