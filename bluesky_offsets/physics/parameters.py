"""A beamline's parameters, and the 34 METRIXS ones.

A table is read from a beamline description (``data/beamlines/<name>.toml``: one
``[[parameter]]`` entry per parameter, the one source of truth); METRIXS's follows Table 1 of
Meier et al. (2025).  Each parameter knows the
RML element and field it drives, its unit, its sampling box ``[low, high]``,
whether a motor moves it, and the value the reference RML holds.

The box is the *sampling box of the surrogate*, not a physical limit: the twin
accepts any finite value, and :meth:`ParameterTable.outside_box` says which
values a surrogate would have to extrapolate to.

Normalized coordinates map ``low -> 0`` and ``high -> 1``.  Offsets are given
in normalized units (fractions of each range) and are at most
:data:`MAX_OFFSET` = 0.2 in magnitude, as in the paper.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.geometry import MISALIGNMENT_KEYS

MAX_OFFSET = 0.2
"""Largest offset magnitude, in normalized units (20 % of each range)."""


def at_offset_bound(offsets, bound: float = MAX_OFFSET) -> np.ndarray:
    """Which normalized offsets sit at the ±``bound`` a fit held them within (within rounding)."""
    return np.abs(np.abs(np.asarray(offsets, float)) - bound) < 1e-6


class ParameterError(InputError):
    """Malformed parameter input; the message names the offending parameter."""


@dataclass(frozen=True)
class Parameter:
    """One beamline parameter.

    Attributes
    ----------
    name : str
        Paper/RML-style name, ``"<component>.<field>"``.
    element : str
        Name of the RML object it acts on.
    field : str
        RML field it sets: a misalignment (``translationXerror`` ...) or an
        element property (``openingWidth``, ``radius`` ...).
    unit : str
        ``"mm"`` for a translation, ``"mrad"`` for a rotation; an element property's own RML unit
        (a radius in mm, a line density in lines/mm), a label.
    low, high : float
        Uniform sampling box of the surrogate (paper Table 1).
    motorized : bool
        ``False`` for the six fixed-but-unknown radii and half-axes.
    reference : float
        Value in the reference RML (the nominal configuration).
    device : str
        ``"<component>.<axis>"`` attribute path used by the ophyd devices.
    description : str
        Human-readable meaning.
    travel : (float, float) or None
        The motor's travel where it is wider than the box (the slit openings: real
        measurements open the ASBL to 4 mm and the exit slit to 100 µm, see
        ``../shared/reference/metrixs_2021_real_settings.csv``).  The IOC's soft limits;
        a configuration outside the box is valid for the twin, not for the surrogate.
    """

    name: str
    element: str
    field: str
    unit: str
    low: float
    high: float
    motorized: bool
    reference: float
    device: str
    description: str
    travel: tuple[float, float] | None = None

    @property
    def limits(self) -> tuple[float, float]:
        """Motor travel (soft limits): ``travel`` where given, else the box."""
        return self.travel if self.travel is not None else (self.low, self.high)

    @property
    def component(self) -> str:
        """The part of ``name`` before its first ``.``: the element the parameter belongs to."""
        return self.name.split(".", 1)[0]

    @property
    def span(self) -> float:
        """The sampling box's width, ``high - low``."""
        return self.high - self.low


