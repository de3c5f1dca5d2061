"""Footprint backends of the simulated focus chamber.

A backend turns the *true* beamline state (a parameter vector in table
order, hidden offsets already applied) and a ray budget into one detector
frame.  It must not block the IOC's event loop: :meth:`submit` returns a
:class:`concurrent.futures.Future`.

* :class:`TwinBackend` traces the RAYX twin in a worker process (RAYX holds
  the GIL for the whole trace, so a thread would freeze the IOC), with a
  fresh random seed per frame: the finite ray budget is the measurement
  noise.  Its frames carry the footprint's profiles at the camera's resolution too.
  An abort stops the worker; a state no beamline can be in (a slit driven past
  closed) is traced closed, so that the truth shows only as light or no light.
* :class:`SurrogateBackend` evaluates a trained surrogate checkpoint
  (:mod:`bluesky_offsets.surrogate.network`) and draws the finite-ray noise itself
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
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from bluesky_offsets.physics.twin import CAMERA, HistogramSpec


@dataclass
class Frame:
    """One focus-chamber frame; histograms are fractions of the source rays.

    ``profile_x``/``profile_y`` are the same footprint projected at the camera's own
    resolution (:data:`bluesky_offsets.physics.twin.CAMERA`) and ``xy`` the rays' screen points;
    None when the backend has no rays.
    """

    hist_x: np.ndarray
    hist_y: np.ndarray
    image: np.ndarray | None  # (bins_y, bins_x), None when the backend has no image
    n_hits: int
    n_rays: int
    seconds: float = 0.0
    profile_x: np.ndarray | None = None
    profile_y: np.ndarray | None = None
    xy: np.ndarray | None = None  # (n_hits, 2) screen points of the rays (mm), for a camera

    @classmethod
    def dark(cls, hist: HistogramSpec, n_rays: int = 0) -> Frame:
        """A frame without rays: all zeros, never NaN."""
        return cls(np.zeros(hist.bins_x), np.zeros(hist.bins_y), np.zeros((hist.bins_y, hist.bins_x)),
                   0, int(n_rays), profile_x=np.zeros(CAMERA.bins_x), profile_y=np.zeros(CAMERA.bins_y),
                   xy=np.empty((0, 2), np.float32))


@runtime_checkable
class FootprintBackend(Protocol):
    """What the focus chamber needs from a beamline model."""

    name: str
    hist: HistogramSpec

    def submit(self, values: np.ndarray, n_rays: int) -> cf.Future:
        """Start one frame at the true parameter vector ``values``; the future yields a :class:`Frame`.

        A backend that can move the screen also takes ``screen=`` (the chamber stage's x, y, z in
        mm); the IOC passes it only while the stage stands away from 0.
        """

    def close(self) -> None:
        """Release workers."""


# --------------------------------------------------------------------------- #
# the RAYX twin in a worker process
# --------------------------------------------------------------------------- #


class FrameAborted(Exception):
    """The frame was aborted: its worker was stopped mid-trace."""


def physical_state(values: np.ndarray, table=None) -> tuple[np.ndarray, str | None]:
    """The state a real beamline would be in: a slit driven past closed is closed.

    Returns the state to trace and, when it had to be changed or cannot be traced at all,
    a note for the simulation's operator (never for its clients: it names true values).
    """
    from bluesky_offsets.physics.metrixs import OPENING_FIELDS, check_physical
    from bluesky_offsets.physics.parameters import METRIXS
    table = table or METRIXS
    v = np.array(values, float)
    note = None
    for i, p in enumerate(table):
        if p.field in OPENING_FIELDS and v[i] < 0:
            note = f"{p.name} = {v[i]:.6g} {p.unit}: closed (traced at 0)"
            v[i] = 0.0
    try:
        check_physical(v, table)
    except ValueError as exc:
        return v, f"impossible state ({exc}): dark frame"
    return v, note


_worker_twins: dict = {}


def _worker_twin_for(hist: HistogramSpec, beamline: str | None):
    """The worker's twin (one per beamline description; None: METRIXS), its table, its camera window."""
    key = (beamline, hist)
    if key not in _worker_twins:
        from bluesky_offsets.physics.twin import RayxEngine, Twin
        if beamline is None:
            from bluesky_offsets.physics.parameters import METRIXS
            _worker_twins[key] = (Twin(RayxEngine(hist=hist), scheduler="inline"), METRIXS, CAMERA)
        else:
            from bluesky_offsets.physics.beamline import RmlEngine, load_beamline
            bl = load_beamline(beamline)
            _worker_twins[key] = (Twin(RmlEngine(bl, hist), scheduler="inline"), bl.table, bl.detector.camera)
    return _worker_twins[key]


