"""What the design's choice costs against the ceiling: the pool's size, the rays a candidate, the criterion.

For hidden offsets drawn as ``bench_design_ceiling.py`` draws them, the beam found by the real
search and a pool of 400 candidate settings (:func:`bluesky_offsets.design.candidate_settings`),
every candidate's information at the truth judged on 16,000 rays none of the choices used; then
the frames after the search chosen in several ways: greedy D-optimal (each frame's matrix clipped
to its positive part, as the design does) from the 400 or from 120 of them, on 16,000 or 1,600
rays a candidate (the design's own: :class:`~bluesky_offsets.design.DesignOptions` ``candidates``
and ``rays``); greedy D-optimal on the unbiased matrices (only the running sum clipped); a random
choice among the 120; and D-optimal among the 400 whose beam stays on the screen under a spread of
the offsets (intensity less ``confidence`` times its linearized σ above the design's floor, as the
design keeps the beam on the screen under its posterior) for the truth's spread and the table's
prior.  Each batch: the offsets it determines and the least RMSE / truth RMS
(:func:`bench_design_ceiling.least_rmse`), at the demo's 5,000 photons and 2,000 model rays a frame.

    python benchmarks/bench_design_choice.py --seeds 0 [--fraction 0.05]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bluesky_offsets.design import DesignOptions, candidate_settings, classes, frame_information  # noqa: E402
from bluesky_offsets.design import predicted_sigma, prior_precision, select  # noqa: E402
from bluesky_offsets.design.choose import PRIOR_SIGMA  # noqa: E402
from bluesky_offsets.design.information import positive_part  # noqa: E402
from bluesky_offsets.offsets.beam_search import acceptance  # noqa: E402
from bluesky_offsets.physics.engine import TorchEngine  # noqa: E402
from bluesky_offsets.physics.parameters import METRIXS as T  # noqa: E402
from bluesky_offsets.physics.twin import Twin  # noqa: E402
from sim_iocs.truth import default_start  # noqa: E402

POOL, SUBSET, JUDGE_RAYS = 400, 120, 16_000
PHOTONS, MODEL_RAYS = 5_000, 2_000


def unbiased_greedy(fisher: np.ndarray, precision: np.ndarray, k: int, allowed: np.ndarray) -> list[int]:
    """Greedy D-optimal on unclipped matrices: each gain the log-determinant of the running sum's positive part."""
    P, ok, out = precision.copy(), allowed.copy(), []
    eps = 1e-12 * np.eye(len(P))
    for _ in range(min(k, int(ok.sum()))):
        base = np.linalg.slogdet(P)[1]
        gains = np.full(len(fisher), -np.inf)
        for i in np.flatnonzero(ok):
            gains[i] = np.linalg.slogdet(positive_part(P + fisher[i]) + eps)[1] - base
        i = int(np.argmax(gains))
        out.append(i)
        ok[i] = False
        P = positive_part(P + fisher[i]) + eps
    return out


