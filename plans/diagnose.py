"""Model vs. measurement as Bluesky plans: compare, diagnose the missing effect, add it, refit.

Thin plans over :mod:`bluesky_offsets.model.state` and :mod:`bluesky_offsets.model.diagnosis`.  Each
opens one run (``open_run=False`` emits into a run that is already open) whose start
document names the measurement run (``measurement_uid``, and its ``truth_id`` in a
simulation); the heavy work runs in a worker thread, so the RunEngine stays responsive, and
its progress comes out live as a ``progress`` stream.

* :func:`compare_model` -> :class:`Comparison`: the twin at the model's compensated
  configurations vs. the measurement; streams ``misfit`` (one event per configuration:
  chi2, MSE, their noise expectation, model histograms, pulls, residual signature) and
  ``misfit_total``.
* :func:`refine_offsets` -> :class:`Refinement`: twin-anchored fit of the offsets (and the
  model's effects); streams ``progress``, ``offsets``, then a comparison.
* :func:`diagnose_effects` -> :class:`Ranking`: every candidate effect fitted with the
  offsets, ranked by its all-data gain (a BIC price per parameter) and checked on held-out
  configurations; streams ``ranking`` (one event per
  candidate, best first, predicted beside observed signature) and ``diagnosis``.
* :func:`add_effect_and_refit` -> :class:`Refit`: ``state.with_effect(name)`` refitted;
  streams ``progress``, ``effect`` (magnitude ± uncertainty), a comparison and
  ``error_history`` (all model versions so far).
* :func:`record_error_history`: the ``error_history`` stream alone.
* :func:`analyse_measurement` -> :class:`Analysis`: the whole analysis, one run per step.

:func:`load_results` reads any of these runs back by uid.  Names, dicts and lists go into
events as strings (``*_json`` keys, decoded by :func:`load_results`): the run store keeps
arrays of at most 16 numbers in its tables as text.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
from concurrent.futures import Executor
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from bluesky.utils import MsgGenerator

from bluesky_offsets import streams
from bluesky_offsets.model import diagnosis as D
from bluesky_offsets.physics import effects as E
from bluesky_offsets.model.diagnosis import Diagnosis, Version, diagnose
from bluesky_offsets.model.misfit import (
    Misfit,
    correlate_with_parameters,
    failing_regions,
    misfit,
    residual_signature,
)
from bluesky_offsets.model.fit import FitOptions
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.model.state import (
    CalibratedState,
    ModelState,
    RefineResult,
    refine,
    simulate_with_noise,
)
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable

from ._stubs import emit_rows, in_run, run_in_thread

MODEL_SEED = streams.MODEL_SEED  # the comparisons' model rays
"""Seed base of the fresh-ray model traces of :func:`compare_model` (as ``diagnosis.evaluate``)."""


# --------------------------------------------------------------------------- #
# results
# --------------------------------------------------------------------------- #
@dataclass
class Comparison:
    """One model version against the measurement (twin traced with fresh rays)."""

    label: str
    state: ModelState
    misfit: Misfit
    model_x: np.ndarray
    model_y: np.ndarray
    signature: dict[str, np.ndarray]       # model − measured moments per configuration ("x.centroid" ...)
    correlations: list[tuple[str, str, float]]
    failing: list[dict]
    model_rays: int
    effect_sigma: dict[str, dict[str, float]] = field(default_factory=dict)
    uid: str | None = None

    @property
    def within_noise(self) -> bool:
        """Whether the model's total misfit is within the measurement's noise."""
        return not self.misfit.total_beyond_noise()

    def version(self) -> Version:
        """The compared model as a version (label, state, misfit, effect σ) for the error history."""
        return Version(self.label, self.state, self.misfit, self.effect_sigma)

    def total_row(self) -> dict:
        """The comparison's totals as one event row: χ²/dof, χ², dof, MSE against noise, frames beyond noise."""
        mf = self.misfit
        return {"model": self.label, "chi2_reduced": mf.chi2_reduced_total, "chi2": mf.chi2_total,
                "dof": mf.dof_total, "mse": mf.mse_total, "expected_mse": mf.expected_mse_total,
                "mse_over_noise": mf.mse_total / max(mf.expected_mse_total, 1e-300),
                "beyond_noise": int(mf.beyond_noise().sum()), "within_noise": self.within_noise}


@dataclass
class Refinement:
    """What :func:`refine_offsets` produced: the fit's result, its comparison with the measurement and its run."""

    result: RefineResult
    comparison: Comparison
    uid: str | None = None

    @property
    def state(self) -> ModelState:
        """The fitted model state."""
        return self.result.state

    @property
    def calibrated(self) -> CalibratedState:
        """The fitted state with the fit's covariance."""
        f = self.result.fit
        return CalibratedState(self.state, f.covariance, tuple(f.names), self.uid, f.prior_sigma)


@dataclass
class Ranking:
    """What :func:`diagnose_effects` produced: the diagnosis (candidates ranked, verdict) and its run."""

    diagnosis: Diagnosis
    uid: str | None = None


@dataclass
class Refit:
    """What :func:`add_effect_and_refit` produced: the effect added, the refitted model, its σ, comparison and run."""

    effect: str
    state: ModelState
    sigma: dict[str, dict[str, float]]
    comparison: Comparison
    history: list[dict]
    versions: list[Version]
    uid: str | None = None
    covariance: np.ndarray | None = None     # the refit's (normalized offsets, then effect parameters)
    fit_names: list[str] | None = None       # its rows' names
    # within noise after the refit: how large each other candidate could be and still hide
    # (diagnosis.detection_limits at the refitted state); empty when beyond noise
    limits: dict[str, dict[str, float]] = field(default_factory=dict)
    prior_sigma: float | None = None         # the offsets' prior σ of the covariance (None: the table's)

    @property
    def calibrated(self) -> CalibratedState:
        """The refitted state with the refit's covariance (None when its run did not store one)."""
        names = None if self.fit_names is None else tuple(self.fit_names)
        return CalibratedState(self.state, self.covariance, names, self.uid, self.prior_sigma)

    def magnitude(self) -> dict[str, tuple[float, float]]:
        """``{parameter: (value, sigma)}`` of the added effect."""
        vals, sig = self.state.effects[self.effect], self.sigma.get(self.effect, {})
        return {k: (float(v), float(sig.get(k, float("nan")))) for k, v in vals.items()}


@dataclass
class Pruning:
    """What the backward step after effects were added produced (:func:`retest_effects`).

    Each added effect is tested with the others in, and the weakest dropped where it no longer earns
    its place (:func:`bluesky_offsets.model.diagnosis.retest_effects`).
    """

    tests: list[dict]                       # per effect: gain, price, kept (EffectTest.as_dict)
    dropped: str | None
    state: ModelState                       # the model after the step (its input when nothing was dropped)
    sigma: dict[str, dict[str, float]]      # of the refit without the dropped effect
    comparison: Comparison | None           # of that model (None when nothing was dropped)
    versions: list[Version]
    uid: str | None = None
    covariance: np.ndarray | None = None
    fit_names: list[str] | None = None
    prior_sigma: float | None = None

    @property
    def calibrated(self) -> CalibratedState:
        """The model after the step with its refit's covariance (None when the run stored none)."""
        names = None if self.fit_names is None else tuple(self.fit_names)
        return CalibratedState(self.state, self.covariance, names, self.uid, self.prior_sigma)


