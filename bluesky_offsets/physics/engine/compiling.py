"""The beamline at a batch of parameter vectors, compiled to tensors for the tracer.

:func:`compile_beamline` evaluates the project's own geometry (:mod:`..geometry`,
:func:`..metrixs.beamline_state`: the same code writes RAYX's RML) on tensors: every element's frame
relative to the previous one, its surface's coefficients, outline, slit opening, slope errors and
grating, as a :class:`CompiledBeamline` of :class:`Optic` s with a leading configuration axis.  The
helpers at the end take and replace those tensors (a compacting trace's rays, the per-ray Jacobian's
leaves) in one fixed order.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.geometry import Misalignment, chain_frames
from bluesky_offsets.physics.metrixs import beamline_state, check_physical, nominal_beamline
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.physics.rml import FLAT_TYPES, GRATING_TYPES, MIRROR_TYPES, RmlError, chain_link

ARCSEC = math.pi / 180.0 / 3600.0
_MIS_KEYS = {"translationXerror": "tx", "translationYerror": "ty", "translationZerror": "tz",
             "rotationXerror": "rx", "rotationYerror": "ry", "rotationZerror": "rz"}


@dataclass
class Optic:
    """One element as the tracer needs it.

    Its tensors have a leading configuration axis (shape (C, 1) to broadcast over rays) or are
    plain numbers when constant.
    """

    name: str
    type: str
    behaviour: str  # "slit", "mirror", "grating", "image"
    surface: str  # "plane", "quadric", "toroid"
    rot: torch.Tensor  # (C, 3, 3): previous local frame -> this local frame
    shift: torch.Tensor  # (C, 3)
    quadric: dict[str, object] = field(default_factory=dict)
    cutout: tuple | None = None  # (shape, W, L): 0 rectangle, 1 ellipse; None unlimited
    opening: tuple | None = None  # slits: (shape, w, h, stop shape, stop w, stop h)
    slope: tuple | None = None  # (sagittal, meridional) rms in rad
    grating: tuple | None = None  # (line density, order, (b1..b6))


@dataclass
class CompiledBeamline:
    """Source and optics of a batch of configurations, ready to trace."""

    n_configs: int
    source: dict[str, Any]  # type, width, height, depth, hor_div, ver_div (rad), energy, spread
    source_rot: torch.Tensor  # (C, 3, 3) source frame -> first optic's local frame
    source_shift: torch.Tensor  # (C, 3)
    optics: list[Optic]
    dtype: torch.dtype
    device: torch.device

    @property
    def names(self) -> list[str]:
        """The optics' names, in beam order."""
        return [o.name for o in self.optics]


_NOMINAL = nominal_beamline()


def _col(v, c: int, dtype, device):
    """A field value as a (C, 1) tensor (or a float when it is a plain constant)."""
    if not torch.is_tensor(v):
        return float(v)
    if v.numel() not in (1, c):
        raise InputError(f"a batched field has {v.numel()} values for {c} configurations")
    return v.to(dtype=dtype, device=device).reshape(-1, 1).expand(c, 1)


