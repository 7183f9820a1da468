"""Boolean-model speckle: disks on a uniform cell grid, point coverage, and image rendering.

The speckle pattern is a Boolean model (Sur, Blaysat & Grédiac, "Rendering deformed speckle
images with a Boolean model", J. Math. Imaging Vis. 60, 2018, doi:10.1007/s10851-018-0834-x):
the union of disks whose centres come from a Poisson process. This module holds the device side:

* :class:`SpeckleModel` (a ``@wp.struct``): disk centres and radii sorted into a uniform grid of
  square cells, with per-cell ``start``/``count`` indices. Units are whatever the centres are in
  (pixels for synthetic DIC images, millimetres for textured surfaces in the virtual lab).
* ``@wp.func`` :func:`speckle_coverage` (1 inside any disk, else 0) and
  :func:`speckle_coverage_smooth` (anti-aliased coverage over a small box), callable from other
  modules' kernels (``from kernels.speckle import SpeckleModel, speckle_coverage``).
* :func:`render_speckle`: the rendered (pixel-integrated, Gaussian-blurred) coverage image of the
  pattern seen through an optional inverse displacement, and :func:`speckle_at_points`, the same
  quantity at arbitrary pixel centres.

Rendering (see docs/synth.md). A pixel centred at ``x`` records
``I(x) = ∫ K(y) C(X(x + y)) dy`` where ``C`` is the disk coverage in material coordinates,
``X(·)`` maps current image positions to material (reference) positions, and ``K`` is the pixel
box ``[-1/2, 1/2]²`` convolved with an isotropic Gaussian of standard deviation ``blur`` px (the
point-spread function acts in the image, as in a camera). The integral is a deterministic
midpoint quadrature: every pixel is split into ``s × s`` sub-cells; each sub-cell contributes its
anti-aliased coverage (a linear ramp of the signed distance to the disk boundary over the
sub-cell width ``1/s``) times the exact integral of ``K`` over the sub-cell. Because the quadrature
offsets are the same for every pixel, the rendered image is an exact sample of one continuous,
shift-covariant function: a rigid shift of the pattern produces exactly the shifted image, with
no Monte Carlo noise. Sub-cell values are shared between neighbouring pixels, so ``K`` is
applied as two separable decimating filters.

Conventions: images ``[row, col] = [y, x]``, pixel ``(0, 0)`` centred at ``(0, 0)``
(docs/conventions.md). Device arrays are float32. Positions in float32 carry a rounding error of
about ``|x| · 6e-8`` (1.2e-4 px at x = 2048).
"""
from __future__ import annotations

import math
import sys

import numpy as np
import warp as wp

from ._device import resolve_device
from ._launch import launch_1d
from .checks import as_points, positive_float, positive_int
from .interp import keys_weights

# forward-only kernels: no adjoints are ever needed here, and skipping them halves compilation
wp.set_module_options({"enable_backward": False})

# ---------------------------------------------------------------------------------------------
# the model


@wp.struct
class SpeckleModel:
    """Disks binned by centre into a uniform grid of square cells (any length unit).

    Disk ``k`` (``0 <= k < M``) has centre ``centres[k]`` and radius ``radii[k]``; disks are stored
    sorted by cell, and cell ``c = cy * nx + cx`` owns ``centres[cell_start[c] : cell_start[c] +
    cell_count[c]]``. Cell ``(cx, cy)`` covers ``origin + [cx, cx + 1) × [cy, cy + 1) * cell_size``.
    ``max_radius`` bounds every radius; queries look at the cells within ``max_radius`` (plus the
    anti-aliasing half-width) of the point, i.e. at most 2 × 2 cells when
    ``cell_size >= 2 * (max_radius + half-width)``. Points far from every disk, including points
    outside the grid, are uncovered.
    """

    centres: wp.array(dtype=wp.vec2)
    radii: wp.array(dtype=float)
    cell_start: wp.array(dtype=int)
    cell_count: wp.array(dtype=int)
    origin: wp.vec2
    cell_size: float
    nx: int
    ny: int
    max_radius: float


