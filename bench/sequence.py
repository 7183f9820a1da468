"""Long image sequences (issue 13): sequence throughput, memory over the sequence length, reference strategies.

Run from the repository root::

    .venv/bin/python -m bench.sequence                    # full: 1024x1024, 100/1000 frames, 300 evolving frames
    .venv/bin/python -m bench.sequence --quick            # 128x128, a few frames (seconds; tests/project/test_bench_sequence.py)
    .venv/bin/python -m bench.sequence --parts evolving --modes fixed,auto --evolving-frames 100

Conditions (all parts): 8-bit Boolean speckle from :mod:`dic.synth` (mean radius 2 px, density
0.5, blur 0.7 px) with exact ground truth, 21 px subsets (``--subset``), 1st order, POIs on a grid
of step 5 px (``--step``), CPU (``--device``), frames given as PNG files (so reading and decoding
are part of the run). Three parts (``--parts``):

* **throughput**: a reference and ``--frames`` (100) frames, cycling over 10 rendered PNG images of
  the pattern moved by small rigid shifts (at most 0.3 px). *Track-only rate* = POIs / the median
  time of ``Tracker.track`` of one frame already in memory (previous frame as guess; no reading,
  no strain, no writing), measured in the same process first (kernel compilation excluded).
  *Sequence rate* = POIs × frames / the wall time of the whole sequence run (reference work,
  reading, correlation, strain, writing the HDF5 results file). Target (issue 13): ratio >= 0.9.
  The track-only times are taken before and after the sequence run (median of both), and the
  same ratio of CPU times (all threads; ``cpu_ratio``) is reported too: on a machine shared with
  other jobs it moves less with their load than the wall-time ratio. ``--compression`` sets the
  result file's compression (default: the store's), ``--checksum off`` writes it without HDF5's
  Fletcher-32 checksums (default on, as the store; for the cost of checksums, see also
  ``bench/checksum.py``) ``--throughput-reference`` sets the run's reference mode (default fixed;
  ``incremental`` moves it every frame) and ``--verify-composed`` checks the composed frames against the
  reference image (``verify_composed``: its cost, docs/dic2d.md "Re-verification of composed results").
* **memory**: the same run over ``--frames`` and ``--long-frames`` (1000) frames, each in its own
  process (peak RSS is a per-process high-water mark): peak RSS from ``resource.getrusage``
  (``ru_maxrss``) and the current RSS (``/proc/self/statm``) sampled every 0.2 s. Target: peak at
  1000 frames <= 1.1 × peak at 100 frames.
* **evolving**: :func:`dic.synth.evolving_sequence` — a stretch along x growing linearly to 30 %
  (``--stretch``) about the image centre over ``--evolving-frames`` (300) frames while
  ``--fade`` (0.2 %) of the speckles are replaced every frame, 1 grey level of noise
  (``--noise``). POIs: the grid points whose subsets stay in the image to the last frame (a box
  ROI). For each reference mode (``--modes``: fixed, incremental, every:N, auto): per frame, the
  fraction of those POIs that is valid and the RMS error of the valid ones' (u, v) against the
  exact Lagrangian displacement relative to frame 0, the invalid POIs by status (``CONVERGED``
  there: a ZNCC below ``zncc_min``) and the valid POIs whose place in their reference was
  interpolated (``reference_interpolated``); at frames 1, 10, 30, 100, 200 and the last, the RMS
  error binned by the number of speckles that differ between frame 0 and that frame within reach
  of each POI's subset (``error_by_changed_speckles``: what a changed speckle costs, whatever the
  reference). Target: the automatic mode keeps >= 95 % valid to the last frame with a final RMS
  error <= 0.05 px. With ``--keep DIR`` the rendered frames are reused by later calls with the same
  parameters (modes can run in separate processes).

The engine: ``dic.sequence.track_sequence(reference, frames, out, *, reference=MODE, ...)`` when the
library has it (issue 13); otherwise (``engine: fallback`` in the results) a loop of
``dic.Tracker`` that does what ``specula track`` does today (read, track with the previous
frame as guess, strain with a 5-point window, write the frame to the results store), for the
``fixed`` mode only; the other modes are then reported as skipped. ``--engine fallback`` forces it.
Writes bench/results/sequence_<device>.json (``--out`` to write elsewhere).
"""
from __future__ import annotations

