"""blop interop: the calibrated twin as a blop evaluation function, and the offset finder as a blop optimizer.

blop (NSLS-II's Bayesian beamline optimizer) drives a beamline through three protocols:
an ``Optimizer`` (``suggest`` / ``ingest`` / ``get_best_points``), an ``AcquisitionPlan`` and an
``EvaluationFunction``.  Two bridges, each usable in a plain blop agent or ``blop.plans.optimize``:

* :func:`focus_agent` — a blop ``Agent`` whose DOFs are the beamline's motors and whose
  evaluations are traced on the calibrated twin (:class:`TwinFocus`, acquisition
  :class:`OnTwin`: nothing moves), so the agent searches the focus on the model before the
  beamline is touched; ``agent.navigate_to_best()`` then moves the motors there.
* :class:`OffsetOptimizer` — the offset finder (Levenberg–Marquardt on the surrogate) behind
  blop's ``Optimizer`` protocol: it suggests bright configurations to measure, ingests the
  measured histograms (:class:`FrameHistograms` reads them from the acquisition runs through a
  :class:`Collector` subscribed to the RunEngine) and refits; its best point is the offsets.

Needs the ``[blop]`` extra (``blop[ax]``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import bluesky.plan_stubs as bps
import numpy as np
from bluesky.callbacks import CallbackBase
from bluesky.utils import MsgGenerator

from bluesky_offsets.physics.parameters import MAX_OFFSET, METRIXS, ParameterTable

ID = "_id"


def _configuration(reference: np.ndarray, names: Mapping[str, str], point: Mapping,
                   table: ParameterTable) -> np.ndarray:
    """The twin configuration of a blop point: ``reference`` with each DOF's parameter set to its value."""
    c = np.array(reference, float)
    for dof, parameter in names.items():
        c[table.index(parameter)] = float(point[dof])
    return c


# --------------------------------------------------------------------------- #
# the calibrated twin as a blop evaluation function
# --------------------------------------------------------------------------- #
class OnTwin:
    """A blop acquisition plan that moves nothing: the suggestions are evaluated on the twin."""

    def __call__(self, suggestions: Sequence[Mapping], actuators: Sequence, sensors: Sequence | None = None,
                 md: Mapping[str, Any] | None = None) -> MsgGenerator[list[Mapping]]:
        """Yield one null message and return the suggestions unchanged, as the readings to evaluate."""
        yield from bps.null()
        return [dict(s) for s in suggestions]


class TwinFocus:
    """blop evaluation function: the calibrated model's focus at each suggested motor setting.

    ``focus_um2`` = rms width x times rms width y (µm²), divided by the share of ``keep`` times
    the reference's intensity that the setting keeps where it keeps less (a dimmer focus is not a
    better one); ``intensity`` the fraction of the source on the screen.
    """

    def __init__(self, calibration, reference, names: Mapping[str, str], *, rays: int = 20_000, seed: int = 0,
                 keep: float = 0.9, table: ParameterTable = METRIXS):
        from bluesky_offsets.model.state import CalibratedState
        from bluesky_offsets.physics.beamline import torch_engine
        self.state = CalibratedState.of(calibration).state
        self.reference, self.names, self.table = np.asarray(reference, float), dict(names), table
        self.rays, self.seed, self.keep = int(rays), int(seed), float(keep)
        self.engine = torch_engine(table)
        self.reference_focus = self.focus(self.reference)

    def focus(self, configuration):
        """The calibrated model's predicted focus at twin ``configuration`` (table order, physical units)."""
        from bluesky_offsets.optimize.optimizer import predict
        return predict(self.state, configuration, rays=self.rays, seed=self.seed, engine=self.engine,
                       table=self.table)[0]

    def __call__(self, uid: Sequence[Mapping], suggestions: Sequence[Mapping]) -> list[dict]:
        """``{"_id": ..., "focus_um2": ...}`` for each suggestion, traced on the twin (1e9 where not finite)."""
        out = []
        for s in suggestions:
            f = self.focus(_configuration(self.reference, self.names, s, self.table))
            kept = min(1.0, f.intensity / max(self.keep * self.reference_focus.intensity, 1e-12))
            area = f.rms_x * f.rms_y * 1e6 / max(kept, 1e-3)
            out.append({ID: s[ID], "focus_um2": float(area) if np.isfinite(area) else 1e9})
        return out


