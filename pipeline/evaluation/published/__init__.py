"""The published numbers our reports put beside ours, read from the data files beside this module,
one per source, each table with its `source` (the paper, its table or figure, what the numbers
are); docs/references.md shows them with their protocols:

- `oposm_paper.toml`, the OPOSM paper: table 1 and its LLP column, table 3 (EM against naive VI),
  table 4 with its LLP column and FrankaKitchen rows, figure 5, the seconds per plan and the
  episodes behind its maze2d rates (`oposm report experiments`, results/antmaze.md,
  results/manipulation.md);
- `ogbench.toml`, OGBench (Park et al., ICLR 2025): its methods, seeds, locomotion rows (the point
  and ant mazes) and manipulation rows (results/ogbench-point.md, results/antmaze.md,
  results/manipulation.md);
- `after_ogbench.toml`: methods published after OGBench, on its point mazes and protocol, with a
  note on what is left out and why (results/ogbench-point.md).

Success rates are fractions, (mean, the ± or std the source printed); a table in unit "percent"
holds the numbers as printed and is divided by 100 here, one in unit "fraction" is taken as it is.
Each file is read by a function of its path (`load_oposm_paper`, `load_ogbench`,
`load_after_ogbench`), called on import for the package's own files; a file that lacks what it
should hold raises `PublishedDataError`, naming the file and the key.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

Pair = tuple[float, float]  # (mean, the ± or std printed)
RATES = ("percent", "fraction")  # the units of success rates


class PublishedDataError(ValueError):
    """A data file of published numbers that does not hold what its loader reads."""


def read(path: Path) -> dict[str, Any]:
    """A TOML file's content; `PublishedDataError` naming the file where it cannot be read."""
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError) as error:
        raise PublishedDataError(f"{path}: cannot read it as TOML ({error})") from error


def _fail(path: Path, where: str, what: str) -> PublishedDataError:
    return PublishedDataError(f"{path}: `{where}` {what}")


def _get(path: Path, table: dict[str, Any], key: str, kind: type, where: str = "") -> Any:
    """`table[key]`, of type `kind` (a `where.key` spelled out in the error)."""
    name = f"{where}.{key}" if where else key
    if key not in table:
        raise _fail(path, name, "is missing")
    value = table[key]
    if not isinstance(value, kind) or isinstance(value, bool):
        raise _fail(path, name, f"is {value!r}, not {kind.__name__}")
    return value


def _source(path: Path, table: dict[str, Any], where: str = "") -> str:
    """The table's `source`: where in the paper its numbers are and what they are."""
    text = _get(path, table, "source", str, where)
    if not text.strip():
        raise _fail(path, f"{where}.source" if where else "source", "is empty")
    return text


def _unit(path: Path, table: dict[str, Any], where: str, units: tuple[str, ...]) -> str:
    unit = _get(path, table, "unit", str, where)
    if unit not in units:
        raise _fail(path, f"{where}.unit", f"is {unit!r}, not one of {', '.join(units)}")
    return unit


def _number(path: Path, value: Any, where: str) -> int | float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _fail(path, where, f"is {value!r}, not a number")
    return value


def _count(path: Path, table: dict[str, Any], key: str, where: str = "") -> int:
    value = _get(path, table, key, int, where)
    if value < 1:
        raise _fail(path, f"{where}.{key}" if where else key, f"is {value}, not a count")
    return value


def _rate(path: Path, value: Any, unit: str, where: str) -> float:
    """One number of a rates table as a fraction: as printed / 100 in a "percent" table."""
    number = _number(path, value, where)
    return number / 100 if unit == "percent" else float(number)


def _pair(path: Path, value: Any, unit: str, where: str) -> Pair:
    if not isinstance(value, list) or len(value) != 2:
        raise _fail(path, where, f"is {value!r}, not a pair [mean, spread]")
    mean, spread = (_rate(path, v, unit, where) for v in value)
    return (mean, spread)


def _rated(path: Path, doc: dict[str, Any], name: str) -> tuple[dict[str, Any], str]:
    """A rates table's `rows` and unit, its `source` checked."""
    table = _get(path, doc, name, dict)
    _source(path, table, name)
    return _get(path, table, "rows", dict, name), _unit(path, table, name, RATES)


