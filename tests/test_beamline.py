"""Beamline descriptions: METRIXS from its shipped file, Energize from its RML, and what is refused."""

from __future__ import annotations

import numpy as np
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
    assert main(["simulate", "--beamline", "energize", "--engine", "both", "--rays", "2000", "--seed", "3",
                 "--set", "M4.rotationXerror=0.1", "--json"]) == 0
    runs = __import__("json").loads(capsys.readouterr().out)
    rayx, torch_ = runs["runs"]
    assert rayx["beamline"] == "energize" and rayx["parameters"]["M4.rotationXerror"] == 0.1
    assert rayx["n_hits"] == torch_["n_hits"] > 100 and rayx["centroid_x"] == pytest.approx(0.30, abs=0.01)
    assert runs["comparison"]["chi2_per_dof"] < 1e-6   # RAYX's rays through both: the same footprint


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
    (("unit = \"mrad\"", "unit = \"deg\""), "unit 'deg'; a rotationXerror is in 'mrad'"),
    (("unit = \"mrad\"", "unit = \"mm\""), "unit 'mm'; a rotationXerror is in 'mrad'"),
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
    density = GOOD.replace('element = "Toroid"', 'element = "Plane Grating"').replace(
        'field = "rotationXerror"', 'field = "lineDensity"').replace('unit = "mrad"', 'unit = "lines/mm"')
    assert load_beamline(_write(tmp_path, density.replace("[-0.25, 0.25]", "[1198.0, 1202.0]").replace(
        "reference = 0.0", "reference = 1200.0"), "d.toml")).table.parameters[0].unit == "lines/mm"
    with pytest.raises(BeamlineError, match="No such file"):
        load_beamline(tmp_path / "none.toml")
    with pytest.raises(BeamlineError, match="shipped: \\['energize', 'metrixs'\\]"):
        shipped("bessy")


def test_an_rml_rayx_cannot_import_is_refused_in_one_line_and_this_process_lives(tmp_path, capsys):
    """RAYX ends its process on a parameter it cannot parse; a description whose RML has a source
    without ``numberRays`` is refused in one line naming it (exit 2), and the caller goes on."""
    text = shipped("energize").with_name("Energize_EN_500.rml").read_text()
    start = text.index('<param id="numberRays"')
    path = _write(tmp_path, GOOD)
    (tmp_path / "x.rml").write_text(text[:start] + text[text.index("</param>", start) + len("</param>"):])
    with pytest.raises(BeamlineError, match='cannot import it: parseInt failed for "numberRays"') as err:
        load_beamline(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)
    assert main(["params", "--beamline", str(path)]) == 2
    assert 'parseInt failed for "numberRays"' in capsys.readouterr().err


def _moved(text: str, at: int) -> str:
    """``text`` with the world vector at ``at`` moved by 1 mm along y."""
    y = text.index("<y>", at) + len("<y>")
    end = text.index("</y>", y)
    return text[:y] + repr(float(text[y:end]) + 1.0) + text[end:]


@pytest.mark.parametrize("edit, why", [
    (lambda t, at: t[:at] + t[at:].replace('type="Cylinder"', 'type="Crystal"', 1),
     "object 'Cylinder': element type 'Crystal' is not supported"),
    (lambda t, at: _moved(t, t.index('id="worldPosition"', at)),
     "object 'Cylinder' \\(Cylinder\\): the element chain places it elsewhere .*its position 1 off"),
], ids=["crystal", "moved"])
def test_an_element_the_chain_cannot_place_as_its_rml_does_is_refused_by_name(tmp_path, capsys, edit, why):
    """RAYX places an element by the RML's world vectors and every edit writes them anew from the
    element chain: an element type the chain cannot place (a crystal), or places elsewhere than the
    RML says (a paraboloid; here a world vector moved by hand), is refused at load, exit 2."""
    text = shipped("energize").with_name("Energize_EN_500.rml").read_text()
    path = _write(tmp_path, GOOD)
    (tmp_path / "x.rml").write_text(edit(text, text.index('<object name="Cylinder"')))
    with pytest.raises(BeamlineError, match=why) as err:
        load_beamline(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)
    assert main(["params", "--beamline", str(path)]) == 2
    assert "object 'Cylinder'" in capsys.readouterr().err


