"""A beamline description: the RML, what moves, what is fixed but unknown, the detector, the effects.

One TOML file describes a beamline to bluesky-offsets (``data/beamlines/metrixs.toml`` is
METRIXS's)::

    [beamline]
    name = "energize"
    rml = "Energize_EN_500.rml"        # relative to this file; or builtin = "metrixs"
    effects = ["chamber_z", "detector_blur"]

    [detector]
    image_plane = "ImagePlane"         # the RML object the focus chamber's screen is
    histogram_bins = [50, 50]
    histogram_x = [-10.0, 10.0]        # mm
    histogram_y = [-3.0, 3.0]
    camera_pixels = [1000, 1200]       # the camera's pixels over the same window

    [[parameter]]                      # one per parameter, in table order
    name = "M1.rotationXerror"
    element = "Toroid"                 # the RML object
    field = "rotationXerror"           # a misalignment, or a property the object has (radius, openingWidth …)
    unit = "mrad"
    range = [-0.5, 0.5]                # the surrogate's sampling box
    reference = 0.0
    motor = "m1.rx"                    # its motor's device path (or fixed = "m1.radius": fixed but unknown)
    travel = [-1.0, 1.0]               # optional: the motor's travel where wider than the box
    description = "M1 pitch"

:func:`load_beamline` reads and checks it — unknown keys, elements the RML lacks, fields an
element has not, effects the library does not know, an RML RAYX cannot import, each refused in one
line naming the entry.
"""

from __future__ import annotations

import functools
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.geometry import MISALIGNMENT_KEYS
from bluesky_offsets.physics.parameters import BEAMLINES, ParameterError, ParameterTable, parameter_from_record
from bluesky_offsets.physics.screen import on_image_plane
from bluesky_offsets.physics.rayx_calls import grid_draw, grid_rays, source_varies
from bluesky_offsets.physics.twin import HistogramSpec, RayxEngine, TraceRequest

BUILTIN = ("metrixs",)
"""Beamlines whose geometry is the package's own code (``physics.metrixs``) rather than an RML file."""


class BeamlineError(InputError):
    """A beamline description that cannot be used; the message names the file and the entry."""


@dataclass(frozen=True, kw_only=True)
class Detector:
    """The focus chamber: the image plane it is, the histograms the fits use, the camera's pixels."""

    image_plane: str = "ImagePlane"
    histogram_bins: tuple[int, int] = (50, 50)
    histogram_x: tuple[float, float] = (-10.0, 10.0)
    histogram_y: tuple[float, float] = (-3.0, 3.0)
    camera_pixels: tuple[int, int] = (1000, 1200)

    @property
    def histograms(self) -> HistogramSpec:
        """The binning the fits use: ``histogram_bins`` over the ``histogram_x``, ``histogram_y`` window."""
        return HistogramSpec(self.histogram_bins[0], self.histogram_x, self.histogram_bins[1], self.histogram_y)

    @property
    def camera(self) -> HistogramSpec:
        """The camera's own binning: one bin per pixel (``camera_pixels``) over the same window."""
        return HistogramSpec(self.camera_pixels[0], self.histogram_x, self.camera_pixels[1], self.histogram_y)


@dataclass(frozen=True, kw_only=True)
class Beamline:
    """A described beamline: its name, RML, parameter table, detector, effects and description file.

    Its RML, or the built-in geometry it names instead; the effects that apply; ``path``, the file
    it came from.
    """

    name: str
    table: ParameterTable
    detector: Detector
    effects: tuple[str, ...]
    rml: Path | None = None
    builtin: str | None = None
    path: Path | None = None

    def engine(self, kind: str = "rayx"):
        """RAYX tracing this beamline, or the differentiable torch engine (``kind="torch"``).

        RAYX is the reference twin: ``Twin(beamline.engine())``.
        """
        if kind not in ("rayx", "torch"):
            raise BeamlineError(f"engine kind {kind!r}; known: rayx, torch")
        if self.builtin == "metrixs":
            if kind == "torch":
                from bluesky_offsets.physics.engine import TorchEngine
                return TorchEngine(self.table, self.detector.histograms)
            return RayxEngine(self.table, self.detector.histograms)
        if kind == "rayx":
            return RmlEngine(self)
        from bluesky_offsets.physics.engine import RmlTorchEngine
        return RmlTorchEngine(self)

    @property
    def source_varies(self) -> bool:
        """Whether RAYX's source draws other rays for another seed: a matrix source's grid does not.

        Where it does not, both twins draw each trace's photons from the grid (:meth:`RmlEngine.trace`).
        """
        if self.builtin == "metrixs":
            return True
        return _source_varies(self.rml_file())

    def rml_objects(self) -> dict[str, str]:
        """Object name -> RML type, from the RML file or the built-in geometry."""
        if self.builtin == "metrixs":
            from bluesky_offsets.physics.metrixs import nominal_beamline
            return {o.name: o.type for o in nominal_beamline().objects}
        from bluesky_offsets.physics.rml import read_rml
        return {o.name: o.type for o in read_rml(self.rml_file()).objects}

    def rml_file(self) -> Path:
        """The RML file of a beamline that is not built in."""
        if self.rml is None:
            raise BeamlineError(f"beamline {self.name}: neither an RML file nor a built-in geometry")
        return self.rml


