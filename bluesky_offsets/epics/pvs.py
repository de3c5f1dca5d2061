"""METRIXS's EPICS names: the PV of each motorized parameter and chamber signal, and the devices' errors.

Which PV each motorized parameter and each focus-chamber signal reads, and the errors the
devices raise.

PV names default to ``<prefix><component>:<axis>`` (motor records) and
``<prefix>chamber:<PV>`` (detector), as served by ``sim_iocs.metrixs``; the real
beamline's names are given with ``pv_names={parameter name: record name}`` and
``pv_names={"hist_x": "...", ...}`` for the chamber.
"""

from __future__ import annotations

from collections.abc import Mapping

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.parameters import Parameter, ParameterTable


class FixedParameterError(TypeError):
    """A fixed-but-unknown parameter was asked to move."""


class ChamberError(RuntimeError):
    """The focus chamber reported a failed or aborted acquisition."""


class MotionError(RuntimeError):
    """A motor did not arrive where it was sent (stalled, stopped, at a limit switch)."""


def fixed_message(p: Parameter) -> str:
    """The error message for an attempt to move the fixed-but-unknown parameter ``p``."""
    return (f"{p.name} ({p.description}) is a fixed parameter, not a motor: it cannot be set. "
            f"Its true value is unknown; the offset finder estimates it as an offset from the "
            f"design value {p.reference:g} {p.unit}.")


def default_motor_pv(param: Parameter, prefix: str = "") -> str:
    """``prefix + "e1:rx"`` for the parameter with device path ``e1.rx`` (the simulation IOC's names)."""
    return prefix + param.device.replace(".", ":")


def motor_pvs(table: ParameterTable, prefix: str, pv_names: Mapping[str, str] | None) -> dict[str, str]:
    """Motor record per motorized parameter of ``table``: from ``pv_names``, else the simulation IOC's name."""
    pv_names = dict(pv_names or {})
    unknown = [n for n in pv_names if n not in table.motorized_names]
    if unknown:
        raise InputError(f"pv_names: {unknown} are not motorized parameters of table {table.name!r}")
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


def chamber_pvs(prefix: str, pv_names: Mapping[str, str] | None) -> dict[str, str]:
    """Full PV per chamber signal: from ``pv_names``, else ``prefix`` + its suffix in :data:`CHAMBER_PVS`."""
    pv_names = dict(pv_names or {})
    unknown = set(pv_names) - set(CHAMBER_PVS)
    if unknown:
        raise InputError(f"pv_names: unknown chamber signals {sorted(unknown)}; known: {sorted(CHAMBER_PVS)}")
    return {k: pv_names.get(k, prefix + v) for k, v in CHAMBER_PVS.items()}


STAGE_AXES = ("x", "y", "z")
"""The focus chamber's translation stage (:data:`bluesky_offsets.physics.screen.STAGE`)."""


def stage_pvs(prefix: str, pv_names: Mapping[str, str] | None) -> dict[str, str]:
    """Motor record per stage axis: from ``pv_names``, else the simulation IOC's name.

    The simulation IOC's are ``<prefix>x`` ... (``prefix`` the chamber's).
    """
    pv_names = dict(pv_names or {})
    unknown = set(pv_names) - set(STAGE_AXES)
    if unknown:
        raise InputError(f"stage: unknown axes {sorted(unknown)}; the stage has {', '.join(STAGE_AXES)}")
    return {a: pv_names.get(a, prefix + a) for a in STAGE_AXES}
