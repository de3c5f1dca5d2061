"""docs/benchmarks.md is what benchmarks/results/ gives, and every result file fits the one schema.

Cheap: no benchmark runs; the page is rendered from the result files and compared.
"""

import datetime
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
RESULT_FILES = sorted((BENCH / "results").glob("*.json"))


@pytest.fixture(scope="module")
def bench():
    """The benchmarks' own modules (results, render), imported as the scripts import them."""
    sys.path.insert(0, str(BENCH))
    try:
        import render
        import results
        yield results, render
    finally:
        sys.path.remove(str(BENCH))


def test_the_page_is_what_the_results_give():
    r = subprocess.run([sys.executable, "benchmarks/render.py", "--check"], cwd=ROOT, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]


def test_there_are_results():
    assert len(RESULT_FILES) >= 10
    assert not list((BENCH / "results").glob("*.invalid")), "a benchmark left a result that did not fit the schema"


@pytest.mark.parametrize("path", RESULT_FILES, ids=[p.stem for p in RESULT_FILES])
def test_every_result_file_fits_the_schema(bench, path):
    results, _ = bench
    d = json.loads(path.read_text(encoding="utf-8"))
    assert results.validate(d) == []
    assert d["benchmark"] == path.stem
    for f in d.get("data", []):  # raw outputs the result names are in the repository
        assert (ROOT / f).is_file(), f
    for f in d.get("figures", []):
        assert (ROOT / f["path"]).is_file(), f["path"]
    back = results.load(path).to_dict()
    assert {k: back[k] for k in d} == d  # the reader gives back what the file holds


def test_the_schema_says_what_is_wrong(bench):
    results, _ = bench
    good = json.loads(RESULT_FILES[0].read_text(encoding="utf-8"))
    assert results.validate(good) == []
    bad = {**good, "date": "4 Dec 2026", "commit": "HEAD", "colour": "blue"}
    del bad["summary"]
    errors = " ".join(results.validate(bad))
    for word in ("summary", "colour"):
        assert word in errors
    errors = " ".join(results.validate({**good, "date": "4 Dec 2026", "commit": ["3cfe1fb", "HEAD"]}))
    assert "date" in errors and "commit" in errors
    table = {"caption": "c", "columns": ["a", "b"], "rows": [["1"]]}
    assert any("2 cells" in e for e in results.validate({**good, "tables": [table]}))


def test_a_benchmark_writes_its_result_with_machine_date_and_commit(bench, tmp_path):
    results, render = bench
    r = results.write_result("probe", title="A probe", summary="What it measures.", directory=tmp_path,
                             tables=[results.Table("Rows:", ["x", "y"], [[1, 2.5], [3, None]])],
                             command="python benchmarks/bench_probe.py")
    back = results.load(tmp_path / "probe.json")
    assert back == r
    assert back.date == datetime.date.today().isoformat()
    assert back.machine["description"] and back.machine["cores"]
    assert back.commit is None or re.fullmatch(r"[0-9a-f]{7,40}", back.commit)
    assert "| 3 | — |" in render.section(back)


def test_links_into_the_page_find_their_headings(bench):
    _, render = bench
    anchors = {"benchmarks"} | {render.slug(r.title) for r in render.load_all()}
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    for page in pages:
        for anchor in re.findall(r"benchmarks\.md#([^)\s]+)", page.read_text(encoding="utf-8")):
            assert anchor in anchors, f"{page.relative_to(ROOT)} links to benchmarks.md#{anchor}"


def test_the_page_has_two_heading_levels(bench):
    """MyST (the Sphinx site) wants consecutive heading levels: the page's title, then one per result."""
    _, render = bench
    titles = {f"## {r.title}" for r in render.load_all()}
    lines = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8").splitlines()
    headings = [line for line in lines if line.startswith("#")]
    assert headings[0] == "# Benchmarks"
    assert set(headings[1:]) == titles and len(headings[1:]) == len(titles)
