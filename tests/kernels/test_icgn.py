"""IC-GN kernels: Jacobians and Hessians against finite differences, one Gauss-Newton step against
a NumPy implementation, warp composition against exact numerical composition, statuses, bad input.

Images here are analytic band-limited textures (sums of sinusoids, |k| <= 0.9 rad/px) sampled
exactly at any position, so no reference relies on the code under test.
"""
import numpy as np
import pytest
import warp as wp
from scipy import ndimage

from kernels.conventions import Status
from kernels.icgn import (
    compose_1st,
    compose_2nd,
    icgn,
    n_params,
    prepare_current,
    prepare_reference,
    prepare_subsets,
    refdata_columns,
    refdata_width,
    vec6,
    vec12,
)


class Texture:
    """f(x, y) = 128 + sum_k a_k sin(kx_k x + ky_k y + phi_k), evaluable anywhere (float64)."""

    def __init__(self, seed=0, n=40, kmax=0.9):
        rng = np.random.default_rng(seed)
        k = rng.uniform(0.1, kmax, n)
        ang = rng.uniform(0, 2 * np.pi, n)
        self.kx, self.ky = k * np.cos(ang), k * np.sin(ang)
        self.phi = rng.uniform(0, 2 * np.pi, n)
        self.a = rng.uniform(5, 15, n)

    def __call__(self, x, y):
        x = np.asarray(x, float)[..., None]
        y = np.asarray(y, float)[..., None]
        return 128 + np.sum(self.a * np.sin(self.kx * x + self.ky * y + self.phi), axis=-1)

    def image(self, shape, mapping=None):
        """Image whose pixel (x, y) shows the texture at mapping(x, y) (default identity)."""
        yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
        if mapping is not None:
            xx, yy = mapping(xx, yy)
        return self(xx, yy)


def shape_displacement(q, dx, dy, s, order):
    """(U, V) of the scaled parameters q at offsets (dx, dy) (xi = dx/s, eta = dy/s), see icgn docs."""
    xi, eta = dx / s, dy / s
    m = 3 if order == 1 else 6
    mono = [np.ones_like(xi), xi, eta, 0.5 * xi * xi, xi * eta, 0.5 * eta * eta][:m]
    u = sum(q[k] * mono[k] for k in range(m))
    v = sum(q[m + k] * mono[k] for k in range(m))
    return u, v


def unpack_refdata(row, order):
    k = n_params(order)
    hinv = np.zeros((k, k))
    iu = np.triu_indices(k)
    npk = len(iu[0])
    hinv[iu] = row[:npk]
    hinv = hinv + np.triu(hinv, 1).T
    a_ = row[npk:npk + k]
    c_ = row[npk + k:npk + 2 * k]
    return hinv, a_, c_, row[npk + 2 * k], row[npk + 2 * k + 1]


def fd_terms(img, point, subset, order, h=1e-3):
    """Finite-difference steepest-descent images J (n, K) of the scipy B-spline interpolant, and f."""
    r = subset // 2
    s = float(r)
    cx0, cy0 = int(round(point[0])), int(round(point[1]))
    j, i = np.mgrid[-r:r + 1, -r:r + 1]
    i, j = i.ravel().astype(float), j.ravel().astype(float)
    dx, dy = i + (cx0 - point[0]), j + (cy0 - point[1])
    k = n_params(order)

    def sample(q):
        u, v = shape_displacement(q, dx, dy, s, order)
        return ndimage.map_coordinates(img, [cy0 + j + v, cx0 + i + u], order=3, mode="mirror")

    jac = np.zeros((i.size, k))
    for c in range(k):
        e = np.zeros(k)
        e[c] = h
        jac[:, c] = (sample(e) - sample(-e)) / (2 * h)
    return jac, sample(np.zeros(k)), (cx0, cy0, i, j)


