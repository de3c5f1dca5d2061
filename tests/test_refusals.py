"""Every reason a user can fix ends a command in one line and a non-zero exit status, never a
traceback: a dark beamline, an IOC that does not answer, a store that cannot be written, a bad
truth file, an unknown effect, a checkpoint that does not fit, a bad PV map.

The commands run through ``bluesky_offsets.commands.cli.main``, the console script's entry point,
in this process (a subprocess per case would cost seconds of imports each); the messages are
checked on the captured stderr.
"""

from __future__ import annotations

import json
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from bluesky_offsets.commands import cli

from conftest import start_metrixs_ioc


def refused(capfd, argv: list[str], *expected: str) -> str:
    """Run the command; it must fail with one line naming each of ``expected``."""
    code = cli.main(argv)
    out, err = capfd.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert code != 0, (out, err)
    assert "Traceback" not in err + out
    assert len(lines) == 1 and lines[0].startswith(f"bluesky-offsets {argv[0]}: error: "), err
    for text in expected:
        assert text in lines[0], lines[0]
    return lines[0]


def test_a_dark_beamline_ends_in_one_line(tmp_path):
    """The console script itself (a subprocess): the RunEngine's own log of the failed plan must
    not add a traceback either."""
    # M1's pitch at the end of its travel sends the beam off the screen; three frames cannot find it
    ioc = start_metrixs_ioc(tmp_path, {"start": {"M1_Cylinder.rotationXerror": 0.25}})
    try:
        exe = Path(sys.executable).parent / "bluesky-offsets"
        proc = subprocess.run([str(exe) if exe.exists() else shutil.which("bluesky-offsets"), "calibrate",
                               "--prefix", ioc.prefix, "--store", str(tmp_path / "store"), "--out",
                               str(tmp_path / "out"), "--frames", "5"],  # the beam search may take 3
                              capture_output=True, text=True, timeout=300, env=ioc.env)
    finally:
        ioc.stop()
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and "Traceback" not in proc.stdout + proc.stderr, proc.stderr[-3000:]
    assert lines[-1].startswith("bluesky-offsets calibrate: error: the beam search ended dim after 3 frames")
    # what the command line can change: its --frames (the search's fraction is a plan's argument)
    assert lines[-1].endswith("or give the search more frames (--frames 5 let it take 3)"), lines[-1]
    assert not [line for line in lines[:-1] if "error" in line.lower()], lines  # the one line


def test_a_demo_whose_beam_search_ends_dim_ends_in_one_line(tmp_path):
    """The demo's own simulated beamline starts dark (its hidden offsets); four frames in all leave
    the search its first three, which end dim: one line that names the budget, no traceback, and
    the IOC stopped."""
    exe = Path(sys.executable).parent / "bluesky-offsets"
    proc = subprocess.run([str(exe) if exe.exists() else shutil.which("bluesky-offsets"), "demo", "--frames", "4",
                           "--detector", "histograms", "--rays", "1000", "--out", str(tmp_path / "out"), "--store",
                           str(tmp_path / "store")],
                          capture_output=True, text=True, timeout=300)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and "Traceback" not in proc.stdout + proc.stderr, proc.stderr[-3000:]
    assert len(lines) == 1 and lines[0].startswith("bluesky-offsets demo: error: the beam search ended dim after 3 "
                                                   "frames"), lines
    assert lines[0].endswith("or give the search more frames (--frames 4 let it take 3)"), lines[0]
    ioc = re.search(r"IOC (\S+): on 127\.0\.0\.1:(\d+)", proc.stdout)
    assert ioc and not _listening(int(ioc.group(2))), proc.stdout[-2000:]  # the IOC is stopped


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def test_an_ioc_that_does_not_answer_is_named(tmp_path, capfd):
    refused(capfd, ["calibrate", "--prefix", "NOBODY:HOME:", "--store", str(tmp_path / "store"),
                    "--connect-timeout", "1"], "cannot reach the beamline", "NOBODY:HOME:", "did not connect")


