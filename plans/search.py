"""Find configurations whose footprint has enough rays (paper Sec. 2.2).

Most configurations of the 34-parameter box put (almost) no rays on the
focus-chamber screen, and an empty footprint says little about the offsets.
The paper therefore uses only configurations whose histogram sum exceeds 0.5
and asks for more than 15 of them.

Threshold in our units
----------------------
The paper's histograms are raw bin counts at 1e5 source rays divided by
22594, so a sum of 0.5 means 0.5 x 22594 = 11297 rays of 1e5.  Our
histograms are fractions of the source rays, so the same threshold is
``0.5 * 22594 / 1e5 = 0.11297`` (:data:`HIGH_RAY_THRESHOLD`), applied, as in the
authors' code and in :mod:`bluesky_offsets.offsets.finder`, to the sum over all 100 bins
(x and y histograms together): about 6 % of the source rays inside both windows.

Two searches: :func:`high_ray_configurations_on_model` on a model (the
twin or a surrogate, at the model's belief of the offsets), and the plan
:func:`find_high_ray_configurations` on the beamline.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
from bluesky.utils import MsgGenerator

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable

from .measure import scan_configurations

if TYPE_CHECKING:
    from bluesky_offsets.offsets.beam_search import SearchResult

steps_log = logging.getLogger("bluesky_offsets.workflow")  # the session's step lines (commands.session.StepLines)

PAPER_THRESHOLD = 0.5
"""Histogram-sum threshold of the paper, in its units (raw counts / 22594 at 1e5 rays)."""
PAPER_SCALE = 22594 / 1e5
HIGH_RAY_THRESHOLD = PAPER_THRESHOLD * PAPER_SCALE
"""The paper's threshold in fraction-of-source-rays units: 0.11297."""
MIN_CONFIGURATIONS = 16
"""The paper asks for n > 15 configurations."""


def enough_rays(hist_x, hist_y, threshold: float = HIGH_RAY_THRESHOLD) -> np.ndarray:
    """True where the sum of the x and y histograms exceeds ``threshold`` (rows = configurations)."""
    sx = np.nansum(np.atleast_2d(hist_x), axis=1)
    sy = np.nansum(np.atleast_2d(hist_y), axis=1)
    return sx + sy > threshold


def sample_candidates(n: int, *, rng: np.random.Generator | int | None = None, around=None,
                      spread: float | np.ndarray | None = None, table: ParameterTable = METRIXS) -> np.ndarray:
    """``n`` candidate configurations, uniform in the sampling box or around ``around``.

    Uniform in the sampling box (the paper), or uniform within ``±spread`` (normalized units,
    scalar or per parameter) around ``around``, clipped to the box.  Fixed parameters stay at
    their design values.
    """
    rng = np.random.default_rng(rng)
    if around is None:
        cand = table.sample_uniform(n, rng)
    else:
        centre = table.normalize(around)
        s = np.broadcast_to(np.asarray(0.1 if spread is None else spread, float), centre.shape)
        cand = table.denormalize(np.clip(centre + rng.uniform(-1, 1, (n, len(table))) * s, 0, 1))
    cand[:, ~table.motorized] = table.reference[~table.motorized]
    return cand


def _evaluate(model, values: np.ndarray, n_rays: int | None) -> tuple[np.ndarray, np.ndarray]:
    if hasattr(model, "trace_batch"):  # the twin
        kw = {"n_rays": n_rays} if n_rays else {}
        b = model.trace_batch(values, progress=False, **kw)
        return b.hist_x, b.hist_y
    out = model(values)
    if isinstance(out, tuple) and len(out) == 2:
        return np.asarray(out[0]), np.asarray(out[1])
    out = np.asarray(out)  # (N, bins_x + bins_y), the surrogate's layout
    half = out.shape[1] // 2
    return out[:, :half], out[:, half:]


