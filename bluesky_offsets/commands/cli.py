"""``bluesky-offsets`` command line.

Each sub-command is a thin layer over the library.  Modules outside this
file register their own sub-commands through an ``add_cli(subparsers)``
function listed in :data:`EXTENSIONS`.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import sys

import numpy as np

from bluesky_offsets.epics.pvs import ChamberError, MotionError
from bluesky_offsets.errors import InputError
from bluesky_offsets.store import StoreError

EXTENSIONS: list[str] = [
    # "module:function" pairs, each adding sub-commands.
    "bluesky_offsets.commands.demo:add_cli",
    "bluesky_offsets.commands.surrogate:add_cli",
    "bluesky_offsets.commands.find:add_cli",
    "bluesky_offsets.commands.diagnose:add_cli",
    "bluesky_offsets.commands.calibrate:add_cli",
    "bluesky_offsets.commands.pvs:add_cli",
    "bluesky_offsets.commands.queue:add_cli",
    "sim_iocs.metrixs:add_cli",
]


class CliError(Exception):
    """A user error: printed without a traceback, exit status 2."""


def dark_beamline(exc: Exception, frames: int | None) -> CliError:
    """The beam search's :class:`plans.workflow.DarkBeamline` as the one line a user reads.

    ``frames``: the designed measurement's ``--frames`` (None: the bright design, whose search has a
    budget of its own).
    """
    from plans.design import search_frames
    if frames is None:
        return CliError(str(exc))
    return CliError(f"{getattr(exc, 'what', exc)}: check the shutter, the source and the slits, or give the search "
                    f"more frames (--frames {frames} let it take {search_frames(frames)})")


def output_folder(path, option: str = "--out"):
    """``path`` made now as the folder a command writes into: one it cannot write is refused before any work."""
    from pathlib import Path
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise CliError(f"{option} {folder} is a file, not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"{option} {folder}: cannot make the folder ({exc.strerror or exc})") from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise CliError(f"{option} {folder}: cannot write there")
    return folder


def output_file(path, option: str):
    """``path`` as a file a command will write, its folder made and checked now (see :func:`output_folder`)."""
    from pathlib import Path
    file = Path(path)
    if file.is_dir():
        raise CliError(f"{option} {file} is a folder, not a file")
    output_folder(file.parent, option)
    return file


def quiet_logs() -> None:
    """Set Dask's, tiled's, httpx's and bokeh's loggers to WARNING: their INFO lines would drown the progress.

    Their imports set their loggers to INFO, so they are imported first.
    """
    import importlib
    import logging
    for module in ("distributed", "tiled.server.app"):
        try:
            importlib.import_module(module)
        except ImportError:  # pragma: no cover - a client-only tiled
            pass
    for name in list(logging.root.manager.loggerDict):
        if name.split(".")[0] in ("distributed", "tiled", "httpx", "bokeh"):
            logging.getLogger(name).setLevel(logging.WARNING)


# --------------------------------------------------------------------------- #
# params
def add_analysis_options(p: argparse.ArgumentParser, *, fit_rays: int | None, fit_rays_help: str,
                         resolution_help: str) -> None:
    """Add the options every verb that analyses a measurement shares to the parser ``p``.

    The verbs are ``demo``, ``diagnose`` and ``calibrate``; the options: rounds of diagnosis,
    the fits' rays and posterior starts, screening, the binning fitted, threads.
    """
    p.add_argument("--rounds", type=int, default=None,
                   help="diagnoses at most: after an effect is added the model is diagnosed again (default 3: two "
                        "hidden effects and one added before them that the backward step drops)")
    p.add_argument("--fit-rays", type=int, default=fit_rays, help=fit_rays_help)
    p.add_argument("--fit-top", type=int, default=0,
                   help="screen every start of every candidate first and fit only this many candidates to "
                        "convergence (faster; a screen can miss a defocus: docs/explanations/diagnosis.md); default 0: every "
                        "start fitted")
    p.add_argument("--fit-starts", type=int, default=None,
                   help="starts the offsets fits draw from their posterior, per round while a round gains (default "
                        "4); fewer: faster, and a fit that stalls in a valley near its start is less often found out "
                        "(0: none, the posterior from its curvature and the ray draws alone)")
    p.add_argument("--resolution", choices=("camera", "paper"), default="camera", help=resolution_help)
    p.add_argument("--threads", type=int, default=None,
                   help="fits that do not depend on each other (the starts, the candidates, the ray draws) run this "
                        "many at a time, each on one torch and one BLAS thread, in the twin's Dask worker processes "
                        "(this many on a local cluster; a --scheduler's own); the result is the same for any "
                        f"number (default: $OMP_NUM_THREADS, else the cores this process may use, {default_threads()} "
                        "here)")


def check_analysis_options(args) -> None:
    """One line for each analysis option a user can fix (see :func:`add_analysis_options`)."""
    if args.rounds is None:
        from bluesky_offsets.model.diagnosis import ROUNDS
        args.rounds = ROUNDS
    if args.rounds < 1:
        raise CliError("--rounds must be at least 1")
    if args.fit_rays is not None and args.fit_rays < 100:
        raise CliError("--fit-rays must be at least 100")
    if args.fit_starts is not None and args.fit_starts < 0:
        raise CliError("--fit-starts must be at least 0 (0: no starts drawn from the posterior)")
    if args.fit_top < 0:
        raise CliError("--fit-top must be at least 0 (0: every start of every candidate fitted)")
    if args.threads is None:
        args.threads = default_threads()
    if args.threads < 1:
        raise CliError("--threads must be at least 1")


def default_threads() -> int:
    """The threads an analysis uses by default.

    ``$OMP_NUM_THREADS`` where set (a batch system's or a test runner's share of the
    machine), else the cores this process may use.
    """
    try:
        return max(1, int(os.environ.get("OMP_NUM_THREADS", "")))
    except ValueError:
        return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


# --------------------------------------------------------------------------- #
def _cmd_params(args) -> int:
    from bluesky_offsets.physics.beamline import BeamlineError, resolve
    try:
        bl = resolve(args.beamline)
    except BeamlineError as exc:
        raise CliError(str(exc)) from None
    table = bl.table
    records = table.as_records()
    if args.json:
        print(json.dumps({"table": table.name, "version": table.version, "parameters": records}, indent=2))
        return 0
    where = f"the RML {bl.rml.name}" if bl.rml else f"the built-in {bl.builtin} geometry"
    print(f"{table.name} parameter table (version {table.version}, {where}): {len(records)} parameters, "
          f"{sum(not r['motorized'] for r in records)} fixed-but-unknown (*)")
    print(f"{'#':>2}  {'name':32s} {'unit':5s} {'low':>11s} {'high':>11s} {'reference':>13s}  description")
    for i, r in enumerate(records):
        flag = "*" if not r["motorized"] else " "
        print(f"{i:2d}{flag} {r['name']:32s} {r['unit']:5s} {r['low']:11.4f} {r['high']:11.4f} "
              f"{r['reference']:13.6f}  {r['description']}")
    return 0


# --------------------------------------------------------------------------- #
# simulate
# --------------------------------------------------------------------------- #
def _parse_sets(items: list[str]) -> dict[str, float]:
    out = {}
    for item in items or []:
        if "=" not in item:
            raise CliError(f"--set expects NAME=VALUE, got {item!r}")
        name, value = item.split("=", 1)
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise CliError(f"--set {name}: {value!r} is not a number") from None
    return out


def _sparkline(h: np.ndarray) -> str:
    blocks = " ▁▂▃▄▅▆▇█"
    m = h.max()
    if m <= 0:
        return " " * len(h)
    return "".join(blocks[int(round(v / m * 8))] for v in h)


def _engine(name: str, sampling: str, beamline=None):
    """The twin ``name`` of METRIXS, or of a described ``beamline`` (RAYX's own rays: its source is RAYX's)."""
    if beamline is not None and beamline.builtin is None:
        return beamline.engine(name)
    from bluesky_offsets.physics.twin import make_engine
    return make_engine(name, **({"options": {"sampling": sampling}} if name == "torch" else {}))


def _described(spec: str | None):
    from bluesky_offsets.physics.beamline import BeamlineError, resolve
    try:
        return resolve(spec or "metrixs")
    except BeamlineError as exc:
        raise CliError(str(exc)) from None


def _cmd_simulate(args) -> int:
    from bluesky_offsets.physics.twin import Twin

    if args.rays < 1:
        raise CliError(f"--rays must be positive, got {args.rays}")
    if args.plot:
        output_file(args.plot, "--plot")
    bl = _described(args.beamline)
    table = bl.table
    try:
        values = table.from_mapping(_parse_sets(args.set))
    except ValueError as exc:
        raise CliError(f"--set: {exc}") from None
    overrides = {}
    if args.chamber:
        tx, ty, tz = args.chamber
        overrides["ImagePlane"] = {"translationXerror": tx, "translationYerror": ty, "translationZerror": tz}
    outside = table.outside_box(values)
    names = ("rayx", "torch") if args.engine == "both" else (args.engine,)
    # a described beamline's torch engine carries RAYX's own source rays, as --sampling rayx does
    same = bl.builtin is None or args.sampling == "rayx"
    seed = args.seed
    if seed is None and len(names) == 2 and same:  # one draw for both, or they would not share their rays
        seed = int(np.random.default_rng().integers(2**31))
    runs = []
    for name in names:
        twin = Twin(_engine(name, args.sampling, bl), scheduler="inline", n_rays=args.rays)
        try:
            runs.append((twin, twin.trace(values, overrides=overrides, keep_rays=True, seed=seed)))
        except ValueError as exc:
            raise CliError(str(exc)) from None
    hist = runs[0][0].hist
    comparison = _compare_engines(runs[0][1], runs[1][1], args.rays) if len(runs) == 2 else None
    if args.json:
        outs = []
        for twin, result in runs:
            outs.append({"engine": twin.engine.version, "beamline": table.name, "parameters": table.to_mapping(values),
                         "chamber_translation": list(args.chamber) if args.chamber else [0.0, 0.0, 0.0],
                         "outside_sampling_box": outside, "seed": seed, **result.summary(),
                         "hist_x": result.hist_x.tolist(), "hist_y": result.hist_y.tolist(),
                         "edges_x": hist.edges_x.tolist(), "edges_y": hist.edges_y.tolist()})
        print(json.dumps(outs[0] if len(outs) == 1 else {"runs": outs, "comparison": comparison}, indent=2))
    else:
        changed = {k: v for k, v in _parse_sets(args.set).items()}
        print(f"configuration: reference RML{' with ' + str(changed) if changed else ''}")
        if outside:
            print(f"note: outside the surrogate's sampling box (a model would extrapolate): {', '.join(outside)}")
        for twin, result in runs:
            summary = result.summary()
            print(f"engine: {twin.engine.version}; {args.rays} source rays")
            print(f"  transmission: {summary['transmission']:.4f}  ({summary['n_hits']} rays on the screen)")
            if "centroid_x" in summary:
                print(f"  centroid: x = {summary['centroid_x']:+.4f} mm, y = {summary['centroid_y']:+.4f} mm")
                print(f"  width (std): x = {summary['width_x']:.4f} mm, y = {summary['width_y']:.4f} mm")
            print(f"  x histogram [{hist.range_x[0]:g}, {hist.range_x[1]:g}] mm, sum {result.hist_x.sum():.4f}:")
            print(f"    |{_sparkline(result.hist_x)}|")
            print(f"  y histogram [{hist.range_y[0]:g}, {hist.range_y[1]:g}] mm, sum {result.hist_y.sum():.4f}:")
            print(f"    |{_sparkline(result.hist_y)}|")
        if comparison:
            agree = ("the same source rays: 0 when they agree ray for ray" if same else
                     f"1 ± {comparison['sigma']:.2f} when they agree within counting noise")
            print(f"rayx vs torch: histogram chi2/dof {comparison['chi2_per_dof']:.2f} over {comparison['dof']} "
                  f"bins ({agree})")
    if args.plot:
        from bluesky_offsets.plotting import plot_footprint
        for twin, result in runs:
            path = args.plot if len(runs) == 1 else _suffixed(args.plot, twin.engine.version.split()[0])
            plot_footprint(result, hist, path, title=f"{bl.name} twin ({twin.engine.version.split()[0]}), "
                                                     f"{args.rays} rays")
            if not args.json:
                print(f"plot written to {path}")
    return 0


def _suffixed(path: str, tag: str) -> str:
    from pathlib import Path
    p = Path(path)
    return str(p.with_name(f"{p.stem}-{tag}{p.suffix}"))


def _compare_engines(a, b, n_rays: int) -> dict:
    """Pearson chi-square between two traces' histograms (counts, independent rays)."""
    ca = np.concatenate([a.hist_x, a.hist_y]) * n_rays
    cb = np.concatenate([b.hist_x, b.hist_y]) * n_rays
    used = (ca + cb) > 0
    chi2 = float((((ca - cb) ** 2)[used] / (ca + cb)[used]).sum())
    dof = int(used.sum())
    return {"chi2_per_dof": chi2 / max(dof, 1), "dof": dof, "sigma": float(np.sqrt(2.0 / max(dof, 1)))}


