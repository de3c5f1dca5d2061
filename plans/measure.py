"""Measure the focus-chamber footprint at a list of beamline configurations.

Absolute positions are unknown at the beamline (that is what the offsets
are), so configurations are reached by *differences*: each motor goes to
its position at the start of the plan plus the configuration's difference
from the ``reference`` configuration (the configuration, in twin
coordinates, that the motors stand at when the plan starts).  At the end —
also after an error, a stop or an abort — every motor returns to where it
started.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import bluesky.plan_stubs as bps
import bluesky.preprocessors as bpp
import numpy as np
from bluesky.utils import MsgGenerator

from bluesky_offsets.errors import InputError
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.physics.screen import as_screen, check_travel, moved
from bluesky_offsets.physics.twin import HistogramSpec
from bluesky_offsets.store import camera_floors, consistent_profiles

from .motion import (
    as_configurations,
    check_limits,
    limit_margins,
    move_to,
    pull_inside,
    read_setpoints,
    resolve_motors,
    resolve_stage,
    return_to,
    tolerances,
)


class CommandedConfiguration:
    """Readable holding the configuration being measured (index and twin-coordinate vector).

    Read with every frame, so that every event says which configuration it belongs to.
    """

    def __init__(self, n_parameters: int, name: str = "commanded", screen: bool = False):
        self.name = name
        self.parent = None
        self._index = -1
        self._vector = np.full(n_parameters, np.nan)
        self._screen = np.full(3, np.nan) if screen else None
        self._time = 0.0

    def update(self, index: int, vector: np.ndarray, screen: np.ndarray | None = None) -> None:
        """Hold configuration ``index`` (``vector``, and the screen's x, y, z where it has one), stamped now."""
        import time
        self._index, self._vector, self._time = int(index), np.asarray(vector, float), time.time()
        if self._screen is not None and screen is not None:
            self._screen = np.asarray(screen, float)

    def read(self) -> dict:
        """The held index, configuration vector (and screen position) as a Bluesky reading."""
        out = {"config_index": {"value": self._index, "timestamp": self._time},
               "configuration": {"value": self._vector, "timestamp": self._time}}
        if self._screen is not None:  # the stage's x, y, z: three numbers of their own
            out.update({f"screen_{a}": {"value": float(v), "timestamp": self._time}
                        for a, v in zip("xyz", self._screen)})
        return out

    def describe(self) -> dict:
        """The data keys :meth:`read` returns, with their dtype and shape."""
        out = {"config_index": {"source": "plan", "dtype": "integer", "shape": []},
               "configuration": {"source": "plan", "dtype": "array", "shape": [len(self._vector)],
                                 "dtype_numpy": "<f8"}}
        if self._screen is not None:
            out.update({f"screen_{a}": {"source": "plan", "dtype": "number", "shape": [], "units": "mm"}
                        for a in "xyz"})
        return out


def _signal_name(device, attr: str) -> str | None:
    sig = getattr(device, attr, None)
    return getattr(sig, "name", None) if sig is not None else None


def _optional_read(device, attr: str) -> MsgGenerator[Any]:
    sig = getattr(device, attr, None)
    if sig is None:
        return None
    try:
        value = yield from bps.rd(sig)
    except Exception:
        return None
    return value


def _reference_vector(reference, start: Mapping, table: ParameterTable) -> np.ndarray:
    if reference is None:  # the motors' readbacks are twin coordinates
        return table.from_mapping(start)
    if isinstance(reference, Mapping):
        return table.from_mapping(reference)
    return table.validate(reference, "reference configuration")


def _with_stage(beamline, motors: dict, screen) -> tuple[dict, dict | None]:
    """The scan's motors with the chamber's stage, and the stage's positions per frame.

    The stage is added when the beamline has one (positions None: no stage); a screen to move
    without a stage is refused.
    """
    stage = resolve_stage(beamline)
    if stage is None:
        if moved(screen):
            raise InputError("the beamline has no chamber stage (beamline.chamber_stage, or [stage] in the PV map): "
                             "frames with the screen moved cannot be taken")
        return motors, None
    return {**motors, **stage}, stage


def scan_configurations(configurations, beamline, chamber, *, reference=None, table: ParameterTable = METRIXS,
                        md: Mapping | None = None, keep_going: Callable[[int, dict], bool] | None = None,
                        read_motors: bool = True, return_to_start: bool = True,
                        finish: Callable[[Measurement], MsgGenerator[Any]] | None = None,
                        screen=None, more: Callable[[Measurement], MsgGenerator[Any]] | None = None
                        ) -> MsgGenerator[Measurement]:
    """Core of :func:`measure_configurations`, the on-beamline ray search and the beam optimizer.

    ``keep_going(index, reading)`` (optional) is called after each event and
    ends the scan early when it returns False.  ``return_to_start=False`` leaves the motors at
    the last configuration when the scan succeeds (a move the plan means to keep:
    :func:`plans.optimize.optimize_beam`), and returns them to the start when it fails;
    ``finish(measurement)`` runs inside the run after the last frame (results of the frames as
    streams of their own).  ``screen`` ((n, 3) mm): the chamber's stage per frame (its readbacks
    are the screen's twin coordinates, as the motors' are theirs); None leaves it where it stands.
    ``more(measurement)``: a plan run after the frames so far (``measurement``) that returns the
    next batch, ``(configurations, screen)``, or None to end; each batch is checked against the
    limits before anything moves (the designed measurement: :func:`plans.design.measure_designed`).
    """
    motors = resolve_motors(beamline, table)
    configs = as_configurations(configurations, table)
    motors, stage = _with_stage(beamline, motors, screen)
    tolerance = yield from tolerances(motors)
    start = yield from read_setpoints(motors, tolerance)
    ref = _reference_vector(reference, {n: v for n, v in start.items() if n in table.names}, table)
    col = {n: table.index(n) for n in motors if n not in (stage or {})}
    margin = yield from limit_margins(motors)

    def plan_targets(cfgs, scr):
        """Each frame's motor targets and stage positions (None: no stage), checked against the limits.

        They are kept a margin inside them (:func:`plans.motion.pull_inside`; the configurations follow).
        """
        cfgs = np.array(as_configurations(cfgs, table), dtype=float)
        tgts = [{n: start[n] + (cfg[col[n]] - ref[col[n]]) for n in col} for cfg in cfgs]
        scrs = None
        if stage is not None:
            here = np.array([start[n] for n in stage])
            scrs = np.tile(here, (len(cfgs), 1)) if scr is None else np.array(as_screen(scr, len(cfgs)), float)
            check_travel(scrs)
            for t, row in zip(tgts, scrs):
                t.update(zip(stage, map(float, row)))
        elif moved(scr):
            raise InputError("the beamline has no chamber stage: frames with the screen moved cannot be taken")
        yield from check_limits(motors, tgts)  # all of them, before anything moves
        inside = yield from pull_inside(motors, tgts, margin)
        for k, (t, new) in enumerate(zip(tgts, inside)):
            for n in col:
                cfgs[k, col[n]] += new[n] - t[n]
            for i, n in enumerate(stage or ()):
                scrs[k, i] += new[n] - t[n]
        return cfgs, inside, scrs

    configs, targets, screens = yield from plan_targets(configs, screen)
    commanded = CommandedConfiguration(len(table), screen=stage is not None)
    _md = yield from _scan_md(chamber, table, motors, start, ref, configs, screens)
    _md.update(md or {})

    readings: list[dict] = []
    devices = [chamber, commanded, *(motors.values() if read_motors else ())]

    # where the motors stand: known after each verified move, unknown while one is under way
    # (a pause, an abort, a failed move): then every motor is commanded (motion.move_to)
    here: dict = {"at": dict(start)}

    def frames(cfgs, tgts, scrs):
        for cfg, target, scr in zip(cfgs, tgts, scrs if scrs is not None else [None] * len(cfgs)):
            yield from bps.checkpoint()  # a paused scan resumes at this configuration
            at, here["at"] = here["at"], None
            yield from move_to(motors, target, tolerance=tolerance, current=at)
            here["at"] = target
            commanded.update(len(readings), cfg, scr)
            reading = yield from bps.trigger_and_read(devices)
            readings.append(reading)
            if keep_going is not None and not keep_going(len(readings) - 1, reading):
                return False
        return True

    def body():
        going = yield from frames(configs, targets, screens)
        while going and more is not None:
            batch = yield from more(_measurement(readings, table, None, _md))
            if batch is None:
                break
            going = yield from frames(*(yield from plan_targets(*batch)))
        if finish is not None:
            yield from finish(_measurement(readings, table, None, _md))

    run = bpp.run_wrapper(body(), md=_md)

    def back():  # reads ``here`` when it runs, not when the wrapper is built
        yield from return_to(motors, start, current=here["at"])

    if return_to_start:
        uid = yield from bpp.finalize_wrapper(run, back)
    else:  # kept where the scan ends, unless it fails: then back where they started
        uid = yield from bpp.contingency_wrapper(run, except_plan=lambda exc: back())
    return _measurement(readings, table, uid, _md)


def _scan_md(chamber, table: ParameterTable, motors, start, ref, configs, screens) -> MsgGenerator[dict]:
    """The scan's start document.

    The table, the configurations and the reference, where the motors started, which signals hold
    what, and what the detector says of itself.
    """
    truth_id = yield from _optional_read(chamber, "truth_id")
    n_rays = yield from _optional_read(chamber, "num_rays")
    profile_axes = []
    for axis in "xy":
        profile_axes.append((yield from _optional_read(chamber, f"profile_axis_{axis}")))
    hist = HistogramSpec()
    _md = {
        "plan_name": "measure_configurations",
        "purpose": "offset finding: footprints at known configuration differences",
        "parameter_table": table.name,
        "parameter_table_version": table.version,
        "parameter_names": list(table.names),
        "configurations": configs.tolist(),
        **({"screens": screens.tolist()} if screens is not None else {}),
        "n_configurations": len(configs),
        "reference": ref.tolist(),
        # start documents allow no dots in keys: per-motor values as lists in table order
        "motorized_names": list(motors),
        "start_positions": [start[n] for n in motors],
        "motor_names": [getattr(m, "name", str(m)) for m in motors.values()],
        "detectors": [getattr(chamber, "name", str(chamber))],
        "hist_keys": {k: v for k, v in {"x": _signal_name(chamber, "hist_x"), "y": _signal_name(chamber, "hist_y"),
                                        "counts": _signal_name(chamber, "total_counts"),
                                        "image": _signal_name(chamber, "image"),
                                        "profile_x": _signal_name(chamber, "profile_x"),
                                        "profile_y": _signal_name(chamber, "profile_y")}.items() if v},
        "histogram": hist.fingerprint(),
        "image_shape": [hist.bins_y, hist.bins_x],
        "hints": {"dimensions": [(["time"], "primary")]},
    }
    if all(ax is not None and len(ax) > 1 for ax in profile_axes):
        # the camera-resolution profiles' binning, as the detector publishes it
        _md["profile"] = HistogramSpec.from_centers(*profile_axes).fingerprint()
    if truth_id:
        _md["truth_id"] = str(truth_id)
    if n_rays is not None:
        _md["n_rays"] = int(n_rays)
    return _md


def _value(reading: dict, suffix: str, preferred: str | None):
    if preferred and preferred in reading:
        return reading[preferred]["value"]
    keys = [k for k in reading if k.endswith("-" + suffix) or k.endswith("_" + suffix) or k == suffix]
    if len(keys) != 1:
        raise KeyError(f"cannot find the {suffix!r} reading among {sorted(reading)}")
    return reading[keys[0]]["value"]


def _measurement(readings, table, uid, md) -> Measurement:
    """The frames of ``readings``, each at the configuration (and stage position) it was taken at."""
    keys = md.get("hist_keys", {})
    n = len(readings)
    if n == 0:
        return Measurement(np.zeros((0, len(table))), np.zeros((0, 50)), np.zeros((0, 50)), names=table.names,
                           uid=uid, metadata=md)
    hx = np.array([_value(r, "hist_x", keys.get("x")) for r in readings], dtype=float)
    hy = np.array([_value(r, "hist_y", keys.get("y")) for r in readings], dtype=float)
    try:
        counts = np.array([_value(r, "total_counts", keys.get("counts")) for r in readings])
    except KeyError:
        counts = None
    cfgs = np.array([r["configuration"]["value"] for r in readings], dtype=float)
    scr = (np.array([[r[f"screen_{a}"]["value"] for a in "xyz"] for r in readings], dtype=float)
           if "screen_x" in readings[0] else None)
    px = py = None
    if md.get("profile"):
        try:
            px, py = consistent_profiles([_value(r, "profile_x", keys.get("profile_x")) for r in readings],
                                         [_value(r, "profile_y", keys.get("profile_y")) for r in readings],
                                         md["profile"], hx, hy)
        except KeyError:
            pass
    floors = camera_floors(lambda key: [_value(r, key, None) for r in readings], px is not None)
    return Measurement(cfgs, hx, hy, names=table.names, uid=uid, total_counts=counts, metadata=dict(md),
                       profile_x=px, profile_y=py, screen=scr, **floors)


def measure_configurations(configurations, beamline, chamber, *, reference=None,
                           table: ParameterTable = METRIXS, md: Mapping | None = None,
                           read_motors: bool = True, screen=None) -> MsgGenerator[Measurement]:
    """Measure both focus-chamber histograms at each configuration; one event per configuration.

    Parameters
    ----------
    configurations : array_like or sequence of mapping
        ``(n, 34)`` configurations in twin coordinates (table order), ``(n, 28)``
        motorized values, or ``{parameter name: value}`` mappings.  Fixed
        parameters stay at their design values.
    beamline : mapping or device
        Motors by parameter name or device path (see :mod:`plans.motion`).
    chamber : Triggerable and Readable
        The focus-chamber detector; its readings must include ``hist_x`` and
        ``hist_y`` (data keys ending in those names).
    reference : array_like or mapping, optional
        Twin-coordinate configuration the motors stand at when the plan starts;
        default: their readbacks.  Motor *i* goes to ``start_i + (config_i - reference_i)``.
    table : ParameterTable
        Parameter table (default METRIXS).
    md : mapping, optional
        Extra run metadata.
    read_motors : bool
        Also record every motor's readback in each event (default True).
    screen : array_like, shape (n, 3), optional
        The focus chamber's stage (x, y, z in mm, its readbacks' coordinates) per configuration;
        default: where it stands.  Needs a beamline with a stage (:func:`plans.motion.resolve_stage`).

    Returns
    -------
    Measurement
        The configurations and histograms just taken (also in the run store
        when a ``TiledWriter`` is subscribed); ``uid`` is the run's uid.

    Notes
    -----
    Run metadata: ``parameter_table_version``, ``parameter_names``,
    ``configurations``, ``reference``, ``start_positions``, ``truth_id``
    (simulation only, read from the chamber), ``hist_keys``.  All targets are
    checked against the motor limits before anything moves; a violation raises
    :class:`plans.motion.MotorLimitError` and leaves every motor where it was.
    """
    return (yield from scan_configurations(configurations, beamline, chamber, reference=reference,
                                           table=table, md=md, read_motors=read_motors, screen=screen))
