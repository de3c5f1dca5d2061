"""The calibrated beamline model: offsets + physical effects, fitted to measurements.

A :class:`ModelState` is what the model believes about the real beamline: normalized
offsets for the 34 parameters and the values of the physical effects it includes.
:func:`simulate` traces it with the twin (RAYX) at the commanded configurations of a
:class:`Measurement`; :func:`refine` fits it with the one fit engine
(:mod:`bluesky_offsets.model.fit`: the differentiable torch twin, exact Jacobians).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.model.fit import FitOptions, FitResult, engine_for, fit
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.model.values import CalibratedState, ModelState  # noqa: F401 - the model's value types
from bluesky_offsets.physics import effects as E
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.physics.screen import per_frame_overrides


def solve_normal(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x = b`` for the fits' normal equations; least squares where ``a`` is singular.

    ``a`` is singular for a Jacobian with no information on some direction (e.g. all zero),
    where ``solve`` fails with 'Singular matrix'.
    """
    try:
        return np.linalg.solve(a, b)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(a, b, rcond=None)[0]


def _twin_overrides(state: ModelState) -> dict:
    """RML overrides of the state's twin-level effects (detector-level ones act on histograms)."""
    return E.twin_overrides({n: v for n, v in state.effects.items() if E.get(n).level == "twin"})


def simulate_raw(twin, configurations: np.ndarray, state: ModelState, n_rays: int, seed=None,
                 table: ParameterTable = METRIXS, screen=None) -> tuple[np.ndarray, np.ndarray]:
    """Twin histograms of ``state`` before detector-level effects.

    The chamber's stage is at ``screen`` ((n, 3) mm, :mod:`bluesky_offsets.physics.screen`; None: at 0).
    """
    n = len(np.atleast_2d(configurations))
    res = twin.trace_batch(table.model_values(configurations, state.offsets),
                           overrides=per_frame_overrides(_twin_overrides(state), screen, n),
                           n_rays=n_rays, seed=seed, progress=False, raise_on_error=True)
    return res.hist_x, res.hist_y


