"""The authors' current baselines, each through the library they use, behind the finder's interface.

Meier et al.'s public offset-finding code now recommends a genetic algorithm (its README:
evotorch, 500 candidates, 1,000 generations, simulated binary crossover at rate 0.8,
tournaments of 3, Gaussian mutation σ = 0.2 of each parameter's range) and compares Powell,
simulated annealing, gradient descent through the surrogate and BLOP (blop's Ax agent, UCB
β = 10).  Here each is an algorithm object with the finder methods' ``run(objective, tracker,
generator)``, so :func:`finder.find_offsets` runs it under the same budget, evaluation count and
loss history as ours; gradient descent is the finder's own ``gradient``.

Optional dependencies: ``evotorch`` (``[harness]``), ``blop[ax]`` (``[blop]``); SciPy is core.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from bluesky_offsets.offsets import finder as F

RECORD_EVERY = 256
"""A one-candidate method records its loss curve at every improvement and every this many evaluations."""


def _need(module: str, extra: str) -> None:
    """A finder error in one line where a baseline's library is not installed."""
    import importlib.util
    if importlib.util.find_spec(module) is None:
        raise F.FinderError(f"this baseline needs {module}: pip install 'bluesky-offsets[{extra}]'")


class _Spent(Exception):
    """The evaluation or time budget ran out inside a library's loop."""


def _scalar(obj: F.Objective, tr: F._Tracker):
    """The objective as SciPy calls it: one float64 vector in, one float out, the budget enforced."""
    def f(x: np.ndarray) -> float:
        if tr.exhausted():
            raise _Spent
        cand = torch.as_tensor(np.asarray(x)[None], device=obj.device, dtype=obj.dtype)
        loss = obj(cand)
        before = tr.best_loss
        tr.update(cand, loss, record=float(loss[0]) < before or obj.evaluations % RECORD_EVERY == 0)
        return float(loss[0]) if math.isfinite(float(loss[0])) else 1e30
    return f


@dataclass
class Powell:
    """SciPy's bounded Powell from zero offsets, then from uniform restarts while the budget lasts.

    Zero offsets: the uncompensated model.
    """

    xtol: float = 1e-6
    ftol: float = 1e-12
    name = "powell"

    def run(self, obj: F.Objective, tr: F._Tracker, gen: torch.Generator) -> None:
        """Powell from zero offsets, then from uniform restarts, until the budget is spent; ends kept in ``final``."""
        from scipy.optimize import minimize
        P, lim = obj.problem.n_parameters, obj.limit
        f, start = _scalar(obj, tr), np.zeros(P)
        self.final, self.final_losses = [], []
        while not tr.exhausted():
            try:
                r = minimize(f, start, method="Powell", bounds=[(-lim, lim)] * P,
                             options={"xtol": self.xtol, "ftol": self.ftol, "maxfev": 10**9})
                self.final.append(r.x)
                self.final_losses.append(float(r.fun))
            except _Spent:
                break
            start = F._uniform(1, P, lim, gen, obj)[0].double().cpu().numpy()


@dataclass
class Annealing:
    """SciPy's dual annealing (generalized simulated annealing with a local search), box-bounded."""

    initial_temp: float = 5230.0
    name = "annealing"

    def run(self, obj: F.Objective, tr: F._Tracker, gen: torch.Generator) -> None:
        """Dual annealing over the offsets' box, restarted with the next seed until the budget is spent."""
        from scipy.optimize import dual_annealing
        P, lim = obj.problem.n_parameters, obj.limit
        f = _scalar(obj, tr)
        seed = int(torch.randint(1, 2**31 - 1, (1,), generator=gen))
        while not tr.exhausted():
            try:
                dual_annealing(f, [(-lim, lim)] * P, maxfun=int(min(tr.remaining_evaluations(), 10**9)),
                               initial_temp=self.initial_temp, seed=seed)
            except _Spent:
                break
            seed += 1