# --------------------------------------------------------------------------- #
# entry point
# --------------------------------------------------------------------------- #
def build_parser() -> argparse.ArgumentParser:
    """The ``bluesky-offsets`` argument parser, with the sub-commands of every module in :data:`EXTENSIONS`."""
    parser = argparse.ArgumentParser(prog="bluesky-offsets",
                                     description="Offset finding for the METRIXS beamline's digital twin.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log more")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="no progress (bars on a terminal, a line per task in a file); results and errors only")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("params", help="print a beamline's parameter table (METRIXS's 34 by default)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--beamline", default="metrixs", metavar="FILE|NAME",
                   help="a beamline description (TOML) or a shipped one: metrixs (default), energize")
    p.set_defaults(func=_cmd_params)

    p = sub.add_parser("simulate", help="trace one configuration with the twin (RAYX, or the torch engine)")
    p.add_argument("--set", action="append", metavar="NAME=VALUE",
                   help="change a parameter from the reference RML value (repeatable)")
    p.add_argument("--rays", type=int, default=20000, help="source rays (default 20000)")
    p.add_argument("--chamber", type=float, nargs=3, metavar=("TX", "TY", "TZ"),
                   help="focus-chamber translation in mm (detector property, not one of the 34)")
    p.add_argument("--engine", choices=("rayx", "torch", "both"), default="rayx",
                   help="rayx: the reference (default); torch: the differentiable twin; both: trace with "
                        "each and compare their histograms within counting noise")
    p.add_argument("--seed", type=int, default=None,
                   help="random seed (the same seed gives the same trace; with --engine both on METRIXS each "
                        "engine draws its own rays unless --sampling rayx; on a described beamline both trace "
                        "RAYX's rays, one seed drawn for both where none is given)")
    p.add_argument("--sampling", choices=("fast", "rayx"), default="fast",
                   help="torch engine's random stream: fast, or rayx (RAYX's own rays for the same seed)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--plot", metavar="FILE.png", help="footprint scatter with both histograms")
    p.add_argument("--beamline", default=None, metavar="FILE|NAME",
                   help="a described beamline (TOML, or a shipped one: energize) instead of METRIXS")
    p.set_defaults(func=_cmd_simulate)

    for ext in EXTENSIONS:
        module, func = ext.split(":")
        getattr(importlib.import_module(module), func)(sub)
    return parser


