"""Re-verification of composed warps against the original reference image: one ZNCC per point.

With a moved reference (a sequence tracked incrementally, or every N frames), a point's reported
warp in frame ``k`` is a composition of several correlations (:mod:`dic.correlation.lagrangian`).
:class:`ComposedCheck` re-derives, in one launch per frame, the zero-normalised cross-correlation
between the point's square subset in the ORIGINAL reference image (at whole pixels, centred on the
POI rounded half away from zero like IC-GN) and frame ``k`` sampled at the composed warp
(cubic B-spline, :mod:`kernels.interp`): the check that pyALDIC-3D makes with a ZNSSD for every
node of every frame (``ZNSSD = 2 (1 - ZNCC)``). A wrong match carried through a reference update
has a low ZNCC against the original reference even when each correlation of the chain was good.

The warp of subset pixel ``(dx, dy)`` (px, from the subset centre) is that of IC-GN
(:mod:`kernels.icgn`, parameter order :data:`kernels.conventions.PARAMS_2ND`):
``x' = cx + dx + u + ux dx + uy dy + uxx dx^2 / 2 + uxy dx dy + uyy dy^2 / 2`` and the same for
``y'`` with ``v``; 1st-order warps have zero second derivatives.

Outcome per point (:data:`CHECKED`, :data:`OUTSIDE`, :data:`FLAT`, :data:`SKIPPED`): a ZNCC, or why
there is none (a subset that leaves the image in the reference or in frame ``k``; a subset with no
grey-level variation in either; a point not asked for).
"""
from __future__ import annotations

import math

import numpy as np
import warp as wp

from ._common import icgn_module_options
from ._device import host_copy, resolve_device
from ._launch import launch_1d
from .checks import as_points, odd_int
from .conventions import round_half_away
from .images import as_float32_image
from .interp import PaddedImage, bspline3_weights_fast, bspline_coefficients, rows4_view, stencil_dot_rows4

# the IC-GN family's options (FMA contraction, -march=native on the CPU): the same interpolation, about as fast
wp.set_module_options(icgn_module_options("_composed_zncc"))

__all__ = ["ComposedCheck", "composed_threshold", "composed_failures", "check_verify_spread", "CHECKED", "OUTSIDE", "FLAT", "SKIPPED",
           "MIN_SPREAD_POINTS", "VERIFY_SPREAD", "PEAK_PROBES", "PEAK_MARGIN"]

#: outcome codes of :meth:`ComposedCheck.zncc`
CHECKED = 0   #: the ZNCC was computed
OUTSIDE = 1   #: the reference subset or its warped copy leaves the image: no ZNCC (NaN)
FLAT = 2      #: no grey-level variation in the reference subset or in its warped copy: no ZNCC (NaN)
SKIPPED = 3   #: not asked for (``check`` False): no ZNCC (NaN)

#: the fewest checked points of a frame whose ZNCCs can lower the threshold (:func:`composed_threshold`)
MIN_SPREAD_POINTS = 20
#: the default robust standard deviations below a frame's median composed ZNCC at which a point fails when that
#: is below ``verify_zncc`` (``verify_spread``), by measurement (docs/dic2d.md, "Re-verification of composed results")
VERIFY_SPREAD = 4.0


def check_verify_spread(spread):
    """``verify_spread`` validated: a finite number >= 0 (float), or ``"off"`` / None (None: the threshold
    ``verify_zncc`` alone, the rule before the option)."""
    if spread is None or (isinstance(spread, str) and spread == "off"):
        return None
    if isinstance(spread, bool) or not isinstance(spread, (int, float, np.integer, np.floating)) or \
            not math.isfinite(float(spread)) or float(spread) < 0:
        raise ValueError(f"verify_spread must be a finite number >= 0 (robust standard deviations) or 'off', "
                         f"got {spread!r}")
    return float(spread)


#: the peak test of :func:`composed_failures`: the probes (du, dv) px around a point's composed warp, and the margin
#: (times 1 - the frame's median ZNCC) by which a probe must beat the composed warp for the point to fail
PEAK_PROBES = ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))
PEAK_MARGIN = 0.2

#: the MAD of a normal distribution times this is its standard deviation
_MAD_TO_STD = 1.4826

_CHECKED = wp.constant(CHECKED)
_OUTSIDE = wp.constant(OUTSIDE)
_FLAT = wp.constant(FLAT)
_SKIPPED = wp.constant(SKIPPED)


