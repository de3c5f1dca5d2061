"""``bluesky-offsets dataset | train | surrogate`` sub-commands (thin layer)."""

from __future__ import annotations

import argparse
import json
import logging
import os

from bluesky_offsets.commands.cli import CliError, output_file


# --------------------------------------------------------------------------- #
# dataset
# --------------------------------------------------------------------------- #
def _prepare_tracing(args) -> None:
    if not logging.getLogger().isEnabledFor(logging.INFO) and args.scheduler != "inline":
        import distributed  # noqa: F401  (configures its loggers on import; quiet them after)
        logging.getLogger("distributed").setLevel(logging.WARNING)
    import signal

    def _term(signum, frame):  # SIGTERM: stop like Ctrl-C (committed blocks are kept)
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _term)
    if args.scheduler == "inline":
        # many small traces in one process: OpenMP threads cost more than they give (~10x for 300 rays)
        os.environ.setdefault("OMP_NUM_THREADS", "1")


def _settings_from_args(args):
    from bluesky_offsets.surrogate.dataset import DrawScheme, GenerationSettings
    try:
        scheme = DrawScheme(screen_rays=args.screen_rays, screen_min_hits=args.screen_min_hits,
                            keep_fraction=args.keep_fraction)
        return GenerationSettings(n_rays=args.rays, seed=args.seed, block_size=args.block_size, scheme=scheme,
                                  engine=args.engine, chamber=args.chamber)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _cmd_dataset_generate(args) -> int:
    from bluesky_offsets.surrogate.dataset import DatasetError, generate
    if args.samples < 1:
        raise CliError("--samples must be positive")
    if args.workers is not None and args.workers < 1:
        raise CliError("--workers must be positive (leave it out for all cores)")
    if args.rayx_check < 0:
        raise CliError("--rayx-check must be 0 (no check) or more")
    settings = _settings_from_args(args)
    _prepare_tracing(args)
    try:
        stats = generate(args.out, args.samples, settings, scheduler=args.scheduler, n_workers=args.workers,
                         progress=not args.no_progress, rayx_check=args.rayx_check)
    except DatasetError as exc:
        raise CliError(str(exc)) from None
    if args.json:
        print(json.dumps(stats, indent=2))
    else:
        print(f"dataset {args.out}: {stats['n_samples']} samples from {stats['n_draws']} draws "
              f"({stats['n_nonempty']} non-empty, {stats['n_good']} good >= 10 rays, "
              f"{stats['n_stratum1']} kept despite failing the screen), {stats['cpu_s']:.0f} CPU-s")
        if "rayx_check" in stats:
            print(_check_line(stats["rayx_check"]))
    return 0


def _check_line(c: dict) -> str:
    lo, hi = c["mse_ratio_ci95"]
    hlo, hhi = c["hits_ratio_ci95"]
    verdict = "consistent with RAYX" if c["consistent"] else "NOT consistent with RAYX"
    return (f"RAYX check on {c['n_checked']} non-empty samples at {c['n_rays']} rays: MSE(store, RAYX) / "
            f"MSE(RAYX, RAYX') = {c['mse_ratio']:.2f} [{lo:.2f}, {hi:.2f}], screen hits {c['hits_ratio']:.3f} "
            f"[{hlo:.3f}, {hhi:.3f}] of RAYX's (95 %): {verdict}")


def _cmd_dataset_check(args) -> int:
    from bluesky_offsets.surrogate.dataset import DatasetError, check_against_rayx
    if args.samples < 1:
        raise CliError("--samples must be positive")
    _prepare_tracing(args)
    try:
        out = check_against_rayx(args.path, args.samples, seed=args.seed, scheduler=args.scheduler,
                                 n_workers=args.workers, progress=not args.no_progress)
    except DatasetError as exc:
        raise CliError(str(exc)) from None
    print(json.dumps(out, indent=2) if args.json else _check_line(out))
    return 0 if out["consistent"] else 1


