"""MCAP metadata records of an oposm dataset: `DatasetInfo` and the episode index, as `str -> str`.

- `oposm.dataset` (written first): one key per `DatasetInfo` field plus `format_version`. `str`
  fields are stored as is, every other value as JSON, so any MCAP tool shows readable values and
  `decode_info(encode_info(info)) == info`.
- `oposm.episodes` (written after the messages): `episodes`, `steps` and `episode_lengths` (a JSON
  list), so `oposm inspect` does not have to scan the messages.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from typing import Any

import numpy as np

from pipeline.dataset import DatasetInfo
from pipeline.recording.schema import FORMAT_VERSION

DATASET_RECORD = "oposm.dataset"
EPISODES_RECORD = "oposm.episodes"
FORMAT_KEY = "format_version"


def _matches(value: Any, hint: Any) -> bool:
    """Whether a decoded JSON value has the declared type (`list[str]`, `int | None`, ...)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return True
    if hint is type(None):
        return value is None
    if origin is types.UnionType or origin is typing.Union:
        return any(_matches(value, arg) for arg in args)
    if origin is list:
        return isinstance(value, list) and all(_matches(v, args[0]) for v in value)
    if origin is dict:
        return isinstance(value, dict) and all(_matches(v, args[1]) for v in value.values())
    if hint is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, hint)


def _string_fields() -> set[str]:
    hints = typing.get_type_hints(DatasetInfo)
    return {f.name for f in dataclasses.fields(DatasetInfo) if hints[f.name] is str}


def _json_default(value: Any) -> Any:
    # numpy scalars and arrays sneak into generator params; store them as plain JSON numbers/lists.
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def encode_info(info: DatasetInfo) -> dict[str, str]:
    """`DatasetInfo` as the `oposm.dataset` metadata record.

    Raises:
        ValueError: A field holds a value that is not plain JSON (NaN, inf, arbitrary objects);
            the message names the field.
    """
    strings = _string_fields()
    record = {FORMAT_KEY: str(FORMAT_VERSION)}
    for f in dataclasses.fields(DatasetInfo):
        value = getattr(info, f.name)
        if f.name in strings:
            record[f.name] = str(value)
            continue
        try:
            record[f.name] = json.dumps(value, default=_json_default, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"DatasetInfo.{f.name} cannot be stored as JSON: {exc}") from exc
    return record


def decode_info(record: dict[str, str]) -> DatasetInfo:
    """Inverse of `encode_info`; fields missing from the record take their defaults.

    Raises:
        ValueError: A required field is missing, or a value is not valid JSON or not of the
            field's type (names the field).
    """
    strings = _string_fields()
    hints = typing.get_type_hints(DatasetInfo)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(DatasetInfo):
        if f.name not in record:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ValueError(f"metadata `{DATASET_RECORD}` has no key `{f.name}`")
            continue
        raw = record[f.name]
        try:
            kwargs[f.name] = raw if f.name in strings else json.loads(raw)
        except json.JSONDecodeError as exc:
            raise ValueError(f"metadata key `{f.name}` is not valid JSON ({exc})") from exc
        if not _matches(kwargs[f.name], hints[f.name]):
            raise ValueError(f"metadata key `{f.name}` is not a {hints[f.name]}: {raw[:80]}")
    return DatasetInfo(**kwargs)


def format_version(record: dict[str, str]) -> int:
    """The `format_version` of an `oposm.dataset` record (ValueError if missing or not an int)."""
    try:
        return int(record[FORMAT_KEY])
    except (KeyError, ValueError) as exc:
        raise ValueError(f"metadata `{DATASET_RECORD}` has no valid `{FORMAT_KEY}`") from exc


def encode_episodes(lengths: list[int]) -> dict[str, str]:
    """The `oposm.episodes` record for episodes of the given lengths (in steps)."""
    return {
        "episodes": str(len(lengths)),
        "steps": str(sum(lengths)),
        "episode_lengths": json.dumps(lengths),
    }


def decode_episodes(record: dict[str, str]) -> list[int]:
    """Episode lengths from an `oposm.episodes` record (ValueError if inconsistent)."""
    try:
        lengths = [int(n) for n in json.loads(record["episode_lengths"])]
        episodes, steps = int(record["episodes"]), int(record["steps"])
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"metadata `{EPISODES_RECORD}` is malformed ({exc})") from exc
    if episodes != len(lengths) or steps != sum(lengths):
        raise ValueError(f"metadata `{EPISODES_RECORD}` counts disagree with its episode lengths")
    return lengths
