"""The torch engine against RAYX: trace throughput and feature Jacobians.

    python benchmarks/bench_torch_engine.py [--quick] [--device cuda] [--json out.json]

Measures, on this machine:

* trace time per source ray, 1e4 and 1e5 rays x 1 and 16 configurations, 1 and 2 threads:
  RAYX as the twin calls it (RML written and imported, footprint extracted) and RAYX's bare
  ``trace()``; the torch engine (fast and RAYX sampling, float64 and float32);
* the Jacobian of the five beam features for 16 configurations x (34 parameters + the
  chamber's z) at 1e4 rays: torch reverse mode against one-sided finite differences through
  RAYX (35 extra traces per configuration, common seed), as the fits do today;
* how many rays a torch feature Jacobian needs to be accurate to 1 % (relative error of the
  entries above noise against a 2e5-ray reference, median over entries and configurations);
* the per-ray Jacobian every fit step takes (:meth:`TorchEngine.ray_jacobian`, then its
  camera histograms' Jacobian) at a diagnosis's candidate-fit size: 14 configurations x
  3000 rays, 34 parameters + the chamber's z, one thread, at the reference and at the 2021
  settings (``--only ray-jacobian``).

Results: ``benchmarks/results/torch_engine.json`` (``torch_engine_cuda.json`` on a GPU) and
``ray_jacobian.json``, with machine, command, date and commit; ``--json`` keeps every number.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine  # noqa: E402

from bluesky_offsets.physics.parameters import METRIXS  # noqa: E402
from bluesky_offsets.physics.engine import TorchEngine  # noqa: E402
from bluesky_offsets.physics.twin import RayxEngine, TraceRequest  # noqa: E402
from bluesky_offsets.physics.rayx_calls import fix_seed  # noqa: E402


def configurations(n, seed=0):
    rng = np.random.default_rng(seed)
    vals = METRIXS.reference + 0.01 * METRIXS.span * rng.uniform(-1, 1, (n, 34))
    vals[:, [METRIXS.index("E1.rotationZerror"), METRIXS.index("E2.rotationZerror")]] = 0.0
    return vals


def best(fn, repeat):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def bench_trace(sizes, threads, device, repeat):
    import rayx
    rows = []
    for nthreads in threads:
        torch.set_num_threads(nthreads)
        for n_rays, n_cfg in sizes:
            vals = configurations(n_cfg)
            reqs = [TraceRequest(v, {}, 1) for v in vals]
            rx = RayxEngine()
            t_rx = best(lambda: [rx.trace(r, n_rays) for r in reqs], repeat)
            path = Path("/tmp/bench_torch_engine.rml")
            rx.build(reqs[0], n_rays).write(path)
            bl = rayx.import_beamline(str(path))
            fix_seed(1)
            t_bare = best(lambda: [bl.trace() for _ in reqs], repeat)
            row = {"threads": nthreads, "rays": n_rays, "configs": n_cfg,
                   "rayx_engine_us_per_ray": 1e6 * t_rx / (n_rays * n_cfg),
                   "rayx_bare_us_per_ray": 1e6 * t_bare / (n_rays * n_cfg)}
            for sampling in ("fast", "rayx"):
                for dtype in ("float64", "float32"):
                    if sampling == "rayx" and dtype == "float32":
                        continue
                    eng = TorchEngine(options={"sampling": sampling, "dtype": dtype, "device": device})
                    eng.trace_many(reqs[:1], 1000)  # warm up
                    t = best(lambda: eng.trace_many(reqs, n_rays), repeat)
                    row[f"torch_{sampling}_{dtype}_us_per_ray"] = 1e6 * t / (n_rays * n_cfg)
            row["speedup_fast_float64_vs_rayx_engine"] = row["rayx_engine_us_per_ray"] / row["torch_fast_float64_us_per_ray"]
            row["speedup_fast_float64_vs_rayx_bare"] = row["rayx_bare_us_per_ray"] / row["torch_fast_float64_us_per_ray"]
            print(json.dumps(row), flush=True)
            rows.append(row)
    return rows


def bench_jacobian(n_cfg, n_rays, device, fd_configs):
    torch.set_num_threads(1)
    vals = configurations(n_cfg, 1)
    eng = TorchEngine(options={"device": device})
    effects = {"chamber_z": {"z": 5.0}}
    eng.jacobian("features", vals[:1], effects, n_rays=1000, seed=1)
    t = time.perf_counter()
    eng.jacobian("features", vals, effects, n_rays=n_rays, seed=1)
    t_torch = time.perf_counter() - t
    # finite differences through RAYX, one-sided, common seed: 36 traces per configuration
    rx = RayxEngine()
    t = time.perf_counter()
    for v in vals[:fd_configs]:
        for j in range(36):
            vv = v.copy()
            if j < 34:
                vv[j] += 1e-3 * METRIXS.span[j]
            ov = {"ImagePlane": {"translationZerror": 5.0 + (1e-2 if j == 34 else 0.0)}}
            rx.trace(TraceRequest(vv, ov, 1), n_rays, keep_rays=True)
    t_fd = (time.perf_counter() - t) * n_cfg / fd_configs
    return {"configs": n_cfg, "rays": n_rays, "parameters": 35, "threads": 1, "torch_reverse_s": t_torch,
            "rayx_finite_differences_s": t_fd, "fd_measured_on_configs": fd_configs, "speedup": t_fd / t_torch}


def _rayx_fd_features(vals, n_rays, seed, effects_z=5.0):
    """Feature Jacobian through RAYX by one-sided finite differences at a common seed (the
    way the fits differentiate today): 36 traces per configuration."""
    rx = RayxEngine()

    def feats(v, z):
        r = rx.trace(TraceRequest(v, {"ImagePlane": {"translationZerror": z}}, seed), n_rays, keep_rays=True)
        x, y = r.rays[:, 0], r.rays[:, 1]
        return np.array([r.n_hits / n_rays, x.mean(), y.mean(), x.std(), y.std()])

    out = []
    for v in vals:
        f0 = feats(v, effects_z)
        cols = []
        for j in range(35):
            vv, z = v.copy(), effects_z
            h = 1e-3 * METRIXS.span[j] if j < 34 else 1e-2
            if j < 34:
                vv[j] += h
            else:
                z += h
            cols.append((feats(vv, z) - f0) / h)
        out.append(np.stack(cols, 1))
    return np.stack(out)


def _errors(jac, ref):
    """Relative Frobenius error per configuration, and the median relative error of the
    entries above 5 % of their row's largest (the entries that carry information)."""
    frob = np.linalg.norm(jac - ref, axis=(1, 2)) / np.linalg.norm(ref, axis=(1, 2))
    big = np.abs(ref) > 0.05 * np.abs(ref).max(axis=2, keepdims=True)
    return {"frobenius_relative_error": float(np.median(frob)),
            "median_entry_relative_error": float(np.median((np.abs(jac - ref) / np.abs(ref))[big]))}