def compile_beamline(values, overrides: Mapping | Sequence[Mapping] | None = None, *,
                     table: ParameterTable = METRIXS, dtype=torch.float64, device="cpu",
                     beamline=None, check: bool = True) -> CompiledBeamline:
    """The METRIXS beamline at a batch of parameter vectors, as tensors.

    Parameters
    ----------
    values : tensor or array (C, 34) or (34,)
        Parameter vectors (physical units); a tensor that requires grad keeps its graph.
    overrides : mapping or sequence of mappings
        RML-level overrides ``{object: {field: value}}`` (effects, the chamber), shared by
        all configurations (values may be tensors of shape () or (C,), with gradients) or one
        mapping of numbers per configuration.  Structural changes (``"type"``) must agree.
    beamline : RmlBeamline, optional
        Another beamline than METRIXS (values then (C, 0) and overrides carry everything):
        the RAY-UI reference files are traced this way.
    check : bool
        Refuse unphysical parameter vectors (one Python call per row: the per-ray batches of
        :meth:`TorchEngine.ray_jacobian` check their configurations once instead).
    """
    device = torch.device(device)
    vals = values if torch.is_tensor(values) else torch.as_tensor(np.asarray(values, dtype=float))
    vals = vals.to(device=device, dtype=torch.float64)
    if vals.ndim == 1:
        vals = vals[None, :]
    c = vals.shape[0]
    base, state = _compiled_state(vals, overrides, table, beamline, check, device)
    getter = _getter(state)
    frames = _world_frames(base, state, getter)
    f64 = dict(dtype=torch.float64, device=device)

    def frame_tensors(fr):
        p = torch.as_tensor(fr.position, **f64) if not torch.is_tensor(fr.position) else fr.position.to(**f64)
        o = torch.as_tensor(fr.orientation, **f64) if not torch.is_tensor(fr.orientation) \
            else fr.orientation.to(**f64)
        return p.expand(c, 3), o.expand(c, 3, 3)

    src_obj = base.objects[0]
    if not src_obj.is_source:
        raise RmlError("the first object must be the source")
    swap = torch.tensor([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]], **f64)
    prev_p, prev_o = frame_tensors(frames[0])  # physical source frame: world = p + O r
    source = _source(src_obj, getter(src_obj), c, device)
    optics: list[Optic] = []
    src_rot: torch.Tensor | None = None
    src_shift: torch.Tensor | None = None
    for obj, fr in zip(base.objects[1:], frames[1:]):
        p, o = frame_tensors(fr)
        s = swap if obj.type in FLAT_TYPES or obj.type == "ImagePlane" else torch.eye(3, **f64)
        to_local = s @ o.transpose(-1, -2)  # world -> local (rows)
        rot = to_local @ prev_o
        shift = (to_local @ (prev_p - p)[..., None])[..., 0]
        if src_rot is None:
            src_rot, src_shift = rot, shift
        prev_p, prev_o = p, o @ s  # local -> world: r = p + (O S) l
        optics.append(_optic(obj, getter(obj), rot, shift, c, device))
    for opt in optics:
        opt.rot, opt.shift = opt.rot.to(dtype), opt.shift.to(dtype)
    assert src_rot is not None and src_shift is not None, "no element after the source"
    return CompiledBeamline(c, source, src_rot.to(dtype), src_shift.to(dtype), optics, dtype, device)


def _compiled_state(vals, overrides, table: ParameterTable, beamline, check: bool, device):
    """The beamline to compile (METRIXS's nominal one, or ``beamline``) and its state at ``vals``.

    The state is every field and misalignment the parameters and ``overrides`` set, as (C,) columns.
    """
    c = vals.shape[0]
    if beamline is None:
        if vals.shape[1] != len(table):
            raise InputError(f"expected parameter vectors of {len(table)} values, got shape {tuple(vals.shape)}")
        for row in (vals.detach().cpu().numpy() if check else ()):
            check_physical(row, table)
        if overrides is not None and not isinstance(overrides, Mapping):
            ovs = list(overrides)
            if len(ovs) != c:
                raise InputError(f"{len(ovs)} overrides for {c} configurations")
            state = _stack_states([beamline_state(vals[i], ov, table) for i, ov in enumerate(ovs)], device)
        else:
            state = beamline_state(vals, overrides, table)
        base = _NOMINAL.copy()
    else:
        base = beamline.copy()
        state = beamline_state(vals[:, :0], None, ParameterTable([], name="none"))
        for name, flds in (overrides or {}).items():
            for k, v in flds.items():
                (state.misalignment if k in _MIS_KEYS else state.fields).setdefault(name, {})[k] = v
    for name, t in state.types.items():
        base[name].type = t
    return base, state


def _getter(state):
    """``getter(obj)``: a field of ``obj`` as the state sets it, else as the RML has it."""
    def getter(obj):
        mine = state.fields.get(obj.name, {})

        def get(key, default=None):
            if key in mine:
                return mine[key]
            return obj.get_float(key, default)
        return get
    return getter


def _world_frames(base, state, getter) -> list:
    """Every element's misaligned world frame, down the nominal chain (RAY-UI's rule)."""
    links = []
    for obj in base.objects:
        mis = obj.misalignment
        extra = state.misalignment.get(obj.name)
        if extra:
            mis = Misalignment(**{**asdict(mis), **{_MIS_KEYS[k]: v for k, v in extra.items()}})
        links.append(chain_link(obj.type, getter(obj), obj.comment, mis, obj.name))
    return chain_frames(links)


