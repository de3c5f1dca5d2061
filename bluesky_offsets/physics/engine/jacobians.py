"""Exact Jacobians: every ray's derivatives in the inputs, and the products' from them.

:meth:`TorchEngine.ray_jacobian <..torch_twin.TorchEngine.ray_jacobian>` traces each ray with
derivatives as a configuration of its own (:func:`_kept_ray_grads`); :class:`RayJacobian` holds the
rays with their derivatives and bins them into histograms with their Jacobian (:func:`_hist_jacobian`).
:func:`_batched_grad` is the batched backward pass the whole-batch Jacobians use, and
:data:`FORWARD_AD` the lock every use of forward-mode AD holds.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any

import torch

from bluesky_offsets.physics.engine.binning import _hist
from bluesky_offsets.physics.engine.compiling import CompiledBeamline, _replace_tensors
from bluesky_offsets.physics.engine.sampling import SourceUnits, source_rays
from bluesky_offsets.physics.engine.tracing import trace_rays
from bluesky_offsets.physics.traces import HistogramSpec

# soft weight below which a ray's derivatives are taken as 0 (TorchEngine.ray_jacobian): each is
# bounded by the weight times its apertures' logistic slopes (|dw/dθ| / w up to about 6e4 per
# unit of an input, the exit slit's height), so below 1e-16 beneath the rounding of any product
# of the rays, and fewer rays are traced for their derivatives (docs/benchmarks.md, "Per-ray Jacobian")
RAY_WEIGHT_FLOOR = 1e-16
#: Held by every use of forward-mode AD (``torch.autograd.forward_ad``, ``torch.func.jvp``).
#: Its dual level is one for the whole process: torch refuses a second one, and the level a
#: thread leaves is gone for the thread still inside it ("Trying to access a forward AD level
#: with an invalid index").  Fits
#: run side by side on threads (:func:`bluesky_offsets.model.fit.gather`); reverse mode, what
#: they mostly use, is safe there.
FORWARD_AD = threading.RLock()


def _kept_ray_grads(bl: CompiledBeamline, fields: list[torch.Tensor], live: list[int], dfield_live: torch.Tensor,
                    rays_k: SourceUnits, conf: torch.Tensor, edge: float) -> list[torch.Tensor]:
    """The derivatives (K, P) of the kept rays' x, y and soft weight in the inputs.

    As :meth:`TorchEngine.ray_jacobian <..torch_twin.TorchEngine.ray_jacobian>` returns them: each
    ray ``k`` traced as a configuration of its own (of ``conf[k]``, its randomness ``rays_k``) with
    its own copy of the live compiled fields (``fields[i]`` for ``i`` in ``live``) as leaves,
    chained with its configuration's d field / d input ``dfield_live`` (C, F', P).
    """
    c, k_n, n_live = bl.n_configs, int(conf.numel()), dfield_live.shape[1]
    sub: list[Any] = [t.detach()[conf] for t in fields]  # tensors, the live ones as tuples of entries
    # the live fields' entries as leaves, in the order of their flattening: frame
    # matrices and shifts as tuples of entries (see _entries), the rest whole
    comps: list[torch.Tensor] = []
    for i in live:
        t = sub[i]
        if t.ndim == 2 and t.shape[1] == 1:
            comps.append(t.requires_grad_(True))
            continue
        ent = [e.clone().requires_grad_(True) for e in t.reshape(k_n, -1).unbind(1)]
        comps += ent
        sub[i] = tuple(ent) if t.ndim == 2 else tuple(tuple(ent[3 * a:3 * a + 3]) for a in range(3))
    per_config = torch.bincount(conf, minlength=c).tolist()
    with torch.enable_grad():
        bl_k = _replace_tensors(bl, c, iter(sub), k_n)
        beam = trace_rays(bl_k, source_rays(bl_k, rays_k), rays_k.draws, edge=edge)
        # (F', K): one row per live field entry, one buffer for the three outputs
        buf = torch.empty(n_live, k_n, dtype=dfield_live.dtype, device=dfield_live.device)
        grads = []
        for k, out in enumerate((beam.x, beam.y, beam.weight)):
            g = torch.autograd.grad(out.sum(), comps, retain_graph=k < 2, allow_unused=True)
            torch.cat([(gi if gi is not None else torch.zeros_like(t)).reshape(1, k_n)
                       for gi, t in zip(g, comps)], 0, out=buf)
            # each kept ray's field derivatives times its configuration's d field / d
            # input, as (P, K) products of the buffer's contiguous rows instead of (K, P)
            # ones of its transpose; the rays' rows are a view of them
            grads.append(torch.cat([dfield_live[j].T @ blk for j, blk in
                                    enumerate(buf.split(per_config, 1)) if blk.shape[1]], 1).T)
    return grads


@dataclass
class RayJacobian:
    """Rays at the screen (C, N) with their derivatives in the P inputs ``names``.

    Values are RAYX's (hard survival ``alive``); the derivatives are those of the soft beam
    (weights that fall off over ``edge`` of each aperture), the smooth version of the same
    rays whose expectation the hard beam's counts follow.  Only the rays whose soft weight is
    above :data:`RAY_WEIGHT_FLOOR` have derivatives: ``rows`` (K,) are their flat indices
    (configuration-major) and ``rows_jx``, ``rows_jy``, ``rows_jw`` (K, P) their derivatives;
    every other ray's are 0 to rounding (:attr:`jx` etc. give them all, (C, N, P)).
    """

    x: torch.Tensor
    y: torch.Tensor
    alive: torch.Tensor
    weight: torch.Tensor
    rows: torch.Tensor
    rows_jx: torch.Tensor
    rows_jy: torch.Tensor
    rows_jw: torch.Tensor
    n_rays: int
    names: list[str]

    def _dense(self, t: torch.Tensor) -> torch.Tensor:
        c, n = self.x.shape
        out = torch.zeros(c * n, t.shape[1], dtype=t.dtype, device=t.device)
        out[self.rows] = t
        return out.reshape(c, n, -1)

    @property
    def jx(self) -> torch.Tensor:
        """Every ray's x derivatives (C, N, P), 0 for the rays outside ``rows``."""
        return self._dense(self.rows_jx)

    @property
    def jy(self) -> torch.Tensor:
        """Every ray's y derivatives (C, N, P), 0 for the rays outside ``rows``."""
        return self._dense(self.rows_jy)

    @property
    def jw(self) -> torch.Tensor:
        """Every ray's soft weight derivatives (C, N, P), 0 for the rays outside ``rows``."""
        return self._dense(self.rows_jw)

    def histograms(self, spec: HistogramSpec, kernel: float = 1.0,
                   soft: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """The x then y histograms (C, bins_x + bins_y) as fractions of source rays, and their Jacobian.

        The Jacobian (C, bins_x + bins_y, P) is the soft beam's, binned with a Gaussian kernel of
        ``kernel`` bins rms.  The values are RAYX's (hard counts, RAYX's binning), or with
        ``soft`` the soft beam's, whose derivative the Jacobian is (a smooth objective).
        """
        w = self.weight if soft else self.alive.to(self.x.dtype)
        hx = _hist(self.x, w, spec.bins_x, spec.range_x, soft, kernel)
        hy = _hist(self.y, w, spec.bins_y, spec.range_y, soft, kernel)
        c, n = self.x.shape
        conf, wk = self.rows // n, self.weight.reshape(-1)[self.rows]
        jx = _hist_jacobian(c, conf, self.x.reshape(-1)[self.rows], wk, self.rows_jx, self.rows_jw,
                            spec.bins_x, spec.range_x, kernel)
        jy = _hist_jacobian(c, conf, self.y.reshape(-1)[self.rows], wk, self.rows_jy, self.rows_jw,
                            spec.bins_y, spec.range_y, kernel)
        return torch.cat([hx, hy], 1) / self.n_rays, torch.cat([jx, jy], 1) / self.n_rays


def _hist_jacobian(c, conf, v, w, jv, jw, bins, rng, kernel):
    """d/dθ of Σ_i w_i K_b(v_i) for Gaussian-kernel bins K_b: Σ_i (K_b jw_i + w_i K_b' jv_i).

    The sum runs over the rays i of configuration ``conf[i]`` (of ``c``) with derivatives, each (K,).
    """
    lo, hi = rng
    p = jv.shape[1]
    scale = bins / (hi - lo)
    pos = (v - lo) * scale
    reach = int(math.ceil(4 * kernel)) + 1
    centre = pos.floor().long()
    near = torch.nonzero((centre > -reach) & (centre < bins + reach - 1)).squeeze(1)
    ci, pos, centre, w = conf[near], pos[near], centre[near], w[near]
    jv, jw = jv[near] * scale, jw[near]
    out = torch.zeros(c * (bins + 2 * reach), p, dtype=jv.dtype, device=jv.device)
    root2 = math.sqrt(2.0) * kernel
    norm = 1.0 / (math.sqrt(2.0 * math.pi) * kernel)
    for k in range(-reach, reach + 1):
        j = centre + k
        left, right = (j - pos) / root2, (j + 1 - pos) / root2
        mass = 0.5 * (torch.erf(right) - torch.erf(left))
        # d mass / d pos = pdf(left edge) - pdf(right edge)
        dmass = norm * (torch.exp(-left * left) - torch.exp(-right * right))
        idx = ci * (bins + 2 * reach) + (j + reach).clamp(0, bins + 2 * reach - 1)
        out.index_add_(0, idx, mass[:, None] * jw + (w * dmass)[:, None] * jv)
    return out.reshape(c, bins + 2 * reach, p)[:, reach:reach + bins]


def _batched_grad(part: torch.Tensor, inputs: list[torch.Tensor]) -> torch.Tensor:
    """The derivatives d part[c, k] / d inputs[c, ...] for every k, as (C, m, n_in).

    All in one batched backward pass: the configurations are independent, so summing over them
    separates nothing.
    """
    c, m = part.shape
    eye = torch.eye(m, dtype=part.dtype, device=part.device)[:, None, :].expand(m, c, m)
    try:
        grads = torch.autograd.grad(part, inputs, grad_outputs=eye, retain_graph=True, allow_unused=True,
                                    is_grads_batched=True)
    except RuntimeError:  # an op without a batching rule: one pass per component
        per = [torch.autograd.grad(part[:, k].sum(), inputs, retain_graph=True, allow_unused=True)
               for k in range(m)]
        grads = tuple(torch.stack([g[i] if g[i] is not None else torch.zeros_like(t) for g in per])
                      for i, t in enumerate(inputs))
    cols = [(g if g is not None else torch.zeros((m, *t.shape), dtype=t.dtype, device=t.device)).reshape(m, c, -1)
            for g, t in zip(grads, inputs)]
    return torch.cat(cols, 2).permute(1, 0, 2)
