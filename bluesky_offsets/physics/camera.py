"""The focus chamber as a camera: pixel geometry, frames to profiles, the gain from frames.

A camera images the chamber's screen on a grid of pixels: :class:`CameraGeometry` says where
each pixel lies on the screen (its size, the screen point at the sensor's centre, and how the
sensor is mounted: mirrored or turned).  :func:`screen_image` turns a frame as the camera
delivers it into screen orientation, :func:`profiles` sums the dark-subtracted counts of a
region of interest into x and y profiles in photons with their variances, and
:func:`photon_transfer` measures the gain (ADU per photon) and the read noise from repeated
frames at one setting and dark frames, as the photon-transfer method does: the variance of a
pixel grows with its mean by the gain.

Examples
--------
>>> import numpy as np
>>> geo = CameraGeometry(width=4, height=3, pixel_x_mm=1.0, pixel_y_mm=1.0)
>>> geo.photons(np.array([[0.2, 0.1], [1.5, -1.2]])).tolist()  # rows run along y, from its low end
[[0, 0, 0, 1], [0, 0, 1, 0], [0, 0, 0, 0]]
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.options import refuse_unknown
from bluesky_offsets.physics.traces import CAMERA, HistogramSpec


@dataclass(frozen=True, kw_only=True)
class CameraGeometry:
    """Where the camera's pixels lie on the screen.

    Parameters
    ----------
    width, height : int
        Pixels along the screen's x and y (before the mounting turns the sensor).
    pixel_x_mm, pixel_y_mm : float
        A pixel's size on the screen (mm); the optics' magnification included.
    center_x_mm, center_y_mm : float
        The screen point imaged on the sensor's centre (mm).
    flip_x, flip_y, transpose : bool
        The mounting: the frame's columns run against the screen's x, its rows against y, or
        rows and columns are swapped (a camera turned by 90 degrees), applied in this order.
    """

    width: int = CAMERA.bins_x
    height: int = CAMERA.bins_y
    pixel_x_mm: float = (CAMERA.range_x[1] - CAMERA.range_x[0]) / CAMERA.bins_x
    pixel_y_mm: float = (CAMERA.range_y[1] - CAMERA.range_y[0]) / CAMERA.bins_y
    center_x_mm: float = 0.5 * (CAMERA.range_x[0] + CAMERA.range_x[1])
    center_y_mm: float = 0.5 * (CAMERA.range_y[0] + CAMERA.range_y[1])
    flip_x: bool = False
    flip_y: bool = False
    transpose: bool = False

    def __post_init__(self):
        if not (self.width > 0 and self.height > 0 and self.pixel_x_mm > 0 and self.pixel_y_mm > 0):
            raise InputError("a camera needs positive pixel counts and pixel sizes")
        if not (np.isfinite(self.center_x_mm) and np.isfinite(self.center_y_mm)):
            raise InputError("the camera's centre must be finite")

    @classmethod
    def from_dict(cls, fields: Mapping) -> CameraGeometry:
        """From a mapping such as a PV map's ``camera`` table; unknown keys are refused."""
        refuse_unknown(cls, fields, "camera: unknown keys")
        return cls(**fields)

    @property
    def spec(self) -> HistogramSpec:
        """The screen window the pixels cover, as the twin's histogram binning."""
        hx, hy = 0.5 * self.width * self.pixel_x_mm, 0.5 * self.height * self.pixel_y_mm
        return HistogramSpec(self.width, (self.center_x_mm - hx, self.center_x_mm + hx),
                             self.height, (self.center_y_mm - hy, self.center_y_mm + hy))

    @property
    def shape(self) -> tuple[int, int]:
        """The frame's shape as the camera delivers it (rows, columns)."""
        return (self.width, self.height) if self.transpose else (self.height, self.width)

    def photons(self, xy: np.ndarray) -> np.ndarray:
        """Photons per pixel of the points ``xy`` (n, 2; mm on the screen), as the camera delivers them."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        return self.mount(self.spec.image(xy[:, 0], xy[:, 1], 1).astype(np.int64))

    def mount(self, screen: np.ndarray) -> np.ndarray:
        """A screen-oriented array (rows y, columns x) as this camera delivers it."""
        out = screen[:, ::-1] if self.flip_x else screen
        out = out[::-1, :] if self.flip_y else out
        return out.T if self.transpose else out

    def unmount(self, frame: np.ndarray) -> np.ndarray:
        """A frame as the camera delivers it, turned to the screen's orientation (rows y, columns x)."""
        frame = np.asarray(frame)
        if frame.shape[-2:] != self.shape:
            raise InputError(f"a frame of shape {frame.shape[-2:]} from a camera of shape {self.shape}")
        out = np.swapaxes(frame, -1, -2) if self.transpose else frame
        out = out[..., ::-1, :] if self.flip_y else out
        return out[..., :, ::-1] if self.flip_x else out


