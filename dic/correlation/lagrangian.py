"""Lagrangian composition of shape-function parameters across reference updates (pure NumPy).

Used by the sequence engine's reference strategies (:mod:`dic.sequence.reference`, 2-D) and by the
moved references of stereo tracks (:meth:`dic.StereoCorrelation.move_reference`): a
displacement ``w`` measured against a reference at the moved points ``X_r = X0 + d_r(X0)``
composes as ``d(X0) = d_r(X0) + w(X_r)``, the gradients by the chain rule.
"""
from __future__ import annotations

import numpy as np

__all__ = ["compose_params", "relative_params", "moved_points", "shift_params", "fill_reference", "displacement_outliers",
           "reference_anchors", "MovedReference"]

#: the normalised median test's defaults (Westerweel & Scarano 2005): neighbours compared, threshold on the
#: normalised residual, and the noise level (px) added to the neighbours' median deviation
OUTLIER_NEIGHBOURS = 8
OUTLIER_THRESHOLD = 2.0
OUTLIER_NOISE_PX = 0.1


def _gradients(params: np.ndarray, order: int):
    """(N, 2) displacement, (N, 2, 2) gradient G[i, a] = d u_i / d x_a and, for order 2, (N, 2, 2, 2) Hessians."""
    h = params.shape[1] // 2
    d = np.stack([params[:, 0], params[:, h]], 1)
    G = np.stack([params[:, 1:3], params[:, h + 1:h + 3]], 1)
    H = None
    if order == 2:
        H = np.empty((params.shape[0], 2, 2, 2))
        for i, base in enumerate((0, h)):
            xx, xy, yy = params[:, base + 3], params[:, base + 4], params[:, base + 5]
            H[:, i] = np.stack([np.stack([xx, xy], -1), np.stack([xy, yy], -1)], -2)
    return d, G, H


def _pack(d, G, H, order: int) -> np.ndarray:
    n = d.shape[0]
    out = np.zeros((n, 6 if order == 1 else 12))
    h = out.shape[1] // 2
    for i, base in enumerate((0, h)):
        out[:, base] = d[:, i]
        out[:, base + 1:base + 3] = G[:, i]
        if order == 2:
            out[:, base + 3] = H[:, i, 0, 0]
            out[:, base + 4] = H[:, i, 0, 1]
            out[:, base + 5] = H[:, i, 1, 1]
    return out


def compose_params(ref_params: np.ndarray, inc_params: np.ndarray, order: int) -> np.ndarray:
    """Parameters of ``d(X) = d_r(X) + w(X + d_r(X))`` from those of ``d_r`` (at X) and ``w`` (at X + d_r(X)).

    Chain rule: gradient ``G = G_r + G_w F_r`` (``F_r = I + G_r``); second order
    ``H_i = H_r,i + F_r^T H_w,i F_r + sum_a G_w[i, a] H_r,a``.
    """
    dr, Gr, Hr = _gradients(np.asarray(ref_params, np.float64), order)
    dw, Gw, Hw = _gradients(np.asarray(inc_params, np.float64), order)
    F = np.eye(2)[None] + Gr
    G = Gr + np.einsum("nia,nab->nib", Gw, F)
    H = None
    if order == 2:
        H = Hr + np.einsum("nab,niac,ncd->nibd", F, Hw, F) + np.einsum("nia,nabc->nibc", Gw, Hr)
    return _pack(dr + dw, G, H, order)


def relative_params(ref_params: np.ndarray, params: np.ndarray, order: int) -> np.ndarray:
    """The inverse of :func:`compose_params` to first order: ``w`` with ``d = d_r ∘ w`` (translation and
    gradient; second-order terms zero), used as the initial guess against a moved reference."""
    dr, Gr, _ = _gradients(np.asarray(ref_params, np.float64), order)
    d, G, _ = _gradients(np.asarray(params, np.float64), order)
    F = np.eye(2)[None] + Gr
    with np.errstate(all="ignore"):
        Gw = np.einsum("nia,nab->nib", G - Gr, np.linalg.inv(F))
    return _pack(d - dr, Gw, np.zeros((d.shape[0], 2, 2, 2)), order)


