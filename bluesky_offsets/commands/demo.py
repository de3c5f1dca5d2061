"""``bluesky-offsets demo``: the main job, on embedded defaults.

A whole calibration and diagnosis session against the simulated beamline:

1. start the simulated METRIXS IOC (RAYX twin backend, 127.0.0.1, a free port) with hidden
   offsets in all 34 parameters (±5 % of each range by default) *and* hidden physical effects
   (default: the focus chamber 20 mm downstream);
2. in a RunEngine, with every run written to the embedded run store: find the beam from the
   start (slits open, the sensitive motors scanned), find bright configurations around it,
   measure them (>= 16), find the offsets (surrogate finder, then a fit through the
   differentiable twin), compare model and measurement, diagnose the missing effect, add the
   winner, refit, diagnose again;
3. the smallest focus on the calibrated twin (:func:`plans.optimize.optimize_beam`): settings
   computed, motors moved there, frames before and after; beside it the best the hidden true
   beamline can reach (the same optimizer on the true state);
4. write one self-contained HTML report and print a summary: run uids, the error history
   (twin -> + offsets -> + effect), the fitted effect next to the hidden one, the focus before,
   after and predicted, and how to load the runs back.

With ``--beamline FILE|NAME`` the same session runs on a described beamline (docs/reference/beamlines.md):
its IOC, devices, designed frames, fits and effects, up to the validation frames.

The IOC is always stopped, also after an error or Ctrl-C.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bluesky_offsets.model import diagnosis as D
from bluesky_offsets.physics import effects as E
from bluesky_offsets.model.fit import FitOptions
from bluesky_offsets.physics.parameters import METRIXS

from bluesky_offsets.design import DesignOptions
from bluesky_offsets.streams import stream

if TYPE_CHECKING:  # plans (bluesky) load when the demo runs, not with every command
    from bluesky_offsets.model.posterior import Posterior
    from plans.workflow import MeasurementDesign

# Hidden truth: offsets in all 34 parameters, uniform within ±``offsets_fraction`` of each range
# (drawn from the seed), and one physical effect.  With ``offsets_fraction = 0`` the offsets are
# DEMO_OFFSETS instead: a few per cent in the motors that steer the focus and in one focal length.
DEMO_OFFSETS = {"E1.rotationXerror": 0.015, "E2.rotationXerror": -0.015, "M1_Cylinder.rotationXerror": 0.01,
                "E1.translationYerror": 0.01, "E2.translationYerror": -0.01, "ExitSlit.translationZerror": 0.02,
                "E2.longHalfAxisA": 0.01}
DEMO_EFFECT = ("chamber_z", {"z": 20.0})


def _design(**kw) -> MeasurementDesign:
    from plans.workflow import MeasurementDesign
    return MeasurementDesign(**kw)


@dataclass
class DemoSettings:
    """The demo's settings: the simulated beamline, what is measured, the hidden truth, the analysis."""

    n_rays: int = 5000                # per measured frame
    # the simulated motors: seconds for a full-range move (velocity = range / move_time), far
    # faster than a real motor: the speed changes the wall time, not the frames or the results
    move_time: float = 0.1
    # "perfect" axes, or "realistic" ones: encoder noise, backlash, retries (sim_iocs.metrixs.motor_profile)
    motors: str = "perfect"
    # the focus chamber read as a "camera" (its areaDetector: frames reduced with a dark, a gain by
    # photon transfer, the flux at the screen) or as "histograms" (the simulator's ray-count PVs)
    detector: str = "camera"
    # what is measured: frames designed for the offsets ("optimal": ``optimal``'s budget, batches,
    # criterion) or the bright design ("bright": ``measurement``'s 16 bright configurations, 4 of
    # them again with the slits open, 14 fitted); their seeds are the demo's ``seed``
    design_kind: str = "optimal"
    optimal: DesignOptions = field(default_factory=DesignOptions)
    measurement: MeasurementDesign = field(default_factory=lambda: _design())
    # hidden effects, ((name, values), ...): found one after the other
    effects: tuple = (DEMO_EFFECT,)
    # offsets in all 34 parameters, uniform within ± this fraction of each range (drawn from
    # ``seed``); 0: ``offsets`` instead
    offsets_fraction: float = 0.05
    offsets: dict = field(default_factory=lambda: dict(DEMO_OFFSETS))
    # an evaluation budget, never a time budget: the same command gives the same result under any load
    finder_evaluations: int = 3000
    fit: FitOptions = D.DESIGNED_FIT  # the offsets fit and the refits (D.FIT for the bright design)
    scan: FitOptions = D.DESIGNED_SCAN  # the diagnosis's candidate fits (D.SCAN for the bright design)
    rounds: int = D.ROUNDS            # diagnoses at most
    fit_top: int | None = D.FIT_TOP   # screen every start, fit this many candidates (None: fit all)
    # the diagnosis reads the camera-resolution profiles ("camera") or the paper's histograms ("paper")
    resolution: str = "camera"
    candidates_effects: Sequence[str] | None = None
    seed: int = 0
    # the twin's Dask workers (RAYX traces of the comparisons); None: one per thread below
    workers: int | None = None
    # fits that do not depend on each other run this many at a time (the same result for any)
    threads: int = 1
    # the last step: the smallest focus with the calibrated twin (plans.optimize.optimize_beam),
    # frames averaged before and after the move
    optimize: bool = True
    frames: int = 3
    # refit the calibration with the frames taken after the move, optimize and move once more
    # (plans.optimize): the first move's prediction rests on offsets fitted where the beam was
    # measured, the second's also on frames at the new settings (issue 17: the fitted offsets
    # reproduce the frames but not the truth, so the first prediction can miss by > 10 %)
    closed_loop: bool = True
    # a described beamline (a description file or a shipped name, ``physics.beamline``); None: METRIXS
    beamline: str | None = None

    @property
    def described(self):
        """The described beamline (:class:`~bluesky_offsets.physics.beamline.Beamline`), or None for METRIXS."""
        if self.beamline is None:
            return None
        from bluesky_offsets.physics.beamline import resolve
        return resolve(self.beamline)

    @property
    def table(self):
        """The parameter table: METRIXS's, or the described beamline's."""
        bl = self.described
        return METRIXS if bl is None else bl.table

    @property
    def display(self) -> str:
        """The beamline's name as printed: ``METRIXS``, or the described beamline's table name."""
        return "METRIXS" if self.beamline is None else self.table.name

    @property
    def steps(self) -> int:
        """The demo's numbered steps: 6 with the beam optimization, 5 without."""
        return 6 if self.optimize else 5

    @property
    def design(self) -> DesignOptions | MeasurementDesign:
        """What the session measures (:func:`plans.workflow.calibration_session`), drawn from ``seed``."""
        if self.design_kind == "optimal":
            return self.optimal.replace(seed=self.seed)
        return replace(self.measurement, seed=self.seed)

    @property
    def hidden(self) -> dict[str, dict[str, float]]:
        """The hidden effects' values by effect name (the unnamed ones left out)."""
        return {name: dict(values) for name, values in self.effects if name}