def simulate_raw_many(twin, configurations: np.ndarray, states: Sequence[ModelState], n_rays: int, seeds,
                      table: ParameterTable = METRIXS, screen=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`simulate_raw` for several states at the same configurations and seeds, in one batch.

    One batch keeps the workers busy; common random numbers make the states comparable.
    """
    n = len(configurations)
    if not states:
        return []
    vals = np.concatenate([table.model_values(configurations, st.offsets) for st in states])
    ovs = [ov for st in states for ov in _frames_overrides(_twin_overrides(st), screen, n)]
    res = twin.trace_batch(vals, overrides=ovs, n_rays=n_rays, seed=list(seeds) * len(states), progress=False,
                           raise_on_error=True)
    hx, hy = res.hist_x, res.hist_y
    return [(hx[i * n:(i + 1) * n], hy[i * n:(i + 1) * n]) for i in range(len(states))]


def _frames_overrides(overrides: dict, screen, n: int) -> list[Mapping]:
    ov = per_frame_overrides(overrides, screen, n)
    return list(ov) if isinstance(ov, list) else [overrides] * n  # the stage never moved: ``ov`` is ``overrides``


def _detector_effects(state: ModelState) -> dict:
    """``state``'s detector-level effects with their values."""
    return {n: v for n, v in state.effects.items() if E.get(n).level == "detector"}


def detector_view(hx, hy, state: ModelState, spec):
    """Histograms ``hx``, ``hy`` through ``state``'s detector-level effects (unchanged where it has none)."""
    det = _detector_effects(state)
    return E.apply_detector_effects(hx, hy, det, spec) if det else (hx, hy)


def simulate(twin, configurations: np.ndarray, state: ModelState, n_rays: int, seed=None,
             table: ParameterTable = METRIXS, screen=None) -> tuple[np.ndarray, np.ndarray]:
    """Twin histograms of ``state`` as the focus chamber would record them (detector-level effects applied).

    ``configurations``: the commanded configurations (n, 34); ``screen``: the stage positions.
    """
    hx, hy = simulate_raw(twin, configurations, state, n_rays, seed, table, screen)
    return detector_view(hx, hy, state, twin.hist)


def simulate_with_noise(twin, configurations: np.ndarray, state: ModelState, n_rays: int, seed=None,
                        table: ParameterTable = METRIXS, screen=None):
    """:func:`simulate`'s histograms and their counting noise through the detector-level effects.

    Returns ``(hx, hy, noise)``: ``noise`` the ``(x, y)`` second moments of the bins' counts
    (:func:`bluesky_offsets.physics.effects.detector_noise`; a blurred model's bins share their
    rays), None where the state has no detector-level effect.  What a misfit of a traced model
    takes as ``model_noise``.
    """
    hx, hy = simulate_raw(twin, configurations, state, n_rays, seed, table, screen)
    det = _detector_effects(state)
    return (*detector_view(hx, hy, state, twin.hist), E.detector_noise(hx, hy, det, twin.hist) if det else None)


def simulate_frames(twin, configurations: np.ndarray, state: ModelState, n_rays: int, seed=None,
                    table: ParameterTable = METRIXS, *, oversample: int = 16,
                    screen=None) -> tuple[np.ndarray, np.ndarray]:
    """Frames of ``state`` as a photon-counting camera records them.

    The twin's histograms at ``oversample`` × ``n_rays`` (near their expectation) go through the
    detector-level effects, then ``n_rays`` source photons are drawn from them (how many reach
    the screen, then where).

    Why not :func:`simulate` where the state has detector-level effects: it applies them to
    counted histograms, which smooths the counting noise along with the beam (a blurred frame
    then carries a fraction of the noise its counts imply), and the analysis's noise model (counts)
    would read every misfit of such frames as within noise (χ²/dof far below 1 at the truth).
    Without detector-level effects the twin's counted histograms are such frames already:
    :func:`simulate`'s.  ``seed``: the configurations' seeds (as :func:`simulate`), which also
    seed the draw (None: unseeded).
    """
    if not _detector_effects(state):
        return simulate(twin, configurations, state, n_rays, seed, table, screen)
    hx, hy = simulate(twin, configurations, state, n_rays * oversample, seed, table, screen)
    rng = np.random.default_rng(None if seed is None else [int(s) for s in np.atleast_1d(seed)])
    fx, fy = np.zeros_like(hx), np.zeros_like(hy)
    for c in range(len(hx)):
        px, py = np.clip(hx[c], 0, None), np.clip(hy[c], 0, None)
        sx, sy = min(px.sum(), 1.0), min(py.sum(), 1.0)
        kx = rng.binomial(n_rays, sx)
        ky = kx if abs(sx - sy) <= 1e-9 else rng.binomial(n_rays, sy)  # the same photons on both axes
        if kx:
            fx[c] = rng.multinomial(kx, px / px.sum()) / n_rays
        if ky:
            fy[c] = rng.multinomial(ky, py / py.sum()) / n_rays
    return fx, fy


def check_twin(meas: Measurement, twin) -> None:
    """The twin must bin its histograms as the measurement is binned."""
    if twin.hist != meas.spec:
        raise InputError(f"the twin bins its histograms as {twin.hist.fingerprint()}, the measurement as "
                         f"{meas.spec.fingerprint()}: use twin.with_hist(measurement.spec)")


@dataclass
class RefineResult:
    """A refinement's outcome: the fitted state, its effects' uncertainties, the fit's history and the fit."""

    state: ModelState
    effect_sigma: dict[str, dict[str, float]]
    history: list[dict]
    fit: FitResult

    @property
    def offset_sigma(self) -> np.ndarray:
        """The fitted normalized offsets' standard deviations (the fit's)."""
        return self.fit.offset_sigma

    @property
    def calibrated(self) -> CalibratedState:
        """The fitted state with the fit's covariance (what the posterior and the calibration file read)."""
        return CalibratedState(self.state, self.fit.covariance, tuple(self.fit.names), prior_sigma=self.fit.prior_sigma)


def refine(meas: Measurement, state: ModelState, twin=None, forward_model=None, *,
           options: FitOptions | Mapping | None = None, progress=None, engine=None,
           table: ParameterTable = METRIXS, also_from: Sequence[ModelState] = (),
           executor: Executor | None = None) -> RefineResult:
    """Fit the offsets and the state's effects to ``meas`` with :func:`bluesky_offsets.model.fit.fit`.

    ``twin`` names the parameter table (the fit traces the torch twin, ``engine``, made for
    the measurement's bins unless given); ``forward_model`` is accepted for symmetry with the
    finders and not used: the twin's own Jacobian is exact and cheap.  ``executor`` runs the
    fit's starts and ray draws side by side (the same result).
    """
    o = FitOptions.resolve(options)
    engine = engine or engine_for(meas, o, table)
    res = fit(meas, state, engine, o, progress=progress, table=table, also_from=also_from, executor=executor)
    return RefineResult(res.state, res.effect_sigma(), res.history, res)
