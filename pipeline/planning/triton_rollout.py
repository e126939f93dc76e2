"""The planner's rollout and goal cost as one Triton kernel (`deploy.planner.kernel: triton`).

`SkillPlanner._rollout` followed by `GoalCost` launches about ten matrix products and as many
elementwise kernels per skill step: some 300 kernels per CEM iteration, which on a GPU take far
longer to launch and run one after another than their arithmetic takes (results/speed-gpu.md:
318 kernels per iteration, 2.9 µs each). Here one kernel does the whole rollout of a block of
candidates: all L skill steps, each the prior's five layers and the TAWM mean's four, the skills,
the predicted states and the goal cost (the distance to the goal from the predicted state nearest
to it, plus `skill_penalty` per skill, as `GoalCost`). Each program owns `BM` candidate rows; the
activations between layers go through a small per-program scratch buffer (L1/L2-resident), and
the layers are computed in `[BM, BN]` tiles, so the same kernel serves any hidden size (padded to
16) and any state and skill size (padded to powers of two); it was timed at h 128 and 256
(results/speed-gpu.md).

Numerics: float32 weights multiply in IEEE float32 (no TF32), so the kernel gives the eager
planner's rollout up to summation order (tests/test_triton_rollout.py, tests/test_gpu.py);
`bfloat16` multiplies in bfloat16 with float32 accumulation, as `PlannerNets` does.

Triton compiles for a GPU. On a machine without one, Triton's interpreter runs the same kernel
on CPU tensors through NumPy: orders of magnitude slower, which is what the CPU tests use to check
the kernel against the eager rollout. Costs other than `GoalCost`, or with a fall test, keep the
eager rollout (`SkillPlanner._fused`).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl
from triton.runtime.interpreter import InterpretedFunction

from pipeline.model.skill_model import SkillModel

INTERPRETED = not torch.cuda.is_available()
# Every function of this module is compiled for the GPU, or all are interpreted (a compiled kernel
# cannot call interpreted functions, nor the reverse).
_jit = InterpretedFunction if INTERPRETED else triton.jit

BM = 16  # candidate rows per program (tl.dot's smallest tile)

# Only `triton.language` builtins and this module's functions below: the standard library's
# jit-decorated helpers (`tl.zeros`, `tl.sum`, ...) were compiled, not interpreted, at import.


@_jit
def _add(a, b):
    return a + b


@_jit
def _dense(x_ptr, x_stride, w_ptr, b_ptr, y_ptr, y_stride, IN: tl.constexpr, OUT: tl.constexpr,
           BM: tl.constexpr, BK: tl.constexpr, BN: tl.constexpr, PREC: tl.constexpr):  # fmt: skip
    """`y[:, :OUT] = relu(x[:, :IN] @ W + b)` for the program's BM scratch rows, tile by tile."""
    rows = tl.arange(0, BM)
    ks = tl.arange(0, BK)
    ns = tl.arange(0, BN)
    for n0 in range(0, OUT, BN):
        acc = tl.full([BM, BN], 0.0, tl.float32) + tl.load(b_ptr + n0 + ns)[None, :]
        for k0 in range(0, IN, BK):
            x = tl.load(x_ptr + rows[:, None] * x_stride + (k0 + ks)[None, :])
            w = tl.load(w_ptr + (k0 + ks)[:, None] * OUT + (n0 + ns)[None, :])
            acc += tl.dot(x.to(w.dtype), w, input_precision=PREC)
        tl.store(y_ptr + rows[:, None] * y_stride + (n0 + ns)[None, :], tl.maximum(acc, 0.0))
    tl.debug_barrier()  # the next layer reads what every thread wrote


@_jit
def _dense_out(x_ptr, x_stride, w_ptr, b_ptr, IN: tl.constexpr, OUT: tl.constexpr,
               BM: tl.constexpr, BK: tl.constexpr, PREC: tl.constexpr):  # fmt: skip
    """`x[:, :IN] @ W + b` -> `[BM, OUT]` in registers (an output layer: OUT is small)."""
    rows = tl.arange(0, BM)
    ks = tl.arange(0, BK)
    ns = tl.arange(0, OUT)
    acc = tl.full([BM, OUT], 0.0, tl.float32) + tl.load(b_ptr + ns)[None, :]
    for k0 in range(0, IN, BK):
        x = tl.load(x_ptr + rows[:, None] * x_stride + (k0 + ks)[None, :])
        w = tl.load(w_ptr + (k0 + ks)[:, None] * OUT + ns[None, :])
        acc += tl.dot(x.to(w.dtype), w, input_precision=PREC)
    return acc


