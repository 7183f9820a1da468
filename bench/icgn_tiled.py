"""Prototype: 1st-order IC-GN with one block of lanes per POI (Warp tiles), for the GPU.

:func:`kernels.icgn.icgn` runs one thread per POI: each thread walks its whole subset serially,
which needs many POIs to fill a GPU and lets a warp wait for its slowest POI. Here a block of
:data:`TILE_LANES` lanes (one warp) shares a POI: lane ``l`` visits the subset pixels ``l, l + L,
l + 2L, ...`` (row-major), and the per-iteration sums (``sum J^T g``, ``sum g``, ``sum g^2``,
``sum (f - fm) g``) are reduced across the lanes with ``wp.tile_sum``; every lane then computes the
same Gauss-Newton update (the reference side, ``H^-1`` and friends, comes from
:func:`kernels.icgn.prepare_subsets` unchanged). The criterion, update, statuses and convergence
test are those of ``kernels.icgn._icgn_1st``; only the order of the float32 sums differs, so the
results agree to float32 rounding (tests/kernels/test_kernel_variants.py).

Status: a prototype, not used by the engine, so it lives in ``bench/`` (not installed); ``bench.gpu``
times it and ``tests/kernels/test_kernel_variants.py`` checks it. It is correct on the CPU (where Warp runs the lanes
of a block one after another when ``wp.config.enable_cpu_blocks`` is set), and its sm_90 resources
are recorded in docs/dic2d.md ("GPU"); whether it beats one thread per POI must be measured on a
GPU (``bench/gpu.sh``).
"""
from __future__ import annotations

import warp as wp

from kernels._common import (
    ICGN_MODULE_OPTIONS,
    ST_CONVERGED,
    ST_DIVERGED,
    ST_MAX_ITERATIONS,
    ST_OUT_OF_BOUNDS,
)
from kernels._device import resolve_device
from kernels.checks import positive_float
from kernels.icgn import (
    REFDATA_1ST,
    CurrentCoefficients,
    CurrentImage,
    IcgnOutputs,
    IcgnResult,
    ReferenceSubsets,
    SubsetTable,
    _as_guess,
    check_max_iter,
    compose_1st,
    gn_step_scale,
    gn_update6,
    vec6,
    warped_inside,
    warped_value,
)

#: lanes per POI (one warp on CUDA); also the module's CUDA block size and the kernel's launch bounds
TILE_LANES = 32

wp.set_module_options({**ICGN_MODULE_OPTIONS, "block_dim": TILE_LANES})

COL_FMEAN = wp.constant(REFDATA_1ST.fmean)
COL_FNORM = wp.constant(REFDATA_1ST.fnorm)


@wp.func
def subset_pass_1st_lanes(
    fgrad: wp.array(dtype=wp.vec3), width: int, coef: wp.array(dtype=wp.vec4), pitch: int,
    cx0: int, cy0: int, r: int, dl: wp.vec2, inv_s: float, p: vec6, fmean: float, goff: float, lane: int,
):
    """This lane's share of :func:`kernels.icgn.subset_pass_1st` (pixels lane, lane + L, ..., L the block size)."""
    b = vec6()
    sg = float(0.0)
    sgg = float(0.0)
    sfg = float(0.0)
    size = 2 * r + 1
    q = lane
    while q < size * size:
        jj = q // size
        i = q - jj * size - r
        j = jj - r
        dx = float(i) + dl[0]
        dy = float(j) + dl[1]
        g = warped_value(coef, pitch, cx0 + i, cy0 + j, p[0] + p[1] * dx + p[2] * dy,
                         p[3] + p[4] * dx + p[5] * dy) - goff
        fg = fgrad[(cy0 + j) * width + cx0 + i]
        sg += g
        sgg += g * g
        sfg += (fg[0] - fmean) * g
        gx = fg[1] * g
        gy = fg[2] * g
        xi = dx * inv_s
        eta = dy * inv_s
        b += vec6(gx, gx * xi, gx * eta, gy, gy * xi, gy * eta)
        q += wp.block_dim()
    return b, wp.vec3(sg, sgg, sfg)