@dataclass
class Analysis:
    """Everything one analysis produced, with the uids of its runs."""

    measurement: Measurement
    comparisons: list[Comparison]
    rankings: list[Ranking] = field(default_factory=list)
    refinement: Refinement | None = None
    refits: list[Refit] = field(default_factory=list)
    pruning: Pruning | None = None          # the backward step (two effects added, or one within 2σ of none)
    uids: dict[str, str | None] = field(default_factory=dict)  # None: a step that recorded no run
    resumed: dict[str, str] = field(default_factory=dict)   # steps taken from earlier runs: step -> uid

    @property
    def ranking(self) -> Ranking | None:
        """The first diagnosis (of the offsets-only model)."""
        return self.rankings[0] if self.rankings else None

    @property
    def refit(self) -> Refit | None:
        """The first effect added."""
        return self.refits[0] if self.refits else None

    @property
    def dropped(self) -> str | None:
        """The added effect the backward step took out again (None: every one kept)."""
        return self.pruning.dropped if self.pruning is not None else None

    @property
    def _pruned(self) -> Pruning | None:
        """The backward step where it dropped an added effect (None: every effect kept)."""
        return self.pruning if self.pruning is not None and self.pruning.dropped is not None else None

    @property
    def retests(self) -> list[dict]:
        """The backward step's test of each added effect (empty: it did not run)."""
        return self.pruning.tests if self.pruning is not None else []

    def magnitudes(self) -> dict[str, dict[str, tuple[float, float]]]:
        """``{effect: {parameter: (value, sigma)}}`` of the effects the analysis ends with.

        In the order they were added, from the last fit (the pruning's, else the last refit's).
        """
        if not self.refits:
            return {}
        if (pruned := self._pruned) is not None:
            state, sigma = pruned.state, pruned.sigma
        else:
            state, sigma = self.refits[-1].state, self.refits[-1].sigma
        return {r.effect: {k: (float(v), float(sigma.get(r.effect, {}).get(k, float("nan"))))
                           for k, v in state.effects[r.effect].items()}
                for r in self.refits if r.effect in state.effects}

    @property
    def could_hide(self) -> dict[str, dict[str, float]]:
        """How large each candidate the final model does not hold could be and still hide behind the offsets.

        Only with the model the analysis ends with within noise
        (:func:`~bluesky_offsets.model.diagnosis.detection_limits`: of the last diagnosis when it
        found the model within noise, of the last refit when that reached the noise); else empty.
        """
        if self._ends_with_refit:
            return self.refit_limits
        last = self.rankings[-1].diagnosis if self.rankings else None
        return last.limits if last is not None and last.best is None else {}

    @property
    def _ends_with_refit(self) -> bool:
        """The analysis ends with its last refit's model (no backward step dropped an effect since)."""
        return bool(self.refits) and self.final is self.refits[-1].comparison

    @property
    def refit_limits(self) -> dict[str, dict[str, float]]:
        """The last refit's detection limits where the analysis ends with that refit's model; else empty.

        The refit holds them when it reached the noise.
        """
        return self.refits[-1].limits if self._ends_with_refit else {}

    @property
    def could_hide_json(self) -> dict[str, dict[str, float | None]]:
        """:attr:`could_hide` for a JSON file.

        A parameter the data do not see at all (an infinite limit) is null, so that strict JSON
        parsers read it.
        """
        return {e: {q: (v if np.isfinite(v) else None) for q, v in d.items()} for e, d in self.could_hide.items()}

    @property
    def could_hide_line(self) -> str:
        """:attr:`could_hide` as one line of text."""
        # linear limits: an effect the offsets compensate non-linearly can hide beyond them
        return "could hide within noise, behind the offsets (linearised; more can hide): " + \
            D.limits_text(self.could_hide)

    @property
    def verdict(self) -> str:
        """What the diagnoses found, in order: the effects added (and kept), or why none was."""
        # the diagnosis that added each effect: the candidates it did not tell from it
        rivals = {rk.diagnosis.best.name: rk.diagnosis.rivals for rk in self.rankings if rk.diagnosis.best is not None}
        found = [f"{e} ({', '.join(f'{k} = {v:.4g} ± {s:.2g}' for k, (v, s) in m.items())}"
                 + (", within 2 sigma of none)" if none_within(m) else ")") + D.rivals_text(rivals.get(e, ()))
                 for e, m in self.magnitudes().items()]
        last = self.rankings[-1].diagnosis if self.rankings else None
        pruned = self._pruned
        if not found and pruned is None:
            return last.verdict if last else "not diagnosed"
        tail = "" if last is None or last.best is not None else f"; then {last.verdict}"
        if pruned is not None:
            t = next(t for t in pruned.tests if t["effect"] == pruned.dropped)
            others = "with the others in it " if len(pruned.tests) > 1 else ""
            why = ("without it the model is within noise" if not t["beyond_noise_without"] else
                   f"the model fits better without it (χ² lower by {-t['gain']:.3g})" if t["gain"] <= 0 else
                   f"{others}it bought Δχ² = {t['gain']:.3g}, below its price {t['price']:.3g}")
            tail += f"; {pruned.dropped} was added before and dropped: {why}"
        if not found:  # the one effect added was dropped again
            head = ("no significant missing effect" if self.final.within_noise else
                    f"misfit beyond noise (chi2/dof = {self.final.misfit.chi2_reduced_total:.3g}) that no "
                    "candidate effect explains significantly")
            return head + tail
        if last is not None and last.best is not None and not self.final.within_noise:
            # the last diagnosis added an effect and the model still does not reach the noise: the
            # search ran out of rounds, not of effects, and the effects found may stand in for the
            # missing one at values that are not theirs
            n = len(self.rankings)
            tail += (f"; the model is still beyond noise after {n} diagnos{'is' if n == 1 else 'es'} (chi2/dof = "
                     f"{self.final.misfit.chi2_reduced_total:.3g}): an effect may be missing or another set "
                     "may fit, and the values above hold only for a complete model")
        return "missing effect" + ("s" if len(found) > 1 else "") + ": " + "; ".join(found) + tail

    @property
    def versions(self) -> list[Version]:
        """Each compared model version, in order: the error history."""
        return [c.version() for c in self.comparisons]

    @property
    def calibrated(self) -> CalibratedState:
        """The model the analysis ends with and the covariance of the fit that gave it.

        The covariance is the last refit's, else the offsets fit's: what
        :func:`plans.optimize.optimize_beam` optimizes on.
        """
        if (pruned := self._pruned) is not None:
            return pruned.calibrated
        if self.refits and self.refits[-1].covariance is not None:
            return self.refits[-1].calibrated
        if self.refinement is not None and not self.refits:
            return self.refinement.calibrated
        return CalibratedState(self.final.state, None, None, self.final.uid)

    @property
    def final(self) -> Comparison:
        """The last comparison: the model the analysis ends with against the measurement."""
        return self.comparisons[-1]


