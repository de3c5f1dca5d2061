"""Plan stubs for moving the beamline between configurations.

Device-agnostic: a *beamline* is any of

* a mapping ``{parameter name or device path: movable}``,
* an object with a ``motors`` mapping (``bluesky_offsets.epics.devices.MetrixsBeamline``,
  ``make_beamline_v1(...)``),
* an object whose attribute paths follow the table's ``device`` paths
  (``beamline.e1.rx``).

Motors need the bluesky ``Movable`` and ``Readable`` protocols; limits are
read from ``low_limit_travel``/``high_limit_travel`` (ophyd and ophyd-async
motor records) or a ``limits`` tuple when present.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import bluesky.plan_stubs as bps
import numpy as np
from bluesky.utils import MsgGenerator

from bluesky_offsets.epics.pvs import STAGE_AXES, MotionError
from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.parameters import METRIXS, ParameterError, ParameterTable


class MotorLimitError(InputError):
    """A requested configuration lies outside a motor's limits; nothing was moved."""


def resolve_motors(beamline, table: ParameterTable = METRIXS) -> dict:
    """``{parameter name: movable}`` for the motorized parameters of ``table`` (table order)."""
    if isinstance(beamline, Mapping):
        source = beamline
    elif isinstance(getattr(beamline, "motors", None), Mapping):
        source = beamline.motors
    else:
        source = None
    out, missing = {}, []
    for p in table:
        if not p.motorized:
            continue
        if source is not None:
            dev = source.get(p.name, source.get(p.device))
        else:
            dev = beamline
            for part in p.device.split("."):
                dev = getattr(dev, part, None)
                if dev is None:
                    break
        if dev is None:
            missing.append(p.name)
        else:
            out[p.name] = dev
    if missing:
        raise InputError(f"beamline lacks motors for {len(missing)} parameters: {', '.join(missing)}")
    return out


def resolve_stage(beamline) -> dict | None:
    """The focus chamber's translation stage, ``{"stage.x": movable, "stage.y": ..., "stage.z": ...}``.

    Taken from ``beamline.chamber_stage``, or a mapping's ``"chamber_stage"`` entry (a device or a
    mapping of its axes); None for a beamline without one.
    """
    stage = (beamline.get("chamber_stage") if isinstance(beamline, Mapping)
             else getattr(beamline, "chamber_stage", None))
    if stage is None:
        return None
    axes = {a: (stage.get(a) if isinstance(stage, Mapping) else getattr(stage, a, None)) for a in STAGE_AXES}
    if missing := [a for a, m in axes.items() if m is None]:
        raise InputError(f"the chamber's stage lacks the axes {', '.join(missing)}")
    return {f"stage.{a}": m for a, m in axes.items()}


def as_configurations(configurations, table: ParameterTable = METRIXS, base=None) -> np.ndarray:
    """Configurations as an ``(n, P)`` array in table order.

    Accepts an ``(n, P)`` array, an ``(n, M)`` array of the ``M`` motorized
    parameters, or a sequence of ``{name: value}`` mappings (unnamed
    parameters take their value from ``base``, default the table's reference).
    Fixed parameters always take their design value: they cannot be moved.
    """
    if isinstance(configurations, Mapping):
        configurations = [configurations]
    if len(configurations) and isinstance(configurations[0], Mapping):
        arr = np.array([table.from_mapping(c, base=base) for c in configurations])
    else:
        arr = np.atleast_2d(np.asarray(configurations, dtype=float))
        n_mot = int(table.motorized.sum())
        if arr.ndim == 2 and arr.shape[1] == n_mot and n_mot != len(table):
            full = np.tile(table.reference, (len(arr), 1))
            full[:, table.motorized] = arr
            arr = full
        arr = table.validate(arr, "configurations")
    if arr.ndim != 2 or len(arr) == 0:
        raise ParameterError(f"configurations: expected a non-empty list of configurations, got shape {arr.shape}")
    fixed = ~table.motorized
    moved = np.abs(arr[:, fixed] - table.reference[fixed]) > 1e-12 * np.maximum(1, np.abs(table.reference[fixed]))
    if moved.any():
        names = sorted({table.names[i] for i in np.flatnonzero(fixed)[np.argwhere(moved)[:, 1]]})
        raise ParameterError(f"configurations change fixed (non-motorized) parameters {names}; "
                             f"leave them at their design values")
    return arr