def test_a_source_rayx_cannot_trace_is_refused_in_one_line(tmp_path, capsys):
    """RAYX 0.4.5's "Simple Undulator" (HRRIXS's, RAYX's benchmark input) emits rays with non-finite
    positions: a description with it loads (it is the source), and a trace with either engine, or
    ``simulate``, refuses it in one line (exit 2) where the screen would silently stay dark."""
    from pathlib import Path

    from bluesky_offsets.errors import InputError
    from bluesky_offsets.physics.twin import Twin
    text = shipped("energize").with_name("Energize_EN_500.rml").read_text()
    start = text.index('<object name="Dipole"')
    end = text.index("</object>", start) + len("</object>")
    undulator = (Path(__file__).parent / "data" / "reference" / "simple_undulator_object.xml").read_text()
    (tmp_path / "x.rml").write_text(text[:start] + undulator.replace('name="SU"', 'name="Dipole"').strip() + text[end:])
    path = tmp_path / "bl.toml"
    path.write_text(GOOD)
    bl = load_beamline(path)
    for engine in ("rayx", "torch"):
        with pytest.raises(InputError, match="source 'Dipole' \\(Simple Undulator\\).*non-finite position x") as err:
            Twin(bl.engine(engine), scheduler="inline").trace(bl.table.reference, n_rays=200, seed=1)
        assert "\n" not in str(err.value)
    capsys.readouterr()
    assert main(["simulate", "--beamline", str(path), "--rays", "200"]) == 2
    assert "none can be traced" in capsys.readouterr().err


def test_rayx_traces_a_described_beamline_as_its_rml_says():
    """The RML engine writes Energize's file anew (world frames from the element chain) and RAYX
    traces it ray for ray as the shipped file; a mirror's pitch turns the beam by twice the angle."""
    import rayx

    from bluesky_offsets.physics.twin import TraceRequest, Twin, footprint
    from bluesky_offsets.physics.rayx_calls import fix_seed
    bl = load_beamline(shipped("energize"))
    eng = bl.engine()
    r = eng.trace(TraceRequest(bl.table.reference, seed=7), 1000, keep_rays=True)
    raw = rayx.import_beamline(str(bl.rml))
    fix_seed(7)
    x, y, _ = footprint(raw.trace(), len(raw.sources) + len(raw.elements), 1000)
    assert r.n_hits == len(x) > 50
    assert np.max(np.abs(r.rays - np.column_stack([x, y]))) < 1e-9
    tilted = bl.table.reference.copy()
    tilted[bl.table.index("M4.rotationXerror")] += 0.1   # mrad: the beam turns by 0.2 mrad, 1,500 mm upstream
    t = eng.trace(TraceRequest(tilted, seed=7), 4000, keep_rays=True)
    n = eng.trace(TraceRequest(bl.table.reference, seed=7), 4000, keep_rays=True)
    assert abs(t.rays[:, 0].mean() - n.rays[:, 0].mean()) == pytest.approx(0.2e-3 * 1500, rel=0.05)
    batch = Twin(eng, scheduler="inline").trace_batch(np.stack([bl.table.reference, tilted]), n_rays=2000, seed=1)
    assert batch.hist_x.shape == (2, 50) and np.all(batch.hist_x.sum(1) > 0.05)
    with pytest.raises(ValueError, match="M1.longRadius"):
        bad = bl.table.reference.copy()
        bad[bl.table.index("M1.longRadius")] = -1.0
        eng.trace(TraceRequest(bad), 100)


