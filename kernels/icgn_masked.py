"""IC-GN over the kept pixels of each subset: holes, free edges and cracks (per-POI pixel masks).

A subset that overlaps a hole, the background beyond a free edge or the far side of a crack is
correlated on the pixels that belong to the specimen only. Each POI carries a row of ``S*S`` flags
(1 = kept; the order of :mod:`dic.correlation.subset_masks`: entry ``(j + r) * S + (i + r)`` is
pixel ``(round(x) + i, round(y) + j)``), and every sum of :mod:`kernels.icgn` runs over the kept
pixels only:

* the reference mean ``fm`` and norm ``df`` of the ZNSSD, the centred Hessian
  ``H = sum (J - Jm)^T (J - Jm)``, ``sum J^T (f - fm)`` and ``sum J`` (:func:`prepare_subsets_masked`),
* the warped subset's ``sum g``, ``sum g^2``, ``sum (f - fm) g`` and ``sum J^T g`` of every
  iteration, hence the criterion, the ZNCC and the update (:func:`icgn_masked`),

with the kept count ``n`` in place of ``S*S``. The arithmetic is otherwise that of
:mod:`kernels.icgn` (the same refdata columns, H^-1 solve, composition and statuses), plus
``TOO_FEW_PIXELS``: a subset that keeps fewer than ``min_kept`` pixels is not tracked.

This is a separate Warp module with its own kernels, so the unmasked kernels of :mod:`kernels.icgn`,
:mod:`kernels.frames` and :mod:`kernels.rg_device` are untouched (the same code, the same bits, the
same registers) and compile no faster or slower; the masked path is chosen by
:func:`prepare_subsets_masked` and followed by :func:`kernels.icgn.icgn`,
:func:`kernels.icgn.gather_subsets` and :class:`kernels.frames.FrameTracker` (through
:data:`kernels.icgn.MASKED_PATH`, which this module fills: no import runs the other way).

The full ``S x S`` box must still lie in the image (``OUT_OF_BOUNDS`` as before), and a warped
subset is checked against the image bounds on the whole box.
"""
from __future__ import annotations

import math

import numpy as np
import warp as wp

from ._common import (
    ST_CONVERGED,
    ST_DIVERGED,
    ST_FLAT,
    ST_MAX_ITERATIONS,
    ST_OUT_OF_BOUNDS,
    ST_SINGULAR,
    ST_TOO_FEW_PIXELS,
    icgn_module_options,
    struct_of,
)
from ._launch import cuda_launch_bounds, launch_1d
from .checks import as_points
from .frames import FrameArrays, frame_current, frame_outputs
from .icgn import (
    MASKED_PATH,
    PREPARE_PARTS,
    CurrentCoefficients,
    IcgnOutputs,
    ReferenceImage,
    ReferenceSubsets,
    SubsetTable,
    _pad5,
    check_subset_order,
    compose_1st,
    compose_2nd,
    gn_step_scale,
    gn_update6,
    gn_update12,
    mat55d,
    mat66d,
    mat1212d,
    mono_exponents,
    n_params,
    refdata_columns,
    refdata_width,
    vec5,
    vec6,
    vec6d,
    vec12,
    vec12d,
    warped_inside,
    warped_value,
)

wp.set_module_options(icgn_module_options("_icgn_masked_2nd"))

#: the default minimum kept fraction of a masked subset (``min_kept_fraction``): below it, TOO_FEW_PIXELS
DEFAULT_MIN_KEPT_FRACTION = 0.5


@wp.struct
class SubsetMask:
    """The per-POI pixel masks on the device (:attr:`kernels.icgn.ReferenceSubsets.mask`)."""

    #: (N, S*S) 1 where the subset pixel is kept (row-major about the rounded POI)
    pixels: wp.array2d(dtype=wp.uint8)
    #: (N,) kept pixels per POI (written by the masked preparation)
    kept: wp.array(dtype=wp.int32)
    #: a subset keeping fewer pixels than this is TOO_FEW_PIXELS (>= 1)
    min_kept: int


