"""Live views of a session: standard bluesky callbacks (``RE.subscribe(...)``), headless-safe.

* :class:`LiveFootprints` — the measured x/y histograms (and the camera's profiles), one panel
  per configuration, as the frames arrive; the model of every later comparison of that measurement (``compare_model``,
  ``refine_offsets``, ``add_effect_and_refit`` runs) drawn over them, with its χ²/dof.
* :class:`LiveFitProgress` — the offset finder's loss per evaluation and each fit's χ²/dof
  per iteration (the ``finder`` and ``progress`` streams), one figure per run.

With a GUI backend (``%matplotlib qt``, a desktop session) the figures are pyplot windows that
update as documents arrive; without one they are plain Agg figures.  Either way, with
``directory`` set, each figure is written there as PNG when its run stops (a measurement's
footprints, which every later comparison draws on, at most every ``every`` seconds, and the
last state at :func:`flush`).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from bluesky.callbacks.core import CallbackBase

if TYPE_CHECKING:
    from matplotlib.figure import Figure

NON_GUI = {"agg", "pdf", "ps", "svg", "cairo", "pgf", "template"}


def _windows(show: bool | None) -> bool:
    """Whether figures are windows: ``show``, or by default whether the backend is a GUI's."""
    if show is None:
        import matplotlib
        return matplotlib.get_backend().lower() not in NON_GUI
    return bool(show)


def _figure(figsize, show: bool | None):
    if _windows(show):
        import matplotlib.pyplot as plt
        return plt.figure(figsize=figsize)
    from matplotlib.figure import Figure
    return Figure(figsize=figsize)


def in_background(callback):
    """``callback`` on a thread of its own when it draws no windows, else itself.

    On its own thread: a :class:`bluesky_offsets.queued.QueuedCallback`, for Agg figures written
    as PNG; a GUI's figures belong to its main loop.  Writing a 20-panel footprint figure takes
    0.8 s, which the RunEngine would wait for at the end of every run that draws on it.
    :func:`flush` before reading ``written``.
    """
    from bluesky_offsets.queued import QueuedCallback
    if _windows(getattr(callback, "show", None)):
        return callback
    return QueuedCallback(callback, name=f"live-{type(callback).__name__}")


def flush(callbacks) -> None:
    """Wait until the callbacks have drawn every document so far and written every figure changed since.

    The callbacks may be made with :func:`in_background` or not; a figure is written when it was
    drawn on since it was last written.
    """
    for cb in callbacks:
        if hasattr(type(cb), "flush"):
            cb.flush()


