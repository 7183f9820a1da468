"""Accuracy of the calibration-target detectors on synthetic views with exact ground truth.

    .venv/bin/python -m repro.targets [--quick] [--out repro/results/targets.json] [--figures docs/img]

Camera 1024 x 768, f = 1200 px, no distortion; the paper's monitor (1920 x 1080, 0.311 mm) at
933 mm (cells of ~120 px), turned about its vertical axis by ``tilt``; rendering with
:func:`calibration.targets.render_view` (2 x 2 sub-samples per pixel, exact screen points),
Gaussian blur ``sigma``, 1 grey level of noise, 8-bit. Methods on the same pose and blur:

- phase dots, pass 1 only (radial phase model) and with pass 2 (defocus bias removed);
- OpenCV ``findChessboardCornersSB`` on a 9 x 6 checkerboard of 150 px squares;
- OpenCV ``findCirclesGrid`` on a 6 x 3 grid of 150 px circles at 300 px pitch;
- dense mode: per-pixel screen coordinates (error in screen px; 1 screen px = 0.311 mm).

Writes a JSON of every number and prints markdown tables (docs/targets.md quotes them).
"""
from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np


def _rot_y(deg):
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _pose(target, tilt, distance=933.0, mirrored=False):
    R = _rot_y(tilt)
    centre = np.array([(target.screen[0] - 1) / 2, (target.screen[1] - 1) / 2, 0.0]) * target.pixel_pitch
    t = np.array([0.0, 0.0, distance]) - R @ centre
    if mirrored:
        S = np.diag([-1.0, 1.0, 1.0])
        R, t = S @ R, S @ t
    return R, t


def _rms(d):
    return float(np.sqrt(np.mean(np.sum(np.atleast_2d(d) ** 2, axis=1))))


def main(argv=None):
    from scipy.spatial import cKDTree

    from calibration.camera import Camera
    from calibration.detect import (
        DetectionError,
        decode_dense,
        detect_checkerboard,
        detect_circle_grid,
        detect_dots_in_images,
    )
    from calibration.targets import (
        CheckerboardTarget,
        CircleGridTarget,
        PhaseTarget,
        render_view,
        screen_points_of_pixels,
    )

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer blur levels")
    ap.add_argument("--out", default="repro/results/targets.json")
    ap.add_argument("--figures", default=None, help="folder for docs figures (targets_*.png)")
    args = ap.parse_args(argv)

    cam = Camera(K=[[1200, 0, 511.5], [0, 1200, 383.5], [0, 0, 1]], size=(1024, 768))
    phase_t = PhaseTarget()
    board = CheckerboardTarget(corners=(9, 6), square=150)
    circles = CircleGridTarget(grid=(6, 3), pitch=300, diameter=150)
    blurs = [0.0, 5.0, 10.0] if args.quick else [0.0, 2.0, 5.0, 10.0, 15.0]
    rows = []
    for tilt in (0.0, 50.0):
        R, t = _pose(phase_t, tilt)
        for blur in blurs:
            row = {"tilt_deg": tilt, "blur_px": blur}
            imgs = render_view(phase_t, cam, R, t, blur_sigma=blur, noise_sigma=1.0, seed=11, supersample=2)
            truth = cam.project((R @ phase_t.object_points.T).T + t)
            for key, corr in (("phase_pass1", False), ("phase", True)):
                t0 = time.perf_counter()
                try:
                    det = detect_dots_in_images(imgs, phase_t, device="cpu", correct_blur=corr)
                    e = det.image_points - truth[det.ids]
                    row[key] = {"n": len(det), "rms": _rms(e), "max": float(np.abs(e).max()),
                                "blur_est": det.blur_sigma, "seconds": time.perf_counter() - t0}
                except DetectionError as exc:
                    row[key] = {"n": 0, "error": str(exc)}
            for key, tgt, fn in (("checkerboard_sb", board, detect_checkerboard), ("circle_grid", circles, detect_circle_grid)):
                img = render_view(tgt, cam, R, t, blur_sigma=blur, noise_sigma=1.0, seed=12, supersample=2)[0]
                tr = cam.project((R @ tgt.object_points.T).T + t)
                found = fn(img, tgt)
                if found is None:
                    row[key] = {"n": 0, "error": "not found"}
                else:
                    d, _ = cKDTree(tr).query(found[0])
                    row[key] = {"n": len(d), "rms": float(np.sqrt(np.mean(d ** 2))), "max": float(d.max())}
            rows.append(row)
            print(json.dumps(row), flush=True)

    # mirrored view
    R, t = _pose(phase_t, 40.0, mirrored=True)
    imgs = render_view(phase_t, cam, R, t, blur_sigma=10.0, noise_sigma=1.0, seed=13, supersample=2)
    det = detect_dots_in_images(imgs, phase_t, device="cpu")
    truth = cam.project((R @ phase_t.object_points.T).T + t)
    mirror_row = {"tilt_deg": 40.0, "blur_px": 10.0, "mirrored_detected": det.mirrored, "n": len(det),
                  "rms": _rms(det.image_points - truth[det.ids])}
    print(json.dumps(mirror_row), flush=True)

    # dense mode
    dense_rows = []
    for tilt, blur in ((0.0, 0.0), (50.0, 0.0), (0.0, 5.0), (50.0, 5.0), (50.0, 10.0)):
        R, t = _pose(phase_t, tilt)
        imgs = render_view(phase_t.dense_view(), cam, R, t, blur_sigma=blur, noise_sigma=1.0, seed=14, supersample=1)
        t0 = time.perf_counter()
        dec = decode_dense(imgs, phase_t, device="cpu")
        sec = time.perf_counter() - t0
        h, w = dec.mask.shape
        y, x = np.mgrid[0:h, 0:w]
        tr = screen_points_of_pixels(cam, R, t, phase_t.pixel_pitch, np.c_[x.ravel(), y.ravel()].astype(float))
        err = (dec.screen_xy - tr.reshape(h, w, 2))[dec.mask]
        per = dec.period[dec.mask]
        dense_rows.append({"tilt_deg": tilt, "blur_px": blur, "valid_px": int(dec.mask.sum()),
                           "median_err": np.median(err, axis=0).tolist(), "rms_err": _rms(err),
                           "p99_abs_err": float(np.percentile(np.abs(err).max(axis=1), 99)),
                           "finest_period_median": np.median(per, axis=0).tolist(), "seconds": sec})
        print(json.dumps(dense_rows[-1]), flush=True)

    result = {"device": platform.processor() or platform.machine(), "python": platform.python_version(),
              "camera": {"K": cam.K.tolist(), "size": cam.size}, "distance_mm": 933.0, "noise_grey": 1.0, "bits": 8,
              "dots": rows, "mirrored": mirror_row, "dense": dense_rows}
    import os

    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(result, fh, indent=1)

    def cell(r):
        return "fails" if r.get("n", 0) == 0 else f"{r['rms']:.3f} ({r['max']:.3f})"

    print("\n| tilt | blur σ (px) | phase dots | phase, pass 1 only | checkerboard SB | circle grid |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['tilt_deg']:.0f}° | {r['blur_px']:.0f} | {cell(r['phase'])} | {cell(r['phase_pass1'])} | "
              f"{cell(r['checkerboard_sb'])} | {cell(r['circle_grid'])} |")
    print("\n| tilt | blur σ (px) | valid px | median error (screen px) | RMS per pixel | 99 % | finest period |")
    print("|---|---|---|---|---|---|---|")
    for r in dense_rows:
        m = r["median_err"]
        print(f"| {r['tilt_deg']:.0f}° | {r['blur_px']:.0f} | {r['valid_px']} | {m[0]:+.3f}, {m[1]:+.3f} | "
              f"{r['rms_err']:.3f} | {r['p99_abs_err']:.2f} | {r['finest_period_median'][0]:.0f}, "
              f"{r['finest_period_median'][1]:.0f} |")

    if args.figures:
        _figures(args.figures, rows, phase_t, cam)