def subset_mask(pixels: wp.array, kept: wp.array, min_kept: int) -> SubsetMask:
    """A :class:`SubsetMask` of the device arrays ``pixels`` (N, S*S) uint8 and ``kept`` (N,) int32."""
    return struct_of(SubsetMask, pixels=pixels, kept=kept, min_kept=int(min_kept))


def min_kept_pixels(fraction, subset: int) -> int:
    """The minimum kept pixel count of a subset of size ``subset`` for a kept ``fraction`` in (0, 1]:
    ``ceil(fraction * S^2)`` (at least 1)."""
    if isinstance(fraction, bool) or not isinstance(fraction, (int, float, np.floating, np.integer)) \
            or not math.isfinite(fraction) or not 0.0 < fraction <= 1.0:
        raise ValueError(f"min_kept_fraction must be a number in (0, 1] (the fraction of a subset's pixels it "
                         f"must keep), got {fraction!r}")
    return max(1, int(math.ceil(float(fraction) * subset * subset - 1e-9)))


# ----------------------------------------------------------------------------------------------
# reference side
# ----------------------------------------------------------------------------------------------


@wp.func
def _row_moments_deg4_masked(fgrad: wp.array(dtype=wp.vec3), row: int, r: int, dlx: float, inv_s: float, fm: float,
                             pixels: wp.array2d(dtype=wp.uint8), n: int, mrow: int):
    """:func:`kernels.icgn._row_moments_deg4` over the kept pixels of one subset row (mask row from ``mrow + i``)."""
    rxx = vec5()
    rxy = vec5()
    ryy = vec5()
    rx = wp.vec3()
    ry = wp.vec3()
    rxf = wp.vec3()
    ryf = wp.vec3()
    rss = float(0.0)
    for i in range(-r, r + 1):
        if pixels[n, mrow + i] != wp.uint8(0):
            xi = (float(i) + dlx) * inv_s
            fg = fgrad[row + i]
            fd = fg[0] - fm
            x2 = xi * xi
            pw = vec5(1.0, xi, x2, x2 * xi, x2 * x2)
            pw3 = wp.vec3(1.0, xi, x2)
            rxx += (fg[1] * fg[1]) * pw
            rxy += (fg[1] * fg[2]) * pw
            ryy += (fg[2] * fg[2]) * pw
            rx += fg[1] * pw3
            ry += fg[2] * pw3
            rxf += (fg[1] * fd) * pw3
            ryf += (fg[2] * fd) * pw3
            rss += fd * fd
    return rxx, rxy, ryy, _pad5(rx), _pad5(ry), _pad5(rxf), _pad5(ryf), rss


@wp.func
def _row_moments_deg2_masked(fgrad: wp.array(dtype=wp.vec3), row: int, r: int, dlx: float, inv_s: float, fm: float,
                             pixels: wp.array2d(dtype=wp.uint8), n: int, mrow: int):
    """:func:`kernels.icgn._row_moments_deg2` over the kept pixels of one subset row."""
    rxx = wp.vec3()
    rxy = wp.vec3()
    ryy = wp.vec3()
    rx = wp.vec3()
    ry = wp.vec3()
    rxf = wp.vec3()
    ryf = wp.vec3()
    rss = float(0.0)
    for i in range(-r, r + 1):
        if pixels[n, mrow + i] != wp.uint8(0):
            xi = (float(i) + dlx) * inv_s
            fg = fgrad[row + i]
            fd = fg[0] - fm
            pw = wp.vec3(1.0, xi, xi * xi)
            rxx += (fg[1] * fg[1]) * pw
            rxy += (fg[1] * fg[2]) * pw
            ryy += (fg[2] * fg[2]) * pw
            rx += fg[1] * pw
            ry += fg[2] * pw
            rxf += (fg[1] * fd) * pw
            ryf += (fg[2] * fd) * pw
            rss += fd * fd
    return _pad5(rxx), _pad5(rxy), _pad5(ryy), _pad5(rx), _pad5(ry), _pad5(rxf), _pad5(ryf), rss


