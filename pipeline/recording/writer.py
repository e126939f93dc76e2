"""Write a dataset (a `DatasetInfo` and a stream of `Episode`s) as one oposm MCAP file.

Layout: header (profile "oposm"), metadata `oposm.dataset`, one chunked, zstd-compressed
`/demo/step` channel of `oposm.Step` protobuf messages with log time = publish time = simulated
time in ns, metadata `oposm.episodes`, then the summary section (schema, channel, statistics,
chunk and metadata indexes) written by `mcap_protobuf.writer.Writer` with the mcap defaults.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType
from mcap_protobuf.writer import Writer

from pipeline.dataset import DatasetInfo, Episode
from pipeline.errors import UserError
from pipeline.io import atomic_path
from pipeline.recording.checks import check_episode, check_info
from pipeline.recording.metadata import (
    DATASET_RECORD,
    EPISODES_RECORD,
    encode_episodes,
    encode_info,
)
from pipeline.recording.schema import PROFILE, TOPIC, Step


@dataclass(frozen=True)
class WriteSummary:
    """What `write_dataset` wrote.

    Attributes:
        path: The MCAP file.
        episodes: Number of episodes.
        steps: Number of steps (= messages) over all episodes.
        bytes: File size in bytes.
    """

    path: Path
    episodes: int
    steps: int
    bytes: int


def to_nanoseconds(time: float) -> int:
    """Simulated time in seconds -> MCAP log time in integer nanoseconds."""
    return int(round(time * 1e9))


def _write_episode(writer: Writer, episode: Episode) -> None:
    """Write one checked episode as N `oposm.Step` messages."""
    columns = {
        "state": episode.observations.tolist(),
        "action": episode.actions.tolist(),
        "physics": None if episode.physics is None else episode.physics.tolist(),
        "goal": None if episode.goals is None else episode.goals.tolist(),
    }
    scalars = {
        "goal_reached": episode.goal_reached,
        "reward": episode.rewards,
        "terminal": episode.terminals,
    }
    scalars = {k: v.tolist() for k, v in scalars.items() if v is not None}
    for t, time in enumerate(episode.time.tolist()):
        step = Step(episode_index=episode.index, frame_index=t, time=time)
        for name, rows in columns.items():
            if rows is not None:
                getattr(step, name).extend(rows[t])
        for name, values in scalars.items():
            setattr(step, name, values[t])
        ns = to_nanoseconds(time)
        writer.write_message(TOPIC, step, log_time=ns, publish_time=ns, sequence=t)


def write_dataset(
    path: str | Path,
    info: DatasetInfo,
    episodes: Iterable[Episode],
    *,
    chunk_size: int = 1024 * 1024,
    shown_as: str | Path | None = None,
    source: str | Path | None = None,
) -> WriteSummary:
    """Write `episodes` to the MCAP file `path`, atomically, checking each one first.

    Episodes are streamed: `episodes` may be a generator of unknown length; only one episode is
    held at a time. Each must have index 0, 1, 2, ... in order, N > 0 steps, arrays of the shapes
    `info` implies (`[N, state_dim]`, `[N, action_dim]`, `[N, physics_dim]` if physics_dim > 0,
    `[N, goal_dim]` if goal_dim > 0, `[N]` for time and the optional flags/rewards), finite values,
    and times >= 0 that never decrease over the dataset.

    Args:
        path: Destination `.mcap` file (parent directories are created).
        info: Dataset description, stored as the `oposm.dataset` metadata.
        episodes: Episodes 0, 1, 2, ... in order.
        chunk_size: Uncompressed bytes of messages per MCAP chunk (the unit of reading and CRC).
        shown_as: The file messages name (default `path`): the destination, when `path` is a
            temporary that will be renamed onto it.
        source: The file the episodes come from (an import), named by messages about bad
            episodes; None for generated data.

    Raises:
        UserError: An invalid `info` or episode (names the file, episode, field and step), or no
            episodes at all. Nothing is left at `path` (nor a temporary file).
    """
    path = Path(path)
    name = shown_as if shown_as is not None else path
    try:
        check_info(info)
        info_record = encode_info(info)
    except ValueError as exc:
        raise UserError(f"cannot write {name}: {exc}") from exc
    lengths: list[int] = []
    with atomic_path(path) as tmp, tmp.open("wb") as stream:
        writer = Writer(
            stream, chunk_size=chunk_size, compression=CompressionType.ZSTD, profile=PROFILE
        )
        writer.add_metadata(DATASET_RECORD, info_record)
        last_time = 0.0
        for position, episode in enumerate(episodes):
            try:
                checked = check_episode(episode, info, position, last_time)
            except ValueError as exc:
                if source is None:
                    raise UserError(f"cannot write {name}: {exc}; fix the source data") from exc
                raise UserError(
                    f"{source}: {exc}; fix the source data ({name} was not written)"
                ) from exc
            _write_episode(writer, checked)
            lengths.append(len(checked))
            last_time = float(checked.time[-1])
        if not lengths:
            raise UserError(
                f"cannot write {name}: no episodes; the source "
                f"{f'{source} ' if source else ''}produced nothing"
            )
        writer.add_metadata(EPISODES_RECORD, encode_episodes(lengths))
        writer.finish()
    return WriteSummary(path, len(lengths), sum(lengths), path.stat().st_size)