@pytest.mark.parametrize("order", [1, 2])
def test_refdata_columns_name_the_packed_layout(order):
    # the named columns the kernels read (kernels.icgn.RefdataColumns) against the layout unpacked here
    # independently (unpack_refdata: the upper triangle, then H^-1 a, H^-1 c, fm, df)
    k = n_params(order)
    npk = len(np.triu_indices(k)[0])
    cols = refdata_columns(order)
    assert (cols.hinv, cols.hinv_a, cols.hinv_c, cols.fmean, cols.fnorm) == (0, npk, npk + k, npk + 2 * k,
                                                                             npk + 2 * k + 1)
    assert cols.width == refdata_width(order) == npk + 2 * k + 2
    # fm and df of an integer POI's subset, read through the names, against NumPy on the image itself
    img = Texture(1).image((60, 60))
    subs = prepare_subsets(prepare_reference(img, device="cpu"), np.array([[30.0, 29.0]]), subset=11, order=order)
    patch = img[29 - 5:29 + 6, 30 - 5:30 + 6].astype(np.float64)
    row = subs.refdata.numpy()[0]
    assert abs(row[cols.fmean] - patch.mean()) < 1e-4 * patch.mean()
    assert abs(row[cols.fnorm] - np.linalg.norm(patch - patch.mean())) < 1e-4 * row[cols.fnorm]


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("point", [(40.0, 37.0), (51.3, 44.6)])
def test_hessian_and_jacobians_match_finite_differences(device, order, point):
    img = Texture(1).image((90, 100))
    subset = 21
    ref = prepare_reference(img, device=device)
    subs = prepare_subsets(ref, np.array([point]), subset=subset, order=order)
    assert subs.status.numpy()[0] == Status.CONVERGED
    hinv, a_k, c_k, fmean, fnorm = unpack_refdata(subs.refdata.numpy()[0].astype(np.float64), order)
    jac, f, _ = fd_terms(img, point, subset, order)
    jc = jac - jac.mean(axis=0)
    h_fd = jc.T @ jc  # centred Gauss-Newton Hessian (docs: sum (J - Jm)^T (J - Jm))
    a_fd = jac.T @ (f - f.mean())
    c_fd = jac.sum(axis=0)
    h_k = np.linalg.inv(hinv)
    # FD truncation ~h^2 f''' / 6 ~ 1e-7 relative; H^-1 is stored in float32 and the scaled
    # Hessians here have condition numbers <= ~200, so inverting it back costs ~200 * 6e-8 ~ 1e-5
    # (measured ~2e-7)
    assert np.linalg.norm(h_k - h_fd) / np.linalg.norm(h_fd) < 1e-5
    sol = np.linalg.solve(h_fd, np.c_[a_fd, c_fd])
    assert np.linalg.norm(a_k - sol[:, 0]) <= 1e-3 * np.linalg.norm(sol[:, 0]) + 1e-6
    assert np.linalg.norm(c_k - sol[:, 1]) <= 1e-3 * np.linalg.norm(sol[:, 1]) + 1e-6
    assert abs(fmean - f.mean()) < 1e-3
    assert abs(fnorm - np.linalg.norm(f - f.mean())) < 1e-4 * fnorm


@wp.kernel
def _compose1_probe(p: wp.array2d(dtype=float), dp: wp.array2d(dtype=float), out: wp.array2d(dtype=float)):
    i = wp.tid()
    a = vec6()
    b = vec6()
    for k in range(6):
        a[k] = p[i, k]
        b[k] = dp[i, k]
    c = compose_1st(a, b)
    for k in range(6):
        out[i, k] = c[k]


@wp.kernel
def _compose2_probe(p: wp.array2d(dtype=float), dp: wp.array2d(dtype=float), s: float, out: wp.array2d(dtype=float)):
    i = wp.tid()
    a = vec12()
    b = vec12()
    for k in range(12):
        a[k] = p[i, k]
        b[k] = dp[i, k]
    c = compose_2nd(a, b, s)
    for k in range(12):
        out[i, k] = c[k]


