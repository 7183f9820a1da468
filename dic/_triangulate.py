"""Triangulation of matched image points with a calibrated stereo rig, and point undistortion.

User-facing wrappers around :mod:`kernels.triangulate` (Warp, float64 throughout). Frames and units
follow docs/conventions.md: 3-D points are in millimetres in the **left camera frame**; the rig
stores the right camera's pose in the left frame, ``x_right = R_right_left @ x_left + t_right_left``;
image points are ``(x, y)`` pixels with (0, 0) the centre of the top-left pixel. Method, statuses
and measured accuracy: docs/stereo.md, section "Triangulation".
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kernels._device import host_copy
from kernels.checks import as_points
from kernels.triangulate import METHODS, TriangulationStatus
from kernels.triangulate import optimal_triangulation_jacobian as _optimal_jacobian
from kernels.triangulate import triangulate_points as _triangulate_points
from kernels.triangulate import undistort_points as _undistort_points

__all__ = ["TriangulationStatus", "Triangulation", "Undistortion", "triangulate", "undistort_points"]


def _status_counts(status: np.ndarray) -> dict[str, int]:
    codes, counts = np.unique(status, return_counts=True)
    return {TriangulationStatus(int(c)).name: int(n) for c, n in zip(codes, counts)}


@dataclass(frozen=True)
class Triangulation:
    """Result of :func:`triangulate`; unpacks to ``(points, residuals)``.

    Attributes
    ----------
    points : (N, 3) float64
        3-D points in mm in the left camera frame. NaN only where ``status`` is
        ``INVALID_INPUT``, ``UNDISTORT_FAILED`` or ``DEGENERATE``.
    residuals : (N,) float64
        RMS reprojection residual in px, ``sqrt((|e_left|^2 + |e_right|^2) / 2)`` with the
        distortion included. NaN where ``points`` is NaN and for ``BEHIND_CAMERA``.
    status : (N,) int32
        :class:`kernels.triangulate.TriangulationStatus` code per point.
    method : str
        ``"optimal"`` or ``"linear"``.
    """

    points: np.ndarray
    residuals: np.ndarray
    status: np.ndarray
    method: str

    def __iter__(self):
        yield self.points
        yield self.residuals

    def __len__(self) -> int:
        return int(self.status.shape[0])

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: ``status == OK``."""
        return self.status == TriangulationStatus.OK

    def counts(self) -> dict[str, int]:
        """Number of points per status name, e.g. ``{"OK": 998, "DEGENERATE": 2}``."""
        return _status_counts(self.status)


@dataclass(frozen=True)
class Undistortion:
    """Result of :func:`undistort_points`; unpacks to ``(points, status)``.

    ``points`` (N, 2) float64 are ideal (undistorted) pixels with the camera's own K, NaN where
    ``status`` is ``UNDISTORT_FAILED`` or ``INVALID_INPUT``; ``status`` (N,) int32.
    """

    points: np.ndarray
    status: np.ndarray

    def __iter__(self):
        yield self.points
        yield self.status

    @property
    def valid(self) -> np.ndarray:
        return self.status == TriangulationStatus.OK

    def counts(self) -> dict[str, int]:
        return _status_counts(self.status)


def _camera_fields(camera, name: str):
    missing = [a for a in ("K", "dist", "size") if not hasattr(camera, a)]
    if missing:
        raise ValueError(
            f"{name} must be a calibration.camera.Camera (attributes K, dist, size); "
            f"got {type(camera).__name__} without {', '.join(missing)}"
        )
    size = tuple(camera.size) if camera.size is not None else None
    if size is not None and (len(size) != 2 or min(size) <= 0):
        size = None  # (0, 0) = unknown size: no out-of-image check
    return camera.K, camera.dist, size


def _image_points(points, name: str) -> np.ndarray:
    # NaN pixels are allowed (they come back NaN with their status); so is N = 0
    return as_points(points, name, allow_empty=True, finite=False)


def undistort_points(camera, points, device=None, *, margin_px: float = 0.0, tol_px: float = 1e-9,
                     max_iter: int = 50) -> Undistortion:
    """Remove lens distortion from observed pixels: distorted (N, 2) px -> ideal (N, 2) px.

    Newton iterations on the OpenCV model with an analytic Jacobian, to ``tol_px`` (the forward
    model reproduces the input to within it; default 1e-9 px) plus one final step.

    Parameters
    ----------
    camera : calibration.camera.Camera (K, dist, size)
    points : (N, 2) array-like, px
        NaN rows are flagged ``INVALID_INPUT``; points outside the image by more than
        ``margin_px`` are computed and flagged ``OUT_OF_IMAGE``.
    device : None, "cpu" or "cuda:N"

    Returns
    -------
    Undistortion
        Unpacks to ``(points, status)``: (N, 2) float64 ideal pixels and (N,) int32 statuses.
    """
    K, dist, size = _camera_fields(camera, "camera")
    pts = _image_points(points, "points")
    out, status = _undistort_points(pts, K, dist, image_size=size, margin_px=margin_px, tol_px=tol_px,
                                    max_iter=max_iter, device=device)
    return Undistortion(host_copy(out).reshape(-1, 2), host_copy(status))


