"""Which PVs the METRIXS devices use: one file for the 28 motor records and the camera.

Switching from the simulated IOC to the real beamline is this file: a TOML table of
``[motors]`` (parameter name -> motor record) and ``[chamber]`` (detector signal -> PV)::

    name = "METRIXS at BESSY II"
    [motors]
    "E1.rotationXerror" = "METRIXS:E1:PITCH"
    ...
    [chamber]
    acquire = "METRIXS:CAM:Acquire"
    hist_x = "METRIXS:CAM:HistX"
    ...

``bluesky-offsets pv-map --prefix P`` writes the simulated IOC's file (a template to edit);
``bluesky-offsets check-pvs FILE`` connects to every PV and reports the missing ones and the
motor records whose units or soft limits do not match the parameter table
(:func:`check_pvs`).  The queueserver's startup module reads the file named by
``$BLUESKY_OFFSETS_PVS`` (:meth:`PVMap.from_environment`).
"""

from __future__ import annotations

import os
import time
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from bluesky_offsets.epics.pvs import CHAMBER_PVS, STAGE_AXES, chamber_pvs, motor_pvs, stage_pvs
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable

ENV_PVS = "BLUESKY_OFFSETS_PVS"
ENV_PREFIX = "BLUESKY_OFFSETS_PREFIX"
SIM_PREFIX = "SIM:METRIXS:"  # sim_iocs.metrixs.DEFAULT_PREFIX (not imported: the IOC is not needed here)

# the motor-record fields check_pvs reads
MOTOR_FIELDS = ("RBV", "EGU", "LLM", "HLM", "DMOV")


class PVMapError(ValueError):
    """A PV map file that cannot be used (its message names the file and the entry)."""