def compose(p, dp, order, s, device):
    pa = wp.array(np.atleast_2d(p).astype(np.float32), dtype=wp.float32, device=device)
    da = wp.array(np.atleast_2d(dp).astype(np.float32), dtype=wp.float32, device=device)
    out = wp.zeros(pa.shape, dtype=wp.float32, device=device)
    if order == 1:
        wp.launch(_compose1_probe, dim=pa.shape[0], inputs=[pa, da, out], device=device)
    else:
        wp.launch(_compose2_probe, dim=pa.shape[0], inputs=[pa, da, float(s), out], device=device)
    return out.numpy()[0].astype(np.float64)


def physical_displacement(p, x, y, order):
    """(U, V) of physical parameters (PARAMS order) at offsets (x, y)."""
    if order == 1:
        return p[0] + p[1] * x + p[2] * y, p[3] + p[4] * x + p[5] * y
    u = p[0] + p[1] * x + p[2] * y + 0.5 * p[3] * x * x + p[4] * x * y + 0.5 * p[5] * y * y
    v = p[6] + p[7] * x + p[8] * y + 0.5 * p[9] * x * x + p[10] * x * y + 0.5 * p[11] * y * y
    return u, v


def exact_composition(p, dp, x, y, order):
    """Points W(p)(W(dp)^-1(x, y)), the inverse by Newton iterations (float64)."""
    zx, zy = x.copy(), y.copy()
    for _ in range(50):
        u, v = physical_displacement(dp, zx, zy, order)
        rx, ry = zx + u - x, zy + v - y
        hh = 1e-6
        ux1, vx1 = physical_displacement(dp, zx + hh, zy, order)
        uy1, vy1 = physical_displacement(dp, zx, zy + hh, order)
        a11, a12 = 1 + (ux1 - u) / hh, (uy1 - u) / hh
        a21, a22 = (vx1 - v) / hh, 1 + (vy1 - v) / hh
        det = a11 * a22 - a12 * a21
        zx, zy = zx - (a22 * rx - a12 * ry) / det, zy - (-a21 * rx + a11 * ry) / det
    u, v = physical_displacement(p, zx, zy, order)
    return zx + u, zy + v


def test_composition_1st_order_is_exact(device):
    r = 10
    j, i = np.mgrid[-r:r + 1, -r:r + 1].astype(float)
    p = np.array([1.7, 0.02, -0.015, -0.6, 0.01, 0.03])
    dp = np.array([0.05, 0.004, -0.002, -0.03, 0.001, 0.006])
    c = compose(p, dp, 1, r, device)
    xe, ye = exact_composition(p, dp, i, j, 1)
    u, v = physical_displacement(c, i, j, 1)
    # affine warps form a group: only float32 rounding remains (~1e-6 px)
    assert np.max(np.hypot(i + u - xe, j + v - ye)) < 2e-5


