"""2-D subset DIC: POI grids, initial guesses and IC-GN tracking into :class:`Field2D` results.

The heavy lifting is done by Warp kernels: :mod:`kernels.icgn` (IC-GN / ZNSSD, 1st and 2nd order,
Pan et al. 2013, doi:10.1007/s11340-012-9640-x; Gao et al. 2015, doi:10.1016/j.optlaseng.2014.04.002)
and :mod:`kernels.search` (integer initial guesses). This module validates input, builds POI
grids, runs the initial-guess strategies (ZNCC window search, FFT phase correlation, Gaussian-pyramid
coarse-to-fine, reliability-guided propagation after Pan et al. 2009, doi:10.1364/AO.48.001535) and
packs the results. See docs/dic2d.md for the algorithm, parameters and measured accuracy.

Conventions (docs/conventions.md): points ``(x, y)`` in reference pixels (pixel (0, 0) is the
centre of the top-left pixel), displacements ``(u, v)`` in pixels, parameters in
:data:`kernels.conventions.PARAMS_1ST` / ``PARAMS_2ND`` order, statuses :class:`Status`.
"""
from __future__ import annotations

import heapq
import math
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kernels._device import as_float32_image, resolve_device
from kernels.conventions import Status, param_names
from kernels.icgn import (
    ReferenceSubsets,
    check_subset_order,
    icgn,
    n_params,
    prepare_current,
    prepare_reference,
    prepare_subsets,
)
from kernels.search import phase_correlation, pyramid, zncc_search

__all__ = ["Field2D", "Tracker", "grid", "track", "SEARCH_METHODS"]

#: initial-guess strategies accepted by ``search=``
SEARCH_METHODS = ("zncc", "fft", "pyramid", "rg")

#: statuses whose result is usable (subject to the ZNCC threshold)
_GOOD = (int(Status.CONVERGED), int(Status.MAX_ITERATIONS))


# ----------------------------------------------------------------------------------------------
# results