# --------------------------------------------------------------------------- #
# stubs: measurements, events, work in a thread
# --------------------------------------------------------------------------- #
def resolve_measurement(measurement, store=None, *, n_rays: int | None = None, resolution: str = "camera",
                        table: ParameterTable = METRIXS) -> tuple[Measurement, dict]:
    """The measurement as the fits read it, and the run metadata worth linking.

    The fits read it through :meth:`Measurement.for_analysis`.

    ``measurement`` is a :class:`bluesky_offsets.model.measurement.Measurement` or a measurement
    run's uid in ``store``; the camera-resolution profiles are taken where it has them
    (``resolution="camera"``), else (or with ``"paper"``) the 50 x 50 histograms.
    """
    from bluesky_offsets import store as S
    if isinstance(measurement, str):
        measurement = S.as_measurement(measurement, store)
    if not isinstance(measurement, Measurement):
        raise TypeError(f"expected a measurement or a run uid, got {type(measurement).__name__}")
    m = measurement.for_analysis(n_rays, table, resolution=resolution)
    md = {"measurement_uid": m.uid, "histogram": m.spec.fingerprint()}
    if m.truth_id:
        md["truth_id"] = m.truth_id
    return m, md


def _jsonable(obj):
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return obj.item()
    return obj


def _json(obj) -> str:
    return json.dumps(_jsonable(obj))


def _state_md(state: ModelState, table: ParameterTable) -> dict:
    return {"model_label": state.label, "model_offsets": [float(v) for v in state.offsets],
            "model_effects": _jsonable(state.effects), "parameter_table_version": table.version}


def _sig_key(prefix: str, key: str) -> str:
    return f"{prefix}_{key.replace('.', '_')}"


# --------------------------------------------------------------------------- #
# compare
# --------------------------------------------------------------------------- #
def _compare(meas: Measurement, state: ModelState, twin, label: str, model_rays: int, seed: int,
             effect_sigma: Mapping | None, table: ParameterTable) -> Comparison:
    hx, hy, noise = simulate_with_noise(twin, meas.configurations, state, model_rays,
                                        [seed + i for i in range(meas.n)], table, meas.screen)
    mf = misfit(meas.hist_x, meas.hist_y, hx, hy, meas.ray_budget, model_rays=model_rays, floor_x=meas.floor_x,
                floor_y=meas.floor_y, model_noise=noise)
    sig = residual_signature(meas.hist_x, meas.hist_y, hx, hy, twin.hist)
    corr = correlate_with_parameters(sig, meas.configurations, table.names)
    return Comparison(label, state, mf, hx, hy, sig.delta, corr, failing_regions(mf, twin.hist), model_rays,
                      {k: dict(v) for k, v in (effect_sigma or {}).items()})


def emit_comparison(c: Comparison) -> MsgGenerator[None]:
    """Streams ``misfit`` (per configuration) and ``misfit_total`` of a comparison."""
    mf = c.misfit
    beyond = mf.beyond_noise()
    rows = []
    for i in range(len(mf.chi2)):
        row = {"config_index": i, "chi2": float(mf.chi2[i]), "dof": float(mf.dof[i]),
               "chi2_reduced": float(mf.chi2_reduced[i]), "mse": float(mf.mse[i]),
               "expected_mse": float(mf.expected_mse[i]), "beyond_noise": bool(beyond[i]),
               "model_hist_x": c.model_x[i], "model_hist_y": c.model_y[i],
               "pulls_x": mf.pulls_x[i], "pulls_y": mf.pulls_y[i]}
        row.update({_sig_key("signature", k): float(v[i]) for k, v in c.signature.items()})
        rows.append(row)
    yield from emit_rows("misfit", rows)
    total = {"label": c.label, "chi2_total": mf.chi2_total, "dof_total": mf.dof_total,
             "chi2_reduced_total": mf.chi2_reduced_total, "chi2_expected": float(mf.dof_total),
             "chi2_expected_sigma": float(np.sqrt(2 * max(mf.dof_total, 1))), "mse_total": mf.mse_total,
             "expected_mse_total": mf.expected_mse_total,
             "mse_over_noise": mf.mse_total / max(mf.expected_mse_total, 1e-300),
             "within_noise": c.within_noise, "n_beyond_noise": int(beyond.sum()), "model_rays": c.model_rays,
             "model_offsets": np.asarray(c.state.offsets, float), "effects_json": _json(c.state.effects),
             "effect_sigma_json": _json(c.effect_sigma), "correlations_json": _json(c.correlations),
             "failing_json": _json(c.failing[:50])}
    total.update({_sig_key("signature", k): float(np.mean(v)) for k, v in c.signature.items()})
    yield from emit_rows("misfit_total", [total])


def compare_model(measurement, state: ModelState, twin, *, label: str | None = None, store=None,
                  model_rays: int | None = None, seed: int = MODEL_SEED, effect_sigma: Mapping | None = None,
                  open_run: bool = True, md: Mapping | None = None, show: bool = True,
                  table: ParameterTable = METRIXS) -> MsgGenerator[Comparison]:
    """Compare a model version with a measurement run.

    Parameters
    ----------
    measurement : Measurement or str
        The measurement, or its run uid in ``store``.
    state : ModelState
        The model version (offsets and effects).
    twin : Twin
        Traces the model at commanded configurations + offsets, with its effects.
    label : str, optional
        Version name in the error history (default ``state.label``).
    model_rays : int, optional
        Rays per model trace (default 4x the measurement's, a sharper model than the data).
    open_run : bool
        A run of its own (default) or events in the run already open.

    Returns
    -------
    Comparison
        Misfit per configuration and in total, with its noise expectation (chi2 = dof,
        MSE = ``expected_mse``), model histograms, residual signatures, their strongest
        correlations with the parameters and the failing regions; ``uid`` of the run.
    """
    meas, link = resolve_measurement(measurement, store, table=table)
    twin = twin.with_hist(meas.spec)  # the twin bins as the measurement does
    label = label or state.label
    rays = int(model_rays or 4 * meas.ray_budget)
    _md = {"plan_name": "compare_model", "purpose": "model vs. measurement", **link, **_state_md(state, table),
           "version_label": label, "n_configurations": meas.n, "n_rays": meas.ray_budget, "model_rays": rays,
           "model_seed": int(seed), **dict(md or {})}

    def body():
        c = yield from run_in_thread(lambda progress: _compare(meas, state, twin, label, rays, seed, effect_sigma,
                                                               table), stream=None,
                                     desc=f"compare '{label}' ({meas.n} traces)", show=show)
        yield from emit_comparison(c)
        return c

    c, uid = yield from in_run(body, _md, open_run)
    c.uid = uid
    return c


