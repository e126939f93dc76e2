"""The oposm MCAP format: round trips, readability by plain mcap tools, streaming, clear errors."""

from __future__ import annotations

import inspect
import json
import re
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter
from mcap_protobuf.decoder import DecoderFactory
from mcap_protobuf.writer import Writer as ProtobufWriter

from pipeline.dataset import DatasetInfo, Episode
from pipeline.errors import UserError
from pipeline.recording import (
    Step,
    format_summary,
    iter_episodes,
    read_episodes,
    read_info,
    summarize,
    write_dataset,
)
from pipeline.recording.metadata import DATASET_RECORD, EPISODES_RECORD, encode_episodes
from pipeline.recording.metadata import encode_info as encode_info_record
from pipeline.recording.schema import PROTO_PATH, STEP_FIELDS

PERIOD = 0.05


def make_info(physics_dim: int = 0, goal_dim: int = 0) -> DatasetInfo:
    return DatasetInfo(
        name="tiny",
        source="maze",
        env_id="PointMaze_UMaze-v3",
        state_names=["x", "y", "vx", "vy"],
        action_names=["ax", "ay"],
        state_units=["m", "m", "m/s", "m/s"],
        action_units=["", ""],
        control_period=PERIOD,
        physics_dim=physics_dim,
        goal_dim=goal_dim,
        seed=7 if physics_dim else None,
        env_kwargs={"maze_map": [[1, 1, 1], [1, "g", 1], [1, 1, 1]], "continuing_task": True},
        generator={"kp": 10.0, "noise": 0.1, "nested": {"a": [1, 2.5, None]}},
        versions={"oposm": "0.1.0", "mujoco": "4.0.0"},
    )


def make_episodes(info: DatasetInfo, lengths: list[int], seed: int = 0) -> list[Episode]:
    """Random episodes on one clock; each optional field is present in some episodes only."""
    rng = np.random.default_rng(seed)
    episodes, start = [], 0.0
    for index, n in enumerate(lengths):
        time = start + PERIOD * np.arange(n) + rng.uniform(0, 1e-3, n).cumsum()
        start = float(time[-1]) + PERIOD
        episode = Episode(
            index=index,
            observations=rng.normal(size=(n, info.state_dim)),
            actions=rng.uniform(-1, 1, size=(n, info.action_dim)),
            time=time,
        )
        if info.physics_dim:
            episode.physics = rng.normal(size=(n, info.physics_dim))
        if info.goal_dim:
            episode.goals = rng.normal(size=(n, info.goal_dim))
        if index % 2 == 0:
            episode.goal_reached = np.arange(n) == n - 1
            episode.rewards = rng.normal(size=n)
        if index % 3 != 1:
            episode.terminals = np.zeros(n, dtype=bool)
            episode.terminals[-1] = index == 0
        episodes.append(episode)
    return episodes


def assert_same_episode(got: Episode, want: Episode) -> None:
    assert got.index == want.index
    for name in ("observations", "actions", "time", "physics", "goals"):
        a, b = getattr(got, name), getattr(want, name)
        assert (a is None) == (b is None), name
        if a is not None:
            assert a.dtype == np.float64 and np.array_equal(a, b), name
    for name, dtype in (("goal_reached", bool), ("rewards", np.float64), ("terminals", bool)):
        a, b = getattr(got, name), getattr(want, name)
        assert (a is None) == (b is None), name
        if a is not None:
            assert a.dtype == dtype and np.array_equal(a, b), name


@pytest.fixture
def dataset(tmp_path: Path) -> tuple[Path, DatasetInfo, list[Episode]]:
    info = make_info(physics_dim=3, goal_dim=2)
    episodes = make_episodes(info, [5, 1, 8])
    path = tmp_path / "tiny.mcap"
    write_dataset(path, info, iter(episodes))
    return path, info, episodes


def write_raw(
    path: Path,
    info: DatasetInfo,
    steps: list[Step],
    lengths: list[int],
    changes: dict[str, str] | None = None,
) -> None:
    """A file with our schema and metadata (with `changes`) but arbitrary messages."""
    with path.open("wb") as stream:
        writer = ProtobufWriter(stream)
        writer.add_metadata(DATASET_RECORD, encode_info_record(info) | (changes or {}))
        for step in steps:
            ns = int(round(step.time * 1e9))
            writer.write_message("/demo/step", step, log_time=ns, publish_time=ns)
        writer.add_metadata(EPISODES_RECORD, encode_episodes(lengths))
        writer.finish()


