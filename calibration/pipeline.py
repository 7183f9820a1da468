"""Calibration from images: phase-shifted image stacks → wrapped phase → dot centres → cameras and rigs.

This module chains the pieces of the calibration package the way the paper behind Specula
("Stereo-camera calibration for large-scale DIC measurements with active phase targets and planar
mirrors", Optics Express 27(6), 9040, 2019, doi:10.1364/OE.27.009040, Section 2, Steps 1–5) uses
them, from the recorded images to the files:

1. Each *view* is one pose of the monitor (direct or seen in a mirror) recorded as the N
   phase-shifted images of a :class:`~calibration.targets.PhaseTarget` (``target.steps`` images,
   display order), or as its dense sequence (``target.n_dense_images`` images). A view is given as
   an (N, H, W) array, a list of N arrays or image files, a folder holding exactly those images, or
   a glob pattern.
2. :func:`detect_view` demodulates the stack (``kernels.phase`` through
   :func:`calibration.detect.demodulate_images`) and finds the dots, their ids and whether the
   view is mirrored (:func:`calibration.detect.detect_dots`); in dense mode it decodes the
   per-pixel screen coordinates (:func:`calibration.detect.decode_dense`). A view that cannot be
   used is *dropped* with the reason, never silently.
3. :func:`calibrate_intrinsics_from_images` — Zhang's method with the direct and mirrored views in
   one bundle (:func:`calibration.intrinsics.calibrate_intrinsics`; the mirrored flag comes from
   the detection) → :class:`IntrinsicsCalibration`.
4. :func:`calibrate_mirror_from_images` — the camera's pose relative to the monitor from K ≥ 3
   mirror tilts (:func:`calibration.mirror.mirror_extrinsics`, closed form + bundle adjustment) on
   the dots every view shows → :class:`MirrorCalibration` (saved as a *pose file* that keeps the
   observations, so that the stereo step can re-adjust both cameras jointly).
5. :func:`calibrate_rig_from_mirrors` — the rig from the two cameras' mirror calibrations
   (:func:`calibration.stereo.rig_from_mirror`, the paper's ``H_LR = H_TR (H_TL)⁻¹``) and, with
   views of the monitor that both cameras see (the paper's last frame), the joint bundle adjustment
   :func:`calibration.mirror.joint_mirror_stereo`; further common views are reconstructed as a
   check (:func:`calibration.stereo.reconstruct_target`) → :class:`RigCalibration`.
6. :func:`stereo_from_checkerboards` — the conventional alternative: ``cv2.stereoCalibrate`` from
   checkerboard pairs (:func:`calibration.stereo.stereo_calibrate`).

Dense mode (``mode="dense"``): the monitor shows two orthogonal sets of phase-shifted linear
fringes (:meth:`PhaseTarget.dense_images`); every camera pixel that sees it gets its screen
coordinate. The pipeline does not use the pixels one by one (each carries the phase noise of one
pixel): it locates a regular grid of screen points (every ``dense_spacing`` screen px, the same
grid in every view) by a local quadratic fit of the decoded map over the pixels around each point
(:func:`dense_grid_points`); the mirror extrinsics need exactly that (the same target points in
every view), and the intrinsics get many well-averaged points per view. Choose the target's
finest dense period so that it spans at least ~8 camera pixels in every view (coarser fringes
survive blur and pixel integration; finer ones lose their modulation).

Frames and units: docs/conventions.md (mm, px, camera frame x right / y down / z forward, pixel
(0, 0) the centre of the top-left pixel); target frame: :mod:`calibration.targets`.
"""
from __future__ import annotations

import dataclasses
import glob
import math
import os
import re
from dataclasses import dataclass, field

import numpy as np

from .camera import Camera, _check_schema, _read_json, _write_json
from .detect import (DenseDecoding, DetectionError, DotDetection, decode_dense, demodulate_images,
                     detect_checkerboard, detect_dots)
from .intrinsics import DISTORTION_MODELS, IntrinsicsResult, calibrate_intrinsics
from .mirror import JointMirrorResult, MirrorExtrinsicsResult, joint_mirror_stereo, mirror_extrinsics
from .stereo import (StereoCalibrationResult, StereoRig, reconstruct_target, rig_from_mirror,
                     stereo_calibrate)
from .targets import CheckerboardTarget, PhaseTarget
from .uncertainty import rig_covariance_from_intrinsics

__all__ = [
    "IMAGE_SUFFIXES",
    "MIRROR_POSE_SCHEMA",
    "MIRROR_POSE_SCHEMA_VERSION",
    "ViewResult",
    "StereoView",
    "IntrinsicsCalibration",
    "MirrorCalibration",
    "RigCalibration",
    "CheckerboardStereo",
    "list_view_files",
    "read_stack",
    "detect_view",
    "detect_views",
    "dense_grid_points",
    "dense_view_points",
    "calibrate_intrinsics_from_images",
    "calibrate_intrinsics_from_detections",
    "calibrate_mirror_from_images",
    "calibrate_mirror_from_detections",
    "detect_stereo_view",
    "calibrate_rig_from_mirrors",
    "stereo_from_checkerboards",
]

#: Image files a view folder or glob may hold (case-insensitive suffixes).
IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".bmp")

#: Name and version of the pose file written by :meth:`MirrorCalibration.save`.
MIRROR_POSE_SCHEMA = "specula.mirror_calibration"
MIRROR_POSE_SCHEMA_VERSION = 1

MODES = ("dots", "dense")
#: Floor of :func:`detect_view`'s vignetting test (relative modulation change across a dot's fit
#: window): about twice the largest value on the fully lit dots of the virtual lab's direct views.
MIN_VIGNETTING_SLOPE = 0.015


# ------------------------------------------------------------------------------------------------
# reading views
# ------------------------------------------------------------------------------------------------
def _natural_key(path: str):
    parts = re.split(r"(\d+)", os.path.basename(path))
    return [int(p) if p.isdigit() else p.lower() for p in parts], path


def list_view_files(source) -> list[str]:
    """The image files of one view, in natural order (``img_2`` before ``img_10``).

    ``source`` is a folder (all files with a suffix in :data:`IMAGE_SUFFIXES`), a glob pattern
    (``"view03/*.png"``) or a list of file paths (kept in the given order). Raises ``ValueError``
    when nothing matches.
    """
    if isinstance(source, (list, tuple)):
        files = [os.fspath(p) for p in source]
        if not files:
            raise ValueError("a view given as a list of files must not be empty")
        return files
    src = os.fspath(source)
    if os.path.isdir(src):
        files = [os.path.join(src, f) for f in os.listdir(src) if f.lower().endswith(IMAGE_SUFFIXES)]
        if not files:
            raise ValueError(f"view folder {src!r} holds no image files ({', '.join(IMAGE_SUFFIXES)})")
        return sorted(files, key=_natural_key)
    if os.path.isfile(src):
        raise ValueError(
            f"{src!r} is a single file; a view is a folder or a glob pattern of its N phase-shifted images "
            "(quote the pattern so that the shell does not expand it, e.g. 'view03/*.png')")
    if glob.has_magic(src):
        files = [f for f in glob.glob(src) if os.path.isfile(f)]
        if not files:
            raise ValueError(f"the pattern {src!r} matches no files")
        return sorted(files, key=_natural_key)
    raise ValueError(f"view {src!r} is neither a folder, nor an existing glob pattern, nor a file list")


def _read_image(path: str) -> np.ndarray:
    if not os.path.isfile(path):
        raise ValueError(f"image file not found: {path}")
    if os.path.getsize(path) == 0:
        raise ValueError(f"image file is empty: {path}")
    suffix = os.path.splitext(path)[1].lower()
    if suffix not in IMAGE_SUFFIXES:
        raise ValueError(f"unsupported image format {suffix!r} for {path}; expected one of {', '.join(IMAGE_SUFFIXES)}")
    try:
        if suffix in (".tif", ".tiff"):
            import tifffile

            arr = tifffile.imread(path)
        else:
            import imageio.v3 as iio

            arr = iio.imread(path)
    except Exception as exc:  # the readers raise many types for corrupt files
        raise ValueError(f"cannot read image {path}: {exc}") from None
    arr = np.asarray(arr)
    if arr.ndim == 3 and arr.shape[2] in (3, 4) and np.all(arr[..., 0] == arr[..., 1]) and np.all(arr[..., 1] == arr[..., 2]):
        arr = arr[..., 0]  # grey stored as RGB(A)
    if arr.ndim != 2:
        raise ValueError(f"{path}: expected a grey-level image (H, W), got shape {arr.shape}; convert colour images to grey")
    return arr


