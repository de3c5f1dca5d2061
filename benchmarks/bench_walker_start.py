"""Why does the smart walker get trapped on some seeds? Its start, not its steps.

The paper's walker starts from the best of m = 1e6 uniform candidates; on this CPU
the benchmark affords m = 256.  This probe runs, on one seed of the paper's problem
(shipped surrogate, surrogate observations):

* the walker as specified with ``--m`` candidates (``--selection plus|comma``) for
  ``--iterations``;
* with ``--screen S``: a diagnostic that is *not* the paper's walker — the best of
  S uniform candidates as the start, then steps of m = 256 — to separate the start
  from the walk.

    python benchmarks/bench_walker_start.py --seed 9 --m 1024 --iterations 60
    python benchmarks/bench_walker_start.py --seed 9 --screen 16384 --iterations 400

Prints the best MSE every 100 iterations and at the end (1 torch thread); the result:
``benchmarks/results/walker_start.json``.
"""

from __future__ import annotations

import argparse
import time

import torch


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=9)
    ap.add_argument("--m", type=int, default=256, help="walker candidates per iteration")
    ap.add_argument("--iterations", type=int, default=400)
    ap.add_argument("--selection", choices=("plus", "comma"), default="plus")
    ap.add_argument("--screen", type=int, default=0, help="diagnostic: start from the best of this many")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    from bluesky_offsets.offsets import finder as F

    model = F.load_forward_model(None)
    problem = F.make_problem(model, seed=args.seed)
    t0 = time.perf_counter()
    if not args.screen:
        r = F.find_offsets(problem, model, "smart-walker", F.Budget(evaluations=args.m * (args.iterations + 1)),
                           seed=args.seed, progress=False, threads=1, candidates=args.m, selection=args.selection)
        print(f"seed {args.seed}: walker m={args.m} {args.selection}, {r.evaluations} evaluations: "
              f"MSE {r.loss:.3e} (start {r.history['loss'][0]:.3e}), parameter RMSE "
              f"{r.parameter_rmse(problem.true_offsets):.3f}, {time.perf_counter() - t0:.0f} s")
        write(args, [[f"the walker as specified (selection={args.selection}; start {r.history['loss'][0]:.3e})",
                      args.m, args.iterations, f"{r.evaluations:,}", f"{r.loss:.3e}"]])
        return
    obj = F.Objective(problem, model)
    gen = torch.Generator().manual_seed(args.seed)
    x = F._uniform(args.screen, problem.n_parameters, obj.limit, gen, obj)
    loss = obj(x)
    best, best_loss = x[int(torch.argmin(loss))].clone(), float(loss.min())
    print(f"seed {args.seed}: best of {args.screen} uniform: {best_loss:.3e}")
    rows = [[f"start: the best of {args.screen:,} uniform candidates", None, 0, f"{obj.evaluations:,}",
             f"{best_loss:.3e}"]]
    for it in range(1, args.iterations + 1):
        c = (best[None] + F.PAPER_STEP * F._normal((args.m, problem.n_parameters), gen, obj)).clamp_(
            -obj.limit, obj.limit)
        lc = obj(c)
        i = int(torch.argmin(lc))
        if float(lc[i]) < best_loss:
            best, best_loss = c[i].clone(), float(lc[i])
        if it % 100 == 0 or it == args.iterations:
            print(f"  iteration {it}: {best_loss:.3e} after {obj.evaluations} evaluations, "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
            rows.append(["then the walker's steps", args.m, it, f"{obj.evaluations:,}", f"{best_loss:.3e}"])
    write(args, rows)


def write(args, rows: list) -> None:
    """The result ``walker_start``: the best MSE where the run reported it."""
    from render import section
    from results import Table, write_result
    table = Table(f"Seed {args.seed}, one torch thread:", ["run", "m", "iterations", "evaluations", "best MSE"], rows,
                  align=["l", "r", "r", "r", "r"])
    result = write_result(
        "walker_start", title="Offset finder: where the walker starts", tables=[table],
        summary=f"Seed {args.seed} of the paper's problem (shipped surrogate, surrogate observations): the smart "
                "walker as specified, or, as a diagnostic that is not the paper's walker, started from the best of "
                "many uniform candidates and then stepped with m candidates — to separate the start from the walk. "
                "The paper's walker starts from the best of m = 1e6.")
    print(section(result))


if __name__ == "__main__":
    main()
