"""Typed params: one pydantic model per stage, matching the sections of `params.yaml` one to one.

Every model forbids unknown keys, so a typo in `params.yaml` (or in a `--set` override) is an error
that names the key instead of a silently ignored setting. The models are the one source of every
default: `params.yaml` spells each of them out, and the library's configs take every value from
these models (`pipeline.planning.settings`, `pipeline.model.settings`, `updater_for`).

A params variant (`params-paper.yaml`, `params-ogbench-*.yaml`) is an overlay: its first key,
`extends: <file>` (relative to the variant), names the file it builds on, and it holds only the
keys that differ. Loading merges it onto its base (`read_params_file`), then applies the `-S`
overrides, then validates; the experts' params files load the same way (`load_model_file`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from pipeline.envs.ids import MANIPSPACE_ENVS, OGBENCH_MAZES, SUPPORTED_ENVS
from pipeline.envs.maze.expert import ExpertConfig
from pipeline.errors import UserError


class _Section(BaseModel):
    # No float param can take inf or nan (a learning rate of inf trains nothing): refused.
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


class LeRobotSourceParams(_Section):
    """`ingest.lerobot`: a LeRobot v3.0 dataset (`ingest.source: lerobot`)."""

    repo_id: str = Field(
        "local/demos",
        description="Hugging Face repo id (user/name): fetched from the hub unless `root` or "
        "$HF_LEROBOT_HOME/<repo_id> holds it; only a label when `root` is set.",
    )
    root: str | None = Field(None, description="Local dataset folder (holding meta/info.json).")
    state_features: list[str] = Field(
        default_factory=lambda: ["observation.state"],
        min_length=1,
        description="Numeric features concatenated, in this order, into the state.",
    )
    action_feature: str = Field("action", description="The action feature.")


class D4RLSourceParams(_Section):
    """`ingest.d4rl`: a D4RL hdf5 file (`ingest.source: d4rl`)."""

    path: str | None = Field(None, description="The .hdf5 file.")
    env_id: Literal[("", *SUPPORTED_ENVS)] = Field(  # type: ignore[valid-type]
        "",
        description="For maze2d files, the PointMaze of the same map: coordinates are converted "
        "to gymnasium-robotics' and the data becomes simulatable. Empty for other files.",
    )
    control_period: float | None = Field(
        None, gt=0, description="Seconds per step; default the maze's dt (required for non-mazes)."
    )


class MinariSourceParams(_Section):
    """`ingest.minari`: a local Minari dataset (`ingest.source: minari`)."""

    dataset_id: str | None = Field(
        None, description="Minari id, looked up under MINARI_DATASETS_PATH (~/.minari/datasets)."
    )
    path: str | None = Field(None, description="The dataset folder, instead of an id.")
    state_keys: list[str] = Field(
        default_factory=lambda: ["observation"],
        description="Observation dict keys concatenated into the state; [] for array observations.",
    )
    action_key: str | None = Field(None, description="Key of a dict action space; null for arrays.")
    goal_key: str | None = Field(
        "desired_goal", description="Observation dict key recorded as the goal, when present."
    )
    control_period: float | None = Field(
        None, gt=0, description="Seconds per step; default the environment's dt."
    )


class DisturbanceParams(_Section):
    """Random external pushes on the agent: uncontrolled stochasticity (`pipeline.envs.
    disturbance`); recorded with the data, and validate and deploy run the same process."""

    probability: float = Field(0.0, ge=0, le=1, description="Chance of a push per control step.")
    impulse: float = Field(
        0.0, ge=0, description="N s per push, random direction (4.2 = 1 m/s for the 4.19 kg point)."
    )


class OGBenchSourceParams(_Section):
    """`ingest.ogbench`: OGBench data (`ingest.source: ogbench`), generated with OGBench's
    recipe (sizes: `ingest.episodes` x `ingest.episode_steps`, `ingest.seed`; ant mazes with
    our ant expert; manipulation with OGBench's scripted oracles) or imported from a downloaded
    `.npz` (`path`; manipulation: states restored from its qpos / qvel)."""

    env_id: Literal[(*OGBENCH_MAZES, *MANIPSPACE_ENVS)] = Field(  # type: ignore[valid-type]
        "pointmaze-medium-v0",
        description="The OGBench env: pointmaze-* or antmaze-* (medium, large, giant, "
        "teleport), or a manipulation env (cube-single-v0, cube-double-v0, scene-v0, "
        "puzzle-3x3-v0 ... puzzle-4x6-v0).",
    )
    dataset_type: Literal["navigate", "stitch", "explore", "play", "noisy"] = Field(
        "navigate",
        description="OGBench's recipe. Mazes: navigate (new goal on reach), stitch (goals 4 "
        "cells away), explore (random directions); manipulation: play (plan oracles, smoothed "
        "noise) or noisy (Markov oracles, Gaussian noise, 10 % random actions; puzzles 20 %).",
    )
    noise: float | None = Field(
        None,
        ge=0,
        description="Action noise std; null: OGBench's (point 0.5, ant 0.2; explore 1.0; "
        "manipulation 0.1: play's plan noise, noisy's largest per-episode std).",
    )
    expert: str | None = Field(
        None,
        description="Ant mazes: the ant expert's actor (.safetensors, its .json beside it), "
        "e.g. experts/ant/actor.safetensors; null for point mazes.",
    )
    max_fallen_share: float = Field(
        0.15,
        ge=0,
        le=1,
        description="Ant data: largest share of steps with the ant fallen (torso height "
        "outside [0.2, 1.0] m or upside down) that the ingest checks accept (our expert with "
        "OGBench's noise 0.2: 8.6 % on antmaze-medium-navigate, 1.8 % on large).",
    )
    path: str | None = Field(
        None, description="An OGBench .npz to import instead of generating; null: generate."
    )
    include_val: bool = Field(
        True, description="Also import the file's -val.npz companion, when it is there."
    )
    workers: int = Field(
        1,
        ge=1,
        description="Processes generating episodes (the data do not depend on it: each episode "
        "is a function of its own seed).",
    )


class IngestParams(_Section):
    """`oposm ingest`: demonstrations into `data/demos/<name>.mcap`."""

    name: str = Field(
        "pointmaze-medium",
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$",
        description="Dataset name: the MCAP file stem and the segments directory name.",
    )
    source: Literal["maze", "lerobot", "d4rl", "minari", "ogbench"] = Field(
        "maze",
        description="Where demonstrations come from: the built-in expert (maze), OGBench's "
        "recipe or file (ogbench), or an import.",
    )
    env_id: Literal[tuple(SUPPORTED_ENVS)] = Field(  # type: ignore[valid-type]
        "PointMaze_Medium-v3", description="Gymnasium-robotics maze the expert drives in."
    )
    episodes: int = Field(200, ge=1, description="Number of episodes to record.")
    episode_steps: int = Field(1000, ge=2, description="Steps per episode.")
    seed: int = Field(0, description="Seed of the expert, the noise and the start state.")
    expert: ExpertConfig = Field(
        default_factory=ExpertConfig, description="The scripted waypoint expert (D4RL maze2d)."
    )
    disturbance: DisturbanceParams = Field(
        default_factory=DisturbanceParams, description="Random pushes (source: maze only)."
    )
    lerobot: LeRobotSourceParams = Field(default_factory=LeRobotSourceParams)
    d4rl: D4RLSourceParams = Field(default_factory=D4RLSourceParams)
    minari: MinariSourceParams = Field(default_factory=MinariSourceParams)
    ogbench: OGBenchSourceParams = Field(default_factory=OGBenchSourceParams)


class SplitParams(_Section):
    """Fractions of episodes per split; they must sum to 1."""

    train: float = Field(0.8, ge=0, le=1)
    validation: float = Field(0.1, ge=0, le=1)
    test: float = Field(0.1, ge=0, le=1)

    @model_validator(mode="after")
    def _sums_to_one(self) -> SplitParams:
        total = self.train + self.validation + self.test
        if abs(total - 1.0) > 1e-6:
            raise ValueError(f"split fractions must sum to 1, got {total:g}")
        if self.train <= 0:
            raise ValueError("the train split must get some episodes (train > 0)")
        return self


class SegmentParams(_Section):
    """`oposm segment`: sub-trajectory windows, splits and normalization statistics."""

    window: int = Field(
        40, ge=2, description="States per window, T + 1 (the paper uses 40 for mazes)."
    )
    stride: int = Field(1, ge=1, description="Steps between consecutive window starts.")
    split: SplitParams = Field(default_factory=SplitParams)
    seed: int = Field(0, description="Seed of the episode shuffle that assigns splits.")
    exclude_fallen: bool = Field(
        False,
        description="Drop the windows in which the agent has fallen at any step (the ant: torso "
        "out of its healthy height or upside down, which it cannot undo); false: keep all.",
    )


class TrainParams(_Section):
    """`oposm train`: EM training of the skill model (paper §2.1, appendix C.5)."""

    method: Literal["em", "vi"] = Field(
        "em", description="em: the paper's EM (eqs. 15-16); vi: the naive joint ELBO (eq. 1)."
    )
    z_dim: int = Field(16, ge=1, description="Skill latent size (paper: 256).")
    hidden: int = Field(128, ge=1, description="Width of every hidden layer (paper: 256).")
    tawm_shared_std: bool = Field(
        True, description="One scalar s_T std for all state dims (paper, mazes) vs per dim."
    )
    tawm_components: int = Field(
        1,
        ge=1,
        description="Gaussians in the TAWM p(s_T | s_0, z): 1 is the paper's; K > 1 a mixture "
        "of K (a mixture density network), for skills whose outcome has several modes (a grasp "
        "that holds or slips: one Gaussian's mean lies between them). The planner chains the "
        "most probable component's mean.",
    )
    tawm_residual: bool = Field(
        False,
        description="false: the paper's TAWM, whose mean of s_T comes straight from (s_0, z). "
        "true (not the paper's): the mean is s_0 plus the network's output (normalized units), "
        "as a single-step model predicts a change: an object a skill does not touch is "
        "predicted where it stands, where the paper's network must learn to copy it, and its "
        "small copying errors add up over a chain of skills.",
    )
    tawm_chain: int = Field(
        1,
        ge=1,
        description="Skills the TAWM is trained to chain: 1 is the paper's (p(s_T | s_0, z) of "
        "one window). K > 1: windows of K consecutive skills, the M-step's TAWM term averaged "
        "over the K outcomes, each predicted from the TAWM's own previous prediction (the "
        "planner's chain), so it learns from its own errors (`pipeline/training/losses.py`).",
    )
    encoder: Literal["gru", "conv"] = Field(
        "conv",
        description="The skill posterior's network over a window: conv (strided 1-D "
        "convolutions, not the paper's: EM about 2x faster on CPU, the same deploy success on "
        "seeds 0-9, docs/performance.md) or gru (appendix C.1's bidirectional GRU).",
    )
    min_std: float = Field(1e-4, gt=0, description="Floor added to every predicted std.")
    batch_size: int = Field(100, ge=1, description="Windows per update step (paper: 100).")
    action_likelihood: Literal["gaussian", "censored"] = Field(
        "gaussian",
        description="The policy's likelihood of an action. censored: actions at the data's "
        "bounds (each dim's min and max, where clipped actions pile up) are scored as the "
        "probability beyond the bound, a Gaussian density inside; gaussian: the density "
        "everywhere (the paper's), which rewards a std shrinking without limit on clipped "
        "actions (results/em-trace-*.md).",
    )
    policy_trunk: Literal["relu", "layernorm_silu"] = Field(
        "relu",
        description="The policy's two hidden layers: relu (appendix C) or layernorm_silu "
        "(LayerNorm + SiLU, as DreamerV3 and TD-MPC2). Prior and TAWM stay appendix C's.",
    )
    policy_ignore_dims: list[int] = Field(
        default_factory=list,
        description="State dims the low-level policy does not see (the posterior, prior and "
        "TAWM see all): where the state gives the next action away without the skill (an "
        "arm's joint velocities under a position controller, docs/manipulation.md), the skill "
        "must carry it. []: the paper's policy, which sees the whole state.",
    )
    e_kl: Literal["sampled", "closed_form"] = Field(
        "sampled",
        description="The E-step's KL(q || prior). sampled: log q - log p at the drawn skill (eq. "
        "15 as the paper's code computes it); closed_form: the two Gaussians' KL, as vi "
        "computes it (the same objective with less noise; em only).",
    )
    e_prior: Literal["ema", "current"] = Field(
        "ema",
        description="The prior the E-step holds the posterior to. ema: a copy averaged over "
        "the last ~1/prior_ema M-steps, so posterior and prior cannot drift off together "
        "(results/stability-cpu.md); current: the prior as the last M-step left it (the "
        "paper's, which collapses on some seeds). em only.",
    )
    prior_ema: float = Field(
        0.01, gt=0, le=1, description="Per-step rate of the E-step's prior average (e_prior: ema)."
    )
    lr_e: float = Field(2.5e-4, gt=0, description="Adam learning rate of the E-step (paper: 5e-5).")
    lr_m: float = Field(
        2.5e-4, gt=0, description="Adam learning rate of the M-step and of vi (paper: 5e-5)."
    )
    grad_clip: float | None = Field(
        None, gt=0, description="Clip each step's gradient norm to this; null: no clipping."
    )
    max_steps: int = Field(5000, ge=1, description="Update steps (E+M pairs) in total.")
    max_minutes: float | None = Field(
        None, gt=0, description="Wall-clock budget in minutes over resumed runs; null: none."
    )
    eval_every: int = Field(250, ge=1, description="Steps between validations.")
    val_windows: int = Field(2000, ge=1, description="Validation windows (a fixed subset).")
    select: Literal["st_nll", "st_nll_prior"] = Field(
        "st_nll_prior",
        description="The validation metric that picks the published checkpoint. st_nll: s_T NLL "
        "under the posterior skill; st_nll_prior: s_T NLL with the skill drawn from the prior, "
        "as the planner draws it. The best of each is also kept in models/<name>/by/<metric>/.",
    )
    divergence_margin: float | None = Field(
        1.0,
        gt=0,
        description="A run counts as diverged when its validation `select` metric stays more "
        "than this many nats above its best for `divergence_evals` validations in a row: logged "
        "as a warning and recorded in metrics/train.json (diverged, diverged_step); null: no "
        "check.",
    )
    divergence_evals: int = Field(3, ge=1, description="Validations in a row (see above).")
    checkpoint_every: int = Field(250, ge=1, description="Steps between resume-state saves.")
    seed: int = Field(0, description="Seed of initialization, sampling and noise.")
    threads: int | Literal["auto"] | None = Field(
        "auto",
        description="Torch CPU threads on CPU. auto: every core if nothing else runs as "
        "training starts, else 1 (never slowed down by a busy core); null: torch's default.",
    )

    @field_validator("threads")
    @classmethod
    def _positive_threads(cls, v: int | str | None) -> int | str | None:
        if isinstance(v, int) and v < 1:
            raise ValueError("must be >= 1, auto or null")
        return v

    @model_validator(mode="after")
    def _chain_is_em(self) -> TrainParams:
        if self.tawm_chain > 1 and self.method != "em":
            raise ValueError(
                f"tawm_chain ({self.tawm_chain}) chains the TAWM in EM's M-step; with method "
                f"{self.method} set tawm_chain to 1"
            )
        return self

    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="auto: CUDA when available, else CPU."
    )
    compile: bool = Field(
        False,
        description="torch.compile each step's losses and their backward (same random draws as "
        "eager; compiling takes a minute or more on CPU: for long runs on a GPU).",
    )
    cuda_graph: bool = Field(
        False,
        description="On CUDA, replay each step as CUDA graphs (the same update, without the "
        "host's launch overhead; single process). Ignored on CPU.",
    )
    dtype: Literal["auto", "float32", "bfloat16"] = Field(
        "float32",
        description="What the hidden layers and the posterior's GRU multiply in. bfloat16 "
        "(torch.autocast): 1.9x the steps/s measured on one AVX512-BF16 CPU, 0.5x on another "
        "without AMX; GPUs not yet measured; weights, Adam, output layers, losses and validation "
        "stay float32. auto: bfloat16 on a CPU with AMX-BF16 (Linux's /proc/cpuinfo flags), "
        "else float32; the choice is logged and in metrics/train.json. The two differ in "
        "rounding: a model trained here is the same bits only on a CPU of the same kind.",
    )


class DynamicsParams(_Section):
    """`oposm dynamics`: the single-step model p(s_{t+1} | s_t, a_t) (paper §4.1, LLP baseline)."""

    hidden: int = Field(128, ge=1, description="Width of every hidden layer.")
    min_std: float = Field(1e-4, gt=0, description="Floor added to the predicted std.")
    batch_size: int = Field(256, ge=1, description="Transitions per Adam step.")
    lr: float = Field(1e-3, gt=0, description="Adam learning rate.")
    max_steps: int = Field(10000, ge=1, description="Adam steps.")
    eval_every: int = Field(1000, ge=1, description="Steps between validations (best kept).")
    val_transitions: int = Field(5000, ge=1, description="Validation transitions (fixed subset).")
    seed: int = Field(0, description="Seed of initialization and sampling.")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="auto: CUDA when available, else CPU."
    )


class PolicyParams(_Section):
    """What `bc` and `gcbc` share: a Gaussian MLP policy fit by maximum likelihood."""

    hidden: int = Field(128, ge=1, description="Width of every hidden layer.")
    min_std: float = Field(1e-4, gt=0, description="Floor added to the predicted std.")
    learned_std: bool = Field(
        True, description="Predict the action std; false: fixed at 1 (normalized units)."
    )
    batch_size: int = Field(256, ge=1, description="Steps per Adam step.")
    lr: float = Field(1e-3, gt=0, description="Adam learning rate.")
    max_steps: int = Field(5000, ge=1, description="Adam steps.")
    eval_every: int = Field(1000, ge=1, description="Steps between validations (best kept).")
    val_transitions: int = Field(5000, ge=1, description="Validation steps (a fixed subset).")
    seed: int = Field(0, description="Seed of initialization, sampling and goals.")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="auto: CUDA when available, else CPU."
    )


class BCParams(PolicyParams):
    """`oposm bc`: the Gaussian BC policy p(a | s) whose mean and std whiten LLP's actions
    (paper §4.2; the paper code: h 512, lr 1e-4, batch 100)."""


class GCBCParams(PolicyParams):
    """`oposm gcbc`: goal-conditioned BC p(a | s, g), hindsight goals as OGBench's GCBC (its
    defaults, `impls/agents/gcbc.py`: 3 x 512 GELU MLP on the raw observation and goal, constant
    std 1, lr 3e-4, batch 1024, 1M steps, the final parameters evaluated)."""

    learned_std: bool = Field(
        False, description="Predict the action std; false: fixed at 1 (OGBench: const_std)."
    )
    normalize: bool = Field(
        True,
        description="Whiten states, goals and actions with the train statistics; false: raw "
        "units, as OGBench's GCBC (its constant std is then 1 raw action unit).",
    )
    keep: Literal["best", "last"] = Field(
        "best",
        description="Parameters kept: best validation NLL, or the last step's (OGBench's).",
    )


class ValueParams(_Section):
    """`oposm value`: a goal-conditioned value V(s, g) learned offline (GCIVL: OGBench's implicit
    value learning, its defaults `impls/agents/gcivl.py` except the width and steps, sized for a
    CPU), and its use by OPOSM's planner (`weight`). Not in the paper: with `weight` 0 (the
    default) the planner's cost is the paper's and the value is not loaded."""

    weight: float = Field(
        0.0,
        ge=0,
        description="Goal units the planner's cost adds per skill still to go after each "
        "predicted state (the value's steps to go / T, plus the skills used): 0: the paper's "
        "cost, no value needed; > 0: run `oposm value` first.",
    )
    hidden: int = Field(256, ge=1, description="Width of every hidden layer (OGBench: 512).")
    layers: int = Field(3, ge=1, description="Hidden layers per head (OGBench: 3).")
    heads: int = Field(2, ge=1, description="Independent value heads (OGBench: 2).")
    discount: float = Field(0.99, gt=0, lt=1, description="Discount (OGBench: 0.99).")
    expectile: float = Field(
        0.9, gt=0, lt=1, description="Expectile of the in-sample maximum (OGBench: 0.9)."
    )
    tau: float = Field(0.005, gt=0, le=1, description="Target network's Polyak rate.")
    p_current: float = Field(
        0.2, ge=0, le=1, description="Share of goals that are the step itself (OGBench: 0.2)."
    )
    p_trajectory: float = Field(
        0.5,
        ge=0,
        le=1,
        description="Share of goals a geometric number of steps later in the same episode "
        "(OGBench: 0.5); the rest are random train steps.",
    )
    batch_size: int = Field(256, ge=1, description="Transitions per Adam step (OGBench: 1024).")
    lr: float = Field(3e-4, gt=0, description="Adam learning rate (OGBench: 3e-4).")
    max_steps: int = Field(20000, ge=1, description="Adam steps (OGBench: 1M).")
    eval_every: int = Field(2000, ge=1, description="Steps between validations.")
    val_transitions: int = Field(2000, ge=1, description="Validation transitions (fixed).")
    eval_horizon: int = Field(
        200, ge=1, description="Validation goals lie 1 to this many steps ahead."
    )
    seed: int = Field(0, description="Seed of initialization, sampling and goals.")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="auto: CUDA when available, else CPU."
    )

    @model_validator(mode="after")
    def _shares(self) -> ValueParams:
        if self.p_current + self.p_trajectory > 1:
            raise ValueError("p_current + p_trajectory must be <= 1")
        return self


class ValidateParams(_Section):
    """`oposm validate`: TAWM vs single-step model on held-out open-loop rollouts (paper §4.1)."""

    starts: int = Field(100, ge=1, description="Held-out start states from test episodes.")
    skills: int = Field(5, ge=1, description="Skills per open-loop sequence (horizons 1..L).")
    repeats: int = Field(4, ge=1, description="Executions of each skill sequence.")
    sample_actions: bool = Field(
        True, description="Sample actions from the policy (true) or take its mean."
    )
    particles: int = Field(64, ge=1, description="Samples propagating TAWM uncertainty.")
    record_starts: int = Field(4, ge=0, description="Start states drawn in the Rerun recording.")
    seed: int = Field(0, description="Seed of starts, prior skills, action noise, particles.")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="auto: CUDA when available, else CPU (the simulator runs on CPU)."
    )


class PlannerParams(_Section):
    """`deploy.planner`: CEM over whitened skill sequences (paper §3, appendix C.6, table 14)."""

    horizon: int = Field(10, ge=1, description="Skills per plan, L (paper: 10).")
    candidates: int = Field(100, ge=1, description="Candidates per CEM iteration, K (paper: 100).")
    elites: int = Field(20, ge=1, description="Candidates the Gaussian is refit to, N_keep.")
    iterations: int = Field(20, ge=1, description="Maximum CEM iterations, N_iters (paper: 100).")
    init_std: float = Field(1.0, gt=0, description="Initial epsilon std (1: the skill prior).")
    min_std: float = Field(0.0, ge=0, description="Floor on the refit epsilon std.")
    prior_weight: float = Field(
        2.0,
        ge=0,
        description="Weight of the skill-prior penalty mean(eps^2) added to the task cost "
        "(0: the paper's task cost alone).",
    )
    skill_penalty: float = Field(
        0.0,
        ge=0,
        description="Goal units (m) the cost adds per skill before the predicted state nearest "
        "the goal, so a plan that gets there sooner wins (0: the paper's cost, indifferent to "
        "when).",
    )
    fall_penalty: float = Field(
        0.0,
        ge=0,
        description="Goal units (m) added to a plan whose predicted states include a fallen "
        "agent (the ant: torso down or upside down; others cannot fall). 0: the paper's cost.",
    )
    uncertainty_weight: float = Field(
        0.0,
        ge=0,
        description="Weight of the plan's uncertainty added to its cost: the TAWM's predicted "
        "std of each skill's outcome (normalized state units, the mean over the state's dims), "
        "summed over the plan's skills, so plans through outcomes the model is unsure of cost "
        "more (MOPO's penalty, with the TAWM's own std). 0: the paper's cost.",
    )
    support_weight: float = Field(
        0.0,
        ge=0,
        description="Weight of the plan's support excess added to its cost: for each of its "
        "(start state, skill) pairs, the squared distance to the nearest pair of the training "
        "windows (first state, posterior skill; the state and skill parts each a mean over "
        "their dims) beyond what support_quantile of the data's own pairs reach, summed over "
        "the plan's skills. Plans that rest on a skill the data never start near that state "
        "cost more. 0: the paper's cost.",
    )
    support_windows: int = Field(
        4096,
        ge=1,
        description="Training windows (evenly spaced) whose pairs make the support bank "
        "(with support_weight > 0; the distance costs a matrix product with the bank).",
    )
    support_quantile: float = Field(
        0.9,
        ge=0,
        le=1,
        description="The support margin: this quantile of the distances of training windows "
        "outside the bank; pairs nearer than it pay nothing.",
    )
    data_skills: int = Field(
        0,
        ge=0,
        description="The first skill of every plan is one the data ran from a like state: the "
        "nearest (to CEM's proposal) of the posterior skills of the data_skills support-bank "
        "windows whose first states are nearest the current state; CEM searches the later "
        "skills as before. 0: any skill (the paper).",
    )
    stop_cost: float | None = Field(
        None, gt=0, description="Stop a plan once its objective is below this; null: never."
    )
    warm_start: bool = Field(True, description="Start replans from the previous plan, shifted.")
    compile: bool = Field(
        False,
        description="torch.compile the CEM iterations and, on CUDA, replay each plan as a CUDA "
        "graph (the eager plans up to rounding; minutes of compilation on a small CPU).",
    )
    dtype: Literal["float32", "bfloat16"] = Field(
        "float32",
        description="What the prior and TAWM multiply in during the search: bfloat16 is about "
        "twice as fast on CPUs with AVX512-BF16 and on GPUs (states stay float32).",
    )
    kernel: Literal["torch", "triton"] = Field(
        "torch",
        description="What computes the rollout and goal cost in the search: torch (an "
        "operation per layer and skill), or triton: one fused kernel per CEM iteration (CUDA "
        "only; costs with a fall penalty or a per-dim goal scale, as on OGBench's manipulation "
        "envs, stay on torch). The same plans up to rounding.",
    )

    @model_validator(mode="after")
    def _elites_fit(self) -> PlannerParams:
        if self.elites > self.candidates:
            raise ValueError(f"elites ({self.elites}) must be <= candidates ({self.candidates})")
        return self


class SubgoalParams(_Section):
    """`deploy.subgoals`: once an episode stops getting closer to its goal (`patience`), aim
    each replan at a waypoint from a graph of the data's skills when the goal is more than
    `reach` skills away (`pipeline/planning/subgoals.py`)."""

    enabled: bool = Field(
        True,
        description="Plan to waypoints (when stuck, with `patience`); false: always to the goal, "
        "the paper.",
    )
    cell: float = Field(
        0.25, gt=0, description="Grid side (m) of the graph's nodes over the goal dimensions."
    )
    reach: int = Field(
        2,
        ge=1,
        description="Skills ahead a waypoint may be (at most the planner's horizon); the goal "
        "itself once it is this close. Skill hops count the data's longest windows, so a goal "
        "a few hops away may still lie round a wall: keep it small.",
    )
    line_of_sight: bool = Field(
        True,
        description="Aim at the goal, or at a waypoint, only when the straight line to it crosses "
        "cells the data visits (no wall between), else at the best waypoint in sight; false: "
        "by skill hops alone.",
    )
    patience: int | None = Field(
        2,
        ge=1,
        description="Plan to the goal itself until an episode has gone this many replans "
        "without getting `progress` closer to it than ever before, then to the graph's "
        "waypoints for the rest of the episode (the straight-line cost's local minimum behind "
        "a wall is where this happens); null: waypoints from the first replan.",
    )
    progress: float = Field(
        0.25,
        gt=0,
        description="What counts as getting closer for `patience`: the goal distance (goal "
        "units, m in a maze) below the episode's best so far by at least this much.",
    )


class LLPParams(_Section):
    """`deploy.llp`: CEM over whitened actions along the single-step model's predicted states
    (paper §4.2, LLP). Defaults: the paper code's maze2d settings; its timing figure used
    horizon 400 and 100 iterations."""

    horizon: int = Field(20, ge=1, description="Actions per plan, L (paper code: 20).")
    execute: int = Field(5, ge=1, description="Planned actions executed before replanning (5).")
    candidates: int = Field(100, ge=1, description="Candidates per CEM iteration, K (100).")
    elites: int = Field(20, ge=1, description="Candidates the Gaussian is refit to (20 %: 20).")
    iterations: int = Field(5, ge=1, description="CEM iterations (paper code: 5).")
    init_std: float = Field(1.0, gt=0, description="Initial epsilon std (1: the BC policy).")
    min_std: float = Field(0.0, ge=0, description="Floor on the refit epsilon std.")
    l2_penalty: float = Field(
        0.01, ge=0, description="Weight of mean(eps^2) added to the task cost (paper code: 0.01)."
    )
    plan_from: Literal["mean", "best"] = Field(
        "mean",
        description="Execute CEM's final mean (the paper code) or the best candidate it saw.",
    )
    warm_start: bool = Field(
        False, description="Start replans from the previous plan shifted (paper code: no)."
    )
    stop_cost: float | None = Field(
        None, gt=0, description="Stop a plan once its objective is below this; null: never."
    )

    @model_validator(mode="after")
    def _fits(self) -> LLPParams:
        if self.elites > self.candidates:
            raise ValueError(f"elites ({self.elites}) must be <= candidates ({self.candidates})")
        if self.execute > self.horizon:
            raise ValueError(f"execute ({self.execute}) must be <= horizon ({self.horizon})")
        return self


class GCBCAgentParams(_Section):
    """`deploy.gcbc`: the goal-conditioned BC policy run closed loop."""

    sample_actions: bool = Field(
        False, description="Sample actions (else the mean: OGBench evaluates at temperature 0)."
    )


class ExpertAgentParams(_Section):
    """`deploy.expert`: the scripted controller that made the data, as an agent (PointMaze:
    waypoints + PD; OGBench: its BFS oracle's direction)."""

    action_noise: float | None = Field(
        None,
        ge=0,
        description="Std of its action noise; null: the dataset's (D4RL: 0.5; OGBench point: 0.5).",
    )


AGENTS = ("oposm", "oposm_sim", "llp", "gcbc", "expert")


class DeployParams(_Section):
    """`oposm deploy`: agents (skill MPC and the baselines) in the maze of the training data,
    success rates, planning cost, recordings."""

    agents: list[Literal[AGENTS]] = Field(  # type: ignore[valid-type]
        default_factory=lambda: ["oposm"],
        min_length=1,
        description="Agents run on the same episodes: oposm (skill MPC), oposm_sim (its "
        "planner scoring each candidate in the simulator instead of the TAWM: an upper bound, "
        "slow), llp (low-level planning: `oposm dynamics` + `oposm bc`), gcbc (`oposm gcbc`), "
        "expert (the data's).",
    )
    tasks: list[Literal["corners", "random_goal", "goal", "ogbench", "kitchen"]] = Field(
        default_factory=lambda: ["random_goal", "corners"],
        min_length=1,
        description="corners: D4RL's opposite-corner task; random_goal: goals from training "
        "data, random start cell; goal: `goal` from random start cells; ogbench: an OGBench "
        "maze's five evaluation tasks (`episodes` each, success_radius must be OGBench's); "
        "kitchen: the Franka kitchen's D4RL task set (its four subtasks from the env's reset, "
        "D4RL's score: subtasks completed / 4).",
    )
    episodes: int = Field(100, ge=1, description="Episodes per task.")
    goal: list[float] | None = Field(
        None, min_length=2, max_length=2, description="[x, y] of the `goal` task."
    )
    num_envs: int = Field(100, ge=1, description="Environments stepped and planned together.")
    replan_every: int | None = Field(
        20,
        ge=1,
        description="Steps of a skill executed before the next plan, tau, at most the model's T "
        "(window - 1) (paper table 14: 40 on maze2d, 10 on antmaze-large); null: T, each skill "
        "whole.",
    )
    sample_actions: bool = Field(
        True, description="Sample a ~ pi(a | s, z) as in §3 (else the policy's mean action)."
    )
    max_steps: int | None = Field(
        None,
        ge=1,
        description="Step limit per episode; null: D4RL's (300/600/800). Longer runs also "
        "report success within D4RL's limit (the paper code: 2000, `done` ignored).",
    )
    success_radius: float = Field(0.5, gt=0, description="Success distance (paper, D4RL: 0.5).")
    start_noise: float = Field(0.1, ge=0, description="Uniform +- noise on start positions (m).")
    record_episodes: int = Field(10, ge=0, description="Episodes per task with a recording.")
    mass_scale: float = Field(
        1.0,
        gt=0,
        description="Every body's mass and inertia in the simulator times this (the "
        "robustness experiment, paper fig. 5); the models stay as trained.",
    )
    planner: PlannerParams = Field(default_factory=PlannerParams)
    subgoals: SubgoalParams = Field(default_factory=SubgoalParams)
    object_subtasks: bool = Field(
        False,
        description="OPOSM on an object goal (manipulation): plan to one object at a time, the "
        "first in the goal's order not yet within its tolerance, the objects to come left where "
        "they are (`pipeline/planning/subtasks.py`); false: to the whole goal (the paper).",
    )
    llp: LLPParams = Field(default_factory=LLPParams)
    gcbc: GCBCAgentParams = Field(default_factory=GCBCAgentParams)
    expert: ExpertAgentParams = Field(default_factory=ExpertAgentParams)
    threads: int | None = Field(
        1, ge=1, description="Torch CPU threads; null: torch's default (all cores)."
    )
    workers: int | Literal["auto"] = Field(
        "auto",
        description="Processes running the (agent, task) jobs side by side, each on `threads` "
        "torch threads; the episodes do not depend on it. auto: one per job up to the cores "
        "this process may use (1 on CUDA).",
    )
    seed: int = Field(0, description="Seed of tasks, CEM noise and action noise.")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="auto: CUDA when available, else CPU (the simulator runs on CPU)."
    )

    @field_validator("workers")
    @classmethod
    def _positive_workers(cls, v: int | str) -> int | str:
        if isinstance(v, int) and v < 1:
            raise ValueError("must be >= 1 or auto")
        return v

    @model_validator(mode="after")
    def _agents_once(self) -> DeployParams:
        if len(set(self.agents)) != len(self.agents):
            raise ValueError(f"each agent at most once, got {self.agents}")
        if self.subgoals.reach > self.planner.horizon:  # also while disabled: it cannot work
            raise ValueError(
                f"subgoals.reach ({self.subgoals.reach}) must be <= planner.horizon "
                f"({self.planner.horizon}): a waypoint lies within one plan; lower "
                "subgoals.reach or raise planner.horizon"
            )
        return self


