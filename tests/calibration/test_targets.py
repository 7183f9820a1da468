"""Calibration targets (calibration/targets.py) and the ``specula target`` command."""
import json

import numpy as np
import pytest

from calibration.camera import Camera
from calibration.targets import (
    CheckerboardTarget,
    CircleGridTarget,
    PhaseTarget,
    load_target,
    make_cell_code,
    render_view,
)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def test_default_target_geometry():
    tg = PhaseTarget()  # the paper's 6x3 grid of 300 px cells on the 27" 1920x1080 monitor
    imgs = tg.images()
    assert imgs.shape == (4, 1080, 1920) and imgs.dtype == np.uint8
    obj = tg.object_points
    assert obj.shape == (18, 3) and np.all(obj[:, 2] == 0)
    # ids run along x then y, 300 px = 93.3 mm apart (paper, Fig. 3)
    assert np.allclose(obj[1] - obj[0], [300 * 0.311, 0, 0])
    assert np.allclose(obj[6] - obj[0], [0, 300 * 0.311, 0])
    # centred on the screen: mean of the dots is the centre of pixel ((W-1)/2, (H-1)/2)
    assert np.allclose(obj[:, :2].mean(axis=0), [959.5 * 0.311, 539.5 * 0.311])
    # frame origin: centre of screen pixel (0, 0)
    assert np.allclose(tg.screen_to_target([[0.0, 0.0]]), 0)
    assert np.allclose(tg.target_to_screen(tg.object_points), tg.dot_centres_px)


def test_paper_section3_target():
    # "4 x 2 pattern of circles with a 300 pixels diameter at a 450 pixels distance" = 139.95 mm
    tg = PhaseTarget(grid=(4, 2), pitch=450, period=300)
    d = np.diff(tg.object_points[:4, 0])
    assert np.allclose(d, 139.95)
    # the wrapped phase jumps at r = period / 2 = 150 px around a code-0 dot centre
    i = int(np.flatnonzero(tg.dot_codes == 0)[0])
    cx, cy = tg.dot_centres_px[i]
    r = np.array([149.0, 151.0])
    ph = _wrap(tg.phase(cx + r, np.full(2, cy)))
    assert ph[0] > 3.0 and ph[1] < -3.0


def test_displayed_images_encode_the_phase():
    tg = PhaseTarget(grid=(4, 2), pitch=450, period=300)
    imgs = tg.images().astype(np.float64)
    d = tg.phase_shifts
    # independent demodulation (N-step sums) of the 8-bit screen images
    s = np.tensordot(np.cos(d), imgs, axes=1)
    c = np.tensordot(np.sin(d), imgs, axes=1)
    phase = np.arctan2(s, c)
    y, x = np.mgrid[0:1080, 0:1920].astype(np.float64)
    truth = tg.phase(x, y)
    lit = np.isfinite(truth)
    err = np.abs(_wrap(phase - truth))[lit]
    # 8-bit rounding (<= 0.5 grey) of A = 127: phase error <= 0.5 * sum|cos d| / (N/2 * A) = 0.008 rad
    assert err.max() < 0.009
    assert np.all(np.hypot(s, c)[~lit] < 1e-6)  # no fringes outside the lit area


def test_code_windows_are_unique_under_rotation_and_reflection():
    # brute force, independent of the search: every 2x3 / 3x2 window against every other
    # placement of the same shape in all 8 orientations differs in >= 2 cells
    for grid in [(6, 3), (4, 2), (8, 5)]:
        code, window = make_cell_code(grid)
        ny, nx = code.shape
        a, b = window
        for h, w in {(a, b), (b, a)}:
            if h > ny or w > nx:
                continue
            true_blocks, all_blocks = [], []
            for j in range(ny - h + 1):
                for i in range(nx - w + 1):
                    true_blocks.append(((j, i), code[j:j + h, i:i + w]))
            for hh, ww in {(h, w), (w, h)}:
                for j in range(ny - hh + 1):
                    for i in range(nx - ww + 1):
                        blk = code[j:j + hh, i:i + ww]
                        for t in range(8):
                            v = np.rot90(blk if t < 4 else blk.T, t % 4)
                            if v.shape == (h, w):
                                all_blocks.append(((j, i, hh, ww, t), v))
            for (j, i), blk in true_blocks:
                for key, v in all_blocks:
                    if key == (j, i, h, w, 0):
                        continue
                    assert np.sum(v != blk) >= 2, (grid, (j, i), key)


