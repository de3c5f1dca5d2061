"""The surrogate artifact: architecture, batched differentiable inference, safe checkpoints."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from bluesky_offsets.surrogate import network as surrogate
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.surrogate.network import Architecture, Normalization, Surrogate, SurrogateError
from bluesky_offsets.physics.twin import HistogramSpec


def _model(width=32, seed=0) -> Surrogate:
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    hist = rng.random((20, 100)) * 0.05
    norm = Normalization.fit(METRIXS, hist)
    return Surrogate.new(Architecture(width=width), norm, provenance={"n_rays": 1000}, metrics={"test": {"mse": 1.0}})


def test_architecture_is_the_papers():
    m = _model()
    linear = [mod for mod in m.net.modules() if isinstance(mod, torch.nn.Linear)]
    mish = [mod for mod in m.net.modules() if isinstance(mod, torch.nn.Mish)]
    assert len(linear) == 7 and len(mish) == 6
    assert linear[0].in_features == 34 and linear[-1].out_features == 100
    assert isinstance(list(m.net.layers)[-1], torch.nn.Linear)  # no activation after the last layer


def test_predict_batched_chunked_differentiable():
    m = _model()
    rng = np.random.default_rng(1)
    phys = METRIXS.denormalize(rng.random((5, 7, 34)))
    out = m.predict(phys)
    assert isinstance(out, np.ndarray) and out.shape == (5, 7, 100) and (out >= 0).all()
    # chunking does not change the result; normalized input gives the same
    assert np.allclose(m.predict(phys, chunk_size=3), out, atol=1e-6)
    assert np.allclose(m.predict(METRIXS.normalize(phys), normalized=True), out, atol=1e-6)
    # gradients flow to the (normalized) inputs through all chunks
    x = torch.as_tensor(METRIXS.normalize(phys), dtype=torch.float32).requires_grad_(True)
    y = m.predict(x, normalized=True, chunk_size=4, clamp=False)
    assert isinstance(y, torch.Tensor) and y.requires_grad
    y.sum().backward()
    assert x.grad is not None and x.grad.shape == x.shape and torch.isfinite(x.grad).all()
    assert (x.grad.abs().sum(-1) > 0).all()
    with pytest.raises(ValueError, match="length 34"):
        m.predict(np.zeros((3, 33)))


def test_save_load_roundtrip(tmp_path):
    m = _model()
    p = m.save(tmp_path / "m.pt")
    meta = json.loads((tmp_path / "m.json").read_text())
    assert meta["table"]["names"] == list(METRIXS.names) and meta["histogram"] == HistogramSpec().fingerprint()
    assert meta["provenance"]["n_rays"] == 1000 and meta["metrics"]["test"]["mse"] == 1.0
    m2 = surrogate.load(p)
    x = METRIXS.denormalize(np.random.default_rng(2).random((4, 34)))
    assert np.array_equal(m.predict(x), m2.predict(x))
    assert np.allclose(m2.norm.out_span, m.norm.out_span)


def _table_with_changed_range(name: str, high: float) -> ParameterTable:
    params = [p if p.name != name else type(p)(**{**p.__dict__, "high": high}) for p in METRIXS.parameters]
    return ParameterTable(params)


def test_checkpoint_for_other_table_is_refused_naming_the_mismatch(tmp_path):
    m = _model()
    p = m.save(tmp_path / "m.pt")
    other = _table_with_changed_range("E2.rotationXerror", 0.6)
    with pytest.raises(SurrogateError, match=r"range of 'E2.rotationXerror' differs.*stored \[-0.5, 0.5\]"):
        surrogate.load(p, table=other)
    # and the other way round: a model trained on the changed table, loaded with the current one
    m_other = Surrogate.new(Architecture(width=8), Normalization.fit(other, np.ones((2, 100))), table=other)
    p2 = m_other.save(tmp_path / "other.pt")
    with pytest.raises(SurrogateError, match="E2.rotationXerror"):
        surrogate.load(p2)


def test_checkpoint_for_other_histogram_spec_is_refused(tmp_path):
    p = _model().save(tmp_path / "m.pt")
    with pytest.raises(SurrogateError, match="range_y"):
        surrogate.load(p, hist=HistogramSpec(range_y=(-2.0, 2.0)))


def test_truncated_and_corrupt_files_give_clear_errors(tmp_path):
    m = _model()
    p = m.save(tmp_path / "m.pt")
    blob = p.read_bytes()
    trunc = tmp_path / "trunc.pt"
    trunc.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(SurrogateError, match="truncated or corrupt"):
        surrogate.load(trunc)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint at all")
    with pytest.raises(SurrogateError, match="truncated or corrupt"):
        surrogate.load(junk)
    # a flipped weight byte: either the archive check or our checksum catches it
    flipped = bytearray(blob)
    raw = m.net.layers[2].weight.detach().numpy().tobytes()
    i = blob.find(raw[:64])
    assert i > 0
    flipped[i + 100] ^= 0x01
    bad = tmp_path / "flip.pt"
    bad.write_bytes(bytes(flipped))
    with pytest.raises(SurrogateError, match="corrupt"):
        surrogate.load(bad)
    with pytest.raises(SurrogateError, match="does not exist"):
        surrogate.load(tmp_path / "missing.pt")


def test_shipped_checkpoint_loads_with_provenance():
    """The shipped model knows the focus chamber (34 + 3 inputs) and says where it came from."""
    path = surrogate.default_checkpoint()
    assert path.exists(), "the package ships bluesky_offsets/data/surrogate.pt"
    assert path.stat().st_size < 20 * 2**20
    m = surrogate.load()
    prov = m.provenance
    assert m.chamber and m.arch.n_inputs == 37 and m.arch.decoder == "joint"
    # issue 18's data target: >= 1 million samples at 1e4 rays, >= 300,000 of them good
    assert prov["engine"] == "torch" and prov["n_rays"] == 10_000
    assert prov["n_samples"] >= 1_000_000 and prov["n_good"] >= 300_000
    assert prov["twin"].startswith("torch") and m.metrics["test"]["mse_nonempty"] > 0
    x = METRIXS.denormalize(np.full((2, 34), 0.5))
    at = m.predict(x, chamber=(0.0, 0.0, 20.0))
    assert at.shape == (2, 100) and np.isfinite(at).all()
    assert np.array_equal(at, m.predict(np.concatenate([x, [[0.0, 0.0, 20.0]] * 2], 1)))
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["weights_sha256"] and meta["table_version"] == METRIXS.version


def test_the_fast_checkpoint_is_a_student_of_the_default():
    """The second shipped checkpoint, by name: a smaller net distilled from the default one, on the
    same data and split (its test samples unseen by either), for the CPU's evaluations per second."""
    fast, default = surrogate.load("fast"), surrogate.load("default")
    path = surrogate.resolve_checkpoint("fast")
    assert path.name == "surrogate_fast.pt" and path.stat().st_size < 20 * 2**20
    teacher = fast.provenance["teacher"]
    assert teacher["weights_sha256"] == json.loads(surrogate.default_checkpoint().with_suffix(".json")
                                                   .read_text())["weights_sha256"]
    assert fast.provenance["dataset"] == default.provenance["dataset"]
    assert fast.provenance["n_test"] == default.provenance["n_test"]
    assert fast.chamber and fast.arch.n_inputs == default.arch.n_inputs
    # fewer multiply-adds a row than the default: what makes it fast
    def macs(a):
        return a.n_inputs * a.width + (a.n_layers - 2) * a.width ** 2 + a.width * (a.n_outputs + 2)
    assert macs(fast.arch) < 0.5 * macs(default.arch)
    x = METRIXS.denormalize(np.full((2, 34), 0.5))
    assert np.isfinite(fast.predict(x, chamber=(0.0, 0.0, 20.0))).all()


