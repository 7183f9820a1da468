"""The paper's Section 3 experiments in the virtual lab: calibration → measurement → metrics.

One chain, shared by ``repro/paper.py`` (the full reproduction) and ``repro/demo.py`` (the quick
end-to-end demo):

1. **Calibration images** of the paper rig (:func:`dic.lab.paper_rig`): the coded phase target
   (:class:`calibration.targets.PhaseTarget`, N-step fringes) on the monitor, seen by each camera
   through its mirror at the rig's three tilts, and directly at several poses spread over depth
   (intrinsics); optionally a far view both cameras see (joint adjustment), and checkerboard views
   at the far working distance (the conventional calibration, for comparison).
2. **Calibration** with the project's own pipeline, :mod:`calibration.pipeline` (what ``specula
   calibrate`` runs): dot centres (:mod:`calibration.detect`, the pipeline's dot filters),
   intrinsics from the direct + mirrored views (``calibrate_intrinsics_from_detections``), mirror
   extrinsics per camera (``calibrate_mirror_from_detections``: the paper's method + bundle
   adjustment), the rig (``calibrate_rig_from_mirrors``: per camera, and the joint adjustment with
   the far view). The ground-truth cameras of the virtual lab are **never** used by the
   measurement: only rendered images go in.
3. **Measurement images**: the paper's 4 × 2 dot target (300 px dots at 450 px pitch, as phase
   dots) and a speckle image at the 27 monitor positions; shifted and sinusoidally deformed
   speckle at the central position.
4. **Metrics**: neighbouring-dot distances against 139.95 mm, deviation of the DIC surface from
   its best-fit plane, measured against imposed displacements (the paper's Table 1 and Fig. 10).
   Monitor coordinates of DIC points come from the triangulated dots at the same position (a rigid
   fit of the dot target to its measured 3-D dots), not from the lab's ground truth.

Paper: "Stereo-camera calibration for large-scale DIC measurements with active phase targets and
planar mirrors", Optics Express 27(6), 9040 (2019), doi:10.1364/OE.27.009040, Section 3.

Renders are cached on disk (``cache`` folder, ``.npy`` per image, keyed by every parameter that
changes the image), so an interrupted run resumes where it stopped.
"""
from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dic.lab.paper import MONITOR_PITCH_MM, WORKING_DISTANCE_MM
from dic.lab.paper import MONITOR_RESOLUTION as MONITOR_RES
from kernels.checks import positive_int

DOT_SPACING_PX = 450.0
DOT_SPACING_MM = DOT_SPACING_PX * MONITOR_PITCH_MM  # 139.95 mm

__all__ = ["ExperimentConfig", "Experiment", "RenderCache", "CalibrationOutcome", "dot_test", "plane_deviation",
           "speckle_monitor_image", "DOT_SPACING_MM"]


@dataclass
class ExperimentConfig:
    """Everything that changes the rendered images or the processing.

    scale : camera resolution factor of the paper rig (1 = 2352 × 1728 px).
    samples : render sub-samples per pixel (a perfect square).
    speckle_samples : sub-samples per pixel for the speckle renders (planarity, displacement and
        deformation tests); None = ``samples``. The lens aperture is sampled with these points, so a
        defocused speckle rendered with few samples carries Monte Carlo noise that a camera does not
        have (measured at full scale, 2.5 px blur: 4 samples give 0.20 mm planarity RMS where 64 give
        0.043 mm); the dots and calibration views, located by phase fits over whole dots, need fewer.
    noise : read + shot noise on (quantisation to 8 bits and defocus are always on).
    calib_grid, calib_pitch : coded phase target for calibration (dots, screen px).
    direct_distances_mm : distances of the direct intrinsic views along each camera's axis.
    far_view : also render a far view both cameras see (joint mirror-stereo adjustment).
    checkerboard : also render the conventional far checkerboard views.
    positions : monitor test positions (indices 0..26).
    speckle_radius_cam_px : mean speckle disk radius, in camera px at the central depth.
    step, subset, order : stereo-DIC settings (the paper: step 2, 21 px subsets, 2nd order).
    shifts_px : horizontal shifts of the displayed speckle (monitor px) for the displacement test.
    deform_amplitude_px, deform_frequency : x_d = x + A sin(2 pi f y) (monitor px), paper A = 24, f = 1/600.
    """

    scale: float = 0.25
    samples: int = 9
    speckle_samples: int | None = None
    noise: bool = True
    seed: int = 2019
    calib_grid: tuple = (8, 4)
    calib_pitch: float = 225.0
    direct_distances_mm: tuple = (1100.0, 1250.0, 1400.0, 1600.0, 1700.0, 1800.0, 1900.0, 2000.0, 2150.0, 2300.0,
                                  2500.0, 2700.0)
    far_view: bool = True
    checkerboard: bool = True
    checker_views: int = 10
    positions: tuple = tuple(range(27))
    speckle_radius_cam_px: float = 1.6
    step: int = 2
    subset: int = 21
    order: int = 2
    shifts_px: tuple = (4, 8, 16, 32, 64, 128, 256, 384)
    deform_amplitude_px: float = 24.0
    deform_frequency: float = 1.0 / 600.0
    displacement_test: bool = True
    deformation_test: bool = True
    device: str | None = None

    def __post_init__(self):
        for name in ("samples", "speckle_samples"):
            v = getattr(self, name)
            if v is None and name == "speckle_samples":
                continue
            positive_int(v, f"ExperimentConfig.{name}")
        if not self.scale > 0:
            raise ValueError(f"ExperimentConfig.scale must be > 0, got {self.scale!r}")

    def key(self) -> dict:
        """Parameters that change rendered images (the cache key)."""
        return {"scale": self.scale, "samples": self.samples, "noise": self.noise, "seed": self.seed,
                "calib_grid": list(self.calib_grid), "calib_pitch": self.calib_pitch,
                "speckle_radius_cam_px": self.speckle_radius_cam_px}

    @property
    def speckle_render_samples(self) -> int:
        return self.samples if self.speckle_samples is None else int(self.speckle_samples)

    def speckle_key(self) -> dict:
        """Cache key of the speckle renders (the same as :meth:`key` when ``speckle_samples`` is None)."""
        return {**self.key(), "samples": self.speckle_render_samples}


