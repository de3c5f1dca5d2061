"""What a demo's frames determine about the offsets, against what its calibration reports.

For finished demo runs (each a ``bench_demo.py --out`` draw: ``out/summary.json``,
``out/calibration.json``, ``store``): the Fisher information of the frames the run measured,
computed at the hidden truth (offsets, and the chamber's hidden shift added to the stage's
position) with the twin's exact Jacobian on two independent ray sets (unbiased), at the frames'
photons N and the fit's model rays K (:func:`bluesky_offsets.design.frame_information`); the
offsets it determines (σ below a tenth of the prior's) beside those the calibration reports; the
reported σ over that Fisher σ; and the offsets' errors in both σ.  The count from the Fisher
matrix is the most those frames can determine: the design's part of the gap to the ceiling
(``bench_design_ceiling.py``) is what the frames lack, the analysis's part what the report lacks.

    python benchmarks/bench_design_gap.py RUN [RUN ...] [--rays 8000] [--photons 5000] [--model-rays 2000]

The result goes to ``benchmarks/results/design_gap.json``, the rows beside it.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bluesky_offsets.design import classes, frame_information, predicted_sigma, prior_precision  # noqa: E402
from bench_design_ceiling import least_rmse  # noqa: E402
from bluesky_offsets.model.posterior import PRIOR_SIGMA  # noqa: E402
from bluesky_offsets.design.information import HALF_SEED, positive_part  # noqa: E402
from bluesky_offsets.physics.engine import TorchEngine  # noqa: E402
from bluesky_offsets.physics.parameters import METRIXS as T  # noqa: E402
from bluesky_offsets.store import open_store  # noqa: E402

CLASSES = ("determined", "weak", "undetermined")


def frames_fisher(run: Path, s: dict, rays: int, photons: int, model_rays: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The Fisher matrix of ``run``'s measured frames at its hidden truth, the truth, and the frames' count.

    ``s``: the run's ``summary.json``.
    """
    truth = np.array([s["hidden_offsets"][n] for n in T.names])
    shift = np.array([s["hidden_effects"].get(f"chamber_{a}", {}).get(a, 0.0) for a in "xyz"])
    m = open_store(str(run / "store")).load_measurement(s["uids"]["measurement"])
    screen = (np.zeros((m.n, 3)) if m.screen is None else np.asarray(m.screen, float)) + shift
    engine = TorchEngine(options={"common_rays": False})
    halves = [frame_information(engine, m.configurations, truth, photons=photons, model_rays=model_rays, rays=rays,
                                screen=screen, seed=seed, psd=False).fisher.sum(0) for seed in (11, 11 + HALF_SEED)]
    return positive_part(0.5 * (halves[0] + halves[1])), truth, m.n


def row(run: Path, a) -> dict:
    """One run's counts, σ ratio and pulls."""
    t0 = time.perf_counter()
    s = json.loads((run / "out" / "summary.json").read_text())
    fisher, truth, n = frames_fisher(run, s, a.rays, a.photons, a.model_rays)
    sig_f = predicted_sigma(prior_precision(len(T)) + fisher)
    cal = json.loads((run / "out" / "calibration.json").read_text())["offsets"]
    value = np.array([cal[name]["normalized"] for name in T.names])
    sig_r = np.array([cal[name]["normalized_sigma"] for name in T.names])
    err = value - truth
    # the report's classes read against the table's prior whatever spread its σ are under
    cf, cr = classes(sig_f), [cal[name]["class"] for name in T.names]
    return {"run": str(run), "frames": n, "fisher": {c: cf.count(c) for c in CLASSES},
            "reported": {c: cr.count(c) for c in CLASSES},
            "sigma_ratio": [float(q) for q in np.percentile(sig_r / sig_f, [25, 50, 75])],
            "pull_reported": float(np.sqrt(np.mean((err / sig_r) ** 2))),
            "pull_fisher": float(np.sqrt(np.mean((err / sig_f) ** 2))),
            "rmse_ratio": float(np.sqrt(np.mean(err ** 2)) / np.sqrt(np.mean(truth ** 2))),
            "fisher_rmse_ratio": float(np.sqrt(np.mean(sig_f ** 2)) / np.sqrt(np.mean(truth ** 2))),
            "least_rmse_ratio": least_rmse(fisher, s["offsets_fraction"]),
            "seconds": time.perf_counter() - t0}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", type=Path, nargs="+", help="finished demo draws (bench_demo.py --out DIR/seedS)")
    p.add_argument("--rays", type=int, default=8000, help="model rays per frame's Jacobian (two sets of half)")
    p.add_argument("--photons", type=int, default=5000, help="photons a frame (the demo's IOC: 5,000)")
    p.add_argument("--model-rays", type=int, default=2000, help="model rays a fit traces per frame")
    a = p.parse_args()
    rows = []
    for run in a.runs:
        rows.append(row(run, a))
        r = rows[-1]
        print(f"{run}: {r['frames']} frames; Fisher at the truth {r['fisher']}, reported {r['reported']}; "
              f"σ reported / Fisher {r['sigma_ratio'][1]:.2f}; pulls {r['pull_reported']:.2f} (reported σ), "
              f"{r['pull_fisher']:.2f} (Fisher σ); {r['seconds']:.0f} s", flush=True)
    write(rows, a)


