"""Stereo rig model and file, triangulation, cv2.stereoCalibrate comparison, target check, covariances."""
import json

import cv2
import numpy as np
import pytest

from calibration.mirror import joint_mirror_stereo
from calibration.stereo import StereoRig, reconstruct_target, stereo_calibrate
from calibration.uncertainty import covariance_from_jacobian, propagate
from repro.mirror_setup import checkerboard_far_views, paper_mirror_setup, simulate_mirror_observations

NOISE = 0.03


@pytest.fixture(scope="module")
def setup():
    return paper_mirror_setup()


@pytest.fixture(scope="module")
def truth(setup):
    return StereoRig(setup.left, setup.right, setup.R_right_left, setup.t_right_left)


def _scene(rng, n=100):  # points in the working volume of the paper (3 m x 2 m x 1.8 m around 5.4 m)
    return np.stack([rng.uniform(-1500, 1500, n), rng.uniform(-1000, 1000, n), rng.uniform(4500, 6300, n)], axis=1)


def test_geometry(truth, setup):
    assert truth.baseline == pytest.approx(1650.0, abs=1e-9)
    # right camera centre in the left frame: 1650 mm along the baseline direction of the rig
    C = truth.right_center
    C_world = -setup.R_right_world.T @ setup.t_right_world
    assert np.allclose(setup.R_left_world.T @ C + (-setup.R_left_world.T @ setup.t_left_world), C_world, atol=1e-9)


def test_project_matches_opencv(truth, rng):
    P = _scene(rng)
    ql, qr = truth.project(P)
    rv, _ = cv2.Rodrigues(truth.R_right_left)
    ref, _ = cv2.projectPoints(P.reshape(-1, 1, 3), rv, truth.t_right_left, truth.right.K, truth.right.dist)
    assert np.max(np.abs(qr - ref.reshape(-1, 2))) < 1e-7


def test_triangulation_exact_and_against_opencv(truth, rng):
    P = _scene(rng)
    ql, qr = truth.project(P)
    assert np.max(np.abs(truth.triangulate(ql, qr) - P)) < 1e-6  # noise-free: exact (mm at 6 m)
    # with noise, compare with OpenCV's linear triangulation of the undistorted points
    nl, nr = ql + rng.normal(0, 0.1, ql.shape), qr + rng.normal(0, 0.1, qr.shape)
    ul = cv2.undistortPoints(nl.reshape(-1, 1, 2), truth.left.K, truth.left.dist, None, None, None,
                                 (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-14)).reshape(-1, 2)
    ur = cv2.undistortPoints(nr.reshape(-1, 1, 2), truth.right.K, truth.right.dist, None, None, None,
                                 (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-14)).reshape(-1, 2)
    Xh = cv2.triangulatePoints(np.hstack([np.eye(3), np.zeros((3, 1))]),
                               np.hstack([truth.R_right_left, truth.t_right_left[:, None]]), ul.T, ur.T)
    ref = (Xh[:3] / Xh[3]).T
    ours_linear = truth.triangulate(nl, nr, refine=False)
    assert np.max(np.abs(ours_linear - ref)) < 1e-3  # same DLT on the same normalised points
    # the reprojection-optimal refinement cannot do worse in reprojection error than the DLT
    ours = truth.triangulate(nl, nr)
    rep = lambda X: np.sum((np.concatenate(truth.project(X), 1) - np.concatenate([nl, nr], 1)) ** 2, axis=1)
    assert np.all(rep(ours) <= rep(ref) + 1e-9)


def test_json_round_trip(truth, tmp_path):
    rig = StereoRig(truth.left, truth.right, truth.R_right_left, truth.t_right_left,
                    covariance=np.diag([1e-10, 2e-10, 3e-10, 0.01, 0.02, 0.03]), metadata={"method": "test"})
    path = tmp_path / "rig.json"
    rig.save(path)
    data = json.loads(path.read_text())
    assert data["schema"] == "specula.stereo_rig" and data["schema_version"] == 1
    assert data["units"]["lengths"] == "mm" and "x_right = R_right_left" in data["conventions"]["rig"]
    back = StereoRig.load(path)
    assert np.array_equal(back.R_right_left, rig.R_right_left) and np.array_equal(back.t_right_left, rig.t_right_left)
    assert np.array_equal(back.covariance, rig.covariance) and back.metadata == {"method": "test"}
    assert np.array_equal(back.left.K, rig.left.K) and np.array_equal(back.right.dist, rig.right.dist)
    data["schema_version"] = 2
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="schema_version 2 but this version of Specula reads version 1"):
        StereoRig.load(path)
    path.write_text(json.dumps(truth.left.to_dict()))
    with pytest.raises(ValueError, match="not a Specula stereo rig file"):
        StereoRig.load(path)


def test_rig_rejects_bad_poses(truth):
    with pytest.raises(ValueError, match="proper rotation"):
        StereoRig(truth.left, truth.right, np.diag([1.0, 1.0, -1.0]), truth.t_right_left)
    with pytest.raises(ValueError, match="t_right_left is zero"):
        StereoRig(truth.left, truth.right, np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="Camera"):
        StereoRig("left", truth.right, np.eye(3), truth.t_right_left)
    with pytest.raises(ValueError, match="matching"):
        truth.triangulate(np.zeros((3, 2)), np.zeros((4, 2)))


