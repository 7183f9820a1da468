"""Stereo defaults by measurement: shape-function order and subset size against exact truth.

Run from the repository root::

    .venv/bin/python -m bench.defaults_stereo [--size 480 360] [--samples 16] [--out FILE]

Scene (virtual lab, dic.lab, exact ground truth): two pinhole cameras (12 mm lens, 7.4 um pixels,
f = 1641 px, no distortion), 300 mm apart (``--baseline``), toed in on a point 1000 mm away; a 300 x 250 mm speckled
plane (Boolean model, 1.2 mm disk radius ~ 2 px) facing them at 1000 mm. Images ray-traced with
``--samples`` samples per pixel, with the lab's sensor noise, 8-bit. States, each against the
reference pair:

* ``rigid``: a translation (1.0, -0.5, 2.0) mm;
* ``stretch``: a uniform in-plane stretch of 0.5 % along the plane's x axis;
* ``bulge``: an out-of-plane bulge w = 3 mm sin(pi X / 300) sin(pi Y / 250) with a 0.5 % stretch
  (a curved, non-uniform field: what 2nd-order subsets are for).

For each order (1, 2) and subset (21, 31, 41 px) at step 10 px: the RMS of the 3-D displacement
error (mm, left camera frame) over the points valid in that state, the RMS of the W error, and the
valid count. Truth: each left reference pixel's ray intersected with the plane gives its material
point, whose displacement the scene's :class:`dic.lab.Displacement` evaluates exactly as rendered.
Writes bench/results/defaults_stereo.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace
from datetime import datetime, timezone

import numpy as np

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
PLANE_MM = (300.0, 250.0)


def _lab(size, samples, baseline_mm=300.0):
    from calibration.stereo import StereoRig
    from dic.lab import Displacement, LabCamera, Scene, SpecklePlane, render
    from dic.synth import make_speckle

    cams = [LabCamera.from_lens(name=name, size=tuple(size), focal_length_mm=12.0, f_number=float("inf"),
                                focus_distance_mm=1000.0, position=(x, 0.0, 0.0), look_at_point=(0.0, 0.0, 1000.0),
                                exposure_dn=200.0, bit_depth=8)
            for name, x in (("left", -baseline_mm / 2), ("right", baseline_mm / 2))]
    speckle = make_speckle(region=(-5, -5, PLANE_MM[0] + 5, PLANE_MM[1] + 5), radius=1.2, density=0.5, bits=None, seed=3)
    plane = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=PLANE_MM, speckle=speckle)
    extent = (0, PLANE_MM[0], 0, PLANE_MM[1])
    t_local = plane.R_world_surface.T @ np.array([1.0, -0.5, 2.0])
    fields = {
        "rigid": lambda X, Y: (t_local[0] + 0 * X, t_local[1] + 0 * X, t_local[2] + 0 * X),
        "stretch": lambda X, Y: (0.005 * (X - 150.0), 0.0 * Y, 0.0 * X),
        "bulge": lambda X, Y: (0.005 * (X - 150.0), 0.0 * Y,
                               -3.0 * np.sin(np.pi * X / PLANE_MM[0]) * np.sin(np.pi * Y / PLANE_MM[1])),
    }
    states = {}
    for k, (name, func) in enumerate([("reference", None), *fields.items()]):
        p = plane if func is None else replace(plane, displacement=Displacement.from_function(func, extent, step=5.0))
        scene = Scene(cameras=cams, planes=[p])
        states[name] = (tuple(render(scene, i, samples=samples, seed=10 * k + i, noise=True) for i in range(2)),
                        p.displacement)
    left, right = cams
    R = right.R_cam_world @ left.R_cam_world.T
    rig = StereoRig(left.camera, right.camera, R, right.t_cam_world - R @ left.t_cam_world)
    return rig, states, plane, left


def _truth(rig, plane, left, points, displacement):
    """(N, 3) mm: the exact displacement, left camera frame, of the material point seen at each left pixel."""
    xy = rig.left.undistort_normalized(rig.left.pixels_to_normalized(points))
    rays_left = np.column_stack([xy, np.ones(len(xy))])
    rays_world = rays_left @ left.R_cam_world          # rows: R_world_left @ ray
    origin_world = -left.R_cam_world.T @ left.t_cam_world
    n = plane.R_world_surface[:, 2]
    centre = plane.to_world(np.array([[0.0, 0.0]]))[0]
    s = ((centre - origin_world) @ n) / (rays_world @ n)
    X_world = origin_world + rays_world * s[:, None]
    XY_local = (X_world - centre) @ plane.R_world_surface[:, :2]
    u_local = displacement.evaluate(XY_local)
    return (u_local @ plane.R_world_surface.T) @ left.R_cam_world.T


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, nargs=2, default=(480, 360), help="image width height px")
    parser.add_argument("--samples", type=int, default=16, help="render samples per pixel")
    parser.add_argument("--step", type=int, default=10)
    parser.add_argument("--subsets", type=int, nargs="+", default=(21, 31, 41))
    parser.add_argument("--baseline", type=float, default=300.0, help="camera distance mm (300: 17 deg between the axes)")
    parser.add_argument("--out", default=os.path.join(RESULTS, "defaults_stereo.json"))
    args = parser.parse_args(argv)

    from dic._stereo import StereoCorrelation

    t0 = time.perf_counter()
    rig, states, plane, left = _lab(args.size, args.samples, args.baseline)
    print(f"rendered {len(states)} pairs of {args.size[0]}x{args.size[1]} px in {time.perf_counter() - t0:.0f} s")
    (l0, r0), _ = states["reference"]
    rows = []
    for order in (1, 2):
        for subset in args.subsets:
            sc = StereoCorrelation(rig, l0, r0, step=args.step, subset=subset, order=order, device="cpu")
            for name in ("rigid", "stretch", "bulge"):
                (l1, r1), disp = states[name]
                f = sc.measure(l1, r1, index=1, use_previous=False)
                ok = f.valid
                truth = _truth(rig, plane, left, f.points[ok], disp)
                err = np.column_stack([f.U, f.V, f.W])[ok] - truth
                row = {"order": order, "subset": subset, "state": name, "points": len(f), "valid": int(ok.sum()),
                       "rms_3d_um": 1e3 * float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))),
                       "rms_w_um": 1e3 * float(np.sqrt(np.mean(err[:, 2] ** 2))),
                       "rms_uv_um": 1e3 * float(np.sqrt(np.mean(np.sum(err[:, :2] ** 2, axis=1))))}
                rows.append(row)
                print(f"order {order} subset {subset:2d} {name:8s}: valid {row['valid']:5d}/{row['points']:5d}  "
                      f"3-D {row['rms_3d_um']:7.2f} um  W {row['rms_w_um']:7.2f} um  in-plane {row['rms_uv_um']:7.2f} um",
                      flush=True)
    out = {"benchmark": "defaults_stereo", "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           "machine": platform.processor() or platform.machine(), "size_px": list(args.size),
           "samples": args.samples, "baseline_mm": args.baseline, "step": args.step, "rows": rows}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(out, fh, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
