"""The run store: Bluesky runs in a tiled catalog, measurements loaded back as arrays.

By default the catalog is embedded and persistent: a SQLite catalog plus
array/table storage in a user data directory
(``platformdirs.user_data_path("bluesky-offsets") / "runs"``), served
in-process, written by ``bluesky_tiled_plugins.TiledWriter``.  The location
can be changed with the ``BLUESKY_OFFSETS_STORE`` environment variable or
the ``location`` argument, which may also be a tiled server URL
(``http://host:8000``, API key from ``TILED_API_KEY``).

Typical use::

    store = open_store()                 # or open_store("/data/metrixs-runs")
    RE.subscribe(store.writer)
    (uid,) = RE(measure_configurations(configs, beamline, chamber))
    m = store.load_measurement(uid)      # m.configurations (n, 34), m.hist_x (n, 50), m.hist_y (n, 50)
"""

from __future__ import annotations

import logging
import os
import sqlite3
import warnings
import weakref
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable

if TYPE_CHECKING:
    from tiled.client import Context

log = logging.getLogger("bluesky_offsets.store")

ENV_STORE = "BLUESKY_OFFSETS_STORE"


class StoreError(OSError):
    """The run store cannot be opened or written (the message names the location)."""


def default_store_location() -> str:
    """``$BLUESKY_OFFSETS_STORE`` or ``<user data dir>/bluesky-offsets/runs``."""
    env = os.environ.get(ENV_STORE)
    if env:
        return env
    try:
        from platformdirs import user_data_path
        base = user_data_path("bluesky-offsets", appauthor=False)
    except ImportError:  # pragma: no cover - platformdirs is a dependency
        base = Path.home() / ".local" / "share" / "bluesky-offsets"
    return str(base / "runs")


# --------------------------------------------------------------------------- #
# measurements as arrays
# --------------------------------------------------------------------------- #
def _key(keys, suffix: str, preferred: str | None = None) -> str:
    if preferred and preferred in keys:
        return preferred
    hits = [k for k in keys if k == suffix or k.endswith("-" + suffix) or k.endswith("_" + suffix)]
    if len(hits) != 1:
        raise KeyError(f"cannot tell which data key holds {suffix!r}: candidates {hits or sorted(keys)}")
    return hits[0]


def measurement_from_run(run, *, stream: str = "primary") -> Measurement:
    """Arrays of a measurement run (a tiled BlueskyRun node)."""
    start = dict(run.metadata["start"])
    uid = start.get("uid")
    if "configurations" not in start:
        raise InputError(f"run {uid} has no 'configurations' in its metadata: not a measure_configurations run")
    names = tuple(start.get("parameter_names", METRIXS.names))
    configs = np.asarray(start["configurations"], dtype=float)
    if stream not in run:
        return Measurement(configs[:0], np.zeros((0, 50)), np.zeros((0, 50)), names=names, uid=uid, metadata=start)
    ds = run[stream].read()
    keys = list(ds.data_vars) if hasattr(ds, "data_vars") else list(ds)
    hk = start.get("hist_keys", {})
    kx, ky = _key(keys, "hist_x", hk.get("x")), _key(keys, "hist_y", hk.get("y"))
    hist_x, hist_y = np.asarray(ds[kx]), np.asarray(ds[ky])
    if "configuration" in keys:  # each frame's own (a designed measurement chooses them as it goes)
        configs = np.asarray(ds["configuration"], dtype=float)
        idx = np.arange(len(hist_x))
    else:
        idx_key = next((k for k in keys if k.endswith("config_index")), None)
        idx = np.asarray(ds[idx_key], dtype=int) if idx_key else np.arange(len(hist_x))
    counts = images = None
    try:
        counts = np.asarray(ds[_key(keys, "total_counts", hk.get("counts"))])
    except KeyError:
        pass
    try:
        img = np.asarray(ds[_key(keys, "image", hk.get("image"))])
        shape = start.get("image_shape")
        if shape and img.ndim == 2 and img.shape[1] == int(np.prod(shape)):
            images = img.reshape(len(img), *shape)
    except KeyError:
        pass
    stop = run.metadata.get("stop") or {}
    md = dict(start, exit_status=stop.get("exit_status"))
    px, py = _profiles(ds, keys, hk, start, hist_x, hist_y)
    screens = (np.stack([np.asarray(ds[f"screen_{a}"], dtype=float) for a in "xyz"], 1)
               if "screen_x" in keys else None)
    floors = camera_floors(lambda key: ds[_key(keys, key)], px is not None)
    return Measurement(configs[idx], hist_x, hist_y, names=names, uid=uid, total_counts=counts, images=images,
                       metadata=md, profile_x=px, profile_y=py, screen=screens, **floors)


