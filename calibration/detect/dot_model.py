"""Dot detector, steps 3 and 5 (:mod:`calibration.detect.dots`): the per-dot fit of the projective
radial phase model, and the defocus-bias correction that runs the identical fit on a simulated,
blurred view of each dot.

Conventions: docs/conventions.md (pixel (0, 0) is the centre of the top-left pixel, points are
(x, y)); target frame: :mod:`calibration.targets`.
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..targets import PhaseTarget
from .common import TWO_PI, _apply_h, _homography, _jacobian_h, _wrap


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
