"""Pinhole camera with OpenCV's lens distortion model (float64, NumPy).

Frames and units (docs/conventions.md): camera frame x right, y down, z forward; millimetres;
pixel (0, 0) is the centre of the top-left pixel. Distortion coefficients follow OpenCV's order
``k1, k2, p1, p2[, k3[, k4, k5, k6]]`` (the rational model when 8 are given).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _as_points(points, ncols: int, name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == ncols:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != ncols:
        raise ValueError(f"{name} must have shape (N, {ncols}), got {np.shape(points)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


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
    """

    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    size: tuple[int, int] = (0, 0)
    name: str = ""

    def __post_init__(self):
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(f"Camera.K must be a finite 3x3 matrix, got {np.shape(self.K)}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"Camera.K focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise ValueError(f"Camera.K must be upper triangular with last row [0, 0, 1], got\n{K}")
        dist = np.asarray(self.dist, dtype=np.float64).ravel()
        if dist.size not in (0, 4, 5, 8) or not np.all(np.isfinite(dist)):
            raise ValueError(
                f"Camera.dist must hold 0, 4, 5 or 8 finite OpenCV coefficients (k1 k2 p1 p2 k3 k4 k5 k6), got {dist.size}"
            )
        size = tuple(int(s) for s in self.size)
        if len(size) != 2 or min(size) < 0:
            raise ValueError(f"Camera.size must be (width, height) in pixels, got {self.size}")
        self.K, self.dist, self.size = K, dist, size

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
        xy = _as_points(xy, 2, "xy")
        k1, k2, p1, p2, k3, k4, k5, k6 = self.dist8
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=1)

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
