"""Pointwise least-squares strain of a 2-D displacement field on a grid of points.

Pan, Asundi, Xie & Gao, "Digital image correlation using iterative least squares and pointwise
least squares for displacement field and strain field measurements", Optics and Lasers in
Engineering 47 (2009), doi:10.1016/j.optlaseng.2008.10.014: at each grid point, planes
``u ≈ a0 + a1 Δx + a2 Δy`` and ``v ≈ b0 + b1 Δx + b2 Δy`` are fitted by least squares to the valid
points of a ``window × window`` neighbourhood (fewer at the edges of the grid or next to invalid
points); the slopes are the displacement gradients at that point. For a full, symmetric window
the slopes are exact for any quadratic field (the quadratic terms are orthogonal to the plane's
basis), so the truncation error is third order.

Strains (x right, y down, displacements in px, gradients dimensionless; docs/conventions.md), all
from the same fitted gradient ``H = [[∂u/∂x, ∂u/∂y], [∂v/∂x, ∂v/∂y]]``, ``F = I + H``; the strain
type is chosen by name (:data:`STRAIN_TYPES`, ``strain_type=``):

* ``"green-lagrange"`` (the default, 2-D and stereo alike): ``E = ½(FᵀF − I)``, i.e.
  ``Exx = ∂u/∂x + ½((∂u/∂x)² + (∂v/∂x)²)``, ``Eyy = ∂v/∂y + ½((∂u/∂y)² + (∂v/∂y)²)``,
  ``Exy = ½(∂u/∂y + ∂v/∂x + ∂u/∂x ∂u/∂y + ∂v/∂x ∂v/∂y)``; zero for any rigid motion, what VIC-3D,
  DICe and Ncorr report by default;
* ``"small"`` (engineering, infinitesimal): ``ε = ½(H + Hᵀ)``: ``exx = ∂u/∂x``, ``eyy = ∂v/∂y``,
  ``exy = ½(∂u/∂y + ∂v/∂x)`` (not zero under a finite rotation);
* ``"euler-almansi"``: ``e = ½(I − F⁻ᵀF⁻¹)`` (spatial, in the fixed x, y axes).

``exx``, ``eyy``, ``exy`` of a :class:`StrainField` are the chosen type; ``Exx``, ``Eyy``, ``Exy``
are always Green-Lagrange (as in files before strain types existed). Shears are tensor components
(the engineering shear strain is ``2 exy``). The three agree to first order in ``H``: at a 10 %
stretch (``F = diag(1.1, 1)``) ``exx`` is ``0.105``, ``0.1`` and ``0.0868``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kernels.checks import as_points, odd_int, positive_int

__all__ = ["StrainField", "StrainPlan", "strain", "grid_layout", "check_strain_window", "STRAIN_TYPES",
           "DEFAULT_STRAIN_TYPE", "check_strain_type", "strain_type_label", "strain_from_gradient",
           "stored_strain_type"]

#: the strain types by name, with what a label calls them
STRAIN_TYPES = {"green-lagrange": "Green-Lagrange", "small": "small (engineering)", "euler-almansi": "Euler-Almansi"}
#: the strain type of a run, a recomputation and ``dic.strain`` unless one is chosen (2-D and stereo alike)
DEFAULT_STRAIN_TYPE = "green-lagrange"


def check_strain_type(strain_type, name: str = "strain_type") -> str:
    """The strain type's name (:data:`STRAIN_TYPES`): case and ``_``/space for ``-`` tolerated; ValueError otherwise."""
    if isinstance(strain_type, str):
        key = strain_type.strip().lower().replace("_", "-").replace(" ", "-")
        if key in STRAIN_TYPES:
            return key
    raise ValueError(f"{name} must be one of {', '.join(STRAIN_TYPES)}, got {strain_type!r}")


