"""Independent references from kornia (the optional ``torch`` extra): its lens distortion, undistortion and
linear triangulation against Specula's Warp kernels (kernels/distortion.py, kernels/triangulate.py).

kornia implements OpenCV's model in PyTorch, written independently of our kernels and of OpenCV's C++;
agreement to float64 round-off checks the model, and agreement of the DLT with ours checks the linear
triangulation. Skipped when torch or kornia is not installed.
"""
import numpy as np
import pytest

torch = pytest.importorskip("torch")
kornia_calibration = pytest.importorskip("kornia.geometry.calibration")
kornia_epipolar = pytest.importorskip("kornia.geometry.epipolar")

from kernels.triangulate import project_points, triangulate_points, undistort_points  # noqa: E402

K = np.array([[1650.0, 0.0, 1176.3], [0.0, 1651.5, 861.2], [0.0, 0.0, 1.0]])
#: k1, k2, p1, p2, k3, k4, k5, k6 (OpenCV's rational model), all non-zero
DIST8 = np.array([-0.085, 0.21, 2.1e-4, -3.3e-4, -0.35, 0.01, -0.02, 0.03])
SIZE = (2352, 1728)


def _camera_points(n, seed):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.6, 0.6, size=(n, 2))          # normalised coordinates within the field of view
    z = rng.uniform(800.0, 3000.0, size=n)
    return np.column_stack([xy * z[:, None], z])        # mm, camera frame


@pytest.mark.parametrize("dist", [DIST8[:5], DIST8])
def test_projection_matches_kornia_distort_points(dist):
    X = _camera_points(500, 1)
    px, _, status = project_points(X, K, dist, image_size=SIZE, margin_px=np.inf, device="cpu")
    ideal = (X[:, :2] / X[:, 2:3]) @ K[:2, :2].T + K[:2, 2]  # undistorted pixels
    ref = kornia_calibration.distort_points(torch.from_numpy(ideal), torch.from_numpy(K), torch.from_numpy(dist)).numpy()
    assert np.all(status.numpy() == 0)
    np.testing.assert_allclose(px.numpy(), ref, atol=1e-8)


def test_undistortion_matches_kornia():
    X = _camera_points(500, 2)
    ideal = (X[:, :2] / X[:, 2:3]) @ K[:2, :2].T + K[:2, 2]
    distorted = kornia_calibration.distort_points(torch.from_numpy(ideal), torch.from_numpy(K),
                                                  torch.from_numpy(DIST8)).numpy()
    ours, status = undistort_points(distorted, K, DIST8, image_size=SIZE, margin_px=np.inf, device="cpu")
    theirs = kornia_calibration.undistort_points(torch.from_numpy(distorted), torch.from_numpy(K),
                                                 torch.from_numpy(DIST8), num_iters=50).numpy()
    assert np.all(status.numpy() == 0)
    np.testing.assert_allclose(ours.numpy(), ideal, atol=1e-7)  # ours converges to 1e-9 px
    # kornia's fixed-point iteration converges more slowly at the image corners: compare where it settled
    settled = np.linalg.norm(theirs - ideal, axis=1) < 1e-6
    assert settled.mean() > 0.9
    np.testing.assert_allclose(ours.numpy()[settled], theirs[settled], atol=2e-6)


def test_linear_triangulation_matches_kornia_dlt():
    rng = np.random.default_rng(3)
    X = np.column_stack([rng.uniform(-400, 400, 300), rng.uniform(-300, 300, 300), rng.uniform(2500, 4000, 300)])
    a = np.radians(12.0)
    R = np.array([[np.cos(a), 0.0, -np.sin(a)], [0.0, 1.0, 0.0], [np.sin(a), 0.0, np.cos(a)]])
    t = np.array([-800.0, 5.0, 120.0])
    zero = np.zeros(5)
    left = (X[:, :2] / X[:, 2:3]) @ K[:2, :2].T + K[:2, 2]
    Xr = X @ R.T + t
    right = (Xr[:, :2] / Xr[:, 2:3]) @ K[:2, :2].T + K[:2, 2]
    noise = rng.normal(0.0, 0.05, size=(2, 300, 2))
    left, right = left + noise[0], right + noise[1]
    P1 = K @ np.column_stack([np.eye(3), np.zeros(3)])
    P2 = K @ np.column_stack([R, t])
    theirs = kornia_epipolar.triangulate_points(torch.from_numpy(P1)[None], torch.from_numpy(P2)[None],
                                                torch.from_numpy(left)[None], torch.from_numpy(right)[None])[0].numpy()
    res = triangulate_points(left, right, K_left=K, dist_left=zero, K_right=K, dist_right=zero, R_right_left=R,
                             t_right_left=t, method="linear", margin_px=np.inf, device="cpu")
    ours, _, status = (r.numpy() for r in res)
    assert np.all(status == 0) and np.abs(ours - X).max() < 5.0  # sane: within the noise's reach of the truth
    # both are the homogeneous DLT of the same rays; with 0.05 px noise they agree far below the noise's
    # effect on the points (~0.1 mm at 3 m): the normalisation differs only in round-off
    np.testing.assert_allclose(ours, theirs, atol=1e-6 * np.abs(theirs).max())
