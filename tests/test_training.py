"""EM training on small real data: parameter groups, learning, NaN guard, resume, Accelerate."""

import copy
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
from factories import make_info, make_skill_episodes, skill_model_config, train_updater
from safetensors.torch import load_file

from pipeline.errors import UserError
from pipeline.model import SkillModel
from pipeline.segments import build_segments, save_segments
from pipeline.training.cuda_graphs import CudaGraphUpdater
from pipeline.training.data import WindowSampler
from pipeline.training.loop import Budget, Callbacks, Trainer, evaluate
from pipeline.training.losses import e_step_loss, m_step_loss, prior_marginal_nll
from pipeline.training.state import Progress, _load_optimizer
from pipeline.training.updaters import EMUpdater, in_precision

ROOT = Path(__file__).resolve().parents[1]
SPLIT = {"train": 0.8, "validation": 0.1, "test": 0.1}


@pytest.fixture(scope="module")
def segments():
    episodes = make_skill_episodes(n_episodes=30, length=200, seed=0)
    return build_segments(episodes, make_info("skills", physics_dim=0), 11, 1, SPLIT, seed=0)


def _model(segments, hidden=32, z_dim=4) -> SkillModel:
    torch.manual_seed(0)
    # The paper's GRU posterior, as these EM tests measured it (the conv posterior's learning:
    # tests/test_conv_encoder.py).
    model = SkillModel(skill_model_config(4, 2, z_dim=z_dim, hidden=hidden, encoder="gru"))
    s = segments.stats
    model.set_normalization(s.state_mean, s.state_std, s.action_mean, s.action_std)
    return model


def _snapshot(params):
    return [p.detach().clone() for p in params]


def _changed(before, params):
    return [not torch.equal(b, p) for b, p in zip(before, params, strict=True)]


def test_e_step_updates_only_the_posterior_and_m_step_only_the_rest(segments):
    model = _model(segments)
    updater = train_updater(model, lr_e=1e-2, lr_m=1e-2, e_prior="current")
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
    train_updater(model, method="vi", lr_m=1e-2).step(
        WindowSampler(segments, "train", torch.device("cpu"), 0).sample(8)
    )
    assert all(_changed(before, model.parameters()))


def test_gaussian_heads_multiply_hidden_layers_in_bfloat16_and_output_float32():
    torch.manual_seed(0)
    model = SkillModel(skill_model_config(4, 2, z_dim=8, hidden=64))
    s0 = torch.randn(16, 4)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        hidden = model.tawm.trunk(torch.cat([s0, torch.randn(16, 8)], -1))
        mean, std = model.prior(s0)
    assert hidden.dtype == torch.bfloat16
    assert mean.dtype == std.dtype == torch.float32
    float_mean, float_std = model.prior(s0)
    assert not torch.equal(mean, float_mean)  # the hidden layers did round
    torch.testing.assert_close(mean, float_mean, atol=0.05, rtol=0.05)
    torch.testing.assert_close(std, float_std, atol=0.05, rtol=0.05)


@pytest.mark.parametrize("loss", [e_step_loss, m_step_loss], ids=["e", "m"])
def test_bfloat16_losses_and_gradients_follow_float32(segments, loss):
    """train.dtype bfloat16: the same skills are drawn, the loss is float32 and not float32's
    bit for bit (the products ran in bfloat16), and loss and gradient stay close to float32's."""
    batch = WindowSampler(segments, "train", torch.device("cpu"), 0).sample(32)
    results = {}
    for dtype in ("float32", "bfloat16"):
        model = _model(segments, hidden=64, z_dim=8)
        torch.manual_seed(1)
        value, _ = in_precision(loss, dtype)(model, batch)
        value.backward()
        grad = torch.cat([p.grad.flatten() for p in model.parameters() if p.grad is not None])
        results[dtype] = value, grad
    (loss32, grad32), (loss16, grad16) = results["float32"], results["bfloat16"]
    assert loss16.dtype == torch.float32
    assert loss16.item() != loss32.item()
    assert abs(loss16.item() - loss32.item()) < 1e-3 * abs(loss32.item())  # measured: 1e-5
    assert torch.nn.functional.cosine_similarity(grad16, grad32, dim=0) > 0.999  # 0.99997


def _fit(segments, model, updater, steps, on_best=lambda c, p, m: None, eval_every=None):
    """Train; returns the trainer, its progress and the logged `(step, metrics)` validations."""
    train = WindowSampler(segments, "train", torch.device("cpu"), 0)
    val = WindowSampler(segments, "validation", torch.device("cpu"), 0)
    logged = []
    trainer = Trainer(
        model,
        updater,
        train,
        val,
        val.fixed_subset(500, 0),
        Budget(steps, None, 64, eval_every=eval_every or steps, checkpoint_every=10**9),
        Callbacks(lambda s, m: logged.append((s, m)), on_best, lambda p: None),
        progress_bar=False,
    )
    return trainer, trainer.fit(Progress()), logged


