"""Startup module of a bluesky-queueserver RE Manager at METRIXS.

What the worker's namespace holds:

* devices ``metrixs`` (the 28 motors and 6 fixed parameters) and ``chamber`` (the focus
  chamber), classic ophyd devices on the PVs of ``$BLUESKY_OFFSETS_PVS`` (a PV map file,
  :mod:`bluesky_offsets.epics.pvmap`), else of the simulated IOC under
  ``$BLUESKY_OFFSETS_PREFIX`` (default ``SIM:METRIXS:``); they connect when first used;
* ``RE``, a RunEngine whose documents go to the run store (``$BLUESKY_OFFSETS_STORE``, default
  the embedded one);
* the plans, whose arguments are plain values (device names, numbers, names, run uids or
  ``"last"``): :func:`~plans.workflow.measure_for_offsets` (find the beam, then frames designed
  for the offsets: the default measurement), :func:`~plans.workflow.measure_bright` (find the
  beam, find bright configurations, measure them), :func:`~plans.workflow.measure` (given
  configurations), :func:`~plans.workflow.find_offsets_in_store`, :func:`~plans.workflow.analyse`,
  :func:`~plans.workflow.validate` (frames no fit used), :func:`~plans.workflow.export_calibration`,
  :func:`~plans.workflow.optimize` (the beam on the calibrated twin).
"""

import logging

from bluesky import RunEngine

from bluesky_offsets.epics.pvmap import PVMap
from bluesky_offsets.store import shared_store
from plans.workflow import (  # noqa: F401 - the plans
    analyse,
    export_calibration,
    find_offsets_in_store,
    measure,
    measure_bright,
    measure_for_offsets,
    optimize,
    validate,
)

logging.getLogger("bluesky_offsets.workflow").setLevel(logging.INFO)
if not logging.getLogger().handlers:
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")

pv_map = PVMap.from_environment()
metrixs = pv_map.beamline_v1("metrixs")
chamber = pv_map.focus_chamber_v1("chamber")

RE = RunEngine({})
run_store = shared_store()
run_store.subscribe(RE)
