"""What an idle LocalCluster costs: Dask's defaults against the twin's (``physics.twin.QUIET_CLUSTER``).

The twin's workers sit idle through most of a demo (the IOC's RAYX worker between frames, the
analysis's workers between fits) while their event loops tick, their stacks are sampled and
their memory is polled; on two cores that CPU is taken from the fits beside them.

    python benchmarks/bench_cluster_idle.py [--workers 2] [--seconds 30]

Prints the CPU of this process (scheduler, nannies, client) and of each worker process over
``--seconds`` of idling, as a percentage of one core, for both settings.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time


def _measure(quiet: bool, workers: int, seconds: float) -> str:
    import dask
    import psutil
    from distributed import Client, LocalCluster

    from bluesky_offsets.physics.twin import QUIET_CLUSTER
    with dask.config.set(QUIET_CLUSTER if quiet else {}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address="127.0.0.1:0", host="127.0.0.1")
    client = Client(cluster)
    try:
        time.sleep(5)  # started and settled
        procs = [psutil.Process()] + psutil.Process().children(recursive=True)

        def cpu():
            return [sum(p.cpu_times()[:2]) for p in procs]

        a = cpu()
        time.sleep(seconds)
        b = cpu()
        share = [100 * (y - x) / seconds for x, y in zip(a, b)]
        return (f"{'twin (QUIET_CLUSTER)' if quiet else 'Dask defaults':22s} total {sum(share):5.1f} % of a core "
                f"(this process {share[0]:.1f} %, the other {len(share) - 1} processes "
                f"{', '.join(f'{s:.1f}' for s in share[1:])} %)")
    finally:
        client.close()
        cluster.close()


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--one", choices=("defaults", "quiet"), help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.one:
        print(_measure(a.one == "quiet", a.workers, a.seconds), flush=True)
        return
    for which in ("defaults", "quiet"):  # each in a fresh process: no state carried over
        subprocess.run([sys.executable, __file__, "--one", which, "--workers", str(a.workers),
                        "--seconds", str(a.seconds)], check=True, stderr=subprocess.DEVNULL)


if __name__ == "__main__":
    main()