def _beamline_error(exc: BaseException | None) -> BaseException | None:
    """The motion or chamber error ``exc`` is or was raised from (a failed status wraps it), else None."""
    while exc is not None:
        if isinstance(exc, (MotionError, ChamberError)):
            return exc
        exc = exc.__cause__
    return None


def main(argv: list[str] | None = None) -> int:
    """Run ``bluesky-offsets`` on ``argv``; return the exit status (2: a user error, 3: a beamline error)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    from bluesky_offsets.progress import set_quiet
    set_quiet(args.quiet)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not args.verbose:
        # the RunEngine logs a failed plan with its traceback before re-raising it; the error is
        # reported here (one line for what a user can fix), so its log would only repeat it
        logging.getLogger("bluesky").setLevel(logging.CRITICAL)
    if getattr(args, "rays", 1) is not None and getattr(args, "rays", 1) < 1:
        parser.error("--rays must be positive")
    try:
        return int(args.func(args) or 0)
    except (CliError, InputError, StoreError) as exc:
        # input the library refused (bad parameter, impossible geometry, bad file ...); any other
        # exception is a bug, or a failure the user did not cause, and keeps its traceback
        if args.verbose:
            raise
        print(f"bluesky-offsets {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader left (``| head``): nothing more to say, and nowhere to say it
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except Exception as exc:  # last: a broken pipe above is an exception too
        # the beamline did not do what it was told (a stalled motor, a failed frame), maybe inside
        # the status a plan waited on: say which
        cause = _beamline_error(exc)
        if cause is None or args.verbose:
            raise
        print(f"bluesky-offsets {args.command}: beamline error: {cause}", file=sys.stderr)
        return 3


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
