"""Throughput and accuracy of IC-GN subset tracking (kernels/icgn.py), Warp vs. NumPy/SciPy.

Run from the repository root::

    .venv/bin/python -m bench.icgn [--size 2048] [--step 2] [--devices cpu cuda:0] [--quick]

On a ``--size``^2 8-bit Boolean speckle pair (dic.synth) with a known sub-pixel shift, POIs on a
grid of ``--step`` px, 21x21 subsets, zero initial guess, for both shape-function orders and every
available device (or those given):

* ``reference``: per-reference work (reference gradients + per-POI Hessians), done once per
  reference image (``prepare_reference`` + ``prepare_subsets``);
* ``current``: per-image B-spline prefilter (``prepare_current``);
* ``icgn``: the iterations (``icgn``).

POI/s are reported for tracking a new image (``current`` + ``icgn``, the sequence case) and end to
end (all three, one image pair). Compilation is excluded (a warm-up on a few POIs first), the device
is synchronised, and the median of ``--repeats`` runs is kept; the process CPU time is recorded to
show how many cores the run actually got (the development machine is shared).

The denominator of the speed-up is a plain NumPy/SciPy implementation of the same IC-GN (same
subsets, Hessian, ZNSSD update, compositions and convergence test; vectorised over POIs,
``scipy.ndimage.map_coordinates`` for the cubic B-spline) run on a random subsample of
``--numpy-points`` POIs and extrapolated linearly to POI/s.

Writes ``bench/results/icgn_<device>.json`` and prints a table.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from datetime import datetime, timezone

import numpy as np
import scipy
import warp as wp
from scipy import ndimage

from bench._host import cpu_model
from dic._track import grid
from dic.synth import speckle_pair
from kernels._device import available_devices, resolve_device
from kernels._launch import cpu_threads
from kernels.conventions import Status
from kernels.icgn import icgn, n_params, prepare_current, prepare_reference, prepare_subsets

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
GOOD = (int(Status.CONVERGED), int(Status.MAX_ITERATIONS))


# ----------------------------------------------------------------------------------------------
# NumPy/SciPy reference implementation of the same IC-GN


def _monomials(xi, eta, order):
    m = [np.ones_like(xi), xi, eta]
    if order == 2:
        m += [0.5 * xi * xi, xi * eta, 0.5 * eta * eta]
    return np.stack(m, axis=-1)


def _bspline_gradients(coef):
    """Exact derivatives of the cubic B-spline interpolant at the pixel centres."""
    c = np.pad(coef, 1, mode="reflect")  # mirror coefficients c[-1] = c[1] (scipy mode='mirror')
    dx = c[:, 2:] - c[:, :-2]
    dy = c[2:, :] - c[:-2, :]
    fx = (dx[:-2] + 4 * dx[1:-1] + dx[2:]) / 12.0
    fy = (dy[:, :-2] + 4 * dy[:, 1:-1] + dy[:, 2:]) / 12.0
    return fx, fy


def _affine(p):
    m = np.zeros(p.shape[:1] + (3, 3))
    m[:, 0] = np.stack([1 + p[:, 1], p[:, 2], p[:, 0]], -1)
    m[:, 1] = np.stack([p[:, 4], 1 + p[:, 5], p[:, 3]], -1)
    m[:, 2, 2] = 1
    return m


def _quad(p):
    a1, a2, a3 = 1 + p[:, 1], p[:, 2], p[:, 0]
    b1, b2, b3 = p[:, 7], 1 + p[:, 8], p[:, 6]
    uxx, uxy, uyy, vxx, vxy, vyy = (p[:, k] for k in (3, 4, 5, 9, 10, 11))
    z = np.zeros_like(a1)
    rows = [
        [a1 * a1 + a3 * uxx, 2 * (a1 * a2 + a3 * uxy), a2 * a2 + a3 * uyy, 2 * a3 * a1, 2 * a3 * a2, a3 * a3],
        [a1 * b1 + 0.5 * (a3 * vxx + b3 * uxx), a1 * b2 + a2 * b1 + a3 * vxy + b3 * uxy,
         a2 * b2 + 0.5 * (a3 * vyy + b3 * uyy), a3 * b1 + a1 * b3, a3 * b2 + a2 * b3, a3 * b3],
        [b1 * b1 + b3 * vxx, 2 * (b1 * b2 + b3 * vxy), b2 * b2 + b3 * vyy, 2 * b3 * b1, 2 * b3 * b2, b3 * b3],
        [0.5 * uxx, uxy, 0.5 * uyy, a1, a2, a3],
        [0.5 * vxx, vxy, 0.5 * vyy, b1, b2, b3],
        [z, z, z, z, z, z + 1],
    ]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def _compose(p, dp, order, s):
    if order == 1:
        m = _affine(p) @ np.linalg.inv(_affine(dp))
        return np.stack([m[:, 0, 2], m[:, 0, 0] - 1, m[:, 0, 1], m[:, 1, 2], m[:, 1, 0], m[:, 1, 1] - 1], -1)
    scale = np.array([1 / s, 1, 1, s, s, s] * 2)
    m = _quad(p * scale) @ np.linalg.inv(_quad(dp * scale))
    rx, ry = m[:, 3], m[:, 4]
    out = np.stack([rx[:, 5], rx[:, 3] - 1, rx[:, 4], 2 * rx[:, 0], rx[:, 1], 2 * rx[:, 2],
                    ry[:, 5], ry[:, 3], ry[:, 4] - 1, 2 * ry[:, 0], ry[:, 1], 2 * ry[:, 2]], -1)
    return out / scale


def numpy_icgn(ref, cur, points, subset, order, max_iter, tol):
    """IC-GN / ZNSSD vectorised over integer POIs; returns (params, iterations, timings)."""
    t0 = time.perf_counter()
    r = subset // 2
    s = float(r)
    k = n_params(order)
    j, i = (a.ravel().astype(float) for a in np.mgrid[-r:r + 1, -r:r + 1])
    mono = _monomials(i / s, j / s, order)  # (n, m)
    cref = ndimage.spline_filter(ref.astype(np.float64), order=3, mode="mirror")
    fxi, fyi = _bspline_gradients(cref)
    cx, cy = points[:, 0].astype(int), points[:, 1].astype(int)
    rows = cy[:, None] + j.astype(int)[None]
    cols = cx[:, None] + i.astype(int)[None]
    f = ref[rows, cols].astype(np.float64)
    jac = np.concatenate([fxi[rows, cols][..., None] * mono, fyi[rows, cols][..., None] * mono], axis=-1)
    fz = f - f.mean(1, keepdims=True)
    fnorm = np.linalg.norm(fz, axis=1)
    jc = jac - jac.mean(1, keepdims=True)
    hinv = np.linalg.inv(np.einsum("npk,npl->nkl", jc, jc))
    t_ref = time.perf_counter() - t0
    t0 = time.perf_counter()
    ccur = ndimage.spline_filter(cur.astype(np.float64), order=3, mode="mirror")
    scale = np.array([1, s, s, 1, s, s] if order == 1 else [1, s, s, s * s, s * s, s * s] * 2, float)
    params = np.zeros((len(points), k))
    iters = np.zeros(len(points), int)
    active = np.arange(len(points))
    for _ in range(max_iter):
        if active.size == 0:
            break
        p = params[active]
        if order == 1:
            u = p[:, [0]] + p[:, [1]] * i + p[:, [2]] * j
            v = p[:, [3]] + p[:, [4]] * i + p[:, [5]] * j
        else:
            u = p[:, [0]] + p[:, [1]] * i + p[:, [2]] * j + 0.5 * p[:, [3]] * i * i + p[:, [4]] * i * j + 0.5 * p[:, [5]] * j * j
            v = p[:, [6]] + p[:, [7]] * i + p[:, [8]] * j + 0.5 * p[:, [9]] * i * i + p[:, [10]] * i * j + 0.5 * p[:, [11]] * j * j
        g = ndimage.map_coordinates(ccur, [rows[active] + v, cols[active] + u], order=3, mode="mirror", prefilter=False)
        gz = g - g.mean(1, keepdims=True)
        e = fz[active] - (fnorm[active] / np.linalg.norm(gz, axis=1))[:, None] * gz
        dq = -np.einsum("nkl,nl->nk", hinv[active], np.einsum("npk,np->nk", jac[active], e))
        params[active] = _compose(p, dq / scale, order, s)
        iters[active] += 1
        active = active[np.linalg.norm(dq, axis=1) >= tol]
    t_cur = time.perf_counter() - t0
    return params, iters, {"reference_s": t_ref, "current_and_icgn_s": t_cur}


# ----------------------------------------------------------------------------------------------
# timing




def _timed(fn, device):
    wp.synchronize_device(device)
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn()
    wp.synchronize_device(device)
    return out, time.perf_counter() - t0, time.process_time() - c0


def bench_device(device, ref, cur, points, shift, subset, max_iter, tol, repeats):
    rows = {}
    for order in (1, 2):
        k = n_params(order)
        # warm-up: compiles and loads every kernel involved (excluded from the timings)
        warm = prepare_subsets(prepare_reference(ref[:128, :128], device=device), points[:8] % 100 + 12,
                               subset=subset, order=order)
        icgn(warm, prepare_current(cur[:128, :128], device=device), max_iter=2).numpy()
        rec = {"reference_s": [], "current_s": [], "icgn_s": [], "cpu_s": []}
        for _ in range(repeats):
            subs, t_ref, c_ref = _timed(lambda: prepare_subsets(prepare_reference(ref, device=device), points,
                                                                subset=subset, order=order), device)
            curp, t_cur, c_cur = _timed(lambda: prepare_current(cur, device=device), device)
            res, t_icgn, c_icgn = _timed(lambda: icgn(subs, curp, max_iter=max_iter, tol=tol), device)
            rec["reference_s"].append(t_ref)
            rec["current_s"].append(t_cur)
            rec["icgn_s"].append(t_icgn)
            rec["cpu_s"].append(c_ref + c_cur + c_icgn)
            out = res.numpy()
            subs = res = None  # free the buffers before the next repeat
        n = len(points)
        med = {key: statistics.median(v) for key, v in rec.items()}
        wall = med["reference_s"] + med["current_s"] + med["icgn_s"]
        ok = np.isin(out["status"], GOOD)
        eu = out["params"][ok, 0] - shift[0]
        ev = out["params"][ok, k // 2] - shift[1]
        rows[order] = {
            "n_points": n,
            "seconds_median": med,
            "seconds_all": rec,
            "poi_per_s_tracking": n / (med["current_s"] + med["icgn_s"]),
            "poi_per_s_tracking_best": n / min(a + b for a, b in zip(rec["current_s"], rec["icgn_s"])),
            "poi_per_s_end_to_end": n / wall,
            "cores_used": med["cpu_s"] / wall if str(device) == "cpu" else None,
            # POIs per CPU-second (end to end): what one fully available core delivers; on a shared
            # machine this, times the core count, estimates the unloaded throughput (not measured)
            "poi_per_cpu_s_end_to_end": n / med["cpu_s"] if str(device) == "cpu" else None,
            "mean_iterations": float(out["iterations"].mean()),
            "converged_fraction": float(np.mean(out["status"] == int(Status.CONVERGED))),
            "u_bias_px": float(eu.mean()), "u_std_px": float(eu.std()),
            "v_bias_px": float(ev.mean()), "v_std_px": float(ev.std()),
        }
    return rows


def bench_numpy(ref, cur, points, shift, subset, max_iter, tol, n_sub, seed=0):
    rng = np.random.default_rng(seed)
    sub = points[rng.choice(len(points), size=min(n_sub, len(points)), replace=False)]
    rows = {}
    for order in (1, 2):
        k = n_params(order)
        c0 = time.process_time()
        params, iters, t = numpy_icgn(ref, cur, sub, subset, order, max_iter, tol)
        cpu = time.process_time() - c0
        total = t["reference_s"] + t["current_and_icgn_s"]
        rows[order] = {
            "n_points": len(sub),
            "seconds": t,
            "cpu_s": cpu,
            "poi_per_s_tracking": len(sub) / t["current_and_icgn_s"],
            "poi_per_s_end_to_end": len(sub) / total,
            "mean_iterations": float(iters.mean()),
            "u_bias_px": float((params[:, 0] - shift[0]).mean()), "u_std_px": float((params[:, 0] - shift[0]).std()),
            "v_bias_px": float((params[:, k // 2] - shift[1]).mean()),
            "v_std_px": float((params[:, k // 2] - shift[1]).std()),
        }
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=2048, help="image side (px), default 2048")
    ap.add_argument("--step", type=int, default=2, help="POI grid step (px), default 2")
    ap.add_argument("--subset", type=int, default=21)
    ap.add_argument("--shift", type=float, nargs=2, default=(0.35, -0.2), help="rigid (u, v) shift (px)")
    ap.add_argument("--devices", nargs="*", default=None, help="default: every available device")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--numpy-points", type=int, default=3000, help="POIs of the NumPy baseline subsample")
    ap.add_argument("--max-iter", type=int, default=30)
    ap.add_argument("--tol", type=float, default=1e-3)
    ap.add_argument("--quick", action="store_true", help="512^2 image, 1 repeat, 500 NumPy POIs (smoke test)")
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.repeats, args.numpy_points = 512, 1, 500
    devices = args.devices or available_devices()
    devices = [resolve_device(d) for d in devices]
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    ref, cur = speckle_pair((args.size, args.size), tuple(args.shift), seed=2024, bits=8)
    t_synth = time.perf_counter() - t0
    points = grid(ref.shape, args.step, margin=args.subset // 2)
    print(f"{args.size}x{args.size} speckle pair, shift {tuple(args.shift)} px ({t_synth:.1f} s to render), "
          f"{len(points)} POIs (step {args.step}, subset {args.subset}), CPU threads {cpu_threads()}", flush=True)
    np_rows = bench_numpy(ref, cur, points, args.shift, args.subset, args.max_iter, args.tol, args.numpy_points)
    for order, row in np_rows.items():
        print(f"  numpy/scipy order {order}: {row['poi_per_s_end_to_end']:.0f} POI/s end to end "
              f"({row['n_points']} POIs, {row['mean_iterations']:.2f} iterations)", flush=True)
    header = (f"{'device':<8} {'order':>5} {'POIs':>9} {'track POI/s':>12} {'e2e POI/s':>11} {'numpy POI/s':>12} "
              f"{'speed-up':>9} {'iters':>6} {'cores':>6} {'e2e/CPU-s':>10} {'u bias':>9} {'u std':>8}")
    lines = []
    for device in devices:
        rows = bench_device(device, ref, cur, points, args.shift, args.subset, args.max_iter, args.tol, args.repeats)
        result = {
            "benchmark": "icgn",
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "device": device,
            "device_name": wp.get_device(device).name,
            "cpu_model": cpu_model(),
            "cpu_count": os.cpu_count(),
            "cpu_threads_used": cpu_threads(),
            "load_average_before": load0,
            "load_average_after": os.getloadavg(),
            "versions": {"warp": wp.config.version, "numpy": np.__version__, "scipy": scipy.__version__,
                         "python": sys.version.split()[0]},
            "parameters": {"size": args.size, "step": args.step, "subset": args.subset, "shift_px": list(args.shift),
                           "n_points": len(points), "max_iter": args.max_iter, "tol_px": args.tol,
                           "initial_guess": "zero", "image": "dic.synth.speckle_pair 8-bit, seed 2024",
                           "repeats": args.repeats},
            "warp": {str(o): r for o, r in rows.items()},
            "numpy_scipy": {str(o): r for o, r in np_rows.items()},
            "speedup_end_to_end": {str(o): rows[o]["poi_per_s_end_to_end"] / np_rows[o]["poi_per_s_end_to_end"]
                                   for o in rows},
            "speedup_tracking": {str(o): rows[o]["poi_per_s_tracking"] / np_rows[o]["poi_per_s_tracking"]
                                 for o in rows},
            "note": "NumPy/SciPy figures are measured on a random subsample of POIs and extrapolated linearly",
        }
        for order, r in rows.items():
            lines.append(f"{device:<8} {order:>5} {r['n_points']:>9} {r['poi_per_s_tracking']:>12.0f} "
                         f"{r['poi_per_s_end_to_end']:>11.0f} {np_rows[order]['poi_per_s_end_to_end']:>12.0f} "
                         f"{result['speedup_end_to_end'][str(order)]:>9.1f} {r['mean_iterations']:>6.2f} "
                         f"{(r['cores_used'] or 0):>6.2f} {(r['poi_per_cpu_s_end_to_end'] or 0):>10.0f} "
                         f"{r['u_bias_px']:>+9.5f} {r['u_std_px']:>8.5f}")
        if not args.no_write:
            os.makedirs(RESULTS, exist_ok=True)
            path = os.path.join(RESULTS, f"icgn_{device.replace(':', '')}.json")
            with open(path, "w") as fh:
                json.dump(result, fh, indent=2)
            print(f"wrote {path}")
    print(header)
    print("\n".join(lines))
    print("track = prepare_current + icgn (a new image of a known reference); e2e adds the reference "
          "precomputation; speed-up = e2e / NumPy-SciPy e2e; cores = process CPU time / wall time; "
          "e2e/CPU-s = POIs per CPU-second end to end (CPU only)")


if __name__ == "__main__":
    main()
