"""Twin datasets for the surrogate: parameter vectors -> RAYX -> histograms, in Zarr.

Drawing scheme
--------------
Draw ``i`` (a global, never reused index) gets its own random stream
``default_rng([seed, i])``: its parameter vector (uniform in the table's box,
the paper's scheme), a keep-lottery number and the RAYX seeds of its traces.
Every draw is therefore the same wherever and whenever it is computed, which
is what makes generation resumable and repeatable.

Uniform draws are ~99 % dark at the focus, so a draw is first *pre-screened*
with a few hundred rays (a few ms, dominated by fixed cost).  Draws with at
least ``screen_min_hits`` screen hits are traced in full (stratum 0, weight
1).  The others are dropped, except a recorded random share
``keep_fraction`` that is traced in full anyway (stratum 1, weight
``1 / keep_fraction``): they give the "bad" class its empty and low-ray
samples, and the weights turn any average over the stored samples back into
an unbiased average over the uniform box.  ``screen_rays = 0`` disables the
screen (every draw traced in full, the paper's scheme).  The screen hits of
*every* draw are stored too, so pass rates are on record.

The store is a ``zarr`` v3 group::

    raw/*                  rows in the order blocks finished (work area);
    draws/screen_hits      screen hits of every draw (-1: not screened / failed);
    progress.json          committed blocks -> rows, written atomically *after* the rows;
    params, hist_x, hist_y, n_hits, screen_hits, stratum, weight, index
                           the finished dataset: exactly n_samples rows, the first
                           n_samples accepted draws in draw order.

Group attributes hold the generation settings and statistics.

A killed run leaves at most uncommitted rows past the committed row count;
the next run overwrites them, so nothing is lost twice or stored twice.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.effects import CHAMBER_HIGH, CHAMBER_INPUTS, CHAMBER_LOW
from bluesky_offsets.physics.metrixs import IMAGE_PLANE
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.physics.twin import SOURCE_FRAME, HistogramSpec, TraceRequest, Twin

log = logging.getLogger(__name__)

FORMAT = "bluesky-offsets-dataset/1"
GOOD_MIN_RAYS = 10  # the paper's "good" threshold (rays on the screen at full ray count)
_ROW_CHUNK = 1024
_STRATA = {0: "passed pre-screen", 1: "failed pre-screen, kept by lottery"}


class DatasetError(RuntimeError):
    """A dataset store that cannot be used as asked (mismatch, incomplete, corrupt)."""


@dataclass(frozen=True)
class DrawScheme:
    """How samples are drawn: uniform box, then an optional low-ray pre-screen.

    Attributes
    ----------
    screen_rays : int
        Source rays of the pre-screen trace; 0 disables the screen.
    screen_min_hits : int
        Screen hits needed to pass.
    keep_fraction : float
        Share of screened-out draws traced in full anyway (the recorded
        "bad"-class sample; weight ``1 / keep_fraction``).
    """

    screen_rays: int = 300
    screen_min_hits: int = 1
    keep_fraction: float = 0.02

    def __post_init__(self):
        if self.screen_rays < 0:
            raise InputError(f"screen_rays must be >= 0, got {self.screen_rays}")
        if self.screen_min_hits < 1:
            raise InputError(f"screen_min_hits must be >= 1, got {self.screen_min_hits}")
        if not 0.0 < self.keep_fraction <= 1.0:
            raise InputError(f"keep_fraction must be in (0, 1], got {self.keep_fraction}")

    @property
    def screened(self) -> bool:
        """Whether draws are pre-screened (``screen_rays`` > 0)."""
        return self.screen_rays > 0

    def describe(self) -> str:
        """The scheme in words, as a store's attributes and the evaluation record it."""
        if not self.screened:
            return "uniform draws from the box, every draw traced in full"
        return (f"uniform draws from the box; pre-screen at {self.screen_rays} rays; draws with >= "
                f"{self.screen_min_hits} screen hits traced in full (weight 1), a random "
                f"{self.keep_fraction:g} share of the others traced in full anyway "
                f"(weight {1 / self.keep_fraction:g}), the rest dropped")


ENGINES = ("rayx", "torch")


