"""OpenCV's lens distortion model as generic Warp functions (float32 or float64), used by every kernel.

The model maps ideal normalised coordinates ``(x, y) = (X/Z, Y/Z)`` to distorted normalised
coordinates (OpenCV's ``projectPoints`` before ``K``; docs/conventions.md):

    r² = x² + y²
    radial = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
    x_d = x·radial + 2 p1 x y + p2 (r² + 2 x²)
    y_d = y·radial + p1 (r² + 2 y²) + 2 p2 x y

Coefficients are one 8-vector in OpenCV's order ``k1 k2 p1 p2 k3 k4 k5 k6`` (shorter sets padded
with zeros: :func:`distortion_coefficients`), :data:`vec8f` for float32 kernels (the virtual lab's
renderer) and :data:`vec8d` for float64 kernels (triangulation). OpenCV's thin-prism (s1-s4) and
tilted-sensor terms are not supported. The functions are generic (``Any``): the precision follows
the arguments, and the arithmetic is written once, so both precisions evaluate the same expression.

Inverting the model has no closed form; callers iterate Newton steps with
:func:`distort_normalized_jacobian` (``kernels.triangulate.undistort_newton``: damped, to a pixel
tolerance, float64) or :func:`undistort_step` (plain steps, float32 rendering).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

#: 8 OpenCV distortion coefficients ``k1 k2 p1 p2 k3 k4 k5 k6``, float32 and float64.
vec8f = wp.types.vector(length=8, dtype=wp.float32)
vec8d = wp.types.vector(length=8, dtype=wp.float64)

#: Number of coefficients the kernels hold (OpenCV's rational model).
N_COEFFICIENTS = 8


@wp.func
def radial_factor_terms(r2: Any, dist: Any):
    """Numerator and denominator of the radial factor at ``r2 = x² + y²`` (scalars).

    ``num = 1 + k1 r² + k2 r⁴ + k3 r⁶``, ``den = 1 + k4 r² + k5 r⁴ + k6 r⁶`` (Horner form).
    """
    one = type(r2)(1.0)
    num = one + r2 * (dist[0] + r2 * (dist[1] + r2 * dist[4]))
    den = one + r2 * (dist[5] + r2 * (dist[6] + r2 * dist[7]))
    return num, den


@wp.func
def distort_normalized(xy: Any, dist: Any):
    """OpenCV distortion: ideal normalised ``xy`` (vec2) -> distorted normalised coordinates (vec2).

    ``dist``: :data:`vec8f` / :data:`vec8d` ``k1 k2 p1 p2 k3 k4 k5 k6`` of the same precision as ``xy``.
    """
    x = xy[0]
    y = xy[1]
    r2 = x * x + y * y
    num, den = radial_factor_terms(r2, dist)
    radial = num / den
    two = type(x)(2.0)
    xd = x * radial + two * dist[2] * x * y + dist[3] * (r2 + two * x * x)
    yd = y * radial + dist[2] * (r2 + two * y * y) + two * dist[3] * x * y
    return type(xy)(xd, yd)


@wp.func
def distort_normalized_jacobian(xy: Any, dist: Any):
    """Distorted normalised coordinates (vec2, :func:`distort_normalized`) and the analytic Jacobian
    d(distorted)/d(ideal) (mat22, symmetric)."""
    two = type(xy[0])(2.0)
    three = type(xy[0])(3.0)
    six = type(xy[0])(6.0)
    x = xy[0]
    y = xy[1]
    r2 = x * x + y * y
    num, den = radial_factor_terms(r2, dist)
    dnum = dist[0] + r2 * (two * dist[1] + three * r2 * dist[4])  # d num / d r2
    dden = dist[5] + r2 * (two * dist[6] + three * r2 * dist[7])
    radial = num / den
    dradial = (dnum * den - num * dden) / (den * den)  # d radial / d r2
    dxx = radial + two * x * x * dradial + two * dist[2] * y + six * dist[3] * x
    dxy = two * x * y * dradial + two * dist[2] * x + two * dist[3] * y
    dyy = radial + two * y * y * dradial + six * dist[2] * y + two * dist[3] * x
    return distort_normalized(xy, dist), wp.matrix(dxx, dxy, dxy, dyy, shape=(2, 2))


@wp.func
def undistort_step(xy: Any, target: Any, dist: Any):
    """One plain Newton step of ``distort_normalized(xy) = target`` (vec2, normalised coordinates).

    No damping and no check of the Jacobian's determinant: for starts close to the solution, on the
    invertible side of the model's fold (rendering iterates it from the distorted position).
    """
    value, J = distort_normalized_jacobian(xy, dist)
    fx = value[0] - target[0]
    fy = value[1] - target[1]
    det = J[0, 0] * J[1, 1] - J[0, 1] * J[0, 1]
    return type(xy)(xy[0] - (J[1, 1] * fx - J[0, 1] * fy) / det, xy[1] - (-J[0, 1] * fx + J[0, 0] * fy) / det)


def distortion_coefficients(dist, name: str = "dist", sizes=(0, 4, 5, 8)) -> np.ndarray:
    """OpenCV coefficients padded to the 8 ``k1 k2 p1 p2 k3 k4 k5 k6`` (float64, shape (8,)).

    ``dist``: None (no distortion) or a 1-D array-like whose length is one of ``sizes``. Raises
    ValueError for another length or non-finite values.
    """
    try:
        d = np.zeros(0) if dist is None else np.asarray(dist, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numeric OpenCV coefficients (k1 k2 p1 p2 k3 k4 k5 k6), got {dist!r}") from exc
    if d.size not in sizes:
        raise ValueError(
            f"{name} must hold {', '.join(str(s) for s in sizes[:-1])} or {sizes[-1]} OpenCV coefficients "
            f"(k1 k2 p1 p2 k3 k4 k5 k6), got {d.size}; the thin-prism and tilted models (12 or 14) are not supported"
        )
    if not np.all(np.isfinite(d)):
        raise ValueError(f"{name} contains NaN or infinite values")
    out = np.zeros(N_COEFFICIENTS)
    out[: d.size] = d
    return out
