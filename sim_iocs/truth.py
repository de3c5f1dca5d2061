"""The hidden truth of the simulated beamline.

The operator sees motor positions; the beamline "really" sits at those
positions plus fixed, unknown offsets, and its six fixed parameters (mirror
radius, grating radius, ellipse half-axes) differ from their design values.
Hidden physical effects (RML-level overrides such as a focus-chamber
translation along the beam) can be added on top.  None of this is published
on any PV; only :attr:`Truth.truth_id`, a hash, is, so that stored runs say
which truth produced them.  A truth drawn from a seed is hashed with a random secret salt
(written with it by ``--dump-truth``): else a small seed could be found by hashing every seed.

Truth file (JSON), every key optional::

    {
      "offsets": {"E1.rotationXerror": 0.08, "M1_Cylinder.radius": -0.05},
      "offsets_physical": {"E2.rotationXerror": -0.05},
      "overrides": {"ImagePlane": {"translationZerror": 5.0}},
      "start": {"E1.rotationZerror": 10.0},
      "motors": {"E1.rotationXerror": {"step_scale": 0.02}, "chamber.z": {"stalled": true}},
      "salt": "…"
    }

``offsets`` are normalized (fractions of each parameter's range, at most
±0.2, as in the paper), ``offsets_physical`` in mm/mrad; unnamed parameters
have no offset.  ``start`` sets motor positions at IOC start (default: the
centre of each motor's range).  ``motors`` changes how single axes (a motorized parameter or
``chamber.x``/``y``/``z``) really move, on top of the IOC's ``--motors`` profile: any field of
:class:`sim_iocs.motor_record.Mechanics` (a step-scale error, a stalled load, backlash, ...).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bluesky_offsets.physics.parameters import METRIXS, ParameterError, ParameterTable
from bluesky_offsets.physics.screen import STAGE

from .motor_record import Mechanics

_MECHANICS = {f.name: f.type for f in dataclasses.fields(Mechanics)}


def _motor_faults(spec, table: ParameterTable) -> dict:
    """``{axis: {Mechanics field: value}}`` checked: known axes and fields, values that make a Mechanics."""
    if not isinstance(spec, Mapping) or not all(isinstance(v, Mapping) for v in spec.values()):
        raise ParameterError("motors must be {axis name: {mechanics field: value}}")
    axes = set(table.motorized_names) | {f"chamber.{ax.name}" for ax in STAGE}
    out = {}
    for axis, fields in spec.items():
        if axis not in axes:
            raise ParameterError(f"motors: {axis!r} is not a motorized parameter or chamber.x/y/z")
        if unknown := set(fields) - set(_MECHANICS):
            raise ParameterError(f"motors: {axis}: unknown fields {sorted(unknown)}; expected some of "
                                 f"{sorted(_MECHANICS)}")
        try:
            clean: dict[str, Any] = {k: (bool(v) if k in ("encoder", "stalled") else float(v))
                                     for k, v in fields.items()}
            Mechanics(**{**({"encoder": True} if clean.get("readback_noise") else {}), **clean})
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"motors: {axis}: {exc}") from None
        out[str(axis)] = clean
    return out


def default_start(table: ParameterTable = METRIXS) -> np.ndarray:
    """Motor positions at IOC start: the centre of each motor's range; fixed parameters at design value."""
    start = 0.5 * (table.low + table.high)
    return np.where(table.motorized, start, table.reference)


def _field_value(obj, field, x):
    """An RML field value: a number, or a word such as an element type.

    A word stays text: a thermal bump turns M1 into a ``Toroid``.
    """
    if isinstance(x, str):
        try:
            return float(x)
        except ValueError:
            if not x.strip():
                raise ParameterError(f"overrides: {obj}.{field} is empty") from None
            return x
    try:
        return float(x)
    except (TypeError, ValueError):
        raise ParameterError(f"overrides: {obj}.{field} = {x!r} is neither a number nor a word") from None