# ---------------------------------------------------------------------------------------------
# device functions


@wp.func
def speckle_coverage(model: SpeckleModel, p: wp.vec2) -> float:
    """Binary coverage of point ``p`` (same unit as the model): 1.0 inside any disk, else 0.0."""
    reach = model.max_radius
    inv = 1.0 / model.cell_size
    cx0 = wp.max(int(wp.floor((p[0] - reach - model.origin[0]) * inv)), 0)
    cx1 = wp.min(int(wp.floor((p[0] + reach - model.origin[0]) * inv)), model.nx - 1)
    cy0 = wp.max(int(wp.floor((p[1] - reach - model.origin[1]) * inv)), 0)
    cy1 = wp.min(int(wp.floor((p[1] + reach - model.origin[1]) * inv)), model.ny - 1)
    for cy in range(cy0, cy1 + 1):
        for cx in range(cx0, cx1 + 1):
            cell = cy * model.nx + cx
            start = model.cell_start[cell]
            for k in range(start, start + model.cell_count[cell]):
                d = p - model.centres[k]
                r = model.radii[k]
                if wp.dot(d, d) <= r * r:
                    return 1.0
    return 0.0


@wp.func
def speckle_coverage_smooth(model: SpeckleModel, p: wp.vec2, width: float) -> float:
    """Anti-aliased coverage of a box of side ``width`` centred on ``p`` (model units).

    Returns ``clamp(1/2 - d / width, 0, 1)`` where ``d`` is the signed distance from ``p`` to the
    nearest disk boundary (negative inside), i.e. the exact covered fraction of the box for a
    straight edge parallel to a side; 1 deep inside, 0 far outside. ``width <= 0`` gives the binary
    :func:`speckle_coverage`.
    """
    if width <= 0.0:
        return speckle_coverage(model, p)
    half = 0.5 * width
    reach = model.max_radius + half
    inv = 1.0 / model.cell_size
    cx0 = wp.max(int(wp.floor((p[0] - reach - model.origin[0]) * inv)), 0)
    cx1 = wp.min(int(wp.floor((p[0] + reach - model.origin[0]) * inv)), model.nx - 1)
    cy0 = wp.max(int(wp.floor((p[1] - reach - model.origin[1]) * inv)), 0)
    cy1 = wp.min(int(wp.floor((p[1] + reach - model.origin[1]) * inv)), model.ny - 1)
    best = float(half)  # signed distance to the nearest boundary, capped at +half
    for cy in range(cy0, cy1 + 1):
        for cx in range(cx0, cx1 + 1):
            cell = cy * model.nx + cx
            start = model.cell_start[cell]
            for k in range(start, start + model.cell_count[cell]):
                d = p - model.centres[k]
                r = model.radii[k]
                dd = wp.dot(d, d)
                if dd < (r + half) * (r + half):
                    s = wp.sqrt(dd) - r
                    if s <= -half:
                        return 1.0
                    best = wp.min(best, s)
    return wp.clamp(0.5 - best / width, 0.0, 1.0)


@wp.func
def _keys_sample2(fu: wp.array2d(dtype=float), fv: wp.array2d(dtype=float), fx: float, fy: float) -> wp.vec2:
    """Keys bicubic values of two same-shape fields ``[row, col]`` at grid position (fx, fy); taps clamped."""
    ix = int(wp.floor(fx))
    iy = int(wp.floor(fy))
    wx = keys_weights(fx - float(ix))
    wy = keys_weights(fy - float(iy))
    nrow = fu.shape[0]
    ncol = fu.shape[1]
    c0 = wp.clamp(ix - 1, 0, ncol - 1)
    c1 = wp.clamp(ix, 0, ncol - 1)
    c2 = wp.clamp(ix + 1, 0, ncol - 1)
    c3 = wp.clamp(ix + 2, 0, ncol - 1)
    acc = wp.vec2(0.0, 0.0)
    for j in range(4):
        row = wp.clamp(iy + j - 1, 0, nrow - 1)
        su = wx[0] * fu[row, c0] + wx[1] * fu[row, c1] + wx[2] * fu[row, c2] + wx[3] * fu[row, c3]
        sv = wx[0] * fv[row, c0] + wx[1] * fv[row, c1] + wx[2] * fv[row, c2] + wx[3] * fv[row, c3]
        acc += wy[j] * wp.vec2(su, sv)
    return acc


