"""Checkerboard inner corners with OpenCV (:func:`detect_checkerboard`), in the target's id order.

Conventions: docs/conventions.md (pixel (0, 0) is the centre of the top-left pixel, points are
(x, y)); target frame: :mod:`calibration.targets`.
"""
from __future__ import annotations

import numpy as np

from ..targets import CheckerboardTarget
from .common import _check_target, _gray_u8, _orderings, _pick_ordering


def detect_checkerboard(image, target: CheckerboardTarget, *, mirrored: bool = False):
    """Inner corners of a checkerboard, with OpenCV (for comparison and for printed boards).

    Tries ``cv2.findChessboardCornersSB`` (exhaustive + accuracy flags, then normalised), then
    the classic ``cv2.findChessboardCorners`` refined by ``cv2.cornerSubPix``. The corners are put
    in the target's id order: the handedness follows ``mirrored`` (a checkerboard cannot tell),
    and the 180-degree ambiguity is resolved from the square colours when ``nx + ny`` is odd
    (else the board's x axis is taken closest to the image x axis).

    Returns ``(image_points (N, 2), ids (N,))`` or ``None`` when OpenCV finds no board."""
    import cv2

    _check_target(target, CheckerboardTarget)
    gray = _gray_u8(image)
    nx, ny = target.corners
    corners = None
    for flags in (cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY, cv2.CALIB_CB_NORMALIZE_IMAGE):
        ok, found = cv2.findChessboardCornersSB(gray, (nx, ny), flags=flags)
        if ok and found is not None:
            corners = found
            break
    if corners is None:
        ok, found = cv2.findChessboardCorners(gray, (nx, ny))
        if not ok or found is None:
            return None
        corners = cv2.cornerSubPix(gray, found, (11, 11), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4))
    grid_pts = corners.reshape(ny, nx, 2).astype(np.float64)
    from scipy import ndimage

    def colour_score(pts):
        # inner square between corners (i, j) and (i+1, j+1) is target square (i+1, j+1): dark
        # when i + j is even
        g = pts.reshape(ny, nx, 2)
        centres = 0.25 * (g[:-1, :-1] + g[1:, :-1] + g[:-1, 1:] + g[1:, 1:])
        jj, ii = np.mgrid[0:ny - 1, 0:nx - 1]
        dark = ((ii + jj) % 2 == 0).ravel()
        vals = ndimage.map_coordinates(gray.astype(np.float64), [centres[..., 1].ravel(), centres[..., 0].ravel()], order=1)
        return float(np.mean(vals[~dark]) - np.mean(vals[dark]))

    pts = _pick_ordering(_orderings(grid_pts), target.points_px, mirrored,
                         colour_score if (nx + ny) % 2 == 1 else None)
    if pts is None:
        return None
    return pts, np.arange(len(pts))