def _profiles(ds, keys, hk, start, hist_x, hist_y):
    """The camera-resolution profiles of a run's stream, or (None, None)."""
    if not start.get("profile"):
        return None, None
    try:
        px = np.asarray(ds[_key(keys, "profile_x", hk.get("profile_x"))])
        py = np.asarray(ds[_key(keys, "profile_y", hk.get("profile_y"))])
    except KeyError:
        return None, None
    return consistent_profiles(px, py, start["profile"], hist_x, hist_y)


def camera_floors(get, with_profiles: bool) -> dict:
    """A camera's noise floors of a run's frames as :class:`Measurement` fields.

    ``get(key)`` gives the values of the reading ``floor_hx`` ...; ``{}`` for a detector without them.
    """
    try:
        out = {"floor_x": np.asarray(get("floor_hx"), float), "floor_y": np.asarray(get("floor_hy"), float)}
        if with_profiles:
            out.update(profile_floor_x=np.asarray(get("floor_px"), float),
                       profile_floor_y=np.asarray(get("floor_py"), float))
    except KeyError:
        return {}
    return out


def consistent_profiles(profile_x, profile_y, fingerprint, hist_x, hist_y):
    """``(profile_x, profile_y)`` as float arrays if they are consistent with the histograms.

    Consistent: binned as ``fingerprint`` says, they sum up to the histograms; ``(None, None)``
    otherwise (a detector backend without rays publishes zeros).
    """
    from bluesky_offsets.physics.twin import HistogramSpec
    try:
        px, py = np.asarray(profile_x, dtype=float), np.asarray(profile_y, dtype=float)
        spec = HistogramSpec.from_fingerprint(fingerprint)
        hx, hy = np.asarray(hist_x, dtype=float), np.asarray(hist_y, dtype=float)
        rx, ry = spec.rebin(px, py, HistogramSpec(hx.shape[-1], spec.range_x, hy.shape[-1], spec.range_y))
    except (KeyError, ValueError, TypeError):
        return None, None
    if not (np.allclose(rx, hx, rtol=1e-4, atol=1e-7) and np.allclose(ry, hy, rtol=1e-4, atol=1e-7)):
        return None, None
    return px, py


# --------------------------------------------------------------------------- #
# the catalog
# --------------------------------------------------------------------------- #
def _first_line(exc: BaseException) -> str:
    """The first line of an error's message (its type's name if it has none), for one-line errors."""
    return (str(exc).splitlines() or [type(exc).__name__])[0][:300]