def _figures(folder, rows, phase_t, cam):
    import os

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from calibration.detect import demodulate_images, detect_dots
    from calibration.targets import render_view

    os.makedirs(folder, exist_ok=True)
    R, t = _pose(phase_t, 50.0)
    imgs = render_view(phase_t, cam, R, t, blur_sigma=10.0, noise_sigma=1.0, seed=11, supersample=2)
    ph, mod, _, valid = demodulate_images(imgs, device="cpu")
    det = detect_dots(ph, mod, phase_t, mask=valid)
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.4))
    ax[0].imshow(phase_t.images()[0], cmap="gray")
    ax[0].set_title("displayed image k = 0 (coded 6x3)")
    ax[1].imshow(imgs[0], cmap="gray", vmin=0, vmax=255)
    ax[1].set_title("camera: 50° tilt, blur σ = 10 px")
    ax[2].imshow(np.where(valid, ph, np.nan), cmap="twilight")
    ax[2].plot(det.image_points[:, 0], det.image_points[:, 1], "k+", ms=8)
    for p, i in zip(det.image_points, det.ids):
        ax[2].text(p[0] + 6, p[1] - 6, str(i), fontsize=7)
    ax[2].set_title("wrapped phase, centres and ids")
    for a in ax:
        a.set_xticks([])
        a.set_yticks([])
    fig.tight_layout()
    fig.savefig(os.path.join(folder, "targets_view.png"), dpi=60)
    plt.close(fig)

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.4), sharey=True)
    for a, tilt in zip(ax, (0.0, 50.0)):
        sub = [r for r in rows if r["tilt_deg"] == tilt]
        b = [r["blur_px"] for r in sub]
        for key, label in (("phase", "phase dots"), ("phase_pass1", "phase, pass 1"),
                           ("checkerboard_sb", "checkerboard SB"), ("circle_grid", "circle grid")):
            y = [r[key]["rms"] if r[key].get("n", 0) else np.nan for r in sub]
            a.semilogy(b, y, "o-", label=label)
        a.axhline(0.05, color="k", ls=":", lw=0.8)
        a.set_title(f"monitor tilt {tilt:.0f}°")
        a.set_xlabel("Gaussian blur σ (px)")
        a.grid(alpha=0.3)
    ax[0].set_ylabel("RMS centre error (px)")
    ax[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(folder, "targets_accuracy.png"), dpi=60)
    plt.close(fig)


if __name__ == "__main__":
    main()
