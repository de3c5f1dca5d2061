"""The calibration with realistic motors against perfect ones, on the same draws.

Each draw runs the README's main job (``bluesky-offsets demo --seed S``) twice: with perfect
simulated motors and with ``--motors realistic`` (every axis read by an encoder with noise, with
backlash taken out by ``BDST`` and retries within ``RDBD``: ``sim_iocs.metrixs.motor_profile``).
Per run: the offsets' RMSE against the hidden truth over the truth's own RMS (normalized), the
share of offsets within 2σ of the truth, the hidden effect's fitted value, the focus reached.

    python benchmarks/bench_motors.py [--seeds 3 4] [--out DIR] [-- extra demo options]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine  # noqa: E402

PROFILES = ("perfect", "realistic")


def run(seed: int, label: str, options: list[str], out: Path, extra: list[str]) -> dict:
    """``bluesky-offsets demo --seed S OPTIONS`` into ``out`` (read back when it finished before), scored."""
    out.mkdir(parents=True, exist_ok=True)
    summary = out / "out" / "summary.json"
    if not summary.exists():  # resumable: a finished draw is read back
        exe = Path(sys.executable).parent / "bluesky-offsets"
        cmd = [str(exe), "demo", "--seed", str(seed), *options, "--out", str(out / "out"),
               "--store", str(out / "store"), *extra]
        t = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        (out / "log").write_text(proc.stdout + proc.stderr + f"\nwall {time.perf_counter() - t:.0f} s\n")
        if proc.returncode:
            raise SystemExit(f"seed {seed}, {label}: the demo failed ({proc.returncode}); log: {out / 'log'}")
    return score(json.loads(summary.read_text()), seed, label)


def score(s: dict, seed: int, label: str) -> dict:
    post = s["offsets"]["offsets"]
    names = list(post)
    truth = np.array([s["hidden_offsets"].get(n, 0.0) for n in names])
    fitted = np.array([post[n]["normalized"] for n in names])
    sigma = np.array([post[n]["normalized_sigma"] for n in names])
    err = fitted - truth
    beam = s.get("beam") or {}
    return {"seed": seed, "run": label, "seconds": s["seconds"],
            "rmse_over_rms": float(np.sqrt(np.mean(err ** 2)) / np.sqrt(np.mean(truth ** 2))),
            "within_2sigma": float(np.mean(np.abs(err) <= 2 * sigma)),
            "hidden_effects": s["hidden_effects"], "fitted_effects": s["fitted_effects"],
            "focus_um": [1e3 * beam["after"]["rms_x"], 1e3 * beam["after"]["rms_y"]] if beam else None,
            "focus_over_best": ([beam["after"]["rms_x"] / beam["true_best"]["rms_x"],
                                 beam["after"]["rms_y"] / beam["true_best"]["rms_y"]]
                                if beam and beam.get("true_best") else None),
            "validation_chi2": (s.get("validation") or {}).get("chi2_reduced"),
            "verdict": s["verdict"]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[3, 4])
    p.add_argument("--out", type=Path, default=None, help="keep (and resume) each run's output here")
    p.add_argument("extra", nargs="*", help="more demo options (after --)")
    a = p.parse_args()
    compare(a, "motors", {m: ["--motors", m] for m in PROFILES})


def compare(a, name: str, runs: dict[str, list[str]]) -> None:
    """Each seed of ``a.seeds`` with each of ``runs`` (label: demo options); a line each, then the
    rows in ``benchmarks/results/raw/<name>_seeds<S...>.json`` and the result ``<name>.json``."""
    root = a.out or Path(tempfile.mkdtemp(prefix=f"bench-{name}-"))
    rows = []
    for seed in a.seeds:
        for label, options in runs.items():
            r = run(seed, label, options, root / f"seed{seed}-{label}", a.extra)
            rows.append(r)
            eff = _effects(r)
            focus = "-" if r["focus_um"] is None else (f"{r['focus_um'][0]:.1f} x {r['focus_um'][1]:.1f} µm (best x "
                                                      f"{r['focus_over_best'][0]:.2f}, {r['focus_over_best'][1]:.2f})")
            print(f"seed {seed:3d} {label:10s} RMSE/RMS {r['rmse_over_rms']:.2f}  within 2σ "
                  f"{r['within_2sigma']:.2f}  effects: {eff}  focus {focus}  {r['seconds']:.0f} s", flush=True)
    from results import raw_path
    res = raw_path(f"{name}_seeds{'-'.join(map(str, a.seeds))}.json")
    res.write_text(json.dumps({"machine": machine(), "command": " ".join(sys.argv), "rows": rows}, indent=1))
    print(f"written: {res}")
    write(name, rows, res)


# each comparison's result: its heading, the column that names a run's setting, what it measures
PAGES = {
    "motors": ("Motors as they move (issue 52)", "motors",
               "Realistic motors against perfect ones: the README's main job (`bluesky-offsets demo --seed S`) with "
               "and without `--motors realistic` (every axis read by an encoder with noise, backlash taken out by "
               "`BDST`, retries within `RDBD`: `sim_iocs.metrixs.motor_profile`); per run the offsets' RMSE against "
               "the hidden truth over the truth's own RMS, the share within 2σ, the hidden effect's fitted value, the "
               "focus reached."),
    "camera": ("The focus chamber as a camera (issue 52)", "detector",
               "The README's main job read through the simulated camera (`bluesky-offsets demo --detector camera`: "
               "the areaDetector's frames, dark frames, the gain by photon transfer where the measurement was "
               "brightest, frames reduced to the same histograms with the camera's own noise beside them) against "
               "the simulator's histogram PVs, on the same draws; scored as \"Motors as they move\"."),
}


def _effects(r: dict) -> str:
    return "; ".join(f"{e} {', '.join(f'{k} {v[0]:.3g} ± {v[1]:.2g}' for k, v in d.items())}"
                     for e, d in r["fitted_effects"].items()) or "none"


def write(name: str, rows: list[dict], raw: Path) -> None:
    """The result ``<name>``: one row per draw and setting."""
    from render import section
    from results import Table, write_result
    title, column, summary = PAGES.get(name, (name, "run", f"The README's main job, {name}."))
    table = Table("Each draw with each setting:",
                  ["seed", column, "offsets RMSE / truth RMS", "within 2σ", "effects fitted", "focus after (µm)",
                   "over the truth's best (x, y)", "validation χ²/dof", "seconds"],
                  [[r["seed"], r["run"], f"{r['rmse_over_rms']:.2f}", f"{r['within_2sigma']:.2f}", _effects(r),
                    "—" if r["focus_um"] is None else f"{r['focus_um'][0]:.1f} × {r['focus_um'][1]:.1f}",
                    "—" if r["focus_over_best"] is None else
                    f"{r['focus_over_best'][0]:.2f}, {r['focus_over_best'][1]:.2f}",
                    "—" if r["validation_chi2"] is None else f"{r['validation_chi2']:.2f}", f"{r['seconds']:.0f}"]
                   for r in rows], align=["r", "l", "r", "r", "l", "r", "r", "r", "r"])
    print(section(write_result(name, title=title, summary=summary, tables=[table], data=[str(raw)])))


if __name__ == "__main__":
    main()
