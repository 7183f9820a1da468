"""Calibration of the paper's stereo rig in the virtual lab, from rendered images to the rig (issue 4).

Run from the repository root (the full-resolution run renders ~300 images and takes hours on the shared
2-core CPU; rendered stacks are cached in ``--cache`` so an interrupted run resumes)::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m repro.calibration_lab                 # full resolution
    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m repro.calibration_lab --scale 0.25 --samples 4   # quick
    .venv/bin/python -m repro.calibration_lab --export session/     # image folders for the CLI walk-through

On 2 cores, render first with one process per camera (Warp's CPU launches use one core each), then run::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m repro.calibration_lab --render-only left &
    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m repro.calibration_lab --render-only right; wait
    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m repro.calibration_lab

What it does, in the virtual lab's paper rig (``dic.lab.paper_rig``: two 2352 × 1728 px 8-bit cameras
with read noise 1 DN and shot noise, 28 mm f/2.8 lenses focused at 5.4 m, 1650 mm baseline, mirrors
400 mm ahead, the 27" monitor 650 mm behind the cameras):

* renders, for each camera, the N-step phase target (``calibration.targets.PhaseTarget``) at
  direct poses through the depth of field (1.15–3.4 m, tilts up to 30°, blur up to ~28 px) and
  through the mirror at the mount's tilts, plus the monitor at places both cameras see;
* runs ``calibration.pipeline`` on the images: intrinsics (direct + mirrored views in one bundle),
  mirror extrinsics per camera, the rig (per camera and joint with the far view), and
  reconstructs independent check views (distances between dots);
* compares with the lab's ground truth, for the paper-faithful setup (6×3 dots, 3 tilts, per-camera
  composition), the improved one (24×12 dots, 5 tilts, joint adjustment with the far view) and the
  "more views" one (the improved setup with 48 instead of 12 direct poses of both targets per camera:
  ``EXTRA_DIRECT_POSES``; ``--extra-views 0`` leaves it out), and
  with ``cv2.stereoCalibrate`` from a 9×6 checkerboard of 40 mm squares shown by the monitor around
  the working distance;
* writes ``repro/results/calibration_lab.json`` (or ``--out``) and prints a table.

The helpers (:func:`direct_pose`, :func:`render_view_stack`, :class:`LabTruth` ...) are also used by
tests/calibration/test_calibration_lab.py at reduced resolution.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time

import numpy as np

from calibration.camera import Camera, rotation_angle_deg
from calibration.targets import CheckerboardTarget, PhaseTarget
from dic.lab.paper import GRID_SPACING_MM, MONITOR_PITCH_MM, WORKING_DISTANCE_MM
from dic.lab.session import (  # noqa: F401
    DENSE_DIRECT_POSES,
    DIRECT_POSES,
    EXTRA_DIRECT_POSES,
    MIRROR_TILTS,
    Cache,
    LabSession,
    common_pose,
    dense_target,
    direct_pose,
    export_session,
    paper_target,
    render_view_stack,
    rot_xy,
    target_pose,
    true_rig,
)


def intrinsic_errors(calib, truth: Camera) -> dict:
    """Errors of an IntrinsicsResult against the true camera: per parameter value, error, σ, error/σ."""
    cam = calib.camera
    est = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}
    tru = {"fx": truth.fx, "fy": truth.fy, "cx": truth.cx, "cy": truth.cy}
    for i, nm in enumerate(("k1", "k2", "p1", "p2", "k3")):
        est[nm] = float(cam.dist8[i])
        tru[nm] = float(truth.dist8[i])
    out = {}
    for nm in est:
        sd = calib.std.get(nm)
        err = est[nm] - tru[nm]
        out[nm] = {"estimate": est[nm], "truth": tru[nm], "error": err, "sigma": sd,
                   "error_over_sigma": (err / sd) if sd else None}
    out["focal_error_percent"] = 100 * max(abs(cam.fx - truth.fx) / truth.fx, abs(cam.fy - truth.fy) / truth.fy)
    out["max_error_over_sigma"] = max(abs(v["error_over_sigma"]) for v in out.values()
                                      if isinstance(v, dict) and v["error_over_sigma"] is not None)
    return out


def pose_errors(R, t, R_true, t_true) -> dict:
    return {"rotation_deg": rotation_angle_deg(R, R_true), "translation_mm": float(np.linalg.norm(t - t_true))}


# -- the benchmark ----------------------------------------------------------------------------------
#: Dot detection without the detector's defocus-bias correction (pass 2): on the lab's full-resolution
#: views (blur σ 4.7-7 px) it changed the centre errors by < 0.002 px RMS and took 2.5-3x longer.
CORRECT_BLUR = False


def _summary_intrinsics(ic, truth):
    e = intrinsic_errors(ic.result, truth)
    return {"views": len(ic.result.view_indices), "points": int(sum(len(ic.image_points[i]) for i in ic.result.view_indices)),
            "rms_px": ic.result.rms, "focal_error_percent": e["focal_error_percent"],
            "max_error_over_sigma": e["max_error_over_sigma"], "parameters": {k: v for k, v in e.items() if isinstance(v, dict)},
            "dropped": [{"view": n, "reason": r} for n, r in ic.dropped], "outlier_points": len(ic.dropped_points)}


def _summary_mirror(mc, truth_pose):
    R, t = truth_pose
    r = mc.result
    return {"tilts": len(mc.names), "points": int(len(mc.point_ids)), "rms_px": r.rms,
            "closed_form": pose_errors(r.closed_form.R_cam_target, r.closed_form.t_cam_target, R, t),
            "adjusted": pose_errors(r.R_cam_target, r.t_cam_target, R, t),
            "reported_sigma_rotation_deg": r.std_rotation_deg.tolist(),
            "reported_sigma_translation_mm": r.std_translation_mm.tolist()}


def _summary_rig(rig, truth, checks=(), calibration=None):
    from calibration.camera import vector_from_rotation

    e = rig.errors_to(truth)
    out = {"rotation_error_deg": e["rotation_deg"], "translation_error_mm": e["translation_mm"],
           "baseline_error_mm": e["baseline_mm"], "baseline_error_percent": e["baseline_percent"],
           "baseline_mm": rig.baseline,
           "rotation_error_vector_deg": np.degrees(vector_from_rotation(rig.R_right_left @ truth.R_right_left.T)).tolist()}
    if rig.covariance is not None:
        out["reported_sigma_baseline_percent"] = 100 * rig.std_baseline_mm / rig.baseline
        out["reported_sigma_rotation_deg"] = rig.std_rotation_deg.tolist()
        out["rotation_error_over_sigma"] = (np.array(out["rotation_error_vector_deg"]) / rig.std_rotation_deg).tolist()
    if calibration is not None and calibration.covariance_intrinsic is not None:
        # the rig's σ above includes both cameras' intrinsic covariances; these are its two parts
        out["reported_sigma_rotation_views_only_deg"] = np.degrees(np.sqrt(np.diag(calibration.covariance_extrinsic)[:3])).tolist()
        out["reported_sigma_rotation_intrinsics_deg"] = np.degrees(np.sqrt(np.diag(calibration.covariance_intrinsic)[:3])).tolist()
    if checks:
        ne = np.concatenate([c.neighbour_errors for c in checks])
        ae = np.concatenate([c.distance_errors for c in checks])
        rel = np.concatenate([c.distance_errors / c.true_distances for c in checks])
        out["check"] = {"views": len(checks), "neighbour_error_mean_mm": float(np.mean(ne)),
                        "neighbour_error_rms_mm": float(np.sqrt(np.mean(ne ** 2))),
                        "all_pairs_rms_mm": float(np.sqrt(np.mean(ae ** 2))),
                        "scale_error_percent": float(100 * np.mean(rel)),
                        "relative_error_rms_percent": float(100 * np.sqrt(np.mean(rel ** 2))),
                        "neighbour_distance_mm": float(np.mean(np.concatenate([c.neighbour_true for c in checks])))}
    return out


def centre_errors(scene, camera: str, target: PhaseTarget, det, mirror_index=None) -> np.ndarray:
    """Detected minus exact image positions (N, 2) px of the dots of one detection."""
    from dic.lab import project

    truth = project(scene, camera, scene.monitor.to_world(target.dot_centres_px[det.ids]), mirror=mirror_index)
    return det.image_points - truth


def run(scale: float, samples: int, cache: str | None, out_path: str, n_direct: int | None = None,
        checks=None, boards: int = 15, dense_poses=None, extra_views: int | None = None) -> dict:
    from calibration import pipeline as pl
    from calibration.stereo import reconstruct_target, rig_from_mirror

    t_start = time.time()
    log = lambda s: print(s, flush=True)  # noqa: E731
    S = LabSession(scale=scale, samples=samples, cache=cache, log=log)
    rig_truth = true_rig(S.rig)
    targets = {"paper": paper_target(), "dense": dense_target()}
    poses = DIRECT_POSES if n_direct is None else DIRECT_POSES[:n_direct]
    # the "more views" setup: the same session plus EXTRA_DIRECT_POSES (indices len(poses)...; 0 = leave it out)
    extra = EXTRA_DIRECT_POSES if extra_views is None else EXTRA_DIRECT_POSES[:extra_views]
    all_poses = tuple(poses) + tuple(extra)
    result = {"conditions": {
        "scale": scale, "image_size": list(S.rig.camera("left").size), "samples_per_pixel": samples,
        "camera_noise": "8-bit, read noise 1 DN, shot noise 80 e-/DN", "phase_steps": 4,
        "direct_poses": [list(p) for p in poses], "extra_direct_poses": [list(p) for p in extra],
        "mirror_tilts_deg": [list(t) for t in S.tilts],
        "targets": {k: {"grid": list(t.grid), "pitch_px": t.pitch, "pitch_mm": t.spacing_mm} for k, t in targets.items()},
        "detector": f"calibration.detect.detect_dots(correct_blur={CORRECT_BLUR}), then "
                    "calibration.pipeline.filter_detection (vignetted dots: modulation slope > max(0.015, 3 x the view's "
                    "median); poor phase fit: misfit > 1.5 x median)",
        "dense_direct_poses": [i for i in DENSE_DIRECT_POSES if i < len(poses)] if dense_poses is None else list(dense_poses),
        "outlier_points": "removed above 4 x robust RMS (calibration.pipeline, reject_points=4)",
    }}

    # -- 0. render and detect every view once; dot-centre errors against the lab's exact projection
    det = {}
    centre_stats = {}

    def detect(cam, tname, kind, j):
        key = (cam, tname, kind, j)
        if key not in det:
            tgt = targets[tname]
            scene, stack = S.direct_view(cam, tgt, j, all_poses) if kind == "direct" else S.mirror_view(cam, tgt, j)
            t0 = time.time()
            # detect with the dot filters off, measure every dot, then filter (as detect_view does)
            r = pl.detect_view(stack, tgt, name=f"{tname}:{kind}{j}", correct_blur=CORRECT_BLUR, max_misfit=None,
                               max_slope=None)
            dt = time.time() - t0
            if r.ok:
                mirror = (0 if cam == "left" else 1) if kind == "mirror" else None
                n_all = np.linalg.norm(centre_errors(scene, cam, tgt, r.detection, mirror), axis=1)
                kept, removed, vignetted = pl.filter_detection(r.detection)
                r = dataclasses.replace(r, detection=kept, removed=removed, vignetted=vignetted)
                n = np.linalg.norm(centre_errors(scene, cam, tgt, kept, mirror), axis=1)
                centre_stats[f"{cam} {tname}:{kind}{j}"] = {
                    "dots": len(n), "rms_px": float(np.sqrt(np.mean(n ** 2))), "median_px": float(np.median(n)),
                    "max_px": float(n.max()), "blur_sigma_px": float(r.detection.blur_sigma), "detect_s": dt,
                    "vignetted_removed": len(vignetted), "misfit_removed": len(removed),
                    "unfiltered": {"dots": len(n_all), "rms_px": float(np.sqrt(np.mean(n_all ** 2))),
                                   "median_px": float(np.median(n_all)), "max_px": float(n_all.max())}}
                log(f"    {cam} {tname}:{kind}{j}: {len(n)} dots, centre error RMS {np.sqrt(np.mean(n ** 2)):.4f} px "
                    f"(median {np.median(n):.4f}, max {n.max():.3f}), blur σ {r.detection.blur_sigma:.1f} px, {dt:.0f} s; "
                    f"removed {len(vignetted)} vignetted + {len(removed)} misfit (unfiltered RMS "
                    f"{np.sqrt(np.mean(n_all ** 2)):.4f}, max {n_all.max():.3f})")
            det[key] = r
            if not r.ok:
                log(f"    {cam} {tname}:{kind}{j}: dropped — {r.error}")
        return det[key]

    # -- 1. intrinsics per camera: "paper" = the paper target at the direct poses + its 3 mirror tilts (paper
    #       Step 4); "improved" = the same direct views + the paper target at 5 tilts + the 24x12 target at 5 tilts
    #       and directly at DENSE_DIRECT_POSES; "improved, no dense direct" leaves the latter out (for comparison)
    intr = {}
    dense_direct = [i for i in DENSE_DIRECT_POSES if i < len(poses)] if dense_poses is None else list(dense_poses)
    base = [("paper", "direct", i) for i in range(len(poses))] + [("paper", "mirror", k) for k in range(5)]
    cfg_intr = {
        "paper": [("paper", "direct", i) for i in range(len(poses))] + [("paper", "mirror", k) for k in range(3)],
        "improved": base + [("dense", "mirror", k) for k in range(5)] + [("dense", "direct", i) for i in dense_direct],
        "improved, no dense direct": base + [("dense", "mirror", k) for k in range(5)],
        # the same views as "improved", each weighted by its estimated noise (calibrate_intrinsics(weighting=
        # "per_view")): the 24x12 views count for what they are worth instead of being dropped or swamping the bundle
        "improved, weighted": base + [("dense", "mirror", k) for k in range(5)] + [("dense", "direct", i) for i in dense_direct],
    }
    if extra:
        # "more views": 4x the direct views (both targets at every pose), the lever repro/intrinsics_design.py
        # found for the principal point; equal and per-view weights
        more = (base + [("paper", "direct", i) for i in range(len(poses), len(all_poses))]
                + [("dense", "mirror", k) for k in range(5)]
                + [("dense", "direct", i) for i in dense_direct + list(range(len(poses), len(all_poses)))])
        cfg_intr["more views"] = more
        cfg_intr["more views, weighted"] = more

    for iname, items in cfg_intr.items():
        for cam in ("left", "right"):
            log(f"[intrinsics] {cam}, {iname}: {len(items)} views")
            views = [detect(cam, *it) for it in items]
            t0 = time.time()
            ic = pl.calibrate_intrinsics_from_detections(views, name=cam,
                                                         weighting="per_view" if "weighted" in iname else "equal")
            intr[(iname, cam)] = ic
            s = _summary_intrinsics(ic, S.rig.camera(cam).camera)
            s["time_s"] = time.time() - t0
            result.setdefault("intrinsics", {}).setdefault(iname, {})[cam] = s
            log(f"    RMS {s['rms_px']:.4f} px, focal error {s['focal_error_percent']:.4f} %, "
                f"max |error|/σ {s['max_error_over_sigma']:.2f}, dropped views {len(s['dropped'])}, "
                f"outlier points {s['outlier_points']}")
    result["dot_centres"] = centre_stats

    # -- 2. mirror extrinsics per camera
    mirr = {}
    configs = {"6x3_3tilts": ("paper", 3, "paper"), "6x3_5tilts": ("paper", 5, "improved"),
               "24x12_3tilts": ("dense", 3, "improved"), "24x12_5tilts": ("dense", 5, "improved"),
               "6x3_5tilts_weighted": ("paper", 5, "improved, weighted"),
               "24x12_5tilts_weighted": ("dense", 5, "improved, weighted"),
               "6x3_5tilts_more_views": ("paper", 5, "more views"),
               "6x3_5tilts_more_views_weighted": ("paper", 5, "more views, weighted"),
               "24x12_5tilts_more_views_weighted": ("dense", 5, "more views, weighted"),
               "6x3_5tilts_exact_intrinsics": ("paper", 5, None)}
    for cname, (tname, k, iname) in configs.items():
        if iname is not None and (iname, "left") not in intr:
            continue
        for cam in ("left", "right"):
            views = [detect(cam, tname, "mirror", j) for j in range(k)]
            camera = intr[(iname, cam)].camera if iname else S.rig.camera(cam).camera
            try:
                mc = pl.calibrate_mirror_from_detections(camera, views, targets[tname])
            except ValueError as exc:
                log(f"[mirror] {cname} {cam}: failed: {exc}")
                continue
            mirr[(cname, cam)] = mc
            s = _summary_mirror(mc, S.mirror_truth(cam))
            s["intrinsics"] = iname or "exact"
            s["outlier_points"] = len(mc.dropped_points)
            result.setdefault("mirror", {}).setdefault(cname, {})[cam] = s
            log(f"[mirror] {cname} {cam}: RMS {s['rms_px']:.4f} px, pose error {s['adjusted']['rotation_deg']:.4f} deg / "
                f"{s['adjusted']['translation_mm']:.2f} mm (closed form {s['closed_form']['rotation_deg']:.4f} deg / "
                f"{s['closed_form']['translation_mm']:.2f} mm), outlier points {len(mc.dropped_points)}")

    # -- 3. views both cameras see (the paper target: 18 dots of 93.3 mm pitch, ~66 px apart at 5.4 m):
    #       the far view at the axes' crossing (used by the joint adjustment) and independent check views
    tgt = targets["paper"]
    _, (sl, sr) = S.common_view(tgt, S.rig.crossing_point, tag="far")
    far = pl.detect_stereo_view(sl, sr, tgt, name="far (crossing point)", correct_blur=CORRECT_BLUR)
    # corners of the paper's test volume (its front and rear planes) and the crossing point
    wd, (dx, dy, dz) = WORKING_DISTANCE_MM, GRID_SPACING_MM
    check_places = checks if checks is not None else [
        ((-dx, -dy, wd - dz), 0, 0), ((dx, dy, wd - dz), 0, 0), ((0.0, 0.0, wd), 10, -20),
        ((-dx, dy, wd + dz), 0, 0), ((dx, -dy, wd + dz), 0, 0), ((0.0, 0.0, wd + dz), -15, 15)]
    chk = []
    for j, (c, ax, ay) in enumerate(check_places):
        _, (cl, cr) = S.common_view(tgt, c, ax, ay, tag=f"check{j}")
        try:
            chk.append(pl.detect_stereo_view(cl, cr, tgt, name=f"check{j} at {c}", correct_blur=CORRECT_BLUR))
        except ValueError as exc:
            log(f"    check view {j} skipped: {exc}")
    result["conditions"]["far_view"] = f"paper target at the axes' crossing point (0, 0, {WORKING_DISTANCE_MM:g}), facing the cameras"
    result["conditions"]["check_views"] = [{"center": list(c), "tilt_deg": [ax, ay]} for c, ax, ay in check_places]

    # -- 4. rigs
    rig_configs = {
        "paper-faithful: 6x3 dots, 3 tilts, per camera": ("6x3_3tilts", False),
        "6x3 dots, 3 tilts, joint + far view": ("6x3_3tilts", True),
        "6x3 dots, 5 tilts, per camera": ("6x3_5tilts", False),
        "improved: 6x3 dots, 5 tilts, joint + far view": ("6x3_5tilts", True),
        "24x12 dots, 5 tilts, per camera": ("24x12_5tilts", False),
        "24x12 dots, 5 tilts, joint + far view": ("24x12_5tilts", True),
        "weighted intrinsics: 6x3 dots, 5 tilts, joint + far view": ("6x3_5tilts_weighted", True),
        "weighted intrinsics: 24x12 dots, 5 tilts, joint + far view": ("24x12_5tilts_weighted", True),
        f"{len(all_poses)} direct views, equal weights: 6x3 dots, 5 tilts, joint + far view": ("6x3_5tilts_more_views", True),
        f"{len(all_poses)} direct views, weighted: 6x3 dots, 5 tilts, joint + far view": ("6x3_5tilts_more_views_weighted", True),
        f"{len(all_poses)} direct views, weighted: 24x12 dots, 5 tilts, joint + far view": ("24x12_5tilts_more_views_weighted", True),
        "reference: 6x3 dots, 5 tilts, joint + far view, exact intrinsics": ("6x3_5tilts_exact_intrinsics", True),
    }
    for label, (cname, joint) in rig_configs.items():
        if (cname, "left") not in mirr or (cname, "right") not in mirr:
            continue
        rc = pl.calibrate_rig_from_mirrors(mirr[(cname, "left")], mirr[(cname, "right")],
                                           far_views=[far] if joint else [], check_views=chk, joint=joint)
        s = _summary_rig(rc.rig, rig_truth, rc.checks, calibration=rc)
        if rc.joint is not None:
            s["rms_groups_px"] = rc.joint.rms_groups
        result.setdefault("rig", {})[label] = s
        log(f"[rig] {label}: rotation {s['rotation_error_deg']:.4f} deg (error/σ per axis "
            f"{np.round(s.get('rotation_error_over_sigma', [np.nan] * 3), 2).tolist()}), baseline "
            f"{s['baseline_error_percent']:+.4f} %, check scale {s.get('check', {}).get('scale_error_percent', float('nan')):+.4f} %")
    if ("6x3_3tilts", "left") in mirr and ("6x3_3tilts", "right") in mirr:
        cf = rig_from_mirror(mirr[("6x3_3tilts", "left")].result.closed_form, mirr[("6x3_3tilts", "right")].result.closed_form,
                             left_camera=intr[("paper", "left")].camera, right_camera=intr[("paper", "right")].camera)
        cf_checks = [reconstruct_target(cf, v.left_points, v.right_points, v.object_points) for v in chk]
        result["rig"]["paper-faithful, closed form only (no bundle adjustment)"] = _summary_rig(cf, rig_truth, cf_checks)

    # -- 5. conventional: checkerboard around the working distance, cv2.stereoCalibrate
    if boards:
        result["checkerboard"] = _checkerboard(S, intr, rig_truth, chk, boards, log)
    result["conditions"]["wall_time_s"] = time.time() - t_start
    result["environment"] = {"python": platform.python_version(), "numpy": np.__version__,
                             "machine": platform.machine(), "cpu_count": os.cpu_count(),
                             "load_average": os.getloadavg() if hasattr(os, "getloadavg") else None}
    os.makedirs(os.path.dirname(out_path) or ".", exist_ok=True)
    with open(out_path, "w") as f:
        json.dump(result, f, indent=1, default=lambda o: o.tolist() if isinstance(o, np.ndarray) else float(o))
    print_table(result)
    return result


def checkerboard_poses(rig, n: int, seed: int = 7):
    """``n`` poses of a board centred near the axes' crossing (±10 % in depth, ±30° tilts, spread laterally)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        c = rig.crossing_point + np.array([rng.uniform(-400, 400), rng.uniform(-300, 300), rng.uniform(-540, 540)])
        out.append((c, rng.uniform(-30, 30), rng.uniform(-30, 30)))
    return out


