"""The agents `oposm deploy` runs, built from their models and the deploy params.

`build_agent(name, ...)` loads what agent `name` needs (the skill model, the single-step model and
BC policy, the GCBC policy, the ant expert's actor) and checks it against the segments and the
environment; a missing model names the stage that makes it. `AgentSetup` is the built agent with
how often it replans and what the report says about it.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.ant_expert.actor import load_actor
from pipeline.config import Params
from pipeline.envs.kitchen import KitchenSpec
from pipeline.envs.manipspace.env import ManipSpaceSpec
from pipeline.envs.maze.expert import ExpertConfig
from pipeline.envs.ogbench import OGBenchMazeSpec
from pipeline.envs.ogbench_oracle import POINT_NOISE, OGBenchOracleAgent
from pipeline.envs.perturb import scale_mass
from pipeline.envs.spec import EnvSpec
from pipeline.errors import UserError
from pipeline.evaluation.compat import check_model_dims, check_same_environment
from pipeline.model.checkpoint import load_dynamics, load_model, load_policy, skill_horizon
from pipeline.paths import Paths
from pipeline.planning.agents import Agent, ExpertAgent, PolicyAgent
from pipeline.planning.llp import LowLevelMPC, LowLevelPlanner
from pipeline.planning.mpc import SkillMPC
from pipeline.planning.settings import llp_config, planner_config
from pipeline.planning.simulated import SimulatedRollout, SimulatedSkillMPC, SimulatorPlanner
from pipeline.planning.skills import SkillPlanner
from pipeline.planning.subgoals import StuckWatch, SubgoalGraph
from pipeline.planning.subtasks import ObjectSubtasks
from pipeline.planning.support import SkillSupport
from pipeline.segments import Segments
from pipeline.value.network import load_value

log = logging.getLogger(__name__)

# Environments whose goals are object configurations, not places in a maze.
OBJECT_GOALS = (ManipSpaceSpec, KitchenSpec)


@dataclass
class AgentSetup:
    """An agent ready to run: how often it replans and what the report says about it."""

    agent: Agent
    replan_every: int | None
    about: dict[str, Any] = field(default_factory=dict)
    plan_state_steps: int | None = None  # environment steps per predicted plan state
    count_flops: bool = True  # the report counts a replan's matrix-product FLOPs


def _check(meta: dict, segments: Segments, spec: EnvSpec, dims: tuple[int, int], what: str):
    check_same_environment(segments.info, meta, what)
    check_model_dims(*dims, spec, what)


def _skill_model(params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device):
    """The skill model of `data/models/<name>/`, its metadata and folder, checked against the
    segments and the environment."""
    cfg, name = params.deploy, params.ingest.name
    model_dir = paths.existing(paths.model(name))
    model, meta = load_model(model_dir, device=device)
    what = f"the model in {model_dir}"
    _check(meta, segments, spec, (model.config.state_dim, model.config.action_dim), what)
    if segments.info.name != meta.get("dataset"):
        raise UserError(
            f"{paths.segments(name)} holds dataset '{segments.info.name}' but the model was "
            f"trained on '{meta.get('dataset')}'; re-run `oposm train`"
        )
    if cfg.planner.kernel == "triton" and device.type != "cuda":
        raise UserError(
            f"deploy.planner.kernel: triton runs on a CUDA GPU, but deploy.device is "
            f"{device.type}; set deploy.planner.kernel=torch"
        )
    return model, meta, model_dir


def _oposm(params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device) -> AgentSetup:
    cfg = params.deploy
    model, meta, model_dir = _skill_model(params, paths, segments, spec, device)
    support = None
    if cfg.planner.support_weight or cfg.planner.data_skills:
        p = cfg.planner
        quantile = p.support_quantile if p.support_weight else None  # the margin: the penalty's
        support = SkillSupport.from_segments(model, segments, p.support_windows, quantile)
        log.info("support bank: %d (state, skill) pairs of the training windows, margin %.3f",
                 len(support.bank), support.margin)  # fmt: skip
    planner = SkillPlanner(model, planner_config(cfg.planner), support)
    subgoals = None
    if cfg.subgoals.enabled and isinstance(spec, OBJECT_GOALS):
        raise UserError(
            f"deploy.subgoals: the subgoal graph is a maze's (cells of the plane); {spec.env_id} "
            "plans to its object goals directly: set deploy.subgoals.enabled=false"
        )
    if cfg.subgoals.enabled:
        sub = cfg.subgoals
        subgoals = SubgoalGraph.from_segments(
            segments, spec.goal_dims, sub.cell, sub.reach, device, line_of_sight=sub.line_of_sight
        )
        log.info("subgoal graph: %d nodes (cells of %g m), reach %d skills%s%s",
                 len(subgoals.nodes), sub.cell, sub.reach,
                 ", line of sight" if sub.line_of_sight else "",
                 f", once {sub.patience} replans bring no {sub.progress} m closer"
                 if sub.patience else "")  # fmt: skip
    stuck = None
    if subgoals is not None and cfg.subgoals.patience is not None:
        stuck = StuckWatch(cfg.subgoals.patience, cfg.subgoals.progress)
    subtasks = None
    if cfg.object_subtasks:
        if not isinstance(spec, ManipSpaceSpec):
            raise UserError(
                f"deploy.object_subtasks plans an OGBench manipulation goal one object at a "
                f"time; {spec.env_id} has no such goal: set deploy.object_subtasks=false"
            )
        subtasks = ObjectSubtasks(spec.goal_objects, spec.goal_scale)
        log.info("one object at a time: %d objects in the goal", len(subtasks.objects))
    skill_steps = skill_horizon(meta, model_dir)
    value, value_info = _value(params, paths, segments, spec, device, skill_steps)
    return AgentSetup(
        SkillMPC(
            model,
            planner,
            cfg.sample_actions,
            spec.goal_dims,
            subgoals,
            getattr(spec, "fallen", None),
            getattr(spec, "goal_scale", None),
            value,
            subtasks,
            stuck,
        ),  # fmt: skip
        _tau(cfg.replan_every, skill_horizon(meta, model_dir)),
        {"model": str(model_dir), "model_step": meta.get("step"), **_planner_settings(cfg.planner)}
        | (
            {f"subgoals_{k}": v for k, v in _subgoal_settings(cfg.subgoals).items()}
            if subgoals
            else {}
        )
        | ({"object_subtasks": True} if subtasks else {})
        | value_info,
        plan_state_steps=skill_horizon(meta, model_dir),  # a skill
    )


def _planner_settings(planner) -> dict:
    """`deploy.planner` as the report names it; the support bank's settings only when the cost
    uses it (reports from before they existed read the same)."""
    settings = planner.model_dump()
    if not (planner.support_weight or planner.data_skills):
        for key in ("support_weight", "support_windows", "support_quantile"):
            del settings[key]
    if not planner.data_skills:
        del settings["data_skills"]
    return settings


def _subgoal_settings(sub) -> dict:
    """`deploy.subgoals` as the report names it; `patience` and `progress` only when the graph
    waits for a stuck episode (reports from before they existed read the same)."""
    settings = sub.model_dump()
    if sub.patience is None:
        del settings["patience"], settings["progress"]
    return settings


def _tau(replan_every: int | None, skill_steps: int) -> int:
    """Steps of a skill run before the next plan: `deploy.replan_every`, at most the skill's
    length T (a skill is not run beyond the steps it was trained on); None: T."""
    if replan_every is not None and replan_every > skill_steps:
        log.info("deploy.replan_every %d > the skills' %d steps: replanning every %d",
                 replan_every, skill_steps, skill_steps)  # fmt: skip
    return min(replan_every or skill_steps, skill_steps)


def _value(params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device, skill_steps):
    """The learned steps-to-go for the planner's cost (`value.weight > 0`), with what the
    report says of it; (None, {}) for the paper's cost."""
    weight = params.value.weight
    if not weight:
        return None, {}
    value_dir = paths.existing(paths.value(params.ingest.name))
    value, meta = load_value(value_dir, device=device)
    c = value.config
    what = f"the value in {value_dir}"
    _check(meta, segments, spec, (c.state_dim, segments.info.action_dim), what)
    if c.goal_dims != tuple(spec.goal_dims):
        raise UserError(
            f"the value in {value_dir} takes goals in state dims {list(c.goal_dims)}, "
            f"{spec.env_id} gives {list(spec.goal_dims)}; re-run `oposm value`"
        )
    info = {"value": str(value_dir), "value_weight": weight, "value_skill_steps": skill_steps}
    return (value.steps_to_go, weight, skill_steps), info


