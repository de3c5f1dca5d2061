"""The main job's wall time and verdicts: ``bluesky-offsets demo`` over several draws (asked: a
median ≤ 180 s on 2 cores).

Each draw is the README's command with ``--seed S`` (hidden offsets in all 34 parameters within
±5 % and the candidate design drawn from S, the default hidden effect), run as a user runs it, one
after the other.  The table splits each run at the demo's own step lines: IOC start-up, beam
search and the designed frames, the analysis (compare, fit, diagnose, add, refit), the validation
frames, the beam optimization, the report; and gives each draw's frames, χ²/dof, validation and
fitted offsets against the hidden ones.

    python benchmarks/bench_demo.py [--seeds 0 1 2] [--threads N] [--out DIR] [--result NAME] [-- extra demo options]

With ``--result NAME`` the draws are written as ``benchmarks/results/NAME.json`` (other demo options,
say ``-- --effect none``: how often the verdict is right), not as the wall-time result.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

STEP = re.compile(r"^\s*(\d+) s  \[(\d)/(\d)\]")


def run(seed: int, out: Path, threads: int | None, extra: list[str]) -> dict:
    """One draw of the demo in ``out`` (kept: a draw already there is read, not run again)."""
    if not ((out / "out" / "summary.json").exists() and (out / "wall").exists()):
        exe = Path(sys.executable).parent / "bluesky-offsets"
        cmd = [str(exe), "demo", "--seed", str(seed), "--out", str(out / "out"), "--store", str(out / "store"),
               *(["--threads", str(threads)] if threads else []), *extra]
        t = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        (out / "log").write_text(proc.stdout + proc.stderr)
        if proc.returncode:
            raise SystemExit(f"seed {seed}: the demo failed ({proc.returncode}); its log: {out / 'log'}")
        (out / "wall").write_text(f"{time.perf_counter() - t:.1f}\n")
    return parse(seed, out)


def parse(seed: int, out: Path) -> dict:
    """A finished draw's step times, verdict, frames, χ²/dof, validation and offset classes."""
    log = (out / "log").read_text()
    steps = {}
    for line in log.splitlines():
        m = STEP.match(line)
        if m:
            steps[int(m.group(2))] = int(m.group(1))
    done = re.search(r"done in (\d+) s", log)
    wall = float((out / "wall").read_text())
    summary = json.loads((out / "out" / "summary.json").read_text())
    hist, val = summary.get("history") or [{}], summary.get("validation") or {}
    counts = (summary.get("offsets") or {}).get("counts", {})
    return {"seed": seed, "wall": wall, "done": int(done.group(1)) if done else float("nan"), "steps": steps,
            "verdict": summary.get("verdict", "?"), "frames": summary.get("frames"),
            "chi2": [hist[0].get("chi2_reduced"), hist[-1].get("chi2_reduced")],
            "validation_chi2": val.get("chi2_reduced"), "validation_passed": val.get("passed"),
            "offsets": [counts.get(k) for k in ("determined", "weak", "undetermined")],
            "first_move": _first_move(summary), **_against_truth(summary)}


def _first_move(summary: dict) -> list[float] | None:
    """The open loop: the first move's measured rms widths (x, y) over the hidden truth's best."""
    beam = summary.get("beam") or {}
    best, steps = beam.get("true_best"), beam.get("steps")
    if not (best and steps):
        return None
    return [steps[0]["after"][f"rms_{a}"] / best[f"rms_{a}"] for a in "xy"]


def _against_truth(summary: dict) -> dict:
    """The fitted offsets against the hidden ones (normalized): RMSE over the truth's RMS, the share
    within 2σ, and how many determined ones are within 2σ."""
    fitted, truth = (summary.get("offsets") or {}).get("offsets"), summary.get("hidden_offsets") or {}
    if not fitted:
        return {"rmse_ratio": None, "within_2sigma": None, "determined_right": None}
    t = np.array([truth.get(k, 0.0) for k in fitted])
    v = np.array([e["normalized"] for e in fitted.values()])
    sig = np.array([e["normalized_sigma"] for e in fitted.values()])
    det = np.array([e["class"] == "determined" for e in fitted.values()])
    near = np.abs(v - t) <= 2 * sig
    rms = float(np.sqrt(np.mean(t ** 2)))
    return {"rmse_ratio": float(np.sqrt(np.mean((v - t) ** 2))) / rms if rms > 0 else None,
            "within_2sigma": float(near.mean()), "determined_right": int((near & det).sum())}


