"""Feature correspondences between two images and the per-POI affine guesses fitted to them.

SIFT (Lowe, IJCV 60, 2004, doi:10.1023/B:VISI.0000029664.99615.94) keypoints matched between two
images with Lowe's ratio test give sparse correspondences; :func:`affine_guess` fits, for each POI,
an affine map to the nearest ones (robust least squares). The ``"features"`` initial-guess strategy
(:mod:`.guesses`) uses both: for the stereo match left -> right and for large motions in time.
"""
from __future__ import annotations

import numpy as np

from kernels._device import as_float32_image
from kernels._launch import cpu_threads

from .order_stats import percentile

__all__ = ["feature_matches", "affine_guess", "affine_fit"]


def _image(img, name: str) -> np.ndarray:
    return as_float32_image(img, name)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    """The image's 0.5-99.5 % grey range stretched to 0-255 (float64 arithmetic, in place on one temporary)."""
    lo, hi = percentile(image, [0.5, 99.5])  # np.percentile's values (float64), faster on large images
    if not hi > lo:
        hi = lo + 1.0
    scaled = np.subtract(image, lo, dtype=np.float64)
    scaled *= 255.0 / (hi - lo)
    return np.clip(scaled, 0, 255, out=scaled).astype(np.uint8)


def _sift_matches(a: np.ndarray, b: np.ndarray, scale: int, max_features: int, ratio: float):
    import cv2

    if scale > 1:
        a = cv2.resize(a, None, fx=1.0 / scale, fy=1.0 / scale, interpolation=cv2.INTER_AREA)
        b = cv2.resize(b, None, fx=1.0 / scale, fy=1.0 / scale, interpolation=cv2.INTER_AREA)
    sift = cv2.SIFT_create(nfeatures=int(max_features))
    ka, da = sift.detectAndCompute(a, None)
    kb, db = sift.detectAndCompute(b, None)
    empty = (np.zeros((0, 2)), np.zeros((0, 2)))
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return empty
    # FLANN's randomised k-d trees draw from OpenCV's global RNG: seed it, so that the same images
    # give the same matches on every call (unseeded, a second stereo match in one process differed
    # in the last bits)
    cv2.setRNGSeed(0)
    matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    ia, ib = [], []
    for p in matcher.knnMatch(da, db, k=2):
        if len(p) == 2 and p[0].distance < ratio * p[1].distance:
            ia.append(p[0].queryIdx)
            ib.append(p[0].trainIdx)
    if not ia:
        return empty
    pa = np.array([ka[i].pt for i in ia], dtype=np.float64)
    pb = np.array([kb[i].pt for i in ib], dtype=np.float64)
    # pixel centres: x_full = (x_small + 0.5) * scale - 0.5
    return (pa + 0.5) * scale - 0.5, (pb + 0.5) * scale - 0.5


