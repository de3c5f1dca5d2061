"""Which effect is missing — against the simulated IOC, through the main job (issue 6 acceptance).

Each scenario runs ``bluesky-offsets demo`` as a user does: the METRIXS IOC (twin backend,
127.0.0.1, a free port, seeded frame noise) with hidden offsets in all 34 parameters (±5 % of
each range, the demo's default draw) and a hidden effect (or none), then the calibration through
the IOC into the run store and compare → fit the offsets → diagnose (camera-resolution
profiles) → add the winner → refit → diagnose again, every step a run in the store.  The
chamber_z scenario is the README's main job on a smaller configuration, for the suite's time:
the designed measurement at 32 frames (the demo's default: 60), its fits at 1,000 model rays (2,000)
with one start a round drawn from their posterior (4), ranking chamber_z against the four effects the
full ranking puts next to it, read back from the store by uid.  The scenario with no hidden effect
measures as the bright design does (``--design bright``: 16 bright configurations and 4 of them again
with the slits open, the surrogate finder on the 16; its fits at 1,000 model rays, one posterior start
a round) and ranks all 15 candidates.  The main job at its own size is ``benchmarks/bench_demo.py``;
other effects (a thermal bump on M1 and the source's divergence among them) through the IOC, and the
whole grid over all 15, are ``benchmarks/bench_diagnosis_grid.py``; in-process,
``tests/test_diagnosis.py``.  The checks read ``summary.json``.

Beside the rest of the suite on two cores: the main job's scenario 10-26 minutes, the other 4-11.
``BLUESKY_OFFSETS_SKIP_ACCEPTANCE=1`` skips them for a quick local run.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bluesky_offsets.optimize import OptimizeOptions
from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.store import open_store
from plans.camera import gain_scale
from plans.diagnose import load_results

SKIP = os.environ.get("BLUESKY_OFFSETS_SKIP_ACCEPTANCE") == "1"
# a guard against a hang, not a time limit: beside the suite the main job's demo ran 1,440-1,540 s on 2 cores
pytestmark = [pytest.mark.slow, pytest.mark.timeout(3100),
              pytest.mark.skipif(SKIP, reason="BLUESKY_OFFSETS_SKIP_ACCEPTANCE=1")]

# (hidden effect as given to --effect, its name, the parameter checked, its hidden value)
SCENARIOS = {
    "chamber_z": ("chamber_z:z=20", "chamber_z", "z", 20.0),
}


def _demo(tmp_path: Path, effect: str, *extra: str) -> tuple[dict, subprocess.CompletedProcess]:
    exe = Path(sys.executable).parent / "bluesky-offsets"  # the console script, as a user runs it
    # the demo's fits one at a time ($OMP_NUM_THREADS, tests/conftest.py): the two workers' demos
    # overlap, so a second fit thread gains nothing
    cmd = [str(exe) if exe.exists() else shutil.which("bluesky-offsets"), "demo", "--effect", effect,
           "--out", str(tmp_path / "out"), "--store", str(tmp_path / "runs"), *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3000,
                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    print(proc.stdout[-2500:])
    return json.loads((tmp_path / "out" / "summary.json").read_text()), proc


# the main job (the camera, the designed measurement) on a smaller configuration, for the suite's time;
# the candidates: chamber_z and the four the full ranking puts next to it; one posterior start a round
# (the default 4 costs a quarter of the demo's CPU; tests/test_fit.py checks the starts themselves)
MAIN_JOB = ("--frames", "32", "--fit-rays", "1000", "--fit-starts", "1",
            "--candidates", "chamber_z,slope_error_e2,chamber_x,chamber_y,source_size")


class _Scenario:
    """One scenario's demo, run once for the tests of its class: pytest-xdist (``--dist
    loadscope``) runs a class on one worker, so the demos spread over the workers.  Only the
    main job's scenario ends with the beam optimization (``optimize``); the other stops after
    the diagnosis (``--no-optimize``), the step it tests."""

    optimize = False
    options: tuple[str, ...] = ("--design", "bright")

    @pytest.fixture(scope="class")
    @classmethod
    def demo(cls, scenario, tmp_path_factory) -> tuple[Path, dict, subprocess.CompletedProcess]:
        """(folder, summary, process)"""
        tmp = tmp_path_factory.mktemp(scenario)
        return (tmp, *_demo(tmp, SCENARIOS[scenario][0] if scenario in SCENARIOS else scenario, *cls.options,
                            *(() if cls.optimize else ("--no-optimize",))))


class _HiddenEffect(_Scenario):
    def test_hidden_effect_is_found_added_and_fitted(self, scenario, demo):
        effect, name, param, hidden = SCENARIOS[scenario]
        _, s, _ = demo
        assert s["rankings"][0][0] == name and s["verdict"].startswith(f"missing effect: {name}"), s["rankings"]
        fitted, sigma = s["fitted_effects"][name][param]
        assert fitted == pytest.approx(hidden, rel=0.25)
        assert abs(fitted - hidden) <= 3 * sigma, (fitted, sigma, hidden)
        before, after = s["history"][-2], s["history"][-1]
        assert after["chi2"] < before["chi2"]
        # within 1.5x its noise expectation: chi2 against its expected value (the dof) and the MSE
        assert after["chi2"] < 1.5 * after["dof"], f"chi2/dof {after['chi2_reduced']:.2f} after adding {name}"
        assert after["mse"] < 1.5 * after["expected_mse"]


def _scenario(name: str):
    """The class's scenario, as the tests' parameter (their ids keep it: ``...[chamber_z]``)."""
    return pytest.mark.parametrize("scenario", [name], scope="class")


@_scenario("chamber_z")
class TestChamberZ(_HiddenEffect):
    optimize = True
    options = MAIN_JOB

    def test_the_main_job_ends_with_a_smaller_focus_as_predicted(self, demo):
        """Issue 21: the smallest focus computed on the calibrated twin, moved to, measured; then,
        in the closed loop, the model refitted with those frames, the focus computed again, moved
        to and measured. Each run holds its frames with the prediction and loads back by uid."""
        tmp_path, s, proc = demo
        b = s["beam"]
        before, after, pred, best = b["before"], b["after"], b["predicted"], b["true_best"]
        for a in "xy":
            assert after[f"rms_{a}"] < 0.6 * before[f"rms_{a}"], (a, before, after)
            assert np.isfinite(b["predicted_sigma"][a]) and b["predicted_sigma"][a] > 0
        assert after["intensity"] >= 0.9 * before["intensity"]
        assert b["moved"] and all(n.startswith(("E1", "E2")) for n in b["moved"])
        assert "smallest focus: before" in proc.stdout and "hidden truth's best" in proc.stdout
        steps = b["steps"]
        # a third step only where the second move measured worse: back to the first's settings
        assert len(steps) in (2, 3) and steps[-1]["uid"] == b["uid"]
        assert f"{len(steps)} moves (closed loop)" in proc.stdout
        assert all(n.startswith(("E1", "E2")) for st in steps for n in st["moved"])
        # each move's σ read from posterior states fitted to the calibration's frames (the refit's after the first)
        assert all(st["sigma_samples"] == OptimizeOptions().posterior_samples for st in steps)
        assert "posterior states fitting the frames" in proc.stdout
        with open_store(tmp_path / "runs") as store:
            settings = []
            for k, st in enumerate(steps):
                m = store.load_measurement(st["uid"])
                md = m.metadata
                # the first move's run holds the frames before and after it, each later one those after
                assert len(m) == (2 if k == 0 else 1) * b["frames"] and m.profile_x is not None
                assert md["plan_name"] == "optimize_beam" and md["step"] == k + 1
                assert md["predicted"]["rms_x"] == pytest.approx(st["predicted"]["rms_x"])
                cur, new = np.asarray(md["current"]), np.asarray(md["settings"])
                assert np.allclose(m.configurations[0], new if k else cur) and np.allclose(m.configurations[-1], new)
                beam = load_results(store, st["uid"])["beam"]
                assert [r["what"] for r in beam] == ["before", "predicted", "after"]
                settings.append(new)
                if k:
                    assert md["previous_uid"] == steps[k - 1]["uid"]
            if len(steps) == 3:
                assert np.allclose(settings[2], settings[0]) and steps[2]["note"]
                # the smallest focus's cost, widths over the start's: the second measured worse
                cost = [sum((st["after"][f"rms_{a}"] / before[f"rms_{a}"]) ** 2 for a in "xy") for st in steps[:2]]
                assert cost[1] > cost[0]
        html = (tmp_path / "out" / "report.html").read_text()
        assert "The smallest focus with the calibrated twin" in html and b["uid"] in html
        # Measured as predicted and as small as the hidden true beamline allows (10 % each: issue
        # 21's acceptance; benchmarks/bench_optimize_beam.py checks five other draws), after the
        # closed loop. The first move's prediction rests on offsets that reproduce the frames
        # within noise but are not the truth's, so it can miss by 20 %; the refit with the frames
        # taken there brings the second move's prediction within a few %.
        over = {a: after[f"rms_{a}"] / best[f"rms_{a}"] for a in "xy"}
        ratio = {a: after[f"rms_{a}"] / pred[f"rms_{a}"] for a in "xy"}
        for a in "xy":
            assert over[a] <= 1.10, (a, over, after, best)
            assert abs(ratio[a] - 1) <= 0.10, (a, ratio, after, pred)

    def test_the_main_job_s_runs_load_back_by_uid(self, demo):
        """The chamber_z scenario is the README's main job: the designed measurement within its budget,
        every step a run in the store linked to the measurement, the posterior of every offset in the
        summary and the calibration file, the validation frames; the load-back line it prints works as
        printed; the report is self-contained."""
        from bluesky_offsets import load_calibration
        tmp_path, summary, proc = demo
        assert _gone(summary["ioc"]["pid"])  # the simulated IOC is stopped
        uids = summary["uids"]
        assert {"find_beam", "measurement", "compare", "refine_offsets", "diagnose", "add_effect", "posterior",
                "validation"} <= set(uids)
        n = summary["n_configurations"]
        assert summary["design"] == "optimal" and summary["frames"] <= int(MAIN_JOB[1])
        assert summary["frames"] == summary["beam_search"]["frames"] + n and len(summary["design_steps"]) >= 2
        assert n < summary["n_analysed_configurations"] <= summary["frames"]  # the beam search's lit frames too
        labels = [h["model"] for h in summary["history"]]
        assert labels[:3] == ["twin", "design estimate", "+ offsets"]
        out = proc.stdout
        assert "error history" in out and "load them back" in out and uids["measurement"] in out
        assert "Virtual circuit disconnect" not in proc.stderr  # channels closed before the IOC stopped
        # every offset as value ± sigma with its class, in the summary and in the calibration file
        post = summary["offsets"]["offsets"]
        assert list(post) == list(METRIXS.names)
        for name, e in post.items():
            assert e["unit"] == METRIXS[name].unit and e["class"] in ("determined", "weak", "undetermined")
            assert np.isfinite(e["value"]) and e["sigma"] > 0
        cal = load_calibration(summary["calibration"])
        assert np.allclose(cal.state.offsets, [post[k]["normalized"] for k in METRIXS.names])
        assert "chamber_z" in cal.state.effects and cal.uid in uids.values()  # the fit it comes from
        v = summary["validation"]
        assert v["configurations"] == 6 and v["uid"] == uids["validation"] and np.isfinite(v["chi2_reduced"])
        with open_store(tmp_path / "runs") as store:
            assert set(summary["all_run_uids"]) <= set(store.uids())
            m = store.load_measurement(uids["measurement"])
            # its frames read back at the gain measured after it, as the session fitted them
            sheet = float(re.search(r"the data sheet's gain ([\d.]+) ADU/photon until measured", out).group(1))
            gain = float(re.search(r"gain ([\d.]+) ± [\d.]+ ADU/photon \(photon transfer", out).group(1))
            assert gain_scale(store, m.uid) == pytest.approx(sheet / gain, rel=1e-3)
            assert m.hist_x.shape == (n, 50) and m.truth_id == summary["truth_id"] and np.isfinite(m.hist_y).all()
            assert m.screen.shape == (n, 3) and np.any(m.screen[:, 2] != 0)  # the screen moved along the beam
            design = load_results(store, uids["measurement"])["design"]
            assert [r["step"] for r in design] == list(range(len(summary["design_steps"])))
            back = {step: load_results(store, uids[step]) for step in ("compare", "refine_offsets", "diagnose",
                                                                        "add_effect")}
            for step, res in back.items():
                assert res["start"]["measurement_uid"] == uids["measurement"], step
            starts = int(MAIN_JOB[MAIN_JOB.index("--fit-starts") + 1])
            assert back["refine_offsets"]["start"]["fit_options"]["posterior_starts"] == starts
            ranking = back["diagnose"]["ranking"]
            assert [r["effect"] for r in ranking] == summary["rankings"][0]
            hist = back["add_effect"]["error_history"]
            assert [h["label"] for h in hist] == labels
            assert hist[-1]["chi2_reduced"] == pytest.approx(summary["history"][-1]["chi2_reduced"])
            assert load_results(store, uids["validation"])["start"]["plan_name"] == "measure_validation"
            rows = load_results(store, uids["posterior"])["posterior"]  # the posterior in the store too
            assert [r["parameter"] for r in rows[:len(METRIXS)]] == list(METRIXS.names)
            assert [r["class"] for r in rows[:len(METRIXS)]] == [post[k]["class"] for k in METRIXS.names]

        # the load-back line the summary prints works as printed
        line = next(l_ for l_ in out.splitlines() if l_.strip().startswith("python -c"))
        code = re.search(r'python -c "(.*)"\s*$', line).group(1)
        back = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        assert back.returncode == 0 and f"({n}, 50)" in back.stdout, back.stderr[-2000:]

        html = (tmp_path / "out" / "report.html").read_text()
        assert html.count("data:image/png;base64,") >= 5
        assert not re.search(r'(src|href)=["\']?(https?:)?//', html)  # self-contained: opens offline
        for text in ("Error history", "ranking", summary["verdict"], uids["measurement"], uids["diagnose"],
                     "The designed measurement", "Validation frames", "Offsets of the final model"):
            assert text in html


@_scenario("none")
class TestNoHiddenEffect(_Scenario):
    # the bright design's fits at 1,000 model rays (its default: 5,000), one posterior start a round: the suite's time
    options = ("--design", "bright", "--fit-rays", "1000", "--fit-starts", "1")

    def test_no_hidden_effect_reports_none(self, demo):
        _, s, _ = demo
        assert s["verdict"] == "no significant missing effect", (s["verdict"], s["history"][-1])
        assert s["fitted_effects"] == {}


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False
