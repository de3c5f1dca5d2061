"""Offset finder: problem definition, the four methods, budgets, bad input.

The forward model is a small MLP trained here on real RAYX twin traces near
the centre of the box (see ``_finder_model``); problems are drawn in that
region with offsets up to 0.01 (normalized) where the model is valid.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from _finder_model import CENTER, HALF_WIDTH, trained_model
from bluesky_offsets.offsets import finder as F
from bluesky_offsets.physics.parameters import METRIXS

pytestmark = pytest.mark.slow  # over a minute: scheduled first (conftest)

REGION = (CENTER - HALF_WIDTH, CENTER + HALF_WIDTH)
LIMIT = 0.01
SETTINGS = {"smart-walker": dict(candidates=128, step=LIMIT / 100 * 4),
            "monte-carlo": dict(candidates=128),
            "gradient": dict(starts=8, screen=128, lr=LIMIT / 10),
            "levenberg-marquardt": dict(starts=4, screen=128),
            "cmaes": dict(sigma0=LIMIT / 4, screen=128)}


@pytest.fixture(scope="module")
def model():
    return trained_model()


@pytest.fixture(scope="module")
def problem(model):
    return F.make_problem(model, seed=3, region=REGION, limit=LIMIT)


def test_problem_is_the_papers_and_reproducible(model, problem):
    again = F.make_problem(model, seed=3, region=REGION, limit=LIMIT)
    other = F.make_problem(model, seed=4, region=REGION, limit=LIMIT)
    np.testing.assert_array_equal(problem.configurations, again.configurations)
    np.testing.assert_array_equal(problem.true_offsets, again.true_offsets)
    assert not np.allclose(problem.true_offsets, other.true_offsets)
    assert problem.n == 16 and problem.source == "surrogate" and problem.noise_mse == 0.0
    assert np.all(np.abs(problem.true_offsets) <= LIMIT)
    # every configuration is bright enough (the paper's histogram-sum criterion) ...
    assert np.all(problem.observations.sum(axis=1) > F.PAPER_MIN_HIST_SUM)
    # ... and the observations are the model at the true (offset) configurations
    with torch.no_grad():
        pred = model(torch.as_tensor(problem.configurations + problem.true_offsets, dtype=torch.float32))
    np.testing.assert_allclose(problem.observations, pred.double().numpy(), rtol=1e-5, atol=1e-7)
    # fixed-but-unknown parameters (radii, half-axes) are the same in every configuration
    fixed = ~METRIXS.motorized
    assert np.ptp(problem.configurations[:, fixed], axis=0).max() == 0
    assert np.ptp(problem.configurations[:, ~fixed], axis=0).min() > 0
    assert F.final_mse(problem, model, problem.true_offsets) < 1e-12


@pytest.mark.parametrize("method", list(F.METHODS))
def test_method_finds_offsets_within_budget(model, problem, method):
    budget = F.Budget(evaluations=3000)
    seen = []
    r = F.find_offsets(problem, model, method, budget, seed=1, progress=False, threads=1, callback=seen.append,
                       **SETTINGS[method])
    start = F.final_mse(problem, model, np.zeros(34))
    assert r.method == method and r.evaluations <= 3000
    assert r.evaluations >= 3000 - max(128, 14 * 8)  # used (nearly) all of it
    loss = np.asarray(r.history["loss"])
    assert np.all(np.diff(loss) <= 0), "the loss curve is the best so far"
    assert np.all(np.diff(r.history["evaluations"]) > 0) and np.all(np.diff(r.history["seconds"]) >= 0)
    assert math.isclose(r.loss, loss[-1]) and math.isclose(r.loss, F.final_mse(problem, model, r.offsets),
                                                           rel_tol=1e-4)
    assert np.all(np.abs(r.offsets) <= LIMIT + 1e-7)
    # Monte Carlo only has to beat "no offsets"; the others must do far better
    assert r.loss < (1.0 if method == "monte-carlo" else 0.2) * start, f"{method}: {r.loss:.3e} vs {start:.3e} with zero offsets"
    assert seen and seen[-1]["evaluations"] == r.evaluations and seen[-1]["loss"] == r.loss
    d = r.to_dict()
    assert d["method"] == method and len(d["history"]["loss"]) == len(loss)


def test_seeded_runs_repeat(model, problem):
    a = F.find_offsets(problem, model, "smart-walker", F.Budget(evaluations=1000), seed=7, progress=False, threads=1,
                       **SETTINGS["smart-walker"])
    b = F.find_offsets(problem, model, "smart-walker", F.Budget(evaluations=1000), seed=7, progress=False, threads=1,
                       **SETTINGS["smart-walker"])
    np.testing.assert_array_equal(a.offsets, b.offsets)
    assert a.history["loss"] == b.history["loss"]


def test_smart_walker_beats_monte_carlo_and_gradient_methods_beat_both(model, problem):
    budget = F.Budget(evaluations=4000)
    res = {m: F.find_offsets(problem, model, m, budget, seed=2, progress=False, threads=1, **SETTINGS[m])
           for m in ("smart-walker", "monte-carlo", "gradient", "levenberg-marquardt")}
    assert res["smart-walker"].loss < res["monte-carlo"].loss
    assert res["gradient"].loss < res["smart-walker"].loss
    # the least-squares structure pays: Levenberg-Marquardt recovers the offsets of a noise-free problem
    assert res["levenberg-marquardt"].loss < 1e-3 * res["smart-walker"].loss
    assert res["levenberg-marquardt"].parameter_rmse(problem.true_offsets) < 0.1 * LIMIT
    # the multi-start method reports its independent end points for the identifiability spread
    g = res["gradient"]
    assert g.solutions.shape == (8, 34) and g.solution_losses.shape == (8,)


def test_time_budget_is_respected(model, problem):
    r = F.find_offsets(problem, model, "monte-carlo", F.Budget(seconds=0.5), seed=0, progress=False, threads=1,
                       candidates=64)
    assert r.seconds < 0.5 + 1.0
    assert r.history["seconds"][-1] >= 0.5 or r.evaluations > 0


def test_twin_observations_carry_noise(model):
    from bluesky_offsets.physics.twin import Twin
    twin = Twin(scheduler="inline")
    p = F.make_problem(model, seed=3, region=REGION, limit=LIMIT, observe="twin", twin=twin, n_rays=2000)
    ref = F.make_problem(model, seed=3, region=REGION, limit=LIMIT)
    np.testing.assert_array_equal(p.configurations, ref.configurations)  # the same problem, observed by RAYX
    assert p.source == "twin" and p.n_rays == 2000 and p.noise_mse > 0
    assert p.metadata["surrogate_vs_twin_mse"] > 0
    r = F.find_offsets(p, model, "gradient", F.Budget(evaluations=1500), seed=0, progress=False, threads=1,
                       **SETTINGS["gradient"])
    assert r.loss < F.final_mse(p, model, np.zeros(34))


def test_problem_from_measurements_round_trip(problem):
    phys = METRIXS.denormalize(problem.configurations)
    p = F.problem_from_measurements(phys, problem.observations.reshape(-1, 2, 50), n_rays=100_000)
    np.testing.assert_allclose(p.configurations, problem.configurations, atol=1e-12)
    assert p.source == "measurement" and p.true_offsets is None and p.noise_mse > 0


def test_bad_input_is_refused_clearly(model, problem):
    obs = problem.observations.copy()
    obs[2, 7] = np.nan
    with pytest.raises(F.FinderError, match="row 2, bin 7"):
        F.OffsetProblem(problem.configurations, obs)
    with pytest.raises(F.FinderError, match=r"\(n, 100\)"):
        F.OffsetProblem(problem.configurations, obs[:, :50])
    with pytest.raises(F.FinderError, match="16 configurations but 15"):
        F.OffsetProblem(problem.configurations, problem.observations[:15])
    with pytest.raises(F.FinderError, match="unknown method 'annealing'"):
        F.find_offsets(problem, model, "annealing", F.Budget(evaluations=10))
    with pytest.raises(F.FinderError, match="needs evaluations and/or seconds"):
        F.Budget()
    with pytest.raises(F.FinderError, match="smart-walker"):
        F.find_offsets(problem, model, "smart-walker", F.Budget(evaluations=10), nonsense=1)
    with pytest.raises(F.FinderError, match="needs a Twin"):
        F.make_problem(model, observe="twin")


def test_the_shipped_surrogate_is_a_forward_model():
    """The shipped checkpoint through the finder's adapter equals the surrogate's own predict()."""
    from bluesky_offsets.surrogate.network import load
    fm = F.load_forward_model()
    assert isinstance(fm, F.ForwardModel) and fm.test_mse > 0
    rng = np.random.default_rng(0)
    # bright inputs (most whole-box draws are dark, where any two models agree): the reference
    # (the RML's, outside the box in its slit sizes and E1/E2 rotation Z) moved into the box, the
    # source's own offsets among them: a checkpoint trained with the mirrored source frame sees
    # them reflected
    x = np.clip(METRIXS.normalize(METRIXS.reference) + rng.uniform(-0.02, 0.02, (5, 3, 34)), 0.0, 1.0)
    ours = fm(torch.as_tensor(x, dtype=torch.float32)).numpy()
    theirs = load().predict(METRIXS.denormalize(x))
    assert theirs.sum(-1).min() > 0.01
    np.testing.assert_allclose(ours, theirs, rtol=1e-4, atol=1e-6)
    assert ours.shape == (5, 3, 100) and (ours >= 0).all()
    with pytest.raises(F.FinderError, match="does not exist"):
        F.load_forward_model("/nonexistent/surrogate.pt")


def test_find_command_end_to_end(tmp_path, capsys):
    """``bluesky-offsets find`` on the shipped surrogate, tiny budgets: summary, JSON, plots."""
    import json

    from bluesky_offsets.commands.cli import main
    out = tmp_path / "find"
    rc = main(["find", "--runs", "2", "--candidates", "32", "--iterations", "4", "--threads", "1",
               "--methods", "smart-walker,monte-carlo,levenberg-marquardt", "--no-progress", "--quiet",
               "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "Monte Carlo / smart walker final MSE" in text and "identifiability" in text
    res = json.loads((out / "results.json").read_text())
    assert set(res["summary"]) == {"smart-walker", "monte-carlo", "levenberg-marquardt"}
    assert res["budgets"]["smart-walker"]["evaluations"] == 32 * 5
    assert res["budgets"]["levenberg-marquardt"]["evaluations"] == 16  # a tenth
    assert len(res["results"]["monte-carlo"]) == 2 and res["seeds"] == [0, 1]
    for f in ("curves.png", "identifiability.png", "identifiability.txt"):
        assert (out / f).stat().st_size > 0
    assert main(["find", "--methods", "simplex", "--out", str(out)]) == 2
    assert "unknown method" in capsys.readouterr().err


def test_sinkhorn_and_twin_check(problem, tmp_path):
    """POT's debiased Sinkhorn on ray clouds; the twin re-simulation at true vs. found offsets; Fig. 6."""
    from bluesky_offsets.offsets import evaluate as E
    from bluesky_offsets.physics.twin import Twin
    rng = np.random.default_rng(0)
    a = rng.normal(0, [0.07, 0.016], (400, 2))
    b = rng.normal(0, [0.07, 0.016], (400, 2))
    assert E.sinkhorn(a, b) < E.sinkhorn(a, b + [0.3, 0.0])
    assert math.isnan(E.sinkhorn(a, np.empty((0, 2))))
    sub = F.OffsetProblem(problem.configurations[:3], problem.observations[:3], problem.true_offsets,
                          "surrogate", LIMIT)
    twin = Twin(scheduler="inline")
    exact = E.twin_check(twin, sub, sub.true_offsets, n_rays=1000, sinkhorn_points=300)
    off = E.twin_check(twin, sub, np.clip(sub.true_offsets + 0.008, -LIMIT, LIMIT), n_rays=1000,
                       sinkhorn_points=300)
    assert exact["mse_repeat"] > 0 and len(exact["per_configuration"]["sinkhorn_compensated"]) == 3
    assert off["mse_compensated"] > exact["mse_compensated"]
    path = E.plot_footprints(twin, sub, sub.true_offsets, tmp_path / "fp.png", n_rays=1000)
    assert path.stat().st_size > 10_000