def one(seed: int, fraction: float) -> list[dict]:
    from bench_design import Beamline, find_beam
    from bench_design_ceiling import least_rmse
    truth = np.random.default_rng([seed, 17]).uniform(-fraction, fraction, len(T))
    beam = find_beam(Beamline(truth, {}, 5000, seed), default_start())
    acc = acceptance(Twin(TorchEngine()), beam.configuration, open_slits=False)
    opts = DesignOptions(seed=seed)
    cfg, screen = candidate_settings(beam.configuration[None], POOL, np.random.default_rng([seed, 5]),
                                     acceptance=acc, options=opts)
    engine = TorchEngine(options={"common_rays": False})

    def info(rays: int, s: int, psd: bool):
        return frame_information(engine, cfg, truth, photons=PHOTONS, model_rays=MODEL_RAYS, rays=rays,
                                 screen=screen, seed=s, psd=psd)

    judged_info = info(JUDGE_RAYS, seed + 1_000_003, False)
    judge, bright = judged_info.fisher, judged_info.intensity >= opts.floor
    subset = np.zeros(POOL, bool)
    subset[np.random.default_rng(seed).choice(POOL, SUBSET, replace=False)] = True
    k = 60 - beam.frames
    box, spread = prior_precision(len(T)), fraction / np.sqrt(3.0)
    # each candidate's unbiased matrix, and its positive part as the design clips it: one trace per ray count
    unbiased = {rays: info(rays, seed, False) for rays in (JUDGE_RAYS, opts.rays)}
    clipped = {rays: positive_part(u.fisher) for rays, u in unbiased.items()}
    rows = []

    def judged(indices, how: str, allowed: np.ndarray) -> None:
        F = positive_part(judge[indices].sum(0))
        rows.append({"seed": seed, "how": how, "frames": len(indices), "search_frames": beam.frames,
                     "candidates": int(allowed.sum()),
                     "determined": classes(predicted_sigma(box + F)).count("determined"),
                     "least_rmse": least_rmse(F, fraction)})
        print(f"seed {seed}, {how} ({len(indices)} frames of {int(allowed.sum())} allowed): "
              f"{rows[-1]['determined']} determined, least RMSE / truth RMS "
              f"{rows[-1]['least_rmse']:.3f}", flush=True)

    for rays in (JUDGE_RAYS, opts.rays):
        allowed = bright
        judged(select(clipped[rays], box, k, allowed=allowed).indices, f"D-optimal, {POOL} candidates, {rays:,} rays",
               allowed)
        allowed = bright & subset
        judged(select(clipped[rays], box, k, allowed=allowed).indices,
               f"D-optimal, {SUBSET} candidates, {rays:,} rays", allowed)
        judged(unbiased_greedy(unbiased[rays].fisher, box, k, allowed),
               f"D-optimal unclipped, {SUBSET} candidates, {rays:,} rays", allowed)
    design = unbiased[opts.rays]  # the design's own rays a candidate
    for name, sigma in (("the truth's spread", spread), ("the table's prior", PRIOR_SIGMA)):
        allowed = design.intensity - opts.confidence * design.intensity_sigma(np.eye(len(T)) * sigma ** 2) \
            >= opts.floor
        judged(select(clipped[opts.rays], box, k, allowed=allowed).indices,
               f"D-optimal, {POOL} candidates, {opts.rays:,} rays, lit within {opts.confidence:g}σ of {name}", allowed)
    allowed = bright & subset
    pick = np.random.default_rng(seed + 9).choice(np.flatnonzero(allowed), k, replace=False)
    judged(list(pick), f"random, {SUBSET} candidates", allowed)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--fraction", type=float, default=0.05)
    a = p.parse_args()
    rows = [r for seed in a.seeds for r in one(seed, a.fraction)]
    from render import section
    from results import Table, write_result
    seeds = list(dict.fromkeys(r["seed"] for r in rows))
    hows = list(dict.fromkeys(r["how"] for r in rows))
    by = {(r["how"], r["seed"]): r for r in rows}
    table = Table("Each batch: frames chosen of the candidates allowed; offsets determined; the least RMSE / truth RMS:",
                  ["choice", *(f"seed {s}" for s in seeds)],
                  [[h, *(f"{by[h, s]['frames']} of {by[h, s]['candidates']}; {by[h, s]['determined']}; "
                         f"{by[h, s]['least_rmse']:.2f}" for s in seeds)] for h in hows],
                  align=["l"] + ["r"] * len(seeds))
    result = write_result(
        "design_choice", title="The designed measurement: what the choice costs", tables=[table],
        notes=["Frames designed after the beam search's: "
               f"{', '.join(str(60 - by[hows[0], s]['search_frames']) for s in seeds)}."],
        summary=f"For hidden offsets within ±{100 * a.fraction:g} %, the beam found by the real search and {POOL} "
                "candidate settings drawn as the design draws them, every candidate judged at the truth on "
                f"{JUDGE_RAYS:,} rays none of the choices used, at {PHOTONS:,} photons and {MODEL_RAYS:,} model "
                "rays a frame: the batch chosen from the whole pool or from the design's share of it, on the "
                "design's rays a candidate or ten times more, by the design's criterion, without its per-frame "
                "clipping, or at random.")
    print(section(result))


if __name__ == "__main__":
    main()
