"""Benchmarks that print numbers (never timed tests): `oposm bench data`."""

from __future__ import annotations

import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

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
