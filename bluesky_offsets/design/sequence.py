"""One step of the designed measurement, and the update between steps.

A designed measurement alternates: :func:`next_batch` (candidates, their information at the
current estimate of the offsets, the batch the criterion prefers), the frames measured, then
:func:`update` (the offsets refitted to every frame so far, from where the last fit ended, and
the precision of the posterior taken anew at the refitted offsets from the frames actually
measured; where the refitted model is dark where the beamline was lit, refits from
:func:`global_starts`, the best kept).  The plan that drives the beamline is
:func:`plans.design.measure_designed`; a benchmark drives the same functions with simulated frames.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass

import numpy as np

from bluesky_offsets.design.choose import (
    PRIOR_SIGMA,
    DesignOptions,
    candidate_settings,
    classes,
    criterion_value,
    predicted_sigma,
    prior_precision,
    select,
)
from bluesky_offsets.design.information import frame_information, positive_part
from bluesky_offsets.physics.parameters import MAX_OFFSET, METRIXS, ParameterTable
from bluesky_offsets.physics.screen import STAGE

STEP_SEED = 7_919
"""Multiplies a step's number in the seed of its candidates' model rays."""


@dataclass(frozen=True)
class DesignStep:
    """What one step of the design chose, and why.

    The batch's settings, each frame's predicted gain of the criterion and share of the source on
    the screen, the criterion before and after the batch, the offsets' predicted σ after it, how
    many candidates were drawn and how many kept the beam on the screen under the posterior, and the
    seconds it took.
    """

    step: int
    configurations: np.ndarray
    screen: np.ndarray
    gains: np.ndarray
    intensity: np.ndarray
    criterion: str
    before: float
    after: float
    sigma: np.ndarray
    candidates: int
    allowed: int
    seconds: float

    @property
    def n_determined(self) -> int:
        """How many offsets the predicted σ after the batch counts as determined."""
        return classes(self.sigma).count("determined")

    def row(self) -> dict:
        """The step as one event of the ``design`` stream."""
        return {"step": self.step, "criterion": self.criterion, "criterion_before": self.before,
                "criterion_after": self.after, "predicted_gain": float(np.sum(self.gains)),
                "gains": np.asarray(self.gains, float), "frames": len(self.gains),
                "predicted_intensity": np.asarray(self.intensity, float),
                "predicted_sigma": np.asarray(self.sigma, float), "predicted_determined": self.n_determined,
                "candidates": self.candidates, "allowed": self.allowed, "seconds": self.seconds}


def _screen_scan(anchor: np.ndarray, k: int, step: int, precision: np.ndarray, candidates: int,
                 options: DesignOptions, t0: float) -> DesignStep:
    """``k`` frames at ``anchor`` (where the beam was found) with the screen spread along the beam.

    The screen spreads over the stage's travel: where the estimate lights no candidate, the real
    beam is still there, and these frames give the next refit something to move the estimate with.
    """
    z = np.linspace(STAGE[2].low, STAGE[2].high, k)
    screen = np.column_stack([np.zeros(k), np.zeros(k), z])
    c = criterion_value(precision, options.criterion)
    return DesignStep(step, np.tile(anchor, (k, 1)), screen, np.zeros(k), np.zeros(k), options.criterion, c, c,
                      predicted_sigma(precision), candidates, 0, time.perf_counter() - t0)


def next_batch(engine, offsets: np.ndarray, precision: np.ndarray, anchors: np.ndarray, acceptance: np.ndarray,
               *, k: int, step: int, photons: int, options: DesignOptions,
               table: ParameterTable = METRIXS) -> DesignStep:
    """The next ``k`` frames, the most informative of candidates whose beam stays on the screen.

    Candidates around ``anchors`` (settings where the beam was on the screen), their information at
    ``offsets`` (the current estimate, normalized), those whose beam stays on the screen under the
    posterior (``precision``), the best batch of them by the criterion.  ``engine``: the torch twin,
    a random stream per configuration.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng([options.seed, step])
    cfg, screen = candidate_settings(anchors, options.candidates, rng, acceptance=acceptance, options=options,
                                     table=table)
    info = frame_information(engine, cfg, offsets, photons=photons, model_rays=options.fit_rays, rays=options.rays,
                             screen=screen, seed=options.seed + STEP_SEED * (step + 1), table=table)
    spread = info.intensity_sigma(np.linalg.inv(precision))
    allowed = info.intensity - options.confidence * spread >= options.floor
    if not allowed.any():  # a prior-wide posterior: the estimate's own light, rather than no frame at all
        allowed = info.intensity >= options.floor
    choice = select(info.fisher, precision, k, criterion=options.criterion, allowed=allowed)
    idx = choice.indices
    if not idx and options.screen:
        return _screen_scan(anchors[-1], k, step, precision, len(cfg), options, t0)
    return DesignStep(step, cfg[idx], screen[idx], np.asarray(choice.gains), info.intensity[idx], options.criterion,
                      criterion_value(precision, options.criterion), criterion_value(choice.precision,
                                                                                     options.criterion),
                      predicted_sigma(choice.precision), len(cfg), int(allowed.sum()), time.perf_counter() - t0)


