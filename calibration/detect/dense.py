"""Dense decoding of a phase target (:func:`decode_dense`): per-pixel screen coordinates from the
multi-frequency fringe sequence (temporal, hierarchical unwrapping), and their sampling into
point correspondences (:func:`dense_correspondences`).

Conventions: docs/conventions.md (pixel (0, 0) is the centre of the top-left pixel, points are
(x, y)); target frame: :mod:`calibration.targets`. Accuracy measured in docs/targets.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..targets import PhaseTarget
from .common import TWO_PI, _apply_h, _check_target, _estimate_blur, _homography, demodulate_images


@dataclass
class DenseDecoding:
    """Per-pixel screen coordinates decoded from the dense fringe sequence.

    Attributes
    ----------
    screen_xy : (H, W, 2) float64
        Screen position (x, y) in screen px seen by each camera pixel (NaN where invalid).
    mask : (H, W) bool
        Pixels decoded: enough modulation at the coarsest level, no saturation, on the screen,
        away from its blurred edge.
    modulation : (H, W) float64
        Modulation of the finest level used (mean of both axes), grey levels.
    pixel_pitch : float
        Screen pixel pitch (mm), for :attr:`target_xy`.
    mirrored : bool or None
        Orientation of the image-to-screen mapping (None when too few pixels are valid).
    period : (H, W, 2) float64
        Finest fringe period (screen px) each pixel was decoded with, per axis: under strong
        blur the finest fringes fade and a pixel keeps the last level it could resolve.
    """

    screen_xy: np.ndarray
    mask: np.ndarray
    modulation: np.ndarray
    pixel_pitch: float
    mirrored: bool | None = None
    period: np.ndarray | None = None

    @property
    def target_xy(self) -> np.ndarray:
        """(H, W, 2) float64 target-frame coordinates (mm) of each pixel (NaN where invalid)."""
        return self.screen_xy * self.pixel_pitch


def decode_dense(images, target: PhaseTarget, *, min_modulation: float = 3.0, min_contrast: float = 0.8,
                 max_step_error: float = 0.5 * math.pi, erode: int | None = None, blur_sigma: float | None = None,
                 device=None) -> DenseDecoding:
    """Decode the dense sequence (``target.dense_images()`` as recorded) into screen coordinates.

    Each level is demodulated; the coarsest level's phase is absolute (its period exceeds the
    screen), and each finer level is unwrapped with the scaled coarser one,
    ``Phi_f = phi_f + 2 pi round((Phi_c P_c / P_f - phi_f) / 2 pi)`` (temporal, hierarchical
    multi-frequency unwrapping). A pixel is valid when the coarsest level has
    ``modulation >= min_modulation`` and nothing saturates; it climbs to finer levels while they
    have enough modulation and the unwrapping step is consistent to ``max_step_error`` rad, and
    keeps the finest level it reached (``DenseDecoding.period``). A level counts as resolved
    where its modulation is at least ``min_contrast`` times the coarsest level's: blur attenuates
    fringes of image period ``T`` by ``exp(-2 pi^2 sigma^2 / T^2)`` and, where the fringes are
    also chirped by perspective, shifts their phase; fringes attenuated by less than 20 % keep
    the shift small (measured in docs/targets.md). ``erode`` (px) shrinks the
    valid mask away from the edge of the screen, where blur mixes the bezel into the phase;
    default ``3 sigma + 1`` with ``sigma`` the blur (``blur_sigma``, px, else measured from the
    modulation edge). Blurring a curved image-to-screen map ``s(x)`` moves the decoded phase by
    ``~ 1/2 sigma^2 lap(s) - 1/2 sigma^4 k^2 grad(s)^T Hess(s) grad(s)`` (Gaussian blur of a
    chirp, ``k = 2 pi / period``); this is subtracted using a homography fitted to the decoded
    map for the derivatives.

    Returns a :class:`DenseDecoding` with the screen position (px) seen by every valid pixel.
    """
    _check_target(target)
    if not 0 <= min_contrast < 1:
        raise ValueError(f"min_contrast must be in [0, 1), got {min_contrast!r}")
    n = len(images) if isinstance(images, (list, tuple)) else (np.shape(images)[0] if np.ndim(images) == 3 else None)
    if n != target.n_dense_images:
        raise ValueError(
            f"the dense sequence of this target has {target.n_dense_images} images "
            f"({len(target.dense_levels)} levels x {target.steps} steps), got {n if n is not None else np.shape(images)}"
        )
    coords = []
    mask = None
    finest = []
    fine_mod = []
    for axis in (0, 1):
        levels = [lv for lv in target.dense_levels if lv.axis == axis]
        unwrapped = period = mod_used = None
        active = None
        for lv in reversed(levels):  # coarse to fine
            stack = images[lv.first: lv.first + target.steps]
            ph, mod, _, ok = demodulate_images(stack, min_modulation=min_modulation, device=device)
            if unwrapped is None:  # the coarsest level is absolute
                unwrapped, period, mod_used = ph, np.full(ph.shape, lv.period), mod
                base_mod = mod
                if axis == 0:
                    coarse_mod = mod
                active = ok.copy()
                mask = ok if mask is None else (mask & ok)
                continue
            scaled = unwrapped * period / lv.period
            kk = np.rint((scaled - ph) / TWO_PI)
            err = scaled - ph - TWO_PI * kk
            # a pixel moves on to this finer level while the fringes still reach it
            # (enough modulation) and the unwrapping is consistent; otherwise it keeps the
            # coarser (less precise) estimate and stops refining
            step_ok = active & ok & (np.abs(err) <= max_step_error) & (mod >= min_contrast * base_mod)
            unwrapped = np.where(step_ok, ph + TWO_PI * kk, unwrapped)
            period = np.where(step_ok, lv.period, period)
            mod_used = np.where(step_ok, mod, mod_used)
            active = step_ok
        coords.append(target.centre[axis] + unwrapped * period / TWO_PI)
        finest.append(period)
        fine_mod.append(mod_used)
    screen = np.stack(coords, axis=-1)
    w, h = target.screen
    mask &= (screen[..., 0] >= -0.5) & (screen[..., 0] <= w - 0.5) & (screen[..., 1] >= -0.5) & (screen[..., 1] <= h - 0.5)
    sigma = _estimate_blur(coarse_mod, mask) if blur_sigma is None else float(blur_sigma)
    if sigma > 0.5 and mask.sum() > 100:
        screen = _correct_dense_blur(screen, mask, np.stack(finest, axis=-1), sigma)
    if erode is None:
        # blur mixes the dark bezel into the phase near the edge of the screen: stay 3 sigma away
        erode = int(math.ceil(3.0 * sigma)) + 1
    elif not isinstance(erode, (int, np.integer)) or erode < 0:
        raise ValueError(f"erode must be a number of pixels >= 0 or None (automatic), got {erode!r}")
    if erode > 0:
        from scipy import ndimage

        mask = ndimage.binary_erosion(mask, iterations=int(erode), border_value=0)
    screen = np.where(mask[..., None], screen, np.nan)
    mirrored = None
    if mask.sum() > 100:
        gxx = np.gradient(screen[..., 0], axis=1)
        gxy = np.gradient(screen[..., 0], axis=0)
        gyx = np.gradient(screen[..., 1], axis=1)
        gyy = np.gradient(screen[..., 1], axis=0)
        det = gxx * gyy - gxy * gyx
        det = det[np.isfinite(det)]
        if det.size:
            mirrored = bool(np.median(det) < 0)
    period = np.stack(finest, axis=-1)
    period[~mask] = np.nan
    return DenseDecoding(screen, mask, 0.5 * (fine_mod[0] + fine_mod[1]), target.pixel_pitch, mirrored, period)


def _correct_dense_blur(screen, mask, period, sigma):
    """Subtract the blur-induced shift of decoded screen coordinates (see :func:`decode_dense`)."""
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    pick = np.linspace(0, len(xs) - 1, min(len(xs), 4000)).astype(int)
    img = np.stack([xs[pick], ys[pick]], axis=1).astype(np.float64)
    H = _homography(img, screen[ys[pick], xs[pick]])
    out = screen.copy()
    pts = np.stack([xs, ys], axis=1).astype(np.float64)
    e = 1.0  # px, finite-difference step on the (smooth) homography
    f0 = _apply_h(H, pts)
    fxp, fxm = _apply_h(H, pts + (e, 0)), _apply_h(H, pts - (e, 0))
    fyp, fym = _apply_h(H, pts + (0, e)), _apply_h(H, pts - (0, e))
    fpp, fmm = _apply_h(H, pts + (e, e)), _apply_h(H, pts - (e, e))
    fpm, fmp = _apply_h(H, pts + (e, -e)), _apply_h(H, pts + (-e, e))
    gx, gy = (fxp - fxm) / (2 * e), (fyp - fym) / (2 * e)
    hxx, hyy = (fxp - 2 * f0 + fxm) / e ** 2, (fyp - 2 * f0 + fym) / e ** 2
    hxy = (fpp - fpm - fmp + fmm) / (4 * e ** 2)
    for a in (0, 1):
        k = 2 * np.pi / period[ys, xs, a]
        quad = gx[:, a] ** 2 * hxx[:, a] + 2 * gx[:, a] * gy[:, a] * hxy[:, a] + gy[:, a] ** 2 * hyy[:, a]
        shift = 0.5 * sigma ** 2 * (hxx[:, a] + hyy[:, a]) - 0.5 * sigma ** 4 * k ** 2 * quad
        out[ys, xs, a] = screen[ys, xs, a] - shift
    return out


def dense_correspondences(decoding: DenseDecoding, step: int = 8, *, max_points: int | None = None):
    """Sample a :class:`DenseDecoding` on a regular pixel grid.

    Returns ``(image_points (N, 2) px, object_points (N, 3) mm)`` for the valid pixels of every
    ``step``-th row and column (optionally thinned to ``max_points``)."""
    if not isinstance(decoding, DenseDecoding):
        raise ValueError(f"decoding must be a DenseDecoding from decode_dense, got {type(decoding).__name__}")
    if not isinstance(step, (int, np.integer)) or step < 1:
        raise ValueError(f"step must be an integer >= 1, got {step!r}")
    h, w = decoding.mask.shape
    ys, xs = np.mgrid[0:h:step, 0:w:step]
    ok = decoding.mask[ys, xs]
    img = np.stack([xs[ok], ys[ok]], axis=1).astype(np.float64)
    obj = decoding.target_xy[ys[ok], xs[ok]]
    obj = np.concatenate([obj, np.zeros((len(obj), 1))], axis=1)
    if max_points is not None and len(img) > max_points:
        pick = np.linspace(0, len(img) - 1, int(max_points)).astype(int)
        img, obj = img[pick], obj[pick]
    return img, obj
