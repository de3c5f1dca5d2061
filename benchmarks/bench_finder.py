"""Offset-finder benchmark: the paper's comparison on this CPU, then the stronger methods.

Runs ``bluesky-offsets find`` (10 seeded runs per method on the paper's
problem with surrogate observations: each seed draws its own problem and the
method's own random numbers), then writes ``benchmarks/results/finder_surrogate.json``
(``finder_fast.json`` with ``--model fast``; ``--result NAME`` otherwise): final MSE mean ± std per
method at its budget, the Monte Carlo / smart walker ratio, and the evaluations and seconds each
method needs to reach the smart walker's final MSE.

    python benchmarks/bench_finder.py --out data/bench_finder            # full run (~30 min on 2 busy cores)
    python benchmarks/bench_finder.py --runs 2 --candidates 64 --iterations 20 --out /tmp/bf   # smoke

Results (JSON, plots) go to ``--out``; the page's section goes to stdout and to
``--out``/section.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np


TITLES = {"finder_surrogate": "Offset finder: ten seeds on the shipped surrogate (issue 18)",
          "finder_fast": "Offset finder: the fast checkpoint",
          "finder_gpu": "Offset finder: the paper's m = 1,000,000 on a GPU"}


def _fmt(x, spec=".3g"):
    return "never" if x is None or not math.isfinite(x) else format(x, spec)


def _tables(res: dict) -> list:
    """The final MSE per method, the runs' reach of the walker's final MSE, and the twin check."""
    from results import Table
    s, reach = res["summary"], res.get("reach_smart_walker_mse")
    tables = [Table(f"Final MSE at each method's budget (wall time {res['wall_seconds'] / 60:.1f} min):",
                    ["method", "settings", "evaluations", "final MSE (mean ± std)", "median", "parameter RMSE",
                     "s / run"],
                    [[m, ", ".join(f"{k}={val}" for k, val in v["settings"].items()), v["evaluations"],
                      f"{v['mse_mean']:.3e} ± {v['mse_std']:.2e}", f"{v['mse_median']:.3e}",
                      f"{v['rmse_mean']:.3f} ± {v['rmse_std']:.3f}", f"{v['seconds_mean']:.1f}"]
                     for m, v in s.items()], align=["l", "l", "r", "r", "r", "r", "r"])]
    sw = s.get("smart-walker")
    if reach and sw:
        rows = []
        for m, v in reach.items():
            share = v["evaluations_median"] / sw["evaluations"] if math.isfinite(v["evaluations_median"]) else math.inf
            rows.append([m, res["budgets"][m]["evaluations"], f"{v['reached']}/{v['runs']}",
                         f"{_fmt(v['evaluations_median'], '.0f')} / {_fmt(v['evaluations_max'], '.0f')}",
                         _fmt(share, ".3f"), f"{_fmt(v['seconds_median'], '.1f')} / {_fmt(v['seconds_max'], '.1f')}"])
        tables.append(Table(f"Evaluations and seconds to reach the smart walker's final mean MSE ({sw['mse_mean']:.3e}); "
                            "medians over the runs, a run that never reaches it counts as infinite:",
                            ["method", "budget", "runs reaching", "evaluations to reach (median / max)",
                             "share of the walker's evaluations", "seconds to reach (median / max)"], rows,
                            align=["l", "r", "r", "r", "r", "r"]))
    if "twin_check" in res:
        tables.append(Table("Twin re-simulation (ray coordinates, debiased Sinkhorn divergence, POT, squared mm, "
                            "blur 0.01 mm²; histogram MSE), compensated vs. true configurations, next to the twin's "
                            "own repeat (true vs. true, other seed):",
                            ["method", "runs", "Sinkhorn compensated", "Sinkhorn repeat", "histogram MSE compensated",
                             "histogram MSE repeat", "dark in the twin (true / mismatched)"],
                            [[m, v["runs"], f"{v['sinkhorn_compensated']:.3e}", f"{v['sinkhorn_repeat']:.3e}",
                              f"{v['mse_compensated']:.3e}", f"{v['mse_repeat']:.3e}",
                              f"{v.get('dark_true', 0)} / {v.get('dark_mismatch', 0)}"]
                             for m, v in res["twin_check"].items()], align=["l"] + ["r"] * 6))
    return tables


def _notes(res: dict) -> list[str]:
    """The identifiability at the best solution, with and without the model's error, and by configurations."""
    idf, notes = res.get("identifiability"), []
    if not idf:
        return notes
    su = idf["summary"]
    notes.append(f"Identifiability at the {idf['method']} solution of seed {idf['seed']} ({su['n_configurations']} "
                 f"configurations, counting noise of {su['n_rays']} rays, a perfect model): {su['n_determined']} "
                 f"determined, {su['n_weak']} weak, {su['n_undetermined']} undetermined. Strongest compensating "
                 "pairs: " + "; ".join(f"{a} ~ {b} ({c:+.2f})" for a, b, c in idf["pairs"][:3]) + ".")
    wm = res.get("identifiability_with_model_error")
    if wm:
        notes.append(f"With the surrogate's own test MSE ({wm['model_mse']:.2e} per bin) added to every bin's "
                     f"variance: {wm['n_determined']} determined, {wm['n_weak']} weak, {wm['n_undetermined']} "
                     "undetermined.")
    cc = idf.get("configuration_curve")
    if cc:
        notes.append("Adding configurations (first k of the problem's): " + ", ".join(
            f"k={k}: {d} determined / {u} undetermined"
            for k, d, u in zip(cc["counts"], cc["n_determined"], cc["n_undetermined"])) + ".")
    return notes


