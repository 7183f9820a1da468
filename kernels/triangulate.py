"""Undistortion of image points, projection and two-view triangulation (Warp kernels, float64).

Frames and units follow docs/conventions.md: camera frame x right, y down, z forward; millimetres;
pixel (0, 0) is the centre of the top-left pixel; the right camera's pose is stored in the left
camera's frame, ``x_right = R_right_left @ x_left + t_right_left``. Lens distortion is OpenCV's
model with coefficients ``k1, k2, p1, p2[, k3[, k4, k5, k6]]`` (rational model when 8 are given),
from :mod:`kernels.distortion` (shared with the renderer).

Precision. Unlike the rest of the device code (float32), everything here is float64: image
coordinates of 2000-4000 px have a float32 spacing of 1.2e-4 to 2.4e-4 px and metre-scale 3-D
coordinates a spacing of 2.4e-4 to 4.9e-4 mm, so float32 can neither represent a 1e-6 px
undistortion nor a micrometre-level 3-D point. One thread handles one point; the per-point
problems are tiny (2x2 Newton, a 4x4 SVD, a 3x3 Gauss-Newton), so float64 costs little
(CPU throughput and the measured effect of float32 in docs/stereo.md).

Results stay on the device: the launchers return ``wp.array`` outputs (written in place when
``out=`` is given, so a reused ``out`` is overwritten by the next call). ``.numpy()`` of a CPU array
is a view of that buffer, of a CUDA array a copy; for host results that are the caller's on every
device use :func:`kernels._device.host_copy` (as :mod:`dic.triangulate` does).

Algorithms
----------
* Undistortion: Newton's method on ``distort(x) = x_d`` with the analytic 2x2 Jacobian and
  backtracking, started at ``x = x_d``, iterated until the residual of the *forward* model is
  below ``tol_px`` pixels (default 1e-9 px), then one more Newton step (quadratic convergence
  takes the error to rounding level) -- not OpenCV's fixed 5 fixed-point iterations. A
  solution where the Jacobian determinant is not positive lies beyond the fold of the polynomial
  model (no unique inverse) and is reported as ``UNDISTORT_FAILED``.
* Linear triangulation: homogeneous DLT (Hartley & Zisserman, *Multiple View Geometry*, 2nd ed.,
  Sec. 12.2; the method of ``cv2.triangulatePoints``) on undistorted normalised coordinates with
  ``P_left = [I | 0]`` and ``P_right = [R | t / |t|]`` (baseline scaled to unit length for
  conditioning; the result is scaled back). The smallest right singular vector of the 4x4 DLT
  matrix ``A`` comes from a one-sided Jacobi SVD in float64.
* Optimal triangulation: Gauss-Newton on the 3-D point, started from the linear solution,
  minimising the sum of squared reprojection errors in *both* images measured in the observed
  (distorted) pixels, with the distortion inside the projection and an analytic Jacobian,
  with step halving for steps larger than 1e-3 px (smaller steps are taken in full: their
  cost change is below the rounding of the cost). Under independent, isotropic Gaussian
  noise on the measured pixel positions this is the maximum-likelihood point, which Hartley &
  Sturm's polynomial method ("Triangulation", Computer Vision and Image Understanding 68(2),
  146-157, 1997, doi:10.1006/cviu.1997.0547) is only for an undistorted pinhole camera. From
  the DLT point it needs 1-2 steps (measured: 0.02 px and 0.5 px noise, every point converged
  with max_iter=3, the last iteration only confirming convergence). Iterations stop when the Gauss-Newton step
  moves both projections by less than ``tol_px``.

Residual: ``sqrt((|e_left|^2 + |e_right|^2) / 2)`` in pixels, the RMS over the two images of
the distance between the observed point and the projection of the 3-D point (distortion
included), for both methods.

Per-point status (``TriangulationStatus``, int32), most severe first:
``INVALID_INPUT`` (NaN/inf input; outputs NaN), ``UNDISTORT_FAILED`` (lens model not invertible
there; NaN), ``DEGENERATE`` (rays parallel within ``min_parallax``; NaN), ``BEHIND_CAMERA``
(the intersection has z <= 0 in a camera; point kept, residual NaN), ``NOT_CONVERGED`` (optimal
refinement hit ``max_iter`` or could not decrease the cost; last iterate kept),
``OUT_OF_IMAGE`` (an input point lies outside its image by more than ``margin_px``: the result
is computed but the lens model is extrapolated), ``OK``.
"""
from __future__ import annotations

import sys
from enum import IntEnum

import numpy as np
import warp as wp

from ._device import resolve_device
from ._launch import launch_1d
from .checks import positive_float, positive_int
from .distortion import distort_normalized, distort_normalized_jacobian, distortion_coefficients, vec8d


