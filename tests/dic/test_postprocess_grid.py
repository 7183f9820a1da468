"""Post-processing on the point grid: no value across a hole, an excluded region or invalid points (issue 25).

Ground truth: result files written directly (dic.store.ResultWriter) with exactly linear
displacement fields on a regular grid with a circular hole (the points a run whose region
excludes the hole has) and a block of points invalid in the last frame. Bilinear interpolation
of a linear field is exact, so values are compared at 1e-12; which query points have no value
is worked out here from the geometry (the corners of the grid cell around each query), not by
the code under test. The first test fails against the code before issue 25 (Delaunay over the
valid points bridged the hole).
"""
import math

import numpy as np
import pytest
from click.testing import CliRunner

from dic.cli import main
from dic.postprocess import extensometer, line_profile, point_history
from dic.store import ResultWriter

STEP = 4.0
X0 = 10.0
SIDE = 41  # nodes per side: x, y in [10, 170]
CX = CY = 90.0  # the hole's centre
RADIUS = 30.0  # nodes closer than this to the centre are no points of the result
FRAMES = (1, 2, 3)
BLOCK = (130.0, 142.0, 30.0, 42.0)  # x0, x1, y0, y1 of the points invalid in frame 3


def _u(k, x, y):
    a = 0.01 * k
    return a * (x - CX) + 0.2 * a * (y - CY) + 0.5 * k


def _v(k, x, y):
    a = 0.01 * k
    return -0.3 * a * (y - CY) + 0.1 * a * (x - CX) - 0.25 * k


def _is_point(x, y):
    """Whether the node (x, y) is a point of the result (on the grid, outside the hole)."""
    return (X0 <= x <= X0 + STEP * (SIDE - 1) and X0 <= y <= X0 + STEP * (SIDE - 1)
            and math.hypot(x - CX, y - CY) >= RADIUS)


def _in_block(x, y):
    return BLOCK[0] <= x <= BLOCK[1] and BLOCK[2] <= y <= BLOCK[3]


def _needed_nodes(x, y):
    """The grid nodes a bilinear value at (x, y) depends on (those of weight > 0)."""
    def axis(c):
        f = (c - X0) / STEP
        lo = math.floor(f)
        return [X0 + STEP * lo] if f == lo else [X0 + STEP * lo, X0 + STEP * (lo + 1)]
    return [(nx, ny) for nx in axis(x) for ny in axis(y)]


