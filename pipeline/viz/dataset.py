"""An MCAP dataset (`data/demos/<name>.mcap`) as a curated Rerun view: the demonstrations over the
maze, the right way up.

Rerun 0.41 opens our MCAP itself (`rerun mcap convert` decodes the protobuf channel), but what it
gets is one opaque `oposm.Step` struct per message on a 1970 timestamp timeline: no maze, no notion
of episode or goal, and no view shows a position. So `oposm view <file>.mcap` writes this view
instead (`write_dataset_view`): every episode's path (one colour per episode, static), the goals the
demonstrator reached (rings), and on the `time` timeline (the dataset's clock, simulated seconds)
the agent, the current episode's path and goal, the actions and the other state dimensions
(velocities) as plots; an `episode` timeline jumps between episodes. The text panel is
`oposm inspect`'s summary. Point and ant mazes share this view; OGBench's manipulation datasets
have no maze and get a 3-D view of the table instead (`pipeline.viz.manip_dataset`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.envs.manipspace.env import ManipSpaceSpec, is_manipspace, manipspace_spec
from pipeline.envs.spec import make_env_spec
from pipeline.errors import UserError
from pipeline.io import atomic_path
from pipeline.recording import format_summary, iter_episodes, read_info, summarize
from pipeline.viz.manip_dataset import (
    MAX_MANIP_EPISODES,
    log_manip_episode,
    log_manip_paths,
    log_manip_scene,
    log_manip_styles,
    manip_blueprint,
    manip_legend,
)
from pipeline.viz.manip_scene import ArmPoses
from pipeline.viz.maze import (
    AGENT,
    GOAL,
    ORDER_AGENT,
    ORDER_GOAL,
    ORDER_MARKER,
    ORDER_PLAN,
    ORDER_TRACE,
    OUTLINE,
    faded,
    log_legend,
    log_maze,
    map_view,
    to_view,
    unit,
)

APPLICATION_ID = "oposm-dataset"
MAX_EPISODES = 200  # per-step data beyond this many episodes makes a large, slow view
# A qualitative palette of mid-dark colours that read on the light floor (tab10 without grey).
EPISODE_COLORS = [
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
    (140, 86, 75), (227, 119, 194), (188, 189, 34), (23, 190, 207),
]  # fmt: skip
SERIES_COLORS = [(50, 100, 200), (230, 130, 20), (120, 120, 120), (150, 80, 200), (30, 150, 60)]


def _layout(info: Any) -> tuple[dict[str, Any] | None, list[int]]:
    """The maze layout (None without a simulator here, or for an env without a maze) and the
    position dims."""
    try:
        spec = make_env_spec(info.env_id, info.env_kwargs)
    except UserError:
        return None, [0, 1]
    if "bounds" not in spec.layout:
        return None, [0, 1]
    return spec.layout, list(spec.goal_dims)


def _manip_spec(info: Any) -> ManipSpaceSpec | None:
    """The spec of an OGBench manipulation env, else None."""
    return manipspace_spec(info.env_id) if is_manipspace(info.env_id) else None


def dataset_blueprint(
    layout: dict[str, Any] | None, others: list[str], window: float
) -> rrb.Blueprint:
    """Map (3/5) beside the summary and the plots (`window` seconds around the time cursor: an
    episode's worth); time panel on the dataset clock."""
    contents = ["/demos/**"]
    if layout is None:
        map_: rrb.Spatial2DView = rrb.Spatial2DView(name="positions", origin="/", contents=contents)
    else:
        map_ = map_view(layout, "demonstrations", contents)
    plots: list[Any] = [rrb.TextDocumentView(name="dataset", contents="/summary")]
    axis = rrb.TimeAxis(
        view_range=rr.TimeRange(
            start=rrb.TimeRangeBoundary.cursor_relative(seconds=-window / 2),
            end=rrb.TimeRangeBoundary.cursor_relative(seconds=window / 2),
        ),
    )  # not linked: a linked axis takes the global range instead
    plots.append(rrb.TimeSeriesView(name="actions", contents="/actions/**", axis_x=axis))
    if others:
        plots.append(rrb.TimeSeriesView(name="state", contents="/state/**", axis_x=axis))
    return rrb.Blueprint(
        rrb.Horizontal(map_, rrb.Vertical(*plots, row_shares=[3] + [2] * (len(plots) - 1))),
        rrb.TimePanel(timeline="time", play_state="paused", state="collapsed"),
        collapse_panels=True,
    )


def _log_episode(
    rec: rr.RecordingStream, ep: Any, pos: list[int], color: tuple[int, ...], names: Any
) -> np.ndarray:
    """One episode's per-step data on the `time` and `episode` timelines; returns its path."""
    xy = to_view(ep.observations[:, pos])
    times = [
        rr.TimeColumn("time", duration=ep.time),
        rr.TimeColumn("episode", sequence=np.full(len(ep), ep.index)),
    ]
    twice = rr.Points2D.columns(positions=np.repeat(xy, 2, axis=0))  # rim and dot
    rec.send_columns("demos/agent", times, twice.partition(np.full(len(ep), 2)))
    first = [
        rr.TimeColumn("time", duration=ep.time[:1]),
        rr.TimeColumn("episode", sequence=[ep.index]),
    ]
    rec.send_columns("demos/current", first, rr.LineStrips2D.columns(strips=[xy], colors=[color]))
    if ep.goals is not None:
        changes = np.flatnonzero(np.r_[True, np.any(np.diff(ep.goals, axis=0) != 0, axis=1)])
        rec.send_columns(
            "demos/goal",
            [
                rr.TimeColumn("time", duration=ep.time[changes]),
                rr.TimeColumn("episode", sequence=np.full(len(changes), ep.index)),
            ],
            rr.Ellipses2D.columns(centers=to_view(ep.goals[changes][:, :2])),
        )
    action_names, state_names, others = names
    for k, name in enumerate(action_names):
        rec.send_columns(f"actions/{name}", times, rr.Scalars.columns(scalars=ep.actions[:, k]))
    for k in others:
        rec.send_columns(
            f"state/{state_names[k]}", times, rr.Scalars.columns(scalars=ep.observations[:, k])
        )
    return xy


def write_dataset_view(
    mcap: str | Path, path: str | Path, max_episodes: int = MAX_EPISODES
) -> dict[str, Any]:
    """Write the view of the dataset `mcap` to `path` (.rrd, atomically): the first
    `max_episodes` episodes. Returns `{"episodes": shown, "total": in the file}`.

    Raises:
        UserError: `mcap` is not a readable oposm dataset (see `pipeline.recording`).
    """
    info = read_info(mcap)
    summary = summarize(mcap)
    manip = _manip_spec(info)
    if manip is not None:
        return _write_manip_view(mcap, path, info, summary, manip, min(max_episodes,
                                 MAX_MANIP_EPISODES))  # fmt: skip
    layout, pos = _layout(info)
    others = [k for k in range(info.state_dim) if k not in pos]
    names = (info.action_names, info.state_names, others)
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=f"dataset-{info.name}")
    paths, colors, reached = [], [], []
    with atomic_path(path) as tmp:
        try:  # the file is closed before it is renamed into place, or removed after an error
            window = summary["steps"] / max(summary["episodes"], 1) * info.control_period
            rec.save(tmp, default_blueprint=dataset_blueprint(layout, others, window))
            rec.send_recording_name(info.name)
            if layout is not None:
                log_maze(rec, layout)
            goal_radius = float((info.generator or {}).get("expert", {}).get("goal_radius", 0.5))
            u = 1.0 if layout is None else unit(layout)
            _log_styles(rec, names, goal_radius, u)
            for ep in iter_episodes(mcap):
                if ep.index >= max_episodes:
                    break
                color = EPISODE_COLORS[ep.index % len(EPISODE_COLORS)]
                paths.append(_log_episode(rec, ep, pos, color, names))
                colors.append(faded(color, 0.55))
                if ep.goals is not None and ep.goal_reached is not None:
                    reached.append(ep.goals[ep.goal_reached][:, :2])
            rec.log(
                "demos/paths",
                rr.LineStrips2D(paths, colors=colors, radii=0.008 * u, draw_order=ORDER_TRACE),
                static=True,
            )
            if reached and sum(len(r) for r in reached):
                rec.log(
                    "demos/goals_reached",
                    rr.Points2D(
                        to_view(np.concatenate(reached)),
                        colors=faded(GOAL, 0.6),
                        radii=0.04 * u,
                        draw_order=ORDER_MARKER,
                    ),
                    static=True,
                )
            _log_summary(rec, summary, len(paths))
            if layout is not None:
                log_legend(rec, layout, _legend())
            rec.flush()
        finally:
            rec.disconnect()
    return {"episodes": len(paths), "total": summary["episodes"]}


