"""What a calibration knows about each offset: value ± σ, whether the data determine it, with whom it trades.

A fit's covariance (:class:`~bluesky_offsets.model.state.CalibratedState`) holds the offsets'
posterior in normalized units (fractions of each range); this module says it per parameter in
its physical unit, after compensation by all others:

* ``determined``: σ below a tenth of the prior's (the offsets' prior: uniform within ±20 % of each
  range, σ = 0.2/√3 of the range);
* ``undetermined``: σ above half the prior's (the data barely beat the prior);
* ``weak`` in between.

The values and σ are under the offsets' prior the fit held: the table's, or the spread the data
prefer (:func:`evidence_spread`); the classes always read the σ under the table's prior
(:func:`with_prior`), so that they say what the frames determine, not what the spread does.

Each offset's strongest compensating partners are the largest correlations of the posterior;
the determined combinations are the posterior's directions with σ below a tenth of the prior's
that are not one offset alone (two mirrors tilted against each other move the focus back:
their difference may be known where neither is).  An undetermined offset is always printed as
such, never as a value alone.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from bluesky_offsets.physics import effects as E
from bluesky_offsets.physics.parameters import MAX_OFFSET, METRIXS, ParameterTable, at_offset_bound

PRIOR_SIGMA = MAX_OFFSET / math.sqrt(3.0)
DETERMINED, UNDETERMINED = 0.1, 0.5
PARTNER_CORRELATION = 0.5
"""A partner is an offset correlated with this one beyond this (in absolute value)."""


def scaled_inverse(a: np.ndarray) -> np.ndarray:
    """The pseudo-inverse of a symmetric matrix, scaled to unit diagonal first.

    Scaled because the parameters' units differ by orders of magnitude.
    """
    d = np.sqrt(np.clip(np.diag(a), 1e-300, None))
    return np.linalg.pinv(a / np.outer(d, d), rcond=1e-12) / np.outer(d, d)


def _information(covariance: np.ndarray, n_offsets: int, prior_sigma: float) -> np.ndarray:
    """What the data alone say: the precision of ``covariance`` less its offsets' prior (negative parts dropped)."""
    q = scaled_inverse(covariance)
    q[np.arange(n_offsets), np.arange(n_offsets)] -= prior_sigma ** -2.0
    w, v = np.linalg.eigh(0.5 * (q + q.T))
    return (v * np.clip(w, 0.0, None)) @ v.T


def _under(information: np.ndarray, b: np.ndarray, n_offsets: int,
           precision: float) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussian posterior's mean and covariance: the data's ``information``, ``b``, the offsets' prior precision."""
    a = information.copy()
    a[np.arange(n_offsets), np.arange(n_offsets)] += precision
    cov = scaled_inverse(a)
    return cov @ b, cov


def with_prior(covariance: np.ndarray, n_offsets: int, prior_sigma: float, to_sigma: float) -> np.ndarray:
    """``covariance`` (offsets first, their Gaussian prior σ ``prior_sigma``) under the prior σ ``to_sigma`` instead.

    The same information from the data, another prior: what the class of an offset is read from
    when the fit's prior was the spread estimated from the data.  Rows the data do not see (NaN) stay NaN.
    """
    cov = np.asarray(covariance, float)
    ok = np.isfinite(np.diag(cov))
    k = int(ok[:n_offsets].sum())
    f = _information(cov[np.ix_(ok, ok)], k, prior_sigma)
    out = np.full_like(cov, np.nan)
    out[np.ix_(ok, ok)] = _under(f, np.zeros(len(f)), k, to_sigma ** -2.0)[1]
    return out


def evidence_spread(vector: np.ndarray, covariance: np.ndarray, n_offsets: int, prior_sigma: float,
                    iterations: int = 200) -> float:
    """The offsets' prior σ the data prefer, within [a tenth, all] of ``prior_sigma``: where the evidence is largest.

    ``vector``: a fit's solution, its ``n_offsets`` normalized offsets first, then effect
    parameters; ``covariance``: its posterior under the offsets' Gaussian prior σ ``prior_sigma``.
    In the Gaussian approximation the posterior under a prior σ τ has the mean
    m(τ) = (F + τ⁻²)⁻¹ b (F the data's information, b the posterior's precision times its mean);
    the evidence is largest where τ² = ‖m(τ)'s offsets‖² / γ, γ = n − τ⁻² tr Σ(τ)'s offsets the
    number the data determine (MacKay's fixed point).  Why: the table's prior spans ±20 % of
    each range, a beamline's offsets may be far smaller, and the offsets the frames barely see
    then wander within the wider prior (docs/explanations/offsets.md, "The offsets' spread").
    Not below a tenth of ``prior_sigma`` (the σ that counts as determined): few determined
    directions estimate a spread coarsely, and one too narrow would claim every offset known.
    """
    cov = np.asarray(covariance, float)
    ok = np.isfinite(np.diag(cov))
    k = int(ok[:n_offsets].sum())
    z = np.asarray(vector, float)[ok]
    f = _information(cov[np.ix_(ok, ok)], k, prior_sigma)
    b = scaled_inverse(cov[np.ix_(ok, ok)]) @ z
    # λ = τ⁻², between the table's prior's and a tenth of its σ's
    lam, lowest, highest = prior_sigma ** -2.0, prior_sigma ** -2.0, (DETERMINED * prior_sigma) ** -2.0
    for _ in range(iterations):
        m, c = _under(f, b, k, lam)
        gamma = k - lam * float(np.trace(c[:k, :k]))
        new = min(max(gamma / max(float(m[:k] @ m[:k]), 1e-300), lowest), highest)
        if abs(new / lam - 1.0) < 1e-9:
            break
        lam = new
    return float(lam ** -0.5)


