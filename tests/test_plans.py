"""Plans against the simulated beamline: the acceptance scan, limits, abort, searches, find_offsets."""

from __future__ import annotations

import threading
import time

import bluesky.plan_stubs as bps
import numpy as np
import pytest
from bluesky import RunEngine
from bluesky.utils import RunEngineInterrupted

from bluesky_offsets.epics.devices import FocusChamber, MetrixsBeamline
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.twin import CAMERA, HistogramSpec, Twin
from conftest import start_metrixs_ioc
from plans.motion import resolve_motors
from plans import (
    HIGH_RAY_THRESHOLD,
    MotorLimitError,
    OffsetResult,
    enough_rays,
    find_high_ray_configurations,
    find_offsets,
    high_ray_configurations_on_model,
    measure_configurations,
    sample_candidates,
)
from sim_iocs.truth import Truth, default_start

N_RAYS = 5000
REFERENCE = 4  # the twin's reference frames hold this many times the measured rays
# Hidden truth of the acceptance IOC: offsets in the sensitive axes large enough to move the
# footprint by several bins, small ones elsewhere, the six fixed parameters off their design
# values, and a hidden effect (focus chamber 3 mm along the beam).
ACCEPTANCE_TRUTH = {
    "offsets": {"E1.rotationXerror": 0.1, "E2.rotationXerror": -0.12, "M1_Cylinder.rotationXerror": 0.06,
                "E1.translationYerror": -0.05, "E2.translationYerror": 0.05,
                "SphericalGrating.rotationZerror": 0.1, "ExitSlit.translationZerror": -0.1,
                "U41_318eV.translationXerror": 0.1, "ASBL.totalWidth": 0.05, "E1.rotationYerror": 0.15,
                "M1_Cylinder.radius": 0.1, "SphericalGrating.radius": -0.1, "E1.longHalfAxisA": -0.1,
                "E1.shortHalfAxisB": 0.05, "E2.longHalfAxisA": 0.1, "E2.shortHalfAxisB": 0.08},
    "overrides": {"ImagePlane": {"translationZerror": 3.0}},
}


@pytest.fixture(scope="module")
def RE():
    return RunEngine({}, call_returns_result=True)


@pytest.fixture(scope="module")
def acceptance_ioc(tmp_path_factory):
    ioc = start_metrixs_ioc(tmp_path_factory.mktemp("acceptance_ioc"), ACCEPTANCE_TRUTH, extra=("--rays", N_RAYS))
    yield ioc
    ioc.stop()


def _devices(prefix):
    from ophyd_async.core import init_devices
    with init_devices():
        beamline = MetrixsBeamline(prefix, name="metrixs")
        chamber = FocusChamber(prefix + "chamber:", name="chamber")
    return beamline, chamber


@pytest.fixture(scope="module")
def devices(RE, metrixs_ioc):
    return _devices(metrixs_ioc.prefix)


@pytest.fixture(scope="module")
def store(run_store):
    return run_store


def _spread(value: float) -> np.ndarray:
    """Per-parameter candidate spread (normalized); M1 sideways loses the beam within ~50 µm."""
    s = np.full(len(METRIXS), value)
    s[METRIXS.index("M1_Cylinder.translationXerror")] = min(value, 0.003)
    return s


def _counts(h, n):
    return np.round(np.asarray(h) * n)


