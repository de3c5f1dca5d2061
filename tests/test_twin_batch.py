"""Batches on Dask: input order, seeds, failures reported with their parameters."""

import os
import sys

import cloudpickle
import numpy as np
import pytest

from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.physics.twin import RayxEngine, TraceEngine, TraceFailed, Twin

CRASH_MARK = 0.123  # source x offset that makes the engine below kill its worker


class CrashingEngine(RayxEngine):
    """The real RAYX engine, plus a hard process crash for one marked configuration
    (stands in for RAYX aborting the process on input it cannot handle)."""

    def trace(self, request, n_rays, keep_rays=False):
        if request.values[0] == CRASH_MARK:
            os._exit(3)
        return super().trace(request, n_rays, keep_rays)


cloudpickle.register_pickle_by_value(sys.modules[__name__])


def _configs(n):
    v = np.tile(METRIXS.reference, (n, 1))
    v[:, METRIXS.index("E2.rotationXerror")] = np.linspace(-0.4, 0.4, n)
    return v


@pytest.fixture(scope="module")
def dask_twin():
    twin = Twin(CrashingEngine(), n_rays=2000, n_workers=2)
    yield twin
    twin.close()


def test_engine_protocol():
    assert isinstance(RayxEngine(), TraceEngine)


def test_batch_in_input_order_and_matches_inline(dask_twin):
    values = _configs(9)
    res = dask_twin.trace_batch(values, seed=100, chunk_size=2, progress=False)
    assert res.ok.all() and len(res) == 9
    centroids = (res.hist_y * Twin().hist.centers_y).sum(1) / res.hist_y.sum(1)
    assert np.all(np.diff(centroids) < 0)  # E2 pitch up -> beam down, in input order
    inline = Twin(n_rays=2000, scheduler="inline").trace_batch(values, seed=100, progress=False)
    np.testing.assert_array_equal(inline.hist_x, res.hist_x)
    np.testing.assert_array_equal(inline.hist_y, res.hist_y)


def test_failures_are_reported_with_parameters(dask_twin, caplog):
    values = _configs(6)
    values[2, METRIXS.index("E1.shortHalfAxisB")] = -1.0          # refused before RAYX
    values[4, 0] = CRASH_MARK                                    # kills its worker process
    res = dask_twin.trace_batch(values, chunk_size=3, progress=False)
    assert list(np.flatnonzero(~res.ok)) == [2, 4]
    (i2, v2, e2), (i4, v4, e4) = res.failures
    assert "E1.shortHalfAxisB" in e2 and v2[METRIXS.index("E1.shortHalfAxisB")] == -1.0
    assert "worker" in e4.lower() and v4[0] == CRASH_MARK
    assert np.isnan(res.hist_x[2]).all() and np.isfinite(res.hist_x[[0, 1, 3, 5]]).all()
    assert "simulation 4 failed" in caplog.text
    with pytest.raises(TraceFailed, match="simulation 2 failed"):
        dask_twin.trace_batch(values[:3], progress=False, raise_on_error=True)


def test_bad_batch_input_is_refused_before_any_work():
    twin = Twin(scheduler="inline")
    with pytest.raises(ValueError, match="34 parameters"):
        twin.trace_batch(np.zeros((3, 30)))
    bad = _configs(2)
    bad[1, 5] = np.nan
    with pytest.raises(ValueError, match="ASBL.totalHeight"):
        twin.trace_batch(bad)
    with pytest.raises(ValueError, match="3 seeds for 2"):
        twin.trace_batch(_configs(2), seed=[1, 2, 3])


def test_with_hist_shares_the_tracer_and_bins_anew():
    from bluesky_offsets.physics.twin import CAMERA, HistogramSpec
    twin = Twin(scheduler="inline", n_rays=2000)
    fine = twin.with_hist(CAMERA)
    assert twin.with_hist(HistogramSpec()) is twin and fine.hist == CAMERA and twin.hist == HistogramSpec()
    a = twin.trace(METRIXS.reference, seed=4)
    b = fine.trace(METRIXS.reference, seed=4)
    np.testing.assert_allclose(CAMERA.rebin(b.hist_x, b.hist_y, twin.hist)[0], a.hist_x, atol=1e-12)
    fine.close()  # a borrowed twin leaves its parent usable
    assert twin.trace(METRIXS.reference, seed=4).n_hits == a.n_hits
