"""Outlier-robust IC-GN refinement: Tukey-weighted Gauss-Newton that discounts pixels the reference cannot explain,
and the residual test that decides where it is needed (adaptive robust IC-GN).

Why
    Plain IC-GN (:mod:`kernels.icgn`) weighs every subset pixel equally. When the texture itself
    changes between the reference and the current image (a speckle that flakes off, a new one
    painted on, a dust grain, a specular glint), the pixels of that change pull the least-squares
    fit: one changed 2 px speckle in a 21 px subset biases ``u, v`` by about 0.06 px, and in a long
    sequence with reference updates each such bias is composed into the result for good
    (bench/sequence.py, evolving texture). Their residuals are, however, far larger than the image
    noise, so an M-estimator can recognise and ignore them.

What
    Starting from a (plain IC-GN) solution ``p``, iteratively reweighted least squares on the
    grey-level residual of the linear intensity model

        ``e_i = f_i - (alpha g_i + beta)``

    (``f``: reference subset pixels, ``g``: current image at the warped pixels, ``alpha, beta``: the
    weighted least-squares contrast and offset) with a redescending weight: ``w_i = 1`` for
    ``|e_i| <= a s``, Tukey's biweight ``(1 - t^2)^2``, ``t = (|e_i| - a s) / ((c - a) s)``, beyond,
    and 0 from ``|e_i| >= c s`` (``a`` = :data:`CORE_A` = 3, ``c`` = :data:`TUKEY_C` = 6). ``s`` is the
    residual scale: the plain RMS residual at the start, then 1.4826 x the median ``|e|`` of the
    subset (the MAD: consistent for Gaussian noise, 50 % breakdown), read from a histogram of ``|e|``
    built in the same pass (a kernel cannot sort), floored at :data:`SCALE_FLOOR` of the subset's
    grey-level std. Each iteration is an inverse-compositional step with the weighted, offset-centred
    Hessian ``H_w = sum w J^T J - (sum w J)(sum w J)^T / sum w`` (recomputed per iteration because the
    weights change; assembled from row-separable moments like :func:`kernels.icgn.prepare_subsets`) and
    ``dq = -H_w^-1 sum w J e``; the warp update and the scaled convergence norm are those of
    :mod:`kernels.icgn`. It stops when ``|dq| < tol`` and the scale moved by less than
    :data:`SCALE_RTOL` over two weighted iterations, or when a weighted pass left every pixel at full
    weight. The weights were chosen on measurements (docs/dic2d.md, "Robust correlation"): narrower
    ones remove more of a changed texture's bias but cost precision where residuals are not noise-like
    (ray-traced renders), wider ones leave more bias.

Adaptive use
    :func:`residual_outliers` tells, from the residuals of each subset at its plain IC-GN warp, whether they
    hold a compact blob of outliers (kurtosis above :data:`KURTOSIS_MAX` in a moment pass, then the largest
    3 x 3 box sum of the residual above :data:`BOX_MAX` x its noise level in a box pass); ``Tracker(robust=
    "adaptive")``, the 2-D default, runs it on the subsets whose plain residual exceeds the gates of
    :data:`RMS_GATE` and :data:`NOISE_GATE` (:func:`reference_noise`) and refines only the flagged ones, so
    that every other subset keeps the plain result bit for bit.

Outputs per POI: parameters, the plain (unweighted) ZNCC at the final warp (so quality thresholds
mean what they mean for plain IC-GN), iterations, status, the inlier fraction ``sum w / n`` and the
number of pixels given zero weight.
A POI whose inlier fraction falls below ``min_inliers`` is DIVERGED: most of its subset is not
the reference texture. Only POIs flagged ``active`` are refined; the others are NOT_COMPUTED.

Both shape-function orders; float32 per pixel, float64 across rows and in the solve.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from ._common import (
    ST_CONVERGED,
    ST_DIVERGED,
    ST_MAX_ITERATIONS,
    ST_NOT_COMPUTED,
    ST_OUT_OF_BOUNDS,
    icgn_module_options,
)
from ._device import host_copy
from ._launch import cuda_launch_bounds, launch_1d
from .checks import in_range, positive_float
from .icgn import (
    CurrentCoefficients,
    CurrentImage,
    IcgnOutputs,
    ReferenceSubsets,
    SubsetTable,
    _as_guess,
    _row_to_moments_func,
    check_max_iter,
    compose_1st,
    compose_2nd,
    icgn_outputs,
    mat55d,
    mat66d,
    mat1212d,
    mono_exponents,
    n_params,
    refdata_columns,
    vec5,
    vec6,
    vec6d,
    vec12,
    vec12d,
    warped_inside,
    warped_value,
)

wp.set_module_options(icgn_module_options("_icgn_robust_1st"))


#: residuals beyond this many scales get zero weight
TUKEY_C = 6.0
#: full weight for residuals within this many scales (the core of the weight function)
CORE_A = 3.0
#: the residual scale is 1.4826 x the median |residual| (the MAD, consistent for Gaussian noise, 50 %
#: breakdown), read from a histogram of |residual| with HIST_PER_OCTAVE bins per factor 2 below
#: HIST_TOP scales (the median is interpolated within its bin: about 1 % resolution)
MAD_TO_SIGMA = wp.constant(1.482602218505602)
HIST_BINS = wp.constant(27)
HIST_PER_OCTAVE = wp.constant(3.0)
HIST_TOP = wp.constant(8.0)
vechist = wp.types.vector(length=27, dtype=wp.float32)
#: the box pass of :func:`residual_outliers` walks the subset in strips of this many box centres (two rows of
#: horizontal 3-sums of this length are kept on the stack)
BOX_STRIP = 32
vecstrip = wp.types.vector(length=BOX_STRIP, dtype=wp.float32)
vec5d = wp.types.vector(length=5, dtype=wp.float64)
#: the residual scale never drops below this fraction of the reference subset's grey-level std
#: (noise-free images: keeps interpolation residuals from being called outliers)
SCALE_FLOOR = 0.01
#: the scale has settled when it moves by less than this (relative) in one iteration
SCALE_RTOL = 0.03


@dataclass
class RobustResult:
    """Per-POI output of :func:`icgn_robust`, on the device (:meth:`numpy` for host copies).

    ``params`` (N, 6|12) float32; ``zncc`` (N,) float32, unweighted, at the final warp;
    ``iterations`` (N,) int32 (refinement iterations); ``status`` (N,) int32; ``inliers`` (N,)
    float32, ``sum w / n`` at the last iteration, and ``outliers`` (N,) float32, the pixels given zero
    weight there (both NaN where not refined).
    """

    params: wp.array
    zncc: wp.array
    iterations: wp.array
    status: wp.array
    inliers: wp.array
    outliers: wp.array

    def numpy(self) -> dict[str, np.ndarray]:
        return {name: host_copy(getattr(self, name)) for name in ("params", "zncc", "iterations", "status", "inliers",
                                                                "outliers")}


def _make_robust_kernel(order: int):
    kk = n_params(order)
    mm = kk // 2
    deg = order
    matk = mat66d if order == 1 else mat1212d
    veck = vec6d if order == 1 else vec12d
    vecp = vec6 if order == 1 else vec12
    moments_hi = _row_to_moments_func(2 * deg)
    moments_lo = _row_to_moments_func(deg)
    cols = refdata_columns(order)  # kernels.icgn.prepare_subsets' refdata
    col_fmean = cols.fmean
    col_fnorm = cols.fnorm
    tukey_c = float(TUKEY_C)
    core_a = float(CORE_A)
    scale_floor = float(SCALE_FLOOR)
    scale_rtol = float(SCALE_RTOL)

    # per-row moment vectors: powers xi^0..xi^(2 deg) for G = fx^2, fx fy, fy^2 and xi^0..xi^deg for the rest
    vhi = wp.vec3 if order == 1 else vec5
    vlo = wp.vec2 if order == 1 else wp.vec3

    @wp.func
    def powers(xi: float):
        """(xi^0..xi^(2 deg), xi^0..xi^deg)."""
        if wp.static(order == 1):
            return wp.vec3(1.0, xi, xi * xi), wp.vec2(1.0, xi)
        else:
            x2 = xi * xi
            return vec5(1.0, xi, x2, x2 * xi, x2 * x2), wp.vec3(1.0, xi, x2)

    @wp.func
    def pad5(v: Any):
        out = vec5()
        for i in range(wp.static(len(v))):
            out[i] = v[i]
        return out

    @wp.func
    def hist_median(hist: vechist, n: float, top: float):
        """The |e| below which half of the n pixels lie, from the histogram of :func:`weighted_pass`
        (interpolated geometrically within its bin; ``top`` when more than half lie above it)."""
        half = 0.5 * n
        cum = float(0.0)
        result = top
        found = int(0)
        for ii in range(HIST_BINS):
            i = HIST_BINS - 1 - ii
            c = hist[i]
            if found == 0 and c > 0.0 and cum + c >= half:
                frac = (half - cum) / c
                result = top * wp.pow(2.0, -(float(i) + 1.0 - frac) / HIST_PER_OCTAVE)
                found = 1
            cum += c
        return result

    @wp.func
    def warp_uv(p: Any, dx: float, dy: float):
        """Displacement (U, V) of the subset offset (dx, dy) under the physical parameters p."""
        if wp.static(order == 1):
            return p[0] + p[1] * dx + p[2] * dy, p[3] + p[4] * dx + p[5] * dy
        else:
            uu = p[0] + dx * (p[1] + 0.5 * p[3] * dx + p[4] * dy) + dy * (p[2] + 0.5 * p[5] * dy)
            vv = p[6] + dx * (p[7] + 0.5 * p[9] * dx + p[10] * dy) + dy * (p[8] + 0.5 * p[11] * dy)
            return uu, vv

    @wp.func
    def cholesky_solve(h: Any, rhs: Any):
        """x with h x = rhs for symmetric positive-definite h; ok = 0 when a pivot is not positive."""
        lo = matk()
        ok = int(1)
        hmax = wp.float64(0.0)
        for j in range(kk):
            hmax = wp.max(hmax, h[j, j])
        for j in range(kk):
            s = h[j, j]
            for m in range(j):
                s -= lo[j, m] * lo[j, m]
            if not (s > wp.float64(1e-9) * hmax):
                ok = 0
                s = wp.float64(1.0)
            d = wp.sqrt(s)
            lo[j, j] = d
            for i in range(j + 1, kk):
                t = h[i, j]
                for m in range(j):
                    t -= lo[i, m] * lo[j, m]
                lo[i, j] = t / d
        y = veck()
        for i in range(kk):
            t = rhs[i]
            for m in range(i):
                t -= lo[i, m] * y[m]
            y[i] = t / lo[i, i]
        x = veck()
        for ii in range(kk):
            i = kk - 1 - ii
            t = y[i]
            for m in range(i + 1, kk):
                t -= lo[m, i] * x[m]
            x[i] = t / lo[i, i]
        return x, ok

    @wp.func
    def weighted_pass(
        fgrad: wp.array(dtype=wp.vec3), width: int, coef: wp.array(dtype=wp.vec4), pitch: int,
        cx0: int, cy0: int, r: int, dl: wp.vec2, p: Any, fm: float, goff: float,
        alpha: float, beta: float, cut: float, top: float, core: float,
    ):
        """One pass over the warped subset at p.

        Pixel residual with the previous contrast/offset: e = f' - alpha g' - beta (f' = f - fm,
        g' = g - goff); weight w = 1 within ``core``, Tukey's biweight from ``core`` to ``cut`` (cut <= 0:
        w = 1). Returns the weighted moments
        of the steepest-descent images (for H_w, sum w J, sum w J f', sum w J g') and the scalar
        sums (sum w, sum w f', sum w g', sum w f'^2, sum w g'^2, sum w f' g'), the count of |e| >= top,
        the unweighted sums (sum g', sum g'^2, sum f' g') for the ZNCC, the counts of pixels beyond the
        core and at zero weight, and the histogram of |e| below ``top`` (top <= 0: none).
        """
        inv_s = 1.0 / float(r)
        mxx = mat55d()
        mxy = mat55d()
        myy = mat55d()
        mx = mat55d()
        my = mat55d()
        mxf = mat55d()
        myf = mat55d()
        mxg = mat55d()
        myg = mat55d()
        sw = wp.float64(0.0)
        swf = wp.float64(0.0)
        swg = wp.float64(0.0)
        swff = wp.float64(0.0)
        swgg = wp.float64(0.0)
        swfg = wp.float64(0.0)
        above = wp.float64(0.0)
        hist = vechist()
        sg = wp.float64(0.0)
        sgg = wp.float64(0.0)
        sfg = wp.float64(0.0)
        sdown = wp.float64(0.0)
        szero = wp.float64(0.0)
        for j in range(-r, r + 1):
            dy = float(j) + dl[1]
            row = (cy0 + j) * width + cx0
            rxx = vhi()
            rxy = vhi()
            ryy = vhi()
            rx = vlo()
            ry = vlo()
            rxf = vlo()
            ryf = vlo()
            rxg = vlo()
            ryg = vlo()
            rw = float(0.0)
            rwf = float(0.0)
            rwg = float(0.0)
            rwff = float(0.0)
            rwgg = float(0.0)
            rwfg = float(0.0)
            rg = float(0.0)
            rgg = float(0.0)
            rfg = float(0.0)
            rdown = int(0)
            rzero = int(0)
            for i in range(-r, r + 1):
                dx = float(i) + dl[0]
                uu, vv = warp_uv(p, dx, dy)
                g = warped_value(coef, pitch, cx0 + i, cy0 + j, uu, vv) - goff
                fgr = fgrad[row + i]
                f = fgr[0] - fm
                e = f - alpha * g - beta
                w = float(1.0)
                if cut > 0.0:
                    # full weight inside the core, Tukey's biweight from the core's edge to the cut
                    t = wp.max(wp.abs(e) - core, 0.0) / (cut - core)
                    t2 = t * t
                    w = float(0.0)
                    if t2 < 1.0:
                        w = (1.0 - t2) * (1.0 - t2)
                    if t > 0.0:
                        rdown += 1
                    if t >= 1.0:
                        rzero += 1
                if top > 0.0:  # the histogram of |e| for the median (bins of 2^(1/3) below top)
                    ae = wp.abs(e)
                    if ae >= top:
                        above += wp.float64(1.0)
                    else:
                        b = HIST_BINS - 1
                        if ae > 0.0:
                            b = wp.min(int(wp.floor(wp.log2(top / ae) * HIST_PER_OCTAVE)), HIST_BINS - 1)
                        hist[b] = hist[b] + 1.0
                rg += g
                rgg += g * g
                rfg += f * g
                xi = dx * inv_s
                phi, plo = powers(xi)
                wgx = w * fgr[1]
                wgy = w * fgr[2]
                rxx += (wgx * fgr[1]) * phi
                rxy += (wgx * fgr[2]) * phi
                ryy += (wgy * fgr[2]) * phi
                rx += wgx * plo
                ry += wgy * plo
                rxf += (wgx * f) * plo
                ryf += (wgy * f) * plo
                rxg += (wgx * g) * plo
                ryg += (wgy * g) * plo
                rw += w
                rwf += w * f
                rwg += w * g
                rwff += w * f * f
                rwgg += w * g * g
                rwfg += w * f * g
            eta = wp.float64(dy * inv_s)
            mxx = moments_hi(mxx, pad5(rxx), eta)
            mxy = moments_hi(mxy, pad5(rxy), eta)
            myy = moments_hi(myy, pad5(ryy), eta)
            mx = moments_lo(mx, pad5(rx), eta)
            my = moments_lo(my, pad5(ry), eta)
            mxf = moments_lo(mxf, pad5(rxf), eta)
            myf = moments_lo(myf, pad5(ryf), eta)
            mxg = moments_lo(mxg, pad5(rxg), eta)
            myg = moments_lo(myg, pad5(ryg), eta)
            sw += wp.float64(rw)
            swf += wp.float64(rwf)
            swg += wp.float64(rwg)
            swff += wp.float64(rwff)
            swgg += wp.float64(rwgg)
            swfg += wp.float64(rwfg)
            sg += wp.float64(rg)
            sgg += wp.float64(rgg)
            sfg += wp.float64(rfg)
            sdown += wp.float64(rdown)
            szero += wp.float64(rzero)
        # assemble H_w (uncentred), sum w J, sum w J f', sum w J g' from the moments
        h = matk()
        cj = veck()
        cf = veck()
        cg = veck()
        for i in range(kk):
            ai, bi, wi = mono_exponents(i % mm)
            wid = wp.float64(wi)
            if i < mm:
                cj[i] = wid * mx[ai, bi]
                cf[i] = wid * mxf[ai, bi]
                cg[i] = wid * mxg[ai, bi]
            else:
                cj[i] = wid * my[ai, bi]
                cf[i] = wid * myf[ai, bi]
                cg[i] = wid * myg[ai, bi]
        for i in range(kk):
            ai, bi, wi = mono_exponents(i % mm)
            for jj in range(i, kk):
                aj, bj, wj = mono_exponents(jj % mm)
                gm = mxy[ai + aj, bi + bj]
                if i < mm and jj < mm:
                    gm = mxx[ai + aj, bi + bj]
                if i >= mm and jj >= mm:
                    gm = myy[ai + aj, bi + bj]
                h[i, jj] = wp.float64(wi * wj) * gm
                h[jj, i] = h[i, jj]
        sums = vec12d(sw, swf, swg, swff, swgg, swfg, above, sg, sgg, sfg, sdown, szero)
        return h, cj, cf, cg, sums, hist

    def robust_kernel(
        offset: int, sub: SubsetTable, cur: CurrentCoefficients, active: wp.array(dtype=wp.int32),
        guess: wp.array2d(dtype=float), max_iter: int, tol: float, min_inliers: float, out: IcgnOutputs,
        inliers: wp.array(dtype=float), outliers: wp.array(dtype=float),
    ):
        n = wp.tid() + offset
        r = sub.r
        width = sub.width
        height = sub.height
        refdata = sub.refdata
        p = vecp()
        for i in range(kk):
            p[i] = guess[n, i]
        st = ST_NOT_COMPUTED
        cc = float(wp.nan)
        inl = float(wp.nan)
        outl = float(wp.nan)
        it = int(0)
        if active[n] != 0 and sub.status[n] == ST_CONVERGED:
            fm = refdata[n, col_fmean]
            npx = (2 * r + 1) * (2 * r + 1)
            nd = wp.float64(npx)
            fstd = refdata[n, col_fnorm] / wp.sqrt(float(npx))
            floor = scale_floor * fstd
            ctr = sub.centres[n]
            dl = sub.deltas[n]
            s = float(r)
            goff = fm
            alpha = float(1.0)
            beta = float(0.0)
            scale = float(0.0)  # 0: not known yet (first pass unweighted, unclipped)
            settled = int(0)
            st = ST_MAX_ITERATIONS
            while it < max_iter:
                if wp.static(order == 1):
                    inside = warped_inside(ctr[0], ctr[1], r, dl, width, height, p[0], p[1], p[2], 0.0, 0.0, 0.0,
                                           p[3], p[4], p[5], 0.0, 0.0, 0.0)
                else:
                    inside = warped_inside(ctr[0], ctr[1], r, dl, width, height, p[0], p[1], p[2], p[3], p[4],
                                           p[5], p[6], p[7], p[8], p[9], p[10], p[11])
                if inside == 0:
                    st = ST_OUT_OF_BOUNDS
                    break
                cut = tukey_c * scale
                top = HIST_TOP * scale
                core = core_a * scale
                h, cj, cf, cg, sm, hist = weighted_pass(sub.fgrad, width, cur.coef, cur.pitch, ctr[0], ctr[1], r, dl, p,
                                                        fm, goff, alpha, beta, cut, top, core)
                it += 1
                sw = sm[0]
                # unweighted ZNCC at this warp
                gmean = sm[7] / nd
                dg2 = sm[8] - sm[7] * gmean
                df2 = wp.float64(refdata[n, col_fnorm]) * wp.float64(refdata[n, col_fnorm])
                if dg2 > wp.float64(0.0) and df2 > wp.float64(0.0):
                    cc = float(sm[9] / wp.sqrt(df2 * dg2))  # sum f' = 0: sum f' (g' - gm) = sum f' g'
                inl = float(sw / nd)
                outl = float(sm[11])
                if not (sw > wp.float64(min_inliers) * nd) or not (sw > wp.float64(kk + 2)):
                    st = ST_DIVERGED
                    break
                # weighted contrast and offset of the model f' = alpha g' + beta
                wfm = sm[1] / sw
                wgm = sm[2] / sw
                cov = sm[5] - sm[1] * wgm
                varg = sm[4] - sm[2] * wgm
                if not (varg > wp.float64(1e-12) * sm[4]) or not (varg > wp.float64(0.0)):
                    st = ST_DIVERGED
                    break
                a64 = cov / varg
                b64 = wfm - a64 * wgm
                # the residual scale: plain RMS first, then the normalised median absolute residual
                if scale == 0.0:
                    rss = sm[3] - sm[1] * wfm - a64 * cov
                    new_scale = float(wp.sqrt(wp.max(rss, wp.float64(0.0)) / wp.float64(npx - 2)))
                else:
                    new_scale = MAD_TO_SIGMA * hist_median(hist, float(nd), top)
                new_scale = wp.max(new_scale, floor)
                moved = float(1.0)
                if scale > 0.0:
                    moved = wp.abs(new_scale - scale) / scale
                weighted = int(0)
                if scale > 0.0:  # this pass used weights
                    weighted = 1
                # IC step on the weighted, offset-centred system: dq = -H_w^-1 sum w (J - Jw) e
                hc = h - wp.outer(cj, cj) / sw
                rhs = veck()
                for i in range(kk):
                    rhs[i] = -(cf[i] - a64 * cg[i] - b64 * cj[i])
                dq64, ok = cholesky_solve(hc, rhs)
                if ok == 0:
                    st = ST_DIVERGED
                    break
                alpha = float(a64)
                beta = float(b64)
                scale = new_scale
                dq = vecp()
                for i in range(kk):
                    dq[i] = float(dq64[i])
                norm = wp.length(dq)
                if not (norm <= float(2 * r + 1)):
                    st = ST_DIVERGED
                    break
                if wp.static(order == 1):
                    p = compose_1st(p, vec6(dq[0], dq[1] / s, dq[2] / s, dq[3], dq[4] / s, dq[5] / s))
                else:
                    s2 = s * s
                    dp = vec12(dq[0], dq[1] / s, dq[2] / s, dq[3] / s2, dq[4] / s2, dq[5] / s2,
                               dq[6], dq[7] / s, dq[8] / s, dq[9] / s2, dq[10] / s2, dq[11] / s2)
                    pn = compose_2nd(p, dp, s)
                    if not wp.isfinite(pn):
                        st = ST_DIVERGED
                        break
                    p = pn
                settled += weighted
                # converged: the scale has settled over two weighted passes, or a weighted pass left every
                # pixel in the core (all weights 1: the weighted problem is the plain one, already solved)
                clean = int(0)
                if weighted == 1 and sm[10] == wp.float64(0.0):
                    clean = 1
                if norm < tol and ((moved < scale_rtol and settled >= 2) or clean == 1):
                    st = ST_CONVERGED
                    break
        for i in range(kk):
            out.params[n, i] = p[i]
        out.zncc[n] = cc
        out.iterations[n] = it
        out.status[n] = st
        inliers[n] = inl
        outliers[n] = outl

    @wp.func
    def hist_beyond(hist: vechist, above: float, top: float, t: float):
        """The number of pixels with |e| >= t from the histogram of :func:`weighted_pass` (``above``: those
        beyond ``top``; within a bin, the count is split geometrically)."""
        cnt = above
        for i in range(HIST_BINS):
            lo = top * wp.pow(2.0, -(float(i) + 1.0) / HIST_PER_OCTAVE)
            hi = top * wp.pow(2.0, -float(i) / HIST_PER_OCTAVE)
            if lo >= t:
                cnt += hist[i]
            elif hi > t:
                cnt += hist[i] * wp.log2(hi / t) * HIST_PER_OCTAVE
        return cnt

    @wp.func
    def max_box_sum(fgrad: wp.array(dtype=wp.vec3), width: int, coef: wp.array(dtype=wp.vec4), pitch: int,
                    cx0: int, cy0: int, r: int, dl: wp.vec2, p: Any, fm: float, a: float, b: float):
        """The largest |sum of e over a 3 x 3 box| of the subset's residual ``e = (f - fm) - a (g - fm) - b``
        (every box inside the subset: centres within r - 1 of the centre), one pass over the warped subset
        per strip of :data:`BOX_STRIP` box centres (two rows of horizontal 3-sums kept per strip)."""
        best = float(0.0)
        n_centres = 2 * r - 1
        n_strips = (n_centres + BOX_STRIP - 1) // BOX_STRIP
        for s in range(n_strips):
            c0 = -r + 1 + s * BOX_STRIP
            c1 = wp.min(c0 + BOX_STRIP - 1, r - 1)
            h1 = vecstrip()  # the previous row's horizontal 3-sums, by centre column - c0
            h2 = vecstrip()  # the row before that
            for j in range(-r, r + 1):
                dy = float(j) + dl[1]
                row = (cy0 + j) * width + cx0
                em = float(0.0)
                e0 = float(0.0)
                for i in range(c0 - 1, c1 + 2):
                    dx = float(i) + dl[0]
                    uu, vv = warp_uv(p, dx, dy)
                    e = (fgrad[row + i][0] - fm) - a * (warped_value(coef, pitch, cx0 + i, cy0 + j, uu, vv) - fm) - b
                    if i >= c0 + 1:
                        k = i - 1 - c0
                        h = em + e0 + e
                        if j >= -r + 2:
                            best = wp.max(best, wp.abs(h2[k] + h1[k] + h))
                        h2[k] = h1[k]
                        h1[k] = h
                    em = e0
                    e0 = e
        return best

    def statistics_kernel(
        offset: int, sub: SubsetTable, cur: CurrentCoefficients, active: wp.array(dtype=wp.int32),
        params: wp.array2d(dtype=float), kurtosis_max: float, beyond_max: float, with_scale: int, box_max: float,
        rms_out: wp.array(dtype=float),
        kurtosis_out: wp.array(dtype=float), beyond_out: wp.array(dtype=float), box_out: wp.array(dtype=float),
        flagged: wp.array(dtype=wp.int32),
    ):
        n = wp.tid() + offset
        r = sub.r
        rms = float(wp.nan)
        kurt = float(wp.nan)
        beyond = float(wp.nan)
        box = float(wp.nan)
        flag = int(0)
        if active[n] != 0 and sub.status[n] == ST_CONVERGED:
            p = vecp()
            for i in range(kk):
                p[i] = params[n, i]
            ctr = sub.centres[n]
            dl = sub.deltas[n]
            if wp.static(order == 1):
                inside = warped_inside(ctr[0], ctr[1], r, dl, sub.width, sub.height, p[0], p[1], p[2], 0.0, 0.0, 0.0,
                                       p[3], p[4], p[5], 0.0, 0.0, 0.0)
            else:
                inside = warped_inside(ctr[0], ctr[1], r, dl, sub.width, sub.height, p[0], p[1], p[2], p[3], p[4],
                                       p[5], p[6], p[7], p[8], p[9], p[10], p[11])
            if inside != 0:
                fm = sub.refdata[n, col_fmean]
                npx = (2 * r + 1) * (2 * r + 1)
                nd = wp.float64(npx)
                # one pass: the raw moments sum x^i y^j (i + j <= 4) of x = f - fm, y = g - fm, in float64
                mom = mat55d()
                for j in range(-r, r + 1):
                    dy = float(j) + dl[1]
                    row = (ctr[1] + j) * sub.width + ctr[0]
                    for i in range(-r, r + 1):
                        dx = float(i) + dl[0]
                        uu, vv = warp_uv(p, dx, dy)
                        x = wp.float64(sub.fgrad[row + i][0] - fm)
                        y = wp.float64(warped_value(cur.coef, cur.pitch, ctr[0] + i, ctr[1] + j, uu, vv) - fm)
                        x2 = x * x
                        y2 = y * y
                        mom[1, 0] += x
                        mom[0, 1] += y
                        mom[2, 0] += x2
                        mom[1, 1] += x * y
                        mom[0, 2] += y2
                        mom[3, 0] += x2 * x
                        mom[2, 1] += x2 * y
                        mom[1, 2] += x * y2
                        mom[0, 3] += y2 * y
                        mom[4, 0] += x2 * x2
                        mom[3, 1] += x2 * x * y
                        mom[2, 2] += x2 * y2
                        mom[1, 3] += x * y2 * y
                        mom[0, 4] += y2 * y2
                mom[0, 0] = nd
                # least-squares contrast and offset of x = a y + b, then sum e^2 and sum e^4 of e = x - a y - b
                # expanded in the moments: sum e^m = sum_{i+j+k=m} m!/(i! j! k!) (-a)^j (-b)^k sum x^i y^j
                mx = mom[1, 0] / nd
                my = mom[0, 1] / nd
                vy = mom[0, 2] / nd - my * my
                cxy = mom[1, 1] / nd - mx * my
                if vy > wp.float64(0.0):
                    a = cxy / vy
                    b = mx - a * my
                    fact = vec5d(wp.float64(1.0), wp.float64(1.0), wp.float64(2.0), wp.float64(6.0), wp.float64(24.0))
                    pa = vec5d()
                    pb = vec5d()
                    pa[0] = wp.float64(1.0)
                    pb[0] = wp.float64(1.0)
                    for i in range(1, 5):
                        pa[i] = pa[i - 1] * (-a)
                        pb[i] = pb[i - 1] * (-b)
                    se2 = wp.float64(0.0)
                    se4 = wp.float64(0.0)
                    for i in range(5):
                        for jj in range(5):
                            if i + jj <= 2:
                                k2 = 2 - i - jj
                                se2 += fact[2] / (fact[i] * fact[jj] * fact[k2]) * pa[jj] * pb[k2] * mom[i, jj]
                            if i + jj <= 4:
                                k4 = 4 - i - jj
                                se4 += fact[4] / (fact[i] * fact[jj] * fact[k4]) * pa[jj] * pb[k4] * mom[i, jj]
                    if se2 > wp.float64(0.0):
                        rms = float(wp.sqrt(se2 / wp.float64(npx - 2)))
                        kurt = float(nd * wp.max(se4, wp.float64(0.0)) / (se2 * se2))
                        fstd = sub.refdata[n, col_fnorm] / wp.sqrt(float(npx))
                        if with_scale != 0:
                            # the comparison statistic: the fraction of pixels beyond CORE_A MAD-scales
                            top = HIST_TOP * rms
                            h, cj, cf, cg, sm, hist = weighted_pass(
                                sub.fgrad, sub.width, cur.coef, cur.pitch, ctr[0], ctr[1], r, dl, p, fm, fm, float(a),
                                float(b), 0.0, top, 0.0)
                            mad = wp.max(MAD_TO_SIGMA * hist_median(hist, float(nd), top), scale_floor * fstd)
                            beyond = hist_beyond(hist, float(sm[6]), top, core_a * mad) / float(npx)
                        noise_free = rms <= scale_floor * fstd
                        if box_max < wp.inf and not noise_free and kurt > kurtosis_max:
                            box = max_box_sum(sub.fgrad, sub.width, cur.coef, cur.pitch, ctr[0], ctr[1], r, dl, p, fm,
                                              float(a), float(b)) / (3.0 * rms)
                        if box_max < wp.inf:
                            if box > box_max and not noise_free:
                                flag = 1
                        elif (kurt > kurtosis_max or beyond > beyond_max) and not noise_free:
                            flag = 1
        rms_out[n] = rms
        kurtosis_out[n] = kurt
        beyond_out[n] = beyond
        box_out[n] = box
        flagged[n] = flag

    name = "_icgn_robust_1st" if order == 1 else "_icgn_robust_2nd"
    robust_kernel.__name__ = robust_kernel.__qualname__ = name
    stats_name = "_residual_outliers_1st" if order == 1 else "_residual_outliers_2nd"
    statistics_kernel.__name__ = statistics_kernel.__qualname__ = stats_name
    return (wp.kernel(robust_kernel, launch_bounds=cuda_launch_bounds(name)),
            wp.kernel(statistics_kernel, launch_bounds=cuda_launch_bounds(stats_name)))


#: the robust refinement kernels by shape-function order
_icgn_robust_1st, _residual_outliers_1st = _make_robust_kernel(1)
_icgn_robust_2nd, _residual_outliers_2nd = _make_robust_kernel(2)
_icgn_robust = {1: _icgn_robust_1st, 2: _icgn_robust_2nd}
#: the residual-statistics kernels (:func:`residual_outliers`) by shape-function order
_residual_outliers = {1: _residual_outliers_1st, 2: _residual_outliers_2nd}


def robust_result(n: int, k: int, device: str) -> RobustResult:
    """Empty output buffers of :func:`icgn_robust` for ``n`` POIs with ``k`` parameters."""
    return RobustResult(wp.empty((n, k), dtype=wp.float32, device=device), wp.empty(n, dtype=wp.float32, device=device),
                        wp.empty(n, dtype=wp.int32, device=device), wp.empty(n, dtype=wp.int32, device=device),
                        wp.empty(n, dtype=wp.float32, device=device), wp.empty(n, dtype=wp.float32, device=device))


def icgn_robust(subsets: ReferenceSubsets, current: CurrentImage, guess, active=None, *, max_iter: int = 30,
                tol: float = 1e-3, min_inliers: float = 0.5, out: RobustResult | None = None) -> RobustResult:
    """Refine IC-GN solutions with Tukey-weighted IC-GN (see the module doc).

    Parameters
    ----------
    subsets : ReferenceSubsets from :func:`kernels.icgn.prepare_subsets`.
    current : CurrentImage from :func:`kernels.icgn.prepare_current` (either layout).
    guess : (N, 6|12) array or float32 ``wp.array`` on the subsets' device
        Starting parameters, normally a converged plain IC-GN solution.
    active : (N,) bool/int array, optional
        POIs to refine (default all); the others come out NOT_COMPUTED with their guess.
    max_iter : int in [1, MAX_ITER]; tol : float > 0 (px, the scaled update norm of kernels.icgn)
    min_inliers : float in [0, 1)
        A POI whose inlier fraction ``sum w / n`` drops below this is DIVERGED.
    out : RobustResult, optional (reused buffers, :func:`robust_result`)

    Returns
    -------
    RobustResult on the device.
    """
    device = _check_subsets_current(subsets, current)
    max_iter = check_max_iter(max_iter)
    tol = positive_float(tol, "tol", detail=" of pixels")
    min_inliers = in_range(min_inliers, 0.0, 1.0, "min_inliers")
    if min_inliers >= 1.0:
        raise ValueError(f"min_inliers must be below 1 (a fraction of the subset's pixels), got {min_inliers!r}")
    n = subsets.n_points
    k = n_params(subsets.order)
    g = _as_guess(guess, n, k, device)
    act = _as_active(active, n, device)
    if out is None:
        out = robust_result(n, k, device)
    elif out.params.shape != (n, k):
        raise ValueError(f"out was allocated for {out.params.shape}, expected params of shape {(n, k)}")
    launch_1d(
        _icgn_robust[subsets.order], n,
        [0, subsets.table, current.coefficients(), act, g, int(max_iter), float(tol), float(min_inliers),
         icgn_outputs(out.params, out.zncc, out.iterations, out.status), out.inliers, out.outliers],
        device, offset_index=0, min_chunk=64,
    )
    return out


@dataclass
class ResidualOutliers:
    """Per-POI output of :func:`residual_outliers`, host arrays.

    ``rms`` (N,) float32, grey levels: RMS residual ``sqrt(sum e^2 / (n - 2))`` of the least-squares
    intensity model at the given warp; ``kurtosis`` (N,) float32: ``n sum e^4 / (sum e^2)^2`` (3 for
    Gaussian residuals, large when a few pixels carry large residuals); ``beyond`` (N,) float32: the
    fraction of the subset's pixels whose |e| exceeds :data:`CORE_A` x the MAD-scale (only with
    ``with_scale``, else NaN); ``flagged`` (N,) bool: with ``box_max`` (the default) ``box > box_max``, else
    ``kurtosis > kurtosis_max`` (or ``beyond > beyond_max`` when given), and ``rms`` above :data:`SCALE_FLOOR` x
    the subset's grey-level std; ``box`` (N,) float32: the box statistic, the largest |sum of e over a 3 x 3
    box inside the subset| over 3 x ``rms`` (computed only with ``box_max``, where the kurtosis exceeds
    ``kurtosis_max``). NaN / False where not computed.
    """

    rms: np.ndarray
    kurtosis: np.ndarray
    beyond: np.ndarray
    flagged: np.ndarray
    box: np.ndarray


#: the kurtosis n sum e^4 / (sum e^2)^2 of a subset's final residuals above which adaptive robust IC-GN
#: refines it (3 for Gaussian noise, sd about sqrt(24 / n) = 0.23 for a 21 px subset: 4 is 4 sd above). Chosen on
#: measurements (bench/robust.py, docs/dic2d.md "Robust correlation"): on the 60-frame evolving texture 4 gives
#: 0.047 px final RMS error (as robust=True), 6 gives 0.051 px; on clean speckle pairs (noise 0.5-4 GL) the
#: default refines at most 2 % of the subsets and the displacement std stays at or below plain IC-GN's
KURTOSIS_MAX = 4.0
#: adaptive robust IC-GN tests only the subsets whose plain RMS residual (known without a pass from the plain
#: ZNCC C: sqrt((1 - C^2) n / (n - 2)) x the subset's grey-level std) exceeds RMS_GATE x that std: a changed
#: speckle raises a subset's residual to a good part of its contrast, image noise of a few grey levels does not
#: (a rule per subset, so that a POI's result does not depend on which other POIs are tracked with it)
RMS_GATE = 0.05
#: the box statistic (:func:`residual_outliers`): the largest |sum of the residual over a 3 x 3 box| of the
#: subset over 3 x its RMS residual (about 3 to 3.5 for independent pixel noise, whatever its distribution
#: far in the tails; up to sqrt(n - 2), 21 for a 21 px subset, when one compact blob carries the residual).
#: A changed speckle is such a blob; the edge residuals of smooth anti-aliased renders are not. Above BOX_MAX
#: adaptive robust IC-GN refines the subset. Measured (bench/robust.py, docs/dic2d.md "Robust correlation"): on
#: the 2 spp virtual-lab renders of bench/stereo.py rates the 99th percentile is 5.3, 0.3-0.4 % exceed 6; on the
#: evolving texture (2 % of the speckles replaced per frame) the median is 13 and the subsets below 6 carry
#: no measurable bias
BOX_MAX = 6.0


#: adaptive robust IC-GN tests only the subsets whose plain RMS residual (from the ZNCC, as for RMS_GATE) exceeds
#: NOISE_GATE x sqrt(2) x the reference subset's fine-scale roughness (:func:`reference_noise`: Immerkaer's noise
#: estimate over the subset, which also counts the texture's own pixel-scale detail): the residual a pair of images
#: with that much pixel-scale noise would leave (1 for pure white noise). A changed speckle leaves more (median 3-5 on
#: the evolving texture, 2 % of the speckles replaced per frame); the anti-aliased edge residuals of smooth renders and
#: the noise of clean speckle images less (virtual-lab renders of bench/stereo.py rates: 0.47 median, 0.68 at the
#: 90th percentile; clean speckle at 4 GL: 0.74 / 0.81). Measured: docs/dic2d.md "Robust correlation"
NOISE_GATE = 0.8
#: Immerkaer's noise estimate: sigma = sqrt(pi / 2) / 6 x mean |I * M| with M the 3 x 3 mask below
_IMMERKAER = np.sqrt(np.pi / 2.0) / 6.0


def reference_noise(image, centres, subset: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-subset fine-scale roughness and grey-level std of a reference image (host, numpy).

    ``image`` (H, W) grey; ``centres`` (N, 2) integer subset centres ``(x, y)`` (subsets inside the image; others
    are clipped to it); ``subset`` odd (px). Returns ``(sigma, std)``, each (N,) float64 grey levels: ``sigma``
    is Immerkaer's noise estimate (J. Immerkaer, "Fast noise variance estimation", CVIU 64, 1996) over the
    subset's pixels, ``sqrt(pi / 2) / 6 x mean |I * M|`` with ``M = [[1, -2, 1], [-2, 4, -2], [1, -2, 1]]`` (edge
    pixels replicated); it equals the noise std on white noise and adds the texture's own pixel-scale detail.
    ``std``: the population std of the subset's pixels.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must be a 2-D grey image, got shape {img.shape}")
    c = np.asarray(centres)
    if c.ndim != 2 or c.shape[1] != 2:
        raise ValueError(f"centres must be an (N, 2) array of (x, y), got shape {c.shape}")
    if not isinstance(subset, (int, np.integer)) or subset < 3 or subset % 2 == 0:
        raise ValueError(f"subset must be an odd integer >= 3, got {subset!r}")
    pad = np.pad(img, 1, mode="edge")
    lap = (pad[:-2, :-2] + pad[:-2, 2:] + pad[2:, :-2] + pad[2:, 2:]
           - 2.0 * (pad[:-2, 1:-1] + pad[2:, 1:-1] + pad[1:-1, :-2] + pad[1:-1, 2:]) + 4.0 * img)

    def window_mean(a):
        ii = np.zeros((a.shape[0] + 1, a.shape[1] + 1))
        ii[1:, 1:] = a.cumsum(0).cumsum(1)
        r = subset // 2
        h, w = a.shape
        x0 = np.clip(c[:, 0].astype(np.int64) - r, 0, w)
        x1 = np.clip(c[:, 0].astype(np.int64) + r + 1, 0, w)
        y0 = np.clip(c[:, 1].astype(np.int64) - r, 0, h)
        y1 = np.clip(c[:, 1].astype(np.int64) + r + 1, 0, h)
        area = np.maximum((x1 - x0) * (y1 - y0), 1)
        return (ii[y1, x1] - ii[y0, x1] - ii[y1, x0] + ii[y0, x0]) / area

    sigma = _IMMERKAER * window_mean(np.abs(lap))
    mean = window_mean(img)
    std = np.sqrt(np.maximum(window_mean(img * img) - mean * mean, 0.0))
    return sigma, std


def residual_outliers(subsets: ReferenceSubsets, current: CurrentImage, params, active=None, *,
                      kurtosis_max: float = KURTOSIS_MAX, beyond_max: float | None = None,
                      with_scale: bool = False, box_max: float | None = BOX_MAX) -> ResidualOutliers:
    """Whether the residuals of each subset at its warp show outliers (the test of adaptive robust IC-GN).

    One pass over each warped subset accumulates the float64 moments ``sum x^i y^j`` (i + j <= 4) of
    ``x = f - fm`` and ``y = g - fm`` (f: reference subset, g: current image at the warp, fm: the reference
    subset mean); from them the least-squares contrast and offset ``x = a y + b`` and, exactly, the sums
    of ``e^2`` and ``e^4`` of the residual ``e = x - a y - b``: the RMS residual and the kurtosis.
    Where the kurtosis exceeds ``kurtosis_max`` (a few pixels with residuals far above the rest) and
    ``box_max`` is given (the default, :data:`BOX_MAX`), a second pass computes the box statistic (the largest
    |3 x 3 box sum of e| over 3 x the RMS: about 3 for independent pixel residuals, up to sqrt(n - 2) for one
    compact blob) and the subset is ``flagged`` when it exceeds ``box_max``: a speckle that changed, a glint,
    rather than the spread edge residuals of anti-aliased renders. With ``box_max=None`` the kurtosis alone
    flags (the test before issue 26's box rule). Either way its RMS must be above the noise-free floor
    (:data:`SCALE_FLOOR` of the subset's grey-level std, as :func:`icgn_robust`'s scale).
    ``with_scale``: also the fraction of pixels beyond :data:`CORE_A` MAD-scales (a second pass with the
    histogram of |e|; the alternative statistic, for measurements); ``beyond_max``: flag a subset also when
    that fraction exceeds it (implies ``with_scale``).

    Parameters
    ----------
    subsets : ReferenceSubsets; current : CurrentImage (either layout), on the subsets' device.
    params : (N, 6|12) array or float32 ``wp.array``: the warps (normally converged plain IC-GN).
    active : (N,) bool/int array, optional: the POIs to test (default all); others come out NaN / False.
    kurtosis_max : float > 0 (None: the kurtosis flags nothing); beyond_max : float in [0, 1] or None (not with
    ``box_max``); with_scale : bool; box_max : float > 0 or None.

    Returns
    -------
    ResidualOutliers (host arrays).
    """
    device = _check_subsets_current(subsets, current)
    kurtosis_max = float(np.inf) if kurtosis_max is None else positive_float(kurtosis_max, "kurtosis_max")
    if not isinstance(with_scale, (bool, np.bool_)):
        raise ValueError(f"with_scale must be True or False, got {with_scale!r}")
    if beyond_max is None:
        beyond_max = float(np.inf)
    else:
        beyond_max = in_range(beyond_max, 0.0, 1.0, "beyond_max")
        with_scale = True
    if box_max is not None and beyond_max != float(np.inf):
        raise ValueError("give beyond_max (the MAD-fraction rule) or box_max (the box rule), not both")
    box_max = float(np.inf) if box_max is None else positive_float(box_max, "box_max")
    n = subsets.n_points
    k = n_params(subsets.order)
    g = _as_guess(params, n, k, device)
    act = _as_active(active, n, device)
    rms = wp.empty(n, dtype=wp.float32, device=device)
    kurt = wp.empty(n, dtype=wp.float32, device=device)
    beyond = wp.empty(n, dtype=wp.float32, device=device)
    box = wp.empty(n, dtype=wp.float32, device=device)
    flagged = wp.empty(n, dtype=wp.int32, device=device)
    launch_1d(_residual_outliers[subsets.order], n,
              [0, subsets.table, current.coefficients(), act, g, float(kurtosis_max), float(beyond_max), int(bool(with_scale)),
               float(box_max), rms, kurt, beyond, box, flagged], device,
              offset_index=0, min_chunk=64)
    return ResidualOutliers(host_copy(rms), host_copy(kurt), host_copy(beyond), host_copy(flagged) != 0,
                            host_copy(box))


def _as_active(active, n: int, device: str) -> wp.array:
    """``active`` (None: all, an int32 ``wp.array`` or a (N,) bool/int array) as an int32 ``wp.array``."""
    if active is None:
        return wp.full(n, 1, dtype=wp.int32, device=device)
    if isinstance(active, wp.array):
        if active.shape != (n,) or active.dtype != wp.int32:
            raise ValueError(f"active must be an int32 array of shape {(n,)}, got {active.shape} {active.dtype}")
        return active
    a = np.asarray(active)
    if a.shape != (n,) or not (a.dtype == bool or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"active must be a (N,) = ({n},) bool or integer array, got shape {a.shape} dtype {a.dtype}")
    return wp.array((a != 0).astype(np.int32), dtype=wp.int32, device=device)


__all__ = ["TUKEY_C", "CORE_A", "SCALE_FLOOR", "KURTOSIS_MAX", "RMS_GATE", "BOX_MAX", "NOISE_GATE", "reference_noise", "RobustResult", "ResidualOutliers", "icgn_robust",
           "residual_outliers", "robust_result"]


def _check_subsets_current(subsets, current):
    """The device of ``subsets`` (:func:`kernels.icgn.prepare_subsets`) once ``current``
    (:func:`kernels.icgn.prepare_current`) is checked to be on it with the reference's shape."""
    if not isinstance(subsets, ReferenceSubsets):
        raise ValueError(f"subsets must be a ReferenceSubsets from prepare_subsets(), got {type(subsets).__name__}")
    if not isinstance(current, CurrentImage):
        raise ValueError(f"current must be a CurrentImage from prepare_current(), got {type(current).__name__}")
    device = subsets.device
    if current.device != device:
        raise ValueError(f"current is on {current.device} but the subsets are on {device}")
    if current.shape != subsets.reference.shape:
        raise ValueError(f"current image has shape {current.shape} but the reference has shape "
                         f"{subsets.reference.shape}")
    return device