class RenderCache:
    """On-disk cache of rendered images: ``folder/<hash of (config key, label)>.npy``; None = no cache."""

    def __init__(self, folder=None):
        self.folder = None if folder is None else Path(folder)
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
        self.hits = 0
        self.renders = 0
        self.render_s = 0.0

    def get(self, key: dict, label: str, make):
        name = hashlib.sha1(json.dumps([key, label], sort_keys=True).encode()).hexdigest()[:20]
        path = None if self.folder is None else self.folder / f"{name}.npy"
        if path is not None and path.exists():
            try:
                self.hits += 1
                return np.load(path)
            except Exception:  # a truncated file from an interrupted run: render again
                self.hits -= 1
        t0 = time.perf_counter()
        img = make()
        self.render_s += time.perf_counter() - t0
        self.renders += 1
        if path is not None:
            tmp = path.with_suffix(".tmp.npy")
            np.save(tmp, img)
            tmp.replace(path)
        return img


# ------------------------------------------------------------------------------------------------
# monitor images
# ------------------------------------------------------------------------------------------------
def speckle_monitor_image(radius_px: float, seed: int, displacement=None) -> np.ndarray:
    """(1080, 1920) uint8 Boolean speckle for the monitor, optionally displaced (monitor px).

    ``displacement``: None, a constant (u, v) or a callable (x, y) -> (u, v) of reference monitor
    pixel coordinates (the displayed image shows material point X at X + u(X)).
    """
    from dic.synth import make_speckle, render

    W, H = MONITOR_RES
    margin = 420.0 + 4 * radius_px
    model = make_speckle(region=(-margin, -margin, W + margin, H + margin), radius=radius_px, density=0.5,
                         blur=0.7, bits=8, samples=2, seed=seed)
    img = render(model, (H, W), displacement)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _camera_pose_world(lab_cam):
    R = np.asarray(lab_cam.R_cam_world, float)
    t = np.asarray(lab_cam.t_cam_world, float)
    return R, t, -R.T @ t


def _rot(axis, deg):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float)).as_matrix()


def _monitor_pose_facing(center_world, R_world_base, tilt_x_deg=0.0, tilt_y_deg=0.0, roll_deg=0.0):
    """Screen pose whose centre is ``center_world`` and whose frame is the base frame turned by the tilts."""
    R = R_world_base @ _rot([1, 0, 0], tilt_x_deg) @ _rot([0, 1, 0], tilt_y_deg) @ _rot([0, 0, 1], roll_deg)
    W, H = MONITOR_RES
    c_local = np.array([(W - 1) / 2 * MONITOR_PITCH_MM, (H - 1) / 2 * MONITOR_PITCH_MM, 0.0])
    return R, center_world - R @ c_local


# ------------------------------------------------------------------------------------------------
# calibration
# ------------------------------------------------------------------------------------------------
@dataclass
class CalibrationOutcome:
    """The calibrated rig(s) and their figures."""

    rig: object                       # StereoRig used for the measurements (mirror, or joint when far view)
    rig_mirror: object                # paper-faithful: rig_from_mirror of per-camera mirror extrinsics
    rig_joint: object | None          # joint mirror-stereo adjustment with the far view
    rig_conventional: object | None   # checkerboard at the far working distance, OpenCV's 5-term lens model
    figures: dict = field(default_factory=dict)
    #: the same checkerboard views with a k1, k2-only lens model (what few far views can constrain)
    rig_conventional_k1k2: object | None = None


