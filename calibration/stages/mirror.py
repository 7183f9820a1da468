"""Mirror stage: one camera's pose relative to the monitor from its views in a mirror at K ≥ 3 tilts
(paper Steps 2, 5; :func:`calibration.mirror.mirror_extrinsics`, closed form + bundle adjustment) on
the target points the views show → :class:`MirrorCalibration`, saved as a pose file
(:mod:`calibration.posefiles`) that keeps the observations for the joint rig adjustment.

The entry point from image files is :func:`calibration.pipeline.calibrate_mirror_from_images`.
Frames and units: docs/conventions.md (mm, px, camera frame x right / y down / z forward, pixel
(0, 0) the centre of the top-left pixel); target frame: :mod:`calibration.targets`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from ..mirror import MirrorExtrinsicsResult, mirror_extrinsics
from ..posefiles import mirror_pose_dict, mirror_pose_fields, read_mirror_pose_fields, write_mirror_pose
from ..reports import mirror_report
from ..targets import PhaseTarget
from ..views import ViewResult, _check_phase_target, _dense_screen_grid, dense_grid_points
from .intrinsics import _outlier_threshold

__all__ = ["MirrorCalibration", "calibrate_mirror_from_detections"]


@dataclass
class MirrorCalibration:
    """Pose of one camera relative to the monitor from K ≥ 3 mirror tilts
    (:func:`calibration.pipeline.calibrate_mirror_from_images`).

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
        """The text report (:func:`calibration.reports.mirror_report`)."""
        return mirror_report(self)

    # -- file -------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The pose file's content (:func:`calibration.posefiles.mirror_pose_dict`)."""
        return mirror_pose_dict(self)

    def save(self, path) -> None:
        """Write the pose file (JSON, schema ``specula.mirror_calibration`` version 1) with the
        observations, so that :func:`calibrate_rig_from_mirrors` can re-adjust both cameras jointly
        (:func:`calibration.posefiles.write_mirror_pose`)."""
        write_mirror_pose(path, self)

    @classmethod
    def from_dict(cls, data: dict) -> "MirrorCalibration":
        """From a pose file's content (:func:`calibration.posefiles.mirror_pose_fields`)."""
        return cls(**mirror_pose_fields(data))

    @classmethod
    def load(cls, path) -> "MirrorCalibration":
        """Read a pose file written by :meth:`save`; another schema version raises ``ValueError``."""
        return cls(**read_mirror_pose_fields(path))


def calibrate_mirror_from_detections(camera: Camera, results, target: PhaseTarget, *, dense_spacing: float | None = None,
                                     sigma_px: float | None = None, min_common: int = 6,
                                     reject_points: float | None = 4.0) -> MirrorCalibration:
    """The adjustment of :func:`calibration.pipeline.calibrate_mirror_from_images` on views already
    detected (a list of :class:`ViewResult` of ``target``, all in the same mode); same options. The
    inputs are not modified."""
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
