"""Reading and writing RAY-UI's RML beamline files.

An :class:`RmlBeamline` is an ordered list of :class:`RmlObject` (source,
elements, image plane), each an ordered list of ``<param>`` entries.  The
world position and orientation of every object are *computed* from the
element chain (:mod:`bluesky_offsets.physics.geometry`) when the file is written:
whatever world vectors an input file held are replaced.  That is what makes
misalignments real for RAYX, which reads the world vectors only.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.geometry import (MISALIGNMENT_KEYS, ChainLink, Frame, Misalignment, chain_frames,
                       ellipsoid_tangent_angle)

WORLD_KEYS = ("worldPosition", "worldXdirection", "worldYdirection", "worldZdirection")
MIRROR_TYPES = {"Plane Mirror", "Cylinder", "Ellipsoid", "Toroid", "Sphere", "Cone", "Paraboloid",
                "Experts Optics", "Cubic"}
GRATING_TYPES = {"Plane Grating", "Spherical Grating", "Toroidal Grating"}
FLAT_TYPES = {"Slit", "ImagePlane", "Foil"}
SOURCE_TYPES = {"Dipole", "Dipole Source", "Simple Undulator"}
"""Source types whose name does not say "Source" (RAY-UI's dipole, RAYX's undulator); any "... Source" is one too."""


def is_source_type(type_: str) -> bool:
    """Whether an RML object type is a source (any "... Source", or one of :data:`SOURCE_TYPES`)."""
    return "Source" in type_ or type_ in SOURCE_TYPES


class RmlError(InputError):
    """An RML file or object that cannot be understood."""


@dataclass
class RmlParam:
    """One ``<param>`` of an RML object: its id, its text and its other XML attributes (``comment``, ...)."""

    id: str
    value: str
    attrs: dict[str, str] = field(default_factory=dict)


@dataclass
class RmlObject:
    """One ``<object>`` of an RML beamline."""

    name: str
    type: str
    params: dict[str, RmlParam] = field(default_factory=dict)

    # -- parameter access ---------------------------------------------------
    def has(self, pid: str) -> bool:
        """Whether the object has parameter ``pid``."""
        return pid in self.params

    def get(self, pid: str) -> str:
        """Parameter ``pid``'s text (an :class:`RmlError` where the object has none)."""
        try:
            return self.params[pid].value
        except KeyError:
            raise RmlError(f"{self.name!r} ({self.type}) has no parameter {pid!r}") from None

    def get_float(self, pid: str, default: float | None = None) -> float:
        """Parameter ``pid`` as a number; ``default`` where the object has none and a default is given."""
        if pid not in self.params and default is not None:
            return default
        try:
            return float(self.get(pid))
        except ValueError:
            raise RmlError(f"{self.name!r}: parameter {pid!r} = {self.get(pid)!r} is not a number") from None

    def comment(self, pid: str) -> str:
        """Parameter ``pid``'s ``comment`` attribute ("" where it has none)."""
        return self.params[pid].attrs.get("comment", "") if pid in self.params else ""

    def set(self, pid: str, value, comment: str | None = None) -> None:
        """Set (or add) a scalar parameter, keeping its attributes."""
        if isinstance(value, (bool, np.bool_)):
            raise RmlError(f"{self.name!r}: parameter {pid!r} takes a number, not a bool")
        if isinstance(value, (int, np.integer)):
            text = str(int(value))
        elif isinstance(value, (float, np.floating)):
            text = _fmt(value)
        else:
            text = str(value)
        if pid in self.params:
            self.params[pid].value = text
            if comment is not None:
                self.params[pid].attrs["comment"] = comment
        else:
            attrs = {} if comment is None else {"comment": comment}
            attrs["enabled"] = "T"
            self.params[pid] = RmlParam(pid, text, attrs)

    # -- geometry -----------------------------------------------------------
    @property
    def is_source(self) -> bool:
        """Whether the object is a source (:func:`is_source_type`)."""
        return is_source_type(self.type)

    @property
    def misalignment(self) -> Misalignment:
        """The object's alignment errors (zero when RAY-UI's switch says "No")."""
        if self.has("alignmentError") and self.comment("alignmentError") not in ("Yes", ""):
            return Misalignment()
        return Misalignment.from_rml({k: self.get_float(k) for k in MISALIGNMENT_KEYS if self.has(k)})

    def set_misalignment(self, **values: float) -> None:
        """Set alignment errors by RML key (``translationXerror=...``) and switch them on."""
        for key, value in values.items():
            if key not in MISALIGNMENT_KEYS:
                raise RmlError(f"{key!r} is not an alignment error ({', '.join(MISALIGNMENT_KEYS)})")
            if self.is_source and key in ("translationZerror", "rotationZerror"):
                raise RmlError(f"source {self.name!r} has no {key}")
            self.set(key, float(value))
        self.set("alignmentError", 0, comment="Yes")

    def chain_link(self) -> ChainLink:
        """How this object sits in the element chain."""
        return chain_link(self.type, self.get_float, self.comment, self.misalignment, self.name)


