"""IC-GN subset tracking with the ZNSSD criterion, 1st- and 2nd-order shape functions.

Inverse compositional Gauss-Newton (IC-GN) as in Pan, Li & Tong, "Fast, robust and accurate digital
image correlation calculation without redundant computations", Experimental Mechanics 53, 2013,
doi:10.1007/s11340-012-9640-x, with the 2nd-order shape function and its compositional update of
Gao, Cheng, Su & Wu, "High-efficiency and high-accuracy digital image correlation for
three-dimensional measurement", Optics and Lasers in Engineering 65, 2015,
doi:10.1016/j.optlaseng.2014.04.002. Current images are interpolated with cubic B-splines
(:mod:`kernels.interp`).

Conventions (docs/conventions.md): points ``(x, y)`` in reference-image pixels; parameters in the
order of :data:`kernels.conventions.PARAMS_1ST` / ``PARAMS_2ND`` (``u, v`` in px, gradients
dimensionless, 2nd derivatives in 1/px); per-POI outcome :class:`kernels.conventions.Status`.

Subsets
    A subset of odd size ``S = 2r + 1`` around the POI ``(cx, cy)`` is the square of integer pixels
    centred on ``(round(cx), round(cy))``. Its offsets from the POI are ``dx = i + (round(cx) - cx)``,
    ``i = -r..r`` (likewise ``dy``), so the shape function is expanded about the POI itself and
    ``u, v`` are the displacement *at the POI*; for integer POIs the subset is exactly centred. The
    reference subset uses pixel values and B-spline gradients at integer pixels, so nothing of the
    reference is interpolated during tracking.

Criterion and update
    ZNSSD ``C = sum [(f - fm)/df - (g - gm)/dg]^2`` (``df = sqrt(sum (f - fm)^2)``, likewise ``dg``).
    With the steepest-descent images ``J = grad f . dW/dq`` of the reference and the constant,
    mean-centred Hessian ``H = sum (J - Jm)^T (J - Jm)`` (the exact Gauss-Newton Hessian of the
    offset-invariant criterion; ~3 iterations instead of ~5 with Pan's ``sum J^T J`` for 2nd order),
    each iteration solves
    ``dq = -H^-1 [sum J^T (f - fm) - (df/dg) sum J^T (g - gm)]`` and updates the warp
    ``W(p) <- W(p) o W(dp)^-1`` (1st order: 3x3 affine matrices; 2nd order: Gao's 6x6 matrices on
    ``(x^2, xy, y^2, x, y, 1)``). The warped subset is never stored: one pass over it per iteration
    accumulates ``sum g``, ``sum g^2``, ``sum (f - fm) g`` and ``sum J^T g``, while
    ``sum J^T (f - fm)``, ``sum J`` and ``H^-1`` are precomputed once per reference
    (:func:`prepare_subsets`).

Scaled parameters and convergence norm
    Internally the gradients are scaled by the subset half-width ``r`` (``q = (u, r ux, r uy, v, ...)``
    and ``r^2 uxx`` ...), which conditions the Hessian and makes every component read in pixels
    (the displacement it causes at the subset edge). Convergence: ``|dq| < tol`` with
    ``|dq|^2 = du^2 + dv^2 + r^2 (dux^2 + duy^2 + dvx^2 + dvy^2)
    + r^4 (duxx^2 + duxy^2 + duyy^2 + dvxx^2 + dvxy^2 + dvyy^2)`` (px).

Statuses
    ``CONVERGED`` (norm < tol), ``MAX_ITERATIONS``, ``OUT_OF_BOUNDS`` (the reference subset, or a
    warped subset at any iteration, leaves ``[0, W-1] x [0, H-1]``), ``FLAT_SUBSET`` (reference
    grey-level standard deviation <= ``flat_std``), ``SINGULAR_HESSIAN`` (a Cholesky pivot below
    1e-6 of the largest diagonal entry of the scaled Hessian), ``DIVERGED`` (non-finite values,
    among them a 2nd-order update too degenerate to compose (:func:`solve_transposed6`), an update
    longer than the subset size, or a warped subset whose grey-level std is <= ``flat_std``).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import warp as wp

from ._common import (  # noqa: F401 - the status constants are re-exported for the other kernel modules
    ST_CONVERGED,
    ST_DIVERGED,
    ST_FLAT,
    ST_MAX_ITERATIONS,
    ST_NOT_COMPUTED,
    ST_OUT_OF_BOUNDS,
    ST_SINGULAR,
    icgn_module_options,
    struct_of,
)
from ._device import host_copy, resolve_device
from ._launch import cuda_launch_bounds, launch_1d
from .checks import as_points, odd_int, positive_float, positive_int
from .images import as_float32_image
from .interp import (
    PaddedImage,
    bspline3_value_grad,
    bspline3_weights_fast,
    bspline_coefficients,
    expand_rows4,
    rows4_view,
    stencil_dot_rows4,
)

wp.set_module_options(icgn_module_options("_icgn_2nd"))

vec6 = wp.types.vector(length=6, dtype=wp.float32)
vec12 = wp.types.vector(length=12, dtype=wp.float32)
mat66 = wp.types.matrix(shape=(6, 6), dtype=wp.float32)
vec12d = wp.types.vector(length=12, dtype=wp.float64)
mat1212d = wp.types.matrix(shape=(12, 12), dtype=wp.float64)
vec6d = wp.types.vector(length=6, dtype=wp.float64)
mat66d = wp.types.matrix(shape=(6, 6), dtype=wp.float64)
vec5 = wp.types.vector(length=5, dtype=wp.float32)
mat55d = wp.types.matrix(shape=(5, 5), dtype=wp.float64)

#: A Cholesky pivot below this fraction of the largest diagonal entry of the (scaled) Hessian makes
#: it SINGULAR_HESSIAN: beyond a condition number ~1e6 float32 solves lose the weak direction.
PIVOT_RTOL = 1e-6


def n_params(order: int) -> int:
    """Number of shape-function parameters of ``order`` (6 or 12)."""
    return 6 if order == 1 else 12


@dataclass(frozen=True)
class RefdataColumns:
    """The columns of one row of ``refdata``, the per-POI reference table of :func:`prepare_subsets`
    (float32, one row per POI, ``K`` = :func:`n_params` of the order)."""

    #: the first of K(K+1)/2 columns: the upper triangle of H^-1 (row-major, diagonal included)
    hinv: int
    #: the first of K columns: H^-1 sum J^T (f - fm)
    hinv_a: int
    #: the first of K columns: H^-1 sum J
    hinv_c: int
    #: fm, the mean grey level of the reference subset
    fmean: int
    #: df = sqrt(sum (f - fm)^2)
    fnorm: int
    #: floats per row
    width: int


def refdata_columns(order: int) -> RefdataColumns:
    """The ``refdata`` columns of shape-function ``order`` 1 or 2 (:data:`REFDATA_1ST`, :data:`REFDATA_2ND`)."""
    k = n_params(order)
    packed = k * (k + 1) // 2
    return RefdataColumns(hinv=0, hinv_a=packed, hinv_c=packed + k, fmean=packed + 2 * k, fnorm=packed + 2 * k + 1,
                          width=packed + 2 * k + 2)


#: ``refdata`` columns of the 1st order (hinv 0, hinv_a 21, hinv_c 27, fmean 33, fnorm 34; 35 floats)
REFDATA_1ST = refdata_columns(1)
#: ``refdata`` columns of the 2nd order (hinv 0, hinv_a 78, hinv_c 90, fmean 102, fnorm 103; 104 floats)
REFDATA_2ND = refdata_columns(2)


def refdata_width(order: int) -> int:
    """Floats stored per POI: packed H^-1, H^-1 sum J(f - fm), H^-1 sum J, fm, df."""
    return refdata_columns(order).width


# ----------------------------------------------------------------------------------------------
# the device tables: what an IC-GN kernel reads and writes, by name
# ----------------------------------------------------------------------------------------------


@wp.struct
class SubsetTable:
    """The reference side of IC-GN on the device: the reference image's values and gradients and the
    per-POI tables of :func:`prepare_subsets` (:meth:`ReferenceSubsets.table`)."""

    #: (H*W,) ``(f, df/dx, df/dy)`` of the reference at every pixel, row-major
    fgrad: wp.array(dtype=wp.vec3)
    #: W, H of the reference (px)
    width: int
    height: int
    #: (N,) integer subset centres ``(round(x), round(y))``
    centres: wp.array(dtype=wp.vec2i)
    #: (N,) ``centre - point`` (px)
    deltas: wp.array(dtype=wp.vec2)
    #: (N, :func:`refdata_width`) packed H^-1 and friends (:class:`RefdataColumns`)
    refdata: wp.array2d(dtype=float)
    #: (N,) CONVERGED (= ready) or why the POI cannot be tracked
    status: wp.array(dtype=wp.int32)
    #: subset half-width (px): the subset is (2r + 1)^2 pixels
    r: int
    #: squared grey-level std of a flat subset
    flat_var: float


@wp.struct
class CurrentCoefficients:
    """A current image's B-spline coefficients as IC-GN reads them (:meth:`CurrentImage.coefficients`)."""

    #: ((H + 4) * (W + 4),) four consecutive coefficients of a padded row per entry (either layout)
    coef: wp.array(dtype=wp.vec4)
    #: W + 4, the padded row length
    pitch: int


