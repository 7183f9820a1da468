"""The GPU path measured in one run (issue 13, item 7): CUDA tests, CPU-vs-GPU agreement, throughput.

Run by ``bench/gpu.sh run`` on a machine with an NVIDIA GPU (see bench/README.md, "GPU"), or directly::

    python -m bench.gpu --device cuda:0                  # everything, under --budget seconds (470)
    python -m bench.gpu --device cpu --quick --out DIR   # the smoke test CI runs (tests/project/test_gpu_script.py)
    python -m bench.gpu --device cpu --save-reference    # rewrite bench/results/gpu_reference_cpu.npz
    python -m bench.gpu --prebuild-cache --arch 90       # compile every kernel module for sm_90 into
                                                         # the Warp kernel cache (WARP_CACHE_PATH)

Sections, in this order, the JSON (``gpu_<device>.json``, e.g. ``bench/results/gpu_cuda.json``)
written again after each one, so that a run cut short keeps what it measured:

1. ``environment``: device name, Warp/torch/NumPy versions, the kernel cache in use.
2. ``reference``: a fixed synthetic pair (256 x 256 8-bit speckle, seed 2024, shift (0.35, -0.2) px,
   step 8, 21 px subsets, zero guess, orders 1 and 2) tracked on the device and compared with the
   CPU results carried in ``bench/results/gpu_reference_cpu.npz``: statuses, iteration counts
   and the largest parameter difference (float32 kernels: the GPU's fused multiply-adds and another
   summation order give differences of about 1e-6 px, not bitwise equality); and the same image
   given as a torch tensor on the device (read in place) must give bitwise the NumPy input's results.
3. ``outputs``: IC-GN outputs pre-filled with NaN / inf / -1 must all be written (every POI, also those
   whose subsets leave the image) and two runs must agree bitwise (run-to-run determinism), both orders.
4. ``prepare``: reference preparation (B-spline gradients; per-POI Hessians, both orders) and the
   current image's prefilter, 2048^2, step 5 (``--quick``: 256^2).
5. ``kernel``: kernel-only IC-GN POI/s timed with CUDA events, a fill sweep (10 k to 640 k POIs per
   launch, an ROI of whole rows of a step-2 grid) and a step sweep (2, 5, 10), both orders, 2048^2; the
   variants on the fill sweep: the tiled 1st-order prototype (``1_tiled``) and the plain coefficient
   layout (``1_plain``, ``2_plain``; ``layout``: plain/rows4 POI/s ratios and a bitwise check).
6. ``icgn``: single-frame IC-GN throughput (:func:`bench.icgn.bench_device`: 2048^2, step 2,
   1 028 196 POIs, both orders; ``--quick``: 256^2, step 4).
7. ``pipeline``: the frame pipeline on a 1024^2 8-bit sequence of 20 frames, step 5: today's API
   (``Tracker.track``) against the device-resident loop (:class:`kernels.frames.FrameTracker`, host and
   device frames) and, on CUDA, a CUDA-graph replay of it; the device loop and the replay must equal the
   host loop bitwise.
8. ``search``: the initial-guess searches (zncc, fft, pyramid, rg) on a 512^2 pair (step 5) moved by
   (7.3, -4.6) px: seconds per frame, valid fraction, RMS error against the exact shift.
9. ``sequence``: :func:`dic.sequence.track_sequence` on a synthetic 1024^2 sequence of 50 frames
   (a rigid motion growing by (0.1, -0.05) px per frame), step 5, fixed reference, strain and the
   result file included, frames given as torch tensors on the device and as NumPy arrays; reported as
   POI/s over the whole run against the track-only rate of one frame (``Tracker.track`` of a
   tensor) measured in the same run (``--quick``: 128^2, 4 frames, step 8).
10. ``tests``: ``pytest -m cuda`` (tests marked ``cuda`` and every test of the ``device`` fixture on
   ``cuda:0``, marked by tests/conftest.py) in a subprocess with the time left of ``--budget``
   (skipped on the CPU and with ``--quick``).
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import pkgutil
import platform
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "bench", "results")
REFERENCE = os.path.join(RESULTS, "gpu_reference_cpu.npz")
#: the sections, in the order they run (the fast correctness checks first, the CUDA test suite last)
SECTIONS = ("reference", "outputs", "prepare", "kernel", "icgn", "pipeline", "search", "sequence", "tests")
REF_CASE = {"size": 256, "shift": (0.35, -0.2), "seed": 2024, "step": 8, "subset": 21}


def _label(device: str) -> str:
    return "cuda" if device.startswith("cuda") else device.replace(":", "")


def _versions() -> dict:
    import warp as wp

    out = {"python": sys.version.split()[0], "numpy": np.__version__, "warp": wp.config.version}
    try:
        import torch

        out["torch"] = torch.__version__
    except ImportError:
        out["torch"] = None
    return out


def _torch_device(device: str):
    import torch

    return torch.device("cpu") if device == "cpu" else torch.device(device)


def _sync(device: str) -> None:
    import warp as wp

    wp.synchronize_device(device)
    if device.startswith("cuda"):
        import torch

        torch.cuda.synchronize()


def _same_bits(a: dict, b: dict) -> bool:
    """Two result dicts (params, zncc, iterations, status) equal bit for bit, NaNs included."""
    return all(np.array_equal(np.asarray(a[key]).view(np.int32), np.asarray(b[key]).view(np.int32)) for key in a)


def prebuild_cache(arch: int = 90) -> list[str]:
    """Compile every kernel module of ``kernels`` and the prototype ``bench.icgn_tiled`` for ``sm_<arch>`` into
    Warp's kernel cache (no GPU needed).

    The cache is ``WARP_CACHE_PATH`` (or Warp's default); Warp then loads these binaries on a GPU of that
    architecture instead of compiling the kernels there. Returns the modules compiled.
    """
    import warp as wp

    import kernels
    from kernels._device import _ensure_init

    _ensure_init()
    done = []
    names = [f"kernels.{name}" for _, name, _ in pkgutil.iter_modules(kernels.__path__)
             if not name.startswith("_") and name != "conventions"]
    for name in names + ["bench.icgn_tiled"]:
        module = importlib.import_module(name)
        if any(isinstance(getattr(module, a), wp.Kernel) for a in dir(module)):
            # both forms Warp may look for on that GPU: CUBIN (a driver older than Warp's CUDA) and PTX
            wp.compile_aot_module(module, arch=int(arch), use_ptx=False)
            wp.compile_aot_module(module, arch=int(arch), use_ptx=True)
            done.append(name.split(".", 1)[1])
    return done


def reference_case(device: str, images=None) -> dict:
    """The fixed pair (rendered here, or ``images``: the carried 8-bit pair) tracked on ``device``:
    the images and, per order, params, zncc, status and iterations (host arrays)."""
    from dic._track import Tracker

    c = REF_CASE
    if images is None:
        from dic.synth import speckle_pair

        images = speckle_pair((c["size"], c["size"]), c["shift"], seed=c["seed"], bits=8, device=device)
    ref, cur = (np.asarray(a, np.uint8) for a in images)  # 8-bit grey levels: exact in the file
    out = {"reference": ref, "current": cur}
    for order in (1, 2):
        f = Tracker(ref, step=c["step"], subset=c["subset"], order=order, check_warps=False, device=device).track(cur)
        out.update({f"params{order}": f.params, f"zncc{order}": f.zncc, f"status{order}": f.status,
                    f"iterations{order}": f.iterations})
    return out


def section_reference(device: str) -> dict:
    import torch

    from dic._track import Tracker

    if not os.path.exists(REFERENCE):
        return {"error": f"{REFERENCE} is missing (python -m bench.gpu --device cpu --save-reference)"}
    carried = np.load(REFERENCE)
    t0 = time.perf_counter()
    got = reference_case(device, (carried["reference"], carried["current"]))  # the CPU's own images
    res = {"case": {**REF_CASE, "image": "dic.synth.speckle_pair 8-bit, carried in the npz"},
           "seconds": time.perf_counter() - t0}
    ok = True
    for order in (1, 2):
        p, q = got[f"params{order}"], carried[f"params{order}"]
        same_status = got[f"status{order}"] == carried[f"status{order}"]
        both = same_status & np.isin(got[f"status{order}"], (0, 1))
        dp = np.abs(p[both] - q[both]) if both.any() else np.zeros(1)
        r = {"n_points": int(len(p)),
             "status_agreement": float(same_status.mean()),
             "iterations_equal_fraction": float(np.mean(got[f"iterations{order}"] == carried[f"iterations{order}"])),
             "max_abs_param_diff": float(dp.max()),
             "max_abs_uv_diff_px": float(max(dp[:, 0].max(), dp[:, p.shape[1] // 2].max())),
             "max_abs_zncc_diff": float(np.abs(got[f"zncc{order}"] - carried[f"zncc{order}"])[both].max()
                                        if both.any() else 0.0),
             "bitwise_equal": bool(np.array_equal(p, q) and same_status.all())}
        r["ok"] = r["status_agreement"] >= 0.999 and r["max_abs_uv_diff_px"] <= 1e-3
        ok &= r["ok"]
        res[f"order{order}"] = r
    # the same current image as a torch tensor on the device, read in place: bitwise the NumPy input's result
    tracker = Tracker(got["reference"], step=REF_CASE["step"], check_warps=False, device=device)
    a = tracker.track(got["current"])
    b = tracker.track(torch.from_numpy(got["current"]).to(_torch_device(device)))
    res["tensor_input_bitwise_equal"] = bool(np.array_equal(a.params, b.params) and np.array_equal(a.status, b.status))
    res["ok"] = bool(ok and res["tensor_input_bitwise_equal"])
    res["tolerance"] = "status agreement >= 99.9 %, |du|, |dv| <= 1e-3 px where both converged"
    return res


def section_icgn(device: str, quick: bool) -> dict:
    from bench.icgn import bench_device
    from dic._track import grid
    from dic.synth import speckle_pair

    size, step, repeats = (256, 4, 1) if quick else (2048, 2, 3)
    shift = (0.35, -0.2)
    ref, cur = speckle_pair((size, size), shift, seed=2024, bits=8, device=device)
    points = grid(ref.shape, step, margin=10)
    rows = bench_device(device, ref, cur, points, shift, 21, 30, 1e-3, repeats)
    return {"parameters": {"size": size, "step": step, "subset": 21, "n_points": int(len(points)),
                           "repeats": repeats, "max_iter": 30, "tol_px": 1e-3, "initial_guess": "zero"},
            "orders": {str(o): r for o, r in rows.items()}}


def _sequence_frames(size: int, n: int, device: str):
    from dic.synth import deformed_image, make_speckle

    du, dv = 0.1, -0.05
    model = make_speckle((size, size), margin=abs(du) * n + 8, seed=7, bits=8)
    ref = deformed_image(model, (size, size), None, seed=0, device=device)
    frames = [deformed_image(model, (size, size), (du * k, dv * k), seed=k, device=device) for k in range(1, n + 1)]
    return ref, frames, (du, dv)


def section_sequence(device: str, quick: bool, workdir: str) -> dict:
    import torch

    from dic._track import Tracker
    from dic.sequence import track_sequence

    size, n, step = (128, 4, 8) if quick else (1024, 50, 5)
    t0 = time.perf_counter()
    ref, frames, motion = _sequence_frames(size, n, device)
    t_render = time.perf_counter() - t0
    tdev = _torch_device(device)
    tensors = [torch.from_numpy(f).to(tdev) for f in frames]
    _sync(device)
    # the track-only rate of one frame: Tracker.track of a tensor on the device (after a warm-up)
    tracker = Tracker(ref, step=step, device=device)
    tracker.track(tensors[0])
    times = []
    for t in tensors[: min(3, n)]:
        _sync(device)
        s = time.perf_counter()
        tracker.track(t)
        _sync(device)
        times.append(time.perf_counter() - s)
    n_poi = tracker.n_points
    del tracker
    one = n_poi / min(times)
    res = {"parameters": {"size": size, "frames": n, "step": step, "subset": 21, "n_points": int(n_poi),
                          "motion_per_frame_px": list(motion), "reference": "fixed", "strain_window": 5,
                          "image": "dic.synth Boolean speckle, 8-bit, noise-free"},
           "render_seconds": t_render, "track_only_poi_per_s": one, "track_only_seconds": times}
    for name, given in (("tensors", tensors), ("numpy", frames)):
        out = os.path.join(workdir, f"sequence_{name}.h5")
        _sync(device)
        s = time.perf_counter()
        summary = track_sequence(ref, given, out, mode="overwrite", step=step, device=device)
        _sync(device)
        wall = time.perf_counter() - s
        valid = float(np.mean([f["n_valid"] / f["n_points"] for f in summary.frames]))
        res[name] = {"seconds": wall, "frames_per_s": n / wall, "poi_per_s": n * n_poi / wall,
                     "ratio_to_track_only": (n * n_poi / wall) / one, "mean_valid_fraction": valid}
    return res


# ----------------------------------------------------------------------------------------------
# kernel-level sections (issue 16): CUDA-event timings of the kernels alone
# ----------------------------------------------------------------------------------------------


class _KernelTimer:
    """Seconds of the device work of a callable: CUDA events on a GPU (the kernels alone, no host
    time between launches counted twice), ``perf_counter`` around a synchronised call on the CPU."""

    def __init__(self, device: str):
        import warp as wp

        self.device = device
        self.cuda = device.startswith("cuda")
        if self.cuda:
            self.start = wp.Event(device, enable_timing=True)
            self.end = wp.Event(device, enable_timing=True)

    def __call__(self, fn, repeats: int) -> list[float]:
        import warp as wp

        out = []
        for _ in range(repeats):
            wp.synchronize_device(self.device)
            if self.cuda:
                with wp.ScopedDevice(self.device):
                    wp.record_event(self.start)
                    fn()
                    wp.record_event(self.end)
                out.append(wp.get_event_elapsed_time(self.start, self.end) / 1000.0)
            else:
                s = time.perf_counter()
                fn()
                wp.synchronize_device(self.device)
                out.append(time.perf_counter() - s)
        return out


def _kernel_pair(size: int, device: str):
    from dic.synth import speckle_pair

    return speckle_pair((size, size), (0.35, -0.2), seed=2024, bits=8, device=device)


def section_kernel(device: str, quick: bool) -> dict:
    """Kernel-only IC-GN POI/s (CUDA events) over a fill sweep (POIs per launch) and a step sweep.

    Fill sweep: the first N POIs (row-major: an ROI of whole grid rows) of a step-2 grid of a 2048^2 pair,
    N = 10 k ... 640 k: how many POIs one launch needs to fill the GPU. Step sweep: all POIs of steps
    2, 5 and 10 (neighbouring threads read subsets ``step`` px apart: the memory-access side).
    Zero guess, 30 iterations at most, tol 1e-3 px, the current image prepared beforehand.
    """
    import warp as wp

    from dic._track import grid
    from kernels.icgn import (
        IcgnResult,
        default_layout,
        icgn,
        n_params,
        prepare_current,
        prepare_reference,
        prepare_subsets,
    )

    size = 256 if quick else 2048
    fills = (1000, 4000) if quick else (10_000, 20_000, 40_000, 80_000, 160_000, 320_000, 640_000)
    steps = (4, 8) if quick else (2, 5, 10)
    repeats = 2 if quick else 5
    ref, cur = _kernel_pair(size, device)
    refimg = prepare_reference(ref, device=device)
    curimg = prepare_current(cur, device=device)
    timer = _KernelTimer(device)
    res = {"parameters": {"size": size, "subset": 21, "max_iter": 30, "tol_px": 1e-3, "guess": "zero",
                          "shift_px": [0.35, -0.2], "repeats": repeats,
                          "timing": "CUDA events around the IC-GN launch" if timer.cuda else "perf_counter (CPU)"},
           "fill": {}, "step": {}}

    # the plain layout (kernels.icgn.LAYOUTS): the same kernel reading the padded coefficients in place
    curplain = prepare_current(cur, device=device, layout="plain")

    def measure(points, order, current=curimg, keep=None):
        subs = prepare_subsets(refimg, points, subset=21, order=order)
        n, k = len(points), n_params(order)
        out = IcgnResult(wp.empty((n, k), dtype=wp.float32, device=device),
                         wp.empty(n, dtype=wp.float32, device=device),
                         wp.empty(n, dtype=wp.int32, device=device), wp.empty(n, dtype=wp.int32, device=device))
        guess = wp.zeros((n, k), dtype=wp.float32, device=device)
        icgn(subs, current, guess=guess, out=out)  # warm-up (module load)
        secs = timer(lambda: icgn(subs, current, guess=guess, out=out), repeats)
        iters = out.iterations.numpy()
        if keep is not None:
            keep.append(out.numpy())
        return {"n_points": n, "seconds": secs, "poi_per_s": n / float(np.median(secs)),
                "poi_per_s_best": n / min(secs), "mean_iterations": float(iters.mean())}

    dense = grid(ref.shape, 2, margin=10)
    for order in (1, 2):
        res["fill"][str(order)] = [measure(dense[: min(n, len(dense))], order) for n in fills]
        res["step"][str(order)] = {str(s): measure(grid(ref.shape, s, margin=10), order) for s in steps}
    # the tiled 1st-order prototype (bench/icgn_tiled.py: one warp of lanes per POI), same fill sweep
    from bench.icgn_tiled import icgn_tiled

    def measure_tiled(points):
        subs = prepare_subsets(refimg, points, subset=21, order=1)
        n = len(points)
        out = IcgnResult(wp.empty((n, 6), dtype=wp.float32, device=device),
                         wp.empty(n, dtype=wp.float32, device=device),
                         wp.empty(n, dtype=wp.int32, device=device), wp.empty(n, dtype=wp.int32, device=device))
        guess = wp.zeros((n, 6), dtype=wp.float32, device=device)
        icgn_tiled(subs, curimg, guess=guess, out=out)
        secs = timer(lambda: icgn_tiled(subs, curimg, guess=guess, out=out), repeats)
        return {"n_points": n, "seconds": secs, "poi_per_s": n / float(np.median(secs)),
                "poi_per_s_best": n / min(secs), "mean_iterations": float(out.iterations.numpy().mean())}

    res["fill"]["1_tiled"] = [measure_tiled(dense[: min(n, len(dense))]) for n in fills]
    # layout variant: "plain" (padded coefficients read in place, 4 scalar loads per stencil row, 1x
    # the memory) against the default "rows4" (expanded copy); the same fill sweep, and the outputs of
    # the largest fill compared bitwise (the CUDA default layout is chosen from these figures)
    res["layout"] = {"default": default_layout(device), "bitwise_equal": {}}
    for order in (1, 2):
        pts = dense[: min(fills[-1], len(dense))]
        kept = []
        res["fill"][f"{order}_plain"] = [measure(dense[: min(n, len(dense))], order, curplain) for n in fills[:-1]]
        res["fill"][f"{order}_plain"].append(measure(pts, order, curplain, keep=kept))
        measure(pts, order, curimg, keep=kept)
        a, b = kept
        res["layout"]["bitwise_equal"][str(order)] = _same_bits(a, b)
    res["layout"]["plain_over_rows4"] = {
        str(o): [p["poi_per_s"] / r["poi_per_s"] for p, r in zip(res["fill"][f"{o}_plain"], res["fill"][str(o)])]
        for o in (1, 2)}
    # the opt-in robust refinement (kernels/icgn_robust.py), from the converged plain solution of a step-5 grid
    from kernels.icgn_robust import icgn_robust, robust_result

    res["robust"] = {}
    pts = grid(ref.shape, 8 if quick else 5, margin=10)
    for order in (1, 2):
        subs = prepare_subsets(refimg, pts, subset=21, order=order)
        plain = icgn(subs, curimg)
        out = robust_result(len(pts), n_params(order), device)
        icgn_robust(subs, curimg, plain.params, out=out)  # warm-up (module load)
        secs = timer(lambda: icgn_robust(subs, curimg, plain.params, out=out), repeats)
        r = out.numpy()
        res["robust"][str(order)] = {"n_points": len(pts), "seconds": secs, "poi_per_s": len(pts) / float(np.median(secs)),
                                     "mean_iterations": float(r["iterations"].mean()),
                                     "converged_fraction": float(np.mean(r["status"] == 0))}
    return res


def section_prepare(device: str, quick: bool) -> dict:
    """Reference preparation (gradients; per-POI Hessians of both orders) and current-image prefilter times."""
    from dic._track import grid
    from kernels.icgn import prepare_current, prepare_reference, prepare_subsets

    size, step = (256, 4) if quick else (2048, 5)
    repeats = 2 if quick else 3
    ref, cur = _kernel_pair(size, device)
    points = grid(ref.shape, step, margin=10)
    timer = _KernelTimer(device)
    refimg = prepare_reference(ref, device=device)
    prepare_subsets(refimg, points[:16], order=1)
    prepare_subsets(refimg, points[:16], order=2)
    prepare_current(cur, device=device)
    res = {"parameters": {"size": size, "step": step, "n_points": int(len(points)), "repeats": repeats,
                          "note": "host upload of the 8-bit image included (it is part of each call)"}}
    res["reference_image_s"] = timer(lambda: prepare_reference(ref, device=device), repeats)
    for order in (1, 2):
        res[f"subsets_order{order}_s"] = timer(lambda o=order: prepare_subsets(refimg, points, order=o), repeats)
    res["current_image_s"] = timer(lambda: prepare_current(cur, device=device), repeats)
    # the plain layout skips the row expansion (and its 4x buffer)
    res["current_image_plain_s"] = timer(lambda: prepare_current(cur, device=device, layout="plain"), repeats)
    res["summary"] = {key: float(np.median(v)) for key, v in res.items() if key.endswith("_s")}
    return res


def section_search(device: str, quick: bool) -> dict:
    """Each initial-guess search (zncc, fft, pyramid, rg) on a pair moved well beyond IC-GN's reach:
    seconds per frame, valid fraction and the displacement error against the exact shift."""
    from dic._track import Tracker
    from dic.synth import speckle_pair

    size, step = (256, 8) if quick else (512, 5)  # the searches run partly on the host: keep it bounded
    shift = (7.3, -4.6)
    ref, cur = speckle_pair((size, size), shift, seed=11, bits=8, device=device)
    res = {"parameters": {"size": size, "step": step, "subset": 21, "shift_px": list(shift), "search_radius": 16}}
    for method in ("zncc", "fft", "pyramid", "rg"):
        tracker = Tracker(ref, step=step, search=method, search_radius=16, device=device)
        tracker.track(cur)  # warm-up
        _sync(device)
        s = time.perf_counter()
        f = tracker.track(cur)
        _sync(device)
        ok = f.valid
        err = np.hypot(f.params[ok, 0] - shift[0], f.params[ok, f.params.shape[1] // 2] - shift[1])
        res[method] = {"seconds": time.perf_counter() - s, "n_points": int(tracker.n_points),
                       "valid_fraction": float(ok.mean()),
                       "rms_error_px": float(np.sqrt(np.mean(err ** 2))) if ok.any() else None}
    return res


def output_checks(device: str) -> dict:
    """Outputs pre-filled with NaN / -1 must all be written; two runs must agree bitwise (determinism)."""
    import warp as wp

    from dic._track import grid
    from kernels.icgn import IcgnResult, icgn, n_params, prepare_current, prepare_reference, prepare_subsets

    c = REF_CASE
    ref, cur = _kernel_pair(c["size"], device)
    points = grid(ref.shape, c["step"], margin=0)  # includes POIs whose subsets leave the image
    out = {}
    for order in (1, 2):
        subs = prepare_subsets(prepare_reference(ref, device=device), points, subset=c["subset"], order=order)
        curimg = prepare_current(cur, device=device)
        n, k = len(points), n_params(order)
        runs = []
        for _ in range(2):
            res = IcgnResult(wp.full((n, k), float("nan"), dtype=wp.float32, device=device),
                             wp.full(n, float("inf"), dtype=wp.float32, device=device),
                             wp.full(n, -1, dtype=wp.int32, device=device), wp.full(n, -1, dtype=wp.int32, device=device))
            runs.append(icgn(subs, curimg, out=res).numpy())
        a, b = runs
        out[f"order{order}"] = {
            "unwritten_params": int(np.isnan(a["params"]).sum()),
            "unwritten_zncc": int(np.isinf(a["zncc"]).sum()),
            "unwritten_iterations": int((a["iterations"] < 0).sum()),
            "unwritten_status": int((a["status"] < 0).sum()),
            "deterministic": _same_bits(a, b),
        }
    out["ok"] = all(v["deterministic"] and not any(v[key] for key in v if key.startswith("unwritten"))
                    for v in out.values() if isinstance(v, dict))
    return out


def section_pipeline(device: str, quick: bool) -> dict:
    """The frame pipeline: today's API (``Tracker.track`` of host 8-bit frames, search off), the
    device-resident loop (:class:`kernels.frames.FrameTracker`: host frames and host results; frames
    already on the device and results left there) and, on CUDA, a CUDA-graph replay of that loop (one
    graph launch per frame). Same frames, same propagated guesses: the device loop and the replay must give
    bitwise the host loop's last frame."""
    import warp as wp

    from dic._track import Tracker
    from kernels.frames import FrameTracker

    size, n, step = (128, 3, 8) if quick else (1024, 20, 5)
    ref, frames, motion = _sequence_frames(size, n, device)
    ref8 = np.clip(np.round(ref), 0, 255).astype(np.uint8)
    frames8 = [np.clip(np.round(f), 0, 255).astype(np.uint8) for f in frames]
    tracker = Tracker(ref8, step=step, search=None, device=device)
    npoi = tracker.n_points
    res = {"parameters": {"size": size, "frames": n, "step": step, "subset": 21, "n_points": int(npoi),
                          "motion_per_frame_px": list(motion), "frames_dtype": "uint8"}}

    def rate(seconds):
        return {"seconds": seconds, "frames_per_s": n / seconds, "poi_per_s": n * npoi / seconds}

    tracker.track(frames8[0])  # warm-up
    _sync(device)
    s = time.perf_counter()
    for f in frames8:
        tracker.track(f)
    _sync(device)
    res["tracker_api"] = rate(time.perf_counter() - s)

    ft = FrameTracker(tracker.correlator.subsets, np.uint8, max_iter=tracker.max_iter, tol=tracker.tol,
                      zncc_min=tracker.zncc_min)
    ft.track(frames8[0])  # warm-up
    ft.reset()
    _sync(device)
    s = time.perf_counter()
    for f in frames8:
        host_last = ft.track(f)
    _sync(device)
    res["frame_tracker_host"] = rate(time.perf_counter() - s)

    on_device = [wp.array(f, dtype=wp.uint8, device=device) for f in frames8]
    ft.reset()
    _sync(device)
    s = time.perf_counter()
    for f in on_device:
        last = ft.track_device(f)
    _sync(device)
    res["frame_tracker_device"] = rate(time.perf_counter() - s)
    dev_last = last.numpy()
    res["device_loop_bitwise_equal"] = _same_bits(host_last, dev_last)
    if device.startswith("cuda"):
        graph = ft.capture_graph()
        ft.reset()
        _sync(device)
        s = time.perf_counter()
        for f in on_device:
            wp.copy(ft.frame_buffer, f)
            wp.capture_launch(graph)
        _sync(device)
        res["graph_replay"] = rate(time.perf_counter() - s)
        got = ft.results.numpy()
        res["graph_replay_bitwise_equal"] = _same_bits(host_last, got)
    else:
        res["graph_replay"] = {"skipped": "CUDA graphs need a CUDA device"}
    return res


def section_tests(device: str, seconds: float) -> dict:
    if not device.startswith("cuda"):
        return {"skipped": "the CUDA tests need a CUDA device"}
    if seconds < 30:
        return {"skipped": f"only {seconds:.0f} s of the budget left"}
    cmd = [sys.executable, "-m", "pytest", "-m", "cuda", "-q", "-p", "no:cacheprovider", "--continue-on-collection-errors",
           "-o", "addopts=", "-rfE", "tests"]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=seconds)
        out, rc = p.stdout + p.stderr, p.returncode
    except subprocess.TimeoutExpired as exc:
        out = (exc.stdout or b"").decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        rc = "timeout"
    lines = [ln for ln in out.splitlines() if ln.strip()]
    summary = next((ln for ln in reversed(lines) if " in " in ln and ("passed" in ln or "failed" in ln
                                                                    or "error" in ln)), "")
    return {"command": " ".join(cmd), "returncode": rc, "seconds": time.perf_counter() - t0, "summary": summary,
            "failures": [ln for ln in lines if ln.startswith(("FAILED", "ERROR"))][:50], "tail": lines[-40:]}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda:0", help="Warp device (default cuda:0)")
    ap.add_argument("--quick", action="store_true", help="small sizes, no tests (the CI smoke test, < 30 s on a CPU)")
    ap.add_argument("--out", default=RESULTS, help="folder of the JSON (default bench/results)")
    ap.add_argument("--budget", type=float, default=470.0, help="seconds for the whole run; the tests get what is left")
    ap.add_argument("--sections", default=",".join(SECTIONS),
                    help=f"comma-separated subset of {','.join(SECTIONS)}")
    ap.add_argument("--save-reference", action="store_true", help="write the CPU reference npz and stop")
    ap.add_argument("--prebuild-cache", action="store_true", help="compile the kernels for --arch into the cache and stop")
    ap.add_argument("--arch", type=int, default=90, help="CUDA architecture of --prebuild-cache (default 90)")
    args = ap.parse_args(argv)
    t_start = time.perf_counter()
    if args.prebuild_cache:
        import warp as wp

        names = prebuild_cache(args.arch)
        print(f"compiled {len(names)} kernel modules for sm_{args.arch} into {wp.config.kernel_cache_dir}: "
              f"{', '.join(names)}")
        return {"prebuilt": names}
    from kernels._device import resolve_device

    try:
        device = resolve_device(args.device)
    except ValueError as exc:
        raise SystemExit(f"bench.gpu: {exc}") from None
    if args.save_reference:
        if device != "cpu":
            raise SystemExit("bench.gpu: the carried reference is computed on the CPU (--device cpu)")
        got = reference_case("cpu")
        np.savez_compressed(REFERENCE, **got)
        print(f"wrote {REFERENCE}")
        return {}
    sections = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = set(sections) - set(SECTIONS)
    if unknown:
        raise SystemExit(f"bench.gpu: unknown section(s) {sorted(unknown)}")
    import warp as wp

    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, f"gpu_{_label(device)}.json")
    result = {"benchmark": "gpu", "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "device": device, "quick": bool(args.quick),
              "environment": {"device_name": wp.get_device(device).name, "versions": _versions(),
                              "platform": platform.platform(), "cpu_count": os.cpu_count(),
                              "kernel_cache": wp.config.kernel_cache_dir or os.environ.get("WARP_CACHE_PATH")}}

    def save():
        result["seconds_so_far"] = time.perf_counter() - t_start
        with open(path, "w") as fh:
            json.dump(result, fh, indent=2, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))

    save()
    print(f"bench.gpu on {device} ({result['environment']['device_name']}), writing {path}", flush=True)
    with tempfile.TemporaryDirectory(prefix="specula-gpu-") as work:
        for name in sections:
            s = time.perf_counter()
            try:
                if name == "reference":
                    result[name] = section_reference(device)
                elif name == "outputs":
                    result[name] = output_checks(device)
                elif name == "prepare":
                    result[name] = section_prepare(device, args.quick)
                elif name == "kernel":
                    result[name] = section_kernel(device, args.quick)
                elif name == "search":
                    result[name] = section_search(device, args.quick)
                elif name == "pipeline":
                    result[name] = section_pipeline(device, args.quick)
                elif name == "icgn":
                    result[name] = section_icgn(device, args.quick)
                elif name == "sequence":
                    result[name] = section_sequence(device, args.quick, work)
                elif name == "tests":
                    result[name] = ({"skipped": "--quick"} if args.quick else
                                    section_tests(device, args.budget - (time.perf_counter() - t_start) - 10))
            except Exception as exc:  # noqa: BLE001 - one broken section must not lose the others
                import traceback

                result[name] = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()[-4000:]}
            result[name]["section_seconds"] = time.perf_counter() - s
            save()
            print(f"  {name}: {_brief(name, result[name])} ({result[name]['section_seconds']:.1f} s)", flush=True)
    print(f"wrote {path} in {time.perf_counter() - t_start:.0f} s")
    return result


