"""Dot-centre extraction, dense decoding and OpenCV detectors (calibration/detect/) on
synthetic camera views with exact ground truth (calibration.targets.render_view: every camera
pixel evaluates the target's analytic pattern at its exact screen point, then Gaussian blur,
~1 grey level of noise and 8-bit quantisation)."""
import numpy as np
import pytest

from calibration.camera import Camera
from calibration.detect import (
    DetectionError,
    decode_dense,
    dense_correspondences,
    detect_checkerboard,
    detect_circle_grid,
    detect_dots,
    detect_dots_in_images,
)
from calibration.targets import CheckerboardTarget, CircleGridTarget, PhaseTarget, render_view

CAM = Camera(K=[[1000, 0, 399.5], [0, 1000, 299.5], [0, 0, 1]], size=(800, 600))
TARGET = PhaseTarget()  # the paper's 6x3 grid, 300 px cells, 0.311 mm pixels, 4 steps


def _rot(tilt_y=0.0, tilt_x=0.0, roll=0.0):
    a, b, c = np.deg2rad([tilt_y, tilt_x, roll])
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    Rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _pose(target, distance=850.0, shift=(0.0, 0.0), mirrored=False, **angles):
    """Screen centre on the optical axis (plus ``shift`` mm); ``mirrored``: the view of the target
    in a mirror (reflection x -> -x in the camera frame, an improper pose)."""
    R = _rot(**angles)
    centre = np.array([(target.screen[0] - 1) / 2, (target.screen[1] - 1) / 2, 0.0]) * target.pixel_pitch
    t = np.array([shift[0], shift[1], distance]) - R @ centre
    if mirrored:
        S = np.diag([-1.0, 1.0, 1.0])
        R, t = S @ R, S @ t
    return R, t


def _truth(target, R, t, cam=CAM):
    return cam.project((R @ target.object_points.T).T + t)


def _rms(err):
    return float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))


@pytest.mark.parametrize("tilt", [0.0, 50.0])
def test_dots_in_focus(tilt):
    R, t = _pose(TARGET, tilt_y=tilt)
    imgs = render_view(TARGET, CAM, R, t, noise_sigma=1.0, seed=1, supersample=3)
    det = detect_dots_in_images(imgs, TARGET, device="cpu")
    assert len(det) == 18 and not det.mirrored
    err = det.image_points - _truth(TARGET, R, t)[det.ids]
    # acceptance (issue 4): RMS <= 0.02 px in focus, also at 50 deg; measured 0.005-0.007 px
    assert _rms(err) <= 0.02
    assert np.allclose(det.object_points, TARGET.object_points[det.ids])
    # the fit's own noise estimate is of the order of the error (1 grey level of noise)
    assert np.all(det.sigma_px < 0.02)


def test_dots_blurred_tilted_and_opencv_passive_targets():
    """Defocus blur sigma = 10 px, monitor tilted 50 deg: phase dots <= 0.05 px RMS; OpenCV's
    passive detectors on the same pose and blur fail or are several times worse."""
    R, t = _pose(TARGET, tilt_y=50.0)
    imgs = render_view(TARGET, CAM, R, t, blur_sigma=10.0, noise_sigma=1.0, seed=2, supersample=2)
    det = detect_dots_in_images(imgs, TARGET, device="cpu")
    assert len(det) == 18
    phase_rms = _rms(det.image_points - _truth(TARGET, R, t)[det.ids])
    assert phase_rms <= 0.05  # acceptance; measured 0.015-0.02 px
    assert abs(det.blur_sigma - 10.0) < 0.5  # blur measured from the modulation
    from scipy.spatial import cKDTree

    for passive, detector in ((CheckerboardTarget(corners=(9, 6), square=150), detect_checkerboard),
                              (CircleGridTarget(grid=(6, 3), pitch=300, diameter=150), detect_circle_grid)):
        img = render_view(passive, CAM, R, t, blur_sigma=10.0, noise_sigma=1.0, seed=3, supersample=2)[0]
        found = detector(img, passive)
        if found is None:
            continue  # "fails": acceptable outcome
        truth = _truth(passive, R, t)
        d, _ = cKDTree(truth).query(found[0])  # nearest truth, independent of OpenCV's ordering
        # "several times worse": at least 3x the phase-target RMS (measured 0.3-0.5 px vs 0.02)
        assert np.sqrt(np.mean(d ** 2)) >= 3 * phase_rms


def test_dots_mirrored_view_ids_follow_the_reflected_target():
    R, t = _pose(TARGET, mirrored=True, tilt_y=30.0, tilt_x=10.0, roll=25.0)
    assert np.linalg.det(R) < 0
    imgs = render_view(TARGET, CAM, R, t, blur_sigma=6.0, noise_sigma=1.0, seed=4, supersample=2)
    det = detect_dots_in_images(imgs, TARGET, device="cpu")
    assert det.mirrored and len(det) == 18
    err = det.image_points - _truth(TARGET, R, t)[det.ids]
    # ids right <=> every point lands on the projection of its own object point
    assert _rms(err) <= 0.05 and np.abs(err).max() < 0.1


