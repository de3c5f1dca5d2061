"""Physical effects the offset model lacks: named causes with parameters.

Offsets explain only part of the gap between a twin and its beamline.  Each
:class:`Effect` here is a physical cause with parameters (unit, prior range,
0 = absent) and its implementation:

* **twin level** — a change of the RAYX beamline, as RML overrides
  ``{object: {field: value}}`` (element translations, slope errors, source
  size, photon energy, grating line density, an M1 thermal bump ...);
* **detector level** — a change of the measured histograms (blur,
  background, intensity scale), applicable to twin *and* surrogate output.

Adding an effect is one small class::

    class EntranceSlitShift(Effect):
        name = "entrance_slit_shift"
        description = "entrance slit displaced horizontally"
        parameters = (EffectParameter("x", "mm", -2.0, 2.0, "horizontal shift"),)

        def overrides(self, v):
            return {"Entrance-Slit": {"translationXerror": v["x"]}}

    register(EntranceSlitShift())

The registry :data:`EFFECTS` is what the diagnosis ranks.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.geometry import is_tensor
from bluesky_offsets.physics.metrixs import IMAGE_PLANE, SOURCE, nominal_beamline

_NOMINAL = nominal_beamline()


@dataclass(frozen=True)
class EffectParameter:
    """One parameter of an effect: its name, unit, prior range (0 = absent) and meaning."""

    name: str
    unit: str
    low: float
    high: float
    description: str = ""
    # the diagnosis starts a fit from this parameter alone, away from zero; off for a shift
    # the offsets reproduce anyway (a screen moved across the beam)
    start: bool = True

    @property
    def span(self) -> float:
        """The prior range's width, ``high - low``."""
        return self.high - self.low


class Effect:
    """Base class: override :meth:`overrides` (twin level) and/or :meth:`apply_histograms`."""

    name: str = ""
    description: str = ""
    parameters: tuple[EffectParameter, ...] = ()
    level: str = "twin"  # or "detector"
    order: int = 0  # detector effects apply in this order: blur, gain, then background

    # -- values -------------------------------------------------------------
    def values(self, values: Mapping[str, float] | Iterable[float] | None = None) -> dict[str, float]:
        """Complete ``{parameter: value}`` (missing = 0 = absent), checked for finiteness."""
        names = [p.name for p in self.parameters]
        if values is None:
            out = {}
        elif isinstance(values, Mapping):
            unknown = set(values) - set(names)
            if unknown:
                raise InputError(f"effect {self.name!r} has no parameter {sorted(unknown)}; it has {names}")
            out = dict(values)
        else:
            seq = list(values)
            if len(seq) != len(names):
                raise InputError(f"effect {self.name!r} takes {len(names)} values ({names}), got {len(seq)}")
            out = dict(zip(names, seq))
        # tensors stay tensors (the differentiable twin takes gradients through the effects)
        full: dict[str, Any] = {n: (v if is_tensor(v) else float(v)) for n, v in ((n, out.get(n, 0.0)) for n in names)}
        for n, v in full.items():
            if not (bool(v.isfinite().all()) if is_tensor(v) else math.isfinite(v)):
                raise InputError(f"effect {self.name!r}: {n} = {v} is not finite")
        return full

    def is_absent(self, values: Mapping[str, float]) -> bool:
        """Whether every parameter of the effect is 0 in ``values`` (a missing one counts as 0)."""
        return all(v == 0.0 for v in self.values(values).values())

    # -- implementation -----------------------------------------------------
    def overrides(self, values: Mapping[str, float]) -> dict[str, dict[str, object]]:
        """RML overrides for the twin (twin-level effects)."""
        return {}

    def apply_histograms(self, hist_x: np.ndarray, hist_y: np.ndarray, values: Mapping[str, float],
                         spec) -> tuple[np.ndarray, np.ndarray]:
        """Transform histograms (..., bins) (detector-level effects)."""
        return hist_x, hist_y

    def apply_noise(self, noise_x, noise_y, hist_x, hist_y, values: Mapping[str, float], spec):
        """How the effect carries a traced histogram's counting noise (detector-level effects).

        ``noise``: per bin the second moment ``n`` whose ``(n − h²) / K`` is the bin's variance for
        ``K`` traced rays (a traced histogram's own values ``h``, before any effect); ``hist``: the
        histograms the effect acts on.  Returns the noise of the effect's output.
        """
        raise NotImplementedError(f"effect {self.name!r} does not say what it makes of the counting noise")

    def __repr__(self) -> str:
        return f"<Effect {self.name}: {', '.join(f'{p.name} [{p.unit}]' for p in self.parameters)}>"


