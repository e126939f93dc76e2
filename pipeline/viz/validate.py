"""Figure 4 of the paper as a Rerun recording: the same skill sequence executed R times open loop
in MuJoCo (red), where the TAWM predicted each skill would end with its 2-sigma ellipse (green), and
the single-step model rolled forward under the same actions (blue), over the maze.

One map per (mode, start state), the right way up, bounds fixed to the maze: a single-step path is
cut where it leaves the maze, and a blue x marks where it first walks into a wall (a real path
never does). Paths are static. On the `step` timeline the real agents and the single-step
predictions move, and the ellipse of the skill being executed is drawn bold, so playing it shows
the real agents heading into the TAWM's ellipse while the single-step prediction drifts away.
A legend and a short explanation stand on the right.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.envs.spec import EnvSpec
from pipeline.evaluation.open_loop import ModeResult, OpenLoopResult
from pipeline.evaluation.open_loop_metrics import first_wall_crossing
from pipeline.io import atomic_path
from pipeline.viz.maze import (
    ORDER_AGENT,
    ORDER_GOAL,
    ORDER_MARKER,
    ORDER_PLAN,
    ORDER_TRACE,
    PATH,
    PLAN,
    SINGLE,
    START,
    cross,
    faded,
    legend_width,
    log_legend,
    log_maze,
    map_view,
    to_view,
    unit,
)

APPLICATION_ID = "oposm_validate"
REAL, TAWM = PATH, PLAN
N_SIGMA = 2.0
EXPLANATION = """### Figure 4: where skills end

Each map: one start state from held-out data and one sequence of skills, **prior** (sampled as a
plan would be) or **posterior** (inferred from the recorded data that follows). The sequence runs
open loop in MuJoCo several times (**red**; red dots: where each skill really ended). **Green**:
the TAWM's chained prediction of each skill's end, with its 2σ ellipse. **Blue**: the single-step
model rolled forward under the actions really sent; **x** where it first walks into a wall.
Titles: how far, on average, the real end is from each model's predicted end.

