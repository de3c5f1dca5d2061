"""Bluesky side of the offset finder: find offsets in a run, apply them to the model.

* :class:`OffsetFinder` - the pluggable finder callable for a ``find_offsets``
  plan: measured configurations (physical, as the motors report them) and
  histograms in, a :class:`Calibration` (offsets, uncertainties,
  determined-or-not, loss curve) out.  It runs a global method (default
  multi-start gradient through the surrogate) and, when a twin is given,
  polishes the result against the twin itself (:func:`twin_polish`: the one fit
  engine), since the surrogate's own error is far above a 1e5-ray measurement's noise.
* :class:`LossPlot` - a callback that plots the finder's progress live: the ``finder``
  events of :func:`plans.find_offsets` (evaluations, seconds, best MSE), the plan that
  runs an :class:`OffsetFinder` on a measurement.
* :func:`apply_offsets` - a plan that updates the model (a
  :class:`CalibratedModel`: the twin and/or the surrogate seen through the
  offsets), never the motors, and records what it applied in a run.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from bluesky_offsets.offsets import finder as F
from bluesky_offsets.offsets import identifiability as I
from bluesky_offsets.physics.parameters import MAX_OFFSET, METRIXS, ParameterTable


# --------------------------------------------------------------------------- #
# the result
# --------------------------------------------------------------------------- #
@dataclass
class Calibration:
    """Offsets found for the real beamline, with what the data say about each.

    ``offsets`` / ``sigma`` are normalized (fractions of each parameter's
    range); :meth:`physical_offsets` converts.  ``status`` per parameter:
    determined / weak / undetermined (see :mod:`bluesky_offsets.offsets.identifiability`).
    """

    offsets: np.ndarray
    sigma: np.ndarray
    status: list[str]
    loss: float
    method: str
    history: dict = field(default_factory=dict)
    twin_mse: float | None = None
    repeat_mse: float | None = None
    table_version: str = METRIXS.version
    names: tuple[str, ...] = METRIXS.names
    source_uid: str | None = None
    created: str = field(default_factory=lambda: datetime.now(timezone.utc).isoformat(timespec="seconds"))
    extra: dict = field(default_factory=dict)

    def physical_offsets(self, table: ParameterTable = METRIXS) -> np.ndarray:
        """The offsets in each parameter's physical unit (normalized offsets times the ranges)."""
        return np.asarray(self.offsets) * table.span

    def physical_sigma(self, table: ParameterTable = METRIXS) -> np.ndarray:
        """The offsets' uncertainties in each parameter's physical unit."""
        return np.asarray(self.sigma) * table.span

    def true_values(self, commanded, table: ParameterTable = METRIXS) -> np.ndarray:
        """What the beamline really is at ``commanded`` physical settings, per this calibration."""
        return table.validate(commanded, "commanded configuration") + self.physical_offsets(table)

    def to_dict(self) -> dict:
        """The calibration as plain JSON values (:meth:`load` reads them back)."""
        return {"offsets": np.asarray(self.offsets).tolist(), "sigma": np.asarray(self.sigma).tolist(),
                "status": list(self.status), "loss": self.loss, "method": self.method,
                "history": {k: [float(v) for v in vals] for k, vals in self.history.items()},
                "twin_mse": self.twin_mse, "repeat_mse": self.repeat_mse, "table_version": self.table_version,
                "names": list(self.names), "source_uid": self.source_uid, "created": self.created,
                "extra": self.extra}

    def save(self, path) -> Path:
        """Write the calibration to ``path`` as JSON; returns the path."""
        path = Path(path)
        path.write_text(json.dumps(self.to_dict(), indent=1) + "\n")
        return path

    @classmethod
    def load(cls, path, table: ParameterTable = METRIXS) -> Calibration:
        """The calibration saved at ``path``; a finder error if it was made for another table version."""
        d = json.loads(Path(path).read_text())
        if d.get("table_version") != table.version:
            raise F.FinderError(f"calibration {path} was made for parameter table {d.get('table_version')}, "
                                f"the model uses {table.version}")
        return cls(np.asarray(d["offsets"]), np.asarray(d["sigma"]), d["status"], d["loss"], d["method"],
                   d.get("history", {}), d.get("twin_mse"), d.get("repeat_mse"), d["table_version"],
                   tuple(d["names"]), d.get("source_uid"), d.get("created", ""), d.get("extra", {}))

    def report(self, table: ParameterTable = METRIXS) -> str:
        """A text table: each parameter's physical offset ± σ, its unit and status, under the method and MSE."""
        lines = [f"offsets ({self.method}, MSE {self.loss:.3e}"
                 + (f", twin MSE {self.twin_mse:.3e} vs repeat {self.repeat_mse:.3e}" if self.twin_mse else "") + ")"]
        phys, ps = self.physical_offsets(table), self.physical_sigma(table)
        for p, o, s, st in zip(table, phys, ps, self.status):
            lines.append(f"  {p.name:32s} {o:+11.5f} ± {s:9.5f} {p.unit:4s} {st}")
        return "\n".join(lines)


