"""Finding the beam from a dark start, as an operator does.

Open the slits, then scan the motors the beam is most sensitive to, upstream first, watching the
counts.

Which motors need a scan, and how finely, comes from the model: :func:`acceptance` sweeps
each motor of the nominal twin around the start and measures over which part of its range
the beam keeps half its intensity.  A motor whose acceptance is wider than the offsets it may
carry never loses the beam by itself and is not scanned; the others are scanned over the
offsets' range with steps of about their acceptance (:func:`schedule`).  The plan that drives
the beamline is :func:`plans.search.find_beam`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from bluesky_offsets.model.diagnosis import open_aperture, open_settings
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable

SWEEP = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2)
"""Normalized distances (fractions of a motor's range) the acceptance sweep tries."""


@dataclass(frozen=True)
class ScanStep:
    """One motor scanned over ``positions`` (normalized, relative to where the search stands)."""

    name: str
    positions: tuple[float, ...]
    acceptance: float


def intensity(hist_x, hist_y) -> np.ndarray:
    """The beam's intensity on the screen: the x and y histograms summed, as the paper's threshold counts them.

    Each histogram sums to the share of the source rays on the screen, so this is twice that share.
    """
    return np.nansum(np.atleast_2d(hist_x), axis=1) + np.nansum(np.atleast_2d(hist_y), axis=1)


def acceptance(twin, start, *, open_slits: bool = True, rays: int = 500, seed: int = 0,
               table: ParameterTable = METRIXS) -> np.ndarray:
    """Per parameter: the normalized half-width around ``start`` over which the model's beam keeps half its intensity.

    The half-width is taken with that motor alone moving (NaN for fixed parameters; the largest
    swept distance where it never drops that far).

    ``twin`` traces (``trace_batch``), e.g. ``Twin(TorchEngine())``; ``open_slits`` sweeps
    with the slits open (:func:`bluesky_offsets.model.diagnosis.open_aperture`), as the search does.
    """
    base = np.asarray(start, float)
    if open_slits:
        base = open_aperture(base[None], table=table)[0]
    motors = np.flatnonzero(table.motorized)
    rows, where = [base], []
    for j in motors:
        for u in SWEEP:
            for sign in (-1.0, 1.0):
                v = base.copy()
                v[j] = np.clip(v[j] + sign * u * table.span[j], table.low[j], table.high[j])
                rows.append(v)
                where.append((j, u))
    res = twin.trace_batch(np.asarray(rows), n_rays=rays, seed=seed, progress=False)
    inten = intensity(res.hist_x, res.hist_y)
    i0, out = inten[0], np.full(len(table), np.nan)
    for j in motors:
        out[j] = SWEEP[-1]
        for k, u in enumerate(SWEEP):
            pair = [inten[1 + i] for i, (jj, uu) in enumerate(where) if jj == j and uu == u]
            if i0 <= 0 or min(pair) < 0.5 * i0:
                out[j] = u if k == 0 else math.sqrt(u * SWEEP[k - 1])  # between the last kept and this
                break
    return out


def schedule(widths: np.ndarray, fraction: float, *, max_points: int = 9,
             table: ParameterTable = METRIXS) -> list[ScanStep]:
    """The motors to scan: those whose acceptance is narrower than the offsets they may carry.

    Upstream first (table order), each over ±``fraction`` of its range with steps of about its
    acceptance (at most ``max_points`` positions, the middle one the current position).
    """
    out = []
    for j, name in enumerate(table.names):
        w = widths[j]
        if not table.motorized[j] or not np.isfinite(w) or w >= fraction:
            continue
        k = min(max_points, 2 * math.ceil(fraction / w) + 1)
        k += 1 - k % 2  # odd: the current position is one of them
        out.append(ScanStep(name, tuple(float(p) for p in np.linspace(-fraction, fraction, k)), float(w)))
    return out


@dataclass
class SearchResult:
    """Where the search left the beamline, and how it got there."""

    configuration: np.ndarray        # physical, table order (the slits as they were at the start)
    intensity: float                 # at ``configuration``
    bright: bool
    frames: int
    log: list[str]
    measurements: list = field(default_factory=list, repr=False)  # the runs' frames (plans.search.find_beam)

    @property
    def uids(self) -> list[str]:
        """The uids of the runs that measured it."""
        return [m.uid for m in self.measurements]


def search(start, open_widths: np.ndarray, closed_widths: np.ndarray, *, threshold: float, fraction: float = 0.05,
           max_frames: int = 120, max_points: int = 9,
           table: ParameterTable = METRIXS):
    """The search as a coroutine; it returns a :class:`SearchResult`.

    It yields configurations (k, P) to measure and is sent their intensities (:func:`intensity`).
    ``threshold``: the intensity of a bright frame (``plans.search.HIGH_RAY_THRESHOLD``, the
    paper's).

    1. the start as it is: bright, done;
    2. the slits open (:data:`bluesky_offsets.model.diagnosis.OPEN_APERTURE`); each motor of the
       open-slit :func:`schedule` scanned in turn, upstream first, moving to the brightest
       position (a scan that sees no light leaves the motor where it was);
    3. the slits back as they were; the closed-slit schedule scanned the same way, each motor
       over the part of its range the first pass left uncertain (± one step of that pass);
    4. the brightest configuration seen with the slits as they were.

    The slit openings themselves are never scanned (the operator sets them).  Every yield
    counts its configurations against ``max_frames``.
    """
    start = np.asarray(table.validate(start, "start"), float)
    frames, log = 0, []
    best = [start.copy(), -1.0]

    def note(cfg, value):
        if value > best[1]:
            best[0], best[1] = cfg.copy(), float(value)

    inten = (yield start[None])[0]
    frames += 1
    note(start, inten)
    log.append(f"start: {inten / 2:.3g} of the source rays on the screen")
    if inten > threshold:
        return SearchResult(start, float(inten), True, frames, log)
    skip = set(open_settings(table))  # the openings the search sets, never scanned
    cur = open_aperture(start[None], table=table)[0]
    cur_i = (yield cur[None])[0]
    frames += 1
    log.append(f"slits open: {cur_i:.3g}")
    spacing: dict[str, float] = {}
    for pass_, widths, slits in (("open", open_widths, "open"), ("closed", closed_widths, "as at the start")):
        if pass_ == "closed":
            cur = cur.copy()
            for name in skip:
                cur[table.index(name)] = start[table.index(name)]
            cur_i = (yield cur[None])[0]
            frames += 1
            note(cur, cur_i)
            log.append(f"slits {slits}: {cur_i:.3g}")
            if cur_i > threshold:
                break
        for step in schedule(widths, fraction, max_points=max_points, table=table):
            if step.name in skip:
                continue
            j = table.index(step.name)
            half = min(fraction, spacing.get(step.name, fraction))
            pts = np.linspace(-half, half, len(step.positions))
            cfgs = np.repeat(cur[None], len(pts), 0)
            cfgs[:, j] = np.clip(cur[j] + pts * table.span[j], table.low[j], table.high[j])
            if frames + len(cfgs) > max_frames:
                log.append(f"frame budget ({max_frames}) spent before {step.name}")
                break
            values = np.asarray((yield cfgs), float)
            frames += len(cfgs)
            k = int(np.argmax(values))
            if values[k] > 0 and values[k] >= cur_i:
                cur, cur_i = cfgs[k].copy(), float(values[k])
            spacing[step.name] = float(pts[1] - pts[0]) if len(pts) > 1 else half
            if pass_ == "closed":
                note(cur, cur_i)
            log.append(f"{pass_} slits, {step.name} over ±{half:.3g} of its range in {len(pts)} steps: "
                       f"best {values[k]:.3g} at {pts[k]:+.3g}")
    b, bi = best
    return SearchResult(b, bi, bi > threshold, frames, log)