def test_partial_view_keeps_correct_ids():
    # the monitor half out of the image (as when a mirror's edge cuts it)
    R, t = _pose(TARGET, shift=(260.0, 0.0), roll=-15.0)
    imgs = render_view(TARGET, CAM, R, t, noise_sigma=1.0, seed=5, supersample=2)
    truth = _truth(TARGET, R, t)
    det = detect_dots_in_images(imgs, TARGET, device="cpu")
    inside = (truth[:, 0] > 60) & (truth[:, 0] < 740)
    assert 6 <= len(det) <= inside.sum() + 2
    err = det.image_points - truth[det.ids]
    assert _rms(err) <= 0.02


def test_plain_target_needs_full_view_and_handedness():
    plain = PhaseTarget(code=False)
    assert not plain.coded
    R, t = _pose(plain, roll=3.0)
    imgs = render_view(plain, CAM, R, t, noise_sigma=1.0, seed=6, supersample=2)
    det = detect_dots_in_images(imgs, plain, device="cpu")
    err = det.image_points - _truth(plain, R, t)[det.ids]
    assert len(det) == 18 and _rms(err) <= 0.02


def test_dense_decoding_in_focus_and_blurred():
    cam = Camera(K=[[700, 0, 239.5], [0, 700, 179.5], [0, 0, 1]], size=(480, 360))
    from calibration.targets import screen_points_of_pixels

    for blur, tilt in ((0.0, 30.0), (5.0, 40.0)):
        R, t = _pose(TARGET, distance=900.0, tilt_y=tilt)
        imgs = render_view(TARGET.dense_view(), cam, R, t, blur_sigma=blur, noise_sigma=1.0, seed=7, supersample=1)
        dec = decode_dense(imgs, TARGET, device="cpu")
        h, w = dec.mask.shape
        y, x = np.mgrid[0:h, 0:w]
        truth = screen_points_of_pixels(cam, R, t, TARGET.pixel_pitch, np.c_[x.ravel(), y.ravel()].astype(float))
        err = (dec.screen_xy - truth.reshape(h, w, 2))[dec.mask]
        assert dec.mask.sum() > 20000 and dec.mirrored is False
        # systematic part (median over ~1e5 pixels) removed by the blur correction: well below
        # 0.05 screen px (measured < 0.01); per-pixel noise: 1 grey level on the finest resolved
        # fringes (0.05 screen px in focus, ~0.5 with blur 5 where coarser fringes are used)
        assert np.all(np.abs(np.median(err, axis=0)) < 0.05)
        assert np.sqrt(np.mean(err ** 2)) < (0.1 if blur == 0 else 1.0)
        img_pts, obj_pts = dense_correspondences(dec, step=8)
        assert len(img_pts) > 300 and obj_pts.shape == (len(img_pts), 3)


def test_bad_input():
    with pytest.raises(ValueError, match="phase must be a 2-D map"):
        detect_dots(np.zeros(10), np.zeros(10), TARGET)
    with pytest.raises(ValueError, match="modulation must have"):
        detect_dots(np.zeros((10, 10)), np.zeros((10, 11)), TARGET)
    with pytest.raises(ValueError, match="PhaseTarget"):
        detect_dots(np.zeros((10, 10)), np.zeros((10, 10)), CheckerboardTarget())
    with pytest.raises(ValueError, match="4 phase steps but 3"):
        detect_dots_in_images(np.zeros((3, 20, 20)), TARGET, device="cpu")
    with pytest.raises(ValueError, match="dense sequence"):
        decode_dense(np.zeros((4, 20, 20)), TARGET, device="cpu")
    with pytest.raises(DetectionError, match="fringes"):
        detect_dots_in_images(np.full((4, 50, 60), 100.0), TARGET, device="cpu")
    assert detect_checkerboard(np.full((100, 120), 128, np.uint8), CheckerboardTarget()) is None
    with pytest.raises(ValueError, match="colour image"):
        detect_circle_grid(np.zeros((10, 10, 3)), CircleGridTarget())


