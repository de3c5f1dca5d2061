"""Footprint backends of the simulated focus chamber.

A backend turns the *true* beamline state (a parameter vector in table
order, hidden offsets already applied) and a ray budget into one detector
frame.  It must not block the IOC's event loop: :meth:`submit` returns a
:class:`concurrent.futures.Future`.

* :class:`TwinBackend` traces the RAYX twin in a worker process (RAYX holds
  the GIL for the whole trace, so a thread would freeze the IOC), with a
  fresh random seed per frame: the finite ray budget is the measurement
  noise.  Its frames carry the footprint's profiles at the camera's resolution too.
* :class:`SurrogateBackend` evaluates a trained surrogate checkpoint
  (:mod:`bluesky_offsets.surrogate`) and draws the finite-ray noise itself
  (multinomial counts for the ray budget); it has no image, no camera-resolution
  profiles and cannot apply hidden physical effects.
* Any other backend plugs in through ``--backend module:factory``; the
  factory is called as ``factory(overrides=..., hist=...)`` and returns an
  object with the members of :class:`FootprintBackend`.
"""

from __future__ import annotations

import concurrent.futures as cf
import importlib
import multiprocessing
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from bluesky_offsets.twin import CAMERA, HistogramSpec


@dataclass
class Frame:
    """One focus-chamber frame; histograms are fractions of the source rays.

    ``profile_x``/``profile_y`` are the same footprint projected at the camera's own
    resolution (:data:`bluesky_offsets.twin.CAMERA`); None when the backend has no rays."""

    hist_x: np.ndarray
    hist_y: np.ndarray
    image: np.ndarray | None  # (bins_y, bins_x), None when the backend has no image
    n_hits: int
    n_rays: int
    seconds: float = 0.0
    profile_x: np.ndarray | None = None
    profile_y: np.ndarray | None = None

    @classmethod
    def dark(cls, hist: HistogramSpec, n_rays: int = 0) -> Frame:
        """A frame without rays: all zeros, never NaN."""
        return cls(np.zeros(hist.bins_x), np.zeros(hist.bins_y), np.zeros((hist.bins_y, hist.bins_x)),
                   0, int(n_rays), profile_x=np.zeros(CAMERA.bins_x), profile_y=np.zeros(CAMERA.bins_y))


@runtime_checkable
class FootprintBackend(Protocol):
    """What the focus chamber needs from a beamline model."""

    name: str
    hist: HistogramSpec

    def submit(self, values: np.ndarray, n_rays: int) -> cf.Future:
        """Start one frame at the true parameter vector ``values``; the future yields a :class:`Frame`."""

    def close(self) -> None:
        """Release workers."""


# --------------------------------------------------------------------------- #
# the RAYX twin in a worker process
# --------------------------------------------------------------------------- #
_worker_twin = None


def _twin_frame(values: np.ndarray, overrides: Mapping, n_rays: int, seed: int | None,
                hist: HistogramSpec) -> Frame:
    global _worker_twin
    t0 = time.perf_counter()
    if _worker_twin is None:
        from bluesky_offsets.twin import RayxEngine, Twin
        _worker_twin = Twin(RayxEngine(hist=hist), scheduler="inline")
    r = _worker_twin.trace(values, overrides=overrides, n_rays=n_rays, keep_rays=True, seed=seed)
    x, y = (r.rays[:, 0], r.rays[:, 1]) if r.rays is not None and len(r.rays) else (np.empty(0), np.empty(0))
    image = hist.image(x, y, n_rays)
    px, py = CAMERA.histograms(x, y, n_rays)
    return Frame(np.nan_to_num(r.hist_x), np.nan_to_num(r.hist_y), np.nan_to_num(image), int(r.n_hits),
                 int(n_rays), time.perf_counter() - t0, px, py)


