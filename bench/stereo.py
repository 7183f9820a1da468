"""Stereo-DIC throughput on a 2-camera 5-megapixel sequence (dic.StereoCorrelation).

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
    try:
        from dic.lab import stereo_rig
    except ImportError:  # checkouts before a822256 (the bench runs on older code for before/after figures)
        from calibration.stereo import StereoRig

        left, right = cams
        R = right.R_cam_world @ left.R_cam_world.T
        return StereoRig(left.camera, right.camera, R, right.t_cam_world - R @ left.t_cam_world)
    return stereo_rig(*cams)


def _warm_up(rig, images, device):
    """Compile and load every kernel on a 400x320 crop (sizes unknown to the rig: no size check)."""
    from dataclasses import replace

    from calibration.stereo import StereoRig
    from dic._stereo import StereoCorrelation

    small = StereoRig(replace(rig.left, size=(0, 0)), replace(rig.right, size=(0, 0)), rig.R_right_left,
                      rig.t_right_left)
    h, w = images[0][0].shape[:2]
    crop = (slice(h // 2 - 160, h // 2 + 160), slice(w // 2 - 200, w // 2 + 200))
    with warnings.catch_warnings():
        # the crop does not fit the rig (its principal point moved): a compile-only run, nothing need match
        warnings.simplefilter("ignore", RuntimeWarning)
        sc = StereoCorrelation(small, images[0][0][crop], images[0][1][crop], step=20, device=device)
        sc.measure(images[0][0][crop], images[0][1][crop])


def bench_device(device, rig, images, plane_left, step, subset):
    from dic._stereo import StereoCorrelation

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


# ================================================================================================
# the stereo state rate and the reference-match rate as ratios to the 2-D one-frame rate (issue 23), and a
# 1920x1200 sequence end to end. These run on any Specula version with StereoCorrelation, Tracker, ResultWriter
# and stereo_sequence (run as a script with PYTHONPATH=<old checkout> for the "before" figures).

RATE_SIZE = (1024, 1024)
E2E_SIZE = (1920, 1200)


_LEFT_R_CAM_WORLD = {}  # image size -> the left camera's R_cam_world of the last _lab_pairs scene


def _lab_pairs(size, states, plane_mm, cache, samples, tag):
    """A toed-in 16 mm / 7.4 um stereo pair (baseline 300 mm, 1 m) of a speckled plane translated per state.

    Returns ``(rig, pairs, files, specimen_box)``: image arrays, their PNG files in ``cache`` and the inclusive
    box ``(x0, y0, x1, y1)`` px of the specimen in the left image (5 px inside its projected corners)."""
    from dataclasses import replace

    from dic.lab import Displacement, LabCamera, Scene, SpecklePlane, render
    from dic.synth import make_speckle

    cams = [LabCamera.from_lens(name=name, size=size, focal_length_mm=16.0, f_number=float("inf"),
                                focus_distance_mm=1000.0, position=(x, 0.0, 0.0), look_at_point=(0.0, 0.0, 1000.0),
                                exposure_dn=200.0, bit_depth=8)
            for name, x in (("left", -150.0), ("right", 150.0))]
    w_mm, h_mm = plane_mm
    speckle = make_speckle(region=(-5, -5, w_mm + 5, h_mm + 5), radius=0.8, density=0.5, bits=None, seed=3)
    plane = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=(w_mm, h_mm),
                                speckle=speckle)
    os.makedirs(cache, exist_ok=True)
    pairs, files = [], []
    for k in range(states):
        t_local = plane.R_world_surface.T @ (k * TRANSLATION_PER_STATE_MM)
        disp = Displacement(np.broadcast_to(t_local, (2, 2, 3)).copy(), (0.0, 0.0), (w_mm, h_mm))
        scene = Scene(cameras=cams, planes=[replace(plane, displacement=disp)])
        pair, names = [], []
        for i in range(2):
            path = os.path.join(cache, f"{tag}_{size[0]}x{size[1]}_state{k}_cam{i}_s{samples}.png")
            if not os.path.exists(path):
                cv2.imwrite(path, render(scene, i, samples=samples, seed=100 * k + i))
            pair.append(cv2.imread(path, cv2.IMREAD_UNCHANGED))
            names.append(path)
        pairs.append(tuple(pair))
        files.append(tuple(names))
    rig = _rig(cams)
    _LEFT_R_CAM_WORLD[size] = cams[0].R_cam_world  # the exact displacements in the left camera frame (e2e accuracy)
    corners = np.array([[0.0, 0.0], [w_mm, 0.0], [0.0, h_mm], [w_mm, h_mm]])
    world = plane.to_world(corners)
    xyz = world @ cams[0].R_cam_world.T + cams[0].t_cam_world
    uv = cams[0].camera.project(xyz)
    box = (int(np.ceil(uv[:, 0].min())) + 5, int(np.ceil(uv[:, 1].min())) + 5,
           int(np.floor(uv[:, 0].max())) - 5, int(np.floor(uv[:, 1].max())) - 5)
    box = (max(box[0], 0), max(box[1], 0), min(box[2], size[0] - 1), min(box[3], size[1] - 1))
    return rig, pairs, files, box


def _load():
    """The 1-minute load average and the machine's core count (the figures are taken on a shared machine)."""
    try:
        return {"loadavg_1min": os.getloadavg()[0], "cpu_count": os.cpu_count()}
    except OSError:
        return {"loadavg_1min": None, "cpu_count": os.cpu_count()}