def _log_summary(rec: rr.RecordingStream, summary: dict[str, Any], shown: int) -> None:
    """`oposm inspect`'s summary, and how many episodes the view shows when not all."""
    note = (
        f"\n\nShowing the first {shown} of {summary['episodes']} episodes."
        if shown < summary["episodes"]
        else ""
    )
    text = f"```\n{format_summary(summary)}\n```{note}"
    rec.log("summary", rr.TextDocument(text, media_type="text/markdown"), static=True)


def _write_manip_view(
    mcap: str | Path,
    path: str | Path,
    info: Any,
    summary: dict[str, Any],
    spec: ManipSpaceSpec,
    max_episodes: int,
) -> dict[str, Any]:
    """`write_dataset_view` of a manipulation dataset (`pipeline.viz.manip_dataset`)."""
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=f"dataset-{info.name}")
    poser = ArmPoses(spec)
    pinches: list[np.ndarray] = []
    cubes: list[np.ndarray] = []
    goals = bool(info.goal_dim)
    with atomic_path(path) as tmp:
        try:  # the file is closed before it is renamed into place, or removed after an error
            window = summary["steps"] / max(summary["episodes"], 1) * info.control_period
            legend = manip_legend(spec, goals)
            rec.save(tmp, default_blueprint=manip_blueprint(len(legend), window))
            rec.send_recording_name(info.name)
            log_manip_scene(rec, spec, goals)
            log_manip_styles(rec, list(info.action_names))
            for ep in iter_episodes(mcap):
                if ep.index >= max_episodes:
                    break
                pinch, cube = log_manip_episode(rec, ep, spec, poser, list(info.action_names))
                pinches.append(pinch)
                cubes.append(cube)
            log_manip_paths(rec, pinches, cubes)
            _log_summary(rec, summary, len(pinches))
            rec.flush()
        finally:
            rec.disconnect()
    return {"episodes": len(pinches), "total": summary["episodes"]}


