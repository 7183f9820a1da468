"""Intrinsic calibration (Zhang's method through OpenCV) from direct and mirrored views.

Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000,
doi:10.1109/34.888718 — closed-form initialisation from plane homographies, then a bundle
adjustment of intrinsics, distortion and one pose per view (``cv2.calibrateCameraExtended``).

Mirrored views (the paper behind Specula, Optics Express 2019: "Stereo-camera calibration for
large-scale DIC measurements with active phase targets and planar mirrors", Step 4) enter the
same bundle. A target seen in a plane mirror is a *left-handed* copy of the target: its image
points are the projection of ``H (R X + t)`` with ``H`` a Householder reflection (det −1), so
no proper rotation maps the target frame onto the virtual target. Flipping the object points,
``X' = F X`` with ``F = diag(−1, 1, 1)`` (x → −x in the target frame), turns the virtual target
into an ordinary right-handed target with pose ``x_cam = R' (F X) + t'``, ``R'`` a proper
rotation; a planar target stays planar (z = 0). The reflection has no effect on the intrinsics.

Per-view poses are returned for the object points *as given*: for a direct view
``x_cam = R_cam_target @ X + t_cam_target``; for a mirrored view the same formula with the flipped
points, i.e. ``x_cam = R_cam_target @ (F @ X) + t_cam_target`` where ``R_cam_target`` is proper
(``IntrinsicsResult.flip`` holds ``F``). ``R_cam_target @ F`` is the left-handed pose of the virtual
target.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .camera import Camera, rotation_from_vector, vector_from_rotation

#: The flip applied to the object points of mirrored views (x -> -x in the target frame).
MIRROR_FLIP = np.diag([-1.0, 1.0, 1.0])

#: Names of the OpenCV intrinsic standard deviations, in the order of ``stdDeviationsIntrinsics``.
STD_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
             "s1", "s2", "s3", "s4", "tau_x", "tau_y")


def _model_flags():
    import cv2

    tang0 = cv2.CALIB_ZERO_TANGENT_DIST
    return {
        # name: (flags, number of distortion coefficients kept in Camera.dist)
        "none": (tang0 | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3, 0),
        "radial1": (tang0 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3, 5),
        "radial2": (tang0 | cv2.CALIB_FIX_K3, 5),
        "radial3": (tang0, 5),
        "radial2+tangential": (cv2.CALIB_FIX_K3, 5),
        "opencv5": (0, 5),
        "rational": (cv2.CALIB_RATIONAL_MODEL, 8),
    }


#: Distortion models accepted by :func:`calibrate_intrinsics` (``model=``):
#: ``none``, ``radial1`` (k1), ``radial2`` (k1 k2), ``radial3`` (k1 k2 k3),
#: ``radial2+tangential`` (k1 k2 p1 p2), ``opencv5`` (k1 k2 p1 p2 k3), ``rational`` (8 coefficients).
DISTORTION_MODELS = ("none", "radial1", "radial2", "radial3", "radial2+tangential", "opencv5", "rational")


#: Fewest degrees between the target normals of two views for the views to determine the intrinsics
#: (views whose target planes are all parallel - e.g. all fronto-parallel - leave the focal length free).
MIN_VIEW_ANGLE_DEG = 10.0
#: Largest relative standard deviation of fx and fy accepted from a calibration (the test suite's valid
#: calibrations reach 0.3 %).
MAX_RELATIVE_FOCAL_STD = 0.05
#: Range of the focal lengths accepted, as a multiple of the larger image side (a 120 deg lens ~ 0.29,
#: an 850 mm lens on 3.45 um pixels of a 2448 px sensor ~ 100).
FOCAL_RANGE = (0.1, 100.0)

#: parameters whose undefined standard deviation makes a calibration unusable (the others are
#: higher-order distortion terms, which only warn)
_CORE_PARAMETERS = ("fx", "fy", "cx", "cy", "k1", "p1", "p2")

_VIEWS_TO_ADD = ("add at least 3 views tilted by 10-45 deg in different directions (left/right and up/down) "
                 "to the views you have")


def _distinct_orientations(poses, min_angle_deg: float) -> tuple[int, float]:
    """Number of distinct target orientations (greedy clusters of target normals ``min_angle_deg`` wide)
    and the largest angle (deg) between the target normals of two views."""
    normals = np.array([np.asarray(R)[:, 2] for R, _ in poses])
    cos = np.clip(np.abs(normals @ normals.T), 0.0, 1.0)  # a plane's normal has no sign
    angles = np.degrees(np.arccos(cos))
    centres: list[int] = []
    for v in range(len(poses)):
        if all(angles[v, c] >= min_angle_deg for c in centres):
            centres.append(v)
    return len(centres), float(angles.max(initial=0.0))


def _check_determined(poses, K, std: dict, size) -> None:
    """Refuse a calibration whose views cannot determine the intrinsics (``ValueError`` saying which
    views to add): target planes all (nearly) parallel, a NaN/infinite or large standard deviation, a
    focal length outside :data:`FOCAL_RANGE` times the image size."""
    n_orient, widest = _distinct_orientations(poses, MIN_VIEW_ANGLE_DEG)
    if n_orient < 2:
        raise ValueError(
            f"the views cannot determine the intrinsics: the target planes of all {len(poses)} views are (nearly) "
            f"parallel (largest angle between two views' target normals {widest:.1f} deg, needs >= "
            f"{MIN_VIEW_ANGLE_DEG:g} deg; fronto-parallel or merely shifted views leave the focal length free); "
            + _VIEWS_TO_ADD)
    bad = [nm for nm, v in std.items() if not np.isfinite(v)]
    core = [nm for nm in bad if nm in _CORE_PARAMETERS]
    if core:
        raise ValueError(
            f"the views cannot determine the intrinsics: the standard deviation of {', '.join(bad)} is undefined "
            f"(the bundle is singular); {_VIEWS_TO_ADD}, or choose a distortion model with fewer terms")
    if bad:
        # higher-order distortion terms (k2..k6) that these views leave undetermined: the rational model's
        # k4..k6 often are, and whether OpenCV's covariance comes out NaN for them then depends on round-off
        # (seen run to run on the test suite's views); the camera is usable, the terms are not meaningful
        import warnings

        warnings.warn(f"the views do not determine {', '.join(bad)} (undefined standard deviation); the camera "
                      "is usable, but a distortion model with fewer terms describes these views as well",
                      RuntimeWarning, stacklevel=3)
    side = max(size)
    for nm, f in (("fx", K[0, 0]), ("fy", K[1, 1])):
        if not FOCAL_RANGE[0] * side <= f <= FOCAL_RANGE[1] * side:
            raise ValueError(
                f"the views cannot determine the intrinsics: {nm} = {f:.6g} px is outside {FOCAL_RANGE[0]:g}-"
                f"{FOCAL_RANGE[1]:g} times the image side ({side} px); {_VIEWS_TO_ADD}")
        rel = std.get(nm, 0.0) / f
        if rel > MAX_RELATIVE_FOCAL_STD:
            raise ValueError(
                f"the views cannot determine the intrinsics: {nm} = {f:.6g} ± {std[nm]:.3g} px (relative standard "
                f"deviation {rel:.1%} > {MAX_RELATIVE_FOCAL_STD:.0%}); {_VIEWS_TO_ADD}")


#: Scale of the median absolute deviation to the standard deviation of a normal distribution
#: (``1 / Φ⁻¹(3/4)``), used by the ``reject_mad`` rule.
MAD_TO_SIGMA = 1.4826
#: Floor of the robust spread of the ``reject_mad`` rule, as a fraction of the median per-view RMS: views of
#: equal quality (noise-free or nearly identical) have a MAD near 0, and without a floor any view a little
#: above the median would be dropped.
MAD_FLOOR = 0.05


@dataclass
class DroppedView:
    """A view removed by outlier rejection: its index in the input, its RMS (px) in the solve that
    dropped it, why, and its RMS (px) in the first solve with every view (``rms_all_views``)."""

    index: int
    rms: float
    reason: str
    rms_all_views: float = float("nan")


@dataclass
class IntrinsicsResult:
    """Result of :func:`calibrate_intrinsics`.

    Attributes
    ----------
    camera : Camera
        Calibrated intrinsics (``K``, ``dist`` in the chosen model, ``size``).
    rms : float
        Reprojection RMS over all kept points (px): ``sqrt(mean(|q_obs − q_proj|²))``.
    per_view_rms : (V,) float64
        RMS per kept view (px), same definition.
    std : dict[str, float]
        One standard deviation of each estimated intrinsic parameter (``fx fy cx cy`` in px,
        distortion coefficients dimensionless), from OpenCV's ``stdDeviationsIntrinsics`` (the
        Gauss–Newton covariance scaled by the residual variance). Fixed parameters are left out.
        The full covariance (correlations included: cx with p1, cy with p2...) travels with the
        camera as ``camera.covariance`` / ``camera.covariance_names`` (also :attr:`covariance`), the
        intrinsic block of the bundle's covariance (poses marginalised); it is None with
        ``extra_flags``. The rig calibration propagates it (``calibration.pipeline.calibrate_rig_from_mirrors``).
    poses : list[tuple[(3, 3), (3,)]]
        ``(R_cam_target, t_cam_target)`` per kept view (mm); for mirrored views see the module
        docstring (pose of the flipped object points, a proper rotation).
    view_indices : (V,) int
        Index in the input lists of each kept view.
    mirrored : (V,) bool
        Whether each kept view was a mirrored view.
    dropped : list[DroppedView]
        Views removed by outlier rejection, with the reason.
    residuals : list[(N_v, 2)]
        Observed minus reprojected image points per kept view (px).
    model, flags : str, int
        Distortion model name and the OpenCV flags used.
    weighting : str
        ``"equal"`` (every point counts the same, OpenCV's bundle) or ``"per_view"``.
    view_sigma : (V,) float64 or None
        With ``weighting="per_view"``: the image noise (px per coordinate) estimated for each kept
        view, whose inverse square weights its points.
    rms_all_views : float
        Reprojection RMS (px) of the first solve, with every input view (before view rejection);
        equal to ``rms`` when no view was dropped.
    per_view_rms_all_views : (V_in,) float64
        RMS (px) of every input view in that first solve, indexed like the input lists.
    view_rms_limit : (V,) float64
        The RMS (px) above which each kept view would have been dropped in the final solve (the lowest
        of the active rules: ``reject × median``, ``max_view_rms``, the ``reject_mad`` limit); NaN
        without a rule. The figures draw it.
    """

    camera: Camera
    rms: float
    per_view_rms: np.ndarray
    std: dict
    poses: list
    view_indices: np.ndarray
    mirrored: np.ndarray
    dropped: list = field(default_factory=list)
    residuals: list = field(default_factory=list)
    model: str = "opencv5"
    flags: int = 0
    flip: np.ndarray = field(default_factory=lambda: MIRROR_FLIP.copy())
    weighting: str = "equal"
    view_sigma: np.ndarray | None = None
    rms_all_views: float = float("nan")
    per_view_rms_all_views: np.ndarray | None = None
    view_rms_limit: np.ndarray | None = None

    def rejection_summary(self) -> str:
        """One line on view rejection: the RMS with every view and after the re-solve, or that none was dropped."""
        n_in = len(self.view_indices) + len(self.dropped)
        if not self.dropped:
            return f"view rejection: none of {n_in} views dropped"
        return (f"view rejection: {len(self.dropped)} of {n_in} views dropped; RMS {self.rms_all_views:.4f} px with "
                f"all {n_in} views, {self.rms:.4f} px after the re-solve with {len(self.view_indices)}")

    @property
    def covariance(self) -> np.ndarray | None:
        """(P, P) covariance of the estimated intrinsics named in ``camera.covariance_names``, or None."""
        return self.camera.covariance

    def report(self) -> str:
        """A short readable report: parameters ± σ, RMS per view, dropped views."""
        cam = self.camera
        lines = [f"intrinsics ({self.model}), {len(self.view_indices)} views, RMS {self.rms:.4f} px"
                 + (", views weighted by their noise" if self.weighting == "per_view" else "")]
        values = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}
        for i, name in enumerate(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")):
            if i < cam.dist.size:
                values[name] = float(cam.dist[i])
        for name, value in values.items():
            if name in self.std:
                lines.append(f"  {name:>3} = {value: .6g} ± {self.std[name]:.2g}")
        sig = self.view_sigma if self.view_sigma is not None else [None] * len(self.view_indices)
        for idx, rms, m, sv in zip(self.view_indices, self.per_view_rms, self.mirrored, sig):
            lines.append(f"  view {idx:3d}{' (mirrored)' if m else ''}: RMS {rms:.4f} px"
                         + (f", noise σ {sv:.4f} px" if sv is not None else ""))
        for d in self.dropped:
            lines.append(f"  dropped view {d.index}: RMS {d.rms:.4f} px ({d.rms_all_views:.4f} px with all views) "
                         f"— {d.reason}")
        lines.append("  " + self.rejection_summary())
        return "\n".join(lines)


def _validate_views(object_points, image_points, mirrored):
    if not isinstance(object_points, (list, tuple)) or not isinstance(image_points, (list, tuple)):
        raise ValueError("object_points and image_points must be lists with one (N, 3) / (N, 2) array per view")
    if len(object_points) != len(image_points):
        raise ValueError(f"got {len(object_points)} object-point arrays but {len(image_points)} image-point arrays")
    if mirrored is None:
        mirrored = [False] * len(object_points)
    mirrored = [bool(m) for m in mirrored]
    if len(mirrored) != len(object_points):
        raise ValueError(f"mirrored must have one flag per view ({len(object_points)}), got {len(mirrored)}")
    objs, imgs = [], []
    for v, (o, q) in enumerate(zip(object_points, image_points)):
        o = np.asarray(o, dtype=np.float64)
        q = np.asarray(q, dtype=np.float64)
        if o.ndim != 2 or o.shape[1] != 3:
            raise ValueError(f"object_points[{v}] must have shape (N, 3) in mm, got {o.shape}")
        if q.ndim != 2 or q.shape[1] != 2:
            raise ValueError(f"image_points[{v}] must have shape (N, 2) in px, got {q.shape}")
        if o.shape[0] != q.shape[0]:
            raise ValueError(f"view {v}: {o.shape[0]} object points but {q.shape[0]} image points (rows must correspond)")
        if o.shape[0] < 6:
            raise ValueError(f"view {v} has {o.shape[0]} points; intrinsic calibration needs at least 6 per view")
        if not (np.all(np.isfinite(o)) and np.all(np.isfinite(q))):
            raise ValueError(f"view {v} contains NaN or infinite coordinates; drop undetected points first")
        objs.append(o)
        imgs.append(q)
    return objs, imgs, mirrored


def calibrate_intrinsics(object_points, image_points, image_size, *, mirrored=None, model: str = "opencv5",
                         reject: float | None = 3.0, max_view_rms: float | None = None,
                         reject_mad: float | None = None, extra_flags: int = 0, min_views: int = 3, weighting: str = "equal",
                         name: str = "") -> IntrinsicsResult:
    """Zhang calibration (``cv2.calibrateCameraExtended``) of one camera, direct and mirrored views in one bundle.

    Parameters
    ----------
    object_points : list of (N_v, 3) float64
        Target coordinates (mm, target frame) of the points seen in each view. The initialisation
        (Zhang 2000) needs planar targets with z = 0.
    image_points : list of (N_v, 2) float64
        Their image points (px, distorted, docs/conventions.md), rows aligned with ``object_points``.
    image_size : (width, height)
        Image size in pixels.
    mirrored : list of bool, optional
        True for views of the target seen through a mirror; their object points are flipped
        (x → −x, module docstring) so that the bundle sees a right-handed target.
    model : str
        Distortion model, one of :data:`DISTORTION_MODELS`.
    reject : float or None
        Outlier rejection: after each calibration, views with a per-view RMS above
        ``reject × median(per-view RMS)`` are dropped (the worst one at a time, then recalibrate).
        None disables it.
    max_view_rms : float or None
        Also drop views whose RMS exceeds this absolute value (px).
    reject_mad : float or None
        Also drop views whose RMS exceeds ``median + reject_mad × 1.4826 × MAD`` of the per-view RMS
        (a robust z-score above ``reject_mad``; with ``weighting="per_view"`` over the views of the
        same target), the worst one at a time; the robust spread is at least :data:`MAD_FLOOR` × the
        median, so that equal views are never dropped. None (default) disables it. The default rule is
        ``reject`` = 3 × median, which keeps every view of clean sets (the per-view RMS of the lab's
        sessions spread over 0.009-0.015 px, at most 1.3 × their median) and drops a view with
        corrupted detections; ``reject_mad`` suits sets whose views scatter little, where 3 × median
        is too lenient (e.g. ``reject_mad=5``). Every view dropped by a rule re-solves the bundle
        without it; the result keeps the first solve's RMS (``rms_all_views``,
        ``per_view_rms_all_views``) so that reports give the RMS before and after.
    extra_flags : int
        More OpenCV ``CALIB_*`` flags (e.g. ``cv2.CALIB_FIX_ASPECT_RATIO``).
    min_views : int
        Fewest views allowed after rejection (at least 3).
    weighting : ``"equal"`` or ``"per_view"``
        ``"equal"``: OpenCV's bundle, every point weighted the same. ``"per_view"``: views whose
        points are noisier count for less — for bundles that mix targets or blur levels (a dense
        24 × 12 dot grid measured to 0.05 px beside 6 × 3 dots measured to 0.013 px): each view's
        noise ``σ_v`` is estimated from its residuals (``sqrt(Σ r² / (2 N_v − 6))``), then the
        bundle (intrinsics + every pose) is solved again minimising ``Σ |r|² / σ_v²`` (Levenberg–
        Marquardt on OpenCV's analytic projection Jacobian, two re-weighting rounds), and the
        standard deviations come from that weighted Jacobian. Outlier rejection then compares a
        view with the median of the views of the *same target* (same point spacing), not of all
        views. Needs no ``extra_flags``.

    Returns
    -------
    IntrinsicsResult

    Raises
    ------
    ValueError
        Mismatched/invalid inputs, unknown model, too few views (before or after rejection), a
        non-planar target, or views that cannot determine the intrinsics: fewer than two target
        orientations :data:`MIN_VIEW_ANGLE_DEG` apart (all planes parallel, e.g. all fronto-parallel),
        an undefined (NaN) standard deviation, ``fx``/``fy`` with a relative standard deviation above
        :data:`MAX_RELATIVE_FOCAL_STD`, or outside :data:`FOCAL_RANGE` times the larger image side.
        The message says which views to add.
    """
    import cv2

    flags_by_model = _model_flags()
    if model not in flags_by_model:
        raise ValueError(f"model must be one of {DISTORTION_MODELS}, got {model!r}")
    objs, imgs, mirrored = _validate_views(object_points, image_points, mirrored)
    try:
        w, h = (int(image_size[0]), int(image_size[1]))
    except (TypeError, IndexError, ValueError):
        raise ValueError(f"image_size must be (width, height) in pixels, got {image_size!r}") from None
    if w <= 0 or h <= 0:
        raise ValueError(f"image_size must be positive (width, height), got {image_size!r}")
    if min_views < 3:
        raise ValueError(f"min_views must be at least 3, got {min_views}")
    if len(objs) < min_views:
        raise ValueError(f"intrinsic calibration needs at least {min_views} views, got {len(objs)}")
    for v, o in enumerate(objs):
        if np.max(np.abs(o[:, 2])) > 1e-9 * max(1.0, np.max(np.abs(o))):
            raise ValueError(
                f"object_points[{v}] is not planar with z = 0; Zhang's initialisation needs a planar target "
                "in its own frame (z = 0)"
            )
    if reject is not None and not reject > 1.0:
        raise ValueError(f"reject must be > 1 (a multiple of the median per-view RMS) or None, got {reject!r}")
    if reject_mad is not None and not (isinstance(reject_mad, (int, float, np.number)) and not isinstance(reject_mad, bool)
                                       and np.isfinite(reject_mad) and reject_mad > 0):
        raise ValueError(f"reject_mad must be a positive number of robust standard deviations (MAD × 1.4826) or "
                         f"None, got {reject_mad!r}")
    if weighting not in ("equal", "per_view"):
        raise ValueError(f"weighting must be 'equal' or 'per_view', got {weighting!r}")
    if weighting == "per_view" and extra_flags:
        raise ValueError("weighting='per_view' supports the named models only; drop extra_flags or use weighting='equal'")
    group = _target_groups(objs) if weighting == "per_view" else np.zeros(len(objs), dtype=int)

    flags, ndist = flags_by_model[model]
    flags |= int(extra_flags)
    used_objs = [(MIRROR_FLIP @ o.T).T if m else o for o, m in zip(objs, mirrored)]

    keep = list(range(len(objs)))
    dropped: list[DroppedView] = []
    first = None
    while True:
        sol = _calibrate(cv2, [used_objs[i] for i in keep], [imgs[i] for i in keep], (w, h), flags)
        per_view = sol["per_view_rms"]
        if first is None:
            first = sol
        g = group[keep]
        med_of_group = np.array([np.median(per_view[g == gi]) for gi in g])
        worst = int(np.argmax(per_view / med_of_group))
        med = float(med_of_group[worst])
        of = "median per-view RMS" if weighting == "equal" else "median per-view RMS of the views of this target"
        reason = None
        if max_view_rms is not None and np.max(per_view) > max_view_rms:
            worst = int(np.argmax(per_view))
            reason = f"RMS {per_view[worst]:.4f} px > max_view_rms {max_view_rms:.4f} px"
        elif reject is not None and per_view[worst] > reject * med:
            reason = f"RMS {per_view[worst]:.4f} px > {reject:g} × {of} ({med:.4f} px)"
        elif reject_mad is not None:
            limit = np.empty_like(per_view)
            for gi in np.unique(g):
                rv = per_view[g == gi]
                med_g = np.median(rv)
                spread = max(MAD_TO_SIGMA * np.median(np.abs(rv - med_g)), MAD_FLOOR * med_g)
                limit[g == gi] = med_g + reject_mad * spread
            over = per_view - limit
            if np.max(over) > 0:
                worst = int(np.argmax(per_view / limit))
                reason = (f"RMS {per_view[worst]:.4f} px > {of} + {reject_mad:g} × 1.4826 × MAD "
                          f"({limit[worst]:.4f} px)")
        if reason is None:
            view_limit = np.full(per_view.shape, np.inf)
            if max_view_rms is not None:
                view_limit = np.minimum(view_limit, max_view_rms)
            if reject is not None:
                view_limit = np.minimum(view_limit, reject * med_of_group)
            if reject_mad is not None:
                view_limit = np.minimum(view_limit, limit)
            view_limit[~np.isfinite(view_limit)] = np.nan
            break
        if len(keep) - 1 < min_views:
            raise ValueError(
                f"outlier rejection would leave fewer than {min_views} views (view {keep[worst]}: {reason}); "
                "check the detections or relax reject/max_view_rms"
            )
        dropped.append(DroppedView(index=keep[worst], rms=float(per_view[worst]), reason=reason,
                                   rms_all_views=float(first["per_view_rms"][keep[worst]])))
        del keep[worst]

    estimated = _estimated_parameters(flags, ndist)
    view_sigma = None
    if weighting == "per_view":
        sol, view_sigma = _weighted_bundle(cv2, [used_objs[i] for i in keep], [imgs[i] for i in keep], sol,
                                           estimated, ndist)
    K = sol["K"]
    dist = sol["dist"][:ndist] if ndist else np.zeros(0)
    cov_names, cov = sol.get("covariance_names", ()), sol.get("covariance")
    if cov is None and not extra_flags:
        # the full covariance (OpenCV returns only its diagonal): the rig calibration propagates it
        cov_names, cov = _intrinsic_covariance(cv2, [used_objs[i] for i in keep], [imgs[i] for i in keep], sol,
                                               estimated, ndist)
    if cov is not None and not (np.all(np.isfinite(cov)) and np.min(np.diag(cov)) > 0):
        cov = None  # numerically singular (e.g. the rational model on too few views): no covariance to pass on
    camera = Camera(K=K, dist=dist, size=(w, h), name=name, covariance=cov,
                    covariance_names=tuple(cov_names) if cov is not None else ())
    std = {}
    std_raw = sol["std"]
    for i, nm in enumerate(STD_NAMES):
        if nm in estimated and i < std_raw.size:
            std[nm] = float(std_raw[i])
    _check_determined(sol["poses"], K, std, (w, h))
    return IntrinsicsResult(
        camera=camera,
        rms=sol["rms"],
        per_view_rms=per_view,
        std=std,
        poses=sol["poses"],
        view_indices=np.asarray(keep, dtype=int),
        mirrored=np.asarray([mirrored[i] for i in keep], dtype=bool),
        dropped=dropped,
        residuals=sol["residuals"],
        model=model,
        flags=flags,
        weighting=weighting,
        view_sigma=view_sigma,
        view_rms_limit=view_limit,
        rms_all_views=float(first["rms"]) if dropped else float(sol["rms"]),
        per_view_rms_all_views=np.asarray(first["per_view_rms"], dtype=np.float64).copy(),
    )


def _target_groups(objs) -> np.ndarray:
    """Group index per view: views of the same target (the same point spacing, in bins 2 % wide) share one.

    The spacing (the smallest distance between two object points) identifies the target even when a
    view misses some of its points."""
    from scipy.spatial import cKDTree

    keys, out = {}, []
    for o in objs:
        dist, _ = cKDTree(o).query(o, k=2)
        spacing = float(np.min(dist[:, 1]))
        key = int(np.round(50.0 * np.log(max(spacing, 1e-9))))  # bins 2 % wide: one bin per target pitch
        out.append(keys.setdefault(key, len(keys)))
    return np.asarray(out, dtype=int)


#: Parameter names of cv2.projectPoints' intrinsic Jacobian columns after rvec, tvec (3 + 3).
_PROJECT_JAC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


def _levenberg_marquardt(fun, jac, x, max_iter: int = 50, rel_tol: float = 1e-12):
    """Minimise ``|fun(x)|²`` by Levenberg–Marquardt on the normal equations (few parameters, many residuals).

    MINPACK's QR of the full Jacobian is 30x slower here than forming ``JᵀJ`` (a few hundred
    parameters); the start (OpenCV's solution) is close, so a few damped Gauss–Newton steps converge."""
    r = fun(x)
    cost = float(r @ r)
    lam = 1e-4
    for _ in range(max_iter):
        J = jac(x)
        H, g = J.T @ J, J.T @ r
        D = np.diag(np.maximum(np.diag(H), 1e-30))
        while True:
            try:
                dx = np.linalg.solve(H + lam * D, -g)
            except np.linalg.LinAlgError:
                dx = None
            if dx is not None:
                r_new = fun(x + dx)
                cost_new = float(r_new @ r_new)
                if cost_new <= cost:
                    break
            lam *= 10.0
            if lam > 1e10:
                return x
        x, r, improvement, cost = x + dx, r_new, cost - cost_new, cost_new
        lam = max(lam / 10.0, 1e-12)
        if improvement <= rel_tol * max(cost, 1e-300):
            break
    return x


class _BundleModel:
    """Zhang's bundle (intrinsics + one pose per view) as residual / Jacobian functions of one vector
    ``x = [free intrinsics, (rvec, tvec) per view]``, on ``cv2.projectPoints``' analytic Jacobian.

    ``full0`` holds every intrinsic of the model (``fx fy cx cy`` + ``nd`` distortion terms, the
    columns of :data:`_PROJECT_JAC_NAMES`); ``free`` indexes the estimated ones."""

    def __init__(self, cv2, objs, imgs, full0, free, poses):
        self.cv2, self.imgs, self.full0, self.free = cv2, imgs, np.asarray(full0, dtype=np.float64), free
        self.names = tuple(_PROJECT_JAC_NAMES[i] for i in free)
        self.n_int, self.V = free.size, len(objs)
        self.obj3 = [np.ascontiguousarray(o, dtype=np.float64).reshape(-1, 1, 3) for o in objs]
        self.rows = np.cumsum([0] + [2 * o.shape[0] for o in objs])
        self.x0 = np.concatenate([self.full0[free]] + [np.concatenate([vector_from_rotation(R), t]) for R, t in poses])

    def unpack(self, x):
        full = self.full0.copy()
        full[self.free] = x[:self.n_int]
        K = np.array([[full[0], 0.0, full[2]], [0.0, full[1], full[3]], [0.0, 0.0, 1.0]])
        return K, full[4:], x[self.n_int:].reshape(self.V, 6)

    def project(self, x, jac: bool):
        K, d, P = self.unpack(x)
        out = []
        for v in range(self.V):
            q, J = self.cv2.projectPoints(self.obj3[v], P[v, :3], P[v, 3:], K, d)
            out.append((q.reshape(-1, 2), J if jac else None))
        return out

    def residuals(self, x, sig):
        return np.concatenate([((q - self.imgs[v]) / sig[v]).ravel() for v, (q, _) in enumerate(self.project(x, False))])

    def jacobian(self, x, sig):
        n_int, rows = self.n_int, self.rows
        Jfull = np.zeros((rows[-1], n_int + 6 * self.V))
        for v, (_, J) in enumerate(self.project(x, True)):
            r0, r1 = rows[v], rows[v + 1]
            Jfull[r0:r1, :n_int] = J[:, 6 + self.free] / sig[v]
            Jfull[r0:r1, n_int + 6 * v:n_int + 6 * v + 6] = J[:, :6] / sig[v]
        return Jfull

    def view_sigma(self, x):
        return np.array([np.sqrt(np.sum((q - self.imgs[v]) ** 2) / max(1, 2 * len(q) - 6))
                         for v, (q, _) in enumerate(self.project(x, False))])

    def covariance(self, x, sig):
        """Gauss–Newton covariance of ``x``, scaled by the weighted residual variance ``Σ r² / (n − p)``."""
        J = self.jacobian(x, sig)
        r = self.residuals(x, sig)
        dof = max(1, r.size - x.size)
        # column scaling first: focal lengths (~1e3 px) and k3 (~1e-1) differ by orders of magnitude
        scale = np.linalg.norm(J, axis=0)
        scale[scale == 0] = 1.0
        Jn = J / scale
        try:
            C = np.linalg.inv(Jn.T @ Jn) / np.outer(scale, scale) * float(r @ r) / dof
        except np.linalg.LinAlgError:
            raise ValueError("the intrinsic bundle is singular: the views do not determine the intrinsics") from None
        return 0.5 * (C + C.T)


def _bundle_model(cv2, objs, imgs, sol, estimated: set, ndist: int) -> _BundleModel:
    nd = 8 if ndist == 8 else 5
    names = _PROJECT_JAC_NAMES[: 4 + nd]
    free = np.array([i for i, nm in enumerate(names) if nm in estimated], dtype=int)
    K0, d0 = sol["K"], sol["dist"][:nd]
    full0 = np.array([K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2], *d0])
    return _BundleModel(cv2, objs, imgs, full0, free, sol["poses"])


