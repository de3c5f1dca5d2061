"""The designed measurement's parts: options, candidates, what a frame would teach, the choice,
frames far from the fitted ones; the posterior per offset and the calibration file."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bluesky_offsets.design import (
    PRIOR_SIGMA,
    DesignOptions,
    candidate_settings,
    far_from,
    frame_information,
    prior_precision,
    select,
)
from bluesky_offsets.model.export import CalibrationFileError, load_calibration, write_calibration
from bluesky_offsets.model.posterior import Posterior, evidence_spread, with_prior
from bluesky_offsets.model.state import CalibratedState, ModelState
from bluesky_offsets.physics.parameters import METRIXS as T
from bluesky_offsets.physics.screen import STAGE
from bluesky_offsets.physics.engine import TorchEngine
from sim_iocs.truth import default_start


def test_design_options_refuse_unknown_keys_and_bad_values():
    with pytest.raises(ValueError, match="unknown design option"):
        DesignOptions.from_mapping({"frame": 10})
    for bad in ({"criterion": "E"}, {"frames": 0}, {"floor": 1.5}, {"move": -0.1}, {"target": 2.0},
                {"validation": -1}):
        with pytest.raises(ValueError):
            DesignOptions(**bad)
    assert DesignOptions().replace(batch=3).batch == 3


def test_candidates_stay_within_every_motor_s_limits_and_the_stage_s_travel():
    rng = np.random.default_rng(0)
    acc = np.full(len(T), 0.2)
    cfg, screen = candidate_settings(default_start()[None], 200, rng, acceptance=acc, options=DesignOptions())
    lo = np.array([p.limits[0] for p in T])
    hi = np.array([p.limits[1] for p in T])
    assert np.all(cfg >= lo - 1e-12) and np.all(cfg <= hi + 1e-12)
    assert np.array_equal(cfg[:, ~T.motorized], np.tile(T.reference[~T.motorized], (200, 1)))
    for k, ax in enumerate(STAGE):
        assert np.all(screen[:, k] >= ax.low) and np.all(screen[:, k] <= ax.high)
    assert (screen[:, 2] != 0).mean() > 0.5  # the screen moves along the beam in most
    none = candidate_settings(default_start()[None], 20, rng, acceptance=acc,
                              options=DesignOptions(screen=False))[1]
    assert not none.any()


def test_the_d_optimal_batch_adds_what_the_chosen_frames_leave_open():
    """Two frames that see the same direction teach it once: the second pick is the frame that sees
    another direction, though it sees it less."""
    p = 4
    e = np.eye(p)
    fisher = np.array([1e4 * np.outer(e[0], e[0]), 1e4 * np.outer(e[0], e[0]), 1e2 * np.outer(e[1], e[1]),
                       np.zeros((p, p))])
    ch = select(fisher, prior_precision(p), 2, criterion="D")
    assert ch.indices == [0, 2] and ch.gains[0] > ch.gains[1] > 0
    assert select(fisher, prior_precision(p), 2, allowed=[False, True, True, True]).indices == [1, 2]
    assert select(fisher, prior_precision(p), 2, criterion="A").indices[0] in (0, 1)


def test_frame_information_is_symmetric_positive_and_sees_the_beam():
    eng = TorchEngine(options={"common_rays": False})
    cfg = np.tile(T.reference, (3, 1))
    cfg[1, T.index("E1.rotationXerror")] += 4.0   # the beam 15 mm off the screen horizontally ...
    cfg[1, T.index("E2.rotationXerror")] += 2.0   # ... and 4 mm vertically: dark
    info = frame_information(eng, cfg, np.zeros(len(T)), photons=5000, model_rays=5000, rays=600,
                             screen=np.array([[0, 0, 0], [0, 0, 0], [0, 0, 20.0]]))
    assert info.fisher.shape == (3, len(T), len(T))
    for f in info.fisher:
        assert np.allclose(f, f.T) and np.linalg.eigvalsh(f).min() > -1e-6 * max(1.0, np.abs(f).max())
    assert info.intensity[0] > 0.05 and info.intensity[1] < 0.01
    assert np.trace(info.fisher[0]) > 100 * np.trace(info.fisher[1])
    # the exit slit's position along the beam is seen where the beam is
    j = T.index("E2.rotationXerror")
    assert info.fisher[0][j, j] > 0 and np.isfinite(info.intensity_sigma(np.eye(len(T)) * PRIOR_SIGMA ** 2)).all()


def test_far_from_takes_the_farthest_and_spreads_them():
    fitted = (np.tile(default_start(), (2, 1)), np.zeros((2, 3)))
    cand = np.tile(default_start(), (4, 1))
    scr = np.array([[0, 0, 1.0], [0, 0, 25.0], [0, 0, 26.0], [0, 0, -14.0]])
    assert far_from(fitted, (cand, scr), 2) == [2, 3]  # 26 mm, then -14 mm (25 mm is next to 26)
    assert far_from(fitted, (cand, scr), 2, allowed=[True, True, False, True]) == [1, 3]


def _calibrated() -> CalibratedState:
    n = len(T)
    names = tuple(T.names) + ("chamber_z.z",)
    sig = np.full(n + 1, 0.5 * PRIOR_SIGMA)
    sig[0], sig[1] = 0.01 * PRIOR_SIGMA, 0.3 * PRIOR_SIGMA
    sig[-1] = 1.2
    corr = np.eye(n + 1)
    corr[2, 3] = corr[3, 2] = -0.8
    cov = corr * np.outer(sig, sig)
    offsets = np.zeros(n)
    offsets[:4] = [0.02, -0.05, 0.1, 0.2]
    st = ModelState(offsets, {"chamber_z": {"z": 21.0}}, "+ chamber_z")
    return CalibratedState(st, cov, names, "uid-of-the-fit")


def test_the_posterior_says_each_offset_s_value_sigma_class_and_partners():
    post = Posterior.of(_calibrated())
    e0, e1, e2, e3 = post.offsets[:4]
    assert e0.cls == "determined" and e1.cls == "weak" and e2.cls == "undetermined"
    assert e0.unit == "mm" and e0.value == pytest.approx(0.02 * T.span[0]) and e0.sigma == pytest.approx(
        0.01 * PRIOR_SIGMA * T.span[0])
    assert e2.partners == ((T.names[3], pytest.approx(-0.8)),) and e3.at_bound
    assert e2.text().startswith("undetermined (") and "±" in e0.text() and not e0.text().startswith("undet")
    z = post.effects["chamber_z"]["z"]
    assert z.value == 21.0 and z.sigma == pytest.approx(1.2) and z.cls == "determined"
    c = post.counts()
    assert c["determined"] == 1 and c["weak"] == 1 and sum(c.values()) == len(T)
    assert all(line for line in post.lines()) and "undetermined" in "\n".join(post.lines())
    assert Posterior.of(ModelState()) is None  # no covariance: nothing to say


def test_the_calibration_file_round_trips_and_refuses_what_it_cannot_use(tmp_path):
    cal = _calibrated()
    path = write_calibration(tmp_path / "calibration.json", cal, measurement_uid="m-uid",
                             validation={"chi2_reduced": 1.0})
    rec = json.loads(path.read_text())
    assert rec["parameter_table_version"] == T.version and rec["measurement_uid"] == "m-uid"
    e = rec["offsets"]["U41_318eV.translationXerror"]
    assert e["unit"] == "mm" and e["class"] == "determined" and math.isclose(e["value"], 0.02 * T.span[0])
    back = load_calibration(path)
    assert np.allclose(back.state.offsets, cal.state.offsets) and back.state.effects == {"chamber_z": {"z": 21.0}}
    assert np.allclose(back.covariance, cal.covariance) and back.names == cal.names and back.uid == "uid-of-the-fit"
    import bluesky_offsets
    assert bluesky_offsets.load_calibration(path).uid == "uid-of-the-fit"
    other = dict(rec, parameter_table_version="0123456789ab")
    (tmp_path / "other.json").write_text(json.dumps(other))
    (tmp_path / "corrupt.json").write_text(path.read_text()[:200])
    (tmp_path / "partial.json").write_text(json.dumps({k: v for k, v in rec.items() if k != "covariance"}))
    for name, why in (("other.json", "parameter table"), ("corrupt.json", "not JSON"),
                      ("partial.json", "incomplete"), ("missing.json", "No such file")):
        with pytest.raises(CalibrationFileError, match=why) as err:
            load_calibration(tmp_path / name)
        assert len(str(err.value).splitlines()) == 1 and name in str(err.value)


def _linear_posterior(spread: float, seed: int, prior: float = PRIOR_SIGMA):
    """A linear-Gaussian calibration: offsets drawn with ``spread``, frames that determine a third of
    the directions well, a third weakly and a third not at all; the posterior under the prior σ ``prior``."""
    rng = np.random.default_rng(seed)
    n = len(T)
    truth = rng.normal(0.0, spread, n)
    basis = np.linalg.qr(rng.normal(size=(n, n)))[0]
    strength = np.r_[np.full(12, 1e-3), np.full(11, 3e-2), np.full(11, 10.0)]  # σ of each direction
    information = basis @ np.diag(strength ** -2.0) @ basis.T
    data = basis.T @ truth + rng.normal(0.0, strength)  # each direction measured with its σ
    cov = np.linalg.inv(information + np.eye(n) / prior ** 2)
    mean = cov @ (basis @ (data / strength ** 2))
    return truth, mean, cov


@pytest.mark.parametrize("spread", [0.02, 0.04])
def test_the_offsets_spread_is_estimated_from_the_data(spread):
    """The evidence's maximum over the prior's σ finds the offsets' true spread, within the sampling of
    a few determined directions; offsets as wide as the table's prior keep the table's."""
    est = [evidence_spread(m, c, len(T), PRIOR_SIGMA) for m, c in (_linear_posterior(spread, s)[1:] for s in range(8))]
    assert 0.6 < np.median(est) / spread < 1.5, est
    wide = [evidence_spread(m, c, len(T), PRIOR_SIGMA) for m, c in (_linear_posterior(0.2, s)[1:] for s in range(4))]
    assert all(w == pytest.approx(PRIOR_SIGMA) for w in wide)
    # frames that see nothing keep the table's prior; offsets far below it get a tenth of it, no less
    blind = np.eye(len(T)) * PRIOR_SIGMA ** 2
    assert evidence_spread(np.full(len(T), 1e-9), blind, len(T), PRIOR_SIGMA) == pytest.approx(PRIOR_SIGMA)
    assert evidence_spread(*_linear_posterior(1e-4, 0)[1:], len(T), PRIOR_SIGMA) == pytest.approx(0.1 * PRIOR_SIGMA)


def test_a_posterior_under_the_estimated_spread_keeps_the_classes_of_the_table_s_prior(tmp_path):
    """The values and σ under the spread the data prefer; the classes, the σ / prior and the determined
    combinations read against the table's prior, as without the estimate; the file keeps the prior."""
    truth, mean, cov = _linear_posterior(0.03, 3)
    tau = evidence_spread(mean, cov, len(T), PRIOR_SIGMA)
    narrow = with_prior(cov, len(T), PRIOR_SIGMA, tau)
    assert np.allclose(with_prior(narrow, len(T), tau, PRIOR_SIGMA), cov, rtol=1e-6, atol=1e-12)
    narrow_mean = narrow @ np.linalg.solve(cov, mean)
    names = tuple(T.names)
    wide = Posterior.of(CalibratedState(ModelState(mean), cov, names))
    post = Posterior.of(CalibratedState(ModelState(narrow_mean), narrow, names, prior_sigma=tau))
    assert [e.cls for e in post.offsets] == [e.cls for e in wide.offsets]
    assert [e.determination for e in post.offsets] == pytest.approx([e.determination for e in wide.offsets])
    assert len(post.combinations) == len(wide.combinations)
    assert all(p.normalized_sigma <= w.normalized_sigma * (1 + 1e-9) for p, w in zip(post.offsets, wide.offsets))
    # nearer the truth than the wide prior's mean: the offsets the frames do not see shrink to the spread
    assert np.sqrt(np.mean((narrow_mean - truth) ** 2)) < np.sqrt(np.mean((mean - truth) ** 2))
    assert any("estimated from the data" in line for line in post.lines())
    back = load_calibration(write_calibration(tmp_path / "c.json", CalibratedState(
        ModelState(np.clip(narrow_mean, -0.2, 0.2)), narrow, names, prior_sigma=tau)))
    assert back.prior_sigma == pytest.approx(tau) and load_calibration(
        write_calibration(tmp_path / "w.json", CalibratedState(ModelState(mean), cov, names))).prior_sigma is None


