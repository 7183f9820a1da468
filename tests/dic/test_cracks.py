"""Declared cracks (dic.cracks): geometry against hand-worked truth, strain windows, grid cells and figures that
never reach across a crack, opening/sliding of exact piecewise-linear fields, and tracking of a rendered
displacement jump (dic.synth) with its opening recovered within 0.01 px."""
from __future__ import annotations

import csv
from types import SimpleNamespace

import numpy as np
import pytest

from dic.cracks import (
    Crack,
    as_cracks,
    blocked_pixels,
    crack_opening,
    cracks_settings,
    parse_crack,
    segments_cross,
    subset_crosses,
)


# -- the crack itself ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad, message", [
    ([[1.0, 2.0]], "at least 2 vertices"),
    ([[1.0, 2.0], [1.0, 2.0]], "must have a length: vertices 0 and 1"),
    ([[0.0, 0.0], [np.nan, 1.0]], "finite"),
    ([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], r"\(M, 2\)"),
    ("not a crack", "numbers"),
])
def test_a_crack_is_validated_with_a_clear_message(bad, message):
    with pytest.raises(ValueError, match=message):
        Crack(bad) if not isinstance(bad, str) else parse_crack(bad)


def test_crack_forms_and_stored_form_round_trip():
    one = parse_crack("10,0, 10.5,40,20,80")
    assert np.array_equal(one.vertices, [[10, 0], [10.5, 40], [20, 80]])
    assert one.length == pytest.approx(np.hypot(0.5, 40) + np.hypot(9.5, 40))
    with pytest.raises(ValueError, match="even count"):
        parse_crack("1,2,3")
    assert as_cracks(None) == () and cracks_settings(None) is None
    assert as_cracks(one) == (one,) == as_cracks([[10, 0], [10.5, 40], [20, 80]]) == as_cracks(one.vertices)
    two = as_cracks(["0,0,1,1", one])
    stored = cracks_settings(two)
    assert stored == [[[0.0, 0.0], [1.0, 1.0]], one.vertices.tolist()]
    assert as_cracks(stored) == two
    with pytest.raises(ValueError, match="crack 1: a crack needs at least 2 vertices"):
        as_cracks([[[0, 0], [1, 1]], [[2, 2]]])


# -- the crossing rule -----------------------------------------------------------------------------------------
def test_blocked_pixels_of_a_straight_crack_are_the_far_half_plane():
    """A long oblique crack y = 0.4 x + 3.3 (no pixel centre on it): a subset pixel is blocked exactly when it lies
    on the other side of the line from the POI (independent truth: the sign of y - 0.4 x - 3.3)."""
    crack = Crack([[-100.0, 0.4 * -100 + 3.3], [200.0, 0.4 * 200 + 3.3]])
    rng = np.random.default_rng(1)
    points = rng.uniform(5, 40, size=(60, 2))
    subset = 11
    got = blocked_pixels(points, subset, crack, margin=0)
    assert got.shape == (60, 121) and got.dtype == bool
    r = subset // 2
    centre = np.floor(points + 0.5)  # positive coordinates: half away from zero = floor(x + 0.5)
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    px = centre[:, None, 0] + dx.ravel()
    py = centre[:, None, 1] + dy.ravel()
    side_pixel = np.sign(py - 0.4 * px - 3.3)
    side_poi = np.sign(points[:, 1] - 0.4 * points[:, 0] - 3.3)[:, None]
    assert np.array_equal(got, side_pixel != side_poi)
    assert got.any() and not got.all()
    assert np.array_equal(subset_crosses(points, subset, crack), got.any(axis=1))


