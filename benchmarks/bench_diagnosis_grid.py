"""The diagnosis over a grid of hidden truths: does it name the effect, fit it, and is its ± true?

Each scenario hides offsets in all 34 parameters (uniform within ±``--offsets-fraction`` of
each range, a new draw per seed) and zero, one or two effects.  RAYX (the reference twin)
measures it the way the demo's IOC would: the demo's design (bright configurations around
the start that brings the hidden beamline's motors back to its nominal, plus some of them
with the slits open), at the camera's resolution, with seeded frame noise (a detector-level
effect acts on each photon: :func:`~bluesky_offsets.model.state.simulate_frames`).  The beam
search is not part of this grid (it starts where the beam is); the analysis is the demo's: offsets
fit from the nominal twin → diagnosis → add the winner → refit → diagnose again, all with
the one fit engine.  The final check re-simulates the result with fresh rays (RAYX, or the
torch twin with ``--check torch`` where RAYX is not installed, e.g. on a lent GPU).

Two phases, so that the fits can run on another machine:

    python benchmarks/bench_diagnosis_grid.py make --out grid/        # RAYX measurements (.npz)
    python benchmarks/bench_diagnosis_grid.py run grid/ [--device cuda] [--check torch] [--only NAME]
    python benchmarks/bench_diagnosis_grid.py table grid/              # the result: diagnosis_grid.json

``run`` is resumable: a scenario with a result file is skipped.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

# (label, {effect: {parameter: value}}): both signs of a defocus, a mirror effect, a source
# effect (both signs), a detector-level effect, two at once, and none; two magnitudes each
SCENARIOS = {
    "chamber_z+12": {"chamber_z": {"z": 12.0}},
    "chamber_z-20": {"chamber_z": {"z": -20.0}},
    "chamber_z+25": {"chamber_z": {"z": 25.0}},
    "thermal_bump_m1_300": {"thermal_bump_m1": {"height": 300.0}},
    "thermal_bump_m1_450": {"thermal_bump_m1": {"height": 450.0}},
    "source_divergence+0.5": {"source_divergence": {"divergence": 0.5}},
    "source_divergence-0.3": {"source_divergence": {"divergence": -0.3}},
    "detector_blur_0.03": {"detector_blur": {"sigma": 0.03}},
    "detector_blur_0.06": {"detector_blur": {"sigma": 0.06}},
    "chamber_z+15&thermal_bump_m1_400": {"chamber_z": {"z": 15.0}, "thermal_bump_m1": {"height": 400.0}},
    "none": {},
}


def _make(args) -> None:
    from bluesky_offsets.physics import effects as E
    from bluesky_offsets.commands.demo import DemoSettings
    from bluesky_offsets.model.state import ModelState, simulate, simulate_frames
    from bluesky_offsets.physics.parameters import METRIXS
    from bluesky_offsets.physics.twin import CAMERA, Twin
    from plans import enough_rays
    from plans.workflow import candidate_configurations, measurement_design
    from sim_iocs.truth import default_start

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    twin = Twin(scheduler="inline")
    for label, effects in SCENARIOS.items():
        if args.only and args.only not in label:
            continue
        for draw in range(args.draws):
            path = out / f"{label}__{draw}.npz"
            if path.exists():
                continue
            seed = 1000 * draw + sum(map(ord, label))
            rng = np.random.default_rng(seed)
            off = rng.uniform(-args.offsets_fraction, args.offsets_fraction, len(METRIXS))
            truth = ModelState(off, {n: E.get(n).values(v) for n, v in effects.items()}, "truth")
            s = DemoSettings(seed=draw)
            start = default_start() - np.where(METRIXS.motorized, METRIXS.offsets_to_physical(off), 0.0)
            cand = candidate_configurations(s.design, start)
            hx, hy = simulate(twin, cand, truth, 2000, [seed + i for i in range(len(cand))])
            bright = cand[enough_rays(hx, hy)][:s.design.bright]
            design, analysed = measurement_design(s.design, bright)
            design = design[analysed]
            # frames as a camera counts them: a detector-level effect acts on each photon, so the
            # counts keep their noise (simulate_frames says why simulate would not)
            mx, my = simulate_frames(twin.with_hist(CAMERA), design, truth, args.rays,
                                     [seed + 5000 + i for i in range(len(design))])
            np.savez(path, configurations=design, hist_x=mx, hist_y=my, n_rays=args.rays, offsets=off,
                     effects=json.dumps(effects), n_bright=len(bright))
            print(f"{path.name}: {len(bright)} bright, {len(design)} analysed", flush=True)


def _run(args) -> None:
    import torch
    from _machine import machine

    from bluesky_offsets.model import diagnosis as D
    from bluesky_offsets.model.misfit import misfit
    from bluesky_offsets.model.measurement import Measurement
    from bluesky_offsets.model.state import ModelState, refine, simulate
    from bluesky_offsets.physics.engine import TorchEngine
    from bluesky_offsets.physics.twin import CAMERA, Twin

    folder = Path(args.folder)
    args.rounds = args.rounds or D.ROUNDS
    eng_opts = {"device": args.device}
    prior = {"prior_sigma": args.prior_fraction / np.sqrt(3.0)} if args.prior_fraction else {}
    fit_o = D.FIT.replace(engine=eng_opts, **prior, **({"rays": args.fit_rays} if args.fit_rays else {}))
    scan_o = D.SCAN.replace(engine=eng_opts, **prior)
    if args.threads:
        torch.set_num_threads(args.threads)
    check = Twin(TorchEngine(hist=CAMERA, options=eng_opts)) if args.check == "torch" else \
        Twin(scheduler="inline").with_hist(CAMERA)
    for path in sorted(folder.glob("*.npz")):
        label, draw = path.stem.split("__")
        if (args.only and args.only not in label) or (args.draw is not None and int(draw) != args.draw):
            continue
        res_path = path.with_suffix(".json")
        if res_path.exists():
            continue
        d = np.load(path)
        hidden = json.loads(str(d["effects"]))
        meas = Measurement(d["configurations"], d["hist_x"], d["hist_y"], int(d["n_rays"]), spec=CAMERA)
        t0 = time.perf_counter()

        def evaluate(st, seed=4242):
            rays = 4 * meas.n_rays
            hx, hy = simulate(check, meas.configurations, st, rays, [seed + i for i in range(meas.n)])
            return misfit(meas.hist_x, meas.hist_y, hx, hy, meas.n_rays, model_rays=rays)

        # the analysis's engine (a random stream per configuration), as the demo's offsets fit
        r = refine(meas, ModelState(), options=fit_o)
        cur, found, rankings = r.state, [], []
        for round_ in range(args.rounds):
            diag = D.diagnose(meas, cur, seed=round_, options=scan_o)
            rankings.append([c.name for c in diag.candidates])
            if diag.best is None:
                break
            b = diag.best
            # and from the bare twin's offsets, as the analysis refits (analyse_measurement)
            res = D.add_effect_result(meas, b.refit_start(), b.name, values=b.values,
                                      also_from=[b.twin_start()] if D.REFIT_FROM_TWIN else [],
                                      options=fit_o.replace(seed=fit_o.seed + 1 + round_))
            found.append({"effect": b.name, "values": res.state.effects[b.name],
                          "sigma": res.effect_sigma.get(b.name, {})})
            cur = res.state
            if not evaluate(cur).total_beyond_noise():
                break
        if found:
            # every effect as the last refit left it (the first one's own refit lacked the second)
            found = [{**f, "values": cur.effects[f["effect"]], "sigma": res.effect_sigma.get(f["effect"], {})}
                     for f in found]
        retest, dropped = [], None
        if len(found) >= 2:
            # the backward step (plans.diagnose.analyse_measurement's retest_effects)
            tests = D.retest_effects(meas, cur, [f["effect"] for f in found],
                                     options=fit_o.replace(seed=fit_o.seed + 1 + len(found)))
            retest = [t.as_dict() for t in tests]
            w = D.weakest(tests)
            if w is not None:
                dropped, cur = w.effect, w.without.state
                sig = w.without.effect_sigma()
                found = [{**f, "values": cur.effects[f["effect"]], "sigma": sig.get(f["effect"], {})}
                         if f["effect"] in cur.effects else {**f, "dropped": True} for f in found]
        mf = evaluate(cur)
        at_truth = evaluate(ModelState(d["offsets"], hidden))
        row = {"scenario": label, "draw": int(draw), "hidden": hidden, "found": found, "rankings": rankings,
               "refit_from_twin": D.REFIT_FROM_TWIN,
               "retest": retest, "dropped": dropped, "rounds": args.rounds,
               "fit_rays": fit_o.rays, "prior_sigma": fit_o.prior_sigma,
               "verdict": diag.verdict, "chi2_reduced": mf.chi2_reduced_total,
               "mse_over_noise": mf.mse_total / mf.expected_mse_total,
               "truth_chi2_reduced": at_truth.chi2_reduced_total,
               "offsets_chi2_reduced": evaluate(r.state).chi2_reduced_total,
               "seconds": time.perf_counter() - t0, "device": args.device, "machine": machine(),
               "n_configurations": meas.n,
               "end": {"offsets": cur.offsets.tolist(), "effects": cur.effects}}
        res_path.write_text(json.dumps(row, indent=1, default=float))
        added = [f["effect"] + (" (dropped)" if f.get("dropped") else "") for f in found]
        print(f"{label} #{draw}: {added} chi2/dof {row['chi2_reduced']:.3f} "
              f"({row['seconds']:.0f} s)", flush=True)


def _cells(r) -> list:
    """A run's row: its hidden effects against what it named, fitted and left."""
    hidden = r["hidden"]
    names = [f["effect"] + (" (dropped)" if f.get("dropped") else "") for f in r["found"]]
    cells = []
    for name, vals in hidden.items():
        f = next((x for x in _named(r) if x["effect"] == name), None)
        for k, hv in vals.items():
            if f is None:
                cells.append((f"{name}.{k}: —", "—", "—"))
                continue
            v, s = f["values"][k], f["sigma"].get(k, float("nan"))
            cells.append((f"{name}.{k} = {v:.3g} ± {s:.2g}", f"{(v - hv) / hv * 100:+.0f} %",
                          f"{(v - hv) / s:+.1f}" if s > 0 else "—"))
    if not cells:
        cells = [("—", "—", "—")]
    return [r["scenario"], r["draw"], str(hidden or "none"), ", ".join(names) or "none",
            "; ".join(c[0] for c in cells), "; ".join(c[1] for c in cells), "; ".join(c[2] for c in cells),
            f"{r['chi2_reduced']:.2f}", f"{r['mse_over_noise']:.2f}", f"{r['seconds']:.0f}"]


