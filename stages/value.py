"""Value stage: the goal-conditioned value V(s, g) on the train split (`pipeline.value`).

The success rule that ends an episode in its targets is the environment's own (OGBench's
manipulation: every cube within 0.04 m, the scene's parts in place; a maze: within
`deploy.success_radius` of the goal's x-y). Writes `data/models/<name>-value/` and the report;
`value.weight > 0` makes OPOSM's planner use it.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from pipeline.config import Params
from pipeline.devices import resolve_device, torch_threads
from pipeline.envs.spec import make_env_spec
from pipeline.evaluation.goals import GoalRule
from pipeline.paths import Paths
from pipeline.segments import load_segments
from pipeline.value.fit import Reached, fit_value, spearman_text
from pipeline.value.network import save_value
from stages.report import report_files, split_timings, write_timings

log = logging.getLogger(__name__)


def success_rule(rule: GoalRule, radius: float) -> Reached:
    """`(states [N, sd], goals [N, G]) -> bool [N]`: the environment's rule, or within `radius`."""
    if rule.reached is not None:
        return lambda states, goals: np.asarray(rule.reached(states, goals), dtype=bool)
    dims = list(rule.dims)
    return lambda states, goals: np.linalg.norm(states[:, dims] - goals, axis=-1) <= radius


def _headline(report: dict[str, Any]) -> dict[str, Any]:
    """What `metrics/value.json` shows: the held-out steps-to-go error and rank correlation."""
    keys = ("val_steps_to_go_mae", "val_steps_to_go_spearman", "val_td_loss")
    return {k: None if report[k] is None else round(report[k], 4) for k in keys}


def run(params: Params, paths: Paths) -> dict[str, Any]:
    """Fit V(s, g) (`params.value`) over the environment's goal dims."""
    name, cfg = params.ingest.name, params.value
    files, folders = report_files(paths, "value"), [paths.value(name)]
    paths.check(files, folders)
    segments = load_segments(paths.existing(paths.segments(name)))
    spec = make_env_spec(segments.info.env_id, segments.info.env_kwargs)
    rule = GoalRule.of_spec(spec)
    device = resolve_device(cfg.device, "value.device")
    with torch_threads(1 if device.type == "cpu" else None):
        value, metrics = fit_value(
            segments, cfg, device, rule.dims, success_rule(rule, params.deploy.success_radius)
        )
    extra = {"dataset": segments.info.name, "info": dataclasses.asdict(segments.info)}
    with paths.staged(files, folders) as out:  # the value and its report together
        kept = split_timings(metrics)[0]  # the checkpoint's bytes: not its wall time
        save_value(value, out.folder(paths.value(name)), extra | {"metrics": kept})
        report, timings = split_timings(metrics | {"device": str(device)})
        out.write_json(paths.report("value"), report)
        out.write_json(paths.metrics("value"), _headline(report))
    write_timings(paths, "value", timings)
    log.info(
        "value: steps to go MAE %.1f (Spearman %s) on held-out goals after %d steps -> %s",
        metrics["val_steps_to_go_mae"], spearman_text(metrics["val_steps_to_go_spearman"]),
        metrics["steps"], paths.value(name),
    )  # fmt: skip
    return metrics