@wp.struct
class IcgnOutputs:
    """The per-POI results an IC-GN kernel writes (:meth:`IcgnResult.outputs`)."""

    #: (N, K) parameters, PARAMS_1ST/PARAMS_2ND order
    params: wp.array2d(dtype=float)
    #: (N,) ZNCC at the final warp (NaN where not computed)
    zncc: wp.array(dtype=float)
    #: (N,) IC-GN iterations
    iterations: wp.array(dtype=wp.int32)
    #: (N,) :class:`kernels.conventions.Status`
    status: wp.array(dtype=wp.int32)


def subset_table(subsets: ReferenceSubsets) -> SubsetTable:
    """The :class:`SubsetTable` of ``subsets`` (:attr:`ReferenceSubsets.table` keeps it)."""
    h, w = subsets.reference.shape
    return struct_of(SubsetTable, fgrad=subsets.reference.fgrad, width=w, height=h, centres=subsets.centres,
                     deltas=subsets.deltas, refdata=subsets.refdata, status=subsets.status, r=subsets.subset // 2,
                     flat_var=float(subsets.flat_std) ** 2)


def icgn_outputs(params: wp.array, zncc: wp.array, iterations: wp.array, status: wp.array) -> IcgnOutputs:
    """An :class:`IcgnOutputs` of the four result arrays."""
    return struct_of(IcgnOutputs, params=params, zncc=zncc, iterations=iterations, status=status)


# ----------------------------------------------------------------------------------------------
# @wp.func helpers
# ----------------------------------------------------------------------------------------------


@wp.func
def quad_range_1d(c0: float, c1: float, c2: float, lo: float, hi: float):
    """(min, max) of c0 + c1 t + c2 t^2 over t in [lo, hi]."""
    a = c0 + lo * (c1 + lo * c2)
    b = c0 + hi * (c1 + hi * c2)
    mn = wp.min(a, b)
    mx = wp.max(a, b)
    if c2 != 0.0:
        t = -c1 / (2.0 * c2)
        if t > lo and t < hi:
            v = c0 + t * (c1 + t * c2)
            mn = wp.min(mn, v)
            mx = wp.max(mx, v)
    return mn, mx


@wp.func
def quad_range_2d(a: float, bx: float, by: float, cxx: float, cxy: float, cyy: float, lo: wp.vec2, hi: wp.vec2):
    """(min, max) of a + bx x + by y + cxx x^2/2 + cxy x y + cyy y^2/2 over the box [lo, hi]."""
    # edges x = lo/hi (quadratic in y) and y = lo/hi (quadratic in x) contain all corners
    m0, n0 = quad_range_1d(a + lo[0] * (bx + 0.5 * cxx * lo[0]), by + cxy * lo[0], 0.5 * cyy, lo[1], hi[1])
    m1, n1 = quad_range_1d(a + hi[0] * (bx + 0.5 * cxx * hi[0]), by + cxy * hi[0], 0.5 * cyy, lo[1], hi[1])
    m2, n2 = quad_range_1d(a + lo[1] * (by + 0.5 * cyy * lo[1]), bx + cxy * lo[1], 0.5 * cxx, lo[0], hi[0])
    m3, n3 = quad_range_1d(a + hi[1] * (by + 0.5 * cyy * hi[1]), bx + cxy * hi[1], 0.5 * cxx, lo[0], hi[0])
    mn = wp.min(wp.min(m0, m1), wp.min(m2, m3))
    mx = wp.max(wp.max(n0, n1), wp.max(n2, n3))
    det = cxx * cyy - cxy * cxy
    if det != 0.0:  # interior critical point
        x = (-bx * cyy + by * cxy) / det
        y = (-by * cxx + bx * cxy) / det
        if x > lo[0] and x < hi[0] and y > lo[1] and y < hi[1]:
            v = a + bx * x + by * y + 0.5 * cxx * x * x + cxy * x * y + 0.5 * cyy * y * y
            mn = wp.min(mn, v)
            mx = wp.max(mx, v)
    return mn, mx


@wp.func
def warped_inside(
    cx0: int, cy0: int, r: int, dl: wp.vec2, width: int, height: int,
    u: float, ux: float, uy: float, uxx: float, uxy: float, uyy: float,
    v: float, vx: float, vy: float, vxx: float, vxy: float, vyy: float,
):
    """1 if every warped subset point X = cx0 + i + U(dx, dy) lies in [0, W-1] x [0, H-1]."""
    lo = wp.vec2(float(-r) + dl[0], float(-r) + dl[1])
    hi = wp.vec2(float(r) + dl[0], float(r) + dl[1])
    # X - cx0 = dx - dlx + U(dx, dy)
    xmn, xmx = quad_range_2d(u - dl[0], 1.0 + ux, uy, uxx, uxy, uyy, lo, hi)
    ymn, ymx = quad_range_2d(v - dl[1], vx, 1.0 + vy, vxx, vxy, vyy, lo, hi)
    ok = int(0)
    if xmn >= -float(cx0) and xmx <= float(width - 1 - cx0) and ymn >= -float(cy0) and ymx <= float(height - 1 - cy0):
        ok = 1
    return ok


@wp.func
def warped_value(coef: wp.array(dtype=wp.vec4), pitch: int, x0: int, y0: int, du: float, dv: float):
    """B-spline value at integer pixel (x0, y0) displaced by (du, dv), splitting integer/fraction."""
    fu = wp.floor(du)
    fv = wp.floor(dv)
    return stencil_dot_rows4(coef, pitch, x0 + int(fu), y0 + int(fv), bspline3_weights_fast(du - fu),
                             bspline3_weights_fast(dv - fv))


@wp.func
def subset_pass_1st(
    fgrad: wp.array(dtype=wp.vec3), width: int, coef: wp.array(dtype=wp.vec4), pitch: int,
    cx0: int, cy0: int, r: int, dl: wp.vec2, inv_s: float, p: vec6, fmean: float, goff: float,
):
    """One pass over the warped subset: (sum J^T g', (sum g', sum g'^2, sum (f - fm) g')), g' = g - goff.

    ``goff`` (the previous iteration's mean of g, fm at first) keeps the float32 sums free of
    cancellation: sum g'^2 - (sum g')^2 / n is the variance of g only when g' is nearly centred.
    """
    b = vec6()
    sg = float(0.0)
    sgg = float(0.0)
    sfg = float(0.0)
    for j in range(-r, r + 1):
        dy = float(j) + dl[1]
        u0 = p[0] + p[2] * dy
        v0 = p[3] + p[5] * dy
        row = (cy0 + j) * width + cx0
        sx0 = float(0.0)
        sx1 = float(0.0)
        sy0 = float(0.0)
        sy1 = float(0.0)
        for i in range(-r, r + 1):
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
def subset_pass_2nd(
    fgrad: wp.array(dtype=wp.vec3), width: int, coef: wp.array(dtype=wp.vec4), pitch: int,
    cx0: int, cy0: int, r: int, dl: wp.vec2, inv_s: float, p: vec12, fmean: float, goff: float,
):
    """2nd-order version of :func:`subset_pass_1st` (p physical, PARAMS_2ND order)."""
    b = vec12()
    sg = float(0.0)
    sgg = float(0.0)
    sfg = float(0.0)
    for j in range(-r, r + 1):
        dy = float(j) + dl[1]
        # U = u0 + dx (u1 + dx u2), V likewise
        u0 = p[0] + dy * (p[2] + 0.5 * p[5] * dy)
        u1 = p[1] + p[4] * dy
        u2 = 0.5 * p[3]
        v0 = p[6] + dy * (p[8] + 0.5 * p[11] * dy)
        v1 = p[7] + p[10] * dy
        v2 = 0.5 * p[9]
        row = (cy0 + j) * width + cx0
        sx0 = float(0.0)
        sx1 = float(0.0)
        sx2 = float(0.0)
        sy0 = float(0.0)
        sy1 = float(0.0)
        sy2 = float(0.0)
        for i in range(-r, r + 1):
            dx = float(i) + dl[0]
            g = warped_value(coef, pitch, cx0 + i, cy0 + j, u0 + dx * (u1 + dx * u2), v0 + dx * (v1 + dx * v2)) - goff
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


