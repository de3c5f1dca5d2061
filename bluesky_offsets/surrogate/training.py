"""Training the surrogate: the paper's recipe (Sec. 3.1) as the default, every choice an option.

Recipe: min-max normalized inputs and outputs, 7 linear layers with Mish,
Adam (lr 1e-4), ExponentialLR (gamma 0.999, stepped once per epoch), batch 32,
"good" samples (>= 10 rays on the screen) and "bad" ones shown 3:1, an
80/10/10 train/validation/test split, MSE loss on the normalized outputs.

A run directory holds ``state.pt`` (everything needed to resume: model,
optimizer, scheduler, RNG, history; written atomically every epoch),
``best.pt`` (the best model so far as a loadable surrogate checkpoint) and
``history.json``.  The best model by validation MSE is the result; training
stops early after ``patience`` epochs without improvement.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from bluesky_offsets.errors import InputError
from bluesky_offsets.streams import stream
from bluesky_offsets.surrogate.dataset import GOOD_MIN_RAYS, Dataset
from bluesky_offsets.physics.parameters import METRIXS, ParameterTable
from bluesky_offsets.surrogate.network import (ACTIVATIONS, DECODERS, LIKELIHOOD_DECODERS, Architecture,
                                               Normalization, Surrogate, _weights_digest)
from bluesky_offsets.physics.twin import HistogramSpec

log = logging.getLogger(__name__)


class TrainingError(RuntimeError):
    """Training cannot start or resume as asked."""


@dataclass
class TrainConfig:
    """Training options (defaults: the paper's recipe).

    Attributes
    ----------
    epochs : int
        Maximum epochs (paper: 300).
    batch_size : int
        Samples per optimizer step (paper: 32).
    lr : float
        Adam learning rate (paper: 1e-4).
    gamma : float
        ExponentialLR decay per epoch (paper: 0.999).
    good_min_rays : int
        Rays on the screen (full trace) for a sample to count as "good" (paper: 10).
    good_fraction : float
        Share of good samples in each epoch's stream (paper 3:1 -> 0.75); bad samples
        are drawn with replacement to fill the rest.  ``None``: plain shuffling.
    split : tuple
        Train/validation/test fractions (paper: 0.8/0.1/0.1), random by ``seed``.
    width, n_layers : int
        Network width and number of linear layers (paper: 7 layers; width not
        given there, 512 here).
    output_norm : str
        "global" (one min/max for all bins: the loss stays proportional to the
        histogram MSE) or "per-bin".  The likelihood decoders need none ("none").
    decoder : str
        "bins" (the paper: the net outputs the bins, MSE loss), "factored"
        (transmission x shape per axis, ray-count likelihood loss) or "joint" (the
        same from one net; see :class:`~bluesky_offsets.surrogate.network.Architecture`).
    members : int
        Ensemble size (factored and joint decoders only; 1: a single model).
    patience : int
        Early stop after this many epochs without a better validation MSE (0: never).
    min_delta : float
        Relative improvement of the validation MSE that counts as better.
    epoch_samples : int, optional
        Samples per epoch; default ``n_good_train / good_fraction``.
    device : str
        "auto" (CUDA when available), "cpu" or "cuda".
    seed : int
        Split, initialization and sampling seed.
    threads : int, optional
        torch CPU threads (default: torch's choice).
    max_minutes : float, optional
        Stop (cleanly, after an epoch) when this wall time is used up.
    init : str, optional
        Checkpoint to start from instead of random weights (fine-tuning on a grown
        dataset): its architecture and normalization must match these options.  With
        ``teacher``, an earlier student of the same teacher (a longer schedule).
    teacher : str, optional
        Distillation: train on this checkpoint's predictions at the training samples'
        inputs instead of their traced histograms (a smaller, faster net learns the larger
        one's smooth function, not the counting noise).  Validation, early stopping and the
        test metrics stay against the traced histograms.  The teacher must have been
        trained on the same dataset with the same split and seed (its test samples unseen).
    """

    epochs: int = 300
    batch_size: int = 32
    lr: float = 1e-4
    gamma: float = 0.999
    good_min_rays: int = GOOD_MIN_RAYS
    good_fraction: float | None = 0.75
    split: tuple[float, float, float] = (0.8, 0.1, 0.1)
    width: int = 512
    n_layers: int = 7
    output_norm: str = "global"
    decoder: str = "bins"
    members: int = 1
    activation: str = "mish"
    patience: int = 30
    min_delta: float = 0.0
    epoch_samples: int | None = None
    device: str = "auto"
    seed: int = 0
    threads: int | None = None
    max_minutes: float | None = None
    init: str | None = None
    teacher: str | None = None

    def __post_init__(self):
        self.split = tuple(float(s) for s in self.split)
        if len(self.split) != 3 or any(s < 0 for s in self.split) or not math.isclose(sum(self.split), 1.0):
            raise InputError(f"split must be three fractions summing to 1, got {self.split}")
        if self.good_fraction is not None and not 0 < self.good_fraction < 1:
            raise InputError(f"good_fraction must be in (0, 1), got {self.good_fraction}")
        for name in ("epochs", "batch_size", "width", "n_layers", "members"):
            if getattr(self, name) < 1:
                raise InputError(f"{name} must be positive")
        if self.threads is not None and self.threads < 1:
            raise InputError("threads must be positive (leave it out for torch's choice)")
        if self.max_minutes is not None and not self.max_minutes > 0:
            raise InputError("max_minutes must be positive (leave it out for no time budget)")
        if self.lr <= 0 or not 0 < self.gamma <= 1:
            raise InputError("lr must be > 0 and gamma in (0, 1]")
        if self.decoder not in DECODERS:
            raise InputError(f"decoder must be one of {DECODERS}, got {self.decoder!r}")
        if self.activation not in ACTIVATIONS:
            raise InputError(f"activation must be one of {', '.join(ACTIVATIONS)}, got {self.activation!r}")
        if self.members > 1 and self.decoder not in LIKELIHOOD_DECODERS:
            raise InputError("members > 1 (an ensemble) needs decoder 'factored' or 'joint'")
        if self.decoder in LIKELIHOOD_DECODERS:
            self.output_norm = "none"
        elif self.output_norm == "none":
            raise InputError("output_norm 'none' is only for the factored and joint decoders")
        if self.device not in ("auto", "cpu", "cuda"):
            raise InputError(f"device must be auto, cpu or cuda, got {self.device!r}")

    def to_dict(self) -> dict:
        """The options as plain data (``split`` a list), as a checkpoint records them."""
        d = asdict(self)
        d["split"] = list(self.split)
        return d

    def resolved_device(self) -> torch.device:
        """The torch device to train on: CUDA for "auto" where torch sees one, else the CPU."""
        if self.device == "auto":
            return torch.device("cuda" if torch.cuda.is_available() else "cpu")
        if self.device == "cuda" and not torch.cuda.is_available():
            raise TrainingError("device 'cuda' requested but torch sees no CUDA device")
        return torch.device(self.device)


# the keys that must agree to resume a run
_RESUME_KEYS = ("batch_size", "lr", "gamma", "good_min_rays", "good_fraction", "split", "width", "n_layers",
                "output_norm", "decoder", "members", "activation", "epoch_samples", "seed", "init", "teacher")


def split_indices(n: int, fractions, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random train/validation/test indices (sorted), reproducible by ``seed``."""
    perm = np.random.default_rng(seed).permutation(n)
    n_tr = int(round(fractions[0] * n))
    n_va = int(round(fractions[1] * n))
    return np.sort(perm[:n_tr]), np.sort(perm[n_tr:n_tr + n_va]), np.sort(perm[n_tr + n_va:])


def grown_split_indices(n: int, sizes, fractions, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The split of a store grown to ``n`` samples through the earlier sizes ``sizes`` (oldest first).

    A model fine-tuned (``init``) from one trained on the first ``sizes[-1]`` samples keeps
    their split, so it never trains on its predecessors' validation or test samples; each
    growth step ``k`` is split apart with ``seed + k``.  ``sizes=[m]`` after one growth step.
    """
    sizes = [int(m) for m in np.atleast_1d(sizes)] + [int(n)]
    if sizes[0] < 1 or any(b < a for a, b in zip(sizes, sizes[1:])):
        raise TrainingError(f"the starting model was trained on {sizes[-2]} samples; this store holds {n}")
    parts = [split_indices(sizes[0], fractions, seed)]
    for k, (a, b) in enumerate(zip(sizes, sizes[1:]), start=1):
        if b > a:
            parts.append(tuple(idx + a for idx in split_indices(b - a, fractions, seed + k)))
    train, val, test = (np.concatenate([p[i] for p in parts]).astype(int) for i in range(3))
    return train, val, test


def _grown_from(path: str, init_path: str) -> bool:
    """Whether dataset ``path`` begins with the samples of ``init_path`` (itself or a union)."""
    return path == init_path or path.startswith(init_path + " + ")


def _size_chain(init_prov: dict) -> list[int]:
    """Store sizes the chain of starting models was trained on, oldest first."""
    chain: list[int] = []
    p: dict | None = init_prov
    while p:
        chain.append(int(p["n_samples"]))
        p = p.get("init")
    return chain[::-1]


def epoch_order(good: np.ndarray, bad: np.ndarray, good_fraction: float | None, n_samples: int | None,
                rng: np.random.Generator) -> np.ndarray:
    """Sample indices of one epoch: good and bad shown ``good_fraction : 1 - good_fraction``.

    Every good sample appears (about) once per epoch; bad samples fill the rest,
    drawn without replacement while they last.
    """
    if good_fraction is None or len(good) == 0 or len(bad) == 0:
        allidx = np.concatenate([good, bad])
        n = n_samples or len(allidx)
        return rng.choice(allidx, size=n, replace=n > len(allidx))
    n = n_samples or int(math.ceil(len(good) / good_fraction))
    n_good = int(round(n * good_fraction))
    n_bad = n - n_good
    g = _draw(good, n_good, rng)
    b = _draw(bad, n_bad, rng)
    out = np.concatenate([g, b])
    rng.shuffle(out)
    return out


def _draw(pool: np.ndarray, n: int, rng) -> np.ndarray:
    reps = [rng.permutation(pool) for _ in range(n // len(pool))]
    reps.append(rng.choice(pool, size=n % len(pool), replace=False))
    return np.concatenate(reps)


def _metrics(model: Surrogate, x: torch.Tensor, y: torch.Tensor, n_hits: np.ndarray) -> dict:
    """MSE in histogram units (fraction of source rays), overall and on non-empty samples."""
    if len(x) == 0:
        return {"n": 0}
    with torch.no_grad():
        pred = model.predict(x, normalized=True)
        se = ((pred - y) ** 2).mean(dim=1).cpu().numpy()
    ne = n_hits > 0
    return {"n": int(len(se)), "mse": float(se.mean()),
            "mse_nonempty": float(se[ne].mean()) if ne.any() else float("nan"), "n_nonempty": int(ne.sum())}


def _save_atomic(obj, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _load_init(path: str, table: ParameterTable, hist: HistogramSpec) -> Surrogate:
    from bluesky_offsets.surrogate.network import load
    try:
        return load(path, table=table, hist=hist)
    except Exception as exc:
        raise TrainingError(f"cannot start from {path}: {exc}") from None


def _init_provenance(src: Surrogate, path: str) -> dict:
    keep = ("n_samples", "n_good", "n_rays", "dataset", "init")
    return {"path": str(path), **{k: src.provenance.get(k) for k in keep if k in src.provenance},
            "training": src.training}


def _same_teacher(recorded: dict, teacher: dict) -> bool:
    """Whether a student's recorded teacher is ``teacher``.

    Compared by the teacher's weights' digest, or, for a student recorded before the digest was
    kept, by the teacher's data and training options.
    """
    if "weights_sha256" in recorded:
        return recorded["weights_sha256"] == teacher["weights_sha256"]
    return bool(recorded) and all(recorded.get(k) == teacher.get(k) for k in ("dataset", "n_samples", "training"))


def _warm_start(model: Surrogate, src: Surrogate, path: str) -> None:
    # The normalization stays the new dataset's; for the likelihood decoders there is none,
    # for "bins" a changed min/max would silently rescale the start, so it must agree.
    if src.arch != model.arch:
        raise TrainingError(f"cannot start from {path}: its architecture {src.arch} differs from {model.arch}")
    if model.arch.decoder not in LIKELIHOOD_DECODERS and not (np.allclose(src.norm.out_low, model.norm.out_low)
                                                 and np.allclose(src.norm.out_span, model.norm.out_span)):
        raise TrainingError(f"cannot start from {path}: its output normalization differs from this dataset's")
    model.net.load_state_dict(src.net.state_dict())


@dataclass(frozen=True, kw_only=True)
class _Split:
    """The samples' split and the targets, the warm start's model and provenance, the teacher's provenance.

    The targets are the traced histograms, or a teacher's predictions at the training inputs.
    """

    tr: np.ndarray
    va: np.ndarray
    te: np.ndarray
    Y: np.ndarray
    init: Surrogate | None = None
    init_prov: dict | None = None
    teacher_prov: dict | None = None


def _split(data: Dataset, config: TrainConfig, table: ParameterTable, hist: HistogramSpec) -> _Split:
    """The split that keeps a warm start's or a teacher's validation and test samples out of training."""
    Y = data.hist.astype(np.float32)
    init_src = init_prov = None
    if config.init:
        init_src = _load_init(config.init, table, hist)
        init_prov = _init_provenance(init_src, config.init)
        it = init_prov["training"]
        if list(it.get("split", [])) != list(config.split) or it.get("seed") != config.seed:
            raise TrainingError(f"cannot start from {config.init}: it was trained with split {it.get('split')} "
                                f"and seed {it.get('seed')}, this run has {list(config.split)} and {config.seed}")
        # the same store (grown), or that store followed by others (dataset.concat): either way
        # the starting model's samples come first, in its order, and keep its split
        if not _grown_from(str(data.meta.get("path")), str(init_prov.get("dataset"))):
            raise TrainingError(f"cannot start from {config.init}: it was trained on {init_prov.get('dataset')}, "
                                f"not {data.meta.get('path')} (its validation/test samples would leak)")
        tr, va, te = grown_split_indices(len(data), _size_chain(init_prov), config.split, config.seed)
    else:
        tr, va, te = split_indices(len(data), config.split, config.seed)
    if not config.teacher:
        return _Split(tr=tr, va=va, te=te, Y=Y, init=init_src, init_prov=init_prov)
    teacher = _load_init(config.teacher, table, hist)
    teacher_prov = _init_provenance(teacher, config.teacher)
    teacher_prov["weights_sha256"] = _weights_digest(teacher.net.state_dict())
    if init_src is not None and not _same_teacher(init_src.provenance.get("teacher") or {}, teacher_prov):
        # a student goes on from an earlier student of the same teacher (a new learning-rate
        # schedule), never from a model that learned other targets
        raise TrainingError(f"cannot start a student of {config.teacher} from {config.init}: it is not a "
                            "student of that teacher (the same weights)")
    tt = teacher_prov["training"]
    if (teacher_prov.get("dataset") != data.meta.get("path") or teacher_prov.get("n_samples") != len(data)
            or list(tt.get("split", [])) != list(config.split)
            or tt.get("seed") != config.seed):
        raise TrainingError(f"cannot distil from {config.teacher}: it was trained on {teacher_prov.get('dataset')} "
                            f"({teacher_prov.get('n_samples')} samples, split {tt.get('split')}, seed "
                            f"{tt.get('seed')}), this run has {data.meta.get('path')} ({len(data)}, "
                            f"{list(config.split)}, {config.seed}): its validation/test samples would leak")
    # the teacher's split is the one to keep (its chain of grown stores, if any)
    earlier = _size_chain(teacher_prov)[:-1]
    tr, va, te = (grown_split_indices(len(data), earlier, config.split, config.seed) if earlier
                  else split_indices(len(data), config.split, config.seed))
    # the teacher's histograms at the training inputs replace the traced ones there
    Y = Y.copy()
    Y[tr] = teacher.predict(data.inputs[tr]).astype(np.float32)
    return _Split(tr=tr, va=va, te=te, Y=Y, init=init_src, init_prov=init_prov, teacher_prov=teacher_prov)


def _provenance(data: Dataset, config: TrainConfig, split: _Split, chamber: bool) -> dict:
    """Where the model's samples came from: the dataset, its split, its traces' settings."""
    s = data.meta["settings"]
    out = {"dataset": data.meta.get("path"), "n_samples": len(data),
           "n_train": len(split.tr), "n_val": len(split.va), "n_test": len(split.te),
           "n_good": int((data.n_hits >= config.good_min_rays).sum()),
           "n_nonempty": int((data.n_hits > 0).sum()),
           "n_rays": s["n_rays"], "scheme": s["scheme"],
           "chamber": chamber, "engine": s.get("engine", "rayx"),
           "scheme_text": data.meta.get("scheme"),
           "dataset_seed": ([p["seed"] for p in data.meta["parts"]] if data.meta.get("parts") else s["seed"]),
           "parts": data.meta.get("parts"),
           "twin": data.meta.get("engine"), "source_frame": data.meta.get("source_frame", "mirrored"),
           "table_version": data.meta.get("table_version"),
           "dataset_complete": data.meta.get("complete"),
           "generation_cpu_s": data.meta.get("stats", {}).get("cpu_s")}
    if split.init_prov:
        out["init"] = split.init_prov
    if split.teacher_prov:
        out["teacher"] = split.teacher_prov
    return out


@dataclass
class _Progress:
    """Where a training run stands: its history, best validation MSE, epochs without improvement."""

    history: list[dict]
    best_val: float = math.inf
    stale: int = 0
    epoch: int = 0
    elapsed: float = 0.0


def _resume(state_path: Path, run_dir: Path, config: TrainConfig, provenance: dict, n_samples: int, model: Surrogate,
            opt, sched, rng: np.random.Generator, device) -> _Progress:
    """The run's state from ``state.pt``, when it exists and the dataset and options agree."""
    try:
        st = torch.load(state_path, map_location=device, weights_only=False)
    except Exception as exc:
        raise TrainingError(f"cannot resume from {state_path} ({type(exc).__name__}: {exc}); "
                            "remove it to start over") from None
    old = st["config"]
    diff = [k for k in _RESUME_KEYS
            if json.dumps(old.get(k, getattr(TrainConfig, k, None))) != json.dumps(config.to_dict().get(k))]
    if st["dataset"] != {"path": provenance["dataset"], "n_samples": n_samples}:
        diff.append(f"dataset ({st['dataset']} vs {provenance['dataset']}, {n_samples} samples)")
    if diff:
        raise TrainingError(f"{run_dir} holds a run with different {', '.join(diff)}; "
                            "use another run directory or the same options")
    model.net.load_state_dict(st["model"])
    opt.load_state_dict(st["optimizer"])
    sched.load_state_dict(st["scheduler"])
    rng.bit_generator.state = st["rng"]
    torch.set_rng_state(st["torch_rng"])
    log.info("resuming %s at epoch %d", run_dir, st["epoch"])
    return _Progress(history=st["history"], best_val=st["best_val"], stale=st["stale"], epoch=st["epoch"],
                     elapsed=st.get("elapsed", 0.0))


def _one_epoch(model: Surrogate, opt, X: torch.Tensor, Yn: torch.Tensor, order: np.ndarray, config: TrainConfig,
               label: str, progress: bool) -> float:
    """One pass over ``order`` in batches; returns the running training loss."""
    from bluesky_offsets.progress import bar as progress_bar

    model.net.train()
    order_t = torch.as_tensor(order, device=X.device)
    n_batches = int(math.ceil(len(order) / config.batch_size))
    running = 0.0
    bar = progress_bar(range(n_batches), desc=label, unit="batch", leave=False, disable=not progress,
                       mininterval=1.0)
    for b in bar:
        idx = order_t[b * config.batch_size:(b + 1) * config.batch_size]
        loss = model.net.loss(X[idx], Yn[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        running = 0.98 * running + 0.02 * loss.item() if b else loss.item()
        if b % 200 == 0:
            bar.set_postfix(loss=f"{running:.3e}", refresh=False)
    bar.close()
    return running


def train(data: Dataset, run_dir: str | os.PathLike, config: TrainConfig | None = None, *,
          resume: bool = True, progress: bool = True, table: ParameterTable = METRIXS,
          hist: HistogramSpec | None = None) -> Surrogate:
    """Train a surrogate on ``data``; returns the best model (by validation MSE) with test metrics.

    With ``resume`` (default) a run directory holding ``state.pt`` continues
    where it stopped, provided the dataset and the options agree.
    """
    from bluesky_offsets.progress import bar as progress_bar

    config = config or TrainConfig()
    hist = hist or HistogramSpec()
    run_dir = Path(run_dir)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TrainingError(f"cannot use {run_dir} as the run directory: {exc.strerror or exc}") from None
    device = config.resolved_device()
    if config.threads:
        torch.set_num_threads(config.threads)
    if len(data) < 10:
        raise TrainingError(f"dataset has only {len(data)} samples; need at least 10")

    split = _split(data, config, table, hist)
    tr, va, te = split.tr, split.va, split.te
    chamber = data.chamber is not None
    norm = Normalization.fit(table, split.Y[tr], config.output_norm, chamber=chamber)
    table.validate(data.params)
    X = torch.as_tensor((data.inputs - norm.in_low) / norm.in_span, dtype=torch.float32, device=device)
    Yn = torch.as_tensor((split.Y - norm.out_low) / norm.out_span, dtype=torch.float32, device=device)
    Yt = torch.as_tensor(data.hist.astype(np.float32), device=device)  # metrics: always the traced histograms
    good_tr = tr[data.n_hits[tr] >= config.good_min_rays]
    bad_tr = tr[data.n_hits[tr] < config.good_min_rays]

    arch = Architecture(X.shape[1], hist.bins_x + hist.bins_y, config.width, config.n_layers, config.decoder, hist.bins_x,
                        config.members, config.activation)
    provenance = _provenance(data, config, split, chamber)
    torch.manual_seed(config.seed)
    model = Surrogate.new(arch, norm, table, hist, provenance=provenance, training=config.to_dict())
    if split.init is not None:
        assert config.init is not None  # split.init was loaded from it
        _warm_start(model, split.init, config.init)
    model.to(device)
    opt = torch.optim.Adam(model.net.parameters(), lr=config.lr)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=config.gamma)
    rng = np.random.default_rng(stream(config.seed, "training.epoch_order"))
    state_path, best_path = run_dir / "state.pt", run_dir / "best.pt"
    run = (_resume(state_path, run_dir, config, provenance, len(data), model, opt, sched, rng, device)
           if resume and state_path.exists() else _Progress(history=[]))

    t_start = time.perf_counter() - run.elapsed
    epochs = progress_bar(range(run.epoch, config.epochs), desc="epochs", unit="epoch", disable=not progress,
                          initial=run.epoch, total=config.epochs)
    for epoch in epochs:
        t_ep = time.perf_counter()
        order = epoch_order(good_tr, bad_tr, config.good_fraction, config.epoch_samples, rng)
        running = _one_epoch(model, opt, X, Yn, order, config, f"epoch {epoch + 1}", progress)
        sched.step()
        model.net.eval()
        val = _metrics(model, X[va], Yt[va], data.n_hits[va])
        run.history.append({"epoch": epoch + 1, "train_loss": running, "val_mse": val.get("mse"),
                            "val_mse_nonempty": val.get("mse_nonempty"), "lr": opt.param_groups[0]["lr"],
                            "seconds": time.perf_counter() - t_ep, "samples": len(order)})
        if val.get("mse", math.inf) < run.best_val * (1.0 - config.min_delta):
            run.best_val, run.stale = val["mse"], 0
            model.metrics = {"val": val, "epoch": epoch + 1}
            model.save(best_path, metadata_json=False)
        else:
            run.stale += 1
        run.elapsed = time.perf_counter() - t_start
        _save_atomic({"model": model.net.state_dict(), "optimizer": opt.state_dict(),
                      "scheduler": sched.state_dict(), "rng": rng.bit_generator.state,
                      "torch_rng": torch.get_rng_state(), "history": run.history, "best_val": run.best_val,
                      "stale": run.stale, "epoch": epoch + 1, "elapsed": run.elapsed, "config": config.to_dict(),
                      "dataset": {"path": provenance["dataset"], "n_samples": len(data)}}, state_path)
        (run_dir / "history.json").write_text(json.dumps(run.history, indent=1))
        epochs.set_postfix(loss=f"{running:.3e}", val_mse=f"{val.get('mse', float('nan')):.3e}",
                           val_ne=f"{val.get('mse_nonempty', float('nan')):.3e}", refresh=False)
        if config.patience and run.stale >= config.patience:
            log.info("early stop after epoch %d (%d epochs without improvement)", epoch + 1, run.stale)
            break
        if config.max_minutes is not None and run.elapsed > 60 * config.max_minutes:
            log.info("time budget of %.1f min used up after epoch %d", config.max_minutes, epoch + 1)
            break
    epochs.close()
    return _best(best_path, run_dir, run.history, X, Yt, data, va, te, table, hist, device)


def _best(best_path: Path, run_dir: Path, history: list[dict], X: torch.Tensor, Yt: torch.Tensor, data: Dataset,
          va: np.ndarray, te: np.ndarray, table: ParameterTable, hist: HistogramSpec, device) -> Surrogate:
    """The best epoch's model with its test and validation metrics, saved again with them."""
    from bluesky_offsets.surrogate.network import load
    if not best_path.exists():
        raise TrainingError(f"no epoch finished in {run_dir}")
    best = load(best_path, table=table, hist=hist, device=device)
    best.net.eval()
    test = _metrics(best, X[te], Yt[te], data.n_hits[te])
    val = _metrics(best, X[va], Yt[va], data.n_hits[va])
    n_trained = sum(h["samples"] for h in history)
    t_train = sum(h["seconds"] for h in history)
    best.metrics = {"test": test, "val": val, "best_epoch": best.metrics.get("epoch"),
                    "epochs_run": len(history), "train_seconds": round(t_train, 1),
                    "train_samples_per_s": round(n_trained / t_train, 1) if t_train else None,
                    "device": str(device), "torch": torch.__version__,
                    "first_train_loss": history[0]["train_loss"] if history else None,
                    "last_train_loss": history[-1]["train_loss"] if history else None,
                    "units": "MSE over all 100 bins, histogram values as fraction of source rays"}
    best.save(best_path)
    return best