def bench_rays_for_one_percent(n_cfg, device, ladder, reference_rays, fd_rays=10_000):
    torch.set_num_threads(2)
    vals = configurations(n_cfg, 2)
    eng = TorchEngine(options={"device": device})
    effects = {"chamber_z": {"z": 5.0}}
    _, ref, _ = eng.jacobian("features", vals, effects, n_rays=reference_rays, seed=777)
    ref = ref.cpu().numpy()
    out = []
    for n in ladder:
        _, jac, _ = eng.jacobian("features", vals, effects, n_rays=n, seed=11)
        out.append({"rays": n, **_errors(jac.cpu().numpy(), ref)})
        print(json.dumps(out[-1]), flush=True)
    fd = _rayx_fd_features(vals[:2], fd_rays, 5)
    rayx_fd = {"rays": fd_rays, **_errors(fd, ref[:2])}
    print(json.dumps({"rayx_finite_differences": rayx_fd}), flush=True)
    return {"reference_rays": reference_rays, "configs": n_cfg, "torch_reverse": out,
            "rayx_finite_differences": rayx_fd}


def float32_accuracy(n_rays=20_000):
    """Screen positions of the same rays in float32 against float64 (fast sampling)."""
    vals = configurations(16, 3)
    reqs = [TraceRequest(v, {}, 1) for v in vals]
    a = TorchEngine().trace_many(reqs, n_rays, keep_rays=True)
    b = TorchEngine(options={"dtype": "float32"}).trace_many(reqs, n_rays, keep_rays=True)
    hits = [abs(x.n_hits - y.n_hits) for x, y in zip(a, b)]
    cen = [float(np.abs(x.rays.mean(0) - y.rays.mean(0)).max()) for x, y in zip(a, b)]
    wid = [float(np.abs(x.rays.std(0) / y.rays.std(0) - 1).max()) for x, y in zip(a, b)]
    return {"rays": n_rays, "configs": 16, "max_hit_count_difference": int(max(hits)),
            "max_centroid_difference_mm": max(cen), "max_relative_width_difference": max(wid)}


