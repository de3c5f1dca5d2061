"""Physics pinned down: RAY-UI's misaligned rays, the nominal METRIXS focus, optics, noise."""

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import rayx

from bluesky_offsets.physics.metrixs import nominal_beamline
from bluesky_offsets.physics.noise import expected_repeat_mse, histogram_mse, load_noise_floor
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.rml import read_rml
from bluesky_offsets.physics.twin import HistogramSpec, Twin, footprint
from bluesky_offsets.physics.rayx_calls import fix_seed

SHARED = Path(__file__).resolve().parent / "data" / "reference"  # provenance: its README.md
METRIXS_RML = SHARED / "METRIX_U41_G1_H1_318eV_PS_MLearn_1.15.rml"
RAYUI_FILES = sorted((SHARED / "rayui-misalignment").glob("*.rml"))


@pytest.fixture(scope="module")
def twin():
    return Twin(scheduler="inline", n_rays=20_000)


def _trace_file(path: Path, seed: int = 0):
    bl = rayx.import_beamline(str(path))
    fix_seed(seed)
    return bl, bl.trace()


@pytest.mark.parametrize("path", RAYUI_FILES, ids=lambda p: p.stem)
def test_rayui_misaligned_rays_reproduced(path, tmp_path):
    """(a) alignmentError values -> our frames -> our RML -> RAYX == RAY-UI's output rays."""
    beamline = read_rml(path)  # world vectors of the file are ignored and recomputed
    ours = beamline.write(tmp_path / "ours.rml")
    n_rays = int(beamline.objects[0].get_float("numberRays"))
    _, rays = _trace_file(ours)
    x, y, ray_ids = footprint(rays, len(beamline.objects), n_rays)

    csv = pd.read_csv(path.with_suffix(".csv"), sep="\t", skiprows=1)
    csv = csv.sort_values("ImagePlane_RN")
    assert len(x) == len(csv) == n_rays
    np.testing.assert_array_equal(ray_ids, csv["ImagePlane_RN"].to_numpy())
    np.testing.assert_allclose(x, csv["ImagePlane_OX"].to_numpy(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(y, csv["ImagePlane_OY"].to_numpy(), rtol=0, atol=1e-9)

    # the misalignment matters: without it the rays land elsewhere
    for obj in beamline.objects:
        if not obj.is_source:
            obj.set_misalignment(**{k: 0.0 for k in ("translationXerror", "translationYerror", "translationZerror",
                                                     "rotationXerror", "rotationYerror", "rotationZerror")})
    _, rays0 = _trace_file(beamline.write(tmp_path / "aligned.rml"))
    x0, y0, _ = footprint(rays0, len(beamline.objects), n_rays)
    assert np.hypot(x0 - csv["ImagePlane_OX"].to_numpy(), y0 - csv["ImagePlane_OY"].to_numpy()).max() > 0.1


def test_nominal_matches_direct_rayx_trace(twin, tmp_path):
    """(b) Our METRIXS geometry traces like RAYX on the reference RML: ray by ray with the same
    seed, and in transmission, centroid and widths within sampling noise with independent seeds."""
    n = 20_000
    ref = rayx.import_beamline(str(METRIXS_RML))
    ref.sources[0].numberOfRays = n
    fix_seed(99)
    xr, yr, idr = footprint(ref.trace(), 10, n)
    res = twin.trace(METRIXS.reference, n_rays=n, keep_rays=True, seed=99)
    assert res.n_hits == len(xr)
    np.testing.assert_allclose(res.rays[:, 0], xr, atol=1e-6)
    np.testing.assert_allclose(res.rays[:, 1], yr, atol=1e-6)

    ind = twin.trace(METRIXS.reference, n_rays=n, keep_rays=True, seed=12345)
    t_ref, t_ind = len(xr) / n, ind.transmission
    sigma_t = math.sqrt(t_ref * (1 - t_ref) / n)
    assert abs(t_ind - t_ref) < 5 * math.sqrt(2) * sigma_t
    for k, r in ((0, xr), (1, yr)):
        s = r.std()
        assert abs(ind.rays[:, k].mean() - r.mean()) < 5 * math.sqrt(2) * s / math.sqrt(len(r))
        assert abs(ind.rays[:, k].std() / s - 1) < 0.05
    # the acceptance numbers of the nominal focus
    s = ind.summary()
    assert s["transmission"] == pytest.approx(0.786, abs=0.02)
    assert s["width_x"] == pytest.approx(0.068, abs=0.005)
    assert s["width_y"] == pytest.approx(0.0156, abs=0.002)


def _distance_to_screen(name: str) -> float:
    """Optical path from an element to the focus-chamber screen (sum of the chain distances)."""
    objs = nominal_beamline().objects
    i = [o.name for o in objs].index(name)
    return sum(o.chain_link().distance for o in objs[i + 1:])


@pytest.mark.parametrize("name, delta, axis", [("E2.rotationXerror", 0.5, 1), ("E2.rotationXerror", -0.5, 1),
                                               ("E1.rotationXerror", 1.0, 0), ("E1.rotationXerror", -1.0, 0)])
def test_pitch_moves_focus_by_two_delta_q(twin, name, delta, axis):
    """(c) A mirror pitch of delta deflects the beam by 2 delta: the focus moves 2 delta q."""
    q = _distance_to_screen(name.split(".")[0])
    base = twin.trace(METRIXS.reference, keep_rays=True, seed=1).rays.mean(axis=0)
    moved = twin.trace(METRIXS.from_mapping({name: delta}), keep_rays=True, seed=1).rays.mean(axis=0)
    shift = moved - base
    assert abs(abs(shift[axis]) - 2 * abs(delta) * 1e-3 * q) < 0.05 * 2 * abs(delta) * 1e-3 * q
    assert abs(shift[1 - axis]) < 0.02  # and not in the other direction
    # E1 deflects horizontally (azimuth 90 deg), E2 vertically; q = 1900 and 1000 mm
    assert q == {"E1": 1900.0, "E2": 1000.0}[name.split(".")[0]]


@pytest.mark.parametrize("name, narrow", [("ASBL.totalWidth", 1.0), ("ASBL.totalHeight", 0.3),
                                          ("ExitSlit.totalHeight", 0.01)])
def test_narrowing_a_slit_lowers_transmission(twin, name, narrow):
    wide = twin.trace(METRIXS.reference, seed=3).transmission
    narrowed = twin.trace(METRIXS.from_mapping({name: narrow}), seed=3).transmission
    assert narrowed < wide - 0.1


def test_focus_chamber_translation_along_beam_defocuses(twin):
    """The chamber's z translation is geometry too.  The vertical waist (E2) sits at the
    screen, the horizontal one (E1) ~60 mm behind it: moving the screen 30 mm downstream
    widens y and narrows x, 30 mm upstream widens both; transmission does not change."""
    def widths(z):
        s = twin.trace(METRIXS.reference, keep_rays=True, seed=5,
                       overrides={"ImagePlane": {"translationZerror": z}}).summary()
        return s["width_x"], s["width_y"], s["transmission"]
    x0, y0, t0 = widths(0.0)
    xd, yd, td = widths(30.0)
    xu, yu, tu = widths(-30.0)
    assert yd > 2 * y0 and xd < 0.8 * x0
    assert yu > 1.2 * y0 and xu > 1.2 * x0
    assert td == t0 == tu


def test_histograms_are_fractions_of_source_rays(twin):
    res = twin.trace(METRIXS.reference, n_rays=5000, keep_rays=True, seed=2)
    spec = HistogramSpec()
    inside_x = ((res.rays[:, 0] >= -10) & (res.rays[:, 0] <= 10)).sum()
    assert res.hist_x.shape == (50,) and res.hist_y.shape == (50,)
    assert res.hist_x.sum() == pytest.approx(inside_x / 5000)
    np.testing.assert_allclose(res.hist_x * 5000, np.histogram(res.rays[:, 0], spec.edges_x)[0])
    np.testing.assert_allclose(res.hist_y * 5000, np.histogram(res.rays[:, 1], spec.edges_y)[0])


def test_empty_footprint_gives_zeros(twin):
    res = twin.trace(METRIXS.from_mapping({"M1_Cylinder.translationXerror": 1.0}), n_rays=2000, seed=4)
    assert res.n_hits == 0 and not res.hist_x.any() and not res.hist_y.any()
    assert np.isfinite(res.hist_x).all()


def test_seeded_traces_repeat_and_unseeded_differ(twin):
    a = twin.trace(METRIXS.reference, n_rays=3000, seed=7)
    b = twin.trace(METRIXS.reference, n_rays=3000, seed=7)
    c = twin.trace(METRIXS.reference, n_rays=3000)
    d = twin.trace(METRIXS.reference, n_rays=3000)
    np.testing.assert_array_equal(a.hist_y, b.hist_y)
    assert not np.array_equal(c.hist_y, d.hist_y)


def test_noise_floor_is_stored_and_reproducible(twin):
    """(d) The repeat-noise floor ships with the package and matches a fresh measurement."""
    floor = load_noise_floor()
    assert {"10000", "100000"} <= set(floor)
    f4, f5 = floor["10000"]["box"]["repeat_mse_mean"], floor["100000"]["box"]["repeat_mse_mean"]
    assert 5 < f4 / f5 < 20  # noise MSE falls ~1/N
    nominal = floor["10000"]["nominal_repeat_mse"]
    h = [twin.trace(METRIXS.reference, n_rays=10_000, seed=s) for s in (21, 22, 23, 24)]
    hh = [np.concatenate([r.hist_x, r.hist_y]) for r in h]
    fresh = np.mean([histogram_mse(hh[0], hh[1]), histogram_mse(hh[2], hh[3])])
    assert 0.3 < fresh / nominal < 3
    assert 0.5 < expected_repeat_mse(hh[0], 10_000) / fresh < 2
