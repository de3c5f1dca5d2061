"""From a calibrated twin to a better beam: compute the settings, move there, measure.

:func:`optimize_beam` computes the motor settings for a target beam on the calibrated model
(:func:`bluesky_offsets.optimize.optimize_settings`: the differentiable twin with the fitted
offsets and effects), moves the motors there by differences from their readbacks, takes frames
and records the predicted and the measured beam in one run.  A target the motors cannot reach
within their limits is refused before anything moves.  ``closed_loop`` refits the model on the
calibration measurement and the new frames and corrects once more; where that second move
measures worse than the first, the motors go back to the first's settings (a third, measured step).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from concurrent.futures import Executor
from dataclasses import asdict, dataclass, field, is_dataclass, replace

import numpy as np
from bluesky.utils import MsgGenerator

from bluesky_offsets.errors import InputError
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.model.state import CalibratedState
from bluesky_offsets.optimize import (
    BeamOptimum,
    Constraints,
    Focus,
    OptimizeOptions,
    focus_from_profiles,
    measured_cost,
    moved_names,
    optimize_settings,
    target_from,
)
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable

from ._stubs import emit_rows, run_in_thread
from .measure import scan_configurations
from .motion import _limits, limit_margins, read_positions, resolve_motors

log = logging.getLogger(__name__)


@dataclass
class BeamStep:
    """One move: the settings computed, the beam predicted there and the beam measured."""

    optimum: BeamOptimum
    after: Focus
    uid: str | None
    note: str = ""     # why the move was made, where it is not the optimizer's


@dataclass
class BeamResult:
    """What :func:`optimize_beam` did.

    The beam measured before, each move (one, or two with the closed loop), the frames as a
    measurement (``measurement.uid``: the run).
    """

    before: Focus
    steps: list[BeamStep]
    measurement: Measurement
    model: CalibratedState
    frames: int = 1
    profiles: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    limits: tuple[np.ndarray, np.ndarray] | None = None     # the motors' (one step inside), twin coordinates
    constraints: Constraints | None = None
    options: OptimizeOptions | None = None

    @property
    def optimum(self) -> BeamOptimum:
        """The last move's computed settings and the beam predicted there."""
        return self.steps[-1].optimum

    @property
    def after(self) -> Focus:
        """The beam measured after the last move."""
        return self.steps[-1].after

    @property
    def uid(self) -> str | None:
        """The uid of the last move's measurement run."""
        return self.steps[-1].uid

    def lines(self) -> list[str]:
        """The before/after/predicted focus, one line each."""
        def f(x: Focus) -> str:
            noise = (f" (± {x.sigma_rms_x * 1e3:.1f}, ± {x.sigma_rms_y * 1e3:.1f} µm from the rays counted)"
                     if np.isfinite(x.sigma_rms_x) else "")
            return f"{x.rms_x * 1e3:7.1f} x {x.rms_y * 1e3:6.1f} µm rms, {x.intensity:.3f} of the source rays{noise}"
        out = [f"focus before     {f(self.before)}"]
        for k, s in enumerate(self.steps):
            tag = "" if len(self.steps) == 1 else f" ({k + 1})"
            o = s.optimum
            whence = f"{o.sampled} posterior states fitting the frames" if o.sampled else "the calibration"
            sig = (f" (± {o.sigma['x'] * 1e3:.1f}, ± {o.sigma['y'] * 1e3:.1f} µm from {whence})"
                   if all(np.isfinite(o.sigma[a]) for a in "xy") else "")
            p = o.predicted
            out.append(f"predicted{tag:5s}   {p.rms_x * 1e3:7.1f} x {p.rms_y * 1e3:6.1f} µm rms, {p.intensity:.3f} of "
                       f"the source rays{sig}{'' if o.trusted else '  NOT TRUSTED'}")
            out.append(f"focus after{tag:4s}  {f(s.after)}" + (f"  ({s.note})" if s.note else ""))
        return out


def motor_limits(motors: Mapping, table: ParameterTable = METRIXS) -> MsgGenerator[tuple[np.ndarray, np.ndarray]]:
    """Each motor's soft limits as (lo, hi) arrays in table order, within its parameter's travel.

    The limits are intersected with the parameter's travel (the twin's domain) and brought as far
    inside as the scans send a motor (:func:`plans.motion.limit_margins`); fixed parameters at
    their design values.
    """
    lo = np.array([p.limits[0] if p.motorized else p.reference for p in table], float)
    hi = np.array([p.limits[1] if p.motorized else p.reference for p in table], float)
    margins = yield from limit_margins(motors)
    for name, m in motors.items():
        lim = yield from _limits(m)
        i = table.index(name)
        if lim is not None:
            lo[i], hi[i] = max(lo[i], lim[0]), min(hi[i], lim[1])
        # inside: a controller rounds a target to its steps, and 14 - 1e-9 rounded to 1e-4 steps
        # reads back as 14.000000000000002, past the limit
        gap = margins.get(name, 0.0)
        if hi[i] - lo[i] > 2 * gap:
            lo[i], hi[i] = lo[i] + gap, hi[i] - gap
    return lo, hi


