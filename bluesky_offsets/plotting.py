"""Figures people would rather look at than read (matplotlib, headless)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def pyplot():
    """matplotlib.pyplot on the headless Agg backend (figures are written, never shown)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_figure(fig, path: str | Path, *, dpi: int = 110, title: str = "") -> Path:
    """Title (optional), write and close a figure; returns the path."""
    import matplotlib.pyplot as plt
    if title:
        fig.suptitle(title)
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def plot_footprint(result, hist, path: str | Path, title: str = "") -> Path:
    """Footprint scatter on the focus-chamber screen with its x and y histograms.

    ``result`` is a :class:`~bluesky_offsets.physics.twin.TraceResult` traced with
    ``keep_rays=True``; ``hist`` its :class:`~bluesky_offsets.physics.twin.HistogramSpec`.
    """
    plt = pyplot()
    fig = plt.figure(figsize=(8, 6.5), constrained_layout=True)
    gs = fig.add_gridspec(2, 2, width_ratios=(4, 1.3), height_ratios=(1.3, 4))
    ax = fig.add_subplot(gs[1, 0])
    axx = fig.add_subplot(gs[0, 0], sharex=ax)
    axy = fig.add_subplot(gs[1, 1], sharey=ax)
    rays = result.rays if result.rays is not None else np.empty((0, 2))
    if len(rays):
        ax.scatter(rays[:, 0], rays[:, 1], s=1, alpha=0.3, color="C0", rasterized=True)
        # the focus is far smaller than the histogram window: add a zoom on it
        cx, cy = np.median(rays, axis=0)
        sx, sy = (max(5 * float(np.std(rays[:, k])), 0.01) for k in (0, 1))
        ins = ax.inset_axes([0.62, 0.62, 0.36, 0.36])
        ins.scatter(rays[:, 0], rays[:, 1], s=1, alpha=0.3, color="C0", rasterized=True)
        ins.set_xlim(cx - sx, cx + sx)
        ins.set_ylim(cy - sy, cy + sy)
        ins.set_title("zoom", fontsize=8)
        ins.tick_params(labelsize=7)
    ax.set_xlabel("x on screen [mm]")
    ax.set_ylabel("y on screen [mm]")
    ax.set_xlim(*hist.range_x)
    ax.set_ylim(*hist.range_y)
    ax.grid(alpha=0.3)
    axx.stairs(result.hist_x, hist.edges_x, fill=True, color="C1")
    axx.set_ylabel("fraction / bin")
    axx.tick_params(labelbottom=False)
    axy.stairs(result.hist_y, hist.edges_y, fill=True, color="C2", orientation="horizontal")
    axy.set_xlabel("fraction / bin")
    axy.tick_params(labelleft=False)
    s = result.summary()
    text = f"transmission {s['transmission']:.3f}"
    if "width_x" in s:
        text += (f"\ncentroid ({s['centroid_x']:+.3f}, {s['centroid_y']:+.3f}) mm"
                 f"\nstd ({s['width_x']:.4f}, {s['width_y']:.4f}) mm")
    ax.text(0.02, 0.98, text, transform=ax.transAxes, va="top", fontsize=9,
            bbox=dict(boxstyle="round", fc="white", alpha=0.8))
    return save_figure(fig, path, dpi=120, title=title)
