"""Throughput and precision of undistortion and triangulation (kernels/triangulate.py).

Run from the repository root::

    .venv/bin/python -m bench.triangulate [--points 200000 1000000] [--device cpu] [--repeats 5]

For each available device (or the one given): points per second of ``undistort_points``,
``triangulate(method="linear")`` and ``triangulate(method="optimal")`` on the long-range rig of
the paper (baseline 1.65 m, 5.4 m working distance, 2352x1728 px, f ~ 4050 px, real distortion),
data with 0.02 px noise, after a warm-up launch (compilation excluded), device synchronised, median
of ``--repeats`` runs, host<->device copies included (the public API takes and returns NumPy).
OpenCV (undistortPoints with 5 default iterations + triangulatePoints, CPU) is timed on the same
data for scale. It also measures what float32 would cost in precision (see docs/stereo.md):
noise-free 3-D error with float32-rounded input pixels, and of a float32 DLT (NumPy SVD).
Writes bench/results/triangulate_<device>.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from datetime import datetime, timezone

import cv2
import numpy as np
import warp as wp

from calibration.camera import Camera
from dic._triangulate import triangulate, undistort_points
from kernels._device import available_devices, resolve_device
from kernels._launch import cpu_threads

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")


class Rig:  # duck-typed calibration.stereo.StereoRig
    def __init__(self, left, right, R_right_left, t_right_left):
        self.left, self.right, self.R_right_left, self.t_right_left = left, right, R_right_left, t_right_left


def _look_at(centre, target, roll):
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    c, s = np.cos(roll), np.sin(roll)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ R
    return R, -R @ centre


def long_range_rig() -> Rig:
    """The paper's geometry (dic.lab.paper: baseline, working distance, sensor) with typical lens errors."""
    from dic.lab.paper import BASELINE_MM, IMAGE_SIZE_PX, WORKING_DISTANCE_MM

    left = Camera(np.array([[4050.0, 0, 1176.3], [0, 4051.5, 861.2], [0, 0, 1]]),
                  np.array([-0.085, 0.21, 2.1e-4, -3.3e-4, -0.35]), tuple(IMAGE_SIZE_PX), "left")
    right = Camera(np.array([[4062.0, 0, 1170.9], [0, 4060.8, 866.4], [0, 0, 1]]),
                   np.array([-0.078, 0.17, -1.5e-4, 2.4e-4, -0.22]), tuple(IMAGE_SIZE_PX), "right")
    target = np.array([0.0, 150.0, WORKING_DISTANCE_MM])
    R_l, t_l = _look_at(np.array([-BASELINE_MM / 2, 0.0, 0.0]), target, 0.002)
    R_r, t_r = _look_at(np.array([BASELINE_MM / 2, 0.0, 0.0]), target, -0.004)
    R = R_r @ R_l.T
    return Rig(left, right, R, t_r - R @ t_l)


def rig_points(rig, n, rng):
    left, right = rig.left, rig.right
    w, h = left.size
    uv = np.column_stack([rng.uniform(10, w - 11, 3 * n), rng.uniform(10, h - 11, 3 * n)])
    z = rng.uniform(4500.0, 6300.0, 3 * n)
    X = np.column_stack([left.undistort_normalized(left.pixels_to_normalized(uv)) * z[:, None], z])
    uvr = right.project(X @ rig.R_right_left.T + rig.t_right_left)
    inside = np.all((uvr > 10) & (uvr < np.array(right.size) - 11), axis=1)
    X = X[inside][:n]
    return X, left.project(X), right.project(X @ rig.R_right_left.T + rig.t_right_left)


def _time(fn, device, repeats):
    times = []
    for _ in range(repeats):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _float32_dlt(rig, xl, xr):
    """Homogeneous DLT in float32 (NumPy SVD), same formulation as the kernel (unit baseline)."""
    s = np.linalg.norm(rig.t_right_left)
    P2 = np.hstack([rig.R_right_left, rig.t_right_left[:, None] / s]).astype(np.float32)
    xl, xr = xl.astype(np.float32), xr.astype(np.float32)
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))]).astype(np.float32)
    A = np.stack([xl[:, 0:1] * P1[2] - P1[0], xl[:, 1:2] * P1[2] - P1[1],
                  xr[:, 0:1] * P2[2] - P2[0], xr[:, 1:2] * P2[2] - P2[1]], axis=1)
    v = np.linalg.svd(A)[2][:, -1, :]
    return (v[:, :3] / v[:, 3:4]).astype(np.float64) * s


