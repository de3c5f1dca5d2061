"""The documentation (``docs/``): the site builds with every warning an error, and the pages'
``>>>`` examples run and print what the pages say."""

from __future__ import annotations

import doctest
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.relative_to(DOCS).parts)

pytestmark = pytest.mark.slow  # the build takes most of a minute on CI's two cores: scheduled first (conftest)


class MarkdownExamples(doctest.DocTestParser):
    """The ``>>>`` examples of a Markdown page: a code fence's closing line is not part of the
    output the example before it expects (each fence line is blanked, the line numbers kept)."""

    FENCE = re.compile(r"^[ \t]*(```|~~~).*$", re.M)

    def parse(self, string, name="<string>"):
        return super().parse(self.FENCE.sub("", string), name)


@pytest.mark.timeout(600)
def test_the_site_builds_without_a_warning(tmp_path):
    """``sphinx-build -W --keep-going -b html``, as CI runs it: offline too (no intersphinx inventory
    reachable), every other warning an error.  Prints the warnings when it fails."""
    warnings = tmp_path / "warnings.txt"
    cmd = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-b", "html", "-j", "1", "-q",
           "-d", str(tmp_path / "doctrees"), "-w", str(warnings), str(DOCS), str(tmp_path / "html")]
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=540)
    found = warnings.read_text() if warnings.exists() else ""
    assert r.returncode == 0, f"sphinx-build failed ({r.returncode}):\n{found}\n{r.stderr[-4000:]}"
    assert not found.strip(), found
    for page in ("index.html", "reference/cli.html", "reference/_api/bluesky_offsets.html", "benchmarks.html"):
        assert (tmp_path / "html" / page).is_file(), page


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(DOCS)) for p in PAGES])
def test_the_examples_run(page):
    failed, tried = doctest.testfile(str(page), module_relative=False, parser=MarkdownExamples(), globs={},
                                     encoding="utf-8", optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert failed == 0, f"{failed} of {tried} examples in {page.relative_to(ROOT)} failed (printed above)"


def test_the_examples_are_there():
    """The pages that show the library in Python show it as examples that run."""
    with_examples = {p.relative_to(DOCS).as_posix() for p in PAGES if re.search(r"^\s*>>> ", p.read_text(), re.M)}
    for page in ("explanations/twin.md", "explanations/offsets.md", "explanations/diagnosis.md",
                 "how-to/beamline.md", "how-to/train-surrogate.md", "reference/beamlines.md"):
        assert page in with_examples, page
