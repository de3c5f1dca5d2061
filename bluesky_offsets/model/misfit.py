"""Model vs. measurement: noise-aware misfit, residual signatures, where the model fails.

Everything here is a pure function of histograms (fractions of source rays,
``(n_configurations, bins)`` for x and for y) and ray counts, so it serves the
twin, the surrogate and stored measurement runs alike.

Noise model (:func:`bluesky_offsets.physics.noise.bin_variance`, the one of every misfit and
fit): a measured bin fraction ``m`` from ``N`` source rays has
variance ``p (1 - p) / N`` (multinomial counts).  A model histogram traced by
the twin with ``N_model`` rays adds ``p (1 - p) / N_model``; a surrogate adds
its own error variance ``model_var``.  ``p`` is floored at one ray so empty
bins next to signal still count.  A correct model has ``chi2 / dof ≈ 1``.
"""

from __future__ import annotations

import math

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.noise import bin_variance

SIGNATURE_NAMES = ("intensity", "centroid", "width", "skewness", "tails")


class MeasurementError(InputError):
    """Measurement data that cannot be compared (shape, NaN, table mismatch)."""


def check_histograms(hist_x, hist_y, bins_x: int | None = 50, bins_y: int | None = 50, what: str = "measurement",
                     floors=(None, None)):
    """Validate a stack of x/y histograms; return float arrays (n, bins).

    ``None`` bins: any.  With a camera's noise ``floors`` (variances, as the histograms) a bin may
    read below zero by up to eight of the floor's σ, as a dark-subtracted one does.
    """
    hx = np.asarray(hist_x, dtype=float)
    hy = np.asarray(hist_y, dtype=float)
    if hx.ndim == 1:
        hx, hy = hx[None], hy[None]
    bins_x = hx.shape[-1] if bins_x is None else bins_x
    bins_y = hy.shape[-1] if bins_y is None and hy.ndim == 2 else bins_y
    if hx.ndim != 2 or hx.shape[1] != bins_x:
        raise MeasurementError(f"{what}: x histograms must be (configurations, {bins_x}), got {hx.shape}")
    if hy.shape != (hx.shape[0], bins_y):
        raise MeasurementError(f"{what}: y histograms must be ({hx.shape[0]}, {bins_y}), got {hy.shape}")
    for name, h, floor in (("x", hx, floors[0]), ("y", hy, floors[1])):
        bad = ~np.isfinite(h)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise MeasurementError(f"{what}: {name} histogram of configuration {i} has a non-finite bin {j}")
        low = h < (0.0 if floor is None else -8.0 * np.sqrt(floor))
        if low.any():
            i = int(np.argwhere(low)[0][0])
            raise MeasurementError(f"{what}: {name} histogram of configuration {i} has negative bins"
                                   + ("" if floor is None else " beyond its camera's noise"))
    return hx, hy


