"""The train stage's files: scratch resume state, published outputs, old model kept, bad state."""

import json
import shutil
from pathlib import Path

import pytest
import torch
from factories import make_info, make_skill_episodes
from safetensors.torch import load_file

from pipeline.config import Params
from pipeline.errors import UserError
from pipeline.paths import Paths
from pipeline.segments import build_segments, save_segments
from stages import train

SPLIT = {"train": 0.8, "validation": 0.1, "test": 0.1}
SMALL = {"z_dim": 4, "hidden": 16, "batch_size": 16, "val_windows": 50, "device": "cpu"}


@pytest.fixture(scope="module")
def segments():
    episodes = make_skill_episodes(n_episodes=12, length=120, seed=0)
    return build_segments(episodes, make_info("skills", physics_dim=0), 11, 1, SPLIT, seed=0)


@pytest.fixture
def paths(tmp_path, segments) -> Paths:
    save_segments(segments, tmp_path / "data" / "segments" / "skills")
    return Paths(tmp_path / "data")


def _params(**train) -> Params:
    steps = {"max_steps": 20, "eval_every": 10, "checkpoint_every": 10}
    return Params.model_validate({"ingest": {"name": "skills"}, "train": SMALL | steps | train})


def _run(paths: Paths, **train_params):
    with torch.random.fork_rng():
        return train.run(_params(**train_params), paths, progress_bar=False)


def _weights(paths: Paths) -> dict[str, torch.Tensor]:
    return load_file(paths.model("skills") / "model.safetensors")


def _scratch(paths: Paths) -> list[Path]:
    return sorted((paths.root / "scratch" / "train").iterdir())


def test_outputs_hold_the_model_the_logs_and_the_headline_and_no_resume_state(paths):
    _run(paths)
    model_dir = paths.model("skills")
    assert sorted(p.name for p in model_dir.iterdir()) == ["by", "config.json", "model.safetensors"]
    assert sorted(p.name for p in (model_dir / "by").iterdir()) == ["st_nll", "st_nll_prior"]
    assert json.loads((paths.live("train") / "metrics.json").read_text())["step"] == 20
    headline = json.loads(paths.metrics("train").read_text())
    assert headline["steps"] == 20 and headline["best_step"] in (10, 20)
    assert paths.metrics("train") == paths.root.parent / "metrics" / "train.json"
    (scratch,) = _scratch(paths)
    assert (scratch / "resume" / "state.json").exists()


def test_each_criterion_keeps_its_best_and_select_picks_the_published_one(paths):
    _run(paths, max_steps=40, select="st_nll_prior")
    model_dir = paths.model("skills")
    by = {c: model_dir / "by" / c for c in ("st_nll", "st_nll_prior")}
    meta = {c: json.loads((d / "config.json").read_text()) for c, d in by.items()}
    for criterion, m in meta.items():
        assert m["selected_by"] == criterion and m["step"] in (10, 20, 30, 40)
        assert set(m["val"]) >= {"st_nll", "st_nll_prior", "st_error"}
    published = json.loads((model_dir / "config.json").read_text())
    assert published["selected_by"] == "st_nll_prior"
    assert published["step"] == meta["st_nll_prior"]["step"]
    top, chosen = _weights(paths), load_file(by["st_nll_prior"] / "model.safetensors")
    assert all(torch.equal(top[k], chosen[k]) for k in top)
    headline = json.loads(paths.metrics("train").read_text())
    assert headline["best_step"] == meta["st_nll_prior"]["step"]
    for c in ("st_nll", "st_nll_prior"):  # headlines are rounded to 4 decimals
        assert headline[f"best_val_{c}"] == pytest.approx(meta[c]["val"][c], abs=1e-4)


def test_a_second_run_of_the_same_params_restores_the_outputs_without_training(paths):
    _run(paths)
    first = _weights(paths)
    for out in (paths.model("skills"), paths.live("train")):  # what DVC deletes before a run
        for f in sorted(out.rglob("*"), reverse=True):
            f.unlink() if f.is_file() else f.rmdir()
        out.rmdir()
    headline = paths.metrics("train").read_bytes()
    rate = json.loads(paths.timings("train").read_text())["steps_per_s"]
    progress = _run(paths)
    assert progress.step == 20
    assert paths.metrics("train").read_bytes() == headline  # no clock in it
    again = json.loads(paths.timings("train").read_text())["steps_per_s"]
    assert again > 0  # the whole run's rate, not this call's (no steps)
    assert again == pytest.approx(rate, rel=0.5)
    for name, value in first.items():
        assert torch.equal(value, _weights(paths)[name])


