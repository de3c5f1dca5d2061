"""Which physical effect is missing?  Rank candidates, add the winner, watch the error fall.

For every candidate effect the offsets and the effect's parameters are fitted
together on a twin-anchored local model (:mod:`bluesky_offsets.model`), solved
to convergence, on all configurations and in K folds over them.  A candidate is
scored by its chi-square improvement on all data over the offsets-only fit,
divided by the offsets-only fit's chi-square per bin when that exceeds 1 (a model
beyond noise inflates every candidate's gain alike: the quasi-likelihood
correction), minus a BIC price ``p ln N`` for its ``p`` parameters.  It is
significant only if that score is positive, the held-out folds do not contradict it
(its parameters fitted without a fold, the offsets held where the offsets-only fit
put them, lower that fold's chi-square in at least as many folds as they raise it),
and the base model is not already within noise.
Each candidate also predicts a residual signature (centroid shift, width change,
asymmetry, tails, lost intensity per axis) to set beside the observed one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from . import effects as E
from .diagnostics import Misfit, misfit, moments
from .model import (LocalFit, LocalModel, Measurement, ModelState, _twin_chi2, build_local_model, fit_local, refine,
                    simulate)
from .parameters import METRIXS, ParameterTable


@dataclass
class Candidate:
    name: str
    n_params: int
    values: dict[str, float]
    sigma: dict[str, float]
    delta_chi2_heldout: float
    delta_chi2_all: float
    penalty: float
    significant: bool
    predicted_signature: dict[str, float]
    # the offsets-only fit's chi-square per bin (>= 1) that every gain is divided by
    dispersion: float = 1.0
    # folds whose held-out chi-square the candidate lowered / raised (beyond rounding), of how many
    folds_improved: int = 0
    folds_total: int = 0
    folds_worse: int = 0
    # set when the candidate was refitted through the twin (re-anchored), see diagnose(refine_top=...)
    delta_chi2_twin: float | None = None
    refined_state: ModelState | None = field(default=None, repr=False)

    @property
    def refined(self) -> bool:
        return self.delta_chi2_twin is not None

    @property
    def score(self) -> float:
        gain = self.delta_chi2_twin if self.delta_chi2_twin is not None else self.delta_chi2_all
        return gain / self.dispersion - self.penalty

    @property
    def heldout_confirms(self) -> bool:
        """The held-out folds do not contradict the candidate: it lowers the held-out chi-square
        in at least as many folds as it raises it.  Folds it leaves unchanged (its parameters,
        fitted with the offsets held, stay at their start) count for neither side."""
        return self.folds_total > 0 and self.folds_improved >= self.folds_worse

    def as_dict(self) -> dict:
        return {"name": self.name, "n_params": self.n_params, "values": self.values, "sigma": self.sigma,
                "delta_chi2_heldout": self.delta_chi2_heldout, "delta_chi2_all": self.delta_chi2_all,
                "penalty": self.penalty, "score": self.score, "significant": self.significant,
                "dispersion": self.dispersion, "folds_improved": self.folds_improved,
                "folds_worse": self.folds_worse, "folds_total": self.folds_total,
                "predicted_signature": self.predicted_signature, "delta_chi2_twin": self.delta_chi2_twin}


@dataclass
class Diagnosis:
    base_misfit: Misfit
    within_noise: bool
    candidates: list[Candidate]
    observed_signature: dict[str, float]
    folds: int
    n_traces: int = 0
    notes: list[str] = field(default_factory=list)

    @property
    def best(self) -> Candidate | None:
        sig = [c for c in self.candidates if c.significant]
        return sig[0] if sig else None

    @property
    def verdict(self) -> str:
        if self.best is None:
            if self.within_noise:
                return "no significant missing effect"
            # not the same message: the model is off, the candidates just cannot say why
            return (f"misfit beyond noise (chi2/dof = {self.base_misfit.chi2_reduced_total:.3g}) that no candidate "
                    "effect explains significantly")
        b = self.best
        vals = ", ".join(f"{k} = {v:.4g} ± {b.sigma.get(k, float('nan')):.2g}" for k, v in b.values.items())
        return f"missing effect: {b.name} ({vals})"

    def as_dict(self) -> dict:
        return {"verdict": self.verdict, "within_noise": self.within_noise,
                "base_misfit": self.base_misfit.as_dict(), "observed_signature": self.observed_signature,
                "candidates": [c.as_dict() for c in self.candidates], "folds": self.folds,
                "n_traces": self.n_traces, "notes": self.notes}


def _signature(h: np.ndarray, ref: np.ndarray, spec) -> dict[str, float]:
    """Mean over configurations of moments(h) - moments(ref), per axis."""
    out = {}
    # local-model predictions can dip below zero in empty bins: moments need counts >= 0
    h, ref = np.clip(h, 0, None), np.clip(ref, 0, None)
    for axis, sl, c in (("x", slice(0, 50), spec.centers_x), ("y", slice(50, 100), spec.centers_y)):
        a, b = moments(h[:, sl], c), moments(ref[:, sl], c)
        for k in a:
            out[f"{axis}.{k}"] = float(np.mean(a[k] - b[k]))
    return out


def _folds(n: int, k: int, seed: int) -> list[np.ndarray]:
    order = np.random.default_rng(seed).permutation(n)
    return [np.sort(order[i::k]) for i in range(k)]


def diagnose(meas: Measurement, state: ModelState, twin, forward_model, *,
             candidates: Sequence[str] | None = None, folds: int = 4, anchor_rays: int | None = None,
             seed: int = 0, n_sigma: float = 3.0, reuse=None, refine_top: int = 0, refine_iterations: int = 3,
             origin: ModelState | None = None, refresh_columns: Sequence[int] | None = None,
             table: ParameterTable = METRIXS) -> Diagnosis:
    """Rank candidate effects for the misfit of ``state`` against ``meas``.

    ``state`` should already carry fitted offsets (the finder's, refined by
    :func:`bluesky_offsets.model.refine`).  Candidates default to every registered
    effect the state does not include yet.  ``reuse`` takes the refinement's final
    local model (same state) so that its anchor and offset Jacobian are not traced again.

    ``refine_top`` > 0: when the base model is beyond noise, the best ``refine_top``
    candidates of the local ranking are refitted *through the twin* with the offsets
    (``refine_iterations`` re-anchored iterations, the offset Jacobian reused) and re-ranked
    by the twin's own chi-square improvement minus the parameter price (the ``refine_top``
    with the largest all-data gain of the local fit are chosen).  The local model is
    quadratic in each effect around zero; effects far from zero (a defocus of 20 mm) or
    strongly non-linear ones (an energy offset at the slit edge) are judged by the twin
    itself this way.  Their held-out test stays the local K-fold one.  The refits start
    from ``origin`` (default ``state``) with the effect absent, and an offsets-only refit
    with the same start and iterations is their reference, so a candidate is credited only
    with what it adds; it is significant when its gain beyond the parameter price exceeds
    ``n_sigma`` times the chi-square noise ``sqrt(2 dof)``.  If the reference itself reaches
    the noise, the verdict is "no significant missing effect"; a misfit beyond noise that no
    candidate explains is reported as such.
    ``refresh_columns`` are the offset columns differentiated afresh at every anchor
    (see :func:`bluesky_offsets.model.sensitive_columns`).  Cost:
    ``refine_top * refine_iterations * n (1 + len(refresh_columns) + 2 p)`` traces.
    """
    names = [n for n in (candidates or list(E.EFFECTS)) if n not in state.effects]
    anchor_rays = anchor_rays or (reuse.anchor_rays if reuse is not None else int(meas.n_rays))
    # one anchor for all candidates: every candidate effect at 0, probes one parameter at a time
    probe_state = state
    for n_ in names:
        probe_state = probe_state.with_effect(n_)
    lm_all = build_local_model(meas, probe_state, twin, forward_model, anchor_rays=anchor_rays, seed=seed,
                               reuse=reuse, table=table)
    n_twin_params = sum(len(E.get(n_).parameters) for n_ in names if E.get(n_).level == "twin")
    n_traces = meas.n * (2 * n_twin_params + (0 if reuse is not None else 1 + len(table)))
    m = np.concatenate([meas.hist_x, meas.hist_y], axis=1)
    base_mf = misfit(meas.hist_x, meas.hist_y, lm_all.t0[:, :50], lm_all.t0[:, 50:], meas.n_rays,
                     model_rays=anchor_rays)
    within = not base_mf.total_beyond_noise(n_sigma)

    # column bookkeeping: the state's own effects first, then each candidate's block
    own = len(state.effect_vector())
    blocks, col = {}, own
    for n_ in names:
        k = len(E.get(n_).parameters)
        blocks[n_] = np.arange(col, col + k)
        col += k

    def sub_model(extra_names: Sequence[str]) -> LocalModel:
        """The shared anchor seen by the state plus ``extra_names`` (their columns only)."""
        cols = [blocks[n_] for n_ in extra_names]
        keep = np.concatenate([np.arange(own), *cols]).astype(int)
        return LocalModel(_with(state, extra_names), lm_all.t0, lm_all.jac, lm_all.a[:, :, keep],
                          lm_all.b[:, :, keep], anchor_rays)

    fold_idx = _folds(meas.n, folds, seed)

    def shifted(lm: LocalModel, d_th: np.ndarray, d_own: np.ndarray) -> LocalModel:
        """``lm`` re-anchored (linearly) at offsets + ``d_th`` and the state's effects + ``d_own``."""
        d = np.concatenate([d_own, np.zeros(lm.a.shape[2] - own)])
        anchor = ModelState(lm.anchor.offsets + d_th, lm.anchor.set_effect_vector(lm.anchor.effect_vector() + d),
                            lm.anchor.label)
        return LocalModel(anchor, lm.predict(d_th, d), lm.jac, lm.a + 2 * lm.b * d[None, None, :], lm.b,
                          lm.anchor_rays)

    def heldout_chi2(lm: LocalModel, at: LocalFit) -> list[float]:
        # the effect's parameters fitted without each fold, the offsets held where the
        # offsets-only fit put them on all data: 34 offsets refitted to 3/4 of the
        # configurations extrapolate too wildly to the rest to judge one more parameter
        lm_s = shifted(lm, at.offsets - state.offsets, at.effects - state.effect_vector())
        return [fit_local(meas, lm_s, train=np.setdiff1d(np.arange(meas.n), f), heldout=f, free_offsets=False,
                          table=table).chi2_heldout for f in fold_idx]

    base_lm = sub_model([])
    base_fit = fit_local(meas, base_lm, table=table)
    base_all = base_fit.chi2_train
    base_ho = heldout_chi2(base_lm, base_fit)
    base_pred = base_lm.predict(base_fit.offsets - state.offsets, base_fit.effects - state.effect_vector())
    observed = _signature(m, base_pred, twin.hist)
    n_data = int(base_mf.dof_total)
    dispersion = max(1.0, base_all / max(n_data, 1))
    tol = [1e-9 * max(b_, 1.0) for b_ in base_ho]  # rounding, not evidence
    out = []
    for n_ in names:
        eff = E.get(n_)
        lm = sub_model([n_])
        # on all data the candidate starts where the offsets-only fit ended (nested: never worse)
        fit = fit_local(meas, lm, table=table, start=base_fit)
        chi_all = fit.chi2_train
        ho = heldout_chi2(lm, base_fit)
        improved = sum(b_ - c_ > t for b_, c_, t in zip(base_ho, ho, tol))
        worse = sum(c_ - b_ > t for b_, c_, t in zip(base_ho, ho, tol))
        p = len(eff.parameters)
        penalty = p * math.log(max(n_data, 2))
        d_ho, d_all = sum(base_ho) - sum(ho), base_all - chi_all
        phi0 = lm.anchor.effect_vector()
        pred = lm.predict(fit.offsets - state.offsets, fit.effects - phi0)
        vals = fit.effects[own:]
        sig = np.sqrt(np.clip(np.diag(fit.covariance)[-p:], 0, None))
        out.append(Candidate(
            n_, p, {q.name: float(v) for q, v in zip(eff.parameters, vals)},
            {q.name: float(s) for q, s in zip(eff.parameters, sig)}, float(d_ho), float(d_all), float(penalty),
            False, _signature(pred, base_pred, twin.hist), dispersion=dispersion,
            folds_improved=int(improved), folds_total=len(fold_idx), folds_worse=int(worse)))
        out[-1].significant = bool(not within and out[-1].score > 0 and out[-1].heldout_confirms)
    out.sort(key=lambda c: -c.score)
    refit_note = None
    if refine_top and not within:
        # the twin refits start from the same origin and get the same iterations as an
        # offsets-only refit beside them: a candidate is credited only with what it adds
        origin = origin if origin is not None else state
        common = dict(iterations=refine_iterations, anchor_rays=anchor_rays, offset_jacobian=lm_all.jac,
                      refresh_columns=refresh_columns, effect_step=0.1, table=table)
        ref = refine(meas, origin, twin, forward_model, seed=seed + 7919, **common)
        ref_chi2 = [h for h in ref.history if h["accepted"]][-1]["chi2"]
        ref_mf = _twin_chi2(meas, ref.local_model)
        n_traces += (refine_iterations + 1) * meas.n * (1 + len(refresh_columns or ()))
        if not ref_mf.total_beyond_noise(n_sigma):
            within = True  # the offsets alone reach the noise once refined further
        # a refit's chi-square carries the noise of its anchor: demand more than that
        threshold = n_sigma * math.sqrt(2 * max(ref_mf.dof_total, 1))
        chosen = sorted(out, key=lambda c: -(c.delta_chi2_all - c.penalty))[:refine_top]
        for i, cand in enumerate(chosen):
            if within or cand.delta_chi2_all - cand.penalty <= 0:
                continue  # no gain even on the data it is fitted to: not worth the traces
            res = refine(meas, origin.with_effect(cand.name), twin, forward_model, seed=seed + 7919 * (i + 2),
                         **common)
            accepted = [h for h in res.history if h["accepted"]]
            cand.delta_chi2_twin = float(ref_chi2 - accepted[-1]["chi2"])
            cand.values = {k: float(v) for k, v in res.state.effects[cand.name].items()}
            cand.sigma = dict(res.effect_sigma[cand.name])
            cand.refined_state = res.state
            cand.significant = bool(cand.significant and cand.delta_chi2_twin - cand.penalty > threshold)
            n_traces += (refine_iterations + 1) * meas.n * (1 + len(refresh_columns or ())
                                                            + 2 * len(E.get(cand.name).parameters))
        for cand in out:
            # only what the twin confirmed counts once refits are asked for
            cand.significant = bool(cand.significant and cand.refined and not within)
        refit_note = f"offsets-only twin refit: chi2/dof = {ref_mf.chi2_reduced_total:.2f}"
        out.sort(key=lambda c: (not c.refined, -c.score))
    notes = [refit_note] if refit_note else []
    if within:
        notes.append(f"the base model is within noise (chi2/dof = {base_mf.chi2_reduced_total:.2f})")
    return Diagnosis(base_mf, within, out, observed, folds, n_traces, notes)


