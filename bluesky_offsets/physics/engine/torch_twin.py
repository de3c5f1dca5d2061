"""The torch twin: :class:`TorchEngine`, the engine behind the twin interface, and its options.

It compiles a batch of parameter vectors (:mod:`.compiling`), draws the rays (:mod:`.sampling`),
traces them in memory-bounded chunks (:mod:`.tracing`), bins them (:mod:`.binning`) and gives the
products' Jacobians, whole-batch or per ray (:mod:`.jacobians`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from bluesky_offsets.errors import InputError
from bluesky_offsets.options import refuse_unknown
from bluesky_offsets.physics.engine.binning import features_from_moments, histograms, moments
from bluesky_offsets.physics.engine.compiling import _MIS_KEYS, CompiledBeamline, _compiled_tensors, compile_beamline
from bluesky_offsets.physics.engine.jacobians import (FORWARD_AD, RAY_WEIGHT_FLOOR, RayJacobian, _batched_grad,
                                                      _kept_ray_grads)
from bluesky_offsets.physics.engine.sampling import (LazyDraws, SourceUnits, _batch_units, _generator, source_rays,
                                                     source_units)
from bluesky_offsets.physics.engine.tracing import Beam, trace_rays
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.physics.traces import HistogramSpec, TraceRequest, TraceResult


@dataclass(frozen=True)
class TorchOptions:
    """How the torch engine traces.

    Parameters
    ----------
    dtype : {"float64", "float32"}
        "float64" (default; equal to RAYX ray for ray) or "float32" (faster, coarser:
        docs/benchmarks.md, "Torch engine", gives its accuracy).
    device : str
        "cpu", "cuda", "cuda:1" ...
    sampling : {"fast", "rayx"}
        "fast" (torch's generator, inverse-CDF slit kicks) or "rayx" (RAYX's own
        random stream, for ray-for-ray comparisons; slower: rejection loops).
    common_rays : bool
        share the random numbers across the configurations of a batch (common
        random numbers: differences between configurations carry no sampling noise of
        their own); False draws each configuration from ``seed + i``.
    max_batch : int
        configurations × rays traced at once; larger batches are traced in chunks
        of rays (memory: ~2 kB per ray and configuration with gradients).
    edge : float
        soft-edge width, relative to each aperture dimension, for the smooth (soft)
        beam the gradients use; 0 = hard edges.
    kernel : float
        width (in bins) of the kernel that bins the soft histograms and profiles.
    """

    dtype: Literal["float64", "float32"] = "float64"
    device: str = "cpu"
    sampling: Literal["fast", "rayx"] = "fast"
    common_rays: bool = True
    max_batch: int = 1 << 19
    edge: float = 0.002
    kernel: float = 1.0

    def __post_init__(self):
        if self.dtype not in ("float64", "float32"):
            raise InputError(f"dtype must be 'float64' or 'float32', not {self.dtype!r}")
        if self.sampling not in ("fast", "rayx"):
            raise InputError(f"sampling must be 'fast' or 'rayx', not {self.sampling!r}")
        if int(self.max_batch) < 1:
            raise InputError("max_batch must be positive")
        if not (self.edge >= 0 and math.isfinite(self.edge)):
            raise InputError("edge must be a finite number >= 0")
        if not (self.kernel > 0 and math.isfinite(self.kernel)):
            raise InputError("kernel must be a finite number > 0")
        torch.device(self.device)  # refuses a malformed device string

    @classmethod
    def from_mapping(cls, options: Mapping[str, Any] | None) -> TorchOptions:
        """Options from a mapping; an unknown key is refused, naming the known ones."""
        options = dict(options or {})
        refuse_unknown(cls, options, "unknown torch engine option(s)")
        return cls(**options)

    @property
    def torch_dtype(self) -> torch.dtype:
        """``dtype`` as a torch dtype (``torch.float64`` or ``torch.float32``)."""
        return torch.float64 if self.dtype == "float64" else torch.float32


@dataclass(frozen=True)
class TraceBatch:
    """Hard histograms of a batch (:meth:`TorchEngine.trace_batch`) and the rays on the screen.

    The histograms are fractions of the ``n_rays`` source rays per bin, (C, bins); the rays on
    the screen are counts, (C,).
    """

    hist_x: np.ndarray
    hist_y: np.ndarray
    n_hits: np.ndarray
    n_rays: int


class TorchEngine:
    """The differentiable twin behind the :class:`~bluesky_offsets.physics.twin.TraceEngine` interface.

    ``Twin(engine="torch")`` uses it; RAYX stays the reference engine.  Besides ``trace``
    (one request) it traces batches in one call (:meth:`trace_many`, :meth:`beam`) and gives
    beam features, soft histograms and camera profiles with their Jacobians
    (:meth:`jacobian`).

    Parameters
    ----------
    table, hist : as for :class:`~bluesky_offsets.physics.twin.RayxEngine`.
    options : TorchOptions or a mapping of its fields (unknown keys are refused).
    """

    def __init__(self, table: ParameterTable = METRIXS, hist: HistogramSpec | None = None,
                 options: TorchOptions | Mapping | None = None):
        self.table = table
        self.hist = hist or HistogramSpec()
        self.options = options if isinstance(options, TorchOptions) else TorchOptions.from_mapping(options)

    @property
    def version(self) -> str:
        """Engine name and version, with its sampling, dtype and device, recorded with every dataset and run."""
        o = self.options
        return f"torch {torch.__version__} (bluesky-offsets tracer, {o.sampling} sampling, {o.dtype}, {o.device})"

    # -- batches ----------------------------------------------------------------
    def _units(self, bl: CompiledBeamline, n_rays: int, seed) -> SourceUnits:
        """A trace's randomness: the source's draws (an engine with another source gives its rays)."""
        o = self.options
        return source_units(bl, n_rays, seed, sampling=o.sampling, common=o.common_rays)

    def compile(self, values, overrides=None) -> CompiledBeamline:
        """The beamline at ``values`` (C, P) with ``overrides``, as tensors of the engine's dtype and device."""
        o = self.options
        return compile_beamline(values, overrides, table=self.table, dtype=o.torch_dtype, device=o.device)

    def _chunks(self, bl: CompiledBeamline, n_rays: int, seed, edge: float, keep_hits: bool = False):
        """Trace ``n_rays`` per configuration in memory-bounded chunks of rays."""
        o = self.options
        units = self._units(bl, n_rays, seed)
        rays, draws = source_rays(bl, units), units.draws
        assert not isinstance(draws, LazyDraws)  # drawn up front: the chunks slice them
        step = max(1, o.max_batch // max(bl.n_configs, 1))
        for a in range(0, n_rays, step):
            b = min(n_rays, a + step)
            yield a, trace_rays(bl, rays.slice(a, b), None if draws is None else draws.slice(a, b),
                                edge=edge, keep_hits=keep_hits)

    def beam(self, values, overrides=None, *, n_rays: int, seed=None, edge: float = 0.0,
             keep_hits: bool = False) -> Beam:
        """All rays of a batch at the screen, its chunks joined (all rays held at once)."""
        bl = self.compile(values, overrides)
        parts = list(self._chunks(bl, n_rays, seed, edge, keep_hits))
        if len(parts) == 1:
            return parts[0][1]
        def cat(name):
            return torch.cat([getattr(b, name) for _, b in parts], -1)
        hits = None if not keep_hits else {k: torch.cat([b.hits[k] for _, b in parts], 1) for k in parts[0][1].hits}
        dirs = None if not keep_hits else {k: torch.cat([b.directions[k] for _, b in parts], 1)
                                           for k in parts[0][1].directions}
        return Beam(cat("x"), cat("y"), cat("alive"), cat("weight"), n_rays, hits, dirs)

    def trace_many(self, requests: Sequence[TraceRequest], n_rays: int, keep_rays: bool = False) -> list[TraceResult]:
        """Trace requests as one batch (groups of equal element types), results in order.

        Requests that share one seed share their rays (common random numbers, when the
        options say so); different seeds give each request its own stream.
        """
        if n_rays < 1:
            raise InputError(f"n_rays must be positive, got {n_rays}")
        out: list[TraceResult | None] = [None] * len(requests)
        groups: dict[tuple, list[int]] = {}
        for i, r in enumerate(requests):
            key = tuple(sorted((k, str(f.get("type"))) for k, f in r.overrides.items() if "type" in f))
            groups.setdefault(key, []).append(i)
        for idx in groups.values():
            reqs = [requests[i] for i in idx]
            values = np.stack([self.table.validate(r.values) for r in reqs])
            seeds = [r.seed for r in reqs]
            seed = seeds[0] if len(set(seeds)) == 1 and seeds[0] is not None else seeds
            if all(not r.overrides for r in reqs):
                overrides = None
            else:
                overrides = [dict(r.overrides) for r in reqs]
            for i, res in zip(idx, self._trace_group(values, overrides, n_rays, seed, keep_rays)):
                out[i] = res
        return out  # type: ignore[return-value]

    def _trace_group(self, values, overrides, n_rays, seed, keep_rays) -> list[TraceResult]:
        bl = self.compile(values, overrides)
        c = bl.n_configs
        hx = hy = None
        n_hits = torch.zeros(c, dtype=torch.int64)
        kept: list[list[np.ndarray]] = [[] for _ in range(c)]
        with torch.no_grad():
            for _, beam in self._chunks(bl, n_rays, seed, 0.0):
                bx, by = histograms(beam, self.hist, n_source=n_rays)
                hx = bx if hx is None else hx + bx
                hy = by if hy is None else hy + by
                n_hits += beam.alive.sum(-1).cpu()
                if keep_rays:
                    for k in range(c):
                        a = beam.alive[k]
                        kept[k].append(torch.stack([beam.x[k][a], beam.y[k][a]], -1).cpu().numpy().astype(float))
        assert hx is not None and hy is not None  # n_rays >= 1: at least one chunk
        hx, hy = hx.cpu().numpy().astype(float), hy.cpu().numpy().astype(float)
        return [TraceResult(hx[k], hy[k], int(n_hits[k]), int(n_rays), np.asarray(values[k], float),
                            np.concatenate(kept[k]) if keep_rays else None) for k in range(c)]

    def trace_batch(self, values, overrides=None, *, n_rays: int, seed=None) -> TraceBatch:
        """Hard histograms of many configurations, each traced with rays of its own.

        For datasets: every configuration gets independent rays (no common random numbers),
        all drawn from one generator seeded with ``seed``; slit kicks and slope errors are
        drawn as the rays in flight meet their element (:class:`LazyDraws`), and the trace
        compacts (``trace_rays(compact=True)``), so rays stopped upstream cost nothing more.
        A configuration's histograms are the same for the same batch, ``seed`` and
        ``max_batch``; they follow RAYX's in distribution (``sampling="fast"`` only).
        """
        o = self.options
        if o.sampling != "fast":
            raise InputError("trace_batch draws the fast stream (sampling='fast')")
        if n_rays < 1:
            raise InputError(f"n_rays must be positive, got {n_rays}")
        bl = self.compile(values, overrides)
        c = bl.n_configs
        g = _generator(seed, bl.device)
        step = max(1, o.max_batch // max(c, 1))
        hx = torch.zeros(c, self.hist.bins_x, dtype=torch.float64)
        hy = torch.zeros(c, self.hist.bins_y, dtype=torch.float64)
        n_hits = torch.zeros(c, dtype=torch.int64)
        with torch.no_grad():
            for a in range(0, n_rays, step):
                units = _batch_units(bl, min(n_rays, a + step) - a, g, lazy=True)
                beam = trace_rays(bl, source_rays(bl, units), units.draws, compact=True)
                bx, by = histograms(beam, self.hist)
                # histograms() divides by the chunk's rays: weigh the chunk back to counts
                hx += bx.cpu().double() * beam.n_rays
                hy += by.cpu().double() * beam.n_rays
                n_hits += beam.alive.sum(-1).cpu()
        return TraceBatch((hx / n_rays).numpy(), (hy / n_rays).numpy(), n_hits.numpy(), n_rays)

    def trace(self, request: TraceRequest, n_rays: int, keep_rays: bool = False) -> TraceResult:
        """Trace one beamline state with ``n_rays`` source rays (:meth:`trace_many` with one request)."""
        return self.trace_many([request], n_rays, keep_rays)[0]

    # -- differentiable products --------------------------------------------------
    def inputs(self, values, effects: Mapping[str, Mapping[str, float]] | None = None):
        """Leaf tensors for a Jacobian, with names: parameters (C, 34) and one (C,) tensor per effect parameter.

        One tensor per effect parameter, so that every configuration gets its own derivative.
        """
        vals = torch.as_tensor(np.atleast_2d(self.table.validate(values)), dtype=torch.float64,
                               device=self.options.device)
        c = vals.shape[0]
        eff_leaves: dict[str, dict[str, torch.Tensor]] = {}
        names = list(self.table.names)
        from bluesky_offsets.physics import effects as fx
        for name, vals_e in (effects or {}).items():
            eff = fx.get(name)
            if eff.level != "twin":
                raise InputError(f"effect {name!r} acts on histograms, not in the twin: it has no twin Jacobian")
            full = eff.values(vals_e)
            eff_leaves[name] = {p: torch.full((c,), float(v), dtype=torch.float64, device=vals.device)
                                for p, v in full.items()}
            names += [f"{name}.{p}" for p in full]
        return vals, eff_leaves, names

    def _overrides(self, eff_leaves, extra=None):
        from bluesky_offsets.physics import effects as fx
        ov = fx.twin_overrides(eff_leaves) if eff_leaves else {}
        for obj, flds in (extra or {}).items():
            tgt = ov.setdefault(obj, {})
            for k, v in flds.items():
                tgt[k] = tgt[k] + v if (k in _MIS_KEYS and k in tgt) else v
        return ov

    def products(self, what: str, values, effects=None, *, n_rays: int, seed=0, overrides=None,
                 spec: HistogramSpec | None = None) -> torch.Tensor:
        """Soft beam products (C, m) at fixed rays: ``"features"``, ``"histograms"`` or ``"profiles"``.

        ``"features"`` are intensity, centroid x/y and rms width x/y; ``"histograms"`` x then y,
        fraction of source rays; ``"profiles"`` the same at the camera's resolution.
        """
        vals, leaves, _ = self.inputs(values, effects)
        return self._products(what, vals, leaves, n_rays, seed, overrides, spec)

    def _products(self, what, vals, leaves, n_rays, seed, extra, spec) -> torch.Tensor:
        bl = self.compile(vals, self._overrides(leaves, extra))
        edge, total = self.options.edge, None
        for _, beam in self._chunks(bl, n_rays, seed, edge):
            part = self._product(what, beam, spec, n_rays)
            total = part if total is None else total + part
        assert total is not None  # n_rays >= 1: at least one chunk
        if what == "features":
            return features_from_moments(total, n_rays)
        return total

    def _product(self, what, beam, spec, n_rays: int):
        """One chunk's share of a product of ``n_rays`` per configuration.

        Moments are sums over its rays; histograms fractions of all ``n_rays``.
        """
        if what == "features":
            return moments(beam, soft=self.options.edge > 0)
        if what in ("histograms", "profiles"):
            from bluesky_offsets.physics.traces import CAMERA
            sp = spec or (self.hist if what == "histograms" else CAMERA)
            hx, hy = histograms(beam, sp, soft=True, kernel=self.options.kernel, n_source=n_rays)
            return torch.cat([hx, hy], -1)
        raise InputError(f"unknown product {what!r}: features, histograms or profiles")

    def jacobian(self, what: str, values, effects=None, *, n_rays: int, seed=0, overrides=None,
                 spec: HistogramSpec | None = None, mode: Literal["auto", "forward", "reverse"] = "auto"):
        """Products (C, m) and their Jacobian (C, m, 34 + effect parameters), with the columns' names.

        For a whole batch of configurations at fixed rays.

        ``mode``: "reverse" (the default) takes one batched backward pass per chunk of rays
        for all product components; "forward" one forward-mode pass per input column.
        """
        vals, leaves, names = self.inputs(values, effects)
        flat = [(None, vals)] + [((e, p), t) for e, d in leaves.items() for p, t in d.items()]
        n_in = vals.shape[1] + sum(len(d) for d in leaves.values())
        if mode == "auto":
            # eager forward-mode AD runs several of these ops through Python decompositions and
            # loses to one batched backward pass (docs/benchmarks.md, "Torch engine")
            mode = "reverse"
        if mode == "forward":
            return self._jacobian_forward(what, vals, leaves, flat, n_in, n_rays, seed, overrides, spec, names)
        return self._jacobian_reverse(what, vals, leaves, flat, n_in, n_rays, seed, overrides, spec, names)

    def _jacobian_forward(self, what, vals, leaves, flat, n_in, n_rays, seed, extra, spec, names):
        import torch.autograd.forward_ad as fwd
        cols, out = [], None
        c = vals.shape[0]
        for j in range(n_in):
            with FORWARD_AD, fwd.dual_level():
                k = 0
                dual_vals, dual_leaves = None, {e: {} for e in leaves}
                for key, t in flat:
                    width = t.shape[1] if key is None else 1
                    tangent = torch.zeros_like(t)
                    if k <= j < k + width:
                        if key is None:
                            tangent[:, j - k] = 1.0
                        else:
                            tangent[:] = 1.0
                    dual = fwd.make_dual(t, tangent)
                    if key is None:
                        dual_vals = dual
                    else:
                        dual_leaves[key[0]][key[1]] = dual
                    k += width
                prod = self._products(what, dual_vals, dual_leaves, n_rays, seed, extra, spec)
                primal, tangent = fwd.unpack_dual(prod)
                out = primal.detach() if out is None else out
                cols.append(tangent.detach() if tangent is not None else torch.zeros_like(primal))
        return out, torch.stack(cols, -1).reshape(c, -1, n_in), names

    def _jacobian_reverse(self, what, vals, leaves, flat, n_in, n_rays, seed, extra, spec, names):
        leaves_req = {e: {p: t.clone().requires_grad_(True) for p, t in d.items()} for e, d in leaves.items()}
        vals_req = vals.clone().requires_grad_(True)
        inputs = [vals_req] + [t for d in leaves_req.values() for t in d.values()]
        bl = self.compile(vals_req, self._overrides(leaves_req, extra))
        edge = self.options.edge
        total, jac = None, None
        for _, beam in self._chunks(bl, n_rays, seed, edge):
            part = self._product(what, beam, spec, n_rays)  # (C, m): this chunk's share
            j_part = _batched_grad(part, inputs)
            total = part.detach() if total is None else total + part.detach()
            jac = j_part if jac is None else jac + j_part
        if what != "features":
            return total, jac, names
        s = total.clone().requires_grad_(True)
        feats = features_from_moments(s, n_rays)
        d_fs = torch.stack([torch.autograd.grad(feats[:, k].sum(), s, retain_graph=True)[0]
                            for k in range(feats.shape[1])], 1)  # (C, 5 features, 5 moments)
        return feats.detach(), torch.einsum("cfm,cmp->cfp", d_fs, jac), names


    # -- per-ray derivatives ---------------------------------------------------------
    def ray_jacobian(self, values, effects=None, *, n_rays: int, seed=0, overrides=None,
                     chunk: int = 1 << 16, columns=None, full: Beam | None = None) -> RayJacobian:
        """Every ray's screen position and soft weight with their derivatives in the inputs.

        The inputs are the 34 parameters and the twin-level effect parameters of ``effects``
        (as :meth:`jacobian`).  The beamline is compiled once per configuration and its
        derivatives in the inputs taken there (a small batched backward pass over the compiled
        fields); each ray is then traced as a configuration of its own, with its own copy of
        the compiled fields as leaves, so that three backward passes (x, y, weight) give every
        ray's derivative in every field, and the chain rule every ray's derivative in every
        input.  Any product of the rays (histograms at any binning, camera profiles, moments)
        gets its exact Jacobian from these at the cost of binning (:class:`RayJacobian`).
        Every ray is first traced without derivatives (its values, bit for bit :meth:`beam`'s);
        only the rays whose soft weight is above :data:`RAY_WEIGHT_FLOOR` are traced again for
        theirs (about a fifth of a bright configuration's rays: the rest end far outside a
        slit).  ``chunk`` bounds the rays × configurations traced at once (memory ~5 kB each).
        ``columns`` (indices into the inputs) keeps the derivatives in those inputs only: the
        fields they do not move are no leaves, so nothing upstream of the first field they
        move is traced with a graph (the beam optimizer moves E1 and E2 alone: 0.12 s instead of
        0.96 s at 20,000 rays).
        ``full``: the rays' values as :meth:`beam` traced them at these inputs, rays and seed with
        the soft edge (``edge=options.edge``), taken instead of tracing them again (a fit traces
        the values at a step before it asks for the Jacobian there).
        """
        o = self.options
        vals, leaves, names = self.inputs(values, effects)
        if full is not None and tuple(full.x.shape) != (vals.shape[0], n_rays):
            raise InputError(f"full: rays of shape {tuple(full.x.shape)}, not ({vals.shape[0]}, {n_rays})")
        c = vals.shape[0]
        vals_req = vals.clone().requires_grad_(True)
        leaves_req = {e: {p: t.clone().requires_grad_(True) for p, t in d.items()} for e, d in leaves.items()}
        inputs = [vals_req] + [t for d in leaves_req.values() for t in d.values()]
        bl = self.compile(vals_req, self._overrides(leaves_req, overrides))
        fields = _compiled_tensors(bl, c)
        # d field / d input per configuration: (C, F, P), one batched backward pass
        flat = torch.cat([t.reshape(c, -1) for t in fields], 1)
        dfield = _batched_grad(flat, inputs)
        if columns is not None:
            columns = [int(i) for i in np.asarray(columns).reshape(-1)]
            dfield, names = dfield[:, :, columns], [names[i] for i in columns]
        sizes = [t[0].numel() for t in fields]
        # only the fields the inputs move are leaves of the per-ray traces
        bounds = np.cumsum([0] + sizes)
        live = [i for i in range(len(fields)) if bool(dfield[:, bounds[i]:bounds[i + 1]].any())]
        dfield_live = torch.cat([dfield[:, bounds[i]:bounds[i + 1]] for i in live], 1)
        units = self._units(bl, n_rays, seed)
        assert not isinstance(units.draws, LazyDraws)  # drawn up front: the chunks slice them
        step = max(1, int(chunk) // c)
        parts = []
        for a in range(0, n_rays, step):
            b = min(n_rays, a + step)
            r = b - a
            cut = SourceUnits([t[..., a:b] for t in units.coord],
                              None if units.draws is None else units.draws.slice(a, b),
                              None if units.ctr is None else units.ctr[..., a:b])
            # every ray's values, without a graph (bit for bit the values of :meth:`beam`)
            if full is not None:
                values_k = full.slice(a, b)
            else:
                with torch.no_grad():
                    values_k = trace_rays(bl, source_rays(bl, cut), cut.draws, edge=o.edge)
            # derivatives only for the rays with weight: a ray's soft weight w bounds its
            # derivatives' share of every product (|dw| <= w * sum |du/dθ| over its apertures'
            # logistic arguments u; the position's enters multiplied by w), so below
            # RAY_WEIGHT_FLOOR they lie beneath the rounding of any sum and their rows are 0.
            # Most rays of a bright configuration end far outside a slit: this skips ~80 %.
            keep = torch.nonzero(values_k.weight.reshape(-1) > RAY_WEIGHT_FLOOR).squeeze(1)
            k_n, conf = int(keep.numel()), keep // r
            grads = [torch.zeros(0, len(names), dtype=dfield_live.dtype, device=dfield_live.device)] * 3
            if k_n:
                grads = _kept_ray_grads(bl, fields, live, dfield_live, cut.take(conf, keep % r), conf, o.edge)
            # the kept rays as (configuration, ray) of the whole trace, configuration-major
            rows = conf * n_rays + a + keep % r
            parts.append((values_k.x.reshape(c, r), values_k.y.reshape(c, r), values_k.alive.reshape(c, r),
                          values_k.weight.reshape(c, r), rows, *grads))
        if len(parts) == 1:
            x, y, alive, weight, rows, jx, jy, jw = parts[0]
        else:
            x, y, alive, weight = (torch.cat([p[k] for p in parts], 1) for k in range(4))
            order = torch.argsort(torch.cat([p[4] for p in parts]))  # configuration-major again
            rows, jx, jy, jw = (torch.cat([p[k] for p in parts])[order] for k in range(4, 8))
        return RayJacobian(x, y, alive, weight, rows, jx, jy, jw, n_rays=n_rays, names=names)


def device_agreement(device: str = "cuda", *, n_rays: int = 20_000, seed: int = 3) -> dict:
    """Whether the CPU and ``device`` agree: the check a lent GPU runs before it traces anything for the record.

    The same four configurations near the reference are traced with RAYX's random stream on the
    CPU and on ``device``: whether the same rays survive and how far their screen positions
    differ (mm).
    """
    values = METRIXS.reference + 0.005 * METRIXS.span * np.random.default_rng(8).uniform(-1, 1, (4, len(METRIXS)))
    values[:, [METRIXS.index("E1.rotationZerror"), METRIXS.index("E2.rotationZerror")]] = 0.0
    with torch.no_grad():
        a, b = (TorchEngine(options={"device": d, "sampling": "rayx"}).beam(values, n_rays=n_rays, seed=seed)
                for d in ("cpu", device))
    both = a.alive
    return {"device": str(device), "same_survivors": bool(torch.equal(a.alive, b.alive.cpu())),
            "survivors": int(both.sum()), "max_dx_mm": float((a.x - b.x.cpu())[both].abs().max()),
            "max_dy_mm": float((a.y - b.y.cpu())[both].abs().max())}
