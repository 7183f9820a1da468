"""The one correlation core (dic.correlation): one ROI rule, guesses chosen by name and extensible,
one engine that runs IC-GN for 2-D and stereo, repeatable feature guesses, and a warning when a run
ends with (almost) nothing valid."""
import ast
import pathlib
import warnings

import numpy as np
import pytest

from dic._track import Tracker, track
from dic.correlation.features import feature_matches
from dic.correlation.guesses import _REGISTRY, GuessContext, available_guesses, get_guess, register_guess
from dic.correlation.points import grid, grid_points
from dic.synth import speckle_pair
from kernels.conventions import Status

ROOT = pathlib.Path(__file__).resolve().parents[2]


def _stays_inside(f, shift, shape, half=10):
    """POIs whose subset, moved by ``shift``, stays inside the image (the others are OUT_OF_BOUNDS)."""
    x, y = f.points[:, 0] + shift[0], f.points[:, 1] + shift[1]
    return (x - half >= 0) & (x + half <= shape[1] - 1) & (y - half >= 0) & (y + half <= shape[0] - 1)


def test_roi_has_one_meaning_for_2d_and_stereo():
    """The same ROI selects the same POIs in the 2-D grid and the stereo lattice (before, a box one POI
    wide was valid in 2-D and refused in stereo, and an integer mask was read as a box in stereo)."""
    shape = (100, 160)
    mask = np.zeros(shape, np.uint8)
    mask[:50, 70:] = 255
    for roi in [(40, 20, 80, 60), (50, 20, 50, 60), (50.5, 20, 50.5, 60.2), mask, mask.astype(bool)]:
        if roi[0] == 50.5 if isinstance(roi, tuple) else False:
            # a box between grid columns holds no POI: both refuse it the same way
            for make in (lambda r: grid(shape, 10, margin=10, roi=r), lambda r: grid_points(shape, 10, 21, roi=r)):
                with pytest.raises(ValueError, match="empty ROI"):
                    make(roi)
            continue
        pts2d = grid(shape, 10, margin=10, roi=roi)
        pts, _, in_roi = grid_points(shape, 10, 21, roi=roi)
        assert np.array_equal(pts2d, pts[in_roi])
    for make in (lambda r: grid(shape, 10, margin=10, roi=r), lambda r: grid_points(shape, 10, 21, roi=r)):
        with pytest.raises(ValueError, match="is empty"):
            make((80, 20, 40, 60))
        with pytest.raises(ValueError, match="roi mask must have the image shape"):
            make(np.ones((10, 10), bool))


def test_polygon_and_mask_file_regions_have_one_meaning(tmp_path):
    """Polygons (inside or on the edge) and mask image files select the same POIs in the 2-D grid and the
    stereo lattice; the polygon rule is checked against exact integer arithmetic."""
    from dic.correlation.points import region
    from kernels.images import write_image

    shape = (100, 160)
    # a triangle with integer vertices: lattice point (x, y) is inside or on the edge iff x >= 30, y >= 10 and
    # 80 (x - 30) + 100 (y - 10) <= 8000 (exact, no rounding)
    tri = [(30, 10), (130, 10), (30, 90)]
    pts2d = grid(shape, 10, margin=10, roi=tri)
    x, y = pts2d[:, 0], pts2d[:, 1]
    assert np.all((x >= 30) & (y >= 10) & (80 * (x - 30) + 100 * (y - 10) <= 8000))
    full = grid(shape, 10, margin=10)
    fx, fy = full[:, 0], full[:, 1]
    expected = full[(fx >= 30) & (fy >= 10) & (80 * (fx - 30) + 100 * (fy - 10) <= 8000)]
    assert np.array_equal(pts2d, expected) and len(expected) == 50
    assert [50.0, 10.0] in pts2d.tolist() and [80.0, 50.0] in pts2d.tolist()  # on the edges: inside
    # a polygon that is the box, in any vertex order, selects what the box selects
    box = (40, 20, 80, 60)
    for poly in ([(40, 20), (80, 20), (80, 60), (40, 60)], np.array([(40, 60), (80, 60), (80, 20), (40, 20)], float)):
        assert np.array_equal(grid(shape, 10, margin=10, roi=poly), grid(shape, 10, margin=10, roi=box))
    mask = np.zeros(shape, np.uint8)
    mask[:50, 70:] = 255
    write_image(tmp_path / "mask.png", mask)
    assert np.array_equal(grid(shape, 10, margin=10, roi=tmp_path / "mask.png"), grid(shape, 10, margin=10, roi=mask))
    for roi in (tri, tmp_path / "mask.png", str(tmp_path / "mask.png"), region(tri, shape)):
        pts, _, in_roi = grid_points(shape, 10, 21, roi=roi)
        assert np.array_equal(grid(shape, 10, margin=10, roi=roi), pts[in_roi])
    assert region(tri, shape).settings() == {"polygon": [[30.0, 10.0], [130.0, 10.0], [30.0, 90.0]]}
    s = region(tmp_path / "mask.png", shape).settings()
    assert s["mask"] == str(tmp_path / "mask.png") and s["shape"] == [100, 160] and len(s["sha256"]) == 64
    assert s["sha256"] == region(mask, shape).settings()["sha256"]
    # clear errors
    write_image(tmp_path / "small.png", mask[:50])
    for bad, msg in [([(0, 0), (10, 0)], "at least 3 vertices"), ([(0, 0), (5, 5), (10, 10)], "zero area"),
                     ([(0, 0), (10, 0), (np.nan, 5)], "finite"), ([1, 2, 3], "a polygon"),
                     (tmp_path / "nope.png", "image file not found"),
                     (tmp_path / "small.png", "is 160x50 px but the images are 160x100 px"),
                     ([(200, 200), (210, 200), (210, 210)], "empty ROI")]:
        with pytest.raises(ValueError, match=msg):
            grid(shape, 10, margin=10, roi=bad)


