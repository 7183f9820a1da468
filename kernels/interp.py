"""Image interpolation: cubic B-spline (prefilter + evaluation) and Keys bicubic.

Cubic B-spline interpolation follows Unser, "Splines: a perfect fit for signal and image
processing", IEEE Signal Processing Magazine 16(6), 1999, doi:10.1109/79.799930: the image is
prefiltered into B-spline coefficients ``c`` (a causal then an anti-causal first-order recursive
filter with pole ``z1 = sqrt(3) - 2`` and gain 6, along rows then along columns) so that the
interpolant ``f(x, y) = sum_kl c[l, k] b3(x - k) b3(y - l)`` passes through every pixel value.
Each line is filtered in independent segments of at least :data:`PREFILTER_SEGMENT` samples (one
work item each, so a large image fills a GPU), started from the closed forms of the two recursions
truncated where they fall below float32 resolution; a line shorter than two segments is filtered
whole, and longer lines differ from the whole-line recursion by a few float32 ulps.
Keys bicubic convolution (Keys, "Cubic convolution interpolation for digital image processing",
IEEE TASSP 29(6), 1981, doi:10.1109/TASSP.1981.1163711) uses ``a = -0.5`` on the raw image.

Conventions (docs/conventions.md): images are indexed ``[row, col] = [y, x]``; pixel (0, 0) is the
centre of the top-left pixel; points are ``(x, y)`` in pixels.

Border handling (explicit):

* The signal is extended **mirror-symmetrically about the first and last pixel centres**
  (``... s2 s1 s0 s1 s2 ...``), the same boundary condition as ``scipy.ndimage`` ``mode="mirror"``;
  the B-spline prefilter uses it (exact mirror initialisation of the recursive filters), so values
  near the border equal ``scipy.ndimage.map_coordinates(image, ..., order=3, mode="mirror")``.
* Coefficients (and, for Keys, raw samples) are stored with a 2-pixel mirrored border
  (:data:`PAD`), so the 4x4 stencil of any position with ``-1 <= x < W`` and ``-1 <= y < H`` reads
  inside the array. The ``@wp.func`` evaluators do not check positions: callers guarantee that
  range (IC-GN checks every warped subset against the valid domain before reading).
* The **valid domain** is ``0 <= x <= W - 1``, ``0 <= y <= H - 1``. The public :func:`interpolate`
  returns NaN for points outside it; IC-GN reports subsets that leave it as ``OUT_OF_BOUNDS``.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from ._device import host_copy, resolve_device
from ._launch import cuda_launch_bounds, launch_1d
from .checks import as_points
from .images import as_float32_image

wp.set_module_options({"enable_backward": False})

#: Width of the mirrored border stored around coefficient / sample arrays (pixels).
PAD = 2
#: Samples per segment of the prefilter: each line (row, then column) is filtered in independent
#: segments of at least this many samples, so a 2048-pixel line is 16 work items (CPU threads, GPU
#: lanes) instead of one. Lines shorter than two segments are filtered whole.
PREFILTER_SEGMENT = 128
#: Terms of the truncated sums that start an interior segment (|z1|**16 = 7e-10, under float32
#: resolution); PREFILTER_SEGMENT must be at least this (the sums stay inside the line).
SEGMENT_HORIZON = wp.constant(16)

# ----------------------------------------------------------------------------------------------
# @wp.func helpers
# ----------------------------------------------------------------------------------------------


@wp.func
def bspline3_weights(t: float):
    """Cubic B-spline weights of the 4 taps at offsets -1, 0, 1, 2 for fractional position t in [0, 1)."""
    t2 = t * t
    t3 = t2 * t
    s = 1.0 - t
    return wp.vec4(
        s * s * s * (1.0 / 6.0),
        0.5 * t3 - t2 + (2.0 / 3.0),
        -0.5 * t3 + 0.5 * t2 + 0.5 * t + (1.0 / 6.0),
        t3 * (1.0 / 6.0),
    )


@wp.func
def bspline3_weights_fast(t: float):
    """Same as :func:`bspline3_weights` with fewer operations (partition of unity gives w2)."""
    t2 = t * t
    t3 = t2 * t
    w3 = t3 * (1.0 / 6.0)
    w0 = (1.0 / 6.0) + 0.5 * (t2 - t) - w3
    w1 = (2.0 / 3.0) + 0.5 * t3 - t2
    return wp.vec4(w0, w1, 1.0 - w0 - w1 - w3, w3)


@wp.func
def bspline3_dweights(t: float):
    """Derivatives d/dt of :func:`bspline3_weights`."""
    t2 = t * t
    s = 1.0 - t
    return wp.vec4(-0.5 * s * s, 1.5 * t2 - 2.0 * t, -1.5 * t2 + t + 0.5, 0.5 * t2)


@wp.func
def keys_weights(t: float):
    """Keys cubic-convolution weights (a = -0.5) of the taps at offsets -1, 0, 1, 2, t in [0, 1)."""
    t2 = t * t
    t3 = t2 * t
    return wp.vec4(
        -0.5 * t3 + t2 - 0.5 * t,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * t,
        0.5 * t3 - 0.5 * t2,
    )


@wp.func
def keys_dweights(t: float):
    """Derivatives d/dt of :func:`keys_weights`."""
    t2 = t * t
    return wp.vec4(
        -1.5 * t2 + 2.0 * t - 0.5,
        4.5 * t2 - 5.0 * t,
        -4.5 * t2 + 4.0 * t + 0.5,
        1.5 * t2 - t,
    )


@wp.func
def stencil_dot(c: wp.array(dtype=float), pitch: int, ix: int, iy: int, wx: wp.vec4, wy: wp.vec4):
    """sum_{k,l} c[iy-1+l, ix-1+k] wx[k] wy[l] on a padded flat array (``pitch`` = W + 2*PAD).

    ``(ix, iy)`` are unpadded integer pixel indices (the floor of the position).
    """
    base = (iy + 1) * pitch + ix + 1  # padded index of (iy - 1, ix - 1) with PAD = 2
    r0 = c[base] * wx[0] + c[base + 1] * wx[1] + c[base + 2] * wx[2] + c[base + 3] * wx[3]
    base += pitch
    r1 = c[base] * wx[0] + c[base + 1] * wx[1] + c[base + 2] * wx[2] + c[base + 3] * wx[3]
    base += pitch
    r2 = c[base] * wx[0] + c[base + 1] * wx[1] + c[base + 2] * wx[2] + c[base + 3] * wx[3]
    base += pitch
    r3 = c[base] * wx[0] + c[base + 1] * wx[1] + c[base + 2] * wx[2] + c[base + 3] * wx[3]
    return r0 * wy[0] + r1 * wy[1] + r2 * wy[2] + r3 * wy[3]


@wp.func
def stencil_dot_rows4(c4: wp.array(dtype=wp.vec4), pitch: int, ix: int, iy: int, wx: wp.vec4, wy: wp.vec4):
    """Same as :func:`stencil_dot` on row-expanded coefficients (:func:`expand_rows4`).

    ``c4[k]`` holds the 4 horizontal taps ``c[k-1 .. k+2]`` of the padded flat array, so a 4x4
    stencil is 4 vector loads; combining the rows first (vertical) vectorises well on the CPU.
    """
    base = (iy + 1) * pitch + ix + 2  # padded index of (iy - 1, ix) with PAD = 2
    col = wy[0] * c4[base] + wy[1] * c4[base + pitch] + wy[2] * c4[base + 2 * pitch] + wy[3] * c4[base + 3 * pitch]
    return wp.dot(col, wx)


@wp.func
def bspline3_value_grad(c: wp.array(dtype=float), pitch: int, x: float, y: float):
    """(value, d/dx, d/dy) of the cubic B-spline interpolant at (x, y) (no bounds check)."""
    fx = wp.floor(x)
    fy = wp.floor(y)
    ix = int(fx)
    iy = int(fy)
    wx = bspline3_weights(x - fx)
    wy = bspline3_weights(y - fy)
    dwx = bspline3_dweights(x - fx)
    dwy = bspline3_dweights(y - fy)
    return wp.vec3(
        stencil_dot(c, pitch, ix, iy, wx, wy),
        stencil_dot(c, pitch, ix, iy, dwx, wy),
        stencil_dot(c, pitch, ix, iy, wx, dwy),
    )


@wp.func
def causal_init(c: wp.array2d(dtype=Any), row: int, col: int, drow: int, dcol: int, n: int, z: float):
    """Initial value of the causal filter for mirror boundaries (Unser 1999, exact for n <= horizon);
    ``c`` of any real dtype, read as float32."""
    if n > 32:  # truncated sum, error |z|**32
        acc = float(0.0)
        zk = float(1.0)
        for k in range(32):
            acc += zk * float(c[row + k * drow, col + k * dcol])
            zk *= z
        return acc
    # exact: (s0 + z^(n-1) s_{n-1} + sum_{k=1}^{n-2} (z^k + z^(2n-2-k)) s_k) / (1 - z^(2n-2))
    zn = float(1.0)
    for k in range(n - 1):
        zn *= z  # z^(n-1)
    z2n = zn * zn  # divided by z in the loop: z^(2n-2-k)
    acc = float(c[row, col]) + zn * float(c[row + (n - 1) * drow, col + (n - 1) * dcol])
    zk = z
    for k in range(1, n - 1):
        z2n /= z  # z^(2n-2-k)
        acc += (zk + z2n) * float(c[row + k * drow, col + k * dcol])
        zk *= z
    return acc / (1.0 - zn * zn)


@wp.func
def filter_line(c: wp.array2d(dtype=float), row: int, col: int, drow: int, dcol: int, n: int):
    """In-place cubic B-spline prefilter of n samples c[row + k*drow, col + k*dcol] (gain 6)."""
    z = float(-0.2679491924311228)  # sqrt(3) - 2
    c0 = causal_init(c, row, col, drow, dcol, n, z)
    c[row, col] = c0
    prev = c0
    for k in range(1, n):
        cur = c[row + k * drow, col + k * dcol] + z * prev
        c[row + k * drow, col + k * dcol] = cur
        prev = cur
    last = row + (n - 1) * drow
    lastc = col + (n - 1) * dcol
    # anti-causal initial value for mirror boundaries
    cm = (z / (z * z - 1.0)) * (c[last, lastc] + z * c[last - drow, lastc - dcol])
    c[last, lastc] = 6.0 * cm
    for kk in range(1, n):
        k = n - 1 - kk
        cm = z * (cm - c[row + k * drow, col + k * dcol])
        c[row + k * drow, col + k * dcol] = 6.0 * cm


# ----------------------------------------------------------------------------------------------
# kernels
# ----------------------------------------------------------------------------------------------


@wp.kernel
def _expand_rows4(offset: int, c: wp.array(dtype=float), c4: wp.array(dtype=wp.vec4), pitch: int, n: int):
    k = wp.tid() + offset
    x = k % pitch
    if x >= 1 and x + 2 < pitch:
        c4[k] = wp.vec4(c[k - 1], c[k], c[k + 1], c[k + 2])
    else:
        c4[k] = wp.vec4(0.0)


@wp.func
def segment_starts(n: int, nseg: int, seg: int):
    """(start, end) of segment ``seg`` of ``nseg`` equal segments of a line of n samples."""
    return (seg * n) // nseg, ((seg + 1) * n) // nseg


@wp.func
def segment_entry_values(c: wp.array2d(dtype=Any), row: int, col: int, drow: int, dcol: int, s: int):
    """(causal output at s - 1, anti-causal output at s) of the prefilter of the line through
    c[row, col] (step (drow, dcol)), from the input samples around s alone.

    The causal filter is ``c+[k] = sum_{l >= 0} z^l s[k - l]`` and the anti-causal one
    ``c-[k] = -z / (1 - z^2) sum_m z^|m| s[k + m]`` (the two recursions combined; Unser 1999), both
    truncated at :data:`SEGMENT_HORIZON` samples (|z|^16 = 7e-10 of the grey range, below float32
    resolution). ``s`` must be at least SEGMENT_HORIZON samples from both ends of the line.
    """
    z = wp.float64(-0.2679491924311228)  # sqrt(3) - 2; float64 sums: the entries carry no extra rounding
    cp = wp.float64(0.0)
    zk = wp.float64(1.0)
    for l in range(SEGMENT_HORIZON):
        cp += zk * wp.float64(c[row + (s - 1 - l) * drow, col + (s - 1 - l) * dcol])
        zk *= z
    cm = wp.float64(c[row + s * drow, col + s * dcol])
    zk = wp.float64(1.0)
    for m in range(1, SEGMENT_HORIZON + 1):
        zk *= z
        cm += zk * (wp.float64(c[row + (s + m) * drow, col + (s + m) * dcol])
                    + wp.float64(c[row + (s - m) * drow, col + (s - m) * dcol]))
    return wp.vec2(float(cp), float((-z / (wp.float64(1.0) - z * z)) * cm))


@wp.func
def filter_segment(src: wp.array2d(dtype=Any), sr: int, sc: int, dst: wp.array2d(dtype=float), dr: int, dc: int,
                   drow: int, dcol: int, n: int, s0: int, s1: int, entry_causal: float, entry_anti: float):
    """Cubic B-spline prefilter (gain 6) of samples [s0, s1) of a line of n samples, read from
    ``src`` (origin (sr, sc), any real dtype, read as float32) and written to ``dst`` (origin
    (dr, dc)); may be in place.

    The first segment starts the causal filter with the exact mirror initial value, the last one
    the anti-causal filter with the exact mirror end value (as :func:`filter_line`); interior
    segment ends start from ``entry_causal`` (causal output at s0 - 1) and ``entry_anti``
    (anti-causal output at s1), :func:`segment_entry_values` computed before any sample is
    overwritten. A line that is one segment is filtered exactly as by :func:`filter_line`.
    """
    z = float(-0.2679491924311228)  # sqrt(3) - 2
    k0 = s0
    prev = entry_causal
    if s0 == 0:
        prev = causal_init(src, sr, sc, drow, dcol, n, z)
        dst[dr, dc] = prev
        k0 = 1
    for k in range(k0, s1):
        cur = float(src[sr + k * drow, sc + k * dcol]) + z * prev
        dst[dr + k * drow, dc + k * dcol] = cur
        prev = cur
    k1 = s1
    cm = entry_anti
    if s1 == n:
        last = dr + (n - 1) * drow
        lastc = dc + (n - 1) * dcol
        cm = (z / (z * z - 1.0)) * (dst[last, lastc] + z * dst[last - drow, lastc - dcol])
        dst[last, lastc] = 6.0 * cm
        k1 = n - 1
    for kk in range(s0, k1):
        k = k1 - 1 - (kk - s0)
        cm = z * (cm - dst[dr + k * drow, dc + k * dcol])
        dst[dr + k * drow, dc + k * dcol] = 6.0 * cm


@wp.kernel(launch_bounds=cuda_launch_bounds("_prefilter_entries_rows"))
def _prefilter_entries_rows(offset: int, image: wp.array2d(dtype=float), width: int, height: int, nseg: int,
                            entries: wp.array2d(dtype=wp.vec2)):
    t = wp.tid() + offset  # (segment boundary b = 1..nseg-1, row y), y fastest
    y = t % height
    b = t // height + 1
    s, _e = segment_starts(width, nseg, b)
    entries[y, b] = segment_entry_values(image, y, 0, 0, 1, s)


@wp.kernel(launch_bounds=cuda_launch_bounds("_prefilter_rows"))
def _prefilter_rows(offset: int, image: wp.array2d(dtype=float), coef: wp.array2d(dtype=float), width: int,
                    height: int, nseg: int, entries: wp.array2d(dtype=wp.vec2)):
    t = wp.tid() + offset  # (segment, row y), y fastest
    y = t % height
    seg = t // height
    r = y + 2
    s0, s1 = segment_starts(width, nseg, seg)
    ec = float(0.0)
    ea = float(0.0)
    if seg > 0:
        ec = entries[y, seg][0]
    if seg < nseg - 1:
        ea = entries[y, seg + 1][1]
    filter_segment(image, y, 0, coef, r, 2, 0, 1, width, s0, s1, ec, ea)
    # mirrored coefficient border: c[-1] = c[1], c[-2] = c[2], c[W] = c[W-2], c[W+1] = c[W-3]
    if seg == 0:
        coef[r, 1] = coef[r, 3]
        coef[r, 0] = coef[r, 4]
    if seg == nseg - 1:
        coef[r, width + 2] = coef[r, width]
        coef[r, width + 3] = coef[r, width - 1]


@wp.kernel(launch_bounds=cuda_launch_bounds("_prefilter_entries_cols"))
def _prefilter_entries_cols(offset: int, coef: wp.array2d(dtype=float), height: int, ncols: int, nseg: int,
                            entries: wp.array2d(dtype=wp.vec2)):
    t = wp.tid() + offset  # (segment boundary b, padded column x), x fastest
    x = t % ncols
    b = t // ncols + 1
    s, _e = segment_starts(height, nseg, b)
    entries[x, b] = segment_entry_values(coef, 2, x, 1, 0, s)


@wp.kernel(launch_bounds=cuda_launch_bounds("_prefilter_cols"))
def _prefilter_cols(offset: int, coef: wp.array2d(dtype=float), height: int, ncols: int, nseg: int,
                    entries: wp.array2d(dtype=wp.vec2)):
    t = wp.tid() + offset  # (segment, padded column x), x fastest: neighbouring threads, neighbouring columns
    x = t % ncols
    seg = t // ncols
    s0, s1 = segment_starts(height, nseg, seg)
    ec = float(0.0)
    ea = float(0.0)
    if seg > 0:
        ec = entries[x, seg][0]
    if seg < nseg - 1:
        ea = entries[x, seg + 1][1]
    filter_segment(coef, 2, x, coef, 2, x, 1, 0, height, s0, s1, ec, ea)
    if seg == 0:
        coef[1, x] = coef[3, x]
        coef[0, x] = coef[4, x]
    if seg == nseg - 1:
        coef[height + 2, x] = coef[height, x]
        coef[height + 3, x] = coef[height - 1, x]


@wp.kernel
def _prefilter_entries_rows_frames(offset: int, frames: wp.array3d(dtype=Any), width: int, height: int, nseg: int,
                                   entries: wp.array3d(dtype=wp.vec2)):
    """:func:`_prefilter_entries_rows` of frame ``f`` (``tid = (f * (nseg - 1) + b - 1) * height + y``)."""
    t = wp.tid() + offset
    per = height * (nseg - 1)
    f = t // per
    u = t - f * per
    y = u % height
    b = u // height + 1
    s, _e = segment_starts(width, nseg, b)
    entries[f, y, b] = segment_entry_values(frames[f], y, 0, 0, 1, s)


@wp.kernel(launch_bounds=cuda_launch_bounds("_prefilter_rows_frames"))
def _prefilter_rows_frames(offset: int, frames: wp.array3d(dtype=Any), coef: wp.array3d(dtype=float), width: int,
                           height: int, nseg: int, entries: wp.array3d(dtype=wp.vec2), bad: wp.array(dtype=wp.int32)):
    """:func:`_prefilter_rows` of segment ``seg`` of row ``y`` of frame ``f`` (``tid = (f * nseg + seg) *
    height + y``) reading the raw frame (8/16-bit or float32: the conversion to float happens here) and
    flagging a non-finite pixel in ``bad[f]`` (the frame's on-device validity check, fused into the pass
    that reads it: every pixel is in one segment)."""
    t = wp.tid() + offset
    per = height * nseg
    f = t // per
    u = t - f * per
    y = u % height
    seg = u // height
    c = coef[f]
    img = frames[f]
    r = y + 2
    s0, s1 = segment_starts(width, nseg, seg)
    for x in range(s0, s1):
        if not wp.isfinite(float(img[y, x])):
            bad[f] = 1
    ec = float(0.0)
    ea = float(0.0)
    if seg > 0:
        ec = entries[f, y, seg][0]
    if seg < nseg - 1:
        ea = entries[f, y, seg + 1][1]
    filter_segment(img, y, 0, c, r, 2, 0, 1, width, s0, s1, ec, ea)
    if seg == 0:
        c[r, 1] = c[r, 3]
        c[r, 0] = c[r, 4]
    if seg == nseg - 1:
        c[r, width + 2] = c[r, width]
        c[r, width + 3] = c[r, width - 1]


for _dtype in (wp.uint8, wp.uint16, wp.float32):  # the frame types of the device-resident path
    wp.overload(_prefilter_entries_rows_frames, {"frames": wp.array3d(dtype=_dtype)})
    wp.overload(_prefilter_rows_frames, {"frames": wp.array3d(dtype=_dtype)})


@wp.kernel
def _prefilter_entries_cols_frames(offset: int, coef: wp.array3d(dtype=float), height: int, ncols: int, nseg: int,
                                   entries: wp.array3d(dtype=wp.vec2)):
    """:func:`_prefilter_entries_cols` of frame ``f`` (``tid = (f * (nseg - 1) + b - 1) * ncols + x``)."""
    t = wp.tid() + offset
    per = ncols * (nseg - 1)
    f = t // per
    u = t - f * per
    x = u % ncols
    b = u // ncols + 1
    s, _e = segment_starts(height, nseg, b)
    entries[f, x, b] = segment_entry_values(coef[f], 2, x, 1, 0, s)


@wp.kernel(launch_bounds=cuda_launch_bounds("_prefilter_cols_frames"))
def _prefilter_cols_frames(offset: int, coef: wp.array3d(dtype=float), height: int, ncols: int, nseg: int,
                           entries: wp.array3d(dtype=wp.vec2)):
    """:func:`_prefilter_cols` of segment ``seg`` of column ``x`` of frame ``f``
    (``tid = (f * nseg + seg) * ncols + x``)."""
    t = wp.tid() + offset
    per = ncols * nseg
    f = t // per
    u = t - f * per
    x = u % ncols
    seg = u // ncols
    c = coef[f]
    s0, s1 = segment_starts(height, nseg, seg)
    ec = float(0.0)
    ea = float(0.0)
    if seg > 0:
        ec = entries[f, x, seg][0]
    if seg < nseg - 1:
        ea = entries[f, x, seg + 1][1]
    filter_segment(c, 2, x, c, 2, x, 1, 0, height, s0, s1, ec, ea)
    if seg == 0:
        c[1, x] = c[3, x]
        c[0, x] = c[4, x]
    if seg == nseg - 1:
        c[height + 2, x] = c[height, x]
        c[height + 3, x] = c[height - 1, x]


@wp.kernel
def _expand_rows4_frames(offset: int, c: wp.array2d(dtype=float), c4: wp.array2d(dtype=wp.vec4), pitch: int, n: int):
    """:func:`_expand_rows4` of entry ``k`` of frame ``f`` (``tid = f * n + k``)."""
    t = wp.tid() + offset
    f = t // n
    k = t - f * n
    x = k % pitch
    if x >= 1 and x + 2 < pitch:
        c4[f, k] = wp.vec4(c[f, k - 1], c[f, k], c[f, k + 1], c[f, k + 2])
    else:
        c4[f, k] = wp.vec4(0.0)


@wp.func
def split_position(p: wp.vec2d, width: int, height: int):
    """Split a float64 (x, y) into integer floor and float32 fraction: (ix, iy, tx, ty, inside).

    ``inside`` is 1 when the point lies in the valid domain [0, W-1] x [0, H-1], else 0.
    Keeping the fraction separate preserves sub-pixel precision far from the origin.
    """
    x = p[0]
    y = p[1]
    inside = 0
    if x >= wp.float64(0.0) and x <= wp.float64(width - 1) and y >= wp.float64(0.0) and y <= wp.float64(height - 1):
        inside = 1
    fx = wp.floor(x)
    fy = wp.floor(y)
    return wp.vec4i(int(fx), int(fy), inside, 0), wp.vec2(float(x - fx), float(y - fy))


@wp.kernel
def _interp_kernel(
    c: wp.array(dtype=float), pitch: int, width: int, height: int,
    points: wp.array(dtype=wp.vec2d), keys: int, gradient: int, out: wp.array2d(dtype=float),
):
    i = wp.tid()
    idx, t = split_position(points[i], width, height)
    if idx[2] == 0:
        for k in range(out.shape[1]):
            out[i, k] = wp.nan
        return
    wx = bspline3_weights(t[0])
    wy = bspline3_weights(t[1])
    dwx = bspline3_dweights(t[0])
    dwy = bspline3_dweights(t[1])
    if keys != 0:
        wx = keys_weights(t[0])
        wy = keys_weights(t[1])
        dwx = keys_dweights(t[0])
        dwy = keys_dweights(t[1])
    out[i, 0] = stencil_dot(c, pitch, idx[0], idx[1], wx, wy)
    if gradient != 0:
        out[i, 1] = stencil_dot(c, pitch, idx[0], idx[1], dwx, wy)
        out[i, 2] = stencil_dot(c, pitch, idx[0], idx[1], wx, dwy)


# ----------------------------------------------------------------------------------------------
# launchers
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PaddedImage:
    """A device image stored with a :data:`PAD`-pixel mirrored border.

    Attributes
    ----------
    data : wp.array2d of float32, shape (H + 2*PAD, W + 2*PAD)
        ``data[y + PAD, x + PAD]`` holds pixel (x, y).
    kind : str
        ``"bspline"`` (cubic B-spline coefficients) or ``"samples"`` (raw grey levels, for Keys).
    shape : (H, W) of the unpadded image.
    device : Warp device name.
    """

    data: wp.array
    kind: str
    shape: tuple[int, int]
    device: str

    @property
    def pitch(self) -> int:
        """Row length of the padded array (W + 2*PAD)."""
        return self.shape[1] + 2 * PAD

    @property
    def flat(self) -> wp.array:
        """The padded array as a flat 1-D view (index ``(y + PAD) * pitch + x + PAD``)."""
        return self.data.flatten()


def _check_min_size(arr: np.ndarray, name: str) -> None:
    if arr.shape[0] < 4 or arr.shape[1] < 4:
        raise ValueError(f"{name} must be at least 4x4 pixels for cubic interpolation, got shape {arr.shape}")


_SCRATCH = threading.local()


def _entries_buffer(device: str, shape: tuple) -> wp.array:
    """The segment entry values' scratch (vec2 of ``shape``: (rows, nseg) or (frames, rows, nseg), a
    few hundred KB per frame), kept per thread, device, CUDA stream and number of dimensions and grown
    when too small, so frames allocate nothing here: one thread's calls on one stream run in order,
    so the next call cannot overwrite values in use."""
    cache = getattr(_SCRATCH, "entries", None)
    if cache is None:
        cache = _SCRATCH.entries = {}
    key = (device if device.startswith("cpu") else (device, wp.get_stream(device).cuda_stream), len(shape))
    buf = cache.get(key)
    if buf is None or any(have < need for have, need in zip(buf.shape, shape)):
        grown = shape if buf is None else tuple(max(a, b) for a, b in zip(buf.shape, shape))
        buf = wp.empty(grown, dtype=wp.vec2, device=device)
        cache[key] = buf
    return buf


def prefilter_segments(n: int) -> int:
    """Number of segments the prefilter splits a line of ``n`` samples into (at least
    :data:`PREFILTER_SEGMENT` samples each; 1 for a line shorter than two segments)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive int (samples per line), got {n!r}")
    return max(1, int(n) // PREFILTER_SEGMENT)


def bspline_coefficients(image, device=None, out: wp.array | None = None) -> PaddedImage:
    """Cubic B-spline coefficients of a grey image (Unser 1999, doi:10.1109/79.799930).

    Parameters
    ----------
    image : array-like (H, W), any real dtype, or a float32 ``wp.array2d`` on ``device``
        Grey levels (kept on their original scale). H, W >= 4.
    device : None or str
        Warp device (``None``: ``cuda:0`` if present, else ``cpu``).
    out : wp.array2d of float32, shape (H + 4, W + 4), optional
        Destination (reused across frames to avoid reallocation).

    Returns
    -------
    PaddedImage
        ``kind="bspline"``; coefficients with a 2-pixel mirrored border such that
        ``scipy.ndimage.map_coordinates(image, (y, x), order=3, mode="mirror")`` equals the
        interpolant inside ``[0, W-1] x [0, H-1]``.
    """
    device = resolve_device(device)
    if isinstance(image, wp.array):
        if image.ndim != 2 or image.dtype != wp.float32:
            raise ValueError(f"image as a wp.array must be 2-D float32, got ndim={image.ndim}, dtype={image.dtype}")
        if str(image.device) != device:
            raise ValueError(f"image is on {image.device} but device={device!r}")
        img_wp = image
        h, w = image.shape
        if h < 4 or w < 4:
            raise ValueError(f"image must be at least 4x4 pixels for cubic interpolation, got shape {image.shape}")
    else:
        arr = as_float32_image(image, "image")
        _check_min_size(arr, "image")
        h, w = arr.shape
        # on the CPU the (C-contiguous float32) array is read in place: no copy, no allocation
        img_wp = wp.array(arr, dtype=wp.float32, device=device, copy=not device.startswith("cpu"))
    shape_p = (h + 2 * PAD, w + 2 * PAD)
    if out is None:
        out = wp.empty(shape_p, dtype=wp.float32, device=device)
    elif out.shape != shape_p or out.dtype != wp.float32 or str(out.device) != device:
        raise ValueError(
            f"out must be a float32 wp.array of shape {shape_p} on {device}, "
            f"got shape {out.shape}, dtype {out.dtype}, device {out.device}"
        )
    # lines in segments (PREFILTER_SEGMENT): entry values first (read-only), then the segments
    nseg_r = prefilter_segments(w)
    nseg_c = prefilter_segments(h)
    ncols = w + 2 * PAD
    entries = _entries_buffer(device, (max(h, ncols), max(nseg_r, nseg_c)))
    if nseg_r > 1:
        launch_1d(_prefilter_entries_rows, h * (nseg_r - 1), [0, img_wp, w, h, nseg_r, entries], device,
                  offset_index=0, min_chunk=256)
    launch_1d(_prefilter_rows, h * nseg_r, [0, img_wp, out, w, h, nseg_r, entries], device, offset_index=0,
              min_chunk=64)
    if nseg_c > 1:
        launch_1d(_prefilter_entries_cols, ncols * (nseg_c - 1), [0, out, h, ncols, nseg_c, entries], device,
                  offset_index=0, min_chunk=256)
    launch_1d(_prefilter_cols, ncols * nseg_c, [0, out, h, ncols, nseg_c, entries], device, offset_index=0,
              min_chunk=64)
    return PaddedImage(out, "bspline", (h, w), device)


#: frame dtypes the device-resident path reads directly (converted to float in the prefilter kernel)
FRAME_DTYPES = {np.dtype(np.uint8): wp.uint8, np.dtype(np.uint16): wp.uint16, np.dtype(np.float32): wp.float32}


def bspline_frames(frames: wp.array, n_frames: int, coef: wp.array, rows4: wp.array | None, bad: wp.array) -> None:
    """B-spline coefficients of the first ``n_frames`` frames of a stack, in IC-GN's row-expanded layout.

    The buffers are the caller's, allocated once (:class:`kernels.frames.FrameTracker`); nothing is
    allocated here. ``frames`` (F, H, W) uint8/uint16/float32 on the device (read as they are: grey
    levels keep their scale); ``coef`` (F, H + 4, W + 4) float32; ``rows4`` (F, (H + 4) (W + 4)) vec4, or
    None: no expansion (IC-GN reads ``coef`` in place, the ``"plain"`` layout of :func:`rows4_view`);
    ``bad`` (F,) int32 zeroed by the caller, set to 1 for a frame holding a non-finite pixel. Each
    frame's coefficients equal :func:`bspline_coefficients` and :func:`expand_rows4` of the frame as
    float32 bit for bit (the same segmented filter, built from the same wp.funcs).
    """
    if frames.dtype not in FRAME_DTYPES.values() or frames.ndim != 3:
        raise ValueError(f"frames must be a 3-D uint8/uint16/float32 wp.array, got ndim={frames.ndim}, dtype={frames.dtype}")
    f, h, w = frames.shape
    most = min(f, coef.shape[0], bad.shape[0], f if rows4 is None else rows4.shape[0])
    if not 1 <= n_frames <= most:
        raise ValueError(f"n_frames must be in [1, {most}], got {n_frames}")
    if h < 4 or w < 4 or coef.shape[1:] != (h + 2 * PAD, w + 2 * PAD):
        raise ValueError(f"coef must be (F, {h + 2 * PAD}, {w + 2 * PAD}) for frames of {h}x{w} (>= 4x4), got {coef.shape}")
    device = str(frames.device)
    pitch = w + 2 * PAD
    n = (h + 2 * PAD) * pitch
    # the segmented prefilter of bspline_coefficients, per frame (the same wp.funcs: the same bits)
    nseg_r = prefilter_segments(w)
    nseg_c = prefilter_segments(h)
    entries = _entries_buffer(device, (n_frames, max(h, pitch), max(nseg_r, nseg_c)))
    if nseg_r > 1:
        launch_1d(_prefilter_entries_rows_frames, n_frames * h * (nseg_r - 1), [0, frames, w, h, nseg_r, entries],
                  device, offset_index=0, min_chunk=256)
    launch_1d(_prefilter_rows_frames, n_frames * h * nseg_r, [0, frames, coef, w, h, nseg_r, entries, bad], device,
              offset_index=0, min_chunk=64)
    if nseg_c > 1:
        launch_1d(_prefilter_entries_cols_frames, n_frames * pitch * (nseg_c - 1), [0, coef, h, pitch, nseg_c, entries],
                  device, offset_index=0, min_chunk=256)
    launch_1d(_prefilter_cols_frames, n_frames * pitch * nseg_c, [0, coef, h, pitch, nseg_c, entries], device,
              offset_index=0, min_chunk=64)
    if rows4 is None:
        return
    flat = coef.reshape((coef.shape[0], n))
    launch_1d(_expand_rows4_frames, n_frames * n, [0, flat, rows4, pitch, n], device, offset_index=0,
              min_chunk=1 << 16)


def expand_rows4(coeffs: PaddedImage, out: wp.array | None = None) -> wp.array:
    """Row-expanded copy of padded coefficients for fast 4x4 stencils (:func:`stencil_dot_rows4`).

    Returns a flat ``wp.array`` of ``wp.vec4`` with ``(H + 4) * (W + 4)`` entries where entry
    ``k`` holds ``flat[k-1 : k+3]`` of ``coeffs`` (4x the memory of the coefficients).
    """
    if not isinstance(coeffs, PaddedImage):
        raise ValueError(f"coeffs must be a PaddedImage, got {type(coeffs).__name__}")
    n = coeffs.data.shape[0] * coeffs.data.shape[1]
    if out is None:
        out = wp.empty(n, dtype=wp.vec4, device=coeffs.device)
    elif out.shape != (n,) or out.dtype != wp.vec4 or str(out.device) != coeffs.device:
        raise ValueError(f"out must be a vec4 wp.array of shape {(n,)} on {coeffs.device}, got {out.shape} {out.dtype}")
    launch_1d(_expand_rows4, n, [0, coeffs.flat, out, coeffs.pitch, n], coeffs.device, offset_index=0,
              min_chunk=1 << 16)
    return out


def rows4_view(coeffs: PaddedImage) -> wp.array:
    """The padded coefficients read as :func:`expand_rows4`'s layout, in place (no copy, no pass).

    Returns a ``wp.vec4`` array with a 4-byte stride aliasing ``coeffs``: entry ``k`` is
    ``flat[k-1 : k+3]``, the value :func:`expand_rows4` stores at ``k`` for every ``k`` a 4x4
    stencil reads (:func:`stencil_dot_rows4` reads ``k >= 1``; entry 0 would start one float
    before the buffer and is never read). A kernel taking ``wp.array(dtype=wp.vec4)`` runs
    unchanged on it (Warp indexes arrays through their strides, and ``wp.vec4`` needs only 4-byte
    alignment), so it computes the same bits as on the expanded copy while reading the plain
    coefficients: 4 scalar loads per stencil row, 1x instead of 4x the memory. The view keeps
    ``coeffs.data`` alive.
    """
    if not isinstance(coeffs, PaddedImage):
        raise ValueError(f"coeffs must be a PaddedImage, got {type(coeffs).__name__}")
    data = coeffs.data
    if not data.is_contiguous or data.dtype != wp.float32:
        raise ValueError("coeffs must hold contiguous float32 coefficients")
    n = data.shape[0] * data.shape[1]
    view = wp.array(ptr=data.ptr - 4, dtype=wp.vec4, shape=(n - 2,), strides=(4,), device=coeffs.device,
                    copy=False)
    view._ref = data  # keep the coefficients alive as long as the view
    return view


def padded_samples(image, device=None) -> PaddedImage:
    """Raw grey levels with a 2-pixel mirrored border (input of Keys bicubic interpolation)."""
    device = resolve_device(device)
    arr = as_float32_image(image, "image")
    _check_min_size(arr, "image")
    padded = np.pad(arr, PAD, mode="reflect")  # numpy 'reflect' == scipy 'mirror' (about pixel centres)
    return PaddedImage(wp.array(padded, dtype=wp.float32, device=device), "samples", arr.shape, device)


def _as_points(points, device: str) -> wp.array:
    # empty and NaN points are allowed here: a NaN point interpolates to NaN
    pts = as_points(points, allow_empty=True, finite=False)
    return wp.array(pts, dtype=wp.vec2d, device=device)


def interpolate(image_or_coeffs, points, method: str = "bspline", gradient: bool = False, device=None) -> np.ndarray:
    """Interpolate a grey image at arbitrary sub-pixel points.

    Parameters
    ----------
    image_or_coeffs : array-like (H, W) or PaddedImage
        A grey image, or the result of :func:`bspline_coefficients` (``method="bspline"``) or
        :func:`padded_samples` (``method="keys"``) to skip the preparation.
    points : array-like (N, 2)
        Positions ``(x, y)`` in pixels (x along columns, y along rows).
    method : ``"bspline"`` (cubic B-spline, Unser 1999) or ``"keys"`` (Keys bicubic, a = -0.5).
    gradient : bool
        Also return the spatial derivatives of the interpolant (grey levels per pixel).
    device : None or str

    Returns
    -------
    np.ndarray, float32, shape (N,) or, with ``gradient=True``, (N, 3) holding
    ``(value, d/dx, d/dy)``. Points outside ``[0, W-1] x [0, H-1]`` give NaN (see module doc).
    """
    if method not in ("bspline", "keys"):
        raise ValueError(f"method must be 'bspline' or 'keys', got {method!r}")
    if isinstance(image_or_coeffs, PaddedImage):
        prepared = image_or_coeffs
        expected = "bspline" if method == "bspline" else "samples"
        if prepared.kind != expected:
            raise ValueError(f"method={method!r} needs a PaddedImage of kind {expected!r}, got {prepared.kind!r}")
        device = prepared.device if device is None else resolve_device(device)
        if device != prepared.device:
            raise ValueError(f"prepared image is on {prepared.device} but device={device!r}")
    else:
        device = resolve_device(device)
        prepared = (bspline_coefficients if method == "bspline" else padded_samples)(image_or_coeffs, device=device)
    pts = _as_points(points, device)
    n = pts.shape[0]
    ncol = 3 if gradient else 1
    out = wp.empty((max(n, 1), ncol), dtype=wp.float32, device=device)
    if n > 0:
        h, w = prepared.shape
        keys = int(method == "keys")
        wp.launch(_interp_kernel, dim=n, inputs=[prepared.flat, prepared.pitch, w, h, pts, keys, int(gradient), out],
                  device=device)
    res = host_copy(out)[:n]
    return res if gradient else res[:, 0]
