"""The run overview recording: every deployed episode of every agent on one screen.

One map per agent (the right way up) with each episode's start (dot) and goal (ring) coloured by
success, the paths of the failures and where each failure ended (x, with its task and episode
number: where an agent gets stuck is what a researcher looks for first), and lines joining each
start to its goal (switched off at first: they cross walls and read as paths); a bar chart of the
success rate per task and agent; a table of successes with 95 % Wilson intervals.

`write_overview` takes any list of `EpisodeResult`s and groups them by `result.agent` (in the
order they come), so one call shows one agent or compares several (OPOSM beside LLP).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.envs.spec import EnvSpec
from pipeline.evaluation.episodes import EpisodeResult
from pipeline.evaluation.proportions import wilson_interval
from pipeline.io import atomic_path
from pipeline.viz.maze import (
    FAILURE,
    LLP_PLAN,
    ORDER_GOAL,
    ORDER_MARKER,
    ORDER_TRACE,
    PLAN,
    SUCCESS,
    cross,
    faded,
    log_legend,
    log_maze,
    map_view,
    text_color,
    to_view,
    unit,
)

APPLICATION_ID = "oposm-deploy-overview"  # its own: the viewer keeps one layout per application
RECORDING = "overview"
AGENT_COLORS = {"oposm": PLAN, "llp": LLP_PLAN, "gcbc": (60, 110, 200), "expert": (120, 120, 120)}
OTHER_COLORS = [(230, 130, 20), (130, 80, 180), (40, 160, 170)]
LINK = (150, 150, 150)


def group(results: Sequence[EpisodeResult]) -> dict[str, dict[str, list[EpisodeResult]]]:
    """agent -> task -> results, agents and tasks in the order they first appear."""
    grouped: dict[str, dict[str, list[EpisodeResult]]] = {}
    for r in results:
        grouped.setdefault(r.agent or "agent", {}).setdefault(r.spec.task, []).append(r)
    return grouped


def _tasks(grouped: dict[str, dict[str, list[EpisodeResult]]]) -> list[str]:
    return list(dict.fromkeys(task for by_task in grouped.values() for task in by_task))


def _log_episodes(
    rec: rr.RecordingStream, base: str, results: list[EpisodeResult], pos: list[int], u: float
) -> None:
    """Starts, goals and their links coloured by success; failures' paths and end points."""
    starts = to_view([r.spec.start[pos] for r in results])
    goals = to_view([r.spec.goal for r in results])
    colors = [SUCCESS if r.success else FAILURE for r in results]
    rec.log(
        f"{base}/links",
        rr.LineStrips2D(
            np.stack([starts, goals], axis=1),
            colors=LINK,
            radii=0.008 * u,
            draw_order=ORDER_TRACE - 1,
        ),
        static=True,
    )
    rec.log(
        f"{base}/starts",
        rr.Points2D(starts, colors=colors, radii=0.07 * u, draw_order=ORDER_MARKER),
        static=True,
    )
    rec.log(
        f"{base}/goals",
        rr.Ellipses2D(
            centers=goals,
            half_sizes=np.full_like(goals, 0.11 * u),
            colors=colors,
            line_radii=0.025 * u,
            draw_order=ORDER_MARKER,
        ),
        static=True,
    )
    failed = [r for r in results if not r.success and r.trace.states]
    if not failed:
        return
    paths = [to_view(np.asarray(r.trace.states)[:, pos]) for r in failed]
    rec.log(
        f"{base}/failed_paths",
        rr.LineStrips2D(paths, colors=faded(FAILURE, 0.5), radii=0.012 * u, draw_order=ORDER_TRACE),
        static=True,
    )
    ends = np.stack([p[-1] for p in paths])
    labels = [f"{r.spec.task} {r.spec.index}" for r in failed]
    rec.log(
        f"{base}/failed_ends",
        rr.LineStrips2D(
            cross(ends, 0.09 * u),
            colors=FAILURE,
            radii=0.025 * u,
            labels=labels + [""] * len(labels),
            draw_order=ORDER_GOAL,
        ),
        static=True,
    )


def _rate(results: list[EpisodeResult]) -> tuple[int, int, float, float]:
    wins, n = sum(r.success for r in results), len(results)
    return wins, n, *wilson_interval(wins, n)