# ---------------------------------------------------------------------------------------------
# kernels


@wp.kernel
def _coverage_points_kernel(
    model: SpeckleModel,
    points: wp.array(dtype=wp.vec2),
    width: float,
    out: wp.array(dtype=float),
    offset: int,
):
    i = wp.tid() + offset
    out[i] = speckle_coverage_smooth(model, points[i], width)


_vec16 = wp.types.vector(length=16, dtype=float)
_vec64 = wp.types.vector(length=64, dtype=float)


@wp.func
def _map_point(
    q: wp.vec2,
    mode: int,
    shift: wp.vec2,
    field_u: wp.array2d(dtype=float),
    field_v: wp.array2d(dtype=float),
    field_origin: wp.vec2,
    field_step: float,
) -> wp.vec2:
    """Material point shown at image position q: mode 0 identity, 1 ``q - shift``, 2 ``q - w(q)``."""
    if mode == 1:
        return q - shift
    if mode == 2:
        fx = (q[0] - field_origin[0]) / field_step
        fy = (q[1] - field_origin[1]) / field_step
        return q - _keys_sample2(field_u, field_v, fx, fy)
    return q


@wp.kernel
def _fine_block_kernel(
    model: SpeckleModel,
    start: wp.vec2,
    step: float,
    nrows: int,
    ncols: int,
    nbx: int,
    mode: int,
    shift: wp.vec2,
    field_u: wp.array2d(dtype=float),
    field_v: wp.array2d(dtype=float),
    field_origin: wp.vec2,
    field_step: float,
    width: float,
    out: wp.array(dtype=float),
    out_stride: int,
    offset: int,
):
    # one 8x8 block of sub-cells: map them, gather the disks near the block once (up to 16),
    # then coverage = clamp(1/2 - min_disks(|p - c| - r) / width, 0, 1) per sub-cell
    b = wp.tid() + offset
    r0 = (b / nbx) * 8
    c0 = (b - (b / nbx) * nbx) * 8
    px = _vec64()
    py = _vec64()
    centre = wp.vec2(0.0, 0.0)
    for k in range(64):
        row = wp.min(r0 + k / 8, nrows - 1)
        col = wp.min(c0 + k - (k / 8) * 8, ncols - 1)
        x = _map_point(wp.vec2(start[0] + float(col) * step, start[1] + float(row) * step),
                       mode, shift, field_u, field_v, field_origin, field_step)
        px[k] = x[0]
        py[k] = x[1]
        centre += x
    centre = centre / 64.0
    far2 = float(0.0)
    for k in range(64):
        far2 = wp.max(far2, wp.length_sq(wp.vec2(px[k], py[k]) - centre))
    half = 0.5 * wp.max(width, 0.0)
    reach = wp.sqrt(far2) + half + 1.0e-4
    cx = _vec16()
    cy = _vec16()
    cr = _vec16()
    n = int(0)
    full = int(0)
    overflow = int(0)
    inv = 1.0 / model.cell_size
    look = reach + model.max_radius
    gx0 = wp.max(int(wp.floor((centre[0] - look - model.origin[0]) * inv)), 0)
    gx1 = wp.min(int(wp.floor((centre[0] + look - model.origin[0]) * inv)), model.nx - 1)
    gy0 = wp.max(int(wp.floor((centre[1] - look - model.origin[1]) * inv)), 0)
    gy1 = wp.min(int(wp.floor((centre[1] + look - model.origin[1]) * inv)), model.ny - 1)
    for gy in range(gy0, gy1 + 1):
        for gx in range(gx0, gx1 + 1):
            cell = gy * model.nx + gx
            first = model.cell_start[cell]
            for k in range(first, first + model.cell_count[cell]):
                c = model.centres[k]
                r = model.radii[k]
                dist = wp.length(c - centre)
                if dist < r + reach:
                    if dist + reach <= r:
                        full = 1  # every sub-cell is deeper than width/2 inside this disk
                    elif n < 16:
                        cx[n] = c[0]
                        cy[n] = c[1]
                        cr[n] = r
                        n += 1
                    else:
                        overflow = 1
    init = half  # no disk within width/2: coverage 0
    if width <= 0.0:
        init = 1.0e30  # binary coverage: uncovered unless some |p - c| - r <= 0
    best = _vec64()
    for k in range(64):
        best[k] = init
    for j in range(n):
        c = wp.vec2(cx[j], cy[j])
        r = cr[j]
        for k in range(64):
            best[k] = wp.min(best[k], wp.length(wp.vec2(px[k], py[k]) - c) - r)
    for k in range(64):
        row = r0 + k / 8
        col = c0 + k - (k / 8) * 8
        if row < nrows and col < ncols:
            val = float(1.0)
            if full == 0:
                if overflow == 1:
                    val = speckle_coverage_smooth(model, wp.vec2(px[k], py[k]), width)
                elif width > 0.0:
                    val = wp.clamp(0.5 - best[k] / width, 0.0, 1.0)
                elif best[k] > 0.0:
                    val = 0.0
            out[row * out_stride + col] = val