def focus_agent(calibration, motors: Mapping[str, Any], reference, *, span: Mapping[str, float] | float = 0.02,
                rays: int = 20_000, sobol: int = 8, beta: float = 10.0, seed: int = 0,
                table: ParameterTable = METRIXS):
    """A blop ``Agent`` that searches the smallest focus on the calibrated twin.

    Parameters
    ----------
    calibration : CalibratedState, ModelState or analysis
        The calibrated model (``bluesky_offsets.load_calibration(path)``).
    motors : mapping
        ``{parameter name: motor}``: the DOFs (each motor's ``name`` names its DOF).
    reference : array_like
        The twin configuration the motors stand at (table order, physical units).
    span : float or mapping
        Each DOF's search half-width, as a fraction of its parameter's range (or per parameter).
    sobol, beta : int, float
        Quasi-random points first, then Ax's Gaussian process with UCB(β) (the authors' β = 10).
    """
    from blop.ax import Agent, Objective, RangeDOF

    from bluesky_offsets.offsets.baselines import ucb_strategy
    reference = np.asarray(reference, float)
    dofs, names = [], {}
    for parameter, motor in motors.items():
        p = table[parameter]
        half = (span[parameter] if isinstance(span, Mapping) else span) * (p.high - p.low)
        here = reference[table.index(parameter)]
        lo, hi = max(p.limits[0], here - half), min(p.limits[1], here + half)
        dofs.append(RangeDOF(actuator=motor, bounds=(float(lo), float(hi)), parameter_type="float"))
        names[motor.name] = parameter
    agent = Agent(sensors=[], dofs=dofs, objectives=[Objective(name="focus_um2", minimize=True)],
                  evaluation_function=TwinFocus(calibration, reference, names, rays=rays, seed=seed, table=table),
                  acquisition_plan=OnTwin())
    agent.ax_client.set_generation_strategy(ucb_strategy(sobol, beta, seed))
    return agent


# --------------------------------------------------------------------------- #
# the offset finder behind blop's Optimizer protocol
# --------------------------------------------------------------------------- #
class Collector(CallbackBase):
    """Keeps each run's start document and event data, by run uid.

    It is how an evaluation function reads what the acquisition plan measured.
    """

    def __init__(self):
        super().__init__()
        self.starts: dict[str, dict] = {}
        self.events: dict[str, list[dict]] = {}
        self._run_of: dict[str, str] = {}

    def start(self, doc):
        """Keep the run's start document and open its list of event data."""
        self.starts[doc["uid"]] = doc
        self.events[doc["uid"]] = []

    def descriptor(self, doc):
        """Note which run the descriptor's events belong to."""
        self._run_of[doc["uid"]] = doc["run_start"]

    def event(self, doc):
        """Append the event's data to its run's list."""
        self.events[self._run_of[doc["descriptor"]]].append(doc["data"])


def _ending(data: Mapping, suffix: str) -> np.ndarray:
    keys = [k for k in data if k.endswith(suffix)]
    if len(keys) != 1:
        raise KeyError(f"expected one reading ending in {suffix!r}, found {keys}")
    return np.asarray(data[keys[0]], float)


class FrameHistograms:
    """blop evaluation function: each acquired frame's histograms (x then y), by suggestion.

    They are read from the acquisition run (``blop_acquisition_order`` names the frames' suggestions).
    """

    def __init__(self, collector: Collector):
        self.collector = collector

    def __call__(self, uid: str, suggestions: Sequence[Mapping]) -> list[dict]:
        """``{"_id": ..., "hist": ...}`` for each frame of run ``uid``, in acquisition order."""
        order = self.collector.starts[uid]["blop_acquisition_order"]
        events = self.collector.events[uid]
        if len(events) != len(order):
            raise RuntimeError(f"run {uid}: {len(events)} frames for {len(order)} suggestions")
        return [{ID: i, "hist": np.concatenate([_ending(d, "hist_x"), _ending(d, "hist_y")]).tolist()}
                for i, d in zip(order, events)]


