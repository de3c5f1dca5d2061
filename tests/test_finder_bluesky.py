"""The finder in a Bluesky run: live progress events, offsets in the run, apply_offsets on the model."""

from __future__ import annotations

import numpy as np
import pytest

from _finder_model import CENTER, HALF_WIDTH, trained_model
from bluesky_offsets.offsets import calibration as C
from bluesky_offsets.offsets import finder as F
from bluesky_offsets.physics.parameters import METRIXS

REGION = (CENTER - HALF_WIDTH, CENTER + HALF_WIDTH)
LIMIT = 0.01


@pytest.fixture(scope="module")
def model():
    return trained_model()


@pytest.fixture(scope="module")
def problem(model):
    return F.make_problem(model, seed=11, region=REGION, limit=LIMIT)


def _finder(model, **kw):
    return C.OffsetFinder(model=model, method="gradient", budget=F.Budget(evaluations=2500),
                          settings=dict(starts=8, screen=128, lr=LIMIT / 10), limit=LIMIT, **kw)


def test_find_offsets_streams_progress_and_emits_offsets(model, problem, tmp_path):
    """The one find_offsets plan with the OffsetFinder: its progress live as ``finder`` events (the
    LossPlot draws them), the result as one ``offsets`` event, the run linked to its measurement."""
    from bluesky import RunEngine

    from bluesky_offsets.model.measurement import Measurement
    from plans import find_offsets
    RE = RunEngine({}, call_returns_result=True)
    docs = []
    RE.subscribe(lambda name, doc: docs.append((name, doc)))
    plot = C.LossPlot(path=tmp_path / "loss.png")
    RE.subscribe(plot)
    h = problem.observations
    m = Measurement(METRIXS.denormalize(problem.configurations), h[:, :50], h[:, 50:], uid="measurement-123",
                    metadata={"n_rays": 100_000})
    res = RE(find_offsets(_finder(model), m, show=False)).plan_result
    cal = res.raw
    assert isinstance(cal, C.Calibration) and cal.offsets.shape == (34,) and len(cal.status) == 34
    start = next(d for n, d in docs if n == "start")
    assert start["plan_name"] == "find_offsets" and start["measurement_uid"] == "measurement-123"
    streams = {d["uid"]: d["name"] for n, d in docs if n == "descriptor"}
    finder_events = [d for n, d in docs if n == "event" and streams[d["descriptor"]] == "finder"]
    offsets_events = [d for n, d in docs if n == "event" and streams[d["descriptor"]] == "offsets"]
    assert len(finder_events) >= 1 and len(offsets_events) == 1
    losses = [e["data"]["loss"] for e in finder_events]
    assert losses == sorted(losses, reverse=True)
    ev = offsets_events[0]["data"]
    np.testing.assert_allclose(ev["offsets"], cal.offsets)
    np.testing.assert_allclose(ev["offsets_physical"], cal.offsets * METRIXS.span)
    np.testing.assert_allclose(ev["offsets_sigma"], cal.sigma)
    # one status convention: 2 determined, 1 weak, 0 undetermined
    code = {"determined": 2, "weak": 1, "undetermined": 0}
    assert list(ev["offsets_determined"]) == [code[s] for s in cal.status]
    assert len(ev["loss_curve_loss"]) == len(cal.history["loss"]) and ev["loss"] == cal.loss
    assert next(d for n, d in docs if n == "stop")["exit_status"] == "success"
    assert (tmp_path / "loss.png").stat().st_size > 5_000
    # the found offsets explain the measurement far better than none
    assert cal.loss < 0.2 * F.final_mse(problem, model, np.zeros(34))


def test_apply_offsets_updates_the_model_not_the_motors(model, problem, tmp_path):
    from bluesky import RunEngine
    RE = RunEngine({}, call_returns_result=True)
    docs = []
    RE.subscribe(lambda name, doc: docs.append((name, doc)))
    cm = C.CalibratedModel(forward_model=model)
    commanded = METRIXS.denormalize(problem.configurations)
    before = np.mean((cm.predict(commanded) - problem.observations) ** 2)
    cal = C.Calibration(offsets=problem.true_offsets, sigma=np.full(34, 0.001), status=["weak"] * 34,
                        loss=0.0, method="known", source_uid="abc")
    RE(C.apply_offsets(cm, cal))
    after = np.mean((cm.predict(commanded) - problem.observations) ** 2)
    assert after < 1e-12 < before
    np.testing.assert_allclose(cm.true_values(commanded[0]), commanded[0] + problem.true_offsets * METRIXS.span)
    ev = next(d for n, d in docs if n == "event")["data"]
    np.testing.assert_allclose(ev["offsets_applied"], problem.true_offsets)
    np.testing.assert_allclose(ev["offsets_before"], np.zeros(34))
    # round trip through a file, refused for another table version
    path = cal.save(tmp_path / "cal.json")
    again = C.Calibration.load(path)
    np.testing.assert_allclose(again.offsets, cal.offsets)
    assert "±" in again.report()
    bad = C.Calibration(**{**again.__dict__, "table_version": "000000000000"})
    with pytest.raises(F.FinderError, match="table"):
        cm.set_calibration(bad)


def test_twin_polish_lowers_the_twins_misfit(model):
    from bluesky_offsets.physics.twin import Twin
    twin = Twin(scheduler="inline")
    p = F.make_problem(model, seed=3, region=REGION, limit=LIMIT, observe="twin", twin=twin, n_rays=3000)
    r = F.find_offsets(p, model, "gradient", F.Budget(evaluations=1500), seed=0, progress=False, threads=1,
                       starts=8, screen=128, lr=LIMIT / 10)
    o, mses = C.twin_polish(p, twin, r.offsets, iterations=2, n_rays=3000)
    assert len(mses) == 2 and mses[1] < mses[0]
    assert np.all(np.abs(o) <= LIMIT)
