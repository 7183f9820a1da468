"""How many direct views, and how tilted, does a mirror-calibrated rig need for 0.01° of rig rotation?

Monte Carlo on the exact paper geometry (``repro.mirror_setup.paper_mirror_setup``), with the
**intrinsics calibrated** from simulated views rather than exact (``repro.mirror_accuracy.accuracy_study``
holds them exact): for each camera, direct views of the paper's 6 × 3 target (93.3 mm pitch) and/or
of a 24 × 12 grid on the same area at depths 1.15–3.4 m, tilted up to ``tilt`` degrees, plus the
camera's mirrored views, go into one Zhang bundle (``calibration.calibrate_intrinsics``, OpenCV
5-term model, equal or per-view weights; :data:`DESIGNS`); then each camera's mirror
extrinsics and the joint adjustment with the far view (``calibration.mirror.joint_mirror_stereo``) give
the rig, compared with the truth. Every image point carries Gaussian noise of ``--noise`` px (default
0.014 px per coordinate: the dot-centre RMS of 6 × 3 views measured in the rendered lab,
docs/calibration.md).

Why: in the rendered lab the joint rig's rotation error (0.014°) came almost entirely from the
principal points (with exact intrinsics the same images give 0.001°): a principal-point error δ acts
as a camera rotation of δ / f, which no extrinsic view can detect. This study says how much
intrinsic data removes it.

Run: ``OPENBLAS_NUM_THREADS=1 python -m repro.intrinsics_design [--draws 40]``; writes
``repro/results/intrinsics_design.json`` and prints a table (docs/calibration.md).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from dic.lab.paper import BASELINE_MM, IMAGE_SIZE_PX, MIRROR_DISTANCE_MM, MONITOR_BEHIND_MM, WORKING_DISTANCE_MM

ROOT = Path(__file__).resolve().parents[1]

#: One design per row: label, direct views per camera of the 6 x 3 target (93.3 mm pitch), largest tilt
#: (deg), mirror tilts, direct views of the 24 x 12 target (23.3 mm pitch, same area) and their noise
#: relative to --noise, and the bundle's weighting. The 24 x 12 dots measured 0.026 px in focus and
#: 0.05-0.10 px blurred in the rendered lab (the 6 x 3 dots 0.012-0.014 px): 2x and 4x.
DESIGNS = (
    dict(label="lab bench today: 12 views to 30°, 3 mirror tilts", views=12, tilt=30.0, mirror=3),
    dict(label="12 views to 30°, 5 mirror tilts", views=12, tilt=30.0, mirror=5),
    dict(label="24 views to 30°, 5 mirror tilts", views=24, tilt=30.0, mirror=5),
    dict(label="48 views to 30°, 5 mirror tilts", views=48, tilt=30.0, mirror=5),
    dict(label="96 views to 30°, 5 mirror tilts", views=96, tilt=30.0, mirror=5),
    dict(label="12 views to 45°, 5 mirror tilts", views=12, tilt=45.0, mirror=5),
    dict(label="48 views to 45°, 5 mirror tilts", views=48, tilt=45.0, mirror=5),
    dict(label="12 views of 24 x 12 dots (2x noise) to 30°, 5 mirror tilts", views=0, dense=12, dense_noise=2.0,
         tilt=30.0, mirror=5),
    dict(label="24 views of 24 x 12 dots (2x noise) to 30°, 5 mirror tilts", views=0, dense=24, dense_noise=2.0,
         tilt=30.0, mirror=5),
    dict(label="12 views of 24 x 12 dots (4x noise) to 30°, 5 mirror tilts", views=0, dense=12, dense_noise=4.0,
         tilt=30.0, mirror=5),
    dict(label="24 views of 24 x 12 dots (4x noise) to 30°, 5 mirror tilts", views=0, dense=24, dense_noise=4.0,
         tilt=30.0, mirror=5),
    dict(label="12 views of 6 x 3 + 12 of 24 x 12 (4x noise), equal weights", views=12, dense=12, dense_noise=4.0,
         tilt=30.0, mirror=5),
    dict(label="12 views of 6 x 3 + 12 of 24 x 12 (4x noise), per-view weights", views=12, dense=12, dense_noise=4.0,
         tilt=30.0, mirror=5, weighting="per_view"),
    dict(label="24 views of 6 x 3 + 24 of 24 x 12 (4x noise), per-view weights", views=24, dense=24, dense_noise=4.0,
         tilt=30.0, mirror=5, weighting="per_view"),
)


def _rotation(ax_deg: float, ay_deg: float) -> np.ndarray:
    from calibration.camera import rotation_from_vector

    return rotation_from_vector([np.radians(ax_deg), 0, 0]) @ rotation_from_vector([0, np.radians(ay_deg), 0])


def direct_views(camera, object_points, n_views: int, max_tilt_deg: float, noise_px: float, rng):
    """``n_views`` noisy direct views (object points, image points) of a planar target, in the camera frame.

    Depths spread evenly over 1.15–3.4 m, tilt directions evenly around the circle, tilt angles
    evenly between ``max_tilt / 3`` and ``max_tilt``; the target centre is placed at a random
    offset that keeps every point 3 % of the width inside the image (the offset shrinks until it fits).
    """
    W, H = camera.size
    c = object_points.mean(axis=0)
    views = []
    for i in range(n_views):
        depth = 1150.0 + (3400.0 - 1150.0) * (i + 0.5) / n_views
        tilt = max_tilt_deg * (1 / 3 + (2 / 3) * ((i * 7) % n_views) / max(1, n_views - 1))
        phi = 2 * np.pi * ((i * 0.618034) % 1.0)
        R = _rotation(tilt * np.cos(phi), tilt * np.sin(phi))
        offset = rng.uniform(-1, 1, 2)
        for s in np.linspace(1.0, 0.0, 41):
            centre = np.array([offset[0] * s * (W / 2) / camera.fx * depth, offset[1] * s * (H / 2) / camera.fy * depth,
                               depth])
            q = camera.project((object_points - c) @ R.T + centre)
            m = 0.03 * W
            if np.all((q[:, 0] > m) & (q[:, 0] < W - 1 - m) & (q[:, 1] > m) & (q[:, 1] < H - 1 - m)):
                break
        else:
            continue  # this tilt does not fit at this depth: skip the view
        views.append((object_points, q + rng.normal(0.0, noise_px, q.shape)))
    return views


def _calibrate_camera(true_cam, views, mirrored, X, weighting: str, name: str):
    """Zhang calibration (``opencv5``, no rejection) of one camera from direct ``views`` and its mirrored views."""
    from calibration.intrinsics import calibrate_intrinsics

    mirrored = list(mirrored)
    return calibrate_intrinsics([v[0] for v in views] + [X] * len(mirrored), [v[1] for v in views] + mirrored,
                                true_cam.size, mirrored=[False] * len(views) + [True] * len(mirrored), model="opencv5",
                                reject=None, weighting=weighting, name=name)


def _joint_rig(setup, obs, cams):
    """``f(left, right) -> JointMirrorResult``: the joint mirror adjustment with the far view for given cameras,
    started from the per-camera mirror solutions of ``cams`` (so that re-runs with moved intrinsics start close)."""
    from calibration.mirror import joint_mirror_stereo, mirror_extrinsics

    X = setup.object_points
    L = mirror_extrinsics(cams["left"], obs["left_mirrored"], X)
    R = mirror_extrinsics(cams["right"], obs["right_mirrored"], X)
    far = [(setup.far_object_points, obs["far_left"], obs["far_right"])]
    return lambda lc, rc: joint_mirror_stereo(lc, rc, obs["left_mirrored"], obs["right_mirrored"], X, far_views=far,
                                              left_result=L, right_result=R)


def study(draws: int, noise_px: float, seed: int, designs=DESIGNS, log=print) -> list[dict]:
    from calibration.stereo import StereoRig
    from repro.mirror_setup import PAPER_DOT_PITCH_MM, grid_points, paper_mirror_setup, simulate_mirror_observations

    rng = np.random.default_rng(seed)
    rows = []
    X_dense = grid_points(24, 12, PAPER_DOT_PITCH_MM / 4)  # the same target area as 6 x 3 at 93.3 mm, denser dots
    for d in designs:
        label, n_views, tilt, n_mirror = d["label"], d["views"], d["tilt"], d["mirror"]
        n_dense, dense_noise, weighting = d.get("dense", 0), d.get("dense_noise", 1.0), d.get("weighting", "equal")
        setup = paper_mirror_setup(n_tilts=n_mirror)
        truth = StereoRig(setup.left, setup.right, setup.R_right_left, setup.t_right_left)
        X = setup.object_points
        rec = []
        t0 = time.perf_counter()
        for _ in range(draws):
            obs = simulate_mirror_observations(setup, noise_px, rng)
            est, pp_err, pp_sigma, used = {}, [], [], []
            for name, true_cam in (("left", setup.left), ("right", setup.right)):
                views = (direct_views(true_cam, X, n_views, tilt, noise_px, rng)
                         + direct_views(true_cam, X_dense, n_dense, tilt, dense_noise * noise_px, rng))
                used.append(len(views))
                res = _calibrate_camera(true_cam, views, obs[f"{name}_mirrored"], X, weighting, name)
                est[name] = res.camera
                pp_err += [res.camera.cx - true_cam.cx, res.camera.cy - true_cam.cy]
                pp_sigma += [res.std["cx"], res.std["cy"]]
            rig = _joint_rig(setup, obs, est)(est["left"], est["right"]).rig
            e = rig.errors_to(truth)
            rec.append([e["rotation_deg"], e["baseline_percent"], *pp_err, *pp_sigma, np.mean(used)])
        a = np.asarray(rec)
        row = {"design": label, "direct_views_per_camera": n_views, "max_tilt_deg": tilt, "mirror_tilts": n_mirror,
               "dense_direct_views_per_camera": n_dense, "dense_noise_px": dense_noise * noise_px,
               "weighting": weighting,
               "direct_views_used_mean": float(np.mean(a[:, 10])),
               "draws": draws, "noise_px": noise_px,
               "rig_rotation_deg_rms": float(np.sqrt(np.mean(a[:, 0] ** 2))),
               "rig_rotation_deg_p90": float(np.percentile(a[:, 0], 90)),
               "fraction_rotation_within_0p01_deg": float(np.mean(a[:, 0] <= 0.01)),
               "baseline_percent_rms": float(np.sqrt(np.mean(a[:, 1] ** 2))),
               "principal_point_error_px_rms": float(np.sqrt(np.mean(a[:, 2:6] ** 2))),
               "principal_point_sigma_px_mean": float(np.mean(a[:, 6:10])),
               "seconds": time.perf_counter() - t0}
        rows.append(row)
        log(f"{label:66s} ({row['direct_views_used_mean']:.1f} fit) rot {row['rig_rotation_deg_rms']:.4f}° rms (p90 {row['rig_rotation_deg_p90']:.4f}°, "
            f"{100 * row['fraction_rotation_within_0p01_deg']:.0f} % ≤ 0.01°), baseline {row['baseline_percent_rms']:.4f} %, "
            f"pp err {row['principal_point_error_px_rms']:.3f} px (σ {row['principal_point_sigma_px_mean']:.3f})")
    return rows


def sigma_check(draws: int, noise_px: float, seed: int, view_counts=(12, 48), log=print) -> list[dict]:
    """Does the rig's reported rotation σ match its actual error? (``--sigma-check``)

    Per draw: calibrate both cameras (``n`` direct 6 × 3 views to 30° + 5 mirrored views), the joint
    mirror adjustment with the far view, and the rig covariance with and without both cameras'
    intrinsic covariances (:func:`calibration.uncertainty.rig_covariance_from_intrinsics`). Reports,
    per axis, the RMS of error / σ over the draws: ≈ 1 when σ is right."""
    from calibration.camera import vector_from_rotation
    from calibration.uncertainty import rig_covariance_from_intrinsics
    from repro.mirror_setup import paper_mirror_setup, simulate_mirror_observations

    rng = np.random.default_rng(seed)
    setup = paper_mirror_setup(n_tilts=5)
    X = setup.object_points
    rows = []
    for n_views in view_counts:
        err, s_views, s_total = [], [], []
        t0 = time.perf_counter()
        for _ in range(draws):
            obs = simulate_mirror_observations(setup, noise_px, rng)
            cams = {name: _calibrate_camera(true_cam, direct_views(true_cam, X, n_views, 30.0, noise_px, rng),
                                            obs[f"{name}_mirrored"], X, "equal", name).camera
                    for name, true_cam in (("left", setup.left), ("right", setup.right))}
            joint_rig = _joint_rig(setup, obs, cams)

            def solve(lc, rc):
                r = joint_rig(lc, rc).rig
                return r.R_right_left, r.t_right_left

            rig = joint_rig(cams["left"], cams["right"]).rig
            C_int = rig_covariance_from_intrinsics(solve, cams["left"], cams["right"], rig.R_right_left, rig.t_right_left)
            err.append(np.degrees(vector_from_rotation(rig.R_right_left @ setup.R_right_left.T)))
            s_views.append(np.degrees(np.sqrt(np.diag(rig.covariance)[:3])))
            s_total.append(np.degrees(np.sqrt(np.diag(rig.covariance + C_int)[:3])))
        e, sv, st = np.array(err), np.array(s_views), np.array(s_total)
        row = {"direct_views_per_camera": n_views, "draws": draws, "noise_px": noise_px,
               "rotation_error_rms_deg_per_axis": np.sqrt(np.mean(e ** 2, axis=0)).tolist(),
               "sigma_views_only_mean_deg": sv.mean(axis=0).tolist(),
               "sigma_with_intrinsics_mean_deg": st.mean(axis=0).tolist(),
               "error_over_sigma_rms_views_only": np.sqrt(np.mean((e / sv) ** 2, axis=0)).tolist(),
               "error_over_sigma_rms_with_intrinsics": np.sqrt(np.mean((e / st) ** 2, axis=0)).tolist(),
               "seconds": time.perf_counter() - t0}
        rows.append(row)
        log(f"{n_views} views: error RMS {np.round(row['rotation_error_rms_deg_per_axis'], 4)} deg; σ views only "
            f"{np.round(row['sigma_views_only_mean_deg'], 4)}, with intrinsics {np.round(row['sigma_with_intrinsics_mean_deg'], 4)}; "
            f"error/σ RMS {np.round(row['error_over_sigma_rms_views_only'], 2)} -> "
            f"{np.round(row['error_over_sigma_rms_with_intrinsics'], 2)}")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m repro.intrinsics_design", description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=40)
    ap.add_argument("--noise", type=float, default=0.014, help="image noise per coordinate (px)")
    ap.add_argument("--seed", type=int, default=2019)
    ap.add_argument("--json", default=str(ROOT / "repro/results/intrinsics_design.json"))
    ap.add_argument("--sigma-check", action="store_true",
                    help="instead: compare the rig's reported rotation σ (with / without the intrinsics) with its error "
                         "(writes repro/results/rig_sigma_check.json unless --json is given)")
    args = ap.parse_args(argv)
    if args.draws < 2 or not args.noise > 0:
        ap.error("--draws must be >= 2 and --noise > 0")
    t0 = time.perf_counter()
    if args.sigma_check:
        rows = sigma_check(args.draws, args.noise, args.seed)
        path = Path(args.json if "--json" in (argv if argv is not None else sys.argv) else
                    ROOT / "repro/results/rig_sigma_check.json")
        out = {"benchmark": "rig_sigma_check", "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
               "command": "python -m repro.intrinsics_design " + " ".join(argv if argv is not None else sys.argv[1:]),
               "machine": f"{platform.machine()} CPU, {os.cpu_count()} cores", "wall_s": time.perf_counter() - t0,
               "geometry": "repro.mirror_setup.paper_mirror_setup, 5 mirror tilts, far view at the crossing",
               "rows": rows}
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out, indent=1))
        print(f"wrote {path} ({out['wall_s']:.0f} s)")
        return 0
    rows = study(args.draws, args.noise, args.seed)
    out = {"benchmark": "intrinsics_design", "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "command": "python -m repro.intrinsics_design " + " ".join(argv if argv is not None else sys.argv[1:]),
           "machine": f"{platform.machine()} CPU, {os.cpu_count()} cores", "wall_s": time.perf_counter() - t0,
           "geometry": f"repro.mirror_setup.paper_mirror_setup (f = 4050 px, {IMAGE_SIZE_PX[0]} x {IMAGE_SIZE_PX[1]} px, "
                       f"baseline {BASELINE_MM:g} mm, axes crossing at {WORKING_DISTANCE_MM:g} mm, mirrors "
                       f"{MIRROR_DISTANCE_MM:g} mm ahead, monitor {MONITOR_BEHIND_MM:g} mm behind); far view at the crossing",
           "rows": rows}
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.json} ({out['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
