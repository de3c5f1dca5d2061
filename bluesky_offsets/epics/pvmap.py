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
from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable

ENV_PVS = "BLUESKY_OFFSETS_PVS"
ENV_PREFIX = "BLUESKY_OFFSETS_PREFIX"
def _display(table: ParameterTable) -> str:
    return "METRIXS" if table.version == METRIXS.version else table.name


SIM_PREFIX = "SIM:METRIXS:"  # sim_iocs.metrixs.DEFAULT_PREFIX (not imported: the IOC is not needed here)

# the motor-record fields check_pvs reads
MOTOR_FIELDS = ("RBV", "EGU", "LLM", "HLM", "DMOV")


class PVMapError(InputError):
    """A PV map file that cannot be used (its message names the file and the entry)."""


@dataclass(frozen=True)
class PVMap:
    """Motor record per motorized parameter and PV per focus-chamber signal (full names)."""

    motors: Mapping[str, str]
    chamber: Mapping[str, str]
    name: str = ""
    table: ParameterTable = field(default=METRIXS, repr=False)
    stage: Mapping[str, str] = field(default_factory=dict)  # the chamber's x/y/z motors; empty: none
    camera: Mapping | None = None  # the chamber as an areaDetector camera (CAMERA_KEYS); None: [chamber]

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
        if self.camera is not None:
            _check_camera(self.camera)
            if self.chamber:
                raise PVMapError("[chamber] and [camera]: name the focus chamber's histogram PVs or its camera, "
                                 "not both")
        elif missing := [k for k in CHAMBER_PVS if k not in self.chamber]:
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
    def simulated(cls, prefix: str = SIM_PREFIX, table: ParameterTable = METRIXS, *,
                  camera_directory: str | os.PathLike | None = None) -> PVMap:
        """The simulated IOC's names (``sim_iocs.metrixs``) under ``prefix``.

        With ``camera_directory``, its camera instead of its histogram PVs (the simulated camera's
        data sheet and flux).
        """
        camera = None
        if camera_directory is not None:
            from dataclasses import asdict

            from bluesky_offsets.physics.camera import CameraGeometry
            camera = {"prefix": prefix + "cam:", "directory": str(camera_directory), **SIM_CAMERA,
                      "geometry": asdict(CameraGeometry())}
        return cls(motor_pvs(table, prefix, None), {} if camera else chamber_pvs(prefix + "chamber:", None),
                   f"simulated {_display(table)} IOC, prefix {prefix}", table,
                   stage_pvs(prefix + "chamber:", None), camera)

    @classmethod
    def from_file(cls, path: str | os.PathLike, table: ParameterTable = METRIXS) -> PVMap:
        """The PV map in the TOML file ``path``, checked; :class:`PVMapError` naming the file and what is wrong."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except OSError as exc:
            raise PVMapError(f"PV map {path}: {exc.strerror or exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise PVMapError(f"PV map {path}: not TOML: {exc}") from None
        unknown = sorted(set(data) - {"name", "motors", "chamber", "stage", "camera"})
        if unknown:
            raise PVMapError(f"PV map {path}: unknown keys {', '.join(unknown)} "
                             f"(name, [motors], [chamber] or [camera], [stage])")
        try:
            return cls(dict(data.get("motors", {})), dict(data.get("chamber", {})), str(data.get("name", path.stem)),
                       table, dict(data.get("stage", {})), data.get("camera"))
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
        """The map as a commented TOML file, the form :meth:`from_file` reads."""
        lines = [f"# PV map of the {_display(self.table)} devices (bluesky-offsets): edit the names for another IOC",
                 f"name = {_q(self.name)}", "", "[motors]"]
        for p in self.table:
            if p.motorized:
                lines.append(f"{_q(p.name):36s} = {_q(self.motors[p.name])}  # {p.unit}, {p.description}")
        if self.camera is None:
            lines += ["", "[chamber]"]
            lines += [f"{k:16s} = {_q(self.chamber[k])}" for k in CHAMBER_PVS]
        else:
            lines += ["", "# the focus chamber's camera (areaDetector: cam1: and HDF1: below its prefix)", "[camera]"]
            lines += [f"{k:18s} = {_toml(self.camera[k])}  # {CAMERA_KEYS[k]}" for k in CAMERA_KEYS
                      if k in self.camera and k != "geometry"]
            geometry = dict(self.camera.get("geometry") or {})
            lines += ["", "# where the pixels lie on the screen (omitted: 1000 x 1200 pixels of 20 x 5 µm, centred)",
                      "[camera.geometry]"] + [f"{k} = {_toml(v)}" for k, v in geometry.items()]
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
        """The chamber detector the plans read: the histogram PVs' device, or the camera's.

        The camera's is a :class:`~bluesky_offsets.epics.camera.CameraChamber` with its data sheet's
        calibration.
        """
        if self.camera is not None:
            from bluesky_offsets.epics.camera import CameraChamber
            return CameraChamber(self.camera["prefix"], self.camera["directory"], self.camera_calibration(),
                                 name=name)
        from bluesky_offsets.epics.devices import FocusChamber
        return FocusChamber("", name, pv_names=self.chamber)

    def camera_calibration(self):
        """The camera's calibration as its PV map states it (its data sheet; the flux at the screen)."""
        from bluesky_offsets.physics.camera import CameraCalibration, CameraGeometry
        c = self.camera or {}
        return CameraCalibration(geometry=CameraGeometry.from_dict(dict(c.get("geometry") or {})),
                                 gain=float(c["gain"]), read_noise=float(c["read_noise"]), dark=float(c["dark"]),
                                 photons_per_second=float(c["photons_per_second"]))

    def beamline_v1(self, name: str = "metrixs"):
        """Classic ophyd devices (connect lazily: what a queueserver startup wants)."""
        from bluesky_offsets.epics.devices_v1 import make_beamline_v1
        return make_beamline_v1("", name, table=self.table, pv_names=self.motors, stage=self.stage or None)

    def focus_chamber_v1(self, name: str = "chamber"):
        """The histogram PVs' chamber detector as a classic ophyd device.

        Made by :func:`~bluesky_offsets.epics.devices_v1.make_chamber_v1`; a camera's has no v1 device here.
        """
        from bluesky_offsets.epics.devices_v1 import make_chamber_v1
        return make_chamber_v1("", name=name, pv_names=self.chamber)