class TriangulationStatus(IntEnum):
    """Outcome of undistortion / projection / triangulation for one point (stored as int32)."""

    OK = 0                #: converged, in front of both cameras, inside the image(s)
    OUT_OF_IMAGE = 1      #: computed, but an input point is outside its image (lens model extrapolated)
    NOT_CONVERGED = 2     #: optimal refinement stopped before tol_px; the last iterate is returned
    BEHIND_CAMERA = 3     #: the point has z <= 0 in the left or right camera frame (residual NaN)
    DEGENERATE = 4        #: parallel (or anti-parallel) rays: no finite intersection (outputs NaN)
    UNDISTORT_FAILED = 5  #: the distortion model has no (unique) inverse at this point (outputs NaN)
    INVALID_INPUT = 6     #: NaN or infinite input coordinates (outputs NaN)


_OK = wp.constant(int(TriangulationStatus.OK))
_OUT_OF_IMAGE = wp.constant(int(TriangulationStatus.OUT_OF_IMAGE))
_NOT_CONVERGED = wp.constant(int(TriangulationStatus.NOT_CONVERGED))
_BEHIND_CAMERA = wp.constant(int(TriangulationStatus.BEHIND_CAMERA))
_DEGENERATE = wp.constant(int(TriangulationStatus.DEGENERATE))
_UNDISTORT_FAILED = wp.constant(int(TriangulationStatus.UNDISTORT_FAILED))
_INVALID_INPUT = wp.constant(int(TriangulationStatus.INVALID_INPUT))

#: Newton iterations allowed for undistortion inside triangulation (typically 3-6 are used).
UNDISTORT_MAX_ITER = 50
_UNDISTORT_MAX_ITER = wp.constant(UNDISTORT_MAX_ITER)

_ZERO = wp.constant(wp.float64(0.0))
_ONE = wp.constant(wp.float64(1.0))
_TWO = wp.constant(wp.float64(2.0))
_HALF = wp.constant(wp.float64(0.5))
#: Gauss-Newton steps that move both projections by less than this (px) are taken without line search
_FULL_STEP_PX = wp.constant(wp.float64(1.0e-3))

mat23d = wp.types.matrix(shape=(2, 3), dtype=wp.float64)
mat32d = wp.types.matrix(shape=(3, 2), dtype=wp.float64)
#: relative step (of |X|) of the central differences of the projection Jacobian in optimal_jacobian_kernel
_JACOBIAN_STEP = wp.constant(wp.float64(1.0e-4))

# forward kernels only: no adjoint code (halves compilation time)
wp.set_module_options({"enable_backward": False})


@wp.struct
class CameraModel:
    """Intrinsics of one camera in float64: K entries (px), OpenCV distortion, image size (px).

    ``width = height = 0`` means the image size is unknown (no out-of-image check).
    """

    fx: wp.float64
    fy: wp.float64
    cx: wp.float64
    cy: wp.float64
    skew: wp.float64
    dist: vec8d  # OpenCV k1 k2 p1 p2 k3 k4 k5 k6 (kernels.distortion)
    width: wp.float64
    height: wp.float64


# ---------------------------------------------------------------------------------------------
# camera model
# ---------------------------------------------------------------------------------------------
@wp.func
def normalized_to_pixel(xy: wp.vec2d, cam: CameraModel) -> wp.vec2d:
    return wp.vec2d(cam.fx * xy[0] + cam.skew * xy[1] + cam.cx, cam.fy * xy[1] + cam.cy)


@wp.func
def pixel_to_normalized(uv: wp.vec2d, cam: CameraModel) -> wp.vec2d:
    y = (uv[1] - cam.cy) / cam.fy
    return wp.vec2d((uv[0] - cam.cx - cam.skew * y) / cam.fx, y)


@wp.func
def normalized_delta_to_pixels(d: wp.vec2d, cam: CameraModel) -> wp.vec2d:
    """Linear part of K applied to a difference of normalised coordinates (px)."""
    return wp.vec2d(cam.fx * d[0] + cam.skew * d[1], cam.fy * d[1])


@wp.func
def in_image(uv: wp.vec2d, cam: CameraModel, margin_px: wp.float64) -> bool:
    """True when the image size is unknown or ``uv`` lies within the pixel area plus margin."""
    if cam.width <= _ZERO or cam.height <= _ZERO:
        return True
    lo = -_HALF - margin_px
    return uv[0] >= lo and uv[1] >= lo and uv[0] <= cam.width - _HALF + margin_px and uv[1] <= cam.height - _HALF + margin_px


@wp.func
def project_camera(X: wp.vec3d, cam: CameraModel) -> wp.vec2d:
    """Distorted pixel of a point ``X`` (mm) in the camera frame; requires ``X[2] > 0``."""
    xy = wp.vec2d(X[0] / X[2], X[1] / X[2])
    return normalized_to_pixel(distort_normalized(xy, cam.dist), cam)


@wp.func
def project_camera_jacobian(X: wp.vec3d, cam: CameraModel) -> mat23d:
    """d(pixel)/d(X) of :func:`project_camera` (2x3, px/mm)."""
    iz = _ONE / X[2]
    xy = wp.vec2d(X[0] * iz, X[1] * iz)
    _xyd, Jd = distort_normalized_jacobian(xy, cam.dist)
    Jk = wp.mat22d(cam.fx, cam.skew, _ZERO, cam.fy)
    Jn = mat23d(iz, _ZERO, -xy[0] * iz, _ZERO, iz, -xy[1] * iz)
    return (Jk @ Jd) @ Jn


