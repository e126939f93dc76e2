"""Generated episodes kept in chunks while a dataset is made, so that a killed ingest resumes
from the chunks it had finished instead of from its first episode.

A generator's episodes are functions of their own seeds, so a chunk read back is the chunk that
would be made again: the arrays round-trip bit for bit through safetensors, the scalars through
JSON (in the file's metadata). The chunks live in a folder keyed by the dataset's full
description (`DatasetInfo`: recipe, sizes, seed, noise, the expert's sha256) and the CPU
arithmetic mode; the ingest stage deletes it once the MCAP is written. Nothing is unpickled.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from safetensors import SafetensorError, safe_open
from safetensors.numpy import load_file, save_file

from pipeline import cpu_math
from pipeline.dataset import DatasetInfo
from pipeline.errors import UserError
from pipeline.io import atomic_path

log = logging.getLogger(__name__)

FORMAT = 1
CHUNK = 100  # episodes per file: at most one chunk's work is lost to a kill


def cache_folder(root: Path, info: DatasetInfo) -> Path:
    """Where the chunks of the dataset `info` describes are kept, under `root`."""
    what = {"format": FORMAT, "info": asdict(info), "cpu_math": cpu_math.mode()}
    key = hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]
    return root / f"{info.name}-{key}"


def cached_episodes(
    make: Callable[[Sequence[int]], Iterator[dict[str, Any]]],
    count: int,
    folder: Path | None,
    chunk: int | None = None,
) -> Iterator[dict[str, Any]]:
    """Episodes 0 .. count - 1 in order, `make(indices)` yielding those of `indices` in order.

    With a `folder`, every `chunk` (default `CHUNK`) episodes are saved there as a file as soon
    as they are made, and the files already there are read back instead of made again (one
    `make` call over all the missing episodes, so that a pool of workers stays busy across
    chunks).
    """
    if folder is None:
        yield from make(range(count))
        return
    chunk = chunk or CHUNK
    chunks = [range(s, min(s + chunk, count)) for s in range(0, count, chunk)]
    kept = {c.start for c in chunks if _complete(_chunk_path(folder, c), len(c))}
    missing = [k for c in chunks if c.start not in kept for k in c]
    if kept:
        log.info(
            "resuming: %d of %d episodes read back from %s", count - len(missing), count, folder
        )
    made = make(missing) if missing else iter(())
    try:
        for c in chunks:
            path = _chunk_path(folder, c)
            if c.start in kept:
                yield from _read(path)
                continue
            episodes = [next(made) for _ in c]
            _write(path, episodes)
            yield from episodes
    finally:
        close = getattr(made, "close", None)
        if close is not None:
            close()  # its workers stop now, not when it is collected


def clear(root: Path) -> None:
    """Delete the kept chunks under `root` (once the dataset made from them is written)."""
    shutil.rmtree(root, ignore_errors=True)


def _chunk_path(folder: Path, c: range) -> Path:
    return folder / f"episodes-{c.start:09d}-{c.stop:09d}.safetensors"


def _complete(path: Path, count: int) -> bool:
    """A chunk file of `count` episodes whose header reads and whose size is the one its header
    declares (the arrays are read later); anything else is made again."""
    try:
        with path.open("rb") as f:
            n = int.from_bytes(f.read(8), "little")
            header = json.loads(f.read(n))
        meta = json.loads(header.get("__metadata__", {}).get("episodes", "null"))
        ends = [v["data_offsets"][1] for k, v in header.items() if k != "__metadata__"]
        whole = path.stat().st_size == 8 + n + max(ends, default=0)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False
    ours = isinstance(meta, dict) and meta.get("format") == FORMAT
    return whole and ours and meta.get("count") == count


def _write(path: Path, episodes: list[dict[str, Any]]) -> None:
    arrays: dict[str, np.ndarray] = {}
    scalars, keys = [], []
    for i, ep in enumerate(episodes):
        keys.append(list(ep))  # read back in the same order
        plain = {}
        for key, value in ep.items():
            if isinstance(value, np.ndarray):
                arrays[f"{i}.{key}"] = np.ascontiguousarray(value)
            elif isinstance(value, np.generic):
                plain[key] = value.item()
            else:
                plain[key] = value  # JSON's: bool, int, float, str, None
        scalars.append(plain)
    meta = {"format": FORMAT, "count": len(episodes), "keys": keys, "scalars": scalars}
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        save_file(arrays, str(tmp), metadata={"episodes": json.dumps(meta)})


def _read(path: Path) -> list[dict[str, Any]]:
    try:
        with safe_open(str(path), framework="numpy") as f:
            meta = json.loads(f.metadata()["episodes"])
        arrays = load_file(str(path))
        episodes = [
            {key: scalars[key] if key in scalars else arrays[f"{i}.{key}"] for key in keys}
            for i, (keys, scalars) in enumerate(zip(meta["keys"], meta["scalars"], strict=True))
        ]
    except (OSError, ValueError, KeyError, SafetensorError) as exc:
        raise UserError(
            f"{path} (episodes kept by an earlier ingest) is unreadable ({exc}); delete "
            f"{path.parent} and run ingest again"
        ) from exc
    return episodes
