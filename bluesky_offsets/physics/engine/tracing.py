"""The element-by-element trace: the METRIXS beamline traced in PyTorch with RAYX's physics.

RAYX (the reference engine, and the simulated IOC's "real beamline") has no gradients and
no batch interface.  This engine traces the same beamline, element by element, in RAYX's
conventions (``../shared/reference/RAYX-CONVENTIONS.md``; RAYX's source, hz-b/rayx), batched
over configurations and rays, on CPU or CUDA, differentiable in every parameter:

* **frames** come from the project's own geometry (:mod:`..geometry`, :func:`..metrixs.beamline_state`):
  the same code writes RAYX's RML, here evaluated on tensors;
* **surfaces**: planes (slits, plane mirror, image plane), RAYX's quadrics with its
  dominant-axis root (cylinder, sphere/spherical grating, ellipsoid with ``figureRotation``),
  the toroid by RAYX's Newton iteration; rectangular and elliptical outlines;
* **behaviours**: reflection, RAYX's vector grating equation (with its ``cos δ`` factor),
  slits (absorption, Fraunhofer kicks), the transparent image plane; slope errors as RAYX
  perturbs the normal;
* **random numbers**: ``sampling="rayx"`` draws RAYX's own stream (same source rays and slit
  kicks for the same seed), ``"fast"`` torch's generator with the same distributions.

What it does not do: the non-sequential search.  RAYX tests every element at every step;
a ray counts for the focus only if it meets the elements in order (:func:`..twin.footprint`),
so tracing them in order gives the same surviving rays and hit points.  One consequence:
RAYX also draws slope errors for elements a ray *could* have hit next (RAYX-CONVENTIONS.md
§7); here only the element hit draws, so with slope errors on the two streams part ways
after the first such candidate (same distribution, other rays).

Gradients: hit points, directions and the rays' screen positions are smooth functions of
the parameters.  Survival is not: a ray inside or outside an outline, a slit opening or a
histogram bin is a step.  ``edge > 0`` replaces the outline and opening steps by logistic
weights over ``edge`` times the aperture (the "soft" beam), and the histograms and camera
profiles by kernel binning, so that intensities and rms widths carry the rays crossing an
edge in their derivatives.  Hard steps remain where no ray of a usable beam sits (a missed
quadric, an evanescent grating order, a failed toroid iteration); RAYX's rejection-sampled
slit kicks depend on the opening only through the accepted draw's scale, which is smooth.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.engine import random_streams as rnd
from bluesky_offsets.physics.engine.compiling import CompiledBeamline, _take_optic
from bluesky_offsets.physics.engine.sampling import Draws, LazyDraws, Rays
from bluesky_offsets.physics.engine.surfaces import (SEARCH_SHIFT, _detach, _inside_rect, _plane_hit, _poly,
                                                     _quadric_hit, _toroid_hit, _toroid_rehit, _where_safe, _zero)


HC_EV_NM = 1239.841984332002622  # RAYX's h·c in eV·nm
# a compacting trace gathers the rays still in flight once fewer than this share of those
# traced are (a gather costs about one element's arithmetic on the survivors)
COMPACT_BELOW = 0.8


@dataclass
class Beam:
    """Rays at the screen of a batch: tensors (C, N)."""

    x: torch.Tensor  # screen X (RAY-UI X), mm; arbitrary where not alive
    y: torch.Tensor  # screen Y (vertical)
    alive: torch.Tensor  # bool: the ray reached the screen the way light does
    weight: torch.Tensor  # soft survival (equals alive where edge = 0)
    n_rays: int
    hits: dict[str, torch.Tensor] | None = None  # element -> (C, N, 3) local hit points
    directions: dict[str, torch.Tensor] | None = None  # element -> (C, N, 3) local, after it

    def slice(self, a: int, b: int) -> Beam:
        """Rays ``a`` to ``b`` of every configuration (as :meth:`Rays.slice`)."""
        def per(d):
            return None if d is None else {k: t[:, a:b] for k, t in d.items()}
        return Beam(self.x[:, a:b], self.y[:, a:b], self.alive[:, a:b], self.weight[:, a:b], b - a,
                    per(self.hits), per(self.directions))


def _entries(m) -> tuple:
    """A matrix (C, 3, 3) or vector (C, 3) as nested tuples of its entries (C,).

    One given as such (:meth:`TorchEngine.ray_jacobian`: every entry a leaf of its own) is
    returned as it is.  Entries by unbind, not by indexing: the backward of one index writes the
    whole matrix per entry, which had made 60 % of a per-ray Jacobian (each ray has its own
    matrices there).
    """
    if isinstance(m, tuple):
        return m
    return tuple(_entries(row) for row in m.unbind(1)) if m.ndim > 2 else m.unbind(1)


def _apply(rot, shift, x, y, z):
    r = [[e[:, None] for e in row] for row in _entries(rot)]  # (C, 1) broadcast over rays
    out = [_poly((r[k][0], x), (r[k][1], y), (r[k][2], z)) for k in range(3)]
    if shift is None:
        return tuple(out)
    return tuple(o + s[:, None] for o, s in zip(out, _entries(shift)))


# long: the element loop carries the beam's state in a dozen tensors; split, each part would pass them all
def trace_rays(bl: CompiledBeamline, rays: Rays, draws: Draws | LazyDraws | None = None, *, edge: float = 0.0,
               keep_hits: bool = False, compact: bool = False) -> Beam:
    """Trace source-frame rays through the optics in order (see the module doc).

    ``edge > 0`` makes the beam soft (weights, for gradients); the hard ``alive`` mask is
    RAYX's survival either way.  ``compact`` (hard beam only) drops the rays an element
    stopped before the next one, once they are more than :data:`COMPACT_BELOW` of those
    traced: each survivor goes on as a configuration of its own (its fields gathered), so
    a batch pays for the rays that are still in flight.  Element by element the arithmetic
    is the same, so the surviving rays and their positions are bit for bit the dense
    trace's; the stopped rays' positions are 0.
    """
    if compact and (edge > 0 or keep_hits):
        raise InputError("compact traces the hard beam only (edge = 0, no hit points)")
    n = rays.x.shape[-1]
    c = bl.n_configs
    dt = bl.dtype
    index = owner = None  # once compacted: each ray's flat (C * N) place and its configuration
    x, y, z = _apply(bl.source_rot, bl.source_shift, rays.x, rays.y, rays.z)
    dx, dy, dz = _apply(bl.source_rot, None, rays.dx, rays.dy, rays.dz)
    energy = rays.energy
    ctr = rays.ctr
    alive = torch.ones((c, n), dtype=torch.bool, device=bl.device)
    valid = alive
    weight = torch.ones((c, n), dtype=dt, device=bl.device) if edge > 0 else None
    hits: dict[str, torch.Tensor] = {}
    dirs: dict[str, torch.Tensor] = {}
    wavelength = HC_EV_NM / energy  # nm
    for i, opt in enumerate(bl.optics):
        if owner is not None:  # compacted: this element's fields for the rays in flight
            opt = _take_optic(opt, c, owner)
        if i:
            x, y, z = _apply(opt.rot, opt.shift, x, y, z)
            dx, dy, dz = _apply(opt.rot, None, dx, dy, dz)
        sx, sy, sz = x + SEARCH_SHIFT * dx, y + SEARCH_SHIFT * dy, z + SEARCH_SHIFT * dz
        if opt.surface == "plane":
            (hx, hy, hz), (nx, ny, nz), ok = _plane_hit(sx, sy, sz, dx, dy, dz)
        elif opt.surface == "quadric":
            (hx, hy, hz), (nx, ny, nz), ok = _quadric_hit(opt.quadric, sx, sy, sz, dx, dy, dz)
        else:
            (hx, hy, hz), (nx, ny, nz), ok = _toroid_hit(opt.quadric, sx, sy, sz, dx, dy, dz)
        inside = None
        if opt.cutout is not None:
            shape, w, length = opt.cutout
            if shape == 0:
                inside, soft = _inside_rect(hx, hz, w, length, edge)
            else:
                rr = (hx / (w / 2)) ** 2 + (hz / (length / 2)) ** 2
                inside = rr <= 1
                soft = torch.sigmoid((1 - rr) / (4 * edge)) if edge > 0 else None
            if soft is not None:
                weight = weight * soft
        # orient the normal against the ray
        flip = _poly((nx, dx), (ny, dy), (nz, dz)) > 0
        sgn = torch.where(flip, -1.0, 1.0).to(dt)
        nx, ny, nz = (v if _zero(v) else v * sgn for v in (nx, ny, nz))
        if opt.slope is not None:
            sag, mer = opt.slope
            if ctr is not None:
                ga, gb = rnd.squares_normal(ctr, dt), rnd.squares_normal(ctr + 3, dt)
                # only candidates draw: a forward hit inside the outline
                ctr = torch.where(ok & (True if inside is None else inside), ctr + 6, ctr)
            else:
                assert draws is not None  # the fast stream's draws come with its rays
                gab = draws.slope(dx) if isinstance(draws, LazyDraws) else draws.slopes[opt.name]
                ga, gb = gab[0].to(dt), gab[1].to(dt)
            a, b = ga * sag, gb * mer
            cb, sb, ca, sa = torch.cos(b), torch.sin(b), torch.cos(a), torch.sin(a)
            ny1 = _poly((ny, cb), (nz, sb))
            nz = _poly((nz, cb), (-1.0, ny, sb))
            nx, ny = _poly((nx, ca), (ny1, sa)), _poly((ny1, ca), (-1.0, nx, sa))
        if opt.behaviour == "mirror":
            dot = _poly((nx, dx), (ny, dy), (nz, dz))
            dx, dy, dz = (d if _zero(m) else d - 2 * dot * m for d, m in ((dx, nx), (dy, ny), (dz, nz)))
            if opt.surface == "toroid":
                ok = ok & ~_toroid_rehit(opt, hx, hy, hz, dx, dy, dz)
        elif opt.behaviour == "grating":
            dx, dy, dz, ok_g = _grating(opt, hz, nx, ny, nz, dx, dy, dz, wavelength)
            ok = ok & ok_g
        elif opt.behaviour == "slit":
            assert opt.opening is not None  # compiled for every slit
            _, w, h, stop, sw, sh = opt.opening
            opening, soft = _inside_rect(hx, hz, w, h, edge)
            if stop == 1:
                opening = opening & ~((hx.abs() < sw / 2) & (hz.abs() < sh / 2))
            elif stop == 2:
                opening = opening & ~((hx / (sw / 2)) ** 2 + (hz / (sh / 2)) ** 2 <= 1)
            inside = opening if inside is None else inside & opening
            if soft is not None:
                weight = weight * soft
            if ctr is not None:
                u_w, ctr_w = rnd.fraunhofer_uniform_rayx(ctr, _detach(w), wavelength)
                u_h, ctr_h = rnd.fraunhofer_uniform_rayx(ctr_w, _detach(h), wavelength)
                ctr = torch.where(ok & inside, ctr_h, ctr)  # absorbed rays draw no kick
            else:
                assert draws is not None  # the fast stream's draws come with its rays
                u_w, u_h = draws.slit(dx) if isinstance(draws, LazyDraws) else draws.slits[opt.name]
                if not torch.is_tensor(w) and w == 0:
                    u_w = torch.full_like(u_w, 0.5)
                if not torch.is_tensor(h) and h == 0:
                    u_h = torch.full_like(u_h, 0.5)
            dphi, dpsi = _kick(u_w, wavelength, w, dt), _kick(u_h, wavelength, h, dt)
            phi = torch.atan2(dx, dy) + dphi
            psi = -torch.asin(dz.clamp(-1.0, 1.0)) + dpsi
            dx, dy, dz = torch.cos(psi) * torch.sin(phi), torch.cos(psi) * torch.cos(phi), -torch.sin(psi)
        # RAYX's survival; the soft beam goes on past outlines and openings (its weights
        # carry them), stopped only where the geometry has no continuation
        valid = valid & ok
        alive = alive & ok & (True if inside is None else inside)
        carry = valid if edge > 0 else alive
        # stopped rays continue from a harmless place: no inf/NaN enters any later derivative
        x, y, z = (v if _zero(v) else torch.where(carry, v, 0.0) for v in (hx, hy, hz))
        dx, dy, dz = (torch.where(carry, v, d0) for v, d0 in
                      ((dx, torch.zeros_like(dx)), (dy, torch.zeros_like(dy)), (dz, torch.ones_like(dz))))
        if keep_hits:
            hits[opt.name] = torch.stack(torch.broadcast_tensors(*(torch.zeros_like(hx) if _zero(v) else v
                                                                   for v in (hx, hy, hz))), -1)
            dirs[opt.name] = torch.stack(torch.broadcast_tensors(dx, dy, dz), -1)
        if compact and i + 1 < len(bl.optics):
            in_flight = alive.reshape(-1)
            k = int(in_flight.sum())
            if k < COMPACT_BELOW * in_flight.numel():
                if k == 0:
                    break
                sel = torch.nonzero(in_flight).squeeze(1)
                cc, nn = alive.shape
                ray = sel % nn

                def pick(t):  # (..., C|1, N) -> (..., K, 1); index_select: 5x faster than t[..., conf, ray]
                    if not torch.is_tensor(t):
                        return t
                    lead = t.shape[:-2]
                    if t.shape[-2] == 1:
                        return t.reshape(*lead, nn).index_select(-1, ray)[..., None]
                    t = t.expand(*lead, cc, nn) if t.shape[-1] == 1 and nn > 1 else t
                    return t.reshape(*lead, cc * nn).index_select(-1, sel)[..., None]
                x, y, z, dx, dy, dz, wavelength, ctr = (pick(t) for t in (x, y, z, dx, dy, dz, wavelength, ctr))
                if isinstance(draws, Draws):
                    draws = Draws({kk: pick(v) for kk, v in draws.slits.items()},
                                  {kk: pick(v) for kk, v in draws.slopes.items()})
                alive = valid = torch.ones((k, 1), dtype=torch.bool, device=bl.device)
                owner = sel // nn if owner is None else owner.index_select(0, sel)
                index = sel if index is None else index.index_select(0, sel)
    if index is not None:  # back to (C, N): the compacted survivors in their places
        def scatter(v, fill):
            out = torch.full((c * n,), fill, dtype=v.dtype, device=v.device)
            out[index] = v.reshape(-1)
            return out.reshape(c, n)
        alive_full = scatter(alive, False)
        return Beam(scatter(x, 0.0), scatter(z, 0.0), alive_full, alive_full.to(dt), n)
    w_final = alive.to(dt) if weight is None else weight * valid.to(dt)
    return Beam(x.expand(c, n), z.expand(c, n), alive, w_final, n, hits if keep_hits else None,
                dirs if keep_hits else None)


def _kick(u, wavelength, dim, dt):
    """Fraunhofer kick (rad) of the accepted draw ``u`` for an opening ``dim`` mm.

    As RAYX's ``(u - 0.5) * 10 λ / b``, b in nm; none for a closed dimension, which draws nothing.
    """
    if not torch.is_tensor(dim):
        if dim == 0:
            return torch.zeros_like(u, dtype=dt)
        return (u.to(dt) - 0.5) * (10.0 * wavelength.to(dt) / (dim * 1e06))
    b = _where_safe(dim != 0, dim) * 1e06
    return torch.where(dim != 0, (u.to(dt) - 0.5) * (10.0 * wavelength.to(dt) / b), 0.0)


def _grating(opt, hz, nx, ny, nz, dx, dy, dz, wavelength):
    """RAYX's vector grating equation (RAYX-CONVENTIONS.md §8.2)."""
    nx, ny, nz = (torch.zeros_like(dx) if _zero(n) else n for n in (nx, ny, nz))
    density, order, vls = opt.grating
    zpow = 1.0
    poly = 1.0
    for k, b in enumerate(vls, start=1):
        zpow = zpow * hz
        if torch.is_tensor(b) or b != 0.0:
            poly = poly + (k + 1) * b * zpow
    delta = torch.asin(nz.clamp(-1.0, 1.0))
    cd, sd = torch.cos(delta), torch.sin(delta)
    g = order * density * poly * cd * wavelength.to(hz.dtype) * 1e-6
    eps = -torch.atan(nx / _where_safe(ny != 0, ny))
    ce, se = torch.cos(eps), torch.sin(eps)
    # k = A(δ) B(ε) d
    bx = ce * dx + se * dy
    by = -se * dx + ce * dy
    bz = dz
    kx = bx
    ky = cd * by + sd * bz
    kz = -sd * by + cd * bz
    kz = kz - g
    qq = 1 - kx * kx - kz * kz
    ok = qq > 0
    ky = torch.sqrt(_where_safe(ok, qq))
    # back: Tᵀ = B(ε)ᵀ A(δ)ᵀ
    ay = cd * ky - sd * kz
    az = sd * ky + cd * kz
    ox = ce * kx - se * ay
    oy = se * kx + ce * ay
    return ox, oy, az, ok