def bench_rate(device, step, subset, states, cache, samples):
    """Stereo state rate and reference-match rate as ratios to the one-frame 2-D rate on the same POIs.

    2-D: :class:`dic.Tracker` on the left reference with the stereo POIs (order 2, the stereo max_iter),
    each left image of the sequence tracked from zero (the first), then from the two frames before (the reference
    frame's zero the first of them) extrapolated at constant velocity (as the stereo tracks start with ``motion_prediction="velocity"``, the
    default, on this smooth motion: the same start for both; the device frame path), one frame timed =
    ``Tracker.track``. Stereo: the reference (``StereoCorrelation(...)``: features, match, right
    reference, reference field; also its match stages alone), then per state ``measure`` (two tracks,
    triangulation, acceptance, strain, uncertainty) + ``ResultWriter.write_frame`` (HDF5, fsync).

    On a shared, loaded machine the load drifts within seconds, so the 2-D frames and the stereo states are
    interleaved (2-D frame k, then stereo state k) and each state is compared with the 2-D frame next to it:
    the ratio is the median of the per-state ratios (the reference match: against the mean of the 2-D frames
    timed just before and just after it). Each 2-D frame and state also records its process CPU time (every
    thread: the IC-GN launches run on all cores), whose per-state ratios (``state_cpu_ratio_to_2d``) vary
    less with the machine's load than the wall-time ratios."""
    import tempfile

    from dic._stereo import StereoCorrelation
    from dic._track import Tracker
    from dic.store import ResultWriter

    rig, pairs, files, _ = _lab_pairs(RATE_SIZE, states, (500.0, 450.0), cache, samples, "rate")
    _warm_up(rig, pairs, device)
    load_before = _load()
    # the 2-D tracker first (its reference preparation is not timed), on the stereo POIs: the same grid rule
    from dic.correlation.points import grid_points

    points = grid_points(pairs[0][0].shape, step, subset, None)[0]
    # plain IC-GN, as the stereo tracks (2-D defaults to adaptive robust IC-GN and its neighbour check since issue 26)
    tracker = Tracker(pairs[0][0], points=points, subset=subset, order=2, max_iter=50, tol=1e-3, search=None,
                      device=device, robust=False)
    prev = tracker.track(pairs[1][0])  # warm (buffers allocated)

    def frame_2d(k, guess):
        t0, c0 = time.perf_counter(), time.process_time()
        if isinstance(guess, tuple):  # the two frames before: the stereo tracks' constant-velocity start, for 2-D too
            # (None: the reference frame, whose parameters are zero)
            last = guess[1].params
            before = np.zeros_like(last) if guess[0] is None else guess[0].params
            guess = np.where(np.isfinite(before) & np.isfinite(last), 2.0 * last - before, last)
        f = tracker.track(pairs[k][0], guess=guess)
        wp.synchronize_device(device)
        cpu_2d.append(time.process_time() - c0)
        return f, time.perf_counter() - t0

    cpu_2d = []

    _, t_before = frame_2d(1, None)
    t0, c0 = time.perf_counter(), time.process_time()
    sc = StereoCorrelation(rig, pairs[0][0], pairs[0][1], step=step, subset=subset, order=2, device=device)
    sc.reference  # noqa: B018 - the reference state complete (its strain and uncertainty are computed on first read)
    wp.synchronize_device(device)
    t_ref, c_ref = time.perf_counter() - t0, time.process_time() - c0
    _, t_after = frame_2d(1, None)
    cpu_2d_ref = list(cpu_2d)
    cpu_2d.clear()
    if not np.array_equal(sc.points, points):
        raise RuntimeError("the 2-D and stereo POIs differ")
    timings = dict(sc.timings)
    n = int(len(sc.points))
    t2d, t_states, c_states, stages = [], [], [], []
    prev = None
    with tempfile.TemporaryDirectory() as tmp:
        writer = ResultWriter(os.path.join(tmp, "rate.h5"), kind="stereo", reference_path=files[0],
                              reference_shape=pairs[0][0].shape, settings={"step": step}, rig=rig, mode="overwrite")
        with writer:
            writer.write_match(sc.match)
            writer.write_frame(0, sc.reference, path=files[0])
            before = None
            for k in range(1, states):
                # the 2-D frames start as the stereo tracks do (motion_prediction "velocity", on this smooth motion):
                # frame 1 from zero, then from the two frames before extrapolated, the reference's zero the first of
                # them (the same IC-GN work per point)
                f2d, dt = frame_2d(k, None if prev is None else (before, prev))
                before, prev = prev, f2d
                t2d.append(dt)
                t0, c0 = time.perf_counter(), time.process_time()
                f = sc.measure(pairs[k][0], pairs[k][1], index=k)
                writer.write_frame(k, f, path=files[k])
                wp.synchronize_device(device)
                t_states.append(time.perf_counter() - t0)
                c_states.append(time.process_time() - c0)
                stages.append(dict(sc.timings))
    ratios = [a / b for a, b in zip(t2d, t_states)]
    cpu_ratios = [a / b for a, b in zip(cpu_2d, c_states)]
    t_2d_ref = 0.5 * (t_before + t_after)
    match_s = timings.get("features_s", 0.0) + timings.get("match_icgn_s", 0.0)
    return {"n_points": n, "n_valid_reference": int(np.count_nonzero(sc.reference.valid)),
            "two_d_frame_seconds": t2d, "two_d_pois_per_s": n / float(np.median(t2d)),
            "two_d_around_reference_s": [t_before, t_after],
            "reference_seconds": t_ref, "reference_stages_s": timings,
            "reference_pois_per_s": n / t_ref, "reference_ratio_to_2d": t_2d_ref / t_ref,
            "match_seconds": match_s, "match_ratio_to_2d": t_2d_ref / match_s if match_s else None,
            "state_seconds": t_states, "state_stages_s": stages, "state_pois_per_s": n / float(np.median(t_states)),
            "state_ratios_to_2d": ratios, "state_ratio_to_2d": float(np.median(ratios)),
            # process CPU time (all threads; steadier than wall time on a loaded machine)
            "two_d_frame_cpu_seconds": cpu_2d, "two_d_around_reference_cpu_s": cpu_2d_ref,
            "reference_cpu_seconds": c_ref, "state_cpu_seconds": c_states, "state_cpu_ratios_to_2d": cpu_ratios,
            "state_cpu_ratio_to_2d": float(np.median(cpu_ratios)),
            "load_before": load_before, "load_after": _load()}