def _frames_focus(m: Measurement, rows: slice) -> tuple[Focus, np.ndarray, np.ndarray]:
    """The focus of the frames ``rows`` summed, at the camera's resolution where the detector gives it."""
    spec = m.profile_spec
    if spec is not None and m.profile_x is not None and m.profile_y is not None:
        px, py = m.profile_x[rows].mean(0), m.profile_y[rows].mean(0)
    else:
        spec, px, py = m.spec, m.hist_x[rows].mean(0), m.hist_y[rows].mean(0)
    n = len(m.configurations[rows])
    return focus_from_profiles(px, py, spec, n_rays=m.n_rays * n if m.n_rays else None), px, py


def _jsonable_target(target) -> dict:
    d = asdict(target) if is_dataclass(target) and not isinstance(target, type) else {}
    return {"name": target.name, **{k: v for k, v in d.items() if k != "name"}}


def _optimum_md(o: BeamOptimum, table: ParameterTable) -> dict:
    return {"settings": [float(v) for v in o.settings], "current": [float(v) for v in o.current],
            "moved": list(o.moved), "predicted": o.predicted.as_dict(), "predicted_before": o.predicted_before.as_dict(),
            "predicted_sigma": {a: float(v) for a, v in o.sigma.items()}, "trusted": bool(o.trusted),
            "flags": [f.text() for f in o.flags], "at_limit": list(o.at_limit), "cost": float(o.cost),
            "posterior_states": int(o.states), "sigma_samples": int(o.sampled),
            "starts": [{k: float(v) if isinstance(v, (int, float)) else v for k, v in s.items()} for s in o.starts]}


def _beam_rows(before: Focus, o: BeamOptimum, after: Focus) -> list[dict]:
    rows = []
    for what, f in (("before", before), ("predicted", o.predicted), ("after", after)):
        rows.append({"what": what, **f.as_dict(),
                     "sigma_rms_x": float(o.sigma["x"]) if what == "predicted" else 0.0,
                     "sigma_rms_y": float(o.sigma["y"]) if what == "predicted" else 0.0})
    return rows


def _move_and_measure(opt: BeamOptimum, beamline, chamber, frames: int, before_frames: bool, md: dict,
                      table: ParameterTable, before: Focus | None):
    """Frames at the current setting (``before_frames``), then at the optimum, where the motors stay.

    Returns the measurement and ``{"before": ..., "after": ...}``, each (focus, profile x, profile y)
    of its frames (no "before" without ``before_frames``: ``before`` is the focus to compare with).
    """
    configs = ([opt.current] * frames if before_frames else []) + [opt.settings] * frames
    read: dict = {}
    n_before = frames if before_frames else 0

    def finish(m: Measurement):
        if before_frames:
            read["before"] = _frames_focus(m, slice(0, n_before))
        read["after"] = _frames_focus(m, slice(n_before, None))
        b = read["before"][0] if before_frames else before
        assert b is not None  # passed where the frames before are not taken
        yield from emit_rows("beam", _beam_rows(b, opt, read["after"][0]))
        moves = [{"parameter": n, "from": float(opt.current[table.index(n)]), "to": float(opt.settings[table.index(n)]),
                  "unit": table[n].unit} for n in opt.moved]
        if moves:
            yield from emit_rows("settings", moves)

    m = yield from scan_configurations(np.asarray(configs), beamline, chamber, table=table, md=md,
                                       return_to_start=False, finish=finish)
    return m, read


