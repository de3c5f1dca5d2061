"""The measurement designed for the offsets, as a Bluesky plan.

:func:`measure_designed` finds the beam (:func:`plans.find_beam`), then takes frames in batches,
each batch the most informative about the offsets of the settings the beamline can reach
(:mod:`bluesky_offsets.design`), the offsets refitted to every frame so far between batches,
until the frame budget is spent (or the offsets' predicted σ reach the target).  All designed
frames are events of one measurement run, each with its configuration and the chamber stage's
position; the run's ``design`` stream has one event per batch: the criterion before and after,
the predicted gain, the offsets' predicted σ, the candidates drawn and kept.  A pause resumes at
the next frame (every frame is a checkpoint).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from bluesky.utils import MsgGenerator

from bluesky_offsets.design import DesignOptions
from bluesky_offsets.design.sequence import DesignLoop
from bluesky_offsets.errors import InputError
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable

from ._stubs import Record, emit_rows, run_in_thread

if TYPE_CHECKING:
    from bluesky_offsets.offsets.beam_search import SearchResult

    from .diagnose import Comparison

log = logging.getLogger("bluesky_offsets.workflow")


@dataclass
class Designed:
    """What :func:`measure_designed` did.

    The beam search, the measurement, each batch's design record, the offsets' estimate and the
    design's precision after the last batch.
    """

    beam: SearchResult
    measurement: Measurement
    steps: list[dict] = field(default_factory=list)
    offsets: np.ndarray | None = None
    precision: np.ndarray | None = None

    @property
    def frames(self) -> int:
        """Frames taken in all: the beam search's and the designed ones."""
        return int(self.beam.frames) + self.measurement.n

    @property
    def uid(self) -> str | None:
        """The measurement run's uid (None where it has none)."""
        return self.measurement.uid


def measure_designed(beamline, chamber, *, options: DesignOptions | Mapping | None = None, fraction: float = 0.15,
                     table: ParameterTable = METRIXS, md: Mapping | None = None,
                     show: bool = True) -> MsgGenerator[Designed]:
    """Find the beam, then measure frames designed for what they tell about the offsets.

    Parameters
    ----------
    beamline, chamber : devices
        The motors (with the chamber's stage as ``chamber_stage`` where it has one: without it the
        screen stays where it is) and the focus chamber.
    options : DesignOptions or mapping
        The frame budget (the beam search's frames included), batch size, criterion ...
        (:class:`bluesky_offsets.design.DesignOptions`; an unknown key is refused).
    fraction : float
        The offsets the beam search assumes (normalized; :func:`plans.find_beam`).

    Returns
    -------
    Designed
        The beam search, the measurement (one run: ``uid``), each batch's design record, the
        offsets' last estimate and the design's precision.

    Raises :class:`plans.workflow.DarkBeamline` when the beam search ends dim.
    """
    from .measure import _optional_read, scan_configurations
    from .motion import resolve_stage
    from .search import bright_beam

    o = options if isinstance(options, DesignOptions) else DesignOptions.from_mapping(options)
    if resolve_stage(beamline) is None and o.screen:
        log.info("the beamline has no chamber stage: the design keeps the screen where it is")
        o = o.replace(screen=False)
    beam = yield from bright_beam(beamline, chamber, fraction=fraction, max_frames=max(1, o.frames - 2), table=table)
    photons = yield from _optional_read(chamber, "num_rays")
    loop = DesignLoop(o, beam.configuration, o.frames - beam.frames, int(photons or 10_000), table)
    log.info("designing %d frames (%s-optimal, batches of %d, %d candidates each) around the beam found in %d "
             "frames", loop.budget, o.criterion, o.batch, o.candidates, beam.frames)
    if loop.budget < o.batch:
        log.warning("the beam search took %d of the %d frames: %d are left to design, fewer than one batch; the "
                    "calibration will determine little (a larger frame budget gives the design more)",
                    beam.frames, o.frames, loop.budget)

    record = Record("design")

    def more(meas: Measurement):
        got = yield from run_in_thread(lambda progress: loop.step(meas, progress), stream=None,
                                       desc=f"design step {len(loop.steps) + 1}", show=show)
        if got is None:
            return None
        st, row = got
        yield from emit_rows("design", [row], record)
        log.info("  step %d: %d frames (criterion %s %.1f -> %.1f, %d of %d candidates keep the beam; offsets "
                 "determined so far %d, predicted after it %d)", st.step + 1, len(st.gains), o.criterion,
                 st.before, st.after, st.allowed, st.candidates, row["measured_determined"], st.n_determined)
        return st.configurations, st.screen

    screen = np.zeros((1, 3)) if o.screen else None
    m = yield from scan_configurations(beam.configuration[None], beamline, chamber, table=table, screen=screen,
                                       more=more, md={"purpose": "calibration measurement (designed)",
                                                      "design_options": asdict(o), "beam_search_frames": beam.frames,
                                                      "beam_search_uids": list(beam.uids),
                                                      "n_configurations": loop.budget, **dict(md or {})})
    return Designed(beam, m, loop.steps, loop.offsets, loop.precision)


