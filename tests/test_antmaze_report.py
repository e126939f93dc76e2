"""scripts/antmaze_report.py: the ant-maze report from a run's reports, and its verdicts."""

import importlib.util
import json
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _module():
    spec = importlib.util.spec_from_file_location(
        "antmaze_report", ROOT / "scripts/antmaze_report.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _rate(successes: int, n: int) -> dict:
    from pipeline.evaluation.proportions import wilson_interval

    lo, hi = wilson_interval(successes, n)
    return {
        "episodes": n,
        "successes": successes,
        "success_rate": successes / n,
        "success_ci95_low": lo,
        "success_ci95_high": hi,
    }


def _deploy(successes: list[int], n: int = 50) -> dict:
    tasks = {f"ogbench-task{i + 1}": _rate(s, n) for i, s in enumerate(successes)}
    tasks["ogbench"] = _rate(sum(successes), n * len(successes))
    return {
        "tasks": [*tasks],
        "episodes_per_task": n,
        "max_steps": 1000,
        "by_agent": {"oposm": tasks, "gcbc": tasks},
    }


def test_verdict_compares_the_interval_with_the_best_published_method():
    m = _module()
    assert "**holds**" in m.verdict("medium", _deploy([50, 50, 50, 50, 50]))  # [99, 100] > 97
    assert "**does not hold**" in m.verdict("medium", _deploy([20, 20, 20, 20, 20]))
    assert "**inconclusive**" in m.verdict("medium", _deploy([48, 48, 48, 48, 48]))
    assert "HIQL 96" in m.verdict("medium", _deploy([48] * 5))
    assert "CRL" not in m.verdict("large", _deploy([48] * 5))  # large's best is HIQL 91
    assert m.verdict("medium", None) is None


def test_report_reads_a_runs_reports_and_writes_markdown_and_json(tmp_path, monkeypatch):
    run = tmp_path / "ant"
    reports = run / "reports"
    for stage, body in {
        "ingest": {
            "episodes": 4,
            "steps": 4004,
            "fallen_steps": 0,
            "fallen_episodes": 0,
            "goals_per_1000_steps": 4.5,
        },
        "deploy": _deploy([40, 41, 42, 43, 44]),
    }.items():
        (reports / stage).mkdir(parents=True)
        (reports / stage / "report.json").write_text(json.dumps(body))
    llp = _deploy([10] * 5, n=10)
    llp["by_agent"] = {"llp": llp["by_agent"]["oposm"]}
    (run / "runs/llp/reports/deploy").mkdir(parents=True)
    (run / "runs/llp/reports/deploy/report.json").write_text(json.dumps(llp))
    plain = _deploy([2] * 5, n=10)  # the same agent in another setting: a row of its own
    (run / "runs/plain/reports/deploy").mkdir(parents=True)
    (run / "runs/plain/reports/deploy/report.json").write_text(json.dumps(plain))
    plain["by_agent"]["oposm"]["ogbench"]["fallen"] = 7  # a newer deploy counts falls
    (run / "runs/plain/reports/deploy/report.json").write_text(json.dumps(plain))
    tuning = {"tasks": ["random_goal"], "episodes_per_task": 50, "max_steps": 1000,
              "by_agent": {"oposm": {"random_goal": _rate(40, 50)}}}  # fmt: skip
    (run / "runs/rg/reports/deploy").mkdir(parents=True)  # a choice on training-data goals
    (run / "runs/rg/reports/deploy/report.json").write_text(json.dumps(tuning))
    for factor, successes in ((1.0, [8] * 5), (0.5, [4] * 5), (2.0, [6] * 5)):  # figure 5
        sweep = _deploy(successes, n=10)
        sweep["mass_scale"] = factor
        sweep["by_agent"]["expert"] = _deploy([8] * 5, n=10)["by_agent"]["oposm"]
        (run / f"runs/mass{factor:g}/reports/deploy").mkdir(parents=True)
        (run / f"runs/mass{factor:g}/reports/deploy/report.json").write_text(json.dumps(sweep))
    commands = tmp_path / "commands.json"
    commands.write_text(
        json.dumps(
            {
                "medium": {
                    "commands": ["oposm ingest -p params-ogbench-antmaze-medium.yaml"],
                    "notes": ["trained on another machine"],
                }
            }
        )
    )
    out = tmp_path / "results"
    monkeypatch.setattr(
        sys,
        "argv",
        [
            "x",
            "--maze",
            f"medium={run}",
            "--commands",
            str(commands),
            "--out",
            str(out),
            "--machine",
            "test box",
        ],
    )
    _module().main()
    text = (out / "antmaze.md").read_text()
    assert "| oposm | 50 | 80 (67-89) |" in text and "| gcbc | 50 |" in text
    assert "| llp | 10 | 100 (72-100) |" in text  # an ad-hoc run's report joins the table
    assert "| oposm (run plain) | 10 |" in text
    assert "| **20 (11-33)** | 7 |" in text and "| **84 (79-88)** | – |" in text  # fell
    assert "(run rg)" not in text  # a run on other tasks stays out of OGBench's table
    assert "4 episodes, 4004 steps" in text and "HIQL 96 +- 1" in text
    assert "oposm ingest -p params-ogbench-antmaze-medium.yaml" in text
    assert "Machine: test box. Commit: " in text
    # the development metric (training-data goals) gets a line of its own
    assert "(`random_goal`, run `rg`, the development metric): oposm 80 (67-89) % of 50" in text
    assert "| x0.5 | 40 (28-54) | 40 (28-54) | 80 (67-89) | 51 | 49.3 |" in text  # its table
    assert "oposm 62 %" in text and "expert 100 %" in text  # (40 + 60) / 2 of 80 % at x1
    assert "than the expert policy): **does not hold** (shares 62 % vs 100 %" in text
    assert "(run mass" not in text  # sweep runs stay out of the success table
    assert "- trained on another machine" in text
    results = json.loads((out / "antmaze.json").read_text())
    assert results["mazes"]["medium"]["train"] is None  # not run: reported as missing, not faked
    assert "does not hold" in results["verdicts"]["medium"]
    # --keep: a second maze joins; the first stays as it was, even with its data root gone.
    shutil.move(run, tmp_path / "gone")
    (tmp_path / "gone" / "reports" / "ingest").rename(tmp_path / "gone" / "reports" / "x")
    monkeypatch.setattr(sys, "argv", ["x", "--maze", f"large={tmp_path / 'gone'}", "--keep",
                                      "--out", str(out)])  # fmt: skip
    _module().main()
    results = json.loads((out / "antmaze.json").read_text())
    assert set(results["mazes"]) == {"medium", "large"}
    assert results["mazes"]["medium"]["ingest"]["steps"] == 4004  # kept from the first run
    assert results["mazes"]["large"]["ingest"] is None
    assert set(results["verdicts"]) == {"medium", "large"}
    assert results["machine"] == "test box"  # kept with the mazes
    assert "4 episodes, 4004 steps" in (out / "antmaze.md").read_text()


def test_a_corrupt_report_is_a_one_line_error_naming_it(tmp_path):
    import subprocess

    bad = tmp_path / "ant/reports/ingest/report.json"
    bad.parent.mkdir(parents=True)
    bad.write_text("{not json")
    result = subprocess.run(
        [
            sys.executable,
            str(ROOT / "scripts/antmaze_report.py"),
            "--maze",
            f"medium={tmp_path / 'ant'}",
            "--out",
            str(tmp_path / "results"),
        ],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip().count("\n") == 0 and str(bad) in result.stderr
    assert not (tmp_path / "results").exists()  # nothing half-written
