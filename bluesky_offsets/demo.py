"""``bluesky-offsets demo``: the main job, on embedded defaults.

It runs the part of the workflow that exists so far and grows with the
project: today the RAYX twin of METRIXS — the nominal focus, a beamline with
hidden offsets (what the real one looks like to the twin), and how far apart
their histograms are compared with the twin's own noise.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .noise import expected_repeat_mse, histogram_mse
from .parameters import METRIXS
from .plotting import plot_footprint
from .twin import Twin


def run_demo(out: Path, n_rays: int = 20_000, seed: int = 0) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    twin = Twin(scheduler="inline", n_rays=n_rays)
    print(f"[1/3] twin: {twin.engine.version}, METRIXS table {METRIXS.version} "
          f"({len(METRIXS)} parameters, {len(METRIXS.fixed_names)} fixed-but-unknown)")

    nominal = twin.trace(METRIXS.reference, keep_rays=True, seed=seed)
    s = nominal.summary()
    plot_footprint(nominal, twin.hist, out / "footprint_nominal.png", title="METRIXS twin: nominal (reference RML)")
    print(f"[2/3] nominal focus: transmission {s['transmission']:.3f}, "
          f"std x {s['width_x']:.4f} mm, y {s['width_y']:.4f} mm -> {out / 'footprint_nominal.png'}")

    # Hidden offsets in the beamline's sensitive motors (5 % of their ranges) and the
    # fixed parameters; the commanded configuration is the nominal one.
    offsets = np.zeros(len(METRIXS))
    for name in ("E1.rotationXerror", "E2.rotationXerror", "M1_Cylinder.rotationXerror",
                 "E2.translationYerror", "E1.longHalfAxisA"):
        offsets[METRIXS.index(name)] = rng.choice([-1, 1]) * 0.05
    true_state = METRIXS.reference + METRIXS.offsets_to_physical(offsets)
    real = twin.trace(true_state, keep_rays=True, seed=seed + 1)
    repeat = twin.trace(METRIXS.reference, keep_rays=False, seed=seed + 2)
    plot_footprint(real, twin.hist, out / "footprint_with_offsets.png",
                   title="the 'real' beamline: nominal settings + hidden offsets")
    h_nom = np.concatenate([nominal.hist_x, nominal.hist_y])
    h_real = np.concatenate([real.hist_x, real.hist_y])
    h_rep = np.concatenate([repeat.hist_x, repeat.hist_y])
    mse_off = float(histogram_mse(h_nom, h_real))
    mse_rep = float(histogram_mse(h_nom, h_rep))
    r = real.summary()
    print(f"[3/3] with hidden offsets: transmission {r['transmission']:.3f}, centroid "
          f"({r.get('centroid_x', float('nan')):+.3f}, {r.get('centroid_y', float('nan')):+.3f}) mm; "
          f"histogram MSE to the twin {mse_off:.2e} vs. the twin's repeat noise {mse_rep:.2e} "
          f"(expected {float(expected_repeat_mse(h_nom, n_rays)):.2e}) -> {out / 'footprint_with_offsets.png'}")
    summary = {"n_rays": n_rays, "nominal": s, "with_offsets": r, "hidden_offsets_normalized":
               {n: float(o) for n, o in zip(METRIXS.names, offsets) if o}, "mse_offsets": mse_off,
               "mse_repeat": mse_rep, "seconds": time.perf_counter() - t0}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"done in {summary['seconds']:.1f} s; summary in {out / 'summary.json'}")
    return summary


def add_cli(sub) -> None:
    p = sub.add_parser("demo", help="run the main job (the whole workflow available so far)")
    p.add_argument("--out", default="bluesky-offsets-demo", help="output folder (default ./bluesky-offsets-demo)")
    p.add_argument("--rays", type=int, default=20_000, help="source rays per trace")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=lambda args: run_demo(Path(args.out), args.rays, args.seed) and 0)
