"""The Fisher ceiling of the design space: how many offsets a designed measurement can determine,
against the photons a frame counts and the model rays a fit traces per frame.

For hidden offsets drawn as the demo draws them (±``--fraction`` of each range), the beam found
from the motors' start by the real search, a pool of candidate settings drawn as the design draws
them (:func:`bluesky_offsets.design.candidate_settings`: motors, slits, the chamber's stage), each
candidate's information at the truth from the twin's exact Jacobian (two halves of the rays:
unbiased), then the greedy D-optimal batch of ``--frames`` minus the search's frames.  The
information of a frame is about 1 / (1/N + 1/K) for N photons a frame and K model rays, but not
exactly: a bin's variance is at least one photon's (as the fit counts it), so each budget's
information is computed at its own N and K (scaling one pool's information credited the bins
the beam barely reaches with variances below one photon's: 0.35 where 0.75 holds, seed 1 at ±5 %).
The table gives the determined count (σ below a tenth of the prior's) for each (N, K) — the best a
design from this pool can do, before any fit: a ceiling.  The batch is chosen on one set of rays
and judged on another (its frames' unbiased matrices summed, then made positive semi-definite):
judged on the rays it was chosen on, a batch is credited with the noise it was chosen for
(``determined_as_chosen`` gives that count beside the honest one).

Beside the count, the least RMSE any estimator of the offsets can expect from those frames: the
linear-Gaussian posterior whose prior is the hidden offsets' own spread (σ_t, the uniform draw's),
``sqrt(tr((F + I / σ_t²)⁻¹) / P) / σ_t``, for the D-optimal batch and for a greedy A-optimal one
chosen under that prior (the batch that minimizes this very number), each judged on other rays.

    python benchmarks/bench_design_ceiling.py --seeds 0 1 2 [--frames 60] [--pool 400] [--out FILE]

The rows go to ``--out`` (default ``benchmarks/results/raw/design_ceiling.json``), the result to
``benchmarks/results/design_ceiling.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine  # noqa: E402

from bluesky_offsets.design import DesignOptions, candidate_settings, classes, frame_information  # noqa: E402
from bluesky_offsets.design import predicted_sigma, prior_precision, select  # noqa: E402
from bluesky_offsets.design.information import positive_part  # noqa: E402
from bluesky_offsets.offsets.beam_search import acceptance  # noqa: E402
from bluesky_offsets.physics.parameters import METRIXS as T  # noqa: E402
from bluesky_offsets.physics.engine import TorchEngine  # noqa: E402
from bluesky_offsets.physics.twin import Twin  # noqa: E402
from sim_iocs.truth import default_start  # noqa: E402

BUDGETS = ((5_000, 2_000), (5_000, 5_000), (50_000, 5_000), (50_000, 50_000), (500_000, 500_000),
           (5_000_000, 5_000_000))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--fraction", type=float, default=0.05)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--pool", type=int, default=400)
    p.add_argument("--rays", type=int, default=4000, help="model rays per candidate's Jacobian (two halves)")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--result", default="design_ceiling", help="the result's name under benchmarks/results/")
    p.add_argument("--budgets", nargs="+", default=[f"{n}:{m}" for n, m in BUDGETS],
                   help="photons:model_rays a frame, each (default: all of BUDGETS)")
    a = p.parse_args()
    a.budgets = [tuple(int(v) for v in b.split(":")) for b in a.budgets]
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_design import Beamline, find_beam
    rows = []
    for seed in a.seeds:
        t0 = time.perf_counter()
        truth = np.random.default_rng([seed, 17]).uniform(-a.fraction, a.fraction, len(T))
        beam = find_beam(Beamline(truth, {}, 5000, seed), default_start())
        acc = acceptance(Twin(TorchEngine()), beam.configuration, open_slits=False)
        opts = DesignOptions(seed=seed)
        cfg, screen = candidate_settings(beam.configuration[None], a.pool, np.random.default_rng([seed, 5]),
                                         acceptance=acc, options=opts)
        engine = TorchEngine(options={"common_rays": False})
        k = a.frames - beam.frames
        truth_prior = prior_precision(len(T), a.fraction / np.sqrt(3.0))  # the uniform draw's σ
        for n, m in a.budgets:
            unit = frame_information(engine, cfg, truth, photons=n, model_rays=m, rays=a.rays, screen=screen,
                                     seed=seed)
            judge = frame_information(engine, cfg, truth, photons=n, model_rays=m, rays=a.rays, screen=screen,
                                      seed=seed + 1_000_003, psd=False)
            bright = unit.intensity >= opts.floor
            ch = select(unit.fisher, prior_precision(len(T)), k, allowed=bright)
            judged = positive_part(judge.fisher[ch.indices].sum(0))
            sig = predicted_sigma(prior_precision(len(T)) + judged)
            best = select(unit.fisher, truth_prior, k, criterion="A", allowed=bright)
            rows.append({"seed": seed, "photons": n, "model_rays": m, "frames_designed": len(ch.indices),
                         "search_frames": beam.frames, "determined": classes(sig).count("determined"),
                         "undetermined": classes(sig).count("undetermined"),
                         "determined_as_chosen": classes(predicted_sigma(ch.precision)).count("determined"),
                         "rmse_bound_d": least_rmse(judged, a.fraction),
                         "rmse_bound_a": least_rmse(positive_part(judge.fisher[best.indices].sum(0)), a.fraction)})
            print(f"seed {seed}: N={n:>9,} K={m:>9,}: {rows[-1]['determined']:2d} determined, "
                  f"{rows[-1]['undetermined']:2d} undetermined of 34 with {len(ch.indices)} designed frames "
                  f"(+{beam.frames} search; {rows[-1]['determined_as_chosen']} judged on the rays that chose "
                  f"them); least RMSE / truth RMS {rows[-1]['rmse_bound_d']:.2f} (D), "
                  f"{rows[-1]['rmse_bound_a']:.2f} (A)", flush=True)
        print(f"seed {seed}: {time.perf_counter() - t0:.0f} s", flush=True)
    if a.out is None:  # the rows' record beside the result
        from results import raw_path
        a.out = raw_path(f"{a.result}.json")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"machine": machine(), "args": {k: v for k, v in vars(a).items() if k != "out"},
                                 "rows": rows}, indent=1, default=str))
    write(rows, a)


def least_rmse(fisher: np.ndarray, fraction: float) -> float:
    """The least RMSE / truth RMS an estimator can expect from frames of information ``fisher``.

    The linear-Gaussian posterior whose prior is the hidden offsets' own spread (uniform within
    ±``fraction``, normalized): it knows more than any calibration is told.
    """
    spread = fraction / np.sqrt(3.0)
    cov = np.linalg.inv(prior_precision(len(fisher), spread) + fisher)
    return float(np.sqrt(np.trace(cov) / len(fisher)) / spread)


def write(rows: list, a) -> None:
    """The result ``design_ceiling``: the offsets determined per budget (rows) and draw (columns)."""
    from render import section
    from results import Table, write_result
    seeds = list(dict.fromkeys(r["seed"] for r in rows))
    by = {(r["photons"], r["model_rays"], r["seed"]): r for r in rows}
    table = Table(f"Offsets determined, of {len(T)}:",
                  ["photons N / model rays K a frame", *(f"seed {s}" for s in seeds)],
                  [[f"{n:,} / {m:,}", *(by[n, m, s]["determined"] for s in seeds)] for n, m in a.budgets],
                  align=["l"] + ["r"] * len(seeds))
    least = Table("The least RMSE / truth RMS an estimator can expect from the batch (the linear-Gaussian posterior "
                  "under the truth's own spread): the D-optimal batch / the A-optimal one:",
                  ["photons N / model rays K a frame", *(f"seed {s}" for s in seeds)],
                  [[f"{n:,} / {m:,}", *(f"{by[n, m, s]['rmse_bound_d']:.2f} / {by[n, m, s]['rmse_bound_a']:.2f}"
                                        for s in seeds)] for n, m in a.budgets],
                  align=["l"] + ["r"] * len(seeds))
    frames = ", ".join(f"{by[a.budgets[0][0], a.budgets[0][1], s]['frames_designed']} after "
                       f"{by[a.budgets[0][0], a.budgets[0][1], s]['search_frames']}" for s in seeds)
    result = write_result(
        a.result, title="The designed measurement: the Fisher ceiling", tables=[table, least], data=[str(a.out)],
        notes=[f"{a.rays:,} rays a candidate, two halves; frames designed after those of the beam search, per seed: "
               f"{frames}.",
               "Determined as judged on the rays that chose the batch (optimistic), per budget in the table's order: "
               + "; ".join(
                   f"seed {s}: {', '.join(str(by[n, m, s]['determined_as_chosen']) for n, m in a.budgets)}"
                   for s in seeds) + "."],
        summary=f"How many offsets a designed measurement can determine, before any fit: for hidden offsets drawn "
                f"as the demo draws them (±{100 * a.fraction:g} %), the beam found by the real search, {a.pool} "
                "candidate settings drawn as the design draws them (motors, slits, the chamber's stage), the greedy "
                f"D-optimal batch filling {a.frames} frames, judged on rays other than those that chose it; the "
                "count of offsets determined (σ below a tenth of the prior's) for each budget of photons N and model "
                "rays K a frame.")
    print(section(result))


if __name__ == "__main__":
    main()