@wp.func
def compose_1st(p: vec6, dp: vec6):
    """Warp composition W(p) o W(dp)^-1 for affine warps (PARAMS_1ST order, physical units)."""
    a = wp.mat22(1.0 + p[1], p[2], p[4], 1.0 + p[5])
    d = wp.mat22(1.0 + dp[1], dp[2], dp[4], 1.0 + dp[5])
    dinv = wp.inverse(d)
    m = a * dinv
    t = wp.vec2(p[0], p[3]) - m * wp.vec2(dp[0], dp[3])
    return vec6(t[0], m[0, 0] - 1.0, m[0, 1], t[1], m[1, 0], m[1, 1] - 1.0)


@wp.func
def quad_warp_matrix(p: vec12):
    """Gao et al. (2015) 6x6 matrix of a 2nd-order warp acting on (x^2, xy, y^2, x, y, 1)."""
    a1 = 1.0 + p[1]
    a2 = p[2]
    a3 = p[0]
    b1 = p[7]
    b2 = 1.0 + p[8]
    b3 = p[6]
    uxx = p[3]
    uxy = p[4]
    uyy = p[5]
    vxx = p[9]
    vxy = p[10]
    vyy = p[11]
    m = mat66()
    m[0] = vec6(a1 * a1 + a3 * uxx, 2.0 * (a1 * a2 + a3 * uxy), a2 * a2 + a3 * uyy, 2.0 * a3 * a1, 2.0 * a3 * a2, a3 * a3)
    m[1] = vec6(
        a1 * b1 + 0.5 * (a3 * vxx + b3 * uxx), a1 * b2 + a2 * b1 + a3 * vxy + b3 * uxy,
        a2 * b2 + 0.5 * (a3 * vyy + b3 * uyy), a3 * b1 + a1 * b3, a3 * b2 + a2 * b3, a3 * b3,
    )
    m[2] = vec6(b1 * b1 + b3 * vxx, 2.0 * (b1 * b2 + b3 * vxy), b2 * b2 + b3 * vyy, 2.0 * b3 * b1, 2.0 * b3 * b2, b3 * b3)
    m[3] = vec6(0.5 * uxx, uxy, 0.5 * uyy, a1, a2, a3)
    m[4] = vec6(0.5 * vxx, vxy, 0.5 * vyy, b1, b2, b3)
    m[5] = vec6(0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    return m


#: A pivot of the pivot-free solve below this magnitude makes the composition non-finite (the
#: kernel then reports DIVERGED). Gao's matrices are O(1) in the subset-scaled coordinates, so a
#: pivot this small means an update that (nearly) folds the subset onto a line.
SOLVE_PIVOT_MIN = 1e-6


@wp.func
def solve_transposed6(m: mat66, rhs: vec6):
    """x with x^T m = rhs^T, i.e. m^T x = rhs, by Gaussian elimination without row swaps.

    No pivoting is needed when m is strictly diagonally dominant by rows (m^T by columns): then
    partial pivoting would swap nothing (every Schur complement stays column-dominant, Golub & Van
    Loan, Matrix Computations, 4th ed., sec. 3.4.10), so this performs exactly the operations of the
    partial-pivoting elimination (the same bits when compiled alike; inside the IC-GN kernel the
    compiler fuses them into FMAs differently: float32 rounding), and the solve is backward stable. Gao's matrix of a scaled update
    ``dn`` (:func:`compose_2nd`) is row-dominant whenever every ``|dn_i| < 0.1338`` (the root of
    ``11 d^2 + 6 d - 1``; rows 0-2 are the binding ones), i.e. every component of the IC-GN update
    ``dq`` is below ``0.13 r`` px. Without row swaps nothing is indexed at run time, so the matrix
    stays in registers (with the swap, 168 bytes of stack on sm_90). A pivot whose magnitude is not
    above :data:`SOLVE_PIVOT_MIN` (a degenerate update) returns NaN.
    """
    a = wp.transpose(m)
    x = rhs
    for c in range(6):
        if not (wp.abs(a[c, c]) > SOLVE_PIVOT_MIN):
            return vec6(wp.nan, wp.nan, wp.nan, wp.nan, wp.nan, wp.nan)
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
def compose_2nd(p: vec12, dp: vec12, s: float):
    """W(p) o W(dp)^-1 for 2nd-order warps (Gao et al. 2015), composed in coordinates scaled by s."""
    pn = vec12(p[0] / s, p[1], p[2], p[3] * s, p[4] * s, p[5] * s, p[6] / s, p[7], p[8], p[9] * s, p[10] * s, p[11] * s)
    dn = vec12(dp[0] / s, dp[1], dp[2], dp[3] * s, dp[4] * s, dp[5] * s,
               dp[6] / s, dp[7], dp[8], dp[9] * s, dp[10] * s, dp[11] * s)
    mp = quad_warp_matrix(pn)
    md = quad_warp_matrix(dn)
    # rows 3 and 4 of mp * md^-1
    rx = solve_transposed6(md, mp[3])
    ry = solve_transposed6(md, mp[4])
    return vec12(
        rx[5] * s, rx[3] - 1.0, rx[4], 2.0 * rx[0] / s, rx[1] / s, 2.0 * rx[2] / s,
        ry[5] * s, ry[3], ry[4] - 1.0, 2.0 * ry[0] / s, ry[1] / s, 2.0 * ry[2] / s,
    )


# ----------------------------------------------------------------------------------------------
# kernels
# ----------------------------------------------------------------------------------------------


@wp.kernel(launch_bounds=cuda_launch_bounds("_reference_gradients"))
def _reference_gradients(offset: int, image: wp.array2d(dtype=float), coef: wp.array(dtype=float), pitch: int,
                         width: int, fgrad: wp.array(dtype=wp.vec3)):
    k = wp.tid() + offset
    y = k // width
    x = k - y * width
    vg = bspline3_value_grad(coef, pitch, float(x), float(y))
    fgrad[k] = wp.vec3(image[y, x], vg[1], vg[2])


@wp.kernel(launch_bounds=cuda_launch_bounds("_reference_gradients_window"))
def _reference_gradients_window(offset: int, image: wp.array2d(dtype=float), coef: wp.array(dtype=float), pitch: int,
                                width: int, x0: int, y0: int, window_width: int, fgrad: wp.array(dtype=wp.vec3)):
    """:func:`_reference_gradients` over the pixels of a window (x0, y0, window_width columns) only."""
    t = wp.tid() + offset
    dy = t // window_width
    y = y0 + dy
    x = x0 + (t - dy * window_width)
    vg = bspline3_value_grad(coef, pitch, float(x), float(y))
    fgrad[y * width + x] = wp.vec3(image[y, x], vg[1], vg[2])


@wp.func
def mono_exponents(k: int):
    """(power of xi, power of eta, coefficient) of the k-th term of (1, xi, eta, xi^2/2, xi*eta, eta^2/2)."""
    if k == 0:
        return 0, 0, 1.0
    if k == 1:
        return 1, 0, 1.0
    if k == 2:
        return 0, 1, 1.0
    if k == 3:
        return 2, 0, 0.5
    if k == 4:
        return 1, 1, 1.0
    return 0, 2, 0.5


@wp.func
def _pad5(v: wp.vec3):
    return vec5(v[0], v[1], v[2], 0.0, 0.0)


@wp.func
def _row_moments_deg4(fgrad: wp.array(dtype=wp.vec3), row: int, r: int, dlx: float, inv_s: float, fm: float):
    """One subset row: sums of G * xi^alpha for G = fx^2, fx fy, fy^2 (alpha <= 4) and G = fx, fy,
    fx fd, fy fd (alpha <= 2, entries 3 and 4 left at zero), fd = f - fm; and sum fd^2."""
    rxx = vec5()
    rxy = vec5()
    ryy = vec5()
    rx = wp.vec3()
    ry = wp.vec3()
    rxf = wp.vec3()
    ryf = wp.vec3()
    rss = float(0.0)
    for i in range(-r, r + 1):
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
def _row_moments_deg2(fgrad: wp.array(dtype=wp.vec3), row: int, r: int, dlx: float, inv_s: float, fm: float):
    """As :func:`_row_moments_deg4` for alpha <= 2 (1st order); entries 3, 4 are left at zero."""
    rxx = wp.vec3()
    rxy = wp.vec3()
    ryy = wp.vec3()
    rx = wp.vec3()
    ry = wp.vec3()
    rxf = wp.vec3()
    ryf = wp.vec3()
    rss = float(0.0)
    for i in range(-r, r + 1):
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


def _row_to_moments_func(deg: int):
    """wp.func m[alpha, beta] += row[alpha] * eta^beta for alpha + beta <= deg (deg fixed)."""

    @wp.func
    def row_to_moments(m: mat55d, row: vec5, eta: wp.float64):
        eb = wp.float64(1.0)
        for beta in range(deg + 1):
            for alpha in range(deg + 1 - beta):
                m[alpha, beta] = m[alpha, beta] + wp.float64(row[alpha]) * eb
            eb = eb * eta
        return m

    return row_to_moments


#: order -> the wp.funcs of :func:`_make_prepare_subsets` that :mod:`kernels.icgn_masked` reuses by name
PREPARE_PARTS: dict[int, dict] = {}

#: the masked path's launchers by job ("icgn", "frames", "gather", "buffers", "rows"), registered by
#: :mod:`kernels.icgn_masked` when it is imported: masked subsets come from it, so they are there whenever
#: one is used, and this module imports nothing of it (the kernel modules stay free of import cycles)
MASKED_PATH: dict[str, Any] = {}


def _make_prepare_subsets(order: int):
    """The ``_prepare_subsets`` kernel of one shape-function order, with K = 6 or 12 parameters and
    the moment degree fixed at compile time (constant loop bounds, K x K matrices of the order's
    size), so the compiler can unroll the loops and keep constant-indexed values in registers.

    The arithmetic is that of the former run-time-``k`` kernel, operation for operation, so the
    results are bitwise identical (tests/kernels/test_kernel_variants.py compares against a copy of it).
    """
    kk = n_params(order)  # parameters
    dj = order  # highest total degree of the shape-function monomials (1 or 2)
    mm = kk // 2  # monomials per displacement component
    matk = mat66d if order == 1 else mat1212d
    veck = vec6d if order == 1 else vec12d
    row_moments = _row_moments_deg2 if order == 1 else _row_moments_deg4
    cols = refdata_columns(order)
    col_h = cols.hinv
    col_a = cols.hinv_a
    col_c = cols.hinv_c
    col_fmean = cols.fmean
    col_fnorm = cols.fnorm
    # unrolled, the order-2 Cholesky inverse is ~18 000 lines of C++ (3x the CPU compile time of
    # this module) and still does not fit in registers: it keeps run-time loops
    unroll_solve = order == 1

    moments_hi = _row_to_moments_func(2 * dj)  # G = fx^2, fx fy, fy^2
    moments_lo = _row_to_moments_func(dj)  # G = fx, fy, fx (f - fm), fy (f - fm)

    @wp.func
    def cholesky_inverse(h: Any):
        """Inverse of the symmetric positive-definite K x K matrix h; ok = 0 if singular
        (a pivot below PIVOT_RTOL times the largest diagonal entry)."""
        nk = kk
        if wp.static(not unroll_solve):
            nk = int(kk)  # a run-time value: the loops stay loops
        lo = matk()
        ok = int(1)
        hmax = wp.float64(0.0)
        for j in range(nk):
            hmax = wp.max(hmax, h[j, j])
        for j in range(nk):
            s = h[j, j]
            for m in range(j):
                s -= lo[j, m] * lo[j, m]
            if not (s > wp.float64(PIVOT_RTOL) * hmax):
                ok = 0
                s = wp.float64(1.0)
            d = wp.sqrt(s)
            lo[j, j] = d
            for i in range(j + 1, nk):
                t = h[i, j]
                for m in range(j):
                    t -= lo[i, m] * lo[j, m]
                lo[i, j] = t / d
        inv = matk()
        for col in range(nk):  # solve L L^T x = e_col
            y = veck()
            for i in range(nk):
                t = wp.float64(0.0)
                if i == col:
                    t = wp.float64(1.0)
                for m in range(i):
                    t -= lo[i, m] * y[m]
                y[i] = t / lo[i, i]
            for ii in range(nk):
                i = nk - 1 - ii
                t = y[i]
                for m in range(i + 1, nk):
                    t -= lo[m, i] * inv[m, col]
                inv[i, col] = t / lo[i, i]
        return inv, ok

    @wp.func
    def subset_hessian(fgrad: wp.array(dtype=wp.vec3), width: int, cx0: int, cy0: int, r: int, dl: wp.vec2,
                       fmean: wp.float64):
        """Centred H = sum (J - Jm)^T (J - Jm), a = sum J^T (f - fm), c = sum J, ss = sum (f - fm)^2.

        J are the steepest-descent images of the scaled parameters. The sums are assembled from
        row-separable moments sum G xi^alpha eta^beta (G = fx^2, fx fy, fy^2, fx, fy, fx (f-fm),
        fy (f-fm)): about 40 multiply-adds per pixel instead of K(K+1)/2 + 2K (float32 within a
        row, float64 across rows). Centring J gives the exact Gauss-Newton Hessian of the
        offset-invariant criterion (sum (J - Jm)^T e = sum J^T e because sum e = 0); it makes
        IC-GN converge in about 3 iterations where the uncentred Hessian of Pan et al. (2013)
        needs about 5 (2nd order).
        """
        inv_s = 1.0 / float(r)
        fm = float(fmean)
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
            rxx, rxy, ryy, rx, ry, rxf, ryf, rss = row_moments(fgrad, row, r, dl[0], inv_s, fm)
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
        npx = wp.float64((2 * r + 1) * (2 * r + 1))
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

    @wp.func
    def store_refdata(refdata: wp.array2d(dtype=float), n: int, hinv: Any, a: Any, c: Any,
                      fmean: wp.float64, fnorm: wp.float64):
        """Row ``n`` of ``refdata`` (:class:`RefdataColumns`): packed upper H^-1 (row-major), H^-1 a, H^-1 c, fm, df."""
        col = int(col_h)
        for i in range(kk):
            for j in range(i, kk):
                refdata[n, col] = float(hinv[i, j])
                col += 1
        for i in range(kk):
            ha = wp.float64(0.0)
            hc = wp.float64(0.0)
            for j in range(kk):
                ha += hinv[i, j] * a[j]
                hc += hinv[i, j] * c[j]
            refdata[n, col_a + i] = float(ha)
            refdata[n, col_c + i] = float(hc)
        refdata[n, col_fmean] = float(fmean)
        refdata[n, col_fnorm] = float(fnorm)

    def prepare_subsets_kernel(offset: int, points: wp.array(dtype=wp.vec2d), sub: SubsetTable):
        # fills sub.centres, sub.deltas, sub.refdata and sub.status of POI n from sub.fgrad
        n = wp.tid() + offset
        r = sub.r
        width = sub.width
        pt = points[n]
        cx0 = int(wp.round(pt[0]))
        cy0 = int(wp.round(pt[1]))
        dl = wp.vec2(float(wp.float64(cx0) - pt[0]), float(wp.float64(cy0) - pt[1]))
        sub.centres[n] = wp.vec2i(cx0, cy0)
        sub.deltas[n] = dl
        if cx0 - r < 0 or cy0 - r < 0 or cx0 + r > width - 1 or cy0 + r > sub.height - 1:
            sub.status[n] = ST_OUT_OF_BOUNDS
            return
        npx = (2 * r + 1) * (2 * r + 1)
        fsum = wp.float64(0.0)
        for j in range(-r, r + 1):
            for i in range(-r, r + 1):
                fsum += wp.float64(sub.fgrad[(cy0 + j) * width + cx0 + i][0])
        fmean = fsum / wp.float64(npx)
        h, a, c, ss = subset_hessian(sub.fgrad, width, cx0, cy0, r, dl, fmean)
        if not (ss > wp.float64(npx) * wp.float64(sub.flat_var)):
            sub.status[n] = ST_FLAT
            return
        hinv, ok = cholesky_inverse(h)
        if ok == 0:
            sub.status[n] = ST_SINGULAR
            return
        store_refdata(sub.refdata, n, hinv, a, c, fmean, wp.sqrt(ss))
        sub.status[n] = ST_CONVERGED  # "ready"

    # the order's closures, for the masked reference preparation of kernels.icgn_masked (the same wp.funcs:
    # no second copy is registered in this module, whose kernels and bits stay as they are)
    PREPARE_PARTS[order] = {"cholesky_inverse": cholesky_inverse, "store_refdata": store_refdata,
                            "moments_hi": moments_hi, "moments_lo": moments_lo}
    name = "_prepare_subsets_1st" if order == 1 else "_prepare_subsets_2nd"
    prepare_subsets_kernel.__name__ = prepare_subsets_kernel.__qualname__ = name
    return wp.kernel(prepare_subsets_kernel, launch_bounds=cuda_launch_bounds(name))


#: the per-order kernels computing the reference side of IC-GN (order -> kernel)
_prepare_subsets = {1: _make_prepare_subsets(1), 2: _make_prepare_subsets(2)}


def _make_gn_update(order: int):
    """The Gauss-Newton step of one order, ``dq = ratio (H^-1 b - gm H^-1 c) - H^-1 a``, reading the packed
    H^-1 from ``refdata`` (not registers); K and the columns (:class:`RefdataColumns`) fixed at compile time."""
    kk = n_params(order)
    vecp = vec6 if order == 1 else vec12
    cols = refdata_columns(order)
    col_a = cols.hinv_a
    col_c = cols.hinv_c

    def gn_update(refdata: wp.array2d(dtype=float), n: int, b: Any, ratio: float, gmean: float):
        dq = vecp()
        col = int(0)
        for i in range(kk):
            for j in range(i, kk):
                h = refdata[n, col]
                dq[i] += h * b[j]
                if j != i:
                    dq[j] += h * b[i]
                col += 1
        for i in range(kk):
            dq[i] = ratio * (dq[i] - gmean * refdata[n, col_c + i]) - refdata[n, col_a + i]
        return dq

    gn_update.__name__ = gn_update.__qualname__ = f"gn_update{kk}"
    return wp.func(gn_update)


#: the Gauss-Newton step of the 1st / 2nd order (b: vec6 / vec12)
gn_update6 = _make_gn_update(1)
gn_update12 = _make_gn_update(2)


@wp.func
def gn_step_scale(sums: wp.vec3, npx: int, fnorm: float, flat_var: float):
    """(mean g', df/dg, zncc) from (sum g', sum g'^2, sum (f-fm) g').

    df/dg = 0 flags a warped subset without texture: its grey-level variance is at most
    ``flat_var`` (the reference's flat-subset threshold) or lost in float32 rounding.
    """
    gmean = sums[0] / float(npx)
    dg2 = sums[1] - sums[0] * gmean
    if not (dg2 > 1e-5 * sums[1]) or not (dg2 > float(npx) * flat_var):
        return gmean, 0.0, 0.0
    dg = wp.sqrt(dg2)
    return gmean, fnorm / dg, sums[2] / (fnorm * dg)


def _make_icgn_point(order: int):
    """The per-POI IC-GN body of one shape-function order: ``icgn_point(n, sub, cur, guess, max_iter, tol, out)``
    tracks POI ``n`` of ``sub`` into ``cur`` from ``guess[n]`` and writes row ``n`` of ``out``. The body of
    ``_icgn_1st``/``_icgn_2nd``, of the frames x POIs launch of :mod:`kernels.frames` and of the counted
    launch of :mod:`kernels.rg_device` (one body, so all give the same bits). The order's parts (the
    subset pass, the composition, K, the :class:`RefdataColumns`) are chosen at compile time."""
    kk = n_params(order)
    cols = refdata_columns(order)
    col_fmean = cols.fmean
    col_fnorm = cols.fnorm
    gn_update = gn_update6 if order == 1 else gn_update12

    def icgn_point(n: int, sub: SubsetTable, cur: CurrentCoefficients, guess: wp.array2d(dtype=float), max_iter: int,
                   tol: float, out: IcgnOutputs):
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
                    b, sums = subset_pass_1st(sub.fgrad, sub.width, cur.coef, cur.pitch, ctr[0], ctr[1], r, dl, 1.0 / s,
                                              p, fmean, goff)
                else:
                    b, sums = subset_pass_2nd(sub.fgrad, sub.width, cur.coef, cur.pitch, ctr[0], ctr[1], r, dl, 1.0 / s,
                                              p, fmean, goff)
                it += 1
                gmean, ratio, cc = gn_step_scale(sums, (2 * r + 1) * (2 * r + 1), fnorm, sub.flat_var)
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
                    if not wp.isfinite(pn):  # a degenerate update (see solve_transposed6): keep the last p
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

    icgn_point.__name__ = icgn_point.__qualname__ = f"icgn_point_{'1st' if order == 1 else '2nd'}"
    return wp.func(icgn_point)


#: the per-POI IC-GN bodies of the 1st and 2nd order (:func:`_make_icgn_point`)
icgn_point_1st = _make_icgn_point(1)
icgn_point_2nd = _make_icgn_point(2)


@wp.kernel(launch_bounds=cuda_launch_bounds("_icgn_1st"))
def _icgn_1st(offset: int, sub: SubsetTable, cur: CurrentCoefficients, guess: wp.array2d(dtype=float), max_iter: int,
              tol: float, out: IcgnOutputs):
    icgn_point_1st(wp.tid() + offset, sub, cur, guess, max_iter, tol, out)


@wp.kernel(launch_bounds=cuda_launch_bounds("_icgn_2nd"))
def _icgn_2nd(offset: int, sub: SubsetTable, cur: CurrentCoefficients, guess: wp.array2d(dtype=float), max_iter: int,
              tol: float, out: IcgnOutputs):
    icgn_point_2nd(wp.tid() + offset, sub, cur, guess, max_iter, tol, out)


# ----------------------------------------------------------------------------------------------
# launchers
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReferenceImage:
    """Reference-image quantities computed once per reference (:func:`prepare_reference`).

    Attributes
    ----------
    fgrad : wp.array of wp.vec3, shape (H*W,)
        ``(f, df/dx, df/dy)`` at every pixel, row-major (index ``y*W + x``); the gradients are
        those of the cubic B-spline interpolant (grey levels per pixel).
    shape : (H, W)
    grey_range : float
        ``max(f) - min(f)``, used for the default flat-subset threshold.
    device : str
    """

    fgrad: wp.array
    shape: tuple[int, int]
    grey_range: float
    device: str


@dataclass(frozen=True)
class ReferenceSubsets:
    """Per-POI reference-side IC-GN quantities (:func:`prepare_subsets`), reused for every current image.

    Attributes
    ----------
    reference : ReferenceImage
    points : np.ndarray float64 (N, 2)
        POIs ``(x, y)`` in reference pixels.
    subset : int
        Odd subset size S (the subset is S x S pixels).
    order : int
        1 or 2.
    centres : wp.array of wp.vec2i (N,)   integer subset centres ``(round(x), round(y))``.
    deltas : wp.array of wp.vec2 (N,)     ``centre - point`` (px, in [-0.5, 0.5]).
    refdata : wp.array2d float32 (N, :func:`refdata_width`)   packed ``H^-1`` and friends.
    status : wp.array int32 (N,)          ``CONVERGED`` (= ready) or why the POI cannot be tracked
                                          (``OUT_OF_BOUNDS``, ``FLAT_SUBSET``, ``SINGULAR_HESSIAN``).
    flat_std : float                      grey-level std of a flat subset (also applied to the
                                          warped subsets: DIVERGED when their texture vanishes).
    mask : kernels.icgn_masked.SubsetMask or None
        The per-POI pixel masks (:func:`kernels.icgn_masked.prepare_subsets_masked`): IC-GN of these
        subsets runs over their kept pixels only (the launchers of :data:`MASKED_PATH`); None: every
        pixel (this module's kernels).
    """

    reference: ReferenceImage
    points: np.ndarray
    subset: int
    order: int
    centres: wp.array
    deltas: wp.array
    refdata: wp.array
    status: wp.array
    flat_std: float = 0.0
    mask: Any = None

    @property
    def device(self) -> str:
        return self.reference.device

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @cached_property
    def table(self) -> SubsetTable:
        """These subsets as the :class:`SubsetTable` the kernels read (built once per object)."""
        return subset_table(self)


#: the coefficient layouts IC-GN reads (``prepare_current(..., layout=)``, ``icgn(..., layout=)``):
#: ``"rows4"`` a ``wp.vec4`` per padded pixel holding 4 consecutive coefficients of its row (one
#: vector load per stencil row, 4x the memory, an expansion pass per image); ``"plain"`` the padded
#: coefficients read in place through :func:`kernels.interp.rows4_view` (the same kernel; on sm_90
#: both compile to 4 scalar loads per stencil row). Both give the same bits.
LAYOUTS = ("rows4", "plain")

#: default layout of prepare_current per device kind: "rows4" on both (icgn_batch and the tiled prototype
#: read only it; kernels.frames.FrameTracker has its own, FRAME_LAYOUT: "plain" on the CPU); on CUDA it is kept until ``bench/gpu.py`` (kernel section, ``layout``) has
#: measured both on a GPU; on the CPU both run in the same time (docs/dic2d.md, "Kernels that fit
#: the GPU": the same binary) and "plain" saves the expansion pass
DEFAULT_LAYOUT = {"cpu": "rows4", "cuda": "rows4"}


def default_layout(device) -> str:
    """The coefficient layout used when none is given, for ``device`` (``DEFAULT_LAYOUT``)."""
    device = resolve_device(device)
    return DEFAULT_LAYOUT["cpu" if device == "cpu" else "cuda"]


def check_layout(layout, device=None) -> str:
    """``layout`` as one of :data:`LAYOUTS` (``None``: :func:`default_layout` of ``device``)."""
    if layout is None:
        return default_layout(device)
    if not isinstance(layout, str) or layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS} (or None for the device's default), got {layout!r}")
    return layout


@dataclass(frozen=True)
class CurrentImage:
    """A current (deformed) image prepared for IC-GN (:func:`prepare_current`), once per image.

    Attributes
    ----------
    rows4 : wp.array of wp.vec4, shape ((H + 4) * (W + 4),), or None
        Cubic B-spline coefficients with a 2-pixel mirrored border, row-expanded
        (:func:`kernels.interp.expand_rows4`); None when prepared with ``layout="plain"``.
    shape : (H, W)
    device : str
    coef : wp.array2d float32 (H + 4, W + 4) or None
        The padded coefficients owned by this image (reused, like ``rows4``, by
        :func:`prepare_current` with ``out=``); None when the caller's coefficients were used.
    plain : wp.array of wp.vec4 or None
        The padded coefficients read in place (:func:`kernels.interp.rows4_view`: entry ``k`` is
        ``flat[k-1 : k+3]``, a 4-byte stride, no copy): what ``layout="plain"`` reads; set by
        :func:`prepare_current` for both layouts.
    """

    rows4: wp.array | None
    shape: tuple[int, int]
    device: str
    coef: wp.array | None = None
    plain: wp.array | None = None

    @property
    def pitch(self) -> int:
        return self.shape[1] + 4

    @property
    def layout(self) -> str:
        """``"rows4"`` when the row-expanded coefficients were built, else ``"plain"``."""
        return "rows4" if self.rows4 is not None else "plain"

    def coefficients(self, layout: str | None = None) -> CurrentCoefficients:
        """The coefficients of ``layout`` (default :attr:`layout`) as the :class:`CurrentCoefficients` the
        kernels read (built once per object and layout)."""
        layout = self.layout if layout is None else layout
        cache = self.__dict__.setdefault("_coefficients", {})
        if layout not in cache:
            coef = self.plain if layout == "plain" else self.rows4
            if coef is None:
                raise ValueError(f'this CurrentImage holds no "{layout}" coefficients')
            cache[layout] = struct_of(CurrentCoefficients, coef=coef, pitch=self.pitch)
        return cache[layout]


@dataclass
class IcgnResult:
    """Per-POI IC-GN output, on the device (call :meth:`numpy` for host arrays).

    ``params`` (N, 6|12) float32 in PARAMS_1ST/PARAMS_2ND order; ``zncc`` (N,) float32 (NaN where
    not computed); ``iterations`` (N,) int32; ``status`` (N,) int32 (:class:`Status`).
    """

    params: wp.array
    zncc: wp.array
    iterations: wp.array
    status: wp.array

    @property
    def outputs(self) -> IcgnOutputs:
        """These arrays as the :class:`IcgnOutputs` the kernels write (built when the arrays change)."""
        arrays = (self.params, self.zncc, self.iterations, self.status)
        cached = self.__dict__.get("_outputs")
        if cached is None or any(a is not b for a, b in zip(cached[0], arrays)):
            cached = (arrays, icgn_outputs(*arrays))
            self.__dict__["_outputs"] = cached
        return cached[1]

    def numpy(self) -> dict[str, np.ndarray]:
        """Owned host copies (on every device: a later call reusing these buffers leaves them unchanged)."""
        return {
            "params": host_copy(self.params),
            "zncc": host_copy(self.zncc),
            "iterations": host_copy(self.iterations),
            "status": host_copy(self.status),
        }


def check_subset_order(subset, order) -> tuple[int, int]:
    """Validate the subset size (odd int >= 3) and the shape-function order (1 or 2)."""
    subset = odd_int(subset, "subset", detail=" (e.g. 21)")
    if isinstance(order, bool) or order not in (1, 2):
        raise ValueError(f"order must be 1 (affine, 6 parameters) or 2 (quadratic, 12 parameters), got {order!r}")
    return int(subset), int(order)


def prepare_reference(image, device=None, window=None) -> ReferenceImage:
    """Precompute the reference image's values and B-spline gradients (once per reference).

    Parameters
    ----------
    image : array-like (H, W) grey image (any real dtype; grey levels kept on their scale), H, W >= 4.
    device : None or str
    window : (x0, y0, x1, y1) int, optional
        Compute ``fgrad`` at the pixels ``x0 <= x <= x1``, ``y0 <= y <= y1`` only (clipped to the image), zero
        elsewhere: for subsets known to lie inside it (:func:`subsets_window`); the values there are the same bits.
    """
    device = resolve_device(device)
    if window is not None:
        try:
            x0, y0, x1, y1 = (int(v) for v in window)
            if any(int(v) != v for v in window):
                raise TypeError
        except (TypeError, ValueError):
            raise ValueError(f"window must be 4 integers (x0, y0, x1, y1) px, got {window!r}") from None
    arr = as_float32_image(image, "reference")
    coef = bspline_coefficients(arr, device=device)
    h, w = arr.shape
    img_wp = wp.array(arr, dtype=wp.float32, device=device)
    if window is None:
        fgrad = wp.empty(h * w, dtype=wp.vec3, device=device)
        launch_1d(_reference_gradients, h * w, [0, img_wp, coef.flat, coef.pitch, w, fgrad], device, offset_index=0,
                  min_chunk=1 << 15)
    else:
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w - 1), min(y1, h - 1)
        fgrad = wp.zeros(h * w, dtype=wp.vec3, device=device)
        if x1 >= x0 and y1 >= y0:
            ww = x1 - x0 + 1
            launch_1d(_reference_gradients_window, ww * (y1 - y0 + 1),
                      [0, img_wp, coef.flat, coef.pitch, w, x0, y0, ww, fgrad], device, offset_index=0,
                      min_chunk=1 << 15)
    return ReferenceImage(fgrad, (h, w), float(arr.max() - arr.min()), device)