EFFECTS: dict[str, Effect] = {}


def _any(cond) -> bool:
    """``cond`` for a number, "any element" for a tensor of one value per configuration."""
    return bool(cond.any()) if is_tensor(cond) else bool(cond)


def _all(cond) -> bool:
    return bool(cond.all()) if is_tensor(cond) else bool(cond)


def register(effect: Effect) -> Effect:
    """Add ``effect`` to :data:`EFFECTS` under its name (a name taken or empty is refused); return it."""
    if not effect.name or effect.name in EFFECTS:
        raise InputError(f"effect name {effect.name!r} is empty or already registered")
    EFFECTS[effect.name] = effect
    return effect


def get(name: str) -> Effect:
    """The registered effect ``name`` (an unknown name is refused, naming the known ones)."""
    try:
        return EFFECTS[name]
    except KeyError:
        raise InputError(f"unknown effect {name!r}; known: {sorted(EFFECTS)}") from None


def at_bound(effect: str, parameter: str, value: float) -> bool:
    """Whether a fitted effect parameter sits on its prior range's edge.

    The fit was stopped there: the value is a limit, not an estimate.
    """
    p = next((q for q in get(effect).parameters if q.name == parameter), None)
    return p is not None and min(abs(value - p.low), abs(value - p.high)) <= 1e-6 * p.span


def twin_overrides(effects: Mapping[str, Mapping[str, float]]) -> dict[str, dict[str, object]]:
    """Merge the RML overrides of several effects ``{effect name: values}``.

    Alignment errors of the same object add up; other fields must not clash.
    """
    merged: dict[str, dict[str, Any]] = {}  # numbers or tensors
    for name, values in effects.items():
        eff = get(name)
        for obj, fields in eff.overrides(eff.values(values)).items():
            target = merged.setdefault(obj, {})
            for key, val in fields.items():
                if key.endswith("error") and key in target:
                    target[key] = target[key] + val
                elif key in target and (is_tensor(val) or is_tensor(target[key]) or target[key] != val):
                    raise InputError(f"effects disagree on {obj}.{key}")
                else:
                    target[key] = val
    return merged


def _detector_effects(effects: Mapping[str, Mapping[str, float]]) -> list[tuple[Effect, Mapping[str, float]]]:
    """The detector-level effects among ``effects`` in physical order, with their values."""
    chosen = sorted(((get(n), v) for n, v in effects.items()), key=lambda ev: ev[0].order)
    return [(eff, eff.values(v)) for eff, v in chosen if eff.level == "detector"]


def apply_detector_effects(hist_x, hist_y, effects: Mapping[str, Mapping[str, float]], spec):
    """Apply the detector-level effects among ``effects`` to histograms, in physical order.

    Blur and gain act on the signal, background adds to it.
    """
    for eff, values in _detector_effects(effects):
        hist_x, hist_y = eff.apply_histograms(hist_x, hist_y, values, spec)
    return hist_x, hist_y


def detector_noise(hist_x, hist_y, effects: Mapping[str, Mapping[str, float]], spec):
    """The counting noise of traced histograms ``hist_x``, ``hist_y`` through the detector-level effects.

    Per bin of the effects' output, the second moment ``n`` whose ``(n − f²) / K`` is the bin's
    variance for ``K`` traced rays, ``f`` its value (:meth:`Effect.apply_noise`; the traced
    histograms' own values where no effect changes them): a blurred histogram's bins share their
    rays with their neighbours and each carries a fraction of the noise its value implies.  A gain
    and a background mix no bins and keep the noise model's weighing of a bin by its value (the
    counts' exact variance would scale with the gain's square and take none from a background).
    """
    noise_x, noise_y = hist_x, hist_y
    for eff, values in _detector_effects(effects):
        noise_x, noise_y = eff.apply_noise(noise_x, noise_y, hist_x, hist_y, values, spec)
        hist_x, hist_y = eff.apply_histograms(hist_x, hist_y, values, spec)
    return noise_x, noise_y