def read_positions(motors: Mapping) -> MsgGenerator[dict]:
    """Readbacks of all motors, ``{parameter name: position}``."""
    out = {}
    for name, m in motors.items():
        out[name] = float((yield from bps.rd(m)))
    return out


def read_setpoints(motors: Mapping, tolerance: Mapping) -> MsgGenerator[dict]:
    """Where the motors were last sent, ``{parameter name: setpoint}``.

    The readback stands in for a motor without a ``user_setpoint``; relative moves count from
    there, not from a noisy readback.

    Raises :class:`MotionError` naming each motor whose readback is further from its setpoint
    than ``tolerance`` (it did not arrive at its last move).
    """
    readback = yield from read_positions(motors)
    out, off = {}, []
    for name, m in motors.items():
        sp = getattr(m, "user_setpoint", None)
        out[name] = readback[name] if sp is None else float((yield from bps.rd(sp)))
        if abs(out[name] - readback[name]) > _allowed(tolerance.get(name, 0.0), out[name]):
            off.append(f"{name}: at {readback[name]:.6g}, sent to {out[name]:.6g}")
    if off:
        raise MotionError("motors stand away from their setpoints (a move that did not arrive): " + "; ".join(off))
    return out


def current_configuration(beamline, table: ParameterTable = METRIXS) -> MsgGenerator[np.ndarray]:
    """The motors' readbacks as a configuration vector (table order; fixed parameters at design value)."""
    motors = resolve_motors(beamline, table)
    positions = yield from read_positions(motors)
    return table.from_mapping(positions)


def _limits(motor) -> MsgGenerator[tuple[float, float] | None]:
    lo_sig, hi_sig = getattr(motor, "low_limit_travel", None), getattr(motor, "high_limit_travel", None)
    if lo_sig is not None and hi_sig is not None:
        lo, hi = float((yield from bps.rd(lo_sig))), float((yield from bps.rd(hi_sig)))
    else:
        lim = getattr(motor, "limits", None)
        if lim is None:
            return None
        lo, hi = map(float, lim)
    if lo == hi == 0:  # motor-record convention: no limits
        return None
    return min(lo, hi), max(lo, hi)


def _read_optional(motor, attr: str) -> MsgGenerator[float | None]:
    sig = getattr(motor, attr, None)
    if sig is None:
        return None
    try:
        return abs(float((yield from bps.rd(sig))))
    except Exception:
        return None


def _step(motor) -> MsgGenerator[float]:
    step = yield from _read_optional(motor, "motor_resolution")
    if step is None:
        prec = getattr(motor, "precision", None)
        step = 10.0 ** -int(prec) if isinstance(prec, (int, np.integer)) else 0.0
    return step


def _tolerance(motor) -> MsgGenerator[float]:
    """How far from its target a motor may stand after a move.

    Two steps (``MRES``, else ``10**-precision``), or the retry deadband ``RDBD`` and the step the
    record rounds the target to, when wider (an encoder-read axis).
    """
    step = yield from _step(motor)
    band = yield from _read_optional(motor, "deadband")
    return max(2 * step, band + step if band else 0.0)


def pull_inside(motors: Mapping, targets: Sequence[Mapping], margin: Mapping) -> MsgGenerator[list[dict]]:
    """``targets`` with each position nearer a soft limit than ``margin`` moved ``margin`` inside.

    Such a position is at the limit, or a rounding beyond it (:func:`check_limits` passed them): a
    record rounds a target to its steps (-1.5 at 1e-5 steps reads back -1.5000000000000002) and an
    encoder reads around it, and a client that checks the readback against the limits
    (ophyd-async's ``Motor``) then refuses every later move.
    """
    out = [dict(t) for t in targets]
    for name, m in motors.items():
        lim = yield from _limits(m)
        gap = margin.get(name, 0.0)
        if lim is None or not gap or lim[1] - lim[0] <= 2 * gap:
            continue
        for t in out:
            t[name] = min(max(t[name], lim[0] + gap), lim[1] - gap)
    return out