@dataclass
class Genetic:
    """evotorch's genetic algorithm with the authors' recommended settings."""

    candidates: int = 500
    crossover_rate: float = 0.8
    tournament_size: int = 3
    mutation_scale: float = 0.2
    eta: float = 20.0
    name = "genetic"

    def run(self, obj: F.Objective, tr: F._Tracker, gen: torch.Generator) -> None:
        """Generations of the genetic algorithm while the budget holds a whole one."""
        import logging
        _need("evotorch", "harness")
        from evotorch import Problem
        from evotorch.algorithms import GeneticAlgorithm
        from evotorch.operators import GaussianMutation, SimulatedBinaryCrossOver
        logging.getLogger("evotorch").setLevel(logging.WARNING)
        P, lim, m = obj.problem.n_parameters, obj.limit, self.candidates

        def loss(x: torch.Tensor) -> torch.Tensor:
            out = obj(x)
            tr.update(x, out)
            return torch.nan_to_num(out, nan=math.inf).to(x.dtype)

        problem = Problem("min", loss, solution_length=P, bounds=(-lim, lim), vectorized=True, dtype=obj.dtype,
                          device=obj.device, seed=int(torch.randint(1, 2**31 - 1, (1,), generator=gen)))
        ga = GeneticAlgorithm(problem, popsize=m, operators=[
            SimulatedBinaryCrossOver(problem, tournament_size=self.tournament_size, eta=self.eta,
                                     cross_over_rate=self.crossover_rate),
            GaussianMutation(problem, stdev=self.mutation_scale)])
        step = m  # evaluations a generation costs: the first scores the initial population too
        while tr.cap(step) >= step and not tr.exhausted():
            before = obj.evaluations
            ga.step()
            step = obj.evaluations - before if before else step


@dataclass
class Blop:
    """blop's Ax optimizer (``blop.ax.optimizer.AxOptimizer``): Sobol points, then a Gaussian process with UCB.

    The upper confidence bound with β = 10 (the authors' setting), ``batch`` points per suggestion,
    through blop's ``suggest``/``ingest`` protocol.
    """

    sobol: int = 16
    beta: float = 10.0
    batch: int = 4
    name = "blop"

    def optimizer(self, P: int, lim: float, seed: int | None = None):
        """A blop ``AxOptimizer`` over ``P`` offsets in ``[-lim, lim]`` minimizing ``mse``."""
        _need("blop", "blop")
        from ax import RangeParameterConfig
        from blop.ax.optimizer import AxOptimizer
        opt = AxOptimizer([RangeParameterConfig(name=f"o{i}", parameter_type="float", bounds=(-lim, lim))
                           for i in range(P)], objective="-mse")
        opt.ax_client.set_generation_strategy(ucb_strategy(self.sobol, self.beta, seed))
        return opt

    def run(self, obj: F.Objective, tr: F._Tracker, gen: torch.Generator) -> None:
        """Batches suggested by the optimizer, evaluated and ingested, until the budget is spent."""
        P, lim = obj.problem.n_parameters, obj.limit
        opt = self.optimizer(P, lim, int(torch.randint(1, 2**31 - 1, (1,), generator=gen)))
        while tr.cap(self.batch) > 0 and not tr.exhausted():
            points = opt.suggest(tr.cap(self.batch))
            x = torch.tensor([[p[f"o{i}"] for i in range(P)] for p in points], device=obj.device, dtype=obj.dtype)
            loss = obj(x)
            tr.update(x, loss)
            opt.ingest([{"_id": p["_id"], "mse": float(v)} for p, v in zip(points, loss.tolist())])


def ucb_strategy(sobol: int, beta: float, seed: int | None = None):
    """Ax's generation strategy: ``sobol`` quasi-random points (scrambled by ``seed``), then BoTorch with qUCB(β)."""
    from ax.adapter.registry import Generators
    from ax.generation_strategy.generation_strategy import GenerationStep, GenerationStrategy
    from botorch.acquisition import qUpperConfidenceBound
    return GenerationStrategy(name=f"Sobol+UCB(beta={beta:g})", nodes=[
        GenerationStep(generator=Generators.SOBOL, num_trials=sobol,
                       generator_kwargs={} if seed is None else {"seed": int(seed)}),
        GenerationStep(generator=Generators.BOTORCH_MODULAR, num_trials=-1,
                       generator_kwargs={"botorch_acqf_class": qUpperConfidenceBound,
                                         "acquisition_options": {"beta": beta}})])


BASELINES: dict[str, type] = {"genetic": Genetic, "powell": Powell, "annealing": Annealing, "blop": Blop}
"""The authors' baselines by name; gradient descent through the surrogate is the finder's ``gradient``."""


def algorithm(name: str, **settings):
    """A method of the finder or a baseline, by name, with its settings (a finder error if unknown)."""
    table = {**F.METHODS, **BASELINES}
    if name not in table:
        raise F.FinderError(f"unknown method {name!r}; choose from {', '.join(table)}")
    try:
        return table[name](**settings)
    except (TypeError, ValueError) as exc:
        raise F.FinderError(f"{name}: {exc}") from None
