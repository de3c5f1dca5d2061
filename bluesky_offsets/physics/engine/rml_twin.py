"""The differentiable torch engine on a described beamline's own RML.

Each parameter column drives its element's field (gradients flow through the compiled frames
and surfaces, :func:`.compiling.compile_beamline` with ``beamline=``); the source rays are
RAYX's own draws of the description's source in its local frame (the source's misalignments act
in the engine), cached per seed and count and shared by every configuration of a batch; slit
kicks follow RAYX's counters.  Everything else is :class:`~.torch_twin.TorchEngine`'s.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.engine import random_streams as rnd
from bluesky_offsets.physics.engine.compiling import _MIS_KEYS, compile_beamline
from bluesky_offsets.physics.engine.sampling import Rays, given_units, rays_from_arrays
from bluesky_offsets.physics.engine.torch_twin import TorchEngine
from bluesky_offsets.physics.rml import read_rml
from bluesky_offsets.physics.screen import on_image_plane
from bluesky_offsets.physics.rayx_calls import grid_draw, grid_rays, source_rays
from bluesky_offsets.physics.traces import HistogramSpec


SOURCE_CACHE = 64
"""RAYX source draws an engine keeps (a fit's configurations each have their own seed)."""


def _field_overrides(table, values, overrides=None) -> dict:
    """``{element: {field: column}}`` of a parameter batch ``(C, P)``, the extra ``overrides`` on top.

    Tensor columns keep their gradients.
    """
    out: dict = {}
    for i, p in enumerate(table):
        out.setdefault(p.element, {})[p.field] = values[:, i]
    for element, f in (overrides or {}).items():
        out.setdefault(element, {}).update(f)
    return out


class RmlTorchEngine(TorchEngine):
    """The torch engine on ``beamline`` (a :class:`physics.beamline.Beamline` with an RML)."""

    def __init__(self, beamline, hist: HistogramSpec | None = None, options=None):
        super().__init__(beamline.table, hist or beamline.detector.histograms, options)
        self.described, self.rml = beamline, read_rml(beamline.rml_file())
        self.source_cache: dict = {}

    @property
    def version(self) -> str:
        """The engine as a run records it: torch's version, the RML's beamline, dtype and device."""
        o = self.options
        return (f"torch {torch.__version__} (bluesky-offsets tracer, {self.described.name} RML, RAYX's source rays, "
                f"{o.dtype}, {o.device})")

    def __getstate__(self):
        return {**self.__dict__, "source_cache": {}}  # RAYX redraws them where the engine goes

    def compile(self, values, overrides=None):
        """The RML at a batch of parameter vectors ``(C, P)`` (physical units; a tensor keeps its graph)."""
        o = self.options
        vals = values if torch.is_tensor(values) else torch.as_tensor(np.asarray(values, dtype=float))
        vals = vals.to(dtype=torch.float64, device=o.device)
        vals = vals[None] if vals.ndim == 1 else vals
        if vals.shape[1] != len(self.table):
            raise InputError(f"expected parameter vectors of {len(self.table)} values, got shape {tuple(vals.shape)}")
        overrides = on_image_plane(overrides, self.described.detector.image_plane)
        if overrides is not None and not isinstance(overrides, dict):
            overrides = self._columns(list(overrides), vals.shape[0])
        return compile_beamline(vals[:, :0], _field_overrides(self.table, vals, overrides), beamline=self.rml,
                                dtype=o.torch_dtype, device=o.device)

    def _columns(self, per_config: list, c: int) -> dict:
        """One overrides mapping of ``(C,)`` columns from one mapping per configuration.

        A field a configuration leaves out keeps the RML's value; element types must agree.
        """
        if len(per_config) != c:
            raise InputError(f"{len(per_config)} overrides for {c} configurations")
        keys = {(e, k) for ov in per_config for e, f in ov.items() for k in f}
        out: dict = {}
        for e, k in sorted(keys):
            vals = [ov.get(e, {}).get(k) for ov in per_config]
            if k == "type":
                if len({str(v) for v in vals}) > 1:
                    raise InputError("the configurations of one batch must not change element types differently")
                out.setdefault(e, {})[k] = vals[0]
                continue
            default = getattr(self.rml[e].misalignment, _MIS_KEYS[k]) if k in _MIS_KEYS else self.rml[e].get_float(k)
            col = [torch.as_tensor(default if v is None else v, dtype=torch.float64, device=self.options.device)
                   .reshape(()) for v in vals]
            out.setdefault(e, {})[k] = torch.stack(col)
        return out

    def _units(self, bl, n_rays, seed):
        return given_units(self._source(n_rays, seed))


    def _source(self, n_rays: int, seed):
        """One RAYX draw for a batch, or one per configuration for a sequence of seeds."""
        if not isinstance(seed, (list, tuple)):
            return _rayx_source(self, n_rays, seed)
        parts = [_rayx_source(self, n_rays, s) for s in seed]
        return Rays(*(torch.cat([getattr(r, f) for r in parts], 0) for f in
                      ("x", "y", "z", "dx", "dy", "dz", "energy", "ctr")))


def _rayx_source(eng, n_rays: int, seed):
    """RAYX's source rays for ``seed`` (its local frame), with the counters its slits draw from.

    From a grid source (:attr:`.Beamline.source_varies`) the photons are rays of its grid, drawn
    as :class:`~bluesky_offsets.physics.beamline.RmlEngine` draws them.
    """
    seed = int(seed) if seed is not None else int.from_bytes(os.urandom(4), "little")
    key = (int(n_rays), seed)
    if key not in eng.source_cache:
        if eng.described.source_varies:
            col, ctr = source_rays(eng.rml, n_rays, seed), rnd.rayx_counters(n_rays, rnd.rayx_trace_seed(seed))
        else:
            grid = grid_rays(eng.rml)
            if ("grid", grid) not in eng.source_cache:
                eng.source_cache[("grid", grid)] = source_rays(eng.rml, grid, 0)
            pick = grid_draw(grid, n_rays, seed)
            col = {k: v[pick] for k, v in eng.source_cache[("grid", grid)].items()}
            ctr = rnd.rayx_counters(grid, rnd.rayx_trace_seed(seed))[torch.as_tensor(pick)]
        if len(eng.source_cache) >= SOURCE_CACHE:
            eng.source_cache.pop(next(iter(eng.source_cache)))
        eng.source_cache[key] = rays_from_arrays(
            np.column_stack([col["position_x"], col["position_y"], col["position_z"]]),
            np.column_stack([col["direction_x"], col["direction_y"], col["direction_z"]]), col["energy"],
            dtype=eng.options.torch_dtype, device=eng.options.device, counters=ctr)
    return eng.source_cache[key]