def resolutions(motors: Mapping) -> MsgGenerator[dict]:
    """Each motor's step size (``MRES``, else ``10**-precision``), ``{name: resolution}``."""
    out = {}
    for name, m in motors.items():
        out[name] = yield from _step(m)
    return out


def check_limits(motors: Mapping, targets: Sequence[Mapping]) -> MsgGenerator[None]:
    """Raise :class:`MotorLimitError` naming every target outside its motor's limits.

    Runs before any motion, so a refused scan leaves every motor where it was.
    """
    problems = []
    for name, m in motors.items():
        lim = yield from _limits(m)
        if lim is None:
            continue
        lo, hi = lim
        tol = 1e-9 * max(hi - lo, 1e-12)
        for k, t in enumerate(targets):
            v = t[name]
            if not lo - tol <= v <= hi + tol:
                problems.append(f"configuration {k}: {name} ({getattr(m, 'name', m)}) -> {v:.6g} "
                                f"outside limits [{lo:.6g}, {hi:.6g}]")
    if problems:
        more = f" (and {len(problems) - 5} more)" if len(problems) > 5 else ""
        raise MotorLimitError("requested positions beyond motor limits, nothing was moved: "
                              + "; ".join(problems[:5]) + more)


def tolerances(motors: Mapping) -> MsgGenerator[dict]:
    """Each motor's arrival tolerance (:func:`_tolerance`), ``{name: tolerance}``."""
    out = {}
    for name, m in motors.items():
        out[name] = yield from _tolerance(m)
    return out


def limit_margins(motors: Mapping) -> MsgGenerator[dict]:
    """How far inside its soft limits each motor is sent (:func:`pull_inside`), ``{name: margin}``.

    The margin is its arrival tolerance and one step, so that its readback stays inside them.
    """
    tol = yield from tolerances(motors)
    steps = yield from resolutions(motors)
    return {n: tol[n] + steps[n] for n in motors}


def move_to(motors: Mapping, target: Mapping, *, verify: bool = True, tolerance: Mapping | None = None,
            current: Mapping | None = None) -> MsgGenerator[None]:
    """Move all motors to ``target`` together, wait, and check that each arrived.

    ``current``: where the motors are known to stand (the previous target of a scan); motors
    already at their target are then neither commanded nor checked.  A motor record processes
    every put as a move, also a zero-length one (``DMOV`` 1 -> 0 -> 1, a dozen monitor updates
    each way), and a scan's step changes 1-8 of the 28 motors: on the simulated beamline a move
    of 4 motors by a tiny step takes 16 ms, of all 28 103 ms.  Without ``current`` every motor
    is commanded (after a pause or an interrupted move nobody knows where they stand).
    """
    moving = {n: m for n, m in motors.items()
              if current is None or n not in current or not _same(current[n], target[n])}
    args = []
    for name, m in moving.items():
        args += [m, float(target[name])]
    if args:
        yield from bps.mv(*args)
    if verify and moving:
        yield from verify_positions(moving, target, tolerance)


def _same(a: float, b: float) -> bool:
    return abs(float(a) - float(b)) <= 1e-12 * max(1.0, abs(float(b)))


def _allowed(tolerance: float, target: float) -> float:
    return max(tolerance * (1 + 1e-9), 1e-9 * max(1.0, abs(target)))


def verify_positions(motors: Mapping, target: Mapping, tolerance: Mapping | None = None) -> MsgGenerator[None]:
    """Raise :class:`MotionError` for motors further from ``target`` than their tolerance (:func:`tolerances`)."""
    if tolerance is None:
        tolerance = yield from tolerances(motors)
    off = []
    for name, m in motors.items():
        pos = float((yield from bps.rd(m)))
        if abs(pos - target[name]) > _allowed(tolerance.get(name, 0.0), target[name]):
            off.append(f"{name}: at {pos:.6g}, sent to {target[name]:.6g}")
    if off:
        raise MotionError("motors did not arrive (stalled, stopped, at a limit or refused by the controller): "
                          + "; ".join(off))


def return_to(motors: Mapping, positions: Mapping, current: Mapping | None = None) -> MsgGenerator[None]:
    """Move every motor back to ``positions`` (used as the finalizer of scans).

    ``current`` as for :func:`move_to`.
    """
    yield from move_to(motors, positions, verify=False, current=current)
