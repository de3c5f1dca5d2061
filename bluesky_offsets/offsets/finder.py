"""The offset finder: which offsets make the model's histograms match the measured ones.

The problem (Meier et al. 2025, Sec. 3.2-3.3)
---------------------------------------------
An operator sets ``n`` *configurations* (normalized parameter vectors,
table order, the box mapping to [0, 1]) and measures the focus-chamber
histograms of each (x then y, 100 bins, fraction of source rays).  The real
beamline differs from the model by fixed, unknown *offsets* ``o`` (normalized
units, ``|o_i| <= 0.2``), the same for every configuration: the histograms
measured at configuration ``c`` are those the model gives at ``c + o``.  The
finder searches the ``o`` minimizing

    L(o) = mean over configurations and bins of (model(c + o) - observed)^2,

the paper's MSE.  :func:`make_problem` builds the paper's synthetic problem
(seeded, reproducible); :func:`problem_from_measurements` wraps a measured
run.

Methods
-------
All methods share one interface, :func:`find_offsets` (problem, forward model,
budget -> :class:`FinderResult` with offsets, loss history over evaluations and
seconds, evaluations used).  One *evaluation* is one candidate offset vector
scored on all ``n`` configurations (the paper's unit: m = 1e6 candidates x 200
iterations = 2e8 evaluations); a gradient step on one candidate counts as one
evaluation too, its extra cost (the backward pass, about twice a forward one)
shows in the seconds.

* ``smart-walker`` - the paper's method: m candidates drawn uniformly in the
  offset box, then every iteration m candidates = best so far + N(0, 0.002),
  clamped to the box.  CPU default m = 4096 (see :class:`SmartWalker`).
* ``monte-carlo`` - the paper's baseline: m fresh uniform candidates per iteration.
* ``gradient`` - multi-start projected Adam through the differentiable model:
  a uniform screen picks the best starts, each is descended independently
  (one batched forward/backward per step), projected onto the box.
* ``levenberg-marquardt`` - multi-start damped Gauss-Newton on the residuals
  with the model's Jacobian (the loss is a sum of squares).
* ``cmaes`` - CMA-ES (the maintained ``cma`` package) with box bounds and
  IPOP restarts, its population scored in one batch.

The finder depends on the model only through :class:`ForwardModel`: a
differentiable torch callable ``(..., 34) normalized parameters -> (..., 100)
histograms``.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.parameters import MAX_OFFSET, METRIXS, ParameterTable
from bluesky_offsets.physics.engine import FORWARD_AD

# torch.func has no batching rule for Mish's backward yet: correct, just slower; not the user's concern
warnings.filterwarnings("ignore", message=".*batching rule for aten::mish", category=UserWarning)

N_BINS = 100  # 50 x bins then 50 y bins
# the paper's "enough rays": histogram sum > 0.5 in the authors' units (raw counts at 1e5 rays / 22594),
# i.e. 0.5 * 22594 / 1e5 in fractions of source rays, taken over the x and y histograms together
PAPER_MIN_HIST_SUM = 0.5 * 22594 / 1e5
PAPER_STEP = 0.002


class FinderError(InputError):
    """Bad input to the finder (shapes, NaNs, unknown method, empty budget)."""


# --------------------------------------------------------------------------- #
# the forward model
# --------------------------------------------------------------------------- #
@runtime_checkable
class ForwardModel(Protocol):
    """What the finder needs from a model of the beamline.

    A differentiable torch callable mapping normalized parameters ``(..., P)``
    (``P`` = 34 for METRIXS; the box maps to [0, 1], inputs up to 0.2 outside
    it occur) to histograms ``(..., 100)``: 50 x bins then 50 y bins, fraction
    of source rays per bin.  Any ``torch.nn.Module`` with that signature is one.
    """

    def __call__(self, parameters: torch.Tensor) -> torch.Tensor:
        """Histograms ``(..., 100)`` at normalized parameters ``(..., P)``."""
        ...


def model_device(model) -> torch.device:
    """The device a model's parameters live on (CPU for parameter-free callables)."""
    if isinstance(model, torch.nn.Module):
        for p in model.parameters():
            return p.device
    dev = getattr(model, "device", None)
    return torch.device(dev) if dev is not None else torch.device("cpu")


def model_dtype(model) -> torch.dtype:
    """The dtype of a model's parameters (its ``dtype`` attribute, else float32, for parameter-free callables)."""
    if isinstance(model, torch.nn.Module):
        for p in model.parameters():
            return p.dtype
    return getattr(model, "dtype", torch.float32)