# --------------------------------------------------------------------------- #
# validation frames
# --------------------------------------------------------------------------- #
VALIDATION_LIMIT = 1.3
"""χ²/dof on the validation frames above which the calibration may fail its validation ..."""
VALIDATION_P = 1e-3
"""... when, too, noise alone would reach that χ² less often than this (few frames, few dof)."""


def search_frames(frames: int) -> int:
    """The frames the beam search may take of a designed measurement's ``frames`` in all.

    All but two (:func:`measure_designed` keeps two for designed frames), and never fewer than the
    search's first three: the start, the slits open, the slits as they were.
    """
    return max(3, frames - 2)


def validation_limit(dof: float) -> float:
    """The χ²/dof a calibration must stay within on ``dof`` validation degrees of freedom.

    It is 1.3 (``VALIDATION_LIMIT``), or the χ²/dof noise alone exceeds with probability
    ``VALIDATION_P`` where that is higher.
    """
    from scipy.stats import chi2
    return max(VALIDATION_LIMIT, float(chi2.isf(VALIDATION_P, max(dof, 1.0)) / max(dof, 1.0)))


@dataclass
class Validation:
    """Frames no fit used, far from the fitted ones, and the calibrated model against them."""

    measurement: Measurement
    comparison: Comparison
    uid: str | None = None

    @property
    def chi2_reduced(self) -> float:
        """The model's χ²/dof on the validation frames, all frames together."""
        return float(self.comparison.misfit.chi2_reduced_total)

    @property
    def mse_over_noise(self) -> float:
        """The model's MSE on the validation frames over the MSE noise alone would give."""
        mf = self.comparison.misfit
        return float(mf.mse_total / max(mf.expected_mse_total, 1e-300))

    @property
    def limit(self) -> float:
        """The χ²/dof the validation must stay within (:func:`validation_limit` of its dof)."""
        return validation_limit(float(self.comparison.misfit.dof_total))

    @property
    def passed(self) -> bool:
        """Whether the χ²/dof stays within :attr:`limit`."""
        return self.chi2_reduced <= self.limit

    def summary(self) -> dict:
        """χ²/dof, MSE over noise, frames, run uid, limit and verdict, as a plain dict."""
        return {"chi2_reduced": self.chi2_reduced, "mse_over_noise": self.mse_over_noise,
                "configurations": self.measurement.n, "uid": self.uid, "passed": self.passed,
                "limit": self.limit}

    def line(self) -> str:
        """One line for the operator: frames, χ²/dof, MSE over noise and the verdict."""
        how = "passed" if self.passed else f"FAILED (above {self.limit:.2f}): the offsets reproduce the frames " \
                                           "they were fitted to, not the beamline elsewhere"
        return (f"validation on {self.measurement.n} frames no fit used: chi2/dof = {self.chi2_reduced:.2f}, "
                f"MSE/noise = {self.mse_over_noise:.2f}, {how}")


def stated_verdict(analysis, validation: Validation | None) -> str:
    """The analysis's verdict, and the validation's line where it failed: what a command states."""
    return analysis.verdict + ("" if validation is None or validation.passed else "; " + validation.line())


def validation_settings(model, fitted: Measurement, n: int, *, options: DesignOptions,
                        table: ParameterTable = METRIXS) -> tuple[np.ndarray, np.ndarray]:
    """``n`` settings (configurations, screen) far from the ``fitted`` frames' and from each other.

    Chosen by :func:`bluesky_offsets.design.far_from` among candidates on which the calibrated
    ``model`` puts at least twice the design's floor on the screen.
    """
    import torch

    from bluesky_offsets.design import candidate_settings, far_from
    from bluesky_offsets.model.state import CalibratedState
    from bluesky_offsets.offsets.beam_search import acceptance
    from bluesky_offsets.physics import effects as E
    from bluesky_offsets.physics.screen import add_overrides, tensor_overrides
    from bluesky_offsets.physics.beamline import torch_engine
    from bluesky_offsets.physics.engine import histograms
    from bluesky_offsets.physics.twin import HistogramSpec, Twin
    from plans import enough_rays

    state = CalibratedState.of(model).state
    bright = enough_rays(fitted.hist_x, fitted.hist_y)
    anchors = fitted.configurations[bright] if bright.any() else fitted.configurations
    acc = acceptance(Twin(torch_engine(table)), anchors[0], open_slits=False, table=table)
    rng = np.random.default_rng([options.seed, 2])  # the validation's own stream
    cfg, screen = candidate_settings(anchors, 4 * options.candidates, rng, acceptance=acc,
                                     options=options.replace(move=min(1.0, 2 * options.move)), table=table)
    twin_eff = {e: v for e, v in state.effects.items() if E.get(e).level == "twin"}
    ov = E.twin_overrides(twin_eff) if twin_eff else None
    stage = tensor_overrides(screen, len(cfg))
    engine = torch_engine(table, options={"common_rays": False})
    with torch.no_grad():
        beam = engine.beam(cfg + np.clip(state.offsets, -0.2, 0.2) * table.span,
                           add_overrides(ov, stage) if stage else ov, n_rays=1000, seed=options.seed)
    hx, hy = histograms(beam, HistogramSpec())
    allowed = np.minimum(hx.sum(1).numpy(), hy.sum(1).numpy()) >= 2 * options.floor  # on the screen both ways
    fitted_screen = fitted.screen if fitted.screen is not None else np.zeros((fitted.n, 3))
    idx = far_from((fitted.configurations, fitted_screen), (cfg, screen), n, allowed=allowed, table=table)
    return cfg[idx], screen[idx]


