"""Validate's Rerun recording without a simulator: recorded against predicted, per state dimension.

One tab per held-out start. In each, one plot per state dimension on the `step` timeline: the
recorded state (red), the single-step model rolled over the recorded actions (blue), and the
TAWM's chained prediction of where each recorded skill ends (green dots, at steps H, 2H, ...) with
its 2-sigma band (faded green dots above and below). When the dataset names a position (x, y and
maybe z), a 3-D view draws the recorded path, the single-step path and the TAWM's chain (a 2-D
position lies in the plane z = 0). Everything is static: the plots are the whole story.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.evaluation.recorded import RecordedResult
from pipeline.io import atomic_path
from pipeline.viz.maze import PATH, PLAN, SINGLE, START, faded

APPLICATION_ID = "oposm_validate"
RECORDED, TAWM = PATH, PLAN
N_SIGMA = 2.0
ABOUT = """### Where recorded skills end: the world model against held-out data

No simulator: each tab is one held-out start state from the test split, followed by recorded
windows of H steps. The posterior infers the skill of each window; the TAWM chains those skills
open loop from the start and predicts where each ends (**green** dots, 2σ band in faded green).
**Red**: what the robot recorded. **Blue**: the single-step model rolled forward over the
recorded actions. One plot per state dimension, in the dataset's units; a 3-D view of the
position when the dataset names one. The report (`data/reports/validate/report.json`, section
`recorded`) has the errors and calibration over all held-out starts."""


def _series(rec: rr.RecordingStream, path: str, steps: np.ndarray, values: np.ndarray) -> None:
    rec.send_columns(
        path, [rr.TimeColumn("step", sequence=steps)], rr.Scalars.columns(scalars=values)
    )


def _log_dims(
    rec: rr.RecordingStream, base: str, r: RecordedResult, i: int, names: list[str]
) -> list[str]:
    """The per-dimension plots of start i; returns their entity paths (one view each)."""
    h, n = r.horizon, r.recorded.shape[1]
    steps, ends = np.arange(n), np.arange(1, r.skills + 1) * h
    paths = []
    for j in range(len(names)):
        dim = f"{base}/dim_{j}"  # by index: dataset names may hold any character
        mean, std = r.pred_mean[i, :, j], r.pred_std[i, :, j]
        lines = {
            "recorded": (r.recorded[i, :, j], RECORDED),
            "single_step": (r.single_step[i, :, j], SINGLE),
        }
        for what, (values, color) in lines.items():
            rec.log(f"{dim}/{what}", rr.SeriesLines(colors=color, names=what), static=True)
            _series(rec, f"{dim}/{what}", steps, values)
        dots = {
            "tawm": (r.tawm_mean[i, :, j], TAWM, 5.0, "TAWM"),
            "tawm_high": (mean + N_SIGMA * std, faded(TAWM, 0.5), 3.0, f"+{N_SIGMA:.0f}σ"),
            "tawm_low": (mean - N_SIGMA * std, faded(TAWM, 0.5), 3.0, f"-{N_SIGMA:.0f}σ"),
        }
        for what, (values, color, size, label) in dots.items():
            style = rr.SeriesPoints(colors=color, names=label, markers="Circle", marker_sizes=size)
            rec.log(f"{dim}/{what}", style, static=True)
            _series(rec, f"{dim}/{what}", np.r_[0, ends], np.r_[r.recorded[i, 0, j], values])
        paths.append(dim)
    return paths


def _as_3d(points: np.ndarray) -> np.ndarray:
    """`[..., 2 or 3]` positions -> `[..., 3]` (z = 0 for a plane)."""
    if points.shape[-1] == 3:
        return points
    return np.concatenate([points, np.zeros((*points.shape[:-1], 1))], axis=-1)


def _log_positions(
    rec: rr.RecordingStream, base: str, r: RecordedResult, i: int, pos: list[int]
) -> None:
    """Static 3-D paths of start i over the position dims `pos`."""
    recorded = _as_3d(r.recorded[i][:, pos])
    scale = float(np.ptp(recorded, axis=0).max()) or 1.0  # markers sized to the path
    chain = _as_3d(np.concatenate([r.recorded[i, :1, pos].T, r.tawm_mean[i][:, pos]]))
    ends = _as_3d(r.recorded[i, r.horizon :: r.horizon][:, pos])
    rec.log(
        f"{base}/recorded",
        rr.LineStrips3D([recorded], colors=RECORDED, radii=0.006 * scale),
        static=True,
    )
    rec.log(
        f"{base}/recorded_ends", rr.Points3D(ends, colors=RECORDED, radii=0.02 * scale), static=True
    )
    rec.log(
        f"{base}/single_step",
        rr.LineStrips3D([_as_3d(r.single_step[i][:, pos])], colors=SINGLE, radii=0.006 * scale),
        static=True,
    )
    rec.log(
        f"{base}/tawm/chain",
        rr.LineStrips3D([chain], colors=TAWM, radii=0.005 * scale),
        static=True,
    )
    rec.log(
        f"{base}/tawm/ends", rr.Points3D(chain[1:], colors=TAWM, radii=0.025 * scale), static=True
    )
    rec.log(f"{base}/start", rr.Points3D(chain[:1], colors=START, radii=0.03 * scale), static=True)


def write_recorded_recording(
    path: str | Path,
    r: RecordedResult,
    state_names: list[str],
    pos: list[int],
    n_starts: int,
    labels: list[str],
) -> None:
    """Write the recording of the first `n_starts` starts to `path` (.rrd), atomically.

    Args:
        pos: Position dims drawn in 3-D (empty: none).
        labels: One tab title per start (e.g. "test episode 3, step 40").
    """
    n = min(n_starts, len(r.starts))
    rec = rr.RecordingStream(APPLICATION_ID, recording_id="oposm-validate")
    with atomic_path(path) as tmp:
        try:  # the file is closed before it is renamed into place, or removed after an error
            rec.save(tmp)
            rec.log("about", rr.TextDocument(ABOUT, media_type="text/markdown"), static=True)
            tabs = []
            for i in range(n):
                base = f"recorded/start_{i}"
                dims = _log_dims(rec, base, r, i, state_names)
                views: list[rrb.View] = [
                    rrb.TimeSeriesView(name=name, origin=f"/{d}")
                    for name, d in zip(state_names, dims, strict=True)
                ]
                if pos:
                    _log_positions(rec, f"{base}/positions", r, i, pos)
                    views.insert(0, rrb.Spatial3DView(name="position", origin=f"/{base}/positions"))
                tabs.append(rrb.Grid(*views, name=labels[i]))
            if tabs:
                blueprint = rrb.Blueprint(
                    rrb.Horizontal(
                        rrb.Tabs(*tabs),
                        rrb.TextDocumentView(name="about", contents="/about"),
                        column_shares=[5, 1],
                    ),
                    rrb.TimePanel(timeline="step", state="collapsed"),
                    collapse_panels=True,
                )
                rec.send_blueprint(blueprint, make_default=True)
            rec.flush()
        finally:
            rec.disconnect()
