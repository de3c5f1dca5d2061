"""``bluesky-offsets pv-map`` and ``check-pvs``: the file that names the beamline's PVs, and its check.

``check-pvs`` checks the file against the control system (:mod:`bluesky_offsets.epics.pvmap`).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def _table(args):
    """The parameter table of ``--beamline`` (METRIXS's by default)."""
    from bluesky_offsets.commands.cli import CliError
    from bluesky_offsets.physics.beamline import BeamlineError, resolve
    try:
        return resolve(args.beamline).table
    except BeamlineError as exc:
        raise CliError(str(exc)) from None


def _cmd_pv_map(args) -> int:
    from bluesky_offsets.commands.cli import CliError
    from bluesky_offsets.epics.pvmap import PVMap
    text = PVMap.simulated(args.prefix, _table(args), camera_directory=args.camera).to_toml()
    if args.out:
        try:
            Path(args.out).write_text(text)
        except OSError as exc:
            raise CliError(f"cannot write the PV map to {args.out}: {exc.strerror or exc}") from None
        print(f"PV map of the simulated IOC (prefix {args.prefix}) written to {args.out}: edit it for another IOC, "
              f"then bluesky-offsets check-pvs {args.out}")
    else:
        sys.stdout.write(text)
    return 0


def _cmd_check_pvs(args) -> int:
    from bluesky_offsets.commands.cli import CliError
    from bluesky_offsets.epics.pvmap import PVMap, PVMapError, check_pvs
    if args.timeout <= 0:
        raise CliError("--timeout must be positive")
    try:
        pv_map = PVMap.from_file(args.file, _table(args))
    except PVMapError as exc:
        raise CliError(str(exc)) from None
    from bluesky_offsets.epics.pvmap import CAMERA_PVS
    detector = len(CAMERA_PVS) if pv_map.camera else len(pv_map.chamber)
    n = len(pv_map.motors) + detector + len(pv_map.stage)
    if not args.json:
        stage = f", {len(pv_map.stage)} stage motor records" if pv_map.stage else ""
        what = "areaDetector camera PVs" if pv_map.camera else "chamber PVs"
        print(f"checking {len(pv_map.motors)} motor records{stage} and {detector} {what} of "
              f"{pv_map.name or args.file} (timeout {args.timeout:g} s)", flush=True)
    res = check_pvs(pv_map, timeout=args.timeout)
    if args.json:
        print(json.dumps({"file": args.file, "name": pv_map.name, "ok": res.ok, "checked": n, "passed": res.passed,
                          "missing": [{"entry": k, "pv": pv} for k, pv in res.missing],
                          "mismatched": [{"entry": k, "pv": pv, "why": w} for k, pv, w in res.mismatched]},
                         indent=1))
    else:
        for line in res.lines():
            print(line)
        print(f"{res.ok} of {n} PVs as expected, {len(res.missing)} missing, {len(res.mismatched)} mismatched")
    return 0 if res.passed else 1


def add_cli(sub) -> None:
    """Register the ``pv-map`` and ``check-pvs`` sub-commands on the command line's subparsers ``sub``."""
    from bluesky_offsets.epics.pvmap import SIM_PREFIX
    p = sub.add_parser("pv-map", help="write the PV map of the simulated IOC (a template for the real beamline)")
    p.add_argument("--prefix", default=SIM_PREFIX, help="the simulated IOC's PV prefix (default %(default)s)")
    p.add_argument("--out", default=None, help="file to write (default: standard output)")
    p.add_argument("--camera", metavar="DIR", default=None,
                   help="name the focus chamber's camera (an areaDetector writing its frames to DIR) instead of "
                        "the simulator's histogram PVs")
    p.add_argument("--beamline", default="metrixs", metavar="FILE|NAME",
                   help="the beamline's description (a TOML file, or a shipped one: metrixs, energize)")
    p.set_defaults(func=_cmd_pv_map)

    p = sub.add_parser("check-pvs", help="connect to every PV of a PV map; report missing and mismatched records")
    p.add_argument("file", help="PV map (TOML: [motors] parameter = record, [chamber] signal = PV or [camera])")
    p.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the PVs to connect (default 3)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--beamline", default="metrixs", metavar="FILE|NAME",
                   help="the beamline's description the map's motors belong to (default metrixs)")
    p.set_defaults(func=_cmd_check_pvs)
