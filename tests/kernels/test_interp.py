"""Cubic B-spline and Keys interpolation kernels against independent references.

References: scipy.ndimage.map_coordinates(order=3, mode="mirror") (float64) for the B-spline, a
plain NumPy Keys (a = -0.5) implementation, and finite differences for the gradients.
"""
import numpy as np
import pytest
from scipy import ndimage

from kernels.interp import PAD, bspline_coefficients, expand_rows4, interpolate, padded_samples


def speckle_like(shape, seed=0):
    """0-255 grey levels with speckle-like texture: blurred random disks-ish noise, quantised."""
    rng = np.random.default_rng(seed)
    img = ndimage.gaussian_filter(rng.uniform(0.0, 1.0, shape), 1.2)
    img = (img - img.mean()) / img.std()
    return np.clip(np.round(128 + 60 * img), 0, 255)


def sample_points(shape, n, rng):
    """Random points in the valid domain plus points exactly on the four borders and corners."""
    h, w = shape
    pts = np.c_[rng.uniform(0, w - 1, n), rng.uniform(0, h - 1, n)]
    border = np.array([[0, 0], [w - 1, h - 1], [0, h - 1], [w - 1, 0]], float)
    edges = np.c_[rng.uniform(0, w - 1, 8), np.zeros(8)]
    edges2 = np.c_[np.full(8, w - 1.0), rng.uniform(0, h - 1, 8)]
    return np.vstack([pts, border, edges, edges2])


def keys_numpy(img, pts):
    """Keys cubic convolution (a = -0.5), mirror boundary (numpy 'reflect'), value and gradient."""
    a = -0.5

    def w(d):
        d = np.abs(d)
        return np.where(d <= 1, (a + 2) * d**3 - (a + 3) * d**2 + 1,
                        np.where(d < 2, a * d**3 - 5 * a * d**2 + 8 * a * d - 4 * a, 0.0))

    def dw(d):
        s = np.sign(d)
        d = np.abs(d)
        return s * np.where(d <= 1, 3 * (a + 2) * d**2 - 2 * (a + 3) * d,
                            np.where(d < 2, 3 * a * d**2 - 10 * a * d + 8 * a, 0.0))

    padded = np.pad(img.astype(np.float64), 2, mode="reflect")
    out = np.zeros((len(pts), 3))
    for n, (x, y) in enumerate(pts):
        ix, iy = int(np.floor(x)), int(np.floor(y))
        for k in range(-1, 3):
            for m in range(-1, 3):
                c = padded[iy + k + 2, ix + m + 2]
                dx, dy = x - (ix + m), y - (iy + k)
                out[n, 0] += c * w(dx) * w(dy)
                out[n, 1] += c * dw(dx) * w(dy)
                out[n, 2] += c * w(dx) * dw(dy)
    return out


@pytest.mark.parametrize("shape", [(64, 80), (7, 5), (4, 4)])
def test_bspline_matches_scipy_mirror(device, rng, shape):
    img = speckle_like(shape)
    pts = sample_points(shape, 3000, rng)
    ref = ndimage.map_coordinates(img, [pts[:, 1], pts[:, 0]], order=3, mode="mirror")
    got = interpolate(img, pts, method="bspline", device=device)
    # float32 prefilter and evaluation of 0-255 data: rounding ~1e-5 relative; the bound is 1e-3
    assert np.max(np.abs(got - ref)) < 1e-3


def test_bspline_reproduces_pixels(device):
    img = speckle_like((40, 52), seed=3)
    yy, xx = np.mgrid[0:40, 0:52]
    got = interpolate(img, np.c_[xx.ravel(), yy.ravel()], device=device).reshape(img.shape)
    # an interpolating spline passes through the samples; float32 rounding only
    assert np.max(np.abs(got - img)) < 1e-3


