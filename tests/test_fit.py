"""The one fit engine: exact Jacobians from the rays, and fits through the differentiable twin
of measurements the reference twin (RAYX) made."""

import contextlib
import pickle
import time

import numpy as np
import pytest
import torch

from bluesky_offsets.blas import numpy_avx512_targets, x86_with_avx2
from bluesky_offsets.physics import effects as E
from bluesky_offsets.model.fit import (FRESH_SEED, POSTERIOR_ROUNDS, RAY_DRAW_SEED, SETTLE_FRACTIONS, FitOptions,
                                      _Model, _objective, _Products, _ridge, fit, screen)
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.model.misfit import misfit
from bluesky_offsets.model.state import ModelState, simulate, simulate_frames, simulate_with_noise
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.engine import TorchEngine
from bluesky_offsets.physics.twin import CAMERA, HistogramSpec, Twin
from sim_iocs.truth import default_start


def _configurations(n, seed=0, spread=0.01):
    rng = np.random.default_rng(seed)
    base = METRIXS.normalize(default_start())
    z = np.clip(base + rng.uniform(-spread, spread, (n, len(METRIXS))), 0, 1)
    return np.where(METRIXS.motorized, METRIXS.denormalize(z), METRIXS.reference)


def test_ray_jacobian_gives_the_soft_histograms_exact_jacobian():
    """Per-ray derivatives binned by the chain rule equal one batched backward pass through the
    soft histograms (same rays), parameters and an effect alike."""
    eng = TorchEngine()
    cfg = _configurations(2)
    eff = {"chamber_z": {"z": 4.0}}
    _, J_ref, names = eng.jacobian("histograms", cfg, eff, n_rays=1500, seed=5, spec=HistogramSpec())
    rj = eng.ray_jacobian(cfg, eff, n_rays=1500, seed=5, chunk=1000)  # several chunks
    h, J = rj.histograms(HistogramSpec(), kernel=eng.options.kernel)
    assert rj.names == names and J.shape == J_ref.shape == (2, 100, 35)
    assert float((J - J_ref).abs().max()) <= 1e-9 * float(J_ref.abs().max())
    # the values are the hard counts of the same rays (RAYX's survival and binning)
    from bluesky_offsets.physics.engine import histograms
    hx, hy = histograms(eng.beam(cfg, E.twin_overrides(eff), n_rays=1500, seed=5), HistogramSpec())
    assert torch.equal(h, torch.cat([hx, hy], 1))
    # every ray's position and survival bit for bit the soft beam's, its weight to the last bit:
    # the chunks put other rays in the vectorized transcendental functions' scalar tails, which may
    # round differently in a weight's last bit; derivatives only for the rays with weight
    from bluesky_offsets.physics.engine import RAY_WEIGHT_FLOOR
    soft = eng.beam(cfg, E.twin_overrides(eff), n_rays=1500, seed=5, edge=eng.options.edge)
    assert all(torch.equal(getattr(rj, k), getattr(soft, k)) for k in ("x", "y", "alive"))
    torch.testing.assert_close(rj.weight, soft.weight, rtol=2.0**-52, atol=0.0)
    assert torch.equal(rj.rows, torch.nonzero(soft.weight.reshape(-1) > RAY_WEIGHT_FLOOR).squeeze(1))
    assert 0 < rj.rows.numel() < soft.weight.numel()
    # the derivatives in a few inputs alone (the beam optimizer's E1/E2): the same columns
    cols = [names.index("E1.rotationXerror"), names.index("E2.translationZerror"), names.index("chamber_z.z")]
    sub = eng.ray_jacobian(cfg, eff, n_rays=1500, seed=5, chunk=1000, columns=cols)
    assert sub.names == [names[c] for c in cols] and torch.equal(sub.rows, rj.rows)
    for full, part in ((rj.rows_jx, sub.rows_jx), (rj.rows_jy, sub.rows_jy), (rj.rows_jw, sub.rows_jw)):
        assert float((full[:, cols] - part).abs().max()) <= 1e-12 * max(float(full.abs().max()), 1.0)
    # the values a fit's step has just traced are taken instead of traced again: the same
    # histograms and Jacobian (the weights may differ in the last bit, as above)
    again = eng.ray_jacobian(cfg, eff, n_rays=1500, seed=5, chunk=1000, full=soft)
    h2, J2 = again.histograms(HistogramSpec(), kernel=eng.options.kernel)
    assert torch.equal(h2, h) and torch.equal(again.rows, rj.rows)
    assert float((J2 - J).abs().max()) <= 1e-12 * float(J.abs().max())
    with pytest.raises(ValueError, match=r"full: rays of shape \(2, 1500\), not \(2, 1000\)"):
        eng.ray_jacobian(cfg, eff, n_rays=1000, seed=5, full=soft)