def bench_end_to_end(device, step, states, cache, samples, motion_prediction=None):
    """``stereo_sequence`` over ``states`` 1920x1200 pairs (PNG files) with a ``step`` px grid over the specimen, and
    per state the RMS of the 3-D displacement error of the valid points (mm, left camera frame) against the exact
    translation. ``motion_prediction``: given to ``stereo_sequence`` when not None (its default otherwise)."""
    import tempfile

    from dic.sequence import stereo_sequence

    rig, _, files, box = _lab_pairs(E2E_SIZE, states, (400.0, 250.0), cache, samples, "e2e")
    kw = {} if motion_prediction is None else {"motion_prediction": motion_prediction}
    load_before = _load()
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "e2e.h5")
        t0, c0 = time.perf_counter(), time.process_time()
        fields = stereo_sequence(rig, files, out, step=step, roi=box, mode="overwrite", device=device, **kw)
        seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0
        if isinstance(fields, list):  # a checkout before the sequence summary (8d9f975 and earlier)
            valid, n_points = [int(np.count_nonzero(f.valid)) for f in fields], int(len(fields[0].points))
        else:  # a SequenceSummary: points computed in the region and valid per state
            from dic.store import read_stereo

            valid, n_points = [int(v) for v in fields.n_valid], int(fields.n_points[0])
            back = read_stereo(out)
            fields = [back.fields[k] for k in back.indices]
        R = _LEFT_R_CAM_WORLD[E2E_SIZE]
        error = []
        for k, f in enumerate(fields):
            ok = np.asarray(f.valid, dtype=bool)
            true = R @ (k * TRANSLATION_PER_STATE_MM)
            error.append(float(np.sqrt(np.mean(np.sum((f.uvw[ok] - true) ** 2, axis=1)))) if ok.any() else None)
    return {"seconds": seconds, "cpu_seconds": cpu_seconds, "states": states, "roi": list(box), "n_points": n_points,
            "n_valid": valid, "uvw_error_rms_mm": error, "motion_prediction": motion_prediction,
            "load_before": load_before, "load_after": _load()}


