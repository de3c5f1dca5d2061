"""bluesky-offsets: calibrate the digital twin of a beamline against the real one."""

import os as _os
import platform as _platform


def _pin_blas_kernels() -> None:
    """Pin MKL's (torch's BLAS) and OpenBLAS's (numpy's) kernels to their AVX2 code paths on an
    x86-64 CPU that has AVX2, unless the environment already says otherwise.

    Why: both libraries pick their kernels by CPU, and their sums then round differently; a fit
    on RAYX's hard counts amplifies such a last-bit difference along its path (the normal
    equations of 34 offsets are ill-conditioned), so the same command gave other fitted digits
    on another CPU (the README's analysis, emulated as an AVX2-only machine with
    ``ATEN_CPU_CAPABILITY=avx2 MKL_ENABLE_INSTRUCTIONS=AVX2 OPENBLAS_CORETYPE=Haswell``: chamber_z
    21.36 ± 0.9 mm instead of 21.44 ± 0.74, χ²/dof 3.66 instead of 3.87 after the offsets fit;
    the same verdict).  Pinned, the two gave the same bits: torch's own kernels are the same at
    any vector width (tests/test_fit.py).  Cost: about 7 % of a per-ray Jacobian on an AVX-512
    CPU (docs/benchmarks.md, "Per-ray Jacobian").  It must happen before numpy or torch is
    imported: the command line imports this package first, and every process it starts (the
    IOC, the Dask workers) inherits the environment; a session that imported numpy first keeps
    numpy's own choice.
    ``MKL_CBWR=AUTO`` and ``OPENBLAS_CORETYPE=`` (empty) in the environment undo it."""
    if _x86_with_avx2():
        _os.environ.setdefault("MKL_CBWR", "AVX2")
        _os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")


def _x86_with_avx2() -> bool:
    """An x86-64 CPU with AVX2, as Linux reports it (elsewhere: False, the libraries' own choice)."""
    if _platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    try:
        with open("/proc/cpuinfo") as f:
            return any(line.startswith("flags") and " avx2" in line for line in f)
    except OSError:
        return False


_pin_blas_kernels()


def __getattr__(name):
    """``bluesky_offsets.load_calibration``: loaded when first asked for (the package itself
    imports nothing heavy)."""
    if name in ("load_calibration", "write_calibration"):
        from bluesky_offsets.model import export
        return getattr(export, name)
    raise AttributeError(f"module 'bluesky_offsets' has no attribute {name!r}")
