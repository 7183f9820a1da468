"""Stereo digital image correlation: left-right matching, temporal tracking, 3-D fields.

Pipeline (docs/stereo.md, sections "Stereo matching" and "3-D fields"):

1. **Reference stereo match.** Points of interest (POIs) of the left reference image are matched
   into the right reference image with IC-GN (2nd order by default; Gao et al., Optics and Lasers
   in Engineering 65, 2015, doi:10.1016/j.optlaseng.2014.04.002). The initial guess comes from
   the geometry: SIFT features (Lowe, IJCV 60, 2004, doi:10.1023/B:VISI.0000029664.99615.94)
   matched between the two images and kept when they satisfy the epipolar constraint of the
   calibrated rig (on undistorted points); for each POI an affine map (u, v and their gradients)
   is fitted by robust least squares to the k nearest feature matches. POIs without enough
   nearby matches get their guess from an already matched neighbour (reliability-guided
   propagation, Pan, Applied Optics 48(8), 2009, doi:10.1364/AO.48.001535), and regions with
   neither from a ZNCC search along their epipolar line in the right image. A match is accepted
   when IC-GN converged, its ZNCC is at least ``zncc_min`` and the matched point lies within
   ``epipolar_tol_px`` of the epipolar line; the others keep a :class:`StereoStatus` saying why.
2. **Temporal tracking.** Each later state is tracked left-reference -> left-current and
   right-reference -> right-current (reference subsets precomputed once, the previous state's
   parameters as initial guess, features and propagation for POIs that fail).
3. **Triangulation and fields.** Matched positions (reference position + displacement, float64)
   are triangulated (:func:`dic.triangulate.triangulate`, optimal method); displacements are
   current minus reference positions; surface strains come from :mod:`dic.field3d`.

Conventions (docs/conventions.md): images ``[row, col]``; points ``(x, y)`` px with (0, 0) the
centre of the top-left pixel; 3-D in mm in the left camera frame (or a chosen object frame);
``x_right = R_right_left @ x_left + t_right_left``; shape-function parameters in
:data:`kernels.conventions.PARAMS_2ND` order.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from kernels._device import as_float32_image, resolve_device
from kernels.conventions import Status
from kernels.icgn import check_subset_order, icgn, n_params, prepare_reference, prepare_subsets
from kernels.search import phase_correlation

from .field3d import (Field3D, StereoStatus, as_frame, plane_frame, scattered_neighbours, surface_strain,
                      surface_strain_grid)
from .triangulate import TriangulationStatus, triangulate, undistort_points

__all__ = [
    "StereoStatus", "StereoMatch", "StereoCorrelation", "stereo", "fundamental_matrix", "epipolar_distance",
    "epipolar_residuals", "feature_matches", "affine_guess", "grid_points", "check_rig_images",
]

#: IC-GN outcomes that count as a result (docs/conventions.md: "valid")
_GOOD = (int(Status.CONVERGED), int(Status.MAX_ITERATIONS))
#: guess_source codes
SOURCE_NONE, SOURCE_FEATURES, SOURCE_NEIGHBOUR, SOURCE_SEARCH, SOURCE_PREVIOUS, SOURCE_GLOBAL = -1, 0, 1, 2, 3, 4


# ================================================================================================
# input checks


def _image(img, name: str) -> np.ndarray:
    return as_float32_image(img, name)


def check_rig_images(rig, shape: tuple[int, int]) -> None:
    """Raise ``ValueError`` unless the rig's cameras were calibrated for images of ``shape`` (H, W).

    A camera with ``size == (0, 0)`` (unknown) is accepted.
    """
    missing = [a for a in ("left", "right", "R_right_left", "t_right_left") if not hasattr(rig, a)]
    if missing:
        raise ValueError("rig must be a calibration.stereo.StereoRig (left, right, R_right_left, t_right_left); "
                         f"got {type(rig).__name__} without {', '.join(missing)}")
    h, w = shape
    for side in ("left", "right"):
        size = tuple(int(s) for s in getattr(rig, side).size)
        if size != (0, 0) and size != (w, h):
            raise ValueError(
                f"the rig's {side} camera was calibrated for {size[0]}x{size[1]} px images but the images are "
                f"{w}x{h} px; use the rig file made for these images (or images of the calibrated size)")


def _check_pair(left, right, what: str) -> tuple[np.ndarray, np.ndarray]:
    L = _image(left, f"left {what} image")
    R = _image(right, f"right {what} image")
    if L.shape != R.shape:
        raise ValueError(f"the left and right {what} images differ in size: {L.shape[1]}x{L.shape[0]} and "
                         f"{R.shape[1]}x{R.shape[0]} px (W x H); stereo DIC needs the two cameras' images at their "
                         "calibrated size")
    return L, R


def _positive_float(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}") from None
    if not (v > 0 and np.isfinite(v)):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def grid_points(shape: tuple[int, int], step: int, subset: int, roi=None) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
    """Regular grid of POIs over an image, row-major, and the ROI mask over it.

    Parameters
    ----------
    shape : (H, W)
    step : int >= 1, px between POIs.
    subset : odd int; the grid keeps ``subset // 2`` px from the borders so that subsets fit.
    roi : None, (x0, y0, x1, y1) px (inclusive bounds), or bool array (H, W)
        POIs outside it are kept in the grid (so that the grid stays regular) and flagged.

    Returns
    -------
    points (N, 2) float64, grid_shape (ny, nx), in_roi (N,) bool.
    """
    h, w = shape
    if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step < 1:
        raise ValueError(f"step must be a positive integer number of pixels, got {step!r}")
    r = subset // 2
    xs = np.arange(r, w - r, step, dtype=np.float64)
    ys = np.arange(r, h - r, step, dtype=np.float64)
    if xs.size == 0 or ys.size == 0:
        raise ValueError(f"a {w}x{h} px image is too small for {subset} px subsets")
    gy, gx = np.meshgrid(ys, xs, indexing="ij")
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
    in_roi = np.ones(pts.shape[0], dtype=bool)
    if roi is not None:
        mask = np.asarray(roi)
        if mask.dtype == bool:
            if mask.shape != (h, w):
                raise ValueError(f"roi mask must have the image shape {(h, w)}, got {mask.shape}")
            in_roi = mask[pts[:, 1].astype(int), pts[:, 0].astype(int)]
        else:
            try:
                x0, y0, x1, y1 = (float(v) for v in np.asarray(roi, dtype=np.float64).ravel())
            except (TypeError, ValueError):
                raise ValueError(f"roi must be (x0, y0, x1, y1) in px or a bool mask (H, W), got {roi!r}") from None
            if not (x1 > x0 and y1 > y0):
                raise ValueError(f"roi (x0, y0, x1, y1) must have x1 > x0 and y1 > y0, got {roi!r}")
            in_roi = (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)
        if not np.any(in_roi):
            raise ValueError(f"the ROI {roi if mask.dtype != bool else 'mask'} contains no grid point; "
                             "enlarge it or reduce step")
    return pts, (int(ys.size), int(xs.size)), in_roi


def _as_points(points, shape) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64) if not hasattr(points, "numpy") else np.asarray(points.numpy(), np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must be an (N, 2) array of (x, y) px in the left image, got shape {pts.shape}")
    if pts.shape[0] == 0:
        raise ValueError("points is empty: give at least one point of interest")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points contain NaN or infinite values")
    h, w = shape
    out = (pts[:, 0] < -0.5) | (pts[:, 0] > w - 0.5) | (pts[:, 1] < -0.5) | (pts[:, 1] > h - 0.5)
    if np.any(out):
        i = int(np.argmax(out))
        raise ValueError(f"{int(out.sum())} point(s) lie outside the {w}x{h} px left image, e.g. point {i} at "
                         f"({pts[i, 0]:.6g}, {pts[i, 1]:.6g})")
    return np.ascontiguousarray(pts)


# ================================================================================================
# epipolar geometry


def _skew(t) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def fundamental_matrix(rig) -> np.ndarray:
    """Fundamental matrix (3, 3) of the rig for **undistorted** (ideal) pixels.

    ``x̃_rightᵀ F x̃_left = 0`` for homogeneous ideal pixels ``x̃ = (x, y, 1)``, with
    ``F = K_right⁻ᵀ [t]ₓ R K_left⁻¹`` (Hartley & Zisserman, *Multiple View Geometry*, 2nd ed., §9.2),
    ``R = R_right_left``, ``t = t_right_left``. Scaled to unit Frobenius norm.
    """
    Kl = np.asarray(rig.left.K, dtype=np.float64)
    Kr = np.asarray(rig.right.K, dtype=np.float64)
    R = np.asarray(rig.R_right_left, dtype=np.float64)
    t = np.asarray(rig.t_right_left, dtype=np.float64).ravel()
    F = np.linalg.inv(Kr).T @ _skew(t) @ R @ np.linalg.inv(Kl)
    return F / np.linalg.norm(F)


def epipolar_distance(F, ideal_left, ideal_right) -> np.ndarray:
    """Distance (px) of each ideal right point from the epipolar line ``F x̃_left`` of its left point.

    ``ideal_left``, ``ideal_right``: (N, 2) undistorted pixels. Returns (N,) float64 (NaN where an
    input is NaN).
    """
    pl = np.asarray(ideal_left, dtype=np.float64)
    pr = np.asarray(ideal_right, dtype=np.float64)
    lines = np.column_stack([pl, np.ones(len(pl))]) @ np.asarray(F, dtype=np.float64).T   # (N, 3)
    num = np.abs(np.sum(lines[:, :2] * pr, axis=1) + lines[:, 2])
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / np.hypot(lines[:, 0], lines[:, 1])


def epipolar_residuals(rig, points_left, points_right, *, device=None) -> np.ndarray:
    """Epipolar distance (px, undistorted right image) of matched observed pixels (N, 2) and (N, 2).

    Both sets are undistorted with the rig's lens models (:func:`dic.triangulate.undistort_points`,
    converged to 1e-9 px); NaN where an input is NaN or cannot be undistorted.
    """
    pl = np.asarray(points_left, dtype=np.float64).reshape(-1, 2)
    pr = np.asarray(points_right, dtype=np.float64).reshape(-1, 2)
    if pl.shape != pr.shape:
        raise ValueError(f"points_left and points_right must have the same shape, got {pl.shape} and {pr.shape}")
    if pl.shape[0] == 0:
        return np.zeros(0)
    ul, sl = undistort_points(rig.left, pl, device=device, margin_px=np.inf)
    ur, sr = undistort_points(rig.right, pr, device=device, margin_px=np.inf)
    d = epipolar_distance(fundamental_matrix(rig), ul, ur)
    bad = (sl != TriangulationStatus.OK) | (sr != TriangulationStatus.OK)
    d[bad] = np.nan
    return d


# ================================================================================================
# features and guesses


def _to_uint8(image: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(image, [0.5, 99.5])
    if not hi > lo:
        hi = lo + 1.0
    return np.clip((image - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


def _sift_matches(a: np.ndarray, b: np.ndarray, scale: int, max_features: int, ratio: float):
    import cv2

    if scale > 1:
        a = cv2.resize(a, None, fx=1.0 / scale, fy=1.0 / scale, interpolation=cv2.INTER_AREA)
        b = cv2.resize(b, None, fx=1.0 / scale, fy=1.0 / scale, interpolation=cv2.INTER_AREA)
    sift = cv2.SIFT_create(nfeatures=int(max_features))
    ka, da = sift.detectAndCompute(a, None)
    kb, db = sift.detectAndCompute(b, None)
    empty = (np.zeros((0, 2)), np.zeros((0, 2)))
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return empty
    matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    ia, ib = [], []
    for p in matcher.knnMatch(da, db, k=2):
        if len(p) == 2 and p[0].distance < ratio * p[1].distance:
            ia.append(p[0].queryIdx)
            ib.append(p[0].trainIdx)
    if not ia:
        return empty
    pa = np.array([ka[i].pt for i in ia], dtype=np.float64)
    pb = np.array([kb[i].pt for i in ib], dtype=np.float64)
    # pixel centres: x_full = (x_small + 0.5) * scale - 0.5
    return (pa + 0.5) * scale - 0.5, (pb + 0.5) * scale - 0.5


def feature_matches(image_a, image_b, *, max_features: int = 20000, ratio: float = 0.8,
                    max_pixels: float = 0.35e6, min_matches: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints of ``image_a`` matched into ``image_b`` (Lowe's ratio test, FLANN k-d trees).

    SIFT (Lowe, IJCV 60, 2004, doi:10.1023/B:VISI.0000029664.99615.94) runs on images reduced by
    an integer factor so that they hold at most about ``max_pixels`` pixels (OpenCV's SIFT
    doubles its input first; on speckle, a 1-megapixel image takes ~2.6 s at full resolution
    and ~0.5 s at 1/3, with 99.7 % of the matches within 2 px either way — measured, see
    docs/stereo.md); when fewer than ``min_matches`` matches come out, the factor is halved and
    SIFT rerun. The guesses only need to fall within a few pixels: IC-GN does the rest.

    Returns ``(points_a, points_b)``, (M, 2) float64 px of the full-resolution images (pixel
    centres at integers). M may be 0. No geometric filtering is done here.
    """
    a = _to_uint8(_image(image_a, "image_a"))
    b = _to_uint8(_image(image_b, "image_b"))
    scale = max(1, int(np.sqrt(max(a.size, b.size) / float(max_pixels))))
    while True:
        pa, pb = _sift_matches(a, b, scale, max_features, ratio)
        if pa.shape[0] >= min_matches or scale == 1:
            return pa, pb
        scale //= 2


