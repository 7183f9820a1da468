"""Stereo digital image correlation: left-right matching, temporal tracking, 3-D fields.

Pipeline (docs/stereo.md, sections "Stereo matching" and "3-D fields"):

1. **Reference stereo match.** Points of interest (POIs) of the left reference image are matched
   into the right reference image with IC-GN (1st order by default, chosen by measurement: docs/stereo.md "Defaults"; Gao et al., Optics and Lasers
   in Engineering 65, 2015, doi:10.1016/j.optlaseng.2014.04.002). The initial guess comes from
   the geometry: SIFT features (Lowe, IJCV 60, 2004, doi:10.1023/B:VISI.0000029664.99615.94)
   matched between the two images and kept when they satisfy the epipolar constraint of the
   calibrated rig (on undistorted points); for each POI an affine map (u, v and their gradients)
   is fitted by robust least squares to the k nearest feature matches. POIs without enough
   nearby matches get their guess from an already matched neighbour (reliability-guided
   propagation, Pan, Applied Optics 48(8), 2009, doi:10.1364/AO.48.001535), and regions with
   neither from a ZNCC search along their epipolar line in the right image. A match is accepted
   when IC-GN converged, its ZNCC is at least ``zncc_min`` and the matched point lies within
   ``epipolar_tol_px`` of the epipolar line; the others keep a :class:`StereoStatus` saying why.
   The epipolar search stops after a round that accepted nothing (:data:`MATCH_FRUITLESS_ROUNDS`);
   ``progress=`` reports the match's stages (a tqdm bar or a callback).
2. **Temporal tracking.** Each later state is tracked left-reference -> left-current and
   right-reference -> right-current (reference subsets precomputed once, the previous state's
   parameters as initial guess, the first IC-GN pass on the device frame path of
   :class:`kernels.frames.FrameTracker` with its buffers allocated once per reference, features and
   propagation for POIs that fail). The tracks may start
   from a later state's pair instead (:meth:`StereoCorrelation.move_reference`, the reference
   strategies of :func:`dic.sequence.stereo_sequence`); their results are composed back onto the
   reference pair, so every state stays relative to the reference state (Lagrangian), and points
   not valid in that later state are placed there by local interpolation and tracked again.
3. **Triangulation and fields.** Matched positions (reference position + displacement, float64)
   are triangulated (:func:`dic.triangulate`, optimal method); displacements are
   current minus reference positions; surface strains come from :mod:`dic.field3d`.

Conventions (docs/conventions.md): images ``[row, col]``; points ``(x, y)`` px with (0, 0) the
centre of the top-left pixel; 3-D in mm in the left camera frame (or a chosen object frame);
``x_right = R_right_left @ x_left + t_right_left``; shape-function parameters in
:data:`kernels.conventions.PARAMS_2ND` order.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace

import numpy as np

from calibration.formats import as_rig  # re-exported: dic._stereo.as_rig
from kernels._device import resolve_device
from kernels.checks import as_points, in_range, odd_int, positive_float
from kernels.conventions import Status
from kernels.icgn import check_max_iter, check_subset_order, n_params, prepare_current
from kernels.icgn_masked import DEFAULT_MIN_KEPT_FRACTION
from kernels.images import as_float32_image
from kernels.interp import FRAME_DTYPES
from kernels.search import phase_spectrum, phase_window
from kernels.verify import VERIFY_SPREAD, check_verify_spread

from ._triangulate import TriangulationStatus, optimal_triangulation_jacobian, triangulate, undistort_points
from .correlation.acceptance import (
    MOSTLY_INVALID_FRACTION,
    accepted_mask,
    stage_status,
    status_counts,
    warn_if_mostly_invalid,
)
from .correlation.engine import (
    SOURCE_FEATURES,
    SOURCE_GLOBAL,
    SOURCE_NONE,
    SOURCE_PREVIOUS,
    Correlator,
    check_robust,
    correlate,
)
from .correlation.features import affine_guess, feature_matches
from .correlation.guesses import GuessContext, get_guess
from .correlation.params import check_tol
from .correlation.params import displacement as _displacement
from .correlation.points import grid_points, typical_spacing
from .correlation.subset_masks import check_min_kept_fraction, check_subset_mask, tracking_pixel_masks
from .epipolar import epipolar_distance, epipolar_residuals, fundamental_matrix
from .field3d import (
    Field3D,
    StereoStatus,
    SurfaceStrainPlan,
    as_frame,
    check_grid_window,
    plane_frame,
    scattered_neighbours,
    surface_strain,
)
from .quality import check_noise_sigma, displacement_sigma, propagate_stereo_sigma, sigma_basis, triangulation_jacobian

__all__ = [
    "StereoStatus", "StereoMatch", "StereoCorrelation", "stereo", "fundamental_matrix", "epipolar_distance",
    "epipolar_residuals", "feature_matches", "affine_guess", "grid_points", "check_rig_images", "as_rig",
]


# ================================================================================================
# input checks


def _image(img, name: str) -> np.ndarray:
    return as_float32_image(img, name)


#: raw frame dtypes a state's images stay in until a float copy is needed (the frame path converts in its prefilter)
_RAW_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16))


def _raw_or_float(img, name: str) -> np.ndarray:
    """A 2-D 8/16-bit NumPy image as it is (integers: nothing to check), anything else as the float32 image of
    :func:`_image` (checked). A state's images are converted to float only where a step needs them
    (:class:`_FloatImages`)."""
    if type(img) is np.ndarray and img.dtype in _RAW_DTYPES and img.ndim == 2 and img.size:
        return img
    return _image(img, name)


class _FloatImages:
    """Float32 copies of a state's images, made when first needed and kept by identity (the same object each time:
    a camera's current image is the next state's base, whose phase spectrum is kept by identity, _SpectrumMemo)."""

    def __init__(self):
        self._made: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, img: np.ndarray) -> np.ndarray:
        if img.dtype == np.float32:
            return img
        made = self._made.get(id(img))
        if made is None or made[0] is not img:
            made = (img, as_float32_image(img))
            self._made[id(img)] = made
        return made[1]

    def made(self, img: np.ndarray) -> np.ndarray:
        """``img``'s float copy if one was made, else ``img``."""
        made = self._made.get(id(img))
        return made[1] if made is not None and made[0] is img else img


def check_rig_images(rig, shape: tuple[int, int]) -> None:
    """Raise ``ValueError`` unless the rig's cameras were calibrated for images of ``shape`` (H, W).

    A camera with ``size == (0, 0)`` (unknown) is accepted.
    """
    missing = [a for a in ("left", "right", "R_right_left", "t_right_left") if not hasattr(rig, a)]
    if missing:
        raise ValueError("rig must be a calibration.stereo.StereoRig (left, right, R_right_left, t_right_left); "
                         f"got {type(rig).__name__} without {', '.join(missing)}")
    h, w = shape
    for side in ("left", "right"):
        size = tuple(int(s) for s in getattr(rig, side).size)
        if size != (0, 0) and size != (w, h):
            raise ValueError(
                f"the rig's {side} camera was calibrated for {size[0]}x{size[1]} px images but the images are "
                f"{w}x{h} px; use the rig file made for these images (or images of the calibrated size)")


def _frame(given, checked: np.ndarray) -> np.ndarray:
    """The image for the device frame path: ``given`` itself when it is a NumPy array of a frame dtype (8/16-bit
    or float32) of ``checked``'s shape (converted to float in the prefilter, no host copy), else ``checked``
    (the float32 image :func:`_check_pair` made)."""
    if (isinstance(given, np.ndarray) and given.shape == checked.shape
            and given.dtype in FRAME_DTYPES):
        return given
    return checked


def _check_pair(left, right, what: str, convert=_image) -> tuple[np.ndarray, np.ndarray]:
    """The two images of a pair, checked (``convert``: :func:`_image`, float32; :func:`_raw_or_float`, 8/16-bit
    images as they are) and of one size."""
    L = convert(left, f"left {what} image")
    R = convert(right, f"right {what} image")
    if L.shape != R.shape:
        raise ValueError(f"the left and right {what} images differ in size: {L.shape[1]}x{L.shape[0]} and "
                         f"{R.shape[1]}x{R.shape[0]} px (W x H); stereo DIC needs the two cameras' images at their "
                         "calibrated size")
    return L, R


# ================================================================================================
# results of the reference match


@dataclass
class StereoMatch:
    """Left-reference -> right-reference correspondence of every POI.

    Attributes
    ----------
    points_left : (N, 2) float64 px, the POIs.
    points_right : (N, 2) float64 px, matched positions in the right image (``points_left + (u, v)``),
        NaN where ``status`` is ``NOT_COMPUTED`` or ``NO_GUESS``.
    params : (N, 6|12) float64, IC-GN shape-function parameters (PARAMS_1ST / PARAMS_2ND order).
    zncc : (N,) float64; iterations : (N,) int32; icgn_status : (N,) int32 :class:`kernels.conventions.Status`.
    epipolar_px : (N,) float64, distance from the epipolar line (undistorted right image), NaN where not matched.
    guess_source : (N,) int8: 0 features, 1 neighbour propagation, 2 epipolar search, -1 none.
    status : (N,) int8 :class:`StereoStatus` (``OK``, ``NOT_COMPUTED``, ``NO_GUESS``, ``MATCH_FAILED``,
        ``EPIPOLAR_VIOLATION``, ``LOW_ZNCC`` or ``IMPLAUSIBLE_WARP``).
    n_features : int, epipolar-consistent feature matches used for the guesses.
    """

    points_left: np.ndarray
    points_right: np.ndarray
    params: np.ndarray
    zncc: np.ndarray
    iterations: np.ndarray
    icgn_status: np.ndarray
    epipolar_px: np.ndarray
    guess_source: np.ndarray
    status: np.ndarray
    n_features: int = 0
    #: the shape function's order; None: read from ``params`` (6 columns: 1, 12: 2)
    order: int | None = None

    def __post_init__(self):
        if self.order is None:
            self.order = 2 if np.asarray(self.params).shape[-1] == 12 else 1

    @property
    def valid(self) -> np.ndarray:
        return self.status == StereoStatus.OK

    def counts(self) -> dict[str, int]:
        codes, counts = np.unique(self.status, return_counts=True)
        return {StereoStatus(int(c)).name: int(n) for c, n in zip(codes, counts)}

    def __repr__(self) -> str:
        n = int(np.asarray(self.status).shape[0])
        n_ok = int(np.count_nonzero(self.valid))
        share = f" ({100.0 * n_ok / n:.1f} %)" if n else ""
        failed = {k: v for k, v in self.counts().items() if k != "OK"}
        top = ", ".join(f"{k} {v}" for k, v in sorted(failed.items(), key=lambda kv: -kv[1])[:3])
        return (f"<StereoMatch: {n} points, {n_ok} OK{share}, {self.n_features} feature matches, order {self.order}"
                + (f"; not OK: {top}" if top else "") + ">")

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in ("points_left", "points_right", "params", "zncc", "iterations",
                                               "icgn_status", "epipolar_px", "guess_source", "status")}