@_jit
def _store_skill(e_ptr, zo_ptr, x_ptr, rows, i, valid, mu, sigma, XW: tl.constexpr,
                 L: tl.constexpr, Z: tl.constexpr, SDP: tl.constexpr, ZP: tl.constexpr,
                 BM: tl.constexpr):  # fmt: skip
    """Skill i = mu + sigma * eps_i: into the scratch input `X[:, SDP:]` and the output."""
    cz = tl.arange(0, ZP)
    r = tl.arange(0, BM)
    ok = valid[:, None] & (cz[None, :] < Z)
    e = tl.load(e_ptr + (rows[:, None] * L + i) * Z + cz[None, :], mask=ok, other=0.0)
    z = mu + sigma * e
    tl.store(zo_ptr + (rows[:, None] * L + i) * Z + cz[None, :], z, mask=ok)
    tl.store(x_ptr + r[:, None] * XW + SDP + cz[None, :], z)
    tl.debug_barrier()
    return z


@_jit
def _tawm_step(x_ptr, a_ptr, b_ptr, tw_in, tb_in, tw2, tb2, tw3, tb3, two, tbo, so_ptr, rows,
               i, valid, goal, gmask, smean, sstd, best, skill_penalty, XW: tl.constexpr,
               L: tl.constexpr, SD: tl.constexpr, SDP: tl.constexpr, H: tl.constexpr,
               BM: tl.constexpr, BK: tl.constexpr, BN: tl.constexpr,
               PREC: tl.constexpr):  # fmt: skip
    """The TAWM mean from `X = [s_i | z_i]`: s_{i+1} into `X[:, :SDP]` and the outputs; the
    running goal cost."""
    _dense(x_ptr, XW, tw_in, tb_in, a_ptr, H, XW, H, BM, BK, BN, PREC)
    _dense(a_ptr, H, tw2, tb2, b_ptr, H, H, H, BM, BK, BN, PREC)
    _dense(b_ptr, H, tw3, tb3, a_ptr, H, H, H, BM, BK, BN, PREC)
    s = _dense_out(a_ptr, H, two, tbo, H, SDP, BM, BK, PREC)
    cs = tl.arange(0, SDP)
    r = tl.arange(0, BM)
    tl.store(x_ptr + r[:, None] * XW + cs[None, :], s)
    tl.debug_barrier()
    raw = s * sstd[None, :] + smean[None, :]
    tl.store(so_ptr + (rows[:, None] * (L + 1) + i + 1) * SD + cs[None, :], raw,
             mask=valid[:, None] & (cs[None, :] < SD))  # fmt: skip
    diff = raw - goal
    distance = tl.sqrt(tl.reduce(gmask[None, :] * diff * diff, 1, _add)) + skill_penalty * (i + 1)
    return tl.minimum(best, distance, propagate_nan=tl.PropagateNan.ALL)


