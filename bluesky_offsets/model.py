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

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from . import effects as E
from .diagnostics import MeasurementError, Misfit, beam_features, check_histograms, misfit
from .parameters import MAX_OFFSET, METRIXS, ParameterTable
from .twin import HistogramSpec


# --------------------------------------------------------------------------- #
# data
# --------------------------------------------------------------------------- #
@dataclass
class Measurement:
    """Histograms measured at commanded configurations (absolute positions as the
    beamline's motors report them), binned as ``spec`` says (default: the paper's 50 x 50;
    the camera's own resolution, :data:`bluesky_offsets.twin.CAMERA`, where the detector
    gives it)."""

    configurations: np.ndarray   # (n, 34) physical
    hist_x: np.ndarray           # (n, spec.bins_x) fraction of source rays
    hist_y: np.ndarray           # (n, spec.bins_y)
    n_rays: int                  # source rays (ray budget) per measurement
    table_version: str = METRIXS.version
    uid: str | None = None
    spec: HistogramSpec = field(default_factory=HistogramSpec)

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
        hx, hy = check_histograms(self.hist_x, self.hist_y, self.spec.bins_x, self.spec.bins_y)
        if hx.shape[0] != cfg.shape[0]:
            raise MeasurementError(f"{cfg.shape[0]} configurations but {hx.shape[0]} histogram pairs")
        if int(self.n_rays) <= 0:
            raise MeasurementError("n_rays must be positive")
        self.configurations, self.hist_x, self.hist_y = cfg, hx, hy

    @classmethod
    def from_store(cls, m, n_rays: int | None = None, table: ParameterTable = METRIXS,
                   resolution: str = "camera") -> Measurement:
        """From a run-store :class:`bluesky_offsets.store.Measurement` (ray budget from its
        metadata unless given).  ``resolution="camera"`` takes the camera-resolution profiles
        where the run has them (the paper's histograms otherwise); ``"paper"`` the 50 x 50 ones."""
        try:
            m.check_table(table)
        except ValueError as exc:
            raise MeasurementError(str(exc)) from None
        if resolution not in ("camera", "paper"):
            raise ValueError(f"resolution must be 'camera' or 'paper', not {resolution!r}")
        rays = n_rays or m.metadata.get("n_rays") or m.metadata.get("num_rays")
        if not rays:
            raise MeasurementError(f"measurement {m.uid or ''} does not say its ray budget; pass n_rays")
        if resolution == "camera" and getattr(m, "profile_x", None) is not None:
            return cls(m.configurations, m.profile_x, m.profile_y, int(rays), table.version, m.uid, m.profile_spec)
        return cls(m.configurations, m.hist_x, m.hist_y, int(rays), table.version, m.uid)

    @property
    def bins_x(self) -> int:
        return self.spec.bins_x

    def histograms(self) -> np.ndarray:
        """(n, bins_x + bins_y): x then y."""
        return np.concatenate([self.hist_x, self.hist_y], axis=1)

    def rebinned(self, coarse: HistogramSpec) -> Measurement:
        """The same measurement in coarser bins (e.g. the paper's, for the surrogate)."""
        hx, hy = self.spec.rebin(self.hist_x, self.hist_y, coarse)
        return replace(self, hist_x=hx, hist_y=hy, spec=coarse)

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