def _checkerboard(S: LabSession, intr, rig_truth, checks, n: int, log):
    from calibration import pipeline as pl
    from calibration.stereo import reconstruct_target

    board = CheckerboardTarget(corners=(9, 6), square=40.0 / MONITOR_PITCH_MM)
    img = board.images()
    left, right = [], []
    for j, (c, ax, ay) in enumerate(checkerboard_poses(S.rig, n)):
        R, t = common_pose(S.rig, c, ax, ay)
        scene = S.rig.without_mirrors().with_monitor_pose(R, t)
        seed = S.seed + 70000 + 10 * j
        key = S._key("board", j)
        left.append(S.cache.get(key + "L", lambda: render_view_stack(scene, "left", img, samples=S.samples, seed=seed))[0])
        right.append(S.cache.get(key + "R", lambda: render_view_stack(scene, "right", img, samples=S.samples, seed=seed + 1))[0])
    out = {"board": "9x6 inner corners, 40 mm squares (shown on the monitor)", "views": n}
    for label, cams in (("intrinsics from the phase-target calibration (fixed)",
                         (intr[("improved", "left")].camera, intr[("improved", "right")].camera)),
                        ("intrinsics from the same board views (conventional)", (None, None))):
        try:
            cs = pl.stereo_from_checkerboards(left, right, board, left_camera=cams[0], right_camera=cams[1])
        except ValueError as exc:
            out[label] = {"failed": str(exc)}
            log(f"[checkerboard] {label}: failed: {exc}")
            continue
        cc = [reconstruct_target(cs.rig, v.left_points, v.right_points, v.object_points) for v in checks]
        s = _summary_rig(cs.rig, rig_truth, cc)
        s["pairs_used"] = len(cs.names)
        s["dropped"] = [{"view": a, "reason": b} for a, b in cs.dropped]
        s["rms_px"] = cs.result.rms
        out[label] = s
        log(f"[checkerboard] {label}: {len(cs.names)} pairs, rotation {s['rotation_error_deg']:.4f} deg, "
            f"baseline {s['baseline_error_percent']:+.4f} %")
    return out


