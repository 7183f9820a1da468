"""Leave-p-out stability of the intrinsics and the stereo rig (calibration/stability.py), on exact
synthetic geometry with known truth (the views of tests/calibration/test_intrinsics.py; a 480 x 360 px rig with
f = 700 px and a 300 mm baseline seeing a 9 x 6 board at 1.1-1.5 m)."""
import numpy as np
import pytest
from test_intrinsics import TRUE, _corrupted_views, _poses, _views
from test_verify_distance import LEFT, R_RL, RIGHT, T_RL

from calibration.camera import rotation_from_vector
from calibration.intrinsics import calibrate_intrinsics
from calibration.stability import intrinsics_stability, leave_p_out, leave_p_out_subsets, rig_parameters, rig_stability
from calibration.stereo import StereoRig
from repro.mirror_setup import grid_points


def test_subsets_all_or_seeded_random():
    subsets, exhaustive = leave_p_out_subsets(6, 2, max_subsets=20)
    assert exhaustive and len(subsets) == 15 and len(set(subsets)) == 15
    a, ex_a = leave_p_out_subsets(15, 3, max_subsets=20, seed=5)
    b, _ = leave_p_out_subsets(15, 3, max_subsets=20, seed=5)
    c, _ = leave_p_out_subsets(15, 3, max_subsets=20, seed=6)
    assert not ex_a and a == b and a != c and len(set(a)) == 20
    assert all(len(s) == 3 and len(set(s)) == 3 and max(s) < 15 for s in a)
    with pytest.raises(ValueError, match="p must be between 1"):
        leave_p_out_subsets(5, 5)


def test_intrinsics_leave_one_out_on_a_good_set_moves_every_parameter_less_than_2_sigma():
    objs, imgs, mirrored = _views(_poses(), np.random.default_rng(1))
    full = calibrate_intrinsics(objs, imgs, TRUE.size, mirrored=mirrored, reject=None)
    st = intrinsics_stability(objs, imgs, TRUE.size, mirrored=mirrored, p=1)
    assert st.exhaustive and len(st.left_out) == 15 and not st.failed
    assert st.names == ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    np.testing.assert_allclose(st.reference[:4], [full.camera.fx, full.camera.fy, full.camera.cx, full.camera.cy])
    assert np.all(np.isfinite(st.std)) and np.all(st.std > 0)
    # leaving one of 15 good views out moves a parameter by a fraction of its σ (measured: up to 1.06 σ, for
    # cx and p2 when the most tilted view goes; fx 0.47 σ)
    sigma = np.array([full.std[n] for n in st.names])
    assert np.all(st.max_deviation < 2.0 * sigma), dict(zip(st.names, st.max_deviation / sigma))
    report = st.report()
    assert "leave-1-out stability of the intrinsics: 15 views, every subset" in report and "max deviation" in report


def test_intrinsics_leave_one_out_points_at_the_corrupted_view():
    """View 5 has a row of dots detected 3 px off: leaving it out moves the principal point the most."""
    objs, imgs, mirrored = _corrupted_views()
    st = intrinsics_stability(objs, imgs, TRUE.size, mirrored=mirrored, p=1)
    assert st.worst_subset("cx") == (5,)
    d = st.to_dict()["parameters"]["cx"]
    assert d["worst_left_out"] == [5] and d["unit"] == "px"


def test_intrinsics_leave_three_out_random_subsets_are_repeatable():
    objs, imgs, mirrored = _views(_poses(), np.random.default_rng(1))
    a = intrinsics_stability(objs, imgs, TRUE.size, mirrored=mirrored, p=3, max_subsets=6, seed=3)
    b = intrinsics_stability(objs, imgs, TRUE.size, mirrored=mirrored, p=3, max_subsets=6, seed=3)
    assert not a.exhaustive and a.left_out == b.left_out and len(a.left_out) == 6
    np.testing.assert_array_equal(a.samples, b.samples)
    assert "6 random subsets (seed 3)" in a.report()


def _stereo_views(n=8, noise=0.02, seed=2):
    rig = StereoRig(LEFT, RIGHT, R_RL, T_RL)
    X = grid_points(9, 6, 30.0)
    rng = np.random.default_rng(seed)
    objs, ql, qr = [], [], []
    for _ in range(n):
        R = rotation_from_vector(np.radians([rng.uniform(-25, 25), rng.uniform(-25, 25), rng.uniform(-10, 10)]))
        t = np.array([rng.uniform(-80, 0), rng.uniform(-40, 40), rng.uniform(1100, 1500)]) - R @ X.mean(0)
        a, b = rig.project(X @ R.T + t)
        assert np.all(a > 0) and np.all(a < [479, 359]) and np.all(b > 0) and np.all(b < [479, 359])
        objs.append(X)
        ql.append(a + rng.normal(0, noise, a.shape))
        qr.append(b + rng.normal(0, noise, b.shape))
    return objs, ql, qr


def test_rig_leave_one_out_spread_is_small_and_every_re_solve_near_the_truth():
    objs, ql, qr = _stereo_views()
    st = rig_stability(LEFT, RIGHT, objs, ql, qr, p=1)
    assert st.exhaustive and len(st.left_out) == 8 and not st.failed
    assert st.names == ("rot_x", "rot_y", "rot_z", "t_x", "t_y", "t_z", "baseline")
    assert np.all(np.isfinite(st.std))
    # 0.02 px noise at f = 700 px is 0.0016 deg per point; 7 views x 54 points x 2 cameras: measured spread
    # 0.0006-0.0011 deg (std), max deviation 0.0022 deg and 0.05 mm; bounds 0.01 deg and 0.3 mm
    assert np.all(st.max_deviation[:3] < 0.01) and np.all(st.max_deviation[3:] < 0.3)
    truth = rig_parameters(R_RL, T_RL)[2]
    assert np.all(np.abs(st.samples[:, :3] - truth[:3]) < 0.01)
    assert np.all(np.abs(st.samples[:, 3:] - truth[3:]) < 0.3)


def test_generic_leave_p_out_records_failures():
    def solve(keep):
        if 2 not in keep:
            raise ValueError("view 2 is needed")
        return ["a"], ["mm"], [float(len(keep))]

    st = leave_p_out(4, solve, p=1)
    assert [s for s, _ in st.failed] == [(2,)] and st.left_out == [(0,), (1,), (3,)]
    assert st.max_deviation[0] == 1.0 and "failed: view 2 is needed" in st.report()