def chi2_two_sample(a, b, ratio: float = 1.0) -> tuple[float, int]:
    """Two-sample Poisson chi^2 of count histograms ``a`` and ``b`` and its degrees of freedom
    (occupied bins); ``ratio`` is b's rays over a's.  chi^2/dof is about 1 (a little less:
    multinomial counts) when both are finite-ray samples of the same footprint, and far above
    when the footprints differ."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    occupied = (a + b) > 0
    diff = np.sqrt(ratio) * a - b / np.sqrt(ratio)
    return float(((diff ** 2)[occupied] / (a + b)[occupied]).sum()), int(occupied.sum())


def chi2_quantile(dof: int, z: float) -> float:
    """Wilson-Hilferty approximation of the chi^2 quantile at normal score ``z``."""
    k = max(dof, 1)
    return k * (1 - 2 / (9 * k) + z * np.sqrt(2 / (9 * k))) ** 3


# --------------------------------------------------------------------------- #
# acceptance
# --------------------------------------------------------------------------- #
def test_acceptance_measured_histograms_follow_the_hidden_truth(RE, acceptance_ioc, store):
    truth = Truth.from_mapping(ACCEPTANCE_TRUTH)
    twin = Twin(scheduler="inline", n_rays=N_RAYS)
    start = default_start()
    # Test setup only: the test knows the truth and uses it to pick 16 configurations
    # near the start position that put enough rays on the screen.
    spread = _spread(0.06)
    configs = high_ray_configurations_on_model(twin, 16, candidates=48, offsets=truth.offsets, around=start,
                                               spread=spread, rng=5, n_rays=2000, chunk=16, progress=False)
    assert configs.shape == (16, 34)

    beamline, chamber = _devices(acceptance_ioc.prefix)
    token = store.subscribe(RE)
    try:
        result = RE(measure_configurations(configs, beamline, chamber))
    finally:
        RE.unsubscribe(token)
    assert result.exit_status == "success"
    (uid,) = result.run_start_uids

    m = store.load_measurement(uid)  # loaded back from the embedded store by uid
    assert m.hist_x.shape == (16, 50) and m.hist_y.shape == (16, 50)
    # the camera-resolution profiles of the same frames, and what the diagnosis reads
    assert m.profile_x.shape == (16, CAMERA.bins_x) and m.profile_spec == CAMERA
    fine = m.for_analysis()
    assert fine.spec == CAMERA and fine.hist_y.shape == (16, CAMERA.bins_y)
    np.testing.assert_allclose(fine.rebinned(HistogramSpec()).hist_x, m.hist_x, atol=1e-12)
    np.testing.assert_allclose(m.configurations, configs)
    assert m.truth_id == truth.truth_id and m.metadata["n_rays"] == N_RAYS
    assert np.isfinite(m.hist_x).all() and np.isfinite(m.hist_y).all()

    # the twin's traces seeded, so that only the IOC's frames vary from run to run
    commanded = twin.trace_batch(configs, n_rays=N_RAYS, progress=False, seed=4242)
    # the reference with 4x the rays: most profiles fill 2-3 bins, and one reference's own noise
    # adds to every measured profile's chi^2 alike
    at_truth = twin.trace_batch(np.array([truth.true_values(c) for c in configs]), overrides=truth.overrides,
                                n_rays=REFERENCE * N_RAYS, progress=False, seed=4343)
    meas_counts = np.concatenate([_counts(m.hist_x, N_RAYS), _counts(m.hist_y, N_RAYS)], axis=1)
    cmd_counts = np.concatenate([_counts(commanded.hist_x, N_RAYS), _counts(commanded.hist_y, N_RAYS)], axis=1)
    true_counts = np.concatenate([_counts(at_truth.hist_x, REFERENCE * N_RAYS),
                                  _counts(at_truth.hist_y, REFERENCE * N_RAYS)], axis=1)
    cmd = np.array([chi2_two_sample(a, b) for a, b in zip(meas_counts, cmd_counts)])
    true = np.array([chi2_two_sample(a, b, REFERENCE) for a, b in zip(meas_counts, true_counts)])
    per_bin_cmd, per_bin_true = cmd[:, 0] / cmd[:, 1], true[:, 0] / true[:, 1]
    print(f"\nchi2/bin vs twin at commanded: min {per_bin_cmd.min():.1f} median {np.median(per_bin_cmd):.1f}; "
          f"vs twin at commanded + hidden truth: max {per_bin_true.max():.2f}, pooled "
          f"{true[:, 0].sum() / true[:, 1].sum():.2f}")
    # every configuration differs from the twin at the commanded setting far beyond noise ...
    assert per_bin_cmd.min() > 20, per_bin_cmd
    # ... and agrees with the twin at commanded + hidden truth within noise: each profile below its
    # chi^2 quantile at p = 1e-4 (z = 3.72), and pooled over all of them below the quantile at
    # p = 1e-3 (z = 3.09; ~1.8 per dof at 16 frames). x and y are tested apart: both profiles hold the
    # same rays, so their sum is not chi^2 with the summed dof (a fixed 1.5 on the sum failed the
    # true model in 1 of 60 simulated runs: mean 0.92, sd 0.20).
    for axis in ("hist_x", "hist_y"):
        per_axis = np.array([chi2_two_sample(_counts(a, N_RAYS), _counts(b, REFERENCE * N_RAYS), REFERENCE)
                             for a, b in zip(getattr(m, axis), getattr(at_truth, axis))])
        limits = np.array([chi2_quantile(int(k), 3.72) for k in per_axis[:, 1]])
        assert np.all(per_axis[:, 0] < limits), (axis, per_axis, limits)
        pooled, dof = per_axis.sum(axis=0)
        assert pooled < chi2_quantile(int(dof), 3.09), (axis, pooled, dof)
    # the ray counts agree within Poisson noise with the truth, not necessarily with the commanded twin
    expected = at_truth.n_hits / REFERENCE
    z = (m.total_counts - expected) / np.sqrt(np.maximum(m.total_counts + expected / REFERENCE, 1))
    assert np.all(np.abs(z) < 5), z


def test_frames_with_the_screen_moved_follow_the_truth_and_the_stage_returns(RE, acceptance_ioc, store):
    """The chamber's stage moved along and across the beam: the frames are the truth's at the stage's
    position plus the chamber's hidden displacement, the run records where the screen stood, and the
    stage goes back to where it started."""
    from ophyd_async.core import init_devices

    from bluesky_offsets.physics.screen import per_frame_overrides
    truth = Truth.from_mapping(ACCEPTANCE_TRUTH)
    prefix = acceptance_ioc.prefix
    with init_devices():
        beamline = MetrixsBeamline(prefix, name="staged", stage={a: f"{prefix}chamber:{a}" for a in "xyz"})
        chamber = FocusChamber(prefix + "chamber:", name="chamber")
    twin = Twin(scheduler="inline", n_rays=N_RAYS)
    start = default_start()
    configs = high_ray_configurations_on_model(twin, 3, candidates=24, offsets=truth.offsets, around=start,
                                               spread=_spread(0.03), rng=7, n_rays=2000, chunk=12, progress=False)
    screen = np.array([[0.0, 0.0, 12.0], [0.4, -0.2, -10.0], [0.0, 0.0, 25.0]])
    token = store.subscribe(RE)
    try:
        result = RE(measure_configurations(configs, beamline, chamber, screen=screen))
    finally:
        RE.unsubscribe(token)
    m = store.load_measurement(result.run_start_uids[0])
    np.testing.assert_allclose(m.screen, screen)
    at_truth = twin.trace_batch(np.array([truth.true_values(c) for c in configs]), seed=99, progress=False,
                                overrides=per_frame_overrides(truth.overrides, screen, 3), n_rays=N_RAYS)
    meas = np.concatenate([_counts(m.hist_x, N_RAYS), _counts(m.hist_y, N_RAYS)], axis=1)
    flat = twin.trace_batch(np.array([truth.true_values(c) for c in configs]), seed=98, progress=False,
                            overrides=truth.overrides, n_rays=N_RAYS)
    unmoved = np.concatenate([_counts(flat.hist_x, N_RAYS), _counts(flat.hist_y, N_RAYS)], axis=1)
    other = np.array([chi2_two_sample(a, b) for a, b in zip(meas, unmoved)])
    assert np.all(other[:, 0] / other[:, 1] > 3), other
    # x and y apart (the same rays in both), each summed over the frames below its chi^2 quantile at
    # p = 1e-4: with three frames a pooled chi^2/dof bound of 1.5 is only 1.3 sigma of its noise
    for axis in ("hist_x", "hist_y"):
        same = np.array([chi2_two_sample(_counts(a, N_RAYS), _counts(b, N_RAYS))
                         for a, b in zip(getattr(m, axis), getattr(at_truth, axis))]).sum(0)
        assert same[0] < chi2_quantile(int(same[1]), 3.72), (axis, same)
    assert [float(RE(bps.rd(getattr(beamline.chamber_stage, a))).plan_result) for a in "xyz"] == [0.0, 0.0, 0.0]


# --------------------------------------------------------------------------- #
# robustness of the scan
# --------------------------------------------------------------------------- #
def _positions(ca, prefix):
    return {p.name: ca.get(prefix + p.device.replace(".", ":") + ".RBV") for p in METRIXS if p.motorized}


def test_move_beyond_limits_fails_the_step_and_moves_nothing(RE, devices, metrixs_ioc, ca, store):
    beamline, chamber = devices
    before = _positions(ca, metrixs_ioc.prefix)
    configs = np.tile(default_start(), (3, 1))
    configs[1, METRIXS.index("E1.rotationXerror")] = 2.0  # HLM = 1.5
    configs[2, METRIXS.index("E2.translationZerror")] = -1.5
    n_runs = len(store)
    with pytest.raises(MotorLimitError) as info:
        RE(measure_configurations(configs, beamline, chamber))
    msg = str(info.value)
    assert "nothing was moved" in msg and "E1.rotationXerror" in msg and "[-1.5, 1.5]" in msg
    assert "configuration 2: E2.translationZerror" in msg
    assert _positions(ca, metrixs_ioc.prefix) == before
    assert len(store) == n_runs  # refused before a run was opened
    # a direct move of one motor is refused by the client as well
    from bluesky.utils import FailedStatus
    from ophyd_async.epics.motor import MotorLimitsError
    with pytest.raises(FailedStatus) as info:
        RE(bps.mv(beamline.e1.rx, 2.0))
    assert isinstance(info.value.__cause__, MotorLimitsError)
    assert _positions(ca, metrixs_ioc.prefix) == before


def test_a_scan_commands_only_the_motors_its_configurations_change(RE, devices, metrixs_ioc, ca, store):
    beamline, chamber = devices
    before = _positions(ca, metrixs_ioc.prefix)
    # from where the motors stand (the session's IOC: an earlier test may have left one off its start)
    configs = np.tile(METRIXS.from_mapping(before, base=default_start()), (3, 1))
    configs[:, METRIXS.index("E1.rotationXerror")] += np.array([0.0, 0.02, -0.02])
    commanded = []

    def hook(msg):
        if msg.command == "set":
            commanded.append(msg.obj.name)

    events = []
    RE.msg_hook = hook
    try:
        RE(measure_configurations(configs, beamline, chamber), lambda name, doc: events.append(doc)
           if name == "event" else None)
    finally:
        RE.msg_hook = None
    # the first configuration is where the motors stand: nothing moves; then E1 rx twice and back
    assert commanded == [beamline.e1.rx.name] * 3
    assert _positions(ca, metrixs_ioc.prefix) == before
    # every frame still records where all the motors stand
    motors = resolve_motors(beamline, METRIXS)
    assert len(events) == 3 and all(m.name in ev["data"] for ev in events for m in motors.values())


def test_abort_during_scan_closes_run_and_leaves_ioc_consistent(RE, devices, metrixs_ioc, ca, store):
    beamline, chamber = devices
    P = metrixs_ioc.prefix
    before = _positions(ca, P)
    slow = P + "e2:tz"
    old_velo = ca.get(slow + ".VELO")
    ca.put(slow + ".VELO", 0.25)  # E2 tz moves of 0.2 mm take ~1 s: the pause lands mid-move
    configs = np.tile(default_start(), (6, 1))
    configs[:, METRIXS.index("E2.translationZerror")] += np.array([0.2, -0.2, 0.2, -0.2, 0.2, -0.2])
    configs[:, METRIXS.index("E1.rotationXerror")] += np.linspace(-0.05, 0.05, 6)
    events, starts = [], []
    z0 = before["E2.translationZerror"]

    def pause_mid_move():
        # once E2 tz has left the second configuration for the third (a timer misses the move under load)
        deadline = time.monotonic() + 30
        while ca.get(slow + ".RBV") < z0 - 0.2 + 0.05 and time.monotonic() < deadline:
            time.sleep(0.02)
        RE.request_pause(defer=False)

    def on_doc(name, doc):
        if name == "start":
            starts.append(doc["uid"])
        if name == "event":
            events.append(doc)
            if len(events) == 2:  # while moving to the third configuration
                threading.Thread(target=pause_mid_move, daemon=True).start()

    token = store.subscribe(RE)
    try:
        with pytest.raises(RunEngineInterrupted):
            RE(measure_configurations(configs, beamline, chamber), on_doc)
        moving_when_paused = ca.get(slow + ".RBV")
        RE.abort("test abort")
    finally:
        RE.unsubscribe(token)
        ca.put(slow + ".VELO", old_velo)
    assert RE.state == "idle"
    run = store[starts[0]]
    assert run.metadata["stop"]["exit_status"] == "abort"
    assert run.metadata["start"]["plan_name"] == "measure_configurations"
    assert len(run["primary"].read()["chamber-hist_x"]) == 2
    # the IOC is consistent: every motor done, back where the scan started, VAL = RBV
    assert z0 - 0.2 + 1e-4 < moving_when_paused < z0 + 0.2 - 1e-4  # stopped mid-move by the pause
    for p in METRIXS:
        if p.motorized:
            rec = P + p.device.replace(".", ":")
            assert ca.get(rec + ".DMOV") == 1
            mres = ca.get(rec + ".MRES")
            assert abs(ca.get(rec + ".VAL") - ca.get(rec + ".RBV")) <= mres, p.name
            assert abs(ca.get(rec + ".RBV") - before[p.name]) <= mres, p.name
    assert ca.get(P + "chamber:Status", as_string=True) == "Idle" and ca.get(P + "chamber:Acquire") == 0
    # and the beamline measures again
    out = RE(measure_configurations(configs[:1], beamline, chamber))
    assert out.exit_status == "success"


# --------------------------------------------------------------------------- #
# searches and find_offsets
# --------------------------------------------------------------------------- #
def test_high_ray_threshold_is_the_papers_in_our_units():
    assert HIGH_RAY_THRESHOLD == pytest.approx(0.5 * 22594 / 1e5)
    # the sum over all 100 bins counts, as in the authors' code and the finder
    hx = np.zeros((3, 50))
    hx[0, 10] = 0.06
    hx[1, 10] = 0.05
    hx[2, 10] = 0.2
    hy = hx.copy()
    hy[2] = 0
    assert enough_rays(hx, hy).tolist() == [True, False, True]


def test_find_high_ray_configurations_on_beamline_and_model(RE, devices, metrixs_ioc, ca):
    beamline, chamber = devices
    before = _positions(ca, metrixs_ioc.prefix)
    start = default_start()
    candidates = sample_candidates(5, rng=2, around=start, spread=_spread(0.03))
    candidates[1, METRIXS.index("M1_Cylinder.translationXerror")] = 1.0  # loses the beam
    found = RE(find_high_ray_configurations(candidates, beamline, chamber, n=3)).plan_result
    assert found.shape == (3, 34)
    assert not np.any(np.all(np.isclose(found, candidates[1]), axis=1))
    assert _positions(ca, metrixs_ioc.prefix) == pytest.approx(before, abs=1e-5)
    # the same search on the model: a callable (the surrogate's convention) wrapping the twin
    twin = Twin(scheduler="inline", n_rays=1500)

    def model(values):
        b = twin.trace_batch(values, progress=False)
        return np.concatenate([b.hist_x, b.hist_y], axis=1)

    good = high_ray_configurations_on_model(model, 2, candidates=candidates, progress=False)
    assert good.shape == (2, 34)
    with pytest.raises(ValueError, match="only 0 of 2 candidates"):
        bad = np.tile(start, (2, 1))
        bad[:, METRIXS.index("M1_Cylinder.translationXerror")] = 1.0
        high_ray_configurations_on_model(twin, 2, candidates=bad, progress=False)


def _centroid_finder(measurement):
    """A small real finder: the x/y centroid shifts relative to the first configuration, reported
    as E1/E2 pitch offsets through the measured sensitivities (the full finder comes from its own issue)."""
    cx = (measurement.hist_x * np.arange(50)).sum(1) / np.maximum(measurement.hist_x.sum(1), 1e-12)
    off = np.zeros(34)
    off[METRIXS.index("E1.rotationXerror")] = float(np.ptp(cx)) * 0.4 / 3.8 / METRIXS["E1.rotationXerror"].span
    return OffsetResult(np.clip(off, -0.2, 0.2), float(np.var(cx)))


def test_find_offsets_emits_offsets_stream_standalone_and_inside_a_plan(RE, devices, store):
    beamline, chamber = devices
    configs = sample_candidates(2, rng=3, around=default_start(), spread=_spread(0.02))
    token = store.subscribe(RE)
    try:
        meas = RE(measure_configurations(configs, beamline, chamber)).plan_result
        out = RE(find_offsets(_centroid_finder, meas.uid, store=store))
        res = out.plan_result
        assert isinstance(res, OffsetResult) and res.offsets.shape == (34,)
        run = store[out.run_start_uids[0]]
        assert run.metadata["start"]["measurement_uid"] == meas.uid
        assert run.metadata["start"]["truth_id"] == meas.truth_id
        ds = run["offsets"].read()
        assert float(ds["loss"][0]) == pytest.approx(res.loss)
        assert float(ds["E1_rotationXerror"][0]) == pytest.approx(res.offsets[METRIXS.index("E1.rotationXerror")])
        np.testing.assert_allclose(np.asarray(ds["offsets_physical"][0]), res.physical)

        def larger_plan():  # measure, then find offsets inside the same run, on the events just taken
            m = yield from measure_configurations(configs, beamline, chamber)
            seen = []

            def finder(measurement, *, callback=None):  # a Finder that reports progress
                seen.append((measurement.configurations.shape, measurement.histograms.shape, measurement.n_rays,
                             measurement.uid))
                callback({"evaluations": 1, "seconds": 0.0, "loss": 1e-6})
                return OffsetResult(np.zeros(34), 1e-6)

            yield from bps.open_run({"plan_name": "calibrate"})
            r = yield from find_offsets(finder, m, open_run=False)
            yield from bps.close_run()
            return r, seen, m.uid

        out2 = RE(larger_plan())
        r, seen, muid = out2.plan_result
        assert seen == [((2, 34), (2, 100), 3000, muid)] and r.loss == 1e-6
        assert {"finder", "offsets"} <= set(store[out2.run_start_uids[-1]])  # its progress streamed live
    finally:
        RE.unsubscribe(token)
    with pytest.raises(TypeError, match="must return a FinderResult"):
        RE(find_offsets(lambda m: 3.0, meas))
    with pytest.raises(TypeError, match="must return a FinderResult"):  # one return shape: no tuples, no dicts
        RE(find_offsets(lambda m: (np.zeros(34), 1.0), meas))
    with pytest.raises(ValueError, match="cannot be imported"):
        RE(find_offsets("nowhere.module:finder", meas))


def test_measure_with_classic_ophyd_devices_and_a_motor_mapping(RE, metrixs_ioc, ca):
    from bluesky_offsets.epics.devices_v1 import FocusChamberV1, make_beamline_v1
    P = metrixs_ioc.prefix
    beamline = make_beamline_v1(P, name="v1")
    chamber = FocusChamberV1(P + "chamber:", name="cam")
    beamline.wait_for_connection(timeout=60)
    chamber.wait_for_connection(timeout=30)
    before = _positions(ca, P)
    configs = sample_candidates(2, rng=4, around=default_start(), spread=_spread(0.02))
    docs = []
    # the plan takes any mapping {parameter name: movable}: here classic EpicsMotors
    m = RE(measure_configurations(configs, beamline.motors, chamber), lambda n, d: docs.append((n, d))).plan_result
    assert m.hist_x.shape == (2, 50) and m.total_counts.min() > 0
    events = [d for n, d in docs if n == "event"]
    assert len(events) == 2 and "cam_hist_y" in events[0]["data"] and "v1_e1_rx" in events[0]["data"]
    assert events[1]["data"]["v1_e2_rx"] == pytest.approx(configs[1, METRIXS.index("E2.rotationXerror")], abs=1e-5)
    start = next(d for n, d in docs if n == "start")
    assert start["truth_id"] == ca.get(P + "chamber:TruthId", as_string=True)
    assert start["parameter_table_version"] == METRIXS.version and len(start["configurations"]) == 2
    assert _positions(ca, P) == pytest.approx(before, abs=1e-5)
