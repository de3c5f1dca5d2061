"""Shared test fixtures.

EPICS: IOCs run in subprocesses on 127.0.0.1 only, each on its own port.
A pool of free ports is reserved when this file is imported and put into
``EPICS_CA_ADDR_LIST`` (``127.0.0.1:PORT ...``, ``EPICS_CA_AUTO_ADDR_LIST=NO``)
*before* any Channel Access client library reads the environment, so the
in-process clients (ophyd's caproto layer, ophyd-async's aioca) find every IOC
a test starts; each IOC gets a unique PV prefix so that a stopped IOC's
channels never alias a new one.  Subprocess clients (``caproto-get`` ...)
get ``IocProcess.env`` with the IOC's own port.

Fixtures
--------
ioc_factory
    ``start(module="sim_iocs.metrixs", args=(), ready=...) -> IocProcess``;
    everything it started is stopped at the end of the test.
metrixs_ioc
    One METRIXS simulation IOC for the whole session (mild hidden offsets,
    beam on the screen at the start position, fast motors, 3000 rays).
"""

from __future__ import annotations

import itertools
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sim_iocs.ports import free_port, loopback_env, stop_process_group

_POOL_SIZE = 8


def _free_port() -> int:
    """A port free for both TCP and UDP on loopback (EPICS uses the same number for both)."""
    return free_port()


CA_PORTS: list[int] = []
while len(CA_PORTS) < _POOL_SIZE:
    p = _free_port()
    if p not in CA_PORTS:
        CA_PORTS.append(p)
_free_ports = list(CA_PORTS)
os.environ["EPICS_CA_ADDR_LIST"] = " ".join(f"127.0.0.1:{p}" for p in CA_PORTS)
os.environ["EPICS_CA_AUTO_ADDR_LIST"] = "NO"
os.environ.setdefault("EPICS_CA_REPEATER_PORT", str(_free_port()))
# IOCs send beacons to a repeater; none runs here, so a UDP sink takes them (else: ICMP errors in the IOC log).
_beacon_sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
_beacon_sink.bind(("127.0.0.1", 0))
BEACON_PORT = _beacon_sink.getsockname()[1]
os.environ.setdefault("EPICS_CA_CONN_TMO", "5")
os.environ.setdefault("MPLBACKEND", "Agg")


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker more than the cores; the IOC demos wait on their subprocesses and the
    IOC tests on Channel Access, and a third worker fills those waits (CI: 2 cores)."""
    return (os.cpu_count() or 1) + 1


def _threads_per_worker() -> int | None:
    """pytest-xdist's workers already fill the cores: each gets its share of them as torch's
    threads (and so do the demos and IOCs it starts, through the environment).  A fit's small
    tensors gain little wall time from a second thread and burn CPU the other worker needs."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    return max(1, (os.cpu_count() or 1) // workers) if workers else None


_THREADS = _threads_per_worker()
if _THREADS is not None:
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[_var] = str(_THREADS)
    import torch
    torch.set_num_threads(_THREADS)

_prefix_counter = itertools.count(1)


def _plain(data):
    """A caproto sync-client reading as a Python scalar or string."""
    if not hasattr(data, "dtype"):  # DBR_STRING: a list of bytes
        data = [d.decode() if isinstance(d, bytes) else d for d in data]
        return data[0] if len(data) == 1 else data
    if data.dtype.kind == "S":
        return data[0].decode() if len(data) == 1 else [d.decode() for d in data]
    if data.dtype.kind == "u" and data.dtype.itemsize == 1:
        return data.tobytes().split(b"\0", 1)[0].decode()
    return data[0].item() if len(data) == 1 else data


class IocProcess:
    """An IOC subprocess on loopback with its own port; stop() always kills it (and its children)."""

    def __init__(self, module: str, args, prefix: str, port: int, log_path: Path):
        self.module, self.prefix, self.port, self.log_path = module, prefix, port, log_path
        self.env = dict(os.environ, **loopback_env(port, BEACON_PORT))
        self._log = open(log_path, "w")
        self.proc = subprocess.Popen([sys.executable, "-m", module, "--prefix", prefix, *map(str, args)],
                                     env=self.env, stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)

    def log(self) -> str:
        try:
            return self.log_path.read_text()
        except OSError:
            return ""

    def wait_ready(self, pv: str, value=None, timeout: float = 60.0) -> None:
        """Wait until ``pv`` answers (and equals ``value`` when given)."""
        from caproto.sync.client import read
        deadline = time.monotonic() + timeout
        last = None
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"IOC {self.module} exited with {self.proc.returncode}:\n{self.log()[-3000:]}")
            try:
                resp = read(pv, timeout=1.0, repeater=False)
                last = _plain(resp.data)
                if value is None or last == value:
                    return
            except Exception as exc:  # not up yet
                self._last_error = exc
            time.sleep(0.2)
        self.stop()
        raise TimeoutError(f"IOC {self.module} not ready ({pv} = {last!r}, {getattr(self, '_last_error', '')!r}):\n{self.log()[-3000:]}")

    def stop(self, timeout: float = 10.0) -> None:
        stop_process_group(self.proc, timeout)
        self._log.close()
        if self.port not in _free_ports:
            _free_ports.append(self.port)