def test_reconstruct_target_scale_follows_baseline(truth, setup):
    obs = simulate_mirror_observations(setup, 0.0, np.random.default_rng(0))
    X = setup.far_object_points
    rec = reconstruct_target(truth, obs["far_left"], obs["far_right"], X)
    assert rec.rms_distance_error < 1e-6 and rec.fit_rms < 1e-6 and rec.reprojection_rms < 1e-8
    assert np.allclose(rec.neighbour_true, 93.3)
    # a rig whose baseline is 0.1 % too long reconstructs a scene 0.1 % too large: exact for noise-free data
    longer = StereoRig(truth.left, truth.right, truth.R_right_left, truth.t_right_left * 1.001)
    rec = reconstruct_target(longer, obs["far_left"], obs["far_right"], X)
    assert rec.mean_relative_error == pytest.approx(0.001, abs=1e-9)
    assert "neighbour distance" in rec.report()


def test_stereo_calibrate_checkerboard_at_far_distance(setup, truth):
    """9x6 checkerboard of 40 mm squares at ~5.4 m, cameras 1.65 m apart, 0.03 px noise, exact intrinsics."""
    objs, ql, qr = checkerboard_far_views(setup, n_views=15, rng=np.random.default_rng(1))
    res = stereo_calibrate(setup.left, setup.right, objs, ql, qr)
    e = res.rig.errors_to(truth)
    # float64 polish agrees with OpenCV's own minimum (float32 inputs): same RMS to 1e-4 px
    assert abs(res.rms - res.opencv_rms) < 1e-4
    assert 0.03 < res.rms < 0.055 and res.per_view_rms.shape == (15, 2)
    # errors within 3 reported σ: rotation per axis and baseline
    assert abs(e["baseline_mm"]) < 3 * res.rig.std_baseline_mm
    assert e["rotation_deg"] < 3 * np.linalg.norm(res.rig.std_rotation_deg)
    # bootstrap over views gives the same order of uncertainty as the Jacobian (factor 2)
    boot = stereo_calibrate(setup.left, setup.right, objs, ql, qr, uncertainty="bootstrap", n_bootstrap=25,
                            rng=np.random.default_rng(2))
    ratio = boot.rig.std_baseline_mm / res.rig.std_baseline_mm
    assert 0.5 < ratio < 2.0, ratio


def test_mirror_joint_and_checkerboard_in_the_same_simulation(setup, truth):
    """The improved mirror calibration is at least as good as cv2.stereoCalibrate of the far checkerboard."""
    improved = paper_mirror_setup(grid=(24, 12), pitch=93.3 / 4, n_tilts=5)
    rng = np.random.default_rng(3)
    obs = simulate_mirror_observations(improved, NOISE, rng)
    far = [(improved.far_object_points, obs["far_left"], obs["far_right"])]
    joint = joint_mirror_stereo(improved.left, improved.right, obs["left_mirrored"], obs["right_mirrored"],
                                improved.object_points, far_views=far).rig
    objs, ql, qr = checkerboard_far_views(setup, n_views=15, rng=rng)
    board = stereo_calibrate(setup.left, setup.right, objs, ql, qr).rig
    # compare reported uncertainties (one draw each; the docs give Monte Carlo RMS figures)
    assert joint.std_baseline_mm < board.std_baseline_mm
    assert np.linalg.norm(joint.std_rotation_deg) < np.linalg.norm(board.std_rotation_deg)
    assert joint.errors_to(truth)["rotation_deg"] <= 0.01


def test_stereo_calibrate_bad_inputs(setup):
    objs, ql, qr = checkerboard_far_views(setup, n_views=3, rng=np.random.default_rng(4))
    with pytest.raises(ValueError, match="views; they must match"):
        stereo_calibrate(setup.left, setup.right, objs, ql[:2], qr)
    with pytest.raises(ValueError, match="equal N"):
        stereo_calibrate(setup.left, setup.right, objs, [q[:-1] for q in ql], qr)
    with pytest.raises(ValueError, match="uncertainty must be"):
        stereo_calibrate(setup.left, setup.right, objs, ql, qr, uncertainty="magic")


def test_covariance_helpers_against_closed_forms(rng):
    # linear least squares y = A x + noise: covariance σ² (AᵀA)⁻¹ exactly
    A = rng.normal(size=(50, 3))
    r = rng.normal(size=50)
    cov = covariance_from_jacobian(A, r, sigma=0.5)
    assert np.allclose(cov, 0.25 * np.linalg.inv(A.T @ A), rtol=1e-10)
    cov_est = covariance_from_jacobian(A, r)
    assert np.allclose(cov_est, (r @ r) / 47 * np.linalg.inv(A.T @ A), rtol=1e-10)
    with pytest.raises(ValueError, match="not determined"):
        covariance_from_jacobian(np.c_[A, A[:, :1]], r)
    # propagation through a linear map is exact: M C Mᵀ
    M = rng.normal(size=(2, 3))
    C = np.diag([1.0, 2.0, 3.0])
    assert np.allclose(propagate(lambda x: M @ x, np.ones(3), C), M @ C @ M.T, rtol=1e-7)