def measured_information(engine, meas, offsets: np.ndarray, *, options: DesignOptions, photons: int,
                         table: ParameterTable = METRIXS):
    """The information of the frames of ``meas`` (their settings, at ``offsets``), unbiased frame by frame."""
    return frame_information(engine, meas.configurations, offsets, photons=photons, model_rays=options.fit_rays,
                             rays=options.rays, screen=meas.screen, seed=options.seed, table=table, psd=False)


def posterior_precision(info, table: ParameterTable = METRIXS) -> np.ndarray:
    """The posterior precision of the normalized offsets from measured frames' information, the prior's added."""
    return prior_precision(len(table)) + positive_part(info.fisher.sum(0))  # made semi-definite as a whole


def dark_where_lit(meas, intensity: np.ndarray, floor: float) -> bool:
    """Whether the model is dark in at least half the frames where the beamline was lit.

    Dark: the model puts less than ``floor`` of the source on the screen (``intensity``, per frame
    of ``meas``); lit: the beamline put twice that.  A fit from there has no light to follow.
    """
    lit = np.minimum(meas.hist_x.sum(1), meas.hist_y.sum(1)) >= 2 * floor
    return bool(lit.any()) and int(np.sum(lit & (np.asarray(intensity) < floor))) >= 0.5 * lit.sum()


def update(meas, offsets: np.ndarray, *, options: DesignOptions, step: int, table: ParameterTable = METRIXS):
    """The offsets refitted to every frame of ``meas`` from ``offsets``; returns the fit's result.

    A short fit: the features, then the camera's bins; the analysis fits again in full at the end.
    """
    from bluesky_offsets.model.fit import FitOptions, engine_for, fit
    from bluesky_offsets.model.state import ModelState
    o = FitOptions(rays=options.fit_rays, feature_rays=min(2000, options.fit_rays), seed=options.seed + step,
                   stages=(("features", 8), ("bins", 4)))
    return fit(meas, ModelState(np.asarray(offsets, float).copy(), {}, "design"), engine_for(meas, o, table), o,
               table=table)


GLOBAL_DRAWS = 384
"""Offset vectors a round of :func:`global_starts` traces."""
GLOBAL_ROUNDS = 4
"""Rounds of :func:`global_starts` at most: the first over the prior, each next around the best of the last."""
GLOBAL_ELITE = 24
"""The draws whose spread the next round of :func:`global_starts` draws from."""
GLOBAL_SEED = 53
"""Names the random stream of :func:`global_starts`."""


def global_starts(meas, offsets: np.ndarray, *, photons: int, seed: int, keep: int = 3, draws: int = GLOBAL_DRAWS,
                  rounds: int = GLOBAL_ROUNDS, rays: int = 400, table: ParameterTable = METRIXS) -> np.ndarray:
    """Starts for a fit whose estimate ``offsets`` is dark where the beamline was lit.

    The ``keep`` offset vectors whose twin frames at the settings of ``meas`` come nearest the
    measured ones (χ² of the profiles, ``rays`` model rays a frame, common random numbers), searched
    by the cross-entropy method: ``draws`` over the prior, then rounds drawn from the mean and
    spread of the best :data:`GLOBAL_ELITE`, until the best explains half the light or ``rounds``
    are done.
    """
    from bluesky_offsets.model.state import ModelState, simulate_raw_many
    from bluesky_offsets.physics.beamline import torch_engine
    from bluesky_offsets.physics.twin import Twin
    rng = np.random.default_rng([seed, GLOBAL_SEED])
    twin = Twin(torch_engine(table, meas.spec), scheduler="inline")
    h = np.concatenate([meas.hist_x, meas.hist_y], 1)
    var = h / photons + 1.0 / (photons * rays)
    dark = float(np.sum(h ** 2 / var))  # a model with no light on the screen

    def cost(x: np.ndarray) -> np.ndarray:
        sims = simulate_raw_many(twin, meas.configurations, [ModelState(c) for c in x], rays,
                                 [seed + i for i in range(meas.n)], table, screen=meas.screen)
        return np.array([float(np.sum((np.concatenate(s, 1) - h) ** 2 / var)) for s in sims])

    x = np.vstack([np.asarray(offsets, float)[None], rng.uniform(-MAX_OFFSET, MAX_OFFSET, (draws, len(table)))])
    c = cost(x)
    for _ in range(rounds - 1):
        if c.min() <= 0.5 * dark:
            break
        elite = x[np.argsort(c)[:GLOBAL_ELITE]]
        new = np.clip(elite.mean(0) + np.maximum(elite.std(0), 0.01) * rng.standard_normal((draws, len(table))),
                      -MAX_OFFSET, MAX_OFFSET)
        x, c = np.vstack([x, new]), np.concatenate([c, cost(new)])
    return x[np.argsort(c)[:keep]]


