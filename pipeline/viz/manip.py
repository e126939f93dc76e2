"""Rerun recordings of deployed episodes in OGBench's manipulation envs (cube-single, cube-double,
scene), and their run overview.

An episode's recording: a 3-D view of the workspace (its bounds as a wire box, metres, z up) with
the cubes (dots) and the pinch site (small dot, its path so far as a line) at every step, each
goal cube as a wire box of OGBench's success tolerance (0.04 m) beside them, and at every replan
the chosen plan's predicted cube and pinch positions (green for the TAWM's skill ends, pink for
LLP's actions). On the right: the outcome and the task's goal in words, the distance to the goal in
success tolerances (`pipeline.evaluation.goals`: 1 is at the tolerance), the plan cost, the
actions. Timelines `step` and `sim_time`, as the maze recordings. The scene's buttons, drawer and
window have no geometry here: their goal states and where they are at the end are in the text,
and their part of the distance is in the distance plot.

The overview holds the success table and the bar chart of the maze overview, without a map.

Validate's 3-D view is `pipeline.viz.manip_validate`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.envs.manipspace import (
    DRAWER_SCALE,
    SUCCESS_TOLERANCE,
    WINDOW_SCALE,
    WORKSPACE_BOUNDS,
    XYZ_CENTER,
    XYZ_SCALE,
    ManipSpaceSpec,
)
from pipeline.evaluation.episodes import EpisodeResult
from pipeline.evaluation.goals import GoalRule
from pipeline.io import atomic_path
from pipeline.viz.deploy import ACTION_COLORS, RADIUS_LINE, application_id, recording_name
from pipeline.viz.maze import AGENT, GOAL, LLP_PLAN, PATH, PLAN
from pipeline.viz.overview import APPLICATION_ID, RECORDING, group, log_success_bars, success_table

PINCH = slice(12, 15)  # the pinch site's position in the observation (scaled as the cubes)
CUBE_COLORS = [(230, 130, 20), (60, 120, 220)]
ACTION_NAMES = ("dx", "dy", "dz", "dyaw", "dgrip")
PATH_UPDATES = 80  # the pinch path is re-logged about this often per episode (and at replans)


def to_metres(observed: np.ndarray) -> np.ndarray:
    """Positions `[..., 3]` in observation units (`(p - [0.425, 0, 0]) * 10`) -> metres."""
    return XYZ_CENTER + np.asarray(observed, dtype=np.float64) / XYZ_SCALE


def cube_positions(states: np.ndarray, spec: ManipSpaceSpec) -> np.ndarray:
    """`[..., n_cubes, 3]` cube positions (m) from observations `[..., state_dim]`."""
    return spec.observed_cubes(states)


def _times(steps: np.ndarray, dt: float) -> list[rr.TimeColumn]:
    return [rr.TimeColumn("step", sequence=steps), rr.TimeColumn("sim_time", duration=steps * dt)]


def _colors(n_cubes: int) -> list[tuple[int, int, int]]:
    return [CUBE_COLORS[i % len(CUBE_COLORS)] for i in range(n_cubes)]


def _log_scene(rec: rr.RecordingStream, result: EpisodeResult, spec: ManipSpaceSpec) -> None:
    """The workspace bounds and the goal cubes (static)."""
    low, high = WORKSPACE_BOUNDS
    rec.log(
        "world/workspace",
        rr.Boxes3D(centers=[(low + high) / 2], half_sizes=[(high - low) / 2], colors=[RADIUS_LINE]),
        static=True,
    )
    goal_cubes = to_metres(result.spec.goal[: 3 * spec.n_cubes].reshape(spec.n_cubes, 3))
    rec.log(
        "world/goal",
        rr.Boxes3D(
            centers=goal_cubes,
            half_sizes=[[SUCCESS_TOLERANCE] * 3] * spec.n_cubes,
            colors=[GOAL] * spec.n_cubes,
            labels=[f"goal {i}" for i in range(spec.n_cubes)],
        ),
        static=True,
    )


def _log_states(
    rec: rr.RecordingStream, result: EpisodeResult, spec: ManipSpaceSpec, radius: float
) -> None:
    """Cubes and pinch site at every step, the pinch path, the per-step scalars."""
    states = np.asarray(result.trace.states)  # [n + 1, sd]
    steps = np.arange(len(states))
    n = spec.n_cubes
    cubes = cube_positions(states, spec).reshape(-1, 3)
    rec.send_columns(
        "world/cubes",
        indexes=_times(steps, spec.dt),
        columns=rr.Points3D.columns(positions=cubes).partition(np.full(len(steps), n)),
    )
    rec.log(
        "world/cubes",
        rr.Points3D.from_fields(
            colors=_colors(n), radii=0.02, labels=[f"cube {i}" for i in range(n)]
        ),
        static=True,
    )
    pinch = to_metres(states[:, PINCH])
    rec.send_columns(
        "world/pinch",
        indexes=_times(steps, spec.dt),
        columns=rr.Points3D.columns(positions=pinch).partition(np.ones(len(steps), dtype=int)),
    )
    rec.log("world/pinch", rr.Points3D.from_fields(colors=AGENT, radii=0.01), static=True)
    every = max(1, len(steps) // PATH_UPDATES)
    at = sorted({*range(0, len(steps), every), *result.trace.replan_steps, len(steps) - 1})
    rec.send_columns(
        "world/pinch_path",
        indexes=_times(np.asarray(at), spec.dt),
        columns=rr.LineStrips3D.columns(strips=[pinch[: t + 1] for t in at]),
    )
    rec.log("world/pinch_path", rr.LineStrips3D.from_fields(colors=PATH, radii=0.003), static=True)
    rule = GoalRule.of_spec(spec)
    distance = np.array([rule.distance(s, result.spec.goal) for s in states])
    metrics = {
        "distance_to_goal": (distance, GOAL, "distance to goal (tolerances)"),
        "tolerance": (np.full(len(steps), radius), RADIUS_LINE, "one tolerance"),
    }
    for name, (values, color, label) in metrics.items():
        rec.log(f"metrics/{name}", rr.SeriesLines(colors=color, names=label), static=True)
        rec.send_columns(
            f"metrics/{name}", _times(steps, spec.dt), rr.Scalars.columns(scalars=values)
        )
    if result.trace.actions:
        actions = np.asarray(result.trace.actions)
        for k, name in enumerate(ACTION_NAMES[: actions.shape[1]]):
            style = rr.SeriesLines(colors=ACTION_COLORS[k % len(ACTION_COLORS)], names=name)
            rec.log(f"metrics/action/{name}", style, static=True)
            rec.send_columns(
                f"metrics/action/{name}",
                _times(steps[:-1], spec.dt),
                rr.Scalars.columns(scalars=actions[:, k]),
            )


def _log_plans(rec: rr.RecordingStream, result: EpisodeResult, spec: ManipSpaceSpec) -> None:
    """At each replan: the plan's predicted cube and pinch positions, and its cost."""
    trace = result.trace
    if not trace.plans:
        return
    color = LLP_PLAN if result.agent == "llp" else PLAN
    rec.log(
        "metrics/plan_cost",
        rr.SeriesPoints(colors=color, names="predicted cost", markers="Circle", marker_sizes=4.0),
        static=True,
    )
    for t, plan, cost in zip(trace.replan_steps, trace.plans, trace.plan_costs, strict=True):
        rec.set_time("step", sequence=t)
        rec.set_time("sim_time", duration=t * spec.dt)
        predicted = plan[1:]  # [P, sd]: s_0 is the state planned from
        rec.log(
            "world/plan/cubes",
            rr.Points3D(cube_positions(predicted, spec).reshape(-1, 3), radii=0.008, colors=color),
        )
        rec.log(
            "world/plan/pinch",
            rr.LineStrips3D([to_metres(plan[:, PINCH])], radii=0.002, colors=(*color, 160)),
        )
        if np.isfinite(cost):
            rec.log("metrics/plan_cost", rr.Scalars(cost))


