"""Which physical effect is missing?  Rank candidates, add the winner, watch the error fall.

The offsets absorb much of what a missing effect does to the histograms (they move, widen
and dim the focus too), and a fit of the offsets alone leaves them where they absorbed it: at
that point an effect's own gradient is often flat (a defocus).  So every candidate is *fitted*
together with the offsets, from starting values spread over its prior range, and judged by
the misfit left.  Every fit is the one fit engine (:mod:`bluesky_offsets.model.fit`: the
differentiable twin, exact Jacobians, beam features then bins):

1. **Fit** the offsets alone (the reference) and each candidate with the offsets, from each
   of its :func:`starting_values`, all on one set of rays (common random numbers: their χ²
   differ by what the models differ in, not by sampling noise).  Optionally (``fit_top``)
   every start is first *screened* (:func:`bluesky_offsets.model.fit.screen`: one Jacobian of the
   twin and a few steps on its secant updates) and only the best candidates are fitted; not
   the default, a screen misjudges a defocus (:data:`FIT_TOP`).  The reference is then
   refitted from where the best candidate fits left the offsets (their effect removed): a
   gain that was the offsets' own goes to the reference.
2. **Verify** the best candidates with fresh rays, twice (two independent draws), against the
   offsets-only reference; a candidate's gain is the smaller of its two χ² improvements.
   Held out: each fit and the reference re-solved (one Gauss-Newton step on the exact
   Jacobian) without each of K folds of configurations, scored on the left-out ones.
3. **Decide**: a candidate is significant when the model is beyond noise (χ² above its
   expectation by ``n_sigma`` times ``sqrt(2 dof)``), its gain divided by the dispersion
   (the reference's χ² per degree of freedom when above 1: a model beyond noise inflates every
   gain alike) exceeds a BIC price ``p ln N``, and the held-out folds do not contradict it.
   Whether the measurement tells the best from each other verified candidate is said with it
   (:func:`lead_z`: its lead in σ over the bins; :data:`TOLD_APART`).

Each candidate also predicts a residual signature (centroid shift, width change, asymmetry,
tails, lost intensity per axis) to set beside the observed one.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics import effects as E
from bluesky_offsets.model.misfit import Misfit, misfit, moments
from bluesky_offsets.model.fit import FitOptions, FitResult, engine_for, fit, gather, information, screen
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.model.state import ModelState, refine, simulate_with_noise, solve_normal
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable, at_offset_bound
from bluesky_offsets.physics.twin import Twin
from bluesky_offsets.streams import MODEL_SEED, stream


@dataclass
class Candidate:
    """One candidate effect as a diagnosis scored it: its fitted values, gains, price, held-out folds and verdict."""

    name: str
    n_params: int
    values: dict[str, float]
    sigma: dict[str, float]
    delta_chi2_heldout: float          # feature χ² gain on held-out configurations (summed over folds)
    delta_chi2_all: float              # feature χ² gain of its fit over the offsets-only fit (same rays)
    penalty: float                     # p ln N, N the bins with signal
    significant: bool
    predicted_signature: dict[str, float]
    # the reference's χ² per degree of freedom (>= 1) that every gain is divided by
    dispersion: float = 1.0
    # folds whose held-out feature χ² the candidate lowered / raised (beyond rounding), of how many
    folds_improved: int = 0
    folds_total: int = 0
    folds_worse: int = 0
    # bins χ² gain through the twin, set for the verified candidates
    delta_chi2_twin: float | None = None
    refined_state: ModelState | None = field(default=None, repr=False)  # where its fit ended
    feature_penalty: float = 0.0       # p ln (number of features)
    feature_dispersion: float = 1.0    # the offsets-only fit's feature χ² per feature (>= 1)
    # the share of its signature the offsets can mimic at its fit (1: no measurement of this
    # design tells the effect from offsets)
    absorbed: float = float("nan")
    # fitted with the offsets to convergence (False: only screened, see diagnose's fit_top)
    fitted: bool = True
    # for a verified candidate below the best: by how many σ the measurement prefers the best
    # (the smaller of the two fresh draws, :func:`lead_z`); None for the best and the unverified
    behind_z: float | None = None

    @property
    def refined(self) -> bool:
        """Verified through the twin in bins with fresh rays."""
        return self.delta_chi2_twin is not None

    @property
    def feature_score(self) -> float:
        """Gain on the features its fit saw ÷ the offsets-only fit's feature dispersion − p ln N."""
        return self.delta_chi2_all / self.feature_dispersion - self.feature_penalty

    @property
    def score(self) -> float:
        """Gain ÷ dispersion − p ln N: in bins once verified, else on the features its fit saw."""
        if self.delta_chi2_twin is not None:
            return self.delta_chi2_twin / self.dispersion - self.penalty
        return self.feature_score

    def refit_start(self, label: str = "") -> ModelState:
        """Where adding this candidate starts (:func:`add_effect_result` with ``values``).

        Its fit's offsets and the model's other effects as that fit left them.  Not the model's
        effects as they were: the candidate fit refitted them with its offsets, and the two
        belong together (mixed, they start the refit far off, which can drive a true effect to
        zero).
        """
        st = self.refined_state
        if st is None:
            raise InputError(f"candidate {self.name!r} has no fit to start from")
        return ModelState(st.offsets, {k: v for k, v in st.effects.items() if k != self.name}, label or st.label)

    def twin_start(self) -> ModelState:
        """The refit's second start (:data:`REFIT_FROM_TWIN`).

        The bare twin's offsets with the model's other effects as :meth:`refit_start` has them.
        """
        start = self.refit_start()
        return ModelState(np.zeros(len(start.offsets)), start.effects, "twin")

    @property
    def heldout_confirms(self) -> bool:
        """The held-out folds do not contradict the candidate.

        It lowers the held-out χ² in at least as many folds as it raises it.
        """
        return self.folds_total > 0 and self.folds_improved >= self.folds_worse

    def as_dict(self) -> dict:
        """The candidate's numbers and verdict as plain data (its refined state left out)."""
        return {"name": self.name, "n_params": self.n_params, "values": self.values, "sigma": self.sigma,
                "delta_chi2_heldout": self.delta_chi2_heldout, "delta_chi2_all": self.delta_chi2_all,
                "penalty": self.penalty, "score": self.score, "feature_score": self.feature_score,
                "significant": self.significant, "dispersion": self.dispersion,
                "folds_improved": self.folds_improved, "folds_worse": self.folds_worse,
                "folds_total": self.folds_total, "predicted_signature": self.predicted_signature,
                "delta_chi2_twin": self.delta_chi2_twin, "absorbed": self.absorbed, "fitted": self.fitted,
                "behind_z": self.behind_z}