def test_blocked_pixels_order_rounding_touching_and_tips():
    # a vertical crack between pixel columns 10 and 11; POI 7.5 rounds half away to 8: columns 5..11, row by row
    got = blocked_pixels([[7.5, 10.0]], 7, [[10.5, -50], [10.5, 50]], margin=0).reshape(7, 7)
    expected = np.zeros((7, 7), bool)
    expected[:, 6] = True  # column 11 only
    assert np.array_equal(got, expected)
    # a pixel on the crack counts as across (touching is crossing): the crack x = 11 blocks column 11 too
    got = blocked_pixels([[8.0, 10.0]], 7, [[11.0, -50], [11.0, 50]], margin=0).reshape(7, 7)
    assert np.array_equal(got, expected)
    # a short crack x = 3.5, y in [-1.5, 1.5] seen from (0, 0): a pixel is blocked when its straight segment
    # from the POI passes x = 3.5 at |y| <= 1.5 (independent truth); pixels behind the tip stay reachable
    got = blocked_pixels([[0.0, 0.0]], 11, [[3.5, -1.5], [3.5, 1.5]], margin=0).reshape(11, 11)
    dy, dx = np.mgrid[-5:6, -5:6].astype(float)
    with np.errstate(divide="ignore", invalid="ignore"):
        y_at = dy * 3.5 / dx
    truth = (dx > 3.5) & (np.abs(y_at) <= 1.5)
    assert np.array_equal(got, truth)
    assert got[5 + 1, 5 + 5] and not got[5 + 3, 5 + 5]  # (5, 1) blocked, (5, 3) behind the tip is not
    # no crack: nothing blocked; a POI on the crack has no side: everything off the crack's line is blocked
    assert not blocked_pixels([[8.0, 8.0]], 5, None).any()
    on = blocked_pixels([[10.0, 10.0]], 5, [[10.0, 0.0], [10.0, 20.0]], margin=0).reshape(5, 5)
    assert on[:, [0, 1, 3, 4]].all()


def test_blocked_pixels_margin_drops_the_pixels_along_the_crack_on_both_sides():
    crack = [[10.5, -50.0], [10.5, 50.0]]
    # default 1 px: the columns at 0.5 px from the crack (x = 10 on the POI's side, 11 across)
    got = blocked_pixels([[8.0, 10.0]], 7, crack).reshape(7, 7)  # columns x = 5..11
    assert np.array_equal(got.all(axis=0), [False] * 5 + [True, True]) and np.array_equal(got.any(axis=0), got.all(axis=0))
    wider = blocked_pixels([[8.0, 10.0]], 7, crack, margin=1.6).reshape(7, 7)  # x = 9 (1.5 px) too
    assert np.array_equal(wider.all(axis=0), [False] * 4 + [True] * 3)
    # near a tip the margin is the distance to the segment's end: pixel (12, 52) is hypot(1.5, 2) = 2.5 px away
    tip = blocked_pixels([[12.0, 52.0]], 3, crack, margin=2.4).reshape(3, 3)
    assert not tip[1, 1] and tip[0, 0]  # (11, 51): hypot(0.5, 1) = 1.1 px
    with pytest.raises(ValueError, match="margin"):
        blocked_pixels([[8.0, 10.0]], 7, crack, margin=-1)


def test_segments_cross_broadcasts_and_handles_collinear_segments():
    crack = [[0.0, 0.0], [10.0, 0.0]]
    starts = np.array([[5.0, -1.0], [5.0, 1.0], [12.0, 0.0], [-3.0, 0.0], [11.0, -1.0]])
    ends = np.array([[5.0, 1.0], [5.0, 2.0], [20.0, 0.0], [1.0, 0.0], [11.0, 1.0]])
    assert segments_cross(starts, ends, crack).tolist() == [True, False, False, True, False]
    assert segments_cross(starts[:, None, :], ends[None, :, :], crack).shape == (5, 5)


# -- strain windows --------------------------------------------------------------------------------------------
def _piecewise_field(c=47.5):
    yy, xx = np.mgrid[0:20, 0:20] * 5.0
    pts = np.column_stack([xx.ravel(), yy.ravel()])
    right = pts[:, 0] > c
    u = 1e-3 * pts[:, 0] + 2e-3 * pts[:, 1] + 0.5 * right
    v = -2e-3 * pts[:, 1] + 0.3 * right
    return SimpleNamespace(points=pts, u=u, v=v, valid=np.ones(len(pts), bool)), c


