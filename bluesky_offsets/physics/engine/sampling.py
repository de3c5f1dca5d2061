"""The rays a trace starts from, and every random number it draws.

:func:`source_units` draws the point source's unit coordinates (RAYX's stream for
``sampling="rayx"``, torch's generator for ``"fast"``) and, for the fast stream, the later draws
(slit kicks, slope errors) up front (:class:`Draws`) or as rays meet their element
(:class:`LazyDraws`); seeded draws are cached.  :func:`source_rays` scales them by the source's
sizes (differentiable in them); :func:`rays_from_arrays` takes given rays (RAYX's own) instead.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.engine import random_streams as rnd
from bluesky_offsets.physics.engine.compiling import CompiledBeamline
from bluesky_offsets.physics.rml import RmlError


@dataclass
class Rays:
    """Rays in some frame; tensors (C or 1, N)."""

    x: torch.Tensor
    y: torch.Tensor
    z: torch.Tensor
    dx: torch.Tensor
    dy: torch.Tensor
    dz: torch.Tensor
    energy: torch.Tensor
    ctr: torch.Tensor | None = None  # RAYX's counters (sampling="rayx")

    def slice(self, a: int, b: int) -> Rays:
        """The rays ``a`` to ``b`` (exclusive) of every configuration."""
        def cut(t):
            return None if t is None else t[..., a:b]
        return Rays(*(cut(getattr(self, f.name)) for f in fields(self)))


@dataclass
class Draws:
    """The fast stream's random numbers, drawn up front so that chunking changes nothing.

    ``slits[name]`` (2, C|1, N) are the kicks' accepted draws (width, height), ``slopes[name]``
    (2, C|1, N) standard normals.
    """

    slits: dict[str, torch.Tensor]
    slopes: dict[str, torch.Tensor]

    def slice(self, a: int, b: int) -> Draws:
        """The draws of rays ``a`` to ``b`` (exclusive) of every configuration."""
        return Draws({k: v[..., a:b] for k, v in self.slits.items()},
                     {k: v[..., a:b] for k, v in self.slopes.items()})


def _generator(seed: int | None, device) -> torch.Generator:
    g = torch.Generator(device=device)
    g.manual_seed(int(seed) if seed is not None else int.from_bytes(os.urandom(8), "little") >> 1)
    return g


def _streams(seed, n_configs: int, common: bool) -> list[int | None]:
    """One seed per random stream.

    A sequence gives one per configuration as it is; else one shared stream (``common``) or
    ``seed + i`` for configuration ``i``.
    """
    if isinstance(seed, Sequence):
        seeds = [None if s is None else int(s) for s in seed]
        if len(seeds) != n_configs:
            raise InputError(f"{len(seeds)} seeds for {n_configs} configurations")
        return seeds
    if common:
        return [seed]
    if seed is None:
        return [None] * n_configs
    return [int(seed) + i for i in range(n_configs)]


def sample_source(bl: CompiledBeamline, n_rays: int, seed, *, sampling: str = "fast",
                  common: bool = True, batch_stream: bool = False) -> tuple[Rays, Draws | LazyDraws | None]:
    """Source rays (source frame) and, for the fast stream, every later draw.

    ``sampling="rayx"`` reproduces RAYX's point source for ``rayx::fixSeed(seed)``
    (RAYX-CONVENTIONS.md §3–4): 14 draws per ray in RAYX's order, counters carried on.
    ``batch_stream`` (fast sampling, one seed): every configuration its own rays, all drawn
    from one generator at once (a batch of many configurations pays one call per draw kind
    instead of one per configuration: the dataset's blocks).
    """
    units = source_units(bl, n_rays, seed, sampling=sampling, common=common, batch_stream=batch_stream)
    return source_rays(bl, units), units.draws


@dataclass
class SourceUnits:
    """What a trace's randomness is, apart from the beamline it meets.

    The source's unit draws (6 coordinates, each (C|1, N)) before the source's sizes scale them,
    the later draws of the fast stream and RAYX's counters.
    """

    coord: list[torch.Tensor]
    draws: Draws | LazyDraws | None
    ctr: torch.Tensor | None = None

    def take(self, configs: torch.Tensor, rays: torch.Tensor) -> SourceUnits:
        """The rays ``rays`` of configurations ``configs`` (K each), every one its own configuration.

        A leading axis of K, one ray each: (C|1, N) -> (K, 1).
        """
        def pick(t):
            return t[..., configs if t.shape[-2] > 1 else 0, rays][..., None]
        d = self.draws
        assert not isinstance(d, LazyDraws), "lazy draws are made in the trace: none to take"
        draws = None if d is None else Draws({k: pick(v) for k, v in d.slits.items()},
                                             {k: pick(v) for k, v in d.slopes.items()})
        return SourceUnits([pick(t) for t in self.coord], draws, None if self.ctr is None else pick(self.ctr))


# Seeded source draws, kept for the next call with the same seed: a fit traces its rays again
# at every step (common random numbers), and drawing them (~10 ms for 5000 rays and the
# draws of 3 slits and 5 slope errors) was a sixth of a value trace.  The draws depend on
# the seed, the ray count and which elements draw, never on the parameter values; nothing
# writes into them.  Bounded: entries of at most UNITS_CACHE_BYTES, the last UNITS_CACHE_SIZE.
UNITS_CACHE_SIZE = 8
UNITS_CACHE_BYTES = 64 << 20
_units_cache: dict[tuple, SourceUnits] = {}
_units_lock = threading.Lock()


def _units_key(bl: CompiledBeamline, n_rays: int, seed, sampling: str, common: bool) -> tuple | None:
    """The draws' identity, or None where they are not reproducible (an unseeded stream)."""
    if isinstance(seed, torch.Generator):
        return None
    seeds = _streams(seed, bl.n_configs, common)
    if any(s is None for s in seeds):
        return None
    return (sampling, int(n_rays), tuple(seeds), str(bl.device), tuple(bl.source["dists"]),
            tuple(o.name for o in bl.optics if o.behaviour == "slit"),
            tuple(o.name for o in bl.optics if o.slope is not None))


def _units_bytes(u: SourceUnits) -> int:
    ts = list(u.coord) + ([] if u.ctr is None else [u.ctr])
    assert not isinstance(u.draws, LazyDraws)  # the cache's units are drawn up front
    if u.draws is not None:
        ts += list(u.draws.slits.values()) + list(u.draws.slopes.values())
    return sum(t.numel() * t.element_size() for t in ts)


def source_units(bl: CompiledBeamline, n_rays: int, seed, *, sampling: str = "fast",
                 common: bool = True, batch_stream: bool = False) -> SourceUnits:
    """The random part of :func:`sample_source`.

    Seeded draws come from a small cache: the same tensors for the same seed, ray count and
    drawing elements.
    """
    src = bl.source
    if src["type"] != "Point Source":
        raise RmlError(f"the torch engine samples point sources only ({src['type']!r}: pass rays)")
    key = None if batch_stream else _units_key(bl, n_rays, seed, sampling, common)
    if key is not None:
        with _units_lock:
            hit = _units_cache.pop(key, None)
            if hit is not None:
                _units_cache[key] = hit  # the most recent last
                return hit
    units = _draw_units(bl, n_rays, seed, sampling=sampling, common=common, batch_stream=batch_stream)
    if key is not None and _units_bytes(units) <= UNITS_CACHE_BYTES:
        with _units_lock:
            _units_cache[key] = units
            while len(_units_cache) > UNITS_CACHE_SIZE:
                _units_cache.pop(next(iter(_units_cache)))
    return units


def _draw_units(bl: CompiledBeamline, n_rays: int, seed, *, sampling: str, common: bool,
                batch_stream: bool) -> SourceUnits:
    src = bl.source
    dev, c = bl.device, bl.n_configs
    if batch_stream:
        if sampling != "fast" or isinstance(seed, Sequence):
            raise InputError("batch_stream draws the fast stream from one seed")
        return _batch_units(bl, n_rays, seed)
    seeds = _streams(seed, c, common)
    dists = src["dists"]
    if sampling == "rayx":
        trace_seeds = [rnd.rayx_trace_seed(s if s is not None else int.from_bytes(os.urandom(4), "little"))
                       for s in seeds]
        ctr = torch.stack([rnd.rayx_counters(n_rays, ts, device=dev) for ts in trace_seeds])

        def normal():
            nonlocal ctr
            z = rnd.squares_normal(ctr)
            ctr = ctr + 3
            return z

        def uniform():
            nonlocal ctr
            u = rnd.squares_uniform(ctr)
            ctr = ctr + 1
            return u
        coord: list[Any] = [None] * 6  # filled in RAYX's draw order
        coord[0] = normal() if dists[0] else uniform() - 0.5
        coord[1] = normal() if dists[1] else uniform() - 0.5
        coord[2] = uniform() - 0.5
        coord[3] = uniform() - 0.5
        coord[4] = normal() if dists[3] else uniform() - 0.5
        coord[5] = normal() if dists[2] else uniform() - 0.5
        return SourceUnits(coord, None, ctr)
    slits, slopes = {}, {}
    gens = [_generator(s, dev) for s in seeds]
    # per stream: four normals (width, height, divergences) and six uniforms (depth,
    # energy, and the four coordinates again for hard-edged distributions)
    nn = torch.stack([torch.randn(4, n_rays, generator=g, device=dev, dtype=torch.float64) for g in gens], 1)
    uu = torch.stack([torch.rand(6, n_rays, generator=g, device=dev, dtype=torch.float64) for g in gens], 1)
    coord = [nn[0] if dists[0] else uu[2] - 0.5, nn[1] if dists[1] else uu[3] - 0.5,
             uu[0] - 0.5, uu[1] - 0.5,
             nn[2] if dists[3] else uu[4] - 0.5, nn[3] if dists[2] else uu[5] - 0.5]
    for opt in bl.optics:
        if opt.behaviour == "slit":  # the kicks' accepted draws, by inverse CDF, once for all configurations
            slits[opt.name] = rnd.fraunhofer_uniform_fast(torch.stack(
                [torch.rand(2, n_rays, generator=g, device=dev, dtype=torch.float64) for g in gens], 1))
        if opt.slope is not None:
            slopes[opt.name] = torch.stack([torch.randn(2, n_rays, generator=g, device=dev,
                                                        dtype=torch.float64) for g in gens], 1)
    return SourceUnits(coord, Draws(slits, slopes))


def _batch_units(bl: CompiledBeamline, n_rays: int, seed, lazy: bool = False) -> SourceUnits:
    """The fast stream's draws of :func:`source_units`, (C, N) each, from one generator.

    ``seed`` is a number or a generator; ``lazy``: the later draws as :class:`LazyDraws`.
    """
    dev, c, dists = bl.device, bl.n_configs, bl.source["dists"]
    g = seed if isinstance(seed, torch.Generator) else _generator(seed, dev)
    nn = torch.randn(4, c, n_rays, generator=g, device=dev, dtype=torch.float64)
    uu = torch.rand(6, c, n_rays, generator=g, device=dev, dtype=torch.float64)
    coord = [nn[0] if dists[0] else uu[2] - 0.5, nn[1] if dists[1] else uu[3] - 0.5,
             uu[0] - 0.5, uu[1] - 0.5,
             nn[2] if dists[3] else uu[4] - 0.5, nn[3] if dists[2] else uu[5] - 0.5]
    if lazy:
        return SourceUnits(coord, LazyDraws(g))
    slits, slopes = {}, {}
    for opt in bl.optics:
        if opt.behaviour == "slit":
            slits[opt.name] = rnd.fraunhofer_uniform_fast(
                torch.rand(2, c, n_rays, generator=g, device=dev, dtype=torch.float64))
        if opt.slope is not None:
            slopes[opt.name] = torch.randn(2, c, n_rays, generator=g, device=dev, dtype=torch.float64)
    return SourceUnits(coord, Draws(slits, slopes))


class LazyDraws:
    """The fast stream's later draws (slit kicks, slope errors) made as a ray meets the element.

    They are made for the rays in flight only: in a compacting trace the rays stopped upstream
    draw nothing (most of a dim batch's rays).  Same distributions as :class:`Draws`, other
    numbers.
    """

    def __init__(self, generator: torch.Generator):
        self.generator = generator

    def slit(self, like: torch.Tensor) -> torch.Tensor:
        """A slit's accepted kick draws (width, height) for the rays of ``like``, ``(2, *like.shape)``."""
        return rnd.fraunhofer_uniform_fast(torch.rand(2, *like.shape, generator=self.generator,
                                                      device=like.device, dtype=torch.float64))

    def slope(self, like: torch.Tensor) -> torch.Tensor:
        """Standard normals for the slope errors of the rays of ``like``, ``(2, *like.shape)``."""
        return torch.randn(2, *like.shape, generator=self.generator, device=like.device, dtype=torch.float64)


def source_rays(bl: CompiledBeamline, units: SourceUnits) -> Rays:
    """The source's unit draws scaled by its sizes, divergences and energy (differentiable in them).

    Seven coordinates are rays given as they are (position, direction, energy: another source's
    own draws, :func:`given_units`).
    """
    src, coord = bl.source, units.coord
    if len(coord) == 7:
        dt = bl.dtype
        # mypy counts no starred generator's items (six here)
        return Rays(*(t.to(dt) for t in coord[:6]), coord[6].to(torch.float64), units.ctr)  # type: ignore[call-arg]
    x = coord[0] * src["width"]
    y = coord[1] * src["height"]
    z = coord[2] * src["depth"]
    energy = src["energy"] + coord[3] * src["spread"]
    psi = coord[4] * src["ver_div"]
    phi = coord[5] * src["hor_div"]
    dx, dy, dz = torch.cos(psi) * torch.sin(phi), -torch.sin(psi), torch.cos(psi) * torch.cos(phi)
    dt = bl.dtype
    energy = energy * torch.ones_like(x)
    return Rays(x.to(dt), y.to(dt), z.to(dt), dx.to(dt), dy.to(dt), dz.to(dt), energy.to(torch.float64), units.ctr)


def given_units(rays: Rays) -> SourceUnits:
    """Given rays as a trace's randomness (:func:`source_rays` passes them through)."""
    return SourceUnits([rays.x, rays.y, rays.z, rays.dx, rays.dy, rays.dz, rays.energy], None, rays.ctr)


def rays_from_arrays(position: np.ndarray, direction: np.ndarray, energy: np.ndarray, *,
                     dtype=torch.float64, device="cpu", counters=None) -> Rays:
    """Rays given in the source frame (e.g. RAYX's own emitted rays), shape (N, 3)."""
    p = torch.as_tensor(np.asarray(position, float), dtype=dtype, device=device)
    d = torch.as_tensor(np.asarray(direction, float), dtype=dtype, device=device)
    e = torch.as_tensor(np.asarray(energy, float), dtype=torch.float64, device=device)
    ctr = None if counters is None else torch.as_tensor(counters, dtype=torch.int64, device=device)[None]
    return Rays(p[None, :, 0], p[None, :, 1], p[None, :, 2], d[None, :, 0], d[None, :, 1], d[None, :, 2],
                e[None], ctr)
