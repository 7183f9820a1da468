"""Stereo stage: the rig from the two cameras' mirror calibrations (paper Section 2,
:func:`calibration.stereo.rig_from_mirror`) and, with views both cameras see, the joint bundle
adjustment (:func:`calibration.mirror.joint_mirror_stereo`), its covariance with the cameras'
intrinsic uncertainty propagated, and check views → :class:`RigCalibration`; the result of the
conventional calibration from checkerboard pairs, :class:`CheckerboardStereo`
(:func:`calibration.pipeline.stereo_from_checkerboards`).

Frames and units: docs/conventions.md (mm, px, camera frame x right / y down / z forward, pixel
(0, 0) the centre of the top-left pixel); target frame: :mod:`calibration.targets`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..intrinsics import IntrinsicsResult
from ..mirror import JointMirrorResult, joint_mirror_stereo, mirror_extrinsics
from ..reports import checkerboard_stereo_report, rig_report
from ..stereo import StereoCalibrationResult, StereoRig, reconstruct_target, rig_from_mirror
from ..uncertainty import rig_covariance_from_intrinsics
from ..views import StereoView
from .mirror import MirrorCalibration

__all__ = ["RigCalibration", "CheckerboardStereo", "calibrate_rig_from_mirrors"]


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
        """The text report (:func:`calibration.reports.rig_report`)."""
        return rig_report(self)


def _check_view_sizes(view: StereoView, left: Camera, right: Camera) -> None:
    """A view seen by both cameras must come from images of the sizes the cameras were calibrated for."""
    if view.image_sizes is None:
        return
    for side, cam, size in (("left", left, view.image_sizes[0]), ("right", right, view.image_sizes[1])):
        if size is not None and tuple(cam.size) != (0, 0) and tuple(size) != tuple(cam.size):
            raise ValueError(f"view {view.name or '(unnamed)'}: the {side} image is {size[0]}x{size[1]} px but the {side} "
                             f"camera was calibrated for {cam.size[0]}x{cam.size[1]} px images")


def calibrate_rig_from_mirrors(left: MirrorCalibration, right: MirrorCalibration, *, far_views=(), check_views=(),
                               joint: bool = True, sigma_px: float | None = None,
                               intrinsic_uncertainty: bool = True) -> RigCalibration:
    """The stereo rig from the left and right cameras' mirror calibrations against the same monitor pose.

    Parameters
    ----------
    left, right : MirrorCalibration
        From :func:`calibration.pipeline.calibrate_mirror_from_images` (or
        :meth:`MirrorCalibration.load`), with the monitor in the same place for both.
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
        :func:`calibration.pipeline.calibrate_intrinsics_from_images` into the camera file; a camera
        without one counts as exact), add its effect to the rig's covariance: the rig is re-solved with each camera's intrinsics moved ±1σ along the principal
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
            _check_view_sizes(v, left.camera, right.camera)
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


@dataclass
class CheckerboardStereo:
    """Conventional stereo calibration from checkerboard pairs
    (:func:`calibration.pipeline.stereo_from_checkerboards`)."""

    result: StereoCalibrationResult
    names: list
    dropped: list
    left_intrinsics: IntrinsicsResult | None = None
    right_intrinsics: IntrinsicsResult | None = None
    #: the board points of each kept pair: (N, 3) mm, and their (N, 2) px in the left and right images
    object_points: list | None = None
    left_points: list | None = None
    right_points: list | None = None

    @property
    def rig(self) -> StereoRig:
        return self.result.rig

    def report(self) -> str:
        """The text report (:func:`calibration.reports.checkerboard_stereo_report`)."""
        return checkerboard_stereo_report(self)
