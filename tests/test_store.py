"""The run store: embedded persistent tiled catalog, tiled server URL, measurements as arrays.

Runs here come from a RunEngine reading ophyd-async soft signals shaped like the
focus chamber, so the store is tested on its own; the scans against the IOC
(tests/test_plans.py) load their runs from the store too.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import bluesky.plan_stubs as bps
import numpy as np
import pytest
from bluesky import RunEngine

from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.store import ENV_STORE, default_store_location, open_store


@pytest.fixture(scope="module")
def RE():
    return RunEngine({}, call_returns_result=True)


@pytest.fixture(scope="module")
def chamber(RE):
    from ophyd_async.core import Array1D, StandardReadable, init_devices, soft_signal_rw

    class SoftChamber(StandardReadable):
        def __init__(self, name=""):
            with self.add_children_as_readables():
                self.hist_x = soft_signal_rw(Array1D[np.float64], np.zeros(50))
                self.hist_y = soft_signal_rw(Array1D[np.float64], np.zeros(50))
                self.total_counts = soft_signal_rw(int, 0)
            super().__init__(name=name)

    with init_devices():
        ch = SoftChamber()
    return ch


def measurement_run(chamber, configs, hists, md=None):
    """A run shaped like ``measure_configurations``: configurations in the start document,
    one event per configuration."""
    start = {"plan_name": "measure_configurations", "configurations": np.asarray(configs).tolist(),
             "parameter_names": list(METRIXS.names), "parameter_table_version": METRIXS.version,
             "truth_id": "abc123", **(md or {})}
    yield from bps.open_run(start)
    for hx, hy in hists:
        yield from bps.mv(chamber.hist_x, hx, chamber.hist_y, hy, chamber.total_counts, int(hx.sum() * 1000))
        yield from bps.trigger_and_read([chamber])
    yield from bps.close_run()


def _data(n, seed=0):
    rng = np.random.default_rng(seed)
    configs = METRIXS.sample_uniform(n, rng)
    hists = [(rng.random(50) / 100, rng.random(50) / 100) for _ in range(n)]
    return configs, hists


def test_default_location_is_a_user_data_dir_or_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv(ENV_STORE, raising=False)
    loc = default_store_location()
    assert loc.endswith(os.path.join("bluesky-offsets", "runs")) and os.path.isabs(loc)
    monkeypatch.setenv(ENV_STORE, str(tmp_path / "elsewhere"))
    assert default_store_location() == str(tmp_path / "elsewhere")


def test_embedded_store_persists_and_loads_measurement(RE, chamber, run_store, monkeypatch):
    configs, hists = _data(4)
    token = run_store.subscribe(RE)
    (uid,) = RE(measurement_run(chamber, configs, hists)).run_start_uids
    RE.unsubscribe(token)
    m = run_store.load_measurement(uid)
    assert isinstance(m, Measurement) and len(m) == 4 and m.uid == uid
    np.testing.assert_allclose(m.configurations, configs)
    np.testing.assert_allclose(m.hist_x, [h[0] for h in hists])
    np.testing.assert_allclose(m.hist_y, [h[1] for h in hists])
    assert m.histograms.shape == (4, 100) and m.truth_id == "abc123"
    assert m.metadata["exit_status"] == "success"
    # a second catalog opened on the same directory (the default location, from the
    # environment here) reads the run from disk
    monkeypatch.setenv(ENV_STORE, run_store.location)
    with open_store() as again:
        assert again.location == run_store.location and uid in again
        m2 = again.load_measurement(uid)
    np.testing.assert_allclose(m2.hist_x, m.hist_x)
    np.testing.assert_allclose(m2.configurations, m.configurations)
    # the catalog was created in this process (not by tiled's `catalog init` subprocess) and
    # stamped as that command stamps it: tiled's own check of the schema's revision passes
    import asyncio
    from pathlib import Path

    from sqlalchemy.ext.asyncio import create_async_engine
    from tiled.alembic_utils import check_database
    from tiled.catalog.core import ALL_REVISIONS, REQUIRED_REVISION

    async def check():
        engine = create_async_engine(f"sqlite+aiosqlite:///{Path(run_store.location) / 'catalog.db'}")
        try:
            await check_database(engine, REQUIRED_REVISION, ALL_REVISIONS)
        finally:
            await engine.dispose()
    asyncio.run(check())


def test_a_moved_copied_or_relative_store_reads_its_own_files(RE, chamber, tmp_path, monkeypatch, caplog):
    """tiled addresses a run's files by absolute URI: a store moved or copied elsewhere, or made
    with a relative path and opened from another directory, points its catalog at its own files
    when opened (once, said in one log line) and loads every run."""
    import shutil

    configs, hists = _data(3, seed=4)
    monkeypatch.chdir(tmp_path)
    with open_store("runs") as made:  # relative, as `--store runs` makes it
        token = made.subscribe(RE)
        (uid,) = RE(measurement_run(chamber, configs, hists)).run_start_uids
        RE.unsubscribe(token)
    shutil.copytree(tmp_path / "runs", tmp_path / "copy")
    shutil.move(tmp_path / "runs", tmp_path / "moved")
    # the copy as a store made with a relative path recorded it before new stores were made absolute:
    # its tables by the relative URI
    import sqlite3
    with sqlite3.connect(tmp_path / "copy" / "catalog.db") as con:
        con.execute("UPDATE assets SET data_uri = 'duckdb://localhost/runs/tables.duckdb' "
                    "WHERE data_uri LIKE 'duckdb:%'")
    con.close()
    monkeypatch.chdir(tmp_path.parent)  # elsewhere
    for place in ("moved", "copy"):
        with caplog.at_level("WARNING", logger="bluesky_offsets.store"):
            caplog.clear()
            with open_store(tmp_path / place) as store:
                m = store.load_measurement(uid)
            with open_store(str(tmp_path / place) + "/") as again:  # once: the catalog points here now
                np.testing.assert_allclose(again.load_measurement(uid).hist_y, m.hist_y)
        np.testing.assert_allclose(m.hist_x, [h[0] for h in hists])
        assert [r.getMessage() for r in caplog.records] == [f"run store {tmp_path / place}: made at "
                                                           f"{tmp_path / 'runs' if place == 'moved' else 'runs'}; "
                                                           "its catalog now points at the files here"], place


def test_load_errors_are_clear(RE, chamber, run_store):
    configs, hists = _data(1)

    def not_a_measurement():
        yield from bps.open_run({"plan_name": "count"})
        yield from bps.trigger_and_read([chamber])
        yield from bps.close_run()

    token = run_store.subscribe(RE)
    try:
        (other,) = RE(not_a_measurement()).run_start_uids
        (old,) = RE(measurement_run(chamber, configs, hists, md={"parameter_table_version": "000000000000"})
                    ).run_start_uids
    finally:
        RE.unsubscribe(token)
    with pytest.raises(KeyError, match="no run 'nope'"):
        run_store.load_measurement("nope")
    with pytest.raises(ValueError, match="not a measure_configurations run"):
        run_store.load_measurement(other)
    with pytest.raises(ValueError, match="parameter-table version 000000000000"):
        run_store.load_measurement(old)
    assert len(run_store.load_measurement(old, table=None)) == 1
    with pytest.raises(ValueError, match="1 configurations but 2 x"):
        Measurement(configs, np.zeros((2, 50)), np.zeros((2, 50)))


def test_tiled_server_url(RE, chamber, tmp_path):
    from conftest import _free_port
    port = _free_port()
    log = open(tmp_path / "tiled.log", "w")
    server = subprocess.Popen([os.path.join(os.path.dirname(sys.executable), "tiled"), "serve", "catalog", "--temp",
                               "--api-key", "secret", "--host", "127.0.0.1", "--port", str(port)],
                              stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        import httpx
        deadline = time.monotonic() + 90
        while True:
            try:
                httpx.get(f"http://127.0.0.1:{port}/api/v1/", timeout=1)
                break
            except httpx.HTTPError:
                assert server.poll() is None and time.monotonic() < deadline, (tmp_path / "tiled.log").read_text()
                time.sleep(0.3)
        configs, hists = _data(2, seed=1)
        store = open_store(f"http://127.0.0.1:{port}", api_key="secret")
        token = store.subscribe(RE)
        (uid,) = RE(measurement_run(chamber, configs, hists)).run_start_uids
        RE.unsubscribe(token)
        m = store.load_measurement(uid)
        np.testing.assert_allclose(m.hist_y, [h[1] for h in hists])
        assert uid in store.uids()
    finally:
        try:
            os.killpg(server.pid, signal.SIGTERM)
            server.wait(10)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            os.killpg(server.pid, signal.SIGKILL)
        log.close()


def test_camera_profiles_are_kept_only_when_they_add_up_to_the_histograms():
    """A detector backend without rays (the surrogate) publishes zero profiles: they are ignored."""
    from bluesky_offsets.store import _profiles
    from bluesky_offsets.physics.twin import CAMERA, HistogramSpec
    rng = np.random.default_rng(0)
    px = np.stack([CAMERA.histograms(rng.normal(0, 0.1, 900), rng.normal(0, 0.02, 900), 3000)[0] for _ in range(2)])
    py = np.stack([CAMERA.histograms(rng.normal(0, 0.1, 900), rng.normal(0, 0.02, 900), 3000)[1] for _ in range(2)])
    hx, hy = CAMERA.rebin(px, py, HistogramSpec())
    start = {"profile": CAMERA.fingerprint()}
    keys = ["chamber-profile_x", "chamber-profile_y"]
    got = _profiles({keys[0]: px, keys[1]: py}, keys, {}, start, hx, hy)
    np.testing.assert_array_equal(got[0], px)
    np.testing.assert_array_equal(got[1], py)
    zeros = {keys[0]: np.zeros_like(px), keys[1]: np.zeros_like(py)}
    assert _profiles(zeros, keys, {}, start, hx, hy) == (None, None)
    assert _profiles({keys[0]: px, keys[1]: py}, keys, {}, {}, hx, hy) == (None, None)  # no binning recorded
    m = Measurement(np.tile(METRIXS.reference, (2, 1)), hx, hy, profile_x=px, profile_y=py, metadata=start)
    assert m.profile_spec == CAMERA


def test_writes_are_queued_and_every_read_sees_them(RE, chamber, tmp_path):
    """The writer works on a thread of its own while the RunEngine goes on; a read right after
    the run sees every document, and a document the catalog refuses stops the next one."""
    from bluesky_offsets.store import StoreError
    store = open_store(tmp_path / "runs")
    try:
        token = store.subscribe(RE)
        configs, hists = _data(3)
        for k in range(2):
            (uid,) = RE(measurement_run(chamber, configs, hists, {"k": k})).run_start_uids
            # no wait in between: a read waits for the queue, also through another store on the
            # same catalog (a plan given the location opens its own)
            with open_store(str(tmp_path / "runs") + "/") as other:
                assert other.load_measurement(uid).metadata["exit_status"] == "success"
            m = store.load_measurement(uid)
            assert np.allclose(m.hist_x, [h[0] for h in hists]) and m.metadata["exit_status"] == "success"
        assert len(store) == 2
        RE.unsubscribe(token)
        # the same run again: its uid is in the catalog already, tiled refuses the start document
        writer = store.writer
        run = store[uid].metadata
        writer("start", dict(run["start"]))
        with pytest.raises(StoreError, match="could not be written: 409"):
            store.flush()  # or a later document: raised once, in the RunEngine's thread
        writer("stop", dict(run["stop"]))
    finally:
        store.close()


def test_a_short_configuration_vector_comes_back_as_the_numbers_it_was(RE, tmp_path):
    """A described beamline of a few parameters: each frame's configuration (7 values) is read back
    bit for bit (the writer put arrays of up to 16 values into its table as text, 8 digits)."""
    from plans.measure import CommandedConfiguration
    store = open_store(tmp_path / "runs")
    try:
        token = store.subscribe(RE)
        dev = CommandedConfiguration(7, name="commanded")
        vectors = np.random.default_rng(3).normal(size=(2, 7)) * [1, 1, 1, 1, 1, 1825.0, 1000.0]
        names = [f"p{i}" for i in range(7)]

        def plan():
            yield from bps.open_run({"plan_name": "measure_configurations", "configurations": vectors.tolist(),
                                     "parameter_names": names})
            for i, v in enumerate(vectors):
                dev.update(i, v)
                yield from bps.trigger_and_read([dev])
            yield from bps.close_run()

        (uid,) = RE(plan()).run_start_uids
        RE.unsubscribe(token)
        ds = store[uid]["primary"].read()
        np.testing.assert_array_equal(np.asarray(ds["configuration"]), vectors)
    finally:
        store.close()


def test_a_queued_callback_keeps_the_order_and_reports_failures(caplog):
    from bluesky_offsets.queued import QueuedCallback
    seen = []

    def cb(name, doc):
        if doc.get("bad"):
            raise ValueError("cannot draw this")
        seen.append((name, doc["i"]))

    q = QueuedCallback(cb, error=lambda exc: RuntimeError(f"failed: {exc}"))
    for i in range(50):
        q("event", {"i": i})
    q.flush()
    assert seen == [("event", i) for i in range(50)]
    q("event", {"i": 50, "bad": True})
    q("event", {"i": 51})  # dropped: the failure is raised at the next document or flush
    with pytest.raises(RuntimeError, match="failed: cannot draw this"):
        q.flush()
    q.close()
    assert seen[-1] == ("event", 49)
    with pytest.raises(RuntimeError, match="closed"):
        q("event", {"i": 52})
    # without an error type (a live view): logged once, and the documents after it are drawn
    seen.clear()
    q = QueuedCallback(cb)
    with caplog.at_level("WARNING"):
        for i in range(3):
            q("event", {"i": i, "bad": i == 1})
        q.close()
    assert seen == [("event", 0), ("event", 2)]
    assert sum("cannot draw this" in r.getMessage() for r in caplog.records) == 1


def test_a_measurements_footprints_are_written_paced_and_the_last_state_at_flush(tmp_path):
    """Every comparison draws the model over the measured frames; the figure is written when the
    measurement stops, again only ``every`` seconds later, and as last drawn at ``flush`` (through
    the queue's thread as well as called directly)."""
    from bluesky_offsets.live import LiveFootprints, in_background
    from bluesky_offsets.live import flush as flush_live

    h = np.zeros(50)
    h[20:30] = 1.0

    def run(uid, start, stream, events):
        yield "start", {"uid": uid, "time": 0.0, **start}
        yield "descriptor", {"uid": uid + "-d", "run_start": uid, "name": stream}
        for k, data in enumerate(events):
            yield "event", {"descriptor": uid + "-d", "seq_num": k + 1, "data": data}
        yield "stop", {"run_start": uid}

    def measurement(n=2):
        return run("m", {"plan_name": "measure_configurations", "configurations": [[0.0]] * n}, "primary",
                   [{"hist_x": h, "hist_y": h}] * n)

    def comparison(k, n=2):
        return run(f"c{k}", {"measurement_uid": "m", "version_label": f"model {k}"}, "misfit",
                   [{"config_index": i, "model_hist_x": h, "model_hist_y": h, "chi2_reduced": 1.0 + k}
                    for i in range(n)])

    def counted(fp):
        writes, save = [], fp._save
        fp._save = lambda uid: (writes.append(fp.figures[uid].axes[0].get_title()), save(uid))
        return writes

    for queued in (False, True):
        fp = LiveFootprints(tmp_path / str(queued), show=False, every=3600.0)
        writes = counted(fp)
        cb = in_background(fp) if queued else fp
        for docs in (measurement(), comparison(0), comparison(1), comparison(2)):
            for name, doc in docs:
                cb(name, doc)
        flush_live([cb])
        # written when the measurement stopped, not as the three comparisons stopped (within the
        # hour), then at flush with the last comparison drawn; a second flush writes nothing
        assert writes == ["configuration 0", "configuration 0 — model 2: χ²/dof 3"], (queued, writes)
        flush_live([cb])
        assert len(writes) == 2
        assert (tmp_path / str(queued) / "footprints-m.png").stat().st_size > 5_000
    # with every=0 each run that drew writes
    fp = LiveFootprints(tmp_path / "each", show=False, every=0.0)
    writes = counted(fp)
    for docs in (measurement(1), comparison(0, 1), comparison(1, 1)):
        for name, doc in docs:
            fp(name, doc)
    assert len(writes) == 3