def _make_prepare_masked(order: int):
    """The masked reference preparation of one order: :func:`kernels.icgn._make_prepare_subsets` over the
    kept pixels (the same Cholesky inverse and refdata layout: its wp.funcs, :data:`kernels.icgn.PREPARE_PARTS`)."""
    kk = n_params(order)
    mm = kk // 2
    matk = mat66d if order == 1 else mat1212d
    veck = vec6d if order == 1 else vec12d
    row_moments = _row_moments_deg2_masked if order == 1 else _row_moments_deg4_masked
    parts = PREPARE_PARTS[order]
    cholesky_inverse = parts["cholesky_inverse"]
    store_refdata = parts["store_refdata"]
    moments_hi = parts["moments_hi"]
    moments_lo = parts["moments_lo"]

    @wp.func
    def subset_hessian_masked(fgrad: wp.array(dtype=wp.vec3), width: int, cx0: int, cy0: int, r: int, dl: wp.vec2,
                              fmean: wp.float64, pixels: wp.array2d(dtype=wp.uint8), n: int, kept: int):
        """:func:`kernels.icgn` ``subset_hessian`` over the kept pixels (``kept`` of them)."""
        inv_s = 1.0 / float(r)
        fm = float(fmean)
        side = 2 * r + 1
        mxx = mat55d()
        mxy = mat55d()
        myy = mat55d()
        mx = mat55d()
        my = mat55d()
        mxf = mat55d()
        myf = mat55d()
        ss = wp.float64(0.0)
        for j in range(-r, r + 1):
            eta = wp.float64((float(j) + dl[1]) * inv_s)
            row = (cy0 + j) * width + cx0
            mrow = (j + r) * side + r
            rxx, rxy, ryy, rx, ry, rxf, ryf, rss = row_moments(fgrad, row, r, dl[0], inv_s, fm, pixels, n, mrow)
            ss += wp.float64(rss)
            mxx = moments_hi(mxx, rxx, eta)
            mxy = moments_hi(mxy, rxy, eta)
            myy = moments_hi(myy, ryy, eta)
            mx = moments_lo(mx, rx, eta)
            my = moments_lo(my, ry, eta)
            mxf = moments_lo(mxf, rxf, eta)
            myf = moments_lo(myf, ryf, eta)
        h = matk()
        a = veck()
        c = veck()
        npx = wp.float64(kept)
        for i in range(kk):
            ai, bi, wi = mono_exponents(i % mm)
            if i < mm:
                a[i] = wp.float64(wi) * mxf[ai, bi]
                c[i] = wp.float64(wi) * mx[ai, bi]
            else:
                a[i] = wp.float64(wi) * myf[ai, bi]
                c[i] = wp.float64(wi) * my[ai, bi]
        for i in range(kk):
            ai, bi, wi = mono_exponents(i % mm)
            for jj in range(i, kk):
                aj, bj, wj = mono_exponents(jj % mm)
                g = mxy[ai + aj, bi + bj]
                if i < mm and jj < mm:
                    g = mxx[ai + aj, bi + bj]
                if i >= mm and jj >= mm:
                    g = myy[ai + aj, bi + bj]
                h[i, jj] = wp.float64(wi * wj) * g - c[i] * c[jj] / npx
                h[jj, i] = h[i, jj]
        return h, a, c, ss

    def prepare_masked_kernel(offset: int, points: wp.array(dtype=wp.vec2d), sub: SubsetTable, mask: SubsetMask):
        # fills sub.centres, sub.deltas, sub.refdata, sub.status and mask.kept of POI n
        n = wp.tid() + offset
        r = sub.r
        width = sub.width
        side = 2 * r + 1
        pt = points[n]
        cx0 = int(wp.round(pt[0]))
        cy0 = int(wp.round(pt[1]))
        dl = wp.vec2(float(wp.float64(cx0) - pt[0]), float(wp.float64(cy0) - pt[1]))
        sub.centres[n] = wp.vec2i(cx0, cy0)
        sub.deltas[n] = dl
        mask.kept[n] = 0
        if cx0 - r < 0 or cy0 - r < 0 or cx0 + r > width - 1 or cy0 + r > sub.height - 1:
            sub.status[n] = ST_OUT_OF_BOUNDS
            return
        kept = int(0)
        fsum = wp.float64(0.0)
        for j in range(-r, r + 1):
            for i in range(-r, r + 1):
                if mask.pixels[n, (j + r) * side + i + r] != wp.uint8(0):
                    kept += 1
                    fsum += wp.float64(sub.fgrad[(cy0 + j) * width + cx0 + i][0])
        mask.kept[n] = kept
        if kept < mask.min_kept or kept < 1:
            sub.status[n] = ST_TOO_FEW_PIXELS
            return
        fmean = fsum / wp.float64(kept)
        h, a, c, ss = subset_hessian_masked(sub.fgrad, width, cx0, cy0, r, dl, fmean, mask.pixels, n, kept)
        if not (ss > wp.float64(kept) * wp.float64(sub.flat_var)):
            sub.status[n] = ST_FLAT
            return
        hinv, ok = cholesky_inverse(h)
        if ok == 0:
            sub.status[n] = ST_SINGULAR
            return
        store_refdata(sub.refdata, n, hinv, a, c, fmean, wp.sqrt(ss))
        sub.status[n] = ST_CONVERGED  # "ready"

    name = "_prepare_masked_1st" if order == 1 else "_prepare_masked_2nd"
    prepare_masked_kernel.__name__ = prepare_masked_kernel.__qualname__ = name
    return wp.kernel(prepare_masked_kernel, launch_bounds=cuda_launch_bounds(name))