def _best_of(logged, criterion: str = "st_nll") -> tuple[int, float]:
    """Step and value of the lowest logged validation metric `criterion` (first on ties)."""
    step, metrics = min(logged, key=lambda sm: sm[1][f"val/{criterion}"])
    return step, metrics[f"val/{criterion}"]


@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
def test_validating_more_often_leaves_the_training_unchanged(segments, dtype):
    """Validation reads the model and draws nothing from the training's random streams, so a
    run that validates every 5 steps ends with the same weights as one that never does."""
    weights = []
    for eval_every in (5, 40):
        model = _model(segments)
        torch.manual_seed(1)  # the training's draws
        _fit(
            segments,
            model,
            train_updater(model, lr_e=3e-3, lr_m=3e-3, e_prior="current", dtype=dtype),
            40,
            eval_every=eval_every,
        )
        weights.append(model.state_dict())
    for name, value in weights[0].items():
        assert torch.equal(value, weights[1][name]), name


def test_em_learns_a_world_model_far_better_than_no_model(segments):
    model = _model(segments)
    _, progress, logged = _fit(
        segments,
        model,
        train_updater(model, lr_e=3e-3, lr_m=3e-3, e_prior="current"),
        steps=300,
        eval_every=50,
    )
    assert [s for s, _ in logged] == [50, 100, 150, 200, 250, 300]
    first, last = logged[0][1], logged[-1][1]
    # Untrained, the TAWM is no better than guessing; after 300 EM steps its s_T error given the
    # inferred skill must be well under the s_T = s_0 baseline (measured: about 5x under).
    assert last["val/st_error"] < 0.4 * last["val/st_error_no_model"]
    assert last["val/st_nll"] < first["val/st_nll"] and last["val/kl"] > 0
    assert progress.best_of("st_nll") == _best_of(logged)
    assert progress.best_of("st_nll_prior") == _best_of(logged, "st_nll_prior")
    # Skills drawn from the trained prior explain the real outcome far better than chance:
    assert last["val/st_nll_prior"] < first["val/st_nll_prior"] - 1.0


class _DegradesAfter:
    """EM steps; after `good` steps each step also adds noise to the TAWM's weights, so the
    validation s_T NLL gets worse and the best checkpoint must stay behind."""

    def __init__(self, updater: EMUpdater, good: int):
        self.updater, self.good, self.n = updater, good, 0
        self.generator = torch.Generator().manual_seed(0)

    def step(self, batch):
        metrics = self.updater.step(batch)
        self.n += 1
        if self.n > self.good:
            with torch.no_grad():
                for p in self.updater.model.tawm.parameters():
                    p.add_(0.05 * torch.randn(p.shape, generator=self.generator))
        return metrics


def test_best_checkpoint_is_the_lowest_validation_nll_not_the_last(segments):
    model = _model(segments)
    saved = []  # (best_step, model weights) at each save_best call

    def on_best(criterion, p, metrics):
        if criterion == "st_nll":
            step = p.best_of(criterion)[0]
            saved.append((step, {k: v.clone() for k, v in model.state_dict().items()}))

    updater = _DegradesAfter(
        train_updater(model, lr_e=3e-3, lr_m=3e-3, e_prior="current"), good=100
    )
    trainer, progress, logged = _fit(segments, model, updater, 200, on_best, eval_every=20)
    steps = [s for s, _ in logged]
    assert steps == list(range(20, 201, 20))
    best_step, best_nll = _best_of(logged)
    assert best_step < 200, "the scenario must make the last validation worse than the best"
    assert progress.best_of("st_nll") == (best_step, best_nll)
    # save_best is called exactly at each new running minimum, with the weights of that step.
    running, improved = float("inf"), []
    for s, m in logged:
        if m["val/st_nll"] < running:
            running = m["val/st_nll"]
            improved.append(s)
    assert [s for s, _ in saved] == improved and improved[-1] == best_step
    model.load_state_dict(saved[-1][1])
    assert evaluate(model, trainer.val, trainer.val_idx)["val/st_nll"] == best_nll


