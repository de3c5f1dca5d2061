"""Motor settings for a requested beam, computed on the calibrated differentiable twin.

:func:`optimize_settings` takes a target (:mod:`bluesky_offsets.optimize.targets`), the
calibrated model (offsets and effects, with the calibration's covariance) and where the motors
stand, and returns the settings that give the target beam within the motors' limits, the beam
the model predicts there and how far the calibration's uncertainty lets that prediction be
trusted.

How: Levenberg-Marquardt within the limits (the fit engine's step,
:func:`bluesky_offsets.model.fit.lm_step`) on the target's residuals, from the current setting,
``starts - 1`` random ones near it and the ``global_starts`` best of ``screen`` settings drawn
over the reachable box (half-widths up to each free motor's whole range: the focus a local
search misses lies elsewhere), each for ``survey`` steps and the ``keep`` lowest on to the end,
on one set of rays (common random numbers: the objective is a deterministic function of the
settings).  With ``draws`` and the calibration's covariance the
objective is the target's residuals averaged over the fitted state and states drawn from the
posterior: a setting whose beam is right only for the fitted offsets pays for it.  The
residuals' Jacobian in the motors is exact: every ray's derivatives from
:meth:`TorchEngine.ray_jacobian`, pushed through the target's residual function by forward-mode
differentiation.

The prediction is the hard beam (RAYX's survival) traced with fresh rays and read as a frame is
read (:func:`~bluesky_offsets.optimize.targets.focus_from_profiles` of the camera profiles,
detector-level effects applied).  Its uncertainty comes from the calibration's covariance
twice: propagated through each axis's variance, to first order and with the second-order
widening that dominates at an optimum (where the first derivatives vanish: an offset known to
±σ leaves the motor that corrects it off by as much), and as the spread of the predicted widths
over states drawn from the covariance, each read as a frame is (a spot half a pixel wide
changes its measured rms when its centroid moves across a pixel, which no derivative of the
rays sees); the larger of the two is given.  A state parameter whose share of a width's
uncertainty exceeds ``flag_above`` is flagged (for a motor: its setting is not pinned down), and
the prediction is marked untrusted when the total exceeds ``trust_below``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from concurrent.futures import Executor
from dataclasses import dataclass, field

import numpy as np
import torch

from bluesky_offsets.errors import InputError
from bluesky_offsets.options import refuse_unknown
from bluesky_offsets.physics import effects as E
from bluesky_offsets.physics.parameters import MAX_OFFSET, METRIXS, ParameterTable
from bluesky_offsets.physics.engine import FORWARD_AD
from bluesky_offsets.physics.twin import CAMERA
from bluesky_offsets.streams import stream

from .targets import (
    Constraints,
    Focus,
    Rays,
    Target,
    focus_from_profiles,
    per_ray,
    target_from,
)


class TargetUnreachable(ValueError):
    """The model's best within the limits misses the target; nothing was moved.

    The message names the motors held at a limit that the target pushes against.
    """


class DarkStart(ValueError):
    """No light on the screen at the current setting: the beam must be found first."""


@dataclass(frozen=True)
class OptimizeOptions:
    """How :func:`optimize_settings` runs (unknown keys are refused).

    Parameters
    ----------
    rays, seed : int
        the model rays of the optimization (one set: common random numbers).
    starts : int
        the current setting and ``starts - 1`` random ones within ``spread`` of each free
        motor's range around it.
    screen, global_starts : int
        ``screen`` settings drawn over the reachable box (half-widths from
        ``spread`` to each free motor's whole range), the objective evaluated at each; the
        ``global_starts`` best are started from too (0: the local starts alone).
    draws : int
        states drawn from the calibration's covariance that the objective averages over,
        beside the fitted one (0, the default, or no covariance: the fitted state alone); each
        traces ``rays // (draws + 1)`` rays.  Off by default: where most offsets are
        undetermined the draws' average favours a compromise over the fitted state's focus
        (docs/explanations/optimize.md).
    iterations : int
        Levenberg-Marquardt steps per start at most; ``tolerance`` the relative gain
        below which a start ends.
    survey, keep : int
        with more than ``keep`` starts, each runs ``survey`` steps first and only the ``keep``
        lowest then run on to ``iterations`` (a start that converged within its survey ends there).
    check_rays, check_seed : int
        the prediction: the hard beam, fresh rays.
    flag_above : float
        a state parameter whose uncertainty alone changes a predicted width by more
        than this (relative) is flagged.
    trust_below : float
        the prediction is trusted while its relative uncertainty stays below this.
    samples : int
        states drawn from the calibration's covariance to read the prediction's spread as
        frames would (:func:`sampled_sigma`); 0 or 1: the linear propagation alone.
    posterior_samples : int
        where the calibration's frames are at hand (``plans.optimize.optimize_beam``'s
        ``measurement``): states drawn from its posterior onto them
        (:func:`~bluesky_offsets.model.fit.posterior_samples`) that the spread is read from
        instead; 0 or 1: the covariance's draws.
    engine : mapping, optional
        torch engine options (:class:`~bluesky_offsets.physics.engine.TorchOptions`).
    """

    rays: int = 20_000
    seed: int = 11
    starts: int = 3
    spread: float = 0.03
    screen: int = 192
    global_starts: int = 16
    survey: int = 6
    keep: int = 4
    draws: int = 0
    iterations: int = 30
    tolerance: float = 1e-4
    check_rays: int = 100_000
    check_seed: int = 12_345
    flag_above: float = 0.02
    trust_below: float = 0.10
    samples: int = 24
    posterior_samples: int = 12
    engine: Mapping | None = None

    def __post_init__(self):
        for k in ("samples", "posterior_samples", "screen", "global_starts", "draws"):
            if int(getattr(self, k)) < 0:
                raise InputError(f"optimize option {k} must be >= 0, got {getattr(self, k)!r}")
        for k in ("rays", "starts", "iterations", "check_rays", "survey", "keep"):
            if int(getattr(self, k)) < 1:
                raise InputError(f"optimize option {k} must be at least 1, got {getattr(self, k)!r}")
        for k in ("spread", "tolerance", "flag_above", "trust_below"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"optimize option {k} must be a positive number, got {v!r}")

    @classmethod
    def resolve(cls, options: OptimizeOptions | Mapping | None) -> OptimizeOptions:
        """``options`` as given, the defaults for None, or options from a mapping (unknown keys refused)."""
        if isinstance(options, OptimizeOptions):
            return options
        options = dict(options or {})
        refuse_unknown(cls, options, "unknown optimize option(s)")
        return cls(**options)


@dataclass
class Flag:
    """A state parameter the prediction depends on more than its calibration allows."""

    parameter: str
    sigma: float                 # its uncertainty, physical units
    unit: str
    effect: dict[str, float]     # its share of each width's ("x", "y") relative uncertainty
    motorized: bool

    def text(self) -> str:
        """One line: the parameter, its σ, and its share of the width it affects most."""
        worst = max(self.effect, key=lambda a: self.effect[a])
        what = "its motor's setting is not pinned down" if self.motorized else "not pinned down"
        return (f"{self.parameter} (± {self.sigma:.3g} {self.unit}, {what}): its share ± {self.effect[worst]:.1%} "
                f"of the {worst} width")


@dataclass
class BeamOptimum:
    """What :func:`optimize_settings` found."""

    target: Target
    settings: np.ndarray            # (P,) twin coordinates, table order
    current: np.ndarray             # (P,) where the motors stood
    moved: list[str]                # parameters whose setting changes
    predicted: Focus                # the model's beam at ``settings`` (hard, fresh rays, as a frame is read)
    predicted_before: Focus         # the model's beam at ``current``
    sigma: dict[str, float]         # σ of the predicted rms width per axis (mm), its ray noise in; NaN: none given
    flags: list[Flag]
    trusted: bool
    at_limit: list[str]             # free motors that end at a bound
    cost: float
    history: list[dict] = field(default_factory=list)
    starts: list[dict] = field(default_factory=list)
    profiles: tuple[np.ndarray, np.ndarray] | None = None   # predicted camera profiles at ``settings``
    states: int = 1                 # states the objective averaged over (the fitted one and the posterior's draws)
    sampled: int = 0                # posterior states fitted to the frames that ``sigma`` is read from (0: covariance)

    def relative_sigma(self, axis: str) -> float:
        """The predicted rms width's uncertainty along ``axis`` (``"x"``/``"y"``) over the width."""
        return self.sigma[axis] / getattr(self.predicted, f"rms_{axis}")

    def summary(self) -> str:
        """One line: the predicted rms widths with their σ and, where the prediction is not trusted, why."""
        p = self.predicted
        s = f"predicted {p.rms_x * 1e3:.1f} x {p.rms_y * 1e3:.1f} µm rms"
        if all(math.isfinite(self.sigma[a]) for a in "xy"):
            s += f" (± {self.sigma['x'] * 1e3:.1f}, ± {self.sigma['y'] * 1e3:.1f})"
        if self.trusted:
            return s
        if not all(math.isfinite(self.sigma[a]) for a in "xy"):
            return s + " — not trusted: no calibration uncertainty given"
        return s + " — not trusted: " + "; ".join(f.text() for f in self.flags[:3])


