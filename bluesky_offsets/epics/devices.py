"""Ophyd-async devices of the METRIXS beamline: 28 motors, 6 fixed parameters, the focus chamber.

* :class:`MetrixsBeamline` groups the 28 motors (unmodified
  ``ophyd_async.epics.motor.Motor``) and the 6 fixed parameters by component
  after the parameter table's ``device`` paths: ``beamline.e1.rx`` is the E1
  pitch motor, ``beamline.m1.radius`` the (fixed) M1 radius.
  ``beamline.motors`` / ``beamline.fixed`` map parameter names to devices.
* :class:`FixedParameter` is readable (its design value) and refuses ``set``.
* :class:`FocusChamber` is the focus-chamber detector: triggerable, readable.

The classic ophyd (v1) equivalents are in :mod:`bluesky_offsets.epics.devices_v1`; the PV
names in :mod:`bluesky_offsets.epics.pvs`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import cast

import numpy as np
from ophyd_async.core import (
    Array1D,
    AsyncStatus,
    Device,
    StandardReadable,
    StrictEnum,
    soft_signal_r_and_setter,
)
from ophyd_async.core import StandardReadableFormat as Format
from ophyd_async.epics.core import epics_signal_r, epics_signal_rw
from ophyd_async.epics.motor import Motor

from bluesky_offsets.epics.pvs import (
    ChamberError,
    STAGE_AXES,
    FixedParameterError,
    chamber_pvs,
    fixed_message,
    motor_pvs,
    stage_pvs,
)
from bluesky_offsets.physics.parameters import METRIXS, Parameter, ParameterTable


class FixedParameter(StandardReadable):
    """A fixed-but-unknown parameter (radius, half-axis): reads its design value, refuses ``set``."""

    def __init__(self, parameter: Parameter, name: str = ""):
        self.parameter = parameter
        with self.add_children_as_readables(Format.HINTED_SIGNAL):
            self.value, _ = soft_signal_r_and_setter(float, initial_value=parameter.reference,
                                                     units=parameter.unit)
        super().__init__(name=name)

    def set(self, value, *args, **kwargs):
        """Refuse: raise :class:`~bluesky_offsets.epics.pvs.FixedParameterError` (no motor moves it)."""
        raise FixedParameterError(fixed_message(self.parameter))


class BeamlineComponent(Device):
    """Motors and fixed parameters of one optical component (``source``, ``asbl``, ``m1`` ...)."""

    def __init__(self, children: Mapping[str, Device], name: str = ""):
        for attr, dev in children.items():
            setattr(self, attr, dev)
        super().__init__(name=name)


class ChamberStage(Device):
    """The focus chamber's translation stage: ``x``, ``y``, ``z`` motors (mm)."""

    def __init__(self, pv_names: Mapping[str, str], name: str = ""):
        for axis, pv in pv_names.items():
            setattr(self, axis, Motor(pv))
        super().__init__(name=name)

    @property
    def axes(self) -> dict[str, Motor]:
        """Axis name (``x``, ``y``, ``z``) -> the stage's motor."""
        return {a: getattr(self, a) for a in STAGE_AXES}


class MetrixsBeamline(Device):
    """The METRIXS beamline: 28 motors and 6 fixed parameters grouped by component.

    The focus chamber's stage (``chamber_stage``) is part of it where it has one.

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
    stage : mapping, optional
        ``{"x": record, "y": record, "z": record}``: the chamber stage's motors (none: no stage).
    """

    def __init__(self, prefix: str = "", name: str = "", *, table: ParameterTable = METRIXS,
                 pv_names: Mapping[str, str] | None = None, stage: Mapping[str, str] | None = None):
        self.table = table
        pvs = motor_pvs(table, prefix, pv_names)
        groups: dict[str, dict[str, Device]] = {}
        self._paths: dict[str, tuple[str, str]] = {}
        for p in table:
            comp, axis = p.device.split(".", 1)
            groups.setdefault(comp, {})[axis] = Motor(pvs[p.name]) if p.motorized else FixedParameter(p)
            self._paths[p.name] = (comp, axis)
        for comp, children in groups.items():
            setattr(self, comp, BeamlineComponent(children))
        if stage:
            self.chamber_stage = ChamberStage(stage_pvs("", stage))
        super().__init__(name=name)

    def parameter(self, name: str) -> Device:
        """Device of a parameter by its table name (``"E1.rotationXerror"``)."""
        comp, axis = self._paths[self.table[name].name]
        return getattr(getattr(self, comp), axis)

    @property
    def motors(self) -> dict[str, Motor]:
        """Parameter name -> motor, table order (the 28 motorized parameters)."""
        return {n: cast(Motor, self.parameter(n)) for n in self.table.motorized_names}

    @property
    def fixed(self) -> dict[str, FixedParameter]:
        """Parameter name -> fixed parameter device (the 6 fixed-but-unknown ones)."""
        return {n: cast(FixedParameter, self.parameter(n)) for n in self.table.fixed_names}


class ChamberStatus(StrictEnum):
    """The focus chamber's acquisition state, as its ``status`` PV gives it."""

    IDLE = "Idle"
    ACQUIRING = "Acquiring"
    ERROR = "Error"
    ABORTED = "Aborted"


class FocusChamber(StandardReadable):
    """Focus-chamber detector: ``trigger()`` acquires one frame, ``read()`` gives what it measured.

    The reading holds both histograms, the image (flattened, rows y), both profiles at the
    camera's resolution, the ray count and the frame number.

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
        pv = chamber_pvs(prefix, pv_names)
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
        """Acquire one frame; :class:`~bluesky_offsets.epics.pvs.ChamberError` if it fails or is aborted."""
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




def focus_camera(prefix: str, directory, *, name: str = "camera"):
    """The focus chamber's camera: ophyd-async's areaDetector classes as they are.

    Its frames are written by the camera's HDF5 plugin into ``directory`` (a path the IOC can
    write and this process can read).

    ``prefix`` is the detector's (``BL:cam:``, serving ``cam1:`` and ``HDF1:``).  A plain bluesky
    ``count([camera])`` takes frames; the run store records them as ``StreamResource``/``StreamDatum``
    documents and reads them back from the files.
    """
    from pathlib import Path

    from ophyd_async.core import StaticPathProvider, UUIDFilenameProvider
    from ophyd_async.epics.adcore import ADWriterFactory
    from ophyd_async.epics.adsimdetector import SimDetector

    provider = StaticPathProvider(UUIDFilenameProvider(), Path(directory))
    return SimDetector(prefix, ADWriterFactory.hdf(provider), name=name)
