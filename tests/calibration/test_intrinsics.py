"""Zhang intrinsics through OpenCV with direct and mirrored views, on exact synthetic geometry."""
import numpy as np
import pytest

from calibration.camera import Camera, rotation_from_vector, transform_points
from calibration.intrinsics import MIRROR_FLIP, calibrate_intrinsics
from repro.mirror_setup import grid_points

NOISE = 0.03  # px per coordinate, the noise level
TRUE = Camera(K=[[4050.0, 0, 1172.8], [0, 4050.8, 868.1], [0, 0, 1]], dist=[-0.06, 0.09, 2e-4, -1e-4, 0.0],
              size=(2352, 1728))
X = grid_points(6, 3, 93.3)  # the paper's 6x3 dots, 93.3 mm pitch


def _poses(n_views=15, n_mirrored=3, seed=4):
    """Monitor poses spanning 0.9-3.5 m (the paper's Fig. 6 depth range) with ±35° tilts; the first
    ``n_mirrored`` are views through a mirror (reflection x -> -x of the camera frame)."""
    rng = np.random.default_rng(seed)
    out = []
    for v in range(n_views):
        z = rng.uniform(900, 3500)
        ang = np.radians([rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(-10, 10)])
        half = z * np.array([1176.0, 864.0]) / 4050.0
        t = np.array([rng.uniform(-0.45, 0.45) * half[0], rng.uniform(-0.45, 0.45) * half[1], z])
        out.append((rotation_from_vector(ang), t, v < n_mirrored))
    return out


def _views(poses, rng, noise=NOISE):
    imgs = []
    for R, t, mirrored in poses:
        P = transform_points(R, t, X)
        if mirrored:
            P = P * [-1.0, 1.0, 1.0]  # the virtual target: a left-handed copy
        q = TRUE.project(P)
        assert np.all(q > 0) and np.all(q < [2351, 1727])
        imgs.append(q + rng.normal(0, noise, q.shape))
    return [X] * len(poses), imgs, [m for _, _, m in poses]


def _values(cam):
    return dict(fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy, **dict(zip(("k1", "k2", "p1", "p2", "k3"), cam.dist)))


def test_recovers_truth_within_reported_sigma(rng):
    objs, imgs, mirrored = _views(_poses(), rng)
    res = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored)
    assert len(res.view_indices) == 15 and not res.dropped
    # acceptance: focal length within 0.1 %
    assert abs(res.camera.fx / TRUE.fx - 1) < 1e-3 and abs(res.camera.fy / TRUE.fy - 1) < 1e-3
    est, true = _values(res.camera), _values(TRUE)
    for name in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"):
        # acceptance: every parameter within 3 reported standard deviations
        assert abs(est[name] - true[name]) < 3 * res.std[name], name
    # residual of a 2-D point with σ = 0.03 px per axis: RMS distance 0.03·√2·√(1 − p/2N) ≈ 0.041 px
    assert 0.035 < res.rms < 0.047
    assert res.rms <= 0.05  # acceptance bound
    # mirrored views are handled as right-handed targets: proper rotations, residuals like the others
    for (R, _), m in zip(res.poses, res.mirrored):
        assert np.linalg.det(R) > 0.999999
    assert np.max(res.per_view_rms) < 2.5 * np.median(res.per_view_rms)


def test_mirrored_pose_reproduces_the_virtual_target(rng):
    poses = _poses(n_views=12, n_mirrored=4)
    objs, imgs, mirrored = _views(poses, rng, noise=0.0)
    res = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored)
    for (R, t), (R0, t0, m) in zip(res.poses, poses):
        pts = transform_points(R, t, X @ MIRROR_FLIP.T if m else X)
        truth = transform_points(R0, t0, X) * ([-1.0, 1.0, 1.0] if m else 1.0)
        # noise-free data; OpenCV takes float32 image points (~6e-5 px rounding), i.e. ~1e-3 mm at 3 m
        assert np.max(np.abs(pts - truth)) < 1e-2