def test_a_store_that_cannot_be_written(tmp_path, capfd):
    (tmp_path / "a-file").write_text("")
    bad = str(tmp_path / "a-file" / "store")
    refused(capfd, ["calibrate", "--store", bad], "run store", bad)
    refused(capfd, ["diagnose", "--uid", "x", "--store", bad], "run store", bad)
    refused(capfd, ["pv-map", "--out", str(tmp_path)], "cannot write the PV map", str(tmp_path))
    refused(capfd, ["dataset", "generate", str(tmp_path / "a-file"), "--samples", "4"], "refusing to overwrite")
    # where the report would go, refused before anything runs
    refused(capfd, ["demo", "--out", str(tmp_path / "a-file")], "--out", "is a file, not a folder")
    refused(capfd, ["calibrate", "--out", str(tmp_path / "a-file" / "out")], "--out", "cannot make the folder")
    refused(capfd, ["diagnose", "--uid", "x", "--store", str(tmp_path), "--report", str(tmp_path / "a-file" / "r.html")],
            "--report", "is a file, not a folder")
    refused(capfd, ["simulate", "--rays", "100", "--plot", str(tmp_path)], "--plot", "is a folder, not a file")
    refused(capfd, ["find", "--out", str(tmp_path / "a-file")], "--out", "is a file, not a folder")
    # before Redis or the RE Manager start
    refused(capfd, ["queue-server", "--store", str(tmp_path / "a-file")], "--store", "is a file, not a folder")
    refused(capfd, ["queue-server", "--existing-plans-devices", str(tmp_path / "a-file" / "x.yaml")],
            "--existing-plans-devices", "is a file, not a folder")
    refused(capfd, ["queue-server", "--redis", "127.0.0.1:99999"], "port 99999 is not a TCP port")
    assert (tmp_path / "a-file").read_text() == ""  # the file left as it was
    typo = tmp_path / "runz"
    refused(capfd, ["diagnose", "--uid", "x", "--store", str(typo)], "no run store at", str(typo))
    assert not typo.exists()  # no empty store left behind


def test_a_budget_of_nothing(tmp_path, capfd):
    """A zero or negative budget is refused, not read as "the default"."""
    refused(capfd, ["find", "--evaluations", "0"], "--evaluations must be positive")
    refused(capfd, ["find", "--seconds", "0"], "--seconds must be positive")
    refused(capfd, ["dataset", "generate", str(tmp_path / "d"), "--samples", "4", "--workers", "0"],
            "--workers must be positive")
    refused(capfd, ["dataset", "generate", str(tmp_path / "d"), "--samples", "4", "--rayx-check", "-1"],
            "--rayx-check must be 0")
    refused(capfd, ["surrogate", "evaluate", "--uniform", "-1"], "--uniform must be 0 or more")
    refused(capfd, ["demo", "--rays", "100000000", "--out", str(tmp_path / "d")], "--rays must be at most 1,000,000")
    refused(capfd, ["demo", "--fit-starts", "-1", "--out", str(tmp_path / "d")], "--fit-starts must be at least 0")
    refused(capfd, ["diagnose", "--uid", "x", "--fit-starts", "-2", "--store", str(tmp_path / "d")],
            "--fit-starts must be at least 0")
    refused(capfd, ["ioc", "--noise-seed", "-5"], "--noise-seed must be 0 or more")
    refused(capfd, ["ioc", "--tick", "0"], "--tick must be positive")
    assert not (tmp_path / "d").exists()


def test_an_unknown_effect(tmp_path, capfd):
    for argv in (["calibrate", "--effects", "chamber_z,warp_drive"], ["demo", "--effect", "warp_drive:z=1"],
                 ["diagnose", "--uid", "x", "--effects", "warp_drive"]):
        refused(capfd, argv + ["--store", str(tmp_path / "store")] if argv[0] != "demo" else argv, "warp_drive")


def test_a_bad_truth_file(tmp_path, capfd):
    bad = tmp_path / "truth.json"
    bad.write_text(json.dumps({"offsets": {"E1.rotationXerror": 0.05, "E9.nothing": 1.0}}))
    refused(capfd, ["ioc", "--truth", str(bad)], "E9.nothing")
    bad.write_text("{not json")
    refused(capfd, ["ioc", "--truth", str(bad)], "not valid JSON")


def test_a_checkpoint_that_does_not_fit(tmp_path, capfd):
    from bluesky_offsets.surrogate.network import default_checkpoint
    blob = torch.load(default_checkpoint(), map_location="cpu", weights_only=False)
    meta = json.loads(blob["meta"])
    key = next(iter(meta["histogram"]))
    meta["histogram"][key] = 7 if not isinstance(meta["histogram"][key], list) else [0.0, 7.0]
    blob["meta"] = json.dumps(meta)
    path = tmp_path / "other-camera.pt"
    torch.save(blob, path)
    refused(capfd, ["calibrate", "--checkpoint", str(path), "--store", str(tmp_path / "store")],
            str(path), "different histogram spec")
    (tmp_path / "notes.pt").write_text("not a checkpoint")
    refused(capfd, ["calibrate", "--checkpoint", str(tmp_path / "notes.pt"), "--store", str(tmp_path / "store")],
            "truncated or corrupt")


@pytest.mark.parametrize("content, expected", [
    ("name = 'x'\n[motors]\n'E1.rotationXerror' = 'A:e1:rx'\n", "no record for"),
    ("[motors]\n'E1.radius' = 'A:x'\n", "not motorized"),
    ("[cameras]\n", "unknown keys cameras"),
    ("[motors\n", "not TOML"),
])
def test_a_bad_pv_map(tmp_path, capfd, content, expected):
    path = tmp_path / "pvs.toml"
    path.write_text(content)
    refused(capfd, ["check-pvs", str(path)], str(path), expected)
    refused(capfd, ["calibrate", "--pvs", str(path)], expected)
