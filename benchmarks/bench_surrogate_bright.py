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
non-empty MSE against the twin's repeat noise.  Writes ``benchmarks/results/surrogate_bright.json``.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402



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
    from render import section
    from results import Table, write_result
    table = Table(f"{args.samples} configurations per row, each traced twice by RAYX at {args.rays:,} rays:",
                  ["reference ± (of each range)", "checkpoint", "RAYX transmission, median [max]",
                   "surrogate transmission, median [max]", "non-empty", "MSE non-empty", "repeat noise", "ratio"],
                  [[f"{f:g}", name, f"{np.median(t_twin):.3f} [{t_twin.max():.3f}]",
                    f"{np.median(t_sur):.3f} [{t_sur.max():.3f}]", n, f"{mse:.3g}", f"{noise:.3g}",
                    f"**{mse / noise:.3g}**"] for f, name, t_twin, t_sur, n, mse, noise in rows],
                  align=["r", "l", "l", "l", "r", "r", "r", "r"])
    result = write_result(
        "surrogate_bright", title="Surrogates where a calibration looks: near the reference", tables=[table],
        summary="`surrogate evaluate` draws as the training data is drawn, uniformly from the box, where most "
                "configurations are dark; a calibration looks near the reference. Here: configurations at the "
                "reference ± a fraction of each range (all 34 at once, clipped to the box, the chamber at its "
                "nominal place), each traced twice by RAYX; the surrogate's MSE on the non-empty ones over RAYX's "
                "repeat noise. Few rows are non-empty far from the reference: there the ratios rest on few "
                "configurations.")
    print(section(result))


if __name__ == "__main__":
    main()
