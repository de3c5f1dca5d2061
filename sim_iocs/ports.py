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