@dataclass
class Diagnosis:
    """A diagnosis's outcome: the base misfit, the candidates ranked, the observed signature and its notes."""

    base_misfit: Misfit
    within_noise: bool
    candidates: list[Candidate]
    observed_signature: dict[str, float]
    folds: int
    n_traces: int = 0
    notes: list[str] = field(default_factory=list)
    reference: ModelState | None = field(default=None, repr=False)  # offsets-only compensation
    reference_misfit: Misfit | None = field(default=None, repr=False)
    # with the model within noise: how large each candidate could be and still hide behind the
    # offsets (:func:`detection_limits`), {effect: {parameter: magnitude}}
    limits: dict[str, dict[str, float]] = field(default_factory=dict)

    @property
    def best(self) -> Candidate | None:
        """The first significant candidate of the ranking; None where none is significant."""
        sig = [c for c in self.candidates if c.significant]
        return sig[0] if sig else None

    @property
    def rivals(self) -> list[Candidate]:
        """Verified candidates the measurement does not tell from the best (:data:`TOLD_APART`)."""
        return [c for c in self.candidates if c.behind_z is not None and not c.behind_z >= TOLD_APART]

    @property
    def verdict(self) -> str:
        """The diagnosis in one sentence: the missing effect with its values, or why none is named."""
        if self.best is None:
            if self.within_noise:
                return "no significant missing effect"
            # not the same message: the model is off, the candidates just cannot say why
            return (f"misfit beyond noise (chi2/dof = {self.base_misfit.chi2_reduced_total:.3g}) that no candidate "
                    "effect explains significantly")
        b = self.best
        # the candidate fits on the features give no uncertainty; the refit after adding does
        sig = {k: b.sigma.get(k, float("nan")) for k in b.values}
        vals = ", ".join(f"{k} = {v:.4g}" + (f" ± {sig[k]:.2g}" if math.isfinite(sig[k]) else "")
                         + (" at its prior bound" if E.at_bound(b.name, k, v) else "") for k, v in b.values.items())
        return f"missing effect: {b.name} ({vals})" + rivals_text(self.rivals)

    def as_dict(self) -> dict:
        """The verdict, misfit, signature, candidates, notes and limits as plain data."""
        return {"verdict": self.verdict, "within_noise": self.within_noise,
                "base_misfit": self.base_misfit.as_dict(), "observed_signature": self.observed_signature,
                "candidates": [c.as_dict() for c in self.candidates], "folds": self.folds,
                "n_traces": self.n_traces, "notes": self.notes, "limits": self.limits}


# --------------------------------------------------------------------------- #
# a diagnosis as plain data: what a run stores so that an interrupted analysis resumes
# --------------------------------------------------------------------------- #
def _state_record(st: ModelState | None) -> dict | None:
    if st is None:
        return None
    return {"offsets": [float(v) for v in st.offsets], "label": st.label,
            "effects": {k: {p: float(x) for p, x in v.items()} for k, v in st.effects.items()}}


def _state_from(rec: dict | None) -> ModelState | None:
    return None if rec is None else ModelState(np.asarray(rec["offsets"], float), rec["effects"], rec["label"])


def misfit_record(mf: Misfit | None) -> dict | None:
    """The per-configuration numbers of a misfit (not its pulls: a restored one has none)."""
    if mf is None:
        return None
    return {k: np.asarray(getattr(mf, k), float).tolist() for k in ("chi2", "dof", "mse", "expected_mse")}


def misfit_from(rec: dict | None) -> Misfit | None:
    """The :class:`Misfit` a :func:`misfit_record` holds, with empty pulls (None for None)."""
    if rec is None:
        return None
    n = len(rec["chi2"])
    chi2, dof, mse, expected_mse = (np.asarray(rec[k], float) for k in ("chi2", "dof", "mse", "expected_mse"))
    return Misfit(chi2, dof, mse, expected_mse, pulls_x=np.zeros((n, 0)), pulls_y=np.zeros((n, 0)))


def diagnosis_record(d: Diagnosis) -> dict:
    """Everything of ``d`` but the misfits' pulls, as JSON-able data (:func:`diagnosis_from`)."""
    cands = []
    for c in d.candidates:
        rec = {f: getattr(c, f) for f in ("name", "n_params", "values", "sigma", "delta_chi2_heldout",
                                           "delta_chi2_all", "penalty", "significant", "predicted_signature",
                                           "dispersion", "folds_improved", "folds_total", "folds_worse",
                                           "delta_chi2_twin", "feature_penalty", "feature_dispersion", "absorbed",
                                           "fitted", "behind_z")}
        rec["refined_state"] = _state_record(c.refined_state)
        cands.append(rec)
    return {"base_misfit": misfit_record(d.base_misfit), "within_noise": bool(d.within_noise), "candidates": cands,
            "observed_signature": dict(d.observed_signature), "folds": int(d.folds), "n_traces": int(d.n_traces),
            "notes": list(d.notes), "reference": _state_record(d.reference),
            "reference_misfit": misfit_record(d.reference_misfit), "limits": d.limits}


def diagnosis_from(rec: Mapping) -> Diagnosis:
    """The :class:`Diagnosis` a :func:`diagnosis_record` holds: same ranking, verdict and values."""
    cands = []
    for c in rec["candidates"]:
        c = dict(c)
        c["refined_state"] = _state_from(c.get("refined_state"))
        cands.append(Candidate(**c))
    base = misfit_from(rec["base_misfit"])
    if base is None:
        raise InputError("a diagnosis record without its base misfit")
    return Diagnosis(base, rec["within_noise"], cands, rec["observed_signature"],
                     rec["folds"], rec["n_traces"], list(rec["notes"]), _state_from(rec.get("reference")),
                     misfit_from(rec.get("reference_misfit")), dict(rec.get("limits") or {}))


TOLD_APART = 2.0
"""σ by which the measurement must prefer the best candidate over another verified one for the
verdict to name it alone (:func:`lead_z`, in both fresh draws).  Why: a ranking's score can put
one effect (a detector blur) ahead of the hidden one (a defocus) where, traced with fresh rays,
the two models' χ² differ by far less than their spread: the measurement does not tell them
apart, and the verdict should say so."""


def lead_z(best: Misfit, other: Misfit, dispersion: float = 1.0, price: float = 0.0) -> float:
    """By how many standard deviations the measurement prefers ``best`` over ``other``.

    The two models are not nested, and are traced with the same fresh rays against it.

    Vuong's statistic on the bins: d_b = pull_other,b² − pull_best,b² over the bins where either
    model or the measurement has signal, lead = Σ d_b / ``dispersion`` − ``price`` (the
    difference of their prices p ln N), its spread √(n var d) / ``dispersion``.  Under "the two
    fit equally well" the lead is about normal with that spread, whatever the models: the bins'
    own noise and the models' shape differences both enter var d.
    """
    a = np.concatenate([np.asarray(best.pulls_x, float).ravel(), np.asarray(best.pulls_y, float).ravel()])
    b = np.concatenate([np.asarray(other.pulls_x, float).ravel(), np.asarray(other.pulls_y, float).ravel()])
    keep = (a != 0) | (b != 0)
    d = b[keep] ** 2 - a[keep] ** 2
    if d.size < 2:
        return float("nan")
    lead = float(d.sum()) / dispersion - price
    spread = math.sqrt(d.size * float(d.var())) / dispersion
    if spread == 0:
        return math.copysign(math.inf, lead) if lead else 0.0
    return lead / spread


