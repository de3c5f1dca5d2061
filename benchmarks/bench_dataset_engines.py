"""Dataset throughput: good samples per CPU-second, RAYX against the torch engine.

Usage::

    python benchmarks/bench_dataset_engines.py [--rays 10000] [--draws 2048] [--dask-samples 2000]

Both engines generate blocks of the same uniform draws (same base seed) with the same
pre-screen, in this process on one thread; the torch engine also with other screens, with
the chamber drawn, and through Dask (a LocalCluster of one-thread workers, the path of
``bluesky-offsets dataset generate --engine torch``), where the workers' CPU-seconds count.
A "good" sample has >= 10 rays on the screen at the full ray count (the paper's threshold).
Writes ``benchmarks/results/dataset_engines.json`` and prints the page's section.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402


def in_process(engine: str, n_rays: int, n_draws: int, block: int, scheme, chamber: bool = False) -> dict:
    from bluesky_offsets.surrogate import dataset
    from bluesky_offsets.surrogate.dataset import GenerationSettings
    from bluesky_offsets.physics.twin import make_engine

    eng = make_engine(engine)
    s = GenerationSettings(n_rays=n_rays, seed=12345, block_size=block, scheme=scheme, engine=engine,
                           chamber=chamber)
    torch.set_num_threads(1)
    good = traced = nonempty = 0
    with dataset.openmp_threads(1):
        t0, c0 = time.perf_counter(), time.process_time()
        for b in range(max(1, n_draws // block)):
            res = dataset.generate_block(eng, s, b)
            good += int((res["n_hits"] >= dataset.GOOD_MIN_RAYS).sum())
            nonempty += int((res["n_hits"] > 0).sum())
            traced += len(res["index"])
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    return {"engine": engine, "chamber": chamber, "screen": scheme.screen_rays, "keep": scheme.keep_fraction,
            "draws": max(1, n_draws // block) * block, "traced": traced, "nonempty": nonempty, "good": good,
            "cpu_s": cpu, "wall_s": wall, "good_per_cpu_s": good / cpu}


def through_dask(n_rays: int, n_samples: int, workers: int, scheme, chamber: bool) -> dict:
    from bluesky_offsets.surrogate import dataset
    from bluesky_offsets.surrogate.dataset import GenerationSettings

    s = GenerationSettings(n_rays=n_rays, seed=777, block_size=256, scheme=scheme, engine="torch", chamber=chamber)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        st = dataset.generate(os.path.join(tmp, "ds"), n_samples, s, n_workers=workers, progress=False,
                              rayx_check=0)
        wall = time.perf_counter() - t0
    return {"workers": workers, "samples": st["n_samples"], "draws": st["n_draws"], "good": st["n_good"],
            "worker_cpu_s": st["cpu_s"], "wall_s": wall, "good_per_cpu_s": st["n_good"] / st["cpu_s"],
            "good_per_wall_s": st["n_good"] / wall}


def main() -> None:
    from bluesky_offsets.surrogate.dataset import DrawScheme

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rays", type=int, default=10_000)
    ap.add_argument("--draws", type=int, default=2048, help="uniform draws per in-process row")
    ap.add_argument("--rayx-draws", type=int, default=1024)
    ap.add_argument("--dask-samples", type=int, default=2000)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = ap.parse_args()
    default = DrawScheme()
    rows = [in_process("rayx", args.rays, args.rayx_draws, args.rayx_draws, default)]
    for scheme, chamber in ((default, False), (default, True), (DrawScheme(screen_rays=100), True),
                            (DrawScheme(screen_rays=100, keep_fraction=0.005), True)):
        rows.append(in_process("torch", args.rays, args.draws, 256, scheme, chamber))
    dask = through_dask(args.rays, args.dask_samples, args.workers, default, True)
    ref = rows[0]["good_per_cpu_s"]
    from render import section
    from results import Table, write_result
    t1 = Table("In-process rows, one thread:",
               ["engine", "chamber drawn", "screen rays", "keep fraction", "draws", "traced in full", "non-empty",
                "good", "CPU s", "good / CPU-s", "vs RAYX"],
               [[r["engine"], "yes" if r["chamber"] else "no", r["screen"], f"{r['keep']:g}", r["draws"], r["traced"],
                 r["nonempty"], r["good"], f"{r['cpu_s']:.1f}", f"{r['good_per_cpu_s']:.1f}",
                 f"{r['good_per_cpu_s'] / ref:.1f}×"] for r in rows], align=["l", "l"] + ["r"] * 9)
    t2 = Table("Through Dask (`generate`, chamber drawn, default screen):",
               ["workers", "samples", "good", "draws", "wall s", "worker CPU-s", "good / CPU-s", "vs RAYX",
                "good / wall-s"],
               [[f"{dask['workers']} (one thread each)", dask["samples"], dask["good"], dask["draws"],
                 f"{dask['wall_s']:.1f}", f"{dask['worker_cpu_s']:.1f}", f"**{dask['good_per_cpu_s']:.1f}**",
                 f"{dask['good_per_cpu_s'] / ref:.1f}×", f"{dask['good_per_wall_s']:.1f}"]], align=["r"] * 9)
    result = write_result(
        "dataset_engines", title="Dataset throughput, RAYX and the torch engine", tables=[t1, t2],
        summary=f"Good samples (≥ 10 rays at the full ray count) per CPU-second, RAYX against the torch engine: the "
                f"same uniform draws with the same pre-screen, in this process on one thread, {args.rays:,} rays per "
                "full trace; the torch engine also with other screens, with the chamber drawn, and through Dask "
                "(`generate`, the workers' CPU-seconds counted; the first torch row includes the process's "
                "warm-up). Issue 18's goal: ≥ 50× RAYX's good samples per CPU-second.")
    print(section(result))


if __name__ == "__main__":
    main()