def start_ioc(module: str, args=(), *, log_dir: Path, prefix: str | None = None,
              ready: str | None = None, ready_value=None, timeout: float = 60.0) -> IocProcess:
    """Start an IOC module (``python -m module --prefix P ...``) on a port of the pool.

    ``ready`` is a PV suffix (after the prefix) polled until it answers
    (and equals ``ready_value`` when given).
    """
    if not _free_ports:
        raise RuntimeError(f"all {_POOL_SIZE} CA ports of the test pool are in use")
    port = _free_ports.pop(0)
    prefix = prefix or f"TST{next(_prefix_counter)}x{port}:"
    ioc = IocProcess(module, args, prefix, port, log_dir / f"ioc-{prefix.rstrip(':')}.log")
    try:
        if ready:
            ioc.wait_ready(prefix + ready, ready_value, timeout)
    except BaseException:
        ioc.stop()
        raise
    return ioc


@pytest.fixture
def ioc_factory(tmp_path):
    """Start IOCs for one test; all are stopped afterwards."""
    started: list[IocProcess] = []

    def start(module: str = "sim_iocs.metrixs", args=(), **kw) -> IocProcess:
        kw.setdefault("log_dir", tmp_path)
        ioc = start_ioc(module, args, **kw)
        started.append(ioc)
        return ioc

    yield start
    for ioc in started:
        ioc.stop()


# A hidden truth with the beam on the screen at the start position (box centre):
# small offsets in the sensitive axes, non-zero everywhere it is harmless.
MILD_TRUTH = {
    "offsets": {"E1.rotationXerror": 0.05, "E2.rotationXerror": -0.05, "M1_Cylinder.rotationXerror": 0.03,
                "E2.translationYerror": 0.04, "ExitSlit.translationZerror": 0.1, "E1.rotationYerror": -0.1,
                "M1_Cylinder.radius": 0.05, "E2.longHalfAxisA": -0.05},
}

METRIXS_IOC_ARGS = ("--rays", 3000, "--move-time", 0.5, "--accel-time", 0.02, "--tick", 0.02)


def start_metrixs_ioc(log_dir: Path, truth: dict | None = None, extra=()) -> IocProcess:
    """The METRIXS simulation IOC with a truth dict (written next to its log) and fast test settings."""
    path = Path(log_dir) / f"truth-{next(_prefix_counter)}.json"
    path.write_text(json.dumps(MILD_TRUTH if truth is None else truth))
    return start_ioc("sim_iocs.metrixs", ["--truth", path, *METRIXS_IOC_ARGS, *extra], log_dir=Path(log_dir),
                     ready="chamber:Message", ready_value="ready", timeout=90)


@pytest.fixture(scope="session")
def metrixs_ioc(tmp_path_factory):
    ioc = start_metrixs_ioc(tmp_path_factory.mktemp("metrixs_ioc"), extra=("--list-pvs",))
    ioc.truth = MILD_TRUTH
    yield ioc
    ioc.stop()


class CaClient:
    """Small Channel Access client for tests (caproto's threading client; channels cached).

    ``get(pv)`` returns a scalar, string or numpy array; ``put(pv, value, wait=True)``
    waits for put-completion; ``caget``/``caput`` CLI tools are reachable through
    ``IocProcess.env``.
    """

    def __init__(self):
        from caproto.threading.client import Context
        self.ctx = Context()
        self._pvs = {}

    def pv(self, name: str):
        if name not in self._pvs:
            (self._pvs[name],) = self.ctx.get_pvs(name, timeout=5)
            self._pvs[name].wait_for_connection(timeout=10)
        return self._pvs[name]

    def get(self, name: str, *, as_string: bool = False):
        from caproto import ChannelType
        kw = {"data_type": ChannelType.STRING} if as_string else {}
        return _plain(self.pv(name).read(timeout=10, **kw).data)

    def put(self, name: str, value, *, wait: bool = True, timeout: float = 30):
        from caproto import ChannelType
        kw = {}
        if isinstance(value, str):  # enum strings and strings
            value, kw = [value], {"data_type": ChannelType.STRING}
        return self.pv(name).write(value, wait=wait, notify=wait, timeout=timeout, **kw)

    def close(self):
        self.ctx.disconnect()


@pytest.fixture(scope="session")
def ca():
    client = CaClient()
    yield client
    client.close()


@pytest.fixture(scope="session")
def ca_tools():
    """Paths of the caproto command-line tools of this interpreter's environment."""
    import shutil
    bindir = Path(sys.executable).parent
    tools = {}
    for name in ("caproto-get", "caproto-put", "caproto-monitor"):
        path = bindir / name
        tools[name] = str(path) if path.exists() else shutil.which(name)
        if tools[name] is None:
            raise RuntimeError(f"{name} not found next to {sys.executable} or on PATH (caproto installed?)")
    return tools


@pytest.fixture(scope="session")
def run_store(tmp_path_factory):
    """One embedded run store (tiled catalog in a temporary directory) for the session:
    creating a catalog costs seconds, so tests share it."""
    from bluesky_offsets.store import open_store
    store = open_store(tmp_path_factory.mktemp("run_store"))
    yield store
    store.close()


def pytest_collection_modifyitems(config, items):
    """The longest first, so that pytest-xdist's workers end together.

    pytest-xdist (``--dist loadscope --no-loadscope-reorder``, pyproject) gives each module, or
    each class, to one worker in the order of the items, so that module fixtures (a measured
    beamline, a trained model) are built once; each IOC acceptance demo is a class of its own.
    (``--dist loadgroup`` would group by ``xdist_group`` marks, but with pytest 9.2 it silently
    does not: pytest-xdist #1386.)  Order: tests marked ``slow`` first, the longest timeout
    first among them (the demos), then the rest in their order."""
    def weight(item):
        timeout = item.get_closest_marker("timeout")
        return (item.get_closest_marker("slow") is None, -(timeout.args[0] if timeout and timeout.args else 0))
    items.sort(key=weight)