# --------------------------------------------------------------------------- #
# refine the offsets
# --------------------------------------------------------------------------- #
def _offsets_row(state: ModelState, table: ParameterTable) -> dict:
    row = {"offsets": np.asarray(state.offsets, float), "offsets_physical": np.asarray(state.offsets, float) * table.span}
    row.update({n.replace(".", "_"): float(v) for n, v in zip(table.names, state.offsets)})
    return row


def refine_offsets(measurement, state: ModelState, twin, forward_model=None, *, store=None,
                   options: FitOptions | Mapping | None = None, label: str = "+ offsets", open_run: bool = True,
                   md: Mapping | None = None, show: bool = True, also_from: Sequence[ModelState] = (),
                   executor: Executor | None = None, table: ParameterTable = METRIXS) -> MsgGenerator[Refinement]:
    """Fit the offsets (and the state's effects), starting from ``state``.

    Also from each of ``also_from``: the fit that ends lowest is kept.

    :func:`bluesky_offsets.model.state.refine`: the one fit engine (the differentiable twin, exact
    Jacobians; features, then profiles, then bins), options :class:`~bluesky_offsets.model.fit.FitOptions`
    (default :data:`bluesky_offsets.model.diagnosis.FIT`; an unknown key is an error).  Streams
    ``progress`` (every iteration) and ``offsets`` (values ± σ), then compares the result with
    the measurement through the twin (RAYX, fresh rays).  ``executor`` (a thread pool) runs the
    starts and the ray draws side by side: the same result on any number of threads
    (:func:`bluesky_offsets.model.fit.gather`).

    Returns
    -------
    Refinement
        The refined state and its comparison with the measurement (same run).
    """
    meas, link = resolve_measurement(measurement, store, table=table)
    twin = twin.with_hist(meas.spec)  # the twin bins as the measurement does
    opts = FitOptions.resolve(options, D.FIT)
    _md = {"plan_name": "refine_offsets", "purpose": "offsets through the differentiable twin", **link,
           **_state_md(state, table), "fit_options": _jsonable(asdict(opts)), "n_configurations": meas.n,
           "version_label": label, "also_from": [st.label for st in also_from],
           "jacobian": "exact (torch twin)", **dict(md or {})}

    def body():
        res: RefineResult = yield from run_in_thread(
            lambda progress: refine(meas, state, twin, options=opts, progress=progress, table=table,
                                    also_from=also_from, executor=executor),
            desc="fit the offsets through the differentiable twin", show=show)
        st = ModelState(res.state.offsets, res.state.effects, label)
        row = _offsets_row(st, table)
        # the kept start's last stage (a fit from several starts: model.fit.fit) on the first ray
        # draw, to where the history ends (with several ray draws: their mean)
        end = res.history[-1]
        last = [h for h in res.history if h["stage"] == end["stage"] and h.get("start") == end.get("start")
                and "ray_draw" not in h]
        row.update(chi2_reduced_start=float(last[0]["chi2_reduced"]), chi2_reduced_end=float(end["chi2_reduced"]),
                   offsets_sigma=np.asarray(res.offset_sigma, float),
                   accepted=int(sum(h["accepted"] for h in res.history if h["iteration"])),
                   effects_json=_json(st.effects), effect_sigma_json=_json(res.effect_sigma),
                   history_json=_json(res.history),
                   # the fit's end, for an analysis that resumes after this step (restore_refinement)
                   covariance=np.asarray(res.fit.covariance, float), fit_names_json=_json(res.fit.names),
                   prior_sigma=_prior_row(res.fit.prior_sigma),
                   fit_chi2=float(res.fit.chi2), fit_dof=float(res.fit.dof), fit_inflation=float(res.fit.inflation),
                   fit_stage=str(res.fit.stage), fit_traces=int(res.fit.n_traces))
        yield from emit_rows("offsets", [row])
        c = yield from compare_model(meas, st, twin, label=label, effect_sigma=res.effect_sigma, open_run=False,
                                     show=show, table=table)
        res.state = st
        return Refinement(res, c)

    r, uid = yield from in_run(body, _md, open_run)
    r.uid = r.comparison.uid = uid
    return r


# --------------------------------------------------------------------------- #
# diagnose
# --------------------------------------------------------------------------- #
def ranking_rows(d: Diagnosis) -> list[dict]:
    """One row per candidate of diagnosis ``d``, best first.

    Each row: score, its parts, fitted values and the predicted residual signature beside the
    observed one.
    """
    rows = []
    for rank, c in enumerate(d.candidates, 1):
        eff = E.get(c.name)
        row = {"rank": rank, "effect": c.name, "description": eff.description, "level": eff.level,
               "n_params": c.n_params, "score": float(c.score), "delta_chi2_heldout": float(c.delta_chi2_heldout),
               "delta_chi2_all": float(c.delta_chi2_all), "penalty": float(c.penalty),
               "dispersion": float(c.dispersion), "folds_improved": int(c.folds_improved),
               "folds_worse": int(c.folds_worse), "folds_total": int(c.folds_total),
               "significant": bool(c.significant), "absorbed": float(c.absorbed), "fitted": bool(c.fitted),
               "values_json": _json(c.values), "sigma_json": _json(c.sigma),
               "units_json": _json({p.name: p.unit for p in eff.parameters})}
        for k, v in d.observed_signature.items():
            row[_sig_key("observed", k)] = float(v)
            row[_sig_key("predicted", k)] = float(c.predicted_signature.get(k, float("nan")))
        rows.append(row)
    return rows