class Params(_Section):
    """All of `params.yaml`, one field per stage.

    The `validate` section is the attribute `validation`: a field named `validate` would shadow
    pydantic's `BaseModel.validate`. Files, overrides, dumps and messages use the section's name.
    """

    model_config = ConfigDict(
        extra="forbid",
        validate_assignment=True,
        allow_inf_nan=False,
        validate_by_name=True,
        validate_by_alias=True,
        serialize_by_alias=True,
    )

    ingest: IngestParams = Field(default_factory=IngestParams)
    segment: SegmentParams = Field(default_factory=SegmentParams)
    train: TrainParams = Field(default_factory=TrainParams)
    dynamics: DynamicsParams = Field(default_factory=DynamicsParams)
    bc: BCParams = Field(default_factory=BCParams)
    gcbc: GCBCParams = Field(default_factory=GCBCParams)
    value: ValueParams = Field(default_factory=ValueParams)
    validation: ValidateParams = Field(default_factory=ValidateParams, alias="validate")
    deploy: DeployParams = Field(default_factory=DeployParams)


def _format_validation_error(
    err: ValidationError, source: str, root: type[BaseModel] | None = None
) -> str:
    first = err.errors()[0]
    key = ".".join(str(p) for p in first["loc"]) or "<root>"
    if first["type"] in ("extra_forbidden", "unexpected_keyword_argument"):
        valid = ", ".join(_section_keys(first["loc"][:-1], root or Params))
        return f"{source}: unknown key '{key}'; valid keys here: {valid}"
    expected = first["msg"].removeprefix("Value error, ")
    got = first.get("input")
    more = f" (and {len(err.errors()) - 1} more problems)" if len(err.errors()) > 1 else ""
    if isinstance(got, dict):  # a check across a section's keys: its message names them
        return f"{source}: bad values in '{key}': {expected}{more}"
    return f"{source}: bad value for '{key}': {expected}, got {got!r}{more}"