def test_polygon_rule_matches_opencv(rng):
    """The vectorised polygon rule gives cv2.pointPolygonTest(...) >= 0 (inside or on the edge) on random
    polygons, convex or not, self-intersecting or not, with vertices in whole and half pixels."""
    import cv2

    from dic.correlation.points import lattice, roi_mask

    shape = (60, 80)
    pts, _ = lattice(shape, 1)
    for k in range(40):
        n = int(rng.integers(3, 9))
        v = np.round(rng.uniform([-5, -5], [85, 65], size=(n, 2)) * (2 if k % 2 else 1)) / (2 if k % 2 else 1)
        if k % 5 == 0:  # axis-aligned edges through many lattice points
            v = np.array([[10, 5], [60, 5], [60, 40], [30, 40], [30, 20], [10, 20]], float) + k // 5
        contour = v.astype(np.float32).reshape(-1, 1, 2)
        try:
            mine = roi_mask(pts, v, shape)
        except ValueError:  # zero area: refused
            continue
        ref = np.array([cv2.pointPolygonTest(contour, (float(x), float(y)), False) >= 0 for x, y in pts])
        assert np.array_equal(mine, ref), (k, v.tolist(), np.flatnonzero(mine != ref)[:5])


def test_guesses_by_name_and_extensible():
    assert {"prior", "zncc", "fft", "pyramid", "rg", "shift", "features", "epipolar"} <= set(available_guesses())
    with pytest.raises(ValueError, match="unknown initial-guess strategy 'nope'.*zncc"):
        get_guess("nope")
    shift = (23.0, -17.0)
    ref, cur = speckle_pair((160, 180), lambda x, y: (shift[0] + 0 * x, shift[1] + 0 * y), seed=5)

    @register_guess("oracle")
    def _oracle(ctx: GuessContext, idx):
        g = np.zeros((idx.size, 6 if ctx.order == 1 else 12))
        g[:, 0], g[:, g.shape[1] // 2] = shift
        return g, np.ones(idx.size, bool)

    try:
        f = track(ref, cur, step=10, search="oracle")
    finally:
        _REGISTRY.pop("oracle")
    inside = _stays_inside(f, shift, ref.shape)
    assert np.count_nonzero(f.valid[inside]) > 0.95 * np.count_nonzero(inside) > 0
    assert np.allclose(f.u[f.valid], shift[0], atol=0.02) and np.allclose(f.v[f.valid], shift[1], atol=0.02)
    with pytest.raises(ValueError, match="search must be None or one of"):
        Tracker(ref, search="epipolar")  # needs a stereo rig


def test_large_motion_without_search_says_what_to_try():
    """A 23 px motion without a search gives no valid point; the run warns and names the search option."""
    ref, cur = speckle_pair((160, 180), lambda x, y: (23.0 + 0 * x, 0.0 * y), seed=6)
    with pytest.warns(RuntimeWarning, match=r"only \d+ of \d+ points are valid.*search"):
        f = track(ref, cur, step=10)
    assert np.count_nonzero(f.valid) < 0.05 * f.n_points
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        f = track(ref, cur, step=10, search="zncc")
    inside = _stays_inside(f, (23.0, 0.0), ref.shape)
    assert np.count_nonzero(f.valid[inside]) > 0.95 * np.count_nonzero(inside) > 0


def test_feature_matches_are_repeatable():
    """SIFT + FLANN gave different matches on a second call in the same process (FLANN's random trees
    drew from OpenCV's global RNG); the same images must give the same matches."""
    ref, cur = speckle_pair((240, 320), lambda x, y: (4.3 + 0.01 * x, -2.1 + 0 * y), seed=7, radius=2.5)
    first = feature_matches(ref, cur)
    for _ in range(3):
        again = feature_matches(ref, cur)
        assert np.array_equal(first[0], again[0]) and np.array_equal(first[1], again[1])
    assert first[0].shape[0] > 50


def _imports(path: pathlib.Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            yield node.module, {a.name for a in node.names}
        elif isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, set()


def test_one_engine_runs_icgn():
    """Only the correlation engine calls the IC-GN kernels' launchers: 2-D tracking and stereo DIC both go
    through dic.correlation.engine (one correlation engine in the code)."""
    launchers = {"icgn", "prepare_subsets", "prepare_reference"}
    users = []
    for path in sorted((ROOT / "dic").rglob("*.py")):
        for module, names in _imports(path):
            if module == "kernels.icgn" and names & launchers:
                users.append(path.relative_to(ROOT).as_posix())
    assert users == ["dic/correlation/engine.py"], users


def test_status_code_for_implausible_warps_is_not_a_kernel_code():
    assert int(Status.IMPLAUSIBLE_WARP) == 7
    assert Status.IMPLAUSIBLE_WARP.name not in ("CONVERGED", "MAX_ITERATIONS")


def test_second_opinion_row_median_is_numpys_nanmedian_bit_for_bit():
    """The second opinion's neighbour median (rows of 8 with missing neighbours as NaN, odd and even counts,
    ties) is np.nanmedian's value exactly."""
    from dic.correlation.acceptance import _row_nanmedian

    rng = np.random.default_rng(5)
    values = 0.9 + 0.1 * rng.random((4000, 8))
    values[rng.random(values.shape) < 0.35] = np.nan
    values[:, 0] = np.where(np.isnan(values[:, 0]), 0.95, values[:, 0])  # at least one finite value per row
    values[::5, 3] = values[::5, 0]  # ties
    counts = np.count_nonzero(~np.isnan(values), axis=1)
    assert {1, 2, 7, 8} <= set(counts.tolist())  # odd and even counts
    assert np.array_equal(_row_nanmedian(values), np.nanmedian(values, axis=1))


def test_second_opinion_neighbours_kept_for_the_same_accepted_points():
    """second_opinion_candidates(cache=): a call with the accepted points of the call before reuses its neighbours
    and gives what a new search gives; other accepted points are searched again (and replace the kept ones)."""
    from dic.correlation.acceptance import second_opinion_candidates

    rng = np.random.default_rng(5)
    x, y = np.meshgrid(np.arange(0.0, 200.0, 5.0), np.arange(0.0, 150.0, 5.0))
    points = np.column_stack([x.ravel(), y.ravel()])
    zncc = 0.99 - 0.01 * rng.random(len(points))
    zncc[rng.choice(len(points), 40, replace=False)] = 0.85  # suspects among good neighbours
    accepted = rng.random(len(points)) < 0.9
    cache = {}
    fresh = second_opinion_candidates(points, zncc, accepted, 7.5, 0.05)
    first = second_opinion_candidates(points, zncc, accepted, 7.5, 0.05, cache=cache)
    kept = cache["second_opinion_neighbours"]
    again = second_opinion_candidates(points, zncc, accepted.copy(), 7.5, 0.05, cache=cache)
    assert cache["second_opinion_neighbours"] is kept  # reused, not searched again
    assert fresh[0].size > 10
    for a, b in ((fresh, first), (fresh, again)):
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
    other = accepted.copy()
    other[np.flatnonzero(other)[:25]] = False
    changed = second_opinion_candidates(points, zncc, other, 7.5, 0.05, cache=cache)
    assert cache["second_opinion_neighbours"] is not kept
    expected = second_opinion_candidates(points, zncc, other, 7.5, 0.05)
    np.testing.assert_array_equal(changed[0], expected[0])
    np.testing.assert_array_equal(changed[1], expected[1])
    # another radius: searched again
    second_opinion_candidates(points, zncc, other, 10.0, 0.05, cache=cache)
    assert cache["second_opinion_neighbours"][0] == 10.0
