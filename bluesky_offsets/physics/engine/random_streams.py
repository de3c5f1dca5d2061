"""Random streams of the differentiable twin: RAYX's own, and a fast one.

RAYX draws every random number of a ray from a counter-based generator ("Squares",
Widynski 2020) whose counter starts at ``i * floor((2^64 - 1) / N) + floor(seed * 2^64)``
for ray ``i`` of ``N`` and moves on by one per draw; the per-trace ``seed`` is the first
output of a Mersenne twister seeded by ``rayx::fixSeed`` (RAYX-CONVENTIONS.md §3).  This
module reproduces that stream in torch (int64 arithmetic wraps like RAYX's uint64), so the
twin emits RAYX's source rays and slit kicks for the same seed, and keeps a fast stream
(torch's generator, inverse-CDF slit kicks) with the same distributions for everyday work.

Pure functions; no state beyond what the caller holds.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch

_KEY = 0xC8E4FD154CE32F6D
_KEY_I64 = _KEY - (1 << 64)  # the same 64 bits as a signed int64
_LOW32 = 0xFFFFFFFF
TWO_PI = 2.0 * math.pi


def _rot32(x: torch.Tensor) -> torch.Tensor:
    return (x << 32) | ((x >> 32) & _LOW32)


def squares64(ctr: torch.Tensor) -> torch.Tensor:
    """RAYX's Squares draw at counter ``ctr`` (int64 holding the uint64 bits)."""
    y = x = ctr * _KEY_I64
    z = y + _KEY_I64
    x = _rot32(x * x + y)
    x = _rot32(x * x + z)
    x = _rot32(x * x + y)
    t = x * x + z
    x = _rot32(t)
    return t ^ (((x * x + y) >> 32) & _LOW32)


def squares_uniform(ctr: torch.Tensor, dtype=torch.float64) -> torch.Tensor:
    """``double(draw) / double(2^64 - 1)`` as RAYX computes it, in [0, 1]."""
    out = squares64(ctr)
    hi = ((out >> 32) & _LOW32).to(torch.float64)
    lo = (out & _LOW32).to(torch.float64)
    # hi * 2^32 and lo are exact; their sum rounds once, as RAYX's uint64 -> double does
    return ((hi * 4294967296.0 + lo) / 18446744073709551616.0).to(dtype)


def squares_normal(ctr: torch.Tensor, dtype=torch.float64) -> torch.Tensor:
    """A standard normal from three draws at ``ctr, ctr+1, ctr+2`` (RAYX's Box–Muller)."""
    u = squares_uniform(ctr, torch.float64)
    v = squares_uniform(ctr + 1, torch.float64)
    r = squares_uniform(ctr + 2, torch.float64)
    z = torch.sqrt(-2.0 * torch.log(u))
    return (z * torch.where(r < 0.5, torch.sin(TWO_PI * v), torch.cos(TWO_PI * v))).to(dtype)


def rayx_trace_seed(fix_seed: int) -> float:
    """The seed RAYX's next ``trace()`` uses after ``rayx::fixSeed(fix_seed)``.

    It is the first output of ``std::mt19937(fix_seed)`` over 4294967295 (numpy's legacy seeding
    is the same Mersenne twister initialisation).
    """
    first = int(np.random.RandomState(int(fix_seed) & 0xFFFFFFFF).randint(0, 1 << 32, dtype=np.uint64))
    return first / 4294967295.0


def rayx_counters(n_rays: int, trace_seed: float, start: int = 0, stop: int | None = None,
                  device="cpu") -> torch.Tensor:
    """Initial counters of rays ``start .. stop`` of a RAYX trace of ``n_rays`` rays."""
    stop = n_rays if stop is None else stop
    step = ((1 << 64) - 1) // int(n_rays)
    base = int(trace_seed * 18446744073709551616.0) % (1 << 64)
    i = torch.arange(start, stop, dtype=torch.int64, device=device)
    return i * _as_i64(step) + _as_i64(base)


def _as_i64(v: int) -> int:
    v %= 1 << 64
    return v - (1 << 64) if v >= 1 << 63 else v


