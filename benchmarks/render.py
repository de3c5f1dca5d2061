"""Build ``docs/benchmarks.md`` from the result files in ``benchmarks/results/``.

    python benchmarks/render.py            # write the page
    python benchmarks/render.py --check    # exit 1 if the page is not what the results give

The page is MyST Markdown (the Sphinx site includes it) that GitHub shows as well: one ``##``
section per result, in :data:`ORDER` (results not listed there follow, by name), each with its
command, machine, date and commit, its summary, its tables, notes and figures.
"""

from __future__ import annotations

import argparse
import difflib
import os
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results import RESULTS, ROOT, Result, Table, load_all  # noqa: E402

PAGE = ROOT / "docs" / "benchmarks.md"
# the page's order: what a reader meets first; a result not named here goes last, by name
ORDER = ("twin", "find_defaults", "find_defaults_seeds7-9", "harness", "harness_500k", "harness_twin", "finder_surrogate",
         "finder_fast", "finder_gpu", "walker_start", "finder_twin", "calibration_session", "dataset_engines", "dataset_gpu",
         "surrogate_models", "surrogate_bright", "surrogate_pipeline", "surrogate_inference", "diagnosis_grid",
         "demo_wall_time", "cluster_idle", "pair_fit", "effect_identifiability", "torch_engine", "torch_engine_cuda", "ray_jacobian",
         "optimize_beam", "focus_sigma", "design_5pct", "design_20pct", "design_ceiling", "design_ceiling_20pct", "design_choice", "design_gap",
         "design_main_job",
         "demo_no_effect_5pct", "demo_no_effect_20pct", "motors", "step_scale", "camera",
         "demo_energize_seed2", "demo_energize_seed1", "ci")

INTRO = """\
# Benchmarks

This page is generated from the result files in `benchmarks/results/` by
`python benchmarks/render.py`: do not edit it by hand. The test suite runs
`python benchmarks/render.py --check`, which fails when the page and the results differ.
It holds each benchmark's current numbers only.

**Running a benchmark.** Each section gives its command (most take minutes to hours on the
2-core development machine). A benchmark script writes its result, `benchmarks/results/<name>.json`,
through `benchmarks/results.py`, which records the machine, the date and the commit itself; its raw
output (every run, every draw) goes to `benchmarks/results/raw/` or the folder its `--out` names.
Then `python benchmarks/render.py` rewrites this page. A rerun replaces the result: the history is
git's. After a CI run, `python benchmarks/record_ci.py` adds its times to `ci.json`, which keeps the
latest three.

**Where the numbers come from.** The results marked "converted" were taken from this page's
hand-written form at commit 955cff9, the latest measurement each of its sections reported; that
version also holds the history (dated reruns, what was tried and not kept):
`git show 955cff9:docs/benchmarks.md`. Where it gave no date or commit for a measurement, the
result says "not recorded".
"""


def slug(title: str) -> str:
    """The heading's anchor as GitHub and MyST (``myst_heading_anchors``) make it."""
    return re.sub(r"[^\w\u4e00-\u9fff\- ]", "", title).strip().lower().replace(" ", "-")


def _code(text: str) -> str:
    """``text`` as inline code, with a fence longer than any run of backticks in it."""
    run = max((len(m) for m in re.findall(r"`+", text)), default=0)
    fence = "`" * (run + 1)
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def _cell(value) -> str:
    """A table cell's Markdown: numbers at four significant digits, null as a dash, pipes escaped."""
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value).replace("|", "\\|")


def _align(table: Table) -> list[str]:
    """The table's alignment: as given, else right for columns of numbers."""
    if table.align is not None:
        return list(table.align)
    numeric = [bool(table.rows) and all(isinstance(r[i], (int, float)) or r[i] is None for r in table.rows)
               for i in range(len(table.columns))]
    return ["r" if n else "l" for n in numeric]


def table(t: Table) -> str:
    """A table's caption and its Markdown."""
    rule = {"l": "---", "r": "---:"}
    lines = [t.caption, "", "| " + " | ".join(_cell(c) for c in t.columns) + " |",
             "|" + "|".join(rule[a] for a in _align(t)) + "|"]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in t.rows]
    return "\n".join(lines)


def _commit(commit) -> str:
    if commit is None:
        return "Commit: not recorded"
    if isinstance(commit, (list, tuple)):
        return "Commits: " + ", ".join(commit)
    return f"Commit: {commit}"


def provenance(r: Result) -> str:
    """The line under a section's command: machine, date, commit, and where the numbers came from."""
    line = (f"Machine: {r.machine['description']}. Date: {r.date or 'not recorded'}. "
            f"{_commit(r.commit)}.")
    if r.source:
        line += f" Converted from {r.source}."
    return line


def section(r: Result) -> str:
    """One result as the page shows it."""
    parts = [f"## {r.title}", f"Command: {_code(r.command)}  \n{provenance(r)}", r.summary]
    parts += [table(t) for t in r.tables]
    if r.notes:
        parts.append("Notes:\n\n" + "\n".join(f"* {n}" for n in r.notes))
    docs = PAGE.parent
    parts += [f"![{f.caption}]({os.path.relpath(ROOT / f.path, docs)})" for f in r.figures]
    parts.append(f"Result file: `benchmarks/results/{r.benchmark}.json`"
                 + (", raw data: " + ", ".join(f"`{d}`" for d in r.data) if r.data else "") + ".")
    return "\n\n".join(parts)


def ordered(results: list[Result]) -> list[Result]:
    """``results`` in the page's order: :data:`ORDER`, then the others by name."""
    rank = {name: i for i, name in enumerate(ORDER)}
    return sorted(results, key=lambda r: (rank.get(r.benchmark, len(ORDER)), r.benchmark))


def page(results: list[Result]) -> str:
    """The whole page."""
    titles = [slug(r.title) for r in results]
    twice = sorted({s for s in titles if titles.count(s) > 1})
    if twice:
        raise ValueError(f"two results would have the same heading anchor: {', '.join(twice)}")
    return INTRO + "\n" + "\n\n".join(section(r) for r in ordered(results)) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="compare, do not write: exit 1 if the page differs")
    ap.add_argument("--results", type=Path, default=RESULTS, help=argparse.SUPPRESS)
    ap.add_argument("--page", type=Path, default=PAGE, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    text = page(load_all(args.results))
    if not args.check:
        args.page.write_text(text, encoding="utf-8")
        print(f"written: {args.page} ({len(text.encode()):,} bytes)")
        return 0
    old = args.page.read_text(encoding="utf-8") if args.page.exists() else ""
    if old == text:
        return 0
    diff = difflib.unified_diff(old.splitlines(), text.splitlines(), str(args.page), "from the results",
                                lineterm="", n=1)
    print("\n".join(list(diff)[:60]))
    print(f"{args.page} differs from what benchmarks/results/ gives: run python benchmarks/render.py")
    return 1


if __name__ == "__main__":
    raise SystemExit(main())