@wp.kernel
def _decimate_cols_kernel(
    fine: wp.array2d(dtype=float),
    weights: wp.array(dtype=float),
    factor: int,
    out: wp.array2d(dtype=float),
    offset: int,
):
    # out[r, c] = sum_j weights[j] * fine[r, c * factor + j]
    i = wp.tid() + offset
    ncols = out.shape[1]
    r = i / ncols
    c = i - r * ncols
    base = c * factor
    acc = float(0.0)
    for j in range(weights.shape[0]):
        acc += weights[j] * fine[r, base + j]
    out[r, c] = acc


@wp.kernel
def _decimate_cols4_kernel(
    fine: wp.array(dtype=wp.vec4),
    stride4: int,
    weights: wp.array(dtype=wp.vec4),
    factor4: int,
    out: wp.array2d(dtype=float),
    offset: int,
):
    # the same filter when the factor is a multiple of 4: taps read as aligned vec4 groups
    # (about 2.5x faster on the CPU); fine row r starts at group r * stride4
    i = wp.tid() + offset
    ncols = out.shape[1]
    r = i / ncols
    c = i - r * ncols
    base = r * stride4 + c * factor4
    acc = float(0.0)
    for g in range(weights.shape[0]):
        acc += wp.dot(weights[g], fine[base + g])
    out[r, c] = acc


@wp.kernel
def _decimate_rows_kernel(
    fine: wp.array2d(dtype=wp.vec4),
    weights: wp.array(dtype=float),
    factor: int,
    out: wp.array2d(dtype=wp.vec4),
    offset: int,
):
    # out[r, c] = sum_j weights[j] * fine[r * factor + j, c], four image columns per vec4
    i = wp.tid() + offset
    ncols = out.shape[1]
    r = i / ncols
    c = i - r * ncols
    base = r * factor
    acc = wp.vec4(0.0)
    for j in range(weights.shape[0]):
        acc += weights[j] * fine[base + j, c]
    out[r, c] = acc


@wp.kernel
def _points_kernel(
    model: SpeckleModel,
    points: wp.array(dtype=wp.vec2),
    taps: wp.array(dtype=float),
    weights: wp.array(dtype=float),
    width: float,
    out: wp.array(dtype=float),
    offset: int,
):
    # direct (non-separable) quadrature of one pixel centred at points[i]
    i = wp.tid() + offset
    p = points[i]
    n = taps.shape[0]
    acc = float(0.0)
    for jy in range(n):
        row = float(0.0)
        for jx in range(n):
            row += weights[jx] * speckle_coverage_smooth(model, p + wp.vec2(taps[jx], taps[jy]), width)
        acc += weights[jy] * row
    out[i] = acc