@dataclass
class Field2D:
    """A 2-D displacement field at POIs of the reference image.

    Attributes
    ----------
    points : (N, 2) float64
        POIs ``(x, y)`` in reference pixels.
    u, v : (N,) float64
        Displacement at each POI (px), ``params[:, 0]`` and ``params[:, 3 | 6]``.
    params : (N, 6 | 12) float64
        Shape-function parameters in ``PARAMS_1ST`` / ``PARAMS_2ND`` order.
    zncc : (N,) float64
        Zero-normalised cross-correlation of the last iteration (NaN where not computed).
    iterations : (N,) int32
    status : (N,) int32
        :class:`kernels.conventions.Status` code per POI.
    valid : (N,) bool
        ``status`` in (CONVERGED, MAX_ITERATIONS) and ``zncc >= zncc_min``.
    subset, order : int
        Subset size (px) and shape-function order.
    step : int or None
        Grid spacing when the points come from :func:`grid` (used by :meth:`to_grid`).
    zncc_min : float
        ZNCC threshold behind ``valid``.
    """

    points: np.ndarray
    u: np.ndarray
    v: np.ndarray
    params: np.ndarray
    zncc: np.ndarray
    iterations: np.ndarray
    status: np.ndarray
    valid: np.ndarray
    subset: int
    order: int
    step: int | None = None
    zncc_min: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def param_names(self) -> tuple[str, ...]:
        return param_names(self.order)

    def _lattice(self):
        pts = self.points
        if pts.shape[0] == 0:
            raise ValueError("the field has no points")
        out = []
        for axis in (0, 1):
            c = pts[:, axis]
            lo = c.min()
            step = self.step
            if step is None:
                d = np.diff(np.unique(c))
                step = float(d.min()) if d.size else 1.0
            k = (c - lo) / step
            if not np.allclose(k, np.rint(k), atol=1e-6):
                raise ValueError("the points are not on a regular grid (give step= or use grid())")
            out.append((lo, step, np.rint(k).astype(np.int64)))
        return out

    def grid_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """``(xs, ys)``: coordinates of the grid columns and rows spanned by the points."""
        (x0, sx, kx), (y0, sy, ky) = self._lattice()
        return x0 + sx * np.arange(kx.max() + 1), y0 + sy * np.arange(ky.max() + 1)

    def to_grid(self, values="u", fill=np.nan) -> np.ndarray:
        """A per-point quantity as a 2-D map on the points' grid.

        Parameters
        ----------
        values : str or array-like (N,) / (N, k)
            A field name (``"u"``, ``"v"``, ``"zncc"``, ``"status"``, ``"valid"``, ``"iterations"``
            or a parameter name such as ``"ux"``) or an array with one row per point.
        fill : value for grid nodes without a point (ROIs); NaN by default.

        Returns
        -------
        np.ndarray (ny, nx) or (ny, nx, k); row ``i`` is ``ys[i]``, column ``j`` is ``xs[j]``
        (:meth:`grid_axes`). Invalid points keep their value: mask with ``to_grid("valid")``.
        """
        if isinstance(values, str):
            if values in ("u", "v", "zncc", "status", "valid", "iterations"):
                arr = np.asarray(getattr(self, values))
            elif values in self.param_names:
                arr = self.params[:, self.param_names.index(values)]
            else:
                raise ValueError(f"unknown quantity {values!r}; use u, v, zncc, status, valid, iterations or "
                                 f"one of {self.param_names}")
        else:
            arr = np.asarray(values)
        if arr.shape[0] != self.n_points:
            raise ValueError(f"values must have one row per point ({self.n_points}), got shape {arr.shape}")
        (_, _, kx), (_, _, ky) = self._lattice()
        nx, ny = int(kx.max()) + 1, int(ky.max()) + 1
        if arr.dtype == bool and isinstance(fill, float) and np.isnan(fill):
            fill = False  # boolean maps (valid) are False where there is no point
        dtype = np.result_type(arr.dtype, np.min_scalar_type(fill) if not isinstance(fill, float) else np.float64)
        if arr.dtype == bool and fill is False:
            dtype = bool
        out = np.full((ny, nx) + arr.shape[1:], fill, dtype=dtype)
        out[ky, kx] = arr
        return out


# ----------------------------------------------------------------------------------------------
# input checking


def _as_image(image, name: str) -> np.ndarray:
    """Path, NumPy array (8/16-bit, float) or torch tensor -> float32 (H, W), validated."""
    if isinstance(image, (str, os.PathLike)):
        from dic.io import read_image

        image = read_image(image)
    arr = as_float32_image(image, name)
    if arr.shape[0] < 4 or arr.shape[1] < 4:
        raise ValueError(f"{name} must be at least 4x4 pixels, got shape {arr.shape}")
    return arr


def _shape_of(shape) -> tuple[int, int]:
    if hasattr(shape, "shape") and not isinstance(shape, tuple):
        shape = tuple(shape.shape)
    try:
        h, w = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise ValueError(f"shape must be (H, W), got {shape!r}") from None
    if h <= 0 or w <= 0:
        raise ValueError(f"shape must be positive, got {(h, w)}")
    return h, w


def _check_step(step) -> int:
    if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step < 1:
        raise ValueError(f"step must be a positive integer number of pixels, got {step!r}")
    return int(step)


