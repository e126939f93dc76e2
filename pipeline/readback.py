"""Files the pipeline reads back, checked against typed models before anything uses them.

What a stage wrote (a checkpoint's `config.json`, a resume `state.json`, `segments.json`, an
expert's `actor.json`) may come back damaged, hand-edited or from another version. Each is
validated with a pydantic model (or a dataclass whose fields carry the constraints below) before
a value reaches the code: a string where a size goes, a negative size or a non-finite float is one
`UserError` that names the file, the field and what to do, never a traceback from deep inside
torch. `read_json` + `validated` are the one helper for all of them.
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Annotated, Any

from pydantic import ConfigDict, Field, TypeAdapter, ValidationError

from pipeline.errors import UserError

# Constrained types for the fields of files read back (and of the configs they rebuild).
Size = Annotated[int, Field(ge=1)]
"""A dimension or width: 1 or more."""
Count = Annotated[int, Field(ge=0)]
"""A count or index: 0 or more."""
Finite = Annotated[float, Field(allow_inf_nan=False)]
"""A finite float."""
PositiveFinite = Annotated[float, Field(gt=0, allow_inf_nan=False)]
"""A finite float above 0 (a std floor, a control period)."""
NonNegativeFinite = Annotated[float, Field(ge=0, allow_inf_nan=False)]
"""A finite float of 0 or more (a duration)."""

# Models of files read back ignore keys they do not know: files carry provenance beyond what the
# code reads, and a newer writer may add some.
READBACK_CONFIG = ConfigDict(extra="ignore")


def read_json(path: str | Path, fix: str) -> Any:
    """The JSON value in `path`.

    Raises:
        UserError: the file is unreadable or not JSON (names it and says `fix`).
    """
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except UnicodeDecodeError as exc:
        raise UserError(f"{path} is not a text (JSON) file; it is damaged: {fix}") from exc
    except json.JSONDecodeError as exc:
        raise UserError(
            f"{path} is not valid JSON ({exc.msg}, line {exc.lineno} column {exc.colno}); it is "
            f"damaged or truncated: {fix}"
        ) from exc
    except OSError as exc:
        raise UserError(f"{path} is unreadable ({exc.strerror or exc}); {fix}") from exc


@cache
def _adapter(schema: Any) -> TypeAdapter:
    return TypeAdapter(schema)


def validated[T](schema: type[T], data: Any, path: str | Path, fix: str, prefix: str = "") -> T:
    """`data` (read back from `path`) validated as `schema`: a pydantic model, a dataclass or
    any type pydantic validates.

    Args:
        prefix: Where `data` sits in the file (`model`), for the field's name in messages.

    Raises:
        UserError: one line: the file, the first bad field (dotted, from the file's top) and
            what is wrong with it, then `fix`.
    """
    try:
        return _adapter(schema).validate_python(data)
    except ValidationError as exc:
        problem = describe_error(exc, prefix)
        sep = " " if problem.startswith("has no ") else ": "
        raise UserError(f"{path}{sep}{problem}; {fix}") from exc


def describe_error(exc: ValidationError, prefix: str = "") -> str:
    """The first problem of a `ValidationError`, in words: which field, what is wrong, what it
    holds (short values only: never a whole section)."""
    errors = exc.errors()
    first = errors[0]
    loc = [prefix] if prefix else []
    loc += [str(p) for p in first["loc"]]
    key = ".".join(loc)
    more = f" (and {len(errors) - 1} more problems)" if len(errors) > 1 else ""
    if first["type"] == "missing":
        return f"has no '{key}' entry{more}"
    if first["type"] in ("extra_forbidden", "unexpected_keyword_argument"):
        return f"unknown key '{key}'{more}"
    msg = first["msg"].removeprefix("Value error, ")
    value = first.get("input")
    shown = "" if isinstance(value, dict | list | tuple) else f", got {_short(value)}"
    where = f"bad value for '{key}': " if key else ""
    return f"{where}{msg}{shown}{more}"


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