def test_pitch_moves_the_focus_along_x():
    """The physics of a column: E1's pitch offset moves the centroid along +x."""
    eng = TorchEngine()
    rj = eng.ray_jacobian(_configurations(3), n_rays=2000, seed=1)
    j = METRIXS.index("E1.rotationXerror")
    w = rj.alive.double()
    dcx = ((rj.jx[:, :, j] * w).sum(1) / w.sum(1)).numpy()  # d centroid / d pitch (mm per mrad)
    assert np.all(dcx > 1.0), dcx


def test_fit_options_are_typed_and_refuse_unknown_keys():
    with pytest.raises(ValueError, match=r"unknown fit option\(s\) \['raysx'\]"):
        FitOptions.from_mapping({"raysx": 100})
    with pytest.raises(ValueError, match="a stage is"):
        FitOptions(stages=(("pixels", 3),))
    with pytest.raises(ValueError, match="at least one stage"):
        FitOptions(stages=())
    o = FitOptions.from_mapping({"rays": 100, "stages": [["bins", 2]]})
    assert o.stages == (("bins", 2),) and o.replace(seed=3).seed == 3
    with pytest.raises(ValueError, match="unknown fit option"):
        o.replace(sead=3)


def test_detector_effect_columns_are_exact():
    """Blur, background and gain act on the histograms; their columns match differences."""
    cfg = _configurations(2)
    hx = np.full((2, 50), 0.01)
    meas = Measurement(cfg, hx, hx, 1000)
    st = ModelState().with_effect("detector_blur", {"sigma": 0.2}).with_effect("intensity_scale", {"delta": 0.1})
    st = st.with_effect("background", {"level": 1e-4})
    mdl = _Model(meas, st, TorchEngine(), FitOptions(rays=800, seed=2), METRIXS)
    z = mdl.vector(st)
    h, J, _ = mdl.histograms(z, True)
    for k in range(len(METRIXS), len(z)):
        dz = np.zeros_like(z)
        dz[k] = 1e-6 * max(abs(z[k]), 1e-3)
        hp, _, _ = mdl.histograms(z + dz, False)
        hm, _, _ = mdl.histograms(z - dz, False)
        fd = (hp - hm) / (2 * dz[k])
        assert torch.allclose(J[..., k], fd, rtol=1e-5, atol=1e-9 * float(fd.abs().max() + 1e-30)), mdl.names[k]


@pytest.fixture(scope="module")
def defocus_case():
    """RAYX measures a beamline with offsets in all 34 parameters (±3 % of each range) and the
    screen 15 mm downstream, at the camera's resolution."""
    rng = np.random.default_rng(11)
    off = rng.uniform(-0.03, 0.03, len(METRIXS))
    truth = ModelState(off, {"chamber_z": {"z": 15.0}}, "truth")
    start = default_start() - np.where(METRIXS.motorized, METRIXS.offsets_to_physical(off), 0.0)
    from bluesky_offsets.model.diagnosis import diagnostic_configurations, open_aperture
    cfg = diagnostic_configurations(start, 6, seed=2)
    cfg = np.vstack([cfg, open_aperture(cfg[:2])])
    twin = Twin(scheduler="inline").with_hist(CAMERA)
    hx, hy = simulate(twin, cfg, truth, 4000, seed=[70 + i for i in range(len(cfg))])
    return Measurement(cfg, hx, hy, 4000, spec=CAMERA), truth, twin


def test_fit_through_the_differentiable_twin_recovers_a_hidden_defocus(defocus_case):
    meas, truth, twin = defocus_case
    from bluesky_offsets.model.diagnosis import evaluate
    opts = FitOptions(rays=4000, seed=3, stages=(("features", 12), ("profiles", 6), ("bins", 8)))
    eng = TorchEngine(hist=CAMERA)
    seen = []
    res = fit(meas, ModelState().with_effect("chamber_z"), eng, opts, progress=seen.append)
    assert [h["stage"] for h in seen if h["iteration"] == 0] == ["features", "profiles", "bins"]
    z, sz = res.state.effects["chamber_z"]["z"], res.effect_sigma()["chamber_z"]["z"]
    print(f"chamber_z {z:.2f} ± {sz:.2f} mm (hidden 15)")
    assert 0 < sz < 15 and abs(z - 15.0) <= max(3 * sz, 0.25 * 15.0), (z, sz)
    # the reference twin (RAYX, fresh rays) agrees with the fitted model to within the noise
    mf = evaluate(meas, res.state, twin, model_rays=16000, seed=99)
    assert mf.chi2_reduced_total < 1.5, mf.chi2_reduced_total
    assert res.covariance.shape == (35, 35) and np.all(np.isfinite(res.sigma))