def main_rates(argv=None):
    """``python bench/stereo.py rates|e2e ...``: the figures of issue 23 (docs/stereo.md, "Throughput")."""
    parser = argparse.ArgumentParser(description="stereo rates as ratios to the 2-D rate; end-to-end sequence")
    parser.add_argument("what", choices=("rates", "e2e"))
    parser.add_argument("--step", type=int, default=5)
    parser.add_argument("--subset", type=int, default=21)
    parser.add_argument("--states", type=int, default=None, help="pairs incl. the reference (rates 7, e2e 6)")
    parser.add_argument("--samples", type=int, default=2, help="render samples per pixel")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--cache", default=os.path.join(RESULTS, "..", ".cache"), help="rendered images")
    parser.add_argument("--motion-prediction", default=None, choices=("velocity", "none"),
                        help="e2e: stereo_sequence's motion_prediction (default: its default)")
    parser.add_argument("--label", default="after", help="a name for this run (before/after)")
    parser.add_argument("--out", default=None, help="results JSON (default bench/results/stereo_<what>_<label>.json)")
    args = parser.parse_args(argv)
    import dic

    info = {"benchmark": f"stereo_{args.what}", "label": args.label, "dic": os.path.dirname(dic.__file__),
            "device": args.device, "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "versions": {"python": sys.version.split()[0], "warp": wp.__version__, "numpy": np.__version__},
            "host": {"machine": platform.machine(), "cpu_count": os.cpu_count()},
            "parameters": {"step": args.step, "subset": args.subset, "order": 2, "render_samples": args.samples}}
    if args.what == "rates":
        info["parameters"]["image_size"] = list(RATE_SIZE)
        info["result"] = bench_rate(args.device, args.step, args.subset, args.states or 7, args.cache, args.samples)
        r = info["result"]
        print(f"{args.label}: {r['n_points']} POIs; 2-D {np.median(r['two_d_frame_seconds']):.2f} s/frame; "
              f"state {np.median(r['state_seconds']):.2f} s = {r['state_ratio_to_2d']:.3f} x 2-D (per state "
              f"{np.round(r['state_ratios_to_2d'], 3).tolist()}); CPU time: 2-D "
              f"{np.median(r['two_d_frame_cpu_seconds']):.2f} s, state {np.median(r['state_cpu_seconds']):.2f} s = "
              f"{r['state_cpu_ratio_to_2d']:.3f} x 2-D; reference "
              f"{r['reference_seconds']:.2f} s = {r['reference_ratio_to_2d']:.3f} x 2-D (match stages "
              f"{r['match_seconds']:.2f} s = {r['match_ratio_to_2d']:.3f} x); load {r['load_before']} -> {r['load_after']}")
    else:
        info["parameters"]["image_size"] = list(E2E_SIZE)
        info["result"] = bench_end_to_end(args.device, args.step, args.states or 6, args.cache, args.samples,
                                          args.motion_prediction)
        r = info["result"]
        print(f"{args.label}: {r['states']} pairs, {r['n_points']} POIs, end to end {r['seconds']:.1f} s "
              f"(CPU {r['cpu_seconds']:.1f} s); valid {r['n_valid']}; 3-D error RMS (mm) "
              f"{[None if e is None else round(e, 4) for e in r['uvw_error_rms_mm']]}; "
              f"load {r['load_before']} -> {r['load_after']}")
    path = args.out or os.path.join(RESULTS, f"stereo_{args.what}_{args.label}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        json.dump(info, fh, indent=2)
    print(f"wrote {path}")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] in ("rates", "e2e"):
        main_rates()
    else:
        main()