def _source(src_obj, get, c: int, device) -> dict:
    """The point source's sizes, divergences and energy as (C,) columns.

    Other sources are traced from given rays: their type alone.
    """
    source = {"type": src_obj.type}
    if src_obj.type == "Point Source":
        source.update(width=get("sourceWidth"), height=get("sourceHeight"), depth=get("sourceDepth"),
                      hor_div=get("horDiv") * 1e-3, ver_div=get("verDiv") * 1e-3,
                      energy=get("photonEnergy"), spread=get("energySpread", 0.0))
        source = {k: (v if k == "type" else _col(v, c, torch.float64, device)) for k, v in source.items()}
        source["dists"] = tuple(int(src_obj.get_float(k, 1.0)) for k in (
            "sourceWidthDistribution", "sourceHeightDistribution", "horDivDistribution", "verDivDistribution"))
    return source


def _stack_states(states, device):
    """One state with (C,) tensors from per-configuration states of numbers."""
    from bluesky_offsets.physics.metrixs import BeamlineState
    out = BeamlineState()
    types = [s.types for s in states]
    if any(t != types[0] for t in types):
        raise InputError("the configurations of one batch must not change element types differently")
    out.types = dict(types[0])
    for attr in ("fields", "misalignment"):
        keys = {(o, k) for s in states for o, fl in getattr(s, attr).items() for k in fl}
        target = getattr(out, attr)
        for o, k in keys:
            col = []
            for s in states:
                v = getattr(s, attr).get(o, {}).get(k)
                if v is None:  # not set for this configuration: no misalignment, the nominal field
                    v = 0.0 if attr == "misalignment" else _NOMINAL[o].get_float(k)
                col.append(torch.as_tensor(v, dtype=torch.float64, device=device).reshape(()))
            target.setdefault(o, {})[k] = torch.stack(col)
    return out


def _optic(obj, get, rot, shift, c, device) -> Optic:
    t = obj.type

    def col(key, default=None):
        return _col(get(key, default), c, torch.float64, device)

    if t == "Slit":
        behaviour, surface = "slit", "plane"
    elif t == "ImagePlane":
        behaviour, surface = "image", "plane"
    elif t in GRATING_TYPES:
        behaviour = "grating"
        surface = "plane" if t == "Plane Grating" else "quadric"
    elif t in MIRROR_TYPES:
        behaviour = "mirror"
        surface = "plane" if t == "Plane Mirror" else ("toroid" if t == "Toroid" else "quadric")
    else:
        raise RmlError(f"object {obj.name!r}: element type {t!r} is not traced by the torch engine")
    opt = Optic(obj.name, t, behaviour, surface, rot, shift)
    if surface == "quadric":
        opt.quadric = _quadric(t, col, obj)
    elif surface == "toroid":
        opt.quadric = {"R": col("longRadius"), "rho": col("shortRadius")}
    if t != "ImagePlane":
        shape = int(obj.get_float("geometricalShape", 0))
        if shape not in (0, 1):
            raise RmlError(f"{obj.name!r}: outline shape {shape} (trapezoid) is not traced by the torch engine")
        length = col("totalHeight") if t in FLAT_TYPES else col("totalLength")
        opt.cutout = (shape, col("totalWidth"), length)
    if behaviour == "slit":
        shape, stop = int(obj.get_float("openingShape", 0)), int(obj.get_float("centralBeamstop", 0))
        if shape != 0:
            raise RmlError(f"{obj.name!r}: only rectangular slit openings are traced by the torch engine")
        opt.opening = (shape, col("openingWidth"), col("openingHeight"), stop,
                       col("stopWidth", 0.0), col("stopHeight", 0.0))
    if obj.has("slopeError") and obj.comment("slopeError") == "Yes":
        sag, mer = col("slopeErrorSag", 0.0), col("slopeErrorMer", 0.0)
        if torch.is_tensor(sag) or torch.is_tensor(mer) or sag != 0.0 or mer != 0.0:
            opt.slope = (sag * ARCSEC, mer * ARCSEC)
    if behaviour == "grating":
        vls = tuple(col(f"vlsParameter{i}", 0.0) for i in range(1, 7)) \
            if obj.comment("lineSpacing") == "variable (VLS)" else (0.0,) * 6
        opt.grating = (col("lineDensity"), int(obj.get_float("orderDiffraction")), vls)
    return opt