# --------------------------------------------------------------------------- #
# twin polish
# --------------------------------------------------------------------------- #
def twin_polish(problem: F.OffsetProblem, twin, offsets, *, iterations: int = 4, n_rays: int | None = None,
                seed: int = 0, oversample: float = 2.0,
                callback: Callable[[dict], None] | None = None) -> tuple[np.ndarray, list[float]]:
    """The surrogate's solution fitted on through the twin itself.

    The one fit engine (:func:`bluesky_offsets.model.fit.fit`, the differentiable twin, exact
    Jacobians) on the problem's 50 + 50 bins, ``iterations`` Levenberg-Marquardt steps on the beam
    features, then as many on the bins, at ``oversample`` x the measurement's rays (one set of rays,
    so that a step near the optimum is judged without sampling noise).

    The surrogate finds the right valley, but its own error (~1e-6 per bin) is far above the
    counting noise of a 1e5-ray measurement (~4e-8).  Returns the offsets and the twin's MSE
    to the observations at the start and at the end (the fit's rays).
    """
    from bluesky_offsets.model.fit import FitOptions, engine_for, fit
    from bluesky_offsets.model.measurement import Measurement
    from bluesky_offsets.model.state import ModelState
    from bluesky_offsets.physics.twin import HistogramSpec
    N = int(n_rays or problem.n_rays or 100_000)
    spec = HistogramSpec()
    obs = problem.observations
    cfg = problem.physical_configurations()
    meas = Measurement(cfg, obs[:, :spec.bins_x], obs[:, spec.bins_x:], N, spec,
                       metadata={"parameter_table_version": problem.table.version})
    # the features first: in the paper's bins a focus fills a bin or two, and from the surrogate's
    # solution the bins alone can refuse every step
    rays = max(int(round(N * oversample)), 1)
    opts = FitOptions(rays=rays, feature_rays=None, seed=seed, offset_bound=problem.limit,
                      stages=(("features", int(iterations)), ("bins", int(iterations))))
    engine = engine_for(meas, opts, problem.table)  # the fits' engine: a random stream per configuration

    def mse(o) -> float:
        res = _twin_histograms(engine, cfg + problem.table.offsets_to_physical(o), opts.rays, seed)
        return float(np.mean((res - obs) ** 2))

    o = np.clip(np.asarray(offsets, dtype=float), -problem.limit, problem.limit)
    mses = [mse(o)]
    if iterations:
        def cb(d):
            if callback and d["iteration"]:
                callback({"iteration": d["iteration"], "chi2_reduced": d["chi2_reduced"], "accepted": d["accepted"]})
        res = fit(meas, ModelState(o), engine, opts, progress=cb, table=problem.table)
        o = np.clip(res.state.offsets, -problem.limit, problem.limit)
        mses.append(mse(o))
    return o, mses


def _twin_histograms(engine, values: np.ndarray, n_rays: int, seed: int) -> np.ndarray:
    """Histograms (n, 100) of the torch twin at ``values`` (the fit's rays)."""
    from bluesky_offsets.physics.twin import Twin
    res = Twin(engine).trace_batch(values, n_rays=n_rays, seed=seed, progress=False, raise_on_error=True)
    return np.concatenate([res.hist_x, res.hist_y], axis=1)