#: the per-order masked reference preparation (order -> kernel)
_prepare_masked = {1: _make_prepare_masked(1), 2: _make_prepare_masked(2)}


# ----------------------------------------------------------------------------------------------
# IC-GN iterations
# ----------------------------------------------------------------------------------------------


@wp.func
def subset_pass_1st_masked(
    fgrad: wp.array(dtype=wp.vec3), width: int, coef: wp.array(dtype=wp.vec4), pitch: int,
    cx0: int, cy0: int, r: int, dl: wp.vec2, inv_s: float, p: vec6, fmean: float, goff: float,
    pixels: wp.array2d(dtype=wp.uint8), n: int,
):
    """:func:`kernels.icgn.subset_pass_1st` over the kept pixels of POI ``n``."""
    side = 2 * r + 1
    b = vec6()
    sg = float(0.0)
    sgg = float(0.0)
    sfg = float(0.0)
    for j in range(-r, r + 1):
        dy = float(j) + dl[1]
        u0 = p[0] + p[2] * dy
        v0 = p[3] + p[5] * dy
        row = (cy0 + j) * width + cx0
        mrow = (j + r) * side + r
        sx0 = float(0.0)
        sx1 = float(0.0)
        sy0 = float(0.0)
        sy1 = float(0.0)
        for i in range(-r, r + 1):
            if pixels[n, mrow + i] != wp.uint8(0):
                dx = float(i) + dl[0]
                g = warped_value(coef, pitch, cx0 + i, cy0 + j, u0 + p[1] * dx, v0 + p[4] * dx) - goff
                fg = fgrad[row + i]
                sg += g
                sgg += g * g
                sfg += (fg[0] - fmean) * g
                gx = fg[1] * g
                gy = fg[2] * g
                xi = dx * inv_s
                sx0 += gx
                sx1 += gx * xi
                sy0 += gy
                sy1 += gy * xi
        eta = dy * inv_s
        b[0] += sx0
        b[1] += sx1
        b[2] += sx0 * eta
        b[3] += sy0
        b[4] += sy1
        b[5] += sy0 * eta
    return b, wp.vec3(sg, sgg, sfg)