def raw_step(episode: int, frame: int, state_dim: int = 4) -> Step:
    return Step(
        episode_index=episode,
        frame_index=frame,
        time=0.1 * (10 * episode + frame),
        state=[0.5] * state_dim,
        action=[0.0, 1.0],
    )


# Round trips


@pytest.mark.parametrize("dims", [(0, 0), (3, 2)])
def test_round_trip(tmp_path: Path, dims: tuple[int, int]) -> None:
    info = make_info(*dims)
    episodes = make_episodes(info, [5, 1, 8, 3])
    path = tmp_path / "data" / "demo.mcap"
    summary = write_dataset(path, info, (e for e in episodes))
    assert (summary.path, summary.episodes, summary.steps) == (path, 4, 17)
    assert summary.bytes == path.stat().st_size
    assert read_info(path) == info
    got = list(iter_episodes(path))
    assert len(got) == len(episodes)
    for g, w in zip(got, episodes, strict=True):
        assert_same_episode(g, w)
    assert len(read_episodes(path)) == 4
    assert sorted(p.name for p in path.parent.iterdir()) == ["demo.mcap"]


def test_numpy_values_in_info_become_json(tmp_path: Path) -> None:
    info = make_info()
    info.seed = np.int64(3)
    info.generator = {"gains": np.array([1.0, 2.0]), "n": np.int32(4)}
    path = tmp_path / "np.mcap"
    write_dataset(path, info, make_episodes(info, [2]))
    back = read_info(path)
    assert back.seed == 3 and back.generator == {"gains": [1.0, 2.0], "n": 4}


def test_readable_with_plain_mcap_reader(dataset) -> None:
    path, info, episodes = dataset
    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        summary = reader.get_summary()
        decoded = list(reader.iter_decoded_messages(topics=["/demo/step"]))
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert header.profile == "oposm"
    (schema,) = summary.schemas.values()
    assert (schema.name, schema.encoding) == ("oposm.Step", "protobuf")
    (channel,) = summary.channels.values()
    assert (channel.topic, channel.message_encoding) == ("/demo/step", "protobuf")
    assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
    assert summary.statistics.message_count == sum(len(e) for e in episodes) == len(decoded)
    assert set(metadata) == {"oposm.dataset", "oposm.episodes"}
    assert metadata["oposm.dataset"]["env_id"] == info.env_id
    assert json.loads(metadata["oposm.dataset"]["state_names"]) == info.state_names
    assert json.loads(metadata["oposm.episodes"]["episode_lengths"]) == [5, 1, 8]

    first, last = decoded[0].decoded_message, decoded[-1].decoded_message
    assert (first.episode_index, first.frame_index) == (0, 0)
    assert list(first.state) == episodes[0].observations[0].tolist()
    assert list(first.physics) == episodes[0].physics[0].tolist()
    assert first.HasField("reward") and first.reward == episodes[0].rewards[0]
    assert (last.episode_index, last.frame_index) == (2, 7)
    assert list(last.action) == episodes[2].actions[-1].tolist()
    times = [m.message.log_time for m in decoded]
    assert times == sorted(times)
    assert times[0] == round(episodes[0].time[0] * 1e9)
    assert all(m.message.publish_time == m.message.log_time for m in decoded)
    assert not decoded[5].decoded_message.HasField("reward")  # episode 1 has no rewards