screen_image = CameraGeometry.unmount


@dataclass(frozen=True, kw_only=True)
class Roi:
    """A region of interest in screen pixels: columns ``x0:x1``, rows ``y0:y1`` (None: to the edge)."""

    x0: int = 0
    x1: int | None = None
    y0: int = 0
    y1: int | None = None

    def cut(self, screen: np.ndarray) -> np.ndarray:
        """The region of a screen image (or of a stack of them, on the last two axes)."""
        return screen[..., self.y0:self.y1, self.x0:self.x1]


@dataclass(frozen=True)
class Profiles:
    """The x and y profiles of a frame in photons per screen pixel column/row, with their variances.

    Also the part of the variances that is the camera's own (read noise, the dark's noise:
    ``floor_x``/``floor_y``).
    """

    x: np.ndarray
    y: np.ndarray
    var_x: np.ndarray
    var_y: np.ndarray
    floor_x: np.ndarray | None = None
    floor_y: np.ndarray | None = None

    @property
    def photons(self) -> float:
        """The photons in the frame: the x profile's sum."""
        return float(self.x.sum())

    def binned(self, geometry: CameraGeometry, spec: HistogramSpec) -> Profiles:
        """The profiles summed into the bins of ``spec`` (the paper's 50 x 50, or the camera's own).

        The bins' edges must fall on pixel edges of ``geometry``'s window.
        """
        own = geometry.spec
        ix = _groups(own.edges_x, spec.edges_x, "x")
        iy = _groups(own.edges_y, spec.edges_y, "y")
        fx, fy = ((None if f is None else np.add.reduceat(f, i)) for f, i in ((self.floor_x, ix), (self.floor_y, iy)))
        return Profiles(np.add.reduceat(self.x, ix), np.add.reduceat(self.y, iy),
                        np.add.reduceat(self.var_x, ix), np.add.reduceat(self.var_y, iy), fx, fy)


def _groups(pixel_edges: np.ndarray, bin_edges: np.ndarray, axis: str) -> np.ndarray:
    """The first pixel of each bin; the bins must tile the camera's window on pixel edges."""
    step = pixel_edges[1] - pixel_edges[0]
    k = np.clip(np.rint((bin_edges - pixel_edges[0]) / step).astype(int), 0, len(pixel_edges) - 1)
    if (k[0] != 0 or k[-1] != len(pixel_edges) - 1 or np.any(np.diff(k) <= 0)
            or not np.allclose(pixel_edges[k], bin_edges, atol=1e-6 * step)):
        raise InputError(f"the histogram's {axis} bins do not tile the camera's window on pixel edges")
    return k[:-1]


def profiles(frame: np.ndarray, geometry: CameraGeometry, *, dark: np.ndarray | float, gain: float,
             read_noise: float, roi: Roi | None = None, dark_frames: float | None = None,
             stray: float = 0.0) -> Profiles:
    """The dark-subtracted profiles of ``frame`` in photons, over the region of interest.

    The profiles span the whole screen window (zero outside the ROI).  A pixel holding ``n``
    photons reads ``gain * n + dark`` plus read noise, so a profile bin's variance is its photons
    (Poisson) plus the read noise of the pixels summed into it, in photons²; a dark that is the
    mean of ``dark_frames`` frames adds its own read noise.  ``stray`` (ADU per pixel, the mean of
    the stray photons every pixel receives, :attr:`DarkFrame.events`) is subtracted as well, and
    its photons' Poisson noise joins the floor.  For the sum of ``k`` frames pass ``k * dark``,
    ``sqrt(k) * read_noise``, ``dark_frames / k`` (the dark's noise is in each alike) and ``k * stray``.
    """
    if not gain > 0:
        raise InputError(f"the gain must be positive, got {gain}")
    if not stray >= 0:
        raise InputError(f"the stray light must be >= 0, got {stray}")
    signal = (screen_image(geometry, np.asarray(frame, float) - dark) - stray) / gain
    mask = np.zeros(signal.shape, bool)
    (roi or Roi()).cut(mask)[...] = True
    inside = np.where(mask, signal, 0.0)
    px, py = inside.sum(axis=0), inside.sum(axis=1)
    per_pixel = (read_noise / gain) ** 2 * (1.0 + (1.0 / dark_frames if dark_frames else 0.0)) + stray / gain
    fx, fy = per_pixel * mask.sum(axis=0), per_pixel * mask.sum(axis=1)
    return Profiles(px, py, np.clip(px, 0.0, None) + fx, np.clip(py, 0.0, None) + fy, fx, fy)