def _log_styles(rec: rr.RecordingStream, names: Any, goal_radius: float, u: float) -> None:
    action_names, state_names, others = names
    rec.log(
        "demos/agent",
        rr.Points2D.from_fields(
            colors=[OUTLINE, AGENT], radii=[0.13 * u, 0.1 * u], draw_order=ORDER_AGENT
        ),
        static=True,
    )
    rec.log(
        "demos/current",
        rr.LineStrips2D.from_fields(radii=0.025 * u, draw_order=ORDER_PLAN),
        static=True,
    )
    rec.log(
        "demos/goal",
        rr.Ellipses2D.from_fields(
            half_sizes=[[goal_radius] * 2], colors=GOAL, line_radii=0.03 * u, draw_order=ORDER_GOAL
        ),
        static=True,
    )
    for k, name in enumerate(action_names):
        color = SERIES_COLORS[k % len(SERIES_COLORS)]
        rec.log(f"actions/{name}", rr.SeriesLines(colors=color, names=name), static=True)
    for j, k in enumerate(others):
        color = SERIES_COLORS[j % len(SERIES_COLORS)]
        name = state_names[k]
        rec.log(f"state/{name}", rr.SeriesLines(colors=color, names=name), static=True)


def _legend() -> list[tuple[str, tuple[int, ...], Any]]:
    return [
        ("every episode (colour)", faded(EPISODE_COLORS[0], 0.55), "line"),
        ("current episode", EPISODE_COLORS[0], "line"),
        ("agent", AGENT, "dot"),
        ("current goal", GOAL, "ring"),
        ("goals reached", faded(GOAL, 0.6), "dot"),
    ]