@dataclass(frozen=True)
class GenerationSettings:
    """Everything that determines the samples of a store (apart from how many).

    Attributes
    ----------
    engine : {"rayx", "torch"}
        The twin that traces: RAYX one draw at a time, or the torch engine a block at once
        (:meth:`~bluesky_offsets.physics.engine.TorchEngine.trace_batch`: the block's
        draws share one random stream, so a draw's rays depend on its block).
    chamber : bool
        Draw the focus chamber's translation (x, y, z; :data:`CHAMBER_INPUTS`) with the
        parameters: the samples' inputs are then the 34 parameters and the chamber's 3.
    """

    n_rays: int = 10_000
    seed: int = 0
    block_size: int = 256
    scheme: DrawScheme = field(default_factory=DrawScheme)
    engine: str = "rayx"
    chamber: bool = False

    def __post_init__(self):
        if self.n_rays < 1:
            raise InputError(f"n_rays must be positive, got {self.n_rays}")
        if self.block_size < 1:
            raise InputError(f"block_size must be positive, got {self.block_size}")
        if self.engine not in ENGINES:
            raise InputError(f"engine must be one of {', '.join(ENGINES)}, not {self.engine!r}")

    def to_dict(self) -> dict:
        """The settings as plain data (the scheme a nested dict), the form :meth:`from_dict` reads."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping) -> GenerationSettings:
        """The settings :meth:`to_dict` gave."""
        d = dict(d)
        d["scheme"] = DrawScheme(**d.get("scheme", {}))
        return cls(**d)


# --------------------------------------------------------------------------- #
# drawing and tracing (pure, runs on Dask workers)
# --------------------------------------------------------------------------- #
def draw(table: ParameterTable, seed: int, index: int) -> tuple[np.ndarray, float, int, int]:
    """Parameter vector, keep-lottery number and the two RAYX seeds of draw ``index``."""
    return _draw(table, seed, index)[:4]


def _draw(table: ParameterTable, seed: int, index: int):
    """:func:`draw` and the chamber's translation.

    The translation is drawn after, so that the first four are the same with and without the chamber.
    """
    rng = np.random.default_rng([int(seed), int(index)])
    values = table.low + rng.random(len(table)) * table.span
    lottery = float(rng.random())
    screen_seed, full_seed = (int(s) for s in rng.integers(0, 2**32, size=2))
    chamber = CHAMBER_LOW + rng.random(len(CHAMBER_INPUTS)) * (CHAMBER_HIGH - CHAMBER_LOW)
    return values, lottery, screen_seed, full_seed, chamber


def chamber_overrides(chamber) -> dict:
    """RML overrides that put the focus chamber at ``chamber`` (x, y, z in mm).

    ``chamber`` is (3,) for one draw, or (C, 3) for a batch of the torch engine.
    """
    ch = chamber if isinstance(chamber, np.ndarray) else np.asarray(chamber, float)
    cols: list[Any]  # tensors or numbers
    if ch.ndim == 2:
        import torch
        cols = [torch.as_tensor(ch[:, k], dtype=torch.float64) for k in range(3)]
    else:
        cols = [float(v) for v in ch]
    return {IMAGE_PLANE: {f"translation{a}error": v for a, v in zip("XYZ", cols)}}


def generate_block(engine, settings: GenerationSettings, block: int) -> dict:
    """Draw, screen and trace the draws of one block; returns its accepted samples."""
    t0, c0 = time.perf_counter(), time.process_time()
    table = engine.table
    first = block * settings.block_size
    indices = np.arange(first, first + settings.block_size, dtype=np.int64)
    drawn = [_draw(table, settings.seed, int(i)) for i in indices]
    if hasattr(engine, "trace_batch"):
        rows, screen_hits, n_failed = _trace_block_batched(engine, settings, block, indices, drawn)
    else:
        rows, screen_hits, n_failed = _trace_block(engine, settings, indices, drawn)
    nb = table.__len__()
    out = {
        "block": block,
        "index": np.asarray(rows["index"], dtype=np.int64),
        "params": np.asarray(rows["params"], dtype=np.float64).reshape(-1, nb),
        "hist_x": np.asarray(rows["hist_x"], dtype=np.float32).reshape(-1, engine.hist.bins_x),
        "hist_y": np.asarray(rows["hist_y"], dtype=np.float32).reshape(-1, engine.hist.bins_y),
        "n_hits": np.asarray(rows["n_hits"], dtype=np.int32),
        "screen_hits": np.asarray(rows["screen_hits"], dtype=np.int32),
        "stratum": np.asarray(rows["stratum"], dtype=np.int8),
        "weight": np.asarray(rows["weight"], dtype=np.float32),
        "draw_screen_hits": screen_hits,
        "n_failed": n_failed,
        "cpu_s": time.process_time() - c0,
        "wall_s": time.perf_counter() - t0,
    }
    if settings.chamber:
        out["chamber"] = np.asarray(rows["chamber"], dtype=np.float64).reshape(-1, len(CHAMBER_INPUTS))
    return out


def _accept(sch: DrawScheme, hits: int, lottery: float) -> tuple[int, float] | None:
    """(stratum, weight) of a screened draw, or None: dropped."""
    if hits >= sch.screen_min_hits:
        return 0, 1.0
    if lottery < sch.keep_fraction:
        return 1, 1.0 / sch.keep_fraction
    return None


def _trace_block(engine, settings: GenerationSettings, indices, drawn):
    """One draw at a time (RAYX)."""
    sch = settings.scheme
    screen_hits = np.full(len(indices), -1, dtype=np.int32)
    rows: dict[str, list] = {k: [] for k in _row_fields(settings)}
    n_failed = 0
    for j, (i, (values, lottery, s_seed, f_seed, chamber)) in enumerate(zip(indices, drawn)):
        ov = chamber_overrides(chamber) if settings.chamber else {}
        stratum, weight = 0, 1.0
        try:
            if sch.screened:
                hits = engine.trace(TraceRequest(values, ov, s_seed), sch.screen_rays).n_hits
                screen_hits[j] = hits
                kept = _accept(sch, hits, lottery)
                if kept is None:
                    continue
                stratum, weight = kept
            res = engine.trace(TraceRequest(values, ov, f_seed), settings.n_rays)
        except Exception as exc:  # a failed simulation is counted, never stored
            n_failed += 1
            log.warning("draw %d failed: %s", i, exc)
            continue
        _add_row(rows, i, values, chamber, res.hist_x, res.hist_y, res.n_hits, screen_hits[j], stratum, weight)
    return rows, screen_hits, n_failed


def _trace_block_batched(engine, settings: GenerationSettings, block: int, indices, drawn):
    """Trace the whole block at once (the torch engine): one screen batch, one full batch.

    Each batch draws from a stream of the block's own (seeded by the base seed and the block).
    """
    sch = settings.scheme
    values = np.stack([d[0] for d in drawn])
    chamber = np.stack([d[4] for d in drawn])
    s_seed, f_seed = (int(v) for v in np.random.default_rng([int(settings.seed), int(block), 1]).integers(
        0, 2**62, size=2))
    screen_hits = np.full(len(indices), -1, dtype=np.int32)
    rows: dict[str, list] = {k: [] for k in _row_fields(settings)}

    def overrides(sel):
        return chamber_overrides(chamber[sel]) if settings.chamber else None
    try:
        everyone = np.arange(len(indices))
        if sch.screened:
            hits = engine.trace_batch(values, overrides(everyone), n_rays=sch.screen_rays, seed=s_seed).n_hits
            screen_hits[:] = hits
            kept = [_accept(sch, int(h), d[1]) for h, d in zip(hits, drawn)]
        else:
            kept = [(0, 1.0)] * len(indices)
        sel = np.array([j for j, k in enumerate(kept) if k is not None], dtype=np.int64)
        if len(sel):
            res = engine.trace_batch(values[sel], overrides(sel), n_rays=settings.n_rays, seed=f_seed)
    except Exception as exc:  # a failed batch is counted draw by draw, never stored
        log.warning("block %d failed: %s", block, exc)
        return rows, screen_hits, len(indices)
    for r, j in enumerate(sel):
        _add_row(rows, indices[j], values[j], chamber[j], res.hist_x[r], res.hist_y[r], res.n_hits[r],
                 screen_hits[j], *kept[j])
    return rows, screen_hits, 0


def _add_row(rows, index, values, chamber, hist_x, hist_y, n_hits, screen_hits, stratum, weight) -> None:
    for k, v in (("index", index), ("params", values), ("hist_x", hist_x), ("hist_y", hist_y),
                 ("n_hits", n_hits), ("screen_hits", screen_hits), ("stratum", stratum), ("weight", weight)):
        rows[k].append(v)
    if "chamber" in rows:
        rows["chamber"].append(chamber)


_ROW_FIELDS = ("index", "params", "hist_x", "hist_y", "n_hits", "screen_hits", "stratum", "weight")


def _row_fields(settings: GenerationSettings) -> tuple[str, ...]:
    return _ROW_FIELDS + (("chamber",) if settings.chamber else ())


@contextlib.contextmanager
def openmp_threads(n: int):
    """Limit the OpenMP runtimes loaded in this process to ``n`` threads for a while.

    Many small traces in one process run ~7x faster on one thread than on
    all cores (thread start-up per trace).  Dask workers get
    ``OMP_NUM_THREADS=1`` anyway, but in-process ("inline") runs inherit the
    default, the environment variable is read only when a runtime loads, and
    RAYX's OpenMP calls may bind to another copy of libgomp (torch's) loaded
    first: so every loaded copy is limited.
    """
    import ctypes

    try:
        import rayx  # noqa: F401  (loads its OpenMP runtime)
        with open("/proc/self/maps") as f:
            paths = sorted({line.split()[-1] for line in f
                            if any(k in line for k in ("libgomp", "libiomp", "libomp"))})
        libs = [ctypes.CDLL(p) for p in paths]
    except (ImportError, OSError):
        libs = []
    before = []
    for lib in libs:
        try:
            before.append((lib, lib.omp_get_max_threads()))
            lib.omp_set_num_threads(int(n))
        except AttributeError:
            pass
    try:
        yield
    finally:
        for lib, k in before:
            lib.omp_set_num_threads(k)


def _run_blocks(twin: Twin, settings: GenerationSettings, blocks, on_result: Callable[[dict], bool],
                max_in_flight: int | None = None) -> None:
    """Run blocks (an iterator of block ids) on ``twin``'s Dask client, or inline.

    ``on_result`` is called in this process for each finished block; it
    returns ``False`` to stop submitting new blocks (in-flight ones still finish).
    """
    engine = twin.engine
    if twin.scheduler == "inline":
        with openmp_threads(1):
            for b in blocks:
                if not on_result(generate_block(engine, settings, b)):
                    return
        return
    from distributed import as_completed

    client = twin.client
    n_workers = max(len(client.scheduler_info().get("workers", {})), 1)
    window = max_in_flight or 2 * n_workers
    it = iter(blocks)
    ac = as_completed()
    in_flight = 0
    for _ in range(window):
        b = next(it, None)
        if b is None:
            break
        ac.add(client.submit(generate_block, engine, settings, b, pure=False))
        in_flight += 1
    go_on = True
    while in_flight:
        fut = next(ac)
        in_flight -= 1
        res = fut.result()
        fut.release()
        go_on = on_result(res) and go_on
        if go_on:
            b = next(it, None)
            if b is not None:
                ac.add(client.submit(generate_block, engine, settings, b, pure=False))
                in_flight += 1


# --------------------------------------------------------------------------- #
# the store
# --------------------------------------------------------------------------- #
def _write_json_atomic(path: Path, obj) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        json.dump(obj, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _identity(settings: GenerationSettings, twin: Twin) -> dict:
    return {"format": FORMAT, "settings": settings.to_dict(), "table": twin.table.fingerprint(),
            "table_version": twin.table.version, "histogram": twin.hist.fingerprint()}


class DatasetStore:
    """A dataset store on disk: create or reopen, commit blocks, finalize, load."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    # -- opening -----------------------------------------------------------------
    @property
    def progress_path(self) -> Path:
        """The store's ``progress.json``: its identity (with the settings) and the committed blocks."""
        return self.path / "progress.json"

    def exists(self) -> bool:
        """Whether a dataset store is at ``path`` (it has a ``progress.json``)."""
        return self.progress_path.exists()

    def read_progress(self) -> dict:
        """The store's progress record; :class:`DatasetError` if it is missing or unreadable."""
        try:
            return json.loads(self.progress_path.read_text())
        except FileNotFoundError:
            raise DatasetError(f"{self.path} is not a dataset store (no progress.json)") from None
        except (OSError, json.JSONDecodeError) as exc:
            raise DatasetError(f"{self.progress_path} is unreadable ({exc})") from None

    def _group(self, mode: Literal["r", "r+", "a", "w", "w-"] = "a"):
        import zarr
        try:
            return zarr.open_group(str(self.path), mode=mode)
        except Exception as exc:
            raise DatasetError(f"cannot open Zarr store {self.path}: {exc}") from None

    def open_for_generation(self, settings: GenerationSettings, twin: Twin) -> dict:
        """Create the store or check that an existing one was made with the same settings."""
        ident = _identity(settings, twin)
        if self.exists():
            prog = self.read_progress()
            stored = dict(prog["identity"])
            # a store written before a setting existed has its default (the settings' form now)
            stored["settings"] = GenerationSettings.from_dict(stored.get("settings", {})).to_dict()
            mismatch = [k for k in ("format", "settings", "table", "histogram")
                        if json.dumps(stored.get(k), sort_keys=True) != json.dumps(ident[k], sort_keys=True)]
            if mismatch:
                details = "; ".join(f"{k}: store {prog['identity'].get(k)} vs requested {ident[k]}"
                                    for k in mismatch)
                raise DatasetError(f"{self.path} was generated with different {', '.join(mismatch)} "
                                   f"({details}); use another output path or the store's settings")
            return prog
        if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
            raise DatasetError(f"{self.path} exists and is not a dataset store; refusing to overwrite")
        g = self._group("w")
        raw = g.require_group("raw")
        nb, bx, by = len(twin.table), twin.hist.bins_x, twin.hist.bins_y
        for name, shape, dtype in _row_specs(nb, bx, by, settings.chamber):
            raw.create_array(name, shape=(0, *shape), chunks=(_ROW_CHUNK, *shape), dtype=dtype)
        g.require_group("draws").create_array("screen_hits", shape=(0,), chunks=(65536,), dtype="i4",
                                              fill_value=-1)
        prog = {"identity": ident, "engine": twin.engine.version, "source_frame": SOURCE_FRAME, "rows": 0, "blocks": {},
                "complete": False, "created": _now()}
        _write_json_atomic(self.progress_path, prog)
        return prog

    def commit_block(self, prog: dict, res: dict) -> None:
        """Append one finished block's rows, then record it (rows first, marker second)."""
        g = self._group()
        raw = g["raw"]
        r0, k = prog["rows"], len(res["index"])
        if k:
            for name in _row_fields(_settings_of(prog)):
                arr = raw[name]
                if arr.shape[0] < r0 + k:
                    arr.resize((max(r0 + k, 2 * arr.shape[0], _ROW_CHUNK), *arr.shape[1:]))
                arr[r0:r0 + k] = res[name]
        d = g["draws"]["screen_hits"]
        bs = len(res["draw_screen_hits"])
        lo = res["block"] * bs
        if d.shape[0] < lo + bs:
            d.resize((max(lo + bs, 2 * d.shape[0]),))
        d[lo:lo + bs] = res["draw_screen_hits"]
        prog["blocks"][str(res["block"])] = {"row": r0, "n": k, "failed": res["n_failed"],
                                             "cpu_s": round(res["cpu_s"], 4), "wall_s": round(res["wall_s"], 4)}
        prog["rows"] = r0 + k
        _write_json_atomic(self.progress_path, prog)

    # -- finishing ---------------------------------------------------------------
    @staticmethod
    def prefix(prog: dict) -> tuple[int, int]:
        """(number of contiguous committed blocks from 0, accepted samples in them)."""
        blocks, n, total = prog["blocks"], 0, 0
        while str(n) in blocks:
            total += blocks[str(n)]["n"]
            n += 1
        return n, total

    def finalize(self, prog: dict, n_samples: int) -> dict:
        """Write the first ``n_samples`` accepted draws (draw order) as the dataset."""
        g = self._group()
        raw = g["raw"]
        n_blocks, total = self.prefix(prog)
        if total < n_samples:
            raise DatasetError(f"only {total} samples committed, {n_samples} requested")
        rows = np.concatenate([np.arange(b["row"], b["row"] + b["n"]) for k, b in prog["blocks"].items()
                               if int(k) < n_blocks] or [np.zeros(0, dtype=np.int64)]).astype(np.int64)
        index = raw["index"][:prog["rows"]][rows]
        order = np.argsort(index, kind="stable")[:n_samples]
        sel = rows[order]
        if prog.get("complete"):  # re-finalizing (extension): arrays are about to change
            prog["complete"] = False
            _write_json_atomic(self.progress_path, prog)
        if len(np.unique(index[order])) != n_samples:  # cannot happen by construction; never ship it
            raise DatasetError("duplicate draw indices among committed rows")
        for name in _row_fields(_settings_of(prog)):
            data = raw[name][:prog["rows"]][sel]
            if name in g and name not in ("raw", "draws"):
                del g[name]
            g.create_array(name, shape=data.shape, chunks=(_ROW_CHUNK, *data.shape[1:]), dtype=data.dtype)
            g[name][:] = data
        last = int(index[order][-1]) if n_samples else -1
        s = GenerationSettings.from_dict(prog["identity"]["settings"])
        stats = self._stats(g, prog, s, last, n_blocks)
        g.attrs.update({"format": FORMAT, "settings": s.to_dict(), "scheme": s.scheme.describe(),
                        "n_samples": n_samples, "table": prog["identity"]["table"],
                        "table_version": prog["identity"]["table_version"],
                        "histogram": prog["identity"]["histogram"], "engine": prog["engine"],
                        "strata": {str(k): v for k, v in _STRATA.items()}, "stats": stats,
                        "good_min_rays": GOOD_MIN_RAYS, "finished": _now()})
        prog["complete"] = True
        prog["n_samples"] = n_samples
        _write_json_atomic(self.progress_path, prog)
        return stats

    def _stats(self, g, prog, s: GenerationSettings, last_index: int, n_blocks: int) -> dict:
        n_draws = last_index + 1
        sh = g["draws"]["screen_hits"][:n_draws] if n_draws else np.zeros(0, dtype=np.int32)
        n_hits = g["n_hits"][:]
        stratum = g["stratum"][:]
        blocks = [b for k, b in prog["blocks"].items() if int(k) < n_blocks]
        st = {"n_draws": int(n_draws), "n_samples": int(len(n_hits)),
              "n_stratum0": int((stratum == 0).sum()), "n_stratum1": int((stratum == 1).sum()),
              "n_nonempty": int((n_hits > 0).sum()), "n_good": int((n_hits >= GOOD_MIN_RAYS).sum()),
              "n_failed": int(sum(b["failed"] for b in blocks)),
              "cpu_s": float(sum(b["cpu_s"] for b in blocks)),
              "blocks": n_blocks}
        if s.scheme.screened and n_draws:
            st["screen_pass_rate"] = float((sh >= s.scheme.screen_min_hits).mean())
        w = g["weight"][:].astype(float)
        if n_draws:
            # Horvitz-Thompson: estimated share of the uniform box with >= 1 / >= 10 rays at full count
            st["uniform_nonempty_share_est"] = float((w * (n_hits > 0)).sum() / n_draws)
            st["uniform_good_share_est"] = float((w * (n_hits >= GOOD_MIN_RAYS)).sum() / n_draws)
        if st["cpu_s"] > 0:
            st["good_per_cpu_s"] = st["n_good"] / st["cpu_s"]
        return st


