"""The GPU-fitted kernels against the implementations they replace (issue 16, "Kernels that fit the GPU").

The replaced code is copied here verbatim from commit f1a2312 (kernels/icgn.py, kernels/interp.py)
so that each change is checked against what it replaced, on the same inputs, in the same Warp
module options (FMA contraction as in kernels.icgn): the pivot-free 6x6 solve of the 2nd-order
warp composition, the order-specialised ``_prepare_subsets`` and the segmented B-spline prefilter.
"""
import numpy as np
import pytest
import warp as wp

from kernels import icgn as K
from kernels.conventions import Status
from kernels.icgn import (
    ST_CONVERGED,
    ST_DIVERGED,
    ST_FLAT,
    ST_MAX_ITERATIONS,
    ST_OUT_OF_BOUNDS,
    ST_SINGULAR,
    mat66,
    quad_warp_matrix,
    solve_transposed6,
    vec6,
    vec12,
)
from kernels.interp import filter_line

wp.set_module_options({"enable_backward": False, "cpu_compiler_flags": "-march=native -ffp-contract=fast"})

#: |dn_i| below this makes Gao's matrix strictly row-diagonally dominant (root of 11 d^2 + 6 d - 1)
DOMINANCE_BOUND = (-6.0 + np.sqrt(80.0)) / 22.0


# ------------------------------------------------------------------------------------------------
# copied from f1a2312:kernels/icgn.py (the partial-pivoting solve and the kernel that used it)
# ------------------------------------------------------------------------------------------------


@wp.func
def _solve_pivot(m: mat66, rhs: vec6):
    a = wp.transpose(m)
    x = rhs
    for c in range(6):
        piv = c
        for rr in range(c + 1, 6):
            if wp.abs(a[rr, c]) > wp.abs(a[piv, c]):
                piv = rr
        if piv != c:
            tmp = a[c]
            a[c] = a[piv]
            a[piv] = tmp
            t = x[c]
            x[c] = x[piv]
            x[piv] = t
        for rr in range(c + 1, 6):
            f = a[rr, c] / a[c, c]
            a[rr] = a[rr] - f * a[c]
            x[rr] = x[rr] - f * x[c]
    for cc in range(6):
        c = 5 - cc
        t = x[c]
        for k in range(c + 1, 6):
            t -= a[c, k] * x[k]
        x[c] = t / a[c, c]
    return x


@wp.func
def _compose_2nd_pivot(p: vec12, dp: vec12, s: float):
    pn = vec12(p[0] / s, p[1], p[2], p[3] * s, p[4] * s, p[5] * s, p[6] / s, p[7], p[8], p[9] * s, p[10] * s, p[11] * s)
    dn = vec12(dp[0] / s, dp[1], dp[2], dp[3] * s, dp[4] * s, dp[5] * s,
               dp[6] / s, dp[7], dp[8], dp[9] * s, dp[10] * s, dp[11] * s)
    mp = quad_warp_matrix(pn)
    md = quad_warp_matrix(dn)
    rx = _solve_pivot(md, mp[3])
    ry = _solve_pivot(md, mp[4])
    return vec12(
        rx[5] * s, rx[3] - 1.0, rx[4], 2.0 * rx[0] / s, rx[1] / s, 2.0 * rx[2] / s,
        ry[5] * s, ry[3], ry[4] - 1.0, 2.0 * ry[0] / s, ry[1] / s, 2.0 * ry[2] / s,
    )