def test_strain_windows_do_not_reach_across_a_crack():
    from dic import StrainPlan, strain

    field, c = _piecewise_field()
    crack = [[c, -10.0], [c, 200.0]]
    plain = strain(field, window=5)
    cut = strain(field, window=5, cracks=crack)
    # the jump smears into the plain fits near the crack; with the crack every fit is exact on its own side
    assert np.nanmax(np.abs(plain.dudx - 1e-3)) > 0.01
    for name, truth in (("dudx", 1e-3), ("dudy", 2e-3), ("dvdx", 0.0), ("dvdy", -2e-3)):
        assert np.max(np.abs(getattr(cut, name) - truth)) < 1e-12, name
    assert cut.valid.all()
    inner = (field.points[:, 1] >= 10) & (field.points[:, 1] <= 85)  # rows whose window the grid's edge does not cut
    near = inner & (np.abs(field.points[:, 0] - c) < 5)  # the columns next to the crack: 3 of the 5 window columns
    assert near.sum() == 32 and np.all(cut.n_fit[near] == 15) and np.all(plain.n_fit[near] == 25)
    # a plan gives the same, frame after frame
    plan = StrainPlan(field.points, window=5, cracks=crack)
    again = plan.strain(field)
    assert np.array_equal(again.dudx, cut.dudx) and np.array_equal(plan.strain(field).dvdy, cut.dvdy)
    # huge grids: the strain in bands of rows is the same
    from dic.sequence.chunks import strain_in_bands

    banded = strain_in_bands(field, 5, max_points=60, cracks=crack)
    for name in ("dudx", "dvdy", "n_fit", "valid"):
        assert np.array_equal(getattr(banded, name), getattr(cut, name), equal_nan=True)
    # a crack that cuts no window changes nothing, bit for bit
    far = strain(field, window=5, cracks=[[500.0, 0.0], [500.0, 10.0]])
    for name in ("dudx", "dudy", "dvdx", "dvdy", "n_fit", "valid"):
        assert np.array_equal(getattr(far, name), getattr(plain, name), equal_nan=True)


# -- grid interpolation and figures ----------------------------------------------------------------------------
def test_grid_cells_cut_by_a_crack_give_no_value():
    from dic.gridinterp import GridCells, QueryStatus

    yy, xx = np.mgrid[0:5, 0:5] * 10.0
    pts = np.column_stack([xx.ravel(), yy.ravel()])
    cells = GridCells(pts, cracks=[[15.0, -5.0], [15.0, 25.0]])  # through column 1 of cells, ends in row 2
    expected = np.zeros((4, 4), bool)
    expected[:3, 1] = True
    assert np.array_equal(cells.cut, expected)
    query = [[12, 5], [5, 5], [25, 5], [10, 10], [15, 35], [12, 29]]
    values, status = cells.locate(query).evaluate(pts[:, 0] + 2 * pts[:, 1], np.ones(25, bool))
    assert status.tolist() == [QueryStatus.CRACK, 0, 0, 0, 0, QueryStatus.CRACK]
    assert QueryStatus.CRACK.reason == "in a grid cell cut by a declared crack"
    # elsewhere bilinear and exact for a linear field; on a node (one corner needed) its value
    assert np.isnan(values[0, 0]) and values[1:5, 0].tolist() == [15.0, 35.0, 30.0, 85.0]
    plain = GridCells(pts)
    assert plain.cut is None and plain.locate(query).evaluate(pts[:, 0], np.ones(25, bool))[1].tolist() == [0] * 6


def test_figure_cells_cut_by_a_crack_are_not_drawn_and_the_crack_is():
    from dic.plots.fields import _grid_maps, field_figure

    yy, xx = np.mgrid[0:6, 0:8] * 10.0
    pts = np.column_stack([xx.ravel(), yy.ravel()])
    field = SimpleNamespace(points=pts, u=np.ones(len(pts)), v=np.zeros(len(pts)), valid=np.ones(len(pts), bool))
    crack = Crack([[33.0, -20.0], [33.0, 100.0]])  # inside the cells of column 3 (x 25..35)
    maps, _ = _grid_maps(field, None, ["u"], as_cracks(crack))
    drawn = np.isfinite(maps["u"])
    assert not drawn[:, 3].any() and drawn[:, [0, 1, 2, 4, 5, 6, 7]].all()
    fig = field_figure(None, field, components=["u"], cracks=crack)
    [line] = [ln for ln in fig.axes[0].lines if ln.get_gid() == "crack"]
    assert np.array_equal(line.get_xdata(), [33.0, 33.0]) and np.array_equal(line.get_ydata(), [-20.0, 100.0])


