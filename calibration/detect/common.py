"""Shared by the target detectors: the detection error, phase demodulation, input checks, the
homography helpers and the blur estimate of the phase detectors, and the ordering of OpenCV's grids.

Conventions: docs/conventions.md (pixel (0, 0) is the centre of the top-left pixel, points are
(x, y)); target frame: :mod:`calibration.targets`.
"""
from __future__ import annotations

import math

import numpy as np

from ..targets import PhaseTarget

TWO_PI = 2.0 * math.pi


class DetectionError(RuntimeError):
    """The target could not be found or identified in a view (the message says why)."""


def _check_target(target, kind=PhaseTarget):
    if not isinstance(target, kind):
        raise ValueError(f"target must be a {kind.__name__}, got {type(target).__name__}")


def demodulate_images(images, target: PhaseTarget | None = None, *, min_modulation: float = 3.0, device=None):
    """Demodulate an (N, H, W) stack into float64 NumPy ``(phase, modulation, background, valid)``.

    ``valid`` is bool: modulation >= ``min_modulation`` grey levels and no saturated sample.
    ``target`` (optional) checks that N matches ``target.steps``.
    """
    from kernels.phase import demodulate

    n = len(images) if isinstance(images, (list, tuple)) else np.shape(images)[0] if np.ndim(images) == 3 else None
    if n is None:
        raise ValueError(f"images must be a stack (N, H, W) of phase-shifted images, got shape {np.shape(images)}")
    if target is not None and n != target.steps:
        raise ValueError(f"the target shows {target.steps} phase steps but {n} images were given")
    phase, mod, bg, valid = demodulate(images, min_modulation=min_modulation, device=device)
    return (phase.numpy().astype(np.float64), mod.numpy().astype(np.float64),
            bg.numpy().astype(np.float64), valid.numpy().astype(bool))


def _check_maps(phase, modulation, mask):
    phase = np.asarray(phase, dtype=np.float64)
    modulation = np.asarray(modulation, dtype=np.float64)
    if phase.ndim != 2 or phase.size == 0:
        raise ValueError(f"phase must be a 2-D map (H, W), got shape {phase.shape}")
    if modulation.shape != phase.shape:
        raise ValueError(f"modulation must have the phase map's shape {phase.shape}, got {modulation.shape}")
    if mask is None:
        mask = np.ones(phase.shape, dtype=bool)
    mask = np.asarray(mask)
    if mask.shape != phase.shape:
        raise ValueError(f"mask must have the phase map's shape {phase.shape}, got {mask.shape}")
    finite = np.isfinite(phase) & np.isfinite(modulation)
    return np.where(finite, phase, 0.0), np.where(finite, modulation, 0.0), mask.astype(bool) & finite


def _wrap(a):
    return (a + np.pi) % TWO_PI - np.pi


def _homography(src, dst):
    import cv2

    H, _ = cv2.findHomography(np.asarray(src, np.float64), np.asarray(dst, np.float64), 0)
    if H is None:
        raise DetectionError("could not estimate a local homography (degenerate neighbour layout)")
    return H / H[2, 2]


def _apply_h(H, xy):
    q = np.c_[xy, np.ones(len(xy))] @ H.T
    return q[:, :2] / q[:, 2:3]


def _jacobian_h(H, xy):
    x, y = xy
    q = H @ np.array([x, y, 1.0])
    J = np.zeros((2, 2))
    for c in range(2):
        J[0, c] = (H[0, c] * q[2] - q[0] * H[2, c]) / q[2] ** 2
        J[1, c] = (H[1, c] * q[2] - q[1] * H[2, c]) / q[2] ** 2
    return J


def _estimate_blur(modulation, mask):
    """Rough Gaussian blur (px) from the width of the modulation drop at the fringe-area edge.

    The modulation across a straight edge of the fringe area is ``M0 * Phi(d / sigma)``; its
    10-90 % width is 2.56 sigma (plus ~1 px for the pixel). Measured along image rows and
    columns, median over edges."""
    valid = modulation * mask
    top = np.percentile(valid[mask], 90) if mask.any() else 0.0
    if top <= 0:
        return 0.0
    lo_t, hi_t = 0.1 * top, 0.9 * top
    widths = []
    for arr in (valid, valid.T):
        for row in arr[:: max(1, arr.shape[0] // 64)]:
            above_hi = row >= hi_t
            if not above_hi.any():
                continue
            first_hi = int(np.argmax(above_hi))
            last_hi = len(row) - 1 - int(np.argmax(above_hi[::-1]))
            # rising edge before first_hi
            lo_idx = np.flatnonzero(row[:first_hi] <= lo_t)
            if lo_idx.size:
                widths.append(first_hi - lo_idx[-1])
            lo_idx = np.flatnonzero(row[last_hi:] <= lo_t)
            if lo_idx.size:
                widths.append(lo_idx[0])
    if not widths:
        return 0.0
    wdt = float(np.median(widths))
    return max(0.0, (wdt - 1.0) / 2.56)


def _gray_u8(image):
    from kernels._device import as_float32_image

    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[0] == 1:
        arr = arr[0]
    f = as_float32_image(arr)
    if arr.dtype == np.uint8:
        return arr
    lo, hi = float(f.min()), float(f.max())
    return np.clip(np.rint((f - lo) / max(hi - lo, 1e-9) * 255), 0, 255).astype(np.uint8)


def _orderings(grid_pts: np.ndarray) -> list[np.ndarray]:
    """The 4 re-orderings of an (ny, nx, 2) corner grid that keep its shape (identity, 180 deg,
    flip x, flip y)."""
    return [grid_pts, grid_pts[::-1, ::-1], grid_pts[:, ::-1], grid_pts[::-1, :]]


def _pick_ordering(candidates, object_px, mirrored, score=None):
    """Choose, among grid orderings, one whose target->image handedness matches ``mirrored``;
    ties go to ``score`` (higher better), else to the target x axis closest to image +x."""
    best = None
    for grid_pts in candidates:
        pts = grid_pts.reshape(-1, 2)
        H = _homography(object_px, pts)
        J = _jacobian_h(H, object_px.mean(axis=0))
        if (np.linalg.det(J) < 0) != bool(mirrored):
            continue
        sc = (score(pts) if score is not None else 0.0, J[0, 0] / np.linalg.norm(J[:, 0]))
        if best is None or sc > best[0]:
            best = (sc, pts)
    return None if best is None else best[1]