def _stereo_hint(counts: dict[str, int]) -> str:
    """What to try when a stereo run ends with (almost) no valid point, from the dominant failure."""
    top = max(counts, key=counts.get) if counts else ""
    if top in ("NO_GUESS", "EPIPOLAR_VIOLATION", "MATCH_FAILED"):
        return ("No initial guess could start most points, or their matches left the epipolar lines: the rig does "
                "not fit these images. Check that left and right are not swapped, that the rig file belongs to "
                "this setup and image size (specula calibrate stereo), and that both views see the speckled "
                "surface; a region of interest (roi=, --roi) on the specimen helps when much of the image is "
                "background.")
    if top == "NOT_COMPUTED":
        return ("Most reference subsets are outside the region of interest, flat or leave the image: choose a "
                "region of interest (roi=, --roi) on the speckle pattern, or a smaller subset.")
    if top in ("TRACK_LEFT_FAILED", "TRACK_RIGHT_FAILED", "LOW_ZNCC"):
        return ("The temporal tracks failed: the motion since the previous state may be too large for the guess "
                "(measure intermediate states), or the images do not belong to this sequence.")
    return "Check the rig, the images and the region of interest."


def _warn_if_mostly_invalid(status: np.ndarray, what: str) -> None:
    """The stereo form of :func:`dic.correlation.acceptance.warn_if_mostly_invalid`."""
    valid = status == StereoStatus.OK
    counts = status_counts(status[~valid], StereoStatus)
    warn_if_mostly_invalid(int(np.count_nonzero(valid)), int(status.size), counts, _stereo_hint(counts), what=what,
                           stacklevel=4)


def _warn_if_epipolar_mismatch(match: "StereoMatch", tol_px: float) -> None:
    """Warn when most correlated points miss their epipolar line: the rig does not fit the images.

    Isolated violations are bad matches; a majority means the calibration (usually the relative
    rotation) or the image order is wrong, and every point would silently come out invalid."""
    import warnings

    violated = match.status == StereoStatus.EPIPOLAR_VIOLATION
    correlated = violated | (match.status == StereoStatus.OK)
    if np.count_nonzero(correlated) >= 10 and np.count_nonzero(violated) > 0.5 * np.count_nonzero(correlated):
        median = float(np.nanmedian(match.epipolar_px[violated]))
        warnings.warn(
            f"{np.count_nonzero(violated)} of {np.count_nonzero(correlated)} correlated points are more than "
            f"{tol_px:g} px from their epipolar line (median {median:.2f} px): the rig does not fit these images. "
            "Check that left and right are not swapped and that the rig file belongs to this setup; a relative "
            "rotation error of a few hundredths of a degree (e.g. a mirror-only calibration without a far view) "
            "gives this. Recalibrate (specula calibrate stereo with --far) or raise epipolar_tol_px / --epipolar-tol.",
            RuntimeWarning, stacklevel=3)


#: the reference match stops its epipolar-search fallback after this many rounds in a row that accepted no
#: point (:func:`dic.correlation.engine.correlate`, ``max_fruitless_rounds``): what is left is out of the right
#: view or unmatchable, and each round costs ~13 ms per seed (measured, docs/stereo.md)
MATCH_FRUITLESS_ROUNDS = 1


class _MatchProgress:
    """Progress of the reference match (``StereoCorrelation(progress=...)``): a tqdm bar, a callable or nothing.

    Called as ``report(stage, accepted, settled)`` (:func:`dic.correlation.engine.correlate`'s ``report``);
    shows the POIs settled out of ``total``."""

    def __init__(self, progress, total: int):
        self.total = int(total)
        self._bar = None
        self._call = progress if callable(progress) else None
        if progress is True:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, unit="POI", desc="stereo match", dynamic_ncols=True)

    def __call__(self, stage: str, accepted: int, settled: int) -> None:
        if self._bar is not None:
            self._bar.set_postfix_str(f"{stage}, {accepted} accepted", refresh=False)
            self._bar.update(max(0, min(settled, self.total) - self._bar.n))
        if self._call is not None:
            self._call(stage, int(settled), self.total)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def _check_progress(progress):
    if progress is None or progress is False or progress is True or callable(progress):
        return progress
    raise ValueError(f"progress must be None, a bool or a callable progress(stage, done, total), "
                     f"got {type(progress).__name__}")


# ================================================================================================
# the stereo correlation object


_FRAME_CHOICES = ("left", "plane")