# ---------------------------------------------------------------------------------------------
# host side: building the model


def build_speckle_model(centres, radii, *, cell_size=None, pad: float = 0.0, device=None) -> SpeckleModel:
    """Bin disks into a :class:`SpeckleModel` on ``device``.

    Parameters
    ----------
    centres : array_like, shape (M, 2)
        Disk centres ``(x, y)`` in any length unit (px for images, mm for lab surfaces).
    radii : array_like, shape (M,)
        Disk radii, same unit, > 0.
    cell_size : float, optional
        Side of the square cells. Default ``2 * (max radius + pad)``, so that a query with
        anti-aliasing half-width ``<= pad`` visits at most 2 × 2 cells.
    pad : float
        Largest anti-aliasing half-width the model will be queried with (only sets the default
        cell size; queries stay correct for any width).
    device : str, optional
        Warp device (``None``: ``cuda:0`` when present, else ``cpu``).

    The model keeps references to its device arrays; keep it alive while kernels use it.
    """
    device = resolve_device(device)
    centres = np.asarray(centres, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    if centres.ndim != 2 or centres.shape[1] != 2:
        raise ValueError(f"centres must have shape (M, 2), got {centres.shape}")
    if radii.shape != (centres.shape[0],):
        raise ValueError(f"radii must have shape ({centres.shape[0]},) to match centres, got {radii.shape}")
    if not (np.all(np.isfinite(centres)) and np.all(np.isfinite(radii))):
        raise ValueError("centres and radii must be finite")
    if radii.size and radii.min() <= 0:
        raise ValueError(f"radii must be > 0, smallest is {radii.min()}")
    if pad < 0:
        raise ValueError(f"pad must be >= 0, got {pad}")
    max_radius = float(radii.max()) if radii.size else 0.0
    if cell_size is None:
        cell_size = 2.0 * (max_radius + pad) if radii.size else 1.0
    cell_size = positive_float(cell_size, "cell_size")
    if centres.shape[0]:
        lo = centres.min(axis=0)
        hi = centres.max(axis=0)
    else:
        lo = hi = np.zeros(2)
    nx = int(np.floor((hi[0] - lo[0]) / cell_size)) + 1
    ny = int(np.floor((hi[1] - lo[1]) / cell_size)) + 1
    if nx * ny > 50_000_000:
        raise ValueError(f"a {nx} x {ny} cell grid is too large; increase cell_size")
    cx = np.clip(np.floor((centres[:, 0] - lo[0]) / cell_size).astype(np.int64), 0, nx - 1)
    cy = np.clip(np.floor((centres[:, 1] - lo[1]) / cell_size).astype(np.int64), 0, ny - 1)
    cell = cy * nx + cx
    order = np.argsort(cell, kind="stable")
    count = np.bincount(cell, minlength=nx * ny).astype(np.int32)
    start = np.zeros(nx * ny, dtype=np.int32)
    np.cumsum(count[:-1], out=start[1:])
    c_sorted = centres[order].astype(np.float32)
    r_sorted = radii[order].astype(np.float32)
    if c_sorted.shape[0] == 0:  # Warp arrays of length 0 are fine, but keep one dummy disk far away
        c_sorted = np.full((1, 2), 1e30, dtype=np.float32)
        r_sorted = np.ones(1, dtype=np.float32)
    model = SpeckleModel()
    model.centres = wp.array(c_sorted, dtype=wp.vec2, device=device)
    model.radii = wp.array(r_sorted, dtype=float, device=device)
    model.cell_start = wp.array(start, dtype=int, device=device)
    model.cell_count = wp.array(count, dtype=int, device=device)
    model.origin = wp.vec2(float(lo[0]), float(lo[1]))
    model.cell_size = cell_size
    model.nx = nx
    model.ny = ny
    model.max_radius = max_radius
    return model


_LOADED: set[str] = set()


def _model_device(model) -> str:
    """Validate ``model`` and return its device, with this module loaded there.

    Loading (compiling) once up front keeps the chunked CPU launches from compiling the module
    concurrently in every worker thread.
    """
    if not isinstance(model, SpeckleModel.cls):
        raise ValueError(f"model must be a kernels.speckle.SpeckleModel (see build_speckle_model), got {type(model).__name__}")
    device = str(model.centres.device)
    if device not in _LOADED:
        wp.load_module(sys.modules[__name__], device=device)
        _LOADED.add(device)
    return device


def _points_array(points, device):
    pts = as_points(points, allow_empty=True)
    return wp.array(pts.astype(np.float32), dtype=wp.vec2, device=device)


def speckle_coverage_points(model: SpeckleModel, points, *, width: float = 0.0) -> np.ndarray:
    """Coverage of ``points`` (N, 2) in model units: binary (``width=0``) or anti-aliased.

    Returns float64 (N,) in [0, 1]; runs on the model's device.
    """
    device = _model_device(model)
    if not (width >= 0 and math.isfinite(width)):
        raise ValueError(f"width must be >= 0, got {width}")
    pts = _points_array(points, device)
    out = wp.zeros(pts.shape[0], dtype=float, device=device)
    launch_1d(_coverage_points_kernel, pts.shape[0], [model, pts, float(width), out, 0], device, 4)
    return out.numpy().astype(np.float64)


# ---------------------------------------------------------------------------------------------
# host side: rendering


def _box_gauss_cdf(t: np.ndarray, blur: float) -> np.ndarray:
    """CDF of U(-1/2, 1/2) + N(0, blur²) at ``t`` (the 1-D pixel-box-times-PSF kernel)."""
    from scipy.special import ndtr

    def prim(z):  # antiderivative of Phi(z / blur)
        if blur == 0:
            return np.maximum(z, 0.0)
        zs = z / blur
        return z * ndtr(zs) + blur * np.exp(-0.5 * zs * zs) / math.sqrt(2 * math.pi)

    return prim(t + 0.5) - prim(t - 0.5)


def quadrature_taps(samples: int, blur: float) -> tuple[np.ndarray, np.ndarray]:
    """1-D sub-cell offsets (px, relative to the pixel centre) and weights of the pixel kernel.

    The kernel is the pixel box convolved with a Gaussian of std ``blur`` px, truncated at
    4 ``blur`` and renormalised. Offsets are the centres of sub-cells of width ``1/samples``
    aligned with the pixel; weights are the exact integrals of the kernel over each sub-cell.
    Returns float64 arrays of length ``samples + 2 * ceil(4 * blur * samples)``.
    """
    samples = positive_int(samples, "samples (sub-cells per pixel side)", integral_float=True)
    if not (blur >= 0 and math.isfinite(blur)):
        raise ValueError(f"blur must be a finite number >= 0 (px), got {blur!r}")
    s = int(samples)
    h = 1.0 / s
    reach = int(math.ceil(4.0 * blur * s))
    j = np.arange(s + 2 * reach)
    taps = -0.5 + (j - reach + 0.5) * h
    weights = _box_gauss_cdf(taps + 0.5 * h, blur) - _box_gauss_cdf(taps - 0.5 * h, blur)
    weights /= weights.sum()
    return taps, weights


def speckle_at_points(model: SpeckleModel, points, *, samples: int = 4, blur: float = 0.7) -> np.ndarray:
    """Rendered coverage (0..1) of pixels centred at ``points`` (N, 2) px, undeformed pattern.

    The same quadrature as :func:`render_speckle`, evaluated directly per point (cost
    ``(samples + 8 blur samples)²`` coverage queries per point); for checks and sparse sampling.
    Returns float64 (N,).
    """
    device = _model_device(model)
    taps, weights = quadrature_taps(samples, blur)
    pts = _points_array(points, device)
    out = wp.zeros(pts.shape[0], dtype=float, device=device)
    launch_1d(
        _points_kernel,
        pts.shape[0],
        [model, pts, wp.array(taps.astype(np.float32), device=device),
         wp.array(weights.astype(np.float32), device=device), 1.0 / samples, out, 0],
        device,
        6,
        min_chunk=16,
    )
    return out.numpy().astype(np.float64)


def render_speckle(
    model: SpeckleModel,
    shape,
    *,
    samples: int = 4,
    blur: float = 0.7,
    shift=None,
    inverse_field=None,
    band_elements: int = 8_000_000,
) -> np.ndarray:
    """Render the pattern's coverage image (0..1) as seen by a camera, optionally deformed.

    Parameters
    ----------
    model : SpeckleModel
        Disks in pixel units (reference image coordinates); rendering runs on its device.
    shape : (H, W)
        Output image shape.
    samples : int
        Sub-cells per pixel side (``s``); the quadrature uses ``s × s`` per pixel.
    blur : float
        Standard deviation (px) of the Gaussian point-spread function, applied in the image.
    shift : (2,) optional
        Rigid displacement ``(u, v)`` px: the current image at ``x`` shows material point
        ``x - (u, v)``.
    inverse_field : (w_u, w_v, origin, step), optional
        Inverse displacement ``w`` sampled on a regular grid: ``w_u[r, c]`` at position
        ``origin + step * (c, r)`` (px), such that the current image at ``x`` shows material point
        ``X = x - w(x)``; interpolated with Keys bicubic. The grid must cover ``[-1 - reach,
        W + reach] × [-1 - reach, H + reach]`` with ``reach = 4 blur + 2 step`` (taps are clamped at
        the grid border). Mutually exclusive with ``shift``.
    band_elements : int
        Sub-cells evaluated per band (memory bound: 4 bytes each, plus a fraction for the filters).

    Returns
    -------
    ndarray, float32, shape (H, W)
        Rendered coverage: 0 on background, 1 inside large disks.
    """
    device = _model_device(model)
    try:
        H, W = (int(n) for n in shape)
    except (TypeError, ValueError):
        raise ValueError(f"shape must be (H, W), got {shape!r}") from None
    if H < 1 or W < 1:
        raise ValueError(f"shape must be positive, got {(H, W)}")
    taps, weights = quadrature_taps(samples, blur)
    s = int(samples)
    reach = (taps.size - s) // 2
    w_dev = wp.array(weights.astype(np.float32), device=device)
    mode = 0
    shift_v = wp.vec2(0.0, 0.0)
    dummy = wp.zeros((1, 1), dtype=float, device=device)
    fu = fv = dummy
    f_origin = wp.vec2(0.0, 0.0)
    f_step = 1.0
    if shift is not None and inverse_field is not None:
        raise ValueError("give either shift or inverse_field, not both")
    if shift is not None:
        sh = np.asarray(shift, dtype=np.float64).reshape(-1)
        if sh.shape != (2,) or not np.all(np.isfinite(sh)):
            raise ValueError(f"shift must be a finite (u, v) pair, got {shift!r}")
        mode = 1
        shift_v = wp.vec2(float(sh[0]), float(sh[1]))
    if inverse_field is not None:
        try:
            wu, wv, origin, f_step = inverse_field
        except (TypeError, ValueError):
            raise ValueError("inverse_field must be a tuple (w_u, w_v, origin, step)") from None
        wu = np.asarray(wu, dtype=np.float32)
        wv = np.asarray(wv, dtype=np.float32)
        if wu.ndim != 2 or wu.shape != wv.shape or min(wu.shape) < 4:
            raise ValueError(f"inverse_field w_u, w_v must be 2-D arrays of the same shape (>= 4x4), got {wu.shape}, {wv.shape}")
        if not (np.all(np.isfinite(wu)) and np.all(np.isfinite(wv))):
            raise ValueError("inverse_field contains NaN or infinite values")
        f_step = float(f_step)
        if not f_step > 0:
            raise ValueError(f"inverse_field step must be > 0, got {f_step}")
        origin = np.asarray(origin, dtype=np.float64).reshape(-1)
        need_lo = -1.0 - 4 * blur - 2 * f_step
        need_hi_x = W + 4 * blur + 2 * f_step
        need_hi_y = H + 4 * blur + 2 * f_step
        hi = origin + f_step * (np.array([wu.shape[1], wu.shape[0]]) - 1)
        if origin[0] > need_lo or origin[1] > need_lo or hi[0] < need_hi_x or hi[1] < need_hi_y:
            raise ValueError(
                f"inverse_field grid covers x in [{origin[0]:.2f}, {hi[0]:.2f}], y in [{origin[1]:.2f}, {hi[1]:.2f}]; "
                f"rendering a {H}x{W} image needs at least [{need_lo:.2f}, {need_hi_x:.2f}] x [{need_lo:.2f}, {need_hi_y:.2f}]"
            )
        mode = 2
        fu = wp.array(wu, dtype=float, device=device)
        fv = wp.array(wv, dtype=float, device=device)
        f_origin = wp.vec2(float(origin[0]), float(origin[1]))

    h = 1.0 / s
    W4 = -(-W // 4)  # output columns are computed in groups of 4 (the extra ones are dropped)
    n_fcols = W4 * 4 * s + 2 * reach
    vec4 = s % 4 == 0
    if vec4:  # pad the taps to whole vec4 groups and the sub-cell rows to match
        n_groups = -(-weights.size // 4)
        w4 = np.zeros(4 * n_groups, dtype=np.float32)
        w4[: weights.size] = weights
        w4_dev = wp.array(w4.reshape(n_groups, 4), dtype=wp.vec4, device=device)
        n_fcols = (W4 * 4 - 1) * s + 4 * n_groups
    rows_per_band = max(1, min(H, band_elements // max(1, n_fcols * s)))
    out = np.empty((H, W), dtype=np.float32)
    for r0 in range(0, H, rows_per_band):
        r1 = min(H, r0 + rows_per_band)
        n_frows = (r1 - r0) * s + 2 * reach
        # sub-cell m of pixel i along an axis sits at -0.5 + (m + 0.5) h; the band starts at m = r0 s - reach
        start = wp.vec2(-0.5 + (0 - reach + 0.5) * h, -0.5 + (r0 * s - reach + 0.5) * h)
        fine = wp.empty(n_frows * n_fcols, dtype=float, device=device)
        nbx = (n_fcols + 7) // 8
        nby = (n_frows + 7) // 8
        launch_1d(
            _fine_block_kernel,
            nbx * nby,
            [model, start, h, n_frows, n_fcols, nbx, mode, shift_v, fu, fv, f_origin, f_step, h, fine, n_fcols, 0],
            device,
            15,
        )
        tmp = wp.empty((n_frows, W4 * 4), dtype=float, device=device)
        if vec4:
            fine4 = fine.reshape((n_frows * n_fcols // 4, 4)).view(wp.vec4)
            launch_1d(_decimate_cols4_kernel, n_frows * W4 * 4, [fine4, n_fcols // 4, w4_dev, s // 4, tmp, 0], device, 5)
        else:
            fine2 = fine.reshape((n_frows, n_fcols))
            launch_1d(_decimate_cols_kernel, n_frows * W4 * 4, [fine2, w_dev, s, tmp, 0], device, 4)
        tmp4 = tmp.reshape((n_frows, W4, 4)).view(wp.vec4)
        band = wp.empty((r1 - r0, W4), dtype=wp.vec4, device=device)
        launch_1d(_decimate_rows_kernel, (r1 - r0) * W4, [tmp4, w_dev, s, band, 0], device, 4)
        out[r0:r1] = band.numpy().reshape(r1 - r0, W4 * 4)[:, :W]
    return out