@_jit
def _rollout_kernel(
    eps_ptr, s0_ptr, s0n_ptr, pmean0_ptr, pstd0_ptr, goal_ptr, gmask_ptr, smean_ptr, sstd_ptr,
    pw1, pb1, pw2, pb2, pwh, pbh, pwm, pbm, pws, pbs, tw_in, tb_in, tw2, tb2, tw3, tb3, two, tbo,
    so_ptr, zo_ptr, cost_ptr, scratch_ptr, R, K, skill_penalty, min_std,
    SD: tl.constexpr, Z: tl.constexpr, SDP: tl.constexpr, ZP: tl.constexpr, H: tl.constexpr,
    L: tl.constexpr, BM: tl.constexpr, BK: tl.constexpr, BN: tl.constexpr, PREC: tl.constexpr,
):  # fmt: skip
    pid = tl.program_id(0)
    rows = pid * BM + tl.arange(0, BM)
    valid = rows < R
    problem = tl.minimum(rows, R - 1) // K
    r = tl.arange(0, BM)
    cs = tl.arange(0, SDP)
    cz = tl.arange(0, ZP)
    # This program's scratch: X = [s | z] (BM x XW), then A, B (BM x H) and C (BM x 2H).
    XW: tl.constexpr = SDP + ZP
    x_ptr = scratch_ptr + pid.to(tl.int64) * (BM * (XW + 4 * H))
    a_ptr = x_ptr + BM * XW
    b_ptr = a_ptr + BM * H
    c_ptr = b_ptr + BM * H
    s_ok = cs[None, :] < SD
    s0 = tl.load(s0_ptr + problem[:, None] * SD + cs[None, :], mask=s_ok, other=0.0)
    tl.store(so_ptr + rows[:, None] * ((L + 1) * SD) + cs[None, :], s0, mask=valid[:, None] & s_ok)
    s0n = tl.load(s0n_ptr + problem[:, None] * SD + cs[None, :], mask=s_ok, other=0.0)
    tl.store(x_ptr + r[:, None] * XW + cs[None, :], s0n)
    goal = tl.load(goal_ptr + problem[:, None] * SDP + cs[None, :])
    gmask = tl.load(gmask_ptr + cs)
    smean = tl.load(smean_ptr + cs)
    sstd = tl.load(sstd_ptr + cs)
    best = tl.full([BM], float("inf"), tl.float32)
    # Skill 0: the prior at s_0, computed once per problem outside.
    z_ok = cz[None, :] < Z
    mu = tl.load(pmean0_ptr + problem[:, None] * Z + cz[None, :], mask=z_ok, other=0.0)
    sigma = tl.load(pstd0_ptr + problem[:, None] * Z + cz[None, :], mask=z_ok, other=0.0)
    _store_skill(eps_ptr, zo_ptr, x_ptr, rows, 0, valid, mu, sigma, XW, L, Z, SDP, ZP, BM)
    best = _tawm_step(x_ptr, a_ptr, b_ptr, tw_in, tb_in, tw2, tb2, tw3, tb3, two, tbo, so_ptr,
                      rows, 0, valid, goal, gmask, smean, sstd, best, skill_penalty, XW, L, SD,
                      SDP, H, BM, BK, BN, PREC)  # fmt: skip
    for i in range(1, L):
        # The prior at s_i: trunk (2 layers), the heads' hidden layers side by side, two outputs.
        _dense(x_ptr, XW, pw1, pb1, a_ptr, H, SDP, H, BM, BK, BN, PREC)
        _dense(a_ptr, H, pw2, pb2, b_ptr, H, H, H, BM, BK, BN, PREC)
        _dense(b_ptr, H, pwh, pbh, c_ptr, 2 * H, H, 2 * H, BM, BK, BN, PREC)
        mu = _dense_out(c_ptr, 2 * H, pwm, pbm, H, ZP, BM, BK, PREC)
        pre = _dense_out(c_ptr + H, 2 * H, pws, pbs, H, ZP, BM, BK, PREC)
        softplus = tl.where(pre > 20.0, pre, tl.log(1.0 + tl.exp(tl.minimum(pre, 20.0))))
        sigma = softplus + min_std
        _store_skill(eps_ptr, zo_ptr, x_ptr, rows, i, valid, mu, sigma, XW, L, Z, SDP, ZP, BM)
        best = _tawm_step(x_ptr, a_ptr, b_ptr, tw_in, tb_in, tw2, tb2, tw3, tb3, two, tbo,
                          so_ptr, rows, i, valid, goal, gmask, smean, sstd, best, skill_penalty,
                          XW, L, SD, SDP, H, BM, BK, BN, PREC)  # fmt: skip
    tl.store(cost_ptr + rows, best, mask=valid)


def _pow2(n: int) -> int:
    return max(16, 1 << (n - 1).bit_length())


