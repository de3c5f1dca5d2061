"""The simulated METRIXS beamline as a caproto IOC.

``python -m sim_iocs.metrixs --prefix BL: [--list-pvs]`` (or
``bluesky-offsets ioc ...``) serves

* one motor record per motorized parameter of the table (28):
  ``BL:<component>:<axis>`` after the parameter's ``device`` path
  (``E1.rotationXerror`` -> ``BL:e1:rx``), soft limits = the motor travel (the table's box; wider for the slit openings);
* the focus chamber's translation stage: motor records ``BL:chamber:x``, ``BL:chamber:y`` and
  ``BL:chamber:z`` (mm; :data:`bluesky_offsets.physics.screen.STAGE`), standing at 0 at start;
  the screen truly stands at their position plus the chamber's hidden displacement (an effect);
* the focus chamber's camera as an areaDetector, ``BL:cam:cam1:*`` and ``BL:cam:HDF1:*``
  (:mod:`sim_iocs.camera`);
* the focus-chamber detector ``BL:chamber:*``: ``Acquire`` (put-completion
  when the frame is ready), ``NumRays`` (ray budget), ``AcquireTime``,
  ``HistX``/``HistY`` (50 bins each, fraction of source rays per bin),
  ``Image`` (50 x 50, row-major y then x), ``TotalCounts``, ``AxisX``/``AxisY``
  (bin centres, mm), ``ProfileX``/``ProfileY`` (the same footprint at the camera's
  resolution, 20 µm x 5 µm bins over the same window, with ``ProfileAxisX``/``ProfileAxisY``),
  ``Status``/``Message``, ``ArrayCounter``, ``TruthId``.

Every frame is computed for the *true* state: motor positions plus hidden
offsets, the hidden true values of the six fixed parameters, and hidden
physical effects (:mod:`sim_iocs.truth`), by a backend (:mod:`sim_iocs.backends`,
the RAYX twin by default) in a worker process, with a fresh random seed per
frame.  Ports and interfaces follow the usual EPICS environment variables
(``EPICS_CAS_SERVER_PORT``, ``EPICS_CA_SERVER_PORT``; ``EPICS_CAS_INTF_ADDR_LIST`` unless
``--interfaces`` is given; loopback when neither is); beacons go to the served loopback
interface unless ``EPICS_CAS_BEACON_ADDR_LIST`` says otherwise.

The hidden truth stays hidden from the IOC's clients: no PV, message or file tells it (a
state no beamline can be in, such as a slit driven past closed, gives a dark frame like any
other), and what the operator of the simulation may read goes to ``--truth-log FILE`` only.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import logging
import math
import os
import signal
import socket
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from caproto import ChannelType
from caproto.server import PVGroup, pvproperty
from caproto._data import SkipWrite

from bluesky_offsets.physics.parameters import METRIXS, ParameterError, ParameterTable
from bluesky_offsets.physics.screen import STAGE
from bluesky_offsets.physics.twin import CAMERA, HistogramSpec

from .backends import FootprintBackend, Frame, FrameAborted, make_backend
from .camera import FocusCamera
from .motor_record import AxisSettings, Mechanics, MotorRecord, StrictDouble, StrictLong
from .truth import Truth

log = logging.getLogger("sim_iocs.metrixs")


class RefusedPutInOneLine(logging.Filter):
    """Log filter that shortens caproto's record of a refused put to one line.

    caproto logs a refused put with its whole traceback (25 lines a put); the refusal's own
    message names the field and the reason, so one line says it.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        """Rewrite a refused put's record as one line without its traceback; let every record through."""
        if record.exc_info and str(record.msg).startswith("Invalid write request"):
            ex = record.exc_info[1]
            args = record.args if isinstance(record.args, tuple) else ()  # caproto passes a tuple
            user, host = (args or ("?", "?"))[:2]
            record.msg, record.args = "refused put by %s (%s): %s: %s", (user, host, type(ex).__name__, ex)
            record.exc_info = record.exc_text = None
        return True


class BeaconRefusedOnce(logging.Filter):
    """Log filter that reports a refused beacon once per address, in one line.

    caproto logs every beacon that no CA repeater receives with its traceback, again at each
    beacon period (15 s): one line the first time for each address says it; clients find the IOC by
    their own searches all the same.
    """

    def __init__(self):
        super().__init__()
        self._seen: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        """Pass a failed beacon's record once per address, as a one-line warning; pass every other record."""
        if not str(record.msg).startswith("Failed to send beacon"):
            return True
        where = str(record.args[0]) if isinstance(record.args, tuple) and record.args else "?"
        if where in self._seen:
            return False
        self._seen.add(where)
        record.msg, record.args = "beacons to %s are refused: no CA repeater listens there (yet); clients " \
                                  "searching this host still find the IOC", (where,)
        record.levelno, record.levelname = logging.WARNING, "WARNING"
        record.exc_info = record.exc_text = None
        return True


