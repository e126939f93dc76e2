"""The ant-maze report (pipeline/reporting/antmaze.py; `oposm report antmaze`,
stages/antmaze_report.py): both protocols from one run, its verdicts by the common rules, the
JSON a script can check."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.errors import UserError
from pipeline.reporting import antmaze
from pipeline.reporting.common import FAILS, HOLDS, INCONCLUSIVE, rate
from stages import antmaze_report

ROOT = Path(__file__).resolve().parents[1]


def _row(successes: int, n: int, within: int | None = None) -> dict:
    r = rate(successes, n)
    lo, hi = r["ci95"]
    row = {"episodes": n, "successes": successes, "success_rate": r["rate"],
           "success_ci95_low": lo, "success_ci95_high": hi, "fallen": 1}  # fmt: skip
    if within is not None:  # a 2000-step run: success within OGBench's 1000 steps as well
        row["within_steps"] = {"1000": {"successes": within}}
    return row


def _deploy(agent: str, successes: list[int], n: int = 50, within: list[int] | None = None,
            max_steps: int = 2000, mass: float = 1.0) -> dict:  # fmt: skip
    within = within or successes
    tasks = {f"ogbench-task{i + 1}": _row(s, n, w if max_steps > 1000 else None)
             for i, (s, w) in enumerate(zip(successes, within, strict=True))}  # fmt: skip
    tasks["ogbench"] = _row(sum(successes), n * 5, sum(within) if max_steps > 1000 else None)
    return {"tasks": [*tasks], "episodes_per_task": n, "max_steps": max_steps,
            "mass_scale": mass, "by_agent": {agent: tasks}}  # fmt: skip


def _write(root: Path, rel: str, body: dict) -> None:
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(body))


def _maze(root: Path) -> Path:
    _write(root, "reports/ingest/report.json", {"episodes": 4, "steps": 4004, "fallen_steps": 0,
           "fallen_episodes": 0, "goals_per_1000_steps": 4.5})  # fmt: skip
    _write(root, "reports/validate/report.json", {"starts": 100, "prior": {"skills_1": {
        "steps": 9, "tawm_error_mean": 0.3, "single_step_error_mean": 0.4,
        "no_model_error_mean": 1.2, "tawm_within_1sigma": 0.7}}, "posterior": {"skills_1": {
        "steps": 9, "replay_error_mean": 0.26, "tawm_recorded_error_mean": 0.32,
        "no_model_recorded_error_mean": 1.16}}})  # fmt: skip
    # OPOSM: 49 of 50 per task within 2000 steps, 40 of them within 1000
    _write(root, "runs/oposm/reports/deploy/report.json",
           _deploy("oposm", [49] * 5, within=[40] * 5))  # fmt: skip
    _write(root, "runs/gcbc/reports/deploy/report.json", _deploy("gcbc", [2] * 5))
    old = _deploy("oposm", [10] * 5, n=10, max_steps=1000)  # a 1000-step run: OGBench's only
    _write(root, "runs/old/reports/deploy/report.json", old)
    rg = {
        "tasks": ["random_goal"],
        "episodes_per_task": 50,
        "max_steps": 2000,
        "by_agent": {"oposm": {"random_goal": _row(45, 50, 44) | {"final_distance_mean": 0.8}}},
    }
    _write(root, "runs/random-goal/reports/deploy/report.json", rg)  # fmt: skip
    for factor, s in ((1.0, 9), (0.5, 5), (2.0, 7)):  # figure 5: oposm drops less than expert
        sweep = _deploy("oposm", [s] * 5, n=10, max_steps=1000, mass=factor)
        sweep["by_agent"] |= _deploy("expert", [9 if factor == 1.0 else 1] * 5, n=10,
                                     max_steps=1000)["by_agent"]  # fmt: skip
        _write(root, f"runs/mass{factor:g}/reports/deploy/report.json", sweep)
    return root


def test_protocols_take_ogbench_from_the_first_1000_steps_of_a_longer_run():
    long = antmaze.protocols(_row(49, 50, within=40), max_steps=2000)
    assert long["ogbench"]["successes"] == 40 and long["paper"]["successes"] == 49
    short = antmaze.protocols(_row(30, 50), max_steps=1000)
    assert short["ogbench"]["successes"] == 30 and short["paper"] is None


def test_collect_renders_both_protocols_the_ladder_and_each_verdict(tmp_path):
    maze = antmaze.collect(_maze(tmp_path / "medium"))
    agents = {a["agent"]: a for a in maze["agents"]}
    assert set(agents) == {"oposm", "gcbc", "oposm (run old)"}  # mass runs and random goals apart
    assert agents["oposm"]["tasks"]["ogbench"]["ogbench"]["successes"] == 200
    assert agents["oposm"]["tasks"]["ogbench"]["paper"]["successes"] == 245
    assert agents["oposm (run old)"]["tasks"]["ogbench"]["paper"] is None
    assert "mass_sweep" not in maze  # the mass runs are figure 5's report
    stamp = {"commit": "abc", "machine": "test box", "dvc": None}
    sweep = antmaze.figure5_report("medium", tmp_path / "medium", ["cmd mass"], stamp)
    assert set(sweep["mass_sweep"]["oposm"]) == {"0.5", "1.0", "2.0"}
    assert sweep["episodes_per_factor"] == 50
    checks = {c["claim"].split(" (")[0]: c
              for c in antmaze.verdicts("medium", maze) + sweep["verdicts"]}  # fmt: skip
    # rule 3 against OGBench's table: 80 % [74, 85] is below HIQL's 96 +- 1
    top = checks["OPOSM is above every published method on antmaze-medium-navigate"]
    assert top["verdict"] == FAILS and "HIQL 96 ± 1" in top["detail"]
    # rule 2 against the paper's table 1 (78.3 %): 98 % of 250 under the paper's protocol holds
    assert checks["OPOSM reaches the paper's table 1"]["verdict"] == HOLDS
    assert checks["OPOSM reaches the paper's table 4"]["verdict"] == HOLDS  # 90 % vs 72.6 %
    # rule 5: off x1 pooled, oposm 60 of 100 against the expert's 10 of 100
    fig5 = checks["OPOSM keeps more of its success under mass changes than the expert"]
    assert fig5["verdict"] == HOLDS and fig5["interval"][0] > 0
    report = antmaze.maze_report("medium", tmp_path / "medium", ["a note"], ["cmd a"], stamp)
    page = antmaze.page([report], {"steps": 5}, stamp, [sweep])
    antmaze.write_page(tmp_path / "out", page)
    text = (tmp_path / "out/antmaze.md").read_text()
    assert "| oposm | 50 | 80 [67, 89] | 80 [67, 89] |" in text
    assert text.index("| oposm | 50") < text.index("| oposm (run old)") < text.index("| gcbc | 50")
    assert "| **80 [75, 84]** | 98 [95, 99] | 1 |" in text  # OGBench's overall, the paper's, falls
    assert "| 1 | 9 | 0.26 | 0.32 | 1.16 |" in text  # skill fidelity, executed vs TAWM vs none
    assert "| x0.5 | 50 [37, 63] | 10 [4, 21] | 51 | 49 |" in text  # beside the paper's fig. 5
    assert "code at commit abc" in text and "test box" in text and "cmd a" in text
    assert "cmd mass" in text and "50 episodes per factor" in text
    assert "under mass changes" in text.split("## Protocol")[0]  # its verdict with the others
    saved = json.loads((tmp_path / "out/antmaze.json").read_text())
    flat = {(r["agent"], r["protocol"]): r for r in saved["runs"]}
    assert flat[("oposm", "paper")]["tasks"]["ogbench"] == {"episodes": 250, "successes": 245}
    assert ("oposm (run old)", "paper") not in flat
    assert saved["published"]["antmaze-large-navigate"]["HIQL"] == [91, 2]


def test_llp_on_the_same_tasks_is_judged_by_rule_1_beside_the_papers_table_1(tmp_path):
    root = tmp_path / "large"
    _write(root, "runs/oposm/reports/deploy/report.json",
           _deploy("oposm", [45] * 5, within=[40] * 5))  # fmt: skip
    # LLP: 10 episodes per task, 1000 steps (OGBench's protocol only), 3 of 10 reached
    _write(root, "runs/llp/reports/deploy/report.json",
           _deploy("llp", [3] * 5, n=10, max_steps=1000))  # fmt: skip
    maze = antmaze.collect(root)
    assert [a["agent"] for a in maze["agents"]] == ["oposm", "llp"]
    checks = {c["claim"].split(" (")[0]: c for c in antmaze.verdicts("large", maze)}
    llp = checks["OPOSM reaches goals more often than LLP on antmaze-large-navigate"]
    # 200 of 250 against 15 of 50 (OGBench's protocol): the Newcombe interval is above 0
    assert llp["verdict"] == HOLDS and llp["interval"][0] > 0
    assert "LLP 30.0 [19.1, 43.8]" in llp["detail"]
    assert "the paper's table 1 (antmaze-large-diverse): OPOSM 70.2 vs LLP 14.4" in llp["detail"]
    even = tmp_path / "even"  # the same rate on both sides: inconclusive, never "fails"
    _write(even, "runs/oposm/reports/deploy/report.json", _deploy("oposm", [3] * 5, n=10))
    _write(even, "runs/llp/reports/deploy/report.json", _deploy("llp", [3] * 5, n=10))
    checks = antmaze.verdicts("medium", antmaze.collect(even))
    assert [c["verdict"] for c in checks if "than LLP" in c["claim"]] == [INCONCLUSIVE]


def test_verdicts_are_inconclusive_near_the_best_published_and_absent_without_runs(tmp_path):
    root = tmp_path / "m"
    _write(root, "runs/oposm/reports/deploy/report.json", _deploy("oposm", [48] * 5))
    checks = antmaze.verdicts("medium", antmaze.collect(root))
    assert checks[0]["verdict"] == INCONCLUSIVE  # 96 [93, 98] vs HIQL 96 +- 1
    assert antmaze.verdicts("medium", antmaze.collect(tmp_path / "empty")) == []


def test_a_stitch_maze_is_judged_against_ogbenchs_stitch_row_and_has_no_paper_claims(tmp_path):
    assert antmaze.ogbench_name("medium-stitch") == "antmaze-medium-stitch"
    assert antmaze.ogbench_name("giant") == "antmaze-giant-navigate"
    root = _maze(tmp_path / "medium-stitch")
    checks = antmaze.verdicts("medium-stitch", antmaze.collect(root))
    assert [c["claim"].split(" on ")[-1].split(" (")[0] for c in checks][:1] == [
        "antmaze-medium-stitch"
    ]
    assert "HIQL 94 ± 1" in checks[0]["detail"]
    assert not any("the paper's table" in c["claim"] for c in checks)
    report = antmaze.maze_report("medium-stitch", root, [], [], {})
    page = antmaze.page([report], {}, {})
    assert "antmaze-medium-stitch-diverse" not in page["paper"]
    assert page["runs"][0]["dataset"] == "antmaze-medium-stitch"
    # one goal per stitch episode: the page counts the episodes that reach it, not goal steps
    report["ingest"] |= {"goals_per_1000_steps": 102.2, "episodes_reaching_goal": 3}
    text = antmaze.render(page | {"mazes": {"medium-stitch": report}, "expert": {}, "stamp": {}})
    assert "3 episodes reach their goal" in text and "102.2" not in text


def test_script_writes_each_mazes_report_then_the_page_from_them(tmp_path):
    """`maze`: a maze's report from its data root; `page`: results/antmaze.* from the reports
    alone, so a maze whose data root is gone (another day's run) stays on the page."""
    notes = tmp_path / "notes.json"
    notes.write_text(json.dumps({"medium": ["trained elsewhere"]}))
    reports = tmp_path / "results/antmaze"
    for name in ("large", "medium"):
        root = _maze(tmp_path / name)
        antmaze_report.main(["maze", name, str(root), "--notes", str(notes),
                             "--out", str(reports / f"{name}.json")])  # fmt: skip
        shutil.rmtree(root)
    out = tmp_path / "results"
    antmaze_report.main(["page", str(reports / "large.json"), str(reports / "medium.json"),
                         "--out", str(out)])  # fmt: skip
    text = (out / "antmaze.md").read_text()
    assert text.index("## antmaze-medium-navigate") < text.index("## antmaze-large-navigate")
    assert "- trained elsewhere" in text and "maze@medium" in text
    saved = json.loads((out / "antmaze.json").read_text())
    assert list(saved["mazes"]) == ["medium", "large"]
    assert saved["mazes"]["large"]["ingest"]["steps"] == 4004
    assert {r["maze"] for r in saved["runs"]} == {"medium", "large"}
    with pytest.raises(UserError, match="is not one of"):
        antmaze_report.main(["maze", "huge", str(tmp_path), "--out", str(tmp_path / "x.json")])
    with pytest.raises(UserError, match="does not exist"):
        antmaze_report.main(["page", str(reports / "giant.json"), "--out", str(out)])


def test_figure5_is_its_own_report_and_joins_its_maze_on_the_page(tmp_path):
    root = _maze(tmp_path / "large")
    reports = tmp_path / "results/antmaze"
    antmaze_report.main(["maze", "large", str(root), "--out", str(reports / "large.json")])
    fig5 = reports / "large-figure5.json"
    antmaze_report.main(["figure5", "large", str(root), "--out", str(fig5)])
    out = tmp_path / "results"
    antmaze_report.main(["page", str(reports / "large.json"), "--figure5", str(fig5),
                         "--out", str(out)])  # fmt: skip
    saved = json.loads((out / "antmaze.json").read_text())
    claims = [c["claim"] for c in saved["verdicts"]["large"]]
    assert any("mass changes" in c for c in claims) and any("table 1" in c for c in claims)
    assert saved["mazes"]["large"]["figure5"]["mass_sweep"]["expert"]["0.5"]["successes"] == 5
    antmaze_report.main(["maze", "medium", str(root), "--out", str(reports / "medium.json")])
    with pytest.raises(UserError, match="no maze report beside it"):  # a sweep needs its maze
        antmaze_report.main(["page", str(reports / "medium.json"), "--figure5", str(fig5),
                             "--out", str(out)])  # fmt: skip
    with pytest.raises(UserError, match="no mass"):  # a root without a sweep
        antmaze_report.main(["figure5", "large", str(tmp_path / "empty"), "--out", str(fig5)])


def test_a_corrupt_report_is_a_one_line_error_naming_it(tmp_path):
    bad = tmp_path / "ant/reports/ingest/report.json"
    bad.parent.mkdir(parents=True)
    bad.write_text("{not json")
    result = subprocess.run(
        [sys.executable, str(ROOT / "cli.py"), "report", "antmaze", "maze", "medium",
         str(tmp_path / "ant"), "--out", str(tmp_path / "results/medium.json")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip().count("\n") == 0 and str(bad) in result.stderr
    assert not (tmp_path / "results").exists()  # nothing half-written


def _table3_run(root: Path, method: str, seed: int, successes: int, within: float) -> None:
    run = f"runs/table3-{method}-seed{seed}"
    one = {"tawm_error_mean": 0.5, "tawm_nll": 3.0 - within, "tawm_within_1sigma": within}
    two = {"tawm_error_mean": 0.9, "tawm_nll": 4.0, "tawm_within_1sigma": 0.5}
    validate = {"prior": {"skills_1": one, "skills_2": two}}
    _write(root, f"{run}/reports/validate/report.json", validate)
    _write(root, f"{run}/reports/deploy/report.json",
           _deploy("oposm", [successes] * 5, n=10, max_steps=1000))  # fmt: skip


def test_table3_counts_each_episode_once_and_judges_only_matching_seeds(tmp_path):
    root = _maze(tmp_path / "large")
    for seed in (0, 1, 2):
        _table3_run(root, "em", seed, successes=9, within=0.7 + seed / 100)
        _table3_run(root, "vi", seed, successes=5, within=0.4 + seed / 100)
    reports = tmp_path / "results/antmaze"
    antmaze_report.main(["maze", "large", str(root), "--out", str(reports / "large.json")])
    maze = json.loads((reports / "large.json").read_text())
    assert not any(a["run"].startswith("table3-") for a in maze["agents"])  # not agent rows
    table3 = reports / "large-table3.json"
    antmaze_report.main(["table3", "large", str(root), "--e-kl", "closed_form",
                         "--out", str(table3)])  # fmt: skip
    saved = json.loads(table3.read_text())
    assert saved["episodes_per_run"] == 50  # five tasks of 10, the pooled row not counted again
    assert saved["runs"]["em"]["0"]["success"]["successes"] == 45
    verdicts = {v["claim"].split(", ", 1)[1]: v["verdict"] for v in saved["verdicts"]}
    assert verdicts["OPOSM with EM reaches goals more often than with VI"] == HOLDS
    assert verdicts["VI's TAWM is overconfident: fewer real outcomes within 1 sigma than EM's "
                    "(§2.1, table 3)"] == HOLDS  # fmt: skip
    out = tmp_path / "results"
    antmaze_report.main(["page", str(reports / "large.json"), "--table3", str(table3),
                         "--out", str(out)])  # fmt: skip
    page = json.loads((out / "antmaze.json").read_text())
    assert page["mazes"]["large"]["table3"]["runs"]["vi"]["2"]["success"]["successes"] == 25
    assert page["paper"]["antmaze-large-diverse"]["table3"]["vi"] == [0.583, 0.056]
    assert "Table 3 on this maze" in (out / "antmaze.md").read_text()
    antmaze_report.main(["maze", "medium", str(root), "--out", str(reports / "medium.json")])
    with pytest.raises(UserError, match="table 3 of large has no maze report"):
        antmaze_report.main(["page", str(reports / "medium.json"), "--table3", str(table3),
                             "--out", str(out)])  # fmt: skip
    # a seed that only one method ran: the numbers, no verdict
    shutil.rmtree(root / "runs/table3-vi-seed2")
    antmaze_report.main(["table3", "large", str(root), "--e-kl", "closed_form",
                         "--out", str(table3)])  # fmt: skip
    assert json.loads(table3.read_text())["verdicts"] == []
    with pytest.raises(UserError, match="no table3-"):
        antmaze_report.main(["table3", "large", str(tmp_path / "empty"), "--e-kl", "sampled",
                             "--out", str(table3)])  # fmt: skip


def test_failures_are_sorted_by_what_became_of_each_failed_episode(tmp_path):
    root = _maze(tmp_path / "medium")
    episode = {"agent": "oposm", "task": "ogbench-task1", "steps_to_goal": None, "fell_at": None,
               "min_distance": 9.0}  # fmt: skip
    _write(root, "runs/oposm/reports/deploy/episodes.json", [
        episode | {"steps_to_goal": 400},  # a success within 1000 steps: not a failure
        episode | {"fell_at": 700},  # fell
        episode | {"fell_at": 700, "steps_to_goal": 1500},  # fell first: fell
        episode | {"steps_to_goal": 1500, "min_distance": 0.4},  # late
        episode | {"fell_at": 1600, "min_distance": 3.0},  # near (it fell after step 1000)
        episode | {"min_distance": 4.5},  # far
        episode | {"task": "random_goal", "fell_at": 10},  # not one of OGBench's tasks
        episode | {"agent": "gcbc", "fell_at": 10},  # another agent's
    ])  # fmt: skip
    maze = antmaze.collect(root)
    agents = {a["agent"]: a for a in maze["agents"]}
    assert agents["oposm"]["failures"] == {"fell": 2, "late": 1, "near": 1, "far": 1}
    assert agents["gcbc"]["failures"] is None  # its run has no episode records
    text = "\n".join(antmaze._failure_lines(maze["agents"]))
    assert "| oposm | 5 | 2 | 1 | 1 | 1 |" in text and "gcbc" not in text
    assert antmaze._failure_lines([{"agent": "gcbc", "failures": None}]) == []