def _keys(model: type[BaseModel]) -> dict[str, Any]:
    """Params-file key (the alias, if any) -> field of a section."""
    return {field.alias or name: field for name, field in model.model_fields.items()}


def _section_keys(loc: tuple, root: type[BaseModel]) -> list[str]:
    """Keys of the (nested) section at `loc` of the `root` model, for error messages."""
    model: type = root
    for part in loc:
        field = _keys(model).get(str(part)) if issubclass(model, BaseModel) else None
        if field is None or not isinstance(field.annotation, type):
            break
        model = field.annotation
    if dataclasses.is_dataclass(model):
        return [f.name for f in dataclasses.fields(model)]
    return list(_keys(model)) if issubclass(model, BaseModel) else []


def parse_override(text: str) -> tuple[list[str], Any]:
    """Parse one `section.key=value` override; the value is read as YAML (`3`, `0.5`, `[1, 2]`)."""
    if "=" not in text:
        raise UserError(f"override '{text}' is not of the form section.key=value")
    key, value = text.split("=", 1)
    path = [p for p in key.strip().split(".") if p]
    if not path:
        raise UserError(f"override '{text}' has an empty key")
    try:
        parsed = yaml.safe_load(value) if value.strip() else ""
    except yaml.YAMLError as exc:
        raise UserError(f"override '{text}': value is not valid YAML ({exc})") from exc
    return path, parsed


