"""``bluesky-offsets diagnose``: model vs. a stored measurement run, from the command line.

Loads the measurement by uid from the run store, compares the twin with it, refines the
offsets through the twin, ranks the candidate effects, adds the best one and refits; every
step is a run in the same store, linked to the measurement.  Thin layer over
:func:`plans.diagnose.analyse_measurement` in a RunEngine.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from bluesky_offsets.commands.cli import CliError, add_analysis_options, check_analysis_options, output_file
from bluesky_offsets.model.cluster import analysis_executor


def _load(store, uid: str, n_rays: int | None, resolution: str = "camera"):
    from bluesky_offsets.model.misfit import MeasurementError
    try:
        stored = store.load_measurement(uid)
    except KeyError as exc:
        raise CliError(str(exc).strip("\"'")) from None
    except ValueError as exc:  # not a measurement run, or another parameter table
        raise CliError(str(exc) if uid in str(exc) else f"run {uid}: {exc}") from None
    if len(stored) == 0:
        raise CliError(f"run {uid} holds no measured configurations")
    try:
        return stored, stored.for_analysis(n_rays, resolution=resolution)
    except MeasurementError as exc:
        raise CliError(f"run {uid}: {exc}") from None


def _offsets_from_run(store, uid: str):
    """Normalized offsets stored by a find_offsets / refine_offsets / add_effect run."""
    from bluesky_offsets.physics.parameters import METRIXS
    try:
        run = store[uid]
    except KeyError as exc:
        raise CliError(str(exc).strip("\"'")) from None
    for stream in ("offsets", "effect"):
        if stream in run:
            ds = run[stream].read()
            if "offsets" in ds:
                off = np.asarray(ds["offsets"][-1], dtype=float)
                if off.shape == (len(METRIXS),) and np.all(np.isfinite(off)):
                    return off
    raise CliError(f"run {uid} holds no offsets (expected a find_offsets, refine_offsets or add_effect run)")


def _effects(text: str | None) -> list[str] | None:
    from bluesky_offsets.physics import effects as E
    if not text:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    for n in names:
        try:
            E.get(n)
        except ValueError as exc:
            raise CliError(str(exc)) from None
    return names


def summary_dict(analysis) -> dict:
    """The diagnosis ``analysis`` as JSON-ready data: verdict, rankings, error history, fitted effects, run uids."""
    return {
        "measurement_uid": analysis.measurement.uid,
        "verdict": analysis.verdict,
        "could_hide": analysis.could_hide_json,
        "rankings": [[{"effect": c.name, "score": c.score, "significant": c.significant, "values": c.values,
                       "sigma": c.sigma} for c in r.diagnosis.candidates] for r in analysis.rankings],
        "history": [c.total_row() for c in analysis.comparisons],
        "fitted_effects": {e: {k: {"value": v, "sigma": s} for k, (v, s) in m.items()}
                           for e, m in analysis.magnitudes().items()},
        "retest": analysis.retests,
        "dropped": analysis.dropped,
        "uids": dict(analysis.uids),
        "resumed": dict(analysis.resumed),
    }


def _cmd_diagnose(args) -> int:
    from bluesky_offsets.store import default_store_location, open_store, store_path
    candidates = _effects(args.effects)
    check_analysis_options(args)
    fit_options = {k: v for k, v in (("rays", args.fit_rays), ("posterior_starts", args.fit_starts))
                   if v is not None} or None
    where = str(args.store or default_store_location())
    folder = store_path(where)
    if folder is not None and not folder.exists():
        # the measurement lives in a store: a mistyped path must not leave an empty one behind
        raise CliError(f"no run store at {where}")
    if args.report:
        output_file(args.report, "--report")
    try:
        store = open_store(args.store)
    except OSError as exc:
        raise CliError(str(exc)) from None
    try:
        stored, meas = _load(store, args.uid, args.rays, args.resolution)
        from bluesky_offsets.model.state import ModelState
        starts = [ModelState(label="twin")]
        if args.offsets_uid:
            starts.append(ModelState(_offsets_from_run(store, args.offsets_uid), {}, "stored offsets"))

        from bluesky import RunEngine
        from bluesky.run_engine import RunEngineResult

        from plans.diagnose import analyse_measurement

        from bluesky_offsets.physics.twin import Twin
        RE = RunEngine({}, call_returns_result=True)
        store.subscribe(RE)
        log = sys.stderr if args.json else sys.stdout
        print(f"measurement {meas.uid}: {meas.n} configurations at {meas.n_rays} rays; results go to "
              f"{store.location}", file=log, flush=True)
        with Twin(n_rays=int(meas.n_rays), scheduler=args.scheduler, n_workers=args.threads) as twin:
            from bluesky_offsets.commands.cli import quiet_logs
            if args.scheduler != "inline":
                twin.client
                quiet_logs()
            with analysis_executor(args.threads, twin) as executor:
                result = RE(analyse_measurement(
                    stored, twin, starts=starts, refine=not args.no_refine, candidates=candidates,
                    add_best=not args.no_add, rounds=args.rounds, fit_options=fit_options, seed=args.seed,
                    fit_top=args.fit_top or None, resume=args.resume, store=store, resolution=args.resolution,
                    executor=executor, md={"purpose": "bluesky-offsets diagnose"}))
                assert isinstance(result, RunEngineResult)  # call_returns_result=True
                analysis = result.plan_result
            if analysis.resumed:
                print(f"resumed {len(analysis.resumed)} completed steps from the store: "
                      f"{', '.join(analysis.resumed)}", file=log)
            if args.report:
                from bluesky_offsets.commands.report import write_analysis_report
                path = write_analysis_report(args.report, analysis, analysis.measurement.spec,
                                             title=f"model vs. measurement {meas.uid}",
                                             store_location=store.location)
                print(f"report: {path}", file=log)
        out = summary_dict(analysis)
        if args.json:
            print(json.dumps(out, indent=1, default=float))
        else:
            from bluesky_offsets.commands.report import history_lines
            print(out["verdict"])
            if analysis.could_hide:
                print(analysis.could_hide_line)
            for line in history_lines(analysis):
                print(line)
            for k, v in out["uids"].items():
                print(f"  {k:16s} {v}")
        return 0
    finally:
        store.close()


def add_cli(sub) -> None:
    """Register the ``diagnose`` sub-command on the command line's subparsers ``sub``."""
    p = sub.add_parser("diagnose", help="compare the model with a stored measurement, find the missing effect, "
                                        "add it and refit",
                       description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    p.add_argument("--uid", required=True, help="uid of a measurement run (plans.measure_configurations)")
    p.add_argument("--store", default=None, help="run store directory or tiled URL (default: the embedded store)")
    p.add_argument("--effects", default=None, help="candidate effects, comma separated (default: all registered)")
    p.add_argument("--offsets-uid", default=None,
                   help="also start from the offsets of this run (find_offsets / refine_offsets)")
    p.add_argument("--no-refine", action="store_true", help="diagnose the start as it is (no offsets fit first)")
    p.add_argument("--no-add", action="store_true", help="rank only; do not add the best effect")
    add_analysis_options(p, fit_rays=None, fit_rays_help="model rays per configuration in the fits (default: "
                                                          "bluesky_offsets.model.diagnosis.FIT's)",
                         resolution_help="histograms to fit: the camera's profiles where the run has them (default) "
                                         "or the paper's 50 x 50 bins")
    p.add_argument("--rays", type=int, default=None, help="ray budget of the measurement when the run lacks it")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address, or 'inline' (default: local cluster)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resume", action="store_true",
                   help="take the steps an interrupted run of the same analysis completed from the store, "
                        "compute the rest (nothing is measured again)")
    p.add_argument("--report", type=Path, default=None, help="write a self-contained HTML report here")
    p.add_argument("--json", action="store_true", help="print the result as JSON (progress goes to stderr)")
    p.set_defaults(func=_cmd_diagnose)