def _medians(rows: list[dict]) -> str:
    """The offsets' and the validation's medians over the draws, as a sentence (empty without them)."""
    ratio = [r["rmse_ratio"] for r in rows if r["rmse_ratio"] is not None]
    val = [r["validation_chi2"] for r in rows if r["validation_chi2"] is not None]
    out = ""
    if ratio:
        out += (f" Offsets' RMSE / truth RMS: median {statistics.median(ratio):.2f}; within 2σ: median "
                f"{statistics.median(r['within_2sigma'] for r in rows if r['within_2sigma'] is not None):.2f}.")
    if val:
        out += f" Validation χ²/dof ≤ 1.3 in {sum(v <= 1.3 for v in val)} of {len(val)} draws."
    first = [r["first_move"] for r in rows if r.get("first_move")]
    if first:
        out += (f" The first move within 1.05 of the truth's best in x and y in {sum(max(f) <= 1.05 for f in first)}"
                f" of {len(first)} draws.")
    return out


def _fmt(x, f="{:.2f}") -> str:
    return "?" if x is None else f.format(x)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--threads", type=int, default=None, help="the demo's --threads (default: its own)")
    p.add_argument("--out", type=Path, default=None, help="keep each draw's output here")
    p.add_argument("--result", default="demo_wall_time",
                   help="the result's name (default %(default)s; another name for draws with other demo options)")
    p.add_argument("--title", default=None, help="the result's heading (default: the wall time's)")
    p.add_argument("--note", action="append", default=[], help="a note under the result's table (repeatable)")
    p.add_argument("extra", nargs="*", help="more demo options (after --)")
    a = p.parse_args()
    root = a.out or Path(tempfile.mkdtemp(prefix="bench-demo-"))
    rows = []
    for s in a.seeds:
        d = root / f"seed{s}"
        d.mkdir(parents=True, exist_ok=True)
        rows.append(run(s, d, a.threads, a.extra))
        print(f"seed {s}: {rows[-1]['done']} s", file=sys.stderr, flush=True)
    from render import section
    from results import Table, raw_path, write_result
    rows_out = []
    for r in rows:
        st, n = r["steps"], max(r["steps"]) if r["steps"] else 0
        marks = [st.get(k, float("nan")) for k in range(1, n + 1)] + [r["done"]]
        parts = [b - a for a, b in zip(marks, marks[1:])]
        parts = (parts + [float("nan")] * 6)[:6]
        if n == 5:  # --no-optimize: no beam step
            parts = parts[:4] + [float("nan"), parts[4]]
        # a step the demo did not take (no beam optimization: --no-optimize, a described beamline) is a dash
        rows_out.append([r["seed"], f"{r['done']} s", *("—" if math.isnan(x) else f"{x:.0f} s" for x in parts), r["frames"],
                         f"{_fmt(r['chi2'][0])} → {_fmt(r['chi2'][1])}", _fmt(r["validation_chi2"]),
                         " / ".join(_fmt(c, "{}") for c in r["offsets"]), _fmt(r["determined_right"], "{}"),
                         _fmt(r["rmse_ratio"]), _fmt(r["within_2sigma"]),
                         "—" if not r.get("first_move") else " / ".join(_fmt(f) for f in r["first_move"]),
                         r["verdict"]])
    cmd = " ".join(["bluesky-offsets demo --seed S", *([f"--threads {a.threads}"] if a.threads else []), *a.extra])
    median = statistics.median(r["done"] for r in rows)
    verdicts = collections.Counter(r["verdict"].split(" (")[0].split(";")[0] for r in rows)
    tally = "; ".join(f"{v}: {n} of {len(rows)}" for v, n in verdicts.most_common())
    table = Table(f"{len(rows)} draws, one after the other (`{cmd}`):",
                  ["seed", "wall", "IOC up", "beam found + designed frames", "analysis", "validation",
                   "beam optimized", "report", "frames", "χ²/dof: bare → final", "validation χ²/dof",
                   "offsets determined / weak / undetermined", "determined within 2σ of the truth",
                   "offsets' RMSE / truth RMS", "offsets within 2σ", "first move / truth's best (x / y)", "verdict"],
                  rows_out, align=["r"] * 16 + ["l"])
    raw = raw_path(f"{a.result}.json")
    raw.write_text(json.dumps(rows, indent=1, default=str) + "\n")
    what = "The demo" if a.extra else "The README's main job"
    summary = (f"{what} (`{cmd}`) over several draws, one after the other, each split at the "
               f"demo's own step lines (asked: a median ≤ 180 s on 2 cores). **Median {median:.0f} s over {len(rows)} "
               f"draw{'s' * (len(rows) != 1)}** on this machine; "
               f"verdicts: {tally}.{_medians(rows)}")
    result = write_result(a.result, title=a.title or "The main job's wall time", tables=[table], summary=summary,
                          notes=a.note, data=[str(raw)])
    print(section(result))


if __name__ == "__main__":
    main()
