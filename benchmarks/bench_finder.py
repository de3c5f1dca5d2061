"""Offset-finder benchmark: the paper's comparison on this CPU, then the stronger methods.

Runs ``bluesky-offsets find`` (10 seeded runs per method on the paper's
problem with surrogate observations: each seed draws its own problem and the
method's own random numbers), then prints the Markdown section for
``docs/benchmarks.md``: final MSE mean ± std per method at its budget, the
Monte Carlo / smart walker ratio, and the evaluations and seconds each method
needs to reach the smart walker's final MSE.

    python benchmarks/bench_finder.py --out data/bench_finder            # full run (~30 min on 2 busy cores)
    python benchmarks/bench_finder.py --runs 2 --candidates 64 --iterations 20 --out /tmp/bf   # smoke

Results (JSON, plots) go to ``--out``; the Markdown goes to stdout and to
``--out``/section.md.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
from pathlib import Path

import numpy as np


def _fmt(x, spec=".3g"):
    return "never" if x is None or not math.isfinite(x) else format(x, spec)


def markdown(res: dict, command: str) -> str:
    s, reach = res["summary"], res["reach_smart_walker_mse"]
    sw, mc = s.get("smart-walker"), s.get("monte-carlo")
    lines = ["## Offset finder (issue 5)", "",
             f"Command: `{command}`  ",
             f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores (shared with other "
             f"jobs), torch {res.get('torch', '?')}, {res['threads']} torch thread(s), device {res['device']}.  ",
             f"Problem: the paper's (Sec. 3.2): {res['problem']['n_configurations']} bright configurations, "
             f"hidden offsets uniform in ±20 %, observations from the {res['observe']}; seeds {res['seeds'][0]}"
             f"..{res['seeds'][-1]} (each seed: its own problem and its own method draws).  ",
             f"Wall time {res['wall_seconds'] / 60:.1f} min.", ""]
    lines += ["| method | settings | evaluations | final MSE (mean ± std) | median | parameter RMSE | s / run |",
              "|---|---|---:|---:|---:|---:|---:|"]
    for m, v in s.items():
        st = ", ".join(f"{k}={val}" for k, val in v["settings"].items())
        lines.append(f"| {m} | {st} | {v['evaluations']} | {v['mse_mean']:.3e} ± {v['mse_std']:.2e} | "
                     f"{v['mse_median']:.3e} | {v['rmse_mean']:.3f} ± {v['rmse_std']:.3f} | {v['seconds_mean']:.1f} |")
    if sw and mc:
        lines += ["", f"Monte Carlo / smart walker final MSE at equal evaluations ({sw['evaluations']}): "
                      f"**{mc['mse_mean'] / sw['mse_mean']:.1f}x** (paper: 28x; acceptance: >= 10x).", ""]
    if reach:
        lines += [f"Evaluations and seconds to reach the smart walker's final mean MSE "
                  f"({sw['mse_mean']:.3e}); medians over the runs, a run that never reaches it counts as "
                  f"infinite:", "",
                  "| method | budget | runs reaching | evaluations to reach (median / max) | "
                  "share of the walker's evaluations | seconds to reach (median / max) |",
                  "|---|---:|---:|---:|---:|---:|"]
        for m, v in reach.items():
            share = v["evaluations_median"] / sw["evaluations"] if math.isfinite(v["evaluations_median"]) else math.inf
            lines.append(f"| {m} | {res['budgets'][m]['evaluations']} | {v['reached']}/{v['runs']} | "
                         f"{_fmt(v['evaluations_median'], '.0f')} / {_fmt(v['evaluations_max'], '.0f')} | "
                         f"{_fmt(share, '.3f')} | {_fmt(v['seconds_median'], '.1f')} / "
                         f"{_fmt(v['seconds_max'], '.1f')} |")
    if "twin_check" in res:
        lines += ["", "Twin re-simulation (ray coordinates, debiased Sinkhorn divergence, POT, "
                      "squared mm, blur 0.01 mm²; histogram MSE), compensated vs. true configurations, next to "
                      "the twin's own repeat (true vs. true, other seed):", "",
                  "| method | runs | Sinkhorn compensated | Sinkhorn repeat | histogram MSE compensated | "
                  "histogram MSE repeat | dark in the twin (true / mismatched) |", "|---|---:|---:|---:|---:|---:|---:|"]
        for m, v in res["twin_check"].items():
            lines.append(f"| {m} | {v['runs']} | {v['sinkhorn_compensated']:.3e} | {v['sinkhorn_repeat']:.3e} | "
                         f"{v['mse_compensated']:.3e} | {v['mse_repeat']:.3e} | {v.get('dark_true', 0)} / "
                         f"{v.get('dark_mismatch', 0)} |")
    idf = res.get("identifiability")
    if idf:
        su = idf["summary"]
        lines += ["", f"Identifiability at the {idf['method']} solution of seed {idf['seed']} "
                      f"({su['n_configurations']} configurations, counting noise of {su['n_rays']} rays, a perfect "
                      f"model): {su['n_determined']} determined, {su['n_weak']} weak, "
                      f"{su['n_undetermined']} undetermined. Strongest compensating pairs: "
                      + "; ".join(f"{a} ~ {b} ({c:+.2f})" for a, b, c in idf["pairs"][:3]) + "."]
        wm = res.get("identifiability_with_model_error")
        if wm:
            lines += [f"With the surrogate's own test MSE ({wm['model_mse']:.2e} per bin) added to every bin's "
                      f"variance: {wm['n_determined']} determined, {wm['n_weak']} weak, {wm['n_undetermined']} "
                      f"undetermined."]
        cc = idf.get("configuration_curve")
        if cc:
            lines += ["", "Adding configurations (first k of the problem's): "
                      + ", ".join(f"k={k}: {d} determined / {u} undetermined"
                                  for k, d, u in zip(cc["counts"], cc["n_determined"], cc["n_undetermined"])) + "."]
    lines += ["", "Plots: `curves.png` (Fig. 5: loss vs. evaluations and vs. seconds), `identifiability.png`"
                  + (", `footprints_*.png` (Fig. 6)" if "twin_check" in res else "") + " in the output directory."]
    return "\n".join(lines) + "\n"


def _reach(runs: list[dict], target: float) -> dict:
    ev, sec = [], []
    for r in runs:
        loss = np.asarray(r["history"]["loss"])
        hit = np.flatnonzero(loss <= target)
        ev.append(r["history"]["evaluations"][hit[0]] if len(hit) else math.inf)
        sec.append(r["history"]["seconds"][hit[0]] if len(hit) else math.inf)
    ev, sec = np.asarray(ev, float), np.asarray(sec, float)
    return {"reached": int(np.isfinite(ev).sum()), "runs": len(runs), "evaluations_median": float(np.median(ev)),
            "seconds_median": float(np.median(sec)), "evaluations_max": float(ev.max()), "seconds_max": float(sec.max())}


def merge(dirs: list[Path]) -> dict:
    """Combine the results of several ``find`` runs (methods split over processes) into one."""
    parts = [json.loads((d / "results.json").read_text()) for d in dirs]
    res = dict(parts[0])
    for key in ("summary", "budgets", "results"):
        res[key] = {k: v for part in parts for k, v in part[key].items()}
    for part in parts[1:]:
        if part["seeds"] != res["seeds"]:
            raise SystemExit(f"cannot merge runs with different seeds: {part['seeds']} vs {res['seeds']}")
        if "twin_check" in part:
            res.setdefault("twin_check", {}).update(part["twin_check"])
        if "smart-walker" in part["summary"]:
            for k in ("identifiability", "identifiability_with_model_error"):
                res[k] = part.get(k, res.get(k))
    res["wall_seconds"] = max(p["wall_seconds"] for p in parts)
    if "smart-walker" in res["summary"]:
        target = res["summary"]["smart-walker"]["mse_mean"]
        res["reach_smart_walker_mse"] = {m: _reach(runs, target) for m, runs in res["results"].items()}
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="data/bench_finder")
    ap.add_argument("--markdown-only", action="store_true", help="only format an existing results.json")
    ap.add_argument("--merge", nargs="+", type=Path, default=None,
                    help="format the merged results of these output directories (methods run in separate "
                         "processes with the same seeds)")
    args, rest = ap.parse_known_args(argv)
    if args.merge:
        res = merge(args.merge)
        import torch
        res["torch"] = torch.__version__
        md = markdown(res, "merged: " + ", ".join(str(d) for d in args.merge) + (" " + " ".join(rest) if rest else ""))
        Path(args.out).mkdir(parents=True, exist_ok=True)
        from bluesky_offsets.offsets import finder as F
        from bluesky_offsets.offsets.evaluate import plot_curves
        curves = {m: [F.FinderResult(m, np.asarray(r["offsets"]), r["loss"], r["evaluations"], r["seconds"],
                                     r["history"], r["settings"]) for r in runs] for m, runs in res["results"].items()}
        target = res["summary"].get("smart-walker", {}).get("mse_mean")
        plot_curves(curves, Path(args.out) / "curves.png", target=target,
                    title=f"offset finder, {len(res['seeds'])} runs per method, surrogate observations")
        (Path(args.out) / "section.md").write_text(md)
        print(md)
        return 0
    out = Path(args.out)
    find_args = ["find", "--out", str(out), *rest]
    command = "python benchmarks/bench_finder.py --out " + str(out) + (" " + " ".join(rest) if rest else "")
    if not args.markdown_only:
        from bluesky_offsets.commands.cli import main as cli_main
        rc = cli_main(find_args)
        if rc:
            return rc
    res = json.loads((out / "results.json").read_text())
    import torch
    res["torch"] = torch.__version__
    md = markdown(res, command)
    (out / "section.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