@wp.func
def subset_pass_2nd_masked(
    fgrad: wp.array(dtype=wp.vec3), width: int, coef: wp.array(dtype=wp.vec4), pitch: int,
    cx0: int, cy0: int, r: int, dl: wp.vec2, inv_s: float, p: vec12, fmean: float, goff: float,
    pixels: wp.array2d(dtype=wp.uint8), n: int,
):
    """:func:`kernels.icgn.subset_pass_2nd` over the kept pixels of POI ``n``."""
    side = 2 * r + 1
    b = vec12()
    sg = float(0.0)
    sgg = float(0.0)
    sfg = float(0.0)
    for j in range(-r, r + 1):
        dy = float(j) + dl[1]
        u0 = p[0] + dy * (p[2] + 0.5 * p[5] * dy)
        u1 = p[1] + p[4] * dy
        u2 = 0.5 * p[3]
        v0 = p[6] + dy * (p[8] + 0.5 * p[11] * dy)
        v1 = p[7] + p[10] * dy
        v2 = 0.5 * p[9]
        row = (cy0 + j) * width + cx0
        mrow = (j + r) * side + r
        sx0 = float(0.0)
        sx1 = float(0.0)
        sx2 = float(0.0)
        sy0 = float(0.0)
        sy1 = float(0.0)
        sy2 = float(0.0)
        for i in range(-r, r + 1):
            if pixels[n, mrow + i] != wp.uint8(0):
                dx = float(i) + dl[0]
                g = warped_value(coef, pitch, cx0 + i, cy0 + j, u0 + dx * (u1 + dx * u2),
                                 v0 + dx * (v1 + dx * v2)) - goff
                fg = fgrad[row + i]
                sg += g
                sgg += g * g
                sfg += (fg[0] - fmean) * g
                xi = dx * inv_s
                gx = fg[1] * g
                gy = fg[2] * g
                gxx = gx * xi
                gyx = gy * xi
                sx0 += gx
                sx1 += gxx
                sx2 += gxx * xi
                sy0 += gy
                sy1 += gyx
                sy2 += gyx * xi
        eta = dy * inv_s
        b[0] += sx0
        b[1] += sx1
        b[2] += sx0 * eta
        b[3] += 0.5 * sx2
        b[4] += sx1 * eta
        b[5] += 0.5 * sx0 * eta * eta
        b[6] += sy0
        b[7] += sy1
        b[8] += sy0 * eta
        b[9] += 0.5 * sy2
        b[10] += sy1 * eta
        b[11] += 0.5 * sy0 * eta * eta
    return b, wp.vec3(sg, sgg, sfg)


