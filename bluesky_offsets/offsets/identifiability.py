"""Identifiability: which offsets the measured histograms actually pin down.

The paper's recovered offsets deviate from the true ones with a normalized
RMSE of 0.58 although the histograms match: components compensate each other
(two mirrors tilted against each other move the focus back).  An operator
must know which found offsets to trust.  This module answers with a local,
Gauss-Newton (Fisher) analysis at the solution plus the spread of
independent (multi-start) solutions.

Model
-----
Near the solution ``o*`` the histograms are linear in the offsets,
``h(c + o) ≈ h(c + o*) + J_c (o - o*)`` with ``J_c`` the forward model's
Jacobian (100 x P) at configuration ``c``.  Each bin carries the counting
noise of a measurement with ``N`` source rays, the one noise model of every
fit (:func:`bluesky_offsets.physics.noise.bin_variance`: ``p (1 - p) / N`` for a bin
fraction ``p`` floored at one ray, so empty bins still carry information), plus,
optionally, the model's own error ``model_mse`` per bin.  The Fisher matrix is
``F = Σ_c J_cᵀ diag(1/var_c) J_c``.  The offsets' prior is the search box,
uniform in ``[-limit, limit]``, standard deviation ``σ_prior = limit/√3``;
the posterior covariance is ``C = (F + I/σ_prior²)⁻¹``.

For every parameter the report gives the marginal uncertainty
``σ_i = √C_ii`` (after compensation by all others), the conditional one
``1/√F_ii`` (if all others were known), and the ratio ``σ_i/σ_prior``:

* ``determined``   ratio < 0.1 (the data shrink the box tenfold);
* ``weak``         0.1 <= ratio < 0.5;
* ``undetermined`` ratio >= 0.5 (the data barely beat the prior - a
  parameter the histograms are blind to lands here at exactly 1).

Compensating pairs are the largest ``|corr|`` of ``C``; compensating
directions are the eigenvectors of the prior-whitened Fisher matrix with the
smallest eigenvalues (combinations the histograms cannot see).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from bluesky_offsets.offsets.finder import OffsetProblem, model_device, model_dtype
from bluesky_offsets.physics.noise import bin_variance

DETERMINED, UNDETERMINED = 0.1, 0.5
PAPER_RAYS = 100_000


def jacobian(model, configurations: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """The Jacobian d histogram / d offset at every configuration: ``(n, 100, P)``, float64."""
    device, dtype = model_device(model), model_dtype(model)
    c = torch.as_tensor(np.asarray(configurations), device=device, dtype=dtype)
    o = torch.as_tensor(np.asarray(offsets), device=device, dtype=dtype)

    def f(x):
        return model(c + x)

    # forward mode: one pass per input (34) instead of one per output (configurations x 100 bins);
    # several times faster here, and equal to reverse mode to float32 rounding
    J = torch.autograd.functional.jacobian(f, o, vectorize=True, strategy="forward-mode")
    return J.double().cpu().numpy()


def fisher_matrix(J: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """``Σ_c J_cᵀ diag(1/var_c) J_c`` for ``J`` (n, B, P) and ``variance`` (n, B)."""
    W = 1.0 / np.asarray(variance)
    return np.einsum("nbp,nb,nbq->pq", J, W, J)


@dataclass
class IdentifiabilityReport:
    """Per-parameter uncertainties and compensations at one solution (normalized units)."""

    names: list[str]
    offsets: np.ndarray
    sigma: np.ndarray
    sigma_conditional: np.ndarray
    prior_sigma: float
    status: list[str]
    correlation: np.ndarray
    fisher: np.ndarray
    eigenvalues: np.ndarray  # prior-whitened data Fisher, ascending
    eigenvectors: np.ndarray  # columns
    n_configurations: int
    n_rays: int
    model_mse: float
    spread: np.ndarray | None = None
    n_solutions: int = 0
    thresholds: tuple[float, float] = (DETERMINED, UNDETERMINED)
    extra: dict = field(default_factory=dict)

    @property
    def ratio(self) -> np.ndarray:
        """Each parameter's σ over the prior's σ (what :attr:`status` is read from)."""
        return self.sigma / self.prior_sigma

    def undetermined(self) -> list[str]:
        """The names of the undetermined parameters."""
        return [n for n, s in zip(self.names, self.status) if s == "undetermined"]

    def determined(self) -> list[str]:
        """The names of the determined parameters."""
        return [n for n, s in zip(self.names, self.status) if s == "determined"]

    def pairs(self, k: int = 5, min_info: float = 0.9) -> list[tuple[str, str, float]]:
        """The ``k`` most strongly (anti-)correlated parameter pairs: compensating components.

        Parameters the data do not see at all (ratio > ``min_info``) are left
        out: their correlations are only the prior's.
        """
        seen = self.ratio < min_info
        C = np.where(np.outer(seen, seen), self.correlation, 0.0)
        iu = np.triu_indices(len(self.names), 1)
        order = np.argsort(-np.abs(C[iu]))[:k]
        return [(self.names[iu[0][i]], self.names[iu[1][i]], float(C[iu][i])) for i in order
                if abs(C[iu][i]) > 0]

    def directions(self, k: int = 5, top: int = 4) -> list[dict]:
        """The ``k`` least determined directions: uncertainty along each and its main components."""
        out = []
        for j in range(min(k, len(self.eigenvalues))):
            v = self.eigenvectors[:, j]
            idx = np.argsort(-np.abs(v))[:top]
            sig = self.prior_sigma / math.sqrt(1.0 + max(self.eigenvalues[j], 0.0))
            out.append({"sigma": float(sig), "eigenvalue": float(self.eigenvalues[j]),
                        "components": [(self.names[i], float(v[i])) for i in idx]})
        return out

    def summary(self) -> dict:
        """The counts per status, the median σ, the prior's σ and the data's size (configurations, rays)."""
        return {"n_configurations": self.n_configurations, "n_rays": self.n_rays,
                "n_determined": len(self.determined()), "n_undetermined": len(self.undetermined()),
                "n_weak": sum(s == "weak" for s in self.status),
                "median_sigma": float(np.median(self.sigma)), "prior_sigma": self.prior_sigma}

    def to_dict(self) -> dict:
        """The report as plain JSON values, with its pairs, directions and summary (and spread, if any)."""
        d = {"names": list(self.names), "offsets": self.offsets.tolist(), "sigma": self.sigma.tolist(),
             "sigma_conditional": self.sigma_conditional.tolist(), "prior_sigma": self.prior_sigma,
             "status": list(self.status), "ratio": self.ratio.tolist(),
             "pairs": self.pairs(), "directions": self.directions(), "summary": self.summary(),
             "model_mse": self.model_mse, "thresholds": list(self.thresholds)}
        if self.spread is not None:
            d["spread"] = self.spread.tolist()
            d["n_solutions"] = self.n_solutions
        return d

    def table(self) -> str:
        """Plain-text table, one line per parameter."""
        lines = [f"identifiability at the solution: {self.n_configurations} configurations, counting noise of "
                 f"{self.n_rays:g} rays{f', model error {self.model_mse:.2e}/bin' if self.model_mse else ''}; "
                 f"prior sigma {self.prior_sigma:.3f} (box ±{self.prior_sigma * math.sqrt(3):.2f})",
                 f"{'parameter':32s} {'offset':>8s} {'sigma':>8s} {'alone':>8s} {'ratio':>6s}"
                 f"{' spread':>8s}  status"]
        for i, n in enumerate(self.names):
            sp = f" {self.spread[i]:7.4f}" if self.spread is not None else " " * 8
            lines.append(f"{n:32s} {self.offsets[i]:+8.4f} {self.sigma[i]:8.4f} {self.sigma_conditional[i]:8.4f} "
                         f"{self.ratio[i]:6.2f}{sp}  {self.status[i]}")
        s = self.summary()
        lines.append(f"{s['n_determined']} determined, {s['n_weak']} weak, {s['n_undetermined']} undetermined")
        lines.append("strongest compensating pairs: " + "; ".join(
            f"{a} ~ {b} ({c:+.2f})" for a, b, c in self.pairs()))
        for j, d in enumerate(self.directions(3)):
            comp = " ".join(f"{w:+.2f}*{n}" for n, w in d["components"])
            lines.append(f"weak direction {j + 1} (sigma {d['sigma']:.3f}): {comp}")
        return "\n".join(lines)


def solution_spread(solutions: np.ndarray, losses: np.ndarray, *, best_loss: float | None = None,
                    tolerance: float = 2.0, noise_mse: float = 0.0) -> tuple[np.ndarray | None, int]:
    """Std of the independent solutions that fit as well as the best (loss <= tolerance x best + noise)."""
    if solutions is None or len(solutions) < 2:
        return None, 0 if solutions is None else len(solutions)
    sol, los = np.asarray(solutions), np.asarray(losses)
    best = float(np.min(los)) if best_loss is None else min(best_loss, float(np.min(los)))
    keep = los <= tolerance * best + noise_mse
    if keep.sum() < 2:
        return None, int(keep.sum())
    return sol[keep].std(axis=0, ddof=1), int(keep.sum())


def analyze(problem: OffsetProblem, model, offsets, *, n_rays: int | None = None, model_mse: float = 0.0,
            solutions: np.ndarray | None = None, solution_losses: np.ndarray | None = None,
            configurations: Sequence[int] | None = None, names: Sequence[str] | None = None,
            thresholds: tuple[float, float] = (DETERMINED, UNDETERMINED)) -> IdentifiabilityReport:
    """Identifiability of the offsets at ``offsets`` (normalized) on ``problem``.

    Parameters
    ----------
    n_rays : int
        Rays behind each measured histogram (default: the problem's, else the
        paper's 1e5).
    model_mse : float
        The model's own error per bin (e.g. the surrogate's test MSE), added
        to every bin's variance: a model that is off by that much cannot pin
        offsets below it.
    solutions, solution_losses
        End points of independent searches (e.g. ``FinderResult.solutions``)
        for the spread column.
    configurations
        Indices of the configurations to use (default: all).
    """
    offsets = np.asarray(offsets, dtype=float)
    names = list(names or problem.table.names)
    rows = np.arange(problem.n) if configurations is None else np.asarray(configurations)
    N = int(n_rays or problem.n_rays or PAPER_RAYS)
    c = problem.configurations[rows]
    J = jacobian(model, c, offsets)
    with torch.no_grad():
        pred = model(torch.as_tensor(c + offsets, device=model_device(model), dtype=model_dtype(model)))
    pred = np.clip(pred.double().cpu().numpy(), 0.0, 1.0)
    var = bin_variance(pred, pred, N, model_var=float(model_mse))
    F = fisher_matrix(J, var)
    prior = problem.limit / math.sqrt(3.0)
    # eigen-decomposition of the prior-whitened Fisher matrix: eigenvalue 0 = the data add nothing
    lam, V = np.linalg.eigh(F * prior ** 2)
    lam = np.clip(lam, 0.0, None)
    C = (V / (1.0 + lam)) @ V.T * prior ** 2
    sigma = np.sqrt(np.clip(np.diag(C), 0.0, None))
    d = np.sqrt(np.diag(C))
    corr = C / np.outer(d, d)
    fii = np.diag(F)
    alone = np.where(fii > 0, 1.0 / np.sqrt(np.where(fii > 0, fii, 1.0)), np.inf)
    ratio = sigma / prior
    status = ["determined" if r < thresholds[0] else "undetermined" if r >= thresholds[1] else "weak" for r in ratio]
    low, high = thresholds
    spread, n_sol = (None, 0)
    if solutions is not None and solution_losses is not None:
        spread, n_sol = solution_spread(solutions, solution_losses, noise_mse=problem.noise_mse or 0.0)
    return IdentifiabilityReport(names=names, offsets=offsets, sigma=sigma, sigma_conditional=alone,
                                 prior_sigma=prior, status=status, correlation=corr, fisher=F, eigenvalues=lam,
                                 eigenvectors=V, n_configurations=len(rows), n_rays=N, model_mse=float(model_mse),
                                 spread=spread, n_solutions=n_sol, thresholds=(low, high))


def configuration_curve(problem: OffsetProblem, model, offsets, counts: Sequence[int] | None = None,
                        **kwargs) -> dict:
    """How the uncertainties shrink as configurations are added (first k of the problem's).

    Returns ``{"counts", "sigma" (len(counts), P), "n_determined", "n_undetermined", "median_sigma"}``.
    """
    if counts is None:
        counts = sorted({k for k in (1, 2, 4, 8, 12, 16, 24, 32, problem.n) if k <= problem.n})
    sig, nd, nu = [], [], []
    for k in counts:
        r = analyze(problem, model, offsets, configurations=range(k), **kwargs)
        sig.append(r.sigma)
        nd.append(len(r.determined()))
        nu.append(len(r.undetermined()))
    sigma = np.asarray(sig)
    return {"counts": list(counts), "sigma": sigma, "n_determined": nd, "n_undetermined": nu,
            "median_sigma": np.median(sigma, axis=1).tolist()}


def plot_identifiability(report: IdentifiabilityReport, path, curve: dict | None = None,
                         true_offsets=None) -> Path:
    """Uncertainty per parameter (with the found and true offsets) and the correlation matrix.

    Given a :func:`configuration_curve`, also the gain from more configurations.
    """
    from bluesky_offsets.plotting import pyplot
    plt = pyplot()
    ncols = 3 if curve is not None else 2
    fig, axes = plt.subplots(1, ncols, figsize=(7 * ncols, 7.5), constrained_layout=True,
                             gridspec_kw={"width_ratios": [1.3, 1.0] + ([0.9] if curve is not None else [])})
    ax = axes[0]
    y = np.arange(len(report.names))
    colors = {"determined": "C2", "weak": "C1", "undetermined": "C3"}
    ax.barh(y, 2 * report.sigma, left=report.offsets - report.sigma, height=0.6,
            color=[colors[s] for s in report.status], alpha=0.5, label="offset ± sigma")
    ax.plot(report.offsets, y, "k|", ms=10, label="found")
    if true_offsets is not None:
        ax.plot(true_offsets, y, "x", color="C0", label="true")
    if report.spread is not None:
        ax.errorbar(report.offsets, y + 0.3, xerr=report.spread, fmt="none", ecolor="0.3", lw=1,
                    label=f"spread of {report.n_solutions} solutions")
    lim = report.prior_sigma * math.sqrt(3)
    ax.axvline(-lim, color="0.6", ls=":")
    ax.axvline(lim, color="0.6", ls=":")
    ax.set_yticks(y, [f"{n} ({s[0].upper()})" for n, s in zip(report.names, report.status)], fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("offset [normalized]")
    ax.set_title("offsets and uncertainties (D determined, W weak, U undetermined)", fontsize=10)
    ax.legend(fontsize=7, loc="lower right")
    ax = axes[1]
    im = ax.imshow(report.correlation, cmap="RdBu_r", vmin=-1, vmax=1)
    short = [n.replace("rotation", "r").replace("translation", "t").replace("error", "") for n in report.names]
    ax.set_xticks(y, short, rotation=90, fontsize=6)
    ax.set_yticks(y, short, fontsize=6)
    ax.set_title("posterior correlation (compensations)", fontsize=10)
    fig.colorbar(im, ax=ax, shrink=0.6)
    if curve is not None:
        ax = axes[2]
        ax.plot(curve["counts"], curve["n_determined"], "o-", color="C2", label="determined")
        ax.plot(curve["counts"], curve["n_undetermined"], "s-", color="C3", label="undetermined")
        ax.set_xlabel("configurations used")
        ax.set_ylabel("parameters")
        ax2 = ax.twinx()
        ax2.semilogy(curve["counts"], curve["median_sigma"], "^--", color="0.3", label="median sigma")
        ax2.set_ylabel("median sigma [normalized]")
        ax.legend(loc="center right", fontsize=8)
        ax.set_title("adding configurations", fontsize=10)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