@dataclass
class Truth:
    """Hidden offsets (normalized, table order), hidden effects and start positions."""

    offsets: np.ndarray
    overrides: dict = field(default_factory=dict)
    start: np.ndarray | None = None
    table: ParameterTable = METRIXS
    source: str = ""
    salt: str = ""  # a random secret for a truth drawn from a seed (see the module text)
    motors: dict = field(default_factory=dict)  # {axis: {Mechanics field: value}}, hidden too

    def __post_init__(self):
        self.offsets = self.table.validate(self.offsets, "hidden offsets").astype(float)
        self.table.check_offsets(self.offsets)
        self.start = default_start(self.table) if self.start is None else self.table.validate(self.start, "start")
        bad = [n for n, v, lo, hi, m in zip(self.table.names, self.start, self.table.low, self.table.high,
                                            self.table.motorized) if m and not lo <= v <= hi]
        if bad:
            raise ParameterError(f"start position outside the motor limits for {', '.join(bad)}")
        if not isinstance(self.overrides, Mapping) or not all(isinstance(v, Mapping) for v in self.overrides.values()):
            raise ParameterError("overrides must be {object name: {RML field: value}}")
        self.overrides = {str(k): {str(f): _field_value(k, f, x) for f, x in v.items()}
                          for k, v in self.overrides.items()}
        self.motors = _motor_faults(self.motors, self.table)

    # -- construction -------------------------------------------------------
    @classmethod
    def from_seed(cls, seed: int | None, table: ParameterTable = METRIXS, limit: float = 0.2) -> Truth:
        """Offsets of all parameters drawn uniformly in ±``limit`` (the paper's protocol: 0.2)."""
        if not 0 <= limit <= 0.2:
            raise ParameterError(f"offset limit must lie in [0, 0.2], got {limit}")
        rng = np.random.default_rng(seed)
        return cls(table.sample_offsets(rng, limit=limit), table=table, salt=os.urandom(16).hex(),
                   source=f"seed {seed}, ±{limit:g}" if seed is not None else f"random seed, ±{limit:g}")

    @classmethod
    def from_mapping(cls, spec: Mapping, table: ParameterTable = METRIXS, source: str = "") -> Truth:
        """The truth a truth file's mapping describes (offsets, overrides, start, motors); unknown keys refused."""
        known = {"offsets", "offsets_physical", "overrides", "start", "comment", "salt", "motors"}
        unknown = set(spec) - known
        if unknown:
            raise ParameterError(f"truth: unknown keys {sorted(unknown)}; expected some of {sorted(known)}")
        off = np.zeros(len(table))
        for name, v in dict(spec.get("offsets", {})).items():
            off[table.index(name)] = float(v)
        for name, v in dict(spec.get("offsets_physical", {})).items():
            i = table.index(name)
            off[i] = float(v) / table.span[i]
        start = default_start(table)
        for name, v in dict(spec.get("start", {})).items():
            i = table.index(name)
            if not table.motorized[i]:
                raise ParameterError(f"truth: start position given for {name!r}, which is not a motor")
            start[i] = float(v)
        return cls(off, dict(spec.get("overrides", {})), start, table=table, source=source,
                   salt=str(spec.get("salt", "")), motors=spec.get("motors", {}))

    @classmethod
    def from_file(cls, path: str | Path, table: ParameterTable = METRIXS) -> Truth:
        """The truth in the JSON truth file at ``path`` (:meth:`from_mapping`)."""
        p = Path(path)
        try:
            spec = json.loads(p.read_text())
        except FileNotFoundError:
            raise ParameterError(f"truth file {p} does not exist") from None
        except json.JSONDecodeError as exc:
            raise ParameterError(f"truth file {p} is not valid JSON: {exc}") from None
        if not isinstance(spec, Mapping):
            raise ParameterError(f"truth file {p} must hold a JSON object")
        return cls.from_mapping(spec, table, source=str(p))

    def to_dict(self) -> dict:
        """Everything, normalized offsets for all parameters (for writing a truth file)."""
        assert self.start is not None  # __post_init__ fills it
        return {"offsets": {n: float(v) for n, v in zip(self.table.names, self.offsets)},
                "overrides": self.overrides,
                "start": {n: float(v) for n, v, m in zip(self.table.names, self.start, self.table.motorized) if m},
                "motors": self.motors,
                "salt": self.salt}

    # -- use ------------------------------------------------------------------
    def mechanics(self, axis: str, profile: Mechanics) -> Mechanics:
        """How ``axis`` really moves: the IOC's ``profile`` with this truth's faults on top."""
        fields = self.motors.get(axis, {})
        if fields.get("readback_noise") and not profile.encoder and "encoder" not in fields:
            fields = {**fields, "encoder": True}
        return dataclasses.replace(profile, **fields)

    @property
    def physical_offsets(self) -> np.ndarray:
        """The hidden offsets in physical units (mm/mrad), table order."""
        return self.offsets * self.table.span

    def true_values(self, positions) -> np.ndarray:
        """True beamline state for motor positions ``positions`` (table order).

        Fixed entries are taken at their design value whatever is passed.
        """
        pos = self.table.validate(positions, "positions")
        pos = np.where(self.table.motorized, pos, self.table.reference)
        return pos + self.physical_offsets

    @property
    def truth_id(self) -> str:
        """Short hash of offsets, effects and parameter-table version (safe to publish)."""
        spec = {"table": self.table.version, "offsets": [float(f"{v:.12g}") for v in self.offsets],
                "overrides": self.overrides}
        if self.motors:  # absent when perfect: the ids of every earlier truth stay as they were
            spec["motors"] = self.motors
        if self.salt:
            spec["salt"] = self.salt
        blob = json.dumps(spec, sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:12]
