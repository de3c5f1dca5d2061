"""A simulated EPICS motor record as a caproto PVGroup.

One :class:`MotorRecord` serves the record PV (``P:e1:rx``, which is also
``P:e1:rx.VAL``) and the fields that ophyd's ``EpicsMotor``, ophyd-async's
``Motor``, MEDM-style screens and the caproto command-line tools use.  It
behaves like the record where clients can tell the difference:

* motion takes time: a trapezoidal profile with velocity ``VELO`` and
  acceleration time ``ACCL``; the readback is quantized to ``MRES`` steps;
* ``DMOV`` goes 1 -> 0 -> 1 on every processed move, also a zero-length one,
  and a put-with-completion on ``VAL``, ``DVAL``, ``RLV``, ``TWF``/``TWR`` or
  ``HOMF``/``HOMR`` completes only when ``DMOV`` is back to 1;
* a target outside ``LLM``/``HLM`` is refused: ``LVIO`` = 1, ``VAL`` keeps its
  old value, nothing moves;
* ``STOP`` and ``SPMG`` stop a move (``VAL`` becomes the readback);
* user and dial coordinates: ``user = dial * (+1 | -1 for DIR) + OFF``;
  ``SET`` mode redefines positions without motion (``FOFF`` chooses whether
  ``OFF`` or the dial position changes).

The motion runs in a task owned by the record, not by the client's write:
a client that disconnects mid-move leaves the move running to its end.

The physical position of the axis (what the beamline model sees) is
:attr:`MotorRecord.axis_position`.  With perfect :class:`Mechanics` (the
default) it differs from the dial position only after the dial has been
redefined in ``SET``/``Frozen`` mode.  Real :class:`Mechanics` add what a real
axis does: a step-scale error and backlash between the motor and the load, a
load that stalls, and an encoder (``UEIP``) whose noisy readback the record
corrects with retries (``RDBD``, ``RTRY``, ``RCNT``, ``MISS``); backlash is
taken out, as by the record, with a final approach of ``BDST`` at ``BVEL``.
"""

from __future__ import annotations

import asyncio
import logging
import math
import re
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from caproto import ChannelType
from caproto.server import PVGroup, PvpropertyDouble, PvpropertyInteger, PvpropertyShort, pvproperty
from caproto._data import SkipWrite

MAX_ACCEL_TIME = 10.0  # s: longer ACCL is clamped (a 0.2 mm move would otherwise take minutes)
MAX_MOVE_TIME = 600.0  # s: a VELO that would take longer over the whole travel is refused
STEPS_MAX = 2**31 - 1  # RVAL/RRBV are DBF_LONG: a count beyond saturates, never wraps


def steps(position: float, resolution: float) -> int:
    """``position`` in motor steps of ``resolution``, saturated to the record's 32-bit range."""
    n = position / resolution if resolution > 0 else 0.0
    return int(round(min(max(n, -STEPS_MAX - 1.0), float(STEPS_MAX))))


