"""Stereo-DIC throughput on a 2-camera 5-megapixel sequence (dic.stereo.StereoCorrelation).

Run from the repository root::

    .venv/bin/python -m bench.stereo [--frames 2] [--step 5] [--device cpu] [--cache DIR]

Scene (virtual lab, exact ground truth): two 2448x2048 px (5.0 MP) pinhole cameras with 35 mm
lenses (f = 4901 px), 300 mm apart, toed in on a point 1 m away; a 500 x 450 mm speckled plane
(Boolean model, 0.4 mm = 2 px disk radius) facing them at 1 m, translated by a known 3-D vector
in each later state. Images rendered with 4 samples per pixel, 8-bit, no sensor noise (rendering
is not timed; ``--cache`` keeps the images between runs).

Timed, per device, after a warm-up on a small crop (kernel compilation excluded), 2nd-order
21 px subsets on a grid of ``--step`` px (about 197 000 POIs at step 5):

* the reference: SIFT features + epipolar filter + guesses, left -> right IC-GN with propagation,
  triangulation and the reference Field3D;
* each later state: left and right temporal IC-GN tracks (previous state as guess), epipolar
  check, triangulation, strain -> matched+triangulated POIs per second and frames per second.

Also reports the accuracy against the exact geometry (distance to the true plane, error of the
measured translation). Writes bench/results/stereo_<device>.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings
from datetime import datetime, timezone

import cv2
import numpy as np
import warp as wp

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
SIZE = (2448, 2048)
TRANSLATION_PER_STATE_MM = np.array([0.4, -0.25, 1.5])


def _scene(states: int):
    from dataclasses import replace

    from dic.lab import Displacement, LabCamera, Scene, SpecklePlane
    from dic.synth import make_speckle

    cams = [LabCamera.from_lens(name=name, size=SIZE, focal_length_mm=35.0, f_number=float("inf"),
                                focus_distance_mm=1000.0, position=(x, 0.0, 0.0), look_at_point=(0.0, 0.0, 1000.0),
                                exposure_dn=200.0, bit_depth=8)
            for name, x in (("left", -150.0), ("right", 150.0))]
    speckle = make_speckle(region=(-5, -5, 505, 455), radius=0.4, density=0.5, bits=None, seed=3)
    plane = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=(500.0, 450.0),
                                speckle=speckle)
    scenes = []
    for k in range(states):
        t_local = plane.R_world_surface.T @ (k * TRANSLATION_PER_STATE_MM)
        disp = Displacement(np.broadcast_to(t_local, (2, 2, 3)).copy(), (0.0, 0.0), (500.0, 450.0))
        scenes.append(Scene(cameras=cams, planes=[replace(plane, displacement=disp)]))
    return cams, plane, scenes


def _images(scenes, cache, samples):
    from dic.lab import render

    out = []
    for k, scene in enumerate(scenes):
        pair = []
        for i in range(2):
            path = os.path.join(cache, f"state{k}_cam{i}_s{samples}.png") if cache else None
            if path and os.path.exists(path):
                pair.append(cv2.imread(path, cv2.IMREAD_UNCHANGED))
                continue
            img = render(scene, i, samples=samples, seed=100 * k + i)
            if path:
                os.makedirs(cache, exist_ok=True)
                cv2.imwrite(path, img)
            pair.append(img)
        out.append(tuple(pair))
    return out


def _rig(cams):
    from calibration.stereo import StereoRig

    left, right = cams
    R = right.R_cam_world @ left.R_cam_world.T
    return StereoRig(left.camera, right.camera, R, right.t_cam_world - R @ left.t_cam_world)


def _warm_up(rig, images, device):
    """Compile and load every kernel on a 400x320 crop (sizes unknown to the rig: no size check)."""
    from dataclasses import replace

    from calibration.stereo import StereoRig
    from dic.stereo import StereoCorrelation

    small = StereoRig(replace(rig.left, size=(0, 0)), replace(rig.right, size=(0, 0)), rig.R_right_left,
                      rig.t_right_left)
    crop = (slice(800, 1120), slice(1000, 1400))
    with warnings.catch_warnings():
        # the crop does not fit the rig (its principal point moved): a compile-only run, nothing need match
        warnings.simplefilter("ignore", RuntimeWarning)
        sc = StereoCorrelation(small, images[0][0][crop], images[0][1][crop], step=20, device=device)
        sc.measure(images[0][0][crop], images[0][1][crop])


def bench_device(device, rig, images, plane_left, step, subset):
    from dic.stereo import StereoCorrelation

    _warm_up(rig, images, device)
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    sc = StereoCorrelation(rig, images[0][0], images[0][1], step=step, subset=subset, order=2, device=device)
    wp.synchronize_device(device)
    t_ref = time.perf_counter() - t0
    n = len(sc.points)
    ref = sc.reference
    normal, centre = plane_left
    ok = ref.valid
    dist = (ref.xyz[ok] - centre) @ normal
    reference = {"seconds": t_ref, "n_points": n, "n_valid": int(ok.sum()), "pois_per_s": n / t_ref,
                 "stages_s": dict(sc.timings), "n_features": sc.match.n_features,
                 "status_counts": ref.counts(),
                 "plane_distance_rms_mm": float(np.sqrt(np.mean(dist ** 2))),
                 "plane_distance_max_mm": float(np.abs(dist).max())}
    frames = []
    for k in range(1, len(images)):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        f = sc.measure(images[k][0], images[k][1], index=k)
        wp.synchronize_device(device)
        dt = time.perf_counter() - t0
        ok = f.valid
        true = k * TRANSLATION_PER_STATE_MM  # world = left camera axes rotated; compare in the world frame below
        frames.append({"index": k, "seconds": dt, "pois_per_s": n / dt, "frames_per_s": 1.0 / dt,
                       "n_valid": int(ok.sum()), "stages_s": dict(sc.timings), "status_counts": f.counts(),
                       "uvw_true_world_mm": true.tolist(), "uvw": f.uvw[ok]})
    return reference, frames, sc


def main(argv=None):
    from kernels._device import available_devices, resolve_device
    from kernels._launch import cpu_threads

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=2, help="later states after the reference (default 2)")
    parser.add_argument("--step", type=int, default=5)
    parser.add_argument("--subset", type=int, default=21)
    parser.add_argument("--samples", type=int, default=4, help="render samples per pixel")
    parser.add_argument("--device", default=None, help="cpu or cuda:0 (default: every available device)")
    parser.add_argument("--cache", default=None, help="folder to keep the rendered images in between runs")
    args = parser.parse_args(argv)
    devices = [resolve_device(args.device)] if args.device else available_devices()
    cams, plane, scenes = _scene(args.frames + 1)
    t0 = time.perf_counter()
    images = _images(scenes, args.cache, args.samples)
    t_render = time.perf_counter() - t0
    rig = _rig(cams)
    left = cams[0]
    normal = left.R_cam_world @ plane.R_world_surface[:, 2]
    centre = left.R_cam_world @ plane.to_world(np.array([[250.0, 225.0]]))[0] + left.t_cam_world
    os.makedirs(RESULTS, exist_ok=True)
    for device in devices:
        reference, frames, sc = bench_device(device, rig, images, (normal, centre), args.step, args.subset)
        for fr in frames:
            true_left = left.R_cam_world @ np.asarray(fr["uvw_true_world_mm"])
            err = fr.pop("uvw") - true_left
            fr["uvw_error_mean_mm"] = err.mean(axis=0).tolist()
            fr["uvw_error_std_mm"] = err.std(axis=0).tolist()
        info = wp.get_device(device)
        result = {
            "benchmark": "stereo",
            "device": device,
            "device_name": info.name,
            "cpu_threads": cpu_threads() if device == "cpu" else None,
            "host": {"machine": platform.machine(), "processor": platform.processor(), "cpu_count": os.cpu_count()},
            "versions": {"python": sys.version.split()[0], "warp": wp.__version__, "numpy": np.__version__,
                         "opencv": cv2.__version__},
            "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "parameters": {"image_size": list(SIZE), "megapixels": SIZE[0] * SIZE[1] / 1e6, "step": args.step,
                           "subset": args.subset, "order": 2, "states": args.frames + 1,
                           "render_samples": args.samples, "render_seconds_not_timed": t_render,
                           "rig": "2 x 2448x2048, f = 4901 px, baseline 300 mm, plane at 1 m",
                           "timing": "wall clock, compilation excluded (warm-up on a crop), NumPy images in, "
                                     "Field3D out"},
            "reference": reference,
            "frames": frames,
            "summary": {"n_points": reference["n_points"],
                        "reference_pois_per_s": reference["pois_per_s"],
                        "frame_pois_per_s_median": float(np.median([f["pois_per_s"] for f in frames])) if frames else None,
                        "frames_per_s_median": float(np.median([f["frames_per_s"] for f in frames])) if frames else None,
                        "seconds_per_frame_median": float(np.median([f["seconds"] for f in frames])) if frames else None},
        }
        path = os.path.join(RESULTS, f"stereo_{device.replace(':', '')}.json")
        with open(path, "w") as fh:
            json.dump(result, fh, indent=2)
        print(f"\n{device} ({info.name}), {SIZE[0]}x{SIZE[1]} px, step {args.step}: {reference['n_points']} POIs")
        print(f"reference: {reference['seconds']:.1f} s ({reference['pois_per_s']:.0f} POIs/s), "
              f"stages {json.dumps({k: round(v, 2) for k, v in reference['stages_s'].items()})}")
        for fr in frames:
            print(f"state {fr['index']}: {fr['seconds']:.1f} s ({fr['pois_per_s']:.0f} POIs/s, "
                  f"{fr['frames_per_s']:.3f} frames/s), stages {json.dumps({k: round(v, 2) for k, v in fr['stages_s'].items()})}")
        print(f"accuracy: plane distance RMS {reference['plane_distance_rms_mm']:.4f} mm; "
              + "; ".join(f"state {fr['index']} U,V,W error mean {np.round(fr['uvw_error_mean_mm'], 4).tolist()} "
                          f"std {np.round(fr['uvw_error_std_mm'], 4).tolist()} mm" for fr in frames))
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
