"""The OPOSM skill model (paper §2, appendix C): q_phi, p_omega, pi_theta and the TAWM p_psi.

All four are diagonal Gaussians. Networks work on states and actions normalized with the segment
stage's train statistics; the model stores those statistics as buffers, so its public methods take
and return raw environment units.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn
from torch.distributions import Categorical, Distribution, Independent, MixtureSameFamily, Normal
from torch.nn import functional as F

from pipeline.model.networks import GaussianHead, GaussianMLP, MixtureGaussianMLP
from pipeline.readback import Count, Finite, PositiveFinite, Size

# The posterior's sequence networks (`SkillModelConfig.encoder`, `train.encoder`).
ENCODERS = ("gru", "conv")


@dataclass(frozen=True)
class SkillModelConfig:
    """Everything needed to rebuild a `SkillModel` (stored as the checkpoint's config.json).

    The hyperparameters have no defaults: `train` (`pipeline.config.TrainParams`) holds them and
    `pipeline.model.settings.skill_model_config` builds this from it. The fields with defaults
    default to what a checkpoint written before they existed holds (no bounds, ReLU policy, one
    Gaussian TAWM).

    Attributes:
        state_dim: Size of a state vector.
        action_dim: Size of an action vector.
        z_dim: Size of the skill latent z (paper: 256).
        hidden: Width of every hidden layer (paper: 256).
        tawm_shared_std: One scalar std shared by all state dims in p_psi (paper, mazes) instead
            of one per dim.
        min_std: Floor added to every softplus std.
        action_low: Raw lower bound of each action dim where the data's actions are clipped
            (censored), or None: the policy's likelihood is then a plain Gaussian density (the
            paper's). With bounds, an action at a bound is scored as the probability mass
            beyond it (`censored_log_prob`), so a clipped action cannot reward a vanishing std.
        action_high: Raw upper bounds, likewise (both or neither).
        policy_layer_norm: The policy's trunk normalizes its hidden layers (LayerNorm + SiLU,
            `networks.trunk`) instead of the paper's ReLU layers; the prior and TAWM (what the
            planner runs) keep the paper's.
        policy_ignore_dims: State dims the low-level policy pi(a | s, z) does not see (sorted,
            unique): what would tell it the next action without the skill (an arm's joint
            velocities under a position controller) goes through z instead. Posterior, prior
            and TAWM see every dim. Empty: the paper's policy, which sees the whole state.
        tawm_components: Gaussians in p_psi: 1 is the paper's TAWM; K > 1 a mixture of K
            (`networks.MixtureGaussianMLP`), whose most probable component's mean is what the
            planner and the open loop chain.
        encoder: The posterior's sequence network: "gru" (appendix C.1's bidirectional GRU)
            or "conv" (strided 1-D convolutions, `ConvEncoder`: about a third of the GRU's
            products and no step-by-step recurrence).
        tawm_residual: p_psi's mean is s_0 plus the network's output (normalized units), so a
            skill that leaves a dim alone predicts it unchanged by default; False: the paper's
            mean of s_T straight from (s_0, z).
    """

    state_dim: Size
    action_dim: Size
    z_dim: Size
    hidden: Size
    tawm_shared_std: bool
    min_std: PositiveFinite
    action_low: tuple[Finite, ...] | None = None
    action_high: tuple[Finite, ...] | None = None
    policy_layer_norm: bool = False
    policy_ignore_dims: tuple[Count, ...] = ()
    tawm_components: Size = 1
    encoder: str = "gru"
    tawm_residual: bool = False

    def __post_init__(self) -> None:
        ignore = tuple(sorted({int(d) for d in self.policy_ignore_dims}))
        if any(not 0 <= d < self.state_dim for d in ignore) or len(ignore) == self.state_dim:
            raise ValueError(
                f"policy_ignore_dims {list(ignore)} must be some, not all, of the state dims "
                f"0 to {self.state_dim - 1}"
            )
        object.__setattr__(self, "policy_ignore_dims", ignore)
        if self.encoder not in ENCODERS:
            raise ValueError(f"encoder must be one of {', '.join(ENCODERS)}, got {self.encoder!r}")
        bounds = (self.action_low, self.action_high)
        if (bounds[0] is None) != (bounds[1] is None):
            raise ValueError("action_low and action_high come together (both or neither)")
        for name, value in zip(("action_low", "action_high"), bounds, strict=True):
            if value is not None:
                value = tuple(float(v) for v in value)
                if len(value) != self.action_dim:
                    raise ValueError(f"{name} has {len(value)} values for {self.action_dim} dims")
                object.__setattr__(self, name, value)

    @property
    def censored(self) -> bool:
        """Whether the policy's likelihood is censored at action bounds."""
        return self.action_low is not None

    def to_dict(self) -> dict:
        """The fields, without `encoder` where it is the paper's GRU and `tawm_residual` where
        it is the paper's false: a checkpoint's config.json stays the bytes it was before the
        fields existed (`load` reads their absence as the paper's)."""
        fields = asdict(self)
        if fields["encoder"] == "gru":
            del fields["encoder"]
        if not fields["tawm_residual"]:
            del fields["tawm_residual"]
        return fields