def test_secant_update_reproduces_the_step_and_keeps_the_rest():
    """Broyden's update: along the step the updated Jacobian gives the change the twin made;
    across it the Jacobian is unchanged."""
    rng = np.random.default_rng(0)
    J = rng.normal(size=(3, 4, 5))
    old = _Products(rng.normal(size=(3, 4)), J, 100)
    new = _Products(rng.normal(size=(3, 4)), None, 100)
    step = rng.normal(size=5)
    up = old.secant(new, step)
    assert np.allclose(up.jacobian.reshape(12, 5) @ step, (new.values - old.values).reshape(-1))
    across = np.linalg.svd(step[None])[2][1]  # a direction orthogonal to the step
    assert np.allclose(up.jacobian.reshape(12, 5) @ across, J.reshape(12, 5) @ across)
    assert up.values is new.values


def test_secant_fit_reads_its_uncertainty_from_the_twins_jacobian(defocus_case):
    """With secant updates between exact Jacobians (an option) a fit still lowers χ² and its
    covariance is read from the twin's own Jacobian at the solution, not from an update."""
    meas, truth, twin = defocus_case
    opts = FitOptions(rays=2000, seed=3, stages=(("features", 10), ("bins", 6)), secant=True)
    eng = TorchEngine(hist=CAMERA)
    start = ModelState(truth.offsets * 0.7, {"chamber_z": {"z": 9.0}})
    sec = fit(meas, start, eng, opts)
    assert any(not h["exact"] for h in sec.history)
    for stage in ("features", "bins"):
        chi = [h["chi2"] for h in sec.history if h["stage"] == stage]
        assert chi[-1] < chi[0] and chi == sorted(chi, reverse=True)
    assert all(h["exact"] for h in fit(meas, start, eng, opts.replace(secant=False, stages=(("bins", 2),))).history)
    mdl = _Model(meas, sec.state, eng, opts, METRIXS)
    r, G, _, _ = mdl.residuals("bins", mdl.products("bins", mdl.vector(sec.state), True))
    assert np.array_equal(G, sec.jacobian) and np.array_equal(r, sec.residuals)


def test_screen_is_a_cheap_look_that_only_goes_down(defocus_case):
    """A screen: one Jacobian of the twin, a few steps on the features, the bins χ² where they
    ended; it never raises the features χ² and reads no uncertainty."""
    meas, truth, twin = defocus_case
    opts = FitOptions(rays=2000, seed=3, stages=(("features", 5), ("bins", 5)))
    eng = TorchEngine(hist=CAMERA)
    start = ModelState(truth.offsets * 0.5, {"chamber_z": {"z": 8.0}})
    res = screen(meas, start, eng, opts, iterations=4)
    feats = [h["chi2"] for h in res.history if h["stage"] == "features"]
    assert feats == sorted(feats, reverse=True) and res.history[-1]["stage"] == "bins"
    assert res.chi2 == res.history[-1]["chi2"] and np.all(np.isnan(res.covariance))
    assert res.n_traces == 6 * meas.n  # one Jacobian, four steps, the bins


def test_a_fine_stage_starts_no_worse_than_the_fit_did(defocus_case):
    """Each stage after the first starts from the better, on its own comparison, of the fit's start
    and where the stage before ended: a fit started near the bins' solution does not leave it for
    the features' optimum (here moved by a faint pedestal) and end above it in the bins."""
    meas, truth, twin = defocus_case
    # a faint pedestal over the screen: a little in each bin, much in the widths' second moments
    meas = Measurement(meas.configurations, meas.hist_x + 2e-5, meas.hist_y, meas.ray_budget, spec=CAMERA)
    opts = FitOptions(rays=1500, seed=3, stages=(("features", 6), ("bins", 3)))
    eng = TorchEngine(hist=CAMERA)
    mdl = _Model(meas, truth, eng, opts, METRIXS)
    z = mdl.vector(truth)
    at_start = _objective(mdl.residuals("bins", mdl.products("bins", z, False))[0], z, _ridge(mdl, opts))
    res = fit(meas, truth, eng, opts)
    bins = [h["chi2"] for h in res.history if h["stage"] == "bins"]
    assert bins[0] <= at_start and res.chi2 <= at_start, (bins, at_start)


