"""Which hidden effects can the diagnosis tell apart from the offsets? (linear Fisher analysis)

Traces the twin Jacobian of all 34 offsets and the secant response of each effect (0 -> the
value below) at a truth with hidden offsets, for configurations from
``diagnostic_configurations``, with common random numbers; then, for 5000-ray measurements:
the effect's chi-square signal, the share a fit of the offsets absorbs, its 1-sigma
uncertainty alone and with the offsets free (prior ±0.2), and the rival effect that explains
it best.  Numbers in docs/explanations/diagnosis.md; the result: ``benchmarks/results/effect_identifiability.json``.

    python benchmarks/bench_effect_identifiability.py [--configs 12] [--rays 10000] [--open 4]

``--open K`` appends the first K configurations again with the slits open
(``diagnosis.OPEN_APERTURE``: ASBL 4 x 4 mm, exit slit 100 µm), as the demo measures them.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bluesky_offsets.physics import effects as E
from bluesky_offsets.model.diagnosis import diagnostic_configurations, open_aperture
from bluesky_offsets.model.state import ModelState, detector_view, simulate_raw
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.twin import Twin
from sim_iocs.truth import default_start

HIDDEN = {"E1.rotationXerror": 0.04, "E2.rotationXerror": -0.04, "M1_Cylinder.rotationXerror": 0.02,
          "E1.longHalfAxisA": 0.02, "E2.shortHalfAxisB": -0.02}
EFFECTS = [("chamber_z", "z", 20.0), ("thermal_bump_m1", "height", 300.0), ("photon_energy", "delta", 0.005),
           ("source_divergence", "divergence", 0.2), ("source_size", "size", 0.2),
           ("grating_line_density", "delta", 0.02), ("intensity_scale", "delta", 0.05),
           ("detector_blur", "sigma", 0.05), ("chamber_rotation", "angle", 10.0),
           ("slope_error_m1", "meridional", 2.0)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", type=int, default=12)
    ap.add_argument("--rays", type=int, default=10000, help="rays of the twin traces")
    ap.add_argument("--measured-rays", type=int, default=5000, help="ray budget of the measurement")
    ap.add_argument("--prior", type=float, default=0.2, help="offset prior (normalized)")
    ap.add_argument("--open", type=int, default=0, help="configurations measured again with the slits open")
    args = ap.parse_args(argv)
    tw = Twin(scheduler="inline", n_rays=args.rays)
    cfg = diagnostic_configurations(default_start(), args.configs, seed=1)
    if args.open:
        cfg = np.vstack([cfg, open_aperture(cfg[:args.open])])
    off = np.zeros(len(METRIXS))
    for k, v in HIDDEN.items():
        off[METRIXS.index(k)] = v
    seeds = list(range(len(cfg)))
    t0 = time.perf_counter()
    h0 = np.concatenate(simulate_raw(tw, cfg, ModelState(off), args.rays, seeds), 1)
    jac = np.zeros((len(cfg), 100, len(METRIXS)))
    for j in range(len(METRIXS)):
        o = off.copy()
        o[j] += 0.003
        jac[:, :, j] = (np.concatenate(simulate_raw(tw, cfg, ModelState(o), args.rays, seeds), 1) - h0) / 0.003
    cols = []
    for name, par, val in EFFECTS:
        st = ModelState(off).with_effect(name, {par: val})
        raw = simulate_raw(tw, cfg, st, args.rays, seeds) if E.get(name).level == "twin" else (h0[:, :50], h0[:, 50:])
        cols.append((np.concatenate(detector_view(*raw, st, tw.hist), 1) - h0).reshape(-1))
    n = args.measured_rays
    p = np.maximum(h0, 1 / n).reshape(-1)
    w = 1 / (2 * p * (1 - p) / n)  # measurement and model noise
    J = jac.reshape(-1, len(METRIXS))
    ridge = np.full(len(METRIXS), 1 / args.prior ** 2)

    def residual(s, M, reg):
        H = M.T @ (M * w[:, None]) + np.diag(reg)
        c = np.linalg.solve(H, M.T @ (w * s))
        r = s - M @ c
        return float((w * r * r).sum()), H

    print(f"{len(cfg)} configurations ({args.open} with open slits), {args.rays} rays, {time.perf_counter() - t0:.0f} s of tracing")
    print(f"{'effect':36s} {'signal':>8s} {'absorbed':>9s} {'σ alone':>8s} {'σ w/ offsets':>12s}  closest rival")
    rows = []
    for i, (name, par, val) in enumerate(EFFECTS):
        s = cols[i]
        signal = float((w * s * s).sum())
        left, _ = residual(s, J, ridge)
        _, H = residual(s, np.c_[J, s / val], np.r_[ridge, 1e-12])
        sig_m = np.sqrt(np.linalg.inv(H)[-1, -1])
        sig_a = 1 / np.sqrt((w * (s / val) ** 2).sum())
        rivals = sorted((residual(s, np.c_[J, cols[k] / EFFECTS[k][2]], np.r_[ridge, 1e-12])[0], f"{EFFECTS[k][0]}.{EFFECTS[k][1]}")
                        for k in range(len(EFFECTS)) if k != i)
        print(f"{name + '.' + par + f' ({val:g})':36s} {signal:8.0f} {100 * (1 - left / max(signal, 1e-300)):8.1f}% "
              f"{100 * sig_a / abs(val):7.1f}% {100 * sig_m / abs(val):11.1f}%  {rivals[0][1]} (leaves {rivals[0][0]:.0f})")
        rows.append([f"{name}.{par} ({val:g})", f"{signal:.0f}", f"{100 * (1 - left / max(signal, 1e-300)):.1f} %",
                     f"{100 * sig_a / abs(val):.1f} %", f"{100 * sig_m / abs(val):.1f} %",
                     f"{rivals[0][1]} (leaves {rivals[0][0]:.0f})"])
    write(rows, len(cfg), args)


def write(rows: list, n_cfg: int, args) -> None:
    """The result ``effect_identifiability``: one row per effect."""
    from results import Table, write_result
    table = Table(f"{n_cfg} configurations ({args.open} with open slits), twin traces at {args.rays:,} rays, a "
                  f"{args.measured_rays:,}-ray measurement, offsets' prior ±{args.prior:g}:",
                  ["effect (value)", "χ² signal", "absorbed by the offsets", "1σ alone", "1σ with the offsets free",
                   "closest rival (χ² it leaves)"], rows, align=["l", "r", "r", "r", "r", "l"])
    write_result("effect_identifiability", title="Which effects the diagnosis can tell apart from the offsets",
                 tables=[table],
                 summary="A linear Fisher analysis at a truth with hidden offsets: each effect's χ² signal in a "
                         "measurement, the share a fit of the offsets absorbs, its 1σ uncertainty (relative to the "
                         "value) alone and with the offsets free, and the rival effect that explains it best.")


if __name__ == "__main__":
    main()
