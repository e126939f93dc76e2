"""`oposm report ogbench-point` (stages/ogbench_point_report.py): runs' deploy reports -> the
table beside OGBench's, verdicts, and one-line errors for a wrong run."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
REPORT = [sys.executable, str(ROOT / "cli.py"), "report", "ogbench-point"]


def _rate(successes: int, n: int) -> dict:
    from pipeline.evaluation.proportions import wilson_interval

    lo, hi = wilson_interval(successes, n)
    return {"episodes": n, "successes": successes, "success_rate": successes / n,
            "success_ci95_low": lo, "success_ci95_high": hi}  # fmt: skip


def _run(root: Path, successes: list[int], n: int = 50, agent: str = "oposm") -> Path:
    tasks = {f"ogbench-task{i + 1}": _rate(s, n) for i, s in enumerate(successes)}
    tasks["ogbench"] = _rate(sum(successes), n * len(successes))
    path = root / "reports" / "deploy" / "report.json"
    path.parent.mkdir(parents=True)
    report = {"env_id": "pointmaze-medium-v0", "max_steps": 1000, "success_radius": 1.0,
              "wall_s": 12.0, "by_agent": {agent: tasks}}  # fmt: skip
    path.write_text(json.dumps(report))
    return root


def test_the_report_puts_runs_beside_ogbench_with_a_verdict(tmp_path):
    good = _run(tmp_path / "good", [50, 50, 49, 50, 50])
    weak = _run(tmp_path / "weak", [50, 40, 5, 45, 50])
    gcbc = _run(tmp_path / "gcbc", [50] * 5, agent="gcbc")  # never our verdict's "best run"
    out = tmp_path / "results"
    runs = ["--run", f"medium/sub={good}", "--run", f"medium/plain={weak}"]
    runs += ["--run", f"medium/GCBC (ours)={gcbc}"]
    stitch = _run(tmp_path / "stitch", [40, 40, 40, 40, 40])  # 80 %: not above QRL's 80
    runs += ["--run", f"medium-stitch/sub={stitch}"]
    command = ["--command", "uv run oposm deploy ...", "--out", str(out)]
    command += ["--machine", "the first box"]
    subprocess.run([*REPORT, *runs, *command], check=True, cwd=ROOT)
    text = (out / "ogbench-point.md").read_text()
    assert "| medium | sub | 100 [93, 100] | 100 [93, 100] | 98 [90, 100] |" in text
    assert "| **100 [98, 100]** | 250 |" in text  # 249 of 250
    assert "| medium | 9 ± 6 | 63 ± 6 | 53 ± 8 | 82 ± 5 | 29 ± 7 | 79 ± 5 | QRL 82 |" in text
    # rule 3: 249/250 against every method, OGBench's and the later ones (SAW's 97 +- 2 over 8
    # seeds, the closest)
    assert "- medium: **holds**: sub 100 [98, 100] vs SAW 97 ± 2 (the method deciding it), " in text
    assert "| medium | 97 ± 2 |" in text and "| medium-stitch | 87 ± 4 |" in text  # SAW's tables
    assert "- medium: ours 100 [98, 100], OGBench's 9 ± 6; difference [" in text
    assert "| medium-stitch | 23 ± 18 | 70 ± 14 | 21 ± 9 | 80 ± 12 | 0 ± 1 | 74 ± 6 |" in text
    assert "- medium-stitch: **does not hold**: sub 80 [75, 84] vs SAW 87 ± 4 " in text
    assert "Made by `oposm report ogbench-point`" in text and "code at commit" in text
    data = json.loads((out / "ogbench-point.json").read_text())
    assert [r["label"] for r in data["runs"]] == ["sub", "plain", "GCBC (ours)", "sub"]
    assert data["runs"][2]["agent"] == "gcbc" and data["runs"][2]["dataset"] == "medium"
    assert data["runs"][1]["tasks"]["ogbench-task3"]["successes"] == 5
    assert data["published"]["giant"]["QRL"] == [68, 7]
    assert data["published"]["giant-stitch"]["QRL"] == [50, 8]
    assert data["published"]["medium"]["SAW"] == [97, 2]
    # --keep: the earlier rows stay (their run folders gone); the same DATASET/LABEL is replaced.
    for run in (good, weak, gcbc, stitch):
        (run / "reports" / "deploy" / "report.json").unlink()
    better = _run(tmp_path / "better", [45] * 5)
    again = ["--run", f"medium-stitch/sub={better}", "--run", f"medium-stitch/new={better}"]
    again += ["--keep", "--command", "uv run oposm deploy --run better", "--out", str(out)]
    teleport = _run(tmp_path / "teleport", [30] * 5)  # no published row to compare with
    again += ["--run", f"teleport/sub={teleport}"]
    subprocess.run([*REPORT, *again], check=True, cwd=ROOT)
    data = json.loads((out / "ogbench-point.json").read_text())
    labels = ["sub", "plain", "GCBC (ours)", "sub", "new", "sub"]
    assert [r["label"] for r in data["runs"]] == labels
    assert data["runs"][3]["tasks"]["ogbench"]["successes"] == 225
    assert data["commands"] == ["uv run oposm deploy ...", "uv run oposm deploy --run better"]
    assert data["machine"] == "the first box"  # kept with the rows
    text = (out / "ogbench-point.md").read_text()
    assert "- medium-stitch: **inconclusive**: sub 90 [86, 93] vs SAW 87 ± 4 " in text
    assert "| teleport | not quoted | not quoted |" in text
    assert "- teleport: sub 60 [54, 66]; no published number is quoted here" in text


def test_a_run_that_is_not_of_the_ogbench_tasks_is_a_one_line_error(tmp_path):
    root = tmp_path / "run"
    (root / "reports" / "deploy").mkdir(parents=True)
    (root / "reports" / "deploy" / "report.json").write_text(
        json.dumps(
            {
                "env_id": "x",
                "max_steps": 1,
                "success_radius": 1.0,
                "by_agent": {"oposm": {"random_goal": _rate(1, 2)}},
            }
        )  # fmt: skip
    )
    args = [*REPORT, "--run", f"medium/x={root}", "--out", str(tmp_path / "o")]
    got = subprocess.run(args, capture_output=True, text=True, cwd=ROOT)
    assert got.returncode == 1
    assert got.stderr.strip().count("\n") == 0 and "deploy.tasks: [ogbench]" in got.stderr
    assert not (tmp_path / "o" / "ogbench-point.md").exists()


def test_every_later_method_ran_ogbenchs_number_of_seeds():
    """The verdicts give `above_every` one seed count for OGBench's methods and the later ones:
    a method with another count needs its own before it joins after_ogbench.toml."""
    from pipeline.evaluation import published

    assert set(published.SEEDS.values()) == {published.OGBENCH_SEEDS}
    quoted = {m for row in published.AFTER_OGBENCH.values() for m in row}
    assert quoted == set(published.SEEDS)  # every quoted method states its seeds