def diagnose_effects(measurement, state: ModelState, twin, forward_model=None, *, store=None,
                     candidates: Sequence[str] | None = None, folds: int = 4, seed: int = 0,
                     options: FitOptions | Mapping | None = None, fit_top: int | None = D.FIT_TOP,
                     executor: Executor | None = None, open_run: bool = True, md: Mapping | None = None,
                     show: bool = True, table: ParameterTable = METRIXS,
                     spread: float | None = None) -> MsgGenerator[Ranking]:
    """Which effect is missing: :func:`bluesky_offsets.model.diagnosis.diagnose` as a run.

    Every candidate fitted with the offsets from each of its starts (``fit_top``: screen every
    start first and fit only that many candidates; ``options``: the candidate fits', default
    :data:`bluesky_offsets.model.diagnosis.SCAN`; ``executor``: runs them side by side, the same
    result on any number of threads).  Streams ``progress`` (every fit's iterations),
    ``ranking`` (one event per candidate, best first) and ``diagnosis`` (verdict, base misfit
    and its noise expectation, observed signature).  ``spread``: the offsets' spread the offsets
    fit estimated, the prior of the detection limits of a base model within noise.
    """
    meas, link = resolve_measurement(measurement, store, table=table)
    twin = twin.with_hist(meas.spec)  # the twin bins as the measurement does
    names = list(candidates) if candidates else [n for n in E.EFFECTS if n not in state.effects]
    for n in names:
        E.get(n)  # unknown names fail before the run opens
    opts = FitOptions.resolve(options, D.SCAN)
    _md = {"plan_name": "diagnose_effects", "purpose": "which physical effect is missing", **link,
           **_state_md(state, table), "candidates": names, "folds": folds, "n_configurations": meas.n,
           "fit_options": _jsonable(asdict(opts)), "fit_top": fit_top or 0, "spread": spread,
           **dict(md or {})}

    def body():
        d: Diagnosis = yield from run_in_thread(
            lambda progress: diagnose(meas, state, twin, candidates=names, folds=folds, seed=seed, options=opts,
                                      fit_top=fit_top, progress=progress, executor=executor, table=table,
                                      spread=spread),
            desc=f"rank {len(names)} candidate effects", show=show)
        yield from emit_rows("ranking", ranking_rows(d))
        mf = d.base_misfit
        row = {"verdict": d.verdict, "best": d.best.name if d.best else "", "within_noise": bool(d.within_noise),
               "chi2_total": mf.chi2_total, "dof_total": mf.dof_total, "chi2_reduced_total": mf.chi2_reduced_total,
               "mse_total": mf.mse_total, "expected_mse_total": mf.expected_mse_total, "folds": d.folds,
               "n_traces": int(d.n_traces), "notes_json": _json(d.notes),
               "record_json": _json(D.diagnosis_record(d))}  # all of it, for an analysis that resumes
        row.update({_sig_key("observed", k): float(v) for k, v in d.observed_signature.items()})
        yield from emit_rows("diagnosis", [row])
        return Ranking(d)

    r, uid = yield from in_run(body, _md, open_run)
    r.uid = uid
    return r


# --------------------------------------------------------------------------- #
# add an effect, refit, error history
# --------------------------------------------------------------------------- #
def history_rows(versions: Sequence[Version]) -> list[dict]:
    """One ``error_history`` row per model version: χ²/dof, MSE against noise, effects and their σ (JSON)."""
    rows = []
    for i, v in enumerate(versions):
        mf = v.misfit
        rows.append({"version": i, "label": v.label, "chi2_reduced": mf.chi2_reduced_total, "chi2": mf.chi2_total,
                     "dof": mf.dof_total, "mse": mf.mse_total, "expected_mse": mf.expected_mse_total,
                     "mse_over_noise": mf.mse_total / max(mf.expected_mse_total, 1e-300),
                     "within_noise": bool(not mf.total_beyond_noise()), "effects_json": _json(v.state.effects),
                     "effect_sigma_json": _json(v.effect_sigma)})
    return rows


def record_error_history(versions: Sequence[Version], *, measurement_uid: str | None = None, open_run: bool = False,
                         md: Mapping | None = None) -> MsgGenerator[None]:
    """The ``error_history`` stream: misfit of every model version (base, + offsets, + effect ...)."""
    def body():
        yield from emit_rows("error_history", history_rows(versions))

    yield from in_run(body, {"plan_name": "error_history", "measurement_uid": measurement_uid,
                              "versions": [v.label for v in versions], **dict(md or {})}, open_run)


def add_effect_and_refit(measurement, state: ModelState, effect: str, twin, forward_model=None, *, store=None,
                         values: Mapping[str, float] | None = None, history: Sequence[Version] = (),
                         options: FitOptions | Mapping | None = None, label: str | None = None,
                         open_run: bool = True, md: Mapping | None = None, show: bool = True,
                         candidates: Sequence[str] | None = None, limits_options: FitOptions | Mapping | None = None,
                         also_from: Sequence[ModelState] = (), executor: Executor | None = None,
                         table: ParameterTable = METRIXS) -> MsgGenerator[Refit]:
    """``state.with_effect(effect, values)``, offsets and effect refitted with the one fit engine.

    ``values`` start the effect (e.g. the diagnosis's fitted values; default 0 = absent);
    ``also_from`` more starts, each given the effect at ``values`` (the fit that ends lowest on
    fresh rays is kept: :func:`bluesky_offsets.model.diagnosis.add_effect_result`);
    ``options`` those of the fit (default :data:`bluesky_offsets.model.diagnosis.FIT`).  Streams
    ``progress`` (refit iterations), ``effect`` (fitted magnitude ± uncertainty per parameter),
    the new version's comparison (``misfit``, ``misfit_total``) and ``error_history``
    (``history`` + the new version).  ``executor`` runs the fit's ray draws side by side.
    When the refitted model is within noise, ``limits`` (one row per candidate parameter): how
    large each of ``candidates`` (default: every registered effect the model does not hold)
    could be and still hide behind the offsets
    (:func:`bluesky_offsets.model.diagnosis.detection_limits`, ``limits_options`` default
    :data:`bluesky_offsets.model.diagnosis.SCAN`): what the verdict cannot exclude.
    """
    meas, link = resolve_measurement(measurement, store, table=table)
    twin = twin.with_hist(meas.spec)  # the twin bins as the measurement does
    eff = E.get(effect)
    start_values = eff.values(values)
    label = label or f"+ {effect}"
    opts = FitOptions.resolve(options, D.FIT)
    _md = {"plan_name": "add_effect_and_refit", "purpose": "add the missing effect and refit", **link,
           **_state_md(state, table), "effect": effect, "effect_parameters": [p.name for p in eff.parameters],
           "effect_start": start_values, "fit_options": _jsonable(asdict(opts)), "n_configurations": meas.n,
           "version_label": label, "versions": [v.label for v in history] + [label],
           "also_from": [st.label for st in also_from], **dict(md or {})}

    def body():
        def work(progress):
            res = D.add_effect_result(meas, state, effect, twin, values=start_values, options=opts,
                                      progress=progress, also_from=also_from, executor=executor, table=table)
            return res.state, res.effect_sigma, res.fit

        st, sig, fit = yield from run_in_thread(work, desc=f"add {effect} and refit", show=show)
        st = ModelState(st.offsets, st.effects, label)
        row = {"effect": effect, "values_json": _json(st.effects[effect]), "sigma_json": _json(sig.get(effect, {})),
               "units_json": _json({p.name: p.unit for p in eff.parameters}),
               # the fit's covariance: what an optimization on this model propagates (restore_refit)
               "covariance": np.asarray(fit.covariance, float), "fit_names_json": _json(fit.names),
               "prior_sigma": _prior_row(fit.prior_sigma)}
        for p in eff.parameters:
            row[p.name] = float(st.effects[effect][p.name])
            row[f"{p.name}_sigma"] = float(sig.get(effect, {}).get(p.name, float("nan")))
        row.update(_offsets_row(st, table))
        yield from emit_rows("effect", [row])
        c = yield from compare_model(meas, st, twin, label=label, effect_sigma=sig, open_run=False, show=show,
                                     table=table)
        versions = [*history, c.version()]
        yield from record_error_history(versions)
        limits: dict[str, dict[str, float]] = {}
        if c.within_noise:
            # what could still hide: a model within noise can still miss an effect the offsets absorb
            names = [n for n in (candidates or E.EFFECTS) if n not in st.effects]
            lo = FitOptions.resolve(limits_options, D.SCAN)
            if fit.prior_sigma is not None:  # offsets of the spread the refit found hide less
                lo = lo.replace(prior_sigma=fit.prior_sigma)
            limits = yield from run_in_thread(
                lambda progress: D.detection_limits(meas, st, D.engine_for(meas, lo, table), lo, names,
                                                    c.misfit.noise_margin(), executor=executor, table=table),
                stream=None, desc="what could still hide", show=show)
            yield from emit_rows("limits", [{"effect": e, "parameter": q, "limit": float(v)}
                                            for e, d in limits.items() for q, v in d.items()])
        # the fit's own record (its ray draws in order; the progress events came as they ran)
        return Refit(effect, st, sig, c, [dict(h) for h in fit.history], versions,
                     covariance=np.asarray(fit.covariance, float),
                     fit_names=list(fit.names), limits=limits, prior_sigma=fit.prior_sigma)

    r, uid = yield from in_run(body, _md, open_run)
    r.uid = r.comparison.uid = uid
    return r