def test_a_prior_wide_posterior_still_gets_frames_where_the_estimate_sees_light():
    """Where the posterior's spread leaves no candidate above the light floor with confidence (offsets
    drawn at ±20 %), the candidates the current estimate lights are taken rather than none, and where
    it lights none the screen scans along the beam; the unclipped matrices of ``psd=False`` are the
    clipped ones' symmetric source."""
    from bluesky_offsets.design.information import positive_part
    from bluesky_offsets.design.sequence import next_batch
    eng = TorchEngine(options={"common_rays": False})
    opts = DesignOptions(candidates=6, rays=400, fit_rays=400, seed=3)
    wide = prior_precision(len(T)) * 1e-6   # a posterior far wider than any candidate's light
    st = next_batch(eng, np.zeros(len(T)), wide, T.reference[None], np.full(len(T), 1e-4), k=2, step=0, photons=5000,
                    options=opts)
    assert len(st.gains) == 2 and np.all(st.intensity >= opts.floor)
    # where the estimate lights nothing around the beam (M1 and both mirrors tilted to their bounds:
    # 1 % of the source on the screen), the screen is moved along the beam where the beam was found
    dark = np.zeros(len(T))
    for name in ("M1_Cylinder.rotationZerror", "E1.rotationXerror", "E2.rotationXerror"):
        dark[T.index(name)] = 0.2
    scan = next_batch(eng, dark, wide, T.reference[None], np.full(len(T), 1e-4), k=3, step=1, photons=5000,
                      options=opts.replace(slits=0.0))   # an opened slit may light one candidate
    assert scan.allowed == 0 and np.allclose(scan.configurations, T.reference) and len(scan.gains) == 3
    assert np.allclose(scan.screen[:, 2], [-15.0, 7.5, 30.0]) and np.all(scan.screen[:, :2] == 0)
    raw = frame_information(eng, np.tile(T.reference, (2, 1)), np.zeros(len(T)), photons=5000, model_rays=5000,
                            rays=400, psd=False)
    clipped = frame_information(eng, np.tile(T.reference, (2, 1)), np.zeros(len(T)), photons=5000,
                                model_rays=5000, rays=400)
    assert np.allclose(raw.fisher, np.swapaxes(raw.fisher, 1, 2))
    assert np.allclose(positive_part(raw.fisher), clipped.fisher, atol=1e-9 * np.abs(clipped.fisher).max())