def test_nan_loss_stops_with_the_step_and_keeps_the_best_checkpoint(segments):
    model = _model(segments)
    saved = []
    on_best = lambda criterion, p, metrics: saved.append(criterion)  # noqa: E731
    trainer, progress, _ = _fit(
        segments, model, train_updater(model, lr_e=1e-3, lr_m=1e-3, e_prior="current"), 5, on_best
    )
    assert saved == ["st_nll", "st_nll_prior"]
    trainer.train.states[:] = float("nan")
    trainer.budget.max_steps = 10
    with pytest.raises(UserError, match="diverged at step 6"):
        trainer.fit(progress)
    assert len(saved) == 2  # nothing saved after the NaN


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
def test_cuda_graph_updater_refuses_a_model_off_cuda(segments):
    with pytest.raises(UserError, match="train.cuda_graph needs the model on CUDA"):
        CudaGraphUpdater(train_updater(_model(segments), lr_e=1e-3, lr_m=1e-3, e_prior="current"))


def test_a_capturable_optimizer_state_resumes_in_an_eager_optimizer_and_steps_alike():
    """A resume state written by a CUDA-graph run (capturable Adam) loads into eager Adam: the
    flag stays eager's, the step count moves to the CPU, and the next step is the same."""
    torch.manual_seed(0)
    weights = torch.nn.Parameter(torch.randn(5))
    first = torch.optim.Adam([weights], lr=0.1)
    for _ in range(3):
        first.zero_grad()
        (weights**2).sum().backward()
        first.step()
    saved = copy.deepcopy(first.state_dict())  # state_dict() shares the moment tensors
    saved["param_groups"][0]["capturable"] = True  # as a CUDA-graph run saves it
    resumed_weights = torch.nn.Parameter(weights.detach().clone())
    resumed = torch.optim.Adam([resumed_weights], lr=0.1)
    _load_optimizer(resumed, saved)
    assert resumed.param_groups[0]["capturable"] is False
    assert resumed.state[resumed_weights]["step"].device.type == "cpu"
    for optimizer, w in ((first, weights), (resumed, resumed_weights)):
        optimizer.zero_grad()
        (w**2).sum().backward()
        optimizer.step()
    assert torch.equal(weights, resumed_weights)