def optimize_beam(target, model, beamline, chamber, *, constraints: Constraints | Mapping | None = None,
                  options: OptimizeOptions | Mapping | None = None, frames: int = 1, closed_loop: bool = False,
                  measurement: Measurement | None = None, refit=None, table: ParameterTable = METRIXS,
                  md: Mapping | None = None, executor: Executor | None = None) -> MsgGenerator[BeamResult]:
    """Compute the settings that give ``target`` on the calibrated ``model``, move there, measure.

    Parameters
    ----------
    target : Target, name or mapping
        :class:`~bluesky_offsets.optimize.SmallestFocus` (``"smallest_focus"``), ``FocusAt``,
        ``SpotSize``, ``MaxTransmission``, or a class of one's own
        (:mod:`bluesky_offsets.optimize.targets`).
    model : CalibratedState, ModelState or plans.diagnose.Analysis
        The calibrated twin: offsets, effects and the calibration's covariance (its uncertainty
        propagates into the prediction; a plain state gives a prediction marked untrusted).
    beamline, chamber : the motors (any of :mod:`plans.motion`'s forms) and the focus chamber.
    constraints : motors held (default: all but the refocusing mirrors E1/E2), travel, narrower
        limits, the transmission kept (:class:`~bluesky_offsets.optimize.Constraints`).
    options : :class:`~bluesky_offsets.optimize.OptimizeOptions` (rays, starts, iterations ...).
    frames : frames taken before and after the move (their profiles averaged).
    measurement : the calibration's frames, as analysed: the prediction's σ is read from states of
        the posterior that fit them (``options.posterior_samples``; without them, from the
        calibration's covariance).
    closed_loop : refit the model on ``measurement`` and the frames after the move (``refit``:
        FitOptions for it and for the posterior samples, default ``diagnosis.FIT`` on one draw of
        the model's rays; under the calibration's offsets' spread where it estimated one),
        optimize and move once more.
    executor : runs the optimizer's starts, the posterior samples and the refit's starts side by
        side (the same result).

    Returns
    -------
    BeamResult
        Before, predicted and measured after (each move), the frames (``measurement``, one run:
        ``uid``) with the settings and the prediction in its metadata and a ``beam`` stream.

    Raises
    ------
    bluesky_offsets.optimize.TargetUnreachable
        Before any motion, when the target needs a motor beyond its limits (named).
    bluesky_offsets.optimize.DarkStart
        When the model has no light at the current setting.
    """
    if int(frames) < 1:
        raise InputError(f"frames must be at least 1, got {frames!r}")
    if closed_loop and measurement is None:
        raise InputError("closed_loop needs the calibration measurement (measurement=...) to refit on")
    target = target_from(target)
    cons = constraints if isinstance(constraints, Constraints) else Constraints.from_mapping(constraints)
    o = OptimizeOptions.resolve(options)
    cal = CalibratedState.of(model)
    motors = resolve_motors(beamline, table)
    start = yield from read_positions(motors)
    limits = yield from motor_limits(motors, table)

    def compute(cal: CalibratedState, current: np.ndarray, frames_of: Measurement | None):
        samples = None
        if frames_of is not None and o.posterior_samples > 1:
            samples = yield from _posterior(cal, frames_of, o, refit, executor, table)
        return (yield from run_in_thread(
            lambda progress: optimize_settings(target, cal.state, current, limits=limits, constraints=cons,
                                               covariance=cal.covariance, names=cal.names, samples=samples,
                                               options=o, progress=progress, executor=executor, table=table),
            stream=None, desc=f"optimize the beam ({target.name}) on the calibrated twin"))

    opt = yield from compute(cal, table.from_mapping(start), measurement)
    base_md = {"plan_name": "optimize_beam", "purpose": "optimize the beam with the calibrated twin",
               "target": _jsonable_target(target), "constraints": {"hold": list(cons.hold),
                                                                   "keep_transmission": cons.keep_transmission,
                                                                   "min_transmission": cons.min_transmission},
               "model_uid": cal.uid, "model_label": cal.state.label, "frames": int(frames),
               "plan_args": {"target": target.name, "frames": int(frames), "closed_loop": bool(closed_loop)},
               **dict(md or {})}
    m, read = yield from _move_and_measure(opt, beamline, chamber, int(frames), True,
                                           {**base_md, "step": 1, **_optimum_md(opt, table)}, table, None)
    (before, *before_profiles), (after, *after_profiles) = read["before"], read["after"]
    profiles = {"before": tuple(before_profiles), "after": tuple(after_profiles), "predicted": opt.profiles}
    steps = [BeamStep(opt, after, m.uid)]
    result = BeamResult(before, steps, m, cal, int(frames), profiles, limits, cons, o)
    if closed_loop:
        assert measurement is not None  # refused above without one
        cal2, both = yield from _refit(cal, measurement, m, int(frames), refit, executor, table)
        opt2 = yield from compute(cal2, opt.settings, both)
        m2, read2 = yield from _move_and_measure(opt2, beamline, chamber, int(frames), False,
                                                 {**base_md, "step": 2, "previous_uid": m.uid,
                                                  **_optimum_md(opt2, table)}, table, after)
        after2, *after2_profiles = read2["after"]
        steps.append(BeamStep(opt2, after2, m2.uid))
        result.model = cal2
        result.profiles["after 2"] = tuple(after2_profiles)
        result.profiles["predicted 2"] = opt2.profiles
        yield from _back_if_worse(result, target, beamline, chamber, base_md, table)
    for line in result.lines():
        log.info(line)
    return result


