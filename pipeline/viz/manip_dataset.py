"""A manipulation dataset (OGBench's cube, scene and puzzle envs) as a Rerun view: the
demonstrations on the table in 3-D, what `oposm view <file>.mcap` opens for these envs
(`pipeline.viz.dataset` dispatches here).

Static: every episode's cube paths (one colour per episode) and, fainter, its gripper path. On
the `time` timeline (the dataset's clock) and the `episode` timeline: the arm, the cubes and the
scene's parts as they move (`pipeline.viz.manip_scene`), a puzzle's buttons in their state's
colour (red 0, blue 1), the current episode's gripper path and, where the dataset records goals,
the goal of each cube. Beside it a legend, `oposm inspect`'s summary and the actions as plots.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.envs.manipspace.env import ManipSpaceSpec
from pipeline.viz.manip_scene import (
    PINCH,
    ArmPoses,
    button_legend,
    cube_color,
    legend_view,
    log_buttons,
    log_cubes,
    log_goals,
    log_manip_legend,
    log_robot,
    log_table,
    robot_legend,
    to_metres,
    workspace_view,
)
from pipeline.viz.maze import PATH, Color, faded

# An episode of OGBench's manipulation data is 1001 steps, and each step carries the whole arm:
# more episodes than this make a slow view (the summary says how many there are).
MAX_MANIP_EPISODES = 20
# Without red (the current gripper path), orange (the pinch site) and the cubes' colours.
EPISODE_COLORS: list[Color] = [
    (44, 160, 44), (140, 86, 75), (227, 119, 194), (188, 189, 34), (31, 119, 180),
    (120, 120, 120),
]  # fmt: skip
SERIES_COLORS = [(50, 100, 200), (230, 130, 20), (120, 120, 120), (150, 80, 200), (30, 150, 60)]


def manip_blueprint(n_legend: int, window: float) -> rrb.Blueprint:
    """3-D view, legend column, then the summary and the actions (`window` seconds around the
    time cursor: an episode's worth); time panel on the dataset clock."""
    axis = rrb.TimeAxis(
        view_range=rr.TimeRange(
            start=rrb.TimeRangeBoundary.cursor_relative(seconds=-window / 2),
            end=rrb.TimeRangeBoundary.cursor_relative(seconds=window / 2),
        ),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            workspace_view("demonstrations (m, z up)", "/world/**"),
            legend_view(n_legend),
            rrb.Vertical(
                rrb.TextDocumentView(name="dataset", contents="/summary"),
                rrb.TimeSeriesView(name="actions", contents="/actions/**", axis_x=axis),
                row_shares=[3, 2],
            ),
            column_shares=[3, 0.75, 2],
        ),
        rrb.TimePanel(timeline="time", play_state="paused", state="collapsed"),
        collapse_panels=True,
    )


def manip_legend(spec: ManipSpaceSpec, goals: bool) -> list[tuple[str, Color, Any]]:
    items = robot_legend(spec.n_cubes) if goals else robot_legend(spec.n_cubes)[:2]
    if not goals:
        items += [(f"cube {i}", cube_color(i), "dot") for i in range(spec.n_cubes)]
    if spec.n_buttons:
        items += button_legend(spec, goals=False)
    return items + [
        ("cube paths (colour: episode)", EPISODE_COLORS[0], "line"),
        ("gripper paths", faded(EPISODE_COLORS[0], 0.4), "line"),
        ("current gripper path", PATH, "line"),
    ]


def log_manip_styles(rec: rr.RecordingStream, action_names: list[str]) -> None:
    rec.log("world/current", rr.LineStrips3D.from_fields(colors=PATH, radii=0.003), static=True)
    for k, name in enumerate(action_names):
        color = SERIES_COLORS[k % len(SERIES_COLORS)]
        rec.log(f"actions/{name}", rr.SeriesLines(colors=color, names=name), static=True)


def log_manip_episode(
    rec: rr.RecordingStream, ep: Any, spec: ManipSpaceSpec, poser: ArmPoses, names: list[str]
) -> tuple[np.ndarray, np.ndarray]:
    """One episode on the `time` and `episode` timelines; returns its gripper path `[N, 3]` and
    cube paths `[n_cubes, N, 3]` (m)."""
    obs = np.asarray(ep.observations, dtype=np.float64)
    times = [
        rr.TimeColumn("time", duration=ep.time),
        rr.TimeColumn("episode", sequence=np.full(len(ep), ep.index)),
    ]
    poses = poser(obs)
    log_robot(rec, poses, times)
    cubes = log_cubes(rec, spec, obs, times) if spec.n_cubes else np.zeros((len(obs), 0, 3))
    if spec.n_buttons:
        assert poses.button_tops is not None
        log_buttons(rec, spec, obs, poses.button_tops, times)
    pinch = to_metres(obs[:, PINCH])
    first = [
        rr.TimeColumn("time", duration=ep.time[:1]),
        rr.TimeColumn("episode", sequence=[ep.index]),
    ]
    rec.send_columns("world/current", first, rr.LineStrips3D.columns(strips=[pinch]))
    n = 3 * spec.n_cubes
    if ep.goals is not None and ep.goals.shape[1] >= n:
        changes = np.flatnonzero(np.r_[True, np.any(np.diff(ep.goals, axis=0) != 0, axis=1)])
        for t in changes:
            rec.set_time("time", duration=float(ep.time[t]))
            rec.set_time("episode", sequence=ep.index)
            log_goals(rec, to_metres(ep.goals[t, :n].reshape(-1, 3)), static=False)
    for k, name in enumerate(names):
        rec.send_columns(f"actions/{name}", times, rr.Scalars.columns(scalars=ep.actions[:, k]))
    return pinch, cubes.transpose(1, 0, 2)


def log_manip_paths(
    rec: rr.RecordingStream, pinches: list[np.ndarray], cubes: list[np.ndarray]
) -> None:
    """Every episode's cube paths (its colour) and gripper path (faded), static."""
    colors = [EPISODE_COLORS[k % len(EPISODE_COLORS)] for k in range(len(pinches))]
    rec.log(
        "world/paths/gripper",
        rr.LineStrips3D(pinches, colors=[faded(c, 0.4) for c in colors], radii=0.0012),
        static=True,
    )
    strips = [path for ep in cubes for path in ep]
    rec.log(
        "world/paths/cubes",
        rr.LineStrips3D(
            strips, colors=[c for c, ep in zip(colors, cubes, strict=True) for _ in ep],
            radii=0.003,
        ),
        static=True,
    )  # fmt: skip


def log_manip_scene(rec: rr.RecordingStream, spec: ManipSpaceSpec, goals: bool) -> None:
    """The static part: z up, the table, the legend."""
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    log_table(rec, spec)
    log_manip_legend(rec, manip_legend(spec, goals))