def shrunk_mean(vector: np.ndarray, covariance: np.ndarray, n_offsets: int, prior_sigma: float,
                to_sigma: float) -> np.ndarray:
    """The Gaussian posterior's mean of a fit's ``vector`` (offsets first) under the offsets' prior σ ``to_sigma``.

    ``covariance`` holds the offsets' prior σ ``prior_sigma``: m = (F + to_sigma⁻²)⁻¹ b, as in
    :func:`evidence_spread`.  Rows the data do not see keep their values.
    """
    cov = np.asarray(covariance, float)
    ok = np.isfinite(np.diag(cov))
    k = int(ok[:n_offsets].sum())
    z = np.asarray(vector, float)
    f = _information(cov[np.ix_(ok, ok)], k, prior_sigma)
    out = z.copy()
    out[ok] = _under(f, scaled_inverse(cov[np.ix_(ok, ok)]) @ z[ok], k, to_sigma ** -2.0)[0]
    return out


def classify(ratio: float) -> str:
    """``determined`` / ``weak`` / ``undetermined`` for a posterior σ over the prior's σ."""
    if not math.isfinite(ratio):
        return "undetermined"
    return "determined" if ratio < DETERMINED else "undetermined" if ratio >= UNDETERMINED else "weak"


@dataclass(frozen=True)
class Estimate:
    """One parameter's posterior.

    Its value and σ in its unit, the same normalized by its range, the class, the strongest
    compensating partners ``[(name, correlation)]`` and whether a bound holds it.
    """

    name: str
    unit: str
    value: float
    sigma: float
    normalized: float
    normalized_sigma: float
    cls: str
    partners: tuple[tuple[str, float], ...] = ()
    at_bound: bool = False
    determination: float = math.nan
    """σ over the prior's σ, both under the table's prior: what the class is read from."""

    def text(self) -> str:
        """``-1.49 ± 0.30 mrad``; an undetermined one says so first."""
        v = f"{self.value:+.4g} ± {self.sigma:.2g} {self.unit}" if math.isfinite(self.sigma) else \
            f"{self.value:+.4g} {self.unit} (no σ)"
        return f"undetermined ({v})" if self.cls == "undetermined" else v

    def as_dict(self) -> dict:
        """The estimate as plain JSON values (value, σ, unit, class, normalized, partners, at_bound)."""
        return {"value": self.value, "sigma": self.sigma, "unit": self.unit, "class": self.cls,
                "normalized": self.normalized, "normalized_sigma": self.normalized_sigma,
                "partners": [[n, c] for n, c in self.partners], "at_bound": self.at_bound,
                "sigma_over_prior": self.determination if math.isfinite(self.determination) else None}