HIST = HistogramSpec()
DEFAULT_PREFIX = "SIM:METRIXS:"
MAX_RAYS = 1_000_000  # per frame: RAYX's worker holds ~4 kB per ray (≈4 GB at the bound)
MAX_ACQUIRE_TIME = 3600.0  # s
CHAMBER = "chamber:"
CAMERA_PREFIX = "cam:"
STATUS = ("Idle", "Acquiring", "Error", "Aborted")


def motor_pv(param, prefix: str = "") -> str:
    """Record name of a motorized parameter: its ``device`` path with ``:`` separators."""
    return prefix + param.device.replace(".", ":")


def axis_settings(param, start: float, *, move_time: float = 4.0, accel_time: float = 0.2) -> AxisSettings:
    """Motor-record settings for one parameter.

    Soft limits = its travel (the table's box except for the slit openings), a full-travel move
    takes ``move_time`` seconds, resolution 1e-5 of the box's order of magnitude.
    """
    resolution = 10.0 ** (math.floor(math.log10(param.high - param.low)) - 5)
    low, high = param.limits
    span = high - low
    return AxisSettings(description=f"{param.name}"[:40], egu=param.unit, low=low, high=high,
                        start=float(start), velocity=span / move_time, accel_time=accel_time,
                        resolution=resolution)


def stage_settings(axis, *, move_time: float = 4.0, accel_time: float = 0.2) -> AxisSettings:
    """Motor-record settings of one axis of the chamber's stage (:data:`bluesky_offsets.physics.screen.STAGE`).

    At 0 at start, 0.1 µm steps, a full-travel move in ``move_time`` seconds.
    """
    return AxisSettings(description=f"chamber stage {axis.name}", egu=axis.unit, low=axis.low, high=axis.high,
                        start=0.0, velocity=axis.span / move_time, accel_time=accel_time, resolution=1e-4)


MOTOR_PROFILES = ("perfect", "realistic")
"""``--motors``: perfect axes, or every axis as a typical encoder-read stage (:func:`motor_profile`)."""


def motor_profile(kind: str, settings: AxisSettings) -> tuple[Mechanics, AxisSettings]:
    """The mechanics and record settings of one axis under a ``--motors`` profile.

    ``realistic``, in steps of the axis's resolution ``MRES`` (10 nm on a 2 mm travel): an
    encoder read with 3 steps of noise (σ), 200 steps of backlash taken out by a final approach of
    ``BDST`` = 400 steps, retries (``RTRY`` 10) until within ``RDBD`` = 10 steps.
    """
    if kind not in MOTOR_PROFILES:
        raise ParameterError(f"--motors must be one of {', '.join(MOTOR_PROFILES)}, got {kind!r}")
    if kind == "perfect":
        return Mechanics(), settings
    r = settings.resolution
    return (Mechanics(encoder=True, readback_noise=3 * r, backlash=200 * r),
            dataclasses.replace(settings, deadband=10 * r, backlash_distance=400 * r))


def _zeros(n):
    return [0.0] * n


