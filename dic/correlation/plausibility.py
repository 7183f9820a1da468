"""Plausibility of converged subset warps: subsets that are partly featureless.

Where a subset straddles a specimen's edge, part of it sees a featureless background. Those pixels
do not constrain the warp: the displacement at the subset centre is extrapolated from the textured
part, and the 2nd-order terms (which bend the warp across the subset) are nearly free. IC-GN then
converges, with a high ZNCC and status CONVERGED, to warps that are impossible for the specimen
(on real stereo data: 1.3 px off, shear 0.23, on subsets 70-86 % background). This module finds
such POIs from the reference image and the tracked field alone:

* :func:`textured_fraction` — the share of each subset's pixels that carry texture;
* :func:`implausible_warps` — accepted POIs on partly featureless subsets whose displacement or
  displacement gradient disagrees with what their well-textured accepted neighbours predict.

Conventions (docs/conventions.md): points ``(x, y)`` in reference pixels, displacements in px,
parameters in :data:`kernels.conventions.PARAMS_1ST` / ``PARAMS_2ND`` order.
"""
from __future__ import annotations

import numbers

import numpy as np

from kernels._launch import cpu_threads
from kernels.conventions import round_half_away

from .order_stats import percentile

__all__ = ["textured_pixels", "textured_fraction", "implausible_warps"]


