"""`oposm report experiments`: the experiments' deploy reports -> results/, a verdict per claim."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from cli import app
from pipeline.evaluation.proportions import difference_interval, wilson_interval
from stages.experiments_report import collect, markdown, plot_rows, run

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()


def _task(wins: int, n: int = 200, within: int | None = None) -> dict:
    within = wins if within is None else within
    return {"successes": wins, "episodes": n, "within_steps": {"600": {"successes": within}}}


def _agent(random_goal: int, corners: int, replan_s: float | None) -> dict:
    return {
        "random_goal": _task(random_goal, within=random_goal - 2),
        "corners": _task(corners),
        "planning": {"per_env_latency_s": {"p50": replan_s}},
        "flops_per_replan": None if replan_s is None else 1e9,
    }


def _report(agents: dict[str, dict]) -> dict:
    return {
        "env_id": "PointMaze_Medium-v3",
        "tasks": ["random_goal", "corners"],
        "max_steps": 2000,
        "shorter_limits": [600],
        "episodes_per_task": 200,
        "wall_s": 12.0,
        "by_agent": agents,
    }


def _write(path: Path, report: dict) -> None:
    path.mkdir(parents=True)
    (path / "report.json").write_text(json.dumps(report))


@pytest.fixture
def experiments(tmp_path):
    params = {
        "deploy": {"roots": {"medium": "data", "large": "data/experiments/mazes/large"}},
        "mass": {"maze": "medium", "root": "data", "factors": {"x0.5": 0.5, "x1": 1.0, "x2": 2.0}},
        "em_vi": {"datasets": [{"root": "data", "tag": "plain"}], "seeds": [0, 1, 2]},
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    data = tmp_path / "data"
    medium = {
        "oposm": _agent(199, 190, 0.10),
        "llp": _agent(180, 195, 0.05),
        "gcbc": _agent(150, 90, None),
        "expert": _agent(200, 200, None),
    }
    _write(data / "runs/experiments/reports/deploy", _report(medium))
    for key, (oposm, expert) in {"x0.5": (90, 60), "x1": (98, 99), "x2": (85, 40)}.items():
        agents = {"oposm": _agent(oposm, oposm, 0.1), "expert": _agent(expert, expert, None)}
        _write(data / f"runs/mass-{key}/reports/deploy", _report(agents))
    return tmp_path / "params.yaml", tmp_path


def test_intervals_of_a_rate_and_of_a_difference():
    lo, hi = wilson_interval(200, 200)
    assert hi == 1.0 and 0.98 < lo < 0.985
    lo, hi = difference_interval(199, 200, 180, 200)
    assert 0.04 < lo < 0.095 < hi < 0.15  # excludes 0: OPOSM ahead
    lo, hi = difference_interval(190, 200, 192, 200)
    assert lo < 0 < hi


def test_verdicts_follow_the_intervals_and_missing_runs_are_named(experiments):
    params, data = experiments
    results = collect(params, data)
    verdicts = {c["claim"]: c["verdict"] for c in results["claims"]}
    assert verdicts["OPOSM reaches random goals in maze2d-medium (table 4: 100.0 %)"] == "holds"
    assert verdicts["OPOSM reaches random goals more often than LLP (table 4: 95.7 %), medium"] == (
        "holds"
    )
    timing = next(c for c in results["claims"] if c["claim"].startswith("OPOSM finds a plan"))
    assert timing["verdict"] == "does not hold" and "LLP/OPOSM 0.50x" in timing["numbers"]
    mass = next(c for c in results["claims"] if "than expert" in c["claim"])
    assert mass["verdict"] == "holds"  # 175/400 vs 100/400 off the nominal mass
    assert results["mass"]["perturbed_pooled"]["oposm"]["successes"] == 2 * (90 + 85)
    assert "maze sizes: large" in results["not_run"]
    assert "EM vs naive VI (table 3): 0 of its 6 runs have finished" in results["not_run"]
    assert "model selection: 0 of its 3 deploys have finished" in results["not_run"]
    medium = results["mazes"]["medium"]["agents"]["oposm"]["random_goal"]
    assert medium["within_600"]["successes"] == 197


def test_run_writes_the_report_json_and_plot_csvs(experiments, tmp_path):
    params, data = experiments
    out = tmp_path / "results"
    run(params, data, out)
    text = (out / "experiments.md").read_text()
    assert (
        "| medium | random_goal | llp | 90.0 [85.1, 93.4] | 89.0 [83.9, 92.6] (600) | 95.7" in text
    )
    assert "| oposm (ours) | 45.0" in text and "| expert (paper, antmaze-large) | 49.3" in text
    assert (
        json.loads((out / "experiments.json").read_text())["mazes"]["medium"]["max_steps"] == 2000
    )
    headline = json.loads((out / "metrics.json").read_text())
    assert headline["medium_oposm_random_goal"] == 0.995 and headline["mass_expert"] == 0.25
    mass_csv = (out / "mass.csv").read_text().splitlines()
    assert mass_csv[0] == "mass_factor,oposm,expert" and mass_csv[1].startswith("0.5,0.45,0.3")
    assert (out / "mazes.csv").read_text().splitlines()[1].startswith("medium,0.995,0.9")
    assert markdown(collect(params, data)) == text


def test_cli_prints_verdicts_and_refuses_a_broken_report(experiments, tmp_path):
    params, data = experiments
    args = ["report", "experiments", "--experiments", str(params), "--repo", str(data)]
    result = runner.invoke(app, [*args, "--out", str(tmp_path / "r")])
    assert result.exit_code == 0, result.output
    alias = ["results", *args[2:], "--out", str(tmp_path / "alias")]  # its name before `report`
    assert runner.invoke(app, alias).exit_code == 0
    assert (tmp_path / "alias/experiments.md").read_bytes() == (
        tmp_path / "r/experiments.md"
    ).read_bytes()
    assert "holds  OPOSM reaches random goals in maze2d-medium" in result.output
    (data / "data/runs/experiments/reports/deploy/report.json").write_text("{")
    result = runner.invoke(app, [*args, "--out", str(tmp_path / "r2")])
    assert result.exit_code != 0 and "report.json: not valid JSON" in result.output
    assert "Traceback" not in result.output and not (tmp_path / "r2/experiments.md").exists()


def test_dvc_reads_the_experiments_pipeline():
    command = [sys.executable, "-m", "dvc", "stage", "list", "experiments/dvc.yaml"]
    out = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    names = {line.split()[0].split(":")[1] for line in out.stdout.splitlines() if line.strip()}
    assert {
        "train@large",
        "deploy@umaze",
        "mass@x0_2",
        "mass@x5",
        "em_vi_train@data1-vi-2",
        "results",
    } <= names


def test_em_vi_verdicts_need_every_seed_on_one_side(tmp_path):
    """Pushed maze, 3 seeds each: VI's calibration below all of EM's -> holds; optimism gaps
    that interleave -> inconclusive. The table lists every run."""
    datasets = [{"root": "data", "tag": "plain"}, {"root": "pushed", "tag": "pushed"}]
    params = {
        "deploy": {"roots": {}},
        "mass": {"maze": "medium", "root": "data", "factors": {}},
        "em_vi": {"datasets": datasets, "seeds": [0, 1, 2]},
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    within = {"em": [0.66, 0.70, 0.68], "vi": [0.41, 0.50, 0.45]}
    gaps = {"em": [0.05, 0.20, 0.10], "vi": [0.15, 0.30, 0.08]}
    for method in ("em", "vi"):
        for seed in range(3):
            run = tmp_path / f"pushed/runs/{method}-seed{seed}/reports"
            first = {"tawm_nll": -0.1, "tawm_within_1sigma": within[method][seed]}
            errors = {"em": (0.3, 0.5), "vi": (0.4, 0.8 + 0.3 * seed)}[method]
            prior = {
                "skills_2": first | {"tawm_error_mean": errors[1]},  # order of keys not relied on
                "skills_1": first | {"tawm_error_mean": errors[0]},
            }
            _write(run / "validate", {"prior": prior})
            agent = _agent(90, 80, 0.1) | {
                "optimism_gap": {"random_goal": {"distance_gap_m": {"mean": gaps[method][seed]}}}
            }
            _write(run / "deploy", _report({"oposm": agent}))
    results = collect(tmp_path / "params.yaml", tmp_path)
    verdicts = {c["claim"].split(", ")[1].split(" (")[0]: c["verdict"] for c in results["claims"]}
    assert verdicts["VI's TAWM is overconfident: fewer real outcomes within 1 sigma than EM's"] == (
        "holds"
    )
    assert verdicts["VI's plans are more optimistic than EM's"] == "inconclusive"
    assert results["em_vi"]["pushed"]["vi"]["2"]["success"]["successes"] == 170
    assert "| pushed | vi | 0 | -0.100 | 41.0 |" in markdown(results)
    rows = plot_rows(results)
    assert rows["em_vi_error.csv"] == [
        {"skills": 1, "pushed_em": 0.3, "pushed_vi": 0.4},
        {"skills": 2, "pushed_em": 0.5, "pushed_vi": 1.1},
    ]
    assert rows["optimism_gap.csv"] == [
        {"run": "pushed em", "optimism_gap_m": 0.1167},
        {"run": "pushed vi", "optimism_gap_m": 0.1767},
    ]


def test_selection_compares_the_two_checkpoints_on_the_same_episodes(tmp_path):
    """Three EM seeds: the prior-NLL checkpoints win 3 x 195 / 400 against 3 x 150 / 400 (both
    tasks pooled) -> holds; the table names the step each criterion picked."""
    params = {
        "deploy": {"roots": {}},
        "mass": {"maze": "medium", "root": "data", "factors": {}},
        "em_vi": {"datasets": [{"root": "data", "tag": "plain"}], "seeds": [0, 1, 2]},
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    runs = tmp_path / "data/runs"
    for seed in range(3):
        _write(runs / f"em-seed{seed}/reports/deploy", _report({"oposm": _agent(75, 75, 0.1)}))
        _write(
            runs / f"em-seed{seed}-by-prior/reports/deploy",
            _report({"oposm": _agent(100, 95, 0.1)}),
        )
        by = runs / f"em-seed{seed}/models/pointmaze-medium/by"
        for criterion, step in (("st_nll", 5000), ("st_nll_prior", 3000 + seed)):
            (by / criterion).mkdir(parents=True)
            (by / criterion / "config.json").write_text(json.dumps({"step": step}))
    results = collect(tmp_path / "params.yaml", tmp_path)
    (claim,) = [c for c in results["claims"] if "prior-marginal" in c["claim"]]
    assert claim["verdict"] == "holds" and "0 of 3 seeds picked the same step" in claim["numbers"]
    assert results["selection"]["plain"]["2"]["step_by_st_nll_prior"] == 3002
    table = markdown(results)
    assert "| plain | 2 | 5000 | 37.5 [32.9, 42.3] | 3002 | 48.8 [43.9, 53.6] |" in table
    assert not any("model selection" in x for x in results["not_run"])


def test_the_results_stage_depends_on_every_em_vi_and_selection_run():
    """DVC lists cannot loop: the results stage names each run's reports by hand."""
    stage = yaml.safe_load((ROOT / "experiments/dvc.yaml").read_text())["stages"]["results"]
    cfg = yaml.safe_load((ROOT / "experiments/params.yaml").read_text())["em_vi"]
    expected = set()
    for dataset in cfg["datasets"]:
        runs = f"{dataset['root']}/runs"
        for seed in cfg["seeds"]:
            for method in ("em", "vi"):
                expected |= {
                    f"{runs}/{method}-seed{seed}/reports/{r}" for r in ("validate", "deploy")
                }
            expected.add(f"{runs}/em-seed{seed}/models/pointmaze-medium")
            expected.add(f"{runs}/em-seed{seed}-by-prior/reports/deploy")
    assert expected <= set(stage["deps"])