def _redraw(fig) -> None:
    """Repaint a window; an Agg figure (no window) is drawn once, when it is written."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    if type(fig.canvas) is FigureCanvasAgg or not hasattr(fig.canvas, "manager") or fig.canvas.manager is None:
        return
    canvas = fig.canvas
    canvas.draw_idle()
    flush = getattr(canvas, "flush_events", None)
    if flush is not None:
        try:
            flush()
        except NotImplementedError:  # Agg canvases have no event loop
            pass


def _density(h, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """Bin centres (mm) and the histogram as a density per mm (binnings of any width compare)."""
    h = np.asarray(h, dtype=float)
    width = (hi - lo) / len(h)
    return lo + width * (np.arange(len(h)) + 0.5), h / width


def _value(data: dict, suffix: str):
    return next((v for k, v in data.items() if k == suffix or k.endswith("-" + suffix) or k.endswith("_" + suffix)),
                None)


class LiveFootprints(CallbackBase):
    """Measured histograms per configuration as they arrive, the model drawn over them later.

    Parameters
    ----------
    directory : str or Path, optional
        Where each measurement's figure is written (``footprints-<uid>.png``) when its run, or
        a later comparison with it, stops.
    plans : tuple of str
        Plans whose frames are drawn (default: ``measure_configurations`` runs).
    range_x, range_y : (float, float)
        The screen's extent in mm (the histograms' range).
    columns : int
        Panels per row.
    show : bool, optional
        Pyplot windows (True) or Agg figures (False); default: windows with a GUI backend.
    every : float
        Seconds at least between two writes of one figure as later runs stop; what was drawn
        since is written by the next run that stops after that, or by :meth:`flush`.  A 20-panel
        figure takes a second or two to write, and every comparison draws on its measurement's:
        written each time, it would take the main process's CPU from the fits.
    """

    def __init__(self, directory=None, *, plans: tuple[str, ...] = ("measure_configurations",),
                 range_x=(-10.0, 10.0), range_y=(-3.0, 3.0), columns: int = 5, show: bool | None = None,
                 every: float = 30.0):
        super().__init__()
        self.directory = Path(directory) if directory is not None else None
        self.plans, self.range_x, self.range_y = tuple(plans), tuple(range_x), tuple(range_y)
        self.columns, self.show = int(columns), show
        self.figures: dict[str, Figure] = {}    # measurement uid -> figure
        self.written: list[Path] = []
        self._axes: dict[str, list] = {}
        self._overlays: dict[tuple[str, int], list] = {}
        self._runs: dict[str, dict] = {}         # run uid -> what its documents mean here
        self._descriptors: dict[str, tuple[str, str]] = {}  # descriptor uid -> (run uid, stream)
        # figures drawn on since they were last written: a run that drew nothing (a diagnosis
        # names the measurement but traces no model of it) writes nothing
        self._changed: set[str] = set()
        self.every = float(every)
        self._written_at: dict[str, float] = {}  # measurement uid -> time.monotonic() of its last write

    # the measurement ------------------------------------------------------ #
    def start(self, doc):
        """Open a figure for a measuring run; note a run that compares a model with a drawn measurement."""
        uid = doc["uid"]
        if doc.get("plan_name") in self.plans and doc.get("configurations") is not None:
            n = len(doc["configurations"])
            self._new_figure(uid, n, doc.get("purpose") or doc["plan_name"])
            self._runs[uid] = {"kind": "measurement", "measurement": uid}
        elif doc.get("measurement_uid") in self.figures:
            idx = doc.get("analysed_configurations") or None
            self._runs[uid] = {"kind": "model", "measurement": doc["measurement_uid"], "analysed": idx,
                               "label": doc.get("version_label") or doc.get("effect") or doc.get("plan_name")}

    def descriptor(self, doc):
        """Note the stream of a descriptor of a run drawn here."""
        run = doc["run_start"]
        if run in self._runs:
            self._descriptors[doc["uid"]] = (run, doc.get("name", "primary"))

    def event(self, doc):
        """Draw a measured frame's histograms, or a model's over the measurement's panel."""
        run_uid, stream = self._descriptors.get(doc["descriptor"], (None, None))
        if run_uid is None:
            return
        run, data = self._runs[run_uid], doc["data"]
        if run["kind"] == "measurement" and stream == "primary":
            hx, hy = _value(data, "hist_x"), _value(data, "hist_y")
            i = data.get("config_index", doc.get("seq_num", 1) - 1)
            if hx is not None and hy is not None:
                self._draw_measured(run["measurement"], int(i), hx, hy, _value(data, "profile_x"),
                                    _value(data, "profile_y"))
        elif run["kind"] == "model" and stream == "misfit" and "model_hist_x" in data:
            i = int(data["config_index"])
            idx = run["analysed"]
            j = int(idx[i]) if idx is not None and i < len(idx) else i
            self._draw_model(run["measurement"], j, data["model_hist_x"], data["model_hist_y"],
                             f"{run['label']}: χ²/dof {float(data.get('chi2_reduced', math.nan)):.3g}")

    def stop(self, doc):
        """Write the run's measurement figure if it changed and was not written in the last ``every`` s."""
        run = self._runs.pop(doc["run_start"], None)
        if run is None or run["measurement"] not in self._changed:
            return
        # a file someone may be watching, not a result: its write is paced by the clock
        if time.monotonic() - self._written_at.get(run["measurement"], -math.inf) >= self.every:
            self._save(run["measurement"])

    def flush(self) -> None:
        """Write every figure drawn on since it was last written."""
        for uid in list(self._changed):
            self._save(uid)

    # drawing --------------------------------------------------------------- #
    def _new_figure(self, uid: str, n: int, title: str) -> None:
        cols = max(1, min(self.columns, n))
        rows = max(1, math.ceil(n / cols))
        fig = _figure((2.6 * cols, 1.9 * rows + 0.5), self.show)
        axes = [fig.add_subplot(rows, cols, k + 1) for k in range(n)]
        for k, ax in enumerate(axes):
            ax.set_title(f"configuration {k}", fontsize=8)
            ax.tick_params(labelsize=6)
            ax.set_xlim(*self.range_x)
        fig.suptitle(f"{title} {uid[:8]}: measured x (blue), y (orange) histograms, the camera's profiles faint, "
                     f"the model dashed; density per mm against position in mm", fontsize=9)
        fig.tight_layout()
        self.figures[uid], self._axes[uid] = fig, axes

    def _draw_measured(self, uid: str, i: int, hx, hy, px=None, py=None) -> None:
        axes = self._axes[uid]
        if not 0 <= i < len(axes):
            return
        ax = axes[i]
        lit = []
        for h, rng, color in ((hx, self.range_x, "C0"), (hy, self.range_y, "C1")):
            c, d = _density(h, *rng)
            ax.step(c, d, where="mid", color=color, lw=0.9)
            lit += list(c[np.asarray(h) > 0])
        # the camera's own profiles (20 µm x 5 µm pixels), faint, where the detector publishes them
        for p, rng, color in ((px, self.range_x, "C0"), (py, self.range_y, "C1")):
            if p is not None and np.size(p) and np.sum(p) > 0:
                c, d = _density(p, *rng)
                ax.plot(c, d, color=color, lw=0.4, alpha=0.35)
        if lit:  # the spot is small on the 20 mm screen: zoom to where the light is
            lo, hi = min(lit), max(lit)
            pad = max(0.25 * (hi - lo), 0.5)
            ax.set_xlim(max(lo - pad, self.range_x[0]), min(hi + pad, self.range_x[1]))
        self._changed.add(uid)
        _redraw(self.figures[uid])

    def _draw_model(self, uid: str, i: int, mx, my, label: str) -> None:
        axes = self._axes[uid]
        if not 0 <= i < len(axes):
            return
        ax = axes[i]
        for line in self._overlays.pop((uid, i), []):
            line.remove()
        lines = []
        for h, rng, color in ((mx, self.range_x, "C0"), (my, self.range_y, "C1")):
            c, d = _density(h, *rng)
            lines += ax.plot(c, d, "--", color=color, lw=0.8, alpha=0.9)
        ax.set_title(f"configuration {i} — {label}", fontsize=7)
        self._overlays[(uid, i)] = lines
        self._changed.add(uid)
        _redraw(self.figures[uid])

    def _save(self, uid: str) -> None:
        if self.directory is None or uid not in self.figures:
            return
        self.directory.mkdir(parents=True, exist_ok=True)
        path = self.directory / f"footprints-{uid[:8]}.png"
        self.figures[uid].savefig(path, dpi=80)
        self._changed.discard(uid)
        self._written_at[uid] = time.monotonic()
        if path not in self.written:
            self.written.append(path)