def precision(rig, rng, device, n=20000):
    X, uvl, uvr = rig_points(rig, n, rng)
    out = {"n_points": n}
    for method in ("linear", "optimal"):
        pts = triangulate(rig, uvl, uvr, method=method, device=device).points
        out[f"noise_free_max_error_mm_{method}_float64"] = float(np.max(np.linalg.norm(pts - X, axis=1)))
    pts = triangulate(rig, uvl.astype(np.float32), uvr.astype(np.float32), method="optimal", device=device).points
    out["noise_free_max_error_mm_float32_input_pixels"] = float(np.max(np.linalg.norm(pts - X, axis=1)))
    out["noise_free_rms_error_mm_float32_input_pixels"] = float(np.sqrt(np.mean(np.sum((pts - X) ** 2, axis=1))))
    xl = rig.left.undistort_normalized(rig.left.pixels_to_normalized(uvl))
    xr = rig.right.undistort_normalized(rig.right.pixels_to_normalized(uvr))
    pts = _float32_dlt(rig, xl, xr)
    out["noise_free_max_error_mm_float32_dlt"] = float(np.max(np.linalg.norm(pts - X, axis=1)))
    out["noise_free_rms_error_mm_float32_dlt"] = float(np.sqrt(np.mean(np.sum((pts - X) ** 2, axis=1))))
    ideal = rig.left.normalized_to_pixels(xl)
    und = undistort_points(rig.left, uvl, device=device).points
    out["undistortion_max_error_px_float64"] = float(np.max(np.abs(und - ideal)))
    cv_default = cv2.undistortPoints(uvl.reshape(-1, 1, 2), rig.left.K, rig.left.dist, P=rig.left.K).reshape(-1, 2)
    out["undistortion_max_error_px_opencv_default"] = float(np.max(np.abs(cv_default - ideal)))
    sigma = 0.02
    nl, nr = uvl + rng.normal(0, sigma, uvl.shape), uvr + rng.normal(0, sigma, uvr.shape)
    for method in ("linear", "optimal"):
        r = triangulate(rig, nl, nr, method=method, device=device)
        err = r.points - X
        out[f"noise_{sigma}px_{method}"] = {
            "residual_rms_px": float(np.sqrt(np.mean(r.residuals ** 2))),
            "error_std_mm_xyz": [float(v) for v in err.std(axis=0)],
            "error_mean_mm_xyz": [float(v) for v in err.mean(axis=0)],
            "status_counts": r.counts(),
        }
    return out


def bench_device(device, sizes, repeats, rng):
    rig = long_range_rig()
    n_max = max(sizes)
    X, uvl, uvr = rig_points(rig, min(n_max, 200000), rng)
    reps = -(-n_max // len(X))
    uvl = np.tile(uvl, (reps, 1))[:n_max] + rng.normal(0, 0.02, (n_max, 2))
    uvr = np.tile(uvr, (reps, 1))[:n_max] + rng.normal(0, 0.02, (n_max, 2))
    triangulate(rig, uvl[:16], uvr[:16], device=device)  # warm-up: compile and load
    rows = []
    for n in sizes:
        pl, pr = uvl[:n], uvr[:n]
        row = {"n_points": n}
        row["undistort_pts_per_s"] = n / _time(lambda: undistort_points(rig.left, pl, device=device), device, repeats)
        for method in ("linear", "optimal"):
            dt = _time(lambda: triangulate(rig, pl, pr, method=method, device=device), device, repeats)
            row[f"{method}_pts_per_s"] = n / dt

        def opencv():
            il = cv2.undistortPoints(pl.reshape(-1, 1, 2), rig.left.K, rig.left.dist, P=rig.left.K)
            ir = cv2.undistortPoints(pr.reshape(-1, 1, 2), rig.right.K, rig.right.dist, P=rig.right.K)
            P1 = rig.left.K @ np.hstack([np.eye(3), np.zeros((3, 1))])
            P2 = rig.right.K @ np.hstack([rig.R_right_left, rig.t_right_left[:, None]])
            cv2.triangulatePoints(P1, P2, il.reshape(-1, 2).T.copy(), ir.reshape(-1, 2).T.copy())

        row["opencv_linear_cpu_pts_per_s"] = n / _time(opencv, "cpu", repeats)
        rows.append(row)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, nargs="+", default=[100000, 1000000])
    parser.add_argument("--device", default=None, help="cpu or cuda:0 (default: every available device)")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    devices = [resolve_device(args.device)] if args.device else available_devices()
    os.makedirs(RESULTS, exist_ok=True)
    for device in devices:
        rng = np.random.default_rng(2024)
        rows = bench_device(device, args.points, args.repeats, rng)
        prec = precision(long_range_rig(), rng, device)
        info = wp.get_device(device)
        result = {
            "benchmark": "triangulate",
            "device": device,
            "device_name": info.name,
            "cpu_threads": cpu_threads() if device == "cpu" else None,
            "host": {"machine": platform.machine(), "processor": platform.processor(), "cpu_count": os.cpu_count()},
            "versions": {"python": sys.version.split()[0], "warp": wp.__version__, "numpy": np.__version__,
                         "opencv": cv2.__version__},
            "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "parameters": {"rig": "baseline 1.65 m, 5.4 m, 2352x1728, f~4050 px", "noise_px": 0.02,
                           "repeats": args.repeats, "timing": "median, compilation excluded, NumPy in/out"},
            "throughput": rows,
            "precision": prec,
        }
        path = os.path.join(RESULTS, f"triangulate_{device.replace(':', '')}.json")
        with open(path, "w") as fh:
            json.dump(result, fh, indent=2)
        print(f"\n{device} ({info.name})")
        print(f"{'points':>10} {'undistort/s':>14} {'linear/s':>14} {'optimal/s':>14} {'OpenCV lin/s':>14}")
        for r in rows:
            print(f"{r['n_points']:>10} {r['undistort_pts_per_s']:>14.3g} {r['linear_pts_per_s']:>14.3g} "
                  f"{r['optimal_pts_per_s']:>14.3g} {r['opencv_linear_cpu_pts_per_s']:>14.3g}")
        print(json.dumps(prec, indent=1))
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