def strain_type_label(strain_type) -> str:
    """How labels name a strain type, e.g. ``"Green-Lagrange"`` (an unknown or missing name: ``"strain"``)."""
    try:
        return STRAIN_TYPES[check_strain_type(strain_type)]
    except ValueError:
        return "strain"


#: the strain type of a file that names none: what its run computed before strain types existed (the run
#: records' ADDED_OPTIONS, dic/sequence/options.py: 2-D exx was the small strain, stereo the Green-Lagrange one)
_OLD_STRAIN_TYPE = {"dic2d": "small", "stereo": "green-lagrange"}


def stored_strain_type(kind: str, settings: dict | None, frame=None) -> str:
    """The strain type of a result file's strain: its settings' ``strain_type``, else the one a ``frame``
    of it records (2-D: ``frame.attrs["strain_type"]`` of a file's frame, or its StrainField's;
    stereo: ``frame.strain_type``, read as Green-Lagrange where absent), else what its kind
    (``"dic2d"`` or ``"stereo"``) computed before strain types existed (2-D small, stereo Green-Lagrange)."""
    stored = settings.get("strain_type") if isinstance(settings, dict) else None
    if stored is None and frame is not None:
        if kind == "dic2d":
            attrs = getattr(frame, "attrs", None)
            stored = attrs.get("strain_type") if isinstance(attrs, dict) else None
            if stored is None:
                stored = getattr(getattr(frame, "strain", None), "strain_type", None)
        else:
            stored = getattr(frame, "strain_type", None)
    return check_strain_type(stored if stored is not None else _OLD_STRAIN_TYPE.get(kind, DEFAULT_STRAIN_TYPE))


def strain_from_gradient(dudx, dudy, dvdx, dvdy, strain_type: str = DEFAULT_STRAIN_TYPE):
    """``(exx, eyy, exy)`` of the chosen type from the displacement gradient ``H`` (module docstring).

    Arrays of any one shape (dimensionless); NaN in, NaN out. ``exy`` is the tensor shear.
    Euler-Almansi uses ``F⁻ᵀF⁻¹ = (F Fᵀ)⁻¹`` in closed form (a 2 x 2 inverse; ``det F <= 0``, a
    fold, gives NaN).
    """
    kind = check_strain_type(strain_type)
    ux, uy, vx, vy = (np.asarray(a, dtype=np.float64) for a in (dudx, dudy, dvdx, dvdy))
    if kind == "small":
        return ux.copy(), vy.copy(), 0.5 * (uy + vx)
    if kind == "green-lagrange":
        return ux + 0.5 * (ux * ux + vx * vx), vy + 0.5 * (uy * uy + vy * vy), 0.5 * (uy + vx + ux * uy + vx * vy)
    f11, f12, f21, f22 = 1.0 + ux, uy, vx, 1.0 + vy
    b11 = f11 * f11 + f12 * f12  # b = F Fᵀ (left Cauchy-Green)
    b22 = f21 * f21 + f22 * f22
    b12 = f11 * f21 + f12 * f22
    det = f11 * f22 - f12 * f21
    with np.errstate(invalid="ignore", divide="ignore"):
        det2 = np.where(det > 0, det * det, np.nan)  # det b = (det F)²
        return 0.5 * (1.0 - b22 / det2), 0.5 * (1.0 - b11 / det2), 0.5 * (b12 / det2)