def _finite(value, field: str, *, above: float | None = None, at_least: float | None = None) -> float:
    """``value`` as a finite float (optionally ``> above`` or ``>= at_least``), or ValueError naming the field.

    NaN and infinities never reach a published value or the motion.
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{field} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{field} must be finite, got {v}")
    if above is not None and not v > above:
        raise ValueError(f"{field} must be > {above:g}, got {v}")
    if at_least is not None and not v >= at_least:
        raise ValueError(f"{field} must be >= {at_least:g}, got {v}")
    return v


log = logging.getLogger("sim_iocs.motor_record")

# MSTA bits of the motor record (motor record documentation, "MSTA").
MSTA_DIRECTION, MSTA_DONE, MSTA_PLUS_LS, MSTA_HOME_LS = 1 << 0, 1 << 1, 1 << 2, 1 << 3
MSTA_POSITION, MSTA_SLIP_STALL, MSTA_HOME, MSTA_PRESENT = 1 << 5, 1 << 6, 1 << 7, 1 << 8  # PRESENT: an encoder
MSTA_PROBLEM = 1 << 9
MSTA_MOVING, MSTA_GAIN_SUPPORT, MSTA_MINUS_LS, MSTA_HOMED = 1 << 10, 1 << 11, 1 << 13, 1 << 14


def trapezoid(distance: float, velocity: float, accel_time: float) -> tuple[float, Callable[[float], float]]:
    """Duration and displacement-vs-time of a trapezoidal move.

    The axis accelerates uniformly for ``accel_time`` to ``velocity``, cruises,
    and decelerates symmetrically; a move too short to reach ``velocity`` is a
    triangle.  Returns ``(duration, s)`` where ``s(t)`` is the signed
    displacement at time ``t`` (clipped to ``[0, duration]``).
    """
    d = abs(float(distance))
    v = abs(float(velocity))
    if d == 0.0 or v == 0.0:
        return 0.0, lambda t: 0.0
    ta = max(float(accel_time), 1e-6)
    a = v / ta
    sign = math.copysign(1.0, distance)
    if d <= v * ta:  # triangle: never reaches cruise velocity
        t1 = math.sqrt(d / a)

        def s(t):
            t = min(max(t, 0.0), 2 * t1)
            if t <= t1:
                return sign * 0.5 * a * t * t
            u = 2 * t1 - t
            return sign * (d - 0.5 * a * u * u)
        return 2 * t1, s
    t_cruise = (d - v * ta) / v
    duration = 2 * ta + t_cruise

    def s(t):
        t = min(max(t, 0.0), duration)
        if t <= ta:
            return sign * 0.5 * a * t * t
        if t <= ta + t_cruise:
            return sign * (0.5 * v * ta + v * (t - ta))
        u = duration - t
        return sign * (d - 0.5 * a * u * u)
    return duration, s


@dataclass(frozen=True)
class AxisSettings:
    """Static description of one simulated axis (all in user = dial units at start)."""

    description: str
    egu: str
    low: float            # soft limits (LLM/HLM)
    high: float
    start: float          # position at IOC start; also the home position
    velocity: float       # VELO, EGU/s
    accel_time: float = 0.2   # ACCL, s
    resolution: float = 1e-6  # MRES, EGU per step
    travel_margin: float = 0.25  # hardware limit switches this fraction of the range beyond the soft limits
    deadband: float = 0.0     # RDBD (0: one step)
    backlash_distance: float = 0.0  # BDST: the final approach, from its sign's side

    @property
    def precision(self) -> int:
        """Display precision (PREC): the decimals of one step ``resolution``, within [0, 12]."""
        return int(min(max(-math.floor(math.log10(self.resolution)), 0), 12))


@dataclass(frozen=True, kw_only=True)
class Mechanics:
    """How an axis really moves (EGU).

    The default is a perfect axis: the load follows the commanded steps exactly and the readback is
    the step count.
    """

    encoder: bool = False        # readback from an encoder on the load (UEIP) instead of the step count
    readback_noise: float = 0.0  # encoder noise, σ
    backlash: float = 0.0        # lost motion between motor and load when the direction reverses
    step_scale: float = 0.0      # the load moves (1 + step_scale) times the commanded distance
    stalled: bool = False        # the load does not follow the motor at all

    def __post_init__(self):
        for name in ("readback_noise", "backlash", "step_scale"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"mechanics: {name} must be finite")
        if self.readback_noise < 0 or self.backlash < 0 or not -0.5 < self.step_scale < 0.5:
            raise ValueError("mechanics: readback_noise and backlash >= 0, |step_scale| < 0.5")
        if self.readback_noise and not self.encoder:
            raise ValueError("mechanics: readback noise needs an encoder (a step count has none)")

    @property
    def perfect(self) -> bool:
        """Whether the load follows the commanded steps exactly (no backlash, step-scale error or stall)."""
        return not (self.backlash or self.step_scale or self.stalled)


_NUMBER = re.compile(rb"\s*[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?\s*")
_INTEGER = re.compile(rb"\s*[+-]?\d+\s*")


class StrictText:
    """A numeric field that takes a put as text only when the text is a plain number of its kind.

    caproto reads ``''`` as 0 and Python's ``'1_0'`` as 10, which the record would refuse.
    """

    pattern = _NUMBER

    async def write_from_dbr(self, data, data_type, metadata, *, flags=0):
        """Refuse a text put that is not a plain number of the field's kind; pass the rest to caproto."""
        if data_type in (ChannelType.STRING, ChannelType.CHAR):
            texts = [data] if isinstance(data, (str, bytes)) else list(data)
            for t in texts:
                raw = (t.encode("latin-1") if isinstance(t, str) else bytes(t)).rstrip(b"\0")
                if not self.pattern.fullmatch(raw):
                    raise ValueError(f"not {'an integer' if self.pattern is _INTEGER else 'a number'}: {raw!r}")
        return await super().write_from_dbr(data, data_type, metadata, flags=flags)


class StrictDouble(StrictText, PvpropertyDouble):
    """A double that refuses text other than a plain number."""


class StrictShort(StrictText, PvpropertyShort):
    """A 16-bit integer that refuses text other than a plain integer."""

    pattern = _INTEGER


class StrictLong(StrictText, PvpropertyInteger):
    """A 32-bit integer that refuses text other than a plain integer."""

    pattern = _INTEGER


class _UnclampedDouble(StrictDouble):
    """A double whose control limits are published but not enforced by caproto.

    The motor record enforces its limits itself (``LVIO``) instead of failing
    the put, and clients such as ophyd's ``EpicsMotor`` read the limits from the
    ``VAL`` channel's control metadata.
    """

    async def verify_value(self, value):
        if self.putter is not None:
            return await self.putter(self, value)
        return value


_ENUM = ChannelType.ENUM
_STR = ChannelType.STRING
_SHORT = ChannelType.INT
_LONG = ChannelType.LONG


def _ro(value, name, doc, dtype=None, **kw):
    return pvproperty(value=value, name=name, doc=doc, read_only=True, dtype=dtype, **kw)