def _pad(x: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """`x` zero-padded at the end of each dimension to `shape`."""
    out = x.new_zeros(shape)
    out[tuple(slice(0, n) for n in x.shape)] = x
    return out


class TritonNets:
    """The prior's and the TAWM mean's weights, transposed to `[in, out]` and zero-padded to the
    kernel's tile sizes (padded units compute 0 and feed nothing), gathered once per plan."""

    def __init__(self, model: SkillModel, dtype: torch.dtype = torch.float32):
        cfg = model.config
        self.sd, self.z = cfg.state_dim, cfg.z_dim
        self.sdp, self.zp = _pow2(self.sd), _pow2(self.z)
        self.h = -(-cfg.hidden // 16) * 16
        h, sdp, zp = self.h, self.sdp, self.zp
        self.bk = next(b for b in (64, 32, 16) if h % b == 0 and sdp % b == 0 and zp % b == 0)
        self.bn = next(b for b in (64, 32, 16) if h % b == 0)
        # Launch settings (bench/gpu_kernel.py times the alternatives): "ieee" float32 products
        # ("tf32": tensor cores, 10-bit mantissas; not the eager planner's numbers), warps.
        self.precision = "ieee" if dtype == torch.float32 else ""
        self.num_warps = 4
        self.min_std = float(model.prior.head.min_std)
        prior, tawm = model.prior, model.tawm

        def w(layer: torch.nn.Linear, rows: int, cols: int) -> torch.Tensor:
            return _pad(layer.weight.t(), (rows, cols)).to(dtype).contiguous()

        def b(layer: torch.nn.Linear, cols: int) -> torch.Tensor:
            return _pad(layer.bias, (cols,)).float().contiguous()

        head = prior.head
        hidden = torch.cat([w(head.mean[0], h, h), w(head.std[0], h, h)], dim=1).contiguous()
        first = tawm.trunk[0]  # input [s, z]: s rows at 0, z rows at sdp
        t_in = first.weight.new_zeros(sdp + zp, h)
        t_in[: self.sd, : first.out_features] = first.weight[:, : self.sd].t()
        t_in[sdp : sdp + self.z, : first.out_features] = first.weight[:, self.sd :].t()
        self.weights = [
            w(prior.trunk[0], sdp, h), b(prior.trunk[0], h),
            w(prior.trunk[2], h, h), b(prior.trunk[2], h),
            hidden, torch.cat([b(head.mean[0], h), b(head.std[0], h)]),
            w(head.mean[2], h, zp), b(head.mean[2], zp),
            w(head.std[2], h, zp), b(head.std[2], zp),
            t_in.to(dtype).contiguous(), b(first, h),
            w(tawm.trunk[2], h, h), b(tawm.trunk[2], h),
            w(tawm.head.mean[0], h, h), b(tawm.head.mean[0], h),
            w(tawm.head.mean[2], h, sdp), b(tawm.head.mean[2], sdp),
        ]  # fmt: skip
        self.state_mean = _pad(model.state_mean.float(), (sdp,))
        self.state_std = _pad(model.state_std.float(), (sdp,))
        self.state_std[self.sd :] = 1.0

    def goal_inputs(
        self, goals: torch.Tensor, dims: tuple[int, ...]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """`goals [B, G]` on state `dims` as the kernel reads them, once per plan: the goal in
        state layout `[B, SDP]` and the mask of goal dims `[SDP]`. Device ops only (no host
        copy: a CUDA graph may be capturing)."""
        goal = goals.new_zeros(len(goals), self.sdp)
        mask = goals.new_zeros(self.sdp)
        for j, d in enumerate(dims):
            goal[:, d].copy_(goals[:, j])
            mask.narrow(0, d, 1).fill_(1.0)
        return goal, mask

    def rollout_cost(
        self,
        eps: torch.Tensor,
        s0: torch.Tensor,
        s0_n: torch.Tensor,
        prior0: tuple[torch.Tensor, torch.Tensor],
        goal: tuple[torch.Tensor, torch.Tensor],
        skill_penalty: float,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Candidates `eps [B, K, L, z]` from `s0 [B, sd]` (raw; `s0_n` normalized, `prior0` its
        prior mean and std `[B, z]`) -> raw states `[B, K, L + 1, sd]` (s_0 first), skills
        `[B, K, L, z]` and the goal cost `[B, K]` of `goal` (`goal_inputs`)."""
        return torch.ops.oposm.goal_rollout(
            eps.contiguous(), s0.contiguous(), s0_n.contiguous(), prior0[0].contiguous(),
            prior0[1].contiguous(), goal[0], goal[1], self.state_mean, self.state_std,
            self.weights, float(skill_penalty), self.min_std, self.h, self.bk, self.bn,
            self.precision, self.num_warps,
        )  # fmt: skip


# An operator of its own, so `torch.compile` takes the launch as one opaque call (and a CUDA
# graph captures the kernel it launches).
@torch.library.custom_op("oposm::goal_rollout", mutates_args=())
def _goal_rollout(
    eps: torch.Tensor,
    s0: torch.Tensor,
    s0_n: torch.Tensor,
    prior_mean: torch.Tensor,
    prior_std: torch.Tensor,
    goal: torch.Tensor,
    gmask: torch.Tensor,
    state_mean: torch.Tensor,
    state_std: torch.Tensor,
    weights: list[torch.Tensor],
    skill_penalty: float,
    min_std: float,
    hidden: int,
    bk: int,
    bn: int,
    precision: str,
    num_warps: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    b, k, n_skills, z_dim = eps.shape
    sd, sdp, zp = s0.shape[1], goal.shape[1], _pow2(z_dim)
    states = eps.new_empty(b, k, n_skills + 1, sd)
    skills = torch.empty_like(eps)
    cost = eps.new_empty(b, k)
    rows = b * k
    programs = triton.cdiv(rows, BM)
    scratch = eps.new_empty(programs * BM * (sdp + zp + 4 * hidden))
    _rollout_kernel[(programs,)](
        eps, s0, s0_n, prior_mean, prior_std, goal, gmask, state_mean, state_std, *weights,
        states, skills, cost, scratch, rows, k, skill_penalty, min_std, SD=sd, Z=z_dim, SDP=sdp,
        ZP=zp, H=hidden, L=n_skills, BM=BM, BK=bk, BN=bn, PREC=precision or None,
        num_warps=num_warps,
    )  # fmt: skip
    return states, skills, cost


@_goal_rollout.register_fake
def _(eps, s0, *_args) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    b, k, n_skills, _z = eps.shape
    return (
        eps.new_empty(b, k, n_skills + 1, s0.shape[1]),
        torch.empty_like(eps),
        eps.new_empty(b, k),
    )