def _llp(params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device) -> AgentSetup:
    cfg, name = params.deploy.llp, params.ingest.name
    dyn_dir = paths.existing(paths.dynamics(name))
    dynamics, dyn_meta = load_dynamics(dyn_dir, device=device)
    d = dynamics.config
    _check(dyn_meta, segments, spec, (d.state_dim, d.action_dim), f"the model in {dyn_dir}")
    bc_dir = paths.existing(paths.policy(name, "bc"))
    policy, bc_meta = load_policy(bc_dir, "bc", device=device)
    p = policy.config
    _check(bc_meta, segments, spec, (p.state_dim, p.action_dim), f"the policy in {bc_dir}")
    planner = LowLevelPlanner(policy, dynamics, llp_config(cfg))
    return AgentSetup(
        LowLevelMPC(planner, spec.goal_dims, getattr(spec, "goal_scale", None)),
        cfg.execute,
        {"dynamics": str(dyn_dir), "bc": str(bc_dir), **cfg.model_dump()},
        plan_state_steps=1,  # an action
    )


def _gcbc(params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device) -> AgentSetup:
    policy_dir = paths.existing(paths.policy(params.ingest.name, "gcbc"))
    policy, meta = load_policy(policy_dir, "gcbc", device=device)
    p = policy.config
    _check(meta, segments, spec, (p.state_dim, p.action_dim), f"the policy in {policy_dir}")
    if p.goal_dims != tuple(spec.goal_dims):
        raise UserError(
            f"the policy in {policy_dir} takes goals in state dims {list(p.goal_dims)}, "
            f"{spec.env_id} gives {list(spec.goal_dims)}; re-run `oposm gcbc`"
        )
    sample = params.deploy.gcbc.sample_actions
    return AgentSetup(
        PolicyAgent(policy, sample), None, {"policy": str(policy_dir), "sample_actions": sample}
    )


