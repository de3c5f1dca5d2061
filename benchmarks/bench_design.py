"""The designed measurement against the bright one: do the fitted offsets find the truth?

Each draw hides offsets in all 34 parameters (uniform within ±``--fraction`` of each range) and,
optionally, effects; the frames are RAYX's at the hidden truth (``--photons`` source photons a
frame, fresh noise), the beam is found from the motors' start by the real search
(:func:`bluesky_offsets.offsets.beam_search.search`, driven with those frames), then

* ``optimal``: the designed measurement (:mod:`bluesky_offsets.design`: candidates, information
  from the twin's exact Jacobian, the batch the criterion prefers, the offsets refitted between
  batches) until ``--frames`` frames in all;
* ``bright``: today's design (:func:`plans.workflow.measure_bright`'s: bright configurations around
  the beam, some again with the slits open), the same budget of frames for the fit when
  ``--same-frames``, else its 16 + 4;

and the offsets are fitted once more in full (:data:`bluesky_offsets.model.diagnosis.FIT`).  Per
draw: the offsets' RMSE over the truth's RMS, the share within 2σ, the determined ones (σ below a
tenth of the prior's) and the share of those within 2σ, offsets at a bound, each batch's record
(its predicted determined count is judged on the rays that chose it: optimistic; the ceiling is
``bench_design_ceiling.py``), frames, seconds.

    python benchmarks/bench_design.py --seeds 0 1 2 --fraction 0.05 [--design optimal bright]
        [--frames 60] [--photons 5000] [--criterion D] [--out FILE]

The draws go to ``--out`` (default ``benchmarks/results/raw/design_<pct>pct_seeds<A>-<B>.json``), the
result to ``benchmarks/results/design_<pct>pct.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine  # noqa: E402

from bluesky_offsets.design import DesignOptions  # noqa: E402
from bluesky_offsets.design.sequence import DesignLoop  # noqa: E402
from bluesky_offsets.model import diagnosis as D  # noqa: E402
from bluesky_offsets.model.fit import engine_for, fit  # noqa: E402
from bluesky_offsets.model.measurement import Measurement  # noqa: E402
from bluesky_offsets.model.posterior import Posterior  # noqa: E402
from bluesky_offsets.model.state import CalibratedState, ModelState  # noqa: E402
from bluesky_offsets.offsets.beam_search import acceptance, intensity, search  # noqa: E402
from bluesky_offsets.physics import effects as E  # noqa: E402
from bluesky_offsets.physics.parameters import MAX_OFFSET, METRIXS as T, at_offset_bound  # noqa: E402
from bluesky_offsets.physics.screen import per_frame_overrides  # noqa: E402
from bluesky_offsets.physics.engine import TorchEngine  # noqa: E402
from bluesky_offsets.physics.twin import CAMERA, HistogramSpec, RayxEngine, Twin  # noqa: E402
from plans import HIGH_RAY_THRESHOLD  # noqa: E402
from sim_iocs.truth import default_start  # noqa: E402

PRIOR = MAX_OFFSET / math.sqrt(3.0)


class Beamline:
    """RAYX at a hidden truth: frames at settings (configurations and stage positions)."""

    def __init__(self, offsets, overrides, photons: int, seed: int):
        self.offsets, self.overrides, self.photons = offsets, overrides, photons
        self.twin = Twin(RayxEngine(hist=CAMERA), scheduler="inline")
        self.rng = np.random.default_rng([seed, 31])
        self.frames = 0

    def measure(self, cfg, screen=None) -> Measurement:
        cfg = np.atleast_2d(cfg)
        vals = T.model_values(cfg, self.offsets)
        ov = per_frame_overrides(self.overrides or None, screen, len(cfg))
        seeds = [int(s) for s in self.rng.integers(2 ** 31, size=len(cfg))]
        r = self.twin.trace_batch(vals, overrides=ov, n_rays=self.photons, seed=seeds, progress=False)
        self.frames += len(cfg)
        return Measurement(cfg, r.hist_x, r.hist_y, n_rays=self.photons, spec=CAMERA, screen=screen)


def paper_intensity(m: Measurement) -> np.ndarray:
    hx, hy = m.spec.rebin(m.hist_x, m.hist_y, HistogramSpec())
    return intensity(hx, hy)


def find_beam(bl: Beamline, start, fraction=0.15):
    tw = Twin(TorchEngine())
    widths = acceptance(tw, start, open_slits=True), acceptance(tw, start, open_slits=False)
    gen = search(start, *widths, fraction=fraction, threshold=HIGH_RAY_THRESHOLD, max_frames=120)
    try:
        cfgs = next(gen)
        while True:
            cfgs = gen.send(paper_intensity(bl.measure(cfgs)))
    except StopIteration as stop:
        return stop.value


def designed(bl: Beamline, beam, opts: DesignOptions, log) -> tuple[Measurement, np.ndarray, list]:
    """The plan's loop (bluesky_offsets.design.sequence.DesignLoop) with RAYX's frames at the truth."""
    loop = DesignLoop(opts, beam.configuration, opts.frames - beam.frames, bl.photons)
    meas = bl.measure(beam.configuration[None], np.zeros((1, 3)))
    while (got := loop.step(meas)) is not None:
        st, row = got
        meas = meas.joined(bl.measure(st.configurations, st.screen))
        log(f"    step {st.step}: {meas.n} frames ({bl.frames} with the search), {st.allowed}/{st.candidates} "
            f"candidates allowed, {st.seconds:.0f} s to design, determined before {row['measured_determined']} "
            f"(predicted after {st.n_determined}), update chi2/dof {row['update_chi2_reduced']:.2f}"
            f"{' (also from a global start)' if row['global_start'] else ''}")
    steps = [{k: v for k, v in r.items() if not isinstance(v, np.ndarray)} for r in loop.steps]
    return meas, loop.offsets, steps


def bright_design(bl: Beamline, beam, seed: int) -> Measurement:
    from plans.workflow import MeasurementDesign, candidate_configurations, measurement_design
    design = MeasurementDesign(seed=seed)
    cand = candidate_configurations(design, beam.configuration)
    m = bl.measure(cand)
    found = cand[paper_intensity(m) > HIGH_RAY_THRESHOLD][:design.bright]
    cfgs, idx = measurement_design(design, found)
    return bl.measure(cfgs).subset(idx)


def metrics(truth, fitres) -> dict:
    est, sig = fitres.state.offsets, fitres.offset_sigma
    err = est - truth
    rms = float(np.sqrt(np.mean(truth ** 2)))
    # the classes as the report reads them: against the table's prior, whatever spread the fit held
    post = Posterior.of(CalibratedState(fitres.state, fitres.covariance, tuple(fitres.names),
                                        prior_sigma=fitres.prior_sigma))
    cls = [e.cls for e in post.offsets]
    det = np.array([c == "determined" for c in cls])
    within = np.abs(err) <= 2 * sig
    at_bound = at_offset_bound(est)
    return {"rmse_over_rms": float(np.sqrt(np.mean(err ** 2)) / rms), "within_2sigma": float(within.mean()),
            "determined": int(det.sum()), "weak": cls.count("weak"), "undetermined": cls.count("undetermined"),
            "determined_within_2sigma": float(within[det].mean()) if det.any() else float("nan"),
            "determined_rmse_over_rms": float(np.sqrt(np.mean(err[det] ** 2)) / rms) if det.any() else float("nan"),
            "at_bound": int(at_bound.sum()), "at_bound_truth_far": int((at_bound & ~within).sum()),
            "chi2_reduced": float(fitres.chi2_reduced), "spread": fitres.prior_sigma or PRIOR}


def one(seed: int, how: str, a, log) -> dict:
    rng = np.random.default_rng([seed, 17])
    truth = rng.uniform(-a.fraction, a.fraction, len(T))
    hidden = dict(a.effects)
    overrides = E.twin_overrides(hidden) if hidden else {}
    bl = Beamline(truth, overrides, a.photons, seed)
    t0 = time.perf_counter()
    beam = find_beam(bl, default_start())
    log(f"  seed {seed} {how}: beam found in {beam.frames} frames ({beam.intensity:.3g})")
    if not beam.bright:  # as plans.design.measure_designed: nothing to calibrate on
        log(f"  seed {seed} {how}: the beam search ended dim; no calibration")
        return {"seed": seed, "design": how, "dark": True, "beam_search_frames": beam.frames}
    opts = DesignOptions(frames=a.frames, batch=a.batch, criterion=a.criterion, seed=seed,
                         candidates=a.candidates, rays=a.rays, fit_rays=a.fit_rays)
    steps: list = []
    if how == "optimal":
        meas, start, steps = designed(bl, beam, opts, log)
    else:
        meas, start = bright_design(bl, beam, seed), np.zeros(len(T))
    t1 = time.perf_counter()
    # as the analysis fits the offsets: from the design's estimate and from the bare twin, the end
    # lowest on fresh rays kept, the other's end widening the covariance where the frames do not
    # tell them apart (bluesky_offsets.model.fit.fit)
    fo = (D.FIT if how == "bright" else D.FIT.replace(rays=a.analysis_rays)).replace(seed=seed)
    res = fit(meas, ModelState(start.copy()), engine_for(meas, fo), fo, also_from=[ModelState()] if start.any() else [])
    out = {"seed": seed, "design": how, "frames_total": bl.frames, "frames_fitted": meas.n,
           "beam_search_frames": beam.frames, **metrics(truth, res), "seconds_measure_design": t1 - t0,
           "seconds_final_fit": time.perf_counter() - t1, "steps": steps,
           "truth": truth.tolist(), "fitted": res.state.offsets.tolist(), "sigma": res.offset_sigma.tolist()}
    log(f"  seed {seed} {how}: RMSE/RMS {out['rmse_over_rms']:.2f}, within 2 sigma {out['within_2sigma']:.2f}, "
        f"determined {out['determined']} ({out['determined_within_2sigma']:.2f} within 2 sigma), at bound "
        f"{out['at_bound']}, chi2/dof {out['chi2_reduced']:.2f}, {meas.n} frames fitted of {bl.frames}, "
        f"{t1 - t0:.0f} + {out['seconds_final_fit']:.0f} s")
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--fraction", type=float, default=0.05)
    p.add_argument("--design", nargs="+", default=["optimal", "bright"])
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--candidates", type=int, default=DesignOptions.candidates)
    p.add_argument("--rays", type=int, default=DesignOptions.rays)
    p.add_argument("--fit-rays", type=int, default=DesignOptions.fit_rays)
    p.add_argument("--analysis-rays", type=int, default=2000, help="model rays per frame of the final fit "
                   "(designed; the bright design's is the analysis's 5000)")
    p.add_argument("--photons", type=int, default=5000)
    p.add_argument("--criterion", default="D")
    p.add_argument("--effect", action="append", default=[], help="NAME:PARAM=VALUE (hidden effect)")
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args()
    if a.out is None:  # the draws' record beside the result
        from results import raw_path
        a.out = raw_path(f"design_{round(100 * a.fraction, 6):g}pct_seeds{min(a.seeds)}-{max(a.seeds)}.json")
    a.effects = []
    for text in a.effect:
        name, _, rest = text.partition(":")
        a.effects.append((name, {k: float(v) for k, v in (i.split("=") for i in rest.split(",") if i)}))
    rows = []

    def log(text):
        print(text, flush=True)
    for seed in a.seeds:
        for how in a.design:
            rows.append(one(seed, how, a, log))
            # after every draw: an interrupted run keeps what it measured
            a.out.parent.mkdir(parents=True, exist_ok=True)
            a.out.write_text(json.dumps({"machine": machine(), "args": {k: v for k, v in vars(a).items()
                                                                         if k != "out"},
                                         "rows": rows}, indent=1, default=str))
    for how in a.design:
        r = [x for x in rows if x["design"] == how and not x.get("dark")]
        if not r:
            continue
        med = {k: statistics.median(x[k] for x in r) for k in ("rmse_over_rms", "within_2sigma", "determined",
                                                                "determined_within_2sigma", "frames_total")}
        print(f"{how}: median over {len(r)} draws: " + ", ".join(f"{k} {v:.3g}" for k, v in med.items()))
    write(rows, a)


def _row(x: dict, pct: float) -> list:
    """One draw as the page's table shows it."""
    label = f"±{pct:g} %, seed {x['seed']}"
    if x.get("dark"):
        return [label, x["design"], "dark: the beam search ended dim, no calibration"] + [""] * 7
    det, far = x["determined"], x["at_bound_truth_far"]
    n_det = round(det * x["determined_within_2sigma"]) if det else 0
    frames = f"{x['beam_search_frames']} + {x['frames_fitted']}"
    glob = "—"
    if x["design"] == "optimal":
        glob = "yes" if any(st.get("global_start") for st in x["steps"]) else "no"
    else:
        frames += f" (of {x['frames_total']})"
    return [label, x["design"], f"{x['rmse_over_rms']:.2f}", f"{x['within_2sigma']:.2f}",
            f"{det} ({n_det})" if det else "0", f"{x['at_bound']} ({far})" if x["at_bound"] else "0",
            f"{x['chi2_reduced']:.2f}", frames, glob, f"{x['seconds_measure_design']:.0f} + {x['seconds_final_fit']:.0f}"]