def test_a_fit_from_several_starts_keeps_the_one_that_ends_lowest(defocus_case):
    """``also_from``: the whole fit from each start; the end lowest on rays none of them traced
    (seed + FRESH_SEED) is kept, its iterations last, each tagged with its start; the same as fitting from
    that start alone.  The jackknife widens an uncertainty, never narrows it."""
    meas, truth, twin = defocus_case
    opts = FitOptions(rays=1500, seed=3, stages=(("bins", 3),))
    eng = TorchEngine(hist=CAMERA)
    near = ModelState(truth.offsets * 0.8, {"chamber_z": {"z": 12.0}})
    far = ModelState(np.clip(-truth.offsets * 4, -0.2, 0.2), {"chamber_z": {"z": -5.0}})
    both = fit(meas, far, eng, opts, also_from=[near])
    alone = [fit(meas, st, eng, opts) for st in (far, near)]
    fresh = [fit(meas, a.state, eng, opts.replace(seed=3 + FRESH_SEED, stages=(("bins", 0),))).history[-1]["chi2"]
             for a in alone]
    kept = int(np.argmin(fresh))
    assert kept == 1 and {h["start"] for h in both.history} == {0, 1} and both.history[-1]["start"] == kept
    assert np.array_equal(both.state.offsets, alone[kept].state.offsets)
    assert np.allclose(both.covariance, alone[kept].covariance)
    assert np.all(both.widened >= 1.0) and np.all(np.isfinite(both.sigma))
    with pytest.raises(ValueError, match="same effects"):
        fit(meas, far, eng, opts, also_from=[ModelState(truth.offsets)])


def test_starts_drawn_from_the_posterior_are_fitted_and_judged_as_the_others(defocus_case):
    """``posterior_starts``: after the given start, that many drawn from the Gaussian posterior at its
    end (a named stream: the same draws every time), each fitted in full, in rounds; the end lowest
    on fresh rays is kept, its iterations last, the same as fitting from its start alone."""
    meas, truth, twin = defocus_case
    opts = FitOptions(rays=1500, seed=3, stages=(("bins", 3),))
    eng = TorchEngine(hist=CAMERA)
    start = ModelState(truth.offsets * 0.5, {"chamber_z": {"z": 8.0}})
    res = fit(meas, start, eng, opts.replace(posterior_starts=2))
    starts = {h["start"] for h in res.history}
    rounds = (len(starts) - 1) // 2  # another round only while one gains beyond the 95 % region
    assert starts == set(range(1 + 2 * rounds)) and 1 <= rounds <= POSTERIOR_ROUNDS
    again = fit(meas, start, eng, opts.replace(posterior_starts=2))
    assert np.array_equal(again.state.offsets, res.state.offsets)
    fresh = opts.replace(seed=3 + FRESH_SEED, stages=(("bins", 0),))
    one = fit(meas, start, eng, opts)
    assert fit(meas, res.state, eng, fresh).history[-1]["chi2"] <= fit(meas, one.state, eng, fresh).history[-1]["chi2"]
    with pytest.raises(ValueError, match="posterior_starts"):
        FitOptions(posterior_starts=-1)


def test_ray_draws_average_the_fit_over_the_models_rays(defocus_case):
    """``ray_draws``: the first draw is the one-draw fit; each later draw is the same fit on
    other rays from where the first ended; the solution is their mean, and the covariance is
    the Gauss-Newton one there plus the draws' scatter (one draw's, not over their number: the
    later draws start where the first ended and are not independent estimates)."""
    meas, truth, twin = defocus_case
    opts = FitOptions(rays=1500, seed=3, stages=(("features", 3), ("bins", 3)))
    eng = TorchEngine(hist=CAMERA)
    start = ModelState(truth.offsets * 0.5, {"chamber_z": {"z": 8.0}})
    one = fit(meas, start, eng, opts)
    res = fit(meas, start, eng, opts.replace(ray_draws=3))
    assert res.draws.shape == (3, len(METRIXS) + 1) and one.draws is None
    assert np.array_equal(res.draws[0], np.r_[one.state.offsets, one.state.effect_vector()])
    later = fit(meas, one.state, eng, opts.replace(seed=3 + 2 * RAY_DRAW_SEED))
    assert np.array_equal(res.draws[2], np.r_[later.state.offsets, later.state.effect_vector()])
    mean = res.draws.mean(0)
    assert np.allclose(np.r_[res.state.offsets, res.state.effect_vector()], mean)
    at_mean = fit(meas, res.state, eng, opts.replace(stages=(("bins", 0),)))
    spread = np.cov(res.draws.T, ddof=1)
    assert np.allclose(res.covariance, at_mean.covariance + spread)
    assert {h.get("ray_draw") for h in res.history} == {None, 1, 2, "mean"}
    assert res.history[-1]["ray_draw"] == "mean" and res.history[-1]["chi2"] == pytest.approx(at_mean.history[-1]["chi2"])
    with pytest.raises(ValueError, match="ray_draws"):
        FitOptions(ray_draws=0)