class Experiment:
    """Renders (cached) and measures the paper's experiments on the virtual paper rig."""

    def __init__(self, config: ExperimentConfig | None = None, cache=None, log=print):
        from calibration.targets import PhaseTarget
        from dic.lab import paper_rig

        self.cfg = config or ExperimentConfig()
        self.cache = cache if isinstance(cache, RenderCache) else RenderCache(cache)
        self.log = log
        self.lab = paper_rig(scale=self.cfg.scale, noise=self.cfg.noise)
        self.size = tuple(int(v) for v in self.lab.cameras[0].size)
        self.calib_target = PhaseTarget(grid=self.cfg.calib_grid, pitch=self.cfg.calib_pitch)
        self.dot_target = PhaseTarget(grid=(4, 2), pitch=DOT_SPACING_PX, period=300.0)
        self._calib_imgs = self.calib_target.images()
        self._dot_imgs = self.dot_target.images()
        # speckle grain: radius in camera px at the central depth -> monitor px
        fx = float(self.lab.cameras[0].camera.K[0, 0])
        mm_per_px = WORKING_DISTANCE_MM / fx
        self.speckle_radius_monitor_px = self.cfg.speckle_radius_cam_px * mm_per_px / MONITOR_PITCH_MM
        self._speckle_ref = None
        self.timings = {}

    # -- rendering ---------------------------------------------------------------------------
    def _render(self, scene, cam: str, label: str, seed: int, samples: int | None = None, key: dict | None = None):
        """Cached render of ``scene`` (or of ``scene()`` when it is a callable, built only on a cache miss).

        Direct views of the monitor are windowed (:func:`dic.lab.screens_window`): the same image, the
        background pixels rendered with one sample."""
        from dic.lab import render, screens_window

        samples = self.cfg.samples if samples is None else samples

        def make():
            sc = scene() if callable(scene) else scene
            return render(sc, cam, samples=samples, seed=seed, window=screens_window(sc, cam), device=self.cfg.device)

        return self.cache.get(self.cfg.key() if key is None else key, f"{label}|{cam}", make)

    def _render_stack(self, scene, cam: str, images, label: str, seed: int):
        return np.stack([self._render(scene.with_monitor_image(im), cam, f"{label}|step{k}", (seed + 7919 * k) % (2 ** 31))
                         for k, im in enumerate(images)])

    def _seed(self, label: str) -> int:
        return int(hashlib.sha1(f"{self.cfg.seed}|{label}".encode()).hexdigest()[:7], 16)  # < 2**28

    # -- calibration views -----------------------------------------------------------------------
    def direct_poses(self, cam_index: int):
        """Monitor poses for the direct intrinsic views of one camera (spread in depth, tilted ±25°).

        Views closer than 1.6 m are centred (the target fills most of the image); the farther ones are
        pushed, in turn, toward the image's four corners and four edges until the target's image
        touches the border (2 % margin). The lens distortion is then measured out to the corners,
        where the test positions at the corners of the working volume image: with centred views
        the distortion there was extrapolated and bent the reconstructed planes (docs/paper_reproduction.md).
        """
        cam = self.lab.cameras[cam_index]
        R_cw, _, c = _camera_pose_world(cam)
        R_wc = R_cw.T
        tilts = [(20, 0, 0), (-20, 0, 5), (0, 25, -5), (0, -25, 0), (15, 15, 10), (-15, -20, -10),
                 (20, -15, 0), (-10, 20, 5), (0, 0, 0), (10, 10, -5)]
        directions = [(-1, -1), (1, 1), (1, -1), (-1, 1), (0, -1), (0, 1), (-1, 0), (1, 0)]
        fx, fy, (W, H) = float(cam.camera.K[0, 0]), float(cam.camera.K[1, 1]), cam.size
        lo, hi = self.calib_target._lit_lo * MONITOR_PITCH_MM, self.calib_target._lit_hi * MONITOR_PITCH_MM
        lit = np.array([[lo[0], lo[1], 0.0], [hi[0], lo[1], 0.0], [hi[0], hi[1], 0.0], [lo[0], hi[1], 0.0]])
        margin = 0.02 * W
        poses, k = [], 0
        for n, d in enumerate(self.cfg.direct_distances_mm):
            tx, ty, roll = tilts[n % len(tilts)]
            if d < 1600:
                poses.append(_monitor_pose_facing(c + R_wc @ np.array([0.0, 0.0, d]), R_wc, tx, ty, roll))
                continue
            u, v = directions[k % len(directions)]
            k += 1
            for scale in np.linspace(1.0, 0.0, 41):  # the largest offset that keeps the target in view
                off = np.array([u * scale * (W / 2) / fx * d, v * scale * (H / 2) / fy * d, d])
                R, t = _monitor_pose_facing(c + R_wc @ off, R_wc, tx, ty, roll)
                uv = cam.project(lit @ R.T + t)
                if np.all((uv > margin) & (uv < np.array([W - 1, H - 1]) - margin)):
                    break
            poses.append((R, t))
        return poses

    def far_pose(self):
        """A far view both cameras see (not a test position): 4.6 m, turned 12° / -8°."""
        return _monitor_pose_facing(np.array([150.0, -100.0, 4600.0]), np.eye(3), 8.0, -12.0, 3.0)

    def checker_poses(self):
        """Conventional calibration: monitor (checkerboard) near the far working distance, tilted."""
        rng = np.random.default_rng(self.cfg.seed + 5)
        poses = []
        for n in range(self.cfg.checker_views):
            z = WORKING_DISTANCE_MM + rng.uniform(-500, 500)
            center = np.array([rng.uniform(-500, 500), rng.uniform(-350, 350), z])
            poses.append(_monitor_pose_facing(center, np.eye(3), rng.uniform(-30, 30), rng.uniform(-30, 30),
                                              rng.uniform(-8, 8)))
        return poses

    def detect(self, stack):
        """Dots of a calibration view, with the calibration pipeline's dot filters.

        :func:`calibration.pipeline.filter_detection` drops vignetted dots (fringe modulation falling
        off across the dot: the blur spot cut by a mirror's edge; in this rig a whole row or column
        of every mirrored view) and dots with a poor phase fit, as ``specula calibrate`` does."""
        from calibration.detect import detect_dots_in_images
        from calibration.pipeline import filter_detection

        kept, _, _ = filter_detection(detect_dots_in_images(stack, self.calib_target, device=self.cfg.device))
        return kept

    def calibrate(self) -> CalibrationOutcome:
        """Render the calibration images and calibrate the rig with :mod:`calibration.pipeline`.

        The steps of ``specula calibrate`` on the detected views: intrinsics from the direct and
        mirrored views in one bundle (:func:`~calibration.pipeline.calibrate_intrinsics_from_detections`),
        each camera's mirror extrinsics (:func:`~calibration.pipeline.calibrate_mirror_from_detections`),
        the rig per camera and jointly with the far view
        (:func:`~calibration.pipeline.calibrate_rig_from_mirrors`). Choices of this study, kept so that
        its recorded figures stay the same: no point-outlier rejection (``reject_points=None``), the
        mirror extrinsics on the dots every tilt shows (the joint adjustment: the dots both cameras'
        tilts show), and the rig's covariance without the intrinsics' share."""
        from calibration.detect import DetectionError
        from calibration.pipeline import (
            StereoView,
            ViewResult,
            calibrate_intrinsics_from_detections,
            calibrate_rig_from_mirrors,
        )

        t0 = time.perf_counter()
        lab = self.lab
        names = [c.name for c in lab.cameras]
        n_tilts = len(lab.mirror_tilts_deg)
        mirrored = {n: [] for n in names}
        for k in range(n_tilts):
            scene = lab.with_mirror_tilt(k)
            for n in names:
                stack = self._render_stack(scene, n, self._calib_imgs, f"calib|mirror{k}", self._seed(f"m{k}{n}"))
                try:
                    mirrored[n].append(self.detect(stack))
                except DetectionError as exc:
                    raise DetectionError(f"{n} camera, mirror tilt {k}: the mirrored target was not detected ({exc}); "
                                         "the mirror method needs every tilt") from exc
        self.log("[calib] mirrored views detected: " + ", ".join(
            f"{n} {[len(d.ids) for d in mirrored[n]]}" for n in names))
        direct = {n: [] for n in names}
        for ci, n in enumerate(names):
            for v, (R, t) in enumerate(self.direct_poses(ci)):
                scene = lab.without_mirrors().with_monitor_pose(R, t)
                pose_key = np.round(np.concatenate([R.ravel(), t]), 4).tolist()  # the pose is part of the cache key
                stack = self._render_stack(scene, n, self._calib_imgs, f"calib|direct{v}|{pose_key}",
                                           self._seed(f"d{v}{n}"))
                try:
                    direct[n].append(self.detect(stack))
                except DetectionError as exc:
                    self.log(f"[calib] {n} direct view {v}: not detected ({exc})")
        self.log("[calib] direct views detected: " + ", ".join(f"{n} {[len(d.ids) for d in direct[n]]}" for n in names))
        cams, intr = {}, {}
        for n in names:
            views = ([ViewResult(f"{n} direct {v}", self.size, detection=d) for v, d in enumerate(direct[n])]
                     + [ViewResult(f"{n} mirror tilt {k}", self.size, detection=d) for k, d in enumerate(mirrored[n])])
            # min_points=1: every detected view enters the bundle, as detected
            res = calibrate_intrinsics_from_detections(views, model="opencv5", reject_points=None, min_points=1, name=n)
            cams[n], intr[n] = res.camera, res.result
        # mirror extrinsics per camera: the dots seen in every tilt
        mirror = {}
        for n in names:
            seen_by_all = set(mirrored[n][0].ids.tolist())
            for d in mirrored[n][1:]:
                seen_by_all &= set(d.ids.tolist())
            mirror[n] = self._mirror_calibration(cams[n], mirrored[n], np.array(sorted(seen_by_all)))
        nL, nR = names
        rig_mirror = calibrate_rig_from_mirrors(mirror[nL], mirror[nR], joint=False, intrinsic_uncertainty=False).rig
        figures = {
            "reprojection_rms_px": {n: float(intr[n].rms) for n in names},
            "intrinsic_views": {n: int(len(intr[n].per_view_rms)) for n in names},
            "intrinsic_dropped_views": {n: len(getattr(intr[n], "dropped", []) or []) for n in names},
            "mirror_rms_px": {n: float(mirror[n].result.rms) for n in names},
            "mirror_points": {n: int(len(mirror[n].point_ids)) for n in names},
            "baseline_mm_mirror": float(rig_mirror.baseline),
        }
        rig_joint = None
        if self.cfg.far_view:
            R, t = self.far_pose()
            scene = lab.without_mirrors().with_monitor_pose(R, t)
            dl = self.detect(self._render_stack(scene, names[0], self._calib_imgs, "calib|far", self._seed("farL")))
            dr = self.detect(self._render_stack(scene, names[1], self._calib_imgs, "calib|far", self._seed("farR")))
            ids, ql, qr = _matched(dl, dr)
            far = StereoView(ids, self.calib_target.object_points[ids], ql, qr, name="far")
            # the joint adjustment needs the same points in both cameras' mirrored views: the common dots,
            # each camera's mirror extrinsics re-solved on them as its start
            common = np.intersect1d(mirror[nL].point_ids, mirror[nR].point_ids)
            both = {n: self._mirror_calibration(cams[n], mirrored[n], common) for n in names}
            rig_joint = calibrate_rig_from_mirrors(both[nL], both[nR], far_views=[far], joint=True,
                                                   intrinsic_uncertainty=False).rig
            figures["baseline_mm_joint"] = float(rig_joint.baseline)
            figures["far_view_points"] = int(len(ids))
        rig_conv = rig_conv_k1k2 = None
        if self.cfg.checkerboard:
            rig_conv, rig_conv_k1k2 = self._conventional(names, figures)
        self.timings["calibration_s"] = time.perf_counter() - t0
        rig = rig_joint if rig_joint is not None else rig_mirror
        return CalibrationOutcome(rig=rig, rig_mirror=rig_mirror, rig_joint=rig_joint, rig_conventional=rig_conv,
                                  figures=figures, rig_conventional_k1k2=rig_conv_k1k2)

    def _mirror_calibration(self, camera, detections, ids):
        """:func:`calibration.pipeline.calibrate_mirror_from_detections` of one camera's mirrored views
        restricted to the dots ``ids`` (sorted, seen in every view), without point-outlier rejection."""
        from calibration.pipeline import ViewResult, calibrate_mirror_from_detections

        views = [ViewResult(f"{camera.name} mirror tilt {k}", self.size, detection=_dots_with_ids(d, ids))
                 for k, d in enumerate(detections)]
        return calibrate_mirror_from_detections(camera, views, self.calib_target, reject_points=None)

    def _conventional(self, names, figures):
        """Checkerboard at the far working distance: intrinsics and rig from those views only (OpenCV).

        Returns ``(rig_opencv5, rig_k1k2)``: the rig with OpenCV's default 5-term lens model (k1, k2, p1,
        p2, k3), and with a k1, k2-only model (``radial2``) — a small board far away leaves the outer
        image unconstrained, where a 5-term fit can bend so much that it cannot be inverted; the
        2-term fit is what a careful user would choose with such views. ``(None, None)`` when fewer
        than 3 views are found in both cameras."""
        from calibration.detect import detect_checkerboard
        from calibration.intrinsics import calibrate_intrinsics
        from calibration.stereo import stereo_calibrate
        from calibration.targets import CheckerboardTarget

        board = CheckerboardTarget(corners=(8, 5), square=170)
        img = board.images()[0]
        X = board.object_points
        per = {n: [] for n in names}
        for v, (R, t) in enumerate(self.checker_poses()):
            scene = self.lab.without_mirrors().with_monitor_pose(R, t).with_monitor_image(img)
            found = []
            for n in names:
                im = self._render(scene, n, f"checker{v}|{np.round(t, 4).tolist()}", self._seed(f"c{v}{n}"))
                det = detect_checkerboard(im, board)
                if det is not None:
                    pts = det[0]
                    # OpenCV may start from either end of a symmetric board: put the first corner top-left
                    if pts[0, 0] + pts[0, 1] > pts[-1, 0] + pts[-1, 1]:
                        pts = pts[::-1].copy()
                found.append(None if det is None else pts)
            per[names[0]].append(found[0])
            per[names[1]].append(found[1])
        both = [i for i in range(len(per[names[0]])) if per[names[0]][i] is not None and per[names[1]][i] is not None]
        figures["conventional_views"] = len(both)
        if len(both) < 3:
            self.log(f"[calib] conventional: only {len(both)} checkerboard views found in both cameras; skipped")
            return None, None
        rigs = []
        for model, key in (("opencv5", "conventional"), ("radial2", "conventional_k1k2")):
            cams = {}
            for n in names:
                views = [p for p in per[n] if p is not None]
                res = calibrate_intrinsics([X] * len(views), views, self.size, model=model, name=n)
                cams[n] = res.camera
                figures.setdefault(f"{key}_reprojection_rms_px", {})[n] = float(res.rms)
            sc = stereo_calibrate(cams[names[0]], cams[names[1]], [X] * len(both), [per[names[0]][i] for i in both],
                                  [per[names[1]][i] for i in both], uncertainty="none")
            figures[f"{key}_stereo_rms_px"] = float(getattr(sc, "rms", float("nan")))
            figures[f"baseline_mm_{key}"] = float(sc.rig.baseline)
            rigs.append(sc.rig)
        return tuple(rigs)

    # -- measurement images -------------------------------------------------------------------
    def dot_views(self, position: int):
        """Dot detections (left, right) of the 4 × 2 dot target at a monitor position."""
        from calibration.detect import detect_dots_in_images

        scene = self.lab.with_monitor_at(position)
        out = []
        for n in ("left", "right"):
            stack = self._render_stack(scene, n, self._dot_imgs, f"dots|pos{position}", self._seed(f"dots{position}{n}"))
            out.append(detect_dots_in_images(stack, self.dot_target, device=self.cfg.device))
        return out

    def speckle_image(self, displacement=None, label="ref"):
        if displacement is None:
            if self._speckle_ref is None:
                self._speckle_ref = speckle_monitor_image(self.speckle_radius_monitor_px, self.cfg.seed + 11)
            return self._speckle_ref
        return speckle_monitor_image(self.speckle_radius_monitor_px, self.cfg.seed + 11, displacement)

    def speckle_pair(self, position: int, displacement=None, label="ref"):
        """Rendered (left, right) of the monitor at ``position`` showing the (displaced) speckle."""
        key = f"speckle|{label}|pos{position}"
        cached = []
        lazy = {}

        def image():
            if "img" not in lazy:
                lazy["img"] = self.speckle_image(displacement, label)
            return lazy["img"]

        for n in ("left", "right"):
            seed = self._seed(f"{key}{n}")
            cached.append(self._render(lambda: self.lab.with_monitor_at(position).with_monitor_image(image()), n, key,
                                       seed, samples=self.cfg.speckle_render_samples, key=self.cfg.speckle_key()))
        return cached