def _init_catalog(uri: str) -> None:
    """Create a new tiled catalog at ``uri``: its tables created and stamped with alembic's head.

    As ``tiled catalog init`` does, but in this process, on a thread of its own (its event loop
    and its SQLite connections stay there): tiled's ``init_if_not_exists`` starts that command as
    a subprocess, a new interpreter importing tiled: seconds that every new store of a test and
    of a demo would pay.
    """
    import asyncio
    import threading

    from sqlalchemy.ext.asyncio import create_async_engine
    from tiled.alembic_utils import UninitializedDatabase, check_database, stamp_head
    from tiled.catalog.alembic_constants import ALEMBIC_DIR, ALEMBIC_INI_TEMPLATE_PATH
    from tiled.catalog.core import ALL_REVISIONS, REQUIRED_REVISION, initialize_database
    from tiled.utils import ensure_specified_sql_driver

    uri = ensure_specified_sql_driver(uri)
    failed: list[BaseException] = []

    async def tables() -> None:
        engine = create_async_engine(uri)
        try:
            await check_database(engine, REQUIRED_REVISION, ALL_REVISIONS)
        except UninitializedDatabase:
            await initialize_database(engine)
        finally:
            await engine.dispose()

    def run() -> None:
        try:
            asyncio.run(tables())
            stamp_head(ALEMBIC_INI_TEMPLATE_PATH, ALEMBIC_DIR, uri)
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
            failed.append(exc)

    worker = threading.Thread(target=run, name="tiled-catalog-init")
    worker.start()
    worker.join()
    if failed:
        raise StoreError(f"run store: cannot create the catalog {uri}: {_first_line(failed[0])}") from failed[0]


def _relocate(path: Path, db: Path) -> str | None:
    """Point an embedded catalog that was moved or copied to ``path`` (absolute) at its own files.

    tiled records each array's file and the event tables' DuckDB file by absolute URI (a store
    made with a relative path: the tables' by the relative one), and refuses to read a URI
    outside the store it serves: a moved or copied store, or a relative one opened from another
    directory, could not load a run ("Refusing to serve file://... outside the readable storage
    area").  The old place is read from the tables' URI (``duckdb://localhost/<place>/tables.duckdb``)
    and every URI under it is rewritten to ``path`` in one transaction.  Returns the old place,
    or None when the catalog already points here (or holds no tables yet).
    """
    from contextlib import closing

    head, tail = "duckdb://localhost/", "/tables.duckdb"
    new = str(path)
    with closing(sqlite3.connect(db)) as con:
        duck = [u for (u,) in con.execute("SELECT data_uri FROM assets WHERE data_uri LIKE 'duckdb://%'")]
        olds = {u[len(head):-len(tail)] for u in duck if u.startswith(head) and u.endswith(tail)}
        if len(olds) != 1:
            return None  # no tables yet (nothing was written), or not a store this package made
        old = olds.pop()
        if old == new:
            return None
        # the arrays' files: absolute (a relative store's were made absolute where it was written)
        files = [u for (u,) in con.execute("SELECT data_uri FROM assets WHERE data_uri LIKE 'file://localhost/%'")]
        marker = f"{old.rstrip('/')}/data/" if old.startswith("/") else f"/{old.strip('/')}/data/"
        roots = {u[len("file://localhost"):u.index(marker) + len(marker) - len("/data/")]
                 for u in files if marker in u}
        if len(roots) > 1:
            return None  # files from several places: leave the catalog as it is
        with con:
            con.execute("UPDATE assets SET data_uri = ? WHERE data_uri = ?", (f"{head}{new}{tail}", f"{head}{old}{tail}"))
            for root in roots:
                pre = f"file://localhost{root}/data/"
                con.execute("UPDATE assets SET data_uri = ? || substr(data_uri, ?) WHERE substr(data_uri, 1, ?) = ?",
                            (f"file://localhost{new}/data/", len(pre) + 1, len(pre), pre))
    return old


_WRITERS: dict[str, weakref.WeakSet] = {}
"""The queued writers of this process by catalog: a read waits for all that write to its catalog."""


def store_path(location: str) -> Path | None:
    """The folder of an embedded store at ``location`` (``~`` expanded); None for a tiled server's URL."""
    return None if location.startswith(("http://", "https://")) else Path(location).expanduser()


def _catalog_key(location: str) -> str:
    path = store_path(location)
    return location.rstrip("/") if path is None else str(path.resolve())


