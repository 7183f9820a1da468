"""Mirror-based extrinsics (closed form of the paper / Takahashi 2012, bundle adjustment, joint rig
adjustment) on the exact geometry of the paper's rig: camera, mirror ~0.4 m ahead, monitor ~0.65 m
behind the cameras, 0.03 px image noise."""
import numpy as np
import pytest

from calibration.bundle import RigBundle
from calibration.camera import rotation_angle_deg, rotation_from_vector, transform_points, vector_from_rotation
from calibration.mirror import MirrorPlane, _pnp, joint_mirror_stereo, mirror_closed_form, mirror_extrinsics
from calibration.stereo import StereoRig, rig_from_mirror
from repro.mirror_setup import grid_points, paper_mirror_setup, simulate_mirror_observations

NOISE = 0.03


def _reflect(P, n, d):  # the conventions' formula, written out independently of MirrorPlane
    return P - 2.0 * (P @ np.asarray(n) + d)[:, None] * np.asarray(n)[None, :]


@pytest.fixture(scope="module")
def paper():
    return paper_mirror_setup()


def test_mirror_plane_is_a_householder_reflection():
    m = MirrorPlane([0.1, -0.2, -0.97], 412.0)
    assert abs(np.linalg.norm(m.normal) - 1) < 1e-15 and m.d > 0
    P = np.random.default_rng(0).uniform(-500, 500, (20, 3))
    R1 = m.reflect(P)
    assert np.allclose(m.reflect(R1), P, atol=1e-9)  # involution
    mid = (P + R1) / 2
    assert np.allclose(mid @ m.normal + m.d, 0, atol=1e-9)  # the midpoints lie on the plane
    flipped = MirrorPlane(-m.normal, -m.d)  # same plane, other orientation: normalised to d > 0
    assert np.allclose(flipped.normal, m.normal) and flipped.d == pytest.approx(m.d)


def test_noise_free_geometry_is_recovered_exactly(paper):
    obs = simulate_mirror_observations(paper, 0.0, np.random.default_rng(0))
    R_true, t_true = paper.pose_cam_target("left")
    cf = mirror_closed_form(paper.left, obs["left_mirrored"], paper.object_points)
    # exact data: the closed form is exact up to PnP convergence
    assert rotation_angle_deg(cf.R_cam_target, R_true) < 1e-6
    assert np.linalg.norm(cf.t_cam_target - t_true) < 1e-4
    res = mirror_extrinsics(paper.left, obs["left_mirrored"], paper.object_points)
    assert rotation_angle_deg(res.R_cam_target, R_true) < 1e-8
    assert np.linalg.norm(res.t_cam_target - t_true) < 1e-6
    assert res.rms < 1e-8
    for est, (n, d) in zip(res.mirrors, paper.mirrors_left):
        assert np.allclose(est.normal, n, atol=1e-10) and abs(est.d - d) < 1e-6


def test_bundle_jacobian_matches_finite_differences(paper):
    obs = simulate_mirror_observations(paper, NOISE, np.random.default_rng(1))
    L = mirror_closed_form(paper.left, obs["left_mirrored"], paper.object_points)
    R = mirror_closed_form(paper.right, obs["right_mirrored"], paper.object_points)
    R_rl = R.R_cam_target @ L.R_cam_target.T
    far = [(paper.far_object_points, obs["far_left"], obs["far_right"])]
    model = RigBundle(paper.left, paper.right, paper.object_points, obs["left_mirrored"], obs["right_mirrored"], far,
                      (L.R_cam_target, L.t_cam_target), (R_rl, R.t_cam_target - R_rl @ L.t_cam_target),
                      L.mirrors, R.mirrors, [_pnp(paper.left, paper.far_object_points, obs["far_left"])])
    x = model.x0 + np.random.default_rng(2).normal(0, 1e-3, model.x0.size)  # away from 0: exercises J_l(ω)
    r, J = model.evaluate(x)
    Jn = np.empty_like(J)
    for k in range(x.size):
        h = 1e-6 * max(1.0, abs(x[k]))
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        Jn[:, k] = (model.residuals(xp) - model.residuals(xm)) / (2 * h)
    # central differences: truncation ~h² and rounding ~1e-13·|r|/h: relative error < 1e-5 per column
    rel = np.max(np.abs(J - Jn), axis=0) / np.max(np.abs(Jn), axis=0)
    assert np.max(rel) < 1e-5