def test_the_simulated_ioc_serves_a_described_beamline(ioc_factory, tmp_path, ca):
    """``ioc --beamline energize``: Energize's motors (named by its file), its detector window, RAYX
    tracing its RML with the hidden offsets; a motor's move turns the footprint as the twin says."""
    import json

    from conftest import METRIXS_IOC_ARGS
    bl = load_beamline(shipped("energize"))
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({"offsets": {"M4.rotationXerror": 0.1, "Dipole.translationYerror": -0.05}}))
    ioc = ioc_factory(args=["--beamline", "energize", "--truth", truth, *METRIXS_IOC_ARGS],
                      ready="chamber:Message", ready_value="ready", timeout=90)
    p = ioc.prefix
    assert ca.get(p + "chamber:TableVersion", as_string=True) == bl.table.version
    assert np.allclose(ca.get(p + "chamber:AxisX"), bl.detector.histograms.centers_x)

    def centroid():
        ca.put(p + "chamber:Acquire", 1)
        h = np.asarray(ca.get(p + "chamber:HistX"), float)
        assert h.sum() > 0.02
        return float(np.sum(h * bl.detector.histograms.centers_x) / h.sum())

    ca.put(p + "chamber:NumRays", 20000)
    before = centroid()
    ca.put(p + "m4:rx", ca.get(p + "m4:rx.RBV") - 0.1)   # mrad: the beam turns by 0.2 mrad back
    after = centroid()
    assert after - before == pytest.approx(-0.3, abs=0.06)   # 1,500 mm downstream
    from bluesky import RunEngine
    from ophyd_async.core import init_devices

    from bluesky_offsets.epics.devices import MetrixsBeamline
    RunEngine({})   # ophyd-async connects on the RunEngine's loop
    with init_devices():   # the ophyd-async devices from the same table: every motor connects
        beamline = MetrixsBeamline(p, name="energize", table=bl.table)
    assert len(beamline.motors) == 32 and beamline.parameter("M4.rotationXerror").name == "energize-m4-rx"
    pv_map = tmp_path / "energize_pvs.toml"   # the PV map from the same file, checked against the IOC
    assert main(["pv-map", "--beamline", "energize", "--prefix", p, "--out", str(pv_map)]) == 0
    assert '"M4.rotationXerror"' in pv_map.read_text()
    assert main(["check-pvs", str(pv_map), "--beamline", "energize", "--timeout", "10"]) == 0


def test_the_torch_engine_traces_energize_from_rayx_source_rays(tmp_path):
    """Energize's RML (misaligned) through the torch engine from RAYX's own source rays: the same
    rays reach the image plane, every hit up to the slit within 1e-6 mm of RAYX's. RAYX re-finds
    the M4 toroid just ahead of where a ray left it and bounces it there until its event limit (a
    third of the rays here); the engine loses the same rays. RAYX's M4 hits lie 5-50 µm along the
    mirror from the exact intersection (1-2 µm of surface height at 2° grazing); the image-plane
    points agree within 1e-4 mm."""
    import rayx

    from bluesky_offsets.physics.engine import compile_beamline, rays_from_arrays, trace_rays
    from bluesky_offsets.physics.engine import random_streams as rnd
    from bluesky_offsets.physics.rayx_calls import fix_seed
    from bluesky_offsets.physics.twin import TraceRequest, footprint
    bl = load_beamline(shipped("energize"))
    vals = bl.table.reference.copy()
    vals[bl.table.index("M4.rotationXerror")], vals[bl.table.index("PG.rotationZerror")] = 0.1, 0.5
    n = 2000
    rml = bl.engine().build(TraceRequest(vals), n)
    rb = rayx.import_beamline(str(rml.write(tmp_path / "e.rml")))
    fix_seed(5)
    rays = rb.trace()
    n_objects = len(rb.sources) + len(rb.elements)
    _, _, good = footprint(rays, n_objects, n)
    order = np.lexsort((np.asarray(rays.path_event_id), np.asarray(rays.path_id)))
    ev = {k: np.asarray(getattr(rays, k))[order] for k in ("path_id", "object_id", "position_x", "position_y",
                                                            "position_z", "direction_x", "direction_y",
                                                            "direction_z", "energy")}
    pos = np.column_stack([ev["position_x"], ev["position_y"], ev["position_z"]])
    src = ev["object_id"] == 0
    given = rays_from_arrays(pos[src], np.column_stack([ev["direction_x"], ev["direction_y"], ev["direction_z"]])[src],
                             ev["energy"][src], counters=rnd.rayx_counters(n, rnd.rayx_trace_seed(5)))
    cb = compile_beamline(np.zeros((1, 0)), beamline=rml)
    beam = trace_rays(cb, given, keep_hits=True)
    alive = np.nonzero(beam.alive[0].numpy())[0]
    assert set(good) == set(alive) and len(good) > 50
    last = {p: o for p, o in zip(ev["path_id"], ev["object_id"])}
    trapped = [p for p in set(ev["path_id"]) if p not in set(good) and int(last[p]) == n_objects - 2]
    assert len(trapped) > 20   # the rays RAYX bounced on M4 until its event limit: lost by both
    for k, name in enumerate(cb.names, start=1):
        first = {}
        for p, q in zip(ev["path_id"][ev["object_id"] == k], pos[ev["object_id"] == k]):
            first.setdefault(p, q)
        d = np.abs(np.array([first[p] for p in good]) - beam.hits[name][0].numpy()[good]).max()
        assert d < {"Toroid 1": 0.1, "ImagePlane": 1e-4}.get(name, 1e-6), (name, d)


