"""A variant of OPOSM on a manipulation dataset: the same data, tasks and episodes, one setting
changed (stage `variant@<key>` of `experiments/manipulation/dvc.yaml`,
`results/manipulation/<key>.json`, rendered as a row of its dataset's table in
results/manipulation.md, with its verdicts and a line on its training).

A variant is a run folder of the dataset's data root, `runs/<run>/`, made by the variant's own
stages (`train_variant`, `validate_variant`, `deploy_variant`): its EM model trained with the
variant's overrides (`settings`, e.g. the paper's model sizes `-S train.z_dim=256 -S
train.hidden=256`), its validation and its deploy on OGBench's five tasks. Its verdicts (rules of
`pipeline.reporting.common`): above every published method (rule 3), and more often than OPOSM's
own run of the dataset, `runs/oposm/` (rule 1, the same episodes).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pipeline.errors import UserError
from pipeline.reporting.common import rate_of, read
from pipeline.reporting.manipulation import (
    DATASETS,
    OVERALL,
    TASKS,
    alternative_verdicts,
    deploy_rows,
    find_agent,
)
from pipeline.reporting.manipulation_ladder import open_loop


def _row(root: Path, run: str, label: str) -> dict[str, Any] | None:
    report = read(root / "runs" / run / "reports" / "deploy" / "report.json")
    if not report or "oposm" not in report.get("by_agent", {}):
        return None
    by_task = report["by_agent"]["oposm"]
    return {
        "agent": label,
        "run": run,
        "episodes_per_task": report["episodes_per_task"],
        "max_steps": report.get("max_steps"),
        "final_distance_mean": by_task[OVERALL].get("final_distance_mean"),
        "tasks": {t: rate_of(by_task[t]) for t in [*TASKS, OVERALL] if t in by_task},
    }


def variant_report(
    dataset: str,
    root: Path,
    run: str,
    label: str,
    what: str,
    settings: str,
    stamp: Mapping[str, Any],
) -> dict[str, Any]:
    """The variant's report from the dataset's data root `root`: its row (run `run`, shown as
    `label`), its training and open-loop summary, its verdicts (`what` names it in the claims)
    against the published table and OPOSM's own run, and the overrides it ran with.

    Raises:
        UserError: an unknown dataset, or a data root without the variant's or OPOSM's deploy.
    """
    if dataset not in DATASETS:
        raise UserError(f"dataset {dataset!r} is not one of {', '.join(DATASETS)}")
    row = _row(root, run, label)
    if row is None:
        raise UserError(
            f"{root / 'runs' / run / 'reports' / 'deploy' / 'report.json'} holds no OPOSM "
            f"episodes; run the variant's deploy first (deploy_variant@<key>)"
        )
    oposm = find_agent({"agents": deploy_rows(root)}, "oposm")
    if oposm is None:
        raise UserError(
            f"{root / 'runs' / 'oposm' / 'reports' / 'deploy'} holds no OPOSM episodes; run "
            f"deploy@{dataset} first"
        )
    reports = root / "runs" / run / "reports"
    validate = read(reports / "validate" / "report.json") or {}
    return {
        "dataset": dataset,
        "run": run,
        "label": label,
        "what": what,
        "settings": settings,
        "stamp": dict(stamp),
        "train": read(reports / "train" / "metrics.json"),
        "open_loop": open_loop(validate),
        "agent": row,
        "verdicts": alternative_verdicts(
            dataset, row["tasks"][OVERALL], oposm["tasks"][OVERALL], short=label, what=what,
            baseline="OPOSM with the dataset's own settings (run `oposm`)",
        ),
    }  # fmt: skip
