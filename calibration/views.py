"""One calibration view: the target found in its image stack (:func:`detect_view_stack`), the dot
filters (:func:`filter_detection`), correspondences of dense views on a grid of screen points
(:func:`dense_grid_points`, :func:`dense_view_points`), checkerboard corners in the target's order,
and the results :class:`ViewResult` and :class:`StereoView`.

Reading a view's images from files is :mod:`calibration.pipeline`'s job (:func:`calibration.pipeline.read_stack`,
:func:`calibration.pipeline.detect_view`).

Frames and units: docs/conventions.md (mm, px, camera frame x right / y down / z forward, pixel
(0, 0) the centre of the top-left pixel); target frame: :mod:`calibration.targets`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .detect import (
    DenseDecoding,
    DetectionError,
    DotDetection,
    decode_dense,
    demodulate_images,
    detect_checkerboard,
    detect_dots,
)
from .targets import CheckerboardTarget, PhaseTarget

__all__ = ["MODES", "MIN_VIGNETTING_SLOPE", "ViewResult", "StereoView", "detect_view_stack", "filter_detection",
           "dense_grid_points", "dense_view_points"]

MODES = ("dots", "dense")
#: Floor of :func:`detect_view_stack`'s vignetting test (relative modulation change across a dot's fit
#: window): about twice the largest value on the fully lit dots of the virtual lab's direct views.
MIN_VIGNETTING_SLOPE = 0.015


@dataclass
class ViewResult:
    """What one view gave: the dots (or the dense decoding) or why it was dropped.

    Attributes
    ----------
    name : str
        The view's label (its folder or pattern, or ``view<i>``).
    image_size : (width, height) or None
    detection : DotDetection or None
        Dot mode: image points, ids, object points, per-point quality, ``mirrored``.
    dense : DenseDecoding or None
        Dense mode: screen coordinates per pixel.
    error : str or None
        Why the view was dropped (``None`` when usable).
    preview : (h, w) float32 or None
        The wrapped phase (rad) subsampled by ``preview_step`` (for figures).
    removed : list of (id, misfit)
        Dots the detector found but :func:`detect_view_stack` removed because their phase fit is poor
        (``misfit`` = residual × modulation relative to the view's median; see ``max_misfit``).
    vignetted : list of (id, slope)
        Dots removed because the modulation falls off across their fit window (``slope``: the
        relative change centre → window edge, see ``max_slope``): partly vignetted, e.g. by a
        mirror's edge.
    """

    name: str
    image_size: tuple | None = None
    detection: DotDetection | None = None
    dense: DenseDecoding | None = None
    error: str | None = None
    preview: np.ndarray | None = None
    preview_step: int = 1
    removed: list = field(default_factory=list)
    vignetted: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.error is None

    @property
    def mirrored(self) -> bool | None:
        if self.detection is not None:
            return bool(self.detection.mirrored)
        if self.dense is not None:
            return self.dense.mirrored
        return None

    @property
    def n_points(self) -> int:
        if self.detection is not None:
            return len(self.detection)
        if self.dense is not None:
            return int(self.dense.mask.sum())
        return 0

    def summary(self) -> str:
        if not self.ok:
            return f"{self.name}: dropped — {self.error}"
        kind = "mirrored" if self.mirrored else "direct"
        if self.detection is not None:
            d = self.detection
            q = np.median(d.sigma_px) if np.any(np.isfinite(d.sigma_px)) else float("nan")
            extra = (f"; removed {len(self.removed)} dot(s) with a poor phase fit (ids "
                     f"{', '.join(str(i) for i, _ in self.removed)})") if self.removed else ""
            if self.vignetted:
                extra += (f"; removed {len(self.vignetted)} vignetted dot(s) (ids "
                          f"{', '.join(str(i) for i, _ in self.vignetted)})")
            return (f"{self.name}: {len(d)} dots, {kind}, blur σ ≈ {d.blur_sigma:.1f} px, "
                    f"median centre σ {q:.4f} px{extra}")
        return f"{self.name}: {self.n_points} decoded pixels, {kind}"


def _check_phase_target(target):
    if not isinstance(target, PhaseTarget):
        raise ValueError(f"target must be a calibration.targets.PhaseTarget (load it with "
                         f"calibration.targets.load_target), got {type(target).__name__}")


def _check_mode(mode):
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")


def detect_view_stack(stack, target: PhaseTarget, *, mode: str = "dots", name: str = "view0",
                      min_modulation: float = 3.0, correct_blur: bool | None = None, min_points: int = 4,
                      max_misfit: float | None = 1.5, max_slope: float | None = 3.0, dense_erode: int = 2,
                      device=None) -> ViewResult:
    """Find the target in one view's image stack already in memory (:func:`calibration.pipeline.detect_view`
    without the reading; same options).

    ``stack`` is (N, H, W) grey levels: ``target.steps`` images (``mode="dots"``) or
    ``target.n_dense_images`` (``mode="dense"``), in display order. Returns a :class:`ViewResult`,
    with ``error`` set when the target could not be found or identified; a stack of the wrong
    shape or count raises ``ValueError``.
    """
    _check_phase_target(target)
    _check_mode(mode)
    n_img = target.steps if mode == "dots" else target.n_dense_images
    if not isinstance(stack, np.ndarray) or stack.ndim != 3 or stack.shape[1] == 0 or stack.shape[2] == 0:
        got = getattr(stack, "shape", type(stack).__name__)
        raise ValueError(f"stack must be an (N, H, W) array of phase-shifted images, got {got}")
    if stack.shape[0] != n_img:
        raise ValueError(f"the view holds {stack.shape[0]} images but the target needs {n_img}")
    size = (int(stack.shape[2]), int(stack.shape[1]))
    if mode == "dense":
        try:
            dec = decode_dense(stack, target, min_modulation=min_modulation, erode=dense_erode, device=device)
        except (DetectionError, ValueError) as exc:
            return ViewResult(name, size, error=f"dense decoding failed: {exc}")
        n = int(dec.mask.sum())
        if n < 100 * min_points:
            return ViewResult(name, size, error=f"only {n} pixels decoded (need {100 * min_points})")
        if dec.mirrored is None:
            return ViewResult(name, size, error="could not tell whether the view is mirrored")
        return ViewResult(name, size, dense=dec)
    phase, mod, _, valid = demodulate_images(stack, target, min_modulation=min_modulation, device=device)
    step = max(1, int(math.ceil(max(size) / 800)))
    preview = np.where(valid, phase, np.nan)[::step, ::step].astype(np.float32)
    try:
        extra = {} if correct_blur is None else {"correct_blur": bool(correct_blur)}
        det = detect_dots(phase, mod, target, mask=valid, min_modulation=min_modulation, **extra)
    except DetectionError as exc:
        return ViewResult(name, size, error=f"target not found: {exc}", preview=preview, preview_step=step)
    except np.linalg.LinAlgError as exc:
        # a numerically degenerate view (e.g. dots only a few pixels apart): one dropped view, not a lost session
        return ViewResult(name, size, error=f"target not found: degenerate geometry in the dot fit ({exc})",
                          preview=preview, preview_step=step)
    if not (np.all(np.isfinite(det.image_points))):
        det = _subset_detection(det, np.all(np.isfinite(det.image_points), axis=1))
    det, removed, vignetted = filter_detection(det, max_misfit=max_misfit, max_slope=max_slope, min_points=min_points)
    if len(det) < min_points:
        return ViewResult(name, size, error=f"only {len(det)} dots identified (need {min_points})", preview=preview,
                          preview_step=step)
    return ViewResult(name, size, detection=det, preview=preview, preview_step=step, removed=removed,
                      vignetted=vignetted)


def filter_detection(det: DotDetection, *, max_misfit: float | None = 1.5, max_slope: float | None = 3.0,
                     min_points: int = 4):
    """The dot filters of :func:`detect_view_stack` on a detection (see ``max_slope`` and ``max_misfit``
    of :func:`calibration.pipeline.detect_view`).

    Returns ``(kept DotDetection, removed [(id, misfit)], vignetted [(id, slope)])``. A filter that
    would leave fewer than ``min_points`` dots is skipped."""
    if not isinstance(det, DotDetection):
        raise ValueError(f"det must be a calibration.detect.DotDetection, got {type(det).__name__}")
    vignetted = []
    if max_slope is not None and len(det) >= 4 and det.modulation_slope is not None:
        slope = det.modulation_slope
        finite = slope[np.isfinite(slope)]
        if finite.size:
            thr = max(MIN_VIGNETTING_SLOPE, max_slope * float(np.median(finite)))
            bad = ~(slope <= thr)
            if bad.any() and (~bad).sum() >= min_points:
                vignetted = [(int(i), float(m)) for i, m in zip(det.ids[bad], slope[bad])]
                det = _subset_detection(det, ~bad)
    removed = []
    if max_misfit is not None and len(det) >= 4:
        q = det.residual_rms * det.modulation
        if np.all(np.isfinite(q)) and np.median(q) > 0:
            misfit = q / np.median(q)
            bad = misfit > max_misfit
            if bad.any() and (~bad).sum() >= min_points:
                removed = [(int(i), float(m)) for i, m in zip(det.ids[bad], misfit[bad])]
                det = _subset_detection(det, ~bad)
    return det, removed, vignetted


def _subset_detection(det: DotDetection, keep) -> DotDetection:
    keep = np.asarray(keep)
    return DotDetection(image_points=det.image_points[keep], ids=det.ids[keep], object_points=det.object_points[keep],
                        residual_rms=det.residual_rms[keep], sigma_px=det.sigma_px[keep],
                        modulation=det.modulation[keep], n_pixels=det.n_pixels[keep], mirrored=det.mirrored,
                        blur_sigma=det.blur_sigma,
                        modulation_slope=None if det.modulation_slope is None else det.modulation_slope[keep])


def dense_grid_points(decoding: DenseDecoding, screen_points, *, radius: float | None = None,
                      min_pixels: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Image position of given screen points in a dense decoding (local quadratic inverse fit).

    For each screen point ``p`` (screen px), the decoded pixels whose screen coordinate lies within
    ``radius`` screen px of ``p`` are fitted with a quadratic map screen → image (6 coefficients per
    image coordinate, least squares); its value at ``p`` is the image point. A point is kept only
    when at least ``min_pixels`` pixels surround it on all sides (no extrapolation).

    Returns ``(image_points (M, 2) with NaN rows for points not found, found (M,) bool)``.
    ``radius`` defaults to 3 image pixels' worth of screen px (from the median magnification).
    """
    from scipy.spatial import cKDTree

    if not isinstance(decoding, DenseDecoding):
        raise ValueError(f"decoding must be a DenseDecoding, got {type(decoding).__name__}")
    P = np.asarray(screen_points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 2 or not np.all(np.isfinite(P)):
        raise ValueError(f"screen_points must be a finite (M, 2) array of screen px, got shape {P.shape}")
    ys, xs = np.nonzero(decoding.mask)
    out = np.full((len(P), 2), np.nan)
    if len(xs) < min_pixels:
        return out, np.zeros(len(P), dtype=bool)
    S = decoding.screen_xy[ys, xs]
    if radius is None:
        # screen px per image px from the decoded map's gradient
        gx = np.gradient(decoding.screen_xy[..., 0], axis=1)
        gy = np.gradient(decoding.screen_xy[..., 1], axis=0)
        scale = np.nanmedian(np.sqrt(np.abs(gx * gy)))
        radius = 3.0 * (scale if np.isfinite(scale) and scale > 0 else 1.0)
    tree = cKDTree(S)
    neigh = tree.query_ball_point(P, r=radius)
    for m, idx in enumerate(neigh):
        if len(idx) < min_pixels:
            continue
        idx = np.asarray(idx)
        d = (S[idx] - P[m]) / radius
        # surrounded: pixels on both sides along both screen axes
        if not (d[:, 0].min() < -0.3 and d[:, 0].max() > 0.3 and d[:, 1].min() < -0.3 and d[:, 1].max() > 0.3):
            continue
        A = np.stack([np.ones(len(d)), d[:, 0], d[:, 1], d[:, 0] ** 2, d[:, 0] * d[:, 1], d[:, 1] ** 2], axis=1)
        B = np.stack([xs[idx], ys[idx]], axis=1).astype(np.float64)
        coef, *_ = np.linalg.lstsq(A, B, rcond=None)
        out[m] = coef[0]
    found = np.all(np.isfinite(out), axis=1)
    return out, found


def _dense_screen_grid(target: PhaseTarget, spacing: float) -> np.ndarray:
    w, h = target.screen
    margin = spacing / 2
    xs = np.arange(margin, w - margin + 1e-9, spacing)
    ys = np.arange(margin, h - margin + 1e-9, spacing)
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def dense_view_points(decoding: DenseDecoding, spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Correspondences of one dense view on the screen grid ``(i, j) * spacing`` (screen px).

    Returns ``(image_points (M, 2) px, object_points (M, 3) mm, ids (M,))`` for the grid points that
    :func:`dense_grid_points` finds; ``ids = j * 100000 + i`` name the grid points (the same in every
    view)."""
    if not spacing > 0:
        raise ValueError(f"the dense grid spacing must be > 0 screen px, got {spacing!r}")
    S = decoding.screen_xy[decoding.mask]
    if len(S) == 0:
        return np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    lo = np.floor(S.min(axis=0) / spacing).astype(int)
    hi = np.ceil(S.max(axis=0) / spacing).astype(int)
    ii, jj = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
    P = np.stack([ii.ravel(), jj.ravel()], axis=1) * float(spacing)
    q, found = dense_grid_points(decoding, P)
    ids = (jj.ravel() * 100000 + ii.ravel())[found]
    X = np.concatenate([P[found] * decoding.pixel_pitch, np.zeros((int(found.sum()), 1))], axis=1)
    return q[found], X, ids.astype(np.int64)


@dataclass
class StereoView:
    """A target both cameras see: common dot ids, object points (N, 3) mm and image points (N, 2) in each camera;
    ``image_sizes`` ((w, h) left, (w, h) right) of the images it was detected in, when known."""

    ids: np.ndarray
    object_points: np.ndarray
    left_points: np.ndarray
    right_points: np.ndarray
    name: str = ""
    image_sizes: tuple | None = None

    def as_tuple(self):
        return self.object_points, self.left_points, self.right_points


def _board_corners(image, target: CheckerboardTarget):
    """Checkerboard corners in the target's id order, or None. OpenCV orders the corners of a board
    up to its symmetries; the order is fixed here so that the board's x axis points right in the
    image and the target appears right-handed (a direct view)."""
    found = detect_checkerboard(image, target)
    if found is None:
        return None
    pts, _ = found
    nx, ny = target.corners
    if len(pts) != nx * ny:
        return None
    grid = pts.reshape(ny, nx, 2)
    import cv2

    for _ in range(2):
        obj = target.points_px
        H, _ = cv2.findHomography(obj, grid.reshape(-1, 2), 0)
        if H is None:
            return None
        J = _homography_jacobian(H / H[2, 2], obj.mean(axis=0))
        if np.linalg.det(J) < 0:  # rows were read in the reverse direction
            grid = grid[::-1]
            continue
        if J[0, 0] < 0:  # rotated by 180 degrees
            grid = grid[::-1, ::-1]
        break
    return grid.reshape(-1, 2).astype(np.float64)


def _homography_jacobian(H, xy) -> np.ndarray:
    """d(image)/d(plane) (2, 2) of the homography ``H`` at plane point ``xy``."""
    q = H @ np.array([xy[0], xy[1], 1.0])
    return (H[:2, :2] * q[2] - np.outer(q[:2], H[2, :2])) / q[2] ** 2
