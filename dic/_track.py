"""2-D subset DIC: track POIs of a reference image into current images, as :class:`Field2D` results.

A thin layer over the correlation core (:mod:`dic.correlation`), which 2-D tracking shares with
stereo DIC: POIs and ROIs (:mod:`dic.correlation.points`), initial guesses chosen by name
(:mod:`dic.correlation.guesses`: ZNCC window search, FFT phase correlation, Gaussian-pyramid
coarse-to-fine, reliability-guided propagation after Pan et al. 2009, doi:10.1364/AO.48.001535,
SIFT features), IC-GN (:mod:`kernels.icgn`: ZNSSD, 1st and 2nd order, Pan et al. 2013,
doi:10.1007/s11340-012-9640-x; Gao et al. 2015, doi:10.1016/j.optlaseng.2014.04.002) and
acceptance (:mod:`dic.correlation.acceptance`). This module validates the user's input and packs
the results. See docs/dic2d.md for the algorithm, parameters and measured accuracy.

Conventions (docs/conventions.md): points ``(x, y)`` in reference pixels (pixel (0, 0) is the
centre of the top-left pixel), displacements ``(u, v)`` in pixels, parameters in
:data:`kernels.conventions.PARAMS_1ST` / ``PARAMS_2ND`` order, statuses :class:`Status`.
"""
from __future__ import annotations

import os

import numpy as np

from kernels._device import resolve_device
from kernels.checks import as_points, boolean, in_range, non_negative_int
from kernels.conventions import Status
from kernels.icgn import check_max_iter, check_subset_order, n_params, prepare_current
from kernels.icgn_masked import DEFAULT_MIN_KEPT_FRACTION
from kernels.images import as_float32_image, as_float32_tensor, is_torch_tensor, read_image

from .correlation.acceptance import accepted_mask, flag_implausible, status_counts, warn_if_mostly_invalid
from .correlation.engine import ADAPTIVE, Correlator, check_robust, reliability_guided
from .correlation.guesses import TRACKING_SEARCHES, GuessContext, available_guesses, get_guess
from .correlation.lagrangian import displacement_outliers
from .correlation.params import check_tol, guess_params
from .correlation.points import check_step, grid
from .correlation.subset_masks import check_min_kept_fraction, check_subset_mask, tracking_pixel_masks
from .field2d import Field2D
from .quality import check_noise_sigma, displacement_sigma, sigma_basis

__all__ = ["Field2D", "Tracker", "grid", "track", "SEARCH_METHODS"]

#: initial-guess strategies offered by ``search=`` / ``specula track --search`` (any name registered
#: in :mod:`dic.correlation.guesses` that needs no stereo rig is accepted too, e.g. "features")
SEARCH_METHODS = TRACKING_SEARCHES


def _as_image(image, name: str) -> np.ndarray:
    """Path, NumPy array (8/16-bit, float) or torch tensor -> float32 (H, W), validated."""
    if isinstance(image, (str, os.PathLike)):
        image = read_image(image)
    arr = as_float32_image(image, name)
    if arr.shape[0] < 4 or arr.shape[1] < 4:
        raise ValueError(f"{name} must be at least 4x4 pixels, got shape {arr.shape}")
    return arr


def _device_resident(image) -> bool:
    """Whether ``image`` goes through the device-resident frame path: a 2-D uint8, uint16 or float32 NumPy
    array of at least 4x4 pixels (other dtypes, masked arrays and tensors take the general path)."""
    return (type(image) is np.ndarray and image.ndim == 2 and image.dtype in (np.uint8, np.uint16, np.float32)
            and min(image.shape) >= 4)


def _check_search(search):
    if search is None:
        return None
    names = tuple(n for n in available_guesses() if n != "epipolar")
    if not isinstance(search, str) or search not in names:
        raise ValueError(f"search must be None or one of {SEARCH_METHODS} (also accepted: "
                         f"{', '.join(n for n in names if n not in SEARCH_METHODS)}), got {search!r}")
    return search