def test_iter_episodes_streams(tmp_path: Path) -> None:
    info = make_info()
    episodes = make_episodes(info, [40] * 6)
    path = tmp_path / "many.mcap"
    write_dataset(path, info, episodes, chunk_size=1024)
    stream = iter_episodes(path)
    assert inspect.isgenerator(stream)
    assert_same_episode(next(stream), episodes[0])
    stream.close()

    # Damage the last chunk: the first episodes still arrive, the error comes when it is reached.
    with path.open("rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) > 3
    data = bytearray(path.read_bytes())
    last = chunks[-1]
    middle = last.chunk_start_offset + last.chunk_length - last.compressed_size // 2
    data[middle : middle + 8] = bytes(8)
    path.write_bytes(bytes(data))
    got = []
    with pytest.raises(UserError, match=r"many\.mcap is truncated or corrupt"):
        for episode in iter_episodes(path):
            got.append(episode.index)
    assert got[:3] == [0, 1, 2]


def test_summary(dataset) -> None:
    path, info, _ = dataset
    s = summarize(path)
    assert (s["episodes"], s["steps"], s["messages"]) == (3, 14, 14)
    assert s["episode_length"] == {"min": 1, "mean": 14 / 3, "max": 8}
    assert s["compression"] == "zstd" and s["bytes"] == path.stat().st_size
    assert s["state_names"] == info.state_names and s["seed"] == 7
    assert s["duration_s"] > 14 * PERIOD
    text = format_summary(s)
    assert "x [m], y [m], vx [m/s], vy [m/s]" in text and "ax, ay" in text
    assert "3  (14 steps; length min 1 / mean 4.7 / max 8)" in text
    assert "PointMaze_UMaze-v3" in text and "20 Hz" in text and "zstd" in text
    json.dumps(s)


# Errors on reading


@pytest.mark.parametrize("read", [read_info, read_episodes, summarize])
def test_missing_file(tmp_path: Path, read) -> None:
    with pytest.raises(UserError, match=r"nope\.mcap not found"):
        read(tmp_path / "nope.mcap")


def test_not_mcap(tmp_path: Path) -> None:
    path = tmp_path / "notes.mcap"
    path.write_text("just some text, long enough to be longer than a footer would be\n" * 3)
    with pytest.raises(UserError, match=r"notes\.mcap is not an MCAP file"):
        read_info(path)


@pytest.mark.parametrize("cut", ["half", "minus10", "minus1", "header"])
@pytest.mark.parametrize("read", [read_info, read_episodes])
def test_truncated(dataset, tmp_path: Path, cut: str, read) -> None:
    path = dataset[0]
    data = path.read_bytes()
    size = {"half": len(data) // 2, "minus10": len(data) - 10, "minus1": len(data) - 1}
    cut_path = tmp_path / "cut.mcap"
    cut_path.write_bytes(data[: size.get(cut, 20)])
    with pytest.raises(UserError, match=r"cut\.mcap is truncated or corrupt.*oposm ingest") as err:
        read(cut_path)
    assert "\n" not in str(err.value)


def test_plain_mcap_is_not_oposm(tmp_path: Path) -> None:
    path = tmp_path / "plain.mcap"
    with path.open("wb") as stream:
        writer = ProtobufWriter(stream)
        writer.write_message("/demo/step", raw_step(0, 0), log_time=0, publish_time=0)
        writer.finish()
    with pytest.raises(UserError, match=r"plain\.mcap is not an oposm dataset"):
        read_info(path)


def test_other_schema_is_not_oposm(tmp_path: Path) -> None:
    path = tmp_path / "json.mcap"
    with path.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start()
        writer.add_metadata(DATASET_RECORD, encode_info_record(make_info()))
        schema = writer.register_schema("oposm.Step", "jsonschema", b"{}")
        channel = writer.register_channel("/demo/step", "json", schema)
        writer.add_message(channel, log_time=0, data=b"{}", publish_time=0)
        writer.finish()
    with pytest.raises(UserError, match=r"json\.mcap is not an oposm dataset"):
        read_info(path)


def test_wrong_state_dim_in_file(tmp_path: Path) -> None:
    path = tmp_path / "dims.mcap"
    steps = [raw_step(0, 0), raw_step(0, 1), raw_step(0, 2, state_dim=3)]
    write_raw(path, make_info(), steps, [3])
    assert read_info(path).state_dim == 4  # opening only reads metadata
    with pytest.raises(UserError, match=r"episode 0, frame 2: `state` has 3 values.*says 4"):
        read_episodes(path)


def test_non_finite_in_file(tmp_path: Path) -> None:
    path = tmp_path / "nan.mcap"
    steps = [raw_step(0, 0), raw_step(1, 0), raw_step(1, 1)]
    steps[2].action[1] = float("inf")
    write_raw(path, make_info(), steps, [1, 2])
    with pytest.raises(UserError, match=r"nan\.mcap .*episode 1, frame 1: `action` is inf"):
        read_episodes(path)


def test_episode_indices_not_contiguous(tmp_path: Path) -> None:
    path = tmp_path / "gap.mcap"
    write_raw(path, make_info(), [raw_step(0, 0), raw_step(2, 0)], [1, 1])
    stream = iter_episodes(path)
    assert next(stream).index == 0
    with pytest.raises(UserError, match=r"gap\.mcap .*episode 2 follows episode 0"):
        next(stream)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"state_names": '"xy"'}, r"metadata key `state_names` is not a list\[str\]"),
        ({"control_period": "0.05s"}, "metadata key `control_period` is not valid JSON"),
        ({"state_units": '["m"]'}, "4 state_names but 1 state_units"),
        ({"format_version": "99"}, "format version 99, newer than this oposm reads"),
    ],
)
def test_bad_metadata_in_file(tmp_path: Path, changes: dict[str, str], message: str) -> None:
    path = tmp_path / "meta.mcap"
    write_raw(path, make_info(), [raw_step(0, 0)], [1], changes)
    with pytest.raises(UserError, match=rf"meta\.mcap .*{message}"):
        read_info(path)


