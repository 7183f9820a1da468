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

Where the parts live: this module reads the views' image files and runs the steps from them;
one view's detection on its image stack is :mod:`calibration.views`, the stages on detected views
:mod:`calibration.stages` (``intrinsics``, ``mirror``, ``stereo``), their text reports
:mod:`calibration.reports` and the mirror stage's pose files :mod:`calibration.posefiles`. Every
public name of those modules that this pipeline uses is importable from here too.

Frames and units: docs/conventions.md (mm, px, camera frame x right / y down / z forward, pixel
(0, 0) the centre of the top-left pixel); target frame: :mod:`calibration.targets`.
"""
from __future__ import annotations

import glob
import os

import numpy as np

# the one image reader (same rules as DIC); IMAGE_SUFFIXES: the files a view folder or glob may hold
from kernels.images import IMAGE_SUFFIXES, natural_key, read_image

from .camera import Camera
from .intrinsics import DISTORTION_MODELS, calibrate_intrinsics
from .posefiles import MIRROR_POSE_SCHEMA, MIRROR_POSE_SCHEMA_VERSION
from .stages import (
    CheckerboardStereo,
    IntrinsicsCalibration,
    MirrorCalibration,
    RigCalibration,
    calibrate_intrinsics_from_detections,
    calibrate_mirror_from_detections,
    calibrate_rig_from_mirrors,
)
from .stereo import stereo_calibrate
from .targets import CheckerboardTarget, PhaseTarget
from .views import (
    MIN_VIGNETTING_SLOPE,
    MODES,
    StereoView,
    ViewResult,
    _board_corners,
    _check_mode,
    _check_phase_target,
    dense_grid_points,
    dense_view_points,
    detect_view_stack,
    filter_detection,
)

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
    # also importable from here: the view-level helpers
    "MIN_VIGNETTING_SLOPE",
    "MODES",
    "detect_view_stack",
    "filter_detection",
]



# ------------------------------------------------------------------------------------------------
# reading views
# ------------------------------------------------------------------------------------------------
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
        return sorted(files, key=natural_key)
    if os.path.isfile(src):
        raise ValueError(
            f"{src!r} is a single file; a view is a folder or a glob pattern of its N phase-shifted images "
            "(quote the pattern so that the shell does not expand it, e.g. 'view03/*.png')")
    if glob.has_magic(src):
        files = [f for f in glob.glob(src) if os.path.isfile(f)]
        if not files:
            raise ValueError(f"the pattern {src!r} matches no files")
        return sorted(files, key=natural_key)
    raise ValueError(f"view {src!r} is neither a folder, nor an existing glob pattern, nor a file list")


def _read_image(path: str) -> np.ndarray:
    """One calibration image (H, W) in its file's dtype, by the rules of :func:`kernels.images.read_image`."""
    return read_image(path)


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
    return detect_view_stack(stack, target, mode=mode, name=name, min_modulation=min_modulation,
                             correct_blur=correct_blur, min_points=min_points, max_misfit=max_misfit,
                             max_slope=max_slope, dense_erode=dense_erode, device=device)


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
# intrinsics
# ------------------------------------------------------------------------------------------------
def calibrate_intrinsics_from_images(views, target: PhaseTarget, *, names=None, mode: str = "dots",
                                     model: str = "opencv5", reject: float | None = 3.0,
                                     max_view_rms: float | None = None, reject_mad: float | None = None,
                                     min_points: int = 6, reject_points: float | None = 4.0, dense_spacing: float | None = None,
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
    model, reject, max_view_rms, reject_mad, weighting :
        As :func:`calibration.intrinsics.calibrate_intrinsics` (distortion model, outlier-view
        rejection with a re-solve, ``"equal"`` or ``"per_view"`` weighting of the views by their noise).
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
                                                reject_mad=reject_mad, reject_points=reject_points, min_points=min_points,
                                                dense_spacing=target.pitch / 4 if dense_spacing is None else dense_spacing,
                                                weighting=weighting, name=name)


# ------------------------------------------------------------------------------------------------
# mirror extrinsics
# ------------------------------------------------------------------------------------------------
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