class FocusChamber(PVGroup):
    """Focus-chamber screen: histograms and image of the footprint, one frame per ``Acquire``.

    Parameters
    ----------
    state : callable
        Returns the true parameter vector (table order) at the moment a frame starts.
    backend : FootprintBackend
        Computes frames (the twin, or a surrogate).
    truth_id : str
        Published hash of the hidden truth.
    """

    acquire = pvproperty(value="Done", name="Acquire", dtype=ChannelType.ENUM, enum_strings=("Done", "Acquire"),
                         doc="Acquire one frame (put-completion when ready); write 0 to abort")
    acquire_time = pvproperty(value=0.0, name="AcquireTime", dtype=StrictDouble, units="s", precision=3,
                              doc="Minimum duration of a frame (s)")
    num_rays = pvproperty(value=10000, name="NumRays", dtype=StrictLong,
                          doc="Ray budget: source rays per frame")
    hist_x = pvproperty(value=_zeros(HIST.bins_x), name="HistX", read_only=True, max_length=HIST.bins_x,
                        doc="x histogram, fraction of source rays per bin")
    hist_y = pvproperty(value=_zeros(HIST.bins_y), name="HistY", read_only=True, max_length=HIST.bins_y,
                        doc="y histogram, fraction of source rays per bin")
    image = pvproperty(value=_zeros(HIST.bins_x * HIST.bins_y), name="Image", read_only=True,
                       max_length=HIST.bins_x * HIST.bins_y, doc="2-D histogram, rows y, columns x")
    size_x = pvproperty(value=HIST.bins_x, name="ImageSizeX", dtype=ChannelType.LONG, read_only=True)
    size_y = pvproperty(value=HIST.bins_y, name="ImageSizeY", dtype=ChannelType.LONG, read_only=True)
    axis_x = pvproperty(value=HIST.centers_x.tolist(), name="AxisX", read_only=True, max_length=HIST.bins_x,
                        units="mm", precision=3, doc="x bin centres (mm)")
    profile_x = pvproperty(value=_zeros(CAMERA.bins_x), name="ProfileX", read_only=True, max_length=CAMERA.bins_x,
                           doc="x profile at the camera's resolution, fraction of source rays per bin")
    profile_y = pvproperty(value=_zeros(CAMERA.bins_y), name="ProfileY", read_only=True, max_length=CAMERA.bins_y,
                           doc="y profile at the camera's resolution, fraction of source rays per bin")
    profile_axis_x = pvproperty(value=CAMERA.centers_x.tolist(), name="ProfileAxisX", read_only=True,
                                max_length=CAMERA.bins_x, units="mm", precision=4, doc="x profile bin centres (mm)")
    profile_axis_y = pvproperty(value=CAMERA.centers_y.tolist(), name="ProfileAxisY", read_only=True,
                                max_length=CAMERA.bins_y, units="mm", precision=4, doc="y profile bin centres (mm)")
    axis_y = pvproperty(value=HIST.centers_y.tolist(), name="AxisY", read_only=True, max_length=HIST.bins_y,
                        units="mm", precision=3, doc="y bin centres (mm)")
    total_counts = pvproperty(value=0, name="TotalCounts", dtype=ChannelType.LONG, read_only=True,
                              doc="Rays on the screen in the last frame")
    transmission = pvproperty(value=0.0, name="Transmission", read_only=True, precision=4,
                              doc="TotalCounts / NumRays")
    array_counter = pvproperty(value=0, name="ArrayCounter", dtype=ChannelType.LONG, read_only=True,
                               doc="Frames completed")
    frame_time = pvproperty(value=0.0, name="FrameTime", read_only=True, units="s", precision=3,
                            doc="Computing time of the last frame")
    status = pvproperty(value="Idle", name="Status", dtype=ChannelType.ENUM, enum_strings=STATUS, read_only=True)
    message = pvproperty(value="", name="Message", dtype=str, max_length=256, report_as_string=True,
                         read_only=True)
    truth_id = pvproperty(value="", name="TruthId", dtype=ChannelType.STRING, read_only=True,
                          doc="Hash of the hidden truth (the truth itself is never published)")
    table_version = pvproperty(value=METRIXS.version, name="TableVersion", dtype=ChannelType.STRING,
                               read_only=True, doc="Parameter-table version")
    backend_name = pvproperty(value="", name="Backend", dtype=str, max_length=128, report_as_string=True,
                              read_only=True)

    def __init__(self, *args, state: Callable[[], np.ndarray], backend: FootprintBackend, truth_id: str,
                 table: ParameterTable = METRIXS, n_rays: int = 10000, max_rays: int = MAX_RAYS,
                 truth_log: Callable[[str], None] | None = None,
                 screen: Callable[[], np.ndarray] | None = None, hist: HistogramSpec = HIST,
                 camera: HistogramSpec = CAMERA, **kwargs):
        super().__init__(*args, **kwargs)
        if (hist.bins_x, hist.bins_y, camera.bins_x, camera.bins_y) != (HIST.bins_x, HIST.bins_y, CAMERA.bins_x,
                                                                         CAMERA.bins_y):
            raise ValueError(f"the simulated chamber serves {HIST.bins_x} x {HIST.bins_y} bins and "
                             f"{CAMERA.bins_x} x {CAMERA.bins_y} profile pixels; the detector asks for "
                             f"{hist.bins_x} x {hist.bins_y} and {camera.bins_x} x {camera.bins_y}")
        self._hist, self._camera = hist, camera
        self._state = state
        self._screen = screen or (lambda: np.zeros(3))
        self.backend = backend
        self._truth_id = truth_id
        self._table = table
        self._max_rays = int(max_rays)
        if not 0 <= int(n_rays) <= self._max_rays:
            raise ValueError(f"the ray budget must lie in [0, {self._max_rays}], got {n_rays}")
        self._n_rays = int(n_rays)
        # what only the simulation's operator may read (true values); default: nowhere
        self._truth_log = truth_log or (lambda text: None)
        self._frame: asyncio.Task | None = None
        self._abort = asyncio.Event()

    @acquire.startup
    async def acquire(self, instance, async_lib):
        """Publish the truth id, table version, axes and limits at startup, and warm up the backend."""
        await self.truth_id.write(self._truth_id)
        await self.table_version.write(self._table.version)
        for pv, axis in ((self.axis_x, self._hist.centers_x), (self.axis_y, self._hist.centers_y),
                         (self.profile_axis_x, self._camera.centers_x), (self.profile_axis_y, self._camera.centers_y)):
            await pv.write(axis.tolist())
        await self.backend_name.write(self.backend.name)
        await self.num_rays.write_metadata(lower_ctrl_limit=0, upper_ctrl_limit=self._max_rays)
        await self.acquire_time.write_metadata(lower_ctrl_limit=0.0, upper_ctrl_limit=MAX_ACQUIRE_TIME)
        await self.num_rays.write(self._n_rays)
        await self.message.write("warming up the backend")
        try:  # warm the worker (imports, first trace) so the first real frame is quick
            await asyncio.wrap_future(self.backend.submit(self._state(), 100))
            await self.message.write("ready")
        except Exception as exc:  # reported, the IOC keeps serving
            self._truth_log(f"backend failed to start: {exc}")
            await self.status.write("Error")
            await self.message.write("backend failed to start (see the IOC's log)")
        self._drain_notes()

    @num_rays.putter
    async def num_rays(self, instance, value):
        """Take a ray budget within [0, the IOC's maximum]."""
        if not 0 <= value <= self._max_rays:
            raise ValueError(f"NumRays must lie in [0, {self._max_rays}], got {value}")
        return value

    @acquire_time.putter
    async def acquire_time(self, instance, value):
        """Take a finite acquisition time within [0, ``MAX_ACQUIRE_TIME``] s."""
        if not (math.isfinite(value) and 0 <= value <= MAX_ACQUIRE_TIME):
            raise ValueError(f"AcquireTime must lie in [0, {MAX_ACQUIRE_TIME:g}] s, got {value}")
        return value

    def _drain_notes(self) -> None:
        notes = getattr(self.backend, "notes", None)
        while notes:
            self._truth_log(notes.pop(0))

    @acquire.putter
    async def acquire(self, instance, value):
        """Take a frame (completing when it is done), or abort the frame being taken with ``Done``."""
        if value == "Done":
            if self._frame is not None and not self._frame.done():
                self._abort.set()
                abort = getattr(self.backend, "abort", None)
                if abort is not None:  # stop the tracing itself, not only the wait for it
                    abort()
            return SkipWrite
        if self._frame is None or self._frame.done():
            self._abort.clear()
            await instance.write("Acquire", verify_value=False)
            self._frame = asyncio.get_running_loop().create_task(self._acquire())
        # A second Acquire during a frame completes with that frame.  The frame task
        # owns the outcome, so a client that goes away does not cancel it.
        ok, msg = await asyncio.shield(self._frame)
        if not ok:
            raise RuntimeError(msg)
        return SkipWrite

    async def _acquire(self) -> tuple[bool, str]:
        t0 = time.monotonic()
        n_rays = int(self.num_rays.value)
        await self.status.write("Acquiring")
        try:
            values, screen = self._state(), np.asarray(self._screen(), float)
            if n_rays == 0:
                frame = Frame.dark(HIST, 0)
            else:
                fut = asyncio.wrap_future(submit_frame(self.backend, values, n_rays, screen))
                abort = asyncio.ensure_future(self._abort.wait())
                done, _ = await asyncio.wait({fut, abort}, return_when=asyncio.FIRST_COMPLETED)
                abort.cancel()
                if fut not in done:
                    fut.cancel()  # a queued frame never starts; a running one was stopped by abort()
                    raise _Aborted()
                try:
                    frame = fut.result()
                except FrameAborted:
                    raise _Aborted() from None
            rest = self.acquire_time.value - (time.monotonic() - t0)
            if rest > 0:
                try:
                    await asyncio.wait_for(self._abort.wait(), rest)
                    raise _Aborted()
                except asyncio.TimeoutError:
                    pass
            await self._publish(frame, time.monotonic() - t0)
            return True, "ok"
        except _Aborted:
            await self.status.write("Aborted")
            await self.message.write("acquisition aborted")
            await self.acquire.write("Done", verify_value=False)
            return False, "acquisition aborted"
        except Exception as exc:
            reset = getattr(self.backend, "reset", None)
            if reset is not None:
                reset()  # a fresh worker for the next frame
            # the cause may name true values: it goes to the operator's log only
            self._truth_log(f"frame failed: {type(exc).__name__}: {exc}")
            log.error("acquisition failed (details in the truth log, if one was chosen)")
            msg = "acquisition failed: the beamline model raised an error"
            await self.status.write("Error")
            await self.message.write(msg)
            await self.acquire.write("Done", verify_value=False)
            return False, msg
        finally:
            self._drain_notes()

    async def _publish(self, frame: Frame, seconds: float):
        ts = time.time()  # one timestamp for the whole frame
        hx = np.nan_to_num(np.asarray(frame.hist_x, float))
        hy = np.nan_to_num(np.asarray(frame.hist_y, float))
        img = (np.zeros((HIST.bins_y, HIST.bins_x)) if frame.image is None
               else np.nan_to_num(np.asarray(frame.image, float)))
        await self.image.write(img.ravel().tolist(), timestamp=ts)
        # a backend without rays (the surrogate) has no profiles: zeros, which the loaders
        # recognize as inconsistent with the histograms and ignore
        for pv, prof, n in ((self.profile_x, frame.profile_x, CAMERA.bins_x),
                            (self.profile_y, frame.profile_y, CAMERA.bins_y)):
            await pv.write((np.zeros(n) if prof is None else np.nan_to_num(np.asarray(prof, float))).tolist(),
                           timestamp=ts)
        await self.hist_x.write(hx.tolist(), timestamp=ts)
        await self.hist_y.write(hy.tolist(), timestamp=ts)
        await self.total_counts.write(int(frame.n_hits), timestamp=ts)
        await self.transmission.write(frame.n_hits / frame.n_rays if frame.n_rays else 0.0, timestamp=ts)
        await self.frame_time.write(seconds, timestamp=ts)
        await self.array_counter.write(self.array_counter.value + 1, timestamp=ts)
        note = "" if frame.image is not None else " (backend gives no image)"
        note += "" if frame.profile_x is not None else " (backend gives no profiles)"
        await self.message.write(f"frame {self.array_counter.value}: {frame.n_hits} of {frame.n_rays} rays"
                                 f"{note}", timestamp=ts)
        await self.status.write("Idle", timestamp=ts)
        await self.acquire.write("Done", verify_value=False, timestamp=ts)


