"""Sub-trajectory windows for skill learning, split by episode, with train-only normalization.

A window is T + 1 consecutive states and the T actions between them (the paper's tau_T; T + 1 = 40
for mazes). Episodes are stored once, concatenated; a window is just the global index of its first
step, so overlapping windows are never materialized. Splits are drawn **by episode**, so no window
of the validation or test split overlaps a training window (the original code's split by raw
timestep leaked overlapping windows across splits).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, Field
from safetensors import SafetensorError
from safetensors.numpy import load_file, save_file

from pipeline.dataset import DatasetInfo, Episode
from pipeline.errors import UserError
from pipeline.io import atomic_dir
from pipeline.readback import READBACK_CONFIG, Finite, PositiveFinite, Size, read_json, validated

log = logging.getLogger(__name__)

SPLITS = ("train", "validation", "test")
FORMAT_VERSION = 1
_ARRAYS_FILE = "segments.safetensors"
_META_FILE = "segments.json"
_STD_FLOOR = 1e-6


class _SavedStats(BaseModel):
    state_mean: list[Finite]
    state_std: list[PositiveFinite]
    action_mean: list[Finite]
    action_std: list[PositiveFinite]


class _SavedIndex(BaseModel):
    """segments.json as `load_segments` reads it back (checked before it is used)."""

    model_config = READBACK_CONFIG
    dataset: DatasetInfo
    window: int = Field(ge=2)
    stride: Size
    seed: int
    stats: _SavedStats


@dataclass
class NormStats:
    """Per-dimension mean and std of states and actions over the train split's steps."""

    state_mean: np.ndarray
    state_std: np.ndarray
    action_mean: np.ndarray
    action_std: np.ndarray

    def to_json(self) -> dict[str, list[float]]:
        return {k: v.astype(float).tolist() for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_json(cls, data: dict[str, list[float]]) -> NormStats:
        return cls(**{k: np.asarray(v, dtype=np.float64) for k, v in data.items()})


@dataclass
class Segments:
    """Episodes stored once plus per-split window start indices.

    Attributes:
        info: Provenance of the source dataset.
        window: States per window (T + 1).
        stride: Steps between consecutive window starts.
        states: `[S, state_dim]` float32, all kept episodes concatenated.
        actions: `[S, action_dim]` float32.
        physics: `[S, physics_dim]` float64 simulator states, or None.
        episode_offsets: `[E + 1]` int64; episode e spans `[offsets[e], offsets[e + 1])`.
        episode_index: `[E]` int64, the episode's index in the source dataset.
        episode_split: `[E]` int8, index into `SPLITS`.
        starts: Per split, `[W_split]` int64 global index of each window's first step.
        stats: Normalization statistics (train split only).
        seed: Seed of the split shuffle.
    """

    info: DatasetInfo
    window: int
    stride: int
    states: np.ndarray
    actions: np.ndarray
    physics: np.ndarray | None
    episode_offsets: np.ndarray
    episode_index: np.ndarray
    episode_split: np.ndarray
    starts: dict[str, np.ndarray]
    stats: NormStats
    seed: int

    @property
    def horizon(self) -> int:
        """T: actions per window."""
        return self.window - 1

    def episodes_in(self, split: str) -> np.ndarray:
        """Positions (into `episode_offsets`) of the episodes assigned to `split`."""
        return np.flatnonzero(self.episode_split == SPLITS.index(split))

    def windows(self, split: str, idx: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Gather windows of `split` (all, or those at positions `idx`) in one vectorized index.

        Returns:
            states `[B, T + 1, state_dim]` and actions `[B, T, action_dim]`, float32.
        """
        starts = self.starts[split] if idx is None else self.starts[split][idx]
        steps = starts[:, None] + np.arange(self.window)[None, :]
        return self.states[steps], self.actions[steps[:, :-1]]

    def summary(self) -> dict[str, dict[str, int]]:
        """Episodes, steps and windows per split."""
        lengths = np.diff(self.episode_offsets)
        out = {}
        for i, split in enumerate(SPLITS):
            mask = self.episode_split == i
            out[split] = {
                "episodes": int(mask.sum()),
                "steps": int(lengths[mask].sum()),
                "windows": int(self.starts[split].size),
            }
        return out


def _assign_splits(n: int, fractions: dict[str, float], seed: int) -> np.ndarray:
    """Shuffle n episodes (seeded) and give each split round(fraction * n) of them.

    Every split with a non-zero fraction gets at least one episode when there are enough episodes;
    the remainder goes to train.
    """
    wanted = {s: fractions[s] for s in SPLITS}
    counts = {s: int(round(f * n)) for s, f in wanted.items()}
    for s in ("validation", "test"):
        if wanted[s] > 0 and counts[s] == 0:
            counts[s] = 1
    counts["train"] = n - counts["validation"] - counts["test"]
    if counts["train"] < 1:
        raise UserError(
            f"only {n} usable episodes: too few to split into train/validation/test; "
            "record more episodes (ingest.episodes) or set a split fraction to 0"
        )
    labels = np.repeat(np.arange(len(SPLITS), dtype=np.int8), [counts[s] for s in SPLITS])
    return labels[np.random.default_rng(seed).permutation(n)]


def _norm_stats(states: np.ndarray, actions: np.ndarray) -> NormStats:
    return NormStats(
        state_mean=states.mean(0, dtype=np.float64),
        state_std=np.maximum(states.std(0, dtype=np.float64), _STD_FLOOR),
        action_mean=actions.mean(0, dtype=np.float64),
        action_std=np.maximum(actions.std(0, dtype=np.float64), _STD_FLOOR),
    )


def build_segments(
    episodes: Iterable[Episode],
    info: DatasetInfo,
    window: int,
    stride: int = 1,
    split_fractions: dict[str, float] | None = None,
    seed: int = 0,
    exclude: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Segments:
    """Index windows of `window` states over `episodes` and split them by episode.

    Episodes shorter than `window` hold no window; they are dropped with a warning. With
    `exclude` (an episode's states `[T, S]` -> bool `[T]`), windows holding an excluded step are
    left out of every split (e.g. the ant's fallen steps: `segment.exclude_fallen`).

    Raises:
        UserError: no episodes, no episode long enough, or too few episodes for the splits.
    """
    fractions = split_fractions or {"train": 0.8, "validation": 0.1, "test": 0.1}
    states, actions, physics, kept, lengths = [], [], [], [], []
    total = short = 0
    for ep in episodes:
        total += 1
        if len(ep) < window:
            short += 1
            continue
        states.append(ep.observations.astype(np.float32))
        actions.append(ep.actions.astype(np.float32))
        if ep.physics is not None:
            physics.append(ep.physics)
        kept.append(ep.index)
        lengths.append(len(ep))
    if total == 0:
        raise UserError(f"dataset '{info.name}' has no episodes; re-run `oposm ingest`")
    if not kept:
        raise UserError(
            f"all {total} episodes of '{info.name}' are shorter than the window of {window} "
            "states; lower segment.window or record longer episodes"
        )
    if short:
        log.warning("dropped %d of %d episodes shorter than the window (%d)", short, total, window)

    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    split = _assign_splits(len(kept), fractions, seed)
    starts, excluded = {}, 0
    for i, name in enumerate(SPLITS):
        per_episode = []
        for e in np.flatnonzero(split == i):
            local = np.arange(0, lengths[e] - window + 1, stride, dtype=np.int64)
            if exclude is not None:
                bad = np.concatenate([[0], np.cumsum(exclude(states[e]), dtype=np.int64)])
                clean = bad[local + window] == bad[local]
                excluded += int((~clean).sum())
                local = local[clean]
            per_episode.append(offsets[e] + local)
        starts[name] = np.concatenate(per_episode) if per_episode else np.zeros(0, np.int64)
    if exclude is not None:
        log.info("left out %d windows holding an excluded step", excluded)

    all_states = np.concatenate(states)
    all_actions = np.concatenate(actions)
    train_steps = np.repeat(split == 0, lengths)
    return Segments(
        info=info,
        window=window,
        stride=stride,
        states=all_states,
        actions=all_actions,
        physics=np.concatenate(physics) if len(physics) == len(kept) else None,
        episode_offsets=offsets,
        episode_index=np.asarray(kept, dtype=np.int64),
        episode_split=split,
        starts=starts,
        stats=_norm_stats(all_states[train_steps], all_actions[train_steps]),
        seed=seed,
    )


def save_segments(segments: Segments, directory: str | Path) -> None:
    """Write `segments.safetensors` (arrays) and `segments.json` (metadata) atomically."""
    with atomic_dir(directory) as tmp:
        write_segments(segments, tmp)


def write_segments(segments: Segments, directory: Path) -> None:
    """Write `segments.safetensors` and `segments.json` into the (new, empty) `directory`."""
    arrays = {
        "states": segments.states,
        "actions": segments.actions,
        "episode_offsets": segments.episode_offsets,
        "episode_index": segments.episode_index,
        "episode_split": segments.episode_split,
        **{f"starts_{s}": segments.starts[s] for s in SPLITS},
    }
    if segments.physics is not None:
        arrays["physics"] = segments.physics
    meta = {
        "format_version": FORMAT_VERSION,
        "dataset": dataclasses.asdict(segments.info),
        "window": segments.window,
        "stride": segments.stride,
        "seed": segments.seed,
        "splits": segments.summary(),
        "stats": segments.stats.to_json(),
    }
    save_file({k: np.ascontiguousarray(v) for k, v in arrays.items()}, directory / _ARRAYS_FILE)
    (directory / _META_FILE).write_text(json.dumps(meta, indent=2) + "\n")


def load_segments(directory: str | Path) -> Segments:
    """Load what `save_segments` wrote (no pickle: safetensors + JSON).

    Raises:
        UserError: the directory or its files are missing, unreadable, lack an entry, or disagree
            with each other (e.g. a `segments.json` from another run than the arrays).
    """
    directory = Path(directory)
    meta_path, arrays_path = directory / _META_FILE, directory / _ARRAYS_FILE
    if not meta_path.exists() or not arrays_path.exists():
        raise UserError(f"{directory} holds no segments; run `oposm segment` first")
    fix = "re-run `oposm segment`"
    meta = read_json(meta_path, fix)
    try:
        arrays = load_file(arrays_path)
    except (OSError, ValueError, SafetensorError) as exc:
        raise UserError(
            f"{arrays_path} is unreadable: damaged or not a safetensors file ({exc}); {fix}"
        ) from exc
    if not isinstance(meta, dict):
        raise UserError(f"{meta_path} is not a JSON object; {fix}")
    if meta.get("format_version") != FORMAT_VERSION:
        raise UserError(f"{directory}: segments format is outdated; {fix}")
    index = validated(_SavedIndex, meta, meta_path, fix)
    needed = ["states", "actions", "episode_offsets", "episode_index", "episode_split"]
    missing = [k for k in [*needed, *(f"starts_{s}" for s in SPLITS)] if k not in arrays]
    if missing:
        raise UserError(f"{directory}: {_ARRAYS_FILE} has no '{missing[0]}' entry; {fix}")
    segments = Segments(
        info=index.dataset,
        window=index.window,
        stride=index.stride,
        states=arrays["states"],
        actions=arrays["actions"],
        physics=arrays.get("physics"),
        episode_offsets=arrays["episode_offsets"],
        episode_index=arrays["episode_index"],
        episode_split=arrays["episode_split"],
        starts={s: arrays[f"starts_{s}"] for s in SPLITS},
        stats=NormStats.from_json(index.stats.model_dump()),
        seed=index.seed,
    )
    problem = _inconsistency(segments)
    if problem:
        raise UserError(f"{directory}: {problem}; re-run `oposm segment`")
    return segments


def _inconsistency(seg: Segments) -> str | None:
    """What disagrees between the arrays and the metadata of loaded segments, or None."""
    n_steps = len(seg.states)
    stats = seg.stats
    expected = {
        "states": (n_steps, seg.info.state_dim),
        "actions": (n_steps, seg.info.action_dim),
        "physics": None if seg.physics is None else (n_steps, seg.info.physics_dim),
        "state stats": (seg.info.state_dim,) * 2,
        "action stats": (seg.info.action_dim,) * 2,
    }
    shapes = {
        "states": seg.states.shape,
        "actions": seg.actions.shape,
        "physics": None if seg.physics is None else seg.physics.shape,
        "state stats": (len(stats.state_mean), len(stats.state_std)),
        "action stats": (len(stats.action_mean), len(stats.action_std)),
    }
    for name, want in expected.items():
        if shapes[name] != want:
            return (
                f"{name} have shape {shapes[name]} but {_META_FILE} describes {want} "
                "(files from different runs?)"
            )
    offsets = seg.episode_offsets
    n_episodes = len(offsets) - 1
    if (
        n_episodes < 0
        or offsets[0] != 0
        or offsets[-1] != n_steps
        or np.any(np.diff(offsets) < 0)
        or len(seg.episode_index) != n_episodes
        or len(seg.episode_split) != n_episodes
    ):
        return "the episode index does not match the stored steps"
    if seg.window < 2 or seg.stride < 1:
        return f"window {seg.window} / stride {seg.stride} are invalid"
    for split, starts in seg.starts.items():
        if starts.size and (starts.min() < 0 or starts.max() + seg.window > n_steps):
            return f"{split} windows of {seg.window} states run past the {n_steps} stored steps"
    return None
