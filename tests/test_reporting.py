"""pipeline/reporting: the one format of rates and intervals, the verdict rules, the stamp, and
the committed reports being what their committed JSON renders to."""

import json
import math
from pathlib import Path

import yaml

from pipeline.evaluation import published
from pipeline.reporting import common
from pipeline.reporting.common import (
    FAILS,
    HOLDS,
    INCONCLUSIVE,
    above_every,
    above_published,
    cell,
    kept_share,
    mean_interval,
    mean_std,
    off_nominal,
    pct,
    percent,
    points,
    rate,
    reproduces,
    separated,
    versus,
)

ROOT = Path(__file__).resolve().parents[1]


def test_one_format_for_a_rate_its_interval_and_a_difference():
    assert percent(0.965, 0.93, 0.983) == "96.5 [93.0, 98.3]"
    assert percent(0.965, 0.93, 0.983, digits=0) == "96 [93, 98]"
    assert percent(0.5) == "50.0" and percent(None) == "–"
    assert cell(rate(199, 200)) == "99.5 [97.2, 99.9]" and cell(None) == "–"
    assert points([-0.0004, 0.08]) == "[0.0, 8.0]"  # no "-0.0"
    assert pct(-0.004, 0) == "0" and pct(-0.006, 0) == "-1"
    assert mean_std(0.82, 0.05) == "82 ± 5"


def test_rule_1_and_2_newcombe_intervals_of_a_difference():
    assert versus(rate(199, 200), rate(180, 200))[0] == HOLDS
    assert versus(rate(180, 200), rate(199, 200))[0] == FAILS
    assert versus(rate(190, 200), rate(192, 200))[0] == INCONCLUSIVE
    # a paper's 99.4 % (as 250 episodes): 192/200 is significantly below, 197/200 is not
    assert reproduces(rate(192, 200), 0.994, 250)[0] == FAILS
    assert reproduces(rate(197, 200), 0.994, 250)[0] == HOLDS
    assert reproduces(rate(200, 200), 0.5, 250)[0] == HOLDS  # above the paper: reproduced


def test_rule_3_against_a_published_mean_over_seeds():
    lo, hi = mean_interval(0.82, 0.05, 8)
    assert math.isclose(0.82 - lo, 2.3646 * 0.05 / math.sqrt(8), rel_tol=1e-4) and hi > 0.82
    verdict, (lo, hi) = above_published(rate(249, 250), 0.82, 0.05, 8)
    assert verdict == HOLDS and 0.1 < lo < hi < 0.25
    assert above_published(rate(200, 250), 0.80, 0.12, 8)[0] == INCONCLUSIVE
    assert above_published(rate(0, 250), 0.63, 0.06, 8)[0] == FAILS
    row = published.OGBENCH["pointmaze-medium-navigate"]
    assert above_every(rate(249, 250), row, published.OGBENCH_SEEDS)[:2] == (HOLDS, "QRL")
    word, method, _ = above_every(rate(150, 250), row, published.OGBENCH_SEEDS)  # 60 %
    assert (word, method) == (FAILS, "QRL")  # below QRL's 82 and HIQL's 79: QRL decides
    assert above_every(rate(210, 250), row, published.OGBENCH_SEEDS)[:2] == (INCONCLUSIVE, "QRL")


def test_rule_4_per_seed_values_and_rule_5_pooled_off_the_nominal_factor():
    assert separated([0.6, 0.7, 0.65], [0.4, 0.5, 0.45]) == HOLDS
    assert separated([0.4, 0.5], [0.6, 0.7]) == FAILS
    assert separated([0.4, 0.7], [0.6, 0.5]) == INCONCLUSIVE
    ours = {"0.5": rate(90, 100), "1.0": rate(98, 100), "2.0": rate(85, 100)}
    theirs = {0.5: rate(60, 100), 1.0: rate(99, 100), 2.0: rate(40, 100)}
    assert off_nominal(ours)["successes"] == 175 and off_nominal({"1.0": rate(1, 2)}) is None
    assert versus(off_nominal(ours), off_nominal(theirs))[0] == HOLDS
    assert math.isclose(kept_share(ours), 0.875 / 0.98) and kept_share({1.0: rate(0, 5)}) is None


def test_the_stamp_names_the_commit_machine_and_the_dvc_lock(tmp_path):
    lock = {"stages": {"a@x": {"cmd": "oposm a"}, "report": {"cmd": "python r.py"}}}
    (tmp_path / "exp").mkdir()
    (tmp_path / "exp/dvc.lock").write_text(yaml.safe_dump(lock))
    env = {"DVC_STAGE": "exp/dvc.yaml:report", "DVC_ROOT": str(tmp_path)}
    stamp = common.stamp(ROOT, env)
    assert stamp["commit"] and "cores" in stamp["machine"]
    assert stamp["dvc"]["stage"] == "exp/dvc.yaml:report" and stamp["dvc"]["lock"] == "exp/dvc.lock"
    digest = stamp["dvc"]["upstream_sha256"]
    lock["stages"]["report"]["cmd"] = "changed"  # the stage's own entry is not part of it
    (tmp_path / "exp/dvc.lock").write_text(yaml.safe_dump(lock))
    assert common.lock_digest(tmp_path / "exp/dvc.lock", exclude="report") == digest
    lock["stages"]["a@x"]["cmd"] = "changed"
    (tmp_path / "exp/dvc.lock").write_text(yaml.safe_dump(lock))
    assert common.lock_digest(tmp_path / "exp/dvc.lock", exclude="report") != digest
    main = common.dvc_stamp({"DVC_STAGE": "train", "DVC_ROOT": str(tmp_path)})
    assert main == {"stage": "train", "lock": "dvc.lock", "upstream_sha256": None}
    assert common.dvc_stamp({}) is None
    text = common.stamp_text(stamp)
    assert text.startswith(f"assembled on {stamp['machine']}, code at commit {stamp['commit']}")
    said = "DVC stage `exp/dvc.yaml:report` from the other entries of exp/dvc.lock"
    assert f"{said} (sha256 {digest[:12]})" in text
    assert common.stamp_text({"machine": "m", "commit": "c"}) == "assembled on m, code at commit c"


def test_the_committed_reports_are_what_their_json_renders_to():
    """results/experiments.md and results/ogbench-point.md: edit the code, not the text."""
    from pipeline.reporting.ogbench_point import published_json, render
    from stages.experiments_report import markdown

    results = json.loads((ROOT / "results/experiments.json").read_text())
    assert markdown(results) == (ROOT / "results/experiments.md").read_text()
    point = json.loads((ROOT / "results/ogbench-point.json").read_text())
    text = render(point["runs"], point["commands"], point["machine"], point["stamp"],
                  point.get("not_run", []))  # fmt: skip
    assert text == (ROOT / "results/ogbench-point.md").read_text()
    assert point["published"] == published_json() and point["published"]["giant"]["QRL"] == [68, 7]