def _objects(state: np.ndarray, spec: ManipSpaceSpec) -> str:
    """The scene's buttons, drawer and window (joint positions, m) in a state `[state_dim]`."""
    if not spec.scene:
        return ""
    at = np.asarray(state)[list(spec.goal_dims[3 * spec.n_cubes :])]
    drawer, window = at[2] / DRAWER_SCALE, at[3] / WINDOW_SCALE
    return f"buttons {at[0]:.0f}, {at[1]:.0f}; drawer {drawer:.3f} m, window {window:.3f} m"


def _summary(result: EpisodeResult, spec: ManipSpaceSpec) -> str:
    """Markdown: the outcome, the task, the goal and where the objects ended."""
    r, s = result, result.spec
    if r.error is not None:
        outcome = f"failed after {r.steps} steps: {r.error}"
    elif r.success:
        outcome = f"reached the goal in {r.steps_to_goal} steps ({r.steps_to_goal * spec.dt:.2f} s)"
    else:
        outcome = (
            f"did not reach the goal in {r.steps} steps (closest {r.min_distance:.2f} "
            f"tolerances, final {r.final_distance:.2f})"
        )
    goal_cubes = to_metres(s.goal[: 3 * spec.n_cubes].reshape(spec.n_cubes, 3))
    end_cubes = cube_positions(np.asarray(r.trace.states[-1]), spec)
    lines = [
        f"### {outcome}",
        "",
        f"- **{r.agent}**, {spec.env_id} **{s.task}**, episode "
        f"{s.index}, seed {s.seed}; {r.replans} replans",
    ]
    for i, (goal, end) in enumerate(zip(goal_cubes, end_cubes, strict=True)):
        lines.append(
            f"- cube {i}: goal ({', '.join(f'{v:.3f}' for v in goal)}) m, at the end "
            f"{np.linalg.norm(end - goal):.3f} m from it (success within {SUCCESS_TOLERANCE} m)"
        )
    if spec.scene:
        goal_state = np.full(spec.state_dim, np.nan)
        goal_state[list(spec.goal_dims)] = s.goal
        lines.append(f"- goal: {_objects(goal_state, spec)}")
        lines.append(f"- at the end: {_objects(np.asarray(r.trace.states[-1]), spec)}")
    return "\n".join(lines) + "\n"