def rivals_text(rivals: Sequence[Candidate]) -> str:
    """The verdict's note on the candidates the measurement does not tell from the one it names."""
    if not rivals:
        return ""
    return ", not told apart from " + ", ".join(
        f"{c.name} (preferred by {c.behind_z:.1f} sigma)" if c.behind_z is not None and math.isfinite(c.behind_z)
        else c.name
        for c in rivals)


def _signature(h: np.ndarray, ref: np.ndarray, spec) -> dict[str, float]:
    """Mean over configurations of moments(h) - moments(ref), per axis."""
    out = {}
    # local-model predictions can dip below zero in empty bins: moments need counts >= 0
    h, ref = np.clip(h, 0, None), np.clip(ref, 0, None)
    nx = spec.bins_x
    for axis, sl, c in (("x", slice(0, nx), spec.centers_x), ("y", slice(nx, None), spec.centers_y)):
        a, b = moments(h[:, sl], c), moments(ref[:, sl], c)
        for k in a:
            out[f"{axis}.{k}"] = float(np.mean(a[k] - b[k]))
    return out


def _folds(n: int, k: int, seed: int) -> list[np.ndarray]:
    order = np.random.default_rng(seed).permutation(n)
    return [np.sort(order[i::k]) for i in range(k)]


# The fit options of ``bluesky-offsets demo`` and ``bluesky-offsets diagnose`` (why:
# docs/explanations/diagnosis.md, "Fitting: one engine on the differentiable twin").  The
# offsets fit starts on the beam features, whose wide basin a fit on the bins of a focus a few
# camera pixels wide lacks, then the profiles, then the bins.  The candidate fits of a diagnosis
# start from the offsets fit with the candidate switched on: a few iterations on the features
# let the offsets give back what they had absorbed, then the bins.  All fits of one diagnosis
# share their rays (one seed), so their χ² compare without sampling noise.  The fits with
# effects run on four draws of the model's rays (FitOptions.ray_draws): one draw's fixed rays
# end on a step of a staircase χ².  Their offsets end under the spread the data prefer
# (FitOptions.estimate_spread): the table's ±20 % prior lets the offsets the frames barely see wander.
FIT = FitOptions(rays=5000, stages=(("features", 15), ("profiles", 8), ("bins", 10)), ray_draws=4,
                 estimate_spread=True, posterior_starts=4)
SCAN = FitOptions(rays=3000, stages=(("features", 5), ("bins", 5)))
DESIGNED_FIT = FIT.replace(rays=2000, feature_rays=1500)
DESIGNED_SCAN = SCAN.replace(rays=1500)
"""The fits of a designed measurement (:mod:`bluesky_offsets.design`): three to four times the
frames of the bright design, each fitted with fewer model rays, all frames together about as
many as the bright design's 14 at :data:`FIT`'s and :data:`SCAN`'s."""


def fits_for(designed: bool, rays: int | None = None, starts: int | None = None) -> tuple[FitOptions, FitOptions]:
    """The offsets fit's and the candidate fits' options for a designed (or the bright) measurement.

    ``rays`` (``--fit-rays``): the fit's model rays, and the candidate fits' at most.  ``starts``
    (``--fit-starts``): the offsets fit's :attr:`~FitOptions.posterior_starts` (None: its own).
    """
    fit, scan = (DESIGNED_FIT, DESIGNED_SCAN) if designed else (FIT, SCAN)
    fit = fit.replace(rays=rays or fit.rays, posterior_starts=fit.posterior_starts if starts is None else starts)
    return fit, scan.replace(rays=min(rays or scan.rays, scan.rays))


ROUNDS = 3
"""Diagnoses of an analysis at most (``plans.diagnose.analyse_measurement``): two hidden effects
and one more.  An effect the offsets half mimic (photon energy, the grating's line density) can
rank above the true one and be added first; the backward step (:func:`retest_effects`) drops it
once the true one is in, and the third round leaves room for a second hidden effect."""
REFIT_FROM_TWIN = True
"""Whether an analysis refits an added effect also from the bare twin's offsets, the effect at
the diagnosis's values, beside where the diagnosis's candidate fit ended, keeping the fit that
ends lowest on fresh rays (``plans.diagnose.analyse_measurement``): the diagnosis's end may
hold offsets that compensate part of the effect, the bare twin's do not."""
FIT_TOP: int | None = None
"""Candidates a diagnosis fits to convergence after every start of every candidate is screened
(:func:`bluesky_offsets.model.fit.screen`); None (the default): every start fitted.  Not the default
because a screen misjudges a defocus: offsets that have absorbed one need many exact steps to
give it back, so a screen ranks it low where the full fits name it."""


def starting_values(effect: E.Effect) -> list[dict[str, float]]:
    """Where :func:`diagnose` starts fitting ``effect``: one start per marked parameter and sign.

    Each parameter alone (of those marked ``start``) at ±1/4 of its prior span when it may take
    either sign, at 1/4 of its bound when one-sided; zero when none is marked.  Away from zero on
    purpose: the offsets-only fit has absorbed what it could of the effect, and there the effect's
    gradient is often flat (a defocus is symmetric about the focus).
    """
    out = []
    for q in effect.parameters:
        if not q.start:
            continue
        vals: tuple[float, ...]
        if q.low < 0 < q.high:
            vals = (max(q.low, -0.25 * q.span), min(q.high, 0.25 * q.span))
        else:
            vals = (0.25 * (q.high if q.high > 0 else q.low),)
        out += [{q.name: float(v)} for v in vals]
    return out or [{}]  # nothing worth a start away from zero: one fit from zero


# What separates an effect from the offsets when the design cannot (reported with the verdict).
SEPARATE_BY = {
    "photon_energy": "frames at two or more photon energies (undulator gap and grating angle moved together)",
    "source_size": "frames with the aperture (ASBL) closed down and opened wide",
    "source_divergence": "frames with the aperture (ASBL) closed down and opened wide",
}
UNSEPARABLE = 0.99
"""A candidate whose signature the offsets mimic to this share is reported as not separable."""


def absorbed_share(fit: FitResult, n_offsets: int) -> float:
    """The share of an effect's information that the offsets can take over at the solution.

    The information is the effect's diagonal of the fit's normal matrix, the offsets' prior
    included; the share is 1 − Schur complement / diagonal, the largest over the effect's parameters.
    """
    G = fit.jacobian
    assert G is not None  # fit() keeps its last stage's Jacobian
    A = G.T @ G + np.diag(fit.ridge if fit.ridge is not None else np.zeros(G.shape[1]))
    o, e = slice(0, n_offsets), slice(n_offsets, G.shape[1])
    if e.start >= e.stop:
        return float("nan")
    Aoo = A[o, o] + 1e-12 * np.trace(A[o, o]) / max(n_offsets, 1) * np.eye(n_offsets)
    S = A[e, e] - A[e, o] @ solve_normal(Aoo, A[o, e])
    d = np.diag(A[e, e])
    keep = np.where(d > 0, np.diag(S) / np.where(d > 0, d, 1.0), 0.0)
    return float(np.clip(1.0 - keep.min(), 0.0, 1.0))


