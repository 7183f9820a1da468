"""Pose files of the mirror stage: one camera's pose relative to the monitor with the observations
it came from (JSON, schema ``specula.mirror_calibration`` version 1), so that the rig stage can
re-adjust both cameras jointly (:func:`calibration.stages.stereo.calibrate_rig_from_mirrors`).

Units in the file: mm, rad, px; conventions: docs/conventions.md (``x_cam = R_cam_target @ x_target
+ t_cam_target``; mirror planes ``n · x + d = 0`` in the camera frame, ``|n| = 1``, ``d > 0``).
"""
from __future__ import annotations

import os

import numpy as np

from .camera import Camera, _check_schema, _read_json, _write_json
from .mirror import mirror_extrinsics
from .views import ViewResult

__all__ = ["MIRROR_POSE_SCHEMA", "MIRROR_POSE_SCHEMA_VERSION", "mirror_pose_dict", "mirror_pose_fields",
           "write_mirror_pose", "read_mirror_pose_fields"]

#: Name and version of the pose file written by :meth:`MirrorCalibration.save`.
MIRROR_POSE_SCHEMA = "specula.mirror_calibration"
MIRROR_POSE_SCHEMA_VERSION = 1


def _nan_to_none(points) -> list:
    """(N, 2) array → nested lists with None where a value is NaN (read back as NaN by ``np.asarray(..., float)``)."""
    return [[None if not np.isfinite(v) else float(v) for v in row] for row in np.asarray(points, dtype=np.float64)]


def _require_mirror_calibration(calibration) -> None:
    missing = [a for a in ("result", "point_ids", "object_points", "mirrored_points", "names", "dropped_points")
               if not hasattr(calibration, a)]
    if missing:
        raise ValueError(f"expected a calibration.stages MirrorCalibration, got {type(calibration).__name__} "
                         f"(no {', '.join(missing)})")


def mirror_pose_dict(calibration) -> dict:
    """JSON-ready content of a :class:`~calibration.stages.mirror.MirrorCalibration`'s pose file: the
    camera, the pose of the target with its 6×6 covariance, the mirror planes, and the observations
    (point ids, object points (N, 3) mm, mirrored image points K × (N, 2) px with null where not seen)."""
    _require_mirror_calibration(calibration)
    r = calibration.result
    return {
        "schema": MIRROR_POSE_SCHEMA, "schema_version": MIRROR_POSE_SCHEMA_VERSION,
        "units": {"lengths": "mm", "angles": "rad", "pixels": "px",
                  "pose_covariance": "6x6 over [domega_x, domega_y, domega_z (rad), dt_x, dt_y, dt_z (mm)], "
                                     "R_cam_target = expm(skew(domega)) @ R_cam_target_estimate"},
        "conventions": {"pose": "x_cam = R_cam_target @ x_target + t_cam_target",
                        "mirror_planes": "n . x + d = 0 in the camera frame, |n| = 1, d > 0",
                        "target_frame": "see the target file (calibration/targets.py)"},
        "camera": r.camera.to_dict(),
        "R_cam_target": r.R_cam_target.tolist(), "t_cam_target": r.t_cam_target.tolist(),
        "pose_covariance": r.pose_covariance.tolist(),
        "rms_px": r.rms, "closed_form_rms_px": r.closed_form_rms,
        "closed_form": {"R_cam_target": r.closed_form.R_cam_target.tolist(),
                        "t_cam_target": r.closed_form.t_cam_target.tolist()},
        "mirrors": [{"view": nm, "normal": m.normal.tolist(), "d": m.d, "rms_px": float(rms)}
                    for nm, m, rms in zip(calibration.names, r.mirrors, r.per_mirror_rms)],
        "mode": calibration.mode, "sigma_px": calibration.sigma_px,
        "dropped": [{"view": n, "reason": w} for n, w in calibration.dropped],
        "dropped_points": [{"view": n, "id": i, "residual_px": r, "threshold_px": t}
                           for n, i, r, t in calibration.dropped_points],
        "target": calibration.target,
        "observations": {"point_ids": [int(i) for i in calibration.point_ids],
                         "object_points": calibration.object_points.tolist(),
                         "views": calibration.names,
                         # points not seen in a view are NaN rows: written as null (strict JSON)
                         "mirrored_points": [_nan_to_none(q) for q in calibration.mirrored_points]},
    }


def write_mirror_pose(path, calibration) -> None:
    """Write ``calibration``'s pose file (:func:`mirror_pose_dict`) to ``path`` (JSON)."""
    _write_json(path, mirror_pose_dict(calibration))


def mirror_pose_fields(data: dict) -> dict:
    """The :class:`~calibration.stages.mirror.MirrorCalibration` fields (constructor keywords) of a pose
    file's content. The adjustment is re-run from the stored observations; raises ``ValueError`` for
    another schema or version, a missing key, or a stored pose that does not follow from the observations."""
    if not isinstance(data, dict):
        raise ValueError(f"a mirror calibration must be a dict, got {type(data).__name__}")
    _check_schema(data, MIRROR_POSE_SCHEMA, MIRROR_POSE_SCHEMA_VERSION, "mirror calibration")
    try:
        cam = Camera.from_dict(data["camera"])
        obs = data["observations"]
        X = np.asarray(obs["object_points"], dtype=np.float64)
        q = [np.asarray(v, dtype=np.float64) for v in obs["mirrored_points"]]
        ids = np.asarray(obs["point_ids"], dtype=np.int64)
        names = [str(n) for n in obs["views"]]
    except KeyError as exc:
        raise ValueError(f"mirror calibration file lacks the key {exc}") from None
    sigma = data.get("sigma_px")
    # the adjustment is re-run from the observations (deterministic, ~0.1 s): the result object
    # then carries everything (closed form, covariance, residuals)
    res = mirror_extrinsics(cam, q, X, sigma_px=sigma)
    stored_t = np.asarray(data.get("t_cam_target", res.t_cam_target), dtype=np.float64)
    if np.linalg.norm(stored_t - res.t_cam_target) > 1e-3 * max(1.0, np.linalg.norm(stored_t)):
        raise ValueError("the pose stored in the mirror calibration file does not follow from its observations; "
                         "was the file edited?")
    return dict(result=res, point_ids=ids, object_points=X, mirrored_points=q, names=names,
                views=[ViewResult(d["view"], error=d["reason"]) for d in data.get("dropped", [])],
                mode=str(data.get("mode", "dots")), target=data.get("target"), sigma_px=sigma,
                dropped_points=[(d["view"], d["id"], d["residual_px"], d["threshold_px"])
                                for d in data.get("dropped_points", [])])


def read_mirror_pose_fields(path) -> dict:
    """:func:`mirror_pose_fields` of the pose file at ``path``; a malformed file raises ``ValueError``
    naming it."""
    data = _read_json(path, "mirror calibration")
    try:
        return mirror_pose_fields(data)
    except (ValueError, TypeError, KeyError, IndexError, AttributeError, OverflowError) as exc:
        msg = str(exc) if isinstance(exc, ValueError) else f"malformed content ({type(exc).__name__}: {exc})"
        raise ValueError(f"mirror calibration file {os.fspath(path)!r}: {msg}") from None