@dataclass
class Misfit:
    """Noise-aware misfit of a model against measured histograms."""

    chi2: np.ndarray            # per configuration
    dof: np.ndarray             # expected chi2 of a correct model, per configuration
    mse: np.ndarray             # per configuration, x and y bins together
    expected_mse: np.ndarray    # per configuration, for a correct model
    pulls_x: np.ndarray         # (n, bins) normalized residuals (measured - model) / sigma
    pulls_y: np.ndarray

    @property
    def chi2_total(self) -> float:
        """χ² summed over the configurations."""
        return float(self.chi2.sum())

    @property
    def dof_total(self) -> float:
        """χ²'s expectation for a correct model (degrees of freedom), summed over the configurations."""
        return float(self.dof.sum())

    @property
    def chi2_reduced(self) -> np.ndarray:
        """χ² / dof per configuration (dof floored at 1)."""
        return self.chi2 / np.maximum(self.dof, 1)

    @property
    def chi2_reduced_total(self) -> float:
        """The total χ² over the total dof (floored at 1)."""
        return self.chi2_total / max(self.dof_total, 1)

    @property
    def mse_total(self) -> float:
        """The mean squared error, averaged over the configurations."""
        return float(self.mse.mean())

    @property
    def expected_mse_total(self) -> float:
        """A correct model's mean squared error, averaged over the configurations."""
        return float(self.expected_mse.mean())

    def beyond_noise(self, n_sigma: float = 3.0) -> np.ndarray:
        """Configurations whose chi2 exceeds its expectation by ``n_sigma`` (chi2 with dof)."""
        return self.chi2 > self.dof + n_sigma * np.sqrt(2 * np.maximum(self.dof, 1))

    def noise_margin(self, n_sigma: float = 3.0) -> float:
        """How far χ² may exceed its expectation and the model still be within noise.

        That is ``n_sigma`` times χ²'s spread √(2 dof) (the gate of :meth:`total_beyond_noise`; what a
        hidden effect may add and hide, :func:`bluesky_offsets.model.diagnosis.detection_limits`).
        """
        return float(n_sigma * np.sqrt(2 * max(self.dof_total, 1)))

    def total_beyond_noise(self, n_sigma: float = 3.0) -> bool:
        """Whether the total χ² exceeds the total dof by more than :meth:`noise_margin`."""
        return self.chi2_total > self.dof_total + self.noise_margin(n_sigma)

    def as_dict(self) -> dict:
        """The misfit's totals, per-configuration χ²/dof and MSE, and the configurations beyond noise."""
        return {"chi2_total": self.chi2_total, "dof_total": self.dof_total,
                "chi2_reduced_total": self.chi2_reduced_total, "mse_total": self.mse_total,
                "expected_mse_total": self.expected_mse_total,
                "chi2_reduced": self.chi2_reduced.tolist(), "mse": self.mse.tolist(),
                "configurations_beyond_noise": np.flatnonzero(self.beyond_noise()).tolist()}


def expected_pull2(meas: np.ndarray, model: np.ndarray, n_rays, floor=None) -> np.ndarray:
    """What each bin adds to chi-square on average for a correct model (its degrees of freedom).

    One where the measurement saw rays; where it saw none, ``n p`` for a model that
    expects ``p n < 1`` rays there: such a bin is almost always empty, and its pull is then
    tiny.  Counting it as a whole degree of freedom let a model with a faint background
    (non-zero in all 1600 bins) report chi2/dof ~ 1 while its MSE was 11x its noise.
    With a camera's ``floor`` a bin the model lights is one; a bin it leaves dark is counted only
    where its noise reads beyond :data:`DARK_CUT` σ (:func:`compared`), which a Gaussian does in
    :data:`DARK_PULL2` of its square on average.
    """
    n = np.asarray(n_rays, dtype=float)
    if floor is not None:
        return np.where(np.asarray(model) > 0, 1.0, DARK_PULL2)
    return np.where(meas > 0, 1.0, np.clip(model * n, 0.0, 1.0))


DARK_CUT = 3.0
"""σ of a camera's own noise beyond which a bin the model leaves dark counts as light measured."""
DARK_PULL2 = float(DARK_CUT * np.exp(-DARK_CUT**2 / 2) / np.sqrt(2 * np.pi) + 0.5 * math.erfc(DARK_CUT / np.sqrt(2)))
"""E[z² ; z > DARK_CUT] of a standard normal z: what a dark bin adds to chi-square on average."""


def compared(meas: np.ndarray, model: np.ndarray, floor=None) -> np.ndarray:
    """The bins a chi-square counts: where light was measured or modelled.

    With a camera's floor: where the model has light or the measurement reads beyond
    :data:`DARK_CUT` σ of its noise (the camera's dark bins, thousands a frame, would else drown the
    light's bins in their noise).
    """
    if floor is not None:
        return (np.asarray(model) > 0) | (np.asarray(meas) > DARK_CUT * np.sqrt(floor))
    return (meas > 0) | (model > 0)