def detection_limits(meas: Measurement, state: ModelState, engine, options: FitOptions, names: Sequence[str],
                     excess: float, *, executor: Executor | None = None,
                     table: ParameterTable = METRIXS) -> dict[str, dict[str, float]]:
    """How large each candidate effect could be and still leave the offsets-only model within noise.

    For each of its parameters, the magnitude at which, the offsets refitted to absorb what they
    can, it would add ``excess`` to χ² (the noise gate's ``n_sigma √(2 dof)``).

    Linearised at each of the candidate's :func:`starting_values` (the state with the effect
    there; :func:`bluesky_offsets.model.fit.information`: one exact Jacobian of the twin each):
    the parameter's σ with the offsets free is the Schur complement's, and a magnitude ``a`` adds
    ``(a / σ)²``, so the limit is ``σ √excess``; the smallest over the starts that move the
    parameter (an effect without starts: at zero, every parameter).  Where the twin responds
    less than at the start (a defocus near its focus) more can hide: a limit estimates from below
    what can hide, it is no bound on what shows.  Infinite where the data do not see the
    parameter at all.
    Side by side on ``executor``, read in order.
    """
    jobs = [(name, v) for name in names for v in starting_values(E.get(name))]
    looks = gather([lambda st=state.with_effect(name, v): information(meas, st, engine, options, table=table)
                    for name, v in jobs], executor)
    out: dict[str, dict[str, float]] = {}
    for (name, v), f in zip(jobs, looks):
        sig = f.effect_sigma().get(name, {})
        # a start moves one parameter; an effect without one starts (and is looked at) at zero
        for q in v or [p.name for p in E.get(name).parameters]:
            s = sig.get(q, float("nan"))
            lim = s * math.sqrt(excess) if math.isfinite(s) and s > 0 else math.inf
            out.setdefault(name, {})[q] = min(out.get(name, {}).get(q, math.inf), lim)
    return out


def limits_text(limits: Mapping[str, Mapping[str, float]]) -> str:
    """"chamber_z.z up to 12.3 mm; ..." (:func:`detection_limits`)."""
    return "; ".join(f"{name}.{q} {limit_text(name, q, lim)}" for name, d in limits.items() for q, lim in d.items())


def limit_text(name: str, parameter: str, limit: float) -> str:
    """"up to 12.3 mm", or what an infinite limit means."""
    if not math.isfinite(limit):
        return "at any size (this design does not see it)"
    unit = next((p.unit for p in E.get(name).parameters if p.name == parameter), "")
    return f"up to {limit:.3g}" + (f" {unit}" if unit else "")


def _fresh_misfit(verifier: Twin, meas: Measurement, st: ModelState, rays: int, seed: int, draw: int,
                  table: ParameterTable) -> tuple[Misfit, np.ndarray]:
    """``st`` traced with fresh rays against ``meas``: its misfit and the model's histograms (C, bins x + bins y).

    The rays are draw ``draw`` of streams none of the fits traced.
    """
    seeds = [stream(seed, "diagnosis.fresh_rays", draw=draw) + i for i in range(meas.n)]
    hx, hy, noise = simulate_with_noise(verifier, meas.configurations, st, rays, seeds, table, meas.screen)
    return misfit(meas.hist_x, meas.hist_y, hx, hy, meas.ray_budget, model_rays=rays, floor_x=meas.floor_x,
                  floor_y=meas.floor_y, model_noise=noise), np.c_[hx, hy]


def _heldout(fit: FitResult, folds: Sequence[np.ndarray]) -> np.ndarray:
    """Held-out χ² per fold: the fit re-solved without the fold's configurations, scored on the fold.

    The re-solve is one Gauss-Newton step from the all-data solution on its exact Jacobian.
    """
    G, r, rows = fit.jacobian, fit.residuals, fit.rows
    assert G is not None and r is not None and rows is not None  # fit() keeps its last stage's
    out = []
    for fold in folds:
        test = np.isin(rows, fold)
        Gt, rt = G[~test], r[~test]
        A = Gt.T @ Gt
        A = A + np.diag(np.diag(A)) * 1e-2 + 1e-9 * np.trace(A) / len(A) * np.eye(len(A))
        d = solve_normal(A, Gt.T @ rt)
        res = r[test] - G[test] @ d
        out.append(float(res @ res))
    return np.array(out)


def diagnose(meas: Measurement, state: ModelState, twin=None, forward_model=None, *,
             candidates: Sequence[str] | None = None, folds: int = 4, seed: int = 0, n_sigma: float = 3.0,
             options: FitOptions | Mapping | None = None, verify_rays: int | None = None, verify_top: int = 3,
             fit_top: int | None = FIT_TOP, progress=None, executor: Executor | None = None,
             table: ParameterTable = METRIXS, spread: float | None = None) -> Diagnosis:
    """Rank candidate effects for the misfit of ``state`` against ``meas`` (see the module text).

    ``state`` should already carry fitted offsets (:func:`bluesky_offsets.model.state.refine`).
    Candidates default to every registered effect the state does not include yet.  Every fit
    (the offsets-only reference and each candidate from each of its :func:`starting_values`)
    runs :func:`bluesky_offsets.model.fit.fit` with ``options`` (default :data:`SCAN`) on one set of
    rays.  The ``verify_top`` best are traced again with fresh rays (``verify_rays``, default
    4x the measurement's) beside the reference.  ``executor`` runs the candidate fits side by
    side (:func:`bluesky_offsets.model.fit.gather`: the same fits and the same result on any
    number of threads).  ``fit_top``: with more candidates than this, every start is first
    screened (:func:`bluesky_offsets.model.fit.screen`: the twin's Jacobian there and a few steps
    on its secant updates, a fifth of a fit) and only the best ``fit_top`` candidates are fitted;
    None fits every start.  ``twin`` names the parameter table and ``forward_model`` is not used
    (both kept for symmetry with the other steps).  ``spread``: the offsets' spread the offsets fit
    estimated (:attr:`~bluesky_offsets.model.fit.FitResult.prior_sigma`), the offsets' prior of the
    detection limits where the base model is within noise (offsets that narrow hide less).
    """
    names = [n_ for n_ in (candidates or list(E.EFFECTS)) if n_ not in state.effects]
    for n_ in names:
        E.get(n_)
    o = FitOptions.resolve(options, SCAN)
    o = o.replace(seed=stream(seed, "diagnosis.fits"))
    spec, n = meas.spec, meas.n
    engine = engine_for(meas, o, table)
    verifier = Twin(engine)  # the same twin, traced with fresh rays
    verify_rays = int(verify_rays or 4 * meas.ray_budget)

    def verify(st: ModelState, draw: int = 0) -> tuple[Misfit, np.ndarray]:
        return _fresh_misfit(verifier, meas, st, verify_rays, seed, draw, table)

    base_mf, base_view = verify(state)
    n_traces = n
    n_starts = sum(len(starting_values(E.get(n_))) for n_ in names)
    fold_idx = _folds(n, folds, seed)
    if not base_mf.total_beyond_noise(n_sigma):
        # nothing to explain: no candidate is fitted.  What the verdict cannot exclude is said:
        # an effect the offsets absorb leaves a model within noise
        lo = o if spread is None else o.replace(prior_sigma=spread)
        limits = detection_limits(meas, state, engine, lo, names, base_mf.noise_margin(n_sigma), executor=executor,
                                  table=table)
        n_traces += n * n_starts  # one Jacobian at each start
        return Diagnosis(base_mf, True, [], _signature(meas.histograms, base_view, spec), folds, n_traces,
                         [f"the base model is within noise (chi2/dof = {base_mf.chi2_reduced_total:.2f}): "
                          "no candidate fitted; the limits say how large each could be and still hide behind the "
                          f"offsets ({n_sigma:g} sigma of chi2, linearised at its starts, {o.rays} model rays)"],
                         state, base_mf, limits=limits)

    def report(label):
        def inner(h):
            if progress:
                progress({"fit": label, **h})
        return inner

    fits = _fit_candidates(meas, state, engine, o, names, fit_top=fit_top, verify_top=verify_top, report=report,
                           executor=executor, table=table)
    out = _candidates(names, fits, base_mf, table)
    v = _verify(meas, state, out, fits, verify=verify, verifier=verifier, seed=seed, n_sigma=n_sigma,
                fold_idx=fold_idx, verify_top=verify_top, executor=executor, table=table)
    notes = _notes(out, fits, v, o, n_starts=n_starts, n_names=len(names))
    return Diagnosis(base_mf, v.within, out, v.observed, folds, n_traces + fits.n_traces + v.n_traces, notes,
                     v.ref_state, v.ref_mf)