# ------------------------------------------------------------------------------------------------
# metrics
# ------------------------------------------------------------------------------------------------
def _dots_with_ids(det, ids):
    """The rows of a :class:`calibration.detect.DotDetection` whose dot id is in ``ids``."""
    keep = np.isin(det.ids, ids)
    return replace(det, image_points=det.image_points[keep], ids=det.ids[keep], object_points=det.object_points[keep],
                   residual_rms=det.residual_rms[keep], sigma_px=det.sigma_px[keep], modulation=det.modulation[keep],
                   n_pixels=det.n_pixels[keep],
                   modulation_slope=None if det.modulation_slope is None else det.modulation_slope[keep])


def _matched(det_l, det_r):
    ids = np.intersect1d(det_l.ids, det_r.ids)
    il = {int(i): k for k, i in enumerate(det_l.ids)}
    ir = {int(i): k for k, i in enumerate(det_r.ids)}
    return ids, det_l.image_points[[il[int(i)] for i in ids]], det_r.image_points[[ir[int(i)] for i in ids]]


def triangulate_dots(rig, det_l, det_r, target):
    """Triangulated dots (left frame, mm), their ids and the target's object points."""
    from dic._triangulate import triangulate

    ids, ql, qr = _matched(det_l, det_r)
    res = triangulate(rig, ql, qr, method="optimal")
    ok = np.asarray(res.status) == 0
    if not np.all(ok):
        raise ValueError(f"triangulation of dots {ids[~ok].tolist()} failed (status {np.asarray(res.status)[~ok].tolist()})")
    P = np.asarray(res.points, np.float64)
    return ids, P, target.object_points[ids], np.asarray(res.residuals, np.float64)


