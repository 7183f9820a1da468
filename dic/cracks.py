"""Declared cracks: polylines in the reference image across which nothing is correlated, fitted or drawn.

A :class:`Crack` is a polyline of at least two vertices ``(x, y)`` in reference-image px
(docs/conventions.md: pixel (0, 0) is the centre of the top-left pixel). Declaring one says that
the displacement may jump across it, so that

* a subset correlates only the pixels on its POI's own side (:func:`blocked_pixels`: the pixels
  whose straight segment from the POI centre crosses a crack);
* a strain fit window leaves out the neighbours across it (:class:`dic.StrainPlan` ``cracks=``);
* post-processing never interpolates across it (:class:`dic.gridinterp.GridCells` ``cracks=``,
  query status ``CRACK``), and figures leave out the cells it cuts and draw it as a line;
* its opening and sliding along the polyline are a post-processing quantity
  (:func:`crack_opening`: the jump of the displacement across it, from a linear fit on each side).

**The crossing rule** (one rule everywhere): a segment ``[p, q]`` crosses a crack when it meets
one of the crack's segments, touching included (a pixel lying on the crack, or a crack vertex on
the segment, counts as crossing). A POI exactly on a crack therefore sees every pixel off the
crack's line as blocked: it has no side. Crack tips do not bend the rule: a pixel behind a tip is
reachable on a straight line and is not blocked.

Everything here is NumPy (no Warp, no BLAS beyond 3 x 3 solves).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["CRACK_MARGIN_PX", "Crack", "CrackOpening", "as_cracks", "parse_crack", "cracks_settings", "blocked_pixels",
           "segments_cross", "subset_crosses", "crack_opening", "carry_cracks", "CARRY_NEIGHBOURS", "CARRY_SPACING_PX"]

#: how many (point, pixel, crack segment) triples one vectorised pass of blocked_pixels holds at most
_CHUNK = 4_000_000


@dataclass(frozen=True, eq=False)
class Crack:
    """A declared crack: a polyline in reference-image px.

    Parameters
    ----------
    vertices : (M, 2) array-like, M >= 2
        The polyline's vertices ``(x, y)`` px, in order. Every coordinate finite; consecutive
        vertices distinct (no zero-length segment).

    Attributes
    ----------
    vertices : (M, 2) float64, read-only
    """

    vertices: np.ndarray

    def __post_init__(self):
        try:
            v = np.array(self.vertices, dtype=np.float64, copy=True)
        except (TypeError, ValueError):
            raise ValueError(f"a crack must be an (M, 2) array of vertices (x, y) px, got {self.vertices!r}") from None
        if v.ndim != 2 or v.shape[1] != 2:
            raise ValueError(f"a crack must be an (M, 2) array of vertices (x, y) px, got shape {v.shape}")
        if v.shape[0] < 2:
            raise ValueError(f"a crack needs at least 2 vertices, got {v.shape[0]}")
        if not np.all(np.isfinite(v)):
            raise ValueError("a crack's vertices must be finite (x, y) px, got NaN or infinity")
        seg = np.hypot(*np.diff(v, axis=0).T)
        if np.any(seg == 0.0):
            k = int(np.flatnonzero(seg == 0.0)[0])
            raise ValueError(f"a crack's segments must have a length: vertices {k} and {k + 1} are both "
                             f"({v[k, 0]:g}, {v[k, 1]:g})")
        v.flags.writeable = False
        object.__setattr__(self, "vertices", v)

    def __eq__(self, other) -> bool:
        return isinstance(other, Crack) and np.array_equal(self.vertices, other.vertices)

    def __hash__(self) -> int:
        return hash(self.vertices.tobytes())

    def __repr__(self) -> str:
        return f"Crack({self.vertices.tolist()})"

    @property
    def segments(self) -> tuple[np.ndarray, np.ndarray]:
        """Start and end points of the segments, each (M - 1, 2) px."""
        return self.vertices[:-1], self.vertices[1:]

    @property
    def length(self) -> float:
        """Length of the polyline, px."""
        return float(np.sum(np.hypot(*np.diff(self.vertices, axis=0).T)))

    def settings(self) -> list[list[float]]:
        """The stored (JSON) form: ``[[x, y], ...]``."""
        return self.vertices.tolist()


def parse_crack(text: str) -> Crack:
    """A crack from the command line's form ``"x1,y1,x2,y2,..."`` (px; at least two vertices)."""
    if not isinstance(text, str):
        raise ValueError(f"a crack is written x1,y1,x2,y2,... (px), got {text!r}")
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"a crack is written x1,y1,x2,y2,... with numbers (px), got {text!r}") from None
    if len(values) % 2 or len(values) < 4:
        raise ValueError(f"a crack is written x1,y1,x2,y2,... (an even count of at least 4 numbers, px), "
                         f"got {len(values)} number(s) in {text!r}")
    return Crack(np.reshape(values, (-1, 2)))


