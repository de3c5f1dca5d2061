"""What the beam should be: targets and constraints for :func:`~bluesky_offsets.optimize.optimizer.optimize_settings`.

A target is a least-squares problem on the rays at the screen.  Its residuals are torch
functions of the rays' positions and soft weights (:class:`Rays`), so the optimizer gets
their exact Jacobian in the motor settings from the differentiable twin by the chain rule.
Minimizing a beam size is least squares on the rays themselves (a variance is the mean
square of the rays' distances from their centroid), which is why Gauss-Newton converges on
it in a few steps.

Extending: a class with ``name``, ``residuals(rays, start)`` and ``unmet(focus)``::

    @dataclass(frozen=True)
    class NarrowX:
        name: str = "narrow x"

        def residuals(self, rays, start):
            return per_ray(rays, "x") / start.rms_x      # the x width only

        def unmet(self, focus):
            return None                                   # as small as the limits allow

Every target is frozen; building one from a mapping (:func:`target_from`) refuses unknown keys.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from bluesky_offsets.errors import InputError
from bluesky_offsets.options import refuse_unknown
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable

REFOCUSING = ("E1", "E2")
"""The refocusing mirrors: what an operator moves to focus."""

MONOCHROMATOR = tuple(p.name for p in METRIXS if p.motorized and p.component not in REFOCUSING)
"""Every motor upstream of the refocusing mirrors (source, aperture, M1, grating, exit slit): held by
default.  They set the photon energy, the resolution and the flux; moved to focus, they trim the beam
on slit edges, where the calibration knows the least, so light the model keeps there can be lost on
the true beamline (docs/explanations/optimize.md, "The closed loop, and what it gives")."""


# --------------------------------------------------------------------------- #
# the beam as a target sees it
# --------------------------------------------------------------------------- #
@dataclass
class Rays:
    """Rays at the screen of one configuration: positions (mm) and soft weights (N,), torch."""

    x: torch.Tensor
    y: torch.Tensor
    w: torch.Tensor
    n_rays: int

    @property
    def intensity(self) -> torch.Tensor:
        """Fraction of the source rays on the screen."""
        return self.w.sum() / self.n_rays

    def centroid(self, axis: str) -> torch.Tensor:
        """The light-weighted mean position along ``axis`` (``"x"`` or ``"y"``, mm)."""
        v = getattr(self, axis)
        return (self.w * v).sum() / self.w.sum().clamp(min=1e-300)

    def rms(self, axis: str) -> torch.Tensor:
        """The light-weighted rms width along ``axis`` (``"x"`` or ``"y"``, mm)."""
        v = getattr(self, axis)
        d = v - self.centroid(axis)
        return torch.sqrt(((self.w * d * d).sum() / self.w.sum().clamp(min=1e-300)).clamp(min=1e-30))


def per_ray(rays: Rays, axis: str) -> torch.Tensor:
    """Residuals whose sum of squares is the variance along ``axis``.

    Each ray's distance from the centroid, weighted by the square root of its share of the light.
    """
    v = getattr(rays, axis)
    share = rays.w / rays.w.sum().clamp(min=1e-300)
    return torch.sqrt(share.clamp(min=0)) * (v - rays.centroid(axis))


# --------------------------------------------------------------------------- #
# the beam as measured: one definition for model and frame
# --------------------------------------------------------------------------- #
@dataclass(frozen=True)
class Focus:
    """A footprint's numbers: intensity, centroid, rms width, FWHM and the widths' uncertainty.

    Intensity (fraction of source rays on the screen), centroid and rms width per axis (mm), FWHM
    per axis (mm), and the rms widths' statistical uncertainty from the rays counted (mm; NaN when
    the ray count is not known).
    """

    intensity: float
    x: float
    y: float
    rms_x: float
    rms_y: float
    fwhm_x: float = float("nan")
    fwhm_y: float = float("nan")
    sigma_rms_x: float = float("nan")
    sigma_rms_y: float = float("nan")

    def as_dict(self) -> dict[str, float]:
        """Every field as a float, by name."""
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}

    def size(self, axis: str, measure: str = "rms") -> float:
        """The width along ``axis`` (``"x"``/``"y"``) by ``measure`` (``"rms"`` or ``"fwhm"``), mm."""
        return float(getattr(self, f"{measure}_{axis}"))


def _fwhm(h: np.ndarray, centers: np.ndarray) -> float:
    if h.max() <= 0:
        return float("nan")
    half = 0.5 * h.max()
    above = np.flatnonzero(h >= half)
    i, j = above[0], above[-1]
    step = centers[1] - centers[0]

    def cross(a, b):  # where the profile crosses half between bins a (below) and b (above)
        ha, hb = h[a], h[b]
        return centers[a] + (half - ha) / (hb - ha) * (centers[b] - centers[a]) if hb != ha else centers[b]
    left = cross(i - 1, i) if i > 0 else centers[i] - 0.5 * step
    right = cross(j + 1, j) if j < len(h) - 1 else centers[j] + 0.5 * step
    return float(right - left)


WINDOW_FWHM, WINDOW_BINS = 3.0, 4
"""A focus's moments are taken within ``WINDOW_FWHM`` FWHM of its peak (at least ``WINDOW_BINS`` bins):
beyond it a camera's profile holds read noise and stray photons, whose weight grows as the distance
squared, and next to no light."""


def _window(h: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The bins within :data:`WINDOW_FWHM` FWHM (at least :data:`WINDOW_BINS` bins) of ``h``'s peak."""
    i = int(np.argmax(h))
    half = max(WINDOW_FWHM * _fwhm(np.clip(h, 0, None), c), WINDOW_BINS * (c[1] - c[0]))
    return np.abs(c - c[i]) <= half


