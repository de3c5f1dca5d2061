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


def test_demo_refuses_bad_options(tmp_path, capfd):
    # the console script itself once, as a user runs it
    proc = _demo(tmp_path, "--effect", "gravity:g=9.8", timeout=120)
    assert proc.returncode == 2 and "unknown effect 'gravity'" in proc.stderr and "Traceback" not in proc.stderr
    # the rest through its entry point in this process (a subprocess each would cost seconds of imports)
    from bluesky_offsets.commands import cli
    cases = [(["--effect", "chamber_z:z=500"], "chamber_z"),
             (["--open-configurations", "9"], "--open-configurations must lie in [0, 6]"),
             (["--fit-top", "-1"], "--fit-top must be at least 0"),
             (["--effect", "chamber_z:z=5", "--effect", "chamber_z:z=6"], "each effect once"),
             (["--offsets-fraction", "0.5"], "--offsets-fraction must lie in [0, 0.2]"),
             (["--threads", "0"], "--threads must be at least 1")]
    for extra, message in cases:
        code = cli.main(["demo", "--out", str(tmp_path / "out"), "--store", str(tmp_path / "runs"), *ARGS, *extra])
        err = capfd.readouterr().err
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1, (extra, err)
    assert not (tmp_path / "runs").exists()  # refused before anything started