def _twin_frame(values: np.ndarray, overrides: Mapping, n_rays: int, seed: int | None,
                hist: HistogramSpec, beamline: str | None = None) -> tuple[Frame, str | None]:
    t0 = time.perf_counter()
    twin, table, camera = _worker_twin_for(hist, beamline)
    values, note = physical_state(values, table)
    if note is not None and note.startswith("impossible"):
        # no beamline can be in this state: no light, as in any dark frame
        return Frame.dark(hist, n_rays), note
    r = twin.trace(values, overrides=overrides, n_rays=n_rays, keep_rays=True, seed=seed)
    x, y = (r.rays[:, 0], r.rays[:, 1]) if r.rays is not None and len(r.rays) else (np.empty(0), np.empty(0))
    image = hist.image(x, y, n_rays)
    px, py = camera.histograms(x, y, n_rays)
    return Frame(np.nan_to_num(r.hist_x), np.nan_to_num(r.hist_y), np.nan_to_num(image), int(r.n_hits),
                 int(n_rays), time.perf_counter() - t0, px, py, np.column_stack([x, y]).astype(np.float32)), note


def _worker_loop(conn) -> None:
    """A frame worker: jobs in, ``("ok", (frame, note))`` or ``("error", text)`` out."""
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the IOC stops its workers itself
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        try:
            conn.send(("ok", _twin_frame(*job)))
        except Exception as exc:  # reported to the IOC, which decides what its clients see
            conn.send(("error", f"{type(exc).__name__}: {exc}"))


class WorkerDied(RuntimeError):
    """The frame's worker process ended during the trace (RAYX crashed)."""


class _Worker:
    """One frame-worker process; :meth:`kill` stops a trace at once."""

    def __init__(self, ctx, warm_job=None):
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker_loop, args=(child,), daemon=True,
                                name="metrixs-frame-worker")
        self.proc.start()
        child.close()
        self.lock = threading.Lock()
        self.killed = False
        self._warming = warm_job is not None
        if warm_job is not None:  # imports and a first trace start now; the first job collects them
            self.conn.send(warm_job)

    def run(self, job):
        with self.lock:
            if self.killed:
                raise FrameAborted()
            try:
                if self._warming:
                    self._warming = False
                    self.conn.recv()
                self.conn.send(job)
                return self.conn.recv()
            except (EOFError, OSError, BrokenPipeError):
                if self.killed:
                    raise FrameAborted() from None
                raise WorkerDied("the frame worker died") from None

    def alive(self) -> bool:
        return not self.killed and self.proc.is_alive()

    def kill(self) -> None:
        self.killed = True
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join(5)
        self.conn.close()


_TRACE_TRIES = 5  # a frame whose worker died is traced again, on a fresh worker, up to this often in all
_WARM_RAYS = 20_000  # a worker's first trace: rayx 0.4.5 can overrun its buffers when a later trace outgrows the first