def _blueprint(plans: bool) -> rrb.Blueprint:
    def linked(name: str, contents: str | list[str]) -> rrb.TimeSeriesView:
        return rrb.TimeSeriesView(
            name=name, contents=contents, axis_x=rrb.TimeAxis(link="LinkToGlobal")
        )

    plots = [
        rrb.TextDocumentView(name="outcome", contents="/summary"),
        linked(
            "distance to goal (success tolerances)",
            ["/metrics/distance_to_goal", "/metrics/tolerance"],
        ),
        *([linked("plan cost at each replan", "/metrics/plan_cost")] if plans else []),
        linked("actions", "/metrics/action/**"),
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="workspace (m, z up)", origin="/world"),
            rrb.Vertical(*plots, row_shares=[2] + [3] * (len(plots) - 1)),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="sim_time", play_state="following", state="collapsed"),
        rrb.BlueprintPanel(state="expanded"),
        rrb.SelectionPanel(state="collapsed"),
    )


def write_manip_episode_recording(
    path: str | Path, result: EpisodeResult, spec: ManipSpaceSpec
) -> None:
    """Write one manipulation episode's recording to `path`, atomically (module docstring)."""
    rec = rr.RecordingStream(application_id(result), recording_id=recording_name(result))
    with atomic_path(path) as tmp:
        try:  # the file is closed before it is renamed into place, or removed after an error
            rec.save(tmp, default_blueprint=_blueprint(bool(result.trace.plans)))
            rec.send_recording_name(recording_name(result))
            rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
            _log_scene(rec, result, spec)
            rec.log(
                "summary",
                rr.TextDocument(_summary(result, spec), media_type="text/markdown"),
                static=True,
            )
            _log_states(rec, result, spec, 1.0)
            _log_plans(rec, result, spec)
            rec.flush()
        finally:
            rec.disconnect()


def write_manip_overview(
    path: str | Path, results: Sequence[EpisodeResult], spec: ManipSpaceSpec
) -> None:
    """The run overview: the success table and bars per task; nothing for no results."""
    grouped = group(results)
    if not grouped:
        return
    total = sum(len(rs) for by_task in grouped.values() for rs in by_task.values())
    wins = sum(r.success for by_task in grouped.values() for rs in by_task.values() for r in rs)
    text = (
        f"### {spec.env_id}: {wins} of {total} episodes reached the goal\n\n"
        f"{success_table(grouped)}\n\n"
        "Open `<agent>-<task>-<episode>.rrd` for an episode's 3-D view (when it was recorded)."
    )
    tasks = list(dict.fromkeys(t for by_task in grouped.values() for t in by_task))  # as the bars
    blueprint = rrb.Blueprint(
        rrb.Horizontal(
            rrb.TextDocumentView(name="success per task", contents="/summary"),
            rrb.BarChartView(
                name="success rate (%) per task: "
                + ", ".join(f"{i} {t}" for i, t in enumerate(tasks)),
                contents="/success/**",
            ),
        ),
        rrb.TimePanel(state="hidden"),
    )
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=RECORDING)
    with atomic_path(path) as tmp:
        try:
            rec.save(tmp, default_blueprint=blueprint)
            rec.send_recording_name(RECORDING)
            rec.log("summary", rr.TextDocument(text, media_type="text/markdown"), static=True)
            log_success_bars(rec, grouped)
            rec.flush()
        finally:
            rec.disconnect()
