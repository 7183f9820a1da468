"""Epipolar geometry, feature-based guesses, POI grids, object frames and surface strain of dic.stereo / dic.field3d.

References are independent: OpenCV's 8-point fundamental matrix, explicit back-projection and
projection of points, and closed-form Green-Lagrange strains of homogeneous deformations.
"""
import numpy as np
import pytest

from calibration.camera import Camera, rotation_from_vector
from calibration.stereo import StereoRig
from dic._stereo import affine_guess, epipolar_distance, epipolar_residuals, fundamental_matrix, grid_points
from dic.field3d import Field3D, grid_neighbours, plane_frame, scattered_neighbours, surface_strain


def _rig(distorted: bool = True) -> StereoRig:
    K_left = np.array([[1650.0, 0.0, 640.2], [0.0, 1648.0, 511.7], [0.0, 0.0, 1.0]])
    K_right = np.array([[1710.0, 0.0, 655.9], [0.0, 1712.5, 498.3], [0.0, 0.0, 1.0]])
    dist_l = [-0.12, 0.09, 3e-4, -2e-4, -0.02] if distorted else []
    dist_r = [-0.08, 0.05, -1e-4, 4e-4, 0.0] if distorted else []
    left = Camera(K_left, dist_l, (1280, 1024), "left")
    right = Camera(K_right, dist_r, (1280, 1024), "right")
    R = rotation_from_vector([0.01, -0.28, 0.02])
    return StereoRig(left, right, R, np.array([-420.0, 8.0, 60.0]))


def _scene_points(rng, n):
    return np.column_stack([rng.uniform(-300, 300, n), rng.uniform(-250, 250, n), rng.uniform(1200, 2000, n)])


def test_fundamental_matrix_against_opencv(rng):
    import cv2

    rig = _rig(distorted=False)
    X = _scene_points(rng, 60)
    pl, pr = rig.project(X)
    F_cv, _ = cv2.findFundamentalMat(pl, pr, cv2.FM_8POINT)
    F = fundamental_matrix(rig)
    F_cv = F_cv / np.linalg.norm(F_cv)
    # the same matrix up to sign: 8-point from exact correspondences is exact to rounding (~1e-8 here)
    assert min(np.abs(F - F_cv).max(), np.abs(F + F_cv).max()) < 1e-6
    # exact correspondences lie on their epipolar lines
    assert np.abs(epipolar_distance(F, pl, pr)).max() < 1e-8


def test_epipolar_residuals_with_distortion(rng):
    rig = _rig(distorted=True)
    X = _scene_points(rng, 200)
    pl, pr = rig.project(X)
    # exact (distorted) correspondences: zero after undistortion (converged to 1e-9 px)
    assert np.nanmax(epipolar_residuals(rig, pl, pr)) < 1e-6
    # move each ideal right point by a known distance perpendicular to its epipolar line, found
    # independently by projecting the left ray at two depths
    xl = rig.left.undistort_normalized(rig.left.pixels_to_normalized(pl))
    ideal_right = rig.right.undistort_points(pr)
    shifts = rng.uniform(-3, 3, len(X))
    moved = np.empty_like(ideal_right)
    ideal_cam = Camera(rig.right.K)
    for i in range(len(X)):
        ray = np.array([xl[i, 0], xl[i, 1], 1.0])
        a, b = (ideal_cam.project(((ray * z) @ rig.R_right_left.T + rig.t_right_left)[None])[0] for z in (800.0, 3000.0))
        d = (b - a) / np.linalg.norm(b - a)
        moved[i] = ideal_right[i] + shifts[i] * np.array([-d[1], d[0]])
    # back to observed pixels through the lens model, then the residual must equal |shift|
    observed = rig.right.normalized_to_pixels(rig.right.distort_normalized(rig.right.pixels_to_normalized(moved)))
    assert np.allclose(epipolar_residuals(rig, pl, observed), np.abs(shifts), atol=1e-6)
    # NaN inputs give NaN, not an error
    pl[3] = np.nan
    res = epipolar_residuals(rig, pl, observed)
    assert np.isnan(res[3]) and np.all(np.isfinite(np.delete(res, 3)))