class RunStore:
    """A tiled catalog of Bluesky runs: embedded (a directory) or a tiled server (URL).

    Parameters
    ----------
    location : str or Path, optional
        Directory of an embedded catalog (created if missing) or ``http(s)://`` URL
        of a tiled server.  Default: :func:`default_store_location`.
    api_key : str, optional
        For a server; default ``$TILED_API_KEY``.
    """

    def __init__(self, location: str | os.PathLike | None = None, *, api_key: str | None = None):
        loc = str(location) if location is not None else default_store_location()
        self.location = loc
        self._context: Context | None = None
        self._frames: Path | None = None
        path = store_path(loc)
        if path is None:
            from tiled.client import from_uri
            self._client = from_uri(loc, api_key=api_key or os.environ.get("TILED_API_KEY"))
        else:
            self._client = self._embedded(path)
        self._writer = None
        self._catalog = _catalog_key(loc)  # every read looks up the writers by it

    @property
    def client(self):
        """The tiled client of the catalog, once every document handed to :attr:`writer` is in."""
        self.flush()
        return self._client

    def flush(self) -> None:
        """Wait until every document handed to :attr:`writer`, or to another store's on this catalog, is written.

        The other stores are those open on the same catalog in this process (a plan given the
        location rather than the store opens one of its own); raise :class:`StoreError` if a
        document could not be written.
        """
        for writer in list(_WRITERS.get(self._catalog, ())):
            writer.flush()

    def _embedded(self, path: Path):
        from tiled.catalog import from_uri as catalog_from_uri
        from tiled.client import Context, from_context
        from tiled.server.app import build_app

        # the in-process server's start-up line ("Tiled version ...") is a server log, not the user's output
        logging.getLogger("tiled.server.app").setLevel(logging.WARNING)
        # absolute and normalized (symbolic links kept): tiled records the files by absolute URI,
        # and a relative place would be recorded as such for the tables (_relocate)
        path = Path(os.path.normpath(path.absolute()))
        try:
            (path / "data").mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreError(f"run store: cannot create {path}: {exc.strerror or exc}") from None
        if not os.access(path / "data", os.W_OK):
            raise StoreError(f"run store: {path} is not writable")
        db = path / "catalog.db"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # tiled's in-process client warns about httpx/starlette
            if not db.exists():
                _init_catalog(f"sqlite:///{db}")
            else:
                try:
                    old = _relocate(path, db)
                except sqlite3.Error as exc:
                    raise StoreError(f"run store: cannot read the catalog {db}: {_first_line(exc)}") from None
                if old is not None:
                    log.warning("run store %s: made at %s; its catalog now points at the files here", path, old)
            # a camera's HDF5 files are registered where they lie: under frames/, which tiled may read
            self._frames = path / "frames"
            self._frames.mkdir(exist_ok=True)
            adapter = catalog_from_uri(f"sqlite:///{db}",
                                       writable_storage=[str(path / "data"), f"duckdb:///{path / 'tables.duckdb'}"],
                                       readable_storage=[str(self._frames)])
            self._context = Context.from_app(build_app(adapter))
            try:
                client = from_context(self._context)
            except Exception as exc:  # noqa: BLE001 - e.g. the DuckDB tables locked by another process
                self._context.close()
                self._context = None
                first = _first_line(exc)
                raise StoreError(f"run store: cannot open {path}: {first} (an embedded store serves one process "
                                 f"at a time; several need a tiled server: BLUESKY_OFFSETS_STORE=http://...)") from None
        return client

    @property
    def frames_directory(self) -> Path:
        """Where a camera writes its files so that this embedded store can serve them.

        A tiled server serves the directories its own configuration names: for one, this raises
        StoreError.
        """
        if self._frames is None:
            raise StoreError(f"run store {self.location}: a tiled server reads the camera's files where its "
                             "configuration allows (readable_storage); give the camera that directory")
        return self._frames

    @property
    def writer(self):
        """The callback for ``RE.subscribe`` (one per store).

        Documents go to a ``TiledWriter`` on a thread of its own, in order; every read of the store
        waits for them (:meth:`flush`).
        """
        if self._writer is None:
            from bluesky_tiled_plugins import TiledWriter

            from bluesky_offsets.queued import QueuedCallback

            def failed(exc: BaseException) -> StoreError:
                return StoreError(f"run store {self.location}: a document could not be written: "
                                  f"{_first_line(exc)}")

            # queued: a catalog answers each request in 20-100 ms of Python, a run's end takes two
            # dozen (1.0 s for each beam-search run); written while the motors move instead.
            # max_array_size 0: every array as an array (up to 16 values went into the table as text, 8 digits)
            self._writer = QueuedCallback(TiledWriter(self._client, max_array_size=0), name="run-store-writer",
                                          error=failed)
            _WRITERS.setdefault(self._catalog, weakref.WeakSet()).add(self._writer)
        return self._writer

    def subscribe(self, RE) -> int:
        """Send ``RE``'s documents to this store; returns the subscription token."""
        return RE.subscribe(self.writer)

    def __getitem__(self, uid: str):
        try:
            return self.client[uid]
        except KeyError:
            raise KeyError(f"no run {uid!r} in the store at {self.location}") from None

    def __contains__(self, uid: str) -> bool:
        return uid in self.client

    def __len__(self) -> int:
        return len(self.client)

    def uids(self, n: int | None = None) -> list[str]:
        """Run uids, most recent last (the last ``n`` when given)."""
        keys = list(self.client.keys())
        return keys[-n:] if n else keys

    def latest(self, plan_names, **match) -> str | None:
        """Uid of the most recent successful run of one of ``plan_names`` whose start has ``match``'s values.

        ``plan_names`` is one name or several; successful: the stop document's ``exit_status`` is
        ``"success"``.  None if there is none.
        """
        from tiled.queries import Eq, In
        names = [plan_names] if isinstance(plan_names, str) else list(plan_names)
        results = self.client.search(In("start.plan_name", names))
        for key, value in match.items():
            results = results.search(Eq(f"start.{key}", value))
        for uid in reversed(list(results.keys())):
            stop = results[uid].metadata.get("stop") or {}
            if stop.get("exit_status") == "success":
                return uid
        return None

    def load_measurement(self, uid: str, *, table: ParameterTable | None = METRIXS) -> Measurement:
        """Configurations x histograms of a measurement run (checked against ``table``)."""
        m = measurement_from_run(self[uid])
        if table is not None:
            m.check_table(table)
        return m

    def close(self) -> None:
        """Write what is queued, then close (an embedded catalog's server ends with it).

        A document that could not be written raises :class:`StoreError` after the close.
        """
        writer, self._writer = self._writer, None
        try:
            if writer is not None:
                writer.close()
        finally:
            if self._context is not None:
                self._context.close()
                self._context = None

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"RunStore({self.location!r})"