def grid(shape, step: int, *, margin: int | None = None, roi=None) -> np.ndarray:
    """POIs on a regular grid of integer pixels.

    Parameters
    ----------
    shape : (H, W) or a 2-D array (its shape is used)
    step : int >= 1
        Grid spacing (px), the same along x and y.
    margin : int, optional
        Distance of the first and last rows/columns from the image border (px); default 0.
        :func:`track` uses ``subset // 2`` so that every subset fits in the image.
    roi : None, (H, W) bool mask, or (x0, y0, x1, y1)
        Keep only POIs inside the mask, or inside the inclusive pixel box.

    Returns
    -------
    (N, 2) float64 ``(x, y)``, x varying fastest (row-major), starting at ``(margin, margin)``.

    Raises
    ------
    ValueError : bad step/margin/roi, or no POI left (empty ROI).
    """
    h, w = _shape_of(shape)
    step = _check_step(step)
    margin = 0 if margin is None else margin
    if isinstance(margin, bool) or not isinstance(margin, (int, np.integer)) or margin < 0:
        raise ValueError(f"margin must be a non-negative integer, got {margin!r}")
    xs = np.arange(margin, w - margin, step)
    ys = np.arange(margin, h - margin, step)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1).astype(np.float64)
    if roi is not None:
        if isinstance(roi, np.ndarray) and roi.ndim == 2:
            if roi.shape != (h, w):
                raise ValueError(f"roi mask must have the image shape {(h, w)}, got {roi.shape}")
            mask = roi.astype(bool)
            keep = mask[pts[:, 1].astype(int), pts[:, 0].astype(int)] if pts.size else np.zeros(0, bool)
        else:
            try:
                x0, y0, x1, y1 = (float(c) for c in roi)
            except (TypeError, ValueError):
                raise ValueError(f"roi must be an (H, W) boolean mask or (x0, y0, x1, y1), got {roi!r}") from None
            if not (x1 >= x0 and y1 >= y0):
                raise ValueError(f"roi box (x0, y0, x1, y1) = {roi!r} is empty (needs x1 >= x0 and y1 >= y0)")
            keep = (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)
        pts = pts[keep]
    if pts.shape[0] == 0:
        raise ValueError(
            f"no POI left: image {(h, w)}, step {step}, margin {margin}"
            + (", roi leaves none (empty ROI)" if roi is not None else "")
        )
    return pts


def _as_points(points) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must be an (N, 2) array of (x, y), got shape {pts.shape}")
    if pts.shape[0] == 0:
        raise ValueError("points is empty")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points contain NaN or infinite values")
    return pts


