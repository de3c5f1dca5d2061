"""The one measurement: configurations and the focus-chamber histograms measured at them.

A :class:`Measurement` is what the measure plans return, what the run store loads back by
uid, and what the fits, the diagnosis and the finders read.  As measured it may carry the
camera-resolution profiles beside the paper's 50 x 50 histograms; :meth:`Measurement.for_analysis`
gives the one binning an analysis uses (``spec``), checked against the parameter table, with
its ray budget.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.model.misfit import MeasurementError, check_histograms
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.physics.screen import as_screen
from bluesky_offsets.physics.twin import HistogramSpec

RESOLUTIONS = ("camera", "paper")


@dataclass
class Measurement:
    """Configurations and the focus-chamber histograms measured at them.

    Attributes
    ----------
    configurations : ndarray, shape (n, P)
        Commanded configurations, absolute as the motors report them (table order).
    hist_x, hist_y : ndarray, shape (n, bins)
        Measured histograms (fraction of source rays per bin), binned as ``spec`` says.
    n_rays : int or None
        Source rays (ray budget) per frame; None: the metadata's ``n_rays`` if it has one.
    spec : HistogramSpec
        Binning of ``hist_x``/``hist_y`` (default the paper's 50 x 50).
    names : tuple of str
        Parameter names (table order).
    uid : str or None
        Run uid when the measurement comes from a stored run.
    total_counts : ndarray, shape (n,), optional
        Rays on the screen per configuration.
    images : ndarray, shape (n, ny, nx), optional
        2-D histograms when recorded.
    metadata : dict
        The run's start document (or the plan's metadata).
    profile_x, profile_y : ndarray, shape (n, bins), optional
        The footprint at the camera's resolution (``profile_spec``), when the detector gave it.
    screen : ndarray, shape (n, 3), optional
        The focus chamber's stage (x, y, z, mm) per frame (:mod:`bluesky_offsets.physics.screen`);
        None: the stage stood at 0 for every frame.
    floor_x, floor_y : ndarray, shape (n, bins), optional
        A camera's own noise in each bin (read noise, its dark's noise; fraction² of the source),
        beside the photons' counting noise; a dark-subtracted bin may then read below zero.
    profile_floor_x, profile_floor_y : ndarray, optional
        The same for the profiles.
    """

    configurations: np.ndarray
    hist_x: np.ndarray
    hist_y: np.ndarray
    n_rays: int | None = None
    spec: HistogramSpec = field(default_factory=HistogramSpec)
    names: tuple[str, ...] = METRIXS.names
    uid: str | None = None
    total_counts: np.ndarray | None = None
    images: np.ndarray | None = None
    metadata: dict = field(default_factory=dict)
    profile_x: np.ndarray | None = None
    profile_y: np.ndarray | None = None
    screen: np.ndarray | None = None
    floor_x: np.ndarray | None = None
    floor_y: np.ndarray | None = None
    profile_floor_x: np.ndarray | None = None
    profile_floor_y: np.ndarray | None = None

    def __post_init__(self):
        self.names = tuple(self.names)
        cfg = np.asarray(self.configurations, dtype=float)
        cfg = cfg[None] if cfg.ndim == 1 else cfg
        if cfg.ndim != 2 or cfg.shape[1] != len(self.names):
            raise MeasurementError(f"measured configurations: expected {len(self.names)} parameters in table "
                                   f"order, got shape {cfg.shape}")
        floors = _floors(self.floor_x, self.floor_y, len(cfg), self.spec)
        hx, hy = check_histograms(self.hist_x, self.hist_y, self.spec.bins_x, self.spec.bins_y, floors=floors)
        self.floor_x, self.floor_y = floors
        if len(hx) != len(cfg):
            raise MeasurementError(f"measurement: {len(cfg)} configurations but {len(hx)} x and {len(hy)} y histograms")
        self.configurations, self.hist_x, self.hist_y = cfg, hx, hy
        if self.screen is not None:
            try:
                self.screen = as_screen(self.screen, len(cfg))
            except ValueError as exc:
                raise MeasurementError(f"measurement: {exc}") from None
        if self.n_rays is None:
            rays = self.metadata.get("n_rays") or self.metadata.get("num_rays")
            self.n_rays = int(rays) if rays else None
        elif int(self.n_rays) <= 0:
            raise MeasurementError("n_rays must be positive")
        else:
            self.n_rays = int(self.n_rays)

    def __len__(self) -> int:
        return len(self.configurations)

    @property
    def n(self) -> int:
        """Number of configurations."""
        return len(self.configurations)

    @property
    def ray_budget(self) -> int:
        """``n_rays``, which a comparison with a model needs (a MeasurementError without it)."""
        if self.n_rays is None:
            raise MeasurementError(f"measurement {self.uid or ''} does not say its ray budget; pass n_rays")
        return self.n_rays

    @property
    def histograms(self) -> np.ndarray:
        """``(n, bins_x + bins_y)``: x then y histogram per configuration.

        This is the surrogate's output layout at the paper's binning.
        """
        return np.concatenate([self.hist_x, self.hist_y], axis=1)

    @property
    def profile_spec(self) -> HistogramSpec | None:
        """Binning of the profiles (from the run's ``profile`` metadata); None without profiles."""
        fp = self.metadata.get("profile")
        return HistogramSpec.from_fingerprint(fp) if fp and self.profile_x is not None else None

    @property
    def truth_id(self) -> str | None:
        """The run's ``truth_id`` metadata (the published hash of a simulated IOC's hidden truth), or None."""
        return self.metadata.get("truth_id")

    @property
    def table_version(self) -> str | None:
        """The version of the parameter table the run was taken with (its metadata); None if unknown."""
        return self.metadata.get("parameter_table_version")

    def subset(self, idx) -> Measurement:
        """The configurations ``idx`` (index array or mask) with their histograms; same uid."""
        def pick(a):
            return None if a is None else np.asarray(a)[idx]
        return replace(self, configurations=self.configurations[idx], hist_x=self.hist_x[idx],
                       hist_y=self.hist_y[idx], total_counts=pick(self.total_counts), images=pick(self.images),
                       profile_x=pick(self.profile_x), profile_y=pick(self.profile_y), screen=pick(self.screen),
                       floor_x=pick(self.floor_x), floor_y=pick(self.floor_y),
                       profile_floor_x=pick(self.profile_floor_x), profile_floor_y=pick(self.profile_floor_y))

    def joined(self, other: Measurement) -> Measurement:
        """One measurement of these frames, then ``other``'s (binned alike; this one's uid and metadata).

        Each frame keeps where the chamber's stage stood; a camera's profiles, images and floors are
        kept where both have them.
        """
        if self.spec != other.spec:
            raise MeasurementError(f"cannot join frames binned as {other.spec.fingerprint()} to frames binned as "
                                   f"{self.spec.fingerprint()}")
        screen = None
        if self.screen is not None or other.screen is not None:
            screen = np.vstack([as_screen(self.screen, self.n), as_screen(other.screen, other.n)])
        floors: list[np.ndarray | None] = [None, None]
        if self.floor_x is not None or other.floor_x is not None:
            floors = [np.vstack([_or_zeros(a.floor_x if k == 0 else a.floor_y, a.hist_x if k == 0 else a.hist_y)
                                 for a in (self, other)]) for k in (0, 1)]

        def both(name: str):
            a, b = getattr(self, name), getattr(other, name)
            return None if a is None or b is None else np.concatenate([np.asarray(a), np.asarray(b)])
        profiles = {} if self.profile_spec != other.profile_spec else {
            k: both(k) for k in ("profile_x", "profile_y", "profile_floor_x", "profile_floor_y", "images")}
        return Measurement(np.vstack([self.configurations, other.configurations]),
                           np.vstack([self.hist_x, other.hist_x]), np.vstack([self.hist_y, other.hist_y]),
                           n_rays=self.n_rays, spec=self.spec, names=self.names, uid=self.uid,
                           metadata=dict(self.metadata), screen=screen, floor_x=floors[0], floor_y=floors[1],
                           total_counts=both("total_counts"), **profiles)

    def rebinned(self, coarse: HistogramSpec) -> Measurement:
        """The same measurement in coarser bins (e.g. the paper's, for the surrogate)."""
        hx, hy = self.spec.rebin(self.hist_x, self.hist_y, coarse)
        fx = fy = None
        # (both floors or neither) independent pixels: the floors add up as the bins do
        if self.floor_x is not None and self.floor_y is not None:
            fx, fy = self.spec.rebin(self.floor_x, self.floor_y, coarse)
        return replace(self, hist_x=hx, hist_y=hy, spec=coarse, floor_x=fx, floor_y=fy)

    def check_table(self, table: ParameterTable = METRIXS) -> None:
        """Raise if the measurement was taken with a different parameter table."""
        if tuple(self.names) != tuple(table.names):
            raise MeasurementError(f"measurement {self.uid or ''} uses other parameters than table {table.name!r}: "
                                   f"{table.diff({'names': list(self.names), 'low': [], 'high': []})}")
        v = self.table_version
        if v is not None and v != table.version:
            raise MeasurementError(f"measurement {self.uid or ''} was taken with parameter-table version {v}, "
                                   f"current is {table.version} (ranges changed)")

    def for_analysis(self, n_rays: int | None = None, table: ParameterTable = METRIXS,
                     resolution: str = "camera") -> Measurement:
        """The measurement as the fits read it: one binning, the table's parameters, its ray budget.

        ``resolution="camera"`` takes the camera-resolution profiles where it has them (the
        paper's histograms otherwise); ``"paper"`` the 50 x 50 ones.  ``n_rays`` overrides the
        ray budget.  Raises :class:`~bluesky_offsets.model.misfit.MeasurementError` for another
        parameter table, a configuration outside it, or an unknown ray budget.
        """
        if resolution not in RESOLUTIONS:
            raise InputError(f"resolution must be 'camera' or 'paper', not {resolution!r}")
        self.check_table(table)
        try:
            cfg = table.validate(self.configurations, "measured configurations")
        except ValueError as exc:
            raise MeasurementError(str(exc)) from None
        rays = n_rays or self.n_rays
        if not rays:
            raise MeasurementError(f"measurement {self.uid or ''} does not say its ray budget; pass n_rays")
        if (resolution == "camera" and self.profile_x is not None and self.profile_y is not None
                and self.profile_spec is not None):
            return replace(self, configurations=cfg, hist_x=self.profile_x, hist_y=self.profile_y,
                           spec=self.profile_spec, n_rays=int(rays), profile_x=None, profile_y=None, images=None,
                           floor_x=self.profile_floor_x, floor_y=self.profile_floor_y,
                           profile_floor_x=None, profile_floor_y=None)
        return replace(self, configurations=cfg, n_rays=int(rays), profile_x=None, profile_y=None, images=None,
                       profile_floor_x=None, profile_floor_y=None)

    def scaled(self, factor: float) -> Measurement:
        """The measured fractions times ``factor``, the floors times its square.

        These are a camera's frames reduced with another gain (``factor`` = the gain used / the gain
        measured); this measurement itself for a factor of 1.
        """
        if factor == 1.0:
            return self

        def times(a, f):
            return None if a is None else np.asarray(a, float) * f
        return replace(self, hist_x=self.hist_x * factor, hist_y=self.hist_y * factor,
                       profile_x=times(self.profile_x, factor), profile_y=times(self.profile_y, factor),
                       floor_x=times(self.floor_x, factor**2), floor_y=times(self.floor_y, factor**2),
                       profile_floor_x=times(self.profile_floor_x, factor**2),
                       profile_floor_y=times(self.profile_floor_y, factor**2))

    @property
    def floor(self) -> np.ndarray | None:
        """``(n, bins_x + bins_y)``: the camera's own noise per bin (fraction²), None without a camera."""
        return None if self.floor_x is None else np.concatenate([self.floor_x, self.floor_y], axis=1)


def _or_zeros(floor, like):
    return np.zeros_like(np.asarray(like, float)) if floor is None else floor


def _floors(fx, fy, n: int, spec: HistogramSpec):
    """The floors as (n, bins) arrays, both or neither, finite and non-negative."""
    if fx is None and fy is None:
        return None, None
    if fx is None or fy is None:
        raise MeasurementError("measurement: a camera's noise floor needs both x and y")
    fx, fy = (np.broadcast_to(np.asarray(f, float), (n, b)).copy() for f, b in ((fx, spec.bins_x), (fy, spec.bins_y)))
    if not (np.isfinite(fx).all() and np.isfinite(fy).all() and (fx >= 0).all() and (fy >= 0).all()):
        raise MeasurementError("measurement: a camera's noise floor must be finite and non-negative")
    return fx, fy
