"""Offset finding as a plan: measurement in, offsets per parameter and loss out, as a stream.

The finder itself is pluggable: anything that satisfies :class:`Finder`, i.e.
``finder(measurement, callback=None)`` with a
:class:`bluesky_offsets.model.measurement.Measurement`, returning a :class:`FinderResult`
(normalized ``offsets`` in table order and a ``loss``: an :class:`OffsetResult`, a
:class:`bluesky_offsets.offsets.calibration.Calibration`, or any object with both).
:class:`bluesky_offsets.offsets.calibration.OffsetFinder` is the project's own.

The finder runs in a worker thread, so the RunEngine stays responsive
(pause/abort) while it works; a finder that takes ``callback=`` reports its progress
(dicts of evaluations, seconds, loss) and the plan streams it live as ``finder``
events (plot them with :class:`bluesky_offsets.offsets.calibration.LossPlot`).  For
bluesky-queueserver, pass the finder as an import path string
(``"package.module:function"``) and the measurement as a run uid: both are plain JSON.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from bluesky.utils import MsgGenerator

from bluesky_offsets.errors import InputError
from bluesky_offsets.model.measurement import Measurement
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.store import RunStore, as_measurement

from ._stubs import emit_rows, in_run, run_in_thread


@dataclass
class OffsetResult:
    """Offsets found for one measurement.

    Attributes
    ----------
    offsets : ndarray, shape (P,)
        Normalized offsets (fractions of each parameter's range), table order.
    loss : float
        The finder's final loss (e.g. histogram MSE).
    info : dict
        Anything else the finder reports (iterations, timings ...).
    """

    offsets: np.ndarray
    loss: float
    info: dict = field(default_factory=dict)
    table: ParameterTable = METRIXS
    raw: object = None  # the finder's own result object
    uid: str | None = None  # the find_offsets run (None inside a run opened by the caller)

    @property
    def physical(self) -> np.ndarray:
        """Offsets in mm/mrad."""
        return self.offsets * self.table.span

    def as_mapping(self) -> dict[str, float]:
        """``{parameter name: normalized offset}`` in table order."""
        return {n: float(v) for n, v in zip(self.table.names, self.offsets)}


class FinderResult(Protocol):
    """What a finder returns: normalized offsets (fractions of each range, table order) and its final loss.

    Anything else it carries (uncertainties ``sigma``, ``status``, ``history``, ``twin_mse``) goes
    into the run when present.
    """

    offsets: np.ndarray
    loss: float


@runtime_checkable
class Finder(Protocol):
    """An offset finder: a measurement in, a :class:`FinderResult` out.

    ``callback`` (a finder may leave it out of its signature) receives progress dicts
    (evaluations, seconds, loss).
    """

    def __call__(self, measurement: Measurement, *,
                 callback: Callable[[dict], None] | None = None) -> FinderResult:
        """Find the offsets that explain ``measurement``, reporting progress to ``callback``."""
        ...


def _as_result(raw, table: ParameterTable) -> OffsetResult:
    if isinstance(raw, OffsetResult):
        return raw
    if not (hasattr(raw, "offsets") and hasattr(raw, "loss")):
        raise TypeError("a finder must return a FinderResult: an object with 'offsets' (normalized, table order) "
                        f"and 'loss' (e.g. plans.OffsetResult); got {type(raw).__name__}")
    off = table.validate(np.asarray(raw.offsets, dtype=float), "finder offsets")
    return OffsetResult(off, float(raw.loss), {}, table, raw)


def _resolve_finder(finder) -> Callable:
    if callable(finder):
        return finder
    if isinstance(finder, str) and ":" in finder:
        module, func = finder.split(":", 1)
        try:
            return getattr(importlib.import_module(module), func)
        except (ImportError, AttributeError) as exc:
            raise InputError(f"finder {finder!r} cannot be imported: {exc}") from None
    raise TypeError(f"finder must be a callable or 'module:function', got {finder!r}")


def _reports_progress(func: Callable) -> bool:
    """True for finders that take ``callback=`` (progress dicts while they work)."""
    import inspect
    try:
        params = inspect.signature(func).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(p.name == "callback" or p.kind is p.VAR_KEYWORD for p in params)


_STATUS_CODE = {"determined": 2.0, "weak": 1.0, "undetermined": 0.0}


def _extras(raw, n: int) -> dict[str, object]:
    """Uncertainties, identifiability and the loss curve, when the finder reports them."""
    out: dict[str, object] = {}
    sigma = getattr(raw, "sigma", None)
    if sigma is not None and np.asarray(sigma).shape == (n,):
        out["offsets_sigma"] = np.asarray(sigma, dtype=float)
    status = getattr(raw, "status", None)
    if status is not None and len(status) == n:
        # 2 determined, 1 weak, 0 undetermined (numbers: event data wants numeric arrays)
        out["offsets_determined"] = np.array([_STATUS_CODE.get(str(s), 0.0) for s in status])
    twin_mse = getattr(raw, "twin_mse", None)
    if twin_mse is not None:
        out["twin_mse"] = float(twin_mse)
    history = getattr(raw, "history", None)
    if isinstance(history, Mapping):
        for key, val in history.items():
            arr = np.asarray(val)
            if arr.ndim == 1 and arr.size and arr.dtype.kind in "fiu":
                out[f"loss_curve_{key}"] = arr.astype(float)
    return out


def data_key(name: str) -> str:
    """Event data key of a parameter (dots are not welcome in table column names)."""
    return name.replace(".", "_")


def find_offsets(finder, measurement=None, *, store: RunStore | str | None = None,
                 table: ParameterTable = METRIXS, stream_name: str = "offsets", open_run: bool = True,
                 md: Mapping | None = None, show: bool = True) -> MsgGenerator[OffsetResult]:
    """Run an offset finder on a measurement and emit the result as a stream.

    Parameters
    ----------
    finder : Finder or str
        ``finder(measurement, callback=None) -> FinderResult`` (:class:`Finder`), or its import
        path ``"module:function"``.
    measurement : Measurement or str
        The measurement (e.g. returned by :func:`plans.measure_configurations`)
        or the uid of a measurement run in ``store``.
    store : RunStore or str, optional
        Where to load a uid from (default store when omitted).
    stream_name : str
        Name of the event stream holding the result (default ``"offsets"``).
    open_run : bool
        Open a run of its own (default); ``False`` emits the stream into the run
        that is already open (inside a larger plan).
    md : mapping, optional
        Extra run metadata.

    Returns
    -------
    OffsetResult

    Notes
    -----
    The stream has one event: ``loss``, the normalized offset of every
    parameter (key = name with ``.`` -> ``_``), and arrays ``offsets`` /
    ``offsets_physical`` in table order; when the finder reports them (e.g. a
    :class:`bluesky_offsets.offsets.calibration.Calibration`), also ``offsets_sigma``,
    ``offsets_determined`` (2 determined, 1 weak, 0 undetermined) and the loss
    curve ``loss_curve_<key>`` arrays.
    """
    func = _resolve_finder(finder)
    m: Measurement = as_measurement(measurement, store)
    m.check_table(table)
    live = _reports_progress(func)

    def body():
        # the finder in a worker thread: the RunEngine keeps serving pause and abort, and a
        # finder that reports progress streams it live ("finder": evaluations, seconds, loss)
        result: OffsetResult = yield from run_in_thread(
            lambda progress: _as_result(func(m, callback=progress) if live else func(m), table),
            stream="finder" if live else None, desc="find offsets", show=show)
        values = {"loss": result.loss, "offsets": result.offsets, "offsets_physical": result.physical}
        values.update({data_key(n): float(v) for n, v in zip(table.names, result.offsets)})
        values.update(_extras(result.raw, len(table)))
        yield from emit_rows(stream_name, [values])
        return result

    _md = {"plan_name": "find_offsets", "purpose": "offset finding",
           "plan_args": {"finder": finder if isinstance(finder, str) else repr(func),
                         "measurement": m.uid or "", "stream_name": stream_name},
           "measurement_uid": m.uid, "parameter_table_version": table.version,
           "parameter_names": list(table.names), "finder": getattr(func, "__qualname__", repr(func)),
           "n_configurations": len(m)}
    if m.truth_id:
        _md["truth_id"] = m.truth_id
    _md.update(md or {})
    result, uid = yield from in_run(body, _md, open_run)
    result.uid = uid
    return result
