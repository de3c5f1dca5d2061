"""The focus's σ "from the calibration" against the focus measured: how often it covers, and why it is wide.

For finished demos (``bench_demo.py``'s folders, each with ``out/`` and ``store/``), every move of
the beam optimization: the predicted rms widths, their printed σ and the widths measured after
the move, as ``measured / predicted − 1`` and that over σ.  With ``--draws N`` also, at the
calibration the first move used (``out/calibration.json``): N states drawn from its covariance,
as the optimizer draws them (:func:`bluesky_offsets.optimize.optimizer.covariance_states`), each
state's χ² on the frames the analysis fitted (the designed ones and the beam search's lit ones,
the last stage of the fit options its run recorded) above the calibration's
own: whether the frames allow the states the σ is read from (their joint 95 % region is
``chi2.ppf(0.95, k)`` above it, k the fitted parameters).  A drawn offset beyond its bound is
traced at the bound.  With ``--samples N``, the first move's σ as the optimizer reads it where it
has the calibration's frames: from N posterior samples fitted to them
(:func:`bluesky_offsets.model.fit.posterior_samples`), against the widths measured after the move
with their own σ.

    python benchmarks/bench_focus_sigma.py [LABEL=]DIR ... [--draws 16] [--samples 12] [--result focus_sigma]

Each run's draws and samples are kept in its folder (``focus_sigma_draws.json``,
``focus_sigma_samples.json``) and read again by a later call.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def moves(run: Path, label: str) -> list[dict]:
    """Each move's predicted widths, their σ and the widths measured after it (µm)."""
    beam = json.loads((run / "out" / "summary.json").read_text()).get("beam") or {}
    rows = []
    for k, st in enumerate(beam.get("steps", [])[:2]):  # a third step goes back to the first's settings
        for a in "xy":
            p, s, m = 1e3 * st["predicted"][f"rms_{a}"], 1e3 * st["predicted_sigma"][a], 1e3 * st["after"][f"rms_{a}"]
            rows.append({"run": label, "move": k + 1, "axis": a, "predicted": p, "sigma": s, "measured": m,
                         "error": m / p - 1.0, "pull": abs(m - p) / s})
    return rows


def drawn_chi2(run: Path, label: str, n: int) -> dict:
    """χ² of ``n`` states drawn from the calibration's covariance, above the calibration's own.

    Kept in the run's folder (``focus_sigma_draws.json``): a run measured with as many draws is read, not measured again.
    """
    kept = run / "focus_sigma_draws.json"
    if kept.exists() and len((got := json.loads(kept.read_text()))["above"]) == n:
        return {**got, "run": label}
    got = _drawn_chi2(run, n)
    kept.write_text(json.dumps(got))
    return {**got, "run": label}


def _opened(run: Path):
    """A finished demo's summary and its run store."""
    import bluesky_offsets.blas as blas
    blas.pin_kernels()
    from bluesky_offsets.store import open_store
    return json.loads((run / "out" / "summary.json").read_text()), open_store(run / "store")


def _calibrated(run: Path):
    """A finished demo's summary, its calibration, its run store, and the frames and fit options of its fit.

    As the queue's ``optimize`` reads them (:func:`plans.workflow.calibration_frames`); for a demo
    whose fitted model's run does not say its frame count, read from that run without the check.
    """
    from bluesky_offsets import load_calibration
    from bluesky_offsets.model.fit import FitOptions
    from bluesky_offsets.physics.parameters import METRIXS
    from plans.diagnose import load_results
    from plans.workflow import as_analysed, calibration_frames

    summary, store = _opened(run)
    cal = load_calibration(run / "out" / "calibration.json")
    fitted = calibration_frames(cal, store)
    if fitted is None:
        start = load_results(store, cal.uid)["start"]
        fitted = (as_analysed(store, store.load_measurement(start["measurement_uid"], table=METRIXS)),
                  FitOptions.from_mapping(start["fit_options"]))
    return summary, cal, store, fitted