@dataclass(frozen=True)
class DarkFrame:
    """The dark level of each pixel (ADU) and the read noise (ADU) from two or more dark frames.

    Also the single-frame events left out of the level (``rejected``) and what they add to a pixel
    of a frame on average (``events``, ADU): stray photons and cosmic rays, which every frame
    receives alike.
    """

    level: np.ndarray
    read_noise: float
    frames: int
    rejected: int
    events: float = 0.0


def dark_frame(darks: np.ndarray, *, threshold: float = 8.0) -> DarkFrame:
    """The dark level and read noise from dark frames, single-frame events rejected.

    A stray photon or a cosmic ray in one dark frame adds ``gain`` ADU (tens of read-noise σ) to one
    pixel: averaged into the dark it is subtracted from every frame after, a column of negative
    photons.  A value more than ``threshold`` robust σ (the frame's median absolute deviation, the
    fixed pattern included) above its frame's median is such an event when another frame's value of
    the same pixel is not; it is left out of that pixel's mean and of the read noise.  A pixel
    bright in every frame is the fixed pattern (a hot pixel) and is kept.  The events' excess over
    the level, per pixel and frame, is :attr:`DarkFrame.events`: the light frames hold such events
    too, at the same rate per second, and :func:`profiles` subtracts their mean (``stray``).
    """
    d = np.asarray(darks, float)
    if d.ndim < 2 or len(d) < 2:
        raise InputError("dark frames: two or more frames of one camera")
    flat = d.reshape(len(d), -1)
    med = np.median(flat, axis=1, keepdims=True)
    mad = np.median(np.abs(flat - med), axis=1, keepdims=True)
    event = flat > med + threshold * np.maximum(1.4826 * mad, 0.5)
    event &= ~event.all(axis=0)
    keep = ~event
    n = keep.sum(axis=0)
    level = np.where(keep, flat, 0.0).sum(axis=0) / n
    # the read noise from pixels with every frame kept: the unbiased variance over frames
    whole = n == len(d)
    var = flat[:, whole].var(axis=0, ddof=1).mean() if whole.any() else 0.0
    events = float(np.where(event, flat - level, 0.0).sum() / flat.size)
    return DarkFrame(level.reshape(d.shape[1:]), float(np.sqrt(var)), len(d), int(event.sum()), events)


@dataclass(frozen=True)
class PhotonTransfer:
    """The gain (ADU per photon) and read noise (ADU) measured from frames, with the gain's σ."""

    gain: float
    gain_sigma: float
    read_noise: float
    pixels: int


