"""Rerun recordings of deployed episodes in OGBench's manipulation envs (cube-single, cube-double,
scene, the puzzles), and their run overview.

An episode's recording: a 3-D view of the table (metres, z up, framed on the workspace) with the
arm, the cubes and the scene's parts at every step (`pipeline.viz.manip_scene`: MuJoCo's
kinematics of the observed joints), each cube's goal as a wire box of OGBench's success tolerance
(0.04 m) in the cube's colour, the pinch site's path so far, and at every replan the chosen plan's
predicted cube and pinch positions (green for the TAWM's skill ends, pink for LLP's actions). On
the right: the outcome and the task in words beside a legend, the distance to the goal in success
tolerances (`pipeline.evaluation.goals`: 1 is at the tolerance), the plan cost, the actions.
Timelines `step` and `sim_time`, as the maze recordings. The scene's goal states of its buttons,
drawer and window are in the text; their part of the distance is in the distance plot. A puzzle
has no cube: its buttons are drawn in their state's colour at every step (red 0, blue 1, as in
OGBench), each goal state as a wire box around its button in that state's colour, and the text
has the grid's states row by row at the start, the goal and the end.

The overview holds the success table and the success bars of the maze overview, without a map.

Validate's 3-D view is `pipeline.viz.manip_validate`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.envs.manipspace.env import (
    DRAWER_SCALE,
    SUCCESS_TOLERANCE,
    WINDOW_SCALE,
    ManipSpaceSpec,
)
from pipeline.evaluation.episodes import EpisodeResult
from pipeline.evaluation.goals import GoalRule
from pipeline.io import atomic_path
from pipeline.viz.deploy import ACTION_COLORS, RADIUS_LINE, application_id, recording_name
from pipeline.viz.manip_scene import (
    PINCH,
    ArmPoses,
    button_legend,
    legend_view,
    log_button_goals,
    log_buttons,
    log_cubes,
    log_goals,
    log_manip_legend,
    log_robot,
    log_table,
    log_to_goal,
    observed_buttons,
    robot_legend,
    to_metres,
    workspace_view,
)
from pipeline.viz.maze import GOAL, LLP_PLAN, PATH, PLAN, Color
from pipeline.viz.overview import (
    APPLICATION_ID,
    RECORDING,
    group,
    log_success_bars,
    success_bars_view,
    success_table,
)

ACTION_NAMES = ("dx", "dy", "dz", "dyaw", "dgrip")
PATH_UPDATES = 80  # the pinch path is re-logged about this often per episode (and at replans)


def cube_positions(states: np.ndarray, spec: ManipSpaceSpec) -> np.ndarray:
    """`[..., n_cubes, 3]` cube positions (m) from observations `[..., state_dim]`."""
    return spec.observed_cubes(states)


def _times(steps: np.ndarray, dt: float) -> list[rr.TimeColumn]:
    return [rr.TimeColumn("step", sequence=steps), rr.TimeColumn("sim_time", duration=steps * dt)]


def goal_cubes(result: EpisodeResult, spec: ManipSpaceSpec) -> np.ndarray:
    """`[n_cubes, 3]` the episode's goal positions of the cubes (m)."""
    return to_metres(result.spec.goal[: 3 * spec.n_cubes].reshape(spec.n_cubes, 3))


def _legend(result: EpisodeResult, spec: ManipSpaceSpec) -> list[tuple[str, Color, Any]]:
    items = robot_legend(spec.n_cubes) + [("gripper path", PATH, "line")]
    if spec.n_buttons:
        items += button_legend(spec)
    if result.trace.plans:
        name = "LLP: predicted" if result.agent == "llp" else "TAWM: predicted"
        color = LLP_PLAN if result.agent == "llp" else PLAN
        if spec.n_cubes:
            items.append((f"{name} cubes", color, "dot"))
        items.append((f"{name} gripper", color, "line"))
    return items


def _log_states(
    rec: rr.RecordingStream, result: EpisodeResult, spec: ManipSpaceSpec, radius: float
) -> None:
    """Robot, cubes and scene parts at every step, the pinch path, the per-step scalars."""
    states = np.asarray(result.trace.states)  # [n + 1, sd]
    steps = np.arange(len(states))
    times = _times(steps, spec.dt)
    poses = ArmPoses(spec)(states)
    log_robot(rec, poses, times)
    if spec.n_cubes:
        cubes = log_cubes(rec, spec, states, times)
        log_to_goal(rec, cubes, goal_cubes(result, spec), times)
    if spec.n_buttons:
        assert poses.button_tops is not None
        log_buttons(rec, spec, states, poses.button_tops, times)
    pinch = to_metres(states[:, PINCH])
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
        rec.send_columns(f"metrics/{name}", times, rr.Scalars.columns(scalars=values))
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
        if spec.n_cubes:
            rec.log(
                "world/plan/cubes",
                rr.Points3D(cube_positions(predicted, spec).reshape(-1, 3), radii=0.008,
                            colors=color),
            )  # fmt: skip
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