def subsets_window(points, subset: int, active=None) -> tuple[int, int, int, int] | None:
    """``(x0, y0, x1, y1)``: the pixels the subsets of the (``active``) POIs ``points`` (N, 2) px read in the reference
    (their integer centres ``round(x)``, ``round(y)`` +- ``subset // 2``); None when there is none."""
    pts = as_points(points, finite=False, allow_empty=True)
    r = odd_int(subset, "subset", detail=" (e.g. 21)") // 2
    if active is not None:
        act = np.asarray(active)
        if act.dtype != bool or act.shape != (pts.shape[0],):
            raise ValueError(f"active must be an ({pts.shape[0]},) bool array (one per POI), got {act.dtype} {act.shape}")
        pts = pts[act]
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if pts.shape[0] == 0:
        return None
    # the kernels' centres are rounded half away from zero; one pixel more either way covers any rounding
    lo = np.floor(pts.min(axis=0)).astype(int) - r - 1
    hi = np.ceil(pts.max(axis=0)).astype(int) + r + 1
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


def prepare_current(image, device=None, out: CurrentImage | None = None, layout: str | None = None) -> CurrentImage:
    """B-spline coefficients of a current image, in the layout IC-GN reads (once per image).

    Parameters
    ----------
    image : array-like (H, W) grey image, a float32 ``wp.array2d`` already on ``device`` (used in
        place, no host copy), or a :class:`kernels.interp.PaddedImage` of kind ``"bspline"`` from
        :func:`kernels.interp.bspline_coefficients`.
    device : None or str
    out : CurrentImage, optional
        A previous result of the same shape and device whose buffers (coefficients and their
        row-expanded layout) are reused: on the CPU a NumPy image then allocates no Warp memory.
    layout : None, "rows4" or "plain"
        ``"plain"`` skips the row expansion (no 4x buffer, no expansion pass; IC-GN then needs
        ``layout="plain"``); ``None``: :func:`default_layout` of the device.
    """
    if out is not None and not isinstance(out, CurrentImage):
        raise ValueError("out must be a CurrentImage of the same shape and device")
    if layout is not None:
        layout = check_layout(layout)

    if isinstance(image, PaddedImage):
        if image.kind != "bspline":
            raise ValueError(f"current must hold B-spline coefficients, got a PaddedImage of kind {image.kind!r}")
        coef = image
        device = coef.device if device is None else resolve_device(device)
        if device != coef.device:
            raise ValueError(f"coefficients are on {coef.device} but device={device!r}")
    elif isinstance(image, wp.array):
        # already on the device (e.g. wp.from_torch of a tensor): no host round trip
        device = resolve_device(device)
        coef = bspline_coefficients(image, device=device, out=_reusable(out, device, image.shape))
    else:
        device = resolve_device(device)
        arr = as_float32_image(image, "current")
        coef = bspline_coefficients(arr, device=device, out=_reusable(out, device, arr.shape))
    layout = check_layout(layout, device)
    buf = None
    if out is not None:
        if out.shape != coef.shape or out.device != device:
            raise ValueError("out must be a CurrentImage of the same shape and device")
        buf = out.rows4
    own = None if isinstance(image, PaddedImage) else coef.data  # never reuse (overwrite) the caller's coefficients
    rows4 = expand_rows4(coef, out=buf) if layout == "rows4" else None
    return CurrentImage(rows4, coef.shape, device, own, rows4_view(coef))