def measure_validation(beamline, chamber, model, fitted: Measurement, twin, *, n: int = 6,
                       options: DesignOptions | Mapping | None = None, table: ParameterTable = METRIXS,
                       md: Mapping | None = None, show: bool = True) -> MsgGenerator[Validation]:
    """Measure frames at ``n`` settings no fit used and compare the calibrated ``model`` with them.

    The settings are far from the ``fitted`` ones (other motor settings, other screen positions:
    :func:`validation_settings`), and the comparison is in the same run (its ``misfit`` and
    ``misfit_total`` streams): the test that the offsets are right, not only the frames.
    ``model``: a calibrated state or an analysis.
    """
    from bluesky_offsets.model.state import CalibratedState

    from .diagnose import compare_model
    from .measure import scan_configurations
    from .motion import resolve_stage

    o = options if isinstance(options, DesignOptions) else DesignOptions.from_mapping(options)
    if resolve_stage(beamline) is None:
        o = o.replace(screen=False)
    cal = CalibratedState.of(model)
    cfg, screen = yield from run_in_thread(
        lambda progress: validation_settings(cal, fitted, n, options=o, table=table), stream=None,
        desc="choose validation frames", show=show)
    if not len(cfg):
        raise InputError("no setting far from the fitted frames keeps the beam on the screen: no validation frames")
    box = {}

    def compare(meas: Measurement):
        box["c"] = yield from compare_model(meas.for_analysis(table=table), cal.state, twin, label="validation",
                                            open_run=False, show=show, table=table)

    m = yield from scan_configurations(cfg, beamline, chamber, table=table, screen=screen if o.screen else None,
                                       finish=compare, md={"purpose": "validation frames",
                                                           "plan_name": "measure_validation",
                                                           "calibrated_uid": cal.uid or "",
                                                           "measurement_uid": fitted.uid or "", **dict(md or {})})
    return Validation(m, box["c"], m.uid)


# --------------------------------------------------------------------------- #
# the posterior of the offsets, as a run
# --------------------------------------------------------------------------- #
def record_posterior(model, *, measurement_uid: str | None = None, table: ParameterTable = METRIXS,
                     md: Mapping | None = None) -> MsgGenerator[str | None]:
    """Record the calibrated ``model``'s posterior as a run (``plan_name`` "record_posterior"); its uid.

    The run's ``posterior`` stream has one event per offset and effect parameter: value ± σ in its
    unit, its class and the parameters it trades with
    (:class:`bluesky_offsets.model.posterior.Posterior`); its start document names the parameter
    table's version, the fit's run and the measurement.  None (no run) where the model has no
    covariance.
    """
    from bluesky_offsets.model.posterior import Posterior
    from bluesky_offsets.model.state import CalibratedState

    from ._stubs import in_run
    cal = CalibratedState.of(model)
    post = Posterior.of(cal, table)
    if post is None:
        return None
    estimates = [*post.offsets, *(e for d in post.effects.values() for e in d.values())]
    rows = [{"parameter": e.name, "value": e.value, "sigma": e.sigma, "unit": e.unit, "class": e.cls,
             "normalized": e.normalized, "normalized_sigma": e.normalized_sigma, "at_bound": e.at_bound,
             "partners_json": json.dumps([[n, c] for n, c in e.partners])} for e in estimates]
    _md = {"plan_name": "record_posterior", "purpose": "the calibration's posterior, per parameter",
           "parameter_table": table.name, "parameter_table_version": table.version, "model_uid": cal.uid or "",
           "measurement_uid": measurement_uid or "", "counts": post.counts(), **dict(md or {})}

    def body():
        yield from emit_rows("posterior", rows)

    _, uid = yield from in_run(body, _md, True)
    return uid