def _width_sigma(h: np.ndarray, c: np.ndarray, m: float, var: float, n: float) -> float:
    """The rms width's σ from ``n`` rays counted, ``rms·√((κ−1)/4N)``; NaN where the light has no spread.

    κ is the kurtosis of the light's own shape: a camera's noise below zero could take it below 1.
    """
    lit = np.clip(h, 0.0, None)
    m2, m4 = (float((lit * (c - m) ** k).sum() / lit.sum()) for k in (2, 4))
    return math.sqrt(var) * math.sqrt(max(m4 / m2 ** 2 - 1.0, 0.0) / (4.0 * n)) if m2 > 0 else float("nan")


def _noise_sigma(h: np.ndarray, c: np.ndarray, inside: np.ndarray, m: float, var: float, s: float) -> float:
    """The rms width's σ from a camera profile's noise, its level read from the bins outside the window."""
    if inside.all():
        return 0.0
    level = float(np.mean(h[~inside] ** 2))  # dark-subtracted: the far bins are noise about zero
    var_var = level * float(np.sum(((c[inside] - m) ** 2 - var) ** 2)) / s ** 2
    return math.sqrt(var_var / (4.0 * var))


def focus_from_profiles(profile_x, profile_y, spec, n_rays: int | None = None) -> Focus:
    """The :class:`Focus` of x/y profiles (fraction of source rays per bin): moments over the bin centres.

    The profiles are binned as ``spec`` (a :class:`~bluesky_offsets.physics.twin.HistogramSpec`).
    Measured frames and the model's predictions are both read with this, within the same window
    about the peak (:data:`WINDOW_FWHM`).  ``n_rays``: the source rays behind the profiles (all
    frames), for the widths' statistical uncertainty (an rms of N rays scatters by
    rms·√((κ−1)/4N), κ the profile's kurtosis); a camera's profile (dark-subtracted: some bins below
    zero) adds its noise's share, read from the bins outside the window.
    """
    out = []
    for h, c in ((np.asarray(profile_x, float), spec.centers_x), (np.asarray(profile_y, float), spec.centers_y)):
        inside = _window(h, c)
        w = np.where(inside, h, 0.0)
        s = w.sum()
        if s <= 0:
            out.append((0.0, float("nan"), float("nan"), float("nan"), float("nan")))
            continue
        m = float((w * c).sum() / s)
        var = max(float((w * (c - m) ** 2).sum() / s), 0.0)
        sig = float("nan")
        if n_rays and var > 0:
            sig = _width_sigma(w, c, m, var, float(s) * n_rays)
            if (h < 0).any():
                sig = math.hypot(sig, _noise_sigma(h, c, inside, m, var, s))
        out.append((float(s), m, math.sqrt(var), _fwhm(w, c), sig))
    (ix, mx, sx, fx, ex), (iy, my, sy, fy, ey) = out
    return Focus(0.5 * (ix + iy), mx, my, sx, sy, fx, fy, ex, ey)


