"""Import a LeRobot dataset (format v3.0) through the `lerobot` library (`LeRobotDataset`).

The dataset comes from a local folder (`root`, the one holding `meta/info.json`), from the local
cache `$HF_LEROBOT_HOME/<repo_id>`, or, if neither has it, from the Hugging Face hub (the only
case that uses the network). The state is the concatenation of `state_features` in the order
given, the action is `action_feature`; `next.reward`, `next.done` and `next.success` become
rewards, terminals and goal_reached when present. Image and video features are skipped with a
warning: the pipeline is state-based. Episodes and frame indices carry over; the time of a frame
is `frame_index / fps` on one clock for the whole dataset (timestamps are checked against it).
Tasks and feature names go into `DatasetInfo`.

A dataset exported by `oposm export lerobot` carries our metadata in `meta/oposm.json`; it is
read back (env id, maze, names and units, goals and physics) when the default features are used.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from pipeline.dataset import DatasetInfo, Episode
from pipeline.errors import UserError
from pipeline.recording.metadata import decode_info
from pipeline.sources.common import (
    Clock,
    ImportedDataset,
    missing,
    numeric,
    unique_names,
    vector_names,
    versions,
    with_progress,
)

log = logging.getLogger(__name__)

SIDECAR = "meta/oposm.json"
DEFAULT_STATE, DEFAULT_ACTION = ["observation.state"], "action"
GOAL_FEATURE, PHYSICS_FEATURE = "observation.goal", "observation.physics"
# Optional per-step scalars: LeRobot feature -> Episode field.
FLAGS = {"next.reward": "rewards", "next.done": "terminals", "next.success": "goal_reached"}
VISUAL = ("image", "video")
# LeRobot's own default tolerance between timestamps and frame_index / fps (seconds).
TOLERANCE_S = 1e-4
CONVERT = "python -m lerobot.scripts.convert_dataset_v21_to_v30 --repo-id={repo_id}"


def _check_local(root: Path, repo_id: str) -> None:
    """Fail early, without touching the network, on a folder that lerobot 0.6 cannot read."""
    if not root.is_dir():
        raise UserError(f"LeRobot dataset folder {root} does not exist")
    info_path = root / "meta" / "info.json"
    if not info_path.is_file():
        held = ", ".join(sorted(p.name for p in root.iterdir())[:8]) or "nothing"
        raise UserError(f"{root} is not a LeRobot dataset: no meta/info.json (it holds {held})")
    try:
        meta = json.loads(info_path.read_text())
        version = str(meta["codebase_version"])
    except (ValueError, KeyError, TypeError) as exc:
        raise UserError(f"{info_path} is malformed (no codebase_version): {exc}") from exc
    if version == "v2.1":
        command = CONVERT.format(repo_id=repo_id) + f" --root={root} --push-to-hub=false"
        raise UserError(
            f"{root} is a LeRobot v2.1 dataset; lerobot 0.6 reads v3.0: convert it with `{command}`"
        )
    if not version.startswith("v3."):
        raise UserError(f"{root} is a LeRobot {version} dataset; lerobot 0.6 reads only v3.x")
    if not meta.get("total_frames"):
        raise UserError(f"{root} holds no frames (empty LeRobot dataset)")


def _open(repo_id: str, root: Path | None) -> Any:
    """The `LeRobotDataset` (metadata and parquet data; videos are never downloaded)."""
    import httpx
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.datasets.utils import CompatibilityError
    from lerobot.utils.constants import HF_LEROBOT_HOME

    if root is None and (HF_LEROBOT_HOME / repo_id).is_dir():
        root = HF_LEROBOT_HOME / repo_id
    if root is not None:
        _check_local(root, repo_id)
    try:
        # pyav: skip lerobot's torchcodec probe, which logs FFmpeg load tracebacks; videos are
        # skipped anyway.
        return LeRobotDataset(repo_id, root=root, download_videos=False, video_backend="pyav")
    except CompatibilityError as exc:
        command = CONVERT.format(repo_id=repo_id)
        raise UserError(
            f"{repo_id} is a LeRobot v2.1 dataset; convert it with `{command}`"
        ) from exc
    except (OSError, ValueError, httpx.HTTPError) as exc:  # httpx: the hub is unreachable
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        where = f"in {root}" if root else f"fetched from the hub: not in {HF_LEROBOT_HOME}"
        raise UserError(f"cannot load LeRobot dataset {repo_id!r} ({where}): {first}") from exc


def _numeric_feature(features: dict[str, dict], key: str, where: str) -> int:
    """Size of a 1-D numeric feature; errors name the feature and list the usable ones."""
    if key not in features:
        raise missing("feature", key, features, where)
    ft = features[key]
    if not _is_numeric(ft) or len(ft["shape"]) != 1:
        usable = [k for k, f in features.items() if _is_numeric(f) and len(f["shape"]) == 1]
        raise UserError(
            f"feature {key!r} of {where} is {ft['dtype']} of shape {tuple(ft['shape'])}, not a "
            f"numeric vector; numeric vectors: {', '.join(usable)}"
        )
    return int(ft["shape"][0])


def _is_numeric(ft: dict) -> bool:
    try:
        return np.dtype(ft["dtype"]).kind in "biuf"
    except TypeError:
        return False


def _names(ft: dict, key: str, dim: int) -> list[str]:
    names = ft.get("names")
    if isinstance(names, dict):  # e.g. {"motors": ["shoulder", ...]}
        names = [n for v in names.values() for n in (v if isinstance(v, list) else [v])]
    return vector_names(key, dim, names if isinstance(names, list) else None)


def _sidecar(root: Path, state: list[str], action: str) -> DatasetInfo | None:
    """Our metadata from `meta/oposm.json`, if present and the default features are used."""
    path = root / SIDECAR
    if not path.is_file():
        return None
    if state != DEFAULT_STATE or action != DEFAULT_ACTION:
        log.info("%s ignored: custom state/action features are selected", path)
        return None
    try:
        return decode_info(json.loads(path.read_text())["dataset"])
    except (ValueError, KeyError, TypeError) as exc:
        log.warning("%s is unreadable (%s); imported without it", path, exc)
        return None


def read_lerobot(
    repo_id: str,
    name: str,
    root: str | Path | None = None,
    state_features: list[str] | None = None,
    action_feature: str = DEFAULT_ACTION,
    progress: bool = False,
) -> ImportedDataset:
    """Open a LeRobot v3.0 dataset as a stream of episodes.

    Args:
        repo_id: Hub repo id (`user/name`); a label when `root` is given.
        name: Dataset name for `DatasetInfo`.
        root: Local dataset folder; default `$HF_LEROBOT_HOME/<repo_id>`, else the hub.
        state_features: Features concatenated, in this order, into the state.
        action_feature: The action feature.
        progress: Show a progress bar while the episodes are read.

    Raises:
        UserError: not a dataset, a v2.1 dataset (with the conversion command), missing or
            non-numeric features, an empty dataset, frames out of order.
    """
    state_features = list(state_features or DEFAULT_STATE)
    ds = _open(repo_id, Path(root) if root else None)
    meta, where = ds.meta, f"LeRobot dataset {repo_id}"
    if meta.total_frames == 0 or meta.total_episodes == 0:
        raise UserError(f"{where} holds no frames (empty dataset)")
    features = meta.features
    dims = [_numeric_feature(features, key, where) for key in state_features]
    action_dim = _numeric_feature(features, action_feature, where)
    skipped = [k for k, ft in features.items() if ft["dtype"] in VISUAL]
    if skipped:
        log.warning("skipping image/video features (the pipeline is state-based): %s", skipped)
    flags = {
        k: f
        for k, f in FLAGS.items()
        if k in features and _is_numeric(features[k]) and tuple(features[k]["shape"]) == (1,)
    }
    ours = _sidecar(Path(ds.root), state_features, action_feature)
    columns = {"state": state_features, "action": [action_feature]}
    if ours is not None and (len(ours.state_names), ours.action_dim) != (sum(dims), action_dim):
        log.warning("%s ignored: its state/action sizes differ from the features", SIDECAR)
        ours = None
    if ours is not None:
        ours = _with_extras(ours, features, columns)
    info = _info(ds, name, state_features, dims, action_feature, action_dim, skipped, ours)
    episodes = _episodes(ds, info, columns, flags)
    frames = int(meta.total_frames)
    return ImportedDataset(info, with_progress(episodes, frames, name, progress), frames)


def _with_extras(
    ours: DatasetInfo, features: dict[str, dict], columns: dict[str, list[str]]
) -> DatasetInfo:
    """Keep the sidecar's goal/physics dims only where the matching features exist."""
    for feature, field in ((GOAL_FEATURE, "goal_dim"), (PHYSICS_FEATURE, "physics_dim")):
        dim = getattr(ours, field)
        if dim and features.get(feature, {}).get("shape") == (dim,):
            columns[field] = [feature]
        else:
            setattr(ours, field, 0)
    return ours


