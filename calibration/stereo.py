"""Stereo rig model, its file, the rig from two mirror calibrations, conventional stereo calibration and checks.

* :class:`StereoRig` — two :class:`~calibration.camera.Camera` s and the right camera's pose in the
  left camera frame, ``x_right = R_right_left @ x_left + t_right_left`` (mm), with an optional 6×6
  covariance ``[δρ (rad), δt (mm)]`` (``R_right_left = exp([δρ]×) R̂``); projection, triangulation,
  JSON file with schema version, units and frame conventions.
* :func:`rig_from_mirror` — the rig from the two per-camera mirror calibrations of the paper behind
  Specula (Optics Express 2019, Section 2: ``H_LR = H_TR (H_TL)⁻¹``), i.e.
  ``R_right_left = R_right_target R_left_targetᵀ``, ``t_right_left = t_right_target − R_right_left t_left_target``.
* :func:`stereo_calibrate` — conventional calibration (``cv2.stereoCalibrateExtended``) from views
  that both cameras see, with a float64 bundle-adjustment polish and the rig covariance from its
  Jacobian, or a bootstrap over views.
* :func:`reconstruct_target` — triangulate a target that both cameras see and compare the distances
  between its points with the known ones (the paper's check on its last frame).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from .bundle import RigBundle
from .camera import (
    FRAME_CONVENTIONS,
    Camera,
    _check_schema,
    _read_json,
    _write_json,
    nearest_rotation,
    require_image_size,
    rigid_fit,
    rotation_angle_deg,
    rotation_from_vector,
    transform_points,
    vector_from_rotation,
)
from .uncertainty import propagate

RIG_SCHEMA = "specula.stereo_rig"
RIG_SCHEMA_VERSION = 1
RIG_UNITS = {"lengths": "mm", "angles": "rad", "pixels": "px",
             "covariance": "6x6 over [drho_x, drho_y, drho_z (rad), dt_x, dt_y, dt_z (mm)], "
                           "R_right_left = expm(skew(drho)) @ R_right_left_estimate"}


@dataclass
class StereoRig:
    """Two cameras and the pose of the right camera in the left camera frame (mm).

    ``x_right = R_right_left @ x_left + t_right_left``. 3-D results are in the left camera frame.
    """

    left: Camera
    right: Camera
    R_right_left: np.ndarray
    t_right_left: np.ndarray
    covariance: np.ndarray | None = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        if not isinstance(self.left, Camera) or not isinstance(self.right, Camera):
            raise ValueError("StereoRig.left and .right must be calibration.camera.Camera instances")
        try:
            R = np.asarray(self.R_right_left, dtype=np.float64)
            t = np.asarray(self.t_right_left, dtype=np.float64).reshape(-1)
            c = None if self.covariance is None else np.asarray(self.covariance, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError("R_right_left, t_right_left and covariance must be arrays of numbers "
                             "(3x3, 3 and 6x6)") from None
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise ValueError(f"R_right_left must be a finite 3x3 matrix, got shape {R.shape}")
        if np.max(np.abs(R @ R.T - np.eye(3))) > 1e-6 or np.linalg.det(R) < 0:
            raise ValueError("R_right_left must be a proper rotation (orthonormal, det +1)")
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise ValueError(f"t_right_left must be a finite 3-vector in mm, got shape {t.shape}")
        if np.linalg.norm(t) == 0:
            raise ValueError("t_right_left is zero: the two cameras cannot share one centre")
        self.R_right_left, self.t_right_left = nearest_rotation(R), t
        if c is not None:
            if c.shape != (6, 6) or not np.all(np.isfinite(c)):
                raise ValueError(f"covariance must be a finite 6x6 matrix, got shape {c.shape}")
            self.covariance = c

    # -- geometry --------------------------------------------------------------------------------
    @property
    def baseline(self) -> float:
        """Distance between the two camera centres (mm)."""
        return float(np.linalg.norm(self.t_right_left))

    @property
    def right_center(self) -> np.ndarray:
        """Right camera centre in the left camera frame (mm)."""
        return -self.R_right_left.T @ self.t_right_left

    def to_right(self, points_left) -> np.ndarray:
        return transform_points(self.R_right_left, self.t_right_left, points_left)

    def project(self, points_left) -> tuple[np.ndarray, np.ndarray]:
        """Project points (N, 3) in the left camera frame (mm) into both images -> ((N, 2), (N, 2)) px."""
        return self.left.project(points_left), self.right.project(self.to_right(points_left))

    def triangulate(self, uv_left, uv_right, refine: bool = True) -> np.ndarray:
        """3-D points (N, 3) in the left camera frame from matching distorted pixels (N, 2) in both images.

        Linear (DLT) triangulation of the undistorted normalised coordinates, then (``refine``)
        Gauss–Newton on the pixel reprojection error of both images, distortion included
        (Hartley & Sturm, CVIU 68(2), 1997, optimal under Gaussian image noise).
        """
        ql = np.asarray(uv_left, dtype=np.float64)
        qr = np.asarray(uv_right, dtype=np.float64)
        if ql.ndim != 2 or ql.shape[1] != 2 or ql.shape != qr.shape:
            raise ValueError(f"uv_left and uv_right must be matching (N, 2) arrays, got {ql.shape} and {qr.shape}")
        if not (np.all(np.isfinite(ql)) and np.all(np.isfinite(qr))):
            raise ValueError("uv_left / uv_right contain NaN or infinite values")
        xl = self.left.undistort_normalized(self.left.pixels_to_normalized(ql))
        xr = self.right.undistort_normalized(self.right.pixels_to_normalized(qr))
        P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
        P2 = np.hstack([self.R_right_left, self.t_right_left[:, None]])
        A = np.stack([xl[:, 0:1] * P1[2] - P1[0], xl[:, 1:2] * P1[2] - P1[1],
                      xr[:, 0:1] * P2[2] - P2[0], xr[:, 1:2] * P2[2] - P2[1]], axis=1)  # (N, 4, 4)
        _, _, Vt = np.linalg.svd(A)
        Xh = Vt[:, -1, :]
        X = Xh[:, :3] / Xh[:, 3:4]
        if not refine:
            return X
        obs = np.concatenate([ql, qr], axis=1)
        for _ in range(10):
            f0 = np.concatenate(self.project(X), axis=1) - obs
            J = np.empty((X.shape[0], 4, 3))
            for k in range(3):
                h = 1e-6 * np.maximum(1.0, np.abs(X[:, k]))
                Xp = X.copy()
                Xp[:, k] += h
                J[:, :, k] = (np.concatenate(self.project(Xp), axis=1) - obs - f0) / h[:, None]
            JtJ = np.einsum("nik,nil->nkl", J, J)
            Jtf = np.einsum("nik,ni->nk", J, f0)
            dX = np.linalg.solve(JtJ, Jtf[..., None])[..., 0]
            X = X - dX
            if np.max(np.abs(dX)) < 1e-9:
                break
        return X

    # -- uncertainty -----------------------------------------------------------------------------
    @property
    def std_rotation_deg(self) -> np.ndarray | None:
        return None if self.covariance is None else np.degrees(np.sqrt(np.diag(self.covariance)[:3]))

    @property
    def std_translation_mm(self) -> np.ndarray | None:
        return None if self.covariance is None else np.sqrt(np.diag(self.covariance)[3:])

    @property
    def std_baseline_mm(self) -> float | None:
        if self.covariance is None:
            return None
        g = self.t_right_left / self.baseline
        return float(np.sqrt(g @ self.covariance[3:, 3:] @ g))

    def errors_to(self, other: "StereoRig") -> dict:
        """Rotation (deg), translation (mm) and baseline (mm, %) differences with another rig."""
        db = self.baseline - other.baseline
        return {"rotation_deg": rotation_angle_deg(self.R_right_left, other.R_right_left),
                "translation_mm": float(np.linalg.norm(self.t_right_left - other.t_right_left)),
                "baseline_mm": db, "baseline_percent": 100.0 * db / other.baseline}

    def report(self) -> str:
        rv = np.degrees(vector_from_rotation(self.R_right_left))
        lines = [f"stereo rig: baseline {self.baseline:.3f} mm"
                 + (f" ± {self.std_baseline_mm:.3f}" if self.covariance is not None else ""),
                 f"  t_right_left = {np.array2string(self.t_right_left, precision=3)} mm"
                 + (f" ± {np.array2string(self.std_translation_mm, precision=3)}" if self.covariance is not None else ""),
                 f"  rotation vector = {np.array2string(rv, precision=4)} deg"
                 + (f" ± {np.array2string(self.std_rotation_deg, precision=4)}" if self.covariance is not None else "")]
        return "\n".join(lines)

    # -- files -----------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        out = {"schema": RIG_SCHEMA, "schema_version": RIG_SCHEMA_VERSION, "units": dict(RIG_UNITS),
               "conventions": dict(FRAME_CONVENTIONS,
                                   rig="x_right = R_right_left @ x_left + t_right_left; 3-D results in the left camera frame"),
               "left": self.left.to_dict(), "right": self.right.to_dict(),
               "R_right_left": self.R_right_left.tolist(), "t_right_left": self.t_right_left.tolist(),
               "baseline_mm": self.baseline}
        if self.covariance is not None:
            out["covariance"] = self.covariance.tolist()
        if self.metadata:
            out["metadata"] = self.metadata
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "StereoRig":
        if not isinstance(data, dict):
            raise ValueError(f"a rig description must be a dict, got {type(data).__name__}")
        _check_schema(data, RIG_SCHEMA, RIG_SCHEMA_VERSION, "stereo rig")
        missing = [k for k in ("left", "right", "R_right_left", "t_right_left") if k not in data]
        if missing:
            raise ValueError(f"stereo rig description lacks the keys {missing}")
        metadata = data.get("metadata", {})
        if not isinstance(metadata, dict):
            raise ValueError(f"stereo rig description: 'metadata' must be a dict, got {type(metadata).__name__}")
        cams = []
        for side in ("left", "right"):
            try:
                cams.append(Camera.from_dict(data[side]))
            except ValueError as exc:
                raise ValueError(f"{side} camera: {exc}") from None
        return cls(cams[0], cams[1], data["R_right_left"], data["t_right_left"], covariance=data.get("covariance"),
                   metadata=metadata)

    def save(self, path) -> None:
        """Write the rig as JSON (schema ``specula.stereo_rig`` version 1); both cameras must have a known
        image size (:func:`calibration.camera.require_image_size`)."""
        for side, cam in (("left", self.left), ("right", self.right)):
            require_image_size(cam, f"cannot save the rig: {side} camera")
        _write_json(path, self.to_dict())

    @classmethod
    def load(cls, path) -> "StereoRig":
        """Read a rig JSON file; another schema version or a malformed file raises ``ValueError``
        naming the file and the field."""
        data = _read_json(path, "stereo rig")
        try:
            rig = cls.from_dict(data)
            for side, cam in (("left", rig.left), ("right", rig.right)):
                require_image_size(cam, f"{side} camera")
            return rig
        except ValueError as exc:
            raise ValueError(f"stereo rig file {os.fspath(path)!r}: {exc}") from None


# -- rig from mirrors ------------------------------------------------------------------------------
def _pose_of(result, which):
    for attr in ("R_cam_target", "t_cam_target"):
        if not hasattr(result, attr):
            raise ValueError(f"{which} must be a mirror_extrinsics result (with R_cam_target, t_cam_target), "
                             f"got {type(result).__name__}")
    return np.asarray(result.R_cam_target, float), np.asarray(result.t_cam_target, float)


def rig_from_mirror(left_result, right_result, left_camera: Camera | None = None,
                    right_camera: Camera | None = None) -> StereoRig:
    """Stereo rig from the mirror calibrations of the left and right cameras against the same target.

    ``R_right_left = R_right_target R_left_targetᵀ``, ``t_right_left = t_right_target − R_right_left
    t_left_target`` (paper Section 2). The covariance is propagated from the two pose covariances
    (taken as independent) when both results carry one. Both results must refer to the same target
    frame (the monitor did not move between the two cameras' mirror views). The results are
    :class:`~calibration.mirror.MirrorExtrinsicsResult` (which carry their camera) or closed-form
    solutions (then pass ``left_camera`` / ``right_camera``).
    """
    R_l, t_l = _pose_of(left_result, "left_result")
    R_r, t_r = _pose_of(right_result, "right_result")
    left_camera = left_camera if left_camera is not None else getattr(left_result, "camera", None)
    right_camera = right_camera if right_camera is not None else getattr(right_result, "camera", None)
    if left_camera is None or right_camera is None:
        raise ValueError("rig_from_mirror needs the cameras: pass left_camera= and right_camera= with closed-form results")
    R_rl = R_r @ R_l.T
    t_rl = t_r - R_rl @ t_l
    cov = None
    cl = getattr(left_result, "pose_covariance", None)
    cr = getattr(right_result, "pose_covariance", None)
    if cl is not None and cr is not None:
        def f(x):
            Rl = rotation_from_vector(x[0:3]) @ R_l
            Rr = rotation_from_vector(x[6:9]) @ R_r
            R = Rr @ Rl.T
            t = (t_r + x[9:12]) - R @ (t_l + x[3:6])
            return np.concatenate([vector_from_rotation(R @ R_rl.T), t])

        C = np.zeros((12, 12))
        C[:6, :6], C[6:, 6:] = cl, cr
        cov = propagate(f, np.zeros(12), C, step=1e-6)
        cov = 0.5 * (cov + cov.T)
    return StereoRig(left_camera, right_camera, R_rl, t_rl, covariance=cov,
                     metadata={"method": "mirror, per camera" + ("" if cov is not None else " (closed form)")})


# -- conventional stereo calibration -----------------------------------------------------------------
@dataclass
class StereoCalibrationResult:
    """Result of :func:`stereo_calibrate`: the rig (with covariance), RMS (px) overall and per view
    ``(V, 2)`` (left, right), the left-camera pose of the target in each view, the OpenCV RMS."""

    rig: StereoRig
    rms: float
    per_view_rms: np.ndarray
    poses_left: list
    opencv_rms: float
    bootstrap_samples: np.ndarray | None = None

    def report(self) -> str:
        lines = [f"stereo calibration: {len(self.per_view_rms)} views, RMS {self.rms:.4f} px (OpenCV {self.opencv_rms:.4f} px)",
                 self.rig.report()]
        for v, (l, r) in enumerate(self.per_view_rms):
            lines.append(f"  view {v:3d}: RMS left {l:.4f} px, right {r:.4f} px")
        return "\n".join(lines)


def _validate_stereo_views(object_points, left_points, right_points):
    if not all(isinstance(a, (list, tuple)) for a in (object_points, left_points, right_points)):
        raise ValueError("object_points, left_points, right_points must be lists with one array per view")
    if not len(object_points) == len(left_points) == len(right_points):
        raise ValueError(f"got {len(object_points)}, {len(left_points)}, {len(right_points)} views; they must match")
    if len(object_points) < 1:
        raise ValueError("stereo calibration needs at least one view seen by both cameras")
    out = []
    for v, (o, a, b) in enumerate(zip(object_points, left_points, right_points)):
        o, a, b = (np.asarray(z, dtype=np.float64) for z in (o, a, b))
        if o.ndim != 2 or o.shape[1] != 3 or a.shape != (o.shape[0], 2) or b.shape != (o.shape[0], 2):
            raise ValueError(f"view {v}: expected (N, 3), (N, 2), (N, 2) arrays with equal N, got {o.shape}, {a.shape}, {b.shape}")
        if o.shape[0] < 4:
            raise ValueError(f"view {v} has {o.shape[0]} points; need at least 4")
        if not all(np.all(np.isfinite(z)) for z in (o, a, b)):
            raise ValueError(f"view {v} contains NaN or infinite values")
        out.append((o, a, b))
    return out


def _cv_stereo(left, right, views, flags):
    import cv2

    obj = [np.ascontiguousarray(o, np.float32).reshape(-1, 1, 3) for o, _, _ in views]
    ql = [np.ascontiguousarray(a, np.float32).reshape(-1, 1, 2) for _, a, _ in views]
    qr = [np.ascontiguousarray(b, np.float32).reshape(-1, 1, 2) for _, _, b in views]
    dl = left.dist.copy() if left.dist.size else np.zeros(5)
    dr = right.dist.copy() if right.dist.size else np.zeros(5)
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        out = cv2.stereoCalibrateExtended(obj, ql, qr, left.K.copy(), dl, right.K.copy(), dr, left.size,
                                          np.eye(3), np.zeros((3, 1)), flags=flags, criteria=criteria)
    except cv2.error as exc:
        raise ValueError(f"OpenCV stereo calibration failed: {exc.err}") from None
    rms, K1, D1, K2, D2, R, T = out[:7]
    rvecs, tvecs = out[9], out[10]
    return float(rms), K1, D1, K2, D2, np.asarray(R, float), np.asarray(T, float).ravel(), rvecs, tvecs


def _stereo_ba(left, right, views, R0, t0, poses0, sigma_px):
    model = RigBundle(left, right, np.zeros((0, 3)), [], [], views, None, (R0, t0), [], [], poses0)
    x, r, cov = model.solve(sigma_px)
    p = model.unpack(x)
    R, t = p["rig"]
    return R, t, p["far"], r, cov[model.sl["rig"], model.sl["rig"]]


def stereo_calibrate(left: Camera, right: Camera, object_points, left_points, right_points, *,
                     fix_intrinsics: bool = True, flags: int = 0, uncertainty: str = "jacobian",
                     n_bootstrap: int = 50, rng=None, sigma_px: float | None = None) -> StereoCalibrationResult:
    """Conventional stereo calibration from views of a target that both cameras see (``cv2.stereoCalibrateExtended``).

    Parameters
    ----------
    left, right : Camera
        Intrinsics (held fixed when ``fix_intrinsics``; otherwise refined by OpenCV and then held).
    object_points, left_points, right_points : lists of (N_v, 3), (N_v, 2), (N_v, 2)
        Target points (mm, target frame) and their images in each camera, rows aligned.
    flags : int
        Extra OpenCV flags.
    uncertainty : ``"jacobian"``, ``"bootstrap"`` or ``"none"``
        Rig covariance from the Jacobian of a float64 bundle adjustment over the rig and the view
        poses (intrinsics fixed), or from ``n_bootstrap`` resamplings of the views with replacement.
    """
    import cv2

    views = _validate_stereo_views(object_points, left_points, right_points)
    if uncertainty not in ("jacobian", "bootstrap", "none"):
        raise ValueError(f"uncertainty must be 'jacobian', 'bootstrap' or 'none', got {uncertainty!r}")
    fl = int(flags) | (cv2.CALIB_FIX_INTRINSIC if fix_intrinsics else cv2.CALIB_USE_INTRINSIC_GUESS)
    cv_rms, K1, D1, K2, D2, R, T, rvecs, tvecs = _cv_stereo(left, right, views, fl)
    if not fix_intrinsics:
        nl, nr = max(left.dist.size, 5), max(right.dist.size, 5)
        left = Camera(K1, np.asarray(D1).ravel()[:nl], left.size, left.name)
        right = Camera(K2, np.asarray(D2).ravel()[:nr], right.size, right.name)
    poses0 = [(rotation_from_vector(np.asarray(rv).ravel()), np.asarray(tv, float).ravel()) for rv, tv in zip(rvecs, tvecs)]
    R, t, poses, r, cov = _stereo_ba(left, right, views, R, T, poses0, sigma_px)
    per_view, o = [], 0
    for (oo, _, _) in views:
        n = 2 * oo.shape[0]
        rl = r[o:o + n].reshape(-1, 2)
        rr = r[o + n:o + 2 * n].reshape(-1, 2)
        per_view.append([np.sqrt(np.mean(np.sum(rl ** 2, 1))), np.sqrt(np.mean(np.sum(rr ** 2, 1)))])
        o += 2 * n
    samples = None
    rig_cov = cov if uncertainty == "jacobian" else None
    if uncertainty == "bootstrap":
        rng = np.random.default_rng(0) if rng is None else rng
        samples = []
        V = len(views)
        for _ in range(int(n_bootstrap)):
            idx = rng.integers(0, V, V)
            _, _, _, _, _, Rb, Tb, _, _ = _cv_stereo(left, right, [views[i] for i in idx], fl | cv2.CALIB_FIX_INTRINSIC)
            samples.append(np.concatenate([vector_from_rotation(Rb @ R.T), Tb]))
        samples = np.asarray(samples)
        rig_cov = np.cov(samples.T)
    rig = StereoRig(left, right, nearest_rotation(R), t, covariance=rig_cov,
                    metadata={"method": "cv2.stereoCalibrateExtended + float64 bundle adjustment",
                              "views": len(views), "uncertainty": uncertainty})
    return StereoCalibrationResult(rig=rig, rms=float(np.sqrt(np.mean(np.sum(r.reshape(-1, 2) ** 2, 1)))),
                                   per_view_rms=np.asarray(per_view), poses_left=poses, opencv_rms=cv_rms,
                                   bootstrap_samples=samples)


# -- checks ----------------------------------------------------------------------------------------
@dataclass
class TargetReconstruction:
    """Result of :func:`reconstruct_target` (mm unless stated).

    ``points`` (N, 3) left camera frame; ``distance_errors`` measured − true distance for every pair
    of points (N(N−1)/2,); ``neighbour_errors`` the same for nearest-neighbour pairs (the paper's
    "distance between adjacent dots"); ``fit_rms`` RMS residual of a rigid fit of the target onto
    the reconstruction; ``reprojection_rms`` (px) over both images.
    """

    points: np.ndarray
    distance_errors: np.ndarray
    true_distances: np.ndarray
    neighbour_errors: np.ndarray
    neighbour_true: np.ndarray
    fit_rms: float
    reprojection_rms: float

    @property
    def rms_distance_error(self) -> float:
        return float(np.sqrt(np.mean(self.distance_errors ** 2)))

    @property
    def max_distance_error(self) -> float:
        return float(np.max(np.abs(self.distance_errors)))

    @property
    def mean_relative_error(self) -> float:
        """Mean of (measured − true)/true over all pairs (signed, dimensionless): the scale error."""
        return float(np.mean(self.distance_errors / self.true_distances))

    def report(self) -> str:
        ne = self.neighbour_errors
        return (f"target check: {self.points.shape[0]} points; neighbour distance {np.mean(self.neighbour_true):.3f} mm, "
                f"error {np.mean(ne):+.4f} ± {np.std(ne):.4f} mm; all pairs RMS {self.rms_distance_error:.4f} mm, "
                f"max {self.max_distance_error:.4f} mm, scale error {100 * self.mean_relative_error:+.4f} %; "
                f"rigid-fit RMS {self.fit_rms:.4f} mm; reprojection RMS {self.reprojection_rms:.4f} px")


def reconstruct_target(rig: StereoRig, left_points, right_points, object_points) -> TargetReconstruction:
    """Triangulate a target both cameras see and compare its point distances with the true ones.

    left_points, right_points : (N, 2) px; object_points : (N, 3) mm (target frame), rows aligned.
    """
    X = np.asarray(object_points, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] < 2:
        raise ValueError(f"object_points must have shape (N, 3) with N >= 2, got {X.shape}")
    ql = np.asarray(left_points, dtype=np.float64)
    qr = np.asarray(right_points, dtype=np.float64)
    if ql.shape != (X.shape[0], 2) or qr.shape != (X.shape[0], 2):
        raise ValueError(f"left_points and right_points must have shape ({X.shape[0]}, 2), got {ql.shape}, {qr.shape}")
    P = rig.triangulate(ql, qr)
    iu, ju = np.triu_indices(X.shape[0], 1)
    d_true = np.linalg.norm(X[iu] - X[ju], axis=1)
    if np.any(d_true == 0):
        raise ValueError("object_points contains duplicate points")
    d_meas = np.linalg.norm(P[iu] - P[ju], axis=1)
    err = d_meas - d_true
    nn = np.isclose(d_true, d_true.min(), rtol=1e-6)
    R, t = rigid_fit(X, P)
    fit = transform_points(R, t, X) - P
    pl, pr = rig.project(P)
    rep = np.concatenate([pl - ql, pr - qr])
    return TargetReconstruction(points=P, distance_errors=err, true_distances=d_true, neighbour_errors=err[nn],
                                neighbour_true=d_true[nn], fit_rms=float(np.sqrt(np.mean(np.sum(fit ** 2, 1)))),
                                reprojection_rms=float(np.sqrt(np.mean(np.sum(rep ** 2, 1)))))
