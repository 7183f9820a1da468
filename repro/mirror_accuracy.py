"""Monte Carlo accuracy of mirror vs checkerboard rig calibration on the exact paper geometry.

    OPENBLAS_NUM_THREADS=1 python -m repro.mirror_accuracy [--draws 50] [--noise 0.03] [--json FILE]

Prints the table of docs/calibration.md ("Accuracy on the exact paper geometry"). The geometry is
:func:`repro.mirror_setup.paper_mirror_setup`. Moved here from ``calibration/uncertainty.py``
(formerly ``python -m repro.mirror_accuracy``).
"""
from __future__ import annotations

import numpy as np

from calibration.camera import rotation_angle_deg, rotation_from_vector
from repro.mirror_setup import (
    PAPER_DOT_PITCH_MM,
    checkerboard_far_views,
    paper_mirror_setup,
    simulate_mirror_observations,
)

__all__ = ["accuracy_study", "main"]


def accuracy_study(draws: int = 30, noise_px: float = 0.03, seed: int = 2019, configs=None) -> list[dict]:
    """Monte Carlo comparison of rig calibrations on the exact paper geometry (docs/calibration.md).

    For each configuration and noise draw: calibrate, compare with the true rig (rotation error,
    baseline error, translation error) and reconstruct an independent far view of the 6×3-dot
    target (neighbour-distance error). Intrinsics are exact in every configuration, so the figures
    isolate the extrinsic calibration. Returns one dict of RMS figures per configuration.
    """
    from calibration.mirror import joint_mirror_stereo, mirror_closed_form, mirror_extrinsics
    from calibration.stereo import StereoRig, reconstruct_target, rig_from_mirror, stereo_calibrate

    if configs is None:
        configs = [
            ("paper: 6x3 dots, 3 tilts of 3 deg, closed form", dict(), "closed"),
            ("paper: 6x3 dots, 3 tilts of 3 deg, closed form + BA per camera", dict(), "mirror"),
            ("paper + joint BA with the far view", dict(), "joint"),
            ("24x12 dots, 5 tilts of 3 deg, BA per camera", dict(grid=(24, 12), pitch=PAPER_DOT_PITCH_MM / 4, n_tilts=5), "mirror"),
            ("24x12 dots, 5 tilts of 3 deg, joint BA + far view",
             dict(grid=(24, 12), pitch=PAPER_DOT_PITCH_MM / 4, n_tilts=5), "joint"),
            ("48x24 dots, 5 tilts of 4 deg, joint BA + far view",
             dict(grid=(48, 24), pitch=PAPER_DOT_PITCH_MM / 8, n_tilts=5, tilt_deg=4.0), "joint"),
            ("cv2.stereoCalibrate, 15 views of a 9x6 checkerboard (40 mm) at 5.4 m", dict(), "checkerboard"),
            ("same, intrinsics refined from the same 15 views (started at the truth)", dict(), "checkerboard_free"),
        ]
    rng = np.random.default_rng(seed)
    rows = []
    for label, kw, method in configs:
        setup = paper_mirror_setup(**kw)
        check = paper_mirror_setup()  # independent far view: 6x3 dots at 5.4 m, shifted and turned
        check.R_world_far = rotation_from_vector(np.radians([8.0, -15.0, 3.0]))
        check.t_world_far = np.array([180.0, -120.0, 5200.0])
        truth = StereoRig(setup.left, setup.right, setup.R_right_left, setup.t_right_left)
        errs = []
        for _ in range(draws):
            obs = simulate_mirror_observations(setup, noise_px, rng)
            if method.startswith("checkerboard"):
                objs, ql, qr = checkerboard_far_views(setup, noise_px=noise_px, rng=rng)
                rig = stereo_calibrate(setup.left, setup.right, objs, ql, qr,
                                       fix_intrinsics=(method == "checkerboard")).rig
                pose_err = (np.nan, np.nan)
            else:
                X = setup.object_points
                if method == "closed":
                    L = mirror_closed_form(setup.left, obs["left_mirrored"], X)
                    R = mirror_closed_form(setup.right, obs["right_mirrored"], X)
                    rig = rig_from_mirror(L, R, setup.left, setup.right)
                    est = L
                else:
                    L = mirror_extrinsics(setup.left, obs["left_mirrored"], X)
                    R = mirror_extrinsics(setup.right, obs["right_mirrored"], X)
                    est = L
                    if method == "mirror":
                        rig = rig_from_mirror(L, R)
                    else:
                        far = [(setup.far_object_points, obs["far_left"], obs["far_right"])]
                        rig = joint_mirror_stereo(setup.left, setup.right, obs["left_mirrored"], obs["right_mirrored"],
                                                  X, far_views=far, left_result=L, right_result=R).rig
                R_true, t_true = setup.pose_cam_target("left")
                pose_err = (rotation_angle_deg(est.R_cam_target, R_true), float(np.linalg.norm(est.t_cam_target - t_true)))
            e = rig.errors_to(truth)
            cobs = simulate_mirror_observations(check, noise_px, rng)
            rec = reconstruct_target(rig, cobs["far_left"], cobs["far_right"], check.far_object_points)
            sb = rig.std_baseline_mm if rig.covariance is not None else np.nan
            sr = float(np.degrees(np.sqrt(np.trace(rig.covariance[:3, :3])))) if rig.covariance is not None else np.nan
            errs.append([e["rotation_deg"], e["baseline_percent"], e["translation_mm"], *pose_err,
                         100 * sb / truth.baseline, sr, np.mean(rec.neighbour_errors), rec.mean_relative_error * 100])
        a = np.asarray(errs)
        def rms(v):
            return float(np.sqrt(np.mean(v[np.isfinite(v)] ** 2))) if np.any(np.isfinite(v)) else float("nan")

        def mean(v):
            return float(np.mean(v[np.isfinite(v)])) if np.any(np.isfinite(v)) else float("nan")

        rows.append({"config": label, "draws": draws, "rig_rotation_deg": rms(a[:, 0]), "baseline_percent": rms(a[:, 1]),
                     "rig_translation_mm": rms(a[:, 2]), "left_pose_rotation_deg": rms(a[:, 3]),
                     "left_pose_translation_mm": rms(a[:, 4]), "reported_sigma_baseline_percent": mean(a[:, 5]),
                     "reported_sigma_rotation_deg": mean(a[:, 6]),
                     "check_neighbour_error_mm": rms(a[:, 7]), "check_scale_error_percent": rms(a[:, 8]),
                     "max_rig_rotation_deg": float(np.max(a[:, 0])), "max_baseline_percent": float(np.max(np.abs(a[:, 1])))})
    return rows


def main(argv=None):  # pragma: no cover - documentation tool
    import argparse
    import json
    import time

    ap = argparse.ArgumentParser(description="Monte Carlo accuracy of mirror vs checkerboard rig calibration")
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--noise", type=float, default=0.03)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    t0 = time.time()
    rows = accuracy_study(args.draws, args.noise)
    print("| configuration | rig rotation error (deg, RMS) | baseline error (%, RMS) | rig translation error (mm, RMS) "
          "| left pose rot. (deg) / transl. (mm) | reported σ baseline (%) | check: neighbour error (mm, RMS) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['config']} | {r['rig_rotation_deg']:.4f} | {r['baseline_percent']:.4f} | {r['rig_translation_mm']:.3f} "
              f"| {r['left_pose_rotation_deg']:.4f} / {r['left_pose_translation_mm']:.2f} "
              f"| {r['reported_sigma_baseline_percent']:.4f} | {r['check_neighbour_error_mm']:.4f} |")
    print(f"({args.draws} draws per configuration, noise {args.noise} px, {time.time() - t0:.0f} s)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"noise_px": args.noise, "rows": rows}, f, indent=2)


if __name__ == "__main__":  # pragma: no cover
    main()
