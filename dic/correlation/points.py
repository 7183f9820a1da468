"""Points of interest (POIs) and regions of interest (ROIs), with one meaning for 2-D and stereo DIC.

A POI grid is the lattice ``x = margin, margin + step, ... < W - margin`` (same along y), row-major
(x varies fastest); :func:`tracking` uses ``margin = subset // 2`` so that every reference subset
fits in the image. An ROI is either

* a box ``(x0, y0, x1, y1)`` in px with **inclusive** bounds (``x1 >= x0``, ``y1 >= y0``; a box one
  POI wide is valid), or
* a mask: a 2-D array of the image's shape ``(H, W)``, non-zero (True) inside.

A POI is inside the ROI when its pixel is inside the box / the mask. The ROI never moves POIs: it
only selects lattice points. 2-D tracking (:func:`grid`) keeps only the POIs inside; stereo DIC
(:func:`grid_points`) keeps the whole lattice, so that strain windows stay regular, and
flags the POIs outside as not computed. Both call :func:`roi_mask`, so the rule is the same.
"""
from __future__ import annotations

import numpy as np

from kernels.checks import as_points, non_negative_int, positive_int

__all__ = ["image_shape", "check_step", "lattice", "roi_mask", "grid", "grid_points", "as_points",
           "typical_spacing"]


def image_shape(shape) -> tuple[int, int]:
    """``(H, W)`` from a shape tuple or from an array (its ``.shape``); positive ints."""
    if hasattr(shape, "shape") and not isinstance(shape, tuple):
        shape = tuple(shape.shape)
    try:
        h, w = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise ValueError(f"shape must be (H, W), got {shape!r}") from None
    if h <= 0 or w <= 0:
        raise ValueError(f"shape must be positive, got {(h, w)}")
    return h, w


def check_step(step) -> int:
    """The grid spacing as a positive int (px), or ValueError."""
    return positive_int(step, "step", detail=" number of pixels")


def _check_margin(margin) -> int:
    return 0 if margin is None else non_negative_int(margin, "margin")


def lattice(shape, step: int, *, margin: int | None = None) -> tuple[np.ndarray, tuple[int, int]]:
    """The full POI lattice: ``points (N, 2) float64 (x, y)`` row-major and ``grid_shape (ny, nx)``.

    Raises ValueError (containing "no POI" and "too small") when the image holds no lattice point.
    """
    h, w = image_shape(shape)
    step = check_step(step)
    margin = _check_margin(margin)
    xs = np.arange(margin, w - margin, step)
    ys = np.arange(margin, h - margin, step)
    if xs.size == 0 or ys.size == 0:
        raise ValueError(f"no POI left: a {w}x{h} px image is too small for a grid {margin} px from the borders "
                         f"(subsets of {2 * margin + 1} px), step {step}")
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1).astype(np.float64)
    return pts, (int(ys.size), int(xs.size))


def roi_mask(points: np.ndarray, roi, shape) -> np.ndarray:
    """(N,) bool: which of ``points`` (integer pixel positions, (N, 2)) lie inside ``roi``.

    ``roi``: None (everything), a box ``(x0, y0, x1, y1)`` px with inclusive bounds, or a 2-D mask
    array of the image shape ``(H, W)`` (non-zero inside). See the module docstring.
    """
    h, w = image_shape(shape)
    n = points.shape[0]
    if roi is None:
        return np.ones(n, dtype=bool)
    if isinstance(roi, np.ndarray) and roi.ndim == 2:
        if roi.shape != (h, w):
            raise ValueError(f"roi mask must have the image shape {(h, w)}, got {roi.shape}")
        mask = roi.astype(bool)
        if n == 0:
            return np.zeros(0, dtype=bool)
        return mask[points[:, 1].astype(int), points[:, 0].astype(int)]
    try:
        x0, y0, x1, y1 = (float(c) for c in np.asarray(roi, dtype=np.float64).ravel())
    except (TypeError, ValueError):
        raise ValueError(f"roi must be an (H, W) boolean mask or a box (x0, y0, x1, y1) in px, got {roi!r}") from None
    if not all(np.isfinite([x0, y0, x1, y1])):
        raise ValueError(f"roi box (x0, y0, x1, y1) must be finite, got {roi!r}")
    if not (x1 >= x0 and y1 >= y0):
        raise ValueError(f"roi box (x0, y0, x1, y1) = {roi!r} is empty (needs x1 >= x0 and y1 >= y0)")
    return (points[:, 0] >= x0) & (points[:, 0] <= x1) & (points[:, 1] >= y0) & (points[:, 1] <= y1)


def _empty_roi_error(roi, shape, step, margin) -> ValueError:
    what = "mask" if isinstance(roi, np.ndarray) and roi.ndim == 2 else f"box {roi!r}"
    return ValueError(f"no POI left: the ROI {what} contains no grid point (empty ROI) of the {shape[1]}x{shape[0]} "
                      f"px image at step {step}, margin {margin}; enlarge it or reduce step")


def grid(shape, step: int, *, margin: int | None = None, roi=None) -> np.ndarray:
    """POIs on a regular grid of integer pixels, only those inside ``roi``.

    Parameters
    ----------
    shape : (H, W) or a 2-D array (its shape is used)
    step : int >= 1
        Grid spacing (px), the same along x and y.
    margin : int, optional
        Distance of the first and last rows/columns from the image border (px); default 0.
        :func:`dic.track.track` uses ``subset // 2`` so that every subset fits in the image.
    roi : None, (H, W) mask, or (x0, y0, x1, y1) inclusive box (module docstring).

    Returns
    -------
    (N, 2) float64 ``(x, y)``, x varying fastest (row-major), starting at ``(margin, margin)``.

    Raises
    ------
    ValueError : bad step/margin/roi, or no POI left (image too small, empty ROI).
    """
    h, w = image_shape(shape)
    pts, _ = lattice((h, w), step, margin=margin)
    keep = roi_mask(pts, roi, (h, w))
    if not np.any(keep):
        raise _empty_roi_error(roi, (h, w), step, _check_margin(margin))
    return pts[keep]


def grid_points(shape, step: int, subset: int, roi=None) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
    """The whole lattice ``subset // 2`` px from the borders, its grid shape and the ROI flags.

    Returns ``points (N, 2) float64``, ``grid_shape (ny, nx)``, ``in_roi (N,) bool``. POIs outside
    the ROI stay in the lattice (stereo DIC flags them NOT_COMPUTED; strain windows stay regular).
    """
    h, w = image_shape(shape)
    margin = int(subset) // 2
    pts, grid_shape = lattice((h, w), step, margin=margin)
    in_roi = roi_mask(pts, roi, (h, w))
    if not np.any(in_roi):
        raise _empty_roi_error(roi, (h, w), step, margin)
    return pts, grid_shape, in_roi


def typical_spacing(points: np.ndarray, default: float = 10.0) -> float:
    """Median nearest-neighbour distance of scattered POIs (px), at least 1; ``default`` for < 2 points."""
    if points.shape[0] < 2:
        return default
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points, k=2)
    return float(max(np.median(d[:, 1]), 1.0))