def _make_icgn_point_masked(order: int):
    """The masked per-POI IC-GN body of one order: :func:`kernels.icgn._make_icgn_point` with the subset
    passes over the kept pixels and the kept count in place of S^2."""
    kk = n_params(order)
    cols = refdata_columns(order)
    col_fmean = cols.fmean
    col_fnorm = cols.fnorm
    gn_update = gn_update6 if order == 1 else gn_update12

    def icgn_point_masked(n: int, sub: SubsetTable, mask: SubsetMask, cur: CurrentCoefficients,
                          guess: wp.array2d(dtype=float), max_iter: int, tol: float, out: IcgnOutputs):
        if wp.static(order == 1):
            p = vec6(guess[n, 0], guess[n, 1], guess[n, 2], guess[n, 3], guess[n, 4], guess[n, 5])
        else:
            p = vec12()
            for i in range(12):
                p[i] = guess[n, i]
        r = sub.r
        st = sub.status[n]
        cc = float(wp.nan)
        it = int(0)
        if st == ST_CONVERGED:
            kept = mask.kept[n]
            fmean = sub.refdata[n, col_fmean]
            fnorm = sub.refdata[n, col_fnorm]
            goff = fmean
            ctr = sub.centres[n]
            dl = sub.deltas[n]
            s = float(r)
            s2 = s * s
            st = ST_MAX_ITERATIONS
            while it < max_iter:
                if wp.static(order == 1):
                    inside = warped_inside(ctr[0], ctr[1], r, dl, sub.width, sub.height, p[0], p[1], p[2], 0.0, 0.0,
                                           0.0, p[3], p[4], p[5], 0.0, 0.0, 0.0)
                else:
                    inside = warped_inside(ctr[0], ctr[1], r, dl, sub.width, sub.height, p[0], p[1], p[2], p[3], p[4],
                                           p[5], p[6], p[7], p[8], p[9], p[10], p[11])
                if inside == 0:
                    st = ST_OUT_OF_BOUNDS
                    break
                if wp.static(order == 1):
                    b, sums = subset_pass_1st_masked(sub.fgrad, sub.width, cur.coef, cur.pitch, ctr[0], ctr[1], r, dl,
                                                     1.0 / s, p, fmean, goff, mask.pixels, n)
                else:
                    b, sums = subset_pass_2nd_masked(sub.fgrad, sub.width, cur.coef, cur.pitch, ctr[0], ctr[1], r, dl,
                                                     1.0 / s, p, fmean, goff, mask.pixels, n)
                it += 1
                gmean, ratio, cc = gn_step_scale(sums, kept, fnorm, sub.flat_var)
                goff = goff + gmean
                dq = gn_update(sub.refdata, n, b, ratio, gmean)
                norm = wp.length(dq)
                if ratio == 0.0 or not (norm <= float(2 * r + 1)):
                    st = ST_DIVERGED
                    break
                if wp.static(order == 1):
                    p = compose_1st(p, vec6(dq[0], dq[1] / s, dq[2] / s, dq[3], dq[4] / s, dq[5] / s))
                else:
                    dp = vec12(dq[0], dq[1] / s, dq[2] / s, dq[3] / s2, dq[4] / s2, dq[5] / s2,
                               dq[6], dq[7] / s, dq[8] / s, dq[9] / s2, dq[10] / s2, dq[11] / s2)
                    pn = compose_2nd(p, dp, s)
                    if not wp.isfinite(pn):
                        st = ST_DIVERGED
                        break
                    p = pn
                if norm < tol:
                    st = ST_CONVERGED
                    break
        for i in range(kk):
            out.params[n, i] = p[i]
        out.zncc[n] = cc
        out.iterations[n] = it
        out.status[n] = st

    icgn_point_masked.__name__ = icgn_point_masked.__qualname__ = f"icgn_point_masked_{'1st' if order == 1 else '2nd'}"
    return wp.func(icgn_point_masked)


#: the masked per-POI IC-GN bodies of the 1st and 2nd order
icgn_point_masked_1st = _make_icgn_point_masked(1)
icgn_point_masked_2nd = _make_icgn_point_masked(2)


@wp.kernel(launch_bounds=cuda_launch_bounds("_icgn_masked_1st"))
def _icgn_masked_1st(offset: int, sub: SubsetTable, mask: SubsetMask, cur: CurrentCoefficients,
                     guess: wp.array2d(dtype=float), max_iter: int, tol: float, out: IcgnOutputs):
    icgn_point_masked_1st(wp.tid() + offset, sub, mask, cur, guess, max_iter, tol, out)


@wp.kernel(launch_bounds=cuda_launch_bounds("_icgn_masked_2nd"))
def _icgn_masked_2nd(offset: int, sub: SubsetTable, mask: SubsetMask, cur: CurrentCoefficients,
                     guess: wp.array2d(dtype=float), max_iter: int, tol: float, out: IcgnOutputs):
    icgn_point_masked_2nd(wp.tid() + offset, sub, mask, cur, guess, max_iter, tol, out)


