"""Dataset generation: deterministic draws, exact counts, resumable after a hard kill."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bluesky_offsets.surrogate import dataset
from bluesky_offsets.commands.cli import main
from bluesky_offsets.surrogate.dataset import DatasetError, DrawScheme, GenerationSettings
from bluesky_offsets.physics.parameters import METRIXS

os.environ.setdefault("OMP_NUM_THREADS", "1")  # inline tracing of many tiny traces

SMALL = GenerationSettings(n_rays=300, seed=3, block_size=24, scheme=DrawScheme(screen_rays=60, keep_fraction=0.05))


def test_draws_are_deterministic_and_in_the_box():
    a = dataset.draw(METRIXS, 5, 123)
    b = dataset.draw(METRIXS, 5, 123)
    c = dataset.draw(METRIXS, 5, 124)
    assert np.array_equal(a[0], b[0]) and a[1:] == b[1:]
    assert not np.array_equal(a[0], c[0])
    assert ((a[0] >= METRIXS.low) & (a[0] <= METRIXS.high)).all()


def test_generate_exact_count_metadata_and_extension(tmp_path):
    out = tmp_path / "ds.zarr"
    stats = dataset.generate(out, 10, SMALL, scheduler="inline", progress=False)
    d = dataset.load(out)
    assert len(d) == 10 and stats["n_samples"] == 10
    assert np.all(np.diff(d.index) > 0)  # draw order, no duplicates
    assert set(np.unique(d.stratum)) <= {0, 1}
    assert np.allclose(d.weight[d.stratum == 1], 1 / 0.05) and np.allclose(d.weight[d.stratum == 0], 1)
    # every stored sample is reproducible from its index: same parameters
    for i, idx in enumerate(d.index[:3]):
        assert np.array_equal(dataset.draw(METRIXS, SMALL.seed, int(idx))[0], d.params[i])
    import zarr
    attrs = zarr.open_group(str(out), mode="r").attrs
    assert attrs["settings"]["n_rays"] == 300 and attrs["settings"]["scheme"]["screen_rays"] == 60
    assert "pre-screen at 60 rays" in attrs["scheme"]
    assert attrs["stats"]["n_draws"] >= 10 and attrs["engine"].startswith("rayx")
    assert np.allclose(d.hist.sum(1), (d.hist_x.sum(1) + d.hist_y.sum(1)))
    # extending keeps the first samples (deterministic draws)
    dataset.generate(out, 14, SMALL, scheduler="inline", progress=False)
    d2 = dataset.load(out)
    assert len(d2) == 14 and np.array_equal(d2.index[:10], d.index)
    assert np.array_equal(d2.hist_x[:10], d.hist_x)
    # other settings on the same store are refused, naming what differs
    with pytest.raises(DatasetError, match="settings"):
        dataset.generate(out, 14, GenerationSettings(n_rays=400, seed=3, block_size=24, scheme=SMALL.scheme),
                         scheduler="inline", progress=False)


def test_incomplete_store_refused_unless_partial(tmp_path):
    out = tmp_path / "ds.zarr"
    dataset.generate(out, 6, SMALL, scheduler="inline", progress=False)
    prog = json.loads((out / "progress.json").read_text())
    prog["complete"] = False
    (out / "progress.json").write_text(json.dumps(prog))
    with pytest.raises(DatasetError, match="incomplete"):
        dataset.load(out)
    assert len(dataset.load(out, allow_partial=True)) >= 6
    with pytest.raises(DatasetError, match="not a dataset store"):
        dataset.load(tmp_path / "nothing")


def _committed_blocks(store: Path) -> int:
    try:
        return len(json.loads((store / "progress.json").read_text())["blocks"])
    except (OSError, ValueError, KeyError):
        return 0


def test_kill_and_resume_cli_exact_no_duplicates(tmp_path):
    """SIGKILL the real `bluesky-offsets dataset generate` (Dask, 2 workers) mid-run, then rerun."""
    store = tmp_path / "kill.zarr"
    n = 40
    args = [str(store), "--samples", str(n), "--rays", "300", "--screen-rays", "60", "--keep-fraction", "0.05",
            "--block-size", "24", "--seed", "11"]
    cmd = [sys.executable, "-m", "bluesky_offsets.commands.cli", "dataset", "generate", *args, "--workers", "2",
           "--no-progress"]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.time() + 120
        while _committed_blocks(store) < 3 and time.time() < deadline and proc.poll() is None:
            time.sleep(0.05)
        assert proc.poll() is None, proc.stdout.read().decode()[-2000:]
        os.killpg(proc.pid, signal.SIGKILL)  # the CLI and its Dask workers, no chance to clean up
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    prog = json.loads((store / "progress.json").read_text())
    assert not prog.get("complete") and 0 < prog["rows"] < n
    with pytest.raises(DatasetError, match="incomplete"):
        dataset.load(store)

    assert main(["dataset", "generate", *args, "--scheduler", "inline", "--no-progress"]) == 0
    d = dataset.load(store)
    assert len(d) == n
    assert len(np.unique(d.index)) == n
    # identical to an uninterrupted run with the same settings
    ref = tmp_path / "ref.zarr"
    assert main(["dataset", "generate", str(ref), *args[1:], "--scheduler", "inline", "--no-progress"]) == 0
    r = dataset.load(ref)
    assert np.array_equal(r.index, d.index)
    assert np.array_equal(r.params, d.params)
    assert np.array_equal(r.hist_x, d.hist_x) and np.array_equal(r.n_hits, d.n_hits)


def test_torch_engine_store_with_the_chamber_is_checked_against_rayx(tmp_path, capsys):
    """`dataset generate --engine torch --chamber`: the block traced at once, 37 inputs, the
    engine on record, a RAYX slice compared in distribution; resumable like RAYX's stores."""
    out = tmp_path / "torch.zarr"
    args = [str(out), "--samples", "30", "--rays", "1500", "--screen-rays", "100", "--block-size", "200",
            "--seed", "4", "--engine", "torch", "--chamber", "--scheduler", "inline", "--no-progress",
            "--rayx-check", "12"]
    assert main(["dataset", "generate", *args]) == 0
    printed = capsys.readouterr().out
    assert "RAYX check on 12 non-empty samples at 1500 rays" in printed
    d = dataset.load(out)
    assert len(d) == 30 and d.inputs.shape == (30, 37)
    assert d.meta["inputs"][-3:] == ["chamber_x", "chamber_y", "chamber_z"]
    assert d.meta["engine"].startswith("torch") and d.meta["settings"]["engine"] == "torch"
    assert ((d.chamber >= dataset.CHAMBER_LOW) & (d.chamber <= dataset.CHAMBER_HIGH)).all()
    assert np.ptp(d.chamber[:, 2]) > 10  # z drawn over its box
    for i, idx in enumerate(d.index[:3]):  # inputs reproducible from the draw index
        assert np.array_equal(dataset.draw(METRIXS, 4, int(idx))[0], d.params[i])
    assert (d.n_hits[d.stratum == 0] > 0).all()
    np.testing.assert_allclose(d.hist_x.sum(1), d.hist_y.sum(1), atol=1e-6)  # both axes see every ray
    import zarr
    check = zarr.open_group(str(out), mode="r").attrs["rayx_check"]
    assert check["n_checked"] == 12 and check["mse_ratio"] > 0 and "consistent" in check
    # the same command again: the finished store is reused, nothing traced twice
    assert main(["dataset", "generate", *args[:-2], "--rayx-check", "0"]) == 0
    # a store written before the engine and chamber settings existed still resumes as RAYX's
    ref = tmp_path / "old.zarr"
    dataset.generate(ref, 4, SMALL, scheduler="inline", progress=False)
    prog = json.loads((ref / "progress.json").read_text())
    for k in ("engine", "chamber"):
        del prog["identity"]["settings"][k]
    (ref / "progress.json").write_text(json.dumps(prog))
    dataset.generate(ref, 6, SMALL, scheduler="inline", progress=False)
    assert len(dataset.load(ref)) == 6
    with pytest.raises(ValueError, match="engine must be one of rayx, torch"):
        GenerationSettings(engine="ray-ui")