class _Aborted(Exception):
    pass


def submit_frame(backend: FootprintBackend, values: np.ndarray, n_rays: int, screen: np.ndarray):
    """``backend.submit`` with the chamber's stage where it stands.

    A backend that cannot move the screen (a plugged-in one without a ``screen`` argument) is asked
    only while the stage is at 0.
    """
    if not np.any(screen):
        return backend.submit(values, n_rays)
    try:
        return backend.submit(values, n_rays, screen=screen)  # type: ignore[call-arg]  # optional to the protocol
    except TypeError as exc:
        if "screen" not in str(exc):
            raise
        raise RuntimeError(f"backend {backend.name!r} cannot move the screen (its submit takes no screen)") from None


class MetrixsIOC:
    """The 28 motor records and the focus chamber, with one hidden truth.

    Parameters
    ----------
    prefix : str
        PV prefix (``"BL:"`` gives ``BL:e1:rx``, ``BL:chamber:Acquire``).
    truth : Truth
        Hidden offsets, effects and start positions.
    backend : FootprintBackend or str
        Footprint model (default: the twin).
    n_rays : int
        Initial ray budget per frame.
    move_time, accel_time, tick : float
        A full-range move takes ``move_time`` s; ``ACCL``; readback update period.
    noise_seed : int, optional
        Seeds the frames' ray noise (a backend named by string); default: fresh from the OS.
    max_rays : int
        Upper bound of ``NumRays`` (memory: RAYX holds ~4 kB per ray).
    truth_log : callable, optional
        Receives the notes that name true values (impossible states, model errors).
    leave_out : sequence of str
        Motorized parameters served without a motor record (a beamline with a record
        missing, for ``bluesky-offsets check-pvs``): they stay where the truth starts them.
    """

    def __init__(self, prefix: str = DEFAULT_PREFIX, truth: Truth | None = None,
                 backend: FootprintBackend | str = "twin", *, table: ParameterTable = METRIXS,
                 n_rays: int = 10000, move_time: float = 4.0, accel_time: float = 0.2, tick: float = 0.05,
                 noise_seed: int | None = None, max_rays: int = MAX_RAYS,
                 truth_log: Callable[[str], None] | None = None, leave_out: Sequence[str] = (),
                 motors: str = "perfect", beamline=None):
        self.prefix = prefix
        self.beamline = beamline
        self.table = table = beamline.table if beamline is not None else table
        hist, camera = (beamline.detector.histograms, beamline.detector.camera) if beamline is not None else \
            (HIST, CAMERA)
        self.truth = truth or Truth.from_seed(None, table)
        if isinstance(backend, str):
            backend = make_backend(backend, overrides=self.truth.overrides, hist=hist, noise_seed=noise_seed,
                                   beamline=None if beamline is None or beamline.builtin else str(beamline.path))
        self.backend = backend
        unknown = [n for n in leave_out if n not in table.motorized_names]
        if unknown:
            raise ValueError(f"--leave-out: {', '.join(unknown)} are not motorized parameters")
        self.motors: dict[str, MotorRecord] = {}
        self._fixed_start = np.array(self.truth.start, dtype=float)

        def record(name, pv, settings, k):
            mechanics, settings = motor_profile(motors, settings)
            rng = None if noise_seed is None else [noise_seed, 7, k]  # the encoders' own stream
            return MotorRecord(prefix=pv, settings=settings, tick=tick, name=name, rng=rng,
                               mechanics=self.truth.mechanics(name, mechanics))

        for i, p in enumerate(table):
            if p.motorized and p.name not in leave_out:
                settings = axis_settings(p, self._fixed_start[i], move_time=move_time, accel_time=accel_time)
                self.motors[p.name] = record(p.name, motor_pv(p, prefix), settings, i)
        self.stage = {ax.name: record(f"chamber.{ax.name}", f"{prefix}{CHAMBER}{ax.name}",
                                      stage_settings(ax, move_time=move_time, accel_time=accel_time), len(table) + k)
                      for k, ax in enumerate(STAGE)}
        self.chamber = FocusChamber(prefix=prefix + CHAMBER, state=self.true_state, backend=backend,
                                    truth_id=self.truth.truth_id, table=table, n_rays=n_rays, max_rays=max_rays,
                                    truth_log=truth_log, screen=self.screen, hist=hist, camera=camera,
                                    name="chamber")
        self.camera = FocusCamera(prefix + CAMERA_PREFIX, trace=self._trace, max_rays=max_rays,
                                  rng=np.random.default_rng(None if noise_seed is None else [noise_seed, 11]))
        self.pvdb = {}
        for group in (*self.motors.values(), *self.stage.values(), self.chamber, self.camera):
            self.pvdb.update(group.pvdb)

    def _trace(self, n_rays: int):
        """A frame of ``n_rays`` at the true state, the screen where the stage stands (a future)."""
        return submit_frame(self.backend, self.true_state(), n_rays, self.screen())

    def positions(self) -> np.ndarray:
        """Physical axis positions, table order (fixed parameters at design value)."""
        pos = self.table.reference.copy()
        for name in self.table.motorized_names:  # a left-out motor stands where the truth started it
            pos[self.table.index(name)] = self._fixed_start[self.table.index(name)]
        for name, m in self.motors.items():
            pos[self.table.index(name)] = m.axis_position
        return pos

    def true_state(self) -> np.ndarray:
        """The true parameter vector at the motors' present positions (the hidden truth applied)."""
        return self.truth.true_values(self.positions())

    def screen(self) -> np.ndarray:
        """The chamber stage's x, y, z (mm); the hidden displacement of the chamber adds to it."""
        return np.array([self.stage[ax.name].axis_position for ax in STAGE])

    def describe(self) -> str:
        """Human-readable list of the records and detector PVs."""
        lines = [f"{len(self.motors)} motor records (fields: .VAL .RBV .DVAL .DRBV .OFF .DIR .DMOV .MOVN .STOP "
                 ".SPMG .HLM .LLM .DHLM .DLLM .LVIO .VELO .ACCL .TWV .TWF .TWR .RLV .EGU .DESC .PREC .MRES "
                 ".RDBD .MSTA ...):"]
        for name, m in self.motors.items():
            s = m.settings
            lines.append(f"  {m.prefix:28s} {name:32s} [{s.low:g}, {s.high:g}] {s.egu}")
        lines.append("focus-chamber stage (motor records):")
        for name, m in self.stage.items():
            s = m.settings
            lines.append(f"  {m.prefix:28s} {'chamber.' + name:32s} [{s.low:g}, {s.high:g}] {s.egu}")
        lines.append("focus-chamber detector:")
        for pv, inst in self.chamber.pvdb.items():
            n = getattr(inst, "max_length", 1) or 1
            kind = type(inst).__name__.replace("Pvproperty", "").replace("RO", " (read-only)")
            lines.append(f"  {pv:34s} {kind}{f'[{n}]' if n > 1 else ''}")
        lines.append(f"focus-chamber camera (areaDetector: {self.camera.prefix}cam1:, {self.camera.prefix}HDF1:, "
                     f"{len(self.camera.pvdb)} PVs)")
        return "\n".join(lines)

    def close(self) -> None:
        """Close the backend and its workers."""
        self.backend.close()


