"""``bluesky-offsets find``: the offset finder's evaluation harness (thin layer).

Repeated seeded runs of the methods on the paper's problem, final MSE mean ±
std, the loss curves (Fig. 5), identifiability at the best solution, and -
with ``--twin-check`` - the twin re-simulating the compensated configurations
(histogram MSE, Sinkhorn divergence vs. the twin's repeat noise) and the
footprint plots (Fig. 6).  Everything lands in ``--out`` (JSON + PNG).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from bluesky_offsets.commands.cli import CliError, output_folder

DEFAULT_METHODS = "smart-walker,monte-carlo,gradient,levenberg-marquardt,cmaes"
HEADLINE = {"candidates": 1024, "iterations": 400, "runs": 3}
"""The settings at which the walker ends ≥ 10x below Monte Carlo on the means (docs/benchmarks.md,
"Offset finder: the find command's defaults"); with fewer it may stop short of that."""
PAPER_GPU = {"candidates": 1_000_000, "iterations": 200}
"""The paper's sizes (m = 1e6 candidates, 200 iterations), the defaults where the model runs on a GPU."""
BLOP_EVALUATIONS = 64
"""blop's budget at most: its Bayesian optimizer's cost grows with its data (benchmarks/bench_harness.py)."""


def _count(text: str) -> int:
    """A count as a user types it: ``1024`` or ``1e6``."""
    import argparse
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not v.is_integer():
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}")
    return int(v)


def _fmt(x) -> str:
    return "inf" if x is None or not math.isfinite(x) else f"{x:.3g}"


def _cmd_find(args) -> int:
    from bluesky_offsets.offsets import finder as F
    try:
        return _find(args)
    except F.FinderError as exc:
        raise CliError(str(exc)) from None


def _checked_find_args(args) -> list[str]:
    """The methods asked for, with ``args`` checked and completed.

    Completed: the device, the sizes of the GPU or the headline comparison, the paper's histogram
    floor.  CliError for what a user can fix.
    """
    import torch

    from bluesky_offsets.offsets import baselines as B
    from bluesky_offsets.offsets import finder as F

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    known = {**F.METHODS, **B.BASELINES}
    unknown = [m for m in methods if m not in known]
    if unknown:
        raise CliError(f"unknown method(s) {unknown}; choose from {', '.join(known)}")
    if args.runs < 1:
        raise CliError("--runs must be positive")
    on_gpu = (args.device or ("cuda" if torch.cuda.is_available() else "cpu")).startswith("cuda")
    args.device = args.device or ("cuda" if on_gpu else None)
    sizes = PAPER_GPU if on_gpu else HEADLINE
    args.candidates = sizes["candidates"] if args.candidates is None else args.candidates
    args.iterations = sizes["iterations"] if args.iterations is None else args.iterations
    if args.candidates < 1 or args.iterations < 1:
        raise CliError("--candidates and --iterations must be positive")
    if args.evaluations is not None and args.evaluations < 1:
        raise CliError("--evaluations must be positive (leave it out for candidates x (iterations + 1))")
    if args.seconds is not None and not args.seconds > 0:
        raise CliError("--seconds must be positive")
    if args.min_hist_sum is None:
        args.min_hist_sum = F.PAPER_MIN_HIST_SUM
    if not 0 < args.fast_fraction <= 1:
        raise CliError("--fast-fraction must be in (0, 1]")
    return methods