def test_affine_guess_recovers_local_affine_map(rng):
    # correspondences of a smooth (homography-like) map, with 0.3 px noise and 15 % gross outliers
    A = np.array([[0.93, 0.04], [-0.03, 1.02]])
    b = np.array([35.0, -12.0])

    def mapping(p):
        return p @ A.T + b + 1e-5 * (p - 500.0) ** 2

    src = rng.uniform(0, 1000, (3000, 2))
    dst = mapping(src) + rng.normal(0, 0.3, src.shape)
    bad = rng.random(len(src)) < 0.15
    dst[bad] += rng.uniform(-40, 40, (bad.sum(), 2))
    pois = rng.uniform(100, 900, (200, 2))
    params, ok = affine_guess(pois, src, dst, k=16, radius=120.0)
    assert ok.all()
    true_uv = mapping(pois) - pois
    # guesses only need to land within a few px for IC-GN; 16 neighbours of 0.3 px noise, outliers
    # down-weighted by the Cauchy reweighting: within 1 px (measured max 0.36 px)
    assert np.abs(params[:, 0] - true_uv[:, 0]).max() < 1.0
    assert np.abs(params[:, 3] - true_uv[:, 1]).max() < 1.0
    # gradients: d(u)/dx = A00 - 1 + 2e-5 (x - 500); a gradient error of 0.05 moves the edge of a
    # 21 px subset by 0.5 px, which IC-GN absorbs
    assert np.abs(params[:, 1] - (A[0, 0] - 1 + 2e-5 * (pois[:, 0] - 500))).max() < 0.05
    assert np.abs(params[:, 5] - (A[1, 1] - 1 + 2e-5 * (pois[:, 1] - 500))).max() < 0.05
    # a POI far from every correspondence gets no guess
    params, ok = affine_guess(np.array([[5000.0, 5000.0]]), src, dst, radius=120.0)
    assert not ok[0] and np.all(np.isnan(params[0]))


@pytest.mark.parametrize("grid_step", [5.0, 40.0])  # POIs denser than the fit cells (20 px), then sparser
def test_affine_guess_at_active_points_only(rng, grid_step):
    """``active``: the guesses of the active POIs are bit for bit those computed for every POI (the cells of the
    active POIs fitted only; whether cells are used is decided on all POIs), the others get none."""
    src = rng.uniform(0, 1000, (3000, 2))
    dst = src * 1.01 + np.array([12.0, -7.0]) + rng.normal(0, 0.3, src.shape)
    ys, xs = np.mgrid[0:1000:grid_step, 0:1000:grid_step]
    pois = np.c_[xs.ravel(), ys.ravel()] + 0.5
    active = (pois[:, 0] > 300) & (pois[:, 0] < 620) & (pois[:, 1] < 450)
    every, ok_every = affine_guess(pois, src, dst, radius=120.0)
    some, ok_some = affine_guess(pois, src, dst, radius=120.0, active=active)
    assert np.count_nonzero(ok_every[active]) > 0.9 * np.count_nonzero(active)
    assert np.array_equal(some[active], every[active], equal_nan=True)
    assert np.array_equal(ok_some, ok_every & active) and np.all(np.isnan(some[~active]))
    with pytest.raises(ValueError, match="active must be"):
        affine_guess(pois, src, dst, active=active[1:])


def test_grid_points_and_roi():
    pts, shape, in_roi = grid_points((100, 160), 10, 21)
    assert shape == (8, 14) and pts.shape == (112, 2) and in_roi.all()
    assert pts[:, 0].min() == 10 and pts[:, 0].max() <= 160 - 1 - 10 and pts[:, 1].max() <= 100 - 1 - 10
    _, _, in_roi = grid_points((100, 160), 10, 21, roi=(40, 20, 80, 60))
    assert in_roi.sum() == 5 * 5
    mask = np.zeros((100, 160), bool)
    mask[:50] = True
    p, _, in_roi = grid_points((100, 160), 10, 21, roi=mask)
    assert np.array_equal(in_roi, p[:, 1] < 50)
    with pytest.raises(ValueError, match="contains no grid point"):
        grid_points((100, 160), 10, 21, roi=(0, 0, 5, 5))
    with pytest.raises(ValueError, match="too small"):
        grid_points((15, 160), 10, 21)
    with pytest.raises(ValueError, match="roi mask must have the image shape"):
        grid_points((100, 160), 10, 21, roi=np.ones((10, 10), bool))