def test_an_estimate_dark_where_the_beamline_was_lit_is_refitted_from_a_global_start():
    """At ±20 % the estimate can put no light where the beamline did (here the source shifted up,
    M1 and both mirrors tilted the other way): the update's fit has no light to follow.
    :func:`global_starts` finds offsets nearer the frames, and the refit from them lights the
    frames and ends nearer them than the one from the dark estimate."""
    from bluesky_offsets.design.sequence import dark_where_lit, global_starts, update
    from bluesky_offsets.model.measurement import Measurement
    from bluesky_offsets.model.state import simulate_raw
    from bluesky_offsets.physics.twin import HistogramSpec, Twin
    truth = np.zeros(len(T))
    for name in ("U41_318eV.translationYerror", "M1_Cylinder.rotationZerror", "E1.rotationXerror",
                 "E2.rotationXerror"):
        truth[T.index(name)] = 0.2
    cfg = np.tile(T.reference - truth * T.span, (4, 1))   # where the motors put the true beam on the screen
    screen = np.column_stack([np.zeros(4), np.zeros(4), [-15.0, 0.0, 15.0, 30.0]])
    spec = HistogramSpec(250, (-10.0, 10.0), 300, (-3.0, 3.0))  # a quarter of the camera's resolution
    twin = Twin(TorchEngine(hist=spec), scheduler="inline")
    hx, hy = simulate_raw(twin, cfg, ModelState(truth), 5000, [11, 12, 13, 14], screen=screen)
    meas = Measurement(cfg, hx, hy, n_rays=5000, spec=spec, screen=screen)
    ex, ey = simulate_raw(twin, cfg, ModelState(np.zeros(len(T))), 2000, 0, screen=screen)
    assert dark_where_lit(meas, np.minimum(ex.sum(1), ey.sum(1)), 0.02)
    assert not dark_where_lit(meas, np.minimum(hx.sum(1), hy.sum(1)), 0.02)
    starts = global_starts(meas, np.zeros(len(T)), photons=5000, seed=2, keep=1, draws=192, rounds=2, rays=200)
    assert starts.shape == (1, len(T)) and np.all(np.abs(starts) <= 0.2)
    opts = DesignOptions(fit_rays=1000, seed=2)
    refit, stuck = (update(meas, x, options=opts, step=1) for x in (starts[0], np.zeros(len(T))))
    assert refit.chi2 < stuck.chi2
    rx, ry = simulate_raw(twin, cfg, refit.state, 2000, 0, screen=screen)
    assert not dark_where_lit(meas, np.minimum(rx.sum(1), ry.sum(1)), 0.02)


