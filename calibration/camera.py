"""Pinhole camera with OpenCV's lens distortion model (float64, NumPy), pose helpers and the
camera JSON file.

Frames and units (docs/conventions.md): camera frame x right, y down, z forward; millimetres;
pixel (0, 0) is the centre of the top-left pixel. Distortion coefficients follow OpenCV's order
``k1, k2, p1, p2[, k3[, k4, k5, k6]]`` (the rational model when 8 are given).

Camera file (JSON, ``Camera.save`` / ``Camera.load``)::

    {"schema": "specula.camera", "schema_version": 1,
     "units": {...}, "conventions": {...},          # written for the reader, checked on load
     "name": "left", "size": [width, height],
     "K": [[fx, skew, cx], [0, fy, cy], [0, 0, 1]],  # px
     "dist": [k1, k2, p1, p2, k3, ...],              # OpenCV order, normalised coordinates
     "covariance": {"names": ["fx", ...], "matrix": [[...]]},   # optional: of the calibrated parameters
     "metadata": {...}}                              # free, e.g. calibration report

A file with another ``schema`` or ``schema_version`` is refused with a ``ValueError``.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kernels._atomic import atomic_output
from kernels.checks import as_points

#: Name and version of the camera JSON schema written by :meth:`Camera.save`.
CAMERA_SCHEMA = "specula.camera"
CAMERA_SCHEMA_VERSION = 1

#: Conventions written into every camera / rig file so that a reader needs no other document.
FRAME_CONVENTIONS: dict[str, str] = {
    "camera_frame": "x right, y down, z forward (OpenCV); right-handed",
    "pixel_origin": "pixel (0, 0) is the centre of the top-left pixel; x = column, y = row",
    "distortion_model": "OpenCV: k1 k2 p1 p2 k3 k4 k5 k6 applied to normalised coordinates x/z, y/z",
    "pose_naming": "R_a_b, t_a_b map frame-b coordinates into frame a: x_a = R_a_b @ x_b + t_a_b",
}
CAMERA_UNITS: dict[str, str] = {"K": "px", "size": "px", "dist": "dimensionless", "lengths": "mm",
                                 "covariance": "products of the parameters' units (px for fx fy cx cy)"}
#: Intrinsic parameter names, in the order of ``K``'s ``fx fy cx cy`` then OpenCV's distortion terms.
INTRINSIC_PARAMETERS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


def _as_points(points, ncols: int, name: str) -> np.ndarray:
    """(N, ncols) float64 finite points; one point may be given as a 1-D (ncols,) array; N = 0 allowed."""
    arr = np.asarray(points)
    if arr.ndim == 1 and arr.shape[0] == ncols:
        arr = arr[None, :]
    return as_points(arr, name, ncols=ncols, allow_empty=True)


def _as_matrix3(R, name: str) -> np.ndarray:
    arr = np.asarray(R, dtype=np.float64)
    if arr.shape != (3, 3) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be a finite 3x3 matrix, got shape {np.shape(R)}")
    return arr


def _as_vector3(t, name: str) -> np.ndarray:
    arr = np.asarray(t, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be a finite 3-vector, got shape {np.shape(t)}")
    return arr


# -- rotations -----------------------------------------------------------------------------------
def rotation_from_vector(rvec) -> np.ndarray:
    """Rotation vector (axis * angle, rad) -> rotation matrix (3, 3), Rodrigues' formula."""
    w = _as_vector3(rvec, "rvec")
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        return np.eye(3) + W + 0.5 * W @ W
    k = w / theta
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * Kx @ Kx


def vector_from_rotation(R) -> np.ndarray:
    """Rotation matrix (3, 3) -> rotation vector (axis * angle, rad); inverse of :func:`rotation_from_vector`."""
    from scipy.spatial.transform import Rotation

    R = _as_matrix3(R, "R")
    return Rotation.from_matrix(R).as_rotvec()


def rotation_angle_deg(R_a, R_b=None) -> float:
    """Angle in degrees of the rotation ``R_a`` (or of ``R_a @ R_b.T`` when ``R_b`` is given)."""
    R = _as_matrix3(R_a, "R_a")
    if R_b is not None:
        R = R @ _as_matrix3(R_b, "R_b").T
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    # arccos loses precision near 0: use the skew part for small angles
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.degrees(np.arctan2(s, c)))