def device_agreement(device, n_rays=100_000):
    """The same RAYX-stream rays traced on ``device`` and on the CPU (float64)."""
    vals = configurations(16, 4)
    out = {}
    beams = {}
    for dev in ("cpu", device):
        eng = TorchEngine(options={"device": dev, "sampling": "rayx"})
        with torch.no_grad():
            beams[dev] = eng.beam(vals, n_rays=n_rays, seed=3)
    a, b = beams["cpu"], beams[device]
    alive_a, alive_b = a.alive.cpu(), b.alive.cpu()
    both = alive_a & alive_b
    out["survivors_differ"] = int((alive_a ^ alive_b).sum())
    out["max_screen_difference_mm"] = float(max((a.x.cpu() - b.x.cpu())[both].abs().max(),
                                                (a.y.cpu() - b.y.cpu())[both].abs().max()))
    return out


def bench_device(device, repeat=3):
    """Throughput and Jacobian time on an accelerator (no RAYX there)."""
    rows = []
    for n_rays, n_cfg in [(10_000, 16), (100_000, 16), (1_000_000, 16)]:
        vals = configurations(n_cfg)
        reqs = [TraceRequest(v, {}, 1) for v in vals]
        for dtype in ("float64", "float32"):
            eng = TorchEngine(options={"device": device, "dtype": dtype, "max_batch": 1 << 23})
            eng.trace_many(reqs, 1000)
            torch.cuda.synchronize()
            t = best(lambda: (eng.trace_many(reqs, n_rays), torch.cuda.synchronize()), repeat)
            rows.append({"rays": n_rays, "configs": n_cfg, "dtype": dtype, "us_per_ray": 1e6 * t / (n_rays * n_cfg),
                         "s": t})
            print(json.dumps(rows[-1]), flush=True)
    jac = []
    for n_rays in (10_000, 100_000):
        eng = TorchEngine(options={"device": device, "max_batch": 1 << 22})
        vals = configurations(16, 1)
        eng.jacobian("features", vals[:2], {"chamber_z": {"z": 5.0}}, n_rays=1000, seed=1)
        torch.cuda.synchronize()
        t = time.perf_counter()
        eng.jacobian("features", vals, {"chamber_z": {"z": 5.0}}, n_rays=n_rays, seed=1)
        torch.cuda.synchronize()
        jac.append({"rays": n_rays, "configs": 16, "parameters": 35, "s": time.perf_counter() - t})
        print(json.dumps(jac[-1]), flush=True)
    return {"trace": rows, "jacobian": jac}


def bench_ray_jacobian(n_cfg=14, n_rays=3000, repeat=5):
    """Seconds per :meth:`TorchEngine.ray_jacobian` and per camera-histogram Jacobian of it, at
    two sets of configurations: the reference ±1 % of each range (most rays reach the screen)
    and the 2021 settings ±1 % (the slits pass about a seventh: what the demo measures)."""
    import resource
    from bluesky_offsets.physics.twin import CAMERA
    from sim_iocs.truth import default_start
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    start = np.clip(METRIXS.normalize(default_start()) + rng.uniform(-0.01, 0.01, (n_cfg, len(METRIXS))), 0, 1)
    sets = {"reference": configurations(n_cfg),
            "2021 settings": np.where(METRIXS.motorized, METRIXS.denormalize(start), METRIXS.reference)}
    eng, eff = TorchEngine(hist=CAMERA), {"chamber_z": {"z": 3.0}}
    out = []
    for label, vals in sets.items():
        rj = eng.ray_jacobian(vals, eff, n_rays=n_rays, seed=1)  # warm-up
        r0 = resource.getrusage(resource.RUSAGE_SELF)
        ray = best(lambda: eng.ray_jacobian(vals, eff, n_rays=n_rays, seed=1), repeat)
        hist = best(lambda: rj.histograms(CAMERA), repeat)
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        out.append({"configurations": f"{n_cfg}, {label} ±1 %", "rays": n_rays, "inputs": len(rj.names),
                    "threads": 1, "on_screen": float(rj.alive.double().mean()),
                    "with_derivatives": rj.rows.numel() / rj.alive.numel(),
                    "ray_jacobian_s": ray, "histogram_jacobian_s": hist,
                    "sys_share": (r1.ru_stime - r0.ru_stime) / max(r1.ru_utime - r0.ru_utime + r1.ru_stime
                                                                  - r0.ru_stime, 1e-9)})
        print(json.dumps(out[-1]), flush=True)
    return out