class TwinBackend:
    """The RAYX digital twin in a worker process, a fresh seed for every frame.

    An abort stops the worker at once and the next frame goes to a spare worker that is
    already warm; a worker that died is replaced before the next frame.  A frame whose worker
    died or failed (rayx 0.4.5 overruns its event buffer on rays caught inside a toroid, which
    hit it more often than its event limit) is traced again on a fresh worker with its noise
    drawn anew, up to five times in all; the operator's log says so.  RAYX's input files
    live only for their import (:func:`bluesky_offsets.physics.rayx_calls.import_rml`).

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
                 noise_seed: int | None = None, beamline: str | None = None):
        from importlib.metadata import PackageNotFoundError, version
        self.beamline = None if beamline is None else str(beamline)
        self.overrides = {k: dict(v) for k, v in (overrides or {}).items()}
        self.hist = hist or HistogramSpec()
        self._noise = None if noise_seed is None else np.random.default_rng(noise_seed)
        try:
            self.name = f"twin (rayx {version('rayx')})"
        except PackageNotFoundError:  # pragma: no cover
            self.name = "twin (rayx)"
        # spawn: no copy of the IOC's event loop and sockets in the workers
        self._ctx = multiprocessing.get_context("spawn")
        self._active: _Worker | None = None
        self._spare: _Worker | None = None
        self._swap = threading.Lock()
        self._frames = cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix="frames")
        self.notes: list[str] = []  # for the operator's log only (they name true values)

    def _new_worker(self) -> _Worker:
        return _Worker(self._ctx, (self._warm_state(), self.overrides, _WARM_RAYS, 0, self.hist, self.beamline))

    def _warm_state(self) -> np.ndarray:
        from bluesky_offsets.physics.parameters import METRIXS
        if self.beamline is None:
            return METRIXS.reference.copy()
        from bluesky_offsets.physics.beamline import load_beamline
        return load_beamline(self.beamline).table.reference.copy()

    def _worker(self) -> _Worker:
        with self._swap:
            if self._active is None or not self._active.alive():
                if self._active is not None:
                    self._active.kill()
                spare, self._spare = self._spare, None
                self._active = spare if spare is not None and spare.alive() else self._new_worker()
            if self._spare is None or not self._spare.alive():
                self._spare = self._new_worker()
            return self._active

    def _frame(self, values: np.ndarray, n_rays: int, seed: int, screen=None) -> Frame:
        worker = self._worker()
        overrides: Mapping = self.overrides
        if screen is not None and np.any(screen):  # the stage's position plus the chamber's hidden displacement
            from bluesky_offsets.physics.screen import per_frame_overrides
            frames = per_frame_overrides(overrides, np.asarray(screen, float)[None], 1)
            assert isinstance(frames, Sequence)  # the stage moved: one mapping per frame
            overrides = frames[0]
        frame, note = self._trace(worker, np.asarray(values, float), overrides, int(n_rays), seed)
        if note:
            self.notes.append(note)
        return frame

    def _trace(self, worker: _Worker, values: np.ndarray, overrides: Mapping, n_rays: int, seed: int):
        """``(frame, note)`` from ``worker``; where it dies or fails, from a fresh one with other noise."""
        for attempt in range(1, _TRACE_TRIES + 1):
            last = attempt == _TRACE_TRIES
            try:
                status, payload = worker.run((values, overrides, n_rays, seed, self.hist, self.beamline))
            except WorkerDied:
                if last:
                    raise
                status, payload = "died", "the frame worker died"
            if status == "ok" or last:
                break
            # rayx 0.4.5 overruns its event buffer on rays caught inside a toroid
            self.notes.append(f"rayx failed tracing a frame (seed {seed}, {n_rays} rays: {payload}); traced again")
            seed = int(np.random.SeedSequence([seed, attempt]).generate_state(1)[0])
            worker.kill()
            worker = self._worker()
        if status != "ok":
            raise RuntimeError(payload)
        return payload

    def submit(self, values: np.ndarray, n_rays: int, screen=None) -> cf.Future:
        """One frame at the true ``values``, the chamber's stage at ``screen`` (x, y, z mm; None: 0)."""
        # fresh noise for every frame
        seed = int(self._noise.integers(2 ** 32)) if self._noise is not None else int.from_bytes(os.urandom(4), "little")
        return self._frames.submit(self._frame, np.asarray(values, float), int(n_rays), seed, screen)

    def abort(self) -> None:
        """Stop the frame being traced now (its future raises :class:`FrameAborted`)."""
        with self._swap:
            if self._active is not None:
                self._active.kill()
                self._active = None

    def reset(self) -> None:
        """Drop the worker; the next frame starts on the spare."""
        self.abort()

    def close(self) -> None:
        """Kill the active and the spare worker and stop taking frames."""
        with self._swap:
            for w in (self._active, self._spare):
                if w is not None:
                    w.kill()
            self._active = self._spare = None
        self._frames.shutdown(wait=False, cancel_futures=True)