def _guess_params(guess, n: int, order: int) -> np.ndarray | None:
    """Normalise a guess to (N, K) float64 parameters (None stays None)."""
    if guess is None:
        return None
    k = n_params(order)
    if isinstance(guess, Field2D):
        if guess.n_points != n:
            raise ValueError(f"guess field has {guess.n_points} points, expected {n}")
        g = _convert_order(np.asarray(guess.params, dtype=np.float64), order)
        return np.where(np.isfinite(g), g, 0.0)
    g = np.asarray(guess, dtype=np.float64)
    if g.shape == (2,):
        g = np.broadcast_to(g, (n, 2))
    if g.shape == (n, 2):
        out = np.zeros((n, k))
        out[:, 0] = g[:, 0]
        out[:, k // 2] = g[:, 1]
        g = out
    elif g.shape in ((n, 6), (n, 12)):
        g = _convert_order(g, order)
    else:
        raise ValueError(f"guess must be (u, v), an (N, 2) array of (u, v), an (N, {k}) parameter array or a "
                         f"Field2D, with N = {n}; got shape {g.shape}")
    if not np.all(np.isfinite(g)):
        raise ValueError("guess contains NaN or infinite values")
    return np.ascontiguousarray(g)


def _convert_order(params: np.ndarray, order: int) -> np.ndarray:
    k = n_params(order)
    if params.shape[1] == k:
        return params
    if k == 6:  # 2nd -> 1st: drop second derivatives
        return params[:, [0, 1, 2, 6, 7, 8]]
    out = np.zeros((params.shape[0], 12))
    out[:, [0, 1, 2, 6, 7, 8]] = params
    return out


# ----------------------------------------------------------------------------------------------
# initial guesses


def _nearest_fill(points: np.ndarray, params: np.ndarray, ok: np.ndarray, targets: np.ndarray, scale: float = 1.0):
    """Guess at ``targets`` from the nearest ``ok`` point's affine prediction (coordinates / scale).

    ``points``/``params`` live on a level whose coordinates are ``scale`` times smaller than the
    targets' (``scale = 2`` between pyramid levels); displacements are multiplied back by scale.
    Returns (M, 6) 1st-order parameters.
    """
    from scipy.spatial import cKDTree

    out = np.zeros((targets.shape[0], 6))
    if not np.any(ok):
        return out
    src = points[ok]
    p = _convert_order(params[ok], 1)
    t = targets / scale
    _, idx = cKDTree(src).query(t, k=1)
    d = t - src[idx]
    pi = p[idx]
    out[:, 0] = scale * (pi[:, 0] + pi[:, 1] * d[:, 0] + pi[:, 2] * d[:, 1])
    out[:, 3] = scale * (pi[:, 3] + pi[:, 4] * d[:, 0] + pi[:, 5] * d[:, 1])
    out[:, [1, 2, 4, 5]] = pi[:, [1, 2, 4, 5]]
    return out


def _median_outliers(points: np.ndarray, uv: np.ndarray, ok: np.ndarray, step: float, threshold: float) -> np.ndarray:
    """Flag points whose (u, v) differ from the median of their valid neighbours by > threshold px."""
    from scipy.spatial import cKDTree

    if np.count_nonzero(ok) < 5:
        return ok
    src = points[ok]
    tree = cKDTree(src)
    neigh = tree.query_ball_point(points, r=1.5 * step)
    ok = ok.copy()
    vals = uv[ok]
    for i, nb in enumerate(neigh):
        if not ok[i] or len(nb) < 4:
            continue
        med = np.median(vals[nb], axis=0)
        if np.max(np.abs(uv[i] - med)) > threshold:
            ok[i] = False
    return ok


def _pyramid_guess(ref: np.ndarray, cur: np.ndarray, targets: np.ndarray, subset: int, radius: int,
                   zncc_min: float, device: str) -> np.ndarray:
    """Coarse-to-fine 1st-order guesses at ``targets`` (Gaussian pyramid, ZNCC search at the top).

    Levels: the coarsest level sees motions up to ``radius / 2^L <= 4`` px, limited so that the
    coarsest image still holds a few subsets. At the top a ZNCC window search seeds IC-GN on a grid
    of step ``subset // 2``; each finer level re-runs IC-GN from the nearest valid coarse result
    (outliers removed by a neighbourhood-median test), and the final level's field predicts
    ``targets``.
    """
    levels = max(0, math.ceil(math.log2(max(radius, 1) / 4.0)))
    while levels > 0 and min(ref.shape) / 2 ** levels < 2 * subset + 1:
        levels -= 1
    pr = pyramid(ref, levels, device=device)
    pc = pyramid(cur, levels, device=device)
    r = subset // 2
    step = max(2, subset // 2)
    prev = None  # (points, params, ok) at the coarser level
    for lvl in range(levels, 0, -1):
        img_r, img_c = pr[lvl], pc[lvl]
        pts = grid(img_r.shape, step, margin=r)
        if prev is None:
            top = int(math.ceil(radius / 2 ** lvl)) + 1
            uv, _ = zncc_search(img_r, img_c, pts, top, subset=subset, device=device)
            g = np.zeros((pts.shape[0], 6))
            g[:, 0], g[:, 3] = uv[:, 0], uv[:, 1]
        else:
            g = _nearest_fill(*prev, pts, scale=2.0)
        subs = prepare_subsets(prepare_reference(img_r, device=device), pts, subset=subset, order=1)
        res = icgn(subs, img_c, guess=g).numpy()
        p = res["params"].astype(np.float64)
        ok = np.isin(res["status"], _GOOD) & (res["zncc"] >= zncc_min)
        ok = _median_outliers(pts, p[:, [0, 3]], ok, step, threshold=2.0)
        prev = (pts, p, ok)
    if prev is None:  # no pyramid level: a ZNCC search at full resolution
        uv, _ = zncc_search(ref, cur, targets, radius, subset=subset, device=device)
        g = np.zeros((targets.shape[0], 6))
        g[:, 0], g[:, 3] = uv[:, 0], uv[:, 1]
        return g
    return _nearest_fill(*prev, targets, scale=2.0)


# ----------------------------------------------------------------------------------------------
# tracking


class Tracker:
    """Track one reference image into any number of current images (reference work done once).

    Parameters
    ----------
    reference : array-like (H, W), path or torch tensor
        Grey reference image (8/16-bit or float; grey levels keep their scale).
    points : (N, 2) array of POIs ``(x, y)``, optional
        Integer or sub-pixel positions. Default: ``grid(shape, step, margin=subset // 2, roi=roi)``.
    step : int, optional
        Grid spacing when ``points`` is not given (default ``subset // 2``).
    roi : (H, W) bool mask or (x0, y0, x1, y1), optional
        Region of interest for the default grid.
    subset : odd int >= 3
        Subset size (px). Default 21.
    order : 1 or 2
        Shape function: 1 (affine, 6 parameters) or 2 (quadratic, 12 parameters).
    search : None, "zncc", "fft", "pyramid" or "rg"
        Initial-guess strategy when a current image is tracked without a guess (see
        docs/dic2d.md): None starts from zero displacement (IC-GN converges from a few px).
    search_radius : int
        Largest displacement the search has to find (px). Default 32.
    max_iter : int
        IC-GN iteration limit per POI. Default 30.
    tol : float
        Convergence threshold on the scaled parameter-update norm (px). Default 1e-3.
    zncc_min : float
        ZNCC below which a converged POI is not ``valid``. Default 0.8.
    flat_std : float, optional
        Grey-level standard deviation below which a subset is FLAT_SUBSET (default 1e-3 of the
        reference's grey-level range).
    device : None or str
    """

    def __init__(self, reference, *, points=None, step: int | None = None, roi=None, subset: int = 21,
                 order: int = 1, search: str | None = None, search_radius: int = 32, max_iter: int = 30,
                 tol: float = 1e-3, zncc_min: float = 0.8, flat_std: float | None = None, device=None):
        self.subset, self.order = check_subset_order(subset, order)
        if search is not None and search not in SEARCH_METHODS:
            raise ValueError(f"search must be None or one of {SEARCH_METHODS}, got {search!r}")
        if isinstance(search_radius, bool) or not isinstance(search_radius, (int, np.integer)) or search_radius < 0:
            raise ValueError(f"search_radius must be a non-negative integer (px), got {search_radius!r}")
        if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
            raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
        if not (isinstance(tol, (int, float, np.floating)) and np.isfinite(tol) and tol > 0):
            raise ValueError(f"tol must be a positive number of pixels, got {tol!r}")
        if not (isinstance(zncc_min, (int, float, np.floating)) and -1.0 <= zncc_min <= 1.0):
            raise ValueError(f"zncc_min must be in [-1, 1], got {zncc_min!r}")
        self.search, self.search_radius = search, int(search_radius)
        self.max_iter, self.tol, self.zncc_min = int(max_iter), float(tol), float(zncc_min)
        self.device = resolve_device(device)
        self.reference = _as_image(reference, "reference")
        self.shape = self.reference.shape
        if points is None:
            self.step = _check_step(step) if step is not None else max(1, self.subset // 2)
            self.points = grid(self.shape, self.step, margin=self.subset // 2, roi=roi)
        else:
            if step is not None:
                self.step = _check_step(step)
            else:
                self.step = None
            if roi is not None:
                raise ValueError("give either points or roi (roi selects grid points), not both")
            self.points = _as_points(points)
        self._ref = prepare_reference(self.reference, device=self.device)
        self._subsets: ReferenceSubsets = prepare_subsets(self._ref, self.points, subset=self.subset,
                                                          order=self.order, flat_std=flat_std)
        self._current_buf = None
        self._out = None

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    def _check_current(self, current) -> np.ndarray:
        cur = _as_image(current, "current")
        if cur.shape != self.shape:
            raise ValueError(f"current image has shape {cur.shape} but the reference has shape {self.shape}; "
                             "DIC needs images of the same size")
        return cur

    def initial_guess(self, cur: np.ndarray, guess=None, search: str | None = None) -> np.ndarray:
        """(N, K) initial parameters for a current image: ``guess`` refined by ``search``."""
        n, k = self.n_points, n_params(self.order)
        g = _guess_params(guess, n, self.order)
        if g is None:
            g = np.zeros((n, k))
        if search is None:
            return g
        if search == "zncc":
            uv, _ = zncc_search(self.reference, cur, self.points, self.search_radius, subset=self.subset,
                                start=g[:, [0, k // 2]], device=self.device)
            g[:, 0], g[:, k // 2] = uv[:, 0], uv[:, 1]
        elif search == "fft":
            u, v, _ = phase_correlation(self.reference, cur)
            uv, _ = zncc_search(self.reference, cur, self.points, 3, subset=self.subset,
                                start=np.tile([u, v], (n, 1)), device=self.device)
            g[:] = 0.0
            g[:, 0], g[:, k // 2] = uv[:, 0], uv[:, 1]
        elif search == "pyramid":
            g1 = _pyramid_guess(self.reference, cur, self.points, self.subset, self.search_radius,
                                min(self.zncc_min, 0.7), self.device)
            g = _convert_order(g1, self.order).copy()
        return g

    def track(self, current, *, guess=None, search: str | None = "default") -> Field2D:
        """Track the POIs into ``current``.

        Parameters
        ----------
        current : array-like (H, W), path or torch tensor, same shape as the reference.
        guess : None, (u, v), (N, 2), (N, 6|12) parameters or a Field2D (e.g. the previous frame)
        search : initial-guess strategy for this image; default: the tracker's ``search``.
        """
        search = self.search if search == "default" else search
        if search is not None and search not in SEARCH_METHODS:
            raise ValueError(f"search must be None or one of {SEARCH_METHODS}, got {search!r}")
        cur = self._check_current(current)
        self._current_buf = prepare_current(cur, device=self.device, out=self._current_buf)
        if search == "rg":
            return self._track_rg(cur, guess)
        g = self.initial_guess(cur, guess, search)
        res = icgn(self._subsets, self._current_buf, guess=g, max_iter=self.max_iter, tol=self.tol,
                   out=self._out)
        self._out = res
        return self._field(res.numpy())

    def _field(self, r: dict, extra: dict | None = None) -> Field2D:
        k = n_params(self.order)
        params = r["params"].astype(np.float64)
        zncc = r["zncc"].astype(np.float64)
        status = r["status"].astype(np.int32)
        valid = np.isin(status, _GOOD) & (zncc >= self.zncc_min)
        return Field2D(self.points.copy(), params[:, 0].copy(), params[:, k // 2].copy(), params, zncc,
                       r["iterations"].astype(np.int32), status, valid, self.subset, self.order, self.step,
                       self.zncc_min, extra or {})

    # -- reliability-guided propagation (Pan et al. 2009, doi:10.1364/AO.48.001535) --------------
    def _track_rg(self, cur: np.ndarray, guess) -> Field2D:
        """Seeds by ZNCC search + IC-GN, then neighbours in decreasing-ZNCC order (batched waves).

        Each wave tracks, in one launch, every untracked POI adjacent (within 1.5 grid steps) to a
        tracked valid POI, starting from the affine prediction of its best-ZNCC tracked neighbour;
        a wave only releases neighbours of POIs whose ZNCC is within 0.05 of the best pending one,
        which keeps the reliability ordering while launching many POIs at once.
        """
        from scipy.spatial import cKDTree

        n, k = self.n_points, n_params(self.order)
        ready = self._subsets.status.numpy() == int(Status.CONVERGED)
        base = _guess_params(guess, n, self.order)
        base = np.zeros((n, k)) if base is None else base
        params = base.copy()
        zncc = np.full(n, np.nan)
        iters = np.zeros(n, np.int32)
        status = np.full(n, int(Status.NOT_COMPUTED), np.int32)
        ref_status = self._subsets.status.numpy()
        status[~ready] = ref_status[~ready]
        step = self.step or float(np.median(cKDTree(self.points).query(self.points, k=2)[0][:, 1]))
        neigh = cKDTree(self.points).query_ball_point(self.points, r=1.5 * step)

        def run(idx: np.ndarray, g: np.ndarray):
            subs = prepare_subsets(self._ref, self.points[idx], subset=self.subset, order=self.order)
            res = icgn(subs, self._current_buf, guess=g, max_iter=self.max_iter, tol=self.tol).numpy()
            params[idx] = res["params"]
            zncc[idx] = res["zncc"]
            iters[idx] = res["iterations"]
            status[idx] = res["status"]

        # seeds: a few POIs spread over the field, ZNCC-searched
        cand = np.flatnonzero(ready)
        if cand.size == 0:
            return self._field({"params": params, "zncc": zncc, "iterations": iters, "status": status})
        n_seeds = min(cand.size, 9)
        seeds = cand[np.unique(np.linspace(0, cand.size - 1, n_seeds).round().astype(int))]
        uv, _ = zncc_search(self.reference, cur, self.points[seeds], self.search_radius, subset=self.subset,
                            start=base[seeds][:, [0, k // 2]], device=self.device)
        g = np.zeros((seeds.size, k))
        g[:, 0], g[:, k // 2] = uv[:, 0], uv[:, 1]
        run(seeds, g)
        good = lambda i: status[i] in _GOOD and zncc[i] >= self.zncc_min  # noqa: E731
        heap = [(-zncc[i], i) for i in seeds if good(i)]
        heapq.heapify(heap)
        while heap:
            best = -heap[0][0]
            wave = []
            while heap and -heap[0][0] >= best - 0.05:
                wave.append(heapq.heappop(heap)[1])
            todo = {}
            for i in wave:
                for j in neigh[i]:
                    if status[j] == int(Status.NOT_COMPUTED) and ready[j]:
                        if j not in todo or zncc[i] > zncc[todo[j]]:
                            todo[j] = i
            if not todo:
                continue
            idx = np.fromiter(todo.keys(), dtype=np.int64)
            src = np.fromiter(todo.values(), dtype=np.int64)
            d = self.points[idx] - self.points[src]
            p = _convert_order(params[src], 1)
            g = np.zeros((idx.size, 6))
            g[:, 0] = p[:, 0] + p[:, 1] * d[:, 0] + p[:, 2] * d[:, 1]
            g[:, 3] = p[:, 3] + p[:, 4] * d[:, 0] + p[:, 5] * d[:, 1]
            g[:, [1, 2, 4, 5]] = p[:, [1, 2, 4, 5]]
            gk = _convert_order(g, self.order).copy()
            if k == 12:
                gk[:, [3, 4, 5, 9, 10, 11]] = params[src][:, [3, 4, 5, 9, 10, 11]]
            run(idx, gk)
            for j in idx:
                if good(j):
                    heapq.heappush(heap, (-zncc[j], j))
        return self._field({"params": params, "zncc": zncc, "iterations": iters, "status": status})


def track(reference, current, *, points=None, step: int | None = None, roi=None, subset: int = 21, order: int = 1,
          guess=None, search: str | None = None, search_radius: int = 32, max_iter: int = 30, tol: float = 1e-3,
          zncc_min: float = 0.8, flat_std: float | None = None, device=None) -> Field2D:
    """Track POIs of ``reference`` into ``current`` with IC-GN (see :class:`Tracker` for parameters).

    Returns a :class:`Field2D`. For several current images of one reference, build a
    :class:`Tracker` once and call its ``track`` method (the reference-side work is reused).

    Raises
    ------
    ValueError : mismatched image sizes, NaNs, colour images, unreadable files, even subset size,
        unknown order or search method, empty ROI / points. POIs whose subset leaves the image are
        not an error: they get status OUT_OF_BOUNDS.
    """
    tracker = Tracker(reference, points=points, step=step, roi=roi, subset=subset, order=order, search=search,
                      search_radius=search_radius, max_iter=max_iter, tol=tol, zncc_min=zncc_min,
                      flat_std=flat_std, device=device)
    return tracker.track(current, guess=guess)