class DesignLoop:
    """The designed measurement between its batches.

    It holds where the beam was found, the estimate of the offsets and the design's precision, and
    each batch's record.  :meth:`step` takes the frames so far and returns the next batch (or None);
    the plan (:func:`plans.design.measure_designed`) and the benchmark measure them.
    """

    def __init__(self, options: DesignOptions, here: np.ndarray, budget: int, photons: int,
                 table: ParameterTable = METRIXS):
        from bluesky_offsets.physics.beamline import torch_engine
        self.o, self.budget, self.photons, self.table = options, int(budget), int(photons), table
        self.engine = torch_engine(table, options={"common_rays": False})
        self.here = np.asarray(here, float)
        self.offsets = np.zeros(len(table))
        self.acceptance = self._acceptance_at(self.offsets)
        self._acceptance_lit = False  # whether the model lit the screen where the acceptance was taken
        self.precision: np.ndarray | None = None
        self.steps: list[dict] = []
        self.global_starts: list[int] = []  # the steps whose update also started from :func:`global_starts`

    def anchors(self, meas) -> np.ndarray:
        """The settings of the frames that put the beam on the screen, both ways above twice the floor.

        Before any such frame: where the beam was found.
        """
        lit = np.minimum(meas.hist_x.sum(1), meas.hist_y.sum(1)) >= 2 * self.o.floor
        return meas.configurations[lit] if lit.any() else self.here[None]

    def _acceptance_at(self, offsets: np.ndarray) -> np.ndarray:
        """The motors' acceptance where the beam was found, the model's offsets ``offsets`` (normalized)."""
        from bluesky_offsets.offsets.beam_search import acceptance
        from bluesky_offsets.physics.beamline import torch_engine
        from bluesky_offsets.physics.twin import Twin
        start = self.table.model_values(self.here, offsets)
        return acceptance(Twin(torch_engine(self.table)), start, open_slits=False, table=self.table)

    def _update_acceptance(self, lit: float) -> None:
        """Take the motors' acceptance anew at the estimate once the model lights where the beam was found.

        ``lit``: the model's share on the screen there at the estimate.  Where the model with no
        offsets is dark there (the beam had to be searched for), the acceptance taken at no offsets
        gives every motor the narrowest width, and the candidates barely move the motors.
        """
        if self._acceptance_lit or lit < self.o.floor:
            return
        if np.any(self.offsets):  # at no offsets the acceptance taken at the start stands
            self.acceptance = self._acceptance_at(self.offsets)
        self._acceptance_lit = True

    def step(self, meas, progress=None) -> tuple[DesignStep, dict] | None:
        """Refit to the frames so far (two or more), then choose the next batch.

        Returns the batch and its record (a row of the ``design`` stream); None once the budget is
        spent or the target met.
        """
        progress = progress or (lambda d: None)
        k = len(self.steps)
        left = self.budget - meas.n
        if left <= 0:
            return None
        res = None
        a = meas.for_analysis(table=self.table)
        if meas.n >= 2:
            progress({"step": k, "stage": "update"})
            res = update(a, self.offsets, options=self.o, step=k, table=self.table)
            self.offsets = res.state.offsets
        info = measured_information(self.engine, a, self.offsets, options=self.o, photons=self.photons,
                                    table=self.table)
        if res is not None and dark_where_lit(a, info.intensity, self.o.floor):
            progress({"step": k, "stage": "global start"})
            ends = [update(a, start, options=self.o, step=k, table=self.table)
                    for start in global_starts(a, self.offsets, photons=self.photons, seed=self.o.seed + k,
                                               table=self.table)]
            best = min([res, *ends], key=lambda e: e.chi2)
            if best is not res:
                res, self.offsets = best, best.state.offsets
                info = measured_information(self.engine, a, self.offsets, options=self.o, photons=self.photons,
                                            table=self.table)
            self.global_starts.append(k)
        self._update_acceptance(info.intensity[0])
        self.precision = posterior_precision(info, self.table)
        sigma = predicted_sigma(self.precision)
        if self.o.target is not None and np.all(sigma / PRIOR_SIGMA < self.o.target):
            return None
        progress({"step": k, "stage": "design"})
        # a remainder smaller than half a batch goes with this batch: a step costs a refit
        size = left if left <= 1.5 * self.o.batch else self.o.batch
        st = next_batch(self.engine, self.offsets, self.precision, self.anchors(meas), self.acceptance,
                        k=size, step=k, photons=self.photons, options=self.o, table=self.table)
        if not len(st.gains):
            return None
        row = {key: v for key, v in st.row().items() if key not in ("gains", "predicted_intensity")}
        row.update(frames_before=meas.n, offsets=np.asarray(self.offsets, float),
                   measured_determined=classes(sigma).count("determined"),
                   update_chi2_reduced=float("nan") if res is None else float(res.chi2_reduced),
                   global_start=k in self.global_starts,
                   gains_json=json.dumps([float(g) for g in st.gains]),
                   predicted_intensity_json=json.dumps([float(v) for v in st.intensity]))
        self.steps.append(row)
        return st, row
