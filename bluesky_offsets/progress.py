r"""Progress as people read it: a live bar on a terminal, one line per task in a file, nothing under ``-q``.

On a terminal, a live bar; in a file or a pipe, one line per finished task with its count and
duration (and one a minute while a long one runs); nothing under ``-q``.

:func:`bar` takes tqdm's arguments and returns a tqdm bar on a terminal, else a :class:`Lines`
with the part of tqdm's interface this package uses.  :func:`set_quiet` is the CLI's ``-q``.

>>> import io
>>> out = io.StringIO()
>>> with bar(total=3, desc="tracing", unit="sim", file=out, clock=iter([0.0, 1.0, 2.5]).__next__) as b:
...     b.update(3)
...     b.set_postfix(best=0.25)
>>> out.getvalue()
'tracing: 3/3 sim, 2.5 s, best=0.25\n'
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TextIO

_quiet = False


def set_quiet(quiet: bool = True) -> None:
    """No progress at all from now on (the CLI's ``-q``)."""
    global _quiet
    _quiet = bool(quiet)


def quiet() -> bool:
    """Whether progress is off (after :func:`set_quiet`)."""
    return _quiet


def interactive(stream: TextIO | None = None) -> bool:
    """Whether ``stream`` (default stderr, where progress goes) is a terminal."""
    stream = sys.stderr if stream is None else stream
    return bool(getattr(stream, "isatty", lambda: False)())


def bar(iterable: Iterable | None = None, *, desc: str = "", total: int | None = None, unit: str = "it",
        disable: bool = False, leave: bool = True, file: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic, **tqdm_options: Any):
    """A progress bar: tqdm's on a terminal, :class:`Lines` elsewhere, silent when ``disable`` or quiet.

    A transient bar (``leave=False``) prints nothing outside a terminal.
    """
    if total is None and iterable is not None and hasattr(iterable, "__len__"):
        total = len(iterable)  # type: ignore[arg-type]
    if disable or _quiet or (not leave and not interactive(file)):
        return Lines(iterable, desc=desc, total=total, unit=unit, file=None, clock=clock,
                     initial=tqdm_options.get("initial", 0))
    if interactive(file):
        from tqdm.auto import tqdm
        return tqdm(iterable, desc=desc, total=total, unit=unit, leave=leave, file=file, **tqdm_options)
    return Lines(iterable, desc=desc, total=total, unit=unit, file=file or sys.stderr, clock=clock,
                 initial=tqdm_options.get("initial", 0))


class Lines:
    """tqdm's interface as this package uses it, writing one line when closed (none with ``file=None``)."""

    every = 60.0  # seconds between the lines of a task still running

    def __init__(self, iterable: Iterable | None = None, *, desc: str = "", total: int | None = None,
                 unit: str = "it", file: TextIO | None = None, clock: Callable[[], float] = time.monotonic,
                 initial: int = 0):
        self.iterable, self.desc, self.total, self.unit = iterable, desc, total, unit
        self.n = initial
        self._file, self._clock, self._postfix, self._closed = file, clock, "", False
        self._t0 = self._last = clock()

    def __iter__(self) -> Iterator:
        try:
            for item in (self.iterable if self.iterable is not None else ()):
                yield item
                self.update(1)
        finally:
            self.close()

    def __enter__(self) -> Lines:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def update(self, n: int = 1) -> None:
        """Count ``n`` more done (and write a line if a minute has passed since the last)."""
        self.n += n
        self.refresh()

    def set_postfix(self, ordered_dict: dict | None = None, refresh: bool = True, **kwargs: Any) -> None:
        """Show ``key=value`` pairs after the count (``refresh`` is tqdm's, ignored here)."""
        items = {**(ordered_dict or {}), **kwargs}
        self._postfix = ", ".join(f"{k}={v}" for k, v in items.items())

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        """Show ``s`` after the count (``refresh`` is tqdm's, ignored here)."""
        self._postfix = s

    def refresh(self) -> None:
        """A line if the task has run a minute since the last one (a file is no live display)."""
        if self._file is not None and not self._closed:
            now = self._clock()
            if now - self._last >= self.every:
                self._line(" (running)", now)

    def write(self, s: str) -> None:
        """Print ``s`` as a line of its own to the file (nothing with ``file=None``)."""
        if self._file is not None:
            print(s, file=self._file, flush=True)

    def close(self) -> None:
        """Write the task's final line, once (later calls do nothing)."""
        if self._closed:
            return
        self._closed = True
        if self._file is not None:
            self._line("", self._clock())

    def _line(self, note: str, now: float) -> None:
        self._last = now
        count = f"{self.n}/{self.total}" if self.total is not None else f"{self.n}"
        line = f"{self.desc}: {count} {self.unit}, {now - self._t0:.1f} s{note}"
        print(line + (f", {self._postfix}" if self._postfix else ""), file=self._file, flush=True)
