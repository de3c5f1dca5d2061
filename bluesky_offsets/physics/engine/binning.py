"""Beam products: histograms, camera profiles, moments and features of the rays at the screen.

Hard binning is RAYX's (a ray's bin by its position); soft binning spreads each ray's weight over
the bins with a Gaussian kernel, differentiable in the ray positions.  Moments are sums over rays,
so chunks of a trace add up.
"""

from __future__ import annotations

import math

import torch

from bluesky_offsets.physics.engine.tracing import Beam
from bluesky_offsets.physics.traces import HistogramSpec

# the columns of features_from_moments
FEATURES = ("intensity", "centroid_x", "centroid_y", "width_x", "width_y")


def histograms(beam: Beam, spec: HistogramSpec, *, soft: bool = False, kernel: float = 1.0,
               n_source: int | None = None):
    """The x and y histograms (C, bins) as fraction of source rays (RAYX's bin convention).

    ``soft``: every ray spreads its weight over the bins with a Gaussian kernel of ``kernel``
    bins rms (differentiable in the ray positions).  ``n_source``: the source rays the fractions
    are of (default the beam's own; a chunk of a trace passes the whole trace's, so chunks add up).
    """
    w = beam.weight if soft else beam.alive.to(beam.x.dtype)
    hx = _hist(beam.x, w, spec.bins_x, spec.range_x, soft, kernel)
    hy = _hist(beam.y, w, spec.bins_y, spec.range_y, soft, kernel)
    n = beam.n_rays if n_source is None else n_source
    return hx / n, hy / n


def _hist(v, w, bins, rng, soft, kernel):
    lo, hi = rng
    c = v.shape[0]
    scale = bins / (hi - lo)
    pos = (v - lo) * scale
    if not soft:
        inside = (v >= lo) & (v <= hi) & (w > 0)
        idx = torch.clamp(pos.detach(), 0, bins - 1).long().clamp(max=bins - 1)
        idx = idx + torch.arange(c, device=v.device)[:, None] * bins
        out = torch.zeros(c * bins, dtype=v.dtype, device=v.device)
        out.index_add_(0, idx[inside], w[inside])
        return out.reshape(c, bins)
    reach = int(math.ceil(4 * kernel)) + 1
    centre = pos.detach().floor().long()
    out = torch.zeros(c, bins + 2 * reach, dtype=v.dtype, device=v.device)
    root2 = math.sqrt(2.0) * kernel
    near = (centre > -reach) & (centre < bins + reach - 1)
    centre = centre.clamp(-reach, bins + reach - 1)
    rows = torch.arange(c, device=v.device)[:, None].expand_as(centre)
    for k in range(-reach, reach + 1):
        j = centre + k
        left = torch.erf((j - pos) / root2)
        right = torch.erf((j + 1 - pos) / root2)
        part = 0.5 * (right - left) * w * near
        idx = (j + reach).clamp(0, bins + 2 * reach - 1)
        out = out.index_put((rows.reshape(-1), idx.reshape(-1)), part.reshape(-1), accumulate=True)
    return out[:, reach:reach + bins]


def moments(beam: Beam, *, soft: bool = True) -> torch.Tensor:
    """Sufficient statistics (C, 5) of the beam: Σw, Σwx, Σwy, Σwx², Σwy².

    ``w`` is the soft weight or the hard survival; the statistics are sums over rays, so chunks of
    rays add up.
    """
    w = beam.weight if soft else beam.alive.to(beam.x.dtype)
    x, y = beam.x, beam.y
    return torch.stack([w.sum(-1), (w * x).sum(-1), (w * y).sum(-1), (w * x * x).sum(-1), (w * y * y).sum(-1)], -1)


def features_from_moments(m: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Beam features (C, 5): intensity, centroid x, y, rms width x, y.

    The intensity is a fraction of source rays, centroid and width are in mm; centroid and width
    are NaN where no ray arrives.
    """
    s0 = m[..., 0]
    s0s = torch.where(s0 > 0, s0, torch.ones_like(s0))
    cx, cy = m[..., 1] / s0s, m[..., 2] / s0s
    vx = (m[..., 3] / s0s - cx * cx).clamp(min=1e-30)
    vy = (m[..., 4] / s0s - cy * cy).clamp(min=1e-30)
    out = torch.stack([s0 / n_rays, cx, cy, torch.sqrt(vx), torch.sqrt(vy)], -1)
    nan = torch.full_like(out, float("nan"))
    keep = torch.stack([torch.ones_like(s0, dtype=torch.bool)] + [s0 > 0] * 4, -1)
    return torch.where(keep, out, nan)
