"""The neural surrogate of the twin: 34 beamline parameters -> x and y histograms.

Optionally, the focus chamber's x, y, z are inputs too.

Paper Sec. 3.1: min-max normalized inputs and outputs, seven linear layers,
Mish after every layer but the last, 100 outputs (50 x bins then 50 y bins,
in the twin's units: fraction of source rays per bin).

A :class:`Surrogate` is the network plus everything needed to use it safely:
the parameter table it was trained on (names, order, ranges), the histogram
spec, the normalization, where its data came from and how well it did.
:func:`load` refuses a checkpoint that does not match the current table or
histogram spec, and reports truncated or corrupt files instead of returning
a half-loaded model.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from bluesky_offsets.errors import InputError
from bluesky_offsets.physics.effects import CHAMBER_HIGH, CHAMBER_INPUTS, CHAMBER_LOW
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.physics.twin import SOURCE_FRAME, HistogramSpec

FORMAT = "bluesky-offsets-surrogate/1"
#: the shipped model: 34 parameters and the focus chamber's x, y, z in, torch-engine data at 1e4
#: rays (docs/explanations/surrogate.md says how it was made and how close to the twin's noise it is)
DEFAULT_CHECKPOINT = "surrogate.pt"
# The checkpoints shipped in bluesky_offsets/data, by name: the default is the accurate one; "fast"
# is its distilled student, sized for the CPU's evaluations per second (docs/explanations/surrogate.md)
SHIPPED = {"default": DEFAULT_CHECKPOINT, "fast": "surrogate_fast.pt"}


class SurrogateError(RuntimeError):
    """A checkpoint that cannot be used: missing, corrupt, or made for another table/spec."""


# --------------------------------------------------------------------------- #
# network
# --------------------------------------------------------------------------- #
DECODERS = ("bins", "factored", "joint")
#: the decoders that predict transmission x shape and train on the ray-count likelihood
LIKELIHOOD_DECODERS = ("factored", "joint")


@dataclass(frozen=True)
class Architecture:
    """Fully connected nets: ``n_layers`` linear layers of ``width``, Mish in between.

    ``decoder`` chooses what the nets predict:

    * ``"bins"`` (the paper): one net whose last layer gives the 100 min-max
      normalized bin values directly; trained on their MSE.
    * ``"factored"``: per axis, a histogram is ``transmission x shape``.  One
      net gives the fraction of source rays inside each axis' histogram range
      (a sigmoid), a second one the footprint's shape (a softmax over the
      axis' bins).  Trained on the likelihood of the ray counts (binomial for
      the transmission, multinomial for the shape), whose gradients do not
      vanish on the mostly dark box (docs/explanations/surrogate.md says why this matters).
    * ``"joint"``: the same factors and loss from one net whose last layer gives
      the two transmission logits and the shape logits together: half the
      cost of "factored" per evaluation (what a CPU finder pays for).

    ``members`` > 1 (factored or joint) averages the histograms of that many such
    pairs of nets, trained together from different initializations: the
    members' errors partly cancel.

    ``activation``: Mish (the paper's) or SiLU, whose forward pass costs about half on a CPU
    core (one transcendental function per unit against three).
    """

    n_inputs: int = 34
    n_outputs: int = 100
    width: int = 512
    n_layers: int = 7
    decoder: str = "bins"
    bins_x: int | None = None
    members: int = 1
    activation: str = "mish"

    def __post_init__(self):
        if self.activation not in ACTIVATIONS:
            raise InputError(f"activation must be one of {', '.join(ACTIVATIONS)}, got {self.activation!r}")
        if self.n_layers < 2:
            raise InputError("n_layers must be >= 2")
        if self.width < 1:
            raise InputError("width must be positive")
        if self.decoder not in DECODERS:
            raise InputError(f"decoder must be one of {DECODERS}, got {self.decoder!r}")
        if self.members < 1 or (self.members > 1 and self.decoder not in LIKELIHOOD_DECODERS):
            raise InputError("members > 1 (an ensemble) needs the factored or joint decoder")
        if self.bins_x is None:
            object.__setattr__(self, "bins_x", self.n_outputs // 2)
        if not 0 < self.bins_x < self.n_outputs:
            raise InputError(f"bins_x must be in (0, {self.n_outputs}), got {self.bins_x}")


ACTIVATIONS = {"mish": nn.Mish, "silu": nn.SiLU}

# Rows per forward pass on a CPU: a chunk's activations stay in the core's cache.  A width-128
# net ran 2.3e4 evaluations/s in chunks of 4096 rows and 1.0e4/s with 100,000 rows at once.
CPU_CHUNK_ROWS = 4096


def _mlp(n_in: int, n_out: int, width: int, n_layers: int, activation: str = "mish") -> nn.Sequential:
    sizes = [n_in] + [width] * (n_layers - 1) + [n_out]
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < n_layers - 1:
            layers.append(ACTIVATIONS[activation]())
    return nn.Sequential(*layers)


class SurrogateNet(nn.Module):
    """The bare network(s): normalized inputs -> normalized outputs.

    The likelihood decoders' outputs are the histograms themselves (their
    :class:`Normalization` is the identity).
    """

    def __init__(self, arch: Architecture):
        super().__init__()
        self.decoder = arch.decoder
        self.bins_x = arch.bins_x
        act = arch.activation
        if arch.decoder == "bins":
            self.layers = _mlp(arch.n_inputs, arch.n_outputs, arch.width, arch.n_layers, act)
        elif arch.decoder == "joint":  # 2 transmission logits, then the shape logits
            self.joint_members = nn.ModuleList(_mlp(arch.n_inputs, 2 + arch.n_outputs, arch.width, arch.n_layers, act)
                                               for _ in range(arch.members))
        elif arch.members == 1:  # (flat attribute names keep single-model checkpoints simple)
            self.transmission = _mlp(arch.n_inputs, 2, arch.width, arch.n_layers, act)
            self.shape = _mlp(arch.n_inputs, arch.n_outputs, arch.width, arch.n_layers, act)
        else:
            self.transmission_members = nn.ModuleList(_mlp(arch.n_inputs, 2, arch.width, arch.n_layers, act)
                                                      for _ in range(arch.members))
            self.shape_members = nn.ModuleList(_mlp(arch.n_inputs, arch.n_outputs, arch.width, arch.n_layers, act)
                                               for _ in range(arch.members))

    def _members(self) -> list[tuple[nn.Module, ...]]:
        """The ensemble's members: (transmission net, shape net) or (joint net,)."""
        if hasattr(self, "joint_members"):
            return [(net,) for net in self.joint_members]
        if hasattr(self, "transmission"):
            return [(self.transmission, self.shape)]
        return list(zip(self.transmission_members, self.shape_members))

    def _logits(self, x: torch.Tensor, member):
        """Transmission logits (2) and shape logits (all bins) of one member."""
        if len(member) == 1:
            out = member[0](x)
            return out[..., :2], out[..., 2:]
        return member[0](x), member[1](x)

    def _factors(self, x: torch.Tensor, member):
        logit_t, z = self._logits(x, member)
        bx = self.bins_x
        return logit_t, torch.log_softmax(z[..., :bx], -1), torch.log_softmax(z[..., bx:], -1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Normalized outputs of normalized inputs ``x``; the likelihood decoders' averaged over the members."""
        if self.decoder == "bins":
            return self.layers(x)
        members = self._members()
        bx = self.bins_x
        out: Any = 0.0  # a tensor from the first member on
        for member in members:
            # softmax, not exp(log_softmax): the same histogram in fewer passes over the
            # rows, which a small net's inference time notices (docs/explanations/surrogate.md, "Inference")
            logit_t, z = self._logits(x, member)
            t = torch.sigmoid(logit_t)
            out = out + torch.cat([t[..., :1] * torch.softmax(z[..., :bx], -1),
                                   t[..., 1:] * torch.softmax(z[..., bx:], -1)], -1)
        return out / len(members)

    def loss(self, x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Training loss of a batch (``target`` in the net's output units).

        "bins": the MSE.  "factored" and "joint": per axis, the binomial cross-entropy of
        the in-range fraction plus the multinomial cross-entropy of the shape
        weighted by that fraction: together the negative log-likelihood of the
        ray counts per source ray (up to a constant); summed over the members
        of an ensemble, each of which learns the whole histogram.
        """
        if self.decoder == "bins":
            return nn.functional.mse_loss(self(x), target)
        bx = self.bins_x
        hx, hy = target[..., :bx], target[..., bx:]
        frac = torch.stack([hx.sum(-1), hy.sum(-1)], -1).clamp(0.0, 1.0)
        loss: Any = 0.0  # a tensor from the first member on
        for member in self._members():
            logit_t, log_sx, log_sy = self._factors(x, member)
            loss = loss + 2 * nn.functional.binary_cross_entropy_with_logits(logit_t, frac)
            loss = loss - ((hx * log_sx).sum(-1) + (hy * log_sy).sum(-1)).mean()
        return loss


@dataclass
class Normalization:
    """Min-max normalization of inputs (the table's box) and outputs (histogram values).

    ``out_low``/``out_span`` have one entry per output bin; a "global" output
    normalization simply repeats one value (keeps the loss proportional to the
    histogram MSE, which is what the finder compares); "none" is the identity
    (the likelihood decoders' outputs are histograms already).
    """

    in_low: np.ndarray
    in_span: np.ndarray
    out_low: np.ndarray
    out_span: np.ndarray
    mode: str = "global"

    @classmethod
    def fit(cls, table: ParameterTable, hist: np.ndarray, mode: str = "global",
            chamber: bool = False) -> Normalization:
        """``chamber``: the inputs end with the focus chamber's x, y, z (its box)."""
        hist = np.asarray(hist, dtype=np.float64)
        if mode == "global":
            lo = np.full(hist.shape[1], hist.min())
            hi = np.full(hist.shape[1], hist.max())
        elif mode == "per-bin":
            lo, hi = hist.min(axis=0), hist.max(axis=0)
        elif mode == "none":  # the likelihood decoders predict histograms directly
            lo, hi = np.zeros(hist.shape[1]), np.ones(hist.shape[1])
        else:
            raise InputError(f"output normalization must be 'global', 'per-bin' or 'none', got {mode!r}")
        span = np.where(hi - lo > 0, hi - lo, 1.0)
        in_low, in_span = table.low.copy(), table.span.copy()
        if chamber:
            in_low, in_span = np.concatenate([in_low, CHAMBER_LOW]), np.concatenate([in_span, CHAMBER_HIGH - CHAMBER_LOW])
        return cls(in_low, in_span, lo, span, mode)

    def to_dict(self) -> dict:
        """The normalization as plain lists, the form :meth:`from_dict` reads (stored in a checkpoint)."""
        return {"in_low": self.in_low.tolist(), "in_span": self.in_span.tolist(),
                "out_low": self.out_low.tolist(), "out_span": self.out_span.tolist(), "mode": self.mode}

    @classmethod
    def from_dict(cls, d: Mapping) -> Normalization:
        """The normalization :meth:`to_dict` gave (``mode`` "global" where it is missing)."""
        return cls(np.asarray(d["in_low"], float), np.asarray(d["in_span"], float),
                   np.asarray(d["out_low"], float), np.asarray(d["out_span"], float), d.get("mode", "global"))


# --------------------------------------------------------------------------- #
# the model artifact
# --------------------------------------------------------------------------- #
@dataclass
class Surrogate:
    """Trained network + the context it is valid in.

    Attributes
    ----------
    net : SurrogateNet
    arch : Architecture
    norm : Normalization
    table : dict
        Fingerprint of the parameter table (``ParameterTable.fingerprint()``).
    histogram : dict
        ``HistogramSpec.fingerprint()``.
    provenance : dict
        Data the model was trained on (store, samples, rays, draw scheme, twin version).
    metrics : dict
        Test metrics (MSE in histogram units) and training history summary.
    training : dict
        Training options used.
    """

    net: SurrogateNet
    arch: Architecture
    norm: Normalization
    table: dict
    histogram: dict
    provenance: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    training: dict = field(default_factory=dict)

    @classmethod
    def new(cls, arch: Architecture, norm: Normalization, table: ParameterTable = METRIXS,
            hist: HistogramSpec | None = None, **kw) -> Surrogate:
        """An untrained surrogate of ``arch`` for ``table`` and ``hist``; InputError if they do not fit together."""
        hist = hist or HistogramSpec()
        if arch.n_inputs not in (len(table), len(table) + len(CHAMBER_INPUTS)) \
                or arch.n_outputs != hist.bins_x + hist.bins_y or len(norm.in_low) != arch.n_inputs:
            raise InputError(f"architecture {arch} does not fit {len(table)} parameters (and the chamber's "
                             f"{len(CHAMBER_INPUTS)}) and {hist.bins_x}+{hist.bins_y} bins")
        return cls(SurrogateNet(arch), arch, norm, table.fingerprint(), hist.fingerprint(), **kw)

    @property
    def chamber(self) -> bool:
        """Whether the focus chamber's x, y, z are inputs (after the table's parameters)."""
        return self.arch.n_inputs == len(self.table["names"]) + len(CHAMBER_INPUTS)

    @property
    def inputs(self) -> list[str]:
        """The inputs' names, in order."""
        return list(self.table["names"]) + (list(CHAMBER_INPUTS) if self.chamber else [])

    # -- inference --------------------------------------------------------------
    @property
    def device(self) -> torch.device:
        """The device the network's weights are on."""
        return next(self.net.parameters()).device

    def to(self, device) -> Surrogate:
        """Move the network to ``device``; returns the surrogate itself."""
        self.net.to(device)
        return self

    def _norm_tensors(self, device, dtype):
        key = (str(device), dtype)
        cache = getattr(self, "_cache", None)
        if cache is None or cache[0] != key:
            t = lambda a: torch.as_tensor(a, device=device, dtype=dtype)  # noqa: E731
            cache = (key, t(self.norm.in_low), t(self.norm.in_span), t(self.norm.out_low), t(self.norm.out_span))
            self._cache = cache
        return cache[1:]

    def predict(self, params, *, chamber=None, normalized: bool = False, chunk_size: int | None = None, device=None,
                clamp: bool = True):
        """Histograms for a batch of parameter vectors.

        Parameters
        ----------
        params : array-like or Tensor, shape (..., n_params) or (..., n_inputs)
            Physical values in table order, or normalized coordinates (box ->
            [0, 1]) with ``normalized=True``.  Any leading shape, e.g.
            (candidates, configurations, 34).  A surrogate with the chamber's inputs
            (:attr:`chamber`) also takes the 34 and 3 together.
        chamber : array-like or Tensor, shape (3,) or (..., 3), optional
            The focus chamber's x, y, z in mm (physical, also with ``normalized``), for
            a surrogate with the chamber's inputs given the 34 alone (default: 0, its
            nominal place).  A surrogate without them refuses a chamber away from 0.
        chunk_size : int, optional
            Rows per forward pass (bounds memory; gradients flow through all chunks).
            Default: :data:`CPU_CHUNK_ROWS` on a CPU, 65536 elsewhere.
        device : str or torch.device, optional
            Where to compute (default: the model's device).  A tensor result
            stays there.
        clamp : bool
            Clamp outputs at 0 (histograms are non-negative).

        Returns
        -------
        Tensor or ndarray, shape (..., bins_x + bins_y)
            x bins then y bins, fraction of source rays per bin.  A Tensor
            input gives a Tensor (differentiable w.r.t. the input); anything
            else gives a NumPy array.
        """
        as_numpy = not isinstance(params, torch.Tensor)
        dev = torch.device(device) if device is not None else self.device
        if dev != self.device:
            self.net.to(dev)
        x = torch.as_tensor(np.asarray(params, dtype=np.float32) if as_numpy else params)
        n_table = len(self.table["names"])
        if x.shape[-1] not in (n_table, self.arch.n_inputs):
            raise InputError(f"expected parameter vectors of length {n_table}"
                             + (f" or {self.arch.n_inputs} (with the chamber's x, y, z)" if self.chamber else "")
                             + f" (table order), got shape {tuple(x.shape)}")
        dtype = next(self.net.parameters()).dtype
        x = x.to(device=dev, dtype=dtype)
        in_low, in_span, out_low, out_span = self._norm_tensors(dev, dtype)
        if x.shape[-1] == n_table and self.chamber:
            ch = torch.zeros(3, dtype=dtype, device=dev) if chamber is None else \
                torch.as_tensor(chamber, dtype=dtype).to(dev)
            if normalized:  # the chamber is given in mm: onto the box like the parameters
                ch = (ch - in_low[n_table:]) / in_span[n_table:]
            x = torch.cat([x, ch.expand(*x.shape[:-1], 3)], -1)
        elif chamber is not None and not self.chamber and bool(torch.as_tensor(chamber).ne(0).any()):
            raise InputError("this surrogate was trained without the focus chamber's inputs: it knows the "
                             "chamber at its nominal place only")
        lead = x.shape[:-1]
        x = x.reshape(-1, x.shape[-1])
        if not normalized:
            x = (x - in_low) / in_span
        x = self._as_trained(x)
        chunk_size = chunk_size or (CPU_CHUNK_ROWS if dev.type == "cpu" else 65536)
        # a likelihood decoder's outputs are the histograms themselves (transmission x softmax:
        # never negative) and its normalization is the identity, so the de-normalization and the
        # clamp would be passes over every row that change no bit
        bare = self.arch.decoder in LIKELIHOOD_DECODERS and self.norm.mode == "none"
        outs = []
        with torch.no_grad() if as_numpy else contextlib.nullcontext():
            for i in range(0, max(x.shape[0], 1), chunk_size):
                y = self.net(x[i:i + chunk_size])
                if not bare:
                    y = y * out_span + out_low
                    y = y.clamp_min(0.0) if clamp else y
                outs.append(y)
        y = torch.cat(outs) if len(outs) > 1 else outs[0]  # the loop runs at least once (also for 0 rows)
        y = y.reshape(*lead, self.arch.n_outputs)
        return y.detach().cpu().numpy() if as_numpy else y

    @property
    def source_mirrored(self) -> bool:
        """Trained on data traced with RAYX's mirrored source frame (see twin.SOURCE_FRAME)."""
        return self.provenance.get("source_frame") == "mirrored"

    def _as_trained(self, x):
        """Normalized inputs as the network saw them in training.

        A network trained with the mirrored source frame saw a source offset +t as -t: its four
        source inputs are reflected in their (symmetric) boxes, so that it answers for the twin
        as it is now.
        """
        if not self.source_mirrored:
            return x
        cols = [i for i, n in enumerate(self.table["names"]) if n.startswith("U41_318eV.")]
        if not cols:
            return x
        x = x.clone()
        x[:, cols] = 1.0 - x[:, cols]
        return x

    def split(self, hist):
        """(..., 100) -> x part (..., bins_x), y part (..., bins_y)."""
        bx = self.histogram["bins_x"]
        return hist[..., :bx], hist[..., bx:]

    # -- persistence --------------------------------------------------------------
    def metadata(self) -> dict:
        """The checkpoint's metadata: architecture, inputs, table, histogram, normalization, provenance, metrics."""
        n_par = sum(p.numel() for p in self.net.parameters())
        return {"format": FORMAT, "arch": self.arch.__dict__, "n_weights": int(n_par), "inputs": self.inputs,
                "table": self.table, "table_version": _table_version(self.table),
                "histogram": self.histogram, "normalization": self.norm.to_dict(),
                # a model that does not say otherwise was made with the twin as it is now
                "provenance": {"source_frame": SOURCE_FRAME, **self.provenance},
                "metrics": self.metrics, "training": self.training}

    def save(self, path: str | os.PathLike, *, metadata_json: bool = True) -> Path:
        """Write the checkpoint atomically (and ``<name>.json`` with the metadata)."""
        path = Path(path)
        state = {k: v.detach().cpu().contiguous() for k, v in self.net.state_dict().items()}
        meta = self.metadata()
        meta["weights_sha256"] = _weights_digest(state)
        buf = io.BytesIO()
        torch.save({"meta": json.dumps(meta), "state_dict": state}, buf)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_bytes(buf.getvalue())
        os.replace(tmp, path)
        if metadata_json:
            meta_out = {k: v for k, v in meta.items() if k != "normalization"}
            path.with_suffix(".json").write_text(json.dumps(meta_out, indent=2) + "\n")
        return path


def _weights_digest(state: Mapping[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for k in sorted(state):
        h.update(k.encode())
        h.update(state[k].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _table_version(fp: Mapping) -> str:
    return hashlib.sha256(json.dumps(dict(fp), sort_keys=True).encode()).hexdigest()[:12]


def default_checkpoint(name: str = "default") -> Path:
    """A checkpoint shipped with the package (:data:`SHIPPED`: "default" or "fast")."""
    return Path(str(resources.files("bluesky_offsets") / "data" / SHIPPED[name]))


def resolve_checkpoint(path: str | os.PathLike | None) -> Path:
    """A checkpoint's file: a path, or a shipped name ("default", "fast") where no such file is here.

    ``None`` gives the default checkpoint.
    """
    if path is None:
        return default_checkpoint()
    if str(path) in SHIPPED and not Path(path).exists():
        return default_checkpoint(str(path))
    return Path(path)


def read_metadata(path: str | os.PathLike) -> dict:
    """Metadata of a checkpoint, without building the network."""
    return _read(Path(path))[0]


def _read(path: Path) -> tuple[dict, dict]:
    if not path.exists():
        raise SurrogateError(f"surrogate checkpoint {path} does not exist")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # zip reader / unpickler errors of truncated or foreign files
        raise SurrogateError(f"surrogate checkpoint {path} is truncated or corrupt "
                             f"({type(exc).__name__}: {str(exc).splitlines()[0][:200]})") from None
    if not isinstance(blob, dict) or "meta" not in blob or "state_dict" not in blob:
        raise SurrogateError(f"{path} is not a bluesky-offsets surrogate checkpoint")
    try:
        meta = json.loads(blob["meta"])
    except (TypeError, json.JSONDecodeError) as exc:
        raise SurrogateError(f"surrogate checkpoint {path}: metadata unreadable ({exc})") from None
    if meta.get("format") != FORMAT:
        raise SurrogateError(f"{path}: unsupported checkpoint format {meta.get('format')!r} (expected {FORMAT})")
    return meta, blob["state_dict"]


def load(path: str | os.PathLike | None = None, *, table: ParameterTable = METRIXS,
         hist: HistogramSpec | None = None, device=None) -> Surrogate:
    """Load a checkpoint after checking it fits ``table`` and ``hist``.

    ``path`` is a path, or a shipped checkpoint by name: "default" (the default) or "fast".

    Raises
    ------
    SurrogateError
        Missing, truncated or corrupt file; parameter table or histogram spec
        mismatch (the message names what differs).
    """
    path = resolve_checkpoint(path)
    hist = hist or HistogramSpec()
    meta, state = _read(path)
    problems = table.diff(meta.get("table", {}))
    if problems:
        raise SurrogateError(f"surrogate checkpoint {path} was trained on a different parameter table "
                             f"than the current one ({table.name} {table.version}): {'; '.join(problems)}")
    want = hist.fingerprint()
    got = meta.get("histogram", {})
    hdiff = [f"{k}: checkpoint {got.get(k)!r}, current {want[k]!r}" for k in want if got.get(k) != want[k]]
    if hdiff:
        raise SurrogateError(f"surrogate checkpoint {path} uses a different histogram spec: {'; '.join(hdiff)}")
    if _weights_digest(state) != meta.get("weights_sha256"):
        raise SurrogateError(f"surrogate checkpoint {path} is corrupt: weights do not match their checksum")
    try:
        arch = Architecture(**meta["arch"])
        norm = Normalization.from_dict(meta["normalization"])
        net = SurrogateNet(arch)
        net.load_state_dict(state, strict=True)
    except Exception as exc:
        raise SurrogateError(f"surrogate checkpoint {path} is inconsistent ({type(exc).__name__}: {exc})") from None
    net.eval()
    provenance = dict(meta.get("provenance", {}))
    # a checkpoint that records no source frame predates the record: its data was traced mirrored
    provenance.setdefault("source_frame", "mirrored")
    model = Surrogate(net, arch, norm, meta["table"], meta["histogram"], provenance,
                      meta.get("metrics", {}), meta.get("training", {}))
    if device is not None:
        model.to(device)
    return model
