"""The designed measurement as Bluesky plans, against the simulated IOC: frames chosen batch by
batch with the chamber's stage moved, the ``design`` stream, the budget, validation frames."""

from __future__ import annotations

import numpy as np
import pytest
from bluesky import RunEngine

from bluesky_offsets.design import DesignOptions
from bluesky_offsets.epics.devices import FocusChamber, MetrixsBeamline
from bluesky_offsets.model.state import ModelState
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.twin import Twin
from conftest import start_metrixs_ioc
from plans.design import Validation, measure_designed, measure_validation
from plans.diagnose import load_results

# small offsets (the beam is on the screen where the motors start) and the chamber 4 mm downstream
TRUTH = {"offsets": {**{n: 0.02 * (-1) ** i for i, n in enumerate(METRIXS.names)},
                     "M1_Cylinder.translationXerror": 0.002, "M1_Cylinder.rotationZerror": 0.01},
         "overrides": {"ImagePlane": {"translationZerror": 4.0}}}
OPTIONS = DesignOptions(frames=12, batch=4, candidates=24, rays=400, fit_rays=600, validation=2, seed=3)


@pytest.fixture(scope="module")
def RE():
    return RunEngine({}, call_returns_result=True)


@pytest.fixture(scope="module")
def ioc(tmp_path_factory):
    ioc = start_metrixs_ioc(tmp_path_factory.mktemp("design_ioc"), TRUTH, extra=("--rays", "3000"))
    yield ioc
    ioc.stop()


@pytest.fixture(scope="module")
def devices(RE, ioc):
    from ophyd_async.core import init_devices
    p = ioc.prefix
    with init_devices():
        beamline = MetrixsBeamline(p, name="metrixs", stage={a: f"{p}chamber:{a}" for a in "xyz"})
        chamber = FocusChamber(p + "chamber:", name="chamber")
    return beamline, chamber


@pytest.fixture(scope="module")
def designed(RE, devices, run_store):
    token = run_store.subscribe(RE)
    try:
        return RE(measure_designed(*devices, options=OPTIONS, show=False)).plan_result
    finally:
        RE.unsubscribe(token)


def test_the_designed_frames_stay_within_the_budget_and_move_the_screen(designed, run_store):
    d = designed
    assert d.frames <= OPTIONS.frames and d.measurement.n >= 4 and d.beam.bright
    m = run_store.load_measurement(d.uid)
    np.testing.assert_allclose(m.configurations, d.measurement.configurations)
    np.testing.assert_allclose(m.screen, d.measurement.screen)
    assert np.any(m.screen[:, 2] != 0)  # the screen moved along the beam
    lo = np.array([p.limits[0] for p in METRIXS])
    hi = np.array([p.limits[1] for p in METRIXS])
    assert np.all(m.configurations >= lo - 1e-9) and np.all(m.configurations <= hi + 1e-9)
    rows = load_results(run_store, d.uid)["design"]
    assert len(rows) == len(d.steps) >= 2
    for r in rows:
        assert r["criterion"] == "D" and r["criterion_after"] >= r["criterion_before"]
        assert 0 < r["frames"] <= 1.5 * OPTIONS.batch and r["allowed"] <= r["candidates"] == OPTIONS.candidates
        assert len(r["gains"]) == r["frames"] and np.all(np.asarray(r["gains"]) >= 0)
        assert r["predicted_sigma"].shape == (len(METRIXS),)
    assert d.offsets.shape == (len(METRIXS),) and np.all(np.abs(d.offsets) <= 0.2)


def test_the_beam_search_s_lit_frames_join_the_fitted_ones(designed, run_store):
    """The beam search keeps its frames, run by run as stored; its lit ones are fitted beside the designed."""
    from plans import enough_rays
    from plans.search import lit_frames
    from plans.workflow import with_lit_beam_frames
    beam = designed.beam
    assert sum(r.n for r in beam.measurements) == beam.frames
    for r in beam.measurements:
        np.testing.assert_allclose(run_store.load_measurement(r.uid).hist_x, r.hist_x)
    lit = lit_frames(beam.measurements)
    assert lit is not None and lit.n >= 1 and enough_rays(lit.hist_x, lit.hist_y).all()  # it ended bright
    both = designed.measurement.joined(lit)
    assert both.n == designed.measurement.n + lit.n and both.uid == designed.uid
    np.testing.assert_array_equal(both.screen[designed.measurement.n:], 0)  # the search left the stage at 0
    back = with_lit_beam_frames(run_store, run_store.load_measurement(designed.uid))  # an analysis from the store
    np.testing.assert_allclose(back.configurations, both.configurations)
    np.testing.assert_allclose(back.hist_y, both.hist_y)


def test_validation_frames_lie_far_from_the_fitted_ones_and_judge_the_model(RE, devices, designed, run_store):
    twin = Twin(scheduler="inline", n_rays=3000)
    truth = ModelState(METRIXS.from_mapping(TRUTH["offsets"], base=np.zeros(len(METRIXS))),
                       {"chamber_z": {"z": 4.0}}, "truth")
    token = run_store.subscribe(RE)
    try:
        v = RE(measure_validation(*devices, truth, designed.measurement, twin, n=2, options=OPTIONS,
                                  show=False)).plan_result
        bare = RE(measure_validation(*devices, ModelState(), designed.measurement, twin, n=2, options=OPTIONS,
                                     show=False)).plan_result
    finally:
        RE.unsubscribe(token)
    assert isinstance(v, Validation) and v.measurement.n == 2
    assert v.passed and v.chi2_reduced < 1.6, v.summary()   # the truth passes ...
    assert not bare.passed and bare.chi2_reduced > 3, bare.summary()  # ... the bare twin does not
    res = load_results(run_store, v.uid)
    assert res["start"]["plan_name"] == "measure_validation" and res["start"]["measurement_uid"] == designed.uid
    assert res["misfit_total"][0]["chi2_reduced_total"] == pytest.approx(v.chi2_reduced)
    fitted = np.hstack([designed.measurement.configurations, designed.measurement.screen])
    for row in np.hstack([v.measurement.configurations, v.measurement.screen]):
        assert np.min(np.abs(fitted - row).sum(1)) > 0  # none of them a fitted setting