def _medians(rows: list, pct: float) -> list:
    """Per design: the medians (and ranges) over the draws that were calibrated."""
    out = []
    for how in dict.fromkeys(x["design"] for x in rows):
        r = [x for x in rows if x["design"] == how and not x.get("dark")]
        if not r:
            continue

        def m(k, spec=".2f"):
            v = [x[k] for x in r]
            return f"{statistics.median(v):{spec}} ({min(v):{spec}}–{max(v):{spec}})"
        n_det = sum(x["determined"] for x in r)
        n_in = sum(round(x["determined"] * x["determined_within_2sigma"]) for x in r if x["determined"])
        out.append([f"±{pct:g} %", how, len(r), m("rmse_over_rms"), m("within_2sigma"),
                    f"{m('determined', 'g')}; {n_in} of {n_det} within 2σ", m("chi2_reduced")])
    return out


def write(rows: list, a) -> None:
    """The result ``design_<pct>pct``: every draw and the medians."""
    from render import section
    from results import Table, write_result
    pct = round(100 * a.fraction, 6)
    table = Table("Every draw (\"global start\": an update also ran from the prior-wide search, the model being dark "
                  "where the beamline was lit):",
                  ["draws", "design", "RMSE / truth RMS", "within 2σ", "determined (within 2σ)",
                   "at a bound (truth > 2σ away)", "fit χ²/dof", "frames: search + fitted", "global start",
                   "seconds: measure + fit"], [_row(x, pct) for x in rows])
    medians = Table("Medians (range) over the calibrated draws:",
                    ["offsets drawn", "design", "draws", "RMSE / truth RMS", "within 2σ", "determined", "fit χ²/dof"],
                    _medians(rows, pct))
    result = write_result(
        f"design_{pct:g}pct", title="The designed measurement" + (f" at ±{pct:g} %" if pct != 5 else ""),
        tables=[table, medians], data=[str(a.out)],
        summary=f"Does the designed measurement bring the fitted offsets to the truth, with hidden offsets within "
                f"±{pct:g} %? RAYX frames at the hidden truth, {a.photons:,} photons a frame, the beam found by the "
                f"real search, then {a.frames} frames in all designed (optimal) or the bright design's frames "
                "(bright), and the offsets fitted in full as the analysis fits them (method: docs/explanations/offsets.md). "
                "Determined: σ below a tenth of the prior's.")
    print(section(result))


if __name__ == "__main__":
    main()