def print_table(result: dict) -> None:
    print("\nintrinsics (RMS px / focal error % / max |error|/σ):")
    for tname, d in result.get("intrinsics", {}).items():
        for cam, s in d.items():
            print(f"  {tname:6s} {cam:5s}  {s['rms_px']:.4f}  {s['focal_error_percent']:.4f}  {s['max_error_over_sigma']:.2f}")
    print("\nmirror extrinsics (pose error rotation deg / translation mm, closed form -> adjusted):")
    for cname, d in result.get("mirror", {}).items():
        for cam, s in d.items():
            print(f"  {cname:13s} {cam:5s}  {s['closed_form']['rotation_deg']:.4f} / {s['closed_form']['translation_mm']:.2f}"
                  f"  ->  {s['adjusted']['rotation_deg']:.4f} / {s['adjusted']['translation_mm']:.2f}")
    print("\nrig (rotation error deg, baseline error %, check: neighbour error mean mm, scale error %):")
    rows = dict(result.get("rig", {}))
    for label, s in result.get("checkerboard", {}).items():
        if isinstance(s, dict) and "rotation_error_deg" in s:
            rows["cv2.stereoCalibrate, " + label] = s
    for label, s in rows.items():
        c = s.get("check", {})
        print(f"  {label:70s} {s['rotation_error_deg']:.4f}  {s['baseline_error_percent']:+.4f}  "
              f"{c.get('neighbour_error_mean_mm', float('nan')):+.4f}  {c.get('scale_error_percent', float('nan')):+.4f}")


