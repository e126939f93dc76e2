"""Open an oposm MCAP file from its summary section; every problem becomes a one-line UserError.

Opening reads the first and last bytes, the footer, the summary section (schemas, channels,
statistics, chunk and metadata indexes) and the two metadata records; never the messages. Checks,
in order: the file exists; it starts with the MCAP magic (else "not an MCAP file"); it ends with the
MCAP magic (else truncated: a writer that dies never writes the footer, and every cut of a file
loses its trailing magic); it has a summary; it has the `oposm.dataset` metadata and a `/demo/step`
channel whose embedded schema is a compatible `oposm.Step` (else "not an oposm dataset"); the
metadata decodes and agrees with the statistics. Chunk CRCs are checked whenever a chunk is read.
"""

from __future__ import annotations

import contextlib
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zstandard
from google.protobuf import descriptor_pb2
from google.protobuf.message import DecodeError
from mcap.exceptions import McapError
from mcap.reader import FOOTER_SIZE, McapReader, SeekingReader
from mcap.records import Channel, Header
from mcap.stream_reader import MAGIC_SIZE, CRCValidationError
from mcap.summary import Summary
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import MCAP0_MAGIC
from mcap_protobuf.decoder import DecoderFactory

from pipeline.dataset import DatasetInfo
from pipeline.errors import UserError
from pipeline.recording import metadata
from pipeline.recording.checks import check_info
from pipeline.recording.schema import FORMAT_VERSION, SCHEMA_NAME, TOPIC, build_file_descriptor

REGENERATE = "re-run `oposm ingest` to regenerate it"

# What the mcap/protobuf/zstd stack raises on damaged bytes: EndOfFile, InvalidMagic,
# RecordLengthLimitExceeded and McapProtobufDecodeError are McapErrors; a cut inside a record is a
# struct.error; garbage offsets and lengths give KeyError (unknown channel id), OSError/ValueError/
# OverflowError (bad seek), MemoryError (huge decompressed size), UnicodeDecodeError (strings),
# TypeError (protobuf rejecting a damaged embedded schema).
# Only calls into mcap are wrapped, so our own bugs are not reported as corrupt files.
CORRUPT_ERRORS = (
    McapError,
    CRCValidationError,
    DecodeError,
    struct.error,
    zstandard.ZstdError,
    EOFError,
    KeyError,
    OSError,
    ValueError,
    OverflowError,
    MemoryError,
    TypeError,
)


@dataclass
class DatasetFile:
    """An opened oposm MCAP file: the reader and everything read from the summary section.

    Attributes:
        path: The file.
        reader: Seeking MCAP reader with CRC checks and the protobuf decoder.
        header: MCAP header (profile, library).
        summary: MCAP summary section (statistics, chunk indexes, ...).
        channel: The `/demo/step` channel.
        info: The decoded `oposm.dataset` metadata.
        format_version: The file's format version.
        lengths: Episode lengths from the `oposm.episodes` metadata, in steps.
    """

    path: Path
    reader: McapReader
    header: Header
    summary: Summary
    channel: Channel
    info: DatasetInfo
    format_version: int
    lengths: list[int]

    def iter_steps(self) -> Iterator[Any]:
        """Decoded `oposm.Step` messages in log-time order, one chunk read at a time.

        Errors reading the bytes become a `corrupt` UserError when reached.
        """
        messages = self.reader.iter_decoded_messages(topics=[TOPIC])
        while True:
            with corrupt_as_user_error(self.path):
                message = next(messages, None)
            if message is None:
                return
            yield message.decoded_message

    def invalid(self, problem: str) -> UserError:
        """A UserError for content that contradicts the format (names file and problem)."""
        return invalid(self.path, problem)


def invalid(path: Path, problem: str) -> UserError:
    """A UserError for content that contradicts the format."""
    return UserError(f"{path} is an invalid oposm dataset: {problem}; {REGENERATE}")


def corrupt(path: Path, problem: str) -> UserError:
    """A UserError for a damaged file."""
    return UserError(f"{path} is truncated or corrupt ({problem}); {REGENERATE}")


def no_episodes(path: Path) -> UserError:
    """A UserError for a dataset without a single step."""
    return UserError(f"{path} contains no episodes; {REGENERATE} from a non-empty source")


def not_oposm(path: Path, problem: str) -> UserError:
    """A UserError for an MCAP file that is not an oposm dataset."""
    return UserError(
        f"{path} is not an oposm dataset ({problem}); create datasets with `oposm ingest`"
    )


@contextlib.contextmanager
def corrupt_as_user_error(path: Path) -> Iterator[None]:
    """Re-raise low-level read errors (see CORRUPT_ERRORS) as a one-line `corrupt` UserError."""
    try:
        yield
    except CORRUPT_ERRORS as exc:
        detail = " ".join(f"{type(exc).__name__}: {exc}".split()).rstrip(": ")
        raise corrupt(path, detail) from exc


