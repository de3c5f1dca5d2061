"""World frames of a beamline element chain, with RAY-UI misalignments.

RAYX reads only each element's world position and orientation from the RML;
it ignores the ``alignmentError`` block.  RAY-UI used to bake the
misalignment into those world vectors, so this module does the same:

* the nominal chain: every element sits ``distance`` downstream of the
  previous one along the outgoing central ray, turned by its azimuth and its
  incidence/exit angles;
* the misalignment: translations (mm) and rotations (mrad) in the element's
  own frame, ``O_w = O · Rz(rz) · Ry(ry) · Rx(rx)`` and ``p_w = p + O_w · t``
  (checked against RAY-UI-written world vectors), optionally in a frame tilted
  about x by ``tau`` (RAY-UI's "Ellipsoid" misalignment coordinate system);
* a misaligned element does not move the elements after it.

Orientation matrices have the element's x, y, z axes as columns
(``worldXdirection``, ``worldYdirection``, ``worldZdirection`` in the RML).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

MISALIGNMENT_KEYS = ("translationXerror", "translationYerror", "translationZerror",
                     "rotationXerror", "rotationYerror", "rotationZerror")


def rot_x(a: float) -> np.ndarray:
    """Right-handed active rotation by ``a`` rad about x."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Misalignment:
    """Translations in mm and rotations in mrad, in the element frame."""

    tx: float = 0.0
    ty: float = 0.0
    tz: float = 0.0
    rx: float = 0.0
    ry: float = 0.0
    rz: float = 0.0

    @classmethod
    def from_rml(cls, values: dict) -> Misalignment:
        t = [float(values.get(k, 0.0)) for k in MISALIGNMENT_KEYS]
        return cls(*t)

    @property
    def translation(self) -> np.ndarray:
        return np.array([self.tx, self.ty, self.tz])

    def rotation(self) -> np.ndarray:
        return rot_z(self.rz * 1e-3) @ rot_y(self.ry * 1e-3) @ rot_x(self.rx * 1e-3)

    def is_zero(self) -> bool:
        return not any((self.tx, self.ty, self.tz, self.rx, self.ry, self.rz))


@dataclass(frozen=True)
class ChainLink:
    """Geometry of one element as the chain sees it.

    ``theta_in`` and ``theta_out`` are grazing angles in rad (0 for slits,
    image planes and sources); ``azimuth`` is the azimuthal angle in rad;
    ``distance`` the distance from the previous element in mm.  ``tau`` tilts
    the frame the misalignment is expressed in about x (0: the element frame).
    """

    distance: float = 0.0
    azimuth: float = 0.0
    theta_in: float = 0.0
    theta_out: float = 0.0
    misalignment: Misalignment = field(default_factory=Misalignment)
    tau: float = 0.0
    is_source: bool = False


@dataclass(frozen=True)
class Frame:
    position: np.ndarray
    orientation: np.ndarray

    @property
    def x(self) -> np.ndarray:
        return self.orientation[:, 0]

    @property
    def y(self) -> np.ndarray:
        return self.orientation[:, 1]

    @property
    def z(self) -> np.ndarray:
        return self.orientation[:, 2]


def misalign(nominal: Frame, mis: Misalignment, tau: float = 0.0) -> Frame:
    """Apply a misalignment to a nominal frame.

    With ``tau`` != 0 the translations and rotations are expressed in the frame
    ``E = O · Rx(tau)`` (pivot unchanged), as RAY-UI's ellipsoid misalignment
    coordinate system: ``O_w = O · Rx(tau) · R · Rx(-tau)``, ``p_w = p + O · Rx(tau) · t``.
    """
    if mis.is_zero():
        return nominal
    o = nominal.orientation
    if tau == 0.0:
        o_w = o @ mis.rotation()
        p_w = nominal.position + o_w @ mis.translation
    else:
        e = o @ rot_x(tau)
        o_w = e @ mis.rotation() @ rot_x(-tau)
        # RAYX's description of the ellipsoid frame translates before rotating.
        p_w = nominal.position + e @ mis.translation
    return Frame(p_w, o_w)


def chain_frames(links: Sequence[ChainLink]) -> list[Frame]:
    """World frames of an element chain, first link = source at the origin."""
    beam = np.eye(3)
    pos = np.zeros(3)
    frames: list[Frame] = []
    for i, link in enumerate(links):
        if link.is_source:
            if i != 0:
                raise ValueError("only the first element of a chain can be a source")
            nominal = Frame(pos.copy(), beam.copy())
        else:
            pos = pos + link.distance * beam[:, 2]
            turn = rot_z(link.azimuth)
            orient = beam @ turn @ rot_x(-link.theta_in)
            nominal = Frame(pos.copy(), orient)
            beam = beam @ turn @ rot_x(-link.theta_in - link.theta_out) @ rot_z(-link.azimuth)
        frames.append(misalign(nominal, link.misalignment, link.tau))
    return frames


def ellipsoid_tangent_angle(a: float, b: float, design_grazing_rad: float,
                            entrance_arm: float, exit_arm: float) -> float:
    """Tilt (rad) of the ellipse's major axis against the mirror surface at the pole.

    Follows RAYX's ellipsoid construction: the pole ``(y0, z0)`` on the ellipse
    from the half-axes and the design grazing angle, then the tangent slope
    there.  Positive when the entrance arm is the longer one.
    """
    if a <= b or design_grazing_rad <= 0:
        return 0.0
    y0 = -b * b / (math.tan(design_grazing_rad) * math.sqrt(a * a - b * b))
    if y0 <= -b:
        return 0.0
    z0 = a * math.sqrt(b * b - y0 * y0) / b
    if entrance_arm < exit_arm:
        z0 = -z0
    mt = (b / a) ** 2 * z0 / y0
    return -math.atan(mt)