@wp.kernel
def _icgn_2nd_pivot(
    offset: int, fgrad: wp.array(dtype=wp.vec3), width: int, height: int, coef: wp.array(dtype=wp.vec4), pitch: int,
    centres: wp.array(dtype=wp.vec2i), deltas: wp.array(dtype=wp.vec2), refdata: wp.array2d(dtype=float),
    ref_status: wp.array(dtype=wp.int32), guess: wp.array2d(dtype=float), r: int, max_iter: int, tol: float,
    flat_var: float,
    params: wp.array2d(dtype=float), zncc: wp.array(dtype=float), iterations: wp.array(dtype=wp.int32),
    status: wp.array(dtype=wp.int32),
):
    n = wp.tid() + offset
    p = vec12()
    for i in range(12):
        p[i] = guess[n, i]
    st = ref_status[n]
    cc = float(wp.nan)
    it = int(0)
    if st == ST_CONVERGED:
        fmean = refdata[n, 102]
        fnorm = refdata[n, 103]
        goff = fmean
        ctr = centres[n]
        dl = deltas[n]
        s = float(r)
        s2 = s * s
        st = ST_MAX_ITERATIONS
        while it < max_iter:
            if K.warped_inside(ctr[0], ctr[1], r, dl, width, height, p[0], p[1], p[2], p[3], p[4], p[5],
                               p[6], p[7], p[8], p[9], p[10], p[11]) == 0:
                st = ST_OUT_OF_BOUNDS
                break
            b, sums = K.subset_pass_2nd(fgrad, width, coef, pitch, ctr[0], ctr[1], r, dl, 1.0 / s, p, fmean, goff)
            it += 1
            gmean, ratio, cc = K.gn_step_scale(sums, (2 * r + 1) * (2 * r + 1), fnorm, flat_var)
            goff = goff + gmean
            dq = K.gn_update12(refdata, n, b, ratio, gmean)
            norm = wp.length(dq)
            if ratio == 0.0 or not (norm <= float(2 * r + 1)):
                st = ST_DIVERGED
                break
            dp = vec12(dq[0], dq[1] / s, dq[2] / s, dq[3] / s2, dq[4] / s2, dq[5] / s2,
                       dq[6], dq[7] / s, dq[8] / s, dq[9] / s2, dq[10] / s2, dq[11] / s2)
            p = _compose_2nd_pivot(p, dp, s)
            if norm < tol:
                st = ST_CONVERGED
                break
    for i in range(12):
        params[n, i] = p[i]
    zncc[n] = cc
    iterations[n] = it
    status[n] = st


# ------------------------------------------------------------------------------------------------
# pivot-free solve
# ------------------------------------------------------------------------------------------------


@wp.kernel
def _solve_both(dn: wp.array(dtype=vec12), rhs: wp.array(dtype=vec6), x_new: wp.array(dtype=vec6),
                x_old: wp.array(dtype=vec6), dominant: wp.array(dtype=wp.int32)):
    i = wp.tid()
    md = quad_warp_matrix(dn[i])
    x_new[i] = solve_transposed6(md, rhs[i])
    x_old[i] = _solve_pivot(md, rhs[i])
    dom = int(1)
    for r in range(6):
        off = float(0.0)
        for c in range(6):
            if c != r:
                off += wp.abs(md[r, c])
        if not (wp.abs(md[r, r]) > off):
            dom = 0
    dominant[i] = dom


def _solve_cases(dn: np.ndarray, seed: int = 1):
    rng = np.random.default_rng(seed)
    n = dn.shape[0]
    # right-hand sides as compose_2nd gives them: rows 3, 4 of a near-identity Gao matrix
    rhs = rng.uniform(-0.2, 0.2, (n, 6)).astype(np.float32)
    rhs[:, 3] += 1.0
    rhs[:, 5] = rng.uniform(-3, 3, n)
    args = [wp.array(dn.astype(np.float32), dtype=vec12, device="cpu"), wp.array(rhs, dtype=vec6, device="cpu")]
    outs = [wp.empty(n, dtype=vec6, device="cpu"), wp.empty(n, dtype=vec6, device="cpu"),
            wp.empty(n, dtype=wp.int32, device="cpu")]
    wp.launch(_solve_both, dim=n, inputs=args + outs, device="cpu")
    return outs[0].numpy(), outs[1].numpy(), outs[2].numpy().astype(bool)


