"""Ingest stage: demonstrations into one checked MCAP dataset, `data/demos/<name>.mcap`."""

from __future__ import annotations

import logging
import time

from pipeline.config import Params
from pipeline.envs import check_maze_dataset, dataset_info, generate_episodes, raise_for_problems
from pipeline.io import atomic_path, write_json
from pipeline.paths import Paths
from pipeline.recording import iter_episodes, write_dataset

log = logging.getLogger(__name__)


def run(params: Params, paths: Paths, progress: bool = True) -> dict[str, float]:
    """Generate (or import) the demonstrations, write the MCAP, check it, report metrics.

    The file is written and then read back and checked (`check_maze_dataset`) under a temporary
    name; only a dataset that passes is renamed into place.
    """
    cfg = params.ingest
    dest = paths.demos(cfg.name)
    start = time.perf_counter()
    info = dataset_info(cfg.env_id, cfg.name, cfg.seed, cfg.expert, cfg.episodes, cfg.episode_steps)
    episodes = generate_episodes(
        cfg.env_id, cfg.episodes, cfg.episode_steps, cfg.seed, cfg.expert, progress=progress
    )
    with atomic_path(dest) as tmp:
        written = write_dataset(tmp, info, episodes)
        generated = time.perf_counter() - start
        report = check_maze_dataset(iter_episodes(tmp), info)
        raise_for_problems(report, name=str(dest))
    elapsed = time.perf_counter() - start
    metrics = {
        "episodes": written.episodes,
        "steps": written.steps,
        "bytes": written.bytes,
        "bytes_per_step": written.bytes / written.steps,
        "generate_steps_per_s": written.steps / generated,
        "seconds": elapsed,
        **report.metrics(),
    }
    write_json(paths.report("ingest"), metrics)
    log.info(
        "wrote %s: %d episodes, %d steps, %.1f bytes/step, %.0f steps/s; checks passed",
        dest,
        written.episodes,
        written.steps,
        metrics["bytes_per_step"],
        metrics["generate_steps_per_s"],
    )
    return metrics
