"""The real CLI through Typer's runner, on a tiny real dataset."""

import json
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from cli import app

runner = CliRunner()
TINY = {
    "ingest": {"name": "tiny", "episodes": 6, "episode_steps": 150, "seed": 1},
    "segment": {"window": 20},
}


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """A params file and a data root with an ingested and segmented tiny dataset."""
    root = tmp_path_factory.mktemp("cli")
    (root / "params.yaml").write_text(yaml.safe_dump(TINY))
    common = ["--params", str(root / "params.yaml"), "--data", str(root / "data")]
    for command in ("ingest", "segment"):
        result = runner.invoke(app, [command, *common])
        assert result.exit_code == 0, result.output
    return root, common


def _one_line_error(result):
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert "Traceback" not in result.output
    return lines[0]


def test_help_lists_every_stage():
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for command in ("ingest", "segment", "inspect", "params"):
        assert command in result.output


def test_ingest_and_segment_write_their_artifacts(workdir):
    root, _ = workdir
    assert (root / "data/demos/tiny.mcap").stat().st_size > 0
    assert (root / "data/segments/tiny/segments.safetensors").exists()
    report = json.loads((root / "data/reports/segment/report.json").read_text())
    assert report["train_episodes"] + report["validation_episodes"] + report["test_episodes"] == 6
    ingest = json.loads((root / "data/reports/ingest/report.json").read_text())
    assert ingest["steps"] == 6 * 150


def test_inspect_prints_a_readable_summary(workdir):
    root, _ = workdir
    result = runner.invoke(app, ["inspect", str(root / "data/demos/tiny.mcap")])
    assert result.exit_code == 0, result.output
    for text in ("PointMaze_Medium-v3", "900", "vx"):
        assert text in result.output


def test_set_overrides_params_for_one_run(workdir):
    root, common = workdir
    result = runner.invoke(
        app, ["params", "--params", str(root / "params.yaml"), "-S", "segment.window=7"]
    )
    assert result.exit_code == 0
    assert yaml.safe_load(result.output)["segment"]["window"] == 7


def test_inspect_missing_file_is_a_one_line_error(tmp_path):
    line = _one_line_error(runner.invoke(app, ["inspect", str(tmp_path / "nope.mcap")]))
    assert "nope.mcap" in line


def test_inspect_non_mcap_file_is_a_one_line_error(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_text("not an mcap file\n")
    assert "bad.mcap" in _one_line_error(runner.invoke(app, ["inspect", str(bad)]))


def test_unknown_param_key_is_a_one_line_error(workdir):
    _, common = workdir
    line = _one_line_error(runner.invoke(app, ["segment", *common, "-S", "segment.windw=3"]))
    assert "segment.windw" in line


def test_segment_without_ingest_says_what_to_run(tmp_path):
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(TINY))
    args = ["segment", "--params", str(tmp_path / "params.yaml"), "--data", str(tmp_path / "d")]
    line = _one_line_error(runner.invoke(app, args))
    assert "oposm ingest" in line


def test_ingest_killed_midway_leaves_no_dataset(tmp_path):
    """SIGKILL during generation: the destination never exists half-written."""
    from factories import kill_an_ingest_while_it_writes

    demos = kill_an_ingest_while_it_writes(tmp_path, "big")
    assert not (demos / "big.mcap").exists()


def test_an_os_error_is_one_line_naming_the_path(tmp_path):
    """A data root that cannot be written (here: a file where a folder must be; read-only and full
    disks raise the same `OSError`) is one line naming the path, in every stage."""
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(TINY))
    (tmp_path / "data").write_text("a file, not a folder\n")
    args = ["ingest", "--params", str(tmp_path / "params.yaml"), "--data", str(tmp_path / "data")]
    line = _one_line_error(runner.invoke(app, args))
    assert str(tmp_path / "data") in line and "is a file, and a folder is needed" in line


def test_os_errors_name_the_file_asked_for_not_the_hidden_temporary():
    from cli import _os_error_message

    exc = OSError(28, "No space left on device", "data/demos/.tmp-arm.mcap.yq79p91g")
    assert _os_error_message(exc) == "data/demos/arm.mcap: No space left on device"
    exc = OSError(30, "Read-only file system", "data/models/.old-tiny.1234")
    assert _os_error_message(exc) == "data/models/tiny: Read-only file system"