def misfit(meas_x, meas_y, model_x, model_y, n_rays: int | Sequence[int], *,
           model_rays: int | None = None, model_var: float = 0.0, floor_x=None, floor_y=None,
           model_noise=None) -> Misfit:
    """Chi-square and MSE of model histograms against measured ones.

    Parameters
    ----------
    meas_x, meas_y, model_x, model_y : array_like (n, bins)
        Fractions of source rays per bin.
    n_rays : int or sequence of int
        Source rays (ray budget) of each measurement.
    model_rays : int, optional
        Rays of a twin-traced model (its own noise); ``None`` for a mean model (surrogate).
    model_var : float
        Extra per-bin variance of the model (e.g. a surrogate's test MSE).
    floor_x, floor_y : array_like (n, bins), optional
        A camera's own noise per measured bin (:attr:`Measurement.floor_x`).
    model_noise : tuple of array_like (n, bins), optional
        A twin-traced model's counting noise through its detector-level effects, x and y
        (:func:`bluesky_offsets.model.state.simulate_with_noise`); None: each bin weighed by its value.
    """
    mx, my = check_histograms(meas_x, meas_y, None, None, floors=(floor_x, floor_y))
    fx, fy = check_histograms(model_x, model_y, None, None, what="model")
    for axis, a, b in (("x", fx, mx), ("y", fy, my)):
        if a.shape[1] != b.shape[1]:
            raise MeasurementError(f"the model's {axis} histograms have {a.shape[1]} bins, the measurement's "
                                   f"{b.shape[1]}: bin both alike")
    if fx.shape[0] != mx.shape[0]:
        raise MeasurementError(f"{mx.shape[0]} measured configurations but {fx.shape[0]} modelled")
    n = np.broadcast_to(np.asarray(n_rays, dtype=float), (mx.shape[0],))[:, None]
    if (n <= 0).any():
        raise MeasurementError("ray budgets must be positive")

    nz_x, nz_y = (None, None) if model_noise is None else model_noise

    def _pulls(m, f, floor, noise):
        var = bin_variance(m, f, n, model_rays, model_var, floor, noise)
        return np.where(compared(m, f, floor), (m - f) / np.sqrt(var), 0.0)

    px, py = _pulls(mx, fx, floor_x, nz_x), _pulls(my, fy, floor_y, nz_y)
    chi2 = (px ** 2).sum(1) + (py ** 2).sum(1)
    wx, wy = expected_pull2(mx, fx, n, floor_x), expected_pull2(my, fy, n, floor_y)
    dof = wx.sum(1) + wy.sum(1)
    mse = np.concatenate([(mx - fx) ** 2, (my - fy) ** 2], axis=1).mean(1)
    # a correct model: E[(m - f)^2] = var per bin (its counting part scaled like the dof in
    # nearly empty bins)
    if floor_x is not None:  # every bin's residual enters the MSE: its whole variance, the camera's too
        wx, wy = np.ones_like(wx), np.ones_like(wy)
    counting = np.concatenate([(bin_variance(mx, fx, n, model_rays, floor=floor_x, model_noise=nz_x) * wx),
                               (bin_variance(my, fy, n, model_rays, floor=floor_y, model_noise=nz_y) * wy)], axis=1)
    exp_mse = (counting + model_var).mean(1)
    return Misfit(chi2, dof, mse, exp_mse, px, py)


# --------------------------------------------------------------------------- #
# residual signatures
# --------------------------------------------------------------------------- #
def _centroid_variance(h, centers: np.ndarray):
    """Total, centroid and variance of histograms (..., bins).

    An empty one has centroid and variance 0.  Numpy arrays or torch tensors alike (the fit
    differentiates them).
    """
    if not isinstance(h, np.ndarray):  # a torch tensor: the centres on its device and dtype
        centers = h.new_tensor(centers)
    tot = h.sum(-1)
    safe = tot + (tot <= 0)  # 1 where empty
    mu = (h * centers).sum(-1) / safe
    return tot, mu, (h * (centers - mu[..., None]) ** 2).sum(-1) / safe


def _spot(h, centers: np.ndarray):
    """Centroid and variance of a beam's histograms.

    The variance is floored at the bin's own spread (w^2 / 12: a beam inside one bin still has it).
    Numpy or torch alike.
    """
    w = (centers[-1] - centers[0]) / (len(centers) - 1)
    _, mu, v = _centroid_variance(h, centers)
    return mu, v.clip(min=w * w / 12)


