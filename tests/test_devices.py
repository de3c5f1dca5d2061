"""ophyd-async and classic ophyd devices against the simulated IOC (unmodified clients)."""

from __future__ import annotations

import threading
import time

import bluesky.plan_stubs as bps
import numpy as np
import pytest
from bluesky import RunEngine

from bluesky_offsets.epics.devices import FixedParameter, FocusChamber, MetrixsBeamline
from bluesky_offsets.epics.devices_v1 import FocusChamberV1, make_beamline_v1
from bluesky_offsets.epics.pvs import ChamberError, FixedParameterError
from bluesky_offsets.physics.parameters import METRIXS


@pytest.fixture(scope="module")
def RE():
    return RunEngine({}, call_returns_result=True)


@pytest.fixture(scope="module")
def async_devices(RE, metrixs_ioc):
    from ophyd_async.core import init_devices
    P = metrixs_ioc.prefix
    with init_devices():
        beamline = MetrixsBeamline(P, name="metrixs")
        chamber = FocusChamber(P + "chamber:", name="chamber")
    return beamline, chamber


@pytest.fixture(scope="module")
def v1_devices(metrixs_ioc):
    P = metrixs_ioc.prefix
    beamline = make_beamline_v1(P, name="metrixs_v1")
    chamber = FocusChamberV1(P + "chamber:", name="chamber_v1")
    beamline.wait_for_connection(timeout=60)
    chamber.wait_for_connection(timeout=30)
    return beamline, chamber


def _slow(ca, rec, velo):
    old = ca.get(rec + ".VELO")
    ca.put(rec + ".VELO", velo)
    return old


@pytest.mark.parametrize("client", ["ophyd-async", "ophyd"])
def test_mvr_returns_with_readback_at_target(client, RE, metrixs_ioc, ca):
    """NOTES.md saw an ophyd-async relative move return early against caproto's example motor."""
    P = metrixs_ioc.prefix
    rec = P + ("e2:ty" if client == "ophyd-async" else "e2:tz")
    if client == "ophyd-async":
        from ophyd_async.core import init_devices
        from ophyd_async.epics.motor import Motor
        with init_devices():
            m = Motor(rec, name="m_async")
        readback = m.user_readback
    else:
        from ophyd import EpicsMotor
        m = EpicsMotor(rec, name="m_v1")
        m.wait_for_connection(timeout=30)
        readback = m.user_readback
    mres = ca.get(rec + ".MRES")
    old_velo = _slow(ca, rec, 0.5)  # 0.25 mm takes 0.5 s
    seen = {}

    def plan():
        p0 = yield from bps.rd(m)
        t0 = time.monotonic()
        yield from bps.mvr(m, 0.25)
        seen["elapsed"] = time.monotonic() - t0
        seen["ioc_rbv"] = ca.get(rec + ".RBV")  # what the IOC says the moment the step returns
        seen["ioc_dmov"] = ca.get(rec + ".DMOV")
        seen["client_rbv"] = yield from bps.rd(readback)
        seen["target"] = p0 + 0.25
        yield from bps.mvr(m, -0.25)

    try:
        RE(plan())
    finally:
        ca.put(rec + ".VELO", old_velo)
    assert seen["elapsed"] >= 0.45, seen
    assert seen["ioc_dmov"] == 1
    assert abs(seen["ioc_rbv"] - seen["target"]) <= mres, seen
    assert abs(seen["client_rbv"] - seen["target"]) <= mres, seen


def test_beamline_device_groups_motors_by_component(async_devices, metrixs_ioc, RE):
    from ophyd_async.epics.motor import Motor
    bl, _ = async_devices
    P = metrixs_ioc.prefix
    assert len(bl.motors) == 28 and len(bl.fixed) == 6
    assert list(bl.motors) == list(METRIXS.motorized_names)
    assert isinstance(bl.e1.rx, Motor) and bl.parameter("E1.rotationXerror") is bl.e1.rx
    assert bl.e1.rx.user_readback.source == f"ca://{P}e1:rx.RBV"
    assert bl.exit_slit.tz is bl.motors["ExitSlit.translationZerror"]
    assert isinstance(bl.m1.radius, FixedParameter) and bl.fixed["E2.shortHalfAxisB"] is bl.e2.b
    reading = RE(bps.rd(bl.m1.radius)).plan_result
    assert reading == pytest.approx(174.21)
    with pytest.raises(FixedParameterError, match=r"M1_Cylinder.radius .* fixed parameter, not a motor"):
        RE(bps.mv(bl.m1.radius, 174.3))
    with pytest.raises(FixedParameterError, match="cannot be set"):
        RE(bps.mv(bl.e1.a, 20800))
    assert RE(bps.rd(bl.m1.radius)).plan_result == pytest.approx(174.21)


