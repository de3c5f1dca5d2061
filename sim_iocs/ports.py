"""Loopback ports for simulated IOCs (tests, benchmarks, demos)."""

import socket


def free_port(host: str = "127.0.0.1", attempts: int = 200) -> int:
    """A port free for both TCP and UDP on ``host`` (EPICS uses the same number for both)."""
    for _ in range(attempts):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as t:
            t.bind((host, 0))
            port = t.getsockname()[1]
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
                try:
                    u.bind((host, port))
                except OSError:
                    continue
        return port
    raise RuntimeError(f"no free TCP+UDP port pair on {host}")


def loopback_env(port: int, beacon_port: int | None = None) -> dict[str, str]:
    """EPICS variables for an IOC on ``127.0.0.1:port`` and for clients that talk only to it."""
    env = {"EPICS_CA_ADDR_LIST": f"127.0.0.1:{port}", "EPICS_CA_AUTO_ADDR_LIST": "NO",
           "EPICS_CA_SERVER_PORT": str(port), "EPICS_CAS_SERVER_PORT": str(port),
           "EPICS_CAS_INTF_ADDR_LIST": "127.0.0.1", "EPICS_CAS_BEACON_ADDR_LIST": "127.0.0.1",
           "EPICS_CAS_AUTO_BEACON_ADDR_LIST": "NO", "PYTHONUNBUFFERED": "1"}
    if beacon_port is not None:
        env["EPICS_CAS_BEACON_PORT"] = str(beacon_port)
    return env


def stop_process_group(proc, timeout: float = 10.0) -> None:
    """SIGINT the IOC process, then SIGKILL its whole session: its frame workers must not survive it."""
    import os
    import signal
    import subprocess

    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            pass
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    try:
        proc.wait(5)
    except subprocess.TimeoutExpired:
        pass