def test_smart_walker_selection(model, problem):
    """"comma" walks from the best of the last candidates, "plus" from the best so far."""
    # two candidates per step: both are often worse than the centre, which only "comma" follows
    kw = dict(progress=False, threads=1, candidates=2, step=SETTINGS["smart-walker"]["step"])
    plus = F.find_offsets(problem, model, "smart-walker", F.Budget(evaluations=500), seed=7, **kw)
    comma = F.find_offsets(problem, model, "smart-walker", F.Budget(evaluations=500), seed=7, selection="comma", **kw)
    assert comma.evaluations == plus.evaluations == 500
    assert not np.array_equal(comma.offsets, plus.offsets)
    assert comma.loss < F.final_mse(problem, model, np.zeros(34))
    with pytest.raises(F.FinderError, match="selection must be 'plus' or 'comma'"):
        F.find_offsets(problem, model, "smart-walker", F.Budget(evaluations=10), selection="best")


BASELINES = {"powell": ({}, 3000), "annealing": ({}, 3000),
             "genetic": (dict(candidates=100, mutation_scale=LIMIT / 4), 3000),
             "blop": (dict(sobol=8, batch=4), 16)}


@pytest.mark.parametrize("name", list(BASELINES))
def test_the_authors_baselines_run_through_their_libraries_under_the_finders_budget(model, problem, name):
    """evotorch's GA, SciPy's Powell and dual annealing, blop's Ax optimizer: each scored, counted
    and stopped by the finder's budget, its loss curve the best so far, its result inside the box."""
    from bluesky_offsets.offsets import baselines as B
    if name == "genetic":
        pytest.importorskip("evotorch", reason="the [harness] extra")
    settings, evaluations = BASELINES[name]
    r = F.find_offsets(problem, model, B.algorithm(name, **settings), F.Budget(evaluations=evaluations), seed=1,
                       progress=False, threads=1)
    assert r.method == name and evaluations - 200 <= r.evaluations <= evaluations
    loss = np.asarray(r.history["loss"])
    assert np.all(np.diff(loss) <= 0) and math.isclose(r.loss, F.final_mse(problem, model, r.offsets), rel_tol=1e-4)
    assert np.all(np.abs(r.offsets) <= LIMIT + 1e-7)
    assert r.loss < F.final_mse(problem, model, np.zeros(34))
    with pytest.raises(F.FinderError, match="unknown method"):
        B.algorithm("simplex")