def feature_values(hist_x, hist_y, spec) -> list:
    """The five numbers of :func:`beam_features` without their variances, as a list.

    Intensity, then centroid and rms width per axis; numpy arrays or torch tensors alike, so that
    the fit's model side is the same function as the measurement's.
    """
    out = [hist_x.sum(-1)]
    for h, c in ((hist_x, spec.centers_x), (hist_y, spec.centers_y)):
        mu, v = _spot(h, c)
        out += [mu, np.sqrt(v) if isinstance(v, np.ndarray) else v.sqrt()]
    return out


def moments(hist: np.ndarray, centers: np.ndarray) -> dict[str, np.ndarray]:
    """Intensity, centroid, width (std), skewness and tail fraction of histograms (n, bins).

    Tails: the share of the intensity outside the peak bin ±2 bins (robust for the
    narrow foci that span only a few bins).
    """
    h = np.asarray(hist, dtype=float)
    tot, mu, var = _centroid_variance(h, centers)
    safe = np.where(tot > 0, tot, 1.0)
    sd = np.sqrt(np.clip(var, 0.0, None))  # a camera's noise can make a faint frame's variance negative
    skew = np.where(sd > 0, (h * (centers - mu[..., None]) ** 3).sum(-1) / safe / np.maximum(sd, 1e-12) ** 3, 0.0)
    peak = h.argmax(-1)
    idx = np.arange(h.shape[-1])
    core = np.abs(idx - peak[..., None]) <= 2
    tails = np.where(tot > 0, (h * ~core).sum(-1) / safe, 0.0)
    empty = tot <= 0
    return {"intensity": tot, "centroid": np.where(empty, 0.0, mu), "width": np.where(empty, 0.0, sd),
            "skewness": np.where(empty, 0.0, skew), "tails": tails}


FEATURE_NAMES = ("intensity", "x.centroid", "x.width", "y.centroid", "y.width")
#: a camera's width is compared where its variance's noise is below this share of the variance
#: (its square root then biased by a twelfth of its σ at most)
WIDTH_NOISE = 1.0 / 3.0


def beam_features(hist_x, hist_y, spec, n_rays, floor_x=None, floor_y=None) -> tuple[np.ndarray, np.ndarray]:
    """The beam on the screen in five numbers per configuration, with their noise variances.

    Intensity (fraction of the source rays in the window), centroid and rms width per axis;
    variances for ``n_rays`` source rays (binomial intensity, ``sd^2/N`` centroid,
    ``sd^2/2N`` width).  Unlike bin contents these move smoothly and almost linearly with
    the offsets over many spot widths, which is why fits start on them: a focus narrower
    than a few bins makes every bin a steep step function of the spot position.
    A camera's frames carry their own noise (``floor_x``/``floor_y``, per bin): their bins are
    taken as measured (clipping the noise at zero would bias every moment) and the floor's share
    is added to each variance, the moments' sums linearized; a width the noise swamps (the noise
    of its variance above :data:`WIDTH_NOISE` of it: a focus a few pixels wide in a window a
    thousand wide) is left out, its variance the window's.
    Returns ``(features, variances)``, each ``(..., 5)`` in :data:`FEATURE_NAMES` order.
    """
    n = float(n_rays)
    hx, hy = np.asarray(hist_x, float), np.asarray(hist_y, float)
    if floor_x is None:  # a linearized model may dip below zero in empty bins
        hx, hy = np.clip(hx, 0, None), np.clip(hy, 0, None)
    inten = hx.sum(-1)
    hits = np.maximum(inten * n, 1.0)
    out, var = [inten], [np.maximum(inten * (1 - inten), 1.0 / n) / n]
    if floor_x is not None:
        var[0] = var[0] + np.asarray(floor_x, float).sum(-1)
    for h, c, floor in ((hx, spec.centers_x, floor_x), (hy, spec.centers_y, floor_y)):
        mu, v = _spot(h, c)
        dark = h.sum(-1) <= 0
        # no rays, no position: the whole window as the uncertainty
        big = (c[-1] - c[0]) ** 2
        vc, vw = v / hits, v / (2 * hits)
        if floor is not None:
            tot = np.maximum(np.abs(h.sum(-1)), 1.0 / n)[..., None]
            d2 = (c - mu[..., None]) ** 2
            vc = vc + (floor * d2).sum(-1) / tot[..., 0] ** 2
            noise_v = (floor * (d2 - v[..., None]) ** 2).sum(-1) / tot[..., 0] ** 2
            vw = vw + noise_v / (4 * v)
            # a width whose variance the noise blurs by more than a third of itself: its square
            # root is biased (clipped below, skewed above) and carries nothing, so it is left out
            vw = np.where(noise_v > (WIDTH_NOISE * v) ** 2, big, vw)
        out += [mu, np.sqrt(v)]
        var += [np.where(dark, big, np.minimum(vc, big)), np.where(dark, big, np.minimum(vw, big))]
    return np.stack(out, -1), np.stack(var, -1)


