"""blop interop against the simulated IOC, each through a real blop agent (Ax) or blop's own plan.

The calibrated model here is the IOC's hidden truth itself: the tests judge the bridges (blop
drives our twin, then the motors; blop drives our finder through its protocol), not a fit.
The motors are moved back to where they stood: the session's IOC serves other tests.
"""

from __future__ import annotations

import bluesky.plan_stubs as bps
import numpy as np
import pytest
from blop.plans import optimize
from blop.protocols import OptimizationProblem, Optimizer
from bluesky import RunEngine

from bluesky_offsets.epics.devices import FocusChamber, MetrixsBeamline
from bluesky_offsets.model.state import CalibratedState, ModelState
from bluesky_offsets.offsets import finder as F
from bluesky_offsets.optimize import focus_from_profiles
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.twin import CAMERA
from plans.blop import Collector, FrameHistograms, OffsetOptimizer, focus_agent
from plans.motion import current_configuration, read_positions
from sim_iocs.truth import Truth

FOCUSING = ("E1.rotationXerror", "E2.rotationXerror")   # the x and the y focus


@pytest.fixture(scope="module")
def session(metrixs_ioc):
    from ophyd_async.core import init_devices
    RE = RunEngine({}, call_returns_result=True)
    with init_devices():
        beamline = MetrixsBeamline(metrixs_ioc.prefix, name="metrixs")
        chamber = FocusChamber(metrixs_ioc.prefix + "chamber:", name="chamber")
    return RE, beamline, chamber, Truth.from_mapping(metrixs_ioc.truth)


def _measured_focus(RE, chamber):
    def frame():
        yield from bps.trigger(chamber, wait=True)
        return (yield from bps.read(chamber))
    r = RE(frame()).plan_result
    px, py = (np.asarray(r[f"chamber-profile_{a}"]["value"], float) for a in "xy")
    return focus_from_profiles(px, py, CAMERA)


@pytest.fixture
def restore(session):
    RE, beamline, *_ = session
    motors = {n: beamline.parameter(n) for n in METRIXS.motorized_names}
    before = RE(read_positions(motors)).plan_result
    yield
    RE(bps.mv(*[x for n, m in motors.items() for x in (m, before[n])]))


def test_a_blop_agent_finds_the_focus_on_the_calibrated_twin_then_moves_the_beamline(session, restore):
    RE, beamline, chamber, truth = session
    reference = RE(current_configuration(beamline)).plan_result
    motors = {n: beamline.parameter(n) for n in FOCUSING}
    agent = focus_agent(CalibratedState(ModelState(truth.offsets)), motors, reference, span=0.12, rays=6000,
                        sobol=6, seed=2)
    start = agent.evaluation_function.reference_focus
    RE(agent.optimize(iterations=5, n_points=3))
    _, best, outcome = agent.get_best_points()[0]
    found = outcome["focus_um2"][0] if isinstance(outcome["focus_um2"], tuple) else outcome["focus_um2"]  # Ax: (mean, sem)
    assert found < 0.9 * start.rms_x * start.rms_y * 1e6   # the twin's focus shrank
    measured_before = _measured_focus(RE, chamber)
    RE(agent.navigate_to_best())
    here = RE(read_positions(motors)).plan_result
    for n, m in motors.items():   # the beamline stands where the agent chose
        assert here[n] == pytest.approx(best[m.name], abs=1e-6 * (METRIXS[n].high - METRIXS[n].low) + 1e-9)
    measured = _measured_focus(RE, chamber)
    area, area_before = measured.rms_x * measured.rms_y, measured_before.rms_x * measured_before.rms_y
    assert area < 0.9 * area_before, (measured, measured_before)   # and the real focus shrank with it
    assert area * 1e6 == pytest.approx(found, rel=0.25)


def test_the_offset_finder_runs_as_blop_s_optimizer_in_blop_s_own_plan(session, restore):
    RE, beamline, chamber, truth = session
    reference = RE(current_configuration(beamline)).plan_result
    names = ("E1.rotationXerror", "E2.rotationXerror", "M1_Cylinder.rotationXerror", "E2.translationYerror")
    motors = {n: beamline.parameter(n) for n in names}
    model = F.load_forward_model()
    finder = OffsetOptimizer(model, {n: m.name for n, m in motors.items()}, reference, span=0.03,
                             evaluations=6000, seed=4)
    assert isinstance(finder, Optimizer)   # blop's runtime-checkable protocol
    collector = Collector()
    token = RE.subscribe(collector)
    try:
        problem = OptimizationProblem(optimizer=finder, actuators=list(motors.values()), sensors=[chamber],
                                      evaluation_function=FrameHistograms(collector))
        RE(optimize(problem, iterations=2, n_points=4))
    finally:
        RE.unsubscribe(token)
    assert len(finder.histograms) == 8 and all(np.isfinite(h).all() for h in finder.histograms)
    assert [s["plan_name"] for s in collector.starts.values()].count("optimize") == 1  # blop's run, and its scans
    (_, offsets, outcome), = finder.get_best_points()
    measured = F.problem_from_measurements(np.array(finder.configurations), np.array(finder.histograms))
    assert outcome["mse"] < 0.5 * F.final_mse(measured, model, np.zeros(len(METRIXS)))
    assert list(offsets) == list(METRIXS.names) and max(map(abs, offsets.values())) <= 0.2 + 1e-6  # float32 model