# -- opening and sliding -----------------------------------------------------------------------------------------
def test_opening_and_sliding_of_an_exact_piecewise_linear_field():
    """A bent crack; each side moves by its own affine field; the jump at a station is known exactly."""
    crack = Crack([[20.0, 10.0], [60.0, 50.0], [60.0, 110.0]])
    yy, xx = np.mgrid[0:121:4, 0:101:4].astype(float)
    pts = np.column_stack([xx.ravel(), yy.ravel()])
    # the positive side (normal (-t_y, t_x)): of the first segment (line y = x - 10, n = (-1, 1)/sqrt 2) x - y < 10,
    # of the second (x = 60, n = (-1, 0)) x < 60
    plus = np.where(pts[:, 1] < 50.0, pts[:, 0] - pts[:, 1] < 10.0, pts[:, 0] < 60.0)
    a_plus, a_minus = np.array([0.3, -0.2]), np.array([-0.1, 0.05])
    grad = np.array([[1e-3, 2e-3], [-1e-3, 5e-4]])  # the same gradient both sides: a pure jump
    uv = pts @ grad.T + np.where(plus[:, None], a_plus, a_minus)
    field = SimpleNamespace(points=pts, u=uv[:, 0], v=uv[:, 1], valid=np.ones(len(pts), bool), step=4, subset=21)
    out = crack_opening(field, crack, spacing=10.0)
    jump = a_plus - a_minus
    ok = out.valid
    assert ok.sum() >= 0.8 * ok.size
    expected_open = out.normal @ jump
    expected_slide = out.tangent @ jump
    assert np.max(np.abs(out.opening[ok] - expected_open[ok])) < 1e-9
    assert np.max(np.abs(out.sliding[ok] - expected_slide[ok])) < 1e-9
    # first segment: t = (1, 1)/sqrt 2, n = (-1, 1)/sqrt 2; second: t = (0, 1), n = (-1, 0)
    first, second = out.arclength < 40 * np.sqrt(2) - 1e-9, out.arclength > 40 * np.sqrt(2) + 1e-9
    assert np.allclose(out.normal[first], [-np.sqrt(0.5), np.sqrt(0.5)]) and np.allclose(out.normal[second], [-1, 0])
    # exact data: residual-based sigma ~ 0
    assert np.nanmax(out.sigma_opening) < 1e-9
    table = out.table()
    assert table.shape == (out.opening.size, len(out.COLUMNS))
    # with per-point sigma: the jump's sigma is that of the two extrapolations (independent points: subset None)
    field.sigma_u = np.full(len(pts), 0.01)
    field.sigma_v = np.full(len(pts), 0.01)
    del field.subset
    s = crack_opening(field, crack, spacing=10.0)
    assert np.all(s.sigma_opening[ok] > 0.001) and np.all(s.sigma_opening[ok] < 0.01)
    with pytest.raises(ValueError, match="one crack at a time"):
        crack_opening(field, [crack, crack])
    with pytest.raises(ValueError, match="spacing"):
        crack_opening(field, crack, spacing=0)


# -- tracking a rendered displacement jump -----------------------------------------------------------------------
H, W, C = 120, 200, 100.5  # the crack x = C lies between pixel columns 100 and 101


def _jump_pair(noise=1.0, seed=3):
    """Reference and current images of a speckle whose left part moves u = -0.25 px and right part +0.25 px
    (opening 0.5 px across x = 100.5): each side rendered from the same Boolean model with its own exact shift,
    the current image made of the left render at pixel centres x < 100.5 and the right render beyond."""
    from dic import synth

    model = synth.make_speckle((H, W), margin=10, seed=seed)
    ref = synth.render(model, (H, W))
    left = synth.render(model, (H, W), (-0.25, 0.0))
    right = synth.render(model, (H, W), (0.25, 0.0))
    cur = np.where(np.arange(W)[None, :] < C, left, right)
    return (synth.add_noise(ref, noise_sigma=noise, bits=8, seed=1),
            synth.add_noise(cur, noise_sigma=noise, bits=8, seed=2))