def test_a_fit_settles_what_the_data_barely_see_where_the_prior_puts_it(defocus_case):
    """``settle`` (an option): the damped steps stop once they gain less than the tolerance; the fit
    then takes one undamped Gauss-Newton step (a part of it where the model bends or the step leaves
    the bounds), kept where it lowers the objective.  The offsets the data barely see come nearer
    the prior's mean."""
    meas, truth, twin = defocus_case
    opts = FitOptions(rays=1500, seed=3, stages=(("features", 3), ("bins", 3)), settle=True)
    eng = TorchEngine(hist=CAMERA)
    start = ModelState(truth.offsets * 0.5, {"chamber_z": {"z": 8.0}})
    damped, settled = fit(meas, start, eng, opts.replace(settle=False)), fit(meas, start, eng, opts)
    last = settled.history[-1]
    assert last["settle"] in SETTLE_FRACTIONS and "settle" not in damped.history[-1]
    ridge = settled.ridge
    ends = [np.r_[f.state.offsets, f.state.effect_vector()] for f in (damped, settled)]
    before, after = (_objective(f.residuals, z, ridge) for f, z in zip((damped, settled), ends))
    assert after <= before and last["chi2"] == pytest.approx(after)
    barely = damped.sigma[:len(METRIXS)] > 0.5 * opts.prior_sigma
    assert barely.sum() >= 5
    assert np.sum(ends[1][:len(METRIXS)][barely] ** 2) < np.sum(ends[0][:len(METRIXS)][barely] ** 2)
    # no iterations: a look at the start, which settles nothing
    look = fit(meas, start, eng, opts.replace(stages=(("bins", 0),)))
    assert np.array_equal(look.state.offsets, start.offsets) and "settle" not in look.history[-1]


def test_a_fit_ends_under_the_offsets_spread_the_data_prefer(defocus_case):
    """``estimate_spread``: offsets drawn within ±3 % of each range, the table's prior ±20 %: the fit
    refits its last stage under the narrower spread its posterior's evidence prefers, and the
    offsets end nearer the truth, with a covariance under that prior."""
    meas, truth, twin = defocus_case
    opts = FitOptions(rays=1500, seed=3, stages=(("features", 3), ("bins", 3)))
    eng = TorchEngine(hist=CAMERA)
    start = ModelState(np.zeros(len(METRIXS)), {"chamber_z": {"z": 15.0}})
    wide, narrow = fit(meas, start, eng, opts), fit(meas, start, eng, opts.replace(estimate_spread=True))
    assert wide.prior_sigma is None  # the options' prior
    assert narrow.prior_sigma < 0.95 * opts.prior_sigma
    assert narrow.ridge[0] == pytest.approx(narrow.prior_sigma ** -2.0)
    assert {h.get("spread") for h in narrow.history} >= {narrow.prior_sigma}
    err = [np.sqrt(np.mean((f.state.offsets - truth.offsets) ** 2)) for f in (wide, narrow)]
    print(f"spread {narrow.prior_sigma:.4f} (drawn: RMS {np.sqrt(np.mean(truth.offsets ** 2)):.4f}); "
          f"RMSE {err[0]:.4f} -> {err[1]:.4f}")
    assert err[1] < err[0]
    assert np.all(narrow.offset_sigma <= wide.offset_sigma * 1.5)


