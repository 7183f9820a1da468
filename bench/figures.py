"""Time and size of the field figures (issue 25, item 8): ``write_field_figure`` (the 2-D ``--figures`` frame
figure: u, v, exx, eyy, exy over the reference image) and ``write_figures`` (the stereo ``--figures`` PNGs,
one per quantity) on a 1 MP (1024 x 1024) frame.

    python -m bench.figures                       # the code on PYTHONPATH; writes bench/results/figures_cpu.json
    python -m bench.figures --label old --out /tmp/figures_old.json   # e.g. PYTHONPATH=<old checkout>

Conditions: an 8-bit speckle reference image (1024 x 1024, ~4 px speckles, seed 0); a 2-D result on a grid
of step 5 px (204 x 204 = 41 616 points, 1 % invalid) with u from +1 to +3 px and v from -12 to -5 px (offset,
one-signed fields) and its strain (window 5, ``dic.strain``); a stereo state (Field3D) on the same grid
with U, V, W in mm (W one-signed, 0.011 to 0.022 mm), strains spanning zero, ZNCC and status. Each figure is
drawn and saved ``--repeats`` times (default 3) at the library's default dpi; reported: the median wall time
per figure (wall and this process's CPU time), the PNG size and pixel size, and the load average (the machine is shared: compare runs made back
to back). Timings exclude the first draw (Matplotlib's font cache and imports).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

SIZE = 1024
STEP = 5


def speckle(size: int = SIZE, seed: int = 0) -> np.ndarray:
    """(size, size) uint8 speckle: thresholded smoothed noise (~4 px dots), lightly blurred."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    g = gaussian_filter(rng.standard_normal((size, size)), 1.4)
    img = gaussian_filter((g > 0).astype(np.float64), 0.7)
    return np.round(30 + 190 * img).astype(np.uint8)


def field2d():
    """A Field2D-like result on a step-5 grid: u +1..+3 px, v -12..-5 px (one-signed), 1 % invalid."""
    c = np.arange(10, SIZE - 10, STEP, dtype=np.float64)
    gy, gx = np.meshgrid(c, c, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    x, y = pts[:, 0] / SIZE, pts[:, 1] / SIZE
    u = 1.0 + 2.0 * x + 0.05 * np.sin(6 * y)
    v = -12.0 + 7.0 * y + 0.1 * np.cos(5 * x)
    valid = np.random.default_rng(1).uniform(size=len(pts)) > 0.01
    return SimpleNamespace(points=pts, u=u, v=v, valid=valid)


def field3d():
    from dic.field3d import Field3D

    f2 = field2d()
    pts, n = f2.points, len(f2.points)
    ny = nx = int(round(np.sqrt(n)))
    rng = np.random.default_rng(2)
    status = np.where(f2.valid, 0, 3).astype(np.int8)
    ok = status == 0
    x, y = pts[:, 0] / SIZE, pts[:, 1] / SIZE

    def nan(a):
        return np.where(ok, a, np.nan)

    e = {k: nan(rng.normal(scale=1e-3, size=n) + s * (x - 0.5)) for k, s in (("exx", 2e-3), ("eyy", -1e-3), ("exy", 0))}
    return Field3D(points=pts, grid_shape=(ny, nx), X=nan(pts[:, 0] * 0.05 - 25), Y=nan(pts[:, 1] * 0.05 - 25),
                   Z=nan(500 + 0.2 * x), U=nan(0.02 * x - 0.01), V=nan(-0.03 + 0.01 * y), W=nan(0.011 + 0.011 * x * y),
                   **e, normal=np.where(ok[:, None], [0.0, 0.0, -1.0], np.nan), zncc_stereo=nan(rng.uniform(0.9, 1, n)),
                   zncc_left=rng.uniform(0.9, 1, n), zncc_right=rng.uniform(0.9, 1, n),
                   epipolar_ref_px=rng.uniform(0, 0.1, n), epipolar_px=rng.uniform(0, 0.1, n),
                   reprojection_ref_px=rng.uniform(0, 0.1, n), reprojection_px=rng.uniform(0, 0.1, n),
                   status=status, strain_valid=ok.copy(), index=1)


def _png_shape(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    return int.from_bytes(head[20:24], "big"), int.from_bytes(head[16:20], "big")


def _timed(fn, repeats: int):
    """Median wall time, all wall times, median CPU time of this process (less sensitive to a loaded
    machine than wall time: Matplotlib draws on one thread) and the last result of ``fn()``."""
    fn()  # warm-up (fonts, imports)
    times, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return statistics.median(times), times, statistics.median(cpu), out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--label", default="new")
    ap.add_argument("--out", default=None, help="JSON path (default bench/results/figures_cpu.json)")
    args = ap.parse_args(argv)

    import matplotlib

    import dic
    from dic._strain import strain
    from dic.plots.fields import write_field_figure, write_figures

    load_before = os.getloadavg()
    ref = speckle()
    f2 = field2d()
    s2 = strain(f2, window=5)
    f3 = field3d()
    tmp = Path(tempfile.mkdtemp(prefix="bench_figures_"))
    rows = {}

    t2, all2, c2, p2 = _timed(lambda: write_field_figure(tmp / "frame.png", ref, f2, s2, title="frame 1"), args.repeats)
    rows["2d_frame_figure"] = {"seconds": t2, "all_seconds": all2, "cpu_seconds": c2, "panels": 5, "bytes": p2.stat().st_size,
                               "pixels_hw": _png_shape(p2)}
    t3, all3, c3, paths = _timed(lambda: write_figures(f3, ref, tmp / "stereo", prefix="s1_"), args.repeats)
    sizes = {p.stem.removeprefix("s1_"): p.stat().st_size for p in paths}
    rows["stereo_state_figures"] = {"seconds": t3, "all_seconds": all3, "cpu_seconds": c3, "figures": len(paths),
                                    "seconds_per_figure": t3 / len(paths), "cpu_seconds_per_figure": c3 / len(paths), "bytes": sizes,
                                    "max_bytes": max(sizes.values()), "pixels_hw": _png_shape(paths[0])}
    load_after = os.getloadavg()
    result = {"label": args.label, "dic": str(Path(dic.__file__).parent), "matplotlib": matplotlib.__version__,
              "numpy": np.__version__, "python": platform.python_version(), "cpu_count": os.cpu_count(),
              "loadavg_before": load_before, "loadavg_after": load_after, "image": [SIZE, SIZE], "step": STEP,
              "points": len(f2.points), "repeats": args.repeats, "results": rows, "files": str(tmp)}
    out = Path(args.out) if args.out else Path(__file__).parent / "results" / "figures_cpu.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    r2, r3 = rows["2d_frame_figure"], rows["stereo_state_figures"]
    print(f"[{args.label}] dic from {result['dic']}; load {load_before[0]:.1f} -> {load_after[0]:.1f}")
    print(f"2-D frame figure (5 panels): {r2['seconds']:.2f} s (CPU {r2['cpu_seconds']:.2f} s), {r2['bytes'] / 1e3:.0f} KB, {r2['pixels_hw']} px")
    print(f"stereo state: {r3['figures']} figures, {r3['seconds_per_figure']:.2f} s per figure "
          f"(CPU {r3['cpu_seconds_per_figure']:.2f} s), "
          f"largest {r3['max_bytes'] / 1e3:.0f} KB, {r3['pixels_hw']} px")
    print(f"wrote {out}; figures in {tmp}")
    return result


if __name__ == "__main__":
    main()
