"""Measurement uncertainty and speckle quality: per-POI displacement sigma, image noise, MIG, SSSIG.

**Uncertainty.** IC-GN/ZNSSD (:mod:`kernels.icgn`) solves ``H dq = -sum J^T e`` with the
Hessian ``H = sum (J - Jm)^T (J - Jm)`` of the reference subset and the residual
``e = (f - fm) - (df/dg)(g - gm)``. With white noise of variance ``s2`` per pixel in ``e``, the
parameters near convergence have the covariance ``s2 H^-1``, so

    sigma_u = sqrt(s2 (H^-1)_uu),   sigma_v = sqrt(s2 (H^-1)_vv)   (px)

with ``s2 = 2 sigma_noise^2`` for independent noise of std ``sigma_noise`` (grey levels) in both
images. ``H^-1`` is read from the prepared reference subsets (the packed table IC-GN itself uses;
``u`` and ``v`` are unscaled parameters), so the 2nd-order shape function's larger uncertainty comes
out of the same formula. ``s2`` is either given (``noise_sigma``) or estimated from the converged
subsets' residuals: ``sum e^2 = 2 df^2 (1 - ZNCC)`` per subset, divided by its degrees of freedom
``S^2 - k - 2`` (k warp parameters, offset and scale), pooled as the median over the valid POIs.
Derivation and measured ratios: docs/dic2d.md, "Uncertainty".

**Speckle quality.** Per POI the mean intensity gradient (MIG, Pan et al. 2010,
doi:10.1016/j.optlaseng.2009.08.010) ``mean_subset |grad f|`` and the sums of squared subset
intensity gradients (SSSIG, Pan et al. 2008, doi:10.1016/j.optlaseng.2007.11.004)
``sum_subset f_x^2``, ``sum_subset f_y^2``, with the B-spline gradients IC-GN uses;
:func:`suggest_subset` gives the smallest odd subset whose predicted sigma meets a target.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kernels._device import resolve_device
from kernels.checks import positive_float, positive_int, unit_interval
from kernels.conventions import Status, round_half_away
from kernels.icgn import check_subset_order, n_params
from kernels.images import as_float32_image, read_image

from .correlation.engine import Correlator
from .correlation.points import grid, region

__all__ = ["NOISE_SOURCES", "estimate_noise", "hessian_inverse_uv", "residual_variance", "displacement_sigma",
           "SigmaBasis", "sigma_basis", "triangulation_jacobian", "propagate_stereo_sigma", "predicted_sigma", "SpeckleQuality", "speckle_quality", "SubsetSuggestion", "suggest_subset"]

#: how the noise behind a field's ``sigma_u``/``sigma_v`` was obtained
NOISE_SOURCES = ("given", "residual")

_LAPLACE_DIFF = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])


def _image(image, name: str) -> np.ndarray:
    if isinstance(image, (str, bytes)) or hasattr(image, "__fspath__"):
        image = read_image(image)
    arr = as_float32_image(image, name)
    if arr.shape[0] < 4 or arr.shape[1] < 4:
        raise ValueError(f"{name} must be at least 4x4 pixels, got shape {arr.shape}")
    return arr


def _fraction(value, name: str) -> float:
    v = unit_interval(value, name)
    if not v > 0:
        raise ValueError(f"{name} must be in (0, 1], got {value!r}")
    return v


#: the largest image noise accepted, grey levels (far beyond a 16-bit camera's range of 65535; the
#: uncertainty squares it)
MAX_NOISE_SIGMA = 1e6


def check_noise_sigma(noise_sigma) -> float | None:
    """None, or a finite grey-level standard deviation > 0 and at most :data:`MAX_NOISE_SIGMA` (ValueError
    otherwise)."""
    if noise_sigma is None:
        return None
    value = positive_float(noise_sigma, "noise_sigma", detail=" (grey levels)")
    if value > MAX_NOISE_SIGMA:
        raise ValueError(f"noise_sigma must be at most {MAX_NOISE_SIGMA:g} grey levels, got {noise_sigma!r}")
    return value


#: a ``second`` image whose motion would raise the noise measured from the difference by more than this factor
#: is refused (:func:`estimate_noise`): 1.05, i.e. a bias of 5 %
MOTION_NOISE_FACTOR = 1.05


def _motion_between(f: np.ndarray, g: np.ndarray, d: np.ndarray) -> tuple[float, float, float]:
    """``(dx, dy, residual_std)``: the shift of ``g`` relative to ``f`` (px) and the std of the difference once the
    shift is removed. Phase correlation (OpenCV, Hann window) finds shifts from about half a pixel up; below
    that, one global gradient fit ``f - g = gx dx + gy dy`` (least squares, the outliers of ``d`` excluded)."""
    import cv2
    from scipy.ndimage import sobel

    window = cv2.createHanningWindow((f.shape[1], f.shape[0]), cv2.CV_64F)
    (dx, dy), _ = cv2.phaseCorrelate(f, g, window)
    if np.hypot(dx, dy) >= 0.5:
        return float(dx), float(dy), float("nan")
    gx, gy = sobel(f, 1) / 8.0, sobel(f, 0) / 8.0  # grey levels per px
    inner = (slice(1, -1), slice(1, -1))
    a = np.column_stack([gx[inner].ravel(), gy[inner].ravel(), np.ones(gx[inner].size)])
    b = (f - g)[inner].ravel()
    keep = np.abs(b - np.median(b)) <= 5.0 * d.std() if d.std() > 0 else np.ones(b.size, bool)
    coef, *_ = np.linalg.lstsq(a[keep], b[keep], rcond=None)
    residual = b[keep] - a[keep] @ coef
    return float(coef[0]), float(coef[1]), float(residual.std())


def estimate_noise(image, second=None, *, flat_fraction: float = 0.1, check_motion: bool = True) -> float:
    """Grey-level noise standard deviation of one image (or of a pair of images of a static specimen).

    Parameters
    ----------
    image : (H, W) grey image (array, path or torch tensor).
    second : optional second image of the same, unmoved scene (e.g. two reference shots). Then
        the noise is ``std(image - second) / sqrt(2)`` (after dropping differences beyond 5 std):
        texture cancels and the estimate is unbiased (8-bit rounding included). This is the recommended way to measure a camera's noise.
        With ``check_motion`` (default) a ``second`` image moved relative to ``image`` is refused
        (``ValueError`` with the shift): when removing one global shift would lower the measured noise
        by more than 5 % (:data:`MOTION_NOISE_FACTOR`; on a 256 x 256 synthetic 8-bit pair with a noise of
        2 grey levels: 2.02 unmoved, 2.36 for a 0.05 px shift), or the images are half a pixel or more apart.
    flat_fraction : float in (0, 1]
        Without ``second``: Immerkaer's estimator (the 3x3 Laplacian-difference mask,
        doi:10.1006/cviu.1996.0060) averaged over the ``flat_fraction`` of pixels with the lowest
        Sobel gradient. On sharp speckle the texture still leaks in, so this is an **upper bound**:
        measured on 8-bit synthetic speckle, 1.1 / 1.6 / 2.4 / 4.3 grey levels for a true noise of
        0 / 1 / 2 / 4 (docs/dic2d.md, "Uncertainty").

    Returns
    -------
    float : grey levels (the image's scale).
    """
    from scipy.ndimage import convolve, sobel

    f = _image(image, "image").astype(np.float64)
    if second is not None:
        g = _image(second, "second").astype(np.float64)
        if g.shape != f.shape:
            raise ValueError(f"second image has shape {g.shape} but image has shape {f.shape}")
        d = (f - g).ravel()
        d = d - np.median(d)
        keep = np.ones(d.size, dtype=bool)
        for _ in range(3):  # drop outliers (specular spots, dust) beyond 5 std, then re-estimate
            s = d[keep].std()
            keep = np.abs(d) <= 5.0 * s if s > 0 else keep
        noise = float(d[keep].std() / np.sqrt(2.0))
        if check_motion and noise > 0 and min(f.shape) >= 8:
            dx, dy, residual = _motion_between(f, g, d[keep])
            moved = np.hypot(dx, dy) >= 0.5 or noise > MOTION_NOISE_FACTOR * residual / np.sqrt(2.0)
            if moved:
                effect = "" if not np.isfinite(residual) else \
                    f" ({noise:.3g} grey levels where the unmoved part of the difference gives {residual / np.sqrt(2.0):.3g})"
                raise ValueError(
                    f"the second image is moved by about ({dx:.3g}, {dy:.3g}) px relative to the first: the noise "
                    f"measured from their difference would include the motion{effect}. Give a second shot of the "
                    "unmoved specimen, or the noise itself (noise_sigma / --noise-sigma)")
        return noise
    flat_fraction = _fraction(flat_fraction, "flat_fraction")
    c = convolve(f, _LAPLACE_DIFF, mode="reflect")[1:-1, 1:-1]
    g = np.hypot(sobel(f, 0), sobel(f, 1))[1:-1, 1:-1]
    sel = g <= np.quantile(g, flat_fraction)
    return float(np.sqrt(np.pi / 2.0) * np.abs(c[sel]).mean() / 6.0)


def hessian_inverse_uv(subsets, *, cross: bool = False) -> np.ndarray:
    """(N, 2) float64 ``[(H^-1)_uu, (H^-1)_vv]`` per POI from prepared subsets (px^2 per grey level^2);
    ``cross=True``: (N, 3) ``[(H^-1)_uu, (H^-1)_vv, (H^-1)_uv]`` (the u-v covariance's factor).

    ``subsets`` is a :class:`kernels.icgn.ReferenceSubsets` (``prepare_subsets``); the values are
    read from its packed ``H^-1`` table. NaN where the subset is not ready (out of bounds, flat,
    singular).
    """
    from kernels.icgn import ReferenceSubsets, refdata_columns

    if not isinstance(subsets, ReferenceSubsets):
        raise ValueError(f"subsets must be a kernels.icgn.ReferenceSubsets, got {type(subsets).__name__}")
    k = n_params(subsets.order)
    table = subsets.refdata.numpy()
    ready = subsets.status.numpy() == int(Status.CONVERGED)
    out = np.full((table.shape[0], 3 if cross else 2), np.nan)
    # entries (row, col) of the packed upper triangle (row-major) of u (0) and v (k // 2): unscaled parameters
    entries = ((0, 0), (k // 2, k // 2), (0, k // 2))[:out.shape[1]]
    for j, (row, col) in enumerate(entries):
        at = refdata_columns(subsets.order).hinv + row * k - row * (row - 1) // 2 + (col - row)
        out[ready, j] = table[ready, at]
    return out


def residual_variance(zncc, fnorm, subset: int, order: int) -> np.ndarray:
    """(N,) residual variance per subset pixel (grey levels^2) from ZNCC: ``2 df^2 (1 - ZNCC) / (S^2 - k - 2)``.

    ``fnorm`` is the reference subset's ``df = sqrt(sum (f - fm)^2)`` (the column
    ``kernels.icgn.RefdataColumns.fnorm`` of the prepared subsets' table).
    """
    subset, order = check_subset_order(subset, order)
    z = np.asarray(zncc, dtype=np.float64)
    df = np.asarray(fnorm, dtype=np.float64)
    if z.shape != df.shape:
        raise ValueError(f"zncc and fnorm must have the same shape, got {z.shape} and {df.shape}")
    dof = subset * subset - n_params(order) - 2
    return 2.0 * df ** 2 * np.clip(1.0 - z, 0.0, None) / dof


@dataclass(frozen=True)
class SigmaBasis:
    """What the uncertainty needs from prepared subsets, read back once (:func:`sigma_basis`).

    hinv_uv (N, 2): ``(H^-1)_uu, (H^-1)_vv`` (NaN where not ready); fnorm (N,): ``df`` of each
    reference subset; subset, order; rho_uv (N,): the correlation coefficient of the u and v
    errors, ``(H^-1)_uv / sqrt((H^-1)_uu (H^-1)_vv)`` (independent of the noise; None: taken as 0).
    """

    hinv_uv: np.ndarray
    fnorm: np.ndarray
    subset: int
    order: int
    rho_uv: np.ndarray | None = None


def sigma_basis(subsets) -> SigmaBasis:
    """Read ``diag H^-1`` of u, v and ``df`` from a :class:`kernels.icgn.ReferenceSubsets` once (one host copy)."""
    from kernels.icgn import refdata_columns

    hinv = hessian_inverse_uv(subsets, cross=True)
    fnorm = subsets.refdata.numpy()[:, refdata_columns(subsets.order).fnorm].astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = hinv[:, 2] / np.sqrt(hinv[:, 0] * hinv[:, 1])
    return SigmaBasis(hinv[:, :2].copy(), fnorm, subsets.subset, subsets.order, rho_uv=rho)


def displacement_sigma(subsets, zncc=None, valid=None, noise_sigma=None) -> tuple[np.ndarray, float, str]:
    """Per-POI displacement standard deviation ``(sigma_u, sigma_v)`` of one tracked image.

    Parameters
    ----------
    subsets : kernels.icgn.ReferenceSubsets of the tracked POIs, or its :class:`SigmaBasis`
        (read once and reused for every image of a sequence: no device-to-host copy per image).
    zncc, valid : (N,) the tracking result (needed when ``noise_sigma`` is None).
    noise_sigma : float, optional - grey-level noise std of each image; default: estimated from
        the residuals of the valid POIs.

    Returns
    -------
    (sigma (N, 2) px, NaN where the subset is not ready or, if ``valid`` is given, not valid;
    noise_sigma (grey levels, per image; NaN when estimated and no POI is valid);
    source "given" or "residual")
    """
    noise_sigma = check_noise_sigma(noise_sigma)
    basis = subsets if isinstance(subsets, SigmaBasis) else sigma_basis(subsets)
    hinv = basis.hinv_uv
    n = hinv.shape[0]
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != (n,):
            raise ValueError(f"valid must have shape ({n},), got {valid.shape}")
    if noise_sigma is not None:
        s2, source = 2.0 * noise_sigma ** 2, "given"
    else:
        if zncc is None or valid is None:
            raise ValueError("give noise_sigma, or zncc and valid to estimate it from the residuals")
        z = np.asarray(zncc, dtype=np.float64)
        if z.shape != (n,):
            raise ValueError(f"zncc must have shape ({n},), got {z.shape}")
        r2 = residual_variance(np.nan_to_num(z, nan=-1.0), basis.fnorm, basis.subset, basis.order)
        use = valid & np.isfinite(r2) & np.all(np.isfinite(hinv), axis=1)
        s2 = float(np.median(r2[use])) if use.any() else np.nan
        source = "residual"
    with np.errstate(invalid="ignore"):
        sigma = np.sqrt(s2 * hinv)
    if valid is not None:
        sigma[~valid] = np.nan
    return sigma, float(np.sqrt(s2 / 2.0)), source


def triangulation_jacobian(triangulate, points_left, points_right, step_px: float = 0.05) -> np.ndarray:
    """(N, 3, 4) derivatives of triangulated points by ``(x_left, y_left, x_right, y_right)`` (central differences).

    ``triangulate(points_left, points_right) -> (N, 3)`` is the stereo layer's triangulation;
    rows with a non-finite input or output are NaN.
    """
    pl = np.asarray(points_left, dtype=np.float64)
    pr = np.asarray(points_right, dtype=np.float64)
    if pl.ndim != 2 or pl.shape[1] != 2 or pr.shape != pl.shape:
        raise ValueError(f"points_left and points_right must both have shape (N, 2), got {pl.shape} and {pr.shape}")
    h = positive_float(step_px, "step_px", detail=" (px)")
    jac = np.empty((pl.shape[0], 3, 4))
    for c in range(4):
        d = np.zeros((pl.shape[0], 4))
        d[:, c] = h
        plus = np.asarray(triangulate(pl + d[:, :2], pr + d[:, 2:]), dtype=np.float64)
        minus = np.asarray(triangulate(pl - d[:, :2], pr - d[:, 2:]), dtype=np.float64)
        jac[:, :, c] = (plus - minus) / (2.0 * h)
    return jac


def propagate_stereo_sigma(jac_ref, sigma_match, jac_cur=None, sigma_left=None, sigma_right=None,
                           rotation=None, *, rho_match=None, rho_left=None,
                           rho_right=None) -> tuple[np.ndarray, np.ndarray | None]:
    """Std (mm) of the reference positions ``X, Y, Z`` and of the displacements ``U, V, W`` of stereo DIC.

    The left reference POI is exact; the match puts the right reference point at ``p_r + e_m``;
    the tracks put the current points at ``p_l + d_l + e_l`` and ``p_r + e_m + d_r + e_r`` (the
    right track follows the texture at the matched point, so the match error moves with it).
    With ``A = dX/dp_left``, ``B = dX/dp_right`` (``jac`` columns 0-1 and 2-3) of the reference
    (``ref``) and current (``cur``) state and (u, v) errors of std ``sigma_*`` (N, 2) px whose u and v
    are correlated with coefficient ``rho_*`` (N,) (:attr:`SigmaBasis.rho_uv`; None or NaN: 0),
    ``S = [[su^2, rho su sv], [rho su sv, sv^2]]``, independent between the three correlations:

        Cov(X_ref) = B_ref S_m B_ref^T
        Cov(U)     = A_cur S_l A_cur^T + B_cur S_r B_cur^T + (B_cur - B_ref) S_m (B_cur - B_ref)^T

    ``rotation`` (3, 3): the output frame's rotation from the left camera frame. Returns
    ``(sigma_xyz (N, 3), sigma_uvw (N, 3) or None)``; NaN where an input is NaN.
    """
    # closed-form 2x2 / 3x3 products on per-entry columns (N,): bit for bit the generic contractions
    # einsum("nik,nkl,njl->nij", J, S, J) and einsum("ik,nkl,il->ni", R, C, R) (the same products, (a * b) * c,
    # summed from 0 over k then l; tests/dic/test_quality.py), ~10x faster on 20 k points
    def cov(j, s, rho):
        s = np.asarray(s, dtype=np.float64)
        n = s.shape[0]
        S = [[s[:, 0] ** 2, np.zeros(n)], [np.zeros(n), s[:, 1] ** 2]]
        if rho is not None:
            r = np.nan_to_num(np.asarray(rho, dtype=np.float64), nan=0.0)
            if r.shape != s.shape[:1]:
                raise ValueError(f"rho must have shape {s.shape[:1]}, got {r.shape}")
            S[0][1] = S[1][0] = r * s[:, 0] * s[:, 1]
        J = [[np.ascontiguousarray(j[:, i, k]) for k in range(2)] for i in range(3)]
        return [[_sum_of_products(((J[a][k] * S[k][m], J[b][m]) for k in range(2) for m in range(2)))
                 for b in range(3)] for a in range(3)]

    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)

    def sigma(c):
        return np.sqrt(np.stack([_sum_of_products(((R[i, k] * c[k][m], R[i, m]) for k in range(3) for m in range(3)))
                                 for i in range(3)], axis=1))

    def add(*cs):  # (c_1 + c_2) + c_3 entry by entry
        return [[_add_all([c[a][b] for c in cs]) for b in range(3)] for a in range(3)]

    b_ref = jac_ref[:, :, 2:]
    xyz = sigma(cov(b_ref, sigma_match, rho_match))
    if jac_cur is None:
        return xyz, None
    b_cur = jac_cur[:, :, 2:]
    c = add(cov(jac_cur[:, :, :2], sigma_left, rho_left), cov(b_cur, sigma_right, rho_right),
            cov(b_cur - b_ref, sigma_match, rho_match))
    return xyz, sigma(c)


def _sum_of_products(pairs) -> np.ndarray:
    """``0 + x_1 * y_1 + x_2 * y_2 + ...`` in that order (what einsum's inner loop sums), per column."""
    out = None
    for x, y in pairs:
        p = x * y
        out = 0.0 + p if out is None else np.add(out, p, out=out)
    return out


def _add_all(columns) -> np.ndarray:
    out = columns[0] + columns[1]
    for c in columns[2:]:
        out += c
    return out


def _correlator(ref: np.ndarray, pts: np.ndarray, subset: int, order: int, device) -> Correlator:
    """The correlation core's reference work (gradients, per-POI H^-1) for these POIs; IC-GN limits unused."""
    return Correlator(ref, pts, subset=subset, order=order, max_iter=30, tol=1e-3, device=resolve_device(device))


def _points(shape, subset: int, points, step, roi) -> np.ndarray:
    if points is not None:
        if roi is not None:
            raise ValueError("give either points or roi (roi selects grid points), not both")
        from kernels.checks import as_points

        return as_points(points)
    step = max(1, subset // 2) if step is None else positive_int(step, "step", detail=" (px)")
    return grid(shape, step, margin=subset // 2, roi=roi)


def predicted_sigma(reference, subset: int = 21, order: int = 1, noise_sigma=None, *, points=None, step=None,
                    roi=None, device=None) -> tuple[np.ndarray, np.ndarray]:
    """Predicted displacement std per POI for a subset size, before tracking: ``sqrt(2 noise^2 diag H^-1)``.

    ``noise_sigma`` default: :func:`estimate_noise` of the reference (an upper bound on sharp speckle).
    Returns ``(points (N, 2), sigma (N, 2) px)``; inf where the subset is flat or singular, NaN
    where it leaves the image.
    """
    ref = _image(reference, "reference")
    subset, order = check_subset_order(subset, order)
    noise = check_noise_sigma(noise_sigma)
    noise = estimate_noise(ref) if noise is None else noise
    pts = _points(ref.shape, subset, points, step, roi)
    subsets = _correlator(ref, pts, subset, order, device).subsets
    sigma = np.sqrt(2.0 * noise ** 2 * hessian_inverse_uv(subsets))
    st = subsets.status.numpy()
    sigma[(st == int(Status.FLAT_SUBSET)) | (st == int(Status.SINGULAR_HESSIAN))] = np.inf
    return pts, sigma


@dataclass
class SpeckleQuality:
    """Speckle-quality measures of a reference image (:func:`speckle_quality`).

    points (N, 2) px; mig (N,) mean |grad f| over each subset (grey levels / px); sssig_x,
    sssig_y (N,) sums of squared x / y gradients over each subset (grey levels^2 / px^2);
    image_mig: MIG of the whole image; subset: subset size (px); noise_sigma: grey levels (given
    or :func:`estimate_noise`); sigma_1st (N, 2) px: the 1st-order prediction
    ``sqrt(2 noise^2 diag H^-1)``.
    """

    points: np.ndarray
    mig: np.ndarray
    sssig_x: np.ndarray
    sssig_y: np.ndarray
    image_mig: float
    subset: int
    noise_sigma: float
    sigma_1st: np.ndarray = field(repr=False, default=None)

    def summary(self) -> dict[str, float]:
        """Median and 5th percentile of MIG and SSSIG (the weakest subsets matter), and the image MIG."""
        sss = np.minimum(self.sssig_x, self.sssig_y)
        return {"image_mig": self.image_mig, "mig_median": float(np.median(self.mig)),
                "mig_p5": float(np.percentile(self.mig, 5)), "sssig_median": float(np.median(sss)),
                "sssig_p5": float(np.percentile(sss, 5)), "noise_sigma": self.noise_sigma}


def _box_sum(a: np.ndarray, cx: np.ndarray, cy: np.ndarray, r: int) -> np.ndarray:
    s = np.zeros((a.shape[0] + 1, a.shape[1] + 1))
    s[1:, 1:] = np.cumsum(np.cumsum(a, axis=0), axis=1)
    x0, x1, y0, y1 = cx - r, cx + r + 1, cy - r, cy + r + 1
    return s[y1, x1] - s[y0, x1] - s[y1, x0] + s[y0, x0]


def speckle_quality(reference, subset: int = 21, *, points=None, step=None, roi=None, noise_sigma=None,
                    device=None) -> SpeckleQuality:
    """MIG and SSSIG per POI (subsets of ``subset`` px, B-spline gradients as in IC-GN), and the predicted sigma.

    POIs: ``points``, or a grid of ``step`` (default ``subset // 2``) inside ``roi`` with every subset in the image.
    """
    ref = _image(reference, "reference")
    subset, _ = check_subset_order(subset, 1)
    noise = check_noise_sigma(noise_sigma)
    noise = estimate_noise(ref) if noise is None else noise
    pts = _points(ref.shape, subset, points, step, roi)
    h, w = ref.shape
    r = subset // 2
    c = round_half_away(pts).astype(np.int64)  # the kernels' subset centres
    if np.any((c[:, 0] - r < 0) | (c[:, 1] - r < 0) | (c[:, 0] + r > w - 1) | (c[:, 1] + r > h - 1)):
        raise ValueError(f"every subset of {subset} px must lie inside the {w}x{h} image; move the points "
                         "away from the border or use a smaller subset")
    corr = _correlator(ref, pts, subset, 1, device)
    fg = corr.reference.fgrad.numpy().reshape(h, w, 3).astype(np.float64)
    gx, gy = fg[..., 1], fg[..., 2]
    mag = np.hypot(gx, gy)
    npx = subset * subset
    mig = _box_sum(mag, c[:, 0], c[:, 1], r) / npx
    sx = _box_sum(gx * gx, c[:, 0], c[:, 1], r)
    sy = _box_sum(gy * gy, c[:, 0], c[:, 1], r)
    image_mig = float(mag.mean())
    sigma = np.sqrt(2.0 * noise ** 2 * hessian_inverse_uv(corr.subsets))
    return SpeckleQuality(pts, mig, sx, sy, image_mig, subset, float(noise), sigma)


@dataclass
class SubsetSuggestion:
    """Result of :func:`suggest_subset`.

    subset: the smallest odd size meeting the target (None if none of the sizes tried does);
    target_sigma_px, coverage, order, noise_sigma: the inputs (noise estimated if not given);
    tried: {subset: predicted sigma (px) at the ``coverage`` quantile over the POIs}.
    """

    subset: int | None
    target_sigma_px: float
    coverage: float
    order: int
    noise_sigma: float
    tried: dict = field(default_factory=dict)


def suggest_subset(reference, target_sigma_px: float, noise_sigma=None, *, order: int = 1, coverage: float = 0.95,
                   step: int = 10, roi=None, min_subset: int = 7, max_subset: int = 101,
                   device=None) -> SubsetSuggestion:
    """The smallest odd subset whose predicted displacement std meets ``target_sigma_px`` at ``coverage`` of the POIs.

    For each odd size from ``min_subset`` up, the POIs of a grid of ``step`` px (inside ``roi``)
    get ``max(sigma_u, sigma_v) = sqrt(2 noise^2 max diag H^-1)`` (:func:`predicted_sigma`; flat
    subsets count as missing the target); the first size whose ``coverage`` quantile is within the
    target is returned. ``noise_sigma`` default: :func:`estimate_noise` of the reference (an upper
    bound on sharp speckle, so the suggestion errs on the large side; measure the noise from two
    images of the static specimen with ``estimate_noise(a, b)`` for a tighter one).
    """
    ref = _image(reference, "reference")
    target = positive_float(target_sigma_px, "target_sigma_px", detail=" (px)")
    coverage = _fraction(coverage, "coverage")
    _, order = check_subset_order(21, order)
    step = positive_int(step, "step", detail=" (px)")
    lo, _ = check_subset_order(min_subset, 1)
    hi, _ = check_subset_order(max_subset, 1)
    if hi < lo:
        raise ValueError(f"max_subset ({hi}) must be >= min_subset ({lo})")
    noise = check_noise_sigma(noise_sigma)
    roi = region(roi, ref.shape)  # checked once (a mask file read once); exclusions included
    grid(ref.shape, step, margin=lo // 2, roi=roi)  # a bad ROI or an image too small fails here, with its reason
    noise = estimate_noise(ref) if noise is None else noise
    out = SubsetSuggestion(None, target, coverage, order, float(noise))
    for s in range(lo, hi + 1, 2):
        if s > min(ref.shape):
            break
        try:
            pts = grid(ref.shape, step, margin=s // 2, roi=roi)
        except ValueError:
            break  # no POI of the ROI keeps its subset inside the image any more
        sig = np.sqrt(2.0 * noise ** 2 * hessian_inverse_uv(_correlator(ref, pts, s, order, device).subsets)).max(axis=1)
        sig[~np.isfinite(sig)] = np.inf
        q = float(np.quantile(sig, coverage))
        out.tried[s] = q
        if q <= target:
            out.subset = s
            break
    return out