# --------------------------------------------------------------------------- #
# the finder callable
# --------------------------------------------------------------------------- #
@dataclass
class OffsetFinder:
    """The pluggable finder for a ``find_offsets`` plan.

    ``finder(measurement, callback=...) -> Calibration`` (a :class:`plans.offsets.Finder`):
    the measurement's configurations are physical (motor read-backs; the fixed parameters at
    their nominal values), its histograms the paper's 50 + 50 bins.  ``callback`` receives
    progress dicts (evaluations, seconds, loss).  With a ``twin``, the result is polished
    against the twin and the twin's MSE to the measurement is reported next to the expected
    repeat noise.
    """

    model: object = None  # ForwardModel; None: the shipped surrogate
    # Levenberg-Marquardt: on measured bright configurations multi-start Adam can stall in a
    # valley far above the surrogate's minimum
    method: str = "levenberg-marquardt"
    budget: F.Budget = field(default_factory=lambda: F.Budget(evaluations=20_000, seconds=120))
    settings: dict = field(default_factory=dict)
    twin: object = None
    polish_iterations: int = 4
    seed: int = 0
    limit: float = MAX_OFFSET
    threads: int | None = 1
    progress: bool = False

    def __post_init__(self):
        if self.model is None:
            self.model = F.load_forward_model()

    def __call__(self, measurement, *, callback: Callable[[dict], None] | None = None) -> Calibration:
        """The :class:`Calibration` of ``measurement``: the method's offsets, twin-polished where a twin is given."""
        n_rays, uid = measurement.n_rays, measurement.uid
        problem = F.problem_from_measurements(measurement.configurations, measurement.histograms, n_rays=n_rays,
                                              limit=self.limit, metadata={"uid": uid} if uid else None)
        res = F.find_offsets(problem, self.model, self.method, self.budget, seed=self.seed, progress=self.progress,
                             callback=callback, threads=self.threads, **self.settings)
        offsets, history = res.offsets, dict(res.history)
        twin_mse = repeat = None
        extra = {"evaluations": res.evaluations, "seconds": res.seconds, "settings": res.settings}
        if self.twin is not None and self.polish_iterations:
            def cb(d):
                if callback:
                    callback({"evaluations": res.evaluations, "seconds": res.seconds, "loss": d["chi2_reduced"],
                              "stage": "twin polish"})
            offsets, mses = twin_polish(problem, self.twin, offsets, iterations=self.polish_iterations,
                                        n_rays=n_rays, seed=self.seed, callback=cb)
            twin_mse = mses[-1]
            from bluesky_offsets.physics.noise import expected_repeat_mse
            repeat = float(expected_repeat_mse(problem.observations, int(n_rays or 100_000)).mean())
            extra["twin_polish_mse"] = mses
        model_mse = getattr(self.model, "test_mse", 0.0)
        rep = I.analyze(problem, self.model, offsets, model_mse=model_mse, solutions=res.solutions,
                        solution_losses=res.solution_losses)
        extra["identifiability"] = rep.summary()
        extra["pairs"] = rep.pairs()
        return Calibration(offsets=offsets, sigma=rep.sigma, status=rep.status, loss=res.loss, method=self.method,
                           history=history, twin_mse=twin_mse, repeat_mse=repeat, source_uid=uid, extra=extra)