def _check_likelihood_model(m, x, tmp_path):
    """A likelihood decoder's histograms, loss and checkpoint round trip at inputs ``x``."""
    h = m.predict(x)
    hx, hy = m.split(h)
    # each axis: a fraction of the source rays in [0, 1], spread over the bins
    assert (h >= 0).all() and (hx.sum(-1) <= 1 + 1e-6).all() and (hy.sum(-1) <= 1 + 1e-6).all()
    # the likelihood loss is finite for dark and bright targets and has gradients
    target = torch.zeros(2, 100)
    target[1, 20], target[1, 70] = 0.4, 0.4
    loss = m.net.loss(torch.rand(2, m.arch.n_inputs), target)
    loss.backward()
    assert torch.isfinite(loss) and all(p.grad is not None for p in m.net.parameters())
    m2 = surrogate.load(m.save(tmp_path / "m.pt"))
    assert m2.arch == m.arch and np.array_equal(m2.predict(x), h)


def test_factored_decoder_is_transmission_times_shape(tmp_path):
    torch.manual_seed(0)
    norm = Normalization.fit(METRIXS, np.zeros((3, 100)), "none")
    m = Surrogate.new(Architecture(width=32, decoder="factored"), norm)
    assert sum(isinstance(mod, torch.nn.Linear) for mod in m.net.transmission) == 7
    assert m.net.transmission[-1].out_features == 2 and m.net.shape[-1].out_features == 100
    _check_likelihood_model(m, METRIXS.denormalize(np.random.default_rng(3).random((6, 34))), tmp_path)
    with pytest.raises(ValueError, match="decoder"):
        Architecture(decoder="spline")


def test_joint_decoder_is_the_factored_model_from_one_net(tmp_path):
    """One net's last layer gives the two transmission logits, then the shape logits: the
    factored model's histogram and likelihood at half its cost (one forward pass, not two)."""
    torch.manual_seed(0)
    norm = Normalization.fit(METRIXS, np.zeros((3, 100)), "none", chamber=True)
    m = Surrogate.new(Architecture(n_inputs=37, width=32, n_layers=4, decoder="joint", members=2,
                                   activation="silu"), norm)
    members = m.net._members()
    assert len(members) == 2 and all(len(mb) == 1 and mb[0][-1].out_features == 102 for mb in members)
    _check_likelihood_model(m, np.concatenate([METRIXS.denormalize(np.random.default_rng(1).random((4, 34))),
                                               np.zeros((4, 3))], 1), tmp_path)
