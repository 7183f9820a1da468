"""Feature extraction for calibration: phase-target dot centres, dense phase decoding, and the
conventional checkerboard / circle-grid detectors of OpenCV.

Dot centres (:func:`detect_dots`). The recorded phase-shifted images are demodulated
(:func:`kernels.phase.demodulate`) into a wrapped phase ``phi`` and a modulation ``M``. Defocus
attenuates the fringes but leaves the phase of slowly curved fringes nearly in place, so the phase
map stays sharp where the intensity images are a blur (the paper behind Specula, Optics Express
27(6), 9040, 2019, doi:10.1364/OE.27.009040; Bell, Xu, Zhang, "Method for out-of-focus camera
calibration", Applied Optics 55(9), 2016, doi:10.1364/AO.55.002346).

1. Candidates: the phase gradient of a dot points away from its centre; the divergence of the
   unit gradient field peaks at dot centres (and is negative on cell borders).
2. Lattice: candidates are linked to their grid neighbours (4-neighbour growth with
   extrapolated steps, so perspective is followed), giving each a lattice index.
3. Centre (pass 1): around each dot the projectively mapped radial phase model
   ``phi(x) = 2 pi |s(x)| / period + phi0``, ``s = H^-1 x`` (``H`` a local homography from the
   dot's cell, centred on the dot, to the image) is fitted to the wrapped phase by Gauss-Newton on
   the wrapped residual, weighted by the modulation, on a smooth window of the cell that leaves out
   the cone tip and the cell border. The image point is ``H (0, 0)``: the image of the dot centre
   itself, free of the eccentricity bias of ellipse or intensity centroids (Heikkilä, "Geometric
   camera calibration using circular control points", IEEE TPAMI 22(10), 2000,
   doi:10.1109/34.879788).
4. Ids: each dot's fitted ``phi0`` reads its code symbol; the lattice is matched to the target's
   code over all 8 rotations/reflections and translations. A view whose target-to-image mapping
   reverses orientation (a mirror view) is flagged ``mirrored``; ids follow the reflected target,
   so ``target.object_points[ids]`` stay the right correspondences.
5. Defocus (pass 2): a Gaussian blur bends the phase of curved fringes near the cone tip and
   where cells meet, and moves the pass-1 centres (by up to ~1 px at sigma = 10 px). The blur of
   each dot is measured by matching a simulated modulation map to the measured one, and the bias
   is measured by running the identical pass-1 fit (same pixels, same weights) on a simulated view
   of the dot: the target's exact fringe field (all cells, codes, the edge of the fringe area,
   pixel-area integration at the code jumps) mapped through the current homography and blurred.
   The bias is subtracted, three rounds (the homography and blur are refined in between).

Conventions: docs/conventions.md (pixel (0, 0) is the centre of the top-left pixel, points are
(x, y)); target frame: :mod:`calibration.targets`. Accuracy measured in docs/targets.md.
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .targets import CheckerboardTarget, CircleGridTarget, PhaseTarget

__all__ = [
    "DotDetection",
    "DenseDecoding",
    "DetectionError",
    "demodulate_images",
    "detect_dots",
    "detect_dots_in_images",
    "decode_dense",
    "dense_correspondences",
    "detect_checkerboard",
    "detect_circle_grid",
]

TWO_PI = 2.0 * math.pi


class DetectionError(RuntimeError):
    """The target could not be found or identified in a view (the message says why)."""


# ------------------------------------------------------------------------------------------------
# results
# ------------------------------------------------------------------------------------------------
@dataclass
class DotDetection:
    """Dot centres found in one view of a :class:`~calibration.targets.PhaseTarget`.

    Attributes
    ----------
    image_points : (N, 2) float64
        Sub-pixel image position (x, y) of each found dot centre (px).
    ids : (N,) int64
        Target dot id of each point (``target.object_points[ids]`` are the matching object points).
    object_points : (N, 3) float64
        Target-frame dot centres (mm) matching ``image_points``.
    residual_rms : (N,) float64
        RMS of the wrapped-phase residual of each dot's fit (rad).
    sigma_px : (N,) float64
        Standard deviation of each centre from the fit covariance (px, noise only).
    modulation : (N,) float64
        Median fringe modulation around each dot (grey levels).
    modulation_slope : (N,) float64
        Relative change of the modulation across each dot's fit window (plane fit, centre to
        window edge). Near 0 for a fully lit dot; large where part of the window is vignetted
        (e.g. by a mirror's edge), which biases the centre (see :func:`detect_dots`).
    n_pixels : (N,) int64
        Pixels used in each dot's fit.
    mirrored : bool
        True when the target appears left-handed (seen through a mirror).
    blur_sigma : float
        Gaussian blur estimated from the fringe modulation (px); 0 when sharp.
    """

    image_points: np.ndarray
    ids: np.ndarray
    object_points: np.ndarray
    residual_rms: np.ndarray
    sigma_px: np.ndarray
    modulation: np.ndarray
    n_pixels: np.ndarray
    mirrored: bool
    blur_sigma: float = 0.0
    modulation_slope: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def quality(self) -> np.ndarray:
        """Per-point quality figure: the centre standard deviation (px) from the fit."""
        return self.sigma_px


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


# ------------------------------------------------------------------------------------------------
# input handling
# ------------------------------------------------------------------------------------------------
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


# ------------------------------------------------------------------------------------------------
# 1. candidates
# ------------------------------------------------------------------------------------------------
def _phase_gradient(phase, modulation, mask):
    """Wrapped central-difference phase gradient (rad/px) and a weight map."""
    z = modulation * np.exp(1j * phase) * mask
    gx = np.zeros(phase.shape)
    gy = np.zeros(phase.shape)
    gx[:, 1:-1] = np.angle(z[:, 2:] * np.conj(z[:, :-2])) / 2
    gy[1:-1, :] = np.angle(z[2:, :] * np.conj(z[:-2, :])) / 2
    ok = mask.copy()
    ok[:, 1:-1] &= mask[:, 2:] & mask[:, :-2]
    ok[1:-1, :] &= mask[2:, :] & mask[:-2, :]
    ok[:, [0, -1]] = False
    ok[[0, -1], :] = False
    return gx, gy, ok


def _find_candidates(phase, modulation, mask, period_img: float):
    """Dot-centre candidates (K, 2) from the divergence of the unit phase-gradient field."""
    from scipy import ndimage

    gx, gy, ok = _phase_gradient(phase, modulation, mask)
    norm = np.hypot(gx, gy)
    ok &= norm > 1e-6
    w = np.where(ok, np.minimum(modulation / (np.median(modulation[ok]) + 1e-9), 1.0), 0.0)
    nx = np.where(ok, gx / np.maximum(norm, 1e-12), 0.0) * w
    ny = np.where(ok, gy / np.maximum(norm, 1e-12), 0.0) * w
    div = np.zeros(phase.shape)
    div[:, 1:-1] += (nx[:, 2:] - nx[:, :-2]) / 2
    div[1:-1, :] += (ny[2:, :] - ny[:-2, :]) / 2
    s = max(1.0, period_img / 12)
    div = ndimage.gaussian_filter(div, s)
    cover = ndimage.gaussian_filter(w, s)
    size = int(max(3, round(period_img / 3))) | 1
    peaks = (div == ndimage.maximum_filter(div, size=size)) & (cover > 0.5)
    # a dot's divergence integrates to ~2 pi over a disk: peak height ~ 1 / s
    peaks &= div > 0.15 / s
    ys, xs = np.nonzero(peaks)
    strength = div[ys, xs]
    order = np.argsort(-strength)
    return np.stack([xs[order], ys[order]], axis=1).astype(np.float64), strength[order]


# ------------------------------------------------------------------------------------------------
# 2. lattice
# ------------------------------------------------------------------------------------------------
_STEPS = ((1, 0), (-1, 0), (0, 1), (0, -1))


def _grow_lattice(points: np.ndarray, max_points: int):
    """Assign integer lattice indices to candidate points by 4-neighbour growth.

    Growth starts from each of the (up to 12) candidates nearest the middle that has two
    independent neighbour directions, and the largest labelling wins: a spurious candidate (a
    phase defect near a mirror's edge, a glint) as the seed, or as the seed's nearest neighbour,
    would otherwise set a wrong basis and link only a line of dots.

    Returns (labels (K, 2) int, labelled bool mask)."""
    from scipy.spatial import cKDTree

    k = len(points)
    if k < 4:
        raise DetectionError(f"found {k} dot candidates; at least 4 are needed to set up the grid")
    tree = cKDTree(points)
    centre = np.median(points, axis=0)
    seed_order = np.argsort(np.linalg.norm(points - centre, axis=1))
    best = None
    for seed in seed_order[: min(k, 12)]:
        d, nb = tree.query(points[seed], k=min(k, 9))
        vecs = points[nb[1:]] - points[seed]
        if len(vecs) < 2:
            continue
        e1 = vecs[0]
        # second axis: the nearest vector far from parallel to e1
        cosang = np.abs(vecs @ e1) / (np.linalg.norm(vecs, axis=1) * np.linalg.norm(e1) + 1e-12)
        cand = np.flatnonzero(cosang < 0.5)
        if cand.size == 0:
            continue
        labels, done = _grow_from(points, tree, int(seed), e1, vecs[cand[0]], max_points)
        span = labels[done].max(axis=0) - labels[done].min(axis=0)
        score = (int(np.all(span > 0)), int(done.sum()))   # a 2-D grid beats a line, then more dots
        if best is None or score > best[0]:
            best = (score, labels, done)
        if score[1] >= 0.9 * k:   # (nearly) every candidate linked: no better labelling exists
            break
    if best is None:
        raise DetectionError("the dot candidates do not form a 2-D grid (no two independent neighbour directions)")
    return best[1], best[2]


def _grow_from(points, tree, seed: int, e1, e2, max_points: int):
    """Breadth-first growth of the lattice labelling from ``seed`` with basis (e1, e2)."""
    k = len(points)
    labels = np.zeros((k, 2), dtype=np.int64)
    done = np.zeros(k, dtype=bool)
    where: dict[tuple[int, int], int] = {(0, 0): seed}
    done[seed] = True
    queue = [(0, 0)]
    basis = {(1, 0): e1, (-1, 0): -e1, (0, 1): e2, (0, -1): -e2}
    while queue:
        ij = queue.pop(0)
        p = points[where[ij]]
        for step in _STEPS:
            nij = (ij[0] + step[0], ij[1] + step[1])
            if nij in where:
                continue
            back = (ij[0] - step[0], ij[1] - step[1])
            if back in where:
                v = p - points[where[back]]
            else:
                # the step along the same axis seen from a labelled side neighbour, else the seed basis
                v = basis[step]
                for side in ((step[1], step[0]), (-step[1], -step[0])):
                    a = (ij[0] + side[0], ij[1] + side[1])
                    b = (a[0] + step[0], a[1] + step[1])
                    if a in where and b in where:
                        v = points[where[b]] - points[where[a]]
                        break
            pred = p + v
            d, nb = tree.query(pred)
            if d < 0.3 * np.linalg.norm(v) and not done[nb]:
                where[nij] = int(nb)
                done[nb] = True
                labels[nb] = nij
                queue.append(nij)
        if len(where) > max_points:
            break
    return labels, done


# ------------------------------------------------------------------------------------------------
# 3. per-dot fit of the projective radial phase model
# ------------------------------------------------------------------------------------------------
def _homography(src, dst):
    import cv2

    H, _ = cv2.findHomography(np.asarray(src, np.float64), np.asarray(dst, np.float64), 0)
    if H is None:
        raise DetectionError("could not estimate a local homography (degenerate neighbour layout)")
    return H / H[2, 2]


def _apply_h(H, xy):
    q = np.c_[xy, np.ones(len(xy))] @ H.T
    return q[:, :2] / q[:, 2:3]


@dataclass
class _DotFit:
    centre: np.ndarray
    A: np.ndarray              # image -> cell-centred screen px (3x3)
    phi0: float
    rms: float
    sigma: float
    n: int
    modulation: float
    coverage: float = 1.0      # share of the window's weight on usable pixels
    A_window: np.ndarray | None = None
    modulation_slope: float = 0.0  # relative modulation change centre -> window edge (vignetting)


def _smoothstep(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _fit_dot(phase, modulation, mask, A0, period, pitch, rho_in, border, iterations=30, A_window=None):
    """:func:`_fit_dot_core`, or None when its geometry is numerically singular (e.g. 24 x 12 dots a few
    pixels apart in a small image): one dot without a fit, not a failed detection."""
    try:
        return _fit_dot_core(phase, modulation, mask, A0, period, pitch, rho_in, border, iterations, A_window)
    except np.linalg.LinAlgError:
        return None


def _fit_dot_core(phase, modulation, mask, A0, period, pitch, rho_in, border, iterations=30, A_window=None):
    """Pass 1: fit ``phi = 2 pi |s| / period + phi0``, ``s = dehom(A x)``, around one dot.

    ``A0`` (start) maps image (x, y, 1) to cell-centred screen px. Each pixel's residual is
    weighted by its modulation (phase noise ~ 1 / modulation) times a smooth window of its cell
    position under ``A_window`` (default ``A0``; fixed during the fit) that fades out pixels
    nearer than ``rho_in`` to the dot centre or than ``border`` to the cell edge (screen px, taper
    0.05 pitch). Gauss-Newton on the wrapped residual. Returns a :class:`_DotFit` or None."""
    h, w = phase.shape
    half = pitch / 2 - border
    taper = 0.05 * pitch
    A_window = A0 if A_window is None else A_window
    Ainv = np.linalg.inv(A_window)
    corners = _apply_h(Ainv, np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * (pitch / 2))
    x0, y0 = np.floor(corners.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(corners.max(axis=0)).astype(int) + 2
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w - 1), min(y1, h - 1)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return None
    ys, xs = np.mgrid[y0:y1 + 1, x0:x1 + 1]
    xs, ys = xs.ravel(), ys.ravel()
    X = np.stack([xs, ys, np.ones(xs.size)], axis=1).astype(np.float64)
    sel = mask[ys, xs]
    k = TWO_PI / period
    A = A0 / A0[2, 2]

    def window(s):
        rho = np.hypot(s[:, 0], s[:, 1])
        return (_smoothstep((rho - rho_in) / taper) * _smoothstep((half - np.abs(s[:, 0])) / taper)
                * _smoothstep((half - np.abs(s[:, 1])) / taper)), rho

    win, _ = window(_apply_h(A_window, X[:, :2]))
    # share of the window that lands on usable pixels (inside the image and the mask); the
    # window's full weight is its area in the cell, mapped into the image by the local Jacobian
    full_area = float(np.sum(window(np.stack(np.meshgrid(np.linspace(-pitch / 2, pitch / 2, 61),
                                                           np.linspace(-pitch / 2, pitch / 2, 61)), -1).reshape(-1, 2))[0]))
    full_area *= (pitch / 60) ** 2 * abs(np.linalg.det(_jacobian_h(np.linalg.inv(A_window), np.zeros(2))))
    use = (win > 0) & sel
    coverage = float(np.sum(win[use])) / max(full_area, 1e-12)
    if use.sum() < 30:
        return None
    X, phi, mod, win = X[use], phase[ys[use], xs[use]], modulation[ys[use], xs[use]], win[use]
    ww = mod * win
    s0 = _apply_h(A, X[:, :2])
    rho0 = np.hypot(s0[:, 0], s0[:, 1])
    phi0 = float(np.angle(np.sum(ww * np.exp(1j * (phi - k * rho0)))))
    Hm = None
    centre = _apply_h(np.linalg.inv(A), np.zeros((1, 2)))[0]
    for it in range(iterations):
        uu = X @ A.T
        ss = uu[:, :2] / uu[:, 2:3]
        rr = np.hypot(ss[:, 0], ss[:, 1])
        res = _wrap(phi - (k * rr + phi0))
        q2 = uu[:, 2]
        sx, sy = ss[:, 0], ss[:, 1]
        dpx = k * sx / np.maximum(rr, 1e-9)   # d phi / d s
        dpy = k * sy / np.maximum(rr, 1e-9)
        g0, g1 = dpx / q2, dpy / q2
        g2 = -(dpx * sx + dpy * sy) / q2
        u0, u1, u2 = uu[:, 0], uu[:, 1], uu[:, 2]
        # A <- (I + D) A, D = [[a, b, c], [b, e, f], [g, h, 0]] (rotation gauge removed)
        J = np.stack([g0 * u0, g0 * u1 + g1 * u0, g0 * u2, g1 * u1, g1 * u2, g2 * u0, g2 * u1,
                      np.ones_like(u0)], axis=1)
        Jw = J * ww[:, None]
        Hm = Jw.T @ Jw
        try:
            delta = np.linalg.solve(Hm + 1e-9 * np.diag(np.diag(Hm)), Jw.T @ (res * ww))
        except np.linalg.LinAlgError:
            return None
        a, b, c, e, f, g, hh, dphi = delta
        D = np.array([[a, b, c], [b, e, f], [g, hh, 0.0]])
        A = (np.eye(3) + D) @ A
        A = A / A[2, 2]
        phi0 = float(_wrap(phi0 + dphi))
        new_centre = _apply_h(np.linalg.inv(A), np.zeros((1, 2)))[0]
        moved = float(np.hypot(*(new_centre - centre)))
        centre = new_centre
        if moved < 1e-7 and it > 1:
            break
    u = X @ A.T
    s = u[:, :2] / u[:, 2:3]
    res = _wrap(phi - (k * np.hypot(s[:, 0], s[:, 1]) + phi0))
    # centre covariance from the Gauss-Newton normal matrix (phase noise from the residual)
    sigma = float("nan")
    try:
        s2 = float(np.sum((res * ww) ** 2)) / max(len(res) - 8, 1)
        cov = s2 * np.linalg.inv(Hm)
        Jc = np.zeros((2, 8))
        for p in range(7):
            dp = np.zeros(7)
            dp[p] = 1e-7
            a, b, c, e, f, g, hh = dp
            Ap = (np.eye(3) + np.array([[a, b, c], [b, e, f], [g, hh, 0.0]])) @ A
            Jc[:, p] = (_apply_h(np.linalg.inv(Ap), np.zeros((1, 2)))[0] - centre) / 1e-7
        sigma = float(np.sqrt(max(np.trace(Jc @ cov @ Jc.T), 0.0) / 2))
    except np.linalg.LinAlgError:
        pass
    rms = float(np.sqrt(np.sum(win * res ** 2) / max(np.sum(win), 1e-12)))
    return _DotFit(centre, A, phi0, rms, sigma, len(res), float(np.median(mod)), coverage, A_window,
                   _modulation_slope(s, mod, win, half))


def _modulation_slope(s, mod, win, half):
    """Relative change of the modulation from the dot centre to the edge of its fit window.

    A plane ``mod = a + b sx / half + c sy / half`` (cell coordinates ``s``, screen px) is fitted
    to the window's modulation, weighted by the window; returns ``hypot(b, c) / a``. The dips of
    the modulation at the dot centre and at the cell borders are symmetric and do not tilt the
    plane; a lopsided fall-off does: part of the window lies where a mirror's (or any aperture
    stop's) edge cuts the lens pupil, so those pixels see a truncated, off-centre defocus blur and
    their phase is shifted along the fringe gradient, which biases the dot's centre."""
    X = np.stack([np.ones(len(s)), s[:, 0] / half, s[:, 1] / half], axis=1)
    sw = np.sqrt(np.maximum(win, 0.0))
    try:
        coef, *_ = np.linalg.lstsq(X * sw[:, None], mod * sw, rcond=None)
    except np.linalg.LinAlgError:
        return float("inf")
    return float(np.hypot(coef[1], coef[2]) / coef[0]) if coef[0] > 0 else float("inf")


def _edge_cdf(d, a, b):
    """Fraction of a unit pixel on the inner side of a straight edge, and its derivative.

    ``d`` (px) is the signed distance of the pixel centre from the edge (positive inside), the
    edge normal is ``(a, b) = (|n_x|, |n_y|)``. The projection of the pixel area on the normal is
    the sum of two uniform variables of widths ``a`` and ``b`` (variance ``(a^2 + b^2) / 12``); a
    Gaussian of that variance stands in for it, so that the fraction is smooth in ``d`` (the exact
    piecewise-quadratic profile has kinks that stall the optimiser when a whole row of pixel
    centres crosses them at once)."""
    from scipy.special import ndtr

    sig = np.sqrt((a * a + b * b) / 12.0)
    t = d / sig
    return ndtr(t), np.exp(-0.5 * t * t) / (sig * math.sqrt(2 * math.pi))


def _pixel_field(target: PhaseTarget, Ac, u, c_screen) -> np.ndarray:
    """The complex fringe field ``exp(i Phi)`` a camera pixel integrates, and its derivatives.

    ``u = Ac (x, y, 1)`` per pixel (``Ac``: image -> screen px relative to ``c_screen``). Near a
    cell border the pixel blends the fields of the cells on either side (each cell's radial
    field ``exp(i (k rho_c + offset_c))`` extended across the border) with the area fractions of
    the pixel footprint on each side; the edge of the fringe area is area-weighted the same way.
    Returns the complex field ``E`` (N,) (amplitude 1 where the screen shows fringes)."""
    q2 = u[:, 2]
    sc = u[:, :2] / q2[:, None]
    sa = sc + c_screen
    k = TWO_PI / target.period
    nx, ny = target.grid
    first = target._first
    pitch = target.pitch
    i, j = target.cell_of(sa[:, 0], sa[:, 1])
    rel = sa - (first + np.stack([i, j], axis=1) * pitch)
    # image-space gradients of s_x and s_y: the normals of the screen's vertical/horizontal lines
    gxx = (Ac[0, 0] - sc[:, 0] * Ac[2, 0]) / q2
    gxy = (Ac[0, 1] - sc[:, 0] * Ac[2, 1]) / q2
    gyx = (Ac[1, 0] - sc[:, 1] * Ac[2, 0]) / q2
    gyy = (Ac[1, 1] - sc[:, 1] * Ac[2, 1]) / q2
    nsx = np.maximum(np.hypot(gxx, gxy), 1e-12)
    nsy = np.maximum(np.hypot(gyx, gyy), 1e-12)
    ax_, bx_ = np.abs(gxx) / nsx, np.abs(gxy) / nsx
    ay_, by_ = np.abs(gyx) / nsy, np.abs(gyy) / nsy
    # nearest cell border along x and y, and the neighbour across it
    sgx = np.where(rel[:, 0] >= 0, 1, -1)
    sgy = np.where(rel[:, 1] >= 0, 1, -1)
    i2 = np.clip(i + sgx, 0, nx - 1)
    j2 = np.clip(j + sgy, 0, ny - 1)
    Fx, px_ = _edge_cdf((pitch / 2 - np.abs(rel[:, 0])) * nsx, ax_, bx_)
    Fy, py_ = _edge_cdf((pitch / 2 - np.abs(rel[:, 1])) * nsy, ay_, by_)
    hasx = i2 != i
    hasy = j2 != j
    fx = np.where(hasx, 1 - Fx, 0.0)  # area fraction across the border
    fy = np.where(hasy, 1 - Fy, 0.0)
    off = target.code_offsets
    cells = ((i, j), (i2, j), (i, j2), (i2, j2))
    weights = ((1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy)
    # a pixel straddling a cone tip integrates a rounded cone: sqrt(rho^2 + eps^2) with eps the
    # mean distance of a unit pixel's points from its centre (0.38 px), in screen px
    eps2 = (0.38 ** 2) / (nsx * nsy)
    fields, rels = [], []
    for ci, cj in cells:
        r_c = sa - (first + np.stack([ci, cj], axis=1) * pitch)
        rho_c = np.sqrt(r_c[:, 0] ** 2 + r_c[:, 1] ** 2 + eps2)
        fields.append(np.exp(1j * (k * rho_c + off[cj, ci])))
        rels.append((r_c, rho_c))
    C = sum(w * e for w, e in zip(weights, fields))
    # edge of the fringe area
    lo, hi = target._lit_lo, target._lit_hi
    Flx, plx = _edge_cdf((sa[:, 0] - lo[0]) * nsx, ax_, bx_)
    Fhx, phx = _edge_cdf((hi[0] - sa[:, 0]) * nsx, ax_, bx_)
    Fly, ply = _edge_cdf((sa[:, 1] - lo[1]) * nsy, ay_, by_)
    Fhy, phy = _edge_cdf((hi[1] - sa[:, 1]) * nsy, ay_, by_)
    L = Flx * Fhx * Fly * Fhy
    E = L * C
    return E


class _DotSimulation:
    """The exact view of one dot, rendered through a local homography, for any blur.

    The target's fringe field around the dot (all cells, codes, the edge of the fringe area) is
    sampled on the image pixels of the dot's cell plus a margin through ``A_abs`` (image ->
    screen px); :meth:`blurred` applies a Gaussian blur of ``sigma`` px (FFT)."""

    def __init__(self, target: PhaseTarget, shape, A_abs, c_screen, sigma_max: float):
        from scipy import fft as sfft

        h, w = shape
        Ainv = np.linalg.inv(A_abs)
        half = target.pitch / 2
        corners = _apply_h(Ainv, c_screen + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half)
        x0, y0 = np.floor(corners.min(axis=0)).astype(int) - 2
        x1, y1 = np.ceil(corners.max(axis=0)).astype(int) + 2
        self.x0, self.y0 = max(x0, 0), max(y0, 0)
        self.x1, self.y1 = min(x1, w - 1), min(y1, h - 1)
        self.ok = self.x1 - self.x0 >= 4 and self.y1 - self.y0 >= 4
        if not self.ok:
            return
        self.pad = pad = int(math.ceil(4.0 * max(sigma_max, 1.0))) + 2
        nyb = sfft.next_fast_len(self.y1 - self.y0 + 1 + 2 * pad)
        nxb = sfft.next_fast_len(self.x1 - self.x0 + 1 + 2 * pad)
        gy, gx = np.mgrid[self.y0 - pad:self.y0 - pad + nyb, self.x0 - pad:self.x0 - pad + nxb].astype(np.float64)
        Xb = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], axis=1)
        Ac = np.array([[1, 0, -c_screen[0]], [0, 1, -c_screen[1]], [0, 0, 1.0]]) @ A_abs
        E = _pixel_field(target, Ac, Xb @ Ac.T, c_screen)
        self.spec = sfft.fft2(E.reshape(nyb, nxb), workers=-1)
        self.f2 = sfft.fftfreq(nyb)[:, None] ** 2 + sfft.fftfreq(nxb)[None, :] ** 2
        self.true_centre = _apply_h(Ainv, np.asarray(c_screen, dtype=np.float64)[None])[0]

    def blurred(self, sigma: float) -> np.ndarray:
        from scipy import fft as sfft

        Z = sfft.ifft2(self.spec * np.exp(-2 * np.pi ** 2 * sigma ** 2 * self.f2), workers=-1)
        p = self.pad
        return Z[p:p + self.y1 - self.y0 + 1, p:p + self.x1 - self.x0 + 1]

    def window(self, arr):
        return arr[self.y0:self.y1 + 1, self.x0:self.x1 + 1]


def _fit_blur(sim: _DotSimulation, modulation, mask, sigma0: float) -> float:
    """Blur (px) whose simulated modulation best matches the measured one around the dot
    (least squares with a free gain; golden-section search on log sigma within sigma0 / 1.6 ..
    1.6 sigma0, to 1 %)."""
    from scipy import fft as sfft

    ok = sim.window(mask)
    if ok.sum() < 50:
        return sigma0
    p = sim.pad
    rows, cols = np.nonzero(ok)
    m = sim.window(modulation)[rows, cols]
    rows, cols = rows + p, cols + p

    def cost(ls):
        Z = sfft.ifft2(sim.spec * np.exp(-2 * np.pi ** 2 * math.exp(2 * ls) * sim.f2), workers=-1)
        a = np.abs(Z[rows, cols])
        g = float(a @ m) / max(float(a @ a), 1e-12)
        r = m - g * a
        return float(r @ r)

    lo, hi = math.log(max(sigma0, 0.5) / 1.6), math.log(max(sigma0, 0.5) * 1.6)
    gr = (math.sqrt(5) - 1) / 2
    c, d = hi - gr * (hi - lo), lo + gr * (hi - lo)
    fc, fd = cost(c), cost(d)
    for _ in range(9):
        if fc < fd:
            hi, d, fd = d, c, fc
            c = hi - gr * (hi - lo)
            fc = cost(c)
        else:
            lo, c, fc = c, d, fd
            d = lo + gr * (hi - lo)
            fd = cost(d)
    return math.exp((lo + hi) / 2)


def _smooth_blur(centres, sigmas, sel):
    """Robust plane ``sigma = a + b x + c y`` through per-dot blur estimates (median if < 6)."""
    out = np.array(sigmas, dtype=np.float64)
    if len(sel) < 6:
        out[sel] = np.median(out[sel])
        return out
    X = np.c_[np.ones(len(sel)), centres[sel]]
    y = out[sel]
    w = np.ones(len(sel))
    for _ in range(5):  # iteratively reweighted (Huber-like) least squares
        coef = np.linalg.lstsq(X * w[:, None], y * w, rcond=None)[0]
        r = y - X @ coef
        scale = 1.4826 * np.median(np.abs(r)) + 1e-6
        w = 1.0 / np.maximum(1.0, np.abs(r) / (1.5 * scale))
    out[sel] = np.c_[np.ones(len(sel)), centres[sel]] @ coef
    return np.maximum(out, 0.0)


def _simulated_fit_bias(sim: _DotSimulation, mask, sigma: float, A_start, A_window, period, pitch, rho_in, border):
    """(fitted - true) centre (px) of the pass-1 fit run on the simulated view (same pixel
    window as on the data), or None."""
    Zs = sim.blurred(sigma)
    shift = np.array([[1, 0, sim.x0], [0, 1, sim.y0], [0, 0, 1.0]])
    fit = _fit_dot(np.angle(Zs), np.abs(Zs), sim.window(mask), A_start @ shift, period, pitch, rho_in, border,
                   A_window=A_window @ shift)
    if fit is None:
        return None
    return fit.centre + (sim.x0, sim.y0) - sim.true_centre


# ------------------------------------------------------------------------------------------------
# 4. ids from the code
# ------------------------------------------------------------------------------------------------
_DIHEDRAL = [np.array(m) for m in (
    [[1, 0], [0, 1]], [[0, -1], [1, 0]], [[-1, 0], [0, -1]], [[0, 1], [-1, 0]],
    [[-1, 0], [0, 1]], [[1, 0], [0, -1]], [[0, 1], [1, 0]], [[0, -1], [-1, 0]],
)]


def _match_code(labels: np.ndarray, symbols: np.ndarray, target: PhaseTarget):
    """All placements (mismatches, T, offset) of the lattice labels on the target grid, best first:
    lattice index ``l`` goes to cell ``T l + offset`` (T one of the 8 rotations/reflections)."""
    nx, ny = target.grid
    out = []
    for T in _DIHEDRAL:
        L = labels @ T.T
        lo = L.min(axis=0)
        hi = L.max(axis=0)
        for ox in range(-lo[0], nx - hi[0]):
            for oy in range(-lo[1], ny - hi[1]):
                ij = L + (ox, oy)
                out.append((int(np.sum(target.code[ij[:, 1], ij[:, 0]] != symbols)), T, (ox, oy)))
    out.sort(key=lambda r: r[0])
    return out


def _trim_spurious_lines(labels: np.ndarray, points: np.ndarray, grid):
    """Drop outer lattice rows/columns that make the linked grid larger than the target's.

    A spurious candidate just outside the grid (a phase defect at the monitor's edge, a reflection)
    sits one pitch beyond the last row and gets linked as a row of its own. While the linked grid
    spans more lines than the target has (in either orientation) and has more points than the
    target, the outermost line with the fewest points is removed if it holds at most a quarter of a
    full line; otherwise nothing is trimmed and the size check reports the mismatch.

    labels : (K, 2) int lattice indices; points : (K, 2) px. Returns the kept (labels, points)."""
    big, small = max(grid), min(grid)
    n_dots = grid[0] * grid[1]
    while len(labels) > n_dots:
        span = np.sort(labels.max(axis=0) - labels.min(axis=0) + 1)
        if span[0] <= small and span[1] <= big:
            break
        span = labels.max(axis=0) - labels.min(axis=0) + 1
        lines = []
        for axis in (0, 1):
            for end in (labels[:, axis].min(), labels[:, axis].max()):
                members = labels[:, axis] == end
                lines.append((int(members.sum()), axis, members))
        count, axis, members = min(lines, key=lambda t: t[0])
        if count > max(1, span[1 - axis] // 4):   # a line across the grid holds span[1 - axis] dots
            break
        labels, points = labels[~members], points[~members]
    return labels, points


def _placement_is_unique(best: int, second: int, n_dots: int) -> bool:
    """Whether the best code placement (``best`` misread symbols) identifies the dots safely.

    A full code window differs from any other placement in >= 2 cells, so with no misread dot a
    margin of 2 suffices. Heavy defocus can misread a few dots' symbols (their phase offset is
    shifted unevenly); up to 10 % of the dots (at least 1) may disagree with the code, provided
    the next placement is at least twice as bad (margin >= 2 and >= 2 x best). The disagreeing
    dots are then dropped, never relabelled."""
    return best <= max(1, n_dots // 10) and second - best >= max(2, 2 * best)


def _estimate_period(phase, modulation, mask):
    gx, gy, ok = _phase_gradient(phase, modulation, mask)
    g = np.hypot(gx, gy)[ok]
    if g.size < 100:
        raise DetectionError(f"only {g.size} pixels show fringes with enough modulation; is the target in view?")
    return float(TWO_PI / np.median(g))


def detect_dots(
    phase,
    modulation,
    target: PhaseTarget,
    *,
    mask=None,
    min_modulation: float = 3.0,
    blur_sigma: float | None = None,
    correct_blur: bool = True,
    min_coverage: float = 0.8,
    mirrored: bool | None = None,
) -> DotDetection:
    """Find the dots of a phase target in a demodulated view and their centres.

    Parameters
    ----------
    phase, modulation : (H, W) float
        Wrapped phase (rad) and modulation (grey levels) from :func:`kernels.phase.demodulate`.
    target : PhaseTarget
        The displayed target (grid, pitch, period, code).
    mask : (H, W) bool, optional
        Pixels to use (e.g. the ``valid`` output of the demodulation); combined with
        ``modulation >= min_modulation``.
    blur_sigma : float, optional
        Gaussian blur of the camera (px) if known. By default it is measured: first from the
        width of the modulation drop at the edge of the fringe area, then per dot from its
        modulation map, smoothed by a plane over the image.
    correct_blur : bool
        Run pass 2 (defocus bias removal by simulation) when the blur exceeds 0.3 px.
    min_coverage : float
        Dots whose fit window is less than this share on usable pixels (cut by the image edge,
        the mask, or a mirror's edge) are dropped.
    mirrored : bool, optional
        Only for targets without a code: whether the view is through a mirror (a plain grid
        cannot tell). Coded targets report it.

    Returns
    -------
    DotDetection
        Raises :class:`DetectionError` when no grid can be found or identified.
    """
    _check_target(target)
    phase, modulation, mask = _check_maps(phase, modulation, mask)
    if blur_sigma is not None and (not np.isfinite(blur_sigma) or blur_sigma < 0):
        raise ValueError(f"blur_sigma must be a finite number of px >= 0 or None, got {blur_sigma!r}")
    if not 0 <= min_coverage <= 1:
        raise ValueError(f"min_coverage must be in [0, 1], got {min_coverage!r}")
    mask = mask & (modulation >= min_modulation)
    period_img = _estimate_period(phase, modulation, mask)
    cands, _ = _find_candidates(phase, modulation, mask, period_img * target.pitch / target.period)
    labels, found = _grow_lattice(cands, 4 * target.n_dots)
    pts = cands[found]
    lab = labels[found]
    lab, pts = _trim_spurious_lines(lab, pts, target.grid)
    if len(pts) < 4:
        raise DetectionError(f"only {len(pts)} dots could be linked into a grid; at least 4 are needed")
    where = {tuple(l): n for n, l in enumerate(lab)}
    ncell = np.array(target.grid)
    span = lab.max(axis=0) - lab.min(axis=0) + 1
    if np.any(span > ncell.max()) or len(pts) > target.n_dots:
        raise DetectionError(
            f"found a grid of {span[0]}x{span[1]} dots ({len(pts)} dots) but the target has {ncell[0]}x{ncell[1]}; "
            "check grid/pitch/period of the target"
        )
    pitch = target.pitch
    given_blur = blur_sigma is not None
    if blur_sigma is None:
        blur_sigma = _estimate_blur(modulation, mask)
    # pass 1: radial phase model on the wrapped phase, window margins a fixed fraction of the cell
    rho_in, border = 0.1 * target.period, 0.1 * pitch
    fits = []
    for n, ij in enumerate(lab):
        src, dst = [], []
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                m = where.get((ij[0] + di, ij[1] + dj))
                if m is not None:
                    src.append((di * pitch, dj * pitch))
                    dst.append(pts[m])
        src, dst = np.array(src), np.array(dst)
        if len(src) < 4 or np.linalg.matrix_rank(src - src.mean(axis=0)) < 2:
            fits.append(None)
            continue
        try:
            A0 = np.linalg.inv(_homography(src, dst))
            fit = _fit_dot(phase, modulation, mask, A0, target.period, pitch, rho_in, border)
        except np.linalg.LinAlgError:
            fit = None  # degenerate neighbourhood homography (dots a few pixels apart): this dot has no fit
        fits.append(fit if fit is not None and fit.coverage >= min_coverage else None)
    keep = np.array([f is not None for f in fits])
    if keep.sum() < 4:
        raise DetectionError(f"only {int(keep.sum())} dots are fully in view with a successful fit; at least 4 are needed")
    fits = [f for f in fits if f is not None]
    lab = lab[keep]
    centres = np.array([f.centre for f in fits])
    # ids
    phi0 = np.array([f.phi0 for f in fits])
    step = TWO_PI / target.levels
    # defocus shifts every dot's phi0 by about the same amount: remove the common offset
    # (circular mean of the deviations from the nearest symbol) before reading the symbols
    dev = phi0 - step * np.rint(phi0 / step)
    common = float(np.angle(np.mean(np.exp(1j * dev * target.levels)))) / target.levels
    sym = np.mod(np.rint((phi0 - common) / step), target.levels).astype(np.int64)
    if target.coded:
        placements = _match_code(lab, sym, target)
        if not placements:
            raise DetectionError(
                f"the {len(lab)} linked dots span more rows or columns than the {target.grid[0]} x {target.grid[1]} "
                "target in every orientation (spurious or mislinked dots); check the target file and the view")
        best = placements[0]
        second = placements[1][0] if len(placements) > 1 else 10 ** 6
        if not _placement_is_unique(best[0], second, len(lab)):
            raise DetectionError(
                f"the dot code is ambiguous in this view (best placement {best[0]} mismatches, next {second}); "
                f"{len(lab)} dots seen - show more of the target"
            )
        T, off = best[1], np.array(best[2])
        ij = lab @ T.T + off
        good = target.code[ij[:, 1], ij[:, 0]] == sym  # drops a single misread dot
    else:
        if len(lab) != target.n_dots:
            raise DetectionError(
                f"a target without code must be fully visible: found {len(lab)} of {target.n_dots} dots"
            )
        ij = _uncoded_ids(lab, centres, target, mirrored)
        good = np.ones(len(ij), dtype=bool)
    ids = ij[:, 1] * target.grid[0] + ij[:, 0]
    sigmas = np.full(len(ids), float(blur_sigma))
    if correct_blur and blur_sigma > 0.3:
        centres, good, sigmas = _remove_blur_bias(target, phase.shape, modulation, mask, fits, ids, centres,
                                                  good, float(blur_sigma), given_blur, rho_in, border)
    gsel = np.flatnonzero(good)
    if gsel.size < 4:
        raise DetectionError(f"only {gsel.size} dots were identified; at least 4 are needed")
    # handedness of the target -> image mapping
    screen_c = target.dot_centres_px
    Hg = _homography(screen_c[ids[gsel]], centres[gsel])
    is_mirrored = bool(np.linalg.det(_jacobian_h(Hg, screen_c[ids[gsel]].mean(axis=0))) < 0)
    sel = gsel[np.argsort(ids[gsel])]
    return DotDetection(
        image_points=centres[sel],
        ids=ids[sel].astype(np.int64),
        object_points=target.object_points[ids[sel]],
        residual_rms=np.array([fits[i].rms for i in sel]),
        sigma_px=np.array([fits[i].sigma for i in sel]),
        modulation=np.array([fits[i].modulation for i in sel]),
        n_pixels=np.array([fits[i].n for i in sel], dtype=np.int64),
        mirrored=is_mirrored,
        blur_sigma=float(np.median(sigmas[sel])),
        modulation_slope=np.array([fits[i].modulation_slope for i in sel]),
    )


def _remove_blur_bias(target, shape, modulation, mask, fits, ids, centres, good, blur0, given_blur, rho_in, border):
    """Pass 2: subtract from each pass-1 centre the bias the same fit shows on a simulated view.

    Three rounds: (1) global homography through the current centres, each dot's simulation
    placed on its current estimate, blur ``blur0``; (2) blur measured per dot from the
    modulation (unless given) and smoothed by a plane; (3) final. Returns (centres, good, sigmas).
    """
    screen_c = target.dot_centres_px
    good = good.copy()
    corrected = centres.copy()
    sigmas = np.full(len(ids), blur0)
    workers = max(1, min(4, _cpu_count()))
    pool = ThreadPoolExecutor(max_workers=workers) if workers > 1 else None

    def run(fn, items):
        return list(pool.map(fn, items)) if pool is not None else [fn(i) for i in items]

    try:
        for rnd in range(3):
            sel = np.flatnonzero(good)
            if sel.size < 4:
                break
            H_all = _homography(screen_c[ids[sel]], corrected[sel])

            def simulate(n):
                c_scr = screen_c[ids[n]]
                # the global homography, moved so that the dot lands on its current estimate
                off = corrected[n] - _apply_h(H_all, c_scr[None])[0]
                A_sim = np.linalg.inv(np.array([[1, 0, off[0]], [0, 1, off[1]], [0, 0, 1.0]]) @ H_all)
                sim = _DotSimulation(target, shape, A_sim, c_scr, 1.5 * blur0)
                if not sim.ok:
                    return None
                blur = _fit_blur(sim, modulation, mask, blur0) if (rnd == 1 and not given_blur) else None
                return sim, blur

            sims = dict(zip(sel, run(simulate, sel)))
            if rnd == 1 and not given_blur:
                ok = np.array([n for n in sel if sims[n] is not None])
                for n in ok:
                    sigmas[n] = sims[n][1]
                if ok.size:
                    # a single dot's blur estimate is noisy; the defocus of a flat target varies
                    # smoothly over the image: fit a plane
                    sigmas = _smooth_blur(centres, sigmas, ok)

            def debias(n):
                if sims[n] is None:
                    return None
                f = fits[n]
                return _simulated_fit_bias(sims[n][0], mask, float(sigmas[n]), f.A, f.A_window, target.period,
                                           target.pitch, rho_in, border)

            for n, bias in zip(sel, run(debias, sel)):
                if bias is None:
                    good[n] = False
                else:
                    corrected[n] = centres[n] - bias
    finally:
        if pool is not None:
            pool.shutdown()
    return corrected, good, sigmas


def _cpu_count() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - non-Linux
        return os.cpu_count() or 1


def _jacobian_h(H, xy):
    x, y = xy
    q = H @ np.array([x, y, 1.0])
    J = np.zeros((2, 2))
    for c in range(2):
        J[0, c] = (H[0, c] * q[2] - q[0] * H[2, c]) / q[2] ** 2
        J[1, c] = (H[1, c] * q[2] - q[1] * H[2, c]) / q[2] ** 2
    return J


def _uncoded_ids(lab, centres, target, mirrored):
    """Cell indices (K, 2) for a plain (uncoded), fully visible grid: the placement whose
    handedness matches ``mirrored`` and whose target x axis points closest to the image +x axis."""
    nx, ny = target.grid
    want_mirror = bool(mirrored)
    best = None
    for T in _DIHEDRAL:
        L = lab @ T.T
        L = L - L.min(axis=0)
        if L[:, 0].max() != nx - 1 or L[:, 1].max() != ny - 1:
            continue
        ids = L[:, 1] * nx + L[:, 0]
        H = _homography(target.dot_centres_px[ids], centres)
        J = _jacobian_h(H, target.dot_centres_px.mean(axis=0))
        if (np.linalg.det(J) < 0) != want_mirror:
            continue
        score = J[0, 0] / np.linalg.norm(J[:, 0])
        if best is None or score > best[0]:
            best = (score, L)
    if best is None:
        raise DetectionError(f"no placement of the plain grid matches the requested handedness (mirrored={want_mirror})")
    return best[1]


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


def detect_dots_in_images(images, target: PhaseTarget, *, min_modulation: float = 3.0, device=None, **kwargs) -> DotDetection:
    """Demodulate a recorded (steps, H, W) stack and run :func:`detect_dots` on it."""
    _check_target(target)
    phase, mod, _, valid = demodulate_images(images, target, min_modulation=min_modulation, device=device)
    return detect_dots(phase, mod, target, mask=valid, min_modulation=min_modulation, **kwargs)


# ------------------------------------------------------------------------------------------------
# dense mode
# ------------------------------------------------------------------------------------------------
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


# ------------------------------------------------------------------------------------------------
# conventional targets (OpenCV)
# ------------------------------------------------------------------------------------------------
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