def test_a_displacement_jump_is_measured_without_smearing_and_its_opening_within_001_px():
    """Subset 21, step 4, 1st order, 1 GL noise, 8-bit. Measured on this image (docs/dic2d.md, Declared cracks):
    without the crack the points within half a subset of the line are smeared (up to 0.22 px off their side's u);
    with it every subset is correlated on its own side's pixels (masked IC-GN, the 1 px margin along the crack
    dropped too) and every point within one subset of the line is kept and at most 0.0197 px off (RMS 0.0044 px;
    the interior: at most 0.0124 px); the opening at every station at most 0.0074 px off 0.5 (points within half a
    subset left out of the fits), sliding 0.0071 px.
    Bounds: smearing > 0.15 px without the crack; with it every point within one subset valid and within 0.025 px,
    RMS within 0.008 px; every station's opening within 0.01 px of 0.5 px, sliding within 0.01 px of 0."""
    from dic import Tracker

    ref, cur = _jump_pair()
    crack = Crack([[C, -20.0], [C, H + 20.0]])
    plain = Tracker(ref, subset=21, step=4, device="cpu").track(cur)
    f = Tracker(ref, subset=21, step=4, cracks=crack, device="cpu").track(cur)
    d = np.abs(f.points[:, 0] - C)
    truth = np.where(f.points[:, 0] < C, -0.25, 0.25)
    assert np.max(np.abs(plain.u - truth)[plain.valid & (d < 10.5)]) > 0.15
    near = (d < 21) & (f.points[:, 1] > 10)  # row y = 10 touches the image border (OUT_OF_BOUNDS either way)
    assert near.sum() == 240 and f.valid[near].all()
    err = np.abs(f.u - truth)[near]
    assert np.max(err) < 0.025 and np.sqrt(np.mean(err ** 2)) < 0.008
    assert np.max(np.abs(f.v)[near]) < 0.025
    kept = f.status[near]
    assert np.all((kept == 0) | (kept == 1))
    out = crack_opening(f, crack)
    assert out.valid.all() and out.radius == 63.0 and out.gap == 10.5
    assert np.max(np.abs(out.opening - 0.5)) < 0.01
    assert np.max(np.abs(out.sliding)) < 0.01
    assert np.all(out.sigma_opening > 0) and np.all(out.sigma_opening < 0.01)


def test_robust_refinement_leaves_subsets_a_crack_cuts_masked():
    """The robust (Tukey) refinement weighs every pixel of a subset: run on the subsets a crack cuts, it pulled them
    across the jump (measured: up to 0.25 px off); they keep their masked result, the others are refined."""
    from dic import Tracker

    ref, cur = _jump_pair()
    crack = Crack([[C, -20.0], [C, H + 20.0]])
    f = Tracker(ref, subset=21, step=4, cracks=crack, robust=True, device="cpu").track(cur)
    plain = Tracker(ref, subset=21, step=4, cracks=crack, device="cpu").track(cur)
    cut = blocked_pixels(f.points, 21, crack).any(axis=1)
    # cut: the subset (half width 10 px) reaches the crack or the 1 px margin along it (pixel columns 100, 101)
    assert np.array_equal(cut, np.abs(f.points[:, 0] - C) <= 10.5) and cut.sum() == 150
    assert np.array_equal(f.u[cut], plain.u[cut])
    assert not np.array_equal(f.u[~cut & f.valid], plain.u[~cut & f.valid])  # the others are refined
    near = (np.abs(f.points[:, 0] - C) < 21) & (f.points[:, 1] > 10)
    truth = np.where(f.points[:, 0] < C, -0.25, 0.25)
    assert f.valid[near].all() and np.max(np.abs(f.u - truth)[near]) < 0.025