def _cmd_dataset_info(args) -> int:
    from bluesky_offsets.surrogate.dataset import DatasetError, info
    try:
        out = info(args.path)
    except DatasetError as exc:
        raise CliError(str(exc)) from None
    print(json.dumps(out, indent=2))
    return 0


def _add_generation_options(p: argparse.ArgumentParser, *, rays: int = 10_000) -> None:
    from bluesky_offsets.surrogate.dataset import DrawScheme
    d = DrawScheme()
    p.add_argument("--rays", type=int, default=rays, help=f"source rays per full trace (default {rays})")
    p.add_argument("--screen-rays", type=int, default=d.screen_rays,
                   help=f"rays of the pre-screen trace, 0 = no screen (default {d.screen_rays})")
    p.add_argument("--screen-min-hits", type=int, default=d.screen_min_hits,
                   help=f"screen hits to pass (default {d.screen_min_hits})")
    p.add_argument("--keep-fraction", type=float, default=d.keep_fraction,
                   help=f"share of screened-out draws traced anyway, weight 1/f (default {d.keep_fraction})")
    p.add_argument("--block-size", type=int, default=256, help="draws per Dask task (default 256)")
    p.add_argument("--engine", choices=["rayx", "torch"], default="rayx",
                   help="the twin that traces: RAYX (the reference) draw by draw, or the torch engine a "
                        "block at once (default rayx)")
    p.add_argument("--chamber", action="store_true",
                   help="draw the focus chamber's x, y, z too (the surrogate's inputs: 34 + 3)")
    p.add_argument("--scheduler", default=None,
                   help="Dask scheduler address (tcp://host:8786); 'inline' = no Dask; default: LocalCluster")
    p.add_argument("--workers", type=int, default=None, help="LocalCluster workers (default: all cores)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


# --------------------------------------------------------------------------- #
# train
# --------------------------------------------------------------------------- #
def _cmd_train(args) -> int:
    from bluesky_offsets.surrogate.dataset import DatasetError, load_many
    from bluesky_offsets.surrogate.network import SurrogateError
    from bluesky_offsets.surrogate.training import TrainConfig, TrainingError, train
    try:
        config = TrainConfig(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, gamma=args.gamma,
                             good_min_rays=args.good_min_rays,
                             good_fraction=None if args.good_fraction <= 0 else args.good_fraction,
                             split=tuple(args.split), width=args.width, n_layers=args.layers,
                             output_norm=args.output_norm, decoder=args.decoder, members=args.members,
                             activation=args.activation,
                             patience=args.patience, min_delta=args.min_delta,
                             epoch_samples=args.epoch_samples, device=args.device, seed=args.seed,
                             threads=args.threads, max_minutes=args.max_minutes, init=args.init,
                             teacher=args.teacher)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    try:
        data = load_many(args.dataset, allow_partial=args.allow_partial)
        model = train(data, args.run_dir, config, resume=not args.restart, progress=not args.no_progress)
    except (DatasetError, TrainingError, SurrogateError) as exc:
        raise CliError(str(exc)) from None
    if args.out:
        model.save(args.out)
    m = model.metrics
    if args.json:
        print(json.dumps(m, indent=2))
    else:
        t = m["test"]
        print(f"best epoch {m['best_epoch']} of {m['epochs_run']}: test MSE {t['mse']:.3e} "
              f"({t['n']} samples), non-empty {t['mse_nonempty']:.3e} ({t['n_nonempty']}); "
              f"train loss {m['first_train_loss']:.3e} -> {m['last_train_loss']:.3e}; "
              f"{m['train_samples_per_s']} samples/s on {m['device']}")
        print(f"checkpoint: {args.out or (args.run_dir + '/best.pt')}")
    return 0


# --------------------------------------------------------------------------- #
# surrogate
# --------------------------------------------------------------------------- #
def _load_model(path):
    from bluesky_offsets.surrogate.network import SurrogateError, load
    try:
        return load(path)
    except SurrogateError as exc:
        raise CliError(str(exc)) from None


def _cmd_surrogate_info(args) -> int:
    from bluesky_offsets.surrogate.network import SurrogateError, read_metadata, resolve_checkpoint
    path = resolve_checkpoint(args.checkpoint)
    _load_model(path)  # full check: table, histogram spec, checksum
    try:
        meta = read_metadata(path)
    except SurrogateError as exc:
        raise CliError(str(exc)) from None
    meta.pop("normalization", None)
    print(json.dumps({"path": str(path), **meta}, indent=2))
    return 0


def _cmd_surrogate_evaluate(args) -> int:
    from bluesky_offsets.surrogate.dataset import DrawScheme
    from bluesky_offsets.surrogate.evaluate import evaluate, plot_comparison
    model = _load_model(args.checkpoint)
    if args.plot:
        output_file(args.plot, "--plot")
    _prepare_tracing(args)
    scheme = None
    if args.screen_rays is not None or args.keep_fraction is not None:
        base = DrawScheme(**model.provenance["scheme"]) if model.provenance.get("scheme") else DrawScheme()
        try:
            scheme = DrawScheme(screen_rays=base.screen_rays if args.screen_rays is None else args.screen_rays,
                                screen_min_hits=base.screen_min_hits,
                                keep_fraction=base.keep_fraction if args.keep_fraction is None
                                else args.keep_fraction)
        except ValueError as exc:
            raise CliError(str(exc)) from None
    if args.samples < 1 or args.min_nonempty < 0 or args.min_nonempty > args.samples:
        raise CliError("need --samples >= 1 and 0 <= --min-nonempty <= --samples")
    if args.uniform < 0:
        raise CliError("--uniform must be 0 or more")
    res = evaluate(model, n_samples=args.samples, min_nonempty=args.min_nonempty, n_uniform=args.uniform,
                   n_rays=args.rays, scheme=scheme, seed=args.seed, scheduler=args.scheduler,
                   n_workers=args.workers, progress=not args.no_progress, keep_data=bool(args.plot))
    data = res.pop("_data", None)
    if args.plot and data:
        plot_comparison(model, data["screened"], args.plot)
        res["plot"] = args.plot
    from bluesky_offsets.surrogate.network import resolve_checkpoint
    res["checkpoint"]["path"] = str(resolve_checkpoint(args.checkpoint))
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    print(f"fresh held-out set (seed {res['seed']}, {res['n_rays']} rays): {res['n_samples']} samples, "
          f"{res['n_nonempty']} non-empty; drawn as: {res['screened']['drawing']}")
    for name in ("screened", "uniform"):
        if name not in res:
            continue
        views = [("as drawn", res[name]["as_drawn"])]
        if "uniform_weighted" in res[name]:
            views.append(("re-weighted to the uniform box", res[name]["uniform_weighted"]))
        for label, s in views:
            print(f"[{name}, {label}] n={s['n']} (non-empty {s['n_nonempty']})")
            print(f"  surrogate MSE    overall {s['mse']:.3e}   non-empty {s['mse_nonempty']:.3e}")
            print(f"  twin repeat MSE  overall {s['noise_mse']:.3e}   non-empty {s['noise_mse_nonempty']:.3e}")
            print(f"  ratio            overall {s['ratio']:.2f}        non-empty {s['ratio_nonempty']:.2f}")
            print(f"  (empty-histogram baseline: overall {s['baseline_zero_mse']:.3e}   "
                  f"non-empty {s['baseline_zero_mse_nonempty']:.3e})")
    if args.plot:
        print(f"plot written to {args.plot}")
    return 0


def add_cli(sub) -> None:
    """Register ``dataset``, ``train`` and ``surrogate`` sub-commands."""
    _add_dataset(sub)
    _add_train(sub)
    _add_surrogate(sub)


def _add_dataset(sub) -> None:
    p = sub.add_parser("dataset", help="twin datasets for the surrogate (Zarr, Dask, resumable)")
    dsub = p.add_subparsers(dest="dataset_command", required=True)
    g = dsub.add_parser("generate", help="generate, resume or extend a dataset store",
                        description="Draw uniform parameter vectors, pre-screen them at few rays, trace "
                                    "the accepted ones with the twin and store them in a Zarr store. "
                                    "Killed and run again with the same arguments, it resumes.")
    g.add_argument("out", help="output store (directory)")
    g.add_argument("--samples", type=int, required=True, help="number of samples the store must hold")
    g.add_argument("--seed", type=int, default=0, help="base seed of all draws (default 0)")
    _add_generation_options(g)
    g.add_argument("--rayx-check", type=int, default=64, metavar="N",
                   help="after another engine than RAYX: trace N of the store's non-empty samples again "
                        "with RAYX and compare in distribution (default 64; 0: no check)")
    g.add_argument("--json", action="store_true", help="print the statistics as JSON")
    g.set_defaults(func=_cmd_dataset_generate)
    k = dsub.add_parser("check", help="trace a random slice of a store again with RAYX (in distribution)",
                        description="Trace N random non-empty samples of a store again with RAYX (same inputs, "
                                    "two fresh seeds) and compare the store's histograms with RAYX's repeat "
                                    "noise. Exits 1 when they are not consistent.")
    k.add_argument("path")
    k.add_argument("--samples", type=int, default=256, help="non-empty samples to check (default 256)")
    k.add_argument("--seed", type=int, default=0, help="seed of the slice and the RAYX traces (default 0)")
    k.add_argument("--scheduler", default=None, help="Dask scheduler address, or 'inline'")
    k.add_argument("--workers", type=int, default=None, help="LocalCluster workers")
    k.add_argument("--no-progress", action="store_true")
    k.add_argument("--json", action="store_true")
    k.set_defaults(func=_cmd_dataset_check)
    i = dsub.add_parser("info", help="settings, progress and statistics of a store")
    i.add_argument("path")
    i.set_defaults(func=_cmd_dataset_info)


def _add_train(sub) -> None:
    from bluesky_offsets.surrogate.network import DECODERS
    from bluesky_offsets.surrogate.training import TrainConfig
    c = TrainConfig()
    t = sub.add_parser("train", help="train the surrogate on a dataset store (paper recipe by default)",
                       description="Train the surrogate (min-max normalization, 7 linear layers with Mish, "
                                   "Adam, ExponentialLR, good:bad 3:1, 80/10/10 split). Checkpoints every "
                                   "epoch into RUN_DIR and resumes from there.")
    t.add_argument("dataset", nargs="+",
                   help="dataset store(s) from `bluesky-offsets dataset generate`; several: their union, "
                        "in this order (same ray count, scheme and chamber; distinct seeds)")
    t.add_argument("run_dir", help="run directory (state.pt, best.pt, history.json)")
    t.add_argument("--out", help="also write the final checkpoint here (plus .json metadata)")
    t.add_argument("--epochs", type=int, default=c.epochs, help=f"maximum epochs (default {c.epochs})")
    t.add_argument("--batch-size", type=int, default=c.batch_size, help=f"default {c.batch_size}")
    t.add_argument("--lr", type=float, default=c.lr, help=f"Adam learning rate (default {c.lr})")
    t.add_argument("--gamma", type=float, default=c.gamma, help=f"ExponentialLR decay per epoch (default {c.gamma})")
    t.add_argument("--good-min-rays", type=int, default=c.good_min_rays,
                   help=f"rays for a 'good' sample (default {c.good_min_rays})")
    t.add_argument("--good-fraction", type=float, default=c.good_fraction,
                   help="share of good samples shown (default 0.75 = 3:1; <= 0: plain shuffling)")
    t.add_argument("--split", type=float, nargs=3, default=list(c.split), metavar=("TRAIN", "VAL", "TEST"))
    t.add_argument("--width", type=int, default=c.width, help=f"hidden width (default {c.width})")
    t.add_argument("--layers", type=int, default=c.n_layers, help=f"linear layers (default {c.n_layers})")
    t.add_argument("--activation", choices=["mish", "silu"], default=c.activation,
                   help=f"between the layers: Mish (the paper's) or SiLU, 2.3x cheaper on a CPU (default {c.activation})")
    t.add_argument("--output-norm", choices=["global", "per-bin"], default=c.output_norm)
    t.add_argument("--decoder", choices=list(DECODERS), default=c.decoder,
                   help="bins: the paper's net (MSE on the bins); factored: transmission x shape per axis "
                        "trained on the ray-count likelihood, two nets; joint: the same from one net, "
                        "half the cost (default %(default)s)")
    t.add_argument("--members", type=int, default=c.members,
                   help="ensemble size, factored and joint decoders only (default %(default)s)")
    t.add_argument("--patience", type=int, default=c.patience, help="early-stop patience in epochs (0: off)")
    t.add_argument("--min-delta", type=float, default=0.0, help="relative val-MSE gain that counts (default 0)")
    t.add_argument("--epoch-samples", type=int, default=None, help="samples per epoch (default: good/0.75)")
    t.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    t.add_argument("--seed", type=int, default=c.seed)
    t.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    t.add_argument("--max-minutes", type=float, default=None, help="stop after this wall time (after an epoch)")
    t.add_argument("--init", default=None, metavar="CHECKPOINT",
                   help="start from this checkpoint's weights (fine-tune on a grown dataset; same architecture)")
    t.add_argument("--teacher", default=None, metavar="CHECKPOINT",
                   help="distil: learn this checkpoint's predictions at the training inputs (trained on the same "
                        "data and split); validation and test stay against the traced histograms")
    t.add_argument("--restart", action="store_true", help="ignore RUN_DIR/state.pt and start over")
    t.add_argument("--allow-partial", action="store_true", help="train on an unfinished store's committed rows")
    t.add_argument("--no-progress", action="store_true")
    t.add_argument("--json", action="store_true", help="print the metrics as JSON")
    t.set_defaults(func=_cmd_train)


def _add_surrogate(sub) -> None:
    s = sub.add_parser("surrogate", help="inspect and evaluate surrogate checkpoints")
    ssub = s.add_subparsers(dest="surrogate_command", required=True)
    e = ssub.add_parser("evaluate", help="compare a surrogate with fresh twin traces and the twin's repeat noise",
                        description="Draw a fresh held-out set with the training data's recorded scheme, "
                                    "trace every configuration twice with the twin, and report the "
                                    "surrogate's MSE next to the twin's repeat-noise MSE.")
    e.add_argument("--checkpoint", help="checkpoint: a path or a shipped name, default or fast (default: default)")
    e.add_argument("--samples", type=int, default=500, help="at least this many samples (default 500)")
    e.add_argument("--min-nonempty", type=int, default=100, help="at least this many non-empty (default 100)")
    e.add_argument("--uniform", type=int, default=0, help="also evaluate on N plain uniform draws")
    e.add_argument("--rays", type=int, default=None, help="rays per trace (default: the training ray count)")
    e.add_argument("--screen-rays", type=int, default=None, help="override the recorded pre-screen rays")
    e.add_argument("--keep-fraction", type=float, default=None, help="override the recorded keep fraction")
    e.add_argument("--seed", type=int, default=None, help="seed of the fresh draws (default: random)")
    e.add_argument("--scheduler", default=None, help="Dask scheduler address, or 'inline'")
    e.add_argument("--workers", type=int, default=None, help="LocalCluster workers")
    e.add_argument("--plot", metavar="FILE.png", help="paper Fig. 4 style comparison plot")
    e.add_argument("--no-progress", action="store_true")
    e.add_argument("--json", action="store_true", help="machine-readable output")
    e.set_defaults(func=_cmd_surrogate_evaluate)
    i = ssub.add_parser("info", help="metadata of a checkpoint (after checking it loads)")
    i.add_argument("--checkpoint", help="checkpoint: a path or a shipped name, default or fast (default: default)")
    i.set_defaults(func=_cmd_surrogate_info)