class OffsetOptimizer:
    """The offset finder as a blop ``Optimizer``.

    ``suggest(n)``: ``n`` configurations to measure — candidates around ``reference`` (each DOF
    within ``span`` of its range), the brightest the surrogate predicts at the current offsets.
    ``ingest(points)``: their measured histograms (``"hist"``, x then y); every frame so far is
    refitted (multi-start Levenberg–Marquardt on the surrogate).  ``get_best_points()``: the
    offsets (normalized, by parameter name) and the fit's MSE.

    Parameters
    ----------
    model : ForwardModel
        The surrogate (``offsets.finder.load_forward_model()``).
    motors : mapping
        ``{parameter name: motor name}``: the DOFs blop moves.
    reference : array_like
        The twin configuration at the start (table order, physical units).
    """

    def __init__(self, model, motors: Mapping[str, str], reference, *, span: float = 0.03, candidates: int = 256,
                 evaluations: int = 20_000, seed: int = 0, table: ParameterTable = METRIXS):
        self.model, self.table = model, table
        self.names = {motor: parameter for parameter, motor in motors.items()}
        self.reference = np.asarray(reference, float)
        self.span, self.candidates, self.evaluations = float(span), int(candidates), int(evaluations)
        self.rng = np.random.default_rng([int(seed), 0xB10B])
        self.seed = int(seed)
        self.offsets = np.zeros(len(table))
        self.loss = float("inf")
        self._pending: dict[int, np.ndarray] = {}
        self.configurations: list[np.ndarray] = []
        self.histograms: list[np.ndarray] = []

    def suggest(self, num_points: int | None = None) -> list[dict]:
        """The ``num_points`` (default 1) candidates the surrogate predicts brightest at the current offsets."""
        from bluesky_offsets.offsets.finder import _predict, model_device, model_dtype
        n = int(num_points or 1)
        dofs = list(self.names)
        idx = [self.table.index(self.names[d]) for d in dofs]
        par = [self.table[self.names[d]] for d in dofs]
        width = np.array([p.high - p.low for p in par])
        lo, hi = np.array([p.limits for p in par]).T
        u = self.rng.uniform(-1, 1, (self.candidates, len(dofs)))
        vals = np.clip(self.reference[idx] + u * self.span * width, lo, hi)
        cfg = np.tile(self.reference, (self.candidates, 1))
        cfg[:, idx] = vals
        x = self.table.normalize(cfg) + self.offsets
        bright = _predict(self.model, x, model_device(self.model), model_dtype(self.model)).sum(1)
        out = []
        for k in np.argsort(-bright)[:n]:
            i = len(self._pending) + len(self.configurations)
            self._pending[i] = cfg[k]
            out.append({ID: i, **{d: float(v) for d, v in zip(dofs, vals[k])}})
        return out

    def ingest(self, points: Sequence[Mapping]) -> None:
        """Add the points' measured histograms and refit the offsets on every frame so far."""
        from bluesky_offsets.offsets import finder as F
        for p in points:
            c = self._pending.pop(p[ID]) if p.get(ID) in self._pending else \
                _configuration(self.reference, self.names, p, self.table)
            self.configurations.append(c)
            self.histograms.append(np.asarray(p["hist"], float))
        problem = F.problem_from_measurements(np.array(self.configurations), np.array(self.histograms),
                                              table=self.table, limit=MAX_OFFSET)
        r = F.find_offsets(problem, self.model, "levenberg-marquardt", F.Budget(evaluations=self.evaluations),
                           seed=self.seed + len(self.configurations), progress=False)
        self.offsets, self.loss = r.offsets, float(r.loss)

    def get_best_points(self) -> list[tuple[str, dict, dict]]:
        """The current offsets (normalized, by parameter name) and the fit's MSE, as one best point."""
        return [("offsets", dict(zip(self.table.names, map(float, self.offsets))), {"mse": self.loss})]
