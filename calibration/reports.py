"""Text reports of the calibration stages (:mod:`calibration.stages`): what ``specula calibrate``
prints and writes next to the camera, pose and rig files.

Each ``*_report`` function takes a stage's result and returns the report as one string (lines
joined by newlines); the results' ``report()`` methods call them. Lengths in mm, angles in deg,
image residuals in px. Frames and units: docs/conventions.md (mm, px, camera frame x right / y
down / z forward, pixel (0, 0) the centre of the top-left pixel); target frame: :mod:`calibration.targets`.
"""
from __future__ import annotations

import numpy as np

from .camera import vector_from_rotation
from .stereo import StereoRig

__all__ = ["intrinsics_report", "mirror_report", "rig_report", "checkerboard_stereo_report"]


def _require(calibration, kind: str, attributes: tuple) -> None:
    """Reject what is not a ``kind`` result (checked by its attributes: the result classes live above this module)."""
    missing = [a for a in attributes if not hasattr(calibration, a)]
    if missing:
        raise ValueError(f"expected a calibration.stages {kind}, got {type(calibration).__name__} "
                         f"(no {', '.join(missing)})")


def intrinsics_report(calibration) -> str:
    """Text report of an :class:`~calibration.stages.intrinsics.IntrinsicsCalibration`: parameters with σ,
    one line per view (points, direct / mirrored, RMS px), dropped views, removed dots and points."""
    _require(calibration, "IntrinsicsCalibration", ("result", "views", "used", "image_points", "dropped_points"))
    res = calibration.result
    cam = res.camera
    lines = [f"intrinsic calibration of {cam.name or 'camera'} ({calibration.mode} mode, model {res.model}): "
             f"{len(res.view_indices)} of {len(calibration.views)} views, "
             f"{sum(len(calibration.image_points[i]) for i in res.view_indices)} points, RMS {res.rms:.4f} px"
             + (", views weighted by their noise" if res.weighting == "per_view" else "")]
    values = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}
    for i, nm in enumerate(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")):
        if i < cam.dist.size:
            values[nm] = float(cam.dist[i])
    lines.append("  parameter        value            σ")
    for nm, val in values.items():
        if nm in res.std:
            unit = " px" if nm in ("fx", "fy", "cx", "cy") else ""
            lines.append(f"  {nm:>4} = {val: 16.8g} ± {res.std[nm]:.3g}{unit}")
        else:
            lines.append(f"  {nm:>4} = {val: 16.8g}   (fixed)")
    weighted = res.view_sigma is not None
    lines.append("  view                                   points  kind      RMS (px)" + ("  noise σ (px)" if weighted else ""))
    rms_of = {int(i): float(r) for i, r in zip(res.view_indices, res.per_view_rms)}
    sigma_of = {int(i): float(sv) for i, sv in zip(res.view_indices, res.view_sigma)} if weighted else {}
    for u, vi in enumerate(calibration.used):
        v = calibration.views[vi]
        kind = "mirrored" if v.mirrored else "direct"
        r = rms_of.get(u)
        lines.append(f"  {_short(v.name, 38):38s} {len(calibration.image_points[u]):6d}  {kind:8s}  "
                     + (f"{r:.4f}" if r is not None else "dropped")
                     + (f"    {sigma_of[u]:.4f}" if u in sigma_of else ""))
    for v in calibration.views:
        if not v.ok:
            lines.append(f"  dropped {v.name}: {v.error}")
    for d in res.dropped:  # views rejected by their RMS, then the bundle re-solved without them
        lines.append(f"  dropped {calibration.views[calibration.used[d.index]].name}: RMS {d.rms_all_views:.4f} px "
                     f"with all views; {d.reason}")
    lines.append("  " + res.rejection_summary())
    lines.extend(_removed_lines(calibration.views))
    lines.extend(_dropped_points_lines(calibration.dropped_points))
    return "\n".join(lines)


def mirror_report(calibration) -> str:
    """Text report of a :class:`~calibration.stages.mirror.MirrorCalibration`: the target pose with σ
    (mm, deg), one line per mirror tilt (RMS px, plane), dropped views, removed dots and points."""
    _require(calibration, "MirrorCalibration", ("result", "names", "point_ids", "views", "dropped_points"))
    r = calibration.result
    sr = r.std_rotation_deg
    st = r.std_translation_mm
    rv = np.degrees(_rotvec(r.R_cam_target))
    lines = [f"mirror extrinsics of {r.camera.name or 'camera'} ({calibration.mode} mode): {len(calibration.names)} mirror tilts × "
             f"{len(calibration.point_ids)} points, RMS {r.rms:.4f} px (closed form {r.closed_form_rms:.4f} px)",
             "  pose of the target (monitor) in the camera frame, x_cam = R_cam_target x_target + t_cam_target:",
             f"    t_cam_target = [{', '.join(f'{v:.3f} ± {s:.3f}' for v, s in zip(r.t_cam_target, st))}] mm",
             f"    rotation vector = [{', '.join(f'{v:.4f} ± {s:.4f}' for v, s in zip(rv, sr))}] deg",
             f"    camera–target distance {np.linalg.norm(r.t_cam_target):.2f} mm",
             "  view                                   RMS (px)  mirror normal (camera frame)       d (mm)"]
    for nm, m, rms in zip(calibration.names, r.mirrors, r.per_mirror_rms):
        lines.append(f"  {_short(nm, 38):38s} {rms:8.4f}  [{m.normal[0]: .5f} {m.normal[1]: .5f} {m.normal[2]: .5f}]  {m.d:8.2f}")
    for nm, why in calibration.dropped:
        lines.append(f"  dropped {nm}: {why}")
    lines.extend(_removed_lines(calibration.views))
    lines.extend(_dropped_points_lines(calibration.dropped_points))
    return "\n".join(lines)


def rig_report(calibration) -> str:
    """Text report of a :class:`~calibration.stages.stereo.RigCalibration`: the method, the rig with
    σ (mm, deg), where σ comes from, the joint result against the per-camera composition, the checks."""
    _require(calibration, "RigCalibration", ("rig", "per_camera", "joint", "far_views", "check_views", "checks"))
    lines = []
    if calibration.joint is not None:
        g = ", ".join(f"{k} {v:.4f}" for k, v in calibration.joint.rms_groups.items())
        lines.append(f"stereo rig: joint bundle adjustment of both cameras' mirror views and {len(calibration.far_views)} "
                     f"view(s) both cameras see; RMS {calibration.joint.rms:.4f} px ({g})")
    else:
        lines.append("stereo rig: composition of the two mirror calibrations (paper Section 2: H_LR = H_TR H_TL^-1)")
    lines.append(_rig_lines(calibration.rig))
    if calibration.covariance_intrinsic is not None and calibration.covariance_extrinsic is not None:
        se = np.degrees(np.sqrt(np.diag(calibration.covariance_extrinsic)[:3]))
        si = np.degrees(np.sqrt(np.diag(calibration.covariance_intrinsic)[:3]))
        lines.append(f"  σ = {calibration.rig.metadata.get('covariance', '')}; rotation σ from the views alone "
                     f"[{', '.join(f'{v:.4f}' for v in se)}] deg, from the intrinsics "
                     f"[{', '.join(f'{v:.4f}' for v in si)}] deg")
    elif calibration.rig.covariance is not None:
        lines.append("  σ holds the intrinsics fixed (no intrinsic covariance propagated): a lower bound for the rotation")
    if calibration.joint is not None:
        d = calibration.rig.errors_to(calibration.per_camera)
        lines.append(f"  vs the per-camera composition: rotation {d['rotation_deg']:.4f} deg, translation "
                     f"{d['translation_mm']:.3f} mm, baseline {d['baseline_mm']:+.3f} mm")
    for v, c in zip(calibration.check_views, calibration.checks):
        lines.append(f"  check {v.name}: " + c.report())
    return "\n".join(lines)


def checkerboard_stereo_report(calibration) -> str:
    """Text report of a :class:`~calibration.stages.stereo.CheckerboardStereo`: RMS, the intrinsics
    when calibrated from the boards, the rig, one line per pair, dropped pairs."""
    _require(calibration, "CheckerboardStereo", ("result", "names", "dropped"))
    lines = [f"stereo calibration from {len(calibration.names)} checkerboard pairs (cv2.stereoCalibrate + float64 bundle "
             f"adjustment), RMS {calibration.result.rms:.4f} px"]
    for nm, res in (("left", calibration.left_intrinsics), ("right", calibration.right_intrinsics)):
        if res is not None:
            lines.append(f"  {nm} intrinsics from the boards: RMS {res.rms:.4f} px, fx {res.camera.fx:.3f} ± "
                         f"{res.std.get('fx', float('nan')):.3f} px")
    lines.append(_rig_lines(calibration.rig))
    for nm, (l, r) in zip(calibration.names, calibration.result.per_view_rms):
        lines.append(f"  {_short(nm, 38):38s} RMS left {l:.4f} px, right {r:.4f} px")
    for nm, why in calibration.dropped:
        lines.append(f"  dropped {nm}: {why}")
    return "\n".join(lines)


def _removed_lines(views) -> list[str]:
    out = [f"    {_short(v.name, 36)}: " + ", ".join(f"{i} ({m:.1f}x)" for i, m in v.removed)
           for v in views if v.ok and v.removed]
    if out:
        out.insert(0, "  dots removed for a poor phase fit (residual x modulation above 1.5x the view's median; "
                      "e.g. blur cut by a mirror's edge):")
    vig = [f"    {_short(v.name, 36)}: " + ", ".join(f"{i} ({m:.3f})" for i, m in v.vignetted)
           for v in views if v.ok and v.vignetted]
    if vig:
        vig.insert(0, "  vignetted dots removed (modulation falls off across the dot: relative slope above 3x the "
                      "view's median; e.g. part of the dot beyond a mirror's edge):")
    return out + vig


def _dropped_points_lines(dropped_points) -> list[str]:
    if not dropped_points:
        return []
    by_view: dict = {}
    for nm, pid, r, thr in dropped_points:
        by_view.setdefault(nm, []).append((pid, r))
    thr = max(t for *_, t in dropped_points)
    lines = [f"  removed {len(dropped_points)} outlier point(s) (|residual| > {thr:.3f} px, i.e. 4 × the robust RMS):"]
    for nm, items in by_view.items():
        lines.append(f"    {_short(nm, 36)}: " + ", ".join(f"{pid} ({r:.3f} px)" for pid, r in sorted(items)))
    return lines


def _short(s: str, n: int) -> str:
    return s if len(s) <= n else "…" + s[-(n - 1):]


def _rotvec(R):
    return vector_from_rotation(R)


def _rig_lines(rig: StereoRig) -> str:
    rv = np.degrees(_rotvec(rig.R_right_left))
    t = rig.t_right_left
    if rig.covariance is not None:
        sr, st = rig.std_rotation_deg, rig.std_translation_mm
        return "\n".join([
            f"  baseline {rig.baseline:.3f} ± {rig.std_baseline_mm:.3f} mm",
            f"  t_right_left = [{', '.join(f'{v:.3f} ± {s:.3f}' for v, s in zip(t, st))}] mm",
            f"  rotation vector R_right_left = [{', '.join(f'{v:.4f} ± {s:.4f}' for v, s in zip(rv, sr))}] deg "
            f"(angle {np.linalg.norm(rv):.4f} deg)"])
    return "\n".join([f"  baseline {rig.baseline:.3f} mm",
                      f"  t_right_left = [{', '.join(f'{v:.3f}' for v in t)}] mm",
                      f"  rotation vector R_right_left = [{', '.join(f'{v:.4f}' for v in rv)}] deg"])