@dataclass
class Signature:
    """Model-minus-measurement differences of the histogram moments, per axis and configuration."""

    delta: dict[str, np.ndarray] = field(default_factory=dict)  # "x.centroid" -> (n,)

    def mean(self) -> dict[str, float]:
        """Each difference's mean over the configurations."""
        return {k: float(np.mean(v)) for k, v in self.delta.items()}

    def as_vector(self, keys: Sequence[str] | None = None) -> np.ndarray:
        """The differences ``keys`` (default: all, sorted) stacked as columns: ``(n, len(keys))``."""
        keys = keys or sorted(self.delta)
        return np.stack([self.delta[k] for k in keys], axis=-1)


def residual_signature(meas_x, meas_y, model_x, model_y, spec) -> Signature:
    """How the model differs from the measurement, in physical terms, per configuration.

    Lost intensity, centroid shift, width change, asymmetry and tails, per axis.
    """
    out = {}
    for axis, m, f, c in (("x", meas_x, model_x, spec.centers_x), ("y", meas_y, model_y, spec.centers_y)):
        mm, fm = moments(m, c), moments(f, c)
        for k in SIGNATURE_NAMES:
            out[f"{axis}.{k}"] = fm[k] - mm[k]
    return Signature(out)


def correlate_with_parameters(signature: Signature, configurations: np.ndarray, names: Sequence[str],
                              top: int = 5) -> list[tuple[str, str, float]]:
    """Strongest Pearson correlations between residual signatures and the commanded parameters.

    Correlated across configurations: ``(signature, parameter, r)``, largest ``|r|`` first.
    """
    cfg = np.asarray(configurations, dtype=float)
    out = []
    for key, d in signature.delta.items():
        if np.std(d) == 0:
            continue
        for j, name in enumerate(names):
            col = cfg[:, j]
            if np.std(col) == 0:
                continue
            r = float(np.corrcoef(d, col)[0, 1])
            if np.isfinite(r):
                out.append((key, name, r))
    out.sort(key=lambda t: -abs(t[2]))
    return out[:top]


def failing_regions(misfit_: Misfit, spec, n_sigma: float = 3.0) -> list[dict]:
    """Where the misfit sits, per failing configuration and axis.

    For each configuration beyond noise and each axis with bins whose pulls exceed ``n_sigma``:
    the range in mm those bins span, the largest pull, and the share of the configuration's χ² in them.
    """
    out = []
    for i in np.flatnonzero(misfit_.beyond_noise(n_sigma)):
        for axis, pulls, centers in (("x", misfit_.pulls_x[i], spec.centers_x),
                                     ("y", misfit_.pulls_y[i], spec.centers_y)):
            bad = np.flatnonzero(np.abs(pulls) > n_sigma)
            if bad.size:
                out.append({"configuration": int(i), "axis": axis,
                            "range_mm": [float(centers[bad.min()]), float(centers[bad.max()])],
                            "max_pull": float(pulls[bad][np.argmax(np.abs(pulls[bad]))]),
                            "chi2_share": float((pulls[bad] ** 2).sum() / max(misfit_.chi2[i], 1e-300))})
    return out


