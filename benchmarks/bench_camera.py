"""The calibration read through the focus chamber's camera against its histogram PVs, on the same draws.

Each draw runs the README's main job (``bluesky-offsets demo --seed S``) twice: on the
simulator's ray-count histograms and with ``--detector camera`` (the areaDetector's frames:
dark frames, the gain by photon transfer where the measurement was brightest, frames reduced to
the same histograms with the camera's own noise beside them).  Scored as in ``bench_motors.py``.

    python benchmarks/bench_camera.py [--seeds 0 3] [--out DIR] [-- extra demo options]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_motors import compare  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 3])
    p.add_argument("--out", type=Path, default=None, help="keep (and resume) each run's output here")
    p.add_argument("extra", nargs="*", help="more demo options (after --)")
    compare(p.parse_args(), "camera", {d: ["--detector", d] for d in ("histograms", "camera")})


if __name__ == "__main__":
    main()