@wp.func
def undistort_newton(uv: wp.vec2d, cam: CameraModel, tol_px: wp.float64, max_iter: int):
    """Ideal normalised coordinates of distorted pixel ``uv`` and 1 on success, 0 on failure.

    Newton on ``distort(x) - x_d = 0`` with the analytic Jacobian and step halving; converged
    when the forward model reproduces ``uv`` within ``tol_px`` pixels and the Jacobian
    determinant is positive (the solution is on the invertible side of the model's fold).
    """
    target = pixel_to_normalized(uv, cam)
    xy = target
    ok = int(0)
    for _it in range(max_iter):
        err = wp.length(normalized_delta_to_pixels(distort_normalized(xy, cam.dist) - target, cam))
        _xyd, J = distort_normalized_jacobian(xy, cam.dist)
        det = wp.determinant(J)
        if err < tol_px:
            if det > _ZERO:
                ok = 1
                # one more (quadratically convergent) step takes the error from < tol_px to
                # rounding level at the cost of one 2x2 solve
                xy = xy - wp.inverse(J) @ (distort_normalized(xy, cam.dist) - target)
            break
        if not (det > _ZERO):
            break
        step = wp.inverse(J) @ (distort_normalized(xy, cam.dist) - target)
        alpha = _ONE
        cand = xy - step
        for _ls in range(40):
            cand = xy - alpha * step
            if wp.length(normalized_delta_to_pixels(distort_normalized(cand, cam.dist) - target, cam)) < err:
                break
            alpha = alpha * _HALF
        xy = cand
    return xy, ok


# ---------------------------------------------------------------------------------------------
# triangulation
# ---------------------------------------------------------------------------------------------
@wp.func
def ray_parallax_sine(xl: wp.vec2d, xr: wp.vec2d, R: wp.mat33d) -> wp.float64:
    """|sin| of the angle between the left and right viewing rays (both in the left frame)."""
    dl = wp.vec3d(xl[0], xl[1], _ONE)
    dr = wp.transpose(R) @ wp.vec3d(xr[0], xr[1], _ONE)
    return wp.length(wp.cross(dl, dr)) / (wp.length(dl) * wp.length(dr))


@wp.func
def smallest_right_singular_vector4(A_in: wp.mat44d) -> wp.vec4d:
    """Unit right singular vector of the smallest singular value of a 4x4 matrix.

    One-sided (Hestenes) Jacobi: plane rotations orthogonalise the columns of ``A V``; the
    smallest column norm is the smallest singular value and the matching column of ``V`` its
    right singular vector. Unlike an eigen-decomposition of ``A^T A`` this does not square the
    condition number (Demmel & Veselic, SIAM J. Matrix Anal. Appl. 13(4), 1992).
    """
    A = A_in
    V = wp.identity(n=4, dtype=wp.float64)
    for _sweep in range(30):
        rotated = int(0)
        for p in range(3):
            for q in range(p + 1, 4):
                alpha = _ZERO
                beta = _ZERO
                gamma = _ZERO
                for k in range(4):
                    alpha = alpha + A[k, p] * A[k, p]
                    beta = beta + A[k, q] * A[k, q]
                    gamma = gamma + A[k, p] * A[k, q]
                if wp.abs(gamma) > wp.float64(1.0e-15) * wp.sqrt(alpha * beta):
                    rotated = 1
                    zeta = (beta - alpha) / (_TWO * gamma)
                    t = _ONE / (wp.abs(zeta) + wp.sqrt(_ONE + zeta * zeta))
                    if zeta < _ZERO:
                        t = -t
                    c = _ONE / wp.sqrt(_ONE + t * t)
                    s = c * t
                    for k in range(4):
                        akp = A[k, p]
                        akq = A[k, q]
                        A[k, p] = c * akp - s * akq
                        A[k, q] = s * akp + c * akq
                        vkp = V[k, p]
                        vkq = V[k, q]
                        V[k, p] = c * vkp - s * vkq
                        V[k, q] = s * vkp + c * vkq
        if rotated == 0:
            break
    best = int(0)
    best_norm = wp.float64(wp.inf)
    for j in range(4):
        nj = A[0, j] * A[0, j] + A[1, j] * A[1, j] + A[2, j] * A[2, j] + A[3, j] * A[3, j]
        if nj < best_norm:
            best_norm = nj
            best = j
    return wp.vec4d(V[0, best], V[1, best], V[2, best], V[3, best])


@wp.func
def dlt_row(x: wp.float64, row_z: wp.vec4d, row_xy: wp.vec4d) -> wp.vec4d:
    return x * row_z - row_xy


