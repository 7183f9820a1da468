"""Outlier-robust IC-GN (kernels/icgn_robust.py, Tracker(robust=True), track_sequence, the CLI).

The ground truth is exact: the evolving-texture sequence of dic.synth (speckles disappear and new
ones appear each frame, the material stretches by a known affine field) and speckle pairs with a
known shift. What is checked is what the refinement is for: subsets whose texture partly changed
are measured against the exact field far better than by plain IC-GN, unchanged subsets are not made
worse, and the refinement is available wherever a user tracks (library, sequences, CLI).
"""
import numpy as np
import pytest

from dic.synth import evolving_sequence, speckle_pair
from kernels.conventions import Status
from kernels.icgn import icgn, n_params, prepare_current, prepare_reference, prepare_subsets
from kernels.icgn_robust import (
    BOX_MAX,
    KURTOSIS_MAX,
    NOISE_GATE,
    icgn_robust,
    reference_noise,
    residual_outliers,
    robust_result,
)

SIZE = 160
HALF = 14  # subset half-size + margin
ACCEPTED = [int(Status.CONVERGED), int(Status.MAX_ITERATIONS)]
ZNCC_MIN = 0.8  # dic.Tracker's default


@pytest.fixture(scope="module")
def evolving():
    # 0.2 % of the speckles replaced per frame; frame 40: 8 % replaced, 8 % stretch
    return evolving_sequence((SIZE, SIZE), 300, stretch_final=0.3, fade_fraction=0.002, noise_sigma=1.0, seed=3)


def _points(seq):
    cx = seq.centre[0]
    hx = ((SIZE - 1) / 2 - HALF) / 1.3
    xs = np.arange(int(np.ceil(cx - hx)), int(cx + hx), 5)
    ys = np.arange(HALF, SIZE - HALF, 5)
    return np.array([(x, y) for y in ys for x in xs], dtype=np.float64)


