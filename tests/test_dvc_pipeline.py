"""The real `dvc repro` of the pipeline, in a temporary copy of the repository, on tiny params."""

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


@pytest.mark.slow
def test_dvc_repro_runs_then_skips_then_reruns_only_what_changed(tmp_path):
    repo = tmp_path / "repo"
    _copy_repository(repo)
    _set_params(repo, TINY)
    for git in (["init", "-q"], ["add", "-A"], ["commit", "-qm", "copy"]):
        subprocess.run(
            ["git", "-c", "user.name=t", "-c", "user.email=t@t", *git], cwd=repo, check=True
        )

    first = _dvc(repo, "repro")
    assert "Running stage 'ingest'" in first and "Running stage 'segment'" in first
    assert (repo / "data/segments/pointmaze-medium/segments.json").exists()
    assert "Running stage 'deploy'" in first and "random_goal  success" in first

    second = _dvc(repo, "repro")
    assert "Running stage" not in second

    _set_params(repo, {"segment": {"window": 10}})
    third = _dvc(repo, "repro")
    assert "Running stage 'segment'" in third and "Running stage 'ingest'" not in third
    assert "Running stage 'train'" in third  # new windows, new model

    metrics = _dvc(repo, "metrics", "show")
    assert "train_windows" in metrics