@wp.func
def triangulate_dlt(xl: wp.vec2d, xr: wp.vec2d, R: wp.mat33d, t: wp.vec3d):
    """Homogeneous DLT on normalised coordinates; returns (X in mm, 1) or (anything, 0) at infinity."""
    s = wp.length(t)
    ts = t / s
    e0 = wp.vec4d(_ONE, _ZERO, _ZERO, _ZERO)
    e1 = wp.vec4d(_ZERO, _ONE, _ZERO, _ZERO)
    e2 = wp.vec4d(_ZERO, _ZERO, _ONE, _ZERO)
    p0 = wp.vec4d(R[0, 0], R[0, 1], R[0, 2], ts[0])
    p1 = wp.vec4d(R[1, 0], R[1, 1], R[1, 2], ts[1])
    p2 = wp.vec4d(R[2, 0], R[2, 1], R[2, 2], ts[2])
    a0 = dlt_row(xl[0], e2, e0)
    a1 = dlt_row(xl[1], e2, e1)
    a2 = dlt_row(xr[0], p2, p0)
    a3 = dlt_row(xr[1], p2, p1)
    A = wp.mat44d(a0[0], a0[1], a0[2], a0[3], a1[0], a1[1], a1[2], a1[3],
                  a2[0], a2[1], a2[2], a2[3], a3[0], a3[1], a3[2], a3[3])
    v = smallest_right_singular_vector4(A)
    X = wp.vec3d(v[0], v[1], v[2])
    if wp.abs(v[3]) <= wp.float64(1.0e-12) * wp.length(X):
        return X, 0
    return X * (s / v[3]), 1


@wp.func
def reprojection_cost(X: wp.vec3d, uvl: wp.vec2d, uvr: wp.vec2d, left: CameraModel, right: CameraModel,
                      R: wp.mat33d, t: wp.vec3d) -> wp.float64:
    """|e_left|^2 + |e_right|^2 in px^2; +inf when X is not in front of both cameras."""
    Xr = R @ X + t
    if not (X[2] > _ZERO and Xr[2] > _ZERO):
        return wp.float64(wp.inf)
    el = project_camera(X, left) - uvl
    er = project_camera(Xr, right) - uvr
    return wp.dot(el, el) + wp.dot(er, er)


@wp.func
def refine_optimal(X0: wp.vec3d, uvl: wp.vec2d, uvr: wp.vec2d, left: CameraModel, right: CameraModel,
                   R: wp.mat33d, t: wp.vec3d, tol_px: wp.float64, max_iter: int):
    """Gauss-Newton with step halving on the 3-D point; returns (X, 1 if converged else 0)."""
    X = X0
    converged = int(0)
    for _it in range(max_iter):
        Xr = R @ X + t
        el = project_camera(X, left) - uvl
        er = project_camera(Xr, right) - uvr
        Jl = project_camera_jacobian(X, left)
        Jr = project_camera_jacobian(Xr, right) @ R
        H = wp.transpose(Jl) @ Jl + wp.transpose(Jr) @ Jr
        g = wp.transpose(Jl) @ el + wp.transpose(Jr) @ er
        if not (wp.determinant(H) > _ZERO):
            break
        d = -(wp.inverse(H) @ g)
        step_px = wp.max(wp.length(Jl @ d), wp.length(Jr @ d))
        if step_px < tol_px:
            converged = 1
            break
        if step_px < _FULL_STEP_PX:
            # near the optimum the cost change (~step_px^2) falls below the rounding of the
            # cost itself, so a line search would reject correct steps: take the full step
            X = X + d
            continue
        cost = wp.dot(el, el) + wp.dot(er, er)
        alpha = _ONE
        accepted = int(0)
        cand = X
        for _ls in range(30):
            cand = X + alpha * d
            if reprojection_cost(cand, uvl, uvr, left, right, R, t) < cost:
                accepted = 1
                break
            alpha = alpha * _HALF
        if accepted == 0:
            break
        X = cand
    return X, converged


@wp.func
def vec2_finite(v: wp.vec2d) -> bool:
    return wp.isfinite(v[0]) and wp.isfinite(v[1])


@wp.kernel
def triangulate_kernel(
    left: CameraModel, right: CameraModel, R: wp.mat33d, t: wp.vec3d,
    points_left: wp.array(dtype=wp.vec2d), points_right: wp.array(dtype=wp.vec2d),
    optimal: int, tol_px: wp.float64, max_iter: int, min_parallax_sine: wp.float64, margin_px: wp.float64,
    offset: int,
    out_points: wp.array(dtype=wp.vec3d), out_residual: wp.array(dtype=wp.float64), out_status: wp.array(dtype=wp.int32),
):
    i = wp.tid() + offset
    uvl = points_left[i]
    uvr = points_right[i]
    nan = wp.float64(wp.nan)
    out_points[i] = wp.vec3d(nan, nan, nan)
    out_residual[i] = nan
    if not (vec2_finite(uvl) and vec2_finite(uvr)):
        out_status[i] = _INVALID_INPUT
        return
    xl, okl = undistort_newton(uvl, left, tol_px, _UNDISTORT_MAX_ITER)
    xr, okr = undistort_newton(uvr, right, tol_px, _UNDISTORT_MAX_ITER)
    if okl == 0 or okr == 0:
        out_status[i] = _UNDISTORT_FAILED
        return
    X, ok = triangulate_dlt(xl, xr, R, t)
    if ok == 0 or ray_parallax_sine(xl, xr, R) < min_parallax_sine:
        out_status[i] = _DEGENERATE
        return
    cost = reprojection_cost(X, uvl, uvr, left, right, R, t)
    out_points[i] = X
    if not wp.isfinite(cost):
        out_status[i] = _BEHIND_CAMERA
        return
    status = _OK
    if optimal != 0:
        X, converged = refine_optimal(X, uvl, uvr, left, right, R, t, tol_px, max_iter)
        cost = reprojection_cost(X, uvl, uvr, left, right, R, t)
        if converged == 0:
            status = _NOT_CONVERGED
    out_points[i] = X
    out_residual[i] = wp.sqrt(cost * _HALF)
    if status == _OK and not (in_image(uvl, left, margin_px) and in_image(uvr, right, margin_px)):
        status = _OUT_OF_IMAGE
    out_status[i] = status