def test_reported_sigma_matches_monte_carlo():
    """The reported standard deviations match the spread of the estimates over noise draws."""
    poses = _poses()
    rng = np.random.default_rng(11)
    est, std = [], []
    for _ in range(30):
        objs, imgs, mirrored = _views(poses, rng)
        res = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject=None)
        v = _values(res.camera)
        est.append([v[k] for k in ("fx", "cx", "cy", "k1", "p1")])
        std.append([res.std[k] for k in ("fx", "cx", "cy", "k1", "p1")])
    ratio = np.std(est, axis=0, ddof=1) / np.mean(std, axis=0)
    # 30 draws: the sample standard deviation is known to ±13 % (1σ); accept 0.6–1.5
    assert np.all(ratio > 0.6) and np.all(ratio < 1.5), ratio


def test_outlier_view_is_dropped_with_a_reason(rng):
    objs, imgs, mirrored = _views(_poses(), rng)
    imgs[7] = imgs[7] + rng.normal(0, 1.0, imgs[7].shape)  # a bad detection: 1 px noise
    res = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject=3.0)
    assert [d.index for d in res.dropped] == [7]
    assert "median" in res.dropped[0].reason and res.dropped[0].rms > 0.5
    assert 7 not in res.view_indices
    assert abs(res.camera.fx / TRUE.fx - 1) < 1e-3
    kept = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject=None)
    assert 7 in kept.view_indices and kept.rms > res.rms
    absolute = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject=None, max_view_rms=0.2)
    assert [d.index for d in absolute.dropped] == [7] and "max_view_rms" in absolute.dropped[0].reason
    assert "dropped view 7" in res.report()


def test_distortion_models(rng):
    objs, imgs, mirrored = _views(_poses(), rng)
    res = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, model="radial2")
    assert np.all(res.camera.dist[2:] == 0) and "p1" not in res.std and "k2" in res.std
    rat = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, model="rational")
    assert rat.camera.dist.size == 8 and "k4" in rat.std
    none = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, model="none")
    # the true lens distorts by ~10 px at the corners: without a distortion model the residuals
    # cannot reach the noise level
    assert none.camera.dist.size == 0 and none.rms > 3 * res.rms


@pytest.mark.parametrize("kwargs, message", [
    (dict(model="fisheye"), "model must be one of"),
    (dict(mirrored=[True]), "one flag per view"),
    (dict(image_size=(0, 10)), "image_size must be positive"),
    (dict(reject=0.5), "reject must be > 1"),
])
def test_bad_arguments(rng, kwargs, message):
    objs, imgs, mirrored = _views(_poses(n_views=4), rng)
    args = dict(mirrored=mirrored)
    args.update(kwargs)
    size = args.pop("image_size", TRUE.size)
    with pytest.raises(ValueError, match=message):
        calibrate_intrinsics(objs, imgs, size, **args)