def test_the_torch_engine_equals_rayx_on_energize_across_its_ranges():
    """20 states drawn across the whole box (offsets up to ±20 % of every range, fixed-but-unknown
    radii included): the torch engine on RAYX's source rays delivers RAYX's rays to the image plane,
    where they land within 5e-4 mm (RAYX's toroid Newton stops at 1e-4 mm along the mirror); a ray
    whose re-hit on a toroid RAYX decides within that tolerance may go either way (at most one per
    state)."""
    from bluesky_offsets.physics.twin import TraceRequest
    bl = load_beamline(shipped("energize"))
    t = bl.table
    rayx_, torch_ = bl.engine("rayx"), bl.engine("torch")
    rng = np.random.default_rng(2024)
    exact = lit = 0
    for k in range(20):
        vals = t.reference + t.offsets_to_physical(rng.uniform(-0.2, 0.2, len(t)))
        a = rayx_.trace(TraceRequest(vals, {}, 100 + k), 2000, keep_rays=True)
        b = torch_.trace(TraceRequest(vals, {}, 100 + k), 2000, keep_rays=True)
        assert abs(a.n_hits - b.n_hits) <= 1, (k, a.n_hits, b.n_hits)
        lit += a.n_hits > 0
        if a.n_hits == b.n_hits:
            exact += 1
            if a.n_hits:   # the same rays, in the same order
                assert np.abs(a.rays - b.rays).max() < 5e-4, (k, np.abs(a.rays - b.rays).max())
    assert exact >= 17 and lit >= 15


def test_the_torch_engine_of_a_description_is_differentiable_in_every_kind_of_parameter():
    """``load_beamline(p).engine("torch")``: RAYX's own source rays through the compiled RML; the
    same rays as RAYX's twin at the nominal state, and gradients of the footprint's centroid and
    width within 1 % of central differences for a pitch, a roll and a fixed-but-unknown radius."""
    import torch

    from bluesky_offsets.physics.twin import TraceRequest
    bl = load_beamline(shipped("energize"))
    eng = bl.engine("torch")
    n, seed = 4000, 3
    assert eng.trace(TraceRequest(bl.table.reference, seed=seed), n).n_hits == \
        bl.engine().trace(TraceRequest(bl.table.reference, seed=seed), n).n_hits

    def stats(v):
        b = eng.beam(v[None], n_rays=n, seed=seed)
        w = b.alive[0].to(torch.float64)
        mx, my = (b.x[0] * w).sum() / w.sum(), (b.y[0] * w).sum() / w.sum()
        return torch.stack([mx, my, ((b.x[0] - mx) ** 2 * w).sum() / w.sum()])

    for name, out, h in (("M4.rotationXerror", 0, 1e-3), ("PG.rotationZerror", 1, 1e-3), ("M4.shortRadius", 2, 1e-3)):
        v = torch.tensor(bl.table.reference, dtype=torch.float64, requires_grad=True)
        (g,) = torch.autograd.grad(stats(v)[out], v)
        i = bl.table.index(name)
        up, down = v.detach().clone(), v.detach().clone()
        up[i] += h
        down[i] -= h
        fd = float((stats(up)[out] - stats(down)[out]) / (2 * h))
        assert abs(fd) > 1e-9 and float(g[i]) == pytest.approx(fd, rel=0.01), (name, float(g[i]), fd)