def retest_effects(measurement, state: ModelState, twin, *, store=None, names: Sequence[str] | None = None,
                   history: Sequence[Version] = (), options: FitOptions | Mapping | None = None, seed: int = 0,
                   open_run: bool = True, md: Mapping | None = None, show: bool = True,
                   executor: Executor | None = None, table: ParameterTable = METRIXS) -> MsgGenerator[Pruning]:
    """The backward step: each effect tested with the others in, the weakest dropped if it no longer earns its place.

    The effects tested are ``names`` (default: every effect of ``state``).

    :func:`bluesky_offsets.model.diagnosis.retest_effects` (the rest refitted without each,
    ``options`` default :data:`bluesky_offsets.model.diagnosis.FIT`).  Streams
    ``progress``, ``retest`` (one row per effect: its gain, its price, kept) and, when one is
    dropped, ``effect`` (the refit's covariance), the new version's comparison and
    ``error_history`` (``history`` + the new version).
    """
    meas, link = resolve_measurement(measurement, store, table=table)
    twin = twin.with_hist(meas.spec)  # the twin bins as the measurement does
    names = list(state.effects if names is None else names)
    opts = FitOptions.resolve(options, D.FIT)
    _md = {"plan_name": "retest_effects", "purpose": "does each added effect still earn its place", **link,
           **_state_md(state, table), "effects": names, "fit_options": _jsonable(asdict(opts)),
           "versions": [v.label for v in history], **dict(md or {})}

    def body():
        tests = yield from run_in_thread(
            lambda progress: D.retest_effects(meas, state, names, options=opts, seed=seed, progress=progress,
                                              executor=executor, table=table),
            desc=f"retest {len(names)} added effects", show=show)
        w = D.weakest(tests)
        yield from emit_rows("retest", [{**t.as_dict(), "dropped": t is w} for t in tests])
        if w is None:
            return Pruning([t.as_dict() for t in tests], None, state, {}, None, list(history))
        f = w.without
        sig = f.effect_sigma()
        st = ModelState(f.state.offsets, f.state.effects, f"- {w.effect}")
        yield from emit_rows("effect", [{"effect": w.effect, "covariance": np.asarray(f.covariance, float),
                                         "fit_names_json": _json(f.names), "prior_sigma": _prior_row(f.prior_sigma),
                                         **_offsets_row(st, table)}])
        c = yield from compare_model(meas, st, twin, label=st.label, effect_sigma=sig, open_run=False, show=show,
                                     table=table)
        versions = [*history, c.version()]
        yield from record_error_history(versions)
        return Pruning([t.as_dict() for t in tests], w.effect, st, sig, c, versions,
                       covariance=np.asarray(f.covariance, float), fit_names=list(f.names), prior_sigma=f.prior_sigma)

    r, uid = yield from in_run(body, _md, open_run)
    r.uid = uid
    if r.comparison is not None:
        r.comparison.uid = uid
    return r


# --------------------------------------------------------------------------- #
# results back from their runs: what an interrupted analysis resumes from
# --------------------------------------------------------------------------- #
def _prior_row(sigma: float | None) -> float:
    """A fit's offsets' prior σ as a row's number (NaN: none)."""
    return math.nan if sigma is None else float(sigma)


def _prior_from(row: Mapping) -> float | None:
    """The offsets' prior σ a row stored (None: the table's, or a run from before it was stored)."""
    v = row.get("prior_sigma")
    return None if v is None or not math.isfinite(float(v)) else float(v)


def _arr(rows: Sequence[Mapping], key: str) -> np.ndarray:
    return np.asarray([r[key] for r in rows], dtype=float)


def restore_comparison(res: Mapping, uid: str | None = None) -> Comparison:
    """The :class:`Comparison` a ``compare_model`` run (or a run holding one) stored, as it was."""
    rows, (total,) = res["misfit"], res["misfit_total"]
    mf = Misfit(_arr(rows, "chi2"), _arr(rows, "dof"), _arr(rows, "mse"), _arr(rows, "expected_mse"),
                _arr(rows, "pulls_x"), _arr(rows, "pulls_y"))
    # "signature_x_centroid" holds the signature "x.centroid"
    keys = [k for k in rows[0] if k.startswith("signature_")]
    signature = {k[len("signature_"):].replace("_", ".", 1): _arr(rows, k) for k in keys}
    state = ModelState(np.asarray(total["model_offsets"], float), total["effects"], str(total["label"]))
    corr = [tuple(c) for c in total["correlations"]]
    return Comparison(str(total["label"]), state, mf, _arr(rows, "model_hist_x"), _arr(rows, "model_hist_y"), signature,
                      corr, list(total["failing"]), int(total["model_rays"]), dict(total["effect_sigma"]), uid)


def restore_refinement(res: Mapping, uid: str | None = None) -> Refinement:
    """The :class:`Refinement` of a ``refine_offsets`` run: the fit's end and its comparison."""
    from bluesky_offsets.model.fit import FitResult
    (row,) = res["offsets"]
    c = restore_comparison(res, uid)
    fit = FitResult(c.state, list(row["history"]), np.asarray(row["covariance"], float), list(row["fit_names"]),
                    float(row["fit_chi2"]), float(row["fit_dof"]), float(row["fit_inflation"]),
                    int(row["fit_traces"]), stage=str(row["fit_stage"]), prior_sigma=_prior_from(row))
    return Refinement(RefineResult(c.state, dict(row["effect_sigma"]), list(row["history"]), fit), c, uid)


def restore_ranking(res: Mapping, uid: str | None = None) -> Ranking:
    """The :class:`Ranking` of a ``diagnose_effects`` run: every candidate as it was fitted."""
    (row,) = res["diagnosis"]
    return Ranking(D.diagnosis_from(row["record"]), uid)


