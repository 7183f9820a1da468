"""Values of a result at arbitrary points, from the points' grid cells, never across a hole.

The points of a Specula result lie on a regular grid (``x0 + i dx, y0 + j dy``; a subset of it
when a region excluded some: :func:`dic.grid_layout`). A query point is given a value
only from the **grid cell that contains it**, and only when every corner of that cell that the
value depends on is a point of the result and valid in the frame; otherwise the value is NaN
with a :class:`QueryStatus` that says why. Nothing is ever bridged across a hole, an excluded
region or invalid points.

* :class:`GridCells` — query positions in the grid's own coordinates (reference image px):
  bilinear interpolation in the cell, ``f = Σ w_k f_k`` with the weights
  ``(1-s)(1-t), s(1-t), (1-s)t, st`` of the corners, ``s, t`` in [0, 1] the position in the cell.
  Exact for fields linear in ``(x, y)``. A corner whose weight is 0 (a query on a grid line or
  a node) is not needed: a query on a valid node gives that node's value.
* :class:`TriangleCells` — query positions in other coordinates (stereo ``(X, Y)`` mm of each
  point): each grid cell whose four corners are points with finite coordinates is split into two
  triangles there, and the value is linear in the triangle that contains the query (exact for
  fields linear in those coordinates); the cell's four corners must be valid.
  Its fallback for points **not on a grid** (:meth:`TriangleCells.scattered`): a Delaunay
  triangulation of the points, without the triangles that have an edge longer than
  :data:`MAX_EDGE_SPACINGS` times the median edge (the typical point spacing), so that no
  triangle spans a hole or a gap; a triangle's three corners must be valid.

Declared cracks (:mod:`dic.cracks`, ``GridCells(points, cracks=...)``): a cell that a crack enters
(crosses one of its edges or holds one of its vertices) gives no value to a query that needs more than
one of its corners (:attr:`QueryStatus.CRACK`): nothing is interpolated across a crack.

Both separate what depends on the positions only (:meth:`locate`, computed once for the
queries of a file, since every frame has the same points) from the values of a frame
(:meth:`Located.evaluate`). Neither uses BLAS: a query costs a few array lookups, and locating
a query among triangles a k-d tree search.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

__all__ = ["QueryStatus", "GridCells", "TriangleCells", "Located", "MAX_EDGE_SPACINGS", "cells_for"]

#: scattered points: a Delaunay triangle with an edge longer than this many typical point spacings
#: (the median edge) gives no value (a grid cell's diagonal is sqrt(2) = 1.41 steps)
MAX_EDGE_SPACINGS = 1.5

# points filling fewer than 1 in this many nodes of their grid are taken for scattered points
_MAX_NODES_PER_POINT = 64

# a position this close to a grid line (in grid steps) or a triangle edge (barycentric) is on it
_SNAP = 1e-9


class QueryStatus(enum.IntEnum):
    """Why a query point has a value in a frame, or why not (one code per query point and frame)."""

    #: interpolated from the valid corners of the cell (or triangle) that contains the point
    OK = 0
    #: outside the grid of points (or outside the convex hull of scattered points)
    OUTSIDE = 1
    #: inside the grid, in a cell with a corner that is no point of the result: a hole, an
    #: excluded region (or between scattered points farther apart than MAX_EDGE_SPACINGS spacings)
    NO_POINTS = 2
    #: in a cell of points of which one the value depends on has no valid value in this frame
    #: (a failed correlation; for strain also too few neighbours for the fit)
    INVALID = 3
    #: in a grid cell that a declared crack cuts (dic.cracks): the corners lie on both sides of it
    CRACK = 4

    @property
    def reason(self) -> str:
        """The reason in words (used by the CLI)."""
        return _REASONS[self]


_REASONS = {
    QueryStatus.OK: "interpolated",
    QueryStatus.OUTSIDE: "outside the grid of points",
    QueryStatus.NO_POINTS: "in a hole or an excluded region (no points there)",
    QueryStatus.INVALID: "among points with no valid value in the frame",
    QueryStatus.CRACK: "in a grid cell cut by a declared crack",
}


@dataclass
class Located:
    """Where query points fall, independently of any frame's values.

    ``corners`` (M, C) int64 point indices (-1: none) and ``weights`` (M, C) float64 (the
    interpolation weights of the corners; rows with several candidates hold them one after the
    other, ``group`` (M, C) int64 numbering the candidate each column belongs to, -1 unused),
    ``support`` (M, G, S) int64 the points that must be valid for candidate g (-1 unused) and
    ``status`` (M,) int8 the geometric :class:`QueryStatus` (OK, OUTSIDE or NO_POINTS).
    """

    corners: np.ndarray
    weights: np.ndarray
    group: np.ndarray
    support: np.ndarray
    status: np.ndarray

    def evaluate(self, values, valid, present=None) -> tuple[np.ndarray, np.ndarray]:
        """The values at the query points in one frame.

        Parameters
        ----------
        values : (N,) or (N, k) float
            The frame's values at the points.
        valid : (N,) bool
            Which points have a valid value (non-finite values are not valid either).
        present : (N,) bool, optional
            Which points count as points at all: a query whose cell has a needed corner that is not
            present is NO_POINTS rather than INVALID (stereo points never computed, outside the
            region or on a featureless subset of the reference). Default: all.

        Returns
        -------
        (M, k) float64 values (NaN where there is none) and (M,) int8 :class:`QueryStatus` codes.
        """
        values = np.asarray(values, np.float64)
        values = values.reshape(values.shape[0], -1)
        valid = np.asarray(valid, bool) & np.all(np.isfinite(values), axis=1)
        M = self.status.shape[0]
        status = self.status.copy()
        out = np.full((M, values.shape[1]), np.nan)
        if M == 0:
            return out, status
        used = self.support >= 0  # (M, G, S)
        safe = np.where(used, self.support, 0)
        # a candidate is usable when it has support points and all of them are valid
        usable = np.all(~used | valid[safe], axis=2) & np.any(used, axis=2)
        if present is not None:
            # no candidate whose support points are all present: no points there
            whole = np.all(~used | np.asarray(present, bool)[safe], axis=2) & np.any(used, axis=2)
            status[(status == QueryStatus.OK) & ~whole.any(axis=1)] = QueryStatus.NO_POINTS
        chosen = np.argmax(usable, axis=1)  # the first usable candidate
        found = usable[np.arange(M), chosen] & (status == QueryStatus.OK)
        status[(status == QueryStatus.OK) & ~found] = QueryStatus.INVALID
        if found.any():
            rows = np.flatnonzero(found)
            cols = self.group[rows] == chosen[rows, None]  # (m, C) the chosen candidate's columns
            idx = self.corners[rows]
            w = np.where(cols, self.weights[rows], 0.0)
            gathered = values[np.where(idx < 0, 0, idx)]  # (m, C, k)
            gathered = np.where((w != 0.0)[..., None], gathered, 0.0)
            out[rows] = np.sum(w[..., None] * gathered, axis=1)
        return out, status


def _no_candidates(M: int, status) -> Located:
    return Located(corners=np.full((M, 1), -1, np.int64), weights=np.zeros((M, 1)), group=np.full((M, 1), -1, np.int64),
                   support=np.full((M, 1, 1), -1, np.int64), status=np.asarray(status, np.int8))


def _queries(query) -> np.ndarray:
    q = np.asarray(query, np.float64)
    if q.ndim == 1:
        q = q.reshape(-1, 2)
    if q.ndim != 2 or q.shape[1] != 2:
        raise ValueError(f"query points must be (M, 2) positions (x, y), got shape {q.shape}")
    return q


class GridCells:
    """The grid cells of points on a regular grid, for bilinear interpolation (module docstring).

    Parameters
    ----------
    points : (N, 2) float
        Positions on a regular grid or a subset of one (px); raises ``ValueError`` otherwise
        (:func:`dic.grid_layout`).
    cracks : optional
        Declared cracks (:mod:`dic.cracks`, reference px): the cells they cut give no value
        (:attr:`QueryStatus.CRACK`). Default: none.

    Attributes
    ----------
    points : (N, 2) float64 (read-only copy); ``origin`` (x0, y0) and ``step`` (dx, dy) of the grid;
    ``shape`` (rows, cols); ``node`` (rows, cols) int64, the point at each node (-1: none);
    ``cut`` (rows - 1, cols - 1) bool, the cells a crack cuts (None without cracks).
    """

    def __init__(self, points, *, cracks=None):
        from ._strain import grid_layout

        pts = np.array(points, dtype=np.float64, copy=True)
        index, shape, step = grid_layout(pts)
        if shape[0] * shape[1] > _MAX_NODES_PER_POINT * pts.shape[0] + 4096:
            # grid_layout's tolerance grows as the spacing shrinks: scattered points pass it with a
            # spacing of their smallest coordinate difference and a grid of billions of nodes
            raise ValueError(f"the points fill fewer than 1 in {_MAX_NODES_PER_POINT} nodes of their "
                             f"{shape[0]} x {shape[1]} grid: not a grid of points")
        pts.flags.writeable = False
        self.points = pts
        self.shape = shape
        self.step = (float(step[0]), float(step[1]))
        # the grid's first node: grid_layout counts from the smallest coordinate along each axis
        self.origin = (float(pts[:, 0].min()), float(pts[:, 1].min()))
        self.node = np.full(shape, -1, np.int64)
        self.node[index[:, 1], index[:, 0]] = np.arange(pts.shape[0])
        self.cut = _cut_cells(self.origin, self.step, self.shape, cracks)

    def __repr__(self) -> str:
        return (f"GridCells({self.points.shape[0]} points on a {self.shape[0]} x {self.shape[1]} grid, step "
                f"{self.step[0]:g} x {self.step[1]:g} px)")

    def matches(self, points) -> bool:
        """Whether ``points`` are this grid's points (same values, same order)."""
        pts = np.asarray(points)
        return pts.shape == self.points.shape and bool(np.array_equal(pts, self.points))

    def extent(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` of the grid (px)."""
        (x0, y0), (dx, dy), (rows, cols) = self.origin, self.step, self.shape
        return x0, x0 + (cols - 1) * dx, y0, y0 + (rows - 1) * dy

    def locate(self, query) -> Located:
        """The cell of each query position (M, 2) px, its corners and bilinear weights."""
        q = _queries(query)
        rows, cols = self.shape
        f = (q[:, 0] - self.origin[0]) / self.step[0]
        g = (q[:, 1] - self.origin[1]) / self.step[1]
        with np.errstate(invalid="ignore"):
            outside = ~(np.isfinite(f) & np.isfinite(g)) | (f < -_SNAP) | (f > cols - 1 + _SNAP) | \
                (g < -_SNAP) | (g > rows - 1 + _SNAP)
        f = np.clip(np.nan_to_num(f), 0, cols - 1)
        g = np.clip(np.nan_to_num(g), 0, rows - 1)
        i0 = np.minimum(np.floor(f), max(cols - 2, 0)).astype(np.int64)
        j0 = np.minimum(np.floor(g), max(rows - 2, 0)).astype(np.int64)
        s, t = f - i0, g - j0
        # on a grid line (to rounding): the corners across it are not needed
        s = np.where(s < _SNAP, 0.0, np.where(s > 1 - _SNAP, 1.0, s))
        t = np.where(t < _SNAP, 0.0, np.where(t > 1 - _SNAP, 1.0, t))
        i1, j1 = np.minimum(i0 + 1, cols - 1), np.minimum(j0 + 1, rows - 1)
        corners = np.stack([self.node[j0, i0], self.node[j0, i1], self.node[j1, i0], self.node[j1, i1]], axis=1)
        weights = np.stack([(1 - s) * (1 - t), s * (1 - t), (1 - s) * t, s * t], axis=1)
        needed = weights > 0
        missing = np.any(needed & (corners < 0), axis=1)
        status = np.where(outside, QueryStatus.OUTSIDE, np.where(missing, QueryStatus.NO_POINTS, QueryStatus.OK))
        if self.cut is not None and self.cut.size:
            cracked = self.cut[np.minimum(j0, rows - 2), np.minimum(i0, cols - 2)] & (np.count_nonzero(needed, axis=1) > 1)
            status = np.where((status == QueryStatus.OK) & cracked, QueryStatus.CRACK, status)
        corners = np.where(needed, corners, -1)
        weights = np.where(needed, weights, 0.0)
        group = np.where(needed, 0, -1)
        return Located(corners=corners, weights=weights, group=group, support=corners[:, None, :],
                       status=status.astype(np.int8))


class TriangleCells:
    """Triangles over which values are linear, each with the points that must be valid (module docstring).

    Build with :meth:`from_grid` (the cells of a grid, in other coordinates) or :meth:`scattered`
    (points on no grid).

    Parameters
    ----------
    xy : (N, 2) float
        The points' coordinates in the units of the queries (NaN: a point with no position).
    triangles : (T, 3) int
        Point indices of each triangle's corners.
    support : (T, S) int
        The points that must be valid for a triangle to give a value.
    """

    def __init__(self, xy, triangles, support):
        from scipy.spatial import cKDTree

        self.xy = np.asarray(xy, np.float64)
        self.triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
        self.support = np.asarray(support, np.int64).reshape(self.triangles.shape[0], -1)
        finite = np.all(np.isfinite(self.xy), axis=1)
        self._hull = _hull_equations(self.xy[finite])
        if self.triangles.shape[0]:
            corners = self.xy[self.triangles]  # (T, 3, 2)
            self._a = corners[:, 0]
            self._ab = corners[:, 1] - corners[:, 0]
            self._ac = corners[:, 2] - corners[:, 0]
            self._det = self._ab[:, 0] * self._ac[:, 1] - self._ab[:, 1] * self._ac[:, 0]
            centre = corners.mean(axis=1)
            self._radius = float(np.max(np.linalg.norm(corners - centre[:, None, :], axis=2))) * (1 + 1e-9)
            self._tree = cKDTree(centre)
        else:
            self._tree = None

    def __repr__(self) -> str:
        return f"TriangleCells({self.triangles.shape[0]} triangles over {self.xy.shape[0]} points)"

    def matches(self, xy) -> bool:
        """Whether ``xy`` are the coordinates these triangles were built on."""
        a = np.asarray(xy)
        return a.shape == self.xy.shape and bool(np.array_equal(a, self.xy, equal_nan=True))

    @classmethod
    def from_grid(cls, grid: GridCells, xy) -> TriangleCells:
        """The cells of ``grid`` whose four corners have finite ``xy`` (N, 2), two triangles each
        (split along the diagonal from the cell's first to its last corner); a cell's four corners
        are the support of both its triangles."""
        xy = np.asarray(xy, np.float64)
        node = grid.node
        c00, c10, c01, c11 = node[:-1, :-1], node[:-1, 1:], node[1:, :-1], node[1:, 1:]
        cells = np.stack([c00.ravel(), c10.ravel(), c01.ravel(), c11.ravel()], axis=1)
        finite = np.all(np.isfinite(xy), axis=1)
        keep = np.all(cells >= 0, axis=1)
        keep[keep] = np.all(finite[cells[keep]], axis=1)
        cells = cells[keep]
        triangles = np.concatenate([cells[:, [0, 1, 3]], cells[:, [0, 3, 2]]])
        return cls(xy, triangles, np.concatenate([cells, cells]))

    @classmethod
    def scattered(cls, xy) -> TriangleCells:
        """A Delaunay triangulation of the points with finite ``xy`` (N, 2), less every triangle with an
        edge longer than :data:`MAX_EDGE_SPACINGS` times the median edge (module docstring)."""
        from scipy.spatial import Delaunay, QhullError

        xy = np.asarray(xy, np.float64)
        finite = np.flatnonzero(np.all(np.isfinite(xy), axis=1))
        triangles = np.zeros((0, 3), np.int64)
        if finite.size >= 3:
            try:
                simplices = finite[Delaunay(xy[finite]).simplices]
            except (QhullError, ValueError):  # collinear or degenerate points
                simplices = triangles
            if simplices.shape[0]:
                c = xy[simplices]
                edges = np.linalg.norm(c - np.roll(c, 1, axis=1), axis=2)  # (T, 3)
                limit = MAX_EDGE_SPACINGS * float(np.median(edges))
                triangles = simplices[np.max(edges, axis=1) <= limit]
        return cls(xy, triangles, triangles)

    def locate(self, query) -> Located:
        """The triangles containing each query position (M, 2), with their barycentric weights."""
        q = _queries(query)
        M = q.shape[0]
        finite = np.all(np.isfinite(q), axis=1)
        inside_hull = finite & _inside(self._hull, q)
        status = np.where(inside_hull, QueryStatus.NO_POINTS, QueryStatus.OUTSIDE).astype(np.int8)
        if self._tree is None or not finite.any():
            return _no_candidates(M, status)
        lists = self._tree.query_ball_point(np.where(finite[:, None], q, 0.0), r=self._radius)
        counts = np.array([len(c) if ok else 0 for c, ok in zip(lists, finite)], np.int64)
        if counts.sum() == 0:
            return _no_candidates(M, status)
        qid = np.repeat(np.arange(M), counts)
        tid = np.concatenate([np.asarray(c, np.int64) for c, n in zip(lists, counts) if n])
        d = q[qid] - self._a[tid]
        det = self._det[tid]
        with np.errstate(invalid="ignore", divide="ignore"):
            s = (d[:, 0] * self._ac[tid, 1] - d[:, 1] * self._ac[tid, 0]) / det
            t = (self._ab[tid, 0] * d[:, 1] - self._ab[tid, 1] * d[:, 0]) / det
        bary = np.stack([1 - s - t, s, t], axis=1)
        inside = (det != 0) & np.all(bary >= -_SNAP, axis=1)
        qid, tid, bary = qid[inside], tid[inside], np.clip(bary[inside], 0.0, 1.0)
        bary /= bary.sum(axis=1, keepdims=True)
        if qid.size == 0:
            return _no_candidates(M, status)
        order = np.argsort(qid, kind="stable")
        qid, tid, bary = qid[order], tid[order], bary[order]
        starts = np.searchsorted(qid, np.arange(M))
        rank = np.arange(qid.size) - starts[qid]  # the candidate's number within its query
        G = int(rank.max()) + 1
        S = self.support.shape[1]
        corners = np.full((M, G * 3), -1, np.int64)
        weights = np.zeros((M, G * 3))
        group = np.full((M, G * 3), -1, np.int64)
        support = np.full((M, G, S), -1, np.int64)
        for k in range(3):
            corners[qid, rank * 3 + k] = self.triangles[tid, k]
            weights[qid, rank * 3 + k] = bary[:, k]
            group[qid, rank * 3 + k] = rank
        support[qid, rank] = self.support[tid]
        status[np.isin(np.arange(M), qid)] = QueryStatus.OK
        return Located(corners=corners, weights=weights, group=group, support=support, status=status)


def _cut_cells(origin, step, shape, cracks) -> np.ndarray | None:
    """(rows - 1, cols - 1) bool: the grid cells that a crack enters (crosses an edge of, or holds a vertex of)."""
    from .cracks import as_cracks, segments_cross

    cracks = as_cracks(cracks)
    if not cracks:
        return None
    rows, cols = shape
    if rows < 2 or cols < 2:
        return np.zeros((max(rows - 1, 0), max(cols - 1, 0)), bool)
    x = origin[0] + step[0] * np.arange(cols)
    y = origin[1] + step[1] * np.arange(rows)
    X, Y = np.meshgrid(x, y)  # (rows, cols)
    nodes = np.stack([X, Y], axis=-1)
    horizontal = segments_cross(nodes[:, :-1], nodes[:, 1:], cracks)  # (rows, cols - 1)
    vertical = segments_cross(nodes[:-1, :], nodes[1:, :], cracks)  # (rows - 1, cols)
    cut = horizontal[:-1] | horizontal[1:] | vertical[:, :-1] | vertical[:, 1:]
    for c in cracks:  # a crack that ends inside a cell without crossing its edges
        f = (c.vertices[:, 0] - origin[0]) / step[0]
        g = (c.vertices[:, 1] - origin[1]) / step[1]
        inside = (f >= 0) & (f <= cols - 1) & (g >= 0) & (g <= rows - 1)
        cut[np.minimum(g[inside].astype(np.int64), rows - 2), np.minimum(f[inside].astype(np.int64), cols - 2)] = True
    return cut


def _hull_equations(xy) -> np.ndarray | None:
    """The convex hull's facet equations ``(n_x, n_y, c)`` (inside: ``n·p + c <= 0``), or None."""
    from scipy.spatial import ConvexHull, QhullError

    if xy.shape[0] < 3:
        return None
    try:
        return ConvexHull(xy).equations
    except (QhullError, ValueError):
        return None


def _inside(equations, q) -> np.ndarray:
    if equations is None:
        return np.zeros(q.shape[0], bool)
    scale = max(1.0, float(np.max(np.abs(equations[:, 2]))))
    with np.errstate(invalid="ignore"):
        # element-wise, not q @ n.T: no BLAS call (multithreaded BLAS costs more than it saves here)
        side = q[:, 0, None] * equations[None, :, 0] + q[:, 1, None] * equations[None, :, 1] + equations[None, :, 2]
        return np.all(side <= 1e-9 * scale, axis=1)


def cells_for(points, *, cracks=None):
    """:class:`GridCells` of ``points`` (N, 2) when they lie on a regular grid (with ``cracks``), else the
    :meth:`TriangleCells.scattered` fallback over them (declared cracks are not supported there: ValueError)."""
    try:
        return GridCells(points, cracks=cracks)
    except ValueError:
        from .cracks import as_cracks

        if as_cracks(cracks):
            raise ValueError("declared cracks need points on a regular grid (dic.grid); these are scattered") from None
        return TriangleCells.scattered(points)