def _intrinsic_covariance(cv2, objs, imgs, sol, estimated: set, ndist: int):
    """``(names, (P, P) covariance)`` of the estimated intrinsics of an equal-weight solution.

    The intrinsic block of the full bundle covariance (poses included, i.e. the Schur complement),
    with the residual variance as OpenCV scales its ``stdDeviationsIntrinsics``; their square roots
    agree (tests/calibration/test_intrinsics.py)."""
    model = _bundle_model(cv2, objs, imgs, sol, estimated, ndist)
    cov = model.covariance(model.x0, np.ones(model.V))
    return model.names, cov[:model.n_int, :model.n_int]


def _weighted_bundle(cv2, objs, imgs, sol, estimated: set, ndist: int, rounds: int = 2, sigma=None):
    """Bundle adjustment of intrinsics + poses with per-view weights 1/σ_v², from OpenCV's solution.

    Minimises ``Σ_v Σ_i |q_vi − π(K, d, R_v, t_v; X_vi)|² / σ_v²`` by Levenberg–Marquardt with the
    analytic Jacobian of ``cv2.projectPoints``; σ_v is re-estimated
    from the view's residuals (per coordinate, ``2 N_v − 6`` degrees of freedom) before each round.
    Returns the solution dict of :func:`_calibrate` (``std`` from the weighted Jacobian, in the
    order of :data:`STD_NAMES`; ``covariance`` and ``covariance_names`` of the free intrinsics) and
    the final σ_v. ``sigma`` (V,) fixes σ_v instead (one round; tests).
    """
    model = _bundle_model(cv2, objs, imgs, sol, estimated, ndist)
    x = model.x0
    for _ in range(rounds if sigma is None else 1):
        sig = np.maximum(model.view_sigma(x), 1e-6) if sigma is None else np.asarray(sigma, dtype=np.float64)
        x = _levenberg_marquardt(lambda y: model.residuals(y, sig), lambda y: model.jacobian(y, sig), x)
    try:
        cov = model.covariance(x, sig)
    except ValueError:
        raise ValueError("the weighted intrinsic bundle is singular: the views do not determine the intrinsics") from None
    std_by_name = {nm: float(np.sqrt(cov[k, k])) for k, nm in enumerate(model.names)}
    K, d, P = model.unpack(x)
    dist = np.concatenate([d, np.zeros(8 - d.size)])
    poses, res_list, per_view, sq_total, n_total = [], [], [], 0.0, 0
    for v, (q, _) in enumerate(model.project(x, False)):
        rr = imgs[v] - q
        sq = np.sum(rr * rr, axis=1)
        res_list.append(rr)
        per_view.append(np.sqrt(np.mean(sq)))
        sq_total += float(np.sum(sq))
        n_total += sq.size
        poses.append((rotation_from_vector(P[v, :3]), P[v, 3:].copy()))
    std = np.array([std_by_name.get(nm, 0.0) for nm in STD_NAMES])
    return ({"K": K, "dist": dist, "std": std, "poses": poses, "residuals": res_list,
             "per_view_rms": np.asarray(per_view), "rms": float(np.sqrt(sq_total / n_total)),
             "covariance": cov[:model.n_int, :model.n_int], "covariance_names": model.names},
            model.view_sigma(x))