# An action within this many normalized units of a bound counts as clipped to it.
BOUND_TOLERANCE = 1e-5


def censored_log_prob(
    mean: torch.Tensor, std: torch.Tensor, x: torch.Tensor, low: torch.Tensor, high: torch.Tensor
) -> torch.Tensor:
    """Elementwise log-likelihood (not summed) of `x` under N(mean, std^2) censored at
    `[low, high]`: the density inside, log P(X >= high) at the upper bound, log P(X <= low) at
    the lower one.

    This is the likelihood of data made as clip(mean + noise): an action clipped to a bound is
    only known to lie beyond it. A plain density there rewards a std shrinking to zero without
    limit (the clipped values are a point mass); the censored term is at most 0 (probability 1),
    reached by a mean beyond the bound at any std.
    """
    density = Normal(mean, std, validate_args=False).log_prob(x)
    upper = torch.special.log_ndtr((mean - high) / std)
    lower = torch.special.log_ndtr((low - mean) / std)
    at_high, at_low = x >= high - BOUND_TOLERANCE, x <= low + BOUND_TOLERANCE
    return torch.where(at_high, upper, torch.where(at_low, lower, density))


def diag_normal(mean: torch.Tensor, std: torch.Tensor) -> Independent:
    """A diagonal Gaussian over the last dimension (log_prob sums over it).

    Argument validation is off: it costs time in the hot loop, and a NaN must reach the
    training loop's divergence check (which names the step) rather than fail inside torch.
    """
    return Independent(Normal(mean, std, validate_args=False), 1, validate_args=False)


class ConvEncoder(nn.Module):
    """A window's summary by strided 1-D convolutions (not the paper's; `encoder: conv`): two
    layers of kernel `KERNEL`, stride `STRIDE` (zero-padded to keep every step) and ReLU over the
    sequence, then its average over `POOLED` stretches of the window (adaptive average pooling:
    stretch i covers steps floor(i L / POOLED) to ceil((i + 1) L / POOLED) of the L left),
    flattened in time order, so the summary keeps what happens early apart from what happens
    late.

    Each layer is a product of a window of steps with one matrix (an unfolded convolution), so it
    runs through the same matrix kernels as every linear layer (bit-reproducible on CPU whatever
    the thread count, `pipeline/cpu_math.py`). At the main job's sizes it costs about a third of
    the bidirectional GRU's products, and its steps run in parallel instead of one after another.
    """

    KERNEL, STRIDE, POOLED = 5, 2, 4

    def __init__(self, in_dim: int, hidden: int):
        super().__init__()
        self.layers = nn.ModuleList(
            [nn.Linear(in_dim * self.KERNEL, hidden), nn.Linear(hidden * self.KERNEL, hidden)]
        )
        self.out_dim = hidden * self.POOLED

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """`x [B, T, in_dim]` -> `[B, POOLED * hidden]`."""
        pad = (self.KERNEL - 1) // 2
        for layer in self.layers:
            windows = F.pad(x, (0, 0, pad, pad)).unfold(1, self.KERNEL, self.STRIDE)
            x = F.relu(layer(windows.flatten(2)))  # [B, L, hidden], L = ceil(T / STRIDE)
        pooled = F.adaptive_avg_pool1d(x.transpose(1, 2), self.POOLED)  # [B, hidden, POOLED]
        return pooled.transpose(1, 2).flatten(1)


