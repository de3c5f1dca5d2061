"""What the sessions on a beamline share (``demo``, ``calibrate``).

The devices connected from a PV map, the workflow's lines under each step, a progress bar per
measuring run, the Channel Access channels closed before an IOC goes.
"""

from __future__ import annotations

import logging
import re

from bluesky_offsets.commands.cli import CliError


def connect_devices(pv_map, timeout: float):
    """The ophyd-async beamline and chamber of ``pv_map``, connected.

    CliError naming the PVs that did not answer within ``timeout`` seconds.
    """
    from ophyd_async.core import NotConnectedError, init_devices
    try:
        with init_devices(timeout=timeout):
            beamline = pv_map.beamline("metrixs")
            chamber = pv_map.focus_chamber("chamber")
    except NotConnectedError as exc:
        # motor records appear once per field (.RBV, .EGU ...): count the records
        pvs = sorted({pv.split(".")[0] for pv in re.findall(r"ca://([^\s:]+(?::[^\s:]+)*)", str(exc))})
        shown = ", ".join(pvs[:3]) + (f" and {len(pvs) - 3} more" if len(pvs) > 3 else "")
        raise CliError(f"cannot reach the beamline ({pv_map.name}): {len(pvs) or 'some'} records did not connect within "
                       f"{timeout:g} s ({shown}); is the IOC running, is EPICS_CA_ADDR_LIST set? "
                       f"bluesky-offsets check-pvs FILE lists what is missing") from None
    return beamline, chamber


class StepLines(logging.Handler):
    """The ``bluesky_offsets.workflow`` logger's lines through ``say``, indented under the step."""

    def __init__(self, say):
        super().__init__(logging.INFO)
        self.say = say
        self.logger = logging.getLogger("bluesky_offsets.workflow")
        self._level, self._propagate = self.logger.level, self.logger.propagate
        self.logger.setLevel(logging.INFO)
        self.logger.propagate = False
        self.logger.addHandler(self)

    def emit(self, record):
        """Say the record's message, indented under the step, unless progress is quiet."""
        from bluesky_offsets.progress import quiet
        if not quiet():  # the steps' detail lines are progress too
            self.say("      " + record.getMessage())

    def close(self):
        """Detach from the workflow logger and restore its level and propagation."""
        self.logger.removeHandler(self)
        self.logger.setLevel(self._level)
        self.logger.propagate = self._propagate
        super().close()


class ScanProgress:
    """RunEngine callback: a progress bar per measuring run (one tick per configuration)."""

    PLANS = {"find_high_ray_configurations": "search bright configurations",
             "measure_configurations": "measure configurations"}

    def __init__(self):
        self.bar = None
        self.primary = set()
        self.bright = 0

    def __call__(self, name, doc):
        """Take one document: a bar at a measuring run's start, a tick per primary event, closed at its stop."""
        from bluesky_offsets.progress import bar

        from plans import enough_rays
        if name == "start" and doc.get("plan_name") in self.PLANS:
            self.bar = bar(total=doc.get("n_configurations"), desc=self.PLANS[doc["plan_name"]], unit="cfg")
            self.bright = 0
        elif name == "descriptor" and doc.get("name") == "primary":
            self.primary.add(doc["uid"])
        elif name == "event" and self.bar is not None and doc["descriptor"] in self.primary:
            d = doc["data"]
            hx = next((v for k, v in d.items() if k.endswith("hist_x")), None)
            hy = next((v for k, v in d.items() if k.endswith("hist_y")), None)
            if hx is not None and hy is not None:
                self.bright += int(enough_rays(hx, hy)[0])
                self.bar.set_postfix(bright=self.bright)
            self.bar.update(1)
        elif name == "stop" and self.bar is not None:
            self.bar.close()
            self.bar = None


def subscribe_views(RE, store, out) -> list:
    """Subscribe the run store, the scan progress and the live views to ``RE``; the views.

    The live views are windows with a GUI backend, else PNGs under ``out/live``, written on
    threads of their own.
    """
    from pathlib import Path

    from bluesky_offsets.live import LiveFitProgress, LiveFootprints, in_background
    store.subscribe(RE)
    RE.subscribe(ScanProgress())
    live = [in_background(LiveFootprints(Path(out) / "live")), in_background(LiveFitProgress(Path(out) / "live"))]
    for cb in live:
        RE.subscribe(cb)
    return live


def close_channels(RE) -> None:
    """Close the devices' Channel Access channels before the IOC goes.

    Otherwise libca prints a "Virtual circuit disconnect" exception after the summary.  In the
    RunEngine's loop, whose thread holds the CA context.
    """
    import asyncio

    async def purge():
        from aioca import purge_channel_caches
        purge_channel_caches()

    try:
        asyncio.run_coroutine_threadsafe(purge(), RE.loop).result(timeout=10)
    except Exception:  # noqa: BLE001 - cosmetic; the IOC is stopped either way
        pass