def triangulate(rig, points_left, points_right, *, method: str = "optimal", device=None, tol_px: float = 1e-9,
                max_iter: int = 20, min_parallax: float = 1e-6, margin_px: float = 0.0) -> Triangulation:
    """Triangulate matched observed pixels into 3-D points (mm, left camera frame).

    ``method="linear"``: homogeneous DLT (Hartley & Zisserman, *Multiple View Geometry*, Sec.
    12.2; what ``cv2.triangulatePoints`` does) on undistorted normalised points.
    ``method="optimal"``: Gauss-Newton from the DLT point minimising the sum of squared
    reprojection errors in both images, distortion included -- the maximum-likelihood point for
    independent isotropic Gaussian noise on the observed pixels (cf. Hartley & Sturm,
    "Triangulation", CVIU 68(2), 1997, doi:10.1006/cviu.1997.0547, optimal for distortion-free
    cameras only). Both run in float64 on the device; see docs/stereo.md.

    Parameters
    ----------
    rig : calibration.stereo.StereoRig
        Any object with ``left``, ``right`` (cameras with ``K``, ``dist``, ``size``),
        ``R_right_left`` (3, 3) and ``t_right_left`` (3,) mm.
    points_left, points_right : (N, 2) array-like, px
        Matched observed (distorted) pixels; NaN rows are flagged, not raised.
    method : "optimal" (default) or "linear"
    device : None, "cpu" or "cuda:N"
    tol_px : float
        Convergence tolerance (px) of the undistortion and of the optimal refinement.
    max_iter : int
        Gauss-Newton iterations before ``NOT_CONVERGED`` (3 suffice on the paper's rig).
    min_parallax : float, rad
        Rays closer to parallel than this are ``DEGENERATE`` (default 1e-6 rad).
    margin_px : float
        Inputs farther than this outside their image get ``OUT_OF_IMAGE`` (``inf`` disables).

    Returns
    -------
    Triangulation
        Unpacks to ``(points, residuals)``: (N, 3) float64 mm and (N,) float64 px; also carries
        ``status`` ((N,) int32 :class:`TriangulationStatus`), ``valid`` and ``counts()``.

    Raises
    ------
    ValueError
        Wrong shapes, different numbers of left and right points, an unknown ``method``, or an
        invalid rig (not a rotation, zero baseline, bad intrinsics).
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    missing = [a for a in ("left", "right", "R_right_left", "t_right_left") if not hasattr(rig, a)]
    if missing:
        raise ValueError(
            "rig must be a calibration.stereo.StereoRig (attributes left, right, R_right_left, t_right_left); "
            f"got {type(rig).__name__} without {', '.join(missing)}"
        )
    K_l, dist_l, size_l = _camera_fields(rig.left, "rig.left")
    K_r, dist_r, size_r = _camera_fields(rig.right, "rig.right")
    pl = _image_points(points_left, "points_left")
    pr = _image_points(points_right, "points_right")
    if pl.shape[0] != pr.shape[0]:
        raise ValueError(
            f"points_left and points_right must hold the same number of matched points, got {pl.shape[0]} and {pr.shape[0]}"
        )
    points, residuals, status = _triangulate_points(
        pl, pr, K_left=K_l, dist_left=dist_l, K_right=K_r, dist_right=dist_r,
        R_right_left=rig.R_right_left, t_right_left=np.asarray(rig.t_right_left, dtype=np.float64).ravel(),
        image_size_left=size_l, image_size_right=size_r, method=method, tol_px=tol_px, max_iter=max_iter,
        min_parallax=min_parallax, margin_px=margin_px, device=device,
    )
    return Triangulation(host_copy(points).reshape(-1, 3), host_copy(residuals), host_copy(status), method)


def optimal_triangulation_jacobian(rig, points_left, points_right, points, device=None) -> np.ndarray:
    """(N, 3, 4) derivatives (mm/px) of optimal-triangulated points by ``(x_left, y_left, x_right, y_right)``.

    ``points`` (N, 3) mm, left camera frame: :func:`triangulate` (``method="optimal"``) of the observed
    pixels ``points_left``, ``points_right`` (N, 2). Analytic, by the implicit function theorem on the
    optimality condition (:func:`kernels.triangulate.optimal_triangulation_jacobian`), in one launch; it
    stands in for central differences of :func:`triangulate` (:func:`dic.quality.triangulation_jacobian`),
    which need 8 triangulations. Rows with a NaN input are NaN.
    """
    K_l, dist_l, _ = _camera_fields(rig.left, "rig.left")
    K_r, dist_r, _ = _camera_fields(rig.right, "rig.right")
    pl = _image_points(points_left, "points_left")
    pr = _image_points(points_right, "points_right")
    X = np.asarray(points, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] != pl.shape[0] or pr.shape != pl.shape:
        raise ValueError(f"points_left, points_right must have shape (N, 2) and points (N, 3) with the same N, got "
                         f"{pl.shape}, {pr.shape} and {X.shape}")
    return _optimal_jacobian(pl, pr, X, K_left=K_l, dist_left=dist_l, K_right=K_r, dist_right=dist_r,
                             R_right_left=rig.R_right_left,
                             t_right_left=np.asarray(rig.t_right_left, dtype=np.float64).ravel(), device=device)