def _reusable(out: CurrentImage | None, device: str, shape) -> wp.array | None:
    """``out``'s coefficient buffer when it fits an image of ``shape`` on ``device`` (None: allocate one)."""
    coef = None if out is None else out.coef
    if coef is None or out.device != device or tuple(coef.shape) != (int(shape[0]) + 4, int(shape[1]) + 4):
        return None
    return coef


def prepare_subsets(reference: ReferenceImage, points, subset: int = 21, order: int = 1,
                    flat_std: float | None = None, active=None) -> ReferenceSubsets:
    """Precompute the per-POI reference quantities of IC-GN (Pan et al. 2013, doi:10.1007/s11340-012-9640-x).

    Parameters
    ----------
    reference : ReferenceImage from :func:`prepare_reference`.
    points : array-like (N, 2)
        POIs ``(x, y)`` in reference pixels, integer or sub-pixel.
    subset : odd int >= 3
        Subset size S (S x S pixels).
    order : 1 or 2
    flat_std : float, optional
        A subset whose grey-level standard deviation is <= this is ``FLAT_SUBSET``.
        Default: 1e-3 of the reference image's grey-level range.
    active : (N,) bool, optional
        Prepare these POIs only; the others get status ``NOT_COMPUTED`` (never tracked) and zero tables. The
        prepared rows are bit for bit those of preparing every POI (each POI's row depends on it alone). E.g.
        a grid over the whole image of which a region is correlated.

    Returns
    -------
    ReferenceSubsets
        ``status`` is ``OUT_OF_BOUNDS`` where the subset leaves the image, ``FLAT_SUBSET``,
        ``SINGULAR_HESSIAN``, else ``CONVERGED`` (ready to track). Subsets correlated on some of their
        pixels only (holes, free edges): :func:`kernels.icgn_masked.prepare_subsets_masked`.
    """
    if not isinstance(reference, ReferenceImage):
        raise ValueError(f"reference must be a ReferenceImage from prepare_reference(), got {type(reference).__name__}")
    subset, order = check_subset_order(subset, order)
    pts = as_points(points)
    if flat_std is None:
        flat_std = 1e-3 * reference.grey_range
    if not np.isfinite(flat_std) or flat_std < 0:
        raise ValueError(f"flat_std must be a finite non-negative grey level, got {flat_std!r}")
    device = reference.device
    n = pts.shape[0]
    if active is not None:
        act = np.asarray(active)
        if act.dtype != bool or act.shape != (n,):
            raise ValueError(f"active must be an ({n},) bool array (the POIs to prepare), got {act.dtype} {act.shape}")
        if not act.all():
            return _prepare_active(reference, pts, act, subset, order, float(flat_std))
    centres = wp.empty(n, dtype=wp.vec2i, device=device)
    deltas = wp.empty(n, dtype=wp.vec2, device=device)
    refdata = wp.zeros((n, refdata_width(order)), dtype=wp.float32, device=device)
    status = wp.empty(n, dtype=wp.int32, device=device)
    pts_wp = wp.array(pts, dtype=wp.vec2d, device=device)
    subsets = ReferenceSubsets(reference, pts, subset, order, centres, deltas, refdata, status, float(flat_std))
    launch_1d(_prepare_subsets[order], n, [0, pts_wp, subsets.table], device, offset_index=0, min_chunk=64)
    return subsets


