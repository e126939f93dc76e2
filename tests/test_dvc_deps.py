"""Every stage's `deps` in dvc.yaml cover the code it runs, so editing that code reruns it.

The code a stage runs is `stages/<stage>.py` and every project module it imports, transitively
(AST scan, lazy imports included; `from package import name` also counts `package/name.py`).
"""

import ast
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "stages")
# Plumbing that cannot change what a stage computes: not required in deps and not followed.
# config.py: the params themselves are tracked by each stage's `params:` (and params.yaml equals
# the config defaults, tests/test_config.py); its imports are for validating names.
# readback.py: the checks of files read back, which pass a valid file's values on unchanged or
# refuse the file.
# cpu_math.py: MKL's reproducibility mode, which pipeline/__init__.py sets for every module; like
# the locked torch and MKL versions (uv.lock) it is the environment a lock was made in, and the
# README names it, rather than one stage's code.
NOT_RESULTS = {
    "pipeline/__init__.py",
    "pipeline/cpu_math.py",
    "stages/__init__.py",
    "pipeline/errors.py",
    "pipeline/paths.py",
    "pipeline/io.py",
    "pipeline/devices.py",
    "pipeline/config.py",
    "pipeline/readback.py",
}


def _module_file(name: str) -> Path | None:
    parts = name.split(".")
    if parts[0] not in PACKAGES:
        return None
    base = ROOT.joinpath(*parts)
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.exists():
            return candidate
    return None


def _imports(path: Path) -> set[Path]:
    found: set[Path] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        for name in names:
            parts = name.split(".")
            for i in range(1, len(parts) + 1):  # importing a.b.c runs a/__init__, a/b/__init__
                module = _module_file(".".join(parts[:i]))
                if module is not None:
                    found.add(module)
    return found


def _docstring_only(path: Path) -> bool:
    return all(isinstance(n, ast.Expr) for n in ast.parse(path.read_text()).body)


def code_of(stage_file: Path) -> set[Path]:
    """The project files `stage_file` runs: itself and everything it imports, transitively."""
    seen, todo = set(), [stage_file]
    while todo:
        path = todo.pop()
        if (
            path in seen
            or path.relative_to(ROOT).as_posix() in NOT_RESULTS
            or _docstring_only(path)
        ):
            continue
        seen.add(path)
        todo += _imports(path) - seen
    return seen


PIPELINES = (
    "dvc.yaml",
    "experiments/dvc.yaml",
    "experiments/ogbench/dvc.yaml",
    "experiments/antmaze/dvc.yaml",
    "experiments/manipulation/dvc.yaml",
)  # the main job, the paper's experiments, OGBench's point mazes, the ant mazes, manipulation


def _stages() -> dict[str, dict]:
    """`<dvc.yaml>:<stage>` -> the stage's definition (a foreach stage's `do` body)."""
    stages = {}
    for pipeline in PIPELINES:
        for name, spec in yaml.safe_load((ROOT / pipeline).read_text())["stages"].items():
            stages[f"{pipeline}:{name}"] = spec.get("do", spec)
    return stages


# Packages whose __init__ re-exports their core classes (listed in deps where used).
REEXPORTING = {
    "pipeline/model/__init__.py",
    "pipeline/planning/__init__.py",
    "pipeline/recording/__init__.py",
    "pipeline/sources/__init__.py",
    "pipeline/sources/ogbench/__init__.py",  # keeps `from pipeline.sources.ogbench import ...`
}


def test_package_inits_hold_no_code():
    """A package's __init__ runs on every import of its modules: keep them docstring-only, so
    a stage's code is the modules it names; pipeline/__init__.py only sets the CPU arithmetic
    mode (`cpu_math`) before any matrix product."""
    for init in [*ROOT.glob("pipeline/**/__init__.py"), ROOT / "stages/__init__.py"]:
        rel = init.relative_to(ROOT).as_posix()
        if rel in REEXPORTING:
            continue
        if rel == "pipeline/__init__.py":
            body = [n for n in ast.parse(init.read_text()).body if not isinstance(n, ast.Expr)]
            assert [type(n) for n in body] == [ast.ImportFrom], f"{rel} runs more than cpu_math"
            assert "cpu_math.set_default_environment()" in init.read_text()
            continue
        assert _docstring_only(init), f"{rel} runs code on import"


def test_the_scan_follows_imports_into_packages():
    code = {p.relative_to(ROOT).as_posix() for p in code_of(ROOT / "stages/train.py")}
    assert {"stages/train.py", "pipeline/training/loop.py", "pipeline/model/__init__.py"} <= code


def _entry_point(cmd: str) -> Path:
    """The file a stage's command runs: `oposm <stage>` -> stages/<stage>.py, `python <script>`
    -> the script."""
    words = cmd.split()
    if words[0] == "oposm":
        return ROOT / "stages" / f"{words[1]}.py"
    assert words[0] == "python" and words[1].endswith(".py"), f"unknown command: {cmd}"
    return ROOT / words[1]


def test_the_entry_points_are_found():
    stages = _stages()
    assert _entry_point(stages["dvc.yaml:train"]["cmd"]) == ROOT / "stages/train.py"
    report = _entry_point(stages["experiments/ogbench/dvc.yaml:report"]["cmd"])
    assert report == ROOT / "scripts/ogbench_point_report.py"


@pytest.mark.parametrize("stage", sorted(_stages()))
def test_stage_deps_cover_the_code_it_runs(stage):
    spec = _stages()[stage]
    deps = [d if isinstance(d, str) else next(iter(d)) for d in spec["deps"]]
    missing = []
    for path in sorted(code_of(_entry_point(spec["cmd"]))):
        rel = path.relative_to(ROOT).as_posix()
        if not any(rel == d or rel.startswith(d.rstrip("/") + "/") for d in deps):
            missing.append(rel)
    assert not missing, f"{stage} runs code it does not list in deps: {missing}"
