"""Points of interest (POIs) and regions of interest (ROIs), with one meaning for 2-D and stereo DIC.

A POI grid is the lattice ``x = margin, margin + step, ... < W - margin`` (same along y), row-major
(x varies fastest); :func:`tracking` uses ``margin = subset // 2`` so that every reference subset
fits in the image. An ROI is one of

* a box ``(x0, y0, x1, y1)`` in px with **inclusive** bounds (``x1 >= x0``, ``y1 >= y0``; a box one
  POI wide is valid): four numbers;
* a polygon: a sequence of at least 3 vertices ``[(x, y), ...]`` in px (an (N, 2) array or list of
  pairs; closed automatically; self-intersecting outlines follow the even-odd rule). A POI is
  inside when its pixel centre is inside the polygon **or on its edge** (the same answer as
  ``cv2.pointPolygonTest(...) >= 0``, tested; the edge is decided exactly for vertices in whole or
  half pixels);
* a mask: a 2-D array of the image's shape ``(H, W)``, non-zero (True) inside;
* a mask image file (path): read with :func:`kernels.images.read_image`, non-zero inside, of the
  image's size.

Pixel coordinates follow docs/conventions.md: pixel (0, 0) is the centre of the top-left pixel,
so a POI's pixel centre is its integer position. A POI is inside the ROI when its pixel is inside
the box / the polygon / the mask. The ROI never moves POIs: it only selects lattice points. 2-D
tracking (:func:`grid`) keeps only the POIs inside; stereo DIC (:func:`grid_points`) keeps the
whole lattice, so that strain windows stay regular, and flags the POIs outside as not computed.
Both call :func:`roi_mask`, so the rule is the same. :func:`region` checks and normalises an ROI
once (a mask file is read once) and :meth:`Region.settings` gives its JSON form for result files.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass

import numpy as np

from kernels.checks import as_points, non_negative_int, positive_int

__all__ = ["image_shape", "check_step", "lattice", "Region", "region", "roi_mask", "grid", "grid_points", "as_points",
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


@dataclass(frozen=True, eq=False)
class Region:
    """A checked region of interest (see the module docstring): ``kind`` is ``"box"``, ``"polygon"`` or
    ``"mask"``; ``data`` the box ``(x0, y0, x1, y1)``, the (N, 2) vertices or the (H, W) bool mask;
    ``source`` the mask file it was read from (or None)."""

    kind: str
    data: object
    source: str | None = None

    def describe(self) -> str:
        if self.kind == "box":
            return f"box {tuple(float(c) for c in self.data)}"
        if self.kind == "polygon":
            return f"polygon of {len(self.data)} vertices"
        return f"mask {self.source!r}" if self.source else "mask"

    def settings(self):
        """JSON form for a result file's settings: the box as ``[x0, y0, x1, y1]``, a polygon as
        ``{"polygon": [[x, y], ...]}``, a mask as ``{"mask": path or "array", "sha256": ..., "shape": [H, W]}``."""
        if self.kind == "box":
            return [float(c) for c in self.data]
        if self.kind == "polygon":
            return {"polygon": np.asarray(self.data, np.float64).tolist()}
        mask = np.ascontiguousarray(self.data, dtype=bool)
        digest = hashlib.sha256(np.packbits(mask).tobytes() + repr(mask.shape).encode()).hexdigest()
        return {"mask": self.source or "array", "sha256": digest, "shape": list(mask.shape)}


_ROI_FORMS = ("a box (x0, y0, x1, y1) in px, a polygon [(x, y), ...] of >= 3 vertices, an (H, W) mask array "
              "or a mask image file")


def _read_mask(path, h: int, w: int) -> np.ndarray:
    from kernels.images import read_image

    path = os.fspath(path)
    try:
        img = read_image(path)
    except ValueError as exc:
        raise ValueError(f"roi mask file: {exc}") from None
    if img.shape != (h, w):
        raise ValueError(f"roi mask file {path!r} is {img.shape[1]}x{img.shape[0]} px but the images are "
                         f"{w}x{h} px; the mask must have the image's size")
    return np.asarray(img) != 0


def _polygon(vertices, roi) -> np.ndarray:
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 2:
        raise ValueError(f"roi must be {_ROI_FORMS}; got {roi!r}")
    if v.shape[0] < 3:
        raise ValueError(f"roi polygon needs at least 3 vertices (x, y), got {v.shape[0]}")
    if not np.all(np.isfinite(v)):
        raise ValueError("roi polygon vertices must be finite numbers (px)")
    centred = v - v.mean(axis=0)
    spread = np.linalg.svd(centred, compute_uv=False)
    if spread[1] <= 1e-12 * max(1.0, spread[0]):
        raise ValueError(f"roi polygon {str(v.tolist()):.200} has zero area (its vertices lie on one line)")
    x, y = v[:, 0], v[:, 1]
    if abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) < 1e-12 and not _edges_cross(v):
        # a signed area of 0 is also that of a bow-tie (two equal loops of opposite turn): kept, inside by the
        # even-odd rule; edges that only run back over each other enclose nothing
        raise ValueError(f"roi polygon {str(v.tolist()):.200} encloses no area (its edges run back over each other)")
    return v


def _edges_cross(v: np.ndarray) -> bool:
    """Whether two non-adjacent edges of the closed polygon ``v`` (N, 2) cross properly (a self-intersecting
    polygon such as a bow-tie)."""
    a, b = v, np.roll(v, -1, axis=0)
    n = len(v)

    def side(p, q, r):  # sign of the turn p -> q -> r, broadcast over edges
        return np.sign((q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0]))

    for i in range(n):
        j = np.arange(i + 2, n)
        if i == 0:
            j = j[j != n - 1]  # the last edge is adjacent to the first
        if j.size == 0:
            continue
        d1, d2 = side(a[i], b[i], a[j]), side(a[i], b[i], b[j])
        d3, d4 = side(a[j], b[j], a[i][None]), side(a[j], b[j], b[i][None])
        if np.any((d1 * d2 < 0) & (d3 * d4 < 0)):
            return True
    return False


def region(roi, shape) -> Region | None:
    """Check ``roi`` (any form of the module docstring, or a :class:`Region`) for images of ``shape``
    ``(H, W)`` and return it as a :class:`Region` (None for None). Raises ``ValueError`` naming the
    accepted forms when ``roi`` is none of them."""
    h, w = image_shape(shape)
    if roi is None:
        return None
    if isinstance(roi, Region):
        if roi.kind == "mask" and np.shape(roi.data) != (h, w):
            raise ValueError(f"roi mask must have the image shape {(h, w)}, got {np.shape(roi.data)}")
        return roi
    if isinstance(roi, (str, os.PathLike)):
        return Region("mask", _read_mask(roi, h, w), os.fspath(roi))
    if isinstance(roi, np.ndarray) and roi.ndim == 2:
        is_polygon = (roi.shape != (h, w) and roi.shape[1] == 2
                      and np.issubdtype(roi.dtype, np.number) and roi.dtype != bool)
        if not is_polygon:
            if roi.shape != (h, w):
                raise ValueError(f"roi mask must have the image shape {(h, w)}, got {roi.shape}")
            return Region("mask", roi.astype(bool))
    try:
        arr = np.asarray(roi, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"roi must be {_ROI_FORMS}; got {roi!r}") from None
    if arr.ndim == 2:
        return Region("polygon", _polygon(arr, roi))
    if arr.shape != (4,):
        raise ValueError(f"roi must be {_ROI_FORMS}; got {roi!r}")
    x0, y0, x1, y1 = (float(c) for c in arr)
    if not all(np.isfinite([x0, y0, x1, y1])):
        raise ValueError(f"roi box (x0, y0, x1, y1) must be finite, got {roi!r}")
    if not (x1 >= x0 and y1 >= y0):
        raise ValueError(f"roi box (x0, y0, x1, y1) = {roi!r} is empty (needs x1 >= x0 and y1 >= y0)")
    return Region("box", (x0, y0, x1, y1))


def _inside_polygon(points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """(N,) bool: points inside the closed polygon (even-odd rule) or on one of its edges.

    Vectorised over the points, one pass per edge; float64 throughout, so a point on an edge is
    found exactly when the products of coordinates are exact (vertices in whole or half pixels, any
    image size). Checked against ``cv2.pointPolygonTest(..., False) >= 0`` in tests.
    """
    px, py = points[:, 0], points[:, 1]
    inside = np.zeros(points.shape[0], dtype=bool)
    on_edge = np.zeros(points.shape[0], dtype=bool)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    near = (px >= lo[0]) & (px <= hi[0]) & (py >= lo[1]) & (py <= hi[1])  # only these can be inside
    px, py = px[near], py[near]
    odd = np.zeros(px.size, dtype=bool)
    edge = np.zeros(px.size, dtype=bool)
    for (x0, y0), (x1, y1) in zip(vertices, np.roll(vertices, -1, axis=0)):
        cross = (px - x0) * (y1 - y0) - (py - y0) * (x1 - x0)
        edge |= ((cross == 0) & (px >= min(x0, x1)) & (px <= max(x0, x1)) & (py >= min(y0, y1))
                 & (py <= max(y0, y1)))
        straddles = (y0 > py) != (y1 > py)
        if np.any(straddles):
            with np.errstate(divide="ignore", invalid="ignore"):
                x_at = x0 + (py - y0) * (x1 - x0) / (y1 - y0)
            odd ^= straddles & (px < x_at)
    inside[near] = odd
    on_edge[near] = edge
    return inside | on_edge


def roi_mask(points: np.ndarray, roi, shape) -> np.ndarray:
    """(N,) bool: which of ``points`` (integer pixel positions, (N, 2)) lie inside ``roi``.

    ``roi``: None (everything), a box ``(x0, y0, x1, y1)`` px with inclusive bounds, a polygon
    (>= 3 vertices ``(x, y)``; inside or on the edge), a 2-D mask array of the image shape ``(H, W)``
    (non-zero inside), a mask image file, or a :class:`Region`. See the module docstring.
    """
    reg = region(roi, shape)
    n = points.shape[0]
    if reg is None:
        return np.ones(n, dtype=bool)
    if n == 0:
        return np.zeros(0, dtype=bool)
    if reg.kind == "mask":
        return reg.data[points[:, 1].astype(int), points[:, 0].astype(int)]
    if reg.kind == "polygon":
        return _inside_polygon(points, reg.data)
    x0, y0, x1, y1 = reg.data
    return (points[:, 0] >= x0) & (points[:, 0] <= x1) & (points[:, 1] >= y0) & (points[:, 1] <= y1)


def _empty_roi_error(roi, shape, step, margin) -> ValueError:
    reg = region(roi, shape)
    what = reg.describe() if reg is not None else "(none)"
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
        :func:`dic.track` uses ``subset // 2`` so that every subset fits in the image.
    roi : None, (x0, y0, x1, y1) inclusive box, polygon [(x, y), ...], (H, W) mask, mask image file
        or :class:`Region` (module docstring).

    Returns
    -------
    (N, 2) float64 ``(x, y)``, x varying fastest (row-major), starting at ``(margin, margin)``.

    Raises
    ------
    ValueError : bad step/margin/roi, or no POI left (image too small, empty ROI).
    """
    h, w = image_shape(shape)
    pts, _ = lattice((h, w), step, margin=margin)
    roi = region(roi, (h, w))
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
    roi = region(roi, (h, w))
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