def test_paper_setup_bundle_adjustment_beats_closed_form(paper):
    """Paper-faithful setup (6x3 dots, 3 tilts of ~3°, 0.03 px): six fixed noise draws."""
    rng = np.random.default_rng(2019)
    R_true, t_true = paper.pose_cam_target("left")
    cf_rot, cf_t, ba_rot, ba_t, maha = [], [], [], [], []
    for _ in range(6):
        obs = simulate_mirror_observations(paper, NOISE, rng)
        res = mirror_extrinsics(paper.left, obs["left_mirrored"], paper.object_points)
        cf = res.closed_form
        cf_rot.append(rotation_angle_deg(cf.R_cam_target, R_true))
        cf_t.append(np.linalg.norm(cf.t_cam_target - t_true))
        ba_rot.append(rotation_angle_deg(res.R_cam_target, R_true))
        ba_t.append(np.linalg.norm(res.t_cam_target - t_true))
        e = np.concatenate([vector_from_rotation(R_true @ res.R_cam_target.T), t_true - res.t_cam_target])
        maha.append(e @ np.linalg.solve(res.pose_covariance, e))
        # the residuals of the maximum-likelihood fit sit at the noise level (0.03·√2 ≈ 0.042 px)
        assert 0.03 < res.rms < 0.055 and res.rms <= res.closed_form_rms
    # the closed form is close: the issue measured ~0.02° / 2 mm after BA on this geometry, and the
    # closed form is a few times worse; 0.2° and 20 mm are 5x margins over what the draws give
    assert max(cf_rot) < 0.2 and max(cf_t) < 20.0
    # bundle adjustment better than the closed form alone on average over the draws (acceptance)
    assert np.mean(ba_t) < np.mean(cf_t) and np.mean(ba_rot) < np.mean(cf_rot)
    # reported covariance consistent with the errors: mean Mahalanobis distance² ≈ 6 (χ², 6 dof);
    # over 6 draws its mean has σ ≈ 1.4, accept 2–14
    assert 2.0 < np.mean(maha) < 14.0


def test_improved_setup_meets_rig_acceptance():
    """288 points (24x12 grid), 5 tilts, joint adjustment with the far view: rig rotation error
    ≤ 0.01° and baseline error ≤ 0.05 % (issue acceptance) on every draw."""
    setup = paper_mirror_setup(grid=(24, 12), pitch=93.3 / 4, n_tilts=5)
    truth = StereoRig(setup.left, setup.right, setup.R_right_left, setup.t_right_left)
    rng = np.random.default_rng(7)
    for _ in range(3):
        obs = simulate_mirror_observations(setup, NOISE, rng)
        far = [(setup.far_object_points, obs["far_left"], obs["far_right"])]
        res = joint_mirror_stereo(setup.left, setup.right, obs["left_mirrored"], obs["right_mirrored"],
                                  setup.object_points, far_views=far)
        e = res.rig.errors_to(truth)
        assert e["rotation_deg"] <= 0.01 and abs(e["baseline_percent"]) <= 0.05, e
        # the joint fit explains the data at the noise level in every group of observations
        assert all(0.03 < v < 0.055 for v in res.rms_groups.values()), res.rms_groups
        # its reported σ covers the error (3σ on the baseline)
        assert abs(e["baseline_mm"]) < 3 * res.rig.std_baseline_mm + 1e-3
        # the per-camera solutions give the rig too (rig_from_mirror), less accurately in rotation
        e_sep = res.initial_rig.errors_to(truth)
        assert e_sep["rotation_deg"] < 0.05


def test_rig_from_mirror_exact_poses(paper):
    obs = simulate_mirror_observations(paper, 0.0, np.random.default_rng(3))
    L = mirror_extrinsics(paper.left, obs["left_mirrored"], paper.object_points, sigma_px=NOISE)
    R = mirror_extrinsics(paper.right, obs["right_mirrored"], paper.object_points, sigma_px=NOISE)
    rig = rig_from_mirror(L, R)
    assert rotation_angle_deg(rig.R_right_left, paper.R_right_left) < 1e-8
    assert np.linalg.norm(rig.t_right_left - paper.t_right_left) < 1e-5
    assert abs(rig.baseline - 1650.0) < 1e-5
    # covariance propagated from the two pose covariances (σ given): positive definite, baseline σ > 0
    assert np.all(np.linalg.eigvalsh(rig.covariance) > 0) and rig.std_baseline_mm > 0
    closed = rig_from_mirror(L.closed_form, R.closed_form, paper.left, paper.right)
    assert closed.covariance is None and rotation_angle_deg(closed.R_right_left, paper.R_right_left) < 1e-6
    with pytest.raises(ValueError, match="needs the cameras"):
        rig_from_mirror(L.closed_form, R.closed_form)


def test_more_than_three_mirror_poses_use_all_axes():
    setup = paper_mirror_setup(n_tilts=6)
    obs = simulate_mirror_observations(setup, 0.0, np.random.default_rng(0))
    cf = mirror_closed_form(setup.left, obs["left_mirrored"], setup.object_points)
    for est, (n, _) in zip(cf.mirrors, setup.mirrors_left):
        assert np.allclose(est.normal, n, atol=1e-7)
    assert len(cf.axes) == 6 * 5