def test_the_motors_acceptance_is_taken_again_where_the_estimate_lights_the_beam():
    """Where the model with no offsets is dark at the setting where the beam was found (it had to
    be searched for), the acceptance taken there gives every motor the narrowest width and the
    candidates barely move the motors (seed 42 of the no-effect draws: a median spread of 0.0005
    of each range against 0.11 where the beam was lit at the start).  Once the estimate lights that
    setting, the acceptance is taken at the estimate; where the model was lit at the start it stands."""
    from bluesky_offsets.design.sequence import DesignLoop
    from bluesky_offsets.offsets.beam_search import SWEEP
    truth = np.zeros(len(T))
    for name in ("U41_318eV.translationYerror", "M1_Cylinder.rotationZerror", "E1.rotationXerror",
                 "E2.rotationXerror"):
        truth[T.index(name)] = 0.2
    here = T.reference - truth * T.span   # where the motors put the true beam on the screen
    loop = DesignLoop(DesignOptions(), here, 40, 5000)
    motors = T.motorized
    assert np.all(loop.acceptance[motors] == SWEEP[0])   # dark at no offsets: the narrowest everywhere
    loop._update_acceptance(0.0)                           # the estimate still dark there: nothing to take
    assert np.all(loop.acceptance[motors] == SWEEP[0])
    loop.offsets = truth
    loop._update_acceptance(0.3)
    assert np.median(loop.acceptance[motors]) >= 100 * SWEEP[0]
    lit = DesignLoop(DesignOptions(), T.reference, 40, 5000)
    before = lit.acceptance.copy()
    lit._update_acceptance(0.3)
    lit.offsets = truth
    lit._update_acceptance(0.3)
    assert np.array_equal(lit.acceptance, before, equal_nan=True)
