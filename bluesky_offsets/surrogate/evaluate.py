"""Evaluating a surrogate against the twin on fresh samples, next to the twin's own noise.

The held-out set is drawn *at evaluation time* with a fresh seed, by the same
recorded scheme the training data used (uniform box, low-ray pre-screen, a
recorded lottery share of screened-out draws; see :mod:`.dataset`), and each
accepted configuration is traced twice at the same ray count with
independent seeds.  Reported, in histogram units (fraction of source rays,
mean over the 100 bins):

* ``mse`` / ``mse_nonempty``: surrogate vs. the first trace, over the set as
  drawn and over samples whose first trace has at least one ray;
* ``noise_mse`` / ``noise_mse_nonempty``: first vs. second trace on the same
  configurations: the twin's repeat noise, the physical limit.  A model that
  knew the mean histogram exactly would score half of it;
* ``ratio_nonempty`` = ``mse_nonempty / noise_mse_nonempty``;
* ``baseline_zero_mse*``: the MSE of predicting empty histograms, the trivial baseline;
* the same numbers re-weighted to the uniform box (weights ``1 / keep_fraction``
  for lottery-kept samples), and optionally on a plain uniform set.
"""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import replace
from typing import Any

import numpy as np

from bluesky_offsets.streams import stream
from bluesky_offsets.surrogate.dataset import (GOOD_MIN_RAYS, DrawScheme, GenerationSettings, chamber_overrides,
                                               draw_in_memory, openmp_threads)
from bluesky_offsets.surrogate.network import Surrogate
from bluesky_offsets.physics.twin import Twin


def _fresh_seed() -> int:
    return int.from_bytes(os.urandom(6), "little")


def _mse_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return ((np.asarray(a, float) - np.asarray(b, float)) ** 2).mean(axis=1)


def _summary(se_model, se_noise, n_hits, weight=None, se_zero=None) -> dict:
    ne = n_hits > 0
    good = n_hits >= GOOD_MIN_RAYS
    w = np.ones(len(se_model)) if weight is None else np.asarray(weight, float)

    def avg(v, m):
        return float(np.average(v[m], weights=w[m])) if m.any() else float("nan")

    allm = np.ones(len(se_model), bool)
    out = {"n": int(len(se_model)), "n_nonempty": int(ne.sum()), "n_good": int(good.sum()),
           "mse": avg(se_model, allm), "mse_nonempty": avg(se_model, ne), "mse_good": avg(se_model, good),
           "noise_mse": avg(se_noise, allm), "noise_mse_nonempty": avg(se_noise, ne),
           "noise_mse_good": avg(se_noise, good)}
    if se_zero is not None:  # the trivial baseline: predict empty histograms everywhere
        out["baseline_zero_mse"] = avg(se_zero, allm)
        out["baseline_zero_mse_nonempty"] = avg(se_zero, ne)
    out["ratio"] = out["mse"] / out["noise_mse"] if out["noise_mse"] > 0 else float("nan")
    out["ratio_nonempty"] = (out["mse_nonempty"] / out["noise_mse_nonempty"]
                             if out["noise_mse_nonempty"] > 0 else float("nan"))
    return out


def score(model: Surrogate, kept: dict) -> dict:
    """``model`` scored on a set that :func:`evaluate` kept: MSE, repeat noise and their ratio.

    The set is ``out["_data"][name]`` of an evaluation with ``keep_data=True``, as drawn; the
    scores are over all its samples and over the non-empty ones.  Several models scored on one
    set differ by their own error only, not by the set's draw.
    """
    return _summary(_mse_rows(model.predict(kept["params"]), kept["hist"]),
                    _mse_rows(kept["hist2"], kept["hist"]), kept["n_hits"])


def _trace_set(twin: Twin, settings: GenerationSettings, min_samples: int, min_nonempty: int, seed: int,
               progress: bool) -> dict:
    s = replace(settings, seed=seed)
    data = draw_in_memory(twin, s, min_samples=min_samples, min_nonempty=min_nonempty, progress=progress)
    # repeat traces with seeds no draw uses (the draws' seeds come from their own streams)
    rs = np.random.default_rng([seed, 2**40 + 17]).integers(0, 2**32, size=len(data["index"]))
    ovs = [chamber_overrides(c) for c in data["chamber"]] if settings.chamber else None
    with openmp_threads(1) if twin.scheduler == "inline" else contextlib.nullcontext():
        rep = twin.trace_batch(data["params"], overrides=ovs, n_rays=settings.n_rays, seed=[int(x) for x in rs],
                               progress=progress)
    ok = rep.ok
    data["hist2"] = np.concatenate([rep.hist_x, rep.hist_y], axis=1)
    data["n_hits2"] = rep.n_hits
    data["repeat_ok"] = ok
    return data


