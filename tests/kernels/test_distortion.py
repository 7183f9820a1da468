"""The kernels' one lens-distortion model (kernels/distortion.py) against OpenCV.

Reference: ``cv2.projectPoints`` with ``K = I`` (it then returns the distorted normalised
coordinates) on random points with all eight coefficients ``k1 k2 p1 p2 k3 k4 k5 k6`` non-zero;
the Jacobian against central finite differences of the float64 model; the Newton step against
the distorted ideal points.
"""
import cv2
import numpy as np
import pytest
import warp as wp

from kernels.distortion import (
    distort_normalized,
    distort_normalized_jacobian,
    distortion_coefficients,
    undistort_step,
    vec8d,
    vec8f,
)

#: rational model with every coefficient non-zero (a wide-angle lens: ~10 % distortion at r = 0.6)
DIST8 = np.array([-0.28, 0.11, 1.2e-3, -8.0e-4, -0.03, 0.05, -0.02, 0.004])


@wp.kernel
def _distort64(xy: wp.array(dtype=wp.vec2d), dist: vec8d, out: wp.array(dtype=wp.vec2d),
               jac: wp.array(dtype=wp.mat22d)):
    i = wp.tid()
    out[i] = distort_normalized(xy[i], dist)
    value, J = distort_normalized_jacobian(xy[i], dist)
    jac[i] = J


@wp.kernel
def _distort32(xy: wp.array(dtype=wp.vec2), dist: vec8f, out: wp.array(dtype=wp.vec2)):
    i = wp.tid()
    out[i] = distort_normalized(xy[i], dist)


@wp.kernel
def _undistort32(target: wp.array(dtype=wp.vec2), dist: vec8f, steps: int, out: wp.array(dtype=wp.vec2)):
    i = wp.tid()
    p = target[i]
    for _ in range(steps):
        p = undistort_step(p, target[i], dist)
    out[i] = p


def _points(rng, n=2000, r_max=0.6):
    r = r_max * np.sqrt(rng.uniform(0, 1, n))
    a = rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([r * np.cos(a), r * np.sin(a)])


def _opencv(xy, dist):
    pts = np.column_stack([xy, np.ones(len(xy))]).reshape(-1, 1, 3)
    out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), dist)
    return out.reshape(-1, 2)


def _run64(xy, dist, device):
    pts = wp.array(xy, dtype=wp.vec2d, device=device)
    out = wp.zeros(len(xy), dtype=wp.vec2d, device=device)
    jac = wp.zeros(len(xy), dtype=wp.mat22d, device=device)
    wp.launch(_distort64, len(xy), [pts, vec8d(*dist), out, jac], device=device)
    return out.numpy(), jac.numpy()


def test_float64_matches_cv2_projectpoints(device, rng):
    xy = _points(rng)
    ours, _ = _run64(xy, DIST8, device)
    ref = _opencv(xy, DIST8)
    assert np.max(np.abs(ours - ref)) < 1e-13, np.max(np.abs(ours - ref))


@pytest.mark.parametrize("n_coef", [4, 5])
def test_shorter_coefficient_sets_match_cv2(device, rng, n_coef):
    xy = _points(rng, 500)
    ours, _ = _run64(xy, distortion_coefficients(DIST8[:n_coef]), device)
    np.testing.assert_allclose(ours, _opencv(xy, DIST8[:n_coef]), rtol=0, atol=1e-13)


def test_float32_matches_cv2_projectpoints(device, rng):
    xy = _points(rng)
    pts = wp.array(xy.astype(np.float32), dtype=wp.vec2, device=device)
    out = wp.zeros(len(xy), dtype=wp.vec2, device=device)
    wp.launch(_distort32, len(xy), [pts, vec8f(*DIST8), out], device=device)
    ref = _opencv(xy.astype(np.float32).astype(np.float64), DIST8)
    # float32 rounding of ~20 operations on |x| < 0.7: a few 1e-7
    assert np.max(np.abs(out.numpy() - ref)) < 1e-6


def test_jacobian_matches_finite_differences(device, rng):
    xy = _points(rng, 500)
    _, jac = _run64(xy, DIST8, device)
    h = 1e-6
    for col, e in enumerate(np.eye(2)):
        fd = (_opencv(xy + h * e, DIST8) - _opencv(xy - h * e, DIST8)) / (2 * h)
        np.testing.assert_allclose(jac[:, :, col], fd, rtol=0, atol=1e-8)


def test_newton_steps_invert_the_model(device, rng):
    ideal = _points(rng, 1000, r_max=0.5)
    target = _opencv(ideal, DIST8).astype(np.float32)
    out = wp.zeros(len(ideal), dtype=wp.vec2, device=device)
    wp.launch(_undistort32, len(ideal), [wp.array(target, dtype=wp.vec2, device=device), vec8f(*DIST8), 12, out],
              device=device)
    assert np.max(np.abs(out.numpy() - ideal)) < 2e-6


def test_distortion_coefficients_pads_and_validates():
    np.testing.assert_array_equal(distortion_coefficients(None), np.zeros(8))
    np.testing.assert_array_equal(distortion_coefficients([0.1, 0.2, 0.3, 0.4]), [0.1, 0.2, 0.3, 0.4, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="thin-prism"):
        distortion_coefficients(np.zeros(12))
    with pytest.raises(ValueError, match="NaN"):
        distortion_coefficients([np.nan, 0, 0, 0])
    with pytest.raises(ValueError, match="numeric"):
        distortion_coefficients(["a", "b", "c", "d"])
