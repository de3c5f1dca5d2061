"""The METRIXS beamline (BESSY II, U41 undulator, 318 eV) as our own code.

Distances, angles, radii, half-axes, openings and source properties follow
the authors' RAY-UI model ``METRIX_U41_G1_H1_318eV_PS_MLearn_1.15.rml``;
that file is only a test oracle here, never a template.

:func:`build_beamline` turns a vector of the 34 parameters (plus optional
RML-level overrides, used by the physical-effects library and the
focus-chamber translation) into an :class:`~bluesky_offsets.physics.rml.RmlBeamline`
whose world frames carry every misalignment.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.geometry import MISALIGNMENT_KEYS, is_tensor
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.physics.rml import RmlBeamline, RmlError, RmlObject, make_object

SOURCE, IMAGE_PLANE = "U41_318eV", "ImagePlane"

_ALIGN = [("alignmentError", 0, "Yes")] + [(k, 0.0) for k in MISALIGNMENT_KEYS]
_SOURCE_ALIGN = [("alignmentError", 0, "Yes")] + [(k, 0.0) for k in MISALIGNMENT_KEYS
                                                   if k not in ("translationZerror", "rotationZerror")]
_REFLECTIVE = [("reflectivityType", 0, "100%"), ("materialSubstrate", "Au"), ("surfaceCoating", 0, "Substrate only")]


def _slope(sag: float, mer: float) -> list[tuple]:
    # RAY-UI slope errors (sagittal, meridional; µrad rms), applied by RAYX when the switch is "Yes".
    return [("slopeError", 0, "Yes"), ("profileKind", 2, "no Profile"), ("slopeErrorSag", sag),
            ("slopeErrorMer", mer), ("thermalDistortionAmp", 0.0), ("thermalDistortionSigmaX", 0.0),
            ("thermalDistortionSigmaZ", 0.0), ("cylindricalBowingAmp", 0.0), ("cylindricalBowingRadius", 0.0)]


def _slit(name: str, width: float, height: float, distance: float) -> RmlObject:
    return make_object(name, "Slit", [
        ("openingShape", 0, "rectangle"), ("openingWidth", width), ("openingHeight", height),
        ("centralBeamstop", 0, "none"), ("stopWidth", 20.0), ("stopHeight", 1.0),
        ("geometricalShape", 0, "rectangle"), ("totalWidth", 50.0), ("totalHeight", 50.0),
        ("distancePreceding", distance), ("azimuthalAngle", 0.0), *_ALIGN])


def _ellipsoid(name: str, *, length: float, entrance: float, exit_: float, design_angle: float,
               a: float, b: float, distance: float, azimuth: float, slope: tuple[float, float]) -> RmlObject:
    return make_object(name, "Ellipsoid", [
        ("geometricalShape", 0, "rectangle"), ("totalWidth", 20.0), ("totalLength", length),
        ("grazingIncAngle", 2.0), ("entranceArmLength", entrance), ("exitArmLength", exit_),
        ("designGrazingIncAngle", design_angle), ("longHalfAxisA", a), ("shortHalfAxisB", b),
        # "plane": no sagittal curvature (a11 = 0): E1 and E2 form a KB-like pair.
        ("figureRotation", 1, "plane"), ("parameter_a11", 1.0),
        ("distancePreceding", distance), ("azimuthalAngle", azimuth), *_REFLECTIVE,
        ("alignmentError", 0, "Yes"), ("misalignmentCoordinateSystem", 0, "Ellipsoid"),
        *[(k, 0.0) for k in MISALIGNMENT_KEYS], *_slope(*slope)])


def nominal_beamline() -> RmlBeamline:
    """The METRIXS beamline at its reference (RML) settings, no misalignment."""
    objects = [
        make_object(SOURCE, "Point Source", [
            ("numberRays", 10000),
            ("sourceWidthDistribution", 1, "gaussian (sigma)"), ("sourceWidth", 0.076),
            ("sourceHeightDistribution", 1, "gaussian (sigma)"), ("sourceHeight", 0.027),
            ("sourceDepth", 1.0),
            ("horDivDistribution", 1, "gaussian (sigma)"), ("horDiv", 0.078),
            ("verDivDistribution", 1, "gaussian (sigma)"), ("verDiv", 0.04),
            *_SOURCE_ALIGN,
            ("energyDistributionType", 1, "Values"), ("photonEnergy", 318.0),
            ("energySpreadType", 0, "white band"), ("energySpreadUnit", 0, "eV"), ("energySpread", 0.0),
            ("linearPol_0", 1.0), ("linearPol_45", 0.0), ("circularPol", 0.0),
            ("sourcePulseType", 0, "all rays start simultaneously"), ("sourcePulseLength", 0.0)]),
        _slit("ASBL", 2.0, 2.0, 10000.0),
        make_object("M1-Cylinder", "Cylinder", [
            ("geometricalShape", 0, "rectangle"), ("totalWidth", 20.0), ("totalLength", 320.0),
            ("grazingIncAngle", 1.75), ("entranceArmLength", 12000.0), ("exitArmLength", 3750.0),
            ("bendingRadius", 1, "Short Radius rho"), ("radius", 174.21),
            ("distancePreceding", 2000.0), ("azimuthalAngle", 90.0), *_REFLECTIVE, *_ALIGN,
            *_slope(1.01, 0.16)]),
        _slit("Entrance-Slit", 10.0, 10.0, 3750.0),
        make_object("Plane Mirror", "Plane Mirror", [
            ("geometricalShape", 0, "rectangle"), ("totalWidth", 20.0), ("totalLength", 310.0),
            ("grazingIncAngle", 4.3901672), ("distancePreceding", 5800.0), ("azimuthalAngle", 0.0),
            *_REFLECTIVE, *_ALIGN, *_slope(0.084, 0.023)]),
        make_object("Spherical Grating", "Spherical Grating", [
            ("geometricalShape", 0, "rectangle"), ("totalWidth", 20.0), ("totalLength", 100.0),
            ("gratingMount", 1, "constant incidence angle"), ("deviationAngle", 10.0),
            ("entranceArmLength", 6000.0), ("exitArmLength", 11000.0), ("radius", 109791.0),
            ("designEnergy", 318.0), ("lineDensity", 1199.918), ("orderDiffraction", 1),
            ("alpha", 87.36100673679999), ("beta", -83.85870570260001),
            ("lineSpacing", 0, "constant"), *[(f"vlsParameter{i}", 0.0) for i in range(1, 7)],
            ("distancePreceding", 200.0), ("azimuthalAngle", 180.0),
            ("lineProfile", 3, "unknown"), ("gratingEfficiency", 1.0), ("reflectivityType", 0, "100%"),
            *_ALIGN, *_slope(0.124, 0.102)]),
        _slit("Exit Slit", 20.0, 0.1, 11000.0),
        _ellipsoid("E1", length=390.0, entrance=39600.0, exit_=1900.0, design_angle=1.978,
                   a=20750.0, b=302.721702601, distance=6850.0, azimuth=90.0, slope=(0.037, 0.023)),
        _ellipsoid("E2", length=390.0, entrance=7750.0, exit_=1000.0, design_angle=2.00735,
                   a=4375.0, b=97.1560870104, distance=900.0, azimuth=0.0, slope=(0.045, 0.024)),
        make_object(IMAGE_PLANE, "ImagePlane", [("distanceImagePlane", 1000.0), *_ALIGN]),
    ]
    return RmlBeamline(objects)


_NOMINAL = nominal_beamline()


@dataclass
class BeamlineState:
    """What a parameter vector and overrides change in the nominal beamline.

    ``types``: objects whose element type changes (M1 turned into a toroid); ``fields``:
    ``{object: {RML field: value}}`` set by the parameters, then replaced by the overrides;
    ``misalignment``: ``{object: {alignment key: value}}``, parameters and overrides added.
    Values are numbers, or tensors with one entry per configuration when the parameters come
    as a torch batch (the differentiable twin reads this, RAYX's RML is written from it).
    """

    types: dict[str, str] = field(default_factory=dict)
    fields: dict[str, dict[str, Any]] = field(default_factory=dict)  # numbers or tensors
    misalignment: dict[str, dict[str, Any]] = field(default_factory=dict)


def beamline_state(values, overrides: Mapping[str, Mapping[str, Any]] | None = None,
                   table: ParameterTable = METRIXS) -> BeamlineState:
    """The changes of :func:`build_beamline`, without building it.

    ``values`` is a parameter vector (numbers) or a torch tensor ``(..., 34)``; override values
    may be tensors too.  Unknown objects and fields are refused as in :func:`build_beamline`.
    """
    state = BeamlineState()
    for j, p in enumerate(table):
        v = values[..., j]
        if p.field in MISALIGNMENT_KEYS:
            state.misalignment.setdefault(p.element, {})[p.field] = v
        else:
            state.fields.setdefault(p.element, {})[p.field] = v
    for name, fields in (overrides or {}).items():
        try:
            obj = _NOMINAL[name]
        except RmlError:
            raise RmlError(f"override names unknown object {name!r}; objects: "
                           f"{[o.name for o in _NOMINAL.objects]}") from None
        new_type = fields.get("type")
        if new_type is not None:
            # a structural change (e.g. M1 becoming a toroid): the new type's fields may be added
            state.types[name] = str(new_type)
        for key, value in fields.items():
            if key == "type":
                continue
            value = value if isinstance(value, str) or is_tensor(value) else float(value)
            if key in MISALIGNMENT_KEYS:
                mis = state.misalignment.setdefault(name, {})
                mis[key] = mis.get(key, 0.0) + value
            elif not obj.has(key) and new_type is None:
                raise RmlError(f"override: {name!r} has no field {key!r}")
            else:
                state.fields.setdefault(name, {})[key] = value
    return state


def build_beamline(values, *, overrides: Mapping[str, Mapping[str, object]] | None = None,
                   table: ParameterTable = METRIXS, n_rays: int | None = None) -> RmlBeamline:
    """The METRIXS beamline at parameter vector ``values`` (physical units).

    Parameters
    ----------
    values : array_like, shape (34,)
        Parameter vector in table order.  Values outside the sampling box are
        allowed (see :meth:`ParameterTable.outside_box`).
    overrides : mapping, optional
        ``{object name: {RML field: value}}`` applied after the parameters:
        alignment errors (``translationZerror`` ...) are added to those the
        parameters set, other fields replace the value.  This is how the
        focus-chamber translation (``{"ImagePlane": {"translationZerror": 5}}``)
        and the physical effects reach the twin.  A ``"type"`` entry changes
        the element type (and then admits the new type's fields).
    n_rays : int, optional
        Number of source rays written to the source.
    """
    vec = table.validate(values)
    if vec.ndim != 1:
        raise InputError("build_beamline takes one parameter vector; use the twin for batches")
    state = beamline_state(vec, overrides, table)
    bl = _NOMINAL.copy()
    for name, new_type in state.types.items():
        bl[name].type = new_type
    for name, fields in state.fields.items():
        obj = bl[name]
        for key, value in fields.items():
            obj.set(key, value if isinstance(value, str) else float(value))
    for name, fields in state.misalignment.items():
        bl[name].set_misalignment(**{k: float(v) for k, v in fields.items()})
    if n_rays is not None:
        bl[SOURCE].set("numberRays", int(n_rays))
    return bl


def reference_values(table: ParameterTable = METRIXS) -> np.ndarray:
    """Parameter vector of the reference RML (the nominal configuration)."""
    return table.reference.copy()


_POSITIVE_FIELDS = {"radius", "longRadius", "shortRadius", "longHalfAxisA", "shortHalfAxisB"}
OPENING_FIELDS = {"openingWidth", "openingHeight"}
"""RML fields that are a slit's opening."""


def check_physical(values, table: ParameterTable = METRIXS) -> None:
    """Refuse values no beamline can have (RAYX would abort the whole process).

    Raises
    ------
    ValueError
        Naming the parameter: a radius or half-axis that is not positive, a
        long half-axis not longer than the short one, a negative slit opening.
    """
    vec = table.validate(values)
    for p, v in zip(table, vec):
        if p.field in _POSITIVE_FIELDS and v <= 0:
            raise InputError(f"{p.name} = {v} {p.unit}: must be positive")
        if p.field in OPENING_FIELDS and v < 0:
            raise InputError(f"{p.name} = {v} {p.unit}: a slit opening cannot be negative")
    for element in {p.element for p in table if p.field == "longHalfAxisA"}:
        a = [v for p, v in zip(table, vec) if p.element == element and p.field == "longHalfAxisA"]
        b = [v for p, v in zip(table, vec) if p.element == element and p.field == "shortHalfAxisB"]
        if a and b and a[0] <= b[0]:
            raise InputError(f"{element}: long half-axis {a[0]} mm must exceed short half-axis {b[0]} mm")