# ------------------------------------------------------------------------------------------------
# stereo
# ------------------------------------------------------------------------------------------------
def detect_stereo_view(left_source, right_source, target: PhaseTarget, *, name: str = "", correct_blur: bool | None = None,
                       min_modulation: float = 3.0, min_points: int = 4, max_misfit: float | None = 1.5,
                       device=None) -> StereoView:
    """Detect a direct view of the target in both cameras (e.g. the monitor at the working distance).

    Raises ``ValueError`` when the target is not found in one image, when a view is mirrored, or
    when fewer than ``min_points`` dots are common to both."""
    out, sizes = [], []
    for side, src in (("left", left_source), ("right", right_source)):
        r = detect_view(src, target, name=f"{name or 'stereo view'} ({side})", correct_blur=correct_blur,
                        min_modulation=min_modulation, max_misfit=max_misfit, device=device)
        if not r.ok:
            raise ValueError(f"{r.name}: {r.error}")
        if r.mirrored:
            raise ValueError(f"{r.name}: the target appears mirrored; a stereo view must show the target directly")
        out.append(r.detection)
        sizes.append(r.image_size)
    dl, dr = out
    common = np.intersect1d(dl.ids, dr.ids)
    if len(common) < min_points:
        raise ValueError(f"{name or 'stereo view'}: only {len(common)} dots are seen by both cameras (need {min_points})")
    il = {int(d): n for n, d in enumerate(dl.ids)}
    ir = {int(d): n for n, d in enumerate(dr.ids)}
    ql = dl.image_points[[il[int(i)] for i in common]]
    qr = dr.image_points[[ir[int(i)] for i in common]]
    return StereoView(common.astype(np.int64), target.object_points[common], ql, qr, name,
                      image_sizes=tuple(sizes) if all(sz is not None for sz in sizes) else None)


# ------------------------------------------------------------------------------------------------
# conventional: checkerboard pairs
# ------------------------------------------------------------------------------------------------
def _check_board_image_size(sizes: dict, side: str, image: np.ndarray, camera: Camera | None, name: str) -> None:
    """Every image of a side has one size, and a given camera was calibrated for it (else ValueError)."""
    if image.ndim != 2:
        raise ValueError(f"{name}: the {side} image must be a grey (H, W) image, got shape {image.shape}")
    size = (int(image.shape[1]), int(image.shape[0]))
    if sizes[side] is None:
        sizes[side] = size
        if camera is not None and tuple(camera.size) != (0, 0) and tuple(camera.size) != size:
            raise ValueError(f"the {side} camera was calibrated for {camera.size[0]}x{camera.size[1]} px images but the "
                             f"{side} board images are {size[0]}x{size[1]} px ({name}); use the camera file made for "
                             "these images, or images of the calibrated size")
    elif size != sizes[side]:
        raise ValueError(f"{name}: the {side} image is {size[0]}x{size[1]} px but the first {side} image is "
                         f"{sizes[side][0]}x{sizes[side][1]} px; every {side} image must have the same size")


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

    Raises ``ValueError`` when a given camera was calibrated for another image size than its board
    images (the message names both sizes), when the images of one side differ in size, or when the
    board is found in too few pairs.
    """
    if not isinstance(target, CheckerboardTarget):
        raise ValueError(f"target must be a CheckerboardTarget, got {type(target).__name__}")
    left_images, right_images = list(left_images), list(right_images)
    if len(left_images) != len(right_images) or not left_images:
        raise ValueError(f"need the same non-zero number of left and right images, got {len(left_images)} and {len(right_images)}")
    names = names or [f"pair{i}" if not isinstance(a, (str, os.PathLike))
                      else f"{os.path.basename(os.fspath(a))} | {os.path.basename(os.fspath(b))}"
                      for i, (a, b) in enumerate(zip(left_images, right_images))]
    for side, cam in (("left", left_camera), ("right", right_camera)):
        if cam is not None and not isinstance(cam, Camera):
            raise ValueError(f"{side}_camera must be a calibration.camera.Camera, got {type(cam).__name__}")
    objs, ql, qr, kept, dropped = [], [], [], [], []
    sizes = {"left": None, "right": None}
    for nm, a, b in zip(names, left_images, right_images):
        ia = _read_image(os.fspath(a)) if isinstance(a, (str, os.PathLike)) else np.asarray(a)
        ib = _read_image(os.fspath(b)) if isinstance(b, (str, os.PathLike)) else np.asarray(b)
        for side, img, cam in (("left", ia, left_camera), ("right", ib, right_camera)):
            _check_board_image_size(sizes, side, img, cam, nm)
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
        li = calibrate_intrinsics(objs, ql, sizes["left"], model=model, reject=None, name="left")
        left_camera = li.camera
    if right_camera is None:
        ri = calibrate_intrinsics(objs, qr, sizes["right"], model=model, reject=None, name="right")
        right_camera = ri.camera
    res = stereo_calibrate(left_camera, right_camera, objs, ql, qr, uncertainty=uncertainty)
    return CheckerboardStereo(result=res, names=kept, dropped=dropped, left_intrinsics=li, right_intrinsics=ri,
                              object_points=objs, left_points=ql, right_points=qr)

