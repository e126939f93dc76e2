"""Ingest stage: demonstrations into one checked MCAP dataset, `data/demos/<name>.mcap`.

Episodes generated with OGBench's recipes are kept in `data/scratch/ingest/<name>/` in chunks as
they are made (`pipeline.sources.episode_cache`): a killed ingest, run again with the same
params, reads the finished chunks back and writes the same file.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from pipeline.config import Params
from pipeline.dataset import DatasetInfo, Episode
from pipeline.envs.disturbance import Pushes
from pipeline.envs.manipspace.env import is_manipspace
from pipeline.envs.maze.checks import DatasetReport, check_maze_dataset, raise_for_problems
from pipeline.envs.maze.generate import dataset_info, generate_episodes
from pipeline.envs.spec import check_physics_dim
from pipeline.errors import UserError
from pipeline.paths import Paths
from pipeline.recording import iter_episodes, write_dataset
from pipeline.sources.episode_cache import clear as clear_episodes
from stages.report import report_files, write_report

log = logging.getLogger(__name__)


def _source(
    params: Params, progress: bool, cache_root: Path
) -> tuple[DatasetInfo, Iterator[Episode]]:
    """The dataset's metadata and episode stream: generated (maze) or imported; episodes made
    with OGBench's recipes are kept under `cache_root` as they are made."""
    cfg = params.ingest
    pushes = Pushes(**cfg.disturbance.model_dump())
    if cfg.source == "maze":
        info = dataset_info(
            cfg.env_id,
            cfg.name,
            cfg.seed,
            cfg.expert,
            cfg.episodes,
            cfg.episode_steps,
            disturbance=pushes,
        )
        episodes = generate_episodes(
            cfg.env_id,
            cfg.episodes,
            cfg.episode_steps,
            cfg.seed,
            cfg.expert,
            progress=progress,
            disturbance=pushes,
        )
        return info, episodes
    if pushes.active:
        raise UserError(
            f"ingest.disturbance: pushes apply to the built-in expert's data (source: maze) "
            f"only, not to source: {cfg.source}; set ingest.disturbance.probability=0"
        )
    from pipeline.sources import open_source

    imported = open_source(cfg, progress=progress, cache_root=cache_root)
    return imported.info, imported.episodes


def _source_file(params: Params) -> str | None:
    """The file or folder an import reads (for messages about its data); None when generated."""
    cfg = params.ingest
    if cfg.source == "d4rl":
        return cfg.d4rl.path
    if cfg.source == "lerobot":
        return cfg.lerobot.root or cfg.lerobot.repo_id
    if cfg.source == "minari":
        return cfg.minari.path or cfg.minari.dataset_id
    if cfg.source == "ogbench":
        return cfg.ogbench.path
    return None


def _check(path: Path, info: DatasetInfo, max_fallen_share: float) -> DatasetReport | None:
    """Maze checks of the written file: all of them for the built-in expert, OGBench's own for
    OGBench data (`check_ogbench_dataset`; ant falls up to `max_fallen_share` of the steps; the
    manipulation envs': `check_manipulation_dataset`, states restored exactly); for
    another import, only when its env is a PointMaze we simulate (walls, bounds, jumps, physics,
    clock; episodes are not assumed continuous and someone else's demonstrator is not judged on
    its goal rate)."""
    from pipeline.sources import is_simulated_maze

    if info.source == "maze":
        return check_maze_dataset(iter_episodes(path), info)
    if info.source == "ogbench" and is_manipspace(info.env_id):
        from pipeline.sources.ogbench.manipulation import check_manipulation_dataset

        return check_manipulation_dataset(iter_episodes(path), info)
    if info.source == "ogbench":
        from pipeline.sources.ogbench import check_ogbench_dataset

        return check_ogbench_dataset(iter_episodes(path), info, max_fallen_share)
    if not is_simulated_maze(info):
        log.info("no maze checks: %s is not in a PointMaze we simulate", info.name)
        return None
    return check_maze_dataset(
        iter_episodes(path),
        info,
        continuous=False,
        min_goals_per_1000_steps=0.0,
        max_goal_segment=sys.maxsize,
    )


def run(params: Params, paths: Paths, progress: bool = True) -> dict[str, float]:
    """Generate (or import) the demonstrations, write the MCAP, check it, report metrics.

    Physics states of the wrong size for the environment fail first (`check_physics_dim`). The
    file is written and then read back and checked (`check_maze_dataset`, for simulated mazes)
    under a temporary name; only a dataset that passes is renamed into place. A bad import fails
    before anything is written, or while streaming, leaving no file behind.
    """
    cfg = params.ingest
    dest = paths.demos(cfg.name)
    kept = paths.scratch("ingest", cfg.name)  # generated episodes, until the file is written
    with paths.staged([dest, *report_files(paths, "ingest")]) as out:  # checked before the work
        start = time.perf_counter()
        info, episodes = _source(params, progress, kept)
        check_physics_dim(
            info,
            str(dest),
            "the source was recorded in another MuJoCo model: import it with the env id of that "
            "model, or with none",
        )
        tmp = out.file(dest)
        written = write_dataset(tmp, info, episodes, shown_as=dest, source=_source_file(params))
        generated = time.perf_counter() - start
        report = _check(tmp, info, cfg.ogbench.max_fallen_share)
        if report is not None:
            raise_for_problems(report, name=str(dest))
        elapsed = time.perf_counter() - start
        metrics = {
            "episodes": written.episodes,
            "steps": written.steps,
            "bytes": written.bytes,
            "bytes_per_step": written.bytes / written.steps,
            "generate_steps_per_s": written.steps / generated,
            "seconds": elapsed,
            **(report.metrics() if report is not None else {}),
        }
        write_report(paths, "ingest", metrics, out)
    clear_episodes(kept)  # the file is written: the kept episodes are no longer needed
    log.info(
        "wrote %s (%s): %d episodes, %d steps, %.1f bytes/step, %.0f steps/s%s",
        dest,
        info.source,
        written.episodes,
        written.steps,
        metrics["bytes_per_step"],
        metrics["generate_steps_per_s"],
        "; checks passed" if report is not None else "",
    )
    return metrics
