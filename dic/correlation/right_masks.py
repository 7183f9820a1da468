"""Pixel masks of the right camera's temporal track: the left region carried into the right reference image.

A stereo run's region (a mask or polygon ROI, in the LEFT reference image) masks the left subsets
(:func:`dic.correlation.subset_masks.tracking_pixel_masks`): the stereo match and the left temporal track
correlate the specimen's pixels only. The right temporal track correlates right-image subsets, centred on
the matched points; :func:`right_tracking_pixel_masks` says which of their pixels belong to the specimen by
mapping each right subset pixel back into the left reference image through the POI's stereo match and
reading the (shrunk) left region there.

The match warp of a POI (:mod:`kernels.icgn`, the parameters of :data:`kernels.conventions.PARAMS_1ST` /
``PARAMS_2ND``) takes the left subset pixel at offset ``d`` from the rounded POI ``c_l`` to
``c_l + d + (u, v) + G d`` in the right image (``G`` the displacement gradient; the second-order terms of a
2nd-order match are left out: over a subset they move a pixel by a fraction of a pixel, below the
region's margin). The right subset pixel ``c_r + e`` (``c_r`` the rounded matched point) therefore sees the
left position ``c_l + (I + G)^-1 (c_r + e - c_l - (u, v))``; it is kept when the 4 left pixels around that
position are all in the region (the region shrunk by
:data:`~dic.correlation.subset_masks.REGION_MARGIN_PX`, as for the left subsets), and not beyond either
image. Row order: that of :mod:`dic.correlation.subset_masks` (row-major, x fastest).

Why the 4 pixels, by measurement (a 120 mm plate 150 mm in front of a static speckled background, the
virtual lab's 320 x 240 px rig, subset 21, step 5, 16 samples per pixel; the free-edge test of
tests/dic/test_stereo_masks.py and widths 100 and 140 mm): the nearest left pixel lets the kept right pixels
come up to half a pixel nearer the edge, and the right track's edge points had 1.75-2.17 x the interior's
image-plane RMS error (3-D displacement 1.87-2.16 x); with the 4 pixels 1.49-1.92 x (3-D 1.65-1.84 x).
Without right masks: 30-38 x in 3-D (0.55-0.77 mm against 0.019 mm).
"""
from __future__ import annotations

import numpy as np

from kernels.checks import as_points, odd_int
from kernels.conventions import round_half_away

from .subset_masks import REGION_MARGIN_PX, check_subset_mask, region_pixel_mask, shrink_region, subset_offsets

__all__ = ["right_tracking_pixel_masks", "mapped_pixel_masks"]


