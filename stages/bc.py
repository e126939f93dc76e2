"""BC stage: the Gaussian behaviour-cloning policy p(a | s) on the train split's steps.

Its mean and std whiten the actions the low-level planner (LLP, `deploy.agents: [llp]`) searches
over, as the paper's code does with its `Prior`. Writes `data/models/<name>-bc/` and the report.
`stages/gcbc.py` fits the goal-conditioned policy the same way.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

from pipeline.config import Params, PolicyParams
from pipeline.dataset import DatasetInfo
from pipeline.devices import resolve_device, torch_threads
from pipeline.envs.spec import make_env_spec
from pipeline.errors import UserError
from pipeline.model.checkpoint import save_policy
from pipeline.paths import Paths
from pipeline.segments import load_segments
from pipeline.training.bc import fit_policy
from stages.report import report_files, split_timings, write_report

log = logging.getLogger(__name__)


def _goal_dims(info: DatasetInfo) -> tuple[int, ...]:
    """The state dims a goal gives in the dataset's environment; without a simulator (nothing to
    deploy in) the first two, so that the pipeline still runs end to end."""
    try:
        return make_env_spec(info.env_id, info.env_kwargs).goal_dims
    except UserError as exc:
        log.warning("gcbc: %s; conditioning on the first two state dims", exc)
        return tuple(range(min(2, info.state_dim)))


def fit_and_save(params: Params, paths: Paths, kind: str, cfg: PolicyParams) -> dict[str, Any]:
    """Fit the `kind` policy (`bc`: p(a | s); `gcbc`: p(a | s, g) over the environment's goal
    dims) on `data/segments/<name>/`; write the checkpoint and the report; return the metrics."""
    name = params.ingest.name
    files, folders = report_files(paths, kind), [paths.policy(name, kind)]
    paths.check(files, folders)
    segments = load_segments(paths.existing(paths.segments(name)))
    goal_dims: tuple[int, ...] = ()
    if kind == "gcbc":
        goal_dims = _goal_dims(segments.info)
    device = resolve_device(cfg.device, f"{kind}.device")
    with torch_threads(1 if device.type == "cpu" else None):
        policy, metrics = fit_policy(segments, cfg, device, goal_dims)
    extra = {"dataset": segments.info.name, "info": dataclasses.asdict(segments.info)}
    with paths.staged(files, folders) as out:  # the policy and its report together
        kept = split_timings(metrics)[0]  # the checkpoint's bytes: not its wall time
        save_policy(policy, out.folder(paths.policy(name, kind)), kind, extra | {"metrics": kept})
        write_report(paths, kind, metrics | {"device": str(device)}, out)
    log.info(
        "%s policy: val NLL %.3f, action RMSE %.3f after %d steps (%.0f s) -> %s",
        kind,
        metrics["val_nll"],
        metrics["val_action_rmse"],
        metrics["steps"],
        metrics["wall_s"],
        paths.policy(name, kind),
    )
    return metrics


def run(params: Params, paths: Paths) -> dict[str, Any]:
    """Fit p(a | s) (`params.bc`)."""
    return fit_and_save(params, paths, "bc", params.bc)