def evaluate(model: Surrogate, *, n_samples: int = 500, min_nonempty: int = 100, n_uniform: int = 0,
             n_rays: int | None = None, scheme: DrawScheme | None = None, seed: int | None = None,
             twin: Twin | None = None, scheduler: str | None = None, n_workers: int | None = None,
             block_size: int = 64, progress: bool = True, keep_data: bool = False) -> dict:
    """Trace a fresh held-out set with the twin and compare the surrogate to it and to the twin's noise.

    Parameters
    ----------
    n_samples, min_nonempty : int
        Draw until at least this many samples, this many of them non-empty.
    n_uniform : int
        Also evaluate on this many plain uniform draws (no screen).
    n_rays : int, optional
        Rays per trace (default: the model's training ray count, so that the
        noise comparison is at the same ray count).
    scheme : DrawScheme, optional
        Drawing scheme (default: the one the training data recorded).
    seed : int, optional
        Base seed of the fresh draws (default: random, reported).
    """
    prov = model.provenance
    n_rays = int(n_rays or prov.get("n_rays") or 10_000)
    if scheme is None:
        scheme = DrawScheme(**prov["scheme"]) if prov.get("scheme") else DrawScheme()
    seed = _fresh_seed() if seed is None else int(seed)
    own = twin is None
    twin = twin or Twin(n_rays=n_rays, scheduler=scheduler, n_workers=n_workers)
    t0 = time.perf_counter()
    sets = {}
    try:
        # fresh draws of the same inputs the model was trained on (the chamber too), traced by RAYX
        settings = GenerationSettings(n_rays=n_rays, seed=seed, block_size=block_size, scheme=scheme,
                                      chamber=model.chamber)
        sets["screened"] = _trace_set(twin, settings, n_samples, min_nonempty, seed, progress)
        if n_uniform:
            u = GenerationSettings(n_rays=n_rays, seed=stream(seed, "surrogate_check.uniform"), block_size=block_size,
                                   scheme=DrawScheme(screen_rays=0), chamber=model.chamber)
            sets["uniform"] = _trace_set(twin, u, n_uniform, 0, u.seed, progress)
    finally:
        if own:
            twin.close()

    out: dict[str, Any] = {"checkpoint": {"table_version": prov.get("table_version"),
                          "trained_on": {k: prov.get(k) for k in ("n_samples", "n_good", "n_rays", "twin")},
                          "test_metrics": model.metrics.get("test")},
           "n_rays": n_rays, "seed": seed, "engine": twin.engine.version,
           "units": "mean over all 100 bins of squared differences; histograms as fraction of source rays",
           "noise_definition": "MSE between two independent twin traces of the same configuration "
                               "at the same ray count (a perfect mean predictor scores half of it)"}
    for name, d in sets.items():
        ok = d["repeat_ok"] & np.isfinite(d["hist2"]).all(axis=1)
        hist1 = np.concatenate([d["hist_x"], d["hist_y"]], axis=1)[ok]
        inputs = np.concatenate([d["params"], d["chamber"]], axis=1) if model.chamber else d["params"]
        pred = model.predict(inputs[ok])
        se_m = _mse_rows(pred, hist1)
        se_n = _mse_rows(d["hist2"][ok], hist1)
        se_0 = (hist1.astype(float) ** 2).mean(axis=1)
        res = {"drawing": (GenerationSettings(scheme=scheme).scheme.describe() if name == "screened"
                           else DrawScheme(screen_rays=0).describe()),
               "n_draws": int(d["n_draws"]), "n_failed": int(d["n_failed"] + (~ok).sum()),
               "as_drawn": _summary(se_m, se_n, d["n_hits"][ok], se_zero=se_0)}
        if name == "screened":
            res["uniform_weighted"] = _summary(se_m, se_n, d["n_hits"][ok], d["weight"][ok], se_zero=se_0)
            res["n_stratum1"] = int((d["stratum"][ok] == 1).sum())
        out[name] = res
        if keep_data:
            out.setdefault("_data", {})[name] = {"params": inputs[ok], "hist": hist1, "pred": pred,
                                                 "hist2": d["hist2"][ok], "n_hits": d["n_hits"][ok]}
    main = out["screened"]["as_drawn"]
    out["mse"], out["mse_nonempty"] = main["mse"], main["mse_nonempty"]
    out["noise_mse"], out["noise_mse_nonempty"] = main["noise_mse"], main["noise_mse_nonempty"]
    out["ratio_nonempty"] = main["ratio_nonempty"]
    out["baseline_zero_mse_nonempty"] = main.get("baseline_zero_mse_nonempty")
    out["n_samples"], out["n_nonempty"] = main["n"], main["n_nonempty"]
    out["seconds"] = round(time.perf_counter() - t0, 1)
    return out


def plot_comparison(model: Surrogate, data: dict, path, n: int = 3, seed: int = 0) -> None:
    """Paper Fig. 4: twin histogram, surrogate output and absolute error for a few samples."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bluesky_offsets.physics.twin import HistogramSpec
    spec: dict[str, Any] = {k: (tuple(v) if isinstance(v, list) else v)
                            for k, v in model.histogram.items() if k != "normalization"}
    hs = HistogramSpec(**spec)
    ne = np.flatnonzero(data["n_hits"] >= GOOD_MIN_RAYS)
    if len(ne) == 0:
        ne = np.arange(len(data["n_hits"]))
    pick = np.random.default_rng(seed).choice(ne, size=min(n, len(ne)), replace=False)
    fig, axes = plt.subplots(len(pick), 2, figsize=(10, 2.6 * len(pick)), squeeze=False)
    bx = hs.bins_x
    for row, i in enumerate(pick):
        for col, (sl, centers, width, label) in enumerate(
                ((slice(0, bx), hs.centers_x, hs.edges_x[1] - hs.edges_x[0], "x [mm]"),
                 (slice(bx, None), hs.centers_y, hs.edges_y[1] - hs.edges_y[0], "y [mm]"))):
            ax = axes[row, col]
            t, p = data["hist"][i, sl], data["pred"][i, sl]
            ax.bar(centers, t, width=width, color="tab:orange", alpha=0.6, label="twin (RAYX)")
            ax.step(centers, p, where="mid", color="tab:purple", label="surrogate")
            ax.step(centers, np.abs(p - t), where="mid", color="tab:red", label="|error|")
            ax.set_xlabel(label)
            ax.set_ylabel("fraction of rays")
            if row == 0 and col == 0:
                ax.legend(fontsize=8)
        mse = float(((data["pred"][i] - data["hist"][i]) ** 2).mean())
        axes[row, 0].set_title(f"sample {i}: {int(data['n_hits'][i])} rays, MSE {mse:.2e}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