def _row_specs(nb: int, bx: int, by: int, chamber: bool = False):
    return [("index", (), "i8"), ("params", (nb,), "f8"), ("hist_x", (bx,), "f4"), ("hist_y", (by,), "f4"),
            ("n_hits", (), "i4"), ("screen_hits", (), "i4"), ("stratum", (), "i1"), ("weight", (), "f4")] + (
        [("chamber", (len(CHAMBER_INPUTS),), "f8")] if chamber else [])


def _settings_of(prog: dict) -> GenerationSettings:
    return GenerationSettings.from_dict(prog["identity"]["settings"])


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


# --------------------------------------------------------------------------- #
# generation front-ends
# --------------------------------------------------------------------------- #
def generate(path: str | os.PathLike, n_samples: int, settings: GenerationSettings | None = None, *,
             twin: Twin | None = None, scheduler: str | None = None, n_workers: int | None = None,
             progress: bool = True, rayx_check: int = 64) -> dict:
    """Generate (or resume, or extend) a dataset store with exactly ``n_samples`` samples.

    Returns the dataset statistics.  Killed at any point and called again with
    the same settings, it carries on from the last committed block.  A store traced by
    another engine than RAYX ends with :func:`check_against_rayx` on ``rayx_check`` of
    its non-empty samples (0: no check); the statistics carry its result.
    """
    from bluesky_offsets.progress import bar as progress_bar

    if n_samples < 1:
        raise InputError(f"n_samples must be positive, got {n_samples}")
    settings = settings or GenerationSettings()
    own = twin is None
    twin = twin or Twin(settings.engine, n_rays=settings.n_rays, scheduler=scheduler, n_workers=n_workers)
    store = DatasetStore(path)
    try:
        prog = store.open_for_generation(settings, twin)
        n_pref, got = store.prefix(prog)
        if prog.get("complete") and prog.get("n_samples") == n_samples:
            return dict(store._group("r").attrs["stats"])
        if got < n_samples:
            done = {int(k) for k in prog["blocks"]}
            bar = progress_bar(total=n_samples, initial=min(got, n_samples), desc="dataset", unit="sample",
                               disable=not progress, smoothing=0.05)
            committed = sum(b["n"] for b in prog["blocks"].values())

            def blocks():
                b = 0
                while True:
                    if b not in done:
                        yield b
                    b += 1

            def on_result(res: dict) -> bool:
                nonlocal committed
                store.commit_block(prog, res)
                committed += len(res["index"])
                _, pre = store.prefix(prog)
                bar.n = min(pre, n_samples)
                bar.set_postfix(committed=committed, blocks=len(prog["blocks"]), refresh=False)
                bar.refresh()
                # stop submitting once the committed rows suffice; the prefix check below
                # brings in any block still missing from the contiguous prefix
                return committed < n_samples

            try:
                _run_blocks(twin, settings, blocks(), on_result)
                # Blocks finishing out of order can leave a gap in the prefix: fill it.
                while store.prefix(prog)[1] < n_samples:
                    n_pref, _ = store.prefix(prog)
                    _run_blocks(twin, settings, iter([n_pref]), on_result)
            finally:
                bar.close()
        stats = store.finalize(prog, n_samples)
    finally:
        if own:
            twin.close()
    if settings.engine != "rayx" and rayx_check > 0:
        stats["rayx_check"] = check_against_rayx(path, rayx_check, scheduler=scheduler, n_workers=n_workers,
                                                 progress=progress)
    return stats


