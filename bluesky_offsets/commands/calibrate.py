"""``bluesky-offsets calibrate``: the session against a running beamline.

The IOC is the simulated METRIXS (``--prefix``) or the real one (``--pvs FILE``, a PV map:
:mod:`bluesky_offsets.epics.pvmap`).  In one RunEngine, every run written to the store: find the
beam from where the motors stand, find bright configurations around it and measure them
(:func:`plans.workflow.measure_bright`), find the offsets with the surrogate
(:func:`plans.workflow.surrogate_offsets`), then compare, fit, diagnose, add the winning effect
and refit: :func:`plans.workflow.calibration_session`, as the demo runs it; one HTML report.

Everything a user can fix is refused in one line before a motor moves: the store, the
surrogate checkpoint, the PV map, an IOC that does not answer.  A beamline on which the beam
cannot be found ends in one line too, with the motors where the search left them.
"""

from __future__ import annotations

import time
from pathlib import Path

from bluesky_offsets.commands.cli import CliError, dark_beamline


def _cmd_calibrate(args) -> int:
    from bluesky_offsets.commands.cli import check_analysis_options, output_folder, quiet_logs
    from bluesky_offsets.epics.pvmap import PVMap, PVMapError
    from bluesky_offsets.offsets.finder import FinderError, load_forward_model
    from bluesky_offsets.physics import effects as E
    from bluesky_offsets.store import open_store
    from bluesky_offsets.design import DesignOptions
    from plans.workflow import MeasurementDesign

    check_analysis_options(args)
    if args.evaluations < 1:
        raise CliError("--evaluations must be at least 1")
    if args.connect_timeout <= 0:
        raise CliError("--connect-timeout must be positive")
    design: DesignOptions | MeasurementDesign
    try:
        if args.design == "optimal":
            design = DesignOptions(frames=args.frames, validation=args.validation_frames, seed=args.seed)
        else:
            design = MeasurementDesign(bright=args.bright, reopened=args.reopened, analysed=args.analysed,
                                       candidates=args.candidates, fraction=args.fraction,
                                       max_frames=args.max_frames, seed=args.seed)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    effects = [n.strip() for n in args.effects.split(",")] if args.effects else None
    for n in effects or ():
        try:
            E.get(n)
        except ValueError as exc:
            raise CliError(str(exc)) from None
    try:
        pv_map = PVMap.from_file(args.pvs) if args.pvs else PVMap.simulated(args.prefix)
    except PVMapError as exc:
        raise CliError(str(exc)) from None
    output_folder(args.out)  # before anything moves: the live views and the report go there
    quiet_logs()
    try:
        forward_model = load_forward_model(args.checkpoint)
    except FinderError as exc:
        raise CliError(str(exc)) from None
    store = open_store(args.store)  # a store that cannot be written: StoreError, one line (cli.main)
    try:
        return _calibrate(args, design, effects, pv_map, forward_model, store)
    finally:
        store.close()


def _calibrate(args, design, effects, pv_map, forward_model, store) -> int:
    from bluesky import RunEngine
    from bluesky.run_engine import RunEngineResult
    from bluesky.utils import RunEngineInterrupted

    from bluesky_offsets.model.cluster import analysis_executor
    from bluesky_offsets.commands.session import StepLines, close_channels, connect_devices, subscribe_views
    from bluesky_offsets.physics.twin import Twin
    from plans.workflow import DarkBeamline, calibration_session

    t0 = time.perf_counter()

    def say(msg):
        print(f"{time.perf_counter() - t0:6.0f} s  {msg}", flush=True)

    RE = RunEngine({}, call_returns_result=True)  # before the devices: they connect in its event loop
    lines = StepLines(say)
    try:
        say(f"connecting to {pv_map.name} ({len(pv_map.motors)} motors, the camera)")
        beamline, chamber = connect_devices(pv_map, args.connect_timeout)
        live = subscribe_views(RE, store, args.out)

        twin = Twin(n_rays=10_000, scheduler=args.scheduler, n_workers=args.threads)
        from bluesky_offsets.design import DesignOptions
        from bluesky_offsets.model import diagnosis as D
        designed = isinstance(design, DesignOptions)
        fit, scan = D.fits_for(designed, args.fit_rays, args.fit_starts)
        from plans.camera import camera_steps
        darks, measured_hook = camera_steps(chamber, beamline, md={"purpose": "calibrate"}, say=say, table=pv_map.table)
        try:
            if darks is not None:
                RE(darks())
            with analysis_executor(args.threads, twin) as executor:
                result = RE(calibration_session(
                    beamline, chamber, twin, forward_model, design=design, evaluations=args.evaluations,
                    candidates=effects, rounds=args.rounds, fit=fit, scan=scan,
                    fit_top=args.fit_top or None, resolution=args.resolution, measurement_md={"purpose": "calibrate"},
                    analysis_md={"purpose": "calibration analysis"}, step=say, executor=executor,
                    measured=measured_hook))
                assert isinstance(result, RunEngineResult)  # call_returns_result=True
                session = result.plan_result
        except DarkBeamline as exc:
            raise dark_beamline(exc, args.frames if designed else None) from None
        except RunEngineInterrupted:
            RE.abort("interrupted")
            raise KeyboardInterrupt from None
        finally:
            twin.close()
        _results(args, session, pv_map, store, designed, live, t0)
        return 0
    finally:
        lines.close()
        close_channels(RE)


