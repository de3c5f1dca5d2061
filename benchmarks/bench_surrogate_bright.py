"""The surrogate where the beamline is bright: configurations near the reference, against RAYX.

Usage::

    python benchmarks/bench_surrogate_bright.py [CHECKPOINT ...] [--fractions 0.02 0.05 0.1 0.2]
        [--samples 32] [--rays 10000]

``surrogate evaluate`` draws uniformly from the whole box, as the training data is drawn, and
there almost every configuration is dark; a calibration measures bright ones.  This benchmark
draws configurations at the reference +- a fraction of each parameter's range (uniform, every
parameter at once, clipped to the box: the RML's reference lies outside it in the two slit
sizes and E1/E2 rotation Z; the focus chamber at its nominal place), traces each twice with
RAYX and reports, per fraction, the twin's and the surrogate's transmission and the surrogate's
non-empty MSE against the twin's repeat noise.  Prints a Markdown table for docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from _machine import machine  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoints", nargs="*", help="default: the shipped one")
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.02, 0.05, 0.1, 0.2])
    ap.add_argument("--samples", type=int, default=32, help="configurations per fraction (default 32)")
    ap.add_argument("--rays", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from bluesky_offsets.physics.parameters import METRIXS
    from bluesky_offsets.physics.twin import Twin
    from bluesky_offsets.surrogate.network import default_checkpoint, load

    paths = args.checkpoints or [str(default_checkpoint())]
    models = [load(p) for p in paths]
    twin = Twin("rayx", n_rays=args.rays, scheduler="inline")
    bx = twin.hist.bins_x  # transmission: one axis's histogram summed
    rng = np.random.default_rng(args.seed)
    ref = METRIXS.normalize(METRIXS.reference)
    rows = []
    for f in args.fractions:
        x = np.clip(ref + rng.uniform(-f, f, (args.samples, len(METRIXS))), 0.0, 1.0)
        values = METRIXS.denormalize(x)
        seeds = rng.integers(0, 2**32, size=(2, args.samples))
        a, b = (twin.trace_batch(values, seed=[int(s) for s in seeds[k]]) for k in range(2))
        ha = np.concatenate([a.hist_x, a.hist_y], 1)
        hb = np.concatenate([b.hist_x, b.hist_y], 1)
        nonempty = (a.n_hits > 0) & (b.n_hits > 0)
        noise = np.mean((ha[nonempty] - hb[nonempty]) ** 2)
        for path, m in zip(paths, models):
            p = m.predict(values)
            mse = np.mean((p[nonempty] - ha[nonempty]) ** 2)
            rows.append((f, os.path.basename(path), ha[:, :bx].sum(1), p[:, :bx].sum(1), int(nonempty.sum()),
                         mse, noise))
    print(f"Machine: {machine()}. Command: `python benchmarks/bench_surrogate_bright.py {' '.join(args.checkpoints)} "
          f"--fractions {' '.join(map(str, args.fractions))} --samples {args.samples} --rays {args.rays}`\n")
    print("| reference ± (of each range) | checkpoint | RAYX transmission, median [max] | surrogate transmission, "
          "median [max] | non-empty | MSE non-empty | repeat noise | ratio |")
    print("|---:|---|---|---|---:|---:|---:|---:|")
    for f, name, t_twin, t_sur, n, mse, noise in rows:
        print(f"| {f:g} | {name} | {np.median(t_twin):.3f} [{t_twin.max():.3f}] | {np.median(t_sur):.3f} "
              f"[{t_sur.max():.3f}] | {n} | {mse:.3g} | {noise:.3g} | **{mse / noise:.3g}** |")


if __name__ == "__main__":
    main()
