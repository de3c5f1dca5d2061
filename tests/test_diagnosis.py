"""Which effect is missing: fits through the differentiable twin on data RAYX made with a hidden
effect (small, fast setup)."""

import numpy as np
import pytest

from bluesky_offsets.physics import effects as E
from bluesky_offsets.model.diagnosis import (
    Version, add_effect, diagnose, evaluate, plot_error_history, plot_ranking, retest_effects, weakest)
from bluesky_offsets.model.misfit import MeasurementError
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.model.state import ModelState, refine, simulate, simulate_frames
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.twin import Twin

pytestmark = pytest.mark.slow  # over a minute: scheduled first (conftest)

N_RAYS = 4000
# offsets hidden in three sensitive motors
HIDDEN = {"E1.rotationXerror": 0.012, "E2.rotationXerror": -0.01, "M1_Cylinder.rotationXerror": 0.008}
# 8 configurations in the paper's 50 x 50 bins hold ~40 degrees of freedom for 34 offsets: the
# offsets get the prior of a beamline aligned to a few per cent (without it the compensating
# combinations fit the rays of the fit, and fresh rays see a worse fit)
# In the paper's bins the focus fills a bin or two and the features do most of the work: they get
# all the fit's rays here (with 2000, the default for camera bins, this fit ends above the noise)
# one draw of the model's rays and no starts drawn from the posterior: FitOptions.ray_draws and
# posterior_starts are tested in tests/test_fit.py and, at the analysis's defaults, by the IOC
# demos (tests/test_diagnosis_ioc.py)
FIT = {"rays": 2 * N_RAYS, "feature_rays": None, "stages": [["features", 10], ["bins", 6]], "prior_sigma": 0.03,
       "ray_draws": 1, "posterior_starts": 0}
SCAN = {"rays": N_RAYS, "stages": [["features", 4], ["bins", 4]], "prior_sigma": 0.03}
CANDIDATES = ["intensity_scale", "background", "detector_blur", "chamber_z"]


@pytest.fixture(scope="module")
def twin():
    return Twin(scheduler="inline", n_rays=N_RAYS)


def _measure(twin, effect=None):
    rng = np.random.default_rng(3)
    cfgs = METRIXS.denormalize(0.5 + rng.uniform(-0.01, 0.01, (8, len(METRIXS))))
    off = np.zeros(len(METRIXS))
    for n, v in HIDDEN.items():
        off[METRIXS.index(n)] = v
    truth = ModelState(off, {effect[0]: E.get(effect[0]).values(effect[1])} if effect else {})
    # a detector effect (a gain loss) acts on each photon: frames as a camera counts them
    hx, hy = simulate_frames(twin, cfgs, truth, N_RAYS, seed=[900 + i for i in range(len(cfgs))])
    return Measurement(cfgs, hx, hy, N_RAYS), truth


# A quarter of the flux lost.  At -15 % the diagnosis' offsets-only refit (all 34 offsets,
# slit openings among them) reached chi2/dof 0.90 in the twin's bins on this design once the
# source frame was written the way RAYX reads it (the measurement's draw changed): a loss that
# size is within the offsets' reach here, and "within noise" is then the right verdict.
GAIN_LOSS = -0.25


@pytest.fixture(scope="module")
def with_gain_loss(twin):
    meas, truth = _measure(twin, ("intensity_scale", {"delta": GAIN_LOSS}))
    fit = refine(meas, ModelState(), twin, options=FIT)
    return meas, truth, fit


