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

The functions take plain numbers (the RML writer, RAYX's input) or torch tensors of shape
``(C,)``, one value per configuration (the differentiable twin, batched, with gradients):
one piece of geometry for both engines.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from bluesky_offsets.errors import InputError

MISALIGNMENT_KEYS = ("translationXerror", "translationYerror", "translationZerror",
                     "rotationXerror", "rotationYerror", "rotationZerror")


def is_tensor(value) -> bool:
    """A torch tensor (checked without importing torch)."""
    return type(value).__module__.split(".")[0] == "torch"


def _torch_of(*values):
    """The torch module if any value is a tensor, else None."""
    if any(is_tensor(v) for v in values):
        import torch
        return torch
    return None


def _tensors_like(*values):
    """``values`` as tensors like the first tensor among them (numbers become 0-d tensors)."""
    like = next(v for v in values if is_tensor(v))
    return tuple(as_array_like(v, like) for v in values)


def _cos_sin(a):
    torch = _torch_of(a)
    if torch is not None:
        return torch.cos(a), torch.sin(a)
    return math.cos(a), math.sin(a)


def _matrix(rows, like):
    """A 3x3 matrix (or a batch (..., 3, 3)) from entries that are numbers or arrays like ``like``."""
    torch = _torch_of(like)
    if torch is None:
        return np.array(rows, dtype=float)
    full = [[e if torch.is_tensor(e) else torch.full_like(like, float(e)) for e in row] for row in rows]
    return torch.stack([torch.stack(row, -1) for row in full], -2)


def _apply(m, v):
    """Matrix (..., 3, 3) times vector (..., 3), batched alike for numpy and torch."""
    return (m @ v[..., None])[..., 0]


def as_array_like(x, like):
    """``x`` (numbers or an array) in ``like``'s array type, dtype and device."""
    torch = _torch_of(like)
    if torch is None:
        return np.asarray(x, dtype=float)
    return torch.as_tensor(x, dtype=like.dtype, device=like.device)


def rot_x(a) -> np.ndarray:
    """Right-handed active rotation by ``a`` rad about x."""
    c, s = _cos_sin(a)
    return _matrix([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], c)


def rot_y(a) -> np.ndarray:
    """Right-handed active rotation by ``a`` rad about y."""
    c, s = _cos_sin(a)
    return _matrix([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], c)


def rot_z(a) -> np.ndarray:
    """Right-handed active rotation by ``a`` rad about z."""
    c, s = _cos_sin(a)
    return _matrix([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], c)


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
        """The misalignment of an RML ``alignmentError`` mapping (a key it leaves out is 0)."""
        t = [float(values.get(k, 0.0)) for k in MISALIGNMENT_KEYS]
        return cls(*t)

    @property
    def _values(self) -> tuple:
        return self.tx, self.ty, self.tz, self.rx, self.ry, self.rz

    @property
    def translation(self) -> np.ndarray:
        """The translation ``(tx, ty, tz)`` in mm: an array of 3, or a ``(..., 3)`` tensor for tensors."""
        torch = _torch_of(*self._values)
        if torch is None:
            return np.array([self.tx, self.ty, self.tz], dtype=float)
        return torch.stack(torch.broadcast_tensors(*_tensors_like(*self._values)[:3]), -1)

    def rotation(self) -> np.ndarray:
        """The rotation ``Rz(rz) · Ry(ry) · Rx(rx)`` (angles in mrad): (3, 3), or (..., 3, 3) for tensors."""
        rx, ry, rz = self.rx, self.ry, self.rz
        if _torch_of(*self._values) is not None:
            rx, ry, rz = _tensors_like(*self._values)[3:]
        return rot_z(rz * 1e-3) @ rot_y(ry * 1e-3) @ rot_x(rx * 1e-3)

    def is_zero(self) -> bool:
        """True for an all-zero misalignment of numbers (tensors carry gradients: never zero)."""
        return _torch_of(*self._values) is None and not any(self._values)


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
    """An element's world frame: its position (mm) and orientation (its x, y, z axes as columns)."""

    position: np.ndarray
    orientation: np.ndarray

    @property
    def x(self) -> np.ndarray:
        """The frame's x axis (the orientation's column 0)."""
        return self.orientation[:, 0]

    @property
    def y(self) -> np.ndarray:
        """The frame's y axis (the orientation's column 1)."""
        return self.orientation[:, 1]

    @property
    def z(self) -> np.ndarray:
        """The frame's z axis (the orientation's column 2)."""
        return self.orientation[:, 2]


def misalign(nominal: Frame, mis: Misalignment, tau: float = 0.0) -> Frame:
    """Apply a misalignment to a nominal frame.

    With ``tau`` != 0 the translations and rotations are expressed in the frame
    ``E = O · Rx(tau)`` (pivot unchanged), as RAY-UI's ellipsoid misalignment
    coordinate system: ``O_w = O · Rx(tau) · R · Rx(-tau)``, ``p_w = p + O · Rx(tau) · t``.
    """
    if mis.is_zero():
        return nominal
    rot, t = mis.rotation(), mis.translation
    o, p = as_array_like(nominal.orientation, rot), as_array_like(nominal.position, rot)
    if _torch_of(tau) is None and tau == 0.0:
        o_w = o @ rot
        p_w = p + _apply(o_w, t)
    else:
        # a float tau gives numpy matrices: in the array type of a differentiable rotation
        e = o @ as_array_like(rot_x(tau), o)
        o_w = e @ rot @ as_array_like(rot_x(-tau), o)
        # RAYX's description of the ellipsoid frame translates before rotating.
        p_w = p + _apply(e, t)
    return Frame(p_w, o_w)


def chain_frames(links: Sequence[ChainLink]) -> list[Frame]:
    """World frames of an element chain, first link = source at the origin."""
    beam = np.eye(3)
    pos = np.zeros(3)
    frames: list[Frame] = []
    for i, link in enumerate(links):
        if link.is_source:
            if i != 0:
                raise InputError("only the first element of a chain can be a source")
            nominal = Frame(pos.copy(), beam.copy())
        else:
            pos = pos + link.distance * beam[:, 2]
            turn = rot_z(link.azimuth)
            orient = beam @ turn @ rot_x(-link.theta_in)
            nominal = Frame(pos.copy(), orient)
            beam = beam @ turn @ rot_x(-link.theta_in - link.theta_out) @ rot_z(-link.azimuth)
        frames.append(misalign(nominal, link.misalignment, link.tau))
    return frames


def ellipsoid_pole(a, b, design_grazing_rad, entrance_arm, exit_arm):
    """The pole ``(y0, z0)`` of a mirror on the ellipse with half-axes ``a > b``, from the design grazing angle.

    RAYX's construction: ellipse-centred coordinates, y along the minor axis, z along the major
    one; ``z0 > 0`` when the entrance arm is the longer one.
    Numbers or tensors; for a tensor the caller guarantees ``a > b`` and a positive angle.
    """
    torch = _torch_of(a, b, design_grazing_rad)
    if torch is None:
        if a <= b or design_grazing_rad <= 0:
            return (-b if a > b else 0.0), 0.0
        y0 = -b * b / (math.tan(design_grazing_rad) * math.sqrt(a * a - b * b))
        if y0 <= -b:
            return y0, 0.0
        z0 = a * math.sqrt(b * b - y0 * y0) / b
    else:
        like = a if torch.is_tensor(a) else b
        tan = torch.tan(as_array_like(design_grazing_rad, like))
        y0 = -b * b / (tan * torch.sqrt(a * a - b * b))
        z0 = a * torch.sqrt(b * b - y0 * y0) / b
    return y0, (-z0 if entrance_arm < exit_arm else z0)


def ellipsoid_tangent_angle(a, b, design_grazing_rad, entrance_arm: float, exit_arm: float):
    """Tilt (rad) of the ellipse's major axis against the mirror surface at the pole.

    Follows RAYX's ellipsoid construction: the pole ``(y0, z0)`` on the ellipse
    from the half-axes and the design grazing angle, then the tangent slope
    there.  Positive when the entrance arm is the longer one.
    """
    y0, z0 = ellipsoid_pole(a, b, design_grazing_rad, entrance_arm, exit_arm)
    torch = _torch_of(y0, z0)
    if torch is None:
        if z0 == 0.0:
            return 0.0
        return -math.atan((b / a) ** 2 * z0 / y0)
    return -torch.atan((b / a) ** 2 * z0 / y0)
