"""Which frames to take next: candidates the beamline can reach, and the most informative of them.

Candidates are settings of the motors (each within its limits: the motors' readbacks are the
twin's coordinates), the slit openings and the chamber's stage, drawn around settings where the
beam is known to be on the screen.  A candidate is kept only where the model, under the current
posterior of the offsets, puts the beam on the screen with high probability: its predicted share
of the source's photons minus ``confidence`` times that share's linearized posterior spread is
above ``floor``.  Of those, :func:`select` takes a batch greedily by the criterion:

* ``"D"`` (default): the largest gain of ``log det`` of the posterior precision.  Invariant to the
  offsets' units and to any regrouping of them, it rewards information along every direction
  the current frames leave open: the compensating combinations that keep offsets undetermined.
* ``"A"``: the largest fall of the trace of the posterior covariance (the mean variance of the
  normalized offsets): it chases the offsets that are already cheap to pin down.

``benchmarks/bench_design.py --criterion A|D`` runs the designed measurement's benchmark with either.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.options import refuse_unknown
from bluesky_offsets.physics.parameters import MAX_OFFSET, METRIXS, ParameterTable
from bluesky_offsets.physics.screen import STAGE

CRITERIA = ("D", "A")
PRIOR_SIGMA = MAX_OFFSET / math.sqrt(3.0)
"""The offsets' prior: uniform within ±MAX_OFFSET of each range (normalized)."""
DETERMINED, UNDETERMINED = 0.1, 0.5
"""An offset is determined where its posterior σ is below this share of the prior's, undetermined above."""


@dataclass(frozen=True, kw_only=True)
class DesignOptions:
    """How the measurement is designed.

    Parameters
    ----------
    frames : int
        frames in all, the beam search's included (the budget).
    batch : int
        frames chosen per step (the posterior is updated between steps).
    candidates : int
        candidate settings drawn per step.
    criterion : str
        ``"D"`` or ``"A"`` (:func:`select`).
    rays : int
        model rays per candidate's Jacobian.
    fit_rays : int
        model rays per frame of the fits that update the posterior between steps.
    floor : float
        the least share of the source's photons a designed frame must put on the screen.
    confidence : float
        posterior σ of the predicted share the floor must hold at.
    screen : bool
        move the chamber's stage (x, y, z) too.
    slits : float
        share of candidates with a slit opening drawn anew.
    move : float
        share of the motors a candidate moves.
    target : float or None
        stop once every offset's predicted σ is below this share of the prior's (None: the
        budget alone).
    validation : int
        frames taken after the calibration, far from the fitted ones, that no fit uses.
    seed : int
        the candidates' random stream.
    """

    frames: int = 60
    batch: int = 8
    candidates: int = 120
    criterion: str = "D"
    rays: int = 1600
    fit_rays: int = 2000
    floor: float = 0.02
    confidence: float = 2.0
    screen: bool = True
    slits: float = 0.3
    move: float = 0.3
    target: float | None = None
    validation: int = 6
    seed: int = 0

    def __post_init__(self):
        if self.criterion not in CRITERIA:
            raise InputError(f"criterion must be one of {CRITERIA}, not {self.criterion!r}")
        for name in ("frames", "batch", "candidates", "rays", "fit_rays"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"design option {name} must be at least 1, got {getattr(self, name)!r}")
        if self.validation < 0:
            raise InputError(f"validation frames must be >= 0, got {self.validation}")
        if not 0 < self.floor < 1:
            raise InputError(f"floor must lie in (0, 1), got {self.floor}")
        if not (self.confidence >= 0 and math.isfinite(self.confidence)):
            raise InputError(f"confidence must be a finite number >= 0, got {self.confidence}")
        for name in ("slits", "move"):
            if not 0 <= getattr(self, name) <= 1:
                raise InputError(f"design option {name} must lie in [0, 1], got {getattr(self, name)}")
        if self.target is not None and not 0 < self.target < 1:
            raise InputError(f"target must lie in (0, 1), got {self.target}")

    @classmethod
    def from_mapping(cls, options: Mapping | None = None, **more) -> DesignOptions:
        """Options from a mapping; an unknown key is refused, naming the known ones."""
        opts = {**dict(options or {}), **more}
        refuse_unknown(cls, opts, "unknown design option(s)")
        return cls(**opts)

    def replace(self, **changes) -> DesignOptions:
        """These options with ``changes`` (field names and values) applied, validated as :meth:`from_mapping`."""
        return DesignOptions.from_mapping({f.name: getattr(self, f.name) for f in fields(self)}, **changes)