def _make_icgn_frames_masked(order: int):
    """The frames x POIs kernel of :mod:`kernels.frames` with the masked per-POI body."""
    icgn_point = icgn_point_masked_1st if order == 1 else icgn_point_masked_2nd

    def icgn_frames_masked(offset: int, n_points: int, sub: SubsetTable, mask: SubsetMask, frames: FrameArrays,
                           guess: wp.array3d(dtype=float), guess_stride: int, max_iter: int, tol: float):
        t = wp.tid() + offset
        f = t // n_points
        icgn_point(t - f * n_points, sub, mask, frame_current(frames, f), guess[f * guess_stride], max_iter, tol,
                   frame_outputs(frames, f))

    name = "_icgn_frames_masked_1st" if order == 1 else "_icgn_frames_masked_2nd"
    icgn_frames_masked.__name__ = icgn_frames_masked.__qualname__ = name
    return wp.kernel(icgn_frames_masked, launch_bounds=cuda_launch_bounds(name))


_icgn_frames_masked_1st = _make_icgn_frames_masked(1)
_icgn_frames_masked_2nd = _make_icgn_frames_masked(2)


@wp.kernel
def _gather_masks(offset: int, idx: wp.array(dtype=wp.int32), src: SubsetMask, dst: SubsetMask):
    t = wp.tid() + offset
    n = idx[t]
    dst.kept[t] = src.kept[n]
    for c in range(src.pixels.shape[1]):
        dst.pixels[t, c] = src.pixels[n, c]


# ----------------------------------------------------------------------------------------------
# launchers (called by kernels.icgn and kernels.frames when the subsets carry a mask)
# ----------------------------------------------------------------------------------------------


def as_mask_pixels(pixel_mask, n: int, subset: int) -> np.ndarray:
    """``pixel_mask`` checked as (N, S*S) (bool or 0/1 values) and returned as contiguous uint8."""
    m = np.asarray(pixel_mask)
    if m.shape != (n, subset * subset):
        raise ValueError(f"pixel_mask must have shape (N, subset*subset) = {(n, subset * subset)} (one row of kept "
                         f"pixels per POI, dic.correlation.subset_masks), got {m.shape}")
    if m.dtype != bool:
        if not np.issubdtype(m.dtype, np.integer) or (m.size and (m.min() < 0 or m.max() > 1)):
            raise ValueError(f"pixel_mask must be bool (True = pixel kept) or 0/1 integers, got dtype {m.dtype}")
    return np.ascontiguousarray(m, dtype=np.uint8)


def prepare_subsets_masked(reference: ReferenceImage, points, subset: int = 21, order: int = 1,
                           flat_std: float | None = None, *, pixel_mask,
                           min_kept_fraction: float = DEFAULT_MIN_KEPT_FRACTION) -> ReferenceSubsets:
    """:func:`kernels.icgn.prepare_subsets` of subsets correlated on some of their pixels only.

    Parameters
    ----------
    reference, points, subset, order, flat_std : as :func:`kernels.icgn.prepare_subsets`.
    pixel_mask : (N, S*S) bool or 0/1 array
        The pixels each subset keeps (:func:`dic.correlation.subset_masks.subset_pixel_masks`; row-major
        about the rounded POI): every sum of the reference side, and of :func:`kernels.icgn.icgn`,
        :func:`kernels.icgn.gather_subsets` and :class:`kernels.frames.FrameTracker` on the result, runs
        over the kept pixels only.
    min_kept_fraction : float in (0, 1]
        A subset keeping fewer than ``ceil(min_kept_fraction * S^2)`` pixels is ``TOO_FEW_PIXELS``.

    Returns
    -------
    ReferenceSubsets with ``mask`` set (a :class:`SubsetMask`); ``status`` as :func:`kernels.icgn.prepare_subsets`
    plus ``TOO_FEW_PIXELS``.
    """
    if not isinstance(reference, ReferenceImage):
        raise ValueError(f"reference must be a ReferenceImage from prepare_reference(), got {type(reference).__name__}")
    subset, order = check_subset_order(subset, order)
    pts = as_points(points)
    if flat_std is None:
        flat_std = 1e-3 * reference.grey_range
    if not np.isfinite(flat_std) or flat_std < 0:
        raise ValueError(f"flat_std must be a finite non-negative grey level, got {flat_std!r}")
    min_kept = min_kept_pixels(min_kept_fraction, subset)
    n = pts.shape[0]
    device = reference.device
    pixels = wp.array(as_mask_pixels(pixel_mask, n, subset), dtype=wp.uint8, device=device)
    mask = subset_mask(pixels, wp.zeros(n, dtype=wp.int32, device=device), min_kept)
    subsets = ReferenceSubsets(reference, pts, subset, order, wp.empty(n, dtype=wp.vec2i, device=device),
                               wp.empty(n, dtype=wp.vec2, device=device),
                               wp.zeros((n, refdata_width(order)), dtype=wp.float32, device=device),
                               wp.empty(n, dtype=wp.int32, device=device), float(flat_std), mask)
    pts_wp = wp.array(pts, dtype=wp.vec2d, device=device)
    launch_1d(_prepare_masked[order], n, [0, pts_wp, subsets.table, mask], device, offset_index=0, min_chunk=64)
    return subsets


