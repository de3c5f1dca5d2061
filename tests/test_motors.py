"""Motors as they really move (``--motors realistic``): encoder noise, backlash taken out by
BDST, retries within RDBD, a hidden step-scale error and a stalled load; from outside with
caproto's client, and the plans' arrival check with ophyd-async's Motor."""

from __future__ import annotations

import numpy as np
import pytest

from bluesky_offsets.physics.parameters import METRIXS
from sim_iocs.metrixs import motor_pv
from sim_iocs.truth import default_start

STALLED, SCALED, PLAIN = "E1.rotationXerror", "E2.translationYerror", "M1_Cylinder.translationXerror"
TRUTH = {"offsets": {}, "motors": {STALLED: {"stalled": True}, SCALED: {"step_scale": 0.02}}}
ENCODER_PRESENT, SLIP_STALL = 1 << 8, 1 << 6


@pytest.fixture(scope="module")
def ioc(tmp_path_factory):
    from conftest import start_metrixs_ioc
    proc = start_metrixs_ioc(tmp_path_factory.mktemp("motors"), TRUTH, extra=("--motors", "realistic"))
    yield proc
    proc.stop()


def _pv(ioc, name):
    return motor_pv(METRIXS[name], ioc.prefix)


def test_a_realistic_axis_arrives_within_its_deadband_from_either_side(ioc, ca):
    rec = _pv(ioc, PLAIN)
    mres, rdbd, bdst = (ca.get(f"{rec}.{f}") for f in ("MRES", "RDBD", "BDST"))
    assert rdbd == pytest.approx(10 * mres) and bdst == pytest.approx(400 * mres)
    assert ca.get(f"{rec}.UEIP", as_string=True) == "Yes" and ca.get(f"{rec}.MSTA") & ENCODER_PRESENT
    start = ca.get(rec + ".VAL")
    readbacks = []
    for step in (+2000, -2000, -500, +500):  # reversals: the backlash comes out by the final approach
        target = ca.get(rec + ".VAL") + step * mres
        ca.put(rec, target)
        rbv = ca.get(rec + ".RBV")
        assert abs(rbv - target) <= rdbd * (1 + 1e-9) and ca.get(rec + ".MISS") == 0
        readbacks.append(rbv - target)
    assert np.std(readbacks) > 0  # an encoder reads with noise, a step count would not
    ca.put(rec, start)


def test_a_step_scale_error_is_corrected_by_retries(ioc, ca):
    rec = _pv(ioc, SCALED)
    p = METRIXS[SCALED]
    target = ca.get(rec + ".VAL") + 0.1 * p.span
    ca.put(rec, target)
    assert ca.get(rec + ".RCNT") >= 1 and ca.get(rec + ".MISS") == 0  # 2 % of the move is far beyond RDBD
    assert abs(ca.get(rec + ".RBV") - target) <= ca.get(rec + ".RDBD") * (1 + 1e-9)


def test_a_stalled_load_completes_the_put_and_says_so(ioc, ca):
    rec = _pv(ioc, STALLED)
    before = ca.get(rec + ".RBV")
    target = before + 0.05 * METRIXS[STALLED].span
    ca.put(rec, target, timeout=60)  # put-completion returns: the record ran out of retries
    assert ca.get(rec + ".MISS") == 1 and ca.get(rec + ".MSTA") & SLIP_STALL
    assert ca.get(rec + ".RCNT") == ca.get(rec + ".RTRY")
    assert abs(ca.get(rec + ".RBV") - before) <= ca.get(rec + ".RDBD")  # the load never moved
    ca.put(rec, before, timeout=60)


def test_the_plans_take_frames_with_realistic_motors_and_refuse_a_stalled_one(ioc):
    from bluesky import RunEngine
    from ophyd_async.core import init_devices

    from bluesky_offsets.epics.devices import FocusChamber, MetrixsBeamline
    from plans import MotionError, measure_configurations

    RE = RunEngine({}, call_returns_result=True)
    docs = []
    RE.subscribe(lambda name, doc: docs.append((name, doc)))
    with init_devices():
        beamline = MetrixsBeamline(ioc.prefix, name="metrixs")
        chamber = FocusChamber(ioc.prefix + "chamber:", name="chamber")
    base = default_start()
    cfgs = np.repeat(base[None], 3, 0)
    for k, name in enumerate((PLAIN, SCALED, "ExitSlit.translationZerror")):
        cfgs[k, METRIXS.index(name)] += 0.02 * METRIXS[name].span
    m = RE(measure_configurations(cfgs, beamline, chamber)).plan_result
    np.testing.assert_allclose(m.configurations, cfgs)  # the fits use what was commanded
    assert sum(name == "event" for name, _ in docs) == 3

    docs.clear()
    bad = base.copy()
    bad[METRIXS.index(STALLED)] += 0.02 * METRIXS[STALLED].span
    with pytest.raises(MotionError) as err:
        RE(measure_configurations([bad], beamline, chamber))
    assert STALLED in str(err.value) and "\n" not in str(err.value)
    assert not any(name == "event" for name, _ in docs)  # no frame from a motor that did not arrive


def test_a_frame_at_a_limit_is_taken_a_margin_inside_and_the_motor_moves_on(ioc):
    """A target at a soft limit, rounded to the steps or read by a noisy encoder, would leave a
    readback beyond it, and ophyd-async's Motor refuses every move from there."""
    from bluesky import RunEngine
    from ophyd_async.core import init_devices

    from bluesky_offsets.epics.devices import FocusChamber, MetrixsBeamline
    from plans import measure_configurations

    RE = RunEngine({}, call_returns_result=True)
    with init_devices():
        beamline = MetrixsBeamline(ioc.prefix, name="metrixs")
        chamber = FocusChamber(ioc.prefix + "chamber:", name="chamber")
    j = METRIXS.index(PLAIN)
    edge = default_start()
    edge[j] = METRIXS[PLAIN].limits[1]
    m = RE(measure_configurations([edge, default_start()], beamline, chamber)).plan_result
    assert edge[j] - 1e-3 * METRIXS.span[j] < m.configurations[0, j] < edge[j]  # recorded as taken
    np.testing.assert_array_equal(np.delete(m.configurations[0], j), np.delete(edge, j))
    assert m.configurations[1, j] == default_start()[j]  # and it moved back from there
