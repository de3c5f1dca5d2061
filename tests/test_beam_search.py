"""Finding the beam from a dark start: the search on the model, and the plan on the simulated IOC."""

from __future__ import annotations

import numpy as np
import pytest

from bluesky_offsets.model.diagnosis import open_settings
from bluesky_offsets.offsets.beam_search import acceptance, intensity, schedule, search
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.engine import TorchEngine
from bluesky_offsets.physics.twin import Twin
from plans import HIGH_RAY_THRESHOLD
from sim_iocs.truth import default_start

OPEN_SLITS = tuple(open_settings())  # the slit openings the search sets (never scanned)

pytestmark = pytest.mark.slow  # over a minute: scheduled first (conftest)

# M1 moved sideways out of the beam, plus a few other offsets: the start is dark
DARK = {"M1_Cylinder.translationXerror": 0.06, "E1.rotationXerror": 0.02, "SphericalGrating.rotationZerror": -0.03,
        "ASBL.translationYerror": 0.02}


@pytest.fixture(scope="module")
def twin():
    return Twin(TorchEngine())


@pytest.fixture(scope="module")
def widths(twin):
    return acceptance(twin, default_start(), open_slits=True), acceptance(twin, default_start(), open_slits=False)


def _drive(gen, measure):
    cfgs = next(gen)
    try:
        while True:
            cfgs = gen.send(measure(cfgs))
    except StopIteration as done:
        return done.value


def test_the_model_says_which_motors_lose_the_beam(widths):
    wo, wc = widths
    j = METRIXS.index("M1_Cylinder.translationXerror")
    assert wc[j] < wo[j] < 0.05  # M1 sideways loses the beam within a few per cent of its range
    assert np.isnan(wo[METRIXS.index("E2.longHalfAxisA")])  # fixed parameters are not motors
    steps = schedule(wc, 0.05)
    assert "M1_Cylinder.translationXerror" in [s.name for s in steps]
    for s in steps:  # odd, symmetric, the current position among them, never a slit opening
        assert len(s.positions) % 2 == 1 and s.positions[len(s.positions) // 2] == 0.0 and s.name not in OPEN_SLITS


@pytest.mark.parametrize("seed", [0, 1])
def test_search_brings_the_beam_back_from_a_dark_start(twin, widths, seed):
    off = np.zeros(len(METRIXS))
    for n, v in DARK.items():
        off[METRIXS.index(n)] = v
    off += np.random.default_rng(seed).uniform(-0.02, 0.02, len(METRIXS))
    phys = METRIXS.offsets_to_physical(off)
    seen = []

    def measure(cfgs):
        r = twin.trace_batch(np.asarray(cfgs) + phys, n_rays=2000, seed=11, progress=False)
        seen.append(len(cfgs))
        return intensity(r.hist_x, r.hist_y)

    start = default_start()
    assert measure(start[None])[0] < 0.01  # dark indeed
    res = _drive(search(start, *widths, threshold=HIGH_RAY_THRESHOLD, fraction=0.1, max_frames=80), measure)
    assert res.bright and res.intensity > HIGH_RAY_THRESHOLD, res.log
    assert res.frames == sum(seen[1:]) <= 80
    # the slits are as the operator had them
    for n in OPEN_SLITS:
        assert res.configuration[METRIXS.index(n)] == start[METRIXS.index(n)]


def test_search_respects_its_frame_budget(twin, widths):
    j = METRIXS.index("M1_Cylinder.translationXerror")
    phys = np.zeros(len(METRIXS))
    phys[j] = 0.5 * METRIXS.span[j]  # far out of the beam: the budget ends the search

    def measure(cfgs):
        r = twin.trace_batch(np.asarray(cfgs) + phys, n_rays=500, seed=1, progress=False)
        return intensity(r.hist_x, r.hist_y)

    res = _drive(search(default_start(), *widths, threshold=HIGH_RAY_THRESHOLD, fraction=0.1, max_frames=6), measure)
    assert res.frames <= 6 and not res.bright and any("budget" in line for line in res.log)


def test_find_beam_plan_on_the_simulated_ioc(tmp_path):
    """The plan drives the IOC (RAYX behind it) from a dark start to a bright configuration; every
    scan is a run, and the motors end where the beam is."""
    from bluesky import RunEngine
    from ophyd_async.core import init_devices

    from bluesky_offsets.epics.devices import FocusChamber, MetrixsBeamline
    from conftest import start_metrixs_ioc
    from plans import current_configuration, find_beam, measure_configurations

    ioc = start_metrixs_ioc(tmp_path, {"offsets": DARK}, extra=("--rays", 2000, "--move-time", 0.05))
    try:
        RE = RunEngine({}, call_returns_result=True)
        with init_devices():
            beamline = MetrixsBeamline(ioc.prefix, name="metrixs")
            chamber = FocusChamber(ioc.prefix + "chamber:", name="chamber")
        first = RE(measure_configurations([default_start()], beamline, chamber)).plan_result
        assert intensity(first.hist_x, first.hist_y)[0] < 0.01
        out = RE(find_beam(beamline, chamber, fraction=0.1, max_frames=60))
        res = out.plan_result
        assert res.bright and res.frames <= 60, res.log
        assert len(res.uids) == len(out.run_start_uids) and all(u in out.run_start_uids for u in res.uids)
        here = RE(current_configuration(beamline)).plan_result
        np.testing.assert_allclose(here[METRIXS.motorized], res.configuration[METRIXS.motorized], atol=1e-3)
        # the search may stop just above the threshold: judge the mean of three fresh frames, not one
        again = RE(measure_configurations([here] * 3, beamline, chamber)).plan_result
        assert intensity(again.hist_x, again.hist_y).mean() > HIGH_RAY_THRESHOLD, res.log
    finally:
        ioc.stop()
