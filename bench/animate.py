"""Time and size of ``specula animate`` movies (issue 25, "Movies and point clouds"): ``dic.animate.write_animation``
of a 2-D result file as MP4 and GIF, without and with a reference image beneath the maps.

    python -m bench.animate                 # writes bench/results/animate_cpu.json

Conditions: a 2-D result file of 11 frames on a grid of 240 x 307 points (73 680 points, step 4 px, like the
11-frame CFRP file of issue 25) with u growing from frame to frame (0.1 k + 0.001 k x + 0.01 sin(y / 30) px);
quantity ``u``, 5 frames per second, default dpi (80: 400 px maps, 576 x 448 px frames); the reference image is
a 980 x 1250 uniform noise image (the worst case for the codec). A first movie (not reported) warms up the
imports and Matplotlib's font cache. Reported per movie: wall time, time per frame, file size, and the load
average (the machine is shared).
"""
from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

N_FRAMES = 11
GRID = (240, 307)
STEP = 4.0


def build(path: Path) -> None:
    from dic.field2d import Field2D
    from dic.store import ResultWriter

    ny, nx = GRID
    gy, gx = np.meshgrid(np.arange(ny) * STEP + 10, np.arange(nx) * STEP + 10, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    n = len(pts)
    with ResultWriter(path, reference_path="none.tif", reference_shape=(980, 1250), settings={"step": STEP}) as w:
        for k in range(1, N_FRAMES + 1):
            u = 0.1 * k + 1e-3 * k * pts[:, 0] + 0.01 * np.sin(pts[:, 1] / 30)
            v = np.full(n, -0.05 * k)
            params = np.zeros((n, 6))
            params[:, 0], params[:, 3] = u, v
            status = np.zeros(n, np.int32)
            w.write_frame(k, Field2D(points=pts, u=u, v=v, params=params, zncc=np.full(n, 0.95),
                                     iterations=np.full(n, 3, np.int32), status=status, valid=status == 0, subset=21,
                                     order=1, step=int(STEP), zncc_min=0.8), path=f"cur{k}.tif")


def main() -> None:
    from dic.animate import write_animation

    image = np.random.default_rng(0).random((980, 1250))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        build(tmp / "run.h5")
        write_animation(tmp / "run.h5", tmp / "warm.gif", quantity="u", frames=[1])
        for name, img in (("u.mp4", None), ("u_image.mp4", image), ("u.gif", None), ("u_image.gif", image)):
            t = time.perf_counter()
            out = write_animation(tmp / "run.h5", tmp / name, quantity="u", fps=5, image=img)
            wall = time.perf_counter() - t
            rows.append({"movie": name, "reference_image": img is not None, "frames": N_FRAMES, "wall_s": round(wall, 3),
                         "s_per_frame": round(wall / N_FRAMES, 3), "kbytes": round(os.path.getsize(out) / 1e3, 1)})
            print(f"{name:>12}: {wall:6.2f} s ({wall / N_FRAMES:.3f} s/frame), {rows[-1]['kbytes']:7.1f} KB")
    result = {"benchmark": "animate", "points": GRID[0] * GRID[1], "rows": rows, "load_average": os.getloadavg(),
              "cpu_count": os.cpu_count(), "python": platform.python_version()}
    out = Path(__file__).parent / "results" / "animate_cpu.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