def as_cracks(cracks) -> tuple[Crack, ...]:
    """Cracks in any accepted form -> a tuple of :class:`Crack` (empty for None).

    Accepted: None; a :class:`Crack`; an (M, 2) array of vertices (one crack); the command line's
    string ``"x1,y1,..."``; or a list/tuple of any of these (the stored form, a list of vertex lists,
    included).
    """
    if cracks is None:
        return ()
    if isinstance(cracks, (Crack, str)):
        cracks = [cracks]
    elif isinstance(cracks, np.ndarray):
        if cracks.ndim == 2:
            cracks = [cracks]
        elif cracks.ndim != 3:
            raise ValueError(f"cracks must be a Crack, an (M, 2) array of vertices or a list of them, got an array "
                             f"of shape {cracks.shape}")
    elif not isinstance(cracks, (list, tuple)):
        raise ValueError(f"cracks must be a Crack, an (M, 2) array of vertices or a list of them, "
                         f"got {type(cracks).__name__}")
    elif cracks and _is_vertex(cracks[0]):
        cracks = [cracks]  # one crack as a list of (x, y) vertices
    out = []
    for k, c in enumerate(cracks):
        try:
            out.append(c if isinstance(c, Crack) else parse_crack(c) if isinstance(c, str) else Crack(c))
        except ValueError as exc:
            raise ValueError(f"crack {k}: {exc}") from None
    return tuple(out)


def _is_vertex(item) -> bool:
    """Whether ``item`` is one vertex ``(x, y)``: two real numbers."""
    return (isinstance(item, (list, tuple, np.ndarray)) and np.ndim(item) == 1 and len(item) == 2
            and all(isinstance(c, (int, float, np.integer, np.floating)) and not isinstance(c, (bool, np.bool_))
                    for c in item))


def cracks_settings(cracks) -> list | None:
    """The stored form of cracks (a run record's ``cracks``): None without cracks, else a list of vertex lists."""
    cracks = as_cracks(cracks)
    return [c.settings() for c in cracks] if cracks else None


def _all_segments(cracks) -> tuple[np.ndarray, np.ndarray]:
    """Start and end points (S, 2) of every segment of every crack."""
    cracks = as_cracks(cracks)
    if not cracks:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return (np.concatenate([c.segments[0] for c in cracks]), np.concatenate([c.segments[1] for c in cracks]))


def _cross(ox, oy, ax, ay, bx, by):
    """z of (a - o) x (b - o)."""
    return (ax - ox) * (by - oy) - (ay - oy) * (bx - ox)


def _meet(p, q, a, b) -> np.ndarray:
    """Whether segments [p, q] and [a, b] meet (touching included); arrays broadcast, last axis (x, y)."""
    px, py, qx, qy = p[..., 0], p[..., 1], q[..., 0], q[..., 1]
    ax, ay, bx, by = a[..., 0], a[..., 1], b[..., 0], b[..., 1]
    d1 = _cross(ax, ay, bx, by, px, py)
    d2 = _cross(ax, ay, bx, by, qx, qy)
    d3 = _cross(px, py, qx, qy, ax, ay)
    d4 = _cross(px, py, qx, qy, bx, by)
    general = (d1 * d2 <= 0) & (d3 * d4 <= 0)
    collinear = (d1 == 0) & (d2 == 0)
    # all four collinear: they meet when their boxes overlap (the general test would say yes always)
    overlap = ((np.minimum(px, qx) <= np.maximum(ax, bx)) & (np.minimum(ax, bx) <= np.maximum(px, qx))
               & (np.minimum(py, qy) <= np.maximum(ay, by)) & (np.minimum(ay, by) <= np.maximum(py, qy)))
    return np.where(collinear, overlap, general)