def _rel_diff(a, b):
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1.0)))


def test_pivot_free_solve_is_bitwise_the_pivoting_one_where_rows_dominate():
    rng = np.random.default_rng(0)
    n = 20000
    # near-identity updates, every scaled component up to the dominance bound, plus the corners
    # of that box (all |dn_i| at the bound with random signs: the worst case of the derivation)
    dn = rng.uniform(-1, 1, (n, 12)) * DOMINANCE_BOUND * 0.999
    dn[: n // 4] = np.sign(dn[: n // 4]) * DOMINANCE_BOUND * 0.999
    x_new, x_old, dominant = _solve_cases(dn)
    assert dominant.all(), "the stated bound |dn_i| < 0.1338 must make Gao's matrix row-dominant"
    assert np.all(np.isfinite(x_new))
    np.testing.assert_array_equal(x_new, x_old)


def test_pivot_free_solve_on_moderately_large_updates():
    rng = np.random.default_rng(2)
    dn = rng.uniform(-0.5, 0.5, (20000, 12))
    x_new, x_old, dominant = _solve_cases(dn, seed=3)
    ok = np.all(np.isfinite(x_new), axis=1) & np.all(np.isfinite(x_old), axis=1)
    assert ok.mean() > 0.999
    np.testing.assert_array_equal(x_new[dominant], x_old[dominant])
    # where pivoting would swap rows, only rounding differs (float32, O(1) entries; measured 5.2e-4)
    assert _rel_diff(x_new[ok], x_old[ok]) < 1e-3


def test_pivot_free_solve_degenerate_update_is_nan():
    dn = np.zeros((2, 12))
    dn[0, 1] = -1.0  # ux = -1 folds the subset onto the y axis: zero pivot
    dn[1, 8] = -1.0 + 1e-8
    x_new, _, _ = _solve_cases(dn)
    assert np.all(np.isnan(x_new))


def _icgn2_old_and_new(ref, cur, points, guess):
    from kernels._launch import launch_1d

    rim = K.prepare_reference(ref, device="cpu")
    sub = K.prepare_subsets(rim, points, subset=21, order=2)
    curi = K.prepare_current(cur, device="cpu")
    new = K.icgn(sub, curi, guess=guess, max_iter=30, tol=1e-3).numpy()
    n = sub.n_points
    out = [wp.empty((n, 12), dtype=float, device="cpu"), wp.empty(n, dtype=float, device="cpu"),
           wp.empty(n, dtype=wp.int32, device="cpu"), wp.empty(n, dtype=wp.int32, device="cpu")]
    h, w = rim.shape
    g = wp.array(np.asarray(guess, np.float32), dtype=float, device="cpu")
    launch_1d(_icgn_2nd_pivot, n,
              [0, rim.fgrad, w, h, curi.rows4, curi.pitch, sub.centres, sub.deltas, sub.refdata, sub.status, g,
               10, 30, 1e-3, float(sub.flat_std) ** 2] + out, "cpu", offset_index=0, min_chunk=64)
    old = dict(zip(("params", "zncc", "iterations", "status"), (a.numpy() for a in out)))
    return old, new


def test_icgn_2nd_order_with_pivot_free_solve_matches_the_pivoting_kernel():
    from dic.synth import speckle_pair

    def disp(x, y):  # a smooth 2nd-order field: ~0.6 px shift, 1 % strain, some curvature
        return 0.6 + 0.01 * (x - 64) + 2e-4 * (y - 64) ** 2, -0.3 + 0.008 * (y - 64) + 1e-4 * (x - 64) * (y - 64)

    ref, cur = speckle_pair((128, 128), disp, seed=5, noise_sigma=1.0)
    yy, xx = np.mgrid[12:117:3, 12:117:3]
    pts = np.stack([xx.ravel() + 0.25, yy.ravel()], axis=1).astype(float)
    rng = np.random.default_rng(4)
    guess = np.zeros((pts.shape[0], 12))
    guess[:, 0] = rng.uniform(-1.5, 1.5, pts.shape[0])  # from up to ~2 px away: large first updates
    guess[:, 6] = rng.uniform(-1.5, 1.5, pts.shape[0])
    old, new = _icgn2_old_and_new(ref, cur, pts, guess)
    np.testing.assert_array_equal(new["status"], old["status"])
    np.testing.assert_array_equal(new["iterations"], old["iterations"])
    conv = new["status"] == int(Status.CONVERGED)
    assert conv.mean() > 0.95
    # the same elimination steps, compiled differently (FMA contraction of the unrolled solve):
    # float32 rounding of the parameters only (measured: 3.6e-7 px in u, v; 2.7e-9 in 2nd derivatives)
    d = np.abs(new["params"] - old["params"])
    print("max |d params| (u, ux, uy, uxx, uxy, uyy):", d[:, :6].max(axis=0), "zncc:",
          np.nanmax(np.abs(new["zncc"] - old["zncc"])))
    assert d[:, [0, 6]].max() < 2e-6  # px
    assert d[:, [1, 2, 7, 8]].max() < 1e-6
    assert d[:, [3, 4, 5, 9, 10, 11]].max() < 1e-7  # 1/px
    np.testing.assert_allclose(new["zncc"], old["zncc"], rtol=0, atol=1e-6)


# ------------------------------------------------------------------------------------------------
# copied from f1a2312:kernels/icgn.py: _prepare_subsets with k and deg known only at run time
# ------------------------------------------------------------------------------------------------


@wp.func
def _old_cholesky_inverse(h: K.mat1212d, k: int):
    lo = K.mat1212d()
    ok = int(1)
    hmax = wp.float64(0.0)
    for j in range(k):
        hmax = wp.max(hmax, h[j, j])
    for j in range(k):
        s = h[j, j]
        for m in range(j):
            s -= lo[j, m] * lo[j, m]
        if not (s > wp.float64(K.PIVOT_RTOL) * hmax):
            ok = 0
            s = wp.float64(1.0)
        d = wp.sqrt(s)
        lo[j, j] = d
        for i in range(j + 1, k):
            t = h[i, j]
            for m in range(j):
                t -= lo[i, m] * lo[j, m]
            lo[i, j] = t / d
    inv = K.mat1212d()
    for col in range(k):
        y = K.vec12d()
        for i in range(k):
            t = wp.float64(0.0)
            if i == col:
                t = wp.float64(1.0)
            for m in range(i):
                t -= lo[i, m] * y[m]
            y[i] = t / lo[i, i]
        for ii in range(k):
            i = k - 1 - ii
            t = y[i]
            for m in range(i + 1, k):
                t -= lo[m, i] * inv[m, col]
            inv[i, col] = t / lo[i, i]
    return inv, ok


@wp.func
def _old_row_to_moments(m: K.mat55d, row: K.vec5, eta: wp.float64, deg: int):
    eb = wp.float64(1.0)
    for beta in range(deg + 1):
        for alpha in range(deg + 1 - beta):
            m[alpha, beta] = m[alpha, beta] + wp.float64(row[alpha]) * eb
        eb = eb * eta
    return m


@wp.func
def _old_subset_hessian(fgrad: wp.array(dtype=wp.vec3), width: int, cx0: int, cy0: int, r: int, dl: wp.vec2,
                        k: int, fmean: wp.float64):
    dj = k // 6
    inv_s = 1.0 / float(r)
    fm = float(fmean)
    mxx = K.mat55d()
    mxy = K.mat55d()
    myy = K.mat55d()
    mx = K.mat55d()
    my = K.mat55d()
    mxf = K.mat55d()
    myf = K.mat55d()
    ss = wp.float64(0.0)
    for j in range(-r, r + 1):
        eta = wp.float64((float(j) + dl[1]) * inv_s)
        row = (cy0 + j) * width + cx0
        if dj == 1:
            rxx, rxy, ryy, rx, ry, rxf, ryf, rss = K._row_moments_deg2(fgrad, row, r, dl[0], inv_s, fm)
        else:
            rxx, rxy, ryy, rx, ry, rxf, ryf, rss = K._row_moments_deg4(fgrad, row, r, dl[0], inv_s, fm)
        ss += wp.float64(rss)
        mxx = _old_row_to_moments(mxx, rxx, eta, 2 * dj)
        mxy = _old_row_to_moments(mxy, rxy, eta, 2 * dj)
        myy = _old_row_to_moments(myy, ryy, eta, 2 * dj)
        mx = _old_row_to_moments(mx, rx, eta, dj)
        my = _old_row_to_moments(my, ry, eta, dj)
        mxf = _old_row_to_moments(mxf, rxf, eta, dj)
        myf = _old_row_to_moments(myf, ryf, eta, dj)
    h = K.mat1212d()
    a = K.vec12d()
    c = K.vec12d()
    m = k // 2
    npx = wp.float64((2 * r + 1) * (2 * r + 1))
    for i in range(k):
        ai, bi, wi = K.mono_exponents(i % m)
        if i < m:
            a[i] = wp.float64(wi) * mxf[ai, bi]
            c[i] = wp.float64(wi) * mx[ai, bi]
        else:
            a[i] = wp.float64(wi) * myf[ai, bi]
            c[i] = wp.float64(wi) * my[ai, bi]
    for i in range(k):
        ai, bi, wi = K.mono_exponents(i % m)
        for jj in range(i, k):
            aj, bj, wj = K.mono_exponents(jj % m)
            g = mxy[ai + aj, bi + bj]
            if i < m and jj < m:
                g = mxx[ai + aj, bi + bj]
            if i >= m and jj >= m:
                g = myy[ai + aj, bi + bj]
            h[i, jj] = wp.float64(wi * wj) * g - c[i] * c[jj] / npx
            h[jj, i] = h[i, jj]
    return h, a, c, ss


@wp.func
def _old_store_refdata(refdata: wp.array2d(dtype=float), n: int, hinv: K.mat1212d, a: K.vec12d, c: K.vec12d, k: int,
                       fmean: wp.float64, fnorm: wp.float64):
    col = int(0)
    for i in range(k):
        for j in range(i, k):
            refdata[n, col] = float(hinv[i, j])
            col += 1
    for i in range(k):
        ha = wp.float64(0.0)
        hc = wp.float64(0.0)
        for j in range(k):
            ha += hinv[i, j] * a[j]
            hc += hinv[i, j] * c[j]
        refdata[n, col + i] = float(ha)
        refdata[n, col + k + i] = float(hc)
    refdata[n, col + 2 * k] = float(fmean)
    refdata[n, col + 2 * k + 1] = float(fnorm)


@wp.kernel
def _old_prepare_subsets(
    offset: int, fgrad: wp.array(dtype=wp.vec3), width: int, height: int, points: wp.array(dtype=wp.vec2d),
    r: int, k: int, flat_var: float,
    centres: wp.array(dtype=wp.vec2i), deltas: wp.array(dtype=wp.vec2), refdata: wp.array2d(dtype=float),
    status: wp.array(dtype=wp.int32),
):
    n = wp.tid() + offset
    pt = points[n]
    cx0 = int(wp.round(pt[0]))
    cy0 = int(wp.round(pt[1]))
    dl = wp.vec2(float(wp.float64(cx0) - pt[0]), float(wp.float64(cy0) - pt[1]))
    centres[n] = wp.vec2i(cx0, cy0)
    deltas[n] = dl
    if cx0 - r < 0 or cy0 - r < 0 or cx0 + r > width - 1 or cy0 + r > height - 1:
        status[n] = ST_OUT_OF_BOUNDS
        return
    npx = (2 * r + 1) * (2 * r + 1)
    fsum = wp.float64(0.0)
    for j in range(-r, r + 1):
        for i in range(-r, r + 1):
            fsum += wp.float64(fgrad[(cy0 + j) * width + cx0 + i][0])
    fmean = fsum / wp.float64(npx)
    h, a, c, ss = _old_subset_hessian(fgrad, width, cx0, cy0, r, dl, k, fmean)
    if not (ss > wp.float64(npx) * wp.float64(flat_var)):
        status[n] = ST_FLAT
        return
    hinv, ok = _old_cholesky_inverse(h, k)
    if ok == 0:
        status[n] = ST_SINGULAR
        return
    _old_store_refdata(refdata, n, hinv, a, c, k, fmean, wp.sqrt(ss))
    status[n] = ST_CONVERGED


@pytest.mark.parametrize("order", [1, 2])
def test_order_specialised_prepare_subsets_is_bitwise_the_runtime_k_kernel(order):
    from dic.synth import speckle_pair

    ref, _ = speckle_pair((96, 96), None, seed=7, noise_sigma=0.5)
    ref[60:80, 5:30] = ref[60, 5]  # a flat patch: FLAT_SUBSET
    ref[5:30, 60:62] = 255.0  # a stripe: texture in one direction only (SINGULAR at order 2)
    ref[5:30, 62:90] = 30.0
    rng = np.random.default_rng(order)
    pts = np.concatenate([rng.uniform(-3, 99, (600, 2)), np.mgrid[10:90:6, 10:90:6].reshape(2, -1).T[:, ::-1]])
    pts[::7] = np.round(pts[::7])  # integer POIs too
    rim = K.prepare_reference(ref, device="cpu")
    new = K.prepare_subsets(rim, pts, subset=15, order=order, flat_std=0.5)
    n = pts.shape[0]
    kk = K.n_params(order)
    out = [wp.empty(n, dtype=wp.vec2i, device="cpu"), wp.empty(n, dtype=wp.vec2, device="cpu"),
           wp.zeros((n, K.refdata_width(order)), dtype=wp.float32, device="cpu"), wp.empty(n, dtype=wp.int32, device="cpu")]
    h, w = rim.shape
    wp.launch(_old_prepare_subsets, dim=n,
              inputs=[0, rim.fgrad, w, h, wp.array(pts, dtype=wp.vec2d, device="cpu"), 7, kk, 0.25] + out, device="cpu")
    status = new.status.numpy()
    np.testing.assert_array_equal(status, out[3].numpy())
    for st in (Status.CONVERGED, Status.OUT_OF_BOUNDS, Status.FLAT_SUBSET):
        assert np.any(status == int(st)), f"the case should cover {st.name}"
    np.testing.assert_array_equal(new.centres.numpy(), out[0].numpy())
    np.testing.assert_array_equal(new.deltas.numpy(), out[1].numpy())
    np.testing.assert_array_equal(new.refdata.numpy(), out[2].numpy())  # bitwise, all rows


# ------------------------------------------------------------------------------------------------
# copied from f1a2312:kernels/interp.py: the prefilter with one work item per whole line
# ------------------------------------------------------------------------------------------------

#: kernels.interp's module options (no FMA contraction flags, unlike kernels.icgn and this module)
INTERP_OPTIONS = {"enable_backward": False}


@wp.kernel(module="unique", module_options=INTERP_OPTIONS)
def _old_prefilter_rows(offset: int, image: wp.array2d(dtype=float), coef: wp.array2d(dtype=float), width: int):
    y = wp.tid() + offset
    r = y + 2
    for x in range(width):
        coef[r, x + 2] = image[y, x]
    filter_line(coef, r, 2, 0, 1, width)
    coef[r, 1] = coef[r, 3]
    coef[r, 0] = coef[r, 4]
    coef[r, width + 2] = coef[r, width]
    coef[r, width + 3] = coef[r, width - 1]


@wp.kernel(module="unique", module_options=INTERP_OPTIONS)
def _old_prefilter_cols(offset: int, coef: wp.array2d(dtype=float), height: int):
    x = wp.tid() + offset
    filter_line(coef, 2, x, 1, 0, height)
    coef[1, x] = coef[3, x]
    coef[0, x] = coef[4, x]
    coef[height + 2, x] = coef[height, x]
    coef[height + 3, x] = coef[height - 1, x]


def old_bspline_coefficients(image: np.ndarray) -> np.ndarray:
    from kernels._launch import launch_1d

    h, w = image.shape
    img = wp.array(image.astype(np.float32), dtype=float, device="cpu")
    out = wp.empty((h + 4, w + 4), dtype=float, device="cpu")
    launch_1d(_old_prefilter_rows, h, [0, img, out, w], "cpu", offset_index=0, min_chunk=64)
    launch_1d(_old_prefilter_cols, w + 4, [0, out, h], "cpu", offset_index=0, min_chunk=64)
    return out.numpy()


@pytest.mark.parametrize("shape", [(7, 5), (200, 255), (256, 300), (515, 389)])
def test_segmented_prefilter_matches_the_whole_line_filter(shape):
    from kernels.interp import PREFILTER_SEGMENT, bspline_coefficients, prefilter_segments

    rng = np.random.default_rng(shape[0])
    img = (rng.random(shape) * 255).astype(np.float32)  # white noise: the largest coefficients
    new = bspline_coefficients(img, device="cpu").data.numpy()
    old = old_bspline_coefficients(img)
    if max(prefilter_segments(n) for n in shape) == 1:
        np.testing.assert_array_equal(new, old)  # one segment per line: the same filter, bit for bit
        return
    assert shape[1] // PREFILTER_SEGMENT > 1 or shape[0] // PREFILTER_SEGMENT > 1
    d = np.abs(new - old)
    # segment entries from truncated sums (float64) instead of the running recursion: a few
    # float32 ulps of the coefficients (measured 2.4e-4 grey levels at |c| < 1000 for 2048^2 noise)
    assert d.max() <= 4 * np.spacing(np.abs(old).max()), d.max()
    assert d.max() / 255.0 < 1e-6
    np.testing.assert_array_equal(new[:, :2], new[:, [4, 3]])  # mirrored borders still written
    np.testing.assert_array_equal(new[:2, :], new[[4, 3], :])
    np.testing.assert_array_equal(new[:, -2:], new[:, [-4, -5]])
    np.testing.assert_array_equal(new[-2:, :], new[[-4, -5], :])


def test_prefilter_segments_rejects_bad_lengths():
    from kernels.interp import prefilter_segments

    assert prefilter_segments(255) == 1 and prefilter_segments(256) == 2 and prefilter_segments(2048) == 16
    for bad in (0, -3, 2.5, True, "8"):
        with pytest.raises(ValueError, match="positive int"):
            prefilter_segments(bad)


# ------------------------------------------------------------------------------------------------
# the tiled 1st-order prototype (bench/icgn_tiled.py) against the one-thread-per-POI kernel
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("cpu_blocks", [True, False])
def test_tiled_icgn_prototype_matches_one_thread_per_poi(cpu_blocks):
    from bench.icgn_tiled import icgn_tiled
    from dic.synth import speckle_pair

    ref, cur = speckle_pair((112, 112), lambda x, y: (0.4 + 0.01 * (x - 56), -0.3 + 0.005 * (y - 56)), seed=3,
                            noise_sigma=1.0)
    yy, xx = np.mgrid[8:105:3, 8:105:3]
    pts = np.stack([xx.ravel() + 0.3, yy.ravel()], 1).astype(float)
    rim = K.prepare_reference(ref, device="cpu")
    sub = K.prepare_subsets(rim, pts, subset=21, order=1)
    ci = K.prepare_current(cur, device="cpu")
    guess = np.zeros((len(pts), 6))
    guess[:, 0] = np.where(np.arange(len(pts)) % 5 == 0, 30.0, 0.0)  # some POIs leave the image
    a = K.icgn(sub, ci, guess=guess).numpy()
    saved = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = cpu_blocks  # True: 32 lanes per POI and real tile reductions on the CPU
    try:
        b = icgn_tiled(sub, ci, guess=guess).numpy()
    finally:
        wp.config.enable_cpu_blocks = saved
    np.testing.assert_array_equal(b["status"], a["status"])
    np.testing.assert_array_equal(b["iterations"], a["iterations"])
    for st in (Status.CONVERGED, Status.OUT_OF_BOUNDS):
        assert np.any(a["status"] == int(st))
    # only the order of the float32 sums differs (measured: 1 ulp of u, v (1.9e-6 px at u = 31.6),
    # <= 3.6e-7 in the gradients, where converged;
    # the end points of POIs that never converge follow their rounding more loosely)
    conv = a["status"] == int(Status.CONVERGED)
    print("tiled: max |d params| where converged", np.abs(b["params"] - a["params"])[conv].max(axis=0))
    np.testing.assert_allclose(b["params"][conv], a["params"][conv], rtol=2e-7, atol=1e-6)  # ~1 ulp at u = 30
    np.testing.assert_allclose(b["zncc"][conv], a["zncc"][conv], rtol=0, atol=5e-6)  # float32 sums of 441 terms
    with pytest.raises(ValueError, match="1st-order only"):
        icgn_tiled(K.prepare_subsets(rim, pts[:3], subset=21, order=2), ci)


@wp.kernel
def _compose2(p: wp.array(dtype=vec12), dp: wp.array(dtype=vec12), s: float, out: wp.array(dtype=vec12),
              finite: wp.array(dtype=wp.int32)):
    i = wp.tid()
    c = K.compose_2nd(p[i], dp[i], s)
    out[i] = c
    finite[i] = int(wp.isfinite(c))


def test_compose_2nd_of_a_degenerate_update_is_not_finite():
    """The kernel turns a non-finite composition into DIVERGED (``wp.isfinite`` after compose_2nd)."""
    p = np.zeros((3, 12), np.float32)
    p[:, 0] = 1.5
    dp = np.zeros((3, 12), np.float32)
    dp[0, 1] = -1.0  # ux = -1: the update maps every column of the subset onto one
    dp[1, 8] = -1.0  # vy = -1
    dp[2, 1] = 0.05  # an ordinary update
    out = wp.empty(3, dtype=vec12, device="cpu")
    fin = wp.empty(3, dtype=wp.int32, device="cpu")
    wp.launch(_compose2, dim=3, inputs=[wp.array(p, dtype=vec12, device="cpu"), wp.array(dp, dtype=vec12, device="cpu"),
                                         10.0, out, fin], device="cpu")
    assert fin.numpy().tolist() == [0, 0, 1]


def test_segmented_prefilter_allocates_nothing_per_frame(monkeypatch):
    """The segments' entry values live in a per-thread scratch: a frame with ``out`` given allocates
    nothing (the reliability-guided and sequence paths count allocations per frame)."""
    from kernels.interp import bspline_coefficients

    img = wp.array(np.random.default_rng(0).random((300, 520)).astype(np.float32), dtype=float, device="cpu")
    out = wp.empty((304, 524), dtype=float, device="cpu")
    first = bspline_coefficients(img, device="cpu", out=out).data.numpy().copy()
    made = []
    real_empty, real_zeros = wp.empty, wp.zeros
    monkeypatch.setattr(wp, "empty", lambda *a, **k: made.append(a) or real_empty(*a, **k))
    monkeypatch.setattr(wp, "zeros", lambda *a, **k: made.append(a) or real_zeros(*a, **k))
    again = bspline_coefficients(img, device="cpu", out=out).data.numpy()
    assert made == []
    np.testing.assert_array_equal(again, first)
