"""Which effect is missing — against the simulated IOC, through the main job (issue 6 acceptance).

Each scenario runs ``bluesky-offsets demo`` as a user does: the METRIXS IOC (twin backend,
127.0.0.1, a free port, seeded frame noise) with hidden offsets in all 34 parameters (±5 % of
each range, the demo's default draw) and a hidden effect (or none), the beam search, the
measurement of 16 bright configurations and 4 of them again with the slits open through the
IOC into the run store, the surrogate finder on the 16, then compare → fit the offsets →
diagnose (all 15 candidates, camera-resolution profiles, 10 bright + 4 open configurations) →
add the winner → refit → diagnose again, every step a run in the store.  The checks read
``summary.json``; the chamber_z scenario (the README's main job) is also read back from the
store by uid.

About 2-4 minutes per scenario on two cores (docs/diagnosis.md).
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

from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.store import open_store
from plans.diagnose import load_results

SKIP = os.environ.get("BLUESKY_OFFSETS_SKIP_ACCEPTANCE") == "1"
pytestmark = [pytest.mark.slow, pytest.mark.timeout(1200),
              pytest.mark.skipif(SKIP, reason="BLUESKY_OFFSETS_SKIP_ACCEPTANCE=1")]

# (hidden effect as given to --effect, its name, the parameter checked, its hidden value)
SCENARIOS = {
    "chamber_z": ("chamber_z:z=20", "chamber_z", "z", 20.0),
    "thermal_bump_m1": ("thermal_bump_m1:height=450", "thermal_bump_m1", "height", 450.0),
    "source_divergence": ("source_divergence:divergence=0.5", "source_divergence", "divergence", 0.5),
}


def _demo(tmp_path: Path, effect: str, *extra: str) -> tuple[dict, subprocess.CompletedProcess]:
    exe = Path(sys.executable).parent / "bluesky-offsets"  # the console script, as a user runs it
    # the demo's fits one at a time ($OMP_NUM_THREADS, tests/conftest.py): measured with two at a
    # time, the suite took 14.9 min (its demos 279, 271, 231, 136 s) against 14.7 (291, 280, 228,
    # 117 s) with one: the two workers' demos overlap, and nothing was gained
    cmd = [str(exe) if exe.exists() else shutil.which("bluesky-offsets"), "demo", "--effect", effect,
           "--out", str(tmp_path / "out"), "--store", str(tmp_path / "runs"), *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1150,
                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    print(proc.stdout[-2500:])
    return json.loads((tmp_path / "out" / "summary.json").read_text()), proc


class _Scenario:
    """One scenario's demo, run once for the tests of its class: pytest-xdist (``--dist
    loadscope``) runs a class on one worker, so the demos spread over the workers.  Only the
    main job's scenario ends with the beam optimization (``optimize``); the others stop after
    the diagnosis (``--no-optimize``), the step they test."""

    optimize = False

    @pytest.fixture(scope="class")
    def demo(self, scenario, tmp_path_factory) -> tuple[Path, dict, subprocess.CompletedProcess]:
        """(folder, summary, process)"""
        tmp = tmp_path_factory.mktemp(scenario)
        return (tmp, *_demo(tmp, SCENARIOS[scenario][0] if scenario in SCENARIOS else scenario,
                            *(() if self.optimize else ("--no-optimize",))))


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
        assert len(steps) == 2 and steps[-1]["uid"] == b["uid"] and "2 moves (closed loop)" in proc.stdout
        assert all(n.startswith(("E1", "E2")) for st in steps for n in st["moved"])
        with open_store(tmp_path / "runs") as store:
            for k, st in enumerate(steps):
                m = store.load_measurement(st["uid"])
                md = m.metadata
                # the first move's run holds the frames before and after it, the second's those after
                assert len(m) == (2 - k) * b["frames"] and m.profile_x is not None
                assert md["plan_name"] == "optimize_beam" and md["step"] == k + 1
                assert md["predicted"]["rms_x"] == pytest.approx(st["predicted"]["rms_x"])
                cur, new = np.asarray(md["current"]), np.asarray(md["settings"])
                assert np.allclose(m.configurations[0], new if k else cur) and np.allclose(m.configurations[-1], new)
                beam = load_results(store, st["uid"])["beam"]
                assert [r["what"] for r in beam] == ["before", "predicted", "after"]
            assert store.load_measurement(steps[1]["uid"]).metadata["previous_uid"] == steps[0]["uid"]
        html = (tmp_path / "out" / "report.html").read_text()
        assert "The smallest focus with the calibrated twin" in html and b["uid"] in html
        # Measured as predicted and as small as the hidden true beamline allows (10 % each: issue
        # 21's acceptance; benchmarks/bench_optimize_beam.py checks five other draws), after the
        # closed loop. The first move's prediction rests on offsets that reproduce the frames
        # within noise but are not the truth's (pulls up to 11 sigma; issue 17): measured
        # (2026-11-27, this draw) 9.6 x 6.8 µm against 12.0 x 7.7 predicted (0.80, 0.88); refitted
        # with the frames taken there, the second move's 11.1 x 6.8 predicted, 10.7 x 6.8 measured
        # (0.97, 1.00), the truth's best 10.2 x 6.6 (1.05, 1.03).
        over = {a: after[f"rms_{a}"] / best[f"rms_{a}"] for a in "xy"}
        ratio = {a: after[f"rms_{a}"] / pred[f"rms_{a}"] for a in "xy"}
        for a in "xy":
            assert over[a] <= 1.10, (a, over, after, best)
            assert abs(ratio[a] - 1) <= 0.10, (a, ratio, after, pred)

    def test_the_main_job_s_runs_load_back_by_uid(self, demo):
        """The chamber_z scenario is the README's main job: every step a run in the store, linked to
        the measurement; the load-back line it prints works as printed; the report is self-contained."""
        tmp_path, summary, proc = demo
        assert _gone(summary["ioc"]["pid"])  # the simulated IOC is stopped
        uids = summary["uids"]
        assert {"find_beam", "search", "measurement", "find_offsets", "compare", "refine_offsets",
                "diagnose", "add_effect"} <= set(uids)
        n, n_open, n_an = (summary["n_configurations"], summary["n_open_configurations"],
                           summary["n_analysed_configurations"])
        assert (n, n_open, n_an) == (20, 4, 14)
        labels = [h["model"] for h in summary["history"]]
        assert labels[:3] == ["twin", "surrogate offsets", "+ offsets"]
        out = proc.stdout
        assert "error history" in out and "load them back" in out and uids["measurement"] in out
        assert "Virtual circuit disconnect" not in proc.stderr  # channels closed before the IOC stopped

        analysed = list(range(n_an - n_open)) + list(range(n - n_open, n))  # the first bright ones, the open ones
        with open_store(tmp_path / "runs") as store:
            assert set(summary["all_run_uids"]) <= set(store.uids())
            m = store.load_measurement(uids["measurement"])
            assert m.hist_x.shape == (n, 50) and m.truth_id == summary["truth_id"] and np.isfinite(m.hist_y).all()
            # the last ones are the first bright ones with the slits open (outside the surrogate's box)
            assert np.allclose(m.configurations[-n_open:, 0], m.configurations[:n_open, 0])
            assert np.allclose(m.configurations[-n_open:, METRIXS.index("ExitSlit.totalHeight")], 0.1, atol=1e-6)
            assert store[uids["find_offsets"]].metadata["start"]["n_configurations"] == n - n_open  # its box only
            back = {step: load_results(store, uids[step]) for step in ("compare", "refine_offsets", "diagnose",
                                                                        "add_effect")}
            for step, res in back.items():
                assert res["start"]["measurement_uid"] == uids["measurement"], step
                assert res["start"]["analysed_configurations"] == analysed, step
            ranking = back["diagnose"]["ranking"]
            assert [r["effect"] for r in ranking] == summary["rankings"][0]
            hist = back["add_effect"]["error_history"]
            assert [h["label"] for h in hist] == labels
            assert hist[-1]["chi2_reduced"] == pytest.approx(summary["history"][-1]["chi2_reduced"])

        # the load-back line the summary prints works as printed
        line = next(l_ for l_ in out.splitlines() if l_.strip().startswith("python -c"))
        code = re.search(r'python -c "(.*)"\s*$', line).group(1)
        back = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        assert back.returncode == 0 and f"({n}, 50)" in back.stdout, back.stderr[-2000:]

        html = (tmp_path / "out" / "report.html").read_text()
        assert html.count("data:image/png;base64,") >= 5
        assert not re.search(r'(src|href)=["\']?(https?:)?//', html)  # self-contained: opens offline
        for text in ("Error history", "ranking", summary["verdict"], uids["measurement"], uids["diagnose"]):
            assert text in html


@_scenario("thermal_bump_m1")
class TestThermalBump(_HiddenEffect):
    pass


@_scenario("source_divergence")
class TestSourceDivergence(_HiddenEffect):
    pass


@_scenario("none")
class TestNoHiddenEffect(_Scenario):
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
