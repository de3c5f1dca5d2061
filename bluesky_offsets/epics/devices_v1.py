"""Classic ophyd (v1) devices of the METRIXS beamline, built on ``ophyd.EpicsMotor``: the same
layout and PVs as the ophyd-async ones (:mod:`bluesky_offsets.epics.devices`).

:func:`make_beamline_v1` and :class:`FocusChamberV1`.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping

from ophyd import Component as Cpt
from ophyd import Device as DeviceV1
from ophyd import EpicsMotor, EpicsSignal, EpicsSignalRO
from ophyd.device import create_device_from_components
from ophyd.signal import SignalRO
from ophyd.status import DeviceStatus

from bluesky_offsets.epics.pvs import ChamberError, FixedParameterError, fixed_message, motor_pvs
from bluesky_offsets.physics.parameters import METRIXS, Parameter, ParameterTable


class FixedParameterV1(SignalRO):
    """ophyd v1 fixed-but-unknown parameter: reads its design value, refuses ``set``/``put``."""

    def __init__(self, *, parameter: Parameter, **kwargs):
        self.parameter = parameter
        kwargs.setdefault("value", parameter.reference)
        super().__init__(**kwargs)

    def put(self, value, **kwargs):
        raise FixedParameterError(fixed_message(self.parameter))

    def set(self, value, **kwargs):
        raise FixedParameterError(fixed_message(self.parameter))

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
    pvs = motor_pvs(table, prefix, pv_names)
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
