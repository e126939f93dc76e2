"""How far a planned (start state, skill) pair is from the pairs the data hold.

CEM searches the whole whitened skill space at every state, and the TAWM answers for every
(state, skill) pair, including pairs the demonstrations never show: e.g. with the gripper far from
every cube, a skill that the data only show near a cube (a lift). There the TAWM extrapolates, often
optimistically, and the plan rests on an outcome that will not happen. The skill prior cannot rule
this out: it is one Gaussian per state, wide enough to cover every skill the data start near that
state, and the pairs between its modes.

`SkillSupport` keeps a bank of the training windows' pairs: each window's first state (normalized)
and its posterior mean skill. The support distance of a pair is the squared distance to its nearest
bank pair, with the state part averaged over the state's dims and the skill part over the skill's
dims (each skill dim divided by its spread in the bank), so the two parts weigh alike whatever
their sizes. Even the data's own pairs are some way from the bank (it holds a sample of them), so
a plan pays only for the distance beyond a margin: a quantile of the distances of training
windows the bank does not hold (`deploy.planner.support_quantile`). `deploy.planner.
support_weight` adds `weight x` those excesses of a plan's skills, summed, to its cost (0: the
paper's cost).

With `deploy.planner.data_skills: k` the bank also gives the plan's first skill: the nearest, to
CEM's proposal, of the posterior skills of the k bank windows whose first states are nearest the
current state (`local_skills`, `snap`), so the skill executed is one the data ran from a near state.

The bank is built at deploy time from the segments the model trained on (evenly spaced training
windows, `deploy.planner.support_windows` of them): deterministic, nothing saved beside the model.
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.model.skill_model import SkillModel
from pipeline.segments import Segments

_ROWS = 512  # pairs per distance block: [rows, bank] floats at a time (cache-sized: 2x 4096)


class SkillSupport:
    """A bank of (normalized start state, posterior skill) pairs and the distance to it.

    Args:
        starts_n: `[M, sd]` the windows' first states, normalized as the model normalizes.
        skills: `[M, z]` their posterior mean skills.
    """

    def __init__(self, starts_n: torch.Tensor, skills: torch.Tensor, margin: float = 0.0):
        if len(starts_n) != len(skills) or not len(skills):
            raise ValueError("the bank needs as many start states as skills, and at least one")
        sd, zd = starts_n.shape[-1], skills.shape[-1]
        self.skill_scale = skills.std(dim=0).clamp_min(1e-6) if len(skills) > 1 else torch.ones(zd)
        self._state_w = sd**-0.5
        self._skill_w = zd**-0.5 / self.skill_scale
        self.bank = self._features(starts_n, skills)  # [M, sd + z]
        self._bank_sq = self.bank.pow(2).sum(dim=-1)
        self.margin = float(margin)
        self.starts_n, self.skills = starts_n, skills

    def local_skills(self, states_n: torch.Tensor, k: int) -> torch.Tensor:
        """`[B, k, z]` the skills of the k bank windows whose first states are nearest each of
        `states_n [B, sd]` (normalized; Euclidean), nearest first."""
        d = torch.cdist(states_n, self.starts_n)  # [B, M]
        idx = d.topk(min(k, len(self.skills)), dim=-1, largest=False).indices
        return self.skills[idx]

    def snap(self, skills: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
        """Each of `skills [B, K, z]` replaced by the nearest of its problem's `local [B, k, z]`
        (each dim over the bank's spread)."""
        d = torch.cdist(skills / self.skill_scale, local / self.skill_scale)  # [B, K, k]
        idx = d.argmin(dim=-1)  # [B, K]
        return local.gather(1, idx[..., None].expand(*idx.shape, local.shape[-1]))

    @classmethod
    @torch.no_grad()
    def from_segments(
        cls,
        model: SkillModel,
        segments: Segments,
        windows: int,
        quantile: float | None = None,
        batch: int = 1024,
    ) -> SkillSupport:
        """The bank of `windows` evenly spaced training windows (all of them if fewer). With
        `quantile`, its margin is that quantile of the support distances of the training windows
        halfway between the bank's (the data's own pairs, not in the bank; none: margin 0)."""
        total = len(segments.starts["train"])
        if not total:
            raise ValueError("the segments hold no training windows")
        idx = np.unique(np.linspace(0, total - 1, min(windows, total)).round().astype(np.int64))
        starts, skills = _pairs(model, segments, idx, batch)
        support = cls(starts, skills)
        between = np.setdiff1d((idx[:-1] + idx[1:]) // 2, idx)
        if quantile is not None and len(between):
            own = support.distance(*_pairs(model, segments, between, batch))
            support.margin = float(torch.quantile(own.double(), quantile))
        return support

    def _features(self, states_n: torch.Tensor, skills: torch.Tensor) -> torch.Tensor:
        return torch.cat([states_n * self._state_w, skills * self._skill_w], dim=-1)

    def excess(self, states_n: torch.Tensor, skills: torch.Tensor) -> torch.Tensor:
        """The support distance beyond the margin, `[...]` (0 for pairs as near the bank as
        most of the data's own): what the planner pays for."""
        return (self.distance(states_n, skills) - self.margin).clamp_min(0.0)

    def distance(self, states_n: torch.Tensor, skills: torch.Tensor) -> torch.Tensor:
        """Support distance `[...]` of pairs `states_n [..., sd]` (normalized), `skills [..., z]`:
        the squared distance to the nearest bank pair (state part: mean over the state's dims;
        skill part: mean over the skill's dims of the difference over the bank's spread)."""
        shape = states_n.shape[:-1]
        x = self._features(states_n, skills).reshape(-1, self.bank.shape[-1])
        out = []
        for block in x.split(_ROWS):
            # ||x - b||^2 = ||x||^2 + ||b||^2 - 2 x.b: one matrix product per block
            d = torch.addmm(self._bank_sq, block, self.bank.T, alpha=-2.0)
            out.append(d.amin(dim=-1) + block.pow(2).sum(dim=-1))
        return torch.cat(out).clamp_min(0.0).reshape(shape)


def _pairs(
    model: SkillModel, segments: Segments, idx: np.ndarray, batch: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Training windows `idx`: their first states (normalized) and posterior mean skills."""
    device = model.state_mean.device
    starts, skills = [], []
    for lo in range(0, len(idx), batch):
        states, actions = segments.windows("train", idx[lo : lo + batch])
        s = torch.as_tensor(states, device=device)
        a = torch.as_tensor(actions, device=device)
        mean, _ = model.infer_skill(s[:, :-1], a)
        starts.append(model.norm_states(s[:, 0]))
        skills.append(mean)
    return torch.cat(starts), torch.cat(skills)