def affine_guess(points, src, dst, *, k: int = 16, radius: float = 120.0, min_matches: int = 6,
                 inlier_px: float = 2.0, iterations: int = 4, cell: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-POI affine guess ``(u, ux, uy, v, vx, vy)`` from point correspondences ``src -> dst``.

    For each POI the displacement ``dst - src`` of its ``k`` nearest correspondences within
    ``radius`` px is fitted as an affine function of the offset from the POI by iteratively
    reweighted least squares (Cauchy weights, scale ``inlier_px``). A POI gets a guess when at
    least ``min_matches`` correspondences fit within ``2 inlier_px`` and they are not collinear.
    The fit is made once per square ``cell`` of side ``cell`` px (default ``radius / 6``), about
    the cell's centre, and carried to the POIs inside it through its own affine map (the
    correspondences are ~30 px apart in practice, so a denser evaluation adds nothing but time).

    Returns ``params`` (N, 6) float64 (PARAMS_1ST order, NaN where no guess) and ``ok`` (N,) bool.
    """
    from scipy.spatial import cKDTree

    P = np.asarray(points, dtype=np.float64)
    S = np.asarray(src, dtype=np.float64).reshape(-1, 2)
    D = np.asarray(dst, dtype=np.float64).reshape(-1, 2)
    n = P.shape[0]
    params = np.full((n, 6), np.nan)
    if S.shape[0] < min_matches or n == 0:
        return params, np.zeros(n, dtype=bool)
    h = radius / 6.0 if cell is None else float(cell)
    if h > 0 and n > 1:
        key = np.floor(P / h).astype(np.int64)
        cells, inverse = np.unique(key, axis=0, return_inverse=True)
        inverse = inverse.ravel()
        if cells.shape[0] < n:
            centres = (cells + 0.5) * h
            p_cells, ok_cells = affine_guess(centres, S, D, k=k, radius=radius, min_matches=min_matches,
                                             inlier_px=inlier_px, iterations=iterations, cell=0.0)
            d = P - centres[inverse]
            out = p_cells[inverse].copy()
            out[:, 0] += out[:, 1] * d[:, 0] + out[:, 2] * d[:, 1]
            out[:, 3] += out[:, 4] * d[:, 0] + out[:, 5] * d[:, 1]
            return out, ok_cells[inverse].copy()
    kk = int(min(k, S.shape[0]))
    tree = cKDTree(S)
    for c0 in range(0, n, 65536):          # chunks bound the memory of the (n, k) work arrays
        sl = slice(c0, min(n, c0 + 65536))
        dist, idx = tree.query(P[sl], k=kk, distance_upper_bound=radius)
        dist = dist.reshape(-1, kk)
        idx = idx.reshape(-1, kk)
        have = np.isfinite(dist)
        safe = np.where(have, idx, 0)
        a = S[safe, 0] - P[sl, 0:1]           # offsets of the correspondences from the POI, px
        b = S[safe, 1] - P[sl, 1:2]
        disp = D[safe] - S[safe]              # (m, k, 2)
        # robust start: the best of 32 exact affine fits through 3 of the correspondences (a
        # vectorised RANSAC; with 40 % outliers one triple is clean with probability > 99.9 %),
        # then iteratively reweighted least squares from its inliers
        best = np.full(a.shape[0], -1)
        best_w = have.astype(np.float64)
        for t in _triples(kk):
            ok3 = np.all(have[:, t], axis=1)
            fit3 = affine_fit(np.ones((a.shape[0], 3)), a[:, t], b[:, t], disp[:, t])
            pred = fit3[0][:, None, :] + fit3[1][:, None, :] * a[..., None] + fit3[2][:, None, :] * b[..., None]
            res = np.linalg.norm(disp - pred, axis=2)
            inl = have & (res <= 2.0 * inlier_px)
            count = np.where(ok3 & fit3[3], inl.sum(axis=1), -1)
            better = count > best
            best[better] = count[better]
            best_w[better] = inl[better]
        w = np.where(best[:, None] >= 3, best_w, have.astype(np.float64))
        solvable = have.sum(axis=1) >= min_matches
        fit = None
        for _ in range(max(1, iterations)):
            fit = affine_fit(w, a, b, disp)
            solvable &= fit[3]
            pred = fit[0][:, None, :] + fit[1][:, None, :] * a[..., None] + fit[2][:, None, :] * b[..., None]
            res = np.linalg.norm(disp - pred, axis=2)
            res[~np.isfinite(res)] = 1e9
            w = have / (1.0 + (res / inlier_px) ** 2)
        inliers = have & (res <= 2.0 * inlier_px)
        good = solvable & (inliers.sum(axis=1) >= min_matches)
        c, ga, gb, _ = fit
        block = np.column_stack([c[:, 0], ga[:, 0], gb[:, 0], c[:, 1], ga[:, 1], gb[:, 1]])
        block[~good] = np.nan
        params[sl] = block
    ok = np.all(np.isfinite(params), axis=1)
    params[~ok] = np.nan
    return params, ok


def _triples(k: int, count: int = 32) -> list[np.ndarray]:
    """``count`` fixed index triples drawn from ``range(k)`` (deterministic)."""
    if k < 3:
        return []
    rng = np.random.default_rng(0)
    return [rng.choice(k, size=3, replace=False) for _ in range(count)]


def affine_fit(w: np.ndarray, a: np.ndarray, b: np.ndarray, t: np.ndarray):
    """Weighted least squares ``t ≈ c + g_a a + g_b b`` for many small problems at once.

    ``w``, ``a``, ``b``: (n, k); ``t``: (n, k, c). Returns ``(c (n, c), g_a (n, c), g_b (n, c),
    ok (n,))`` — the fit's value at ``a = b = 0`` and its gradients; ``ok`` is False (and the
    outputs NaN) where the weighted points are too few or collinear. Closed form on centred
    sums (no per-problem matrix objects: ~10x faster than batched ``np.linalg.solve`` here).
    """
    sw = w.sum(axis=1)
    inv = 1.0 / np.maximum(sw, 1e-300)
    ma = (w * a).sum(axis=1) * inv
    mb = (w * b).sum(axis=1) * inv
    mt = np.einsum("nk,nkc->nc", w, t) * inv[:, None]
    ac = a - ma[:, None]
    bc = b - mb[:, None]
    tc = t - mt[:, None, :]
    saa = (w * ac * ac).sum(axis=1)
    sab = (w * ac * bc).sum(axis=1)
    sbb = (w * bc * bc).sum(axis=1)
    sat = np.einsum("nk,nkc->nc", w * ac, tc)
    sbt = np.einsum("nk,nkc->nc", w * bc, tc)
    det = saa * sbb - sab * sab
    ok = (sw > 0) & (det > 1e-9 * (saa + sbb) ** 2) & (saa + sbb > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        inv_det = np.where(ok, 1.0 / det, np.nan)
        ga = (sbb[:, None] * sat - sab[:, None] * sbt) * inv_det[:, None]
        gb = (saa[:, None] * sbt - sab[:, None] * sat) * inv_det[:, None]
    c = mt - ga * ma[:, None] - gb * mb[:, None]
    return c, ga, gb, ok


def _embed(params6: np.ndarray, order: int) -> np.ndarray:
    """(N, 6) first-order parameters -> (N, 6|12) in the order's storage layout."""
    if order == 1:
        return params6.copy()
    out = np.zeros((params6.shape[0], 12))
    out[:, 0:3] = params6[:, 0:3]
    out[:, 6:9] = params6[:, 3:6]
    return out