def test_lowering_max_steps_below_the_resume_state_starts_over(paths, caplog):
    _run(paths, max_steps=30)
    with caplog.at_level("INFO"):
        progress = _run(paths, max_steps=20)
    assert "starting over" in caplog.text
    assert progress.step == 20
    assert json.loads(paths.metrics("train").read_text())["steps"] == 20


def test_a_fresh_run_that_diverges_leaves_the_previous_model_in_place(paths):
    _run(paths)
    before = _weights(paths)
    with pytest.raises(UserError, match="diverged"):
        _run(paths, lr_e=1e30, lr_m=1e30, seed=1)
    after = _weights(paths)
    for name, value in before.items():
        assert torch.equal(value, after[name]), name


@pytest.mark.parametrize(
    "damage",
    [
        lambda d: (d / "state.json").write_text("{not json"),
        lambda d: (d / "model.safetensors").write_bytes(b"\0" * 64),
        lambda d: (d / "optim.pt").write_bytes(b"garbage"),
    ],
    ids=["state.json", "model.safetensors", "optim.pt"],
)
def test_a_corrupt_resume_state_is_a_one_line_error_naming_the_folder(paths, damage):
    _run(paths, max_steps=10)
    (scratch,) = _scratch(paths)
    damage(scratch / "resume")
    with pytest.raises(UserError) as err:
        _run(paths, max_steps=20)
    message = str(err.value)
    assert str(scratch / "resume") in message and "delete" in message
    assert "\n" not in message


@pytest.mark.slow
def test_a_trainer_started_by_dvc_stops_when_dvc_is_killed(paths, tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    import yaml

    root = Path(__file__).resolve().parents[1]
    params = tmp_path / "params.yaml"
    steps = {"max_steps": 100000, "eval_every": 1000, "checkpoint_every": 1000}
    params.write_text(yaml.safe_dump({"ingest": {"name": "skills"}, "train": SMALL | steps}))
    train_cmd = [sys.executable, str(root / "cli.py"), "train", "-p", str(params)]
    train_cmd += ["--data", str(paths.root)]
    fake_dvc = (  # what DVC does: run the stage's command as a child, with DVC_STAGE set
        "import subprocess, sys, time\n"
        f"child = subprocess.Popen({train_cmd!r})\n"
        "print(child.pid, flush=True)\n"
        "child.wait()\n"
    )
    env = {**os.environ, "DVC_STAGE": "train", "OMP_NUM_THREADS": "1", "PYTHONPATH": str(root)}
    dvc = subprocess.Popen([sys.executable, "-c", fake_dvc], stdout=subprocess.PIPE, env=env)
    trainer = int(dvc.stdout.readline())

    def running() -> bool:
        try:
            os.kill(trainer, 0)
            return Path(f"/proc/{trainer}/stat").read_text().split()[2] != "Z"  # Z: unreaped
        except (ProcessLookupError, FileNotFoundError):
            return False

    # Kill DVC once the trainer is training (its dvclive folder exists), however long its
    # imports take on a busy machine.
    deadline = time.monotonic() + 120
    while running() and not any(paths.root.glob("scratch/train/*/live")):
        if time.monotonic() > deadline:
            dvc.kill()
            os.kill(trainer, signal.SIGKILL)
            pytest.fail("the trainer did not start training in 120 s")
        time.sleep(0.1)
    assert running(), "the trainer ended before DVC was killed"
    dvc.kill()
    dvc.wait()
    deadline = time.monotonic() + 30
    while running() and time.monotonic() < deadline:
        time.sleep(0.1)
    if running():
        os.kill(trainer, signal.SIGKILL)
        pytest.fail("the trainer kept running after DVC was killed")


def test_the_headline_says_whether_the_run_diverged(paths):
    progress = _run(paths, max_steps=40, eval_every=10)
    headline = json.loads(paths.metrics("train").read_text())
    assert progress.diverged_step is None
    assert headline["diverged"] is False and headline["diverged_step"] is None


def test_an_ema_prior_run_resumes_bit_identical(paths):
    """train.e_prior ema: the E-step's averaged prior is part of the resume state."""
    _run(paths, max_steps=20, e_prior="ema", prior_ema=0.1)
    straight = _weights(paths)
    for folder in _scratch(paths):
        shutil.rmtree(folder)
    _run(paths, max_steps=10, e_prior="ema", prior_ema=0.1)
    _run(paths, max_steps=20, e_prior="ema", prior_ema=0.1)  # resumes at step 10
    resumed = _weights(paths)
    for name, value in straight.items():
        assert torch.equal(value, resumed[name]), name
