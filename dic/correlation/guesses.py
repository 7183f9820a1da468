"""Initial guesses for IC-GN, behind one interface and chosen by name.

An initial-guess strategy is a function ``guess(ctx, idx) -> (params (m, k), ok (m,))``: for the
POIs ``idx`` of ``ctx.correlator`` it proposes starting shape-function parameters (the correlator's
order and layout) and says which proposals exist. :func:`register_guess` adds one under a name;
:func:`get_guess` looks one up; :func:`available_guesses` lists them. Built in:

==============  ==================================================================================
``"prior"``     the prior parameters as given (the user's guess, the previous frame), zeros if none
``"zncc"``      integer ZNCC window search of radius ``ctx.search_radius`` px around the prior
``"fft"``       global integer shift by phase correlation, refined by a +-3 px ZNCC search per POI
``"pyramid"``   coarse-to-fine over a Gaussian pyramid (ZNCC search at the top, IC-GN per level)
``"rg"``        reliability-guided propagation (Pan 2009): ``"zncc"`` for a few seeds, then the
                engine (:func:`.engine.reliability_guided`) spreads from them (``propagates=True``)
``"shift"``     the prior plus the global integer shift between ``ctx.options["base"]`` and the
                current image (phase correlation); stereo temporal tracking
``"features"``  SIFT feature matches between reference and current image, an affine map fitted to
                the nearest ones (:mod:`.features`); options ``feature_filter``, ``radius``
``"epipolar"``  ZNCC search along the POI's epipolar curve in the other camera's image
                (:func:`dic.epipolar.epipolar_search`); options ``rig``, ``gradient``
==============  ==================================================================================

The strategies used by the engine's fallback (``"features"``, ``"epipolar"``) are the same
functions; docs/architecture.md says how to add one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from kernels.conventions import Status
from kernels.search import (
    phase_correlation,
    phase_correlation_spectra,
    phase_spectrum,
    pyramid,
    search_image,
    zncc_search,
)

from .acceptance import accepted_mask
from .params import convert_order, embed_first_order, n_params
from .points import grid

__all__ = ["GuessContext", "GuessStrategy", "register_guess", "get_guess", "available_guesses", "TRACKING_SEARCHES"]

#: the strategies ``Tracker(search=...)`` / ``specula track --search`` accept (besides None)
TRACKING_SEARCHES = ("zncc", "fft", "pyramid", "rg")


@dataclass
class GuessContext:
    """What an initial-guess strategy may look at.

    correlator : :class:`.engine.Correlator` (points, subset, order, device, reference subsets).
    reference, current : (H, W) float32 images (the correlator's reference and the image to track into).
    prior : (N, k) float64 parameters to start from (zeros when there is no prior).
    search_radius : int, px - the largest motion a search has to find.
    zncc_min : float - acceptance threshold (used by strategies that run IC-GN themselves).
    options : strategy-specific settings (``rig``, ``gradient``, ``base``, ``spectrum``, ``feature_filter``, ...).
    cache : per-image scratch space shared by the strategies (e.g. feature matches, computed once).
    """

    correlator: Any
    reference: np.ndarray
    current: np.ndarray
    prior: np.ndarray
    search_radius: int = 32
    zncc_min: float = 0.8
    options: dict = field(default_factory=dict)
    cache: dict = field(default_factory=dict)

    @property
    def points(self) -> np.ndarray:
        return self.correlator.points

    @property
    def order(self) -> int:
        return self.correlator.order


@dataclass(frozen=True)
class GuessStrategy:
    """A named initial-guess strategy: ``function(ctx, idx) -> (params (m, k), ok (m,))``.

    ``propagates``: the strategy only seeds a propagation that the engine runs
    (:func:`.engine.reliability_guided`); ``function`` then gives the seeds' guesses.
    """

    name: str
    function: Callable[[GuessContext, np.ndarray], tuple[np.ndarray, np.ndarray]]
    description: str = ""
    propagates: bool = False

    def __call__(self, ctx: GuessContext, idx: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        if idx is None:
            idx = np.arange(ctx.points.shape[0])
        return self.function(ctx, np.asarray(idx))


_REGISTRY: dict[str, GuessStrategy] = {}


def register_guess(name: str, *, description: str = "", propagates: bool = False):
    """Decorator: register ``function(ctx, idx) -> (params, ok)`` as the strategy ``name``."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"a guess strategy needs a non-empty name, got {name!r}")

    def deco(function):
        _REGISTRY[name] = GuessStrategy(name, function, description or (function.__doc__ or "").strip().split("\n")[0],
                                        propagates)
        return function

    return deco


def get_guess(name: str) -> GuessStrategy:
    """The registered strategy ``name``; ValueError naming the known ones otherwise."""
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown initial-guess strategy {name!r}; known: {', '.join(available_guesses())}") from None


def available_guesses() -> tuple[str, ...]:
    return tuple(_REGISTRY)


def _all_ok(m: int) -> np.ndarray:
    return np.ones(m, dtype=bool)


def _search_reference(ctx: GuessContext):
    """The reference for :func:`kernels.search.zncc_search`: uploaded once per reference (kept in the
    correlator's cache) when it is the correlator's reference, else the array itself."""
    c = ctx.correlator
    cache = getattr(c, "cache", None)
    if cache is None or ctx.reference is not getattr(c, "image", None):
        return ctx.reference
    key = ("search_reference", str(c.device))
    if key not in cache:
        cache[key] = search_image(ctx.reference, c.device, "reference")
    return cache[key]


# ----------------------------------------------------------------------------------------------
# strategies


@register_guess("prior")
def _prior(ctx: GuessContext, idx: np.ndarray):
    """The prior parameters (user guess or previous frame; zeros when none)."""
    return ctx.prior[idx].copy(), _all_ok(idx.size)


@register_guess("zncc")
def _zncc(ctx: GuessContext, idx: np.ndarray):
    """Integer ZNCC window search around the prior displacement (radius ``search_radius`` px)."""
    c = ctx.correlator
    k = n_params(c.order)
    g = ctx.prior[idx].copy()
    uv, _ = zncc_search(_search_reference(ctx), ctx.current, ctx.points[idx], ctx.search_radius, subset=c.subset,
                        start=g[:, [0, k // 2]], device=c.device)
    g[:, 0], g[:, k // 2] = uv[:, 0], uv[:, 1]
    return g, _all_ok(idx.size)


@register_guess("fft")
def _fft(ctx: GuessContext, idx: np.ndarray):
    """Global integer shift by phase correlation, refined by a +-3 px ZNCC search per POI."""
    c = ctx.correlator
    k = n_params(c.order)
    u, v, _ = phase_correlation(ctx.reference, ctx.current)
    uv, _ = zncc_search(_search_reference(ctx), ctx.current, ctx.points[idx], 3, subset=c.subset,
                        start=np.tile([u, v], (idx.size, 1)), device=c.device)
    g = np.zeros((idx.size, k))
    g[:, 0], g[:, k // 2] = uv[:, 0], uv[:, 1]
    return g, _all_ok(idx.size)


@register_guess("pyramid")
def _pyramid(ctx: GuessContext, idx: np.ndarray):
    """Coarse-to-fine 1st-order guesses over a Gaussian pyramid."""
    c = ctx.correlator
    # the reference pyramid and its level correlators are built once per reference (the correlator's cache)
    cache = getattr(c, "cache", None) if ctx.reference is getattr(c, "image", None) else None
    g1 = pyramid_guess(ctx.reference, ctx.current, ctx.points[idx], c.subset, ctx.search_radius,
                       min(ctx.zncc_min, 0.7), c.device, cache=cache)
    return convert_order(g1, c.order).copy(), _all_ok(idx.size)


@register_guess("rg", propagates=True,
                description="reliability-guided propagation from ZNCC-searched seeds (Pan 2009)")
def _rg_seeds(ctx: GuessContext, idx: np.ndarray):
    """Seeds of the reliability-guided propagation: a ZNCC search from the prior displacement."""
    c = ctx.correlator
    k = n_params(c.order)
    uv, _ = zncc_search(_search_reference(ctx), ctx.current, ctx.points[idx], ctx.search_radius, subset=c.subset,
                        start=ctx.prior[idx][:, [0, k // 2]], device=c.device)
    g = np.zeros((idx.size, k))
    g[:, 0], g[:, k // 2] = uv[:, 0], uv[:, 1]
    return g, _all_ok(idx.size)


@register_guess("shift")
def _shift(ctx: GuessContext, idx: np.ndarray):
    """The prior plus the global integer shift from ``options["base"]`` to the current image."""
    k = n_params(ctx.order)
    g = ctx.prior[idx].copy()
    base = ctx.options.get("base")
    base = ctx.reference if base is None else base
    # options["spectrum"]: a caller's phase_spectrum that keeps each image's spectrum (a sequence reuses them)
    spectrum = ctx.options.get("spectrum") or phase_spectrum
    u, v, peak = phase_correlation_spectra(spectrum(base), spectrum(ctx.current))
    # a weak peak is no evidence of a shift; 0.05 separates speckle matches from noise (measured)
    applied = bool(peak > 0.05 and (u or v))
    if applied:
        g[:, 0] += u
        g[:, k // 2] += v
    ctx.cache["shift_applied"] = applied
    return g, _all_ok(idx.size)


@register_guess("features")
def _features(ctx: GuessContext, idx: np.ndarray):
    """Affine guesses fitted to SIFT feature matches between reference and current image."""
    from .features import affine_guess, feature_matches

    if "features" not in ctx.cache:
        c = ctx.correlator
        pa, pb = feature_matches(ctx.reference, ctx.current, max_features=ctx.options.get("max_features", 20000))
        keep = ctx.options.get("feature_filter")
        if keep is not None and pa.shape[0]:
            mask = keep(pa, pb)
            pa, pb = pa[mask], pb[mask]
        ctx.cache["n_features"] = int(pa.shape[0])
        radius = ctx.options.get("radius", 6.0 * c.subset)
        # guesses where a POI can be correlated: not at the points a Correlator was told not to prepare (active=)
        prepared = c.reference_status != int(Status.NOT_COMPUTED)
        ctx.cache["features"] = affine_guess(c.points, pa, pb, radius=radius, active=prepared)
    p6, ok = ctx.cache["features"]
    g = np.zeros((idx.size, n_params(ctx.order)))
    g[ok[idx]] = embed_first_order(p6[idx][ok[idx]], ctx.order)
    return g, ok[idx]


@register_guess("epipolar")
def _epipolar(ctx: GuessContext, idx: np.ndarray):
    """ZNCC search along each POI's epipolar curve in the current (other camera's) image."""
    from dic.epipolar import epipolar_search

    c = ctx.correlator
    gradient = np.asarray(ctx.options.get("gradient", np.zeros((2, 2))), dtype=np.float64)
    uv, _, ok = epipolar_search(ctx.options["rig"], ctx.reference, ctx.current, ctx.points[idx], c.subset, gradient,
                                c.device, min_score=ctx.options.get("min_score", 0.5))
    g6 = np.zeros((idx.size, 6))
    g6[:, 0] = uv[:, 0] - ctx.points[idx, 0]
    g6[:, 3] = uv[:, 1] - ctx.points[idx, 1]
    g6[:, [1, 2, 4, 5]] = gradient.ravel()
    return embed_first_order(np.nan_to_num(g6), ctx.order), ok


# ----------------------------------------------------------------------------------------------
# the pyramid strategy's helpers


def nearest_fill(points: np.ndarray, params: np.ndarray, ok: np.ndarray, targets: np.ndarray, scale: float = 1.0):
    """Guess at ``targets`` from the nearest ``ok`` point's affine prediction (coordinates / scale).

    ``points``/``params`` live on a level whose coordinates are ``scale`` times smaller than the
    targets' (``scale = 2`` between pyramid levels); displacements are multiplied back by scale.
    Returns (M, 6) 1st-order parameters.
    """
    from scipy.spatial import cKDTree

    out = np.zeros((targets.shape[0], 6))
    if not np.any(ok):
        return out
    src = points[ok]
    p = convert_order(params[ok], 1)
    t = targets / scale
    _, idx = cKDTree(src).query(t, k=1)
    d = t - src[idx]
    pi = p[idx]
    out[:, 0] = scale * (pi[:, 0] + pi[:, 1] * d[:, 0] + pi[:, 2] * d[:, 1])
    out[:, 3] = scale * (pi[:, 3] + pi[:, 4] * d[:, 0] + pi[:, 5] * d[:, 1])
    out[:, [1, 2, 4, 5]] = pi[:, [1, 2, 4, 5]]
    return out


def median_outliers(points: np.ndarray, uv: np.ndarray, ok: np.ndarray, step: float, threshold: float) -> np.ndarray:
    """Flag points whose (u, v) differ from the median of their valid neighbours by > threshold px."""
    from scipy.spatial import cKDTree

    if np.count_nonzero(ok) < 5:
        return ok
    src = points[ok]
    tree = cKDTree(src)
    neigh = tree.query_ball_point(points, r=1.5 * step)
    ok = ok.copy()
    vals = uv[ok]
    for i, nb in enumerate(neigh):
        if not ok[i] or len(nb) < 4:
            continue
        med = np.median(vals[nb], axis=0)
        if np.max(np.abs(uv[i] - med)) > threshold:
            ok[i] = False
    return ok


def pyramid_guess(ref: np.ndarray, cur: np.ndarray, targets: np.ndarray, subset: int, radius: int,
                  zncc_min: float, device: str, cache: dict | None = None) -> np.ndarray:
    """Coarse-to-fine 1st-order guesses at ``targets`` (Gaussian pyramid, ZNCC search at the top).

    Levels: the coarsest level sees motions up to ``radius / 2^L <= 4`` px, limited so that the
    coarsest image still holds a few subsets. At the top a ZNCC window search seeds IC-GN on a grid
    of step ``subset // 2``; each finer level re-runs IC-GN from the nearest valid coarse result
    (outliers removed by a neighbourhood-median test), and the final level's field predicts
    ``targets``. Returns (M, 6) 1st-order parameters.

    ``cache``: a dict kept with the reference (:attr:`.engine.Correlator.cache`); the reference
    pyramid and the per-level correlators (their prepared subsets) are built on the first call and
    reused by the next ones with the same reference, subset, levels and device (bitwise the same
    guesses; only the current image's pyramid is built per call).
    """
    from .engine import Correlator

    if cache is not None and not isinstance(cache, dict):
        raise ValueError(f"cache must be a dict (e.g. Correlator.cache) or None, got {type(cache).__name__}")

    # a radius beyond twice the image finds nothing more (the ZNCC search clamps its window to the
    # image, kernels.search.useful_radius) and picks the same levels: clamp it, so that any int works
    radius = min(int(radius), 2 * max(ref.shape))
    levels = max(0, math.ceil(math.log2(max(radius, 1) / 4.0)))
    while levels > 0 and min(ref.shape) / 2 ** levels < 2 * subset + 1:
        levels -= 1
    r = subset // 2
    step = max(2, subset // 2)
    key = ("pyramid", ref.shape, int(subset), levels, str(device))
    built = None if cache is None else cache.get(key)
    if built is None:
        pr = pyramid(ref, levels, device=device)
        # one correlator per level (reference subsets prepared once), built on first use
        built = (pr, {}, {})
        if cache is not None:
            cache[key] = built
    pr, level_correlators, searched = built

    def uploaded(lvl: int):  # the reference level for the ZNCC search, uploaded once
        if lvl not in searched:
            searched[lvl] = search_image(pr[lvl], device, "reference")
        return searched[lvl]

    pc = pyramid(cur, levels, device=device)
    prev = None  # (points, params, ok) at the coarser level
    for lvl in range(levels, 0, -1):
        img_r, img_c = pr[lvl], pc[lvl]
        pts = grid(img_r.shape, step, margin=r)
        if prev is None:
            top = int(math.ceil(radius / 2 ** lvl)) + 1
            uv, _ = zncc_search(uploaded(lvl), img_c, pts, top, subset=subset, device=device)
            g = np.zeros((pts.shape[0], 6))
            g[:, 0], g[:, 3] = uv[:, 0], uv[:, 1]
        else:
            g = nearest_fill(*prev, pts, scale=2.0)
        level = level_correlators.get(lvl)
        if level is None:
            level = level_correlators[lvl] = Correlator(img_r, pts, subset=subset, order=1, max_iter=30, tol=1e-3,
                                                        device=device)
        res = level.run_all(img_c, g)
        p = res["params"].astype(np.float64)
        ok = accepted_mask(res["status"], res["zncc"], zncc_min)
        ok = median_outliers(pts, p[:, [0, 3]], ok, step, threshold=2.0)
        prev = (pts, p, ok)
    if prev is None:  # no pyramid level: a ZNCC search at full resolution
        uv, _ = zncc_search(uploaded(0), cur, targets, radius, subset=subset, device=device)
        g = np.zeros((targets.shape[0], 6))
        g[:, 0], g[:, 3] = uv[:, 0], uv[:, 1]
        return g
    return nearest_fill(*prev, targets, scale=2.0)
