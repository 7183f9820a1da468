"""Pointwise least-squares strain (dic/strain.py) against analytic fields with exact derivatives."""
from types import SimpleNamespace

import numpy as np
import pytest

from dic.strain import grid_layout, strain


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
    s = strain(f, window=5)
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

    s = strain(make_field(rot))
    assert np.max(np.abs(np.stack([s.Exx, s.Eyy, s.Exy]))) < 1e-12  # exact for a rigid motion
    assert np.allclose(s.exx, np.cos(th) - 1, atol=1e-12)  # the small strain is not objective


def test_to_grid_and_layout():
    f = make_field(lambda x, y: (0.01 * x, 0.0 * y), step=4.0, nx=6, ny=4)
    keep = np.arange(24) != 7
    f2 = make_field(lambda x, y: (0.01 * x, 0.0 * y), step=4.0, nx=6, ny=4)
    f2.points, f2.u, f2.v, f2.valid = f.points[keep], f.u[keep], f.v[keep], f.valid[keep]
    s = strain(f2, window=3)
    g = s.to_grid("exx")
    assert g.shape == (4, 6) and np.isnan(g[1, 1]) and np.allclose(g[~np.isnan(g)], 0.01)
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