def demo_offsets(s: DemoSettings) -> dict[str, float]:
    """The hidden normalized offsets: all the table's drawn (``offsets_fraction``) or ``s.offsets``."""
    table = s.table
    if s.offsets_fraction > 0:
        rng = np.random.default_rng(stream(s.seed, "demo.hidden_offsets"))
        return {n: float(v) for n, v in zip(table.names, rng.uniform(-s.offsets_fraction, s.offsets_fraction,
                                                                     len(table)))}
    return dict(s.offsets)


def demo_truth(s: DemoSettings) -> dict:
    """The IOC's truth file: normalized offsets and the effects' RML overrides."""
    from sim_iocs.truth import Truth
    hidden = s.hidden
    # the IOC's own reading of the overrides (numbers, or words such as an element type),
    # refused here with its message rather than in the IOC's subprocess
    overrides = Truth.from_mapping({"overrides": E.twin_overrides(hidden) if hidden else {}}).overrides
    return {"offsets": demo_offsets(s), "overrides": overrides,
            "comment": f"bluesky-offsets demo: hidden effects {hidden or 'none'}"}


# --------------------------------------------------------------------------- #
# the simulated beamline
# --------------------------------------------------------------------------- #
class SimulatedBeamline:
    """The simulated IOC in a subprocess on loopback, on a free port.

    The IOC is METRIXS, or the described ``beamline`` (a description file); :meth:`stop` always kills it.
    """

    def __init__(self, truth: Mapping, n_rays: int, work: Path, move_time: float = 0.5, noise_seed: int = 0,
                 motors: str = "perfect", beamline: Path | None = None):
        from sim_iocs.ports import free_port, loopback_env
        self.port = free_port()
        self.prefix = f"DEMO{self.port}:"
        self.work = work
        self.truth_path = work / "truth.json"
        self.truth_path.write_text(json.dumps(truth, indent=1))
        # beacons need a listener (none runs here): a UDP sink takes them
        self._sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sink.bind(("127.0.0.1", 0))
        # this process's Channel Access clients look only at this IOC
        env = loopback_env(self.port, self._sink.getsockname()[1])
        os.environ.update(EPICS_CA_ADDR_LIST=env["EPICS_CA_ADDR_LIST"], EPICS_CA_AUTO_ADDR_LIST="NO")
        env = dict(os.environ, **env)
        self.log_path = work / "ioc.log"
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "sim_iocs.metrixs", "--prefix", self.prefix, "--truth", str(self.truth_path),
             "--backend", "twin", "--rays", str(n_rays), "--noise-seed", str(noise_seed),
             "--move-time", str(move_time), "--accel-time", "0.02", "--tick", "0.02", "--interfaces", "127.0.0.1",
             "--motors", motors, *(("--beamline", str(beamline)) if beamline is not None else ())],
            env=env, stdout=self._log, stderr=subprocess.STDOUT, start_new_session=True)

    def log(self) -> str:
        """The IOC log's last 3000 characters ("" when it cannot be read)."""
        try:
            return self.log_path.read_text()[-3000:]
        except OSError:
            return ""

    def wait_ready(self, timeout: float = 120.0) -> None:
        """Wait until the IOC's chamber message says it is ready; raise if it exits or ``timeout`` s pass."""
        from caproto.sync.client import read
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the simulated IOC exited ({self.proc.returncode}):\n{self.log()}")
            try:
                resp = read(self.prefix + "chamber:Message", timeout=1.0, repeater=False)
                data = resp.data
                text = data.tobytes().split(b"\0", 1)[0].decode() if hasattr(data, "tobytes") else str(data)
                if "ready" in text:
                    return
            except Exception:
                pass
            time.sleep(0.3)
        raise TimeoutError(f"the simulated IOC did not come up in {timeout:.0f} s:\n{self.log()}")

    def stop(self) -> None:
        """Kill the IOC's process group and close its log and beacon sink."""
        from sim_iocs.ports import stop_process_group
        stop_process_group(self.proc)
        self._log.close()
        self._sink.close()


