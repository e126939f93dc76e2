"""Validate's Rerun recording in OGBench's manipulation envs (figure 4 of the paper for a cube):
one 3-D view per (mode, start state) with the first cube's real paths of the open-loop executions
(red), where each skill really ended (red dots), the TAWM's chained prediction of each skill's end
(green dots) and the single-step model's path under the same actions (blue); metres, z up, static.
A puzzle has no cube: the paths are the gripper's (its pinch site), which carries out the presses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.envs.manipspace.env import ManipSpaceSpec
from pipeline.evaluation.open_loop import OpenLoopResult
from pipeline.io import atomic_path
from pipeline.viz.maze import PATH, PLAN, SINGLE

VALIDATE_ABOUT = """### Open loop: where skills take the {what}

Each view: one held-out start state and one sequence of skills, **prior** (sampled as a plan
would be) or **posterior** (inferred from the recorded data that follows), run open loop in
MuJoCo several times. **Red**: the {whose} real paths, dots where each skill ended.
**Green**: the TAWM's chained prediction of each skill's end. **Blue**: the single-step model
rolled forward under the actions really sent. Metres, z up."""


def tracked(spec: ManipSpaceSpec, states: np.ndarray) -> np.ndarray:
    """`[..., 3]` what the view follows in states `[..., state_dim]` (m): the first cube, or in
    a puzzle (no cube) the gripper's pinch site."""
    if spec.n_cubes:
        return spec.observed_cubes(states)[..., 0, :]
    return spec.observed_pinch(states)


def about(spec: ManipSpaceSpec) -> str:
    """The view's explanation, naming what it follows."""
    if spec.n_cubes:
        return VALIDATE_ABOUT.format(what="cube", whose="first cube's")
    return VALIDATE_ABOUT.format(what="gripper", whose="gripper's (pinch site)")


def write_validate_recording(
    path: str | Path, v: OpenLoopResult, spec: ManipSpaceSpec, n_starts: int
) -> None:
    """Write validate's recording of the first `n_starts` start states of every mode to `path`
    (.rrd), atomically (module docstring)."""
    n = min(n_starts, len(v.starts))
    views = []
    rec = rr.RecordingStream("oposm_validate", recording_id="oposm-validate")
    with atomic_path(path) as tmp:
        try:
            rec.save(tmp)
            rec.log("about", rr.TextDocument(about(spec), media_type="text/markdown"), static=True)
            for mode, r in v.modes.items():
                row = []
                for i in range(n):
                    base = f"{mode}/start_{i}"
                    rows = slice(i * v.repeats, (i + 1) * v.repeats)
                    real = tracked(spec, r.real[rows])  # [R, LH + 1, 3]
                    ends = real[:, v.horizon :: v.horizon]
                    tawm = tracked(spec, r.tawm_mean[rows])  # [R, L, 3]
                    single = tracked(spec, r.single_step[rows])
                    rec.log(
                        f"{base}/real",
                        rr.LineStrips3D(list(real), colors=PATH, radii=0.002),
                        static=True,
                    )
                    rec.log(
                        f"{base}/real_ends",
                        rr.Points3D(ends.reshape(-1, 3), colors=PATH, radii=0.006),
                        static=True,
                    )
                    rec.log(
                        f"{base}/tawm_ends",
                        rr.Points3D(tawm.reshape(-1, 3), colors=PLAN, radii=0.008),
                        static=True,
                    )
                    rec.log(
                        f"{base}/single_step",
                        rr.LineStrips3D(list(single), colors=SINGLE, radii=0.002),
                        static=True,
                    )
                    error = np.linalg.norm(real[:, -1] - tawm[:, -1], axis=-1).mean()
                    row.append(
                        rrb.Spatial3DView(
                            name=f"{mode} {i} · TAWM end {100 * error:.1f} cm off",
                            origin=f"/{base}",
                        )
                    )
                views.append(rrb.Horizontal(*row))
            if n:
                rec.send_blueprint(
                    rrb.Blueprint(
                        rrb.Horizontal(
                            rrb.Vertical(*views),
                            rrb.TextDocumentView(name="about", contents="/about"),
                            column_shares=[5, 1],
                        ),
                        collapse_panels=True,
                    ),
                    make_default=True,
                )
            rec.flush()
        finally:
            rec.disconnect()