# --------------------------------------------------------------------------- #
# twin-level effects
# --------------------------------------------------------------------------- #
class ChamberTranslation(Effect):
    """The focus chamber's translation on all three axes at once, for a model that should carry them together.

    Not registered: the diagnosis ranks the axes as separate effects (``chamber_x``, ``chamber_y``,
    ``chamber_z``), so that it names the one that is missing rather than a superset that wins
    by absorbing noise; ``register(ChamberTranslation())`` ranks it too.
    """

    name = "chamber_translation"
    description = "focus-measurement chamber displaced (x, y across the beam; z along it)"
    parameters = (EffectParameter("x", "mm", -1.0, 1.0, "horizontal", start=False),
                  EffectParameter("y", "mm", -1.0, 1.0, "vertical", start=False),
                  EffectParameter("z", "mm", -33.0, 33.0, "along the beam"))

    def overrides(self, v):
        """The image plane translated by ``x``, ``y`` and ``z`` (mm)."""
        return {IMAGE_PLANE: {"translationXerror": v["x"], "translationYerror": v["y"],
                              "translationZerror": v["z"]}}


# The focus chamber's translation as a surrogate's inputs beside the 34 parameters (datasets
# drawn with ``chamber``): names and the box of :class:`ChamberTranslation`
CHAMBER_INPUTS = tuple(f"chamber_{p.name}" for p in ChamberTranslation.parameters)
CHAMBER_LOW = np.array([p.low for p in ChamberTranslation.parameters])
CHAMBER_HIGH = np.array([p.high for p in ChamberTranslation.parameters])


class ChamberShift(Effect):
    """The focus-measurement chamber displaced across the beam.

    The whole footprint moves, as offsets of the last mirrors move it too, so a fit starts it at
    zero.
    """

    def __init__(self, axis: str):
        self.axis, self.name = axis, f"chamber_{axis}"
        what = {"x": "horizontally", "y": "vertically"}[axis]
        self.description = f"focus-measurement chamber displaced {what} (across the beam)"
        self.parameters = (EffectParameter(axis, "mm", -1.0, 1.0, f"{what} across the beam", start=False),)

    def overrides(self, v):
        """The image plane translated along the effect's axis (mm)."""
        return {IMAGE_PLANE: {f"translation{self.axis.upper()}error": v[self.axis]}}


class ChamberTranslationZ(Effect):
    """The focus-measurement chamber displaced along the beam (defocus)."""

    name = "chamber_z"
    description = "focus-measurement chamber displaced along the beam (defocus)"
    parameters = (EffectParameter("z", "mm", -33.0, 33.0, "along the beam"),)

    def overrides(self, v):
        """The image plane translated along the beam by ``z`` (mm)."""
        return {IMAGE_PLANE: {"translationZerror": v["z"]}}


class ChamberRotation(Effect):
    """The focus-measurement screen rotated about the beam."""

    name = "chamber_rotation"
    description = "focus-measurement screen rotated about the beam"
    parameters = (EffectParameter("angle", "mrad", -100.0, 100.0, "rotation about the beam axis"),)

    def overrides(self, v):
        """The image plane rotated about the beam by ``angle`` (mrad)."""
        return {IMAGE_PLANE: {"rotationZerror": v["angle"]}}


class SourceScale(Effect):
    """The electron beam's size or its divergence differs from the model (relative change of both planes).

    Two effects rather than one with both parameters: a fit of both trades one
    for the other with the offsets (a hidden divergence comes back partly as a smaller size),
    and the diagnosis should name the one that changed.
    """

    def __init__(self, what: str):
        self.what, self.name = what, f"source_{what}"
        self._keys = {"size": ("sourceWidth", "sourceHeight"), "divergence": ("horDiv", "verDiv")}[what]
        self.description = f"electron-beam {what} differs from the model (relative change)"
        self.parameters = (EffectParameter(what, "rel", -0.5, 1.0, f"relative change of the source {what}"),)

    def overrides(self, v):
        """The source's size or divergence, both planes, scaled by ``1 + change`` (which must stay positive)."""
        f = 1.0 + v[self.what]
        if _any(f <= 0):
            raise InputError(f"the source {self.what} must stay positive (relative change > -1)")
        src = _NOMINAL[SOURCE]
        return {SOURCE: {k: src.get_float(k) * f for k in self._keys}}


class SourceSizeDivergence(Effect):
    """The electron beam's size and divergence together.

    Not registered (see :class:`SourceScale`); ``register(SourceSizeDivergence())`` ranks it too.
    """

    name = "source_size_divergence"
    description = "electron-beam size and divergence differ from the model (relative change)"
    parameters = (EffectParameter("size", "rel", -0.5, 1.0, "relative change of the source size"),
                  EffectParameter("divergence", "rel", -0.5, 1.0, "relative change of the divergence"))

    def overrides(self, v):
        """The source's size and divergence, each scaled as :class:`SourceScale` does."""
        size, div = SourceScale("size").overrides(v), SourceScale("divergence").overrides(v)
        return {SOURCE: {**size[SOURCE], **div[SOURCE]}}