def photon_transfer(frames: np.ndarray, darks: np.ndarray | DarkFrame, *,
                    saturation: float = 65535.0) -> PhotonTransfer:
    """The gain from four or more frames at one setting and two or more dark frames, by photon transfer.

    Over repeated frames a pixel of mean level ``m`` (ADU above dark) varies by
    ``gain * m + read^2``; the dark frames' variance is ``read^2``.  Summed over every pixel (a
    fixed set: pixels picked by their measured level would bias the slope where the read noise
    is comparable), the gain is ``sum(var_light - var_dark) / sum(m)``.  A pixel's variance and
    mean from the same frames covary (Poisson light: by the third cumulant), which biases the
    ratio low where few pixels hold the light; so the frames are split in two halves and each
    half's variance is divided by the other half's levels.  The σ is the first-order one, the
    pixels independent.  A bright spot holds few pixels: more frames, not brighter ones, shrink it.
    ``darks`` are the dark frames, or the :class:`DarkFrame` already made of them.
    """
    f = np.asarray(frames, float).reshape(len(frames), -1)
    dark = darks if isinstance(darks, DarkFrame) else dark_frame(darks)
    if len(f) < 4 or dark.frames < 2 or f.shape[1] != dark.level.size:
        raise InputError("photon transfer: four or more frames and two or more dark frames of one camera")
    if f.max() >= saturation:
        raise InputError("photon transfer: a frame is saturated (a shorter exposure or less light)")
    dark_mean, read2 = dark.level.reshape(-1), dark.read_noise ** 2
    halves = f[: len(f) // 2], f[len(f) // 2:]
    excess = [h.var(axis=0, ddof=1) - read2 for h in halves]
    level = [h.mean(axis=0) - dark_mean for h in halves]
    sums = [lv.sum() for lv in level]
    if min(sums) <= 0:
        raise InputError("photon transfer: no light above the dark frames")
    ratios = [excess[0].sum() / sums[1], excess[1].sum() / sums[0]]
    gain = float(np.mean(ratios))
    influence = 0.5 * ((excess[0] - ratios[0] * level[1]) / sums[1] + (excess[1] - ratios[1] * level[0]) / sums[0])
    gain_sigma = float(np.sqrt(np.sum(influence ** 2)))
    lit = int((0.5 * (level[0] + level[1]) > 3.0 * np.sqrt(read2)).sum())
    return PhotonTransfer(gain, gain_sigma, float(np.sqrt(read2)), lit)


@dataclass(frozen=True, kw_only=True)
class CameraCalibration:
    """What turns a camera's frames into the twin's histograms.

    Where its pixels lie, its dark frame, gain and read noise (:func:`photon_transfer`), the stray
    light every pixel receives (ADU per second: the dark frames' events, :class:`DarkFrame`), the
    region of interest, and the photons the source sends per second of exposure (the flux at the screen,
    measured once: the histograms are fractions of it, as the twin's are fractions of its source
    rays).

    Examples
    --------
    >>> cal = CameraCalibration(gain=12.0, read_noise=2.0, dark=100.0, photons_per_second=5000.0)
    >>> cal.source_photons(0.5)
    2500
    """

    geometry: CameraGeometry = dataclasses.field(default_factory=CameraGeometry)
    gain: float
    read_noise: float
    dark: np.ndarray | float
    dark_frames: float | None = None
    photons_per_second: float
    roi: Roi | None = None
    gain_sigma: float | None = None
    stray_per_second: float = 0.0

    def __post_init__(self):
        if not (self.gain > 0 and self.read_noise >= 0 and self.photons_per_second > 0
                and self.stray_per_second >= 0):
            raise InputError("a camera calibration needs gain > 0, read noise >= 0, photons per second > 0 "
                             "and stray light >= 0")

    def source_photons(self, exposure: float) -> int:
        """Photons the source sends in ``exposure`` seconds: the histograms' denominator."""
        return max(int(round(self.photons_per_second * exposure)), 1)

    def reduce(self, frame: np.ndarray, exposure: float, hist: HistogramSpec) -> dict:
        """One frame as the twin's quantities, fractions of the source photons with their noise floors.

        ``hist_x``/``hist_y`` (binned as ``hist``) and ``profile_x``/``profile_y`` (the camera's
        pixels) as fractions of the source photons, their camera-noise floors in fraction²
        (``floor_hx``, ``floor_hy``, ``floor_px``, ``floor_py``), ``photons`` on the screen and
        ``n_source``.
        """
        p = profiles(frame, self.geometry, dark=self.dark, gain=self.gain, read_noise=self.read_noise,
                     roi=self.roi, dark_frames=self.dark_frames, stray=self.stray_per_second * exposure)
        b = p.binned(self.geometry, hist)
        # profiles() computes the floors; binning keeps them
        assert p.floor_x is not None and p.floor_y is not None and b.floor_x is not None and b.floor_y is not None
        n = self.source_photons(exposure)
        return {"hist_x": b.x / n, "hist_y": b.y / n, "profile_x": p.x / n, "profile_y": p.y / n,
                "floor_hx": b.floor_x / n**2, "floor_hy": b.floor_y / n**2,
                "floor_px": p.floor_x / n**2, "floor_py": p.floor_y / n**2,
                "photons": p.photons, "n_source": n}