def check_against_rayx(path: str | os.PathLike, n_check: int = 64, *, seed: int = 0,
                       scheduler: str | None = None, n_workers: int | None = None, progress: bool = True) -> dict:
    """Trace a random slice of a store's non-empty samples again with RAYX.

    Each with the same inputs and ray count, and two fresh RAYX seeds.

    A sample of another engine is checked *in distribution*: its histograms must differ
    from RAYX's by RAYX's own repeat noise, no more.  ``mse_ratio`` is the mean over the
    slice of MSE(store, RAYX) over the mean of MSE(RAYX, RAYX') (1 when the two engines
    draw from the same distribution), ``hits_ratio`` the mean screen hits of the store
    over RAYX's; each with a 95 % bootstrap interval over the slice.  The result is
    stored in the store's attributes (``rayx_check``) and returned.
    """
    data = load(path, allow_partial=True)
    s = GenerationSettings.from_dict(data.meta["settings"])
    rng = np.random.default_rng([int(seed), 0x5A7])
    nonempty = np.nonzero(data.n_hits > 0)[0]
    if not len(nonempty):
        raise DatasetError(f"{path}: no non-empty sample to check")
    pick = np.sort(rng.choice(nonempty, size=min(int(n_check), len(nonempty)), replace=False))
    ovs = [chamber_overrides(data.chamber[i]) if data.chamber is not None else {} for i in pick]
    seeds = rng.integers(0, 2**31, size=(2, len(pick)))
    t0 = time.perf_counter()
    with Twin("rayx", n_rays=s.n_rays, scheduler=scheduler, n_workers=n_workers) as rayx:
        a, b = (rayx.trace_batch(data.params[pick], overrides=ovs, seed=[int(v) for v in sd], progress=progress,
                                 raise_on_error=True) for sd in seeds)
    h = data.hist[pick].astype(float)
    ha, hb = (np.concatenate([r.hist_x, r.hist_y], axis=1) for r in (a, b))
    mse_store, mse_repeat = ((h - ha) ** 2).mean(1), ((ha - hb) ** 2).mean(1)
    hits_store, hits_rayx = data.n_hits[pick].astype(float), a.n_hits.astype(float)
    boot = rng.integers(0, len(pick), size=(2000, len(pick)))

    def ci(num, den):
        r = num[boot].mean(1) / np.maximum(den[boot].mean(1), 1e-300)
        return [float(np.quantile(r, 0.025)), float(np.quantile(r, 0.975))]
    out = {"n_checked": int(len(pick)), "n_rays": s.n_rays, "seed": int(seed),
           "mse_ratio": float(mse_store.mean() / mse_repeat.mean()), "mse_ratio_ci95": ci(mse_store, mse_repeat),
           "hits_ratio": float(hits_store.mean() / hits_rayx.mean()), "hits_ratio_ci95": ci(hits_store, hits_rayx),
           "mse_store_rayx": float(mse_store.mean()), "mse_rayx_repeat": float(mse_repeat.mean()),
           "wall_s": round(time.perf_counter() - t0, 1)}
    out["consistent"] = bool(out["mse_ratio_ci95"][0] <= 1.0 <= out["mse_ratio_ci95"][1]
                             and out["hits_ratio_ci95"][0] <= 1.0 <= out["hits_ratio_ci95"][1])
    DatasetStore(path)._group().attrs["rayx_check"] = out
    return out