def _extrapolate(params: np.ndarray, d: np.ndarray, order: int) -> np.ndarray:
    """Shape-function parameters of a neighbour (N, k) moved to a POI offset by ``d`` (N, 2) px."""
    dx, dy = d[:, 0], d[:, 1]
    out = params.copy()
    if order == 1:
        for b in (0, 3):
            out[:, b] = params[:, b] + params[:, b + 1] * dx + params[:, b + 2] * dy
        return out
    for b in (0, 6):
        u, ux, uy, uxx, uxy, uyy = (params[:, b + i] for i in range(6))
        out[:, b] = u + ux * dx + uy * dy + 0.5 * uxx * dx * dx + uxy * dx * dy + 0.5 * uyy * dy * dy
        out[:, b + 1] = ux + uxx * dx + uxy * dy
        out[:, b + 2] = uy + uxy * dx + uyy * dy
    return out


def _displacement(params: np.ndarray, order: int) -> np.ndarray:
    """(N, 2) displacement ``(u, v)`` at the POIs from parameters (N, 6|12)."""
    j = 3 if order == 1 else 6
    return np.stack([params[:, 0], params[:, j]], axis=1).astype(np.float64)


def _spread(points: np.ndarray, candidates: np.ndarray, max_count: int) -> np.ndarray:
    """Up to ``max_count`` of the candidate indices, spread over the image (one per grid cell)."""
    if candidates.size <= max_count:
        return candidates
    P = points[candidates]
    lo, hi = P.min(axis=0), P.max(axis=0)
    cells = int(np.ceil(np.sqrt(max_count)))
    span = np.maximum(hi - lo, 1e-9)
    cell = np.minimum((cells * (P - lo) / span).astype(int), cells - 1)
    key = cell[:, 1] * cells + cell[:, 0]
    _, first = np.unique(key, return_index=True)
    chosen = candidates[np.sort(first)]
    return chosen[:max_count]


# ================================================================================================
# IC-GN with propagation


def _prepare_current(image, device: str):
    """A current image in the form the IC-GN kernels read, prepared once per image."""
    from kernels import icgn as _icgn
    from kernels.interp import bspline_coefficients

    if hasattr(_icgn, "prepare_current"):
        return _icgn.prepare_current(image, device=device)
    return bspline_coefficients(image, device=device)  # pragma: no cover - older kernels


class _Correlator:
    """IC-GN of one reference image's POIs into current images; reference quantities computed once."""

    def __init__(self, image: np.ndarray, points: np.ndarray, subset: int, order: int, device: str,
                 max_iter: int, tol: float):
        self.points = points
        self.subset, self.order, self.device = subset, order, device
        self.max_iter, self.tol = max_iter, tol
        self.reference = prepare_reference(image, device=device)
        self.subsets = prepare_subsets(self.reference, points, subset=subset, order=order)
        self.reference_status = self.subsets.status.numpy().astype(np.int32)

    @property
    def ready(self) -> np.ndarray:
        """(N,) bool: the reference subset is trackable (inside the image, textured, regular)."""
        return self.reference_status == int(Status.CONVERGED)

    def run(self, current, idx: np.ndarray, guess: np.ndarray) -> dict:
        n = self.points.shape[0]
        if idx.size == n and np.array_equal(idx, np.arange(n)):
            subsets = self.subsets
        else:
            subsets = prepare_subsets(self.reference, self.points[idx], subset=self.subset, order=self.order)
        res = icgn(subsets, current, guess=np.asarray(guess, dtype=np.float64), max_iter=self.max_iter, tol=self.tol)
        return res.numpy()


