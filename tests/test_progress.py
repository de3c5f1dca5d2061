"""Progress output: a bar on a terminal, one line per task in a file, nothing under ``-q``."""

from __future__ import annotations

import doctest
import io
import subprocess
import sys

import bluesky_offsets.progress as progress


def test_the_module_examples_run():
    assert doctest.testmod(progress).failed == 0


def _clock(*times):
    it = iter(times)
    return lambda: next(it)


def test_a_file_gets_one_line_per_task_and_a_line_a_minute_while_it_runs():
    out = io.StringIO()
    b = progress.bar(total=100, desc="dataset", unit="sample", file=out, clock=_clock(0.0, 30.0, 61.0, 90.0, 100.0, 125.0))
    for _ in range(4):
        b.update(25)
    b.close()
    b.close()  # closing twice says nothing more
    assert out.getvalue().splitlines() == ["dataset: 50/100 sample, 61.0 s (running)", "dataset: 100/100 sample, 125.0 s"]
    assert "\r" not in out.getvalue()


def test_transient_bars_and_quiet_print_nothing_to_a_file():
    out = io.StringIO()
    for _ in progress.bar(range(3), desc="epoch 1", leave=False, file=out):
        pass
    progress.set_quiet(True)
    try:
        with progress.bar(total=2, desc="tracing", file=out) as b:
            b.update(2)
    finally:
        progress.set_quiet(False)
    assert out.getvalue() == ""


def test_quiet_flag_on_the_command_line():
    """``-q`` is accepted before any sub-command and leaves the result's output alone."""
    cmd = [sys.executable, "-m", "bluesky_offsets.commands.cli", "-q", "params", "--json"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.lstrip().startswith(("{", "[")) and r.stderr == "", r.stderr[-500:]


def test_an_array_iterates_as_with_tqdm():
    import numpy as np
    out = io.StringIO()
    assert list(progress.bar(np.arange(3), desc="seeds", file=out)) == [0, 1, 2]
    assert list(progress.bar(np.arange(2), desc="seeds", disable=True)) == [0, 1]
    assert out.getvalue().startswith("seeds: 3/3 it, ")