class PhotonEnergyOffset(Effect):
    """The photon energy differs from the monochromator setting (undulator/energy calibration)."""

    name = "photon_energy"
    description = "photon energy differs from the monochromator setting (undulator/energy calibration)"
    # the exit slit passes a few 10 meV at 318 eV: 50 meV already empties the screen
    parameters = (EffectParameter("delta", "eV", -0.05, 0.05, "photon-energy offset"),)

    def overrides(self, v):
        """The source's photon energy shifted by ``delta`` (eV)."""
        return {SOURCE: {"photonEnergy": _NOMINAL[SOURCE].get_float("photonEnergy") + v["delta"]}}


class SlopeError(Effect):
    """Extra rms meridional and sagittal slope error of one mirror, added in quadrature."""

    level = "twin"

    def __init__(self, element: str, key: str, high: float = 5.0):
        self.element, self.name = element, f"slope_error_{key}"
        self.description = f"{element}: figure (slope) errors larger than specified"
        # at grazing incidence a sagittal slope error deflects the ray ~ the grazing angle times
        # less than a meridional one: a diagnosis starts from the meridional
        self.parameters = (EffectParameter("meridional", "µrad", 0.0, high, "extra rms slope error"),
                           EffectParameter("sagittal", "µrad", 0.0, 4 * high, "extra rms slope error", start=False))

    def overrides(self, v):
        """The mirror's meridional and sagittal slope errors, the extra ones (µrad) added in quadrature."""
        obj = _NOMINAL[self.element]
        urad_to_arcsec = 1e-6 * 180 / math.pi * 3600  # RAYX takes arcsec
        # in quadrature, written out so that a tensor of magnitudes keeps its gradient
        mer = (obj.get_float("slopeErrorMer") ** 2 + (v["meridional"] * urad_to_arcsec) ** 2) ** 0.5
        sag = (obj.get_float("slopeErrorSag") ** 2 + (v["sagittal"] * urad_to_arcsec) ** 2) ** 0.5
        return {self.element: {"slopeErrorMer": mer, "slopeErrorSag": sag}}


class ThermalBump(Effect):
    """Heat load bulges M1: modelled by the bump's central meridional curvature.

    A convex radius R = -sigma^2 / h over the illuminated length (RAYX ignores RAY-UI's
    thermalDistortion fields, so M1 becomes a toroid).
    """

    name = "thermal_bump_m1"
    description = "M1 thermal bump (convex meridional curvature from the heat load)"
    parameters = (EffectParameter("height", "nm", 0.0, 500.0, "bump height"),)
    sigma_mm = 25.0
    min_height_nm = 25.0  # below: |R| > 2.5e7 mm, beyond RAYX's toroid precision; treated as absent

    def overrides(self, v):
        """M1 as a toroid of the bump's convex meridional radius (none below ``min_height_nm``)."""
        h = v["height"]
        if _any(h < 0):
            raise InputError("thermal bump height must be >= 0 (a bulge)")
        if _all(h < self.min_height_nm):
            return {}
        if _any(h < self.min_height_nm):
            raise InputError(f"thermal bump heights below and above {self.min_height_nm} nm change M1's type "
                             "and cannot share one batch")
        radius = -(self.sigma_mm ** 2) / (h * 1e-6)
        m1 = _NOMINAL["M1-Cylinder"]
        return {"M1-Cylinder": {"type": "Toroid", "longRadius": radius,
                                "shortRadius": m1.get_float("radius")}}


class LineDensityError(Effect):
    """The grating's line density differs from its nominal value."""

    name = "grating_line_density"
    description = "grating line density differs from its nominal value"
    parameters = (EffectParameter("delta", "l/mm", -0.3, 0.3, "line-density error"),)

    def overrides(self, v):
        """The grating's line density shifted by ``delta`` (l/mm)."""
        sg = _NOMINAL["Spherical Grating"]
        return {"Spherical Grating": {"lineDensity": sg.get_float("lineDensity") + v["delta"]}}


