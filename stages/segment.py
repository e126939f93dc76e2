"""Segment stage: an MCAP dataset into sub-trajectory windows split by episode."""

from __future__ import annotations

import logging
import time

from pipeline.config import Params
from pipeline.envs.spec import check_physics_dim, make_env_spec
from pipeline.errors import UserError
from pipeline.paths import Paths
from pipeline.recording import iter_episodes, read_info
from pipeline.segments import Segments, build_segments, write_segments
from stages.report import report_files, write_report

log = logging.getLogger(__name__)


def run(params: Params, paths: Paths) -> Segments:
    """Read `data/demos/<name>.mcap`, write `data/segments/<name>/` and `reports/segment/`."""
    cfg = params.segment
    source = paths.existing(paths.demos(params.ingest.name))
    destination = paths.segments(params.ingest.name)
    paths.check(report_files(paths, "segment"), [destination])
    start = time.perf_counter()
    info = read_info(source)
    check_physics_dim(
        info,
        str(source),
        "it was written for another model; record or import it again (`oposm ingest`)",
    )
    exclude = None
    if cfg.exclude_fallen:
        try:
            exclude = getattr(make_env_spec(info.env_id, info.env_kwargs), "fallen", None)
        except UserError as exc:
            raise UserError(f"segment.exclude_fallen: {exc}; or set it to false") from exc
        if exclude is None:
            raise UserError(
                f"segment.exclude_fallen: the agent of {info.env_id} cannot fall; set it to false"
            )
    segments = build_segments(
        iter_episodes(source),
        info,
        window=cfg.window,
        stride=cfg.stride,
        split_fractions=cfg.split.model_dump(),
        seed=cfg.seed,
        exclude=exclude,
    )
    with paths.staged(report_files(paths, "segment"), [destination]) as out:  # all or nothing
        write_segments(segments, out.folder(destination))
        elapsed = time.perf_counter() - start
        summary = segments.summary()
        report = {f"{s}_{k}": v for s, d in summary.items() for k, v in d.items()}
        write_report(paths, "segment", {**report, "seconds": elapsed}, out)
    for split, counts in summary.items():
        log.info(
            "%-10s %4d episodes %8d steps %8d windows",
            split,
            counts["episodes"],
            counts["steps"],
            counts["windows"],
        )
    return segments