# Lever arms that separate a screen translation from focal-length (half-axis) offsets: tilting
# E1/E2 changes where the beam meets the screen and how the focus is aberrated, which a focal
# length change does not (docs/diagnosis.md).  Normalized half-widths of the spread.
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
            raise ValueError(f"{name} is not motorized: it cannot be varied between configurations")
        z[:, i] = np.clip(base[i] + rng.uniform(-half, half, n), 0.0, 1.0)
    return np.where(table.motorized, table.denormalize(z), table.reference)


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
    label: str
    state: ModelState
    misfit: Misfit
    effect_sigma: dict[str, dict[str, float]] = field(default_factory=dict)

    def row(self) -> dict:
        return {"model": self.label, "chi2_reduced": self.misfit.chi2_reduced_total,
                "mse": self.misfit.mse_total, "expected_mse": self.misfit.expected_mse_total,
                "mse_over_noise": self.misfit.mse_total / max(self.misfit.expected_mse_total, 1e-300),
                "effects": {k: dict(v) for k, v in self.state.effects.items()},
                "effect_sigma": self.effect_sigma}


def evaluate(meas: Measurement, state: ModelState, twin, *, model_rays: int | None = None, seed: int = 777,
             table: ParameterTable = METRIXS) -> Misfit:
    """The twin at the model's compensated configurations vs. the measurement (fresh rays)."""
    model_rays = model_rays or 4 * int(meas.n_rays)  # a sharper model than the measurement
    hx, hy = simulate(twin, meas.configurations, state, model_rays, [seed + i for i in range(meas.n)], table)
    return misfit(meas.hist_x, meas.hist_y, hx, hy, meas.n_rays, model_rays=model_rays)