def launch_icgn_masked(order: int, n: int, table: SubsetTable, mask: SubsetMask, coefficients: CurrentCoefficients,
                       guess: wp.array, max_iter: int, tol: float, outputs: IcgnOutputs, device: str) -> None:
    """Masked IC-GN of ``n`` POIs (:func:`kernels.icgn.icgn` of masked subsets)."""
    kernel = _icgn_masked_1st if order == 1 else _icgn_masked_2nd
    launch_1d(kernel, n, [0, table, mask, coefficients, guess, int(max_iter), float(tol), outputs], device,
              offset_index=0, min_chunk=64)


def launch_icgn_frames_masked(order: int, n: int, n_frames: int, table: SubsetTable, mask: SubsetMask,
                              frames: FrameArrays, guess: wp.array, guess_stride: int, max_iter: int, tol: float,
                              device: str) -> None:
    """Masked frames x POIs IC-GN (:class:`kernels.frames.FrameTracker` of masked subsets)."""
    kernel = _icgn_frames_masked_1st if order == 1 else _icgn_frames_masked_2nd
    launch_1d(kernel, n_frames * n, [0, n, table, mask, frames, guess, guess_stride, int(max_iter), float(tol)],
              device, offset_index=0, min_chunk=64)


def launch_gather_masks(count: int, idx: wp.array, src: SubsetMask, dst: SubsetMask, device: str) -> None:
    """Rows ``idx[:count]`` of ``src`` into the first ``count`` rows of ``dst`` (indexed IC-GN)."""
    launch_1d(_gather_masks, int(count), [0, idx, src, dst], device, offset_index=0, min_chunk=1024)


def mask_buffers(mask: SubsetMask, rows: int, subset: int, device: str) -> SubsetMask:
    """Uninitialised mask rows shaped like ``mask`` (:func:`kernels.icgn.subset_buffers`)."""
    return subset_mask(wp.empty((rows, subset * subset), dtype=wp.uint8, device=device),
                       wp.empty(rows, dtype=wp.int32, device=device), mask.min_kept)


def mask_rows(mask: SubsetMask, count: int) -> SubsetMask:
    """The first ``count`` rows of ``mask`` as views (:func:`kernels.icgn.subset_rows`)."""
    return subset_mask(mask.pixels[:count], mask.kept[:count], mask.min_kept)


MASKED_PATH.update(icgn=launch_icgn_masked, frames=launch_icgn_frames_masked, gather=launch_gather_masks,
                   buffers=mask_buffers, rows=mask_rows)


__all__ = ["SubsetMask", "subset_mask", "min_kept_pixels", "DEFAULT_MIN_KEPT_FRACTION", "as_mask_pixels",
           "prepare_subsets_masked", "icgn_point_masked_1st", "icgn_point_masked_2nd", "launch_icgn_masked",
           "launch_icgn_frames_masked", "launch_gather_masks", "mask_buffers", "mask_rows"]