def test_bad_views(rng):
    objs, imgs, _ = _views(_poses(n_views=4), rng)
    with pytest.raises(ValueError, match="at least 3 views"):
        calibrate_intrinsics(objs[:2], imgs[:2], TRUE.size)
    with pytest.raises(ValueError, match="object-point arrays but"):
        calibrate_intrinsics(objs, imgs[:3], TRUE.size)
    with pytest.raises(ValueError, match="rows must correspond"):
        calibrate_intrinsics(objs, [imgs[0][:-1]] + imgs[1:], TRUE.size)
    bad = [q.copy() for q in imgs]
    bad[1][0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        calibrate_intrinsics(objs, bad, TRUE.size)
    with pytest.raises(ValueError, match="not planar"):
        calibrate_intrinsics([X + [0, 0, 1.0] * np.arange(18)[:, None]] * 4, imgs, TRUE.size)
    with pytest.raises(ValueError, match=r"shape \(N, 2\)"):
        calibrate_intrinsics(objs, [q[:, :1] for q in imgs], TRUE.size)


# -- per-view weighting ---------------------------------------------------------------------------
X_DENSE = grid_points(24, 12, 93.3 / 4)  # a denser grid on the same area, measured less precisely


def _mixed_views(rng, n_sparse=12, n_dense=12, sparse_noise=0.014, dense_noise=0.07):
    """Views of the 6x3 target (precise) and of the 24x12 target (5x noisier), some mirrored."""
    poses = _poses(n_views=n_sparse + n_dense, n_mirrored=3, seed=int(rng.integers(1 << 30)))
    objs, imgs, mirrored = [], [], []
    for v, (R, t, m) in enumerate(poses):
        target, noise = (X, sparse_noise) if v < n_sparse else (X_DENSE, dense_noise)
        P = transform_points(R, t, target)
        q = TRUE.project(P * [-1.0, 1.0, 1.0] if m else P)
        objs.append(target)
        imgs.append(q + rng.normal(0, noise, q.shape))
        mirrored.append(m)
    return objs, imgs, mirrored


def test_weighted_bundle_equals_opencv_on_duplicated_points(rng):
    """With fixed weights, minimising Σ w_v |r|² is what OpenCV's unweighted bundle does when each point of
    view v is given w_v times: an independent reference for the weighted solver."""
    import cv2

    from calibration.intrinsics import _calibrate, _estimated_parameters, _model_flags, _weighted_bundle

    objs, imgs, mirrored = _mixed_views(rng, n_sparse=6, n_dense=6)
    used = [(MIRROR_FLIP @ o.T).T if m else o for o, m in zip(objs, mirrored)]
    weights = np.array([9 if o is X else 1 for o in objs])  # σ ratio 3: weight 9
    flags, ndist = _model_flags()["opencv5"]
    dup = _calibrate(cv2, [np.tile(o, (w, 1)) for o, w in zip(used, weights)],
                     [np.tile(q, (w, 1)) for q, w in zip(imgs, weights)], TRUE.size, flags)
    start = _calibrate(cv2, used, imgs, TRUE.size, flags)
    sol, _ = _weighted_bundle(cv2, used, imgs, start, _estimated_parameters(flags, ndist), ndist,
                              sigma=1.0 / np.sqrt(weights))
    # the same minimum: equal weighted cost (ours is not higher) and the same parameters
    cost_dup = sum(float(np.sum(r ** 2)) for r in dup["residuals"])
    cost_ours = sum(w * float(np.sum(r ** 2)) for r, w in zip(sol["residuals"], weights))
    assert cost_ours <= cost_dup * (1 + 1e-7)
    def params(so):
        K, d = so["K"], so["dist"]
        return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *d[:5]])

    sigma = sol["std"][:9]  # fx fy cx cy k1 k2 p1 p2 k3
    assert np.all(np.abs(params(sol) - params(dup)) < 0.005 * sigma)  # both solvers stop within 0.5 % of σ
    assert np.max(np.abs(params(start) - params(dup)) / sigma) > 0.1  # the weights do change the solution


def test_per_view_weighting_estimates_noise_and_improves_mixed_bundles():
    """6x3 views at 0.014 px beside 24x12 views at 0.07 px: per-view weighting finds each view's noise
    (within the χ² spread of ~30-570 degrees of freedom) and beats the equal-weight bundle on cx, cy, fx
    over draws; its reported σ match the observed errors."""
    rng = np.random.default_rng(11)
    err = {"equal": [], "per_view": []}
    sig = []
    for _ in range(6):
        objs, imgs, mirrored = _mixed_views(rng)
        for weighting in err:
            res = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject=None, weighting=weighting)
            e = np.array([res.camera.cx - TRUE.cx, res.camera.cy - TRUE.cy, res.camera.fx - TRUE.fx])
            err[weighting].append(e)
            if weighting == "per_view":
                sparse = np.array([o is X for o in objs])
                assert np.all(np.abs(res.view_sigma[sparse] / 0.014 - 1) < 0.45)
                assert np.all(np.abs(res.view_sigma[~sparse] / 0.07 - 1) < 0.15)
                sig.append([res.std["cx"], res.std["cy"], res.std["fx"]])
    rms = {k: np.sqrt(np.mean(np.square(v), axis=0)) for k, v in err.items()}
    assert np.sqrt(np.mean(rms["per_view"] ** 2)) < 0.8 * np.sqrt(np.mean(rms["equal"] ** 2))
    ratio = rms["per_view"] / np.mean(sig, axis=0)
    assert np.all((ratio > 0.4) & (ratio < 1.8)), ratio  # 6 draws: a loose χ² band on each of 3 parameters


