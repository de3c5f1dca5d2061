"""The finders beside the authors' current baselines, by the authors' protocol.

Every method runs once per repetition on the paper's problem drawn for that repetition (hidden
offsets uniform in ±20 %, 16 bright configurations, observations from the shipped surrogate),
all under one evaluation budget; blop's Bayesian optimizer, whose cost grows with its data, runs
under its own smaller budget and every method is also compared at that count.  Reported per
method: final MSE mean ± σ and median, offset RMSE (normalized), seconds and evaluations; a
two-sided Mann–Whitney U test between every pair on the final MSE; one loss-curve plot.

    python benchmarks/bench_harness.py --out data/harness                 # 30 repetitions, 2 processes
    python benchmarks/bench_harness.py --reps 2 --evaluations 5000 --blop-evaluations 24 --out /tmp/h  # smoke

Each (method, repetition) is saved as it ends (``--out``/runs/), so a stopped run resumes.
Results: ``--out``/harness.json, loss_curves.png, section.md; the result
``benchmarks/results/harness.json`` (``harness_twin.json`` with ``--observe twin``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

OURS = ("smart-walker", "monte-carlo", "levenberg-marquardt", "cmaes", "gradient")
THEIRS = ("genetic", "genetic-100", "powell", "annealing", "blop")
SETTINGS = {"genetic-100": ("genetic", {"candidates": 100}), "smart-walker": ("smart-walker", {"candidates": 1024}),
            "monte-carlo": ("monte-carlo", {"candidates": 1024})}


def _job(args) -> dict:
    """One method on one repetition's problem, in its own process (one torch thread)."""
    label, rep, evaluations, out, observe = args
    path = Path(out) / "runs" / f"{label}_{rep:02d}.json"
    if path.exists():
        return json.loads(path.read_text())
    import torch
    torch.set_num_threads(1)
    from bluesky_offsets.offsets import baselines as B
    from bluesky_offsets.offsets import finder as F
    model = F.load_forward_model()
    twin = None
    if observe == "twin":  # the observations traced by RAYX at 1e5 rays, its sampling noise included
        from bluesky_offsets.physics.twin import Twin
        twin = Twin(scheduler="inline")
    problem = F.make_problem(model, seed=rep, observe=observe, twin=twin)
    name, settings = SETTINGS.get(label, (label, {}))
    r = F.find_offsets(problem, model, B.algorithm(name, **settings), F.Budget(evaluations=evaluations), seed=rep,
                       progress=False)
    d = {"label": label, "rep": rep, "mse": r.loss, "rmse": r.parameter_rmse(problem.true_offsets),
         "seconds": r.seconds, "evaluations": r.evaluations, "settings": r.settings,
         "history": {k: [float(v) for v in vals] for k, vals in r.history.items()}}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(d))
    print(f"{label} rep {rep}: MSE {r.loss:.3e}, RMSE {d['rmse']:.3f}, {r.evaluations} evaluations, "
          f"{r.seconds:.1f} s", flush=True)
    return d


def loss_at(run: dict, evaluations: float) -> float:
    from bluesky_offsets.offsets.finder import loss_at as at
    return at(run["history"], evaluations)


def summarize(runs: dict[str, list[dict]], at: int) -> dict:
    """Per method: MSE, offset RMSE, seconds, evaluations, and the MSE at ``at`` evaluations."""
    out = {}
    for label, rs in runs.items():
        mse = np.array([r["mse"] for r in rs])
        out[label] = {"reps": len(rs), "mse_mean": float(mse.mean()), "mse_std": float(mse.std(ddof=1)),
                      "mse_median": float(np.median(mse)), "rmse_mean": float(np.mean([r["rmse"] for r in rs])),
                      "rmse_std": float(np.std([r["rmse"] for r in rs], ddof=1)),
                      "seconds_mean": float(np.mean([r["seconds"] for r in rs])),
                      "evaluations": int(np.mean([r["evaluations"] for r in rs])),
                      "mse_at_mean": float(np.mean([loss_at(r, at) for r in rs])),
                      "mse_at_median": float(np.median([loss_at(r, at) for r in rs])),
                      "settings": rs[0]["settings"]}
    return out