def success_table(grouped: dict[str, dict[str, list[EpisodeResult]]]) -> str:
    """Markdown: success with its 95 % interval, median steps to goal, failed episodes."""
    lines = [
        "| agent | task | success | 95 % interval | median steps | failed episodes |",
        "|---|---|---|---|---|---|",
    ]
    for agent, by_task in grouped.items():
        for task, results in by_task.items():
            wins, n, lo, hi = _rate(results)
            steps = [r.steps_to_goal for r in results if r.steps_to_goal is not None]
            median = f"{np.median(steps):.0f}" if steps else "-"
            failed = [str(r.spec.index) for r in results if not r.success]
            shown = ", ".join(failed[:12]) + (f" (+{len(failed) - 12})" if len(failed) > 12 else "")
            lines.append(
                f"| {agent} | {task} | {wins}/{n} ({100 * wins / max(n, 1):.0f} %) | "
                f"{100 * lo:.0f}-{100 * hi:.0f} % | {median} | {shown or '-'} |"
            )
    return "\n".join(lines)


def _summary(grouped: dict[str, dict[str, list[EpisodeResult]]], env: EnvSpec) -> str:
    total = sum(len(r) for by_task in grouped.values() for r in by_task.values())
    wins = sum(r.success for by_task in grouped.values() for rs in by_task.values() for r in rs)
    return (
        f"### {env.env_id}: {wins} of {total} episodes reached the goal\n\n"
        f"{success_table(grouped)}\n\n"
        "Maps: start (dot) and goal (ring) of every episode, green if it reached the goal, red "
        "if not; a red x where a failure ended (task and episode: open "
        "`<agent>-<task>-<episode>.rrd` when it was recorded)."
    )


def agent_color(agent: str, index: int) -> tuple[int, ...]:
    """The agent's colour in the bar chart (its plan colour where it has one)."""
    return AGENT_COLORS.get(agent, OTHER_COLORS[index % len(OTHER_COLORS)])


GRID = (200, 200, 200)
AXIS_TEXT = (90, 90, 90)


def _chart_height(n_tasks: int) -> float:
    """Height of 100 % in the chart's units (one task per unit across): Rerun keeps a 2-D view's
    aspect, so the bars are scaled to a chart about 3 : 2 wide."""
    return max(2.0, 0.6 * n_tasks)


def log_success_bars(
    rec: rr.RecordingStream, grouped: dict[str, dict[str, list[EpisodeResult]]]
) -> None:
    """Success per task as a bar chart drawn in a 2-D view (`success_bars_view`): a bar per
    agent and task (`success/<agent>/<task number>`, `wins/n` above it), gridlines at 0, 25, 50,
    75 and 100 %, the task names under their bars and the agents' names in their colours. Drawn
    by hand because Rerun's bar chart view fits its axis to the data (-2..2 at 0 %) and has no
    category names."""
    tasks = _tasks(grouped)
    h = _chart_height(len(tasks))
    width = 0.8 / len(grouped)
    for i, (agent, by_task) in enumerate(grouped.items()):
        x = np.array([tasks.index(t) - 0.4 + width * (i + 0.5) for t in by_task])  # centres
        counts = [_rate(rs)[:2] for rs in by_task.values()]
        rates = np.array([wins / max(n, 1) for wins, n in counts])
        color = agent_color(agent, i)
        tops = rates * h
        for task, xi, top in zip(by_task, x, tops, strict=True):
            if top > 0:  # a bar is a 2 x 2 image stretched over it: filled, square ends
                rec.log(
                    f"success/{agent}/{tasks.index(task)}",
                    rr.Transform3D(
                        translation=[xi - 0.42 * width, -top, 0.0],
                        scale=[0.42 * width, top / 2, 1.0],
                    ),
                    rr.Image(
                        np.full((2, 2, 3), color[:3], dtype=np.uint8),
                        color_model="RGB",
                        draw_order=ORDER_MARKER,
                    ),
                    static=True,
                )
        rec.log(
            f"success/{agent}/counts",
            rr.Points2D(
                np.stack([x, -tops - 0.05 * h], axis=1),
                radii=1e-4,
                colors=text_color(color),
                labels=[f"{wins}/{n}" for wins, n in counts],
                show_labels=True,
            ),
            static=True,
        )
        rec.log(
            f"success/legend/{i}",
            rr.Points2D(
                [[-0.3 + 1.0 * i, -1.12 * h]],
                radii=1e-4,
                colors=text_color(color),
                labels=agent,
                show_labels=True,
            ),
            static=True,
        )
    right = len(tasks) - 0.5
    levels = [0.0, 0.25, 0.5, 0.75, 1.0]
    rec.log(
        "success/grid",
        rr.LineStrips2D(
            [[[-0.5, -v * h], [right, -v * h]] for v in levels],
            radii=[0.004 * h if v in (0.0, 1.0) else 0.002 * h for v in levels],
            colors=GRID,
            draw_order=ORDER_TRACE,
        ),
        static=True,
    )
    rec.log(
        "success/axis",
        rr.Points2D(
            [[-0.75, -v * h] for v in levels],
            radii=1e-4,
            colors=AXIS_TEXT,
            labels=[f"{100 * v:.0f} %" for v in levels],
            show_labels=True,
        ),
        static=True,
    )
    # Long names alternate between two rows so that neighbours do not overlap.
    below = [0.08 * h if k % 2 == 0 or len(tasks) <= 5 else 0.17 * h for k in range(len(tasks))]
    rec.log(
        "success/tasks",
        rr.Points2D(
            [[k, b] for k, b in enumerate(below)],
            radii=1e-4,
            colors=AXIS_TEXT,
            labels=tasks,
            show_labels=True,
        ),
        static=True,
    )