def test_pv_names_are_configurable(metrixs_ioc):
    bl = MetrixsBeamline("BL:", name="bl", pv_names={"E1.rotationXerror": "REAL:E1:PITCH"})
    assert bl.e1.rx.user_readback.source == "ca://REAL:E1:PITCH.RBV"
    assert bl.e2.rx.user_readback.source == "ca://BL:e2:rx.RBV"
    ch = FocusChamber("CAM:", name="cam", pv_names={"hist_x": "CAM:Stats:ProfileX"})
    assert ch.hist_x.source == "ca://CAM:Stats:ProfileX" and ch.hist_y.source == "ca://CAM:HistY"
    with pytest.raises(ValueError, match="not motorized parameters"):
        MetrixsBeamline("BL:", pv_names={"E1.longHalfAxisA": "X"})
    with pytest.raises(ValueError, match="unknown chamber signals"):
        FocusChamber("CAM:", pv_names={"histx": "X"})
    v1 = make_beamline_v1("BL:", name="v1", pv_names={"E2.rotationXerror": "REAL:E2:PITCH"})
    assert v1.e2.rx.user_readback.pvname == "REAL:E2:PITCH.RBV" and v1.e1.rx.prefix == "BL:e1:rx"


def test_focus_chamber_trigger_and_read(async_devices, RE, metrixs_ioc):
    _, ch = async_devices
    docs = []
    RE(_one_event([ch]), lambda name, doc: docs.append((name, doc)))
    event = next(d for n, d in docs if n == "event")["data"]
    descriptor = next(d for n, d in docs if n == "descriptor")
    hx, hy = np.asarray(event["chamber-hist_x"]), np.asarray(event["chamber-hist_y"])
    assert hx.shape == (50,) and hy.shape == (50,) and np.asarray(event["chamber-image"]).shape == (2500,)
    assert event["chamber-total_counts"] > 0 and hx.sum() * 3000 <= event["chamber-total_counts"] + 1e-6
    config = descriptor["configuration"]["chamber"]["data"]
    assert config["chamber-num_rays"] == 3000 and len(config["chamber-truth_id"]) == 12
    assert config["chamber-table_version"] == METRIXS.version
    np.testing.assert_allclose(config["chamber-axis_x"][[0, -1]], [-9.8, 9.8])


def _one_event(devices):
    yield from bps.open_run()
    yield from bps.trigger_and_read(devices)
    yield from bps.close_run()


def test_chamber_reports_an_aborted_frame(async_devices, RE, metrixs_ioc, ca):
    _, ch = async_devices
    P = metrixs_ioc.prefix + "chamber:"
    ca.put(P + "AcquireTime", 2.0)
    timer = threading.Timer(0.7, lambda: ca.put(P + "Acquire", 0))
    try:
        timer.start()
        from bluesky.utils import FailedStatus
        with pytest.raises(FailedStatus) as info:
            RE(bps.trigger(ch, wait=True))
        assert isinstance(info.value.__cause__, ChamberError)
        assert "acquisition aborted" in str(info.value.__cause__)
    finally:
        timer.cancel()
        ca.put(P + "AcquireTime", 0.0)


def test_v1_devices(v1_devices, RE, ca, metrixs_ioc):
    from ophyd import EpicsMotor
    bl, ch = v1_devices
    P = metrixs_ioc.prefix
    assert len(bl.motors) == 28 and len(bl.fixed) == 6
    assert isinstance(bl.e1.rx, EpicsMotor) and bl.e1.rx.prefix == P + "e1:rx"
    assert bl.e1.rx.limits == (-1.5, 1.5)
    assert bl.m1.radius.get() == pytest.approx(174.21)
    with pytest.raises(FixedParameterError, match="fixed parameter"):
        bl.m1.radius.set(174.3)
    with pytest.raises(FixedParameterError):
        RE(bps.mv(bl.m1.radius, 174.3))
    docs = []
    RE(_one_event([ch, bl.e1.rx]), lambda name, doc: docs.append((name, doc)))
    event = next(d for n, d in docs if n == "event")["data"]
    assert np.asarray(event["chamber_v1_hist_x"]).shape == (50,) and event["chamber_v1_total_counts"] > 0
    assert event["metrixs_v1_e1_rx"] == pytest.approx(ca.get(P + "e1:rx.RBV"))
    # the limit check of EpicsMotor refuses a move beyond HLM before anything moves
    from ophyd.utils import LimitError
    with pytest.raises(LimitError):
        RE(bps.mv(bl.e1.rx, 2.0))
    assert ca.get(P + "e1:rx.RBV") == pytest.approx(0.0, abs=1e-4)