def _refit_options(cal: CalibratedState, refit):
    """The fit options of the closed loop's refit and of the posterior samples: ``refit``'s, under the calibration's spread.

    Returns the options and the spread they hold where the calibration estimated one (else None).
    """
    from bluesky_offsets.model.diagnosis import FIT
    from bluesky_offsets.model.fit import FitOptions

    # one draw of the model's rays (FitOptions.ray_draws): this refit sets the next move, where
    # frames are measured and the prediction is checked, and each further draw costs a whole fit
    ro = FIT.replace(ray_draws=1) if refit is None else FitOptions.resolve(refit)
    if ro.estimate_spread and cal.prior_sigma is not None:
        # the calibration's spread: the frames after the move barely change it, estimating it costs two fits
        return ro.replace(prior_sigma=cal.prior_sigma, estimate_spread=False), cal.prior_sigma
    return ro, None


def _posterior(cal: CalibratedState, measurement: Measurement, o: OptimizeOptions, refit,
               executor: Executor | None, table: ParameterTable) -> MsgGenerator[list]:
    """``o.posterior_samples`` states of the calibration's posterior that fit ``measurement`` (its frames, as analysed)."""
    from bluesky_offsets.model.fit import engine_for, posterior_samples

    ro, _ = _refit_options(cal, refit)
    engine = engine_for(measurement, ro, table)
    return (yield from run_in_thread(
        lambda progress: posterior_samples(measurement, cal.state, engine, ro, n=o.posterior_samples, seed=o.seed,
                                           table=table, executor=executor),
        stream=None, desc=f"draw {o.posterior_samples} states of the posterior onto the calibration's frames"))


def _refit(cal: CalibratedState, measurement: Measurement, m: Measurement, frames: int, refit,
           executor: Executor | None, table: ParameterTable) -> MsgGenerator[tuple[CalibratedState, Measurement]]:
    """The calibration refitted on its ``measurement`` and the frames after the move (``m``'s last ``frames``).

    Returns it and the frames it was fitted on.
    """
    from bluesky_offsets.model.state import refine

    new = m.for_analysis(measurement.n_rays, table, resolution="camera" if measurement.spec.bins_x > 50
                         else "paper").subset(slice(frames, None))
    both = _joined(measurement, new)
    ro, spread = _refit_options(cal, refit)
    res = yield from run_in_thread(lambda progress: refine(both, cal.state, options=ro, progress=progress,
                                                           executor=executor, table=table),
                                   stream=None, desc="refit the model with the frames after the move")
    return CalibratedState(res.state, res.fit.covariance, tuple(res.fit.names), m.uid,
                           res.fit.prior_sigma if spread is None else spread), both


def _back_if_worse(result: BeamResult, target, beamline, chamber, md: dict,
                   table: ParameterTable) -> MsgGenerator[None]:
    """Where the second move measured worse than the first (``target``'s cost), back to the first's settings."""
    first, second = result.steps[0], result.steps[1]
    if not _worse(target, second.after, first.after, result.before):
        return
    opt = first.optimum
    back = replace(opt, current=second.optimum.settings, moved=moved_names(second.optimum.settings, opt.settings, table))
    m, read = yield from _move_and_measure(back, beamline, chamber, result.frames, False,
                                           {**md, "step": 3, "previous_uid": second.uid, "back_to_step": 1,
                                            **_optimum_md(back, table)}, table, second.after)
    after, *profiles = read["after"]
    result.steps.append(BeamStep(back, after, m.uid, note="back to the first move's settings: the second measured "
                                                          "worse"))
    result.profiles["after 3"] = tuple(profiles)
    if opt.profiles is not None:
        result.profiles["predicted 3"] = opt.profiles


def _worse(target, second: Focus, first: Focus, start: Focus) -> bool:
    """Whether the second move's measured beam meets ``target`` worse than the first's (False: no way to say)."""
    a, b = measured_cost(target, first, start), measured_cost(target, second, start)
    return a is not None and b is not None and b > a


def _joined(a: Measurement, b: Measurement) -> Measurement:
    """The calibration measurement as analysed and the new frames, binned alike, as one."""
    if a.spec != b.spec:
        raise InputError(f"the new frames are binned as {b.spec.fingerprint()}, the calibration measurement as "
                         f"{a.spec.fingerprint()}")
    return a.joined(b)