@pytest.mark.parametrize("args, why", [
    (["--beamline", "bessy"], "no shipped beamline 'bessy'"),
    (["--beamline", "energize", "--design", "bright"], "--design bright needs the surrogate"),
    (["--beamline", "energize", "--effect", "thermal_bump_m1:height=100"], "not among energize's effects"),
    (["--beamline", "energize", "--candidates", "source_size"], "not among energize's effects"),
])
def test_the_demo_refuses_what_a_described_beamline_cannot_do_in_one_line(tmp_path, capsys, args, why):
    assert main(["demo", "--out", str(tmp_path / "out"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert why in err and "\n" not in err
    assert not (tmp_path / "out").exists()   # refused before anything ran


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_the_demo_calibrates_a_described_beamline_end_to_end(tmp_path):
    """``bluesky-offsets demo --beamline energize`` as a user runs it, on a small budget: the IOC
    serves Energize with hidden offsets in all 37 parameters, the frames are designed on its torch
    twin, the offsets fitted, the diagnosis ranks Energize's own effects, validation frames judge
    the calibration, and the calibration file names Energize's table.  Read through the simulator's
    histogram PVs: at this budget (8 frames of 1,000 photons) the camera's frames leave its flux
    scale to the offsets (χ²/dof 2.2, the scale at −0.27); the camera is the main job's."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    exe = Path(sys.executable).parent / "bluesky-offsets"
    out = tmp_path / "out"
    proc = subprocess.run([str(exe), "demo", "--beamline", "energize", "--effect", "none", "--frames", "8",
                           "--rays", "1000", "--fit-rays", "600", "--fit-starts", "1", "--validation-frames", "2",
                           "--rounds", "1", "--candidates", "chamber_z,detector_blur", "--detector", "histograms",
                           "--out", str(out), "--store", str(tmp_path / "runs")],
                          capture_output=True, text=True, timeout=880)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    bl = load_beamline(shipped("energize"))
    assert s["beamline"] == "energize" and set(s["hidden_offsets"]) == set(bl.table.names)
    assert s["frames"] <= 8 and s["validation"]["configurations"] == 2
    assert s["verdict"] == "no significant missing effect", s["history"][-1]
    assert set(s["could_hide"]) <= set(bl.effects) and "chamber_z" in s["could_hide"]   # its own effects only
    assert s["history"][-1]["chi2_reduced"] < 1.5 and s["validation"]["passed"]
    cal = json.loads(Path(s["calibration"]).read_text())
    assert cal["parameter_table"] == "energize" and set(cal["offsets"]) == set(bl.table.names)
    assert (out / "report.html").stat().st_size > 10_000


def _shifted(text: str, at: int, by: np.ndarray) -> str:
    """``text`` with the world position of the object at ``at`` moved by ``by`` (mm)."""
    start = text.index('id="worldPosition"', at)
    for axis, d in zip("xyz", by):
        a = text.index(f"<{axis}>", start) + len(f"<{axis}>")
        end = text.index(f"</{axis}>", a)
        text = text[:a] + repr(float(text[a:end]) + float(d)) + text[end:]
    return text


def test_a_plane_mirror_centred_elsewhere_on_its_own_plane_is_traced_where_the_beam_meets_it(tmp_path):
    """RAY-UI puts an SX700 premirror's centre off the point where the central ray meets it, on the
    mirror's own plane (HB 1200's by 21 mm): the same surface for RAYX, accepted and placed at the
    chain's point.  Moved off its plane, or farther than a tenth of its length, it is refused."""
    from bluesky_offsets.physics.rml import read_world_vectors
    rml = shipped("energize").with_name("Energize_EN_500.rml")
    text = rml.read_text()
    world = read_world_vectors(rml)["Plane Mirror"]
    at = text.index('<object name="Plane Mirror"')
    path = _write(tmp_path, GOOD)
    (tmp_path / "x.rml").write_text(_shifted(text, at, 15.0 * world["worldZdirection"]))  # 200 mm long
    assert load_beamline(path).table.names and main(["params", "--beamline", str(path)]) == 0
    for by in (0.01 * world["worldYdirection"], 25.0 * world["worldZdirection"]):
        (tmp_path / "x.rml").write_text(_shifted(text, at, by))
        with pytest.raises(BeamlineError, match="object 'Plane Mirror' \\(Plane Mirror\\).*its position"):
            load_beamline(path)


def test_a_grid_source_s_frames_count_photons_from_its_grid_in_both_engines(capsys):
    """RAY-UI's matrix source emits the same grid for every seed: traced as it is, frames would carry
    no counting noise and no misfit could be judged.  Each photon is a ray of its grid, drawn by the
    seed: RAYX and the torch engine land the same photons (``simulate --engine both`` with no seed
    too), another seed draws others, and two traces of one configuration differ by the counting
    noise the misfit expects."""
    from pathlib import Path

    from bluesky_offsets.model.misfit import misfit
    from bluesky_offsets.physics.twin import Twin
    path = Path(__file__).parent / "data" / "beamlines" / "pm_ell.toml"
    bl = load_beamline(path)
    assert not bl.source_varies and load_beamline(shipped("energize")).source_varies
    rayx, torch = Twin(bl.engine(), scheduler="inline"), Twin(bl.engine("torch"), scheduler="inline")
    vals = bl.table.reference + np.array([0.1, -0.2, 0.1, -0.1, 0.2, 0.05]) * bl.table.span
    a, b = (t.trace(vals, n_rays=3000, seed=5, keep_rays=True) for t in (rayx, torch))
    assert a.n_hits == b.n_hits > 2500
    np.testing.assert_allclose(np.sort(a.rays, 0), np.sort(b.rays, 0), rtol=0, atol=1e-6)
    runs = [[rayx.trace(vals, n_rays=3000, seed=s) for s in range(k, k + 12)] for k in (10, 50)]
    assert not np.array_equal(runs[0][0].hist_x, runs[0][1].hist_x)
    (m, f) = ([np.array([getattr(r, h) for r in run]) for h in ("hist_x", "hist_y")] for run in runs)
    chi2 = misfit(*m, *f, 3000, model_rays=3000).chi2_reduced_total
    assert 0.7 < chi2 < 1.4, chi2
    capsys.readouterr()
    assert main(["simulate", "--beamline", str(path), "--engine", "both", "--rays", "2000",
                 "--json"]) == 0
    assert __import__("json").loads(capsys.readouterr().out)["comparison"]["chi2_per_dof"] < 1e-9


@pytest.mark.parametrize("name", ["pm_ell", "sphgr"])
def test_the_documented_example_descriptions_load(name, capsys):
    """The examples docs/reference/beamlines.md names (RAYX's test inputs, described from it) stay valid."""
    from pathlib import Path
    path = Path(__file__).parent / "data" / "beamlines" / f"{name}.toml"
    assert main(["params", "--beamline", str(path)]) == 0
    assert capsys.readouterr().out.startswith(f"{name} parameter table")
    assert not load_beamline(path).source_varies  # both a matrix source's grid
