"""The camera's own calibration: its dark frame, read noise and gain, measured from its frames.

:func:`calibrate_camera` closes the shutter for dark frames, opens it, takes repeated frames where
the beam stands and measures the gain by photon transfer
(:func:`bluesky_offsets.physics.camera.photon_transfer`); the camera reduces every later frame
with the result.  Where the beam gives too little light for a gain within ``max_gain_error``,
the camera keeps the gain it had (its data sheet's), and the result says so.
:func:`calibrate_where_bright` does it after a measurement, where its brightest frame was taken
(the beamline back where it stood after), and returns the measurement rescaled to the gain measured.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import bluesky.plan_stubs as bps
import bluesky.preprocessors as bpp
import numpy as np
from bluesky.utils import MsgGenerator

from bluesky_offsets.errors import InputError
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.physics.camera import CameraCalibration, DarkFrame, dark_frame, photon_transfer
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable

from ._stubs import emit_rows


@dataclasses.dataclass(frozen=True)
class CameraCheck:
    """What :func:`calibrate_camera` measured and whether the gain was taken from it."""

    calibration: CameraCalibration
    measured_gain: float | None
    gain_sigma: float | None
    read_noise: float
    dark_frames: int
    light_frames: int
    gain_measured: bool

    def line(self) -> str:
        """One line for the operator: the dark frames, the read noise and the gain, measured or kept."""
        g = self.calibration
        if self.gain_measured:
            gain = f"gain {g.gain:.2f} ± {self.gain_sigma:.2f} ADU/photon (photon transfer, {self.light_frames} frames)"
        elif self.measured_gain is not None:
            gain = (f"gain {g.gain:.2f} ADU/photon kept: the beam's {self.light_frames} frames gave "
                    f"{self.measured_gain:.2f} ± {self.gain_sigma:.2f}, too uncertain")
        else:
            gain = f"gain {g.gain:.2f} ADU/photon kept: too little light for photon transfer"
        return (f"camera: dark from {self.dark_frames} frames, read noise {self.read_noise:.2f} ADU, "
                f"{stray_text(g)}; {gain}")

    def row(self, used: float) -> dict:
        """The ``gain`` stream's event: the gain the camera had (``used``), the one measured, the one kept."""
        nan = float("nan")
        return {"gain_used": float(used), "gain": float(self.calibration.gain),
                "measured_gain": nan if self.measured_gain is None else float(self.measured_gain),
                "gain_sigma": nan if self.gain_sigma is None else float(self.gain_sigma),
                "gain_measured": bool(self.gain_measured)}


def calibrate_camera(camera, *, darks: int = 4, frames: int = 8, max_gain_error: float = 0.1,
                     md: Mapping | None = None) -> MsgGenerator[CameraCheck]:
    """Measure the camera's dark, read noise and (photon transfer) gain, in one run.

    Dark frames with the shutter closed (the ``dark`` stream), then ``frames`` where the beam stands.

    Parameters
    ----------
    camera : CameraChamber
        The chamber's camera (:class:`bluesky_offsets.epics.camera.CameraChamber`).
    darks, frames : int
        Dark frames (two or more) and frames with light (four or more, for the gain).
    max_gain_error : float
        The largest relative σ of a measured gain that replaces the camera's.
    """
    if darks < 2 or frames < 4:
        raise InputError("calibrate_camera: two or more dark frames and four or more frames with light")
    _md = {"plan_name": "calibrate_camera", "plan_args": {"darks": darks, "frames": frames,
                                                         "max_gain_error": max_gain_error},
           "detectors": [camera.name], **(md or {})}

    taken = {}

    @bpp.stage_decorator([camera])
    @bpp.run_decorator(md=_md)
    def inner():
        dark = dark_frame((yield from _closed(camera, darks)))
        light = yield from _stream(camera, frames, "primary")
        taken["check"] = check = _checked(camera.calibration, dark, light, (yield from _exposure(camera)),
                                          max_gain_error)
        yield from emit_rows("gain", [check.row(camera.calibration.gain)])

    yield from inner()
    camera.calibrate(taken["check"].calibration)
    return taken["check"]


def _checked(before: CameraCalibration, dark: DarkFrame, light: np.ndarray, exposure: float,
             max_gain_error: float) -> CameraCheck:
    """``before`` with the dark of ``dark`` and the photon-transfer gain of ``light`` where it is precise enough."""
    base = _with_dark(before, dark, exposure)
    measured = sigma = None
    try:
        pt = photon_transfer(light, dark)
        measured, sigma = pt.gain, pt.gain_sigma
    except ValueError:
        pass
    ok, cal = False, base
    if measured is not None and sigma is not None and measured > 0 and sigma < max_gain_error * measured:
        ok, cal = True, dataclasses.replace(base, gain=measured, gain_sigma=sigma)
    return CameraCheck(cal, measured, sigma, base.read_noise, dark.frames, len(light), ok)


def _stream(camera, n: int, name: str) -> MsgGenerator[np.ndarray]:
    """``n`` frames as events of stream ``name``; their raw frames."""
    out = []
    for _ in range(n):
        yield from bps.trigger_and_read([camera], name=name)
        out.append(np.asarray(camera.last_frame, float))
    return np.array(out)


def _closed(camera, n: int) -> MsgGenerator[np.ndarray]:
    """``n`` frames with the shutter closed (stream ``dark``); the shutter open again after."""
    yield from bps.mv(camera.shutter, "Close")
    try:
        return (yield from _stream(camera, n, "dark"))
    finally:
        yield from bps.mv(camera.shutter, "Open")