def _no_valid_hint(search, counts: dict[str, int]) -> str:
    """What to try when a 2-D run ends with (almost) no valid POI, from the dominant failure."""
    top = max(counts, key=counts.get) if counts else ""
    if top == "OUT_OF_BOUNDS":
        return ("Most subsets leave the image: the motion carries them out, or the POIs lie too near the border; "
                "use a region of interest (roi=, --roi) away from the border or a smaller subset.")
    if top == "FLAT_SUBSET":
        return "Most subsets carry no texture: choose a region of interest (roi=, --roi) on the speckle pattern."
    if search is None:
        return ("IC-GN converges only from a few px: if the motion is larger, give an initial-guess search "
                "(search='pyramid', 'zncc', 'fft' or 'rg' with search_radius >= the motion in px; CLI: "
                "--search RADIUS [--search-method NAME]) or a guess; check also that the images belong together.")
    return ("The initial-guess search found no start that converges: raise search_radius (CLI: --search RADIUS) "
            "above the largest motion, try another search method, check that the images belong together, "
            "or lower zncc_min if the images are noisy.")


class Tracker:
    """Track one reference image into any number of current images (reference work done once).

    Parameters
    ----------
    reference : array-like (H, W), path or torch tensor
        Grey reference image (8/16-bit or float; grey levels keep their scale).
    points : (N, 2) array of POIs ``(x, y)``, optional
        Integer or sub-pixel positions. Default: ``grid(shape, step, margin=subset // 2, roi=roi)``.
    step : int, optional
        Grid spacing when ``points`` is not given (default ``subset // 2``).
    roi : optional
        Region of interest for the default grid (:mod:`dic.correlation.points`): an inclusive box
        ``(x0, y0, x1, y1)``, a polygon ``[(x, y), ...]`` (POIs inside or on the edge), an (H, W)
        mask array or a mask image file (non-zero inside), or the dict form with excluded shapes
        ``{"box": [...], "exclude": [{"circle": [cx, cy, r]}, ...]}`` (holes, notches).
    subset : odd int >= 3
        Subset size (px). Default 21.
    order : 1 or 2
        Shape function: 1 (affine, 6 parameters) or 2 (quadratic, 12 parameters).
    search : None or the name of an initial-guess strategy ("zncc", "fft", "pyramid", "rg", ...)
        Used when a current image is tracked without a guess (see docs/dic2d.md and
        :mod:`dic.correlation.guesses`): None starts from zero displacement (IC-GN converges from a
        few px).
    search_radius : int
        Largest displacement the search has to find (px). Default 32.
    max_iter : int
        IC-GN iteration limit per POI. Default 30.
    tol : float
        Convergence threshold on the scaled parameter-update norm (px). Default 1e-3.
    zncc_min : float
        ZNCC below which a converged POI is not ``valid``. Default 0.8.
    flat_std : float, optional
        Grey-level standard deviation below which a subset is FLAT_SUBSET (default 1e-3 of the
        reference's grey-level range).
    check_warps : bool
        Flag converged POIs whose warp a partly featureless subset cannot support as
        IMPLAUSIBLE_WARP (:mod:`dic.correlation.plausibility`). Default True.
    noise_sigma : float, optional
        Grey-level noise std of each image, for the per-POI uncertainty ``Field2D.sigma_u``,
        ``sigma_v`` (:mod:`dic.quality`). Default: estimated per image from the residuals of the
        valid POIs.
    robust : bool or "adaptive"
        Outlier-robust (Tukey-weighted) IC-GN (:mod:`kernels.icgn_robust`): subset pixels whose
        change the reference texture cannot explain (speckles that flake off or appear, dust,
        glints) are discounted instead of biasing the displacement. ``"adaptive"`` (default): plain
        IC-GN, then the robust refinement only for the subsets whose final residuals show a compact blob
        of outliers (:meth:`dic.correlation.engine.Correlator.refine_robust`: a residual above the
        reference's pixel-scale roughness, then :func:`kernels.icgn_robust.residual_outliers`); every
        other subset keeps the plain result bit for bit, so clean images and smooth renders keep plain
        precision and speed (docs/dic2d.md, "Robust correlation"). ``True``: every accepted POI
        refined (costs several times the plain IC-GN time and some precision on clean images);
        ``False``: plain IC-GN only. The refined POIs are counted in ``Field2D.info["robust_refined"]``.
    check_outliers : bool, optional
        Flag valid POIs whose displacement disagrees with their neighbours' (the normalised median
        test, :func:`dic.correlation.lagrangian.displacement_outliers`: false matches, often a whole
        pixel off) as NEIGHBOUR_OUTLIER, not valid. Default: on with ``robust`` True or ``"adaptive"``
        (on the evolving texture of bench/robust.py it keeps false matches from moving the result:
        0.048 px final RMS error with it, 0.063 without), off with ``robust=False``.
    device : None or str
    subset_mask : "region" or "none"
        ``"region"`` (default): when ``roi`` is a mask (array or image) or a polygon, each subset is
        correlated on the pixels inside it only (:mod:`dic.correlation.subset_masks`,
        :mod:`kernels.icgn_masked`): subsets that overlap a hole or a free edge keep the specimen's
        pixels. A box ROI chooses where the POIs are and masks no pixel. ``"none"``: every subset
        pixel, whatever the ROI (the behaviour before the option).
    min_kept_fraction : float in (0, 1]
        A masked subset keeping fewer than this fraction of its pixels gets TOO_FEW_PIXELS. Default 0.5.
    blocked_pixels : (N, subset**2) bool array or callable, optional
        Pixels to drop per POI whatever the ROI says (True = dropped, the order of
        :func:`dic.correlation.subset_masks.subset_pixel_masks`), e.g. those beyond a declared crack;
        a callable gets ``(points (N, 2), subset)`` and returns that array. Masks the subsets even
        without a mask ROI (and with ``subset_mask="none"``: it is an explicit request).
    pixel_region : optional
        With ``points`` (and no ``roi``): a region in any ROI form whose pixels the subsets keep (as
        ``roi`` does for the grid's POIs, with ``subset_mask="region"``), without selecting the POIs;
        e.g. the POIs of a chunk of a larger grid (:mod:`dic.sequence`).
    cracks : optional
        Declared cracks (:mod:`dic.cracks`): a :class:`dic.Crack`, an (M, 2) array of polyline vertices
        (x, y) px in the reference image, or a list of them. Each subset is correlated on the pixels on
        its POI's side only, less those within 1 px of a crack (:func:`dic.cracks.blocked_pixels` added to
        ``blocked_pixels``; a subset
        keeping fewer than ``min_kept_fraction`` of its pixels gets TOO_FEW_PIXELS). Default: none.
    """

    def __init__(self, reference, *, points=None, step: int | None = None, roi=None, subset: int = 21,
                 order: int = 1, search: str | None = None, search_radius: int = 32, max_iter: int = 30,
                 tol: float = 1e-3, zncc_min: float = 0.8, flat_std: float | None = None, check_warps: bool = True,
                 noise_sigma: float | None = None, robust: bool | str = "adaptive", check_outliers: bool | None = None,
                 device=None, subset_mask: str = "region", min_kept_fraction: float = DEFAULT_MIN_KEPT_FRACTION,
                 blocked_pixels=None, pixel_region=None, cracks=None):
        self.subset, self.order = check_subset_order(subset, order)
        self.noise_sigma = check_noise_sigma(noise_sigma)
        self.search = _check_search(search)
        self.search_radius = non_negative_int(search_radius, "search_radius", detail=" (px)")
        self.max_iter = check_max_iter(max_iter)
        self.tol = check_tol(tol)
        self.zncc_min = in_range(zncc_min, -1.0, 1.0, "zncc_min")
        self.check_warps = bool(check_warps)
        self.robust = check_robust(robust)
        self.check_outliers = bool(self.robust) if check_outliers is None else boolean(check_outliers, "check_outliers")
        self.device = resolve_device(device)
        self.reference = _as_image(reference, "reference")
        self.shape = self.reference.shape
        if points is None:
            self.step = check_step(step) if step is not None else max(1, self.subset // 2)
            self.points = grid(self.shape, self.step, margin=self.subset // 2, roi=roi)
        else:
            self.step = check_step(step) if step is not None else None
            if roi is not None:
                raise ValueError("give either points or roi (roi selects grid points), not both; pixel_region= "
                                 "masks the subsets of given points")
            self.points = as_points(points)
        if pixel_region is not None:
            if points is None:
                raise ValueError("pixel_region goes with points (a roi masks the subsets of its own grid)")
            roi = pixel_region
        self.subset_mask = check_subset_mask(subset_mask)
        self.min_kept_fraction = check_min_kept_fraction(min_kept_fraction)
        self.cracks = _check_cracks(cracks)
        #: (N, subset**2) bool: the pixels each subset keeps, or None (every pixel)
        self.pixel_mask = tracking_pixel_masks(self.points, self.subset, self.shape, roi, self.subset_mask,
                                               _with_cracks(blocked_pixels, self.cracks))
        self.correlator = Correlator(self.reference, self.points, subset=self.subset, order=self.order,
                                     max_iter=self.max_iter, tol=self.tol, device=self.device, flat_std=flat_std,
                                     pixel_mask=self.pixel_mask,
                                     min_kept_fraction=None if self.pixel_mask is None else self.min_kept_fraction)
        self._current_buf = None
        self._current_tensor = None  # the last torch image read in place (kept alive until the next one)
        self._sigma_basis = None  # diag H^-1 and df of the reference subsets, read back once (dic.quality)
        self._outlier_cache = {}  # the neighbour lists of the neighbour-outlier check (same valid points: reused)

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    def _check_current(self, current) -> np.ndarray:
        cur = _as_image(current, "current")
        if cur.shape != self.shape:
            raise ValueError(f"current image has shape {cur.shape} but the reference has shape {self.shape}; "
                             "DIC needs images of the same size")
        return cur

    def _context(self, cur: np.ndarray, prior: np.ndarray) -> GuessContext:
        return GuessContext(self.correlator, self.reference, cur, prior, self.search_radius, self.zncc_min)

    def initial_guess(self, cur: np.ndarray, guess=None, search: str | None = None) -> np.ndarray:
        """(N, K) initial parameters for a current image: ``guess`` refined by the strategy ``search``."""
        n, k = self.n_points, n_params(self.order)
        g = guess_params(guess, n, self.order)
        g = np.zeros((n, k)) if g is None else g
        if search is None:
            return g
        params, _ = get_guess(_check_search(search))(self._context(cur, g))
        return params

    def track(self, current, *, guess=None, search: str | None = "default") -> Field2D:
        """Track the POIs into ``current``.

        Parameters
        ----------
        current : array-like (H, W), path or torch tensor, same shape as the reference.
            A torch tensor (CPU or CUDA) is read in place on the device when no search runs
            (``search`` None or ``"prior"``): a float32 contiguous tensor on this tracker's device is
            viewed by Warp (``wp.from_torch``) without any copy, other dtypes (8/16-bit, float64) are
            converted on the device by torch, a tensor on another device is moved there first; the
            finiteness check runs on the device, and only the results come back to the host. With a
            search (``"zncc"``, ``"fft"``, ...; they run on the host) the image goes to the host once.
        guess : None, (u, v), (N, 2), (N, 6|12) parameters or a Field2D (e.g. the previous frame)
        search : initial-guess strategy for this image; default: the tracker's ``search``.

        Warns (RuntimeWarning) when fewer than 5 % of the POIs come out valid, saying why and what to try.
        """
        search = self.search if search == "default" else _check_search(search)
        if is_torch_tensor(current) and search in (None, "prior"):
            # read in place on the device: no host copy of the image (only the results come back)
            self._current_buf = prepare_current(self._device_view(current), device=self.device,
                                                out=self._current_buf)
            g = guess_params(guess, self.n_points, self.order)
            r = self.correlator.run_all(self._current_buf, np.zeros((self.n_points, n_params(self.order)))
                                        if g is None else g)
            return self._finish(self._refined(self._current_buf, r), search)
        if isinstance(current, (str, os.PathLike)):
            current = read_image(current)
        if search in (None, "prior") and _device_resident(current):
            # the device-resident frame path: 8/16-bit or float32 frames converted and checked on the device,
            # buffers allocated once, results bitwise those of the path below (tests/kernels/test_frames.py)
            if current.shape != self.shape:
                raise ValueError(f"current image has shape {current.shape} but the reference has shape {self.shape}; "
                                 "DIC needs images of the same size")
            g = guess_params(guess, self.n_points, self.order)
            r = self.correlator.run_frame(current, np.zeros((self.n_points, n_params(self.order))) if g is None else g)
            if self.robust:
                r = self._refined(self.correlator.frame_current(current.dtype), r)
            return self._finish(r, search)
        cur = self._check_current(current)  # a tensor with a search: to the host once (the searches run there)
        self._current_buf = prepare_current(cur, device=self.device, out=self._current_buf)
        strategy = get_guess(search) if search is not None else None
        if strategy is not None and strategy.propagates:
            base = guess_params(guess, self.n_points, self.order)
            base = np.zeros((self.n_points, n_params(self.order))) if base is None else base
            ctx = self._context(cur, base)
            r = reliability_guided(self.correlator, self._current_buf, base, lambda idx: strategy(ctx, idx)[0],
                                   zncc_min=self.zncc_min, step=self.step)
        else:
            g = self.initial_guess(cur, guess, search)
            r = self.correlator.run_all(self._current_buf, g)
        return self._finish(self._refined(self._current_buf, r), search)

    def _refined(self, current, r: dict) -> dict:
        """``r`` refined by robust IC-GN when this tracker is ``robust`` (``"adaptive"``: the POIs whose residuals
        show outliers; else ``r``)."""
        if not self.robust:
            return r
        return self.correlator.refine_robust(current, r, adaptive=self.robust == ADAPTIVE)

    def _device_view(self, current):
        """A torch tensor -> a Warp array viewing its float32 copy or itself on this tracker's device (checked there)."""
        import warp as wp

        image = as_float32_tensor(current, self.device, "current")
        if tuple(image.shape) != tuple(self.shape):
            raise ValueError(f"current image has shape {tuple(image.shape)} but the reference has shape {self.shape}; "
                             "DIC needs images of the same size")
        # held until the next image: Warp may still read it on its own stream after this call returns
        self._current_tensor = image
        return wp.from_torch(image)

    def _finish(self, r: dict, search) -> Field2D:
        field = self._field(r)
        counts = status_counts(field.status[~field.valid], Status)
        warn_if_mostly_invalid(int(np.count_nonzero(field.valid)), field.n_points, counts,
                               _no_valid_hint(search, counts), what="2-D tracking")
        return field

    def track_tensors(self, current, *, guess=None) -> dict:
        """Track into a torch tensor and return torch tensors, with no host copy of the image or results.

        For pipelines that keep frames on the GPU (``torch.cuda`` tensors; CPU tensors work the same
        way). ``current``: a 2-D float32 contiguous torch tensor on this tracker's device (other dtypes
        and devices are converted on the device first). Warp views the tensor's memory
        (``wp.from_torch``) and IC-GN reads it in place; the results are Warp's output buffers seen as
        tensors (``wp.to_torch``): ``params`` (N, 6|12), ``zncc`` (N,), ``iterations`` (N,), ``status``
        (N,) and ``valid`` (N,) bool (status CONVERGED or MAX_ITERATIONS and ZNCC >= ``zncc_min``).
        They are overwritten by the next call: ``.clone()`` what you keep. Starts from ``guess``
        (as in :meth:`track`) or zero; plain IC-GN: no search, no robust refinement, no implausible-warp or
        neighbour check (use :meth:`track` for those). Only the finiteness check of the image reduces on the device to one scalar.
        """
        import torch
        import warp as wp

        if not isinstance(current, torch.Tensor):
            raise ValueError(f"current must be a torch tensor, got {type(current).__name__}; use track() for arrays")
        if current.ndim != 2 or tuple(current.shape) != tuple(self.shape):
            raise ValueError(f"current must be a 2-D tensor of the reference's shape {self.shape}, "
                             f"got shape {tuple(current.shape)}")
        if current.is_complex() or current.dtype == torch.bool:
            raise ValueError(f"current must hold real grey levels, got dtype {current.dtype}")
        self._current_buf = prepare_current(self._device_view(current), device=self.device, out=self._current_buf)
        n, k = self.n_points, n_params(self.order)
        g = guess_params(guess, n, self.order)
        res = self.correlator.run_device(self._current_buf, np.zeros((n, k)) if g is None else g)
        out = {name: wp.to_torch(getattr(res, name)) for name in ("params", "zncc", "iterations", "status")}
        good = (out["status"] == int(Status.CONVERGED)) | (out["status"] == int(Status.MAX_ITERATIONS))
        out["valid"] = good & (out["zncc"] >= self.zncc_min)
        return out

    def _field(self, r: dict) -> Field2D:
        k = n_params(self.order)
        params = r["params"].astype(np.float64)
        zncc = r["zncc"].astype(np.float64)
        status = r["status"].astype(np.int32)
        valid = accepted_mask(status, zncc, self.zncc_min)
        if self.check_warps:
            implausible = flag_implausible(self.correlator, params, valid, self.order)
            status[implausible] = int(Status.IMPLAUSIBLE_WARP)
            valid &= ~implausible
        if self.check_outliers:
            outliers = displacement_outliers(self.points, params[:, 0], params[:, k // 2], valid,
                                             cache=self._outlier_cache)
            status[outliers] = int(Status.NEIGHBOUR_OUTLIER)
            valid &= ~outliers
        if self._sigma_basis is None:
            self._sigma_basis = sigma_basis(self.correlator.subsets)
        sigma, noise, source = displacement_sigma(self._sigma_basis, zncc, valid, self.noise_sigma)
        extra = {}
        if "robust_flagged" in r:  # the POIs refined by robust IC-GN (all accepted ones, or those flagged)
            extra["robust_refined"] = int(np.count_nonzero(r["robust_flagged"]))
        return Field2D(self.points.copy(), params[:, 0].copy(), params[:, k // 2].copy(), params, zncc,
                       r["iterations"].astype(np.int32), status, valid, self.subset, self.order, self.step,
                       self.zncc_min, extra, sigma_u=sigma[:, 0].copy(), sigma_v=sigma[:, 1].copy(), noise_sigma=noise,
                       noise_source=source)


def _check_cracks(cracks):
    """``cracks`` -> a tuple of :class:`dic.cracks.Crack` (empty: none)."""
    from .cracks import as_cracks

    return as_cracks(cracks)


def _with_cracks(blocked, cracks):
    """``blocked_pixels`` with the pixels across ``cracks`` added: a callable ``(points, subset) -> (N, subset²)
    bool`` (or ``blocked`` itself without cracks)."""
    if not cracks:
        return blocked

    def blocked_with_cracks(points, subset):
        from .cracks import blocked_pixels

        out = blocked_pixels(points, subset, cracks)
        if blocked is not None:
            extra = np.asarray(blocked(points, subset) if callable(blocked) else blocked)
            if extra.shape != out.shape or extra.dtype != bool:
                raise ValueError(f"blocked_pixels must be a bool array of shape (N, subset**2) = {out.shape}, "
                                 f"got {extra.dtype} {extra.shape}")
            out |= extra
        return out

    return blocked_with_cracks


def track(reference, current, *, points=None, step: int | None = None, roi=None, subset: int = 21, order: int = 1,
          guess=None, search: str | None = None, search_radius: int = 32, max_iter: int = 30, tol: float = 1e-3,
          zncc_min: float = 0.8, flat_std: float | None = None, check_warps: bool = True, noise_sigma=None,
          robust: bool | str = "adaptive", check_outliers: bool | None = None, device=None, subset_mask: str = "region",
          min_kept_fraction: float = DEFAULT_MIN_KEPT_FRACTION, blocked_pixels=None, pixel_region=None,
          cracks=None) -> Field2D:
    """Track POIs of ``reference`` into ``current`` with IC-GN: every :class:`Tracker` option, plus ``guess``
    (initial parameters of this pair, as :meth:`Tracker.track` takes them).

    Returns a :class:`Field2D`. For several current images of one reference, build a
    :class:`Tracker` once and call its ``track`` method (the reference-side work is reused).

    Raises
    ------
    ValueError : mismatched image sizes, NaNs, colour images, unreadable files, even subset size,
        unknown order or search method, empty ROI / points. POIs whose subset leaves the image are
        not an error: they get status OUT_OF_BOUNDS.
    """
    tracker = Tracker(reference, points=points, step=step, roi=roi, subset=subset, order=order, search=search,
                      search_radius=search_radius, max_iter=max_iter, tol=tol, zncc_min=zncc_min,
                      flat_std=flat_std, check_warps=check_warps, noise_sigma=noise_sigma, robust=robust,
                      check_outliers=check_outliers, device=device, subset_mask=subset_mask,
                      min_kept_fraction=min_kept_fraction, blocked_pixels=blocked_pixels, pixel_region=pixel_region,
                      cracks=cracks)
    return tracker.track(current, guess=guess)