# --------------------------------------------------------------------------- #
# the workflow as one plan
# --------------------------------------------------------------------------- #
def demo_plan(s: DemoSettings, beamline, chamber, twin, forward_model, log, executor=None):
    """The demo as one plan: the calibration session, then the smallest focus on the calibrated twin.

    The session is :func:`plans.workflow.calibration_session` with the demo's settings, the smallest
    focus :func:`plans.optimize.optimize_beam`; steps numbered 2 to 5 of the demo's six; ``executor``
    runs the analysis's independent fits.  Returns (session, beam result or None).
    """
    import itertools

    from plans.optimize import optimize_beam
    from plans.workflow import calibration_session

    table = s.table
    candidates = s.candidates_effects
    if candidates is None and s.described is not None:
        candidates = list(s.described.effects)  # the effects its description says apply

    number = itertools.count(2)
    from plans.camera import camera_steps

    darks, measured = camera_steps(chamber, beamline, md={"purpose": "bluesky-offsets demo"}, say=log, table=s.table)
    if darks is not None:
        yield from darks()
    session = yield from calibration_session(
        beamline, chamber, twin, forward_model, design=s.design, evaluations=s.finder_evaluations,
        candidates=candidates, rounds=s.rounds, fit=s.fit, scan=s.scan, fit_top=s.fit_top,
        resolution=s.resolution, measurement_md={"purpose": "demo measurement"},
        analysis_md={"purpose": "bluesky-offsets demo"}, executor=executor, measured=measured,
        step=lambda text: log(f"[{next(number)}/{s.steps}] {text}"), table=table)
    beam = None
    if s.optimize:
        log(f"[{next(number)}/{s.steps}] the smallest focus with the calibrated twin: settings for E1/E2 within "
            f"their limits, moved there, {s.frames} frames before and after"
            + (f"; the model refitted with them, moved once more, {s.frames} frames (closed loop)" if s.closed_loop
               else ""))
        beam = yield from optimize_beam("smallest_focus", session.analysis, beamline, chamber, frames=s.frames,
                                        options={"seed": stream(s.seed, "demo.beam_optimizer")},
                                        md={"purpose": "bluesky-offsets demo"},
                                        closed_loop=s.closed_loop, measurement=session.analysis.measurement,
                                        refit=s.fit.replace(ray_draws=1), executor=executor)
    session.times["optimize"] = time.perf_counter()
    return session, beam