def add_effect(meas: Measurement, state: ModelState, name: str, twin, forward_model, *, iterations: int = 3,
               anchor_rays: int | None = None, seed: int = 0, progress=None, values=None,
               table: ParameterTable = METRIXS, **refine_kw) -> tuple[ModelState, dict[str, dict[str, float]]]:
    """``model.with_effect(name, values)`` and refit offsets + effect through the twin.

    ``values`` starts the effect where the diagnosis found it (a :class:`Candidate`'s
    ``values``), which saves iterations and keeps the fit in the right basin of effects whose
    response is symmetric about zero (a defocus).  Further keywords go to
    :func:`bluesky_offsets.model.refine` (``twin_columns``, ``reuse_jacobian``, ``effect_step``,
    ``offset_prior`` ...).  See :func:`add_effect_result` for the whole refinement.
    """
    res = add_effect_result(meas, state, name, twin, forward_model, iterations=iterations, anchor_rays=anchor_rays,
                            seed=seed, progress=progress, values=values, table=table, **refine_kw)
    return res.state, res.effect_sigma


def add_effect_result(meas: Measurement, state: ModelState, name: str, twin, forward_model, *,
                      iterations: int = 3, anchor_rays: int | None = None, seed: int = 0, progress=None,
                      values=None, table: ParameterTable = METRIXS, **refine_kw):
    """As :func:`add_effect`, returning the :class:`~bluesky_offsets.model.RefineResult`
    (state, effect uncertainties, iteration history, last local model)."""
    if values is not None and not isinstance(values, dict):
        values = getattr(values, "values", values)  # a Candidate
    return refine(meas, state.with_effect(name, values), twin, forward_model, iterations=iterations,
                  anchor_rays=anchor_rays, seed=seed, progress=progress, table=table, **refine_kw)


def plot_error_history(versions: Sequence[Version], path, title: str = "model error across versions"):
    from .plotting import _plt, save_figure
    plt = _plt()
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
    from .plotting import _plt, save_figure
    plt = _plt()
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
    ax0.set_xlabel("held-out Δχ² − p ln N")
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