def test_dense_sequence_decodes_screen_coordinates():
    from calibration.detect import decode_dense

    tg = PhaseTarget(screen=(480, 270), pixel_pitch=0.5, grid=(3, 2), pitch=100, dense_fine_period=20)
    lv = tg.dense_levels
    assert max(p.period for p in lv if p.axis == 0) > 480 and max(p.period for p in lv if p.axis == 1) > 270
    # the screen seen by an ideal camera with one pixel per screen pixel: decoded = pixel position
    dec = decode_dense(tg.dense_images(), tg, device="cpu", erode=0)
    y, x = np.mgrid[0:270, 0:480]
    err = np.abs(dec.screen_xy - np.stack([x, y], axis=-1))[dec.mask]
    assert dec.mask.mean() > 0.99
    # 8-bit rounding of the finest level (20 px period): 0.008 rad -> 0.03 px
    assert err.max() < 0.04
    assert np.allclose(dec.target_xy[10, 20], [10, 5], atol=0.02)  # 0.5 mm pixels
    assert dec.mirrored is False


def test_conventional_targets():
    cb = CheckerboardTarget(screen=(1200, 800), corners=(9, 6), square=100)
    img = cb.images()[0]
    assert img.shape == (800, 1200)
    pts = cb.points_px
    assert np.allclose(np.diff(pts[:9, 0]), 100) and len(pts) == 54
    # square (a, b) is dark when a + b is even: inner corner 0 joins dark squares (0, 0), (1, 1)
    x0, y0 = pts[0]
    assert img[int(y0 - 50), int(x0 - 50)] == 0 and img[int(y0 + 50), int(x0 + 50)] == 0
    assert img[int(y0 - 50), int(x0 + 50)] == 255
    cg = CircleGridTarget(screen=(1920, 1080), grid=(6, 3), pitch=300, diameter=150)
    img = cg.images()[0]
    cx, cy = cg.points_px[0]
    assert img[int(round(cy)), int(round(cx))] == 0 and img[int(cy) + 100, int(cx)] == 255
    assert np.allclose(cg.object_points[1] - cg.object_points[0], [93.3, 0, 0])


def test_render_view_geometry_matches_opencv_projection(rng):
    """The synthetic camera maps each pixel to the screen point that cv2.projectPoints maps back
    onto that pixel (with lens distortion and an improper, mirrored pose), and a rendered
    checkerboard's corners (OpenCV's detector + cornerSubPix) land on the projected corners."""
    import cv2

    from calibration.targets import screen_points_of_pixels

    cam = Camera(K=[[1000, 0, 401.2], [0, 1010, 297.8], [0, 0, 1]], dist=[-0.12, 0.05, 0.001, -0.0005, 0.0],
                 size=(800, 600))
    a, b = np.deg2rad(35), np.deg2rad(-12)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    R = Ry @ Rx
    t = np.array([-250.0, -150.0, 900.0])
    uv = rng.uniform([0, 0], [799, 599], (200, 2))
    for RR, tt in ((R, t), (np.diag([-1.0, 1, 1]) @ R, np.diag([-1.0, 1, 1]) @ t)):  # direct and mirrored
        sp = screen_points_of_pixels(cam, RR, tt, 0.311, uv)
        X = np.c_[sp * 0.311, np.zeros(len(sp))]
        back, _ = cv2.projectPoints((RR @ X.T).T + tt, np.zeros(3), np.zeros(3), cam.K, cam.dist)
        # Newton undistortion to 1e-12 (normalised) -> ~1e-9 px round trip
        assert np.max(np.abs(back.reshape(-1, 2) - uv)) < 1e-6

    cb = CheckerboardTarget(corners=(9, 6), square=150)
    cam0 = Camera(K=[[1000, 0, 399.5], [0, 1000, 299.5], [0, 0, 1]], size=(800, 600))
    centre = np.array([959.5, 539.5, 0]) * 0.311
    t0 = np.array([0, 0, 900.0]) - centre
    img = render_view(cb, cam0, np.eye(3), t0, supersample=4, noise_sigma=0.0)[0]
    ok, corners = cv2.findChessboardCorners(img, (9, 6))
    assert ok
    corners = cv2.cornerSubPix(img, corners, (7, 7), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-6))
    truth, _ = cv2.projectPoints(cb.object_points, np.zeros(3), t0, cam0.K, np.zeros(5))
    from scipy.spatial import cKDTree

    d, _ = cKDTree(truth.reshape(-1, 2)).query(corners.reshape(-1, 2))
    # smoke test of the whole rendering path: 4x4 point samples per pixel quantise an
    # axis-aligned edge position to 1/4 px steps, so the corners carry up to ~1/8 px of sampling
    # error (measured 0.18 px max with cornerSubPix); the exact check is the round trip above
    assert d.max() < 0.25


