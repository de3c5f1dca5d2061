"""What the benchmarks record about the machine they ran on."""

import os
import platform
import sys
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name as ``/proc/cpuinfo`` gives it, else what :mod:`platform` knows."""
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return cpu


def machine() -> str:
    """CPU model, core count and Python version."""
    return f"{cpu_model()}, {os.cpu_count()} cores, Python {platform.python_version()}"


def machine_info() -> dict:
    """The machine as a result file records it (``benchmarks/results.py``).

    Returns
    -------
    dict
        ``description`` (:func:`machine`), ``cpu``, ``cores``, ``python``, and the versions of
        torch and rayx and the GPU's name where the benchmark had loaded them.
    """
    info = {"description": machine(), "cpu": cpu_model(), "cores": os.cpu_count(),
            "python": platform.python_version()}
    # only what the benchmark imported: importing torch here would cost seconds for nothing
    torch = sys.modules.get("torch")
    if torch is not None:
        info["torch"] = torch.__version__
        if torch.cuda.is_available():
            info["gpu"] = torch.cuda.get_device_name(0)
    rayx = sys.modules.get("rayx")
    if rayx is not None:
        info["rayx"] = getattr(rayx, "__version__", "unknown")
    return {k: v for k, v in info.items() if v is not None}  # os.cpu_count() may not know