import argparse
import inspect
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
N_DISTINCT = 10  # rendered frames the throughput/memory runs cycle over
SEED = 2026
MODE_NAMES = ("fixed", "incremental", "auto")
#: a mode name ending in this runs with robust IC-GN on every point (Tracker(robust=True)), e.g. "auto+robust"
ROBUST_SUFFIX = "+robust"
#: a mode name ending in this runs plain IC-GN (Tracker(robust=False)), e.g. "auto+plain"; a mode name without a
#: suffix runs the tracker's default (robust="adaptive" since issue 26)
PLAIN_SUFFIX = "+plain"


# ----------------------------------------------------------------------------------------------
# the engine: dic.sequence.track_sequence when it exists, else today's loop (fixed reference only)

# the previous frame's result as the next initial guess: the engine's rule, not a copy of it
from dic.sequence.track2d import _guess  # noqa: E402


def fallback_track_sequence(reference, frames, out, *, reference_mode="fixed", strain_window=5, device=None,
                            **tracker_options):
    """Today's serial loop (``specula track``): read, track (previous frame as guess), strain, write.

    Frames are numbered 1, 2, ... in the results file, as ``specula track`` numbers them. Only the
    fixed reference exists here.
    """
    from dic._strain import strain as compute_strain
    from dic._track import Tracker
    from dic.store import ResultWriter, image_digest
    from kernels.images import read_image

    if reference_mode != "fixed":
        raise ValueError(f"the fallback loop has only the fixed reference, not {reference_mode!r}")
    ref = read_image(reference) if isinstance(reference, (str, os.PathLike)) else np.asarray(reference, np.float32)
    tracker = Tracker(ref, device=device, **tracker_options)
    settings = {"subset": tracker.subset, "step": tracker.step, "order": tracker.order, "strain_window": strain_window}
    previous = None
    with ResultWriter(out, reference_path=str(reference) if isinstance(reference, str) else "",
                      reference_shape=ref.shape, reference_sha256=image_digest(ref), settings=settings,
                      mode="overwrite") as writer:
        for k, frame in enumerate(frames):
            t0 = time.perf_counter()
            path = str(frame) if isinstance(frame, (str, os.PathLike)) else ""
            cur = read_image(frame) if path else np.asarray(frame, np.float32)
            field = tracker.track(cur, guess=_guess(previous))  # the engine's own rule
            strain = compute_strain(field, window=strain_window) if strain_window else None
            writer.write_frame(k + 1, field, strain=strain, path=path, sha256=image_digest(cur),
                               attrs={"seconds": time.perf_counter() - t0, "reference_frame": 0})
            previous = (np.asarray(field.params, np.float64), np.asarray(field.valid, bool))


def engine(force_fallback: bool = False):
    """``(name, run)``: ``run(reference, frames, out, mode, **options)`` on the library's engine or the fallback."""
    fn = None
    if not force_fallback:
        try:
            from dic.sequence import track_sequence as fn
        except ImportError:
            fn = None
    if fn is None:
        def run(reference, frames, out, mode, **options):
            return fallback_track_sequence(reference, frames, out, reference_mode=mode, **options)
        return "fallback", run
    params = inspect.signature(fn).parameters
    # the planned API names the mode ``reference=``; take whichever keyword-only name the engine uses
    kw_only = [n for n, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY]
    mode_kw = next((n for n in ("reference", "reference_mode", "strategy", "update") if n in kw_only), None)
    if mode_kw is None:
        raise RuntimeError(f"dic.sequence.track_sequence{inspect.signature(fn)} has no reference-mode keyword")

    def run(reference, frames, out, mode, **options):
        kwargs = dict(options)
        kwargs[mode_kw] = mode
        if "mode" in params:
            kwargs["mode"] = "overwrite"
        if "progress" in params:
            kwargs["progress"] = False
        return fn(reference, frames, out, **kwargs)
    return "dic.sequence.track_sequence", run


def supports(engine_name: str, mode: str) -> bool:
    return engine_name != "fallback" or mode == "fixed"


def frame_results(out, n_given: int):
    """``{sequence frame number: FrameResult}`` read one frame at a time from the results file.

    ``specula track`` numbers the given frames 1, 2, ... (the reference is frame 0); an engine that
    numbers them from 0 is recognised (n_given frames stored, the first one 0).
    """
    from dic.store import ResultReader

    with ResultReader(out) as reader:
        done = reader.done_frames()
        shift = 1 if (done and min(done) == 0 and len(done) == n_given) else 0
        for index in done:
            yield index + shift, reader.read_frame(index)