# --------------------------------------------------------------------------- #
# command line
# --------------------------------------------------------------------------- #
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the IOC's command-line options to ``parser``."""
    parser.add_argument("--prefix", default=DEFAULT_PREFIX, help=f"PV prefix (default {DEFAULT_PREFIX})")
    parser.add_argument("--beamline", default=None, metavar="FILE|NAME",
                        help="serve a described beamline (a TOML file, or a shipped one: energize) instead of "
                             "METRIXS: its motors, its RML traced by RAYX, its detector window")
    parser.add_argument("--list-pvs", action="store_true", help="print the records and detector PVs at start-up")
    src = parser.add_mutually_exclusive_group()
    src.add_argument("--truth", metavar="FILE.json", help="hidden offsets/effects/start positions (JSON)")
    src.add_argument("--seed-file", metavar="FILE",
                     help=f"draw hidden offsets of all the parameters (METRIXS: 34) from the integer seed in FILE (or "
                          f"${SEED_VARIABLE}; default: a random seed); never on the command line, where "
                          f"every process could read it")
    src.add_argument("--seed", type=int, help=argparse.SUPPRESS)  # refused: see _seed
    parser.add_argument("--max-offset", type=float, default=0.2,
                        help="largest drawn offset, fraction of each range (default 0.2, the paper's)")
    parser.add_argument("--dump-truth", metavar="FILE.json",
                        help="write the hidden truth to FILE (for evaluating a finder later) and go on")
    parser.add_argument("--backend", default="twin",
                        help="footprint model: 'twin' (default), 'surrogate[:CHECKPOINT]' or module:factory")
    parser.add_argument("--rays", type=int, default=10000, help="initial ray budget per frame (NumRays)")
    parser.add_argument("--max-rays", type=int, default=MAX_RAYS,
                        help=f"upper bound of NumRays (default {MAX_RAYS:,}; RAYX holds ~4 kB per ray)")
    parser.add_argument("--truth-log", metavar="FILE",
                        help="append what only the simulation's operator may read (impossible true states, "
                             "model errors, with true values) to FILE; default: nowhere")
    parser.add_argument("--noise-seed", type=int, default=None,
                        help="seed of the frames' ray noise: the same acquisitions give the same frames "
                             "(default: fresh noise from the OS for every frame)")
    parser.add_argument("--move-time", type=float, default=4.0, help="seconds for a full-range move (VELO)")
    parser.add_argument("--accel-time", type=float, default=0.2, help="motor acceleration time ACCL (s)")
    parser.add_argument("--tick", type=float, default=0.05, help="readback update period while moving (s)")
    parser.add_argument("--motors", choices=MOTOR_PROFILES, default="perfect",
                        help="perfect axes (default), or encoder noise, backlash and retries on every axis "
                             "(typical values: sim_iocs.metrixs.motor_profile)")
    parser.add_argument("--interfaces", nargs="+", default=None,
                        help="interfaces to serve on (default: $EPICS_CAS_INTF_ADDR_LIST, else loopback only)")
    parser.add_argument("--leave-out", action="append", default=[], metavar="PARAMETER",
                        help="serve no motor record for this motorized parameter (repeatable): a beamline with "
                             "a record missing, e.g. for bluesky-offsets check-pvs")
    parser.add_argument("-v", "--verbose", action="store_true", help="log more")