@functools.cache
def _source_varies(rml: Path) -> bool:
    from bluesky_offsets.physics.rml import read_rml
    return source_varies(read_rml(rml))


def _keys(section: dict, allowed, where: str) -> None:
    if not isinstance(section, dict):
        raise BeamlineError(f"{where}: expected a table, got {type(section).__name__}")
    unknown = sorted(set(section) - set(allowed))
    if unknown:
        raise BeamlineError(f"{where}: unknown keys {unknown}; known: {sorted(allowed)}")


def _detector(section: dict, where: str) -> Detector:
    _keys(section, [f.name for f in fields(Detector)], where)
    out: dict[str, Any] = {}
    for f in fields(Detector):
        if f.name not in section:
            continue
        v = section[f.name]
        if f.name == "image_plane":
            if not isinstance(v, str):
                raise BeamlineError(f"{where}: image_plane must be an object name")
            out[f.name] = v
            continue
        ints = f.name.endswith(("bins", "pixels"))
        ok = isinstance(v, list) and len(v) == 2 and all(
            isinstance(x, int) and x > 0 if ints else isinstance(x, (int, float)) for x in v)
        if not ok or (not ints and not v[0] < v[1]):
            raise BeamlineError(f"{where}: {f.name} must be {'two positive integers' if ints else '[low, high]'}, "
                                f"got {v!r}")
        out[f.name] = tuple(int(x) if ints else float(x) for x in v)
    return Detector(**out)