# ----------------------------------------------------------------------------------------------
# memory


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


class RssSampler:
    """Samples the current RSS every ``period`` s in a thread (a per-frame view of the memory)."""

    def __init__(self, period: float = 0.2):
        self.period = period
        self.samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self):
        t0 = time.perf_counter()
        while not self._stop.is_set():
            self.samples.append((time.perf_counter() - t0, _rss_mb()))
            self._stop.wait(self.period)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.samples.append((self.samples[-1][0] if self.samples else 0.0, _rss_mb()))


# ----------------------------------------------------------------------------------------------
# images


def _write_png(path, image):
    from kernels.images import write_image

    write_image(path, np.clip(np.rint(image), 0, 255).astype(np.uint8))


def rigid_frames(folder, size: int, n_distinct: int = N_DISTINCT):
    """A reference and ``n_distinct`` frames of one pattern under small rigid shifts (PNG), with the shifts."""
    from dic.synth import add_noise, make_speckle, render

    shape = (size, size)
    model = make_speckle(shape, margin=8.0, seed=SEED)
    ref_path = os.path.join(folder, "reference.png")
    _write_png(ref_path, add_noise(render(model, shape), noise_sigma=1.0, seed=[SEED, 0]))
    paths, shifts = [], []
    for j in range(n_distinct):
        phase = 2 * np.pi * (j + 1) / n_distinct
        shift = (0.3 * np.sin(phase), 0.2 * np.cos(phase) - 0.2)
        path = os.path.join(folder, f"frame_{j:03d}.png")
        _write_png(path, add_noise(render(model, shape, shift), noise_sigma=1.0, seed=[SEED, j + 1]))
        paths.append(path)
        shifts.append(shift)
    return ref_path, paths, shifts


def evolving_frames(folder, size: int, n_frames: int, stretch: float, fade: float, noise: float, device):
    """The evolving-texture sequence written as PNG files (rendered once, read by every mode; a ``--keep``
    folder that holds the frames of the same parameters is reused, so modes can run in separate calls)."""
    from dic.synth import evolving_sequence

    seq = evolving_sequence((size, size), n_frames, stretch_final=stretch, fade_fraction=fade, noise_sigma=noise,
                            seed=SEED + 1, device=device)
    paths = [os.path.join(folder, f"evolving_{k:04d}.png") for k in range(n_frames)]
    stamp = os.path.join(folder, "evolving.json")
    key = {"size": size, "n_frames": n_frames, "stretch": stretch, "fade": fade, "noise": noise, "seed": SEED + 1}
    try:
        with open(stamp) as fh:
            if json.load(fh) == key and all(os.path.exists(p) for p in paths):
                return seq, paths
    except (OSError, ValueError):
        pass
    for k, path in enumerate(paths):
        _write_png(path, seq[k])
    with open(stamp, "w") as fh:
        json.dump(key, fh)
    return seq, paths


# ----------------------------------------------------------------------------------------------
# the parts


def _tracker_options(args, roi=None):
    opts = {"subset": args.subset, "step": args.step}
    if roi is not None:
        opts["roi"] = roi
    return opts