def apply_overrides(raw: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Return a copy of `raw` with each `section.key=value` override set."""
    result: dict[str, Any] = _deep_copy(raw)
    for text in overrides:
        path, value = parse_override(text)
        node = result
        for part in path[:-1]:
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            if not isinstance(child, dict):
                raise UserError(f"override '{text}': '{part}' is not a section")
            node = child
        node[path[-1]] = value
    return result


def _deep_copy(raw: dict[str, Any]) -> dict[str, Any]:
    return {k: _deep_copy(v) if isinstance(v, dict) else v for k, v in raw.items()}


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """'line L, column C: problem' of a YAML error (PyYAML's own text spans several lines)."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    if mark is None:
        return problem
    return f"line {mark.line + 1}, column {mark.column + 1}: {problem}"


EXTENDS = "extends"  # a variant's key naming the params file it overlays


def merge_params(base: dict[str, Any], overlay: dict[str, Any]) -> dict[str, Any]:
    """`overlay` deep-merged onto `base` (a new dict): mappings merge key by key, recursively;
    any other value (a scalar, a list, null) replaces the base's."""
    merged = _deep_copy(base)
    for key, value in overlay.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merge_params(merged[key], value)
        else:
            merged[key] = _deep_copy(value) if isinstance(value, dict) else value
    return merged


def _read_mapping(path: Path, what: str, hint: str, sections: str) -> dict[str, Any]:
    """One params file's YAML mapping, as written."""
    if not path.exists():
        raise UserError(f"{what} {path} not found; {hint}")
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise UserError(f"{path} is not valid YAML: {_yaml_problem(exc)}") from exc
    if not isinstance(raw, dict):
        raise UserError(f"{path} must be a mapping of sections ({sections})")
    return raw


def read_params_file(
    path: str | Path,
    what: str = "params file",
    hint: str = "run from the project root or pass --params",
    sections: str = "ingest:, segment:, ...",
) -> tuple[dict[str, Any], list[Path]]:
    """A params file as one mapping, its `extends` chain merged, before validation; and the
    files it was read from (the file first, then its base, its base's base, ...).

    Each file's `extends: <file>` (relative to that file) names its base; the file is
    `merge_params`-ed onto it. `what`, `hint` and `sections` word the errors.

    Raises:
        UserError: a file is missing or not a YAML mapping, `extends` is not a file name, names
            a missing file, or leads back to a file of the chain. One line, naming the file.
    """
    current = Path(path)
    chain: list[Path] = []
    layers: list[dict[str, Any]] = []
    while True:
        raw = _read_mapping(current, what, hint, sections)
        chain.append(current)
        layers.append(raw)
        if EXTENDS not in raw:
            break
        base = raw.pop(EXTENDS)
        if not isinstance(base, str) or not base.strip():
            raise UserError(
                f"{current}: '{EXTENDS}' must name the params file it overlays (a path relative "
                f"to {current.name}), got {base!r}"
            )
        target = current.parent / base
        if not target.exists():
            raise UserError(f"{current}: '{EXTENDS}: {base}': base params file {target} not found")
        if any(target.resolve() == seen.resolve() for seen in chain):
            cycle = " -> ".join(str(p) for p in [*chain, target])
            raise UserError(f"{current}: '{EXTENDS}: {base}' makes a cycle: {cycle}")
        current = target
    merged: dict[str, Any] = {}
    for layer in reversed(layers):
        merged = merge_params(merged, layer)
    return merged, chain


def params_files(path: str | Path) -> list[Path]:
    """The files a params file resolves from: itself, then the bases it `extends` (what a DVC
    stage run with `-p <variant>` lists as params deps, and what an ad-hoc run's folder key
    hashes)."""
    return read_params_file(path)[1]


def load_model_file[M: BaseModel](
    model: type[M],
    path: str | Path,
    overrides: list[str] | None = None,
    what: str = "params file",
    hint: str = "run from the project root or pass --params",
    sections: str = "ingest:, segment:, ...",
) -> M:
    """`read_params_file`, then the `section.key=value` overrides, then `model`'s validation.

    Raises:
        UserError: see `read_params_file`; an override is malformed, a key is unknown or a value
            is bad (the message names the file and the key).
    """
    raw, chain = read_params_file(path, what, hint, sections)
    raw = apply_overrides(raw, overrides or [])
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        source = str(path)
        if len(chain) > 1:
            source += f" (extends {', '.join(str(p) for p in chain[1:])})"
        raise UserError(_format_validation_error(exc, source, model)) from exc


def load_params(path: str | Path = "params.yaml", overrides: list[str] | None = None) -> Params:
    """Load and validate `params.yaml` or a variant (an overlay of it: `read_params_file`),
    applying `section.key=value` overrides for this run.

    Raises:
        UserError: the file is missing or not YAML, its `extends` is broken, a key is unknown or
            a value has the wrong type.
    """
    return load_model_file(Params, path, overrides)
