"""Plan stubs the plans share.

Computed results into event streams, slow work in a worker thread with live progress, and a run
of its own or the one already open.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import bluesky.plan_stubs as bps
import bluesky.preprocessors as bpp
import numpy as np
from bluesky.utils import MsgGenerator

from bluesky_offsets.model.cluster import Progress

__all__ = ["BAR_KEYS", "Record", "emit_rows", "in_run", "run_in_thread"]


class Record:
    """A readable whose values the plan sets: how computed results enter an event stream.

    One instance per stream (the RunEngine requires the same objects in every event of a
    stream); numbers, strings and arrays longer than 16 values.
    """

    def __init__(self, name: str):
        self.name, self.parent = name, None
        self._values: dict[str, Any] = {}
        self._time = time.time()

    def set(self, values: Mapping[str, Any]) -> None:
        self._values, self._time = dict(values), time.time()

    def read(self) -> dict:
        return {k: {"value": v, "timestamp": self._time} for k, v in self._values.items()}

    def describe(self) -> dict:
        out = {}
        for k, v in self._values.items():
            if isinstance(v, str):
                out[k] = {"source": "analysis", "dtype": "string", "shape": []}
            elif isinstance(v, (bool, np.bool_)):
                out[k] = {"source": "analysis", "dtype": "boolean", "shape": []}
            elif np.ndim(v):
                arr = np.asarray(v)
                out[k] = {"source": "analysis", "dtype": "array", "shape": list(arr.shape),
                          "dtype_numpy": arr.dtype.str}
            else:
                out[k] = {"source": "analysis", "dtype": "integer" if isinstance(v, (int, np.integer))
                          else "number", "shape": []}
        return out


def emit_rows(stream: str, rows: Sequence[Mapping[str, Any]], record: Record | None = None) -> MsgGenerator[None]:
    """One event per row in ``stream`` (rows share their keys).

    ``record``: the stream's readable where events are added to it over several calls (the
    RunEngine wants the same one each time).
    """
    rec = record or Record(stream)
    for row in rows:
        rec.set(row)
        yield from bps.create(name=stream)
        yield from bps.read(rec)
        yield from bps.save()


BAR_KEYS = ("iteration", "accepted", "chi2_reduced", "chi2_features", "jacobian_refreshed")


def run_in_thread(func: Callable[[Callable[[dict], None]], Any], *, stream: str | None = "progress",
                  desc: str = "working", poll: float = 0.25, show: bool = True) -> MsgGenerator[Any]:
    """Call ``func(progress)`` in a worker thread; return its result (or raise its error).

    Every ``progress(dict)`` call from the worker becomes an event in ``stream`` (its
    numeric entries; the first call fixes the keys) and a line on a progress bar, so long fits
    show what they do while the RunEngine keeps serving pause and abort.
    """
    from bluesky_offsets.progress import bar as progress_bar
    from bluesky_offsets.progress import interactive

    q: queue.Queue = queue.Queue()
    box: dict = {}

    def work():
        try:
            box["result"] = func(Progress(q.put))  # a Progress: it may be sent to a worker process
        except BaseException as exc:  # re-raised in the plan, where the RunEngine reports it
            box["error"] = exc

    rec, keys = Record(stream or "progress"), None
    t0 = time.monotonic()
    bar = progress_bar(desc=desc, unit="steps", disable=not show,
                       bar_format="{desc}: {n_fmt} steps, {elapsed} {postfix}")

    def drain():
        nonlocal keys
        while True:
            try:
                d = q.get_nowait()
            except queue.Empty:
                return
            num = {k: (int(v) if isinstance(v, (bool, np.bool_)) else v) for k, v in d.items()
                   if isinstance(v, (int, float, bool, np.number, np.bool_))}
            bar.update(1)
            # a few numbers on the bar (all of them go to the stream)
            shown = {k: v for k, v in num.items() if k in BAR_KEYS and not (isinstance(v, float) and np.isnan(v))}
            bar.set_postfix({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in (shown or num).items()},
                            refresh=True)
            if stream is None:
                continue
            keys = keys or sorted(num)
            rec.set({"seconds": time.monotonic() - t0, **{k: num.get(k, float("nan")) for k in keys}})
            yield from bps.create(name=stream)
            yield from bps.read(rec)
            yield from bps.save()

    thread = threading.Thread(target=work, name=f"analysis: {desc}", daemon=True)
    thread.start()
    every = 1.0 if interactive() else 10.0  # the elapsed time ticks on a terminal
    last = time.monotonic()
    try:
        while thread.is_alive():
            yield from bps.sleep(poll)
            if time.monotonic() - last > every:
                bar.refresh()
                last = time.monotonic()
            yield from drain()
        thread.join()
        yield from drain()
    finally:
        bar.close()
    if "error" in box:
        raise box["error"]
    return box["result"]


def in_run(body: Callable[[], MsgGenerator[Any]], md: Mapping, open_run: bool) -> MsgGenerator[tuple[Any, str | None]]:
    """Run ``body()`` in a run of its own (closed as failed on error), or in the open one."""
    if not open_run:
        return (yield from body()), None
    box = {}

    def inner():
        box["result"] = yield from body()

    uid = yield from bpp.run_wrapper(inner(), md=dict(md))
    return box["result"], uid