def part_throughput(args, run, engine_name, folder):
    from dic._track import Tracker
    from kernels.images import read_image

    ref_path, paths, _ = rigid_frames(folder, args.size)
    ref = read_image(ref_path)
    tracker = Tracker(ref, device=args.device, **_tracker_options(args))
    images = [read_image(p) for p in paths[:3]]
    field = tracker.track(images[0])  # warm-up: compiles what the run needs
    times, cpu_times = [], []

    def track_only_times():
        nonlocal field
        for img in images[1:] + images[:1]:
            c0, t0 = time.process_time(), time.perf_counter()
            field = tracker.track(img, guess=field)
            times.append(time.perf_counter() - t0)
            cpu_times.append(time.process_time() - c0)

    track_only_times()  # before the sequence run and after it (below): a load that changes during the run shows
    n_points = tracker.n_points
    frames = [paths[k % len(paths)] for k in range(args.frames)]
    out = os.path.join(folder, "throughput.h5")
    c0, t0 = time.process_time(), time.perf_counter()
    extra = {"compression": args.compression} if args.compression else {}
    if args.checksum == "off":
        from dic.store.layout import Compression, parse_compression

        comp = parse_compression(args.compression)
        extra = {"compression": Compression(comp.filter, comp.level, checksum=False)}
    if args.verify_composed:  # the check of composed results (dic.sequence.verification): its cost
        extra["verify_composed"] = True
    run(ref_path, frames, out, args.throughput_reference, device=args.device, **_tracker_options(args), **extra)
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    load_during = os.getloadavg()[0]
    file_mb = os.path.getsize(out) / 2**20
    track_only_times()
    track_only = n_points / float(np.median(times))
    # CPU time per frame (all threads): less sensitive to other jobs' load than wall time
    cpu_ratio = float(np.median(cpu_times)) / (cpu / len(frames))
    sequence_rate = n_points * len(frames) / wall
    valid = [float(np.mean(fr.valid)) for _, fr in frame_results(out, len(frames))]
    os.remove(out)
    return {
        "n_points": n_points, "frames": len(frames), "track_only_seconds": [float(t) for t in times],
        "track_only_pois_per_s": track_only, "sequence_seconds": wall, "sequence_cpu_seconds": cpu,
        "sequence_pois_per_s": sequence_rate, "sequence_frames_per_s": len(frames) / wall,
        "ratio": sequence_rate / track_only, "target_ratio": 0.9, "track_only_cpu_seconds": cpu_times,
        "cpu_ratio": cpu_ratio, "load_average_1min_at_end_of_sequence": load_during,
        "valid_fraction_min": min(valid) if valid else None,
        "frames_stored": len(valid), "compression": args.compression or "default", "checksum": args.checksum,
        "results_file_mb_per_frame": file_mb / len(frames),
        "reference": args.throughput_reference, "verify_composed": bool(args.verify_composed),
    }


