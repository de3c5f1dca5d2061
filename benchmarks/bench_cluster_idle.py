"""What an idle LocalCluster costs: Dask's defaults against the twin's (``physics.twin.QUIET_CLUSTER``).

The twin's workers sit idle through most of a demo (the IOC's RAYX worker between frames, the
analysis's workers between fits) while their event loops tick, their stacks are sampled and
their memory is polled; on two cores that CPU is taken from the fits beside them.

    python benchmarks/bench_cluster_idle.py [--workers 2] [--seconds 30]

Prints the CPU of this process (scheduler, nannies, client) and of each worker process over
``--seconds`` of idling, as a percentage of one core, for both settings, and writes
``benchmarks/results/cluster_idle.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time


def _measure(quiet: bool, workers: int, seconds: float) -> list[float]:
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
        return [100 * (y - x) / seconds for x, y in zip(a, b)]  # this process first, then its children
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
        print(json.dumps(_measure(a.one == "quiet", a.workers, a.seconds)), flush=True)
        return
    rows = []
    for which in ("defaults", "quiet"):  # each in a fresh process: no state carried over
        out = subprocess.run([sys.executable, __file__, "--one", which, "--workers", str(a.workers),
                              "--seconds", str(a.seconds)], check=True, stderr=subprocess.DEVNULL,
                             stdout=subprocess.PIPE, text=True).stdout
        share = json.loads(out.strip().splitlines()[-1])
        label = "the twin's (`QUIET_CLUSTER`)" if which == "quiet" else "Dask's defaults"
        rows.append([label, f"{sum(share):.1f} %", *(f"{x:.1f} %" for x in share)])
        print(f"{label}: total {sum(share):.1f} % of a core ({', '.join(f'{x:.1f}' for x in share)} %)", flush=True)
    write(rows, a)


def write(rows: list, a) -> None:
    """The result ``cluster_idle``: each setting's CPU, in all and per process."""
    from render import section
    from results import Table, write_result
    width = max(len(r) for r in rows)
    rows = [r + ["—"] * (width - len(r)) for r in rows]  # a process the other setting did not have
    others = [f"process {i}" for i in range(1, width - 2)]
    table = Table(f"{a.workers} workers, {a.seconds:g} s idle, as a share of one core (the processes: this one, "
                  "then its children):", ["settings", "total", "this process", *others], rows,
                  align=["l"] + ["r"] * (width - 1))
    result = write_result(
        "cluster_idle", title="An idle Dask cluster's CPU", tables=[table],
        summary="What an idle LocalCluster costs: the CPU of the client's process (scheduler, nannies) and of "
                "each process it started, as a share of one core, with Dask's defaults and with the twin's "
                "settings (`physics.twin.QUIET_CLUSTER`: a slower event-loop tick, no stack sampler in the "
                "workers, memory and the system polled less often). A demo runs two such clusters, idle most of "
                "the time, beside the fits on two cores.")
    print(section(result))


if __name__ == "__main__":
    main()
