"""Record a CI run's times in ``benchmarks/results/ci.json``: the latest few runs are the current record.

    .ci/run                                    # on a clean clone; note its wall time, pytest's, the user CPU
    python benchmarks/record_ci.py 15.1 12.3 23.4 --note "398 passed, 2 skipped; a quiet machine"
    python benchmarks/render.py                # the page

The run's commit is the checked-out one (``--commit`` names another); the result keeps the last
:data:`KEEP` runs, the oldest first, and records this machine and today's date.
"""

from __future__ import annotations

import argparse
import datetime
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_info  # noqa: E402
from results import RESULTS, Result, Table, current_commit, load, save  # noqa: E402

KEEP = 3  # runs on the page: enough to see the spread between runs, no history
BUDGET_MIN = 15.0  # the suite's budget on 2 cores
COLUMNS = ["commit", "`.ci/run`", "of it pytest", "user CPU"]


def record(total: float, pytest: float, cpu: float | None, commit: str, note: str, path: Path) -> Result:
    """``path``'s result with this run appended and only the last :data:`KEEP` runs kept."""
    old = load(path) if path.exists() else None
    rows = [list(r) for r in old.tables[0].rows] if old and old.tables else []
    label = f"{commit} ({datetime.date.today().isoformat()}; {note})" if note else commit
    rows = (rows + [[label, f"{total:.1f} min", f"{pytest:.1f} min", "—" if cpu is None else f"{cpu:.1f} min"]])[-KEEP:]
    commits = [str(r[0]).split()[0] for r in rows]
    table = Table(f"The latest {len(rows)} runs, the oldest first:", COLUMNS, rows, align=["l", "r", "r", "r"])
    machine = machine_info()
    return Result(benchmark="ci", title="Continuous integration", command=".ci/run",
                  machine={**machine, "description": machine["description"] + ", a clean clone"},
                  date=datetime.date.today().isoformat(), commit=commits,
                  summary="The whole suite with its IOC demos as CI runs it (`.ci/run`: a fresh virtual environment, "
                          "the README's install and test commands) on a clean clone; the budget is "
                          f"{BUDGET_MIN:g} minutes on 2 cores. The latest {len(rows)} runs: the machine's speed moves "
                          "from hour to hour, so one run says little alone.",
                  tables=[table], notes=old.notes if old else ())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("total", type=float, help="minutes of .ci/run")
    ap.add_argument("pytest", type=float, help="minutes of it in pytest")
    ap.add_argument("cpu", type=float, nargs="?", default=None, help="minutes of user CPU")
    ap.add_argument("--commit", default=None, help="default: the checked-out commit")
    ap.add_argument("--note", default="", help="what the run says beside its times (passed, failed, load)")
    args = ap.parse_args(argv)
    commit = args.commit or current_commit()[0]
    if not commit:
        ap.error("no commit: run in the repository or give --commit")
    path = save(record(args.total, args.pytest, args.cpu, commit, args.note, RESULTS / "ci.json"))
    print(f"written: {path} (python benchmarks/render.py updates docs/benchmarks.md)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