def _ogbench_oracle(params: Params, segments: Segments, spec: EnvSpec) -> AgentSetup:
    """OGBench's data-generating BFS oracle, with the dataset's noise (or deploy.expert's)."""
    noise = params.deploy.expert.action_noise
    recorded = (segments.info.generator or {}).get("noise")
    if noise is None:
        noise = POINT_NOISE if recorded is None else float(recorded)
    source = "deploy.expert" if params.deploy.expert.action_noise is not None else "the dataset's"
    info = {"config": "OGBench's BFS oracle (generate_locomaze.py)", "noise": noise, "from": source}
    actor = None
    if spec.loco == "ant":  # the actor that made the data walks the oracle's directions
        made_with = (segments.info.generator or {}).get("expert") or {}
        path = made_with.get("path", "experts/ant/actor.safetensors")
        actor = load_actor(path)
        if (actor.spec.obs_dim, actor.spec.action_dim) != (spec.state_dim, spec.action_dim):
            raise UserError(f"{path} does not fit {spec.env_id}'s ant; re-run `oposm ingest`")
        digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
        info |= {"actor": str(path), "actor_sha256": digest}
        if made_with.get("sha256") not in (None, digest):
            log.warning("%s is not the actor that made the data (its sha256 differs)", path)
    return AgentSetup(OGBenchOracleAgent(spec.env_id, noise, actor=actor), None, info)


def _expert(params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device) -> AgentSetup:
    if isinstance(spec, KitchenSpec):
        raise UserError(
            f"no expert agent for {spec.env_id}: its data are human demonstrations, with no "
            "controller to run; use oposm, llp or gcbc"
        )
    if isinstance(spec, ManipSpaceSpec):
        raise UserError(
            f"no expert agent for {spec.env_id}: OGBench's manipulation oracles pursue the "
            "subtasks the env draws, not an evaluation task's goal; use oposm, llp or gcbc"
        )
    if isinstance(spec, OGBenchMazeSpec):
        return _ogbench_oracle(params, segments, spec)
    recorded = (segments.info.generator or {}).get("expert")
    config = ExpertConfig(**recorded) if recorded else ExpertConfig()
    if params.deploy.expert.action_noise is not None:
        config.action_noise = params.deploy.expert.action_noise
    source = "the dataset's" if recorded else "D4RL's defaults (the dataset records none)"
    return AgentSetup(
        ExpertAgent(spec.layout, config), None, {"config": source, **config.to_dict()}
    )


def _oposm_sim(
    params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device
) -> AgentSetup:
    """OPOSM's CEM over the same skills, each candidate executed in a copy of the deploy
    environment instead of predicted by the TAWM (`pipeline.planning.simulated`)."""
    cfg = params.deploy
    model, meta, model_dir = _skill_model(params, paths, segments, spec, device)
    if cfg.subgoals.enabled:
        raise UserError(
            "agent oposm_sim plans to the goal itself: set deploy.subgoals.enabled=false"
        )
    config = planner_config(cfg.planner)
    steps = skill_horizon(meta, model_dir)
    rollout = SimulatedRollout(
        model, spec, scale_mass(spec.model, cfg.mass_scale), config.cem.candidates, steps
    )
    agent = SimulatedSkillMPC(
        model, SimulatorPlanner(model, config, rollout), cfg.sample_actions, spec.goal_dims,
        None, getattr(spec, "fallen", None), getattr(spec, "goal_scale", None),
    )  # fmt: skip
    return AgentSetup(
        agent,
        _tau(cfg.replan_every, steps),
        {
            "model": str(model_dir),
            "model_step": meta.get("step"),
            "scored_in": "simulator",
            **_planner_settings(cfg.planner),
        },  # fmt: skip
        plan_state_steps=steps,
        count_flops=False,  # the cost of a plan is simulator steps, not matrix products
    )


BUILDERS = {
    "oposm": _oposm, "oposm_sim": _oposm_sim, "llp": _llp, "gcbc": _gcbc, "expert": _expert,
}  # fmt: skip


def build_agent(
    name: str, params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device
) -> AgentSetup:
    """Load what agent `name` needs and build it; a missing model names the stage to run.

    Raises:
        UserError: an unknown agent (the message lists the valid ones), or its models are
            missing, corrupt or from another environment.
    """
    if name not in BUILDERS:
        raise UserError(f"unknown agent {name!r}; use one of: {', '.join(BUILDERS)}")
    try:
        return BUILDERS[name](params, paths, segments, spec, device)
    except UserError as exc:
        raise UserError(f"agent {name}: {exc}") from exc