def _table(args) -> None:
    from render import section
    from results import Table, write_result
    rows = [json.loads(p.read_text()) for p in sorted(Path(args.folder).glob("*.json"))]
    grid = Table(f"{len(rows)} runs:", ["scenario", "draw", "hidden", "added (in order)", "fitted ± σ", "rel. error",
                                        "error/σ", "χ²/dof after", "MSE/noise", "s"],
                 [_cells(r) for r in rows], align=["l", "r", "l", "l", "l", "r", "r", "r", "r", "r"])
    summary = _summary(rows)
    machines = sorted({r["machine"] for r in rows if r.get("machine")})
    notes = [summary] + ([f"The runs ran on: {'; '.join(machines)}."] if machines else [])
    result = write_result(
        "diagnosis_grid", title="Diagnosis on the differentiable twin (issue 17)", tables=[grid], notes=notes,
        summary="Issue 17's scenario grid: each scenario hides offsets in all 34 parameters and zero, one or two "
                "effects; RAYX measures it as the demo's IOC would (the demo's design, camera resolution, seeded "
                "frame noise); the analysis is the demo's (offsets fit → diagnosis → the winner added and refitted "
                "→ diagnose again, then the backward step); the final check re-simulates the result with fresh "
                "rays. Asked by issue 17 (≥ 90 % each): the true effects named, fitted within 25 %, within 2σ, "
                "χ²/dof and MSE/noise ≤ 1.5 after; no effect named without one.")
    print(section(result))