def dot_test(rig, det_l, det_r, target):
    """Neighbouring-dot distances (mm) of one 4 × 2 view; returns dict with distances, errors, centre."""
    ids, P, X, resid = triangulate_dots(rig, det_l, det_r, target)
    nx, ny = target.grid
    where = {int(i): k for k, i in enumerate(ids)}
    d = []
    for j in range(ny):
        for i in range(nx):
            a = j * nx + i
            for b in ((a + 1) if i + 1 < nx else None, (a + nx) if j + 1 < ny else None):
                if b is not None and a in where and b in where:
                    d.append(float(np.linalg.norm(P[where[a]] - P[where[b]])))
    d = np.array(d)
    return {"distances_mm": d, "errors_mm": d - DOT_SPACING_MM, "points": P, "ids": ids,
            "reprojection_px": resid, "centre": P.mean(axis=0)}


def monitor_frame_from_dots(rig, det_l, det_r, target):
    """Measured pose of the monitor (screen frame → left camera frame) from its triangulated dots (Kabsch)."""
    from calibration.camera import rigid_fit

    _, P, X, _ = triangulate_dots(rig, det_l, det_r, target)
    out = rigid_fit(X, P)
    R, t = out[0], out[1]
    return np.asarray(R), np.asarray(t)


def plane_deviation(points):
    """Signed distances (mm) of (N, 3) points to their least-squares plane, and the unit normal."""
    P = np.asarray(points, np.float64)
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    n = vt[2]
    return (P - c) @ n, n


