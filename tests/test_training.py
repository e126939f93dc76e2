"""EM training on small real data: parameter groups, learning, NaN guard, resume, Accelerate."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from factories import make_info, make_skill_episodes
from safetensors.torch import load_file

from pipeline.errors import UserError
from pipeline.model import SkillModel, SkillModelConfig
from pipeline.segments import build_segments, save_segments
from pipeline.training.data import WindowSampler
from pipeline.training.loop import Budget, Callbacks, Trainer, evaluate
from pipeline.training.state import Progress
from pipeline.training.updaters import EMUpdater, VIUpdater

ROOT = Path(__file__).resolve().parents[1]
SPLIT = {"train": 0.8, "validation": 0.1, "test": 0.1}


@pytest.fixture(scope="module")
def segments():
    episodes = make_skill_episodes(n_episodes=30, length=200, seed=0)
    return build_segments(episodes, make_info("skills", physics_dim=0), 11, 1, SPLIT, seed=0)


def _model(segments, hidden=32, z_dim=4) -> SkillModel:
    torch.manual_seed(0)
    model = SkillModel(SkillModelConfig(4, 2, z_dim=z_dim, hidden=hidden))
    s = segments.stats
    model.set_normalization(s.state_mean, s.state_std, s.action_mean, s.action_std)
    return model


def _snapshot(params):
    return [p.detach().clone() for p in params]


def _changed(before, params):
    return [not torch.equal(b, p) for b, p in zip(before, params, strict=True)]


def test_e_step_updates_only_the_posterior_and_m_step_only_the_rest(segments):
    model = _model(segments)
    updater = EMUpdater(model, lr_e=1e-2, lr_m=1e-2)
    batch = WindowSampler(segments, "train", torch.device("cpu"), 0).sample(16)
    posterior, generative = list(model.posterior.parameters()), model.generative()

    before_q, before_g = _snapshot(posterior), _snapshot(generative)
    updater.e_step(batch)
    assert all(_changed(before_q, posterior))
    assert not any(_changed(before_g, generative))

    before_q, before_g = _snapshot(posterior), _snapshot(generative)
    updater.m_step(batch)
    assert not any(_changed(before_q, posterior))
    assert all(_changed(before_g, generative))


def test_vi_step_updates_everything(segments):
    model = _model(segments)
    before = _snapshot(model.parameters())
    VIUpdater(model, lr=1e-2).step(
        WindowSampler(segments, "train", torch.device("cpu"), 0).sample(8)
    )
    assert all(_changed(before, model.parameters()))


def _fit(segments, model, updater, steps, on_best=lambda p: None):
    train = WindowSampler(segments, "train", torch.device("cpu"), 0)
    val = WindowSampler(segments, "validation", torch.device("cpu"), 0)
    logged = []
    trainer = Trainer(
        model,
        updater,
        train,
        val,
        val.fixed_subset(500, 0),
        Budget(steps, None, 64, eval_every=steps, checkpoint_every=10**9),
        Callbacks(lambda s, m: logged.append(m), on_best, lambda p: None),
        progress_bar=False,
    )
    return trainer, trainer.fit(Progress()), logged


def test_em_learns_a_world_model_far_better_than_no_model(segments):
    model = _model(segments)
    _, progress, logged = _fit(segments, model, EMUpdater(model, 3e-3, 3e-3), steps=300)
    val = logged[-1]
    # Untrained, the TAWM is no better than guessing; after 300 EM steps its s_T error given the
    # inferred skill must be well under the s_T = s_0 baseline (measured: about 5x under).
    assert val["val/st_error"] < 0.4 * val["val/st_error_no_model"]
    assert progress.best_step == 300


def test_nan_loss_stops_with_the_step_and_keeps_the_best_checkpoint(segments):
    model = _model(segments)
    saved = []
    trainer, progress, _ = _fit(segments, model, EMUpdater(model, 1e-3, 1e-3), 5, saved.append)
    assert len(saved) == 1
    trainer.train.states[:] = float("nan")
    trainer.budget.max_steps = 10
    with pytest.raises(UserError, match="diverged at step 6"):
        trainer.fit(progress)
    assert len(saved) == 1  # nothing saved after the NaN


def _project(tmp_path: Path, segments, train_overrides: dict) -> Path:
    """A params file + data root with the synthetic segments under the dataset name 'skills'."""
    save_segments(segments, tmp_path / "data" / "segments" / "skills")
    params = {
        "ingest": {"name": "skills"},
        "train": {
            "z_dim": 4,
            "hidden": 32,
            "batch_size": 32,
            "val_windows": 200,
            **train_overrides,
        },
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    return tmp_path


def _train_command(project: Path, *extra: str) -> list[str]:
    return [
        sys.executable,
        str(ROOT / "cli.py"),
        "train",
        "-p",
        str(project / "params.yaml"),
        "--data",
        str(project / "data"),
        *extra,
    ]


def _env():
    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}


@pytest.mark.slow
def test_killed_run_resumes_and_ends_bit_identical_to_an_uninterrupted_one(tmp_path, segments):
    overrides = {"max_steps": 400, "eval_every": 50, "checkpoint_every": 50}
    straight = _project(tmp_path / "straight", segments, overrides)
    subprocess.run(_train_command(straight), check=True, env=_env(), capture_output=True)

    killed = _project(tmp_path / "killed", segments, overrides)
    proc = subprocess.Popen(_train_command(killed), env=_env(), stderr=subprocess.DEVNULL)
    state = killed / "data/models/skills/resume/state.json"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if state.exists() and json.loads(state.read_text())["progress"]["step"] >= 100:
            break
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = json.loads(state.read_text())["progress"]["step"]
    assert 100 <= killed_at < 400, "the run was not killed mid-way"

    result = subprocess.run(_train_command(killed), env=_env(), capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert f"resuming from step {killed_at}" in result.stderr
    a = load_file(straight / "data/models/skills/resume/model.safetensors")
    b = load_file(killed / "data/models/skills/resume/model.safetensors")
    for name in a:
        assert torch.equal(a[name], b[name]), name
    metrics = json.loads((killed / "data/reports/train/metrics.json").read_text())
    assert metrics["step"] == 400


@pytest.mark.slow
def test_two_process_accelerate_run_trains_and_keeps_processes_in_sync(tmp_path, segments):
    project = _project(tmp_path, segments, {"max_steps": 40, "eval_every": 20, "device": "cpu"})
    # Accelerate's --cpu flag launches one process; --multi_gpu runs torchrun, and with
    # train.device=cpu the processes join a gloo CPU process group (Accelerate's MULTI_CPU).
    launch = [
        sys.executable,
        "-m",
        "accelerate.commands.launch",
        "--multi_gpu",
        "--num_processes",
        "2",
        "--num_machines",
        "1",
        "--mixed_precision",
        "no",
        "--dynamo_backend",
        "no",
    ]
    command = _train_command(project)
    result = subprocess.run([*launch, *command[1:]], env=_env(), capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-3000:]
    metrics = json.loads((project / "data/reports/train/metrics.json").read_text())
    assert metrics["processes"] == 2 and metrics["step"] == 40
    assert (project / "data/models/skills/model.safetensors").exists()
    assert "processes in sync" in result.stderr


def test_validation_metrics_are_finite_and_deterministic(segments):
    model = _model(segments)
    val = WindowSampler(segments, "validation", torch.device("cpu"), 0)
    idx = val.fixed_subset(100, 0)
    a, b = evaluate(model, val, idx), evaluate(model, val, idx)
    assert a == b and all(np.isfinite(v) for v in a.values())