# --------------------------------------------------------------------------- #
# plots
# --------------------------------------------------------------------------- #
def plot_overlays(meas_x, meas_y, model_x, model_y, spec, path, misfit_: Misfit | None = None,
                  max_configurations: int = 8, title: str = "measured vs model"):
    """Per configuration: measured and modelled x/y histograms, residuals below."""
    from bluesky_offsets.plotting import pyplot, save_figure
    plt = pyplot()
    n = min(len(meas_x), max_configurations)
    # each configuration zoomed on its own spot: at the camera's resolution a spot fills a few
    # per cent of the window, and the spots of a scan sit millimetres apart
    fig, axes = plt.subplots(4, n, figsize=(2.6 * n, 7.5), squeeze=False,
                             gridspec_kw={"height_ratios": (3, 1, 3, 1)}, constrained_layout=True)
    for i in range(n):
        for row, (m, f, edges, lab) in enumerate(((meas_x, model_x, spec.edges_x, "x"),
                                                  (meas_y, model_y, spec.edges_y, "y"))):
            ax, axr = axes[2 * row, i], axes[2 * row + 1, i]
            # a linearized model leaves faint values far out: they do not set the zoom
            peak = max(float(np.max(m[i])), float(np.max(f[i])), 0.0)
            nz = np.flatnonzero((m[i] > 1e-3 * peak) | (f[i] > 1e-3 * peak)) if peak > 0 else np.array([], int)
            # only the zoomed bins are drawn (the camera's 1,600 bins per axis as filled steps took
            # most of a demo report's 16 s)
            a, b = (max(nz.min() - 2, 0), min(nz.max() + 3, len(edges) - 1)) if nz.size else (0, len(edges) - 1)
            ax.stairs(m[i][a:b], edges[a:b + 1], color="C1", label="measured", lw=1.5)
            ax.stairs(f[i][a:b], edges[a:b + 1], color="C0", label="model", lw=1.2)
            axr.stairs((m[i] - f[i])[a:b], edges[a:b + 1], color="C3", fill=True)
            ax.set_xlim(edges[a], edges[b])
            axr.set_xlim(edges[a], edges[b])
            axr.axhline(0, color="k", lw=0.5)
            if i == 0:
                ax.set_ylabel(f"{lab}: fraction/bin")
                axr.set_ylabel("resid.")
            axr.set_xlabel(f"{lab} [mm]")
        t = f"config {i}"
        if misfit_ is not None:
            t += f"\nχ²/dof {misfit_.chi2_reduced[i]:.2f}"
        axes[0, i].set_title(t, fontsize=9)
    axes[0, 0].legend(fontsize=7)
    return save_figure(fig, path, dpi=100, title=title)


def plot_residual_maps(misfit_: Misfit, spec, path, title: str = "normalized residuals (measured − model) / σ"):
    """Per-bin pulls across configurations, for x and y."""
    from bluesky_offsets.plotting import pyplot, save_figure
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 0.35 * len(misfit_.chi2) + 2), constrained_layout=True)
    lim = max(3.0, float(np.percentile(np.abs(np.concatenate([misfit_.pulls_x.ravel(), misfit_.pulls_y.ravel()])), 99)))
    for ax, pulls, edges, lab in ((axes[0], misfit_.pulls_x, spec.edges_x, "x"),
                                  (axes[1], misfit_.pulls_y, spec.edges_y, "y")):
        # only the bins where any configuration has signal (a focus fills a few per cent of the window)
        cols = np.flatnonzero(np.any(pulls != 0, axis=0))
        a, b = (max(cols.min() - 3, 0), min(cols.max() + 4, pulls.shape[1])) if cols.size else (0, pulls.shape[1])
        im = ax.imshow(pulls[:, a:b], aspect="auto", cmap="RdBu_r", vmin=-lim, vmax=lim,
                       extent=(edges[a], edges[b], len(pulls) - 0.5, -0.5), interpolation="nearest")
        ax.set_xlabel(f"{lab} [mm]")
        ax.set_ylabel("configuration")
    fig.colorbar(im, ax=axes, label="pull")
    return save_figure(fig, path, dpi=100, title=title)
