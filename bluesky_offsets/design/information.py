"""What a frame would teach about the offsets, before it is taken.

The torch twin's Jacobian is exact (:meth:`~bluesky_offsets.physics.engine.TorchEngine.ray_jacobian`),
so the Fisher information of a frame at any setting of the motors, the slits and the chamber's
stage follows from the model at the current estimate of the offsets:

    F_c = J_cᵀ diag(1 / var_c) J_c,   var_cb = p_cb (1 / N + 1 / K)

with ``J_c`` the derivative of the frame's profiles in the normalized offsets, ``p_cb`` the
profile's fraction of source photons in bin ``b``, ``N`` photons in a frame and ``K`` the model
rays a fit traces for it (the fit compares counted frames with a counted model: both count).

The Jacobian is estimated from rays; squared, its sampling noise would add information that is
not there.  Two independent halves of the rays give ``J_a`` and ``J_b``, and the cross product
``(J_aᵀ W J_b + J_bᵀ W J_a) / 2`` has the true Fisher matrix as its expectation; its negative
eigenvalues (sampling noise) are set to zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bluesky_offsets.physics.parameters import MAX_OFFSET, METRIXS, ParameterTable
from bluesky_offsets.physics.screen import tensor_overrides
from bluesky_offsets.physics.twin import CAMERA, HistogramSpec

DESIGN_BINS = (2, 2)
"""Camera bins summed into one bin of the design's profiles (x, y): 40 µm x 10 µm."""
HALF_SEED = 1_000_033
"""Added to the seed of the first half of the rays for the second (streams the first never traces)."""


def design_spec(spec: HistogramSpec = CAMERA, factor: tuple[int, int] = DESIGN_BINS) -> HistogramSpec:
    """The camera's binning with ``factor`` bins summed (x, y)."""
    return HistogramSpec(spec.bins_x // factor[0], spec.range_x, spec.bins_y // factor[1], spec.range_y)


@dataclass(frozen=True)
class FrameInformation:
    """What each candidate frame would teach about the offsets, and how much light it puts on the screen.

    Per candidate frame: its Fisher matrix in the normalized offsets ``(C, P, P)``, the share of
    the source's photons it puts on the screen and that share's gradient in the offsets ``(C, P)``.
    """

    fisher: np.ndarray
    intensity: np.ndarray
    gradient: np.ndarray

    def __len__(self) -> int:
        return len(self.intensity)

    def intensity_sigma(self, covariance: np.ndarray) -> np.ndarray:
        """The linearized spread of each frame's intensity under a posterior of the offsets."""
        g = self.gradient
        return np.sqrt(np.clip(np.einsum("cp,pq,cq->c", g, covariance, g), 0.0, None))


def positive_part(f: np.ndarray) -> np.ndarray:
    """The symmetric matrix (or stack) ``f`` with its negative eigenvalues set to 0."""
    w, v = np.linalg.eigh(0.5 * (f + np.swapaxes(f, -1, -2)))
    return np.einsum("...ij,...j,...kj->...ik", v, np.clip(w, 0.0, None), v)


def frame_information(engine, configurations: np.ndarray, offsets: np.ndarray, *, photons: int, model_rays: int,
                      rays: int = 2000, screen=None, seed: int = 0, spec: HistogramSpec | None = None,
                      table: ParameterTable = METRIXS, chunk: int = 64, psd: bool = True) -> FrameInformation:
    """The Fisher information of frames at ``configurations`` for a beamline whose offsets are ``offsets``.

    ``configurations``: (C, P) twin coordinates; the stage at positions ``screen`` ((C, 3) mm or
    None); ``offsets`` normalized; each frame of ``photons`` source photons fitted with
    ``model_rays`` model rays.

    ``engine`` is a :class:`~bluesky_offsets.physics.engine.TorchEngine` with a random stream
    per configuration (``common_rays=False``); ``rays`` of it per candidate, in two halves.
    ``spec``: the profiles' binning (default :func:`design_spec`).  ``psd``: each frame's matrix
    with its negative eigenvalues (the rays' noise) set to 0, as a choice needs it; False keeps the
    unbiased estimate, whose sum over frames is to be made positive semi-definite only as a whole
    (clipping frame by frame keeps every frame's positive noise: information that is not there).
    """
    cfg = table.validate(np.atleast_2d(configurations), "candidate configurations")
    off = np.clip(table.validate(offsets, "offsets"), -MAX_OFFSET, MAX_OFFSET)
    spec = spec or design_spec()
    span = torch.as_tensor(table.span, dtype=torch.float64)
    n = len(cfg)
    fisher, inten, grad = np.zeros((n, len(table), len(table))), np.zeros(n), np.zeros((n, len(table)))
    inv_var_scale = 1.0 / (1.0 / photons + 1.0 / model_rays)
    half = max(1, int(rays) // 2)
    for a in range(0, n, chunk):
        b = min(n, a + chunk)
        vals = cfg[a:b] + off * table.span
        ov = None if screen is None else tensor_overrides(np.asarray(screen)[a:b], b - a)
        parts = []
        for s in (seed + a, seed + a + HALF_SEED):
            rj = engine.ray_jacobian(vals, n_rays=half, seed=s, overrides=ov)
            h, J = rj.histograms(spec, engine.options.kernel)
            parts.append((h.numpy(), (J[..., :len(table)] * span).numpy()))
        (ha, ja), (hb, jb) = parts
        p = np.maximum(0.5 * (ha + hb), 1.0 / photons)
        w = inv_var_scale / p
        cross = np.einsum("cbp,cb,cbq->cpq", ja, w, jb)
        sym = 0.5 * (cross + np.swapaxes(cross, 1, 2))
        fisher[a:b] = positive_part(sym) if psd else sym
        # on the screen: within the x window (x profile) and the y window (y profile), the lesser
        nx = spec.bins_x
        sx, sy = 0.5 * (ha[:, :nx].sum(1) + hb[:, :nx].sum(1)), 0.5 * (ha[:, nx:].sum(1) + hb[:, nx:].sum(1))
        gx, gy = 0.5 * (ja[:, :nx].sum(1) + jb[:, :nx].sum(1)), 0.5 * (ja[:, nx:].sum(1) + jb[:, nx:].sum(1))
        inten[a:b] = np.minimum(sx, sy)
        grad[a:b] = np.where((sx <= sy)[:, None], gx, gy)
    return FrameInformation(fisher, inten, grad)
