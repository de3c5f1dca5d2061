"""The main job's wall time: ``bluesky-offsets demo`` over several draws (issue 17's benchmark:
median under 90 s on 2 cores over 3 draws).

Each draw is the README's command with ``--seed S`` (hidden offsets in all 34 parameters within
±5 % and the candidate design drawn from S, the default hidden effect), run as a user runs it, one
after the other.  The table splits each run at the demo's own step lines: IOC start-up, beam
search and measurement, the surrogate finder, the analysis (compare, fit, diagnose, add, refit),
the beam optimization, the report.

    python benchmarks/bench_demo.py [--seeds 0 1 2] [--threads N] [--out DIR] [-- extra demo options]
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

STEP = re.compile(r"^\s*(\d+) s  \[(\d)/(\d)\]")


def run(seed: int, out: Path, threads: int | None, extra: list[str]) -> dict:
    exe = Path(sys.executable).parent / "bluesky-offsets"
    cmd = [str(exe), "demo", "--seed", str(seed), "--out", str(out / "out"), "--store", str(out / "store"),
           *(["--threads", str(threads)] if threads else []), *extra]
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    (out / "log").write_text(proc.stdout + proc.stderr)
    if proc.returncode:
        raise SystemExit(f"seed {seed}: the demo failed ({proc.returncode}); its log: {out / 'log'}")
    steps = {}
    for line in proc.stdout.splitlines():
        m = STEP.match(line)
        if m:
            steps[int(m.group(2))] = int(m.group(1))
    done = re.search(r"done in (\d+) s", proc.stdout)
    summary = json.loads((out / "out" / "summary.json").read_text())
    return {"seed": seed, "wall": wall, "done": int(done.group(1)) if done else float("nan"), "steps": steps,
            "verdict": summary.get("verdict", "?")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--threads", type=int, default=None, help="the demo's --threads (default: its own)")
    p.add_argument("--out", type=Path, default=None, help="keep each draw's output here")
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
    from results import Table, write_result
    rows_out = []
    for r in rows:
        st, n = r["steps"], max(r["steps"]) if r["steps"] else 0
        marks = [st.get(k, float("nan")) for k in range(1, n + 1)] + [r["done"]]
        parts = [b - a for a, b in zip(marks, marks[1:])]
        parts += [float("nan")] * (6 - len(parts))
        if n == 5:  # --no-optimize: no beam step
            parts = parts[:4] + [float("nan"), parts[4]]
        rows_out.append([r["seed"], f"{r['done']} s", *(f"{x:.0f} s" for x in parts), r["verdict"]])
    cmd = " ".join(["bluesky-offsets demo --seed S", *([f"--threads {a.threads}"] if a.threads else []), *a.extra])
    median = statistics.median(r["done"] for r in rows)
    table = Table(f"{len(rows)} draws, one after the other (`{cmd}`):",
                  ["seed", "wall", "IOC up", "beam found + measured", "surrogate finder", "analysis",
                   "beam optimized", "report", "verdict"], rows_out, align=["r"] * 8 + ["l"])
    result = write_result(
        "demo_wall_time", title="The main job's wall time (issue 17)", tables=[table],
        summary="Issue 17's benchmark: the README's main job (`bluesky-offsets demo --seed S`) over several draws, "
                "one after the other, each split at the demo's own step lines; asked: a median under 90 s on 2 "
                f"cores. **Median {median:.0f} s over {len(rows)} draws.**")
    print(section(result))


if __name__ == "__main__":
    main()