def read_stack(source, n_images: int | None = None) -> np.ndarray:
    """One view's image stack as an (N, H, W) array.

    ``source``: an (N, H, W) array, a list of N (H, W) arrays, a list of N image files, a folder or a
    glob pattern (:func:`list_view_files`). ``n_images`` (e.g. ``target.steps``) checks the count.
    Grey levels keep their scale and dtype (8/16-bit). Raises ``ValueError`` for missing, unreadable
    or colour images, mismatched sizes or a wrong count.
    """
    if isinstance(source, np.ndarray):
        stack = source
        what = "array"
    elif isinstance(source, (list, tuple)) and source and all(isinstance(s, np.ndarray) for s in source):
        shapes = {s.shape for s in source}
        if len(shapes) > 1:
            raise ValueError(f"the images of a view must have the same shape, got {sorted(shapes)}")
        stack = np.stack(source)
        what = "list of arrays"
    else:
        files = list_view_files(source)
        imgs = [_read_image(f) for f in files]
        shapes = {im.shape for im in imgs}
        if len(shapes) > 1:
            raise ValueError(f"the images of view {_describe(source)} differ in size: {sorted(shapes)}")
        if n_images is not None and len(imgs) != n_images:
            raise ValueError(f"view {_describe(source)} holds {len(imgs)} images but the target needs {n_images} "
                             f"(one per phase step, in display order)")
        return np.stack(imgs)
    if stack.ndim != 3 or stack.shape[1] == 0 or stack.shape[2] == 0:
        raise ValueError(f"a view must be a stack (N, H, W) of phase-shifted images, got a {what} of shape {stack.shape}")
    if n_images is not None and stack.shape[0] != n_images:
        raise ValueError(f"the view holds {stack.shape[0]} images but the target needs {n_images}")
    if not np.issubdtype(stack.dtype, np.number) or np.issubdtype(stack.dtype, np.complexfloating):
        raise ValueError(f"images must be real grey levels, got dtype {stack.dtype}")
    return stack


def _describe(source) -> str:
    if isinstance(source, np.ndarray):
        return f"array{tuple(source.shape)}"
    if isinstance(source, (list, tuple)):
        if source and isinstance(source[0], np.ndarray):
            return f"list of {len(source)} arrays"
        return f"[{os.fspath(source[0])!s}, ...] ({len(source)} files)" if source else "[]"
    return os.fspath(source)


def _view_name(source, index: int) -> str:
    if isinstance(source, (str, os.PathLike)):
        s = os.fspath(source).rstrip("/\\")
        return s if s else f"view{index}"
    return f"view{index}"


# ------------------------------------------------------------------------------------------------
# detection
# ------------------------------------------------------------------------------------------------
@dataclass
class ViewResult:
    """What one view gave: the dots (or the dense decoding) or why it was dropped.

    Attributes
    ----------
    name : str
        The view's label (its folder or pattern, or ``view<i>``).
    image_size : (width, height) or None
    detection : DotDetection or None
        Dot mode: image points, ids, object points, per-point quality, ``mirrored``.
    dense : DenseDecoding or None
        Dense mode: screen coordinates per pixel.
    error : str or None
        Why the view was dropped (``None`` when usable).
    preview : (h, w) float32 or None
        The wrapped phase (rad) subsampled by ``preview_step`` (for figures).
    removed : list of (id, misfit)
        Dots the detector found but :func:`detect_view` removed because their phase fit is poor
        (``misfit`` = residual × modulation relative to the view's median; see ``max_misfit``).
    vignetted : list of (id, slope)
        Dots removed because the modulation falls off across their fit window (``slope``: the
        relative change centre → window edge, see ``max_slope``): partly vignetted, e.g. by a
        mirror's edge.
    """

    name: str
    image_size: tuple | None = None
    detection: DotDetection | None = None
    dense: DenseDecoding | None = None
    error: str | None = None
    preview: np.ndarray | None = None
    preview_step: int = 1
    removed: list = field(default_factory=list)
    vignetted: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.error is None

    @property
    def mirrored(self) -> bool | None:
        if self.detection is not None:
            return bool(self.detection.mirrored)
        if self.dense is not None:
            return self.dense.mirrored
        return None

    @property
    def n_points(self) -> int:
        if self.detection is not None:
            return len(self.detection)
        if self.dense is not None:
            return int(self.dense.mask.sum())
        return 0

    def summary(self) -> str:
        if not self.ok:
            return f"{self.name}: dropped — {self.error}"
        kind = "mirrored" if self.mirrored else "direct"
        if self.detection is not None:
            d = self.detection
            q = np.median(d.sigma_px) if np.any(np.isfinite(d.sigma_px)) else float("nan")
            extra = (f"; removed {len(self.removed)} dot(s) with a poor phase fit (ids "
                     f"{', '.join(str(i) for i, _ in self.removed)})") if self.removed else ""
            if self.vignetted:
                extra += (f"; removed {len(self.vignetted)} vignetted dot(s) (ids "
                          f"{', '.join(str(i) for i, _ in self.vignetted)})")
            return (f"{self.name}: {len(d)} dots, {kind}, blur σ ≈ {d.blur_sigma:.1f} px, "
                    f"median centre σ {q:.4f} px{extra}")
        return f"{self.name}: {self.n_points} decoded pixels, {kind}"


def _check_phase_target(target):
    if not isinstance(target, PhaseTarget):
        raise ValueError(f"target must be a calibration.targets.PhaseTarget (load it with "
                         f"calibration.targets.load_target), got {type(target).__name__}")


def _check_mode(mode):
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")


def detect_view(source, target: PhaseTarget, *, mode: str = "dots", name: str | None = None,
                min_modulation: float = 3.0, correct_blur: bool | None = None, min_points: int = 4,
                max_misfit: float | None = 1.5, max_slope: float | None = 3.0, dense_erode: int = 2,
                device=None) -> ViewResult:
    """Demodulate one view and find the target in it.

    Parameters
    ----------
    source : view (see :func:`read_stack`)
        ``target.steps`` images (``mode="dots"``) or ``target.n_dense_images`` (``mode="dense"``).
    target : PhaseTarget
        The target the monitor showed.
    mode : ``"dots"`` or ``"dense"``
    min_modulation : float
        Pixels with a lower fringe modulation (grey levels) are ignored.
    correct_blur : bool or None
        Dot mode: run the detector's defocus-bias correction (pass 2 of
        :func:`calibration.detect.detect_dots`); ``None`` keeps the detector's default.
    min_points : int
        Fewer dots (or decoded pixels / 100 in dense mode) drop the view.
    max_misfit : float or None
        Dot mode: remove dots whose phase-fit residual, scaled by their modulation (the residual
        expected from noise alone goes as 1 / modulation), exceeds ``max_misfit`` times the view's
        median. Such dots do not follow the radial phase model: in the virtual lab, the dots near a
        mirror's edge, whose defocus blur the edge cuts (vignetting makes the blur spot lopsided), came
        out at 1.6–2.8 times the median and 0.05–0.3 px off, while every dot of the direct views stayed
        below 1.2. None keeps every dot.
    max_slope : float or None
        Dot mode: remove dots whose modulation falls off across their fit window (partial
        vignetting): those whose ``DotDetection.modulation_slope`` (relative modulation change from
        the dot's centre to its window's edge, plane fit) exceeds ``max_slope`` times the view's
        median, and at least :data:`MIN_VIGNETTING_SLOPE`. Where a mirror's edge (0.4 m from the
        lens) cuts part of the pupil, the pixels see a truncated, off-centre defocus blur and the
        phase there is shifted; the misfit test misses most of these dots when the cell is small
        (the residual stays low, the centre moves). In the virtual lab (full resolution) the direct
        views' dots (blur σ 1-7 px, tilts up to 30°) all had a slope ≤ 0.008 and the fully lit
        dots of mirrored views ≤ 0.008 (6×3 target) and ≤ 0.037 (24×12 target, view median 0.013);
        the vignetted ones 0.02-0.17 (6×3, 0.04-0.18 px off) and 0.13-0.78 (24×12, 0.5-4.2 px off).
        None keeps every dot.
    dense_erode : int
        Dense mode: pixels this close to the edge of the decoded area are discarded.

    Returns
    -------
    ViewResult
        With ``error`` set (and nothing else) when the target could not be found or identified.
        Unreadable files and wrong image counts raise ``ValueError`` instead: they are mistakes
        in the input, not properties of the view.
    """
    _check_phase_target(target)
    _check_mode(mode)
    n_img = target.steps if mode == "dots" else target.n_dense_images
    stack = read_stack(source, n_img)
    name = name if name is not None else _view_name(source, 0)
    size = (int(stack.shape[2]), int(stack.shape[1]))
    if mode == "dense":
        try:
            dec = decode_dense(stack, target, min_modulation=min_modulation, erode=dense_erode, device=device)
        except (DetectionError, ValueError) as exc:
            return ViewResult(name, size, error=f"dense decoding failed: {exc}")
        n = int(dec.mask.sum())
        if n < 100 * min_points:
            return ViewResult(name, size, error=f"only {n} pixels decoded (need {100 * min_points})")
        if dec.mirrored is None:
            return ViewResult(name, size, error="could not tell whether the view is mirrored")
        return ViewResult(name, size, dense=dec)
    phase, mod, _, valid = demodulate_images(stack, target, min_modulation=min_modulation, device=device)
    step = max(1, int(math.ceil(max(size) / 800)))
    preview = np.where(valid, phase, np.nan)[::step, ::step].astype(np.float32)
    try:
        extra = {} if correct_blur is None else {"correct_blur": bool(correct_blur)}
        det = detect_dots(phase, mod, target, mask=valid, min_modulation=min_modulation, **extra)
    except DetectionError as exc:
        return ViewResult(name, size, error=f"target not found: {exc}", preview=preview, preview_step=step)
    except np.linalg.LinAlgError as exc:
        # a numerically degenerate view (e.g. dots only a few pixels apart): one dropped view, not a lost session
        return ViewResult(name, size, error=f"target not found: degenerate geometry in the dot fit ({exc})",
                          preview=preview, preview_step=step)
    if not (np.all(np.isfinite(det.image_points))):
        det = _subset_detection(det, np.all(np.isfinite(det.image_points), axis=1))
    det, removed, vignetted = filter_detection(det, max_misfit=max_misfit, max_slope=max_slope, min_points=min_points)
    if len(det) < min_points:
        return ViewResult(name, size, error=f"only {len(det)} dots identified (need {min_points})", preview=preview,
                          preview_step=step)
    return ViewResult(name, size, detection=det, preview=preview, preview_step=step, removed=removed,
                      vignetted=vignetted)


