"""Model vs. measurement on twin data: misfit within noise when the model is right,
beyond noise and with the right signature when an effect is missing."""

import numpy as np
import pytest

from bluesky_offsets.physics import effects as E
from bluesky_offsets.model.misfit import (MeasurementError, correlate_with_parameters, failing_regions, misfit,
                                         plot_overlays, plot_residual_maps, residual_signature)
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.twin import HistogramSpec, Twin

N_MEAS, N_MODEL = 10_000, 40_000


@pytest.fixture(scope="module")
def data():
    twin = Twin(scheduler="inline")
    rng = np.random.default_rng(5)
    cfgs = np.tile(METRIXS.reference, (8, 1))
    cfgs[:, METRIXS.index("E1.rotationXerror")] = rng.uniform(-0.6, 0.6, 8)
    cfgs[:, METRIXS.index("E2.rotationXerror")] = rng.uniform(-0.3, 0.3, 8)
    hidden = E.twin_overrides({"chamber_z": {"z": 20.0}})

    def run(overrides, n, seed):
        res = [twin.trace(c, n_rays=n, seed=seed + i, overrides=overrides) for i, c in enumerate(cfgs)]
        return np.stack([r.hist_x for r in res]), np.stack([r.hist_y for r in res])

    return {"cfgs": cfgs, "meas": run(hidden, N_MEAS, 100), "right": run(hidden, N_MODEL, 200),
            "wrong": run({}, N_MODEL, 300)}


def test_correct_model_is_within_noise(data):
    (mx, my), (fx, fy) = data["meas"], data["right"]
    m = misfit(mx, my, fx, fy, N_MEAS, model_rays=N_MODEL)
    assert 0.6 < m.chi2_reduced_total < 1.5
    assert not m.total_beyond_noise()
    assert m.mse_total < 2 * m.expected_mse_total


def test_faint_model_background_does_not_inflate_the_degrees_of_freedom(data):
    """A background in the model fills every bin; nearly empty bins must not count as whole
    degrees of freedom (they did: chi2/dof ~ 1 with the MSE 11x its noise, demo run v7)."""
    (mx, my), (fx, fy) = data["meas"], data["wrong"]
    plain = misfit(mx, my, fx, fy, N_MEAS, model_rays=N_MODEL)
    faint = 2.5e-6  # 0.025 rays per bin at N_MEAS
    bg = misfit(mx, my, fx + faint, fy + faint, N_MEAS, model_rays=N_MODEL)
    empty = int(((mx == 0) & (fx == 0)).sum() + ((my == 0) & (fy == 0)).sum())
    assert empty > 500
    assert bg.dof_total - plain.dof_total == pytest.approx(empty * faint * N_MEAS, rel=1e-6)
    assert bg.chi2_total == pytest.approx(plain.chi2_total, rel=1e-3)
    assert bg.chi2_reduced_total > 5 and bg.mse_total > 5 * bg.expected_mse_total


def test_a_spot_within_one_bin_has_a_finite_misfit():
    """Every ray in one bin in both the frame and the model: the bin's counting variance p (1 - p)
    is kept one ray from 0 (it was 0 there, and the misfit NaN)."""
    one = np.zeros((1, 50))
    one[0, 20] = 1.0
    near = one.copy()
    near[0, 20], near[0, 21] = 0.999, 0.001
    mf = misfit(one, one, near, one, 5000, model_rays=2000)
    assert np.isfinite(mf.chi2).all() and 0 < mf.chi2_total < 10


def test_missing_effect_is_beyond_noise_with_its_signature(data, tmp_path):
    (mx, my), (fx, fy) = data["meas"], data["wrong"]
    m = misfit(mx, my, fx, fy, N_MEAS, model_rays=N_MODEL)
    assert m.chi2_reduced_total > 5 and m.total_beyond_noise()
    assert m.beyond_noise().sum() >= 6
    spec = HistogramSpec()
    sig = residual_signature(mx, my, fx, fy, spec).mean()
    # chamber 20 mm downstream: the measured spot is wider in y and narrower in x than modelled
    assert sig["y.width"] < -0.01 and sig["x.width"] > 0.01
    assert abs(sig["x.intensity"]) < 0.02
    regions = failing_regions(m, spec)
    assert regions and {r["axis"] for r in regions} <= {"x", "y"}
    corr = correlate_with_parameters(residual_signature(mx, my, fx, fy, spec), data["cfgs"], METRIXS.names)
    assert all(name in ("E1.rotationXerror", "E2.rotationXerror") for _, name, _ in corr)
    assert plot_overlays(mx, my, fx, fy, spec, tmp_path / "o.png", m).stat().st_size > 10_000
    assert plot_residual_maps(m, spec, tmp_path / "r.png").stat().st_size > 5_000