def test_zero_episodes_in_file(tmp_path: Path) -> None:
    path = tmp_path / "empty.mcap"
    write_raw(path, make_info(), [], [])
    with pytest.raises(UserError, match=r"empty\.mcap contains no episodes"):
        read_info(path)


# Errors on writing


def assert_nothing_written(directory: Path) -> None:
    assert list(directory.iterdir()) == []


@pytest.mark.parametrize("field", ["observations", "actions", "rewards"])
def test_write_rejects_non_finite(tmp_path: Path, field: str) -> None:
    info = make_info()
    episodes = make_episodes(info, [3, 4])
    getattr(episodes[1], field if field != "rewards" else "observations")[2].flat[0] = np.nan
    if field == "rewards":
        episodes[1].observations[2, 0] = 0.0
        episodes[1].rewards = np.array([0.0, 1.0, np.inf, 2.0])
    out = tmp_path / "out"
    with pytest.raises(UserError, match=rf"bad\.mcap: episode 1, step 2: `{field}` is (nan|inf)"):
        write_dataset(out / "bad.mcap", info, iter(episodes))
    assert_nothing_written(out)


def test_write_rejects_wrong_state_dim(tmp_path: Path) -> None:
    info = make_info()
    episodes = make_episodes(info, [3, 4])
    episodes[1].observations = episodes[1].observations[:, :3]
    with pytest.raises(UserError, match=r"episode 1: `observations` has shape \(4, 3\)"):
        write_dataset(tmp_path / "bad.mcap", info, episodes)
    assert_nothing_written(tmp_path)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda eps: eps.clear(), "no episodes"),
        (lambda eps: setattr(eps[1], "index", 5), "episode 5 is at position 1"),
        (lambda eps: eps[1].time.__isub__(10.0), "episode 1, step 0: time .* goes backwards"),
        (lambda eps: setattr(eps[0], "physics", np.zeros((3, 2))), "`physics` is set"),
        (lambda eps: setattr(eps[0], "actions", np.zeros((0, 2))), r"shape \(0, 2\)"),
    ],
)
def test_write_rejects_bad_episodes(tmp_path: Path, change, message: str) -> None:
    info = make_info()
    episodes = make_episodes(info, [3, 4])
    change(episodes)
    with pytest.raises(UserError, match=message):
        write_dataset(tmp_path / "bad.mcap", info, episodes)
    assert_nothing_written(tmp_path)


def test_write_rejects_bad_info(tmp_path: Path) -> None:
    info = make_info()
    info.state_units = ["m"]
    with pytest.raises(UserError, match="4 state_names but 1 state_units"):
        write_dataset(tmp_path / "bad.mcap", info, make_episodes(make_info(), [2]))
    info = make_info()
    info.generator = {"limit": float("inf")}
    with pytest.raises(UserError, match=r"DatasetInfo\.generator cannot be stored as JSON"):
        write_dataset(tmp_path / "bad.mcap", info, make_episodes(info, [2]))
    assert_nothing_written(tmp_path)


# Schema


def test_proto_text_matches_descriptor() -> None:
    text = PROTO_PATH.read_text()
    assert re.search(r'^syntax = "proto3";$', text, re.M)
    assert re.search(r"^package oposm;$", text, re.M)
    body = re.search(r"message Step \{(.*?)^\}", text, re.M | re.S).group(1)
    parsed = [
        (m[1] or "", m[2], m[3], int(m[4]))
        for m in re.finditer(r"^\s*(optional|repeated)?\s*(\w+)\s+(\w+)\s*=\s*(\d+);", body, re.M)
    ]
    assert tuple(parsed) == STEP_FIELDS

    fdp = descriptor_pb2.FileDescriptorProto()
    Step.DESCRIPTOR.file.CopyToProto(fdp)
    assert (fdp.package, fdp.syntax, Step.DESCRIPTOR.full_name) == ("oposm", "proto3", "oposm.Step")
    F = descriptor_pb2.FieldDescriptorProto
    types = {"uint32": F.TYPE_UINT32, "double": F.TYPE_DOUBLE, "bool": F.TYPE_BOOL}
    built = [
        (f.name, f.number, f.type, f.label == F.LABEL_REPEATED, f.proto3_optional)
        for f in fdp.message_type[0].field
    ]
    want = [(n, num, types[t], lab == "repeated", lab == "optional") for lab, t, n, num in parsed]
    assert built == want
