"""Smoke test of the paper-reproduction chain (repro/experiments.py) at a very small scale.

Rendered calibration images → Specula's calibration (phase dots, intrinsics from direct + mirrored
views, mirror extrinsics) → rendered measurement images → dot triangulation and stereo DIC. The
ground truth of the virtual lab is used here only as the independent reference the results are
checked against (the chain itself never sees it).
"""
import numpy as np
import pytest

from repro.experiments import (
    DOT_SPACING_MM,
    Experiment,
    ExperimentConfig,
    RenderCache,
    dot_test,
    plane_deviation,
    run_deformation_test,
)


@pytest.fixture(scope="module")
def chain():
    cfg = ExperimentConfig(scale=0.25, samples=1, direct_distances_mm=(1100.0, 1600.0, 2400.0),
                           far_view=True, checkerboard=False, positions=(13,), step=4)
    exp = Experiment(cfg, cache=None, log=lambda m: None)
    cal = exp.calibrate()
    return exp, cal


def test_calibration_from_rendered_images(chain):
    exp, cal = chain
    rms = cal.figures["reprojection_rms_px"]
    # phase-dot centres on 8-bit noisy renders are good to a few 0.01 px; at 1/4 resolution with one
    # sample per pixel, 0.25 px RMS still flags any gross error (a wrong id or flipped mirror view
    # gives several px)
    assert rms["left"] < 0.25 and rms["right"] < 0.25
    # independent reference: the lab's baseline (1650 mm). The paper-faithful mirror method at this
    # resolution (32 dots, 3 tilts) is good to ~0.1 % (docs/calibration.md: 0.015 % at full resolution
    # with exact points); 1 % catches frame or sign errors, which give tens of %
    assert abs(cal.rig.baseline - 1650.0) < 16.5
    true_left = exp.lab.cameras[0].camera
    # focal length within 1 % of the lab's lens (the intrinsic bundle spans 1.1-2.4 m plus mirrors;
    # measured -0.5 % with this tiny design, 3 direct views and 1 sample per pixel)
    assert abs(cal.rig.left.K[0, 0] / true_left.K[0, 0] - 1) < 0.01


def test_dots_and_deformation_at_the_crossing(chain):
    exp, cal = chain
    dl, dr = exp.dot_views(13)
    r = dot_test(cal.rig, dl, dr, exp.dot_target)
    assert len(r["distances_mm"]) == 10  # 6 horizontal + 4 vertical neighbour pairs of the 4 x 2 grid
    # this tiny calibration (3 direct views, 1 sample per pixel, 5 distortion coefficients) leaves the
    # scale uncertain by a few 0.1 % (measured +0.17 %; +1.1 % with 4 direct views and no far view; the bench's 8 views
    # and 4 samples give 0.002-0.05 %);
    # 2 % still catches convention errors (a wrong pitch, mirror flip or pose inversion gives > 10 %)
    assert abs(r["distances_mm"].mean() - DOT_SPACING_MM) < 0.02 * DOT_SPACING_MM
    # the triangulated dots are coplanar (a flat monitor): 0.5 mm ~ a tenth of a pixel at 5.8 mm/px
    dev, _ = plane_deviation(r["points"])
    assert np.abs(dev).max() < 0.5
    de = run_deformation_test(exp, cal.rig, (dl, dr), log=lambda m: None)
    assert de["valid"] > 0.8 * de["points"] > 20
    # imposed u amplitude 24 monitor px; 21 px subsets at 1/4 resolution span ~390 monitor px of a
    # 600 px period, so 2nd-order subsets smooth the peak (the bench measured 6 %): accept 15 %
    assert abs(de["fitted_amplitude_px"] - 24.0) < 0.15 * 24.0
    # spurious in-plane v and out-of-plane w average to ~0: at 1/4 resolution the bench measured
    # v -0.04 +- 0.54 and w -0.16 +- 2.8 monitor px per point; over > 20 points the mean of w has a
    # standard error < 0.7 px, so |mean| < 2 px (and 1 px for v) fails only on a systematic error
    assert abs(de["v_mean_px"]) < 1.0 and abs(de["w_mean_px"]) < 2.0


def test_render_cache_round_trip(tmp_path):
    cache = RenderCache(tmp_path)
    calls = []

    def make():
        calls.append(1)
        return np.arange(6, dtype=np.uint8).reshape(2, 3)

    a = cache.get({"k": 1}, "x", make)
    b = cache.get({"k": 1}, "x", make)
    c = cache.get({"k": 2}, "x", make)
    assert len(calls) == 2 and cache.hits == 1
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, c)


def test_config_validation_and_speckle_cache_key():
    for bad in (dict(samples=0), dict(samples=2.5), dict(speckle_samples=0), dict(scale=0.0)):
        with pytest.raises(ValueError, match="ExperimentConfig"):
            ExperimentConfig(**bad)
    base = ExperimentConfig(samples=4)
    # speckle views rendered with more samples get their own cache entries; the calibration views' key is unchanged
    more = ExperimentConfig(samples=4, speckle_samples=64)
    assert base.speckle_key() == base.key() == more.key()
    assert more.speckle_key() != more.key() and more.speckle_key()["samples"] == 64
    assert more.speckle_render_samples == 64 and base.speckle_render_samples == 4


def test_direct_calibration_views_reach_the_image_corners():
    """The default direct views put the calibration target at every corner and edge of each image (so
    the lens distortion is measured where the corner test positions image, not extrapolated there)."""
    import cv2

    from repro.experiments import MONITOR_PITCH_MM

    exp = Experiment(ExperimentConfig(scale=0.25, samples=1), cache=None, log=lambda m: None)
    t = exp.calib_target
    lo, hi = t._lit_lo * MONITOR_PITCH_MM, t._lit_hi * MONITOR_PITCH_MM
    lit = np.array([[lo[0], lo[1], 0.0], [hi[0], lo[1], 0.0], [hi[0], hi[1], 0.0], [lo[0], hi[1], 0.0]])
    for ci, cam in enumerate(exp.lab.cameras):
        W, H = cam.size
        polys = [cam.project(lit @ R.T + tt).astype(np.float32) for R, tt in exp.direct_poses(ci)]
        for poly in polys:  # every view fits in the image
            assert np.all(poly > 0) and np.all(poly < [W - 1, H - 1])
        # points 12 % of the width/height in from each corner and from the middle of each edge
        probes = [(fx * W, fy * H) for fx in (0.12, 0.5, 0.88) for fy in (0.12, 0.5, 0.88) if (fx, fy) != (0.5, 0.5)]
        for p in probes:
            assert any(cv2.pointPolygonTest(poly.reshape(-1, 1, 2), p, False) >= 0 for poly in polys), (cam.name, p)
