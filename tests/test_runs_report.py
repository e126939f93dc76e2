"""scripts/runs_report.py: train metrics and deploy episodes -> a report that compares deploys
episode by episode, and one-line errors for runs that cannot be compared."""

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts/runs_report.py"


def _deploy(root: Path, outcomes: dict[str, list[bool]], goal_shift: float = 0.0) -> Path:
    episodes = [
        {"agent": "oposm", "task": task, "episode": i, "seed": 100 + i,
         "goal": [float(i) + goal_shift, 1.0], "success": won}
        for task, wins in outcomes.items()
        for i, won in enumerate(wins)
    ]  # fmt: skip
    path = root / "reports" / "deploy" / "episodes.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(episodes))
    return root


def _train(path: Path, nll: float) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"best_step": 4750, "best_val_st_nll_prior": nll,
                                "best_val_st_nll": -0.04, "val_action_nll": 1.1,
                                "steps_per_s": 15.8, "wall_s": 345.0, "steps": 5000}))  # fmt: skip
    return path


def _script(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True,
                          cwd=ROOT)  # fmt: skip


def test_the_report_compares_deploys_episode_by_episode(tmp_path):
    a = _deploy(
        tmp_path / "a", {"corners": [True] * 8 + [False, False], "random_goal": [True] * 10}
    )
    # b: loses episodes 0-2 of corners that a won, wins episode 8 that a lost.
    b = _deploy(tmp_path / "b", {"corners": [False] * 3 + [True] * 6 + [False],
                                 "random_goal": [True] * 10})  # fmt: skip
    out = tmp_path / "precision"
    result = _script(
        "--train", f"f32={_train(tmp_path / 't32.json', 1.578)}",
        "--train", f"bf16={_train(tmp_path / 't16.json', 1.443)}",
        "--deploy", f"A={a}", "--deploy", f"B={b}", "--pair", "A|B",
        "--command", "uv run oposm deploy", "--machine", "test CPU", "--out", str(out),
        "--title", "Precision test", "--intro", "What this compares.",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    report = json.loads(out.with_suffix(".json").read_text())
    corners = report["pairs"][0]["tasks"]["corners"]
    assert corners["successes"] == [8, 6] and corners["episodes"] == 10
    assert (corners["only_first"], corners["only_second"]) == (3, 1)
    assert abs(corners["mcnemar_p"] - 0.625) < 1e-9  # exact binomial: 2 * P(X <= 1 | n 4, 1/2)
    assert report["pairs"][0]["tasks"]["all"]["successes"] == [18, 16]
    assert report["deploy"]["B"]["corners"]["successes"] == 6
    low, high = corners["difference_interval"]
    assert low < corners["difference"] == 0.2 < high
    text = out.with_suffix(".md").read_text()
    assert "| f32 | 4750 | 1.578 |" in text and "| bf16 | 4750 | 1.443 |" in text
    assert "| A | B | corners | 8 vs 6 of 10 | 3 | 1 | 0.62 | +20.0 [" in text
    assert "test CPU" in text and "`uv run oposm deploy`" in text
    assert text.startswith("# Precision test\n") and "(numbers: `precision.json`)" in text
    assert "What this compares." in text


def test_deploys_of_different_episodes_or_a_missing_run_are_one_line_errors(tmp_path):
    a = _deploy(tmp_path / "a", {"corners": [True, False]})
    other = _deploy(tmp_path / "other", {"corners": [True, False]}, goal_shift=0.5)
    result = _script("--deploy", f"A={a}", "--deploy", f"B={other}", "--pair", "A|B",
                     "--out", str(tmp_path / "x"), "--title", "t")  # fmt: skip
    assert result.returncode != 0 and "different episodes" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr
    default = _script("--deploy", f"A={a}", "--out", str(tmp_path / "d"), "--title", "t")
    assert default.returncode == 0, default.stderr  # the machine described by default
    assert f"{os.cpu_count()} cores, torch " in (tmp_path / "d.md").read_text()
    missing = _script(
        "--deploy", f"A={tmp_path / 'nothing'}", "--out", str(tmp_path / "x"), "--title", "t"
    )
    assert missing.returncode != 0 and "episodes.json does not exist" in missing.stderr
    assert not (tmp_path / "x.md").exists()