def open_store(location: str | os.PathLike | None = None, **kwargs) -> RunStore:
    """Open (creating if needed) the run store at ``location`` (see :class:`RunStore`)."""
    return RunStore(location, **kwargs)


_SHARED: dict[str, RunStore] = {}


def shared_store(location: str | os.PathLike | None = None) -> RunStore:
    """One open :class:`RunStore` per location for the whole process.

    What plans that take a run uid read from when they are given no store (a queueserver
    session, a script), and what its RunEngine writes to (``shared_store().subscribe(RE)``).
    """
    loc = str(location) if location is not None else default_store_location()
    if loc not in _SHARED or _SHARED[loc]._context is None and store_path(loc) is not None:
        _SHARED[loc] = RunStore(loc)
    return _SHARED[loc]


def load_measurement(uid: str, location: str | os.PathLike | None = None,
                     table: ParameterTable | None = METRIXS) -> Measurement:
    """Load one measurement run by uid from the store at ``location`` (default store)."""
    with open_store(location) as store:
        return store.load_measurement(uid, table=table)


def as_measurement(obj, store: RunStore | str | None = None) -> Measurement:
    """A :class:`Measurement` from itself, a run uid, or a mapping of its fields."""
    if isinstance(obj, Measurement):
        return obj
    if isinstance(obj, str):
        if isinstance(store, RunStore):
            return store.load_measurement(obj)
        return load_measurement(obj, store)
    if isinstance(obj, Mapping):
        return Measurement(**obj)
    raise TypeError(f"cannot make a measurement from {type(obj).__name__}")