# -- degenerate setups ---------------------------------------------------------------------------
def _setup_with_normals(normals_deg):
    """Left camera of the paper rig with mirrors tilted by the given (about-x, about-y) angles."""
    setup = paper_mirror_setup(n_tilts=3)
    n0 = np.mean([n for n, _ in setup.mirrors_left], axis=0)
    n0 /= np.linalg.norm(n0)
    M = -np.mean([d for _, d in setup.mirrors_left]) * n0  # a point of the nominal plane
    planes = []
    for ax, ay in normals_deg:
        n = rotation_from_vector(np.radians([ax, ay, 0.0])) @ n0
        planes.append((n, float(-n @ M)))
    setup.mirrors_left = planes
    return setup


def _left_views(setup):
    R, t = setup.pose_cam_target("left")
    P = transform_points(R, t, setup.object_points)
    return [setup.left.project(_reflect(P, n, d)) for n, d in setup.mirrors_left]


def test_fewer_than_three_poses_is_rejected(paper):
    views = _left_views(paper)
    with pytest.raises(ValueError, match="at least 3 mirror poses"):
        mirror_extrinsics(paper.left, views[:2], paper.object_points)


def test_tilts_about_a_single_axis_are_rejected():
    setup = _setup_with_normals([(0.0, 0.0), (3.0, 0.0), (-3.0, 0.0)])
    with pytest.raises(ValueError, match="nearly parallel.*two\\s+different axes"):
        mirror_extrinsics(setup.left, _left_views(setup), setup.object_points)


def test_identical_mirror_poses_are_rejected():
    setup = _setup_with_normals([(0.0, 0.0), (3.0, 0.0), (3.0, 0.01)])
    with pytest.raises(ValueError, match="nearly the same"):
        mirror_extrinsics(setup.left, _left_views(setup), setup.object_points)


def test_collinear_points_are_rejected(paper):
    X = grid_points(6, 1, 93.3)
    views = [np.zeros((6, 2))] * 3
    with pytest.raises(ValueError, match="collinear"):
        mirror_extrinsics(paper.left, views, X)


def test_bad_inputs(paper):
    views = _left_views(paper)
    with pytest.raises(ValueError, match=r"shape \(18, 2\)"):
        mirror_extrinsics(paper.left, [v[:-1] for v in views], paper.object_points)
    bad = [v.copy() for v in views]
    bad[0][3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        mirror_extrinsics(paper.left, bad, paper.object_points)
    with pytest.raises(ValueError, match="list of K"):
        mirror_extrinsics(paper.left, np.concatenate(views), paper.object_points)
    stacked = mirror_extrinsics(paper.left, np.stack(views), paper.object_points)  # (K, N, 2) also accepted
    assert stacked.rms < 1e-6
    with pytest.raises(ValueError, match="Camera"):
        mirror_extrinsics("left", views, paper.object_points)
    with pytest.raises(ValueError, match="far_views\\[0\\]"):
        joint_mirror_stereo(paper.left, paper.right, views, views, paper.object_points,
                            far_views=[(paper.far_object_points, np.zeros((3, 2)), np.zeros((3, 2)))])



def test_rig_bundle_rejects_inconsistent_inputs(paper):
    views = _left_views(paper)
    L = mirror_closed_form(paper.left, views, paper.object_points)
    pose = (L.R_cam_target, L.t_cam_target)
    with pytest.raises(ValueError, match="Camera"):
        RigBundle("left", None, paper.object_points, views, [], [], pose, None, L.mirrors, [], [])
    with pytest.raises(ValueError, match="start planes"):
        RigBundle(paper.left, None, paper.object_points, views, [], [], pose, None, L.mirrors[:-1], [], [])
    with pytest.raises(ValueError, match=r"shape \(18, 2\)"):
        RigBundle(paper.left, None, paper.object_points, [v[:-1] for v in views], [], [], pose, None, L.mirrors, [], [])
    with pytest.raises(ValueError, match="target0"):
        RigBundle(paper.left, None, paper.object_points, views, [], [], None, None, L.mirrors, [], [])
    with pytest.raises(ValueError, match="rig0"):
        RigBundle(paper.left, paper.right, paper.object_points, views, [], [], pose, None, L.mirrors, [], [])

def test_report_mentions_rms_and_mirrors(paper):
    obs = simulate_mirror_observations(paper, NOISE, np.random.default_rng(5))
    res = mirror_extrinsics(paper.left, obs["left_mirrored"], paper.object_points)
    text = res.report()
    assert "RMS" in text and text.count("mirror ") >= 3
    assert res.per_mirror_rms.shape == (3,) and len(res.residuals) == 3