def _brief(name: str, r: dict) -> str:
    if "error" in r or "skipped" in r:
        return r.get("error") or f"skipped: {r['skipped']}"
    if name == "reference":
        return (f"ok={r['ok']} order1 max|du,dv|={r['order1']['max_abs_uv_diff_px']:.2e} px, order2 "
                f"{r['order2']['max_abs_uv_diff_px']:.2e} px, tensor bitwise={r['tensor_input_bitwise_equal']}")
    if name == "outputs":
        return f"ok={r['ok']} (every output written, two runs bitwise equal)"
    if name == "prepare":
        return ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in r["summary"].items())
    if name == "kernel":
        return ", ".join(f"order {o}: fill {rows[0]['poi_per_s']:.3g}..{rows[-1]['poi_per_s']:.3g} POI/s"
                         for o, rows in r["fill"].items())
    if name == "pipeline":
        return (f"Tracker API {r['tracker_api']['poi_per_s']:.3g} POI/s, FrameTracker host "
                f"{r['frame_tracker_host']['poi_per_s']:.3g}, device {r['frame_tracker_device']['poi_per_s']:.3g}, "
                f"graph {r['graph_replay'].get('poi_per_s', float('nan')):.3g}; bitwise {r['device_loop_bitwise_equal']}")
    if name == "search":
        return ", ".join(f"{m} {r[m]['seconds']:.2f} s valid {r[m]['valid_fraction']:.3f}"
                         for m in ("zncc", "fft", "pyramid", "rg"))
    if name == "icgn":
        return ", ".join(f"order {o}: {v['poi_per_s_tracking']:.3g} POI/s track, {v['poi_per_s_end_to_end']:.3g} e2e"
                         for o, v in r["orders"].items())
    if name == "sequence":
        return (f"track-only {r['track_only_poi_per_s']:.3g} POI/s; sequence tensors {r['tensors']['poi_per_s']:.3g} "
                f"({r['tensors']['ratio_to_track_only']:.2f}x), numpy {r['numpy']['poi_per_s']:.3g} "
                f"({r['numpy']['ratio_to_track_only']:.2f}x)")
    return f"{r.get('summary', '')} (rc {r.get('returncode')})"


if __name__ == "__main__":
    main()