def roi_from_dots(det_l, target, image_shape, inset_px=60.0):
    """Boolean mask of the monitor's screen (inset) in the left image, from the measured dot homography."""
    import cv2

    X = target.object_points[det_l.ids][:, :2] / target.pixel_pitch
    H, _ = cv2.findHomography(X, det_l.image_points)
    W, Hs = MONITOR_RES
    corners = np.array([[inset_px, inset_px], [W - 1 - inset_px, inset_px], [W - 1 - inset_px, Hs - 1 - inset_px],
                        [inset_px, Hs - 1 - inset_px]], np.float64)
    poly = cv2.perspectiveTransform(corners[None], H)[0]
    mask = np.zeros(image_shape, np.uint8)
    cv2.fillPoly(mask, [np.round(poly).astype(np.int32)], 1)
    return mask.astype(bool)


def to_monitor(R_left_screen, t_left_screen, P):
    """Left-frame points (N, 3) → screen frame (mm); x / 0.311 and y / 0.311 are monitor px."""
    return (np.asarray(P) - t_left_screen) @ R_left_screen


# ------------------------------------------------------------------------------------------------
# the experiments
# ------------------------------------------------------------------------------------------------
def run_dot_tests(exp: Experiment, rigs: dict, positions=None, log=print) -> dict:
    """The 4 × 2 dot test at each position with each rig in ``rigs`` (name → StereoRig)."""
    positions = exp.cfg.positions if positions is None else positions
    out = {name: {"positions": [], "labels": [], "centres_mm": [], "mean_distance_mm": [], "errors_mm": [],
                  "reprojection_rms_px": []} for name in rigs if rigs[name] is not None}
    dets = {}
    for p in positions:
        try:
            dets[p] = exp.dot_views(p)
        except Exception as exc:  # a position whose dots are not found is reported, not fatal
            log(f"[dots] position {p}: detection failed ({exc})")
            continue
        for name, rig in rigs.items():
            if rig is None:
                continue
            o = out[name]
            try:
                r = dot_test(rig, *dets[p], exp.dot_target)
            except ValueError as exc:  # e.g. a lens model that cannot be inverted there: report, go on
                o.setdefault("failed_positions", []).append(int(p))
                log(f"[dots] position {p}, rig {name}: {exc}")
                continue
            o["positions"].append(int(p))
            o["labels"].append(list(exp.lab.monitor_positions[p].label))
            o["centres_mm"].append(r["centre"].tolist())
            o["mean_distance_mm"].append(float(r["distances_mm"].mean()))
            o["errors_mm"].extend(r["errors_mm"].tolist())
            o["reprojection_rms_px"].append(float(np.sqrt(np.mean(r["reprojection_px"] ** 2))))
        log(f"[dots] position {p} {exp.lab.monitor_positions[p].label}: " + ", ".join(
            f"{n} {out[n]['mean_distance_mm'][-1]:.3f} mm" for n in out
            if out[n]["positions"] and out[n]["positions"][-1] == p))
    for name, o in out.items():
        e = np.array(o["errors_mm"])
        d = e + DOT_SPACING_MM
        o["distance_mean_mm"] = float(d.mean()) if d.size else float("nan")
        o["distance_std_mm"] = float(d.std(ddof=1)) if d.size > 1 else float("nan")
        o["error_mean_mm"] = float(e.mean()) if e.size else float("nan")
        o["abs_error_mean_mm"] = float(np.abs(e).mean()) if e.size else float("nan")
        o["relative_error_percent"] = 100.0 * o["error_mean_mm"] / DOT_SPACING_MM
        o["abs_relative_error_percent"] = 100.0 * o["abs_error_mean_mm"] / DOT_SPACING_MM
    return out, dets