@dataclass
class StrainField:
    """Strain at the points of a 2-D DIC result.

    All per-point arrays are float64 of shape (N,), aligned with ``points``; entries where
    ``valid`` is False are NaN.

    Attributes
    ----------
    points : (N, 2) float64
        Reference positions ``(x, y)`` px (those of the displacement field).
    dudx, dudy, dvdx, dvdy :
        Displacement gradients (dimensionless).
    exx, eyy, exy :
        Strain of the type ``strain_type`` (module docstring); ``exy`` is the tensor shear.
    Exx, Eyy, Exy :
        Green-Lagrange strain, whatever ``strain_type``; ``Exy`` is the tensor shear.
    valid : (N,) bool
        The point and at least ``min_points`` non-collinear neighbours were valid.
    n_fit : (N,) int
        Number of points in each fit.
    window : int
        Fit window side in grid points.
    step : (2,) float
        Grid spacing ``(dx, dy)`` px.
    grid_index : (N, 2) int
        Column and row of each point in the grid (see :meth:`to_grid`).
    grid_shape : (rows, cols)
    strain_type : str
        What ``exx``, ``eyy``, ``exy`` are: ``"green-lagrange"``, ``"small"`` or ``"euler-almansi"``.
    """

    points: np.ndarray
    dudx: np.ndarray
    dudy: np.ndarray
    dvdx: np.ndarray
    dvdy: np.ndarray
    exx: np.ndarray
    eyy: np.ndarray
    exy: np.ndarray
    Exx: np.ndarray
    Eyy: np.ndarray
    Exy: np.ndarray
    valid: np.ndarray
    n_fit: np.ndarray
    window: int
    step: tuple[float, float]
    grid_index: np.ndarray
    grid_shape: tuple[int, int]
    strain_type: str = DEFAULT_STRAIN_TYPE

    #: names of the per-point strain/gradient components
    COMPONENTS = ("dudx", "dudy", "dvdx", "dvdy", "exx", "eyy", "exy", "Exx", "Eyy", "Exy")

    def to_grid(self, name: str) -> np.ndarray:
        """The component ``name`` as a (rows, cols) map, NaN where absent or invalid."""
        if name not in self.COMPONENTS:
            raise ValueError(f"unknown strain component {name!r}; choose one of {', '.join(self.COMPONENTS)}")
        out = np.full(self.grid_shape, np.nan)
        out[self.grid_index[:, 1], self.grid_index[:, 0]] = getattr(self, name)
        return out

    def grid_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """x (cols,) and y (rows,) coordinates of the grid lines, px."""
        x0 = self.points[:, 0].min() - self.grid_index[:, 0].min() * self.step[0] if len(self.points) else 0.0
        y0 = self.points[:, 1].min() - self.grid_index[:, 1].min() * self.step[1] if len(self.points) else 0.0
        return (x0 + self.step[0] * np.arange(self.grid_shape[1]), y0 + self.step[1] * np.arange(self.grid_shape[0]))


def grid_layout(points, *, rtol: float = 1e-6):
    """Recover the regular grid of ``points`` (N, 2): per-point (col, row), the shape and the step.

    Points may be any subset of a regular lattice ``(x0 + i dx, y0 + j dy)`` (an ROI, a masked
    grid). Raises ``ValueError`` when they are not on one.
    """
    pts = as_points(points)
    index = np.empty(pts.shape, dtype=np.int64)
    shape, step = [0, 0], [1.0, 1.0]
    for axis in range(2):
        vals = np.unique(pts[:, axis])
        if vals.size == 1:
            d = 1.0
        else:
            d = float(np.min(np.diff(vals)))
        k = (pts[:, axis] - vals[0]) / d
        ki = np.rint(k)
        tol = max(rtol * max(1.0, np.abs(vals).max() / d), 1e-9)
        if np.max(np.abs(k - ki)) > tol:
            raise ValueError(
                "points are not on a regular grid (strain needs the grid of dic.grid or a subset of it); "
                f"{'xy'[axis]} coordinates are not multiples of the spacing {d:g} px")
        index[:, axis] = ki.astype(np.int64)
        shape[1 - axis] = int(ki.max()) + 1
        step[axis] = d
    flat = index[:, 1] * shape[1] + index[:, 0]
    if np.unique(flat).size != flat.size:
        raise ValueError("points contain duplicates; each grid node may appear once")
    return index, (shape[0], shape[1]), (step[0], step[1])