class StereoCorrelation:
    """Stereo DIC of a reference pair, then of any number of current pairs.

    Build it once per reference pair; :meth:`measure` a current pair to get a :class:`Field3D`.
    The reference quantities (B-spline gradients and IC-GN Hessians of the left and right
    reference subsets) are computed once here and reused for every state.

    Parameters
    ----------
    rig : calibration.stereo.StereoRig, or the path of a rig file in any format Specula reads
        (Specula JSON, OpenCV YAML/XML/JSON, VIC-3D XML, DICe XML; :func:`as_rig`).
    left_ref, right_ref : (H, W) grey images of the reference state (same size, the rig's size).
    points : (N, 2) px in the left reference image, optional. Default: a grid of ``step``.
    step : int, grid spacing (px) when ``points`` is None; default ``subset // 2`` (as 2-D).
    roi : optional, in the left reference image: an inclusive box ``(x0, y0, x1, y1)``, a polygon
        ``[(x, y), ...]``, an (H, W) mask or a mask image file, or the dict form with excluded shapes
        ``{"box": [...], "exclude": [{"circle": [cx, cy, r]}, ...]}`` (:mod:`dic.correlation.points`; the
        same rule as 2-D tracking); grid POIs outside are ``NOT_COMPUTED``.
    subset : odd int, subset size (px); order : 1 (default) or 2 (shape function; docs/stereo.md "Defaults").
    frame : "left", "plane" or (R_obj_left, t_obj_left): output frame (see :class:`Field3D`).
    epipolar_tol_px : float, px (undistorted right image) beyond which a match is ``EPIPOLAR_VIOLATION``.
    zncc_min : float, matches and tracks below it are ``LOW_ZNCC``.
    strain_window : odd int, grid points per side of the strain neighbourhood (scattered points:
        the ``strain_window²`` nearest).
    strain_type : "green-lagrange" (default), "small" or "euler-almansi": what ``exx``, ``eyy``, ``exy``
        are (:mod:`dic.field3d`).
    max_iter, tol : IC-GN iteration limit (1..10000) and convergence threshold (px, see kernels/icgn.py).
    triangulation : "optimal" or "linear" (:func:`dic.triangulate`).
    match : StereoMatch, optional: a reference match computed before (e.g. read back from a
        result file); skips the feature matching and the left -> right IC-GN.
    check_warps : bool, flag matches and tracks that converged to a warp their partly featureless
        subset cannot support as ``IMPLAUSIBLE_WARP`` (:mod:`dic.correlation.plausibility`). Default True.
    noise_sigma : float, optional: grey-level noise std of each image, for the per-point image-plane
        uncertainty in ``Field3D.details`` (``sigma_match_px``, ``sigma_left_px``, ``sigma_right_px``,
        :mod:`dic.quality`); default: estimated from each stage's correlation residuals.
    robust : bool or "adaptive", outlier-robust (Tukey-weighted) IC-GN (:mod:`kernels.icgn_robust`) of the
        accepted matches and tracks: pixels whose texture differs from the reference subset (a speckle
        that changed, a glint seen by one camera only) do not bias it. ``"adaptive"``: only the subsets whose
        plain residuals show outliers are refined, the others keep the plain result bit for bit; True: every
        accepted one; False (default): none. Stereo stays plain by default: on the virtual-lab renders the
        residual test flags most subsets (their quadrature noise is heavy-tailed) and adaptive costs 1.4-2.8x in
        displacement std, as True does (docs/dic2d.md, "Robust correlation").
    device : None, "cpu" or "cuda:N".
    progress : progress of the reference match (the long step of the constructor): None or False (silent),
        True (a tqdm bar on stderr: POIs settled, the stage as its postfix), or a callable
        ``progress(stage, done, total)`` called after each stage (``"features"``, ``"first pass"``,
        ``"propagation"``, ``"fallback"``, ``"second opinion"``, ``"done"``) with the POIs settled so far and the
        POIs to match (:func:`dic.correlation.engine.correlate`, ``report``).
    subset_mask : "region" or "none": with a mask or polygon ``roi``, the left reference's subsets keep the
        pixels inside it (:class:`dic.Tracker`'s option): the match left -> right and the left track correlate
        those only, and the right track (with ``right_track_mask``) the pixels the region maps to in the right
        reference image; a moved reference the region carried into its images (:meth:`_moved_pixel_masks`).
        Default "region"; "none": the behaviour before the option.
    min_kept_fraction : float in (0, 1], masked subsets keeping less are ``TOO_FEW_PIXELS``. Default 0.5.
    verify_zncc : float in [-1, 1], optional
        With a moved reference (:meth:`move_reference`): each state's composed left and right tracks are
        checked against the reference pair (each camera's reference subset and the state's image at the
        composed warp, :mod:`dic.correlation.stereo_verify`); a point below ``verify_zncc`` in either camera gets
        ``StereoStatus.COMPOSED_MISMATCH`` before its strain is computed, and the state's details hold
        ``composed_zncc_left`` / ``composed_zncc_right`` (NaN where not checked). Default None: no check
        (:func:`dic.sequence.stereo_sequence` turns it on with a moved reference).
    verify_spread : float >= 0, "off" or None
        With ``verify_zncc``: each state's threshold, per camera, is ``min(verify_zncc, median - verify_spread *
        1.4826 * MAD)`` of that camera's checked ZNCCs (:func:`kernels.verify.composed_threshold`, the 2-D rule:
        lower only where the texture has changed since the reference pair). Default 4
        (:data:`kernels.verify.VERIFY_SPREAD`); "off" or None: ``verify_zncc`` alone (the rule before the option).
    motion_prediction : "velocity" (default) or "none"
        How :meth:`measure` starts the temporal tracks of a state that follows another in a chain of ``use_previous``
        states (the reference pair, whose parameters are zero, is the state before the first one measured):
        "velocity" extrapolates them at constant velocity and keeps that start when its
        first IC-GN pass accepts at least :data:`PREDICTION_MIN_ACCEPTED` of the points the previous state had
        (else, a jump, it starts again from the previous state + the global shift); "none": the previous state +
        the global shift (the behaviour before the option).
    cracks : optional
        Declared cracks (:mod:`dic.cracks`: a :class:`dic.Crack`, an (M, 2) vertex array or a list of them) in
        LEFT reference-image px (:mod:`dic.stereo_cracks`): the left subsets (match, left track) keep the pixels
        on their POI's side only, the right track's subsets the pixels that map there through the match, and
        no surface-strain window reaches across a crack. A moved reference cuts its subsets at the cracks carried
        into its images (:meth:`_moved_pixel_masks`).
    right_track_mask : bool
        With ``subset_mask="region"`` and a mask or polygon ``roi``: the right temporal track's subsets (at the
        matched points, in the right reference image) keep the pixels that map into the left region through
        each POI's stereo match (:mod:`dic.correlation.right_masks`; ``right_pixel_mask``, (M, S*S) bool or
        None). Default True; False: every pixel (the behaviour before the option).
    """

    def __init__(self, rig, left_ref, right_ref, *, points=None, step: int | None = None, roi=None, subset: int = 21,
                 order: int = 1, frame="left", epipolar_tol_px: float = 1.0, zncc_min: float = 0.8,
                 strain_window: int = 5, max_iter: int = 50, tol: float = 1e-3, triangulation: str = "optimal",
                 max_features: int = 20000, match: StereoMatch | None = None, check_warps: bool = True,
                 noise_sigma: float | None = None, robust: bool | str = False, device=None, progress=None,
                 subset_mask: str = "region", min_kept_fraction: float = DEFAULT_MIN_KEPT_FRACTION,
                 strain_type: str = "green-lagrange", verify_zncc: float | None = None, right_track_mask: bool = True,
                 cracks=None, verify_spread: float | str | None = VERIFY_SPREAD,
                 motion_prediction: str = "velocity"):
        from ._strain import check_strain_type

        self.strain_type = check_strain_type(strain_type)  # what exx, eyy, exy are (dic.field3d)
        if motion_prediction not in MOTION_PREDICTIONS:
            raise ValueError(f"motion_prediction must be one of {MOTION_PREDICTIONS}, got {motion_prediction!r}")
        #: the temporal tracks' start from the previous state: "velocity" (constant-velocity extrapolation from
        #: the two states before, kept when its first pass holds) or "none" (the previous state + the global shift)
        self.motion_prediction = motion_prediction
        # the check of composed tracks against the reference pair (None: none; dic.correlation.stereo_verify)
        self.verify_zncc = None if verify_zncc is None else in_range(verify_zncc, -1.0, 1.0, "verify_zncc")
        self.verify_spread = check_verify_spread(verify_spread)  # None: verify_zncc alone (kernels.verify)
        self._composed_check = None  # built at the first state tracked from a moved reference
        self.device = resolve_device(device)
        self._progress = _check_progress(progress)
        self.robust = check_robust(robust)
        self.noise_sigma = check_noise_sigma(noise_sigma)
        self.subset, self.order = check_subset_order(subset, order)
        left_ref, right_ref = _check_pair(left_ref, right_ref, "reference")
        # the images' size stands in where a rig file records none
        rig = as_rig(rig, image_size=(left_ref.shape[1], left_ref.shape[0]))
        check_rig_images(rig, left_ref.shape)
        self.rig = rig
        self.shape = left_ref.shape
        self.epipolar_tol_px = positive_float(epipolar_tol_px, "epipolar_tol_px")
        self.zncc_min = in_range(zncc_min, -1.0, 1.0, "zncc_min")
        self.max_iter = check_max_iter(max_iter)
        self.tol = check_tol(tol)
        strain_window = odd_int(strain_window, "strain window", detail=" (grid points)", integral_float=True)
        if triangulation not in ("optimal", "linear"):
            raise ValueError(f"triangulation must be 'optimal' or 'linear', got {triangulation!r}")
        self.triangulation = triangulation
        self.max_features = int(max_features)
        self.check_warps = bool(check_warps)
        if points is None:
            step = max(1, self.subset // 2) if step is None else step  # the 2-D rule (dic.Tracker)
            self.points, self.grid_shape, in_roi = grid_points(self.shape, step, self.subset, roi)
            self.step = int(step)
            self.neighbours = None
            strain_window = check_grid_window(strain_window, self.grid_shape)
        else:
            if roi is not None:
                raise ValueError("give either points or roi (the ROI selects grid points), not both")
            self.points = as_points(points, shape=self.shape, image_name="left image")
            self.grid_shape = None
            in_roi = np.ones(self.points.shape[0], dtype=bool)
            spacing = typical_spacing(self.points)
            self.step = max(1, int(round(spacing)))
            self.neighbours = scattered_neighbours(self.points, int(strain_window) ** 2,
                                                   max_distance=strain_window * spacing)
        self.in_roi = in_roi
        self.strain_window = int(strain_window)
        #: propagation reach: a neighbour within ~1.5 grid steps (diagonal included)
        self.radius = 1.5 * self.step + 1e-6
        self._left_ref, self._right_ref = left_ref, right_ref
        self._F = fundamental_matrix(rig)
        #: seconds spent per stage in the constructor (reference) and in the last :meth:`measure`
        self.timings: dict[str, float] = {}
        t0 = time.perf_counter()
        # per-POI pixel masks of the left reference's subsets (a mask or polygon ROI, dic.correlation.subset_masks):
        # the left track and the match left -> right correlate the kept pixels of the left subsets; the right
        # track the pixels they map to through the match (right_track_mask), moved references the region carried
        # into their images (_moved_pixel_masks; docs/stereo.md)
        self.subset_mask = check_subset_mask(subset_mask)
        self.min_kept_fraction = check_min_kept_fraction(min_kept_fraction)
        #: the region that masks the subsets (left reference px; None: none) and whether the right track's are masked
        #: too: a moved reference's subsets are masked by them carried into its images (:meth:`_moved_pixel_masks`)
        self._mask_roi, self._right_track_mask = (roi if self.subset_mask == "region" else None), bool(right_track_mask)
        from .cracks import as_cracks
        from .field3d import grid_neighbours
        from .stereo_cracks import CrackCutStrain, crack_blocked_pixels

        #: declared cracks (dic.stereo_cracks): subsets on their POI's side, strain windows not across
        self.cracks = as_cracks(cracks)
        self.pixel_mask = tracking_pixel_masks(self.points, self.subset, self.shape, roi, self.subset_mask,
                                               blocked_pixels=crack_blocked_pixels(self.cracks))
        self._crack_strain = None
        if self.cracks:
            nb = grid_neighbours(self.grid_shape, self.strain_window) if self.neighbours is None else self.neighbours
            self._crack_strain = CrackCutStrain(self.points, nb, self.cracks)
        # the grid's points outside the region are never correlated: not prepared (a region is often a small part of
        # the image; the prepared subsets are the same bits)
        self.left = Correlator(left_ref, self.points, subset=self.subset, order=self.order, max_iter=self.max_iter,
                               tol=self.tol, device=self.device, pixel_mask=self.pixel_mask,
                               min_kept_fraction=None if self.pixel_mask is None else self.min_kept_fraction,
                               active=None if self.pixel_mask is not None else self.in_roi)
        if self.check_warps:  # the warp check of the match needs it: computed meanwhile, on another thread
            self.left.prefetch_textured_fraction()
        self.timings["reference_prepare_s"] = time.perf_counter() - t0
        self._ideal_left, _ = undistort_points(rig.left, self.points, device=self.device, margin_px=np.inf)
        self.match = self._match() if match is None else self._check_match(match)
        _warn_if_epipolar_mismatch(self.match, self.epipolar_tol_px)
        # POIs outside the ROI are not failures: judge the run on the POIs it was asked for
        _warn_if_mostly_invalid(self.match.status[self.in_roi], "stereo matching (left -> right reference)")
        ok = self.match.valid
        self._matched = np.flatnonzero(ok)
        # the right track's subsets keep the pixels of the left region mapped through the match (right_track_mask)
        self.right_pixel_mask = self._right_pixel_mask(roi if right_track_mask else None, ok) if ok.any() else None
        self.right = self._correlator(right_ref, self.match.points_right[ok], pixel_mask=self.right_pixel_mask) \
            if ok.any() else None
        if self.right is not None and self.check_warps:  # for the first state's right track
            self.right.prefetch_textured_fraction()
        t0 = time.perf_counter()
        self._tri_ref = self._triangulate(self.points, self.match.points_right)
        self.timings["triangulation_s"] = time.perf_counter() - t0
        self._frame = self._choose_frame(frame)
        self._previous = None          # (params_left (N, k), params_right (N, k)) of the last state
        self._before = None            # the same of the state before it (a chain of states: motion_prediction)
        self._previous_images = (None, None)
        self._jac_ref = None           # d(X_ref)/d(image points), for the uncertainty (dic.quality)
        self._basis = {}               # "left"/"right": diag H^-1 and df of the reference subsets, read once
        self._moved: _TrackReference | None = None  # the temporal tracks' reference when not the reference pair
        self._strain_plan: SurfaceStrainPlan | None = None  # grid strain: the reference positions' part, once
        self._deferred: dict = {}      # id(field) -> (field, later()): states measured with complete=False
        self._completing = threading.RLock()  # one complete() at a time (the strain plan, the sigma bases)
        #: "left"/"right": the phase-correlation spectrum of the camera's last image (the next state's base)
        self._spectra: dict[str, _SpectrumMemo] = {}
        # the reference pair's state; its strain and uncertainty are computed when it is first read (reference), or
        # on a sequence's writer thread (reference_field(complete=False), then complete())
        self._reference = self._field(None, index=0, defer=True)

    @property
    def reference(self) -> Field3D:
        """The reference pair's state (:class:`Field3D`, index 0: the match, zero displacement, the shape)."""
        return self.complete(self._reference)

    def reference_field(self, complete: bool = True) -> Field3D:
        """The reference pair's state; ``complete=False``: possibly still without its strain and uncertainty
        (:meth:`complete` fills them, e.g. on a sequence's writer thread while the first state tracks)."""
        return self.complete(self._reference) if complete else self._reference

    # -------------------------------------------------------------------------------------------
    def _correlator(self, image: np.ndarray, points: np.ndarray, pixel_mask=None, active=None) -> Correlator:
        return Correlator(image, points, subset=self.subset, order=self.order, max_iter=self.max_iter, tol=self.tol,
                          device=self.device, pixel_mask=pixel_mask,
                          min_kept_fraction=None if pixel_mask is None else self.min_kept_fraction,
                          active=None if pixel_mask is not None else active)

    def _right_pixel_mask(self, roi, matched: np.ndarray):
        """(M, S*S) bool or None: the right reference subsets' pixels (at the matched points) that the left
        region maps to through the match (:func:`dic.correlation.right_masks.right_tracking_pixel_masks`)."""
        from .correlation.right_masks import right_tracking_pixel_masks

        m = self.match
        return right_tracking_pixel_masks(roi, self.shape, self.subset_mask, self.points[matched],
                                          m.points_right[matched], m.params[matched], self.subset,
                                          cracks=self.cracks)

    def _check_match(self, match: StereoMatch) -> StereoMatch:
        if not isinstance(match, StereoMatch):
            raise ValueError(f"match must be a StereoMatch, got {type(match).__name__}")
        if match.points_left.shape != self.points.shape or not np.allclose(match.points_left, self.points):
            raise ValueError("the given StereoMatch was computed for other points than these")
        if match.params.shape[1] != n_params(self.order):
            raise ValueError(f"the given StereoMatch has order {match.order}, expected {self.order}")
        return match

    def _epipolar(self, idx: np.ndarray, right_points: np.ndarray) -> np.ndarray:
        ur, sr = undistort_points(self.rig.right, right_points, device=self.device, margin_px=np.inf)
        d = epipolar_distance(self._F, self._ideal_left[idx], ur)
        d[sr != TriangulationStatus.OK] = np.nan
        return d

    def _match(self) -> StereoMatch:
        """Left reference -> right reference, guided by the rig's epipolar geometry."""
        L, R = self._left_ref, self._right_ref
        k = n_params(self.order)
        t0 = time.perf_counter()
        n = self.points.shape[0]
        report = _MatchProgress(self._progress, int(np.count_nonzero(self.in_roi & self.left.ready)))
        report("features", 0, 0)

        def epipolar_consistent(pa, pb):
            # epipolar filter on undistorted points (a looser tolerance than for the final match: SIFT
            # keypoints are good to ~0.5 px, and the guess only needs to land within a few px)
            ua, sa = undistort_points(self.rig.left, pa, device=self.device, margin_px=np.inf)
            ub, sb = undistort_points(self.rig.right, pb, device=self.device, margin_px=np.inf)
            d = epipolar_distance(self._F, ua, ub)
            return (d <= max(3.0, 3.0 * self.epipolar_tol_px)) & (sa == 0) & (sb == 0)

        ctx = GuessContext(self.left, L, R, np.zeros((n, k)), zncc_min=self.zncc_min,
                           options={"feature_filter": epipolar_consistent, "max_features": self.max_features,
                                    "radius": max(6.0 * self.subset, 3.0 * self.step), "rig": self.rig})
        guess, has = get_guess("features")(ctx)
        n_feat = ctx.cache["n_features"]
        params6, _ = ctx.cache["features"]
        gradient = np.zeros((2, 2))
        if np.any(has):
            gradient = np.array([[np.median(params6[has, 1]), np.median(params6[has, 2])],
                                 [np.median(params6[has, 4]), np.median(params6[has, 5])]])
        ctx.options["gradient"] = gradient
        current = prepare_current(R, device=self.device)

        def extra(idx, p):
            return self._epipolar(idx, self.points[idx] + _displacement(p, self.order)) <= self.epipolar_tol_px

        epipolar_search = get_guess("epipolar")

        def fallback(idx):
            return epipolar_search(ctx, idx)

        eligible = self.in_roi
        self.timings["features_s"] = time.perf_counter() - t0
        report(f"features ({n_feat} matches)", 0, 0)
        t0 = time.perf_counter()
        try:
            res = correlate(self.left, current, guess, has, SOURCE_FEATURES, eligible=eligible, zncc_min=self.zncc_min,
                            radius=self.radius, extra=extra, fallback=fallback, check_warps=self.check_warps,
                            robust=self.robust, report=report, max_fruitless_rounds=MATCH_FRUITLESS_ROUNDS)
        finally:
            report.close()
        self.timings["match_icgn_s"] = time.perf_counter() - t0
        status = stage_status(res, eligible & self.left.ready, StereoStatus.MATCH_FAILED,
                               StereoStatus.EPIPOLAR_VIOLATION, self.zncc_min)
        ran = res.icgn_status != int(Status.NOT_COMPUTED)
        right = np.full_like(self.points, np.nan)
        right[ran] = self.points[ran] + _displacement(res.params[ran], self.order)
        epi = np.full(self.points.shape[0], np.nan)
        if np.any(ran):
            epi[ran] = self._epipolar(np.flatnonzero(ran), right[ran])
        return StereoMatch(self.points.copy(), right, res.params, res.zncc, res.iterations, res.icgn_status, epi,
                           res.source, status, n_feat, self.order)

    def _triangulate(self, pl: np.ndarray, pr: np.ndarray):
        """Triangulate rows where both points are finite; returns (xyz (N, 3), residual (N,), status (N,))."""
        n = pl.shape[0]
        xyz = np.full((n, 3), np.nan)
        res = np.full(n, np.nan)
        st = np.full(n, int(TriangulationStatus.INVALID_INPUT), dtype=np.int32)
        fin = np.all(np.isfinite(pl), axis=1) & np.all(np.isfinite(pr), axis=1)
        if np.any(fin):
            t = triangulate(self.rig, pl[fin], pr[fin], method=self.triangulation, device=self.device)
            xyz[fin], res[fin], st[fin] = t.points, t.residuals, t.status
        return xyz, res, st

    def _choose_frame(self, frame):
        if isinstance(frame, str):
            if frame == "left":
                return np.eye(3), np.zeros(3), "left"
            if frame == "plane":
                good = self.match.valid & (self._tri_ref[2] == TriangulationStatus.OK)
                if np.count_nonzero(good) < 3:
                    raise ValueError("frame='plane' needs at least 3 matched and triangulated points; "
                                     f"the reference match has {int(np.count_nonzero(good))}")
                R, t = plane_frame(self._tri_ref[0], good)
                return R, t, "plane"
            raise ValueError(f"frame must be one of {_FRAME_CHOICES} or (R_obj_left, t_obj_left), got {frame!r}")
        R, t = as_frame(frame)
        return R, t, "custom"

    # -------------------------------------------------------------------------------------------
    def _track(self, corr: Correlator, image: np.ndarray, previous: np.ndarray | None, eligible: np.ndarray,
               reference_image: np.ndarray, previous_image: np.ndarray | None, frame: np.ndarray | None = None,
               *, side: str, predicted: np.ndarray | None = None, floats: _FloatImages | None = None):
        """One temporal track: the first pass over every POI on the device frame path
        (:meth:`Correlator.run_frame`: the correlator's :class:`kernels.frames.FrameTracker`, buffers allocated
        once per reference, ``frame`` (the image as given: 8/16-bit or float32; default ``image``) converted in
        the prefilter), then propagation, the ``"features"`` fallback and the second opinion
        (:func:`dic.correlation.engine.correlate`) for the POIs it did not accept, on the same prepared frame.
        Bitwise the results of the host path (``prepare_current`` + indexed IC-GN) from the same guesses.

        ``predicted``: (N, k) the previous state's parameters extrapolated at constant velocity (``motion_prediction``;
        NaN rows: none). The first pass starts from them (rows without one from ``previous`` moved by the median
        predicted step) and is kept when it accepts at least :data:`PREDICTION_MIN_ACCEPTED` of the points the
        previous state had; otherwise (a jump, a sudden stop) it runs again from ``previous`` + the global shift,
        as without a prediction. The global shift is not measured when the prediction holds.

        ``image`` and ``previous_image`` may be raw 8/16-bit images: ``floats`` makes their float copies where the
        global shift or the features need them (default: a converter of this call's own)."""
        k = n_params(self.order)
        n = corr.points.shape[0]
        frame = image if frame is None else frame
        floats = _FloatImages() if floats is None else floats
        # initial guess: the previous state's parameters (or zero) plus the global integer shift
        # between the previous image (or the reference) and this one, by phase correlation. 2nd-order
        # IC-GN converges slowly from 2-3 px away on fine speckle (measured on the 5 MP benchmark: a
        # 3 px motion took 32 iterations on average, many hitting max_iter; within 0.5 px, 6-8)
        prior = np.zeros((n, k)) if previous is None else np.nan_to_num(previous)
        base = reference_image if previous is None or previous_image is None else previous_image
        tracked = eligible & corr.ready
        # the shift of the tracked points' neighbourhood (the specimen), measured on the bounding box of their
        # reference and previous positions + a margin (SHIFT_WINDOW_MARGIN_PX)
        at = corr.points[tracked]
        if previous is not None:
            at = np.concatenate([at, at + previous[tracked][:, [0, k // 2]]])
        window = phase_window(at, image.shape, corr.subset // 2 + SHIFT_WINDOW_MARGIN_PX)
        spectrum = self._spectra.setdefault(side, _SpectrumMemo()).at(window)  # kept for the next state
        made = []

        def context() -> GuessContext:
            """The guesses' context (the images as float32), made when the shift or the features are needed."""
            if not made:
                made.append(GuessContext(corr, reference_image, floats(image), prior, zncc_min=self.zncc_min,
                                         options={"base": floats(base), "spectrum": spectrum,
                                                  "max_features": self.max_features,
                                                  "radius": max(6.0 * self.subset, 3.0 * self.step)}))
            return made[0]

        features = get_guess("features")  # fallback for POIs that fail: computed once per image, when needed

        def fallback(idx):
            return features(context(), idx)

        corr.limit_frames(eligible)  # the first pass at the POIs this track uses only (the others are skipped)
        first = None
        if predicted is not None and previous is not None:
            guess = _predicted_start(prior, predicted, tracked, k)
            if guess is not None:
                first = corr.run_frame(frame, guess, name="current image")
                had = tracked & np.all(np.isfinite(previous), axis=1)  # the points the previous state had
                kept = accepted_mask(first["status"], first["zncc"], self.zncc_min) & had
                if np.count_nonzero(kept) < PREDICTION_MIN_ACCEPTED * np.count_nonzero(had):
                    first = None  # the motion changed: start again from the previous state + the global shift
            if first is not None:
                has = np.ones(n, dtype=bool)
                src = SOURCE_PREVIOUS
        if first is None:
            ctx = context()
            guess, has = get_guess("shift")(ctx)
            src = SOURCE_NONE if previous is None else SOURCE_PREVIOUS
            if ctx.cache["shift_applied"] and previous is None:
                src = SOURCE_GLOBAL
            first = corr.run_frame(frame, guess, name="current image")
        current = corr.frame_current(frame.dtype)
        return correlate(corr, current, guess, has, src, eligible=eligible, zncc_min=self.zncc_min,
                         radius=self.radius, fallback=fallback, max_seeds=max(64, n),
                         min_fallback=max(16, int(0.01 * n)), check_warps=self.check_warps, robust=self.robust,
                         first=first)

    def measure(self, left_cur, right_cur, *, index: int = 1, use_previous: bool = True, warn: bool = True,
                complete: bool = True) -> Field3D:
        """Track a current pair from the reference pair and return its :class:`Field3D`.

        ``use_previous``: start IC-GN from the parameters of the last measured state (a sequence's
        previous frame); otherwise from zero displacement. POIs that fail are retried from SIFT
        feature matches and from converged neighbours. ``warn=False``: no warning when the tracks
        leave (almost) every point invalid (a caller that may track the state again from another
        reference calls :meth:`warn_if_mostly_invalid` for the result it keeps). ``complete=False``: the
        state's strain and uncertainty are left to :meth:`complete` (NaN until then; everything else, the
        statuses and the next state's start included, is there), so that a sequence computes them on its
        writer thread while the next state tracks (:func:`dic.sequence.stereo_sequence`).
        """
        # 8/16-bit images stay as they are (the frame path converts them in its prefilter); float copies are made
        # where a step needs them (the global shift, the features, the composed check): floats
        L, R = _check_pair(left_cur, right_cur, "current", convert=_raw_or_float)
        floats = _FloatImages()
        frame_l, frame_r = _frame(left_cur, L), _frame(right_cur, R)
        if L.shape != self.shape:
            raise ValueError(f"the current images are {L.shape[1]}x{L.shape[0]} px but the reference images are "
                             f"{self.shape[1]}x{self.shape[0]} px")
        prev = self._previous if use_previous else None
        prev_images = self._previous_images if prev is not None else (None, None)
        # constant velocity: previous + (previous - the one before), where both are known (Lagrangian parameters)
        before = self._before if prev is not None and self.motion_prediction == "velocity" else None
        pred = None if before is None else tuple(_extrapolated(p, b) for p, b in zip(prev, before))
        pred_l = pred_r = None
        matched = self._matched
        mv = self._moved
        if mv is None:  # the reference pair
            corr_l, corr_r, ref_l, ref_r = self.left, self.right, self._left_ref, self._right_ref
            eligible_l, eligible_r = self.match.valid, np.ones(matched.size, dtype=bool)
            guess_l = None if prev is None else prev[0]
            guess_r = None if prev is None else prev[1][matched]
            if pred is not None:
                pred_l, pred_r = pred[0], pred[1][matched]
        else:  # a later state's pair (move_reference): the points it can track, from their positions there
            corr_l, corr_r, ref_l, ref_r = mv.left, mv.right, mv.left_image, mv.right_image
            eligible_l, eligible_r = self.match.valid & mv.usable, mv.usable[matched]
            guess_l = guess_r = None
            if prev is not None:
                guess_l = mv.relative(prev[0], "left", self.order)
                guess_r = mv.relative(prev[1][matched], "right", self.order)
                # a point placed by interpolation whose previous parameters are still those it failed with in
                # that state starts from zero increment (and the global shift), not from its failed warp
                fresh_l, fresh_r = mv.unmeasured(prev[0], "left"), mv.unmeasured(prev[1][matched], "right")
                guess_l[fresh_l] = np.nan
                guess_r[fresh_r] = np.nan
                if pred is not None:
                    pred_l = mv.relative(pred[0], "left", self.order)
                    pred_r = mv.relative(pred[1][matched], "right", self.order)
                    pred_l[fresh_l] = np.nan
                    pred_r[fresh_r] = np.nan
        self.timings = {}
        t0 = time.perf_counter()
        tl = self._track(corr_l, L, guess_l, eligible_l, ref_l, prev_images[0], frame_l, side="left",
                         predicted=pred_l, floats=floats)
        self.timings["track_left_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if corr_r is not None:
            tr = self._track(corr_r, R, guess_r, eligible_r, ref_r, prev_images[1], frame_r, side="right",
                             predicted=pred_r, floats=floats)
        else:
            tr = None
        self.timings["track_right_s"] = time.perf_counter() - t0
        if mv is not None:  # back to the reference state (Lagrangian)
            tl = mv.compose(tl, "left", self.order)
            tr = None if tr is None else mv.compose(tr, "right", self.order)
        checked = (self._check_composed(tl, tr, floats(L), floats(R)) if mv is not None and self.verify_zncc is not None
                   else None)
        f = self._field((tl, tr), index=index, composed=checked, defer=not complete)
        if mv is not None:  # valid here, placed in the tracks' reference by interpolation (not valid there)
            f.reference_interpolated = f.valid & ~mv.valid
        if warn and self._tracks_judged():
            _warn_if_mostly_invalid(f.status[self.in_roi], f"stereo tracking of state {index}")
        # the state before the next one: this state's start. A state measured from the reference pair (no previous
        # state: zero, the first of a chain) has the reference pair's parameters before it, as stored for state 0
        self._before = prev if prev is not None else self._reference_params()
        self._previous = (f.details["params_left"], f.details["params_right"])
        # the next state's base images: the float copies made here (their spectra are kept by identity), else raw
        self._previous_images = (floats.made(L), floats.made(R))
        return f

    def _check_composed(self, tl, tr, L, R):
        """(failed (N,) bool, zncc_left (N,), zncc_right (N,)): the composed tracks checked against the reference
        pair (:class:`dic.correlation.stereo_verify.StereoComposedCheck`, ``verify_zncc``)."""
        from .correlation.stereo_verify import StereoComposedCheck

        if self._composed_check is None:
            m = self.match
            self._composed_check = StereoComposedCheck(self._left_ref, self._right_ref, self.points,
                                                       m.points_right[self._matched], self._matched, self.subset,
                                                       self.verify_zncc, device=self.device, spread=self.verify_spread,
                                                       # the reference pair's subsets checked on their kept pixels
                                                       pixel_mask_left=self.pixel_mask,
                                                       pixel_mask_right=self.right_pixel_mask)
        return self._composed_check.check(tl.params, tl.accepted, L, None if tr is None else tr.params,
                                          None if tr is None else tr.accepted, R)

    def _tracks_judged(self) -> bool:
        # (a failed reference match has been reported already; the warning is about the tracks)
        return np.count_nonzero(self.match.valid) >= MOSTLY_INVALID_FRACTION * np.count_nonzero(self.in_roi)

    def warn_if_mostly_invalid(self, field: Field3D) -> None:
        """The warning :meth:`measure` gives when a state's tracks leave (almost) every point invalid."""
        if self._tracks_judged():
            _warn_if_mostly_invalid(field.status[self.in_roi], f"stereo tracking of state {field.index}")

    def _reference_params(self) -> tuple[np.ndarray, np.ndarray]:
        """(params_left (N, k), params_right (N, k)) of the reference pair's state: zero at the matched points, NaN
        elsewhere (its ``details``, state 0 of a result file)."""
        zero = np.where(self.match.valid[:, None], 0.0, np.nan) * np.ones((1, n_params(self.order)))
        return zero, zero.copy()

    def set_previous(self, params_left, params_right, images=None, before=None) -> None:
        """Set the initial guess of the next :meth:`measure`: parameters (N, 6|12) of the left and right tracks.

        E.g. ``field.details["params_left"]``, ``field.details["params_right"]`` of the previous
        state read back from a result file. NaN rows (points that failed) start from zero.
        ``images``: that state's ``(left, right)`` images, optional (their global shift to the next
        images is added to the guess). ``before``: optional ``(params_left, params_right)`` of the state before
        it, for ``motion_prediction="velocity"`` (a sequence resumed after state k gives state k - 1's, so that
        state k + 1 starts as it would have in one run).
        """
        k = n_params(self.order)
        n = self.points.shape[0]

        def checked(params_left, params_right, what):
            pl = np.asarray(params_left, dtype=np.float64)
            pr = np.asarray(params_right, dtype=np.float64)
            if pl.shape != (n, k) or pr.shape != (n, k):
                raise ValueError(f"{what} parameters must both have shape {(n, k)}, got {pl.shape} and {pr.shape}")
            return pl, pr

        previous = checked(params_left, params_right, "previous")
        if before is not None:
            if not isinstance(before, (tuple, list)) or len(before) != 2:
                raise ValueError("before must be a (params_left, params_right) pair")
            before = checked(before[0], before[1], "before")
        self._previous, self._before = previous, before
        self._previous_images = (None, None) if images is None else _check_pair(images[0], images[1], "previous")

    @property
    def has_previous(self) -> bool:
        """Whether the next :meth:`measure` can start from a previous state (one measured, or :meth:`set_previous`)."""
        return self._previous is not None

    def saved_previous(self):
        """The previous state the next :meth:`measure` starts from, as an opaque value for :meth:`restore_previous`
        (a sequence that measures a state twice, from two references, starts both from the same one)."""
        return self._previous, self._previous_images, self._before

    def restore_previous(self, saved) -> None:
        """Start the next :meth:`measure` from a previous state kept by :meth:`saved_previous`."""
        self._previous, self._previous_images, self._before = saved

    @property
    def trackable(self) -> np.ndarray:
        """(N,) bool: the points the temporal tracks' reference can track: valid in the reference pair, or, after
        :meth:`move_reference`, valid in that state or placed there by local interpolation."""
        return self._reference.valid if self._moved is None else self._moved.usable

    @property
    def reference_index(self) -> int:
        """The state whose images the temporal tracks use as their reference (0: the reference pair)."""
        return 0 if self._moved is None else self._moved.index

    def move_reference(self, left_image=None, right_image=None, state: Field3D | None = None) -> None:
        """Track the next states from a later state's image pair instead of the reference pair.

        ``state``: that pair's :class:`Field3D` (measured by this object or read back from a result
        file; its ``details`` hold ``params_left``, ``params_right``). The left and right tracks get
        new reference subsets, in ``left_image`` and ``right_image``, at the positions the original
        POIs have in that state (points not valid there: the displacement interpolated from valid
        neighbours, :func:`dic.correlation.lagrangian.moved_points`); each later state's parameters
        are composed back onto that state's, so every :meth:`measure` stays relative to the
        reference pair (Lagrangian) and records ``reference_index``. A point not valid in
        ``state`` but matched in the reference pair gets every left and right track parameter
        there interpolated from its valid neighbours
        (:func:`dic.correlation.lagrangian.fill_reference`); where both fills come from a close
        Delaunay triangle of valid points (``supported``) it is tracked again from that place and
        is valid once both tracks are accepted (each such valid point is marked in the measured
        field's ``reference_interpolated`` (N,) bool attribute, set on every state measured from
        a moved reference). The other points not valid in ``state`` are not tracked and keep that
        state's status. The left -> right match of the reference pair is kept.
        ``move_reference()`` (no state) goes back to the reference pair.

        Raises ``ValueError`` for images of another size, a state of other points or without
        parameters, or a state with no valid point.
        """
        if state is None:
            if left_image is not None or right_image is not None:
                raise ValueError("move_reference: give the state measured on these images (a Field3D) with them")
            self._moved = None
            return
        if left_image is None or right_image is None:
            raise ValueError("move_reference: give the state's left and right images")
        L, R = _check_pair(left_image, right_image, "new reference")
        if L.shape != self.shape:
            raise ValueError(f"the new reference images are {L.shape[1]}x{L.shape[0]} px but the reference images are "
                             f"{self.shape[1]}x{self.shape[0]} px")
        if isinstance(state, Field3D):  # (anything else is refused by plan, below)
            self.complete(state)  # a state measured with complete=False: its uncertainty is carried to the new reference
        planned = _TrackReference.plan(self, state)  # a state that cannot serve is refused with the tracks unchanged
        self._moved = None  # the previous moved reference's data are freed before the new ones are prepared
        self._moved = planned.prepare(self, L, R)

    def _correlators_at(self, left_image, right_image, points_left, points_right, masks=(None, None),
                        active_left=None):
        return (self._correlator(left_image, points_left, pixel_mask=masks[0], active=active_left),
                self._correlator(right_image, points_right, pixel_mask=masks[1]) if points_right.shape[0] else None)

    def _moved_pixel_masks(self, moved_left, moved_right):
        """The pixel masks ``(left (N, S*S), right (M, S*S))`` (each bool or None: every pixel) of a moved
        reference's subsets: the region and the declared cracks of the reference pair carried into the state's images
        by that state's measured tracks (docs/stereo.md, "Masks and cracks carried to a moved reference").

        Left (``moved_left``, every POI): as a 2-D moved reference (:func:`dic.sequence.track2d._carry_for`): the
        region's pixels carried into the left image by the left track's field
        (:meth:`dic.correlation.lagrangian.MovedReference.carry_region`), the cracks carried likewise
        (:meth:`~dic.correlation.lagrangian.MovedReference.carry_cracks`) and each subset cut at them
        (:meth:`~dic.correlation.lagrangian.MovedReference.crack_blocked_pixels`). Right (``moved_right``, the
        matched POIs): the rule of the reference pair's right masks (:func:`dic.correlation.right_masks
        .mapped_pixel_masks`: a right subset pixel is kept when the left region holds it and no crack separates
        it from the POI) with each POI's reference match composed with its right track's warp in the state: the
        right subset pixel of the state is mapped back through both into the left reference image. None, None
        without region and cracks (the unmasked kernels: results bit for bit as before)."""
        from .correlation.right_masks import mapped_pixel_masks
        from .correlation.subset_masks import REGION_MARGIN_PX, region_pixel_mask, shrink_region

        region_px = region_pixel_mask(self._mask_roi, self.shape) if self._mask_roi is not None else None
        if region_px is None and not self.cracks:
            return None, None
        pixel_region, blocked = moved_left.carry_cut(region_px, self.cracks, self.subset)
        left = tracking_pixel_masks(moved_left.points, self.subset, self.shape, pixel_region, "region",
                                    blocked_pixels=blocked)
        right_region = region_px if self._right_track_mask else None
        if moved_right.points.shape[0] == 0 or (right_region is None and not self.cracks):
            return left, None
        if right_region is not None:
            right_region = shrink_region(right_region, REGION_MARGIN_PX)
        matched = self._matched
        kept = mapped_pixel_masks(right_region, self.shape, self.points[matched], moved_right.points,
                                  _match_then_track(self.match.params[matched], moved_right.params, self.points[matched],
                                                    self.match.points_right[matched]),
                                  self.subset, cracks=self.cracks)
        return left, (None if kept.all() else kept)

    def _tri_points(self, pl: np.ndarray, pr: np.ndarray) -> np.ndarray:
        return self._triangulate(pl, pr)[0]

    def _triangulation_jacobian(self, pl: np.ndarray, pr: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """(N, 3, 4) d(xyz)/d(pl, pr) (mm/px) of the triangulated points ``xyz`` (N, 3) mm, left camera frame:
        analytic for the optimal triangulation (one launch), central differences of 8 triangulations for the
        linear one."""
        if self.triangulation == "optimal":
            return optimal_triangulation_jacobian(self.rig, pl, pr, xyz, device=self.device)
        return triangulation_jacobian(self._tri_points, pl, pr)

    def _sigmas(self, tracks, pl_cur: np.ndarray, pr_cur: np.ndarray, valid: np.ndarray,
                xyz_cur: np.ndarray, mv) -> dict[str, np.ndarray]:
        """Per-point std of the match and both tracks (N, 2) px, the noise (N, 3) behind them, and
        their propagation to the reference positions and displacements (N, 3) mm in the output frame.
        ``xyz_cur`` (N, 3) mm, left camera frame: the triangulation of ``pl_cur``, ``pr_cur``; ``mv``: the
        tracks' moved reference when they were measured (None: the reference pair)."""
        n = self.points.shape[0]
        m = self.match
        for side, corr in (("left", self.left), ("right", self.right)):
            if side not in self._basis and corr is not None:
                self._basis[side] = sigma_basis(corr.subsets)
        sig_m, noise_m, _ = displacement_sigma(self._basis["left"], m.zncc, m.valid, self.noise_sigma)
        sig_l = np.full((n, 2), np.nan)
        sig_r = np.full((n, 2), np.nan)
        rho_r = np.zeros(n)  # u-v correlation of each stage's error (dic.quality.SigmaBasis.rho_uv)
        rho_l = None
        noise_l = noise_r = np.nan
        if tracks is not None:
            tl, tr = tracks
            basis = self._basis if mv is None else mv.basis()
            sig_l, noise_l, _ = displacement_sigma(basis["left"], tl.zncc, tl.accepted, self.noise_sigma)
            rho_l = basis["left"].rho_uv
            if tr is not None:
                sr, noise_r, _ = displacement_sigma(basis["right"], tr.zncc, tr.accepted, self.noise_sigma)
                sig_r[self._matched] = sr
                if basis["right"].rho_uv is not None:
                    rho_r[self._matched] = basis["right"].rho_uv
            if mv is not None:  # the moved reference's own uncertainty adds in quadrature
                sig_l, sig_r = mv.add_sigma(sig_l, sig_r)
        if self._jac_ref is None:
            self._jac_ref = self._triangulation_jacobian(self.points, m.points_right, self._tri_ref[0])
        R = self._frame[0]
        # propagated at the valid points only (the others' are NaN): each row is computed on its own, so these
        # are bit for bit the rows of propagating every point (a grid over a region holds many invalid points)
        rows = np.flatnonzero(valid)
        sig_xyz = np.full((n, 3), np.nan)
        sig_uvw = np.full((n, 3), np.nan)
        if rows.size:
            def at(a):
                return None if a is None else np.asarray(a)[rows]

            jac_cur = None
            if tracks is not None:
                jac_cur = self._triangulation_jacobian(pl_cur[rows], pr_cur[rows], xyz_cur[rows])
            sx, su = propagate_stereo_sigma(self._jac_ref[rows], sig_m[rows], jac_cur, at(sig_l), at(sig_r),
                                            rotation=R, rho_match=at(self._basis["left"].rho_uv), rho_left=at(rho_l),
                                            rho_right=at(rho_r))
            sig_xyz[rows] = sx
            if su is not None:
                sig_uvw[rows] = su
        return {"sigma_match_px": sig_m, "sigma_left_px": sig_l, "sigma_right_px": sig_r,
                # per point like every details array (exports expect N rows); the same in every row
                "noise_sigma_grey": np.tile([noise_m, noise_l, noise_r], (n, 1)), "sigma_xyz_mm": sig_xyz,
                "sigma_uvw_mm": sig_uvw}

    # -------------------------------------------------------------------------------------------
    def _field(self, tracks, index: int, composed=None, defer: bool = False) -> Field3D:
        """The state's Field3D from its tracks (None: the reference pair). ``defer``: its strain and uncertainty
        left to :meth:`complete` (placeholders until then)."""
        n = self.points.shape[0]
        k = n_params(self.order)
        m = self.match
        xyz_ref, res_ref, tri_ref = self._tri_ref
        status = m.status.astype(np.int8).copy()
        details = {"match_status": m.icgn_status, "guess_source": m.guess_source,
                   "triangulation_ref_status": tri_ref, "points_right_ref": m.points_right,
                   "params_stereo": m.params}
        if tracks is None:
            xyz_cur, res_cur, tri_cur = xyz_ref, res_ref, tri_ref
            epi_cur = m.epipolar_px
            z_left = np.where(m.valid, 1.0, np.nan)
            z_right = z_left.copy()
            pl_cur, pr_cur = self.points.copy(), m.points_right.copy()
            details.update(track_left_status=np.where(m.valid, int(Status.CONVERGED), int(Status.NOT_COMPUTED)).astype(np.int32),
                           track_right_status=np.where(m.valid, int(Status.CONVERGED), int(Status.NOT_COMPUTED)).astype(np.int32),
                           **dict(zip(("params_left", "params_right"), self._reference_params())))
        else:
            tl, tr = tracks
            matched = self._matched
            pl_cur = np.full((n, 2), np.nan)
            pr_cur = np.full((n, 2), np.nan)
            z_left = np.where(np.isfinite(tl.zncc), tl.zncc, np.nan)
            z_right = np.full(n, np.nan)
            left_ok = tl.accepted
            right_ok = np.zeros(n, dtype=bool)
            st_right = np.full(n, int(Status.NOT_COMPUTED), dtype=np.int32)
            p_right = np.full((n, k), np.nan)
            ran_l = tl.icgn_status != int(Status.NOT_COMPUTED)
            pl_cur[ran_l] = self.points[ran_l] + _displacement(tl.params[ran_l], self.order)
            if tr is not None:
                ran_r = tr.icgn_status != int(Status.NOT_COMPUTED)
                sel = matched[ran_r]
                pr_cur[sel] = m.points_right[sel] + _displacement(tr.params[ran_r], self.order)
                z_right[matched] = tr.zncc
                right_ok[matched] = tr.accepted
                st_right[matched] = tr.icgn_status
                p_right[matched] = tr.params
            # per-stage status, first failure wins (reference stages already in `status`)
            fl = stage_status(tl, m.valid, StereoStatus.TRACK_LEFT_FAILED, StereoStatus.TRACK_LEFT_FAILED, self.zncc_min)
            fr = np.full(n, int(StereoStatus.NOT_COMPUTED), dtype=np.int8)
            if tr is not None:
                fr[matched] = stage_status(tr, np.ones(matched.size, dtype=bool), StereoStatus.TRACK_RIGHT_FAILED,
                                            StereoStatus.TRACK_RIGHT_FAILED, self.zncc_min)
            # LOW_ZNCC and IMPLAUSIBLE_WARP keep their own code; other failures name the stage
            kept = (StereoStatus.LOW_ZNCC, StereoStatus.IMPLAUSIBLE_WARP)
            for stage, failed in ((fl, StereoStatus.TRACK_LEFT_FAILED), (fr, StereoStatus.TRACK_RIGHT_FAILED)):
                worse = (status == StereoStatus.OK) & (stage != StereoStatus.OK)
                status[worse] = np.where(np.isin(stage, kept), stage, failed)[worse]
            if self._moved is not None:  # lost before the moved reference and not placed there: that state's status
                lost = m.valid & ~self._moved.usable
                status[lost] = self._moved.status[lost]
            if composed is not None:  # composed tracks below verify_zncc against the reference pair (_check_composed)
                status[(status == StereoStatus.OK) & composed[0]] = StereoStatus.COMPOSED_MISMATCH
                details.update(composed_zncc_left=composed[1], composed_zncc_right=composed[2])
            both = left_ok & right_ok
            use_l = np.where(both[:, None], pl_cur, np.nan)
            use_r = np.where(both[:, None], pr_cur, np.nan)
            t0 = time.perf_counter()
            xyz_cur, res_cur, tri_cur = self._triangulate(use_l, use_r)
            self.timings["triangulation_s"] = time.perf_counter() - t0
            epi_cur = np.full(n, np.nan)
            if np.any(both):
                epi_cur[both] = epipolar_residuals(self.rig, pl_cur[both], pr_cur[both], device=self.device)
            details.update(track_left_status=tl.icgn_status, track_right_status=st_right,
                           params_left=tl.params, params_right=p_right)
        # epipolar check of the current state, triangulation of both states
        ok = status == StereoStatus.OK
        status[ok & ~(epi_cur <= self.epipolar_tol_px)] = StereoStatus.EPIPOLAR_VIOLATION
        ok = status == StereoStatus.OK
        tri_bad = (tri_ref != TriangulationStatus.OK) | (tri_cur != TriangulationStatus.OK)
        status[ok & tri_bad] = StereoStatus.TRIANGULATION_FAILED
        valid = status == StereoStatus.OK
        # coordinates in the output frame
        R, t, name = self._frame
        xyz_ref_f = xyz_ref @ R.T + t
        uvw = (xyz_cur - xyz_ref) @ R.T
        uvw[~valid] = np.nan
        # reference positions are kept wherever the reference match and its triangulation are good
        xyz_ref_f[~(m.valid & (tri_ref == TriangulationStatus.OK))] = np.nan
        camera_center = t  # the left camera centre (origin of the left frame) in the output frame
        mv = self._moved if tracks is not None else None  # the tracks' reference now (it may move before `later` runs)
        timings = self.timings

        def later():
            """The state's uncertainty and strain: what it reads was fixed above (and the plans kept on self)."""
            t0 = time.perf_counter()
            sig = self._sigmas(tracks, pl_cur, pr_cur, valid, xyz_cur, mv)
            timings["uncertainty_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            if self.grid_shape is not None:
                # the reference positions' part of the fits worked out once and kept while the valid points stay
                # the same (SurfaceStrainPlan: bit for bit surface_strain_grid)
                if self._strain_plan is None or not np.array_equal(self._strain_plan.X, xyz_ref_f, equal_nan=True):
                    self._strain_plan = SurfaceStrainPlan(xyz_ref_f, self.grid_shape, self.strain_window,
                                                          camera_center=camera_center, strain_type=self.strain_type)
                strain = self._strain_plan(np.nan_to_num(uvw), valid)
            else:
                strain = surface_strain(xyz_ref_f, np.nan_to_num(uvw), valid, self.neighbours,
                                        camera_center=camera_center, strain_type=self.strain_type)
            if self._crack_strain is not None:  # the windows a declared crack cuts, fitted on their own side
                strain = self._crack_strain.apply(strain, xyz_ref_f, np.nan_to_num(uvw), valid,
                                                  camera_center=camera_center, strain_type=self.strain_type)
            timings["strain_s"] = time.perf_counter() - t0
            return sig, strain

        if defer:  # placeholders, in the order of the complete field's details (filled by complete())
            sig = dict.fromkeys(SIGMA_DETAILS)
            strain = {name: np.full(n, np.nan) for name in ("exx", "eyy", "exy")}
            strain.update(normal=np.full((n, 3), np.nan), strain_valid=np.zeros(n, dtype=bool))
        else:
            with self._completing:  # (a deferred state's completion may be running on another thread)
                sig, strain = later()
        details.update(sig)
        details.update(triangulation_status=tri_cur, points_left_cur=pl_cur, points_right_cur=pr_cur)
        zs = np.where(np.isfinite(m.zncc), m.zncc, np.nan)
        f = Field3D(
            points=self.points, grid_shape=self.grid_shape,
            X=xyz_ref_f[:, 0], Y=xyz_ref_f[:, 1], Z=xyz_ref_f[:, 2], U=uvw[:, 0], V=uvw[:, 1], W=uvw[:, 2],
            exx=strain["exx"], eyy=strain["eyy"], exy=strain["exy"], normal=strain["normal"],
            zncc_stereo=zs, zncc_left=z_left, zncc_right=z_right,
            epipolar_ref_px=m.epipolar_px, epipolar_px=epi_cur, reprojection_ref_px=res_ref, reprojection_px=res_cur,
            status=status, strain_valid=strain["strain_valid"], R_frame_left=R, t_frame_left=t, frame_name=name,
            index=int(index), details=details, reference_index=self.reference_index if tracks is not None else 0,
            strain_type=self.strain_type,
        )
        if defer:
            self._deferred[id(f)] = (f, later)
        return f

    def complete(self, field: Field3D) -> Field3D:
        """Compute the strain and the uncertainty of a state measured with ``measure(..., complete=False)`` into
        ``field`` (its ``exx``, ``eyy``, ``exy``, ``normal``, ``strain_valid`` and the ``sigma_*`` and
        ``noise_sigma_grey`` details); returns it. Nothing to do for a complete field. Safe from any thread: one
        completion runs at a time (they share the strain plan), each once; the result is bit for bit that of
        ``measure(...)`` (the moved reference is the one the state was measured from)."""
        _check_field(field)
        entry = self._deferred.get(id(field))
        if entry is None or entry[0] is not field:
            return field
        with self._completing:
            if self._deferred.get(id(field)) is entry:
                sig, strain = entry[1]()
                field.details.update(sig)
                field.exx, field.eyy, field.exy = strain["exx"], strain["eyy"], strain["exy"]
                field.normal, field.strain_valid = strain["normal"], strain["strain_valid"]
                del self._deferred[id(field)]
        return field

    def discard(self, field: Field3D) -> None:
        """Forget the pending strain and uncertainty of a state measured with ``complete=False`` that is not kept
        (e.g. measured again from another reference)."""
        _check_field(field)
        with self._completing:
            entry = self._deferred.get(id(field))
            if entry is not None and entry[0] is field:
                del self._deferred[id(field)]


#: the details of a state's uncertainty (StereoCorrelation._sigmas), in their order
SIGMA_DETAILS = ("sigma_match_px", "sigma_left_px", "sigma_right_px", "noise_sigma_grey", "sigma_xyz_mm",
                 "sigma_uvw_mm")


def _check_field(field) -> None:
    if not isinstance(field, Field3D):
        raise ValueError(f"field must be a Field3D (a state measured by this StereoCorrelation), got "
                         f"{type(field).__name__}")


#: px beyond the tracked subsets that the global shift of a temporal track is measured on (its phase-correlation
#: window, :func:`kernels.search.phase_window`): the specimen's shift, not the whole image's; shifts up to this
#: keep every subset inside the window in both images (larger ones are still found while most of it overlaps)
SHIFT_WINDOW_MARGIN_PX = 64


class _SpectrumMemo:
    """:func:`kernels.search.phase_spectrum` that keeps the spectrum of the last image it was given, found again
    by identity: a camera's current image of one state is the base of the next state's global shift
    (``GuessContext.options["spectrum"]``), so each image is transformed once, not twice. ``window``: the
    ``(rows, cols)`` slices of the images transformed (:meth:`at`), None: the whole image."""

    def __init__(self):
        self.image = None
        self.spectrum = None
        self.window = None

    def at(self, window) -> "_SpectrumMemo":
        """Transform the part ``window`` of the next images (the kept spectrum is dropped when it changes)."""
        if window != self.window:
            self.window, self.image, self.spectrum = window, None, None
        return self

    def __call__(self, image: np.ndarray):
        if image is not self.image:
            self.spectrum = phase_spectrum(image if self.window is None else image[self.window])
            self.image = image
        return self.spectrum


class _TrackReference:
    """The temporal tracks' reference when it is a later state (:meth:`StereoCorrelation.move_reference`).

    One :class:`dic.correlation.lagrangian.MovedReference` per camera (``moved_left`` at every POI,
    ``moved_right`` at the matched ones: the right track's points): that state's Lagrangian parameters,
    those of the points not valid there interpolated from their valid neighbours (left and right track
    each); ``usable`` (N,) marks the points the tracks follow from this state: valid there, or matched in
    the reference pair and placed by a close Delaunay triangle of valid points on both sides. The new
    reference subsets sit at the whole pixels nearest to the POIs' positions in that state, and the
    warp measured there is carried to the moved point exactly before it is composed.
    """

    def __init__(self, index: int, moved_left, moved_right, valid, status, matched, sigma_left, sigma_right):
        self.index = index
        self.moved_left, self.moved_right = moved_left, moved_right
        self.valid, self.status, self.matched = valid, status, matched
        self.sigma_left, self.sigma_right = sigma_left, sigma_right
        self.usable = moved_left.usable
        self.left = self.right = self.left_image = self.right_image = None
        self._basis: dict = {}

    @classmethod
    def plan(cls, sc: "StereoCorrelation", state) -> "_TrackReference":
        """The moved reference of ``state`` without its correlators (:meth:`prepare`): ValueError when the
        state cannot serve (not a state of these points, no valid point), before anything is freed."""
        from .correlation.lagrangian import MovedReference, reference_anchors

        if not isinstance(state, Field3D):
            raise ValueError(f"move_reference: state must be a Field3D, got {type(state).__name__}")
        details = state.details
        n, k = sc.points.shape[0], n_params(sc.order)
        pl, pr = details.get("params_left"), details.get("params_right")
        if pl is None or pr is None:
            raise ValueError("move_reference: the state has no track parameters (params_left, params_right in its details)")
        pl, pr = np.asarray(pl, dtype=np.float64), np.asarray(pr, dtype=np.float64)
        status = np.asarray(state.status, dtype=np.int8)
        if pl.shape != (n, k) or pr.shape != (n, k) or status.shape != (n,):
            raise ValueError(f"move_reference: the state has {status.shape[0]} points and parameters of shape "
                             f"{pl.shape}; this correlation has {n} points and {k} parameters per point")
        index = int(state.index)
        valid = status == StereoStatus.OK
        if not np.any(valid):
            raise ValueError(f"state {index} has no valid point and cannot serve as a reference")
        matched = sc._matched
        # a point whose left or right track disagrees with its neighbours' (a false match) is no anchor of the
        # moved reference (its error would be composed into every later state): placed like an invalid point
        anchors = reference_anchors(sc.points, pl, valid)
        if matched.size:
            anchors[matched] &= reference_anchors(sc.match.points_right[matched], pr[matched], valid[matched])
        if not np.any(anchors):
            raise ValueError(f"state {index} has no valid point and cannot serve as a reference")
        # the points not valid in the state: every parameter interpolated from the valid ones; tracked again
        # where both tracks' fills are local and the reference match holds
        left = MovedReference(index, sc.points, pl, anchors, sc.order)
        right = MovedReference(index, sc.match.points_right[matched], pr[matched], anchors[matched], sc.order)
        sup_r = np.zeros(n, dtype=bool)
        sup_r[matched] = right.supported
        usable = anchors | (sc.match.valid & left.supported & sup_r)
        left.narrow(usable)
        right.narrow(usable[matched])
        sig = [details.get(name) for name in ("sigma_left_px", "sigma_right_px")]
        sig = [None if s is None or np.shape(s) != (n, 2) else _fill_sigma(sc.points, np.asarray(s, dtype=np.float64),
                                                                            anchors, usable) for s in sig]
        return cls(index, left, right, anchors, status, matched, sig[0], sig[1])

    def prepare(self, sc: "StereoCorrelation", L: np.ndarray, R: np.ndarray) -> "_TrackReference":
        """The reference subsets of both cameras in the state's images ``L``, ``R`` (at the moved points)."""
        self.left_image, self.right_image = L, R
        masks = sc._moved_pixel_masks(self.moved_left, self.moved_right)  # the region and cracks carried there
        # the left subsets of the points this reference tracks only (matched and usable: the left track's eligible)
        self.left, self.right = sc._correlators_at(L, R, self.moved_left.points, self.moved_right.points, masks,
                                                   active_left=sc.match.valid & self.usable)
        return self

    def _moved(self, side: str):
        return self.moved_left if side == "left" else self.moved_right

    def unmeasured(self, params: np.ndarray, side: str) -> np.ndarray:
        """The points placed by interpolation (usable, not valid in the state) whose ``params`` are still
        the state's own: not measured since (their warp there failed), so not a guess to start from."""
        return self._moved(side).unmeasured(params)

    def relative(self, params: np.ndarray, side: str, order: int) -> np.ndarray:
        """A later state's Lagrangian parameters as seen from this reference's (whole-pixel) points:
        the initial guess of the next state. NaN where either is unknown."""
        return self._moved(side).relative_at_points(params)

    def compose(self, res, side: str, order: int):
        """A track result against this reference, back on the reference pair (Lagrangian)."""
        moved = self._moved(side)
        return replace(res, params=moved.compose(res.params), accepted=res.accepted & moved.usable)

    def basis(self) -> dict:
        if not self._basis:
            self._basis["left"] = sigma_basis(self.left.subsets)
            if self.right is not None:
                self._basis["right"] = sigma_basis(self.right.subsets)
        return self._basis

    def add_sigma(self, sig_l: np.ndarray, sig_r: np.ndarray):
        if self.sigma_left is not None:
            sig_l = np.hypot(sig_l, self.sigma_left)
        if self.sigma_right is not None:
            sig_r = np.hypot(sig_r, self.sigma_right)
        return sig_l, sig_r


def _match_then_track(match_params: np.ndarray, track_params: np.ndarray, points_left: np.ndarray,
                      points_right: np.ndarray) -> np.ndarray:
    """(M, 6): the affine warps from the left reference image to a state's right image, per matched POI: the
    reference match ``match_params`` (M, 6|12; left -> right at the rounded POIs ``points_left`` (M, 2) px) followed
    by the right track's Lagrangian warp ``track_params`` (M, 6|12; right reference -> state, at the rounded
    matched points ``points_right`` (M, 2) px), in the layout of :data:`kernels.conventions.PARAMS_1ST` about the
    rounded POI. Second-order terms are left out, as :func:`dic.correlation.right_masks.mapped_pixel_masks` does.
    A left pixel ``c_l + d`` goes to ``x = c_l + d + t_m + G_m d`` in the right reference, then to
    ``x + t_r + G_r (x - c_r)``: translation ``t_m + t_r + G_r (c_l + t_m - c_r)``, gradient
    ``(I + G_r)(I + G_m) - I``. NaN where either is unknown."""
    from kernels.conventions import round_half_away

    pm, pt = np.asarray(match_params, np.float64), np.asarray(track_params, np.float64)
    hm, ht = pm.shape[1] // 2, pt.shape[1] // 2
    tm = np.stack([pm[:, 0], pm[:, hm]], axis=1)
    tr = np.stack([pt[:, 0], pt[:, ht]], axis=1)
    gm = np.stack([pm[:, 1:3], pm[:, hm + 1:hm + 3]], axis=1)  # (M, 2, 2): rows (u, v), columns (x, y)
    gr = np.stack([pt[:, 1:3], pt[:, ht + 1:ht + 3]], axis=1)
    cl, cr = round_half_away(points_left).astype(np.float64), round_half_away(points_right).astype(np.float64)
    t = tm + tr + np.einsum("mij,mj->mi", gr, cl + tm - cr)
    eye = np.eye(2)[None]
    g = np.einsum("mij,mjk->mik", eye + gr, eye + gm) - eye
    out = np.stack([t[:, 0], g[:, 0, 0], g[:, 0, 1], t[:, 1], g[:, 1, 0], g[:, 1, 1]], axis=1)
    out[~(np.all(np.isfinite(pm), axis=1) & np.all(np.isfinite(pt), axis=1))] = np.nan
    return out


#: the temporal tracks' initial guess from the states before (StereoCorrelation(motion_prediction=...))
MOTION_PREDICTIONS = ("velocity", "none")

#: the constant-velocity start is kept when its first pass accepts at least this fraction of the points the
#: previous state had (smooth motion: all but a few; a jump or a sudden stop of more than a few pixels: few)
PREDICTION_MIN_ACCEPTED = 0.95


def _extrapolated(previous: np.ndarray, before: np.ndarray) -> np.ndarray:
    """(N, k) ``previous + (previous - before)``: every parameter at constant velocity; NaN where either is NaN."""
    return previous + (previous - before)


def _predicted_start(prior: np.ndarray, predicted: np.ndarray, tracked: np.ndarray, k: int) -> np.ndarray | None:
    """(N, k) the first pass's start from a constant-velocity prediction: ``predicted`` where it is finite, elsewhere
    ``prior`` (the previous parameters, 0 where none) moved by the median predicted ``u, v`` step of the tracked
    points; None when no tracked point has a prediction."""
    rows = np.all(np.isfinite(predicted), axis=1)
    steps = (predicted - prior)[rows & tracked][:, [0, k // 2]]
    if steps.shape[0] == 0:
        return None
    guess = prior.copy()
    step = np.median(steps, axis=0)
    guess[:, 0] += step[0]
    guess[:, k // 2] += step[1]
    guess[rows] = predicted[rows]
    return guess


def _fill_sigma(points: np.ndarray, sigma: np.ndarray, valid: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """A moved reference's per-point track std (N, 2): at the points placed by interpolation, that of the
    nearest valid point (the interpolation's own error is not counted)."""
    fill = usable & ~valid
    good = valid & np.all(np.isfinite(sigma), axis=1)
    if not np.any(fill) or not np.any(good):
        return sigma
    from scipy.spatial import cKDTree

    _, j = cKDTree(points[good]).query(points[fill], k=1)
    out = sigma.copy()
    out[fill] = sigma[good][j]
    return out


def stereo(rig, left_ref, right_ref, left_cur=None, right_cur=None, *, points=None, step: int | None = None, roi=None,
           subset: int = 21, order: int = 1, frame="left", epipolar_tol_px: float = 1.0, zncc_min: float = 0.8,
           strain_window: int = 5, device=None, **options) -> Field3D:
    """Stereo DIC of one reference pair, and of one current pair when given.

    Parameters
    ----------
    rig : calibration.stereo.StereoRig (cameras ``left``, ``right``; ``R_right_left``, ``t_right_left`` mm),
        or a rig file in any format Specula reads (:func:`as_rig`).
    left_ref, right_ref : (H, W) grey images of the reference state.
    left_cur, right_cur : (H, W) grey images of a current state, optional (both or neither).
    points, step, roi, subset, order, frame, epipolar_tol_px, zncc_min, strain_window, device :
        see :class:`StereoCorrelation`; ``options`` passes ``max_iter``, ``tol``, ``triangulation``,
        ``max_features``, ``robust``, ``subset_mask``, ``min_kept_fraction``.

    Returns
    -------
    Field3D
        The reference shape (``U = V = W = 0``, zero strain) when no current pair is given, else
        the current state's displacements and strains. For sequences use
        :class:`StereoCorrelation` or :func:`dic.sequence.stereo_sequence`.

    Raises
    ------
    ValueError
        Images of different sizes, a rig calibrated for another image size, bad parameters.
    """
    if (left_cur is None) != (right_cur is None):
        raise ValueError("give both left_cur and right_cur (a current stereo pair) or neither")
    sc = StereoCorrelation(rig, left_ref, right_ref, points=points, step=step, roi=roi, subset=subset, order=order,
                           frame=frame, epipolar_tol_px=epipolar_tol_px, zncc_min=zncc_min,
                           strain_window=strain_window, device=device, **options)
    if left_cur is None:
        return sc.reference
    return sc.measure(left_cur, right_cur)
