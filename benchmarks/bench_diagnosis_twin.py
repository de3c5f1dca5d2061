"""The diagnosis workflow on twin-made measurements (no IOC): how far each step gets, and when.

A hidden truth (the demo's offsets and one effect) is traced by the twin at bright
configurations of the demo's design (and some of them with the slits open), with fresh ray seeds — a measurement as the simulated
IOC would give it, at the camera's resolution or at the paper's.  Then the demo's analysis:
surrogate finder on the paper's histograms, refinement of the offsets through the twin,
diagnosis of all candidate effects, the winner added and refitted.  Printed per step: the
misfit (chi2/dof, MSE / noise), the time, the ranking; at the end the truth's own misfit
with the same model rays (what a perfect fit would score).

    python benchmarks/bench_diagnosis_twin.py [--effect chamber_z:z=20 | none] [--resolution camera|paper]
        [--refine-iterations 4] [--refit-iterations 4] [--seed 0] [--json out.json] [--save state.npz]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from bluesky_offsets import effects as E
from bluesky_offsets.calibration import OffsetFinder
from bluesky_offsets.demo import DEMO_OFFSETS, DemoSettings, candidate_configurations, measurement_design, parse_effect
from bluesky_offsets.diagnosis import add_effect_result, diagnose, evaluate, in_box
from bluesky_offsets.finder import Budget, load_forward_model
from bluesky_offsets.model import Measurement, ModelState, refine, simulate
from bluesky_offsets.parameters import METRIXS
from bluesky_offsets.twin import CAMERA, HistogramSpec, Twin
from plans import enough_rays
from sim_iocs.truth import default_start


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--effect", default="chamber_z:z=20")
    ap.add_argument("--resolution", choices=("camera", "paper"), default="camera")
    ap.add_argument("--rays", type=int, default=5000)
    ap.add_argument("--anchor-rays", type=int, default=10_000)
    ap.add_argument("--refine-iterations", type=int, default=4)
    ap.add_argument("--refit-iterations", type=int, default=4)
    ap.add_argument("--feature-iterations", type=int, default=None, help="default: the demo's")
    ap.add_argument("--scan-rays", type=int, default=2000)
    ap.add_argument("--load", default=None, help="start from a --save file: skip the measurement and refinement")
    ap.add_argument("--candidates", default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--json", default=None)
    ap.add_argument("--save", default=None, help="write the measurement and the refined offsets (.npz)")
    args = ap.parse_args(argv)
    name, values = parse_effect(args.effect)
    s = DemoSettings(effect=(name, values), seed=args.seed)
    t0 = time.perf_counter()

    def log(msg):
        print(f"{time.perf_counter() - t0:7.1f} s  {msg}", flush=True)

    paper = HistogramSpec()
    spec = CAMERA if args.resolution == "camera" else paper
    base = Twin(n_rays=args.rays, n_workers=args.workers)
    twin = base.with_hist(spec)
    truth = ModelState(np.array([DEMO_OFFSETS.get(n, 0.0) for n in METRIXS.names]),
                       {name: values} if name else {}, "truth")
    rng = np.random.default_rng(args.seed + 12345)
    cand = candidate_configurations(s, default_start())
    hx, hy = simulate(base, cand, truth, args.rays, list(rng.integers(0, 2**31, len(cand))))
    bright = cand[enough_rays(hx, hy)][: s.configurations]
    design, analysed = measurement_design(s, bright)
    log(f"{len(bright)} bright of {len(cand)} candidates, {len(design) - len(bright)} of them with open slits; "
        f"{len(analysed)} analysed")
    mx, my = simulate(twin, design, truth, args.rays, list(rng.integers(0, 2**31, len(design))))
    full = Measurement(design, mx, my, args.rays, spec=spec)
    coarse = (full if spec == paper else full.rebinned(paper)).subset(in_box(design))  # the surrogate's box
    meas = full.subset(analysed)

    fm = load_forward_model()
    finder = OffsetFinder(model=fm, budget=Budget(evaluations=s.finder_evaluations, seconds=s.finder_seconds),
                          seed=args.seed)
    found = finder(coarse.configurations, coarse.histograms(), n_rays=args.rays)
    log("surrogate finder done")
    report = {"args": vars(args), "steps": []}

    def record(label, st, extra=None):
        mf = evaluate(meas, st, twin, model_rays=args.anchor_rays, seed=4242)
        row = {"model": label, "chi2_reduced": mf.chi2_reduced_total,
               "mse_over_noise": mf.mse_total / mf.expected_mse_total, "t": time.perf_counter() - t0,
               "effects": st.effects, **(extra or {})}
        report["steps"].append(row)
        log(f"{label:28s} chi2/dof {row['chi2_reduced']:8.3f}  MSE/noise {row['mse_over_noise']:7.2f}  {st.effects}")
        return mf

    record("truth", truth)
    record("twin", ModelState())
    start = ModelState(np.asarray(found.offsets, float), {}, "surrogate offsets")
    record("surrogate offsets", start)

    def prog(h):
        log(f"   {h.get('stage', '')[:4]} it {h['iteration']:2d} {'acc' if h['accepted'] else 'REJ'}"
            f"{' J' if h.get('jacobian_refreshed') else ''} chi2/dof {h['chi2_reduced']:8.3f}"
            f" features {h.get('chi2_features', float('nan')):9.1f} {h.get('effects') or ''}")

    kw = dict(s.refine_kw, **({"feature_iterations": args.feature_iterations} if args.feature_iterations else {}))
    r = refine(meas, start, twin, None, iterations=args.refine_iterations, anchor_rays=args.anchor_rays,
               seed=args.seed, progress=prog, also_from=[ModelState()], **kw)
    record("+ offsets", r.state)
    if args.save:
        np.savez(args.save, configurations=meas.configurations, hist_x=meas.hist_x, hist_y=meas.hist_y,
                 n_rays=meas.n_rays, offsets=r.state.offsets, truth=truth.offsets,
                 jac=r.local_model.jac, t0=r.local_model.t0, anchor_seed=r.local_model.seed)
    cands = [c.strip() for c in args.candidates.split(",")] if args.candidates else None
    d = diagnose(meas, r.state, twin, None, candidates=cands, reuse=r.local_model, seed=args.seed,
                 scan_rays=args.scan_rays)
    log(f"diagnosis: {d.verdict}  ({d.n_traces} traces)")
    for note in d.notes:
        log(f"   {note}")
    for c in d.candidates:
        log(f"   {c.name:24s} score {c.score:9.1f}  fit gain {c.delta_chi2_all:8.1f} held-out {c.delta_chi2_heldout:8.1f}"
            f" folds +{c.folds_improved}/-{c.folds_worse}  twin {c.delta_chi2_twin if c.refined else float('nan'):8.1f}"
            f"  {'SIG' if c.significant else '   '} {c.values}")
    report["verdict"] = d.verdict
    report["ranking"] = [c.as_dict() for c in d.candidates]
    if d.best is not None:
        kw = dict(s.refit_kw, **({"feature_iterations": args.feature_iterations} if args.feature_iterations else {}))
        start_fit = ModelState(d.best.refined_state.offsets, r.state.effects, r.state.label)
        res = add_effect_result(meas, start_fit, d.best.name, twin, None, values=d.best.values,
                                iterations=args.refit_iterations, anchor_rays=args.anchor_rays, seed=args.seed + 1,
                                progress=prog, **kw)
        record(f"+ {d.best.name}", res.state, {"sigma": res.effect_sigma})
    log(f"hidden: {name or 'none'} {values}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1, default=float)
    base.close()


if __name__ == "__main__":
    main()
