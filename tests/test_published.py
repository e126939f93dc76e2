"""pipeline/evaluation/published: the published numbers as data files with their sources. Every
table names its source, every row is whole (one cell per method, one rate per factor), the rates
are fractions, a few cells are the ones printed, and a damaged file fails naming itself."""

import tomllib
from pathlib import Path

import pytest

from pipeline.evaluation import published
from pipeline.evaluation.published import (
    AFTER_OGBENCH,
    FIGURE5,
    FIGURE5_FACTORS,
    KITCHEN_TABLE4,
    OGBENCH,
    OGBENCH_MANIPULATION,
    OGBENCH_METHODS,
    TABLE1,
    TABLE1_LLP,
    TABLE3,
    TABLE4,
    TABLE4_LLP,
    PublishedDataError,
    load_after_ogbench,
    load_ogbench,
    load_oposm_paper,
)

HERE = Path(published.__file__).parent
FILES = {
    "oposm_paper.toml": load_oposm_paper,
    "ogbench.toml": load_ogbench,
    "after_ogbench.toml": load_after_ogbench,
}


def _tables(node: dict, where: str = "") -> list[tuple[str, dict]]:
    """The tables of a TOML document that hold numbers or settings of their own (a value that is
    not a table, a note aside), by dotted name, the top level included; a table's `rows` are
    its own (not descended into)."""
    own = any(not isinstance(v, dict) for k, v in node.items() if k != "note")
    found = [(where or "(top level)", node)] if own else []
    for key, value in node.items():
        if isinstance(value, dict) and key != "rows":
            found += _tables(value, f"{where}.{key}" if where else key)
    return found


def test_the_package_holds_one_file_per_source():
    assert sorted(p.name for p in HERE.glob("*.toml")) == sorted(FILES)


@pytest.mark.parametrize("name", list(FILES))
def test_every_table_of_numbers_names_its_source(name):
    """Every table (OGBench's methods and seeds at its top level included) says where in which
    paper its numbers are and what they are, and a table of rows their unit; after_ogbench.toml
    keeps its note on what is left out."""
    doc = tomllib.loads((HERE / name).read_text())
    tables = _tables(doc)
    assert tables, name
    for where, table in tables:
        source = table.get("source")
        assert isinstance(source, str) and source.strip(), f"{name}: {where} has no source"
        assert "rows" not in table or table.get("unit"), f"{name}: {where} has no unit"
    if name == "after_ogbench.toml":
        assert "ALPS" in doc["note"] and "SCoTS" in doc["note"]


def test_every_ogbench_row_has_one_mean_and_std_per_method():
    assert OGBENCH_METHODS == ("GCBC", "GCIVL", "GCIQL", "QRL", "CRL", "HIQL")
    for table in (OGBENCH, OGBENCH_MANIPULATION):
        for dataset, row in table.items():
            assert tuple(row) == OGBENCH_METHODS, dataset
            assert all(len(cell) == 2 for cell in row.values()), dataset
    assert "antmaze-giant-navigate" in OGBENCH and "pointmaze-giant-stitch" in OGBENCH


def _pairs() -> list[tuple[str, tuple[float, float]]]:
    out = []
    for name, table in (("TABLE1_LLP", TABLE1_LLP), ("TABLE4_LLP", TABLE4_LLP)):
        out += [(f"{name}[{k}]", cell) for k, cell in table.items()]
    for name, table in (
        ("TABLE1", TABLE1), ("TABLE3", TABLE3), ("TABLE4", TABLE4),
        ("KITCHEN_TABLE4", KITCHEN_TABLE4), ("OGBENCH", OGBENCH),
        ("OGBENCH_MANIPULATION", OGBENCH_MANIPULATION), ("AFTER_OGBENCH", AFTER_OGBENCH),
    ):  # fmt: skip
        out += [(f"{name}[{k}][{a}]", cell) for k, row in table.items() for a, cell in row.items()]
    return out


def test_every_rate_is_a_fraction():
    pairs = _pairs()
    assert len(pairs) > 100
    for where, (mean, spread) in pairs:
        assert isinstance(mean, float) and isinstance(spread, float), where
        assert 0 <= mean <= 1 and 0 <= spread <= 1, f"{where}: {mean}, {spread}"
    for agent, series in FIGURE5.items():
        assert all(isinstance(v, float) and 0 <= v <= 1 for v in series), agent


def test_figure5_has_one_rate_per_factor():
    assert FIGURE5_FACTORS == (0.2, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0)
    assert set(FIGURE5) == {"oposm", "expert", "opal_bc"}
    for agent, series in FIGURE5.items():
        assert len(series) == len(FIGURE5_FACTORS), agent


def test_cells_as_printed():
    assert OGBENCH_MANIPULATION["cube-double-play"]["GCIQL"] == (0.40, 0.05)
    assert OGBENCH["antmaze-giant-navigate"]["HIQL"] == (0.65, 0.05)
    assert OGBENCH["pointmaze-medium-navigate"]["QRL"] == (0.82, 0.05)
    assert TABLE4["medium"]["oposm"] == (1.0, 0.0)
    assert TABLE4["large"]["llp"] == (0.8667, 0.0497)
    assert TABLE1_LLP["antmaze-large-diverse"] == (0.144, 0.0435)
    assert KITCHEN_TABLE4["kitchen-mixed"]["oposm"] == (0.53125, 0.040)
    assert AFTER_OGBENCH["pointmaze-medium-navigate"]["SAW"] == (0.97, 0.02)
    assert published.SEEDS == {"SAW": 8} and published.OGBENCH_SEEDS == 8
    assert published.EPISODES_MAZE2D == 250
    assert published.PLAN_SECONDS == {"oposm": 0.051, "llp": 3.02}


# file, text replaced, its damage, what the error says besides the file
DAMAGE = [
    ("ogbench.toml", "seeds = 8", "", "`seeds` is missing"),
    ("ogbench.toml", "[[9, 6], [63, 6],", "[[63, 6],", "`locomotion.rows.pointmaze-medium-"),
    ("oposm_paper.toml", 'unit = "fraction"\n\n[table4.rows]', "[table4.rows]", "`table4.unit`"),
    ("oposm_paper.toml", "oposm = [0.35, 0.51,", "oposm = [0.51,", "`figure5.rows.oposm`"),
    ("oposm_paper.toml", "[table1]", "[table1", "cannot read it as TOML"),
    ("after_ogbench.toml", 'source = """SAW', 'origin = """SAW', "`methods.SAW.source` is missing"),
    ("after_ogbench.toml", "[97, 2]", '["97", 2]', "`methods.SAW.pointmaze-medium-navigate`"),
]


@pytest.mark.parametrize(("name", "old", "new", "says"), DAMAGE)
def test_a_damaged_file_fails_naming_itself(tmp_path, name, old, new, says):
    text = (HERE / name).read_text()
    assert text.count(old) == 1, old
    intact, damaged = tmp_path / "intact" / name, tmp_path / "damaged" / name
    for path, content in ((intact, text), (damaged, text.replace(old, new))):
        path.parent.mkdir()
        path.write_text(content)
    assert FILES[name](intact) == FILES[name](HERE / name)  # the copy itself reads
    with pytest.raises(PublishedDataError) as error:
        FILES[name](damaged)
    assert str(damaged) in str(error.value) and says in str(error.value), str(error.value)
