"""Data benchmarks (`oposm bench data`, `oposm bench import`): ingest, segment, import speed."""

from __future__ import annotations

import contextlib
import os
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import yaml

from pipeline.config import Params
from pipeline.paths import Paths


def bench_data(params: Params, steps: int, episode_steps: int = 1000) -> dict[str, float]:
    """Time ingest (generate + write + read back + check) and segment on about `steps` steps.

    Segment runs as its own `oposm segment` process so that its peak resident memory
    (`ru_maxrss` of the child) is the stage's, not this process's.
    """
    from stages import ingest

    params = params.model_copy(deep=True)
    params.ingest.episodes = max(3, steps // episode_steps)
    params.ingest.episode_steps = episode_steps
    total = params.ingest.episodes * episode_steps
    with tempfile.TemporaryDirectory(prefix="oposm-bench-") as root:
        paths = Paths(Path(root) / "data")
        start = time.perf_counter()
        ingested = ingest.run(params, paths, progress=False)
        ingest_s = time.perf_counter() - start

        params_file = Path(root) / "params.yaml"
        params_file.write_text(yaml.safe_dump(params.model_dump(mode="json")))
        cli = Path(__file__).resolve().parents[1] / "cli.py"
        command = [sys.executable, str(cli), "segment", "-p", str(params_file)]
        start = time.perf_counter()
        subprocess.run([*command, "--data", str(paths.root)], check=True, capture_output=True)
        segment_s = time.perf_counter() - start
    peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return {
        "steps": float(total),
        "generate_write_steps_per_s": ingested["generate_steps_per_s"],
        "ingest_total_steps_per_s": total / ingest_s,
        "mcap_bytes_per_step": ingested["bytes_per_step"],
        "segment_seconds": segment_s,
        "segment_steps_per_s": total / segment_s,
        "segment_peak_rss_mib": peak_kib / 1024,
    }


IMPORT_SOURCES = ("lerobot", "d4rl", "minari")


@contextlib.contextmanager
def _minari_root(path: Path) -> Iterator[None]:
    """Point Minari's dataset store (`MINARI_DATASETS_PATH`) at `path` for a while."""
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(path)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


def _write_minari(mcap: Path, dataset_id: str) -> None:
    """Store an MCAP dataset as a Minari dataset with `minari.create_dataset_from_buffers`.

    Each episode gets PointMaze's dict observations and N + 1 of them, as Minari stores them; the
    extra final one repeats the last state (the importer drops it).
    """
    import minari
    from minari.data_collector import EpisodeBuffer

    from pipeline.envs.physics import register_envs
    from pipeline.recording import iter_episodes, read_info

    info = read_info(mcap)
    register_envs()
    buffers = []
    for ep in iter_episodes(mcap):
        obs = np.concatenate([ep.observations, ep.observations[-1:]])
        goal = np.concatenate([ep.goals, ep.goals[-1:]])
        n = len(ep)
        buffers.append(
            EpisodeBuffer(
                id=ep.index,
                observations={
                    "achieved_goal": obs[:, :2],
                    "desired_goal": goal,
                    "observation": obs,
                },
                actions=ep.actions,
                rewards=np.zeros(n),
                terminations=np.zeros(n, bool),
                truncations=np.arange(n) == n - 1,
                infos={},
            )
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # advice to set author, links, eval env
        minari.create_dataset_from_buffers(
            dataset_id, buffers, env=info.env_id, algorithm_name="oposm expert"
        )


def _build(source: str, mcap: Path, root: Path) -> dict[str, object]:
    """Write the MCAP dataset in `source`'s format under `root`; return the ingest section."""
    from pipeline.recording import iter_episodes, read_info
    from pipeline.sources import export_lerobot, write_d4rl

    if source == "lerobot":
        export_lerobot(mcap, root / "lerobot")
        return {"root": str(root / "lerobot"), "repo_id": "local/bench"}
    if source == "d4rl":
        write_d4rl(root / "bench.hdf5", iter_episodes(mcap), read_info(mcap))
        return {"path": str(root / "bench.hdf5"), "env_id": read_info(mcap).env_id}
    _write_minari(mcap, "oposm/bench-v0")
    return {"dataset_id": "oposm/bench-v0"}


def bench_import(
    params: Params, frames: int = 100_000, sources: tuple[str, ...] = IMPORT_SOURCES
) -> dict[str, float]:
    """Import throughput per source on a dataset of about `frames` frames.

    The built-in expert generates the data once (`params.ingest`, episodes of
    `ingest.episode_steps`); each source's own library writes it in that format (LeRobot's
    writer via `oposm export lerobot`, h5py in D4RL's layout,
    `minari.create_dataset_from_buffers`). Then, per source: `read` = open and stream all
    episodes through the importer (library imports already done), `ingest` = the whole
    `oposm ingest` (read + MCAP write + read back + maze checks).
    """
    from pipeline.sources import open_source
    from stages import ingest

    params = params.model_copy(deep=True)
    cfg = params.ingest
    cfg.source, cfg.name = "maze", "bench"
    cfg.episodes = max(3, -(-frames // cfg.episode_steps))
    out: dict[str, float] = {"frames": float(cfg.episodes * cfg.episode_steps)}
    with tempfile.TemporaryDirectory(prefix="oposm-bench-") as tmp:
        root = Path(tmp)
        paths = Paths(root / "data")
        ingest.run(params, paths, progress=False)
        mcap = paths.demos("bench")
        with _minari_root(root / "minari"):
            for source in sources:
                section = _build(source, mcap, root)
                run = params.model_copy(deep=True)
                run.ingest.source, run.ingest.name = source, f"bench-{source}"
                setattr(run.ingest, source, getattr(run.ingest, source).model_copy(update=section))
                start = time.perf_counter()
                steps = sum(len(ep) for ep in open_source(run.ingest).episodes)
                out[f"{source}_read_frames_per_s"] = steps / (time.perf_counter() - start)
                start = time.perf_counter()
                ingest.run(run, paths, progress=False)
                out[f"{source}_ingest_frames_per_s"] = steps / (time.perf_counter() - start)
    return out
