"""The real CLI through Typer's runner, on a tiny real dataset."""

import json

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
    report = json.loads((root / "data/reports/segment.json").read_text())
    assert report["train_episodes"] + report["validation_episodes"] + report["test_episodes"] == 6
    ingest = json.loads((root / "data/reports/ingest.json").read_text())
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
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    (tmp_path / "params.yaml").write_text(
        yaml.safe_dump({"ingest": {"name": "big", "episodes": 2000, "episode_steps": 1000}})
    )
    cli = Path(__file__).resolve().parents[1] / "cli.py"
    proc = subprocess.Popen(
        [sys.executable, str(cli), "ingest", "-p", str(tmp_path / "params.yaml")],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    demos = tmp_path / "data" / "demos"
    deadline = time.monotonic() + 60
    while not any(demos.glob(".tmp-*")) and time.monotonic() < deadline:
        time.sleep(0.05)  # wait until it is writing
    time.sleep(0.5)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert any(demos.glob(".tmp-*")), "the run was killed before it started writing"
    assert not (demos / "big.mcap").exists()