def _field_arrays(field):
    try:
        points = np.asarray(field.points, dtype=np.float64)
        u = np.asarray(field.u, dtype=np.float64).reshape(-1)
        v = np.asarray(field.v, dtype=np.float64).reshape(-1)
    except AttributeError:
        raise ValueError(
            f"strain() needs a displacement field with points, u, v (and valid), e.g. a dic.Field2D; "
            f"got {type(field).__name__}") from None
    n = points.shape[0] if points.ndim == 2 else -1
    if u.shape != (n,) or v.shape != (n,):
        raise ValueError(f"u and v must have shape ({n},) to match points {points.shape}, got {u.shape}, {v.shape}")
    valid = getattr(field, "valid", None)
    valid = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool).reshape(-1)
    if valid.shape != (n,):
        raise ValueError(f"valid must have shape ({n},), got {valid.shape}")
    return points, u, v, valid & np.isfinite(u) & np.isfinite(v)


def _default_min_points(window: int) -> int:
    return max(3, (window // 2 + 1) ** 2)  # a corner of the grid: a quarter window


def check_strain_window(window, grid_shape, *, min_points: int | None = None) -> tuple[int, int]:
    """``(window, min_points)`` checked for a grid of ``grid_shape = (ny, nx)`` points.

    ``window`` must be odd and >= 3; ``min_points`` (default ``(window // 2 + 1)²``) in
    ``[3, window²]``. A window for which no grid point could ever gather ``min_points`` points
    (even with all of them valid) would give no strain at all: that is a ``ValueError`` naming the
    largest window that works on this grid (e.g. ``2 n − 1`` on an ``n × n`` grid). A grid that no
    window can serve (one row or one column of points: collinear) is not an error; its points
    come out without strain (``valid`` False).
    """
    window = odd_int(window, "window", detail=" (grid points per side)")
    given = min_points is not None
    if not given:
        min_points = _default_min_points(window)
    mp = positive_int(min_points, "min_points") if given else min_points
    if mp < 3 or mp > window * window:
        raise ValueError(f"min_points must be in [3, {window * window}] for window {window}, got {min_points!r}")
    ny, nx = (int(v) for v in grid_shape)

    def reach(w: int) -> int:  # the most points a fit window of side w can hold on this grid
        return min(ny, w) * min(nx, w)

    if reach(window) < mp:
        usable = [w for w in range(3, min(window, 2 * max(ny, nx) + 1), 2)
                  if reach(w) >= (mp if given else _default_min_points(w))]
        if usable:  # the window is to blame (a grid too thin for any window is not: its points come out invalid)
            raise ValueError(f"strain window {window} needs {mp} valid points per fit, but no point of the {ny} x {nx} "
                             f"grid has more than {reach(window)} within its window, so no strain could be computed; "
                             f"use a window of at most {usable[-1]}")
    return window, mp


def _kernels(window: int):
    """The fit window's weights: (1, Δcol, Δrow, Δcol², Δcol Δrow, Δrow²), each (window, window)."""
    h = window // 2
    off = np.arange(-h, h + 1, dtype=np.float64)
    kx = np.broadcast_to(off[None, :], (window, window))  # Δcol
    ky = np.broadcast_to(off[:, None], (window, window))  # Δrow
    ones = np.ones((window, window))
    return ones, kx, ky, kx * kx, kx * ky, ky * ky


def _correlate(a, k):
    """Σ over the window centred on each node of ``a * k`` (zeros outside the grid).

    ``scipy.ndimage.correlate(a, k, mode="constant", cval=0.0)`` bit for bit (tested): the same
    products of the kernel's nonzero weights (``|w| > DBL_EPSILON``, C order) added to 0.0 in the same
    order, for an odd (window, window) kernel; without importing scipy.ndimage, which costs 0.4 s of
    CPU (``specula strain``). Cost: one multiply-add over the grid per nonzero weight.
    """
    a = np.asarray(a, dtype=np.float64)
    ky, kx = k.shape
    hy, hx = ky // 2, kx // 2
    ny, nx = a.shape
    pad = np.zeros((ny + 2 * hy, nx + 2 * hx))
    pad[hy:hy + ny, hx:hx + nx] = a
    out = np.zeros((ny, nx))
    eps = np.finfo(np.float64).eps
    for i in range(ky):
        for j in range(kx):
            w = float(k[i, j])
            if abs(w) > eps:
                out += pad[i:i + ny, j:j + nx] * w
    return out


class StrainPlan:
    """What :func:`strain` works out from the points alone, computed once for fields that share them.

    The frames of a sequence all have the same POIs. A plan holds their grid layout
    (:func:`grid_layout`: ``np.unique`` over the points) and the grid cell of each point, and,
    for the last set of valid points it was given, the fits' normal matrices and which points
    have a fit. These change only when the valid points change. ``plan.strain(field)`` is
    bit for bit ``strain(field, window=window, min_points=min_points)``; :func:`strain` itself
    runs through a plan made for the call.

    Parameters
    ----------
    points : (N, 2) float
        The POIs (px) on a regular grid or a subset of one, as for :func:`strain`.
    window, min_points : int
        As for :func:`strain` (checked against the grid: :func:`check_strain_window`).
    cracks : optional
        Declared cracks (:mod:`dic.cracks`): a point's fit leaves out the neighbours whose straight
        segment from the point crosses a crack (those points' fits are summed directly rather than by
        the grid correlation). Default: none.
    strain_type : str
        What ``exx``, ``eyy``, ``exy`` are (:data:`STRAIN_TYPES`; default Green-Lagrange).

    Attributes
    ----------
    points, grid_index, grid_shape, step, window, min_points, strain_type
        The points (a read-only copy) and their grid (as in :class:`StrainField`).

    Memory: about 40 bytes per point for the layout, and about 100 more for the
    normal matrices of the last set of valid points. Calls from several threads are safe; each
    call reads the cached entry once.

    Raises
    ------
    ValueError
        Points not on a regular grid, duplicates, a window no grid point can fill.
    """

    def __init__(self, points, *, window: int = 5, min_points: int | None = None, cracks=None,
                 strain_type: str = DEFAULT_STRAIN_TYPE):
        self.strain_type = check_strain_type(strain_type)
        pts = np.array(as_points(points), dtype=np.float64, order="C", copy=True)
        index, shape, step = grid_layout(pts)
        self.window, self.min_points = check_strain_window(window, shape, min_points=min_points)
        pts.flags.writeable = False
        index.flags.writeable = False
        self.points = pts
        self.grid_index = index
        self.grid_shape = shape
        self.step = step
        self._flat = index[:, 1] * shape[1] + index[:, 0]  # each point's node in the flattened grid
        self._flat.flags.writeable = False
        self._weights = _kernels(self.window)
        self._cut = _crack_cut_windows(pts, index, shape, self.window, cracks)  # (rows, neighbours, offsets) or None
        self._fits_cache = None  # (valid, flat of the valid points, ok, n_fit, flat of the ok points, normal matrices)

    def __repr__(self) -> str:
        return (f"StrainPlan({len(self.points)} points, grid {self.grid_shape[0]} x {self.grid_shape[1]}, "
                f"window {self.window}, {self.strain_type})")

    def matches(self, points) -> bool:
        """Whether ``points`` (N, 2) are this plan's points (equal values, same order)."""
        pts = np.asarray(points)
        return pts.shape == self.points.shape and bool(np.array_equal(pts, self.points))

    def strain(self, field) -> StrainField:
        """:func:`strain` of ``field`` (its ``points`` must be the plan's; ValueError otherwise)."""
        points, u, v, valid = _field_arrays(field)
        if not self.matches(points):
            raise ValueError(f"the field's points ({points.shape[0]} points) are not those of this StrainPlan "
                             f"({len(self.points)} points): make a plan of the field's points")
        return self._strain(points, u, v, valid)

    def _fits(self, valid: np.ndarray):
        """The parts of the fits that depend on which points are valid (cached for the last ``valid``)."""
        cached = self._fits_cache
        if cached is not None and np.array_equal(cached[0], valid):
            return cached
        flat = self._flat
        mask = np.zeros(self.grid_shape)
        flat_sel = flat[valid]
        mask.reshape(-1)[flat_sel] = 1.0
        s0, sx, sy, sxx, sxy, syy = (_correlate(mask, k).reshape(-1)[flat] for k in self._weights)
        if self._cut is not None:  # windows a crack cuts: their sums over the neighbours on the point's side
            rows, nbr, off = self._cut
            use = (nbr >= 0) & valid[np.maximum(nbr, 0)]
            for m, w in zip((s0, sx, sy, sxx, sxy, syy), (1.0, off[0], off[1], off[0] ** 2, off[0] * off[1], off[1] ** 2)):
                m[rows] = np.sum(use * w, axis=1)
        n_fit = np.rint(s0).astype(np.int64)
        # a fit needs enough points that are not all on one line: the centred second moments'
        # determinant is 0 for collinear points (in grid units, so the threshold is scale-free)
        with np.errstate(invalid="ignore", divide="ignore"):
            cxx = sxx - sx ** 2 / s0
            cyy = syy - sy ** 2 / s0
            cxy = sxy - sx * sy / s0
            det = cxx * cyy - cxy**2
        ok = valid & (n_fit >= self.min_points) & (det > 1e-6 * np.maximum(s0, 1.0) ** 2)
        at = np.flatnonzero(ok)
        normal = np.empty((at.size, 3, 3))  # the normal matrix of each fit
        for i, row in enumerate(((s0, sx, sy), (sx, sxx, sxy), (sy, sxy, syy))):
            for j, m in enumerate(row):
                normal[:, i, j] = m[at]
        cached = (valid.copy(), flat_sel, ok, n_fit, flat[ok], normal)
        self._fits_cache = cached
        return cached

    def _strain(self, points, u, v, valid) -> StrainField:
        _, flat_sel, ok, n_fit, flat_ok, normal = self._fits(valid)
        step = self.step
        ug = np.zeros(self.grid_shape)
        vg = np.zeros(self.grid_shape)
        ug.reshape(-1)[flat_sel] = u[valid]
        vg.reshape(-1)[flat_sel] = v[valid]
        grads = np.full((points.shape[0], 4), np.nan)
        if normal.shape[0]:
            rhs = np.empty((normal.shape[0], 3, 2))  # Σ u, Σ u Δcol, Σ u Δrow (and v) over each window
            for j, k in enumerate(self._weights[:3]):
                rhs[:, j, 0] = _correlate(ug, k).reshape(-1)[flat_ok]
                rhs[:, j, 1] = _correlate(vg, k).reshape(-1)[flat_ok]
            if self._cut is not None:
                rows, nbr, off = self._cut
                at = np.flatnonzero(ok)
                pos = np.searchsorted(at, rows)  # the cut rows among the fits
                hit = (pos < at.size) & (at[np.minimum(pos, at.size - 1)] == rows)
                if hit.any():
                    take = nbr[hit]
                    use = (take >= 0) & valid[np.maximum(take, 0)]
                    for j, w in enumerate((1.0, off[0], off[1])):
                        rhs[pos[hit], j, 0] = np.sum(np.where(use, u[np.maximum(take, 0)], 0.0) * w, axis=1)
                        rhs[pos[hit], j, 1] = np.sum(np.where(use, v[np.maximum(take, 0)], 0.0) * w, axis=1)
            sol = np.linalg.solve(normal, rhs)
            grads[ok] = np.stack([sol[:, 1, 0] / step[0], sol[:, 2, 0] / step[1],
                                  sol[:, 1, 1] / step[0], sol[:, 2, 1] / step[1]], -1)
        ux, uy, vx, vy = grads.T
        Exx, Eyy, Exy = strain_from_gradient(ux, uy, vx, vy, "green-lagrange")
        if self.strain_type == "green-lagrange":
            exx, eyy, exy = Exx.copy(), Eyy.copy(), Exy.copy()
        else:
            exx, eyy, exy = strain_from_gradient(ux, uy, vx, vy, self.strain_type)
        return StrainField(
            points=points.copy(), dudx=ux, dudy=uy, dvdx=vx, dvdy=vy, exx=exx, eyy=eyy, exy=exy,
            Exx=Exx, Eyy=Eyy, Exy=Exy,
            valid=ok.copy(), n_fit=n_fit.copy(), window=self.window, step=step, grid_index=self.grid_index.copy(),
            grid_shape=self.grid_shape, strain_type=self.strain_type,
        )


def _crack_cut_windows(points, index, shape, window: int, cracks):
    """The fit windows that a declared crack cuts: ``(rows (m,), neighbours (m, w²), (Δcol, Δrow) (2, w²))``,
    ``neighbours`` the point at each window node that the point reaches without crossing a crack (-1: none,
    or across); None when no window is cut (or no cracks)."""
    from .cracks import as_cracks, segments_cross

    cracks = as_cracks(cracks)
    if not cracks:
        return None
    h = window // 2
    dr, dc = np.mgrid[-h:h + 1, -h:h + 1]
    off = np.stack([dc.ravel(), dr.ravel()]).astype(np.float64)  # (2, w²) Δcol, Δrow: the order of _kernels
    node = np.full(shape, -1, np.int64)
    node[index[:, 1], index[:, 0]] = np.arange(points.shape[0])
    cols = index[:, 0, None] + dc.ravel()[None, :]
    rows = index[:, 1, None] + dr.ravel()[None, :]
    inside = (cols >= 0) & (cols < shape[1]) & (rows >= 0) & (rows < shape[0])
    nbr = np.where(inside, node[np.clip(rows, 0, shape[0] - 1), np.clip(cols, 0, shape[1] - 1)], -1)
    across = (nbr >= 0) & segments_cross(points[:, None, :], points[np.maximum(nbr, 0)], cracks)
    cut = np.flatnonzero(across.any(axis=1))
    if cut.size == 0:
        return None
    return cut, np.where(across[cut], -1, nbr[cut]), off


def strain(field, *, window: int = 5, min_points: int | None = None, cracks=None,
           strain_type: str = DEFAULT_STRAIN_TYPE) -> StrainField:
    """Pointwise least-squares strain of a displacement field (``exx``... of the chosen type).

    Parameters
    ----------
    field : Field2D-like
        Has ``points`` (N, 2) px on a regular grid (or a subset of one), ``u``, ``v`` (N,) px, and
        optionally ``valid`` (N,) bool. Invalid and non-finite points are left out of every fit.
    window : int
        Side of the square fit window in grid points (odd, >= 3). The strain's spatial resolution
        is about ``(window - 1) · step + subset`` px.
    min_points : int, optional
        Fewest valid points a fit needs (default ``(window // 2 + 1)²``, what a grid corner has).
        A window that no grid point can fill is an error (:func:`check_strain_window`).
    cracks : optional
        Declared cracks (:mod:`dic.cracks`): no fit reaches across one (:class:`StrainPlan`).
    strain_type : str
        ``"green-lagrange"`` (default), ``"small"`` or ``"euler-almansi"``: what ``exx``, ``eyy``,
        ``exy`` are (module docstring); ``Exx``, ``Eyy``, ``Exy`` are always Green-Lagrange.

    Returns
    -------
    StrainField
    """
    points, u, v, valid = _field_arrays(field)
    return StrainPlan(points, window=window, min_points=min_points, cracks=cracks,
                      strain_type=strain_type)._strain(points, u, v, valid)