def prerender(camera: str, *, scale: float = 1.0, samples: int = 16, cache: str, log=print) -> int:
    """Render (into ``cache``) every direct view of ``camera``, both targets, and return how many stacks.

    Warp's CPU launches use one core, so two of these (``--render-only left`` and ``--render-only right``)
    fill a 2-core machine before the main run, which then reads the stacks from the cache."""
    if not cache:
        raise ValueError("--render-only needs a --cache folder to render into")
    if camera not in ("left", "right"):
        raise ValueError(f"--render-only: camera must be 'left' or 'right', got {camera!r}")
    S = LabSession(scale=scale, samples=samples, cache=cache, log=log)
    poses = tuple(DIRECT_POSES) + tuple(EXTRA_DIRECT_POSES)
    n = 0
    for tgt in (paper_target(), dense_target()):
        for i in range(len(poses)):
            S.direct_view(camera, tgt, i, poses)
            n += 1
    return n


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scale", type=float, default=1.0, help="camera resolution factor (1: 2352x1728)")
    p.add_argument("--samples", type=int, default=16, help="render samples per pixel")
    p.add_argument("--cache", default="/tmp/specula_calibration_lab_cache", help="folder for rendered stacks ('' = none)")
    p.add_argument("--out", default=None, help="JSON output (default repro/results/calibration_lab.json at scale 1)")
    p.add_argument("--boards", type=int, default=15, help="checkerboard views for cv2.stereoCalibrate (0 = skip)")
    p.add_argument("--dense-poses", default=None, metavar="I,J,...",
                   help="indices of DIRECT_POSES at which to show the 24x12 target directly (default: DENSE_DIRECT_POSES)")
    p.add_argument("--extra-views", type=int, default=None, metavar="N",
                   help=f"how many of the {len(EXTRA_DIRECT_POSES)} EXTRA_DIRECT_POSES the 'more views' setup adds "
                        "(default all; 0 = leave that setup out)")
    p.add_argument("--render-only", default=None, choices=("left", "right"),
                   help="only render (into --cache) every direct view of this camera, then stop")
    p.add_argument("--export", default=None, metavar="DIR",
                   help="only write the session's image folders into DIR (see export_session) and stop")
    a = p.parse_args(argv)
    if a.render_only:
        prerender(a.render_only, scale=a.scale, samples=a.samples, cache=a.cache)
        return
    if a.export:
        export_session(a.export, scale=a.scale, samples=a.samples, cache=a.cache or None)
        return
    out = a.out or ("repro/results/calibration_lab.json" if a.scale == 1.0 else f"repro/results/calibration_lab_scale{a.scale:g}.json")
    dense = None if a.dense_poses is None else [int(x) for x in a.dense_poses.split(",") if x.strip()]
    run(a.scale, a.samples, a.cache or None, out, boards=a.boards, dense_poses=dense, extra_views=a.extra_views)


if __name__ == "__main__":
    sys.exit(main())