SEED_VARIABLE = "BLUESKY_OFFSETS_IOC_SEED"
"""The environment variable that may hold the seed of the hidden truth (as ``--seed-file``)."""


def _seed(args) -> int | None:
    """The truth's seed from ``--seed-file`` or :data:`SEED_VARIABLE`; None: a random one."""
    if args.seed is not None:
        raise ParameterError(f"--seed puts the hidden truth in every process list; use --seed-file FILE or "
                             f"${SEED_VARIABLE}")
    text = os.environ.get(SEED_VARIABLE)
    if args.seed_file:
        try:
            text = Path(args.seed_file).read_text()
        except OSError as exc:
            raise ParameterError(f"--seed-file: {exc.strerror}: {args.seed_file}") from None
    if text is None or not text.strip():
        return None
    try:
        return int(text.strip())
    except ValueError:
        raise ParameterError("the truth's seed must be an integer") from None


def _beamline(args):
    """The described beamline the IOC serves (None: METRIXS)."""
    if not args.beamline:
        return None
    from bluesky_offsets.physics.beamline import BeamlineError, resolve
    try:
        bl = resolve(args.beamline)
    except BeamlineError as exc:
        raise ParameterError(str(exc)) from None
    return None if bl.builtin == "metrixs" else bl


def _build(args) -> MetrixsIOC:
    bl = _beamline(args)
    table = METRIXS if bl is None else bl.table
    truth = Truth.from_file(args.truth, table) if args.truth else Truth.from_seed(_seed(args), table,
                                                                                 limit=args.max_offset)
    if not 0 <= args.rays <= args.max_rays:
        raise ParameterError(f"--rays must lie in [0, --max-rays = {args.max_rays}], not {args.rays}")
    for option in ("move_time", "accel_time", "tick"):
        if not getattr(args, option) > 0:
            raise ParameterError(f"--{option.replace('_', '-')} must be positive, not {getattr(args, option)}")
    if args.noise_seed is not None and args.noise_seed < 0:
        raise ParameterError(f"--noise-seed must be 0 or more, not {args.noise_seed}")
    if args.dump_truth:
        with _private(args.dump_truth, "w") as f:
            json.dump(truth.to_dict(), f, indent=2)
    try:
        return MetrixsIOC(args.prefix, truth, args.backend, n_rays=args.rays, move_time=args.move_time,
                          accel_time=args.accel_time, tick=args.tick, noise_seed=args.noise_seed,
                          max_rays=args.max_rays, truth_log=_truth_logger(args.truth_log),
                          leave_out=args.leave_out, motors=args.motors, beamline=bl)
    except ValueError as exc:
        raise ParameterError(str(exc)) from None


