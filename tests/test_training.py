"""The paper's training recipe end to end on a small budget: dataset -> train -> evaluate."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from bluesky_offsets.physics.parameters import METRIXS
from bluesky_offsets.surrogate import dataset
from bluesky_offsets.surrogate import network as surrogate
from bluesky_offsets.surrogate import training
from bluesky_offsets.commands.cli import main
from bluesky_offsets.surrogate.dataset import DatasetError
from bluesky_offsets.surrogate.training import TrainConfig, TrainingError

os.environ.setdefault("OMP_NUM_THREADS", "1")

GEN = ["--rays", "500", "--screen-rays", "60", "--keep-fraction", "0.05", "--block-size", "32", "--seed", "2",
       "--scheduler", "inline", "--no-progress"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("train") / "ds.zarr"
    assert main(["dataset", "generate", str(path), "--samples", "200", *GEN]) == 0
    return path


def _small(**kw) -> TrainConfig:
    base = dict(epochs=4, width=48, threads=1, epoch_samples=320, patience=0)
    base.update(kw)
    return TrainConfig(**base)


def test_epoch_order_shows_good_and_bad_3_to_1():
    rng = np.random.default_rng(0)
    good, bad = np.arange(0, 90), np.arange(90, 100)
    order = training.epoch_order(good, bad, 0.75, None, rng)
    n_good = np.isin(order, good).sum()
    assert len(order) == 120 and n_good == 90 and len(np.unique(order[np.isin(order, good)])) == 90
    assert (len(order) - n_good) == 30  # bad ones repeat to keep 3:1
    tr, va, te = training.split_indices(1000, (0.8, 0.1, 0.1), 0)
    assert (len(tr), len(va), len(te)) == (800, 100, 100)
    assert len(np.unique(np.concatenate([tr, va, te]))) == 1000


def test_recipe_end_to_end_cli_loss_goes_down(store, tmp_path, capsys):
    run = tmp_path / "run"
    out = tmp_path / "model.pt"
    rc = main(["train", str(store), str(run), "--epochs", "8", "--width", "64", "--threads", "1",
               "--epoch-samples", "640", "--no-progress", "--json", "--out", str(out)])
    assert rc == 0
    metrics = json.loads(capsys.readouterr().out)
    hist = json.loads((run / "history.json").read_text())
    assert len(hist) == 8
    assert hist[-1]["train_loss"] < 0.7 * hist[0]["train_loss"]
    assert min(h["val_mse"] for h in hist[1:]) < hist[0]["val_mse"]
    assert metrics["test"]["n"] == 20 and np.isfinite(metrics["test"]["mse"])
    # a store drawn without the chamber gives 34 inputs: the chamber at its nominal place only
    model = surrogate.load(out)
    assert not model.chamber
    with pytest.raises(ValueError, match="without the focus chamber"):
        model.predict(METRIXS.reference, chamber=[0.0, 0.0, 5.0])
    m = surrogate.load(out)
    assert m.provenance["n_samples"] == 200 and m.provenance["n_rays"] == 500
    assert m.training["lr"] == 1e-4 and m.training["batch_size"] == 32 and m.training["gamma"] == 0.999
    assert m.training["good_fraction"] == 0.75 and m.training["split"] == [0.8, 0.1, 0.1]
    assert json.loads(out.with_suffix(".json").read_text())["metrics"]["test"]["mse"] == metrics["test"]["mse"]

    # evaluate it on a fresh twin set, next to the twin's repeat noise
    plot = tmp_path / "fig4.png"
    rc = main(["surrogate", "evaluate", "--checkpoint", str(out), "--samples", "12", "--min-nonempty", "4",
               "--uniform", "4", "--scheduler", "inline", "--no-progress", "--json", "--plot", str(plot)])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["n_rays"] == 500 and res["n_samples"] >= 12 and res["n_nonempty"] >= 4
    for k in ("mse", "mse_nonempty", "noise_mse", "noise_mse_nonempty", "ratio_nonempty"):
        assert np.isfinite(res[k]) and res[k] > 0, k
    assert res["screened"]["uniform_weighted"]["n"] == res["n_samples"]
    assert res["uniform"]["as_drawn"]["n"] >= 4
    assert plot.exists() and plot.stat().st_size > 10_000


def test_factored_decoder_trains(store, tmp_path):
    data = dataset.load(store)
    m = training.train(data, tmp_path / "f", _small(epochs=6, decoder="factored", lr=1e-3), progress=False)
    hist = json.loads((tmp_path / "f" / "history.json").read_text())
    assert m.arch.decoder == "factored" and m.norm.mode == "none" and m.training["decoder"] == "factored"
    assert hist[-1]["train_loss"] < hist[0]["train_loss"]
    assert min(h["val_mse"] for h in hist[1:]) < hist[0]["val_mse"]
    ens = training.train(data, tmp_path / "e", _small(epochs=2, decoder="factored", members=2), progress=False)
    assert ens.arch.members == 2 and len(ens.net.shape_members) == 2
    with pytest.raises(ValueError, match="ensemble"):
        _small(members=2)
    with pytest.raises(ValueError, match="members must be positive"):
        _small(members=0)
    with pytest.raises(ValueError, match="threads must be positive"):
        _small(threads=0)
    with pytest.raises(ValueError, match="max_minutes must be positive"):
        _small(max_minutes=0)
    (tmp_path / "a-file").write_text("")
    with pytest.raises(TrainingError, match="cannot use .*a-file as the run directory"):
        training.train(data, tmp_path / "a-file", _small(epochs=1), progress=False)


def test_resume_continues_exactly(store, tmp_path):
    data = dataset.load(store)
    a, b = tmp_path / "a", tmp_path / "b"
    training.train(data, a, _small(epochs=2), progress=False)
    training.train(data, a, _small(epochs=4), progress=False)  # resumes at epoch 2
    training.train(data, b, _small(epochs=4), progress=False)
    ha = json.loads((a / "history.json").read_text())
    hb = json.loads((b / "history.json").read_text())
    assert [h["epoch"] for h in ha] == [1, 2, 3, 4]
    assert np.allclose([h["val_mse"] for h in ha], [h["val_mse"] for h in hb], rtol=1e-5)
    with pytest.raises(TrainingError, match="different lr"):
        training.train(data, a, _small(epochs=6, lr=1e-3), progress=False)


def test_early_stopping(store, tmp_path):
    data = dataset.load(store)
    m = training.train(data, tmp_path / "r", _small(epochs=50, patience=2, min_delta=0.5, lr=1e-7),
                       progress=False)
    assert m.metrics["epochs_run"] == 3 and m.metrics["best_epoch"] == 1


def test_init_fine_tunes_from_a_checkpoint(store, tmp_path):
    data = dataset.load(store)
    first = training.train(data, tmp_path / "a", _small(epochs=3, decoder="factored", lr=1e-3), progress=False)
    ckpt = tmp_path / "a" / "best.pt"
    tuned = training.train(data, tmp_path / "b", _small(epochs=1, decoder="factored", lr=1e-12, init=str(ckpt)),
                           progress=False)
    # a vanishing learning rate keeps the starting weights: the start is the checkpoint, not random
    assert tuned.metrics["test"]["mse"] == pytest.approx(first.metrics["test"]["mse"], rel=1e-4)
    assert tuned.provenance["init"]["path"] == str(ckpt)
    with pytest.raises(TrainingError, match="architecture"):
        training.train(data, tmp_path / "c", _small(epochs=1, decoder="factored", width=32, init=str(ckpt)),
                       progress=False)


def test_grown_split_keeps_the_old_samples_where_they_were():
    old = training.split_indices(100, (0.8, 0.1, 0.1), 0)
    grown = training.grown_split_indices(150, [100], (0.8, 0.1, 0.1), 0)
    for a, b in zip(old, grown):
        assert np.array_equal(b[b < 100], a)
    assert sorted(np.concatenate(grown).tolist()) == list(range(150))
    assert [len(g[g >= 100]) for g in grown] == [40, 5, 5]
    twice = training.grown_split_indices(200, [100, 150], (0.8, 0.1, 0.1), 0)  # a chain of fine-tunes
    for a, b in zip(grown, twice):
        assert np.array_equal(b[b < 150], a)
    assert training._size_chain({"n_samples": 150, "init": {"n_samples": 100}}) == [100, 150]
    with pytest.raises(TrainingError, match="trained on 200"):
        training.grown_split_indices(150, [200], (0.8, 0.1, 0.1), 0)


def test_chamber_inputs_torch_data_train_and_evaluate_against_rayx(tmp_path, capsys):
    """A store from the torch engine with the chamber drawn trains a surrogate of 37 inputs;
    it predicts from the 34 plus a chamber position, refuses what does not fit, and is
    evaluated on fresh RAYX traces drawn with the chamber."""
    path = tmp_path / "torch.zarr"
    assert main(["dataset", "generate", str(path), "--samples", "120", "--engine", "torch", "--chamber",
                 "--rayx-check", "0", *GEN]) == 0
    model = training.train(dataset.load(path), tmp_path / "run", _small(decoder="factored", activation="silu"),
                           progress=False)
    assert model.chamber and model.arch.n_inputs == 37
    assert model.inputs[-3:] == ["chamber_x", "chamber_y", "chamber_z"]
    assert model.provenance["engine"] == "torch" and model.provenance["twin"].startswith("torch")
    ref = dataset.load(path).params[0]
    np.testing.assert_allclose(model.predict(ref), model.predict(np.append(ref, [0.0, 0.0, 0.0])), rtol=1e-6)
    np.testing.assert_allclose(model.predict(ref, chamber=[0.1, 0.0, 9.0]),
                               model.predict(np.append(ref, [0.1, 0.0, 9.0])), rtol=1e-6)
    with pytest.raises(ValueError, match="length 34 or 37"):
        model.predict(ref[:30])
    model.save(tmp_path / "m.pt")
    assert surrogate.load(tmp_path / "m.pt").chamber and surrogate.load(tmp_path / "m.pt").arch.activation == "silu"
    with pytest.raises(ValueError, match="activation must be one of mish, silu"):
        TrainConfig(activation="tanh")
    capsys.readouterr()
    assert main(["surrogate", "evaluate", "--checkpoint", str(tmp_path / "m.pt"), "--samples", "12",
                 "--min-nonempty", "4", "--seed", "5", "--scheduler", "inline", "--no-progress", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["engine"].startswith("rayx") and res["n_nonempty"] >= 4 and np.isfinite(res["mse_nonempty"])
    # another model scored on the very set evaluate kept gives evaluate's own numbers for this one
    from bluesky_offsets.surrogate.evaluate import evaluate, score
    kept = evaluate(model, n_samples=12, min_nonempty=4, seed=5, scheduler="inline", progress=False, keep_data=True)
    again = score(model, kept["_data"]["screened"])
    assert again["mse_nonempty"] == pytest.approx(kept["mse_nonempty"], rel=1e-12)
    assert again["ratio_nonempty"] == pytest.approx(kept["ratio_nonempty"], rel=1e-12)
    # the finder's forward model sees the chamber where it is known to be; its unknowns stay 34
    import torch
    from bluesky_offsets.offsets.finder import load_forward_model
    fm = load_forward_model(tmp_path / "m.pt", chamber=[0.1, 0.0, 9.0])
    ours = fm(torch.as_tensor(METRIXS.normalize(ref), dtype=torch.float32)).numpy()
    np.testing.assert_allclose(ours, model.predict(ref, chamber=[0.1, 0.0, 9.0]), rtol=1e-5, atol=1e-7)
    # the IOC's surrogate backend moves the chamber of such a model (the hidden chamber_* effects)
    from sim_iocs.backends import make_backend
    backend = make_backend(f"surrogate:{tmp_path / 'm.pt'}", overrides={"ImagePlane": {"translationZerror": 9.0}},
                           noise_seed=1)
    try:
        frame = backend.submit(ref, 10**9).result(timeout=30)
    finally:
        backend.close()
    expect = model.predict(ref, chamber=[0.0, 0.0, 9.0])
    np.testing.assert_allclose(np.concatenate([frame.hist_x, frame.hist_y]), expect, atol=1e-3)
    # so does the shipped one
    assert surrogate.load().chamber


def test_a_store_grown_by_another_fine_tunes_with_the_old_split(store, tmp_path):
    """`train A B`: the union of two stores (distinct seeds) fine-tunes a model trained on A,
    A's samples first and split as before; the compact form that carries a store to a GPU
    machine gives the same samples back."""
    a = dataset.load(store)
    s = dataset.GenerationSettings.from_dict(a.meta["settings"])
    b = _other(store, tmp_path, 40, seed_offset=1)
    other = b.meta["path"]
    both = dataset.load_many([store, other])
    assert len(both) == len(a) + 40 and both.meta["path"] == f"{store} + {other}"
    assert [p["seed"] for p in both.meta["parts"]] == [s.seed, s.seed + 1]
    assert np.array_equal(both.params[len(a):], b.params)
    first = training.train(a, tmp_path / "a", _small(epochs=1, decoder="factored"), progress=False)
    ckpt = tmp_path / "a" / "best.pt"
    tuned = training.train(both, tmp_path / "b", _small(epochs=1, decoder="factored", init=str(ckpt)),
                           progress=False)
    assert tuned.provenance["dataset"] == both.meta["path"] and tuned.provenance["dataset_seed"] == [s.seed, s.seed + 1]
    assert tuned.provenance["n_test"] == first.provenance["n_test"] + 4  # A's test samples plus 10 % of B's
    with pytest.raises(TrainingError, match="validation/test samples would leak"):
        training.train(dataset.concat([b, a]), tmp_path / "c", _small(epochs=1, decoder="factored", init=str(ckpt)),
                       progress=False)
    with pytest.raises(DatasetError, match="share a base seed"):
        dataset.concat([a, a])
    # the compact form: integer bin counts and the draw index; parameters recomputed from the draw
    rows = dataset.compact_rows({"hist_x": b.hist_x, "hist_y": b.hist_y, "index": b.index, "n_hits": b.n_hits,
                                 "screen_hits": np.zeros(len(b)), "stratum": b.stratum, "weight": b.weight},
                                s.n_rays)
    back = dataset.expand_rows(rows, dataset.GenerationSettings.from_dict(b.meta["settings"]))
    for k in ("params", "hist_x", "hist_y", "n_hits", "stratum", "weight", "index"):
        assert np.array_equal(back[k], getattr(b, k)), k


def test_a_student_learns_the_teachers_predictions(store, tmp_path):
    """`train --teacher`: a smaller net distilled from a trained one sees the teacher's histograms
    at the training inputs; it is validated and tested against the traced ones, on the
    teacher's own split, and a teacher of other data is refused."""
    data = dataset.load(store)
    teacher = training.train(data, tmp_path / "t", _small(epochs=3, decoder="joint", lr=1e-3), progress=False)
    ckpt = tmp_path / "t" / "best.pt"
    student = training.train(data, tmp_path / "s", _small(epochs=2, decoder="joint", width=16, lr=1e-3,
                                                          teacher=str(ckpt)), progress=False)
    assert student.provenance["teacher"]["path"] == str(ckpt)
    assert student.provenance["n_test"] == teacher.provenance["n_test"]
    assert student.arch.width == 16 and np.isfinite(student.metrics["test"]["mse"])
    with pytest.raises(TrainingError, match="cannot distil"):
        training.train(dataset.concat([data, _other(store, tmp_path, 12, seed_offset=7)]), tmp_path / "x",
                       _small(epochs=1, decoder="joint", teacher=str(ckpt)), progress=False)
    # a student goes on from an earlier student of the same teacher, never from another model
    student.save(tmp_path / "s.pt")
    longer = training.train(data, tmp_path / "s2", _small(epochs=1, decoder="joint", width=16, lr=1e-4,
                                                          teacher=str(ckpt), init=str(tmp_path / "s.pt")),
                            progress=False)
    assert longer.provenance["init"]["path"] == str(tmp_path / "s.pt")
    with pytest.raises(TrainingError, match="not a student of that teacher"):
        training.train(data, tmp_path / "s3", _small(epochs=1, decoder="joint", teacher=str(ckpt), init=str(ckpt)),
                       progress=False)


def _other(store, tmp_path, n: int, seed_offset: int):
    """Another store drawn like ``store``, from the base seed ``seed_offset`` further on."""
    s = dataset.GenerationSettings.from_dict(dataset.load(store).meta["settings"])
    path = tmp_path / f"other{seed_offset}.zarr"
    moved = dataset.GenerationSettings(**{**s.to_dict(), "scheme": s.scheme, "seed": s.seed + seed_offset})
    dataset.generate(path, n, moved, scheduler="inline", progress=False)
    return dataset.load(path)