def test_plane_frame(rng):
    n = np.array([0.2, -0.1, -1.0])
    n /= np.linalg.norm(n)
    c = np.array([10.0, -20.0, 1500.0])
    u = np.cross(n, [0, 1, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    P = c + rng.uniform(-100, 100, (50, 1)) * u + rng.uniform(-100, 100, (50, 1)) * v
    R, t = plane_frame(P)
    local = P @ R.T + t
    assert np.abs(local[:, 2]).max() < 1e-9                      # flat in the frame
    assert np.allclose(local.mean(axis=0), 0, atol=1e-9)          # origin at the centroid
    assert R[2] @ (-P.mean(axis=0)) > 0                           # z faces the camera (origin)
    assert abs(R[0, 1]) < 1e-12 or abs(R[0] @ [0, 1, 0]) < 0.2    # x from the camera's x axis
    with pytest.raises(ValueError, match="collinear"):
        plane_frame(np.outer(np.arange(5.0), [1, 2, 3]))


def _deformed_grid(F_in, R_rigid, tilt):
    """Grid on a tilted plane, displaced by x -> R_rigid (c + F_in (x - c)) with F_in acting in the plane."""
    R_plane = rotation_from_vector(tilt)
    a, b = np.meshgrid(np.arange(-20, 21, 4.0), np.arange(-16, 17, 4.0))
    local = np.column_stack([a.ravel(), b.ravel(), np.zeros(a.size)])
    X = local @ R_plane.T + [0.0, 0.0, 1000.0]
    c = X.mean(axis=0)
    F3 = R_plane @ np.pad(F_in, ((0, 1), (0, 1))) @ R_plane.T + np.outer(R_plane[:, 2], R_plane[:, 2])
    x = (X - c) @ (R_rigid @ F3).T + c
    return X, x - X, a.shape, R_plane


def test_surface_strain_exact_for_homogeneous_deformation():
    # in-plane deformation gradient in the plane's own axes, then a rigid rotation of everything
    F_in = np.array([[1.02, 0.015], [-0.004, 0.99]])
    tilt = [0.3, -0.2, 0.1]
    X, U, shape, R_plane = _deformed_grid(F_in, rotation_from_vector([0.05, 0.2, -0.1]), tilt)
    out = surface_strain(X, U, np.ones(len(X), bool), grid_neighbours(shape, 5), x_axis=R_plane[:, 0],
                         y_axis=R_plane[:, 1])
    E = 0.5 * (F_in.T @ F_in - np.eye(2))        # Green-Lagrange in the plane's axes
    ok = out["strain_valid"]
    assert ok.all()
    # exact for affine fields (a least-squares fit of an affine function); rounding only
    assert np.allclose(out["exx"], E[0, 0], atol=1e-12)
    assert np.allclose(out["eyy"], E[1, 1], atol=1e-12)
    assert np.allclose(out["exy"], E[0, 1], atol=1e-12)
    assert np.allclose(np.abs(out["normal"] @ R_plane[:, 2]), 1.0, atol=1e-12)
    assert np.all(out["normal"] @ [0, 0, -1.0] > 0)               # towards the camera at the origin
    # a rigid motion has exactly zero strain (no small-strain approximation)
    X, U, shape, R_plane = _deformed_grid(np.eye(2), rotation_from_vector([0.3, -0.4, 0.5]), tilt)
    out = surface_strain(X, U, np.ones(len(X), bool), grid_neighbours(shape, 3), x_axis=R_plane[:, 0])
    ok = out["strain_valid"]
    assert ok.sum() == len(X) - 4   # the 4 grid corners have 4 < 6 neighbours in a 3x3 window: NaN, flagged
    for k in ("exx", "eyy", "exy"):
        assert np.abs(out[k][ok]).max() < 1e-12 and np.all(np.isnan(out[k][~ok]))


def test_surface_strain_needs_enough_neighbours():
    F_in = np.diag([1.01, 1.0])
    X, U, shape, R_plane = _deformed_grid(F_in, np.eye(3), [0.0, 0.0, 0.0])
    valid = np.zeros(len(X), bool)
    valid[:3] = True            # three points in a row: too few and collinear
    out = surface_strain(X, U, valid, grid_neighbours(shape, 5))
    assert not out["strain_valid"].any() and np.all(np.isnan(out["exx"]))
    # scattered neighbourhoods give the same strain as grid ones for an affine field
    nb = scattered_neighbours(X, 25)
    out = surface_strain(X, U, np.ones(len(X), bool), nb)
    assert np.allclose(out["exx"], 0.5 * (1.01**2 - 1), atol=1e-12)
    with pytest.raises(ValueError, match="odd integer >= 3"):
        grid_neighbours(shape, 4)


def test_field_in_frame_round_trip(rng):
    n = 12
    f = Field3D(points=rng.uniform(0, 100, (n, 2)), grid_shape=None, X=rng.normal(size=n), Y=rng.normal(size=n),
                Z=1000 + rng.normal(size=n), U=rng.normal(size=n), V=rng.normal(size=n), W=rng.normal(size=n),
                exx=np.full(n, 0.01), eyy=np.full(n, -0.002), exy=np.full(n, 0.003),
                normal=np.tile([0.0, 0.0, -1.0], (n, 1)), zncc_stereo=np.ones(n), zncc_left=np.ones(n),
                zncc_right=np.ones(n), epipolar_ref_px=np.zeros(n), epipolar_px=np.zeros(n),
                reprojection_ref_px=np.zeros(n), reprojection_px=np.zeros(n), status=np.zeros(n, np.int8),
                strain_valid=np.ones(n, bool))
    R = rotation_from_vector([0.0, 0.0, np.pi / 2])   # x_obj = y_left, y_obj = -x_left
    g = f.in_frame((R, [1.0, 2.0, 3.0]))
    assert np.allclose(g.xyz, f.xyz @ R.T + [1, 2, 3]) and np.allclose(g.uvw, f.uvw @ R.T)
    # the in-plane axes turn by 90 deg: exx <-> eyy, exy -> -exy
    # (e1' = -e2 and e2' = e1, each e2 on the side of its frame's y axis: exy changes sign)
    assert np.allclose(g.exx, -0.002) and np.allclose(g.eyy, 0.01) and np.allclose(g.exy, -0.003)
    back = g.in_frame("left")
    assert np.allclose(back.xyz, f.xyz) and np.allclose(back.exx, f.exx) and np.allclose(back.exy, f.exy)
    with pytest.raises(ValueError, match="proper rotation"):
        f.in_frame((2 * np.eye(3), np.zeros(3)))
    with pytest.raises(ValueError, match="frame must be"):
        f.in_frame("world")


def test_grid_strain_equals_gathered_strain(rng):
    """The O(N) box-filter version agrees with the explicit neighbour gather on a noisy curved surface."""
    from dic.field3d import surface_strain_grid

    ny, nx = 23, 31
    gy, gx = np.meshgrid(np.arange(ny) * 3.0, np.arange(nx) * 3.0, indexing="ij")
    X = np.column_stack([gx.ravel(), gy.ravel(), 900 + 0.002 * (gx.ravel() - 40) ** 2 + 0.05 * gy.ravel()])
    U = np.column_stack([1e-3 * X[:, 0] + 1e-5 * X[:, 1] ** 2, -2e-3 * X[:, 1], 0.01 * np.sin(X[:, 0] / 20)])
    U += rng.normal(0, 1e-3, U.shape)
    valid = rng.random(len(X)) > 0.1
    a = surface_strain(X, U, valid, grid_neighbours((ny, nx), 7))
    b = surface_strain_grid(X, U, valid, (ny, nx), 7)
    assert np.array_equal(a["strain_valid"], b["strain_valid"]) and a["strain_valid"].sum() > 0.8 * valid.sum()
    ok = a["strain_valid"]
    for k in ("exx", "eyy", "exy"):
        # strains ~1e-3; both are the same least-squares problem, summed in a different order
        assert np.abs(a[k][ok] - b[k][ok]).max() < 1e-10
    assert np.allclose(a["normal"][ok], b["normal"][ok], atol=1e-9)


def test_strain_plan_over_a_sequence_is_bitwise_a_fresh_computation(rng):
    """SurfaceStrainPlan keeps the positions' part while the valid points stay the same: every state equals
    surface_strain_grid computed from scratch bit for bit, also after the valid points change (and back)."""
    from dic.field3d import SurfaceStrainPlan, surface_strain_grid

    ny, nx = 19, 27
    gy, gx = np.meshgrid(np.arange(ny) * 3.0, np.arange(nx) * 3.0, indexing="ij")
    X = np.column_stack([gx.ravel(), gy.ravel(), 900 + 0.002 * (gx.ravel() - 40) ** 2 + 0.05 * gy.ravel()])
    X[5] = np.nan  # a point without a reference position
    plan = SurfaceStrainPlan(X, (ny, nx), 5, camera_center=(0.0, 0.0, 0.0))
    valid_a = rng.random(len(X)) > 0.1
    valid_b = valid_a.copy()
    valid_b[40:60] = False
    for k, valid in enumerate((valid_a, valid_a, valid_b, valid_a, valid_a)):
        U = np.column_stack([1e-3 * k * X[:, 0], -2e-3 * X[:, 1], 0.01 * np.sin(X[:, 0] / 20)])
        U += rng.normal(0, 1e-3, U.shape)
        got = plan(U, valid)
        fresh = surface_strain_grid(X, U, valid, (ny, nx), 5)
        for name in ("exx", "eyy", "exy", "normal", "strain_valid"):
            assert np.array_equal(got[name], fresh[name], equal_nan=name != "strain_valid"), (k, name)
        assert got["strain_valid"].sum() > 0.7 * valid.sum()
    assert plan.reused == 2  # states 1 and 4 (same valid points as the state before)
    with pytest.raises(ValueError, match=r"must be \(ny\*nx, 3\)"):
        plan(U[:-1], valid_a)
