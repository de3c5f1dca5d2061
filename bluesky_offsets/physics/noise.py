"""The twin's own repeat noise: the floor no model can beat.

Two traces of the same configuration differ because RAYX samples the source
afresh.  Their histogram MSE is the *repeat-noise MSE*.  For a histogram of
``N`` source rays with bin probabilities ``p_i`` the counts are multinomial,
so the expected repeat MSE over ``B`` bins is ``2 / (N B) Σ p_i (1 - p_i)``.
:func:`expected_repeat_mse` evaluates that; :func:`measure_noise_floor`
measures it with the twin; the measured floor ships in
``bluesky_offsets/data/noise_floor.json`` (see ``benchmarks/bench_twin.py``).
"""

from __future__ import annotations

import json
from importlib import resources

import numpy as np

from bluesky_offsets.streams import stream

NOISE_FLOOR_FILE = "noise_floor.json"


def histogram_mse(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """MSE over all bins of concatenated x/y histograms (last axis), as in the paper."""
    return np.mean((np.asarray(a) - np.asarray(b)) ** 2, axis=-1)


def multinomial_variance(p, n_rays):
    """The variance of a bin fraction ``p`` of ``N`` source rays: ``p (1 - p) / N``."""
    return p * (1 - p) / n_rays


def bin_variance(meas, model, n_rays, model_rays: int | None = None, model_var: float = 0.0,
                 floor=None, model_noise=None) -> np.ndarray:
    """The variance of a bin's measured − model fraction: the one noise model of every misfit and fit.

    It is ``p (1 - p) / N`` for the measurement and ``p (1 - p) / N_model`` for a traced model
    (a mean model, e.g. a surrogate: its error variance ``model_var`` instead), ``p`` the mean of
    both kept one ray in ``N`` from 0 and from 1 (a spot within one bin); with a camera's own
    noise ``floor`` (read noise; fraction²) that floor instead, added.  ``model_noise``: where the
    model's bins carry less noise than their values imply (a blurred model,
    :func:`bluesky_offsets.physics.effects.detector_noise`): per bin the kernel-squared sum of
    the fractions it gathers, whose multinomial variance ``Σ k² f − (Σ k f)²`` replaces the
    model's ``f (1 − f)`` in its term.
    """
    n = np.asarray(n_rays, dtype=float)
    # counts: at least one ray's worth in a bin and out of it; a camera's floor is the variance an empty bin has
    p = 0.5 * (np.asarray(meas, float) + np.asarray(model, float))
    p = np.maximum(p, 0.0) if floor is not None else np.clip(p, 1.0 / n, 1.0 - 1.0 / n)
    var = multinomial_variance(p, n) + model_var
    if floor is not None:
        var = var + floor
    if model_rays:
        share: float | np.ndarray = 1.0
        if model_noise is not None:  # the model's multinomial variance, Σ k² f − (Σ k f)², over f (1 − f)
            f = np.asarray(model, float)
            inside = (f > 0) & (f < 1)
            g = np.where(inside, f, 0.5)
            share = np.where(inside, np.clip(np.asarray(model_noise, float) - g * g, 0.0, None) / (g * (1 - g)), 1.0)
        var = var + multinomial_variance(p, model_rays) * share
    return var


def expected_repeat_mse(hist: np.ndarray, n_rays: int) -> np.ndarray:
    """Expected MSE between two independent traces with bin fractions ``hist``.

    ``hist`` is (..., bins) of fractions of source rays (x and y histograms
    concatenated), each bin of variance :func:`multinomial_variance` (no floor: the
    expectation of an empty bin's difference is zero).
    """
    p = np.clip(np.asarray(hist, dtype=float), 0.0, 1.0)
    return 2.0 * np.mean(multinomial_variance(p, float(n_rays)), axis=-1)


def good_configurations(twin, n: int, rng: np.random.Generator, *, min_hits: int = 10,
                        screen_rays: int = 500, max_draws: int = 20000) -> np.ndarray:
    """``n`` configurations drawn uniformly from the sampling box that put rays on the screen.

    Each puts at least ``min_hits`` rays (at ``screen_rays`` source rays) on the screen.
    """
    found: list[np.ndarray] = []
    draws = 0
    while len(found) < n and draws < max_draws:
        batch = twin.table.sample_uniform(max(4 * (n - len(found)), 16), rng)
        draws += len(batch)
        res = twin.trace_batch(batch, n_rays=screen_rays, progress=False)
        found.extend(batch[res.n_hits >= min_hits])
    if len(found) < n:
        raise RuntimeError(f"only {len(found)} non-empty configurations in {draws} draws")
    return np.asarray(found[:n])


def measure_noise_floor(twin, configurations: np.ndarray, n_rays: int, seed: int = 0) -> dict:
    """Measure the repeat-noise MSE: every configuration traced twice with independent seeds."""
    a = twin.trace_batch(configurations, n_rays=n_rays, seed=seed, progress=False)
    b = twin.trace_batch(configurations, n_rays=n_rays, seed=stream(seed, "noise_floor.second_trace"), progress=False)
    ha = np.concatenate([a.hist_x, a.hist_y], axis=1)
    hb = np.concatenate([b.hist_x, b.hist_y], axis=1)
    mse = histogram_mse(ha, hb)
    nonempty = (a.n_hits > 0) & (b.n_hits > 0)
    expected = expected_repeat_mse(0.5 * (ha + hb), n_rays)
    return {"n_rays": int(n_rays), "n_configurations": int(len(configurations)),
            "repeat_mse_mean": float(mse.mean()), "repeat_mse_median": float(np.median(mse)),
            "repeat_mse_nonempty_mean": float(mse[nonempty].mean()) if nonempty.any() else 0.0,
            "expected_mse_mean": float(expected.mean()),
            "per_configuration": mse.tolist()}


def load_noise_floor() -> dict:
    """The noise floor measured at package build time, keyed by ray count (str)."""
    text = resources.files("bluesky_offsets").joinpath("data", NOISE_FLOOR_FILE).read_text()
    return json.loads(text)