def _finite_array(values, n: int, names: Sequence[str], what: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{what}: cannot convert to numbers ({exc})") from None
    if arr.ndim == 0 or arr.shape[-1] != n:
        raise ParameterError(
            f"{what}: expected a vector of {n} parameters in table order, got shape {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        col = int(np.argwhere(bad)[0][-1])
        raise ParameterError(f"{what}: parameter {names[col]!r} is not finite ({arr[..., col].ravel()[0]})")
    return arr


class ParameterTable:
    """Ordered, immutable table of beamline parameters with conversions.

    All conversion methods accept a single vector ``(n,)`` or a batch
    ``(..., n)`` in table order and validate shape and finiteness.
    """

    def __init__(self, parameters: Iterable[Parameter], *, name: str = "metrixs", source=None):
        self.parameters: tuple[Parameter, ...] = tuple(parameters)
        self.name = name
        self.source = source  # the description file it was read from (the twin's geometry), if any
        self.names: tuple[str, ...] = tuple(p.name for p in self.parameters)
        if len(set(self.names)) != len(self.names):
            raise ParameterError("duplicate parameter names in table")
        self._index = {n: i for i, n in enumerate(self.names)}
        self.low = np.array([p.low for p in self.parameters])
        self.high = np.array([p.high for p in self.parameters])
        self.span = self.high - self.low
        self.reference = np.array([p.reference for p in self.parameters])
        self.motorized = np.array([p.motorized for p in self.parameters])

    # -- lookup -------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.parameters)

    def __iter__(self):
        return iter(self.parameters)

    def __getitem__(self, name: str) -> Parameter:
        return self.parameters[self.index(name)]

    def index(self, name: str) -> int:
        """The position of parameter ``name`` in the table (an unknown name is refused, with a hint)."""
        try:
            return self._index[name]
        except KeyError:
            close = [n for n in self.names if name.lower() in n.lower()]
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ParameterError(f"unknown parameter {name!r}{hint}") from None

    @property
    def motorized_names(self) -> tuple[str, ...]:
        """The names of the motorized parameters, in table order."""
        return tuple(p.name for p in self.parameters if p.motorized)

    @property
    def fixed_names(self) -> tuple[str, ...]:
        """The names of the fixed-but-unknown (not motorized) parameters, in table order."""
        return tuple(p.name for p in self.parameters if not p.motorized)

    # -- validation and conversion -----------------------------------------
    def validate(self, values, what: str = "parameter vector") -> np.ndarray:
        """Return ``values`` as a float array after checking length and finiteness."""
        return _finite_array(values, len(self), self.names, what)

    def from_mapping(self, mapping: Mapping[str, float], base=None) -> np.ndarray:
        """Build a vector from ``{name: value}``; unspecified entries come from ``base``.

        ``base`` defaults to the reference configuration.
        """
        vec = np.array(self.reference if base is None else self.validate(base), dtype=float, copy=True)
        for name, value in mapping.items():
            i = self.index(name)
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise ParameterError(f"parameter {name!r}: value {value!r} is not a number") from None
            if not math.isfinite(v):
                raise ParameterError(f"parameter {name!r}: value {v} is not finite")
            vec[i] = v
        return vec

    def to_mapping(self, values) -> dict[str, float]:
        """One parameter vector as ``{name: value}``, in table order."""
        vec = self.validate(values)
        if vec.ndim != 1:
            raise ParameterError("to_mapping takes a single parameter vector")
        return {n: float(v) for n, v in zip(self.names, vec)}

    def normalize(self, values) -> np.ndarray:
        """Physical values -> normalized coordinates (box maps to [0, 1])."""
        return (self.validate(values) - self.low) / self.span

    def denormalize(self, normalized) -> np.ndarray:
        """Normalized coordinates -> physical values."""
        return self.validate(normalized, "normalized vector") * self.span + self.low

    def offsets_to_physical(self, offsets) -> np.ndarray:
        """Normalized offsets (fractions of each range) -> physical offsets."""
        off = self.validate(offsets, "offset vector")
        self.check_offsets(off)
        return off * self.span

    def model_values(self, configurations, offsets) -> np.ndarray:
        """Where a model with normalized ``offsets`` puts the parameters at ``configurations``.

        The configurations (one vector or a stack) plus the physical offsets, the offsets first
        held within the model's ±``MAX_OFFSET`` bound (an estimate may step past it by rounding).
        """
        return np.asarray(configurations, float) + self.offsets_to_physical(np.clip(offsets, -MAX_OFFSET, MAX_OFFSET))

    def offsets_to_normalized(self, offsets) -> np.ndarray:
        """Physical offsets -> normalized offsets (fractions of each range)."""
        off = self.validate(offsets, "offset vector") / self.span
        self.check_offsets(off)
        return off

    def check_offsets(self, normalized_offsets, limit: float = MAX_OFFSET) -> None:
        """Refuse normalized offsets beyond ``±limit`` of a parameter's range, naming the first such parameter."""
        off = self.validate(normalized_offsets, "offset vector")
        too_big = np.abs(off) > limit + 1e-12
        if too_big.any():
            col = int(np.argwhere(too_big)[0][-1])
            raise ParameterError(
                f"offset of {self.names[col]!r} is {off[..., col].ravel()[0]:+.4f} of its range; "
                f"offsets are limited to ±{limit:.2f}")

    def sample_uniform(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` vectors drawn uniformly from the sampling box (paper Sec. 3.1)."""
        return self.low + rng.random((n, len(self))) * self.span

    def sample_offsets(self, rng: np.random.Generator, limit: float = MAX_OFFSET,
                       size: int | None = None) -> np.ndarray:
        """Normalized offsets drawn uniformly in ``[-limit, limit]`` (paper Sec. 3.2)."""
        shape = (len(self),) if size is None else (size, len(self))
        return rng.uniform(-limit, limit, shape)

    def outside_box(self, values) -> list[str]:
        """Names of parameters whose value lies outside the sampling box.

        There a surrogate trained on the box would have to extrapolate.
        """
        vec = self.validate(values)
        if vec.ndim != 1:
            raise ParameterError("outside_box takes a single parameter vector")
        tol = 1e-9 * np.maximum(1.0, np.abs(self.span))
        out = (vec < self.low - tol) | (vec > self.high + tol)
        return [n for n, o in zip(self.names, out) if o]

    # -- identity -----------------------------------------------------------
    def as_records(self) -> list[dict]:
        """The parameters as one mapping each: their fields, ``component`` and ``fixed_but_unknown``."""
        return [dict(asdict(p), component=p.component, fixed_but_unknown=not p.motorized)
                for p in self.parameters]

    def fingerprint(self) -> dict:
        """What a model trained on this table must agree with: names, order, ranges."""
        return {"name": self.name,
                "names": list(self.names),
                "low": [float(x) for x in self.low],
                "high": [float(x) for x in self.high]}

    @property
    def version(self) -> str:
        """Short content hash of names, order and ranges (stored with runs and models)."""
        blob = json.dumps(self.fingerprint(), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:12]

    def diff(self, fingerprint: Mapping) -> list[str]:
        """Human-readable differences between this table and a stored fingerprint."""
        problems = []
        theirs = list(fingerprint.get("names", []))
        if theirs != list(self.names):
            missing = [n for n in self.names if n not in theirs]
            extra = [n for n in theirs if n not in self.names]
            if missing or extra:
                problems.append(f"parameters differ: missing {missing}, unexpected {extra}")
            else:
                problems.append("parameter order differs")
            return problems
        for i, n in enumerate(self.names):
            lo, hi = fingerprint["low"][i], fingerprint["high"][i]
            if not (np.isclose(lo, self.low[i], rtol=1e-12, atol=0) and
                    np.isclose(hi, self.high[i], rtol=1e-12, atol=0)):
                problems.append(f"range of {n!r} differs: stored [{lo}, {hi}], "
                                f"current [{self.low[i]}, {self.high[i]}]")
        return problems


PARAMETER_KEYS = ("name", "element", "field", "unit", "range", "reference", "motor", "fixed", "travel", "description")
"""The keys of a ``[[parameter]]`` entry of a beamline description."""
UNITS = ("mm", "mrad")
"""The units of the misalignments: translations in mm, rotations in mrad."""


def misalignment_unit(field: str) -> str | None:
    """The unit RAYX reads a misalignment ``field`` in; None for an element's own property (its RML unit)."""
    if field not in MISALIGNMENT_KEYS:
        return None
    return UNITS[0] if field.startswith("translation") else UNITS[1]


def parameter_from_record(rec: Mapping, where: str = "parameter") -> Parameter:
    """One :class:`Parameter` from a beamline description's ``[[parameter]]`` entry.

    A :class:`ParameterError` names the entry and the key for anything it cannot use.

    ``motor`` (the motor's device path, e.g. ``"e1.rx"``) makes it motorized; ``fixed`` (the
    same for a fixed-but-unknown value) makes it not; exactly one of the two.
    """
    name = rec.get("name", "?") if isinstance(rec, Mapping) else "?"
    where = f"{where} {name!r}"
    if not isinstance(rec, Mapping):
        raise ParameterError(f"{where}: expected a table of keys, got {type(rec).__name__}")
    unknown = sorted(set(rec) - set(PARAMETER_KEYS))
    if unknown:
        raise ParameterError(f"{where}: unknown keys {unknown}; known: {list(PARAMETER_KEYS)}")
    missing = [k for k in ("name", "element", "field", "unit", "range", "reference") if k not in rec]
    if missing:
        raise ParameterError(f"{where}: missing {missing}")
    if ("motor" in rec) == ("fixed" in rec):
        raise ParameterError(f"{where}: give exactly one of 'motor' (a motorized parameter) or 'fixed' "
                             f"(fixed but unknown)")
    for key in ("name", "element", "field", "unit", "description", "motor", "fixed"):
        if key in rec and not (isinstance(rec[key], str) and rec[key].strip()):
            raise ParameterError(f"{where}: {key} must be a non-empty string")
    need = misalignment_unit(rec["field"])
    if need is not None and rec["unit"] != need:
        raise ParameterError(f"{where}: unit {rec['unit']!r}; a {rec['field']} is in {need!r} (RAYX's unit)")

    def pair(key):
        v = rec[key]
        if not (isinstance(v, (list, tuple)) and len(v) == 2 and all(_real(x) for x in v)) or not v[0] < v[1]:
            raise ParameterError(f"{where}: {key} must be [low, high] with finite low < high, got {v!r}")
        return float(v[0]), float(v[1])

    low, high = pair("range")
    if not _real(rec["reference"]):
        raise ParameterError(f"{where}: reference must be a finite number, got {rec['reference']!r}")
    return Parameter(rec["name"], rec["element"], rec["field"], rec["unit"], low, high, "motor" in rec,
                     float(rec["reference"]), rec.get("motor", rec.get("fixed")), rec.get("description", ""),
                     pair("travel") if "travel" in rec else None)


def _real(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def table_from_description(path, *, name: str | None = None) -> ParameterTable:
    """The :class:`ParameterTable` of a beamline description file (TOML, its ``[[parameter]]`` entries in order).

    The whole description is read by :func:`physics.beamline.load_beamline`.
    """
    import tomllib
    from pathlib import Path
    with Path(path).open("rb") as f:
        doc = tomllib.load(f)
    records = doc.get("parameter")
    if not isinstance(records, list) or not records:
        raise ParameterError(f"{path}: no [[parameter]] entries")
    return ParameterTable([parameter_from_record(r) for r in records],
                          name=name or str(doc.get("beamline", {}).get("name", Path(path).stem)),
                          source=Path(path).resolve())


BEAMLINES = __import__("pathlib").Path(__file__).resolve().parent.parent / "data" / "beamlines"
"""The beamline descriptions shipped with the package."""

METRIXS = table_from_description(BEAMLINES / "metrixs.toml")
"""The METRIXS table of the paper (34 parameters, 28 motorized), from the shipped description."""

