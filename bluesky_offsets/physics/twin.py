"""The digital twin: parameter vectors -> RAYX -> focus-chamber histograms.

Layers, from the inside out:

* :func:`footprint` picks the rays that really reached the focus chamber
  from RAYX's non-sequential event list.
* :class:`HistogramSpec` bins a footprint into the x/y histograms of the paper
  (fraction of source rays per bin).
* :class:`TraceEngine` is the small engine interface (request -> histograms,
  hit count, optional rays).  :class:`RayxEngine` is RAYX on the CPU; other
  engines (RAY-UI at the facility, RAYX on a GPU, a differentiable tracer)
  implement the same two members.
* :class:`Twin` runs batches of requests through an engine on Dask (a
  LocalCluster by default, or any scheduler address), in input order, with a
  progress bar, reporting failed simulations with their parameters.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.physics.rayx_calls import check_emitted, ensure_random_stream, fix_seed, import_rml
from bluesky_offsets.physics.traces import (  # noqa: F401 - the twin's types, here where users look
    CAMERA,
    HistogramSpec,
    TraceEngine,
    TraceFailed,
    TraceRequest,
    TraceResult,
    _hist1d,
)

log = logging.getLogger(__name__)

EMITTED, HIT_ELEMENT = 1, 2  # rayx.EventType values

# How the twin places a misaligned source: "physical" since RAYX is handed the inverse source
# frame (rml.rayx_source_frame).  Data and models made before record nothing and were traced
# "mirrored": a source shifted by +t emitted from -t (the four U41 parameters' signs flipped).
SOURCE_FRAME = "physical"


# --------------------------------------------------------------------------- #
# footprint extraction
# --------------------------------------------------------------------------- #
def footprint(rays, n_objects: int, n_source_rays: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays that reached the last object (the image plane) the way light does.

    RAYX traces non-sequentially: a ray that misses an element flies on and may
    still land on the (infinite, transparent) image plane, and a ray may cross
    the image plane before it reaches the last mirror.  A path counts only if
    it is emitted by the source (object 0), then hits every element 1 .. n-2
    in order, once each, with no absorption or error event, and crosses the
    image plane (object n-1) after the last element; its last image-plane
    event is the footprint.

    Returns
    -------
    x, y : ndarray
        Image-plane coordinates in mm (RAY-UI's X, Y = RAYX's ``position_x``,
        ``position_z``).
    path_ids : ndarray
        Source ray number of each returned ray, ascending.
    """
    pid = np.asarray(rays.path_id)
    if pid.size == 0:
        return np.empty(0), np.empty(0), np.empty(0, dtype=np.int64)
    peid = np.asarray(rays.path_event_id)
    order = np.lexsort((peid, pid))
    pid, peid = pid[order], peid[order]
    oid = np.asarray(rays.object_id)[order]
    ev = np.asarray(rays.event_type)[order]
    n_paths = max(int(n_source_rays), int(pid[-1]) + 1)
    paths = np.arange(n_paths)
    ip = n_objects - 1

    on_ip = oid == ip
    # elements (and the source): k-th event of a path must be object k
    pid_el, oid_el, ev_el, peid_el = pid[~on_ip], oid[~on_ip], ev[~on_ip], peid[~on_ip]
    rank = np.arange(pid_el.size) - np.searchsorted(pid_el, pid_el, side="left")
    bad = (oid_el != rank) | (ev_el != np.where(rank == 0, EMITTED, HIT_ELEMENT))
    n_el = np.bincount(pid_el, minlength=n_paths)
    n_bad = np.bincount(pid_el[bad], minlength=n_paths)
    last_el = np.searchsorted(pid_el, paths, side="right") - 1
    last_el_peid = np.where(n_el > 0, peid_el[np.clip(last_el, 0, None)], -1)

    # image plane: the path's last crossing, after its last element
    pid_ip, peid_ip, ev_ip = pid[on_ip], peid[on_ip], ev[on_ip]
    n_ip = np.bincount(pid_ip, minlength=n_paths)
    last_ip = np.clip(np.searchsorted(pid_ip, paths, side="right") - 1, 0, None)
    has_ip = n_ip > 0
    if pid_ip.size:
        after = peid_ip[last_ip] > last_el_peid
        ip_ok = ev_ip[last_ip] == HIT_ELEMENT
    else:
        after = ip_ok = np.zeros(n_paths, dtype=bool)
    good = (n_bad == 0) & (n_el == n_objects - 1) & has_ip & after & ip_ok
    sel = last_ip[good]
    x = np.asarray(rays.position_x)[order][on_ip][sel]
    y = np.asarray(rays.position_z)[order][on_ip][sel]
    return x, y, paths[good]