def _pairs(path: Path, doc: dict[str, Any], name: str) -> dict[str, Pair]:
    """Table `name`'s rows, key -> [mean, spread]."""
    rows, unit = _rated(path, doc, name)
    return {key: _pair(path, cell, unit, f"{name}.rows.{key}") for key, cell in rows.items()}


def _pairs_by_agent(path: Path, doc: dict[str, Any], name: str) -> dict[str, dict[str, Pair]]:
    """Table `name`'s rows, key -> agent -> [mean, spread]."""
    rows, unit = _rated(path, doc, name)
    out, where = {}, f"{name}.rows"
    for key in rows:
        cells = _get(path, rows, key, dict, where)
        out[key] = {a: _pair(path, c, unit, f"{where}.{key}.{a}") for a, c in cells.items()}
    return out


def load_oposm_paper(path: Path) -> dict[str, Any]:
    """The OPOSM paper's numbers in `path` (oposm_paper.toml), by the names this package gives
    them: TABLE1, TABLE1_LLP, TABLE3, TABLE4, TABLE4_LLP, KITCHEN_TABLE4, FIGURE5_FACTORS,
    FIGURE5, PLAN_SECONDS, EPISODES_MAZE2D."""
    doc = read(path)
    figure = _get(path, doc, "figure5", dict)
    _source(path, figure, "figure5")
    unit = _unit(path, figure, "figure5", RATES)
    factors = tuple(
        float(_number(path, f, "figure5.factors"))
        for f in _get(path, figure, "factors", list, "figure5")
    )
    figure5 = {}
    for agent, series in _get(path, figure, "rows", dict, "figure5").items():
        where = f"figure5.rows.{agent}"
        if not isinstance(series, list) or len(series) != len(factors):
            raise _fail(path, where, f"is {series!r}, not one rate per factor ({len(factors)})")
        figure5[agent] = tuple(_rate(path, v, unit, where) for v in series)
    seconds = _get(path, doc, "plan_seconds", dict)
    _source(path, seconds, "plan_seconds")
    _unit(path, seconds, "plan_seconds", ("seconds",))
    plan_seconds = {
        agent: float(_number(path, v, f"plan_seconds.rows.{agent}"))
        for agent, v in _get(path, seconds, "rows", dict, "plan_seconds").items()
    }
    episodes = _get(path, doc, "episodes_maze2d", dict)
    _source(path, episodes, "episodes_maze2d")
    return {
        "TABLE1": _pairs_by_agent(path, doc, "table1"),
        "TABLE1_LLP": _pairs(path, doc, "table1_llp"),
        "TABLE3": _pairs_by_agent(path, doc, "table3"),
        "TABLE4": _pairs_by_agent(path, doc, "table4"),
        "TABLE4_LLP": _pairs(path, doc, "table4_llp"),
        "KITCHEN_TABLE4": _pairs_by_agent(path, doc, "table4_kitchen"),
        "FIGURE5_FACTORS": factors,
        "FIGURE5": figure5,
        "PLAN_SECONDS": plan_seconds,
        "EPISODES_MAZE2D": _count(path, episodes, "episodes", "episodes_maze2d"),
    }


def load_ogbench(path: Path) -> dict[str, Any]:
    """OGBench's numbers in `path` (ogbench.toml): OGBENCH_METHODS, OGBENCH_SEEDS, OGBENCH (the
    locomotion rows) and OGBENCH_MANIPULATION, each row method -> (mean, std) in the methods'
    order."""
    doc = read(path)
    _source(path, doc)
    methods = tuple(_get(path, doc, "methods", list))
    if not methods or not all(isinstance(m, str) and m for m in methods):
        raise _fail(path, "methods", f"is {list(methods)!r}, not a list of method names")

    def rows(name: str) -> dict[str, dict[str, Pair]]:
        table, unit = _rated(path, doc, name)
        out = {}
        for dataset, cells in table.items():
            where = f"{name}.rows.{dataset}"
            if not isinstance(cells, list) or len(cells) != len(methods):
                raise _fail(path, where, f"is {cells!r}, not one [mean, std] per method "
                            f"({', '.join(methods)})")  # fmt: skip
            out[dataset] = {
                m: _pair(path, cell, unit, f"{where}[{i}] ({m})")
                for i, (m, cell) in enumerate(zip(methods, cells, strict=True))
            }
        return out

    return {
        "OGBENCH_METHODS": methods,
        "OGBENCH_SEEDS": _count(path, doc, "seeds"),
        "OGBENCH": rows("locomotion"),
        "OGBENCH_MANIPULATION": rows("manipulation"),
    }