def write(res: dict, command: str, name: str):
    """The result ``benchmarks/results/<name>.json`` of a finished (or merged) run; returns it."""
    from results import write_result
    s = res["summary"]
    sw, mc = s.get("smart-walker"), s.get("monte-carlo")
    ratio = (f" Monte Carlo / smart walker final MSE at equal evaluations ({sw['evaluations']}): "
             f"**{mc['mse_mean'] / sw['mse_mean']:.1f}×** (paper: 28×; asked: ≥ 10×).") if sw and mc else ""
    summary = (f"The paper's problem (Sec. 3.2): {res['problem']['n_configurations']} bright configurations, hidden "
               f"offsets uniform in ±20 %, observations from the {res['observe']}; seeds {res['seeds'][0]}"
               f"..{res['seeds'][-1]}, each its own problem and the method's own draws; torch "
               f"{res.get('torch', '?')}, {res['threads']} torch thread(s), device {res['device']}." + ratio)
    return write_result(name, title=TITLES.get(name, f"Offset finder: {name}"), command=command, summary=summary,
                        tables=_tables(res), notes=_notes(res))


def _result_name(rest: list[str]) -> str:
    """The result a run replaces: the fast checkpoint's or the shipped surrogate's."""
    model = rest[rest.index("--model") + 1] if "--model" in rest[:-1] else None
    return "finder_fast" if model == "fast" else "finder_surrogate"


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
    ap.add_argument("--markdown-only", action="store_true", help="no new runs: the result of an existing results.json")
    ap.add_argument("--merge", nargs="+", type=Path, default=None,
                    help="format the merged results of these output directories (methods run in separate "
                         "processes with the same seeds)")
    ap.add_argument("--result", default=None, help="the result's name (default: finder_surrogate, or "
                                                   "finder_fast with --model fast)")
    args, rest = ap.parse_known_args(argv)
    from render import section
    name = args.result or _result_name(rest)
    if args.merge:
        res = merge(args.merge)
        import torch
        res["torch"] = torch.__version__
        md = section(write(res, "python benchmarks/bench_finder.py --merge " + " ".join(str(d) for d in args.merge)
                           + (" " + " ".join(rest) if rest else ""), name))
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
    md = section(write(res, command, name))
    (out / "section.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
