"""One fit engine: offsets and effects fitted through the differentiable twin.

The model of a measurement is the torch twin (:class:`~bluesky_offsets.physics.engine.TorchEngine`)
traced at the measured configurations plus the offsets, with the state's effects.  Its
Jacobian in the offsets and in every effect parameter is exact: each ray's screen position
and soft weight are differentiated (:meth:`TorchEngine.ray_jacobian`), and the histograms,
profiles and beam features the fit compares are functions of the rays, so their Jacobians
follow by the chain rule.  The derivatives are those of the soft beam (apertures with soft
edges, rays binned with a narrow kernel), whose expectation RAYX's hard counts follow.

A fit runs in stages on one set of rays (common random numbers: the objective is a
deterministic function of the parameters, so a step is judged without sampling noise), a
random stream of its own for each configuration (:func:`engine_for` says why):

1. ``features``: intensity, centroid and rms width per axis
   (:func:`bluesky_offsets.model.misfit.beam_features`), smooth over many spot widths;
2. ``profiles``: the histograms summed into coarser bins;
3. ``bins``: the measured bins (Pearson χ², the variance from measured and model counts:
   :func:`bluesky_offsets.physics.noise.bin_variance`).

Each stage after the first starts from the better, on its own comparison, of the fit's start and
where the stage before ended (:func:`_lower`).  Every stage compares RAYX's own counts; with
``FitOptions.soft_values`` the first two compare the soft beam instead (a smooth objective whose
derivative the Jacobian is exactly).

Each stage is Levenberg-Marquardt within the bounds (offsets within ±``MAX_OFFSET``, effect
parameters within their priors), on the twin's exact Jacobian (optionally its secant updates
between exact ones, ``FitOptions.secant``).  The uncertainty of the result is the inverse of the
last stage's information at the solution, inflated by χ²/dof where the model does not reach the
noise, and widened to the spread over configurations where that is larger
(:func:`jackknife_covariance`: what one configuration alone pulls the solution by, which the
information does not see when the model or the fit's end is off).  The information is the cross
product of two Jacobians from independent rays (:meth:`_Model.fisher`): a Jacobian estimated
from rays carries their noise, and squared that noise reads as information the frames do not
hold (at the camera's bins, 5,000 rays a frame, it made offsets look up to 30 times better known
than the fit's ends were: benchmarks/bench_design.py).

Fits that do not depend on each other (the starts of one fit, its ray draws, a diagnosis's
candidates) run side by side on an executor where one is given (:func:`gather`: threads, or the
processes of the twin's Dask cluster); each has its own rays and its own model, and their
results are used in a fixed order, so the outcome is the same on any number of threads or
workers.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field, fields, replace
from typing import TypeVar

import numpy as np
import torch
from scipy.stats import chi2 as chi2_dist

from bluesky_offsets.errors import InputError
from bluesky_offsets.options import refuse_unknown
from bluesky_offsets.physics import effects as E
from bluesky_offsets.model.posterior import evidence_spread, scaled_inverse, shrunk_mean
from bluesky_offsets.model.misfit import beam_features, compared, expected_pull2, feature_values
from bluesky_offsets.model.values import ModelState
from bluesky_offsets.physics.noise import bin_variance
from bluesky_offsets.physics.parameters import MAX_OFFSET, METRIXS, ParameterTable
from bluesky_offsets.physics.screen import add_overrides, tensor_overrides
from bluesky_offsets.physics.engine import FORWARD_AD
from bluesky_offsets.streams import stream

STAGES = ("features", "profiles", "bins")
#: added to a fit's seed for rays none of its configurations traced (each configuration ``i``
#: traces the stream ``seed + i``): what the ends of several starts are judged on
FRESH_SEED = 1_000_003
#: ``k`` times this added to a fit's seed: the model's rays of its ``k``-th ray draw
#: (:attr:`FitOptions.ray_draws`), streams neither the first draw nor the fresh rays trace
RAY_DRAW_SEED = 3_000_017
#: added to a fit's seed for the second, independent Jacobian of its uncertainty (:meth:`_Model.fisher`)
CROSS_SEED = 5_000_011
WIDE_DRAWS = 2.0
"""σ of the later half of a round's posterior starts over the posterior's: the end a fit stalls at
can lie beyond the reach of draws at its own curvature (the valleys of a ±20 % draw)."""
POSTERIOR_ROUNDS = 6
"""Rounds of :attr:`FitOptions.posterior_starts` at most: another round, drawn at the new best end,
follows while a round's best ends lower than the best before it by more than the fitted
parameters' joint 95 % region (each round's end is a start of the next: it stalls again)."""


@dataclass(frozen=True)
class FitOptions:
    """How a fit runs.

    Parameters
    ----------
    rays : int
        model rays per configuration (one set for the whole fit).
    feature_rays : int or None
        fewer rays for the feature stage (its five numbers per configuration are
        robust to ray noise, and a stage costs in proportion to its rays); None: ``rays``.
    seed : int
        their seed.
    stages : tuple of (str, int)
        ``(stage, iterations)`` in order, stages from :data:`STAGES`.
    profile_factor : tuple of (int, int)
        camera bins summed per profile bin (x, y).
    kernel : float
        width (bins) of the kernel that turns the rays' moves into bin derivatives.
    prior_sigma : float or None
        a Gaussian prior on the offsets (normalized units): by default the spread of
        the model's own prior, offsets uniform within ±``MAX_OFFSET`` (``MAX_OFFSET / √3``).  It
        keeps the directions no measurement sees (compensating combinations) where they are,
        and it bounds the uncertainty an effect inherits from them; None: no prior.
    damping : float
        Levenberg-Marquardt's starting damping.
    tolerance : float
        a stage stops when an accepted step lowers χ² by less than this fraction.
    soft_values : bool
        the features and profiles stages compare the soft beam, a smooth objective
        that the Jacobian differentiates exactly (True), or RAYX's hard counts (False, the
        default).  The soft beam can move where the hard counts refuse every step, but it can
        hide a defocus from the diagnosis, and in the paper's coarse bins its one-bin kernel
        widens the beam: not the default until that is understood.
    offset_bound : float
        the offsets stay within ± this (normalized; default the model's ``MAX_OFFSET``).
    secant : bool
        after an accepted step that gains, update the Jacobian by Broyden's rank-one
        secant (the change the twin actually made along the step) instead of a new exact one: a
        value costs a tenth of a Jacobian.  A step refused on an updated Jacobian is retried on
        the twin's own, a step that gains little is followed by the twin's own, and the
        uncertainty is always read from the twin's Jacobian at the solution.  Off by default:
        updates can speed a fit up, but they can also stall one in coarse bins far above the exact
        Jacobian's end, and leave a short candidate fit of an effect well short of its value.
    ray_draws : int
        a fit with effect parameters repeated on this many independent draws of the
        model's rays, each later draw starting where the first ended; the solution is their mean
        and the covariance adds their spread (their sample covariance, one draw's: not divided
        by their number, see :func:`fit`) to the Gauss-Newton one.  An offsets-only fit is one
        draw: it starts a diagnosis (whose candidate fits refit the offsets) or a refit, and
        each draw costs a whole fit.
        Why: on RAYX's hard counts with a fixed set of rays the χ² is a staircase along the
        directions where offsets compensate an effect (an aperture's size against the source's
        divergence), and one draw ends on whichever step is near, farther from the truth than its
        curvature says; the mean over draws, and their spread in the σ, cover that
        (the scenario grid: docs/benchmarks.md, "Diagnosis on the differentiable twin").
        1: one draw.
    settle : bool
        end with one undamped Gauss-Newton step (:func:`_settle`), kept where it lowers the
        objective: the offsets the data barely see go where the prior and the data put them, not
        where the damped steps left them.  Off by default: it cost a ±20 % draw its fit
        (docs/explanations/diagnosis.md, "Settling", has the numbers).
    estimate_spread : bool
        after the fit, estimate the offsets' spread from the data
        (:func:`~bluesky_offsets.model.posterior.evidence_spread`: the prior σ the evidence
        prefers, at most ``prior_sigma``) and, where it is narrower, refit the last stage from the
        solution under it (ending with :func:`_settle`): the offsets the frames do not determine go
        to where offsets of that spread are, not where the steps left them within the wider prior.
        Off by default; the analysis's fits (:data:`bluesky_offsets.model.diagnosis.FIT`) turn it on.
    posterior_starts : int
        after the starts, this many more drawn from the Gaussian posterior at the best end (its
        Gauss-Newton covariance, half of them at twice its σ, a named random stream), each fitted
        in full, in rounds while a round gains (:data:`POSTERIOR_ROUNDS`); every end is judged on
        fresh rays as several starts are (``also_from`` of :func:`fit`), the lowest kept, the
        others within its joint 95 % region widening its covariance.  Why: on RAYX's hard counts
        Levenberg-Marquardt stalls short of the minimum along the directions the frames barely
        see, and its curvature there does not cover the truth (docs/explanations/offsets.md,
        "Starts drawn from the posterior").  0: none.
    engine : mapping, optional
        options of the torch engine (:class:`~bluesky_offsets.physics.engine.TorchOptions`).
    """

    rays: int = 5000
    feature_rays: int | None = 2000
    seed: int = 0
    stages: tuple[tuple[str, int], ...] = (("features", 15), ("profiles", 8), ("bins", 8))
    profile_factor: tuple[int, int] = (5, 5)
    kernel: float = 1.0
    prior_sigma: float | None = MAX_OFFSET / math.sqrt(3.0)
    damping: float = 1e-3
    tolerance: float = 1e-3
    soft_values: bool = False
    offset_bound: float = MAX_OFFSET
    secant: bool = False
    ray_draws: int = 1
    settle: bool = False
    estimate_spread: bool = False
    posterior_starts: int = 0
    engine: Mapping | None = None

    def __post_init__(self):
        if int(self.rays) < 1 or (self.feature_rays is not None and int(self.feature_rays) < 1):
            raise InputError("rays must be positive")
        if not self.stages:
            raise InputError("a fit needs at least one stage")
        for st in self.stages:
            if len(st) != 2 or st[0] not in STAGES or int(st[1]) < 0:
                raise InputError(f"a stage is (name, iterations) with name in {STAGES}, not {st!r}")
        if not (self.kernel > 0 and math.isfinite(self.kernel)):
            raise InputError("kernel must be a finite number > 0")
        if self.prior_sigma is not None and not self.prior_sigma > 0:
            raise InputError("prior_sigma must be positive")
        if int(self.ray_draws) != self.ray_draws or self.ray_draws < 1:
            raise InputError(f"ray_draws must be a whole number >= 1, not {self.ray_draws!r}")
        if int(self.posterior_starts) != self.posterior_starts or self.posterior_starts < 0:
            raise InputError(f"posterior_starts must be a whole number >= 0, not {self.posterior_starts!r}")
        if not 0 < self.offset_bound <= MAX_OFFSET:
            raise InputError(f"offset_bound must lie in (0, {MAX_OFFSET}]")

    @classmethod
    def from_mapping(cls, options: Mapping | None = None, **more) -> FitOptions:
        """Options from a mapping; an unknown key is an error naming the known ones."""
        opts = {**dict(options or {}), **more}
        refuse_unknown(cls, opts, "unknown fit option(s)")
        if "stages" in opts:
            opts["stages"] = tuple((str(a), int(b)) for a, b in opts["stages"])
        if "profile_factor" in opts:
            opts["profile_factor"] = tuple(int(v) for v in opts["profile_factor"])
        return cls(**opts)

    def replace(self, **changes) -> FitOptions:
        """These options with ``changes`` (field names and values) applied, validated as :meth:`from_mapping`."""
        return FitOptions.from_mapping({f.name: getattr(self, f.name) for f in fields(self)}, **changes)

    @classmethod
    def resolve(cls, options: FitOptions | Mapping | None, default: FitOptions | None = None) -> FitOptions:
        """``options`` as given, ``default`` (or the defaults) for None, a mapping applied to it."""
        base = default or cls()
        if options is None:
            return base
        return options if isinstance(options, FitOptions) else base.replace(**dict(options))


@dataclass
class FitResult:
    """Where a fit ended: the state, its χ² per stage, the uncertainties and the covariance.

    The covariance is over the normalized offsets, then the effect parameters, in :attr:`names` order.
    """

    state: ModelState
    history: list[dict]
    covariance: np.ndarray
    names: list[str]
    chi2: float                         # the last stage's χ² at the solution (the fit's rays)
    dof: float
    inflation: float = 1.0
    n_traces: int = 0
    jacobian: np.ndarray | None = field(default=None, repr=False)  # last stage (residuals, parameters)
    residuals: np.ndarray | None = field(default=None, repr=False)  # last stage, normalized
    rows: np.ndarray | None = field(default=None, repr=False)       # each residual's configuration
    stage: str = ""
    ridge: np.ndarray | None = field(default=None, repr=False)      # the prior's diagonal (normal matrix)
    widened: np.ndarray | None = field(default=None, repr=False)    # σ over the Gauss-Newton σ (jackknife)
    draws: np.ndarray | None = field(default=None, repr=False)      # where each ray draw ended (ray_draws > 1)
    # the other starts' ends within the joint 95 % region of the kept one (their spread is in the covariance)
    alternatives: np.ndarray | None = field(default=None, repr=False)
    # the offsets' spread estimated from the data, where the solution and the covariance hold it as
    # the offsets' prior in place of FitOptions.prior_sigma (FitOptions.estimate_spread); None: not
    prior_sigma: float | None = None

    @property
    def chi2_reduced(self) -> float:
        """The last stage's χ² / dof at the solution (dof floored at 1)."""
        return self.chi2 / max(self.dof, 1.0)

    @property
    def sigma(self) -> np.ndarray:
        """Every fitted parameter's standard deviation from the covariance, in :attr:`names` order."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))

    @property
    def offset_sigma(self) -> np.ndarray:
        """The normalized offsets' standard deviations (the first entries of :attr:`sigma`)."""
        return self.sigma[:len(self.state.offsets)]

    def effect_sigma(self) -> dict[str, dict[str, float]]:
        """The effect parameters' standard deviations, as ``{effect: {parameter: σ}}``."""
        s = self.sigma
        out: dict[str, dict[str, float]] = {}
        for k, name in enumerate(self.names[len(self.state.offsets):], len(self.state.offsets)):
            eff, p = name.split(".", 1)
            out.setdefault(eff, {})[p] = float(s[k])
        return out


# --------------------------------------------------------------------------- #
# the model's products and their Jacobians
# --------------------------------------------------------------------------- #
def engine_for(meas, options: FitOptions, table: ParameterTable = METRIXS):
    """The torch twin a fit of ``meas`` traces.

    It bins as ``meas``, takes the options' engine settings, and by default draws a random stream
    of its own for each configuration (``common_rays=False``; fixed for the whole fit, so the
    objective stays smooth).

    Why not the engine's default, one stream shared by all configurations: the measured frames'
    noise is independent from frame to frame, and the uncertainties assume the model's is too.
    With shared rays the model's sampling error of the source (its drawn spread, say) is the
    same in every configuration and no number of configurations averages it out: a fitted
    effect (the source's divergence, say) then lands off the truth by many times its σ.
    """
    from bluesky_offsets.physics.beamline import torch_engine
    return torch_engine(table, meas.spec, {"common_rays": False, **dict(options.engine or {})})


class _Model:
    """The measurement's model as a function of the fitted vector z.

    z holds the normalized offsets, then the effect parameters; the model gives the values and
    exact Jacobians of each stage's residuals.
    """

    def __init__(self, meas, state, engine, options: FitOptions, table: ParameterTable):
        self.meas, self.engine, self.o, self.table = meas, engine, options, table
        self.base = state
        self.P = len(table)
        self.params = state.effect_parameters()
        self.names = list(table.names) + [f"{e}.{q.name}" for e, q in self.params]
        self.twin_effects = [e for e in state.effects if E.get(e).level == "twin"]
        self.det_effects = [e for e in state.effects if E.get(e).level == "detector"]
        self.span = torch.as_tensor(table.span, dtype=torch.float64)
        self.m = np.concatenate([meas.hist_x, meas.hist_y], 1)
        self.floor = meas.floor  # a camera's own noise per bin, None for ray counts
        self.n_rays = float(meas.ray_budget)  # the measured photons: every comparison weighs by them
        self.fm, self.vm = beam_features(meas.hist_x, meas.hist_y, meas.spec, self.n_rays,
                                         meas.floor_x, meas.floor_y)  # measured: fixed
        self.n_traces = 0
        self.soft = bool(options.soft_values)
        self._measured: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
        # the rays' values last traced without derivatives ((z, rays), Beam): an accepted step
        # asks for the Jacobian where its values were just traced, which then traces no value again
        self._last: tuple | None = None
        # the rays' derivatives last taken ((z, rays), RayJacobian): a stage's last Jacobian is the
        # next stage's first where both trace the same rays
        self._last_rj: tuple | None = None

    # -- z <-> state -----------------------------------------------------------------
    def vector(self, st) -> np.ndarray:
        return st.vector()

    def state(self, z):
        z = np.asarray(z, float)
        return ModelState(z[:self.P].copy(), self.base.set_effect_vector(z[self.P:]), self.base.label)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        b = self.o.offset_bound
        return (np.r_[np.full(self.P, -b), [q.low for _, q in self.params]],
                np.r_[np.full(self.P, b), [q.high for _, q in self.params]])

    # -- histograms ------------------------------------------------------------------
    def rays(self, stage: str) -> int:
        o = self.o
        return min(o.rays, o.feature_rays) if stage == "features" and o.feature_rays else o.rays

    def histograms(self, z, jacobian: bool, rays: int | None = None, soft: bool = False, noise: bool = False):
        """Model histograms (C, B) at the measurement's bins, their Jacobian (C, B, P + p) in z, their noise.

        ``soft``: the soft beam's values, smooth in z, else RAYX's hard counts.  The noise, where
        asked: per bin the second moment of the model's counts through its detector-level effects
        (:func:`bluesky_offsets.physics.effects.detector_noise`); None without such effects.
        """
        rays = int(rays or self.o.rays)
        st = self.state(z)
        vals = self.meas.configurations + self.table.offsets_to_physical(st.offsets)
        twin_eff = {e: st.effects[e] for e in self.twin_effects}
        spec = self.meas.spec
        key = (np.asarray(z, float).tobytes(), rays)
        stage = tensor_overrides(self.meas.screen, self.meas.n)  # the chamber's stage, frame by frame
        if jacobian:
            if self._last_rj is not None and self._last_rj[0] == key:
                rj = self._last_rj[1]
            else:
                self.n_traces += self.meas.n
                full = self._last[1] if self._last is not None and self._last[0] == key else None
                rj = self.engine.ray_jacobian(vals, twin_eff, n_rays=rays, seed=self.o.seed, full=full,
                                              overrides=stage)
                self._last_rj = (key, rj)
            h, J = rj.histograms(spec, self.o.kernel, soft=soft)
            # offsets are normalized: d/dz = d/dvalue * span; effect columns in the state's order
            cols = [J[..., :self.P] * self.span]
            k = self.P
            for e in self.twin_effects:
                for _ in st.effects[e]:
                    cols.append(J[..., k:k + 1])
                    k += 1
            J = torch.cat(cols, -1)
        else:
            self.n_traces += self.meas.n
            # with the soft edge whether or not the values are soft: RAYX's hard counts (the rays'
            # ``alive``) are the same bit for bit, and the Jacobian can take these rays
            with torch.no_grad():
                ov = E.twin_overrides(twin_eff) if twin_eff else None
                beam = self.engine.beam(vals, add_overrides(ov, stage) if stage else ov, n_rays=rays,
                                        seed=self.o.seed, edge=self.engine.options.edge)
            self._last = (key, beam)
            from bluesky_offsets.physics.engine import histograms
            hx, hy = histograms(beam, spec, soft=soft, kernel=self.o.kernel)
            h, J = torch.cat([hx, hy], 1), None
        out, J = self._detector(st, h, J)
        return out, J, self._noise(st, h) if noise else None

    def _noise(self, st, h) -> np.ndarray | None:
        """The counting noise of the traced histograms ``h`` through the state's detector-level effects."""
        if not self.det_effects:
            return None
        nx = self.meas.spec.bins_x
        hn = h.detach().numpy()
        fx, fy = E.detector_noise(hn[:, :nx], hn[:, nx:], {e: st.effects[e] for e in self.det_effects},
                                  self.meas.spec)
        return np.concatenate([fx, fy], 1)

    def _detector(self, st, h, J):
        """Detector-level effects on the histograms (affine in them) with their own columns.

        The Jacobian's columns are every parameter's, in the state's order.
        """
        if not self.det_effects:
            return h, J
        spec = self.meas.spec
        nx = spec.bins_x
        theta = {e: {p: torch.tensor(float(v), dtype=torch.float64) for p, v in st.effects[e].items()}
                 for e in self.det_effects}

        def apply(hh, th):
            hx, hy = hh[..., :nx], hh[..., nx:]
            for e in self.det_effects:
                hx, hy = E.get(e).apply_histograms(hx, hy, th[e], spec)
            return torch.cat([hx, hy], -1)

        out = apply(h, theta)
        if J is None:
            return out, None
        # every detector effect is affine in the histograms: A J = f(J) - f(0)
        c, b, p = J.shape
        cols = J.permute(0, 2, 1).reshape(c * p, b)
        zero = apply(torch.zeros(1, b, dtype=h.dtype), theta)
        JA = (apply(cols, theta) - zero).reshape(c, p, b).permute(0, 2, 1)
        det_cols = {}
        for e in self.det_effects:
            for q in theta[e]:
                def f(v, e=e, q=q):
                    th = {k: dict(d) for k, d in theta.items()}
                    th[e][q] = v
                    return apply(h, th)
                with FORWARD_AD:
                    det_cols[(e, q)] = torch.func.jvp(f, (theta[e][q],), (torch.ones((), dtype=torch.float64),))[1]
        # the columns in the state's order: twin effects are already in JA at their places
        full, k = [JA[..., :self.P]], self.P
        for e in self.base.effects:
            for q in st.effects[e]:
                if e in self.det_effects:
                    full.append(det_cols[(e, q)][..., None])
                else:
                    full.append(JA[..., k:k + 1])
                    k += 1
        return out, torch.cat(full, -1)

    # -- each stage's products and residuals --------------------------------------------
    def products(self, stage: str, z, jacobian: bool) -> _Products:
        """What ``stage`` compares, as the model predicts it at ``z``.

        Beam features (C, 5), or profile or camera bins (C, B), with their Jacobian in z
        (C, K, P + p) when asked.
        """
        rays = self.rays(stage)
        # the camera bins' noise: summed profile bins share a blur's rays, and are weighed by their values
        h, J, noise = self.histograms(z, jacobian, rays, soft=stage != "bins" and self.soft, noise=stage == "bins")
        spec, nx = self.meas.spec, self.meas.spec.bins_x
        if stage == "features":
            hd = h.detach().requires_grad_(jacobian)
            f = torch.stack(feature_values(hd[:, :nx], hd[:, nx:], spec), -1)
            hn = h.detach().numpy()
            _, vf = beam_features(hn[:, :nx], hn[:, nx:], spec, rays)
            Jf = None
            if jacobian:
                # d features / d histograms (C, 5, B), one backward pass per feature
                d = torch.stack([torch.autograd.grad(f[:, k].sum(), hd, retain_graph=k < 4)[0] for k in range(5)], 1)
                Jf = torch.einsum("cfb,cbp->cfp", d, J).numpy()
            return _Products(f.detach().numpy(), Jf, rays, vf)
        if stage == "profiles":
            h = self._rebin(h)
            J = None if J is None else self._rebin(J)
        return _Products(h.detach().numpy(), None if J is None else J.numpy(), rays, noise=noise)

    def _rebin(self, t: torch.Tensor) -> torch.Tensor:
        """Camera bins (C, B, ...) summed into profile bins (C, B', ...)."""
        spec, (fx_, fy_) = self.meas.spec, self.o.profile_factor
        nx = spec.bins_x
        tx, ty = t[:, :nx], t[:, nx:]
        tx = tx.reshape(tx.shape[0], spec.bins_x // fx_, fx_, *tx.shape[2:]).sum(2)
        ty = ty.reshape(ty.shape[0], spec.bins_y // fy_, fy_, *ty.shape[2:]).sum(2)
        return torch.cat([tx, ty], 1)

    def measured(self, stage: str) -> tuple[np.ndarray, np.ndarray | None]:
        """The measured bins ``stage`` compares and their camera floor (None without one)."""
        if stage not in self._measured:
            hm = torch.as_tensor(self.m)
            floor = None if self.floor is None else torch.as_tensor(self.floor)
            if stage == "profiles":  # independent pixels: floors add up as the bins do
                hm, floor = self._rebin(hm), None if floor is None else self._rebin(floor)
            self._measured[stage] = (hm.numpy(), None if floor is None else floor.numpy())
        return self._measured[stage]

    def residuals(self, stage: str, pr: _Products, shift: np.ndarray | None = None):
        """Normalized residuals (measured − model)/σ of ``stage`` (flat), with their Jacobian and dof.

        Returns the residuals, their Jacobian in z (rows, P + p; d model / dz / σ) when ``pr`` has
        one, the degrees of freedom and each row's configuration.  ``shift`` (the stage's values'
        shape, in units of σ) is subtracted from the residuals: frames perturbed by a draw of their noise.
        """
        n_conf = self.meas.n
        if stage == "features":
            sd = np.sqrt(self.vm + pr.variance)
            r = ((self.fm - pr.values) / sd - (0.0 if shift is None else shift)).reshape(-1)
            G = None if pr.jacobian is None else (pr.jacobian / sd[..., None]).reshape(r.size, -1)
            return r, G, float(r.size), np.repeat(np.arange(n_conf), 5)
        m, floor = self.measured(stage)
        f = pr.values
        var = bin_variance(m, f, self.n_rays, pr.rays, floor=floor, model_noise=pr.noise)
        signal = compared(m, f, floor)
        r = np.where(signal, (m - f) / np.sqrt(var) - (0.0 if shift is None else shift), 0.0)
        dof = float(expected_pull2(m, f, self.n_rays, floor).sum())
        keep = signal.reshape(-1)
        G = None
        if pr.jacobian is not None:
            G = (pr.jacobian / np.sqrt(var)[..., None]).reshape(-1, pr.jacobian.shape[-1])[keep]
        rows = np.repeat(np.arange(n_conf), m.shape[1])[keep]
        return r.reshape(-1)[keep], G, dof, rows


def _fisher(mdl: _Model, other: _Model, stage: str, z: np.ndarray, pa: _Products | None = None) -> np.ndarray:
    """The information of ``stage``'s residuals in z at ``z``, from two independent rays' Jacobians.

    That is ``(Jaᵀ W Jb + Jbᵀ W Ja) / 2`` of the Jacobians of two models with independent rays
    (``mdl``'s and ``other``'s), whose expectation is the information itself (one Jacobian squared
    adds its rays' noise), its negative eigenvalues (that noise) set to 0.  The weights are the
    residuals' (:meth:`_Model.residuals`) at the mean of both models' values.  ``pa``: ``mdl``'s
    products at ``z`` with their Jacobian, when at hand.
    """
    pa = pa if pa is not None and pa.jacobian is not None else mdl.products(stage, z, True)
    pb = other.products(stage, z, True)
    assert pa.jacobian is not None and pb.jacobian is not None  # products(..., True)
    if stage == "features":
        assert pa.variance is not None and pb.variance is not None  # features carry their variance
        w = 1.0 / (mdl.vm + 0.5 * (pa.variance + pb.variance))
    else:
        (m, floor), f = mdl.measured(stage), 0.5 * (pa.values + pb.values)
        noise = None if pa.noise is None or pb.noise is None else 0.5 * (pa.noise + pb.noise)
        var = bin_variance(m, f, mdl.n_rays, pa.rays, floor=floor, model_noise=noise)
        w = np.where(compared(m, f, floor), 1.0 / var, 0.0)
    x = np.einsum("cbp,cb,cbq->pq", pa.jacobian, w, pb.jacobian)
    vals, vecs = np.linalg.eigh(0.5 * (x + x.T))
    return (vecs * np.clip(vals, 0.0, None)) @ vecs.T


@dataclass
class _Products:
    """A stage's model values (C, K) and what goes with them.

    Their Jacobian in z (C, K, P + p) or None, the rays they were traced with, (features) the
    values' own ray-noise variance and (camera bins) the second moment of the model's counts
    through the detector-level effects (None: each bin weighed by its value).
    """

    values: np.ndarray
    jacobian: np.ndarray | None
    rays: int
    variance: np.ndarray | None = None
    noise: np.ndarray | None = None

    def secant(self, new: _Products, step: np.ndarray) -> _Products:
        """``new`` with this Jacobian updated along ``step`` (Broyden's rank-one update).

        The update makes the Jacobian reproduce the change the twin actually made.
        """
        assert self.jacobian is not None  # a stage's products carry the Jacobian its steps came from
        c, k, p = self.jacobian.shape
        J = self.jacobian.reshape(c * k, p)
        miss = (new.values - self.values).reshape(-1) - J @ step
        J = J + np.outer(miss, step) / float(step @ step)
        return _Products(new.values, J.reshape(c, k, p), new.rays, new.variance, new.noise)


# --------------------------------------------------------------------------- #
# the fit
# --------------------------------------------------------------------------- #
def _lm_step(G: np.ndarray, r: np.ndarray, z: np.ndarray, lam: float, ridge: np.ndarray) -> np.ndarray:
    A = G.T @ G + np.diag(ridge)
    g = G.T @ r - ridge * z
    d = np.diag(A).copy()
    d[d <= 0] = 1.0
    M = A + lam * np.diag(d) + 1e-12 * np.trace(A) / len(A) * np.eye(len(A))
    try:
        return np.linalg.solve(M, g)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(M, g, rcond=None)[0]


def _objective(r: np.ndarray, z: np.ndarray, ridge: np.ndarray) -> float:
    """What a fit minimizes: χ² of the residuals plus the offsets' prior."""
    return float(r @ r) + float((ridge * z * z).sum())


def _ridge(mdl: _Model, o: FitOptions) -> np.ndarray:
    """The prior's diagonal in the normal matrix: the offsets' Gaussian prior, none on effects."""
    prior = 0.0 if o.prior_sigma is None else o.prior_sigma ** -2.0
    return np.r_[np.full(mdl.P, prior), np.zeros(len(mdl.params))]


def _stage(mdl: _Model, stage: str, z: np.ndarray, pr: _Products, iterations: int, ridge: np.ndarray,
           history: list[dict], progress: Callable[[dict], None] | None, *, secant: bool,
           look: bool = False) -> tuple[np.ndarray, _Products, bool]:
    """Levenberg-Marquardt on one stage from ``z``, whose products (with the twin's Jacobian) are ``pr``.

    Appends to ``history``.  Returns where it ended, the products there and whether their Jacobian
    is the twin's own.  ``look`` (:func:`screen`): every accepted step updates the Jacobian by its
    secant, none is recomputed, and all ``iterations`` run.
    """
    lo, hi = mdl.bounds()
    exact = True  # the Jacobian is the twin's at z (not a secant update of it)
    r, G, dof, _ = mdl.residuals(stage, pr)
    chi2 = _objective(r, z, ridge)
    lam = mdl.o.damping

    def record(it: int, accepted: bool) -> None:
        history.append({"stage": stage, "iteration": it, "accepted": accepted, "chi2": chi2, "dof": dof,
                        "chi2_reduced": chi2 / max(dof, 1.0), "damping": lam, "exact": exact})
        if progress:
            progress(history[-1])

    record(0, True)
    small = 0
    for it in range(1, iterations + 1):
        zc = np.clip(z + _lm_step(G, r, z, lam, ridge), lo, hi)
        pc = mdl.products(stage, zc, False)
        rc = mdl.residuals(stage, pc)[0]
        cc = _objective(rc, zc, ridge)
        accepted = bool(cc < chi2) and bool(np.any(zc != z))
        if accepted:
            gain = (chi2 - cc) / max(chi2, 1e-300)
            small = small + 1 if gain < mdl.o.tolerance else 0
            if look or (secant and not small):
                # a value costs a tenth of a Jacobian: while the steps gain, secant updates
                pr, exact = pr.secant(pc, zc - z), False
            else:
                # little gain (or no secants): the twin's own Jacobian where the step ended,
                # so that a stage ends on what the twin says, not on a stale update
                pr, exact = mdl.products(stage, zc, True), True
            z, chi2 = zc, cc
            r, G, dof, _ = mdl.residuals(stage, pr)
            lam = max(lam / 3.0, 1e-9)
        elif not exact and not look:
            # refused on an updated Jacobian: the twin's own, before any more damping
            pr, exact = mdl.products(stage, z, True), True
            r, G, dof, _ = mdl.residuals(stage, pr)
        else:
            lam *= 4.0
        record(it, accepted)
        if not look and (small >= 2 or lam > 1e6):
            break
    return z, pr, exact


T = TypeVar("T")


# each call is called with no arguments; `...`: a lambda's defaults bind its loop variables
def gather(calls: Sequence[Callable[..., T]], executor: Executor | None = None) -> list[T]:
    """Every call's result, in the calls' order: side by side on ``executor``, one after the other without one.

    The executor is a thread pool or a Dask cluster
    (:class:`~bluesky_offsets.model.cluster.ClusterExecutor`: each call pickled to a worker
    process), so a call returns everything it changes and mutates nothing the caller reads after; a
    progress callback crosses as a :class:`~bluesky_offsets.model.cluster.Progress`.  Only
    independent work belongs here (a call must not wait on the same executor: a bounded pool would
    deadlock); the order of the results, never which call finished first, decides what follows.
    """
    if executor is None:
        return [c() for c in calls]
    return [f.result() for f in [executor.submit(c) for c in calls]]


def _stages(mdl: _Model, z: np.ndarray, ridge: np.ndarray, history: list[dict],
            progress: Callable[[dict], None] | None, tag: dict) -> tuple[np.ndarray, _Products, bool]:
    """All of the options' stages from ``z`` on ``mdl``; returns what the last :func:`_stage` returns.

    Each iteration's record is tagged with ``tag`` (which start, which ray draw).
    """
    def tagged(d):
        d.update(tag)
        if progress:
            progress(d)
    start = z
    for k, (stage, iterations) in enumerate(mdl.o.stages):
        if k:
            z = _lower(mdl, stage, start, z, ridge)
        z, pr, exact = _stage(mdl, stage, z, mdl.products(stage, z, True), iterations, ridge, history, tagged,
                              secant=mdl.o.secant)
    return z, pr, exact


def _lower(mdl: _Model, stage: str, start: np.ndarray, z: np.ndarray, ridge: np.ndarray) -> np.ndarray:
    """Of the fit's start and where the stages before ended, the one ``stage`` scores lower.

    The coarse stages lead into a basin from afar; from a start already near a solution (a
    candidate effect added to fitted offsets) they can end where the finer comparison is worse
    than at the start, and a fine stage's few iterations do not climb back.
    """
    if np.array_equal(start, z):
        return z
    scores = [_objective(mdl.residuals(stage, mdl.products(stage, x, False))[0], x, ridge) for x in (start, z)]
    return start if scores[0] < scores[1] else z


def _run(mdl: _Model, z: np.ndarray, ridge: np.ndarray, progress: Callable[[dict], None] | None,
         tag: dict) -> tuple:
    """:func:`_stages` from ``z``: (z, products, exact, the run's history, the model's traces).

    Everything the run changed is returned (it may run in a process of its own).
    """
    part: list[dict] = []
    z, pr, exact = _stages(mdl, z, ridge, part, progress, tag)
    mdl._last_rj = None  # tens of MB a model, and a fit keeps every start's model
    return z, pr, exact, part, mdl.n_traces


def _runs(jobs: Sequence[tuple[_Model, np.ndarray, dict]], ridge: np.ndarray,
          progress: Callable[[dict], None] | None, executor: Executor | None) -> list[tuple]:
    """:func:`_stages` for each ``(model, z, tag)``, side by side on ``executor``.

    Returns each run's (z, products, exact, its own history), in the jobs' order.
    """
    ends = gather([lambda j=j: _run(j[0], z=j[1], ridge=ridge, progress=progress, tag=j[2]) for j in jobs],
                  executor)
    for (mdl, _, _), end in zip(jobs, ends):
        mdl.n_traces = end[4]  # a run in another process counted on a copy of its model
    return [end[:4] for end in ends]


# long: a 28-line docstring over 88 lines of one Levenberg-Marquardt loop, read at once
def fit(meas, state, engine, options: FitOptions | Mapping | None = None, *,
        progress: Callable[[dict], None] | None = None, table: ParameterTable = METRIXS,
        also_from: Sequence = (), executor: Executor | None = None) -> FitResult:
    """Fit the offsets and the state's effect parameters to ``meas`` (see the module text).

    Parameters
    ----------
    meas : measurement.Measurement (as :meth:`~bluesky_offsets.model.measurement.Measurement.for_analysis` gives it)
        Histograms at their spec (the camera's or the paper's) and the commanded configurations.
    state : model.ModelState
        The start: offsets (normalized) and the effects the model includes, with start values.
    engine : TorchEngine
        The differentiable twin.
    options : FitOptions or a mapping of its fields (unknown keys are refused).
    progress : called with a dict after every iteration (stage, iteration, χ²/dof, accepted).
    also_from : more starts (states with the same effects): the whole fit runs from each and the
        one that ends lowest is kept, its last stage's χ² judged on rays none of the fits traced
        (the options' seed + :data:`FRESH_SEED`); the history's ``start`` says which run each iteration belongs
        to.  Why several starts: the fit ends near where it starts on RAYX's hard counts, and
        neither a start's χ² nor its first stage's end tells which start ends lowest (a surrogate
        finder's offsets for a defocus it cannot represent start lower and end higher than no
        offsets).  The ends of the other starts that the frames do not tell from the kept
        one widen its covariance (:attr:`FitResult.alternatives`).  Why other rays: each fit ends
        fitted to its own rays' noise, and the end that is lowest on them need not be lowest on
        others (docs/explanations/diagnosis.md, "Why every start is fitted").
    executor : runs the starts side by side, then the ray draws (:func:`gather`; the result
        does not depend on it).
    """
    o = FitOptions.resolve(options)
    mdl = _Model(meas, state, engine, o, table)
    ridge = _ridge(mdl, o)
    history: list[dict] = []
    starts = [state, *also_from]
    if any(list(st.effects) != list(state.effects) for st in starts):
        raise InputError("the starts of one fit must hold the same effects")
    extra = o.posterior_starts if any(n for _, n in o.stages) else 0  # no iterations: a look at the start
    tagged = len(starts) > 1 or extra > 0
    region = float(chi2_dist.ppf(0.95, len(mdl.vector(state))))
    # each start on a model of its own, which counts its traces (the rays are the same)
    models = [mdl] + [_Model(meas, state, engine, o, table) for _ in starts[1:]]
    runs = _runs([(m, np.clip(mdl.vector(st), *mdl.bounds()), {"start": k} if tagged else {})
                  for k, (m, st) in enumerate(zip(models, starts))], ridge, progress, executor)
    ends = [(part[-1]["chi2"], k, z, pr, exact, part) for k, (z, pr, exact, part) in enumerate(runs)]
    if tagged:
        fresh = _Model(meas, state, engine, o.replace(seed=o.seed + FRESH_SEED), table)
        ends = _judged(fresh, ends, ridge)
        for round_ in range(POSTERIOR_ROUNDS if extra else 0):
            before = min(e[0] for e in ends)
            more, drawn = _from_the_posterior(mdl, ends, fresh, ridge, extra, progress, executor, round_)
            ends, models = ends + drawn, models + more
            if before - min(e[0] for e in drawn) <= region:
                break
        mdl.n_traces += fresh.n_traces
    kept = min(ends, key=lambda e: (e[0], e[1]))
    _, _, z, pr, exact, _ = kept
    # the other starts' ends that the frames do not tell from the kept one (their χ² on fresh rays
    # within the fitted parameters' joint 95 % region of it): the posterior is at least that wide
    # where the χ² has several valleys, which no curvature at one of them shows
    others = [e[2] for e in ends if e is not kept and e[0] - kept[0] <= region]
    for e in sorted(ends, key=lambda e: e is kept):  # the kept run's iterations last
        history += e[5]
    # the same fit on other rays, from where the first draw ended
    ks = range(1, o.ray_draws if mdl.params else 1)
    dms = [_Model(meas, state, engine, o.replace(seed=o.seed + k * RAY_DRAW_SEED), table) for k in ks]
    later = _runs([(dm, z, {"ray_draw": k}) for k, dm in zip(ks, dms)], ridge, progress, executor)
    draws = np.asarray([z] + [run[0] for run in later])
    history += [h for run in later for h in run[3]]
    mdl.n_traces += sum(m.n_traces for m in models[1:] + dms)
    averaged = len(draws) > 1
    if averaged:
        z, exact = np.clip(draws.mean(0), *mdl.bounds()), False
        # what the rays leave in the mean: one draw's variance, not a quarter of it.  The later
        # draws start where the first ended, and a fit on RAYX's hard counts ends near where it
        # starts, so they are not independent estimates: each moves only part of the way from the
        # first's end toward its own rays' minimum, the mean keeps most of the first draw's
        # error, and their scatter shows only the part they moved: draws that move a fraction a
        # of the way (S: one draw's variance at its own minimum) scatter by a^2 S while their
        # mean varies by S((1 - 3a/4)^2 + 3a^2/16): the scatter is four times that at a = 1
        # (conservative), equal to it at a = 0.6, and short of it below: so the larger is kept
        # (_Ends.widen adds their sample covariance).
    if not exact:
        # the uncertainty (and everything read from the Jacobian) at the twin's own Jacobian
        pr = mdl.products(o.stages[-1][0], z, True)
    r, G, dof, rows = mdl.residuals(o.stages[-1][0], pr)
    if averaged:
        # the mean's χ² on the first draw's rays: where the history ends, as the result
        c2 = _objective(r, z, ridge)
        history.append({"stage": o.stages[-1][0], "iteration": 0, "accepted": True, "chi2": c2, "dof": dof,
                        "chi2_reduced": c2 / max(dof, 1.0), "damping": history[-1]["damping"], "exact": True,
                        "ray_draw": "mean", **({"start": kept[1]} if tagged else {})})
        if progress:
            progress(history[-1])
    if o.settle and any(n for _, n in o.stages):  # a fit with no iterations is a look at its start
        z, pr = _settle(mdl, o.stages[-1][0], z, pr, ridge, history, progress)
    wider = _Ends(draws if averaged else None, others)
    result = _result(mdl, meas, state, engine, o, table, z, pr, ridge, history, wider)
    if o.estimate_spread and o.prior_sigma is not None and any(n for _, n in o.stages):
        result = _with_spread(mdl, meas, state, engine, o, table, result, wider, progress)
    return result


def _judged(fresh: _Model, ends: list[tuple], ridge: np.ndarray) -> list[tuple]:
    """Each end ``(χ², start, z, ...)`` with its χ² of the last stage on ``fresh``'s rays in place of its own."""
    last = fresh.o.stages[-1][0]
    return [(_objective(fresh.residuals(last, fresh.products(last, z, False))[0], z, ridge), k, z, *rest)
            for _, k, z, *rest in ends]


def _from_the_posterior(mdl: _Model, ends: list[tuple], fresh: _Model, ridge: np.ndarray, n: int,
                        progress: Callable[[dict], None] | None, executor: Executor | None,
                        round_: int = 0) -> tuple[list, list]:
    """The fit run from ``n`` draws of the posterior at the best of ``ends``, numbered after them.

    Returns the runs' models (each counts its traces) and their ends, judged on ``fresh``'s rays.
    ``round_``: which block of the draws' stream.
    """
    best = min(ends, key=lambda e: (e[0], e[1]))
    xs = _posterior_draws(mdl, best[2], best[3], ridge, n, stream(mdl.o.seed, "fit.posterior_starts", draw=round_))
    more = [_Model(mdl.meas, mdl.base, mdl.engine, mdl.o, mdl.table) for _ in xs]
    runs = _runs([(m, x, {"start": len(ends) + i}) for i, (m, x) in enumerate(zip(more, xs))], ridge, progress,
                 executor)
    return more, _judged(fresh, [(part[-1]["chi2"], len(ends) + i, z, pr, exact, part)
                                 for i, (z, pr, exact, part) in enumerate(runs)], ridge)


def _posterior_draws(mdl: _Model, z: np.ndarray, pr: _Products, ridge: np.ndarray, n: int, seed: int) -> np.ndarray:
    """``n`` draws of the Gaussian posterior at ``z`` (its products ``pr``), folded into the bounds.

    The Gauss-Newton covariance of the last stage, inflated by its χ²/dof where above 1, and the
    later half of the draws at twice its σ (:data:`WIDE_DRAWS`); a parameter the frames do not see
    (NaN) is not moved.
    """
    r, G, dof, _ = mdl.residuals(mdl.o.stages[-1][0], pr)
    cov = _posterior_covariance(G.T @ G, ridge) * max(1.0, float(r @ r) / max(dof, 1.0))
    vals, vecs = np.linalg.eigh(np.nan_to_num(0.5 * (cov + cov.T)))
    root = vecs * np.sqrt(np.clip(vals, 0.0, None))
    steps = np.random.default_rng(seed).standard_normal((n, len(z))) @ root.T
    steps[n - n // 2:] *= WIDE_DRAWS
    lo, hi = mdl.bounds()
    # folded back into the box, not clipped: a start on a bound tends to end there
    return hi - np.abs(np.mod(z + steps - lo, 2 * (hi - lo)) - (hi - lo))


@dataclass(frozen=True)
class _Ends:
    """What widens a fit's covariance beyond its curvature: the ray draws' ends, the other starts' ends."""

    draws: np.ndarray | None  # two or more; None: one draw
    others: list

    def widen(self, cov: np.ndarray, z: np.ndarray) -> np.ndarray:
        """``cov`` widened by the ray draws' spread and by the other starts' ends around the solution ``z``."""
        if self.draws is not None:
            # where the rays decided the end: what another draw would have moved it by
            cov = cov + np.where(np.isnan(cov), 0.0, np.cov(self.draws.T, ddof=1))
        if self.others:
            # each other end at two standard deviations from the solution, along its own direction
            d = np.asarray(self.others) - z
            cov = cov + np.where(np.isnan(cov), 0.0, d.T @ d / 4.0)
        return cov


def _result(mdl: _Model, meas, state, engine, o: FitOptions, table: ParameterTable, z: np.ndarray, pr: _Products,
            ridge: np.ndarray, history: list[dict], ends: _Ends) -> FitResult:
    """The fit's result at ``z`` (``pr``: the last stage's products there, with the twin's Jacobian).

    The covariance of the last stage: its information at the solution (two independent ray sets'
    Jacobians); a bound that holds a parameter does not shrink its uncertainty below what the data
    say.  Then inflated, widened by the jackknife, the ray draws' spread and the other starts' ends.
    """
    r, G, dof, rows = mdl.residuals(o.stages[-1][0], pr)
    cross = _Model(meas, state, engine, o.replace(seed=o.seed + CROSS_SEED), table)
    cov = _posterior_covariance(_fisher(mdl, cross, o.stages[-1][0], z, pr), ridge)
    mdl.n_traces += cross.n_traces
    chi2 = float(r @ r)
    inflation = max(1.0, chi2 / max(dof, 1.0))
    cov = cov * inflation
    with np.errstate(over="ignore", invalid="ignore"):
        jk = jackknife_covariance(G, r, rows, ridge, z)
    widen = np.ones(len(z))
    if jk is not None:
        v = np.diag(cov)
        # a parameter that one configuration alone determines has no delete-one estimate (its
        # step without that configuration is unbounded, and overflows to NaN): its Gauss-Newton σ stands
        ok = np.isfinite(v) & (v > 0) & np.isfinite(np.diag(jk))
        widen[ok] = np.sqrt(np.maximum(1.0, np.diag(jk)[ok] / v[ok]))
        cov = cov * np.outer(widen, widen)  # the variances widened, the correlations kept
    return FitResult(mdl.state(z), history, ends.widen(cov, z), mdl.names, chi2, dof, inflation, mdl.n_traces, G,
                     r, rows, o.stages[-1][0], ridge, widen, ends.draws,
                     np.asarray(ends.others) if ends.others else None)


SPREAD_REFIT = 0.95
"""An estimated spread below this share of the prior's refits the offsets under it (:func:`_with_spread`)."""


def _with_spread(mdl: _Model, meas, state, engine, o: FitOptions, table: ParameterTable, res: FitResult,
                 ends: _Ends, progress: Callable[[dict], None] | None) -> FitResult:
    """``res`` refitted under the offsets' spread its posterior's evidence prefers, where that is narrower.

    The last stage under the offsets' prior σ set to the estimate, settled (:func:`_settle`), from
    ``res``'s solution and from the Gaussian posterior's mean under it
    (:func:`~bluesky_offsets.model.posterior.shrunk_mean`: on RAYX's hard counts a fit ends near
    where it starts), the end lowest on fresh rays kept as
    :func:`fit` keeps it; the covariance there, under the same prior, widened as ``res``'s was by
    its ray draws and other starts.
    """
    z, prior = mdl.vector(res.state), o.prior_sigma
    assert prior is not None  # fit() asks only with a prior
    tau = evidence_spread(z, res.covariance, mdl.P, prior)
    if not tau < SPREAD_REFIT * prior:
        return res

    def tagged(d):
        d["spread"] = tau
        if progress:
            progress(d)
    sub = o.replace(prior_sigma=tau, stages=o.stages[-1:], settle=True, estimate_spread=False, ray_draws=1)
    mean = np.clip(shrunk_mean(z, res.covariance, mdl.P, prior, tau), *mdl.bounds())
    out = fit(meas, mdl.state(z), engine, sub, progress=tagged, table=table, also_from=[mdl.state(mean)])
    return replace(out, covariance=ends.widen(out.covariance, mdl.vector(out.state)),
                   history=res.history + out.history, n_traces=res.n_traces + out.n_traces, draws=ends.draws,
                   prior_sigma=tau)


SETTLE_FRACTIONS = (1.0, 0.5, 0.25)
"""The parts of the settling step tried in turn (:func:`_settle`)."""


def _settle(mdl: _Model, stage: str, z: np.ndarray, pr: _Products, ridge: np.ndarray, history: list[dict],
            progress: Callable[[dict], None] | None) -> tuple[np.ndarray, _Products]:
    """One undamped Gauss-Newton step from where the iterations stopped, kept where it lowers the objective.

    A stage stops once its steps gain less than the tolerance, before the prior has brought back
    the offsets the data barely see: their pull is far below that.  The undamped step finishes
    them (the posterior mean of the linearized model); half or a quarter of it where the whole
    step raises the objective (the model bends) or leaves the bounds, none where every part does.
    ``pr``: the products at ``z`` with the twin's Jacobian.
    """
    lo, hi = mdl.bounds()
    r, G, dof, _ = mdl.residuals(stage, pr)
    step, before = _lm_step(G, r, z, 0.0, ridge), _objective(r, z, ridge)
    kept, c2 = 0.0, before
    for frac in SETTLE_FRACTIONS:  # the whole step, else part of it where the model bends
        zc = z + frac * step
        if np.any(zc < lo) | np.any(zc > hi):  # beyond the box the linearized posterior is no guide
            continue
        rc, _, dof_c, _ = mdl.residuals(stage, mdl.products(stage, zc, False))
        after = _objective(rc, zc, ridge)
        if after <= before:
            kept, c2, dof = frac, after, dof_c
            break
    history.append({"stage": stage, "iteration": 0, "accepted": bool(kept), "chi2": c2, "dof": dof,
                    "chi2_reduced": c2 / max(dof, 1.0), "damping": 0.0, "exact": True, "settle": kept,
                    **{k: history[-1][k] for k in ("start", "ray_draw") if k in history[-1]}})
    if progress:
        progress(history[-1])
    return (zc, mdl.products(stage, zc, True)) if kept else (z, pr)


POSTERIOR_SAMPLE_STEPS = 3
"""Levenberg-Marquardt steps that move each of :func:`posterior_samples`' draws onto its frames."""
POSTERIOR_SAMPLE_REGION = 0.999
"""A sample whose χ² on the frames exceeds the fitted state's by more than this joint region of the
fitted parameters goes back toward the fitted state, halving, until the frames allow it."""
POSTERIOR_SAMPLE_HALVINGS = 6
"""Halvings at most of a forbidden sample's distance from the fitted state."""


def posterior_samples(meas, state, engine, options: FitOptions | Mapping | None = None, *, n: int = 12,
                      seed: int = 0, table: ParameterTable = METRIXS, executor: Executor | None = None) -> list:
    """``n`` states drawn from the posterior of the fitted ``state`` that fit ``meas``: randomize-then-optimize.

    Each draw perturbs the frames by a draw of their noise and the offsets' prior mean by a draw of
    the prior (``options.prior_sigma``); the undamped Gauss-Newton step from ``state`` on that
    perturbed problem is a draw of the linearized posterior, and :data:`POSTERIOR_SAMPLE_STEPS`
    Levenberg-Marquardt steps from there fit it where the χ² bends, on the options' last stage,
    traced with model rays of its own (named random streams of ``seed``).  For a linear model these
    are exact posterior draws.  Starting at the fitted state instead, the damped steps barely move
    along the directions the frames leave to the prior, and the samples miss the spread there
    (docs/explanations/optimize.md, "What that σ is worth").  A sample the frames forbid
    (:data:`POSTERIOR_SAMPLE_REGION`) is moved back toward ``state``.  The draws run side by side
    on ``executor`` (the same states without one).
    """
    o = FitOptions.resolve(options)
    calls = [lambda k=k: _posterior_sample(meas, state, engine, o, table, seed, k) for k in range(int(n))]
    return gather(calls, executor)


def _posterior_sample(meas, state, engine, o: FitOptions, table: ParameterTable, seed: int, k: int):
    """:func:`posterior_samples`' ``k``-th state."""
    mdl = _Model(meas, state, engine, o.replace(seed=stream(seed, "fit.posterior_sample_rays", draw=k)), table)
    stage, ridge = o.stages[-1][0], _ridge(mdl, o)
    lo, hi = mdl.bounds()
    z0 = np.clip(mdl.vector(state), lo, hi)
    pr = mdl.products(stage, z0, True)
    rng = np.random.default_rng(stream(seed, "fit.posterior_samples", draw=k))
    shift = rng.standard_normal(pr.values.shape)  # the frames' noise, in units of their σ
    mean = np.where(ridge > 0, rng.standard_normal(len(z0)) / np.sqrt(np.where(ridge > 0, ridge, 1.0)), 0.0)
    r0 = mdl.residuals(stage, pr)[0]
    fitted = float(r0 @ r0)  # the fitted state's χ² on this sample's rays
    r, G, _, _ = mdl.residuals(stage, pr, shift)
    z = np.clip(z0 + _lm_step(G, r, z0 - mean, 0.0, ridge), lo, hi)  # the linearized posterior's draw
    r, G, _, _ = mdl.residuals(stage, mdl.products(stage, z, True), shift)
    obj, lam, accepted = _objective(r, z - mean, ridge), o.damping, 0
    # a refused step costs a value, a tenth of a Jacobian: the damping grows fast and tries again
    for _ in range(3 * POSTERIOR_SAMPLE_STEPS):
        zc = np.clip(z + _lm_step(G, r, z - mean, lam, ridge), lo, hi)
        rc = mdl.residuals(stage, mdl.products(stage, zc, False), shift)[0]
        oc = _objective(rc, zc - mean, ridge)
        if oc >= obj:
            lam *= 10.0
            continue
        z, obj, lam, accepted = zc, oc, max(lam / 3.0, 1e-9), accepted + 1
        if accepted == POSTERIOR_SAMPLE_STEPS:
            break
        r, G, _, _ = mdl.residuals(stage, mdl.products(stage, z, True), shift)
    return mdl.state(_allowed(mdl, stage, z0, fitted, z))


def _allowed(mdl: _Model, stage: str, z0: np.ndarray, fitted: float, z: np.ndarray) -> np.ndarray:
    """``z``, or halfway back toward ``z0`` while its χ² on the frames exceeds ``fitted`` beyond :data:`POSTERIOR_SAMPLE_REGION`."""
    region = float(chi2_dist.ppf(POSTERIOR_SAMPLE_REGION, len(z)))
    for _ in range(POSTERIOR_SAMPLE_HALVINGS):
        r = mdl.residuals(stage, mdl.products(stage, z, False))[0]
        if float(r @ r) - fitted <= region:
            break
        z = z0 + 0.5 * (z - z0)
    return z


def _posterior_covariance(F: np.ndarray, ridge: np.ndarray) -> np.ndarray:
    """(F + prior)⁻¹ for the information ``F`` (:func:`~bluesky_offsets.model.posterior.scaled_inverse`).

    A parameter the data do not see at all (a thermal bump below its threshold: no bump, a zero
    column) has no uncertainty to give: NaN, not the pseudo-inverse's "± 0".
    """
    A = F + np.diag(ridge)
    cov = scaled_inverse(A)
    blind = np.diag(A) <= 0
    cov[blind, blind] = np.nan
    return cov


def information(meas, state, engine, options: FitOptions | Mapping | None = None, *,
                table: ParameterTable = METRIXS) -> FitResult:
    """``state`` looked at as it stands, no step taken.

    The last stage's residuals and the twin's exact Jacobian there, and the covariance their
    information gives (two independent ray sets' Jacobians, :func:`_fisher`; not inflated, not
    widened: what the data could say about each parameter there, the others free).  Two Jacobians of
    the twin; :func:`bluesky_offsets.model.diagnosis.detection_limits` reads from it how large an
    effect could be and still hide behind the offsets.
    """
    o = FitOptions.resolve(options)
    mdl = _Model(meas, state, engine, o, table)
    z = np.clip(mdl.vector(state), *mdl.bounds())
    stage = o.stages[-1][0]
    r, G, dof, rows = mdl.residuals(stage, mdl.products(stage, z, True))
    ridge = _ridge(mdl, o)
    cross = _Model(meas, state, engine, o.replace(seed=o.seed + CROSS_SEED), table)
    cov = _posterior_covariance(_fisher(mdl, cross, stage, z), ridge)
    return FitResult(mdl.state(z), [], cov, mdl.names, float(r @ r), dof, 1.0,
                     mdl.n_traces + cross.n_traces, G, r, rows, stage, ridge)


def jackknife_covariance(G: np.ndarray, r: np.ndarray, rows: np.ndarray, ridge: np.ndarray,
                         z: np.ndarray) -> np.ndarray | None:
    """Delete-one-configuration jackknife covariance of a fit's solution.

    Each configuration is left out in turn and the fit re-solved without it by one
    Gauss-Newton step from the solution (``r`` measured − model over σ, ``G`` the model's
    Jacobian over σ, ``ridge`` the prior's diagonal at ``z``); the covariance is
    ``(n − 1)/n Σ (d_i − d̄)(d_i − d̄)ᵀ`` over the n steps.  Where the model describes every
    configuration alike it agrees with the Gauss-Newton covariance; where one configuration
    pulls the solution its own way (a missing effect, a fit stopped short of its minimum on
    hard counts) it is wider.  None for fewer than three configurations.
    """
    confs = np.unique(rows)
    n = len(confs)
    if n < 3:
        return None
    A = G.T @ G + np.diag(ridge)
    b = G.T @ r - ridge * z
    steps = []
    for c in confs:
        m = rows == c
        Ac = A - G[m].T @ G[m]
        bc = b - G[m].T @ r[m]
        d = np.sqrt(np.clip(np.diag(Ac), 1e-300, None))
        steps.append(np.linalg.lstsq(Ac / np.outer(d, d), bc / d, rcond=1e-12)[0] / d)
    D = np.asarray(steps)
    D = D - D.mean(0)
    return (n - 1) / n * D.T @ D


def screen(meas, state, engine, options: FitOptions | Mapping | None = None, *, iterations: int = 6,
           table: ParameterTable = METRIXS) -> FitResult:
    """A cheap look at ``state``: secant steps of the features stage, then the last stage's χ² there.

    The features stage on one Jacobian of the twin (at ``state``) and its secant updates,
    ``iterations`` Levenberg-Marquardt steps; then the last stage's residuals where it ended (values
    only).  About a fifth of a :func:`fit`'s cost: what a diagnosis ranks its candidate starts by
    before it fits the best of them.  The result's χ² is the last stage's; its Jacobian and
    covariance are the features' at ``state`` (a look, not a solution: no uncertainty is read from
    it).
    """
    o = FitOptions.resolve(options)
    mdl = _Model(meas, state, engine, o, table)
    z = np.clip(mdl.vector(state), *mdl.bounds())
    ridge = _ridge(mdl, o)
    pr = mdl.products("features", z, True)
    r0, G0, _, rows0 = mdl.residuals("features", pr)  # the look's Jacobian: the twin's, at ``state``
    history: list[dict] = []
    z, _, _ = _stage(mdl, "features", z, pr, iterations, ridge, history, None, secant=True, look=True)
    stage = o.stages[-1][0]
    rl, _, dof_l, _ = mdl.residuals(stage, mdl.products(stage, z, False))
    chi2_l = float(rl @ rl)
    history.append({"stage": stage, "iteration": 0, "accepted": True, "chi2": chi2_l, "dof": dof_l,
                    "chi2_reduced": chi2_l / max(dof_l, 1.0), "damping": history[-1]["damping"], "exact": False})
    nan = np.full((len(z), len(z)), np.nan)
    return FitResult(mdl.state(z), history, nan, mdl.names, chi2_l, dof_l, 1.0, mdl.n_traces, G0, r0, rows0,
                     "features", ridge)