def _drawn_chi2(run: Path, n: int) -> dict:
    """:func:`drawn_chi2` measured: the calibration and the analysed frames read from the run's folder."""
    from scipy.stats import chi2 as chi2_dist

    from bluesky_offsets.model.fit import _Model
    from bluesky_offsets.model.state import ModelState
    from bluesky_offsets.optimize.optimizer import OptimizeOptions, covariance_states
    from bluesky_offsets.physics.beamline import torch_engine
    from bluesky_offsets.physics.parameters import MAX_OFFSET, METRIXS

    _, cal, _, (meas, o) = _calibrated(run)  # the frames and the options the calibration was fitted with
    engine, P = torch_engine(METRIXS), len(METRIXS)
    stage = o.stages[-1][0]

    def chi2(state: ModelState) -> tuple[float, float]:
        st = ModelState(np.clip(state.offsets, -MAX_OFFSET, MAX_OFFSET), state.effects, state.label)
        mdl = _Model(meas, st, engine, o, METRIXS)
        r, _, dof, _ = mdl.residuals(stage, mdl.products(stage, mdl.vector(st), False))
        return float(r @ r), float(dof)

    c0, dof = chi2(cal.state)
    # the draws the optimizer's sampled σ reads (sampled_sigma: the same seed)
    states = covariance_states(cal.state, cal.covariance, cal.names, n, seed=OptimizeOptions().check_seed)
    above = np.sort([chi2(st)[0] - c0 for st in states])
    return {"frames": meas.n, "dof": dof, "chi2": c0,
            "region": float(chi2_dist.ppf(0.95, len(cal.names or ()) or P)), "above": above.tolist()}


def sampled_move(run: Path, label: str, n: int) -> list[dict]:
    """The first move's σ from ``n`` posterior samples fitted to the calibration's frames, per axis.

    As ``plans.optimize.optimize_beam`` prints it where it is given the calibration's measurement
    (:func:`bluesky_offsets.model.fit.posterior_samples` with the demo's optimizer seed, then
    :func:`bluesky_offsets.optimize.optimizer.prediction_sigma` at the move's settings), and the
    samples' spread alone (:func:`~bluesky_offsets.optimize.optimizer.states_sigma`); against the
    widths measured after the move, with their own σ.  Kept in the run's folder
    (``focus_sigma_samples.json``).
    """
    kept = run / "focus_sigma_samples.json"
    if kept.exists() and (got := json.loads(kept.read_text()))["samples"] == n and "sigma" in got["rows"][0]:
        return [{**row, "run": label} for row in got["rows"]]
    rows = _sampled_move(run, n)
    kept.write_text(json.dumps({"samples": n, "rows": rows}))
    return [{**row, "run": label} for row in rows]


def demo_seed(run: Path) -> int:
    """The demo's ``--seed``: ``bench_demo.py``'s folders are named ``seedN``; else 0, the README's."""
    import re
    found = re.search(r"seed(\d+)$", run.name)
    return int(found.group(1)) if found else 0


def _sampled_move(run: Path, n: int) -> list[dict]:
    """:func:`sampled_move` measured."""
    import time

    from bluesky_offsets.model.fit import engine_for, posterior_samples
    from bluesky_offsets.optimize.optimizer import OptimizeOptions, prediction_sigma, states_sigma
    from bluesky_offsets.physics.parameters import METRIXS
    from bluesky_offsets.streams import stream
    from plans.optimize import _refit_options

    summary, cal, store, (meas, fit) = _calibrated(run)
    # the closed loop's refit options, the samples' (the demo's): one ray draw, under the calibration's spread
    o, _ = _refit_options(cal, fit.replace(ray_draws=1))
    opt = OptimizeOptions(seed=stream(demo_seed(run), "demo.beam_optimizer"))  # the demo's optimizer options
    t0 = time.perf_counter()
    samples = posterior_samples(meas, cal.state, engine_for(meas, o, METRIXS), o, n=n, seed=opt.seed)
    seconds = time.perf_counter() - t0
    step = summary["beam"]["steps"][0]
    settings = np.asarray(store[step["uid"]].metadata["start"]["settings"], float)
    spread = states_sigma(samples, settings, about=cal.state, seed=opt.check_seed)
    sigma = prediction_sigma(cal.state, settings, covariance=cal.covariance, names=cal.names, samples=samples,
                             options=opt)
    rows = []
    for a in "xy":
        p, m_ = 1e3 * step["predicted"][f"rms_{a}"], 1e3 * step["after"][f"rms_{a}"]
        rows.append({"axis": a, "predicted": p, "printed": 1e3 * step["predicted_sigma"][a],
                     "sampled": 1e3 * spread[a], "sigma": 1e3 * sigma[a], "measured": m_,
                     "measured_sigma": 1e3 * step["after"][f"sigma_rms_{a}"], "frames": meas.n, "seconds": seconds})
    return rows


