"""Where a ray meets an element's surface: hit point, normal and whether it hits.

Each surface type as RAYX computes it (``../shared/reference/RAYX-CONVENTIONS.md`` §5), term by
term so that rounding agrees too: planes (slits, plane mirror, image plane), RAYX's quadrics with
its dominant-axis root (cylinder, sphere/spherical grating, ellipsoid), the toroid by RAYX's Newton
iteration; the rectangular and elliptical outlines as hard masks or logistic (soft) weights.  All
in the element's local frame, tensors (C or 1, N).
"""

from __future__ import annotations

import math

import torch

SEARCH_SHIFT = 1e-6  # mm: RAYX starts each search this far along the ray


def _zero(v) -> bool:
    """Whether ``v`` is an exact number 0: a term it multiplies is left out.

    Adding an exact zero changes no rounding, and plane hits, normals and most quadric
    coefficients are exactly zero.
    """
    return not torch.is_tensor(v) and v == 0.0


def _poly(*terms):
    """Sum of products, each term a tuple of factors; terms with an exact-zero factor are skipped.

    Factors are multiplied left to right, and terms added left to right.
    """
    out = None
    for term in terms:
        if any(_zero(f) for f in term):
            continue
        t = term[0]
        for f in term[1:]:
            t = t * f
        out = t if out is None else out + t
    return 0.0 if out is None else out


def _where_safe(cond, value, safe=1.0):
    return torch.where(cond, value, torch.as_tensor(safe, dtype=value.dtype, device=value.device))


def _detach(v):
    return v.detach() if torch.is_tensor(v) else v


def _plane_hit(px, py, pz, dx, dy, dz):
    dys = _where_safe(dy != 0, dy)
    t = -py / dys
    ok = (t >= 0) & (dy != 0)
    hx, hz = px + t * dx, pz + t * dz
    ny = -torch.sign(dy)
    return (hx, 0.0, hz), (0.0, ny, 0.0), ok


# (u, i, j): the dominant axis u of the ray parametrises the line, i and j are the others
# (RAYX's three cases, with its expressions term by term so that rounding agrees too)
_CASES = {0: (0, 1, 2), 1: (1, 0, 2), 2: (2, 0, 1)}


def _coef(q, a: int, b: int):
    """Quadric coefficient a_(a+1)(b+1) (symmetric; index 3 is the constant column)."""
    a, b = min(a, b), max(a, b)
    return q[f"a{a + 1}{b + 1}"]


def _quadric_case(q, case, p, d):
    u, i, j = _CASES[case]
    du = _where_safe(d[u] != 0, d[u])
    ei, ej = d[i] / du, d[j] / du
    ri, rj = p[i] - ei * p[u], p[j] - ej * p[u]
    a_uu, a_ui, a_ii, a_uj = _coef(q, u, u), _coef(q, u, i), _coef(q, i, i), _coef(q, u, j)
    a_ij, a_jj, a_u4, a_i4, a_j4 = _coef(q, i, j), _coef(q, j, j), _coef(q, u, 3), _coef(q, i, 3), _coef(q, j, 3)
    a = _poly((a_uu,), (2, a_ui, ei), (a_ii, ei, ei), (2, a_uj, ej), (2, a_ij, ei, ej), (a_jj, ej, ej))
    b = _poly((a_u4,), (a_i4, ei), (a_j4, ej), (_poly((a_ui,), (a_ii, ei), (a_ij, ej)), ri),
              (_poly((a_uj,), (a_ij, ei), (a_jj, ej)), rj))
    c = _poly((q["a44"],), (a_ii, ri, ri), (2, a_j4, rj), (a_jj, rj, rj), (2, ri, _poly((a_i4,), (a_ij, rj))))
    disc = b * b - a * c
    ok = disc >= 0
    root = torch.sqrt(_where_safe(ok, disc))
    sign = torch.sign(d[u]) * q["icurv"]
    quad = a.abs() > c.abs() * 1e-10
    hu = torch.where(quad, (-b + sign * root) / _where_safe(quad, a), (-c / 2) / _where_safe(~quad & (b != 0), b))
    h = [None, None, None]
    h[u], h[i], h[j] = hu, ri + ei * hu, rj + ej * hu
    return h, ok


