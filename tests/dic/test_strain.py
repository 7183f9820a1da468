"""Pointwise least-squares strain (dic/_strain.py) against analytic fields with exact derivatives."""
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import ndimage

from dic._strain import StrainField, StrainPlan, grid_layout, strain


def make_field(fun, *, step=3.0, nx=20, ny=15, x0=10.0, y0=12.0, valid=None):
    """A minimal Field2D stand-in: points on a grid, u, v = fun(x, y), valid."""
    xs, ys = np.meshgrid(x0 + step * np.arange(nx), y0 + step * np.arange(ny))
    points = np.stack([xs.ravel(), ys.ravel()], 1)
    u, v = fun(points[:, 0], points[:, 1])
    if valid is None:
        valid = np.ones(len(points), bool)
    return SimpleNamespace(points=points, u=np.asarray(u, float), v=np.asarray(v, float), valid=valid)


def green_lagrange(ux, uy, vx, vy):
    """Independent reference: E = (F^T F - I) / 2 with F = I + grad u."""
    F = np.array([[1 + ux, uy], [vx, 1 + vy]])
    return 0.5 * (F.T @ F - np.eye(2))


def test_affine_field_is_exact_everywhere_even_with_holes(rng):
    G = np.array([[0.012, -0.004], [0.007, -0.009]])  # [[ux, uy], [vx, vy]]

    def affine(x, y):
        return 0.3 + G[0, 0] * x + G[0, 1] * y, -1.2 + G[1, 0] * x + G[1, 1] * y

    valid = rng.random(300) > 0.15
    f = make_field(affine, valid=valid)
    s = strain(f, window=5, strain_type="small")  # exx... the small strain (Exx... Green-Lagrange whatever the type)
    # a plane fit reproduces a plane exactly (any window shape, borders and holes included):
    # only float64 rounding remains, bound 1e-12
    assert s.valid.sum() > 0.8 * valid.sum() and not np.any(s.valid & ~valid)
    ok = s.valid
    for name, val in [("dudx", G[0, 0]), ("dudy", G[0, 1]), ("dvdx", G[1, 0]), ("dvdy", G[1, 1])]:
        assert np.max(np.abs(getattr(s, name)[ok] - val)) < 1e-12
    E = green_lagrange(G[0, 0], G[0, 1], G[1, 0], G[1, 1])
    assert np.max(np.abs(s.Exx[ok] - E[0, 0])) < 1e-12
    assert np.max(np.abs(s.Eyy[ok] - E[1, 1])) < 1e-12
    assert np.max(np.abs(s.Exy[ok] - E[0, 1])) < 1e-12
    assert np.max(np.abs(s.exy[ok] - 0.5 * (G[0, 1] + G[1, 0]))) < 1e-12
    assert np.all(np.isnan(s.exx[~s.valid]))


def test_quadratic_field_exact_in_the_interior():
    def quad(x, y):
        return (1e-3 * x + 2e-4 * x * x - 3e-4 * x * y + 1e-4 * y * y,
                -2e-3 * y + 5e-5 * x * x + 4e-4 * x * y - 2e-4 * y * y)

    def grads(x, y):
        return (1e-3 + 4e-4 * x - 3e-4 * y, -3e-4 * x + 2e-4 * y,
                1e-4 * x + 4e-4 * y, -2e-3 + 4e-4 * x - 4e-4 * y)

    f = make_field(quad, step=2.0, nx=25, ny=21)
    s = strain(f, window=7)
    gx, gy = f.points.T
    exact = grads(gx, gy)
    cols, rows = s.grid_index.T
    interior = (cols >= 3) & (cols <= 21) & (rows >= 3) & (rows <= 17)
    for got, want in zip((s.dudx, s.dudy, s.dvdx, s.dvdy), exact):
        # symmetric full window: quadratic terms are orthogonal to the plane basis -> exact
        assert np.max(np.abs(got[interior] - want[interior])) < 1e-12
        # one-sided windows at the border: error = second derivative x offset of the window's
        # centroid (<= 1.5 grid steps = 3 px) -> <= 8e-4 * 3 = 2.4e-3
        assert np.max(np.abs(got - want)) < 2.5e-3


