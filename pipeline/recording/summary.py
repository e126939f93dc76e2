"""What `oposm inspect` shows about a dataset, from the MCAP summary section and metadata only."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pipeline.recording.files import open_dataset


def summarize(path: str | Path) -> dict[str, Any]:
    """Describe a dataset without reading its messages.

    Returns:
        A JSON-serializable dict: file (path, bytes, profile, library, format_version,
        compression, chunks, messages, bytes_per_step), episodes, steps, episode_length
        (min/mean/max), duration_s (simulated seconds from the first step to the end of the last,
        assuming it lasts one control period), and the dataset info (names, units, dims, control
        period, source, env id and kwargs, seed, generator params, versions).

    Raises:
        UserError: The file is missing, not MCAP, truncated or corrupt, or not an oposm dataset.
    """
    with open_dataset(path) as dataset:
        info, lengths, summary = dataset.info, dataset.lengths, dataset.summary
        stats = summary.statistics
        assert stats is not None  # open_dataset checked the message count against it
        size = dataset.path.stat().st_size
        steps = sum(lengths)
        span = (stats.message_end_time - stats.message_start_time) / 1e9
        compression = sorted({c.compression or "none" for c in summary.chunk_indexes})
        return {
            "path": str(dataset.path),
            "bytes": size,
            "profile": dataset.header.profile,
            "library": dataset.header.library,
            "format_version": dataset.format_version,
            "compression": ", ".join(compression) or "none",
            "chunks": stats.chunk_count,
            "messages": stats.message_count,
            "bytes_per_step": size / steps,
            "episodes": len(lengths),
            "steps": steps,
            "episode_length": {
                "min": min(lengths),
                "mean": steps / len(lengths),
                "max": max(lengths),
            },
            "duration_s": span + info.control_period,
            "name": info.name,
            "source": info.source,
            "env_id": info.env_id,
            "env_kwargs": info.env_kwargs,
            "seed": info.seed,
            "state_dim": info.state_dim,
            "state_names": info.state_names,
            "state_units": info.state_units,
            "action_dim": info.action_dim,
            "action_names": info.action_names,
            "action_units": info.action_units,
            "physics_dim": info.physics_dim,
            "goal_dim": info.goal_dim,
            "control_period": info.control_period,
            "generator": info.generator,
            "versions": info.versions,
        }


def _dims(names: list[str], units: list[str]) -> str:
    return ", ".join(
        f"{name} [{unit}]" if unit else name for name, unit in zip(names, units, strict=True)
    )


def _short_json(value: Any, limit: int = 200) -> str:
    text = json.dumps(value, sort_keys=True)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def format_summary(summary: dict[str, Any]) -> str:
    """Human-readable multi-line text of a `summarize` dict (long JSON values are cut short)."""
    s = summary
    length = s["episode_length"]
    period = s["control_period"]
    lines = [
        f"{s['path']}  ({s['bytes'] / 1e6:.2f} MB, {s['compression']}, {s['chunks']} chunks, "
        f"{s['messages']} messages, {s['bytes_per_step']:.1f} bytes/step)",
        f"  format      {s['profile']} v{s['format_version']}, written by {s['library']}",
        f"  dataset     {s['name']}  (source {s['source']}, env {s['env_id'] or '-'}, "
        f"seed {s['seed']})",
        f"  episodes    {s['episodes']}  ({s['steps']} steps; length min {length['min']} / "
        f"mean {length['mean']:.1f} / max {length['max']})",
        f"  time        control period {period:g} s ({1 / period:g} Hz), "
        f"{s['duration_s']:.2f} simulated s",
        f"  state  [{s['state_dim']}]  {_dims(s['state_names'], s['state_units'])}",
        f"  action [{s['action_dim']}]  {_dims(s['action_names'], s['action_units'])}",
        f"  physics dim {s['physics_dim']}, goal dim {s['goal_dim']}",
        f"  env kwargs  {_short_json(s['env_kwargs'])}",
        f"  generator   {_short_json(s['generator'])}",
        f"  versions    {_short_json(s['versions'])}",
    ]
    return "\n".join(lines)