def high_ray_configurations_on_model(model, n: int = MIN_CONFIGURATIONS, *, candidates: int | np.ndarray = 1000,
                                     offsets=None, threshold: float = HIGH_RAY_THRESHOLD,
                                     rng: np.random.Generator | int | None = None, around=None,
                                     spread: float | np.ndarray | None = None, n_rays: int | None = None,
                                     chunk: int = 64, table: ParameterTable = METRIXS,
                                     progress: bool = True) -> np.ndarray:
    """Configurations whose modelled footprint has enough rays.

    Parameters
    ----------
    model : Twin or callable
        The twin (``trace_batch``), or ``f(values (N, P)) -> (hist_x, hist_y)``
        or ``-> (N, bins_x + bins_y)`` (a surrogate).
    n : int
        How many configurations to return (paper: n > 15).
    candidates : int or ndarray
        Number of candidates to draw (:func:`sample_candidates`) or the candidates.
    offsets : array_like, optional
        Normalized offsets (fractions of range) added before evaluating: the
        model's current belief of the beamline's offsets (default none).
    threshold : float
        Histogram-sum threshold, fraction of source rays (default 0.113).
    around, spread : optional
        Draw candidates near a configuration instead of from the whole box.

    Returns
    -------
    ndarray, shape (n, P)
        The first ``n`` candidates that pass, in twin coordinates (without offsets).

    Raises
    ------
    ValueError
        When fewer than ``n`` candidates pass; the message gives the count.
    """
    from bluesky_offsets.progress import bar as progress_bar

    # the ignore: np.isscalar's TypeGuard replaces ``int | ndarray`` by numpy's scalar types, which int() refuses
    cand = (sample_candidates(int(candidates), rng=rng, around=around,  # type: ignore[arg-type]
                              spread=spread, table=table)
            if np.isscalar(candidates) else table.validate(np.atleast_2d(candidates), "candidates"))
    shift = 0.0 if offsets is None else table.offsets_to_physical(offsets)
    found: list[np.ndarray] = []
    with progress_bar(total=n, desc="high-ray configurations", unit="cfg", disable=not progress) as bar:
        for i in range(0, len(cand), chunk):
            block = cand[i:i + chunk]
            hx, hy = _evaluate(model, block + shift, n_rays)
            good = block[enough_rays(hx, hy, threshold)]
            take = good[: n - len(found)]
            found.extend(take)
            bar.update(len(take))
            if len(found) >= n:
                break
    if len(found) < n:
        raise InputError(f"only {len(found)} of {len(cand)} candidates put more than {threshold:.4g} of the "
                         f"source rays on the screen; {n} needed (draw more candidates or search nearer a "
                         f"known good configuration)")
    return np.array(found)


def find_high_ray_configurations(candidates, beamline, chamber, *, n: int = MIN_CONFIGURATIONS,
                                 threshold: float = HIGH_RAY_THRESHOLD, reference=None,
                                 table: ParameterTable = METRIXS, md: Mapping | None = None,
                                 require_all: bool = False) -> MsgGenerator[np.ndarray]:
    """Measure candidates on the beamline until ``n`` have enough rays; return those.

    Each candidate is one event of the run (histograms and readbacks), so
    the search itself is recorded.  Candidates are reached by differences
    from ``reference`` as in :func:`plans.measure_configurations`; the motors
    return to their start positions at the end.

    Parameters
    ----------
    candidates : array_like or sequence of mapping
        Configurations to try, in order (e.g. from :func:`sample_candidates`
        around the current configuration).
    n : int
        Stop after this many pass (paper: n > 15).
    threshold : float
        Histogram-sum threshold in fraction of source rays (default 0.113, see module notes).
    require_all : bool
        Raise ``ValueError`` when fewer than ``n`` pass (default: return what passed).

    Returns
    -------
    ndarray, shape (k, P)
        Passing configurations (twin coordinates), ``k <= n``.
    """
    accepted: list[int] = []

    def keep_going(k: int, reading: dict) -> bool:
        hx = next(v["value"] for key, v in reading.items() if key.endswith("hist_x"))
        hy = next(v["value"] for key, v in reading.items() if key.endswith("hist_y"))
        if enough_rays(hx, hy, threshold)[0]:
            accepted.append(k)
        return len(accepted) < n

    _md = {"plan_name": "find_high_ray_configurations", "purpose": "search for high-ray configurations",
           "threshold": threshold, "threshold_units": "fraction of source rays (paper: 0.5 x 22594/1e5)",
           "n_wanted": n}
    _md.update(md or {})
    m = yield from scan_configurations(candidates, beamline, chamber, reference=reference, table=table,
                                       md=_md, keep_going=keep_going)
    good = m.configurations[enough_rays(m.hist_x, m.hist_y, threshold)] if len(m) else m.configurations
    if require_all and len(good) < n:
        raise InputError(f"only {len(good)} of {len(m)} measured candidates passed the threshold "
                         f"{threshold:.4g}; {n} needed")
    return good