# --------------------------------------------------------------------------- #
# the calibrated model, and the plan that updates it
# --------------------------------------------------------------------------- #
class CalibratedModel:
    """The digital twin and/or surrogate seen through the found offsets.

    ``trace(commanded)`` / ``predict(commanded)`` take the settings the
    operator commands (physical) and evaluate the model at what the real
    beamline is believed to be (commanded + offsets).  :func:`apply_offsets`
    updates it; the motors are never moved.
    """

    def __init__(self, twin=None, forward_model=None, calibration: Calibration | None = None,
                 table: ParameterTable = METRIXS):
        self.twin, self.forward_model, self.table = twin, forward_model, table
        self.calibration = calibration
        self.history: list[Calibration] = []

    @property
    def offsets(self) -> np.ndarray:
        """The normalized offsets in use (zeros without a calibration)."""
        return np.zeros(len(self.table)) if self.calibration is None else np.asarray(self.calibration.offsets)

    def set_calibration(self, cal: Calibration | None) -> None:
        """Use ``cal`` (None: none), the one in use kept in :attr:`history`; refused for another table version."""
        if cal is not None and cal.table_version != self.table.version:
            raise F.FinderError(f"calibration for table {cal.table_version}, model uses {self.table.version}")
        if self.calibration is not None:
            self.history.append(self.calibration)
        self.calibration = cal

    def true_values(self, commanded) -> np.ndarray:
        """What the beamline is believed to be at the ``commanded`` physical settings: commanded + offsets."""
        return self.table.validate(commanded, "commanded configuration") + self.offsets * self.table.span

    def trace(self, commanded, **kw):
        """The twin's trace at the true values of ``commanded`` (``kw`` passed to ``twin.trace``)."""
        if self.twin is None:
            raise F.FinderError("this calibrated model has no twin")
        return self.twin.trace(self.true_values(commanded), **kw)

    def predict(self, commanded) -> np.ndarray:
        """The forward model's histograms at ``commanded`` normalized settings plus the offsets."""
        if self.forward_model is None:
            raise F.FinderError("this calibrated model has no forward model")
        x = self.table.normalize(commanded) + self.offsets
        with torch.no_grad():
            return self.forward_model(torch.as_tensor(x, dtype=F.model_dtype(self.forward_model))).double().numpy()


def apply_offsets(model: CalibratedModel, calibration: Calibration, *, md: Mapping | None = None):
    """Plan: put ``calibration`` into ``model`` (not the motors) and record it in a run.

    The run's one ``applied`` event holds the normalized and physical
    offsets; the start document names the run the offsets came from.
    """
    import bluesky.plan_stubs as bps
    from ophyd import Signal

    md = {"plan_name": "apply_offsets", "offsets_uid": calibration.source_uid, "method": calibration.method,
          "table_version": calibration.table_version, **dict(md or {})}
    yield from bps.open_run(md=md)
    before = Signal(name="offsets_before", value=model.offsets.copy())
    model.set_calibration(calibration)
    after = Signal(name="offsets_applied", value=np.asarray(calibration.offsets))
    phys = Signal(name="offsets_applied_physical", value=calibration.physical_offsets(model.table))
    yield from bps.trigger_and_read([before, after, phys], name="applied")
    yield from bps.close_run()
    return calibration


class LossPlot:
    """Bluesky callback: the finder's best MSE vs. evaluations, live, on a log scale.

    Subscribe it to the RunEngine (``RE.subscribe(LossPlot())``); it follows
    ``finder`` events and, with ``path``, saves the figure when the run stops.
    """

    def __init__(self, path=None, ax=None):
        from bluesky_offsets.plotting import pyplot
        self.plt = pyplot()
        self.path = path
        if ax is None:
            self.fig, self.ax = self.plt.subplots(figsize=(6, 4), constrained_layout=True)
        else:
            self.ax, self.fig = ax, ax.figure
        self._desc: set[str] = set()
        self.x: list[float] = []
        self.y: list[float] = []
        (self.line,) = self.ax.loglog([], [], "o-", ms=3)
        self.ax.set_xlabel("evaluations")
        self.ax.set_ylabel("best MSE")
        self.ax.grid(alpha=0.3, which="both")

    def __call__(self, name, doc):
        """Handle one document: reset on ``start``, plot each ``finder`` event, save on ``stop`` with a path."""
        if name == "start":
            self.x, self.y = [], []
            self.ax.set_title(f"offset finder {doc.get('uid', '')[:8]}")
        elif name == "descriptor" and doc.get("name") == "finder":
            self._desc.add(doc["uid"])
        elif name == "event" and doc["descriptor"] in self._desc:
            d = doc["data"]
            if d.get("loss", 0) > 0 and d.get("evaluations", 0) > 0:
                self.x.append(d["evaluations"])
                self.y.append(d["loss"])
                self.line.set_data(self.x, self.y)
                self.ax.relim()
                self.ax.autoscale_view()
        elif name == "stop" and self.path:
            self.fig.savefig(self.path, dpi=100)