@dataclass
class _TrackResult:
    params: np.ndarray       # (N, k) float64
    zncc: np.ndarray         # (N,) float64
    iterations: np.ndarray   # (N,) int32
    icgn_status: np.ndarray  # (N,) int32 kernels Status (NOT_COMPUTED where never run)
    accepted: np.ndarray     # (N,) bool
    source: np.ndarray       # (N,) int8
    extra_failed: np.ndarray # (N,) bool: converged with good ZNCC but rejected by the extra check


def _correlate(corr: _Correlator, current, guess: np.ndarray, has_guess: np.ndarray, initial_source: int, *,
               eligible: np.ndarray, zncc_min: float, radius: float, extra: Callable | None = None,
               fallback: Callable | None = None, max_attempts: int = 3, max_seeds: int = 64,
               max_fallback_rounds: int = 8, min_fallback: int = 1, zncc_drop: float = 0.05) -> _TrackResult:
    """IC-GN of every eligible POI, from the given guesses, then neighbour propagation and a fallback.

    ``extra(idx, params) -> bool mask`` adds an acceptance test (the epipolar check);
    ``fallback(idx) -> (guess (m, k), ok (m,))`` proposes guesses for isolated POIs; it is called
    only while at least ``min_fallback`` eligible POIs are unresolved and untried. Finally, an
    accepted POI whose ZNCC is more than ``zncc_drop`` below the median of its accepted
    neighbours is retried from its best neighbour; the better-correlating result is kept.
    """
    from scipy.spatial import cKDTree

    n = corr.points.shape[0]
    k = n_params(corr.order)
    params = np.full((n, k), np.nan)
    zncc = np.full(n, np.nan)
    iters = np.zeros(n, dtype=np.int32)
    status = np.full(n, int(Status.NOT_COMPUTED), dtype=np.int32)
    accepted = np.zeros(n, dtype=bool)
    extra_failed = np.zeros(n, dtype=bool)
    source = np.full(n, SOURCE_NONE, dtype=np.int8)
    attempts = np.zeros(n, dtype=np.int32)
    rank = np.full(n, -1, dtype=np.int32)
    eligible = eligible & corr.ready

    def batch(idx: np.ndarray, g: np.ndarray, src: int) -> int:
        if idx.size == 0:
            return 0
        r = corr.run(current, idx, g)
        p = r["params"].astype(np.float64)
        z = r["zncc"].astype(np.float64)
        st = r["status"].astype(np.int32)
        attempts[idx] += 1
        good = np.isin(st, _GOOD) & (z >= zncc_min)
        ext = np.ones(idx.size, dtype=bool)
        if extra is not None and np.any(good):
            ext[good] = extra(idx[good], p[good])
        # keep the best attempt per POI: accepted > rejected by `extra` > low ZNCC > failed, then ZNCC
        new_rank = np.where(good & ext, 3, np.where(good, 2, np.where(np.isin(st, _GOOD), 1, 0)))
        take = (new_rank > rank[idx]) | ((new_rank == rank[idx]) & (np.nan_to_num(z, nan=-2.0)
                                                                   >= np.nan_to_num(zncc[idx], nan=-2.0)))
        t = idx[take]
        params[t], zncc[t], status[t], iters[t] = p[take], z[take], st[take], r["iterations"][take]
        source[t] = src
        rank[t] = new_rank[take]
        extra_failed[t] = (good & ~ext)[take]
        accepted[t] = (good & ext)[take]
        return int(np.count_nonzero((good & ext)[take]))

    start = np.flatnonzero(has_guess & eligible)
    batch(start, guess[start], initial_source)
    fallback_tried = np.zeros(n, dtype=bool)
    for _ in range(max_fallback_rounds + 1):
        # reliability-guided propagation: POIs next to accepted ones start from their parameters
        while True:
            acc = np.flatnonzero(accepted)
            open_ = np.flatnonzero(eligible & ~accepted & (attempts < max_attempts))
            if acc.size == 0 or open_.size == 0:
                break
            d, j = cKDTree(corr.points[acc]).query(corr.points[open_], k=1, distance_upper_bound=radius)
            near = np.isfinite(d)
            if not np.any(near):
                break
            idx = open_[near]
            nb = acc[j[near]]
            g = _extrapolate(params[nb], corr.points[idx] - corr.points[nb], corr.order)
            batch(idx, g, SOURCE_NEIGHBOUR)
        if fallback is None:
            break
        cand = np.flatnonzero(eligible & ~accepted & ~fallback_tried)
        if cand.size < max(1, min_fallback):
            break
        seeds = _spread(corr.points, cand, max_seeds)
        fallback_tried[seeds] = True
        g, ok = fallback(seeds)
        if np.any(ok):
            batch(seeds[ok], g[ok], SOURCE_SEARCH)
            attempts[seeds[ok]] = np.minimum(attempts[seeds[ok]], max_attempts - 1)  # neighbours may still retry
    # second opinion: an accepted POI whose ZNCC is clearly below its neighbours' converged to a
    # wrong local minimum more often than not (measured: a 2nd-order track started 2 px away ended
    # at ZNCC 0.86 with spurious curvature, its neighbours at 0.99); retry it from the best
    # neighbour and keep whichever result correlates better
    acc = np.flatnonzero(accepted)
    if acc.size >= 3:
        kk = min(9, acc.size)
        d, j = cKDTree(corr.points[acc]).query(corr.points[acc], k=kk, distance_upper_bound=2.0 * radius)
        have = np.isfinite(d[:, 1:])
        nb = np.where(have, acc[np.minimum(j[:, 1:], acc.size - 1)], -1)
        z_nb = np.where(have, zncc[np.maximum(nb, 0)], np.nan)
        # the neighbours' median ZNCC, for the POIs that have at least 3 neighbours (NaN for the others)
        enough = np.sum(have, axis=1) >= 3
        med = np.full(acc.size, np.nan)
        if np.any(enough):
            med[enough] = np.nanmedian(z_nb[enough], axis=1)
        suspect = np.isfinite(med) & (zncc[acc] < med - zncc_drop)
        if np.any(suspect):
            idx = acc[suspect]
            best = nb[suspect][np.arange(idx.size), np.nanargmax(np.where(nb[suspect] >= 0, z_nb[suspect], -np.inf), axis=1)]
            g = _extrapolate(params[best], corr.points[idx] - corr.points[best], corr.order)
            batch(idx, g, SOURCE_NEIGHBOUR)  # replaces a result only by an accepted one with a higher ZNCC
    return _TrackResult(params, zncc, iters, status, accepted, source, extra_failed)


# ================================================================================================
# epipolar search (fallback for POIs far from every feature match)


def _zncc_rows(patches: np.ndarray, template: np.ndarray) -> np.ndarray:
    p = patches - patches.mean(axis=1, keepdims=True)
    t = template - template.mean()
    den = np.sqrt(np.sum(p * p, axis=1) * np.sum(t * t))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, (p @ t) / den, -1.0)