# --------------------------------------------------------------------------- #
# targets
# --------------------------------------------------------------------------- #
@runtime_checkable
class Target(Protocol):
    """What the beam should be.

    ``residuals(rays, start)`` (torch, 1-D): their sum of squares is minimized; ``start`` is the
    beam's :class:`Focus` where the optimization begins (for scales).  ``unmet(focus)``: None when
    ``focus`` meets the target, else a line saying how it falls short (a target with no threshold,
    the smallest focus, is always met).
    """

    name: str

    def residuals(self, rays: Rays, start: Focus) -> torch.Tensor:
        """Residuals (torch, 1-D) whose sum of squares the optimizer minimizes; ``start`` sets scales."""
        ...

    def unmet(self, focus: Focus) -> str | None:
        """None when ``focus`` meets the target, else a line saying how it falls short."""
        ...


def _positive(name: str, v: float) -> None:
    if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
        raise InputError(f"{name} must be a positive number, got {v!r}")


@dataclass(frozen=True)
class SmallestFocus:
    """The smallest focus.

    The rms width of each axis relative to where it starts, weighted (``weight_x``, ``weight_y``),
    squared and summed (0 ignores an axis).
    """

    weight_x: float = 1.0
    weight_y: float = 1.0
    name: str = field(default="smallest focus", init=False)

    def __post_init__(self):
        for k in ("weight_x", "weight_y"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"{k} must be a number >= 0, got {v!r}")
        if self.weight_x == self.weight_y == 0:
            raise InputError("smallest focus: weight_x and weight_y are both 0; nothing to minimize")

    def residuals(self, rays: Rays, start: Focus) -> torch.Tensor:
        """Each axis's per-ray residuals over its starting rms width, times the square root of its weight."""
        return torch.cat([math.sqrt(self.weight_x) * per_ray(rays, "x") / start.rms_x,
                          math.sqrt(self.weight_y) * per_ray(rays, "y") / start.rms_y])

    def unmet(self, focus: Focus) -> str | None:
        """None: the smallest focus has no threshold, it is always met."""
        return None

    def cost(self, focus: Focus, start: Focus) -> float:
        """The residuals' sum of squares for a beam of ``focus``'s widths."""
        return self.weight_x * (focus.rms_x / start.rms_x) ** 2 + self.weight_y * (focus.rms_y / start.rms_y) ** 2


@dataclass(frozen=True)
class FocusAt:
    """The focus centred at (``x``, ``y``) on the screen (mm), within ``tolerance`` (mm).

    Otherwise as small as it can be (``size_weight``: how much the width counts beside the position).
    """

    x: float
    y: float
    tolerance: float = 0.01
    size_weight: float = 1.0
    name: str = field(default="focus at a position", init=False)

    def __post_init__(self):
        for k in ("x", "y"):
            if not math.isfinite(getattr(self, k)):
                raise InputError(f"{k} must be a finite number, got {getattr(self, k)!r}")
        _positive("tolerance", self.tolerance)

    def residuals(self, rays: Rays, start: Focus) -> torch.Tensor:
        """The centroid's distance from (``x``, ``y``) in tolerances, then the smallest focus's residuals, weighted."""
        pos = torch.stack([(rays.centroid("x") - self.x), (rays.centroid("y") - self.y)]) / self.tolerance
        size = SmallestFocus().residuals(rays, start) * math.sqrt(self.size_weight)
        return torch.cat([pos, size])

    def unmet(self, focus: Focus) -> str | None:
        """None when the centre lies within twice the tolerance of (``x``, ``y``), else how far off it is."""
        d = math.hypot(focus.x - self.x, focus.y - self.y)
        if d <= 2 * self.tolerance:
            return None
        return (f"the focus centre reaches ({focus.x:.3f}, {focus.y:.3f}) mm, {d:.3f} mm from the target "
                f"({self.x:g}, {self.y:g}) mm (tolerance {self.tolerance:g} mm)")

    def cost(self, focus: Focus, start: Focus) -> float:
        """The residuals' sum of squares for a beam of ``focus``'s centre and widths."""
        miss = ((focus.x - self.x) ** 2 + (focus.y - self.y) ** 2) / self.tolerance ** 2
        return miss + self.size_weight * SmallestFocus().cost(focus, start)