class SurrogateForwardModel(torch.nn.Module):
    """A trained :class:`bluesky_offsets.surrogate.network.Surrogate` as a :class:`ForwardModel`.

    Its network already takes the table-normalized parameters; this module
    adds the output de-normalization (to fractions of source rays) and the
    clamp at zero, as the surrogate's own ``predict`` does, and keeps both as
    buffers so that ``.to(device)`` moves everything.  Weights are frozen.
    """

    # its buffers (register_buffer), which nn.Module's __getattr__ types as Tensor | Module
    out_low: torch.Tensor
    out_span: torch.Tensor
    chamber: torch.Tensor
    mirrored: torch.Tensor

    def __init__(self, surrogate, chamber=None):
        super().__init__()
        self.surrogate = surrogate
        self.net = surrogate.net
        self.net.eval()
        for p in self.net.parameters():
            p.requires_grad_(False)
        norm = surrogate.norm
        self.register_buffer("out_low", torch.as_tensor(np.asarray(norm.out_low), dtype=torch.float32))
        self.register_buffer("out_span", torch.as_tensor(np.asarray(norm.out_span), dtype=torch.float32))
        # a surrogate with the chamber's inputs sees the chamber where it is known to be (default:
        # its nominal place); the finder's unknowns stay the 34 offsets
        n = len(surrogate.table["names"])
        ch = np.zeros(3) if chamber is None else np.asarray(chamber, float)
        if chamber is not None and not surrogate.chamber and ch.any():
            raise FinderError("this surrogate was trained without the focus chamber's inputs")
        self.register_buffer("chamber", torch.as_tensor(
            (ch - norm.in_low[n:]) / norm.in_span[n:] if surrogate.chamber else np.zeros(0), dtype=torch.float32))
        # a checkpoint trained with the mirrored source frame sees the four source inputs
        # reflected in their boxes, as Surrogate.predict shows them (Surrogate._as_trained)
        mirrored = [i for i, name in enumerate(surrogate.table["names"]) if name.startswith("U41_318eV.")] \
            if surrogate.source_mirrored else []
        self.register_buffer("mirrored", torch.as_tensor(mirrored, dtype=torch.long))
        test = (surrogate.metrics or {}).get("test") or {}
        # the model's own error on bright histograms: what the identifiability analysis adds per bin
        self.test_mse = float(test.get("mse_nonempty", test.get("mse", 0.0)) or 0.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Histograms (fractions of source rays, clamped at zero) at normalized parameters ``x``."""
        if self.mirrored.numel():
            x = x.index_copy(-1, self.mirrored, 1.0 - x.index_select(-1, self.mirrored))
        if self.chamber.numel():
            x = torch.cat([x, self.chamber.to(x.dtype).expand(*x.shape[:-1], -1)], -1)
        return (self.net(x) * self.out_span + self.out_low).clamp_min(0.0)


def load_forward_model(path=None, device: str | torch.device | None = None, chamber=None) -> SurrogateForwardModel:
    """The surrogate checkpoint at ``path`` as a :class:`ForwardModel` ready for the finder.

    ``path`` defaults to the one shipped in ``bluesky_offsets/data``; ``chamber`` (x, y, z in mm)
    places the focus chamber for a checkpoint with the chamber's inputs.
    """
    from bluesky_offsets.surrogate.network import SurrogateError, load
    try:
        model = SurrogateForwardModel(load(path), chamber)
    except SurrogateError as exc:
        raise FinderError(str(exc)) from None
    if device is not None:
        model.to(device)
    return model


# --------------------------------------------------------------------------- #
# the problem
# --------------------------------------------------------------------------- #
@dataclass
class OffsetProblem:
    """Configurations and their observed histograms; the unknown is one offset vector.

    Attributes
    ----------
    configurations : ndarray (n, P)
        Normalized settings the operator chose (the *uncompensated* parameters).
    observations : ndarray (n, 100)
        Histograms measured (or simulated) at each configuration.
    true_offsets : ndarray (P,) or None
        The hidden offsets, when known (synthetic problems).
    source : str
        ``"surrogate"``, ``"twin"`` or ``"measurement"``.
    limit : float
        Offsets are searched in ``[-limit, limit]`` (normalized).
    noise_mse : float or None
        Expected MSE between the observations and a perfect noise-free model
        (per-bin multinomial variance at ``n_rays``); 0 for surrogate
        observations.
    n_rays : int or None
        Source rays behind each observed histogram.
    """

    configurations: np.ndarray
    observations: np.ndarray
    true_offsets: np.ndarray | None = None
    source: str = "measurement"
    limit: float = MAX_OFFSET
    noise_mse: float | None = None
    n_rays: int | None = None
    seed: int | None = None
    table: ParameterTable = field(default=METRIXS, repr=False)
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        c = np.asarray(self.configurations, dtype=float)
        o = np.asarray(self.observations, dtype=float)
        P = len(self.table)
        if c.ndim != 2 or c.shape[1] != P:
            raise FinderError(f"configurations must be (n, {P}) normalized vectors, got shape {c.shape}")
        if o.ndim != 2 or o.shape[1] != N_BINS:
            raise FinderError(f"observations must be (n, {N_BINS}) histograms (x then y), got shape {o.shape}")
        if len(c) != len(o):
            raise FinderError(f"{len(c)} configurations but {len(o)} observed histograms")
        if len(c) == 0:
            raise FinderError("the problem has no configurations")
        for name, arr in (("configurations", c), ("observations", o)):
            bad = ~np.isfinite(arr)
            if bad.any():
                row, col = (int(v) for v in np.argwhere(bad)[0])
                what = f"parameter {self.table.names[col]!r}" if name == "configurations" else f"bin {col}"
                raise FinderError(f"{name}: row {row}, {what} is not finite")
        if not 0 < self.limit <= 1:
            raise FinderError(f"offset limit must be in (0, 1], got {self.limit}")
        if self.true_offsets is not None:
            t = np.asarray(self.true_offsets, dtype=float)
            if t.shape != (P,):
                raise FinderError(f"true_offsets must have shape ({P},), got {t.shape}")
            self.true_offsets = t
        self.configurations, self.observations = c, o

    @property
    def n(self) -> int:
        """Number of configurations."""
        return len(self.configurations)

    @property
    def n_parameters(self) -> int:
        """Number of parameters (offsets) per configuration."""
        return self.configurations.shape[1]

    def physical_configurations(self, offsets=None) -> np.ndarray:
        """Physical parameter vectors of the configurations, shifted by normalized ``offsets``."""
        c = self.configurations + (0.0 if offsets is None else np.asarray(offsets, dtype=float))
        return self.table.denormalize(c)

    def summary(self) -> dict:
        """The problem's size, source, seed, limit and noise, the observations' sums and its scalar metadata."""
        sums = self.observations.sum(axis=1)
        return {"n_configurations": self.n, "source": self.source, "seed": self.seed, "limit": self.limit,
                "n_rays": self.n_rays, "noise_mse": self.noise_mse,
                "observed_hist_sum_min": float(sums.min()), "observed_hist_sum_median": float(np.median(sums)),
                **({k: v for k, v in self.metadata.items() if np.isscalar(v) or isinstance(v, str)})}


def _fixed_mask(table: ParameterTable) -> np.ndarray:
    return ~np.asarray(table.motorized, dtype=bool)


@torch.no_grad()
def _predict(model, x: np.ndarray, device, dtype, max_rows: int = 65536) -> np.ndarray:
    flat = np.asarray(x, dtype=float).reshape(-1, x.shape[-1])
    out = []
    for i in range(0, len(flat), max_rows):
        t = torch.as_tensor(flat[i:i + max_rows], device=device, dtype=dtype)
        out.append(model(t).double().cpu().numpy())
    return np.concatenate(out).reshape(*x.shape[:-1], -1)


def make_problem(model, seed: int = 0, *, n_configurations: int = 16, min_hist_sum: float = PAPER_MIN_HIST_SUM,
                 candidate_configurations: int = 1000, offset_trials: int = 100, max_rounds: int = 50,
                 limit: float = MAX_OFFSET, observe: str = "surrogate", twin=None, n_rays: int = 100_000,
                 table: ParameterTable = METRIXS, inside_box: bool = True, region=(0.0, 1.0),
                 progress: bool = False) -> OffsetProblem:
    """The paper's synthetic offset problem, seeded and reproducible.

    Each round draws ``candidate_configurations`` configurations uniformly in
    the box (the fixed-but-unknown parameters - radii, half-axes - take one
    random value shared by all, as on the real beamline) and
    ``offset_trials`` offsets uniformly in ``[-limit, limit]``
    (:meth:`ParameterTable.sample_offsets`).  The first offset for which more
    than 15 (``n_configurations - 1``) offset configurations carry enough rays
    (model histogram sum over x and y > ``min_hist_sum``) wins; its first
    ``n_configurations`` such configurations make the problem.  With
    ``inside_box`` (default; the authors' later code requires it too) each
    configuration is drawn uniformly where both it and its true, offset
    version lie inside the box, where the surrogate is valid and the
    twin and surrogate can be compared; ``inside_box=False`` draws from the
    whole box and lets the model extrapolate up to ``limit`` beyond it.

    ``observe`` = ``"surrogate"`` takes the observations from the model (the
    paper's setting); ``"twin"`` traces the true configurations with the
    RAYX ``twin`` at ``n_rays`` (with its sampling noise, closer to reality).

    ``region`` = (low, high) in normalized units (scalars or per-parameter
    vectors) restricts where configurations are drawn (and where the true
    configurations must lie with ``inside_box``): the paper uses the whole
    box (0, 1); a model valid only near an operating point needs less.
    """
    if observe not in ("surrogate", "twin"):
        raise FinderError(f"observe must be 'surrogate' or 'twin', got {observe!r}")
    if observe == "twin" and twin is None:
        raise FinderError("observe='twin' needs a Twin")
    if n_configurations < 1:
        raise FinderError("n_configurations must be positive")
    device, dtype = model_device(model), model_dtype(model)
    rng = np.random.default_rng([int(seed), 0x0FF5E7])
    P, fixed = len(table), _fixed_mask(table)
    lo = np.broadcast_to(np.asarray(region[0], dtype=float), (P,))
    hi = np.broadcast_to(np.asarray(region[1], dtype=float), (P,))
    if np.any(hi <= lo):
        raise FinderError(f"region must have low < high, got {region}")
    from bluesky_offsets.progress import bar
    for rnd in bar(range(max_rounds), desc="searching a problem", unit="round", disable=not progress):
        offsets = table.sample_offsets(rng, limit, size=offset_trials)
        if inside_box:
            # draw each configuration where both it and it + offset lie in the region (no rejection:
            # rejecting would keep only ~0.9^34 = 3 % of the draws)
            lo_t = np.maximum(lo, lo - offsets)[:, None, :]
            hi_t = np.minimum(hi, hi - offsets)[:, None, :]
        else:
            lo_t, hi_t = lo[None, None, :], hi[None, None, :]
        u = rng.random((offset_trials, candidate_configurations, P))
        u[:, :, fixed] = rng.random((offset_trials, 1, int(fixed.sum())))  # one value per beamline
        configs = lo_t + u * (hi_t - lo_t)  # (trials, configs, P)
        true = configs + offsets[:, None, :]
        hist = _predict(model, true, device, dtype)
        good = hist.sum(axis=-1) > min_hist_sum
        counts = good.sum(axis=1)
        winners = np.flatnonzero(counts >= n_configurations)
        if len(winners):
            t = int(winners[0])
            rows = np.flatnonzero(good[t])[:n_configurations]
            c, o = configs[t, rows], offsets[t]
            meta = {"round": rnd, "good_fraction": float(good[t].mean()), "min_hist_sum": min_hist_sum,
                    "candidate_configurations": candidate_configurations, "offset_trials": offset_trials,
                    "inside_box": inside_box}
            if observe == "surrogate":
                return OffsetProblem(c, hist[t, rows], o, "surrogate", limit, 0.0, None, seed, table, meta)
            from bluesky_offsets.physics.noise import expected_repeat_mse
            res = twin.trace_batch(table.denormalize(c + o), n_rays=n_rays, seed=int(rng.integers(2**31)),
                                   progress=progress)
            obs = np.concatenate([res.hist_x, res.hist_y], axis=1)
            if not np.all(res.ok):
                raise FinderError(f"the twin failed on {int((~res.ok).sum())} configurations: {res.failures[:1]}")
            meta["twin_hist_sum_min"] = float(obs.sum(axis=1).min())
            meta["surrogate_vs_twin_mse"] = float(np.mean((hist[t, rows] - obs) ** 2))
            noise = float(0.5 * expected_repeat_mse(obs, n_rays).mean())
            return OffsetProblem(c, obs, o, "twin", limit, noise, n_rays, seed, table, meta)
    raise FinderError(f"no offset with >= {n_configurations} bright configurations in {max_rounds} rounds of "
                      f"{candidate_configurations} x {offset_trials}; is the model trained?")


def problem_from_measurements(configurations, histograms, *, physical: bool = True, n_rays: int | None = None,
                              table: ParameterTable = METRIXS, limit: float = MAX_OFFSET,
                              metadata: Mapping | None = None) -> OffsetProblem:
    """A problem from a measurement run: set configurations and their measured histograms.

    ``configurations`` (n, P) are physical values (``physical=True``, e.g. the
    motor positions read back in the run, fixed parameters at their nominal
    values) or normalized ones; ``histograms`` (n, 100) or (n, 2, 50).
    """
    h = np.asarray(histograms, dtype=float)
    if h.ndim == 3 and h.shape[1:] == (2, N_BINS // 2):
        h = h.reshape(len(h), N_BINS)
    c = table.validate(configurations, "measured configurations")
    if c.ndim != 2:
        raise FinderError(f"configurations must be (n, {len(table)}), got shape {c.shape}")
    c = table.normalize(c) if physical else c
    noise = None
    if n_rays:
        from bluesky_offsets.physics.noise import expected_repeat_mse
        noise = float(0.5 * expected_repeat_mse(h, n_rays).mean())
    return OffsetProblem(c, h, None, "measurement", limit, noise, n_rays, None, table, dict(metadata or {}))


# --------------------------------------------------------------------------- #
# objective, budget, bookkeeping
# --------------------------------------------------------------------------- #
class Objective:
    """The paper's MSE as a batched torch function of candidate offsets ``(m, P) -> (m,)``.

    Candidates are scored in chunks of at most ``max_rows`` model rows
    (candidates x configurations) to bound memory; every scored candidate is
    counted in :attr:`evaluations`.
    """

    def __init__(self, problem: OffsetProblem, model, *, device=None, dtype=None, max_rows: int = 1 << 16):
        self.problem, self.model = problem, model
        self.device = torch.device(device) if device is not None else model_device(model)
        self.dtype = dtype or model_dtype(model)
        self.configs = torch.as_tensor(problem.configurations, device=self.device, dtype=self.dtype)
        self.observed = torch.as_tensor(problem.observations, device=self.device, dtype=self.dtype)
        self.limit = float(problem.limit)
        self.chunk = max(1, int(max_rows) // problem.n)
        self.evaluations = 0

    def _loss(self, offsets: torch.Tensor) -> torch.Tensor:
        pred = self.model(self.configs[None, :, :] + offsets[:, None, :])
        return ((pred - self.observed) ** 2).mean(dim=(-1, -2))

    @torch.no_grad()
    def __call__(self, offsets) -> torch.Tensor:
        """The loss (MSE) of each candidate offset vector, ``(m, P)`` or one ``(P,)``; each is an evaluation."""
        x = torch.as_tensor(offsets, device=self.device, dtype=self.dtype)
        if x.ndim == 1:
            x = x[None]
        out = torch.cat([self._loss(x[i:i + self.chunk]) for i in range(0, len(x), self.chunk)])
        self.evaluations += len(x)
        return out

    def with_grad(self, offsets: torch.Tensor) -> torch.Tensor:
        """Per-candidate losses with the autograd graph (caller calls backward)."""
        self.evaluations += len(offsets)
        return self._loss(offsets)

    def residuals(self, offsets) -> np.ndarray:
        """Model minus observation ``(n, 100)`` at one offset vector."""
        with torch.no_grad():
            x = torch.as_tensor(offsets, device=self.device, dtype=self.dtype)
            return (self.model(self.configs + x) - self.observed).double().cpu().numpy()


@dataclass
class Budget:
    """Stop after ``evaluations`` candidate evaluations or ``seconds``, whichever comes first."""

    evaluations: int | None = None
    seconds: float | None = None

    def __post_init__(self):
        if self.evaluations is None and self.seconds is None:
            raise FinderError("a budget needs evaluations and/or seconds")
        if self.evaluations is not None and self.evaluations < 1:
            raise FinderError(f"evaluation budget must be positive, got {self.evaluations}")
        if self.seconds is not None and not self.seconds > 0:
            raise FinderError(f"time budget must be positive, got {self.seconds}")


@dataclass
class FinderResult:
    """What a finder run returns.

    ``history`` holds, after every batch, the evaluations used, the seconds
    elapsed and the best loss so far (the loss curve).  ``solutions`` /
    ``solution_losses`` are the end points of independent searches (multi-start
    methods), used for the identifiability spread.
    """

    method: str
    offsets: np.ndarray
    loss: float
    evaluations: int
    seconds: float
    history: dict
    settings: dict
    seed: int | None = None
    device: str = "cpu"
    solutions: np.ndarray | None = None
    solution_losses: np.ndarray | None = None

    def parameter_rmse(self, true_offsets) -> float:
        """Normalized parameter RMSE to the true offsets (the paper: 0.58)."""
        return float(np.sqrt(np.mean((self.offsets - np.asarray(true_offsets)) ** 2)))

    def loss_at(self, evaluations: float) -> float:
        """Best loss reached within ``evaluations``."""
        return loss_at(self.history, evaluations)

    def reached(self, target: float) -> tuple[float, float]:
        """(evaluations, seconds) at which the best loss first fell to ``target`` (inf if never)."""
        loss = np.asarray(self.history["loss"])
        hit = np.flatnonzero(loss <= target)
        if not len(hit):
            return math.inf, math.inf
        return float(self.history["evaluations"][hit[0]]), float(self.history["seconds"][hit[0]])

    def to_dict(self) -> dict:
        """The result as plain JSON values (with the starts' solutions where the method kept them)."""
        d = {"method": self.method, "offsets": self.offsets.tolist(), "loss": self.loss,
             "evaluations": self.evaluations, "seconds": self.seconds, "settings": self.settings,
             "seed": self.seed, "device": self.device,
             "history": {k: [float(v) for v in vals] for k, vals in self.history.items()}}
        if self.solutions is not None and self.solution_losses is not None:  # set together
            d["solutions"] = self.solutions.tolist()
            d["solution_losses"] = self.solution_losses.tolist()
        return d


def loss_at(history: Mapping, evaluations: float) -> float:
    """Best loss of a loss ``history`` (``evaluations``, ``loss``) reached within ``evaluations``."""
    e, loss = np.asarray(history["evaluations"]), np.asarray(history["loss"])
    i = np.searchsorted(e, evaluations, side="right") - 1
    return float(loss[i]) if i >= 0 else math.inf


ProgressCallback = Callable[[dict], None]


class _Tracker:
    """Best-so-far bookkeeping, budget checks, progress bar and live callback."""

    def __init__(self, objective: Objective, budget: Budget, method: str, progress: bool,
                 callback: ProgressCallback | None, callback_every: float = 0.5):
        from bluesky_offsets.progress import bar
        self.obj, self.budget, self.method = objective, budget, method
        self.t0 = time.perf_counter()
        self.best_loss = math.inf
        self.best = torch.zeros(objective.problem.n_parameters, device=objective.device, dtype=objective.dtype)
        self.hist: dict[str, list[float]] = {"evaluations": [], "seconds": [], "loss": []}
        self.callback, self.callback_every, self._last_cb = callback, callback_every, -math.inf
        self._last_cb_evals = -1
        total = budget.evaluations
        self.bar = bar(total=total, desc=method, unit="eval", unit_scale=True, disable=not progress, leave=False)

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def remaining_evaluations(self) -> float:
        if self.budget.evaluations is None:
            return math.inf
        return self.budget.evaluations - self.obj.evaluations

    def exhausted(self) -> bool:
        return self.remaining_evaluations() <= 0 or (
            self.budget.seconds is not None and self.elapsed >= self.budget.seconds)

    def cap(self, m: int) -> int:
        """How many of ``m`` candidates the evaluation budget still allows."""
        return int(max(0, min(m, self.remaining_evaluations())))

    def update(self, candidates: torch.Tensor, losses: torch.Tensor, record: bool = True) -> None:
        """Keep the best of ``candidates``; ``record``: add a point to the loss curve.

        A method that scores one candidate at a time records at improvements and at intervals.
        """
        losses = torch.nan_to_num(losses.detach(), nan=math.inf)
        i = int(torch.argmin(losses))
        if float(losses[i]) < self.best_loss:
            self.best_loss = float(losses[i])
            self.best = candidates[i].detach().clone()
        if record:
            self.record()

    def record(self) -> None:
        now = self.elapsed
        self.hist["evaluations"].append(self.obj.evaluations)
        self.hist["seconds"].append(now)
        self.hist["loss"].append(self.best_loss)
        if self.bar.total is not None:
            self.bar.n = min(self.obj.evaluations, self.bar.total)
        else:
            self.bar.n = self.obj.evaluations
        self.bar.set_postfix(mse=f"{self.best_loss:.3e}", refresh=False)
        self.bar.refresh()
        if self.callback is not None and (now - self._last_cb >= self.callback_every or self.exhausted()):
            self._emit(now)

    def _emit(self, now: float) -> None:
        assert self.callback is not None  # called only where there is one
        self._last_cb, self._last_cb_evals = now, self.obj.evaluations
        self.callback({"method": self.method, "evaluations": self.obj.evaluations, "seconds": now,
                       "loss": self.best_loss, "offsets": self.best.double().cpu().numpy()})

    def finish(self) -> None:
        """Last history point and callback with the final state (a method may stop short of its budget)."""
        if not self.hist["loss"] or self.hist["evaluations"][-1] != self.obj.evaluations:
            self.record()
        if self.callback is not None and self._last_cb_evals != self.obj.evaluations:
            self._emit(self.elapsed)

    def close(self) -> None:
        self.bar.close()


# --------------------------------------------------------------------------- #
# methods
# --------------------------------------------------------------------------- #
def _uniform(m: int, P: int, limit: float, gen: torch.Generator, obj: Objective) -> torch.Tensor:
    u = torch.rand(m, P, generator=gen, dtype=torch.float64, device=gen.device)
    return ((2 * u - 1) * limit).to(device=obj.device, dtype=obj.dtype)


def _normal(shape, gen: torch.Generator, obj: Objective) -> torch.Tensor:
    return torch.randn(*shape, generator=gen, dtype=torch.float64, device=gen.device).to(device=obj.device,
                                                                                         dtype=obj.dtype)


@dataclass
class SmartWalker:
    """The paper's smart walker (Sec. 3.3).

    ``candidates`` (m) offsets uniform in the box are scored; then, every
    iteration, m candidates = centre + N(0, ``step``) per component,
    clamped to ``[-limit, limit]``.  The centre is the best so far
    (``selection="plus"``, elitist, the default) or the best of the last m
    candidates even when it is worse (``"comma"``: the paper's text read
    literally, "evaluate these offsets ... take only the best solution").  With
    m = 1e6 the two coincide; at m = 256-1024 on this CPU neither leaves the
    valley that traps the benchmark's seed 9.  The paper
    uses m = 1e6 on an A100 (200 iterations).  The CPU default m = 4096 keeps one iteration (4096 x 16
    model rows) at ~30 MB of activations for a 7-layer, 512-wide MLP and a
    fraction of a second on two cores; :func:`paper_budget` gives the
    matching evaluation count.
    """

    candidates: int = 4096
    step: float = PAPER_STEP
    selection: str = "plus"
    name = "smart-walker"

    def __post_init__(self):
        if self.selection not in ("plus", "comma"):
            raise InputError(f"selection must be 'plus' or 'comma', not {self.selection!r}")

    def run(self, obj: Objective, tr: _Tracker, gen: torch.Generator) -> None:
        """Uniform candidates, then Gaussian steps around the best (``selection``) until the budget is spent."""
        P, lim = obj.problem.n_parameters, obj.limit
        m = tr.cap(self.candidates)
        x = _uniform(m, P, lim, gen, obj)
        loss = obj(x)
        tr.update(x, loss)
        while not tr.exhausted():
            # "plus": the best so far; "comma": the best of the last m, even when worse
            centre = tr.best if self.selection == "plus" else \
                x[int(torch.argmin(torch.nan_to_num(loss, nan=math.inf)))]
            m = tr.cap(self.candidates)
            x = (centre[None, :] + self.step * _normal((m, P), gen, obj)).clamp_(-lim, lim)
            loss = obj(x)
            tr.update(x, loss)


@dataclass
class MonteCarlo:
    """The paper's baseline: ``candidates`` fresh uniform offsets per iteration, keep the best."""

    candidates: int = 4096
    name = "monte-carlo"

    def run(self, obj: Objective, tr: _Tracker, gen: torch.Generator) -> None:
        """Batches of fresh uniform candidates until the budget is spent."""
        P, lim = obj.problem.n_parameters, obj.limit
        while not tr.exhausted():
            x = _uniform(tr.cap(self.candidates), P, lim, gen, obj)
            tr.update(x, obj(x))


def _screen_size(screen: int, starts: int, tr: _Tracker) -> int:
    """The uniform screen takes at most a quarter of a small evaluation budget."""
    return max(min(screen, int(tr.remaining_evaluations() // 4)), min(starts, tr.cap(starts)), 1)


def _best_starts(obj: Objective, tr: _Tracker, gen: torch.Generator, screen: int,
                 starts: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Screen uniform candidates and return the ``starts`` best, best first, with their losses."""
    x0 = _uniform(_screen_size(screen, starts, tr), obj.problem.n_parameters, obj.limit, gen, obj)
    l0 = obj(x0)
    tr.update(x0, l0)
    order = torch.argsort(l0)[:min(starts, len(x0))]
    return x0[order].clone(), l0[order].clone()


@dataclass
class GradientMultiStart:
    """Multi-start projected Adam through the differentiable model.

    A uniform screen of ``screen`` candidates picks the ``starts`` best as
    starting points (the loss is multimodal: compensating components make
    long valleys and the bright region is small); all starts descend together,
    one batched forward/backward per step, each projected back onto the box.
    The learning rate follows a cosine from ``lr`` to ``lr * lr_floor`` over
    the evaluation budget (or halves every ``halve_every`` steps when only a
    time budget is given).
    """

    starts: int = 8
    screen: int = 2048
    lr: float = 0.03
    lr_floor: float = 0.01
    halve_every: int = 300
    name = "gradient"

    def run(self, obj: Objective, tr: _Tracker, gen: torch.Generator) -> None:
        """Screen, then projected Adam steps of all starts together until the budget is spent; ends in ``final``."""
        lim = obj.limit
        x, start_losses = _best_starts(obj, tr, gen, self.screen, self.starts)
        k = len(x)
        x.requires_grad_(True)
        opt = torch.optim.Adam([x], lr=self.lr)
        total = tr.remaining_evaluations() // max(k, 1)
        step = 0
        while not tr.exhausted():
            if tr.cap(k) < k:
                break
            if math.isfinite(total):
                frac = min(step / max(total, 1), 1.0)
                lr = self.lr * (self.lr_floor + (1 - self.lr_floor) * 0.5 * (1 + math.cos(math.pi * frac)))
            else:
                lr = self.lr * 0.5 ** (step // self.halve_every)
            for g in opt.param_groups:
                g["lr"] = lr
            opt.zero_grad(set_to_none=True)
            losses = obj.with_grad(x)
            losses.sum().backward()
            tr.update(x, losses)
            opt.step()
            with torch.no_grad():
                x.clamp_(-lim, lim)
            step += 1
        with torch.no_grad():
            self.final = x.detach().clone()
            self.final_losses = losses.detach().clone() if step else start_losses


@dataclass
class LevenbergMarquardt:
    """Multi-start Levenberg-Marquardt: the loss is a sum of squares, so use its structure.

    A uniform screen picks the ``starts`` best candidates; each then takes
    damped Gauss-Newton steps ``(JᵀJ + λ diag JᵀJ) δ = -Jᵀr`` with the
    model's Jacobian ``J`` over all configurations (forward mode, batched over
    the starts), projected onto the box, with the usual λ update (a step that
    does not lower the loss is refused and λ grows).  Cost accounting: the
    Jacobian of one start counts as P evaluations (forward mode pushes P
    tangents through the model), each trial step as one more.
    """

    starts: int = 8
    screen: int = 2048
    damping: float = 1e-2
    name = "levenberg-marquardt"

    def run(self, obj: Objective, tr: _Tracker, gen: torch.Generator) -> None:
        """Screen, then damped Gauss-Newton steps of all starts while the budget allows; ends in ``final``."""
        P, lim = obj.problem.n_parameters, obj.limit
        x, loss = _best_starts(obj, tr, gen, self.screen, self.starts)
        k = len(x)
        lam = torch.full((k,), self.damping, device=obj.device, dtype=obj.dtype)
        obs = obj.observed.reshape(-1)

        def resid(o):
            return obj.model(obj.configs + o).reshape(-1) - obs

        jac = torch.func.vmap(torch.func.jacfwd(resid))
        eye = torch.eye(P, device=obj.device, dtype=torch.float64)
        while not tr.exhausted() and tr.cap(k * (P + 1)) >= k * (P + 1):
            with torch.no_grad(), FORWARD_AD:
                J = jac(x).double()  # (k, B, P)
                r = torch.func.vmap(resid)(x).double()  # (k, B)
            obj.evaluations += k * P
            A = J.transpose(1, 2) @ J
            g = (J.transpose(1, 2) @ r[..., None])[..., 0]
            d = torch.diagonal(A, dim1=1, dim2=2).clamp_min(1e-30)
            M = A + lam.double()[:, None, None] * torch.diag_embed(d) + 1e-12 * eye
            step = -torch.linalg.solve(M, g[..., None])[..., 0]
            cand = (x + step.to(obj.dtype)).clamp(-lim, lim)
            lc = obj(cand)
            tr.update(cand, lc)
            better = lc < loss
            x = torch.where(better[:, None], cand, x)
            loss = torch.where(better, lc, loss)
            lam = torch.where(better, lam / 3, lam * 4).clamp(1e-9, 1e9)
        self.final, self.final_losses = x.clone(), loss.clone()


@dataclass
class CMAES:
    """CMA-ES from the ``cma`` package, box-bounded, with IPOP restarts.

    Starts at the best of a uniform ``screen`` with step size ``sigma0``
    (normalized units); when a run stops (converged or stagnated) and budget
    is left, it restarts from a fresh uniform point with a doubled population.
    """

    popsize: int | None = None  # None: cma's default 4 + 3 ln(P) (14 for 34 parameters)
    sigma0: float = 0.05
    screen: int = 2048
    name = "cmaes"

    def run(self, obj: Objective, tr: _Tracker, gen: torch.Generator) -> None:
        """CMA-ES from the screen's best, then from uniform points, population doubled, while budget is left."""
        import cma
        P, lim = obj.problem.n_parameters, obj.limit
        best, _ = _best_starts(obj, tr, gen, self.screen, 1)
        start = best[0].double().cpu().numpy()
        popsize = self.popsize or (4 + int(3 * math.log(P)))
        seed = int(torch.randint(1, 2**31 - 1, (1,), generator=gen))
        self.final, self.final_losses = [], []
        restart = 0
        while not tr.exhausted():
            opts = {"bounds": [-lim, lim], "popsize": popsize, "seed": seed + restart, "verbose": -9,
                    "tolfun": 1e-13, "tolx": 1e-7}
            es = cma.CMAEvolutionStrategy(np.clip(start, -lim * 0.999, lim * 0.999), self.sigma0, opts)
            while not es.stop() and not tr.exhausted():
                X = es.ask()
                n = tr.cap(len(X))
                if n < len(X):
                    X = X[:n]
                    if not n:
                        break
                    tr.update(*self._score(obj, X))
                    break
                cand, f = self._score(obj, X)
                tr.update(cand, f)
                es.tell(X, f.double().cpu().numpy().tolist())
            xb = es.result.xbest
            if xb is not None:
                self.final.append(np.asarray(xb))
                self.final_losses.append(float(es.result.fbest))
            restart += 1
            popsize *= 2
            start = _uniform(1, P, lim, gen, obj)[0].double().cpu().numpy()

    @staticmethod
    def _score(obj, X):
        cand = torch.as_tensor(np.asarray(X), device=obj.device, dtype=obj.dtype)
        return cand, obj(cand)


METHODS: dict[str, type] = {"smart-walker": SmartWalker, "monte-carlo": MonteCarlo,
                            "gradient": GradientMultiStart, "levenberg-marquardt": LevenbergMarquardt,
                            "cmaes": CMAES}


def paper_budget(candidates: int = SmartWalker.candidates, iterations: int = 200) -> Budget:
    """The paper's evaluation count for ``candidates`` per iteration and 200 iterations."""
    return Budget(evaluations=candidates * (iterations + 1))


def find_offsets(problem: OffsetProblem, model, method: str | Any = "smart-walker", budget: Budget | None = None, *,
                 seed: int | None = 0, device: str | torch.device | None = None, progress: bool = True,
                 callback: ProgressCallback | None = None, max_rows: int = 1 << 16,
                 threads: int | None = None, **settings: Any) -> FinderResult:
    """Search the offsets of ``problem`` with ``method``.

    Parameters
    ----------
    problem : OffsetProblem
    model : ForwardModel
        Differentiable ``(..., P) -> (..., 100)`` torch callable.
    method : str or algorithm
        One of :data:`METHODS`, or an algorithm object with ``name`` and ``run(objective, tracker,
        generator)`` (the authors' baselines, :mod:`offsets.baselines`), then without ``settings``.
    budget : Budget
        Evaluations and/or seconds (default: the paper's 201 iterations of the
        smart walker's candidates).
    seed : int
        Seeds every random draw of the method.
    device : str or torch.device
        Where the model runs (default: where its weights are).  The model is
        moved there if it is a ``torch.nn.Module``.
    progress : bool
        Show a progress bar (:func:`bluesky_offsets.progress.bar`).
    callback : callable
        Called with ``{"method", "evaluations", "seconds", "loss", "offsets"}``
        at most every 0.5 s and at the end (live plots, Bluesky documents).
    threads : int
        Torch CPU threads for this run (default: leave torch's setting).  On a
        busy machine, small batches (CMA-ES populations, gradient steps) run
        several times faster on one thread than on contended ones.
    settings
        Method settings (``candidates``, ``step``, ``starts``, ``popsize`` ...).
    """
    if isinstance(method, str):
        if method not in METHODS:
            raise FinderError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
        try:
            algo = METHODS[method](**settings)
        except (TypeError, ValueError) as exc:
            raise FinderError(f"{method}: {exc}") from None
    elif settings:
        raise FinderError(f"{method.name}: settings go to the algorithm object, not to find_offsets")
    else:
        algo = method
    method = algo.name
    budget = budget or paper_budget(getattr(algo, "candidates", SmartWalker.candidates))
    if device is not None and isinstance(model, torch.nn.Module):
        model = model.to(device)
    obj = Objective(problem, model, device=device, max_rows=max_rows)
    # on a GPU the draws come from its own generator: at the paper's m = 1e6 one iteration's normal
    # draws take 0.8 s on a CPU core, longer than the model's 16 million rows on the GPU.  The same
    # seed gives the same run on the same kind of device; a CPU run and a GPU run draw differently.
    gen = torch.Generator(device=obj.device if obj.device.type == "cuda" else "cpu")
    gen.manual_seed(int(seed) if seed is not None else int(torch.seed() % 2**63))
    tr = _Tracker(obj, budget, method, progress, callback)
    old_threads = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    try:
        algo.run(obj, tr, gen)
        tr.finish()
    finally:
        tr.close()
        torch.set_num_threads(old_threads)
    solutions = losses = None
    final = getattr(algo, "final", None)
    if final is not None and len(final):
        solutions = np.asarray([np.asarray(torch.as_tensor(f).double().cpu()) for f in final])
        losses = np.asarray([float(v) for v in getattr(algo, "final_losses")])
    return FinderResult(method=method, offsets=tr.best.double().cpu().numpy(), loss=tr.best_loss,
                        evaluations=obj.evaluations, seconds=tr.elapsed, history=tr.hist,
                        settings={k: v for k, v in asdict(algo).items()}, seed=seed, device=str(obj.device),
                        solutions=solutions, solution_losses=losses)


def final_mse(problem: OffsetProblem, model, offsets) -> float:
    """The paper's MSE of ``offsets`` on ``problem`` (model histograms vs observations)."""
    return float(Objective(problem, model)(np.asarray(offsets)[None])[0])


def available_methods() -> Sequence[str]:
    """The names of the finder's methods."""
    return tuple(METHODS)
