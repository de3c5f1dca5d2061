"""The effects library: each effect is a real change of the twin (or the detector)."""

import numpy as np
import pytest

from bluesky_offsets.physics import effects as E
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.twin import HistogramSpec, Twin

REQUIRED = {"chamber_x", "chamber_y", "chamber_z", "chamber_rotation", "source_size", "source_divergence", "photon_energy",
            "slope_error_m1", "slope_error_e1", "slope_error_e2", "thermal_bump_m1", "grating_line_density",
            "detector_blur", "background", "intensity_scale"}


@pytest.fixture(scope="module")
def twin():
    return Twin(scheduler="inline", n_rays=20_000)


@pytest.fixture(scope="module")
def base(twin):
    return twin.trace(METRIXS.reference, keep_rays=True, seed=3).summary()


def test_library_has_the_required_effects():
    assert REQUIRED <= set(E.EFFECTS)
    for eff in E.EFFECTS.values():
        assert eff.description and eff.parameters and eff.level in ("twin", "detector")
        for p in eff.parameters:
            assert p.low <= 0 <= p.high and p.unit


@pytest.mark.parametrize("name", sorted(n for n in REQUIRED if E.get(n).level == "twin"))
def test_zero_is_absent(twin, name):
    eff = E.get(name)
    a = twin.trace(METRIXS.reference, n_rays=3000, seed=9, overrides=E.twin_overrides({name: {}}))
    b = twin.trace(METRIXS.reference, n_rays=3000, seed=9)
    np.testing.assert_array_equal(a.hist_x, b.hist_x)
    np.testing.assert_array_equal(a.hist_y, b.hist_y)
    assert eff.is_absent({})


@pytest.mark.parametrize("name, values, signature", [
    ("chamber_z", {"z": 20.0}, lambda d: d["width_y"] > 0.015 and d["width_x"] < -0.01),
    ("chamber_x", {"x": 0.5}, lambda d: abs(d["centroid_x"] + 0.5) < 0.02 and abs(d["centroid_y"]) < 0.005),
    ("chamber_y", {"y": -0.3}, lambda d: abs(d["centroid_y"] - 0.3) < 0.02 and abs(d["centroid_x"]) < 0.005),
    ("source_divergence", {"divergence": 1.0}, lambda d: d["transmission"] < -0.2),
    ("photon_energy", {"delta": 0.03}, lambda d: d["transmission"] < -0.3),
    ("grating_line_density", {"delta": 0.2}, lambda d: d["transmission"] < -0.3),
    ("slope_error_e2", {"meridional": 5.0}, lambda d: d["width_y"] > 0.002 and abs(d["width_x"]) < 0.001),
    ("slope_error_e1", {"meridional": 5.0}, lambda d: d["width_x"] > 0.002 and abs(d["width_y"]) < 0.001),
    ("slope_error_m1", {"meridional": 5.0, "sagittal": 20.0}, lambda d: d["width_x"] > 0.001),
    ("thermal_bump_m1", {"height": 200.0}, lambda d: d["width_x"] > 0.01 and abs(d["transmission"]) < 0.01),
])
def test_twin_effect_signatures(twin, base, name, values, signature):
    s = twin.trace(METRIXS.reference, keep_rays=True, seed=3, overrides=E.twin_overrides({name: values})).summary()
    d = {k: s.get(k, 0.0) - base[k] for k in ("transmission", "centroid_x", "centroid_y", "width_x", "width_y")}
    assert signature(d), d


def test_chamber_rotation_rotates_an_elongated_footprint(twin):
    # defocused screen: an elongated spot, whose orientation the rotation changes
    v = METRIXS.reference
    a = twin.trace(v, keep_rays=True, seed=4, overrides={"ImagePlane": {"translationZerror": -60.0}})
    b = twin.trace(v, keep_rays=True, seed=4, overrides=E.twin_overrides(
        {"chamber_rotation": {"angle": 100.0}, "chamber_z": {"z": -60.0}}))
    ca, cb = np.cov(a.rays.T), np.cov(b.rays.T)
    assert abs(cb[0, 1] - ca[0, 1]) > 0.05 * np.sqrt(ca[0, 0] * ca[1, 1])