def restore_refit(res: Mapping, history: Sequence[Version], uid: str | None = None) -> Refit:
    """The :class:`Refit` of an ``add_effect_and_refit`` run, after the versions ``history``."""
    c = restore_comparison(res, uid)
    steps = [{k: v for k, v in r.items() if k not in ("time", "seq_num")} for r in res.get("progress", [])]
    row = (res.get("effect") or [{}])[0]
    cov = row.get("covariance")
    limits: dict[str, dict[str, float]] = {}
    for r in res.get("limits", []):
        limits.setdefault(str(r["effect"]), {})[str(r["parameter"])] = float(r["limit"])
    return Refit(str(res["start"]["effect"]), c.state, dict(c.effect_sigma), c, steps, [*history, c.version()], uid,
                 None if cov is None else np.asarray(cov, float), row.get("fit_names"), limits, _prior_from(row))


def restore_pruning(res: Mapping, history: Sequence[Version], uid: str | None = None) -> Pruning:
    """The :class:`Pruning` of a ``retest_effects`` run, after the versions ``history``."""
    tests = [{k: v for k, v in r.items() if k not in ("time", "seq_num", "dropped")} for r in res["retest"]]
    dropped = next((str(r["effect"]) for r in res["retest"] if r["dropped"]), None)
    if dropped is None:
        start = res["start"]
        state = ModelState(np.asarray(start["model_offsets"], float), start["model_effects"], start["model_label"])
        return Pruning(tests, None, state, {}, None, list(history), uid)
    c = restore_comparison(res, uid)
    row = res["effect"][0]
    return Pruning(tests, dropped, c.state, dict(c.effect_sigma), c, [*history, c.version()], uid,
                   np.asarray(row["covariance"], float), row.get("fit_names"), _prior_from(row))


def analysis_key(meas: Measurement, settings: Mapping) -> str:
    """The key of an analysis: a hash of what makes two analyses the same.

    That is the measurement as fitted (its uid, configurations and histograms) and every setting
    that changes a result.  Stored with each step's run.
    """
    import hashlib
    h = hashlib.sha256()
    h.update(json.dumps(_jsonable({"uid": meas.uid, **settings}), sort_keys=True, default=str).encode())
    for a in (meas.configurations, meas.hist_x, meas.hist_y):
        h.update(np.ascontiguousarray(a, dtype=float).tobytes())
    if meas.screen is not None and np.any(meas.screen):  # where the screen stood (keys of older runs unchanged)
        h.update(np.ascontiguousarray(meas.screen, dtype=float).tobytes())
    return h.hexdigest()[:20]


def completed_steps(store, key: str) -> dict[str, str]:
    """``{step: uid}`` of the runs of analysis ``key`` in ``store`` that ended successfully.

    The latest run of each step.
    """
    from tiled.queries import Eq
    runs = store.client.search(Eq("start.analysis_key", key))
    done = {}
    for uid in runs.keys():
        md = runs[uid].metadata
        if (md.get("stop") or {}).get("exit_status") == "success":
            done[md["start"]["analysis_step"]] = uid
    return done