def _named(r) -> list[dict]:
    """The effects a run ends with: those added and not dropped by the backward step."""
    return [f for f in r["found"] if not f.get("dropped")]


def _summary(rows) -> str:
    """The issue's acceptance numbers over the rows: named first, within 25 %, within 2 σ,
    χ²/dof and MSE/noise ≤ 1.5 after; no effect named without one."""
    with_effect = [r for r in rows if r["hidden"]]
    first = named_ok = exact = within = covered = fine = 0
    params = 0
    for r in with_effect:
        names = [f["effect"] for f in r["found"]]
        named = [f["effect"] for f in _named(r)]
        first += bool(names) and names[0] in r["hidden"] and set(r["hidden"]) <= set(names)
        named_ok += bool(named) and named[0] in r["hidden"] and set(r["hidden"]) <= set(named)
        exact += set(named) == set(r["hidden"])
        fine += r["chi2_reduced"] <= 1.5 and r["mse_over_noise"] <= 1.5
        for name, vals in r["hidden"].items():
            f = next((x for x in _named(r) if x["effect"] == name), None)
            for k, hv in vals.items():
                params += 1
                if f is None:
                    continue
                v, s = f["values"][k], f["sigma"].get(k, float("nan"))
                within += abs(v - hv) <= 0.25 * abs(hv)
                covered += s > 0 and abs(v - hv) <= 2 * s
    none = [r for r in rows if not r["hidden"]]
    quiet = sum(not r["found"] for r in none)
    n = len(with_effect)
    return (f"{n} runs with hidden effects: a true one added first and all found: {first}/{n}; in the end a "
            f"true one named first and all named: {named_ok}/{n}, exactly the hidden ones: {exact}/{n}; "
            f"chi2/dof and MSE/noise <= 1.5 after: {fine}/{n}; of {params} hidden magnitudes: within 25 %: "
            f"{within}, within 2 sigma: {covered}.  {len(none)} runs without: no effect named in {quiet}.")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("make")
    m.add_argument("--out", default="grid")
    m.add_argument("--draws", type=int, default=3)
    m.add_argument("--rays", type=int, default=5000)
    m.add_argument("--offsets-fraction", type=float, default=0.05)
    m.add_argument("--only", default=None, help="scenarios whose label contains this")
    r = sub.add_parser("run")
    r.add_argument("folder")
    r.add_argument("--device", default="cpu")
    r.add_argument("--check", choices=("rayx", "torch"), default="rayx")
    r.add_argument("--only", default=None)
    r.add_argument("--draw", type=int, default=None)
    r.add_argument("--threads", type=int, default=None)
    r.add_argument("--rounds", type=int, default=None, help="diagnoses at most (default: the analysis's, 3)")
    r.add_argument("--prior-fraction", type=float, default=None,
                   help="the offsets' prior: uniform within this fraction of each range (default: the "
                        "analysis's, the paper's 20 %%)")
    r.add_argument("--fit-rays", type=int, default=None,
                   help="rays of the offsets fit, the refits and the backward step (default: diagnosis.FIT's)")
    t = sub.add_parser("table")
    t.add_argument("folder")
    args = ap.parse_args(argv)
    {"make": _make, "run": _run, "table": _table}[args.cmd](args)


if __name__ == "__main__":
    main()