def _quadric(t, col, obj) -> dict:
    """RAYX's quadric coefficients (RAYX-CONVENTIONS.md §5) of a curved element."""
    q = dict(a11=0.0, a12=0.0, a13=0.0, a14=0.0, a22=0.0, a23=0.0, a24=0.0, a33=0.0, a34=0.0, a44=0.0)
    if t == "Cylinder":
        r = col("radius")
        if int(obj.get_float("bendingRadius", 1)) == 1:  # "Short Radius rho": sagittal
            q.update(a11=1.0, a22=1.0, a24=-r)
        else:
            q.update(a22=1.0, a33=1.0, a24=-r)
        q["icurv"] = _sign_icurv(q["a24"])
    elif t in ("Sphere", "Spherical Grating"):
        q.update(a11=1.0, a22=1.0, a33=1.0, a24=-col("radius"), icurv=1.0)
    elif t == "Ellipsoid":
        from bluesky_offsets.physics.geometry import ellipsoid_pole
        a, b = col("longHalfAxisA"), col("shortHalfAxisB")
        theta = math.radians(obj.get_float("designGrazingIncAngle"))
        y0, z0 = ellipsoid_pole(a, b, theta, obj.get_float("entranceArmLength"), obj.get_float("exitArmLength"))
        torch_ns = torch if torch.is_tensor(y0) or torch.is_tensor(z0) else math
        m = (b / a) ** 2 * z0 / y0
        alpha = torch_ns.atan(m)
        k = (b / a) ** 2
        ca, sa = torch_ns.cos(alpha), torch_ns.sin(alpha)
        fr = int(obj.get_float("figureRotation", 0))
        a11 = {0: 1.0, 1: 0.0}.get(fr, obj.get_float("parameter_a11", 1.0))
        q.update(a11=a11, a22=ca * ca + k * sa * sa, a33=sa * sa + k * ca * ca, a23=-(1 - k) * sa * ca,
                 a24=k * z0 * sa + y0 * ca, a34=k * z0 * ca - y0 * sa, a44=y0 * y0 + k * z0 * z0 - b * b,
                 icurv=1.0)
    else:
        raise RmlError(f"{obj.name!r}: surface of type {t!r} is not traced by the torch engine")
    return q


def _sign_icurv(a24):
    if torch.is_tensor(a24):
        return torch.where(a24 <= 0, 1.0, -1.0).to(a24.dtype)
    return 1.0 if a24 <= 0 else -1.0


def _take_optic(opt: Optic, c: int, owner: torch.Tensor) -> Optic:
    """``opt`` with its configuration fields (leading axis ``c``) taken for each of the rays ``owner`` (K,).

    Every ray becomes a configuration of its own (a compacting trace).
    """
    def take(v):
        if torch.is_tensor(v) and v.is_floating_point() and v.ndim >= 1 and v.shape[0] == c and c > 1:
            return v.index_select(0, owner)
        if isinstance(v, tuple):
            return tuple(take(x) for x in v)
        if isinstance(v, dict):
            return {k: take(x) for k, x in v.items()}
        return v
    return Optic(opt.name, opt.type, opt.behaviour, opt.surface, take(opt.rot), take(opt.shift),
                 take(opt.quadric), take(opt.cutout), take(opt.opening), take(opt.slope), take(opt.grating))


def _compiled_tensors(bl: CompiledBeamline, c: int) -> list[torch.Tensor]:
    """The floating-point tensors of a compiled beamline with a configuration axis.

    They come in the order :func:`_replace_tensors` visits them, each broadcast to a leading axis
    of ``c``.
    """
    out: list[torch.Tensor] = []
    _replace_tensors(bl, c, None, c, out)
    return out


def _replace_tensors(bl: CompiledBeamline, c: int, new, c_new: int, found: list | None = None) -> CompiledBeamline:
    """A copy of ``bl`` with its floating tensors taken from the iterator ``new``.

    The tensors (leading axis ``c``, or 1) are replaced by those of ``new`` (leading axis
    ``c_new``) in a fixed order; with ``found``, collect them.
    """
    def sub(v):
        if torch.is_tensor(v) and v.is_floating_point() and v.ndim >= 1 and v.shape[0] in (1, c):
            v = v.expand(c, *v.shape[1:]) if v.shape[0] == 1 and c != 1 else v
            if found is not None:
                found.append(v)
                return v
            return next(new)
        if isinstance(v, tuple):
            return tuple(sub(x) for x in v)
        if isinstance(v, dict):
            return {k: sub(x) for k, x in v.items()}
        return v
    optics = [Optic(o.name, o.type, o.behaviour, o.surface, sub(o.rot), sub(o.shift), sub(o.quadric),
                    sub(o.cutout), sub(o.opening), sub(o.slope), sub(o.grating)) for o in bl.optics]
    source = sub(bl.source)
    return CompiledBeamline(c_new, source, sub(bl.source_rot), sub(bl.source_shift), optics, bl.dtype, bl.device)