def _epipolar_candidates(rig, ideal_left_point: np.ndarray, shape, margin: float, n_depth: int = 4096) -> np.ndarray:
    """Observed right pixels (M, 2) along the epipolar curve of one left point, ~1 px apart, inside the image."""
    h, w = shape
    Kl = rig.left.K
    y = (ideal_left_point[1] - Kl[1, 2]) / Kl[1, 1]
    x = (ideal_left_point[0] - Kl[0, 2] - Kl[0, 1] * y) / Kl[0, 0]
    ray = np.array([x, y, 1.0])
    base = max(np.linalg.norm(rig.t_right_left), 1e-9)
    # inverse depth from ~infinity (1e4 baselines) to 1/50 of a baseline
    rho = np.linspace(1.0 / (1e4 * base), 50.0 / base, n_depth)
    X = ray[None, :] / rho[:, None]
    Xr = X @ np.asarray(rig.R_right_left).T + np.asarray(rig.t_right_left)
    front = Xr[:, 2] > 1e-9 * base
    if not np.any(front):
        return np.zeros((0, 2))
    uv = rig.right.project(Xr[front])
    inside = (uv[:, 0] >= margin) & (uv[:, 0] <= w - 1 - margin) & (uv[:, 1] >= margin) & (uv[:, 1] <= h - 1 - margin)
    uv = uv[inside]
    if uv.shape[0] < 2:
        return uv
    # resample to 1 px steps along the curve (a jump where it leaves and re-enters the image is
    # bridged by a straight segment, which stays inside the convex image rectangle)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))])
    t = np.arange(0.0, s[-1] + 1e-9, 1.0)
    return np.stack([np.interp(t, s, uv[:, 0]), np.interp(t, s, uv[:, 1])], axis=1)