def _quadric_hit(q, px, py, pz, dx, dy, dz):
    """RAYX's quadric intersection (RAYX-CONVENTIONS.md §5.2).

    One root, chosen by the sign of the ray's dominant direction component and the surface's
    ``icurv``.
    """
    p, d = (px, py, pz), (dx, dy, dz)
    ax, ay, az = dx.abs(), dy.abs(), dz.abs()
    use_y = (ay >= ax) & (ay >= az)
    use_z = ~use_y & (az >= ax) & (az >= ay)
    case = torch.where(use_y, 1, torch.where(use_z, 2, 0))
    present = [k for k in (2, 1, 0) if bool((case == k).any())]
    h, ok = _quadric_case(q, present[0], p, d)
    for k in present[1:]:
        hk, okk = _quadric_case(q, k, p, d)
        sel = case == k
        h = [torch.where(sel, a, b) for a, b in zip(hk, h)]
        ok = torch.where(sel, okk, ok)
    hx, hy, hz = h
    # behind the start in any coordinate (RAYX: (h - p)/d < 0; 0/0 passes)
    for hk, pk, dk in ((hx, px, dx), (hy, py, dy), (hz, pz, dz)):
        ok = ok & ~((hk - pk) / _where_safe(dk != 0, dk) < 0)
    fx = _poly((2, q["a14"]), (2, q["a11"], hx), (2, q["a12"], hy), (2, q["a13"], hz))
    fy = _poly((2, q["a24"]), (2, q["a12"], hx), (2, q["a22"], hy), (2, q["a23"], hz))
    fz = _poly((2, q["a34"]), (2, q["a13"], hx), (2, q["a23"], hy), (2, q["a33"], hz))
    norm = torch.sqrt(_poly((fx, fx), (fy, fy), (fz, fz)))
    norm = _where_safe(norm > 0, norm)
    return (hx, hy, hz), tuple(f if _zero(f) else f / norm for f in (fx, fy, fz)), ok


def _toroid_hit(q, px, py, pz, dx, dy, dz):
    """RAYX's Newton iteration on z along the ray (tolerance 1e-4 mm, 50 evaluations)."""
    big_r, rho = q["R"], q["rho"]
    s = torch.sign(torch.as_tensor(rho)) if torch.is_tensor(rho) else math.copysign(1.0, rho)
    dzs = _where_safe(dz != 0, dz)
    ex, ey = dx / dzs, dy / dzs
    zz = torch.zeros_like(px)
    delta = torch.zeros_like(px)
    active = torch.ones_like(px, dtype=torch.bool)
    ok = torch.ones_like(px, dtype=torch.bool)
    count = 0
    hx = hy = hz = gx = gy = gz = None
    while True:
        zz = torch.where(active, zz + delta, zz)
        x = px + ex * (zz - pz)
        lim = 0.95 * abs(rho) if not torch.is_tensor(rho) else 0.95 * rho.abs()
        over = x * x > (rho * rho)
        x = torch.where(over, torch.sign(x) * lim, x)
        y = py + ey * (zz - pz)
        w = torch.sqrt(_where_safe(rho * rho - x * x > 0, rho * rho - x * x))
        r = big_r - rho + s * w
        g1, g2, g3 = -2 * x * s * r / w, -2 * (y - big_r), -2 * zz
        f = -r * r + (y - big_r) ** 2 + zz * zz
        denom = ex * g1 + ey * g2 + g3
        new_delta = f / _where_safe(denom != 0, denom)
        if hx is None:
            hx, hy, hz, gx, gy, gz = x, y, zz, g1, g2, g3
        else:
            hx, hy, hz = (torch.where(active, a, b) for a, b in ((x, hx), (y, hy), (zz, hz)))
            gx, gy, gz = (torch.where(active, a, b) for a, b in ((g1, gx), (g2, gy), (g3, gz)))
        delta = torch.where(active, new_delta, delta)
        count += 1
        if count >= 50:
            ok = ok & ~(active & (delta.abs() > 1e-4))
            break
        active = active & (delta.abs() > 1e-4)
        if not bool(active.any()):
            break
    ok = ok & ((hx - px) * dx + (hy - py) * dy + (hz - pz) * dz > 0)
    norm = torch.sqrt(gx * gx + gy * gy + gz * gz)
    norm = _where_safe(norm > 0, norm)
    return (hx, hy, hz), (gx / norm, gy / norm, gz / norm), ok


def _toroid_rehit(opt, hx, hy, hz, dx, dy, dz) -> torch.Tensor:
    """Rays RAYX's toroid iteration finds on the same toroid again, just ahead of where they left it.

    See RAYX-CONVENTIONS §5.6: RAYX reflects them there until its event cap, and they are lost.
    """
    with torch.no_grad():
        d = [_detach(v) for v in (dx, dy, dz)]
        p = [_detach(h) + SEARCH_SHIFT * v for h, v in zip((hx, hy, hz), d)]
        (qx, _, qz), _, again = _toroid_hit({k: _detach(v) for k, v in opt.quadric.items()}, *p, *d)
        if opt.cutout is not None:
            shape, w, length = (_detach(v) for v in opt.cutout)
            again = again & (((qx > -w / 2) & (qx < w / 2) & (qz > -length / 2) & (qz < length / 2)) if shape == 0
                             else (qx / (w / 2)) ** 2 + (qz / (length / 2)) ** 2 <= 1)
        return again


def _sigmoid_inside(half, coord, edge):
    """Logistic weight of |coord| < half over ``edge * 2 half``; 1/0 when edge = 0."""
    if edge <= 0:
        return None
    scale = edge * 2 * half
    return torch.sigmoid((half - coord.abs()) / scale)


def _inside_rect(x, z, w, length, edge):
    hard = (x > -w / 2) & (x < w / 2) & (z > -length / 2) & (z < length / 2)
    if edge <= 0:
        return hard, None
    return hard, _sigmoid_inside(w / 2, x, edge) * _sigmoid_inside(length / 2, z, edge)