def _info(
    ds: Any,
    name: str,
    state_features: list[str],
    dims: list[int],
    action_feature: str,
    action_dim: int,
    skipped: list[str],
    ours: DatasetInfo | None,
) -> DatasetInfo:
    meta, features = ds.meta, ds.meta.features
    tasks = [] if meta.tasks is None else meta.tasks.sort_values("task_index").index.tolist()
    task_index = {task: i for i, task in enumerate(tasks)}
    episodes = _episode_rows(meta)
    indices = episodes["episode_index"]
    generator: dict[str, Any] = {
        "repo_id": ds.repo_id,
        "root": str(Path(ds.root).resolve()),
        "codebase_version": str(meta.info.codebase_version),
        "fps": int(meta.fps),
        "robot_type": meta.robot_type,
        "state_features": state_features,
        "action_feature": action_feature,
        "skipped_features": skipped,
        "tasks": [str(t) for t in tasks],
        "episode_tasks": [[task_index.get(t, -1) for t in ts] for ts in episodes["tasks"]],
    }
    if indices != list(range(len(indices))):
        generator["source_episode_index"] = indices
    groups = [(k, _names(features[k], k, d)) for k, d in zip(state_features, dims, strict=True)]
    info = DatasetInfo(
        name=name,
        source="lerobot",
        env_id="",
        state_names=unique_names(groups),
        action_names=_names(features[action_feature], action_feature, action_dim),
        state_units=[""] * sum(dims),
        action_units=[""] * action_dim,
        control_period=1.0 / float(meta.fps),
        generator=generator,
        versions=versions("lerobot", "datasets"),
    )
    if ours is not None:  # our own export: restore what LeRobot's format cannot hold
        for field in (
            "env_id",
            "env_kwargs",
            "state_names",
            "action_names",
            "state_units",
            "action_units",
            "physics_dim",
            "goal_dim",
            "seed",
        ):
            setattr(info, field, getattr(ours, field))
        info.generator["exported"] = {k: v for k, v in ours.generator.items() if k != "maze_layout"}
        if "maze_layout" in ours.generator:
            info.generator["maze_layout"] = ours.generator["maze_layout"]
    return info