def _grid_points():
    g = X0 + STEP * np.arange(SIDE)
    gy, gx = np.meshgrid(g, g, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    return pts[np.hypot(pts[:, 0] - CX, pts[:, 1] - CY) >= RADIUS]


def _write_2d(path, pts, with_strain=True):
    from dic._strain import strain
    from dic.field2d import Field2D

    n = len(pts)
    with ResultWriter(path, reference_path="ref.tif", reference_shape=(181, 181), settings={"step": 4}) as w:
        for k in FRAMES:
            bad = np.array([k == 3 and _in_block(x, y) for x, y in pts])
            u = np.where(bad, np.nan, _u(k, pts[:, 0], pts[:, 1]))
            v = np.where(bad, np.nan, _v(k, pts[:, 0], pts[:, 1]))
            params = np.zeros((n, 6))
            params[:, 0], params[:, 3] = u, v
            f = Field2D(points=pts, u=u, v=v, params=params, zncc=np.full(n, 0.99), iterations=np.full(n, 4, np.int32),
                        status=np.where(bad, 5, 0).astype(np.int32), valid=~bad, subset=21, order=1, step=4)
            w.write_frame(k, f, strain=strain(f, window=5) if with_strain else None, path=f"cur{k}.tif")
    return path


@pytest.fixture(scope="module")
def holed(tmp_path_factory):
    """A 2-D result: linear u, v on a 41 x 41 grid (step 4 px) less a hole of radius 30 px at (90, 90)."""
    return _write_2d(tmp_path_factory.mktemp("grid") / "holed.h5", _grid_points())


def test_history_at_the_hole_centre_is_nan_with_the_reason(holed):
    for quantity in ("u", "eyy", "von_mises"):
        h = point_history(holed, (CX, CY), quantity)
        assert np.isnan(h.values).all(), f"{quantity} at the hole centre: {h.values}"  # was bridged before issue 25
        from dic.gridinterp import QueryStatus

        assert list(h.status) == [QueryStatus.NO_POINTS] * 3
        assert QueryStatus(h.status[0]).reason == "in a hole or an excluded region (no points there)"
    # just inside the hole's edge (a cell with one node in the hole): no value either
    h = point_history(holed, (CX + 29.0, CY + 1.0), "u")
    assert not _is_point(118.0, 90.0) and np.isnan(h.values).all()


def test_history_elsewhere_is_exact(holed):
    from dic.gridinterp import QueryStatus

    for x, y in ((31.3, 47.9), (150.0, 150.0), (123.0, 91.0), (X0, X0), (170.0, 123.4)):
        assert all(_is_point(*n) for n in _needed_nodes(x, y))
        h = point_history(holed, (x, y), "u")
        assert np.allclose(h.values, [_u(k, x, y) for k in FRAMES], rtol=0, atol=1e-12)
        assert list(h.status) == [QueryStatus.OK] * 3
        hv = point_history(holed, (x, y), "v", frames=[2])
        assert hv.values[0] == pytest.approx(_v(2, x, y), abs=1e-12)
    # a node on the hole's edge whose neighbours across it are missing: the node's own value
    x, y = 122.0, 90.0
    assert _is_point(x, y) and not _is_point(118.0, 90.0)
    h = point_history(holed, (x, y), "u")
    assert np.allclose(h.values, [_u(k, x, y) for k in FRAMES], rtol=0, atol=1e-12)
    # strain of a linear field: the fit is exact where it is valid
    # eyy is the Green-Lagrange strain (dic.strain's default type since issue 25): dv/dy + (du/dy² + dv/dy²) / 2
    h = point_history(holed, (40.0, 40.0), "eyy")
    want = [-0.003 * k + 0.5 * ((0.002 * k) ** 2 + (0.003 * k) ** 2) for k in FRAMES]
    assert np.allclose(h.values, want, rtol=0, atol=1e-12)


def test_invalid_points_give_nan_in_their_frames_only(holed):
    from dic.gridinterp import QueryStatus

    h = point_history(holed, (137.0, 35.0), "u")  # inside the block invalid in frame 3
    assert np.allclose(h.values[:2], [_u(k, 137.0, 35.0) for k in (1, 2)], rtol=0, atol=1e-12)
    assert np.isnan(h.values[2]) and list(h.status) == [QueryStatus.OK, QueryStatus.OK, QueryStatus.INVALID]
    assert QueryStatus.INVALID.reason == "among points with no valid value in the frame"
    # a cell with one corner in the block (x = 126..130): no value in frame 3
    h = point_history(holed, (128.0, 33.0), "u")
    assert np.isfinite(h.values[:2]).all() and np.isnan(h.values[2])


def test_point_outside_the_grid_is_nan_with_the_reason(holed):
    from dic.gridinterp import QueryStatus

    # within one grid spacing of the points: NaN with the reason
    for p in ((7.0, 40.0), (40.0, 170.5), (8.0, 8.0)):
        h = point_history(holed, p, "u")
        assert np.isnan(h.values).all() and list(h.status) == [QueryStatus.OUTSIDE] * 3
    # farther out: refused before any frame is read (issue 24, "history at a point outside the image")
    for p in ((300.0, 40.0), (-5.0, 40.0), (5.0, 5.0)):
        with pytest.raises(ValueError, match="lies outside the measured points"):
            point_history(holed, p, "u")
    assert QueryStatus.OUTSIDE.reason == "outside the grid of points"


def test_profile_crossing_the_hole(holed):
    from dic.gridinterp import QueryStatus

    y = 92.0  # between the grid rows y = 90 and 94
    p = line_profile(holed, (20.0, y), (160.0, y), "u", samples=71)  # every 2 px: on and between grid lines
    assert p.values.shape == (3, 71) and p.status.shape == (3, 71)
    expect_value = np.array([all(_is_point(*n) for n in _needed_nodes(x, y)) for x in p.positions[:, 0]])
    assert 10 < np.count_nonzero(~expect_value) < 40 and expect_value[0] and expect_value[-1]
    for k, frame in enumerate(FRAMES):
        assert np.array_equal(np.isfinite(p.values[k]), expect_value)
        assert np.array_equal(p.status[k] == QueryStatus.NO_POINTS, ~expect_value)
        want = _u(frame, p.positions[:, 0], y)
        assert np.allclose(p.values[k][expect_value], want[expect_value], rtol=0, atol=1e-12)
    # the samples without a value are those within a cell of the hole
    gap = p.positions[~expect_value, 0]
    assert gap.min() > CX - RADIUS - STEP and gap.max() < CX + RADIUS + STEP


def test_extensometer_across_the_hole_and_in_it(holed):
    from dic.gridinterp import QueryStatus

    a, b = (20.0, 92.0), (160.0, 92.0)  # ends outside the hole: the gauge spans it
    ext = extensometer(holed, a, b)
    assert ext.valid.all() and (ext.start_status == QueryStatus.OK).all() and (ext.end_status == QueryStatus.OK).all()
    for k, frame in enumerate(FRAMES):
        A = np.array(a) + [_u(frame, *a), _v(frame, *a)]
        B = np.array(b) + [_u(frame, *b), _v(frame, *b)]
        assert ext.strain[k] == pytest.approx(np.linalg.norm(B - A) / 140.0 - 1, abs=1e-12)
    ext = extensometer(holed, (CX, CY), b)
    assert not ext.valid.any() and np.isnan(ext.strain).all()
    assert (ext.start_status == QueryStatus.NO_POINTS).all() and (ext.end_status == QueryStatus.OK).all()


def test_at_mm_is_the_same_grid(holed):
    from dic.gridinterp import QueryStatus

    s = 0.05
    h = point_history(holed, (CX * s, CY * s), "u", at="mm", scale=s)
    assert np.isnan(h.values).all() and (h.status == QueryStatus.NO_POINTS).all()
    h = point_history(holed, (31.3 * s, 47.9 * s), "u", at="mm", scale=s)
    assert np.allclose(h.values, [_u(k, 31.3, 47.9) * s for k in FRAMES], rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# points on no grid: the Delaunay fallback refuses triangles longer than 1.5 point spacings


def test_scattered_points_fallback_does_not_bridge(tmp_path):
    from dic.gridinterp import QueryStatus, TriangleCells, cells_for

    rng = np.random.default_rng(3)
    pts = _grid_points() + rng.uniform(-0.6, 0.6, size=(len(_grid_points()), 2))
    assert isinstance(cells_for(pts), TriangleCells)  # not on a grid
    path = _write_2d(tmp_path / "scattered.h5", pts, with_strain=False)
    h = point_history(path, (CX, CY), "u")
    assert np.isnan(h.values).all() and (h.status == QueryStatus.NO_POINTS).all()
    with pytest.raises(ValueError, match="lies outside the measured points"):
        point_history(path, (300.0, 40.0), "u")
    # linear on each triangle: exact for a linear field away from the hole
    for x, y in ((31.3, 47.9), (150.0, 150.0), (60.0, 140.0)):
        h = point_history(path, (x, y), "u")
        assert np.allclose(h.values, [_u(k, x, y) for k in FRAMES], rtol=0, atol=1e-12)
    # one missing point in a scattered set: no triangle spans it (its edges would be ~2 spacings)
    keep = np.ones(len(pts), bool)
    lone = np.argmin(np.hypot(pts[:, 0] - 40.0, pts[:, 1] - 140.0))
    keep[lone] = False
    cells = TriangleCells.scattered(pts[keep])
    located = cells.locate(pts[lone])
    assert located.status[0] == QueryStatus.NO_POINTS


def test_scattered_fallback_needs_valid_corners():
    from dic.gridinterp import QueryStatus, TriangleCells

    g = np.arange(6, dtype=float)
    gy, gx = np.meshgrid(g, g, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()]) + 1e-3 * np.sin(np.arange(36))[:, None]
    cells = TriangleCells.scattered(pts)
    located = cells.locate([[2.5, 2.5], [0.5, 4.5]])
    values = 3.0 * pts[:, 0] - 2.0 * pts[:, 1] + 1.0
    valid = np.ones(36, bool)
    out, status = located.evaluate(values, valid)
    assert np.allclose(out[:, 0], [3 * 2.5 - 2 * 2.5 + 1, 3 * 0.5 - 2 * 4.5 + 1], rtol=0, atol=1e-12)
    valid[np.argmin(np.hypot(pts[:, 0] - 2, pts[:, 1] - 2))] = False
    valid[np.argmin(np.hypot(pts[:, 0] - 3, pts[:, 1] - 3))] = False
    out, status = located.evaluate(values, valid)
    assert np.isnan(out[0, 0]) and status[0] == QueryStatus.INVALID and status[1] == QueryStatus.OK


# ------------------------------------------------------------------------------------------------
# stereo: values at the left reference image's grid points (px), or over their (X, Y) (mm)


def _stereo_file(path, hole_computed=False):
    """Stereo results on the grid less the hole, or (``hole_computed``) on the whole grid with the
    hole's points NOT_COMPUTED (as a stereo run with a region gives them) and the block MATCH_FAILED."""
    from test_store import fake_match, fake_rig

    from dic.field3d import Field3D, StereoStatus

    if hole_computed:
        g = X0 + STEP * np.arange(SIDE)
        gy, gx = np.meshgrid(g, g, indexing="ij")
        pts = np.column_stack([gx.ravel(), gy.ravel()])
        status = np.where([not _is_point(x, y) for x, y in pts], StereoStatus.NOT_COMPUTED,
                          np.where([_in_block(x, y) for x, y in pts], StereoStatus.MATCH_FAILED, StereoStatus.OK))
    else:
        pts = _grid_points()
        status = np.zeros(len(pts), np.int8)
    status = status.astype(np.int8)
    n = len(pts)
    X, Y = 0.2 * (pts[:, 0] - CX), 0.2 * (pts[:, 1] - CY)
    Z = 500.0 + 0.3 * X - 0.1 * Y
    full = lambda v: np.full(n, float(v))  # noqa: E731
    with ResultWriter(path, kind="stereo", rig=fake_rig(), reference_path=("l0.tif", "r0.tif"),
                      reference_shape=(181, 181), settings={"step": 4}) as w:
        w.write_match(fake_match(n))
        for k, e in enumerate((0.0, 0.004, 0.008)):
            f = Field3D(points=pts, grid_shape=None, X=X, Y=Y, Z=Z, U=e * X, V=np.zeros(n), W=0.5 * e * X + 0.1 * e * Y,
                        exx=full(e), eyy=full(-0.3 * e), exy=full(0.1 * e), normal=np.tile([0.0, 0.0, -1.0], (n, 1)),
                        zncc_stereo=full(0.99), zncc_left=full(0.98), zncc_right=full(0.97), epipolar_ref_px=full(0.01),
                        epipolar_px=full(0.01), reprojection_ref_px=full(0.01), reprojection_px=full(0.01),
                        status=status, strain_valid=status == 0, index=k)
            w.write_frame(k, f, path=(f"l{k}.tif", f"r{k}.tif"))
    return path


def test_stereo_history_in_a_cut_out_is_nan(tmp_path):
    from dic.gridinterp import QueryStatus

    path = _stereo_file(tmp_path / "stereo.h5")
    es = np.array([0.0, 0.004, 0.008])
    for quantity in ("W", "U", "eyy"):
        h = point_history(path, (CX, CY), quantity)
        assert np.isnan(h.values).all() and (h.status == QueryStatus.NO_POINTS).all()
    # (X, Y) mm of the hole's centre: no triangle of the grid's cells there
    h = point_history(path, (0.0, 0.0), "W", at="mm")
    assert np.isnan(h.values).all() and (h.status == QueryStatus.NO_POINTS).all()
    with pytest.raises(ValueError, match="lies outside the measured points"):
        point_history(path, (100.0, 0.0), "W", at="mm")
    # elsewhere exact (the fields are affine in x, y and in X, Y)
    x, y = 31.3, 47.9
    X, Y = 0.2 * (x - CX), 0.2 * (y - CY)
    for at, p in (("px", (x, y)), ("mm", (X, Y))):
        h = point_history(path, p, "W", at=at)
        assert np.allclose(h.values, 0.5 * es * X + 0.1 * es * Y, rtol=0, atol=1e-12)
    p = line_profile(path, (20.0, 92.0), (160.0, 92.0), "U", samples=71)
    expect_value = np.array([all(_is_point(*n) for n in _needed_nodes(x, 92.0)) for x in p.positions[:, 0]])
    assert np.array_equal(np.isfinite(p.values[2]), expect_value)
    assert np.allclose(p.values[2][expect_value], 0.008 * 0.2 * (p.positions[expect_value, 0] - CX), rtol=0, atol=1e-12)


def test_stereo_points_not_computed_are_no_points(tmp_path):
    from dic.gridinterp import QueryStatus

    path = _stereo_file(tmp_path / "stereo_full.h5", hole_computed=True)
    for at, p in (("px", (CX, CY)), ("mm", (0.0, 0.0))):
        h = point_history(path, p, "W", at=at)
        assert np.isnan(h.values).all() and (h.status == QueryStatus.NO_POINTS).all()
    h = point_history(path, (137.0, 35.0), "U")  # among MATCH_FAILED points: invalid, not a hole
    assert np.isnan(h.values).all() and (h.status == QueryStatus.INVALID).all()
    h = point_history(path, (31.3, 47.9), "U")
    assert np.allclose(h.values, np.array([0.0, 0.004, 0.008]) * 0.2 * (31.3 - CX), rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# CLI: why there is no value


def _invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_cli_says_why(holed):
    r = _invoke("history", holed, "--point", "90,90", "--quantity", "eyy")
    assert r.exit_code == 1 and "Traceback" not in r.output
    assert r.output.strip() == ("Error: no value at the point (90, 90) px in any frame: it is in a hole or an "
                                "excluded region (no points there)")
    r = _invoke("history", holed, "--point", "300,40")
    assert r.exit_code == 1 and "lies outside the measured points" in r.output
    r = _invoke("history", holed, "--point", "137,35", "--quantity", "u")
    assert r.exit_code == 0, r.output
    assert ("Warning: no value at the point (137, 35) px in frame 3: it is among points with no valid value in "
            "the frame") in r.output
    r = _invoke("profile", holed, "--from", "20,92", "--to", "160,92", "--samples", 71, "-q")
    assert r.exit_code == 0, r.output
    x = np.linspace(20.0, 160.0, 71)  # the samples; those in a cell with a node in the hole have no value
    gap = x[[not all(_is_point(*n) for n in _needed_nodes(xi, 92.0)) for xi in x]] - 20.0
    assert r.output.strip() == (f"Warning: no value at {gap.size} of 71 samples ({gap.min():.4g} to {gap.max():.4g} px "
                                "along the line) in every frame: in a hole or an excluded region (no points there)")
    r = _invoke("profile", holed, "--from", "80,88", "--to", "100,92", "-q")
    assert r.exit_code == 1 and "no value along the line from (80, 88) px to (100, 92) px in any frame" in r.output
    r = _invoke("extensometer", holed, "--from", "20,92", "--to", "160,92", "-q")
    assert r.exit_code == 0 and r.output == ""
    r = _invoke("extensometer", holed, "--from", "90,90", "--to", "160,92")
    assert r.exit_code == 1
    assert "no value at the gauge start (90, 90) px in any frame: it is in a hole" in r.output


# ------------------------------------------------------------------------------------------------
# the CLI's post-processing imports neither Warp nor Matplotlib nor scipy.ndimage (0.5-2.5 s of
# every command before issue 25), and the package's names stay what they were


def test_post_processing_imports_stay_light():
    import subprocess
    import sys

    code = ("import sys, dic.cli, dic.commands.postprocess, dic.postprocess, dic.gridinterp, dic.store; "
            "print(sorted(m for m in ('warp', 'matplotlib', 'scipy.ndimage', 'dic._track', 'dic.sequence') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
    code = ("import types, dic, dic._track, dic._strain; from dic._strain import StrainPlan; import dic._stereo; "
            "print([isinstance(getattr(dic, n), types.FunctionType) for n in ('track', 'strain', 'stereo', "
            "'triangulate')], dic.Tracker.__module__, dic.write_figures.__module__, type(dic.sequence).__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[True, True, True, True] dic._track dic.plots.fields module"