def moved_points(points0: np.ndarray, u: np.ndarray, v: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Where the original POIs are in a frame: ``X0 + (u, v)``; points not valid there get the displacement
    interpolated linearly from the valid ones (nearest valid one outside their hull)."""
    pts = np.asarray(points0, np.float64)
    d = np.stack([u, v], 1).astype(np.float64)
    good = np.asarray(valid, bool) & np.all(np.isfinite(d), axis=1)
    if not np.any(good):
        raise ValueError("no valid point to move the reference with")
    bad = ~good
    if np.any(bad):
        from scipy.interpolate import griddata

        filled = None
        if np.count_nonzero(good) >= 3:
            try:
                filled = griddata(pts[good], d[good], pts[bad], method="linear")
            except Exception:  # noqa: BLE001 - collinear valid points (Qhull): nearest below
                filled = None
        near = griddata(pts[good], d[good], pts[bad], method="nearest")
        if filled is None:
            filled = near
        filled = np.where(np.isfinite(filled), filled, near)
        d = d.copy()
        d[bad] = filled
    return pts + d


def fill_reference(points0: np.ndarray, params: np.ndarray, valid: np.ndarray, *, radius: float | None = None,
                   radius_spacings: float = 4.0):
    """A moved reference's parameters with its invalid points filled in, and where the fill is local.

    ``params`` (N, 6|12): a frame's Lagrangian parameters at the original POIs ``points0`` (N, 2);
    ``valid`` (N,) bool. Returns ``(filled, supported)``: ``filled`` is ``params`` with every
    parameter of the invalid points interpolated linearly from the valid ones (the rule of
    :func:`moved_points`, so ``points0 + filled``'s displacement is where :func:`moved_points` puts
    them; nearest valid point outside their hull); ``supported`` (N,) bool is True at the valid
    points and at the invalid ones whose value came from a Delaunay triangle of valid points with
    every corner within ``radius`` px of them (default ``radius_spacings`` (4) × the POI spacing,
    the median nearest-neighbour distance). A supported point can be tracked against the moved
    reference like a valid one: its position there is as good as the local interpolation of a
    smooth field. Points outside the valid points' hull or in holes wider than ``radius`` are not.
    """
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
    from scipy.spatial import Delaunay, QhullError, cKDTree

    pts = np.asarray(points0, np.float64)
    p = np.asarray(params, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or p.ndim != 2 or p.shape[0] != pts.shape[0] or p.shape[1] not in (6, 12):
        raise ValueError(f"fill_reference needs points (N, 2) and params (N, 6|12) of the same N, got "
                         f"{pts.shape} and {p.shape}")
    v = np.asarray(valid, bool)
    if v.shape != (pts.shape[0],):
        raise ValueError(f"valid must be a (N,) mask of the {pts.shape[0]} points, got shape {v.shape}")
    if radius is not None and not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be a positive number of px, got {radius!r}")
    if not (np.isfinite(radius_spacings) and radius_spacings > 0):
        raise ValueError(f"radius_spacings must be a positive number, got {radius_spacings!r}")
    good = v & np.all(np.isfinite(p), axis=1)
    if not np.any(good):
        raise ValueError("no valid point to move the reference with")
    filled = p.copy()
    supported = good.copy()
    bad = ~good
    if not np.any(bad):
        return filled, supported
    near = NearestNDInterpolator(pts[good], p[good])(pts[bad])
    lin = None
    if np.count_nonzero(good) >= 3:
        try:
            tri = Delaunay(pts[good])
        except (QhullError, ValueError):  # collinear valid points: nearest only, nothing supported
            tri = None
        if tri is not None:
            lin = LinearNDInterpolator(tri, p[good])(pts[bad])
            if radius is None:
                d, _ = cKDTree(pts).query(pts, k=2)
                spacing = float(np.median(d[:, 1])) if len(pts) > 1 else 0.0
                radius = radius_spacings * spacing if spacing > 0 else np.inf
            simplex = tri.find_simplex(pts[bad])
            inside = simplex >= 0
            corners = tri.points[tri.simplices[np.where(inside, simplex, 0)]]  # (B, 3, 2)
            far = np.linalg.norm(corners - pts[bad][:, None, :], axis=2).max(axis=1)
            supported[np.flatnonzero(bad)] = inside & (far <= radius) & np.all(np.isfinite(lin), axis=1)
    if lin is None:
        lin = near
    filled[bad] = np.where(np.isfinite(lin), lin, near)
    return filled, supported


def _median_rows(a: np.ndarray) -> np.ndarray:
    """``np.median(a, axis=1)`` (the same values) by partial sorting: about 3x faster on the (M, 8, 2)
    neighbour arrays of :func:`displacement_outliers`, which runs at every reference update."""
    k = a.shape[1]
    h = k // 2
    if k % 2:
        return np.partition(a, h, axis=1)[:, h]
    q = np.partition(a, (h - 1, h), axis=1)
    return 0.5 * (q[:, h - 1] + q[:, h])


def displacement_outliers(points: np.ndarray, u: np.ndarray, v: np.ndarray, valid: np.ndarray, *,
                          neighbours: int = OUTLIER_NEIGHBOURS, threshold: float = OUTLIER_THRESHOLD,
                          noise_px: float = OUTLIER_NOISE_PX, cache: dict | None = None) -> np.ndarray:
    """Valid points whose displacement disagrees with their valid neighbours': the normalised median test.

    Westerweel & Scarano, "Universal outlier detection for PIV data", Experiments in Fluids 39, 2005,
    doi:10.1007/s00348-005-0016-6. For each valid point and each component (u, v) in px, with the median
    ``m`` of its ``neighbours`` nearest valid points and the median ``s`` of their ``|d - m|``, the point is
    an outlier when ``|d0 - m| / (s + noise_px) > threshold`` for either component. A smooth field passes
    (a linear one exactly: the neighbours surround the point), a false match (a subset that converged to
    the wrong speckle, often a whole pixel off) does not. Points (N, 2) px; u, v (N,) px; valid (N,) bool.
    Returns (N,) bool, False wherever ``valid`` is (and where fewer than 3 valid neighbours exist).
    ``cache``: a dict kept by the caller across calls on the same ``points`` (a tracker's frames): the
    neighbour lists are reused while the usable points stay the same (the same result, without the k-d tree).
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64)
    d = np.stack([np.asarray(u, np.float64), np.asarray(v, np.float64)], axis=1)
    ok = np.asarray(valid, bool)
    if pts.ndim != 2 or pts.shape[1] != 2 or d.shape[0] != pts.shape[0] or ok.shape != (pts.shape[0],):
        raise ValueError(f"displacement_outliers needs points (N, 2), u, v and valid (N,), got {pts.shape}, "
                         f"{np.shape(u)}, {np.shape(v)}, {ok.shape}")
    if isinstance(neighbours, bool) or not isinstance(neighbours, (int, np.integer)) or neighbours < 3:
        raise ValueError(f"neighbours must be an integer >= 3, got {neighbours!r}")
    for name, val in (("threshold", threshold), ("noise_px", noise_px)):
        if not (np.isfinite(val) and val > 0):
            raise ValueError(f"{name} must be a positive number, got {val!r}")
    ok &= np.all(np.isfinite(d), axis=1)
    out = np.zeros(pts.shape[0], dtype=bool)
    idx = np.flatnonzero(ok)
    if idx.size <= 3:
        return out
    k = min(int(neighbours), idx.size - 1)
    key = (k, pts.shape, ok.tobytes())
    if cache is not None and cache.get("key") == key and np.array_equal(cache.get("points"), pts):
        j = cache["j"]
    else:
        _, j = cKDTree(pts[idx]).query(pts[idx], k=k + 1)
        if cache is not None:
            cache.update(key=key, points=pts.copy(), j=j)
    nb = d[idx][j[:, 1:]]  # (M, k, 2): the neighbours' displacements (the point itself is the nearest)
    med = _median_rows(nb)
    spread = _median_rows(np.abs(nb - med[:, None, :]))
    r = np.abs(d[idx] - med) / (spread + noise_px)
    out[idx] = np.any(r > threshold, axis=1)
    return out


def shift_params(params: np.ndarray, delta: np.ndarray, order: int) -> np.ndarray:
    """Shape-function parameters of the same warp seen from a point ``delta`` (N, 2) px away: the
    displacement and gradient evaluated there (exact for the affine and quadratic shape functions)."""
    d, G, H = _gradients(np.asarray(params, np.float64), order)
    delta = np.asarray(delta, np.float64)
    d2 = d + np.einsum("nia,na->ni", G, delta)
    G2 = G
    if order == 2:
        d2 = d2 + 0.5 * np.einsum("niab,na,nb->ni", H, delta, delta)
        G2 = G + np.einsum("niab,nb->nia", H, delta)
    return _pack(d2, G2, H, order)


def reference_anchors(points0: np.ndarray, params: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The points a moved reference is built on: ``valid`` (N,) without the false matches, the valid
    points whose displacement disagrees with their neighbours' (:func:`displacement_outliers`): were one
    an anchor, its error would be composed into every later frame; it is placed by interpolation like an
    invalid point. ``params`` (N, 6|12) at ``points0`` (N, 2) px."""
    p = np.asarray(params, np.float64)
    h = p.shape[1] // 2
    valid = np.asarray(valid, bool)
    return valid & ~displacement_outliers(points0, p[:, 0], p[:, h], valid)


class MovedReference:
    """A reference moved to a later frame ``index``: the one implementation of 2-D and stereo tracks.

    ``points0`` (N, 2) px: the original POIs (2-D: in the reference image; stereo: one camera's
    points in the reference pair); ``params`` (N, 6|12): that frame's Lagrangian parameters at them;
    ``anchors`` (N,) bool: the points it is built on (valid there, no false match:
    :func:`reference_anchors`). The POIs are moved to where they are in that frame
    (:func:`moved_points`), the non-anchors placed by interpolating their anchors' parameters
    (:func:`fill_reference`); the tracked subsets sit at the whole pixels nearest to the moved points
    (``points``, the kernels' rounding), ``offset`` (N, 2) px the rest, so a warp measured at a whole
    pixel is carried to the moved point exactly (:func:`shift_params`) before it is composed
    (:meth:`compose`). ``usable`` (N,) bool: the points that can be tracked against it (anchors and
    the points a close triangle of anchors placed, ``supported`` of :func:`fill_reference`, unless the
    caller narrows it: stereo needs both cameras supported). ``params`` holds the filled values where
    usable, the frame's own (``raw``) elsewhere.

    ValueError: no anchor (a frame with no valid point cannot serve as a reference).
    """

    def __init__(self, index: int, points0: np.ndarray, params: np.ndarray, anchors: np.ndarray, order: int):
        pts0 = np.asarray(points0, np.float64)
        raw = np.asarray(params, np.float64)
        anchors = np.asarray(anchors, bool)
        h = raw.shape[1] // 2
        self.index = int(index)
        self.order = int(order)
        self.points0 = pts0
        self.raw = raw
        self.anchors = anchors
        moved = moved_points(pts0, raw[:, 0], raw[:, h], anchors)
        self.filled, self.supported = fill_reference(pts0, raw, anchors)
        from kernels.conventions import round_half_away

        self.points = round_half_away(moved)  # the kernels' rule (wp.round: half away from zero)
        self.offset = moved - self.points
        self.usable = self.supported
        self.params = np.where(self.usable[:, None], self.filled, raw)

    def narrow(self, usable: np.ndarray) -> "MovedReference":
        """Track only ``usable`` (N,) bool (a subset of :attr:`supported`); the others keep the frame's own parameters."""
        self.usable = np.asarray(usable, bool)
        self.params = np.where(self.usable[:, None], self.filled, self.raw)
        return self

    def compose(self, params: np.ndarray) -> np.ndarray:
        """Parameters (N, 6|12) measured at :attr:`points` against this reference, back in the original
        configuration (Lagrangian): shifted to the moved points, then composed (chain rule)."""
        return compose_params(self.params, shift_params(np.asarray(params, np.float64), self.offset, self.order),
                              self.order)

    def relative(self, params: np.ndarray) -> np.ndarray:
        """A later frame's Lagrangian ``params`` (N, 6|12) as a warp from this reference at the moved points
        (:func:`relative_params`): the initial guess of the next frame, as 2-D sequences use it."""
        return relative_params(self.params, params, self.order)

    def relative_at_points(self, params: np.ndarray) -> np.ndarray:
        """:meth:`relative` carried to the whole-pixel :attr:`points` the subsets sit at; NaN rows where either
        is unknown (stereo tracks' initial guess)."""
        params = np.asarray(params, dtype=np.float64)
        out = np.full(params.shape, np.nan)
        ok = np.all(np.isfinite(self.params), axis=1) & np.all(np.isfinite(params), axis=1)
        if np.any(ok):
            rel = relative_params(self.params[ok], params[ok], self.order)
            out[ok] = shift_params(rel, -self.offset[ok], self.order)
        return out

    def unmeasured(self, params: np.ndarray) -> np.ndarray:
        """The points placed by interpolation (usable, no anchor) whose ``params`` are still the frame's own:
        not measured since (their warp there failed), so not a guess to start from."""
        fresh = self.usable & ~self.anchors
        same = np.all((params == self.raw) | (np.isnan(params) & np.isnan(self.raw)), axis=1)
        return fresh & same

    def carry_cracks(self, cracks, *, spacing: float | None = None) -> tuple:
        """Declared cracks (reference px) carried into this frame's image by its measured field
        (:func:`dic.cracks.carry_cracks`: each vertex moved by the mean of the two faces' displacements, from
        the anchors: measured points, never interpolated across a crack); a tuple of :class:`dic.Crack`."""
        from ..cracks import carry_cracks

        return carry_cracks(cracks, self.points0, self.params, self.anchors & self.usable, spacing=spacing)

    def carry_region(self, region_mask, *, reach: int | None = None, cracks=()) -> np.ndarray:
        """A region's (H, W) pixel mask of the reference image carried into this frame's image by the anchors'
        local warps (:func:`dic.correlation.subset_masks.carry_region_mask`; ``cracks``: the carried ones)."""
        from .subset_masks import carry_region_mask

        return carry_region_mask(region_mask, self.points0, self.params, self.anchors & self.usable, reach=reach,
                                 cracks=cracks)

    def crack_blocked_pixels(self, cracks):
        """A tracker's ``blocked_pixels`` callable ``(points, subset) -> (n, subset²) bool`` for carried ``cracks``
        (this frame's px): :func:`dic.cracks.blocked_pixels` seen from each moved point's own sub-pixel position
        (:attr:`points` + :attr:`offset`) rather than the whole pixel its subset sits at, so that a point within
        half a pixel of a crack keeps its side. Points not among :attr:`points` are seen from where they are."""
        return _BlockedFromMovedPoints(self.points, self.points + self.offset, cracks)

    def carry_cut(self, region_mask, cracks, subset: int):
        """What cuts this reference's subsets, carried from the reference image: ``(pixel_region, blocked_pixels)``,
        the region's (H, W) pixel mask (:meth:`carry_region`, reaching ``subset // 2 + 1`` px beyond the points,
        with the carried cracks) or None without ``region_mask``, and the :meth:`crack_blocked_pixels` callable of
        the carried ``cracks`` (:meth:`carry_cracks`) or None without cracks. What a 2-D moved reference
        (:func:`dic.sequence.track2d`) and a stereo one's left camera (:class:`dic.StereoCorrelation`) are masked by."""
        carried = self.carry_cracks(cracks) if cracks else ()
        pixel_region = None if region_mask is None else self.carry_region(region_mask, reach=int(subset) // 2 + 1,
                                                                         cracks=carried)
        return pixel_region, (self.crack_blocked_pixels(carried) if carried else None)

    def subset(self, rows: np.ndarray) -> "MovedReference":
        """The same reference at ``rows`` of its points only (a view for a camera that tracks a subset)."""
        out = object.__new__(MovedReference)
        out.index, out.order = self.index, self.order
        for name in ("points0", "raw", "anchors", "filled", "supported", "points", "offset", "usable", "params"):
            setattr(out, name, getattr(self, name)[rows])
        return out


class _BlockedFromMovedPoints:
    """The ``blocked_pixels`` callable of :meth:`MovedReference.crack_blocked_pixels`: ``(points, subset) -> (n,
    subset²) bool``, each point among ``points`` (M, 2) whole px seen from its ``exact`` (M, 2) sub-pixel position.
    Picklable and small (the two arrays and the cracks; the look-up built where it is called): a Dask run ships it
    to its workers (:class:`dic.sequence.distributed.CarriedMasks`)."""

    def __init__(self, points: np.ndarray, exact: np.ndarray, cracks):
        from ..cracks import as_cracks

        self.points, self.exact, self.cracks = np.asarray(points, np.float64), np.asarray(exact, np.float64), \
            as_cracks(cracks)
        self._rows = None

    def __getstate__(self):
        return {"points": self.points, "exact": self.exact, "cracks": self.cracks, "_rows": None}

    def __call__(self, points, subset):
        from ..cracks import blocked_pixels

        if self._rows is None:
            rows: dict[tuple[float, float], int] = {}
            for row, xy in enumerate(map(tuple, self.points.tolist())):
                rows.setdefault(xy, row)
            self._rows = rows
        pts = np.asarray(points, np.float64)
        idx = np.array([self._rows.get(xy, -1) for xy in map(tuple, pts.tolist())], dtype=np.int64).reshape(-1)
        seen = np.where((idx >= 0)[:, None], self.exact[np.maximum(idx, 0)], pts) if len(pts) else pts
        return blocked_pixels(seen, subset, self.cracks)