# --------------------------------------------------------------------------- #
# the whole analysis
# --------------------------------------------------------------------------- #
# long: a 62-line numpy docstring over the analysis's resumable steps (97 lines), read in order
def analyse_measurement(measurement, twin, forward_model=None, *, store=None,
                        starts: ModelState | Sequence[ModelState] | None = None, refine: bool = True,
                        candidates: Sequence[str] | None = None, add_best: bool = True, rounds: int = D.ROUNDS,
                        fit_options: FitOptions | Mapping | None = None,
                        scan_options: FitOptions | Mapping | None = None, fit_top: int | None = D.FIT_TOP,
                        folds: int = 4, seed: int = 0, refit_from_twin: bool = D.REFIT_FROM_TWIN, resume: bool = False,
                        md: Mapping | None = None, show: bool = True, resolution: str = "camera",
                        executor: Executor | None = None, table: ParameterTable = METRIXS) -> MsgGenerator[Analysis]:
    """Compare, fit the offsets, diagnose, add the winning effect and refit, diagnose again — one run each.

    Parameters
    ----------
    measurement : Measurement or str
        The measurement or its run uid in ``store``.
    starts : ModelState or sequence of ModelState, optional
        Model versions to compare first (e.g. the bare twin and the surrogate finder's
        offsets); the offsets are fitted from each in one run, and the fit that ends lowest is
        kept (:func:`bluesky_offsets.model.fit.fit`, ``also_from``).  Default: the bare twin.
    refine : bool
        Fit the offsets before the diagnosis (False: diagnose the best start as it is).
    candidates : sequence of str, optional
        Effects to rank (default: all registered).
    add_best : bool
        Add the best significant candidate, starting from the values the diagnosis fitted,
        and refit (nothing is added when no candidate is significant).
    rounds : int
        Diagnoses at most (default :data:`bluesky_offsets.model.diagnosis.ROUNDS`): after an
        effect is added the model is diagnosed again, until it is within noise, no candidate is
        significant, or ``rounds`` diagnoses ran (two hidden effects are found one after the
        other).  With two or more effects added, each is then tested with the others in and the
        weakest dropped where it no longer earns its place (:func:`retest_effects`).
    fit_options, scan_options : FitOptions or mapping, optional
        Of the offsets fit and the refits (default :data:`bluesky_offsets.model.diagnosis.FIT`), and
        of the diagnosis's candidate fits (:data:`bluesky_offsets.model.diagnosis.SCAN`).
    fit_top : int or None
        Screen every start first and fit only this many candidates to convergence (default
        None: every start fitted; :func:`bluesky_offsets.model.diagnosis.diagnose`).
    resolution : {"camera", "paper"}
        Of a stored run: the camera-resolution profiles where it has them, or the 50 x 50
        histograms.
    refit_from_twin : bool
        Refit an added effect also from the bare twin's offsets (the effect at the diagnosis's
        values), beside where the diagnosis ended, and keep the fit that ends lowest on fresh
        rays (default :data:`bluesky_offsets.model.diagnosis.REFIT_FROM_TWIN`).
    resume : bool
        Take every step that an earlier run of the *same* analysis (same measurement, starts and
        settings: :func:`analysis_key`) completed from the store (``store``, default
        :func:`bluesky_offsets.store.shared_store`) instead of computing it again; the first step
        it did not complete, and all after it, run.  After Ctrl-C, ``RE.abort()`` or a crash.
    executor : concurrent.futures.Executor, optional
        Runs independent fits side by side (the starts, the candidates, the ray draws): a thread
        pool (:func:`bluesky_offsets.model.cluster.analysis_executor`).  The result is the same
        with any number of threads, or none (:func:`bluesky_offsets.model.fit.gather`); it is not
        part of the analysis's key.

    Returns
    -------
    Analysis
        The comparisons of every model version (the error history), the rankings, the
        refits, the uids of all runs (``analysis.uids``) and the steps taken from earlier
        runs (``analysis.resumed``: step -> uid).
    """
    meas, link = resolve_measurement(measurement, store, resolution=resolution, table=table)
    twin = twin.with_hist(meas.spec)  # the twin bins as the measurement does
    if starts is None:
        starts = [ModelState(np.zeros(len(table)))]
    elif isinstance(starts, ModelState):
        starts = [starts]
    fopts = FitOptions.resolve(fit_options, D.FIT)
    sopts = FitOptions.resolve(scan_options, D.SCAN)
    key = analysis_key(meas, {
        "starts": [(s.label, s.offsets, s.effects) for s in starts], "refine": refine and "from every start",
        "candidates": candidates,
        "add_best": add_best, "rounds": rounds, "fit": asdict(fopts), "scan": asdict(sopts), "fit_top": fit_top,
        "folds": folds, "seed": seed, "spec": meas.spec.fingerprint(), "n_rays": meas.n_rays,
        **({"refit_from_twin": True} if refit_from_twin else {})})
    md = {**link, **dict(md or {}), "analysis_key": key}
    done: dict[str, str] = {}
    if resume:
        from bluesky_offsets.store import shared_store
        store = store if store is not None and not isinstance(store, str) else shared_store(store)
        done = completed_steps(store, key)
    out = Analysis(meas, [])
    fresh = False  # once a step is computed, the ones after it are too

    def step(name: str, run, restore):
        """``run(md)`` as a plan, or the result of this step's earlier run (``restore``)."""
        nonlocal fresh
        if not fresh and name in done:
            res = restore(load_results(store, done[name]), done[name])
            out.resumed[name] = done[name]
            logging.getLogger("bluesky_offsets.workflow").info("resumed: %s from run %s", name, done[name])
            return res
        fresh = True
        return (yield from run({**md, "analysis_step": name}))

    for k, st in enumerate(starts):
        name = "compare" if k == 0 else f"compare_{k}"
        c = yield from step(name, lambda m, st=st: compare_model(meas, st, twin, md=m, show=show, table=table),
                            restore_comparison)
        out.comparisons.append(c)
        out.uids[name] = c.uid
    order = sorted(out.comparisons, key=lambda c: c.misfit.chi2_reduced_total)
    current = order[0].state
    if refine:
        # The offsets are fitted from every start and the fit that ends lowest is kept.  Why: where
        # the surrogate cannot represent the beamline (a hidden defocus) its finder's offsets lie
        # far off (at the box's edge) while their χ² is a little lower, and the fit ends near where
        # it starts.
        r = yield from step("refine_offsets", lambda m: refine_offsets(
            meas, current, twin, options=fopts, md={**m, "start_label": order[0].label}, show=show,
            also_from=[c.state for c in order[1:]], executor=executor, table=table), restore_refinement)
        out.uids["refine_offsets"] = r.uid
        out.refinement = r
        out.comparisons.append(r.comparison)
        current = r.state
    spread = out.refinement.result.fit.prior_sigma if out.refinement is not None else None
    for round_ in range(max(1, rounds)):
        suffix = "" if round_ == 0 else f"_{round_ + 1}"
        rk = yield from step("diagnose" + suffix, lambda m: diagnose_effects(
            meas, current, twin, candidates=candidates, folds=folds, seed=seed + round_, options=sopts,
            fit_top=fit_top, md=m, show=show, executor=executor, table=table, spread=spread), restore_ranking)
        out.rankings.append(rk)
        out.uids["diagnose" + suffix] = rk.uid
        best = rk.diagnosis.best
        if not add_best or best is None:
            break
        # start where the diagnosis compensated the effect with the offsets, and from the bare
        # twin's offsets (the model's other effects as that fit left them): the offsets-only fit
        # has absorbed what it could of the effect, and a fit ends near where it starts
        start = best.refit_start(current.label)
        history = out.versions
        rf = yield from step("add_effect" + suffix, lambda m: add_effect_and_refit(
            meas, start, best.name, twin, values=best.values, history=history,
            options=fopts.replace(seed=fopts.seed + 1 + round_), md=m, show=show, candidates=candidates,
            limits_options=sopts.replace(seed=streams.stream(seed + round_, "diagnosis.fits")),
            also_from=[best.twin_start()] if refit_from_twin else (), executor=executor, table=table),
            lambda res, uid: restore_refit(res, history, uid))
        out.refits.append(rf)
        out.comparisons.append(rf.comparison)
        out.uids["add_effect" + suffix] = rf.uid
        current = rf.state
        if rf.comparison.within_noise:
            break
    if len(out.refits) >= 2 or (out.refits and none_within(out.refits[0].magnitude())):
        # the backward step: an effect added early may have stood in for one added later, and
        # one alone within 2σ of none may owe its gain to its refit's search, not to itself
        history = out.versions
        pr = yield from step("retest_effects", lambda m: retest_effects(
            meas, current, twin, names=[r.effect for r in out.refits], history=history,
            options=fopts.replace(seed=fopts.seed + 1 + len(out.refits)), seed=seed, md=m, show=show,
            executor=executor, table=table),
            lambda res, uid: restore_pruning(res, history, uid))
        out.pruning = pr
        out.uids["retest_effects"] = pr.uid
        if pr.comparison is not None:
            out.comparisons.append(pr.comparison)
    if not out.refits:
        uid = yield from _history_run(out.versions, {**md, "analysis_step": "error_history"})
        out.uids["error_history"] = uid
    return out


def none_within(magnitude: Mapping[str, tuple[float, float]]) -> bool:
    """Whether every parameter of an effect's ``{parameter: (value, sigma)}`` is within 2σ of its absence (zero)."""
    return all(np.isfinite(s) and abs(v) <= 2 * s for v, s in magnitude.values())


def _history_run(versions, md) -> MsgGenerator[str | None]:
    def body():
        yield from record_error_history(versions)
    _, uid = yield from in_run(body, {"plan_name": "error_history", "versions": [v.label for v in versions], **md},
                                True)
    return uid


# --------------------------------------------------------------------------- #
# reading results back
# --------------------------------------------------------------------------- #
def load_results(store, uid: str) -> dict:
    """A stored analysis run as plain Python: ``{"start": ..., "stop": ..., stream: [row, ...]}``.

    ``*_json`` fields are decoded (``values_json`` -> ``values``); arrays come back as numpy.
    """
    run = store[uid]
    out: dict[str, Any] = {"uid": uid, "start": dict(run.metadata["start"]),
                           "stop": dict(run.metadata.get("stop") or {})}
    for stream in run:
        ds = run[stream].read()
        keys = list(ds.data_vars) if hasattr(ds, "data_vars") else list(ds)
        n = len(ds["time"]) if "time" in ds else (len(ds[keys[0]]) if keys else 0)
        rows = []
        for i in range(n):
            row = {}
            for k in keys:
                v = np.asarray(ds[k][i])
                v = v.item() if v.ndim == 0 else v
                if k.endswith("_json") and isinstance(v, str):
                    row[k[:-5]] = json.loads(v)
                else:
                    row[k] = v
            rows.append(row)
        out[stream] = rows
    return out
