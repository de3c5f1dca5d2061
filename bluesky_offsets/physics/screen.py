"""The focus chamber's translation stage: where the screen stands, as the model traces it.

The chamber sits on an x/y/z stage (the real METRIXS chamber's x/y offsets are in the 2021
settings; the authors' later work scans the screen along z from -15 to +30 mm).  A screen moved
along the beam separates a beam's position from its angle, and a focus from a defocus.  Like
every motor the stage moves precisely relative to where it is while its absolute position is
unknown: the stage's readbacks are the twin's coordinates of the screen (0 = the design's image
plane), and what the model does not know about where the screen truly is stays a physical effect
(``chamber_x``, ``chamber_y``, ``chamber_z``), added to the stage's position.

A measurement's ``screen`` is ``(n, 3)``: the stage's x, y, z per frame, in mm.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.metrixs import IMAGE_PLANE

FIELDS = ("translationXerror", "translationYerror", "translationZerror")


@dataclass(frozen=True, kw_only=True)
class StageAxis:
    """One axis of the chamber's stage: its name, travel (mm) and what it moves."""

    name: str
    low: float
    high: float
    description: str
    unit: str = "mm"

    @property
    def span(self) -> float:
        """The axis's travel, ``high - low`` (mm)."""
        return self.high - self.low


STAGE: tuple[StageAxis, ...] = (
    StageAxis(name="x", low=-5.0, high=5.0, description="screen across the beam, horizontally"),
    StageAxis(name="y", low=-5.0, high=5.0, description="screen across the beam, vertically"),
    StageAxis(name="z", low=-15.0, high=30.0, description="screen along the beam"),
)
"""The stage's three axes and their travel (x, y, z).  z spans the authors' scan, -15 to +30 mm."""


def as_screen(screen, n: int) -> np.ndarray:
    """``screen`` as an ``(n, 3)`` float array (None: the stage at 0 for every frame).

    Another shape or a value that is not finite is refused, in one line.
    """
    if screen is None:
        return np.zeros((n, 3))
    s = np.asarray(screen, dtype=float)
    if s.ndim == 1 and s.shape == (3,):
        s = np.tile(s, (n, 1))
    if s.shape != (n, 3):
        raise InputError(f"screen positions: expected ({n}, 3) (stage x, y, z per frame), got shape {s.shape}")
    if not np.isfinite(s).all():
        raise InputError("screen positions must be finite")
    return s


def moved(screen) -> bool:
    """Whether any frame was taken with the stage away from 0."""
    return screen is not None and bool(np.any(np.asarray(screen) != 0.0))


def check_travel(screen) -> None:
    """Refuse stage positions outside the stage's travel, naming the axis."""
    s = np.atleast_2d(np.asarray(screen, float))
    for k, ax in enumerate(STAGE):
        bad = (s[:, k] < ax.low - 1e-9) | (s[:, k] > ax.high + 1e-9)
        if bad.any():
            raise InputError(f"chamber stage {ax.name} = {s[bad, k][0]:g} mm is outside its travel "
                             f"[{ax.low:g}, {ax.high:g}] mm")


def add_overrides(base: Mapping | None, extra: Mapping) -> dict:
    """``base`` and ``extra`` RML overrides merged.

    Misalignments of one object add up (the stage's position and the chamber's hidden
    displacement); any other field of ``extra`` wins.
    """
    out = {k: dict(v) for k, v in (base or {}).items()}
    for obj, fields in extra.items():
        tgt = out.setdefault(obj, {})
        for key, val in fields.items():
            tgt[key] = tgt[key] + val if key.endswith("error") and key in tgt else val
    return out


def per_frame_overrides(overrides: Mapping | Sequence[Mapping] | None, screen,
                        n: int) -> Mapping | Sequence[Mapping] | None:
    """The overrides of ``n`` frames with the stage at ``screen``.

    ``overrides`` as given (one mapping for all, or one per frame) where the stage never moved,
    else one mapping per frame with the stage's position added to the image plane's.
    """
    if not moved(screen):
        return overrides
    s = as_screen(screen, n)
    base = [overrides or {}] * n if overrides is None or isinstance(overrides, Mapping) else list(overrides)
    return [add_overrides(b, {IMAGE_PLANE: dict(zip(FIELDS, map(float, row)))}) for b, row in zip(base, s)]


def tensor_overrides(screen, n: int, dtype=None, device=None) -> dict | None:
    """The stage's positions as batched overrides of the torch engine (one ``(n,)`` tensor per axis).

    None where the stage never moved.
    """
    if not moved(screen):
        return None
    import torch
    s = torch.as_tensor(as_screen(screen, n), dtype=dtype or torch.float64, device=device)
    return {IMAGE_PLANE: {f: s[:, k] for k, f in enumerate(FIELDS)}}


def on_image_plane(overrides, image_plane: str):
    """``overrides`` with the screen renamed to a described beamline's ``image_plane``.

    ``overrides`` is one mapping, or one per configuration; the effects' and the stage's screen
    (METRIXS's ``ImagePlane``) is renamed.
    """
    if not overrides or image_plane == IMAGE_PLANE:
        return overrides
    if not isinstance(overrides, dict):
        return [on_image_plane(o, image_plane) for o in overrides]
    return {(image_plane if k == IMAGE_PLANE else k): v for k, v in overrides.items()}
