"""One Rerun recording (.rrd) per deployed episode: the maze, the task, the executed path, every
replan's predicted plan (paper fig. 10: the TAWM's skill ends as green dots, LLP's per-action
prediction in pink) and per-step scalars, with the outcome in words.

Timelines: `step` (control steps) and `sim_time` (simulated seconds). Per-step data goes in with
`send_columns`, one call per entity for the whole episode, so writing every episode stays cheap
(a few hundred KB and a few ms each). The file embeds a default blueprint: the map (right way up,
legend beside it) on the left; the outcome, distance to goal, plan cost and actions on the right,
the plots on one linked time axis. It opens at the episode's end.
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
from pipeline.viz.maze import (
    AGENT,
    GOAL,
    LLP_PLAN,
    ORDER_AGENT,
    ORDER_GOAL,
    ORDER_MARKER,
    ORDER_PLAN,
    ORDER_TRACE,
    OUTLINE,
    PATH,
    PLAN,
    START,
    WAYPOINT,
    faded,
    log_legend,
    log_maze,
    map_view,
    to_view,
    unit,
)

APPLICATION_ID = "oposm-deploy"
ACTION_COLORS = [(50, 100, 200), (230, 130, 20), (120, 120, 120), (150, 80, 200)]
RADIUS_LINE = (130, 130, 130)
PATH_UPDATES = 80  # the path so far is re-logged about this often per episode (and at replans)


def application_id(result: EpisodeResult) -> str:
    """`oposm-deploy-<agent>`: the viewer keeps one layout per application id, and agents that do
    not plan have no plan cost plot; the recordings panel groups each agent's episodes."""
    return f"{APPLICATION_ID}-{result.agent}" if result.agent else APPLICATION_ID


def recording_name(result: EpisodeResult) -> str:
    """`<agent>-<task>-<episode>` (`<task>-<episode>` without an agent name), the recording id
    and file stem."""
    name = f"{result.spec.task}-{result.spec.index:04d}"
    return f"{result.agent}-{name}" if result.agent else name


def _plan_style(result: EpisodeResult) -> tuple[tuple[int, ...], float, str]:
    """Colour, dot radius and name of the plan's predicted states."""
    if result.agent == "llp":  # a state per action (dozens, close together): fig. 10's pink
        return LLP_PLAN, 0.03, "predicted path (single-step model)"
    return PLAN, 0.075, "predicted skill ends (TAWM)"


def _linked(name: str, contents: str | list[str]) -> rrb.TimeSeriesView:
    return rrb.TimeSeriesView(
        name=name,
        contents=contents,
        axis_x=rrb.TimeAxis(link="LinkToGlobal"),
        plot_legend=rrb.PlotLegend(corner="RightTop"),
    )


def deploy_blueprint(layout: dict[str, Any], plans: bool = True) -> rrb.Blueprint:
    """Map (3/5 of the width) beside the outcome and the plots (plan cost only when the agent
    plans); time panel on simulated seconds, at the episode's end."""
    plots = [
        rrb.TextDocumentView(name="outcome", contents="/summary"),
        _linked("distance to goal (m)", ["/metrics/distance_to_goal", "/metrics/success_radius"]),
        *([_linked("plan cost at each replan", "/metrics/plan_cost")] if plans else []),
        _linked("actions", "/metrics/action/**"),
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            map_view(layout, "maze", ["/task/**", "/agent/**", "/plan/**"]),
            rrb.Vertical(*plots, row_shares=[2] + [3] * (len(plots) - 1)),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="sim_time", play_state="following", state="collapsed"),
        rrb.BlueprintPanel(state="expanded"),  # lists the recordings: the other episodes
        rrb.SelectionPanel(state="collapsed"),
    )


def _times(steps: np.ndarray, dt: float) -> list[rr.TimeColumn]:
    return [rr.TimeColumn("step", sequence=steps), rr.TimeColumn("sim_time", duration=steps * dt)]


def _set_time(rec: rr.RecordingStream, t: int, dt: float) -> None:
    rec.set_time("step", sequence=t)
    rec.set_time("sim_time", duration=t * dt)


