"""Surrogate pipeline benchmark: generator, training and inference throughput on this machine.

Usage::

    python benchmarks/bench_surrogate.py [--quick] [--rays 1000] [--draws 1536]

Writes ``benchmarks/results/surrogate_pipeline.json`` (``surrogate_inference.json`` with
``--inference-only``) and prints the page's section:

* generator: good samples (>= 10 rays) per CPU-second, with the low-ray
  pre-screen (the default scheme) and without it (every uniform draw traced
  in full, the paper's scheme), measured in-process on the same draws;
* training: samples per second of the paper's recipe (batch 32) and with
  larger batches, for the shipped width;
* inference: surrogate evaluations per second, batched, CPU (and CUDA when present).

CPU-seconds (``time.process_time``) are reported next to wall time because
the machine is shared: wall time depends on the other jobs, CPU time much less.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402


def bench_generator(n_rays: int, n_draws: int, screen_rays: int, keep_fraction: float) -> list[dict]:
    from bluesky_offsets.surrogate import dataset
    from bluesky_offsets.surrogate.dataset import DrawScheme, GenerationSettings
    from bluesky_offsets.physics.twin import Twin

    twin = Twin(scheduler="inline", n_rays=n_rays)
    rows = []
    for label, scheme in (("pre-screen", DrawScheme(screen_rays=screen_rays, keep_fraction=keep_fraction)),
                          ("no screen (every draw traced)", DrawScheme(screen_rays=0))):
        s = GenerationSettings(n_rays=n_rays, seed=12345, block_size=n_draws, scheme=scheme)
        with dataset.openmp_threads(1):
            t0, c0 = time.perf_counter(), time.process_time()
            res = dataset.generate_block(twin.engine, s, 0)
            cpu, wall = time.process_time() - c0, time.perf_counter() - t0
        good = int((res["n_hits"] >= dataset.GOOD_MIN_RAYS).sum())
        rows.append({"scheme": label, "draws": n_draws, "traced_full": len(res["index"]),
                     "nonempty": int((res["n_hits"] > 0).sum()), "good": good, "cpu_s": cpu, "wall_s": wall,
                     "good_per_cpu_s": good / cpu, "ms_per_draw_cpu": 1e3 * cpu / n_draws})
    return rows


def bench_training(width: int, batches=(32, 256), seconds: float = 8.0, threads: int = 1) -> list[dict]:
    from bluesky_offsets.surrogate.network import Architecture, SurrogateNet
    torch.set_num_threads(threads)
    net = SurrogateNet(Architecture(width=width))
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    X, Y = torch.rand(8192, 34), torch.rand(8192, 100)
    out = []
    for bs in batches:
        n, c0, t0 = 0, time.process_time(), time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            i = torch.randint(0, 8192, (bs,))
            loss = torch.nn.functional.mse_loss(net(X[i]), Y[i])
            opt.zero_grad()
            loss.backward()
            opt.step()
            n += bs
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        out.append({"width": width, "batch": bs, "threads": threads, "samples_per_s": n / wall,
                    "samples_per_cpu_s": n / cpu})
    return out


def bench_inference(model, device: str, n: int, seconds: float = 5.0) -> dict:
    """Rows (one configuration each) per second; an evaluation of the finder is 16 rows."""
    x = torch.rand(n, model.arch.n_inputs, device=device)
    model.to(device)
    with torch.no_grad():
        model.predict(x[:1000], normalized=True)
        if device == "cuda":
            torch.cuda.synchronize()
        k, t0, c0 = 0, time.perf_counter(), time.process_time()
        while time.perf_counter() - t0 < seconds:
            model.predict(x, normalized=True)  # its default chunks (network.CPU_CHUNK_ROWS on a CPU)
            k += 1
        if device == "cuda":
            torch.cuda.synchronize()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    model.to("cpu")
    return {"device": device, "batch": n, "evals_per_s": k * n / wall, "evals_per_cpu_s": k * n / cpu,
            "threads": torch.get_num_threads()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke)")
    ap.add_argument("--rays", type=int, default=1000, help="full-trace rays (default 1000, the shipped model's)")
    ap.add_argument("--screen-rays", type=int, default=300)
    ap.add_argument("--keep-fraction", type=float, default=0.02)
    ap.add_argument("--draws", type=int, default=1536, help="uniform draws per generator measurement")
    ap.add_argument("--checkpoint", default=None, nargs="+",
                    help="surrogate(s) for the inference benchmark (default: shipped)")
    ap.add_argument("--inference-only", action="store_true", help="only the inference table (1 thread)")
    args = ap.parse_args()
    draws = 256 if args.quick else args.draws
    secs = 2.0 if args.quick else 8.0

    from bluesky_offsets.surrogate import network as surrogate
    from render import section
    from results import Table, write_result
    models = [surrogate.load(c) for c in (args.checkpoint or [None])]
    if args.inference_only:
        torch.set_num_threads(1)
        rows = []
        for c, m in zip(args.checkpoint or ["shipped"], models):
            for n in (1_000, 100_000):
                r = bench_inference(m, "cpu", n, seconds=secs / 2)
                a = m.arch
                rows.append([os.path.basename(c), a.decoder, a.members, f"{a.width} x {a.n_layers}", a.activation,
                             a.n_inputs, n, f"{r['evals_per_s']:.3g}", f"{r['evals_per_s'] / 16:.3g}"])
        table = Table("One torch thread:", ["checkpoint", "decoder", "members", "width x layers", "activation",
                                            "inputs", "batch", "rows/s", "evaluations (16 rows)/s"], rows,
                      align=["l", "l", "r", "l", "l", "r", "r", "r", "r"])
        result = write_result("surrogate_inference", title="Surrogate inference (issue 18)", tables=[table],
                              summary="`Surrogate.predict` (no grad) rows per second on one torch thread, in "
                                      "`predict`'s default CPU chunks; an evaluation (the finder's) is 16 rows. "
                                      "Issue 18's goal: ≥ 2e4 evaluations per second per core.")
        print(section(result))
        return
    model = models[0]
    width = model.arch.width
    gen = bench_generator(args.rays, draws, args.screen_rays, args.keep_fraction)
    tr = bench_training(width, seconds=secs) + bench_training(width, batches=(256,), seconds=secs, threads=2)
    inf = []
    for threads in sorted({1, os.cpu_count() or 1}):
        torch.set_num_threads(threads)
        inf += [bench_inference(model, "cpu", n, seconds=secs / 2) for n in (1_000, 100_000)]
    if torch.cuda.is_available():
        inf.append(bench_inference(model, "cuda", 1_000_000, seconds=secs / 2))

    tables = [
        Table(f"Generator, full traces at {args.rays:,} rays ({draws:,} uniform draws, seed 12345; pre-screen "
              f"{args.screen_rays} rays, keep fraction {args.keep_fraction}):",
              ["scheme", "draws", "traced in full", "non-empty", "good (>= 10 rays)", "CPU s", "ms/draw",
               "good samples / CPU-s"],
              [[r["scheme"], r["draws"], r["traced_full"], r["nonempty"], r["good"], f"{r['cpu_s']:.1f}",
                f"{r['ms_per_draw_cpu']:.1f}", f"{r['good_per_cpu_s']:.2f}"] for r in gen],
              align=["l"] + ["r"] * 7),
        Table(f"Training throughput (width {width}, 7 layers, Adam, MSE, synthetic tensors):",
              ["batch", "torch threads", "samples/s (wall)", "samples / CPU-s"],
              [[r["batch"], r["threads"], f"{r['samples_per_s']:.0f}", f"{r['samples_per_cpu_s']:.0f}"] for r in tr],
              align=["r"] * 4),
        Table("Inference (the first checkpoint, `Surrogate.predict`, no grad):",
              ["device", "batch", "torch threads", "evaluations/s (wall)", "evaluations / CPU-s"],
              [[r["device"], r["batch"], r["threads"], f"{r['evals_per_s']:.3g}", f"{r['evals_per_cpu_s']:.3g}"]
               for r in inf], align=["l"] + ["r"] * 4)]
    result = write_result(
        "surrogate_pipeline", title="Surrogate pipeline: generator and training (issue 4)", tables=tables,
        summary="The generator's good samples (≥ 10 rays at the full ray count) per CPU-second with RAYX, with the "
                "low-ray pre-screen (the default scheme) and without (every uniform draw traced in full, the "
                "paper's scheme), on the same draws, in-process, one OpenMP thread; the training throughput of the "
                "shipped width; the inference throughput. CPU-seconds are reported beside wall time because on a "
                "shared machine wall time depends on the other jobs, CPU time much less.")
    print(section(result))


if __name__ == "__main__":
    main()
