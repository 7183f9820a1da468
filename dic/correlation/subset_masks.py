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

import numpy as np

from kernels.checks import as_points, odd_int
from kernels.conventions import round_half_away

from .points import Region, _inside_polygon, image_shape, region

__all__ = ["subset_pixel_masks", "region_pixel_mask", "kept_fraction", "subset_offsets"]


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
    with the POI rule (a pixel is inside when its centre is inside the polygon or on its edge). A box
    and None return None: a box chooses where the POIs are, it does not describe the specimen's outline.
    """
    h, w = image_shape(shape)
    reg = region(roi, (h, w))
    if reg is None or reg.kind == "box":
        return None
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