def load_after_ogbench(path: Path) -> dict[str, Any]:
    """The later methods' numbers in `path` (after_ogbench.toml): SEEDS (method -> the seeds
    behind each mean ± std) and AFTER_OGBENCH (OGBench dataset -> method -> (mean, std))."""
    doc = read(path)
    seeds, after = {}, {}
    for method in _get(path, doc, "methods", dict):
        table = _get(path, doc["methods"], method, dict, "methods")
        where = f"methods.{method}"
        _source(path, table, where)
        unit = _unit(path, table, where, RATES)
        seeds[method] = _count(path, table, "seeds", where)
        for dataset, cell in _get(path, table, "rows", dict, where).items():
            after.setdefault(dataset, {})[method] = _pair(path, cell, unit, f"{where}.{dataset}")
    return {"SEEDS": seeds, "AFTER_OGBENCH": after}


_PAPER = load_oposm_paper(Path(__file__).with_name("oposm_paper.toml"))
_OGBENCH = load_ogbench(Path(__file__).with_name("ogbench.toml"))
_AFTER = load_after_ogbench(Path(__file__).with_name("after_ogbench.toml"))

# The OPOSM paper. Table 1: success on D4RL antmaze's fixed goal; table 4: random goals (maze2d
# rows by maze, the antmaze rows by D4RL dataset); their LLP columns on the ant; table 3: EM
# against naive VI on the ant; table 4's FrankaKitchen rows.
TABLE1: dict[str, dict[str, Pair]] = _PAPER["TABLE1"]
TABLE1_LLP: dict[str, Pair] = _PAPER["TABLE1_LLP"]
TABLE3: dict[str, dict[str, Pair]] = _PAPER["TABLE3"]
TABLE4: dict[str, dict[str, Pair]] = _PAPER["TABLE4"]
TABLE4_LLP: dict[str, Pair] = _PAPER["TABLE4_LLP"]
KITCHEN_TABLE4: dict[str, dict[str, Pair]] = _PAPER["KITCHEN_TABLE4"]
FIGURE5_FACTORS: tuple[float, ...] = _PAPER["FIGURE5_FACTORS"]  # antmaze-large's density factors
FIGURE5: dict[str, tuple[float, ...]] = _PAPER["FIGURE5"]  # agent -> success per factor
PLAN_SECONDS: dict[str, float] = _PAPER["PLAN_SECONDS"]  # maze2d, seconds per plan
EPISODES_MAZE2D: int = _PAPER["EPISODES_MAZE2D"]  # episodes behind each maze2d rate

# OGBench: its methods (in its tables' order), the seeds behind each cell, its locomotion rows
# (point and ant mazes, antmaze-giant-navigate included) and manipulation rows.
OGBENCH_METHODS: tuple[str, ...] = _OGBENCH["OGBENCH_METHODS"]
OGBENCH_SEEDS: int = _OGBENCH["OGBENCH_SEEDS"]
OGBENCH: dict[str, dict[str, Pair]] = _OGBENCH["OGBENCH"]
OGBENCH_MANIPULATION: dict[str, dict[str, Pair]] = _OGBENCH["OGBENCH_MANIPULATION"]

# Methods after OGBench: method -> seeds; OGBench dataset -> method -> (mean, std).
SEEDS: dict[str, int] = _AFTER["SEEDS"]
AFTER_OGBENCH: dict[str, dict[str, Pair]] = _AFTER["AFTER_OGBENCH"]
