"""The layering of docs/development.md: the library (`pipeline/`) imports nothing from the stage
layer, the CLI or the benchmarks, and stages do not import the CLI or the benchmarks; inside the
library every part imports only parts on lower floors (`FLOORS`). Checked on every module's source
(AST), including imports inside functions, so a lazy import cannot hide a dependency. Loading the
params loads no simulator and no torch (checked in a fresh interpreter)."""

import ast
import json
import subprocess
import sys
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


# The library's floors, ground first. A part is a module or package under pipeline/, named by
# its dotted path (the longest listed prefix wins: `envs.ids` is a part of its own, the rest of
# `pipeline/envs/` is `envs`). A part imports only parts on lower floors, never one on its own
# floor or above; a new part must be given a floor here. A feature package (`ant_expert`) keeps
# its modules together and gives each its own floor: its actor sits below the envs that drive
# it, its check above the evaluation it uses.
FLOORS: tuple[tuple[str, ...], ...] = (
    ("errors", "cpu_math", "envs.ids"),  # envs.ids: the env ids, no simulator
    ("__init__", "io", "readback", "devices", "envs.maze.expert", "ant_expert"),
    ("config", "dataset", "paths", "ant_expert.actor"),  # the params: below every simulator
    ("segments", "recording", "envs"),
    ("model", "sources", "ant_expert.config"),
    ("planning", "training", "ant_expert.training"),
    ("evaluation", "value"),
    ("reporting", "viz", "analysis", "ant_expert.check"),
)
FLOOR = {part: level for level, parts in enumerate(FLOORS) for part in parts}


def part_of(dotted: str) -> str | None:
    """The `FLOORS` part holding `dotted` (a path under pipeline, `envs.maze.Cell`), or None."""
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in FLOOR:
            return ".".join(parts[:n])
    return None


def library_imports(path: Path) -> list[tuple[int, str]]:
    """(line, name under pipeline) of every import of the library in a Python file; for
    `from pipeline.a import b` the name is `a.b` (b may be a module: `from pipeline import io`)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [f"{node.module}.{alias.name}" for alias in node.names]
        out += [(node.lineno, n.removeprefix("pipeline.")) for n in names
                if n.startswith("pipeline.")]  # fmt: skip
    return out


def test_the_floors_read_dotted_names():
    assert part_of("envs.ids.SUPPORTED_ENVS") == "envs.ids"
    assert part_of("envs.maze.layout_cell") == "envs"
    assert part_of("cpu_math") == "cpu_math"
    assert part_of("no_such_part.x") is None


def test_every_library_part_has_a_floor():
    root = ROOT / "pipeline"
    modules = [".".join(p.relative_to(root).with_suffix("").parts) for p in root.rglob("*.py")]
    assert [m for m in sorted(modules) if part_of(m) is None] == []


def upward_imports(root: Path) -> list[str]:
    """`file:line (part) imports name (part)` for each import, in the library at `root`, of a
    part on the importer's own floor or above."""
    found = []
    for path in sorted(root.rglob("*.py")):
        here = part_of(".".join(path.relative_to(root).with_suffix("").parts))
        for line, name in library_imports(path):
            there = part_of(name)
            if here is not None and there not in (None, here) and FLOOR[there] >= FLOOR[here]:
                found.append(f"{path.relative_to(root)}:{line} ({here}) imports {name} ({there})")
    return found


def test_library_parts_import_only_lower_floors():
    assert upward_imports(ROOT / "pipeline") == []


def test_the_floor_check_sees_upward_and_sideways_imports(tmp_path):
    (tmp_path / "envs").mkdir()
    (tmp_path / "envs" / "solver.py").write_text(
        "from pipeline.envs.ids import TASKS\n\n"
        "def f():\n    from pipeline.evaluation.tasks import TASKS\n"
    )
    (tmp_path / "training.py").write_text("from pipeline import planning\n")
    assert upward_imports(tmp_path) == [
        "envs/solver.py:4 (envs) imports evaluation.tasks.TASKS (evaluation)",
        "training.py:1 (training) imports planning (planning)",
    ]


def test_loading_params_loads_no_simulator_and_no_torch():
    """`oposm params` and every stage's first step load the params: reading a YAML file must
    not import MuJoCo, gymnasium or torch (`pipeline.envs.ids` holds the env ids it checks)."""
    files = sorted(str(p) for p in ROOT.glob("params*.yaml"))
    code = (
        "import json, sys\n"
        "from pipeline.config import load_params\n"
        f"for f in {files!r}:\n"
        "    load_params(f)\n"
        "print(json.dumps([m for m in ('mujoco', 'gymnasium', 'torch') if m in sys.modules]))\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout.splitlines()[-1]) == []
