"""Verification of a stereo rig with a known distance: triangulate two target points seen by both
cameras and compare their distance with the known one (the scale error in %).

A rig whose translation is off by a factor ``1 + ε`` measures every length ``1 + ε`` times too long
(triangulation is scale-covariant in the baseline), so the scale error is the one number a user can
check with a ruler, a scale bar or the calibration target itself, away from the calibration views.
Frames and units: docs/conventions.md (left camera frame, mm; image points in px, distorted, pixel
(0, 0) the centre of the top-left pixel).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .stereo import StereoRig
from .views import StereoView

__all__ = ["DistanceVerification", "verify_distance", "verify_view_distance"]


@dataclass
class DistanceVerification:
    """Result of :func:`verify_distance` (mm unless stated).

    ``points`` (2, 3): the two triangulated points, left camera frame; ``labels`` their names (point
    ids); ``known`` and ``measured`` the distance between them; ``error`` = measured − known;
    ``scale_error_percent`` = 100 × error / known; ``reprojection_px`` (2,): each point's RMS
    reprojection residual over both images (px; large values mean a wrong match, not a scale error).
    """

    points: np.ndarray
    labels: tuple
    known: float
    measured: float
    reprojection_px: np.ndarray
    view: str = ""

    @property
    def error(self) -> float:
        return self.measured - self.known

    @property
    def scale_error_percent(self) -> float:
        return 100.0 * self.error / self.known

    def to_dict(self) -> dict:
        return {"view": self.view, "points": list(self.labels), "known_mm": self.known, "measured_mm": self.measured,
                "error_mm": self.error, "scale_error_percent": self.scale_error_percent,
                "points_left_frame_mm": self.points.tolist(), "reprojection_rms_px": self.reprojection_px.tolist()}

    def report(self) -> str:
        a, b = self.labels
        where = f" in {self.view}" if self.view else ""
        return (f"known distance{where}: points {a} and {b}, {np.linalg.norm(self.points[0]):.1f} and "
                f"{np.linalg.norm(self.points[1]):.1f} mm from the left camera\n"
                f"  known    {self.known:12.4f} mm\n"
                f"  measured {self.measured:12.4f} mm\n"
                f"  error    {self.error:+12.4f} mm  (scale error {self.scale_error_percent:+.4f} %)\n"
                f"  reprojection RMS of the two points {self.reprojection_px[0]:.4f}, {self.reprojection_px[1]:.4f} px")


def _as_pair(points, name: str) -> np.ndarray:
    try:
        q = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be two image points (2, 2) in px") from None
    if q.shape != (2, 2) or not np.all(np.isfinite(q)):
        raise ValueError(f"{name} must be two finite image points, shape (2, 2) in px, got shape {q.shape}")
    return q


def verify_distance(rig: StereoRig, left_points, right_points, known_distance: float, *, labels=(1, 2),
                    view: str = "") -> DistanceVerification:
    """Triangulate two points and compare their distance with ``known_distance`` (mm).

    Parameters
    ----------
    rig : StereoRig
    left_points, right_points : (2, 2) px
        The two points in the left and the right image (distorted pixels), rows aligned.
    known_distance : float
        The true distance between them, mm (> 0).
    labels : pair
        Names of the two points for the report and the JSON (target point ids: ints).
    """
    if not isinstance(rig, StereoRig):
        raise ValueError(f"rig must be a StereoRig, got {type(rig).__name__}")
    ql, qr = _as_pair(left_points, "left_points"), _as_pair(right_points, "right_points")
    try:
        known = float(known_distance)
    except (TypeError, ValueError):
        raise ValueError(f"known_distance must be a number of mm, got {known_distance!r}") from None
    if not (np.isfinite(known) and known > 0):
        raise ValueError(f"known_distance must be a positive distance in mm, got {known_distance!r}")
    if np.allclose(ql[0], ql[1]) and np.allclose(qr[0], qr[1]):
        raise ValueError("the two points are the same point in both images")
    P = rig.triangulate(ql, qr)
    if not np.all(np.isfinite(P)) or np.any(P[:, 2] <= 0):
        raise ValueError("the points do not triangulate in front of the cameras: check that the left and right "
                         "points match and that the rig belongs to these images")
    pl, pr = rig.project(P)
    rep = np.sqrt(0.5 * (np.sum((pl - ql) ** 2, axis=1) + np.sum((pr - qr) ** 2, axis=1)))
    return DistanceVerification(points=P, labels=(labels[0], labels[1]), known=known,
                                measured=float(np.linalg.norm(P[1] - P[0])), reprojection_px=rep, view=view)


def verify_view_distance(rig: StereoRig, view: StereoView, ids=None, known_distance: float | None = None
                         ) -> DistanceVerification:
    """Known-distance check on a detected stereo view of a target (:func:`calibration.pipeline.detect_stereo_view`).

    ``ids``: the two target point ids to measure (default: the two common points farthest apart, the
    longest length the view offers). ``known_distance`` (mm): default the distance of their object
    points, i.e. the target's own pitch (a monitor's pixel pitch, a printed board's measured square);
    give the measured value when it differs.
    """
    if not isinstance(view, StereoView):
        raise ValueError(f"view must be a StereoView, got {type(view).__name__}")
    if view.image_sizes is not None:
        for side, cam, size in (("left", rig.left, view.image_sizes[0]), ("right", rig.right, view.image_sizes[1])):
            if tuple(cam.size) != (0, 0) and tuple(size) != tuple(cam.size):
                raise ValueError(f"the {side} image is {size[0]}x{size[1]} px but the rig's {side} camera was "
                                 f"calibrated for {cam.size[0]}x{cam.size[1]} px")
    index = {int(i): n for n, i in enumerate(view.ids)}
    if ids is None:
        X = view.object_points
        d = np.linalg.norm(X[:, None] - X[None], axis=2)
        a, b = np.unravel_index(int(np.argmax(d)), d.shape)
    else:
        try:
            ia, ib = (int(v) for v in ids)
        except (TypeError, ValueError):
            raise ValueError(f"ids must be two point ids, got {ids!r}") from None
        missing = [i for i in (ia, ib) if i not in index]
        if missing:
            raise ValueError(f"point id(s) {', '.join(map(str, missing))} not seen by both cameras in "
                             f"{view.name or 'the view'} (common ids: {', '.join(map(str, sorted(index)))})")
        if ia == ib:
            raise ValueError("ids must be two different points")
        a, b = index[ia], index[ib]
    if known_distance is None:
        known_distance = float(np.linalg.norm(view.object_points[a] - view.object_points[b]))
    return verify_distance(rig, view.left_points[[a, b]], view.right_points[[a, b]], known_distance,
                           labels=(int(view.ids[a]), int(view.ids[b])), view=view.name)