# --------------------------------------------------------------------------- #
# candidates
# --------------------------------------------------------------------------- #
def candidate_settings(anchors: np.ndarray, n: int, rng: np.random.Generator, *, acceptance: np.ndarray,
                       options: DesignOptions, table: ParameterTable = METRIXS) -> tuple[np.ndarray, np.ndarray]:
    """``n`` settings ``(configurations (n, P), screen (n, 3))`` drawn around ``anchors``.

    ``anchors``: settings (twin coordinates) where the beam was on the screen.  Each setting moves a
    share ``options.move`` of the motors by up to a random fraction of 2.5 times their acceptance
    (the normalized half-width over which the beam keeps half its light,
    :func:`bluesky_offsets.offsets.beam_search.acceptance`), draws a slit opening anew with
    probability ``options.slits`` (log-uniform over its travel, above twice the largest offset the
    model allows it: the slit stays open) and places the stage anywhere in its travel along the beam
    (and up to ±1 mm across it, less where the detector's window is narrow).  Every value lies
    within its motor's limits; fixed parameters stay at their design values.
    """
    anchors = np.atleast_2d(anchors)
    base = anchors[rng.integers(len(anchors), size=n)]
    z = (base - table.low) / table.span
    motors = np.flatnonzero(table.motorized)
    openings = [i for i in motors if table.parameters[i].travel is not None]
    moving = [i for i in motors if i not in openings]
    acc = np.nan_to_num(np.asarray(acceptance, float), nan=0.2)
    reach = np.minimum(0.45, 2.5 * acc)
    scale = np.exp(rng.uniform(np.log(0.15), 0.0, n))
    move = rng.random((n, len(moving))) < options.move
    step = rng.uniform(-1.0, 1.0, (n, len(moving))) * reach[moving] * scale[:, None]
    z[:, moving] = z[:, moving] + np.where(move, step, 0.0)
    cfg = z * table.span + table.low
    for i in motors:
        lo, hi = table.parameters[i].limits
        cfg[:, i] = np.clip(cfg[:, i], lo, hi)
    for i in openings:
        lo, hi = table.parameters[i].limits
        lo = max(lo, 2 * MAX_OFFSET * table.span[i])  # open under any offset the model allows
        pick = rng.random(n) < options.slits
        cfg[pick, i] = np.exp(rng.uniform(np.log(lo), np.log(hi), int(pick.sum())))
    cfg[:, ~table.motorized] = table.reference[~table.motorized]
    screen = np.zeros((n, 3))
    if options.screen:
        zax, xax, yax = STAGE[2], STAGE[0], STAGE[1]
        along = rng.random(n) < 0.7
        screen[along, 2] = rng.uniform(zax.low, zax.high, int(along.sum()))
        across = rng.random(n) < 0.3
        wx, wy = _across(table)
        screen[across, 0] = rng.uniform(max(xax.low, -wx), min(xax.high, wx), int(across.sum()))
        screen[across, 1] = rng.uniform(max(yax.low, -wy), min(yax.high, wy), int(across.sum()))
    return cfg, screen


def _across(table: ParameterTable) -> tuple[float, float]:
    """How far (mm) the stage moves the screen across the beam, per axis (x, y).

    1 mm, or 0.4 of the detector's half window where that is narrower (the beam stays in the
    window the fits read).
    """
    from bluesky_offsets.physics.beamline import of_table
    bl = of_table(table)
    if bl is None or bl.builtin is not None:
        return 1.0, 1.0
    d = bl.detector
    x, y = (min(1.0, 0.2 * (hi - lo)) for lo, hi in (d.histogram_x, d.histogram_y))
    return x, y


# --------------------------------------------------------------------------- #
# the posterior the design works with, and the choice
# --------------------------------------------------------------------------- #
def prior_precision(n: int, sigma: float = PRIOR_SIGMA) -> np.ndarray:
    """The prior's precision of ``n`` normalized offsets: the identity over ``sigma`` squared."""
    return np.eye(n) / sigma ** 2