FRAUNHOFER_PASS, FRAUNHOFER_TRIES = 1 << 15, 16
"""Draws of one pass of :func:`fraunhofer_uniform_rayx`, and the most tries a pending ray takes in one."""


def fraunhofer_uniform_rayx(ctr: torch.Tensor, dim_mm, wavelength_nm) -> tuple[torch.Tensor, torch.Tensor]:
    """RAYX's rejection sampler of a rectangular slit's Fraunhofer kick (one dimension).

    Returns the accepted first uniform ``u`` (the kick is ``(u - 0.5) * 10 λ / b``) and the
    counters after the draws.  Every try takes two draws; rays with ``dim_mm == 0`` take none
    and get ``u = 0.5`` (no kick).  No gradients flow through the choice of ``u``.  Each pass
    draws several tries per pending ray where they are few (:data:`FRAUNHOFER_PASS`) and keeps
    the first accepted: the same draws and the same choice as one try at a time, in far fewer
    passes (about ten tries a ray on average, over a hundred for the slowest of thousands).
    """
    with torch.no_grad():
        dim = torch.as_tensor(dim_mm, dtype=torch.float64, device=ctr.device)
        wl = torch.as_tensor(wavelength_nm, dtype=torch.float64, device=ctr.device)
        ctr, dim, wl = torch.broadcast_tensors(ctr, dim, wl)
        ctr = ctr.clone()
        u_acc = torch.full(ctr.shape, 0.5, dtype=torch.float64, device=ctr.device)
        pending = (dim != 0).reshape(-1)
        flat_ctr, flat_u = ctr.reshape(-1), u_acc.reshape(-1)
        b_all = dim.reshape(-1) * 1e06
        wl_all = wl.reshape(-1)
        idx = pending.nonzero().squeeze(1)
        while idx.numel():
            block = max(1, min(FRAUNHOFER_TRIES, FRAUNHOFER_PASS // idx.numel()))
            tries = 2 * torch.arange(block, dtype=torch.int64, device=ctr.device)
            c = flat_ctr[idx][:, None] + tries  # (rays, block): each try's first counter
            u1, u2 = squares_uniform(c), squares_uniform(c + 1)
            b, w = b_all[idx][:, None], wl_all[idx][:, None]
            angle = (u1 - 0.5) * (10.0 * w / b)
            v = math.pi * b * torch.sin(angle) / w
            wd = torch.where(v != 0, (torch.sin(v) / torch.where(v != 0, v, 1.0)) ** 2, 1.0)
            ok = wd - u2 >= 0
            hit, first = ok.any(1), ok.to(torch.uint8).argmax(1)  # argmax: the first accepted try
            rows = torch.arange(len(idx), device=ctr.device)
            flat_u[idx[hit]] = u1[rows[hit], first[hit]]
            flat_ctr[idx] = torch.where(hit, c[rows, first], c[:, -1]) + 2
            idx = idx[~hit]
        return flat_u.reshape(ctr.shape), flat_ctr.reshape(ctr.shape)


@lru_cache(maxsize=4)
def _sinc2_quantiles(n: int = 1 << 14) -> np.ndarray:
    """Quantiles of the density ∝ sinc²(πt) on [-5, 5], at ``n + 1`` evenly spaced probabilities.

    The density is that of the kick in units of λ/b that RAYX's rejection sampler accepts.
    """
    t = np.linspace(-5.0, 5.0, 2_000_001)
    dens = np.sinc(t) ** 2  # numpy's sinc is sin(πt)/(πt)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(t))])
    cdf /= cdf[-1]
    return np.interp(np.linspace(0.0, 1.0, n + 1), cdf, t)


def fraunhofer_uniform_fast(u: torch.Tensor) -> torch.Tensor:
    """The same accepted ``u`` as :func:`fraunhofer_uniform_rayx` in distribution, from one uniform draw.

    The draw goes through the inverse CDF (no rejection loop).
    """
    q = torch.as_tensor(_sinc2_quantiles(), dtype=torch.float64, device=u.device)
    n = q.numel() - 1
    pos = u.to(torch.float64).clamp(0.0, 1.0) * n
    i = pos.floor().clamp(max=n - 1).long()
    frac = pos - i
    t = q[i] + frac * (q[i + 1] - q[i])
    return 0.5 + t / 10.0