def test_track_crack_option_is_stored_and_specula_crack_measures_it(tmp_path):
    from click.testing import CliRunner

    from dic.cli import main
    from dic.io import write_image
    from dic.sequence.options import TrackOptions
    from dic.store import ResultReader

    ref, cur = _jump_pair()
    write_image(tmp_path / "ref.tif", ref.astype(np.uint8))
    write_image(tmp_path / "cur.tif", cur.astype(np.uint8))
    out = tmp_path / "run.h5"
    runner = CliRunner()
    args = ["track", str(tmp_path / "ref.tif"), str(tmp_path / "cur.tif"), "-o", str(out), "--step", "4", "-q",
            "--device", "cpu", "--crack", f"{C},-20,{C},{H + 20}"]
    res = runner.invoke(main, args)
    assert res.exit_code == 0, res.output
    with ResultReader(out) as r:
        settings = r.settings
        frame = r.read_frame(1)
    assert settings["cracks"] == [[[C, -20.0], [C, H + 20.0]]]
    d = np.abs(frame.points[:, 0] - C)
    near = (d < 10.5) & (frame.points[:, 1] > 10)
    assert frame.valid[near].all()  # masked to their own side
    assert np.max(np.abs(frame.u - np.where(frame.points[:, 0] < C, -0.25, 0.25))[near]) < 0.03
    assert TrackOptions.from_settings(settings).cracks == [[[C, -20.0], [C, H + 20.0]]]
    # resuming with the same crack is the same run; another crack is refused by name
    assert runner.invoke(main, args).exit_code == 0
    other = runner.invoke(main, args[:-1] + [f"{C + 1},-20,{C + 1},{H + 20}"])
    assert other.exit_code != 0 and "--crack (cracks)" in other.output
    csv_path = tmp_path / "crack.csv"
    res = runner.invoke(main, ["crack", str(out), "--frame", "1", "-o", str(csv_path)])
    assert res.exit_code == 0, res.output
    assert "crack 0:" in res.output
    with open(csv_path) as fh:
        rows = list(csv.DictReader(fh))
    opening = np.array([float(r["opening_px"]) for r in rows])
    assert len(rows) >= 30 and np.all(np.abs(opening - 0.5) < 0.01)
    # post-processing reads the run's cracks: no value in a grid cell the crack cuts
    hist = runner.invoke(main, ["history", str(out), "--point", "100,60"])
    assert hist.exit_code == 1 and "in a grid cell cut by a declared crack" in hist.output
    assert runner.invoke(main, ["history", str(out), "--point", "60,60"]).exit_code == 0
    bad = runner.invoke(main, ["track", str(tmp_path / "ref.tif"), str(tmp_path / "cur.tif"), "-o",
                               str(tmp_path / "x.h5"), "--crack", "1,2,3"])
    assert bad.exit_code != 0 and "--crack" in bad.output and "even count" in bad.output


def test_track_sequence_cracks_keyword_and_old_files_read_as_no_cracks(tmp_path):
    from dic.sequence import track_sequence
    from dic.sequence.options import TrackOptions
    from dic.store import ResultReader

    ref, cur = _jump_pair()
    out = tmp_path / "lib.h5"
    crack = Crack([[C, -20.0], [C, H + 20.0]])
    track_sequence(ref, [cur], out, step=8, cracks=crack, device="cpu")
    with ResultReader(out) as r:
        assert r.settings["cracks"] == [crack.vertices.tolist()]
        f = r.read_frame(1)
    truth = np.where(f.points[:, 0] < C, -0.25, 0.25)
    near = (np.abs(f.points[:, 0] - C) < 10.5) & (f.points[:, 1] > 10)
    assert f.valid[near].all() and np.max(np.abs(f.u - truth)[near]) < 0.03
    # a schema-2 record without the option reads as no cracks (its old behaviour)
    settings = TrackOptions().to_settings()
    del settings["cracks"]
    assert TrackOptions.from_settings(settings).cracks is None
    with pytest.raises(ValueError, match="cracks: crack 0: a crack needs at least 2 vertices") as err:
        TrackOptions(cracks=[[0, 0]])
    assert err.value.option == "cracks"