def test_finite_rotation_has_zero_green_lagrange_strain():
    th = np.deg2rad(5.0)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])

    def rot(x, y):
        X = np.stack([x, y])
        d = (R - np.eye(2)) @ X
        return d[0], d[1]

    s = strain(make_field(rot), strain_type="small")
    assert np.max(np.abs(np.stack([s.Exx, s.Eyy, s.Exy]))) < 1e-12  # exact for a rigid motion
    assert np.allclose(s.exx, np.cos(th) - 1, atol=1e-12)  # the small strain is not objective


def test_to_grid_and_layout():
    f = make_field(lambda x, y: (0.01 * x, 0.0 * y), step=4.0, nx=6, ny=4)
    keep = np.arange(24) != 7
    f2 = make_field(lambda x, y: (0.01 * x, 0.0 * y), step=4.0, nx=6, ny=4)
    f2.points, f2.u, f2.v, f2.valid = f.points[keep], f.u[keep], f.v[keep], f.valid[keep]
    s = strain(f2, window=3)
    g = s.to_grid("exx")
    # u = 0.01 x: Green-Lagrange (the default type) exx = 0.01 + 0.01² / 2
    assert g.shape == (4, 6) and np.isnan(g[1, 1]) and np.allclose(g[~np.isnan(g)], 0.01 + 0.5 * 0.01**2, rtol=0, atol=1e-14)
    xs, ys = s.grid_axes()
    assert np.allclose(xs, 10 + 4 * np.arange(6)) and np.allclose(ys, 12 + 4 * np.arange(4))
    index, shape, step = grid_layout(f.points)
    assert shape == (4, 6) and step == (4.0, 4.0)


def test_bad_input():
    f = make_field(lambda x, y: (0 * x, 0 * y))
    with pytest.raises(ValueError, match="odd integer >= 3"):
        strain(f, window=4)
    with pytest.raises(ValueError, match="points, u, v"):
        strain(object())
    g = make_field(lambda x, y: (0 * x, 0 * y))
    g.points = g.points + np.random.default_rng(0).normal(0, 0.3, g.points.shape)
    with pytest.raises(ValueError, match="not on a regular grid"):
        strain(g)
    h = make_field(lambda x, y: (0 * x, 0 * y))
    h.u = h.u[:-1]
    with pytest.raises(ValueError, match="must have shape"):
        strain(h)
    line = make_field(lambda x, y: (0.01 * x, 0 * y), ny=1)
    assert not np.any(strain(line).valid)  # collinear points: no plane can be fitted


