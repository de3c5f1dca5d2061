"""Two hidden effects the analysis missed: the greedy forward step against joint fits of the pair.

The analysis adds one effect at a time, each fitted with the offsets from where the offsets-only
fit ended (``model.diagnosis.diagnose``).  For a finished demo with two hidden effects this fits,
on the configurations the analysis fitted and with its own fit options (``diagnosis.FIT``, one ray
draw, or ``diagnosis.SCAN``):

* the hidden truth (the IOC's offsets and effects) as it stands, and refitted from there;
* each hidden effect alone and the pair jointly, from each of the effects' starting values
  (``diagnosis.starting_values``), from the analysis's offsets-only fit and from the bare twin.

It prints χ²/dof on the fit's rays (the same rays for every line) and each fitted value with its
σ and its pull against the hidden value: whether the joint fit reaches the truth's basin, or
whether the offsets' path stops it as it stops the greedy step; the lines also go to
``benchmarks/results/pair_fit.json``.

    bluesky-offsets demo --seed 17 --effect thermal_bump_m1:height=330 \\
        --effect source_divergence:divergence=-0.25 --no-optimize --out D/out --store D/runs
    python benchmarks/bench_pair_fit.py D [--options fit|scan]
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("demo", type=Path, help="the folder holding the demo's out/ and runs/")
    p.add_argument("--options", choices=("fit", "scan"), default="fit",
                   help="the analysis's refit options (one ray draw) or its candidate fits'")
    args = p.parse_args(argv)

    from bluesky_offsets.model import diagnosis as D
    from bluesky_offsets.model.fit import engine_for, fit
    from bluesky_offsets.model.state import ModelState
    from bluesky_offsets.physics import effects as E
    from bluesky_offsets.physics.parameters import METRIXS
    from bluesky_offsets.store import open_store
    from plans.diagnose import load_results, restore_refinement

    s = json.loads((args.demo / "out" / "summary.json").read_text())
    hidden = {k: dict(v) for k, v in s["hidden_effects"].items()}
    if len(hidden) != 2:
        p.error(f"the demo hid {len(hidden)} effect(s); this compares a pair")
    with open_store(args.demo / "runs") as store:
        m = store.load_measurement(s["uids"]["measurement"], table=METRIXS)
        refined = restore_refinement(load_results(store, s["uids"]["refine_offsets"])).state
    meas = m.for_analysis(table=METRIXS)
    idx = m.metadata.get("analysed_configurations")
    if idx is not None:
        meas = meas.subset(np.asarray(idx, dtype=int))  # the configurations the analysis fitted
    o = D.FIT.replace(ray_draws=1) if args.options == "fit" else D.SCAN.replace(seed=D.SCAN.seed + 7919)
    engine = engine_for(meas, o)
    print(f"hidden: {hidden}; the analysis's verdict: {s['verdict']}")
    print(f"{meas.n} configurations, {args.options} options ({', '.join(f'{a} {k}' for a, k in o.stages)}, "
          f"{o.rays} rays)\n")

    lines = []

    def run(st: ModelState, label: str, options=o) -> None:
        t0 = time.perf_counter()
        f = fit(meas, st, engine, options)
        sig = f.effect_sigma()
        vals = "; ".join(f"{e}.{q} {v:.4g} ± {sig[e][q]:.2g}"
                         + (f" ({(v - hidden[e][q]) / sig[e][q]:+.1f}σ)" if e in hidden and sig[e][q] > 0 else "")
                         for e, d in f.state.effects.items() for q, v in d.items())
        print(f"{label:58s} χ²/dof {f.chi2_reduced:7.3f}  {vals or '-'}  ({time.perf_counter() - t0:.0f} s)",
              flush=True)
        lines.append([label, f"{f.chi2_reduced:.3f}", vals or "—", f"{time.perf_counter() - t0:.0f}"])

    truth = ModelState(np.array([s["hidden_offsets"][n] for n in METRIXS.names]), hidden, "truth")
    run(truth, "the hidden truth, as it stands", o.replace(stages=((o.stages[-1][0], 0),)))
    run(truth, "the hidden truth, refitted")
    a, b = hidden
    for start, base in (("offsets-only fit", refined), ("bare twin", ModelState(label="twin"))):
        run(base, f"{start}: offsets only")
        for name in (a, b):
            for v in D.starting_values(E.get(name)):
                run(base.with_effect(name, v), f"{start}: {name} {v}")
        for va, vb in itertools.product(D.starting_values(E.get(a)), D.starting_values(E.get(b))):
            run(base.with_effect(a, va).with_effect(b, vb), f"{start}: both {va} {vb}")
    write(lines, hidden, s["verdict"], meas.n, args.options)
    return 0


def write(lines: list, hidden: dict, verdict: str, n: int, options: str) -> None:
    """The result ``pair_fit``: every fit's χ²/dof and values, the pulls against the hidden ones."""
    from results import Table, write_result
    table = Table(f"Every fit on the analysis's {n} configurations ({options} options; the same rays for every line):",
                  ["start", "χ²/dof", "fitted (pull against the hidden value)", "s"], lines,
                  align=["l", "r", "l", "r"])
    write_result("pair_fit", title="Two hidden effects fitted jointly", tables=[table],
                 summary=f"A finished demo with two hidden effects ({hidden}; the analysis's verdict: {verdict}): "
                         "the hidden truth, each effect alone and the pair jointly, fitted from each of the effects' "
                         "starting values, from the analysis's offsets-only fit and from the bare twin — whether the "
                         "joint fit reaches the truth's basin, or whether the offsets' path stops it as it stops the "
                         "greedy forward step.")


if __name__ == "__main__":
    raise SystemExit(main())
