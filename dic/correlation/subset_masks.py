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
           "check_min_kept_fraction", "carry_region_mask"]

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


def carry_region_mask(region_mask, points0, params, usable, *, reach: int | None = None, cracks=()) -> np.ndarray:
    """A region's pixels carried from the reference image into a later frame's image by a measured field.

    A moved reference (:class:`dic.correlation.lagrangian.MovedReference`) tracks from frame ``r``; the
    specimen (its holes and free edges) has moved with the material there, so its region is carried
    with the displacement field measured in frame ``r``: every pixel ``x`` of frame ``r`` is mapped back
    to the reference image through the inverse of the local affine warp of the nearest usable POI
    (nearest by its moved position ``X0 + d(X0)``, one not across a carried crack when ``cracks`` are
    given), ``X = X0 + (I + G)^-1 (x - X0 - d)``, and keeps the value of ``region_mask`` at the pixel
    nearest to ``X`` (a pixel mapped outside the reference image is not kept). Second-order terms are
    left out: within the half POI spacing of the nearest point they move ``X`` by a few thousandths of a px.

    Parameters
    ----------
    region_mask : (H, W) array, non-zero = specimen, in the reference image (the region as given; the
        tracker of frame ``r`` removes its 1 px rim, :data:`REGION_MARGIN_PX`, there). Frame ``r`` has
        the same size.
    points0 : (N, 2) px, the POIs in the reference image.
    params : (N, 6|12), frame ``r``'s Lagrangian parameters at ``points0`` (the filled ones of a moved
        reference, :attr:`~dic.correlation.lagrangian.MovedReference.params`).
    usable : (N,) bool, the points whose parameters carry the region (non-finite rows are left out too).
    reach : int, optional
        Only the pixels within ``reach`` px (each axis) of a usable moved point are carried (the others,
        which no subset of frame ``r`` reaches, are False); default: every pixel.
    cracks : the declared cracks carried into frame ``r`` (:func:`dic.cracks.carry_cracks`), optional.

    Returns
    -------
    (H, W) bool, the region in frame ``r``'s image.
    """
    m = np.asarray(region_mask)
    if m.ndim != 2 or m.shape[0] < 1 or m.shape[1] < 1:
        raise ValueError(f"region_mask must be a 2-D (H, W) array, got shape {m.shape}")
    m = m != 0
    pts0 = as_points(points0)
    p = np.asarray(params, np.float64)
    ok = np.asarray(usable, bool)
    if p.ndim != 2 or p.shape != (pts0.shape[0], p.shape[1]) or p.shape[1] not in (6, 12) \
            or ok.shape != (pts0.shape[0],):
        raise ValueError(f"carry_region_mask needs points0 (N, 2), params (N, 6|12) and usable (N,) of the same N, "
                         f"got {pts0.shape}, {p.shape} and {ok.shape}")
    ok = ok & np.all(np.isfinite(p), axis=1)
    if not np.any(ok):
        raise ValueError("no usable point to carry the region with")
    h = p.shape[1] // 2
    d = np.stack([p[ok, 0], p[ok, h]], axis=1)
    F = np.stack([p[ok, 1:3], p[ok, h + 1:h + 3]], axis=1) + np.eye(2)[None]  # (M, 2, 2): I + G
    with np.errstate(all="ignore"):
        Finv = np.linalg.inv(F)
    x0 = pts0[ok]
    moved = x0 + d
    from scipy.spatial import cKDTree

    from ..cracks import as_cracks, segments_cross

    cracks = as_cracks(cracks)
    tree = cKDTree(moved)
    H, W = m.shape
    out = np.zeros((H, W), dtype=bool)
    if reach is None:
        x_lo, y_lo, x_hi, y_hi = 0, 0, W - 1, H - 1
    else:
        lo = np.floor(moved.min(axis=0)).astype(int) - int(reach) - 1
        hi = np.ceil(moved.max(axis=0)).astype(int) + int(reach) + 1
        x_lo, y_lo = max(lo[0], 0), max(lo[1], 0)
        x_hi, y_hi = min(hi[0], W - 1), min(hi[1], H - 1)
        if x_lo > x_hi or y_lo > y_hi:
            return out
    xs = np.arange(x_lo, x_hi + 1)
    k = min(4, moved.shape[0])
    crack_tree = None
    if cracks:  # the cracks sampled at most 0.5 px apart: which pixels lie near one (a k-d tree of the samples)
        samples = []
        for c in cracks:
            for a, b in zip(*c.segments):
                n_s = max(1, int(np.ceil(np.hypot(*(b - a)) / 0.5)))
                samples.append(a + np.linspace(0.0, 1.0, n_s + 1)[:, None] * (b - a))
        crack_tree = cKDTree(np.concatenate(samples))
    rows = max(1, 131072 // xs.size)
    for y0 in range(y_lo, y_hi + 1, rows):
        yy, xx = np.meshgrid(np.arange(y0, min(y0 + rows, y_hi + 1)), xs, indexing="ij")
        pix = np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float64)
        dist, j = tree.query(pix, k=1)
        if crack_tree is not None:
            # the segment from a pixel to its nearest point can cross a crack only where the crack comes within
            # that distance of the pixel (the samples are within 0.25 px of the crack): there, the nearest point
            # on the pixel's side of every carried crack (else the nearest)
            dc, _ = crack_tree.query(pix, distance_upper_bound=float(dist.max()) + 1.0)
            maybe = np.flatnonzero(dc <= dist + 0.5)
            if maybe.size and k > 1:
                _, jj = tree.query(pix[maybe], k=k)
                across = segments_cross(moved[jj], pix[maybe, None, :], cracks)
                j[maybe] = jj[np.arange(maybe.size), np.argmax(~across, axis=1)]
        X = x0[j] + np.einsum("nab,nb->na", Finv[j], pix - moved[j])
        with np.errstate(invalid="ignore"):
            Xi = round_half_away(X)
        inside = np.all(np.isfinite(Xi), axis=1)
        inside &= (Xi[:, 0] >= 0) & (Xi[:, 0] <= W - 1) & (Xi[:, 1] >= 0) & (Xi[:, 1] <= H - 1)
        kept = np.zeros(pix.shape[0], dtype=bool)
        idx = Xi[inside].astype(np.int64)
        kept[inside] = m[idx[:, 1], idx[:, 0]]
        out[yy, xx] = kept.reshape(yy.shape)
    return out