@dataclass(frozen=True)
class SpotSize:
    """A spot of the given rms widths (mm), e.g. a defocused 0.2 x 0.05 mm.

    ``tolerance`` is relative (0.05: within 5 %).
    """

    rms_x: float
    rms_y: float
    tolerance: float = 0.05
    name: str = field(default="spot size", init=False)

    def __post_init__(self):
        _positive("rms_x", self.rms_x)
        _positive("rms_y", self.rms_y)
        _positive("tolerance", self.tolerance)

    def residuals(self, rays: Rays, start: Focus) -> torch.Tensor:
        """Each axis's relative miss of its rms width, in tolerances."""
        return torch.stack([(rays.rms("x") / self.rms_x - 1.0), (rays.rms("y") / self.rms_y - 1.0)]) / self.tolerance

    def unmet(self, focus: Focus) -> str | None:
        """None when both widths lie within twice the tolerance of the target, else the spot reached."""
        rel = [abs(focus.rms_x / self.rms_x - 1), abs(focus.rms_y / self.rms_y - 1)]
        if max(rel) <= 2 * self.tolerance:
            return None
        return (f"the spot reaches {focus.rms_x * 1e3:.1f} x {focus.rms_y * 1e3:.1f} µm rms, target "
                f"{self.rms_x * 1e3:.1f} x {self.rms_y * 1e3:.1f} µm (tolerance {self.tolerance:.0%})")

    def cost(self, focus: Focus, start: Focus) -> float:
        """The residuals' sum of squares for a beam of ``focus``'s widths."""
        return ((focus.rms_x / self.rms_x - 1) ** 2 + (focus.rms_y / self.rms_y - 1) ** 2) / self.tolerance ** 2


@dataclass(frozen=True)
class MaxTransmission:
    """As much light on the screen as possible at a spot no larger than ``rms_x`` x ``rms_y`` (mm)."""

    rms_x: float
    rms_y: float
    name: str = field(default="maximum transmission", init=False)

    def __post_init__(self):
        _positive("rms_x", self.rms_x)
        _positive("rms_y", self.rms_y)

    def residuals(self, rays: Rays, start: Focus) -> torch.Tensor:
        """The light lost against the start (log, shifted positive), then each width's excess over its bound."""
        # -log I as a residual: sqrt of a positive shift keeps it a sum of squares
        light = torch.sqrt((5.0 - torch.log(rays.intensity.clamp(min=1e-12) / max(start.intensity, 1e-12)))
                           .clamp(min=0))
        over = torch.stack([torch.relu(rays.rms("x") / self.rms_x - 1), torch.relu(rays.rms("y") / self.rms_y - 1)])
        return torch.cat([light[None], 30.0 * over])

    def unmet(self, focus: Focus) -> str | None:
        """None when both widths are within 5 % above their bounds, else the spot it stays at."""
        if focus.rms_x <= 1.05 * self.rms_x and focus.rms_y <= 1.05 * self.rms_y:
            return None
        return (f"the spot stays at {focus.rms_x * 1e3:.1f} x {focus.rms_y * 1e3:.1f} µm rms, above the "
                f"{self.rms_x * 1e3:.1f} x {self.rms_y * 1e3:.1f} µm asked for")

    def cost(self, focus: Focus, start: Focus) -> float:
        """The residuals' sum of squares for a beam of ``focus``'s intensity and widths."""
        light = max(5.0 - math.log(max(focus.intensity, 1e-12) / max(start.intensity, 1e-12)), 0.0)
        over = [max(focus.rms_x / self.rms_x - 1, 0.0), max(focus.rms_y / self.rms_y - 1, 0.0)]
        return light + 900.0 * (over[0] ** 2 + over[1] ** 2)