def _estimated_parameters(flags: int, ndist: int) -> set:
    import cv2

    est = {"fx", "fy", "cx", "cy"}
    if flags & cv2.CALIB_FIX_PRINCIPAL_POINT:
        est -= {"cx", "cy"}
    if flags & cv2.CALIB_FIX_FOCAL_LENGTH and flags & cv2.CALIB_USE_INTRINSIC_GUESS:
        est -= {"fx", "fy"}
    if flags & cv2.CALIB_FIX_ASPECT_RATIO:
        est -= {"fx"}  # OpenCV estimates fy and keeps fx/fy fixed
    if ndist:
        for nm, fl in (("k1", cv2.CALIB_FIX_K1), ("k2", cv2.CALIB_FIX_K2), ("k3", cv2.CALIB_FIX_K3)):
            if not flags & fl:
                est.add(nm)
        if not flags & (cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_TANGENT_DIST):
            est |= {"p1", "p2"}
        if flags & cv2.CALIB_RATIONAL_MODEL:
            for nm, fl in (("k4", cv2.CALIB_FIX_K4), ("k5", cv2.CALIB_FIX_K5), ("k6", cv2.CALIB_FIX_K6)):
                if not flags & fl:
                    est.add(nm)
    return est


def _calibrate(cv2, objs, imgs, size, flags):
    obj32 = [np.ascontiguousarray(o, dtype=np.float32).reshape(-1, 1, 3) for o in objs]
    img32 = [np.ascontiguousarray(q, dtype=np.float32).reshape(-1, 1, 2) for q in imgs]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        out = cv2.calibrateCameraExtended(obj32, img32, size, None, None, flags=flags, criteria=criteria)
    except cv2.error as exc:
        raise ValueError(f"OpenCV calibration failed: {exc.err}; check that the views are not all parallel "
                         "and that image and object points correspond") from None
    _, K, dist, rvecs, tvecs, std_int, _, _ = out
    K = np.asarray(K, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64).ravel()
    poses, residuals, per_view, sq_total, n_total = [], [], [], 0.0, 0
    for o, q, rv, tv in zip(objs, imgs, rvecs, tvecs):
        rv = np.asarray(rv, dtype=np.float64).ravel()
        tv = np.asarray(tv, dtype=np.float64).ravel()
        proj, _ = cv2.projectPoints(o.reshape(-1, 1, 3), rv, tv, K, dist)
        r = q - proj.reshape(-1, 2)
        sq = np.sum(r * r, axis=1)
        residuals.append(r)
        per_view.append(np.sqrt(np.mean(sq)))
        sq_total += float(np.sum(sq))
        n_total += sq.size
        poses.append((rotation_from_vector(rv), tv))
    return {
        "K": K,
        "dist": np.concatenate([dist, np.zeros(max(0, 8 - dist.size))]),
        "std": np.asarray(std_int, dtype=np.float64).ravel(),
        "poses": poses,
        "residuals": residuals,
        "per_view_rms": np.asarray(per_view),
        "rms": float(np.sqrt(sq_total / n_total)),
    }