def test_detector_effects():
    spec = HistogramSpec()
    hx = np.zeros(50)
    hx[25] = 0.5
    hy = np.zeros(50)
    hy[20] = 0.5
    bx, by = E.apply_detector_effects(hx, hy, {"detector_blur": {"sigma": 0.4}}, spec)
    assert bx.sum() == pytest.approx(0.5) and bx.max() < 0.5 and by.max() < bx.max()
    gx, _ = E.apply_detector_effects(hx, hy, {"background": {"level": 1e-3}, "intensity_scale": {"delta": -0.1}},
                                     spec)
    assert gx[25] == pytest.approx(0.45 + 1e-3) and gx[0] == pytest.approx(1e-3)


@pytest.mark.parametrize("sigma", [0.1, 0.05])
def test_a_blurred_histograms_counting_noise_is_carried_through_the_kernel_squared(sigma):
    """The variance of a blurred counted histogram's bin, over repeated draws, is what
    ``detector_noise`` gives it (``Σ k² p − (Σ k p)²`` per source ray), not its value's; a gain
    after it keeps about that share, and alone a gain and a background change nothing."""
    from bluesky_offsets.physics.noise import bin_variance
    spec = HistogramSpec(100, (-1.0, 1.0), 100, (-1.0, 1.0))
    p = np.exp(-0.5 * (np.linspace(-1, 1, 100) / 0.1) ** 2)
    p *= 0.4 / p.sum()  # 40 % of the source's rays on the screen
    blur = {"detector_blur": {"sigma": sigma}}
    rng = np.random.default_rng(7)
    n = 2000
    draws = np.array([E.apply_detector_effects(rng.multinomial(n, np.r_[p, 0.6])[None, :100] / n, p[None], blur,
                                               spec)[0][0] for _ in range(3000)])
    f, _ = E.apply_detector_effects(p[None], p[None], blur, spec)
    noise, _ = E.detector_noise(p[None], p[None], blur, spec)
    predicted = bin_variance(f, f, np.inf, n, model_noise=noise)[0]
    bins = [50, 55, 60]
    np.testing.assert_allclose(draws[:, bins].var(0), predicted[bins], rtol=0.1)
    assert np.all(bin_variance(f, f, np.inf, n)[0][bins] > 2 * predicted[bins])
    more = {**blur, "intensity_scale": {"delta": 0.2}}
    g, _ = E.apply_detector_effects(p[None], p[None], more, spec)
    shared, _ = E.detector_noise(p[None], p[None], more, spec)
    ratio = bin_variance(g, g, np.inf, n, model_noise=shared)[0] / bin_variance(g, g, np.inf, n)[0]
    np.testing.assert_allclose(ratio[bins], (predicted / bin_variance(f, f, np.inf, n)[0])[bins], rtol=0.15)
    alone = {"intensity_scale": {"delta": 0.2}, "background": {"level": 1e-3}}
    h, _ = E.apply_detector_effects(p[None], p[None], alone, spec)
    np.testing.assert_allclose(bin_variance(h, h, np.inf, n, model_noise=E.detector_noise(p[None], p[None], alone,
                                                                                          spec)[0]),
                               bin_variance(h, h, np.inf, n))


def test_bad_effect_input():
    with pytest.raises(ValueError, match="unknown effect 'warp'"):
        E.twin_overrides({"warp": {}})
    with pytest.raises(ValueError, match="no parameter"):
        E.twin_overrides({"chamber_z": {"w": 1.0}})
    with pytest.raises(ValueError, match="not finite"):
        E.twin_overrides({"chamber_z": {"z": float("nan")}})
    with pytest.raises(ValueError, match="takes 3 values"):
        E.ChamberTranslation().values([1.0])


def test_a_user_effect_is_one_small_class(twin):
    class EntranceSlitShift(E.Effect):
        name = "entrance_slit_shift_test"
        description = "entrance slit displaced horizontally"
        parameters = (E.EffectParameter("x", "mm", -8.0, 8.0, "horizontal shift"),)

        def overrides(self, v):
            return {"Entrance-Slit": {"translationXerror": v["x"]}}

    E.register(EntranceSlitShift())
    try:
        moved = twin.trace(METRIXS.reference, n_rays=3000, seed=1,
                           overrides=E.twin_overrides({"entrance_slit_shift_test": {"x": 8.0}}))
        assert moved.transmission < 0.5  # the 10 mm wide slit now clips the beam
    finally:
        del E.EFFECTS["entrance_slit_shift_test"]
