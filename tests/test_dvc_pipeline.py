"""The real `dvc repro` of the pipeline, in a temporary copy of the repository, on tiny params."""

import csv
import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
TINY = {
    "ingest": {"episodes": 6, "episode_steps": 150},
    "segment": {"window": 20},
    "train": {"z_dim": 4, "hidden": 16, "max_steps": 20, "eval_every": 10, "val_windows": 50},
    "dynamics": {"hidden": 16, "max_steps": 50, "eval_every": 25, "val_transitions": 200},
    "bc": {"hidden": 16, "max_steps": 50, "eval_every": 25, "val_transitions": 200},
    "gcbc": {"hidden": 16, "max_steps": 50, "eval_every": 25, "val_transitions": 200},
    "validate": {"starts": 5, "skills": 2, "repeats": 2, "particles": 8, "record_starts": 1},
    "deploy": {
        "episodes": 2,
        "max_steps": 40,
        "record_episodes": 1,
        "planner": {"horizon": 2, "candidates": 8, "elites": 2, "iterations": 2},
    },
}


def _copy_repository(dest: Path) -> None:
    files = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
        cwd=ROOT,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.split("\0")
    for name in filter(None, files):
        src = ROOT / name
        if src.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)
    (dest / "dvc.lock").unlink(missing_ok=True)  # a fresh run, whatever was committed
    shutil.rmtree(dest / "experiments")  # the main job's workflow only (its outputs: hours)


def _set_params(repo: Path, overrides: dict) -> None:
    params = yaml.safe_load((repo / "params.yaml").read_text())
    for section, values in overrides.items():
        params[section].update(values)
    (repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))


def _dvc(repo: Path, *args: str) -> str:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    result = subprocess.run(
        [sys.executable, "-m", "dvc", *args], cwd=repo, env=env, capture_output=True, text=True
    )
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout + result.stderr


def _git(repo: Path, *args: str) -> str:
    result = subprocess.run(
        ["git", "-c", "user.name=t", "-c", "user.email=t@t", *args],
        cwd=repo,
        check=True,
        capture_output=True,
        text=True,
    )
    return result.stdout


@pytest.fixture
def repo(tmp_path) -> Path:
    """A git copy of the repository on tiny params, with no outputs and no dvc.lock."""
    repo = tmp_path / "repo"
    _copy_repository(repo)
    shutil.rmtree(repo / "metrics", ignore_errors=True)
    _set_params(repo, TINY)
    _git(repo, "init", "-q")
    _git(repo, "add", "-A")
    _git(repo, "commit", "-qm", "copy")
    return repo


def _model_weights(repo: Path) -> bytes:
    return (repo / "data/models/pointmaze-medium/model.safetensors").read_bytes()


@pytest.mark.slow
def test_dvc_repro_experiments_compare_and_models_come_back_from_the_cache(repo):
    """The DVC workflow of docs/experiments.md in one pass (a `dvc repro` costs half a minute)."""
    first = _dvc(repo, "repro")
    assert "Running stage 'ingest'" in first and "Running stage 'segment'" in first
    assert "Running stage 'deploy'" in first and "random_goal  success" in first
    for stage in ("ingest", "segment", "train", "dynamics", "bc", "gcbc", "validate", "deploy"):
        assert (repo / f"metrics/{stage}.json").exists(), stage
    metrics = _dvc(repo, "metrics", "show")
    assert "train_windows" in metrics and "best_val_st_nll" in metrics
    shown = json.loads(_dvc(repo, "metrics", "show", "--json"))
    (files,) = [rev["data"] for rev in shown.values()]

    def leaves(node) -> int:
        return sum(leaves(v) for v in node.values()) if isinstance(node, dict) else 1

    assert leaves({f: d["data"] for f, d in files.items()}) <= 50  # headlines (it was 317)
    assert "Running stage" not in _dvc(repo, "repro")
    baseline = _model_weights(repo)
    _git(repo, "add", "dvc.lock", "metrics")
    _git(repo, "commit", "-qm", "baseline results")

    short = _dvc(repo, "exp", "run", "-n", "short", "-S", "train.max_steps=10")
    assert "Running stage 'train'" in short and "Running stage 'segment'" not in short
    assert _model_weights(repo) != baseline
    _dvc(repo, "exp", "run", "-n", "seed1", "-S", "train.seed=1")

    table = _dvc(repo, "exp", "show", "--csv", "--no-fetch")
    rows = list(csv.DictReader(io.StringIO(table)))
    by_name = {row["Experiment"] or row["rev"]: row for row in rows}

    def metric(row: dict, name: str) -> str:  # DVC names a column by its shortest unique suffix
        (column,) = [c for c in row if c == name or c.endswith(f":{name}")]
        return row[column]

    for name in ("short", "seed1", "workspace"):
        nll = metric(by_name[name], "best_val_st_nll")
        assert nll not in ("", "!", "-"), (name, nll)
        assert metric(by_name[name], "oposm.random_goal.success") not in ("", "!", "-")
    assert metric(by_name["short"], "best_step") == "10"
    assert metric(by_name["seed1"], "best_val_st_nll") != metric(
        by_name["short"], "best_val_st_nll"
    )

    # Back to the first experiment: its model comes from the cache, nothing retrains.
    _dvc(repo, "exp", "apply", "short")
    assert "Running stage" not in _dvc(repo, "repro")
    diff = _dvc(repo, "metrics", "diff", "--md")
    assert "best_val_st_nll" in diff and "steps" in diff

    # Back to the committed params without their dvc.lock: the run cache restores the model.
    _git(repo, "checkout", "--", "params.yaml")
    (repo / "dvc.lock").unlink()
    again = _dvc(repo, "repro")
    assert "Running stage 'train'" not in again and "Stage 'train' is cached" in again
    assert _model_weights(repo) == baseline


@pytest.mark.slow
def test_committed_dvc_lock_matches_params_and_code():
    """`dvc.lock` records the params and code of the default main job: it cannot go stale."""
    from dvc.dependency.param import ParamsDependency
    from dvc.repo import Repo

    lock = yaml.safe_load((ROOT / "dvc.lock").read_text())["stages"]
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    with Repo(str(ROOT)) as dvc_repo:
        stages = {  # the main job's (experiments/dvc.yaml has its own lock)
            stage.addressing: stage
            for stage in dvc_repo.index.stages
            if stage.dvcfile.path == str(ROOT / "dvc.yaml")
        }
        assert set(lock) == set(stages), "dvc.lock and dvc.yaml list different stages"
        for name, stage in stages.items():
            for section, values in lock[name].get("params", {}).get("params.yaml", {}).items():
                node = params
                for part in section.split("."):
                    node = node[part]
                assert node == values, f"dvc.lock: {name} params {section} are stale"
            recorded = {d["path"]: d["md5"] for d in lock[name]["deps"]}
            for dep in stage.deps:
                path = dep.def_path
                if isinstance(dep, ParamsDependency) or path.startswith("data/"):
                    continue  # data: checked by `dvc status` where the data is
                dep.save()
                assert dep.hash_info.value == recorded[path], (
                    f"dvc.lock: {name} dep {path} changed since the lock was written; "
                    "run `uv run dvc repro` and commit dvc.lock"
                )