class MotorRecord(PVGroup):
    """EPICS motor record with simulated, finite-speed motion.

    Parameters
    ----------
    prefix : str
        Record name, e.g. ``"BL:e1:rx"``; fields are ``prefix + ".FIELD"``.
    settings : AxisSettings
        Limits, start position, velocity, resolution, units and description.
    tick : float
        Readback update period during motion (s).
    mechanics : Mechanics
        How the axis really moves (hidden from clients but through its readback).
    rng : numpy.random.Generator or int, optional
        The encoder noise's random stream.
    """

    # --- positions ---------------------------------------------------------
    val = pvproperty(value=0.0, name="", dtype=_UnclampedDouble, doc="User desired value (VAL)")
    rbv = _ro(0.0, ".RBV", "User readback value")
    dval = pvproperty(value=0.0, name=".DVAL", dtype=_UnclampedDouble, doc="Dial desired value")
    drbv = _ro(0.0, ".DRBV", "Dial readback value")
    rval = _ro(0, ".RVAL", "Raw desired value (steps)", _LONG)
    rrbv = _ro(0, ".RRBV", "Raw readback value (steps)", _LONG)
    diff = _ro(0.0, ".DIFF", "Difference DVAL - DRBV")
    rlv = pvproperty(dtype=StrictDouble, value=0.0, name=".RLV", doc="Relative value (EGU)")
    off = pvproperty(dtype=StrictDouble, value=0.0, name=".OFF", doc="User offset (EGU)")
    dir = pvproperty(value="Pos", name=".DIR", dtype=_ENUM, enum_strings=("Pos", "Neg"),
                     doc="User direction")
    foff = pvproperty(value="Variable", name=".FOFF", dtype=_ENUM, enum_strings=("Variable", "Frozen"),
                      doc="Offset-freeze switch")
    set_ = pvproperty(value="Use", name=".SET", dtype=_ENUM, enum_strings=("Use", "Set"),
                      doc="Set/Use switch")
    # --- motion status -----------------------------------------------------
    dmov = _ro(1, ".DMOV", "Done moving to value", _SHORT)
    movn = _ro(0, ".MOVN", "Motor is moving", _SHORT)
    mip = _ro(0, ".MIP", "Motion in progress", _SHORT)
    tdir = _ro(1, ".TDIR", "Direction of travel", _SHORT)
    msta = _ro(0, ".MSTA", "Motor status bits", _LONG)
    athm = _ro(0, ".ATHM", "At home", _SHORT)
    lvio = _ro(0, ".LVIO", "Limit violation", _SHORT)
    hls = _ro(0, ".HLS", "At high limit switch", _SHORT)
    lls = _ro(0, ".LLS", "At low limit switch", _SHORT)
    # --- commands -----------------------------------------------------------
    stop = pvproperty(value=0, name=".STOP", dtype=StrictShort, doc="Stop")
    spmg = pvproperty(value="Go", name=".SPMG", dtype=_ENUM, enum_strings=("Stop", "Pause", "Move", "Go"),
                      doc="Stop/Pause/Move/Go")
    cnen = pvproperty(value="Enable", name=".CNEN", dtype=_ENUM, enum_strings=("Disable", "Enable"),
                      doc="Enable control (torque)")
    twv = pvproperty(dtype=StrictDouble, value=0.0, name=".TWV", doc="Tweak step size (EGU)")
    twf = pvproperty(value=0, name=".TWF", dtype=StrictShort, doc="Tweak motor forward")
    twr = pvproperty(value=0, name=".TWR", dtype=StrictShort, doc="Tweak motor reverse")
    homf = pvproperty(value=0, name=".HOMF", dtype=StrictShort, doc="Home forward")
    homr = pvproperty(value=0, name=".HOMR", dtype=StrictShort, doc="Home reverse")
    # --- limits ---------------------------------------------------------------
    hlm = pvproperty(dtype=StrictDouble, value=0.0, name=".HLM", doc="User high limit")
    llm = pvproperty(dtype=StrictDouble, value=0.0, name=".LLM", doc="User low limit")
    dhlm = pvproperty(dtype=StrictDouble, value=0.0, name=".DHLM", doc="Dial high limit")
    dllm = pvproperty(dtype=StrictDouble, value=0.0, name=".DLLM", doc="Dial low limit")
    # --- dynamics and resolution ----------------------------------------------
    velo = pvproperty(dtype=StrictDouble, value=1.0, name=".VELO", doc="Velocity (EGU/s)")
    vmax = pvproperty(dtype=StrictDouble, value=10.0, name=".VMAX", doc="Max. velocity (EGU/s)")
    vbas = pvproperty(dtype=StrictDouble, value=0.0, name=".VBAS", doc="Base velocity (EGU/s)")
    hvel = pvproperty(dtype=StrictDouble, value=1.0, name=".HVEL", doc="Home velocity (EGU/s)")
    accl = pvproperty(dtype=StrictDouble, value=0.2, name=".ACCL", doc="Seconds to velocity")
    mres = pvproperty(dtype=StrictDouble, value=1e-6, name=".MRES", doc="Motor step size (EGU)")
    eres = pvproperty(dtype=StrictDouble, value=1e-6, name=".ERES", doc="Encoder step size (EGU)")
    rres = pvproperty(dtype=StrictDouble, value=1e-6, name=".RRES", doc="Readback step size (EGU)")
    rdbd = pvproperty(dtype=StrictDouble, value=1e-6, name=".RDBD", doc="Retry deadband (EGU)")
    rtry = pvproperty(value=10, name=".RTRY", dtype=StrictShort, doc="Max retry count")
    rcnt = _ro(0, ".RCNT", "Retry count", _SHORT)
    miss = _ro(0, ".MISS", "Ran out of retries", _SHORT)
    ueip = pvproperty(value="No", name=".UEIP", dtype=_ENUM, enum_strings=("No", "Yes"),
                      doc="Use encoder if present")
    bdst = pvproperty(dtype=StrictDouble, value=0.0, name=".BDST", doc="Backlash distance (EGU)")
    bvel = pvproperty(dtype=StrictDouble, value=1.0, name=".BVEL", doc="Backlash velocity (EGU/s)")
    bacc = pvproperty(dtype=StrictDouble, value=0.2, name=".BACC", doc="Backlash seconds to velocity")
    srev = pvproperty(value=200, name=".SREV", dtype=StrictLong, doc="Steps per revolution")
    urev = pvproperty(dtype=StrictDouble, value=2e-4, name=".UREV", doc="EGUs per revolution")
    # --- description --------------------------------------------------------
    egu = pvproperty(value="", name=".EGU", dtype=_STR, doc="Engineering units")
    desc = pvproperty(value="", name=".DESC", dtype=_STR, doc="Descriptor")
    prec = pvproperty(value=6, name=".PREC", dtype=StrictShort, doc="Display precision")
    rtyp = _ro("motor", ".RTYP", "Record type", _STR)
    out = _ro("asyn(SIM_METRIXS)", ".OUT", "Output specification", _STR)

    def __init__(self, *args, settings: AxisSettings, tick: float = 0.05, mechanics: Mechanics = Mechanics(),
                 rng: np.random.Generator | int | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.settings = settings
        self.tick = float(tick)
        self.mechanics = mechanics
        self._rng = np.random.default_rng(rng)
        s = settings
        # Internal state (plain floats; the PVs mirror them).
        self._sign = 1.0
        self._offset = 0.0
        self._dial_shift = 0.0          # dial = motor (steps) or load (encoder) + dial_shift
        self._axis = self._quantize(s.start, s.resolution)   # the load: what the beamline sees
        self._motor = self._drive = self._axis               # the step count; what the load is driven to
        self._noise = 0.0                                    # the encoder's last reading error
        self._axis_low = s.low - s.travel_margin * (s.high - s.low)   # hardware travel (axis units)
        self._axis_high = s.high + s.travel_margin * (s.high - s.low)
        self._target_dial = self._axis
        self._motion: asyncio.Task | None = None
        self._waiters: list[asyncio.Future] = []
        self._paused = False
        self._homed = False
        self._generation = 0
        self._lock = asyncio.Lock()

    # ------------------------------------------------------------------ model
    @staticmethod
    def _quantize(x: float, step: float) -> float:
        return round(x / step) * step if step > 0 else x

    @property
    def axis_position(self) -> float:
        """Physical position of the axis (the value the beamline sees, before hidden offsets)."""
        return self._axis

    @property
    def moving(self) -> bool:
        """Whether a motion is under way."""
        return self._motion is not None and not self._motion.done()

    def _uses_encoder(self) -> bool:
        return self.mechanics.encoder and self.ueip.value == "Yes"

    def _dial(self) -> float:
        """The dial readback: the encoder's last reading when it is used, else the step count."""
        if self._uses_encoder():
            return self._quantize(self._axis + self._dial_shift + self._noise, self.eres.value)
        return self._motor + self._dial_shift

    def _sample(self) -> None:
        """A fresh encoder reading."""
        sigma = self.mechanics.readback_noise if self._uses_encoder() else 0.0
        self._noise = float(self._rng.normal(0.0, sigma)) if sigma else 0.0

    def _advance(self, motor: float) -> None:
        """The motor (axis units) steps to ``motor``; the load follows through the mechanics."""
        delta, self._motor = motor - self._motor, motor
        m = self.mechanics
        if m.perfect:
            self._axis = self._drive = motor
            return
        if not m.stalled:
            self._drive += (1.0 + m.step_scale) * delta
        half = 0.5 * m.backlash
        self._axis = min(max(self._axis, self._drive - half), self._drive + half)

    def _user_from_dial(self, dial: float) -> float:
        return self._sign * dial + self._offset

    def _dial_from_user(self, user: float) -> float:
        return (user - self._offset) * self._sign

    def _msta(self) -> int:
        bits = MSTA_GAIN_SUPPORT | MSTA_POSITION
        if self.mechanics.encoder:
            bits |= MSTA_PRESENT
        if self.miss.value:
            bits |= MSTA_SLIP_STALL
        if self.tdir.value:
            bits |= MSTA_DIRECTION
        if not self.moving:
            bits |= MSTA_DONE
        else:
            bits |= MSTA_MOVING
        if self.hls.value:
            bits |= MSTA_PLUS_LS
        if self.lls.value:
            bits |= MSTA_MINUS_LS
        if self._homed:
            bits |= MSTA_HOMED
        if self.athm.value:
            bits |= MSTA_HOME
        return bits

    # -------------------------------------------------------------- startup
    @val.startup
    async def val(self, instance, async_lib):
        """Publish the axis's settings, limits, position and status at startup."""
        s = self.settings
        prec = s.precision
        units = dict(units=s.egu, precision=prec)
        for pv in (self.val, self.rbv, self.dval, self.drbv, self.rlv, self.off, self.diff, self.twv,
                   self.hlm, self.llm, self.dhlm, self.dllm):
            await pv.write_metadata(**units)
        await self.egu.write(s.egu)
        await self.desc.write(s.description[:40])
        await self.prec.write(prec)
        for pv in (self.mres, self.eres, self.rres):
            await pv.write(s.resolution)
        await self.rdbd.write(s.deadband or s.resolution)
        await self.bdst.write(s.backlash_distance)
        await self.urev.write(s.resolution * self.srev.value)
        await self.vmax.write(10 * s.velocity)  # before VELO, which is clamped to VMAX
        await self.velo.write(s.velocity)
        await self.hvel.write(s.velocity)
        await self.bvel.write(s.velocity)
        await self.accl.write(s.accel_time)
        await self.bacc.write(s.accel_time)
        await self.ueip.write("Yes" if self.mechanics.encoder else "No")
        await self.twv.write(abs(s.high - s.low) / 100)
        await self.dhlm.write(s.high, verify_value=False)
        await self.dllm.write(s.low, verify_value=False)
        await self._publish_limits()
        await self._publish_position(setpoint=True)
        await self.msta.write(self._msta())

    # ------------------------------------------------------------ publishing
    async def _publish_limits(self):
        lo, hi = sorted((self._user_from_dial(self.dllm.value), self._user_from_dial(self.dhlm.value)))
        await self.hlm.write(hi, verify_value=False)
        await self.llm.write(lo, verify_value=False)
        # ophyd's EpicsMotor reads the soft limits from VAL's control limits.
        await self.val.write_metadata(lower_ctrl_limit=lo, upper_ctrl_limit=hi,
                                      lower_disp_limit=lo, upper_disp_limit=hi)

    async def _publish_position(self, *, setpoint: bool = False, timestamp: float | None = None):
        ts = timestamp or time.time()
        dial = self._dial()
        res = self.mres.value or 1.0
        if setpoint:
            await self.dval.write(self._target_dial, verify_value=False, timestamp=ts)
            await self.val.write(self._user_from_dial(self._target_dial), verify_value=False, timestamp=ts)
            await self.rval.write(steps(self._target_dial, res), timestamp=ts)
        await self.drbv.write(dial, timestamp=ts)
        await self.rrbv.write(steps(dial, res), timestamp=ts)
        await self.diff.write(self._target_dial - dial, timestamp=ts)
        await self.rbv.write(self._user_from_dial(dial), timestamp=ts)

    # --------------------------------------------------------------- motion
    def _in_soft_limits(self, dial: float) -> bool:
        lo, hi = self.dllm.value, self.dhlm.value
        if lo == 0 and hi == 0:  # motor-record convention: no limits
            return True
        tol = 1e-9 * max(abs(hi - lo), 1e-12)
        return lo - tol <= dial <= hi + tol

    async def _request_move(self, dial_target: float) -> bool:
        """Validate and start a move to a dial position.  Returns False (LVIO set) when refused."""
        dial_target = self._quantize(dial_target, self.mres.value)
        if not self._in_soft_limits(dial_target):
            await self.lvio.write(1)
            return False
        if self.lvio.value:
            await self.lvio.write(0)
        if self.spmg.value == "Stop":
            raise ValueError("SPMG is Stop: motion is disabled (set SPMG to Go or Move)")
        self._target_dial = dial_target
        await self._publish_position(setpoint=True)
        if self.spmg.value == "Pause":
            self._paused = True
            return True
        self._start_motion()
        return True

    def _start_motion(self):
        if self.moving:
            self._motion.cancel()  # retarget from where the axis is now
        self._generation += 1
        self._motion = asyncio.get_running_loop().create_task(self._move(self._target_dial, self._generation))

    async def _move(self, dial_target: float, generation: int):
        limit_hit = None
        try:
            async with self._lock:
                await self.dmov.write(0)
                await self.movn.write(1)
                await self.mip.write(1)
                await self.tdir.write(1 if dial_target >= self._dial() else 0)
                await self.athm.write(0)
                await self.hls.write(0)
                await self.lls.write(0)
                await self.rcnt.write(0)
                await self.miss.write(0)
                await self.msta.write(self._msta())
            limit_hit = await self._approach(dial_target - self._dial())
            tries = 0
            while limit_hit is None and self._uses_encoder():
                self._sample()
                error = dial_target - self._dial()
                if abs(error) <= self.rdbd.value:
                    break
                if tries >= self.rtry.value:
                    await self.miss.write(1)
                    log.warning("%s: not within RDBD after %d retries (%.6g from the target)", self.prefix,
                                tries, error)
                    break
                tries += 1
                await self.rcnt.write(tries)
                limit_hit = await self._approach(error)
        except asyncio.CancelledError:
            # Stopped, paused or retargeted: the axis stays where it is.
            await self._publish_position()
            raise
        except Exception:  # never leave DMOV at 0 and a put waiting: end the move where it stands
            log.exception("%s: motion failed; stopped", self.prefix)
            await self._finish_motion(generation, stopped=True)
            return
        await self._finish_motion(generation, limit_hit)

    async def _approach(self, distance: float) -> str | None:
        """Step the motor by ``distance`` (dial units); the limit switch hit, if any.

        The last ``BDST`` of it is taken at ``BVEL`` from ``BDST``'s side, as the record takes out
        backlash.
        """
        bdst = self.bdst.value
        if not bdst:
            legs = [(distance, self.velo.value, self.accl.value)]
        elif distance * bdst > 0 and abs(distance) <= abs(bdst):
            legs = [(distance, self.bvel.value, self.bacc.value)]
        else:
            legs = [(distance - bdst, self.velo.value, self.accl.value), (bdst, self.bvel.value, self.bacc.value)]
        for leg in legs:
            if limit_hit := await self._leg(*leg):
                return limit_hit
        return None

    async def _leg(self, distance: float, velocity: float, accel_time: float) -> str | None:
        """One trapezoidal move of the motor by ``distance``; the limit switch hit, if any."""
        m0 = self._motor + self._dial_shift
        duration, profile = trapezoid(distance, max(abs(velocity), 1e-12), accel_time)
        res = self.mres.value
        t0 = time.monotonic()
        while True:
            # Sleep at least one tick: DMOV=0 is visible even for a zero-length move.
            remaining = duration - (time.monotonic() - t0)
            await asyncio.sleep(min(self.tick, remaining) if remaining > 0 else self.tick)
            t = time.monotonic() - t0
            self._advance(self._quantize(m0 + profile(t), res) - self._dial_shift)
            limit_hit = None
            if self._axis >= self._axis_high or self._axis <= self._axis_low:
                limit_hit = "high" if self._axis >= self._axis_high else "low"
                self._axis = min(max(self._axis, self._axis_low), self._axis_high)
                if self.mechanics.perfect:
                    self._motor = self._drive = self._axis
            self._sample()
            if limit_hit or t >= duration:
                return limit_hit
            await self._publish_position()

    async def _finish_motion(self, generation: int, limit_hit: str | None = None, *, stopped: bool = False):
        async with self._lock:
            if generation != self._generation:
                return  # a newer move has taken over; it finishes (and completes the puts)
            self._motion = None
            waiters, self._waiters = self._waiters, []
            if limit_hit:
                await (self.hls if limit_hit == "high" else self.lls).write(1)
            if stopped or limit_hit:
                self._target_dial = self._dial()  # like the record: VAL follows the readback
                await self._publish_position(setpoint=True)
            else:
                await self._publish_position()
            home_dial = self.settings.start + self._dial_shift
            await self.athm.write(int(abs(self._dial() - home_dial) <= (self.mres.value or 0)))
            await self.movn.write(0)
            await self.mip.write(0)
            await self.msta.write(self._msta())
            await self.dmov.write(1)
        for w in waiters:
            if not w.done():
                w.set_result(True)

    async def _cancel_motion(self) -> bool:
        task = self._motion
        if task is None or task.done():
            return False
        task.cancel()
        try:
            await task
        except asyncio.CancelledError:
            pass
        return True

    async def _halt(self):
        """Stop now; VAL takes the readback; pending put-completions finish."""
        was_paused, self._paused = self._paused, False
        if await self._cancel_motion() or was_paused:
            await self._finish_motion(self._generation, stopped=True)

    async def _wait_done(self):
        """Wait until the current move (if any) ends: the put-completion of motion fields."""
        if not self.moving and not self._paused:
            return
        fut = asyncio.get_running_loop().create_future()
        self._waiters.append(fut)
        await fut

    async def _move_and_wait(self, dial_target: float) -> bool:
        ok = await self._request_move(dial_target)
        if ok:
            await self._wait_done()
        return ok

    # --------------------------------------------------------------- putters
    @val.putter
    async def val(self, instance, value):
        """Move to user position VAL (completing when the move ends); in SET mode, redefine the position there."""
        value = _finite(value, "VAL")
        if self.set_.value == "Set":
            await self._redefine_user(value)
            return SkipWrite
        await self._move_and_wait(self._dial_from_user(value))
        # VAL was published by the move (or kept, when refused): nothing left to write.
        return SkipWrite

    @dval.putter
    async def dval(self, instance, value):
        """Move to dial position DVAL (completing when the move ends); in SET mode, redefine the position there."""
        value = _finite(value, "DVAL")
        if self.set_.value == "Set":
            await self._redefine_user(self._user_from_dial(value))
            return SkipWrite
        await self._move_and_wait(value)
        return SkipWrite

    @rlv.putter
    async def rlv(self, instance, value):
        """Move by RLV (user units) from the present target; RLV reads 0 again."""
        target_user = self._user_from_dial(self._target_dial) + _finite(value, "RLV")
        await self._move_and_wait(self._dial_from_user(target_user))
        return 0.0

    async def _tweak(self, sign: float):
        step = sign * abs(self.twv.value)
        target_user = self._user_from_dial(self._target_dial) + step
        await self._move_and_wait(self._dial_from_user(target_user))

    @twf.putter
    async def twf(self, instance, value):
        """Tweak forward by TWV."""
        if value:
            await self._tweak(+1.0)
        return 0

    @twr.putter
    async def twr(self, instance, value):
        """Tweak in reverse by TWV."""
        if value:
            await self._tweak(-1.0)
        return 0

    async def _home(self):
        home_dial = self.settings.start + self._dial_shift
        ok = await self._request_move(home_dial)
        if ok:
            await self._wait_done()
            self._homed = True
            await self.msta.write(self._msta())

    @homf.putter
    async def homf(self, instance, value):
        """Home: move to the axis's start position and mark it homed."""
        if value:
            await self._home()
        return 0

    @homr.putter
    async def homr(self, instance, value):
        """Home: move to the axis's start position and mark it homed."""
        if value:
            await self._home()
        return 0

    @stop.putter
    async def stop(self, instance, value):
        """Stop the motion."""
        if value:
            await self._halt()
        return 0

    @spmg.putter
    async def spmg(self, instance, value):
        """Stop, pause or resume (Move, Go) the motion."""
        if value == "Stop":
            await self._halt()
        elif value == "Pause":
            if await self._cancel_motion():
                self._motion = None
                self._paused = True
                # like the record: the axis stands (MOVN 0), the move is not done (DMOV stays 0)
                await self.movn.write(0)
                await self.mip.write(0)
                await self.msta.write(self._msta())
        elif self._paused:  # Move or Go resume a paused move
            self._paused = False
            self._start_motion()
        return value

    async def _redefine_user(self, user: float):
        """SET mode: make the readback read ``user`` without moving."""
        if self.foff.value == "Variable":
            self._offset = user - self._sign * self._dial()
            await self.off.write(self._offset, verify_value=False)
        else:
            new_dial = self._dial_from_user(user)
            shift = new_dial - self._dial()
            self._dial_shift += shift
            # Dial limits follow the physical travel, which has not changed.
            await self.dhlm.write(self.dhlm.value + shift, verify_value=False)
            await self.dllm.write(self.dllm.value + shift, verify_value=False)
        self._target_dial = self._dial()
        await self._publish_limits()
        await self._publish_position(setpoint=True)

    def _check_user(self, *, offset: float | None = None, dial_limits: tuple[float, float] | None = None,
                    field: str) -> None:
        """Refuse a put after which a user coordinate (position or limit) would not be finite."""
        off = self._offset if offset is None else offset
        lo, hi = dial_limits or (self.dllm.value, self.dhlm.value)
        for dial in (lo, hi, self._dial(), self._target_dial):
            if not math.isfinite(self._sign * dial + off):
                raise ValueError(f"{field}: the user coordinates would not be finite")

    @off.putter
    async def off(self, instance, value):
        """Set the user offset OFF, refused where a user coordinate would not be finite."""
        off = _finite(value, "OFF")
        self._check_user(offset=off, field="OFF")
        self._offset = off
        await self._publish_limits()
        await self._publish_position(setpoint=True)
        return self._offset

    @twv.putter
    async def twv(self, instance, value):
        """Take a finite tweak step TWV."""
        return _finite(value, "TWV")

    @dir.putter
    async def dir(self, instance, value):
        """Set the user direction (Pos, Neg) and republish the limits and position."""
        # As in the record, OFF is kept: the user coordinates change sign.
        self._sign = -1.0 if value == "Neg" else 1.0
        await self._publish_limits()
        await self._publish_position(setpoint=True)
        return value

    @hlm.putter
    async def hlm(self, instance, value):
        """Set the user high limit (the dial limit it maps to)."""
        await self._set_user_limit(_finite(value, "HLM"), high=True)
        return SkipWrite

    @llm.putter
    async def llm(self, instance, value):
        """Set the user low limit (the dial limit it maps to)."""
        await self._set_user_limit(_finite(value, "LLM"), high=False)
        return SkipWrite

    async def _set_user_limit(self, user_value: float, *, high: bool):
        dial = _finite(self._dial_from_user(user_value), "HLM" if high else "LLM")
        # With DIR=Neg the user high limit is the dial low limit.
        dial_high = high if self._sign > 0 else not high
        await self._set_dial_limit(dial, high=dial_high)
        await self._publish_limits()

    async def _set_dial_limit(self, dial: float, *, high: bool):
        lo, hi = (self.dllm.value, dial) if high else (dial, self.dhlm.value)
        self._check_user(dial_limits=(lo, hi), field="DHLM" if high else "DLLM")
        await (self.dhlm if high else self.dllm).write(dial, verify_value=False)

    @dhlm.putter
    async def dhlm(self, instance, value):
        """Set the dial high limit and republish the user limits."""
        await self._set_dial_limit(_finite(value, "DHLM"), high=True)
        await self._publish_limits()
        return SkipWrite

    @dllm.putter
    async def dllm(self, instance, value):
        """Set the dial low limit and republish the user limits."""
        await self._set_dial_limit(_finite(value, "DLLM"), high=False)
        await self._publish_limits()
        return SkipWrite

    def _slowest(self) -> float:
        """The least speed that crosses the whole travel within :data:`MAX_MOVE_TIME`."""
        return (self._axis_high - self._axis_low) / MAX_MOVE_TIME

    @velo.putter
    async def velo(self, instance, value):
        """Take a speed VELO fast enough to cross the travel within ``MAX_MOVE_TIME``, kept within [VBAS, VMAX]."""
        v = _finite(value, "VELO", above=0.0)
        if v < self._slowest():
            raise ValueError(f"VELO must be >= {self._slowest():.3g} (the whole travel within {MAX_MOVE_TIME:g} s)")
        vmax = self.vmax.value
        return max(min(v, vmax) if vmax > 0 else v, self.vbas.value)  # within [VBAS, VMAX], as the record

    @vmax.putter
    async def vmax(self, instance, value):
        """Take the maximum speed VMAX (0: none), lowering VELO to it where faster."""
        vmax = _finite(value, "VMAX", at_least=0.0)  # 0: no maximum
        if 0 < vmax < max(self.vbas.value, self._slowest()):
            raise ValueError(f"VMAX must be 0 or >= max(VBAS, {self._slowest():.3g})")
        if vmax > 0 and self.velo.value > vmax:
            await self.velo.write(vmax, verify_value=False)
        return vmax

    @vbas.putter
    async def vbas(self, instance, value):
        """Take the base speed VBAS (at most VMAX), raising VELO to it where slower."""
        vbas = _finite(value, "VBAS", at_least=0.0)
        if self.vmax.value > 0 and vbas > self.vmax.value:
            raise ValueError("VBAS must be <= VMAX")
        if self.velo.value < vbas:
            await self.velo.write(vbas, verify_value=False)
        return vbas

    @hvel.putter
    async def hvel(self, instance, value):
        """Take the homing speed HVEL, its sign dropped."""
        return _finite(abs(_finite(value, "HVEL")), "HVEL", above=0.0)  # a speed: its sign is dropped

    @accl.putter
    async def accl(self, instance, value):
        """Take the acceleration time ACCL, within [1 ms, ``MAX_ACCEL_TIME``]."""
        # the record's ACCL is seconds to velocity: kept within [1 ms, MAX_ACCEL_TIME]
        return min(max(_finite(value, "ACCL"), 1e-3), MAX_ACCEL_TIME)

    @mres.putter
    async def mres(self, instance, value):
        """Take a positive motor resolution MRES (EGU per step)."""
        return _finite(value, "MRES", above=0.0)

    @eres.putter
    async def eres(self, instance, value):
        """Take a finite encoder resolution ERES."""
        return _finite(value, "ERES")

    @rres.putter
    async def rres(self, instance, value):
        """Take a finite readback resolution RRES."""
        return _finite(value, "RRES")

    @rdbd.putter
    async def rdbd(self, instance, value):
        """Take a non-negative retry deadband RDBD."""
        return _finite(value, "RDBD", at_least=0.0)

    @rtry.putter
    async def rtry(self, instance, value):
        """Take the retry count RTRY, within [0, 255]."""
        return min(max(int(value), 0), 255)  # the record's RTRY is an unsigned char

    @ueip.putter
    async def ueip(self, instance, value):
        """Use the encoder for the readback (refused on an axis without one)."""
        if value == "Yes" and not self.mechanics.encoder:
            raise ValueError("UEIP: this axis has no encoder")
        return value

    @bdst.putter
    async def bdst(self, instance, value):
        """Take the backlash distance BDST, shorter than the axis's travel."""
        bdst = _finite(value, "BDST")
        if abs(bdst) > self._axis_high - self._axis_low:
            raise ValueError("BDST must be shorter than the axis's travel")
        return bdst

    @bvel.putter
    async def bvel(self, instance, value):
        """Take a backlash speed BVEL fast enough to cross the travel within ``MAX_MOVE_TIME``."""
        v = _finite(value, "BVEL", above=0.0)
        if v < self._slowest():
            raise ValueError(f"BVEL must be >= {self._slowest():.3g} (the whole travel within {MAX_MOVE_TIME:g} s)")
        return v

    @bacc.putter
    async def bacc(self, instance, value):
        """Take the backlash acceleration time BACC, within [1 ms, ``MAX_ACCEL_TIME``]."""
        return min(max(_finite(value, "BACC"), 1e-3), MAX_ACCEL_TIME)

    @urev.putter
    async def urev(self, instance, value):
        """Take a finite distance per motor revolution UREV."""
        return _finite(value, "UREV")

    @prec.putter
    async def prec(self, instance, value):
        """Take the display precision PREC (within [0, 15]) and set it on the position fields."""
        value = min(max(int(value), 0), 15)
        for pv in (self.val, self.rbv, self.dval, self.drbv, self.hlm, self.llm, self.dhlm, self.dllm):
            await pv.write_metadata(precision=value)
        return value

    @egu.putter
    async def egu(self, instance, value):
        """Take the engineering units EGU and set them on the position fields."""
        for pv in (self.val, self.rbv, self.dval, self.drbv, self.hlm, self.llm, self.dhlm, self.dllm):
            await pv.write_metadata(units=str(value))
        return value