def test_an_error_under_an_open_progress_bar_starts_on_its_own_line(workdir, monkeypatch):
    from tqdm import tqdm

    from pipeline.errors import UserError
    from stages import segment

    def fails_midway(params, paths):
        bar = tqdm(total=10, desc="segment")
        bar.update(3)
        raise UserError("something went wrong")

    monkeypatch.setattr(segment, "run", fails_midway)
    _, common = workdir
    result = runner.invoke(app, ["segment", *common])
    assert result.exit_code == 1
    lines = result.stderr.split("\n")  # a bar redraws with \r: split on newlines only
    assert "error: something went wrong" in lines, lines


def test_third_party_info_logs_stay_out_of_the_output(tmp_path):
    """`datasets` logs "JAX version ... available" at INFO on every LeRobot import path."""
    import subprocess
    import sys

    code = (
        "import logging, cli; cli._setup_logging(); "
        "logging.getLogger('datasets').info('JAX version 0.0 available.'); "
        "logging.getLogger('pipeline.sources').info('ours')"
    )
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=True
    )
    assert "ours" in out.stderr and "JAX" not in out.stderr


def test_view_without_a_display_suggests_the_web_viewer(tmp_path, monkeypatch):
    (tmp_path / "x.rrd").write_bytes(b"")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    assert "--web" in _one_line_error(runner.invoke(app, ["view", str(tmp_path)]))


def test_train_says_what_it_does_before_its_first_output(workdir, monkeypatch, caplog):
    """Importing PyTorch, Accelerate and dvclive takes seconds before the first progress bar."""
    import logging

    from stages import train

    seen: list[str] = []
    monkeypatch.setattr(train, "run", lambda params, paths: seen.extend(caplog.messages))
    _, common = workdir
    with caplog.at_level(logging.INFO, logger="cli"):
        assert runner.invoke(app, ["train", *common]).exit_code == 0
    assert any(m.startswith("train: loading PyTorch") for m in seen), seen


def test_ad_hoc_runs_write_under_a_run_folder_and_leave_the_pipelines_outputs(
    tmp_path, monkeypatch, caplog
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(TINY))
    assert runner.invoke(app, ["ingest"]).exit_code == 0  # the pipeline's own command
    pipeline_demos = tmp_path / "data/demos/tiny.mcap"
    before = pipeline_demos.read_bytes()
    assert json.loads((tmp_path / "metrics/ingest.json").read_text())["episodes"] == 6

    quick = ["-S", "ingest.episodes=4"]
    result = runner.invoke(app, ["ingest", *quick])
    assert result.exit_code == 0, result.output
    (run,) = (tmp_path / "data/runs").iterdir()
    assert f"data/runs/{run.name}" in caplog.text  # it says where
    assert pipeline_demos.read_bytes() == before
    assert json.loads((tmp_path / "metrics/ingest.json").read_text())["episodes"] == 6
    assert json.loads((run / "metrics/ingest.json").read_text())["episodes"] == 4

    # The same overrides in the next stage land in the same run and read its own demos.
    assert runner.invoke(app, ["segment", *quick]).exit_code == 0
    split = json.loads((run / "reports/segment/report.json").read_text())
    assert split["train_episodes"] + split["validation_episodes"] + split["test_episodes"] == 4
    assert not (tmp_path / "data/segments").exists()

    # A named run without demos of its own reads the pipeline's.
    assert runner.invoke(app, ["segment", "--run", "mine"]).exit_code == 0
    split = json.loads((tmp_path / "data/runs/mine/reports/segment/report.json").read_text())
    assert split["train_episodes"] + split["validation_episodes"] + split["test_episodes"] == 6

    bad = runner.invoke(app, ["segment", "--run", "../escape"])
    assert "--run" in _one_line_error(bad)


def _wrong_physics_source(params, progress, cache_root):
    """Real PointMaze episodes whose physics states carry one number too many (6, not 5)."""
    import dataclasses

    import numpy as np

    from pipeline.envs.maze.expert import ExpertConfig
    from pipeline.envs.maze.generate import dataset_info, generate_episodes

    cfg, expert = params.ingest, ExpertConfig()
    info = dataset_info(cfg.env_id, cfg.name, 0, expert, cfg.episodes, cfg.episode_steps)
    episodes = generate_episodes(cfg.env_id, cfg.episodes, cfg.episode_steps, 0, expert)
    widened = (
        dataclasses.replace(ep, physics=np.column_stack([ep.physics, np.zeros(len(ep))]))
        for ep in episodes
    )
    return dataclasses.replace(info, physics_dim=6), widened


