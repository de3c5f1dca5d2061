"""How RAYX is called: its process-global random generator seeded, a beamline imported from memory.

Shared by the RAYX twin (:mod:`bluesky_offsets.physics.twin`) and the torch engine's RML twin
(:mod:`bluesky_offsets.physics.engine.rml_twin`), which draws its source rays with RAYX.
"""

from __future__ import annotations

import functools
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.streams import stream

_seeded_pids: set[int] = set()


@functools.cache
def _fix_seed_fn():
    """``rayx::fixSeed`` from RAYX's compiled module, through ctypes (looked up once)."""
    import ctypes

    import rayx
    fn = ctypes.CDLL(rayx.core.__file__)._ZN4rayx7fixSeedEj
    fn.argtypes, fn.restype = [ctypes.c_uint32], None
    return fn


def fix_seed(seed: int) -> None:
    """Seed RAYX's global random generator (``rayx::fixSeed``, not exposed to Python).

    RAYX draws each trace's seed from a process-global Mersenne twister that
    starts from the same default state in every process, so without this,
    parallel workers would repeat each other's noise.
    """
    _fix_seed_fn()(int(seed) & 0xFFFFFFFF)


def ensure_random_stream() -> None:
    """Seed RAYX once per process from the OS: parallel workers draw independent noise."""
    pid = os.getpid()
    if pid not in _seeded_pids:
        fix_seed(int.from_bytes(os.urandom(4), "little"))
        _seeded_pids.add(pid)


def import_rml(beamline):
    """RAYX's beamline from ours.

    RAYX imports from a path only; the file holds the state traced
    (a simulated beamline's hidden truth included), so on Linux it lives in memory
    (``memfd_create``): no file another process could open by name, none left by a killed worker.
    Elsewhere it lives only for the import in the system's temporary folder.
    """
    import rayx
    text = beamline.to_xml().encode()
    if hasattr(os, "memfd_create") and os.path.isdir("/proc/self/fd"):
        with os.fdopen(os.memfd_create("bluesky-offsets.rml"), "wb") as f:
            f.write(text)
            f.flush()
            return rayx.import_beamline(f"/proc/self/fd/{f.fileno()}")
    fd, name = tempfile.mkstemp(prefix="bluesky-offsets-", suffix=".rml")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(text)
        return rayx.import_beamline(name)
    finally:
        os.unlink(name)


@functools.lru_cache(maxsize=16)
def _import_error(text: bytes) -> str | None:
    """What RAYX says on importing the RML ``text`` in a child process; None where it imports it."""
    code = "import rayx, sys; rayx.import_beamline(sys.argv[1])"
    with tempfile.TemporaryDirectory(prefix="bluesky-offsets-") as tmp:
        path = Path(tmp) / "probe.rml"
        path.write_bytes(text)
        proc = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=120)
    if proc.returncode == 0:
        return None
    # RAYX's lines look like "\x1b[31m[   xml.cpp:435] parseInt failed for "x"": its words only
    plain = re.sub(r"\x1b\[[0-9;]*m", "", proc.stderr + proc.stdout)
    lines = [re.sub(r"^\s*\[[^]]*\]", "", ln).strip() for ln in plain.splitlines()]
    said = [ln for ln in lines if ln and not ln.startswith("Terminating")]
    return "; ".join(said[-3:]) or f"exit status {proc.returncode}"


SOURCE_COLUMNS = ("position_x", "position_y", "position_z", "direction_x", "direction_y", "direction_z", "energy")
"""The columns of an emitted ray that :func:`source_rays` returns."""


def source_rays(rml, n_rays: int, seed: int) -> dict[str, np.ndarray]:
    """RAYX's draw of ``n_rays`` from the first source of ``rml`` (an ``RmlBeamline``), in its local frame.

    The source alone: RAYX draws its rays before any element, and tracing the rest costs ~40x more.
    Returns :data:`SOURCE_COLUMNS`, each ordered by the rays' path index.
    """
    from bluesky_offsets.physics.rml import RmlBeamline
    bl = RmlBeamline(rml.sources[:1], rml.version).copy()
    bl.sources[0].set("numberRays", int(n_rays))
    rb = import_rml(bl)
    fix_seed(seed)
    rays = rb.trace()
    check_emitted(rays, rml.source_label)
    obj, pid = np.asarray(rays.object_id), np.asarray(rays.path_id)
    first = np.flatnonzero(obj == 0)
    first = first[np.argsort(pid[first], kind="stable")]
    if len(first) != n_rays:
        raise RuntimeError(f"RAYX emitted {len(first)} source rays for {n_rays}")
    return {k: np.asarray(getattr(rays, k))[first] for k in SOURCE_COLUMNS}


GRID_RAYS = 10_000
"""The fewest rays of a grid source's grid (a matrix source: its RML's count where that is more)."""


def grid_rays(rml) -> int:
    """The rays of the grid that the frames of ``rml``'s grid source draw their photons from."""
    return max(int(rml.sources[0].get_float("numberRays")), GRID_RAYS)


def grid_draw(grid: int, n_rays: int, seed: int | None) -> np.ndarray:
    """Which of a grid's ``grid`` rays ``n_rays`` photons are: drawn with replacement, the same for a seed."""
    rng = np.random.default_rng(None if seed is None else stream(int(seed), "grid.photons"))
    return rng.integers(0, grid, int(n_rays))


def source_varies(rml) -> bool:
    """Whether the first source of ``rml`` emits other rays for another seed (a matrix source's grid does not)."""
    a, b = (source_rays(rml, 64, s) for s in (1, 2))
    if os.getpid() in _seeded_pids:  # the probe's seeds must not become this process's stream
        fix_seed(int.from_bytes(os.urandom(4), "little"))
    return any(not np.array_equal(a[k], b[k]) for k in SOURCE_COLUMNS)


def check_importable(path: str | Path) -> None:
    """Refuse, in one line, an RML that RAYX cannot import.

    RAYX ends the whole process on a parameter it cannot parse (a source without ``numberRays``:
    "parseInt failed … Terminating"), so it is tried once in a child process.
    """
    path = Path(path)
    error = _import_error(path.read_bytes())
    if error is not None:
        from importlib.metadata import version
        raise InputError(f"RML {path}: RAYX {version('rayx')} cannot import it: {error}")


def check_emitted(rays, source: str = "the source") -> None:
    """Refuse, in one line, a source whose emitted rays RAYX gives with non-finite positions or directions.

    RAYX 0.4.5's "Simple Undulator" emits such rays: every ray would silently miss the beamline.
    """
    emitted = np.asarray(rays.object_id) == 0  # a ray's first event: emitted by source 0
    for key in ("position_x", "position_y", "position_z", "direction_x", "direction_y", "direction_z"):
        if not np.isfinite(np.asarray(getattr(rays, key))[emitted]).all():
            from importlib.metadata import version
            raise InputError(f"{source}: RAYX {version('rayx')} emits rays with a non-finite "
                             f"{key.replace('_', ' ')}, so none can be traced (describe the beamline with "
                             "another source type)")
