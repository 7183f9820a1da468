"""Peak memory of the exports and post-processing of a result file against its number of frames (issue 13,
"memory bounded by design"): ``python -m bench.export_memory``.

A synthetic 2-D result file (``--points`` POIs on a grid, smooth u, v and their strain, uncompressed) is
written with ``--frames`` frames (default 100 and 1000); each export (``specula export`` csv, netcdf, vtk,
mat) and each post-processing (extensometer, point history, line profile, strain with another window) of
each file runs in a fresh child process, which reports its peak RSS (``ru_maxrss``) and the RSS it had
before the call (imports done), and the wall time. CSV, netCDF, VTK and the post-processing should need
the same memory for every length; MATLAB v5 is written whole (its matrices, F x N per quantity).

Options: ``--frames 100,1000``, ``--points 1600``, ``--only csv,netcdf``, ``--out``
(default ``bench/results/export_memory_cpu.json``).
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import resource
import shutil
import tempfile
import time

import numpy as np

from bench._host import cpu_model, write_json

TASKS = ("csv", "netcdf", "vtk", "mat", "extensometer", "point_history", "line_profile", "recompute_strain")


def write_file(path, n_frames: int, n_side: int) -> None:
    from dic._strain import strain
    from dic.field2d import Field2D
    from dic.store import ResultWriter

    gy, gx = np.meshgrid(np.arange(n_side) * 5.0 + 20, np.arange(n_side) * 5.0 + 20, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    n = len(pts)
    with ResultWriter(path, reference_path="ref.tif", reference_shape=(n_side * 5 + 40,) * 2,
                      settings={"subset": 21, "step": 5}, compression="none") as w:
        for k in range(1, n_frames + 1):
            u = 1e-4 * k * pts[:, 0]
            v = -3e-5 * k * pts[:, 1]
            params = np.zeros((n, 6))
            params[:, 0], params[:, 3] = u, v
            f = Field2D(points=pts, u=u, v=v, params=params, zncc=np.full(n, 0.99), iterations=np.full(n, 4, np.int32),
                        status=np.zeros(n, np.int32), valid=np.ones(n, bool), subset=21, order=1, step=5, zncc_min=0.8)
            w.write_frame(k, f, strain=strain(f, window=5), path=f"cur{k}.tif")


def _run(task: str, src: str, out: str, queue) -> None:
    from dic.export import export_results
    from dic.postprocess import extensometer, line_profile, point_history, recompute_strain

    calls = {
        "csv": lambda: export_results(src, "csv", os.path.join(out, "csv")),
        "netcdf": lambda: export_results(src, "netcdf", os.path.join(out, "run.nc")),
        "vtk": lambda: export_results(src, "vtk", os.path.join(out, "vtk")),
        "mat": lambda: export_results(src, "mat", os.path.join(out, "run.mat")),
        "extensometer": lambda: extensometer(src, (40, 40), (120, 60)),
        "point_history": lambda: point_history(src, (60, 60), "exx"),
        "line_profile": lambda: line_profile(src, (30, 30), (150, 150), "u", samples=20),
        "recompute_strain": lambda: recompute_strain(src, os.path.join(out, "strain.h5"), window=7),
    }
    import pandas  # noqa: F401 - the libraries an export loads, before the baseline
    import scipy.io  # noqa: F401
    import xarray  # noqa: F401

    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    t = time.perf_counter()
    calls[task]()
    wall = time.perf_counter() - t
    queue.put((before, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, wall))


def measure(task: str, src: str) -> dict:
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    out = tempfile.mkdtemp(prefix="export_memory_")
    try:
        p = ctx.Process(target=_run, args=(task, src, out, queue))
        p.start()
        before, peak, wall = queue.get()
        p.join()
    finally:
        shutil.rmtree(out, ignore_errors=True)
    return {"rss_before_mb": round(before, 1), "peak_rss_mb": round(peak, 1), "growth_mb": round(peak - before, 1),
            "seconds": round(wall, 2)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", default="100,1000")
    ap.add_argument("--points", type=int, default=1600)
    ap.add_argument("--only", default=",".join(TASKS))
    ap.add_argument("--out", default="bench/results/export_memory_cpu.json")
    args = ap.parse_args(argv)
    frames = [int(v) for v in args.frames.split(",")]
    tasks = [t for t in args.only.split(",") if t]
    unknown = [t for t in tasks if t not in TASKS]
    if unknown:
        raise SystemExit(f"unknown task(s) {unknown}; choose from {', '.join(TASKS)}")
    n_side = max(2, int(round(args.points ** 0.5)))
    load0 = os.getloadavg()
    result = {"benchmark": "export_memory", "cpu": cpu_model(), "cores": os.cpu_count(), "python": platform.python_version(),
              "points": n_side * n_side, "frames": frames, "runs": {}}
    workdir = tempfile.mkdtemp(prefix="export_memory_src_")
    try:
        for n_frames in frames:
            src = os.path.join(workdir, f"run_{n_frames}.h5")
            t = time.perf_counter()
            write_file(src, n_frames, n_side)
            print(f"{n_frames} frames x {n_side * n_side} points: written in {time.perf_counter() - t:.1f} s, "
                  f"{os.path.getsize(src) / 2**20:.1f} MiB")
            for task in tasks:
                r = measure(task, src)
                result["runs"].setdefault(task, {})[str(n_frames)] = r
                print(f"  {task:>17}: peak RSS {r['peak_rss_mb']:7.1f} MB (before {r['rss_before_mb']:6.1f}, "
                      f"+{r['growth_mb']:6.1f}), {r['seconds']:6.2f} s")
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    result["load_average"] = {"before": load0, "after": os.getloadavg()}
    write_json(result, args.out)


if __name__ == "__main__":
    main()
