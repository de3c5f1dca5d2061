"""Classic ophyd (v1) devices of the METRIXS beamline, built on ``ophyd.EpicsMotor``.

They have the same layout and PVs as the ophyd-async ones (:mod:`bluesky_offsets.epics.devices`).

:func:`make_beamline_v1`, :class:`FocusChamberV1` and :func:`make_chamber_v1` (full PV names).
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

from bluesky_offsets.epics.pvs import (
    CHAMBER_PVS,
    ChamberError,
    FixedParameterError,
    chamber_pvs,
    fixed_message,
    motor_pvs,
    stage_pvs,
)
from bluesky_offsets.physics.parameters import METRIXS, Parameter, ParameterTable


class FixedParameterV1(SignalRO):
    """ophyd v1 fixed-but-unknown parameter: reads its design value, refuses ``set``/``put``."""

    def __init__(self, *, parameter: Parameter, **kwargs):
        self.parameter = parameter
        kwargs.setdefault("value", parameter.reference)
        super().__init__(**kwargs)

    def put(self, value, **kwargs):
        """Refuse: raise :class:`~bluesky_offsets.epics.pvs.FixedParameterError`."""
        raise FixedParameterError(fixed_message(self.parameter))

    def set(self, value, **kwargs):
        """Refuse: raise :class:`~bluesky_offsets.epics.pvs.FixedParameterError`."""
        raise FixedParameterError(fixed_message(self.parameter))

    def describe(self):
        """The signal's description, with the parameter's unit as ``units``."""
        desc = super().describe()
        desc[self.name]["units"] = self.parameter.unit
        return desc


class MetrixsBeamlineV1(DeviceV1):
    """Base of the classes made by :func:`make_beamline_v1` (components are added there)."""

    table: ParameterTable = METRIXS
    _paths: dict[str, tuple[str, str]] = {}

    def parameter(self, name: str):
        """Device of a parameter by its table name (``"E1.rotationXerror"``)."""
        comp, axis = self._paths[self.table[name].name]
        return getattr(getattr(self, comp), axis)

    @property
    def motors(self) -> dict[str, EpicsMotor]:
        """Parameter name -> ``EpicsMotor``, table order (the motorized parameters)."""
        return {n: self.parameter(n) for n in self.table.motorized_names}

    @property
    def fixed(self) -> dict[str, FixedParameterV1]:
        """Parameter name -> fixed parameter signal (the fixed-but-unknown ones)."""
        return {n: self.parameter(n) for n in self.table.fixed_names}


def make_beamline_v1(prefix: str = "", name: str = "metrixs", *, table: ParameterTable = METRIXS,
                     pv_names: Mapping[str, str] | None = None,
                     stage: Mapping[str, str] | None = None) -> MetrixsBeamlineV1:
    """The beamline as a classic ophyd Device of ``EpicsMotor`` components.

    The same layout as :class:`MetrixsBeamline`, the chamber's stage as ``chamber_stage`` where
    ``stage`` names its records.
    """
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
    if stage:
        axes = {a: Cpt(EpicsMotor, pv, kind="hinted") for a, pv in stage_pvs("", stage).items()}
        comp_cpts["chamber_stage"] = Cpt(create_device_from_components("ChamberStageV1", **axes), "")
    cls = create_device_from_components("MetrixsBeamlineV1", base_class=MetrixsBeamlineV1,
                                        docstring=MetrixsBeamlineV1.__doc__, **comp_cpts)
    cls.table, cls._paths = table, paths
    return cls("", name=name)


# signal -> (class, kind, options): the same signals as the ophyd-async FocusChamber
_CHAMBER_V1 = {
    "acquire": (EpicsSignal, "omitted", {"put_complete": True}),
    "status": (EpicsSignalRO, "omitted", {"string": True}),
    "message": (EpicsSignalRO, "omitted", {"string": True}),
    **{k: (EpicsSignalRO, "normal", {"auto_monitor": False})
       for k in ("hist_x", "hist_y", "total_counts", "array_counter", "image", "profile_x", "profile_y")},
    "num_rays": (EpicsSignal, "config", {}),
    "acquire_time": (EpicsSignal, "config", {}),
    **{k: (EpicsSignalRO, "config", {}) for k in ("axis_x", "axis_y", "profile_axis_x", "profile_axis_y")},
    **{k: (EpicsSignalRO, "config", {"string": True}) for k in ("truth_id", "table_version", "backend")},
    "transmission": (EpicsSignalRO, "omitted", {}),
}


def _chamber_components(pvs: Mapping[str, str]) -> dict[str, Cpt]:
    return {k: Cpt(cls, pvs[k], kind=kind, **kw) for k, (cls, kind, kw) in _CHAMBER_V1.items()}


class ChamberV1Base(DeviceV1):
    """The focus chamber's behaviour: a frame per ``trigger``.

    Its signals come from :data:`_CHAMBER_V1` with the PV names of :class:`FocusChamberV1` or
    :func:`make_chamber_v1`.
    """

    def __init__(self, prefix: str = "", *, name: str, acquire_timeout: float = 120.0, **kwargs):
        super().__init__(prefix, name=name, **kwargs)
        self.acquire_timeout = acquire_timeout

    def trigger(self):
        """Acquire one frame; the status fails with :class:`~bluesky_offsets.epics.pvs.ChamberError` if it does."""
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


FocusChamberV1 = create_device_from_components(
    "FocusChamberV1", base_class=ChamberV1Base, **_chamber_components(CHAMBER_PVS),
    docstring="Classic ophyd focus-chamber detector: the PVs of :class:`FocusChamber` after ``prefix``.")


def make_chamber_v1(prefix: str = "", *, name: str = "chamber", pv_names: Mapping[str, str] | None = None,
                    acquire_timeout: float = 120.0) -> ChamberV1Base:
    """The focus chamber as a classic ophyd Device with full PV names.

    ``pv_names``: signal -> PV, the others ``prefix`` + the simulated IOC's suffix, e.g. from a
    :class:`bluesky_offsets.epics.pvmap.PVMap`.
    """
    cls = create_device_from_components("FocusChamberV1", base_class=ChamberV1Base,
                                        docstring=FocusChamberV1.__doc__,
                                        **_chamber_components(chamber_pvs(prefix, pv_names)))
    return cls("", name=name, acquire_timeout=acquire_timeout)