def test_ingest_refuses_physics_states_of_the_wrong_size(tmp_path, monkeypatch):
    from stages import ingest

    monkeypatch.setattr(ingest, "_source", _wrong_physics_source)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(TINY))
    args = ["ingest", "--params", str(tmp_path / "params.yaml"), "--data", str(tmp_path / "d")]
    line = _one_line_error(runner.invoke(app, args))
    assert str(tmp_path / "d/demos/tiny.mcap") in line
    assert "have 6 numbers" in line and "PointMaze_Medium-v3 has 5" in line
    assert not list((tmp_path / "d/demos").glob("*"))


def test_segment_refuses_a_dataset_whose_physics_states_have_the_wrong_size(tmp_path):
    """Such a file (written before the ingest check, or by another tool) used to pass segment and
    deploy and fail only in validate."""
    from factories import make_episodes, make_info

    from pipeline.recording import write_dataset

    demos = tmp_path / "d/demos"
    demos.mkdir(parents=True)
    info = make_info("tiny", physics_dim=6)
    write_dataset(demos / "tiny.mcap", info, make_episodes([60] * 6, physics_dim=6))
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(TINY))
    args = ["segment", "--params", str(tmp_path / "params.yaml"), "--data", str(tmp_path / "d")]
    line = _one_line_error(runner.invoke(app, args))
    assert str(demos / "tiny.mcap") in line and "oposm ingest" in line
    assert "have 6 numbers" in line and "PointMaze_Medium-v3 has 5" in line
    assert not (tmp_path / "d/segments").exists()


def test_segment_exclude_fallen_on_a_point_maze_is_a_one_line_error(tmp_path):
    from factories import make_episodes, make_info

    from pipeline.recording import write_dataset

    demos = tmp_path / "d/demos"
    demos.mkdir(parents=True)
    write_dataset(demos / "tiny.mcap", make_info("tiny"), make_episodes([60] * 6))
    params = {**TINY, "segment": {**TINY.get("segment", {}), "exclude_fallen": True}}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    args = ["segment", "--params", str(tmp_path / "params.yaml"), "--data", str(tmp_path / "d")]
    line = _one_line_error(runner.invoke(app, args))
    assert "segment.exclude_fallen" in line and "cannot fall" in line
    assert not (tmp_path / "d/segments").exists()


@pytest.mark.parametrize(
    ("stage", "lower"),
    [
        ("train", "train.batch_size"),
        ("dynamics", "dynamics.batch_size"),
        ("validate", "validate.particles"),
        ("deploy", "deploy.num_envs"),
    ],
)
def test_cuda_out_of_memory_is_one_line_saying_which_params_to_lower(
    workdir, monkeypatch, stage, lower
):
    import importlib

    import torch

    def runs_out(params, paths):
        raise torch.cuda.OutOfMemoryError(
            "CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has a total capacity of "
            "79.19 GiB of which 1.06 GiB is free.\nIncluding non-PyTorch memory, ..."
        )

    monkeypatch.setattr(importlib.import_module(f"stages.{stage}"), "run", runs_out)
    _, common = workdir
    line = _one_line_error(runner.invoke(app, [stage, *common]))
    assert f"`oposm {stage}`" in line and "(tried to allocate 2.00 GiB)" in line
    assert lower in line and f"-S {stage}.device=cpu" in line


def test_the_params_named_for_out_of_memory_are_real_keys():
    from cli import _MEMORY_PARAMS
    from pipeline.config import load_params

    defaults = load_params(Path(__file__).resolve().parents[1] / "params.yaml").model_dump()
    for lower, device in _MEMORY_PARAMS.values():
        for key in [*lower, device]:
            if key.startswith("--"):
                continue
            node = defaults
            for part in key.split("."):
                assert isinstance(node, dict) and part in node, f"{key} is not a param"
                node = node[part]


def test_the_cli_starts_without_importing_torch():
    import subprocess
    import sys

    code = "import sys, cli; print('torch' in sys.modules)"
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True)
    assert out.stdout.strip() == "False", out.stderr


def test_metrics_option_puts_the_headline_numbers_where_asked(tmp_path, monkeypatch):
    """experiments/dvc.yaml gives each variant's data root its own metrics folder."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(TINY))
    args = ["ingest", "--data", "variant", "--metrics", "variant/metrics"]
    args += ["-S", "ingest.episodes=4"]
    assert runner.invoke(app, args).exit_code == 0
    assert json.loads((tmp_path / "variant/metrics/ingest.json").read_text())["episodes"] == 4
    assert (tmp_path / "variant/demos/tiny.mcap").exists() and not (tmp_path / "metrics").exists()


def test_bench_train_rejects_an_unknown_dtype_in_one_line():
    result = runner.invoke(app, ["bench", "train", "--dtypes", "float32,float16"])
    assert "--dtypes" in _one_line_error(result) and "float16" in result.stderr