def _grid_text(states: np.ndarray, spec: ManipSpaceSpec) -> str:
    """A puzzle's button states `[n_buttons]` row by row (`110 101 011`; a prediction rounded)."""
    assert spec.grid is not None
    rows, cols = spec.grid
    on = (np.asarray(states, dtype=np.float64) >= 0.5).astype(int).reshape(rows, cols)
    return " ".join("".join(str(v) for v in row) for row in on)


def _puzzle_lines(result: EpisodeResult, spec: ManipSpaceSpec) -> list[str]:
    """The text's lines on a puzzle's buttons: start, goal, end, how many end right."""
    states = np.asarray(result.trace.states)
    goal = np.asarray(result.spec.goal)
    start, end = observed_buttons(spec, states[0]), observed_buttons(spec, states[-1])
    right = int((np.round(end) == goal).sum())
    return [
        f"- buttons (rows, 1 on): start {_grid_text(start, spec)}, goal {_grid_text(goal, spec)}",
        f"- at the end: {_grid_text(end, spec)}, {right} of {spec.n_buttons} in their goal state",
    ]


def _summary(result: EpisodeResult, spec: ManipSpaceSpec) -> str:
    """Markdown: the outcome (short: it is the heading), the task, where the objects ended."""
    r, s = result, result.spec
    if r.error is not None:
        outcome = f"failed after {r.steps} steps"
    elif r.success:
        outcome = f"reached the goal in {r.steps_to_goal} steps ({r.steps_to_goal * spec.dt:.1f} s)"
    else:
        outcome = f"did not reach the goal in {r.steps} steps"
    lines = [
        f"### {r.agent + ': ' if r.agent else ''}{outcome}",
        "",
        f"- {spec.env_id} **{s.task}**, episode {s.index}, seed {s.seed}, {r.replans} replans",
    ]
    if r.error is not None:
        lines.append(f"- error: {r.error}")
    elif not r.success:
        lines.append(
            f"- closest {r.min_distance:.2f} tolerances from the goal, final {r.final_distance:.2f}"
        )
    end_cubes = cube_positions(np.asarray(r.trace.states[-1]), spec)
    for i, (goal, end) in enumerate(zip(goal_cubes(r, spec), end_cubes, strict=True)):
        lines.append(
            f"- cube {i} ends {100 * np.linalg.norm(end - goal):.1f} cm from its goal "
            f"(success within {100 * SUCCESS_TOLERANCE:.0f} cm)"
        )
    if spec.grid is not None:
        lines += _puzzle_lines(r, spec)
    if spec.scene:
        goal_state = np.full(spec.state_dim, np.nan)
        goal_state[list(spec.goal_dims)] = s.goal
        lines.append(f"- goal: {_objects(goal_state, spec)}")
        lines.append(f"- at the end: {_objects(np.asarray(r.trace.states[-1]), spec)}")
    return "\n".join(lines) + "\n"


def _blueprint(plans: bool, legend_items: int) -> rrb.Blueprint:
    def linked(name: str, contents: str | list[str]) -> rrb.TimeSeriesView:
        return rrb.TimeSeriesView(
            name=name,
            contents=contents,
            axis_x=rrb.TimeAxis(link="LinkToGlobal"),
            plot_legend=rrb.PlotLegend(corner="RightTop"),
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
            workspace_view("workspace (m, z up)", "/world/**"),
            legend_view(legend_items),
            rrb.Vertical(*plots, row_shares=[3] + [2] * (len(plots) - 1)),
            column_shares=[3, 0.75, 2],
        ),
        rrb.TimePanel(timeline="sim_time", play_state="following", state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


def write_manip_episode_recording(
    path: str | Path, result: EpisodeResult, spec: ManipSpaceSpec
) -> None:
    """Write one manipulation episode's recording to `path`, atomically (module docstring)."""
    rec = rr.RecordingStream(application_id(result), recording_id=recording_name(result))
    legend = _legend(result, spec)
    with atomic_path(path) as tmp:
        try:  # the file is closed before it is renamed into place, or removed after an error
            rec.save(tmp, default_blueprint=_blueprint(bool(result.trace.plans), len(legend)))
            rec.send_recording_name(recording_name(result))
            rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
            log_table(rec, spec)
            if spec.n_cubes:
                log_goals(rec, goal_cubes(result, spec))
            if spec.n_buttons:  # the goal: cube positions, button states, drawer, window
                at = 3 * spec.n_cubes
                goal = np.asarray(result.spec.goal)[at : at + spec.n_buttons]
                log_button_goals(rec, spec, goal)
            log_manip_legend(rec, legend)
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
    blueprint = rrb.Blueprint(
        rrb.Horizontal(
            rrb.TextDocumentView(name="success per task", contents="/summary"),
            success_bars_view(grouped),
            column_shares=[1, 1],
        ),
        rrb.TimePanel(state="hidden"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
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
