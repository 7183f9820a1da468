"""Intrinsics stage: one camera's intrinsics from detected views, direct and mirrored together
(paper Steps 3–4; :func:`calibration.intrinsics.calibrate_intrinsics`), with outlier points removed
and the calibration repeated → :class:`IntrinsicsCalibration`.

The entry point from image files is :func:`calibration.pipeline.calibrate_intrinsics_from_images`.
Frames and units: docs/conventions.md (mm, px, camera frame x right / y down / z forward, pixel
(0, 0) the centre of the top-left pixel); target frame: :mod:`calibration.targets`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from ..intrinsics import DISTORTION_MODELS, IntrinsicsResult, calibrate_intrinsics
from ..reports import intrinsics_report
from ..views import ViewResult, dense_view_points

__all__ = ["IntrinsicsCalibration", "calibrate_intrinsics_from_detections"]


@dataclass
class IntrinsicsCalibration:
    """Intrinsic calibration from images (:func:`calibration.pipeline.calibrate_intrinsics_from_images`).

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
        """The text report (:func:`calibration.reports.intrinsics_report`)."""
        return intrinsics_report(self)

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
                "model": res.model, "rms_px": res.rms, "rms_all_views_px": res.rms_all_views, "std": res.std, "view_rms_px": self.view_rms(),
                "mirrored_views": [self.views[self.used[i]].name for i, m in zip(res.view_indices, res.mirrored) if m],
                "dropped": [{"view": n, "reason": r} for n, r in self.dropped],
                "dropped_views": [{"view": self.views[self.used[d.index]].name, "rms_px": d.rms,
                                   "rms_all_views_px": d.rms_all_views, "reason": d.reason} for d in res.dropped],
                "dropped_points": [{"view": n, "id": i, "residual_px": r, "threshold_px": t}
                                   for n, i, r, t in self.dropped_points],
                "removed_dots": {v.name: [{"id": i, "misfit": m} for i, m in v.removed] for v in self.views if v.removed},
                "vignetted_dots": {v.name: [{"id": i, "modulation_slope": m} for i, m in v.vignetted]
                                   for v in self.views if v.vignetted}}


def calibrate_intrinsics_from_detections(results, *, model: str = "opencv5", reject: float | None = 3.0,
                                         max_view_rms: float | None = None, reject_mad: float | None = None,
                                         reject_points: float | None = 4.0,
                                         min_points: int = 6, dense_spacing: float = 75.0,
                                         weighting: str = "equal", name: str = "") -> IntrinsicsCalibration:
    """The bundle of :func:`calibration.pipeline.calibrate_intrinsics_from_images` on views already
    detected (a list of :class:`ViewResult` from :func:`calibration.pipeline.detect_views`, possibly of
    different targets or modes); same options (``dense_spacing`` in screen px for dense views)."""
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
                                   max_view_rms=max_view_rms, reject_mad=reject_mad, weighting=weighting, name=name)
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