Play the `step` timeline: large dots are where the real agents and the single-step predictions
are at that step, the bold ellipse is the end the TAWM predicts for the skill being executed."""


def _inside(paths: np.ndarray, layout: dict[str, Any]) -> np.ndarray:
    """`[B]` number of leading points of each path `[B, T + 1, 2]` (world) inside the maze."""
    xmin, xmax, ymin, ymax = layout["bounds"]
    x, y = paths[..., 0], paths[..., 1]
    out = (x < xmin) | (x > xmax) | (y < ymin) | (y > ymax)
    return np.where(out.any(1), out.argmax(1), paths.shape[1])


def _log_paths(
    rec: rr.RecordingStream, base: str, real: np.ndarray, single: np.ndarray, h: int, layout: Any
) -> np.ndarray:
    """Static paths; returns `[R]` how many points of each single-step path are drawn."""
    u = unit(layout)
    rec.log(
        f"{base}/real",
        rr.LineStrips2D(to_view(real), colors=REAL, radii=0.015 * u, draw_order=ORDER_TRACE),
        static=True,
    )
    ends = to_view(real[:, h::h].reshape(-1, 2))
    rec.log(
        f"{base}/real_ends",
        rr.Points2D(ends, colors=REAL, radii=0.045 * u, draw_order=ORDER_MARKER),
        static=True,
    )
    keep = np.maximum(_inside(single, layout), 1)
    strips = [to_view(p[:k]) for p, k in zip(single, keep, strict=True)]
    rec.log(
        f"{base}/single_step",
        rr.LineStrips2D(strips, colors=SINGLE, radii=0.015 * u, draw_order=ORDER_TRACE + 1),
        static=True,
    )
    hit = first_wall_crossing(single, layout)
    walls = [to_view(p[t]) for p, t, k in zip(single, hit, keep, strict=True) if t < k]
    if walls:
        rec.log(
            f"{base}/single_step_wall",
            rr.LineStrips2D(
                cross(walls, 0.08 * u), colors=SINGLE, radii=0.02 * u, draw_order=ORDER_GOAL
            ),
            static=True,
        )
    return keep


def _log_start(
    rec: rr.RecordingStream,
    base: str,
    r: ModeResult,
    rows: slice,
    pos: list[int],
    dt: float,
    layout: dict[str, Any],
) -> None:
    real, single = r.real[rows][..., pos], r.single_step[rows][..., pos]  # [R, L H + 1, 2]
    n_skills = r.tawm_mean.shape[1]
    h = (real.shape[1] - 1) // n_skills
    keep = _log_paths(rec, base, real, single, h, layout)
    u = unit(layout)
    rec.log(
        f"{base}/start",
        rr.Points2D(to_view(real[:1, 0]), colors=START, radii=0.08 * u, draw_order=ORDER_MARKER),
        static=True,
    )
    first = rows.start  # the TAWM prediction is the same for every repeat of a sequence
    chain = to_view(np.concatenate([real[:1, 0], r.tawm_mean[first][:, pos]]))
    mean = to_view(r.pred_mean[first][:, pos])
    half = N_SIGMA * r.pred_std[first][:, pos]
    rec.log(
        f"{base}/tawm/chain",
        rr.LineStrips2D([chain], colors=TAWM, radii=0.012 * u, draw_order=ORDER_PLAN),
        static=True,
    )
    rec.log(
        f"{base}/tawm/mean",
        rr.Points2D(mean, colors=TAWM, radii=0.06 * u, draw_order=ORDER_PLAN),
        static=True,
    )
    rec.log(
        f"{base}/tawm/sigma2",
        rr.Ellipses2D(
            centers=mean,
            half_sizes=half,
            colors=faded(TAWM, 0.6),
            line_radii=0.012 * u,
            draw_order=ORDER_PLAN,
        ),
        static=True,
    )
    steps = np.arange(real.shape[1])
    times = [rr.TimeColumn("step", sequence=steps), rr.TimeColumn("sim_time", duration=steps * dt)]
    skill = np.minimum(np.maximum(steps - 1, 0) // h, n_skills - 1)  # the skill being executed
    rec.send_columns(
        f"{base}/now/tawm",
        indexes=times,
        columns=rr.Ellipses2D.columns(centers=mean[skill], half_sizes=half[skill]),
    )
    rec.log(
        f"{base}/now/tawm",
        rr.Ellipses2D.from_fields(colors=TAWM, line_radii=0.03 * u, draw_order=ORDER_GOAL),
        static=True,
    )
    for name, paths, color, shown in (
        ("real", real, REAL, np.full(len(real), real.shape[1])),
        ("single_step", single, SINGLE, keep),
    ):
        # Step-major; a single-step marker disappears where its path leaves the maze.
        visible = steps[:, None] < shown[None, :]  # [T + 1, R]
        flat = to_view(paths.transpose(1, 0, 2)[visible])
        rec.send_columns(
            f"{base}/now/{name}",
            indexes=times,
            columns=rr.Points2D.columns(positions=flat).partition(visible.sum(1)),
        )
        rec.log(
            f"{base}/now/{name}",
            rr.Points2D.from_fields(colors=color, radii=0.08 * u, draw_order=ORDER_AGENT),
            static=True,
        )


def _end_errors(r: ModeResult, rows: slice, pos: list[int]) -> tuple[float, float]:
    """Mean distance (m) from the real end to the TAWM's and the single-step model's ends."""
    real = r.real[rows][:, -1, pos]
    tawm = np.linalg.norm(real - r.tawm_mean[rows][:, -1, pos], axis=1).mean()
    single = np.linalg.norm(real - r.single_step[rows][:, -1, pos], axis=1).mean()
    return float(tawm), float(single)


def _legend() -> list[tuple[str, tuple[int, ...], Any]]:
    return [
        ("start", START, "dot"),
        ("real rollouts", REAL, "line"),
        ("real skill ends", REAL, "dot"),
        ("TAWM skill ends", TAWM, "dot"),
        (f"TAWM {N_SIGMA:.0f}σ, current skill", TAWM, "ring"),
        ("single-step model", SINGLE, "line"),
        ("single-step in a wall", SINGLE, "cross"),
    ]


def validate_blueprint(layout: dict[str, Any], rows: list[list[tuple[str, str]]]) -> rrb.Blueprint:
    """One row of maps per mode (`rows`: (entity base, view name)); the explanation and the
    legend on the right; time panel on `step`, at the end."""
    xmin, xmax, ymin, ymax = layout["bounds"]
    legend = rrb.Spatial2DView(
        name="legend",
        origin="/",
        contents="/legend/**",
        visual_bounds=rrb.VisualBounds2D(
            x_range=[xmax, xmax + legend_width(layout)], y_range=[-ymax, -ymin]
        ),
    )
    maps = [
        rrb.Horizontal(*[map_view(layout, name, [f"/{base}/**"], False) for base, name in row])
        for row in rows
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(*maps),
            rrb.Vertical(
                rrb.TextDocumentView(name="about", contents="/about"), legend, row_shares=[1, 1]
            ),
            column_shares=[5, 1],
        ),
        rrb.TimePanel(timeline="step", play_state="following", state="collapsed"),
        collapse_panels=True,
    )


def write_recording(path: str | Path, v: OpenLoopResult, spec: EnvSpec, n_starts: int) -> None:
    """Write `path` (.rrd) with the first `n_starts` start states of every mode, atomically;
    positions are the state dims `spec.goal_dims`, over the maze `spec.layout`."""
    pos = list(spec.goal_dims)
    n = min(n_starts, len(v.starts))
    rec = rr.RecordingStream(APPLICATION_ID, recording_id="oposm-validate")
    with atomic_path(path) as tmp:
        try:  # the file is closed before it is renamed into place, or removed after an error
            rec.save(tmp)
            log_maze(rec, spec.layout)
            log_legend(rec, spec.layout, _legend())
            rec.log("about", rr.TextDocument(EXPLANATION, media_type="text/markdown"), static=True)
            rows = []
            for mode, result in v.modes.items():
                row = []
                for i in range(n):
                    base = f"{mode}/start_{i}"
                    starts = slice(i * v.repeats, (i + 1) * v.repeats)
                    _log_start(rec, base, result, starts, pos, spec.dt, spec.layout)
                    tawm, single = _end_errors(result, starts, pos)
                    name = f"{mode} {i} · TAWM {tawm:.2f} m · single-step {single:.2f} m"
                    row.append((base, name))
                rows.append(row)
            if rows and rows[0]:
                rec.send_blueprint(validate_blueprint(spec.layout, rows), make_default=True)
            rec.flush()
        finally:
            rec.disconnect()