class SkillPosterior(nn.Module):
    """q_phi(z | s_0..T-1, a_0..T-1), appendix C.1.

    States pass through Linear + ReLU; embedded states concatenated with actions feed a one-layer
    bidirectional GRU; the final hidden states of both directions feed the mean and std heads.
    With `encoder: conv` a `ConvEncoder` takes the GRU's place.
    """

    def __init__(self, config: SkillModelConfig):
        super().__init__()
        h = config.hidden
        self.embed = nn.Sequential(nn.Linear(config.state_dim, h), nn.ReLU())
        self.encoder = config.encoder
        if self.encoder == "gru":
            self.gru = nn.GRU(h + config.action_dim, h, batch_first=True, bidirectional=True)
            summary = 2 * h
        else:
            self.conv = ConvEncoder(h + config.action_dim, h)
            summary = self.conv.out_dim
        self.head = GaussianHead(summary, h, config.z_dim, min_std=config.min_std)

    def forward(self, states: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Normalized `states [B, T, sd]`, `actions [B, T, ad]` -> mean, std `[B, z_dim]`."""
        x = torch.cat([self.embed(states), actions], dim=-1)
        if self.encoder == "conv":
            return self.head(self.conv(x))
        _, h_n = self.gru(x)  # [2, B, h]: last hidden state of the forward and backward passes
        return self.head(torch.cat([h_n[0], h_n[1]], dim=-1))


class SkillModel(nn.Module):
    """Posterior, prior, low-level policy and temporally abstract world model, with normalization.

    Parameter groups (for the EM optimizers): `posterior` (E-step) and `generative()` (M-step:
    policy, TAWM, prior).
    """

    def __init__(self, config: SkillModelConfig):
        super().__init__()
        self.config = config
        sd, ad, z, h = config.state_dim, config.action_dim, config.z_dim, config.hidden
        self.posterior = SkillPosterior(config)
        self.prior = GaussianMLP(sd, h, z, min_std=config.min_std)
        seen = [d for d in range(sd) if d not in set(config.policy_ignore_dims)]
        self.register_buffer("policy_dims", torch.tensor(seen, dtype=torch.long), persistent=False)
        self.policy = GaussianMLP(
            len(seen) + z, h, ad, min_std=config.min_std, layer_norm=config.policy_layer_norm
        )
        if config.tawm_components == 1:
            self.tawm = GaussianMLP(
                sd + z, h, sd, shared_std=config.tawm_shared_std, min_std=config.min_std
            )
        else:
            self.tawm = MixtureGaussianMLP(
                sd + z, h, sd, config.tawm_components, config.tawm_shared_std, config.min_std
            )
        self.register_buffer("state_mean", torch.zeros(sd))
        self.register_buffer("state_std", torch.ones(sd))
        self.register_buffer("action_mean", torch.zeros(ad))
        self.register_buffer("action_std", torch.ones(ad))
        if config.censored:  # raw bounds from the config, not the weights file
            for name in ("action_low", "action_high"):
                bound = torch.tensor(getattr(config, name), dtype=torch.float32)
                self.register_buffer(name, bound, persistent=False)

    def generative(self) -> list[nn.Parameter]:
        """Parameters updated by the M-step: theta (policy), psi (TAWM), omega (prior)."""
        return [*self.policy.parameters(), *self.tawm.parameters(), *self.prior.parameters()]

    def set_normalization(self, state_mean, state_std, action_mean, action_std) -> None:
        """Copy train-split statistics (array-likes) into the model's buffers."""
        for name, value in zip(
            ("state_mean", "state_std", "action_mean", "action_std"),
            (state_mean, state_std, action_mean, action_std),
            strict=True,
        ):
            buffer = getattr(self, name)
            buffer.copy_(torch.as_tensor(value, dtype=buffer.dtype))

    # -- normalization ----------------------------------------------------------------------
    def norm_states(self, s: torch.Tensor) -> torch.Tensor:
        return (s - self.state_mean) / self.state_std

    def norm_actions(self, a: torch.Tensor) -> torch.Tensor:
        return (a - self.action_mean) / self.action_std

    # -- distributions on normalized inputs (training) ---------------------------------------
    def posterior_dist(self, states_n: torch.Tensor, actions_n: torch.Tensor) -> Independent:
        """q_phi(z | tau) from normalized `states [B, T, sd]` (s_0..T-1), `actions [B, T, ad]`."""
        return diag_normal(*self.posterior(states_n, actions_n))

    def prior_dist(self, s0_n: torch.Tensor) -> Independent:
        """p_omega(z | s_0) from normalized `s0 [..., sd]`."""
        return diag_normal(*self.prior(s0_n))

    def policy_stats(self, s_n: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """pi_theta's mean, std `[..., ad]` (normalized actions) from normalized `s_n [..., sd]`
        and `z [..., z]`; the policy sees the state dims not in `policy_ignore_dims`."""
        if self.config.policy_ignore_dims:
            s_n = s_n.index_select(-1, self.policy_dims)
        return self.policy(torch.cat([s_n, z], dim=-1))

    def policy_log_prob(
        self, s_n: torch.Tensor, z: torch.Tensor, a_n: torch.Tensor
    ) -> torch.Tensor:
        """log pi_theta(a | s, z) `[...]` of normalized actions `a_n [..., ad]`, summed over
        dims: a Gaussian density, or censored at the action bounds (`SkillModelConfig`)."""
        mean, std = self.policy_stats(s_n, z)
        if not self.config.censored:
            return diag_normal(mean, std).log_prob(a_n)
        low, high = self.norm_actions(self.action_low), self.norm_actions(self.action_high)
        return censored_log_prob(mean, std, a_n, low, high).sum(-1)

    def clip_actions(self, a: torch.Tensor) -> torch.Tensor:
        """Raw actions `a` clipped to the action bounds (unchanged without bounds): what the
        censored policy's samples and mean mean as executed actions."""
        if not self.config.censored:
            return a
        return torch.minimum(torch.maximum(a, self.action_low), self.action_high)

    def tawm_dist(self, s0_n: torch.Tensor, z: torch.Tensor) -> Distribution:
        """p_psi(s_T | s_0, z) over normalized s_T; `s0 [..., sd]`, `z [..., z]`: a diagonal
        Gaussian, or a mixture of them (`tawm_components`)."""
        x = torch.cat([s0_n, z], dim=-1)
        if self.config.tawm_components == 1:
            mean, std = self.tawm(x)
            return diag_normal(self._from_start(mean, s0_n), std)
        means, stds, logits = self.tawm(x)
        return MixtureSameFamily(
            Categorical(logits=logits, validate_args=False),
            diag_normal(self._from_start(means, s0_n[..., None, :]), stds),
            validate_args=False,
        )

    def tawm_outcome(
        self, s0_n: torch.Tensor, z: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, ...]:
        """The TAWM's predicted s_T as a planner chains it: mean, std `[..., sd]` (normalized)
        of its Gaussian, or of one component of the mixture: the most probable, or with
        `generator` one drawn by the mixture's weights (a sampled outcome's component; one
        uniform draw per row, none for a single Gaussian)."""
        x = torch.cat([s0_n, z], dim=-1)
        if self.config.tawm_components == 1:
            mean, std = self.tawm(x)
        elif generator is None:
            mean, std = self.tawm.readout(x)
        else:
            means, stds, logits = self.tawm(x)
            u = torch.rand(logits.shape[:-1], generator=generator, device=generator.device)
            cdf = logits.softmax(-1).cumsum(-1)
            index = (u.to(cdf.device)[..., None] > cdf).sum(-1).clamp(max=logits.shape[-1] - 1)
            index = index[..., None, None].expand(*means.shape[:-2], 1, means.shape[-1])
            mean, std = means.gather(-2, index).squeeze(-2), stds.gather(-2, index).squeeze(-2)
        return self._from_start(mean, s0_n), std

    def _from_start(self, mean: torch.Tensor, s0_n: torch.Tensor) -> torch.Tensor:
        """The TAWM network's mean output as a mean of s_T: itself (the paper's), or added to
        the start (`config.tawm_residual`)."""
        return mean + s0_n if self.config.tawm_residual else mean

    # -- raw-unit interface (planning, validation, deployment) ----------------------------------
    @torch.no_grad()
    def skill_prior(self, s0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw `s0 [..., sd]` -> prior mean, std over z `[..., z]` (for whitened planning)."""
        return self.prior(self.norm_states(s0))

    @torch.no_grad()
    def predict_end(self, s0: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw `s0 [..., sd]`, `z [..., z]` -> TAWM mean, std of s_T in raw units `[..., sd]`."""
        mean, std = self.tawm_outcome(self.norm_states(s0), z)
        return mean * self.state_std + self.state_mean, std * self.state_std

    @torch.no_grad()
    def act(self, s: torch.Tensor, z: torch.Tensor, sample: bool = False) -> torch.Tensor:
        """Raw `s [..., sd]`, `z [..., z]` -> raw action `[..., ad]` (mean, or sampled)."""
        mean, std = self.policy_stats(self.norm_states(s), z)
        a = mean + std * torch.randn_like(std) if sample else mean
        return self.clip_actions(a * self.action_std + self.action_mean)

    @torch.no_grad()
    def infer_skill(
        self, states: torch.Tensor, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw `states [B, T, sd]` (s_0..T-1), `actions [B, T, ad]` -> posterior mean, std."""
        return self.posterior(self.norm_states(states), self.norm_actions(actions))