def _epipolar_search(rig, left: np.ndarray, right: np.ndarray, points: np.ndarray, subset: int, gradient: np.ndarray,
                     device: str, min_score: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ZNCC search of each left POI along its epipolar curve in the right image.

    ``gradient`` (2, 2): ``[[ux, uy], [vx, vy]]`` used to shape the right patch (e.g. from the
    global fit of the feature matches; zeros for a pure translation).
    Returns ``(right_points (m, 2), score (m,), ok (m,))``.
    """
    import cv2

    r = subset // 2
    m = points.shape[0]
    out = np.full((m, 2), np.nan)
    score = np.full(m, -1.0)
    ideal, st = undistort_points(rig.left, points, device=device, margin_px=np.inf)
    off = np.arange(-r, r + 1, dtype=np.float64)
    oy, ox = np.meshgrid(off, off, indexing="ij")
    offs = np.stack([ox.ravel(), oy.ravel()], axis=1)               # (S², 2)
    A = np.eye(2) + np.asarray(gradient, dtype=np.float64)
    shaped = offs @ A.T
    for i in range(m):
        if st[i] != TriangulationStatus.OK:
            continue
        cx, cy = int(round(points[i, 0])), int(round(points[i, 1]))
        template = left[cy - r:cy + r + 1, cx - r:cx + r + 1].astype(np.float64).ravel()
        if template.size != offs.shape[0] or template.std() == 0:
            continue
        cand = _epipolar_candidates(rig, ideal[i], left.shape, margin=r * max(1.0, np.abs(A).sum(axis=1).max()) + 1)
        if cand.shape[0] == 0:
            continue
        # the template is centred on the integer pixel; shift the candidates accordingly
        delta = np.array([cx - points[i, 0], cy - points[i, 1]]) @ A.T
        best_s, best_c = -1.0, None
        for c0 in range(0, cand.shape[0], 2048):
            c = cand[c0:c0 + 2048]
            pos = (c + delta)[:, None, :] + shaped[None, :, :]      # (M, S², 2)
            mx = pos[..., 0].astype(np.float32)
            my = pos[..., 1].astype(np.float32)
            patches = cv2.remap(right, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
            z = _zncc_rows(patches, template)
            j = int(np.argmax(z))
            if z[j] > best_s:
                best_s, best_c = float(z[j]), c[j]
        if best_c is not None and best_s >= min_score:
            out[i] = best_c
            score[i] = best_s
    ok = np.all(np.isfinite(out), axis=1)
    return out, score, ok


# ================================================================================================
# results of the reference match


@dataclass
class StereoMatch:
    """Left-reference -> right-reference correspondence of every POI.

    Attributes
    ----------
    points_left : (N, 2) float64 px, the POIs.
    points_right : (N, 2) float64 px, matched positions in the right image (``points_left + (u, v)``),
        NaN where ``status`` is ``NOT_COMPUTED`` or ``NO_GUESS``.
    params : (N, 6|12) float64, IC-GN shape-function parameters (PARAMS_1ST / PARAMS_2ND order).
    zncc : (N,) float64; iterations : (N,) int32; icgn_status : (N,) int32 :class:`kernels.conventions.Status`.
    epipolar_px : (N,) float64, distance from the epipolar line (undistorted right image), NaN where not matched.
    guess_source : (N,) int8: 0 features, 1 neighbour propagation, 2 epipolar search, -1 none.
    status : (N,) int8 :class:`StereoStatus` (``OK``, ``NOT_COMPUTED``, ``NO_GUESS``, ``MATCH_FAILED``,
        ``EPIPOLAR_VIOLATION`` or ``LOW_ZNCC``).
    n_features : int, epipolar-consistent feature matches used for the guesses.
    """

    points_left: np.ndarray
    points_right: np.ndarray
    params: np.ndarray
    zncc: np.ndarray
    iterations: np.ndarray
    icgn_status: np.ndarray
    epipolar_px: np.ndarray
    guess_source: np.ndarray
    status: np.ndarray
    n_features: int = 0
    order: int = 2

    @property
    def valid(self) -> np.ndarray:
        return self.status == StereoStatus.OK

    def counts(self) -> dict[str, int]:
        codes, counts = np.unique(self.status, return_counts=True)
        return {StereoStatus(int(c)).name: int(n) for c, n in zip(codes, counts)}

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in ("points_left", "points_right", "params", "zncc", "iterations",
                                               "icgn_status", "epipolar_px", "guess_source", "status")}


def _warn_if_epipolar_mismatch(match: "StereoMatch", tol_px: float) -> None:
    """Warn when most correlated points miss their epipolar line: the rig does not fit the images.

    Isolated violations are bad matches; a majority means the calibration (usually the relative
    rotation) or the image order is wrong, and every point would silently come out invalid."""
    import warnings

    violated = match.status == StereoStatus.EPIPOLAR_VIOLATION
    correlated = violated | (match.status == StereoStatus.OK)
    if np.count_nonzero(correlated) >= 10 and np.count_nonzero(violated) > 0.5 * np.count_nonzero(correlated):
        median = float(np.nanmedian(match.epipolar_px[violated]))
        warnings.warn(
            f"{np.count_nonzero(violated)} of {np.count_nonzero(correlated)} correlated points are more than "
            f"{tol_px:g} px from their epipolar line (median {median:.2f} px): the rig does not fit these images. "
            "Check that left and right are not swapped and that the rig file belongs to this setup; a relative "
            "rotation error of a few hundredths of a degree (e.g. a mirror-only calibration without a far view) "
            "gives this. Recalibrate (specula calibrate stereo with --far) or raise epipolar_tol_px / --epipolar-tol.",
            RuntimeWarning, stacklevel=3)


def _final_status(res: _TrackResult, eligible: np.ndarray, failed_code: StereoStatus, extra_code: StereoStatus,
                  zncc_min: float) -> np.ndarray:
    """Per-POI StereoStatus of a correlation stage."""
    out = np.full(res.accepted.shape, int(StereoStatus.OK), dtype=np.int8)
    ran = res.icgn_status != int(Status.NOT_COMPUTED)
    out[~ran] = StereoStatus.NO_GUESS
    bad = ran & ~np.isin(res.icgn_status, _GOOD)
    out[bad] = failed_code
    low = ran & np.isin(res.icgn_status, _GOOD) & ~(res.zncc >= zncc_min)
    out[low] = StereoStatus.LOW_ZNCC
    out[res.extra_failed & ~res.accepted] = extra_code
    out[res.accepted] = StereoStatus.OK
    out[~eligible] = StereoStatus.NOT_COMPUTED
    return out


# ================================================================================================
# the stereo correlation object


_FRAME_CHOICES = ("left", "plane")


class StereoCorrelation:
    """Stereo DIC of a reference pair, then of any number of current pairs.

    Build it once per reference pair; :meth:`measure` a current pair to get a :class:`Field3D`.
    The reference quantities (B-spline gradients and IC-GN Hessians of the left and right
    reference subsets) are computed once here and reused for every state.

    Parameters
    ----------
    rig : calibration.stereo.StereoRig
    left_ref, right_ref : (H, W) grey images of the reference state (same size, the rig's size).
    points : (N, 2) px in the left reference image, optional. Default: a grid of ``step``.
    step : int, grid spacing (px) when ``points`` is None.
    roi : (x0, y0, x1, y1) or bool mask (H, W), optional: grid POIs outside are ``NOT_COMPUTED``.
    subset : odd int, subset size (px); order : 1 or 2 (shape function; 2 recommended for stereo).
    frame : "left", "plane" or (R_obj_left, t_obj_left): output frame (see :class:`Field3D`).
    epipolar_tol_px : float, px (undistorted right image) beyond which a match is ``EPIPOLAR_VIOLATION``.
    zncc_min : float, matches and tracks below it are ``LOW_ZNCC``.
    strain_window : odd int, grid points per side of the strain neighbourhood (scattered points:
        the ``strain_window²`` nearest).
    max_iter, tol : IC-GN iteration limit and convergence threshold (px, see kernels/icgn.py).
    triangulation : "optimal" or "linear" (:func:`dic.triangulate.triangulate`).
    match : StereoMatch, optional: a reference match computed before (e.g. read back from a
        result file); skips the feature matching and the left -> right IC-GN.
    device : None, "cpu" or "cuda:N".
    """

    def __init__(self, rig, left_ref, right_ref, *, points=None, step: int = 10, roi=None, subset: int = 21,
                 order: int = 2, frame="left", epipolar_tol_px: float = 1.0, zncc_min: float = 0.8,
                 strain_window: int = 5, max_iter: int = 50, tol: float = 1e-3, triangulation: str = "optimal",
                 max_features: int = 20000, match: StereoMatch | None = None, device=None):
        self.device = resolve_device(device)
        self.subset, self.order = check_subset_order(subset, order)
        left_ref, right_ref = _check_pair(left_ref, right_ref, "reference")
        check_rig_images(rig, left_ref.shape)
        self.rig = rig
        self.shape = left_ref.shape
        self.epipolar_tol_px = _positive_float(epipolar_tol_px, "epipolar_tol_px")
        if not (-1.0 <= float(zncc_min) <= 1.0):
            raise ValueError(f"zncc_min must be in [-1, 1], got {zncc_min!r}")
        self.zncc_min = float(zncc_min)
        if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
            raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
        self.max_iter, self.tol = int(max_iter), _positive_float(tol, "tol")
        if triangulation not in ("optimal", "linear"):
            raise ValueError(f"triangulation must be 'optimal' or 'linear', got {triangulation!r}")
        self.triangulation = triangulation
        self.max_features = int(max_features)
        if points is None:
            self.points, self.grid_shape, in_roi = grid_points(self.shape, step, self.subset, roi)
            self.step = int(step)
            if isinstance(strain_window, bool) or int(strain_window) != strain_window or strain_window < 3 \
                    or strain_window % 2 == 0:
                raise ValueError(f"strain window must be an odd integer >= 3 (grid points), got {strain_window!r}")
            self.neighbours = None
        else:
            if roi is not None:
                raise ValueError("give either points or roi (the ROI selects grid points), not both")
            self.points = _as_points(points, self.shape)
            self.grid_shape = None
            in_roi = np.ones(self.points.shape[0], dtype=bool)
            spacing = self._typical_spacing(self.points)
            self.step = max(1, int(round(spacing)))
            if isinstance(strain_window, bool) or int(strain_window) != strain_window or strain_window < 3 or strain_window % 2 == 0:
                raise ValueError(f"strain window must be an odd integer >= 3 (grid points), got {strain_window!r}")
            self.neighbours = scattered_neighbours(self.points, int(strain_window) ** 2,
                                                   max_distance=strain_window * spacing)
        self.in_roi = in_roi
        self.strain_window = int(strain_window)
        #: propagation reach: a neighbour within ~1.5 grid steps (diagonal included)
        self.radius = 1.5 * self.step + 1e-6
        self._left_ref, self._right_ref = left_ref, right_ref
        self._F = fundamental_matrix(rig)
        #: seconds spent per stage in the constructor (reference) and in the last :meth:`measure`
        self.timings: dict[str, float] = {}
        t0 = time.perf_counter()
        self.left = _Correlator(left_ref, self.points, self.subset, self.order, self.device, self.max_iter, self.tol)
        self.timings["reference_prepare_s"] = time.perf_counter() - t0
        self._ideal_left, _ = undistort_points(rig.left, self.points, device=self.device, margin_px=np.inf)
        self.match = self._match() if match is None else self._check_match(match)
        _warn_if_epipolar_mismatch(self.match, self.epipolar_tol_px)
        ok = self.match.valid
        self._matched = np.flatnonzero(ok)
        self.right = (_Correlator(right_ref, self.match.points_right[ok], self.subset, self.order, self.device,
                                  self.max_iter, self.tol) if ok.any() else None)
        t0 = time.perf_counter()
        self._tri_ref = self._triangulate(self.points, self.match.points_right)
        self.timings["triangulation_s"] = time.perf_counter() - t0
        self._frame = self._choose_frame(frame)
        self._previous = None          # (params_left (N, k), params_right (N, k)) of the last state
        self._previous_images = (None, None)
        self.reference = self._field(None, index=0)

    # -------------------------------------------------------------------------------------------
    @staticmethod
    def _typical_spacing(points: np.ndarray) -> float:
        if points.shape[0] < 2:
            return 10.0
        from scipy.spatial import cKDTree

        d, _ = cKDTree(points).query(points, k=2)
        return float(max(np.median(d[:, 1]), 1.0))

    def _check_match(self, match: StereoMatch) -> StereoMatch:
        if not isinstance(match, StereoMatch):
            raise ValueError(f"match must be a StereoMatch, got {type(match).__name__}")
        if match.points_left.shape != self.points.shape or not np.allclose(match.points_left, self.points):
            raise ValueError("the given StereoMatch was computed for other points than these")
        if match.params.shape[1] != n_params(self.order):
            raise ValueError(f"the given StereoMatch has order {match.order}, expected {self.order}")
        return match

    def _epipolar(self, idx: np.ndarray, right_points: np.ndarray) -> np.ndarray:
        ur, sr = undistort_points(self.rig.right, right_points, device=self.device, margin_px=np.inf)
        d = epipolar_distance(self._F, self._ideal_left[idx], ur)
        d[sr != TriangulationStatus.OK] = np.nan
        return d

    def _match(self) -> StereoMatch:
        """Left reference -> right reference, guided by the rig's epipolar geometry."""
        L, R = self._left_ref, self._right_ref
        k = n_params(self.order)
        t0 = time.perf_counter()
        pa, pb = feature_matches(L, R, max_features=self.max_features)
        n_feat = 0
        params6 = np.full((self.points.shape[0], 6), np.nan)
        has = np.zeros(self.points.shape[0], dtype=bool)
        gradient = np.zeros((2, 2))
        if pa.shape[0]:
            # epipolar filter on undistorted points (a looser tolerance than for the final match: SIFT
            # keypoints are good to ~0.5 px, and the guess only needs to land within a few px)
            ua, sa = undistort_points(self.rig.left, pa, device=self.device, margin_px=np.inf)
            ub, sb = undistort_points(self.rig.right, pb, device=self.device, margin_px=np.inf)
            d = epipolar_distance(self._F, ua, ub)
            keep = (d <= max(3.0, 3.0 * self.epipolar_tol_px)) & (sa == 0) & (sb == 0)
            pa, pb = pa[keep], pb[keep]
            n_feat = int(pa.shape[0])
            radius = max(6.0 * self.subset, 3.0 * self.step)
            params6, has = affine_guess(self.points, pa, pb, radius=radius)
            if np.any(has):
                gradient = np.array([[np.median(params6[has, 1]), np.median(params6[has, 2])],
                                     [np.median(params6[has, 4]), np.median(params6[has, 5])]])
        guess = np.zeros((self.points.shape[0], k))
        guess[has] = _embed(params6[has], self.order)
        current = _prepare_current(R, self.device)

        def extra(idx, p):
            return self._epipolar(idx, self.points[idx] + _displacement(p, self.order)) <= self.epipolar_tol_px

        def fallback(idx):
            uv, _, ok = _epipolar_search(self.rig, L, R, self.points[idx], self.subset, gradient, self.device,
                                         min_score=0.5)
            g = np.zeros((idx.size, k))
            g6 = np.zeros((idx.size, 6))
            g6[:, 0] = uv[:, 0] - self.points[idx, 0]
            g6[:, 3] = uv[:, 1] - self.points[idx, 1]
            g6[:, [1, 2, 4, 5]] = gradient.ravel()
            g[:] = _embed(np.nan_to_num(g6), self.order)
            return g, ok

        eligible = self.in_roi
        self.timings["features_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = _correlate(self.left, current, guess, has, SOURCE_FEATURES, eligible=eligible, zncc_min=self.zncc_min,
                         radius=self.radius, extra=extra, fallback=fallback)
        self.timings["match_icgn_s"] = time.perf_counter() - t0
        status = _final_status(res, eligible & self.left.ready, StereoStatus.MATCH_FAILED,
                               StereoStatus.EPIPOLAR_VIOLATION, self.zncc_min)
        ran = res.icgn_status != int(Status.NOT_COMPUTED)
        right = np.full_like(self.points, np.nan)
        right[ran] = self.points[ran] + _displacement(res.params[ran], self.order)
        epi = np.full(self.points.shape[0], np.nan)
        if np.any(ran):
            epi[ran] = self._epipolar(np.flatnonzero(ran), right[ran])
        return StereoMatch(self.points.copy(), right, res.params, res.zncc, res.iterations, res.icgn_status, epi,
                           res.source, status, n_feat, self.order)

    def _triangulate(self, pl: np.ndarray, pr: np.ndarray):
        """Triangulate rows where both points are finite; returns (xyz (N, 3), residual (N,), status (N,))."""
        n = pl.shape[0]
        xyz = np.full((n, 3), np.nan)
        res = np.full(n, np.nan)
        st = np.full(n, int(TriangulationStatus.INVALID_INPUT), dtype=np.int32)
        fin = np.all(np.isfinite(pl), axis=1) & np.all(np.isfinite(pr), axis=1)
        if np.any(fin):
            t = triangulate(self.rig, pl[fin], pr[fin], method=self.triangulation, device=self.device)
            xyz[fin], res[fin], st[fin] = t.points, t.residuals, t.status
        return xyz, res, st

    def _choose_frame(self, frame):
        if isinstance(frame, str):
            if frame == "left":
                return np.eye(3), np.zeros(3), "left"
            if frame == "plane":
                good = self.match.valid & (self._tri_ref[2] == TriangulationStatus.OK)
                if np.count_nonzero(good) < 3:
                    raise ValueError("frame='plane' needs at least 3 matched and triangulated points; "
                                     f"the reference match has {int(np.count_nonzero(good))}")
                R, t = plane_frame(self._tri_ref[0], good)
                return R, t, "plane"
            raise ValueError(f"frame must be one of {_FRAME_CHOICES} or (R_obj_left, t_obj_left), got {frame!r}")
        R, t = as_frame(frame)
        return R, t, "custom"

    # -------------------------------------------------------------------------------------------
    def _track(self, corr: _Correlator, image: np.ndarray, previous: np.ndarray | None, eligible: np.ndarray,
               reference_image: np.ndarray, previous_image: np.ndarray | None) -> _TrackResult:
        k = n_params(self.order)
        n = corr.points.shape[0]
        current = _prepare_current(image, self.device)
        # initial guess: the previous state's parameters (or zero) plus the global integer shift
        # between the previous image (or the reference) and this one, by phase correlation. 2nd-order
        # IC-GN converges slowly from 2-3 px away on fine speckle (measured on the 5 MP benchmark: a
        # 3 px motion took 32 iterations on average, many hitting max_iter; within 0.5 px, 6-8)
        guess = np.zeros((n, k)) if previous is None else np.nan_to_num(previous)
        src = SOURCE_NONE if previous is None else SOURCE_PREVIOUS
        base = reference_image if previous is None or previous_image is None else previous_image
        u, v, peak = phase_correlation(base, image)
        if peak > 0.05 and (u or v):
            guess[:, 0] += u
            guess[:, k // 2] += v
            src = SOURCE_GLOBAL if previous is None else src
        has = np.ones(n, dtype=bool)
        cache = {}

        def fallback(idx):
            if "features" not in cache:
                pa, pb = feature_matches(reference_image, image, max_features=self.max_features)
                cache["features"] = affine_guess(corr.points, pa, pb, radius=max(6.0 * self.subset, 3.0 * self.step))
            p6, ok = cache["features"]
            g = np.zeros((idx.size, k))
            g[ok[idx]] = _embed(p6[idx][ok[idx]], self.order)
            return g, ok[idx]

        return _correlate(corr, current, guess, has, src, eligible=eligible, zncc_min=self.zncc_min,
                          radius=self.radius, fallback=fallback, max_seeds=max(64, n),
                          min_fallback=max(16, int(0.01 * n)))

    def measure(self, left_cur, right_cur, *, index: int = 1, use_previous: bool = True) -> Field3D:
        """Track a current pair from the reference pair and return its :class:`Field3D`.

        ``use_previous``: start IC-GN from the parameters of the last measured state (a sequence's
        previous frame); otherwise from zero displacement. POIs that fail are retried from SIFT
        feature matches and from converged neighbours.
        """
        L, R = _check_pair(left_cur, right_cur, "current")
        if L.shape != self.shape:
            raise ValueError(f"the current images are {L.shape[1]}x{L.shape[0]} px but the reference images are "
                             f"{self.shape[1]}x{self.shape[0]} px")
        prev = self._previous if use_previous else None
        prev_images = self._previous_images if prev is not None else (None, None)
        matched = self._matched
        self.timings = {}
        t0 = time.perf_counter()
        tl = self._track(self.left, L, None if prev is None else prev[0], self.match.valid, self._left_ref,
                         prev_images[0])
        self.timings["track_left_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if self.right is not None:
            tr = self._track(self.right, R, None if prev is None else prev[1][matched],
                             np.ones(matched.size, dtype=bool), self._right_ref, prev_images[1])
        else:
            tr = None
        self.timings["track_right_s"] = time.perf_counter() - t0
        f = self._field((tl, tr), index=index)
        self._previous = (f.details["params_left"], f.details["params_right"])
        self._previous_images = (L, R)
        return f

    def set_previous(self, params_left, params_right, images=None) -> None:
        """Set the initial guess of the next :meth:`measure`: parameters (N, 6|12) of the left and right tracks.

        E.g. ``field.details["params_left"]``, ``field.details["params_right"]`` of the previous
        state read back from a result file. NaN rows (points that failed) start from zero.
        ``images``: that state's ``(left, right)`` images, optional (their global shift to the next
        images is added to the guess).
        """
        k = n_params(self.order)
        n = self.points.shape[0]
        pl = np.asarray(params_left, dtype=np.float64)
        pr = np.asarray(params_right, dtype=np.float64)
        if pl.shape != (n, k) or pr.shape != (n, k):
            raise ValueError(f"previous parameters must both have shape {(n, k)}, got {pl.shape} and {pr.shape}")
        self._previous = (pl, pr)
        self._previous_images = (None, None) if images is None else _check_pair(images[0], images[1], "previous")

    # -------------------------------------------------------------------------------------------
    def _field(self, tracks, index: int) -> Field3D:
        n = self.points.shape[0]
        k = n_params(self.order)
        m = self.match
        xyz_ref, res_ref, tri_ref = self._tri_ref
        status = m.status.astype(np.int8).copy()
        details = {"match_status": m.icgn_status, "guess_source": m.guess_source,
                   "triangulation_ref_status": tri_ref, "points_right_ref": m.points_right,
                   "params_stereo": m.params}
        if tracks is None:
            xyz_cur, res_cur, tri_cur = xyz_ref, res_ref, tri_ref
            epi_cur = m.epipolar_px
            z_left = np.where(m.valid, 1.0, np.nan)
            z_right = z_left.copy()
            pl_cur, pr_cur = self.points.copy(), m.points_right.copy()
            details.update(track_left_status=np.where(m.valid, int(Status.CONVERGED), int(Status.NOT_COMPUTED)).astype(np.int32),
                           track_right_status=np.where(m.valid, int(Status.CONVERGED), int(Status.NOT_COMPUTED)).astype(np.int32),
                           params_left=np.where(m.valid[:, None], 0.0, np.nan) * np.ones((n, k)),
                           params_right=np.where(m.valid[:, None], 0.0, np.nan) * np.ones((n, k)))
        else:
            tl, tr = tracks
            matched = self._matched
            pl_cur = np.full((n, 2), np.nan)
            pr_cur = np.full((n, 2), np.nan)
            z_left = np.where(np.isfinite(tl.zncc), tl.zncc, np.nan)
            z_right = np.full(n, np.nan)
            left_ok = tl.accepted
            right_ok = np.zeros(n, dtype=bool)
            st_right = np.full(n, int(Status.NOT_COMPUTED), dtype=np.int32)
            p_right = np.full((n, k), np.nan)
            ran_l = tl.icgn_status != int(Status.NOT_COMPUTED)
            pl_cur[ran_l] = self.points[ran_l] + _displacement(tl.params[ran_l], self.order)
            if tr is not None:
                ran_r = tr.icgn_status != int(Status.NOT_COMPUTED)
                sel = matched[ran_r]
                pr_cur[sel] = m.points_right[sel] + _displacement(tr.params[ran_r], self.order)
                z_right[matched] = tr.zncc
                right_ok[matched] = tr.accepted
                st_right[matched] = tr.icgn_status
                p_right[matched] = tr.params
            # per-stage status, first failure wins (reference stages already in `status`)
            fl = _final_status(tl, m.valid, StereoStatus.TRACK_LEFT_FAILED, StereoStatus.TRACK_LEFT_FAILED, self.zncc_min)
            fr = np.full(n, int(StereoStatus.NOT_COMPUTED), dtype=np.int8)
            if tr is not None:
                fr[matched] = _final_status(tr, np.ones(matched.size, dtype=bool), StereoStatus.TRACK_RIGHT_FAILED,
                                            StereoStatus.TRACK_RIGHT_FAILED, self.zncc_min)
            ok_ref = status == StereoStatus.OK
            status[ok_ref & (fl != StereoStatus.OK)] = np.where(fl == StereoStatus.LOW_ZNCC, StereoStatus.LOW_ZNCC,
                                                                StereoStatus.TRACK_LEFT_FAILED)[ok_ref & (fl != StereoStatus.OK)]
            ok_ref = status == StereoStatus.OK
            status[ok_ref & (fr != StereoStatus.OK)] = np.where(fr == StereoStatus.LOW_ZNCC, StereoStatus.LOW_ZNCC,
                                                                StereoStatus.TRACK_RIGHT_FAILED)[ok_ref & (fr != StereoStatus.OK)]
            both = left_ok & right_ok
            use_l = np.where(both[:, None], pl_cur, np.nan)
            use_r = np.where(both[:, None], pr_cur, np.nan)
            t0 = time.perf_counter()
            xyz_cur, res_cur, tri_cur = self._triangulate(use_l, use_r)
            self.timings["triangulation_s"] = time.perf_counter() - t0
            epi_cur = np.full(n, np.nan)
            if np.any(both):
                epi_cur[both] = epipolar_residuals(self.rig, pl_cur[both], pr_cur[both], device=self.device)
            details.update(track_left_status=tl.icgn_status, track_right_status=st_right,
                           params_left=tl.params, params_right=p_right)
        # epipolar check of the current state, triangulation of both states
        ok = status == StereoStatus.OK
        status[ok & ~(epi_cur <= self.epipolar_tol_px)] = StereoStatus.EPIPOLAR_VIOLATION
        ok = status == StereoStatus.OK
        tri_bad = (tri_ref != TriangulationStatus.OK) | (tri_cur != TriangulationStatus.OK)
        status[ok & tri_bad] = StereoStatus.TRIANGULATION_FAILED
        valid = status == StereoStatus.OK
        # coordinates in the output frame
        R, t, name = self._frame
        xyz_ref_f = xyz_ref @ R.T + t
        uvw = (xyz_cur - xyz_ref) @ R.T
        uvw[~valid] = np.nan
        # reference positions are kept wherever the reference match and its triangulation are good
        xyz_ref_f[~(m.valid & (tri_ref == TriangulationStatus.OK))] = np.nan
        camera_center = t  # the left camera centre (origin of the left frame) in the output frame
        t0 = time.perf_counter()
        if self.grid_shape is not None:
            strain = surface_strain_grid(xyz_ref_f, np.nan_to_num(uvw), valid, self.grid_shape, self.strain_window,
                                         camera_center=camera_center)
        else:
            strain = surface_strain(xyz_ref_f, np.nan_to_num(uvw), valid, self.neighbours, camera_center=camera_center)
        self.timings["strain_s"] = time.perf_counter() - t0
        details.update(triangulation_status=tri_cur, points_left_cur=pl_cur, points_right_cur=pr_cur)
        zs = np.where(np.isfinite(m.zncc), m.zncc, np.nan)
        return Field3D(
            points=self.points, grid_shape=self.grid_shape,
            X=xyz_ref_f[:, 0], Y=xyz_ref_f[:, 1], Z=xyz_ref_f[:, 2], U=uvw[:, 0], V=uvw[:, 1], W=uvw[:, 2],
            exx=strain["exx"], eyy=strain["eyy"], exy=strain["exy"], normal=strain["normal"],
            zncc_stereo=zs, zncc_left=z_left, zncc_right=z_right,
            epipolar_ref_px=m.epipolar_px, epipolar_px=epi_cur, reprojection_ref_px=res_ref, reprojection_px=res_cur,
            status=status, strain_valid=strain["strain_valid"], R_frame_left=R, t_frame_left=t, frame_name=name,
            index=int(index), details=details,
        )


def stereo(rig, left_ref, right_ref, left_cur=None, right_cur=None, *, points=None, step: int = 10, roi=None,
           subset: int = 21, order: int = 2, frame="left", epipolar_tol_px: float = 1.0, zncc_min: float = 0.8,
           strain_window: int = 5, device=None, **options) -> Field3D:
    """Stereo DIC of one reference pair, and of one current pair when given.

    Parameters
    ----------
    rig : calibration.stereo.StereoRig (cameras ``left``, ``right``; ``R_right_left``, ``t_right_left`` mm).
    left_ref, right_ref : (H, W) grey images of the reference state.
    left_cur, right_cur : (H, W) grey images of a current state, optional (both or neither).
    points, step, roi, subset, order, frame, epipolar_tol_px, zncc_min, strain_window, device :
        see :class:`StereoCorrelation`; ``options`` passes ``max_iter``, ``tol``, ``triangulation``,
        ``max_features``.

    Returns
    -------
    Field3D
        The reference shape (``U = V = W = 0``, zero strain) when no current pair is given, else
        the current state's displacements and strains. For sequences use
        :class:`StereoCorrelation` or :func:`dic.sequence.stereo_sequence`.

    Raises
    ------
    ValueError
        Images of different sizes, a rig calibrated for another image size, bad parameters.
    """
    if (left_cur is None) != (right_cur is None):
        raise ValueError("give both left_cur and right_cur (a current stereo pair) or neither")
    sc = StereoCorrelation(rig, left_ref, right_ref, points=points, step=step, roi=roi, subset=subset, order=order,
                           frame=frame, epipolar_tol_px=epipolar_tol_px, zncc_min=zncc_min,
                           strain_window=strain_window, device=device, **options)
    if left_cur is None:
        return sc.reference
    return sc.measure(left_cur, right_cur)