def run_planarity(exp: Experiment, rig, dets: dict, positions=None, log=print) -> dict:
    """Speckle at each position: stereo-DIC shape, deviation from the best-fit plane."""
    from dic._stereo import stereo

    positions = exp.cfg.positions if positions is None else positions
    out = {"positions": [], "labels": [], "rms_mm": [], "mean_abs_mm": [], "points": [], "valid": [], "centres_mm": [],
           "time_s": []}
    for p in positions:
        if p not in dets:
            continue
        L, R = exp.speckle_pair(p)
        roi = roi_from_dots(dets[p][0], exp.dot_target, L.shape)
        t0 = time.perf_counter()
        f = stereo(rig, L, R, step=exp.cfg.step, subset=exp.cfg.subset, order=exp.cfg.order, roi=roi,
                   device=exp.cfg.device)
        dt = time.perf_counter() - t0
        v = np.asarray(f.valid, bool)
        P = np.stack([np.asarray(f.X), np.asarray(f.Y), np.asarray(f.Z)], axis=1)[v]
        dev, _ = plane_deviation(P)
        out["positions"].append(int(p))
        out["labels"].append(list(exp.lab.monitor_positions[p].label))
        out["rms_mm"].append(float(np.sqrt(np.mean(dev ** 2))))
        out["mean_abs_mm"].append(float(np.mean(np.abs(dev))))
        out["points"].append(int(np.sum(np.asarray(f.status) != 1)))  # POIs in the ROI (1 = NOT_COMPUTED)
        out["valid"].append(int(v.sum()))
        out["centres_mm"].append(P.mean(axis=0).tolist())
        out["time_s"].append(dt)
        log(f"[plane] position {p}: {v.sum()}/{v.size} points, RMS deviation {out['rms_mm'][-1]:.4f} mm ({dt:.1f} s)")
    r = np.array(out["rms_mm"])
    out["rms_mean_mm"] = float(r.mean()) if r.size else float("nan")
    out["rms_std_mm"] = float(r.std(ddof=1)) if r.size > 1 else float("nan")
    a = np.array(out["mean_abs_mm"])
    out["mean_abs_mean_mm"] = float(a.mean()) if a.size else float("nan")
    return out


def _central_position(exp):
    return next(p.index for p in exp.lab.monitor_positions if tuple(p.label) == (2, 2, 2))


