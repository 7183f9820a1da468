"""Speed of the post-processing commands on an 11-frame, ~74 k-point file with a hole (issue 25):
``python -m bench.postprocess``.

Two synthetic result files are written through :class:`dic.store.ResultWriter` (uncompressed), each
with ``--frames`` frames (default 11) of the points of a ``--side`` x ``--side`` grid (default 280,
step 5 px: a 1440 x 1440 px reference image) less a circular hole of radius ``--hole`` grid steps
(default 40: 200 px) about the image centre -- the points a run with a region excluding the hole
has (78 400 - 5 025 = 73 375 points) -- and a 9 x 9 block of points invalid from frame 6 on:

* ``dic2d``: a 2-D result with the exactly linear field ``u = a_k (x - cx)``, ``v = -0.3 a_k (y - cy)``,
  ``a_k = 0.001 k``, and its strain (``dic.strain``, window 5);
* ``stereo``: a stereo result on the same left-image grid: a tilted plane ``X = 0.05 (x - cx)`` mm,
  ``Y = 0.05 (y - cy)``, ``Z = 500 + 0.3 X - 0.1 Y``, displacements ``U = a_k X``, ``W = 0.5 a_k X``
  and a uniform surface strain.

Each command then runs in a fresh process through the CLI (``specula history / profile /
extensometer / strain``, as a user types it), with BLAS and OpenMP left at their defaults (the
``*_NUM_THREADS`` variables of this process are removed from the child's environment), and its
wall time and CPU time (user + system over all its threads: less sensitive to the load of a shared
machine) are reported, with those of ``import dic.cli`` alone for reference (median of
``--repeats``, default 3). ``--code DIR`` runs the commands with ``PYTHONPATH=DIR`` (e.g.
``/work/main``, the code before issue 25) instead of this repository (children run ``python -P``,
so that the working directory does not come first on the path; the bench checks where ``dic``
is imported from); ``--out`` (default
``bench/results/postprocess_cpu.json``).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from bench._host import cpu_model, write_json

STEP = 5.0
ORIGIN = 20.0
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def grid_points(side: int, hole: float):
    """(N, 2) px points of a side x side grid at STEP px, less a circle of ``hole`` steps about its centre;
    the centre (px) and the image shape."""
    gy, gx = np.meshgrid(ORIGIN + STEP * np.arange(side), ORIGIN + STEP * np.arange(side), indexing="ij")
    x, y = gx.ravel(), gy.ravel()
    c = ORIGIN + STEP * (side - 1) / 2.0
    keep = np.hypot(x - c, y - c) > hole * STEP
    size = int(2 * ORIGIN + STEP * (side - 1)) + 1
    return np.column_stack([x[keep], y[keep]]), c, (size, size)


def _invalid_block(points, c, frame):
    """Points invalid in ``frame``: a 9 x 9 block 60 steps right of the centre, from frame 6 on."""
    x, y = points[:, 0], points[:, 1]
    block = (np.abs(x - (c + 60 * STEP)) <= 4 * STEP) & (np.abs(y - c) <= 4 * STEP)
    return block & (frame >= 6)


def write_2d(path, frames: int, side: int, hole: float):
    from dic._strain import StrainPlan
    from dic.field2d import Field2D
    from dic.store import ResultWriter

    pts, c, shape = grid_points(side, hole)
    n = len(pts)
    plan = StrainPlan(pts, window=5)
    with ResultWriter(path, reference_path="ref.tif", reference_shape=shape,
                      settings={"subset": 21, "step": int(STEP), "strain_window": 5}, compression="none") as w:
        for k in range(1, frames + 1):
            a = 1e-3 * k
            bad = _invalid_block(pts, c, k)
            u = np.where(bad, np.nan, a * (pts[:, 0] - c))
            v = np.where(bad, np.nan, -0.3 * a * (pts[:, 1] - c))
            params = np.zeros((n, 6))
            params[:, 0], params[:, 3] = u, v
            f = Field2D(points=pts, u=u, v=v, params=params, zncc=np.full(n, 0.99), iterations=np.full(n, 4, np.int32),
                        status=np.where(bad, 5, 0).astype(np.int32), valid=~bad, subset=21, order=1, step=int(STEP),
                        zncc_min=0.8)
            w.write_frame(k, f, strain=plan.strain(f), path=f"cur{k}.tif")
    return n, c


def write_stereo(path, frames: int, side: int, hole: float):
    from calibration.camera import Camera
    from calibration.stereo import StereoRig
    from dic._stereo import StereoMatch
    from dic.field3d import Field3D
    from dic.store import ResultWriter

    pts, c, shape = grid_points(side, hole)
    n = len(pts)
    K = np.array([[4000.0, 0, shape[1] / 2], [0, 4000.0, shape[0] / 2], [0, 0, 1]])
    rig = StereoRig(Camera(K=K, size=(shape[1], shape[0]), name="left"),
                    Camera(K=K, size=(shape[1], shape[0]), name="right"), np.eye(3), np.array([-300.0, 0.0, 0.0]))
    X, Y = 0.05 * (pts[:, 0] - c), 0.05 * (pts[:, 1] - c)
    Z = 500.0 + 0.3 * X - 0.1 * Y
    match = StereoMatch(points_left=pts, points_right=pts - [30.0, 0.0], params=np.zeros((n, 12)),
                        zncc=np.full(n, 0.99), iterations=np.full(n, 4, np.int32), icgn_status=np.zeros(n, np.int32),
                        epipolar_px=np.full(n, 0.01), guess_source=np.ones(n, np.int8), status=np.zeros(n, np.int8),
                        n_features=100, order=1)
    full = lambda value: np.full(n, float(value))  # noqa: E731
    with ResultWriter(path, kind="stereo", rig=rig, reference_path=("l0.tif", "r0.tif"), reference_shape=shape,
                      settings={"step": int(STEP), "subset": 21}, compression="none") as w:
        w.write_match(match)
        for k in range(frames):
            a = 1e-3 * k
            bad = _invalid_block(pts, c, k)
            nan = lambda values: np.where(bad, np.nan, values)  # noqa: E731
            f = Field3D(points=pts, grid_shape=None, X=X, Y=Y, Z=Z, U=nan(a * X), V=nan(np.zeros(n)),
                        W=nan(0.5 * a * X), exx=nan(full(a)), eyy=nan(full(-0.3 * a)), exy=nan(full(0.1 * a)),
                        normal=np.tile([0.0, 0.0, -1.0], (n, 1)), zncc_stereo=full(0.99), zncc_left=full(0.98),
                        zncc_right=full(0.97), epipolar_ref_px=full(0.01), epipolar_px=full(0.01),
                        reprojection_ref_px=full(0.01), reprojection_px=full(0.01),
                        status=np.where(bad, 3, 0).astype(np.int8), strain_valid=~bad, index=k)
            w.write_frame(k, f, path=(f"l{k}.tif", f"r{k}.tif"))
    return n, c


def commands(kind: str, src: str, c: float, hole: float, out: str) -> dict[str, list[str]]:
    """The CLI commands timed on a file of ``kind`` (the hole's centre at (c, c) px, its radius ``hole`` steps)."""
    r = hole * STEP  # px
    left, right = f"{c - r - 60:g},{c:g}", f"{c + r + 60:g},{c:g}"
    strain_q = "eyy"
    disp_q = "u" if kind == "dic2d" else "U"
    cmds = {
        "history_disp": ["history", src, "--point", f"{c - r - 30:g},{c + 25:g}", "--quantity", disp_q, "-q"],
        "history_strain": ["history", src, "--point", f"{c - r - 30:g},{c + 25:g}", "--quantity", strain_q, "-q"],
        "profile": ["profile", src, "--from", f"{c - r - 100:g},{c:g}", "--to", f"{c + r + 100:g},{c:g}",
                    "--quantity", strain_q, "-q"],
        "extensometer": ["extensometer", src, "--from", left, "--to", right, "-q"],
    }
    # strain recomputed with another window: 2-D and (since issue 25's strain25) stereo files
    cmds["strain"] = ["strain", src, "--window", "7", "-o", os.path.join(out, "w7.h5"), "-q"]
    return cmds


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_cli(args: list[str], env: dict) -> tuple[float, float, int, str]:
    """Wall time, CPU time (user + system, all threads), exit status and output tail of one command."""
    code = "import sys; from dic.cli import main; sys.argv = ['specula'] + sys.argv[1:]; main()"
    cpu, t = _children_cpu(), time.perf_counter()
    p = subprocess.run([sys.executable, "-P", "-c", code, *args], env=env, capture_output=True, text=True)
    return time.perf_counter() - t, _children_cpu() - cpu, p.returncode, (p.stdout + p.stderr).strip()[-300:]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=11)
    ap.add_argument("--side", type=int, default=280)
    ap.add_argument("--hole", type=float, default=40.0, help="hole radius, grid steps")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--kinds", default="dic2d,stereo")
    ap.add_argument("--only", default=None,
                    help="commands to time, e.g. history_disp,profile,extensometer (default: all)")
    ap.add_argument("--code", default=None, help="PYTHONPATH of the code to time (default: this repository)")
    ap.add_argument("--out", default="bench/results/postprocess_cpu.json")
    args = ap.parse_args(argv)
    code = os.path.abspath(args.code or os.getcwd())
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    env["PYTHONPATH"] = code  # and python -P: the working directory is not put first on the path
    check = subprocess.run([sys.executable, "-P", "-c", "import dic; print(dic.__file__)"], env=env, check=True,
                           capture_output=True, text=True).stdout.strip()
    if not check.startswith(code + os.sep):
        raise SystemExit(f"the child imports dic from {check}, not from {code}")
    load0 = os.getloadavg()
    result = {"benchmark": "postprocess", "cpu": cpu_model(), "cores": os.cpu_count(), "python": platform.python_version(),
              "numpy": np.__version__, "code": code, "frames": args.frames, "side": args.side, "hole_steps": args.hole,
              "repeats": args.repeats, "thread_variables_removed": list(THREAD_VARIABLES), "runs": {}}
    times, cpus = [], []
    for _ in range(args.repeats):
        cpu, t = _children_cpu(), time.perf_counter()
        subprocess.run([sys.executable, "-P", "-c", "import dic.cli"], env=env, check=True)
        times.append(time.perf_counter() - t)
        cpus.append(_children_cpu() - cpu)
    result["import_seconds"] = round(float(np.median(times)), 3)
    result["import_cpu_seconds"] = round(float(np.median(cpus)), 3)
    print(f"import dic.cli: {result['import_seconds']:.2f} s wall, {result['import_cpu_seconds']:.2f} s CPU  (code: {code})")
    workdir = tempfile.mkdtemp(prefix="bench_postprocess_")
    try:
        for kind in [k for k in args.kinds.split(",") if k]:
            src = os.path.join(workdir, f"{kind}.h5")
            t = time.perf_counter()
            n, c = (write_2d if kind == "dic2d" else write_stereo)(src, args.frames, args.side, args.hole)
            print(f"{kind}: {args.frames} frames x {n} points written in {time.perf_counter() - t:.1f} s, "
                  f"{os.path.getsize(src) / 2**20:.0f} MiB")
            runs = result["runs"].setdefault(kind, {"points": n})
            for name, cmd in commands(kind, src, c, args.hole, workdir).items():
                if args.only and name not in args.only.split(","):
                    continue
                walls, cpus = [], []
                for _ in range(args.repeats):
                    wall, cpu, rc, tail = run_cli(cmd, env)
                    walls.append(wall)
                    cpus.append(cpu)
                runs[name] = {"command": "specula " + " ".join(os.path.basename(a) if a.startswith(workdir) else a
                                                               for a in cmd),
                              "seconds": round(float(np.median(walls)), 3), "all_seconds": [round(w, 3) for w in walls],
                              "cpu_seconds": round(float(np.median(cpus)), 3),
                              "exit_status": rc, "output_tail": tail}
                print(f"  {name:>15}: {runs[name]['seconds']:7.2f} s wall, {runs[name]['cpu_seconds']:7.2f} s CPU "
                      f"(exit {rc})  {runs[name]['command']}", flush=True)
                result["load_average"] = {"before": load0, "after": os.getloadavg()}
                with open(args.out + ".partial", "w") as fh:  # what is done so far, should a slow run be stopped
                    json.dump(result, fh, indent=1)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    result["load_average"] = {"before": load0, "after": os.getloadavg()}
    write_json(result, args.out)
    if os.path.exists(args.out + ".partial"):
        os.unlink(args.out + ".partial")


if __name__ == "__main__":
    main()