def draw_in_memory(twin: Twin, settings: GenerationSettings, *, min_samples: int, min_nonempty: int = 0,
                   max_blocks: int = 100_000, progress: bool = True) -> dict:
    """Draw samples with ``settings`` without a store (fresh evaluation sets).

    Runs blocks until at least ``min_samples`` samples, ``min_nonempty`` of them
    non-empty, were accepted; returns all rows of the blocks run, in draw order,
    plus the screen hits of every draw.
    """
    from bluesky_offsets.progress import bar as progress_bar

    results: list[dict] = []
    got = nonempty = 0
    bar = progress_bar(total=min_samples, desc="drawing", unit="sample", disable=not progress)

    def on_result(res):
        nonlocal got, nonempty
        results.append(res)
        got += len(res["index"])
        nonempty += int((res["n_hits"] > 0).sum())
        bar.n = min(got, min_samples)
        bar.set_postfix(nonempty=nonempty, refresh=False)
        bar.refresh()
        return got < min_samples or nonempty < min_nonempty

    try:
        _run_blocks(twin, settings, iter(range(max_blocks)), on_result)
    finally:
        bar.close()
    results.sort(key=lambda r: r["block"])
    out: dict[str, Any] = {k: np.concatenate([r[k] for r in results]) for k in _row_fields(settings)}
    out["draw_screen_hits"] = np.concatenate([r["draw_screen_hits"] for r in results])
    out["n_draws"] = len(out["draw_screen_hits"])
    out["cpu_s"] = float(sum(r["cpu_s"] for r in results))
    out["n_failed"] = int(sum(r["n_failed"] for r in results))
    return out


