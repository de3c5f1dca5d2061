"""Ophyd devices of the METRIXS beamline: 28 motors, 6 fixed parameters, the focus chamber.

ophyd-async is the primary API:

* :class:`MetrixsBeamline` groups the 28 motors (unmodified
  ``ophyd_async.epics.motor.Motor``) and the 6 fixed parameters by component
  after the parameter table's ``device`` paths: ``beamline.e1.rx`` is the E1
  pitch motor, ``beamline.m1.radius`` the (fixed) M1 radius.
  ``beamline.motors`` / ``beamline.fixed`` map parameter names to devices.
* :class:`FixedParameter` is readable (its design value) and refuses ``set``.
* :class:`FocusChamber` is the focus-chamber detector: triggerable, readable.

Classic ophyd (v1) equivalents, built on ``ophyd.EpicsMotor``:
:func:`make_beamline_v1` and :class:`FocusChamberV1`.

PV names default to ``<prefix><component>:<axis>`` (motor records) and
``<prefix>chamber:<PV>`` (detector), as served by ``sim_iocs.metrixs``; the real
beamline's names are given with ``pv_names={parameter name: record name}``
and ``FocusChamber(prefix, pv_names={"hist_x": "...", ...})``.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping

import numpy as np

from bluesky_offsets.physics.parameters import METRIXS, Parameter, ParameterTable


class FixedParameterError(TypeError):
    """A fixed-but-unknown parameter was asked to move."""


class ChamberError(RuntimeError):
    """The focus chamber reported a failed or aborted acquisition."""


def _fixed_message(p: Parameter) -> str:
    return (f"{p.name} ({p.description}) is a fixed parameter, not a motor: it cannot be set. "
            f"Its true value is unknown; the offset finder estimates it as an offset from the "
            f"design value {p.reference:g} {p.unit}.")


def default_motor_pv(param: Parameter, prefix: str = "") -> str:
    """``prefix + "e1:rx"`` for the parameter with device path ``e1.rx`` (the simulation IOC's names)."""
    return prefix + param.device.replace(".", ":")


def _motor_pvs(table: ParameterTable, prefix: str, pv_names: Mapping[str, str] | None) -> dict[str, str]:
    pv_names = dict(pv_names or {})
    unknown = [n for n in pv_names if n not in table.motorized_names]
    if unknown:
        raise ValueError(f"pv_names: {unknown} are not motorized parameters of table {table.name!r}")
    return {p.name: pv_names.get(p.name, default_motor_pv(p, prefix)) for p in table if p.motorized}


CHAMBER_PVS = {
    "acquire": "Acquire", "acquire_time": "AcquireTime", "num_rays": "NumRays",
    "hist_x": "HistX", "hist_y": "HistY", "image": "Image", "total_counts": "TotalCounts",
    "transmission": "Transmission", "array_counter": "ArrayCounter", "axis_x": "AxisX", "axis_y": "AxisY",
    "status": "Status", "message": "Message", "truth_id": "TruthId", "table_version": "TableVersion",
    "backend": "Backend", "profile_x": "ProfileX", "profile_y": "ProfileY", "profile_axis_x": "ProfileAxisX",
    "profile_axis_y": "ProfileAxisY",
}
"""Detector signal -> PV suffix (after the chamber prefix) on the simulation IOC."""


def _chamber_pvs(prefix: str, pv_names: Mapping[str, str] | None) -> dict[str, str]:
    pv_names = dict(pv_names or {})
    unknown = set(pv_names) - set(CHAMBER_PVS)
    if unknown:
        raise ValueError(f"pv_names: unknown chamber signals {sorted(unknown)}; known: {sorted(CHAMBER_PVS)}")
    return {k: pv_names.get(k, prefix + v) for k, v in CHAMBER_PVS.items()}


# =========================================================================== #
# ophyd-async
# =========================================================================== #
from ophyd_async.core import (  # noqa: E402
    Array1D,
    AsyncStatus,
    Device,
    StandardReadable,
    StrictEnum,
    soft_signal_r_and_setter,
)
from ophyd_async.core import StandardReadableFormat as Format  # noqa: E402
from ophyd_async.epics.core import epics_signal_r, epics_signal_rw  # noqa: E402
from ophyd_async.epics.motor import Motor  # noqa: E402


class FixedParameter(StandardReadable):
    """A fixed-but-unknown parameter (radius, half-axis): reads its design value, refuses ``set``."""

    def __init__(self, parameter: Parameter, name: str = ""):
        self.parameter = parameter
        with self.add_children_as_readables(Format.HINTED_SIGNAL):
            self.value, _ = soft_signal_r_and_setter(float, initial_value=parameter.reference,
                                                     units=parameter.unit)
        super().__init__(name=name)

    def set(self, value, *args, **kwargs):
        raise FixedParameterError(_fixed_message(self.parameter))


class BeamlineComponent(Device):
    """Motors and fixed parameters of one optical component (``source``, ``asbl``, ``m1`` ...)."""

    def __init__(self, children: Mapping[str, Device], name: str = ""):
        for attr, dev in children.items():
            setattr(self, attr, dev)
        super().__init__(name=name)


class MetrixsBeamline(Device):
    """The METRIXS beamline: 28 motors and 6 fixed parameters grouped by component.

    Parameters
    ----------
    prefix : str
        PV prefix of the motor records (``"SIM:METRIXS:"`` -> ``SIM:METRIXS:e1:rx``).
    name : str
        Device name (reading keys become ``<name>-e1-rx``).
    table : ParameterTable
        Parameter table (default: the paper's 34 parameters).
    pv_names : mapping, optional
        ``{parameter name: motor record name}`` overriding the default names,
        e.g. for the real beamline.
    """

    def __init__(self, prefix: str = "", name: str = "", *, table: ParameterTable = METRIXS,
                 pv_names: Mapping[str, str] | None = None):
        self.table = table
        pvs = _motor_pvs(table, prefix, pv_names)
        groups: dict[str, dict[str, Device]] = {}
        self._paths: dict[str, tuple[str, str]] = {}
        for p in table:
            comp, axis = p.device.split(".", 1)
            groups.setdefault(comp, {})[axis] = Motor(pvs[p.name]) if p.motorized else FixedParameter(p)
            self._paths[p.name] = (comp, axis)
        for comp, children in groups.items():
            setattr(self, comp, BeamlineComponent(children))
        super().__init__(name=name)

    def parameter(self, name: str) -> Device:
        """Device of a parameter by its table name (``"E1.rotationXerror"``)."""
        comp, axis = self._paths[self.table[name].name]
        return getattr(getattr(self, comp), axis)

    @property
    def motors(self) -> dict[str, Motor]:
        """Parameter name -> motor, table order (the 28 motorized parameters)."""
        return {n: self.parameter(n) for n in self.table.motorized_names}

    @property
    def fixed(self) -> dict[str, FixedParameter]:
        """Parameter name -> fixed parameter device (the 6 fixed-but-unknown ones)."""
        return {n: self.parameter(n) for n in self.table.fixed_names}


class ChamberStatus(StrictEnum):
    IDLE = "Idle"
    ACQUIRING = "Acquiring"
    ERROR = "Error"
    ABORTED = "Aborted"


class FocusChamber(StandardReadable):
    """Focus-chamber detector: ``trigger()`` acquires one frame, ``read()`` gives both
    histograms, the image (flattened, rows y), both profiles at the camera's resolution,
    the ray count and the frame number.

    Parameters
    ----------
    prefix : str
        PV prefix of the detector (``"SIM:METRIXS:chamber:"``).
    name : str
        Device name.
    pv_names : mapping, optional
        ``{signal: full PV name}`` overriding defaults (see :data:`CHAMBER_PVS`).
    acquire_timeout : float
        Longest time a frame may take (s).
    """

    def __init__(self, prefix: str = "", name: str = "", *, pv_names: Mapping[str, str] | None = None,
                 acquire_timeout: float = 120.0):
        pv = _chamber_pvs(prefix, pv_names)
        self.acquire_timeout = float(acquire_timeout)
        self.acquire = epics_signal_rw(bool, pv["acquire"])
        self.status = epics_signal_r(ChamberStatus, pv["status"])
        self.message = epics_signal_r(str, pv["message"])
        # Read uncached: the values of *this* frame, fetched after the put-completion.
        with self.add_children_as_readables(Format.UNCACHED_SIGNAL):
            self.hist_x = epics_signal_r(Array1D[np.float64], pv["hist_x"])
            self.hist_y = epics_signal_r(Array1D[np.float64], pv["hist_y"])
            self.total_counts = epics_signal_r(int, pv["total_counts"])
            self.array_counter = epics_signal_r(int, pv["array_counter"])
            self.image = epics_signal_r(Array1D[np.float64], pv["image"])
            self.profile_x = epics_signal_r(Array1D[np.float64], pv["profile_x"])
            self.profile_y = epics_signal_r(Array1D[np.float64], pv["profile_y"])
        with self.add_children_as_readables(Format.CONFIG_SIGNAL):
            self.num_rays = epics_signal_rw(int, pv["num_rays"])
            self.acquire_time = epics_signal_rw(float, pv["acquire_time"])
            self.axis_x = epics_signal_r(Array1D[np.float64], pv["axis_x"])
            self.axis_y = epics_signal_r(Array1D[np.float64], pv["axis_y"])
            self.profile_axis_x = epics_signal_r(Array1D[np.float64], pv["profile_axis_x"])
            self.profile_axis_y = epics_signal_r(Array1D[np.float64], pv["profile_axis_y"])
            self.truth_id = epics_signal_r(str, pv["truth_id"])
            self.table_version = epics_signal_r(str, pv["table_version"])
            self.backend = epics_signal_r(str, pv["backend"])
        self.transmission = epics_signal_r(float, pv["transmission"])
        super().__init__(name=name)

    @AsyncStatus.wrap
    async def trigger(self):
        try:
            await self.acquire.set(True, timeout=self.acquire_timeout)
        except Exception as exc:  # the put failed: an error or an abort, the chamber says which
            status = await self.status.get_value()
            if status == ChamberStatus.ABORTED:
                raise ChamberError(f"{self.name}: acquisition aborted: {await self.message.get_value()}") from exc
            detail = await self.message.get_value() if status == ChamberStatus.ERROR else f"{type(exc).__name__}: {exc}"
            raise ChamberError(f"{self.name}: acquisition failed: {detail}") from exc
        status = await self.status.get_value()
        if status != ChamberStatus.IDLE:
            msg = await self.message.get_value()
            raise ChamberError(f"{self.name}: acquisition {status.value.lower()}: {msg}")


# =========================================================================== #
# classic ophyd (v1)
# =========================================================================== #
from ophyd import Component as Cpt  # noqa: E402
from ophyd import Device as DeviceV1  # noqa: E402
from ophyd import EpicsMotor, EpicsSignal, EpicsSignalRO  # noqa: E402
from ophyd.device import create_device_from_components  # noqa: E402
from ophyd.signal import SignalRO  # noqa: E402
from ophyd.status import DeviceStatus  # noqa: E402


class FixedParameterV1(SignalRO):
    """ophyd v1 fixed-but-unknown parameter: reads its design value, refuses ``set``/``put``."""

    def __init__(self, *, parameter: Parameter, **kwargs):
        self.parameter = parameter
        kwargs.setdefault("value", parameter.reference)
        super().__init__(**kwargs)

    def put(self, value, **kwargs):
        raise FixedParameterError(_fixed_message(self.parameter))

    def set(self, value, **kwargs):
        raise FixedParameterError(_fixed_message(self.parameter))

    def describe(self):
        desc = super().describe()
        desc[self.name]["units"] = self.parameter.unit
        return desc


class MetrixsBeamlineV1(DeviceV1):
    """Base of the classes made by :func:`make_beamline_v1` (components are added there)."""

    table: ParameterTable = METRIXS
    _paths: dict[str, tuple[str, str]] = {}

    def parameter(self, name: str):
        comp, axis = self._paths[self.table[name].name]
        return getattr(getattr(self, comp), axis)

    @property
    def motors(self) -> dict[str, EpicsMotor]:
        return {n: self.parameter(n) for n in self.table.motorized_names}

    @property
    def fixed(self) -> dict[str, FixedParameterV1]:
        return {n: self.parameter(n) for n in self.table.fixed_names}


def make_beamline_v1(prefix: str = "", name: str = "metrixs", *, table: ParameterTable = METRIXS,
                     pv_names: Mapping[str, str] | None = None) -> MetrixsBeamlineV1:
    """The beamline as a classic ophyd Device of ``EpicsMotor``s (same layout as :class:`MetrixsBeamline`)."""
    pvs = _motor_pvs(table, prefix, pv_names)
    comps: dict[str, dict[str, Cpt]] = {}
    paths = {}
    for p in table:
        comp, axis = p.device.split(".", 1)
        if p.motorized:
            cpt = Cpt(EpicsMotor, pvs[p.name], kind="hinted")
        else:
            cpt = Cpt(FixedParameterV1, parameter=p, kind="config")
        comps.setdefault(comp, {})[axis] = cpt
        paths[p.name] = (comp, axis)
    comp_cpts = {comp: Cpt(create_device_from_components(f"{comp.title().replace('_', '')}V1", **children), "")
                 for comp, children in comps.items()}
    cls = create_device_from_components("MetrixsBeamlineV1", base_class=MetrixsBeamlineV1,
                                        docstring=MetrixsBeamlineV1.__doc__, **comp_cpts)
    cls.table, cls._paths = table, paths
    return cls("", name=name)


class FocusChamberV1(DeviceV1):
    """Classic ophyd focus-chamber detector (same PVs as :class:`FocusChamber`)."""

    acquire = Cpt(EpicsSignal, "Acquire", put_complete=True, kind="omitted")
    status = Cpt(EpicsSignalRO, "Status", string=True, kind="omitted")
    message = Cpt(EpicsSignalRO, "Message", string=True, kind="omitted")
    hist_x = Cpt(EpicsSignalRO, "HistX", kind="normal", auto_monitor=False)
    hist_y = Cpt(EpicsSignalRO, "HistY", kind="normal", auto_monitor=False)
    total_counts = Cpt(EpicsSignalRO, "TotalCounts", kind="normal", auto_monitor=False)
    array_counter = Cpt(EpicsSignalRO, "ArrayCounter", kind="normal", auto_monitor=False)
    image = Cpt(EpicsSignalRO, "Image", kind="normal", auto_monitor=False)
    profile_x = Cpt(EpicsSignalRO, "ProfileX", kind="normal", auto_monitor=False)
    profile_y = Cpt(EpicsSignalRO, "ProfileY", kind="normal", auto_monitor=False)
    num_rays = Cpt(EpicsSignal, "NumRays", kind="config")
    acquire_time = Cpt(EpicsSignal, "AcquireTime", kind="config")
    axis_x = Cpt(EpicsSignalRO, "AxisX", kind="config")
    axis_y = Cpt(EpicsSignalRO, "AxisY", kind="config")
    profile_axis_x = Cpt(EpicsSignalRO, "ProfileAxisX", kind="config")
    profile_axis_y = Cpt(EpicsSignalRO, "ProfileAxisY", kind="config")
    truth_id = Cpt(EpicsSignalRO, "TruthId", string=True, kind="config")
    table_version = Cpt(EpicsSignalRO, "TableVersion", string=True, kind="config")
    backend = Cpt(EpicsSignalRO, "Backend", string=True, kind="config")

    def __init__(self, prefix: str = "", *, name: str, acquire_timeout: float = 120.0, **kwargs):
        super().__init__(prefix, name=name, **kwargs)
        self.acquire_timeout = acquire_timeout

    def trigger(self):
        result = DeviceStatus(self, timeout=self.acquire_timeout)
        put = self.acquire.set(1)

        def check():
            # CA gets from a separate thread, never from the CA callback thread.
            try:
                put.wait(self.acquire_timeout)
                status = self.status.get(use_monitor=False)
                if status != "Idle":
                    raise ChamberError(f"{self.name}: acquisition {str(status).lower()}: "
                                       f"{self.message.get(use_monitor=False)}")
            except ChamberError as exc:
                result.set_exception(exc)
            except Exception as exc:  # the put failed: an abort is reported as one
                status = self.status.get(use_monitor=False)
                what = "aborted" if status == "Aborted" else "failed"
                result.set_exception(ChamberError(f"{self.name}: acquisition {what}: {exc}"))
            else:
                result.set_finished()

        threading.Thread(target=check, daemon=True, name=f"{self.name}-trigger").start()
        return result