def _cpu_tables(result: dict) -> list:
    """The page's tables of a CPU run: trace times, the feature Jacobian, the rays it needs."""
    from results import Table
    out = []
    if "trace" in result:
        keys = ("rayx_engine_us_per_ray", "rayx_bare_us_per_ray", "torch_fast_float64_us_per_ray",
                "torch_fast_float32_us_per_ray", "torch_rayx_float64_us_per_ray")
        out.append(Table("Trace time per source ray [µs] (the configurations share their rays; best of the repeats):",
                         ["threads", "rays", "configs", "RAYX as the twin calls it", "RAYX bare `trace()`",
                          "torch fast float64", "torch fast float32", "torch RAYX stream float64",
                          "torch vs RAYX engine", "vs bare"],
                         [[r["threads"], f"{r['rays']:,}", r["configs"], *(f"{r[k]:.2f}" for k in keys),
                           f"{r['speedup_fast_float64_vs_rayx_engine']:.1f}×",
                           f"{r['speedup_fast_float64_vs_rayx_bare']:.1f}×"] for r in result["trace"]],
                         align=["r"] * 10))
    if "jacobian" in result:
        j = result["jacobian"]
        out.append(Table(f"Feature Jacobian: {j['configs']} configurations × {j['parameters']} inputs at "
                         f"{j['rays']:,} rays, one thread:", ["method", "seconds", ""],
                         [["torch, reverse mode", f"{j['torch_reverse_s']:.2f}", ""],
                          ["one-sided finite differences through RAYX (common seed)",
                           f"{j['rayx_finite_differences_s']:.1f}",
                           f"measured on {j['fd_measured_on_configs']} configurations, × "
                           f"{j['configs'] / j['fd_measured_on_configs']:g}"],
                          ["speed-up", f"{j['speedup']:.1f}×", ""]], align=["l", "r", "l"]))
    if "rays_for_jacobian" in result:
        a = result["rays_for_jacobian"]
        rows = [["torch, soft features", f"{r['rays']:,}", f"{100 * r['median_entry_relative_error']:.2f} %",
                 f"{100 * r['frobenius_relative_error']:.1f} %"] for r in a["torch_reverse"]]
        fd = a["rayx_finite_differences"]
        rows.append(["RAYX, one-sided differences, common seed (2 configurations)", f"{fd['rays']:,}",
                     f"{100 * fd['median_entry_relative_error']:.2f} %", f"{100 * fd['frobenius_relative_error']:.1f} %"])
        out.append(Table(f"How many rays a feature Jacobian needs ({a['configs']} configurations; reference: torch at "
                         f"{a['reference_rays']:,} rays, another seed):",
                         ["Jacobian", "rays", "median relative error of the entries above 5 % of their row's largest",
                          "relative error, Frobenius norm (median over configurations)"], rows,
                         align=["l", "r", "r", "r"]))
    return out


