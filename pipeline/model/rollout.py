"""Skill sequences rolled through the model: the prior picks each skill, the TAWM chains the states.

The one rollout the planner (paper §3, appendix C.6) and the open-loop validation (§4.1) share.
From s_0, for k = 0..L-1:

    z_k = mu_omega(s_k) + sigma_omega(s_k) * eps_k      (whitened skills eps, `eps=`)
          or the given z_k                              (`z=`)
    s_{k+1} ~ p_psi(s_T | s_k, z_k) = N(mu_psi, sigma_psi^2):
          its mean (the planner's prediction), or a sample (`generator=`, particles);
          of a mixture TAWM, the most probable component's mean, or a sample of a component
          drawn by the mixture's weights

Inside, everything stays in the train-normalized units the networks work in; raw states come in and
go out at the boundary only. This is the planner's hot path: one prior and one TAWM pass per skill
for all candidates of all problems at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.model.skill_model import SkillModel


@dataclass
class SkillRollout:
    """A rollout of L skills from B start states (`*B`: any leading batch shape), raw units.

    Attributes:
        z: `[*B, L, z_dim]` the skills.
        states: `[*B, L + 1, sd]` s_0 and the chained states s_1..s_L (TAWM means, or samples).
        mean: `[*B, L, sd]` the TAWM mean of s_{k+1} given the chained s_k.
        std: `[*B, L, sd]` the TAWM std of s_{k+1} given the chained s_k.
    """

    z: torch.Tensor
    states: torch.Tensor
    mean: torch.Tensor
    std: torch.Tensor


@torch.no_grad()
def rollout_skills(
    model: SkillModel,
    s0: torch.Tensor,
    *,
    eps: torch.Tensor | None = None,
    z: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
) -> SkillRollout:
    """Roll L skills forward through the skill prior and the TAWM (see the module docstring).

    Args:
        model: The skill model.
        s0: `[*B, sd]` raw start states (broadcast to the batch shape of `eps` / `z`).
        eps: `[*B, L, z_dim]` whitened skills: z_k from the prior at the chained state s_k.
        z: `[*B, L, z_dim]` the skills themselves (exactly one of `eps`, `z`).
        generator: Sample each s_{k+1} from the TAWM (noise from this generator; of a mixture,
            from a component drawn by its weights) instead of taking its mean.

    Returns:
        The skills, chained states and the TAWM's Gaussians, in raw units.
    """
    if (eps is None) == (z is None):
        raise ValueError("give exactly one of eps (whitened skills) and z (skills)")
    given = eps if eps is not None else z
    *batch, n_skills, z_dim = given.shape
    sd = s0.shape[-1]
    # Flat [N, ...] rows: one matmul per network and skill for the whole batch.
    s0 = s0.expand(*batch, sd).reshape(-1, sd)
    s = model.norm_states(s0)
    given = given.reshape(-1, n_skills, z_dim)
    states, skills, means, stds = [], [], [], []
    for k in range(n_skills):
        if eps is not None:
            mu_z, sigma_z = model.prior(s)
            skills.append(mu_z + sigma_z * given[:, k])
        else:
            skills.append(given[:, k])
        mean, std = model.tawm_outcome(s, skills[-1], generator)
        if generator is None:
            s = mean
        else:
            noise = torch.randn(mean.shape, generator=generator, device=generator.device)
            s = mean + std * noise.to(mean.device)
        states.append(s)
        means.append(mean)
        stds.append(std)

    def raw(xs: list[torch.Tensor], shift: bool = True) -> torch.Tensor:
        x = torch.stack(xs, dim=1) * model.state_std
        return x + model.state_mean if shift else x

    mean = raw(means)
    chained = mean if generator is None else raw(states)  # the means themselves, unsampled
    return SkillRollout(
        z=torch.stack(skills, dim=1).reshape(*batch, n_skills, z_dim),
        states=torch.cat([s0[:, None], chained], dim=1).reshape(*batch, n_skills + 1, sd),
        mean=mean.reshape(*batch, n_skills, sd),
        std=raw(stds, shift=False).reshape(*batch, n_skills, sd),
    )