@pytest.mark.parametrize("mutate, message", [
    (lambda x, y: (x[:, :40], y), "the model's x histograms have 50 bins, the measurement's 40"),
    (lambda x, y: (x, y[:3]), r"y histograms must be"),
    (lambda x, y: (np.where(np.arange(50) == 7, np.nan, x), y), "non-finite bin 7"),
    (lambda x, y: (x, -y), "negative"),
])
def test_bad_measurements_are_refused(data, mutate, message):
    mx, my = mutate(*data["meas"])
    fx, fy = data["right"]
    with pytest.raises(MeasurementError, match=message):
        misfit(mx, my, fx, fy, N_MEAS)


def test_beam_features_of_a_known_beam():
    """Intensity, centroid and width of a Gaussian beam binned at the camera's resolution,
    with noise variances that match the scatter of repeated finite-ray frames."""
    from bluesky_offsets.model.misfit import FEATURE_NAMES, beam_features
    from bluesky_offsets.physics.twin import CAMERA
    rng = np.random.default_rng(1)
    n_rays, frames = 5000, 200
    feats = []
    for _ in range(frames):
        k = rng.binomial(n_rays, 0.3)  # 30 % of the rays reach the screen
        x, y = rng.normal(0.5, 0.07, k), rng.normal(-0.2, 0.02, k)
        feats.append(beam_features(*CAMERA.histograms(x, y, n_rays), CAMERA, n_rays))
    f = np.array([a for a, _ in feats])
    var = np.array([v for _, v in feats]).mean(0)
    assert len(FEATURE_NAMES) == f.shape[1] == 5
    np.testing.assert_allclose(f.mean(0), [0.3, 0.5, 0.07, -0.2, 0.02], rtol=0.02, atol=1e-3)
    # the stated variances are the frame-to-frame scatter (within the sampling error of 200 frames)
    np.testing.assert_allclose(f.var(0) / var, 1.0, atol=0.35)
    # a dark frame has an intensity but no position: its centroid weighs nothing
    dark, dvar = beam_features(np.zeros(CAMERA.bins_x), np.zeros(CAMERA.bins_y), CAMERA, n_rays)
    assert dark[0] == 0 and dvar[1] > 100 and np.all(np.isfinite(dark))


@pytest.mark.parametrize("width, kept", [(0.05, False), (2.0, True)])
def test_a_camera_width_the_noise_swamps_is_left_out(width, kept):
    """A camera frame's noise over the whole window (0.5 photons of 5,000 a bin, as the simulated
    camera's): a 50 µm focus's width is not compared (its variance the window's), a 2 mm beam's is,
    without bias and with a variance that matches its scatter."""
    from bluesky_offsets.model.misfit import beam_features
    from bluesky_offsets.physics.twin import CAMERA
    rng = np.random.default_rng(5)
    n_rays, frames, floor = 5000, 200, 1.2e-8
    fx_floor, fy_floor = np.full(CAMERA.bins_x, floor), np.full(CAMERA.bins_y, floor)
    feats = []
    for _ in range(frames):
        k = rng.binomial(n_rays, 0.3)
        hx, hy = CAMERA.histograms(rng.normal(0.5, width, k), rng.normal(-0.2, 0.02, k), n_rays)
        hx = hx + rng.normal(0, np.sqrt(floor), hx.shape)
        feats.append(beam_features(hx, hy, CAMERA, n_rays, fx_floor, fy_floor))
    f, var = np.array([a for a, _ in feats])[:, 2], np.array([v for _, v in feats])[:, 2]
    window = (CAMERA.centers_x[-1] - CAMERA.centers_x[0]) ** 2
    if not kept:
        assert np.mean(var >= window) > 0.95, np.mean(var >= window)
        return
    assert np.all(var < 0.1), var.max()
    assert abs(f.mean() - width) < 3 * np.sqrt(var.mean() / frames), (f.mean(), np.sqrt(var.mean()))
    assert 0.7 < f.var() / var.mean() < 1.4, f.var() / var.mean()


def test_histogram_specs_rebin_and_describe_themselves():
    from bluesky_offsets.physics.twin import CAMERA
    paper = HistogramSpec()
    assert CAMERA.factors(paper) == (20, 24)
    rng = np.random.default_rng(2)
    x, y = rng.normal(0, 1, 5000), rng.normal(0, 0.5, 5000)
    fx, fy = CAMERA.histograms(x, y, 5000)
    cx, cy = CAMERA.rebin(fx, fy, paper)
    px, py = paper.histograms(x, y, 5000)
    np.testing.assert_allclose(cx, px, atol=1e-12)
    np.testing.assert_allclose(cy, py, atol=1e-12)
    assert HistogramSpec.from_centers(CAMERA.centers_x, CAMERA.centers_y) == CAMERA
    assert HistogramSpec.from_fingerprint(CAMERA.fingerprint()) == CAMERA
    with pytest.raises(ValueError, match="cannot be re-binned"):
        paper.factors(CAMERA)
    with pytest.raises(ValueError, match="not uniform"):
        HistogramSpec.from_centers([0, 1, 3], [0, 1])