def nearest_rotation(M) -> np.ndarray:
    """Closest proper rotation (Frobenius norm) to a 3x3 matrix, by SVD."""
    M = _as_matrix3(M, "M")
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rigid_fit(points_from, points_to) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid transform (Kabsch / Umeyama without scale): ``to ≈ R @ from + t``.

    points_from, points_to : (N, 3) float64, N >= 3, not collinear. Returns ``R`` (3, 3) proper
    rotation and ``t`` (3,).
    """
    A = _as_points(points_from, 3, "points_from")
    B = _as_points(points_to, 3, "points_to")
    if A.shape != B.shape or A.shape[0] < 3:
        raise ValueError(f"rigid_fit needs two (N, 3) arrays with N >= 3 of equal shape, got {A.shape} and {B.shape}")
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    H = (A - ca).T @ (B - cb)
    U, s, Vt = np.linalg.svd(H)
    if s[1] <= 1e-12 * max(s[0], 1e-300):
        raise ValueError("rigid_fit: the points are collinear, the rotation about their line is undetermined")
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


def transform_points(R, t, points) -> np.ndarray:
    """``R @ p + t`` for every row p of ``points`` (N, 3)."""
    p = _as_points(points, 3, "points")
    return p @ _as_matrix3(R, "R").T + _as_vector3(t, "t")


def distort_normalized(xy, dist, jacobian: bool = False):
    """OpenCV's lens distortion: ideal normalised coordinates -> distorted normalised coordinates.

    The host (NumPy, float64) twin of ``kernels.distortion.distort_normalized``; the one copy of
    the model in calibration (:meth:`Camera.distort_normalized`, the bundle adjustments).

    Parameters
    ----------
    xy : (N, 2) array-like
        Ideal normalised coordinates ``(X/Z, Y/Z)`` (dimensionless); NaN rows give NaN rows.
    dist : (0|4|5|8,) array-like
        OpenCV coefficients ``k1 k2 p1 p2 [k3 [k4 k5 k6]]``.
    jacobian : bool
        Also return the analytic Jacobian d(distorted)/d(ideal).

    Returns
    -------
    (N, 2) float64 distorted normalised coordinates, and with ``jacobian`` a tuple with the
    (N, 2, 2) Jacobian (symmetric per point).
    """
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"xy must have shape (N, 2), got {np.shape(xy)}")
    d = np.asarray(dist, dtype=np.float64).ravel()
    if d.size not in (0, 4, 5, 8):
        raise ValueError(f"dist must hold 0, 4, 5 or 8 OpenCV coefficients (k1 k2 p1 p2 k3 k4 k5 k6), got {d.size}")
    k1, k2, p1, p2, k3, k4, k5, k6 = np.concatenate([d, np.zeros(8 - d.size)])
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    distorted = np.empty_like(xy)
    distorted[:, 0] = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    distorted[:, 1] = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    if not jacobian:
        return distorted
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    dradial = (dnum * den - num * dden) / (den * den)  # d radial / d r2
    J = np.empty((xy.shape[0], 2, 2))
    J[:, 0, 0] = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
    J[:, 0, 1] = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    J[:, 1, 0] = J[:, 0, 1]
    J[:, 1, 1] = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
    return distorted, J


#: Largest image side (px) a camera accepts.
MAX_IMAGE_SIDE = 1 << 20


def _image_size(size) -> tuple[int, int]:
    """``(width, height)`` in whole pixels, both positive or both 0 (size unknown)."""
    bad = ValueError(f"Camera.size must be (width, height) in whole pixels, both positive (or both 0: "
                     f"unknown), got {size!r:.80}")
    if isinstance(size, (str, bytes, dict)) or not hasattr(size, "__len__") or len(size) != 2:
        raise bad
    out = []
    for v in size:
        if isinstance(v, (bool, np.bool_)):
            raise bad
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise bad from None
        if not np.isfinite(f) or f != int(f) or not 0 <= f <= MAX_IMAGE_SIDE:
            raise bad
        out.append(int(f))
    if (out[0] == 0) != (out[1] == 0):
        raise bad
    return out[0], out[1]


@dataclass
class Camera:
    """Intrinsic model of one camera.

    Attributes
    ----------
    K : (3, 3) float64
        Camera matrix in pixels ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.
    dist : (n,) float64
        OpenCV distortion coefficients, n in {0, 4, 5, 8}: ``k1, k2, p1, p2, k3, k4, k5, k6``.
    size : (width, height)
        Image size in pixels.
    name : str
        Free label (``"left"``, ``"right"``...).
    covariance : (P, P) float64 or None
        Covariance of the calibrated intrinsic parameters named in ``covariance_names`` (units: px² for
        ``fx fy cx cy``, products with px for the mixed terms, dimensionless for distortion), as
        :func:`calibration.calibrate_intrinsics` estimates it; None when unknown. The rig
        calibration propagates it into the rig's covariance.
    covariance_names : tuple of str
        Parameter of each row/column of ``covariance``, from :data:`INTRINSIC_PARAMETERS`.
    """

    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    size: tuple[int, int] = (0, 0)
    name: str = ""
    covariance: np.ndarray | None = None
    covariance_names: tuple = ()

    def __post_init__(self):
        try:
            K = np.asarray(self.K, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"Camera.K must be a finite 3x3 matrix of numbers, got {self.K!r:.80}") from None
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(f"Camera.K must be a finite 3x3 matrix, got {np.shape(self.K)}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"Camera.K focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise ValueError(f"Camera.K must be upper triangular with last row [0, 0, 1], got\n{K}")
        K = K.copy()
        K[2] = (0.0, 0.0, 1.0)  # exactly (a file's rounding of it is accepted, not kept)
        try:
            dist = np.asarray(self.dist, dtype=np.float64).ravel()
        except (TypeError, ValueError):
            raise ValueError(f"Camera.dist must be a list of numbers, got {self.dist!r:.80}") from None
        if dist.size not in (0, 4, 5, 8) or not np.all(np.isfinite(dist)):
            raise ValueError(
                f"Camera.dist must hold 0, 4, 5 or 8 finite OpenCV coefficients (k1 k2 p1 p2 k3 k4 k5 k6), got {dist.size}"
            )
        size = _image_size(self.size)

        self.K, self.dist, self.size = K, dist, size
        if self.covariance is not None:
            try:
                C = np.asarray(self.covariance, dtype=np.float64)
                names = tuple(str(n) for n in self.covariance_names)
            except (TypeError, ValueError):
                raise ValueError("Camera.covariance must be a square matrix of numbers and covariance_names "
                                 "a list of parameter names") from None
            if C.ndim != 2 or C.shape[0] != C.shape[1] or C.shape[0] != len(names) or not np.all(np.isfinite(C)):
                raise ValueError(f"Camera.covariance must be a finite square matrix with one row per name in "
                                 f"covariance_names ({len(names)}), got shape {C.shape}")
            unknown = [n for n in names if n not in INTRINSIC_PARAMETERS[:4 + max(dist.size, 0)]]
            if unknown or len(set(names)) != len(names):
                raise ValueError(f"Camera.covariance_names must be distinct parameters of this camera "
                                 f"({INTRINSIC_PARAMETERS[:4 + dist.size]}), got {names}")
            if not np.allclose(C, C.T, rtol=1e-6, atol=1e-9 * float(np.max(np.abs(C), initial=0.0))) or np.min(np.diag(C)) < 0:
                raise ValueError("Camera.covariance must be symmetric with a non-negative diagonal")
            self.covariance, self.covariance_names = 0.5 * C + 0.5 * C.T, names  # no overflow near 1e308
        elif self.covariance_names:
            raise ValueError("Camera.covariance_names given without a covariance")

    def _parameter_index(self, name: str) -> int:
        """Index of ``name`` in :data:`INTRINSIC_PARAMETERS`, if this camera has that parameter."""
        i = INTRINSIC_PARAMETERS.index(name) if name in INTRINSIC_PARAMETERS else -1
        if i < 0 or i >= 4 + self.dist.size:
            raise ValueError(f"unknown parameter {name!r} for a camera with {self.dist.size} distortion terms")
        return i

    def parameter(self, name: str) -> float:
        """Value of one intrinsic parameter by name (:data:`INTRINSIC_PARAMETERS`)."""
        i = self._parameter_index(name)
        return float((self.fx, self.fy, self.cx, self.cy)[i]) if i < 4 else float(self.dist[i - 4])

    def with_parameters(self, **values: float) -> "Camera":
        """A copy with some intrinsic parameters changed, e.g. ``camera.with_parameters(cx=1175.2)``.

        The copy carries no covariance (it describes other values)."""
        K, dist = self.K.copy(), self.dist.copy()
        for name, v in values.items():
            i = self._parameter_index(name)
            if i < 4:
                K[(0, 1, 0, 1)[i], (0, 1, 2, 2)[i]] = float(v)
            else:
                dist[i - 4] = float(v)
        return Camera(K=K, dist=dist, size=self.size, name=self.name)

    # -- convenience -------------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def dist8(self) -> np.ndarray:
        """Distortion padded to the 8 coefficients ``k1 k2 p1 p2 k3 k4 k5 k6``."""
        out = np.zeros(8)
        out[: self.dist.size] = self.dist
        return out

    # -- distortion in normalised coordinates --------------------------------------------------
    def distort_normalized(self, xy) -> np.ndarray:
        """Apply the OpenCV distortion to ideal normalised coordinates (N, 2) -> (N, 2)."""
        return distort_normalized(_as_points(xy, 2, "xy"), self.dist8)

    def undistort_normalized(self, xy_distorted, tol: float = 1e-12, max_iter: int = 100) -> np.ndarray:
        """Invert :meth:`distort_normalized` by Newton iterations with a numerical Jacobian.

        Converges to ``tol`` in normalised units (1e-12 ~ 1e-9 px for f ~ 1000 px), unlike
        OpenCV's fixed 5 fixed-point iterations.
        """
        target = _as_points(xy_distorted, 2, "xy_distorted")
        xy = target.copy()
        if not np.any(self.dist):
            return xy
        h = 1e-7
        for _ in range(max_iter):
            f = self.distort_normalized(xy) - target
            if np.max(np.abs(f)) < tol:
                break
            fx = (self.distort_normalized(xy + [h, 0]) - self.distort_normalized(xy - [h, 0])) / (2 * h)
            fy = (self.distort_normalized(xy + [0, h]) - self.distort_normalized(xy - [0, h])) / (2 * h)
            det = fx[:, 0] * fy[:, 1] - fy[:, 0] * fx[:, 1]
            det = np.where(np.abs(det) < 1e-15, 1e-15, det)
            dx = (fy[:, 1] * f[:, 0] - fy[:, 0] * f[:, 1]) / det
            dy = (-fx[:, 1] * f[:, 0] + fx[:, 0] * f[:, 1]) / det
            xy = xy - np.stack([dx, dy], axis=1)
        return xy

    # -- pixels <-> rays ---------------------------------------------------------------------
    def normalized_to_pixels(self, xy) -> np.ndarray:
        xy = _as_points(xy, 2, "xy")
        K = self.K
        u = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
        v = K[1, 1] * xy[:, 1] + K[1, 2]
        return np.stack([u, v], axis=1)

    def pixels_to_normalized(self, uv) -> np.ndarray:
        uv = _as_points(uv, 2, "uv")
        K = self.K
        y = (uv[:, 1] - K[1, 2]) / K[1, 1]
        x = (uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return np.stack([x, y], axis=1)

    def project(self, points_cam) -> np.ndarray:
        """Project 3-D points in the camera frame (N, 3) mm to distorted pixels (N, 2).

        Points with z <= 0 (behind the camera) raise ``ValueError``.
        """
        p = _as_points(points_cam, 3, "points_cam")
        if np.any(p[:, 2] <= 0):
            bad = int(np.argmax(p[:, 2] <= 0))
            raise ValueError(f"point {bad} lies behind the camera (z = {p[bad, 2]:.6g} mm); cannot project")
        xy = p[:, :2] / p[:, 2:3]
        return self.normalized_to_pixels(self.distort_normalized(xy))

    def undistort_points(self, uv) -> np.ndarray:
        """Distorted pixels (N, 2) -> ideal (undistorted) pixels (N, 2) with the same K."""
        return self.normalized_to_pixels(self.undistort_normalized(self.pixels_to_normalized(uv)))

    def rays(self, uv) -> np.ndarray:
        """Unit viewing rays (N, 3) in the camera frame for distorted pixels (N, 2)."""
        xy = self.undistort_normalized(self.pixels_to_normalized(uv))
        d = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def project_points(self, points, R_cam_obj=None, t_cam_obj=None) -> np.ndarray:
        """Project points (N, 3) given in an object frame to distorted pixels (N, 2).

        ``x_cam = R_cam_obj @ x_obj + t_cam_obj`` (identity / zero when omitted), then :meth:`project`.
        """
        p = _as_points(points, 3, "points")
        if R_cam_obj is not None or t_cam_obj is not None:
            R = np.eye(3) if R_cam_obj is None else R_cam_obj
            t = np.zeros(3) if t_cam_obj is None else t_cam_obj
            p = transform_points(R, t, p)
        return self.project(p)

    @property
    def skew(self) -> float:
        """``K[0, 1]`` in pixels (0 for OpenCV calibrations)."""
        return float(self.K[0, 1])

    # -- images ----------------------------------------------------------------------------------
    def undistortion_maps(self, K_new=None, size=None) -> tuple[np.ndarray, np.ndarray]:
        """Maps for ``cv2.remap`` that undistort an image of this camera.

        Returns ``(map_x, map_y)``, float32 arrays of shape (height, width): for each pixel of the
        undistorted image (camera matrix ``K_new``, default ``K``) the distorted pixel to sample,
        i.e. :meth:`project` of its ray. Computed with this model (skew included; OpenCV's
        ``initUndistortRectifyMap`` ignores ``K[0, 1]``), pixel centres as in docs/conventions.md.
        """
        w, h = self.size if size is None else (int(size[0]), int(size[1]))
        if w <= 0 or h <= 0:
            raise ValueError(f"undistortion_maps needs the image size, got size={(w, h)}; set Camera.size or pass size=")
        new = Camera(self.K if K_new is None else _as_matrix3(K_new, "K_new"))
        map_x = np.empty((h, w), dtype=np.float32)
        map_y = np.empty((h, w), dtype=np.float32)
        u = np.arange(w, dtype=np.float64)
        rows = max(1, 262144 // w)
        for y0 in range(0, h, rows):
            yy, xx = np.meshgrid(np.arange(y0, min(h, y0 + rows), dtype=np.float64), u, indexing="ij")
            xy = new.pixels_to_normalized(np.stack([xx.ravel(), yy.ravel()], axis=1))
            uv = self.normalized_to_pixels(self.distort_normalized(xy))
            map_x[y0:y0 + yy.shape[0]] = uv[:, 0].reshape(yy.shape)
            map_y[y0:y0 + yy.shape[0]] = uv[:, 1].reshape(yy.shape)
        return map_x, map_y

    def undistort_image(self, image, K_new=None, interpolation: str = "cubic") -> np.ndarray:
        """Undistort an image (H, W) or (H, W, C) of this camera with ``cv2.remap``.

        ``interpolation`` is ``"linear"`` or ``"cubic"``; pixels that map outside the input are 0.
        The output has the input's dtype and the size of ``Camera.size`` (which must match the image).
        For display and checks: ``cv2.remap`` quantises sub-pixel positions to 1/32 px, so measure on
        the original images and undistort *points* (:meth:`undistort_points`) instead.
        """
        import cv2

        img = np.asarray(image)
        if img.ndim not in (2, 3) or img.size == 0:
            raise ValueError(f"image must be a non-empty (H, W) or (H, W, C) array, got shape {img.shape}")
        h, w = img.shape[:2]
        if self.size != (0, 0) and self.size != (w, h):
            raise ValueError(f"image is {w}x{h} px but the camera was calibrated for {self.size[0]}x{self.size[1]} px")
        modes = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC}
        if interpolation not in modes:
            raise ValueError(f"interpolation must be one of {sorted(modes)}, got {interpolation!r}")
        map_x, map_y = self.undistortion_maps(K_new=K_new, size=(w, h))
        return cv2.remap(img, map_x, map_y, modes[interpolation], borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    # -- files -----------------------------------------------------------------------------------
    def to_dict(self, metadata: dict | None = None) -> dict[str, Any]:
        """JSON-ready dictionary with schema, version, units and conventions (see module docstring)."""
        out: dict[str, Any] = {
            "schema": CAMERA_SCHEMA,
            "schema_version": CAMERA_SCHEMA_VERSION,
            "units": dict(CAMERA_UNITS),
            "conventions": dict(FRAME_CONVENTIONS),
            "name": self.name,
            "size": [int(self.size[0]), int(self.size[1])],
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
        }
        if self.covariance is not None:
            out["covariance"] = {"names": list(self.covariance_names), "matrix": self.covariance.tolist()}
        if metadata:
            out["metadata"] = metadata
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "Camera":
        """Inverse of :meth:`to_dict`; refuses another schema or schema version with ``ValueError``."""
        if not isinstance(data, dict):
            raise ValueError(f"a camera description must be a dict, got {type(data).__name__}")
        _check_schema(data, CAMERA_SCHEMA, CAMERA_SCHEMA_VERSION, "camera")
        missing = [k for k in ("K", "dist", "size") if k not in data]
        if missing:
            raise ValueError(f"camera description lacks the keys {missing}")
        cov = data.get("covariance")
        if cov is not None and not (isinstance(cov, dict) and "names" in cov and "matrix" in cov
                                    and isinstance(cov["names"], list)):
            raise ValueError("camera description: 'covariance' must be {'names': [...], 'matrix': [[...]]}")
        name = data.get("name", "")
        if not isinstance(name, str):
            raise ValueError(f"camera description: 'name' must be a string, got {type(name).__name__}")
        return cls(K=data["K"], dist=data["dist"], size=data["size"], name=name,
                   covariance=None if cov is None else cov["matrix"],
                   covariance_names=() if cov is None else tuple(cov["names"]))

    def save(self, path, metadata: dict | None = None) -> None:
        """Write the camera as JSON (see module docstring); ``metadata`` is stored as given. A camera whose image
        size is unknown (``(0, 0)``) is refused: a camera file must say the size it was calibrated for."""
        require_image_size(self, "cannot save the camera")
        _write_json(path, self.to_dict(metadata))

    @classmethod
    def load(cls, path) -> "Camera":
        """Read a camera JSON file written by :meth:`save`; a malformed file raises ``ValueError``
        naming the file and the field."""
        data = _read_json(path, "camera")
        try:
            return require_image_size(cls.from_dict(data), "")
        except ValueError as exc:
            raise ValueError(f"camera file {os.fspath(path)!r}: {exc}") from None


def require_image_size(camera: "Camera", context: str) -> "Camera":
    """``camera`` when its image size is known; ``ValueError`` (starting with ``context``) when it is ``(0, 0)``.

    In memory a size of ``(0, 0)`` means "unknown"; a camera or rig *file* must give the size the
    camera was calibrated for (the principal point and the distortion only mean something for that
    size), so files with ``[0, 0]`` are refused when written and when read.
    """
    if tuple(camera.size) == (0, 0):
        name = f" {camera.name!r}" if camera.name else ""
        raise ValueError(f"{context + ': ' if context else ''}the image size of camera{name} is unknown (size [0, 0]); "
                         "a camera file must give the (width, height) in px it was calibrated for")
    return camera


def _check_schema(data: dict, schema: str, version: int, what: str) -> None:
    got = data.get("schema")
    if got != schema:
        raise ValueError(f"not a Specula {what} file: schema is {got!r}, expected {schema!r}")
    v = data.get("schema_version")
    if v != version:
        raise ValueError(
            f"{what} file has schema_version {v!r} but this version of Specula reads version {version}; "
            f"convert the file or use the matching Specula version"
        )


def _write_json(path, data: dict) -> None:
    with atomic_output(path, mkdir=False) as tmp:  # whole or not at all
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=2)
            f.write("\n")


def _read_json(path, what: str) -> dict:
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError:
        raise ValueError(f"{what} file {path!r} does not exist") from None
    except IsADirectoryError:
        raise ValueError(f"{what} file {path!r} is a directory") from None
    except PermissionError:
        raise ValueError(f"{what} file {path!r} cannot be read (permission denied)") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{what} file {path!r} is not UTF-8 text ({exc.reason} at byte {exc.start}); "
                         "is it a JSON file?") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{what} file {path!r} is not valid JSON ({exc}); is it truncated?") from None
    except RecursionError:
        raise ValueError(f"{what} file {path!r} is not a valid {what} file (JSON nested too deeply)") from None