def test_json_round_trip(tmp_path):
    tg = PhaseTarget(grid=(4, 2), pitch=450, period=300)
    path = tmp_path / "t.json"
    tg.save_json(path)
    data = json.loads(path.read_text())
    assert data["schema"] == "specula.target" and "object_points" in data and "target_frame" in data
    back = load_target(path)
    assert isinstance(back, PhaseTarget)
    assert np.array_equal(back.code, tg.code) and np.allclose(back.object_points, tg.object_points)
    for t in (CheckerboardTarget(corners=(9, 6), square=100), CircleGridTarget()):
        t.save_json(tmp_path / "c.json")
        assert np.allclose(load_target(tmp_path / "c.json").object_points, t.object_points)
    data["schema_version"] = 99
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="schema_version"):
        load_target(path)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="cannot read"):
        load_target(tmp_path / "bad.json")


def test_bad_target_parameters():
    with pytest.raises(ValueError, match="outside the 1920x1080 screen"):
        PhaseTarget(grid=(20, 3))
    with pytest.raises(ValueError, match="steps"):
        PhaseTarget(steps=2)
    with pytest.raises(ValueError, match="screen"):
        PhaseTarget(screen="1920-1080")
    with pytest.raises(ValueError, match="pixel_pitch"):
        PhaseTarget(pixel_pitch=0)
    with pytest.raises(ValueError, match="background"):
        PhaseTarget(background=200, amplitude=100)
    with pytest.raises(ValueError, match="code must be"):
        PhaseTarget(code=np.zeros((2, 2), dtype=int))
    with pytest.raises(ValueError, match="coarsest dense period"):
        PhaseTarget(dense_periods=((40, 400), (40, 2000)))
    with pytest.raises(ValueError, match="smaller than the pitch"):
        CircleGridTarget(pitch=100, diameter=120)
    with pytest.raises(ValueError, match="does not fit"):
        CheckerboardTarget(corners=(20, 12), square=200)
    cam = Camera(K=np.eye(3) * [100, 100, 1], size=(10, 10))
    with pytest.raises(ValueError, match="orthogonal"):
        render_view(PhaseTarget(), cam, np.ones((3, 3)), np.zeros(3))


def test_cli_writes_images_and_json(tmp_path):
    from click.testing import CliRunner

    from dic.cli import main

    runner = CliRunner()
    res = runner.invoke(main, ["target", "fringes", "--screen", "640x360", "--pixel-pitch", "0.5", "--grid", "3x2",
                               "--pitch", "150", "--steps", "3", "-o", str(tmp_path / "f")])
    assert res.exit_code == 0, res.output
    files = sorted(p.name for p in (tmp_path / "f").iterdir())
    assert files == ["fringes.json", "fringes_00.png", "fringes_01.png", "fringes_02.png"]
    tg = load_target(tmp_path / "f" / "fringes.json")
    assert tg.grid == (3, 2) and tg.steps == 3
    res = runner.invoke(main, ["target", "checkerboard", "--screen", "640x360", "--corners", "5x3", "--square", "60",
                               "-o", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(main, ["target", "fringes", "--grid", "20x3", "-o", str(tmp_path / "x")])
    assert res.exit_code != 0 and "outside" in res.output
    res = runner.invoke(main, ["target", "circles", "--grid", "6-3", "-o", str(tmp_path / "x")])
    assert res.exit_code != 0 and "AxB" in res.output