def test_posterior_samples_fit_the_frames_where_the_covariance_s_draws_do_not(defocus_case):
    """Randomize-then-optimize: each sample is the fit of the frames perturbed by their noise and
    of the prior's mean perturbed by its spread, a few steps from the fitted state on rays of its
    own.  The samples fit the frames about as well as a posterior draw should (their χ² a few tens
    above the fit's, where the Gaussian covariance's draws lie far above), spread where the frames
    leave room, and the same seed gives the same samples, side by side or not."""
    from concurrent.futures import ThreadPoolExecutor

    from scipy.stats import chi2 as chi2_dist

    from bluesky_offsets.model.fit import posterior_samples
    from bluesky_offsets.optimize.optimizer import covariance_states
    from bluesky_offsets.streams import stream
    meas, truth, twin = defocus_case
    opts = FitOptions(rays=1500, seed=3, stages=(("features", 3), ("bins", 4)))
    eng = TorchEngine(hist=CAMERA)
    res = fit(meas, ModelState(np.zeros(len(METRIXS)), {"chamber_z": {"z": 15.0}}), eng, opts)
    samples = posterior_samples(meas, res.state, eng, opts, n=4, seed=5)
    with ThreadPoolExecutor(2) as ex:
        again = posterior_samples(meas, res.state, eng, opts, n=4, seed=5, executor=ex)
    assert all(np.array_equal(a.offsets, b.offsets) and a.effects == b.effects for a, b in zip(samples, again))

    def above(st, seed=opts.seed):  # on the rays ``seed`` draws; a state beyond a bound traced at the bound
        mdl = _Model(meas, res.state, eng, opts.replace(seed=seed), METRIXS)
        r, r0 = (mdl.residuals("bins", mdl.products("bins", np.clip(mdl.vector(s), *mdl.bounds()), False))[0]
                 for s in (st, res.state))
        return float(r @ r) - float(r0 @ r0)
    region = chi2_dist.ppf(0.999, len(res.names))
    # each sample on its own rays (the fitted state too), against the unperturbed frames
    fitted = [above(st, stream(5, "fit.posterior_sample_rays", draw=k)) for k, st in enumerate(samples)]
    drawn = [above(st) for st in covariance_states(res.state, res.covariance, res.names, 4, seed=5)]
    print(f"chi2 above the fit: samples {np.round(fitted, 1)}, covariance draws {np.round(drawn, 1)} "
          f"(99.9 % region {region:.1f})")
    assert max(fitted) < region, fitted
    z = np.array([np.r_[st.offsets, st.effect_vector()] for st in samples])
    assert np.all(np.ptp(z, axis=0)[:len(METRIXS)] > 0)  # every offset moved: the prior's draw at least


@contextlib.contextmanager
def _side_by_side(where: str):
    """Two threads of this process, or the two worker processes of a twin's Dask cluster."""
    if where == "threads":
        from concurrent.futures import ThreadPoolExecutor
        with ThreadPoolExecutor(2) as ex:
            yield ex
        return
    from bluesky_offsets.model.cluster import ClusterExecutor
    with Twin(n_workers=2) as twin:
        ex = ClusterExecutor(twin.client)
        try:
            yield ex
        finally:
            ex.shutdown()


@pytest.mark.parametrize("where", ["threads", "workers"])
def test_fits_side_by_side_give_what_one_after_the_other_gives(defocus_case, where):
    """``executor``: the starts and then the ray draws of one fit run side by side, each on a
    model of its own, and are used in their order: the result and the history are the ones
    of the serial fit, to the bit, on threads or pickled to the processes of the twin's Dask
    cluster (:class:`ClusterExecutor`: the runs' trace counts come back, every progress record
    is forwarded from the workers, a call's error is raised where it is read)."""
    from bluesky_offsets.model.cluster import Progress
    from bluesky_offsets.model.fit import gather
    meas, truth, _ = defocus_case
    opts = FitOptions(rays=1000, seed=5, stages=(("features", 2), ("bins", 2)), ray_draws=3)
    eng = TorchEngine(hist=CAMERA)
    start = ModelState(truth.offsets * 0.5, {"chamber_z": {"z": 8.0}})
    other = ModelState(np.zeros(len(METRIXS)), {"chamber_z": {"z": 20.0}})
    from bluesky_offsets.model.cluster import one_thread
    seen: list[dict] = []
    threads = torch.get_num_threads()
    # one torch and one BLAS thread here, as on the workers and as the analysis's executor sets
    # them (model.cluster.analysis_executor): else a sum runs in another order (pytest -n 0 on two cores)
    try:
        with one_thread():
            one = fit(meas, start, eng, opts, also_from=[other])
            with _side_by_side(where) as ex:
                two = fit(meas, start, eng, opts, also_from=[other], executor=ex, progress=Progress(seen.append))
                assert gather([lambda k=k: k * k for k in range(5)], ex) == [0, 1, 4, 9, 16]
                with pytest.raises(ZeroDivisionError):
                    gather([lambda: 1 / 0], ex)
                t = time.monotonic()
                while len(seen) < len(two.history) and time.monotonic() - t < 30:
                    time.sleep(0.1)  # a worker's records travel through the scheduler
    finally:
        torch.set_num_threads(threads)  # one_thread leaves torch on one thread; the tests after keep theirs
    assert np.array_equal(one.draws, two.draws) and np.array_equal(one.covariance, two.covariance, equal_nan=True)
    assert one.history == two.history and one.n_traces == two.n_traces
    assert len(seen) == len(two.history)  # every record reported (the iterations as they ran)
    with pytest.raises(TypeError, match="ClusterExecutor"):
        pickle.dumps(Progress(seen.append))  # to another process only through the executor


