"""scripts/stability_report.py: runs of several recipes and seeds -> the stability table, with
a run stable only when its NLL is near its recipe's median and its random goals are reached."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts/stability_report.py"


def _run_folder(root: Path, step: int, nll: float, success: float | None) -> Path:
    (root / "metrics").mkdir(parents=True)
    train = {"best_step": step, "best_val_st_nll_prior": nll, "diverged": nll > 3}
    (root / "metrics/train.json").write_text(json.dumps(train))
    if success is not None:
        goal = {"success": success, "episodes": 100}
        corners = {"success": 0.5, "episodes": 10}
        deploy = {"oposm": {"random_goal": goal, "corners": corners, "flops": 3}}
        (root / "metrics/deploy.json").write_text(json.dumps(deploy))
    return root


def test_stability_table_marks_each_run_against_its_recipe(tmp_path):
    runs = {
        ("new", 0): (5000, 1.40, 0.97),
        ("new", 1): (5000, 1.60, 0.99),
        ("new", 2): (5000, 2.30, 0.98),  # 0.7 above the median (1.6)
        ("new", 3): (4750, 1.50, 0.90),  # below 95 % of the goals
        ("old", 0): (500, 3.40, 0.60),
    }
    args = []
    for (recipe, seed), numbers in runs.items():
        folder = _run_folder(tmp_path / f"{recipe}-{seed}", *numbers)
        args += ["--run", f"{recipe} {seed} {folder}"]
    args += ["--run", f"old 1 {tmp_path / 'missing'}"]
    out = tmp_path / "results" / "stability"
    out.parent.mkdir()
    subprocess.run([sys.executable, SCRIPT, "--out", out, *args], check=True, cwd=ROOT)
    report = json.loads(out.with_suffix(".json").read_text())
    stable = {(r["recipe"], r["seed"]): r.get("stable") for r in report["runs"]}
    assert stable == {("new", 0): True, ("new", 1): True, ("new", 2): False,
                      ("new", 3): False, ("old", 0): False, ("old", 1): None}  # fmt: skip
    first = report["runs"][0]
    assert first["published_step"] == 5000 and first["random_goal_success"] == 0.97
    text = out.with_suffix(".md").read_text()
    row = "| new | 0 | 5000 | 1.400 | False | 97 [92, 99], 97/100 | 50 [24, 76], 5/10 | yes |"
    assert row in text
    assert "| old | 1 | not run yet |" in text
    assert "| new | 4 of 4 | 2 | " in text
    assert first["commit"] == report["commit"] and first["machine"] == report["stamp"]["machine"]
    never = next(r for r in report["runs"] if (r["recipe"], r["seed"]) == ("old", 1))
    assert "commit" not in never and "machine" not in never  # not run: dated to no commit


def _report_keeping(tmp_path: Path, earlier: dict, args: list[str]) -> Path:
    """Run the report with `--keep` of the `earlier` report; returns the output stem."""
    (tmp_path / "earlier.json").write_text(json.dumps(earlier))
    out = tmp_path / "stability"
    subprocess.run(
        [sys.executable, SCRIPT, "--out", out, "--keep", tmp_path / "earlier.json", *args],
        check=True,
        cwd=ROOT,
    )
    return out


def test_rows_not_rerun_keep_their_earlier_commit_and_machine(tmp_path):
    """`--keep`: a run whose folder is empty here keeps its row of the earlier report (a legacy
    recipe name renamed), with that report's commit; a rerun row replaces its earlier one."""
    earlier = {
        "commit": "abc1234",
        "runs": [
            {"recipe": "ema", "seed": 0, "published_step": 4750, "val_st_nll_prior": 1.3,
             "diverged": False, "random_goal_success": 1.0, "random_goal_episodes": 100},
            {"recipe": "default", "seed": 0, "published_step": 100, "val_st_nll_prior": 9.0},
        ],
    }  # fmt: skip
    fresh = _run_folder(tmp_path / "default-0", 5000, 1.4, 0.99)
    args = ["--run", f"default 0 {fresh}", "--run", f"bfloat16 0 {tmp_path / 'gone'}"]
    out = _report_keeping(tmp_path, earlier, args)
    report = json.loads(out.with_suffix(".json").read_text())
    rows = {(r["recipe"], r["seed"]): r for r in report["runs"]}
    assert rows["bfloat16", 0]["commit"] == "abc1234" and rows["bfloat16", 0]["stable"] is True
    assert rows["default", 0]["published_step"] == 5000
    assert rows["default", 0]["commit"] == report["commit"] != "abc1234"
    text = out.with_suffix(".md").read_text()
    assert "| bfloat16 | 1 of 1 | 1 | abc1234 | not recorded |" in text


def test_a_run_read_again_keeps_the_commit_it_was_reported_at(tmp_path):
    """A finished run whose folder is still here is read again by every later report: with the
    same numbers it keeps its earlier row's commit and machine; with others it is a new run."""
    same = _run_folder(tmp_path / "default-0", 5000, 1.4, 0.99)
    other = _run_folder(tmp_path / "default-1", 4500, 1.5, 1.0)
    first = {"commit": "abc1234", "stamp": {"machine": "cpu A"}, "runs": []}
    for seed, (step, nll, ok) in enumerate([(5000, 1.4, 0.99), (4750, 1.6, 0.98)]):
        first["runs"].append({
            "recipe": "default", "seed": seed, "run": "x", "published_step": step,
            "val_st_nll_prior": nll, "diverged": False, "random_goal_success": ok,
            "random_goal_episodes": 100, "corners_success": 0.5, "corners_episodes": 10,
        })  # fmt: skip
    args = ["--run", f"default 0 {same}", "--run", f"default 1 {other}"]
    out = _report_keeping(tmp_path, first, args)
    rows = {r["seed"]: r for r in json.loads(out.with_suffix(".json").read_text())["runs"]}
    assert (rows[0]["commit"], rows[0]["machine"]) == ("abc1234", "cpu A")
    assert rows[1]["commit"] != "abc1234" and rows[1]["published_step"] == 4500


def test_the_sweep_script_refuses_a_bad_option_before_running_anything():
    """`scripts/stability_cpu.sh` checks its recipes and `--jobs` first: a typo costs nothing."""
    script = ROOT / "scripts/stability_cpu.sh"
    for args, message in ((["--jobs", "3", "default"], "--jobs is 1 or 2, not 3"),
                          (["--seeds", "0,3", "nosuch"], "unknown recipe nosuch")):  # fmt: skip
        done = subprocess.run(["bash", script, *args], capture_output=True, text=True, cwd=ROOT)
        assert done.returncode == 2 and message in done.stderr, done.stderr