def memory_child(args) -> dict:
    """One sequence run in this process (``--memory-child N``): peak and sampled RSS."""
    _, run = engine(args.engine == "fallback")
    folder = args.frames_dir
    ref_path = os.path.join(folder, "reference.png")
    paths = sorted(os.path.join(folder, f) for f in os.listdir(folder) if f.startswith("frame_"))
    frames = [paths[k % len(paths)] for k in range(args.memory_child)]
    out = os.path.join(folder, f"memory_{args.memory_child}.h5")
    rss_before = _rss_mb()
    t0 = time.perf_counter()
    with RssSampler() as sampler:
        run(ref_path, frames, out, "fixed", device=args.device, **_tracker_options(args))
    wall = time.perf_counter() - t0
    size = os.path.getsize(out)
    os.remove(out)
    rss = np.array([s[1] for s in sampler.samples])
    n = rss.size
    return {"frames": len(frames), "seconds": wall, "peak_rss_mb": _peak_rss_mb(), "rss_before_run_mb": rss_before,
            "rss_first_tenth_max_mb": float(rss[: max(1, n // 10)].max()),
            "rss_last_tenth_max_mb": float(rss[n - max(1, n // 10):].max()),
            "rss_samples": int(n), "results_file_mb": size / 2**20}


def part_memory(args, folder):
    if not os.path.exists(os.path.join(folder, "reference.png")):
        rigid_frames(folder, args.size)
    rows = []
    for n in (args.frames, args.long_frames):
        cmd = [sys.executable, "-m", "bench.sequence", "--memory-child", str(n), "--frames-dir", folder,
               "--size", str(args.size), "--step", str(args.step), "--subset", str(args.subset),
               "--engine", args.engine]
        if args.device:
            cmd += ["--device", args.device]
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=os.path.dirname(os.path.dirname(RESULTS)))
        if proc.returncode != 0:
            raise RuntimeError(f"memory run of {n} frames failed:\n{proc.stderr[-3000:]}")
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    short, long = rows
    return {"runs": rows, "peak_ratio": long["peak_rss_mb"] / short["peak_rss_mb"], "target_peak_ratio": 1.1}


def split_mode(name: str) -> tuple[str, bool | None]:
    """``"auto+robust"`` -> ``("auto", True)``, ``"auto+plain"`` -> ``("auto", False)``, ``"auto"`` -> ``("auto",
    None)``: a reference mode, and the ``robust`` it runs (None: the tracker's default)."""
    if name.endswith(ROBUST_SUFFIX):
        return name[: -len(ROBUST_SUFFIX)], True
    if name.endswith(PLAIN_SUFFIX):
        return name[: -len(PLAIN_SUFFIX)], False
    return name, None


def part_evolving(args, run, engine_name, folder):
    size = args.size
    seq, paths = evolving_frames(folder, size, args.evolving_frames, args.stretch, args.fade, args.noise, args.device)
    # POIs whose subsets stay in the image to the last frame
    half = args.subset // 2 + 2
    cx, cy = seq.centre
    a_last = 1.0 + args.stretch
    hx = ((size - 1) / 2 - half) / a_last
    roi = (int(np.ceil(cx - hx)), half, int(np.floor(cx + hx)), size - 1 - half)
    diag = _changed_speckle_counts(seq, roi, args)
    modes = {}
    for mode_name in args.modes:
        mode, robust = split_mode(mode_name)
        extra = {} if robust is None else {"robust": robust}
        if not supports(engine_name, mode) or (robust is not None and engine_name != "dic.sequence.track_sequence"):
            modes[mode_name] = {"skipped": f"the {engine_name} engine has no {mode!r} reference mode "
                                      "(dic.sequence.track_sequence is not in this checkout)"}
            continue
        out = os.path.join(folder, f"evolving_{mode_name.replace(':', '_').replace('+', '_')}.h5")
        t0 = time.perf_counter()
        try:
            run(paths[0], paths[1:], out, mode, device=args.device, **_tracker_options(args, roi), **extra)
        except Exception as exc:  # a mode the engine refuses or fails in: report it, run the others
            modes[mode_name] = {"failed": f"{type(exc).__name__}: {exc}"}
            continue
        wall = time.perf_counter() - t0
        per_frame = []
        by_change = {}
        for k, fr in frame_results(out, len(paths) - 1):
            pts = np.asarray(fr.points, np.float64)
            valid = np.asarray(fr.valid, bool)
            truth = seq.displacement(pts, k)
            err_all = np.hypot(np.asarray(fr.u) - truth[:, 0], np.asarray(fr.v) - truth[:, 1])
            err = err_all[valid]
            if k in diag:
                by_change[str(k)] = _error_by_changes(diag[k](pts), err_all, valid)
            ref_used = next((fr.attrs[a] for a in ("reference_frame", "reference_index", "reference")
                             if a in fr.attrs), None)
            status = np.asarray(fr.status) if getattr(fr, "status", None) is not None else None
            why = {} if status is None else {_status_name(c): int(n) for c, n in
                                              zip(*np.unique(status[~valid], return_counts=True))}
            per_frame.append({"frame": int(k), "valid_fraction": float(valid.mean()),
                              "rms_error_px": float(np.sqrt(np.mean(err**2))) if err.size else None,
                              "max_error_px": float(err.max()) if err.size else None,
                              "reference_frame": _plain(ref_used),
                              "invalid_by_status": why,  # CONVERGED/MAX_ITERATIONS here: ZNCC below zncc_min
                              "reference_interpolated": _plain(fr.attrs.get("reference_interpolated"))})
        os.remove(out)
        last = per_frame[-1] if per_frame else {}
        modes[mode_name] = {"seconds": wall, "frames_per_s": len(per_frame) / wall if wall else None,
                       "n_points": int(np.asarray(fr.points).shape[0]) if per_frame else 0,
                       "final_valid_fraction": last.get("valid_fraction"),
                       "final_rms_error_px": last.get("rms_error_px"),
                       "min_valid_fraction": min(f["valid_fraction"] for f in per_frame) if per_frame else None,
                       "max_rms_error_px": max((f["rms_error_px"] for f in per_frame if f["rms_error_px"] is not None),
                                               default=None),
                       "error_by_changed_speckles": by_change, "per_frame": per_frame}
    return {"frames": args.evolving_frames, "stretch_final": args.stretch, "fade_fraction": args.fade,
            "noise_sigma": args.noise, "roi": list(roi), "speckles_alive": int(np.count_nonzero(seq.alive(0))),
            "speckles_replaced_per_frame": int(seq.n_changed_per_frame),
            "targets": {"auto": {"final_valid_fraction": 0.95, "final_rms_error_px": 0.05}}, "modes": modes}


# ----------------------------------------------------------------------------------------------


CHANGE_BINS = ((0, 0), (1, 1), (2, 3), (4, 7), (8, None))


def _changed_speckle_counts(seq, roi, args) -> dict:
    """``{frame: counts(points)}`` at a few frames: how many speckles differ between frame 0 and that frame
    (alive in one, not the other: the net texture change a fixed reference sees) within reach of each
    POI's subset (their centres in the subset's square grown by the mean radius and 2 blur sigmas)."""
    from scipy.spatial import cKDTree

    last = args.evolving_frames - 1
    frames = sorted({k for k in (1, 10, 30, 100, 200, last) if 1 <= k <= last})
    p = seq.pattern
    reach = args.subset // 2 + p.radius + 2 * p.blur
    alive0 = seq.alive(0)
    out = {}
    for k in frames:
        changed = alive0 != seq.alive(k)
        if not np.any(changed):
            out[k] = lambda pts: np.zeros(len(pts), np.int64)
            continue
        tree = cKDTree(p.centres[changed])
        out[k] = lambda pts, tree=tree: np.asarray(tree.query_ball_point(pts, reach, p=np.inf, return_length=True))
    return out


def _error_by_changes(counts, err, valid) -> dict:
    """RMS error of the valid POIs binned by the number of changed speckles in their subset."""
    rows = {}
    for lo, hi in CHANGE_BINS:
        sel = (counts >= lo) & (True if hi is None else counts <= hi)
        name = f"{lo}" if hi == lo else f"{lo}+" if hi is None else f"{lo}-{hi}"
        good = sel & valid
        rows[name] = {"n_points": int(sel.sum()), "n_valid": int(good.sum()),
                      "rms_error_px": float(np.sqrt(np.mean(err[good] ** 2))) if good.any() else None}
    return rows


def _status_name(code) -> str:
    from kernels.conventions import Status

    try:
        return Status(int(code)).name
    except ValueError:
        return str(int(code))


def _plain(value):
    """A JSON-able form of an HDF5 attribute (NumPy scalars and bytes included)."""
    if value is None:
        return None
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    arr = np.asarray(value)
    if arr.size == 1 and arr.dtype.kind in "biuf":
        return arr.item()
    return str(value)




def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="128x128 px, a few frames (a smoke test, seconds)")
    parser.add_argument("--parts", default="throughput,memory,evolving",
                        help="comma-separated: throughput, memory, evolving (default all)")
    parser.add_argument("--size", type=int, default=None, help="image side, px (default 1024; quick 128)")
    parser.add_argument("--step", type=int, default=5)
    parser.add_argument("--subset", type=int, default=21)
    parser.add_argument("--frames", type=int, default=None, help="frames of the throughput run (default 100; quick 6)")
    parser.add_argument("--long-frames", type=int, default=None, help="frames of the long memory run (default 1000; quick 12)")
    parser.add_argument("--evolving-frames", type=int, default=None, help="evolving-texture frames (default 300; quick 8)")
    parser.add_argument("--stretch", type=float, default=0.30, help="stretch at the last evolving frame (default 0.30)")
    parser.add_argument("--fade", type=float, default=0.002, help="fraction of the speckles replaced per frame")
    parser.add_argument("--noise", type=float, default=1.0, help="grey-level noise std of the evolving frames")
    parser.add_argument("--modes", default="fixed,incremental,every:10,auto", help="reference modes of the evolving part")
    parser.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    parser.add_argument("--checksum", default="on", choices=["on", "off"],
                        help="Fletcher-32 checksums in the result file of the throughput run (default on)")
    parser.add_argument("--compression", default=None,
                        help="result file compression of the throughput run (none, lzf, gzip:N; default: the store's)")
    parser.add_argument("--engine", default="auto", choices=["auto", "fallback"],
                        help="auto: dic.sequence.track_sequence when present; fallback: today's loop")
    parser.add_argument("--out", default=None, help="results JSON (default bench/results/sequence_<device>.json)")
    parser.add_argument("--keep", default=None, help="folder for the rendered frames (default a temporary one)")
    parser.add_argument("--throughput-reference", default="fixed",
                        help="reference mode of the throughput run (default fixed; e.g. incremental)")
    parser.add_argument("--verify-composed", action="store_true",
                        help="throughput run with verify_composed (the check of composed results against the reference)")
    parser.add_argument("--memory-child", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--frames-dir", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    quick = args.quick
    args.size = args.size or (128 if quick else 1024)
    args.frames = args.frames or (6 if quick else 100)
    args.long_frames = args.long_frames or (12 if quick else 1000)
    args.evolving_frames = args.evolving_frames or (8 if quick else 300)
    args.parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    bad = [p for p in args.parts if p not in ("throughput", "memory", "evolving")]
    if bad:
        parser.error(f"unknown part(s) {bad}; choose from throughput, memory, evolving")
    args.modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    for m in args.modes:
        m = split_mode(m)[0]
        if m not in MODE_NAMES and not (m.startswith("every:") and m[6:].isdigit() and int(m[6:]) > 0):
            parser.error(f"unknown reference mode {m!r}; choose from fixed, incremental, every:N, auto (each "
                         "optionally +robust: robust IC-GN on every point, or +plain: plain IC-GN; none: adaptive)")
    for name in ("size", "step", "subset", "frames", "long_frames", "evolving_frames"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1")
    if args.evolving_frames < 2:
        parser.error("--evolving-frames must be >= 2")
    if not 0 <= args.fade < 1:
        parser.error("--fade must be in [0, 1)")
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.memory_child is not None:
        print(json.dumps(memory_child(args)))
        return None
    import warp as wp

    from kernels._launch import cpu_threads

    engine_name, run = engine(args.engine == "fallback")
    folder = args.keep or tempfile.mkdtemp(prefix="specula_bench_sequence_")
    os.makedirs(folder, exist_ok=True)
    load_before = os.getloadavg()
    result = {
        "benchmark": "sequence", "engine": engine_name, "device": args.device, "quick": bool(args.quick),
        "host": {"cpu": cpu_model(), "cpu_count": os.cpu_count(), "cpu_threads": cpu_threads(),
                 "load_average_before": list(load_before)},
        "versions": {"python": sys.version.split()[0], "warp": wp.__version__, "numpy": np.__version__},
        "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "parameters": {"image_size": [args.size, args.size], "step": args.step, "subset": args.subset, "order": 1,
                       "frames": args.frames, "long_frames": args.long_frames,
                       "evolving_frames": args.evolving_frames, "images": "8-bit PNG files, Boolean speckle "
                       "(dic.synth), mean radius 2 px, density 0.5, blur 0.7 px, noise 1 grey level"},
    }
    t_all = time.perf_counter()
    try:
        if "throughput" in args.parts:
            result["throughput"] = part_throughput(args, run, engine_name, folder)
            t = result["throughput"]
            print(f"throughput ({engine_name}): {t['n_points']} POIs x {t['frames']} frames: sequence "
                  f"{t['sequence_pois_per_s']:.0f} POI/s ({t['sequence_frames_per_s']:.2f} frames/s), track-only "
                  f"{t['track_only_pois_per_s']:.0f} POI/s: ratio {t['ratio']:.2f} (target >= 0.9)")
        if "memory" in args.parts:
            result["memory"] = part_memory(args, folder)
            m = result["memory"]
            print("memory: " + "; ".join(f"{r['frames']} frames: peak RSS {r['peak_rss_mb']:.0f} MB "
                                          f"(first tenth {r['rss_first_tenth_max_mb']:.0f}, last tenth "
                                          f"{r['rss_last_tenth_max_mb']:.0f} MB)" for r in m["runs"])
                  + f": ratio {m['peak_ratio']:.3f} (target <= 1.1)")
        if "evolving" in args.parts:
            result["evolving"] = part_evolving(args, run, engine_name, folder)
            for mode, r in result["evolving"]["modes"].items():
                if "per_frame" not in r:
                    print(f"evolving {mode}: {r.get('skipped') or r.get('failed')}")
                    continue
                print(f"evolving {mode}: final valid {r['final_valid_fraction']:.3f} (min {r['min_valid_fraction']:.3f}), "
                      f"final RMS error {r['final_rms_error_px']} px, {r['frames_per_s']:.2f} frames/s")
    finally:
        if args.keep is None:
            shutil.rmtree(folder, ignore_errors=True)
    result["total_seconds"] = time.perf_counter() - t_all
    result["host"]["load_average_after"] = list(os.getloadavg())
    out = args.out or os.path.join(RESULTS, f"sequence_{args.device.replace(':', '')}.json")
    write_json(result, out)
    return result


if __name__ == "__main__":
    main()