def _find(args) -> int:
    import torch

    from bluesky_offsets.offsets import finder as F
    from bluesky_offsets.offsets import evaluate as E

    methods = _checked_find_args(args)
    try:
        model = F.load_forward_model(args.model, device=args.device)
    except F.FinderError as exc:
        raise CliError(str(exc)) from None
    out = output_folder(args.out)
    twin = None
    if args.observe == "twin" or args.twin_check:
        from bluesky_offsets.physics.twin import Twin
        twin = Twin(n_rays=args.rays, scheduler=args.scheduler)

    E_paper = args.candidates * (args.iterations + 1)
    evaluations = args.evaluations or E_paper
    seconds = args.seconds
    paper = {"smart-walker": {"candidates": args.candidates}, "monte-carlo": {"candidates": args.candidates}}
    settings = {m: paper.get(m, {}) for m in methods}
    budgets = {}
    for m in methods:
        ev = evaluations if m in paper else max(1, int(evaluations * args.fast_fraction))
        if m == "blop":  # a Gaussian process's cost grows with its data: tens of evaluations, not thousands
            ev = min(ev, BLOP_EVALUATIONS)
        budgets[m] = F.Budget(evaluations=ev, seconds=seconds)

    def make(seed):
        return F.make_problem(model, seed=seed, observe=args.observe, twin=twin, n_rays=args.rays,
                              n_configurations=args.configurations, min_hist_sum=args.min_hist_sum,
                              candidate_configurations=args.candidate_configurations,
                              offset_trials=args.offset_trials, max_rounds=args.max_rounds,
                              progress=not args.no_progress)

    log_lines = []

    def log(msg):
        log_lines.append(msg)
        if not args.quiet:
            print(msg, flush=True)

    seeds = list(range(args.seed, args.seed + args.runs))
    t0 = time.perf_counter()
    problems, results = E.run_methods(model, settings, budgets, seeds, make, threads=args.threads,
                                      progress=not args.no_progress, log=log)
    summary = E.summarize(problems, results)
    target = summary["smart-walker"]["mse_mean"] if "smart-walker" in summary else None
    reach = E.reach_table(results, target) if target is not None else {}
    report = {"model": str(args.model or "shipped"), "device": str(F.model_device(model)),
              "threads": args.threads or torch.get_num_threads(), "observe": args.observe, "seeds": seeds,
              "budgets": {m: {"evaluations": b.evaluations, "seconds": b.seconds} for m, b in budgets.items()},
              "problem": problems[0].summary(), "summary": summary, "reach_smart_walker_mse": reach,
              "results": {m: [r.to_dict() for r in rs] for m, rs in results.items()},
              "wall_seconds": None}
    E.plot_curves(results, out / "curves.png", target=target,
                  title=f"offset finder, {args.runs} runs, {problems[0].n} configurations, {args.observe} observations")

    best_m, rep = _identifiability(report, model, summary, results, problems, seeds, out)

    if args.twin_check:
        report["twin_check"] = _twin_check(args, twin, methods, results, problems, seeds, best_m, out, log)
    if twin is not None:
        twin.close()
    report["wall_seconds"] = time.perf_counter() - t0
    report["log"] = log_lines
    (out / "results.json").write_text(json.dumps(report, indent=1, default=float) + "\n")

    if args.json:
        print(json.dumps({k: report[k] for k in ("summary", "reach_smart_walker_mse", "budgets")}, indent=2,
                         default=float))
    else:
        print(f"\n{'method':14s} {'evaluations':>11s} {'final MSE':>22s} {'param RMSE':>14s} {'s/run':>7s}"
              f"   to reach smart walker's MSE (median evals / s, runs)")
        for m, s in summary.items():
            rc = reach.get(m, {})
            print(f"{m:14s} {s['evaluations']:11d} {s['mse_mean']:10.3e} ± {s['mse_std']:9.3e} "
                  f"{(s['rmse_mean'] or 0):6.3f} ± {(s['rmse_std'] or 0):5.3f} {s['seconds_mean']:7.1f}   "
                  f"{_fmt(rc.get('evaluations_median'))} / {_fmt(rc.get('seconds_median'))} "
                  f"({rc.get('reached', 0)}/{rc.get('runs', 0)})")
        if "smart-walker" in summary and "monte-carlo" in summary:
            ratio = summary["monte-carlo"]["mse_mean"] / summary["smart-walker"]["mse_mean"]
            print(f"Monte Carlo / smart walker final MSE: {ratio:.1f}x (paper: 28x)")
            if args.candidates * (args.iterations + 1) < HEADLINE["candidates"] * (HEADLINE["iterations"] + 1):
                print(f"  (the benchmark's headline ran at --candidates {HEADLINE['candidates']} --iterations "
                      f"{HEADLINE['iterations']}, the defaults; with fewer the walker may stop short of Monte "
                      "Carlo's tenth; docs/benchmarks.md, 'Offset finder: the find command's defaults')")
        print(f"identifiability ({best_m}, seed {seeds[0]}): {rep.summary()['n_determined']} determined, "
              f"{rep.summary()['n_weak']} weak, {rep.summary()['n_undetermined']} undetermined "
              f"-> {out / 'identifiability.txt'}")
        print(f"results and plots in {out}/")
    return 0