def mann_whitney(runs: dict[str, list[dict]]) -> dict:
    """Two-sided Mann–Whitney U p-values on the final MSE between every pair of methods."""
    from scipy.stats import mannwhitneyu
    vals = {k: [r["mse"] for r in rs] for k, rs in runs.items()}
    return {a: {b: float(mannwhitneyu(vals[a], vals[b]).pvalue) for b in vals if b != a} for a in vals}


def below(runs: dict[str, list[dict]], reference: str) -> dict:
    """One-sided Mann–Whitney U p-values that each method's final MSE lies below ``reference``'s."""
    from scipy.stats import mannwhitneyu
    ref = [r["mse"] for r in runs[reference]]
    return {k: float(mannwhitneyu([r["mse"] for r in rs], ref, alternative="less").pvalue)
            for k, rs in runs.items() if k != reference}


def plot(runs: dict[str, list[dict]], path: Path) -> None:
    """Every method's best MSE against evaluations, geometric mean over repetitions, on one axis."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(8, 5), constrained_layout=True)
    top = max(max(r["history"]["evaluations"][-1] for r in rs) for rs in runs.values())
    grid = np.geomspace(1, top, 400)
    for i, (label, rs) in enumerate(runs.items()):
        g = grid[grid <= max(r["history"]["evaluations"][-1] for r in rs)]
        curves = np.log10([[loss_at(r, e) for e in g] for r in rs])
        ok = np.isfinite(curves).all(0)
        ax.loglog(g[ok], 10 ** curves[:, ok].mean(0), color=f"C{i % 10}", ls="-" if label in OURS else "--",
                  label=f"{label} ({len(rs)})")
    ax.set_xlabel("evaluations (candidate offset vectors scored)")
    ax.set_ylabel("best MSE so far (geometric mean)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, ncol=2)
    fig.savefig(path, dpi=110)


def tables(res: dict) -> list:
    """The page's tables: every method sorted by its median, and the two-sided p-values between them."""
    from results import Table
    s, p = res["summary"], res["mann_whitney"]
    names = sorted(s, key=lambda k: s[k]["mse_median"])
    blop = "blop" in s  # the MSE at blop's count, where blop ran
    rows = [[k, ", ".join(f"{a}={b}" for a, b in s[k]["settings"].items()), s[k]["reps"], f"{s[k]['evaluations']:,}",
             f"{s[k]['mse_mean']:.2e} ± {s[k]['mse_std']:.1e}", f"{s[k]['mse_median']:.2e}",
             *([_at(s[k])] if blop else []),
             f"{s[k]['rmse_mean']:.3f} ± {s[k]['rmse_std']:.3f}", f"{s[k]['seconds_mean']:.1f}"] for k in names]
    out = [Table(f"{max(v['reps'] for v in s.values())} repetitions per method, sorted by the median:",
                 ["method", "settings", "reps", "evaluations", "final MSE mean ± σ", "median",
                  *([f"MSE at {res['at']} evaluations (mean / median)"] if blop else []), "offset RMSE", "s / run"],
                 rows, align=["l", "l"] + ["r"] * (7 if blop else 6))]
    if len(names) > 1:
        at = f"blop at its {res['blop_evaluations']} evaluations, every other method" if blop else "every method"
        out.append(Table(f"Mann–Whitney U, two-sided p-values on the final MSE ({at} at {res['evaluations']:,}):",
                         ["", *names],
                         [[a, *("—" if a == b else f"{p[a][b]:.1e}" for b in names)] for a in names],
                         align=["l"] + ["r"] * len(names)))
    return out


