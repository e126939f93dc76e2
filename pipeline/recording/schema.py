"""The `oposm.Step` protobuf message, built at import time from a descriptor (no protoc step).

`step.proto` next to this file is the human-readable source; `STEP_FIELDS` below must say the same
thing (a test compares them). The message class lives in a private `DescriptorPool`, so it cannot
clash with another `oposm.Step` registered in the default pool. `mcap_protobuf.writer.Writer` embeds
its FileDescriptorSet in every file, so readers decode with the file's own schema.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

PACKAGE = "oposm"
SCHEMA_NAME = "oposm.Step"
TOPIC = "/demo/step"
PROFILE = "oposm"
PROTO_FILE = "oposm/step.proto"
PROTO_PATH = Path(__file__).with_name("step.proto")

# Bumped whenever the meaning of the schema or the metadata changes; readers refuse newer files.
FORMAT_VERSION = 1

_FDP = descriptor_pb2.FieldDescriptorProto
_TYPES = {"uint32": _FDP.TYPE_UINT32, "double": _FDP.TYPE_DOUBLE, "bool": _FDP.TYPE_BOOL}
_LABELS = {
    "": _FDP.LABEL_OPTIONAL,
    "optional": _FDP.LABEL_OPTIONAL,
    "repeated": _FDP.LABEL_REPEATED,
}

# (label, type, name, number), exactly as written in step.proto. "optional" is proto3 explicit
# presence, so an absent reward/terminal/goal_reached is distinguishable from False/0.
STEP_FIELDS: tuple[tuple[str, str, str, int], ...] = (
    ("", "uint32", "episode_index", 1),
    ("", "uint32", "frame_index", 2),
    ("", "double", "time", 3),
    ("repeated", "double", "state", 4),
    ("repeated", "double", "action", 5),
    ("repeated", "double", "physics", 6),
    ("repeated", "double", "goal", 7),
    ("optional", "bool", "goal_reached", 8),
    ("optional", "double", "reward", 9),
    ("optional", "bool", "terminal", 10),
)


def build_file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    """The FileDescriptorProto of `step.proto`, built from `STEP_FIELDS`."""
    file_proto = descriptor_pb2.FileDescriptorProto(
        name=PROTO_FILE, package=PACKAGE, syntax="proto3"
    )
    message = file_proto.message_type.add(name="Step")
    for label, type_name, name, number in STEP_FIELDS:
        field = message.field.add(
            name=name,
            number=number,
            type=_TYPES[type_name],
            label=_LABELS[label],
            json_name=_json_name(name),
        )
        if label == "optional":
            # proto3 `optional` is encoded as a synthetic one-field oneof named "_<field>".
            field.proto3_optional = True
            field.oneof_index = len(message.oneof_decl)
            message.oneof_decl.add(name=f"_{name}")
    return file_proto


def _json_name(name: str) -> str:
    """lowerCamelCase name, as protoc fills `json_name` in."""
    head, *rest = name.split("_")
    return head + "".join(part.capitalize() for part in rest)


def _build_step_class() -> type[Any]:
    pool = descriptor_pool.DescriptorPool()
    pool.AddSerializedFile(build_file_descriptor().SerializeToString())
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(SCHEMA_NAME))


Step: type[Any] = _build_step_class()
"""The `oposm.Step` message class (a regular generated protobuf class)."""
