"""Known-distance verification of a rig (calibration/verify.py) on exact projections.

For noise-free points, a rig whose translation is (1 + ε) times the true one triangulates every point
at (1 + ε) times its true position (the rays of both cameras scale about the left centre), so the
reported scale error must be 100 ε % to round-off."""
import numpy as np
import pytest

from calibration.camera import Camera, rotation_from_vector
from calibration.stereo import StereoRig
from calibration.verify import verify_distance, verify_view_distance
from calibration.views import StereoView

LEFT = Camera(K=[[700.0, 0, 241.3], [0, 700.0, 178.2], [0, 0, 1]], dist=[-0.12, 0.08, 2e-4, -1e-4, 0.0], size=(480, 360))
RIGHT = Camera(K=[[705.0, 0, 238.1], [0, 705.0, 181.7], [0, 0, 1]], dist=[-0.10, 0.05, -1e-4, 2e-4, 0.0], size=(480, 360))
R_RL = rotation_from_vector([0.0, np.radians(6.0), np.radians(0.5)])
T_RL = -R_RL @ np.array([300.0, 2.0, -10.0])
P = np.array([[-260.0, -40.0, 1400.0], [220.0, 60.0, 1500.0]])


@pytest.mark.parametrize("eps", [0.0, 0.01, -0.003])
def test_scale_error_of_a_scaled_rig_is_its_scale(eps):
    ql, qr = StereoRig(LEFT, RIGHT, R_RL, T_RL).project(P)
    res = verify_distance(StereoRig(LEFT, RIGHT, R_RL, (1 + eps) * T_RL), ql, qr, np.linalg.norm(P[1] - P[0]))
    assert res.scale_error_percent == pytest.approx(100 * eps, abs=1e-6)
    np.testing.assert_allclose(res.points, (1 + eps) * P, atol=1e-5)
    assert np.all(res.reprojection_px < 1e-6)
    assert "scale error" in res.report()


def test_view_distance_defaults_to_the_farthest_pair_and_the_target_distance():
    rig = StereoRig(LEFT, RIGHT, R_RL, T_RL)
    X = np.array([[0.0, 0, 0], [100, 0, 0], [0, 50, 0], [100, 50, 0]])  # target frame, mm
    Rt, tt = rotation_from_vector([0.2, -0.3, 0.05]), np.array([-60.0, -20.0, 1300.0])
    Xc = X @ Rt.T + tt
    ql, qr = rig.project(Xc)
    view = StereoView(np.array([4, 7, 9, 12]), X, ql, qr, name="check", image_sizes=((480, 360), (480, 360)))
    res = verify_view_distance(rig, view)
    assert set(res.labels) == {4, 12} and res.known == pytest.approx(np.hypot(100, 50), rel=1e-12)
    assert abs(res.scale_error_percent) < 1e-6
    res = verify_view_distance(rig, view, ids=(7, 9), known_distance=112.0)  # true 111.803 mm
    assert res.scale_error_percent == pytest.approx(100 * (np.hypot(100, 50) / 112.0 - 1), abs=1e-6)
    with pytest.raises(ValueError, match="5 not seen by both cameras"):
        verify_view_distance(rig, view, ids=(4, 5))
    with pytest.raises(ValueError, match="calibrated for 480x360"):
        verify_view_distance(rig, StereoView(view.ids, X, ql, qr, image_sizes=((640, 480), (480, 360))))


@pytest.mark.parametrize("args, message", [
    (dict(known_distance=0.0), "positive distance"),
    (dict(known_distance=float("nan")), "positive distance"),
    (dict(left_points=np.zeros((3, 2))), "shape \\(2, 2\\)"),
])
def test_bad_input(args, message):
    rig = StereoRig(LEFT, RIGHT, R_RL, T_RL)
    ql, qr = rig.project(P)
    kw = dict(left_points=ql, right_points=qr, known_distance=100.0) | args
    with pytest.raises(ValueError, match=message):
        verify_distance(rig, **kw)