@dataclass(frozen=True)
class Posterior:
    """The posterior of a calibrated model: its offsets (table order) and effect parameters."""

    offsets: tuple[Estimate, ...]
    effects: dict[str, dict[str, Estimate]]
    combinations: tuple[dict, ...]
    covariance: np.ndarray
    names: tuple[str, ...]
    prior_sigma: float = PRIOR_SIGMA
    """The offsets' prior σ (normalized) of the values and σ: the table's, or the spread estimated from the data."""

    @classmethod
    def of(cls, model, table: ParameterTable = METRIXS) -> Posterior | None:
        """The posterior of a calibrated state (or an analysis, or a state with a covariance).

        None where no covariance is known.
        """
        from bluesky_offsets.model.state import CalibratedState
        cal = CalibratedState.of(model)
        if cal.covariance is None or cal.names is None:
            return None
        cov = np.asarray(cal.covariance, float)
        names = tuple(cal.names)
        st = cal.state
        n = len(table)
        sig = np.sqrt(np.clip(np.nan_to_num(np.diag(cov), nan=np.inf), 0.0, None))
        spread = PRIOR_SIGMA if cal.prior_sigma is None else float(cal.prior_sigma)
        # the class says what the data determine, against the table's prior whatever prior the fit held
        ref_cov = cov if spread == PRIOR_SIGMA else with_prior(cov, n, spread, PRIOR_SIGMA)
        ref = np.sqrt(np.clip(np.nan_to_num(np.diag(ref_cov), nan=np.inf), 0.0, None))
        d = np.where(np.isfinite(sig) & (sig > 0), sig, np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = cov / np.outer(d, d)
        offs = []
        for i, p in enumerate(table):
            z, s = float(st.offsets[i]), float(sig[i])
            ratio = float(ref[i]) / PRIOR_SIGMA
            offs.append(Estimate(p.name, p.unit, z * p.span, s * p.span, z, s, classify(ratio),
                                 _partners(corr, i, names[:n]), bool(at_offset_bound(z)), ratio))
        effects: dict[str, dict[str, Estimate]] = {}
        k = n
        for eff in st.effects:
            for q in E.get(eff).parameters:
                v, s = float(st.effects[eff][q.name]), float(sig[k]) if k < len(sig) else math.nan
                prior = q.span / math.sqrt(12.0)
                effects.setdefault(eff, {})[q.name] = Estimate(
                    f"{eff}.{q.name}", q.unit, v, s, v, s, classify(s / prior),
                    _partners(corr, k, names), bool(min(abs(v - q.low), abs(v - q.high)) < 1e-9 * max(q.span, 1)),
                    s / prior)
                k += 1
        return cls(tuple(offs), effects, _combinations(ref_cov[:n, :n], names[:n]), cov, names, spread)

    def counts(self) -> dict[str, int]:
        """How many offsets are determined, weak and undetermined."""
        out = {"determined": 0, "weak": 0, "undetermined": 0}
        for e in self.offsets:
            out[e.cls] += 1
        return out

    def as_dict(self) -> dict:
        """The posterior as plain JSON values, for ``summary.json`` and the calibration file.

        Per offset and effect parameter, the counts and the determined combinations.
        """
        return {"offsets": {e.name: e.as_dict() for e in self.offsets},
                "effects": {eff: {q: e.as_dict() for q, e in d.items()} for eff, d in self.effects.items()},
                "counts": self.counts(), "combinations": list(self.combinations),
                "prior_sigma_normalized": PRIOR_SIGMA, "spread_normalized": self.prior_sigma,
                "spread_estimated": self.prior_sigma != PRIOR_SIGMA, "thresholds": [DETERMINED, UNDETERMINED]}

    def rows(self) -> list[dict]:
        """One row per offset for a report's table."""
        return [{"parameter": e.name, "offset": e.text(), "class": e.cls,
                 "σ / prior": f"{e.determination:.2f}",
                 "trades with": ", ".join(f"{n} ({c:+.2f})" for n, c in e.partners) or "-",
                 **({"note": "at the ±20 % bound"} if e.at_bound else {})} for e in self.offsets]

    def lines(self) -> list[str]:
        """The posterior as text lines: the counts, one line per offset, the determined combinations."""
        c = self.counts()
        out = [f"offsets: {c['determined']} determined, {c['weak']} weak, {c['undetermined']} undetermined "
               f"(σ below 0.1 / above 0.5 of the prior's)"]
        if self.prior_sigma != PRIOR_SIGMA:
            out.append(f"  the offsets' spread, estimated from the data: σ {self.prior_sigma:.3g} of each range "
                       f"(the table's prior {PRIOR_SIGMA:.3g}); the values and ± below are under it, the classes "
                       "against the table's")
        for e in self.offsets:
            partners = "; trades with " + ", ".join(f"{n} {v:+.2f}" for n, v in e.partners) if e.partners else ""
            out.append(f"  {e.name:32s} {e.text():36s} {e.cls}{partners}")
        for d in self.combinations:
            comp = " ".join(f"{w:+.2f}*{n}" for n, w in d["components"])
            out.append(f"  determined combination (σ {d['sigma']:.3g} of the ranges): {comp}")
        return out


def _partners(corr: np.ndarray, i: int, names, k: int = 2) -> tuple[tuple[str, float], ...]:
    row = np.nan_to_num(np.array(corr[i, :len(names)], float))
    if i < len(row):
        row[i] = 0.0
    order = np.argsort(-np.abs(row))[:k]
    return tuple((names[j], float(row[j])) for j in order if abs(row[j]) >= PARTNER_CORRELATION)


def _combinations(cov: np.ndarray, names, top: int = 4, most: int = 6) -> tuple[dict, ...]:
    """The posterior's well-determined directions that mix offsets, best first.

    Well determined: σ below a tenth of the prior's; mixing: no component above 0.9.
    """
    c = np.nan_to_num(cov)
    lam, vec = np.linalg.eigh(0.5 * (c + c.T))
    out: list[dict] = []
    for j in np.argsort(lam):
        s = math.sqrt(max(lam[j], 0.0))
        if s >= DETERMINED * PRIOR_SIGMA or len(out) >= most:
            break
        v = vec[:, j] * np.sign(vec[np.argmax(np.abs(vec[:, j])), j])
        if np.max(np.abs(v)) > 0.9:
            continue
        idx = np.argsort(-np.abs(v))[:top]
        out.append({"sigma": s, "components": [(names[i], float(v[i])) for i in idx]})
    return tuple(out)


def summary(posterior: Posterior | None) -> Mapping | None:
    """``posterior.as_dict()``, None for no posterior."""
    return None if posterior is None else posterior.as_dict()
