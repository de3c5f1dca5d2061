"""The focus chamber as a camera: an areaDetector read through ophyd-async's own classes.

:class:`CameraChamber` drives the camera's ``cam1:`` (``ADBaseIO``) and ``HDF1:``
(``NDFileHDF5IO``), both unmodified: staged, the HDF5 plugin streams every frame to one file; a
``trigger`` takes one frame, reads it back from that file (the camera's file system mounted
here, as at a beamline) and turns it into what the fits read (:class:`CameraCalibration`):
the histograms and the camera-resolution profiles as fractions of the source's photons, and the
camera's own noise floor beside them.  Its readings carry the keys of the histogram detector
(:class:`bluesky_offsets.epics.devices.FocusChamber`), so every plan takes either.
"""

from __future__ import annotations

import asyncio
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
from ophyd_async.core import (
    Array1D,
    AsyncStatus,
    EnableDisable,
    StandardReadable,
    set_and_wait_for_value,
    soft_signal_r_and_setter,
    wait_for_value,
)
from ophyd_async.core import StandardReadableFormat as Format
from ophyd_async.epics.adcore import ADBaseIO, ADFileWriteMode, ADImageMode, ADState, NDFileHDF5IO
from ophyd_async.epics.core import epics_signal_rw, stop_busy_record

from bluesky_offsets.epics.pvs import ChamberError
from bluesky_offsets.physics.camera import CameraCalibration
from bluesky_offsets.physics.twin import HistogramSpec

_FLOAT_ARRAYS = ("hist_x", "hist_y", "profile_x", "profile_y", "floor_hx", "floor_hy", "floor_px", "floor_py")


def _read_frame(path: str, index: int) -> np.ndarray:
    import h5py
    with h5py.File(path, "r", locking=False) as f:  # the camera appends while readers hold the file
        return np.asarray(f["entry/data/data"][index])


class CameraChamber(StandardReadable):
    """The focus chamber's camera as the chamber detector of the plans.

    Parameters
    ----------
    prefix : str
        The areaDetector's prefix (``"BL:cam:"``: ``cam1:`` and ``HDF1:`` below it).
    directory : path
        Where the camera writes its HDF5 file, readable from here.
    calibration : CameraCalibration
        Geometry, dark, gain, read noise, region of interest and the source's photons per second.
    hist : HistogramSpec
        The binning of ``hist_x``/``hist_y`` (default the paper's 50 x 50).
    """

    def __init__(self, prefix: str, directory, calibration: CameraCalibration, *, name: str = "",
                 hist: HistogramSpec | None = None, acquire_timeout: float = 120.0):
        self.driver = ADBaseIO(prefix + "cam1:")
        self.hdf = NDFileHDF5IO(prefix + "HDF1:")
        self.shutter = epics_signal_rw(str, prefix + "cam1:ShutterControl")
        self.calibration = calibration
        self.hist = hist or HistogramSpec()
        self.directory = Path(directory)
        self.acquire_timeout = float(acquire_timeout)
        self.last_frame: np.ndarray | None = None  # the raw frame of the last trigger (for calibrations)
        self._setters: dict[str, Callable[..., None]] = {}
        with self.add_children_as_readables():
            for key in _FLOAT_ARRAYS:
                sig, self._setters[key] = soft_signal_r_and_setter(Array1D[np.float64])
                setattr(self, key, sig)
            self.total_counts, self._setters["total_counts"] = soft_signal_r_and_setter(int)
            self.array_counter, self._setters["array_counter"] = soft_signal_r_and_setter(int)
        spec = calibration.geometry.spec
        with self.add_children_as_readables(Format.CONFIG_SIGNAL):
            self.num_rays, self._setters["num_rays"] = soft_signal_r_and_setter(int)
            self.profile_axis_x, _ = soft_signal_r_and_setter(Array1D[np.float64], initial_value=spec.centers_x)
            self.profile_axis_y, _ = soft_signal_r_and_setter(Array1D[np.float64], initial_value=spec.centers_y)
            self.gain, self._setters["gain"] = soft_signal_r_and_setter(float, initial_value=calibration.gain)
            self.read_noise, self._setters["read_noise"] = soft_signal_r_and_setter(
                float, initial_value=calibration.read_noise)
        self.add_readables([self.driver.acquire_time], Format.CONFIG_SIGNAL)
        super().__init__(name=name)

    def calibrate(self, calibration: CameraCalibration) -> None:
        """Reduce the frames from now on with ``calibration`` (a new dark, gain or region of interest)."""
        self.calibration = calibration
        self._setters["gain"](calibration.gain)
        self._setters["read_noise"](calibration.read_noise)

    @AsyncStatus.wrap
    async def stage(self) -> None:
        """One HDF5 file for the frames from now until unstaged; single frames on each trigger."""
        await super().stage()
        await self._capture()

    async def _capture(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        await asyncio.gather(
            self.hdf.enable_callbacks.set(EnableDisable.ENABLE),
            self.hdf.file_path.set(f"{self.directory}/"),
            self.hdf.file_name.set(f"{self.name or 'camera'}-{uuid.uuid4().hex[:12]}"),
            self.hdf.file_template.set("%s%s.h5"),
            self.hdf.file_write_mode.set(ADFileWriteMode.STREAM),
            self.hdf.num_capture.set(0),
            self.driver.image_mode.set(ADImageMode.SINGLE),
        )
        if not await self.hdf.file_path_exists.get_value():
            raise ChamberError(f"{self.name}: the camera cannot write to {self.directory}")
        await set_and_wait_for_value(self.hdf.capture, True, wait_for_set_completion=False)
        exposure = await self.driver.acquire_time.get_value()
        self._setters["num_rays"](self.calibration.source_photons(exposure))

    @AsyncStatus.wrap
    async def unstage(self) -> None:
        """Stop the HDF5 plugin's capture, closing the frames' file."""
        await stop_busy_record(self.hdf.capture)
        await super().unstage()

    @AsyncStatus.wrap
    async def trigger(self) -> None:
        """Take one frame, read it back from the HDF5 file and set the readings to its reduction."""
        if not await self.hdf.capture.get_value():  # a plan that does not stage its detectors
            await self._capture()
        before = await self.hdf.num_captured.get_value()
        try:
            await self.driver.acquire.set(True, timeout=self.acquire_timeout)
        except Exception as exc:
            raise ChamberError(f"{self.name}: acquisition failed: {type(exc).__name__}: {exc}") from exc
        state = await self.driver.detector_state.get_value()
        if state != ADState.IDLE:
            raise ChamberError(f"{self.name}: acquisition ended {state.value}")
        try:  # the file plugin may lag the frame on a loaded camera server
            await wait_for_value(self.hdf.num_captured, before + 1, timeout=self.acquire_timeout)
        except TimeoutError as exc:
            raise ChamberError(f"{self.name}: the HDF5 plugin wrote no frame within {self.acquire_timeout:g} s "
                               f"of the acquisition") from exc
        path, exposure, counter = await asyncio.gather(self.hdf.full_file_name.get_value(),
                                                       self.driver.acquire_time.get_value(),
                                                       self.driver.array_counter.get_value())
        frame = self.last_frame = await asyncio.to_thread(_read_frame, path, before)
        reduced = self.calibration.reduce(frame, exposure, self.hist)
        for key in _FLOAT_ARRAYS:
            self._setters[key](np.asarray(reduced[key], float))
        self._setters["total_counts"](int(round(reduced["photons"])))
        self._setters["array_counter"](int(counter))
        self._setters["num_rays"](reduced["n_source"])