@wp.func
def _gradient_change(X: wp.vec3d, e: wp.vec3d, el: wp.vec2d, er: wp.vec2d, left: CameraModel, right: CameraModel,
                     R: wp.mat33d, t: wp.vec3d) -> wp.vec3d:
    """Central difference along ``e`` (mm) of ``Jl(X)^T el + Jr(X)^T er`` with the residuals held fixed."""
    Jl_p = project_camera_jacobian(X + e, left)
    Jl_m = project_camera_jacobian(X - e, left)
    Jr_p = project_camera_jacobian(R @ (X + e) + t, right) @ R
    Jr_m = project_camera_jacobian(R @ (X - e) + t, right) @ R
    g_p = wp.transpose(Jl_p) @ el + wp.transpose(Jr_p) @ er
    g_m = wp.transpose(Jl_m) @ el + wp.transpose(Jr_m) @ er
    return (g_p - g_m) / (_TWO * wp.length(e))


@wp.kernel
def optimal_jacobian_kernel(
    left: CameraModel, right: CameraModel, R: wp.mat33d, t: wp.vec3d,
    points_left: wp.array(dtype=wp.vec2d), points_right: wp.array(dtype=wp.vec2d), points: wp.array(dtype=wp.vec3d),
    offset: int,
    out_left: wp.array(dtype=mat32d), out_right: wp.array(dtype=mat32d),
):
    """d(X)/d(pixel) of the optimal (least reprojection error) point ``X`` of each pair, by the implicit
    function theorem on its stationarity condition (see :func:`optimal_triangulation_jacobian`)."""
    i = wp.tid() + offset
    uvl = points_left[i]
    uvr = points_right[i]
    X = points[i]
    nan = wp.float64(wp.nan)
    out_left[i] = mat32d(nan, nan, nan, nan, nan, nan)
    out_right[i] = mat32d(nan, nan, nan, nan, nan, nan)
    if not (vec2_finite(uvl) and vec2_finite(uvr) and wp.isfinite(X[0]) and wp.isfinite(X[1]) and wp.isfinite(X[2])):
        return
    Xr = R @ X + t
    if not (X[2] > _ZERO and Xr[2] > _ZERO):
        return
    el = project_camera(X, left) - uvl
    er = project_camera(Xr, right) - uvr
    Jl = project_camera_jacobian(X, left)
    Jr = project_camera_jacobian(Xr, right) @ R
    # d(gradient)/dX = Jl^T Jl + Jr^T Jr + sum_k e_k d^2(pixel_k)/dX^2; the last (residual) term by central
    # differences of the analytic projection Jacobian, step 1e-4 |X|
    h = _JACOBIAN_STEP * wp.length(X)
    c0 = _gradient_change(X, wp.vec3d(h, _ZERO, _ZERO), el, er, left, right, R, t)
    c1 = _gradient_change(X, wp.vec3d(_ZERO, h, _ZERO), el, er, left, right, R, t)
    c2 = _gradient_change(X, wp.vec3d(_ZERO, _ZERO, h), el, er, left, right, R, t)
    H = wp.transpose(Jl) @ Jl + wp.transpose(Jr) @ Jr + wp.matrix_from_cols(c0, c1, c2)
    if not (wp.abs(wp.determinant(H)) > _ZERO):
        return
    Hinv = wp.inverse(H)
    out_left[i] = Hinv @ wp.transpose(Jl)
    out_right[i] = Hinv @ wp.transpose(Jr)


@wp.kernel
def undistort_kernel(
    cam: CameraModel, points: wp.array(dtype=wp.vec2d), tol_px: wp.float64, max_iter: int, margin_px: wp.float64,
    offset: int, out_points: wp.array(dtype=wp.vec2d), out_status: wp.array(dtype=wp.int32),
):
    i = wp.tid() + offset
    uv = points[i]
    nan = wp.float64(wp.nan)
    out_points[i] = wp.vec2d(nan, nan)
    if not vec2_finite(uv):
        out_status[i] = _INVALID_INPUT
        return
    xy, ok = undistort_newton(uv, cam, tol_px, max_iter)
    if ok == 0:
        out_status[i] = _UNDISTORT_FAILED
        return
    out_points[i] = normalized_to_pixel(xy, cam)
    if in_image(uv, cam, margin_px):
        out_status[i] = _OK
    else:
        out_status[i] = _OUT_OF_IMAGE


