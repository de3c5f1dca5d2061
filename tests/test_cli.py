"""The command line: params, simulate (acceptance numbers), clear errors."""

import json
import subprocess
import sys

import pytest

from bluesky_offsets.commands.cli import main


def _json(capsys, argv):
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out)


def test_params_json(capsys):
    out = _json(capsys, ["params", "--json"])
    params = out["parameters"]
    assert len(params) == 34
    assert sum(p["fixed_but_unknown"] for p in params) == 6
    e2 = next(p for p in params if p["name"] == "E2.rotationZerror")
    assert (e2["low"], e2["high"], e2["unit"]) == (22.0, 32.0, "mrad")


def test_params_table_text(capsys):
    assert main(["params"]) == 0
    text = capsys.readouterr().out
    assert "34 parameters, 6 fixed-but-unknown" in text and "E1.longHalfAxisA" in text


def test_simulate_nominal_acceptance(capsys):
    out = _json(capsys, ["simulate", "--rays", "20000", "--json"])
    assert out["transmission"] == pytest.approx(0.786, abs=0.02)
    assert out["width_x"] == pytest.approx(0.068, abs=0.005)
    assert out["width_y"] == pytest.approx(0.0156, abs=0.002)
    assert len(out["hist_x"]) == 50 and len(out["hist_y"]) == 50
    assert sum(out["hist_x"]) == pytest.approx(out["transmission"])
    assert "E2.rotationZerror" in out["outside_sampling_box"]


@pytest.mark.parametrize("setting, axis, expected", [("E2.rotationXerror=0.5", "centroid_y", 1.00),
                                                     ("E1.rotationXerror=1", "centroid_x", 3.80)])
def test_simulate_set_moves_centroid(capsys, setting, axis, expected):
    base = _json(capsys, ["simulate", "--rays", "20000", "--json"])
    moved = _json(capsys, ["simulate", "--rays", "20000", "--json", "--set", setting])
    assert abs(moved[axis] - base[axis]) == pytest.approx(expected, rel=0.05)


def test_simulate_plot_and_text(capsys, tmp_path):
    png = tmp_path / "fp.png"
    assert main(["simulate", "--rays", "3000", "--plot", str(png), "--chamber", "0", "0", "10"]) == 0
    text = capsys.readouterr().out
    assert "transmission" in text and "outside the surrogate's sampling box" in text
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("argv, message", [
    (["simulate", "--set", "E9.rotationXerror=1"], "unknown parameter 'E9.rotationXerror'"),
    (["simulate", "--set", "E2.rotationXerror=abc"], "not a number"),
    (["simulate", "--set", "E2.rotationXerror"], "NAME=VALUE"),
    (["simulate", "--set", "E2.rotationXerror=nan"], "not finite"),
    (["simulate", "--set", "E1.shortHalfAxisB=30000"], "must exceed short half-axis"),
])
def test_simulate_bad_input(capsys, argv, message):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_console_script_entry_point():
    out = subprocess.run([sys.executable, "-m", "bluesky_offsets.commands.cli", "params", "--json"],
                         capture_output=True, text=True, check=True).stdout
    assert len(json.loads(out)["parameters"]) == 34


def test_a_beamline_error_inside_a_failed_status_is_found():
    """A chamber's error raised inside a status a plan waited on reaches the command wrapped (bluesky's
    ``FailedStatus`` from it): the command line finds it for its one line; anything else is not one."""
    from bluesky.utils import FailedStatus

    from bluesky_offsets.commands.cli import _beamline_error
    from bluesky_offsets.epics.pvs import ChamberError

    try:
        try:
            raise ChamberError("chamber: the HDF5 plugin wrote no frame within 120 s of the acquisition")
        except ChamberError as exc:
            raise FailedStatus("status") from exc
    except FailedStatus as wrapped:
        assert str(_beamline_error(wrapped)).startswith("chamber: the HDF5 plugin")
    assert _beamline_error(RuntimeError("a bug")) is None