def _exact_guess(truth, order):
    k = n_params(order)
    g = np.zeros((truth.shape[0], k))
    g[:, 0], g[:, k // 2] = truth[:, 0], truth[:, 1]
    return g


def _error(params, truth, order):
    k = n_params(order)
    return np.hypot(params[:, 0] - truth[:, 0], params[:, k // 2] - truth[:, 1])


def _rms(e):
    return float(np.sqrt(np.mean(e**2)))


@pytest.mark.parametrize("order", [1, 2])
def test_robust_refinement_removes_the_bias_of_changed_speckles(evolving, order):
    # frame 27: 5 % of the speckles replaced, as between two reference updates of the benchmark's auto mode
    k_frame = 27
    pts = _points(evolving)
    ref = prepare_reference(evolving[0].astype(np.float32), device="cpu")
    sub = prepare_subsets(ref, pts, subset=21, order=order)
    cur = prepare_current(evolving[k_frame].astype(np.float32), device="cpu")
    truth = evolving.displacement(pts, k_frame)
    plain = icgn(sub, cur, _exact_guess(truth, order)).numpy()
    ok = np.isin(plain["status"], ACCEPTED) & (plain["zncc"] >= ZNCC_MIN)  # valid, as a Tracker says
    assert ok.mean() > 0.9
    robust = icgn_robust(sub, cur, plain["params"], ok).numpy()
    good = np.isin(robust["status"], ACCEPTED) & (robust["zncc"] >= ZNCC_MIN)
    assert good[ok].mean() > 0.98
    e_plain = _error(plain["params"], truth, order)[ok & good]
    e_robust = _error(robust["params"], truth, order)[ok & good]
    # plain IC-GN: each changed speckle biases its subset (~0.06 px per speckle, bench/sequence.py)
    assert _rms(e_plain) > 0.08
    # robust: the changed pixels are discounted; the target of issue 13 is 0.05 px after 300 frames
    # (per reference segment: 0.05 px / sqrt(11 segments of the benchmark) = 0.015 px)
    assert np.median(e_robust) < 0.01
    assert _rms(e_robust) < 0.2 * _rms(e_plain)
    if order == 1:  # the benchmark's order
        assert _rms(e_robust) < 0.015
    # (2nd order, measured: RMS 0.037 px against 0.234 plain, median 0.008 px; the RMS comes from a few subsets
    # with many changed speckles that reach the iteration limit at 0.2-0.7 px, as their plain result does)
    # most pixels are inliers
    inl = robust["inliers"][ok & good]
    assert 0.5 < np.median(inl) < 1.0
    # the ZNCC reported is the unweighted one at the refined warp: what one plain IC-GN pass measures there
    # (it is computed before the last, sub-tolerance update, like plain IC-GN's own)
    check = icgn(sub, cur, robust["params"], max_iter=1).numpy()["zncc"]
    conv = ok & (robust["status"] == int(Status.CONVERGED))
    np.testing.assert_allclose(robust["zncc"][conv], check[conv], atol=1e-3)
    assert np.median(robust["zncc"][ok & good] - plain["zncc"][ok & good]) > -0.02


@pytest.mark.parametrize("order", [1, 2])
def test_robust_refinement_keeps_unchanged_subsets_accurate(order):
    ref, cur = speckle_pair((128, 128), (0.37, -0.21), noise_sigma=1.0, seed=5)
    pts = np.array([(x, y) for y in range(20, 108, 6) for x in range(20, 108, 6)], dtype=np.float64)
    sub = prepare_subsets(prepare_reference(ref, device="cpu"), pts, subset=21, order=order)
    c = prepare_current(cur, device="cpu")
    plain = icgn(sub, c).numpy()
    robust = icgn_robust(sub, c, plain["params"]).numpy()
    k = n_params(order)
    assert np.all(robust["status"] == int(Status.CONVERGED))
    e_plain = np.hypot(plain["params"][:, 0] - 0.37, plain["params"][:, k // 2] + 0.21)
    e_robust = np.hypot(robust["params"][:, 0] - 0.37, robust["params"][:, k // 2] + 0.21)
    # Gaussian noise only: the weights cost a little efficiency, never accuracy
    assert _rms(e_robust) < 0.01
    assert _rms(e_robust) < 1.5 * _rms(e_plain) + 1e-3
    # the scale estimate is consistent: most of the subset stays in (Tukey c = 3 keeps ~80 % of the weight)
    assert np.median(robust["inliers"]) > 0.7


def test_inactive_points_are_left_alone():
    ref, cur = speckle_pair((96, 96), (0.5, 0.25), noise_sigma=1.0, seed=2)
    pts = np.array([(40.0, 40.0), (50.0, 50.0), (60.0, 40.0)])
    sub = prepare_subsets(prepare_reference(ref, device="cpu"), pts, subset=21, order=1)
    guess = np.array([[0.4, 0, 0, 0.2, 0, 0]] * 3, dtype=np.float32)
    out = robust_result(3, 6, "cpu")
    res = icgn_robust(sub, prepare_current(cur, device="cpu"), guess, np.array([True, False, True]), out=out).numpy()
    assert res["status"][1] == int(Status.NOT_COMPUTED)
    np.testing.assert_array_equal(res["params"][1], guess[1])
    assert np.isnan(res["zncc"][1]) and np.isnan(res["inliers"][1]) and res["iterations"][1] == 0
    assert np.all(res["status"][[0, 2]] == int(Status.CONVERGED))
    assert np.all(np.abs(res["params"][[0, 2], 0] - 0.5) < 0.02)


def test_bad_inputs_are_refused_with_a_message():
    ref, cur = speckle_pair((64, 64), (0.0, 0.0), seed=1)
    sub = prepare_subsets(prepare_reference(ref, device="cpu"), [(32.0, 32.0)], subset=15, order=1)
    c = prepare_current(cur, device="cpu")
    g = np.zeros((1, 6))
    with pytest.raises(ValueError, match="ReferenceSubsets"):
        icgn_robust("subsets", c, g)
    with pytest.raises(ValueError, match="CurrentImage"):
        icgn_robust(sub, cur, g)
    with pytest.raises(ValueError, match="guess must have shape"):
        icgn_robust(sub, c, np.zeros((2, 6)))
    with pytest.raises(ValueError, match="active"):
        icgn_robust(sub, c, g, np.ones(3, bool))
    with pytest.raises(ValueError, match="min_inliers"):
        icgn_robust(sub, c, g, min_inliers=1.0)
    with pytest.raises(ValueError, match="max_iter"):
        icgn_robust(sub, c, g, max_iter=0)
    with pytest.raises(ValueError, match="NaN"):
        icgn_robust(sub, c, np.full((1, 6), np.nan))


def _frames(seq, ks):
    return [np.clip(np.round(seq[k]), 0, 255).astype(np.uint8) for k in ks]


def test_tracker_robust_on_every_path(evolving):
    from dic._track import Tracker

    k_frame = 40
    ref, cur = _frames(evolving, [0, k_frame])
    pts = _points(evolving)
    truth = evolving.displacement(pts, k_frame)
    plain = Tracker(ref, points=pts, robust=False, device="cpu")  # plain IC-GN (the default is "adaptive")
    robust = Tracker(ref, points=pts, robust=True, device="cpu")
    guess = _exact_guess(truth, 1)
    f_plain = plain.track(cur, guess=guess)  # the device-resident frame path (uint8, no search)
    f_frame = robust.track(cur, guess=guess)
    f_host = robust.track(cur.astype(np.float64), guess=guess, search="zncc")  # the general path (a search)
    e_plain = np.hypot(f_plain.u - truth[:, 0], f_plain.v - truth[:, 1])[f_plain.valid]
    for f in (f_frame, f_host):
        assert f.valid.mean() > 0.9
        e = np.hypot(f.u - truth[:, 0], f.v - truth[:, 1])[f.valid]
        assert _rms(e) < 0.2 * _rms(e_plain)
    # the same refinement from the same converged start on both paths
    both = f_frame.valid & f_host.valid
    assert np.max(np.abs(f_frame.u[both] - f_host.u[both])) < 5e-3
    with pytest.raises(ValueError, match="robust must be True or False"):
        Tracker(ref, points=pts, robust="yes")


def test_track_sequence_and_cli_robust(evolving, tmp_path):
    from click.testing import CliRunner

    from dic.cli import main
    from dic.sequence import track_sequence
    from dic.store import ResultReader
    from kernels.images import write_image

    ks = [0, 14, 27]
    frames = _frames(evolving, ks)
    pts = _points(evolving)
    out = tmp_path / "robust.h5"
    track_sequence(frames[0], frames[1:], out, reference="fixed", points=pts, robust=True, device="cpu")
    with ResultReader(out) as rd:
        assert rd.settings.get("robust") is True
        fields = [fr for _, fr in rd.iter_frames()]
    last = fields[-1]
    truth = evolving.displacement(np.asarray(last.points), ks[-1])
    valid = np.asarray(last.valid)
    e = np.hypot(np.asarray(last.u) - truth[:, 0], np.asarray(last.v) - truth[:, 1])[valid]
    assert valid.mean() > 0.9 and _rms(e) < 0.015
    paths = []
    for k, img in zip(ks, frames):
        p = tmp_path / f"f{k:03d}.png"
        write_image(p, img)
        paths.append(str(p))
    res = CliRunner().invoke(main, ["track", *paths, "-o", str(tmp_path / "cli.h5"), "--robust", "--step", "8",
                                    "--strain-window", "0", "-q", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    with ResultReader(tmp_path / "cli.h5") as rd:
        assert rd.settings.get("robust") is True


# -- adaptive robust IC-GN: the residual test and the default ----------------------------------------------


def _changed_speckles_near(seq, k, pts, subset=21):
    """Exact truth of the texture change: per POI, the speckles alive in frame 0 or frame k but not both whose
    centres lie within reach of its subset (the subset's square grown by the mean radius and 2 blur sigmas)."""
    from scipy.spatial import cKDTree

    p = seq.pattern
    changed = seq.alive(0) != seq.alive(k)
    reach = subset // 2 + p.radius + 2 * p.blur
    return np.asarray(cKDTree(p.centres[changed]).query_ball_point(pts, reach, p=np.inf, return_length=True))


def test_residual_statistics_are_those_of_the_subset_residuals():
    # an integer shift: the warped current subset is the current image's pixels, so the least-squares residual
    # e = (f - fm) - a (g - fm) - b and its RMS and kurtosis follow from the pixels in NumPy
    ref, cur = speckle_pair((96, 96), (3.0, -2.0), noise_sigma=2.0, seed=4)
    cur = cur.copy()
    cur[44:48, 50:53] = 250.0  # a bright blob: outliers in the subsets that hold it
    pts = np.array([(40.0, 40.0), (50.0, 50.0), (60.0, 44.0), (30.0, 60.0)])
    sub = prepare_subsets(prepare_reference(ref, device="cpu"), pts, subset=21, order=1)
    params = np.array([[3.0, 0, 0, -2.0, 0, 0]] * 4)
    stats = residual_outliers(sub, prepare_current(cur, device="cpu"), params, with_scale=True, box_max=BOX_MAX)
    for i, (x, y) in enumerate(pts.astype(int)):
        f = ref[y - 10:y + 11, x - 10:x + 11].astype(np.float64)
        g = cur[y - 12:y + 9, x - 7:x + 14].astype(np.float64)  # (x + 3, y - 2)
        A = np.column_stack([g.ravel(), np.ones(g.size)])
        e = f.ravel() - A @ np.linalg.lstsq(A, f.ravel(), rcond=None)[0]
        np.testing.assert_allclose(stats.rms[i], np.sqrt(np.sum(e**2) / (e.size - 2)), rtol=1e-4)
        np.testing.assert_allclose(stats.kurtosis[i], e.size * np.sum(e**4) / np.sum(e**2) ** 2, rtol=1e-3)
        # the MAD rule's fraction: pixels beyond 3 x 1.4826 x median |e| (the kernel reads the median from a
        # histogram with bins of 2^(1/3): within a bin's width of the exact fraction)
        s = 1.4826 * np.median(np.abs(e))
        lo, hi = np.mean(np.abs(e) > 3 * s * 2 ** (1 / 3)), np.mean(np.abs(e) > 3 * s / 2 ** (1 / 3))
        assert lo - 1e-3 <= stats.beyond[i] <= hi + 1e-3
        if i < 2:  # the box statistic: the largest |3 x 3 box sum of e| over 3 x the RMS (subsets with the blob)
            E = e.reshape(21, 21)
            boxes = sum(E[dy:dy + 19, dx:dx + 19] for dy in range(3) for dx in range(3))
            np.testing.assert_allclose(stats.box[i], np.abs(boxes).max() / (3 * np.sqrt(np.sum(e**2) / (e.size - 2))),
                                       rtol=1e-3)
    # the blob (in reference coordinates x 47-49, y 46-49) is in the subsets of the first two POIs: their
    # kurtosis is far above a Gaussian's 3, the others' is not (and their box statistic is not computed)
    assert stats.flagged.tolist() == [True, True, False, False]
    assert np.all(stats.kurtosis[[2, 3]] < 4.0) and np.all(stats.kurtosis[[0, 1]] > 2 * KURTOSIS_MAX)
    assert np.all(stats.box[[0, 1]] > 2 * BOX_MAX) and np.all(np.isnan(stats.box[[2, 3]]))
    # inactive POIs are left out
    some = residual_outliers(sub, prepare_current(cur, device="cpu"), params, np.array([0, 1, 0, 1]))
    assert np.isnan(some.kurtosis[0]) and not some.flagged[0] and some.flagged[1] and not some.flagged[3]


def test_residual_test_flags_the_subsets_whose_texture_changed(evolving):
    # frame 10: 2 % of the speckles replaced; exact truth of which subsets hold a changed speckle
    k_frame = 10
    pts = _points(evolving)
    sub = prepare_subsets(prepare_reference(evolving[0].astype(np.float32), device="cpu"), pts, subset=21, order=1)
    cur = prepare_current(evolving[k_frame].astype(np.float32), device="cpu")
    truth = evolving.displacement(pts, k_frame)
    plain = icgn(sub, cur, _exact_guess(truth, 1)).numpy()
    ok = np.isin(plain["status"], ACCEPTED) & (plain["zncc"] >= ZNCC_MIN)
    flagged = residual_outliers(sub, cur, plain["params"], ok).flagged
    changed = _changed_speckles_near(evolving, k_frame, pts)
    assert np.count_nonzero(ok & (changed == 0)) >= 100 and np.count_nonzero(ok & (changed >= 2)) >= 100
    # measured (KURTOSIS_MAX 4): 0.995 of the subsets with >= 2 changed speckles flagged, 0.83 of those with one
    # (some of them only touch the subset's edge), 0.008 of those with none
    assert flagged[ok & (changed >= 2)].mean() > 0.95
    assert flagged[ok & (changed == 1)].mean() > 0.6
    assert flagged[ok & (changed == 0)].mean() < 0.05
    # the subsets left unflagged are those plain IC-GN measures well (measured 0.0034 px RMS against 0.071)
    e = _error(plain["params"], truth, 1)
    assert _rms(e[ok & ~flagged]) < 0.01 and _rms(e[ok & flagged]) > 0.05


def test_adaptive_is_the_default_and_keeps_clean_subsets_bitwise(evolving):
    from dic._track import Tracker, track

    k_frame = 10
    ref, cur = _frames(evolving, [0, k_frame])
    pts = _points(evolving)
    truth = evolving.displacement(pts, k_frame)
    guess = _exact_guess(truth, 1)
    plain = Tracker(ref, points=pts, robust=False, device="cpu")
    defaults = Tracker(ref, points=pts, device="cpu")
    assert defaults.robust == "adaptive" and defaults.check_outliers and not plain.check_outliers
    # the refinement alone (the neighbour check, on by default with robust IC-GN, may flag some valid POIs)
    default = Tracker(ref, points=pts, check_outliers=False, device="cpu")
    for path in ("frame", "host"):  # the device-resident frame path (uint8) and the general path (float64)
        image = cur if path == "frame" else cur.astype(np.float64)
        search = None if path == "frame" else "prior"
        f_plain = plain.track(image, guess=guess, search=search)
        f_adapt = default.track(image, guess=guess, search=search)
        same = np.all(f_plain.params == f_adapt.params, axis=1)
        for name in ("zncc", "iterations", "status"):
            same_here = getattr(f_plain, name) == getattr(f_adapt, name)
            assert np.all(same_here | ~same)
        refined = f_adapt.extra["robust_refined"]
        # every POI but the refined ones keeps the plain result bit for bit
        assert np.count_nonzero(~same) <= refined < pts.shape[0]
        assert "robust_refined" not in f_plain.extra
        e_plain = np.hypot(f_plain.u - truth[:, 0], f_plain.v - truth[:, 1])[f_plain.valid]
        e_adapt = np.hypot(f_adapt.u - truth[:, 0], f_adapt.v - truth[:, 1])[f_adapt.valid]
        assert f_adapt.valid.mean() > 0.9 and _rms(e_adapt) < 0.2 * _rms(e_plain)
    f = track(ref, cur, points=pts, guess=guess, check_outliers=False, device="cpu")
    assert f.extra["robust_refined"] == refined
    with pytest.raises(ValueError, match="robust must be True or False, or 'adaptive'"):
        Tracker(ref, points=pts, robust="sometimes")


@pytest.mark.parametrize("order", [1, 2])
def test_adaptive_leaves_clean_images_at_plain_precision(order):
    # Gaussian noise only: few subsets flagged, the displacement error's std within 5 % of plain IC-GN
    from dic._track import Tracker

    ref, cur = speckle_pair((160, 160), lambda x, y: (0.3 + 0.005 * (x - 80), -0.2 + 0.004 * (y - 80)),
                            noise_sigma=2.0, seed=7)
    u_true = lambda f: 0.3 + 0.005 * (f.points[:, 0] - 80)  # noqa: E731
    v_true = lambda f: -0.2 + 0.004 * (f.points[:, 1] - 80)  # noqa: E731
    out = {}
    for robust in (False, "adaptive"):
        f = Tracker(ref, step=6, order=order, robust=robust, device="cpu").track(cur, guess=(0.3, -0.2))
        err = np.concatenate([(f.u - u_true(f))[f.valid], (f.v - v_true(f))[f.valid]])
        out[robust] = (np.std(err), f)
    assert out["adaptive"][1].extra["robust_refined"] <= 0.05 * out["adaptive"][1].n_points
    assert out["adaptive"][0] <= 1.05 * out[False][0]


@pytest.mark.parametrize("noise", [0.5, 4.0])
@pytest.mark.parametrize("order", [1, 2])
def test_adaptive_default_keeps_plain_precision_from_low_to_high_noise(noise, order):
    # clean speckle pairs at both ends of the 0.5-4 GL range (issue 26 target: std within 5 % of plain IC-GN);
    # measured (bench/robust.py, 512^2): no subset refined at any of 0.5, 1, 2, 4 GL
    from dic._track import Tracker

    field = lambda x, y: (0.3 + 0.005 * (x - 80), -0.2 + 0.004 * (y - 80) + 0.0 * x)  # noqa: E731
    ref, cur = speckle_pair((160, 160), field, noise_sigma=noise, seed=17)
    out = {}
    for robust in (False, "adaptive"):
        f = Tracker(ref, step=6, order=order, robust=robust, check_outliers=False, device="cpu").track(cur, guess=(0.3, -0.2))
        u, v = field(f.points[:, 0], f.points[:, 1])
        out[robust] = (np.std(np.concatenate([(f.u - u)[f.valid], (f.v - v)[f.valid]])), f)
    assert out["adaptive"][1].extra["robust_refined"] <= 0.01 * out["adaptive"][1].n_points
    assert out["adaptive"][0] <= 1.05 * out[False][0]


def test_reference_noise_is_the_noise_of_white_noise_and_the_subset_std():
    # Immerkaer's estimator is unbiased on white noise: a flat image plus Gaussian noise of known std
    rng = np.random.default_rng(5)
    img = 100.0 + 3.0 * rng.standard_normal((120, 140))
    centres = np.array([(x, y) for y in range(15, 106, 10) for x in range(15, 126, 10)])
    sigma, std = reference_noise(img, centres, 21)
    # unbiased over the 120 subsets; each from 441 correlated pixels scatters by a few % (measured sd 4 %)
    assert abs(np.mean(sigma) / 3.0 - 1) < 0.02 and np.all(np.abs(sigma / 3.0 - 1) < 0.2)
    for k, (x, y) in enumerate(centres):
        np.testing.assert_allclose(std[k], img[y - 10:y + 11, x - 10:x + 11].std(), rtol=1e-9)
    with pytest.raises(ValueError, match="odd integer"):
        reference_noise(img, centres, 20)


def _lab_render_pair(size=256, samples=2):
    """A speckled plane seen obliquely by a 16 mm / 7.4 um camera at 1 m (the camera and the pattern of
    bench/stereo.py rates, 1.7 px speckles), translated by (0.4, -0.25, 1.5) mm: 8-bit, anti-aliased with
    ``samples`` per pixel, no sensor noise."""
    from dataclasses import replace

    from dic.lab import Displacement, LabCamera, Scene, SpecklePlane, render
    from dic.synth import make_speckle

    cam = LabCamera.from_lens(name="cam", size=(size, size), focal_length_mm=16.0, f_number=float("inf"),
                              focus_distance_mm=1000.0, position=(-150.0, 0.0, 0.0), look_at_point=(0.0, 0.0, 1000.0),
                              exposure_dn=200.0, bit_depth=8)
    speckle = make_speckle(region=(-5, -5, 155, 155), radius=0.8, density=0.5, bits=None, seed=3)
    plane = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=(150.0, 150.0),
                                speckle=speckle)
    images = []
    for k in range(2):
        t_local = plane.R_world_surface.T @ (k * np.array([0.4, -0.25, 1.5]))
        disp = Displacement(np.broadcast_to(t_local, (2, 2, 3)).copy(), (0.0, 0.0), (150.0, 150.0))
        images.append(render(Scene(cameras=[cam], planes=[replace(plane, displacement=disp)]), 0, samples=samples,
                             seed=100 * k))
    return images


@pytest.mark.parametrize("order", [1, 2])
def test_adaptive_leaves_smooth_renders_alone(order):
    # the images where the kurtosis test alone engaged on most subsets (issue 26): anti-aliased renders without
    # sensor noise, whose edge residuals are heavy-tailed (kurtosis about 5) but spread, not one compact blob
    from dic._track import Tracker

    ref, cur = _lab_render_pair()
    plain = Tracker(ref, step=8, order=order, robust=False, check_outliers=False, device="cpu").track(cur)
    tracker = Tracker(ref, step=8, order=order, check_outliers=False, device="cpu")  # robust: the default
    adaptive = tracker.track(cur)
    assert tracker.robust == "adaptive" and plain.valid.mean() > 0.9
    # measured: 0 of 900 refined (1024^2 renders of bench/stereo.py rates: 0 of 15 876), the result plain's bit for bit
    assert adaptive.extra["robust_refined"] <= 0.01 * adaptive.n_points
    same = np.all(adaptive.params == plain.params, axis=1) | np.all(np.isnan(plain.params), axis=1)
    assert np.count_nonzero(~same) <= adaptive.extra["robust_refined"]
    # what the new gates spare: the kurtosis rule alone flags most of the valid subsets here (measured 0.91)
    ok = plain.valid
    kurtosis_only = residual_outliers(tracker.correlator.subsets, prepare_current(cur, device="cpu"),
                                      plain.params.astype(np.float32), ok, box_max=None).flagged
    assert kurtosis_only[ok].mean() > 0.5
    # the noise gate: the residual over sqrt(2) x the reference's roughness stays below NOISE_GATE on most subsets
    sigma, std = reference_noise(ref, tracker.correlator.subsets.table.centres.numpy(), 21)
    rms = std * np.sqrt(np.clip(1 - plain.zncc**2, 0, None) * 441 / 439)
    assert np.mean((rms / (np.sqrt(2) * sigma))[ok] > NOISE_GATE) < 0.05


def test_default_sequence_on_an_evolving_texture_meets_the_target(tmp_path):
    # issue 26: an evolving texture (2 % of the speckles replaced per frame) tracked with --reference auto and the
    # defaults ends at <= 0.05 px RMS against the exact Lagrangian truth (512^2, 60 frames, 30 %: 0.048 px, docs/dic2d.md);
    # here 160^2, 30 frames, 15 % stretch (measured: defaults 0.021 px, plain IC-GN 0.37 px). The composed-result check
    # is off: against frame 0 the replaced speckles fail it by design (docs/dic2d.md, "Robust correlation")
    from dic.sequence import track_sequence
    from dic.store import ResultReader

    n = 30
    seq = evolving_sequence((SIZE, SIZE), n, stretch_final=0.15, fade_fraction=0.02, noise_sigma=1.0, seed=11)
    frames = [seq[k] for k in range(n)]
    cx = seq.centre[0]
    hx = ((SIZE - 1) / 2 - 12) / 1.15
    roi = (int(np.ceil(cx - hx)), 12, int(np.floor(cx + hx)), SIZE - 13)
    rms = {}
    for name, options in (("defaults", {}), ("plain", {"robust": False})):
        out = tmp_path / f"{name}.h5"
        track_sequence(frames[0], frames[1:], out, reference="auto", roi=roi, device="cpu", verify_composed=False,
                       **options)
        with ResultReader(out) as reader:
            assert reader.settings["robust"] == ("adaptive" if name == "defaults" else False)
            fr = reader.read_frame(n - 1)
            truth = seq.displacement(np.asarray(fr.points, np.float64), n - 1)
            valid = np.asarray(fr.valid, bool)
            assert valid.mean() > 0.85
            rms[name] = _rms(np.hypot(np.asarray(fr.u) - truth[:, 0], np.asarray(fr.v) - truth[:, 1])[valid])
    assert rms["defaults"] <= 0.05 and rms["plain"] > 0.2
