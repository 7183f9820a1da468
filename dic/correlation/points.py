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
  image's size;
* a dict, the JSON form a result file stores (:meth:`Region.settings`): ``{"box": [x0, y0, x1, y1]}``,
  ``{"polygon": [[x, y], ...]}`` or ``{"mask": FILE}``, each with an optional ``"exclude"`` list, or
  ``{"exclude": [...]}`` alone (the whole image less the excluded shapes).

**Excluded shapes** (holes, notches, clamps) are taken out of any region: ``"exclude"`` is a list
of shapes, each ``{"circle": [cx, cy, r]}`` (px; a pixel centre at distance <= r is excluded),
``{"box": [x0, y0, x1, y1]}`` (inclusive bounds) or ``{"polygon": [[x, y], ...]}`` (>= 3 vertices;
inside or on the edge is excluded), or the command line's text form ``"circle:CX,CY,R"``,
``"box:X0,Y0,X1,Y1"``, ``"polygon:X1,Y1,X2,Y2,X3,Y3,..."`` (:func:`exclusion`). A POI is in the
region when its pixel is inside the region and in none of the excluded shapes. The exclusions are
part of the region: :func:`roi_mask` (POIs) and :meth:`Region.pixel_mask` (every pixel of the
image, the mask a subset's pixels are masked by) apply them, and the JSON form stores them.

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

__all__ = ["image_shape", "check_step", "lattice", "Exclusion", "exclusion", "EXCLUDE_FORMS", "Region", "region",
           "roi_mask", "grid", "grid_points", "as_points", "typical_spacing"]


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


#: the forms of one excluded shape, for messages
EXCLUDE_FORMS = ('circle:CX,CY,R, box:X0,Y0,X1,Y1 or polygon:X1,Y1,X2,Y2,X3,Y3,... (px), or {"circle": [cx, cy, r]}, '
                 '{"box": [x0, y0, x1, y1]} or {"polygon": [[x, y], ...]}')
_EXCLUDE_KINDS = ("circle", "box", "polygon")


@dataclass(frozen=True, eq=False)
class Exclusion:
    """A shape taken out of a region of interest (module docstring): ``kind`` ``"circle"`` (``data``
    ``(cx, cy, r)`` px; pixel centres at distance <= r are excluded), ``"box"`` (``(x0, y0, x1, y1)`` px,
    inclusive) or ``"polygon"`` (``(N, 2)`` vertices px; inside or on the edge is excluded). Build it
    with :func:`exclusion`, which checks the numbers."""

    kind: str
    data: object

    def describe(self) -> str:
        if self.kind == "polygon":
            return f"polygon of {len(self.data)} vertices"
        return f"{self.kind} {tuple(float(c) for c in self.data)}"

    def settings(self) -> dict:
        """JSON form: ``{"circle": [cx, cy, r]}``, ``{"box": [x0, y0, x1, y1]}`` or ``{"polygon": [[x, y], ...]}``."""
        if self.kind == "polygon":
            return {"polygon": np.asarray(self.data, np.float64).tolist()}
        return {self.kind: [float(c) for c in self.data]}

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: which of ``points`` (N, 2) px (pixel centres) the shape excludes."""
        points = np.asarray(points, dtype=np.float64)
        if self.kind == "circle":
            cx, cy, r = self.data
            return (points[:, 0] - cx) ** 2 + (points[:, 1] - cy) ** 2 <= r * r
        if self.kind == "polygon":
            return _inside_polygon(points, self.data)
        x0, y0, x1, y1 = self.data
        return (points[:, 0] >= x0) & (points[:, 0] <= x1) & (points[:, 1] >= y0) & (points[:, 1] <= y1)


def _numbers(values, what: str, given) -> list[float]:
    try:
        out = [float(c) for c in values]
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be numbers (px), got {given!r}") from None
    if not all(np.isfinite(out)):
        raise ValueError(f"{what} must be finite numbers (px), got {given!r}")
    return out


def _box(values, what: str, given) -> tuple[float, float, float, float]:
    """A checked inclusive box ``(x0, y0, x1, y1)`` px; ``what`` names it in messages."""
    c = _numbers(values, f"{what} (x0, y0, x1, y1)", given)
    if len(c) != 4:
        raise ValueError(f"{what} needs 4 numbers x0, y0, x1, y1 (px), got {len(c)}: {given!r}")
    x0, y0, x1, y1 = c
    if not (x1 >= x0 and y1 >= y0):
        raise ValueError(f"{what} (x0, y0, x1, y1) = {given!r} is empty (needs x1 >= x0 and y1 >= y0)")
    return x0, y0, x1, y1


def exclusion(shape) -> Exclusion:
    """One excluded shape from its text form (``"circle:CX,CY,R"``, ``"box:X0,Y0,X1,Y1"``,
    ``"polygon:X1,Y1,X2,Y2,X3,Y3,..."``, px; ``;`` may separate the polygon's vertices), its JSON form
    (``{"circle": [cx, cy, r]}``, ``{"box": [...]}``, ``{"polygon": [[x, y], ...]}``) or an
    :class:`Exclusion`. Raises ``ValueError`` starting with ``exclude`` and naming the forms."""
    if isinstance(shape, Exclusion):
        return shape
    if isinstance(shape, str):
        kind, sep, rest = shape.partition(":")
        kind = kind.strip().lower()
        if not sep or kind not in _EXCLUDE_KINDS:
            raise ValueError(f"exclude: {shape!r} is not a shape; give {EXCLUDE_FORMS}")
        parts = [p for p in rest.replace(";", ",").replace(" ", "").split(",") if p]
        coords = _numbers(parts, f"exclude {kind} {shape!r}: the coordinates", rest)
        if kind == "polygon":
            if len(coords) % 2:
                raise ValueError(f"exclude polygon {shape!r}: give x,y pairs (an even count of numbers), got {len(coords)}")
            coords = np.asarray(coords, dtype=np.float64).reshape(-1, 2)
        data = coords
    elif isinstance(shape, dict) and len(shape) == 1 and next(iter(shape)) in _EXCLUDE_KINDS:
        kind, data = next(iter(shape.items()))
    else:
        raise ValueError(f"exclude: {shape!r} is not a shape; give {EXCLUDE_FORMS}")
    if kind == "circle":
        c = _numbers(data if isinstance(data, (list, tuple, np.ndarray)) else [data], "exclude circle (cx, cy, r)", data)
        if len(c) != 3:
            raise ValueError(f"exclude circle needs 3 numbers cx, cy, r (px), got {len(c)}: {shape!r}")
        if not c[2] > 0:
            raise ValueError(f"exclude circle radius must be > 0 px, got {c[2]:g} in {shape!r}")
        return Exclusion("circle", tuple(c))
    if kind == "box":
        return Exclusion("box", _box(data if isinstance(data, (list, tuple, np.ndarray)) else [data], "exclude box", shape))
    try:
        v = np.asarray(data, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"exclude polygon must be [[x, y], ...] (px), got {data!r}") from None
    return Exclusion("polygon", _polygon(v, shape, what="exclude polygon"))


@dataclass(frozen=True, eq=False)
class Region:
    """A checked region of interest (see the module docstring): ``kind`` is ``"box"``, ``"polygon"``,
    ``"mask"`` or ``"image"`` (the whole image, with exclusions only); ``data`` the box ``(x0, y0, x1, y1)``,
    the (N, 2) vertices, the (H, W) bool mask or None; ``source`` the mask file it was read from (or
    None); ``exclude`` the :class:`Exclusion` shapes taken out of it."""

    kind: str
    data: object
    source: str | None = None
    exclude: tuple = ()

    def describe(self) -> str:
        if self.kind == "box":
            base = f"box {tuple(float(c) for c in self.data)}"
        elif self.kind == "polygon":
            base = f"polygon of {len(self.data)} vertices"
        elif self.kind == "image":
            base = "whole image"
        else:
            base = f"mask {self.source!r}" if self.source else "mask"
        if self.exclude:
            base += " less " + ", ".join(e.describe() for e in self.exclude)
        return base

    def settings(self):
        """JSON form for a result file's settings: the box as ``[x0, y0, x1, y1]``, a polygon as
        ``{"polygon": [[x, y], ...]}``, a mask as ``{"mask": path or "array", "sha256": ..., "shape": [H, W]}``;
        with exclusions the box is ``{"box": [...]}`` and each form gains ``"exclude": [shape, ...]``
        (:meth:`Exclusion.settings`; the whole image less exclusions is ``{"exclude": [...]}``). The
        form is itself a ``roi`` :func:`region` takes (a mask from its file)."""
        if self.kind == "box":
            base = [float(c) for c in self.data]
        elif self.kind == "polygon":
            base = {"polygon": np.asarray(self.data, np.float64).tolist()}
        elif self.kind == "image":
            base = {}
        else:
            mask = np.ascontiguousarray(self.data, dtype=bool)
            base = {"mask": self.source or "array", "sha256": _mask_digest(mask), "shape": list(mask.shape)}
        if not self.exclude:
            return base
        out = {"box": base} if self.kind == "box" else dict(base)
        out["exclude"] = [e.settings() for e in self.exclude]
        return out

    def pixel_mask(self, shape) -> np.ndarray:
        """(H, W) bool: every pixel of an image of ``shape`` that is in the region (inside it and in
        no excluded shape); the same rule as :func:`roi_mask` at each pixel centre (tested), each
        shape evaluated on the pixels of its bounding box only."""
        h, w = image_shape(shape)
        if self.kind == "mask":
            if np.shape(self.data) != (h, w):
                raise ValueError(f"roi mask must have the image shape {(h, w)}, got {np.shape(self.data)}")
            out = np.array(self.data, dtype=bool)
        elif self.kind == "image":
            out = np.ones((h, w), dtype=bool)
        else:
            out = np.zeros((h, w), dtype=bool)
            inside = Exclusion(self.kind, self.data)  # a box or a polygon: the same pixel test
            _paint(out, inside, True)
        for shape_ in self.exclude:
            _paint(out, shape_, False)
        return out


def _paint(out: np.ndarray, shape: Exclusion, value: bool) -> None:
    """Set ``out`` (H, W) to ``value`` at the pixels (centres) ``shape`` contains, within its bounding box."""
    h, w = out.shape
    if shape.kind == "circle":
        cx, cy, r = shape.data
        lo, hi = (cx - r, cy - r), (cx + r, cy + r)
    elif shape.kind == "box":
        lo, hi = shape.data[:2], shape.data[2:]
    else:
        v = np.asarray(shape.data)
        lo, hi = v.min(axis=0), v.max(axis=0)
    x0, y0 = max(int(np.ceil(lo[0])), 0), max(int(np.ceil(lo[1])), 0)
    x1, y1 = min(int(np.floor(hi[0])), w - 1), min(int(np.floor(hi[1])), h - 1)
    if x1 < x0 or y1 < y0:
        return
    if shape.kind == "box":  # inclusive bounds: exactly the pixels of the clipped box
        out[y0:y1 + 1, x0:x1 + 1] = value
        return
    if shape.kind == "polygon":
        out[y0:y1 + 1, x0:x1 + 1][_polygon_pixels(np.asarray(shape.data, np.float64), x0, y0, x1, y1)] = value
        return
    ys, xs = np.mgrid[y0:y1 + 1, x0:x1 + 1]
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    block = out[y0:y1 + 1, x0:x1 + 1]
    block[shape.contains(pts).reshape(block.shape)] = value


def _polygon_pixels(vertices: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """(y1 - y0 + 1, x1 - x0 + 1) bool: the pixel centres of the block ``[x0, x1] x [y0, y1]`` that
    :func:`_inside_polygon` finds inside ``vertices`` or on an edge, by scanlines: each edge toggles the
    parity of the pixels left of its crossing of each row it straddles (the same float expression as
    :func:`_inside_polygon`), and on-edge pixels are tested with the same exact cross product, at most
    one candidate per row of an edge (every row of a horizontal one). O(edges x rows + pixels)."""
    ny, nx = y1 - y0 + 1, x1 - x0 + 1
    toggles = np.zeros((ny, nx + 1), dtype=np.int8)
    edge = np.zeros((ny, nx), dtype=bool)
    py = np.arange(y0, y1 + 1, dtype=np.float64)
    rows = np.arange(ny)
    for (ax, ay), (bx, by) in zip(vertices, np.roll(vertices, -1, axis=0)):
        straddles = (ay > py) != (by > py)
        if np.any(straddles):
            yy = py[straddles]
            x_at = ax + (yy - ay) * (bx - ax) / (by - ay)
            k = np.clip(np.ceil(x_at) - x0, 0, nx).astype(np.intp)  # pixels px < x_at: columns [0, k)
            r = rows[straddles]
            toggles[r, 0] ^= 1
            np.bitwise_xor.at(toggles, (r, k), 1)
        on_rows = (py >= min(ay, by)) & (py <= max(ay, by))
        if not np.any(on_rows):
            continue
        yy, r = py[on_rows], rows[on_rows]
        if ay == by:  # horizontal: every pixel of the row between the ends
            cand_x = np.arange(max(np.ceil(min(ax, bx)), x0), min(np.floor(max(ax, bx)), x1) + 1)
            rr = np.repeat(r, cand_x.size)
            cx = np.tile(cand_x, r.size)
            cy = np.repeat(yy, cand_x.size)
        else:
            cx = np.round(ax + (yy - ay) * (bx - ax) / (by - ay))
            rr, cy = r, yy
        ok = (cx >= x0) & (cx <= x1)
        cx, cy, rr = cx[ok], cy[ok], rr[ok]
        cross = (cx - ax) * (by - ay) - (cy - ay) * (bx - ax)
        hit = ((cross == 0) & (cx >= min(ax, bx)) & (cx <= max(ax, bx)) & (cy >= min(ay, by)) & (cy <= max(ay, by)))
        edge[rr[hit], (cx[hit] - x0).astype(np.intp)] = True
    odd = (np.cumsum(toggles[:, :nx], axis=1, dtype=np.int64) & 1).astype(bool)
    return odd | edge


def _mask_digest(mask: np.ndarray) -> str:
    return hashlib.sha256(np.packbits(mask).tobytes() + repr(mask.shape).encode()).hexdigest()


_ROI_FORMS = ("a box (x0, y0, x1, y1) in px, a polygon [(x, y), ...] of >= 3 vertices, an (H, W) mask array, "
              'a mask image file, or a dict {"box" | "polygon" | "mask": ..., "exclude": [shape, ...]}')


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


def _polygon(vertices, roi, what: str = "roi polygon") -> np.ndarray:
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 2:
        if what != "roi polygon":
            raise ValueError(f"{what} must be >= 3 vertices [[x, y], ...] (px); got {roi!r}")
        raise ValueError(f"roi must be {_ROI_FORMS}; got {roi!r}")
    if v.shape[0] < 3:
        raise ValueError(f"{what} needs at least 3 vertices (x, y), got {v.shape[0]}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{what} vertices must be finite numbers (px)")
    centred = v - v.mean(axis=0)
    spread = np.linalg.svd(centred, compute_uv=False)
    if spread[1] <= 1e-12 * max(1.0, spread[0]):
        raise ValueError(f"{what} {str(v.tolist()):.200} has zero area (its vertices lie on one line)")
    x, y = v[:, 0], v[:, 1]
    if abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) < 1e-12 and not _edges_cross(v):
        # a signed area of 0 is also that of a bow-tie (two equal loops of opposite turn): kept, inside by the
        # even-odd rule; edges that only run back over each other enclose nothing
        raise ValueError(f"{what} {str(v.tolist()):.200} encloses no area (its edges run back over each other)")
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
    if isinstance(roi, dict):
        return _region_dict(roi, h, w)
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
    return Region("box", _box(arr, "roi box", roi))


def _region_dict(roi: dict, h: int, w: int) -> Region | None:
    """A region from its JSON form (:meth:`Region.settings`), exclusions included."""
    unknown = sorted(set(roi) - {"box", "polygon", "mask", "sha256", "shape", "exclude"})
    kinds = [k for k in ("box", "polygon", "mask") if k in roi]
    if unknown or len(kinds) > 1 or not (kinds or "exclude" in roi):
        raise ValueError(f"roi must be {_ROI_FORMS} (one of box, polygon, mask); got {roi!r}")
    shapes = roi.get("exclude", [])
    if isinstance(shapes, (str, dict)) or not isinstance(shapes, (list, tuple)):
        raise ValueError(f"roi 'exclude' must be a list of shapes ({EXCLUDE_FORMS}), got {shapes!r}")
    exclude = tuple(exclusion(e) for e in shapes)
    if not kinds:
        return Region("image", None, exclude=exclude) if exclude else None
    kind = kinds[0]
    if kind == "box":
        base = Region("box", _box(roi["box"] if isinstance(roi["box"], (list, tuple, np.ndarray)) else [roi["box"]],
                                  "roi box", roi["box"]))
    elif kind == "polygon":
        try:
            v = np.asarray(roi["polygon"], dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"roi polygon must be [[x, y], ...] (px), got {roi['polygon']!r}") from None
        base = Region("polygon", _polygon(v, roi["polygon"]))
    else:
        source = roi["mask"]
        if isinstance(source, np.ndarray):
            base = region(source, (h, w))
        elif not isinstance(source, (str, os.PathLike)) or source == "array":
            raise ValueError("roi mask: the stored form of a mask given as an array holds only its digest; "
                             "give the (H, W) mask array or its image file")
        else:
            base = Region("mask", _read_mask(source, h, w), os.fspath(source))
            if "sha256" in roi and roi["sha256"] != _mask_digest(base.data):
                raise ValueError(f"roi mask file {os.fspath(source)!r} differs from the mask the region was made "
                                 "with (its sha256 does not match)")
    return Region(base.kind, base.data, base.source, exclude)


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
    (non-zero inside), a mask image file, a dict with ``"exclude"`` shapes, or a :class:`Region`.
    Points in an excluded shape are outside. See the module docstring.
    """
    reg = region(roi, shape)
    n = points.shape[0]
    if reg is None:
        return np.ones(n, dtype=bool)
    if n == 0:
        return np.zeros(0, dtype=bool)
    if reg.kind == "mask":
        keep = reg.data[points[:, 1].astype(int), points[:, 0].astype(int)]
    elif reg.kind == "polygon":
        keep = _inside_polygon(points, reg.data)
    elif reg.kind == "image":
        keep = np.ones(n, dtype=bool)
    else:
        x0, y0, x1, y1 = reg.data
        keep = (points[:, 0] >= x0) & (points[:, 0] <= x1) & (points[:, 1] >= y0) & (points[:, 1] <= y1)
    for shape in reg.exclude:
        keep &= ~shape.contains(points)
    return keep


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