def _identifiability(report: dict, model, summary, results, problems, seeds, out: Path):
    """What the best method's first solution leaves open, into ``report`` and its files.

    Returns ``(best method, its identifiability report)``.
    """
    from bluesky_offsets.offsets import identifiability as I

    # identifiability at the best solution of the best method on the first problem: what the counting
    # noise of a 1e5-ray measurement leaves open (a perfect model), and what the surrogate's own error adds
    best_m = min(summary, key=lambda m: summary[m]["mse_mean"])
    r0, p0 = results[best_m][0], problems[0]
    model_mse = getattr(model, "test_mse", 0.0)
    rep = I.analyze(p0, model, r0.offsets, solutions=r0.solutions, solution_losses=r0.solution_losses)
    rep_m = I.analyze(p0, model, r0.offsets, model_mse=model_mse)
    curve = I.configuration_curve(p0, model, r0.offsets)
    I.plot_identifiability(rep, out / "identifiability.png", curve, p0.true_offsets)
    report["identifiability"] = {"method": best_m, "seed": seeds[0], **rep.to_dict(),
                                 "configuration_curve": {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                                                         for k, v in curve.items()}}
    report["identifiability_with_model_error"] = {"model_mse": model_mse, **rep_m.summary(),
                                                  "status": rep_m.status}
    (out / "identifiability.txt").write_text(rep.table() + "\n\nwith the surrogate's test MSE per bin added:\n"
                                             + rep_m.table() + "\n")
    return best_m, rep


def _twin_check(args, twin, methods, results, problems, seeds, best_m: str, out: Path, log) -> dict:
    """Each method's first runs' offsets checked on the twin, and the footprints of the walker's and the best.

    The check is a RAYX re-simulation against the problem's observations and their repeat noise.
    """
    from bluesky_offsets.offsets import evaluate as E

    checks: dict[str, dict[str, Any]] = {}
    for m in methods:
        rows = []
        for r, p in list(zip(results[m], problems))[:args.twin_check]:
            c = E.twin_check(twin, p, r.offsets, n_rays=args.check_rays, seed=int(p.seed or 0) + 1)
            rows.append({k: v for k, v in c.items() if not k.startswith("_")})
        checks[m] = {"runs": len(rows),
                     "sinkhorn_compensated": float(np.nanmean([c["sinkhorn_compensated"] for c in rows])),
                     "sinkhorn_repeat": float(np.nanmean([c["sinkhorn_repeat"] for c in rows])),
                     "dark_true": int(sum(c["dark_true"] for c in rows)),
                     "dark_mismatch": int(sum(c["dark_mismatch"] for c in rows)),
                     "mse_compensated": float(np.mean([c["mse_compensated"] for c in rows])),
                     "mse_repeat": float(np.mean([c["mse_repeat"] for c in rows])), "per_run": rows}
        log(f"twin check {m}: Sinkhorn {checks[m]['sinkhorn_compensated']:.3e} (repeat "
            f"{checks[m]['sinkhorn_repeat']:.3e}), histogram MSE {checks[m]['mse_compensated']:.3e} "
            f"(repeat {checks[m]['mse_repeat']:.3e})")
    for m in ("smart-walker", best_m):
        if m in results:
            # show the configurations the twin finds bright first (a surrogate may call dark ones bright)
            run = checks[m]["per_run"][0] if checks[m]["per_run"] else {}
            bright = run.get("bright_true", [])
            cols = (bright + [i for i in range(problems[0].n) if i not in bright])[:4]
            E.plot_footprints(twin, problems[0], results[m][0].offsets, out / f"footprints_{m}.png",
                              columns=cols, n_rays=args.check_rays,
                              title=f"{m}, seed {seeds[0]}: twin re-simulation "
                                    f"({len(bright)}/{problems[0].n} configurations bright in the twin)")
    return checks