def _reference_strain(field, window):
    """The strain as dic.strain computed it before StrainPlan (every array from scratch): the
    reference that the plan's cached layout and fits must match bit for bit."""
    points = np.asarray(field.points, np.float64)
    u, v = np.asarray(field.u, np.float64), np.asarray(field.v, np.float64)
    valid = np.asarray(field.valid, bool) & np.isfinite(u) & np.isfinite(v)
    index, shape, step = grid_layout(points)
    min_points = max(3, (window // 2 + 1) ** 2)
    mask, ug, vg = np.zeros(shape), np.zeros(shape), np.zeros(shape)
    mask[index[valid, 1], index[valid, 0]] = 1.0
    ug[index[valid, 1], index[valid, 0]] = u[valid]
    vg[index[valid, 1], index[valid, 0]] = v[valid]
    h = window // 2
    off = np.arange(-h, h + 1, dtype=np.float64)
    kx = np.broadcast_to(off[None, :], (window, window))
    ky = np.broadcast_to(off[:, None], (window, window))
    ones = np.ones((window, window))

    def corr(a, k):
        return ndimage.correlate(a, k, mode="constant", cval=0.0)

    s0, sx, sy = corr(mask, ones), corr(mask, kx), corr(mask, ky)
    sxx, sxy, syy = corr(mask, kx * kx), corr(mask, kx * ky), corr(mask, ky * ky)
    M = np.stack([np.stack([s0, sx, sy], -1), np.stack([sx, sxx, sxy], -1), np.stack([sy, sxy, syy], -1)], -2)
    rhs_u = np.stack([corr(ug, ones), corr(ug, kx), corr(ug, ky)], -1)
    rhs_v = np.stack([corr(vg, ones), corr(vg, kx), corr(vg, ky)], -1)
    r, c = index[:, 1], index[:, 0]
    n_fit = np.rint(s0[r, c]).astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        cxx = sxx[r, c] - sx[r, c] ** 2 / s0[r, c]
        cyy = syy[r, c] - sy[r, c] ** 2 / s0[r, c]
        cxy = sxy[r, c] - sx[r, c] * sy[r, c] / s0[r, c]
        det = cxx * cyy - cxy**2
    ok = valid & (n_fit >= min_points) & (det > 1e-6 * np.maximum(s0[r, c], 1.0) ** 2)
    grads = np.full((len(points), 4), np.nan)
    if np.any(ok):
        sol = np.linalg.solve(M[r, c][ok], np.stack([rhs_u[r[ok], c[ok]], rhs_v[r[ok], c[ok]]], -1))
        grads[ok] = np.stack([sol[:, 1, 0] / step[0], sol[:, 2, 0] / step[1],
                              sol[:, 1, 1] / step[0], sol[:, 2, 1] / step[1]], -1)
    ux, uy, vx, vy = grads.T
    return {"dudx": ux, "dudy": uy, "dvdx": vx, "dvdy": vy, "exx": ux, "eyy": vy, "exy": 0.5 * (uy + vx),
            "Exx": ux + 0.5 * (ux * ux + vx * vx), "Eyy": vy + 0.5 * (uy * uy + vy * vy),
            "Exy": 0.5 * (uy + vx + ux * uy + vx * vy), "valid": ok, "n_fit": n_fit, "grid_index": index,
            "points": points}


def _bits(a):
    a = np.ascontiguousarray(a)
    return a.dtype.str, a.shape, a.tobytes()


def _assert_same_strain(s, ref):
    names = StrainField.COMPONENTS + ("valid", "n_fit", "grid_index", "points")
    if isinstance(ref, dict):
        assert [_bits(getattr(s, k)) for k in names] == [_bits(ref[k]) for k in names]
    else:
        assert [_bits(getattr(s, k)) for k in names] == [_bits(getattr(ref, k)) for k in names]
        assert (s.window, s.step, s.grid_shape) == (ref.window, ref.step, ref.grid_shape)


@pytest.mark.parametrize("window", [3, 5, 7])
def test_a_plan_reused_over_frames_is_strain_bit_for_bit(rng, window):
    """One StrainPlan over frames whose valid points change (the cached fits recomputed), stay the same
    (the cache reused) or come back: every frame bit for bit the strain computed from scratch."""
    base = make_field(lambda x, y: (0.0 * x, 0.0 * y), step=5.0, nx=31, ny=27)
    keep = np.ones(len(base.points), bool)
    keep[rng.choice(len(keep), 40, replace=False)] = False  # an ROI: a subset of the grid
    points = base.points[keep]
    n = len(points)
    plan = StrainPlan(points, window=window, strain_type="small")  # _reference_strain's exx is the small strain
    masks = [np.ones(n, bool), rng.random(n) > 0.05, None, rng.random(n) > 0.6, None, None, np.zeros(n, bool)]
    masks[2] = masks[1].copy()  # the same valid points again: the cached fits are used
    masks[4] = masks[5] = masks[1]  # back after other ones: recomputed, then used
    hits = 0
    for k, valid in enumerate(masks):
        u = 0.01 * points[:, 0] - 0.004 * points[:, 1] + rng.normal(0, 0.05, n)
        v = 0.002 * points[:, 0] ** 1.5 / 40 + rng.normal(0, 0.05, n)
        if k == 3:
            u[rng.choice(n, 7)] = np.nan  # non-finite displacements are left out, as invalid points
        field = SimpleNamespace(points=points.copy(), u=u, v=v, valid=valid.copy())
        before = plan._fits_cache
        s = plan.strain(field)
        hits += before is not None and plan._fits_cache is before
        _assert_same_strain(s, _reference_strain(field, window))
        _assert_same_strain(s, strain(field, window=window, strain_type="small"))
    assert hits == 2
    # the valid array handed to the plan is not its cache key: changing it afterwards changes the next fit
    valid = np.ones(n, bool)
    field = SimpleNamespace(points=points, u=u, v=v, valid=valid)
    plan.strain(field)
    valid[: n // 3] = False
    _assert_same_strain(plan.strain(field), _reference_strain(field, window))


def test_strain_is_the_reference_algorithm_bit_for_bit(rng):
    f = make_field(lambda x, y: (0.012 * x - 0.003 * y ** 1.2, -0.007 * x + 0.002 * y), step=3.0, nx=40, ny=33,
                   valid=rng.random(40 * 33) > 0.1)
    for window in (3, 5, 9):
        _assert_same_strain(strain(f, window=window, strain_type="small"), _reference_strain(f, window))


def test_strain_plan_results_are_the_callers():
    f = make_field(lambda x, y: (0.01 * x, -0.02 * y), nx=12, ny=10)
    plan = StrainPlan(f.points, window=5, strain_type="small")
    a = plan.strain(f)
    a.grid_index[:] = -1
    a.valid[:] = False
    a.n_fit[:] = 0
    f.points[0, 0] = -99.0  # the plan keeps its own copy of the points
    b = plan.strain(make_field(lambda x, y: (0.01 * x, -0.02 * y), nx=12, ny=10))
    assert b.grid_index.min() == 0 and b.valid.all() and b.n_fit.min() == 9 and np.allclose(b.exx, 0.01)
    assert not plan.points.flags.writeable and plan.grid_shape == (10, 12) and plan.step == (3.0, 3.0)
    assert "120 points" in repr(plan)


def test_strain_plan_refuses_bad_input():
    f = make_field(lambda x, y: (0 * x, 0 * y), nx=8, ny=6)
    with pytest.raises(ValueError, match="odd integer >= 3"):
        StrainPlan(f.points, window=4)
    with pytest.raises(ValueError, match="min_points must be in"):
        StrainPlan(f.points, window=3, min_points=10)
    with pytest.raises(ValueError, match="use a window of at most"):
        StrainPlan(f.points, window=15)
    with pytest.raises(ValueError, match="not on a regular grid"):
        StrainPlan(f.points + np.random.default_rng(0).normal(0, 0.3, f.points.shape))
    with pytest.raises(ValueError, match="duplicates"):
        StrainPlan(np.vstack([f.points, f.points[:1]]))
    with pytest.raises(ValueError, match="points"):
        StrainPlan(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="finite"):
        StrainPlan(np.full((4, 2), np.nan))
    plan = StrainPlan(f.points, window=3)
    other = make_field(lambda x, y: (0 * x, 0 * y), nx=8, ny=6, x0=11.0)
    with pytest.raises(ValueError, match="not those of this StrainPlan"):
        plan.strain(other)
    with pytest.raises(ValueError, match="not those of this StrainPlan"):
        plan.strain(SimpleNamespace(points=f.points[:-1], u=f.u[:-1], v=f.v[:-1]))
    with pytest.raises(ValueError, match="points, u, v"):
        plan.strain(object())
    assert plan.matches(f.points) and not plan.matches(other.points) and not plan.matches(f.points[::-1])


@pytest.mark.parametrize("window", [3, 5, 7, 9])
def test_the_window_sums_are_scipy_ndimage_correlate_bit_for_bit(rng, window):
    """dic._strain._correlate (numpy, so that `specula strain` need not import scipy.ndimage: 0.4 s of CPU)
    gives the bits of ndimage.correlate(mode="constant") for every fit kernel, on values of both signs."""
    from dic._strain import _correlate, _kernels

    a = rng.normal(0.0, 3.0, (23, 31)) * (rng.random((23, 31)) > 0.2)
    for k in _kernels(window):
        want = ndimage.correlate(a, k, mode="constant", cval=0.0)
        assert _bits(_correlate(a, k)) == _bits(want)