def write(rows: list[dict], a) -> None:
    """The result ``design_gap``."""
    from render import section
    from results import Table, raw_path, write_result
    raw = raw_path("design_gap.json")
    raw.write_text(json.dumps({"args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()
                                        if k != "runs"}, "rows": rows}, indent=1, default=str) + "\n")
    cells = [[Path(r["run"]).parent.name + "/" + Path(r["run"]).name, r["frames"],
              " / ".join(str(r["fisher"][c]) for c in CLASSES), " / ".join(str(r["reported"][c]) for c in CLASSES),
              "{:.2f} ({:.2f}–{:.2f})".format(r["sigma_ratio"][1], r["sigma_ratio"][0], r["sigma_ratio"][2]),
              f"{r['pull_reported']:.2f}", f"{r['pull_fisher']:.2f}", f"{r['rmse_ratio']:.2f}",
              f"{r['fisher_rmse_ratio']:.2f}", f"{r['least_rmse_ratio']:.2f}"] for r in rows]
    table = Table("Each run (determined / weak / undetermined, of 34):",
                  ["run", "designed frames", "the frames at the truth (Fisher)", "the calibration reports",
                   "reported σ / Fisher σ: median (quartiles)", "errors' RMS in reported σ", "in Fisher σ",
                   "offsets' RMSE / truth RMS", "Fisher σ's RMS / truth RMS", "least RMSE / truth RMS"], cells,
                  align=["l"] + ["r"] * 9)
    med = statistics.median
    summary = (f"What the frames of {len(rows)} demo runs determine about the offsets, computed at the hidden truth "
               f"(the twin's exact Jacobian on two independent ray sets, {a.photons:,} photons a frame and "
               f"{a.model_rays:,} model rays a fit traces for it), against what each calibration reports; the prior "
               f"σ is {PRIOR_SIGMA:.4f} of each range. Median determined: the frames "
               f"{med(r['fisher']['determined'] for r in rows):g}, the report "
               f"{med(r['reported']['determined'] for r in rows):g}; the reported σ a median "
               f"{med(r['sigma_ratio'][1] for r in rows):.2f} of the Fisher σ; the errors' RMS "
               f"{med(r['pull_fisher'] for r in rows):.2f} Fisher σ and "
               f"{med(r['pull_reported'] for r in rows):.2f} reported σ (medians). The least RMSE any estimator "
               f"can expect from the frames (the linear-Gaussian posterior under the draw's own spread as prior): a "
               f"median {med(r['least_rmse_ratio'] for r in rows):.2f} of the truth's RMS; the calibrations' "
               f"{med(r['rmse_ratio'] for r in rows):.2f}.")
    result = write_result("design_gap", title="The designed measurement: what its frames determine",
                          tables=[table], summary=summary, data=[str(raw)])
    print(section(result))


if __name__ == "__main__":
    main()