def test_per_view_rejection_compares_views_of_the_same_target(rng):
    objs, imgs, mirrored = _mixed_views(rng, n_sparse=8, n_dense=8)
    imgs[10] = imgs[10] + rng.normal(0, 0.5, imgs[10].shape)  # one bad 24x12 view (7x its target's noise)
    res = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject=3.0, weighting="per_view")
    assert [d.index for d in res.dropped] == [10]
    assert "views of this target" in res.dropped[0].reason
    # the equal-weight rule compares with all views: it also drops good 24x12 views (5x the 6x3 RMS)
    eq = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject=3.0, weighting="equal")
    assert len(eq.dropped) > 1
    assert "noise σ" in res.report() and "weighted by their noise" in res.report()


def test_weighting_bad_input(rng):
    objs, imgs, mirrored = _views(_poses(n_views=5), rng)
    with pytest.raises(ValueError, match="weighting must be"):
        calibrate_intrinsics(objs, imgs, TRUE.size, weighting="robust")
    with pytest.raises(ValueError, match="extra_flags"):
        calibrate_intrinsics(objs, imgs, TRUE.size, weighting="per_view", extra_flags=1)


def test_full_covariance_matches_opencv_and_monte_carlo():
    """camera.covariance: its diagonal is OpenCV's stdDeviationsIntrinsics (computed independently by
    OpenCV's own bundle) and its correlations match the scatter of the estimates over noise draws."""
    poses = _poses()
    rng = np.random.default_rng(5)
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    est, covs = [], []
    for draw in range(30):
        objs, imgs, mirrored = _views(poses, rng)
        res = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject=None)
        cam = res.camera
        assert cam.covariance_names == names and res.covariance is cam.covariance
        if draw == 0:
            np.testing.assert_allclose(np.sqrt(np.diag(cam.covariance)), [res.std[n] for n in names], rtol=0.02)
            w = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject=None, weighting="per_view")
            np.testing.assert_allclose(np.sqrt(np.diag(w.covariance)), [w.std[n] for n in w.camera.covariance_names],
                                       rtol=1e-9)
        est.append([cam.parameter(n) for n in names])
        covs.append(cam.covariance)
    est = np.array(est)
    C_mc = np.cov(est.T)
    C_rep = np.mean(covs, axis=0)
    corr = lambda C: C / np.sqrt(np.outer(np.diag(C), np.diag(C)))  # noqa: E731
    # the strongly correlated pairs (principal point with the tangential terms, fx with fy, the radial terms)
    for a, b in (("cx", "p2"), ("cy", "p1"), ("fx", "fy"), ("k1", "k2"), ("k2", "k3")):
        i, j = names.index(a), names.index(b)
        assert abs(corr(C_rep)[i, j]) > 0.7, (a, b, corr(C_rep)[i, j])  # a real correlation, not noise
        # 30 draws: a sample correlation of 0.7-0.99 is known to ±0.1 or better (1σ); accept 0.3
        assert abs(corr(C_mc)[i, j] - corr(C_rep)[i, j]) < 0.3, (a, b, corr(C_mc)[i, j], corr(C_rep)[i, j])


