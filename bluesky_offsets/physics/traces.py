"""What a twin is asked and answers, apart from how it traces.

The histogram binning (:class:`HistogramSpec`, the camera's :data:`CAMERA`), a request
(:class:`TraceRequest`), its result (:class:`TraceResult`) and the engine interface
(:class:`TraceEngine`) that RAYX and the torch engine implement.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.parameters import ParameterTable


# --------------------------------------------------------------------------- #
# histograms
# --------------------------------------------------------------------------- #
@dataclass(frozen=True)
class HistogramSpec:
    """Binning of the focus-chamber footprint, normalized as fraction of source rays.

    The paper's: 50 bins over [-10, 10] mm in x, 50 bins over [-3, 3] mm in y.
    """

    bins_x: int = 50
    range_x: tuple[float, float] = (-10.0, 10.0)
    bins_y: int = 50
    range_y: tuple[float, float] = (-3.0, 3.0)

    @property
    def edges_x(self) -> np.ndarray:
        """The ``bins_x + 1`` bin edges in x (mm)."""
        return np.linspace(*self.range_x, self.bins_x + 1)

    @property
    def edges_y(self) -> np.ndarray:
        """The ``bins_y + 1`` bin edges in y (mm)."""
        return np.linspace(*self.range_y, self.bins_y + 1)

    @property
    def centers_x(self) -> np.ndarray:
        """The ``bins_x`` bin centres in x (mm)."""
        e = self.edges_x
        return 0.5 * (e[1:] + e[:-1])

    @property
    def centers_y(self) -> np.ndarray:
        """The ``bins_y`` bin centres in y (mm)."""
        e = self.edges_y
        return 0.5 * (e[1:] + e[:-1])

    def histograms(self, x: np.ndarray, y: np.ndarray, n_source_rays: int) -> tuple[np.ndarray, np.ndarray]:
        """The x and y histograms as fraction of ``n_source_rays`` per bin."""
        hx = _hist1d(x, self.bins_x, self.range_x)
        hy = _hist1d(y, self.bins_y, self.range_y)
        scale = 1.0 / max(int(n_source_rays), 1)
        return hx * scale, hy * scale

    def image(self, x: np.ndarray, y: np.ndarray, n_source_rays: int) -> np.ndarray:
        """2-D histogram (bins_y, bins_x), fraction of source rays per pixel."""
        img, _, _ = np.histogram2d(y, x, bins=(self.bins_y, self.bins_x), range=(self.range_y, self.range_x))
        return img / max(int(n_source_rays), 1)

    def fingerprint(self) -> dict:
        """The binning as a plain mapping (bins, ranges, normalization), as datasets record it."""
        return {"bins_x": self.bins_x, "range_x": list(self.range_x),
                "bins_y": self.bins_y, "range_y": list(self.range_y), "normalization": "fraction of source rays"}

    @classmethod
    def from_fingerprint(cls, fp: Mapping) -> HistogramSpec:
        """The spec a :meth:`fingerprint` describes."""
        lo_x, hi_x = map(float, fp["range_x"])
        lo_y, hi_y = map(float, fp["range_y"])
        return cls(int(fp["bins_x"]), (lo_x, hi_x), int(fp["bins_y"]), (lo_y, hi_y))

    @classmethod
    def from_centers(cls, centers_x, centers_y) -> HistogramSpec:
        """The spec of uniform bins with these centres (as a detector publishes its axes)."""
        def axis(c):
            c = np.asarray(c, float)
            if c.size < 2:
                raise InputError("a histogram axis needs at least two bin centres")
            w = (c[-1] - c[0]) / (c.size - 1)
            if not np.allclose(np.diff(c), w, rtol=1e-6, atol=1e-9):
                raise InputError("histogram bins are not uniform")
            # rounded: the centres travel as float32 or text, the window edges are round numbers
            return c.size, (round(float(c[0] - w / 2), 6), round(float(c[-1] + w / 2), 6))
        (bx, rx), (by, ry) = axis(centers_x), axis(centers_y)
        return cls(bx, rx, by, ry)

    def factors(self, coarse: HistogramSpec) -> tuple[int, int]:
        """How many of this spec's bins make one bin of ``coarse`` (x, y).

        ValueError if the edges of ``coarse`` are not edges of this spec.
        """
        if self.range_x != coarse.range_x or self.range_y != coarse.range_y \
                or self.bins_x % coarse.bins_x or self.bins_y % coarse.bins_y:
            raise InputError(f"histograms binned as {self.fingerprint()} cannot be re-binned to {coarse.fingerprint()}")
        return self.bins_x // coarse.bins_x, self.bins_y // coarse.bins_y

    def rebin(self, hist_x: np.ndarray, hist_y: np.ndarray, coarse: HistogramSpec) -> tuple[np.ndarray, np.ndarray]:
        """Histograms of this spec (..., bins) summed into the bins of ``coarse``."""
        fx, fy = self.factors(coarse)
        hx, hy = np.asarray(hist_x, float), np.asarray(hist_y, float)
        return (hx.reshape(*hx.shape[:-1], coarse.bins_x, fx).sum(-1),
                hy.reshape(*hy.shape[:-1], coarse.bins_y, fy).sum(-1))


# The focus-chamber camera at its own resolution (20 µm x 5 µm bins over the paper's window):
# the paper's 50 x 50 histograms are these summed 20 x 24 at a time.  The surrogate sees the
# paper's binning; the diagnosis fits the camera's, where a focus (x 68 µm, y 16-23 µm rms)
# spans several bins instead of one, so its position, width and shape carry information.
CAMERA = HistogramSpec(1000, (-10.0, 10.0), 1200, (-3.0, 3.0))


def _hist1d(v: np.ndarray, bins: int, rng: tuple[float, float]) -> np.ndarray:
    # Same bin convention as np.histogram (last bin closed), ~5x faster.
    lo, hi = rng
    v = v[(v >= lo) & (v <= hi)]
    idx = np.minimum(((v - lo) * (bins / (hi - lo))).astype(np.int64), bins - 1)
    return np.bincount(idx, minlength=bins).astype(float)


# --------------------------------------------------------------------------- #
# engine interface
# --------------------------------------------------------------------------- #
@dataclass
class TraceRequest:
    """One beamline state to trace.

    ``values`` is the physical parameter vector (table order); ``overrides``
    holds RML-level changes ``{object: {field: value}}`` (focus-chamber
    translation, physical effects); ``seed`` makes the trace reproducible.
    """

    values: np.ndarray
    overrides: Mapping[str, Mapping[str, object]] = field(default_factory=dict)
    seed: int | None = None  # None: a fresh random stream


@dataclass
class TraceResult:
    """Histograms and hit count of one traced beamline state."""

    hist_x: np.ndarray
    hist_y: np.ndarray
    n_hits: int
    n_rays: int
    values: np.ndarray
    rays: np.ndarray | None = None  # (n_hits, 2): x, y in mm
    error: str | None = None

    @property
    def ok(self) -> bool:
        """Whether the trace succeeded (no ``error``)."""
        return self.error is None

    @property
    def transmission(self) -> float:
        """The fraction of source rays that reached the screen (0 without rays)."""
        return self.n_hits / self.n_rays if self.n_rays else 0.0

    def summary(self) -> dict:
        """Transmission, centroid and widths (mm) from the raw rays when kept."""
        out = {"n_rays": self.n_rays, "n_hits": self.n_hits, "transmission": self.transmission,
               "hist_sum_x": float(self.hist_x.sum()), "hist_sum_y": float(self.hist_y.sum())}
        if self.rays is not None and len(self.rays):
            out.update(centroid_x=float(self.rays[:, 0].mean()), centroid_y=float(self.rays[:, 1].mean()),
                       width_x=float(self.rays[:, 0].std()), width_y=float(self.rays[:, 1].std()))
        return out


class TraceFailed(RuntimeError):
    """A simulation failed; carries the parameter vector it failed for."""

    def __init__(self, message: str, values: np.ndarray | None = None):
        super().__init__(message)
        self.values = values


@runtime_checkable
class TraceEngine(Protocol):
    """What a ray-tracing engine must provide to be a twin."""

    table: ParameterTable
    hist: HistogramSpec

    @property
    def version(self) -> str:
        """Engine name and version, recorded with every dataset and run."""

    def trace(self, request: TraceRequest, n_rays: int, keep_rays: bool = False) -> TraceResult:
        """Trace one beamline state with ``n_rays`` source rays."""