def chain_link(type_: str, get: Callable, comment: Callable, mis: Misalignment, name: str = "") -> ChainLink:
    """How an object of ``type_`` sits in the element chain.

    ``get(field[, default])`` returns a field's value, ``comment(field)`` its switch text: the
    RML objects give numbers, the differentiable twin tensors (the ellipsoid's misalignment
    frame then follows its half-axes with gradients).
    """
    deg = math.radians
    if is_source_type(type_):
        return ChainLink(misalignment=mis, is_source=True)
    if type_ == "ImagePlane":
        return ChainLink(distance=get("distanceImagePlane"), misalignment=mis)
    distance = get("distancePreceding")
    azimuth = deg(get("azimuthalAngle", 0.0))
    if type_ in FLAT_TYPES:
        return ChainLink(distance, azimuth, 0.0, 0.0, mis)
    if type_ in GRATING_TYPES:
        alpha, beta = get("alpha"), get("beta")
        return ChainLink(distance, azimuth, deg(90.0 - alpha), deg(90.0 + beta), mis)
    if type_ in MIRROR_TYPES:
        theta = deg(get("grazingIncAngle"))
        tau = 0.0
        if type_ == "Ellipsoid" and comment("misalignmentCoordinateSystem") == "Ellipsoid":
            tau = ellipsoid_tangent_angle(
                get("longHalfAxisA"), get("shortHalfAxisB"),
                deg(get("designGrazingIncAngle", get("grazingIncAngle"))),
                get("entranceArmLength"), get("exitArmLength"))
        return ChainLink(distance, azimuth, theta, theta, mis, tau)
    raise RmlError(f"object {name!r}: element type {type_!r} is not supported")


