"""``bluesky-offsets demo``'s refusals.  The demo itself runs in the IOC acceptance scenarios
(tests/test_diagnosis_ioc.py), whose chamber_z run is the README's main job and is read back
from the store by uid there."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ARGS = ["--rays", "2000", "--fit-rays", "2000", "--configurations", "6", "--open-configurations", "2",
        "--analysed-configurations", "6", "--candidates", "chamber_z,intensity_scale"]


def _demo(tmp_path, *extra, timeout=600):
    exe = Path(sys.executable).parent / "bluesky-offsets"  # the console script, as a user runs it
    cmd = [str(exe) if exe.exists() else shutil.which("bluesky-offsets"), "demo", "--out", str(tmp_path / "out"),
           "--store", str(tmp_path / "runs"), *ARGS, *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=dict(os.environ, PYTHONUNBUFFERED="1"))


def test_demo_refuses_bad_options(tmp_path):
    proc = _demo(tmp_path, "--effect", "gravity:g=9.8", timeout=120)
    assert proc.returncode == 2 and "unknown effect 'gravity'" in proc.stderr
    proc = _demo(tmp_path, "--effect", "chamber_z:z=500", timeout=120)
    assert proc.returncode == 2 and "chamber_z" in proc.stderr
    proc = _demo(tmp_path, "--open-configurations", "9", timeout=120)
    assert proc.returncode == 2 and "--open-configurations must lie in [0, 6]" in proc.stderr
    proc = _demo(tmp_path, "--fit-top", "-1", timeout=120)
    assert proc.returncode == 2 and "--fit-top must be at least 0" in proc.stderr
    proc = _demo(tmp_path, "--effect", "chamber_z:z=5", "--effect", "chamber_z:z=6", timeout=120)
    assert proc.returncode == 2 and "each effect once" in proc.stderr
    proc = _demo(tmp_path, "--offsets-fraction", "0.5", timeout=120)
    assert proc.returncode == 2 and "--offsets-fraction must lie in [0, 0.2]" in proc.stderr
    proc = _demo(tmp_path, "--threads", "0", timeout=120)
    assert proc.returncode == 2 and "--threads must be at least 1" in proc.stderr
    assert not (tmp_path / "runs").exists()  # refused before anything started