# --------------------------------------------------------------------------- #
# reading
# --------------------------------------------------------------------------- #
@dataclass
class Dataset:
    """A dataset in memory (rows in draw order)."""

    params: np.ndarray  # (N, n_params) physical
    hist_x: np.ndarray  # (N, bins_x)
    hist_y: np.ndarray
    n_hits: np.ndarray
    stratum: np.ndarray
    weight: np.ndarray
    index: np.ndarray
    meta: dict
    chamber: np.ndarray | None = None  # (N, 3) the focus chamber's x, y, z (mm), if drawn

    def __len__(self) -> int:
        return len(self.index)

    @property
    def inputs(self) -> np.ndarray:
        """(N, 34 [+ 3]): the parameters, then the chamber's translation where drawn."""
        return self.params if self.chamber is None else np.concatenate([self.params, self.chamber], axis=1)

    @property
    def hist(self) -> np.ndarray:
        """(N, bins_x + bins_y): x then y, the surrogate's output layout."""
        return np.concatenate([self.hist_x, self.hist_y], axis=1)

    @property
    def good(self) -> np.ndarray:
        """(N,) bool: the paper's "good" samples, at least :data:`GOOD_MIN_RAYS` rays on the screen."""
        return self.n_hits >= GOOD_MIN_RAYS