def test_refine_finds_the_offsets_through_the_twin(twin):
    meas, truth = _measure(twin)
    start = evaluate(meas, ModelState(), twin)
    fit = refine(meas, ModelState(), twin, options=FIT)
    end = evaluate(meas, fit.state, twin)
    assert start.chi2_reduced_total > 5 and end.chi2_reduced_total < 1.5
    assert [h["stage"] for h in fit.history if h["iteration"] == 0] == ["features", "bins"]
    # (the offsets themselves are only determined up to compensating combinations)
    d = diagnose(meas, fit.state, twin, candidates=CANDIDATES, options=SCAN)
    assert d.verdict == "no significant missing effect", d.as_dict()
    # within noise, nothing is fitted, and what that cannot exclude is said: how large each
    # candidate could be and still hide behind the offsets, every parameter of every candidate
    assert d.within_noise and not d.candidates
    assert {n: set(v) for n, v in d.limits.items()} == {
        n: {p.name for p in E.get(n).parameters} for n in CANDIDATES}, d.limits
    assert all(lim > 0 for v in d.limits.values() for lim in v.values()), d.limits
    assert "how large each could be and still hide" in d.notes[-1]
    # offsets of a narrower spread (estimated by the offsets fit) absorb less: less can hide
    narrow = diagnose(meas, fit.state, twin, candidates=CANDIDATES, options=SCAN, spread=0.25 * SCAN["prior_sigma"])
    assert all(narrow.limits[n][q] <= d.limits[n][q] * (1 + 1e-9) for n in d.limits for q in d.limits[n])
    assert any(narrow.limits[n][q] < 0.9 * d.limits[n][q] for n in d.limits for q in d.limits[n])


def test_hidden_effect_ranked_first_and_fitted(twin, with_gain_loss, tmp_path):
    meas, truth, fit = with_gain_loss
    d = diagnose(meas, fit.state, twin, candidates=CANDIDATES, options=SCAN)
    assert d.best is not None and d.best.name == "intensity_scale", d.as_dict()
    assert d.candidates[0].name == "intensity_scale"
    assert d.observed_signature["x.intensity"] < 0 and d.candidates[0].predicted_signature["x.intensity"] < 0
    # the best's lead over each other verified candidate is measured; a tie would be said
    assert all((c.behind_z is not None) == (c.refined and c is not d.best and c.score > 0) for c in d.candidates)
    assert d.verdict.startswith("missing effect: intensity_scale (")
    assert ("not told apart from" in d.verdict) == bool(d.rivals), (d.verdict, [c.behind_z for c in d.candidates])
    state, sigma = add_effect(meas, fit.state, "intensity_scale", twin, values=d.best.values, options=FIT)
    fitted, s = state.effects["intensity_scale"]["delta"], sigma["intensity_scale"]["delta"]
    assert fitted == pytest.approx(GAIN_LOSS, rel=0.25) and 0 < s < 0.05
    assert abs(fitted - GAIN_LOSS) <= 3 * s, (fitted, s)
    versions = [Version("twin", ModelState(), evaluate(meas, ModelState(), twin)),
                Version("+ offsets", fit.state, evaluate(meas, fit.state, twin)),
                Version("+ intensity_scale", state, evaluate(meas, state, twin), sigma)]
    chi = [v.misfit.chi2_reduced_total for v in versions]
    assert chi[0] > chi[1] > chi[2] and versions[2].misfit.mse_total < 1.5 * versions[2].misfit.expected_mse_total
    assert plot_error_history(versions, tmp_path / "h.png").stat().st_size > 5000
    assert plot_ranking(d, tmp_path / "r.png").stat().st_size > 5000
    # the backward step: an effect added beside the true one that buys nothing is dropped, the
    # true one is kept (the model without it is far beyond noise)
    both = state.with_effect("background", {"level": 0.0})
    tests = {t.effect: t for t in retest_effects(meas, both, options=FIT)}
    assert tests["intensity_scale"].kept and tests["intensity_scale"].beyond_noise_without
    assert not tests["background"].kept and tests["background"].gain < tests["background"].price
    assert weakest(list(tests.values())).effect == "background"
    assert "background" not in tests["background"].without.state.effects


def test_model_versions_and_bad_data():
    st = ModelState().with_effect("chamber_z")
    assert st.effects == {"chamber_z": {"z": 0.0}} and "chamber_z" in st.label
    with pytest.raises(ValueError, match="already includes"):
        st.with_effect("chamber_z")
    with pytest.raises(ValueError, match="unknown effect"):
        st.with_effect("gravity")
    cfg = np.tile(METRIXS.reference, (2, 1))
    with pytest.raises(MeasurementError, match="2 configurations but 3"):
        Measurement(cfg, np.zeros((3, 50)), np.zeros((3, 50)), 1000)
    with pytest.raises(MeasurementError, match="parameter-table version 0000"):
        Measurement(cfg, np.zeros((2, 50)), np.zeros((2, 50)), 1000,
                    metadata={"parameter_table_version": "0000"}).for_analysis()
    bad = cfg.copy()
    bad[1, 3] = np.nan
    with pytest.raises(MeasurementError, match="U41_318eV.rotationYerror"):
        Measurement(bad, np.zeros((2, 50)), np.zeros((2, 50)), 1000).for_analysis()