def _prepare_active(reference: ReferenceImage, pts: np.ndarray, active: np.ndarray, subset: int, order: int,
                    flat_std: float) -> ReferenceSubsets:
    """:func:`prepare_subsets` of the ``active`` POIs, scattered into tables of every POI (the others NOT_COMPUTED)."""
    device = reference.device
    n = pts.shape[0]
    idx = np.flatnonzero(active)
    full = ReferenceSubsets(reference, pts, subset, order, wp.zeros(n, dtype=wp.vec2i, device=device),
                            wp.zeros(n, dtype=wp.vec2, device=device),
                            wp.zeros((n, refdata_width(order)), dtype=wp.float32, device=device),
                            wp.full(n, int(ST_NOT_COMPUTED), dtype=wp.int32, device=device), flat_std)
    if idx.size:
        part = prepare_subsets(reference, pts[idx], subset=subset, order=order, flat_std=flat_std)
        launch_1d(_scatter_subsets, int(idx.size), [0, wp.array(idx.astype(np.int32), dtype=wp.int32, device=device),
                                                    part.table, full.table], device, offset_index=0, min_chunk=1024)
    return full


def _as_guess(guess, n: int, k: int, device: str) -> wp.array:
    if guess is None:
        return wp.zeros((n, k), dtype=wp.float32, device=device)
    if isinstance(guess, wp.array):
        if guess.shape != (n, k) or guess.dtype != wp.float32:
            raise ValueError(f"guess must be float32 of shape {(n, k)}, got {guess.shape} {guess.dtype}")
        if str(guess.device) != device:
            raise ValueError(f"guess is on {guess.device} but the subsets are on {device}")
        return guess
    g = np.asarray(guess, dtype=np.float64)
    if g.shape != (n, k):
        raise ValueError(f"guess must have shape {(n, k)} (one row of parameters per POI), got {g.shape}")
    if not np.all(np.isfinite(g)):
        raise ValueError("guess contains NaN or infinite values; give a finite guess or mask those POIs out")
    return wp.array(g.astype(np.float32), dtype=wp.float32, device=device)