def mapped_pixel_masks(region_mask, right_shape, points_left, points_right, params, subset: int,
                       cracks=None) -> np.ndarray:
    """``(M, S*S)`` bool: the right subsets' pixels that map into ``region_mask`` through the match.

    ``region_mask`` (H, W) bool: the specimen's pixels in the left reference image (None: every pixel);
    ``right_shape`` (H, W): the right image's; ``points_left`` (M, 2) px: the POIs; ``points_right`` (M, 2) px:
    their matched points; ``params`` (M, 6) or (M, 12): the match warps (left -> right; 1st or 2nd order);
    ``subset`` px (odd); ``cracks`` (declared cracks in left reference px, :mod:`dic.cracks`), optional: a pixel
    whose mapped left position lies across a crack from the POI (the segment between them crosses it), or
    within :data:`dic.cracks.CRACK_MARGIN_PX` of one, is not kept either. A point whose warp is not finite or
    singular keeps no pixel.
    """
    from ..cracks import CRACK_MARGIN_PX, as_cracks, segments_cross

    cracks = as_cracks(cracks)
    mask = None if region_mask is None else np.asarray(region_mask, dtype=bool)
    if mask is not None and mask.ndim != 2:
        raise ValueError(f"region_mask must be an (H, W) bool array, got shape {mask.shape}")
    pl, pr = as_points(points_left), as_points(points_right)
    p = np.asarray(params, dtype=np.float64)
    subset = odd_int(subset, "subset", detail=" (e.g. 21)")
    m = pl.shape[0]
    if pr.shape[0] != m or p.ndim != 2 or p.shape[0] != m or p.shape[1] not in (6, 12):
        raise ValueError(f"points_left, points_right and params must have M rows (params (M, 6) or (M, 12)); got "
                         f"{pl.shape}, {pr.shape}, {p.shape}")
    half = p.shape[1] // 2
    u, ux, uy = p[:, 0], p[:, 1], p[:, 2]
    v, vx, vy = p[:, half], p[:, half + 1], p[:, half + 2]
    a, b, c, d = 1.0 + ux, uy, vx, 1.0 + vy  # I + G
    det = a * d - b * c
    usable = np.isfinite(det) & (np.abs(det) > 1e-6) & np.all(np.isfinite(p), axis=1)
    det = np.where(usable, det, 1.0)
    cl = round_half_away(pl).astype(np.float64)
    cr = round_half_away(pr).astype(np.float64)
    di, dj = subset_offsets(subset)
    h_l, w_l = mask.shape if mask is not None else (0, 0)
    h_r, w_r = int(right_shape[0]), int(right_shape[1])
    out = np.zeros((m, subset * subset), dtype=bool)
    for start in range(0, m, 4096):  # bounded memory: 4096 x S^2 at a time
        s = slice(start, start + 4096)
        # (c_r + e) - c_l - (u, v), then (I + G)^-1
        rx = (cr[s, :1] + di[None, :]) - cl[s, :1] - np.where(usable[s], u[s], 0.0)[:, None]
        ry = (cr[s, 1:] + dj[None, :]) - cl[s, 1:] - np.where(usable[s], v[s], 0.0)[:, None]
        inv = 1.0 / det[s][:, None]
        dx = (d[s][:, None] * rx - b[s][:, None] * ry) * inv
        dy = (-c[s][:, None] * rx + a[s][:, None] * ry) * inv
        xf = cl[s, :1] + np.where(np.isfinite(dx), dx, -1e9)
        yf = cl[s, 1:] + np.where(np.isfinite(dy), dy, -1e9)
        # kept when the 4 left pixels around the mapped position are all in the region (module docstring)
        x0, y0 = np.floor(xf).astype(np.int64), np.floor(yf).astype(np.int64)
        kept = np.ones(x0.shape, dtype=bool)
        for ox, oy in (((0, 0), (0, 1), (1, 0), (1, 1)) if mask is not None else ()):
            xl, yl = x0 + ox, y0 + oy
            inside_l = (xl >= 0) & (xl < w_l) & (yl >= 0) & (yl < h_l)
            k = np.zeros(xl.shape, dtype=bool)
            k[inside_l] = mask[yl[inside_l], xl[inside_l]]
            kept &= k
        xr = cr[s, :1].astype(np.int64) + di[None, :]
        yr = cr[s, 1:].astype(np.int64) + dj[None, :]
        inside_r = (xr >= 0) & (xr < w_r) & (yr >= 0) & (yr < h_r)
        if cracks:  # across a crack from the POI, or within the margin of one (left reference px)
            q = np.stack([xf, yf], axis=-1)
            kept &= ~segments_cross(pl[s, None, :], q, cracks) & ~_near(q, cracks, CRACK_MARGIN_PX)
        out[s] = kept & inside_r & usable[s][:, None]
    return out


def _near(positions, cracks, margin: float) -> np.ndarray:
    """``(...)`` bool: whether each position ``(..., 2)`` px lies nearer than ``margin`` px to a crack segment."""
    from ..cracks import _all_segments

    q = np.asarray(positions, np.float64)
    out = np.zeros(q.shape[:-1], bool)
    a, b = _all_segments(cracks)
    for a_s, b_s in zip(a, b):
        ab = b_s - a_s
        t = np.clip(((q[..., 0] - a_s[0]) * ab[0] + (q[..., 1] - a_s[1]) * ab[1]) / (ab[0] ** 2 + ab[1] ** 2), 0.0, 1.0)
        out |= np.hypot(a_s[0] + t * ab[0] - q[..., 0], a_s[1] + t * ab[1] - q[..., 1]) < margin
    return out


def right_tracking_pixel_masks(roi, shape, subset_mask: str, points_left, points_right, params,
                               subset: int, cracks=None) -> np.ndarray | None:
    """The pixel masks of the right temporal track: ``(M, S*S)`` bool, or None when no pixel is masked.

    ``roi`` (any ROI form, in the left reference image) masks when ``subset_mask`` is ``"region"`` and it is a
    mask or a polygon (:func:`dic.correlation.subset_masks.region_pixel_mask`, shrunk by
    :data:`~dic.correlation.subset_masks.REGION_MARGIN_PX` as the left subsets' masks are); ``shape`` (H, W):
    the images'; the matched points, their match warps and ``cracks`` (declared cracks, left reference px: masked
    in any case) as :func:`mapped_pixel_masks`. None also when every pixel is kept (the unmasked kernels then run, bit for bit as without masks).
    """
    subset_mask = check_subset_mask(subset_mask)
    region_mask = region_pixel_mask(roi, shape) if subset_mask == "region" else None
    if region_mask is None and not cracks:
        return None
    if region_mask is not None:
        region_mask = shrink_region(region_mask, REGION_MARGIN_PX)
    kept = mapped_pixel_masks(region_mask, shape, points_left, points_right, params, subset, cracks=cracks)
    return None if kept.all() else kept
