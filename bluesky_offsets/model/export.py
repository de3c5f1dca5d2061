"""The calibrated twin as a file: ``calibration.json``.

:func:`write_calibration` writes a calibrated model (offsets and effects, each as value ± σ in
its physical unit with its class, the covariance, the parameter table's version, the uids of the
measurement and of the fit) and :func:`load_calibration` reads it back as a
:class:`~bluesky_offsets.model.state.CalibratedState`: the model the twins (RAYX or torch) trace
and that :func:`plans.optimize.optimize_beam`, the diagnosis and the queue plans accept.  A file
of another parameter table, or one that is not such a file, is refused in one line
(:class:`CalibrationFileError`).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics import effects as E
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable

FORMAT = "bluesky-offsets calibration"
VERSION = 1


class CalibrationFileError(InputError):
    """A calibration file that cannot be used; the message names the file and why."""


def calibration_record(model, *, table: ParameterTable = METRIXS, measurement_uid: str | None = None,
                       validation: Mapping | None = None) -> dict:
    """The file's content for a calibrated ``model`` (a calibrated state or an analysis)."""
    from bluesky_offsets.model.posterior import Posterior
    from bluesky_offsets.model.state import CalibratedState
    cal = CalibratedState.of(model)
    post = Posterior.of(cal, table)
    if post is None:
        raise CalibrationFileError("the model has no covariance: a calibration file needs the fit's uncertainty")
    cov = [[v if math.isfinite(v) else None for v in row] for row in post.covariance.tolist()]
    return {"format": FORMAT, "version": VERSION, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "parameter_table": table.name, "parameter_table_version": table.version,
            "measurement_uid": measurement_uid, "model_uid": cal.uid, "label": cal.state.label,
            "offsets": {e.name: e.as_dict() for e in post.offsets},
            "effects": {eff: {q: e.as_dict() for q, e in d.items()} for eff, d in post.effects.items()},
            "counts": post.counts(), "combinations": list(post.combinations),
            # the offsets' prior the values and the covariance hold; the classes are against the table's
            "prior": {"sigma_normalized": post.prior_sigma, "estimated_from_data": cal.prior_sigma is not None},
            "covariance": {"units": "normalized offsets (fractions of each range), then effect parameters",
                           "names": list(post.names), "matrix": cov},
            "validation": dict(validation) if validation else None}


def write_calibration(path: str | os.PathLike, model, *, table: ParameterTable = METRIXS,
                      measurement_uid: str | None = None, validation: Mapping | None = None) -> Path:
    """Write ``model`` to ``path`` (JSON); returns the path."""
    path = Path(path)
    rec = calibration_record(model, table=table, measurement_uid=measurement_uid, validation=validation)
    path.write_text(json.dumps(rec, indent=1, allow_nan=False, default=_plain))
    return path


def _plain(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    raise TypeError(f"{type(v).__name__} is not JSON")


def load_calibration(path: str | os.PathLike, *, table: ParameterTable = METRIXS):
    """The calibrated model of a calibration file, as a :class:`~bluesky_offsets.model.state.CalibratedState`.

    Raises :class:`CalibrationFileError` (one line: the file and why) for a file that does not read
    as a calibration, or one of another parameter table version.
    """
    from bluesky_offsets.model.state import CalibratedState, ModelState
    path = Path(path)
    try:
        rec = json.loads(path.read_text())
    except OSError as exc:
        raise CalibrationFileError(f"calibration {path}: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CalibrationFileError(f"calibration {path}: not JSON ({exc})") from None
    if not isinstance(rec, dict) or rec.get("format") != FORMAT:
        raise CalibrationFileError(f"calibration {path}: not a {FORMAT} file")
    if rec.get("version") != VERSION:
        raise CalibrationFileError(f"calibration {path}: format version {rec.get('version')!r}, this reads {VERSION}")
    if rec.get("parameter_table_version") != table.version:
        raise CalibrationFileError(f"calibration {path}: made with parameter table {rec.get('parameter_table')!r} "
                                   f"version {rec.get('parameter_table_version')!r}, this is {table.name!r} version "
                                   f"{table.version}")
    try:
        offsets = np.array([float(rec["offsets"][n]["normalized"]) for n in table.names])
        effects = {eff: E.get(eff).values({q: float(v["value"]) for q, v in d.items()})
                   for eff, d in rec["effects"].items()}
        names = tuple(rec["covariance"]["names"])
        cov = np.array([[math.nan if v is None else float(v) for v in row] for row in rec["covariance"]["matrix"]])
        prior = rec.get("prior") or {}
        spread = float(prior["sigma_normalized"]) if prior.get("estimated_from_data") else None
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationFileError(f"calibration {path}: incomplete or malformed ({type(exc).__name__}: {exc})") \
            from None
    if cov.shape != (len(names), len(names)) or len(names) != len(table) + sum(len(v) for v in effects.values()):
        raise CalibrationFileError(f"calibration {path}: the covariance does not match its parameters")
    if not np.isfinite(offsets).all() or np.abs(offsets).max() > 0.2 + 1e-9:
        raise CalibrationFileError(f"calibration {path}: offsets outside ±0.2 of their ranges")
    if spread is not None and not 0.0 < spread <= 0.2:
        raise CalibrationFileError(f"calibration {path}: the offsets' prior σ {spread!r} is not within (0, 0.2]")
    state = ModelState(offsets, effects, str(rec.get("label") or "calibration"))
    return CalibratedState(state, cov, names, rec.get("model_uid"), spread)
