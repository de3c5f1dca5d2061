"""The calibration session's steps as plans whose arguments are plain values.

Device arguments are devices (bluesky-queueserver passes them by name: ``"metrixs"``,
``"chamber"``); everything else is a number, a name, a list of them or a run uid, so that a
queue item can carry it as JSON.  A uid argument also takes ``"last"``: the most recent run of
that kind in the run store (``store``, default :func:`bluesky_offsets.store.shared_store`),
which is how one queue measures, finds the offsets and analyses without knowing the uids
in advance.

* :func:`measure_bright` — find the beam from where the motors stand, find bright
  configurations around it and measure them (and some again with the slits open).
* :func:`find_offsets_in_store` — the shipped surrogate finder on a stored measurement.
* :func:`analyse` — compare, fit the offsets, diagnose, add the winning effect, refit,
  diagnose again (:func:`plans.diagnose.analyse_measurement`) on a stored measurement.

Progress lines go to the ``bluesky_offsets.workflow`` logger (the queueserver's console,
the demo's terminal).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from bluesky.utils import MsgGenerator

from bluesky_offsets.design import DesignOptions
from bluesky_offsets.errors import InputError
from bluesky_offsets.model import diagnosis as D
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.physics.screen import as_screen

from .camera import gain_scale
from .search import DarkBeamline, bright_beam, lit_frames

if TYPE_CHECKING:
    from bluesky_offsets.offsets.beam_search import SearchResult

    from .design import Designed, Validation
    from .diagnose import Analysis
    from .offsets import OffsetResult

log = logging.getLogger("bluesky_offsets.workflow")

__all__ = ["DarkBeamline", "MeasurementDesign", "Measured", "Session", "analyse", "calibration_session",
           "candidate_configurations", "export_calibration", "find_offsets_in_store", "measure", "measure_bright",
           "measure_for_offsets", "measurement_design", "resolve_run", "validate"]


# --------------------------------------------------------------------------- #
# what is measured
# --------------------------------------------------------------------------- #
@dataclass(frozen=True, kw_only=True)
class MeasurementDesign:
    """How many configurations :func:`measure_bright` looks for and measures.

    ``bright`` configurations (the paper's 16), the first ``reopened`` of them again with the slits
    open (:func:`bluesky_offsets.model.diagnosis.open_aperture`: a source change shows there),
    ``analysed`` of them fitted by the analysis (the first bright ones and all open ones);
    ``candidates`` tried around the beam (:func:`bluesky_offsets.model.diagnosis.diagnostic_configurations`);
    the beam search assumes offsets up to ``fraction`` of each range and takes at most
    ``max_frames`` frames.
    """

    bright: int = 16
    reopened: int = 4
    analysed: int = 14
    candidates: int = 40
    fraction: float = 0.15
    max_frames: int = 120
    seed: int = 0

    def __post_init__(self):
        if self.bright < 2:
            raise InputError(f"bright must be at least 2 (the paper measures 16), got {self.bright}")
        if not 0 <= self.reopened <= self.bright:
            raise InputError(f"reopened must lie in [0, bright={self.bright}], got {self.reopened}")
        if self.analysed < 2:
            raise InputError(f"analysed must be at least 2, got {self.analysed}")
        if self.candidates < self.bright - 1:
            raise InputError(f"candidates ({self.candidates}) cannot give {self.bright} bright configurations")
        if not 0 < self.fraction <= 0.2:
            raise InputError(f"fraction must lie in (0, 0.2], got {self.fraction}")
        if self.max_frames < 1:
            raise InputError(f"max_frames must be at least 1, got {self.max_frames}")


def candidate_configurations(design: MeasurementDesign, start: np.ndarray) -> np.ndarray:
    """The start, then ``design.candidates`` configurations around it.

    The start comes first because an operator begins where the beam is; the others are
    :func:`bluesky_offsets.model.diagnosis.diagnostic_configurations`, drawn from ``design.seed``.
    """
    return np.vstack([start, D.diagnostic_configurations(start, design.candidates, seed=design.seed, table=METRIXS)])


def measurement_design(design: MeasurementDesign, bright: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What is measured and what is analysed: the configurations and the indices the fits use.

    Measured are the ``bright`` configurations, then the first ``design.reopened`` of them again
    with the slits open; the fits use the first bright ones and all open ones, ``design.analysed``
    in all.
    """
    n_open = min(design.reopened, len(bright))
    configs = np.vstack([bright, D.open_aperture(bright[:n_open])]) if n_open else np.asarray(bright)
    n_bright = max(0, min(len(bright), design.analysed - n_open))
    return configs, np.r_[np.arange(n_bright), np.arange(len(bright), len(configs))].astype(int)


@dataclass
class Measured:
    """What :func:`measure_bright` (or :func:`plans.design.measure_designed`) did.

    The beam search and the measurement; ``designed`` the design's record where the frames were
    designed.
    """

    beam: SearchResult
    measurement: Measurement
    n_open: int
    analysed: np.ndarray         # indices of the configurations the analysis fits
    designed: Designed | None = None

    @property
    def uid(self) -> str | None:
        """The measurement run's uid (None where it has none)."""
        return self.measurement.uid

    @property
    def frames(self) -> int:
        """Frames taken in all (the beam search's, a bright search's and the measurement's)."""
        if self.designed is not None:
            return self.designed.frames
        return int(self.beam.frames) + int(self.measurement.metadata.get("search_frames", 0)) + self.measurement.n


def measure_bright(beamline, chamber, *, bright: int = 16, reopened: int = 4, analysed: int = 14,
                   candidates: int = 40, fraction: float = 0.15, max_frames: int = 120, seed: int = 0,
                   md: dict | None = None) -> MsgGenerator[Measured]:
    """Find the beam, find bright configurations around it, measure them.

    :func:`plans.find_beam` from where the motors stand (slits opened, the sensitive motors
    scanned upstream first, as an operator does); then ``candidates`` configurations around the
    beam (:func:`bluesky_offsets.model.diagnosis.diagnostic_configurations`, drawn from ``seed``)
    until ``bright`` are bright (:func:`plans.find_high_ray_configurations`); then
    :func:`plans.measure_configurations` of those and of the first ``reopened`` again with the
    slits open.  The measurement run records the design (``design``) and which configurations the
    analysis fits (``analysed_configurations``), so that :func:`analyse` needs only its uid.

    Raises :class:`DarkBeamline` (before measuring) when the beam or enough bright
    configurations cannot be found.

    Returns
    -------
    Measured
        The beam search, the measurement (``uid``), how many were measured with the slits open,
        the analysed indices.  ``md`` goes into the measurement run's metadata.
    """
    from plans import find_high_ray_configurations, measure_configurations

    design = MeasurementDesign(bright=bright, reopened=reopened, analysed=analysed, candidates=candidates,
                               fraction=fraction, max_frames=max_frames, seed=seed)
    beam = yield from bright_beam(beamline, chamber, fraction=fraction, max_frames=max_frames)
    here = beam.configuration
    cand = candidate_configurations(design, here)
    log.info("searching %d candidate configurations around it for %d bright ones (beam found in %d frames)",
             len(cand), bright, beam.frames)
    found = yield from find_high_ray_configurations(cand, beamline, chamber, n=bright, table=METRIXS)
    if len(found) < bright:
        raise DarkBeamline(f"only {len(found)} of {len(cand)} candidate configurations were bright; {bright} needed")
    configs, idx = measurement_design(design, found)
    n_open = len(configs) - len(found)
    # the search stops at the last bright one it needs: the frames it took
    at = [int(np.flatnonzero(np.all(cand == f, axis=1))[0]) for f in found]
    searched = max(at) + 1 if len(found) >= bright else len(cand)
    log.info("measuring %d bright configurations%s", len(found),
             f" and {n_open} of them with the slits open (ASBL 4 x 4 mm, exit slit 100 µm)" if n_open else "")
    m = yield from measure_configurations(configs, beamline, chamber, table=METRIXS, md={
        "purpose": "calibration measurement", "design": asdict(design), "n_bright": len(found), "n_open": n_open,
        "search_frames": searched,
        "analysed_configurations": [int(i) for i in idx], "beam_search_uids": list(beam.uids), **dict(md or {})})
    return Measured(beam, m, n_open, idx)


def measure(beamline, chamber, configurations: list, *, md: dict | None = None) -> MsgGenerator[Measurement]:
    """:func:`plans.measure_configurations` with plain values.

    ``configurations`` is a list of 34-number lists (twin coordinates, table order) or of
    ``{parameter: value}`` dicts.
    """
    from plans import measure_configurations
    return (yield from measure_configurations(configurations, beamline, chamber, md=md))


# --------------------------------------------------------------------------- #
# runs by uid
# --------------------------------------------------------------------------- #
PLANS_OF_KIND = {
    "measurement": ("measure_configurations",),
    "offsets": ("find_offsets",),
    "model": ("add_effect_and_refit", "refine_offsets"),   # a fitted model with its covariance
}


def resolve_run(store, uid: str, kind: str, **match) -> str:
    """``uid`` itself, or for ``"last"`` the most recent successful run of ``kind`` that matches.

    ``kind`` is a key of :data:`PLANS_OF_KIND`; the run's start document must have ``match``'s
    values.
    """
    if uid != "last":
        if uid not in store:
            raise KeyError(f"no run {uid!r} in the store at {store.location}")
        return uid
    found = store.latest(PLANS_OF_KIND[kind], **match)
    if found is None:
        what = ", ".join(f"{k} = {v}" for k, v in match.items())
        raise LookupError(f"no {kind} run in the store at {store.location}" + (f" with {what}" if what else ""))
    return found


def _store(store):
    from bluesky_offsets.store import shared_store
    return shared_store() if store is None else store


# --------------------------------------------------------------------------- #
# offsets
# --------------------------------------------------------------------------- #
def find_offsets_in_store(measurement: str = "last", *, evaluations: int = 3000, seed: int = 0,
                          checkpoint: str | None = None, store=None, md: dict | None = None) -> MsgGenerator:
    """The surrogate finder on a stored measurement's configurations inside the surrogate's box.

    The finder is :class:`bluesky_offsets.offsets.calibration.OffsetFinder` (``evaluations`` of the
    surrogate, ``seed``); the slits-open configurations are outside the box.

    ``measurement`` is a run uid or ``"last"``; ``checkpoint`` another surrogate (default the
    shipped one).  Returns the :class:`plans.offsets.OffsetResult`; the run is a ``find_offsets``
    run linked to the measurement (``measurement_uid``).
    """
    from bluesky_offsets.offsets.finder import load_forward_model

    if evaluations < 1:
        raise InputError(f"evaluations must be at least 1, got {evaluations}")
    store = _store(store)
    m = store.load_measurement(resolve_run(store, measurement, "measurement"), table=METRIXS)
    return (yield from surrogate_offsets(m, load_forward_model(checkpoint), evaluations=evaluations, seed=seed,
                                         md=md))


def surrogate_offsets(m: Measurement, forward_model, *, evaluations: int = 3000, seed: int = 0,
                      md: dict | None = None) -> MsgGenerator:
    """:func:`find_offsets_in_store` on a :class:`Measurement` with a loaded surrogate."""
    from bluesky_offsets.offsets.calibration import OffsetFinder
    from bluesky_offsets.offsets.finder import Budget
    from plans import find_offsets

    # the surrogate sees the chamber at its stage's zero: frames with the screen moved are not its
    inside = D.in_box(m.configurations, METRIXS) & ~np.any(as_screen(m.screen, m.n) != 0, axis=1)
    if not inside.any():
        raise InputError(f"measurement {m.uid}: no configuration inside the surrogate's box with the screen at 0")
    finder = OffsetFinder(model=forward_model, budget=Budget(evaluations=evaluations), seed=seed)
    log.info("finding the offsets with the surrogate on the %d configurations in its box (%d evaluations)",
             int(inside.sum()), evaluations)
    return (yield from find_offsets(finder, m if inside.all() else m.subset(inside), table=METRIXS,
                                    md={"evaluations": int(evaluations), "seed": int(seed), **dict(md or {})}))


# --------------------------------------------------------------------------- #
# the whole session
# --------------------------------------------------------------------------- #
@dataclass
class Session:
    """What :func:`calibration_session` did, and when each part ended (``times``, perf_counter)."""

    measured: Measured
    offsets: OffsetResult | None  # ``uid``: its run; None for a designed one
    analysis: Analysis
    times: dict
    validation: Validation | None = None


def calibration_session(beamline, chamber, twin, forward_model, *, design: MeasurementDesign | DesignOptions,
                        evaluations: int = 3000, candidates: Sequence[str] | None = None, rounds: int = D.ROUNDS,
                        fit=None, scan=None, fit_top: int | None = D.FIT_TOP, resolution: str = "camera",
                        measurement_md: dict | None = None, analysis_md: dict | None = None,
                        step=log.info, executor=None, measured=None, table=METRIXS) -> MsgGenerator[Session]:
    """The calibration session on a beamline: the measurement, its analysis and (designed) validation frames.

    With :class:`~bluesky_offsets.design.DesignOptions` (the default of the demo and ``calibrate``):
    :func:`plans.design.measure_designed`, then :func:`plans.diagnose.analyse_measurement` of every
    designed frame and the beam search's lit ones (:func:`plans.search.lit_frames`) from the bare
    twin and the design's last estimate of the offsets, then validation frames no fit used
    (:func:`plans.design.measure_validation`).  With a :class:`MeasurementDesign` (the bright
    design): :func:`measure_bright`, :func:`surrogate_offsets` on it, then the analysis of the
    analysed configurations from the bare twin and the surrogate's offsets.  ``step(text)``
    announces each part (the demo numbers them); ``executor`` runs the analysis's independent fits
    side by side (the same result); seeds from ``design.seed``.  ``measured(m, among=k)``, a plan,
    gets the frames to fit before the analysis and returns them as they are to be analysed (a
    camera calibrated where the first ``k`` of them, the measurement's own, were brightest:
    :func:`plans.camera.calibrate_where_bright`).  ``table`` names the beamline; a described one
    (not METRIXS) is measured by design only: the surrogate is METRIXS's.
    """
    from bluesky_offsets.model.state import ModelState

    from .diagnose import analyse_measurement

    if isinstance(design, DesignOptions):
        return (yield from _designed_session(beamline, chamber, twin, design=design, candidates=candidates,
                                             rounds=rounds, fit=fit, scan=scan, fit_top=fit_top,
                                             resolution=resolution, measurement_md=measurement_md,
                                             analysis_md=analysis_md, step=step, executor=executor,
                                             measured=measured, table=table))
    if table.version != METRIXS.version:
        raise InputError(f"the bright design finds the offsets with the surrogate, trained on METRIXS; on "
                         f"{table.name} the measurement is designed (DesignOptions)")
    t = {"start": time.perf_counter()}
    step("finding the beam, bright configurations around it, measuring them")
    bright = yield from measure_bright(beamline, chamber, **asdict(design), md=measurement_md)
    if measured is not None:
        bright = replace(bright, measurement=(yield from measured(bright.measurement)))
    t["measure"] = time.perf_counter()
    m, analysed, n_open = bright.measurement, bright.analysed, bright.n_open
    meas = m.for_analysis(resolution=resolution).subset(analysed)

    step("finding the offsets with the surrogate, then through the twin")
    found = yield from surrogate_offsets(m, forward_model, evaluations=evaluations, seed=design.seed)
    t["finder"] = time.perf_counter()
    starts = [ModelState(np.zeros(len(METRIXS)), _flux_start(m, METRIXS), "twin"),
              ModelState(np.asarray(found.offsets, float), _flux_start(m, METRIXS), "surrogate offsets")]
    step(f"compare → fit offsets (differentiable twin, exact Jacobians) → diagnose → add the winning effect "
         f"→ refit → diagnose again ({len(analysed) - n_open} bright + {n_open} open configurations)")
    analysis = yield from analyse_measurement(meas, twin, starts=starts, candidates=candidates, rounds=rounds,
                                              fit_options=fit, scan_options=scan, fit_top=fit_top, seed=design.seed,
                                              executor=executor,
                                              md={**dict(analysis_md or {}),
                                                  "analysed_configurations": [int(i) for i in analysed]})
    t["analysis"] = time.perf_counter()
    return Session(bright, found, analysis, t)


def _flux_start(m, table: ParameterTable) -> dict:
    """The effects a calibration starts with: the flux scale where the frames' flux is not known.

    A camera's counts carry its gain and the flux reading, each known to a few %, and a described
    beamline's source says nothing of the flux the real one delivers: one scale, fitted.
    """
    from bluesky_offsets.physics.beamline import of_table
    described = of_table(table)
    unknown = m.floor_x is not None or (described is not None and described.builtin is None
                                        and "intensity_scale" in described.effects)
    return {"intensity_scale": {"delta": 0.0}} if unknown else {}


def _designed_session(beamline, chamber, twin, *, design: DesignOptions, candidates, rounds, fit, scan, fit_top,
                      resolution, measurement_md, analysis_md, step, executor, measured,
                      table=METRIXS) -> MsgGenerator[Session]:
    from bluesky_offsets.model.state import ModelState

    from .design import measure_designed, measure_validation, record_posterior
    from .diagnose import analyse_measurement

    t = {"start": time.perf_counter()}
    step(f"finding the beam, then frames designed for the offsets ({design.frames} frames in all, "
         f"{design.criterion}-optimal batches of {design.batch} on the twin's exact Jacobians)")
    d = yield from measure_designed(beamline, chamber, options=design, md=measurement_md, table=table)
    m = d.measurement
    lit = lit_frames(d.beam.measurements)
    fitted = m if lit is None else m.joined(lit)
    if measured is not None:  # the camera calibrated where the designed frames were brightest
        fitted = yield from measured(fitted, among=m.n)
        m = fitted.subset(np.arange(m.n))
        d = replace(d, measurement=m)
    measured = Measured(d.beam, m, 0, np.arange(m.n), d)
    t["measure"] = t["finder"] = time.perf_counter()
    starts = [ModelState(np.zeros(len(table)), _flux_start(m, table), "twin"),
              ModelState(np.asarray(d.offsets, float), _flux_start(m, table), "design estimate")]
    step(f"compare → fit offsets (differentiable twin, exact Jacobians) → diagnose → add the winning effect "
         f"→ refit → diagnose again ({m.n} designed frames + {fitted.n - m.n} lit frames of the beam search)")
    analysis = yield from analyse_measurement(fitted.for_analysis(resolution=resolution, table=table), twin,
                                              starts=starts, candidates=candidates, rounds=rounds, fit_options=fit,
                                              scan_options=scan, fit_top=fit_top, seed=design.seed,
                                              executor=executor, md=dict(analysis_md or {}), table=table)
    t["analysis"] = time.perf_counter()
    analysis.uids["posterior"] = yield from record_posterior(analysis, measurement_uid=m.uid, md=analysis_md,
                                                             table=table)
    validation = None
    if design.validation:
        step(f"{design.validation} validation frames far from the fitted ones, the calibrated model against them")
        validation = yield from measure_validation(beamline, chamber, analysis, m, twin, n=design.validation,
                                                   options=design, md={"purpose": "validation frames"}, table=table)
        log.info("  %s", validation.line())
    t["validation"] = time.perf_counter()
    return Session(measured, None, analysis, t, validation)


# --------------------------------------------------------------------------- #
# the analysis
# --------------------------------------------------------------------------- #
def analyse(measurement: str = "last", offsets: str | None = "last", *, candidates: list[str] | None = None,
            rounds: int = D.ROUNDS, fit: dict | None = None, scan: dict | None = None,
            fit_top: int | None = D.FIT_TOP, resolution: str = "camera", seed: int = 0, rays: int | None = None,
            scheduler: str | None = None, resume: bool = False, store=None, md: dict | None = None) -> MsgGenerator:
    """Compare, fit the offsets, diagnose, add the winner, refit, diagnose again, on a stored measurement.

    :func:`plans.diagnose.analyse_measurement`, one run per step.

    Parameters
    ----------
    measurement : str
        Measurement run uid, or ``"last"``.  Its ``analysed_configurations`` (written by
        :func:`measure_bright`) choose the configurations fitted; all of them otherwise.
    offsets : str or None
        A ``find_offsets`` run of this measurement whose offsets start the fit beside the bare
        twin (``"last"``: the most recent one, if any; None: the bare twin only).
    candidates : list of str, optional
        Effects to rank (default: all).
    fit, scan : mapping, optional
        :class:`bluesky_offsets.model.fit.FitOptions` of the offsets fit and refits, and of the
        diagnosis's candidate fits, as plain dicts (an unknown key is refused).
    rays : int, optional
        Rays per trace of the twin's comparisons (default 10,000).
    scheduler : str, optional
        Where the twin's RAYX traces run: None, a Dask LocalCluster; ``"inline"``, this process;
        a scheduler address, a cluster.
    resume : bool
        Take the steps an interrupted run of the same analysis completed from the store
        (:func:`plans.diagnose.analyse_measurement`); nothing is measured again.

    Returns
    -------
    plans.diagnose.Analysis
    """
    from bluesky_offsets.model.fit import FitOptions
    from bluesky_offsets.model.state import ModelState
    from bluesky_offsets.physics.twin import Twin

    from .diagnose import analyse_measurement

    store = _store(store)
    uid = resolve_run(store, measurement, "measurement")
    m = store.load_measurement(uid, table=METRIXS)
    designed = "design_options" in m.metadata  # plans.design.measure_designed's: its fits and its estimate
    base_fit, base_scan = D.fits_for(designed)
    fit_opts, scan_opts = FitOptions.resolve(fit, base_fit), FitOptions.resolve(scan, base_scan)
    for n in candidates or ():
        from bluesky_offsets.physics import effects as E
        E.get(n)  # an unknown name fails before anything runs
    idx = m.metadata.get("analysed_configurations")
    meas = as_analysed(store, m, resolution)
    starts = [ModelState(label="twin")]
    if designed:
        from .diagnose import load_results
        rows = load_results(store, uid).get("design") or []
        if rows:
            starts.append(ModelState(np.asarray(rows[-1]["offsets"], float), {}, "design estimate"))
    off_uid = None
    if offsets is not None:
        try:
            off_uid = resolve_run(store, offsets, "offsets", measurement_uid=uid)
        except LookupError:
            if offsets != "last":
                raise
        if off_uid is not None:
            row = store[off_uid]["offsets"].read()
            starts.append(ModelState(np.asarray(row["offsets"][0], float), {}, "surrogate offsets"))
    log.info("analysing measurement %s: %d configurations, starts: %s", uid, meas.n,
             ", ".join(s.label for s in starts))
    twin = Twin(n_rays=int(rays or 10_000), scheduler=scheduler)
    try:
        out = yield from analyse_measurement(
            meas, twin, store=store, starts=starts, candidates=candidates, rounds=rounds, fit_options=fit_opts,
            scan_options=scan_opts, fit_top=fit_top, seed=seed, resolution=resolution, table=METRIXS, resume=resume,
            md={"purpose": "calibration analysis", "offsets_uid": off_uid or "",
                "analysed_configurations": [int(i) for i in idx] if idx is not None else [], **dict(md or {})})
        log.info("verdict: %s", out.verdict)
        return out
    finally:
        twin.close()


def as_analysed(store, m: Measurement, resolution: str = "camera", table: ParameterTable = METRIXS) -> Measurement:
    """A stored measurement as :func:`analyse` fits it.

    A designed one joined by its beam search's lit frames; rescaled to the camera's gain measured
    after it (:func:`plans.camera.gain_scale`); its ``analysed_configurations`` (written by
    :func:`measure_bright`) chosen, all of them otherwise; at ``resolution``.
    """
    idx = m.metadata.get("analysed_configurations")
    if "design_options" in m.metadata:
        m = with_lit_beam_frames(store, m, table)
    meas = m.scaled(gain_scale(store, m.uid)).for_analysis(resolution=resolution, table=table)
    return meas if idx is None else meas.subset(np.asarray(idx, dtype=int))


def calibration_frames(cal, store=None, table: ParameterTable = METRIXS):
    """The frames a calibration was fitted on, as its fit read them, and the fit's options.

    Read from the calibration's fitted model's run (``cal.uid``) and its measurement in ``store``;
    None where the store lacks either or they no longer agree (frames, binning).
    """
    from bluesky_offsets.model.fit import FitOptions

    from .diagnose import load_results
    try:
        start = load_results(store, cal.uid)["start"] if cal.uid else {}
        m = store.load_measurement(start["measurement_uid"], table=table) if "fit_options" in start else None
    except (KeyError, LookupError):
        return None
    hist = start.get("histogram") or {}
    if m is None or "bins_x" not in hist:
        return None
    # the binning the fit read: the camera's profiles, or the paper's 50 x 50 histograms
    meas = as_analysed(store, m, "camera" if hist["bins_x"] > 50 else "paper", table)
    if meas.spec.fingerprint() != hist or meas.n != start.get("n_configurations"):
        return None
    return meas, FitOptions.from_mapping(start["fit_options"])


def with_lit_beam_frames(store, m: Measurement, table: ParameterTable = METRIXS) -> Measurement:
    """A stored designed measurement joined by its beam search's lit frames, as the session fits them.

    The beam search's runs are the measurement's ``beam_search_uids``; :func:`plans.search.lit_frames`.
    """
    lit = lit_frames([store.load_measurement(u, table=table) for u in m.metadata.get("beam_search_uids", ())])
    return m if lit is None else m.joined(lit)


# --------------------------------------------------------------------------- #
# the better beam
# --------------------------------------------------------------------------- #
def calibrated_in_store(uid: str = "last", store=None):
    """The calibrated state of a stored fitted model's run, or of a calibration file.

    A :class:`bluesky_offsets.model.state.CalibratedState`: of a stored ``add_effect_and_refit`` or
    ``refine_offsets`` run (``"last"``: the newest), with its fit's covariance; or of a calibration
    file (a path ending in ``.json``: :func:`bluesky_offsets.model.export.load_calibration`).
    """
    if str(uid).endswith(".json"):
        from bluesky_offsets.model.export import load_calibration
        return load_calibration(uid)
    from .diagnose import load_results, restore_refinement, restore_refit
    store = _store(store)
    uid = resolve_run(store, uid, "model")
    res = load_results(store, uid)
    if res["start"]["plan_name"] == "add_effect_and_refit":
        return restore_refit(res, [], uid).calibrated
    return restore_refinement(res, uid).calibrated


def optimize(beamline, chamber, target: dict | None = None, model: str = "last", *, frames: int = 1,
             constraints: dict | None = None, options: dict | None = None, store=None,
             md: dict | None = None) -> MsgGenerator:
    """:func:`plans.optimize.optimize_beam` with plain values, for a queue.

    ``target`` a mapping (``{"kind": "spot_size", "rms_x": 0.2, "rms_y": 0.05}``; default the
    smallest focus), ``model`` the uid of a fitted model's run, ``"last"`` or a calibration file
    (:func:`calibrated_in_store`), ``constraints``/``options`` mappings of
    :class:`bluesky_offsets.optimize.Constraints` / :class:`~bluesky_offsets.optimize.OptimizeOptions`
    fields.  Where the store holds the frames the model was fitted on (:func:`calibration_frames`),
    the prediction's σ is read from posterior samples that fit them, else from its covariance.
    """
    from .optimize import optimize_beam
    store = _store(store)
    cal = calibrated_in_store(model, store)
    # the calibration's frames, where the store holds them: the prediction's σ from posterior samples
    fitted = calibration_frames(cal, store)
    return (yield from optimize_beam(target or "smallest_focus", cal, beamline, chamber, frames=frames,
                                     constraints=constraints, options=options,
                                     measurement=None if fitted is None else fitted[0],
                                     refit=None if fitted is None else fitted[1].replace(ray_draws=1),
                                     md={"model_uid": cal.uid, **dict(md or {})}))


# --------------------------------------------------------------------------- #
# the designed measurement, its validation and the calibration file, for a queue
# --------------------------------------------------------------------------- #
def measure_for_offsets(beamline, chamber, *, frames: int = 60, batch: int = 8, criterion: str = "D",
                        seed: int = 0, options: dict | None = None, md: dict | None = None) -> MsgGenerator:
    """:func:`plans.design.measure_designed` with plain values: the queue's default measurement.

    The frame budget (the beam search's included), the batch size, the criterion, the seed, and any
    other :class:`~bluesky_offsets.design.DesignOptions` field in ``options`` (an unknown key is
    refused).  :func:`analyse` then fits it (``measurement="last"``).
    """
    from .design import measure_designed
    o = DesignOptions.from_mapping(options, frames=frames, batch=batch, criterion=criterion, seed=seed)
    return (yield from measure_designed(beamline, chamber, options=o, md=md))


def validate(beamline, chamber, model: str = "last", measurement: str = "last", *, frames: int = 6,
             seed: int = 0, rays: int | None = None, scheduler: str | None = None, store=None,
             md: dict | None = None) -> MsgGenerator:
    """:func:`plans.design.measure_validation` with plain values.

    ``frames`` settings far from the fitted frames of ``measurement`` (a run uid or ``"last"``),
    measured, and the calibrated ``model`` (a fitted model's run uid or ``"last"``) compared with
    them.
    """
    from bluesky_offsets.physics.twin import Twin

    from .design import measure_validation
    store = _store(store)
    cal = calibrated_in_store(model, store)
    m = store.load_measurement(resolve_run(store, measurement, "measurement"), table=METRIXS).for_analysis()
    twin = Twin(n_rays=int(rays or 10_000), scheduler=scheduler)
    try:
        v = yield from measure_validation(beamline, chamber, cal, m, twin, n=frames,
                                          options=DesignOptions(seed=seed), md=md)
    finally:
        twin.close()
    log.info("%s", v.line())
    return v


def export_calibration(path: str, model: str = "last", measurement: str = "last", *, store=None) -> MsgGenerator:
    """Write the calibrated ``model`` as a calibration file at ``path``, linked to ``measurement``.

    ``model`` is a fitted model's run uid or ``"last"``; the file is written by
    :func:`bluesky_offsets.model.export.write_calibration`.
    """
    import bluesky.plan_stubs as bps

    from bluesky_offsets.model.export import write_calibration
    store = _store(store)
    cal = calibrated_in_store(model, store)
    uid = resolve_run(store, measurement, "measurement")
    out = write_calibration(path, cal, measurement_uid=uid)
    log.info("calibration written to %s", out)
    yield from bps.null()
    return str(out)