@dataclass(frozen=True)
class PVMap:
    """Motor record per motorized parameter and PV per focus-chamber signal (full names)."""

    motors: Mapping[str, str]
    chamber: Mapping[str, str]
    name: str = ""
    table: ParameterTable = field(default=METRIXS, repr=False)
    stage: Mapping[str, str] = field(default_factory=dict)  # the chamber's x/y/z motors; empty: none

    def __post_init__(self):
        missing = [n for n in self.table.motorized_names if n not in self.motors]
        unknown = [n for n in self.motors if n not in self.table.motorized_names]
        if unknown:
            raise PVMapError(f"[motors]: {', '.join(unknown)} are not motorized parameters of {self.table.name} "
                             f"(those are: {', '.join(self.table.motorized_names)})")
        if missing:
            raise PVMapError(f"[motors]: no record for {', '.join(missing)}")
        bad = sorted(set(self.chamber) - set(CHAMBER_PVS))
        if bad:
            raise PVMapError(f"[chamber]: unknown signals {', '.join(bad)} (known: {', '.join(CHAMBER_PVS)})")
        if missing := [k for k in CHAMBER_PVS if k not in self.chamber]:
            raise PVMapError(f"[chamber]: no PV for {', '.join(missing)}")
        if bad := sorted(set(self.stage) - set(STAGE_AXES)):
            raise PVMapError(f"[stage]: unknown axes {', '.join(bad)} (the stage has {', '.join(STAGE_AXES)})")
        if self.stage and (missing := [a for a in STAGE_AXES if a not in self.stage]):
            raise PVMapError(f"[stage]: no record for {', '.join(missing)} (name all three axes, or none)")
        for what, pvs in (("motors", self.motors), ("chamber", self.chamber), ("stage", self.stage)):
            for k, v in pvs.items():
                if not isinstance(v, str) or not v.strip():
                    raise PVMapError(f"[{what}] {k}: expected a PV name, got {v!r}")

    # ------------------------------------------------------------------ #
    @classmethod
    def simulated(cls, prefix: str = SIM_PREFIX, table: ParameterTable = METRIXS) -> PVMap:
        """The simulated IOC's names (``sim_iocs.metrixs``) under ``prefix``."""
        return cls(motor_pvs(table, prefix, None), chamber_pvs(prefix + "chamber:", None),
                   f"simulated METRIXS IOC, prefix {prefix}", table, stage_pvs(prefix + "chamber:", None))

    @classmethod
    def from_file(cls, path: str | os.PathLike, table: ParameterTable = METRIXS) -> PVMap:
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except OSError as exc:
            raise PVMapError(f"PV map {path}: {exc.strerror or exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise PVMapError(f"PV map {path}: not TOML: {exc}") from None
        unknown = sorted(set(data) - {"name", "motors", "chamber", "stage"})
        if unknown:
            raise PVMapError(f"PV map {path}: unknown keys {', '.join(unknown)} (name, [motors], [chamber], [stage])")
        try:
            return cls(dict(data.get("motors", {})), dict(data.get("chamber", {})), str(data.get("name", path.stem)),
                       table, dict(data.get("stage", {})))
        except PVMapError as exc:
            raise PVMapError(f"PV map {path}: {exc}") from None

    @classmethod
    def from_environment(cls, table: ParameterTable = METRIXS) -> PVMap:
        """``$BLUESKY_OFFSETS_PVS`` (a file), else the simulated IOC under ``$BLUESKY_OFFSETS_PREFIX``."""
        path = os.environ.get(ENV_PVS)
        if path:
            return cls.from_file(path, table)
        return cls.simulated(os.environ.get(ENV_PREFIX, SIM_PREFIX), table)

    def to_toml(self) -> str:
        lines = ["# PV map of the METRIXS devices (bluesky-offsets): edit the names for another IOC",
                 f"name = {_q(self.name)}", "", "[motors]"]
        for p in self.table:
            if p.motorized:
                lines.append(f"{_q(p.name):36s} = {_q(self.motors[p.name])}  # {p.unit}, {p.description}")
        lines += ["", "[chamber]"]
        lines += [f"{k:16s} = {_q(self.chamber[k])}" for k in CHAMBER_PVS]
        lines += ["", "# the focus chamber's x/y/z translation stage (mm); leave the section out if it has none",
                  "[stage]" if self.stage else "# [stage]"]
        lines += [f"{'' if self.stage else '# '}{a} = {_q(self.stage.get(a, f'CHAMBER:{a.upper()}'))}"
                  for a in STAGE_AXES]
        return "\n".join(lines) + "\n"

    # ------------------------------------------------------------------ #
    def beamline(self, name: str = "metrixs"):
        """The ophyd-async :class:`~bluesky_offsets.epics.devices.MetrixsBeamline` (connect it in ``init_devices``)."""
        from bluesky_offsets.epics.devices import MetrixsBeamline
        return MetrixsBeamline("", name, table=self.table, pv_names=self.motors, stage=self.stage or None)

    def focus_chamber(self, name: str = "chamber"):
        from bluesky_offsets.epics.devices import FocusChamber
        return FocusChamber("", name, pv_names=self.chamber)

    def beamline_v1(self, name: str = "metrixs"):
        """Classic ophyd devices (connect lazily: what a queueserver startup wants)."""
        from bluesky_offsets.epics.devices_v1 import make_beamline_v1
        return make_beamline_v1("", name, table=self.table, pv_names=self.motors, stage=self.stage or None)

    def focus_chamber_v1(self, name: str = "chamber"):
        from bluesky_offsets.epics.devices_v1 import make_chamber_v1
        return make_chamber_v1("", name=name, pv_names=self.chamber)


def _q(text: str) -> str:
    return '"' + str(text).replace("\\", "\\\\").replace('"', '\\"') + '"'


# --------------------------------------------------------------------------- #
# checking a map against the control system
# --------------------------------------------------------------------------- #
@dataclass
class PVCheck:
    """What :func:`check_pvs` found: ``missing`` (entry, PV), ``mismatched`` (entry, PV, why), ``ok`` count."""

    missing: list[tuple[str, str]] = field(default_factory=list)
    mismatched: list[tuple[str, str, str]] = field(default_factory=list)
    ok: int = 0

    @property
    def passed(self) -> bool:
        return not self.missing and not self.mismatched

    def lines(self) -> list[str]:
        out = [f"missing: {k} ({pv}) did not connect" for k, pv in self.missing]
        out += [f"mismatch: {k} ({pv}): {why}" for k, pv, why in self.mismatched]
        return out


def check_pvs(pv_map: PVMap, *, timeout: float = 3.0, progress=None) -> PVCheck:
    """Connect to every PV of ``pv_map`` and compare the motor records with the parameter table.

    A motor record is *mismatched* when its ``EGU`` is not the parameter's unit, or when its soft
    limits (``LLM``, ``HLM``) leave less travel than the table's (``Parameter.limits``): the
    model would ask for moves the record refuses.  Limits are compared as spans, since the
    motors' positions differ from the twin's coordinates by the unknown offsets.  All channels
    are searched at once; a PV that does not connect within ``timeout`` seconds is *missing*.
    """
    from caproto import ChannelType
    from caproto.threading.client import Context

    table = pv_map.table
    names: dict[str, str] = {}
    for n, rec in pv_map.motors.items():
        for f in MOTOR_FIELDS:
            names[f"{rec}.{f}"] = n
    for k, pv in pv_map.chamber.items():
        names[pv] = f"chamber.{k}"
    for a, rec in pv_map.stage.items():
        for f in MOTOR_FIELDS:
            names[f"{rec}.{f}"] = f"stage.{a}"
    out = PVCheck()
    ctx = Context(timeout=timeout)
    try:
        pvs = dict(zip(names, ctx.get_pvs(*names, timeout=timeout)))
        deadline = time.monotonic() + timeout  # one wait for all: the searches run in parallel
        while time.monotonic() < deadline and not all(pv.connected for pv in pvs.values()):
            time.sleep(0.05)
        values: dict[str, object] = {}
        for name, pv in pvs.items():
            if not pv.connected:
                continue
            try:
                kw = {"data_type": ChannelType.STRING} if name.endswith(".EGU") else {}
                data = pv.read(timeout=timeout, **kw).data
                values[name] = data[0].decode() if kw else data
            except Exception as exc:  # noqa: BLE001 - reported as a mismatch of that PV
                values[name] = exc
        from bluesky_offsets.physics.screen import STAGE
        records = [(n, rec, table[n].unit, table[n].limits) for n, rec in pv_map.motors.items()]
        records += [(f"stage.{ax.name}", pv_map.stage[ax.name], ax.unit, (ax.low, ax.high))
                    for ax in STAGE if ax.name in pv_map.stage]
        for n, rec, unit, (low, high) in records:
            absent = [f for f in MOTOR_FIELDS if not pvs[f"{rec}.{f}"].connected]
            if absent:
                out.missing.append((n, rec if len(absent) == len(MOTOR_FIELDS) else
                                    f"{rec} fields {', '.join('.' + f for f in absent)}"))
                continue
            why = _record_mismatch(values, rec, unit, low, high)
            if why:
                out.mismatched.append((n, rec, why))
            else:
                out.ok += 1
            if progress:
                progress(n)
        for k, pv in pv_map.chamber.items():
            if not pvs[pv].connected:
                out.missing.append((f"chamber.{k}", pv))
            else:
                out.ok += 1
    finally:
        ctx.disconnect()
    return out


def _record_mismatch(values: Mapping, rec: str, unit: str, low: float, high: float) -> str:
    """Why a motor record does not fit its axis (units, too little travel), or ''."""
    why = []
    egu = values[f"{rec}.EGU"]
    if isinstance(egu, str) and egu.strip() != unit:
        why.append(f"units {egu.strip()!r}, the table's are {unit!r}")
    llm, hlm = (float(values[f"{rec}.{f}"][0]) for f in ("LLM", "HLM"))
    if hlm <= llm:
        why.append(f"soft limits LLM = {llm:g}, HLM = {hlm:g} leave no travel")
    elif hlm - llm < (high - low) * (1 - 1e-9):
        why.append(f"soft limits [{llm:g}, {hlm:g}] allow {hlm - llm:g} {unit} of travel, "
                   f"the table's range needs {high - low:g}")
    return "; ".join(why)
