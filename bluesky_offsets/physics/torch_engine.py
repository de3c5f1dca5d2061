"""The differentiable twin: the METRIXS beamline traced in PyTorch with RAYX's physics.

RAYX (the reference engine, and the simulated IOC's "real beamline") has no gradients and
no batch interface.  This engine traces the same beamline, element by element, in RAYX's
conventions (``../shared/reference/RAYX-CONVENTIONS.md``; RAYX's source, hz-b/rayx), batched
over configurations and rays, on CPU or CUDA, differentiable in every parameter:

* **frames** come from the project's own geometry (:mod:`.geometry`, :func:`.metrixs.beamline_state`):
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
a ray counts for the focus only if it meets the elements in order (:func:`.twin.footprint`),
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

import math
import os
import threading
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Literal

import numpy as np
import torch

from bluesky_offsets.errors import InputError
from bluesky_offsets.options import refuse_unknown
from bluesky_offsets.physics import torch_random as rnd
from bluesky_offsets.physics.geometry import Misalignment, chain_frames
from bluesky_offsets.physics.metrixs import beamline_state, check_physical, nominal_beamline
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.physics.rml import FLAT_TYPES, GRATING_TYPES, MIRROR_TYPES, RmlError, chain_link
from bluesky_offsets.physics.traces import HistogramSpec, TraceRequest, TraceResult

HC_EV_NM = 1239.841984332002622  # RAYX's h·c in eV·nm
SEARCH_SHIFT = 1e-6  # mm: RAYX starts each search this far along the ray
ARCSEC = math.pi / 180.0 / 3600.0
# soft weight below which a ray's derivatives are taken as 0 (TorchEngine.ray_jacobian): each is
# bounded by the weight times its apertures' logistic slopes (|dw/dθ| / w measured up to 6e4 per
# unit of an input, the exit slit's height), so below 1e-16 beneath the rounding of any product
# of the rays (measured: the camera-histogram Jacobian moves by at most 1.2e-15 of each column's
# largest entry against a floor of 1e-30, as with 1e-24), and 18 % fewer rays are traced for
# their derivatives at the main job's configurations (docs/benchmarks.md, "Per-ray Jacobian")
RAY_WEIGHT_FLOOR = 1e-16
# a compacting trace gathers the rays still in flight once fewer than this share of those
# traced are (a gather costs about one element's arithmetic on the survivors)
COMPACT_BELOW = 0.8
#: Held by every use of forward-mode AD (``torch.autograd.forward_ad``, ``torch.func.jvp``).
#: Its dual level is one for the whole process: torch refuses a second one, and the level a
#: thread leaves is gone for the thread still inside it (measured: two beam optimizations on
#: two threads failed with "Trying to access a forward AD level with an invalid index").  Fits
#: run side by side on threads (:func:`bluesky_offsets.model.fit.gather`); reverse mode, what
#: they mostly use, is safe there.
FORWARD_AD = threading.RLock()
FEATURES = ("intensity", "centroid_x", "centroid_y", "width_x", "width_y")
_MIS_KEYS = {"translationXerror": "tx", "translationYerror": "ty", "translationZerror": "tz",
             "rotationXerror": "rx", "rotationYerror": "ry", "rotationZerror": "rz"}


# --------------------------------------------------------------------------- #
# options
# --------------------------------------------------------------------------- #
@dataclass(frozen=True)
class TorchOptions:
    """How the torch engine traces.

    dtype : "float64" (default; equal to RAYX ray for ray) or "float32" (faster, coarser:
        docs/benchmarks.md gives its measured accuracy).
    device : "cpu", "cuda", "cuda:1" ...
    sampling : "fast" (torch's generator, inverse-CDF slit kicks) or "rayx" (RAYX's own
        random stream, for ray-for-ray comparisons; slower: rejection loops).
    common_rays : share the random numbers across the configurations of a batch (common
        random numbers: differences between configurations carry no sampling noise of
        their own); False draws each configuration from ``seed + i``.
    max_batch : configurations × rays traced at once; larger batches are traced in chunks
        of rays (memory: ~2 kB per ray and configuration with gradients).
    edge : soft-edge width, relative to each aperture dimension, for the smooth (soft)
        beam the gradients use; 0 = hard edges.
    kernel : width (in bins) of the kernel that bins the soft histograms and profiles.
    """

    dtype: Literal["float64", "float32"] = "float64"
    device: str = "cpu"
    sampling: Literal["fast", "rayx"] = "fast"
    common_rays: bool = True
    max_batch: int = 1 << 19
    edge: float = 0.002
    kernel: float = 1.0

    def __post_init__(self):
        if self.dtype not in ("float64", "float32"):
            raise InputError(f"dtype must be 'float64' or 'float32', not {self.dtype!r}")
        if self.sampling not in ("fast", "rayx"):
            raise InputError(f"sampling must be 'fast' or 'rayx', not {self.sampling!r}")
        if int(self.max_batch) < 1:
            raise InputError("max_batch must be positive")
        if not (self.edge >= 0 and math.isfinite(self.edge)):
            raise InputError("edge must be a finite number >= 0")
        if not (self.kernel > 0 and math.isfinite(self.kernel)):
            raise InputError("kernel must be a finite number > 0")
        torch.device(self.device)  # refuses a malformed device string

    @classmethod
    def from_mapping(cls, options: Mapping[str, object] | None) -> TorchOptions:
        """Options from a mapping; an unknown key is refused, naming the known ones."""
        options = dict(options or {})
        refuse_unknown(cls, options, "unknown torch engine option(s)")
        return cls(**options)

    @property
    def torch_dtype(self) -> torch.dtype:
        return torch.float64 if self.dtype == "float64" else torch.float32


# --------------------------------------------------------------------------- #
# the compiled beamline
# --------------------------------------------------------------------------- #
@dataclass
class Optic:
    """One element as the tracer needs it; tensors have a leading configuration axis
    (shape (C, 1) to broadcast over rays) or are plain numbers when constant."""

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
    source: dict[str, object]  # width, height, depth, hor_div, ver_div (rad), energy, spread
    source_rot: torch.Tensor  # (C, 3, 3) source frame -> first optic's local frame
    source_shift: torch.Tensor  # (C, 3)
    optics: list[Optic]
    dtype: torch.dtype
    device: torch.device

    @property
    def names(self) -> list[str]:
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
    src_rot = src_shift = None
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
    return CompiledBeamline(c, source, src_rot.to(dtype), src_shift.to(dtype), optics, dtype, device)


def _compiled_state(vals, overrides, table: ParameterTable, beamline, check: bool, device):
    """The beamline to compile (METRIXS's nominal one, or ``beamline``) and its state at ``vals``:
    every field and misalignment the parameters and ``overrides`` set, as (C,) columns."""
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
    """The point source's sizes, divergences and energy as (C,) columns (other sources are traced
    from given rays: their type alone)."""
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


# --------------------------------------------------------------------------- #
# rays
# --------------------------------------------------------------------------- #
@dataclass
class Rays:
    """Rays in some frame; tensors (C or 1, N)."""

    x: torch.Tensor
    y: torch.Tensor
    z: torch.Tensor
    dx: torch.Tensor
    dy: torch.Tensor
    dz: torch.Tensor
    energy: torch.Tensor
    ctr: torch.Tensor | None = None  # RAYX's counters (sampling="rayx")

    def slice(self, a: int, b: int) -> Rays:
        def cut(t):
            return None if t is None else t[..., a:b]
        return Rays(*(cut(getattr(self, f.name)) for f in fields(self)))


@dataclass
class Draws:
    """The fast stream's random numbers, drawn up front so that chunking changes nothing:
    ``slits[name]`` (2, C|1, N) the kicks' accepted draws (width, height), ``slopes[name]``
    (2, C|1, N) standard normals."""

    slits: dict[str, torch.Tensor]
    slopes: dict[str, torch.Tensor]

    def slice(self, a: int, b: int) -> Draws:
        return Draws({k: v[..., a:b] for k, v in self.slits.items()},
                     {k: v[..., a:b] for k, v in self.slopes.items()})


def _generator(seed: int | None, device) -> torch.Generator:
    g = torch.Generator(device=device)
    g.manual_seed(int(seed) if seed is not None else int.from_bytes(os.urandom(8), "little") >> 1)
    return g


def _streams(seed, n_configs: int, common: bool) -> list[int | None]:
    """One seed per random stream: a sequence gives one per configuration as it is; else
    one shared stream (common) or ``seed + i`` for configuration ``i``."""
    if isinstance(seed, Sequence):
        seeds = [None if s is None else int(s) for s in seed]
        if len(seeds) != n_configs:
            raise InputError(f"{len(seeds)} seeds for {n_configs} configurations")
        return seeds
    if common:
        return [seed]
    if seed is None:
        return [None] * n_configs
    return [int(seed) + i for i in range(n_configs)]


def sample_source(bl: CompiledBeamline, n_rays: int, seed, *, sampling: str = "fast",
                  common: bool = True, batch_stream: bool = False) -> tuple[Rays, Draws | None]:
    """Source rays (source frame) and, for the fast stream, every later draw.

    ``sampling="rayx"`` reproduces RAYX's point source for ``rayx::fixSeed(seed)``
    (RAYX-CONVENTIONS.md §3–4): 14 draws per ray in RAYX's order, counters carried on.
    ``batch_stream`` (fast sampling, one seed): every configuration its own rays, all drawn
    from one generator at once (a batch of many configurations pays one call per draw kind
    instead of one per configuration: the dataset's blocks).
    """
    units = source_units(bl, n_rays, seed, sampling=sampling, common=common, batch_stream=batch_stream)
    return source_rays(bl, units), units.draws


@dataclass
class SourceUnits:
    """The source's unit draws (6 coordinates, each (C|1, N)) before the source's sizes scale
    them, the later draws of the fast stream and RAYX's counters: what a trace's randomness is,
    apart from the beamline it meets."""

    coord: list[torch.Tensor]
    draws: Draws | None
    ctr: torch.Tensor | None = None

    def take(self, configs: torch.Tensor, rays: torch.Tensor) -> SourceUnits:
        """The rays ``rays`` of configurations ``configs`` (K each), every one its own
        configuration (a leading axis of K, one ray each): (C|1, N) -> (K, 1)."""
        def pick(t):
            return t[..., configs if t.shape[-2] > 1 else 0, rays][..., None]
        d = self.draws
        draws = None if d is None else Draws({k: pick(v) for k, v in d.slits.items()},
                                             {k: pick(v) for k, v in d.slopes.items()})
        return SourceUnits([pick(t) for t in self.coord], draws, None if self.ctr is None else pick(self.ctr))


# Seeded source draws, kept for the next call with the same seed: a fit traces its rays again
# at every step (common random numbers), and drawing them (~10 ms for 5000 rays and the
# draws of 3 slits and 5 slope errors) was a sixth of a value trace.  The draws depend on
# the seed, the ray count and which elements draw, never on the parameter values; nothing
# writes into them.  Bounded: entries of at most UNITS_CACHE_BYTES, the last UNITS_CACHE_SIZE.
UNITS_CACHE_SIZE = 8
UNITS_CACHE_BYTES = 64 << 20
_units_cache: dict[tuple, SourceUnits] = {}
_units_lock = threading.Lock()


def _units_key(bl: CompiledBeamline, n_rays: int, seed, sampling: str, common: bool) -> tuple | None:
    """The draws' identity, or None where they are not reproducible (an unseeded stream)."""
    if isinstance(seed, torch.Generator):
        return None
    seeds = _streams(seed, bl.n_configs, common)
    if any(s is None for s in seeds):
        return None
    return (sampling, int(n_rays), tuple(seeds), str(bl.device), tuple(bl.source["dists"]),
            tuple(o.name for o in bl.optics if o.behaviour == "slit"),
            tuple(o.name for o in bl.optics if o.slope is not None))


def _units_bytes(u: SourceUnits) -> int:
    ts = list(u.coord) + ([] if u.ctr is None else [u.ctr])
    if u.draws is not None:
        ts += list(u.draws.slits.values()) + list(u.draws.slopes.values())
    return sum(t.numel() * t.element_size() for t in ts)


def source_units(bl: CompiledBeamline, n_rays: int, seed, *, sampling: str = "fast",
                 common: bool = True, batch_stream: bool = False) -> SourceUnits:
    """The random part of :func:`sample_source` (seeded draws come from a small cache: the
    same tensors for the same seed, ray count and drawing elements)."""
    src = bl.source
    if src["type"] != "Point Source":
        raise RmlError(f"the torch engine samples point sources only ({src['type']!r}: pass rays)")
    key = None if batch_stream else _units_key(bl, n_rays, seed, sampling, common)
    if key is not None:
        with _units_lock:
            hit = _units_cache.pop(key, None)
            if hit is not None:
                _units_cache[key] = hit  # the most recent last
                return hit
    units = _draw_units(bl, n_rays, seed, sampling=sampling, common=common, batch_stream=batch_stream)
    if key is not None and _units_bytes(units) <= UNITS_CACHE_BYTES:
        with _units_lock:
            _units_cache[key] = units
            while len(_units_cache) > UNITS_CACHE_SIZE:
                _units_cache.pop(next(iter(_units_cache)))
    return units


def _draw_units(bl: CompiledBeamline, n_rays: int, seed, *, sampling: str, common: bool,
                batch_stream: bool) -> SourceUnits:
    src = bl.source
    dev, c = bl.device, bl.n_configs
    if batch_stream:
        if sampling != "fast" or isinstance(seed, Sequence):
            raise InputError("batch_stream draws the fast stream from one seed")
        return _batch_units(bl, n_rays, seed)
    seeds = _streams(seed, c, common)
    dists = src["dists"]
    if sampling == "rayx":
        trace_seeds = [rnd.rayx_trace_seed(s if s is not None else int.from_bytes(os.urandom(4), "little"))
                       for s in seeds]
        ctr = torch.stack([rnd.rayx_counters(n_rays, ts, device=dev) for ts in trace_seeds])

        def normal():
            nonlocal ctr
            z = rnd.squares_normal(ctr)
            ctr = ctr + 3
            return z

        def uniform():
            nonlocal ctr
            u = rnd.squares_uniform(ctr)
            ctr = ctr + 1
            return u
        coord = [None] * 6
        coord[0] = normal() if dists[0] else uniform() - 0.5
        coord[1] = normal() if dists[1] else uniform() - 0.5
        coord[2] = uniform() - 0.5
        coord[3] = uniform() - 0.5
        coord[4] = normal() if dists[3] else uniform() - 0.5
        coord[5] = normal() if dists[2] else uniform() - 0.5
        return SourceUnits(coord, None, ctr)
    slits, slopes = {}, {}
    gens = [_generator(s, dev) for s in seeds]
    # per stream: four normals (width, height, divergences) and six uniforms (depth,
    # energy, and the four coordinates again for hard-edged distributions)
    nn = torch.stack([torch.randn(4, n_rays, generator=g, device=dev, dtype=torch.float64) for g in gens], 1)
    uu = torch.stack([torch.rand(6, n_rays, generator=g, device=dev, dtype=torch.float64) for g in gens], 1)
    coord = [nn[0] if dists[0] else uu[2] - 0.5, nn[1] if dists[1] else uu[3] - 0.5,
             uu[0] - 0.5, uu[1] - 0.5,
             nn[2] if dists[3] else uu[4] - 0.5, nn[3] if dists[2] else uu[5] - 0.5]
    for opt in bl.optics:
        if opt.behaviour == "slit":  # the kicks' accepted draws, by inverse CDF, once for all configurations
            slits[opt.name] = rnd.fraunhofer_uniform_fast(torch.stack(
                [torch.rand(2, n_rays, generator=g, device=dev, dtype=torch.float64) for g in gens], 1))
        if opt.slope is not None:
            slopes[opt.name] = torch.stack([torch.randn(2, n_rays, generator=g, device=dev,
                                                        dtype=torch.float64) for g in gens], 1)
    return SourceUnits(coord, Draws(slits, slopes))


def _batch_units(bl: CompiledBeamline, n_rays: int, seed, lazy: bool = False) -> SourceUnits:
    """The fast stream's draws of :func:`source_units`, (C, N) each, from one generator
    (``seed``: a number or a generator); ``lazy``: the later draws as :class:`LazyDraws`."""
    dev, c, dists = bl.device, bl.n_configs, bl.source["dists"]
    g = seed if isinstance(seed, torch.Generator) else _generator(seed, dev)
    nn = torch.randn(4, c, n_rays, generator=g, device=dev, dtype=torch.float64)
    uu = torch.rand(6, c, n_rays, generator=g, device=dev, dtype=torch.float64)
    coord = [nn[0] if dists[0] else uu[2] - 0.5, nn[1] if dists[1] else uu[3] - 0.5,
             uu[0] - 0.5, uu[1] - 0.5,
             nn[2] if dists[3] else uu[4] - 0.5, nn[3] if dists[2] else uu[5] - 0.5]
    if lazy:
        return SourceUnits(coord, LazyDraws(g))
    slits, slopes = {}, {}
    for opt in bl.optics:
        if opt.behaviour == "slit":
            slits[opt.name] = rnd.fraunhofer_uniform_fast(
                torch.rand(2, c, n_rays, generator=g, device=dev, dtype=torch.float64))
        if opt.slope is not None:
            slopes[opt.name] = torch.randn(2, c, n_rays, generator=g, device=dev, dtype=torch.float64)
    return SourceUnits(coord, Draws(slits, slopes))


class LazyDraws:
    """The fast stream's later draws (slit kicks, slope errors) made as a ray meets the element,
    for the rays in flight only: in a compacting trace the rays stopped upstream draw nothing
    (most of a dim batch's rays).  Same distributions as :class:`Draws`, other numbers."""

    def __init__(self, generator: torch.Generator):
        self.generator = generator

    def slit(self, like: torch.Tensor) -> torch.Tensor:
        return rnd.fraunhofer_uniform_fast(torch.rand(2, *like.shape, generator=self.generator,
                                                      device=like.device, dtype=torch.float64))

    def slope(self, like: torch.Tensor) -> torch.Tensor:
        return torch.randn(2, *like.shape, generator=self.generator, device=like.device, dtype=torch.float64)


def source_rays(bl: CompiledBeamline, units: SourceUnits) -> Rays:
    """The source's unit draws scaled by its sizes, divergences and energy (differentiable in them);
    seven coordinates are rays given as they are (position, direction, energy: another source's
    own draws, :func:`given_units`)."""
    src, coord = bl.source, units.coord
    if len(coord) == 7:
        dt = bl.dtype
        return Rays(*(t.to(dt) for t in coord[:6]), coord[6].to(torch.float64), units.ctr)
    x = coord[0] * src["width"]
    y = coord[1] * src["height"]
    z = coord[2] * src["depth"]
    energy = src["energy"] + coord[3] * src["spread"]
    psi = coord[4] * src["ver_div"]
    phi = coord[5] * src["hor_div"]
    dx, dy, dz = torch.cos(psi) * torch.sin(phi), -torch.sin(psi), torch.cos(psi) * torch.cos(phi)
    dt = bl.dtype
    energy = energy * torch.ones_like(x)
    return Rays(x.to(dt), y.to(dt), z.to(dt), dx.to(dt), dy.to(dt), dz.to(dt), energy.to(torch.float64), units.ctr)


def given_units(rays: Rays) -> SourceUnits:
    """Given rays as a trace's randomness (:func:`source_rays` passes them through)."""
    return SourceUnits([rays.x, rays.y, rays.z, rays.dx, rays.dy, rays.dz, rays.energy], None, rays.ctr)


def rays_from_arrays(position: np.ndarray, direction: np.ndarray, energy: np.ndarray, *,
                     dtype=torch.float64, device="cpu", counters=None) -> Rays:
    """Rays given in the source frame (e.g. RAYX's own emitted rays), shape (N, 3)."""
    p = torch.as_tensor(np.asarray(position, float), dtype=dtype, device=device)
    d = torch.as_tensor(np.asarray(direction, float), dtype=dtype, device=device)
    e = torch.as_tensor(np.asarray(energy, float), dtype=torch.float64, device=device)
    ctr = None if counters is None else torch.as_tensor(counters, dtype=torch.int64, device=device)[None]
    return Rays(p[None, :, 0], p[None, :, 1], p[None, :, 2], d[None, :, 0], d[None, :, 1], d[None, :, 2],
                e[None], ctr)


# --------------------------------------------------------------------------- #
# tracing
# --------------------------------------------------------------------------- #
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


def _zero(v) -> bool:
    """An exact number 0: a term it multiplies is left out (adding an exact zero changes no
    rounding, and plane hits, normals and most quadric coefficients are exactly zero)."""
    return not torch.is_tensor(v) and v == 0.0


def _poly(*terms):
    """Sum of products, each term a tuple of factors multiplied left to right, terms added
    left to right; terms with an exact-zero factor are skipped."""
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


def _entries(m) -> tuple:
    """A matrix (C, 3, 3) or vector (C, 3) as nested tuples of its entries (C,); given as such
    (:meth:`TorchEngine.ray_jacobian`: every entry a leaf of its own), as it is.  Entries by
    unbind, not by indexing: the backward of one index writes the whole matrix per entry,
    which had made 60 % of a per-ray Jacobian (each ray has its own matrices there)."""
    if isinstance(m, tuple):
        return m
    return tuple(_entries(row) for row in m.unbind(1)) if m.ndim > 2 else m.unbind(1)


def _apply(rot, shift, x, y, z):
    r = [[e[:, None] for e in row] for row in _entries(rot)]  # (C, 1) broadcast over rays
    out = [_poly((r[k][0], x), (r[k][1], y), (r[k][2], z)) for k in range(3)]
    if shift is None:
        return tuple(out)
    return tuple(o + s[:, None] for o, s in zip(out, _entries(shift)))


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
    """RAYX's quadric intersection (RAYX-CONVENTIONS.md §5.2): one root, chosen by the sign
    of the ray's dominant direction component and the surface's ``icurv``."""
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
    """Rays RAYX's toroid iteration finds on the same toroid again, just ahead of where they left it
    (RAYX-CONVENTIONS §5.6): RAYX reflects them there until its event cap, and they are lost."""
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


# One function over 100 lines: the loop over the elements carries the beam's state in a dozen
# tensors (positions, directions, survival, weights, hits, the compaction's indices); split, each
# part would take and return them all.
def trace_rays(bl: CompiledBeamline, rays: Rays, draws: Draws | None = None, *, edge: float = 0.0,
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


def _detach(v):
    return v.detach() if torch.is_tensor(v) else v


def _kick(u, wavelength, dim, dt):
    """Fraunhofer kick (rad) of the accepted draw ``u`` for an opening ``dim`` mm (RAYX:
    ``(u - 0.5) * 10 λ / b``, b in nm); none for a closed dimension, which draws nothing."""
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


# --------------------------------------------------------------------------- #
# beam products: histograms, profiles, features
# --------------------------------------------------------------------------- #
def histograms(beam: Beam, spec: HistogramSpec, *, soft: bool = False, kernel: float = 1.0,
               n_source: int | None = None):
    """x and y histograms (C, bins) as fraction of source rays (RAYX's bin convention).

    ``soft``: every ray spreads its weight over the bins with a Gaussian kernel of ``kernel``
    bins rms (differentiable in the ray positions).  ``n_source``: the source rays the fractions
    are of (default the beam's own; a chunk of a trace passes the whole trace's, so chunks add up)."""
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
    """Sufficient statistics (C, 5) of the beam: Σw, Σwx, Σwy, Σwx², Σwy² (w the soft weight
    or the hard survival); sums over rays, so chunks of rays add up."""
    w = beam.weight if soft else beam.alive.to(beam.x.dtype)
    x, y = beam.x, beam.y
    return torch.stack([w.sum(-1), (w * x).sum(-1), (w * y).sum(-1), (w * x * x).sum(-1), (w * y * y).sum(-1)], -1)


def features_from_moments(m: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Beam features (C, 5): intensity (fraction of source rays), centroid x, y, rms width
    x, y (mm); centroid and width are NaN where no ray arrives."""
    s0 = m[..., 0]
    s0s = torch.where(s0 > 0, s0, torch.ones_like(s0))
    cx, cy = m[..., 1] / s0s, m[..., 2] / s0s
    vx = (m[..., 3] / s0s - cx * cx).clamp(min=1e-30)
    vy = (m[..., 4] / s0s - cy * cy).clamp(min=1e-30)
    out = torch.stack([s0 / n_rays, cx, cy, torch.sqrt(vx), torch.sqrt(vy)], -1)
    nan = torch.full_like(out, float("nan"))
    keep = torch.stack([torch.ones_like(s0, dtype=torch.bool)] + [s0 > 0] * 4, -1)
    return torch.where(keep, out, nan)


@dataclass(frozen=True)
class TraceBatch:
    """Hard histograms of a batch (:meth:`TorchEngine.trace_batch`): fractions of the
    ``n_rays`` source rays per bin, (C, bins), and the rays on the screen, (C,)."""

    hist_x: np.ndarray
    hist_y: np.ndarray
    n_hits: np.ndarray
    n_rays: int


# --------------------------------------------------------------------------- #
# the engine
# --------------------------------------------------------------------------- #
class TorchEngine:
    """The differentiable twin behind the :class:`~bluesky_offsets.physics.twin.TraceEngine` interface.

    ``Twin(engine="torch")`` uses it; RAYX stays the reference engine.  Besides ``trace``
    (one request) it traces batches in one call (:meth:`trace_many`, :meth:`beam`) and gives
    beam features, soft histograms and camera profiles with their Jacobians
    (:meth:`jacobian`).

    Parameters
    ----------
    table, hist : as for :class:`~bluesky_offsets.physics.twin.RayxEngine`.
    options : TorchOptions or a mapping of its fields (unknown keys are refused).
    """

    def __init__(self, table: ParameterTable = METRIXS, hist: HistogramSpec | None = None,
                 options: TorchOptions | Mapping | None = None):
        self.table = table
        self.hist = hist or HistogramSpec()
        self.options = options if isinstance(options, TorchOptions) else TorchOptions.from_mapping(options)

    @property
    def version(self) -> str:
        o = self.options
        return f"torch {torch.__version__} (bluesky-offsets tracer, {o.sampling} sampling, {o.dtype}, {o.device})"

    # -- batches ----------------------------------------------------------------
    def _units(self, bl: CompiledBeamline, n_rays: int, seed) -> SourceUnits:
        """A trace's randomness: the source's draws (an engine with another source gives its rays)."""
        o = self.options
        return source_units(bl, n_rays, seed, sampling=o.sampling, common=o.common_rays)

    def compile(self, values, overrides=None) -> CompiledBeamline:
        o = self.options
        return compile_beamline(values, overrides, table=self.table, dtype=o.torch_dtype, device=o.device)

    def _chunks(self, bl: CompiledBeamline, n_rays: int, seed, edge: float, keep_hits: bool = False):
        """Trace ``n_rays`` per configuration in memory-bounded chunks of rays."""
        o = self.options
        units = self._units(bl, n_rays, seed)
        rays, draws = source_rays(bl, units), units.draws
        step = max(1, o.max_batch // max(bl.n_configs, 1))
        for a in range(0, n_rays, step):
            b = min(n_rays, a + step)
            yield a, trace_rays(bl, rays.slice(a, b), None if draws is None else draws.slice(a, b),
                                edge=edge, keep_hits=keep_hits)

    def beam(self, values, overrides=None, *, n_rays: int, seed=None, edge: float = 0.0,
             keep_hits: bool = False) -> Beam:
        """All rays of a batch at the screen, its chunks joined (all rays held at once)."""
        bl = self.compile(values, overrides)
        parts = list(self._chunks(bl, n_rays, seed, edge, keep_hits))
        if len(parts) == 1:
            return parts[0][1]
        def cat(name):
            return torch.cat([getattr(b, name) for _, b in parts], -1)
        hits = None if not keep_hits else {k: torch.cat([b.hits[k] for _, b in parts], 1) for k in parts[0][1].hits}
        dirs = None if not keep_hits else {k: torch.cat([b.directions[k] for _, b in parts], 1)
                                           for k in parts[0][1].directions}
        return Beam(cat("x"), cat("y"), cat("alive"), cat("weight"), n_rays, hits, dirs)

    def trace_many(self, requests: Sequence[TraceRequest], n_rays: int, keep_rays: bool = False) -> list[TraceResult]:
        """Trace requests as one batch (groups of equal element types), results in order.

        Requests that share one seed share their rays (common random numbers, when the
        options say so); different seeds give each request its own stream."""
        if n_rays < 1:
            raise InputError(f"n_rays must be positive, got {n_rays}")
        out: list[TraceResult | None] = [None] * len(requests)
        groups: dict[tuple, list[int]] = {}
        for i, r in enumerate(requests):
            key = tuple(sorted((k, str(f.get("type"))) for k, f in r.overrides.items() if "type" in f))
            groups.setdefault(key, []).append(i)
        for idx in groups.values():
            reqs = [requests[i] for i in idx]
            values = np.stack([self.table.validate(r.values) for r in reqs])
            seeds = [r.seed for r in reqs]
            seed = seeds[0] if len(set(seeds)) == 1 and seeds[0] is not None else seeds
            if all(not r.overrides for r in reqs):
                overrides = None
            else:
                overrides = [dict(r.overrides) for r in reqs]
            for i, res in zip(idx, self._trace_group(values, overrides, n_rays, seed, keep_rays)):
                out[i] = res
        return out  # type: ignore[return-value]

    def _trace_group(self, values, overrides, n_rays, seed, keep_rays) -> list[TraceResult]:
        bl = self.compile(values, overrides)
        c = bl.n_configs
        hx = hy = None
        n_hits = torch.zeros(c, dtype=torch.int64)
        kept: list[list[np.ndarray]] = [[] for _ in range(c)]
        with torch.no_grad():
            for _, beam in self._chunks(bl, n_rays, seed, 0.0):
                bx, by = histograms(beam, self.hist, n_source=n_rays)
                hx = bx if hx is None else hx + bx
                hy = by if hy is None else hy + by
                n_hits += beam.alive.sum(-1).cpu()
                if keep_rays:
                    for k in range(c):
                        a = beam.alive[k]
                        kept[k].append(torch.stack([beam.x[k][a], beam.y[k][a]], -1).cpu().numpy().astype(float))
        hx, hy = hx.cpu().numpy().astype(float), hy.cpu().numpy().astype(float)
        return [TraceResult(hx[k], hy[k], int(n_hits[k]), int(n_rays), np.asarray(values[k], float),
                            np.concatenate(kept[k]) if keep_rays else None) for k in range(c)]

    def trace_batch(self, values, overrides=None, *, n_rays: int, seed=None) -> TraceBatch:
        """Hard histograms of many configurations, each traced with rays of its own.

        For datasets: every configuration gets independent rays (no common random numbers),
        all drawn from one generator seeded with ``seed``; slit kicks and slope errors are
        drawn as the rays in flight meet their element (:class:`LazyDraws`), and the trace
        compacts (``trace_rays(compact=True)``), so rays stopped upstream cost nothing more.
        A configuration's histograms are the same for the same batch, ``seed`` and
        ``max_batch``; they follow RAYX's in distribution (``sampling="fast"`` only).
        """
        o = self.options
        if o.sampling != "fast":
            raise InputError("trace_batch draws the fast stream (sampling='fast')")
        if n_rays < 1:
            raise InputError(f"n_rays must be positive, got {n_rays}")
        bl = self.compile(values, overrides)
        c = bl.n_configs
        g = _generator(seed, bl.device)
        step = max(1, o.max_batch // max(c, 1))
        hx = torch.zeros(c, self.hist.bins_x, dtype=torch.float64)
        hy = torch.zeros(c, self.hist.bins_y, dtype=torch.float64)
        n_hits = torch.zeros(c, dtype=torch.int64)
        with torch.no_grad():
            for a in range(0, n_rays, step):
                units = _batch_units(bl, min(n_rays, a + step) - a, g, lazy=True)
                beam = trace_rays(bl, source_rays(bl, units), units.draws, compact=True)
                bx, by = histograms(beam, self.hist)
                # histograms() divides by the chunk's rays: weigh the chunk back to counts
                hx += bx.cpu().double() * beam.n_rays
                hy += by.cpu().double() * beam.n_rays
                n_hits += beam.alive.sum(-1).cpu()
        return TraceBatch((hx / n_rays).numpy(), (hy / n_rays).numpy(), n_hits.numpy(), n_rays)

    def trace(self, request: TraceRequest, n_rays: int, keep_rays: bool = False) -> TraceResult:
        return self.trace_many([request], n_rays, keep_rays)[0]

    # -- differentiable products --------------------------------------------------
    def inputs(self, values, effects: Mapping[str, Mapping[str, float]] | None = None):
        """Leaf tensors for a Jacobian: parameters (C, 34) and one (C,) tensor per effect
        parameter (so that every configuration gets its own derivative), with names."""
        vals = torch.as_tensor(np.atleast_2d(self.table.validate(values)), dtype=torch.float64,
                               device=self.options.device)
        c = vals.shape[0]
        eff_leaves: dict[str, dict[str, torch.Tensor]] = {}
        names = list(self.table.names)
        from bluesky_offsets.physics import effects as fx
        for name, vals_e in (effects or {}).items():
            eff = fx.get(name)
            if eff.level != "twin":
                raise InputError(f"effect {name!r} acts on histograms, not in the twin: it has no twin Jacobian")
            full = eff.values(vals_e)
            eff_leaves[name] = {p: torch.full((c,), float(v), dtype=torch.float64, device=vals.device)
                                for p, v in full.items()}
            names += [f"{name}.{p}" for p in full]
        return vals, eff_leaves, names

    def _overrides(self, eff_leaves, extra=None):
        from bluesky_offsets.physics import effects as fx
        ov = fx.twin_overrides(eff_leaves) if eff_leaves else {}
        for obj, flds in (extra or {}).items():
            tgt = ov.setdefault(obj, {})
            for k, v in flds.items():
                tgt[k] = tgt[k] + v if (k in _MIS_KEYS and k in tgt) else v
        return ov

    def products(self, what: str, values, effects=None, *, n_rays: int, seed=0, overrides=None,
                 spec: HistogramSpec | None = None) -> torch.Tensor:
        """Soft beam products (C, m) at fixed rays: ``"features"`` (intensity, centroid x/y,
        rms width x/y), ``"histograms"`` (x then y, fraction of source rays) or
        ``"profiles"`` (the same at the camera's resolution)."""
        vals, leaves, _ = self.inputs(values, effects)
        return self._products(what, vals, leaves, n_rays, seed, overrides, spec)

    def _products(self, what, vals, leaves, n_rays, seed, extra, spec) -> torch.Tensor:
        bl = self.compile(vals, self._overrides(leaves, extra))
        edge, total = self.options.edge, None
        for _, beam in self._chunks(bl, n_rays, seed, edge):
            part = self._product(what, beam, spec, n_rays)
            total = part if total is None else total + part
        if what == "features":
            return features_from_moments(total, n_rays)
        return total

    def _product(self, what, beam, spec, n_rays: int):
        """One chunk's share of a product of ``n_rays`` per configuration: moments are sums over its
        rays; histograms fractions of all ``n_rays``."""
        if what == "features":
            return moments(beam, soft=self.options.edge > 0)
        if what in ("histograms", "profiles"):
            from bluesky_offsets.physics.traces import CAMERA
            sp = spec or (self.hist if what == "histograms" else CAMERA)
            hx, hy = histograms(beam, sp, soft=True, kernel=self.options.kernel, n_source=n_rays)
            return torch.cat([hx, hy], -1)
        raise InputError(f"unknown product {what!r}: features, histograms or profiles")

    def jacobian(self, what: str, values, effects=None, *, n_rays: int, seed=0, overrides=None,
                 spec: HistogramSpec | None = None, mode: Literal["auto", "forward", "reverse"] = "auto"):
        """Products (C, m) and their Jacobian (C, m, 34 + effect parameters), with the names
        of the columns, for a whole batch of configurations at fixed rays.

        ``mode``: "reverse" (the default) takes one batched backward pass per chunk of rays
        for all product components; "forward" one forward-mode pass per input column.
        """
        vals, leaves, names = self.inputs(values, effects)
        flat = [(None, vals)] + [((e, p), t) for e, d in leaves.items() for p, t in d.items()]
        n_in = vals.shape[1] + sum(len(d) for d in leaves.values())
        if mode == "auto":
            # measured (docs/benchmarks.md): eager forward-mode AD runs several of these ops
            # through Python decompositions and loses to one batched backward pass
            mode = "reverse"
        if mode == "forward":
            return self._jacobian_forward(what, vals, leaves, flat, n_in, n_rays, seed, overrides, spec, names)
        return self._jacobian_reverse(what, vals, leaves, flat, n_in, n_rays, seed, overrides, spec, names)

    def _jacobian_forward(self, what, vals, leaves, flat, n_in, n_rays, seed, extra, spec, names):
        import torch.autograd.forward_ad as fwd
        cols, out = [], None
        c = vals.shape[0]
        for j in range(n_in):
            with FORWARD_AD, fwd.dual_level():
                k = 0
                dual_vals, dual_leaves = None, {e: {} for e in leaves}
                for key, t in flat:
                    width = t.shape[1] if key is None else 1
                    tangent = torch.zeros_like(t)
                    if k <= j < k + width:
                        if key is None:
                            tangent[:, j - k] = 1.0
                        else:
                            tangent[:] = 1.0
                    dual = fwd.make_dual(t, tangent)
                    if key is None:
                        dual_vals = dual
                    else:
                        dual_leaves[key[0]][key[1]] = dual
                    k += width
                prod = self._products(what, dual_vals, dual_leaves, n_rays, seed, extra, spec)
                primal, tangent = fwd.unpack_dual(prod)
                out = primal.detach() if out is None else out
                cols.append(tangent.detach() if tangent is not None else torch.zeros_like(primal))
        return out, torch.stack(cols, -1).reshape(c, -1, n_in), names

    def _jacobian_reverse(self, what, vals, leaves, flat, n_in, n_rays, seed, extra, spec, names):
        leaves_req = {e: {p: t.clone().requires_grad_(True) for p, t in d.items()} for e, d in leaves.items()}
        vals_req = vals.clone().requires_grad_(True)
        inputs = [vals_req] + [t for d in leaves_req.values() for t in d.values()]
        bl = self.compile(vals_req, self._overrides(leaves_req, extra))
        edge = self.options.edge
        total, jac = None, None
        for _, beam in self._chunks(bl, n_rays, seed, edge):
            part = self._product(what, beam, spec, n_rays)  # (C, m): this chunk's share
            j_part = _batched_grad(part, inputs)
            total = part.detach() if total is None else total + part.detach()
            jac = j_part if jac is None else jac + j_part
        if what != "features":
            return total, jac, names
        s = total.clone().requires_grad_(True)
        feats = features_from_moments(s, n_rays)
        d_fs = torch.stack([torch.autograd.grad(feats[:, k].sum(), s, retain_graph=True)[0]
                            for k in range(feats.shape[1])], 1)  # (C, 5 features, 5 moments)
        return feats.detach(), torch.einsum("cfm,cmp->cfp", d_fs, jac), names


    # -- per-ray derivatives ---------------------------------------------------------
    # Over 100 lines with its docstring (a fifth of it), which the method's two passes need: the
    # compiled fields' derivatives in the inputs, then the rays chunk by chunk in those fields.
    def ray_jacobian(self, values, effects=None, *, n_rays: int, seed=0, overrides=None,
                     chunk: int = 1 << 16, columns=None, full: Beam | None = None) -> RayJacobian:
        """Every ray's screen position and soft weight with their derivatives in the inputs.

        The inputs are the 34 parameters and the twin-level effect parameters of ``effects``
        (as :meth:`jacobian`).  The beamline is compiled once per configuration and its
        derivatives in the inputs taken there (a small batched backward pass over the compiled
        fields); each ray is then traced as a configuration of its own, with its own copy of
        the compiled fields as leaves, so that three backward passes (x, y, weight) give every
        ray's derivative in every field, and the chain rule every ray's derivative in every
        input.  Any product of the rays (histograms at any binning, camera profiles, moments)
        gets its exact Jacobian from these at the cost of binning (:class:`RayJacobian`).
        Every ray is first traced without derivatives (its values, bit for bit :meth:`beam`'s);
        only the rays whose soft weight is above :data:`RAY_WEIGHT_FLOOR` are traced again for
        theirs (about a fifth of a bright configuration's rays: the rest end far outside a
        slit).  ``chunk`` bounds the rays × configurations traced at once (memory ~5 kB each).
        ``columns`` (indices into the inputs) keeps the derivatives in those inputs only: the
        fields they do not move are no leaves, so nothing upstream of the first field they
        move is traced with a graph (the beam optimizer moves E1 and E2 alone: 0.12 s instead of
        0.96 s at 20,000 rays).
        ``full``: the rays' values as :meth:`beam` traced them at these inputs, rays and seed with
        the soft edge (``edge=options.edge``), taken instead of tracing them again (a fit traces
        the values at a step before it asks for the Jacobian there).
        """
        o = self.options
        vals, leaves, names = self.inputs(values, effects)
        if full is not None and tuple(full.x.shape) != (vals.shape[0], n_rays):
            raise InputError(f"full: rays of shape {tuple(full.x.shape)}, not ({vals.shape[0]}, {n_rays})")
        c = vals.shape[0]
        vals_req = vals.clone().requires_grad_(True)
        leaves_req = {e: {p: t.clone().requires_grad_(True) for p, t in d.items()} for e, d in leaves.items()}
        inputs = [vals_req] + [t for d in leaves_req.values() for t in d.values()]
        bl = self.compile(vals_req, self._overrides(leaves_req, overrides))
        fields = _compiled_tensors(bl, c)
        # d field / d input per configuration: (C, F, P), one batched backward pass
        flat = torch.cat([t.reshape(c, -1) for t in fields], 1)
        dfield = _batched_grad(flat, inputs)
        if columns is not None:
            columns = [int(i) for i in np.asarray(columns).reshape(-1)]
            dfield, names = dfield[:, :, columns], [names[i] for i in columns]
        sizes = [t[0].numel() for t in fields]
        # only the fields the inputs move are leaves of the per-ray traces
        bounds = np.cumsum([0] + sizes)
        live = [i for i in range(len(fields)) if bool(dfield[:, bounds[i]:bounds[i + 1]].any())]
        dfield_live = torch.cat([dfield[:, bounds[i]:bounds[i + 1]] for i in live], 1)
        units = self._units(bl, n_rays, seed)
        step = max(1, int(chunk) // c)
        n_live = dfield_live.shape[1]
        parts = []
        for a in range(0, n_rays, step):
            b = min(n_rays, a + step)
            r = b - a
            cut = SourceUnits([t[..., a:b] for t in units.coord],
                              None if units.draws is None else units.draws.slice(a, b),
                              None if units.ctr is None else units.ctr[..., a:b])
            # every ray's values, without a graph (bit for bit the values of :meth:`beam`)
            if full is not None:
                values_k = full.slice(a, b)
            else:
                with torch.no_grad():
                    values_k = trace_rays(bl, source_rays(bl, cut), cut.draws, edge=o.edge)
            # derivatives only for the rays with weight: a ray's soft weight w bounds its
            # derivatives' share of every product (|dw| <= w * sum |du/dθ| over its apertures'
            # logistic arguments u; the position's enters multiplied by w), so below
            # RAY_WEIGHT_FLOOR they lie beneath the rounding of any sum and their rows are 0.
            # Most rays of a bright configuration end far outside a slit: this skips ~80 %.
            keep = torch.nonzero(values_k.weight.reshape(-1) > RAY_WEIGHT_FLOOR).squeeze(1)
            k_n, conf = int(keep.numel()), keep // r
            grads = [torch.zeros(0, len(names), dtype=dfield_live.dtype, device=dfield_live.device)] * 3
            if k_n:
                sub = [t.detach()[conf] for t in fields]
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
                rays_k = cut.take(conf, keep % r)
                per_config = torch.bincount(conf, minlength=c).tolist()
                with torch.enable_grad():
                    bl_k = _replace_tensors(bl, c, iter(sub), k_n)
                    beam = trace_rays(bl_k, source_rays(bl_k, rays_k), rays_k.draws, edge=o.edge)
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
            # the kept rays as (configuration, ray) of the whole trace, configuration-major
            rows = conf * n_rays + a + keep % r
            parts.append((values_k.x.reshape(c, r), values_k.y.reshape(c, r), values_k.alive.reshape(c, r),
                          values_k.weight.reshape(c, r), rows, *grads))
        if len(parts) == 1:
            x, y, alive, weight, rows, jx, jy, jw = parts[0]
        else:
            x, y, alive, weight = (torch.cat([p[k] for p in parts], 1) for k in range(4))
            order = torch.argsort(torch.cat([p[4] for p in parts]))  # configuration-major again
            rows, jx, jy, jw = (torch.cat([p[k] for p in parts])[order] for k in range(4, 8))
        return RayJacobian(x, y, alive, weight, rows, jx, jy, jw, n_rays=n_rays, names=names)


def device_agreement(device: str = "cuda", *, n_rays: int = 20_000, seed: int = 3) -> dict:
    """The same four configurations near the reference traced with RAYX's random stream on the
    CPU and on ``device``: whether the same rays survive and how far their screen positions
    differ (mm).  The check a lent GPU runs before it traces anything for the record."""
    values = METRIXS.reference + 0.005 * METRIXS.span * np.random.default_rng(8).uniform(-1, 1, (4, len(METRIXS)))
    values[:, [METRIXS.index("E1.rotationZerror"), METRIXS.index("E2.rotationZerror")]] = 0.0
    with torch.no_grad():
        a, b = (TorchEngine(options={"device": d, "sampling": "rayx"}).beam(values, n_rays=n_rays, seed=seed)
                for d in ("cpu", device))
    both = a.alive
    return {"device": str(device), "same_survivors": bool(torch.equal(a.alive, b.alive.cpu())),
            "survivors": int(both.sum()), "max_dx_mm": float((a.x - b.x.cpu())[both].abs().max()),
            "max_dy_mm": float((a.y - b.y.cpu())[both].abs().max())}


def _take_optic(opt: Optic, c: int, owner: torch.Tensor) -> Optic:
    """``opt`` with its configuration fields (leading axis ``c``) taken for each of the rays
    ``owner`` (K,): every ray a configuration of its own (a compacting trace)."""
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
    """The floating-point tensors of a compiled beamline with a configuration axis, in the
    order :func:`_replace_tensors` visits them (each broadcast to a leading axis of ``c``)."""
    out: list[torch.Tensor] = []
    _replace_tensors(bl, c, None, c, out)
    return out


def _replace_tensors(bl: CompiledBeamline, c: int, new, c_new: int, found: list | None = None) -> CompiledBeamline:
    """A copy of ``bl`` with its floating tensors (leading axis ``c``, or 1) taken from the
    iterator ``new`` (leading axis ``c_new``) in a fixed order; with ``found``, collect them."""
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


@dataclass
class RayJacobian:
    """Rays at the screen (C, N) with their derivatives in the P inputs ``names``.

    Values are RAYX's (hard survival ``alive``); the derivatives are those of the soft beam
    (weights that fall off over ``edge`` of each aperture), the smooth version of the same
    rays whose expectation the hard beam's counts follow.  Only the rays whose soft weight is
    above :data:`RAY_WEIGHT_FLOOR` have derivatives: ``rows`` (K,) are their flat indices
    (configuration-major) and ``rows_jx``, ``rows_jy``, ``rows_jw`` (K, P) their derivatives;
    every other ray's are 0 to rounding (:attr:`jx` etc. give them all, (C, N, P))."""

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
        return self._dense(self.rows_jx)

    @property
    def jy(self) -> torch.Tensor:
        return self._dense(self.rows_jy)

    @property
    def jw(self) -> torch.Tensor:
        return self._dense(self.rows_jw)

    def histograms(self, spec: HistogramSpec, kernel: float = 1.0,
                   soft: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """x then y histograms (C, bins_x + bins_y) as fractions of source rays and their
        Jacobian (C, bins_x + bins_y, P) from the soft beam binned with a Gaussian kernel of
        ``kernel`` bins rms.  The values are RAYX's (hard counts, RAYX's binning), or with
        ``soft`` the soft beam's, whose derivative the Jacobian is (a smooth objective)."""
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
    """d/dθ of Σ_i w_i K_b(v_i) for Gaussian-kernel bins K_b: Σ_i (K_b jw_i + w_i K_b' jv_i),
    over the rays i of configuration ``conf[i]`` (of ``c``) with derivatives, each (K,)."""
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
    """d part[c, k] / d inputs[c, ...] for every k in one batched backward pass (the
    configurations are independent, so summing over them separates nothing), as (C, m, n_in)."""
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
