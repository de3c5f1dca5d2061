"""Twin benchmark: throughput, overhead over bare RAYX, and the repeat-noise floor.

Usage::

    python benchmarks/bench_twin.py [--quick] [--no-noise] [--write-noise-floor]

Writes its result to ``benchmarks/results/twin.json`` (``benchmarks/results.py``) and prints
the page's section; with ``--write-noise-floor`` it also writes
``bluesky_offsets/data/noise_floor.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np


def bench_overhead(n_rays: int, repeats: int) -> dict:
    """Our engine vs. a bare RAYX import+trace of the same RML, single thread, same seed."""
    import rayx

    from bluesky_offsets.physics.metrixs import build_beamline
    from bluesky_offsets.physics.parameters import METRIXS
    from bluesky_offsets.physics.twin import RayxEngine, TraceRequest
    from bluesky_offsets.physics.rayx_calls import fix_seed

    engine = RayxEngine()
    values = METRIXS.reference
    path = Path("/tmp/bench_twin_bare.rml")
    build_beamline(values, n_rays=n_rays).write(path)
    ours, bare_trace, bare_import_trace = [], [], []
    for i in range(repeats):
        fix_seed(i)
        t = time.perf_counter()
        bl = rayx.import_beamline(str(path))
        t1 = time.perf_counter()
        bl.trace()
        t2 = time.perf_counter()
        bare_trace.append(t2 - t1)
        bare_import_trace.append(t2 - t)
        t = time.perf_counter()
        engine.trace(TraceRequest(values, {}, seed=i), n_rays)
        ours.append(time.perf_counter() - t)
    med = statistics.median
    return {"n_rays": n_rays, "ours_s": med(ours), "bare_trace_s": med(bare_trace),
            "bare_import_trace_s": med(bare_import_trace),
            "overhead_vs_trace": med(ours) / med(bare_trace) - 1,
            "overhead_vs_import_trace": med(ours) / med(bare_import_trace) - 1}


def bench_throughput(n_rays: int, n_workers: int, n_samples: int) -> dict:
    from bluesky_offsets.physics.parameters import METRIXS
    from bluesky_offsets.physics.twin import Twin

    rng = np.random.default_rng(1)
    # the nominal beam with small random misalignments: every sample traces the full chain
    values = np.tile(METRIXS.reference, (n_samples, 1))
    values[:, METRIXS.index("E2.rotationXerror")] = rng.uniform(-0.3, 0.3, n_samples)
    with Twin(n_rays=n_rays, n_workers=n_workers) as twin:
        twin.trace_batch(values[: 2 * n_workers], progress=False)  # warm up the workers
        t = time.perf_counter()
        res = twin.trace_batch(values, progress=False)
        dt = time.perf_counter() - t
    assert res.ok.all()
    return {"n_rays": n_rays, "n_workers": n_workers, "n_samples": n_samples, "seconds": dt,
            "samples_per_s": n_samples / dt}


SUMMARY = ("The digital twin's cost over a bare RAYX trace, its throughput on Dask, and its repeat-noise floor. "
           "Overhead: the same RML and seed traced by our engine (RML generation with the misaligned world "
           "frames, import, footprint selection, histograms) against RAYX's bare trace, one thread "
           "(OMP_NUM_THREADS=1, RAYX single-threaded per worker); the goal is below 10 %. The noise floor is the "
           "MSE between two traces of the same configuration: \"box\" configurations are uniform draws from the "
           "sampling box with ≥ 10 rays on the screen at 500 rays (their selection varies between runs), the "
           "nominal rows are seeded and repeat exactly.")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer samples")
    ap.add_argument("--no-noise", action="store_true", help="skip the noise-floor measurement")
    ap.add_argument("--write-noise-floor", action="store_true",
                    help="store the measured floor in bluesky_offsets/data/noise_floor.json")
    ap.add_argument("--noise-configs", type=int, default=24)
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from render import section
    from results import Table, write_result

    rows = []
    for n_rays, rep in ((10_000, 9 if args.quick else 21), (100_000, 3 if args.quick else 7)):
        r = bench_overhead(n_rays, rep)
        print(json.dumps(r), file=sys.stderr)
        rows.append([f"{n_rays:,}", f"{r['ours_s']:.4f}", f"{r['bare_trace_s']:.4f}", f"{r['bare_import_trace_s']:.4f}",
                     f"{100 * r['overhead_vs_trace']:+.1f} %", f"{100 * r['overhead_vs_import_trace']:+.1f} %"])
    tables = [Table("Per-sample overhead over a bare RAYX trace (same RML, same seed, 1 thread):",
                    ["rays", "ours [s]", "bare trace [s]", "bare import+trace [s]", "overhead vs trace",
                     "vs import+trace"], rows, align=["r"] * 6)]

    rows = []
    for n_rays, n in ((10_000, 40 if args.quick else 120), (100_000, 8 if args.quick else 24)):
        for w in (1, 2):
            r = bench_throughput(n_rays, w, n)
            print(json.dumps(r), file=sys.stderr)
            rows.append([f"{n_rays:,}", w, n, f"{r['seconds']:.1f}", f"{r['samples_per_s']:.2f}"])
    tables.append(Table("Throughput on Dask (LocalCluster, 1 thread per worker):",
                        ["rays", "workers", "samples", "seconds", "samples/s"], rows, align=["r"] * 5))

    notes = []
    if not args.no_noise:
        from bluesky_offsets.physics.noise import good_configurations, measure_noise_floor
        from bluesky_offsets.physics.parameters import METRIXS
        from bluesky_offsets.physics.twin import Twin
        n_cfg = 8 if args.quick else args.noise_configs
        floor = {"description": "MSE between two independent twin traces of the same configuration "
                                "(x and y histograms concatenated, fraction of source rays). "
                                "'box': configurations drawn uniformly from the sampling box with >= 10 rays "
                                "on the screen at 500 rays; 'nominal': the reference RML.",
                 "engine": None, "measured": time.strftime("%Y-%m-%d")}
        rows = []
        with Twin(n_workers=2) as twin:
            floor["engine"] = twin.engine.version
            cfgs = good_configurations(twin, n_cfg, np.random.default_rng(2024))
            for n_rays in (10_000, 100_000):
                box = measure_noise_floor(twin, cfgs, n_rays, seed=11)
                nom = measure_noise_floor(twin, METRIXS.reference[None, :], n_rays, seed=12)
                floor[str(n_rays)] = {"box": {k: v for k, v in box.items() if k != "per_configuration"},
                                      "nominal_repeat_mse": nom["repeat_mse_mean"]}
                rows.append([f"{n_rays:,}", f"{box['repeat_mse_mean']:.3e}", f"{box['repeat_mse_median']:.3e}",
                             f"{box['expected_mse_mean']:.3e}", f"{nom['repeat_mse_mean']:.3e}"])
        tables.append(Table(f"Repeat-noise floor (MSE between two traces, {n_cfg} non-empty box configurations "
                            "+ nominal):", ["rays", "box: mean MSE", "box: median", "multinomial expectation",
                                            "nominal MSE"], rows, align=["r"] * 5))
        if args.write_noise_floor:
            out = Path(__file__).resolve().parents[1] / "bluesky_offsets" / "data" / "noise_floor.json"
            out.write_text(json.dumps(floor, indent=2) + "\n")
            print(f"wrote {out}", file=sys.stderr)
            notes.append("The noise floor is stored in `bluesky_offsets/data/noise_floor.json` "
                         "(`--write-noise-floor`).")
    result = write_result("twin", title="Twin (RAYX)", summary=SUMMARY, tables=tables, notes=notes)
    print(section(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
