"""Evaluation harness of the offset finder (paper Sec. 4, Figs. 5 and 6).

* :func:`run_methods` - repeated, seeded runs of several methods, each run on
  its own seeded problem (the seed fixes both the problem and the method's
  random draws).
* :func:`summarize` / :func:`reach_table` - final MSE mean ± std, parameter
  RMSE, and the evaluations and seconds each method needs to reach a target
  MSE (e.g. the smart walker's final one).
* :func:`plot_curves` - loss vs. evaluations and vs. seconds, mean and std
  band over runs (Fig. 5).
* :func:`twin_check` - the twin re-simulates the configurations at the true
  and at the compensated offsets: histogram MSE and the (debiased) Sinkhorn
  divergence of the ray coordinates (POT), next to the twin's own repeat
  values (paper: 3.06e-5 vs 2.03e-6).
* :func:`plot_footprints` - uncompensated / observed / compensated footprints
  re-simulated by the twin (Fig. 6).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from bluesky_offsets.offsets import baselines as B
from bluesky_offsets.offsets import finder as F

SINKHORN_REG = 1e-2  # mm^2: entropic blur ~0.1 mm, about one y bin (0.12 mm)
SINKHORN_POINTS = 1000


def run_methods(model, methods: Mapping[str, Mapping], budgets: Mapping[str, F.Budget], seeds: Sequence[int],
                make_problem: Callable[[int], F.OffsetProblem], *, threads: int | None = None,
                progress: bool = True, log: Callable[[str], None] | None = None):
    """Run every method once per seed; returns ``(problems, {method: [FinderResult, ...]})``."""
    from bluesky_offsets.progress import bar
    problems = [make_problem(int(s)) for s in bar(seeds, desc="problems", unit="problem", disable=not progress)]
    results: dict[str, list[F.FinderResult]] = {m: [] for m in methods}
    for name, settings in methods.items():
        for s, p in zip(seeds, problems):
            r = F.find_offsets(p, model, B.algorithm(name, **dict(settings)), budgets[name], seed=int(s),
                               progress=progress, threads=threads)
            results[name].append(r)
            if log:
                rmse = f", parameter RMSE {r.parameter_rmse(p.true_offsets):.3f}" if p.true_offsets is not None else ""
                log(f"{name} seed {s}: MSE {r.loss:.3e} after {r.evaluations} evaluations, {r.seconds:.1f} s{rmse}")
    return problems, results


def summarize(problems: Sequence[F.OffsetProblem], results: Mapping[str, Sequence[F.FinderResult]]) -> dict:
    """Per method: final MSE mean/std, parameter RMSE mean/std, evaluations, seconds."""
    out = {}
    for name, rs in results.items():
        loss = np.array([r.loss for r in rs])
        rmse = np.array([r.parameter_rmse(p.true_offsets) for r, p in zip(rs, problems)
                         if p.true_offsets is not None])
        out[name] = {"runs": len(rs), "mse_mean": float(loss.mean()), "mse_std": float(loss.std(ddof=1)) if len(rs) > 1
                     else 0.0, "mse_median": float(np.median(loss)),
                     "rmse_mean": float(rmse.mean()) if len(rmse) else None,
                     "rmse_std": float(rmse.std(ddof=1)) if len(rmse) > 1 else None,
                     "evaluations": int(np.mean([r.evaluations for r in rs])),
                     "seconds_mean": float(np.mean([r.seconds for r in rs])),
                     "settings": rs[0].settings if rs else {}}
    return out


def reach_table(results: Mapping[str, Sequence[F.FinderResult]], target: float | Sequence[float]) -> dict:
    """Evaluations and seconds each method needs to reach ``target`` (one value, or one per run).

    Medians over the runs that reach it, and how many do; a run that never
    reaches it counts as infinite (so the median is infinite if most fail).
    """
    out = {}
    for name, rs in results.items():
        tg = np.broadcast_to(np.asarray(target, dtype=float), (len(rs),))
        hits = [r.reached(t) for r, t in zip(rs, tg)]
        ev = np.array([h[0] for h in hits])
        sec = np.array([h[1] for h in hits])
        out[name] = {"reached": int(np.isfinite(ev).sum()), "runs": len(rs),
                     "evaluations_median": float(np.median(ev)), "seconds_median": float(np.median(sec)),
                     "evaluations_max": float(ev.max()), "seconds_max": float(sec.max())}
    return out


def _band(rs: Sequence[F.FinderResult], key: str, grid: np.ndarray):
    curves = []
    for r in rs:
        x, y = np.asarray(r.history[key], float), np.asarray(r.history["loss"], float)
        idx = np.searchsorted(x, grid, side="right") - 1
        curves.append(np.where(idx >= 0, y[np.clip(idx, 0, None)], np.nan))
    c = np.log10(np.asarray(curves))
    seen = np.isfinite(c).any(axis=0)  # grid points before any run's first value: no band
    mean, std = np.full(len(grid), np.nan), np.full(len(grid), np.nan)
    mean[seen], std[seen] = np.nanmean(c[:, seen], axis=0), np.nanstd(c[:, seen], axis=0)
    return 10 ** mean, 10 ** std


def plot_curves(results: Mapping[str, Sequence[F.FinderResult]], path, *, title: str = "",
                target: float | None = None) -> Path:
    """Best MSE vs. evaluations and vs. seconds: geometric mean over runs, shaded x/÷ one std (Fig. 5)."""
    from bluesky_offsets.plotting import pyplot, save_figure
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), constrained_layout=True)
    for ax, key, label in ((axes[0], "evaluations", "evaluations (candidate offsets scored)"),
                           (axes[1], "seconds", "seconds (this machine)")):
        xmax = max(max(r.history[key][-1] for r in rs) for rs in results.values() if rs)
        xmin = min(min(r.history[key][0] for r in rs) for rs in results.values() if rs)
        grid = np.geomspace(max(xmin, 1e-3), xmax, 300)
        for i, (name, rs) in enumerate(results.items()):
            if not rs:
                continue
            g = grid[grid <= max(r.history[key][-1] for r in rs)]
            m, s = _band(rs, key, g)
            ax.loglog(g, m, color=f"C{i}", label=f"{name} ({len(rs)} runs)")
            ax.fill_between(g, m / s, m * s, color=f"C{i}", alpha=0.2)
        if target is not None:
            ax.axhline(target, color="0.4", ls=":", lw=1, label="smart walker's final MSE")
        ax.set_xlabel(label)
        ax.set_ylabel("best MSE so far")
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=8)
    return save_figure(fig, path, dpi=110, title=title)


# --------------------------------------------------------------------------- #
# back to the twin
# --------------------------------------------------------------------------- #
def sinkhorn(a: np.ndarray, b: np.ndarray, *, reg: float = SINKHORN_REG, max_points: int = SINKHORN_POINTS,
             rng: np.random.Generator | None = None) -> float:
    """Debiased Sinkhorn divergence (POT) between two ray clouds (n, 2) in mm, squared-Euclidean cost.

    Clouds larger than ``max_points`` are subsampled at random (the cost is
    quadratic in the points).  NaN if a cloud is empty (no rays on the
    screen: the divergence is undefined; :func:`twin_check` counts those).
    """
    import ot
    if len(a) == 0 or len(b) == 0:
        return math.nan
    rng = rng or np.random.default_rng(0)
    if len(a) > max_points:
        a = a[rng.choice(len(a), max_points, replace=False)]
    if len(b) > max_points:
        b = b[rng.choice(len(b), max_points, replace=False)]
    return float(max(ot.bregman.empirical_sinkhorn_divergence(a, b, reg, warn=False), 0.0))


def twin_check(twin, problem: F.OffsetProblem, offsets, *, n_rays: int = 20_000, seed: int = 0,
               sinkhorn_points: int = SINKHORN_POINTS, reg: float = SINKHORN_REG, progress: bool = False) -> dict:
    """Re-simulate with the twin: the true configurations (twice, independent seeds) and the compensated ones.

    Returns per-configuration and mean values of the histogram MSE and the
    Sinkhorn divergence, compensated vs. true, next to true vs. true (the
    twin's own repeat noise); the rays are returned for footprint plots.
    """
    if problem.true_offsets is None:
        raise F.FinderError("twin_check needs a problem with known true offsets")
    true = problem.physical_configurations(problem.true_offsets)
    comp = problem.physical_configurations(offsets)
    n = problem.n
    both = np.concatenate([true, true, comp])
    res = twin.trace_batch(both, n_rays=n_rays, keep_rays=True, seed=seed, progress=progress)
    hist = np.concatenate([res.hist_x, res.hist_y], axis=1)
    rays = [r.rays if r.rays is not None else np.empty((0, 2)) for r in res.results]
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    rep_mse = np.mean((hist[:n] - hist[n:2 * n]) ** 2, axis=1)
    comp_mse = np.mean((hist[2 * n:] - hist[:n]) ** 2, axis=1)
    rep_sk = np.array([sinkhorn(rays[i], rays[n + i], reg=reg, max_points=sinkhorn_points, rng=rng) for i in range(n)])
    comp_sk = np.array([sinkhorn(rays[2 * n + i], rays[i], reg=reg, max_points=sinkhorn_points, rng=rng)
                        for i in range(n)])
    dark_true = int(sum(len(rays[i]) == 0 for i in range(n)))
    dark_mismatch = int(sum((len(rays[i]) == 0) != (len(rays[2 * n + i]) == 0) for i in range(n)))
    return {"n_rays": n_rays, "sinkhorn_reg_mm2": reg, "sinkhorn_points": sinkhorn_points,
            "mse_compensated": float(comp_mse.mean()), "mse_repeat": float(rep_mse.mean()),
            "sinkhorn_compensated": float(np.nanmean(comp_sk)) if np.isfinite(comp_sk).any() else math.nan,
            "sinkhorn_repeat": float(np.nanmean(rep_sk)) if np.isfinite(rep_sk).any() else math.nan,
            "dark_true": dark_true, "dark_mismatch": dark_mismatch,
            "bright_true": [i for i in range(n) if len(rays[i])],
            "per_configuration": {"mse_compensated": comp_mse.tolist(), "mse_repeat": rep_mse.tolist(),
                                  "sinkhorn_compensated": comp_sk.tolist(), "sinkhorn_repeat": rep_sk.tolist()},
            "sinkhorn_seconds": time.perf_counter() - t0,
            "_rays": {"true": rays[:n], "compensated": rays[2 * n:]},
            "_hist": {"true": hist[:n], "compensated": hist[2 * n:]}}


def plot_footprints(twin, problem: F.OffsetProblem, offsets, path, *, columns: Sequence[int] | None = None,
                    n_rays: int = 20_000, seed: int = 0, title: str = "") -> Path:
    """Footprints re-simulated by the twin: uncompensated, observed and compensated (Fig. 6).

    Uncompensated: the configuration as set; observed: with the true offsets, or the measured
    histograms; compensated: with the found offsets.
    """
    from bluesky_offsets.plotting import pyplot, save_figure
    plt = pyplot()
    cols = list(columns if columns is not None else range(min(4, problem.n)))
    rows = [("uncompensated", problem.physical_configurations(None), "C0")]
    if problem.true_offsets is not None:
        rows.append(("observed (true offsets)", problem.physical_configurations(problem.true_offsets), "C1"))
    rows.append(("compensated (found offsets)", problem.physical_configurations(offsets), "C2"))
    vals = np.concatenate([r[1][cols] for r in rows])
    res = twin.trace_batch(vals, n_rays=n_rays, keep_rays=True, seed=seed, progress=False)
    h = twin.hist
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(3.6 * len(cols), 3.0 * len(rows)),
                             constrained_layout=True, squeeze=False)
    for ri, (label, _, color) in enumerate(rows):
        for ci, c in enumerate(cols):
            ax = axes[ri][ci]
            r = res.results[ri * len(cols) + ci]
            rays = r.rays if r.rays is not None else np.empty((0, 2))
            if len(rays):
                ax.scatter(rays[:, 0], rays[:, 1], s=0.5, alpha=0.3, color=color, rasterized=True)
            ax2 = ax.twinx()
            ax2.stairs(r.hist_x, h.edges_x, color=color, alpha=0.8)
            ax2.set_yticks([])
            if problem.true_offsets is None and ri == 0:
                pass
            ax.set_xlim(*h.range_x)
            ax.set_ylim(*h.range_y)
            ax.set_title(f"config {c}: {label}\ntransmission {r.transmission:.3f}", fontsize=8)
            ax.tick_params(labelsize=7)
            if ci == 0:
                ax.set_ylabel("y [mm]")
            if ri == len(rows) - 1:
                ax.set_xlabel("x [mm]")
    if problem.true_offsets is None:
        # a measurement: overlay the measured x histograms on the compensated row
        for ci, c in enumerate(cols):
            ax2 = axes[-1][ci].twinx()
            ax2.stairs(problem.observations[c, :h.bins_x], h.edges_x, color="C1", ls="--", label="measured")
            ax2.set_yticks([])
    return save_figure(fig, path, dpi=110, title=title)