@dataclass
class RmlBeamline:
    """An RML beamline: its objects in beam order (the source first) and the RML version."""

    objects: list[RmlObject]
    version: str = "1.15"

    def __getitem__(self, name: str) -> RmlObject:
        for obj in self.objects:
            if obj.name == name:
                return obj
        raise RmlError(f"no object named {name!r}; objects: {[o.name for o in self.objects]}")

    def copy(self) -> RmlBeamline:
        """An independent copy: new objects and parameters, to set without touching this one."""
        # explicit copy: ~5x faster than deepcopy, which matters for low-ray pre-screens
        return RmlBeamline([RmlObject(o.name, o.type, {k: RmlParam(p.id, p.value, dict(p.attrs))
                                                         for k, p in o.params.items()})
                            for o in self.objects], self.version)

    @property
    def sources(self) -> list[RmlObject]:
        """The source objects."""
        return [o for o in self.objects if o.is_source]

    @property
    def source_label(self) -> str:
        """The source as messages name it: ``source 'SU' (Simple Undulator)``."""
        src = self.sources[0]
        return f"source {src.name!r} ({src.type})"

    @property
    def elements(self) -> list[RmlObject]:
        """The objects that are not sources, in beam order."""
        return [o for o in self.objects if not o.is_source]

    def frames(self) -> list[Frame]:
        """World frames of all objects, misalignments applied."""
        if len(self.sources) != 1 or not self.objects[0].is_source:
            raise RmlError("expected exactly one source, first in the beamline")
        return chain_frames([o.chain_link() for o in self.objects])

    def to_xml(self) -> str:
        """The beamline as RML text, with world vectors recomputed from the chain (misalignments applied)."""
        frames = self.frames()
        lab = ET.Element("lab")
        ET.SubElement(lab, "version").text = self.version
        bl = ET.SubElement(lab, "beamline")
        for obj, frame in zip(self.objects, frames):
            node = ET.SubElement(bl, "object", {"name": obj.name, "type": obj.type})
            if obj.is_source:
                frame = rayx_source_frame(frame)
            world = dict(zip(WORLD_KEYS, (frame.position, frame.x, frame.y, frame.z)))
            written_world = False
            for p in obj.params.values():
                if p.id in WORLD_KEYS:
                    continue
                ET.SubElement(node, "param", {"id": p.id, **p.attrs}).text = p.value
                if p.id == "rotationZerror" or (obj.is_source and p.id == "rotationYerror"):
                    _write_world(node, world)
                    written_world = True
            if not written_world:
                _write_world(node, world)
        ET.indent(lab, space=" ")
        return "<?xml version='1.0' encoding='UTF-8'?>\n" + ET.tostring(lab, encoding="unicode") + "\n"

    def write(self, path: str | Path) -> Path:
        """Write :meth:`to_xml` to ``path``; return the path."""
        path = Path(path)
        path.write_text(self.to_xml())
        return path


def rayx_source_frame(frame: Frame) -> Frame:
    """The world vectors that make RAYX emit from ``frame``.

    RAYX moves a source's rays to the world with the source's *world-to-local* matrix
    (RAYX-CONVENTIONS.md §2.3): written as it is, a source shifted +0.5 mm in x would emit
    from -0.5 mm.  Writing the inverse frame, position ``-Oᵀp`` and axes the columns of
    ``Oᵀ``, makes RAYX's inversion undo itself: the beam leaves from ``p`` along ``O``.
    """
    o = np.asarray(frame.orientation, dtype=float)
    return Frame(-(o.T @ np.asarray(frame.position, dtype=float)), o.T.copy())


def _fmt(v) -> str:
    return repr(float(v))


def _write_world(node: ET.Element, world: Mapping[str, np.ndarray]) -> None:
    for key, vec in world.items():
        p = ET.SubElement(node, "param", {"id": key, "enabled": "F"})
        for axis, comp in zip("xyz", vec):
            ET.SubElement(p, axis).text = _fmt(comp + 0.0)


def read_rml(path: str | Path) -> RmlBeamline:
    """Parse an RML file into an :class:`RmlBeamline`.

    World vectors are kept as read in :func:`read_world_vectors`, but recomputed on write.
    """
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise RmlError(f"cannot read RML {path}: {exc}") from None
    return _from_root(root)


def _attr(node: ET.Element, key: str) -> str:
    """An attribute every RML file has (an object's name and type, a parameter's id)."""
    value = node.get(key)
    if value is None:
        raise RmlError(f"RML <{node.tag}> without {key!r}")
    return value


def _beamline(root: ET.Element) -> ET.Element:
    bl = root.find("beamline")
    if bl is None:
        raise RmlError("RML has no <beamline>")
    return bl


def _from_root(root: ET.Element) -> RmlBeamline:
    version = (root.findtext("version") or "1.15").strip()
    objects = []
    for node in _beamline(root).iter("object"):
        params: dict[str, RmlParam] = {}
        for p in node.findall("param"):
            pid = _attr(p, "id")
            attrs = {k: v for k, v in p.attrib.items() if k != "id"}
            params[pid] = RmlParam(pid, (p.text or "").strip(), attrs)
        objects.append(RmlObject(_attr(node, "name"), _attr(node, "type"), params))
    if not objects:
        raise RmlError("RML beamline has no objects")
    return RmlBeamline(objects, version)


