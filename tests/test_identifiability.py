"""Identifiability: blind parameters are flagged, uncertainties shrink with more configurations."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from _finder_model import CENTER, HALF_WIDTH, trained_model
from bluesky_offsets.offsets import finder as F
from bluesky_offsets.offsets import identifiability as I
from bluesky_offsets.physics.parameters import METRIXS, Parameter, ParameterTable

REGION = (CENTER - HALF_WIDTH, CENTER + HALF_WIDTH)
LIMIT = 0.01

# a 35th parameter the beamline's histograms cannot see (e.g. a motor wired to nothing)
BLIND = Parameter("Spare.translationXerror", "Spare", "translationXerror", "mm", -1.0, 1.0, True, 0.0,
                  "spare.tx", "a motor the focus chamber cannot see")
TABLE35 = ParameterTable(METRIXS.parameters + (BLIND,), name="metrixs+spare")


class WithBlindInput(torch.nn.Module):
    """The twin-trained model with one extra input it ignores: the histograms are blind to it."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, x):
        return self.model(x[..., :34])


@pytest.fixture(scope="module")
def model():
    return trained_model()


@pytest.fixture(scope="module")
def solved(model):
    p = F.make_problem(model, seed=5, region=REGION, limit=LIMIT)
    r = F.find_offsets(p, model, "gradient", F.Budget(evaluations=3000), seed=0, progress=False, threads=1,
                       starts=8, screen=128, lr=LIMIT / 10)
    return p, r


def test_a_parameter_without_effect_is_flagged_undetermined(model, solved):
    p, r = solved
    m35 = WithBlindInput(model)
    rng = np.random.default_rng(0)
    c35 = np.column_stack([p.configurations, rng.uniform(*REGION, p.n)])
    p35 = F.OffsetProblem(c35, p.observations, np.append(p.true_offsets, 0.004), "surrogate", LIMIT,
                          table=TABLE35)
    off35 = np.append(r.offsets, -0.003)
    rep = I.analyze(p35, m35, off35)
    i = TABLE35.index(BLIND.name)
    assert rep.status[i] == "undetermined"
    assert rep.ratio[i] == pytest.approx(1.0, abs=1e-6)  # the data add nothing to the box prior
    assert np.isinf(rep.sigma_conditional[i])
    assert BLIND.name in rep.undetermined()
    # the blind direction is the least determined one, made of that parameter alone
    d0 = rep.directions(1)[0]
    assert d0["components"][0][0] == BLIND.name and abs(d0["components"][0][1]) == pytest.approx(1.0)
    # it never shows up as a compensating partner
    assert all(BLIND.name not in (a, b) for a, b, _ in rep.pairs(10))
    # the real parameters keep the uncertainties they have without the spare input
    rep34 = I.analyze(p, model, r.offsets)
    np.testing.assert_allclose(rep.sigma[:34], rep34.sigma, rtol=1e-4)
    assert "undetermined" in rep.table() and BLIND.name in rep.table()


def test_uncertainties_shrink_with_more_configurations(model, solved):
    p, r = solved
    curve = I.configuration_curve(p, model, r.offsets, counts=[1, 4, 16])
    sig = curve["sigma"]
    assert sig.shape == (3, 34)
    assert np.all(sig[1] <= sig[0] * (1 + 1e-6)) and np.all(sig[2] <= sig[1] * (1 + 1e-6))
    assert curve["median_sigma"][2] < 0.5 * curve["median_sigma"][0]
    # one configuration (100 bins) cannot pin down 34 coupled offsets: most stay undetermined
    assert curve["n_undetermined"][0] > curve["n_undetermined"][2]


def test_counting_noise_and_model_error_widen_uncertainties(model, solved):
    p, r = solved
    a = I.analyze(p, model, r.offsets, n_rays=100_000)
    b = I.analyze(p, model, r.offsets, n_rays=1_000)
    c = I.analyze(p, model, r.offsets, n_rays=100_000, model_mse=1e-6)
    assert np.all(b.sigma >= a.sigma * (1 - 1e-9)) and np.median(b.sigma) > np.median(a.sigma)
    assert np.median(c.sigma) > np.median(a.sigma)
    assert np.all(a.sigma <= a.prior_sigma * (1 + 1e-9))


def test_spread_of_multistart_solutions_and_report(model, solved, tmp_path):
    p, r = solved
    rep = I.analyze(p, model, r.offsets, solutions=r.solutions, solution_losses=r.solution_losses)
    d = rep.to_dict()
    assert len(d["sigma"]) == 34 and set(d["status"]) <= {"determined", "weak", "undetermined"}
    assert d["summary"]["n_configurations"] == p.n
    if rep.spread is not None:
        assert rep.spread.shape == (34,) and rep.n_solutions >= 2
    pairs = rep.pairs(3)
    assert len(pairs) == 3 and all(-1 <= c <= 1 for _, _, c in pairs)
    curve = I.configuration_curve(p, model, r.offsets, counts=[2, 8, 16])
    out = I.plot_identifiability(rep, tmp_path / "ident.png", curve, p.true_offsets)
    assert out.stat().st_size > 10_000