def test_measurement_from_the_run_store():
    cfg = np.tile(METRIXS.reference, (2, 1))
    stored = Measurement(cfg, np.zeros((2, 50)), np.zeros((2, 50)), uid="u1",
                         metadata={"n_rays": 5000, "parameter_table_version": METRIXS.version})
    m = stored.for_analysis()
    assert m.n == 2 and m.n_rays == 5000 and m.uid == "u1"
    with pytest.raises(MeasurementError, match="ray budget"):
        Measurement(cfg, np.zeros((2, 50)), np.zeros((2, 50))).for_analysis()
    with pytest.raises(MeasurementError, match="version"):
        Measurement(cfg, np.zeros((2, 50)), np.zeros((2, 50)),
                    metadata={"n_rays": 1, "parameter_table_version": "xyz"}).for_analysis()


@pytest.mark.parametrize("change, message", [
    (lambda c, hx, hy: (c, hx[:, :40], hy), r"x histograms must be \(configurations, 50\), got \(2, 40\)"),
    (lambda c, hx, hy: (c, hx, hy[:, :49]), r"y histograms must be \(2, 50\), got \(2, 49\)"),
    (lambda c, hx, hy: (c, hx[..., None], hy), r"x histograms must be .* got \(2, 50, 1\)"),
    (lambda c, hx, hy: (c, np.where(np.arange(50) == 7, np.nan, hx), hy), "non-finite bin 7"),
    (lambda c, hx, hy: (c, hx, -hy), "negative bins"),
    (lambda c, hx, hy: (c[:, :33], hx, hy), r"34 parameters in table order, got shape \(2, 33\)"),
])
def test_measurement_refuses_wrong_shapes_and_nan(change, message):
    cfg = np.tile(METRIXS.reference, (2, 1))
    hist = np.full((2, 50), 0.01)
    c, hx, hy = change(cfg, hist, hist)
    with pytest.raises(MeasurementError, match=message):
        Measurement(c, hx, hy, 1000).for_analysis()


def test_stored_measurement_with_another_parameter_table_is_refused():
    names = list(METRIXS.names)
    names[0] = "U41.tx"
    stored = Measurement(np.tile(METRIXS.reference, (2, 1)), np.zeros((2, 50)), np.zeros((2, 50)), names=names,
                         metadata={"n_rays": 1000})
    with pytest.raises(MeasurementError, match=r"missing \['U41_318eV.translationXerror'\], unexpected \['U41.tx'\]"):
        stored.for_analysis()


# --------------------------------------------------------------------------- #
# at the camera's resolution: the path the demo and the IOC tests take
# --------------------------------------------------------------------------- #
@pytest.fixture(scope="module")
def camera_case():
    """A defocus (the screen 20 mm downstream) hidden behind offsets, measured at the camera's
    resolution on a small diagnostic design, and the offsets fitted from the nominal twin
    (features first, then bins)."""
    from bluesky_offsets.model.diagnosis import diagnostic_configurations
    from bluesky_offsets.physics.twin import CAMERA
    from sim_iocs.truth import default_start
    twin = Twin(scheduler="inline", n_rays=N_RAYS).with_hist(CAMERA)
    cfgs = diagnostic_configurations(default_start(), 8, seed=1)
    off = np.zeros(len(METRIXS))
    for n, v in HIDDEN.items():
        off[METRIXS.index(n)] = v
    truth = ModelState(off, {"chamber_z": {"z": 20.0}})
    hx, hy = simulate(twin, cfgs, truth, N_RAYS, seed=[500 + i for i in range(len(cfgs))])
    meas = Measurement(cfgs, hx, hy, N_RAYS, spec=CAMERA)
    fit = refine(meas, ModelState(), twin, options=FIT)
    return twin, meas, truth, fit