def _check_image(image, name: str = "reference_image") -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim != 2 or arr.shape[0] < 2 or arr.shape[1] < 2:
        raise ValueError(f"{name} must be a 2-D grey image (H, W), got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"{name} must hold real grey levels, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


def _check_points(points) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must be an (N, 2) array of (x, y), got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points contain NaN or infinite values")
    return pts


def _check_positive_odd(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1 or value % 2 == 0:
        raise ValueError(f"{name} must be a positive odd integer (px), got {value!r}")
    return int(value)


def _check_fraction(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (0.0 <= value <= 1.0):
        raise ValueError(f"{name} must be a number in [0, 1], got {value!r}")
    return float(value)


def _check_positive(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (value > 0 and np.isfinite(value)):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return float(value)


def textured_pixels(reference_image, *, window: int = 7, relative_threshold: float = 0.1,
                    noise_sigma: float | None = None, noise_factor: float = 4.0) -> np.ndarray:
    """Pixels of the reference image that carry texture: (H, W) bool.

    A pixel is textured when the grey-level standard deviation in the ``window`` × ``window`` box
    around it exceeds a threshold ``t = max(relative_threshold · s95, noise_factor · noise_sigma)``,
    where ``s95`` is the 95th percentile of that local standard deviation over the image (the
    contrast of the speckle) and ``noise_sigma`` the camera noise (grey levels) when known.
    A featureless background shows only its noise there (about 2 grey levels for 2 GL of noise),
    speckle tens of grey levels (dic.synth defaults, 8 bits: s95 = 65-67 GL, t ≈ 6.6 GL; the 5th
    percentile on a fully speckled image is 33 GL); pixels within
    ``window // 2`` px of a specimen edge count as textured (the edge itself has contrast).
    Measured on the band case of tests/dic/test_edge_subsets.py (Boolean speckle, radius 2 px,
    density 0.5, 2 GL noise, 10 GL background): 99.86 % of the specimen's pixels are textured and
    1.9 % of the background's (those next to the edge); a subset wholly on the speckle has a
    textured fraction of 0.94 or more (large gaps between speckles are locally flat).

    Parameters
    ----------
    reference_image : (H, W) array of grey levels
    window : odd int
        Side (px) of the box in which the local standard deviation is taken.
    relative_threshold : float in [0, 1]
        Threshold as a fraction of the image's 95th-percentile local standard deviation.
    noise_sigma : float, optional
        Camera noise (grey levels); when given, the threshold is at least ``noise_factor`` times it.
    noise_factor : float
    """
    import cv2

    image = _check_image(reference_image)
    window = _check_positive_odd(window, "window")
    relative_threshold = _check_fraction(relative_threshold, "relative_threshold")
    noise_factor = _check_positive(noise_factor, "noise_factor")
    floor = 0.0
    if noise_sigma is not None:
        if isinstance(noise_sigma, bool) or not isinstance(noise_sigma, numbers.Real) or not (
                noise_sigma >= 0 and np.isfinite(noise_sigma)):
            raise ValueError(f"noise_sigma must be a non-negative number of grey levels, got {noise_sigma!r}")
        floor = noise_factor * float(noise_sigma)
    # local variance E[I²] - E[I]² with box filters, centred on the grey mean for precision
    # (in place on the checked copy and the filters' outputs: the same values as the expressions in the comments,
    # with fewer full-image temporaries)
    centred = image
    centred -= image.mean()  # image - mean
    mean = cv2.boxFilter(centred, cv2.CV_64F, (window, window), borderType=cv2.BORDER_REFLECT)
    np.multiply(centred, centred, out=centred)
    mean_sq = cv2.boxFilter(centred, cv2.CV_64F, (window, window), borderType=cv2.BORDER_REFLECT)
    np.multiply(mean, mean, out=mean)
    np.subtract(mean_sq, mean, out=mean_sq)
    local_std = np.sqrt(np.clip(mean_sq, 0.0, None, out=mean_sq), out=mean_sq)  # sqrt(clip(mean_sq - mean², 0))
    # np.percentile's value, found without partitioning the whole image (dic.correlation.order_stats)
    threshold = max(relative_threshold * float(percentile(local_std, 95.0)), floor)
    return local_std > threshold


def textured_fraction(reference_image, points, subset: int, *, window: int = 7, relative_threshold: float = 0.1,
                      noise_sigma: float | None = None, noise_factor: float = 4.0) -> np.ndarray:
    """Fraction of each subset's pixels that carry texture: (N,) float64 in [0, 1].

    The subset of a POI ``(x, y)`` is the ``subset`` × ``subset`` box centred on the nearest pixel;
    pixels outside the image count as untextured. Textured pixels are those of
    :func:`textured_pixels` (same keyword arguments), computed once for the image, and summed
    per subset from an integral image: O(H·W + N); 0.15 s for 1 M points on a 256² image.

    Parameters
    ----------
    reference_image : (H, W) array of grey levels
    points : (N, 2) array of POIs ``(x, y)`` in px
    subset : odd int, subset size (px)
    window, relative_threshold, noise_sigma, noise_factor : see :func:`textured_pixels`.
    """
    import cv2

    pts = _check_points(points)
    subset = _check_positive_odd(subset, "subset")
    mask = textured_pixels(reference_image, window=window, relative_threshold=relative_threshold,
                           noise_sigma=noise_sigma, noise_factor=noise_factor)
    H, W = mask.shape
    integral = cv2.integral(mask.astype(np.uint8), sdepth=cv2.CV_64F)  # (H + 1, W + 1)
    half = subset // 2
    col = round_half_away(pts[:, 0]).astype(np.int64)  # the kernels' subset centres (half away from zero)
    row = round_half_away(pts[:, 1]).astype(np.int64)
    c0 = np.clip(col - half, 0, W)
    c1 = np.clip(col + half + 1, 0, W)
    r0 = np.clip(row - half, 0, H)
    r1 = np.clip(row + half + 1, 0, H)
    count = integral[r1, c1] - integral[r0, c1] - integral[r1, c0] + integral[r0, c0]
    return count / float(subset * subset)


def _first_order(params: np.ndarray, order: int) -> np.ndarray:
    """(N, 6) ``u, ux, uy, v, vx, vy`` from 1st- or 2nd-order parameters."""
    if order == 1:
        return params
    return params[:, [0, 1, 2, 6, 7, 8]]


def _quadratic_prediction(at: np.ndarray, where: np.ndarray, values: np.ndarray):
    """Values and gradients at ``at`` (M, 2) of quadratics fitted to neighbours' values and gradients.

    ``where`` (M, k, 2) are the neighbours' positions and ``values`` (M, k, 3, c) their
    ``(w, wx, wy)`` for ``c`` displacement components ``w``. Each neighbour gives three equations
    for the six coefficients of ``w(d) = a + b·d + ½ dᵀ C d`` around ``at`` (``d`` = neighbour −
    ``at``): ``w = a + b·d + ½ dᵀ C d`` and ``∇w = b + C d``. Gradients make the fit well posed even
    when the neighbours lie on one line (along an edge); a small ridge keeps unobserved curvature
    at 0. Coordinates are scaled by the mean neighbour distance ``L`` so that the equations are
    comparable. Returns ``(a (M, c), b (M, 2, c))``.
    """
    m, k = where.shape[:2]
    d = where - at[:, None, :]  # (M, k, 2)
    scale = np.maximum(np.mean(np.hypot(d[..., 0], d[..., 1]), axis=1), 1e-9)  # (M,) px
    dx, dy = d[..., 0] / scale[:, None], d[..., 1] / scale[:, None]
    # unknowns (a, L·bx, L·by, L²·cxx, L²·cxy, L²·cyy); rows: value, L·wx, L·wy of each neighbour
    design = np.zeros((m, 3, k, 6))
    design[:, 0] = np.stack([np.ones_like(dx), dx, dy, 0.5 * dx * dx, dx * dy, 0.5 * dy * dy], axis=-1)
    design[:, 1, :, 1], design[:, 1, :, 3], design[:, 1, :, 4] = 1.0, dx, dy
    design[:, 2, :, 2], design[:, 2, :, 4], design[:, 2, :, 5] = 1.0, dx, dy
    design = design.reshape(m, 3 * k, 6)
    rhs = np.swapaxes(values, 1, 2).copy()  # (M, 3, k, c)
    rhs[:, 1:] *= scale[:, None, None, None]
    rhs = rhs.reshape(m, 3 * k, -1)
    design_t = np.swapaxes(design, 1, 2)
    coef = np.linalg.solve(design_t @ design + 1e-6 * np.eye(6), design_t @ rhs)  # (M, 6, c)
    return coef[:, 0, :], coef[:, 1:3, :] / scale[:, None, None]


def implausible_warps(points, params, order: int, accepted, textured_fraction, *, partial_below: float = 0.8,
                      well_textured: float = 0.97, neighbours: int = 20, displacement_tol: float = 0.03,
                      gradient_tol: float = 0.03) -> np.ndarray:
    """Accepted POIs whose warp is implausible because part of their subset is featureless: (N,) bool.

    The rule follows from what a partly featureless subset can measure. Its featureless pixels
    do not constrain the warp, so the displacement at its centre is extrapolated from the textured
    part and, in 2nd order, the quadratic terms are nearly free: IC-GN can converge (high ZNCC,
    status CONVERGED) to a warp that bends the featureless part anywhere. A POI is flagged when

    1. it is accepted and its subset is *partial*: ``textured_fraction < partial_below``
       (0.8: the wrong POIs below had at most 60 % specimen, a textured fraction of 0.7 or less
       with the edge's own contrast, while a subset wholly on rendered speckle with wide gaps can
       read 0.9: 0.896 for an interior POI of the stereo scene of tests/dic/test_stereo_dic.py, 0.039 px
       from the truth, which a threshold of 0.9 flagged); and
    2. its displacement or its displacement gradient disagrees with the prediction of its
       well-textured neighbours: the ``neighbours`` nearest accepted POIs with
       ``textured_fraction >= well_textured`` give their displacements and gradients (1st-order
       terms), a quadratic ``w(d) = a + b·d + ½ dᵀ C d`` is fitted to them per component by least
       squares (values and gradients: 3 equations per neighbour, so neighbours lined up along an
       edge still fix it), and its value ``a`` and gradient ``b`` at the POI are the prediction.
       Flag when ``|Δu|`` or ``|Δv|`` exceeds ``displacement_tol`` px, or any of
       ``Δux, Δuy, Δvx, Δvy`` exceeds ``gradient_tol``.

    A partial POI with no well-textured accepted POI anywhere cannot be vouched for and is flagged.
    Fully textured POIs are never flagged, so an ordinary speckle image gives no flag whatever its
    deformation. The quadratic fit follows curvature (a 1st-order Taylor step from each neighbour,
    tried first, flagged 31 correct edge POIs of a 128 px sinusoid instead of 7); its error is the
    neighbours' noise amplified by the extrapolation, plus the cubic part of the field.

    Measured (tests/dic/test_edge_subsets.py: 256² speckled band with slanted edges on a dark
    featureless background, 2 GL noise, subset 21, step 8, strains ~1 %, 20 neighbours): the
    prediction is within 0.028 px of the truth (RMS 0.012 px, 2nd order); the wrong POIs (0.05 to
    0.58 px off, ZNCC >= 0.997) disagree with it by 0.032 px or more (median 0.15 px, 2nd order;
    0.09 px, 1st order), the correct partial ones by a median 0.016 px (gradients: 0.005 median,
    0.024 at most). ``displacement_tol = 0.03`` px therefore flags every POI off by more than
    0.05 px there (48 of 449 accepted in 2nd order, plus 7 correct ones; 26 + 6 in 1st order);
    over 4 seeds × (subset 21, 31) × (order 1, 2) it missed one POI 0.061 px off. The gradient
    test is a backstop (it flagged none that the displacement test missed there). Limitation: in
    a strongly curved field the prediction over 10-20 px is not accurate to 0.03 px, so correct
    edge POIs get flagged (0.5 px sinusoid of 64 px wavelength: 35 of 86 partial POIs).

    Parameters
    ----------
    points : (N, 2) POIs ``(x, y)`` px
    params : (N, 6 | 12) warp parameters in ``PARAMS_1ST`` / ``PARAMS_2ND`` order
    order : 1 or 2, the shape-function order of ``params``
    accepted : (N,) bool, the POIs currently reported valid (only these are judged or used)
    textured_fraction : (N,) float in [0, 1], from :func:`textured_fraction`
    partial_below : float, subsets with less textured fraction are judged
    well_textured : float, subsets with at least this fraction vouch for their neighbours
    neighbours : int, how many well-textured neighbours predict each judged POI
    displacement_tol : float, px
    gradient_tol : float, dimensionless (strain/rotation)

    Returns
    -------
    (N,) bool, True where the POI is accepted but implausible.
    """
    from scipy.spatial import cKDTree

    pts = _check_points(points)
    n = pts.shape[0]
    if isinstance(order, bool) or order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order!r}")
    k_params = 6 if order == 1 else 12
    p = np.asarray(params, dtype=np.float64)
    if p.shape != (n, k_params):
        raise ValueError(f"params must be (N, {k_params}) for order {order} with N = {n} points, got shape {p.shape}")
    ok = np.asarray(accepted)
    if ok.shape != (n,) or ok.dtype != bool:
        raise ValueError(f"accepted must be an (N,) bool array with N = {n}, got {ok.dtype} of shape {ok.shape}")
    frac = np.asarray(textured_fraction, dtype=np.float64)
    if frac.shape != (n,) or not np.all((frac >= 0) & (frac <= 1)):
        raise ValueError(f"textured_fraction must be an (N,) array of values in [0, 1] with N = {n}, "
                         f"got shape {frac.shape}")
    partial_below = _check_fraction(partial_below, "partial_below")
    well_textured = _check_fraction(well_textured, "well_textured")
    if well_textured < partial_below:
        raise ValueError(f"well_textured ({well_textured}) must be >= partial_below ({partial_below})")
    if isinstance(neighbours, bool) or not isinstance(neighbours, numbers.Integral) or neighbours < 1:
        raise ValueError(f"neighbours must be a positive integer, got {neighbours!r}")
    displacement_tol = _check_positive(displacement_tol, "displacement_tol")
    gradient_tol = _check_positive(gradient_tol, "gradient_tol")

    judged = ok & (frac < partial_below)
    finite = np.all(np.isfinite(p), axis=1)
    flags = judged & ~finite  # an accepted warp that is not even finite is implausible
    judged &= finite
    vouch = ok & finite & (frac >= well_textured)
    if not np.any(judged):
        return flags
    if not np.any(vouch):
        return flags | judged
    idx = np.flatnonzero(judged)
    src = np.flatnonzero(vouch)
    k = min(int(neighbours), src.size)
    _, nn = cKDTree(pts[src]).query(pts[idx], k=k, workers=cpu_threads())
    nn = src[nn.reshape(idx.size, k)]  # (M, k) indices into the points
    first = _first_order(p, order)  # (N, 6): u, ux, uy, v, vx, vy
    value, gradient = _quadratic_prediction(pts[idx], pts[nn], first[nn].reshape(idx.size, k, 2, 3).swapaxes(2, 3))
    u_pred, v_pred = value[:, 0], value[:, 1]
    grad_pred = gradient.transpose(0, 2, 1).reshape(idx.size, 4)  # (M, 4): ux, uy, vx, vy
    mine = first[idx]
    disp_off = np.maximum(np.abs(mine[:, 0] - u_pred), np.abs(mine[:, 3] - v_pred))
    grad_off = np.max(np.abs(mine[:, [1, 2, 4, 5]] - grad_pred), axis=1)
    flags[idx] = (disp_off > displacement_tol) | (grad_off > gradient_tol)
    return flags