@dataclass(frozen=True, kw_only=True)
class _CandidateFits:
    """:func:`diagnose`'s fits on one set of rays.

    The offsets-only reference (refitted from where the best candidates left the offsets), each
    candidate's best fit or look, and which were fitted.
    """

    ref: FitResult
    best: dict[str, FitResult]
    fitted: set[str]
    screened: bool
    n_traces: int


def _fit_candidates(meas: Measurement, state: ModelState, engine, o: FitOptions, names: Sequence[str], *,
                    fit_top: int | None, verify_top: int, report, executor: Executor | None,
                    table: ParameterTable) -> _CandidateFits:
    """The offsets-only reference and every candidate with the offsets, on one set of rays."""
    ref = fit(meas, state, engine, o, progress=report("offsets only"), table=table)
    n_traces = ref.n_traces
    jobs = [(name, ref.state.with_effect(name, v)) for name in names for v in starting_values(E.get(name))]
    best: dict[str, FitResult] = {}
    screened = fit_top is not None and fit_top < len(names)
    if screened:
        # every start looked at once (the twin's Jacobian there, a few steps on its secant
        # updates); the best few candidates fitted from where their best start's look ended
        looks = gather([lambda st=st: screen(meas, st, engine, o, table=table) for _, st in jobs], executor)
        for k, ((name, _), f) in enumerate(zip(jobs, looks)):
            n_traces += f.n_traces
            report(name)({"stage": "screen", "iteration": k + 1, "accepted": True, "chi2": f.chi2,
                          "chi2_reduced": f.chi2_reduced})
            if name not in best or f.chi2 < best[name].chi2:
                best[name] = f
        chosen = sorted(best, key=lambda n_: best[n_].chi2)[:fit_top]
        jobs = [(name, best[name].state) for name in chosen]
    fits = gather([lambda name=name, st=st: fit(meas, st, engine, o, progress=report(name), table=table)
                   for name, st in jobs], executor)
    fitted = set()
    for (name, _), f in zip(jobs, fits):
        n_traces += f.n_traces
        if name not in fitted or f.chi2 < best[name].chi2:
            best[name] = f
        fitted.add(name)
    n_traces += _from_the_twin(meas, ref, best, fitted, engine, o, verify_top, report, executor, table)
    # the reference as well fitted as the candidates: the offsets alone, refitted in the last
    # stage from where the best candidate fits left the offsets (their effect removed).  A
    # candidate's gain that was the offsets' (its fit went on where the reference's stopped)
    # goes to the reference; a true effect's does not (without it, those offsets no longer
    # compensate), so a small spurious candidate cannot outscore a true one.
    # (the last stage alone: the features stage would first trade the bins for the features)
    froms = [n_ for n_ in sorted(fitted, key=lambda n_: best[n_].chi2)[:verify_top] if best[n_].chi2 < ref.chi2]
    # (each call holds only its start: one that reached ``best`` would carry every candidate's
    # Jacobian to the worker)
    alt_fits = [lambda st=ModelState(best[name].state.offsets, state.effects, state.label), name=name:
                fit(meas, st, engine, o.replace(stages=o.stages[-1:]), progress=report(f"offsets only, from {name}'s"),
                    table=table)
                for name in froms]
    # side by side all at once; one after the other only as far as the loop goes (the same
    # result: the loop reads them in order and stops at the same place)
    alts = gather(alt_fits, executor) if executor is not None else None
    for k, name in enumerate(froms):
        if best[name].chi2 >= ref.chi2:
            break  # beside the reference as it now stands, this candidate gained nothing
        alt = alts[k] if alts is not None else alt_fits[k]()
        n_traces += alt.n_traces
        if alt.chi2 < ref.chi2:
            ref = alt
    return _CandidateFits(ref=ref, best=best, fitted=fitted, screened=screened, n_traces=n_traces)


def _from_the_twin(meas: Measurement, ref: FitResult, best: dict[str, FitResult], fitted: set[str], engine,
                   o: FitOptions, top: int, report, executor: Executor | None, table: ParameterTable) -> int:
    """The best ``top`` candidates fitted again from the twin's offsets where ``ref`` left offsets at their bounds.

    Each from zero offsets with the effects as its fit left them; ``best`` keeps the lower χ².
    Returns the traces it took.  Offsets at a bound have absorbed what the prior let them (a
    defocus, on a screen that barely tells it from them); a candidate started among them can stay
    where it starts.
    """
    if not at_offset_bound(ref.state.offsets, o.offset_bound).any():
        return 0
    names = sorted(fitted, key=lambda n_: best[n_].chi2)[:top]
    again = gather([lambda st=ModelState(np.zeros(len(best[n_].state.offsets)), best[n_].state.effects), n_=n_:
                    fit(meas, st, engine, o, progress=report(f"{n_}, from the twin's offsets"), table=table)
                    for n_ in names], executor)
    for name, f in zip(names, again):
        if f.chi2 < best[name].chi2:
            best[name] = f
    return sum(f.n_traces for f in again)