def write(res: dict, out: Path):
    """The result ``res["result"]`` (default ``harness``, ``harness_twin`` on RAYX's frames); returns it."""
    from results import Figure, ROOT, write_result
    twin = res.get("observe", "surrogate") == "twin"
    name = res.get("result") or ("harness_twin" if twin else "harness")
    summary = (f"Our finders beside the authors' baselines through their own libraries (`offsets/baselines.py`), by "
               f"their protocol: repetition r draws problem r (the paper's: ±20 %, 16 bright configurations, "
               f"observations from {'RAYX at 1e5 rays' if twin else 'the shipped surrogate'}) and the method's "
               f"random numbers from r; every method {res['evaluations']:,} evaluations"
               + (f", blop {res['blop_evaluations']} (its Gaussian process's cost grows with its data)"
                  if "blop" in res["summary"] else "")
               + f"; {res['processes']} processes of one torch thread each, wall {res['wall_seconds'] / 60:.0f} min.")
    notes = []
    if res.get("below_genetic"):
        notes.append("One-sided: final MSE below the authors' GA (500 candidates) at equal evaluations: " + ", ".join(
            f"{k} p = {v:.1e}" for k, v in sorted(res["below_genetic"].items(), key=lambda kv: kv[1]) if k != "blop")
            + ".")
    figures = []
    if name == "harness" and (out / "loss_curves.png").exists():
        page_img = ROOT / "docs" / "img" / "harness_loss_curves.png"  # the page shows the plot of its result
        shutil.copyfile(out / "loss_curves.png", page_img)
        figures.append(Figure("docs/img/harness_loss_curves.png", "best MSE so far against evaluations, every "
                              "method, geometric mean over the repetitions"))
    title = "Offset finder: the authors' protocol" + (" on RAYX's frames" if twin else "") + (
        f" at {res['evaluations']:,} evaluations" if name not in ("harness", "harness_twin") else "") + " (issue 53)"
    return write_result(name, title=title, command=res["command"], summary=summary,
                        tables=tables(res), notes=notes, figures=figures)


def _at(v: dict) -> str:
    """The MSE at blop's count; a method whose first batch is larger has none yet."""
    return "—" if not np.isfinite(v["mse_at_mean"]) else f"{v['mse_at_mean']:.2e} / {v['mse_at_median']:.2e}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("data/harness"))
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--evaluations", type=int, default=50_000)
    ap.add_argument("--blop-evaluations", type=int, default=64)
    ap.add_argument("--blop-reps", type=int, default=None, help="repetitions of blop (default: --reps)")
    ap.add_argument("--methods", default=",".join(OURS + THEIRS))
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--observe", choices=("surrogate", "twin"), default="surrogate",
                    help="the observations: the surrogate's (the paper's) or RAYX's frames at 1e5 rays")
    ap.add_argument("--result", default=None, help="the result's name (default: harness, or harness_twin)")
    a = ap.parse_args(argv)
    from _machine import machine
    labels = a.methods.split(",")
    jobs = [(m, r, a.blop_evaluations if m == "blop" else a.evaluations, str(a.out), a.observe)
            for r in range(a.reps) for m in labels if not (m == "blop" and a.blop_reps is not None and r >= a.blop_reps)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(a.processes) as pool:
        done = list(pool.map(_job, jobs))
    runs: dict[str, list[dict]] = {m: [d for d in done if d["label"] == m] for m in labels}
    at = a.blop_evaluations if "blop" in labels else a.evaluations
    res = {"command": "python benchmarks/bench_harness.py " + " ".join(argv or sys.argv[1:]), "machine": machine(),
           "processes": a.processes, "wall_seconds": time.perf_counter() - t0, "evaluations": a.evaluations,
           "blop_evaluations": a.blop_evaluations, "at": at, "observe": a.observe, "result": a.result, "summary": summarize(runs, at),
           "mann_whitney": mann_whitney(runs),
           "below_genetic": below(runs, "genetic") if "genetic" in labels else {}}
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "harness.json").write_text(json.dumps(res, indent=1))
    plot(runs, a.out / "loss_curves.png")
    from render import section
    md = section(write(res, a.out))
    (a.out / "section.md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    raise SystemExit(main())