def _episodes(
    ds: Any, info: DatasetInfo, columns: dict[str, list[str]], flags: dict[str, str]
) -> Iterator[Episode]:
    """Read the parquet data one episode at a time (rows `dataset_from_index:to_index`)."""
    needed = [c for cs in columns.values() for c in cs] + list(flags)
    # Arrow, not datasets' numpy formatter: that one turns float64 features into float32.
    table = ds.hf_dataset.select_columns(
        list(dict.fromkeys([*needed, "episode_index", "frame_index", "timestamp"]))
    ).with_format("arrow")
    episodes = _episode_rows(ds.meta)
    clock, fps = Clock(info.control_period), float(ds.meta.fps)
    bounds = zip(
        episodes["episode_index"],
        episodes["dataset_from_index"],
        episodes["dataset_to_index"],
        strict=True,
    )
    for index, (source, start, stop) in enumerate(bounds):
        rows = _arrays(table[int(start) : int(stop)])
        n = int(stop) - int(start)
        _check_frames(rows, int(source), n, fps, info.name)
        parts = {field: _stack(rows, keys, n) for field, keys in columns.items()}
        extra = {
            field: rows[key].reshape(n).astype(np.float64 if field == "rewards" else bool)
            for key, field in flags.items()
        }
        yield Episode(
            index=index,
            observations=parts["state"],
            actions=parts["action"],
            time=clock.next(n),
            physics=parts.get("physics_dim"),
            goals=parts.get("goal_dim"),
            **extra,
        )


def _stack(rows: dict[str, np.ndarray], keys: list[str], n: int) -> np.ndarray:
    """The features `keys` of one episode side by side, `[n, sum of their dims]` float64."""
    return np.concatenate([numeric(rows[k].reshape(n, -1), k) for k in keys], axis=1)


def _episode_rows(meta: Any) -> dict[str, list]:
    """Per-episode metadata columns (index, tasks, row range), ordered by episode index."""
    keys = ["episode_index", "tasks", "dataset_from_index", "dataset_to_index"]
    columns = meta.episodes.select_columns(keys).to_dict()
    order = np.argsort(columns["episode_index"], kind="stable")
    return {k: [columns[k][i] for i in order] for k in keys}


def _arrays(rows: Any) -> dict[str, np.ndarray]:
    """Columns of a pyarrow table as numpy arrays (`[n]`, or `[n, dim]` for vector features)."""
    out = {}
    for name in rows.column_names:
        column = rows.column(name).combine_chunks()
        if pa.types.is_fixed_size_list(column.type) or pa.types.is_list(column.type):
            values = column.flatten().to_numpy(zero_copy_only=False)
            out[name] = values.reshape(len(column), -1)
        else:
            out[name] = column.to_numpy(zero_copy_only=False)
    return out


def _check_frames(rows: dict[str, np.ndarray], episode: int, n: int, fps: float, name: str) -> None:
    """Rows belong to `episode`, frame indices are 0..n-1, timestamps are frame_index / fps."""
    where = f"LeRobot dataset {name}, episode {episode}"
    if n == 0:
        raise UserError(f"{where} has no frames")
    if not np.all(rows["episode_index"] == episode):
        raise UserError(f"{where}: its rows hold other episodes' frames; the dataset is corrupt")
    frames = rows["frame_index"].reshape(n)
    bad = np.flatnonzero(frames != np.arange(n))
    if bad.size:
        t = int(bad[0])
        raise UserError(f"{where}: frame {t} has frame_index {frames[t]} (frames missing?)")
    stamps = rows["timestamp"].reshape(n).astype(np.float64)
    drift = np.abs(stamps - stamps[0] - np.arange(n) / fps)
    if drift.max() > TOLERANCE_S:
        t = int(np.argmax(drift))
        raise UserError(
            f"{where}: frame {t} has timestamp {stamps[t]:.6f} s, not frame_index / fps "
            f"({t / fps:.6f} s); frames are not evenly spaced"
        )
