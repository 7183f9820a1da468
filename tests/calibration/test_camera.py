"""Camera model: projection against OpenCV, pose helpers, undistortion maps and images, JSON file."""
import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.camera import (
    Camera,
    distort_normalized,
    nearest_rotation,
    rigid_fit,
    rotation_angle_deg,
    rotation_from_vector,
    transform_points,
    vector_from_rotation,
)


@pytest.fixture
def camera():
    return Camera(K=[[1800.0, 0.0, 1010.0], [0, 1795.0, 760.0], [0, 0, 1]], dist=[-0.12, 0.08, 4e-4, -3e-4, 0.01],
                  size=(2048, 1536), name="left")


def _points(rng, n=200):
    return np.stack([rng.uniform(-600, 600, n), rng.uniform(-450, 450, n), rng.uniform(1500, 3000, n)], axis=1)


def test_project_matches_opencv(camera, rng):
    P = _points(rng)
    ours = camera.project(P)
    ref, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K, camera.dist)
    # both evaluate the same closed-form model in float64: agreement to rounding (~1e-9 px)
    assert np.max(np.abs(ours - ref.reshape(-1, 2))) < 1e-8


def test_rational_model_matches_opencv(rng):
    cam = Camera(K=[[1500.0, 0, 640], [0, 1500, 480], [0, 0, 1]], dist=[0.1, -0.05, 1e-3, 2e-4, 0.01, 0.05, -0.02, 0.004])
    P = _points(rng)
    ref, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.max(np.abs(cam.project(P) - ref.reshape(-1, 2))) < 1e-8


def test_distort_normalized_and_its_jacobian_match_opencv(rng):
    # the one host copy of the model (Camera and the bundle adjustments use it), every coefficient non-zero
    dist = np.array([-0.28, 0.11, 1.2e-3, -8.0e-4, -0.03, 0.05, -0.02, 0.004])
    xy = rng.uniform(-0.4, 0.4, (300, 2))

    def opencv(points):
        out, _ = cv2.projectPoints(np.column_stack([points, np.ones(len(points))]).reshape(-1, 1, 3), np.zeros(3),
                                   np.zeros(3), np.eye(3), dist)
        return out.reshape(-1, 2)

    distorted, J = distort_normalized(xy, dist, jacobian=True)
    assert np.max(np.abs(distorted - opencv(xy))) < 1e-13
    np.testing.assert_array_equal(distort_normalized(xy, dist), distorted)
    h = 1e-6
    for col, e in enumerate(np.eye(2)):
        fd = (opencv(xy + h * e) - opencv(xy - h * e)) / (2 * h)
        np.testing.assert_allclose(J[:, :, col], fd, rtol=0, atol=1e-8)
    with pytest.raises(ValueError, match="shape"):
        distort_normalized(xy[:, :1], dist)
    with pytest.raises(ValueError, match="0, 4, 5 or 8"):
        distort_normalized(xy, dist[:6])


def test_project_points_with_pose_matches_opencv(camera, rng):
    X = rng.uniform(-200, 200, (50, 3))
    rvec, tvec = np.array([0.1, -0.2, 0.05]), np.array([30.0, -20.0, 2000.0])
    ref, _ = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, tvec, camera.K, camera.dist)
    ours = camera.project_points(X, rotation_from_vector(rvec), tvec)
    assert np.max(np.abs(ours - ref.reshape(-1, 2))) < 1e-8


def test_undistort_points_inverts_projection(camera, rng):
    P = _points(rng)
    q = camera.project(P)
    ideal = Camera(camera.K).project(P)
    # Newton inversion to 1e-12 in normalised units ~ 2e-9 px at f = 1800 px
    assert np.max(np.abs(camera.undistort_points(q) - ideal)) < 1e-7
    rays = camera.rays(q)
    expected = P / np.linalg.norm(P, axis=1, keepdims=True)
    assert np.max(np.abs(rays - expected)) < 1e-10


def test_project_behind_camera_is_rejected(camera):
    with pytest.raises(ValueError, match="behind the camera"):
        camera.project([[0.0, 0.0, -1.0]])


def test_rotation_helpers_match_scipy(rng):
    for _ in range(5):
        w = rng.normal(0, 1.0, 3)
        R = rotation_from_vector(w)
        assert np.allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-14)
        assert np.allclose(vector_from_rotation(R), Rotation.from_matrix(R).as_rotvec(), atol=1e-12)
    # small angles keep their precision (arccos alone would lose it below ~1e-8 rad)
    R = rotation_from_vector([1e-9, 0, 0])
    assert abs(rotation_angle_deg(R) - np.degrees(1e-9)) < 1e-15
    M = rotation_from_vector([0.3, 0.1, -0.2]) + rng.normal(0, 1e-3, (3, 3))
    Rn = nearest_rotation(M)
    assert np.allclose(Rn @ Rn.T, np.eye(3), atol=1e-12) and np.linalg.det(Rn) > 0