def add_cli(sub) -> None:
    """Register ``find``."""
    p = sub.add_parser("find", help="offset finder: repeated seeded runs of the methods on the paper's problem",
                       description="Build the paper's offset problem (random bright configurations, hidden "
                                   "offsets up to ±20 %%) for each seed, run each method, and report final MSE "
                                   "mean ± std, loss curves (Fig. 5), evaluations/seconds to reach the smart "
                                   "walker's MSE, identifiability, and optionally the twin re-simulation "
                                   "(Sinkhorn, footprints, Fig. 6).")
    p.add_argument("--model", default=None,
                   help="surrogate checkpoint: a path or a shipped name, default or fast (default: default)")
    p.add_argument("--methods", default=DEFAULT_METHODS,
                   help=f"comma-separated (default {DEFAULT_METHODS}); the authors' baselines: genetic (evotorch, "
                        f"the [harness] extra), powell, annealing, blop (the [blop] extra; at most {BLOP_EVALUATIONS} "
                        f"evaluations)")
    p.add_argument("--runs", type=int, default=HEADLINE["runs"],
                   help=f"seeded runs per method (default {HEADLINE['runs']}; the benchmark page's table: 10)")
    p.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    p.add_argument("--candidates", type=_count, default=None,
                   help=f"smart walker / Monte Carlo candidates per iteration (default {HEADLINE['candidates']} on a "
                        "CPU, the benchmark's headline; the paper's 1e6 on a GPU)")
    p.add_argument("--iterations", type=_count, default=None,
                   help=f"smart walker iterations (default {HEADLINE['iterations']} on a CPU, the benchmark's "
                        f"headline; the paper's {PAPER_GPU['iterations']} on a GPU)")
    p.add_argument("--evaluations", type=int, default=None,
                   help="evaluation budget of smart walker and Monte Carlo (default candidates x (iterations+1))")
    p.add_argument("--fast-fraction", type=float, default=0.1,
                   help="budget share of the other methods (default 0.1: they must reach the walker's MSE "
                        "within a tenth of its evaluations)")
    p.add_argument("--seconds", type=float, default=None, help="also stop each run after this many seconds")
    p.add_argument("--configurations", type=int, default=16, help="configurations per problem (default 16, n > 15)")
    p.add_argument("--min-hist-sum", type=float, default=None,
                   help="a configuration is bright if its x+y histogram sum exceeds this (fraction of source "
                        "rays; default the paper's 0.5 in its units = 0.113)")
    p.add_argument("--candidate-configurations", type=int, default=1000,
                   help="random configurations per problem-search round (paper 1000; the authors' later code "
                        "10000)")
    p.add_argument("--offset-trials", type=int, default=100, help="random offsets per round (paper 100)")
    p.add_argument("--max-rounds", type=int, default=50, help="give up after this many rounds (default 50)")
    p.add_argument("--observe", choices=("surrogate", "twin"), default="surrogate",
                   help="observations from the surrogate (paper) or the RAYX twin with noise")
    p.add_argument("--rays", type=int, default=100_000, help="rays of twin observations (default 1e5)")
    p.add_argument("--twin-check", type=int, default=0, metavar="RUNS",
                   help="re-simulate the first RUNS runs of each method with the twin: Sinkhorn, MSE, footprints")
    p.add_argument("--check-rays", type=int, default=20_000, help="rays of the twin check (default 2e4)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler for the twin ('inline' = no Dask)")
    p.add_argument("--device", default=None, help="torch device (default: cpu)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    p.add_argument("--out", default="out/find", help="output directory (default out/find)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no per-run lines")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_find)