def load_beamline(path) -> Beamline:
    """The :class:`Beamline` of a description file (TOML), checked against its RML and the effects library.

    A :class:`BeamlineError` in one line for anything it cannot use.
    """
    from bluesky_offsets.physics import effects as E
    path = Path(path)
    try:
        with path.open("rb") as f:
            doc = tomllib.load(f)
    except OSError as exc:
        raise BeamlineError(f"beamline {path}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise BeamlineError(f"beamline {path}: not TOML ({exc})") from None
    _keys(doc, ("beamline", "detector", "parameter"), f"beamline {path}")
    head = doc.get("beamline", {})
    _keys(head, ("name", "rml", "builtin", "effects"), f"beamline {path} [beamline]")
    if ("rml" in head) == ("builtin" in head):
        raise BeamlineError(f"beamline {path} [beamline]: give exactly one of rml (a file) or builtin "
                            f"({', '.join(BUILTIN)})")
    if "builtin" in head and head["builtin"] not in BUILTIN:
        raise BeamlineError(f"beamline {path}: builtin {head['builtin']!r}; known: {list(BUILTIN)}")
    rml = (path.parent / head["rml"]).resolve() if "rml" in head else None
    if rml is not None and not rml.is_file():
        raise BeamlineError(f"beamline {path}: RML {rml} not found")
    effects = tuple(head.get("effects", ()))
    unknown = [e for e in effects if e not in E.EFFECTS]
    if unknown:
        raise BeamlineError(f"beamline {path}: unknown effects {unknown}; known: {sorted(E.EFFECTS)}")
    records = doc.get("parameter")
    if not isinstance(records, list) or not records:
        raise BeamlineError(f"beamline {path}: no [[parameter]] entries")
    try:
        table = ParameterTable([parameter_from_record(r, f"{path.name} parameter") for r in records],
                               name=str(head.get("name", path.stem)), source=path.resolve())
    except ParameterError as exc:
        raise BeamlineError(f"beamline {path}: {exc}") from None
    bl = Beamline(name=table.name, table=table, detector=_detector(doc.get("detector", {}),
                                                                   f"beamline {path} [detector]"),
                  effects=effects, rml=rml, builtin=head.get("builtin"), path=path)
    _check_against_rml(bl, path)
    return bl


def _check_against_rml(bl: Beamline, path: Path) -> None:
    """Check that the parameters and the detector name what the RML has.

    Every parameter's element is an object of the RML and its field a misalignment or one of the
    object's own parameters; the detector's image plane is an ImagePlane; the element chain
    places every object where the RML does (:func:`~bluesky_offsets.physics.rml.check_frames`);
    RAYX imports the RML.
    """
    from bluesky_offsets.physics.metrixs import nominal_beamline
    from bluesky_offsets.physics.rayx_calls import check_importable
    from bluesky_offsets.physics.rml import check_frames, read_rml
    rml = nominal_beamline() if bl.builtin == "metrixs" else read_rml(bl.rml_file())
    objects = {o.name: o for o in rml.objects}
    for p in bl.table:
        if p.element not in objects:
            raise BeamlineError(f"beamline {path}: parameter {p.name!r}: the RML has no object {p.element!r}; "
                                f"objects: {list(objects)}")
        if p.field not in MISALIGNMENT_KEYS and not objects[p.element].has(p.field):
            raise BeamlineError(f"beamline {path}: parameter {p.name!r}: {p.element!r} "
                                f"({objects[p.element].type}) has no field {p.field!r}")
    ip = objects.get(bl.detector.image_plane)
    if ip is None or ip.type != "ImagePlane":
        raise BeamlineError(f"beamline {path}: detector image_plane {bl.detector.image_plane!r} is not an "
                            f"ImagePlane of the RML")
    if bl.builtin is None:
        try:
            check_frames(rml, bl.rml_file())
            check_importable(bl.rml_file())
        except InputError as exc:
            raise BeamlineError(f"beamline {path}: {exc}") from None


@functools.lru_cache(maxsize=8)
def _described(path: Path) -> Beamline:
    return load_beamline(path)


def of_table(table: ParameterTable) -> Beamline | None:
    """The described beamline ``table`` was read from (``None``: a table built in code)."""
    return None if getattr(table, "source", None) is None else _described(Path(table.source))


def torch_engine(table: ParameterTable, hist: HistogramSpec | None = None, options=None):
    """The differentiable twin of the beamline ``table`` describes, binned by ``hist``.

    METRIXS's built-in geometry (or a table with no description) or the described RML's.
    """
    bl = of_table(table)
    if bl is None or bl.builtin == "metrixs":
        from bluesky_offsets.physics.engine import TorchEngine
        return TorchEngine(table=table, hist=hist, options=options)
    from bluesky_offsets.physics.engine import RmlTorchEngine
    return RmlTorchEngine(bl, hist, options)


def rayx_engine(table: ParameterTable, hist: HistogramSpec | None = None):
    """RAYX on the beamline ``table`` describes (the reference twin), binned by ``hist``."""
    bl = of_table(table)
    if bl is None or bl.builtin == "metrixs":
        return RayxEngine(table, hist)
    return RmlEngine(bl, hist)


def local_overrides(beamline: Beamline, overrides):
    """``overrides`` with the screen renamed to the description's image plane (:func:`screen.on_image_plane`)."""
    return on_image_plane(overrides, beamline.detector.image_plane)


def resolve(spec: str | Path) -> Beamline:
    """A beamline from what a user types: a description file (``*.toml``) or a shipped name.

    A shipped name is read once per process, as :func:`of_table` reads it.
    """
    spec = str(spec)
    return _described(Path(spec if spec.endswith(".toml") or Path(spec).is_file() else shipped(spec)).resolve())


def shipped(name: str) -> Path:
    """The description shipped with the package for ``name`` (``"metrixs"``, ``"energize"``)."""
    p = BEAMLINES / f"{name}.toml"
    if not p.is_file():
        raise BeamlineError(f"no shipped beamline {name!r}; shipped: "
                            f"{sorted(q.stem for q in BEAMLINES.glob('*.toml'))}")
    return p


class RmlEngine(RayxEngine):
    """RAYX on a described beamline's RML.

    Each parameter sets its element's field (a misalignment switches the element's alignment
    errors on), ``overrides`` set any other field, the world frames are recomputed from the
    element chain (``physics.rml``), the source emits ``n_rays``.
    """

    def __init__(self, beamline: Beamline, hist: HistogramSpec | None = None):
        from bluesky_offsets.physics.rml import read_rml
        super().__init__(beamline.table, hist or beamline.detector.histograms)
        self.beamline = beamline
        self.rml = read_rml(beamline.rml_file())
        self.source_label = self.rml.source_label

    def hits(self, request: TraceRequest, n_rays: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """RAYX's hits; from a grid source (:attr:`Beamline.source_varies`), ``n_rays`` photons drawn from its grid.

        A grid source emits the same rays for every seed, so a trace of it would carry no counting
        noise: RAYX traces the grid (:func:`~.rayx_calls.grid_rays`) and each photon is one of its
        rays (:func:`~.rayx_calls.grid_draw`), as the torch engine draws them.
        """
        if self.beamline.source_varies:
            return super().hits(request, n_rays)
        grid = grid_rays(self.rml)
        values, x, y, pid = super().hits(request, grid)
        counts = np.bincount(grid_draw(grid, n_rays, request.seed), minlength=grid)[pid]
        return values, np.repeat(x, counts), np.repeat(y, counts), np.repeat(pid, counts)

    def build(self, request: TraceRequest, n_rays: int):
        """A copy of the RML set to ``request`` (parameters, then overrides) with ``n_rays`` source rays."""
        from bluesky_offsets.physics.metrixs import check_physical
        values = self.table.validate(request.values)
        check_physical(values, self.table)
        bl = self.rml.copy()
        for p, v in zip(self.table, values):
            if p.field in MISALIGNMENT_KEYS:
                bl[p.element].set_misalignment(**{p.field: float(v)})
            else:
                bl[p.element].set(p.field, float(v))
        for element, fields_ in (local_overrides(self.beamline, request.overrides) or {}).items():
            for key, v in fields_.items():
                if key in MISALIGNMENT_KEYS:
                    bl[element].set_misalignment(**{key: float(v)})
                else:
                    bl[element].set(key, v)
        bl.sources[0].set("numberRays", int(n_rays))
        return bl

