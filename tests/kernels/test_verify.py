"""kernels.verify.ComposedCheck: the ZNCC of a reference subset and a frame at a given warp, against a NumPy and
SciPy computation (scipy.ndimage.map_coordinates, cubic B-spline, mirror boundary), and its outcome codes."""
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from kernels.verify import CHECKED, FLAT, OUTSIDE, SKIPPED, ComposedCheck

SHAPE = (64, 72)
SUBSET = 11


def _zncc_numpy(ref, cur, point, params, subset):
    """The ZNCC written out: reference subset at whole pixels, current at the 2nd-order warp (scipy cubic spline)."""
    h = subset // 2
    cx, cy = int(np.floor(point[0] + 0.5)), int(np.floor(point[1] + 0.5))
    dy, dx = np.mgrid[-h:h + 1, -h:h + 1].astype(np.float64)
    u, ux, uy, uxx, uxy, uyy, v, vx, vy, vxx, vxy, vyy = params
    x = cx + dx + u + ux * dx + uy * dy + 0.5 * uxx * dx ** 2 + uxy * dx * dy + 0.5 * uyy * dy ** 2
    y = cy + dy + v + vx * dx + vy * dy + 0.5 * vxx * dx ** 2 + vxy * dx * dy + 0.5 * vyy * dy ** 2
    f = ref[cy - h:cy + h + 1, cx - h:cx + h + 1].astype(np.float64).ravel()
    g = map_coordinates(cur.astype(np.float64), [y.ravel(), x.ravel()], order=3, mode="mirror")
    f, g = f - f.mean(), g - g.mean()
    return float(f @ g / np.sqrt((f @ f) * (g @ g)))


def test_zncc_matches_numpy_for_1st_and_2nd_order_warps(device):
    rng = np.random.default_rng(4)
    ref = rng.uniform(0, 255, SHAPE).astype(np.float32)
    cur = rng.uniform(0, 255, SHAPE).astype(np.float32)
    cur[10:50, 10:60] = ref[10:50, 10:60] * 0.7 + cur[10:50, 10:60] * 0.3  # correlated where the subsets are
    pts = np.array([[20.0, 20.0], [36.0, 30.0], [50.0, 40.0], [30.4, 25.6]])
    p2 = np.zeros((4, 12))
    p2[:, 0], p2[:, 6] = [0.3, -0.7, 1.25, 0.0], [0.5, 0.2, -0.4, 0.1]
    p2[:, 1], p2[:, 2], p2[:, 7], p2[:, 8] = 0.01, -0.02, 0.015, 0.005
    p2[:, 3], p2[:, 4], p2[:, 5] = 0.002, -0.001, 0.0015
    p2[:, 9], p2[:, 10], p2[:, 11] = -0.001, 0.002, 0.0005
    check = ComposedCheck(ref, pts, SUBSET, device=device)
    z2, out2 = check.zncc(cur, p2)
    assert np.all(out2 == CHECKED)
    expected2 = [_zncc_numpy(ref, cur, pts[i], p2[i], SUBSET) for i in range(4)]
    assert np.allclose(z2, expected2, atol=2e-5), (z2, expected2)
    p1 = p2[:, [0, 1, 2, 6, 7, 8]]
    z1, out1 = check.zncc(cur, p1)
    full = np.zeros_like(p2)
    full[:, [0, 1, 2, 6, 7, 8]] = p1
    expected1 = [_zncc_numpy(ref, cur, pts[i], full[i], SUBSET) for i in range(4)]
    assert np.all(out1 == CHECKED) and np.allclose(z1, expected1, atol=2e-5)
    assert len(set(np.round(expected1, 3))) == 4  # the points differ: the values are not one number


def test_outcomes_outside_flat_skipped(device):
    rng = np.random.default_rng(5)
    ref = rng.uniform(0, 255, SHAPE).astype(np.float32)
    ref[40:60, 40:60] = 100.0  # flat
    pts = np.array([[3.0, 30.0], [30.0, 30.0], [50.0, 50.0], [30.0, 30.0], [30.0, 30.0]])
    params = np.zeros((5, 6))
    params[3, 0] = 40.0  # the warped subset leaves the frame
    params[4, 0] = np.nan  # never checked
    check = ComposedCheck(ref, pts, SUBSET, device=device)
    z, out = check.zncc(ref, params, np.array([True, True, True, True, True]))
    assert list(out) == [OUTSIDE, CHECKED, FLAT, OUTSIDE, SKIPPED]
    assert z[1] == pytest.approx(1.0, abs=1e-6)  # the identity warp of the reference itself
    assert np.all(np.isnan(z[[0, 2, 3, 4]]))
    z, out = check.zncc(ref, np.zeros((5, 6)), np.array([False, True, False, False, False]))
    assert list(out) == [SKIPPED, CHECKED, SKIPPED, SKIPPED, SKIPPED]


def test_bad_inputs_are_refused():
    ref = np.zeros(SHAPE, np.float32)
    check = ComposedCheck(ref, [[30.0, 30.0]], SUBSET, device="cpu")
    with pytest.raises(ValueError, match=r"params must be \(1, 6\) or \(1, 12\)"):
        check.zncc(ref, np.zeros((2, 6)))
    with pytest.raises(ValueError, match="check must be a"):
        check.zncc(ref, np.zeros((1, 6)), np.array([1]))
    with pytest.raises(ValueError, match="frame has shape"):
        check.zncc(np.zeros((10, 10)), np.zeros((1, 6)))
    with pytest.raises(ValueError, match="subset must be an odd integer"):
        ComposedCheck(ref, [[30.0, 30.0]], 10, device="cpu")