def _check_magic(path: Path) -> None:
    if not path.exists():
        raise UserError(f"dataset file {path} not found; check the path or run `oposm ingest`")
    if not path.is_file():
        raise UserError(f"dataset path {path} is not a file; give the path of a .mcap file")
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(MAGIC_SIZE)
        if head != MCAP0_MAGIC:
            raise UserError(
                f"{path} is not an MCAP file (it does not start with the MCAP magic bytes); "
                "give the path of a .mcap dataset written by `oposm ingest`"
            )
        f.seek(max(size - MAGIC_SIZE, 0))
        tail = f.read(MAGIC_SIZE)
    if size < 2 * MAGIC_SIZE + FOOTER_SIZE or tail != MCAP0_MAGIC:
        raise corrupt(path, f"no MCAP footer at the end of its {size} bytes")


def _step_channel(path: Path, summary: Summary) -> Channel:
    """The `/demo/step` channel, after checking that its embedded schema is a compatible Step."""
    channel = next((c for c in summary.channels.values() if c.topic == TOPIC), None)
    if channel is None or channel.message_encoding != MessageEncoding.Protobuf:
        raise not_oposm(path, f"no protobuf channel `{TOPIC}`")
    schema = summary.schemas.get(channel.schema_id)
    if schema is None or schema.name != SCHEMA_NAME or schema.encoding != SchemaEncoding.Protobuf:
        raise not_oposm(path, f"channel `{TOPIC}` does not use the protobuf schema `{SCHEMA_NAME}`")
    package, _, name = SCHEMA_NAME.rpartition(".")
    found = {
        f.name: f
        for file in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file
        if file.package == package
        for message in file.message_type
        if message.name == name
        for f in message.field
    }
    for expected in build_file_descriptor().message_type[0].field:
        got = found.get(expected.name)
        if got is None or (got.number, got.type, got.label) != (
            expected.number,
            expected.type,
            expected.label,
        ):
            raise not_oposm(
                path, f"schema `{SCHEMA_NAME}` has no compatible field `{expected.name}`"
            )
    return channel


def _read_metadata(
    path: Path, records: dict[str, dict[str, str]], message_count: int | None
) -> tuple[int, DatasetInfo, list[int]]:
    """Decode the metadata records: (format version, info, episode lengths), checked against the
    number of `/demo/step` messages in the statistics."""
    try:
        version = metadata.format_version(records[metadata.DATASET_RECORD])
        if version > FORMAT_VERSION:
            raise UserError(
                f"{path} uses oposm format version {version}, newer than this oposm reads "
                f"({FORMAT_VERSION}); upgrade oposm"
            )
        info = metadata.decode_info(records[metadata.DATASET_RECORD])
        check_info(info)
        if metadata.EPISODES_RECORD not in records:
            raise corrupt(path, f"no `{metadata.EPISODES_RECORD}` metadata")
        lengths = metadata.decode_episodes(records[metadata.EPISODES_RECORD])
    except (ValueError, TypeError) as exc:
        raise invalid(path, str(exc)) from exc
    if not lengths:
        raise no_episodes(path)
    if message_count is None:
        raise corrupt(path, "no MCAP statistics record")
    if message_count != sum(lengths):
        raise invalid(
            path,
            f"the statistics count {message_count} messages but the metadata {sum(lengths)} steps",
        )
    return version, info, lengths


@contextlib.contextmanager
def open_dataset(path: str | Path) -> Iterator[DatasetFile]:
    """Open and check an oposm MCAP file (see the module docstring); messages are not read."""
    path = Path(path)
    _check_magic(path)
    with path.open("rb") as stream:
        with corrupt_as_user_error(path):
            # No record can be longer than the file: a corrupt length fails fast instead of
            # attempting a huge read.
            reader = SeekingReader(
                stream,
                validate_crcs=True,
                decoder_factories=[DecoderFactory()],
                record_size_limit=path.stat().st_size,
            )
            summary = reader.get_summary()
            if summary is None:
                raise corrupt(path, "no summary section")
            names = {index.name for index in summary.metadata_indexes}
            if metadata.DATASET_RECORD not in names:
                raise not_oposm(path, f"no `{metadata.DATASET_RECORD}` metadata")
            stats = summary.statistics
            if stats is not None and stats.message_count == 0:
                raise no_episodes(path)
            channel = _step_channel(path, summary)
            records: dict[str, dict[str, str]] = {}
            for record in reader.iter_metadata():
                records.setdefault(record.name, record.metadata)
            if metadata.DATASET_RECORD not in records:
                raise corrupt(path, "metadata index and records disagree")
            header = reader.get_header()
        count = None if stats is None else stats.channel_message_counts.get(channel.id, 0)
        version, info, lengths = _read_metadata(path, records, count)
        yield DatasetFile(path, reader, header, summary, channel, info, version, lengths)
