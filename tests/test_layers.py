"""The layering of docs/development.md: the library (`pipeline/`) imports nothing from the stage
layer, the CLI or the benchmarks, and stages do not import the CLI or the benchmarks. Checked on
every module's source (AST), including imports inside functions, so a lazy import cannot hide a
dependency."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, dotted name) of every absolute import in a Python file."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module))
    return out


def offending(package: str, forbidden: tuple[str, ...]) -> list[str]:
    """`file:line imports name` for each import of a forbidden top-level package."""
    found = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for line, name in imported_modules(path):
            if name.split(".")[0] in forbidden:
                found.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    return found


def test_the_import_scan_sees_lazy_imports(tmp_path):
    source = tmp_path / "m.py"
    source.write_text("import os\n\ndef f():\n    from stages import run\n    import bench.plan\n")
    assert [n for _, n in imported_modules(source)] == ["os", "stages", "bench.plan"]


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [("pipeline", ("stages", "cli", "bench")), ("stages", ("cli", "bench"))],
)
def test_lower_layers_never_import_higher_ones(package, forbidden):
    assert offending(package, forbidden) == []