def _q(text: str) -> str:
    return '"' + str(text).replace("\\", "\\\\").replace('"', '\\"') + '"'


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    return _q(v) if isinstance(v, str) else repr(v)


CAMERA_KEYS = {
    "prefix": "the areaDetector's PV prefix",
    "directory": "where it writes its HDF5 files, as this machine sees them",
    "photons_per_second": "the flux at the screen (a photodiode's reading): the histograms are fractions of it",
    "gain": "ADU per photon, the data sheet's (photon transfer measures it)",
    "read_noise": "ADU, the data sheet's (dark frames measure it)",
    "dark": "ADU, the mean dark level (dark frames measure it pixel by pixel)",
    "geometry": "pixel size, centre and mounting (bluesky_offsets.physics.camera.CameraGeometry)",
}
"""The ``[camera]`` table of a PV map."""

SIM_CAMERA = {"photons_per_second": 5000.0, "gain": 60.0, "read_noise": 1.0, "dark": 100.0}
"""The simulated camera's data sheet (``sim_iocs.camera.CameraNoise``, whose true gain is 64 ADU a
photon and read noise 0.75 ADU) and the flux at its screen."""

CAMERA_PVS = ("cam1:Acquire", "cam1:AcquireTime", "cam1:ImageMode", "cam1:DetectorState_RBV", "cam1:ArrayCounter_RBV",
              "cam1:ShutterControl", "HDF1:FilePath", "HDF1:FileName", "HDF1:Capture", "HDF1:NumCaptured_RBV",
              "HDF1:FullFileName_RBV", "HDF1:FilePathExists_RBV")
"""What :func:`check_pvs` asks of a camera (all of ADCore's names; ophyd-async connects more)."""


def _check_camera(camera: Mapping) -> None:
    from bluesky_offsets.physics.camera import CameraGeometry
    if not isinstance(camera, Mapping):
        raise PVMapError("[camera]: expected a table")
    if unknown := sorted(set(camera) - set(CAMERA_KEYS)):
        raise PVMapError(f"[camera]: unknown keys {', '.join(unknown)} (known: {', '.join(CAMERA_KEYS)})")
    if missing := [k for k in CAMERA_KEYS if k != "geometry" and k not in camera]:
        raise PVMapError(f"[camera]: no {', '.join(missing)}")
    for k in ("prefix", "directory"):
        if not isinstance(camera[k], str) or not camera[k].strip():
            raise PVMapError(f"[camera] {k}: expected text, got {camera[k]!r}")
    for k in ("photons_per_second", "gain", "read_noise", "dark"):
        v = camera[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v == v or v < 0 or v == float("inf"):
            raise PVMapError(f"[camera] {k}: expected a finite number >= 0, got {v!r}")
    if not camera["gain"] > 0 or not camera["photons_per_second"] > 0:
        raise PVMapError("[camera]: gain and photons_per_second must be positive")
    try:
        CameraGeometry.from_dict(dict(camera.get("geometry") or {}))
    except (TypeError, ValueError) as exc:
        raise PVMapError(f"[camera.geometry]: {exc}") from None


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
        """Whether every PV connected and no motor record mismatched."""
        return not self.missing and not self.mismatched

    def lines(self) -> list[str]:
        """One line per missing or mismatched PV."""
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
    prefix = pv_map.camera["prefix"] if pv_map.camera else ""
    camera_pvs = [prefix + s for s in CAMERA_PVS] if pv_map.camera else []
    for pv in camera_pvs:
        names[pv] = f"camera {pv[len(prefix):]}"
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
        for k, pv in [*pv_map.chamber.items(), *((names[pv], pv) for pv in camera_pvs)]:
            if not pvs[pv].connected:
                out.missing.append((k if k.startswith("camera") else f"chamber.{k}", pv))
            else:
                out.ok += 1
        if pv_map.camera and not os.access(pv_map.camera["directory"], os.R_OK):
            out.mismatched.append(("camera directory", pv_map.camera["directory"], "not readable here (the camera "
                                   "writes its frames there; mount it, or name where it is mounted)"))
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