def test_bspline_gradient_matches_finite_differences(device, rng):
    img = speckle_like((48, 56), seed=1)
    pts = sample_points(img.shape, 500, rng)
    pts = np.clip(pts, 1e-3, None)
    pts[:, 0] = np.minimum(pts[:, 0], 56 - 1 - 1e-3)
    pts[:, 1] = np.minimum(pts[:, 1], 48 - 1 - 1e-3)
    got = interpolate(img, pts, gradient=True, device=device)
    h = 1e-4  # float64 central differences of the scipy interpolant: truncation ~h^2 f''' ~ 1e-6
    f = lambda x, y: ndimage.map_coordinates(img, [y, x], order=3, mode="mirror")  # noqa: E731
    gx = (f(pts[:, 0] + h, pts[:, 1]) - f(pts[:, 0] - h, pts[:, 1])) / (2 * h)
    gy = (f(pts[:, 0], pts[:, 1] + h) - f(pts[:, 0], pts[:, 1] - h)) / (2 * h)
    # gradients reach ~100 grey/px; float32 sums of ~16 terms of size ~300 round at ~1e-4..1e-3
    assert np.max(np.abs(got[:, 1] - gx)) < 2e-3
    assert np.max(np.abs(got[:, 2] - gy)) < 2e-3
    assert np.max(np.abs(got[:, 0] - f(pts[:, 0], pts[:, 1]))) < 1e-3


def test_keys_matches_numpy(device, rng):
    img = speckle_like((30, 34), seed=2)
    pts = sample_points(img.shape, 300, rng)
    ref = keys_numpy(img, pts)
    got = interpolate(img, pts, method="keys", gradient=True, device=device)
    # same formula in float32 vs float64: rounding of 16-term sums of 0-255 values
    assert np.max(np.abs(got - ref)) < 1e-3
    val = interpolate(padded_samples(img, device=device), pts, method="keys", device=device)
    assert np.max(np.abs(val - ref[:, 0])) < 1e-3


def test_outside_domain_is_nan(device):
    img = speckle_like((20, 24))
    pts = np.array([[-0.01, 5.0], [23.01, 5.0], [5.0, -1.0], [5.0, 19.5], [5.0, 5.0], [23.0, 19.0]])
    for method in ("bspline", "keys"):
        got = interpolate(img, pts, method=method, gradient=True, device=device)
        assert np.all(np.isnan(got[:4])), method
        assert np.all(np.isfinite(got[4:])), method


def test_rows4_layout(device):
    img = speckle_like((10, 12))
    coef = bspline_coefficients(img, device=device)
    rows4 = expand_rows4(coef).numpy()
    flat = coef.flat.numpy()
    pitch = coef.pitch
    k = 3 * pitch + 5
    assert coef.data.shape == (10 + 2 * PAD, 12 + 2 * PAD)
    np.testing.assert_array_equal(rows4[k], flat[k - 1:k + 3])


def test_sub_pixel_positions_far_from_origin(device):
    # float64 points are split into integer + fraction, so precision does not degrade at x ~ 1000
    img = speckle_like((8, 1200), seed=4)
    pts = np.array([[1100.123456, 3.3], [1100.123466, 3.3]])
    got = interpolate(img, pts, gradient=True, device=device)
    ref = ndimage.map_coordinates(img, [pts[:, 1], pts[:, 0]], order=3, mode="mirror")
    assert np.max(np.abs(got[:, 0] - ref)) < 1e-3


def test_bad_input(device):
    img = speckle_like((16, 16))
    with pytest.raises(ValueError, match="colour"):
        interpolate(np.zeros((16, 16, 3)), [[1, 1]], device=device)
    bad = img.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        interpolate(bad, [[1, 1]], device=device)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        interpolate(img, [1.0, 2.0, 3.0], device=device)
    with pytest.raises(ValueError, match="method"):
        interpolate(img, [[1, 1]], method="linear", device=device)
    with pytest.raises(ValueError, match="at least 4x4"):
        bspline_coefficients(np.zeros((3, 10)), device=device)
    with pytest.raises(ValueError, match="kind"):
        interpolate(bspline_coefficients(img, device=device), [[1, 1]], method="keys", device=device)
