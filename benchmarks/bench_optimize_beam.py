"""From a calibrated twin to a better beam, over several draws (issue 21's first acceptance item).

Each draw is the README's main job (``bluesky-offsets demo``) with its own seed and a hidden
effect the tests do not use: the simulated IOC with hidden offsets in all 34 parameters, the
calibration (beam search and designed frames, the offsets fitted through the differentiable
twin, diagnosis, effect added and refitted, validation frames), then
``plans.optimize.optimize_beam`` for the smallest focus in a closed loop (3 frames before and
after each move).  The demo also runs the same optimizer, with the same limits and options, on
the hidden true state: the best the true beamline can reach.  A draw passes issue 21's item
when the measured focus is within 10 % of that best and of the prediction, per axis (rms);
issue 50 asks within 5 % of the best per axis.  The target's own cost (both widths over where
they started, squared and summed) is given beside: the optimizer trades one axis for the other.

    python benchmarks/bench_optimize_beam.py [--draws 5] [--out DIR]
    python benchmarks/bench_optimize_beam.py --rows DIR/optimize_beam.json   # the result again from its rows

Writes ``DIR/optimize_beam.json``, its copy in ``benchmarks/results/raw/`` and the result
``benchmarks/results/optimize_beam.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path


# (seed, --effect): hidden effects and values the tests never use
DRAWS = [(1, "chamber_z:z=-14"), (2, "thermal_bump_m1:height=320"), (3, "source_divergence:divergence=0.35"),
         (4, "chamber_z:z=9"), (5, "grating_line_density:delta=0.12")]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=5)
    ap.add_argument("--out", default="bench-optimize-beam")
    ap.add_argument("--rows", type=Path, help="write the result from these rows instead of running the draws")
    args = ap.parse_args(argv)
    if args.rows is not None:
        write(json.loads(args.rows.read_text()))
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed, effect in DRAWS[:args.draws]:
        d = out / f"seed{seed}"
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "bluesky_offsets.commands.cli", "demo", "--seed", str(seed),
                               "--effect", effect, "--out", str(d), "--store", str(d / "runs")],
                              capture_output=True, text=True)
        (d / "demo.log").parent.mkdir(parents=True, exist_ok=True)
        (d / "demo.log").write_text(proc.stdout + proc.stderr)
        if proc.returncode != 0:
            rows.append({"seed": seed, "effect": effect, "error": proc.stderr.strip().splitlines()[-1:]})
            print(f"seed {seed} ({effect}): the demo failed, see {d / 'demo.log'}", flush=True)
            continue
        s = json.loads((d / "summary.json").read_text())
        b = s["beam"]
        r = {"seed": seed, "effect": effect, "verdict": s["verdict"], "seconds": time.perf_counter() - t0,
             "uid": b["uid"], "trusted": b["trusted"]}
        for a in "xy":
            r[f"before_{a}"] = b["before"][f"rms_{a}"]
            r[f"after_{a}"] = b["after"][f"rms_{a}"]
            r[f"predicted_{a}"] = b["predicted"][f"rms_{a}"]
            r[f"sigma_{a}"] = b["predicted_sigma"][a]
            r[f"best_{a}"] = b["true_best"][f"rms_{a}"]
            r[f"after_over_best_{a}"] = r[f"after_{a}"] / r[f"best_{a}"]
            r[f"after_over_predicted_{a}"] = r[f"after_{a}"] / r[f"predicted_{a}"]
            # after - predicted in units of both uncertainties (the calibration's, the rays counted)
            r[f"noise_{a}"] = b["after"].get(f"sigma_rms_{a}", float("nan"))
            r[f"pull_{a}"] = (r[f"after_{a}"] - r[f"predicted_{a}"]) / (r[f"sigma_{a}"] ** 2 + r[f"noise_{a}"] ** 2) ** 0.5
        r["intensity_before"], r["intensity_after"] = b["before"]["intensity"], b["after"]["intensity"]
        r["cost_after_over_best"] = _cost(r, "after") / _cost(r, "best")
        r["pass"] = all(r[f"after_over_best_{a}"] <= 1.10 and abs(r[f"after_over_predicted_{a}"] - 1) <= 0.10
                        for a in "xy")
        rows.append(r)
        print(json.dumps(r), flush=True)
        (out / "optimize_beam.json").write_text(json.dumps(rows, indent=1))
    write(rows)
    return 0


def _cost(r: dict, which: str) -> float:
    """The smallest-focus target's own cost of the row's ``which`` beam, against where it started."""
    from bluesky_offsets.optimize.targets import Focus, SmallestFocus

    def focus(k: str) -> Focus:
        return Focus(math.nan, math.nan, math.nan, r[f"{k}_x"], r[f"{k}_y"])
    return SmallestFocus().cost(focus(which), focus("before"))


def write(rows: list[dict]) -> None:
    """The result ``optimize_beam`` from the draws' rows."""
    from render import section
    from results import Table, raw_path, write_result
    table_rows = []
    for r in rows:
        if "error" in r:
            table_rows.append([r["seed"], r["effect"], f"failed: {r['error']}", "", "", "", "", "", "", "", "no"])
            continue

        def um(k):
            return f"{r[k + '_x'] * 1e3:.1f} × {r[k + '_y'] * 1e3:.1f}"
        table_rows.append([r["seed"], r["effect"], um("before"), um("after"),
                           f"{um('predicted')} (± {r['sigma_x'] * 1e3:.1f}, ± {r['sigma_y'] * 1e3:.1f})", um("best"),
                           f"{r['after_over_best_x']:.3f}, {r['after_over_best_y']:.3f}",
                           f"{r['after_over_predicted_x']:.3f}, {r['after_over_predicted_y']:.3f}",
                           f"{r['pull_x']:+.1f}, {r['pull_y']:+.1f}", f"{_cost(r, 'after') / _cost(r, 'best'):.3f}",
                           "yes" if r["pass"] else "no"])
    ok = sum(bool(r.get("pass")) for r in rows)
    # issue 50's item: open loop, one move, within 5 % of the truth's best per axis
    near = sum(all(r.get(f"after_over_best_{a}", float("inf")) <= 1.05 for a in "xy") for r in rows)
    cheaper = sum("error" not in r and _cost(r, "after") <= 1.05 * _cost(r, "best") for r in rows)
    raw = raw_path("optimize_beam.json")
    raw.write_text(json.dumps(rows, indent=1))
    table = Table(f"{len(rows)} draws:", ["seed", "hidden effect", "before x × y [µm]", "after", "predicted (± σ)",
                                          "true best", "after/best x, y", "after/predicted x, y",
                                          "(after − predicted)/σ x, y", "target's cost: after/best", "pass"],
                  table_rows, align=["r"] + ["l"] * 10)
    result = write_result(
        "optimize_beam", title="Beam optimization (issue 21)", tables=[table], data=[str(raw)],
        summary="Issue 21's first acceptance item, from a calibrated twin to a better beam. Each draw is "
                "`bluesky-offsets demo --seed S --effect E` (hidden offsets in all 34 parameters, a hidden effect "
                "the tests do not use), ending with `optimize_beam(\"smallest_focus\", ...)` in a closed loop (a move, "
                "the model refitted with its frames, a second move, back to the first where the second measured "
                "worse; 3 frames before and after each); \"after\" is where the loop ended; \"true best\" is the same optimizer, limits and options on the hidden true state. "
                "σ of the prediction: the calibration's; the pull divides by it and the measured width's own "
                "statistical σ (the rays counted) in quadrature. Pass: after ≤ 1.1 × true best and "
                f"|after/predicted − 1| ≤ 0.1, per axis. **{ok} of {len(rows)} draws pass; {near} of {len(rows)} "
                f"within 1.05 of the true best in x and y (issue 50); {cheaper} of {len(rows)} within 1.05 of it by the "
                f"target's own cost, which trades one axis against the other.**")
    print(section(result))


if __name__ == "__main__":
    sys.exit(main())
