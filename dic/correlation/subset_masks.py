"""Per-POI pixel masks: which pixels of each reference subset belong to the specimen.

A subset that overlaps a hole, the background beyond a free edge, or the other side of a declared
crack is correlated on the pixels it keeps only (:mod:`kernels.icgn_masked`: the reference mean and
norm of the ZNSSD, the Hessian, the steepest-descent images and the criterion over the kept pixels).
This module builds the masks on the host; the kernels read them as ``(N, S*S)`` ``uint8``.

Pixel order of one POI's row (the kernels' order): the subset of size ``S = 2r + 1`` around the POI
``(x, y)`` covers the integer pixels ``(X + i, Y + j)``, ``i, j = -r..r``, with ``X, Y`` the POI
rounded half away from zero (:func:`kernels.conventions.round_half_away`, the kernels' rounding);
entry ``(j + r) * S + (i + r)`` of the row is pixel ``(X + i, Y + j)`` (row-major, x fastest).

What a mask comes from (docs/dic2d.md, "Holes, edges and masks"):

* the region of a run (:func:`region_pixel_mask`): a mask array or image, a polygon, and the
  excluded shapes folded into them; a plain box ROI chooses where POIs are and masks no pixel;
* ``blocked``: pixels to drop per POI whatever the region says (declared cracks: the pixels on the
  far side of a crack from the POI).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from kernels.checks import as_points, odd_int
from kernels.conventions import round_half_away

from .points import Region, _inside_polygon, image_shape, region

__all__ = ["subset_pixel_masks", "region_pixel_mask", "kept_fraction", "kept_textured_fraction", "subset_offsets",
           "SUBSET_MASKS", "check_subset_mask", "tracking_pixel_masks", "shrink_region", "REGION_MARGIN_PX",
           "check_min_kept_fraction"]

#: the choices of ``subset_mask`` (Tracker, track_sequence, ``specula track --subset-mask``): "region" masks
#: subsets by a mask or polygon region (the default), "none" correlates every subset pixel (before the option)
SUBSET_MASKS = ("region", "none")


#: the region's pixels within this distance (px, 8-connected) of its outline are not kept by
#: :func:`tracking_pixel_masks`: their grey level and B-spline gradient mix in what lies beyond the edge
#: (the imaging blur and the spline's support). Measured (bench/holes.py, docs/dic2d.md "Holes, edges and
#: masks"): with a textured background behind a hole, the kept edge points' RMS error is 2.5-3.7 x the
#: interior's with the region as given and 1.4-1.7 x with 1 px less; on a featureless background both
#: stay below 1.7 x.
REGION_MARGIN_PX = 1


def shrink_region(region_mask, margin_px: int) -> np.ndarray:
    """``region_mask`` (H, W) bool less its pixels within ``margin_px`` px (8-connected: a 3x3 erosion per
    px) of its outline; the image border is not an outline (pixels beyond it count as inside)."""
    from scipy.ndimage import binary_erosion

    m = np.asarray(region_mask, dtype=bool)
    if margin_px <= 0:
        return m
    return binary_erosion(m, structure=np.ones((3, 3), bool), iterations=int(margin_px), border_value=1)


def check_min_kept_fraction(fraction) -> float:
    """``fraction`` as a float in (0, 1] (the minimum kept fraction of a masked subset), else ``ValueError``."""
    if isinstance(fraction, bool) or not isinstance(fraction, (int, float, np.floating, np.integer)) \
            or not np.isfinite(fraction) or not 0.0 < fraction <= 1.0:
        raise ValueError(f"min_kept_fraction must be a number in (0, 1] (the fraction of a subset's pixels it "
                         f"must keep), got {fraction!r}")
    return float(fraction)


def check_subset_mask(subset_mask) -> str:
    """``subset_mask`` as one of :data:`SUBSET_MASKS`, else ``ValueError``."""
    if not isinstance(subset_mask, str) or subset_mask not in SUBSET_MASKS:
        raise ValueError(f"subset_mask must be one of {SUBSET_MASKS} (\"region\": subsets keep the pixels of a mask or "
                         f"polygon ROI; \"none\": every pixel), got {subset_mask!r}")
    return subset_mask


def tracking_pixel_masks(points, subset: int, shape, roi, subset_mask: str = "region",
                         blocked_pixels=None) -> np.ndarray | None:
    """The pixel masks a tracker uses: ``(N, S*S)`` bool, or None when no pixel is masked.

    ``roi`` (any ROI form) masks the subsets when ``subset_mask`` is ``"region"`` and it is a mask or a
    polygon (:func:`region_pixel_mask`), shrunk by :data:`REGION_MARGIN_PX` (:func:`shrink_region`); ``blocked_pixels`` ((N, S*S) bool or a callable
    ``(points, subset) -> array``) drops pixels in any case. None when neither applies (or when every
    pixel is kept: the unmasked kernels then run, bit for bit as without masks).
    """
    subset_mask = check_subset_mask(subset_mask)
    pts = as_points(points)
    region_mask = region_pixel_mask(roi, shape) if subset_mask == "region" else None
    if region_mask is not None:
        region_mask = shrink_region(region_mask, REGION_MARGIN_PX)
    blocked = blocked_pixels(pts, subset) if callable(blocked_pixels) else blocked_pixels
    if region_mask is None and blocked is None:
        return None
    kept = subset_pixel_masks(pts, subset, region_mask, blocked=blocked)
    return None if kept.all() else kept


def subset_offsets(subset: int) -> tuple[np.ndarray, np.ndarray]:
    """``(di, dj)``, each ``(S*S,)`` int64: the pixel offsets from the rounded POI of the entries of a
    mask row (row-major, x fastest: entry ``(j + r) * S + (i + r)`` is offset ``(i, j)``)."""
    subset = odd_int(subset, "subset", detail=" (e.g. 21)")
    r = subset // 2
    dj, di = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1), indexing="ij")
    return di.ravel(), dj.ravel()


def region_pixel_mask(roi, shape) -> np.ndarray | None:
    """The pixels of the region ``roi`` as an ``(H, W)`` bool array, or None when it masks no pixel.

    ``roi``: any ROI form of :mod:`dic.correlation.points` (or a :class:`~dic.correlation.points.Region`).
    A mask (array or image file) is returned as it is (non-zero = specimen); a polygon is rasterised
    with the POI rule (a pixel is inside when its centre is inside the polygon or on its edge); excluded
    shapes (holes, notches: a region's ``exclude``) are taken out. A plain box and None return None: a box
    chooses where the POIs are, it does not describe the specimen's outline (with excluded shapes, the
    whole image less the shapes).
    """
    h, w = image_shape(shape)
    reg = region(roi, (h, w))
    exclude = tuple(getattr(reg, "exclude", ()))  # excluded shapes (holes, notches) of a region, where it has them
    if reg is None or (reg.kind == "box" and not exclude):
        return None
    if hasattr(reg, "pixel_mask"):  # the region's own rasterisation (the POI rule at every pixel centre)
        # a box with excluded shapes: the shapes describe the specimen, the box's sides do not
        target = replace(reg, kind="image", data=None) if reg.kind == "box" else reg
        return np.ascontiguousarray(target.pixel_mask((h, w)), dtype=bool)
    if reg.kind == "mask":
        return np.ascontiguousarray(reg.data, dtype=bool)
    yy, xx = np.mgrid[0:h, 0:w]
    centres = np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float64)
    return _inside_polygon(centres, np.asarray(reg.data, np.float64)).reshape(h, w)


def subset_pixel_masks(points, subset: int, region_mask, *, blocked=None) -> np.ndarray:
    """Which pixels of each POI's reference subset are kept: ``(N, S*S)`` bool (module docstring: order).

    Parameters
    ----------
    points : (N, 2) POIs ``(x, y)`` px (integer or sub-pixel).
    subset : odd int >= 3, the subset size S (px).
    region_mask : (H, W) bool array (non-zero = specimen) or None (every pixel kept: the image size is
        not known then; IC-GN refuses a subset that leaves the image as OUT_OF_BOUNDS anyway). With a
        mask, pixels outside the image are never kept.
    blocked : (N, S*S) bool array, optional
        Pixels to drop for each POI (True = dropped) whatever ``region_mask`` says, e.g. the pixels
        beyond a declared crack.

    Returns
    -------
    (N, S*S) bool: True where the pixel lies in the image, in ``region_mask`` and is not ``blocked``.
    """
    pts = as_points(points)
    subset = odd_int(subset, "subset", detail=" (e.g. 21)")
    n = pts.shape[0]
    npx = subset * subset
    if region_mask is None:
        mask = None
    else:
        if isinstance(region_mask, Region):
            raise ValueError("region_mask must be an (H, W) bool array; turn a Region into one with region_pixel_mask()")
        mask = np.asarray(region_mask)
        if mask.ndim != 2 or mask.shape[0] < 1 or mask.shape[1] < 1:
            raise ValueError(f"region_mask must be a 2-D (H, W) array of the image's shape, got shape {mask.shape}")
        mask = mask != 0
    if blocked is not None:
        blocked = np.asarray(blocked)
        if blocked.shape != (n, npx):
            raise ValueError(f"blocked must have shape (N, subset*subset) = {(n, npx)}, got {blocked.shape}")
        if blocked.dtype != bool:
            raise ValueError(f"blocked must be a bool array (True = pixel dropped), got dtype {blocked.dtype}")
    di, dj = subset_offsets(subset)
    centre = round_half_away(pts).astype(np.int64)
    xs = centre[:, :1] + di[None, :]
    ys = centre[:, 1:] + dj[None, :]
    if mask is None:
        kept = np.ones((n, npx), dtype=bool)
        if blocked is None:
            return kept
    else:
        h, w = mask.shape
        inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
        kept = np.zeros((n, npx), dtype=bool)
        kept[inside] = mask[ys[inside], xs[inside]]
    if blocked is not None:
        kept &= ~blocked
    return kept


def kept_fraction(masks) -> np.ndarray:
    """(N,) float64: the fraction of each subset's pixels that a mask of :func:`subset_pixel_masks` keeps."""
    m = np.asarray(masks)
    if m.ndim != 2 or m.shape[1] < 1:
        raise ValueError(f"masks must be (N, S*S), got shape {m.shape}")
    return m.astype(bool).mean(axis=1)


