"""Figure 4 of the paper as a Rerun recording: real open-loop rollouts (red), the TAWM's
predictions with their uncertainty (green), single-step model predictions (blue), over the maze.

One 2D view per (mode, start state). Paths are static; the current positions of the real and
single-step rollouts also play back on the `step` and `sim_time` timelines.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.envs.spec import EnvSpec
from pipeline.evaluation.open_loop import ModeResult, OpenLoopResult
from pipeline.io import atomic_path
from pipeline.viz.maze import log_maze

REAL = (220, 50, 50)
TAWM = (40, 170, 70)
SINGLE = (50, 90, 220)
_ELLIPSE_POINTS = 48


def ellipses(mean: np.ndarray, std: np.ndarray, n_sigma: float) -> np.ndarray:
    """Polylines `[K, P + 1, 2]` of the axis-aligned n-sigma ellipses of diagonal Gaussians
    `mean, std [K, 2]` (closed: the first point is repeated)."""
    angle = np.linspace(0, 2 * np.pi, _ELLIPSE_POINTS + 1)
    unit = np.stack([np.cos(angle), np.sin(angle)], -1)  # [P + 1, 2]
    return mean[:, None] + n_sigma * std[:, None] * unit[None]


def _log_start(
    rec: rr.RecordingStream,
    base: str,
    r: ModeResult,
    rows: slice,
    pos: list[int],
    dt: float,
) -> None:
    real, single = r.real[rows][..., pos], r.single_step[rows][..., pos]
    rec.log(f"{base}/real", rr.LineStrips2D(real, colors=REAL, radii=0.012), static=True)
    rec.log(f"{base}/single_step", rr.LineStrips2D(single, colors=SINGLE, radii=0.012), static=True)
    first = rows.start  # the TAWM prediction is the same for every repeat of a sequence
    chain = np.concatenate([real[:1, 0], r.tawm_mean[first][:, pos]])
    mean, std = r.pred_mean[first][:, pos], r.pred_std[first][:, pos]
    rec.log(f"{base}/tawm/chain", rr.LineStrips2D([chain], colors=TAWM, radii=0.01), static=True)
    rec.log(f"{base}/tawm/mean", rr.Points2D(mean, colors=TAWM, radii=0.05), static=True)
    for n_sigma, alpha in ((1, 255), (2, 140)):
        rec.log(
            f"{base}/tawm/sigma{n_sigma}",
            rr.LineStrips2D(ellipses(mean, std, n_sigma), colors=(*TAWM, alpha), radii=0.01),
            static=True,
        )
    steps = np.arange(real.shape[1])
    times = [rr.TimeColumn("step", sequence=steps), rr.TimeColumn("sim_time", duration=steps * dt)]
    reps = [real.shape[0]] * len(steps)
    for name, paths, color in (("real", real, REAL), ("single_step", single, SINGLE)):
        flat = paths.transpose(1, 0, 2).reshape(-1, 2)  # step-major
        rec.send_columns(
            f"{base}/now/{name}",
            indexes=times,
            columns=rr.Points2D.columns(
                positions=flat, colors=np.tile(color, (len(flat), 1))
            ).partition(reps),
        )


def write_recording(path: str | Path, v: OpenLoopResult, spec: EnvSpec, n_starts: int) -> None:
    """Write `path` (.rrd) with the first `n_starts` start states of every mode, atomically;
    positions are the state dims `spec.goal_dims`, over the maze `spec.layout`."""
    pos = list(spec.goal_dims)
    n = min(n_starts, len(v.starts))
    rec = rr.RecordingStream("oposm_validate", recording_id="oposm-validate")
    with atomic_path(path) as tmp:
        try:  # the file is closed before it is renamed into place, or removed after an error
            rec.save(tmp)
            log_maze(rec, spec.layout)
            views = []
            for mode, result in v.modes.items():
                for i in range(n):
                    base = f"{mode}/start_{i}"
                    rows = slice(i * v.repeats, (i + 1) * v.repeats)
                    _log_start(rec, base, result, rows, pos, spec.dt)
                    views.append(
                        rrb.Spatial2DView(
                            name=base, origin="/", contents=["/maze/**", f"/{base}/**"]
                        )
                    )
            rec.send_blueprint(rrb.Blueprint(rrb.Grid(*views), collapse_panels=True))
            rec.flush()
        finally:
            rec.disconnect()