def measured_cost(target: Target, focus: Focus, start: Focus) -> float | None:
    """``target.cost(focus, start)``: how well a measured beam meets the target; None for a target without one."""
    cost = getattr(target, "cost", None)
    if cost is None:
        return None
    v = float(cost(focus, start))
    return v if math.isfinite(v) else None


TARGETS = {"smallest_focus": SmallestFocus, "focus_at": FocusAt, "spot_size": SpotSize,
           "max_transmission": MaxTransmission}


def target_from(spec) -> Target:
    """A target from a :class:`Target`, a name or a mapping: what the queue and the command line hand over.

    A name: ``"smallest_focus"``; a mapping: ``kind`` and the target's fields
    (``{"kind": "spot_size", "rms_x": 0.2, "rms_y": 0.05}``).
    """
    if isinstance(spec, Target):
        return spec
    if isinstance(spec, str):
        spec = {"kind": spec}
    if not isinstance(spec, Mapping) or "kind" not in spec:
        raise InputError(f"a target is one of {sorted(TARGETS)} or a mapping with 'kind', got {spec!r}")
    kind = str(spec["kind"])
    if kind not in TARGETS:
        raise InputError(f"unknown target {kind!r}; known: {sorted(TARGETS)}")
    args = {k: v for k, v in spec.items() if k != "kind"}
    refuse_unknown(TARGETS[kind], args, f"target {kind!r}: unknown key(s)")
    try:
        return TARGETS[kind](**{k: float(v) for k, v in args.items()})
    except (TypeError, ValueError) as exc:
        raise InputError(f"target {kind!r}: {exc}") from None


# --------------------------------------------------------------------------- #
# constraints
# --------------------------------------------------------------------------- #
@dataclass(frozen=True)
class Constraints:
    """What the optimizer may do.

    Parameters
    ----------
    hold : tuple of str
        parameters whose motors must not move (default: all but the refocusing mirrors,
        :data:`MONOCHROMATOR`; ``()`` frees every motor).
    travel : mapping
        ``{parameter: largest move}`` from where the motor stands (its units).
    limits : mapping
        ``{parameter: (low, high)}`` narrower than the motors' own (twin coordinates).
    keep_transmission : float or None
        the fraction of the current transmission that must stay (0.98: lose at
        most 2 % of the light); None: no such bound.
    min_transmission : float or None
        an absolute floor (fraction of the source rays on the screen), or None.
    """

    hold: tuple[str, ...] = MONOCHROMATOR
    travel: Mapping[str, float] = field(default_factory=dict)
    limits: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    keep_transmission: float | None = 0.98
    min_transmission: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "hold", tuple(self.hold))
        for k in ("keep_transmission", "min_transmission"):
            v = getattr(self, k)
            if v is not None and not (math.isfinite(v) and 0 <= v <= 1):
                raise InputError(f"{k} must lie in [0, 1], got {v!r}")
        for name, v in self.travel.items():
            _positive(f"travel of {name}", float(v))
        for name, lim in self.limits.items():
            lo, hi = map(float, lim)
            if not lo <= hi:
                raise InputError(f"limits of {name}: low {lo:g} above high {hi:g}")

    def check(self, table: ParameterTable = METRIXS) -> None:
        """Refuse a name the table does not know, or one whose parameter no motor moves."""
        for what, names in (("hold", self.hold), ("travel", self.travel), ("limits", self.limits)):
            for n in names:
                if n not in table.names:
                    raise InputError(f"constraints {what}: unknown parameter {n!r}")
                if not table[n].motorized and what != "hold":
                    raise InputError(f"constraints {what}: {n} has no motor")

    @classmethod
    def from_mapping(cls, options: Mapping | None) -> Constraints:
        """Constraints from a mapping of their fields (None: the defaults); an unknown key is refused."""
        options = dict(options or {})
        refuse_unknown(cls, options, "constraints: unknown key(s)")
        if "limits" in options:
            options["limits"] = {k: tuple(v) for k, v in options["limits"].items()}
        return cls(**options)