def read_world_vectors(path: str | Path) -> dict[str, dict[str, np.ndarray]]:
    """World vectors exactly as stored in an RML file, per object name."""
    root = ET.parse(path).getroot()
    out: dict[str, dict[str, np.ndarray]] = {}
    for node in _beamline(root).iter("object"):
        vecs = {}
        for p in node.findall("param"):
            pid = p.get("id")
            if pid in WORLD_KEYS:
                vecs[pid] = np.array([float(p.findtext(a, "")) for a in "xyz"])
        out[_attr(node, "name")] = vecs
    return out


FRAME_TOLERANCE = (1e-3, 1e-6)
"""How far (mm, and in a direction's components) a chained world frame may lie from the RML's own."""
IN_PLANE_SHARE = 0.1
"""How far a plane mirror's RML centre may lie within its own surface from the chain's, as a share of
its length (along the beam) and width: RAYX traces the same plane, its edges barely moved."""


def _in_own_plane(obj: RmlObject, frame: Frame, position: np.ndarray) -> bool:
    """Whether ``position`` lies in the plane mirror ``obj``'s surface at ``frame``, near its centre there.

    RAY-UI puts an SX700 premirror's centre off the point where the central ray meets it (HB 1200's
    by 21 mm along the mirror); the chain puts it at that point, on the same plane.
    """
    if obj.type != "Plane Mirror":
        return False
    d = position - frame.position
    return (abs(float(d @ frame.y)) <= FRAME_TOLERANCE[0]
            and abs(float(d @ frame.z)) <= IN_PLANE_SHARE * obj.get_float("totalLength", 0.0)
            and abs(float(d @ frame.x)) <= IN_PLANE_SHARE * obj.get_float("totalWidth", 0.0))


def check_frames(bl: RmlBeamline, path: str | Path) -> None:
    """Refuse the RML ``bl`` (read from ``path``) where the element chain does not reproduce its world frames.

    RAYX places each element by the world vectors the RML stores; every edit of an element
    (a parameter set, a misalignment) writes them anew from the chain (:meth:`RmlBeamline.to_xml`).
    An element type whose placement the chain does not know (a paraboloid's) or cannot chain at all
    (a crystal) would be traced somewhere else than the RML says.  A plane mirror whose centre the
    RML puts elsewhere on the same plane (:func:`_in_own_plane`) is traced at the chain's point, its
    misalignments' pivot there.  Objects without stored world vectors are not compared; the message
    names the object.
    """
    stored = read_world_vectors(path)
    for obj, frame in zip(bl.objects, bl.frames()):
        ref = stored.get(obj.name, {})
        if obj.is_source or len(ref) < len(WORLD_KEYS):
            continue
        moved = 0.0 if _in_own_plane(obj, frame, ref["worldPosition"]) else float(
            np.abs(frame.position - ref["worldPosition"]).max())
        off = [("position", moved, FRAME_TOLERANCE[0])]
        off += [(key, float(np.abs(vec - ref[key]).max()), FRAME_TOLERANCE[1])
                for key, vec in zip(WORLD_KEYS[1:], (frame.x, frame.y, frame.z))]
        for what, d, tol in off:
            if d > tol:
                raise RmlError(f"object {obj.name!r} ({obj.type}): the element chain places it elsewhere than the "
                               f"RML's world vectors (its {what} {d:.3g} off): it cannot be traced as the RML says")


def make_object(name: str, type_: str, params: Iterable[tuple]) -> RmlObject:
    """Build an object from ``(id, value)`` or ``(id, value, comment)`` tuples."""
    obj = RmlObject(name, type_)
    for entry in params:
        pid, value, *rest = entry
        obj.set(pid, value, comment=rest[0] if rest else None)
    return obj
