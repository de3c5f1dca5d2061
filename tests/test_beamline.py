"""Beamline descriptions: METRIXS from its shipped file, Energize from its RML, and what is refused."""

from __future__ import annotations

import pytest

from bluesky_offsets.commands.cli import main
from bluesky_offsets.physics.beamline import BeamlineError, load_beamline, shipped
from bluesky_offsets.physics.parameters import METRIXS

METRIXS_VERSION = "5ded541cd337"
"""The METRIXS table's version before it moved into its description file: names, order and ranges."""


def test_metrixs_is_its_shipped_description_and_unchanged():
    bl = load_beamline(shipped("metrixs"))
    assert bl.table.version == METRIXS.version == METRIXS_VERSION
    assert bl.table.parameters == METRIXS.parameters and bl.builtin == "metrixs" and bl.rml is None
    assert (len(METRIXS), int(METRIXS.motorized.sum())) == (34, 28)
    p = METRIXS["ExitSlit.totalHeight"]
    assert (p.element, p.field, p.unit, p.reference, p.travel, p.device) == (
        "Exit Slit", "openingHeight", "mm", 0.1, (0.005, 0.2), "exit_slit.height")
    assert METRIXS["E1.longHalfAxisA"].motorized is False
    assert bl.detector.histograms.bins_x == 50 and bl.detector.camera.bins_y == 1200
    assert "chamber_z" in bl.effects


def test_energize_is_described_by_its_rml(capsys):
    bl = load_beamline(shipped("energize"))
    objects = bl.rml_objects()
    assert bl.rml.name == "Energize_EN_500.rml" and objects["Dipole"] == "Dipole"
    assert all(p.element in objects for p in bl.table) and len(bl.table) == 37
    assert sorted(p.name for p in bl.table if not p.motorized) == [
        "M1.longRadius", "M1.shortRadius", "M3.radius", "M4.longRadius", "M4.shortRadius"]
    assert main(["params", "--beamline", "energize"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("energize parameter table") and "37 parameters" in out and "PG.rotationXerror" in out


def _write(tmp_path, text: str, name: str = "bl.toml"):
    (tmp_path / "x.rml").write_text(shipped("energize").with_name("Energize_EN_500.rml").read_text())
    p = tmp_path / name
    p.write_text(text)
    return p


GOOD = '''[beamline]
name = "t"
rml = "x.rml"
[[parameter]]
name = "M1.rotationXerror"
element = "Toroid"
field = "rotationXerror"
unit = "mrad"
range = [-0.25, 0.25]
reference = 0.0
motor = "m1.rx"
'''


@pytest.mark.parametrize("change, why", [
    (("unit = \"mrad\"", "unit = \"mrad\"\nspeed = 3"), "unknown keys \\['speed'\\]"),
    (("element = \"Toroid\"", "element = \"Toroid 7\""), "no object 'Toroid 7'"),
    (("field = \"rotationXerror\"", "field = \"lineDensity\""), "has no field 'lineDensity'"),
    (("range = [-0.25, 0.25]", "range = [0.25, -0.25]"), "finite low < high"),
    (("motor = \"m1.rx\"", "motor = \"m1.rx\"\nfixed = \"m1.rx\""), "exactly one of 'motor'"),
    (("rml = \"x.rml\"", "rml = \"x.rml\"\neffects = [\"gravity\"]"), "unknown effects \\['gravity'\\]"),
    (("rml = \"x.rml\"", "rml = \"x.rml\"\nbuiltin = \"metrixs\""), "exactly one of rml"),
    (("rml = \"x.rml\"", "builtin = \"bessy\""), "builtin 'bessy'; known"),
    (("[beamline]", "[beamline]\ncolour = 1"), "unknown keys \\['colour'\\]"),
    (("unit = \"mrad\"", "unit = \"deg\""), "unit 'deg'"),
    (("[[parameter]]", "[detector]\nimage_plane = \"Slit\"\n[[parameter]]"), "not an ImagePlane"),
    (("name = \"t\"", "name = \"t\n"), "not TOML"),
])
def test_a_description_is_refused_in_one_line_naming_what_is_wrong(tmp_path, change, why):
    path = _write(tmp_path, GOOD.replace(*change))
    with pytest.raises(BeamlineError, match=why) as err:
        load_beamline(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)


def test_a_good_description_loads_and_a_missing_one_says_so(tmp_path):
    assert load_beamline(_write(tmp_path, GOOD)).table.names == ("M1.rotationXerror",)
    with pytest.raises(BeamlineError, match="No such file"):
        load_beamline(tmp_path / "none.toml")
    with pytest.raises(BeamlineError, match="shipped: \\['energize', 'metrixs'\\]"):
        shipped("bessy")