@wp.func
def _row_terms(c: wp.float64, dy: wp.float64, p0: wp.float64, p1: wp.float64, p2: wp.float64, p3: wp.float64,
               p4: wp.float64, p5: wp.float64):
    """A subset row's warp along one axis as ``a + b dx + q dx^2`` in dx: ``(a, b, q)`` for the parameters
    ``p0..p5`` (u, ux, uy, uxx, uxy, uyy, or v, ...; x axis) at row offset ``dy`` from the centre ``c``."""
    half = wp.float64(0.5)
    return wp.vec3d(c + p0 + dy * (p2 + half * p5 * dy), wp.float64(1.0) + p1 + p4 * dy, half * p3)


@wp.kernel
def _composed_zncc(offset: int, reference: wp.array2d(dtype=float), coef: wp.array(dtype=wp.vec4), pitch: int,
                   centres: wp.array(dtype=wp.vec2i), params: wp.array2d(dtype=wp.float64), check: wp.array(dtype=wp.int32),
                   half: int, zncc: wp.array(dtype=float), outcome: wp.array(dtype=wp.int32)):
    i = wp.tid() + offset
    zncc[i] = wp.nan
    if check[i] == 0:
        outcome[i] = _SKIPPED
        return
    h = reference.shape[0]
    w = reference.shape[1]
    cx = centres[i][0]
    cy = centres[i][1]
    if cx - half < 0 or cy - half < 0 or cx + half > w - 1 or cy + half > h - 1:
        outcome[i] = _OUTSIDE
        return
    fx0 = wp.float64(cx)
    fy0 = wp.float64(cy)
    sf = wp.float64(0.0)
    sg = wp.float64(0.0)
    sff = wp.float64(0.0)
    sgg = wp.float64(0.0)
    sfg = wp.float64(0.0)
    for jy in range(-half, half + 1):
        dy = wp.float64(jy)
        # along the row: x' = ax + bx dx + qx dx^2, y' = ay + by dx + qy dx^2 (the 1 of dy/dy in vy + 1)
        tx = _row_terms(fx0, dy, params[i, 0], params[i, 1], params[i, 2], params[i, 3], params[i, 4], params[i, 5])
        ty = _row_terms(fy0, dy, params[i, 6], params[i, 7], params[i, 8] + wp.float64(1.0), params[i, 9],
                        params[i, 10], params[i, 11])
        by = ty[1] - wp.float64(1.0)  # d y' / d dx: vx + vxy dy (_row_terms added the 1 of the x axis)
        for jx in range(-half, half + 1):
            dx = wp.float64(jx)
            x = tx[0] + dx * (tx[1] + tx[2] * dx)
            y = ty[0] + dx * (by + ty[2] * dx)
            if not (x >= wp.float64(0.0) and x <= wp.float64(w - 1) and y >= wp.float64(0.0)
                    and y <= wp.float64(h - 1)):
                outcome[i] = _OUTSIDE
                return
            fx = wp.floor(x)
            fy = wp.floor(y)
            g = wp.float64(stencil_dot_rows4(coef, pitch, int(fx), int(fy), bspline3_weights_fast(float(x - fx)),
                                             bspline3_weights_fast(float(y - fy))))
            f = wp.float64(reference[cy + jy, cx + jx])
            sf += f
            sg += g
            sff += f * f
            sgg += g * g
            sfg += f * g
    n = wp.float64((2 * half + 1) * (2 * half + 1))
    var_f = sff - sf * sf / n
    var_g = sgg - sg * sg / n
    if not (var_f > wp.float64(1e-6) * n and var_g > wp.float64(1e-6) * n):
        outcome[i] = _FLAT
        return
    zncc[i] = float((sfg - sf * sg / n) / wp.sqrt(var_f * var_g))
    outcome[i] = _CHECKED