#: the largest IC-GN iteration limit accepted (``max_iter``, ``--max-iter``): far more than any
#: converging POI needs (typically 3-30), and small enough for the kernel's 32-bit counter
MAX_ITER = 10000


def check_max_iter(max_iter) -> int:
    """``max_iter`` as an ``int`` in ``[1, MAX_ITER]``, else ``ValueError`` naming the bound."""
    return positive_int(max_iter, "max_iter", maximum=MAX_ITER, detail=" (IC-GN iterations per point)")


def icgn(subsets: ReferenceSubsets, current, guess=None, max_iter: int = 30, tol: float = 1e-3,
         out: IcgnResult | None = None, layout: str | None = None) -> IcgnResult:
    """Track every POI of ``subsets`` into a current image with IC-GN / ZNSSD.

    Parameters
    ----------
    subsets : ReferenceSubsets from :func:`prepare_subsets` (fixes device, subset size and order).
    current : CurrentImage from :func:`prepare_current` (prepare it once per image), or a grey
        image array of the reference's shape.
    guess : array-like (N, 6|12), optional
        Initial parameters (PARAMS_1ST/PARAMS_2ND order, physical units); default zeros. IC-GN
        converges from guesses within a few pixels; use :mod:`kernels.search` for larger motion.
    max_iter : int in [1, MAX_ITER]
        Iteration limit per POI (IC-GN converges in a few iterations from a good guess; the
        bound keeps the kernel's 32-bit counter from wrapping).
    tol : float > 0
        Convergence threshold on the scaled update norm (px, see the module doc).
    out : IcgnResult, optional
        Preallocated outputs (reused across frames).
    layout : None, "rows4" or "plain"
        The coefficient layout the kernel reads (:data:`LAYOUTS`; the same bits either way).
        ``None``: ``current``'s own layout when it is a :class:`CurrentImage`, else
        :func:`default_layout` of the device. ``"rows4"`` needs a current prepared with it.

    Returns
    -------
    IcgnResult (device arrays).
    """
    if not isinstance(subsets, ReferenceSubsets):
        raise ValueError(f"subsets must be a ReferenceSubsets from prepare_subsets(), got {type(subsets).__name__}")
    device = subsets.device
    h, w = subsets.reference.shape
    if layout is not None:
        layout = check_layout(layout)
    if isinstance(current, CurrentImage):
        if current.device != device:
            raise ValueError(f"current is on {current.device} but the subsets are on {device}")
        cur = current
        layout = cur.layout if layout is None else layout
        if layout == "rows4" and cur.rows4 is None:
            raise ValueError('layout="rows4" needs a current prepared with prepare_current(..., layout="rows4")')
        if layout == "plain" and cur.plain is None:
            raise ValueError('layout="plain" needs a current from prepare_current() (its plain coefficients)')
    else:
        layout = check_layout(layout, device)
        cur = prepare_current(current, device=device, layout=layout)
    if cur.shape != (h, w):
        raise ValueError(f"current image has shape {cur.shape} but the reference has shape {(h, w)}")
    max_iter = check_max_iter(max_iter)
    tol = positive_float(tol, "tol", detail=" of pixels")
    n = subsets.n_points
    k = n_params(subsets.order)
    g = _as_guess(guess, n, k, device)
    if out is None:
        out = IcgnResult(
            wp.empty((n, k), dtype=wp.float32, device=device),
            wp.empty(n, dtype=wp.float32, device=device),
            wp.empty(n, dtype=wp.int32, device=device),
            wp.empty(n, dtype=wp.int32, device=device),
        )
    elif out.params.shape != (n, k) or out.zncc.shape != (n,):
        raise ValueError(f"out was allocated for {out.params.shape}, expected params of shape {(n, k)}")
    # the same kernel for both layouts (hence the same bits): only the array it reads differs
    if subsets.mask is not None:  # per-POI pixel masks: the kernels of kernels.icgn_masked
        MASKED_PATH["icgn"](subsets.order, n, subsets.table, subsets.mask, cur.coefficients(layout), g, max_iter, tol,
                            out.outputs, device)
        return out
    kernel = _icgn_1st if subsets.order == 1 else _icgn_2nd
    launch_1d(kernel, n, [0, subsets.table, cur.coefficients(layout), g, int(max_iter), float(tol), out.outputs],
              device, offset_index=0, min_chunk=64)
    return out