def test_rigid_fit_recovers_transform(rng):
    A = rng.uniform(-100, 100, (30, 3))
    R = rotation_from_vector([0.2, -0.4, 0.9])
    t = np.array([10.0, -5.0, 1000.0])
    Rf, tf = rigid_fit(A, transform_points(R, t, A))
    assert rotation_angle_deg(Rf, R) < 1e-9 and np.allclose(tf, t, atol=1e-9)
    with pytest.raises(ValueError, match="collinear"):
        rigid_fit(np.outer(np.arange(5.0), [1, 2, 3]), np.outer(np.arange(5.0), [1, 2, 3]))


def test_undistortion_maps_match_opencv(camera):
    map_x, map_y = camera.undistortion_maps()
    ref_x, ref_y = cv2.initUndistortRectifyMap(camera.K, camera.dist, None, camera.K, camera.size, cv2.CV_32FC1)
    # same model (no skew); float32 rounding ~1e-4 px at 2000 px
    assert max(np.max(np.abs(map_x - ref_x)), np.max(np.abs(map_y - ref_y))) < 1e-3


def test_undistortion_maps_follow_the_model_with_skew(camera):
    camera = Camera(camera.K + [[0, 0.4, 0], [0, 0, 0], [0, 0, 0]], camera.dist, camera.size)
    map_x, map_y = camera.undistortion_maps()
    assert map_x.shape == (1536, 2048) and map_x.dtype == np.float32
    # the map at undistorted pixel (u, v) is the projection of its ray: independent of OpenCV's inversion
    v, u = np.mgrid[0:1536:97, 0:2048:131]
    uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(float)
    rays = np.concatenate([Camera(camera.K).pixels_to_normalized(uv), np.ones((uv.shape[0], 1))], axis=1)
    expected = camera.project(rays)
    got = np.stack([map_x[v.ravel(), u.ravel()], map_y[v.ravel(), u.ravel()]], axis=1)
    # float32 maps: ~1e-4 px rounding at 2000 px
    assert np.max(np.abs(got - expected)) < 2e-3


def test_undistort_image_recovers_a_smooth_scene():
    camera = Camera(K=[[300.0, 0, 161.0], [0, 300.0, 118.0], [0, 0, 1]], dist=[-0.2, 0.1, 1e-3, -5e-4, 0.0],
                    size=(320, 240))
    w, h = camera.size

    def scene(x, y):  # smooth grey levels on undistorted pixel coordinates
        return 100 + 60 * np.sin(x / 17.0) * np.cos(y / 13.0)

    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    ideal = camera.undistort_points(np.stack([xx.ravel(), yy.ravel()], axis=1))
    distorted = scene(ideal[:, 0], ideal[:, 1]).reshape(h, w)
    out = camera.undistort_image(distorted, interpolation="cubic")
    interior = (slice(20, h - 20), slice(20, w - 20))
    # cv2.remap quantises positions to 1/32 px: with gradients up to 60·(1/17 + 1/13) ≈ 8 grey levels/px
    # that alone gives up to 0.13 grey level; plus the cubic kernel's error on an 80-px period: < 0.5
    err = out[interior] - scene(xx, yy)[interior]
    assert np.max(np.abs(err)) < 0.5
    with pytest.raises(ValueError, match="calibrated for"):
        camera.undistort_image(np.zeros((100, 100)))
    with pytest.raises(ValueError, match="interpolation"):
        camera.undistort_image(distorted, interpolation="nearest")


def test_json_round_trip(camera, tmp_path):
    path = tmp_path / "cam.json"
    camera.save(path, metadata={"rms_px": 0.04})
    data = json.loads(path.read_text())
    assert data["schema"] == "specula.camera" and data["schema_version"] == 1
    assert "camera_frame" in data["conventions"] and data["units"]["K"] == "px"
    back = Camera.load(path)
    assert np.array_equal(back.K, camera.K) and np.array_equal(back.dist, camera.dist)
    assert back.size == camera.size and back.name == camera.name


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(schema_version=2), "schema_version 2"),
    (lambda d: d.update(schema="other"), "not a Specula camera"),
    (lambda d: d.pop("K"), "lacks the keys"),
])
def test_json_bad_files(camera, tmp_path, edit, message):
    d = camera.to_dict()
    edit(d)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=message):
        Camera.load(path)


def test_json_truncated_and_missing(camera, tmp_path):
    path = tmp_path / "cam.json"
    camera.save(path)
    path.write_text(path.read_text()[:50])
    with pytest.raises(ValueError, match="not valid JSON"):
        Camera.load(path)
    with pytest.raises(ValueError, match="does not exist"):
        Camera.load(tmp_path / "nope.json")