@pytest.mark.slow  # three training processes
def test_killed_run_resumes_and_ends_bit_identical_to_an_uninterrupted_one(tmp_path, segments):
    overrides = {"max_steps": 400, "eval_every": 50, "checkpoint_every": 50, "dtype": "auto"}
    straight = _project(tmp_path / "straight", segments, overrides)
    subprocess.run(_train_command(straight), check=True, env=_env(), capture_output=True)

    killed = _project(tmp_path / "killed", segments, overrides)
    proc = subprocess.Popen(_train_command(killed), env=_env(), stderr=subprocess.DEVNULL)
    scratch = killed / "data/scratch/train"
    deadline = time.monotonic() + 120
    state = None
    while time.monotonic() < deadline:
        states = list(scratch.glob("skills-*/resume/state.json"))
        state = states[0] if states else None
        if state is not None and json.loads(state.read_text())["progress"]["step"] >= 100:
            break
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = json.loads(state.read_text())["progress"]["step"]
    assert 100 <= killed_at < 400, "the run was not killed mid-way"

    result = subprocess.run(_train_command(killed), env=_env(), capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert f"resuming from step {killed_at}" in result.stderr
    (resumed,) = (killed / "data/scratch/train").glob("skills-*/resume/model.safetensors")
    (uninterrupted,) = (straight / "data/scratch/train").glob("skills-*/resume/model.safetensors")
    for a, b in [
        (load_file(uninterrupted), load_file(resumed)),
        *[  # the published best models too
            (load_file(straight / p), load_file(killed / p))
            for p in ["data/models/skills/model.safetensors"]
        ],
    ]:
        for name in a:
            assert torch.equal(a[name], b[name]), name
    metrics = json.loads((killed / "data/reports/train/metrics.json").read_text())
    assert metrics["step"] == 400
    # the precision it ran in, as resolved (`train.dtype: auto` is this CPU's choice)
    from pipeline.training.updaters import resolve_dtype

    assert metrics["dtype"] == resolve_dtype("auto", torch.device("cpu"))


def _busy_process() -> subprocess.Popen:
    """A process that keeps one core busy until it is killed."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


def _kill_after_state(command: list[str], scratch: Path, step: int) -> int:
    """Run `command`, SIGKILL it once its resume state reaches `step`; the state's step."""
    proc = subprocess.Popen(command, env=_env(), stderr=subprocess.DEVNULL)
    deadline, state = time.monotonic() + 240, None
    while time.monotonic() < deadline and proc.poll() is None:
        states = list(scratch.glob("skills-*/resume/state.json"))
        state = states[0] if states else None
        if state is not None and json.loads(state.read_text())["progress"]["step"] >= step:
            break
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert state is not None, "the run wrote no resume state"
    return json.loads(state.read_text())["progress"]["step"]


@pytest.mark.slow  # three training processes at the main job's sizes, one beside a busy core
def test_a_run_killed_and_resumed_under_load_on_other_thread_counts_is_bit_identical(tmp_path):
    """The main job's sizes (batch 100 x window 40, hidden 128, z 16, float32): a run on one
    thread, against one killed mid-way on two threads and resumed with `threads: auto` beside a
    busy process (which takes one thread, then two once the process ends). Same bits."""
    episodes = make_skill_episodes(n_episodes=24, length=200, seed=1)
    segments = build_segments(episodes, make_info("skills", physics_dim=0), 40, 1, SPLIT, seed=0)
    sizes = {"z_dim": 16, "hidden": 128, "batch_size": 100, "dtype": "float32",
             "max_steps": 40, "eval_every": 10, "checkpoint_every": 10}  # fmt: skip
    straight = _project(tmp_path / "straight", segments, sizes | {"threads": 1})
    subprocess.run(_train_command(straight), check=True, env=_env(), capture_output=True)

    killed = _project(tmp_path / "killed", segments, sizes | {"threads": 2})
    busy = _busy_process()
    try:
        at = _kill_after_state(_train_command(killed), killed / "data/scratch/train", 10)
        assert 10 <= at < 40, "the run was not killed mid-way"
        resume = _train_command(killed, "-S", "train.threads=auto")
        result = subprocess.run(resume, env=_env(), capture_output=True, text=True)
    finally:
        busy.kill()
        busy.wait()
    assert result.returncode == 0, result.stderr
    assert f"resuming from step {at}" in result.stderr
    for path in ("data/models/skills/model.safetensors", "data/reports/train/metrics.json"):
        assert (straight / path).read_bytes() == (killed / path).read_bytes(), path


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


def test_prior_marginal_nll_is_the_monte_carlo_mixture_likelihood(segments):
    torch.manual_seed(3)
    model = _model(segments)
    batch = WindowSampler(segments, "validation", torch.device("cpu"), 0).sample(7)
    s0, s_t = batch.states[:, 0], batch.states[:, -1]
    eps = torch.randn(5, model.config.z_dim)
    got = prior_marginal_nll(model, s0, s_t, eps)
    prior = model.prior_dist(s0)
    # The same mixture, one window and one skill at a time:
    for b in range(7):
        densities = [
            model.tawm_dist(s0[b], prior.mean[b] + prior.stddev[b] * e).log_prob(s_t[b]).exp()
            for e in eps
        ]
        assert torch.allclose(got[b], -torch.stack(densities).mean().log(), rtol=1e-4)
    # One draw repeated K times is that draw's NLL: the estimate does not grow with K.
    one = prior_marginal_nll(model, s0, s_t, eps[:1])
    assert torch.allclose(prior_marginal_nll(model, s0, s_t, eps[:1].repeat(4, 1)), one)


def test_the_ema_prior_follows_the_prior_at_its_rate_and_holds_the_e_step(segments):
    """train.e_prior ema: after each step the average moves `rate` of the way to the prior;
    the E-step's gradient differs from the current prior's (it holds q to the average)."""

    batch = WindowSampler(segments, "train", torch.device("cpu"), 0).sample(32)
    model = _model(segments, hidden=32, z_dim=4)
    updater = train_updater(model, lr_e=1e-3, lr_m=1e-3, prior_ema=0.25)
    before = [p.clone() for p in updater.prior_ema.net.parameters()]
    updater.step(batch)
    averaged, current = updater.prior_ema.net.parameters(), model.prior.parameters()
    for old, avg, cur in zip(before, averaged, current, strict=True):
        torch.testing.assert_close(avg, old + 0.25 * (cur - old))
    assert not any(p.requires_grad for p in updater.prior_ema.parameters())
    assert not any(torch.equal(a, c) for a, c in zip(before, model.prior.parameters(), strict=True))


def test_divergence_check_flags_a_run_above_its_best_for_evals_in_a_row(caplog):
    """A collapsed run's validation jumps by nats and stays up; one excursion that comes back
    within `evals` validations is not a divergence."""
    from pipeline.training.loop import DivergenceCheck

    check = DivergenceCheck("st_nll_prior", margin=1.0, evals=3)
    progress = Progress(best={"st_nll_prior": {"step": 500, "value": 3.3}})
    flagged = []
    for step, value in [(750, 9.0), (1000, 5.0), (1250, 3.5), (1500, 7.0), (1750, 4.4),
                        (2000, 4.5), (2250, 4.0)]:  # fmt: skip
        progress.step = step
        flagged.append(check.update(progress, value))
    assert flagged == [False, False, False, False, False, True, False]
    assert progress.diverged_step == 2000 and progress.evals_above_best == 0
    assert not DivergenceCheck("st_nll_prior", margin=None, evals=3).update(Progress(), 1e9)