def filter_detection(det: DotDetection, *, max_misfit: float | None = 1.5, max_slope: float | None = 3.0,
                     min_points: int = 4):
    """The dot filters of :func:`detect_view` (see its ``max_slope`` and ``max_misfit``) on a detection.

    Returns ``(kept DotDetection, removed [(id, misfit)], vignetted [(id, slope)])``. A filter that
    would leave fewer than ``min_points`` dots is skipped."""
    if not isinstance(det, DotDetection):
        raise ValueError(f"det must be a calibration.detect.DotDetection, got {type(det).__name__}")
    vignetted = []
    if max_slope is not None and len(det) >= 4 and det.modulation_slope is not None:
        slope = det.modulation_slope
        finite = slope[np.isfinite(slope)]
        if finite.size:
            thr = max(MIN_VIGNETTING_SLOPE, max_slope * float(np.median(finite)))
            bad = ~(slope <= thr)
            if bad.any() and (~bad).sum() >= min_points:
                vignetted = [(int(i), float(m)) for i, m in zip(det.ids[bad], slope[bad])]
                det = _subset_detection(det, ~bad)
    removed = []
    if max_misfit is not None and len(det) >= 4:
        q = det.residual_rms * det.modulation
        if np.all(np.isfinite(q)) and np.median(q) > 0:
            misfit = q / np.median(q)
            bad = misfit > max_misfit
            if bad.any() and (~bad).sum() >= min_points:
                removed = [(int(i), float(m)) for i, m in zip(det.ids[bad], misfit[bad])]
                det = _subset_detection(det, ~bad)
    return det, removed, vignetted


def _subset_detection(det: DotDetection, keep) -> DotDetection:
    keep = np.asarray(keep)
    return DotDetection(image_points=det.image_points[keep], ids=det.ids[keep], object_points=det.object_points[keep],
                        residual_rms=det.residual_rms[keep], sigma_px=det.sigma_px[keep],
                        modulation=det.modulation[keep], n_pixels=det.n_pixels[keep], mirrored=det.mirrored,
                        blur_sigma=det.blur_sigma,
                        modulation_slope=None if det.modulation_slope is None else det.modulation_slope[keep])


def detect_views(sources, target: PhaseTarget, *, names=None, progress=None, **kwargs) -> list[ViewResult]:
    """:func:`detect_view` for each view of ``sources`` (a list). ``names`` labels them;
    ``progress(i, view_result)`` is called after each view (e.g. to print)."""
    if isinstance(sources, (str, os.PathLike)) or (isinstance(sources, np.ndarray) and sources.ndim == 3):
        raise ValueError("sources must be a list of views (one folder, glob, file list or array per view)")
    sources = list(sources)
    if names is not None and len(names) != len(sources):
        raise ValueError(f"got {len(names)} names for {len(sources)} views")
    out = []
    for i, src in enumerate(sources):
        nm = names[i] if names is not None else _view_name(src, i)
        res = detect_view(src, target, name=nm, **kwargs)
        out.append(res)
        if progress is not None:
            progress(i, res)
    return out