class ComposedCheck:
    """The original reference image and its POIs on the device, to check composed warps frame after frame.

    Parameters
    ----------
    reference : array-like (H, W)
        The original reference image (grey levels; uploaded once, read at whole pixels).
    points : (N, 2) float px
        The POIs (x, y) in the reference; each subset is centred on the point rounded half away
        from zero (:func:`kernels.conventions.round_half_away`), as IC-GN centres it.
    subset : int
        Odd subset side in px (the run's).
    device : None or str

    :meth:`zncc` takes a frame and the points' composed parameters and returns their ZNCC; the
    frame's B-spline coefficients go to a buffer allocated once.
    """

    def __init__(self, reference, points, subset: int, device=None):
        self.device = resolve_device(device)
        ref = as_float32_image(reference, "reference")
        if ref.shape[0] < 4 or ref.shape[1] < 4:
            raise ValueError(f"reference must be at least 4x4 pixels, got shape {ref.shape}")
        pts = as_points(points)
        self.subset = odd_int(subset, "subset")
        self.shape = ref.shape
        self.n_points = len(pts)
        self._reference = wp.array(np.ascontiguousarray(ref), dtype=wp.float32, device=self.device)
        centres = round_half_away(pts).astype(np.int32)
        self._centres = wp.array(centres, dtype=wp.vec2i, device=self.device)
        self._coef: wp.array | None = None
        self._params = wp.empty((self.n_points, 12), dtype=wp.float64, device=self.device)
        self._check = wp.empty(self.n_points, dtype=wp.int32, device=self.device)
        self._zncc = wp.empty(self.n_points, dtype=wp.float32, device=self.device)
        self._outcome = wp.empty(self.n_points, dtype=wp.int32, device=self.device)

    def zncc(self, frame, params, check=None) -> tuple[np.ndarray, np.ndarray]:
        """ZNCC of each point's reference subset and ``frame`` at its composed warp.

        Parameters
        ----------
        frame : array-like (H, W) (any real dtype), a float32 ``wp.array2d`` on the device, or a
            :class:`kernels.interp.PaddedImage` of B-spline coefficients of the frame
        params : (N, 6) or (N, 12) float
            Warp parameters at the POIs, against the original reference (1st or 2nd order,
            :data:`kernels.conventions.PARAMS_1ST` / ``PARAMS_2ND``; u, v in px).
        check : (N,) bool, optional
            The points to check (default: all; rows with non-finite parameters are never checked).

        Returns
        -------
        zncc : (N,) float32, in [-1, 1]; NaN where no ZNCC was computed
        outcome : (N,) int32, :data:`CHECKED`, :data:`OUTSIDE`, :data:`FLAT` or :data:`SKIPPED`
        """
        p = np.asarray(params, dtype=np.float64)
        if p.ndim != 2 or p.shape[0] != self.n_points or p.shape[1] not in (6, 12):
            raise ValueError(f"params must be ({self.n_points}, 6) or ({self.n_points}, 12), got shape {p.shape}")
        if check is None:
            mask = np.ones(self.n_points, dtype=bool)
        else:
            mask = np.asarray(check)
            if mask.dtype != bool or mask.shape != (self.n_points,):
                raise ValueError(f"check must be a ({self.n_points},) bool mask, got {mask.dtype} {mask.shape}")
        mask = mask & np.all(np.isfinite(p), axis=1)
        full = np.zeros((self.n_points, 12))
        if p.shape[1] == 6:
            full[:, [0, 1, 2, 6, 7, 8]] = p
        else:
            full[:] = p
        full[~mask] = 0.0
        coef = self._coefficients(frame)
        self._params.assign(full)
        self._check.assign(mask.astype(np.int32))
        launch_1d(_composed_zncc, self.n_points,
                  [0, self._reference, rows4_view(coef), coef.pitch, self._centres, self._params, self._check,
                   self.subset // 2, self._zncc, self._outcome], self.device, offset_index=0, min_chunk=64)
        return host_copy(self._zncc), host_copy(self._outcome)

    def coefficients(self, frame) -> PaddedImage:
        """The B-spline coefficients of ``frame`` (as :meth:`zncc` takes it) in the buffer of this check: pass them
        to several :meth:`zncc` calls on one frame to prefilter it once (valid until the next frame's)."""
        return self._coefficients(frame)

    def _coefficients(self, frame) -> PaddedImage:
        if isinstance(frame, PaddedImage):
            if frame.kind != "bspline" or tuple(frame.shape) != tuple(self.shape) or frame.device != self.device:
                raise ValueError(f"frame coefficients must be B-spline coefficients of a {self.shape} image on "
                                 f"{self.device}, got kind {frame.kind!r}, shape {frame.shape} on {frame.device}")
            return frame
        shape = tuple(frame.shape)
        if shape != tuple(self.shape):
            raise ValueError(f"frame has shape {shape} but the reference has shape {self.shape}")
        out = bspline_coefficients(frame, device=self.device, out=self._coef)
        self._coef = out.data
        return out


def composed_threshold(zncc, checked, threshold: float, spread: float | None) -> float:
    """The ZNCC below which a checked point of one frame fails the check of composed warps.

    ``min(threshold, median - spread * 1.4826 * MAD)`` of the ZNCCs of the frame's checked points (the frame's
    typical value less ``spread`` robust standard deviations): ``threshold`` (``verify_zncc``) on a texture that
    still matches the reference image, where the correct points score close to 1 with a small spread (results
    as with ``threshold`` alone), and lower on a texture that has changed since the reference image (an evolving
    speckle), where every correct point has lost correlation with it and a fixed threshold would refuse them
    all; a point far below the frame's own distribution still fails. ``spread`` None, or fewer than
    :data:`MIN_SPREAD_POINTS` checked points: ``threshold``.

    Parameters
    ----------
    zncc : (N,) float
        The points' ZNCC (:meth:`ComposedCheck.zncc`; NaN where none).
    checked : (N,) bool
        The points whose ZNCC counts (checked and reported valid).
    threshold : float in [-1, 1]
    spread : float >= 0 or None
        Robust standard deviations below the median.

    Returns
    -------
    float
    """
    threshold = float(threshold)
    if spread is None:
        return threshold
    z = np.asarray(zncc, np.float64)[np.asarray(checked, bool)]
    z = z[np.isfinite(z)]
    if z.size < MIN_SPREAD_POINTS:
        return threshold
    median = float(np.median(z))
    scale = _MAD_TO_STD * float(np.median(np.abs(z - median)))
    return min(threshold, median - float(spread) * scale)


def composed_failures(zncc, checked, threshold: float, spread: float | None, probe=None) -> tuple[np.ndarray, float]:
    """The checked points of one frame that fail the check of composed warps, and the frame's threshold.

    A point fails when its ZNCC is below the frame's threshold (:func:`composed_threshold`). Where that threshold
    is below ``threshold`` (the texture has changed since the reference image), a point between the two also
    fails when its composed warp is not where the ZNCC against the reference image peaks: ``probe`` gives the
    ZNCC at the warp moved by each of :data:`PEAK_PROBES` (1 px along x and y), and a point fails when one of
    them beats its own ZNCC by more than ``PEAK_MARGIN * (1 - median)`` (the frame's median ZNCC). A correct warp
    sits on the peak of what is left of the reference texture; a warp 1 px off does not, however decorrelated
    the texture. Where the frame's threshold is ``threshold`` (a texture that still matches the reference image)
    nothing is probed and the result is that of ``threshold`` alone.

    Parameters
    ----------
    zncc : (N,) float
        The points' ZNCC at their composed warps (NaN where none).
    checked : (N,) bool
        The points judged (checked and reported valid).
    threshold : float in [-1, 1]
        ``verify_zncc``.
    spread : float >= 0 or None
        ``verify_spread`` (None: ``threshold`` alone, no probe).
    probe : callable(du, dv, which) -> (N,) float, optional
        The ZNCC of the points ``which`` ((N,) bool) at their composed warps moved by (du, dv) px (NaN where none
        or not asked); None: no peak test.

    Returns
    -------
    failed : (N,) bool
    limit : float, the frame's threshold
    """
    checked = np.asarray(checked, bool)
    limit = composed_threshold(zncc, checked, threshold, spread)
    failed = checked & ~(zncc >= limit)
    if probe is None or not limit < float(threshold):
        return failed, limit
    candidates = checked & ~failed & ~(zncc >= float(threshold))
    if np.any(candidates):
        z = np.asarray(zncc, np.float64)
        judged = z[checked & np.isfinite(z)]
        margin = PEAK_MARGIN * (1.0 - float(np.median(judged)))
        best = np.full(z.shape, -np.inf)
        for du, dv in PEAK_PROBES:
            best = np.fmax(best, np.asarray(probe(du, dv, candidates), np.float64))
        failed = failed | (candidates & (best > z + margin))
    return failed, limit


def shifted_params(params, du: float, dv: float) -> np.ndarray:
    """``params`` (N, 6 or 12) with u and v moved by (du, dv) px (a copy, float64)."""
    q = np.array(params, dtype=np.float64, copy=True)
    q[:, 0] += du
    q[:, q.shape[1] // 2] += dv
    return q
