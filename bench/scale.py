"""Scale (issue 13): a large frame pair at step 2 through ``track_sequence``, peak memory measured.

Run from the repository root::

    .venv/bin/python -m bench.scale                     # 8192 x 8192, step 2: 16.7 M POIs (minutes)
    .venv/bin/python -m bench.scale --size 2048         # a smaller pair (same method)
    .venv/bin/python -m bench.scale --size 8192 --keep /tmp/scale   # keep (and reuse) the rendered PNGs

Conditions: a ``--size`` x ``--size`` 8-bit Boolean speckle pair from :func:`dic.synth.speckle_pair`
(mean radius 2 px, density 0.5, blur 0.7 px, 1 grey level of noise; seed fixed) written once as PNG
files; the current image is the reference deformed by the affine field
``u = U0 + EXX (x - c) + EXY (y - c)``, ``v = V0 + EYX (x - c) + EYY (y - c)`` about the image
centre ``c`` (exact ground truth: the field at each POI). POIs on a grid of ``--step`` (2) px,
21 px subsets, 1st order, CPU, ``track_sequence(reference, [current], out)`` with its defaults
(``max_memory`` a quarter of the machine's memory unless ``--max-memory``; strain window 5; the
store's default compression) in a child process, so that its peak RSS (``ru_maxrss``, and the
current RSS sampled every 0.5 s) is the tracking run's alone (rendering runs in another child).

Reported: POIs, the chunks used (``dic.sequence.chunks``: POIs per chunk and their number), wall
time and its parts, peak RSS, the result file's size, the valid fraction and the RMS / max error of
the valid POIs' (u, v) against the exact field. Target (issue 13): peak RSS <= 8 GB at 8192 x 8192.
Writes bench/results/scale_<device>.json (``--out``). Not a test (minutes; CI does not run it).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from datetime import datetime, timezone

import numpy as np

from bench._host import cpu_model, write_json

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
SEED = 8192
U0, V0 = 0.35, -0.2  # px
EXX, EXY, EYX, EYY = 4e-4, 1e-4, -1e-4, -2e-4  # displacement gradients (max |u| about 2 px at 8192 px)


def exact_field(x, y, size: int):
    """The exact displacement (u, v) px at reference points (x, y) of a ``size`` px image."""
    c = (size - 1) / 2.0
    return U0 + EXX * (x - c) + EXY * (y - c), V0 + EYX * (x - c) + EYY * (y - c)


def _paths(folder: str, size: int) -> tuple[str, str]:
    return (os.path.join(folder, f"scale_{size}_reference.png"), os.path.join(folder, f"scale_{size}_current.png"))


def render_child(args) -> dict:
    """Render the pair and write it as 8-bit PNG files (in its own process: its memory is not measured)."""
    from dic.synth import speckle_pair
    from kernels.images import write_image

    t0 = time.perf_counter()
    ref, cur = speckle_pair((args.size, args.size), lambda x, y: exact_field(x, y, args.size), noise_sigma=1.0,
                            bits=8, seed=SEED, device=args.device)
    for path, img in zip(_paths(args.folder, args.size), (ref, cur)):
        write_image(path, np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return {"render_seconds": time.perf_counter() - t0}


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def track_child(args) -> dict:
    """The tracking run (this process's peak RSS is the figure)."""
    from dic.sequence import track_sequence
    from dic.sequence.chunks import bytes_per_poi, default_max_memory
    from dic.store import ResultReader

    ref_path, cur_path = _paths(args.folder, args.size)
    out = os.path.join(args.folder, f"scale_{args.size}.h5")
    samples: list[tuple[float, float]] = []
    stop = threading.Event()
    t_start = time.perf_counter()

    def sample():
        while not stop.is_set():
            samples.append((time.perf_counter() - t_start, _rss_mb()))
            stop.wait(0.5)

    thread = threading.Thread(target=sample, daemon=True)
    rss_before = _rss_mb()
    thread.start()
    chunks = {}
    from dic.sequence import chunks as chunk_module

    real_track = chunk_module.ChunkedTracker.track

    def chunked_track(self, current, guess=None):  # the engine's own chunk plan, as it runs
        chunks.update(n_chunks=self.n_chunks, poi_per_chunk=self.chunk)
        return real_track(self, current, guess=guess)

    chunk_module.ChunkedTracker.track = chunked_track

    def spy(index, field, strain):
        chunks["n_points"] = int(len(field.u))

    try:
        summary = track_sequence(ref_path, [cur_path], out, mode="overwrite", step=args.step, subset=args.subset,
                                 order=1, device=args.device, max_memory=args.max_memory, callback=spy)
    finally:
        stop.set()
        thread.join()
    wall = time.perf_counter() - t_start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    budget = args.max_memory or default_max_memory()
    n = chunks.get("n_points", 0)
    with ResultReader(out) as r:
        f = r.read_frame(1)
        compression = r.compression.text
    ue, ve = exact_field(f.points[:, 0], f.points[:, 1], args.size)
    valid = np.asarray(f.valid, bool)
    err = np.hypot(f.u[valid] - ue[valid], f.v[valid] - ve[valid])
    eu, ev = f.u[valid] - ue[valid], f.v[valid] - ve[valid]
    size_mb = os.path.getsize(out) / 2**20
    if not args.keep_result:
        os.remove(out)
    rss = np.array([s[1] for s in samples]) if samples else np.array([peak])
    return {
        "n_points": n, "max_memory_bytes": int(budget), "bytes_per_poi": bytes_per_poi(1),
        "chunked": "n_chunks" in chunks, "poi_per_chunk": int(chunks.get("poi_per_chunk", n)),
        "n_chunks": int(chunks.get("n_chunks", 1)),
        "seconds": wall, "frame_seconds": summary.frames[0]["seconds"] if summary.frames else None,
        "peak_rss_mb": peak, "rss_before_run_mb": rss_before, "rss_samples": int(rss.size),
        "rss_timeline_mb": [[round(t, 1), round(m, 1)] for t, m in samples[:: max(1, len(samples) // 60)]],
        "results_file_mb": size_mb, "compression": compression,
        "valid_fraction": float(valid.mean()) if valid.size else 0.0,
        "rms_error_px": float(np.sqrt(np.mean(err**2))) if err.size else None,
        "max_error_px": float(err.max()) if err.size else None,
        "bias_u_px": float(eu.mean()) if eu.size else None, "bias_v_px": float(ev.mean()) if ev.size else None,
        "std_u_px": float(eu.std()) if eu.size else None, "std_v_px": float(ev.std()) if ev.size else None,
    }


def _child(args, flag: str) -> dict:
    cmd = [sys.executable, "-m", "bench.scale", flag, "--folder", args.folder, "--size", str(args.size),
           "--step", str(args.step), "--subset", str(args.subset), "--device", args.device]
    if args.max_memory:
        cmd += ["--max-memory", str(args.max_memory)]
    if args.keep_result:
        cmd += ["--keep-result"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=os.path.dirname(os.path.dirname(RESULTS)))
    if proc.returncode != 0:
        raise RuntimeError(f"{flag} failed:\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])




def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=8192, help="image side, px (default 8192)")
    parser.add_argument("--step", type=int, default=2, help="POI grid step, px (default 2)")
    parser.add_argument("--subset", type=int, default=21)
    parser.add_argument("--max-memory", type=int, default=None, help="track_sequence's max_memory, bytes (default its own)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--keep", default=None, help="folder for the PNG pair (kept and reused; default temporary)")
    parser.add_argument("--keep-result", action="store_true", help="keep the .h5 result file")
    parser.add_argument("--out", default=None, help="results JSON (default bench/results/scale_<device>.json)")
    parser.add_argument("--render-child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--track-child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--folder", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    for name in ("size", "step", "subset"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1")
    if args.size < 4 * args.subset:
        parser.error(f"--size must be at least {4 * args.subset} px for subsets of {args.subset} px")
    if args.max_memory is not None and args.max_memory < 1:
        parser.error("--max-memory must be >= 1 byte")
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.render_child:
        print(json.dumps(render_child(args)))
        return None
    if args.track_child:
        print(json.dumps(track_child(args)))
        return None
    args.folder = args.keep or tempfile.mkdtemp(prefix="specula_bench_scale_")
    os.makedirs(args.folder, exist_ok=True)
    load_before = os.getloadavg()
    result = {
        "benchmark": "scale", "device": args.device,
        "host": {"cpu": cpu_model(), "cpu_count": os.cpu_count(),
                 "memory_gb": os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 1e9,
                 "load_average_before": list(load_before)},
        "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "parameters": {"image_size": [args.size, args.size], "step": args.step, "subset": args.subset, "order": 1,
                       "frames": 1, "max_memory": args.max_memory or "default",
                       "field": {"u0": U0, "v0": V0, "dudx": EXX, "dudy": EXY, "dvdx": EYX, "dvdy": EYY,
                                 "about": "image centre"},
                       "images": "8-bit PNG files, Boolean speckle (dic.synth.speckle_pair), mean radius 2 px, "
                                 "density 0.5, blur 0.7 px, noise 1 grey level"},
    }
    try:
        if not all(os.path.exists(p) for p in _paths(args.folder, args.size)):
            result["render"] = _child(args, "--render-child")
            print(f"rendered the {args.size} x {args.size} pair in {result['render']['render_seconds']:.0f} s")
        r = result["track"] = _child(args, "--track-child")
    finally:
        if args.keep is None:
            shutil.rmtree(args.folder, ignore_errors=True)
    result["host"]["load_average_after"] = list(os.getloadavg())
    print(f"{args.size} x {args.size}, step {args.step}: {r['n_points']} POIs in {r['n_chunks']} chunk(s) of <= "
          f"{r['poi_per_chunk']}: {r['seconds']:.0f} s, peak RSS {r['peak_rss_mb']:.0f} MB (target <= 8000 at 8192), "
          f"file {r['results_file_mb']:.0f} MB; valid {r['valid_fraction']:.4f}, RMS error {r['rms_error_px']:.4f} px")
    out = args.out or os.path.join(RESULTS, f"scale_{args.device.replace(':', '')}.json")
    write_json(result, out)
    return result


if __name__ == "__main__":
    main()