def moved_names(current: np.ndarray, settings: np.ndarray, table: ParameterTable = METRIXS,
                free: np.ndarray | None = None) -> list[str]:
    """The parameters (of ``free``, default all) whose setting differs from ``current`` beyond rounding."""
    free = np.ones(len(table), bool) if free is None else free
    return [table.names[i] for i in np.flatnonzero(free) if abs(settings[i] - current[i]) > 1e-9 * table.span[i]]


# --------------------------------------------------------------------------- #
# the model as a function of the settings
# --------------------------------------------------------------------------- #
class _Problem:
    """The target's residuals as a function of the free motors, over the fitted state and the posterior's draws.

    ``u``: the free motors' moves in fractions of each range from the current setting; the states
    are the rows of ``offsets`` (physical units; the first the fitted state's).
    """

    def __init__(self, target: Target, state, current, lo, hi, free, options: OptimizeOptions, engine, overrides,
                 table: ParameterTable, draws: np.ndarray | None = None):
        self.target, self.state, self.o, self.engine, self.table = target, state, options, engine, table
        self.current = np.asarray(current, float)
        self.lo, self.hi, self.free = lo, hi, free
        normalized = np.atleast_2d(state.offsets) if draws is None else np.vstack([state.offsets, draws])
        self.offsets = table.offsets_to_physical(np.clip(normalized, -MAX_OFFSET, MAX_OFFSET))
        self.n = max(1, options.rays // len(self.offsets))   # rays per state
        self.twin_effects = _twin_effects(state)
        self.extra = dict(overrides or {})
        self.overrides = _rml_overrides(state, overrides)
        self.span = table.span[free]
        self.start: Focus | None = None
        self.floor = 0.0

    def config(self, u: np.ndarray) -> np.ndarray:
        c = self.current.copy()
        c[self.free] = self.current[self.free] + u * self.span
        return c

    def bounds_u(self):
        return (self.lo[self.free] - self.current[self.free]) / self.span, \
               (self.hi[self.free] - self.current[self.free]) / self.span

    def keep(self, states) -> None:
        """Keep these states (indices; the fitted state, 0, always)."""
        self.offsets = self.offsets[sorted({0, *states})]
        self.n = max(1, self.o.rays // len(self.offsets))

    def values(self, cfg) -> np.ndarray:
        """(S, P) physical values of the setting ``cfg`` in each state."""
        return np.asarray(cfg, float)[None] + self.offsets

    def rays(self, cfgs) -> list[list[Rays]]:
        """The rays of each setting of ``cfgs`` (N, P) in each state, one batch."""
        vals = np.concatenate([self.values(c) for c in np.atleast_2d(cfgs)])
        with torch.no_grad():
            b = self.engine.beam(vals, self.overrides or None, n_rays=self.n, seed=self.o.seed,
                                 edge=self.engine.options.edge)
        out = [Rays(b.x[k][keep], b.y[k][keep], b.weight[k][keep], self.n) for k, keep in enumerate(b.weight > 0)]
        S = len(self.offsets)
        return [out[i:i + S] for i in range(0, len(out), S)]

    def residuals(self, rays: list[Rays]) -> torch.Tensor:
        """The target's residuals of every state, and the transmission floor on the mean intensity.

        The residuals are scaled so that their sum of squares is the mean cost over the states.
        """
        assert self.start is not None  # optimize() sets it before the first step
        r = torch.cat([self.target.residuals(x, self.start).reshape(-1) for x in rays]) / math.sqrt(len(rays))
        if self.floor > 0:  # the transmission floor, a steep wall
            mean = torch.stack([x.intensity for x in rays]).mean()
            r = torch.cat([r, (30.0 * torch.relu(math.log(self.floor) - torch.log(mean.clamp(min=1e-300))))[None]])
        return r

    def _cost(self, rays: list[Rays]) -> float:
        if any(float(x.w.sum()) <= 0 for x in rays):
            return math.inf
        r = self.residuals(rays)
        c = float(r @ r)
        return c if math.isfinite(c) else math.inf

    def cost(self, cfg) -> float:
        return self._cost(self.rays(cfg)[0])

    def costs(self, cfgs, batch: int = 8) -> np.ndarray:
        """The cost of each setting of ``cfgs`` (N, P), ``batch`` settings per trace."""
        cfgs = np.atleast_2d(cfgs)
        return np.array([self._cost(r) for i in range(0, len(cfgs), batch) for r in self.rays(cfgs[i:i + batch])])

    def ray_jacobian(self, cfg, effects: bool = False, columns=None):
        # with the effects as inputs (the prediction's uncertainty): the fitted state alone
        vals, n = (self.values(cfg)[:1], self.o.rays) if effects else (self.values(cfg), self.n)
        return self.engine.ray_jacobian(vals, self.twin_effects if effects else None, n_rays=n, seed=self.o.seed,
                                        overrides=self.overrides if not effects else (self.extra or None),
                                        columns=columns), n

    def linearized(self, cfg, func: Callable[[list[Rays]], torch.Tensor], columns=None, effects: bool = False):
        """``func``'s residuals at the rays of ``cfg``, their Jacobian and the exact gradient of their sum of squares.

        The residuals at the rays of ``cfg`` (one :class:`Rays` per state), their Jacobian (m, n) in
        the inputs ``columns`` (indices into the ray Jacobian's inputs; default the free motors)
        with the rays' weights held, and the exact gradient (n,) of their sum of squares.

        Why two: a ray in an aperture's soft edge has a weight derivative of the order of the
        weight over the edge's width.  Summed over the rays (the gradient) these average into
        the derivative of the light cut; squared ray by ray (a Gauss-Newton matrix) they would
        not, and would swamp it.  So the curvature comes from the rays' moves, the slope from
        everything.
        """
        cols = np.flatnonzero(self.free) if columns is None else np.asarray(columns)
        rj, n = self.ray_jacobian(cfg, effects, cols)  # the derivatives in these inputs only
        rows = rj.rows
        x, y, w = (t.reshape(-1)[rows].detach() for t in (rj.x, rj.y, rj.weight))
        tx, ty, tw = (t.T.contiguous() for t in (rj.rows_jx, rj.rows_jy, rj.rows_jw))
        state = torch.as_tensor(rows) // n
        groups = [torch.nonzero(state == k).reshape(-1) for k in range(rj.x.shape[0])]

        def split(a, b, c):
            return [Rays(a[g], b[g], c[g], n) for g in groups]

        def moved(a, b):
            return func(split(a, b, w))

        def total(a, b, c):
            r = func(split(a, b, c))
            return (r * r).sum()

        value = moved(x, y)
        with FORWARD_AD:
            jac = torch.func.vmap(lambda dx, dy: torch.func.jvp(moved, (x, y), (dx, dy))[1])(tx, ty)
            grad = torch.func.vmap(lambda dx, dy, dw: torch.func.jvp(total, (x, y, w), (dx, dy, dw))[1])(tx, ty, tw)
        return value.detach().numpy(), jac.T.detach().numpy(), grad.detach().numpy()


def _twin_effects(state) -> dict:
    return {n: v for n, v in state.effects.items() if E.get(n).level == "twin"}


def _rml_overrides(state, extra) -> dict:
    """The RML overrides the twin traces ``state`` with: its twin-level effects, then ``extra``."""
    twin = _twin_effects(state)
    ov = E.twin_overrides(twin) if twin else {}
    for obj, flds in (extra or {}).items():
        ov.setdefault(obj, {}).update(flds)
    return ov


def _step(A: np.ndarray, g: np.ndarray, lam: float) -> np.ndarray:
    """The Levenberg-Marquardt step for curvature ``A`` (Gauss-Newton) and gradient ``g`` of the cost."""
    d = np.diag(A).copy()
    d[d <= 0] = 1.0
    M = A + lam * np.diag(d) + 1e-12 * np.trace(A) / len(A) * np.eye(len(A))
    try:
        return -np.linalg.solve(M, g)
    except np.linalg.LinAlgError:
        return -np.linalg.lstsq(M, g, rcond=None)[0]


# --------------------------------------------------------------------------- #
# the optimizer
# --------------------------------------------------------------------------- #
def bounds(current, constraints: Constraints, limits=None, table: ParameterTable = METRIXS):
    """Lower and upper bounds (P,) of the settings and the free mask.

    The motors' limits (``limits`` (lo, hi) arrays, default each parameter's travel), narrowed by
    the constraints' limits and travel; held and fixed parameters stay where they are.
    """
    current = np.asarray(current, float)
    if limits is None:
        lo = np.array([p.limits[0] for p in table])
        hi = np.array([p.limits[1] for p in table])
    else:
        lo, hi = (np.asarray(v, float).copy() for v in limits)
    for name, (a, b) in constraints.limits.items():
        i = table.index(name)
        lo[i], hi[i] = max(lo[i], a), min(hi[i], b)
    for name, t in constraints.travel.items():
        i = table.index(name)
        lo[i], hi[i] = max(lo[i], current[i] - t), min(hi[i], current[i] + t)
    free = table.motorized.copy()
    for name in constraints.hold:
        free[table.index(name)] = False
    # a hair inside: a setting reached as start + (setting - current) must not round past a limit
    # (e.g. 14.000000000000002 against a limit of 14, which the motor refuses)
    margin = 1e-9 * table.span
    lo, hi = lo + margin, hi - margin
    free &= hi > lo
    return np.where(free, lo, current), np.where(free, hi, current), free


def _soft_focus(rays: Rays) -> Focus:
    return Focus(float(rays.intensity), float(rays.centroid("x")), float(rays.centroid("y")),
                 float(rays.rms("x")), float(rays.rms("y")))


def _lm(pb: _Problem, u0: np.ndarray, progress, label: str, iterations: int,
        done: int = 0) -> tuple[np.ndarray, float, list[dict]]:
    """Levenberg-Marquardt from ``u0`` for ``iterations`` at most, numbered after the ``done`` before.

    Its history's last entry says ``"converged"``: whether it stopped by itself (more would gain nothing).
    """
    lo, hi = pb.bounds_u()
    u = np.clip(u0, lo, hi)
    cost = pb.cost(pb.config(u))
    hist = [{"start": label, "iteration": done, "cost": cost, "accepted": True, "converged": False}]
    if not math.isfinite(cost):
        hist[-1]["converged"] = True
        return u, cost, hist
    lam, small = 1e-3, 0

    def linear(u):  # Gauss-Newton curvature and gradient of the cost, per unit of u
        _, J, g = pb.linearized(pb.config(u), pb.residuals)
        J = J * pb.span[None, :]
        return 2.0 * J.T @ J, g * pb.span

    A, g = linear(u)
    for it in range(done + 1, done + iterations + 1):
        # motors at a bound that the gradient pushes further out stay there; the step is
        # solved for the others (a clipped full step wastes most iterations at a bound)
        pinned = ((u - lo < 1e-9) & (g > 0)) | ((hi - u < 1e-9) & (g < 0))
        step = np.zeros_like(u)
        act = ~pinned
        if act.any():
            step[act] = _step(A[np.ix_(act, act)], g[act], lam)
        uc = np.clip(u + step, lo, hi)
        cc = pb.cost(pb.config(uc))
        ok = cc < cost and bool(np.any(uc != u))
        if ok:
            gain = (cost - cc) / max(cost, 1e-300)
            small = small + 1 if gain < pb.o.tolerance else 0
            u, cost = uc, cc
            A, g = linear(u)
            lam = max(lam / 3.0, 1e-9)
        else:
            lam *= 4.0
        converged = small >= 2 or lam > 1e6
        hist.append({"start": label, "iteration": it, "cost": cost, "accepted": bool(ok), "damping": lam,
                     "converged": converged})
        if progress:
            progress(hist[-1])
        if converged:
            break
    return u, cost, hist


def _search(pb: _Problem, inits: list[tuple[str, np.ndarray]], progress,
            executor: Executor | None) -> list[tuple[np.ndarray, float, list[dict]]]:
    """Every start for ``survey`` iterations, then the ``keep`` lowest of those not yet converged to the end.

    Why: the global starts' screened costs say little about where their descents end (a valley
    a few µm wide lies between screen points); a few iterations each do.
    """
    from bluesky_offsets.model.fit import gather
    o = pb.o
    first = o.iterations if len(inits) <= o.keep else min(o.survey, o.iterations)
    runs = gather([lambda u0=u0, label=label: _lm(pb, u0, progress, label, first) for label, u0 in inits], executor)
    more = o.iterations - first
    open_ = [k for k, (_, cost, hist) in enumerate(runs) if not hist[-1]["converged"] and math.isfinite(cost)]
    go_on = sorted(open_, key=lambda k: (runs[k][1], k))[:o.keep] if more else []
    later = gather([lambda k=k: _lm(pb, runs[k][0], progress, inits[k][0], more, first) for k in go_on], executor)
    for k, (u, cost, hist) in zip(go_on, later):
        runs[k] = (u, cost, runs[k][2] + hist[1:])
    return runs


def _root(covariance) -> np.ndarray:
    """A square root ``R`` (``R Rᵀ = C``) of the covariance.

    Its non-finite entries are taken as 0 and its negative eigenvalues clipped: ``state + R z`` for
    standard normal ``z`` draws from it.
    """
    cov = np.where(np.isfinite(covariance), covariance, 0.0)
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    return V * np.sqrt(np.clip(w, 0, None))


def posterior_draws(state, covariance, n: int, *, seed: int = 0, table: ParameterTable = METRIXS) -> np.ndarray | None:
    """``n`` normalized offset vectors drawn from the calibration's covariance around ``state``'s offsets.

    The covariance's first ``len(table)`` rows and columns; the draws lie within the offsets'
    bounds; None without a covariance or draws.
    """
    if covariance is None or n < 1:
        return None
    P = len(table)
    root = _root(np.asarray(covariance, float)[:P, :P])
    z = np.random.default_rng([seed, 7]).standard_normal((n, P))
    return np.clip(np.asarray(state.offsets, float)[None] + z @ root.T, -MAX_OFFSET, MAX_OFFSET)


def _starts(pb: _Problem, o: OptimizeOptions) -> list[tuple[str, np.ndarray]]:
    """The labelled starts (``u``).

    The current setting, ``starts - 1`` random ones near it, and the ``global_starts`` lowest-cost
    of ``screen`` settings drawn over the reachable box.
    """
    rng = np.random.default_rng(o.seed)
    ulo, uhi = pb.bounds_u()
    m = len(ulo)
    out = [("current", np.zeros(m))]
    out += [(f"random {k}", np.clip(rng.uniform(-o.spread, o.spread, m), ulo, uhi)) for k in range(1, o.starts)]
    if o.screen and o.global_starts:
        radii = np.geomspace(o.spread, 1.0, o.screen)   # from near to the whole range
        cand = np.clip(rng.uniform(-1.0, 1.0, (o.screen, m)) * radii[:, None], ulo, uhi)
        c = pb.costs(np.array([pb.config(u) for u in cand]))
        order = [int(i) for i in np.argsort(c) if math.isfinite(c[i])][:o.global_starts]
        out += [(f"global {k + 1} (cost {c[i]:.3g})", cand[i]) for k, i in enumerate(order)]
    return out


def predict(state, configuration, *, rays: int = 100_000, seed: int = 12_345, overrides=None, engine=None,
            table: ParameterTable = METRIXS) -> tuple[Focus, np.ndarray, np.ndarray]:
    """The model's footprint at ``configuration`` as a frame reads it: its :class:`Focus` and the profiles.

    The hard beam (fresh rays), camera profiles, the state's detector-level effects.
    """
    return predict_many([state], configuration, rays=rays, seed=seed, overrides=overrides, engine=engine,
                        table=table)[0]


def predict_many(states, configuration, *, rays: int = 100_000, seed: int = 12_345, overrides=None, engine=None,
                 table: ParameterTable = METRIXS) -> list[tuple[Focus, np.ndarray, np.ndarray]]:
    """:func:`predict` for several states (one batch, the same rays) at one configuration."""
    from bluesky_offsets.physics.beamline import torch_engine
    from bluesky_offsets.physics.engine import histograms
    engine = engine or torch_engine(table)
    vals, ovs = [], []
    for st in states:
        ovs.append(_rml_overrides(st, overrides))
        vals.append(table.model_values(configuration, st.offsets))
    shared = all(o == ovs[0] for o in ovs)
    with torch.no_grad():
        beam = engine.beam(np.stack(vals), (ovs[0] or None) if shared else ovs, n_rays=rays, seed=seed)
        hx, hy = histograms(beam, CAMERA)
    out = []
    for k, st in enumerate(states):
        px, py = hx[k].numpy().astype(float), hy[k].numpy().astype(float)
        det = {n: v for n, v in st.effects.items() if E.get(n).level == "detector"}
        if det:
            px, py = (a[0] for a in E.apply_detector_effects(px[None], py[None], det, CAMERA))
        out.append((focus_from_profiles(px, py, CAMERA), px, py))
    return out


def covariance_states(state, covariance, names, n: int, *, seed: int = 0, table: ParameterTable = METRIXS) -> list:
    """``n`` model states drawn from the calibration's Gaussian covariance around ``state``.

    The covariance is over the normalized offsets, then effect parameters, ``names`` in that
    order; an effect parameter is clipped to its range, an offset is not.
    """
    from bluesky_offsets.model.state import ModelState
    P = len(table)
    root = _root(covariance)
    eff_names = list(names[P:]) if names is not None else []
    z0 = np.r_[state.offsets, [state.effects.get(name.split(".", 1)[0], {}).get(name.split(".", 1)[1], 0.0)
                               for name in eff_names]]
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(n):
        z = z0 + root @ rng.standard_normal(len(z0))
        effects = {e: dict(v) for e, v in state.effects.items()}
        for name, v in zip(eff_names, z[P:]):
            e, p = name.split(".", 1)
            if e in effects:
                q = next(q for q in E.get(e).parameters if q.name == p)
                effects[e][p] = float(np.clip(v, q.low, q.high))
        draws.append(ModelState(z[:P], effects, state.label))
    return draws


def sampled_sigma(state, configuration, covariance, names, *, samples: int = 24, rays: int = 30_000, seed: int = 0,
                  overrides=None, engine=None, table: ParameterTable = METRIXS) -> dict[str, float]:
    """The spread of the predicted rms widths over states drawn from the calibration's covariance.

    The covariance is over the normalized offsets, then effect parameters, ``names`` in that order;
    each state is read as a frame is (hard beam, camera pixels): what the linear propagation misses
    at an optimum, where a shifted centroid lands the spot on other pixels, is in it.
    """
    draws = covariance_states(state, covariance, names, samples, seed=seed, table=table)
    return states_sigma(draws, configuration, rays=rays, seed=seed, overrides=overrides, engine=engine, table=table)


def states_sigma(states, configuration, *, about=None, rays: int = 30_000, seed: int = 0, overrides=None,
                 engine=None, table: ParameterTable = METRIXS) -> dict[str, float]:
    """The spread of the predicted rms widths over ``states`` at ``configuration``, each read as a frame is.

    Their standard deviation, or with ``about`` (the fitted state, traced with the same rays) their
    root-mean-square distance from its width: where the posterior's mean focus lies off the fitted
    state's, the prediction misses by that too.
    """
    traces = stream(seed, "optimizer.posterior_draws")  # the draws' rays, apart from the draws themselves
    batch = [*states, *([] if about is None else [about])]
    foci = [f for f, _, _ in predict_many(batch, configuration, rays=rays, seed=traces, overrides=overrides,
                                          engine=engine, table=table)]
    out = {}
    for a in "xy":
        w = np.array([getattr(f, f"rms_{a}") for f in foci], float)
        out[a] = (float(np.nanstd(w, ddof=1)) if about is None
                  else float(np.sqrt(np.nanmean((w[:-1] - w[-1]) ** 2))))
    return out


def samples_covariance(samples) -> np.ndarray:
    """The covariance of posterior samples (model states), over the normalized offsets, then effect parameters."""
    z = np.asarray([st.vector() for st in samples], float)
    return np.atleast_2d(np.cov(z.T, ddof=1))


def _uncertainty(pb: _Problem, cfg, covariance, names, o: OptimizeOptions, table: ParameterTable):
    """Per-axis σ of the predicted rms width from the state's covariance, and the flags."""
    nan = {"x": float("nan"), "y": float("nan")}
    if covariance is None:
        return nan, [], False
    cov = np.asarray(covariance, float)
    P = len(table)
    n_eff = len(cov) - P
    # the covariance in physical units: offsets are normalized (fractions of each range)
    scale = np.r_[table.span, np.ones(n_eff)]
    cov = cov * np.outer(scale, scale)
    cov = np.where(np.isfinite(cov), cov, 0.0)
    eff_names = [n for n in names[P:]] if names is not None else []
    # effect columns the ray Jacobian knows (twin-level effects); detector ones enter nothing here
    rj_cols = list(range(P))
    cov_idx = list(range(P))
    k = P
    for e, vals in pb.state.effects.items():
        for p in vals:
            nm = f"{e}.{p}"
            if E.get(e).level == "twin" and nm in eff_names:
                rj_cols.append(k)
                cov_idx.append(P + eff_names.index(nm))
            k += 1 if E.get(e).level == "twin" else 0
    C = cov[np.ix_(cov_idx, cov_idx)]
    sig, contrib = {}, {}
    for axis in "xy":
        # mypy cannot infer a lambda with a default argument (the loop variable bound)
        r, J, g = pb.linearized(cfg, lambda rays, a=axis: per_ray(rays[0], a),  # type: ignore[misc]
                                columns=rj_cols, effects=True)
        var = float(r @ r)                     # g: d var / d state
        JtJ = J.T @ J                          # half the Gauss-Newton Hessian of var
        first = float(g @ C @ g)
        second = float(np.trace(JtJ @ C))      # expected widening of var
        sig[axis] = math.sqrt(first + second ** 2) / (2.0 * math.sqrt(var))
        # each parameter's share of that variance (shares sum to it; correlated parameters that
        # compensate each other share little even where each alone is poorly known)
        share = g * (C @ g) + second * np.diag(JtJ @ C)
        contrib[axis] = np.sqrt(np.abs(share)) / (2.0 * var)   # relative, on the rms width
    flags = []
    labels = list(table.names) + [names[i] for i in cov_idx[P:]] if names is not None else list(table.names)
    for j, name in enumerate(labels):
        eff = {a: float(contrib[a][j]) for a in "xy"}
        if max(eff.values()) > o.flag_above and C[j, j] > 0:
            is_param = j < P
            unit = table[name].unit if is_param else ""
            flags.append(Flag(name, float(math.sqrt(C[j, j])), unit, eff, bool(is_param and table[name].motorized)))
    flags.sort(key=lambda f: -max(f.effect.values()))
    return sig, flags, True


def _sigma(pb: _Problem, settings, covariance, names, samples, profiles, o: OptimizeOptions, table: ParameterTable):
    """The predicted widths' σ at ``settings``, the flags, whether known: from ``samples`` where given, else ``covariance``.

    The larger of the linear propagation and the spread over the states, read as frames are, and
    the prediction's own ray noise (its ``profiles``, x and y).  Fewer than two samples count as none.
    """
    samples = _fitted(samples)
    sigma, flags, known = _uncertainty(pb, settings, covariance if samples is None else samples_covariance(samples),
                                       names, o, table)
    if known and (samples is not None or o.samples > 1):
        drawn = (sampled_sigma(pb.state, settings, covariance, names, samples=o.samples, seed=o.check_seed,
                               overrides=pb.extra, engine=pb.engine, table=table) if samples is None else
                 states_sigma(samples, settings, about=pb.state, seed=o.check_seed, overrides=pb.extra,
                              engine=pb.engine, table=table))
        sigma = {a: max(sigma[a], drawn[a]) for a in "xy"}
    px, py = profiles
    return (_with_ray_noise(sigma, px, py, o.check_rays) if known else sigma), flags, known


def _fitted(samples):
    """``samples`` where there are two or more (a spread), else None."""
    return samples if samples is not None and len(samples) > 1 else None


def prediction_sigma(state, settings, *, covariance=None, names=None, samples=None,
                     options: OptimizeOptions | Mapping | None = None, overrides=None, engine=None,
                     table: ParameterTable = METRIXS) -> dict[str, float]:
    """The σ (mm, per axis) of the rms widths predicted at ``settings``, as :func:`optimize_settings` gives it.

    From ``samples`` (two or more posterior states fitting the frames) where given, else from
    ``covariance`` over ``names``; NaN with neither.  ``options`` as the optimization's: its rays
    and seeds are the σ's.
    """
    from bluesky_offsets.physics.beamline import torch_engine
    o = OptimizeOptions.resolve(options)
    settings = table.validate(settings, "settings").astype(float)
    engine = engine or torch_engine(table, options=dict(o.engine or {}))
    pb = _Problem(target_from("smallest_focus"), state, settings, settings, settings, np.ones(len(table), bool), o,
                  engine, overrides, table)
    _, px, py = predict(state, settings, rays=o.check_rays, seed=o.check_seed, overrides=overrides, engine=engine,
                        table=table)
    return _sigma(pb, settings, covariance, names, samples, (px, py), o, table)[0]


def _with_ray_noise(sigma: Mapping[str, float], px, py, rays: int) -> dict[str, float]:
    """``sigma`` with the prediction's own ray noise added in quadrature.

    The prediction traces ``rays`` rays, and the states' spread is read on rays they share, so it
    leaves that noise out.
    """
    counted = focus_from_profiles(px, py, CAMERA, n_rays=rays)
    return {a: math.hypot(sigma[a], float(np.nan_to_num(getattr(counted, f"sigma_rms_{a}")))) for a in "xy"}


def optimize_settings(target, state, current, *, limits=None, constraints: Constraints | Mapping | None = None,
                      covariance=None, names=None, samples=None, options: OptimizeOptions | Mapping | None = None,
                      overrides=None, engine=None, progress: Callable[[dict], None] | None = None,
                      executor: Executor | None = None, table: ParameterTable = METRIXS) -> BeamOptimum:
    """The motor settings that give ``target`` on the model ``state``, within the limits.

    Parameters
    ----------
    target : Target, name or mapping (:func:`~bluesky_offsets.optimize.targets.target_from`).
    state : ModelState
        The calibrated model: normalized offsets and effects.
    current : array_like (P,)
        Where the motors stand (twin coordinates, table order).
    limits : (lo, hi) arrays (P,), optional
        The motors' limits in twin coordinates (default: each parameter's travel).
    constraints : Constraints or mapping (held motors, travel, narrower limits, transmission).
    covariance, names : the calibration's covariance (normalized offsets, then effect parameters,
        ``names`` in that order); None: the prediction's uncertainty is unknown (not trusted).
    samples : states drawn from the calibration's posterior that fit its frames
        (:func:`~bluesky_offsets.model.fit.posterior_samples`, two or more): the prediction's σ
        and flags are read from them instead of from ``covariance``, whose Gaussian spreads along
        combinations the frames forbid.
    overrides : extra RML overrides of the state (e.g. a hidden truth's effects).
    progress : called with a dict per iteration.
    executor : runs the starts side by side (the same result: the best in the starts' order).

    Raises
    ------
    DarkStart : no light at ``current``.
    TargetUnreachable : the best within the limits misses the target (naming the motors it pushes
        against their limits).
    """
    from bluesky_offsets.physics.beamline import torch_engine
    target = target_from(target)
    cons = constraints if isinstance(constraints, Constraints) else Constraints.from_mapping(constraints)
    cons.check(table)
    o = OptimizeOptions.resolve(options)
    current = table.validate(current, "current setting").astype(float)
    lo, hi, free = bounds(current, cons, limits, table)
    engine = engine or torch_engine(table, options=dict(o.engine or {}))
    pb = _Problem(target, state, current, lo, hi, free, o, engine, overrides, table,
                  posterior_draws(state, covariance, o.draws, seed=o.seed, table=table))
    at_current = pb.rays(current)[0]
    start_rays = at_current[0]
    # draws that lose the light where the motors stand contradict the frames just measured
    pb.keep([k for k, r in enumerate(at_current) if float(r.intensity) >= 0.5 * float(start_rays.intensity)])
    if float(start_rays.intensity) < 1e-4:
        raise DarkStart(f"no light on the screen at the current setting ({float(start_rays.intensity):.2g} of the "
                        f"source rays in the model): find the beam first (plans.find_beam)")
    pb.start = _soft_focus(start_rays)
    floors = [f for f in ((cons.keep_transmission or 0) * pb.start.intensity, cons.min_transmission or 0) if f]
    pb.floor = max(floors) if floors else 0.0
    if not free.any():
        raise InputError("no motor is free to move (all held, fixed or at zero travel)")

    inits = _starts(pb, o)
    ulo, uhi = pb.bounds_u()
    runs = _search(pb, inits, progress, executor)
    best: tuple[np.ndarray, float] | None = None
    history: list[dict] = []
    starts: list[dict] = []
    for u, cost, hist in runs:
        history += hist
        starts.append({"start": hist[0]["start"], "cost_start": hist[0]["cost"], "cost": cost,
                       "iterations": hist[-1]["iteration"]})
        if best is None or cost < best[1]:
            best = (u, cost)
    assert best is not None  # the current setting is always a start
    u, cost = best
    if not math.isfinite(cost):
        raise DarkStart("every start lost the light in the model: find the beam first")
    settings = pb.config(u)
    predicted, px, py = predict(state, settings, rays=o.check_rays, seed=o.check_seed, overrides=overrides,
                                engine=engine, table=table)
    before, _, _ = predict(state, current, rays=o.check_rays, seed=o.check_seed, overrides=overrides, engine=engine,
                           table=table)
    at_lo, at_hi = (u - ulo) < 1e-6, (uhi - u) < 1e-6   # u: fractions of each range
    names_free = np.asarray(table.names)[free]
    at_limit = [str(n) for n, a, b in zip(names_free, at_lo, at_hi) if a or b]
    why = target.unmet(predicted)
    if why is not None:
        g = pb.linearized(settings, pb.residuals)[2]      # the cost falls along -g
        pushing = [f"{n} (at its {'low' if a else 'high'} limit {lo[free][i] if a else hi[free][i]:.6g} "
                   f"{table[str(n)].unit})" for i, (n, a, b) in enumerate(zip(names_free, at_lo, at_hi))
                   if (a and g[i] > 0) or (b and g[i] < 0)]
        raise TargetUnreachable(f"{target.name}: {why} — " + (
            "it needs " + ", ".join(pushing) + " beyond its limit; nothing was moved" if pushing else
            "no motor within its limits gets there in the model; nothing was moved"))
    sigma, flags, known = _sigma(pb, settings, covariance, names, samples, (px, py), o, table)
    rel = max(sigma[a] / getattr(predicted, f"rms_{a}") for a in "xy") if known else math.inf
    trusted = known and rel < o.trust_below
    moved = moved_names(current, settings, table, free)
    return BeamOptimum(target, settings, current, moved, predicted, before, sigma, flags, trusted, at_limit, cost,
                       history, starts, (px, py), len(pb.offsets), len(_fitted(samples) or ()))