def load(path: str | os.PathLike, *, allow_partial: bool = False,
         table: ParameterTable = METRIXS, hist: HistogramSpec | None = None) -> Dataset:
    """Load a finished dataset (or, with ``allow_partial``, the rows committed so far)."""
    store = DatasetStore(path)
    prog = store.read_progress()
    hist = hist or HistogramSpec()
    ident = prog["identity"]
    problems = table.diff(ident["table"])
    if problems:
        raise DatasetError(f"{path} was generated for another parameter table: {'; '.join(problems)}")
    if ident["histogram"] != hist.fingerprint():
        raise DatasetError(f"{path} uses histogram spec {ident['histogram']}, expected {hist.fingerprint()}")
    g = store._group("r")
    settings = GenerationSettings.from_dict(ident["settings"])
    meta = {"path": str(path), "settings": settings.to_dict(), "scheme": settings.scheme.describe(),
            "engine": prog["engine"], "source_frame": prog.get("source_frame", "mirrored"),
            "table_version": ident["table_version"], "histogram": ident["histogram"],
            "inputs": list(table.names) + (list(CHAMBER_INPUTS) if settings.chamber else [])}
    try:
        if prog.get("complete"):
            data = {k: g[k][:] for k in _row_fields(settings)}
            meta.update(complete=True, stats=dict(g.attrs.get("stats", {})))
        elif allow_partial:
            raw = g["raw"]
            data = {k: raw[k][:prog["rows"]] for k in _row_fields(settings)}
            order = np.argsort(data["index"], kind="stable")
            data = {k: v[order] for k, v in data.items()}
            meta.update(complete=False, stats={"n_samples": int(len(order)),
                                               "cpu_s": float(sum(b["cpu_s"] for b in prog["blocks"].values()))})
        else:
            raise DatasetError(f"{path} is incomplete ({prog['rows']} samples committed); run "
                               "`bluesky-offsets dataset generate` again with the same settings to finish it, "
                               "or load it with allow_partial")
    except DatasetError:
        raise
    except Exception as exc:
        raise DatasetError(f"{path}: cannot read arrays ({type(exc).__name__}: {exc})") from None
    if len(np.unique(data["index"])) != len(data["index"]):
        raise DatasetError(f"{path}: duplicate draw indices (corrupt store)")
    meta["n_samples"] = int(len(data["index"]))
    return Dataset(params=data["params"], hist_x=data["hist_x"], hist_y=data["hist_y"],
                   n_hits=data["n_hits"], stratum=data["stratum"], weight=data["weight"],
                   index=data["index"], meta=meta, chamber=data.get("chamber"))


