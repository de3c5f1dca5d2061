"""The focus chamber's camera as an areaDetector: a ``cam1:`` driver and an ``HDF1:`` file plugin.

The PVs carry the names of ADCore's ``ADBase``/``NDFile``/``NDFileHDF5`` templates, so that
ophyd-async's areaDetector classes (``SimDetector`` with ``ADWriterFactory.hdf``) connect to them
unmodified.  A frame is the traced rays through a camera model (:class:`CameraNoise`): each ray
that reaches the screen is a photon; the exposure (``AcquireTime``) sets how many the source
sends; a photon reads ``gain`` ADU, on a dark level with a fixed pattern, read noise, a stray
background and a 16-bit saturation.  ``ShutterControl`` closed gives dark frames.  The HDF5
plugin appends each frame to ``/entry/data/data`` of ``FullFileName_RBV`` and closes the file
between frames, so readers need no SWMR.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from caproto import ChannelType
from caproto.server import PVGroup, pvproperty
from caproto._data import SkipWrite

from bluesky_offsets.physics.camera import CameraGeometry

from .backends import Frame
from .motor_record import StrictDouble, StrictLong

log = logging.getLogger("sim_iocs.camera")

_ENUM = ChannelType.ENUM
_NO_YES = ("No", "Yes")
_STATES = ("Idle", "Acquire", "Readout", "Correct", "Saving", "Aborting", "Error", "Waiting",
           "Initializing", "Disconnected", "Aborted")
_DATA_TYPES = ("Int8", "UInt8", "Int16", "UInt16", "Int32", "UInt32", "Int64", "UInt64", "Float32", "Float64")
_COLOR_MODES = ("Mono", "Bayer", "RGB1", "RGB2", "RGB3", "YUV444", "YUV422", "YUV421")
_COMPRESSION = ("None", "N-bit", "szip", "zlib", "Blosc", "BSLZ4", "LZ4", "JPEG")


@dataclass(frozen=True, kw_only=True)
class CameraNoise:
    """How the simulated camera turns photons into counts (ADU).

    The defaults are typical of a directly illuminated soft X-ray CCD: a photon of ~930 eV frees
    ~255 electrons, read at 4 electrons per ADU, with 3 electrons of read noise.

    Parameters
    ----------
    gain : float
        ADU per detected photon.
    dark : float
        Mean dark level (ADU); ``fixed_pattern`` its pixel-to-pixel spread (ADU, the same every frame).
    read_noise : float
        Read noise per pixel and frame (ADU).
    background : float
        Stray photons per pixel and second of exposure.
    bits : int
        Counts saturate at ``2**bits - 1``.
    rays_per_second : float
        Photons the source sends per second of exposure (traced rays; capped by the IOC's ray limit).
    """

    gain: float = 64.0
    dark: float = 100.0
    fixed_pattern: float = 1.0
    read_noise: float = 0.75
    background: float = 2e-5
    bits: int = 16
    rays_per_second: float = 5000.0

    def __post_init__(self):
        numbers = dataclasses.astuple(self)
        if not all(np.isfinite(v) and v >= 0 for v in numbers) or self.gain <= 0 or not 8 <= self.bits <= 16:
            raise ValueError(f"camera noise: every value finite and >= 0, gain > 0, 8 <= bits <= 16: {self}")

    def pattern(self, geometry: CameraGeometry, seed: int = 0) -> np.ndarray:
        """The dark level of each pixel (ADU), as the camera delivers frames: its fixed pattern."""
        rng = np.random.default_rng([seed, 0xDA7C])  # the sensor's own stream: the same every frame
        return self.dark + self.fixed_pattern * rng.standard_normal(geometry.shape)

    def render(self, xy: np.ndarray, geometry: CameraGeometry, pattern: np.ndarray, exposure: float,
               rng: np.random.Generator) -> np.ndarray:
        """One frame (uint16) of the screen points ``xy`` (photons, mm) after ``exposure`` seconds."""
        photons = geometry.photons(xy)
        if self.background > 0:
            photons = photons + rng.poisson(self.background * exposure, photons.shape)
        adu = pattern + self.gain * photons + self.read_noise * rng.standard_normal(photons.shape)
        return np.clip(np.rint(adu), 0, 2 ** self.bits - 1).astype(np.uint16)


def _rw(value, name, **kw):
    return pvproperty(value=value, name=name, **kw)


def _ro(value, name, **kw):
    return pvproperty(value=value, name=name, read_only=True, **kw)


def _text(value, name, read_only=False):
    # a char waveform, as areaDetector's paths are: longer than a DBR_STRING's 40 characters
    return pvproperty(value=value, name=name, dtype=ChannelType.CHAR, max_length=256, string_encoding="latin-1",
                      read_only=read_only)


class _Mirrored(PVGroup):
    """A group whose setpoints publish their ``_RBV`` readback on every accepted put."""

    async def group_write(self, instance, value):
        rbv = getattr(self, instance.pvspec.attr + "_rbv", None)
        if rbv is not None:
            await rbv.write(value)
        return value


class NDArrayBase(_Mirrored):
    """The ``NDArrayBase.template`` PVs every driver and plugin has."""

    port_name_rbv = _ro("CAM", "PortName_RBV", dtype=ChannelType.STRING)
    unique_id_rbv = _ro(0, "UniqueId_RBV")
    nd_attributes_file = _text("", "NDAttributesFile")
    array_size_x_rbv = _ro(0, "ArraySizeX_RBV")
    array_size_y_rbv = _ro(0, "ArraySizeY_RBV")
    array_size_z_rbv = _ro(0, "ArraySizeZ_RBV")
    array_size0_rbv = _ro(0, "ArraySize0_RBV")
    array_size1_rbv = _ro(0, "ArraySize1_RBV")
    array_size2_rbv = _ro(0, "ArraySize2_RBV")
    color_mode_rbv = _ro("Mono", "ColorMode_RBV", dtype=_ENUM, enum_strings=_COLOR_MODES)
    data_type_rbv = _ro("UInt16", "DataType_RBV", dtype=_ENUM, enum_strings=_DATA_TYPES)
    array_counter = _rw(0, "ArrayCounter", dtype=StrictLong)
    array_counter_rbv = _ro(0, "ArrayCounter_RBV")
    ad_core_version_rbv = _ro("3.12.1", "ADCoreVersion_RBV", dtype=ChannelType.STRING)
    driver_version_rbv = _ro("bluesky-offsets", "DriverVersion_RBV", dtype=ChannelType.STRING)
    time_stamp_rbv = _ro(0.0, "TimeStamp_RBV")

    async def frame_done(self, shape: tuple[int, int], uid: int, ts: float) -> None:
        """Publish one frame's counters and size (rows, columns)."""
        for pv, v in ((self.array_size_x_rbv, shape[1]), (self.array_size_y_rbv, shape[0]),
                      (self.array_size0_rbv, shape[1]), (self.array_size1_rbv, shape[0]),
                      (self.unique_id_rbv, uid), (self.time_stamp_rbv, ts)):
            await pv.write(v, timestamp=ts)
        await self.array_counter.write(self.array_counter.value + 1, timestamp=ts)


class HDF5Plugin(NDArrayBase):
    """``NDFileHDF5``: appends each frame of the driver to an HDF5 file while ``Capture`` is on."""

    nd_array_port = _rw("CAM", "NDArrayPort", dtype=ChannelType.STRING)
    nd_array_port_rbv = _ro("CAM", "NDArrayPort_RBV", dtype=ChannelType.STRING)
    enable_callbacks = _rw("Disable", "EnableCallbacks", dtype=_ENUM, enum_strings=("Disable", "Enable"))
    enable_callbacks_rbv = _ro("Disable", "EnableCallbacks_RBV", dtype=_ENUM, enum_strings=("Disable", "Enable"))
    nd_array_address = _rw(0, "NDArrayAddress", dtype=StrictLong)
    nd_array_address_rbv = _ro(0, "NDArrayAddress_RBV")
    queue_size = _rw(20, "QueueSize", dtype=StrictLong)
    queue_size_rbv = _ro(20, "QueueSize_RBV")
    file_path = _text("", "FilePath")
    file_path_rbv = _text("", "FilePath_RBV", read_only=True)
    file_name = _text("", "FileName")
    file_name_rbv = _text("", "FileName_RBV", read_only=True)
    file_path_exists_rbv = _ro("No", "FilePathExists_RBV", dtype=_ENUM, enum_strings=_NO_YES)
    file_template = _text("%s%s_%3.3d.h5", "FileTemplate")
    file_template_rbv = _text("%s%s_%3.3d.h5", "FileTemplate_RBV", read_only=True)
    full_file_name_rbv = _text("", "FullFileName_RBV", read_only=True)
    file_number = _rw(0, "FileNumber", dtype=StrictLong)
    auto_increment = _rw("No", "AutoIncrement", dtype=_ENUM, enum_strings=_NO_YES)
    file_write_mode = _rw("Single", "FileWriteMode", dtype=_ENUM, enum_strings=("Single", "Capture", "Stream"))
    file_write_mode_rbv = _ro("Single", "FileWriteMode_RBV", dtype=_ENUM, enum_strings=("Single", "Capture", "Stream"))
    num_capture = _rw(1, "NumCapture", dtype=StrictLong)
    num_capture_rbv = _ro(1, "NumCapture_RBV")
    num_captured_rbv = _ro(0, "NumCaptured_RBV")
    capture = _rw("Done", "Capture", dtype=_ENUM, enum_strings=("Done", "Capture"))
    capture_rbv = _ro("Done", "Capture_RBV", dtype=_ENUM, enum_strings=("Done", "Capture"))
    array_size0_plain = _ro(0, "ArraySize0")
    array_size1_plain = _ro(0, "ArraySize1")
    create_directory = _rw(0, "CreateDirectory", dtype=StrictLong)
    position_mode = _rw("No", "PositionMode", dtype=_ENUM, enum_strings=_NO_YES)
    position_mode_rbv = _ro("No", "PositionMode_RBV", dtype=_ENUM, enum_strings=_NO_YES)
    compression = _rw("None", "Compression", dtype=_ENUM, enum_strings=_COMPRESSION)
    compression_rbv = _ro("None", "Compression_RBV", dtype=_ENUM, enum_strings=_COMPRESSION)
    num_extra_dims = _rw(0, "NumExtraDims", dtype=StrictLong)
    num_extra_dims_rbv = _ro(0, "NumExtraDims_RBV")
    swmr_mode = _rw("No", "SWMRMode", dtype=_ENUM, enum_strings=_NO_YES)
    swmr_mode_rbv = _ro("No", "SWMRMode_RBV", dtype=_ENUM, enum_strings=_NO_YES)
    flush_now = _rw("No", "FlushNow", dtype=_ENUM, enum_strings=_NO_YES)
    xml_file_name = _text("", "XMLFileName")
    xml_file_name_rbv = _text("", "XMLFileName_RBV", read_only=True)
    num_frames_chunks = _rw(0, "NumFramesChunks", dtype=StrictLong)
    num_frames_chunks_rbv = _ro(0, "NumFramesChunks_RBV")
    chunk_size_auto = _rw("No", "ChunkSizeAuto", dtype=_ENUM, enum_strings=_NO_YES)
    chunk_size_auto_rbv = _ro("No", "ChunkSizeAuto_RBV", dtype=_ENUM, enum_strings=_NO_YES)
    lazy_open = _rw("No", "LazyOpen", dtype=_ENUM, enum_strings=_NO_YES)
    lazy_open_rbv = _ro("No", "LazyOpen_RBV", dtype=_ENUM, enum_strings=_NO_YES)
    write_message = _text("", "WriteMessage", read_only=True)

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._path: Path | None = None
        self._done: asyncio.Event | None = None

    @file_path.putter
    async def file_path(self, instance, value):
        """Take the directory (created where ``CreateDirectory`` asks) and say whether it is writable."""
        path = Path(value)
        if int(self.create_directory.value) != 0 and not path.exists():
            try:
                path.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                await self.write_message.write(f"cannot create {value}: {exc.strerror}")
        ok = path.is_dir() and os.access(path, os.W_OK)
        await self.file_path_exists_rbv.write("Yes" if ok else "No")
        await self.file_path_rbv.write(value)
        return value

    @capture.putter
    async def capture(self, instance, value):
        """Start a capture into the next file (completing when it ends), or stop it with ``Done``."""
        if value == "Done":
            await self._stop("stopped")
            return SkipWrite
        if self.capture_rbv.value == "Capture":
            raise ValueError("Capture: already capturing")
        name = c_format(self.file_template.value, self.file_path.value, self.file_name.value,
                        int(self.file_number.value))
        if self.file_path_exists_rbv.value != "Yes":
            await self.write_message.write(f"the directory {self.file_path.value!r} does not exist or is not writable")
            raise ValueError("Capture: FilePath does not exist or is not writable")
        self._path = Path(name)
        self._done = asyncio.Event()
        await self.full_file_name_rbv.write(name)
        await self.num_captured_rbv.write(0)
        await self.capture_rbv.write("Capture")
        await instance.write("Capture", verify_value=False)
        await self._done.wait()  # put-completion when the capture ends
        return SkipWrite

    async def _stop(self, why: str) -> None:
        if self.capture_rbv.value != "Capture":
            return
        if self.auto_increment.value == "Yes":
            await self.file_number.write(int(self.file_number.value) + 1)
        await self.capture_rbv.write("Done")
        await self.capture.write("Done", verify_value=False)
        await self.write_message.write(f"{why}: {self.num_captured_rbv.value} frames in {self._path}")
        if self._done is not None:
            self._done.set()

    async def process(self, frame: np.ndarray, uid: int, ts: float) -> None:
        """A frame from the driver: appended to the file while capturing (callbacks enabled)."""
        if self.enable_callbacks.value != "Enable":
            return
        await self.frame_done(frame.shape, uid, ts)
        await self.array_size0_plain.write(frame.shape[1])
        await self.array_size1_plain.write(frame.shape[0])
        if self.capture_rbv.value != "Capture" or self._path is None:
            return
        try:
            await asyncio.to_thread(_append, self._path, frame, uid, ts)
        except OSError as exc:
            await self.write_message.write(f"cannot write {self._path}: {exc}")
            await self._stop("write failed")
            return
        n = int(self.num_captured_rbv.value) + 1
        await self.num_captured_rbv.write(n, timestamp=ts)
        if 0 < int(self.num_capture.value) <= n:
            await self._stop("captured")


def c_format(template: str, path: str, name: str, number: int) -> str:
    """``template`` filled as areaDetector's C ``sprintf`` does: path, name, number for its % fields."""
    fields = re.findall(r"%[-+ #0]*\d*(?:\.\d+)?[sdi]", template)
    try:
        return template % (path, name, number)[:len(fields)]
    except (TypeError, ValueError):
        raise ValueError(f"FileTemplate {template!r}: expected %s (path), %s (name), then an integer field") from None


def _append(path: Path, frame: np.ndarray, uid: int, ts: float) -> None:
    import h5py
    # no file lock: a reader (the client, the run store) holding the file open must not stop the capture
    with h5py.File(path, "a", locking=False) as f:
        if "entry/data/data" not in f:
            f.create_dataset("entry/data/data", shape=(0, *frame.shape), maxshape=(None, *frame.shape),
                             dtype=frame.dtype, chunks=(1, *frame.shape))
            f.create_dataset("entry/instrument/NDAttributes/NDArrayUniqueId", shape=(0,), maxshape=(None,),
                             dtype=np.int32)
            f.create_dataset("entry/instrument/NDAttributes/NDArrayTimeStamp", shape=(0,), maxshape=(None,),
                             dtype=np.float64)
        d = f["entry/data/data"]
        d.resize(d.shape[0] + 1, axis=0)
        d[-1] = frame
        for key, v in (("NDArrayUniqueId", uid), ("NDArrayTimeStamp", ts)):
            a = f[f"entry/instrument/NDAttributes/{key}"]
            a.resize(a.shape[0] + 1, axis=0)
            a[-1] = v


class CamDriver(NDArrayBase):
    """``ADBase``: exposure, image mode, acquire, state; the frames come from the owner's ``take``."""

    acquire_time = _rw(1.0, "AcquireTime", dtype=StrictDouble, units="s", precision=3)
    acquire_time_rbv = _ro(1.0, "AcquireTime_RBV", units="s", precision=3)
    acquire_period = _rw(0.0, "AcquirePeriod", dtype=StrictDouble, units="s", precision=3)
    acquire_period_rbv = _ro(0.0, "AcquirePeriod_RBV", units="s", precision=3)
    num_images = _rw(1, "NumImages", dtype=StrictLong)
    num_images_rbv = _ro(1, "NumImages_RBV")
    num_images_counter_rbv = _ro(0, "NumImagesCounter_RBV")
    image_mode = _rw("Single", "ImageMode", dtype=_ENUM, enum_strings=("Single", "Multiple", "Continuous"))
    image_mode_rbv = _ro("Single", "ImageMode_RBV", dtype=_ENUM, enum_strings=("Single", "Multiple", "Continuous"))
    detector_state_rbv = _ro("Idle", "DetectorState_RBV", dtype=_ENUM, enum_strings=_STATES)
    acquire = _rw("Done", "Acquire", dtype=_ENUM, enum_strings=("Done", "Acquire"))
    acquire_rbv = _ro("Done", "Acquire_RBV", dtype=_ENUM, enum_strings=("Done", "Acquire"))
    wait_for_plugins = _rw("No", "WaitForPlugins", dtype=_ENUM, enum_strings=_NO_YES)
    shutter_control = _rw("Open", "ShutterControl", dtype=_ENUM, enum_strings=("Close", "Open"))
    shutter_control_rbv = _ro("Open", "ShutterControl_RBV", dtype=_ENUM, enum_strings=("Close", "Open"))
    status_message = _text("", "StatusMessage_RBV", read_only=True)
    manufacturer_rbv = _ro("bluesky-offsets", "Manufacturer_RBV", dtype=ChannelType.STRING)
    model_rbv = _ro("simulated focus-chamber camera", "Model_RBV", dtype=ChannelType.STRING)
    serial_number_rbv = _ro("0", "SerialNumber_RBV", dtype=ChannelType.STRING)
    sdk_version_rbv = _ro("", "SDKVersion_RBV", dtype=ChannelType.STRING)
    firmware_version_rbv = _ro("", "FirmwareVersion_RBV", dtype=ChannelType.STRING)
    max_size_x_rbv = _ro(0, "MaxSizeX_RBV")
    max_size_y_rbv = _ro(0, "MaxSizeY_RBV")

    def __init__(self, *args, take: Callable, shape: tuple[int, int], **kwargs):
        super().__init__(*args, **kwargs)
        self._take = take  # async (exposure, shutter_open) -> uint16 frame
        self._shape = shape
        self._task: asyncio.Task | None = None
        self._stop = asyncio.Event()

    @acquire.startup
    async def acquire(self, instance, async_lib):
        """Publish the sensor's size at startup."""
        # the frame's size is known before the first frame, as a configured sensor's is
        rows, cols = self._shape
        for pv, v in ((self.array_size_x_rbv, cols), (self.array_size_y_rbv, rows),
                      (self.max_size_x_rbv, cols), (self.max_size_y_rbv, rows)):
            await pv.write(v)

    @acquire_time.putter
    async def acquire_time(self, instance, value):
        """Take an exposure time within [1e-4, 1000] s and echo it to the readback."""
        if not 1e-4 <= value <= 1000:
            raise ValueError(f"AcquireTime must lie in [1e-4, 1000] s, got {value}")
        await self.acquire_time_rbv.write(value)
        return value

    @num_images.putter
    async def num_images(self, instance, value):
        """Take a frame count within [1, 100000] and echo it to the readback."""
        if not 1 <= value <= 100000:
            raise ValueError(f"NumImages must lie in [1, 100000], got {value}")
        await self.num_images_rbv.write(value)
        return value

    @acquire.putter
    async def acquire(self, instance, value):
        """Start an acquisition (completing when it ends), or stop the running one with ``Done``."""
        if value == "Done":
            self._stop.set()
            return SkipWrite
        if self._task is None or self._task.done():
            self._stop.clear()
            await self.acquire_rbv.write("Acquire")
            await self.detector_state_rbv.write("Acquire")
            await instance.write("Acquire", verify_value=False)
            self._task = asyncio.get_running_loop().create_task(self._acquire())
        await asyncio.shield(self._task)  # put-completion when the acquisition ends
        return SkipWrite

    async def _acquire(self) -> None:
        mode = self.image_mode.value
        n = 1 if mode == "Single" else int(self.num_images.value) if mode == "Multiple" else None
        k, state = 0, "Idle"
        await self.num_images_counter_rbv.write(0)
        try:
            while (n is None or k < n) and not self._stop.is_set():
                t0 = time.monotonic()
                exposure = float(self.acquire_time.value)
                take = asyncio.ensure_future(self._take(exposure, self.shutter_control.value == "Open"))
                stop = asyncio.ensure_future(self._stop.wait())
                await asyncio.wait({take, stop}, return_when=asyncio.FIRST_COMPLETED)
                stop.cancel()
                if not take.done():
                    take.cancel()
                    state = "Aborted"
                    break
                take.result()  # a frame that failed ends the acquisition in Error, not as taken
                k += 1
                await self.num_images_counter_rbv.write(k)
                rest = float(self.acquire_period.value) - (time.monotonic() - t0)
                if rest > 0 and (n is None or k < n):
                    try:
                        await asyncio.wait_for(self._stop.wait(), rest)
                    except asyncio.TimeoutError:
                        pass
            if self._stop.is_set() and state != "Aborted" and (n is None or k < n):
                state = "Aborted"
        except Exception as exc:  # noqa: BLE001 - the camera reports and stays up
            log.error("camera frame failed: %s", exc)
            await self.status_message.write("frame failed (see the IOC's log)")
            state = "Error"
        finally:
            await self.detector_state_rbv.write(state)
            await self.acquire_rbv.write("Done")
            await self.acquire.write("Done", verify_value=False)


class FocusCamera:
    """The chamber's camera: ``<prefix>cam1:`` and ``<prefix>HDF1:``.

    Its frames come from ``trace(n_rays)`` (a future of a :class:`Frame` with the rays' screen
    points) through the camera model.
    """

    def __init__(self, prefix: str, *, trace: Callable, geometry: CameraGeometry | None = None,
                 noise: CameraNoise | None = None, max_rays: int = 200_000,
                 rng: np.random.Generator | None = None):
        self.prefix = prefix
        self.geometry = geometry or CameraGeometry()
        self.noise = noise or CameraNoise()
        self._trace = trace
        self._max_rays = int(max_rays)
        self._rng = rng or np.random.default_rng()
        self._pattern = self.noise.pattern(self.geometry)
        self._uid = 0
        self.cam = CamDriver(prefix=prefix + "cam1:", take=self.take, shape=self.geometry.shape, name="camera.cam")
        self.hdf = HDF5Plugin(prefix=prefix + "HDF1:", name="camera.hdf")
        self.pvdb = {**self.cam.pvdb, **self.hdf.pvdb}

    def rays(self, exposure: float) -> int:
        """Photons (traced rays) the source sends in ``exposure`` seconds: a Poisson number, as light's is."""
        return int(min(self._max_rays, self._rng.poisson(self.noise.rays_per_second * exposure)))

    async def take(self, exposure: float, shutter_open: bool) -> np.ndarray:
        """One frame: traced, rendered, published, handed to the file plugin."""
        xy = np.empty((0, 2))
        n = self.rays(exposure)
        if shutter_open and n > 0:
            frame: Frame = await asyncio.wrap_future(self._trace(n))
            if frame.xy is None:
                raise RuntimeError("the backend gives no rays: the camera needs the twin backend")
            xy = frame.xy
        image = await asyncio.to_thread(self.noise.render, xy, self.geometry, self._pattern, exposure, self._rng)
        self._uid += 1
        ts = time.time()
        await self.cam.frame_done(image.shape, self._uid, ts)
        await self.hdf.process(image, self._uid, ts)
        return image