def test_composition_2nd_order(device):
    r = 10
    j, i = np.mgrid[-r:r + 1, -r:r + 1].astype(float)
    p = np.array([1.7, 0.02, -0.015, 3e-4, -2e-4, 1e-4, -0.6, 0.01, 0.03, -1e-4, 2e-4, 3e-4])
    dp0 = np.array([0.05, 0.004, -0.002, 4e-5, -3e-5, 2e-5, -0.03, 0.001, 0.006, 2e-5, 1e-5, -4e-5])
    errors = []
    for scale in (1.0, 0.1):
        dp = dp0 * scale
        c = compose(p, dp, 2, r, device)
        xe, ye = exact_composition(p, dp, i, j, 2)
        u, v = physical_displacement(c, i, j, 2)
        errors.append(np.max(np.hypot(i + u - xe, j + v - ye)))
    # Gao's 6x6 matrices drop cubic/quartic monomials: the error is a product of the quadratic
    # terms of p (r^2 |uxx| ~ 0.03 px) with dp (~0.05 px), a few 1e-5 px here (measured 3.4e-5),
    # and it shrinks at least in proportion to dp (p o 0 = p, so IC-GN's fixed point is exact)
    assert errors[0] < 1e-4
    assert errors[1] < 0.15 * errors[0] + 2e-5
    # with a purely affine p the truncated terms are products of dp with itself: O(|dp|^2) ~ 3e-6
    p_aff = p.copy()
    p_aff[[3, 4, 5, 9, 10, 11]] = 0.0
    c = compose(p_aff, dp0, 2, r, device)
    xe, ye = exact_composition(p_aff, dp0, i, j, 2)
    u, v = physical_displacement(c, i, j, 2)
    assert np.max(np.hypot(i + u - xe, j + v - ye)) < 2e-5
    # identity: p o 0 = p
    np.testing.assert_allclose(compose(p, np.zeros(12), 2, r, device), p, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("order", [1, 2])
def test_one_gauss_newton_step_matches_numpy(device, order):
    tex = Texture(2)
    shape = (90, 100)
    ref_img = tex.image(shape)
    # current: an affine deformation of the texture (its exact parameters do not matter here:
    # the NumPy step below uses the same current image)
    cur_img = tex.image(shape, lambda x, y: (x - 0.35 - 0.01 * y, y + 0.2 - 0.008 * x))
    point = (48.0, 43.0)
    subset = 21
    ref = prepare_reference(ref_img, device=device)
    subs = prepare_subsets(ref, np.array([point]), subset=subset, order=order)
    res = icgn(subs, prepare_current(cur_img, device=device), max_iter=1, tol=1e-9).numpy()
    assert res["status"][0] == Status.MAX_ITERATIONS and res["iterations"][0] == 1
    # NumPy IC-GN step from zero: e = (f - fm) - df/dg (g - gm), dq = -H^-1 sum J^T e
    jac, f, (cx0, cy0, i, j) = fd_terms(ref_img, point, subset, order)
    g = cur_img[(cy0 + j).astype(int), (cx0 + i).astype(int)]
    fz, gz = f - f.mean(), g - g.mean()
    e = fz - np.linalg.norm(fz) / np.linalg.norm(gz) * gz
    jc = jac - jac.mean(axis=0)
    dq = -np.linalg.solve(jc.T @ jc, jac.T @ e)
    s = subset // 2
    scale = np.array([1, s, s, 1, s, s] if order == 1 else [1, s, s, s * s, s * s, s * s] * 2, float)
    dp = dq / scale
    expected = compose(np.zeros(n_params(order)), dp, order, s, device)
    # the kernel's B-spline gradients vs FD of scipy's spline (~1e-7 relative) and float32 sums
    # over 441 pixels (~1e-6 relative): measured ~1e-6 scaled px for |dq| ~ 0.8 px
    err = np.abs(res["params"][0] - expected) * scale
    assert np.max(err) < 1e-5 * max(1.0, np.max(np.abs(dq)))
    zncc = fz @ gz / (np.linalg.norm(fz) * np.linalg.norm(gz))
    assert abs(res["zncc"][0] - zncc) < 1e-5


@pytest.mark.parametrize("order", [1, 2])
def test_converges_on_integer_and_subpixel_points(device, order):
    tex = Texture(3)
    shape = (80, 90)
    u0, v0 = 0.63, -0.41
    ref_img = tex.image(shape)
    cur_img = tex.image(shape, lambda x, y: (x - u0, y - v0))
    pts = np.array([[40.0, 40.0], [30.0, 45.0], [52.25, 33.7], [47.5, 41.5]])
    ref = prepare_reference(ref_img, device=device)
    subs = prepare_subsets(ref, pts, subset=21, order=order)
    res = icgn(subs, cur_img).numpy()
    k = n_params(order)
    assert np.all(res["status"] == Status.CONVERGED)
    assert np.all(res["iterations"] <= 6)
    # band-limited texture, B-spline interpolation error < 1e-3 grey: displacement error ~1e-4 px
    assert np.max(np.abs(res["params"][:, 0] - u0)) < 2e-3
    assert np.max(np.abs(res["params"][:, k // 2] - v0)) < 2e-3
    assert np.all(res["zncc"] > 0.9999)


def test_statuses(device):
    tex = Texture(4)
    shape = (80, 100)
    img = tex.image(shape)
    img[5:40, 60:95] = 100.0  # flat patch
    stripes = 128 + 50 * np.sin(0.7 * np.arange(100))[None, :] * np.ones((80, 1))
    img[45:78, 60:95] = stripes[45:78, 60:95]  # texture along x only: singular Hessian
    pts = np.array([[30.0, 30.0], [5.0, 40.0], [77.0, 20.0], [77.0, 61.0], [40.0, 40.0]])
    ref = prepare_reference(img, device=device)
    subs = prepare_subsets(ref, pts, subset=21, order=1)
    st = subs.status.numpy()
    assert st[1] == Status.OUT_OF_BOUNDS  # reference subset crosses the left border
    assert st[2] == Status.FLAT_SUBSET
    assert st[3] == Status.SINGULAR_HESSIAN
    guess = np.zeros((5, 6))
    guess[4, 0] = 50.0  # warped subset would leave the image
    cur = tex.image(shape, lambda x, y: (x - 0.4, y))
    res = icgn(subs, cur, guess=guess).numpy()
    assert res["status"][0] == Status.CONVERGED
    assert res["status"][4] == Status.OUT_OF_BOUNDS
    assert np.all(res["status"][1:4] == st[1:4])
    assert np.isnan(res["zncc"][1])
    res = icgn(subs, cur, max_iter=1).numpy()
    assert res["status"][0] == Status.MAX_ITERATIONS
    res = icgn(subs, np.full(shape, 90.0)).numpy()  # nothing to correlate with
    assert res["status"][0] == Status.DIVERGED


def test_bad_input(device):
    img = Texture(5).image((40, 40))
    ref = prepare_reference(img, device=device)
    with pytest.raises(ValueError, match="odd"):
        prepare_subsets(ref, [[20, 20]], subset=20)
    with pytest.raises(ValueError, match="order"):
        prepare_subsets(ref, [[20, 20]], order=3)
    with pytest.raises(ValueError, match="empty"):
        prepare_subsets(ref, np.zeros((0, 2)))
    subs = prepare_subsets(ref, [[20, 20]], subset=11)
    with pytest.raises(ValueError, match="shape"):
        icgn(subs, np.zeros((40, 41)))
    with pytest.raises(ValueError, match=r"\(1, 6\)"):
        icgn(subs, img, guess=np.zeros((1, 12)))
    with pytest.raises(ValueError, match="NaN"):
        icgn(subs, img, guess=np.full((1, 6), np.nan))
    with pytest.raises(ValueError, match="max_iter"):
        icgn(subs, img, max_iter=0)
    with pytest.raises(ValueError, match="tol"):
        icgn(subs, img, tol=-1.0)


@pytest.mark.parametrize("order", [1, 2])
def test_prepare_subsets_of_active_points_only(order):
    """``active``: the active POIs' tables are bit for bit those of preparing every POI (so are their IC-GN
    results), the others NOT_COMPUTED with zero tables and never tracked; a wrong mask is refused."""
    from dic.synth import speckle_pair

    ref, cur = speckle_pair((96, 120), (0.4, -0.3), seed=5)
    ys, xs = np.mgrid[4:92:6, 4:116:6]  # a grid over the whole image: some subsets leave it
    pts = np.c_[xs.ravel() + 0.25, ys.ravel()].astype(np.float64)
    active = (pts[:, 0] > 30) & (pts[:, 0] < 90) & (pts[:, 1] > 20)
    reference = prepare_reference(ref, device="cpu")
    every = prepare_subsets(reference, pts, subset=15, order=order)
    some = prepare_subsets(reference, pts, subset=15, order=order, active=active)
    for name in ("centres", "deltas", "refdata", "status"):
        a, b = getattr(every, name).numpy(), getattr(some, name).numpy()
        assert np.array_equal(a[active], b[active]), name
        assert not np.any(b[~active] if name != "status" else b[~active] != int(Status.NOT_COMPUTED)), name
    assert np.count_nonzero(every.status.numpy()[active] == int(Status.CONVERGED)) > 50
    current = prepare_current(cur, device="cpu")
    ra, rb = icgn(every, current).numpy(), icgn(some, current).numpy()
    for key in ("params", "zncc", "iterations", "status"):
        assert np.array_equal(ra[key][active], rb[key][active], equal_nan=True), key
    assert np.all(rb["status"][~active] == int(Status.NOT_COMPUTED)) and np.all(rb["iterations"][~active] == 0)
    with pytest.raises(ValueError, match="active must be"):
        prepare_subsets(reference, pts, subset=15, order=order, active=active[:-1])
    with pytest.raises(ValueError, match="active must be"):
        prepare_subsets(reference, pts, subset=15, order=order, active=active.astype(int))


def test_reference_gradients_of_a_window_are_the_same_bits():
    """``prepare_reference(window=)``: the values and gradients inside the window are those of the whole image bit for
    bit, zero outside; subsets_window covers every pixel of the given subsets (so their IC-GN is unchanged)."""
    from dic.synth import speckle_pair
    from kernels.icgn import subsets_window

    ref, cur = speckle_pair((90, 130), (0.3, 0.2), seed=9)
    whole = prepare_reference(ref, device="cpu").fgrad.numpy().reshape(90, 130, 3)
    part = prepare_reference(ref, device="cpu", window=(20, 15, 97, 70)).fgrad.numpy().reshape(90, 130, 3)
    assert np.array_equal(part[15:71, 20:98], whole[15:71, 20:98])
    inside = np.zeros((90, 130), dtype=bool)
    inside[15:71, 20:98] = True
    assert not np.any(part[~inside])
    clipped = prepare_reference(ref, device="cpu", window=(-5, -5, 200, 200)).fgrad.numpy()
    assert np.array_equal(clipped, whole.reshape(-1, 3))
    pts = np.array([[30.5, 22.4], [60.0, 50.0], [95.49, 60.51], [np.nan, np.nan]])
    active = np.array([True, True, True, False])
    x0, y0, x1, y1 = subsets_window(pts, 11, active)
    centres = np.floor(pts[:3] + 0.5)
    assert x0 <= centres[:, 0].min() - 5 and y0 <= centres[:, 1].min() - 5
    assert x1 >= centres[:, 0].max() + 5 and y1 >= centres[:, 1].max() + 5
    assert subsets_window(pts, 11, np.zeros(4, dtype=bool)) is None
    with pytest.raises(ValueError, match="active must be"):
        subsets_window(pts, 11, active[:3])
    with pytest.raises(ValueError, match="subset must be an odd integer"):
        subsets_window(pts, 10, active)
    for bad in ((1, 2, 3), (0, 0, 10.5, 10), "abcd"):
        with pytest.raises(ValueError, match="window must be 4 integers"):
            prepare_reference(ref, device="cpu", window=bad)
    sub_w = prepare_subsets(prepare_reference(ref, device="cpu", window=(x0, y0, x1, y1)), pts[:3], subset=11)
    sub = prepare_subsets(prepare_reference(ref, device="cpu"), pts[:3], subset=11)
    current = prepare_current(cur, device="cpu")
    a, b = icgn(sub, current).numpy(), icgn(sub_w, current).numpy()
    for key in ("params", "zncc", "iterations", "status"):
        assert np.array_equal(a[key], b[key], equal_nan=True), key
