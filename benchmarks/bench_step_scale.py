"""How large a step-scale error each motor could have and still hide in a finished demo's frames.

A motor that moves (1 + s) times what it is told stands, at frame f, ``s (c_f - c_0)`` away from
where the twin puts it (``c_0``: anywhere; the rest is a constant, which the motor's offset takes).
On the frames the analysis fitted, at the calibrated model (``OUT/calibration.json``), with every
offset and the fitted effects free, the twin's exact Jacobian gives each motor's scale column
(its offset's column times the frame's normalized distance from the frames' mean) and the
information in it: σ(s) per motor, the others free.  One Jacobian squared (the information of its
own rays included): the σ are, if anything, too small.

    bluesky-offsets demo --seed 3 --out D/out --store D/store
    python benchmarks/bench_step_scale.py D [--json FILE]     # the result: benchmarks/results/step_scale.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("demo", type=Path, help="the folder holding the demo's out/ and store/")
    p.add_argument("--json", type=Path, default=None,
                   help="write the σ per motor here (default: benchmarks/results/raw/step_scale.json)")
    args = p.parse_args(argv)

    from bluesky_offsets.model import diagnosis as D
    from bluesky_offsets.model.export import load_calibration
    from bluesky_offsets.model.fit import engine_for, information
    from bluesky_offsets.physics.parameters import METRIXS
    from bluesky_offsets.store import open_store

    s = json.loads((args.demo / "out" / "summary.json").read_text())
    with open_store(args.demo / "store") as store:
        m = store.load_measurement(s["uids"]["measurement"], table=METRIXS)
    meas = m.for_analysis(table=METRIXS)
    idx = m.metadata.get("analysed_configurations")
    if idx is not None:
        meas = meas.subset(np.asarray(idx, dtype=int))
    state = load_calibration(args.demo / "out" / "calibration.json").state
    o = D.DESIGNED_FIT
    info = information(meas, state, engine_for(meas, o), o)
    G, rows = info.jacobian, info.rows
    motors = [i for i, q in enumerate(METRIXS) if q.motorized]
    dist = (meas.configurations - meas.configurations.mean(0)) / METRIXS.span  # normalized, per frame
    scale = G[:, motors] * dist[rows][:, motors]
    Ga = np.concatenate([G, scale], 1)
    ridge = np.r_[info.ridge, np.zeros(len(motors))]  # no prior on a scale
    F = Ga.T @ Ga + np.diag(ridge)
    d = np.sqrt(np.clip(np.diag(F), 1e-300, None))
    cov = np.linalg.pinv(F / np.outer(d, d), rcond=1e-12) / np.outer(d, d)
    sig = np.sqrt(np.clip(np.diag(cov)[G.shape[1]:], 0, None))
    spread = dist[:, motors].std(0)
    order = np.argsort(sig)
    print(f"{meas.n} frames; χ²/dof at the calibration {info.chi2_reduced:.2f}; σ of a step-scale error, the "
          f"offsets and {', '.join(state.effects) or 'no effects'} free:")
    for k in order:
        print(f"  {METRIXS.names[motors[k]]:34s} σ(s) {100 * sig[k]:8.2f} %   frames' spread "
              f"{spread[k]:.3f} of the range")
    print(f"median σ(s) {100 * np.median(sig):.1f} %, smallest {100 * sig[order[0]]:.2f} % "
          f"({METRIXS.names[motors[order[0]]]})")
    if args.json is None:  # the σ per motor beside the result
        from results import raw_path
        args.json = raw_path("step_scale.json")
    args.json.write_text(json.dumps({"machine": machine(), "demo": str(args.demo), "frames": meas.n,
                                     "sigma": {METRIXS.names[motors[k]]: float(sig[k]) for k in order},
                                     "spread": {METRIXS.names[motors[k]]: float(spread[k]) for k in order}},
                                    indent=1))
    write([(METRIXS.names[motors[k]], sig[k], spread[k]) for k in order], meas.n, info.chi2_reduced, state, args)
    return 0


def write(rows: list, frames: int, chi2: float, state, args) -> None:
    """The result ``step_scale``: σ(s) per motor, smallest first."""
    from render import section
    from results import Table, write_result
    table = Table("σ of a step-scale error per motor, the others free:",
                  ["motor", "σ(s)", "frames' spread (of the range)"],
                  [[name, f"{100 * sig:.2f} %", f"{spread:.3g}"] for name, sig, spread in rows], align=["l", "r", "r"])
    result = write_result(
        "step_scale", title="Step-scale errors that could hide (issue 52)", tables=[table], data=[str(args.json)],
        summary=f"How large a step-scale error each motor could have and still hide in a finished demo's {frames} "
                "analysed frames: a motor moving (1 + s) times what it is told shifts each frame by s times its "
                "distance from the others; σ(s) per motor from the twin's exact Jacobian at the calibration "
                f"(χ²/dof {chi2:.2f} there), every offset and {', '.join(state.effects) or 'no effect'} free.",
        notes=["One Jacobian squared (the information of its own rays included): the σ are, if anything, too small.",
               f"The demo: {args.demo}."])
    print(section(result))


if __name__ == "__main__":
    raise SystemExit(main())