def solve_normal(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x = b`` for the fits' normal equations; least squares where ``a`` is singular (a
    Jacobian with no information on some direction, e.g. all zero: measured as a 'Singular
    matrix' failure of the diagnose command)."""
    try:
        return np.linalg.solve(a, b)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(a, b, rcond=None)[0]


def _true_values(configurations, state: ModelState, table: ParameterTable) -> np.ndarray:
    return np.asarray(configurations) + table.offsets_to_physical(np.clip(state.offsets, -MAX_OFFSET, MAX_OFFSET))


def _twin_overrides(state: ModelState) -> dict:
    """RML overrides of the state's twin-level effects (detector-level ones act on histograms)."""
    return E.twin_overrides({n: v for n, v in state.effects.items() if E.get(n).level == "twin"})


def simulate_raw(twin, configurations: np.ndarray, state: ModelState, n_rays: int, seed=None,
                 table: ParameterTable = METRIXS) -> tuple[np.ndarray, np.ndarray]:
    """Twin histograms of ``state`` before detector-level effects."""
    res = twin.trace_batch(_true_values(configurations, state, table), overrides=_twin_overrides(state),
                           n_rays=n_rays, seed=seed, progress=False, raise_on_error=True)
    return res.hist_x, res.hist_y


def simulate_raw_many(twin, configurations: np.ndarray, states: Sequence[ModelState], n_rays: int, seeds,
                      table: ParameterTable = METRIXS) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`simulate_raw` for several states at the same configurations and seeds, in one
    batch (the workers stay busy; common random numbers make the states comparable)."""
    n = len(configurations)
    if not states:
        return []
    vals = np.concatenate([_true_values(configurations, st, table) for st in states])
    ovs = [_twin_overrides(st) for st in states for _ in range(n)]
    res = twin.trace_batch(vals, overrides=ovs, n_rays=n_rays, seed=list(seeds) * len(states), progress=False,
                           raise_on_error=True)
    hx, hy = res.hist_x, res.hist_y
    return [(hx[i * n:(i + 1) * n], hy[i * n:(i + 1) * n]) for i in range(len(states))]


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
    """d histograms / d normalized offsets at each configuration: (n, bins, 34)."""
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
    t0: np.ndarray            # (n, bins) twin at the anchor
    jac: np.ndarray           # (n, bins, 34) surrogate Jacobian in normalized offsets
    a: np.ndarray             # (n, bins, p) effect slopes
    b: np.ndarray             # (n, bins, p) effect curvatures
    anchor_rays: int
    raw: tuple[np.ndarray, np.ndarray] | None = None  # twin at the anchor before detector effects
    seed: int = 0
    bins_x: int = 50          # x bins, then y bins, along axis 1
    jac_at_anchor: bool = True  # False: (part of) ``jac`` was traced at an earlier state

    def split(self, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return h[..., :self.bins_x], h[..., self.bins_x:]

    def predict(self, d_offsets: np.ndarray, d_effects: np.ndarray, idx=slice(None)) -> np.ndarray:
        h = self.t0[idx] + np.einsum("nbk,k->nb", self.jac[idx], d_offsets)
        if d_effects.size:
            h = h + np.einsum("nbp,p->nb", self.a[idx], d_effects) \
                + np.einsum("nbp,p->nb", self.b[idx], d_effects ** 2)
        return h

    def design(self, d_effects: np.ndarray, idx=slice(None)) -> np.ndarray:
        """Jacobian of :meth:`predict` w.r.t. (offsets, effects): (n, bins, 34 + p)."""
        eff = self.a[idx] + 2 * self.b[idx] * d_effects[None, None, :] if d_effects.size else self.a[idx]
        return np.concatenate([self.jac[idx], eff], axis=2)


def check_twin(meas: Measurement, twin) -> None:
    """The twin must bin its histograms as the measurement is binned."""
    if twin.hist != meas.spec:
        raise ValueError(f"the twin bins its histograms as {twin.hist.fingerprint()}, the measurement as "
                         f"{meas.spec.fingerprint()}: use twin.with_hist(measurement.spec)")


def twin_jacobian(twin, configurations: np.ndarray, state: ModelState, raw0, n_rays: int, seeds,
                  columns: Sequence[int], step: float = 0.002, table: ParameterTable = METRIXS) -> np.ndarray:
    """Finite-difference Jacobian of the twin's histograms in normalized offsets, (n, bins, 34),
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
    res = twin.trace_batch(vals, overrides=_twin_overrides(state), n_rays=n_rays,
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
    anchor's histograms and cost nothing.  ``offset_jacobian`` (n, bins, 34) is used as is
    instead of differentiating again (a Jacobian traced at a nearby state: it changes slowly,
    while the anchor carries the exact twin).  ``jacobian_rays`` (default: ``anchor_rays``)
    traces the twin's finite differences with fewer rays, against a base traced with those
    rays and the same seeds: the cost of a Jacobian is linear in rays, and Gauss-Newton
    needs its direction, not the anchor's precision (the anchor keeps ``anchor_rays``).
    """
    check_twin(meas, twin)
    n, nx = meas.n, meas.bins_x
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
    at_anchor = True
    if reuse is not None:
        jac = reuse.jac
        twin_columns = ()
        at_anchor = reuse.jac_at_anchor
    elif offset_jacobian is not None:
        # a Jacobian from before; only the ``twin_columns`` named are differentiated afresh
        jac = np.array(offset_jacobian, dtype=float)
        if jac.shape != (n, t0.shape[1], len(table)):
            raise ValueError(f"offset_jacobian must be {(n, t0.shape[1], len(table))}, got {jac.shape}")
        twin_columns = () if twin_columns is None else twin_columns
        at_anchor = len(set(twin_columns)) == len(table)
    elif forward_model is not None:
        jac = surrogate_jacobian(forward_model, meas.configurations, state.offsets, table)
        if jac.shape[1] != t0.shape[1]:
            raise ValueError(f"the surrogate predicts {jac.shape[1]} bins per configuration, the measurement has "
                             f"{t0.shape[1]}: use the twin's Jacobian (forward_model=None) or the paper's binning "
                             "(Measurement.rebinned / resolution='paper')")
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
            jac[:, :, j] = view(state, (raw[0] + tj[:, :nx, j], raw[1] + tj[:, nx:, j])) - t0
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
    return LocalModel(state, t0, jac, a, b, anchor_rays, raw, seed, nx, at_anchor)


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


@dataclass
class FeatureFit:
    """Result of :func:`fit_features` / :func:`fit_features_many`."""

    state: ModelState
    history: list[dict]
    jacobian: np.ndarray | None          # the twin's bin Jacobian in the offsets, last traced (n, bins, 34)
    jacobian_state: ModelState | None    # where it was traced
    columns: np.ndarray | None = field(default=None, repr=False)  # feature Jacobian at the end (n, 5, P + p)
    raw: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)  # the last anchor
    seeds: list[int] | None = field(default=None, repr=False)

    @property
    def chi2(self) -> float:
        """Bins χ² at the last anchor."""
        return float(self.history[-1]["chi2"])

    @property
    def chi2_features(self) -> float:
        return float(self.history[-1]["chi2_features"])


class _Features:
    """The beam features of a measurement and of twin traces, and their Jacobian (shared by the
    feature fits)."""

    def __init__(self, meas: Measurement, twin, rays: int, jacobian_step: float, effect_step: float,
                 table: ParameterTable):
        self.meas, self.twin, self.rays, self.table = meas, twin, rays, table
        self.jacobian_step, self.effect_step = jacobian_step, effect_step
        self.fm, self.vm = beam_features(meas.hist_x, meas.hist_y, meas.spec, meas.n_rays)
        self.P = len(table)

    def seeds(self, s: int) -> list[int]:
        return [s + i for i in range(self.meas.n)]

    def of(self, st: ModelState, raw) -> tuple[np.ndarray, np.ndarray]:
        return beam_features(*detector_view(*raw, st, self.twin.hist), self.meas.spec, self.rays)

    def chi2(self, f, v, z=None, ridge=None) -> float:
        penalty = 0.0 if z is None or ridge is None else float((ridge * z * z).sum())
        return float(((self.fm - f) ** 2 / (self.vm + v)).sum()) + penalty

    def bins(self, st: ModelState, raw) -> dict:
        # the anchors are whole histograms: their bin misfit comes for free
        m = self.meas
        mf = misfit(m.hist_x, m.hist_y, *detector_view(*raw, st, self.twin.hist), m.n_rays, model_rays=self.rays)
        return {"chi2_reduced": mf.chi2_reduced_total, "chi2": mf.chi2_total, "dof": mf.dof_total,
                "mse": mf.mse_total, "chi2_reference": float("nan"), "trust_region": float("nan")}

    @staticmethod
    def vector(st: ModelState) -> np.ndarray:
        return np.r_[st.offsets, st.effect_vector()]

    @staticmethod
    def bounds(st: ModelState) -> tuple[np.ndarray, np.ndarray]:
        params = st.effect_parameters()
        P = len(st.offsets)
        return (np.r_[np.full(P, -MAX_OFFSET), [q.low for _, q in params]],
                np.r_[np.full(P, MAX_OFFSET), [q.high for _, q in params]])

    def probes(self, st: ModelState) -> list[tuple[float, ModelState]]:
        """One forward probe per effect parameter (backwards at its upper bound)."""
        z0, out = self.vector(st), []
        for k, (_, q) in enumerate(st.effect_parameters()):
            d = self.effect_step * q.span * (1 if z0[self.P + k] + self.effect_step * q.span <= q.high else -1)
            z = z0.copy()
            z[self.P + k] += d
            out.append((d, ModelState(z[:self.P].copy(), st.set_effect_vector(z[self.P:]), st.label)))
        return out

    def offset_columns(self, st: ModelState, raw, f0, jac) -> np.ndarray:
        """Feature Jacobian in the offsets (n, 5, P), through the bin Jacobian ``jac``."""
        nx, h = self.meas.bins_x, self.jacobian_step
        G = np.zeros((*f0.shape, self.P))
        for j in range(self.P):
            if jac[:, :, j].any():
                bumped = (raw[0] + h * jac[:, :nx, j], raw[1] + h * jac[:, nx:, j])
                G[:, :, j] = (self.of(st, bumped)[0] - f0) / h
        return G

    def effect_columns(self, st: ModelState, raw, f0, probe_raws) -> np.ndarray:
        """Feature Jacobian in the effect parameters (n, 5, p), from their probes (traced with
        the anchor's rays, or none for detector effects)."""
        params = st.effect_parameters()
        G = np.zeros((*f0.shape, len(params)))
        for k, ((d, probe), (name, _)) in enumerate(zip(self.probes(st), params)):
            praw = raw if E.get(name).level == "detector" else probe_raws[k]
            G[:, :, k] = (self.of(probe, praw)[0] - f0) / d
        return G

    def columns(self, st: ModelState, raw, f0, jac, probe_raws) -> np.ndarray:
        """Feature Jacobian (n, 5, P + p) at ``st``: offsets, then effect parameters."""
        return np.concatenate([self.offset_columns(st, raw, f0, jac),
                               self.effect_columns(st, raw, f0, probe_raws)], axis=2)

    def trace_probes(self, states: Sequence[ModelState], seeds) -> list[list]:
        """Raw traces of every twin-level probe of every state, in one batch."""
        todo = [(i, k, pr) for i, st in enumerate(states)
                for k, ((_, pr), (name, _)) in enumerate(zip(self.probes(st), st.effect_parameters()))
                if E.get(name).level == "twin"]
        raws = simulate_raw_many(self.twin, self.meas.configurations, [pr for _, _, pr in todo], self.rays, seeds,
                                 self.table)
        out = [[None] * len(st.effect_parameters()) for st in states]
        for (i, k, _), r in zip(todo, raws):
            out[i][k] = r
        return out

    def step(self, G, f0, v0, z0, lam: float, ridge) -> np.ndarray:
        """A Levenberg-Marquardt step on the features (Marquardt's scaling)."""
        w = (1.0 / (self.vm + v0)).reshape(-1)
        Gf = G.reshape(-1, G.shape[2])
        A = Gf.T @ (Gf * w[:, None]) + np.diag(ridge)
        g = Gf.T @ (w * (self.fm - f0).reshape(-1)) - ridge * z0
        # the small ridge keeps parameters the features do not see in place
        d = solve_normal(A + lam * np.diag(np.diag(A)) + 1e-9 * np.trace(A) / len(A) * np.eye(len(A)), g)
        return d if np.all(np.isfinite(d)) else np.zeros_like(z0)


def _feature_noise_limit(n_features: int, n_sigma: float) -> float:
    """Feature χ² a correct model stays below: its expectation plus ``n_sigma`` σ."""
    return n_features + n_sigma * math.sqrt(2 * n_features)


def fit_features(meas: Measurement, state: ModelState, twin, *, iterations: int = 8, anchor_rays: int | None = None,
                 seed: int = 0, jacobian_step: float = 0.005, effect_step: float = 0.05, damping: float = 1.0,
                 offset_jacobian: np.ndarray | None = None, progress=None, n_sigma: float = 3.0,
                 prior_sigma: float | None = None, jacobian_rays: int | None = None,
                 table: ParameterTable = METRIXS) -> FeatureFit:
    """Fit the offsets (and the state's effects) to the beam's intensity, centroids and widths
    (:func:`bluesky_offsets.diagnostics.beam_features`) through the twin.

    The first stage of a fit: these five numbers per configuration respond smoothly and
    almost linearly to the offsets over many spot widths, while bin contents of a focus a
    few bins wide are steep steps, so a fit on bins only converges from close by (measured:
    from the nominal twin, bins χ²/dof 40 -> 18 in 8 Gauss-Newton iterations, features ->
    1.0 in 4; docs/diagnosis.md).  Levenberg-Marquardt on the features with Marquardt's
    scaling; the offset Jacobian is the twin's (finite differences with common random
    numbers, ``34 n`` traces), traced once and reused at later anchors until a step is
    refused after the fit has moved on; effect parameters are differentiated at every anchor
    (``n`` traces each, step ``effect_step`` of their prior range).  Each proposal is judged
    against the current state traced with the proposal's rays (``2 n`` traces).  Stops after
    ``iterations`` or once the features fit within noise (χ² below its expectation +
    ``n_sigma`` σ).  ``prior_sigma`` adds a Gaussian prior on the offsets (normalized units).
    ``jacobian_rays`` (default ``anchor_rays``) traces the offset Jacobian with fewer rays:
    with common random numbers every ray moves smoothly, so centroids and widths differentiate
    cleanly from a few thousand rays, and the Jacobian is most of a fit's cost.
    """
    check_twin(meas, twin)
    rays = int(anchor_rays or meas.n_rays)
    fx = _Features(meas, twin, rays, jacobian_step, effect_step, table)
    cfg, n, P = meas.configurations, meas.n, len(table)
    lo, hi = fx.bounds(state)
    limit = _feature_noise_limit(fx.fm.size, n_sigma)
    ridge = np.r_[np.full(P, 0.0 if prior_sigma is None else prior_sigma ** -2.0),
                  np.zeros(len(state.effect_parameters()))]

    def state_of(z):
        return ModelState(z[:P].copy(), state.set_effect_vector(z[P:]), state.label)

    s, cur = seed, state
    raw = simulate_raw(twin, cfg, cur, rays, fx.seeds(s), table)
    f0, v0 = fx.of(cur, raw)
    jac, jac_state, fresh = offset_jacobian, None, False
    # moved: steps accepted since the Jacobian was traced (one handed in may be from elsewhere)
    lam, moved = damping, 0 if offset_jacobian is None else 2
    G = last = None
    history = [{"stage": "features", "iteration": 0, "accepted": True, "jacobian_refreshed": False,
                "chi2_features": fx.chi2(f0, v0), "features": fx.fm.size, "damping": lam, **fx.bins(cur, raw),
                "effects": {k: dict(v) for k, v in cur.effects.items()}}]
    if progress:
        progress(history[-1])
    for it in range(1, iterations + 1):
        if history[-1]["chi2_features"] <= limit or lam > 1e3 * damping:
            break  # within noise, or five refusals in a row on a fresh Jacobian: no step left to try
        refreshed = False
        if jac is None:
            j_rays = int(jacobian_rays or rays)
            raw_j = raw if j_rays == rays else simulate_raw(twin, cfg, cur, j_rays, fx.seeds(s), table)
            jac = twin_jacobian(twin, cfg, cur, raw_j, j_rays, fx.seeds(s), range(P), step=jacobian_step, table=table)
            jac_state, fresh, refreshed = cur, True, True
        G = fx.columns(cur, raw, f0, jac, fx.trace_probes([cur], fx.seeds(s))[0])
        z0 = fx.vector(cur)
        step = fx.step(G, f0, v0, z0, lam, ridge)
        cand = state_of(np.clip(z0 + step, lo, hi))
        s2 = seed + 1000 * it
        raw_c, raw_r = simulate_raw_many(twin, cfg, [cand, cur], rays, fx.seeds(s2), table)
        (fc, vc), (fr, vr) = fx.of(cand, raw_c), fx.of(cur, raw_r)
        cc, cr = fx.chi2(fc, vc, fx.vector(cand), ridge), fx.chi2(fr, vr, z0, ridge)
        accepted = bool(cc < cr) and bool(step.any())
        if accepted:
            cur, raw, f0, v0, s = cand, raw_c, fc, vc, s2
            lam, fresh = max(lam / 3, 1e-6), False
            moved += 1
        else:
            raw, f0, v0, s = raw_r, fr, vr, s2  # the current state, freshly traced: the next anchor
            if fresh or moved < 2 or cr < 1.2 * limit:
                # near the noise a refusal is mostly noise, and a Jacobian a step or two old is
                # not stale: a fresh one (34 n traces) would not help
                lam *= 4
            else:
                last, jac, moved = jac, None, 0  # a stale Jacobian is the first suspect: trace it afresh next
        history.append({"stage": "features", "iteration": it, "accepted": accepted,
                        "jacobian_refreshed": refreshed, "chi2_features": cc if accepted else cr,
                        "features": fx.fm.size, "damping": lam, **fx.bins(cur, raw),
                        "effects": {k: dict(v) for k, v in cur.effects.items()}})
        if progress:
            progress(history[-1])
    return FeatureFit(cur, history, jac if jac is not None else last, jac_state, G, raw, fx.seeds(s))


def fit_features_many(meas: Measurement, states: Sequence[ModelState], twin, offset_jacobian: np.ndarray, *,
                      iterations: int = 5, rays: int | None = None, seed: int = 0, jacobian_step: float = 0.005,
                      effect_step: float = 0.1, damping: float = 1.0, directions: int = 12,
                      table: ParameterTable = METRIXS) -> list[FeatureFit]:
    """:func:`fit_features` for many states side by side — the candidate models of a diagnosis.

    The offsets move in the ``directions`` combinations the beam features respond to most at
    ``states[0]`` (principal directions of its noise-weighted feature Jacobian, from
    ``offset_jacobian``).  The derivatives along them are traced where each fit starts
    (``directions * n`` traces; states that differ from ``states[0]`` only at the detector
    share its): an effect such as a defocus changes how the features respond to the offsets,
    and a fit on the old Jacobian stalls (measured: chamber_z from 16.5 mm, feature χ² stuck at
    3700 until the Jacobian was traced at the defocused state, then 470 with z = 20.5 mm).
    All fits share one set of
    rays (the same seeds at every anchor), so their χ² compare sharply with each other and a
    step is judged against the current anchor without a second trace; each iteration traces
    every fit's proposal and effect probes in one batch (``n (1 + p)`` traces per fit for
    ``p`` twin-level effect parameters).
    """
    check_twin(meas, twin)
    rays = int(rays or meas.n_rays)
    fx = _Features(meas, twin, rays, jacobian_step, effect_step, table)
    cfg, P, h = meas.configurations, len(table), jacobian_step
    seeds = fx.seeds(seed)
    cur = list(states)
    raws = simulate_raw_many(twin, cfg, cur, rays, seeds, table)
    fs = [fx.of(st, r) for st, r in zip(cur, raws)]

    G0 = fx.offset_columns(cur[0], raws[0], fs[0][0], offset_jacobian)
    sw = np.sqrt(1.0 / (fx.vm + fs[0][1])).reshape(-1)
    U = np.linalg.svd(G0.reshape(-1, P) * sw[:, None], full_matrices=False)[2][:directions].T  # (P, r)
    # derivatives along the directions, traced where each fit starts (one batch): the first
    # state's serve every state that differs from it only at the detector.  All fits get fresh
    # ones alike: a fit on a fresher Jacobian than its reference would be credited with the
    # offsets' further convergence (measured: chamber_x at x = 0 "gained" 380)
    r = U.shape[1]
    own = [k == 0 or any(E.get(e).level == "twin" for e in st.effects if e not in states[0].effects)
           for k, st in enumerate(cur)]
    bumped = [ModelState(st.offsets + h * U[:, k], st.effects, st.label)
              for st, o in zip(cur, own) if o for k in range(r)]
    braws = simulate_raw_many(twin, cfg, bumped, rays, seeds, table)
    by_state, i = [], 0
    for o in own:
        by_state.append(braws[i:i + r] if o else None)
        i += r if o else 0
    Goff = []
    for st, (f0, _), b in zip(cur, fs, by_state):
        b = b if b is not None else by_state[0]
        Goff.append(np.stack([(fx.of(st, b[k])[0] - f0) / h for k in range(r)], axis=-1))
    lams = [damping] * len(cur)
    hist = [[{"stage": "features", "iteration": 0, "accepted": True, "chi2_features": fx.chi2(*f), **fx.bins(st, rr),
              "effects": {k: dict(v) for k, v in st.effects.items()}}] for st, rr, f in zip(cur, raws, fs)]
    cols = [None] * len(cur)
    for it in range(1, iterations + 1):
        probe_raws = fx.trace_probes(cur, seeds)
        cands = []
        for i, st in enumerate(cur):
            Ge = fx.effect_columns(st, raws[i], fs[i][0], probe_raws[i])
            cols[i] = np.concatenate([Goff[i] @ U.T, Ge], axis=2)  # back in offset coordinates
            za = np.r_[np.zeros(r), st.effect_vector()]
            step = fx.step(np.concatenate([Goff[i], Ge], axis=2), fs[i][0], fs[i][1], za, lams[i], np.zeros_like(za))
            lo, hi = fx.bounds(st)
            zz = np.clip(np.r_[st.offsets + U @ step[:r], st.effect_vector() + step[r:]], lo, hi)
            cands.append(ModelState(zz[:P].copy(), st.set_effect_vector(zz[P:]), st.label))
        craws = simulate_raw_many(twin, cfg, cands, rays, seeds, table)
        for i, (c, rr) in enumerate(zip(cands, craws)):
            fc = fx.of(c, rr)
            ok = fx.chi2(*fc) < fx.chi2(*fs[i])
            if ok:
                cur[i], raws[i], fs[i], lams[i] = c, rr, fc, max(lams[i] / 3, 1e-6)
            else:
                lams[i] *= 4
            hist[i].append({"stage": "features", "iteration": it, "accepted": bool(ok),
                            "chi2_features": fx.chi2(*fs[i]), **fx.bins(cur[i], raws[i]),
                            "effects": {k: dict(v) for k, v in cur[i].effects.items()}})
    return [FeatureFit(st, hh, offset_jacobian, None, G, rr, seeds) for st, hh, G, rr in zip(cur, hist, cols, raws)]


def _twin_chi2(meas: Measurement, lm: LocalModel):
    return misfit(meas.hist_x, meas.hist_y, *lm.split(lm.t0), meas.n_rays, model_rays=lm.anchor_rays)


def refine(meas: Measurement, state: ModelState, twin, forward_model, *, iterations: int = 4,
           anchor_rays: int | None = None, seed: int = 0, free_offsets: bool = True, offset_prior: float = 0.01,
           twin_columns: Sequence[int] | None = None, progress=None, reuse_jacobian: bool = False,
           effect_step: float = 0.25, start: LocalModel | None = None, sigma_offset_prior: float | None = None,
           offset_jacobian: np.ndarray | None = None, refresh_columns: Sequence[int] | None = None,
           refresh_on_reject: bool = False, jacobian_rays: int | None = None, jacobian_step: float = 0.002,
           paired: bool = True, step_factors: Sequence[float] = (1.0, 0.25, 0.0625),
           feature_iterations: int = 0, feature_kw: Mapping | None = None, also_from: Sequence = (),
           also_from_beyond_noise: bool = False, max_refreshes: int | None = None,
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
    ``offset_jacobian`` (n, bins, 34) one traced before at a nearby state, used throughout.
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
    ``max_refreshes`` bounds the Jacobians ``refresh_on_reject`` traces (``34 n`` traces each).
    ``jacobian_rays`` and ``jacobian_step`` set the twin's finite differences (see
    :func:`build_local_model`).  ``paired`` (default) judges a step against the current state
    traced with the proposal's own ray seeds (``n`` more traces per iteration) rather than
    against the current anchor's chi-square: that one is the minimum of noisy draws, and far
    from the noise floor a draw scatters by about ``2 sqrt(chi2)``.  ``step_factors`` scale
    the trust region into a ladder of steps per iteration, all traced with the same rays
    (``n`` traces each); the best is proposed, and a local model (Jacobian, effect probes)
    is built only for an accepted step.
    ``feature_iterations`` > 0 first fits the beam features (intensity, centroids, widths) with
    :func:`fit_features` (options in ``feature_kw``), whose wide basin brings the state close
    enough for the bins; its twin Jacobian then starts this fit (with a surrogate as
    ``forward_model``, the surrogate's is used).  The history holds both stages (``"stage"``).
    ``also_from`` (offset vectors or states) are further starts of the feature stage, sharing
    its first Jacobian; the one whose bins fit best at the end of it goes on (a solution of
    the surrogate on the paper's coarse histograms can sit in a basin of compensating offsets
    that the camera's resolution tells apart: measured, features from there ended at bins
    χ²/dof 1.4, from the nominal twin at 1.0; docs/diagnosis.md).  ``also_from_beyond_noise``
    tries them only when the first start's features did not reach the noise.
    """
    check_twin(meas, twin)
    anchor_rays = anchor_rays or int(meas.n_rays)
    history: list[dict] = []
    if feature_iterations:
        if start is not None:
            raise ValueError("refine: start= and feature_iterations= exclude each other")
        fkw = {"iterations": feature_iterations, "anchor_rays": anchor_rays, "seed": seed + 500_000,
               "progress": progress, "table": table, **dict(feature_kw or {})}
        ff = fit_features(meas, state, twin, offset_jacobian=offset_jacobian, **fkw)
        last = ff.history[-1]
        settled = last["chi2_features"] <= _feature_noise_limit(last["features"], fkw.get("n_sigma", 3.0))
        for k, alt in enumerate(() if also_from_beyond_noise and settled else also_from):
            off = np.asarray(getattr(alt, "offsets", alt), dtype=float)
            fa = fit_features(meas, ModelState(off, state.effects, state.label), twin,
                              offset_jacobian=ff.jacobian if offset_jacobian is None else offset_jacobian,
                              **{**fkw, "seed": seed + 500_000 * (k + 2)})
            for h in fa.history:
                h["start"] = k + 1
            if fa.history[-1]["chi2"] < ff.history[-1]["chi2"]:
                ff = fa
        state, history = ff.state, ff.history
        if ff.jacobian is not None and forward_model is None:
            offset_jacobian = ff.jacobian
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
    nan = float("nan")
    stage = {"stage": "bins", "chi2_features": nan, "features": nan, "damping": nan}
    history.append({**stage, "iteration": 0, "accepted": True, "jacobian_refreshed": False,
                    "chi2_reduced": mf.chi2_reduced_total, "mse": mf.mse_total, "chi2": mf.chi2_total,
                    "dof": mf.dof_total, "chi2_reference": nan, "trust_region": nan,
                    "effects": {k: dict(v) for k, v in state.effects.items()}})
    if progress:
        progress(history[-1])
    current, prior, refreshes = state, offset_prior, 0
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
        elif refresh_on_reject and not jac_fresh and (max_refreshes is None or refreshes < max_refreshes):
            refreshes += 1
            # a new anchor with its own seeds and a full Jacobian there; it is the reference now
            lm = build_local_model(meas, current, twin, forward_model, anchor_rays=anchor_rays,
                                   seed=it_seed + 500, twin_columns=twin_columns,
                                   effect_step=effect_step, table=table, **jkw)
            mf, jac, jac_fresh, refreshed = _twin_chi2(meas, lm), lm.jac, True, True
        else:
            prior = min(priors) / 4.0
        history.append({**stage, "iteration": it, "accepted": bool(accepted), "jacobian_refreshed": refreshed,
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