def segments_cross(start, end, cracks) -> np.ndarray:
    """Whether each segment ``[start[i], end[i]]`` crosses any crack (the module's crossing rule).

    Parameters
    ----------
    start, end : (..., 2) float px (broadcast against each other)
    cracks : anything :func:`as_cracks` takes

    Returns
    -------
    (...) bool
    """
    p = np.asarray(start, np.float64)
    q = np.asarray(end, np.float64)
    if p.shape[-1:] != (2,) or q.shape[-1:] != (2,):
        raise ValueError(f"segment ends must be (..., 2) positions (x, y) px, got shapes {p.shape} and {q.shape}")
    p, q = np.broadcast_arrays(p, q)
    a, b = _all_segments(cracks)
    out = np.zeros(p.shape[:-1], bool)
    if a.shape[0] == 0 or out.size == 0:
        return out
    flat_p, flat_q, flat = p.reshape(-1, 2), q.reshape(-1, 2), out.reshape(-1)
    # only segments whose box comes near a crack segment's box can cross it
    lo = np.minimum(flat_p, flat_q)
    hi = np.maximum(flat_p, flat_q)
    rows = max(1, _CHUNK // a.shape[0])
    for s in range(0, flat.size, rows):
        sl = slice(s, s + rows)
        near = np.any((lo[sl, None, 0] <= np.maximum(a[:, 0], b[:, 0])) & (hi[sl, None, 0] >= np.minimum(a[:, 0], b[:, 0]))
                      & (lo[sl, None, 1] <= np.maximum(a[:, 1], b[:, 1])) & (hi[sl, None, 1] >= np.minimum(a[:, 1], b[:, 1])),
                      axis=1)
        idx = s + np.flatnonzero(near)
        if idx.size:
            flat[idx] = np.any(_meet(flat_p[idx, None, :], flat_q[idx, None, :], a[None], b[None]), axis=1)
    return out


def _subset_offsets(subset: int) -> np.ndarray:
    """(subset², 2) offsets (dx, dy) of a subset's pixels, row by row (dy outer, dx inner: the kernels' order)."""
    r = subset // 2
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    return np.stack([dx.ravel(), dy.ravel()], axis=1).astype(np.float64)


def _check_subset(subset) -> int:
    from kernels.checks import odd_int

    return odd_int(subset, "subset", detail=" (px)")


#: blocked_pixels' default margin, px: the pixels whose centre lies nearer a crack are dropped too
CRACK_MARGIN_PX = 1.0


def blocked_pixels(points, subset: int, cracks, *, margin: float = CRACK_MARGIN_PX) -> np.ndarray:
    """Which pixels of each POI's subset lie across a crack from the POI.

    Parameters
    ----------
    points : (N, 2) float
        POIs ``(x, y)`` px (sub-pixel allowed). A subset's pixels are the whole pixels
        ``(round(x) + i, round(y) + j)``, ``i, j`` in ``[-subset // 2, subset // 2]`` (rounded half away
        from zero, as the kernels do: :func:`kernels.conventions.round_half_away`).
    subset : odd int >= 3
        Subset size (px).
    cracks : anything :func:`as_cracks` takes
    margin : float >= 0
        Pixels whose centre lies nearer than this to a crack (px) are dropped too, on both sides
        (default :data:`CRACK_MARGIN_PX`, 1 px: the column of pixels along the crack). In an image
        their grey level mixes both faces or the gap, and the current image's B-spline
        interpolation next to the crack reaches the other side: in docs/dic2d.md's case the 1 px margin
        took the RMS error of the points within half a subset of a crack from 0.0091 to 0.0056 px.
        0: the crossing rule alone.

    Returns
    -------
    (N, subset * subset) bool
        True where the straight segment from the POI ``(x, y)`` to the pixel's centre crosses a crack
        (the module's crossing rule) or the pixel lies within ``margin`` of one; pixels in row order
        (row ``j`` outer, column ``i`` inner), the order of the IC-GN kernels. All False without cracks.
    """
    from kernels.checks import as_points, in_range
    from kernels.conventions import round_half_away

    pts = as_points(points, allow_empty=True)
    subset = _check_subset(subset)
    margin = in_range(margin, 0.0, 1e6, "margin", detail=" (px)")
    cracks = as_cracks(cracks)
    n, k = pts.shape[0], subset * subset
    out = np.zeros((n, k), bool)
    a, b = _all_segments(cracks)
    if n == 0 or a.shape[0] == 0:
        return out
    centres = np.stack([round_half_away(pts[:, 0]), round_half_away(pts[:, 1])], axis=1).astype(np.float64)
    offsets = _subset_offsets(subset)
    # a segment from the POI to a pixel of its subset stays within this distance of the POI
    reach = np.hypot(*(np.abs(pts - centres) + subset // 2).T) + 1e-9 + margin
    for a_s, b_s in zip(a, b):  # one crack segment at a time, over the POIs it can reach
        ab = b_s - a_s
        t = np.clip(((pts[:, 0] - a_s[0]) * ab[0] + (pts[:, 1] - a_s[1]) * ab[1]) / (ab[0] ** 2 + ab[1] ** 2), 0.0, 1.0)
        dist = np.hypot(*(a_s + t[:, None] * ab - pts).T)
        idx = np.flatnonzero(dist <= reach)
        rows = max(1, _CHUNK // k)
        for s in range(0, idx.size, rows):
            sel = idx[s:s + rows]
            pixels = centres[sel, None, :] + offsets[None]  # (m, k, 2)
            out[sel] |= _meet(pts[sel, None, :], pixels, a_s, b_s)
            if margin > 0:
                w = np.clip(((pixels[..., 0] - a_s[0]) * ab[0] + (pixels[..., 1] - a_s[1]) * ab[1])
                            / (ab[0] ** 2 + ab[1] ** 2), 0.0, 1.0)
                out[sel] |= np.hypot(a_s[0] + w * ab[0] - pixels[..., 0], a_s[1] + w * ab[1] - pixels[..., 1]) < margin
    return out


def subset_crosses(points, subset: int, cracks) -> np.ndarray:
    """(N,) bool: whether any pixel of each POI's subset lies across a crack (:func:`blocked_pixels`, no margin)."""
    return blocked_pixels(points, subset, cracks, margin=0.0).any(axis=1)


# -- opening and sliding ---------------------------------------------------------------------------------------
@dataclass
class CrackOpening:
    """The displacement jump across one crack at stations along it (:func:`crack_opening`).

    All per-station arrays have shape (S,); lengths and displacements in px.

    Attributes
    ----------
    stations : (S, 2) float64
        Station positions ``(x, y)`` px on the polyline.
    arclength : (S,) float64
        Distance of each station from the first vertex along the polyline, px.
    tangent, normal : (S, 2) float64
        Unit tangent (from the first vertex towards the last) and normal ``(-t_y, t_x)`` of the
        segment holding the station. The normal points to the *positive side*.
    opening, sliding : (S,) float64
        ``(U+ - U-) · normal`` and ``(U+ - U-) · tangent`` px: the jump of the displacement from the
        negative to the positive side, each side's value extrapolated onto the line. Opening > 0:
        the faces move apart. NaN where a side had too few points.
    sigma_opening, sigma_sliding : (S,) float64
        Their standard uncertainties, px (from the points' ``sigma_u``, ``sigma_v`` when the field has
        them, else from the residuals of each side's fit).
    n_plus, n_minus : (S,) int64
        Points in each side's fit.
    valid : (S,) bool
    crack : Crack
    radius : float
        Radius of the fit neighbourhoods, px.
    gap : float
        Points closer than this to the crack were left out of the fits, px.
    """

    stations: np.ndarray
    arclength: np.ndarray
    tangent: np.ndarray
    normal: np.ndarray
    opening: np.ndarray
    sliding: np.ndarray
    sigma_opening: np.ndarray
    sigma_sliding: np.ndarray
    n_plus: np.ndarray
    n_minus: np.ndarray
    valid: np.ndarray
    crack: Crack
    radius: float
    gap: float = 0.0

    #: the columns of :meth:`table` (and of ``specula crack``'s CSV), with their units
    COLUMNS = (("arclength", "px"), ("x", "px"), ("y", "px"), ("opening", "px"), ("sliding", "px"),
               ("sigma_opening", "px"), ("sigma_sliding", "px"), ("n_plus", ""), ("n_minus", ""))

    def table(self) -> np.ndarray:
        """(S, 9) float64: the :attr:`COLUMNS` per station."""
        return np.column_stack([self.arclength, self.stations[:, 0], self.stations[:, 1], self.opening, self.sliding,
                                self.sigma_opening, self.sigma_sliding, self.n_plus, self.n_minus])


def _stations(crack: Crack, spacing: float):
    """Stations every ``spacing`` px from the first vertex (the last vertex included)."""
    v = crack.vertices
    seg_len = np.hypot(*np.diff(v, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    total = cum[-1]
    s = np.arange(0.0, total, spacing)
    s = np.append(s, total) if total - s[-1] > 1e-9 * max(total, 1.0) else s
    seg = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg_len) - 1)
    t = ((v[seg + 1] - v[seg]) / seg_len[seg, None])
    pos = v[seg] + t * (s - cum[seg])[:, None]
    return s, pos, t


def _side_fit(dxy, values, sigmas, subset):
    """A linear fit ``f = c0 + c1 dx + c2 dy`` of ``values`` (n, 2) at offsets ``dxy`` (n, 2) from the station:
    ``c0`` (2,) (the value at the station) and its standard uncertainty (2,), or None (too few / collinear).

    ``sigmas`` (n, 2) px, the points' uncertainties, or None (then from the fit's residuals). Points closer
    than a ``subset`` (px, or None: independent) share pixels, so their errors correlate: the model is
    ``cov_ij = σ_i σ_j ρ_ij`` with ``ρ_ij`` the overlap fraction of their subsets,
    ``max(0, 1 - |Δx| / subset) · max(0, 1 - |Δy| / subset)``.
    """
    n = dxy.shape[0]
    if n < 4:
        return None
    X = np.column_stack([np.ones(n), dxy])
    xtx = X.T @ X
    c = dxy - dxy.mean(axis=0)
    cxx, cyy, cxy = c[:, 0] @ c[:, 0], c[:, 1] @ c[:, 1], c[:, 0] @ c[:, 1]
    if cxx * cyy - cxy ** 2 <= 1e-6 * (cxx + cyy) ** 2:
        return None  # (nearly) collinear points: no plane
    inv = np.linalg.inv(xtx)
    coef = inv @ X.T @ values  # (3, 2)
    row = (inv @ X.T)[0]  # c0 = row . values
    if sigmas is not None:
        if subset:
            gap = np.abs(dxy[:, None, :] - dxy[None, :, :]) / float(subset)  # (n, n, 2)
            rho = np.prod(np.clip(1.0 - gap, 0.0, None), axis=2)
            a = row[:, None] * sigmas  # (n, 2)
            sig = np.sqrt(np.maximum(np.einsum("ik,ij,jk->k", a, rho, a), 0.0))
        else:
            sig = np.sqrt(np.sum(row[:, None] ** 2 * sigmas ** 2, axis=0))
    else:
        dof = n - 3
        resid = values - X @ coef
        s2 = np.sum(resid ** 2, axis=0) / dof if dof > 0 else np.full(2, np.nan)
        sig = np.sqrt(s2 * inv[0, 0])
    return coef[0], sig


def crack_opening(field, crack, *, spacing: float | None = None, radius: float | None = None,
                  min_points: int = 6, subset: int | None = None, gap: float | None = None) -> CrackOpening:
    """Opening and sliding of ``crack`` in a 2-D displacement field.

    At stations every ``spacing`` px along the polyline, the valid points within ``radius`` px of the
    station are split by the side of the station's segment they lie on (``(p - station) · normal``);
    a point counts for a side only when the straight segment from it to the station's side of the
    line does not cross a crack (so a bend or another branch does not lend points). On each side a
    linear fit ``u = c0 + c1 dx + c2 dy`` (and v) is evaluated at the station; the jump
    ``U+ - U-`` projected on the normal is the opening, on the tangent the sliding.

    Parameters
    ----------
    field : Field2D-like
        ``points`` (N, 2) px, ``u``, ``v`` (N,) px, optional ``valid`` (N,) bool and ``sigma_u``,
        ``sigma_v`` (N,) px (used for the uncertainty when finite at every fitted point, with the errors of
        points closer than a ``subset`` correlated by their subsets' overlap), ``subset`` px.
    crack : Crack or anything :func:`as_cracks` takes that holds exactly one crack
    spacing : float, optional
        Distance between stations along the polyline, px. Default: the field's ``step`` (else 5 px).
    radius : float, optional
        Radius of each side's fit neighbourhood, px. Default ``3 * subset`` of the field (else 30 px).
        A linear fit assumes the field is linear within ``radius`` on each side.
    min_points : int
        Fewest points a side's fit needs (>= 4). Default 6.
    subset : int, optional
        The subset size of the field's correlation (px), for the default ``radius`` and ``gap`` and the
        correlation of neighbouring points' errors. Default: the field's ``subset``.
    gap : float, optional
        Points closer than this to the crack (px) are left out of the fits. Default ``subset / 2``: the
        points whose subsets lie wholly on one side. Closer points are measured (a tracker with cracks
        masks their subsets) but biased by the other side's pixels that the current image's B-spline
        interpolation reaches (up to 0.025 px in docs/dic2d.md's case, which moved the opening by
        +0.010 px); without a subset 0.

    Returns
    -------
    CrackOpening
    """
    from kernels.checks import in_range, positive_float, positive_int

    cracks = as_cracks(crack)
    if len(cracks) != 1:
        raise ValueError(f"crack_opening measures one crack at a time, got {len(cracks)}")
    crack = cracks[0]
    try:
        pts = np.asarray(field.points, np.float64)
        u = np.asarray(field.u, np.float64).reshape(-1)
        v = np.asarray(field.v, np.float64).reshape(-1)
    except AttributeError:
        raise ValueError(f"crack_opening needs a displacement field with points, u, v (a dic.Field2D), "
                         f"got {type(field).__name__}") from None
    n = pts.shape[0] if pts.ndim == 2 and pts.shape[1:] == (2,) else -1
    if n < 0 or u.shape != (n,) or v.shape != (n,):
        raise ValueError(f"points must be (N, 2) and u, v (N,), got {pts.shape}, {u.shape}, {v.shape}")
    valid = getattr(field, "valid", None)
    valid = np.ones(n, bool) if valid is None else np.asarray(valid, bool).reshape(-1)
    if valid.shape != (n,):
        raise ValueError(f"valid must have shape ({n},), got {valid.shape}")
    valid = valid & np.isfinite(u) & np.isfinite(v) & np.all(np.isfinite(pts), axis=1)
    su, sv = getattr(field, "sigma_u", None), getattr(field, "sigma_v", None)
    sig = None
    if su is not None and sv is not None:
        sig = np.column_stack([np.asarray(su, np.float64).reshape(-1), np.asarray(sv, np.float64).reshape(-1)])
        if sig.shape != (n, 2):
            raise ValueError(f"sigma_u and sigma_v must have shape ({n},), got {np.shape(su)}, {np.shape(sv)}")
    if spacing is None:
        step = getattr(field, "step", None)
        spacing = float(step) if isinstance(step, (int, float)) and not isinstance(step, bool) and step else 5.0
    spacing = positive_float(spacing, "spacing", detail=" (px)")
    if subset is not None:
        sub = positive_int(subset, "subset", detail=" (px)")
    else:
        sub = getattr(field, "subset", None)
        sub = int(sub) if isinstance(sub, (int, np.integer)) and not isinstance(sub, bool) and sub > 0 else None
    if radius is None:
        radius = 3.0 * sub if sub else 30.0
    radius = positive_float(radius, "radius", detail=" (px)")
    if gap is None:
        gap = sub / 2.0 if sub else 0.0
    gap = in_range(gap, 0.0, math.inf, "gap", detail=" (px)")
    min_points = positive_int(min_points, "min_points", minimum=4)

    s, pos, t = _stations(crack, spacing)
    normal = np.column_stack([-t[:, 1], t[:, 0]])
    S = s.size
    opening, sliding = np.full(S, np.nan), np.full(S, np.nan)
    sig_o, sig_s = np.full(S, np.nan), np.full(S, np.nan)
    n_plus, n_minus = np.zeros(S, np.int64), np.zeros(S, np.int64)
    if gap > 0:  # the distance of each point to the crack's polyline
        a, b = crack.segments
        ab = b - a
        dist = np.full(n, np.inf)
        for a_s, ab_s in zip(a, ab):
            w = np.clip(((pts[:, 0] - a_s[0]) * ab_s[0] + (pts[:, 1] - a_s[1]) * ab_s[1]) / (ab_s @ ab_s), 0.0, 1.0)
            dist = np.minimum(dist, np.hypot(a_s[0] + w * ab_s[0] - pts[:, 0], a_s[1] + w * ab_s[1] - pts[:, 1]))
        valid = valid & (dist >= gap)
    use = np.flatnonzero(valid)
    P = pts[use]
    UV = np.column_stack([u[use], v[use]])
    SG = sig[use] if sig is not None else None
    eps = 1e-3  # px: the station's side of the line, just off it
    for k in range(S):
        d = P - pos[k]
        near = np.flatnonzero(np.hypot(d[:, 0], d[:, 1]) <= radius)
        side = d[near] @ normal[k]
        values = {}
        for sign, counter in ((1.0, n_plus), (-1.0, n_minus)):
            cand = near[side * sign > 0]
            target = pos[k] + sign * eps * normal[k]
            reach = ~segments_cross(P[cand], target[None, :], crack)
            cand = cand[reach]
            counter[k] = cand.size
            if cand.size < min_points:
                continue
            sg = SG[cand] if SG is not None and np.all(np.isfinite(SG[cand])) else None
            fit = _side_fit(d[cand], UV[cand], sg, sub if sg is not None else None)
            if fit is not None:
                values[sign] = fit
        if len(values) == 2:
            (up, sp), (um, sm) = values[1.0], values[-1.0]
            jump = up - um
            var = sp ** 2 + sm ** 2  # (u, v) variances of the jump
            opening[k] = jump @ normal[k]
            sliding[k] = jump @ t[k]
            sig_o[k] = math.sqrt(var @ normal[k] ** 2)
            sig_s[k] = math.sqrt(var @ t[k] ** 2)
    return CrackOpening(stations=pos, arclength=s, tangent=t, normal=normal, opening=opening, sliding=sliding,
                        sigma_opening=sig_o, sigma_sliding=sig_s, n_plus=n_plus, n_minus=n_minus,
                        valid=np.isfinite(opening), crack=crack, radius=float(radius),
                        gap=float(gap))



# -- a crack carried into a moved reference --------------------------------------------------------------------
#: how many nearest POIs :func:`carry_cracks` takes on each side of a vertex (affine extrapolations averaged)
CARRY_NEIGHBOURS = 4
#: the least default spacing of a carried crack's resampled vertices, px (:func:`carry_cracks`)
CARRY_SPACING_PX = 10.0


def _vertex_normals(crack: Crack, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """The polyline resampled at most ``spacing`` px apart (its own vertices kept) and a unit normal at each vertex
    (the segment's; at an inner vertex of the polyline the bisector of its two segments')."""
    v = crack.vertices
    seg = np.diff(v, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    seg_normal = np.column_stack([-seg[:, 1], seg[:, 0]]) / length[:, None]
    out, normals = [v[:1]], []
    for k in range(len(seg)):
        n_sub = max(1, int(math.ceil(length[k] / spacing)))
        t = np.arange(1, n_sub + 1)[:, None] / n_sub
        out.append(v[k] + t * seg[k])
        normals.append(np.repeat(seg_normal[k][None], n_sub, axis=0))
    pts = np.concatenate(out)
    nrm = np.concatenate([seg_normal[:1]] + normals)
    # the original inner vertices: the bisector of their two segments' normals
    ends = np.cumsum([max(1, int(math.ceil(length[k] / spacing))) for k in range(len(seg))])
    for k, idx in enumerate(ends[:-1]):
        b = seg_normal[k] + seg_normal[k + 1]
        nb = np.hypot(*b)
        nrm[idx] = b / nb if nb > 1e-12 else seg_normal[k]
    return pts, nrm


def carry_cracks(cracks, points0, params, usable, *, spacing: float | None = None) -> tuple[Crack, ...]:
    """Declared cracks carried from the reference image into a later frame's image by a measured field.

    A moved reference (:class:`dic.correlation.lagrangian.MovedReference`) tracks from frame ``r``, where the
    crack has moved with the specimen; its subsets must be cut where the crack is in frame ``r``. Each crack is
    resampled at most ``spacing`` px apart (so that the carried polyline follows a non-uniform field), and each
    vertex ``V`` is moved by **the mean of the two faces' displacements** there: on each side of the crack
    (by the vertex's normal; a POI counts for a side only when its straight segment to the vertex's side of the
    line crosses no crack) the :data:`CARRY_NEIGHBOURS` nearest usable POIs extrapolate their affine warps to
    ``V`` (``d + G (V - X0)``), averaged; the two sides are averaged (one side where the other has no POI;
    the nearest POI's where neither has). The carried crack is thus the middle of the opened gap in frame
    ``r``: with the 1 px margin of :func:`blocked_pixels`, a subset on either face keeps its own face's pixels
    and drops the gap and the other face for an opening below 2 px (beyond, the gap's pixels nearer the own face
    than ``opening / 2 - 1`` px are kept). Moving each vertex with one face instead would put the crack on that
    face, and the other face's subsets would reach into the gap.

    Parameters
    ----------
    cracks : anything :func:`as_cracks` takes (reference px)
    points0 : (N, 2) px, the POIs in the reference image
    params : (N, 6|12), frame ``r``'s Lagrangian parameters at ``points0``
    usable : (N,) bool, the points whose parameters carry the cracks (non-finite rows are left out too)
    spacing : float, optional
        Largest distance between the resampled vertices, px. Default: the POI spacing (the median
        nearest-neighbour distance of ``points0``), at least :data:`CARRY_SPACING_PX` (a chord of 10 px
        departs from a field's curve by ``|d²u/ds²| 100 / 8`` px: 0.001 px at a strain gradient of 1e-4 / px).

    Returns
    -------
    tuple of :class:`Crack`, in frame ``r``'s px (empty without cracks).
    """
    from scipy.spatial import cKDTree

    from kernels.checks import as_points, positive_float

    cracks = as_cracks(cracks)
    if not cracks:
        return ()
    pts0 = as_points(points0)
    p = np.asarray(params, np.float64)
    ok = np.asarray(usable, bool)
    if p.ndim != 2 or p.shape[0] != pts0.shape[0] or p.shape[1] not in (6, 12) or ok.shape != (pts0.shape[0],):
        raise ValueError(f"carry_cracks needs points0 (N, 2), params (N, 6|12) and usable (N,) of the same N, "
                         f"got {pts0.shape}, {p.shape} and {ok.shape}")
    ok = ok & np.all(np.isfinite(p), axis=1)
    if not np.any(ok):
        raise ValueError("no usable point to carry the cracks with")
    if spacing is None:
        if pts0.shape[0] > 1:
            dist, _ = cKDTree(pts0).query(pts0, k=2)
            spacing = max(CARRY_SPACING_PX, float(np.median(dist[:, 1])))
        else:
            spacing = CARRY_SPACING_PX
    spacing = positive_float(spacing, "spacing", detail=" (px)")
    h = p.shape[1] // 2
    x0 = pts0[ok]
    d = np.stack([p[ok, 0], p[ok, h]], axis=1)
    G = np.stack([p[ok, 1:3], p[ok, h + 1:h + 3]], axis=1)
    tree = cKDTree(x0)
    k = min(8 * CARRY_NEIGHBOURS, x0.shape[0])
    eps = 1e-3  # px: the vertex's side of the line, just off it
    out = []
    for crack in cracks:
        verts, normals = _vertex_normals(crack, spacing)
        _, near = tree.query(verts, k=k)
        near = near.reshape(len(verts), k)
        moved = np.empty_like(verts)
        for i, (vert, nrm) in enumerate(zip(verts, normals)):
            cand = near[i]
            side = (x0[cand] - vert) @ nrm
            faces = []
            for sign in (1.0, -1.0):
                c = cand[side * sign > 0]
                if c.size:
                    c = c[~segments_cross(x0[c], (vert + sign * eps * nrm)[None, :], cracks)][:CARRY_NEIGHBOURS]
                if c.size:
                    faces.append(np.mean(d[c] + np.einsum("nab,nb->na", G[c], vert - x0[c]), axis=0))
            if not faces:
                c = cand[0]
                faces.append(d[c] + G[c] @ (vert - x0[c]))
            moved[i] = vert + np.mean(faces, axis=0)
        keep = np.concatenate([[True], np.hypot(*np.diff(moved, axis=0).T) > 0])  # no zero-length segment
        out.append(Crack(moved[keep]))
    return tuple(out)