def concat(parts) -> Dataset:
    """Several stores' samples as one dataset, in the order given (a store grown by another).

    The stores must describe the same samples: ray count, draw scheme, chamber, parameter
    table and histograms.  Their draws must be distinct, i.e. each store has its own base
    seed (a draw is keyed by (seed, index)).  ``meta["path"]`` joins the paths with
    ``" + "``, so a model trained on the first store can be fine-tuned on the union and keep
    its split (:func:`~bluesky_offsets.surrogate.training.train`); ``meta["parts"]`` lists
    each store's path, size, seed, engine and statistics.
    """
    parts = list(parts)
    if not parts:
        raise DatasetError("no dataset to concatenate")
    if len(parts) == 1:
        return parts[0]
    first = parts[0].meta
    for d in parts[1:]:
        m = d.meta
        for key in ("table_version", "histogram", "source_frame"):
            if m.get(key) != first.get(key):
                raise DatasetError(f"{m['path']} has {key} {m.get(key)!r}, {first['path']} has {first.get(key)!r}")
        for key in ("n_rays", "scheme", "chamber"):
            if m["settings"].get(key) != first["settings"].get(key):
                raise DatasetError(f"{m['path']} was drawn with {key} {m['settings'].get(key)!r}, "
                                   f"{first['path']} with {first['settings'].get(key)!r}")
    seeds = [d.meta["settings"]["seed"] for d in parts]
    if len(set(seeds)) != len(seeds):
        raise DatasetError(f"the stores share a base seed ({seeds}): their draws would repeat")
    meta = {**first, "path": " + ".join(d.meta["path"] for d in parts), "n_samples": sum(len(d) for d in parts),
            "complete": all(d.meta.get("complete") for d in parts),
            "engine": "; ".join(dict.fromkeys(d.meta["engine"] for d in parts)),
            "parts": [{"path": d.meta["path"], "n_samples": len(d), "seed": d.meta["settings"]["seed"],
                       "engine": d.meta["engine"], "stats": d.meta.get("stats", {})} for d in parts]}
    meta["stats"] = {"cpu_s": sum(float(d.meta.get("stats", {}).get("cpu_s") or 0.0) for d in parts)}
    cat = {k: np.concatenate([getattr(d, k) for d in parts]) for k in
           ("params", "hist_x", "hist_y", "n_hits", "stratum", "weight", "index")}
    chamber = None if parts[0].chamber is None else np.concatenate([d.chamber for d in parts])
    return Dataset(**cat, meta=meta, chamber=chamber)


def load_many(paths, **kw) -> Dataset:
    """:func:`load` each store and :func:`concat` them."""
    return concat([load(p, **kw) for p in paths])


# --------------------------------------------------------------------------- #
# a compact form for moving samples between machines
# --------------------------------------------------------------------------- #
#: the fields of :func:`compact_rows`'s result
COMPACT_FIELDS = ("index", "counts_x", "counts_y", "n_hits", "screen_hits", "stratum", "weight")


def compact_rows(res: Mapping, n_rays: int) -> dict:
    """A block's or a dataset's rows without what the draw recomputes, the histograms as ray counts.

    The parameters and the chamber follow from (seed, index) (:func:`draw`), and a histogram bin
    is a ray count over ``n_rays``, so it travels as an integer (uint16: at most 65,535 rays in a bin).
    """
    out = {}
    for axis in ("x", "y"):
        counts = np.rint(np.asarray(res[f"hist_{axis}"], dtype=np.float64) * n_rays)
        if counts.size and counts.max() > np.iinfo(np.uint16).max:
            raise DatasetError("a bin holds more than 65,535 rays: the compact form cannot carry it")
        out[f"counts_{axis}"] = counts.astype(np.uint16)
    for k, dt in (("index", np.int64), ("n_hits", np.int32), ("screen_hits", np.int32), ("stratum", np.int8),
                  ("weight", np.float32)):
        out[k] = np.asarray(res[k], dtype=dt)
    return out


def expand_rows(rows: Mapping, settings: GenerationSettings, table: ParameterTable = METRIXS) -> dict:
    """The inverse of :func:`compact_rows`: the full row fields of ``settings``'s store."""
    drawn = [_draw(table, settings.seed, int(i)) for i in rows["index"]]
    nb = len(table)
    out = {"index": np.asarray(rows["index"], dtype=np.int64),
           "params": np.asarray([d[0] for d in drawn], dtype=np.float64).reshape(-1, nb),
           "hist_x": (rows["counts_x"].astype(np.float64) / settings.n_rays).astype(np.float32),
           "hist_y": (rows["counts_y"].astype(np.float64) / settings.n_rays).astype(np.float32),
           "n_hits": np.asarray(rows["n_hits"], dtype=np.int32),
           "screen_hits": np.asarray(rows["screen_hits"], dtype=np.int32),
           "stratum": np.asarray(rows["stratum"], dtype=np.int8),
           "weight": np.asarray(rows["weight"], dtype=np.float32)}
    if settings.chamber:
        out["chamber"] = np.asarray([d[4] for d in drawn], dtype=np.float64).reshape(-1, len(CHAMBER_INPUTS))
    return out


def info(path: str | os.PathLike) -> dict:
    """Settings, progress and statistics of a store (finished or not)."""
    store = DatasetStore(path)
    prog = store.read_progress()
    s = GenerationSettings.from_dict(prog["identity"]["settings"])
    out = {"path": str(path), "complete": bool(prog.get("complete")), "engine": prog["engine"],
           "settings": s.to_dict(), "scheme": s.scheme.describe(),
           "table_version": prog["identity"]["table_version"], "committed_rows": prog["rows"],
           "committed_blocks": len(prog["blocks"]),
           "cpu_s": float(sum(b["cpu_s"] for b in prog["blocks"].values()))}
    if prog.get("complete"):
        out["n_samples"] = prog.get("n_samples")
        out["stats"] = dict(store._group("r").attrs.get("stats", {}))
    return out