def _candidates(names: Sequence[str], fits: _CandidateFits, base_mf: Misfit, table: ParameterTable) -> list[Candidate]:
    """Each candidate scored on the fits' rays (Δχ² against the reference, less its BIC price), best first."""
    ref, best = fits.ref, fits.best
    dispersion_fit = max(1.0, ref.chi2_reduced)
    n_signal = int(base_mf.dof_total)
    out = []
    for name in names:
        eff, f = E.get(name), best[name]
        p = len(eff.parameters)
        values = {k: float(v) for k, v in f.state.effects[name].items()}
        # a screened start has no uncertainty: it is not a solution
        sigma = f.effect_sigma().get(name, {}) if name in fits.fitted else {}
        out.append(Candidate(name, p, values, {k: float(sigma.get(k, float("nan"))) for k in values}, 0.0,
                             ref.chi2 - f.chi2, p * math.log(max(n_signal, 2)), False, {},
                             refined_state=f.state, feature_penalty=p * math.log(max(n_signal, 2)),
                             feature_dispersion=dispersion_fit, fitted=name in fits.fitted))
    for c in out:
        c.absorbed = absorbed_share(best[c.name], len(table))
    out.sort(key=lambda c: -c.score)
    return out


@dataclass(frozen=True, kw_only=True)
class _Verified:
    """:func:`diagnose`'s check with fresh rays.

    The refitted reference, its misfit, whether it is within noise, the candidates it verified,
    the observed residual signature.
    """

    ref_state: ModelState
    ref_mf: Misfit
    within: bool
    top: list[Candidate]
    observed: dict
    n_traces: int


def _verify(meas: Measurement, state: ModelState, out: list[Candidate], fits: _CandidateFits, *, verify, verifier,
            seed: int, n_sigma: float, fold_idx: Sequence[np.ndarray], verify_top: int, executor: Executor | None,
            table: ParameterTable) -> _Verified:
    """The best few verified with fresh rays beside the reference, and on held-out folds.

    ``out`` is re-sorted, verified first, each with its gain, significance and predicted signature.
    """
    ref, best, spec, n = fits.ref, fits.best, meas.spec, meas.n
    top = [c for c in out if c.score > 0 and c.fitted][:verify_top]
    ref_state = ModelState(ref.state.offsets, state.effects, f"{state.label} (offsets refitted)")
    # every fresh trace below at once, side by side on the executor (independent traces, read
    # in this order: the same numbers on any number of threads): the reference and the best few
    # on two draws each, and the others at the measurement's rays for the ranking plot's
    # signatures (a picture, not a verdict; the verified ones have 4x)
    rest = [c for c in out if not any(c is t for t in top)]  # by identity: Candidate's == compares fields
    traced = gather([lambda st=st, k=k: verify(st, k) for st in [ref_state] + [c.refined_state for c in top]
                     for k in (0, 1)]
                    + [lambda c=c: _fresh_misfit(verifier, meas, c.refined_state, meas.ray_budget, seed, 0, table)
                       for c in rest], executor)
    (ref_mf, ref_view), (ref_mf2, _) = traced[0], traced[1]
    within = not ref_mf.total_beyond_noise(n_sigma)
    dispersion = max(1.0, ref_mf.chi2_total / max(ref_mf.dof_total, 1.0))
    ref_ho = _heldout(ref, fold_idx)
    for j, c in enumerate(top):
        (mf_c, h), (mf_c2, _) = traced[2 + 2 * j], traced[3 + 2 * j]
        # a gain must hold with two independent sets of fresh rays: a verdict that another
        # draw of the model's rays would flip is not significant
        c.delta_chi2_twin = float(min(ref_mf.chi2_total - mf_c.chi2_total, ref_mf2.chi2_total - mf_c2.chi2_total))
        c.dispersion = dispersion
        c.predicted_signature = _signature(h, ref_view, spec)
        gain = ref_ho - _heldout(best[c.name], fold_idx)
        tol = 1e-9 * np.maximum(ref_ho, 1.0)
        c.delta_chi2_heldout = float(gain.sum())
        c.folds_improved, c.folds_worse = int((gain > tol).sum()), int((gain < -tol).sum())
        c.folds_total = len(fold_idx)
        # nested models scored on the same measurement and the same fresh rays: under "no such
        # effect" the gain is ~ dispersion * chi2_p, which the BIC price p ln N covers
        c.significant = bool(not within and c.score > 0 and c.heldout_confirms)
    for c, (_, h) in zip(rest, traced[2 + 2 * len(top):]):
        c.predicted_signature = _signature(h, ref_view, spec)
    observed = _signature(meas.histograms, ref_view, spec)
    out.sort(key=lambda c: (not c.refined, -c.score))
    # whether the measurement tells the best from each other verified candidate: the lead of
    # the best over it in σ, the smaller of the two fresh draws (a tie is said with the verdict)
    ranked = [c for c in out if c.refined]
    lead = next((c for c in ranked if c.significant), None)
    if lead is not None:
        drawn = {c.name: (traced[2 + 2 * j][0], traced[3 + 2 * j][0]) for j, c in enumerate(top)}
        for c in ranked:
            if c is not lead and c.score > 0:
                c.behind_z = min(lead_z(b, o, dispersion, lead.penalty - c.penalty)
                                 for b, o in zip(drawn[lead.name], drawn[c.name]))
    return _Verified(ref_state=ref_state, ref_mf=ref_mf, within=within, top=top, observed=observed,
                     n_traces=2 * n * (1 + len(top)) + n * len(rest))


def _notes(out: list[Candidate], fits: _CandidateFits, v: _Verified, o: FitOptions, *, n_starts: int,
           n_names: int) -> list[str]:
    """What the diagnosis did, which candidates the offsets mimic, whether the offsets alone reach the noise."""
    how = (f"{n_starts} starts of {n_names} candidates screened (one Jacobian of the twin each), the best "
           f"{len(fits.fitted)} fitted" if fits.screened else f"{n_starts} fits of {n_names} candidates")
    notes = [(f"{how} with the offsets ({', '.join(f'{s} {k}' for s, k in o.stages)} iterations, {o.rays} rays, "
             f"exact Jacobians); "
             f"offsets-only refit: chi2/dof {fits.ref.chi2_reduced:.3g} on the fit's rays, "
             f"{v.ref_mf.chi2_reduced_total:.3g} with fresh rays; verified: {', '.join(c.name for c in v.top) or 'none'}")]
    for c in (c for c in out if c.absorbed >= UNSEPARABLE):
        notes.append(f"{c.name} cannot be told from offsets with this design (the offsets mimic "
                     f"{100 * c.absorbed:.1f} % of it); what would separate it: "
                     f"{SEPARATE_BY.get(c.name, 'frames that move the motors its signature resembles')}")
    if v.within:
        notes.append(f"the offsets alone reach the noise once refitted (chi2/dof = {v.ref_mf.chi2_reduced_total:.2f})")
    return notes


