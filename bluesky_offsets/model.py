"""The calibrated beamline model: offsets + physical effects, fitted to measurements.

A :class:`ModelState` is what the model believes about the real beamline:
normalized offsets for the 34 parameters and the values of the physical
effects it includes.  :func:`simulate` traces it with the twin (RAYX) at the
commanded configurations of a :class:`Measurement`.

Fitting is *twin-anchored*: around the current state the histograms are
modelled as

    h_k(θ, φ) = T_k(θ0, φ0) + J_k (θ - θ0) + A_k (φ - φ0) + B_k (φ - φ0)²

with ``T_k`` the twin at configuration ``k`` (so the model is exact at the
anchor, whatever the surrogate's error), ``J_k`` the surrogate's Jacobian in
the offsets (the surrogate is differentiable and cheap), and ``A_k``, ``B_k``
the twin's response to each effect parameter from two extra traces per
configuration with common random numbers (seeded RAYX).  Gauss-Newton steps
on this local model, re-anchored with fresh twin traces, converge to a state
where the *twin* matches the measurement.  This is how an effect becomes a
real input of the fitted model without retraining the surrogate: its cost is
``2 p`` extra traces per configuration and iteration for ``p`` effect
parameters (see docs/diagnosis.md).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from . import effects as E
from .diagnostics import MeasurementError, Misfit, check_histograms, misfit
from .parameters import MAX_OFFSET, METRIXS, ParameterTable


# --------------------------------------------------------------------------- #
# data
# --------------------------------------------------------------------------- #
@dataclass
class Measurement:
    """Histograms measured at commanded configurations (absolute positions as the
    beamline's motors report them)."""

    configurations: np.ndarray   # (n, 34) physical
    hist_x: np.ndarray           # (n, 50) fraction of source rays
    hist_y: np.ndarray           # (n, 50)
    n_rays: int                  # source rays (ray budget) per measurement
    table_version: str = METRIXS.version
    uid: str | None = None

    def __post_init__(self):
        self.validate()

    def validate(self, table: ParameterTable = METRIXS) -> None:
        if self.table_version != table.version:
            raise MeasurementError(f"measurement was taken with parameter table {self.table_version}, "
                                   f"the model uses {table.version}")
        try:
            cfg = table.validate(self.configurations, "measured configurations")
        except ValueError as exc:
            raise MeasurementError(str(exc)) from None
        if cfg.ndim != 2:
            raise MeasurementError("configurations must be (n, 34)")
        hx, hy = check_histograms(self.hist_x, self.hist_y)
        if hx.shape[0] != cfg.shape[0]:
            raise MeasurementError(f"{cfg.shape[0]} configurations but {hx.shape[0]} histogram pairs")
        if int(self.n_rays) <= 0:
            raise MeasurementError("n_rays must be positive")
        self.configurations, self.hist_x, self.hist_y = cfg, hx, hy

    @classmethod
    def from_store(cls, m, n_rays: int | None = None, table: ParameterTable = METRIXS) -> Measurement:
        """From a run-store :class:`bluesky_offsets.store.Measurement` (ray budget from its
        metadata unless given)."""
        try:
            m.check_table(table)
        except ValueError as exc:
            raise MeasurementError(str(exc)) from None
        rays = n_rays or m.metadata.get("n_rays") or m.metadata.get("num_rays")
        if not rays:
            raise MeasurementError(f"measurement {m.uid or ''} does not say its ray budget; pass n_rays")
        return cls(m.configurations, m.hist_x, m.hist_y, int(rays), table.version, m.uid)

    @property
    def n(self) -> int:
        return len(self.configurations)

    def subset(self, idx) -> Measurement:
        return replace(self, configurations=self.configurations[idx], hist_x=self.hist_x[idx],
                       hist_y=self.hist_y[idx])


@dataclass
class ModelState:
    """Normalized offsets (fractions of each range) and included effects with values."""

    offsets: np.ndarray = field(default_factory=lambda: np.zeros(len(METRIXS)))
    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    label: str = "twin"

    def with_effect(self, name: str, values: Mapping[str, float] | None = None) -> ModelState:
        """A new model version that includes effect ``name`` (values default to 0 = absent)."""
        eff = E.get(name)
        if name in self.effects:
            raise ValueError(f"the model already includes {name!r}")
        return ModelState(self.offsets.copy(), {**self.effects, name: eff.values(values)},
                          f"{self.label} + {name}")

    def effect_vector(self) -> np.ndarray:
        return np.array([v for name in self.effects for v in self.effects[name].values()], dtype=float)

    def set_effect_vector(self, vec: np.ndarray) -> dict[str, dict[str, float]]:
        out, i = {}, 0
        for name, vals in self.effects.items():
            out[name] = {}
            for k in vals:
                out[name][k] = float(vec[i])
                i += 1
        return out

    def effect_parameters(self) -> list[tuple[str, E.EffectParameter]]:
        return [(name, p) for name in self.effects for p in E.get(name).parameters]


def _true_values(configurations, state: ModelState, table: ParameterTable) -> np.ndarray:
    return np.asarray(configurations) + table.offsets_to_physical(np.clip(state.offsets, -MAX_OFFSET, MAX_OFFSET))


def simulate_raw(twin, configurations: np.ndarray, state: ModelState, n_rays: int, seed=None,
                 table: ParameterTable = METRIXS) -> tuple[np.ndarray, np.ndarray]:
    """Twin histograms of ``state`` before detector-level effects."""
    twin_fx = {n: v for n, v in state.effects.items() if E.get(n).level == "twin"}
    res = twin.trace_batch(_true_values(configurations, state, table), overrides=E.twin_overrides(twin_fx),
                           n_rays=n_rays, seed=seed, progress=False, raise_on_error=True)
    return res.hist_x, res.hist_y


def detector_view(hx, hy, state: ModelState, spec):
    det = {n: v for n, v in state.effects.items() if E.get(n).level == "detector"}
    return E.apply_detector_effects(hx, hy, det, spec) if det else (hx, hy)


def simulate(twin, configurations: np.ndarray, state: ModelState, n_rays: int, seed=None,
             table: ParameterTable = METRIXS) -> tuple[np.ndarray, np.ndarray]:
    """Twin histograms of ``state`` at the commanded ``configurations`` (n, 34), as the
    focus chamber would record them (detector-level effects applied)."""
    hx, hy = simulate_raw(twin, configurations, state, n_rays, seed, table)
    return detector_view(hx, hy, state, twin.hist)


def surrogate_jacobian(forward_model, configurations: np.ndarray, offsets: np.ndarray,
                       table: ParameterTable = METRIXS) -> np.ndarray:
    """d histograms / d normalized offsets at each configuration: (n, 100, 34)."""
    import torch
    x = table.normalize(configurations) + np.clip(offsets, -MAX_OFFSET, MAX_OFFSET)
    dtype = next(iter(forward_model.parameters()), torch.zeros(())).dtype if hasattr(forward_model, "parameters") \
        else torch.float32
    xt = torch.as_tensor(x, dtype=dtype)
    jac = torch.func.vmap(torch.func.jacrev(lambda v: forward_model(v[None])[0]))(xt)
    return jac.detach().double().numpy()


# --------------------------------------------------------------------------- #
# the local model and its Gauss-Newton fit
# --------------------------------------------------------------------------- #
@dataclass
class LocalModel:
    """Histograms around an anchor state, linear in offsets, quadratic in effect parameters."""

    anchor: ModelState
    t0: np.ndarray            # (n, 100) twin at the anchor
    jac: np.ndarray           # (n, 100, 34) surrogate Jacobian in normalized offsets
    a: np.ndarray             # (n, 100, p) effect slopes
    b: np.ndarray             # (n, 100, p) effect curvatures
    anchor_rays: int
    raw: tuple[np.ndarray, np.ndarray] | None = None  # twin at the anchor before detector effects
    seed: int = 0

    def predict(self, d_offsets: np.ndarray, d_effects: np.ndarray, idx=slice(None)) -> np.ndarray:
        h = self.t0[idx] + np.einsum("nbk,k->nb", self.jac[idx], d_offsets)
        if d_effects.size:
            h = h + np.einsum("nbp,p->nb", self.a[idx], d_effects) \
                + np.einsum("nbp,p->nb", self.b[idx], d_effects ** 2)
        return h

    def design(self, d_effects: np.ndarray, idx=slice(None)) -> np.ndarray:
        """Jacobian of :meth:`predict` w.r.t. (offsets, effects): (n, 100, 34 + p)."""
        eff = self.a[idx] + 2 * self.b[idx] * d_effects[None, None, :] if d_effects.size else self.a[idx]
        return np.concatenate([self.jac[idx], eff], axis=2)


def twin_jacobian(twin, configurations: np.ndarray, state: ModelState, raw0, n_rays: int, seeds,
                  columns: Sequence[int], step: float = 0.002, table: ParameterTable = METRIXS) -> np.ndarray:
    """Finite-difference Jacobian of the twin's histograms in normalized offsets, (n, 100, 34),
    for ``columns`` (others zero).  Forward differences with the anchor's seeds: common random
    numbers cancel most of the ray noise."""
    n = len(configurations)
    t0 = np.concatenate(raw0, axis=1)
    jac = np.zeros((n, t0.shape[1], len(table)))
    cols = list(columns)
    if not cols:
        return jac
    batch = []
    for j in cols:
        off = state.offsets.copy()
        h = step if off[j] + step <= MAX_OFFSET else -step
        off[j] += h
        batch.append((j, h, ModelState(off, state.effects, state.label)))
    # one Dask batch for all columns
    vals = np.concatenate([_true_values(configurations, st, table) for _, _, st in batch])
    twin_fx = {k: v for k, v in state.effects.items() if E.get(k).level == "twin"}
    res = twin.trace_batch(vals, overrides=E.twin_overrides(twin_fx), n_rays=n_rays,
                           seed=list(seeds) * len(batch), progress=False, raise_on_error=True)
    hs = np.concatenate([res.hist_x, res.hist_y], axis=1).reshape(len(batch), n, -1)
    for (j, h, _), hj in zip(batch, hs):
        jac[:, :, j] = (hj - t0) / h
    return jac


def build_local_model(meas: Measurement, state: ModelState, twin, forward_model, *, anchor_rays: int,
                      seed: int = 0, twin_columns: Sequence[int] | None = None, reuse: LocalModel | None = None,
                      offset_jacobian: np.ndarray | None = None, effect_step: float = 0.25,
                      jacobian_rays: int | None = None, jacobian_step: float = 0.002,
                      anchor_raw: tuple[np.ndarray, np.ndarray] | None = None,
                      table: ParameterTable = METRIXS) -> LocalModel:
    """Trace the anchor and the effect responses; the offset Jacobian comes from the surrogate.

    Twin-level effect parameters cost two traces per configuration each (same seeds as
    the anchor: common random numbers make the differences smooth), probed at
    ``±effect_step`` of each parameter's prior range; detector-level ones are applied to the
    anchor's histograms and cost nothing.  ``offset_jacobian`` (n, 100, 34) is used as is
    instead of differentiating again (a Jacobian traced at a nearby state: it changes slowly,
    while the anchor carries the exact twin).  ``jacobian_rays`` (default: ``anchor_rays``)
    traces the twin's finite differences with fewer rays, against a base traced with those
    rays and the same seeds: the cost of a Jacobian is linear in rays, and Gauss-Newton
    needs its direction, not the anchor's precision (the anchor keeps ``anchor_rays``).
    """
    n = meas.n
    if reuse is not None:
        # same offsets and twin-level effects as a model already traced: reuse its anchor and Jacobian
        if not (np.array_equal(reuse.anchor.offsets, state.offsets) and reuse.raw is not None
                and reuse.anchor_rays == anchor_rays):
            raise ValueError("reuse: the local model was built for another state")
        seed = reuse.seed
    seeds = [seed + i for i in range(n)]
    if reuse is not None:
        raw = reuse.raw
    elif anchor_raw is not None:  # the anchor traced already, with these seeds and rays
        raw = anchor_raw
    else:
        raw = simulate_raw(twin, meas.configurations, state, anchor_rays, seeds, table)

    def view(st: ModelState, raw_h) -> np.ndarray:
        return np.concatenate(detector_view(*raw_h, st, twin.hist), axis=1)

    t0 = view(state, raw)
    if reuse is not None:
        jac = reuse.jac
        twin_columns = ()
    elif offset_jacobian is not None:
        # a Jacobian from before; only the ``twin_columns`` named are differentiated afresh
        jac = np.array(offset_jacobian, dtype=float)
        if jac.shape != (n, t0.shape[1], len(table)):
            raise ValueError(f"offset_jacobian must be {(n, t0.shape[1], len(table))}, got {jac.shape}")
        twin_columns = () if twin_columns is None else twin_columns
    elif forward_model is not None:
        jac = surrogate_jacobian(forward_model, meas.configurations, state.offsets, table)
    else:
        jac = np.zeros((n, t0.shape[1], len(table)))
        twin_columns = range(len(table)) if twin_columns is None else twin_columns
    if twin_columns:
        # columns the twin differentiates itself (before detector effects, which scale linearly)
        j_rays = int(jacobian_rays or anchor_rays)
        raw_j = raw if j_rays == anchor_rays else simulate_raw(twin, meas.configurations, state, j_rays, seeds, table)
        tj = twin_jacobian(twin, meas.configurations, state, raw_j, j_rays, seeds, twin_columns, step=jacobian_step,
                           table=table)
        for j in twin_columns:
            # detector effects are affine in the histograms: map the raw derivative through them
            jac[:, :, j] = view(state, (raw[0] + tj[:, :50, j], raw[1] + tj[:, 50:, j])) - t0
    params = state.effect_parameters()
    phi0 = state.effect_vector()
    a = np.zeros((n, t0.shape[1], len(params)))
    b = np.zeros_like(a)
    for j, (name, p) in enumerate(params):
        step = effect_step * p.span
        if phi0[j] - step < p.low - 1e-12:
            pts = (step, 2 * step)       # one-sided parameter at its lower bound
        elif phi0[j] + step > p.high + 1e-12:
            pts = (-2 * step, -step)
        else:
            pts = (-step, step)
        hs = []
        for d in pts:
            vec = phi0.copy()
            vec[j] += d
            probe = ModelState(state.offsets, state.set_effect_vector(vec), state.label)
            probe_raw = raw if E.get(name).level == "detector" else \
                simulate_raw(twin, meas.configurations, probe, anchor_rays, seeds, table)
            hs.append(view(probe, probe_raw))
        (d1, d2), (h1, h2) = pts, hs
        # h = t0 + a d + b d^2 through the two probes
        det = d1 * d2 * (d2 - d1)
        a[:, :, j] = ((h1 - t0) * d2 ** 2 - (h2 - t0) * d1 ** 2) / det
        b[:, :, j] = ((h2 - t0) * d1 - (h1 - t0) * d2) / det
    return LocalModel(state, t0, jac, a, b, anchor_rays, raw, seed)


@dataclass
class LocalFit:
    offsets: np.ndarray
    effects: np.ndarray
    chi2_train: float
    chi2_heldout: float
    dof_train: int
    dof_heldout: int
    covariance: np.ndarray   # of (offsets, effects) at the solution


def _weights(meas_h: np.ndarray, model_h: np.ndarray, n_rays: int, anchor_rays: int) -> tuple[np.ndarray, np.ndarray]:
    p = np.maximum(0.5 * (meas_h + model_h), 1.0 / n_rays)
    var = p * (1 - p) * (1.0 / n_rays + 1.0 / anchor_rays)
    signal = (meas_h > 0) | (model_h > 0)
    return np.where(signal, 1.0 / var, 0.0), signal


def fit_local(meas: Measurement, lm: LocalModel, *, train=None, heldout=None, offset_prior: float = 0.03,
              free_offsets: bool = True, iterations: int = 200, start: LocalFit | None = None,
              table: ParameterTable = METRIXS) -> LocalFit:
    """Weighted least squares on the local model, solved to convergence within the box.

    ``offset_prior`` (normalized units) keeps offset changes near the anchor where the
    linear model holds and tames the directions the data do not determine.  The bounded
    trust-region solver (scipy's ``least_squares``, ``trf``) converges to the local optimum
    whatever the start: a projected Levenberg-Marquardt loop stalled at the box and left
    the offsets-only fit unconverged, so a candidate effect started from it was credited
    with the offsets' continued convergence (an effect fitted at exactly zero "gained"
    hundreds in chi-square).  Nested models now gain >= 0 and an absent effect ~0.
    ``iterations`` bounds the solver's Jacobian evaluations (0: no fit, the
    covariance at the start).
    """
    from scipy.optimize import least_squares

    idx_all = np.arange(meas.n)
    train = idx_all if train is None else np.asarray(train)
    heldout = np.array([], dtype=int) if heldout is None else np.asarray(heldout)
    m = np.concatenate([meas.hist_x, meas.hist_y], axis=1)
    params = lm.anchor.effect_parameters()
    p = len(params)
    nt = len(table)
    k = nt if free_offsets else 0
    phi0 = lm.anchor.effect_vector()
    lo = np.concatenate([-MAX_OFFSET - lm.anchor.offsets if k else np.empty(0),
                         np.array([q.low for _, q in params]) - phi0])
    hi = np.concatenate([MAX_OFFSET - lm.anchor.offsets if k else np.empty(0),
                         np.array([q.high for _, q in params]) - phi0])
    # an anchor exactly on a bound leaves a zero-width interval, which the solver refuses
    hi = np.maximum(hi, lo + 1e-12)
    prior = np.concatenate([np.full(k, 1.0 / offset_prior ** 2),
                            np.array([1.0 / (10 * q.span) ** 2 for _, q in params])])
    w, sig = _weights(m[train], lm.t0[train], meas.n_rays, lm.anchor_rays)
    sw, sp = np.sqrt(w), np.sqrt(prior)
    keep = sw > 0

    def unpack(z):
        return (z[:k] if k else np.zeros(nt)), z[k:]

    def design(z):
        D = lm.design(unpack(z)[1], train)
        return D if k else D[:, :, nt:]

    def residuals(z):
        th, ph = unpack(z)
        r = sw * (m[train] - lm.predict(th, ph, train))
        return np.concatenate([r[keep], sp * z])

    def jacobian(z):
        D = design(z)
        return np.concatenate([-(sw[:, :, None] * D)[keep], np.diag(sp)])

    z = np.zeros(k + p)
    if start is not None:
        if k:
            z[:k] = start.offsets - lm.anchor.offsets
        q = min(p, len(start.effects))
        z[k:k + q] = start.effects[:q] - phi0[:q]
    z = np.clip(z, lo, hi)
    if iterations > 0 and z.size:
        sol = least_squares(residuals, z, jac=jacobian, bounds=(lo, hi), method="trf", x_scale="jac",
                            ftol=1e-10, xtol=1e-10, gtol=1e-10, max_nfev=iterations)
        z = np.clip(sol.x, lo, hi)
    th, ph = unpack(z)
    chi2_tr = float((w * (m[train] - lm.predict(th, ph, train)) ** 2).sum())
    chi2_ho, dof_ho = 0.0, 0
    if heldout.size:
        pred_ho = lm.predict(th, ph, heldout)
        w_ho, sig_ho = _weights(m[heldout], lm.t0[heldout], meas.n_rays, lm.anchor_rays)
        chi2_ho = float((w_ho * (m[heldout] - pred_ho) ** 2).sum())
        dof_ho = int(sig_ho.sum())
    D = design(z)
    H = np.einsum("nbi,nbj->ij", D * w[:, :, None], D) + np.diag(prior)
    cov = np.linalg.pinv(H)
    return LocalFit(lm.anchor.offsets + th, phi0 + ph, chi2_tr, chi2_ho, int(sig.sum()), dof_ho, cov)


def sensitive_columns(meas: Measurement, lm: LocalModel, top: int = 12) -> list[int]:
    """The ``top`` offset columns with the largest Fisher information (noise-weighted norm of
    their Jacobian column) at ``lm``'s anchor, most informative first."""
    m = np.concatenate([meas.hist_x, meas.hist_y], axis=1)
    w, _ = _weights(m, lm.t0, meas.n_rays, lm.anchor_rays)
    info = np.einsum("nbk,nb->k", lm.jac ** 2, w)
    return [int(i) for i in np.argsort(-info)[:top] if info[i] > 0]


@dataclass
class RefineResult:
    state: ModelState
    effect_sigma: dict[str, dict[str, float]]
    history: list[dict]
    local_model: LocalModel


def _twin_chi2(meas: Measurement, lm: LocalModel):
    return misfit(meas.hist_x, meas.hist_y, lm.t0[:, :50], lm.t0[:, 50:], meas.n_rays, model_rays=lm.anchor_rays)


def refine(meas: Measurement, state: ModelState, twin, forward_model, *, iterations: int = 4,
           anchor_rays: int | None = None, seed: int = 0, free_offsets: bool = True, offset_prior: float = 0.01,
           twin_columns: Sequence[int] | None = None, progress=None, reuse_jacobian: bool = False,
           effect_step: float = 0.25, start: LocalModel | None = None, sigma_offset_prior: float | None = None,
           offset_jacobian: np.ndarray | None = None, refresh_columns: Sequence[int] | None = None,
           refresh_on_reject: bool = False, jacobian_rays: int | None = None, jacobian_step: float = 0.002,
           paired: bool = True, step_factors: Sequence[float] = (1.0, 0.25, 0.0625),
           table: ParameterTable = METRIXS) -> RefineResult:
    """Fit offsets and the state's effects to ``meas`` by re-anchored Gauss-Newton through the twin.

    Each iteration solves the local problem, traces the twin at the proposed
    state and keeps it only if the twin's chi-square falls; the trust region
    on the offsets (``offset_prior``, normalized units) grows after a success
    and shrinks after a failure (Levenberg-Marquardt).  ``twin_columns``
    names offset parameters whose Jacobian the twin itself provides by finite
    differences (all of them when ``forward_model`` is None).

    ``reuse_jacobian`` keeps the first offset Jacobian for all iterations: each
    iteration then costs only the anchor and the effect probes (``n (1 + 2 p)``
    traces instead of ``n (35 + 2 p)``); the anchor is the exact twin, so the
    fixed point is the same, only the convergence is linear.  ``start`` is a local
    model already built for ``state`` (e.g. a refinement's last one) to begin from;
    ``offset_jacobian`` (n, 100, 34) one traced before at a nearby state, used throughout.
    ``refresh_columns`` (with a reused Jacobian) are differentiated afresh at every anchor:
    the few offsets that move the footprint across bins (see :func:`sensitive_columns`),
    whose derivative changes as the footprint moves, at ``n`` traces per column.
    ``refresh_on_reject`` (with a reused Jacobian): when the twin refuses a step, the whole
    offset Jacobian is differentiated afresh at the current state (the surrogate's, or the
    twin's for ``twin_columns``, all 34 without a surrogate: ``34 n`` traces) before the
    trust region shrinks — a stale Jacobian, not the step size, is
    then the likely cause; the fresh one is reused from there on.  Each anchor gets new
    ray seeds: the same seeds at every anchor measured worse (docs/diagnosis.md: the fit
    adapts to one ray sample).
    The reported effect uncertainties come from the Gauss-Newton covariance at the
    solution with the offsets free within the final trust region (default), or within
    ``sigma_offset_prior`` (normalized; e.g. ``MAX_OFFSET``, the physical prior), which lets
    correlations with poorly determined offsets widen them: the honest, larger number.
    ``jacobian_rays`` and ``jacobian_step`` set the twin's finite differences (see
    :func:`build_local_model`).  ``paired`` (default) judges a step against the current state
    traced with the proposal's own ray seeds (``n`` more traces per iteration) rather than
    against the current anchor's chi-square: that one is the minimum of noisy draws, and far
    from the noise floor a draw scatters by about ``2 sqrt(chi2)``.  ``step_factors`` scale
    the trust region into a ladder of steps per iteration, all traced with the same rays
    (``n`` traces each); the best is proposed, and a local model (Jacobian, effect probes)
    is built only for an accepted step.
    """
    anchor_rays = anchor_rays or int(meas.n_rays)
    jkw = {"jacobian_rays": jacobian_rays, "jacobian_step": jacobian_step}
    if start is not None:
        if not (np.array_equal(start.anchor.offsets, state.offsets) and start.anchor_rays == anchor_rays
                and start.anchor.effect_vector().size == state.effect_vector().size
                and np.allclose(start.anchor.effect_vector(), state.effect_vector())):
            raise ValueError("start: the local model was built for another state")
        lm = start
    else:
        lm = build_local_model(meas, state, twin, forward_model, anchor_rays=anchor_rays, seed=seed,
                               twin_columns=(refresh_columns or ()) if offset_jacobian is not None else twin_columns,
                               offset_jacobian=offset_jacobian, effect_step=effect_step, table=table, **jkw)
    jac = lm.jac if (reuse_jacobian or offset_jacobian is not None) else None

    mf = _twin_chi2(meas, lm)
    history = [{"iteration": 0, "accepted": True, "jacobian_refreshed": False, "chi2_reduced": mf.chi2_reduced_total,
                "mse": mf.mse_total,
                "chi2": mf.chi2_total, "dof": mf.dof_total,
                "effects": {k: dict(v) for k, v in state.effects.items()}}]
    if progress:
        progress(history[-1])
    current, prior = state, offset_prior
    # a Jacobian differentiated here for the start state is fresh; one handed in may be stale
    jac_fresh = jac is None or (start is None and offset_jacobian is None)

    def traced_chi2(st: ModelState, raw) -> Misfit:
        hx, hy = detector_view(*raw, st, twin.hist)
        return misfit(meas.hist_x, meas.hist_y, hx, hy, meas.n_rays, model_rays=anchor_rays)

    for it in range(1, iterations + 1):
        it_seed = seed + 1000 * it
        seeds_it = [it_seed + i for i in range(meas.n)]
        # a ladder of trust regions, each step traced with the same rays: the footprint spans
        # one or two bins, so how far the linear model holds changes from step to step
        priors = [prior * f for f in step_factors]
        proposals = []
        for pr_ in priors:
            fit = fit_local(meas, lm, offset_prior=pr_, free_offsets=free_offsets, table=table)
            proposals.append(ModelState(np.clip(fit.offsets, -MAX_OFFSET, MAX_OFFSET),
                                        current.set_effect_vector(fit.effects), current.label))
        raws = [simulate_raw(twin, meas.configurations, st, anchor_rays, seeds_it, table) for st in proposals]
        mfs = [traced_chi2(st, raw) for st, raw in zip(proposals, raws)]
        best = int(np.argmin([m_.chi2_total for m_ in mfs]))
        proposal, mf_p = proposals[best], mfs[best]
        if paired:
            # the current state with the proposals' rays: common random numbers make the
            # comparison sharp, and a current chi-square that won its own draw no longer
            # refuses every later step (the winner's curse stalled refinements at 16-19)
            chi2_ref = traced_chi2(current, simulate_raw(twin, meas.configurations, current, anchor_rays, seeds_it,
                                                         table)).chi2_total
        else:
            chi2_ref = mf.chi2_total
        accepted = mf_p.chi2_total < chi2_ref
        refreshed = False
        if accepted:
            lm = build_local_model(meas, proposal, twin, forward_model, anchor_rays=anchor_rays, seed=it_seed,
                                   anchor_raw=raws[best],
                                   twin_columns=(refresh_columns or ()) if jac is not None else twin_columns,
                                   offset_jacobian=jac, effect_step=effect_step, table=table, **jkw)
            current, mf = proposal, _twin_chi2(meas, lm)
            prior = min(priors[best] * 2.0, 0.05)
            jac_fresh = jac is None
        elif refresh_on_reject and not jac_fresh:
            # a new anchor with its own seeds and a full Jacobian there; it is the reference now
            lm = build_local_model(meas, current, twin, forward_model, anchor_rays=anchor_rays,
                                   seed=it_seed + 500, twin_columns=twin_columns,
                                   effect_step=effect_step, table=table, **jkw)
            mf, jac, jac_fresh, refreshed = _twin_chi2(meas, lm), lm.jac, True, True
        else:
            prior = min(priors) / 4.0
        history.append({"iteration": it, "accepted": bool(accepted), "jacobian_refreshed": refreshed,
                        "chi2_reduced": mf_p.chi2_reduced_total, "chi2_reference": float(chi2_ref),
                        "trust_region": float(priors[best]),
                        "mse": mf_p.mse_total, "chi2": mf_p.chi2_total, "dof": mf_p.dof_total,
                        "effects": {k: dict(v) for k, v in proposal.effects.items()}})
        if progress:
            progress(history[-1])
    # uncertainty of the effect parameters at the solution (local Gauss-Newton covariance)
    final = fit_local(meas, lm, offset_prior=sigma_offset_prior or prior, free_offsets=free_offsets, table=table,
                      iterations=0 if sigma_offset_prior else 1)
    p = len(current.effect_vector())
    sig = np.sqrt(np.clip(np.diag(final.covariance)[-p:], 0, None)) if p else np.array([])
    return RefineResult(current, current.set_effect_vector(sig), history, lm)