_ARITHMETIC_FIT = """
import os, sys, hashlib
from bluesky_offsets.blas import pin_kernels; pin_kernels()  # first, as the command line does
import numpy as np
from bluesky_offsets.model.fit import FitOptions, fit
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.model.state import ModelState
from bluesky_offsets.physics.engine import TorchEngine
from bluesky_offsets.physics.twin import CAMERA
d = np.load(sys.argv[1])
meas = Measurement(d["cfg"], d["hx"], d["hy"], int(d["n"]), spec=CAMERA)
res = fit(meas, ModelState(d["start"], {"chamber_z": {"z": 8.0}}), TorchEngine(hist=CAMERA),
          FitOptions(rays=1500, seed=5, stages=(("features", 3), ("profiles", 2), ("bins", 3))))
print(os.environ["MKL_CBWR"], os.environ["OPENBLAS_CORETYPE"],
      hashlib.sha256(res.covariance.tobytes() + res.state.offsets.tobytes()).hexdigest(),
      repr(res.state.effects["chamber_z"]["z"]), repr(res.chi2))
"""


@pytest.mark.skipif(not x86_with_avx2(), reason="the kernels are pinned on x86-64 CPUs with AVX2 (Linux)")
def test_another_cpus_arithmetic_gives_the_same_bits(defocus_case, tmp_path):
    """Issue 17's "the same result on any machine": a fit in a process as this CPU runs it and in
    one that computes as an AVX2-only CPU would (torch's AVX2 kernels, MKL's AVX2 instructions)
    gives the same bits, because the package pins MKL's (to its vendor-neutral branch: a named
    ISA branch holds on Intel CPUs only) and OpenBLAS's kernels
    (:func:`bluesky_offsets.blas.pin_kernels`), and on an AVX-512 CPU numpy's and torch's own
    vector functions too.  Without the pinning another CPU's analysis differs in its digits (docs/explanations/diagnosis.md,
    "Another CPU's arithmetic")."""
    import subprocess
    import sys
    meas, truth, _ = defocus_case
    data = tmp_path / "meas.npz"
    np.savez(data, cfg=meas.configurations, hx=meas.hist_x, hy=meas.hist_y, n=meas.n_rays, start=truth.offsets * 0.5)
    script = tmp_path / "fit.py"
    script.write_text(_ARITHMETIC_FIT)
    outs = []
    for extra in ({}, AVX2_ONLY):
        proc = subprocess.run([sys.executable, str(script), str(data)], capture_output=True, text=True,
                              env={**_unpinned_environment(), **extra}, timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
        outs.append(proc.stdout.split())
    assert outs[0][:2] == ["COMPATIBLE", "Haswell"], outs  # pinned by the call, not by this test
    assert outs[0] == outs[1], outs


# how an AVX2-only CPU computes, on this one: torch's AVX2 kernels, MKL's AVX2 instructions, numpy's
# AVX2 loops
AVX2_ONLY = {"ATEN_CPU_CAPABILITY": "avx2", "MKL_ENABLE_INSTRUCTIONS": "AVX2",
             "NPY_DISABLE_CPU_FEATURES": numpy_avx512_targets()}


def _unpinned_environment() -> dict:
    import os
    return {k: v for k, v in os.environ.items() if k not in ("MKL_CBWR", "OPENBLAS_CORETYPE", *AVX2_ONLY)}


_ELEMENTWISE = """
import hashlib
from bluesky_offsets.blas import pin_kernels; pin_kernels()
import numpy as np, torch
x = np.linspace(-3.0, 3.0, 100_001)
parts = [f(x) for f in (np.exp, np.arctan, np.sinh, np.cbrt)] + [np.log(x * x + 0.1), np.arctan2(x, 1.3), np.power(x * x, 0.7)]
t = torch.from_numpy(x)
parts += [v.numpy() for v in (torch.exp(t), torch.sin(t), torch.atan2(t, t + 4.0), torch.sqrt(t * t + 1.0))]
print(hashlib.sha256(b"".join(p.tobytes() for p in parts)).hexdigest())
"""


@pytest.mark.skipif(not x86_with_avx2(), reason="the kernels are pinned on x86-64 CPUs with AVX2 (Linux)")
def test_numpy_and_torch_functions_round_as_on_an_avx2_cpu(tmp_path):
    """numpy's float64 exp, log, arctan, power... and torch's exp, sin, atan2 round otherwise in
    their AVX-512 loops (the designed measurement chose other frames with them); pinned, this CPU
    computes them as an AVX2-only CPU does (on an AVX2-only CPU the two are the same)."""
    import subprocess
    import sys
    script = tmp_path / "elementwise.py"
    script.write_text(_ELEMENTWISE)
    outs = [subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                           env={**_unpinned_environment(), **extra}).stdout for extra in ({}, AVX2_ONLY)]
    assert outs[0] and outs[0] == outs[1]