# Lever arms that separate a screen translation from focal-length (half-axis) offsets: tilting
# E1/E2 changes where the beam meets the screen and how the focus is aberrated, which a focal
# length change does not (docs/explanations/diagnosis.md).  Normalized half-widths of the spread.
DIAGNOSTIC_SPREAD = {"E1.rotationXerror": 0.3, "E1.rotationYerror": 0.3, "E2.rotationXerror": 0.3,
                     "E2.rotationYerror": 0.3}


def diagnostic_configurations(around, n: int = 12, *, seed: int = 0, spread: dict[str, float] | None = None,
                              table: ParameterTable = METRIXS) -> np.ndarray:
    """``n`` configurations (n, P) around ``around`` (physical, table order) for a diagnosis.

    Motorized parameters named in ``spread`` (default :data:`DIAGNOSTIC_SPREAD`) are drawn
    uniformly within ± their normalized half-width and clipped to the box; the others stay at
    ``around``; fixed parameters at their design value.
    """
    spread = DIAGNOSTIC_SPREAD if spread is None else spread
    base = table.normalize(table.validate(np.asarray(around, dtype=float), "around"))
    rng = np.random.default_rng(seed)
    z = np.tile(base, (n, 1))
    for name, half in spread.items():
        i = table.index(name)
        if not table.motorized[i]:
            raise InputError(f"{name} is not motorized: it cannot be varied between configurations")
        z[:, i] = np.clip(base[i] + rng.uniform(-half, half, n), 0.0, 1.0)
    return np.where(table.motorized, table.denormalize(z), table.reference)


# Real METRIXS measurements also open the aperture and the exit slit (ASBL 4 mm, exit slit
# 100 µm: ../shared/reference/metrixs_2021_real_settings.csv).  With the slits at their usual
# 2 x 1 mm and 10 µm a source-divergence change only changes how much the ASBL and the slit cut
# away, which a gain change and slit offsets mimic (98 % of its signal absorbed by the offsets);
# wide open, the whole beam reaches the optics and the change shows in the focus shape (73 %
# absorbed, a gain change leaves 62 of the 398 left: bench_effect_identifiability.py --open 4).
OPEN_APERTURE = {"ASBL.totalWidth": 4.0, "ASBL.totalHeight": 4.0, "ExitSlit.totalHeight": 0.1}


def open_settings(table: ParameterTable = METRIXS) -> dict[str, float]:
    """The openings of an open aperture.

    METRIXS's :data:`OPEN_APERTURE`; on another beamline every motorized opening at the end of its
    travel.
    """
    if all(n in table.names for n in OPEN_APERTURE):
        return dict(OPEN_APERTURE)
    from bluesky_offsets.physics.metrixs import OPENING_FIELDS
    return {p.name: p.limits[1] for p in table if p.motorized and p.field in OPENING_FIELDS}


def open_aperture(configurations, settings: dict[str, float] | None = None,
                  table: ParameterTable = METRIXS) -> np.ndarray:
    """Copies of ``configurations`` (n, P) with the slit openings of ``settings``.

    ``settings``: physical, default :func:`open_settings`.  They lie outside the surrogate's box:
    the twin models them, the surrogate finder must not see them (``table.outside_box``).
    """
    cfg = np.array(table.validate(np.atleast_2d(configurations), "configurations"), dtype=float)
    for name, value in (open_settings(table) if settings is None else settings).items():
        p = table[name]
        lo, hi = p.limits
        if not lo <= value <= hi:
            raise InputError(f"{name} = {value:g} {p.unit} is outside the motor's travel [{lo:g}, {hi:g}]")
        cfg[:, table.index(name)] = value
    return cfg


def in_box(configurations, table: ParameterTable = METRIXS) -> np.ndarray:
    """Mask of the configurations inside the surrogate's box."""
    return np.array([not table.outside_box(c) for c in np.atleast_2d(configurations)], dtype=bool)


def _with(state: ModelState, names: Sequence[str]) -> ModelState:
    st = state
    for n_ in names:
        st = st.with_effect(n_)
    return st


# --------------------------------------------------------------------------- #
# model versions and the error history
# --------------------------------------------------------------------------- #
@dataclass
class Version:
    """One version of the model: its label, state, misfit and effects' uncertainties."""

    label: str
    state: ModelState
    misfit: Misfit
    effect_sigma: dict[str, dict[str, float]] = field(default_factory=dict)

    def row(self) -> dict:
        """The version as a row of the error history: χ²/dof, MSE against its noise, effects and their σ."""
        return {"model": self.label, "chi2_reduced": self.misfit.chi2_reduced_total,
                "mse": self.misfit.mse_total, "expected_mse": self.misfit.expected_mse_total,
                "mse_over_noise": self.misfit.mse_total / max(self.misfit.expected_mse_total, 1e-300),
                "effects": {k: dict(v) for k, v in self.state.effects.items()},
                "effect_sigma": self.effect_sigma}


def evaluate(meas: Measurement, state: ModelState, twin, *, model_rays: int | None = None, seed: int = MODEL_SEED,
             table: ParameterTable = METRIXS) -> Misfit:
    """The twin at the model's compensated configurations vs. the measurement (fresh rays)."""
    model_rays = model_rays or 4 * meas.ray_budget  # a sharper model than the measurement
    hx, hy, noise = simulate_with_noise(twin, meas.configurations, state, model_rays,
                                        [seed + i for i in range(meas.n)], table, meas.screen)
    return misfit(meas.hist_x, meas.hist_y, hx, hy, meas.ray_budget, model_rays=model_rays, floor_x=meas.floor_x,
                  floor_y=meas.floor_y, model_noise=noise)


def add_effect(meas: Measurement, state: ModelState, name: str, twin=None, forward_model=None, *,
               values=None, options: FitOptions | Mapping | None = None, progress=None,
               executor: Executor | None = None,
               table: ParameterTable = METRIXS) -> tuple[ModelState, dict[str, dict[str, float]]]:
    """``state.with_effect(name, values)`` with offsets and effect refitted (:func:`add_effect_result`)."""
    res = add_effect_result(meas, state, name, twin, forward_model, values=values, options=options,
                            progress=progress, executor=executor, table=table)
    return res.state, res.effect_sigma


def add_effect_result(meas: Measurement, state: ModelState, name: str, twin=None, forward_model=None, *,
                      values=None, options: FitOptions | Mapping | None = None, progress=None,
                      also_from: Sequence[ModelState] = (), executor: Executor | None = None,
                      table: ParameterTable = METRIXS):
    """``state.with_effect(name, values)``, offsets and effect refitted with the one fit engine.

    The fit is :func:`bluesky_offsets.model.state.refine`, options default :data:`FIT`; returns its
    :class:`~bluesky_offsets.model.state.RefineResult`.  ``values`` starts the effect where the
    diagnosis found it (a :class:`Candidate` or its ``values``).  ``also_from``: more starts
    (offsets, and the model's other effects), each given the effect at ``values``; the fit that
    ends lowest on fresh rays is kept (:func:`bluesky_offsets.model.fit.fit`).  ``executor`` runs
    the starts, then the fit's ray draws, side by side.
    """
    if values is not None and not isinstance(values, dict):
        values = getattr(values, "values", values)  # a Candidate
    o = FitOptions.resolve(options, FIT)
    return refine(meas, state.with_effect(name, values), twin, forward_model, options=o, progress=progress,
                  also_from=[st.with_effect(name, values) for st in also_from], executor=executor, table=table)