@wp.kernel(launch_bounds=TILE_LANES)
def _icgn_1st_tiled(sub: SubsetTable, cur: CurrentCoefficients, guess: wp.array2d(dtype=float), max_iter: int,
                    tol: float, out: IcgnOutputs):
    n, lane = wp.tid()
    p = vec6(guess[n, 0], guess[n, 1], guess[n, 2], guess[n, 3], guess[n, 4], guess[n, 5])
    st = sub.status[n]
    cc = float(wp.nan)
    it = int(0)
    r = sub.r
    width = sub.width
    if st == ST_CONVERGED:  # uniform across the block: every lane of a POI takes the same path
        fmean = sub.refdata[n, COL_FMEAN]
        fnorm = sub.refdata[n, COL_FNORM]
        goff = fmean
        ctr = sub.centres[n]
        dl = sub.deltas[n]
        s = float(r)
        st = ST_MAX_ITERATIONS
        while it < max_iter:
            if warped_inside(ctr[0], ctr[1], r, dl, width, sub.height, p[0], p[1], p[2], 0.0, 0.0, 0.0,
                             p[3], p[4], p[5], 0.0, 0.0, 0.0) == 0:
                st = ST_OUT_OF_BOUNDS
                break
            bl, sl = subset_pass_1st_lanes(sub.fgrad, width, cur.coef, cur.pitch, ctr[0], ctr[1], r, dl, 1.0 / s, p, fmean,
                                           goff, lane)
            bt = wp.tile_sum(wp.tile(bl, preserve_type=True))
            stt = wp.tile_sum(wp.tile(sl, preserve_type=True))
            b = bt[0]
            sums = stt[0]
            it += 1
            gmean, ratio, cc = gn_step_scale(sums, (2 * r + 1) * (2 * r + 1), fnorm, sub.flat_var)
            goff = goff + gmean
            dq = gn_update6(sub.refdata, n, b, ratio, gmean)
            norm = wp.length(dq)
            if ratio == 0.0 or not (norm <= float(2 * r + 1)):
                st = ST_DIVERGED
                break
            p = compose_1st(p, vec6(dq[0], dq[1] / s, dq[2] / s, dq[3], dq[4] / s, dq[5] / s))
            if norm < tol:
                st = ST_CONVERGED
                break
    if lane == 0:
        for i in range(6):
            out.params[n, i] = p[i]
        out.zncc[n] = cc
        out.iterations[n] = it
        out.status[n] = st


def icgn_tiled(subsets: ReferenceSubsets, current: CurrentImage, guess=None, max_iter: int = 30,
               tol: float = 1e-3, out: IcgnResult | None = None) -> IcgnResult:
    """1st-order IC-GN with :data:`TILE_LANES` lanes per POI (prototype; see the module doc).

    Parameters as :func:`kernels.icgn.icgn` (``current`` prepared with
    :func:`kernels.icgn.prepare_current`; ``guess`` array-like or a float32 ``wp.array`` (N, 6);
    ``out`` preallocated outputs); ``subsets`` must be of order 1.
    """
    if not isinstance(subsets, ReferenceSubsets):
        raise ValueError(f"subsets must be a ReferenceSubsets from prepare_subsets(), got {type(subsets).__name__}")
    if subsets.order != 1:
        raise ValueError(f"icgn_tiled is 1st-order only, got subsets of order {subsets.order}")
    if not isinstance(current, CurrentImage) or current.device != subsets.device:
        raise ValueError("current must be a CurrentImage (prepare_current) on the subsets' device")
    if current.shape != subsets.reference.shape:
        raise ValueError(f"current image has shape {current.shape} but the reference has {subsets.reference.shape}")
    if current.rows4 is None:
        raise ValueError('current was prepared with layout="plain"; the tiled prototype reads "rows4"')
    max_iter = check_max_iter(max_iter)
    tol = positive_float(tol, "tol", detail=" of pixels")
    device = resolve_device(subsets.device)
    n = subsets.n_points
    g = _as_guess(guess, n, 6, device)
    if out is None:
        out = IcgnResult(wp.empty((n, 6), dtype=wp.float32, device=device),
                         wp.empty(n, dtype=wp.float32, device=device),
                         wp.empty(n, dtype=wp.int32, device=device), wp.empty(n, dtype=wp.int32, device=device))
    elif not isinstance(out, IcgnResult) or out.params.shape != (n, 6) or out.zncc.shape != (n,):
        raise ValueError(f"out must be an IcgnResult with params of shape {(n, 6)}")
    if n == 0:
        return out
    wp.launch_tiled(_icgn_1st_tiled, dim=[n],
                    inputs=[subsets.table, current.coefficients("rows4"), g, int(max_iter), float(tol), out.outputs],
                    block_dim=TILE_LANES, device=device)
    return out