def _private(path: str, mode: str):
    """``path`` opened for writing, readable by its owner only (0600, also when it existed)."""
    flags = os.O_WRONLY | os.O_CREAT | (os.O_APPEND if mode == "a" else os.O_TRUNC)
    fd = os.open(path, flags, 0o600)
    os.fchmod(fd, 0o600)
    return os.fdopen(fd, mode)


def _truth_logger(path: str | None) -> Callable[[str], None] | None:
    if not path:
        return None

    def write(text: str) -> None:
        with _private(path, "a") as f:
            f.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {text}\n")
    return write


def _client_address(interface: str) -> str:
    """Where a client finds this IOC: the interface, and the search port the server reads as caproto does."""
    from caproto import get_environment_variables
    port = int(get_environment_variables()["EPICS_CA_SERVER_PORT"])
    return interface if port == 5064 else f"{interface}:{port}"


def _interfaces(given: list[str] | None) -> list[str]:
    if given:
        return list(given)
    env = os.environ.get("EPICS_CAS_INTF_ADDR_LIST", "").split()
    return env or ["127.0.0.1"]


def _beacon_environment(interfaces: list[str]) -> None:
    """Send beacons to the served loopback interface, not caproto's default 255.255.255.255.

    Only where every served interface is a loopback one, and not where the caller chose their
    addresses (``EPICS_CAS_BEACON_ADDR_LIST``).
    """
    if os.environ.get("EPICS_CAS_BEACON_ADDR_LIST"):
        return
    loop = [i for i in interfaces if i.startswith("127.")]
    if loop and len(loop) == len(interfaces):
        os.environ["EPICS_CAS_BEACON_ADDR_LIST"] = " ".join(loop)
        os.environ["EPICS_CAS_AUTO_BEACON_ADDR_LIST"] = "NO"