def test_a_parameter_the_data_do_not_see_has_no_uncertainty():
    """A thermal bump below its threshold is no bump (its column is zero): its σ is NaN, never
    the pseudo-inverse's 0 that would print "± 0"."""
    cfg = _configurations(2)
    truth = ModelState(np.zeros(len(METRIXS)), {})
    eng = TorchEngine()
    hx, hy = simulate(Twin(eng), cfg, truth, 800, seed=[1, 2])
    meas = Measurement(cfg, hx, hy, 800)
    res = fit(meas, ModelState().with_effect("thermal_bump_m1", {"height": 0.0}), eng,
              FitOptions(rays=800, seed=2, stages=(("bins", 1),)))
    assert np.isnan(res.effect_sigma()["thermal_bump_m1"]["height"])
    assert np.all(np.isfinite(res.offset_sigma)) and np.all(res.offset_sigma > 0)


def test_a_blur_gains_nothing_by_smoothing_the_models_ray_noise():
    """A model traced with few rays and then blurred carries a fraction of the noise its counts
    imply: weighed as counts, a blur the beamline does not have lowers χ² at the truth (the twin's
    rays' noise smoothed away), so a diagnosis would name it.  With the model's noise carried
    through the blur (``model_noise``) it does not; without a blur nothing changes."""
    cfg = _configurations(2)
    twin = Twin(TorchEngine(hist=CAMERA))
    n, k = 20_000, 1_000
    m = simulate_frames(twin, cfg, ModelState(np.zeros(len(METRIXS))), n, [1, 2])

    def chi2(effects, carried=True):
        hx, hy, noise = simulate_with_noise(twin, cfg, ModelState(np.zeros(len(METRIXS)), effects), k, [5, 6])
        return misfit(m[0], m[1], hx, hy, n, model_rays=k, model_noise=noise if carried else None).chi2_total

    bare, blurred = chi2({}), {"detector_blur": {"sigma": 0.01}}  # two of the camera's bins in y
    assert chi2(blurred, carried=False) < 0.6 * bare  # the smoothing's false gain
    assert chi2(blurred) > bare
    assert simulate_with_noise(twin, cfg, ModelState(np.zeros(len(METRIXS))), k, [5, 6])[2] is None


def test_blurred_frames_keep_their_counting_noise():
    """A detector blur acts on each photon: two frames of ``simulate_frames`` differ by counting
    noise (χ²/dof ≈ 1 under the analysis's noise model), where ``simulate``'s blurred counted
    histograms differ by a fraction of it (the blur smooths their noise too: a misfit would
    read as within noise).  Both axes count the same photons; the seeds fix the frames."""
    cfg = _configurations(2)
    truth = ModelState(np.zeros(len(METRIXS)), {"detector_blur": {"sigma": 0.03}})
    twin = Twin(TorchEngine(hist=CAMERA))
    n = 4000

    def chi2_reduced(p, q):
        return misfit(p[0], p[1], q[0], q[1], n, model_rays=n).chi2_reduced_total

    a, b = (simulate_frames(twin, cfg, truth, n, s) for s in ([1, 2], [3, 4]))
    c, d = (simulate(twin, cfg, truth, n, s) for s in ([1, 2], [3, 4]))
    assert 0.6 < chi2_reduced(a, b) < 1.5  # two configurations, ~300 photons each
    assert chi2_reduced(c, d) < 0.1  # the smoothing hides the counting noise
    assert np.allclose(a[0].sum(1), a[1].sum(1))
    assert np.array_equal(simulate_frames(twin, cfg, truth, n, [1, 2])[0], a[0])