def _results(args, session, pv_map, store, designed: bool, live, t0: float) -> None:
    """The session's report, calibration file and summary lines."""
    from bluesky_offsets.commands.report import history_lines, paragraph, write_analysis_report
    from bluesky_offsets.live import flush as flush_live

    measured, analysis, validation = session.measured, session.analysis, session.validation
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    uids = {"measurement": measured.uid, **({"find_offsets": session.offsets.uid} if session.offsets else {}),
            **analysis.uids, **({"validation": validation.uid} if validation is not None else {})}
    how = (f"{len(measured.measurement)} frames designed for the offsets (with the beam search's lit ones, "
           f"{analysis.measurement.n})" if designed else
           f"{len(measured.measurement)} configurations measured ({measured.n_open} with the slits open), "
           f"offsets found with the surrogate")
    extra = []
    if designed:
        from bluesky_offsets.commands.report import design_section, validation_section
        extra = [("The designed measurement", design_section(measured.designed))]
        if validation is not None:
            extra.append(("Validation frames", validation_section(validation)))
    report = write_analysis_report(
        out / "report.html", analysis, analysis.measurement.spec, title=f"bluesky-offsets calibrate: {pv_map.name}",
        intro=[("What this is", paragraph(
            f"The calibration session on {pv_map.name}: the beam found in {measured.beam.frames} frames, {how}, "
            f"fitted through the differentiable twin, the missing effects diagnosed, added and refitted."))],
        uids=uids, store_location=store.location, extra=extra, validation=validation)
    from bluesky_offsets.model.export import write_calibration
    from bluesky_offsets.model.posterior import Posterior
    calibration = None
    if Posterior.of(analysis) is not None:
        calibration = write_calibration(out / "calibration.json", analysis, measurement_uid=measured.uid,
                                        validation=None if validation is None else validation.summary())
    print()
    from plans.design import stated_verdict
    print(f"verdict: {stated_verdict(analysis, validation)}")
    if validation is not None and validation.passed:  # a failed one is in the verdict
        print(validation.line())
    if analysis.could_hide:
        print(analysis.could_hide_line)
    print("error history (a correct model: chi2/dof ≈ 1, MSE ≈ its noise expectation):")
    for line in history_lines(analysis):
        print(line)
    print("runs in the store:")
    for k, v in uids.items():
        print(f"  {k:16s} {v}")
    print(f"report: {report}")
    if calibration is not None:
        print(f"calibration (every offset as value ± sigma, its class, the covariance): {calibration}")
    flush_live(live)
    print(f"live views: {sum(len(cb.written) for cb in live)} figures in {Path(args.out) / 'live'}")
    print(f"done in {time.perf_counter() - t0:.0f} s")


def add_cli(sub) -> None:
    """Register the ``calibrate`` sub-command on the command line's subparsers ``sub``."""
    from bluesky_offsets.commands.cli import add_analysis_options
    from bluesky_offsets.epics.pvmap import SIM_PREFIX
    from bluesky_offsets.model import diagnosis as D
    p = sub.add_parser("calibrate", help="the calibration session against a running beamline (simulated IOC or "
                                         "the real one through a PV map)",
                       description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    where = p.add_mutually_exclusive_group()
    where.add_argument("--pvs", default=None, help="PV map file of the beamline (bluesky-offsets pv-map writes one)")
    where.add_argument("--prefix", default=SIM_PREFIX, help="the simulated IOC's PV prefix (default %(default)s)")
    p.add_argument("--store", default=None, help="run store (default: the embedded store, $BLUESKY_OFFSETS_STORE)")
    p.add_argument("--out", default="bluesky-offsets-calibrate", help="folder of the report (default ./%(default)s)")
    p.add_argument("--design", choices=("optimal", "bright"), default="optimal",
                   help="what is measured: frames designed for the offsets (default) or the bright configurations "
                        "around the beam (--bright, --reopened, --analysed, --candidates, --max-frames)")
    p.add_argument("--frames", type=int, default=60,
                   help="frames in all, the beam search's included (the designed measurement's budget; default "
                        "%(default)s)")
    p.add_argument("--validation-frames", type=int, default=6,
                   help="frames after the calibration, far from the fitted ones, that no fit uses (default "
                        "%(default)s)")
    p.add_argument("--bright", type=int, default=16, help="bright configurations to measure (default %(default)s)")
    p.add_argument("--reopened", type=int, default=4,
                   help="of them measured again with the slits open (default %(default)s)")
    p.add_argument("--analysed", type=int, default=14, help="configurations the fits use (default %(default)s)")
    p.add_argument("--candidates", type=int, default=40,
                   help="candidate configurations tried around the beam (default %(default)s)")
    p.add_argument("--fraction", type=float, default=0.15,
                   help="offsets the beam search assumes, fraction of each range (default %(default)s)")
    p.add_argument("--max-frames", type=int, default=120, help="frames the beam search may take (default %(default)s)")
    p.add_argument("--evaluations", type=int, default=3000, help="surrogate evaluations of the finder (default 3000)")
    p.add_argument("--checkpoint", default=None, help="surrogate checkpoint (default: the shipped one)")
    p.add_argument("--effects", default=None, help="effects to rank, comma separated (default: all)")
    add_analysis_options(p, fit_rays=None, fit_rays_help=f"model rays per configuration in the fits (default "
                                                         f"{D.DESIGNED_FIT.rays} for the designed measurement, "
                                                         f"{D.FIT.rays} for the bright one)",
                         resolution_help="histograms the diagnosis fits: the camera's profiles (default) or the "
                                         "paper's 50 x 50 bins")
    p.add_argument("--scheduler", default=None,
                   help="where the twin's RAYX traces run: a Dask scheduler address, 'inline' (this process) or "
                        "default a LocalCluster")
    p.add_argument("--connect-timeout", type=float, default=10.0,
                   help="seconds the PVs may take to connect (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="candidate design and fit seeds (default %(default)s)")
    p.set_defaults(func=_cmd_calibrate)