def feature_matches(image_a, image_b, *, max_features: int = 20000, ratio: float = 0.8,
                    max_pixels: float = 0.35e6, min_matches: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints of ``image_a`` matched into ``image_b`` (Lowe's ratio test, FLANN k-d trees).

    SIFT (Lowe, IJCV 60, 2004, doi:10.1023/B:VISI.0000029664.99615.94) runs on images reduced by
    an integer factor so that they hold at most about ``max_pixels`` pixels (OpenCV's SIFT
    doubles its input first; on speckle, a 1-megapixel image takes ~2.6 s at full resolution
    and ~0.5 s at 1/3, with 99.7 % of the matches within 2 px either way — measured, see
    docs/stereo.md); when fewer than ``min_matches`` matches come out, the factor is halved and
    SIFT rerun. The guesses only need to fall within a few pixels: IC-GN does the rest.

    Returns ``(points_a, points_b)``, (M, 2) float64 px of the full-resolution images (pixel
    centres at integers). M may be 0. No geometric filtering is done here.
    """
    a = _to_uint8(_image(image_a, "image_a"))
    b = _to_uint8(_image(image_b, "image_b"))
    scale = max(1, int(np.ceil(np.sqrt(max(a.size, b.size) / float(max_pixels)))))
    while True:
        pa, pb = _sift_matches(a, b, scale, max_features, ratio)
        if pa.shape[0] >= min_matches or scale == 1:
            return pa, pb
        scale //= 2


def affine_guess(points, src, dst, *, k: int = 16, radius: float = 120.0, min_matches: int = 6,
                 inlier_px: float = 2.0, iterations: int = 4, cell: float | None = None,
                 active: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-POI affine guess ``(u, ux, uy, v, vx, vy)`` from point correspondences ``src -> dst``.

    For each POI the displacement ``dst - src`` of its ``k`` nearest correspondences within
    ``radius`` px is fitted as an affine function of the offset from the POI by iteratively
    reweighted least squares (Cauchy weights, scale ``inlier_px``). A POI gets a guess when at
    least ``min_matches`` correspondences fit within ``2 inlier_px`` and they are not collinear.
    The fit is made once per square ``cell`` of side ``cell`` px (default ``radius / 6``), about
    the cell's centre, and carried to the POIs inside it through its own affine map (the
    correspondences are ~30 px apart in practice, so a denser evaluation adds nothing but time).

    ``active`` (N,) bool, optional: the POIs that need a guess (the others get none, NaN); the guesses of those
    are bit for bit the ones computed for every POI (each cell's fit is its own; whether cells are used at all is
    decided on all ``points``). E.g. a grid over the whole image of which a region is correlated.

    Returns ``params`` (N, 6) float64 (PARAMS_1ST order, NaN where no guess) and ``ok`` (N,) bool.
    """
    from scipy.spatial import cKDTree

    P = np.asarray(points, dtype=np.float64)
    S = np.asarray(src, dtype=np.float64).reshape(-1, 2)
    D = np.asarray(dst, dtype=np.float64).reshape(-1, 2)
    n = P.shape[0]
    params = np.full((n, 6), np.nan)
    if active is not None:
        active = np.asarray(active)
        if active.dtype != bool or active.shape != (n,):
            raise ValueError(f"active must be an ({n},) bool array, got {active.dtype} {active.shape}")
        if active.all():
            active = None
    if S.shape[0] < min_matches or n == 0:
        return params, np.zeros(n, dtype=bool)
    h = radius / 6.0 if cell is None else float(cell)
    if h > 0 and n > 1:
        key = np.floor(P / h).astype(np.int64)
        # the cells in np.unique(key, axis=0)'s order (rows sorted lexicographically) from one int64 key per POI:
        # the same cells and inverse, without sorting rows as structured values
        low = key.min(axis=0)
        span = int(key[:, 1].max() - low[1]) + 1
        linear, inverse = np.unique((key[:, 0] - low[0]) * span + (key[:, 1] - low[1]), return_inverse=True)
        cells = np.column_stack([linear // span + low[0], linear % span + low[1]])
        inverse = inverse.ravel()
        if cells.shape[0] < n:
            centres = (cells + 0.5) * h
            # the cells of the active POIs only (each cell's fit is computed on its own row)
            needed = None if active is None else np.unique(inverse[active])
            p_cells, ok_cells = affine_guess(centres if needed is None else centres[needed], S, D, k=k, radius=radius,
                                             min_matches=min_matches, inlier_px=inlier_px, iterations=iterations,
                                             cell=0.0)
            if needed is not None:  # back to every cell (the others: no guess)
                p_all, ok_all = np.full((cells.shape[0], 6), np.nan), np.zeros(cells.shape[0], dtype=bool)
                p_all[needed], ok_all[needed] = p_cells, ok_cells
                p_cells, ok_cells = p_all, ok_all
            d = P - centres[inverse]
            out = p_cells[inverse].copy()
            out[:, 0] += out[:, 1] * d[:, 0] + out[:, 2] * d[:, 1]
            out[:, 3] += out[:, 4] * d[:, 0] + out[:, 5] * d[:, 1]
            ok = ok_cells[inverse].copy()
            if active is not None:  # (an inactive POI in an active POI's cell: none either)
                out[~active], ok[~active] = np.nan, False
            return out, ok
    if active is not None:  # each POI's own fit, at the active ones
        rows = np.flatnonzero(active)
        p_rows, ok_rows = affine_guess(P[rows], S, D, k=k, radius=radius, min_matches=min_matches, inlier_px=inlier_px,
                                       iterations=iterations, cell=0.0)
        ok = np.zeros(n, dtype=bool)
        params[rows], ok[rows] = p_rows, ok_rows
        return params, ok
    kk = int(min(k, S.shape[0]))
    tree = cKDTree(S)
    for c0 in range(0, n, 65536):          # chunks bound the memory of the (n, k) work arrays
        sl = slice(c0, min(n, c0 + 65536))
        dist, idx = tree.query(P[sl], k=kk, distance_upper_bound=radius, workers=cpu_threads())
        dist = dist.reshape(-1, kk)
        idx = idx.reshape(-1, kk)
        have = np.isfinite(dist)
        safe = np.where(have, idx, 0)
        a = S[safe, 0] - P[sl, 0:1]           # offsets of the correspondences from the POI, px
        b = S[safe, 1] - P[sl, 1:2]
        disp = D[safe] - S[safe]              # (m, k, 2)
        # robust start: the best of 32 exact affine fits through 3 of the correspondences (a
        # vectorised RANSAC; with 40 % outliers one triple is clean with probability > 99.9 %),
        # then iteratively reweighted least squares from its inliers
        best = np.full(a.shape[0], -1)
        best_w = have.astype(np.float64)
        for t in _triples(kk):
            ok3 = np.all(have[:, t], axis=1)
            fit3 = affine_fit(np.ones((a.shape[0], 3)), a[:, t], b[:, t], disp[:, t])
            pred = fit3[0][:, None, :] + fit3[1][:, None, :] * a[..., None] + fit3[2][:, None, :] * b[..., None]
            res = np.linalg.norm(disp - pred, axis=2)
            inl = have & (res <= 2.0 * inlier_px)
            count = np.where(ok3 & fit3[3], inl.sum(axis=1), -1)
            better = count > best
            best[better] = count[better]
            best_w[better] = inl[better]
        w = np.where(best[:, None] >= 3, best_w, have.astype(np.float64))
        solvable = have.sum(axis=1) >= min_matches
        fit = None
        for _ in range(max(1, iterations)):
            fit = affine_fit(w, a, b, disp)
            solvable &= fit[3]
            pred = fit[0][:, None, :] + fit[1][:, None, :] * a[..., None] + fit[2][:, None, :] * b[..., None]
            res = np.linalg.norm(disp - pred, axis=2)
            res[~np.isfinite(res)] = 1e9
            w = have / (1.0 + (res / inlier_px) ** 2)
        inliers = have & (res <= 2.0 * inlier_px)
        good = solvable & (inliers.sum(axis=1) >= min_matches)
        c, ga, gb, _ = fit
        block = np.column_stack([c[:, 0], ga[:, 0], gb[:, 0], c[:, 1], ga[:, 1], gb[:, 1]])
        block[~good] = np.nan
        params[sl] = block
    ok = np.all(np.isfinite(params), axis=1)
    params[~ok] = np.nan
    return params, ok


def _triples(k: int, count: int = 32) -> list[np.ndarray]:
    """``count`` fixed index triples drawn from ``range(k)`` (deterministic)."""
    if k < 3:
        return []
    rng = np.random.default_rng(0)
    return [rng.choice(k, size=3, replace=False) for _ in range(count)]


def affine_fit(w: np.ndarray, a: np.ndarray, b: np.ndarray, t: np.ndarray):
    """Weighted least squares ``t ≈ c + g_a a + g_b b`` for many small problems at once.

    ``w``, ``a``, ``b``: (n, k); ``t``: (n, k, c). Returns ``(c (n, c), g_a (n, c), g_b (n, c),
    ok (n,))`` — the fit's value at ``a = b = 0`` and its gradients; ``ok`` is False (and the
    outputs NaN) where the weighted points are too few or collinear. Closed form on centred
    sums (no per-problem matrix objects: ~10x faster than batched ``np.linalg.solve`` here).
    """
    sw = w.sum(axis=1)
    inv = 1.0 / np.maximum(sw, 1e-300)
    ma = (w * a).sum(axis=1) * inv
    mb = (w * b).sum(axis=1) * inv
    mt = np.einsum("nk,nkc->nc", w, t) * inv[:, None]
    ac = a - ma[:, None]
    bc = b - mb[:, None]
    tc = t - mt[:, None, :]
    saa = (w * ac * ac).sum(axis=1)
    sab = (w * ac * bc).sum(axis=1)
    sbb = (w * bc * bc).sum(axis=1)
    sat = np.einsum("nk,nkc->nc", w * ac, tc)
    sbt = np.einsum("nk,nkc->nc", w * bc, tc)
    det = saa * sbb - sab * sab
    ok = (sw > 0) & (det > 1e-9 * (saa + sbb) ** 2) & (saa + sbb > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        inv_det = np.where(ok, 1.0 / det, np.nan)
        ga = (sbb[:, None] * sat - sab[:, None] * sbt) * inv_det[:, None]
        gb = (saa[:, None] * sbt - sab[:, None] * sat) * inv_det[:, None]
    c = mt - ga * ma[:, None] - gb * mb[:, None]
    return c, ga, gb, ok
