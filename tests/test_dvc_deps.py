"""Every stage's `deps` in the dvc.yaml files are the code it runs, generated from the import
graph by scripts/dvc_deps.py (so editing that code reruns it, and nothing else does), and the
script's `--record` re-expresses a lock's code entries without hiding a change."""

import importlib.util
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


def _module():
    spec = importlib.util.spec_from_file_location("dvc_deps", ROOT / "scripts/dvc_deps.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks its module up
    spec.loader.exec_module(module)
    return module


deps = _module()

# Packages whose __init__ re-exports their core classes (a stage that imports them runs them).
REEXPORTING = {
    "pipeline/model/__init__.py",
    "pipeline/planning/__init__.py",
    "pipeline/recording/__init__.py",
    "pipeline/sources/__init__.py",
    "pipeline/sources/ogbench/__init__.py",  # keeps `from pipeline.sources.ogbench import ...`
    "pipeline/evaluation/published/__init__.py",  # the loader of the data files beside it
}


def test_package_inits_hold_no_code():
    """A package's __init__ runs on every import of its modules: keep them docstring-only, so
    a stage's code is the modules it names; pipeline/__init__.py only sets the CPU arithmetic
    mode (`cpu_math`) before any matrix product."""
    import ast

    for init in [*ROOT.glob("pipeline/**/__init__.py"), ROOT / "stages/__init__.py"]:
        rel = init.relative_to(ROOT).as_posix()
        if rel in REEXPORTING:
            continue
        if rel == "pipeline/__init__.py":
            body = [n for n in ast.parse(init.read_text()).body if not isinstance(n, ast.Expr)]
            assert [type(n) for n in body] == [ast.ImportFrom], f"{rel} runs more than cpu_math"
            assert "cpu_math.set_default_environment()" in init.read_text()
            continue
        assert deps.docstring_only(init), f"{rel} runs code on import"


def test_the_scan_follows_imports_into_packages_and_functions():
    code = {deps.rel(p) for p in deps.code_of(ROOT / "stages/train.py")}
    assert {"stages/train.py", "pipeline/training/loop.py", "pipeline/model/__init__.py"} <= code
    assert "pipeline/config.py" not in code  # plumbing: the params are the stage's `params:`
    listed = deps.code_deps("oposm deploy")
    assert listed[0] == "stages/deploy.py" and "pipeline/planning" in listed  # a folder
    assert not any(p.startswith("pipeline/planning/") for p in listed)


def test_the_entry_points_are_found():
    assert deps.entry_point("oposm train -S x=1") == ROOT / "stages/train.py"
    script = "python scripts/stability_report.py --x"
    assert deps.entry_point(script) == ROOT / "scripts/stability_report.py"
    page = "oposm report ogbench-point --vars v.yaml"
    assert deps.entry_point(page) == ROOT / "stages/ogbench_point_report.py"
    with pytest.raises(ValueError, match="unknown command"):
        deps.entry_point("bash run.sh")


@pytest.mark.parametrize("pipeline", deps.PIPELINES)
def test_every_stage_lists_the_generated_code_deps(pipeline):
    """`scripts/dvc_deps.py --check`: rewriting the file would change nothing."""
    _, changed = deps.rewritten((ROOT / pipeline).read_text())
    assert not changed, f"{pipeline}: run `uv run python scripts/dvc_deps.py` ({changed})"


def test_a_missing_or_extra_code_entry_is_rewritten_and_data_entries_stay():
    text = (ROOT / "dvc.yaml").read_text()
    broken = text.replace("      - pipeline/segments.py\n", "", 1).replace(
        "      - stages/train.py\n", "      - stages/train.py\n      - pipeline/extra.py\n", 1
    )
    fixed, changed = deps.rewritten(broken)
    assert fixed == text and changed
    assert "- data/segments/${ingest.name}" in fixed  # the data entry kept, before the code
    assert yaml.safe_load(fixed)["stages"]["train"]["deps"][0] == "data/segments/${ingest.name}"


def test_a_comment_inside_a_deps_list_keeps_the_list_whole():
    """Data entries after a comment line stay in the stage's list, the code entries come after
    them all, once each, and the comment stays where it was."""
    text = """stages:
  report:
    cmd: oposm segment
    deps:
      - data/a
      - stages/segment.py
      # more roots (a comment inside the list)
      - data/b
      - stages/segment.py
    outs:
      - out
"""
    fixed, changed = deps.rewritten(text)
    listed = yaml.safe_load(fixed)["stages"]["report"]["deps"]
    assert changed == ["report"] and listed[:2] == ["data/a", "data/b"]
    assert listed[2:] == list(deps.code_deps("oposm segment"))
    assert "      # more roots (a comment inside the list)\n      - data/b" in fixed


def _run(repo: Path, *args: str) -> str:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    env.pop("DVC_STAGE", None)
    out = subprocess.run(args, cwd=repo, env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout + out.stderr


def test_a_renamed_entry_point_keeps_its_arguments():
    """`--record` writes a stage's new command only where the locked one, its entry point renamed
    by COMMAND_MOVES, is exactly it: the same arguments after it."""
    old = "python scripts/antmaze_report.py page results/antmaze/medium.json --out results"
    assert (
        deps.moved_command(old)
        == "oposm report antmaze page results/antmaze/medium.json --out results"
    )
    assert deps.moved_command("oposm results") == "oposm report experiments"
    assert deps.moved_command("oposm resultsx --y") == "oposm resultsx --y"  # not a prefix word
    assert deps.moved_command("oposm train -S a=1") == "oposm train -S a=1"
    for _old, new in deps.COMMAND_MOVES:  # every new entry point is a file the scan can read
        assert deps.entry_point(new + " x").exists(), new


@pytest.mark.slow  # the real dvc, in a repository of its own
def test_record_re_expresses_unchanged_code_and_keeps_a_change_stale(tmp_path):
    """A lock listing a package's files, its dvc.yaml now the package's folder: `record` writes
    the folder's hash when the files are as the lock recorded them (`dvc status` clean), and
    leaves it stale when one changed."""
    for case, edit in (("same", False), ("edited", True)):
        repo = tmp_path / case
        (repo / "pipeline/model").mkdir(parents=True)
        (repo / "pipeline/model/a.py").write_text("A = 1\n")
        (repo / "pipeline/model/b.py").write_text("B = 2\n")
        stage = textwrap.dedent("""\
            stages:
              make:
                cmd: echo made > out.txt
                deps:
                - pipeline/model/a.py
                - pipeline/model/b.py
                outs:
                - out.txt
            """)
        (repo / "dvc.yaml").write_text(stage)
        _run(repo, "git", "init", "-q")
        _run(repo, sys.executable, "-m", "dvc", "init", "-q")
        _run(repo, sys.executable, "-m", "dvc", "repro", "-q")
        (repo / "dvc.yaml").write_text(
            stage.replace("- pipeline/model/a.py\n    - pipeline/model/b.py", "- pipeline/model")
        )
        if edit:
            (repo / "pipeline/model/b.py").write_text("B = 3\n")
        done = deps.record("dvc.yaml", root=repo)
        status = _run(repo, sys.executable, "-m", "dvc", "status")
        lock = yaml.safe_load((repo / "dvc.lock").read_text())["stages"]["make"]["deps"]
        if edit:
            assert done[0] == "dvc.yaml:make: pipeline/model left stale (changed since the lock)"
            assert "pipeline/model" in status
            assert [e["path"] for e in lock] == ["pipeline/model/a.py", "pipeline/model/b.py"]
        else:
            assert "dvc.yaml:make: pipeline/model recorded (unchanged since the lock)" in done
            assert "Data and pipelines are up to date" in status
            assert [e["path"] for e in lock] == ["pipeline/model"]


@pytest.mark.slow  # the real dvc, in a repository of its own
def test_record_takes_a_file_moved_unchanged_and_keeps_a_moved_and_edited_one_stale(tmp_path):
    """A module moved to a new folder: `record` writes its new entry when its content is what the
    lock recorded under the old path (`dvc status` clean), and leaves it new when it changed."""
    for case, edit in (("same", False), ("edited", True)):
        repo = tmp_path / case
        (repo / "pipeline/envs").mkdir(parents=True)
        (repo / "pipeline/envs/actor.py").write_text("A = 1\n")
        stage = "stages:\n  make:\n    cmd: echo made > out.txt\n    deps:\n    - {}\n"
        stage += "    outs:\n    - out.txt\n"
        (repo / "dvc.yaml").write_text(stage.format("pipeline/envs/actor.py"))
        _run(repo, "git", "init", "-q")
        _run(repo, sys.executable, "-m", "dvc", "init", "-q")
        _run(repo, sys.executable, "-m", "dvc", "repro", "-q")
        (repo / "pipeline/expert").mkdir()
        (repo / "pipeline/envs/actor.py").rename(repo / "pipeline/expert/actor.py")
        if edit:
            (repo / "pipeline/expert/actor.py").write_text("A = 2\n")
        (repo / "dvc.yaml").write_text(stage.format("pipeline/expert/actor.py"))
        done = deps.record("dvc.yaml", root=repo)
        status = _run(repo, sys.executable, "-m", "dvc", "status")
        lock = yaml.safe_load((repo / "dvc.lock").read_text())["stages"]["make"]["deps"]
        if edit:
            new = "dvc.yaml:make: pipeline/expert/actor.py left new (the stage never ran it)"
            assert new in done
            assert "pipeline/expert/actor.py" in status
            assert lock == []
        else:
            assert (
                "dvc.yaml:make: pipeline/expert/actor.py recorded (pipeline/envs/actor.py moved "
                "here unchanged)" in done
            )
            assert "Data and pipelines are up to date" in status
            assert [e["path"] for e in lock] == ["pipeline/expert/actor.py"]


@pytest.mark.slow  # the real dvc, in a repository of its own
def test_bytecode_caches_are_not_inputs(tmp_path):
    """Python writes `__pycache__/` beside the code a stage imports (where
    PYTHONDONTWRITEBYTECODE is not set): the repository's .dvcignore keeps it out of a code
    folder's hash, so a fresh clone's second `dvc repro` reruns nothing."""
    repo = tmp_path / "repo"
    (repo / "pipeline/model").mkdir(parents=True)
    (repo / "pipeline/model/a.py").write_text("A = 1\n")
    (repo / ".dvcignore").write_text((ROOT / ".dvcignore").read_text())
    stage = "stages:\n  make:\n    cmd: echo made > out.txt\n    deps:\n    - pipeline/model\n"
    (repo / "dvc.yaml").write_text(stage + "    outs:\n    - out.txt\n")
    _run(repo, "git", "init", "-q")
    _run(repo, sys.executable, "-m", "dvc", "init", "-q")
    _run(repo, sys.executable, "-m", "dvc", "repro", "-q")
    (repo / "pipeline/model/__pycache__").mkdir()
    (repo / "pipeline/model/__pycache__/a.cpython-312.pyc").write_bytes(b"\x00bytecode")
    assert "Data and pipelines are up to date" in _run(repo, sys.executable, "-m", "dvc", "status")
    (repo / "pipeline/model/b.py").write_text("B = 2\n")  # a real change still shows
    assert "pipeline/model" in _run(repo, sys.executable, "-m", "dvc", "status")