def _log_task(
    rec: rr.RecordingStream, result: EpisodeResult, pos: list[int], radius: float, u: float = 1.0
) -> None:
    spec = result.spec
    start, goal = to_view(spec.start[pos]), to_view(spec.goal)
    rec.log(
        "task/start",
        rr.Points2D([start], radii=0.1 * u, colors=START, draw_order=ORDER_MARKER),
        static=True,
    )
    rec.log(
        "task/goal",
        rr.Points2D([goal], radii=0.05 * u, colors=GOAL, draw_order=ORDER_GOAL),
        static=True,
    )
    rec.log(
        "task/goal_region",
        rr.Ellipses2D(
            centers=[goal],
            half_sizes=[[radius, radius]],
            line_radii=0.03 * u,
            colors=GOAL,
            draw_order=ORDER_GOAL,
        ),
        static=True,
    )


def _log_agent(
    rec: rr.RecordingStream,
    result: EpisodeResult,
    pos: list[int],
    dt: float,
    radius: float,
    u: float = 1.0,
) -> None:
    """The agent (a dot with a dark rim, at every step), the path so far, the scalars."""
    trace = result.trace
    states = np.asarray(trace.states)  # [n + 1, sd]
    steps = np.arange(len(states))
    xy = to_view(states[:, pos])
    rec.send_columns(
        "agent/position",
        indexes=_times(steps, dt),
        columns=rr.Points2D.columns(positions=np.repeat(xy, 2, axis=0)).partition(
            np.full(len(steps), 2)
        ),
    )
    rec.log(
        "agent/position",
        rr.Points2D.from_fields(
            colors=[OUTLINE, AGENT], radii=[0.13 * u, 0.1 * u], draw_order=ORDER_AGENT
        ),
        static=True,
    )
    # The path so far, every few steps and at each replan (every step would be O(n^2) points).
    every = max(1, len(steps) // PATH_UPDATES)
    at = sorted({*range(0, len(steps), every), *trace.replan_steps, len(steps) - 1})
    rec.send_columns(
        "agent/path",
        indexes=_times(np.asarray(at), dt),
        columns=rr.LineStrips2D.columns(strips=[xy[: t + 1] for t in at]),
    )
    rec.log(
        "agent/path",
        rr.LineStrips2D.from_fields(colors=PATH, radii=0.025 * u, draw_order=ORDER_TRACE),
        static=True,
    )
    distance = np.linalg.norm(states[:, pos] - result.spec.goal, axis=1)
    metrics = {
        "distance_to_goal": (distance, GOAL, "distance to goal"),
        "success_radius": (np.full(len(steps), radius), RADIUS_LINE, f"success radius {radius} m"),
    }
    for name, (values, color, label) in metrics.items():
        rec.log(f"metrics/{name}", rr.SeriesLines(colors=color, names=label), static=True)
        rec.send_columns(f"metrics/{name}", _times(steps, dt), rr.Scalars.columns(scalars=values))
    if trace.actions:
        actions = np.asarray(trace.actions)
        dims = actions.shape[1]
        names = ["fx", "fy"] if dims == 2 else [f"a{k}" for k in range(dims)]
        for k, name in enumerate(names):
            style = rr.SeriesLines(colors=ACTION_COLORS[k % len(ACTION_COLORS)], names=name)
            rec.log(f"metrics/action/{name}", style, static=True)
            rec.send_columns(
                f"metrics/action/{name}",
                _times(steps[:-1], dt),
                rr.Scalars.columns(scalars=actions[:, k]),
            )


def _log_plans(
    rec: rr.RecordingStream, result: EpisodeResult, pos: list[int], dt: float, u: float = 1.0
) -> None:
    """At each replan: the new plan bright, labelled with its number; the earlier ones faded."""
    trace = result.trace
    if not trace.plans:
        return
    color, radius, _ = _plan_style(result)
    radius *= u
    rec.log(
        "metrics/plan_cost",
        rr.SeriesPoints(colors=color, names="predicted cost", markers="Circle", marker_sizes=4.0),
        static=True,
    )
    earlier: list[np.ndarray] = []
    for k, (t, plan, cost) in enumerate(
        zip(trace.replan_steps, trace.plans, trace.plan_costs, strict=True)
    ):
        _set_time(rec, t, dt)
        xy = to_view(plan[:, pos])
        labels = [""] * (len(xy) - 2) + [f"plan {k + 1}"]
        rec.log(
            "plan/states",
            rr.Points2D(xy[1:], radii=radius, colors=color, labels=labels, draw_order=ORDER_PLAN),
        )
        rec.log(
            "plan/path",
            rr.LineStrips2D([xy], radii=0.012 * u, colors=(*color, 160), draw_order=ORDER_PLAN),
        )
        if earlier:
            rec.log(
                "plan/earlier",
                rr.Points2D(
                    np.concatenate(earlier),
                    radii=0.6 * radius,
                    colors=faded(color),
                    draw_order=ORDER_PLAN - 1,
                ),
            )
        earlier.append(xy[1:])
        if trace.plan_targets:  # deploy.subgoals: the waypoint this plan aimed at
            at = to_view(trace.plan_targets[k][None])
            rec.log("plan/waypoint", rr.Points2D(at, radii=1.6 * radius, colors=WAYPOINT,
                                                 draw_order=ORDER_PLAN + 1))  # fmt: skip
        if np.isfinite(cost):
            rec.log("metrics/plan_cost", rr.Scalars(cost))


def _outcome(result: EpisodeResult, dt: float) -> str:
    if result.error is not None:
        return f"failed after {result.steps} steps: {result.error}"
    if result.success:
        return (
            f"reached the goal in {result.steps_to_goal} steps ({result.steps_to_goal * dt:.2f} s)"
        )
    return (
        f"did not reach the goal in {result.steps} steps "
        f"(closest {result.min_distance:.2f} m, final {result.final_distance:.2f} m)"
    )


def _summary(result: EpisodeResult, pos: list[int], dt: float) -> str:
    """Markdown: the outcome as a heading, then the task, start, goal, seed and planning."""
    spec = result.spec

    def xy(v: np.ndarray) -> str:
        return "({:.2f}, {:.2f})".format(*np.asarray(v, dtype=float)[:2])

    agent = f"**{result.agent}**, " if result.agent else ""
    return (
        f"### {_outcome(result, dt)}\n\n"
        f"- {agent}task **{spec.task}**, episode {spec.index}, seed {spec.seed}\n"
        f"- start {xy(spec.start[pos])} m → goal {xy(spec.goal)} m\n"
        f"- {f'{result.replans} replans; ' if result.replans else ''}"
        f"closest to the goal {result.min_distance:.2f} m\n"
    )


def _legend(result: EpisodeResult) -> list[tuple[str, tuple[int, ...], Any]]:
    items: list[tuple[str, tuple[int, ...], Any]] = [
        ("start", START, "dot"),
        ("goal region", GOAL, "ring"),
        ("agent", AGENT, "dot"),
        ("executed path", PATH, "line"),
    ]
    if result.trace.plans:
        color, _, name = _plan_style(result)
        items += [(name, color, "dot"), ("earlier plans", faded(color), "dot")]
    if result.trace.plan_targets:
        items.append(("waypoint (subgoals)", WAYPOINT, "dot"))
    return items


def write_episode_recording(
    path: str | Path,
    result: EpisodeResult,
    env: EnvSpec,
    success_radius: float = 0.5,
) -> None:
    """Write one episode's recording to `path` (atomically) with the deploy blueprint: the maze
    `env.layout`, positions = the state dims `env.goal_dims`, time in steps of `env.dt`."""
    pos, dt = list(env.goal_dims), env.dt
    rec = rr.RecordingStream(application_id(result), recording_id=recording_name(result))
    blueprint = deploy_blueprint(env.layout, plans=bool(result.trace.plans))
    with atomic_path(path) as tmp:
        try:  # the file is closed before it is renamed into place, or removed after an error
            rec.save(tmp, default_blueprint=blueprint)
            rec.send_recording_name(recording_name(result))
            log_maze(rec, env.layout)
            log_legend(rec, env.layout, _legend(result))
            u = unit(env.layout)
            _log_task(rec, result, pos, success_radius, u)
            rec.log(
                "summary",
                rr.TextDocument(_summary(result, pos, dt), media_type="text/markdown"),
                static=True,
            )
            _log_agent(rec, result, pos, dt, success_radius, u)
            _log_plans(rec, result, pos, dt, u)
            rec.flush()
        finally:
            rec.disconnect()