def _write(result: dict) -> None:
    """The results ``torch_engine`` (or ``torch_engine_cuda``) and ``ray_jacobian`` of this run."""
    from render import section
    from results import Table, write_result
    if result["device"] != "cpu":
        ag = result["agreement_with_cpu"]
        rows = [[f"{r['rays']:,}", r["configs"], r["dtype"], f"{r['s']:.3f}", f"{r['us_per_ray']:.4f}"]
                for r in result["trace"]]
        rows += [[f"feature Jacobian, {r['rays']:,} rays", f"{r['configs']} × {r['parameters']}", "float64",
                  f"{r['s']:.3f}", ""] for r in result["jacobian"]]
        t = Table(f"One {result['gpu']}:", ["rays", "configs", "dtype", "seconds", "µs per ray"], rows,
                  align=["r", "r", "l", "r", "r"])
        print(section(write_result(
            "torch_engine_cuda", title="Torch engine on CUDA", tables=[t],
            summary="The torch engine on a GPU: trace time for 16 configurations at 1e4–1e6 rays in float64 and "
                    "float32, and the feature Jacobian. Against the CPU on the same RAYX-stream rays (16 "
                    f"configurations × 100,000, float64): {ag['survivors_differ']} surviving rays differ, screen "
                    f"positions within {ag['max_screen_difference_mm']:.2g} mm.")))
        return
    tables = _cpu_tables(result)
    if tables:
        notes = []
        f32 = result.get("float32_accuracy")
        if f32:
            notes.append(f"float32 against float64 (same rays, fast stream, {f32['configs']} configurations × "
                         f"{f32['rays']:,} rays): largest hit-count difference {f32['max_hit_count_difference']} "
                         f"rays; centroids within {1e3 * f32['max_centroid_difference_mm']:.2g} µm; rms widths "
                         f"within {100 * f32['max_relative_width_difference']:.2g} %.")
        print(section(write_result(
            "torch_engine", title="Torch engine", tables=tables, notes=notes,
            summary="The torch engine (issue 16) against RAYX on the CPU: trace time per source ray (RAYX as the "
                    "twin calls it, with the RML written and read, and RAYX's bare `trace()`; the torch engine's "
                    "fast and RAYX sampling, float64 and float32), the feature Jacobian against one-sided finite "
                    "differences through RAYX, and how many rays a feature Jacobian needs.")))
    if "ray_jacobian" in result:
        rows = [[r["configurations"], f"{r['rays']:,}", r["inputs"], f"{100 * r['on_screen']:.0f} %",
                 f"{100 * r['with_derivatives']:.0f} %", f"{r['ray_jacobian_s']:.3f} s",
                 f"{r['histogram_jacobian_s']:.3f} s"] for r in result["ray_jacobian"]]
        t = Table("Best of the repeats, one thread:", ["configurations", "rays", "inputs", "rays on the screen",
                                                        "rays given derivatives", "`ray_jacobian`",
                                                        "its camera-histogram Jacobian"], rows,
                  align=["l", "r", "r", "r", "r", "r", "r"])
        print(section(write_result(
            "ray_jacobian", title="Per-ray Jacobian", tables=[t],
            summary="The per-ray Jacobian every fit step takes (`TorchEngine.ray_jacobian`, the values traced "
                    "inside) and its camera histograms' Jacobian, at a diagnosis's candidate-fit size, 34 "
                    "parameters + the chamber's z, one thread: at the reference ±1 % of each range (most rays "
                    "reach the screen) and at the 2021 settings ±1 % (the slits pass about a seventh: what the "
                    "demo measures).")))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--only", choices=("trace", "jacobian", "accuracy", "ray-jacobian"), help="run one part only")
    args = ap.parse_args(argv)
    if args.quick:
        sizes, threads, repeat = [(10_000, 1), (10_000, 16)], [1], 1
        jac = (4, 2000, 1)
        ladder, ref = [1000, 3000], 20_000
    else:
        sizes, threads, repeat = [(10_000, 1), (10_000, 16), (100_000, 1), (100_000, 16)], [1, 2], 2
        jac = (16, 10_000, 2)
        ladder, ref = [1000, 3000, 10_000, 30_000, 100_000], 200_000
    result = {"machine": machine(), "device": args.device, "torch": torch.__version__,
              "date": time.strftime("%Y-%m-%d")}
    if args.device != "cpu":
        result["gpu"] = torch.cuda.get_device_name(args.device)
        result["agreement_with_cpu"] = device_agreement(args.device)
        print(json.dumps(result["agreement_with_cpu"]), flush=True)
        result.update(bench_device(args.device))
        if args.json:
            Path(args.json).write_text(json.dumps(result, indent=2))
        _write(result)
        return 0
    if args.only in (None, "trace"):
        result["float32_accuracy"] = float32_accuracy()
        print(json.dumps(result["float32_accuracy"]), flush=True)
        result["trace"] = bench_trace(sizes, threads, args.device, repeat)
    if args.only in (None, "jacobian"):
        result["jacobian"] = bench_jacobian(jac[0], jac[1], args.device, jac[2])
        print(json.dumps(result["jacobian"]), flush=True)
    if args.only in (None, "accuracy"):
        result["rays_for_jacobian"] = bench_rays_for_one_percent(4, args.device, ladder, ref)
    if args.only in (None, "ray-jacobian"):
        result["ray_jacobian"] = bench_ray_jacobian(repeat=2 if args.quick else 5)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
    _write(result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
