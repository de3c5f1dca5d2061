"""The PV map: one file names the 28 motor records and the camera PVs; ``check-pvs`` finds what
the control system lacks or disagrees on (against the simulated IOC with a motor left out)."""

from __future__ import annotations

import json

from bluesky_offsets.commands import cli
from bluesky_offsets.epics.pvmap import PVMap
from bluesky_offsets.physics.parameters import METRIXS

from conftest import start_metrixs_ioc


def test_the_simulated_map_round_trips_through_its_file(tmp_path):
    m = PVMap.simulated("BL:")
    path = tmp_path / "pvs.toml"
    path.write_text(m.to_toml())
    back = PVMap.from_file(path)
    assert back.motors == m.motors and back.chamber == m.chamber and back.name == m.name
    assert len(back.motors) == len(METRIXS.motorized_names) == 28
    # the devices take their names from the map (a real beamline's names are anything)
    real = PVMap({**m.motors, "E2.rotationXerror": "METRIXS:E2:PITCH"}, {**m.chamber, "hist_x": "CAM1:HX"}, "real")
    assert real.beamline_v1().parameter("E2.rotationXerror").prefix == "METRIXS:E2:PITCH"
    assert real.focus_chamber_v1().hist_x.pvname == "CAM1:HX"
    assert real.focus_chamber_v1().hist_y.pvname == "BL:chamber:HistY"


def test_check_pvs_reports_a_missing_motor_record_and_a_mismatched_one(tmp_path, capfd, ca):
    ioc = start_metrixs_ioc(tmp_path, extra=("--leave-out", "E1.rotationXerror"))
    try:
        path = tmp_path / "pvs.toml"
        assert cli.main(["pv-map", "--prefix", ioc.prefix, "--out", str(path)]) == 0
        capfd.readouterr()
        assert cli.main(["check-pvs", str(path)]) == 1  # the left-out record
        out = capfd.readouterr().out
        assert f"missing: E1.rotationXerror ({ioc.prefix}e1:rx) did not connect" in out
        assert "50 of 51 PVs as expected, 1 missing, 0 mismatched" in out

        # a record whose soft limits leave less travel than the model needs
        ca.put(ioc.prefix + "e2:rx.HLM", 0.1)
        assert cli.main(["check-pvs", str(path), "--json"]) == 1
        res = json.loads(capfd.readouterr().out)
        assert res["missing"] == [{"entry": "E1.rotationXerror", "pv": f"{ioc.prefix}e1:rx"}]
        (bad,) = res["mismatched"]
        assert bad["entry"] == "E2.rotationXerror" and "soft limits" in bad["why"] and "needs 1" in bad["why"]
    finally:
        ioc.stop()


def test_a_camera_map_names_no_simulator_pv_and_checks_against_the_ioc(tmp_path, capfd, metrixs_ioc):
    """``pv-map --camera DIR`` names the focus chamber's areaDetector (prefix, directory, data sheet,
    pixels) and nothing only the simulator has; ``check-pvs`` finds its PVs on the IOC; bad camera
    tables are refused in one line."""
    import pytest

    from bluesky_offsets.epics.pvmap import CAMERA_PVS, PVMapError

    ioc = metrixs_ioc
    path, frames = tmp_path / "camera.toml", tmp_path / "frames"
    frames.mkdir()
    assert cli.main(["pv-map", "--prefix", ioc.prefix, "--camera", str(frames), "--out", str(path)]) == 0
    m = PVMap.from_file(path)
    assert m.chamber == {} and m.camera["prefix"] == f"{ioc.prefix}cam:"
    text = path.read_text()
    for simulator_only in ("HistX", "NumRays", "TruthId", "TableVersion", "Backend"):
        assert simulator_only not in text
    assert m.camera_calibration().geometry.pixel_y_mm == 0.005
    capfd.readouterr()
    assert cli.main(["check-pvs", str(path)]) == 0
    out = capfd.readouterr().out
    assert f"{len(CAMERA_PVS)} areaDetector camera PVs" in out
    assert f"{28 + 3 + len(CAMERA_PVS)} of {28 + 3 + len(CAMERA_PVS)} PVs as expected" in out
    good = dict(m.camera)
    for bad, why in (({**good, "exposure": 1.0}, "unknown keys exposure"), ({**good, "gain": -1.0}, "gain"),
                     ({k: v for k, v in good.items() if k != "directory"}, "no directory"),
                     ({**good, "geometry": {"pixel": 1}}, "camera.geometry")):
        with pytest.raises(PVMapError, match=why):
            PVMap(m.motors, {}, "x", m.table, m.stage, bad)
    with pytest.raises(PVMapError, match="not both"):
        PVMap(m.motors, PVMap.simulated("BL:").chamber, "x", m.table, m.stage, good)