def success_bars_view(grouped: dict[str, dict[str, list[EpisodeResult]]]) -> rrb.Spatial2DView:
    """The 2-D view of `log_success_bars`, its bounds fixed to the chart."""
    n = len(_tasks(grouped))
    h = _chart_height(n)
    return rrb.Spatial2DView(
        name="success rate per task",
        origin="/",
        contents=["/success/**"],
        visual_bounds=rrb.VisualBounds2D(x_range=[-1.05, n - 0.4], y_range=[-1.2 * h, 0.25 * h]),
        background=(252, 252, 252),
    )


def overview_blueprint(
    layout: dict[str, Any], grouped: dict[str, dict[str, list[EpisodeResult]]]
) -> rrb.Blueprint:
    """One map per agent on the left; the table and the bar chart on the right."""
    maps = []
    for agent, by_task in grouped.items():
        wins, n, _, _ = _rate([r for rs in by_task.values() for r in rs])
        name = f"{agent}: {wins}/{n} reached the goal"
        links = [f"/agents/{agent}/{task}/links" for task in by_task]
        legend = agent == list(grouped)[-1]  # one legend, beside the last map
        maps.append(map_view(layout, name, [f"/agents/{agent}/**"], legend, links))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Grid(*maps) if len(maps) > 1 else maps[0],
            rrb.Vertical(
                rrb.TextDocumentView(name="success per task", contents="/summary"),
                success_bars_view(grouped),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(state="hidden"),
        rrb.BlueprintPanel(state="expanded"),  # lists the recordings: the other episodes
        rrb.SelectionPanel(state="collapsed"),
    )


def write_overview(
    path: str | Path,
    results: Sequence[EpisodeResult],
    env: EnvSpec,
) -> None:
    """Write the overview of `results` (any agents, any tasks) to `path`, atomically: the maze
    `env.layout`, positions = the state dims `env.goal_dims`. Nothing is written for no results."""
    grouped = group(results)
    if not grouped:
        return
    pos, u = list(env.goal_dims), unit(env.layout)
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=RECORDING)
    with atomic_path(path) as tmp:
        try:  # the file is closed before it is renamed into place, or removed after an error
            rec.save(tmp, default_blueprint=overview_blueprint(env.layout, grouped))
            rec.send_recording_name(RECORDING)
            log_maze(rec, env.layout)
            log_legend(
                rec,
                env.layout,
                [
                    ("start, reached", SUCCESS, "dot"),
                    ("goal, reached", SUCCESS, "ring"),
                    ("start, failed", FAILURE, "dot"),
                    ("goal, failed", FAILURE, "ring"),
                    ("failed path", faded(FAILURE, 0.5), "line"),
                    ("where it ended", FAILURE, "cross"),
                    ("start-goal (off)", LINK, "line"),
                ],
            )
            for agent, by_task in grouped.items():
                for task, task_results in by_task.items():
                    _log_episodes(rec, f"agents/{agent}/{task}", task_results, pos, u)
            rec.log(
                "summary",
                rr.TextDocument(_summary(grouped, env), media_type="text/markdown"),
                static=True,
            )
            log_success_bars(rec, grouped)
            rec.flush()
        finally:
            rec.disconnect()
