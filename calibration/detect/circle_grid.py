"""Circle centres of a symmetric circle grid with OpenCV (:func:`detect_circle_grid`), in the
target's id order.

Conventions: docs/conventions.md (pixel (0, 0) is the centre of the top-left pixel, points are
(x, y)); target frame: :mod:`calibration.targets`.
"""
from __future__ import annotations

import numpy as np

from ..targets import CircleGridTarget
from .common import _check_target, _gray_u8, _orderings, _pick_ordering


def detect_circle_grid(image, target: CircleGridTarget, *, mirrored: bool = False, blob_detector=None):
    """Circle centres of a symmetric grid of dark circles with ``cv2.findCirclesGrid`` (the
    blob centroids; tries the clustering variant for perspective views). A symmetric grid has no
    orientation mark: the handedness follows ``mirrored`` and the grid's x axis is taken closest
    to the image x axis. Returns ``(image_points (N, 2), ids (N,))`` or ``None``."""
    import cv2

    _check_target(target, CircleGridTarget)
    gray = _gray_u8(image)
    if blob_detector is None:
        params = cv2.SimpleBlobDetector_Params()
        params.maxArea = float(gray.size)
        params.minArea = 10.0
        blob_detector = cv2.SimpleBlobDetector_create(params)
    nx, ny = target.grid
    centres = None
    for flags in (cv2.CALIB_CB_SYMMETRIC_GRID, cv2.CALIB_CB_SYMMETRIC_GRID | cv2.CALIB_CB_CLUSTERING):
        ok, found = cv2.findCirclesGrid(gray, (nx, ny), flags=flags, blobDetector=blob_detector)
        if ok and found is not None:
            centres = found
            break
    if centres is None:
        return None
    pts = _pick_ordering(_orderings(centres.reshape(ny, nx, 2).astype(np.float64)), target.points_px, mirrored)
    if pts is None:
        return None
    return pts, np.arange(len(pts))
