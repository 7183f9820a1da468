"""Per-frame host overhead of 2-D tracking: today's path against the device-resident frame path (issue 16).

``python -m bench.frame_overhead [--device cpu] [--frames 3] [--quick]``

For each size (1024², step 5 and 2048², step 10; ``--quick``: 256², step 8), 8-bit frames of a synthetic
speckle sequence (``dic.synth.speckle_pair``, small rigid shifts), subset 21, order 1, one reference:

* ``tracker``: ``dic.Tracker.track(frame_uint8, guess=previous, search=None)`` through the general
  path (before issue 16: host conversion and checks of the frame, ``prepare_current``,
  ``Correlator.run_all``, acceptance, implausible-warp flags, uncertainty, the ``Field2D``);
* ``tracker_resident``: the same call as it runs now (``Correlator.run_frame``: the device-resident path,
  then the same acceptance, flags, uncertainty and ``Field2D``);
* ``icgn_loop``: the bare loop of today's kernels, ``prepare_current(frame_uint8, out=buffer)`` then
  ``icgn(subsets, current, guess, out=buffers).numpy()`` with the guess propagated on the host;
* ``frame_tracker``: ``kernels.frames.FrameTracker.track(frame_uint8)`` (the guess propagated on the device).

Every Warp launch is timed (CPU launches are synchronous; on CUDA the launch timer synchronises), so
the per-frame time splits into the IC-GN kernel, the other kernels (prefilter, expansion, guess,
packing) and the host (everything else). Reported: medians over frames 2..N (frame 1 compiles).
Writes ``bench/results/frame_overhead_<device>.json``.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np


def _timed_launches(modules):
    """Wrap ``launch_1d`` in ``modules`` to add each launch's seconds to a dict keyed 'icgn' / 'other'."""
    import warp as wp

    acc = {"icgn": 0.0, "other": 0.0}
    originals = {}
    for mod in modules:
        real = mod.launch_1d
        originals[mod] = real

        def timed(kernel, n, inputs, device, offset_index, min_chunk=256, _real=real):
            t0 = time.perf_counter()
            _real(kernel, n, inputs, device, offset_index, min_chunk)
            if not str(device).startswith("cpu"):
                wp.synchronize_device(device)
            key = "icgn" if "icgn" in kernel.key else "other"
            acc[key] += time.perf_counter() - t0

        mod.launch_1d = timed
    return acc, originals


def run(device: str, sizes, n_frames: int) -> dict:
    import warp as wp

    import kernels.frames
    import kernels.icgn
    import kernels.interp
    from dic._track import Tracker
    from dic.synth import speckle_pair
    from kernels.frames import FrameTracker
    from kernels.icgn import icgn, prepare_current

    results = []
    for size, step in sizes:
        shape = (size, size)
        ref, _ = speckle_pair(shape, (0, 0), seed=2024)
        frames = [speckle_pair(shape, (0.3 * k, -0.2 * k), seed=2024)[1].astype(np.uint8) for k in range(1, n_frames + 1)]
        tracker = Tracker(ref, step=step, subset=21, device=device)
        subsets = tracker.correlator.subsets
        n = tracker.n_points
        acc, originals = _timed_launches([kernels.icgn, kernels.interp, kernels.frames])
        row = {"size": size, "step": step, "n_points": n}
        try:
            def measure(name, step_fn):
                per = []
                for fr in frames:
                    acc["icgn"] = acc["other"] = 0.0
                    t0 = time.perf_counter()
                    step_fn(fr)
                    if not device.startswith("cpu"):
                        wp.synchronize_device(device)
                    total = time.perf_counter() - t0
                    per.append((total, acc["icgn"], acc["other"]))
                per = np.array(per[1:] if len(per) > 1 else per)
                med = np.median(per, axis=0)
                row[name] = {"total_ms": 1e3 * med[0], "icgn_kernel_ms": 1e3 * med[1], "other_kernels_ms": 1e3 * med[2],
                             "host_ms": 1e3 * (med[0] - med[1] - med[2]),
                             "outside_icgn_ms": 1e3 * (med[0] - med[1]), "frames": int(per.shape[0])}

            state = {"g": None}

            def tracker_step(fr):
                f = tracker.track(fr, guess=state["g"], search=None)
                ok = f.valid
                state["g"] = np.where(ok[:, None], f.params, 0.0 if state["g"] is None else state["g"])

            track_module = sys.modules["dic._track"]
            resident = track_module._device_resident
            track_module._device_resident = lambda image: False  # today's general path
            try:
                measure("tracker", tracker_step)
            finally:
                track_module._device_resident = resident
            state["g"] = None
            measure("tracker_resident", tracker_step)
            buf = {"cur": None, "out": None, "g": np.zeros((n, 6))}

            def loop_step(fr):
                buf["cur"] = prepare_current(fr, device=device, out=buf["cur"])
                buf["out"] = icgn(subsets, buf["cur"], guess=buf["g"], out=buf["out"])
                r = buf["out"].numpy()
                ok = np.isin(r["status"], (0, 1)) & (r["zncc"] >= 0.8)
                buf["g"] = np.where(ok[:, None], r["params"], buf["g"])

            measure("icgn_loop", loop_step)
            ft = FrameTracker(subsets, np.uint8)
            measure("frame_tracker", lambda fr: ft.track(fr))
        finally:
            for mod, real in originals.items():
                mod.launch_1d = real
        results.append(row)
        print(json.dumps(row, indent=None, default=float))
    return {"device": device, "platform": platform.platform(), "processor": platform.processor(),
            "warp": wp.__version__, "numpy": np.__version__, "results": results}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--frames", type=int, default=3)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    from kernels._device import resolve_device

    device = resolve_device(a.device)
    sizes = [(256, 8)] if a.quick else [(1024, 5), (2048, 10)]
    res = run(device, sizes, max(2, a.frames))
    out = Path(a.out) if a.out else Path(__file__).parent / "results" / f"frame_overhead_{device.replace(':', '')}.json"
    out.write_text(json.dumps(res, indent=1, default=float))
    print("wrote", out)


if __name__ == "__main__":
    main()
