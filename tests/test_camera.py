"""The focus chamber as a camera: pixel geometry, the camera model, the gain from frames, and the
simulated IOC's areaDetector camera read by ophyd-async's own classes through a bluesky ``count``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bluesky_offsets.physics.camera import CameraGeometry, Roi, dark_frame, photon_transfer, profiles, screen_image
from bluesky_offsets.physics.twin import CAMERA, HistogramSpec
from sim_iocs.camera import CameraNoise, c_format


def _spot(rng, n=20000, poisson=False):
    n = rng.poisson(n) if poisson else n
    return np.column_stack([rng.normal(0.4, 0.3, n), rng.normal(-0.1, 0.02, n)])


@pytest.mark.parametrize("mount", [{}, {"flip_x": True}, {"flip_y": True, "transpose": True},
                                   {"flip_x": True, "flip_y": True, "transpose": True}])
def test_a_mounted_camera_gives_the_screen_back(mount):
    rng = np.random.default_rng(1)
    xy = _spot(rng)
    geo = CameraGeometry(**mount)
    frame = geo.photons(xy)
    assert frame.shape == geo.shape
    hx, hy = CAMERA.histograms(xy[:, 0], xy[:, 1], 1)
    p = profiles(frame, geo, dark=0.0, gain=1.0, read_noise=0.0)
    np.testing.assert_array_equal(p.x, hx)
    np.testing.assert_array_equal(p.y, hy)
    np.testing.assert_array_equal(screen_image(geo, frame).sum(axis=0), hx)
    paper = HistogramSpec()
    b = p.binned(geo, paper)
    px, py = paper.histograms(xy[:, 0], xy[:, 1], 1)
    np.testing.assert_allclose(b.x, px)
    np.testing.assert_allclose(b.y, py)
    with pytest.raises(ValueError, match="pixel edges"):
        p.binned(geo, HistogramSpec(bins_x=47))


def test_geometry_refuses_unknown_keys_and_bad_sizes():
    with pytest.raises(ValueError, match="unknown keys"):
        CameraGeometry.from_dict({"pixel_size": 0.02})
    with pytest.raises(ValueError, match="positive"):
        CameraGeometry(pixel_x_mm=0.0)


def test_photon_transfer_measures_the_gain_and_profiles_carry_the_noise():
    """Four frames of one spot and two dark frames give the gain within its σ, and the profiles'
    variances (photons plus read noise) match the scatter of repeated frames."""
    noise = CameraNoise(gain=7.0, read_noise=3.0, fixed_pattern=4.0, background=0.0)
    geo = CameraGeometry(width=200, height=300)
    pattern = noise.pattern(geo, seed=3)
    rng = np.random.default_rng(5)
    spot = lambda: _spot(rng, 30000, poisson=True)  # noqa: E731
    light = [noise.render(spot(), geo, pattern, 1.0, rng) for _ in range(4)]
    darks = np.array([noise.render(np.empty((0, 2)), geo, pattern, 1.0, rng) for _ in range(2)])
    pt = photon_transfer(light, darks)
    assert photon_transfer(light, dark_frame(darks)) == pt  # the dark frames, or their DarkFrame
    assert abs(pt.gain - 7.0) < 3 * pt.gain_sigma and pt.gain_sigma < 0.08 * 7.0
    assert abs(pt.read_noise - 3.0) < 0.1
    dark = darks.mean(axis=0)
    roi = Roi(y0=100, y1=200)
    ps = [profiles(noise.render(spot(), geo, pattern, 1.0, rng), geo, dark=dark, gain=pt.gain,
                   read_noise=pt.read_noise, roi=roi) for _ in range(40)]
    x = np.array([p.x for p in ps])
    lit = x.mean(axis=0) > 20
    ratio = x.var(axis=0, ddof=1)[lit] / np.mean([p.var_x for p in ps], axis=0)[lit]
    assert 0.85 < np.median(ratio) < 1.15
    assert abs(np.mean([p.photons for p in ps]) * pt.gain / 7.0 / 30000 - 1) < 0.015  # all in the ROI


def _two_samples_chi2(n: np.ndarray, m: np.ndarray, floor: np.ndarray, lit: np.ndarray,
                      least: float = 5.0) -> tuple[float, int]:
    """χ² and its degrees of freedom of two histograms of one shape (counts ``n``, ``m``; ``floor``:
    ``n``'s variance beside its counts), over the span of the ``lit`` bins.  Neighbouring bins are
    grouped until each group expects ``least`` counts of the smaller sample: χ² has its distribution
    only there (a tail bin holding one ray of the smaller sample would weigh as a many-σ outlier)."""
    a, b = n.sum(), m.sum()
    idx = np.flatnonzero(lit)
    n, m, floor = (v[idx[0]:idx[-1] + 1] for v in (n, m, floor))
    share = min(a, b) / (a + b)
    groups: list[list[int]] = [[]]
    for i in range(len(n)):
        if groups[-1] and (n[groups[-1]].sum() + m[groups[-1]].sum()) * share >= least:
            groups.append([])
        groups[-1].append(i)
    if len(groups) > 1 and (n[groups[-1]].sum() + m[groups[-1]].sum()) * share < least:
        groups[-2] += groups.pop()
    ng, mg, fg = (np.array([v[g].sum() for g in groups]) for v in (n, m, floor))
    pooled = np.clip(ng + mg, 0.0, None) / (a + b)
    return float(np.sum((ng / a - mg / b) ** 2 / (pooled * (1 / a + 1 / b) + fg / a**2))), len(groups) - 1


def _dark_noise(noise: CameraNoise) -> float:
    """A dark frame's noise per pixel (ADU): read noise and the counts' rounding (stray photons are
    events, left out of the dark)."""
    return float(np.sqrt(noise.read_noise**2 + 1 / 12))


def test_stray_photons_are_events_of_the_dark_and_their_mean_is_subtracted_from_every_frame():
    """A stray photon in a dark frame is ``gain`` ADU in one pixel: averaged into the dark, it took
    4 photons from a column of every sum of 8 frames (7 σ of the noise the profiles carry).  Left
    out of the dark, their mean is what every frame receives, and is subtracted from each."""
    noise = CameraNoise(background=2e-3)  # ~480 stray photons in each dark frame of 4 s
    # three dark frames: with two, a pixel hit in both (~4 here, none at the camera's own rate) is a hot pixel
    geo = CameraGeometry(width=300, height=200)
    pattern = noise.pattern(geo, seed=3)
    rng = np.random.default_rng(11)
    darks = np.array([noise.render(np.empty((0, 2)), geo, pattern, 4.0, rng) for _ in range(3)])
    d = dark_frame(darks)
    expected = 3 * geo.width * geo.height * noise.background * 4.0
    assert abs(d.rejected - expected) < 5 * np.sqrt(expected), (d.rejected, expected)
    assert abs(d.read_noise / _dark_noise(noise) - 1) < 0.05, d
    assert np.abs(d.level - pattern).max() < 6 * noise.read_noise, np.abs(d.level - pattern).max()  # no photon's 64 ADU
    per_pixel = noise.gain * noise.background * 4.0  # ADU a pixel receives in a frame, on average
    assert abs(d.events / per_pixel - 1) < 5 / np.sqrt(expected), (d.events, per_pixel)
    # eight frames with no light but their own stray photons: every column within the noise, the
    # stray light's mean subtracted and its Poisson noise in the floor
    k = 8
    frames = sum(noise.render(np.empty((0, 2)), geo, pattern, 4.0, rng).astype(float) for _ in range(k))
    p = profiles(frames, geo, dark=k * d.level, gain=noise.gain, read_noise=np.sqrt(k) * d.read_noise,
                 dark_frames=3 / k, stray=k * d.events)
    for prof, floor in ((p.x, p.floor_x), (p.y, p.floor_y)):
        z = prof / np.sqrt(floor)  # no light: the camera's own noise and the stray light's alone
        assert np.abs(z).max() < 5 and 0.7 < np.mean(z**2) < 1.3 and abs(z.mean()) < 5 / np.sqrt(z.size), (
            np.abs(z).max(), np.mean(z**2), z.mean())


def test_the_camera_appends_while_another_process_reads_its_file(tmp_path):
    """A reader holding the frames' file open (the run store, a client) does not stop the capture:
    with HDF5's file lock the camera's next append failed and every later frame was lost."""
    import subprocess
    import sys

    from sim_iocs.camera import _append

    path = tmp_path / "frames.h5"
    frame = np.arange(12, dtype=np.uint16).reshape(3, 4)
    _append(path, frame, 1, 0.0)
    code = ("import sys, h5py; f = h5py.File(sys.argv[1], 'r'); print('open', flush=True); sys.stdin.read()")
    reader = subprocess.Popen([sys.executable, "-c", code, str(path)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True)
    try:
        assert reader.stdout.readline().strip() == "open"
        _append(path, frame + 1, 2, 1.0)
    finally:
        reader.communicate("")
    from bluesky_offsets.epics.camera import _read_frame
    assert np.array_equal(_read_frame(str(path), 1), frame + 1)


def test_file_names_follow_the_c_template():
    assert c_format("%s%s.h5", "/d/", "f", 3) == "/d/f.h5"
    assert c_format("%s%s_%3.3d.h5", "/d/", "f", 3) == "/d/f_003.h5"
    for bad in ("%s%s%s%s", "%d%s"):
        with pytest.raises(ValueError, match="FileTemplate"):
            c_format(bad, "/d/", "f", 3)


def test_ophyd_async_area_detector_counts_frames_into_the_store(metrixs_ioc, run_store, ca):
    """ophyd-async's SimDetector, unmodified, on the simulated camera: a plain ``count`` writes
    frames through the HDF5 plugin, the run store reads them back from the file, the gain measured
    from them (photon transfer, the shutter closed for the dark frames) is the camera's, and their
    profiles have the shape the chamber's profile PVs give at the same state."""
    from bluesky import RunEngine
    from bluesky import plan_stubs as bps
    from bluesky.plans import count
    from ophyd_async.core import init_devices
    from ophyd_async.epics.core import epics_signal_rw

    from bluesky_offsets.epics.devices import focus_camera

    ioc = metrixs_ioc  # the session's IOC: a client that saw a stopped IOC's port would find a stale circuit
    rays = ca.get(ioc.prefix + "chamber:NumRays")
    RE = RunEngine({}, call_returns_result=True)
    run_store.subscribe(RE)
    frames = run_store.frames_directory
    with init_devices():
        camera = focus_camera(ioc.prefix + "cam:", frames)
        shutter = epics_signal_rw(str, ioc.prefix + "cam:cam1:ShutterControl")
    try:

        def take(n):
            uid = RE(count([camera], num=n)).run_start_uids[0]
            # (events, frames per event, rows, columns)
            return np.asarray(run_store[uid]["primary"]["camera"].read())

        RE(bps.mv(camera.driver.acquire_time, 4.0))
        light = take(8)[:, 0]
        assert light.shape == (8, *CameraGeometry().shape) and light.dtype == np.uint16
        RE(bps.mv(shutter, "Close"))
        dark = take(2)[:, 0]
        assert len(list(frames.glob("*.h5"))) >= 2
        noise = CameraNoise()
        pt = photon_transfer(light, dark)
        assert abs(pt.gain - noise.gain) < 3 * pt.gain_sigma and pt.gain_sigma < 0.12 * noise.gain, pt
        assert abs(pt.read_noise / _dark_noise(noise) - 1) < 0.1, pt
        geo = CameraGeometry()
        # the same footprint as the chamber's profile PVs (20 x 5 µm bins, the camera's pixels) at the
        # same state: the shapes agree within noise
        ca.put(ioc.prefix + "chamber:NumRays", 20000)
        ca.put(ioc.prefix + "chamber:Acquire", "Acquire")
        hist = {a: np.asarray(ca.get(ioc.prefix + f"chamber:Profile{a.upper()}")) * 20000 for a in "xy"}
        bx, by = (np.flatnonzero(hist[a])[[0, -1]] for a in "xy")
        roi = Roi(x0=max(bx[0] - 20, 0), x1=bx[1] + 21, y0=max(by[0] - 20, 0), y1=by[1] + 21)  # around the beam
        k = len(light)
        p = profiles(light.sum(axis=0, dtype=float), geo, dark=k * dark_frame(dark).level, gain=pt.gain,
                     read_noise=np.sqrt(k) * pt.read_noise, roi=roi, dark_frames=len(dark) / k)
        assert 0 < p.photons < 5.0 * k * noise.rays_per_second  # ~ every photon of 4 s at most
        for axis in "xy":
            cam, var, floor = getattr(p, axis), getattr(p, "var_" + axis), getattr(p, "floor_" + axis)
            lit = (hist[axis] > 0) | (np.abs(cam) > 3 * np.sqrt(var))
            # two samples of one shape: each bin's expectation from both (a bin's own few counts as
            # its variance bias the sum upwards where the tails hold one or two rays)
            chi2, dof = _two_samples_chi2(cam, hist[axis], floor, lit)
            assert chi2 / max(dof, 1) < 2.5, (axis, chi2, dof, roi, np.flatnonzero(lit))
    finally:
        RE(bps.mv(camera.driver.acquire_time, 1.0, shutter, "Open"))
        ca.put(ioc.prefix + "chamber:NumRays", rays)


def test_the_camera_chamber_measures_what_the_histogram_chamber_measures(tmp_path, metrixs_ioc, ca):
    """The plans' chamber on the camera: its calibration (dark frames with the shutter closed, the
    gain by photon transfer), then ``measure_configurations`` on the camera and on the histogram PVs
    at the same configurations; at the true gain their intensities agree within the photon noise
    (the camera's stray light subtracted by its reduction), their histograms within the photon
    noise and the camera's floor."""
    from bluesky import RunEngine
    from bluesky import plan_stubs as bps
    from ophyd_async.core import init_devices

    from bluesky_offsets.epics.camera import CameraChamber
    from bluesky_offsets.epics.devices import FocusChamber, MetrixsBeamline
    from bluesky_offsets.physics.camera import CameraCalibration
    from bluesky_offsets.physics.parameters import METRIXS
    from plans.camera import calibrate_camera
    from plans.measure import measure_configurations
    from sim_iocs.truth import default_start

    ioc = metrixs_ioc
    rays = ca.get(ioc.prefix + "chamber:NumRays")
    RE = RunEngine({}, call_returns_result=True)
    noise = CameraNoise()
    nominal = CameraCalibration(gain=noise.gain, read_noise=noise.read_noise, dark=noise.dark,
                                photons_per_second=noise.rays_per_second)
    with init_devices():
        beamline = MetrixsBeamline(ioc.prefix, name="metrixs")
        chamber = FocusChamber(ioc.prefix + "chamber:", name="chamber")
        camera = CameraChamber(ioc.prefix + "cam:", tmp_path / "frames", nominal, name="camera")
    ca.put(ioc.prefix + "chamber:NumRays", 20000)
    try:
        RE(bps.mv(camera.driver.acquire_time, 4.0))
        check = RE(calibrate_camera(camera, darks=3, frames=12, max_gain_error=0.2)).plan_result
        assert abs(check.read_noise / _dark_noise(noise) - 1) < 0.15 and check.dark_frames == 3
        assert check.gain_measured and abs(check.measured_gain - noise.gain) < 3 * check.gain_sigma, check.line()
        assert camera.calibration.gain == check.measured_gain and check.line().startswith("camera: dark from 3")
        configs = np.tile(default_start(), (2, 1))  # where the IOC starts: the beam on the screen
        configs[1, METRIXS.index("E1.rotationXerror")] += 0.002
        cam = RE(measure_configurations(configs, beamline, camera)).plan_result
        ref = RE(measure_configurations(configs, beamline, chamber)).plan_result
        assert cam.n_rays == 20000 and ref.n_rays == 20000
        assert cam.hist_x.shape == ref.hist_x.shape == (2, 50)
        assert cam.profile_x is not None and cam.profile_floor_x.shape == cam.profile_x.shape
        both = cam.joined(cam.subset([1]))  # frames joined keep the camera's profiles and floors
        np.testing.assert_array_equal(both.profile_x, cam.profile_x[[0, 1, 1]])
        np.testing.assert_array_equal(both.profile_floor_y, cam.profile_floor_y[[0, 1, 1]])
        # the stray light as the dark frames saw it: what each pixel receives a second
        geo = camera.calibration.geometry
        stray = camera.calibration.stray_per_second / noise.gain * geo.width * geo.height  # photons/s
        expected = noise.background * geo.width * geo.height
        assert abs(stray / expected - 1) < 5 / np.sqrt(3 * 4.0 * expected), (stray, expected)
        # the gain's own error is judged above, against the truth; here the reduction, at the true gain
        to_true = check.measured_gain / noise.gain
        for a, b, floor in ((cam.hist_x, ref.hist_x, cam.floor_x), (cam.hist_y, ref.hist_y, cam.floor_y)):
            a, floor = a * to_true, floor * to_true**2
            photons = 20000 * np.array([a.sum(axis=1), b.sum(axis=1)])
            excess = a.sum(axis=1) / b.sum(axis=1) - 1
            # the stray light's own noise beside the two beams'
            sigma = np.sqrt(1 / photons[0] + 1 / photons[1] + 4.0 * expected / photons[1] ** 2)
            assert np.all(np.abs(excess) < 3 * sigma), (excess, photons)
            occupied = (a > 0) | (b > 0)
            var = (np.clip(a, 0, None) + b) / 20000 + floor
            chi2 = float((((a - b) ** 2) / var)[occupied].sum())
            assert chi2 / occupied.sum() < 2.5, chi2
    finally:  # the session's IOC as it was: exposure, ray budget, no capture running
        RE(bps.mv(camera.driver.acquire_time, 1.0))
        RE(bps.unstage(camera))
        ca.put(ioc.prefix + "chamber:NumRays", rays)


def test_the_camera_is_calibrated_where_bright_and_the_beamline_left_where_it_stood(tmp_path, metrixs_ioc, ca,
                                                                                   run_store):
    """``calibrate_where_bright`` goes to a measurement's brightest frame (its motors and screen) for
    the camera's gain, then brings the motors and the chamber's stage back: the beam optimization
    after it would else work at that frame's screen position.  The measurement read back from the
    store is rescaled to the gain measured, as the session fitted it."""
    from bluesky import RunEngine
    from bluesky import plan_stubs as bps
    from ophyd_async.core import init_devices

    from bluesky_offsets.epics.camera import CameraChamber
    from bluesky_offsets.epics.devices import MetrixsBeamline
    from bluesky_offsets.physics.camera import CameraCalibration
    from plans.camera import calibrate_where_bright, gain_scale
    from plans.measure import measure_configurations
    from plans.motion import read_positions, resolve_motors, resolve_stage
    from plans.workflow import as_analysed
    from sim_iocs.truth import default_start

    ioc = metrixs_ioc
    RE = RunEngine({}, call_returns_result=True)
    noise = CameraNoise()
    nominal = CameraCalibration(gain=noise.gain, read_noise=noise.read_noise, dark=noise.dark,
                                photons_per_second=noise.rays_per_second)
    with init_devices():
        beamline = MetrixsBeamline(ioc.prefix, name="staged", stage={a: f"{ioc.prefix}chamber:{a}" for a in "xyz"})
        camera = CameraChamber(ioc.prefix + "cam:", tmp_path / "frames", nominal, name="camera")
    stage = resolve_stage(beamline)
    assert stage is not None
    motors = {**resolve_motors(beamline), **stage}
    token = run_store.subscribe(RE)
    try:
        before = RE(read_positions(motors)).plan_result
        configs = np.tile(default_start(), (2, 1))
        screen = np.array([[0.0, 0.0, 6.0], [0.5, 0.0, -4.0]])
        m = RE(measure_configurations(configs, beamline, camera, screen=screen)).plan_result
        assert gain_scale(run_store, m.uid) == 1.0  # not yet calibrated after it
        scaled = RE(calibrate_where_bright(camera, beamline, m, among=1, darks=2, frames=4,
                                           max_gain_error=1.0)).plan_result
        after = RE(read_positions(motors)).plan_result
        assert after == pytest.approx(before, abs=1e-6), {k: (before[k], after[k]) for k in before
                                                          if abs(before[k] - after[k]) > 1e-6}
        assert scaled.hist_x.sum() == pytest.approx(m.hist_x.sum() * noise.gain / camera.calibration.gain, rel=0.3)
        run_store.flush()
        assert gain_scale(run_store, m.uid) == pytest.approx(noise.gain / camera.calibration.gain, rel=1e-12)
        # this camera's frames say no ray budget: one given, as a comparison needs
        back = as_analysed(run_store, dataclasses.replace(run_store.load_measurement(m.uid), n_rays=1000))
        fitted = dataclasses.replace(scaled, n_rays=1000).for_analysis()
        assert np.allclose(back.hist_x, fitted.hist_x, rtol=1e-9, atol=0)
        assert np.allclose(back.floor, fitted.floor, rtol=1e-9, atol=0)
    finally:
        RE.unsubscribe(token)
        RE(bps.unstage(camera))


def test_a_frame_that_fails_ends_the_acquisition_in_error():
    """A frame the beamline model could not make ends the acquisition ``Error`` at once: counted as
    taken, it left the client waiting for a file plugin that never got it."""
    import asyncio

    from sim_iocs.camera import CamDriver

    async def take(exposure, shutter_open):
        raise RuntimeError("the frame worker died")

    async def acquire():
        cam = CamDriver(prefix="T:", take=take, shape=(4, 5), name="cam")
        await cam._acquire()
        return cam.detector_state_rbv.value, cam.num_images_counter_rbv.value, cam.status_message.value

    state, taken, message = asyncio.run(acquire())
    assert (state, taken) == ("Error", 0) and "frame failed" in message