def predicted_sigma(precision: np.ndarray) -> np.ndarray:
    """Each offset's posterior σ (normalized) after compensation by all others."""
    return np.sqrt(np.clip(np.diag(np.linalg.inv(precision)), 0.0, None))


def classes(sigma: np.ndarray, prior: float = PRIOR_SIGMA) -> list[str]:
    """``determined`` / ``weak`` / ``undetermined`` by σ against the prior's σ."""
    r = np.asarray(sigma) / prior
    return ["determined" if v < DETERMINED else "undetermined" if v >= UNDETERMINED else "weak" for v in r]


def criterion_value(precision: np.ndarray, criterion: str = "D") -> float:
    """``log det`` of the precision (D) or minus the trace of the covariance (A): larger is better."""
    if criterion == "D":
        return float(np.linalg.slogdet(precision)[1])
    return -float(np.trace(np.linalg.inv(precision)))


def _gains(precision: np.ndarray, fisher: np.ndarray, criterion: str) -> np.ndarray:
    if criterion == "D":
        try:
            L = np.linalg.cholesky(precision)
        except np.linalg.LinAlgError:  # rounding at very large precisions: a ridge of 1e-12 of the mean
            sym = 0.5 * (precision + precision.T)
            L = np.linalg.cholesky(sym + 1e-12 * np.trace(sym) / len(sym) * np.eye(len(sym)))
        Li = np.linalg.inv(L)
        M = Li @ fisher @ Li.T  # (C, P, P)
        eye = np.eye(len(precision))
        return np.linalg.slogdet(eye + M)[1]
    cov = np.linalg.inv(precision)
    return np.array([np.trace(cov) - np.trace(np.linalg.inv(precision + f)) for f in fisher])


@dataclass(frozen=True)
class Choice:
    """A chosen batch of candidate frames.

    The candidate indices in order, each one's predicted gain of the criterion, and the precision
    after all of them.
    """

    indices: list[int]
    gains: list[float]
    precision: np.ndarray


def select(fisher: np.ndarray, precision: np.ndarray, k: int, *, criterion: str = "D",
           allowed: np.ndarray | None = None) -> Choice:
    """Greedy batch of ``k`` candidates (their ``fisher`` matrices, (C, P, P)).

    Each is the one that adds most to the criterion given the ones chosen before it (the precision
    updated in turn); only ``allowed`` candidates (a mask), each at most once.
    """
    if criterion not in CRITERIA:
        raise InputError(f"criterion must be one of {CRITERIA}, not {criterion!r}")
    ok = np.ones(len(fisher), bool) if allowed is None else np.asarray(allowed, bool).copy()
    P = np.array(precision, float)
    chosen, gains = [], []
    for _ in range(min(k, int(ok.sum()))):
        g = np.where(ok, _gains(P, fisher, criterion), -np.inf)
        i = int(np.argmax(g))
        chosen.append(i)
        gains.append(float(g[i]))
        ok[i] = False
        P = P + fisher[i]
    return Choice(chosen, gains, P)


def far_from(fitted: tuple[np.ndarray, np.ndarray], candidates: tuple[np.ndarray, np.ndarray], n: int, *,
             allowed: np.ndarray | None = None, table: ParameterTable = METRIXS) -> list[int]:
    """``n`` of the ``candidates`` (configurations, screen) as far as possible from the ``fitted`` settings.

    Far also from each other (farthest-point order): distances over the motors in units of their
    travel and the stage's axes in units of theirs.  The frames a calibration is tested on.
    """
    def coords(cfg, screen):
        lo = np.array([p.limits[0] for p in table])
        hi = np.array([p.limits[1] for p in table])
        z = (np.asarray(cfg) - lo) / (hi - lo)
        s = np.asarray(screen) / np.array([ax.span for ax in STAGE])
        return np.hstack([z[:, table.motorized], s])
    have = coords(*fitted)
    cand = coords(*candidates)
    ok = np.ones(len(cand), bool) if allowed is None else np.asarray(allowed, bool).copy()
    d = np.min(np.linalg.norm(cand[:, None] - have[None], axis=-1), axis=1)
    out = []
    for _ in range(min(n, int(ok.sum()))):
        i = int(np.argmax(np.where(ok, d, -np.inf)))
        out.append(i)
        ok[i] = False
        d = np.minimum(d, np.linalg.norm(cand - cand[i], axis=-1))
    return out