def kept_textured_fraction(reference_image, points, subset: int, masks) -> np.ndarray:
    """(N,) float64: the fraction of each subset's *kept* pixels that carry texture
    (:func:`dic.correlation.plausibility.textured_pixels`), 0 where a subset keeps none: the textured
    fraction of a masked subset, for the implausible-warp rule (:mod:`dic.correlation.plausibility`)."""
    from .plausibility import textured_pixels

    pts = as_points(points)
    subset = odd_int(subset, "subset", detail=" (e.g. 21)")
    m = np.asarray(masks, dtype=bool)
    if m.shape != (pts.shape[0], subset * subset):
        raise ValueError(f"masks must have shape (N, subset*subset) = {(pts.shape[0], subset * subset)}, got {m.shape}")
    textured = textured_pixels(reference_image)
    h, w = textured.shape
    di, dj = subset_offsets(subset)
    centre = round_half_away(pts).astype(np.int64)
    out = np.zeros(pts.shape[0], dtype=np.float64)
    for start in range(0, pts.shape[0], 4096):  # bounded memory: 4096 x S^2 indices at a time
        c = centre[start:start + 4096]
        xs = c[:, :1] + di[None, :]
        ys = c[:, 1:] + dj[None, :]
        inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
        tex = np.zeros(xs.shape, dtype=bool)
        tex[inside] = textured[ys[inside], xs[inside]]
        kept = m[start:start + 4096]
        n_kept = kept.sum(axis=1)
        out[start:start + 4096] = np.where(n_kept > 0, (tex & kept).sum(axis=1) / np.maximum(n_kept, 1), 0.0)
    return out
