"""What the result file's checksums cost (issue 24): writing and reading a frame with and without HDF5's
Fletcher-32 filter.

Run from the repository root::

    .venv/bin/python -m bench.checksum                 # 1024x1024, step 5 (40 401 POIs), 30 frames per setting
    .venv/bin/python -m bench.checksum --quick         # 128x128, 4 frames (seconds; a smoke test)

Conditions: one real frame of ``dic.Tracker`` (a :func:`dic.synth.speckle_pair` of ``--size``² px
moved by (0.35, -0.2) px, 21 px subsets, step ``--step``, 1st order, strain with a 5-point window,
CPU) is written ``--frames`` times into a result file through :class:`dic.store.ResultWriter`
(``compression="none"``, the default; the same 21 datasets as a ``track_sequence`` frame), once with
checksums (the default) and once without (``Compression(None, checksum=False)``), the two files
written frame by frame in alternation so that a change of the machine's load touches both alike.
Reported per setting: the median wall and CPU time of ``write_frame`` (the datasets, then flush and
fsync of the file), of ``read_frame`` (every dataset read back, checksums verified), the file's MiB
per frame; and the difference with - without, per frame and as a fraction of the sequence's time per
frame (``--sequence-seconds``, default 0.80 s: the 40 401-POI frame of docs/dic2d.md's sequence
throughput, 1024², step 5, 2 CPU cores).

With ``--sequence-frames N`` (default 12; 0 skips it) the same in a real sequence: four
``dic.sequence.track_sequence`` runs of N frames (arrays in memory, the pair's pattern moved by
(0.05 k, -0.03 k) px, step ``--step``, strain window 5), checksums off, on, on, off, with the
writer thread's CPU time (``time.thread_time``) and wall time around each ``write_frame`` (median
over the frames but the first) and each run's CPU and wall seconds per frame. Writes
bench/results/checksum_cpu.json (``--out``).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from bench._host import cpu_model, write_json


def one_frame(size: int, step: int):
    """A real tracked frame and its strain (what a sequence writes per frame)."""
    from dic._strain import strain
    from dic._track import Tracker
    from dic.synth import speckle_pair

    ref, cur = speckle_pair((size, size), (0.35, -0.2), seed=2024)
    tracker = Tracker(ref, subset=21, step=step, device="cpu")
    field = tracker.track(cur)
    return field, strain(field, window=5)


def run(args) -> dict:
    from dic.store import ResultWriter
    from dic.store.layout import Compression

    field, field_strain = one_frame(args.size, args.step)
    n_points = int(len(field.points))
    settings = {"subset": 21, "step": args.step, "bench": "checksum"}
    timings = {name: {"write": [], "write_cpu": [], "read": [], "read_cpu": []} for name in ("checksum", "none")}
    setting = {"checksum": Compression(None, checksum=True), "none": Compression(None, checksum=False)}
    with tempfile.TemporaryDirectory(dir=args.tmp) as folder:
        paths = {name: os.path.join(folder, f"{name}.h5") for name in setting}
        writers = {name: ResultWriter(paths[name], reference_shape=(args.size, args.size), settings=settings,
                                      compression=setting[name], mode="overwrite") for name in setting}
        try:
            for k in range(1, args.frames + 1):
                for name in (("checksum", "none") if k % 2 else ("none", "checksum")):
                    c0, t0 = time.process_time(), time.perf_counter()
                    writers[name].write_frame(k, field, strain=field_strain, path=f"frame{k}.png")
                    timings[name]["write"].append(time.perf_counter() - t0)
                    timings[name]["write_cpu"].append(time.process_time() - c0)
        finally:
            for w in writers.values():
                w.close()
        sizes = {name: os.path.getsize(p) / 2**20 / args.frames for name, p in paths.items()}
        from dic.store import ResultReader

        readers = {name: ResultReader(p) for name, p in paths.items()}
        try:
            for k in range(1, args.frames + 1):
                for name in (("checksum", "none") if k % 2 else ("none", "checksum")):
                    c0, t0 = time.process_time(), time.perf_counter()
                    readers[name].read_frame(k)
                    timings[name]["read"].append(time.perf_counter() - t0)
                    timings[name]["read_cpu"].append(time.process_time() - c0)
        finally:
            for r in readers.values():
                r.close()
    med = {name: {key: float(np.median(v)) for key, v in t.items()} for name, t in timings.items()}
    extra_write = med["checksum"]["write"] - med["none"]["write"]
    extra_write_cpu = med["checksum"]["write_cpu"] - med["none"]["write_cpu"]
    from dic.store.results import _nbytes

    arrays_mib = (_nbytes(field) + _nbytes(field_strain)) / 2**20  # what the frame's datasets hold
    return {
        "n_points": n_points, "frames_per_setting": args.frames, "size": args.size, "step": args.step,
        "frame_arrays_mib": arrays_mib, "medians_seconds": med, "file_mib_per_frame": sizes,
        "checksum_extra_write_seconds_per_frame": extra_write,
        "checksum_extra_write_cpu_seconds_per_frame": extra_write_cpu,
        "checksum_extra_read_seconds_per_frame": med["checksum"]["read"] - med["none"]["read"],
        "sequence_seconds_per_frame": args.sequence_seconds,
        "checksum_extra_fraction_of_sequence_frame": extra_write / args.sequence_seconds,
        "timings_seconds": timings,
    }


def in_sequence(args) -> list[dict]:
    """Writer-thread CPU per frame inside ``track_sequence``, checksums off / on / on / off."""
    from dic.sequence import track_sequence
    from dic.store import ResultWriter
    from dic.store.layout import Compression
    from dic.synth import speckle_pair

    size = args.size
    ref, _ = speckle_pair((size, size), (0, 0), seed=2024)
    frames = [speckle_pair((size, size), (0.05 * k, -0.03 * k), seed=2024)[1] for k in range(1, args.sequence_frames + 1)]
    real = ResultWriter.write_frame
    times: list[tuple[float, float]] = []

    def timed(self, *a, **k):
        c0, t0 = time.thread_time(), time.perf_counter()
        real(self, *a, **k)
        times.append((time.thread_time() - c0, time.perf_counter() - t0))
    ResultWriter.write_frame = timed
    runs = []
    try:
        for setting in ("off", "on", "on", "off"):
            times.clear()
            with tempfile.TemporaryDirectory(dir=args.tmp) as folder:
                c0, t0 = time.process_time(), time.perf_counter()
                track_sequence(ref, frames, os.path.join(folder, "r.h5"), step=args.step, strain_window=5, device="cpu",
                               compression=Compression(None, checksum=setting == "on"))
                cpu, wall = time.process_time() - c0, time.perf_counter() - t0
            w = np.asarray(times[1:] or times)
            runs.append({"checksum": setting, "writer_cpu_seconds_median": float(np.median(w[:, 0])),
                         "writer_wall_seconds_median": float(np.median(w[:, 1])),
                         "run_cpu_seconds_per_frame": cpu / len(frames), "run_wall_seconds_per_frame": wall / len(frames),
                         "load_average_1min": os.getloadavg()[0]})
            r = runs[-1]
            print(f"  sequence, checksums {setting:3s}: writer thread CPU {1e3 * r['writer_cpu_seconds_median']:.2f} ms, "
                  f"wall {1e3 * r['writer_wall_seconds_median']:.2f} ms per frame; run CPU "
                  f"{r['run_cpu_seconds_per_frame']:.3f} s per frame (load {r['load_average_1min']:.1f})", flush=True)
    finally:
        ResultWriter.write_frame = real
    return runs


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="128x128 px, 4 frames (a smoke test)")
    parser.add_argument("--size", type=int, default=None, help="image side, px (default 1024; quick 128)")
    parser.add_argument("--step", type=int, default=5)
    parser.add_argument("--frames", type=int, default=None, help="frames per setting (default 30; quick 4)")
    parser.add_argument("--sequence-seconds", type=float, default=0.80,
                        help="the sequence's wall time per frame the cost is compared with (default 0.80 s)")
    parser.add_argument("--sequence-frames", type=int, default=None,
                        help="frames of each of the four track_sequence runs (default 12; quick 3; 0: skip them)")
    parser.add_argument("--tmp", default=None, help="folder for the result files (default: the system's temp)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    args.size = args.size or (128 if args.quick else 1024)
    args.frames = args.frames or (4 if args.quick else 30)
    if args.sequence_frames is None:
        args.sequence_frames = 3 if args.quick else 12
    load_before = os.getloadavg()[0]
    result = run(args)
    result.update({"device": "cpu", "cpu": cpu_model(), "cores": os.cpu_count(), "load_average_1min_before": load_before,
                   "load_average_1min_after": os.getloadavg()[0]})
    med = result["medians_seconds"]
    print(f"{result['n_points']} POIs, {result['frame_arrays_mib']:.2f} MiB of arrays per frame, "
          f"{args.frames} frames per setting")
    for name in ("none", "checksum"):
        print(f"  {name:9s} write {1e3 * med[name]['write']:7.2f} ms (CPU {1e3 * med[name]['write_cpu']:6.2f})  "
              f"read {1e3 * med[name]['read']:7.2f} ms  file {result['file_mib_per_frame'][name]:.2f} MiB/frame")
    print(f"  checksums add {1e3 * result['checksum_extra_write_seconds_per_frame']:.2f} ms per frame written "
          f"({100 * result['checksum_extra_fraction_of_sequence_frame']:.2f} % of a {args.sequence_seconds:.2f} s frame)")
    if args.sequence_frames > 0:
        result["in_sequence"] = in_sequence(args)
        result["load_average_1min_after"] = os.getloadavg()[0]
    out = args.out or os.path.join("bench", "results", "checksum_cpu.json" if not args.quick else "checksum_quick.json")
    write_json(result, out)


if __name__ == "__main__":
    main()