def run_demo(out: Path, settings: DemoSettings | None = None, store_location: str | None = None) -> dict:
    """The whole demo; returns the summary (also written to ``out/summary.json``)."""
    s = settings or DemoSettings()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    def log(msg):
        print(f"{time.perf_counter() - t0:6.0f} s  {msg}", flush=True)

    truth = demo_truth(s)
    table, described = s.table, s.described
    work = Path(tempfile.mkdtemp(prefix="bluesky-offsets-demo-"))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    log(f"[1/{s.steps}] starting the simulated {s.display} IOC (RAYX twin backend; hidden offsets in "
        f"{len(truth['offsets'])} of {len(table)} parameters, hidden effects: {', '.join(s.hidden) or 'none'}); load "
        f"average {load:.1f} on {os.cpu_count()} cores; the analysis's fits {s.threads} at a time)")
    # seeded frame noise: the same settings give the same demo, --seed another draw of it
    ioc = SimulatedBeamline(truth, s.n_rays, work, move_time=s.move_time, noise_seed=stream(s.seed, "demo.ioc_noise"),
                            motors=s.motors, beamline=None if described is None else described.path)
    twin = RE = steps_log = None
    pool = contextlib.ExitStack()  # the analysis's executor (one torch and BLAS thread a fit) to the end
    try:
        from bluesky import RunEngine
        from bluesky.run_engine import RunEngineResult
        from bluesky.utils import RunEngineInterrupted

        from bluesky_offsets.commands.cli import quiet_logs
        from bluesky_offsets.commands.session import StepLines, close_channels
        from bluesky_offsets.model.cluster import analysis_executor
        from bluesky_offsets.offsets.finder import load_forward_model
        from bluesky_offsets.physics.beamline import rayx_engine
        from bluesky_offsets.physics.twin import Twin
        from bluesky_offsets.store import open_store

        quiet_logs()
        steps_log = StepLines(log)  # the workflow plans' progress lines, indented under the step
        store = open_store(store_location)
        forward_model = load_forward_model()
        # as many RAYX workers as the demo may use cores (--threads): a test runner's share of
        # one core (OMP_NUM_THREADS=1) starts one worker, not a worker per core of the machine
        twin = Twin(rayx_engine(table), n_rays=s.n_rays, n_workers=s.workers or s.threads)
        twin.client  # start the Dask workers while the IOC comes up
        RE = RunEngine({}, call_returns_result=True)  # before the devices: they connect in its event loop
        ioc.wait_ready()
        beamline, chamber, live = _devices(s, ioc, work, store, RE, out)
        log(f"      IOC {ioc.prefix} on 127.0.0.1:{ioc.port}; run store {store.location}")
        # the analysis's independent fits on the twin's workers: processes, so that two fits do
        # not share one interpreter lock (nor this process's with the RunEngine and live views)
        executor = pool.enter_context(analysis_executor(s.threads, twin))
        try:
            result = RE(demo_plan(s, beamline, chamber, twin, forward_model, log, executor))
        except RunEngineInterrupted:  # Ctrl-C paused it: end the run as aborted, then clean up
            RE.abort("interrupted")
            raise KeyboardInterrupt from None
        assert isinstance(result, RunEngineResult)  # call_returns_result=True
        session, beam_result = result.plan_result
        uids = list(result.run_start_uids)
        steps = _step_uids(session, beam_result, uids)
        best = None if beam_result is None else _log_beam(truth, beam_result, log)
        log(f"[{s.steps}/{s.steps}] writing the report")
        outcome = _outcome(s, out, session, beam_result, t0)
        report = _write_report(s, truth, out, session, beam_result, best, steps, store.location, outcome)
        from bluesky_offsets.live import flush as flush_live
        flush_live(live)
        summary = _summary(s, truth, session, beam_result, best, outcome, report=report, steps=steps, uids=uids,
                           store=store.location, ioc=ioc, live=live, seconds=time.perf_counter() - t0, load=load)
        (out / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
        _print_summary(summary, session.analysis, store.location)
        store.close()
        return summary
    finally:
        pool.close()
        if steps_log is not None:
            steps_log.close()
        if twin is not None:
            twin.close()
        if RE is not None:
            close_channels(RE)
        ioc.stop()
        if not (work / "frames").exists():  # the truth file and the IOC's log; camera files stay with their runs
            import shutil
            shutil.rmtree(work, ignore_errors=True)


def _devices(s: DemoSettings, ioc: SimulatedBeamline, work: Path, store, RE, out: Path) -> tuple:
    """The beamline's and the chamber's devices on the IOC, connected in ``RE``'s loop.

    The store and the live views are subscribed.  Returns (beamline, chamber, live views).
    """
    from bluesky_offsets.commands.session import connect_devices, subscribe_views
    from bluesky_offsets.epics.pvmap import PVMap

    frames = None
    if s.detector == "camera":
        from bluesky_offsets.store import StoreError
        try:
            frames = store.frames_directory  # the embedded store serves the camera's files
        except StoreError:
            frames = work / "frames"
    pv_map = PVMap.simulated(ioc.prefix, s.table, camera_directory=frames)
    beamline, chamber = connect_devices(pv_map, timeout=10.0)
    if pv_map.camera:  # an exposure that gives the frames the demo's photons
        import bluesky.plan_stubs as bps
        RE(bps.mv(chamber.driver.acquire_time, s.n_rays / pv_map.camera["photons_per_second"]))
    return beamline, chamber, subscribe_views(RE, store, out)


def _step_uids(session, beam_result, uids: Sequence[str]) -> dict[str, str]:
    """The uid of each step's run, by step name, in the order the session took them."""
    beam, m = session.measured.beam, session.measured.measurement
    if session.measured.designed is None:  # the beam search's runs come first, then the bright search's
        steps = {"find_beam": beam.uids[-1], "search": uids[len(beam.uids)], "measurement": m.uid,
                 "find_offsets": session.offsets.uid}
    else:
        steps = {"find_beam": beam.uids[-1], "measurement": m.uid}
    steps.update({k: v for k, v in session.analysis.uids.items() if v})
    if session.validation is not None:
        steps["validation"] = session.validation.uid
    if beam_result is not None:
        steps["optimize_beam"] = beam_result.uid
    return steps


def _log_beam(truth: Mapping, beam_result, log):
    """The beam optimization's lines, and beside them the hidden true beamline's best; returns the best."""
    best = _true_best(truth, beam_result)
    for line in beam_result.lines():
        log("      " + line)
    log(f"      the hidden true beamline's best (the same optimizer on the true state, also from each move's settings): "
        f"{best.rms_x * 1e3:.1f} x {best.rms_y * 1e3:.1f} µm rms; after / best: "
        f"x {beam_result.after.rms_x / best.rms_x:.2f}, y {beam_result.after.rms_y / best.rms_y:.2f}")
    return best


@dataclass(frozen=True, kw_only=True)
class _Outcome:
    """What the session gives besides its runs: the steps' durations, the posterior, the calibration file."""

    timing: dict[str, float]
    calibration: Path | None
    posterior: Posterior | None


def _outcome(s: DemoSettings, out: Path, session, beam_result, t0: float) -> _Outcome:
    """The steps' durations, the offsets' posterior and, where it exists, the exported calibration."""
    from bluesky_offsets.model.export import write_calibration
    from bluesky_offsets.model.posterior import Posterior

    analysis, validation = session.analysis, session.validation
    posterior = Posterior.of(analysis, s.table)
    calibration = None if posterior is None else write_calibration(
        out / "calibration.json", analysis, table=s.table, measurement_uid=session.measured.measurement.uid,
        validation=None if validation is None else validation.summary())
    return _Outcome(timing=_timing(session, beam_result, t0), calibration=calibration, posterior=posterior)


def _timing(session, beam_result, t0: float) -> dict[str, float]:
    """Seconds per step of the session, for the report and the summary."""
    t, designed, validation = session.times, session.measured.designed, session.validation
    return {"IOC up": t["start"] - t0, "beam search + measure" + (" (designed)" if designed else ""):
            t["measure"] - t["start"],
            **({} if designed else {"surrogate finder": t["finder"] - t["measure"]}),
            "compare/fit/diagnose/refit": t["analysis"] - t["finder"],
            **({"validation frames": t["validation"] - t["analysis"]} if validation is not None else {}),
            **({"optimize, move, measure": t["optimize"] - t.get("validation", t["analysis"])}
               if beam_result is not None else {})}


def _intro(s: DemoSettings, offsets: Mapping, session, location: str) -> list[tuple[str, str]]:
    """The report's opening sections: what this demo is, and what it measured."""
    from bluesky_offsets.commands.report import paragraph, table_

    table = s.table
    analysis, m, n_open = session.analysis, session.measured.measurement, session.measured.n_open
    beam, designed, validation = session.measured.beam, session.measured.designed, session.validation
    what = (f"hidden offsets in all {len(table)} parameters (uniform within ±{s.offsets_fraction:g} of each "
            f"range)" if s.offsets_fraction > 0 else
            f"hidden offsets in {len(offsets)} of the {len(table)} parameters ({', '.join(offsets)})")
    how = (f"{len(m)} frames designed for the offsets ({designed.steps[0]['criterion'] if designed.steps else 'D'}"
           f"-optimal batches on the twin's exact Jacobians, the chamber's stage moved along the beam) after "
           f"{beam.frames} frames of the beam search, {session.measured.frames} in all; the offsets fitted through "
           f"the differentiable twin to all of them and to the beam search's lit ones, "
           f"{analysis.measurement.n} frames" if designed is not None else
           f"{len(m)} configurations measured through EPICS ({len(m) - n_open} bright ones, {n_open} of them again "
           f"with the slits open); offsets found with the shipped surrogate (on the configurations inside its "
           f"box) and fitted through the differentiable twin on {analysis.measurement.n}")
    return [("What this is", paragraph(
        f"bluesky-offsets demo: a simulated {s.display} beamline (caproto IOC, RAYX twin at the hidden true state, "
        f"{s.n_rays} rays per frame) with {what} and hidden effects: "
        f"{', '.join(f'{k} {v}' for k, v in s.hidden.items()) or 'none'}; {how}; the missing effects diagnosed, "
        f"added and refitted one after the other"
        + ("; then frames that no fit used, far from the fitted ones, to test the calibration" if validation
           else "") + f". Every step is a run in the store {location}.")),
        ("Measurement", table_([{"frames in all": session.measured.frames, "beam search": beam.frames,
                                 "measured for the fits": len(m), "with open slits": n_open,
                                 "analysed": analysis.measurement.n, "rays per frame": s.n_rays,
                                 "measurement uid": m.uid, "truth id": m.truth_id or ""}]))]


def _write_report(s: DemoSettings, truth: Mapping, out: Path, session, beam_result, best, steps: Mapping[str, str],
                  location: str, outcome: _Outcome) -> Path:
    """The HTML report."""
    from bluesky_offsets.commands.report import (beam_section, design_section, table_, validation_section,
                                                 write_analysis_report)

    analysis, validation, designed = session.analysis, session.validation, session.measured.designed
    beam_secs = [] if beam_result is None else [
        ("The smallest focus with the calibrated twin", beam_section(beam_result, out, best=best))]
    design_secs = [] if designed is None else [("The designed measurement", design_section(designed))]
    valid_secs = [] if validation is None else [("Validation frames", validation_section(validation))]
    report = write_analysis_report(out / "report.html", analysis, analysis.measurement.spec, title="bluesky-offsets demo",
                                   intro=_intro(s, truth["offsets"], session, location) + design_secs, truth=s.hidden, uids=steps,
                                   store_location=location, table=s.table, validation=validation,
                                   extra=[*valid_secs, *beam_secs,
                                          ("Timing", table_([{k: f"{v:.0f} s" for k, v in outcome.timing.items()}]))])
    return Path(report)


def _summary(s: DemoSettings, truth: Mapping, session, beam_result, best, outcome: _Outcome, *, report: Path,
             steps: Mapping, uids: Sequence[str], store: str, ioc: SimulatedBeamline, live: Sequence, seconds: float,
             load: float) -> dict:
    """The demo's ``summary.json``: what was hidden, measured, fitted and concluded, with every run's uid."""
    from plans.design import stated_verdict
    analysis, m, n_open = session.analysis, session.measured.measurement, session.measured.n_open
    beam, designed, validation = session.measured.beam, session.measured.designed, session.validation
    posterior, calibration = outcome.posterior, outcome.calibration
    return {
        "seconds": seconds, "load_average_start": load, "threads": s.threads, "timing_s": outcome.timing,
        "store": store,
        "uids": dict(steps), "all_run_uids": list(uids), "report": str(report), "n_configurations": len(m),
        "frames": session.measured.frames, "design": s.design_kind,
        "design_steps": [] if designed is None else [{k: np.asarray(v).tolist() if np.ndim(v) else v
                                                      for k, v in row.items()} for row in designed.steps],
        "n_open_configurations": n_open, "n_analysed_configurations": analysis.measurement.n,
        "beam_search": {"frames": beam.frames, "bright": beam.bright, "intensity": beam.intensity,
                        "steps": beam.log, "uids": beam.uids},
        "offsets": None if posterior is None else posterior.as_dict(),
        "validation": None if validation is None else validation.summary(),
        "calibration": None if calibration is None else str(calibration),
        "beamline": s.display, "n_rays": s.n_rays, "hidden_offsets": truth["offsets"],
        "offsets_fraction": s.offsets_fraction, "hidden_effects": s.hidden,
        "verdict": stated_verdict(analysis, validation),
        # a within-noise verdict: how large each candidate could be and still hide
        "could_hide": analysis.could_hide_json,
        "rankings": [[c.name for c in r.diagnosis.candidates] for r in analysis.rankings],
        "history": [c.total_row() for c in analysis.comparisons],
        "fitted_effects": analysis.magnitudes(),
        "retest": analysis.retests, "dropped": analysis.dropped,
        "truth_id": m.truth_id, "ioc": {"prefix": ioc.prefix, "port": ioc.port, "pid": ioc.proc.pid},
        "live_views": [str(p) for cb in live for p in cb.written],
        "beam": None if beam_result is None else _beam_summary(beam_result, best)}


def _true_best(truth: Mapping, beam):
    """The hidden true beamline's smallest focus.

    The same optimizer, options and limits on the true state (a simulation's check of the plan's
    result; the plan never sees it), from the last computed move's start, and refined from each
    computed move's settings: the true beamline reaches at least what the calibrated model's moves
    reached, so a best that the moves beat is no best.
    """
    from bluesky_offsets.model.state import ModelState
    from bluesky_offsets.optimize import DarkStart, TargetUnreachable, optimize_settings
    true = ModelState(METRIXS.from_mapping(truth["offsets"], base=np.zeros(len(METRIXS))), label="hidden truth")
    computed = [st.optimum for st in beam.steps if not st.note]

    def best_from(current, options):
        return optimize_settings(computed[-1].target, true, current, limits=beam.limits,
                                 constraints=beam.constraints, options=options,
                                 overrides=truth.get("overrides") or None)

    first = best_from(computed[-1].current, beam.options)
    found = [first.predicted]
    local = replace(beam.options, starts=1, global_starts=0)
    # the last move's start too: the search's survey can leave its own first start behind
    for settings in (o.settings for o in computed):
        with contextlib.suppress(DarkStart, TargetUnreachable):
            refined = best_from(settings, local)
            # the move's own settings on the truth as well: the soft beam the refinement descends can
            # part from the hard one
            found += [refined.predicted, refined.predicted_before]
    return min(found, key=lambda f: first.target.cost(f, first.predicted_before))


def _beam_summary(beam, best) -> dict:
    o = beam.optimum
    return {"uid": beam.uid, "target": o.target.name, "before": beam.before.as_dict(), "after": beam.after.as_dict(),
            "predicted": o.predicted.as_dict(), "predicted_sigma": dict(o.sigma), "trusted": o.trusted,
            "flags": [f.text() for f in o.flags], "moved": list(o.moved), "at_limit": list(o.at_limit),
            "true_best": None if best is None else best.as_dict(), "frames": beam.frames,
            "steps": [{"uid": st.uid, "predicted": st.optimum.predicted.as_dict(),
                       "predicted_sigma": dict(st.optimum.sigma), "sigma_samples": st.optimum.sampled,
                       "after": st.after.as_dict(),
                       "moved": list(st.optimum.moved), **({"note": st.note} if st.note else {})}
                      for st in beam.steps]}


def _print_summary(summary: dict, analysis, location: str) -> None:
    from bluesky_offsets.commands.report import history_lines
    print()
    print(f"verdict: {summary['verdict']}")
    if analysis.could_hide:
        print(analysis.could_hide_line)
    for k, ranking in enumerate(summary["rankings"], 1):
        print(f"ranking {k}: " + (", ".join(ranking[:5]) + (" ..." if len(ranking) > 5 else "") if ranking
                                  else "no candidate fitted (the model fits the frames within noise)"))
    print("hidden: " + (", ".join(f"{k} {v}" for k, v in summary["hidden_effects"].items()) or "no effect"))
    for name, vals in summary["fitted_effects"].items():
        hidden = summary["hidden_effects"].get(name, {})
        print(f"fitted {name}: " + ", ".join(
            f"{k} = {v:.3g}" + (f" ± {sg:.2g}" if math.isfinite(sg) else "") + (f" (hidden {hidden[k]:.3g})" if k in hidden else "")
            for k, (v, sg) in vals.items()))
    print("error history (a correct model: chi2/dof ≈ 1, MSE ≈ its noise expectation):")
    for line in history_lines(analysis):
        print(line)
    if summary.get("offsets"):
        c = summary["offsets"]["counts"]
        print(f"offsets ({summary['frames']} frames in all): {c['determined']} determined, {c['weak']} weak, "
              f"{c['undetermined']} undetermined; each as value ± sigma in {summary.get('calibration')}"
              + (f" (their spread estimated from the data: sigma {summary['offsets']['spread_normalized']:.3g} of each "
                 "range)" if summary["offsets"].get("spread_estimated") else ""))
    if summary.get("validation") and summary["validation"]["passed"]:  # a failed one is in the verdict
        v = summary["validation"]
        print(f"validation on {v['configurations']} frames no fit used: chi2/dof = {v['chi2_reduced']:.2f}, "
              f"MSE/noise = {v['mse_over_noise']:.2f} (passed)")
    print("runs in the store:")
    for k, v in summary["uids"].items():
        print(f"  {k:16s} {v}")
    first = summary["uids"].get("measurement")
    print("load them back:")
    print(f"  python -c \"from bluesky_offsets.store import open_store; from plans.diagnose import load_results; "
          f"s = open_store('{location}'); print(s.load_measurement('{first}').hist_x.shape); "
          f"print(load_results(s, '{summary['uids'].get('diagnose', first)}')['diagnosis'])\"")
    b = summary.get("beam")
    if b:
        def um(f):
            return f"{f['rms_x'] * 1e3:.1f} x {f['rms_y'] * 1e3:.1f} µm rms"
        print(f"smallest focus: before {um(b['before'])}; after {um(b['after'])}; predicted {um(b['predicted'])} "
              f"(± {b['predicted_sigma']['x'] * 1e3:.1f}, ± {b['predicted_sigma']['y'] * 1e3:.1f}"
              f"{'' if b['trusted'] else ', not trusted'}); the hidden truth's best {um(b['true_best'])}"
              + (f"; {len(b['steps'])} moves (closed loop), the first predicted {um(b['steps'][0]['predicted'])}, "
                 f"measured {um(b['steps'][0]['after'])}" if len(b.get("steps", ())) > 1 else "")
              + (f"; the second measured {um(b['steps'][1]['after'])}: back to the first's settings"
                 if b.get("steps") and b["steps"][-1].get("note") else ""))
    print(f"report: {summary['report']}")
    if summary.get("live_views"):
        print(f"live views: {len(summary['live_views'])} figures in {Path(summary['live_views'][0]).parent}")
    print(f"done in {summary['seconds']:.0f} s")


def add_cli(sub) -> None:
    """Register the ``demo`` sub-command on the command line's subparsers ``sub``."""
    from bluesky_offsets.commands.cli import add_analysis_options
    p = sub.add_parser("demo", help="the main job: calibrate and diagnose a simulated METRIXS end to end",
                       description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    p.add_argument("--beamline", default=None, metavar="FILE|NAME",
                   help="a described beamline (a description file, or a shipped one: energize) instead of METRIXS; "
                        "its measurement is designed, its effects those its file names")
    p.add_argument("--out", default="bluesky-offsets-demo", help="output folder (default ./bluesky-offsets-demo)")
    p.add_argument("--store", default=None, help="run store (default: the embedded store, $BLUESKY_OFFSETS_STORE)")
    p.add_argument("--rays", type=int, default=5000, help="source rays per measured frame (default %(default)s)")
    p.add_argument("--design", choices=("optimal", "bright"), default="optimal",
                   help="what is measured: frames designed for the offsets (default) or the bright configurations "
                        "around the beam (the paper's 16, 4 of them again with the slits open)")
    p.add_argument("--frames", type=int, default=DesignOptions.frames,
                   help="frames in all, the beam search's included (the designed measurement's budget; default "
                        "%(default)s)")
    p.add_argument("--validation-frames", type=int, default=DesignOptions.validation,
                   help="frames after the calibration, far from the fitted ones, that no fit uses (default "
                        "%(default)s; 0: none)")
    p.add_argument("--configurations", type=int, default=16, help="with --design bright: bright configurations to "
                                                                   "measure (>= 16)")
    p.add_argument("--open-configurations", type=int, default=None,
                   help="bright configurations measured again with the slits open, ASBL 4 x 4 mm and exit slit "
                        "100 µm (default 4)")
    p.add_argument("--analysed-configurations", type=int, default=14,
                   help="configurations the fits use: the open ones and the first bright ones (default %(default)s)")
    p.add_argument("--effect", action="append", default=None,
                   help="hidden effect NAME:PARAM=VALUE,... (repeat for several) or 'none' (default "
                        f"{DEMO_EFFECT[0]}:" + ",".join(f"{k}={v:g}" for k, v in DEMO_EFFECT[1].items()) + ")")
    p.add_argument("--offsets-fraction", type=float, default=DemoSettings.offsets_fraction,
                   help="hidden offsets in all parameters (METRIXS: 34), uniform within ± this fraction of each range "
                        "(default %(default)s; the paper's is 0.2; 0: 7 fixed offsets of 1-2 %% instead)")
    p.add_argument("--candidates", default=None, help="effects to rank, comma separated (default: all)")
    add_analysis_options(p, fit_rays=None,
                         fit_rays_help=f"model rays per configuration in the fits (default {D.DESIGNED_FIT.rays} for "
                                       f"the designed measurement's frames, {D.FIT.rays} for the bright design's; the "
                                       f"diagnosis's candidate fits use at most {D.DESIGNED_SCAN.rays} and "
                                       f"{D.SCAN.rays})",
                         resolution_help="histograms the diagnosis fits: the camera's profiles (20 µm x 5 µm bins, "
                                         "default) or the paper's 50 x 50 bins")
    p.add_argument("--seed", type=int, default=0,
                   help="another draw of the demo: candidate design, frame noise, fit seeds (default %(default)s)")
    p.add_argument("--motors", choices=("perfect", "realistic"), default="perfect",
                   help="the simulated motors: perfect (default), or every axis with encoder noise, backlash "
                        "and retries at typical values (sim_iocs.metrixs.motor_profile)")
    p.add_argument("--detector", choices=("camera", "histograms"), default=None,
                   help="read the focus chamber's camera (METRIXS's default; an areaDetector: dark frames, the gain "
                        "by photon transfer, frames reduced to histograms) or the simulator's ray-count histogram "
                        "PVs (a described beamline's default)")
    p.add_argument("--no-optimize", action="store_true",
                   help="end after the diagnosis, without the last step (the smallest focus with the calibrated "
                        "twin: computed, moved there, measured)")
    p.add_argument("--open-loop", action="store_true",
                   help="move once: without refitting the model with the frames taken after the move, "
                        "optimizing and moving once more (the default)")
    p.set_defaults(func=_cmd_demo)


def parse_effect(text: str) -> tuple[str, dict]:
    """Read ``--effect NAME:PARAM=VALUE,...`` (or ``none``): the effect's name and all its values, checked."""
    from bluesky_offsets.commands.cli import CliError
    if text.lower() in ("none", ""):
        return ("", {})
    name, _, rest = text.partition(":")
    try:
        eff = E.get(name)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    values = {}
    for item in filter(None, rest.split(",")):
        k, _, v = item.partition("=")
        try:
            values[k.strip()] = float(v)
        except ValueError:
            raise CliError(f"--effect {name}: {item!r} is not PARAM=NUMBER") from None
    try:
        full = eff.values(values)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    for p in eff.parameters:
        if not p.low <= full[p.name] <= p.high:
            raise CliError(f"--effect {name}: {p.name} = {full[p.name]:g} {p.unit} lies outside its prior range "
                           f"[{p.low:g}, {p.high:g}]")
    return name, full


def _check_beamline(args, hidden: Sequence[str]) -> bool:
    """Read ``--beamline``'s description and check the options against it (one line each).

    Returns whether the demo ends with the beam optimization.
    """
    from bluesky_offsets.commands.cli import CliError
    from bluesky_offsets.physics.beamline import BeamlineError, resolve
    if args.beamline is None:
        return not args.no_optimize
    try:
        bl = resolve(args.beamline)
    except BeamlineError as exc:
        raise CliError(str(exc)) from None
    if bl.builtin == "metrixs":
        args.beamline = None
        return not args.no_optimize
    if args.design != "optimal":
        raise CliError(f"--design bright needs the surrogate, trained on METRIXS; on {bl.name} the measurement is "
                       f"designed (the default)")
    asked = [c.strip() for c in args.candidates.split(",")] if args.candidates else []
    foreign = [n for n in [*hidden, *asked] if n not in bl.effects]
    if foreign:
        raise CliError(f"--effect/--candidates: {', '.join(foreign)} not among {bl.name}'s effects "
                       f"({', '.join(bl.effects)}; its description file names them)")
    if not args.no_optimize:
        print(f"the beam optimization's targets are METRIXS's (E1/E2); on {bl.name} the demo ends with the "
              f"validation frames", flush=True)
    return False


def _cmd_demo(args) -> int:
    from bluesky_offsets.commands.cli import CliError, check_analysis_options, dark_beamline, output_folder
    if args.configurations < 2:
        raise CliError("--configurations must be at least 2 (the paper asks for 16)")
    n_open = args.open_configurations if args.open_configurations is not None else 4
    if not 0 <= n_open <= args.configurations:
        raise CliError(f"--open-configurations must lie in [0, {args.configurations}] (the bright ones reopened)")
    if args.analysed_configurations < 2:
        raise CliError("--analysed-configurations must be at least 2")
    if args.rays < 100:
        raise CliError("--rays must be at least 100")
    from sim_iocs.metrixs import MAX_RAYS
    if args.rays > MAX_RAYS:
        raise CliError(f"--rays must be at most {MAX_RAYS:,} (the simulated IOC's bound on a frame)")
    if args.frames < 4:
        raise CliError("--frames must be at least 4 (the beam search's and the designed ones)")
    if args.validation_frames < 0:
        raise CliError("--validation-frames must be 0 or more")
    if not 0 <= args.offsets_fraction <= 0.2:
        raise CliError("--offsets-fraction must lie in [0, 0.2] (offsets beyond 20 % of a range are outside the model)")
    check_analysis_options(args)
    effects = tuple(parse_effect(e) for e in (args.effect or [f"{DEMO_EFFECT[0]}:z={DEMO_EFFECT[1]['z']}"]))
    effects = tuple(e for e in effects if e[0])
    names = [e[0] for e in effects]
    if len(set(names)) != len(names):
        raise CliError(f"--effect: each effect once ({', '.join(names)})")
    try:
        E.twin_overrides({n: v for n, v in effects if E.get(n).level == "twin"})
    except ValueError as exc:
        raise CliError(f"--effect: {exc}") from None
    if any(E.get(n).level == "detector" for n in names):
        raise CliError("--effect: the simulated IOC hides twin-level effects only (detector-level ones: "
                       + ", ".join(n for n in names if E.get(n).level == "detector") + ")")
    optimize = _check_beamline(args, names)
    fit, scan = D.fits_for(args.design == "optimal", args.fit_rays, args.fit_starts)
    s = DemoSettings(n_rays=args.rays, effects=effects, design_kind=args.design,
                     optimal=DesignOptions(frames=args.frames, validation=args.validation_frames),
                     measurement=_design(bright=args.configurations, reopened=n_open,
                                         analysed=args.analysed_configurations),
                     offsets_fraction=args.offsets_fraction, rounds=args.rounds, seed=args.seed,
                     fit_top=args.fit_top or None, fit=fit, scan=scan,
                     resolution=args.resolution, optimize=optimize, closed_loop=not args.open_loop,
                     threads=args.threads, motors=args.motors,
                     detector=args.detector or ("camera" if args.beamline is None else "histograms"),
                     candidates_effects=[c.strip() for c in args.candidates.split(",")] if args.candidates else None,
                     beamline=args.beamline)
    for n in s.candidates_effects or ():
        try:
            E.get(n)
        except ValueError as exc:
            raise CliError(str(exc)) from None
    # a batch system or a CI runner stops jobs with SIGTERM: unwind like Ctrl-C, so that the
    # ``finally`` of run_demo stops the IOC and the Dask workers instead of orphaning them
    import signal

    def _terminate(signum, frame):
        raise SystemExit(128 + signum)

    from plans.workflow import DarkBeamline
    output_folder(args.out)  # before the IOC starts: a report that cannot be written is known now
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        run_demo(Path(args.out), s, args.store)
    except DarkBeamline as exc:
        raise dark_beamline(exc, args.frames if s.design_kind == "optimal" else None) from None
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0