def _vignetted_view(target, cam, R, t, *, blur_sigma, edge_x, band, seed):
    """A view whose right part is cut by an aperture edge far out of focus (a mirror's edge 0.4 m
    from the lens): left of ``edge_x - band`` every pixel sees the full defocus blur (a Gaussian of
    ``blur_sigma``), right of ``edge_x + band`` none; in between the pupil is partly cut, so the
    blur kernel along x is the Gaussian truncated at ``c(x) = 2.5 blur_sigma (edge_x - x) / band``
    (rays with image offset u > c(x) miss the mirror). Independent of the detector: space-variant
    convolution of the sharp float render, then 1 grey level of noise and 8-bit quantisation."""
    from scipy.ndimage import correlate1d, gaussian_filter1d

    sharp = render_view(target, cam, R, t, noise_sigma=0.0, bits=None, supersample=2)
    sharp = gaussian_filter1d(sharp, blur_sigma, axis=1, mode="nearest")  # full blur along y
    r = int(np.ceil(4 * blur_sigma))
    u = np.arange(-r, r + 1, dtype=float)
    g = np.exp(-0.5 * (u / blur_sigma) ** 2)
    g /= g.sum()
    cuts = np.linspace(-3 * blur_sigma, 3 * blur_sigma, 49)
    # image(x) = sum_u sharp(x - u) g(u) [u <= c]: correlate1d with the reversed kernel
    conv = np.stack([correlate1d(sharp, (g * (u <= c))[::-1], axis=2, mode="nearest") for c in cuts])
    x = np.arange(cam.size[0], dtype=float)
    c = np.clip(2.5 * blur_sigma * (edge_x - x) / band, cuts[0], cuts[-1])
    j = np.clip(np.searchsorted(cuts, c) - 1, 0, len(cuts) - 2)
    a = (c - cuts[j]) / (cuts[j + 1] - cuts[j])
    cols = np.arange(len(x))
    out = conv[j, :, :, cols] * (1 - a)[:, None, None] + conv[j + 1, :, :, cols] * a[:, None, None]
    out = np.moveaxis(out, 0, -1)  # (n, H, W)
    out = out + np.random.default_rng(seed).normal(0.0, 1.0, out.shape)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def test_vignetted_dots_flagged_by_modulation_slope_and_removed():
    """Dots partly beyond a defocused aperture edge (a mirror's edge) have a lopsided blur: their
    centres move by a few tenths of a px. The detector's modulation_slope flags them and
    calibration.pipeline.detect_view removes them; fully lit dots are kept."""
    from calibration.pipeline import MIN_VIGNETTING_SLOPE, detect_view

    R, t = _pose(TARGET, tilt_y=20.0, roll=5.0)
    truth = _truth(TARGET, R, t)
    # the edge's transition band (+-40 px, like the lab's ~110 px wide mirror edge vs ~10 px
    # defocus blur) over the right part of the rightmost dot column's cells
    edge_x = float(np.max(truth[:, 0])) + 35.0
    imgs = _vignetted_view(TARGET, CAM, R, t, blur_sigma=5.0, edge_x=edge_x, band=40.0, seed=11)
    full = detect_view(imgs, TARGET, correct_blur=False, max_misfit=None, max_slope=None, device="cpu")
    assert full.ok and len(full.detection) == 18
    det = full.detection
    err = np.linalg.norm(det.image_points - truth[det.ids], axis=1)
    # the dots whose cell (about +-55 px around the centre) reaches the band are vignetted
    hit = truth[det.ids, 0] + 55.0 > edge_x - 40.0  # the rightmost column
    assert hit.sum() >= 3
    # fully lit dots: flat modulation (measured slope <= 0.01) and centres within the in-focus
    # bound; the vignetted ones at least 3x the lab's largest lit-dot slope and off by > 0.05 px
    # (measured 0.1-0.3 px), i.e. worth removing
    assert det.modulation_slope[~hit].max() < MIN_VIGNETTING_SLOPE
    assert det.modulation_slope[hit].min() > 3 * 0.008
    assert np.sqrt(np.mean(err[~hit] ** 2)) <= 0.02 < 0.05 < np.sqrt(np.mean(err[hit] ** 2))
    kept = detect_view(imgs, TARGET, correct_blur=False, max_misfit=None, device="cpu")
    assert sorted(i for i, _ in kept.vignetted) == sorted(det.ids[hit].tolist())
    assert "vignetted" in kept.summary()
    err_kept = np.linalg.norm(kept.detection.image_points - truth[kept.detection.ids], axis=1)
    assert np.sqrt(np.mean(err_kept ** 2)) <= 0.02  # the in-focus acceptance bound


def test_degenerate_dot_fit_drops_the_dot_not_the_run(monkeypatch):
    """A numerically singular dot fit (seen on 24 x 12 dots a few pixels apart in a quarter-size render)
    must drop that dot, and a view with no fittable dot must come back as a failed view with a reason."""
    import calibration.detect.dots as dots
    from calibration.pipeline import detect_view

    R, t = _pose(TARGET)
    imgs = render_view(TARGET, CAM, R, t, noise_sigma=1.0, seed=1, supersample=1)
    real_fit = dots._fit_dot
    calls = {"n": 0}

    def one_singular(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 1:
            raise np.linalg.LinAlgError("Singular matrix")
        return real_fit(*args, **kwargs)

    monkeypatch.setattr(dots, "_fit_dot", one_singular)
    det = detect_dots_in_images(imgs, TARGET, device="cpu")
    assert len(det) == 17  # the dot whose fit failed is left out, the others are found

    def always_singular(*args, **kwargs):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(dots, "_fit_dot", always_singular)
    res = detect_view(np.asarray(imgs), TARGET, name="degenerate")
    assert not res.ok and "target not found" in res.error


def test_lattice_larger_than_the_target_is_a_detection_error(monkeypatch):
    import calibration.detect.dots as dots

    R, t = _pose(TARGET)
    imgs = render_view(TARGET, CAM, R, t, noise_sigma=1.0, seed=1, supersample=1)
    monkeypatch.setattr(dots, "_match_code", lambda *a, **k: [])  # no placement fits the grid
    with pytest.raises(DetectionError, match="span more rows or columns"):
        detect_dots_in_images(imgs, TARGET, device="cpu")
