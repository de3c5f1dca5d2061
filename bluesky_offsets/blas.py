"""The BLAS kernels pinned so that another CPU's arithmetic gives the same digits.

See :func:`pin_kernels` and docs/explanations/diagnosis.md, "Another CPU's arithmetic".
"""

from __future__ import annotations

import functools
import os
import platform


def pin_kernels() -> None:
    """Pin MKL's and OpenBLAS's kernels to one code path each, unless the environment says otherwise.

    MKL's (torch's BLAS) kernels go to its one vendor-neutral code path on x86-64, and
    OpenBLAS's (numpy's) to its AVX2 kernels where the CPU has AVX2. Where the CPU has AVX-512,
    numpy's and torch's own vectorized functions run their AVX2 variants
    (``NPY_DISABLE_CPU_FEATURES``, ``ATEN_CPU_CAPABILITY=avx2``): numpy's float64 ``exp``,
    ``log``, ``arctan``, ``power`` and others round otherwise in their AVX-512 variants, and the
    designed measurement then chooses other frames.

    Why: both libraries pick their kernels by CPU, and their sums then round differently; a fit
    on RAYX's hard counts amplifies such a last-bit difference along its path (the normal
    equations of 34 offsets are ill-conditioned; docs/explanations/diagnosis.md, "Another CPU's
    arithmetic").
    MKL honours a named branch such as ``AVX2`` on Intel CPUs only and runs its automatic
    dispatch elsewhere, so an AMD and an Intel CPU took different paths; ``COMPATIBLE`` is the
    one branch it runs alike on every x86-64 CPU; its cost is the CPU's: none measurable on an Intel
    Xeon, 1.6× the per-ray Jacobian's time on an AMD EPYC (docs/explanations/diagnosis.md).
    It must happen before numpy or torch is imported: the command line calls it first thing,
    the test suite through its plugin (:mod:`bluesky_offsets.testing`), and every process they
    start (the IOC, the Dask workers) inherits the environment.
    ``MKL_CBWR=AUTO``, ``OPENBLAS_CORETYPE=``, ``NPY_DISABLE_CPU_FEATURES=`` and
    ``ATEN_CPU_CAPABILITY=default`` in the environment undo it.
    """
    if x86_64():
        os.environ.setdefault("MKL_CBWR", "COMPATIBLE")
    if x86_with_avx2():
        os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")
    if _cpu_flag("avx512f"):
        # numpy's float64 exp, log, arctan, power... and torch's vector kernels have AVX-512
        # variants that round otherwise than the AVX2 ones every x86-64 CPU of today runs
        os.environ.setdefault("NPY_DISABLE_CPU_FEATURES", numpy_avx512_targets())
        os.environ.setdefault("ATEN_CPU_CAPABILITY", "avx2")


def numpy_avx512_targets() -> str:
    """The names numpy gives its AVX-512 dispatch targets (2.4 groups them as X86_V4), read without importing it."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        major, minor = (int(x) for x in version("numpy").split(".")[:2])
    except (PackageNotFoundError, ValueError):
        major, minor = 0, 0
    if (major, minor) >= (2, 4):
        return "X86_V4 AVX512_ICL AVX512_SPR"
    return "AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR"


def x86_64() -> bool:
    """Whether this machine's CPU is x86-64 (as :func:`platform.machine` names it)."""
    return platform.machine().lower() in ("x86_64", "amd64")


def x86_with_avx2() -> bool:
    """An x86-64 CPU with AVX2, as Linux reports it (elsewhere: False, the libraries' own choice)."""
    return _cpu_flag("avx2")


def _cpu_flag(flag: str) -> bool:
    """Whether Linux reports ``flag`` for this x86-64 CPU (elsewhere: False)."""
    return flag in _cpu_flags()


@functools.cache
def _cpu_flags() -> frozenset[str]:
    """The words of every ``flags`` line Linux reports for this x86-64 CPU, read once (elsewhere: none)."""
    if not x86_64():
        return frozenset()
    try:
        with open("/proc/cpuinfo") as f:
            return frozenset(w for line in f if line.startswith("flags") for w in line.split())
    except OSError:
        return frozenset()