@wp.kernel
def project_kernel(
    cam: CameraModel, R: wp.mat33d, t: wp.vec3d, points: wp.array(dtype=wp.vec3d), margin_px: wp.float64,
    offset: int, out_pixels: wp.array(dtype=wp.vec2d), out_jacobian: wp.array(dtype=mat23d),
    out_status: wp.array(dtype=wp.int32),
):
    i = wp.tid() + offset
    X = R @ points[i] + t
    nan = wp.float64(wp.nan)
    out_pixels[i] = wp.vec2d(nan, nan)
    out_jacobian[i] = mat23d(nan, nan, nan, nan, nan, nan)
    if not (wp.isfinite(X[0]) and wp.isfinite(X[1]) and wp.isfinite(X[2])):
        out_status[i] = _INVALID_INPUT
        return
    if not (X[2] > _ZERO):
        out_status[i] = _BEHIND_CAMERA
        return
    uv = project_camera(X, cam)
    out_pixels[i] = uv
    out_jacobian[i] = project_camera_jacobian(X, cam) @ R
    if in_image(uv, cam, margin_px):
        out_status[i] = _OK
    else:
        out_status[i] = _OUT_OF_IMAGE


# ---------------------------------------------------------------------------------------------
# launchers
# ---------------------------------------------------------------------------------------------
METHODS = ("linear", "optimal")