# ------------------------------------------------------------------------------------------------
# dense correspondences on a common grid of screen points
# ------------------------------------------------------------------------------------------------
def dense_grid_points(decoding: DenseDecoding, screen_points, *, radius: float | None = None,
                      min_pixels: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Image position of given screen points in a dense decoding (local quadratic inverse fit).

    For each screen point ``p`` (screen px), the decoded pixels whose screen coordinate lies within
    ``radius`` screen px of ``p`` are fitted with a quadratic map screen → image (6 coefficients per
    image coordinate, least squares); its value at ``p`` is the image point. A point is kept only
    when at least ``min_pixels`` pixels surround it on all sides (no extrapolation).

    Returns ``(image_points (M, 2) with NaN rows for points not found, found (M,) bool)``.
    ``radius`` defaults to 3 image pixels' worth of screen px (from the median magnification).
    """
    from scipy.spatial import cKDTree

    if not isinstance(decoding, DenseDecoding):
        raise ValueError(f"decoding must be a DenseDecoding, got {type(decoding).__name__}")
    P = np.asarray(screen_points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 2 or not np.all(np.isfinite(P)):
        raise ValueError(f"screen_points must be a finite (M, 2) array of screen px, got shape {P.shape}")
    ys, xs = np.nonzero(decoding.mask)
    out = np.full((len(P), 2), np.nan)
    if len(xs) < min_pixels:
        return out, np.zeros(len(P), dtype=bool)
    S = decoding.screen_xy[ys, xs]
    if radius is None:
        # screen px per image px from the decoded map's gradient
        gx = np.gradient(decoding.screen_xy[..., 0], axis=1)
        gy = np.gradient(decoding.screen_xy[..., 1], axis=0)
        scale = np.nanmedian(np.sqrt(np.abs(gx * gy)))
        radius = 3.0 * (scale if np.isfinite(scale) and scale > 0 else 1.0)
    tree = cKDTree(S)
    neigh = tree.query_ball_point(P, r=radius)
    for m, idx in enumerate(neigh):
        if len(idx) < min_pixels:
            continue
        idx = np.asarray(idx)
        d = (S[idx] - P[m]) / radius
        # surrounded: pixels on both sides along both screen axes
        if not (d[:, 0].min() < -0.3 and d[:, 0].max() > 0.3 and d[:, 1].min() < -0.3 and d[:, 1].max() > 0.3):
            continue
        A = np.stack([np.ones(len(d)), d[:, 0], d[:, 1], d[:, 0] ** 2, d[:, 0] * d[:, 1], d[:, 1] ** 2], axis=1)
        B = np.stack([xs[idx], ys[idx]], axis=1).astype(np.float64)
        coef, *_ = np.linalg.lstsq(A, B, rcond=None)
        out[m] = coef[0]
    found = np.all(np.isfinite(out), axis=1)
    return out, found


def _dense_screen_grid(target: PhaseTarget, spacing: float) -> np.ndarray:
    w, h = target.screen
    margin = spacing / 2
    xs = np.arange(margin, w - margin + 1e-9, spacing)
    ys = np.arange(margin, h - margin + 1e-9, spacing)
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def dense_view_points(decoding: DenseDecoding, spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Correspondences of one dense view on the screen grid ``(i, j) * spacing`` (screen px).

    Returns ``(image_points (M, 2) px, object_points (M, 3) mm, ids (M,))`` for the grid points that
    :func:`dense_grid_points` finds; ``ids = j * 100000 + i`` name the grid points (the same in every
    view)."""
    if not spacing > 0:
        raise ValueError(f"the dense grid spacing must be > 0 screen px, got {spacing!r}")
    S = decoding.screen_xy[decoding.mask]
    if len(S) == 0:
        return np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    lo = np.floor(S.min(axis=0) / spacing).astype(int)
    hi = np.ceil(S.max(axis=0) / spacing).astype(int)
    ii, jj = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
    P = np.stack([ii.ravel(), jj.ravel()], axis=1) * float(spacing)
    q, found = dense_grid_points(decoding, P)
    ids = (jj.ravel() * 100000 + ii.ravel())[found]
    X = np.concatenate([P[found] * decoding.pixel_pitch, np.zeros((int(found.sum()), 1))], axis=1)
    return q[found], X, ids.astype(np.int64)


# ------------------------------------------------------------------------------------------------
# intrinsics
# ------------------------------------------------------------------------------------------------
@dataclass
class IntrinsicsCalibration:
    """Intrinsic calibration from images (:func:`calibrate_intrinsics_from_images`).

    ``result`` is the :class:`~calibration.intrinsics.IntrinsicsResult` (camera, RMS, per-view RMS,
    σ, poses, residuals, views dropped by outlier rejection — their indices refer to ``used``).
    ``views`` lists every input view; ``used`` the indices (into ``views``) that entered the bundle.
    ``image_points`` / ``object_points`` / ``point_ids`` are what entered the bundle, per used view;
    ``dropped_points`` lists ``(view name, point id, |residual| px, threshold px)`` for every point removed as
    an outlier (e.g. a dot whose blur is cut by the edge of a mirror).
    """

    result: IntrinsicsResult
    views: list
    used: list
    image_points: list
    object_points: list
    mode: str = "dots"
    point_ids: list = field(default_factory=list)
    dropped_points: list = field(default_factory=list)

    @property
    def camera(self) -> Camera:
        return self.result.camera

    @property
    def dropped(self) -> list[tuple[str, str]]:
        """(view name, reason) for every view left out: detection failures and outlier rejection."""
        out = [(v.name, v.error) for v in self.views if not v.ok]
        for d in self.result.dropped:
            out.append((self.views[self.used[d.index]].name, d.reason))
        return out

    def view_rms(self) -> dict:
        """RMS (px) per kept view, by view name."""
        return {self.views[self.used[i]].name: float(r) for i, r in zip(self.result.view_indices, self.result.per_view_rms)}

    def report(self) -> str:
        res = self.result
        cam = res.camera
        lines = [f"intrinsic calibration of {cam.name or 'camera'} ({self.mode} mode, model {res.model}): "
                 f"{len(res.view_indices)} of {len(self.views)} views, "
                 f"{sum(len(self.image_points[i]) for i in res.view_indices)} points, RMS {res.rms:.4f} px"
                 + (", views weighted by their noise" if res.weighting == "per_view" else "")]
        values = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}
        for i, nm in enumerate(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")):
            if i < cam.dist.size:
                values[nm] = float(cam.dist[i])
        lines.append("  parameter        value            σ")
        for nm, val in values.items():
            if nm in res.std:
                unit = " px" if nm in ("fx", "fy", "cx", "cy") else ""
                lines.append(f"  {nm:>4} = {val: 16.8g} ± {res.std[nm]:.3g}{unit}")
            else:
                lines.append(f"  {nm:>4} = {val: 16.8g}   (fixed)")
        weighted = res.view_sigma is not None
        lines.append("  view                                   points  kind      RMS (px)" + ("  noise σ (px)" if weighted else ""))
        rms_of = {int(i): float(r) for i, r in zip(res.view_indices, res.per_view_rms)}
        sigma_of = {int(i): float(sv) for i, sv in zip(res.view_indices, res.view_sigma)} if weighted else {}
        for u, vi in enumerate(self.used):
            v = self.views[vi]
            kind = "mirrored" if v.mirrored else "direct"
            r = rms_of.get(u)
            lines.append(f"  {_short(v.name, 38):38s} {len(self.image_points[u]):6d}  {kind:8s}  "
                         + (f"{r:.4f}" if r is not None else "dropped")
                         + (f"    {sigma_of[u]:.4f}" if u in sigma_of else ""))
        for nm, why in self.dropped:
            lines.append(f"  dropped {nm}: {why}")
        lines.extend(_removed_lines(self.views))
        lines.extend(_dropped_points_lines(self.dropped_points))
        return "\n".join(lines)

    def metadata(self) -> dict:
        """JSON-ready summary stored in the camera file."""
        res = self.result
        method = ("Zhang (cv2.calibrateCameraExtended), phase-target dots" if self.mode == "dots"
                  else "Zhang (cv2.calibrateCameraExtended), dense phase decoding")
        if res.weighting == "per_view":
            method += ", then a bundle adjustment weighting each view by its estimated noise"
        extra = {}
        if res.view_sigma is not None:
            extra["view_noise_px"] = {self.views[self.used[int(i)]].name: float(sv)
                                      for i, sv in zip(res.view_indices, res.view_sigma)}
        return {"method": method, "weighting": res.weighting, **extra,
                "model": res.model, "rms_px": res.rms, "std": res.std, "view_rms_px": self.view_rms(),
                "mirrored_views": [self.views[self.used[i]].name for i, m in zip(res.view_indices, res.mirrored) if m],
                "dropped": [{"view": n, "reason": r} for n, r in self.dropped],
                "dropped_points": [{"view": n, "id": i, "residual_px": r, "threshold_px": t}
                                   for n, i, r, t in self.dropped_points],
                "removed_dots": {v.name: [{"id": i, "misfit": m} for i, m in v.removed] for v in self.views if v.removed},
                "vignetted_dots": {v.name: [{"id": i, "modulation_slope": m} for i, m in v.vignetted]
                                   for v in self.views if v.vignetted}}


def _removed_lines(views) -> list[str]:
    out = [f"    {_short(v.name, 36)}: " + ", ".join(f"{i} ({m:.1f}x)" for i, m in v.removed)
           for v in views if v.ok and v.removed]
    if out:
        out.insert(0, "  dots removed for a poor phase fit (residual x modulation above 1.5x the view's median; "
                      "e.g. blur cut by a mirror's edge):")
    vig = [f"    {_short(v.name, 36)}: " + ", ".join(f"{i} ({m:.3f})" for i, m in v.vignetted)
           for v in views if v.ok and v.vignetted]
    if vig:
        vig.insert(0, "  vignetted dots removed (modulation falls off across the dot: relative slope above 3x the "
                      "view's median; e.g. part of the dot beyond a mirror's edge):")
    return out + vig


def _dropped_points_lines(dropped_points) -> list[str]:
    if not dropped_points:
        return []
    by_view: dict = {}
    for nm, pid, r, thr in dropped_points:
        by_view.setdefault(nm, []).append((pid, r))
    thr = max(t for *_, t in dropped_points)
    lines = [f"  removed {len(dropped_points)} outlier point(s) (|residual| > {thr:.3f} px, i.e. 4 × the robust RMS):"]
    for nm, items in by_view.items():
        lines.append(f"    {_short(nm, 36)}: " + ", ".join(f"{pid} ({r:.3f} px)" for pid, r in sorted(items)))
    return lines


def _short(s: str, n: int) -> str:
    return s if len(s) <= n else "…" + s[-(n - 1):]


def calibrate_intrinsics_from_images(views, target: PhaseTarget, *, names=None, mode: str = "dots",
                                     model: str = "opencv5", reject: float | None = 3.0,
                                     max_view_rms: float | None = None, min_points: int = 6,
                                     reject_points: float | None = 4.0, dense_spacing: float | None = None,
                                     correct_blur: bool | None = None, max_misfit: float | None = 1.5,
                                     min_modulation: float = 3.0, weighting: str = "equal", name: str = "",
                                     progress=None, device=None) -> IntrinsicsCalibration:
    """Intrinsics of one camera from image stacks of the phase target, direct and mirrored views together.

    Parameters
    ----------
    views : list of views (folders, globs, file lists or (N, H, W) arrays; :func:`read_stack`)
        The monitor at many poses through the camera's depth of field, and seen in the mirror(s)
        (paper Steps 3–4; ≥ 3 usable views, ~15 recommended). Blurred close-up views are fine.
    target : PhaseTarget
    mode : ``"dots"`` (dot centres) or ``"dense"`` (per-pixel screen coordinates, located on a grid
        of screen points every ``dense_spacing`` screen px, default ``target.pitch / 4``;
        :func:`dense_view_points`).
    model, reject, max_view_rms, weighting :
        As :func:`calibration.intrinsics.calibrate_intrinsics` (distortion model, outlier-view
        rejection, ``"equal"`` or ``"per_view"`` weighting of the views by their noise).
    reject_points : float or None
        Outlier points: after each calibration, points whose residual exceeds ``reject_points`` times
        the robust RMS of all residuals (with ``weighting="per_view"``: of the residuals divided by
        their view's noise) are removed and the calibration is repeated (listed in
        ``dropped_points``). In the virtual lab this removes the dots whose defocus blur is cut by the
        edge of the mirror (vignetting makes their blur spot lopsided). None disables it.
    min_points : int
        Views with fewer identified points are dropped.
    correct_blur, max_misfit, min_modulation, device :
        Passed to :func:`detect_view`.
    name : str
        Camera name written into the result (``"left"``...).
    progress : callable, optional
        ``progress(i, view_result)`` after each view's detection.

    Returns
    -------
    IntrinsicsCalibration
        Raises ``ValueError`` when fewer than 3 views are usable (the message lists why each view
        was dropped) or the views differ in image size.
    """
    _check_phase_target(target)
    _check_mode(mode)
    if model not in DISTORTION_MODELS:
        raise ValueError(f"model must be one of {DISTORTION_MODELS}, got {model!r}")
    results = detect_views(views, target, names=names, mode=mode, correct_blur=correct_blur, min_points=min_points,
                           min_modulation=min_modulation, max_misfit=max_misfit, device=device, progress=progress)
    return calibrate_intrinsics_from_detections(results, model=model, reject=reject, max_view_rms=max_view_rms,
                                                reject_points=reject_points, min_points=min_points,
                                                dense_spacing=target.pitch / 4 if dense_spacing is None else dense_spacing,
                                                weighting=weighting, name=name)


def calibrate_intrinsics_from_detections(results, *, model: str = "opencv5", reject: float | None = 3.0,
                                         max_view_rms: float | None = None, reject_points: float | None = 4.0,
                                         min_points: int = 6, dense_spacing: float = 75.0,
                                         weighting: str = "equal", name: str = "") -> IntrinsicsCalibration:
    """The bundle of :func:`calibrate_intrinsics_from_images` on views already detected (a list of
    :class:`ViewResult` from :func:`detect_views`, possibly of different targets or modes); same options
    (``dense_spacing`` in screen px for dense views)."""
    if not isinstance(results, (list, tuple)) or not all(isinstance(r, ViewResult) for r in results):
        raise ValueError("results must be a list of ViewResult (from detect_views)")
    if model not in DISTORTION_MODELS:
        raise ValueError(f"model must be one of {DISTORTION_MODELS}, got {model!r}")
    results = list(results)
    modes = {"dense" if r.dense is not None else "dots" for r in results if r.ok}
    mode = modes.pop() if len(modes) == 1 else "mixed"
    sizes = {r.image_size for r in results if r.image_size is not None}
    if len(sizes) > 1:
        raise ValueError(f"the views have different image sizes {sorted(sizes)}; calibrate one camera at a time")
    used, objs, imgs, flags, pids = [], [], [], [], []
    for i, r in enumerate(results):
        if not r.ok:
            continue
        if r.detection is not None:
            q, X, ids = r.detection.image_points, r.detection.object_points, r.detection.ids
        else:
            q, X, ids = dense_view_points(r.dense, dense_spacing)
        if len(q) < min_points:
            r.error = f"only {len(q)} points (need {min_points})"
            continue
        used.append(i)
        imgs.append(np.asarray(q, dtype=np.float64))
        objs.append(np.asarray(X, dtype=np.float64))
        pids.append(np.asarray(ids, dtype=np.int64))
        flags.append(bool(r.mirrored))
    if len(used) < 3:
        why = "; ".join(f"{r.name}: {r.error}" for r in results if not r.ok) or "none dropped"
        raise ValueError(f"only {len(used)} of {len(results)} views are usable; intrinsic calibration needs at least 3 "
                         f"({why})")
    size = results[used[0]].image_size
    dropped_points = []
    for _ in range(6):
        res = calibrate_intrinsics(objs, imgs, size, mirrored=flags, model=model, reject=reject,
                                   max_view_rms=max_view_rms, weighting=weighting, name=name)
        if reject_points is None:
            break
        norms = [np.linalg.norm(r_, axis=1) for r_ in res.residuals]
        if res.view_sigma is not None:  # weighted bundle: compare each point with its own view's noise
            norms = [n_ / s_ for n_, s_ in zip(norms, res.view_sigma)]
        thr = _outlier_threshold(np.concatenate(norms), reject_points)
        removed = False
        for k, u in enumerate(res.view_indices):
            bad = norms[k] > thr
            if bad.any() and len(bad) - bad.sum() >= min_points:
                for j in np.flatnonzero(bad):
                    dropped_points.append((results[used[u]].name, int(pids[u][j]), float(norms[k][j]), float(thr)))
                imgs[u], objs[u], pids[u] = imgs[u][~bad], objs[u][~bad], pids[u][~bad]
                removed = True
        if not removed:
            break
    return IntrinsicsCalibration(result=res, views=results, used=used, image_points=imgs, object_points=objs, mode=mode,
                                 point_ids=pids, dropped_points=dropped_points)


def _outlier_threshold(norms: np.ndarray, k: float) -> float:
    """``k`` times a robust RMS of 2-D residual lengths: for Gaussian residuals (σ per axis) the length
    is Rayleigh-distributed, median 1.1774 σ, RMS √2 σ, so RMS ≈ 1.2011 × median."""
    return float(k * 1.2011 * np.median(norms))


# ------------------------------------------------------------------------------------------------
# mirror extrinsics
# ------------------------------------------------------------------------------------------------
@dataclass
class MirrorCalibration:
    """Pose of one camera relative to the monitor from K ≥ 3 mirror tilts (:func:`calibrate_mirror_from_images`).

    ``result`` is the :class:`~calibration.mirror.MirrorExtrinsicsResult` (``R_cam_target,
    t_cam_target``, mirror planes, closed form, RMS, covariance). ``point_ids`` are the target
    points every kept view shows (dot ids, or indices of the dense screen grid), ``object_points``
    (N, 3) mm their target coordinates, ``mirrored_points`` the K (N, 2) image points, ``names`` the
    kept views. ``views`` lists every input view with its detection or the reason it was dropped.
    """

    result: MirrorExtrinsicsResult
    point_ids: np.ndarray
    object_points: np.ndarray
    mirrored_points: list
    names: list
    views: list = field(default_factory=list)
    mode: str = "dots"
    target: dict | None = None
    sigma_px: float | None = None
    dropped_points: list = field(default_factory=list)

    @property
    def camera(self) -> Camera:
        return self.result.camera

    @property
    def R_cam_target(self) -> np.ndarray:
        return self.result.R_cam_target

    @property
    def t_cam_target(self) -> np.ndarray:
        return self.result.t_cam_target

    @property
    def dropped(self) -> list[tuple[str, str]]:
        return [(v.name, v.error) for v in self.views if not v.ok]

    def report(self) -> str:
        r = self.result
        sr = r.std_rotation_deg
        st = r.std_translation_mm
        rv = np.degrees(_rotvec(r.R_cam_target))
        lines = [f"mirror extrinsics of {r.camera.name or 'camera'} ({self.mode} mode): {len(self.names)} mirror tilts × "
                 f"{len(self.point_ids)} points, RMS {r.rms:.4f} px (closed form {r.closed_form_rms:.4f} px)",
                 "  pose of the target (monitor) in the camera frame, x_cam = R_cam_target x_target + t_cam_target:",
                 f"    t_cam_target = [{', '.join(f'{v:.3f} ± {s:.3f}' for v, s in zip(r.t_cam_target, st))}] mm",
                 f"    rotation vector = [{', '.join(f'{v:.4f} ± {s:.4f}' for v, s in zip(rv, sr))}] deg",
                 f"    camera–target distance {np.linalg.norm(r.t_cam_target):.2f} mm",
                 "  view                                   RMS (px)  mirror normal (camera frame)       d (mm)"]
        for nm, m, rms in zip(self.names, r.mirrors, r.per_mirror_rms):
            lines.append(f"  {_short(nm, 38):38s} {rms:8.4f}  [{m.normal[0]: .5f} {m.normal[1]: .5f} {m.normal[2]: .5f}]  {m.d:8.2f}")
        for nm, why in self.dropped:
            lines.append(f"  dropped {nm}: {why}")
        lines.extend(_removed_lines(self.views))
        lines.extend(_dropped_points_lines(self.dropped_points))
        return "\n".join(lines)

    # -- file -------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        r = self.result
        return {
            "schema": MIRROR_POSE_SCHEMA, "schema_version": MIRROR_POSE_SCHEMA_VERSION,
            "units": {"lengths": "mm", "angles": "rad", "pixels": "px",
                      "pose_covariance": "6x6 over [domega_x, domega_y, domega_z (rad), dt_x, dt_y, dt_z (mm)], "
                                         "R_cam_target = expm(skew(domega)) @ R_cam_target_estimate"},
            "conventions": {"pose": "x_cam = R_cam_target @ x_target + t_cam_target",
                            "mirror_planes": "n . x + d = 0 in the camera frame, |n| = 1, d > 0",
                            "target_frame": "see the target file (calibration/targets.py)"},
            "camera": r.camera.to_dict(),
            "R_cam_target": r.R_cam_target.tolist(), "t_cam_target": r.t_cam_target.tolist(),
            "pose_covariance": r.pose_covariance.tolist(),
            "rms_px": r.rms, "closed_form_rms_px": r.closed_form_rms,
            "closed_form": {"R_cam_target": r.closed_form.R_cam_target.tolist(),
                            "t_cam_target": r.closed_form.t_cam_target.tolist()},
            "mirrors": [{"view": nm, "normal": m.normal.tolist(), "d": m.d, "rms_px": float(rms)}
                        for nm, m, rms in zip(self.names, r.mirrors, r.per_mirror_rms)],
            "mode": self.mode, "sigma_px": self.sigma_px,
            "dropped": [{"view": n, "reason": w} for n, w in self.dropped],
            "dropped_points": [{"view": n, "id": i, "residual_px": r, "threshold_px": t}
                               for n, i, r, t in self.dropped_points],
            "target": self.target,
            "observations": {"point_ids": [int(i) for i in self.point_ids],
                             "object_points": self.object_points.tolist(),
                             "views": self.names,
                             # points not seen in a view are NaN rows: written as null (strict JSON)
                             "mirrored_points": [_nan_to_none(q) for q in self.mirrored_points]},
        }

    def save(self, path) -> None:
        """Write the pose file (JSON, schema ``specula.mirror_calibration`` version 1) with the
        observations, so that :func:`calibrate_rig_from_mirrors` can re-adjust both cameras jointly."""
        _write_json(path, self.to_dict())

    @classmethod
    def from_dict(cls, data: dict) -> "MirrorCalibration":
        if not isinstance(data, dict):
            raise ValueError(f"a mirror calibration must be a dict, got {type(data).__name__}")
        _check_schema(data, MIRROR_POSE_SCHEMA, MIRROR_POSE_SCHEMA_VERSION, "mirror calibration")
        try:
            cam = Camera.from_dict(data["camera"])
            obs = data["observations"]
            X = np.asarray(obs["object_points"], dtype=np.float64)
            q = [np.asarray(v, dtype=np.float64) for v in obs["mirrored_points"]]
            ids = np.asarray(obs["point_ids"], dtype=np.int64)
            names = [str(n) for n in obs["views"]]
        except KeyError as exc:
            raise ValueError(f"mirror calibration file lacks the key {exc}") from None
        sigma = data.get("sigma_px")
        # the adjustment is re-run from the observations (deterministic, ~0.1 s): the result object
        # then carries everything (closed form, covariance, residuals)
        res = mirror_extrinsics(cam, q, X, sigma_px=sigma)
        stored_t = np.asarray(data.get("t_cam_target", res.t_cam_target), dtype=np.float64)
        if np.linalg.norm(stored_t - res.t_cam_target) > 1e-3 * max(1.0, np.linalg.norm(stored_t)):
            raise ValueError("the pose stored in the mirror calibration file does not follow from its observations; "
                             "was the file edited?")
        return cls(result=res, point_ids=ids, object_points=X, mirrored_points=q, names=names,
                   views=[ViewResult(d["view"], error=d["reason"]) for d in data.get("dropped", [])],
                   mode=str(data.get("mode", "dots")), target=data.get("target"), sigma_px=sigma,
                   dropped_points=[(d["view"], d["id"], d["residual_px"], d["threshold_px"])
                                   for d in data.get("dropped_points", [])])

    @classmethod
    def load(cls, path) -> "MirrorCalibration":
        """Read a pose file written by :meth:`save`; another schema version raises ``ValueError``."""
        return cls.from_dict(_read_json(path, "mirror calibration"))


def _nan_to_none(points) -> list:
    """(N, 2) array → nested lists with None where a value is NaN (read back as NaN by ``np.asarray(..., float)``)."""
    return [[None if not np.isfinite(v) else float(v) for v in row] for row in np.asarray(points, dtype=np.float64)]


def _rotvec(R):
    from .camera import vector_from_rotation

    return vector_from_rotation(R)


def calibrate_mirror_from_images(camera: Camera, views, target: PhaseTarget, *, names=None, mode: str = "dots",
                                 dense_spacing: float | None = None, sigma_px: float | None = None,
                                 correct_blur: bool | None = None, min_modulation: float = 3.0, min_common: int = 6,
                                 reject_points: float | None = 4.0, max_misfit: float | None = 1.5,
                                 progress=None, device=None) -> MirrorCalibration:
    """Pose of ``camera`` relative to the monitor from views of it in a mirror at K ≥ 3 tilts (paper Steps 2, 5).

    Parameters
    ----------
    camera : Camera
        Calibrated intrinsics (e.g. from :func:`calibrate_intrinsics_from_images` with these same
        mirrored views in the bundle).
    views : list of K ≥ 3 views
        The monitor (which stays put) seen in the mirror, one view per mirror tilt; tilt the mirror
        about two different axes.
    target : PhaseTarget
    mode : ``"dots"`` or ``"dense"``
        Dense mode uses a grid of screen points every ``dense_spacing`` screen px (default
        ``target.pitch / 2``) located in each view by :func:`dense_grid_points`.
    sigma_px : float, optional
        Image noise for the covariance (default: from the residuals).
    min_common : int
        Fewest target points that every kept view must show.
    reject_points : float or None
        Outlier points: a target point whose residual in any view exceeds ``reject_points`` times the
        robust RMS is removed from all views and the adjustment repeated (``dropped_points``).

    Returns
    -------
    MirrorCalibration
        Views that are not mirrored (the target appears right-handed) or in which the target is not
        found are dropped with the reason; the adjustment uses the points every kept view shows.
        Raises ``ValueError`` when fewer than 3 views remain, too few points are common, or the
        setup is degenerate (the message says what to change).
    """
    _check_phase_target(target)
    _check_mode(mode)
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a calibration.camera.Camera, got {type(camera).__name__}")
    results = detect_views(views, target, names=names, mode=mode, correct_blur=correct_blur, min_modulation=min_modulation,
                           max_misfit=max_misfit, device=device, progress=progress)
    return calibrate_mirror_from_detections(camera, results, target, dense_spacing=dense_spacing, sigma_px=sigma_px,
                                            min_common=min_common, reject_points=reject_points)


def calibrate_mirror_from_detections(camera: Camera, results, target: PhaseTarget, *, dense_spacing: float | None = None,
                                     sigma_px: float | None = None, min_common: int = 6,
                                     reject_points: float | None = 4.0) -> MirrorCalibration:
    """The adjustment of :func:`calibrate_mirror_from_images` on views already detected (a list of
    :class:`ViewResult` of ``target``, all in the same mode); same options. The inputs are not modified."""
    import dataclasses

    _check_phase_target(target)
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a calibration.camera.Camera, got {type(camera).__name__}")
    if not isinstance(results, (list, tuple)) or not all(isinstance(r, ViewResult) for r in results):
        raise ValueError("results must be a list of ViewResult (from detect_views)")
    modes = {"dense" if r.dense is not None else "dots" for r in results if r.ok}
    if len(modes) > 1:
        raise ValueError("the mirror views mix dot detections and dense decodings; use one mode")
    mode = modes.pop() if modes else "dots"
    results = list(results)
    for i, r in enumerate(results):
        if r.ok and r.image_size != tuple(camera.size) and camera.size != (0, 0):
            raise ValueError(f"view {r.name} is {r.image_size[0]}x{r.image_size[1]} px but the camera was calibrated "
                             f"for {camera.size[0]}x{camera.size[1]} px")
        if r.ok and not r.mirrored:
            results[i] = dataclasses.replace(r, error="the target appears right-handed: this is not a view through a mirror")
    kept = [r for r in results if r.ok]
    if len(kept) < 3:
        why = "; ".join(f"{r.name}: {r.error}" for r in results if not r.ok) or "none dropped"
        raise ValueError(f"only {len(kept)} usable mirror views; the mirror calibration needs at least 3 tilts ({why})")
    if mode == "dots":
        # every dot seen in at least one view; a view that misses a dot (outside the mirror, or removed
        # as vignetted) has a NaN row there (mirror_extrinsics leaves it out)
        for r in kept:
            if len(r.detection) < min_common:
                raise ValueError(f"only {len(r.detection)} dots are seen in mirror view {r.name} (need {min_common}); "
                                 "keep more of the target inside the mirror at every tilt, or use smaller tilts")
        ids = np.array(sorted(set().union(*(set(int(i) for i in r.detection.ids) for r in kept))), dtype=np.int64)
        q = []
        for r in kept:
            pos = {int(d): n for n, d in enumerate(r.detection.ids)}
            qq = np.full((len(ids), 2), np.nan)
            for n, i in enumerate(ids):
                if int(i) in pos:
                    qq[n] = r.detection.image_points[pos[int(i)]]
            q.append(qq)
        X = target.object_points[ids]
    else:
        spacing = float(target.pitch / 2 if dense_spacing is None else dense_spacing)
        if not spacing > 0:
            raise ValueError(f"dense_spacing must be > 0 screen px, got {dense_spacing!r}")
        grid = _dense_screen_grid(target, spacing)
        found_all = np.ones(len(grid), dtype=bool)
        pts = []
        for r in kept:
            p, f = dense_grid_points(r.dense, grid)
            pts.append(p)
            found_all &= f
        ids = np.flatnonzero(found_all)
        if len(ids) < min_common:
            raise ValueError(f"only {len(ids)} screen points are decoded in every mirror view (need {min_common})")
        q = [p[ids] for p in pts]
        X = target.screen_to_target(grid[ids])
    names = [r.name for r in kept]
    dropped_points = []
    for _ in range(6):
        res = mirror_extrinsics(camera, q, X, sigma_px=sigma_px)
        if reject_points is None:
            break
        norms = np.linalg.norm(np.stack(res.residuals), axis=2)  # (K, N), NaN where not seen
        thr = _outlier_threshold(norms[np.isfinite(norms)], reject_points)
        bad = (norms > thr).any(axis=0)
        if not bad.any() or len(ids) - bad.sum() < min_common:
            break
        for n in np.flatnonzero(bad):
            j = int(np.argmax(norms[:, n]))
            dropped_points.append((names[j], int(ids[n]), float(norms[j, n]), float(thr)))
        ids, X, q = ids[~bad], X[~bad], [p[~bad] for p in q]
    return MirrorCalibration(result=res, point_ids=ids, object_points=X, mirrored_points=q, names=names, views=results,
                             mode=mode, target=target.to_dict(), sigma_px=sigma_px, dropped_points=dropped_points)


# ------------------------------------------------------------------------------------------------
# stereo
# ------------------------------------------------------------------------------------------------
@dataclass
class StereoView:
    """A target both cameras see: common dot ids, object points (N, 3) mm and image points (N, 2) in each camera."""

    ids: np.ndarray
    object_points: np.ndarray
    left_points: np.ndarray
    right_points: np.ndarray
    name: str = ""

    def as_tuple(self):
        return self.object_points, self.left_points, self.right_points


def detect_stereo_view(left_source, right_source, target: PhaseTarget, *, name: str = "", correct_blur: bool | None = None,
                       min_modulation: float = 3.0, min_points: int = 4, max_misfit: float | None = 1.5,
                       device=None) -> StereoView:
    """Detect a direct view of the target in both cameras (e.g. the monitor at the working distance).

    Raises ``ValueError`` when the target is not found in one image, when a view is mirrored, or
    when fewer than ``min_points`` dots are common to both."""
    out = []
    for side, src in (("left", left_source), ("right", right_source)):
        r = detect_view(src, target, name=f"{name or 'stereo view'} ({side})", correct_blur=correct_blur,
                        min_modulation=min_modulation, max_misfit=max_misfit, device=device)
        if not r.ok:
            raise ValueError(f"{r.name}: {r.error}")
        if r.mirrored:
            raise ValueError(f"{r.name}: the target appears mirrored; a stereo view must show the target directly")
        out.append(r.detection)
    dl, dr = out
    common = np.intersect1d(dl.ids, dr.ids)
    if len(common) < min_points:
        raise ValueError(f"{name or 'stereo view'}: only {len(common)} dots are seen by both cameras (need {min_points})")
    il = {int(d): n for n, d in enumerate(dl.ids)}
    ir = {int(d): n for n, d in enumerate(dr.ids)}
    ql = dl.image_points[[il[int(i)] for i in common]]
    qr = dr.image_points[[ir[int(i)] for i in common]]
    return StereoView(common.astype(np.int64), target.object_points[common], ql, qr, name)


@dataclass
class RigCalibration:
    """The stereo rig from two mirror calibrations (:func:`calibrate_rig_from_mirrors`).

    ``rig`` is the final rig (joint adjustment when far views were given and ``joint`` was asked,
    else the per-camera composition); ``per_camera`` the paper's composition of the two poses;
    ``joint`` the :class:`~calibration.mirror.JointMirrorResult` or None; ``checks`` one
    :class:`~calibration.stereo.TargetReconstruction` per check view (views *not* used in the
    adjustment), ``far_views`` / ``check_views`` the :class:`StereoView` s.
    ``rig.covariance`` is ``covariance_extrinsic`` (the adjustment's, intrinsics held fixed) plus
    ``covariance_intrinsic`` (both cameras' intrinsic covariances propagated through the rig,
    :func:`calibration.uncertainty.rig_covariance_from_intrinsics`) when the cameras carry one;
    ``covariance_intrinsic`` is None otherwise.
    """

    rig: StereoRig
    per_camera: StereoRig
    joint: JointMirrorResult | None
    far_views: list
    check_views: list
    checks: list
    left: MirrorCalibration
    right: MirrorCalibration
    covariance_extrinsic: np.ndarray | None = None
    covariance_intrinsic: np.ndarray | None = None

    def report(self) -> str:
        lines = []
        if self.joint is not None:
            g = ", ".join(f"{k} {v:.4f}" for k, v in self.joint.rms_groups.items())
            lines.append(f"stereo rig: joint bundle adjustment of both cameras' mirror views and {len(self.far_views)} "
                         f"view(s) both cameras see; RMS {self.joint.rms:.4f} px ({g})")
        else:
            lines.append("stereo rig: composition of the two mirror calibrations (paper Section 2: H_LR = H_TR H_TL^-1)")
        lines.append(_rig_lines(self.rig))
        if self.covariance_intrinsic is not None and self.covariance_extrinsic is not None:
            se = np.degrees(np.sqrt(np.diag(self.covariance_extrinsic)[:3]))
            si = np.degrees(np.sqrt(np.diag(self.covariance_intrinsic)[:3]))
            lines.append(f"  σ = {self.rig.metadata.get('covariance', '')}; rotation σ from the views alone "
                         f"[{', '.join(f'{v:.4f}' for v in se)}] deg, from the intrinsics "
                         f"[{', '.join(f'{v:.4f}' for v in si)}] deg")
        elif self.rig.covariance is not None:
            lines.append("  σ holds the intrinsics fixed (no intrinsic covariance propagated): a lower bound for the rotation")
        if self.joint is not None:
            d = self.rig.errors_to(self.per_camera)
            lines.append(f"  vs the per-camera composition: rotation {d['rotation_deg']:.4f} deg, translation "
                         f"{d['translation_mm']:.3f} mm, baseline {d['baseline_mm']:+.3f} mm")
        for v, c in zip(self.check_views, self.checks):
            lines.append(f"  check {v.name}: " + c.report())
        return "\n".join(lines)


def _rig_lines(rig: StereoRig) -> str:
    rv = np.degrees(_rotvec(rig.R_right_left))
    t = rig.t_right_left
    if rig.covariance is not None:
        sr, st = rig.std_rotation_deg, rig.std_translation_mm
        return "\n".join([
            f"  baseline {rig.baseline:.3f} ± {rig.std_baseline_mm:.3f} mm",
            f"  t_right_left = [{', '.join(f'{v:.3f} ± {s:.3f}' for v, s in zip(t, st))}] mm",
            f"  rotation vector R_right_left = [{', '.join(f'{v:.4f} ± {s:.4f}' for v, s in zip(rv, sr))}] deg "
            f"(angle {np.linalg.norm(rv):.4f} deg)"])
    return "\n".join([f"  baseline {rig.baseline:.3f} mm",
                      f"  t_right_left = [{', '.join(f'{v:.3f}' for v in t)}] mm",
                      f"  rotation vector R_right_left = [{', '.join(f'{v:.4f}' for v in rv)}] deg"])


def calibrate_rig_from_mirrors(left: MirrorCalibration, right: MirrorCalibration, *, far_views=(), check_views=(),
                               joint: bool = True, sigma_px: float | None = None,
                               intrinsic_uncertainty: bool = True) -> RigCalibration:
    """The stereo rig from the left and right cameras' mirror calibrations against the same monitor pose.

    Parameters
    ----------
    left, right : MirrorCalibration
        From :func:`calibrate_mirror_from_images` (or :meth:`MirrorCalibration.load`), with the
        monitor in the same place for both.
    far_views : list of StereoView
        Views of the target that both cameras see directly (the paper's last frame; e.g. the
        monitor at the working distance). With ``joint``, they enter the joint bundle adjustment
        (:func:`calibration.mirror.joint_mirror_stereo`), which also re-adjusts both cameras' mirror
        views together; this pins the rig rotation that the mirror views alone determine weakly.
    check_views : list of StereoView
        Views reconstructed with the final rig as a check (distances between dots; keep them out
        of ``far_views`` for an independent check).
    joint : bool
        Run the joint adjustment (needs points common to both cameras' mirror views). Without far
        views it still couples the two cameras through the common target pose.
    sigma_px : float, optional
        Image noise (px) for the adjustment's covariance (default: from its residuals).
    intrinsic_uncertainty : bool
        When the cameras carry an intrinsic covariance (``Camera.covariance``, written by
        :func:`calibrate_intrinsics_from_images` into the camera file; a camera without one counts as
        exact), add its effect to the rig's covariance: the rig is re-solved with each camera's intrinsics moved ±1σ along the principal
        axes of its covariance (4 × 9 re-solves for the 5-term model). In the rendered lab this term
        dominates the rotation σ (docs/calibration.md). False keeps the adjustment's covariance only.
    """
    for nm, m in (("left", left), ("right", right)):
        if not isinstance(m, MirrorCalibration):
            raise ValueError(f"{nm} must be a MirrorCalibration, got {type(m).__name__}")
    far_views, check_views = list(far_views), list(check_views)
    for nm, vs in (("far_views", far_views), ("check_views", check_views)):
        for v in vs:
            if not isinstance(v, StereoView):
                raise ValueError(f"{nm} must hold StereoView objects (from detect_stereo_view), got {type(v).__name__}")
    if left.mode != right.mode:
        raise ValueError(f"the left and right mirror calibrations use different modes ({left.mode} / {right.mode})")
    per_camera = rig_from_mirror(left.result, right.result)
    jres = None
    rig = per_camera
    if joint:
        common = np.intersect1d(left.point_ids, right.point_ids)
        if len(common) < 6:
            raise ValueError(f"only {len(common)} target points are common to both cameras' mirror views; the joint "
                             "adjustment needs the same points in both (pass joint=False)")
        il = {int(d): n for n, d in enumerate(left.point_ids)}
        ir = {int(d): n for n, d in enumerate(right.point_ids)}
        li = [il[int(i)] for i in common]
        ri = [ir[int(i)] for i in common]
        X = left.object_points[li]
        if not np.allclose(X, right.object_points[ri], atol=1e-6):
            raise ValueError("the left and right mirror calibrations used different targets (object points differ)")
        left_obs, right_obs = [q[li] for q in left.mirrored_points], [q[ri] for q in right.mirrored_points]
        far = [v.as_tuple() for v in far_views] or None

        def joint_rig(lc, rc):  # the joint adjustment with given intrinsics (also re-run for the covariance)
            return joint_mirror_stereo(lc, rc, left_obs, right_obs, X, far_views=far, left_result=left.result,
                                       right_result=right.result, sigma_px=sigma_px)

        def solve(lc, rc):
            r = joint_rig(lc, rc).rig
            return r.R_right_left, r.t_right_left

        jres = joint_rig(left.camera, right.camera)
        rig = jres.rig
    else:
        def solve(lc, rc):
            r = rig_from_mirror(mirror_extrinsics(lc, left.mirrored_points, left.object_points),
                                mirror_extrinsics(rc, right.mirrored_points, right.object_points))
            return r.R_right_left, r.t_right_left
    cov_ext = None if rig.covariance is None else rig.covariance.copy()
    cov_int = None
    with_cov = [nm for nm, m in (("left", left), ("right", right)) if m.camera.covariance is not None]
    if intrinsic_uncertainty and with_cov:
        cov_int = rig_covariance_from_intrinsics(solve, left.camera, right.camera, rig.R_right_left, rig.t_right_left)
        if cov_ext is not None:
            rig = dataclasses.replace(rig, covariance=cov_ext + cov_int)
    rig.metadata = dict(rig.metadata)
    rig.metadata.update({"left_views": left.names, "right_views": right.names,
                         "far_views": [v.name for v in far_views]})
    if rig.covariance is not None and cov_int is None:
        rig.metadata["covariance"] = "adjustment only, intrinsics held fixed (a lower bound)"
    elif rig.covariance is not None:
        which = "left and right cameras" if len(with_cov) == 2 else f"{with_cov[0]} camera"
        missing = "" if len(with_cov) == 2 else f" (the {({'left', 'right'} - set(with_cov)).pop()} camera carries none)"
        rig.metadata["covariance"] = f"adjustment (intrinsics fixed) + the intrinsic covariance of the {which} propagated{missing}"
    checks = [reconstruct_target(rig, v.left_points, v.right_points, v.object_points) for v in check_views]
    return RigCalibration(rig=rig, per_camera=per_camera, joint=jres, far_views=far_views, check_views=check_views,
                          checks=checks, left=left, right=right, covariance_extrinsic=cov_ext,
                          covariance_intrinsic=cov_int)


# ------------------------------------------------------------------------------------------------
# conventional: checkerboard pairs
# ------------------------------------------------------------------------------------------------
@dataclass
class CheckerboardStereo:
    """Conventional stereo calibration from checkerboard pairs (:func:`stereo_from_checkerboards`)."""

    result: StereoCalibrationResult
    names: list
    dropped: list
    left_intrinsics: IntrinsicsResult | None = None
    right_intrinsics: IntrinsicsResult | None = None

    @property
    def rig(self) -> StereoRig:
        return self.result.rig

    def report(self) -> str:
        lines = [f"stereo calibration from {len(self.names)} checkerboard pairs (cv2.stereoCalibrate + float64 bundle "
                 f"adjustment), RMS {self.result.rms:.4f} px"]
        for nm, res in (("left", self.left_intrinsics), ("right", self.right_intrinsics)):
            if res is not None:
                lines.append(f"  {nm} intrinsics from the boards: RMS {res.rms:.4f} px, fx {res.camera.fx:.3f} ± "
                             f"{res.std.get('fx', float('nan')):.3f} px")
        lines.append(_rig_lines(self.rig))
        for nm, (l, r) in zip(self.names, self.result.per_view_rms):
            lines.append(f"  {_short(nm, 38):38s} RMS left {l:.4f} px, right {r:.4f} px")
        for nm, why in self.dropped:
            lines.append(f"  dropped {nm}: {why}")
        return "\n".join(lines)


def _board_corners(image, target: CheckerboardTarget):
    """Checkerboard corners in the target's id order, or None. OpenCV orders the corners of a board
    up to its symmetries; the order is fixed here so that the board's x axis points right in the
    image and the target appears right-handed (a direct view)."""
    found = detect_checkerboard(image, target)
    if found is None:
        return None
    pts, _ = found
    nx, ny = target.corners
    if len(pts) != nx * ny:
        return None
    grid = pts.reshape(ny, nx, 2)
    import cv2

    for _ in range(2):
        obj = target.points_px
        H, _ = cv2.findHomography(obj, grid.reshape(-1, 2), 0)
        if H is None:
            return None
        J = _homography_jacobian(H / H[2, 2], obj.mean(axis=0))
        if np.linalg.det(J) < 0:  # rows were read in the reverse direction
            grid = grid[::-1]
            continue
        if J[0, 0] < 0:  # rotated by 180 degrees
            grid = grid[::-1, ::-1]
        break
    return grid.reshape(-1, 2).astype(np.float64)


def _homography_jacobian(H, xy) -> np.ndarray:
    """d(image)/d(plane) (2, 2) of the homography ``H`` at plane point ``xy``."""
    q = H @ np.array([xy[0], xy[1], 1.0])
    return (H[:2, :2] * q[2] - np.outer(q[:2], H[2, :2])) / q[2] ** 2


def stereo_from_checkerboards(left_images, right_images, target: CheckerboardTarget, *, left_camera: Camera | None = None,
                              right_camera: Camera | None = None, names=None, model: str = "opencv5",
                              uncertainty: str = "jacobian") -> CheckerboardStereo:
    """Conventional stereo calibration (``cv2.stereoCalibrate``) from checkerboard image pairs.

    Parameters
    ----------
    left_images, right_images : lists of images (arrays (H, W) or file paths), paired by position
    target : CheckerboardTarget
        The board (inner corners, square size; :class:`calibration.targets.CheckerboardTarget`).
    left_camera, right_camera : Camera, optional
        Known intrinsics (held fixed). When omitted, each camera is first calibrated from its board
        views (Zhang, :func:`calibration.intrinsics.calibrate_intrinsics`), the conventional way.
    """
    if not isinstance(target, CheckerboardTarget):
        raise ValueError(f"target must be a CheckerboardTarget, got {type(target).__name__}")
    left_images, right_images = list(left_images), list(right_images)
    if len(left_images) != len(right_images) or not left_images:
        raise ValueError(f"need the same non-zero number of left and right images, got {len(left_images)} and {len(right_images)}")
    names = names or [f"pair{i}" if not isinstance(a, (str, os.PathLike))
                      else f"{os.path.basename(os.fspath(a))} | {os.path.basename(os.fspath(b))}"
                      for i, (a, b) in enumerate(zip(left_images, right_images))]
    objs, ql, qr, kept, dropped, size = [], [], [], [], [], None
    for nm, a, b in zip(names, left_images, right_images):
        ia = _read_image(os.fspath(a)) if isinstance(a, (str, os.PathLike)) else np.asarray(a)
        ib = _read_image(os.fspath(b)) if isinstance(b, (str, os.PathLike)) else np.asarray(b)
        if size is None:
            size = (ia.shape[1], ia.shape[0])
        ca = _board_corners(ia, target)
        cb = _board_corners(ib, target)
        if ca is None or cb is None:
            dropped.append((nm, "board not found in the " + ("left" if ca is None else "right") + " image"))
            continue
        objs.append(target.object_points)
        ql.append(ca)
        qr.append(cb)
        kept.append(nm)
    if len(kept) < (1 if left_camera is not None and right_camera is not None else 3):
        raise ValueError(f"the board was found in both images of only {len(kept)} pairs "
                         f"({'; '.join(f'{n}: {w}' for n, w in dropped)})")
    li = ri = None
    if left_camera is None:
        li = calibrate_intrinsics(objs, ql, size, model=model, reject=None, name="left")
        left_camera = li.camera
    if right_camera is None:
        ri = calibrate_intrinsics(objs, qr, size, model=model, reject=None, name="right")
        right_camera = ri.camera
    res = stereo_calibrate(left_camera, right_camera, objs, ql, qr, uncertainty=uncertainty)
    return CheckerboardStereo(result=res, names=kept, dropped=dropped, left_intrinsics=li, right_intrinsics=ri)