# --------------------------------------------------------------------------- #
# the backward step: does each added effect still earn its place with the others in?
# --------------------------------------------------------------------------- #
@dataclass
class EffectTest:
    """One effect of a model tested against the model refitted without it."""

    effect: str
    n_params: int
    gain: float                 # χ² (fresh rays) without it minus with it: the smaller of two draws
    price: float                # p ln N times the dispersion (the model's χ²/dof when above 1)
    beyond_noise_without: bool  # the model without it is beyond noise
    without: FitResult = field(repr=False)  # the model refitted without it

    @property
    def kept(self) -> bool:
        """Significant given the others: the diagnosis's criterion turned around."""
        return self.beyond_noise_without and self.gain > self.price

    def as_dict(self) -> dict:
        """The test's numbers, whether the effect is kept, and the χ²/dof without it."""
        return {"effect": self.effect, "n_params": self.n_params, "gain": self.gain, "price": self.price,
                "beyond_noise_without": self.beyond_noise_without, "kept": self.kept,
                "chi2_reduced_without": self.without.chi2_reduced}


def retest_effects(meas: Measurement, state: ModelState, names: Sequence[str] | None = None, *,
                   options: FitOptions | Mapping | None = None, seed: int = 0, n_sigma: float = 3.0,
                   verify_rays: int | None = None, progress=None, executor: Executor | None = None,
                   table: ParameterTable = METRIXS) -> list[EffectTest]:
    """Each of ``names`` (default: every effect of ``state``) tested given the others.

    Effects are added one after another, each the best candidate *then*; an effect added early
    may have stood in for one added later (photon energy, which the offsets half mimic, can rank
    above a hidden source divergence and fit to zero once the divergence is in).  So, after the
    forward steps, each effect is removed in turn, the rest refitted from where the full model
    ended with every stage of ``options`` (default :data:`FIT`, as the full model was: an effect
    the offsets half mimic moves the beam, and the offsets need the features' wide basin to take
    it back: with the last stage alone, removing even an effect fitted near zero looks costly),
    and both traced with fresh rays (two draws, the smaller gain counts).  An effect is kept when
    the model without it is beyond noise and its gain exceeds the diagnosis's price (``p ln N``
    times the dispersion).  ``executor`` runs each refit's ray draws side by side.
    """
    names = list(state.effects if names is None else names)
    o = FitOptions.resolve(options, FIT)
    engine = engine_for(meas, o, table)
    verifier = Twin(engine)
    verify_rays = int(verify_rays or 4 * meas.ray_budget)

    def verify(st: ModelState, draw: int) -> Misfit:
        return _fresh_misfit(verifier, meas, st, verify_rays, seed, draw, table)[0]

    full = [verify(state, d) for d in (0, 1)]
    dispersion = max(1.0, full[0].chi2_reduced_total)
    n_signal = max(int(full[0].dof_total), 2)
    out = []
    for name in names:
        rest = ModelState(state.offsets, {k: v for k, v in state.effects.items() if k != name}, state.label)

        def report(h, name=name):
            if progress:
                progress({"fit": f"without {name}", **h})
        res = fit(meas, rest, engine, o, progress=report, table=table, executor=executor)
        without = [verify(res.state, d) for d in (0, 1)]
        p = len(E.get(name).parameters)
        out.append(EffectTest(name, p, float(min(w.chi2_total - f.chi2_total for w, f in zip(without, full))),
                              p * math.log(n_signal) * dispersion, bool(without[0].total_beyond_noise(n_sigma)), res))
    return out


def weakest(tests: Sequence[EffectTest]) -> EffectTest | None:
    """The test of the effect to drop, of those not kept.

    The one whose gain falls furthest short of its price (None: every effect kept).
    """
    dropped = [t for t in tests if not t.kept]
    return min(dropped, key=lambda t: t.gain - t.price) if dropped else None


def plot_error_history(versions: Sequence[Version], path, title: str = "model error across versions"):
    """χ²/dof and MSE over its noise expectation of each model version, as bars on a log scale."""
    from bluesky_offsets.plotting import pyplot, save_figure
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 3.8), constrained_layout=True)
    labels = [v.label for v in versions]
    chi = [v.misfit.chi2_reduced_total for v in versions]
    mse_ratio = [v.misfit.mse_total / max(v.misfit.expected_mse_total, 1e-300) for v in versions]
    x = np.arange(len(versions))
    ax.bar(x - 0.2, chi, 0.4, label="χ² / dof", color="C0")
    ax.bar(x + 0.2, mse_ratio, 0.4, label="MSE / noise expectation", color="C1")
    ax.axhline(1.0, color="k", lw=0.8, ls="--", label="noise level")
    ax.set_yscale("log")
    ax.set_xticks(x, labels, rotation=15, ha="right")
    ax.set_ylabel("misfit relative to noise")
    ax.legend(fontsize=8)
    ax.set_title(title)
    return save_figure(fig, path, dpi=110)


def plot_ranking(diag: Diagnosis, path, top: int = 5):
    """Candidate scores, and the top candidates' predicted signatures beside the observed one."""
    from bluesky_offsets.plotting import pyplot, save_figure
    plt = pyplot()
    cands = diag.candidates[:top]
    keys = [k for k in diag.observed_signature if not k.endswith("skewness")]
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(13, 4.2), constrained_layout=True,
                                   gridspec_kw={"width_ratios": (1, 2)})
    scores = [c.score for c in diag.candidates][::-1]
    names = [c.name for c in diag.candidates][::-1]
    colors = ["C2" if c.significant else "C7" for c in diag.candidates][::-1]
    ax0.barh(names, scores, color=colors)
    ax0.axvline(0, color="k", lw=0.8)
    ax0.set_xscale("symlog")
    ax0.set_xlabel("score: Δχ² ÷ dispersion − p ln N")
    ax0.set_title(diag.verdict, fontsize=9)
    x = np.arange(len(keys))
    width = 0.8 / (len(cands) + 1)
    scale = {k: max(abs(diag.observed_signature[k]), 1e-12) for k in keys}
    ax1.bar(x, [diag.observed_signature[k] / scale[k] for k in keys], width, color="k", label="observed")
    for i, c in enumerate(cands):
        ax1.bar(x + (i + 1) * width, [c.predicted_signature[k] / scale[k] for k in keys], width,
                label=f"{c.name}", color=f"C{i}")
    ax1.set_xticks(x + 0.4, keys, rotation=30, ha="right")
    ax1.set_ylabel("signature / |observed|")
    ax1.axhline(0, color="k", lw=0.5)
    ax1.legend(fontsize=7, ncol=2)
    ax1.set_title("what the data lack (observed) vs. what each effect adds (predicted)", fontsize=9)
    return save_figure(fig, path, dpi=100)