def _finite_array(value, shape, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array of shape {shape}, got {value!r}") from exc
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


def camera_model(K, dist=None, image_size=None, name: str = "camera") -> CameraModel:
    """Validate intrinsics and pack them into a :class:`CameraModel` struct.

    Parameters
    ----------
    K : (3, 3) array, px
        ``[[fx, skew, cx], [0, fy, cy], [0, 0, 1]]`` with fx, fy > 0.
    dist : (0|4|5|8,) array or None
        OpenCV coefficients ``k1 k2 p1 p2 [k3 [k4 k5 k6]]``.
    image_size : (width, height) in px, or None / (0, 0) for unknown (no out-of-image check).
    """
    K = _finite_array(K, (3, 3), f"{name} K")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"{name} K must have positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise ValueError(f"{name} K must be upper triangular with last row [0, 0, 1], got\n{K}")
    d8 = distortion_coefficients(dist, f"{name} dist")
    if image_size is None:
        width = height = 0.0
    else:
        size = np.asarray(image_size, dtype=np.float64).ravel()
        if size.shape != (2,) or not np.all(np.isfinite(size)) or np.any(size < 0):
            raise ValueError(f"{name} image_size must be (width, height) in pixels, got {image_size!r}")
        width, height = float(size[0]), float(size[1])
    cam = CameraModel()
    cam.fx, cam.fy, cam.cx, cam.cy, cam.skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    cam.dist = vec8d(*(float(c) for c in d8))
    cam.width, cam.height = width, height
    return cam


def _rotation(R, name: str) -> np.ndarray:
    R = _finite_array(R, (3, 3), name)
    err = np.max(np.abs(R.T @ R - np.eye(3)))
    if err > 1e-6 or np.linalg.det(R) <= 0:
        raise ValueError(
            f"{name} must be a rotation matrix (orthonormal, det +1); |R^T R - I| = {err:.3g}, det = {np.linalg.det(R):.6g}"
        )
    return R


def _points(points, ncols: int, name: str, device: str) -> wp.array:
    """(N, ncols) float64 device array of vec2d/vec3d; NaNs allowed (flagged per point)."""
    vec = wp.vec2d if ncols == 2 else wp.vec3d
    if isinstance(points, wp.array):
        if points.dtype == vec and points.ndim == 1:
            if str(points.device) != device:
                raise ValueError(f"{name} is on device {points.device}, expected {device}")
            return points
        points = points.numpy()
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric (N, {ncols}) array, got {type(points).__name__}") from exc
    if arr.ndim != 2 or arr.shape[1] != ncols:
        raise ValueError(f"{name} must have shape (N, {ncols}), got {arr.shape}")
    return wp.array(np.ascontiguousarray(arr), dtype=vec, device=device)


def _check_out(out, expected: list, device: str):
    if out is None:
        return [wp.empty(n, dtype=dt, device=device) for n, dt in expected]
    out = list(out)
    if len(out) != len(expected):
        raise ValueError(f"out must hold {len(expected)} arrays, got {len(out)}")
    for k, (arr, (n, dt)) in enumerate(zip(out, expected)):
        if not isinstance(arr, wp.array) or arr.dtype != dt or arr.shape != (n,) or str(arr.device) != device:
            raise ValueError(
                f"out[{k}] must be a warp array of shape ({n},), dtype {wp.types.type_repr(dt)} on {device}, got "
                f"{getattr(arr, 'shape', None)}, {getattr(arr, 'dtype', type(arr).__name__)} on {getattr(arr, 'device', None)}"
            )
    return out


def _load(device: str) -> None:
    """Compile/load this module once before a chunked launch (pool threads would each compile it)."""
    wp.load_module(sys.modules[__name__], device=device)


def _margin(value) -> float:
    v = float(value)
    if not (v >= 0):  # +inf allowed: disables the out-of-image flag
        raise ValueError(f"margin_px must be >= 0 (or inf to disable the check), got {value!r}")
    return v


def undistort_points(points, K, dist=None, *, image_size=None, margin_px: float = 0.0, tol_px: float = 1e-9,
                     max_iter: int = UNDISTORT_MAX_ITER, device=None, out=None):
    """Undistort image points: distorted pixels -> ideal pixels (same K), per-point status.

    Parameters
    ----------
    points : (N, 2) array-like (float64 after conversion) or warp array of vec2d, px
        Observed (distorted) pixel coordinates ``(x, y)``; NaN/inf rows get ``INVALID_INPUT``.
    K, dist, image_size : see :func:`camera_model`.
    margin_px : float
        Points farther than this outside the pixel area ``[-0.5, W - 0.5] x [-0.5, H - 0.5]`` get
        ``OUT_OF_IMAGE`` (still computed). ``inf`` disables the check.
    tol_px : float
        Convergence tolerance: the distortion model applied to the result reproduces the input
        within ``tol_px`` pixels.
    max_iter : int
        Newton iterations before ``UNDISTORT_FAILED``.

    Returns
    -------
    (ideal_pixels, status) : warp arrays ``(N,) vec2d`` (px; NaN where status is
        ``UNDISTORT_FAILED`` or ``INVALID_INPUT``) and ``(N,) int32`` :class:`TriangulationStatus`.
    """
    device = resolve_device(device)
    cam = camera_model(K, dist, image_size)
    pts = _points(points, 2, "points", device)
    tol_px, max_iter, margin_px = positive_float(tol_px, "tol_px"), positive_int(max_iter, "max_iter", integral_float=True), _margin(margin_px)
    n = pts.shape[0]
    out_points, out_status = _check_out(out, [(n, wp.vec2d), (n, wp.int32)], device)
    _load(device)
    launch_1d(undistort_kernel, n, [cam, pts, tol_px, max_iter, margin_px, 0, out_points, out_status], device, 5)
    return out_points, out_status


def project_points(points, K, dist=None, *, R=None, t=None, image_size=None, margin_px: float = 0.0,
                   device=None, out=None):
    """Project 3-D points through ``x_cam = R @ X + t`` and the lens model to distorted pixels.

    Parameters
    ----------
    points : (N, 3) array-like or warp array of vec3d, mm
    K, dist, image_size : see :func:`camera_model`.
    R, t : (3, 3), (3,) or None (identity / zero): the pose ``R_cam_frame, t_cam_frame`` (mm).

    Returns
    -------
    (pixels, jacobian, status) : warp arrays ``(N,) vec2d`` px, ``(N,) mat23d`` d(pixel)/d(X)
        in px/mm, ``(N,) int32`` :class:`TriangulationStatus` (``BEHIND_CAMERA`` when z <= 0,
        ``OUT_OF_IMAGE`` when the projection falls outside the image plus ``margin_px``).
    """
    device = resolve_device(device)
    cam = camera_model(K, dist, image_size)
    R = np.eye(3) if R is None else _rotation(R, "R")
    t = np.zeros(3) if t is None else _finite_array(t, (3,), "t")
    pts = _points(points, 3, "points", device)
    margin_px = _margin(margin_px)
    n = pts.shape[0]
    out_px, out_jac, out_status = _check_out(out, [(n, wp.vec2d), (n, mat23d), (n, wp.int32)], device)
    _load(device)
    launch_1d(project_kernel, n, [cam, wp.mat33d(R), wp.vec3d(t), pts, margin_px, 0, out_px, out_jac, out_status],
              device, 5)
    return out_px, out_jac, out_status


def triangulate_points(points_left, points_right, *, K_left, dist_left, K_right, dist_right, R_right_left,
                       t_right_left, image_size_left=None, image_size_right=None, method: str = "optimal",
                       tol_px: float = 1e-9, max_iter: int = 20, min_parallax: float = 1e-6,
                       margin_px: float = 0.0, device=None, out=None):
    """Triangulate matched distorted pixels into the left camera frame.

    Parameters
    ----------
    points_left, points_right : (N, 2) array-like or warp arrays of vec2d, px
        Matched observed pixels; NaN rows get ``INVALID_INPUT``.
    K_left, dist_left, K_right, dist_right, image_size_left, image_size_right :
        Intrinsics, see :func:`camera_model`.
    R_right_left, t_right_left : (3, 3), (3,) mm
        Right camera pose in the left frame, ``x_right = R_right_left @ x_left + t_right_left``.
    method : "optimal" or "linear"
        ``linear``: homogeneous DLT on undistorted normalised points; ``optimal``: Gauss-Newton
        refinement of the DLT point minimising the reprojection error in both images (see the
        module docstring).
    tol_px : float
        Convergence tolerance (px) of the undistortion and of the optimal refinement step.
    max_iter : int
        Gauss-Newton iterations of the optimal refinement before ``NOT_CONVERGED``.
    min_parallax : float, rad
        Rays closer to parallel than this angle are ``DEGENERATE``.
    margin_px : float
        Out-of-image tolerance for the ``OUT_OF_IMAGE`` flag (``inf`` disables it).

    Returns
    -------
    (points, residual, status) : warp arrays ``(N,) vec3d`` mm in the left camera frame,
        ``(N,) float64`` RMS reprojection residual px, ``(N,) int32`` :class:`TriangulationStatus`.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    device = resolve_device(device)
    left = camera_model(K_left, dist_left, image_size_left, "left camera")
    right = camera_model(K_right, dist_right, image_size_right, "right camera")
    R = _rotation(R_right_left, "R_right_left")
    t = _finite_array(t_right_left, (3,), "t_right_left")
    if not np.linalg.norm(t) > 0:
        raise ValueError("t_right_left is zero: the two cameras share a centre and cannot triangulate")
    pl = _points(points_left, 2, "points_left", device)
    pr = _points(points_right, 2, "points_right", device)
    if pl.shape[0] != pr.shape[0]:
        raise ValueError(
            f"points_left and points_right must hold the same number of points, got {pl.shape[0]} and {pr.shape[0]}"
        )
    tol_px, max_iter, margin_px = positive_float(tol_px, "tol_px"), positive_int(max_iter, "max_iter", integral_float=True), _margin(margin_px)
    min_parallax = float(min_parallax)
    if not (0 <= min_parallax < np.pi / 2):
        raise ValueError(f"min_parallax must be an angle in [0, pi/2) rad, got {min_parallax!r}")
    n = pl.shape[0]
    out_points, out_res, out_status = _check_out(out, [(n, wp.vec3d), (n, wp.float64), (n, wp.int32)], device)
    inputs = [left, right, wp.mat33d(R), wp.vec3d(t), pl, pr, int(method == "optimal"), tol_px, max_iter,
              float(np.sin(min_parallax)), margin_px, 0, out_points, out_res, out_status]
    _load(device)
    launch_1d(triangulate_kernel, n, inputs, device, 11)
    return out_points, out_res, out_status


def optimal_triangulation_jacobian(points_left, points_right, points, *, K_left, dist_left, K_right, dist_right,
                                   R_right_left, t_right_left, device=None) -> np.ndarray:
    """(N, 3, 4) derivatives of optimal-triangulated points by ``(x_left, y_left, x_right, y_right)`` (mm/px).

    ``points`` (N, 3) mm (left camera frame) are the optimal triangulation (:func:`triangulate_points`,
    ``method="optimal"``) of the distorted pixels ``points_left``, ``points_right`` (N, 2). At that point the
    gradient of the reprojection cost ``g(X, u) = Jl^T e_l + Jr^T e_r`` vanishes (``e`` the residuals, ``J``
    the projection Jacobians, distortion included), so by the implicit function theorem
    ``dX/du = (Jl^T Jl + Jr^T Jr + sum_k e_k d^2 pixel_k/dX^2)^-1 [Jl^T | Jr^T]``. The residual term uses
    central differences of the analytic projection Jacobian (step 1e-4 |X|); the rest is analytic. One
    thread per point, float64. Exact for a converged point (the triangulation's ``tol_px`` of 1e-9 px); it
    replaces 8 perturbed triangulations (central differences of the whole solve), with which it agrees to
    about 1e-7 relative (tests/kernels/test_triangulate.py). Rows with a non-finite input, a point behind a
    camera or a singular system are NaN.
    """
    device = resolve_device(device)
    left = camera_model(K_left, dist_left, None, "left camera")
    right = camera_model(K_right, dist_right, None, "right camera")
    R = _rotation(R_right_left, "R_right_left")
    t = _finite_array(t_right_left, (3,), "t_right_left")
    pl = _points(points_left, 2, "points_left", device)
    pr = _points(points_right, 2, "points_right", device)
    X = _points(points, 3, "points", device)
    n = pl.shape[0]
    if pr.shape[0] != n or X.shape[0] != n:
        raise ValueError(f"points_left, points_right and points must hold the same number of points, got "
                         f"{n}, {pr.shape[0]} and {X.shape[0]}")
    out_left = wp.empty(n, dtype=mat32d, device=device)
    out_right = wp.empty(n, dtype=mat32d, device=device)
    _load(device)
    launch_1d(optimal_jacobian_kernel, n, [left, right, wp.mat33d(R), wp.vec3d(t), pl, pr, X, 0, out_left, out_right],
              device, 7)
    jac = np.empty((n, 3, 4))
    jac[:, :, :2] = out_left.numpy().reshape(n, 3, 2)
    jac[:, :, 2:] = out_right.numpy().reshape(n, 3, 2)
    return jac
