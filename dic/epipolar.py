"""Epipolar geometry of a calibrated stereo rig, and the ZNCC search along an epipolar curve.

Conventions (docs/conventions.md): ``x_right = R_right_left @ x_left + t_right_left`` (mm); pixels
``(x, y)`` with (0, 0) the centre of the top-left pixel; *ideal* pixels are undistorted ones.
The search (:func:`epipolar_search`) is the ``"epipolar"`` initial-guess strategy of
:mod:`dic.correlation.guesses`: the fallback of the stereo match for POIs far from every feature.
"""
from __future__ import annotations

import numpy as np

from ._triangulate import TriangulationStatus, undistort_points

__all__ = ["fundamental_matrix", "epipolar_distance", "epipolar_residuals", "epipolar_candidates", "epipolar_search"]


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

    Both sets are undistorted with the rig's lens models (:func:`dic.undistort_points`,
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


def _zncc_rows(patches: np.ndarray, template: np.ndarray) -> np.ndarray:
    p = patches - patches.mean(axis=1, keepdims=True)
    t = template - template.mean()
    den = np.sqrt(np.sum(p * p, axis=1) * np.sum(t * t))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, (p @ t) / den, -1.0)


def epipolar_candidates(rig, ideal_left_point: np.ndarray, shape, margin: float, n_depth: int = 4096) -> np.ndarray:
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


def epipolar_search(rig, left: np.ndarray, right: np.ndarray, points: np.ndarray, subset: int, gradient: np.ndarray,
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
        cand = epipolar_candidates(rig, ideal[i], left.shape, margin=r * max(1.0, np.abs(A).sum(axis=1).max()) + 1)
        if cand.shape[0] == 0:
            continue
        # the template is centred on the integer pixel; shift the candidates accordingly
        delta = np.array([cx - points[i, 0], cy - points[i, 1]]) @ A.T
        best_s, best_c = -1.0, None
        for c0 in range(0, cand.shape[0], 2048):
            c = cand[c0:c0 + 2048] + delta
            # the subset's sample positions at each candidate (M, S²), x and y apart (float64 sums, then float32)
            mx = np.add.outer(c[:, 0], shaped[:, 0]).astype(np.float32)
            my = np.add.outer(c[:, 1], shaped[:, 1]).astype(np.float32)
            patches = cv2.remap(right, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
            z = _zncc_rows(patches, template)
            j = int(np.argmax(z))
            if z[j] > best_s:
                best_s, best_c = float(z[j]), cand[c0 + j]
        if best_c is not None and best_s >= min_score:
            out[i] = best_c
            score[i] = best_s
    ok = np.all(np.isfinite(out), axis=1)
    return out, score, ok