# ----------------------------------------------------------------------------------------------
# indexed IC-GN: a subset of the prepared POIs, without preparing them again
# ----------------------------------------------------------------------------------------------


@wp.func
def copy_subset_row(src: SubsetTable, n: int, dst: SubsetTable, t: int):
    """Row ``t`` of ``dst``'s per-POI tables := row ``n`` of ``src``'s (centre, delta, refdata, status)."""
    dst.centres[t] = src.centres[n]
    dst.deltas[t] = src.deltas[n]
    dst.status[t] = src.status[n]
    for c in range(src.refdata.shape[1]):
        dst.refdata[t, c] = src.refdata[n, c]


@wp.kernel
def _gather_subsets(offset: int, idx: wp.array(dtype=wp.int32), src: SubsetTable, dst: SubsetTable):
    t = wp.tid() + offset
    copy_subset_row(src, idx[t], dst, t)


@wp.kernel
def _scatter_subsets(offset: int, idx: wp.array(dtype=wp.int32), src: SubsetTable, dst: SubsetTable):
    t = wp.tid() + offset
    copy_subset_row(src, t, dst, idx[t])


def subset_buffers(subsets: ReferenceSubsets, capacity: int | None = None) -> ReferenceSubsets:
    """Uninitialised per-POI buffers of ``capacity`` rows (default N) shaped like ``subsets``: the
    destination of :func:`gather_subsets` (allocate once, gather into them per batch)."""
    if not isinstance(subsets, ReferenceSubsets):
        raise ValueError(f"subsets must be a ReferenceSubsets from prepare_subsets(), got {type(subsets).__name__}")
    m = subsets.n_points if capacity is None else positive_int(capacity, "capacity")
    dev = subsets.device
    mask = None if subsets.mask is None else MASKED_PATH["buffers"](subsets.mask, m, subsets.subset, dev)
    return ReferenceSubsets(
        subsets.reference, np.full((m, 2), np.nan), subsets.subset, subsets.order,
        wp.empty(m, dtype=wp.vec2i, device=dev), wp.empty(m, dtype=wp.vec2, device=dev),
        wp.empty((m, refdata_width(subsets.order)), dtype=wp.float32, device=dev), wp.empty(m, dtype=wp.int32, device=dev),
        subsets.flat_std, mask,
    )


def subset_rows(subsets: ReferenceSubsets, count: int, points=None) -> ReferenceSubsets:
    """The first ``count`` rows of ``subsets`` as a ReferenceSubsets of views (no device allocation);
    ``points`` (count, 2) their POIs when known on the host, else the buffer's rows (NaN for a gather
    made on the device)."""
    pts = subsets.points[:count] if points is None else np.asarray(points, dtype=np.float64).reshape(count, 2)
    mask = None if subsets.mask is None else MASKED_PATH["rows"](subsets.mask, count)
    return ReferenceSubsets(subsets.reference, pts, subsets.subset, subsets.order, subsets.centres[:count],
                            subsets.deltas[:count], subsets.refdata[:count], subsets.status[:count], subsets.flat_std,
                            mask)


def gather_subsets(subsets: ReferenceSubsets, idx: wp.array, count: int, out: ReferenceSubsets,
                   points=None) -> ReferenceSubsets:
    """The prepared POIs ``idx[:count]`` of ``subsets``, copied into the first ``count`` rows of ``out``
    (:func:`subset_buffers`); returns those rows (:func:`subset_rows`). No subset is prepared again:
    IC-GN of the result (:func:`icgn`) gives each POI bitwise the result it gets in ``subsets``.

    ``idx``: int32 Warp array on the subsets' device, indices in ``[0, N)`` (not checked on the device:
    check host indices before the upload, e.g. :meth:`dic.correlation.Correlator.check_indices`).
    """
    if not isinstance(subsets, ReferenceSubsets) or not isinstance(out, ReferenceSubsets):
        raise ValueError("subsets and out must be ReferenceSubsets (prepare_subsets(), subset_buffers())")
    if out.order != subsets.order or out.subset != subsets.subset or out.device != subsets.device:
        raise ValueError("out must be subset_buffers() of the same subsets (order, subset size, device)")
    if not isinstance(idx, wp.array) or idx.dtype != wp.int32 or idx.ndim != 1 or str(idx.device) != subsets.device:
        raise ValueError(f"idx must be a 1-D int32 Warp array on {subsets.device}")
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or not 0 <= count <= min(idx.shape[0],
                                                                                                   out.n_points):
        raise ValueError(f"count must be an int in [0, {min(idx.shape[0], out.n_points)}], got {count!r}")
    if (subsets.mask is None) != (out.mask is None):
        raise ValueError("out must be subset_buffers() of the same subsets (both masked or both not)")
    launch_1d(_gather_subsets, int(count), [0, idx, subsets.table, out.table], subsets.device, offset_index=0,
              min_chunk=1024)
    if subsets.mask is not None:
        MASKED_PATH["gather"](int(count), idx, subsets.mask, out.mask, subsets.device)
    return subset_rows(out, int(count), points)
