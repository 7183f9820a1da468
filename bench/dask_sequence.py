"""A 2-D sequence on a Dask LocalCluster against one process (dic.sequence.track_sequence(client=)).

Run from the repository root (needs the ``dask`` extra)::

    .venv/bin/python -m bench.dask_sequence [--size 1024] [--frames 40] [--step 5] [--workers 2] [--quick]

Images: ``--size``² 8-bit Boolean speckle from ``dic.synth.speckle_pair`` (seed 7), frame k translated
by (0.05 k, -0.03 k) px plus a 0.01 % / frame stretch (exact ground truth); 21 px subsets on a grid of
``--step`` px, 1st order, fixed reference, every frame from a zero start (``guess="none"``: what a
distributed run does), strain window 5, CPU. Timed, reading (arrays in memory), correlation, strain
and writing the result file included, after a warm-up run of 2 frames (kernel compilation excluded):

* one process: ``track_sequence(..., guess="none")`` (Warp's CPU launches use every core);
* Dask: a ``LocalCluster(n_workers=--workers, processes=True, threads_per_worker=1)`` whose workers
  run Warp on ``--worker-threads`` threads each (``SPECULA_THREADS``), started and warmed up with
  the same 2-frame run before the clock (start-up and warm-up reported apart, as a long-lived
  cluster would have done them); each worker's preparation of the run's reference is timed.

Reported: POI/s over the whole run for both, their ratio (issue 13's target: >= 0.85 with 2 workers
on 2 cores), and whether the two result files are identical. Writes bench/results/dask_sequence_cpu.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from datetime import datetime, timezone

import numpy as np

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")


def _frames(size: int, n: int):
    from dic.synth import speckle_pair

    ref, _ = speckle_pair((size, size), (0, 0), seed=7)
    c = size / 2
    frames = [speckle_pair((size, size), lambda x, y, k=k: (0.05 * k + 1e-4 * k * (x - c), -0.03 * k + 1e-4 * k * (y - c)),
                           seed=7)[1] for k in range(1, n + 1)]
    return np.round(ref).astype(np.uint8), [np.round(f).astype(np.uint8) for f in frames]


def _same(a, b) -> bool:
    from dic.store import read_results

    ra, rb = read_results(a), read_results(b)
    if sorted(ra.frames) != sorted(rb.frames):
        return False
    return all(np.array_equal(getattr(ra.frames[k], n), getattr(rb.frames[k], n), equal_nan=True)
               for k in ra.frames for n in ("u", "v", "params", "zncc", "status", "valid"))


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=1024)
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--step", type=int, default=5)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--worker-threads", type=int, default=1, help="SPECULA_THREADS of each worker")
    p.add_argument("--quick", action="store_true", help="256 px, 6 frames (smoke test)")
    a = p.parse_args(argv)
    if a.quick:
        a.size, a.frames = 256, 6
    import distributed

    from dic.sequence import track_sequence

    ref, frames = _frames(a.size, a.frames)
    kw = dict(step=a.step, subset=21, order=1, device="cpu", mode="overwrite")
    with tempfile.TemporaryDirectory() as tmp:
        track_sequence(ref, frames[:2], os.path.join(tmp, "warm.h5"), guess="none", **kw)  # compile the kernels
        t0 = time.perf_counter()
        s1 = track_sequence(ref, frames, os.path.join(tmp, "one.h5"), guess="none", **kw)
        t_one = time.perf_counter() - t0
        n_poi = s1.frames[0]["n_points"]
        tc = time.perf_counter()
        with distributed.LocalCluster(n_workers=a.workers, processes=True, threads_per_worker=1,
                                      dashboard_address=None,
                                      env={"SPECULA_THREADS": str(a.worker_threads)}) as cluster, \
                distributed.Client(cluster) as client:
            # the same warm-up as the one process got (a long-lived cluster has loaded its kernels)
            track_sequence(ref, frames[:2], os.path.join(tmp, "warm_dask.h5"), client=client, **kw)
            t_cluster = time.perf_counter() - tc
            t0 = time.perf_counter()
            track_sequence(ref, frames, os.path.join(tmp, "dask.h5"), client=client, **kw)
            t_dask = time.perf_counter() - t0
        identical = _same(os.path.join(tmp, "one.h5"), os.path.join(tmp, "dask.h5"))
    one = n_poi * a.frames / t_one
    dask = n_poi * a.frames / t_dask
    out = {
        "benchmark": "dask_sequence", "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "load_average_before": os.getloadavg()},
        "versions": {"distributed": distributed.__version__, "numpy": np.__version__},
        "size": a.size, "frames": a.frames, "step": a.step, "pois": n_poi, "workers": a.workers,
        "worker_threads": a.worker_threads,
        "one_process": {"seconds": t_one, "poi_per_s": one, "frames_per_s": a.frames / t_one},
        "dask": {"seconds": t_dask, "cluster_start_s": t_cluster, "poi_per_s": dask, "frames_per_s": a.frames / t_dask},
        "ratio": dask / one, "identical": identical,
    }
    print(f"{a.size}x{a.size} px, {n_poi} POIs, {a.frames} frames, step {a.step}")
    print(f"one process : {one:10.0f} POI/s ({a.frames / t_one:.2f} frames/s)")
    print(f"dask x{a.workers}     : {dask:10.0f} POI/s ({a.frames / t_dask:.2f} frames/s; cluster start + warm-up {t_cluster:.1f} s "
          "not included)")
    print(f"ratio {dask / one:.2f}, identical results: {identical}")
    if not a.quick:
        os.makedirs(RESULTS, exist_ok=True)
        with open(os.path.join(RESULTS, "dask_sequence_cpu.json"), "w") as f:
            json.dump(out, f, indent=2)
    return out


if __name__ == "__main__":
    main()