class LiveFitProgress(CallbackBase):
    """The finder's loss and each fit's χ²/dof per iteration, one figure per run.

    Draws the ``finder`` stream (loss against evaluations) and the ``progress`` stream
    (χ²/dof of every iteration; a diagnosis fits many candidates one after the other, so the
    iterations are numbered through the run).  Written as ``progress-<plan>-<uid>.png`` when the
    run stops (``directory``).
    """

    STREAMS = {"finder": ("evaluations", "loss"), "progress": (None, "chi2_reduced")}

    def __init__(self, directory=None, *, show: bool | None = None):
        super().__init__()
        self.directory = Path(directory) if directory is not None else None
        self.show = show
        self.written: list[Path] = []
        self._runs: dict[str, dict] = {}
        self._descriptors: dict[str, tuple[str, str]] = {}

    def start(self, doc):
        """Note the run and its plan's name; its figure opens with its first point."""
        self._runs[doc["uid"]] = {"plan": doc.get("plan_name", "run"), "fig": None, "lines": {}, "x": {}, "y": {}}

    def descriptor(self, doc):
        """Note a ``finder`` or ``progress`` stream's descriptor."""
        if doc.get("name") in self.STREAMS and doc["run_start"] in self._runs:
            self._descriptors[doc["uid"]] = (doc["run_start"], doc["name"])

    def event(self, doc):
        """Add the event's finite loss or χ²/dof to its run's curve."""
        run_uid, stream = self._descriptors.get(doc["descriptor"], (None, None))
        if run_uid is None:
            return
        xkey, ykey = self.STREAMS[stream]
        data = doc["data"]
        y = data.get(ykey)
        if y is None or not np.isfinite(y):
            return
        run = self._runs[run_uid]
        xs, ys = run["x"].setdefault(stream, []), run["y"].setdefault(stream, [])
        xs.append(float(data[xkey]) if xkey else float(len(xs)))
        ys.append(float(y))
        if run["fig"] is None:
            run["fig"] = _figure((6, 3.2), self.show)
            ax = run["fig"].add_subplot(1, 1, 1)
            ax.set_yscale("log")
            ax.set_title(f"{run['plan']} {run_uid[:8]}", fontsize=9)
            ax.set_xlabel("finder: evaluations; fits: iterations (all fits of the run in a row)", fontsize=8)
            ax.set_ylabel("finder loss / fit χ²/dof", fontsize=8)
            run["ax"] = ax
        if stream not in run["lines"]:
            (run["lines"][stream],) = run["ax"].plot([], [], ".-", ms=3, lw=0.8,
                                                      label="finder loss" if stream == "finder" else "fit χ²/dof")
            run["ax"].legend(fontsize=7)
        run["lines"][stream].set_data(xs, ys)
        run["ax"].relim()
        run["ax"].autoscale_view()
        _redraw(run["fig"])

    def stop(self, doc):
        """Write the run's figure as ``progress-<plan>-<uid>.png`` if it drew one and there is a ``directory``."""
        run = self._runs.pop(doc["run_start"], None)
        if run is None or run["fig"] is None or self.directory is None:
            return
        self.directory.mkdir(parents=True, exist_ok=True)
        path = self.directory / f"progress-{run['plan']}-{doc['run_start'][:8]}.png"
        run["fig"].tight_layout()
        run["fig"].savefig(path, dpi=80)
        self.written.append(path)