class TwinBackend:
    """The RAYX digital twin, one worker process, a fresh seed for every frame.

    Parameters
    ----------
    overrides : mapping, optional
        RML-level hidden physical effects, e.g.
        ``{"ImagePlane": {"translationZerror": 5.0}}``.
    hist : HistogramSpec, optional
        Binning of the chamber (default: the paper's 50 x 50 bins).
    noise_seed : int, optional
        Seeds the frames' ray noise: the same acquisitions then give the same frames
        (default: fresh from the OS for every frame).
    """

    def __init__(self, overrides: Mapping | None = None, hist: HistogramSpec | None = None,
                 noise_seed: int | None = None):
        from importlib.metadata import PackageNotFoundError, version
        self.overrides = {k: dict(v) for k, v in (overrides or {}).items()}
        self.hist = hist or HistogramSpec()
        self._noise = None if noise_seed is None else np.random.default_rng(noise_seed)
        try:
            self.name = f"twin (rayx {version('rayx')})"
        except PackageNotFoundError:  # pragma: no cover
            self.name = "twin (rayx)"
        self._pool: cf.ProcessPoolExecutor | None = None

    def _executor(self) -> cf.ProcessPoolExecutor:
        if self._pool is None:
            # spawn: no copy of the IOC's event loop and sockets in the worker
            self._pool = cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
        return self._pool

    def submit(self, values: np.ndarray, n_rays: int) -> cf.Future:
        # fresh noise for every frame
        seed = int(self._noise.integers(2 ** 32)) if self._noise is not None else int.from_bytes(os.urandom(4), "little")
        try:
            return self._executor().submit(_twin_frame, np.asarray(values, float), self.overrides, int(n_rays),
                                           seed, self.hist)
        except cf.process.BrokenProcessPool:
            self._pool = None  # the worker died (crash in the tracer): start a new one
            return self._executor().submit(_twin_frame, np.asarray(values, float), self.overrides, int(n_rays),
                                           seed, self.hist)

    def reset(self) -> None:
        """Drop a broken worker; the next frame starts a fresh one."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


# --------------------------------------------------------------------------- #
# a trained surrogate
# --------------------------------------------------------------------------- #
def finite_ray_sample(p: np.ndarray, n_rays: int, rng: np.random.Generator) -> np.ndarray:
    """Counts of ``n_rays`` source rays over bins with expected fractions ``p`` (the rest
    misses the window): the noise a frame of that ray budget has."""
    p = np.clip(np.nan_to_num(np.asarray(p, float)), 0.0, None)
    total = p.sum()
    if total > 1.0:
        p = p / total
    return rng.multinomial(int(n_rays), np.append(p, max(0.0, 1.0 - p.sum())))[:-1]


class SurrogateBackend:
    """A trained surrogate checkpoint with finite-ray noise, in a worker thread.

    Parameters
    ----------
    path : str, optional
        Checkpoint (default: the one shipped with the package).
    overrides : mapping, optional
        Must be empty: the surrogate knows only the table's parameters.
    """

    def __init__(self, path: str | None = None, overrides: Mapping | None = None,
                 hist: HistogramSpec | None = None, noise_seed: int | None = None):
        if overrides:
            raise ValueError("the surrogate backend cannot apply hidden physical effects "
                             f"({sorted(overrides)}); use the twin backend")
        from pathlib import Path

        from bluesky_offsets.surrogate import SurrogateError, load
        self.hist = hist or HistogramSpec()
        try:
            self.model = load(path, hist=self.hist)
        except SurrogateError as exc:
            raise ValueError(str(exc)) from None
        self.name = f"surrogate ({Path(path).name if path else 'shipped'})"
        self._rng = np.random.default_rng(noise_seed)  # None: fresh from the OS
        self._pool = cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix="surrogate")

    def _frame(self, values: np.ndarray, n_rays: int) -> Frame:
        t0 = time.perf_counter()
        pred = np.asarray(self.model.predict(np.asarray(values, float)[None, :]))[0]
        px, py = pred[:self.hist.bins_x], pred[self.hist.bins_x:]
        cx, cy = finite_ray_sample(px, n_rays, self._rng), finite_ray_sample(py, n_rays, self._rng)
        n = max(int(n_rays), 1)
        return Frame(cx / n, cy / n, None, int(max(cx.sum(), cy.sum())), int(n_rays), time.perf_counter() - t0)

    def submit(self, values: np.ndarray, n_rays: int) -> cf.Future:
        return self._pool.submit(self._frame, values, n_rays)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


def make_backend(spec: str, *, overrides: Mapping | None = None, hist: HistogramSpec | None = None,
                 noise_seed: int | None = None) -> FootprintBackend:
    """Backend from its command-line name: ``twin``, ``surrogate[:checkpoint]`` or ``module:factory``
    (``noise_seed``: see :class:`TwinBackend`; a factory's backend draws its own noise)."""
    if spec == "twin":
        return TwinBackend(overrides=overrides, hist=hist, noise_seed=noise_seed)
    if spec == "surrogate" or spec.startswith("surrogate:"):
        return SurrogateBackend(spec.partition(":")[2] or None, overrides=overrides, hist=hist, noise_seed=noise_seed)
    if ":" not in spec:
        raise ValueError(f"unknown backend {spec!r}: use 'twin' or 'module:factory'")
    module, func = spec.split(":", 1)
    try:
        factory = getattr(importlib.import_module(module), func)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"backend {spec!r} cannot be loaded: {exc}") from None
    backend = factory(overrides=dict(overrides or {}), hist=hist or HistogramSpec())
    if not isinstance(backend, FootprintBackend):
        raise ValueError(f"backend {spec!r} lacks name/hist/submit/close")
    return backend