def find_beam(beamline, chamber, *, fraction: float = 0.15, twin=None, max_frames: int = 120,
              threshold: float = HIGH_RAY_THRESHOLD, table: ParameterTable = METRIXS,
              md: Mapping | None = None) -> MsgGenerator:
    """Bring the beam onto the screen from a dark or dim start, as an operator does.

    :func:`bluesky_offsets.offsets.beam_search.search`: the start as it is; else the slits opened and
    the motors the beam is most sensitive to scanned one by one, upstream first, watching the
    counts; then the slits closed again and the same motors scanned finely.  Which motors,
    over what range and in how many steps comes from the model (the nominal twin's acceptance
    of each motor, :func:`bluesky_offsets.offsets.beam_search.acceptance`) and from ``fraction``, the
    offsets the motors may carry (normalized; 0.15 = 15 % of each range).  Every scan is a run
    of its own in the store (``purpose`` "beam search").  The motors stay where the brightest
    frame with the slits as they were was taken.

    Parameters
    ----------
    twin : Twin, optional
        Traces the acceptance sweeps (default: the torch twin, in this process).
    max_frames : int
        Frames the search may take.

    Returns
    -------
    bluesky_offsets.offsets.beam_search.SearchResult
        The configuration (twin coordinates, motor readbacks), its intensity, whether it is
        bright (``threshold``), the frames used, a line per step, the uids of its runs and their frames.
    """
    from bluesky_offsets.offsets.beam_search import acceptance, intensity, search
    from bluesky_offsets.physics.beamline import torch_engine
    from bluesky_offsets.physics.twin import Twin

    from .measure import scan_configurations
    from .motion import current_configuration, move_to, resolve_motors

    if not 0 < fraction <= 0.2:
        raise InputError(f"fraction must lie in (0, 0.2], got {fraction}")
    here = yield from current_configuration(beamline, table)
    twin = twin or Twin(torch_engine(table))
    widths = (acceptance(twin, here, open_slits=True, table=table), acceptance(twin, here, open_slits=False,
                                                                               table=table))
    gen = search(here, *widths, fraction=fraction, threshold=threshold, max_frames=max_frames, table=table)
    cfgs = next(gen)
    step, runs = 0, []
    while True:
        step += 1
        _md = {"plan_name": "find_beam", "purpose": "beam search", "search_step": step, "fraction": fraction,
               **dict(md or {})}
        m = yield from scan_configurations(cfgs, beamline, chamber, md=_md, table=table)
        runs.append(m)
        try:
            cfgs = gen.send(intensity(m.hist_x, m.hist_y))
        except StopIteration as done:
            result = done.value
            break
    motors = resolve_motors(beamline, table)
    yield from move_to(motors, {n: float(result.configuration[table.index(n)]) for n in motors})
    result.measurements = runs
    return result


def lit_frames(runs, threshold: float = HIGH_RAY_THRESHOLD):
    """The frames of ``runs`` (measurements) with enough rays (:func:`enough_rays`), joined; None if none.

    The beam search's bright frames say as much about the offsets as any other frame; its dark ones
    only where the beam is not.
    """
    lit = [r.subset(np.flatnonzero(enough_rays(r.hist_x, r.hist_y, threshold))) for r in runs if r.n]
    lit = [r for r in lit if r.n]
    if not lit:
        return None
    out = lit[0]
    for r in lit[1:]:
        out = out.joined(r)
    return out


class DarkBeamline(RuntimeError):
    """The beam search or the bright-configuration search came back without enough light.

    ``what`` says what ended dim; ``advice`` what a plan's caller can change (a command line says its own).
    """

    def __init__(self, what: str, advice: str = ""):
        super().__init__(f"{what}: {advice}" if advice else what)
        self.what = what


def bright_beam(beamline, chamber, *, fraction: float, max_frames: int,
                table=METRIXS) -> MsgGenerator[SearchResult]:
    """:func:`find_beam`, its steps logged; :class:`DarkBeamline` where it ends dim."""
    steps_log.info("finding the beam (offsets up to ±%g of each range assumed)", fraction)
    beam = yield from find_beam(beamline, chamber, fraction=fraction, max_frames=max_frames, table=table)
    for line in beam.log:
        steps_log.info("  %s", line)
    if not beam.bright:
        raise DarkBeamline(f"the beam search ended dim after {beam.frames} frames ({beam.intensity:.3g} of the "
                           f"source rays on the screen, {HIGH_RAY_THRESHOLD:.3g} needed)",
                           "check the shutter, the source and the slits, or widen the search (fraction, the frames "
                           "it may take)")
    return beam