def test_camera_file_keeps_the_covariance(rng, tmp_path):
    objs, imgs, mirrored = _views(_poses(), rng)
    cam = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored).camera
    cam.save(tmp_path / "cam.json")
    back = Camera.load(tmp_path / "cam.json")
    assert back.covariance_names == cam.covariance_names
    np.testing.assert_array_equal(back.covariance, cam.covariance)
    assert cam.with_parameters(cx=cam.cx + 1).covariance is None
    assert cam.with_parameters(cx=cam.cx + 1, k1=0.5).cx == cam.cx + 1
    with pytest.raises(ValueError, match="one row per name"):
        Camera(K=cam.K, dist=cam.dist, covariance=np.eye(3), covariance_names=("fx", "fy"))
    with pytest.raises(ValueError, match="distinct parameters"):
        Camera(K=cam.K, dist=cam.dist, covariance=np.eye(2), covariance_names=("fx", "k4"))
    with pytest.raises(ValueError, match="symmetric"):
        Camera(K=cam.K, dist=cam.dist, covariance=[[1.0, 2.0], [0.0, 1.0]], covariance_names=("fx", "fy"))
    with pytest.raises(ValueError, match="unknown parameter"):
        cam.with_parameters(s1=1.0)


def _corrupted_views(seed=3, shift_px=3.0):
    """The 15 views of :func:`_poses` (0.03 px noise) with view 5's first row of 6 dots detected ``shift_px``
    off in x (a corrupted detection: no pose or intrinsics explains it)."""
    rng = np.random.default_rng(seed)
    objs, imgs, mirrored = _views(_poses(), rng)
    imgs[5] = imgs[5].copy()
    imgs[5][:6, 0] += shift_px
    return objs, imgs, mirrored


def _intrinsic_error(cam):
    est, true = _values(cam), _values(TRUE)
    return float(np.sqrt(sum((est[k] - true[k]) ** 2 for k in ("fx", "fy", "cx", "cy"))))


@pytest.mark.parametrize("rule", [dict(reject=3.0), dict(reject=None, reject_mad=5.0)])
def test_corrupted_view_is_rejected_and_the_re_solve_is_closer_to_the_truth(rule):
    objs, imgs, mirrored = _corrupted_views()
    kept = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject=None)
    res = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, **rule)
    assert [d.index for d in res.dropped] == [5]
    # its error before: the view's RMS in the solve with every view (0.70 px; the others 0.031-0.049 px)
    assert res.dropped[0].rms_all_views == pytest.approx(kept.per_view_rms[5], rel=1e-9)
    assert res.per_view_rms_all_views[5] == pytest.approx(kept.per_view_rms[5], rel=1e-9)
    # RMS before / after the re-solve
    assert res.rms_all_views == pytest.approx(kept.rms, rel=1e-9)
    assert res.rms < 0.5 * res.rms_all_views
    # the re-solve is the calibration without view 5, and it is closer to the lab's truth
    without = calibrate_intrinsics([o for i, o in enumerate(objs) if i != 5], [q for i, q in enumerate(imgs) if i != 5],
                                   TRUE.size, mirrored=[m for i, m in enumerate(mirrored) if i != 5], reject=None)
    np.testing.assert_allclose(res.camera.K, without.camera.K, rtol=1e-12)
    assert _intrinsic_error(res.camera) < 0.7 * _intrinsic_error(kept.camera)
    assert "view rejection: 1 of 15 views dropped" in res.report()
    assert f"RMS {res.rms_all_views:.4f} px with all 15 views" in res.rejection_summary()


def test_view_rejection_keeps_every_view_of_a_clean_set(rng):
    objs, imgs, mirrored = _views(_poses(), rng)
    for rule in (dict(reject=3.0), dict(reject=None, reject_mad=5.0)):
        res = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, **rule)
        assert not res.dropped and res.rms_all_views == res.rms
        assert "none of 15 views dropped" in res.rejection_summary()


def test_mad_rule_floor_keeps_identical_views():
    """Noise-free views: the per-view RMS are all ~1e-5 px and their MAD ~0; the floor keeps them."""
    objs, imgs, mirrored = _views(_poses(), np.random.default_rng(0), noise=0.0)
    res = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject=None, reject_mad=3.0)
    assert not res.dropped


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan"), "5", True])
def test_reject_mad_must_be_positive(rng, value):
    objs, imgs, mirrored = _views(_poses(), rng)
    with pytest.raises(ValueError, match="reject_mad must be a positive"):
        calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject_mad=value)