def test_feature_stage_then_diagnosis_find_a_hidden_defocus(camera_case):
    """The workflow's physics on a small design (8 configurations, 4000 rays): the acceptance
    numbers (magnitude within 25 %, misfit within 1.5x noise) are checked on the demo's design
    against the IOC (tests/test_diagnosis_ioc.py)."""
    from bluesky_offsets.model.diagnosis import add_effect_result
    twin, meas, truth, fit = camera_case
    features = [h["chi2"] for h in fit.history if h["stage"] == "features"]
    assert features[-1] < 0.5 * features[0]  # the offsets alone explain part of it ...
    truth_mf = evaluate(meas, truth, twin)
    at_truth = truth_mf.chi2_reduced_total
    offsets_only = evaluate(meas, fit.state, twin).chi2_reduced_total
    # ... not all of it: the rest is beyond what the noise gives, by the diagnosis's own 3σ (Δχ²
    # in σ of a χ² of dof degrees of freedom)
    dof = truth_mf.dof_total
    assert (offsets_only - at_truth) * dof > 3 * np.sqrt(2 * dof), dof
    # the candidates side by side (two detector-level ones: their forward-mode derivatives
    # take turns: bluesky_offsets.physics.engine.FORWARD_AD)
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(2) as ex:
        d = diagnose(meas, fit.state, twin, candidates=["chamber_z", "detector_blur", "intensity_scale"], options=SCAN,
                     executor=ex)
    assert d.best is not None and d.best.name == "chamber_z", d.as_dict()
    assert d.candidates[0].refined and d.candidates[0].delta_chi2_twin > 0
    start = ModelState(d.best.refined_state.offsets)
    res = add_effect_result(meas, start, "chamber_z", twin, values=d.best.values, options=FIT)
    z, sz = res.state.effects["chamber_z"]["z"], res.effect_sigma["chamber_z"]["z"]
    assert abs(z - 20.0) <= max(3 * sz, 5.0), (z, sz)  # downstream, as hidden
    # adding it gives back most of what the offsets could not explain
    assert evaluate(meas, res.state, twin).chi2_reduced_total < at_truth + 0.3 * (offsets_only - at_truth)


def test_adding_an_effect_starts_where_the_diagnosis_fit_it():
    """The refit's start is the candidate fit's end: its offsets and the model's other effects
    as that fit left them (they were fitted together), the candidate itself left to ``values``."""
    from bluesky_offsets.model.diagnosis import Candidate
    end = ModelState(np.full(len(METRIXS), 0.01), {"grating_line_density": {"delta": -0.07},
                                                   "thermal_bump_m1": {"height": 390.0}}, "fit")
    c = Candidate("thermal_bump_m1", 1, {"height": 390.0}, {"height": 12.0}, 0.0, 50.0, 6.0, True, {},
                  refined_state=end)
    st = c.refit_start("model")
    assert np.array_equal(st.offsets, end.offsets) and st.label == "model"
    assert st.effects == {"grating_line_density": {"delta": -0.07}}


def test_the_lead_of_one_model_over_another_is_measured_in_sigma():
    """``lead_z``: Vuong's statistic on the bins' squared pulls of two models traced with the same
    fresh rays. Two models that fit alike are not told apart; one worse in every bin by a
    little is; a price difference counts against the dearer model."""
    from bluesky_offsets.model.diagnosis import lead_z
    from bluesky_offsets.model.misfit import Misfit

    rng = np.random.default_rng(3)

    def mf(px, py):
        return Misfit(np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4), px, py)

    px, py = rng.normal(size=(4, 200)), rng.normal(size=(4, 200))
    same = lead_z(mf(px, py), mf(px, py))
    assert same == 0.0
    # another model: the same noise, its own shape error of about 1 σ in every bin (2·800 = 1600
    # more χ² against a spread of ~ 2 √(1600))
    worse = mf(px + 1.0, py + 1.0)
    z = lead_z(mf(px, py), worse)
    assert z > 10 and lead_z(worse, mf(px, py)) == pytest.approx(-z)
    # a model that differs by noise alone: |z| of order 1
    other = mf(px + 0.05 * rng.normal(size=px.shape), py + 0.05 * rng.normal(size=py.shape))
    assert abs(lead_z(mf(px, py), other)) < 3
    # the dispersion divides lead and spread alike; a price moves the lead
    assert lead_z(mf(px, py), worse, dispersion=2.0) == pytest.approx(z)
    assert lead_z(mf(px, py), worse, price=1e6) < 0