# --------------------------------------------------------------------------- #
# a trained surrogate
# --------------------------------------------------------------------------- #
def finite_ray_sample(p: np.ndarray, n_rays: int, rng: np.random.Generator) -> np.ndarray:
    """Counts of ``n_rays`` source rays over bins with expected fractions ``p`` (the rest misses the window).

    The draw has the noise a frame of that ray budget has.
    """
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
        Hidden effects as RML overrides: only the focus chamber's translation (the
        ``chamber_x``/``_y``/``_z`` effects), and only for a checkpoint with the chamber's
        inputs; the surrogate knows nothing else.
    """

    def __init__(self, path: str | None = None, overrides: Mapping | None = None,
                 hist: HistogramSpec | None = None, noise_seed: int | None = None):
        from pathlib import Path

        from bluesky_offsets.physics.metrixs import IMAGE_PLANE
        from bluesky_offsets.surrogate.network import SurrogateError, load
        fields = dict((overrides or {}).get(IMAGE_PLANE, {}))
        self.chamber = np.array([float(fields.pop(f"translation{a}error", 0.0)) for a in "XYZ"])
        rest = sorted(k for k in (overrides or {}) if k != IMAGE_PLANE) + [f"{IMAGE_PLANE}.{k}" for k in fields]
        if rest:
            raise ValueError("the surrogate backend cannot apply hidden physical effects other than the "
                             f"chamber's translation ({rest}); use the twin backend")
        self.hist = hist or HistogramSpec()
        try:
            self.model = load(path, hist=self.hist)
        except SurrogateError as exc:
            raise ValueError(str(exc)) from None
        if self.chamber.any() and not self.model.chamber:
            raise ValueError("this surrogate checkpoint was trained without the focus chamber's inputs: it "
                             "cannot move the chamber; use one trained on a store drawn with --chamber, or the "
                             "twin backend")
        self.name = f"surrogate ({Path(path).name if path else 'shipped'})"
        self._rng = np.random.default_rng(noise_seed)  # None: fresh from the OS
        self._pool = cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix="surrogate")

    def _frame(self, values: np.ndarray, n_rays: int, screen=None) -> Frame:
        t0 = time.perf_counter()
        chamber = self.chamber + (0.0 if screen is None else np.asarray(screen, float))
        if chamber.any() and not self.model.chamber:
            raise ValueError("this surrogate checkpoint was trained without the focus chamber's inputs: it "
                             "cannot move the screen")
        pred = np.asarray(self.model.predict(np.asarray(values, float)[None, :],
                                             chamber=chamber if self.model.chamber else None))[0]
        px, py = pred[:self.hist.bins_x], pred[self.hist.bins_x:]
        cx, cy = finite_ray_sample(px, n_rays, self._rng), finite_ray_sample(py, n_rays, self._rng)
        n = max(int(n_rays), 1)
        return Frame(cx / n, cy / n, None, int(max(cx.sum(), cy.sum())), int(n_rays), time.perf_counter() - t0)

    def submit(self, values: np.ndarray, n_rays: int, screen=None) -> cf.Future:
        """One frame at the true ``values``, the screen moved by ``screen`` (x, y, z mm; None: 0); a future."""
        return self._pool.submit(self._frame, values, n_rays, screen)

    def close(self) -> None:
        """Finish the frame in progress, drop the queued ones and stop the worker thread."""
        self._pool.shutdown(wait=True, cancel_futures=True)


def make_backend(spec: str, *, overrides: Mapping | None = None, hist: HistogramSpec | None = None,
                 noise_seed: int | None = None, beamline: str | None = None) -> FootprintBackend:
    """Backend from its command-line name: ``twin``, ``surrogate[:checkpoint]`` or ``module:factory``.

    ``noise_seed``: see :class:`TwinBackend` (a factory's backend draws its own noise);
    ``beamline``: a description file the twin traces instead of METRIXS.
    """
    if spec == "twin":
        return TwinBackend(overrides=overrides, hist=hist, noise_seed=noise_seed, beamline=beamline)
    if beamline is not None:
        raise ValueError(f"backend {spec!r} serves METRIXS only; a described beamline needs the twin backend")
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