def run_displacement_test(exp: Experiment, rig, dets_centre, log=print) -> dict:
    """Eight horizontal shifts of the displayed speckle at (2, 2, 2): measured vs imposed (Table 1)."""
    from dic._stereo import StereoCorrelation

    p = _central_position(exp)
    L0, R0 = exp.speckle_pair(p)
    roi = roi_from_dots(dets_centre[0], exp.dot_target, L0.shape)
    Rm, tm = monitor_frame_from_dots(rig, *dets_centre, exp.dot_target)
    sc = StereoCorrelation(rig, L0, R0, step=max(exp.cfg.step, 2), subset=exp.cfg.subset, order=exp.cfg.order,
                           roi=roi, device=exp.cfg.device)
    rows = []
    for s in exp.cfg.shifts_px:
        L, R = exp.speckle_pair(p, (float(s), 0.0), label=f"shift{s}")
        f = sc.measure(L, R)
        v = np.asarray(f.valid, bool)
        U = np.stack([np.asarray(f.U), np.asarray(f.V), np.asarray(f.W)], axis=1)[v]
        Um = U @ Rm  # components in the measured monitor frame (mm)
        mag = np.linalg.norm(U, axis=1)
        imposed = s * MONITOR_PITCH_MM
        n_roi = int(np.sum(np.asarray(f.status) != 1))
        rows.append({"imposed_px": float(s), "imposed_mm": imposed, "measured_mm": float(mag.mean()),
                     "std_mm": float(mag.std(ddof=1)), "error_mm": float(mag.mean() - imposed),
                     "relative_error_percent": float(100 * (mag.mean() - imposed) / imposed),
                     "u_monitor_mm": float(Um[:, 0].mean()), "v_monitor_mm": float(Um[:, 1].mean()),
                     "w_monitor_mm": float(Um[:, 2].mean()), "valid": int(v.sum()), "points": n_roi})
        log(f"[shift] {s} px = {imposed:.3f} mm: measured {mag.mean():.4f} ± {mag.std():.4f} mm ({v.sum()}/{v.size})")
    return {"position": int(p), "rows": rows}


def run_deformation_test(exp: Experiment, rig, dets_centre, log=print) -> dict:
    """x_d = x + A sin(2 pi f y) on the displayed speckle at (2, 2, 2): u profile, spurious v, w."""
    from dic._stereo import stereo

    A, fr = exp.cfg.deform_amplitude_px, exp.cfg.deform_frequency
    p = _central_position(exp)
    L0, R0 = exp.speckle_pair(p)
    L1, R1 = exp.speckle_pair(p, lambda x, y: (A * np.sin(2 * np.pi * fr * y), 0.0 * y), label=f"sine{A}_{fr:.6g}")
    roi = roi_from_dots(dets_centre[0], exp.dot_target, L0.shape)
    Rm, tm = monitor_frame_from_dots(rig, *dets_centre, exp.dot_target)
    f = stereo(rig, L0, R0, L1, R1, step=exp.cfg.step, subset=exp.cfg.subset, order=exp.cfg.order, roi=roi,
               device=exp.cfg.device)
    v = np.asarray(f.valid, bool)
    P = np.stack([np.asarray(f.X), np.asarray(f.Y), np.asarray(f.Z)], axis=1)[v]
    U = np.stack([np.asarray(f.U), np.asarray(f.V), np.asarray(f.W)], axis=1)[v]
    Pm = to_monitor(Rm, tm, P) / MONITOR_PITCH_MM           # monitor px (x, y, z/0.311)
    Um = (U @ Rm) / MONITOR_PITCH_MM                         # displacement in monitor px
    u_true = A * np.sin(2 * np.pi * fr * Pm[:, 1])
    resid = Um[:, 0] - u_true
    # profile: bin by monitor row
    edges = np.linspace(Pm[:, 1].min(), Pm[:, 1].max(), 41)
    idx = np.clip(np.digitize(Pm[:, 1], edges) - 1, 0, len(edges) - 2)
    prof_y = [float(Pm[idx == b, 1].mean()) for b in range(len(edges) - 1) if np.any(idx == b)]
    prof_u = [float(Um[idx == b, 0].mean()) for b in range(len(edges) - 1) if np.any(idx == b)]
    # peak smoothing: amplitude of the fitted sinusoid (phase known from the imposed field)
    s = np.sin(2 * np.pi * fr * Pm[:, 1])
    c = np.cos(2 * np.pi * fr * Pm[:, 1])
    coef, *_ = np.linalg.lstsq(np.stack([s, c, np.ones_like(s)], 1), Um[:, 0], rcond=None)
    out = {"position": int(p), "points": int(np.sum(np.asarray(f.status) != 1)), "valid": int(v.sum()),
           "v_mean_px": float(Um[:, 1].mean()), "v_std_px": float(Um[:, 1].std(ddof=1)),
           "w_mean_px": float(Um[:, 2].mean()), "w_std_px": float(Um[:, 2].std(ddof=1)),
           "u_residual_rms_px": float(np.sqrt(np.mean(resid ** 2))), "u_residual_mean_px": float(resid.mean()),
           "fitted_amplitude_px": float(coef[0]), "imposed_amplitude_px": float(A),
           "peak_smoothing_percent": float(100 * (1 - coef[0] / A)),
           "profile_y_px": prof_y, "profile_u_px": prof_u,
           "_map": {"x_px": Pm[:, 0], "y_px": Pm[:, 1], "u_px": Um[:, 0], "residual_px": resid}}
    log(f"[sine] u amplitude {coef[0]:.3f} px of {A} ({out['peak_smoothing_percent']:.2f} % smoothing), "
        f"v {out['v_mean_px']:.4f} ± {out['v_std_px']:.4f} px, w {out['w_mean_px']:.4f} ± {out['w_std_px']:.4f} px")
    return out
