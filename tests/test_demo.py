"""``bluesky-offsets demo`` end to end, small: 6 bright configurations at 2000 rays, 2 of them
again with the slits open, 6 analysed, fits at 2000 model rays, two candidate effects.

The full-size demo (16 + 4 configurations, 10 + 4 analysed, all 15 candidates) is measured by hand:
docs/diagnosis.md, "Workflow".
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bluesky_offsets.parameters import METRIXS
from bluesky_offsets.store import open_store
from plans.diagnose import load_results

ARGS = ["--rays", "2000", "--fit-rays", "2000", "--configurations", "6", "--open-configurations", "2",
        "--analysed-configurations", "6", "--candidates", "chamber_z,intensity_scale"]


def _demo(tmp_path, *extra, timeout=600):
    exe = Path(sys.executable).parent / "bluesky-offsets"  # the console script, as a user runs it
    cmd = [str(exe) if exe.exists() else shutil.which("bluesky-offsets"), "demo", "--out", str(tmp_path / "out"),
           "--store", str(tmp_path / "runs"), *ARGS, *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=dict(os.environ, PYTHONUNBUFFERED="1"))


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_demo_runs_the_workflow_and_its_runs_load_back_by_uid(tmp_path):
    proc = _demo(tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert _gone(summary["ioc"]["pid"])  # the simulated IOC is stopped
    uids = summary["uids"]
    assert {"search", "measurement", "find_offsets", "compare", "refine_offsets", "diagnose"} <= set(uids)
    assert (summary["n_configurations"], summary["n_open_configurations"], summary["n_analysed_configurations"]) == (8, 2, 6)
    labels = [h["model"] for h in summary["history"]]
    assert labels[:3] == ["twin", "surrogate offsets", "+ offsets"]
    out = proc.stdout
    assert "error history" in out and "load them back" in out and uids["measurement"] in out
    assert "Virtual circuit disconnect" not in proc.stderr  # channels closed before the IOC stopped

    with open_store(tmp_path / "runs") as store:
        assert set(summary["all_run_uids"]) <= set(store.uids())
        m = store.load_measurement(uids["measurement"])
        assert m.hist_x.shape == (8, 50) and m.truth_id == summary["truth_id"] and np.isfinite(m.hist_y).all()
        # the last two are the first two bright ones with the slits open (outside the surrogate's box)
        assert np.allclose(m.configurations[-2:, 0], m.configurations[:2, 0])
        assert np.allclose(m.configurations[-2:, METRIXS.index("ExitSlit.totalHeight")], 0.1, atol=1e-6)
        offsets_run = store[uids["find_offsets"]]
        assert offsets_run.metadata["start"]["n_configurations"] == 6  # the surrogate saw its box only
        for step in ("compare", "refine_offsets", "diagnose"):
            res = load_results(store, uids[step])
            assert res["start"]["measurement_uid"] == uids["measurement"], step
            assert res["start"]["analysed_configurations"] == [0, 1, 2, 3, 6, 7], step  # 4 bright + 2 open
        ranking = load_results(store, uids["diagnose"])["ranking"]
        assert [r["effect"] for r in ranking] == summary["rankings"][0]
        last = uids.get("add_effect") or uids["error_history"]
        hist = load_results(store, last)["error_history"]
        assert [h["label"] for h in hist] == labels
        assert hist[-1]["chi2_reduced"] == pytest.approx(summary["history"][-1]["chi2_reduced"])

    # the load-back line the summary prints works as printed
    line = next(l for l in out.splitlines() if l.strip().startswith("python -c"))
    code = re.search(r'python -c "(.*)"\s*$', line).group(1)
    back = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert back.returncode == 0 and "(8, 50)" in back.stdout, back.stderr[-2000:]

    html = (tmp_path / "out" / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 5
    assert not re.search(r'(src|href)=["\']?(https?:)?//', html)  # self-contained: opens offline
    for text in ("Error history", "ranking", summary["verdict"], uids["measurement"], uids["diagnose"]):
        assert text in html


def test_demo_refuses_bad_options(tmp_path):
    proc = _demo(tmp_path, "--effect", "gravity:g=9.8", timeout=120)
    assert proc.returncode == 2 and "unknown effect 'gravity'" in proc.stderr
    proc = _demo(tmp_path, "--effect", "chamber_z:z=500", timeout=120)
    assert proc.returncode == 2 and "chamber_z" in proc.stderr
    proc = _demo(tmp_path, "--open-configurations", "9", timeout=120)
    assert proc.returncode == 2 and "--open-configurations must lie in [0, 6]" in proc.stderr
    proc = _demo(tmp_path, "--effect", "chamber_z:z=5", "--effect", "chamber_z:z=6", timeout=120)
    assert proc.returncode == 2 and "each effect once" in proc.stderr
    proc = _demo(tmp_path, "--offsets-fraction", "0.5", timeout=120)
    assert proc.returncode == 2 and "--offsets-fraction must lie in [0, 0.2]" in proc.stderr
    assert not (tmp_path / "runs").exists()  # refused before anything started
