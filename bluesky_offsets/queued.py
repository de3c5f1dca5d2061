"""A RunEngine callback that does its work on a thread of its own.

The run store's writer and the headless live views take most of the RunEngine's time between
frames when they run in its thread: an embedded catalog answers each request in 20-100 ms of
Python (two dozen requests when a run stops), and a 20-panel footprint figure takes 0.8 s to
write as PNG.  Behind a queue they
work while the motors move, the camera integrates and the fits run; the documents reach the
wrapped callback in the order they came, on one thread.
"""

from __future__ import annotations

import atexit
import functools
import logging
import queue
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)

_FLUSH = object()  # queued by flush(): the wrapped callback's own flush, on its thread


class QueuedCallback:
    """``RE.subscribe(QueuedCallback(callback))``: ``callback(name, doc)`` on a thread of its own.

    Parameters
    ----------
    callback : callable
        The callback; only the queue's thread calls it (it may own state such as figures).
    name : str
        The thread's name.
    error : callable, optional
        ``error(exc) -> Exception``: a failure of ``callback`` is raised as ``error(exc)``, once, at
        the first document handed over or :meth:`flush` after it (the RunEngine then stops the
        plan, as it would have for the callback itself); the documents queued until then are
        dropped.  Without it a failure is logged once and the callback is called on.

    The wrapped callback's attributes are read through (``queued.written``); :meth:`flush` first
    where they change with the documents.  A program that ends without :meth:`close` still
    delivers what it queued: the threading module's exit hooks drain the queue, before those
    registered earlier (an embedded tiled server's, which stops there).
    """

    def __init__(self, callback: Callable[[str, dict], object], *, name: str = "queued-callback",
                 error: Callable[[BaseException], BaseException] | None = None):
        self.callback = callback
        self._error_type = error
        self._queue: queue.Queue = queue.Queue()
        self._error: BaseException | None = None
        self._logged = False
        self._thread = threading.Thread(target=self._work, name=name, daemon=True)
        self._thread.start()
        register = getattr(threading, "_register_atexit", None) or atexit.register
        register(functools.partial(self.close, raise_error=False))

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                if self._error is None:
                    if item is _FLUSH:
                        getattr(self.callback, "flush")()  # queued only where it has one
                    else:
                        self.callback(*item)
            except BaseException as exc:  # noqa: BLE001 - handed to the RunEngine's thread, or logged
                if self._error_type is not None:
                    self._error = exc
                elif not self._logged:
                    self._logged = True
                    log.warning("%s failed on a %r document (later failures not logged): %s",
                                type(self.callback).__name__, "flush" if item is _FLUSH else item[0], exc,
                                exc_info=exc)
            finally:
                self._queue.task_done()

    def _raise(self) -> None:
        exc, self._error = self._error, None
        if exc is not None:
            assert self._error_type is not None  # an error is kept only to be raised as one
            raise self._error_type(exc) from exc

    def __call__(self, name: str, doc: dict) -> None:
        """Queue the document for the callback (raising a failure of the callback kept from before)."""
        self._raise()
        if not self._thread.is_alive():
            raise RuntimeError(f"{self._thread.name}: closed, the {name!r} document was not delivered")
        self._queue.put((name, doc))

    def flush(self) -> None:
        """Wait until the callback has had every document queued so far, and its own ``flush`` run.

        The callback's own ``flush`` is run where it has one (work it defers, such as a figure's
        next write).
        """
        self._queue_own_flush()
        self._queue.join()
        self._raise()

    def _queue_own_flush(self) -> None:
        if callable(getattr(self.callback, "flush", None)):
            self._queue.put(_FLUSH)

    def close(self, raise_error: bool = True) -> None:
        """Deliver what is queued (and run the callback's own ``flush``), then end the thread."""
        if self._thread.is_alive():
            self._queue_own_flush()
            self._queue.put(None)
            self._thread.join()
        if raise_error:
            self._raise()

    def __getattr__(self, attr: str):
        if attr == "callback":  # not yet set (during __init__)
            raise AttributeError(attr)
        return getattr(self.callback, attr)