def truth_check(run: Path, label: str) -> dict[str, dict]:
    """Per axis, the hidden truth's width at the first move's settings, with its own ray noise.

    Read as a frame is, from two traces of 200,000 rays.  Kept in the run's folder
    (``focus_sigma_truth.json``).
    """
    kept = run / "focus_sigma_truth.json"
    if kept.exists():
        return json.loads(kept.read_text())
    from bluesky_offsets.model.state import ModelState
    from bluesky_offsets.optimize.optimizer import predict
    from bluesky_offsets.optimize.targets import focus_from_profiles
    from bluesky_offsets.physics.parameters import METRIXS
    from bluesky_offsets.physics.twin import CAMERA

    summary, store = _opened(run)
    settings = np.asarray(store[summary["beam"]["steps"][0]["uid"]].metadata["start"]["settings"], float)
    true = ModelState(METRIXS.from_mapping(summary["hidden_offsets"], base=np.zeros(len(METRIXS))),
                      summary.get("hidden_effects") or {}, "hidden truth")

    def focus(state, rays, seed):
        _, px, py = predict(state, settings, rays=rays, seed=seed)
        return focus_from_profiles(px, py, CAMERA, n_rays=rays)

    truth = [focus(true, 200_000, s) for s in (99, 100)]
    got = {a: {"true": 1e3 * float(np.mean([getattr(f, f"rms_{a}") for f in truth])),
               "true_noise": 1e3 * getattr(truth[0], f"sigma_rms_{a}") / np.sqrt(2)} for a in "xy"}
    kept.write_text(json.dumps(got))
    return got


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", help="finished demos: folders with out/ and store/, each as DIR or LABEL=DIR")
    p.add_argument("--draws", type=int, default=0, help="states drawn from each calibration's covariance")
    p.add_argument("--samples", type=int, default=0,
                   help="posterior samples fitted to each calibration's frames: the first move's σ read from them")
    p.add_argument("--result", default="focus_sigma")
    p.add_argument("--title", default="The focus's σ against the focus measured")
    p.add_argument("--note", action="append", default=[])
    args = p.parse_args(argv)
    given = [(a.split("=", 1) if "=" in a else (Path(a).name, a)) for a in args.runs]
    runs = [(label, Path(d)) for label, d in given if (Path(d) / "out" / "summary.json").exists()]
    rows = [row for label, r in runs for row in moves(r, label)]
    if not rows:
        raise SystemExit("no finished demo with a beam optimization among the folders given")
    err = np.abs([r["error"] for r in rows])
    rel = np.array([r["sigma"] / r["predicted"] for r in rows])
    within = float(np.mean(err <= rel))
    for r in rows:
        print(f"{r['run']} move {r['move']} {r['axis']}: predicted {r['predicted']:.2f} ± {r['sigma']:.2f} µm, "
              f"measured {r['measured']:.2f} ({r['error']:+.1%})", flush=True)
    chis = []
    for label, r in runs if args.draws else []:
        c = drawn_chi2(r, label, args.draws)
        chis.append(c)
        print(f"{c['run']}: χ² {c['chi2']:.0f} on {c['dof']:.0f} dof; {args.draws} draws above it by "
              f"{c['above'][0]:.0f} … {c['above'][-1]:.0f} (the 95 % region: {c['region']:.1f})", flush=True)

    sampled = [row for label, r in runs if args.samples for row in sampled_move(r, label, args.samples)]
    checks = {label: truth_check(r, label) for label, r in runs if args.samples}
    for r in sampled:
        c = checks[r["run"]][r["axis"]]
        r["pull"] = abs(r["measured"] - r["predicted"]) / float(np.hypot(r["sigma"], r["measured_sigma"]))
        r["true"] = c["true"]
        r["pull_true"] = abs(r["true"] - r["predicted"]) / float(np.hypot(r["sigma"], c["true_noise"]))
        r["pull_true_samples"] = abs(r["true"] - r["predicted"]) / float(np.hypot(r["sampled"], c["true_noise"]))
    for r in sampled:
        print(f"{r['run']} move 1 {r['axis']}: predicted {r['predicted']:.2f} ± {r['sigma']:.2f} µm from "
              f"{args.samples} posterior samples (spread {r['sampled']:.2f}; printed then ± {r['printed']:.2f}), "
              f"measured {r['measured']:.2f} ± {r['measured_sigma']:.2f}: {r['pull']:.2f} σ; "
              f"the truth's {r['true']:.2f}: {r['pull_true']:.2f} σ",
              flush=True)

    from results import Table, write_result
    tables = [Table("Each move's predicted rms width, its printed σ (the calibration's) and the width measured after "
                    "the move", ("run", "move", "axis", "predicted (µm)", "σ (µm)", "measured (µm)",
                                 "measured / predicted − 1", "|measured − predicted| / σ"),
                    [(r["run"], r["move"], r["axis"], round(r["predicted"], 2), round(r["sigma"], 2),
                      round(r["measured"], 2), f"{r['error']:+.1%}", round(r["pull"], 3)) for r in rows])]
    if chis:
        tables.append(Table(f"{args.draws} states drawn from each calibration's covariance: their χ² on the "
                            "frames the analysis fitted, above the calibration's", (
                                "run", "frames", "dof", "χ² of the calibration", "above it: least",
                                "median", "most", "draws within the 95 % region"),
                            [(c["run"], c["frames"], round(c["dof"]), round(c["chi2"], 1), round(c["above"][0], 1),
                              round(float(np.median(c["above"])), 1), round(c["above"][-1], 1),
                              int(np.sum(np.asarray(c["above"]) <= c["region"]))) for c in chis]))
    if sampled:
        tables.append(Table(f"The first move's σ read from {args.samples} posterior samples fitted to the "
                            "calibration's frames (randomize-then-optimize), against the width measured after the move "
                            "with its own σ and the hidden truth's width there", (
                                "run", "axis", "predicted (µm)", "σ the demo printed (µm)", "the samples' spread (µm)",
                                "σ as printed now (µm)", "measured (µm)", "its σ (µm)",
                                "|measured − predicted| / both σ", "truth (µm)", "|truth − predicted| / σ",
                                "samples' time (s)"),
                            [(r["run"], r["axis"], round(r["predicted"], 2), round(r["printed"], 2),
                              round(r["sampled"], 2), round(r["sigma"], 2), round(r["measured"], 2),
                              round(r["measured_sigma"], 2), round(r["pull"], 2), round(r["true"], 2),
                              round(r["pull_true"], 2), round(r["seconds"])) for r in sampled]))
    summary = (f"Over {len(rows)} predicted widths ({len(rows) // 2} moves, {len(runs)} demos) the widths measured "
               f"after the move lay a median {np.median(err):.1%} (at most {err.max():.1%}) from the prediction, "
               f"while the printed σ was a median {np.median(rel):.0%} of it ({rel.min():.0%} to {rel.max():.0%}); "
               f"{within:.0%} of them within 1σ (a 1σ that holds covers 68 %).")
    if chis:
        above = np.concatenate([c["above"] for c in chis])
        inside = sum(int(np.sum(np.asarray(c["above"]) <= c["region"])) for c in chis)
        regions = sorted({round(c["region"]) for c in chis})
        summary += (f" Of the {len(above)} states drawn from the calibrations' covariances ({args.draws} each, as the "
                    f"optimizer draws them for its σ), {inside} fit the frames within their joint 95 % region of the "
                    f"calibration ({'–'.join(map(str, regions))} above its χ²); the median lay {np.median(above):,.0f} "
                    "above it.")
    if sampled:
        pulls = np.array([r["pull"] for r in sampled])
        rel_s = np.array([r["sigma"] / r["predicted"] for r in sampled])
        truth = np.array([r["pull_true"] for r in sampled])
        bare = np.array([r["pull_true_samples"] for r in sampled])
        summary += (f" As the optimizer prints it from {args.samples} posterior samples fitted to the frames (the larger "
                    f"of their spread and their covariance propagated, with the prediction's own ray noise), the first "
                    f"move's σ was a median {np.median(rel_s):.1%} of the width ({rel_s.min():.1%} to "
                    f"{rel_s.max():.1%}); with the measured width's own σ, {np.mean(pulls <= 1):.0%} of {len(pulls)} "
                    f"widths lay within 1σ and {np.mean(pulls <= 2):.0%} within 2σ (68 % and 95 % claimed), the "
                    f"farthest {pulls.max():.1f}σ. Against the hidden truth's width at the same settings: "
                    f"{np.mean(truth <= 1):.0%} within 1σ, {np.mean(truth <= 2):.0%} within 2σ, the farthest "
                    f"{truth.max():.1f}σ (the samples' spread alone: {np.mean(bare <= 1):.0%} and {np.mean(bare <= 2):.0%}).")
    write_result(args.result, title=args.title, summary=summary, tables=tables, notes=args.note,
                 data=[str(r) for _, r in runs])
    print(summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