def stray_text(cal: CameraCalibration) -> str:
    """"stray light 24 photons/s over the sensor (subtracted)", at the calibration's gain."""
    w, h = cal.geometry.shape
    return f"stray light {cal.stray_per_second / cal.gain * w * h:.3g} photons/s over the sensor (subtracted)"


def _exposure(camera) -> MsgGenerator[float]:
    """The camera's exposure (s), as its dark frames were taken."""
    return float((yield from bps.rd(camera.driver.acquire_time)))


def _with_dark(cal: CameraCalibration, dark: DarkFrame, exposure: float) -> CameraCalibration:
    """``cal`` with the dark level, read noise and stray light of ``dark`` (frames of ``exposure`` s)."""
    return dataclasses.replace(cal, dark=dark.level, dark_frames=float(dark.frames), read_noise=dark.read_noise,
                               stray_per_second=dark.events / exposure if exposure > 0 else 0.0)


def take_darks(camera, n: int = 4, *, md: Mapping | None = None) -> MsgGenerator[CameraCalibration]:
    """``n`` dark frames with the shutter closed (one run, stream ``dark``).

    They give the camera's dark frame and read noise from now on; no light is needed, so a session
    takes them first.
    """
    if n < 2:
        raise InputError("take_darks: two or more dark frames")
    taken = {}

    @bpp.stage_decorator([camera])
    @bpp.run_decorator(md={"plan_name": "take_darks", "plan_args": {"n": n}, "detectors": [camera.name],
                           **dict(md or {})})
    def inner():
        taken["dark"] = yield from _closed(camera, n)

    yield from inner()
    cal = _with_dark(camera.calibration, dark_frame(taken["dark"]), (yield from _exposure(camera)))
    camera.calibrate(cal)
    return cal


def calibrate_where_bright(camera, beamline, m: Measurement, *, among: int | None = None, darks: int = 4,
                           frames: int = 8, max_gain_error: float = 0.1, md: Mapping | None = None, report=None,
                           table: ParameterTable = METRIXS) -> MsgGenerator[Measurement]:
    """Calibrate ``camera`` where measurement ``m`` was brightest, and rescale ``m`` to the gain measured.

    After measurement ``m`` (taken with ``camera``): to its brightest frame's configuration and
    screen (the brightest of its first ``among`` frames where given), :func:`calibrate_camera`
    there, the motors and the chamber's stage back where they stood (what comes next starts where
    the measurement left the beamline, not at its brightest frame's screen position), and ``m``
    rescaled from the gain it was reduced with to the one measured (unchanged where the gain was
    kept).  The calibration's run names ``m`` (``measurement_uid``), so that ``m`` read back from
    the store is rescaled alike (:func:`gain_scale`).  ``report(check)`` sees the result.
    """
    from .measure import scan_configurations
    from .motion import read_setpoints, resolve_motors, resolve_stage, return_to, tolerances

    motors = {**resolve_motors(beamline, table), **(resolve_stage(beamline) or {})}
    here = yield from read_setpoints(motors, (yield from tolerances(motors)))
    k = int(np.argmax(m.hist_x[:among].sum(axis=1)))
    used = camera.calibration.gain
    screen = None if m.screen is None else m.screen[k][None]

    def there():
        yield from scan_configurations(m.configurations[k][None], beamline, camera, screen=screen, table=table,
                                       return_to_start=False, md={"purpose": "to the brightest frame, for the "
                                                                  "camera's calibration", **dict(md or {})})
        return (yield from calibrate_camera(camera, darks=darks, frames=frames, max_gain_error=max_gain_error,
                                            md={**dict(md or {}), "measurement_uid": m.uid or ""}))

    check = yield from bpp.finalize_wrapper(there(), return_to(motors, here))
    if report is not None:
        report(check)
    return m.scaled(_scale(check.row(used)))


def _scale(row: Mapping) -> float:
    """The factor on frames reduced with the gain the camera had, for the gain measured (1 where kept)."""
    return float(row["gain_used"]) / float(row["gain"]) if bool(row["gain_measured"]) else 1.0


def gain_scale(store, uid: str | None) -> float:
    """The factor on stored measurement ``uid``'s frames for the gain measured after it, 1 where none was.

    The frames are stored as the camera reduced them; :func:`calibrate_where_bright`'s
    ``calibrate_camera`` run names the measurement and holds the gain it measured (stream ``gain``).
    """
    found = None if uid is None else store.latest("calibrate_camera", measurement_uid=uid)
    if found is None:
        return 1.0
    try:
        ds = store[found]["gain"].read()
    except KeyError:  # a run from before the gain was recorded
        return 1.0
    return _scale({k: np.asarray(ds[k])[-1] for k in ("gain_used", "gain", "gain_measured")})


def camera_steps(chamber, beamline, *, md: Mapping | None = None, say=print, table: ParameterTable = METRIXS):
    """What a session adds for a camera chamber: ``(darks, measured)``.

    ``darks`` is the plan that takes its dark frames first, ``measured(m, among=None)`` the hook that
    calibrates its gain where the measurement was brightest (:func:`plans.workflow.calibration_session`'s
    ``measured``); ``(None, None)`` for another chamber.
    """
    if not callable(getattr(chamber, "calibrate", None)):
        return None, None

    def darks():
        cal = yield from take_darks(chamber, md=md)
        say(f"      camera: dark from {cal.dark_frames:g} frames with the shutter closed, read noise "
            f"{cal.read_noise:.2f} ADU, {stray_text(cal)}; the data sheet's gain {cal.gain:g} ADU/photon until measured")

    def measured(m, among=None):
        return (yield from calibrate_where_bright(chamber, beamline, m, among=among, md=md, table=table,
                                                  report=lambda check: say("      " + check.line())))
    return darks, measured