class RayxEngine:
    """RAYX (HZB's ray tracer) on the CPU, driving the METRIXS geometry."""

    source_label = "the METRIXS source"  # names the source where RAYX cannot trace it

    def __init__(self, table: ParameterTable = METRIXS, hist: HistogramSpec | None = None):
        self.table = table
        self.hist = hist or HistogramSpec()

    @property
    def version(self) -> str:
        """Engine name and version (``rayx <version>``), recorded with every dataset and run."""
        from importlib.metadata import PackageNotFoundError, version
        try:
            return f"rayx {version('rayx')}"
        except PackageNotFoundError:  # pragma: no cover - reported, not fatal
            return "rayx (unknown version)"

    def build(self, request: TraceRequest, n_rays: int):
        """The RML beamline of ``request`` with ``n_rays`` source rays, refused where unphysical."""
        from bluesky_offsets.physics.metrixs import build_beamline, check_physical
        check_physical(request.values, self.table)
        return build_beamline(request.values, overrides=request.overrides, table=self.table, n_rays=n_rays)

    def trace(self, request: TraceRequest, n_rays: int, keep_rays: bool = False) -> TraceResult:
        """Trace one beamline state with ``n_rays`` source rays in RAYX (the rays kept with ``keep_rays``)."""
        values, x, y, _ = self.hits(request, n_rays)
        hx, hy = self.hist.histograms(x, y, n_rays)
        return TraceResult(hx, hy, int(x.size), int(n_rays), values,
                           np.column_stack([x, y]) if keep_rays else None)

    def hits(self, request: TraceRequest, n_rays: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """RAYX's trace of ``request``: the validated values, the screen's hits ``x``, ``y`` and their rays' numbers."""
        values = self.table.validate(request.values)
        if n_rays < 1:
            raise InputError(f"n_rays must be positive, got {n_rays}")
        bl = import_rml(self.build(request, n_rays))
        if request.seed is None:
            ensure_random_stream()
        else:
            fix_seed(request.seed)
        rays = bl.trace()
        check_emitted(rays, self.source_label)
        return values, *footprint(rays, len(bl.sources) + len(bl.elements), n_rays)


# --------------------------------------------------------------------------- #
# batches on Dask
# --------------------------------------------------------------------------- #
def _trace_chunk(engine: TraceEngine, requests: Sequence[TraceRequest], n_rays: int,
                 keep_rays: bool) -> list[TraceResult]:
    many = getattr(engine, "trace_many", None)
    if many is not None and len(requests) > 1:
        try:  # a batched engine traces the chunk at once; on failure, row by row for the message
            return many(requests, n_rays, keep_rays)
        except Exception:
            pass
    out = []
    for req in requests:
        try:
            out.append(engine.trace(req, n_rays, keep_rays))
        except Exception as exc:  # reported with its parameters by the caller
            out.append(_failed(engine, req, n_rays, f"{type(exc).__name__}: {exc}"))
    return out


def _failed(engine: TraceEngine, req: TraceRequest, n_rays: int, message: str) -> TraceResult:
    nan_x = np.full(engine.hist.bins_x, np.nan)
    nan_y = np.full(engine.hist.bins_y, np.nan)
    return TraceResult(nan_x, nan_y, 0, n_rays, np.asarray(req.values, dtype=float), None, message)


def _compact(values: np.ndarray) -> str:
    return np.array2string(np.asarray(values), precision=6, separator=",", max_line_width=10**6)


@dataclass
class BatchResult:
    """Results of a batch, in input order; failed rows hold NaN and an error message."""

    results: list[TraceResult]

    @property
    def hist_x(self) -> np.ndarray:
        """The x histograms stacked, (rows, bins_x)."""
        return np.stack([r.hist_x for r in self.results]) if self.results else np.empty((0, 0))

    @property
    def hist_y(self) -> np.ndarray:
        """The y histograms stacked, (rows, bins_y)."""
        return np.stack([r.hist_y for r in self.results]) if self.results else np.empty((0, 0))

    @property
    def n_hits(self) -> np.ndarray:
        """The rays on the screen per row."""
        return np.array([r.n_hits for r in self.results], dtype=np.int64)

    @property
    def ok(self) -> np.ndarray:
        """Per row, whether its trace succeeded."""
        return np.array([r.ok for r in self.results], dtype=bool)

    @property
    def failures(self) -> list[tuple[int, np.ndarray, str | None]]:
        """The failed rows as ``(index, values, error message)``."""
        return [(i, r.values, r.error) for i, r in enumerate(self.results) if not r.ok]

    def __len__(self) -> int:
        return len(self.results)

    def __getitem__(self, i: int) -> TraceResult:
        return self.results[i]


ENGINES = ("rayx", "torch")


def make_engine(engine: TraceEngine | str | None = None, **options) -> TraceEngine:
    """An engine by name (``"rayx"``, the reference, or ``"torch"``) or the engine given."""
    if engine is None or engine == "rayx":
        return RayxEngine(**options)
    if engine == "torch":
        from bluesky_offsets.physics.engine import TorchEngine
        return TorchEngine(**options)
    if isinstance(engine, str):
        raise InputError(f"unknown engine {engine!r}; known: {', '.join(ENGINES)}")
    return engine


# The LocalCluster's workers: one OpenMP thread
WORKER_ENV = {"OMP_NUM_THREADS": "1"}

# The LocalCluster's housekeeping, slower than Dask's defaults: its event loops' 20 ms tick, the
# workers' 10 ms stack sampler (the dashboard's profile), the nannies' 100 ms memory poll and the
# 0.5 s system monitor with disk counters: an idle cluster's CPU is the fits' loss
# (benchmarks/bench_cluster_idle.py).  What runs, and where, is unchanged; the dashboard still
# shows tasks and memory (no profile pane).
QUIET_CLUSTER = {"distributed.admin.tick.interval": "200ms",
                 "distributed.worker.profile.enabled": False,
                 "distributed.worker.memory.monitor-interval": "1s",
                 "distributed.admin.system-monitor.interval": "2s",
                 "distributed.admin.system-monitor.disk": False}


class Twin:
    """The METRIXS digital twin: parameter vectors in, focus-chamber histograms out.

    Parameters
    ----------
    engine : TraceEngine or str, optional
        ``"rayx"`` (the default, :class:`RayxEngine`: the reference), ``"torch"`` (the
        differentiable twin, :class:`~bluesky_offsets.physics.engine.TorchEngine`) or an engine.
    n_rays : int
        Source rays per simulation (the paper: 1e5).
    scheduler : str, optional
        Dask scheduler address (``tcp://host:8786``) to scale out; ``None``
        starts a LocalCluster on first use (a batched engine such as the torch one
        traces in this process instead); ``"inline"`` runs batches in this
        process (no Dask).
    n_workers : int, optional
        Workers of the LocalCluster (default: all cores), one thread each.
    """

    _borrowed = False  # a copy sharing another twin's workers (with_hist): closing it leaves them running

    def __init__(self, engine: TraceEngine | str | None = None, *, n_rays: int = 10_000,
                 scheduler: str | None = None, n_workers: int | None = None, client=None):
        self.engine = make_engine(engine)
        self.n_rays = int(n_rays)
        self.scheduler = scheduler
        self.n_workers = n_workers
        self._client = client
        self._cluster = None

    @property
    def table(self) -> ParameterTable:
        """The engine's parameter table."""
        return self.engine.table

    @property
    def hist(self) -> HistogramSpec:
        """The engine's histogram binning."""
        return self.engine.hist

    def with_hist(self, hist: HistogramSpec) -> Twin:
        """The same tracer and workers, histograms binned by ``hist`` (``self`` if it already is).

        The engine is copied with the new spec; the Dask client is shared (started first if
        needed): the original twin owns it, closing the copy leaves it running.
        """
        if hist == self.hist:
            return self
        import copy
        engine = copy.copy(self.engine)
        engine.hist = hist
        client = None if self.scheduler == "inline" else self.client
        twin = Twin(engine, n_rays=self.n_rays, scheduler=self.scheduler, n_workers=self.n_workers, client=client)
        twin._borrowed = True
        return twin

    # -- single traces (in-process) ------------------------------------------
    def trace(self, values, *, overrides: Mapping | None = None, n_rays: int | None = None,
              keep_rays: bool = False, seed: int | None = None) -> TraceResult:
        """Trace one configuration in this process; raises :class:`TraceFailed` on failure."""
        req = TraceRequest(self.table.validate(values), dict(overrides or {}), seed)
        try:
            return self.engine.trace(req, n_rays or self.n_rays, keep_rays)
        except (ValueError, TypeError):
            raise
        except Exception as exc:
            raise TraceFailed(f"simulation failed for {self.table.to_mapping(req.values)}: {exc}",
                              req.values) from exc

    # -- batches ----------------------------------------------------------------
    @property
    def client(self):
        """The Dask client of the batches: on ``scheduler``, or on a LocalCluster started on first use."""
        if self._client is None:
            from distributed import Client, LocalCluster
            if self.scheduler:
                self._client = Client(self.scheduler)
            else:
                import dask
                n = self.n_workers or os.cpu_count() or 1
                # One thread per worker, so a task that kills its worker (RAYX aborting on bad
                # input) is the only suspect: fail it at once instead of killing 3 more workers.
                # glibc's heap for blocks up to 32 MiB: Dask's nanny sets MALLOC_TRIM_THRESHOLD_,
                # which turns off glibc's adaptive mmap threshold, so that every array above
                # 128 kB (each of a batch trace's ray arrays) would be mapped and page-faulted
                # afresh, at several times a plain process's CPU.  glibc reads it at start: pre-spawn.
                with dask.config.set({"distributed.scheduler.allowed-failures": 0,
                                      "distributed.nanny.pre-spawn-environ.MALLOC_MMAP_THRESHOLD_": 32 << 20,
                                      **QUIET_CLUSTER}):
                    self._cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                 dashboard_address="127.0.0.1:0", env=WORKER_ENV,
                                                 host="127.0.0.1")
                self._client = Client(self._cluster)
        return self._client

    def close(self) -> None:
        """Close the Dask client and the LocalCluster this twin started (a copy leaves the original's running)."""
        if self._borrowed:
            self._client = None  # the twin it was made from owns the workers
            return
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    def __enter__(self) -> Twin:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def trace_batch(self, values, *, overrides: Mapping | Sequence[Mapping] | None = None,
                    n_rays: int | None = None, keep_rays: bool = False, progress: bool = True,
                    chunk_size: int | None = None, raise_on_error: bool = False,
                    seed: int | Sequence[int] | None = None) -> BatchResult:
        """Trace a batch of configurations, results in input order.

        ``overrides`` is one mapping for all rows or one per row.  ``seed``
        (an int: row ``i`` gets ``seed + i``; or one per row) makes the batch
        reproducible wherever it runs.  Failed
        simulations come back with NaN histograms and their error message
        (and are logged with their parameters); ``raise_on_error`` raises
        :class:`TraceFailed` for the first one instead.
        """
        vals = self.table.validate(values, "parameter batch")
        if vals.ndim == 1:
            vals = vals[None, :]
        ovs: list[Mapping]
        if overrides is None or isinstance(overrides, Mapping):
            ovs = [dict(overrides or {})] * len(vals)
        else:
            ovs = list(overrides)
            if len(ovs) != len(vals):
                raise InputError(f"{len(ovs)} overrides for {len(vals)} configurations")
        seeds: list[int | None]
        if seed is None:
            seeds = [None] * len(vals)
        elif isinstance(seed, (int, np.integer)):
            seeds = [int(seed) + i for i in range(len(vals))]
        else:
            seeds = [int(s) for s in seed]
            if len(seeds) != len(vals):
                raise InputError(f"{len(seeds)} seeds for {len(vals)} configurations")
        requests = [TraceRequest(v, o, s) for v, o, s in zip(vals, ovs, seeds)]
        n = n_rays or self.n_rays
        if self.scheduler == "inline" or (self.scheduler is None and self._client is None
                                          and hasattr(self.engine, "trace_many")):
            results = self._run_inline(requests, n, keep_rays, progress)
        else:
            results = self._run_dask(requests, n, keep_rays, progress, chunk_size)
        batch = BatchResult(results)
        for i, v, err in batch.failures:
            log.warning("simulation %d failed (%s) for parameters %s", i, err, _compact(v))
        if raise_on_error and batch.failures:
            i, v, err = batch.failures[0]
            raise TraceFailed(f"simulation {i} failed ({err}) for parameters {_compact(v)}", v)
        return batch

    def _run_inline(self, requests, n, keep_rays, progress) -> list[TraceResult]:
        from bluesky_offsets.progress import bar as progress_bar
        # a batched engine takes many configurations per call
        step = 64 if hasattr(self.engine, "trace_many") else 1
        out = []
        with progress_bar(total=len(requests), desc="tracing", unit="sim", disable=not progress) as bar:
            for i in range(0, len(requests), step):
                out.extend(_trace_chunk(self.engine, requests[i:i + step], n, keep_rays))
                bar.update(len(requests[i:i + step]))
        return out

    def _run_dask(self, requests, n, keep_rays, progress, chunk_size) -> list[TraceResult]:
        from distributed import as_completed

        from bluesky_offsets.progress import bar as progress_bar

        client = self.client
        n_workers = max(len(client.scheduler_info().get("workers", {})), 1)
        if chunk_size is None:
            # a few chunks per worker: good load balance, little scheduling overhead
            chunk_size = max(1, min(64, len(requests) // (4 * n_workers) or 1))
        chunks = [list(range(i, min(i + chunk_size, len(requests))))
                  for i in range(0, len(requests), chunk_size)]
        engine_f = self.engine  # small; scattering it would tie every task to one worker's memory
        futures = {client.submit(_trace_chunk, engine_f, [requests[i] for i in idx], n, keep_rays,
                                 pure=False): idx for idx in chunks}
        results: list[TraceResult | None] = [None] * len(requests)
        with progress_bar(total=len(requests), desc="tracing", unit="sim", disable=not progress) as bar:
            for fut in as_completed(futures):
                idx = futures[fut]
                try:
                    chunk_results = fut.result()
                except Exception as exc:
                    # The worker died (a crash inside the tracer): retry rows one by one
                    # to pin the failure on the configuration that caused it.
                    chunk_results = self._isolate(client, engine_f, [requests[i] for i in idx], n, keep_rays, exc)
                for i, r in zip(idx, chunk_results):
                    results[i] = r
                bar.update(len(idx))
        return results  # type: ignore[return-value]

    def _isolate(self, client, engine_f, requests, n, keep_rays, exc) -> list[TraceResult]:
        if len(requests) == 1:
            return [_failed(self.engine, requests[0], n, f"worker lost: {type(exc).__name__}: {exc}")]
        out = []
        for req in requests:
            fut = client.submit(_trace_chunk, engine_f, [req], n, keep_rays, pure=False)
            try:
                out.extend(fut.result())
            except Exception as exc2:
                out.append(_failed(self.engine, req, n, f"worker lost: {type(exc2).__name__}: {exc2}"))
        return out