def serve(args) -> int:
    """Run the IOC until interrupted (SIGINT or SIGTERM)."""
    ioc = _build(args)
    circuit_log = logging.getLogger("caproto.circ")
    if not any(isinstance(f, RefusedPutInOneLine) for f in circuit_log.filters):
        circuit_log.addFilter(RefusedPutInOneLine())
    context_log = logging.getLogger("caproto.ctx")
    if not any(isinstance(f, BeaconRefusedOnce) for f in context_log.filters):
        context_log.addFilter(BeaconRefusedOnce())
    origin = "from a file" if args.truth else "drawn from a seed"
    # the truth's source (a seed) is the truth: only its salted id is shown
    print(f"{'METRIXS' if ioc.beamline is None else ioc.beamline.name} simulation IOC, prefix {args.prefix!r}, "
          f"backend {ioc.backend.name}, "
          f"truth id {ioc.truth.truth_id} ({origin})", flush=True)
    if args.list_pvs:
        print(ioc.describe(), flush=True)

    def _terminate(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _terminate)
    # SIGINT stops the IOC even when its parent ignored SIGINT (a disposition children inherit:
    # such an IOC would sit out the grace its stopper gives it before killing it)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    interfaces = _interfaces(args.interfaces)
    _beacon_environment(interfaces)
    if all(i.startswith("127.") for i in interfaces):
        print(f"serving {', '.join(interfaces)} only: clients in another shell need "
              f"EPICS_CA_ADDR_LIST={_client_address(interfaces[0])} EPICS_CA_AUTO_ADDR_LIST=NO", flush=True)
    try:
        asyncio.run(_serve(ioc.pvdb, interfaces))
    except KeyboardInterrupt:
        pass
    finally:
        ioc.close()
    return 0


def _completed(command):
    """A failed put-with-completion answered the way an EPICS IOC answers it.

    That is a WriteNotifyResponse with ECA_PUTFAIL.  caproto's server sends an ErrorResponse instead,
    which caproto's own clients (ophyd's control layer among them) never match to the put:
    it would wait until its timeout.
    """
    import caproto as ca
    if isinstance(command, ca.ErrorResponse):
        req = command.original_request
        if req.command == ca.WriteNotifyRequest.ID:
            return ca.WriteNotifyResponse(data_type=req.data_type, data_count=req.data_count,
                                          status=ca.CAStatus.ECA_PUTFAIL, ioid=req.parameter2)
    return command


def _nodelay_context():
    from caproto.asyncio.server import Context, VirtualCircuit

    class Circuit(VirtualCircuit):
        async def send(self, *commands):
            await super().send(*(_completed(c) for c in commands))

    class NoDelayContext(Context):
        """caproto's asyncio server with TCP_NODELAY on client circuits, as EPICS IOCs have.

        Without it, two requests in flight on one circuit (ophyd-async reads
        several fields of a motor at once) wait for the client's delayed ACK:
        ~45 ms instead of ~1 ms per round trip.
        """

        CircuitClass = Circuit

        async def tcp_handler(self, client, addr):
            sock = client.writer.get_extra_info("socket")
            if sock is not None:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            return await super().tcp_handler(client, addr)

    return NoDelayContext


async def _serve(pvdb, interfaces):
    ctx = _nodelay_context()(pvdb, interfaces)
    await ctx.run(log_pv_names=False)


def _cmd_ioc(args) -> int:
    return serve(args)  # the CLI reports ParameterError cleanly (exit 2)


def add_cli(subparsers) -> None:
    """``bluesky-offsets ioc ...``: the simulated beamline."""
    p = subparsers.add_parser("ioc", help="serve the simulated beamline, METRIXS or a described one (caproto IOC)",
                              description=__doc__.split("\n\n")[0])
    add_arguments(p)
    p.set_defaults(func=_cmd_ioc)


def main(argv: list[str] | None = None) -> int:
    """``python -m sim_iocs.metrixs``: parse ``argv`` and serve the IOC; the exit status (2 for a bad parameter)."""
    parser = argparse.ArgumentParser(prog="python -m sim_iocs.metrixs",
                                     description="Simulated METRIXS beamline (caproto IOC).")
    add_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return serve(args)
    except ParameterError as exc:
        print(f"sim_iocs.metrixs: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