# --------------------------------------------------------------------------- #
# detector-level effects (histograms; twin and surrogate alike)
# --------------------------------------------------------------------------- #
def _gauss_blur(h, sigma_bins, power: int = 1):
    """Gaussian blur of histograms (..., bins) by ``sigma_bins``; numpy or torch alike.

    A torch ``sigma_bins`` keeps its gradient.  ``power`` 2: through the kernel's weights squared,
    what the blur makes of the bins' independent counting variances.
    """
    if is_tensor(h) or is_tensor(sigma_bins):
        import torch
        h = torch.as_tensor(h, dtype=torch.float64)
        s = torch.as_tensor(sigma_bins, dtype=torch.float64)
        # no branch on the value (it may carry a forward-mode tangent): at 0 the kernel is the identity
        idx = torch.arange(h.shape[-1], dtype=torch.float64)
        kernel = torch.exp(-0.5 * ((idx[:, None] - idx[None, :]) / torch.clamp(s, min=1e-6)) ** 2)
        kernel = kernel / kernel.sum(0, keepdim=True)
        return h @ kernel ** power
    if sigma_bins <= 0:
        return h
    at = np.arange(h.shape[-1])
    weights = np.exp(-0.5 * ((at[:, None] - at[None, :]) / sigma_bins) ** 2)
    weights /= weights.sum(axis=0, keepdims=True)  # keeps the total inside the window
    return h @ weights ** power


def _array(h):
    return h if is_tensor(h) else np.asarray(h)


class DetectorBlur(Effect):
    """The finite resolution of the screen/camera, as a Gaussian blur."""

    name = "detector_blur"
    description = "finite resolution of the screen/camera (Gaussian blur)"
    level = "detector"
    parameters = (EffectParameter("sigma", "mm", 0.0, 0.3, "rms blur"),)

    def apply_histograms(self, hx, hy, v, spec):
        """Both histograms blurred by ``sigma`` (mm rms), in bins of ``spec``."""
        wx = (spec.range_x[1] - spec.range_x[0]) / spec.bins_x
        wy = (spec.range_y[1] - spec.range_y[0]) / spec.bins_y
        return _gauss_blur(_array(hx), v["sigma"] / wx), _gauss_blur(_array(hy), v["sigma"] / wy)

    def apply_noise(self, noise_x, noise_y, hist_x, hist_y, v, spec):
        """Through the kernel's weights squared: a blur spreads each ray over its neighbours.

        Exact on a traced histogram's counts (``noise`` their values): the blur applies first.
        """
        wx = (spec.range_x[1] - spec.range_x[0]) / spec.bins_x
        wy = (spec.range_y[1] - spec.range_y[0]) / spec.bins_y
        return _gauss_blur(_array(noise_x), v["sigma"] / wx, 2), _gauss_blur(_array(noise_y), v["sigma"] / wy, 2)


class Background(Effect):
    """A uniform background on the screen (stray light, dark signal)."""

    name = "background"
    description = "uniform background on the screen (stray light, dark signal)"
    level = "detector"
    order = 2
    parameters = (EffectParameter("level", "fraction/bin", 0.0, 2e-3, "background per bin"),)

    def apply_histograms(self, hx, hy, v, spec):
        """``level`` (fraction per bin) added to every bin of both histograms."""
        return _array(hx) + v["level"], _array(hy) + v["level"]

    def apply_noise(self, noise_x, noise_y, hist_x, hist_y, v, spec):
        """Weighed as counts of its own, as the noise model weighs every bin's value (no bins mixed)."""
        return _array(noise_x) + v["level"], _array(noise_y) + v["level"]


class IntensityScale(Effect):
    """The detector gain or beam current differs: a relative change of all counts."""

    name = "intensity_scale"
    description = "detector gain / beam current differs (relative change of all counts)"
    level = "detector"
    order = 1
    parameters = (EffectParameter("delta", "rel", -0.3, 0.3, "relative intensity change"),)

    def apply_histograms(self, hx, hy, v, spec):
        """Both histograms scaled by ``1 + delta``."""
        return _array(hx) * (1 + v["delta"]), _array(hy) * (1 + v["delta"])

    def apply_noise(self, noise_x, noise_y, hist_x, hist_y, v, spec):
        """Scaled with the values, as the noise model weighs every bin's value (no bins mixed)."""
        return _array(noise_x) * (1 + v["delta"]), _array(noise_y) * (1 + v["delta"])


for _eff in (ChamberShift("x"), ChamberShift("y"), ChamberTranslationZ(), ChamberRotation(), SourceScale("size"),
             SourceScale("divergence"),
             PhotonEnergyOffset(), SlopeError("M1-Cylinder", "m1"), SlopeError("E1", "e1"),
             SlopeError("E2", "e2"), ThermalBump(), LineDensityError(), DetectorBlur(), Background(),
             IntensityScale()):
    register(_eff)
