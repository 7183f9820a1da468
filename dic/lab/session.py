"""A calibration session of the paper's rig in the virtual lab, rendered as image folders.

What a lab session records, made with :mod:`dic.lab` so that the result can be compared with the
truth: the monitor showing the phase-shifted fringes of the paper's target, seen directly by each
camera at many poses (intrinsics), in a mirror behind the cameras at several tilts (mirror
extrinsics), where both cameras see it (the far view) and once more for checking. ``specula lab
session DIR`` writes it (:func:`export_session`); the CLI walk-through of docs/calibration.md runs on
it, and ``repro/calibration_lab.py`` measures the calibration on the same views.

Conventions (docs/conventions.md): world and camera frames in mm, poses ``R_world_screen``,
``t_world_screen`` etc., images ``[row, col]``.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass

import numpy as np

from calibration.camera import rotation_from_vector
from calibration.stereo import StereoRig
from calibration.targets import PhaseTarget, make_cell_code
from kernels._atomic import atomic_output

__all__ = ["DIRECT_POSES", "EXTRA_DIRECT_POSES", "MIRROR_TILTS", "DENSE_DIRECT_POSES", "paper_target", "dense_target",
           "direct_pose", "common_pose", "render_view_stack", "target_pose", "true_rig", "Cache", "LabSession",
           "export_session"]


# -- scenario ---------------------------------------------------------------------------------------
#: Direct intrinsic views: (depth along the camera axis mm, offset u, v as a fraction of the room
#: left in the image, tilt about the camera x and y axes in degrees). Depths from 1.15 m (the
#: monitor fills the image, ~28 px blur at full resolution) to 3.4 m.
DIRECT_POSES = (
    (1150, 0, 0, 0, 0), (1250, 0, 0, 25, 0), (1250, 0, 0, 0, -30), (1500, -1, -1, -20, 20), (1500, 1, 1, 20, -20),
    (1800, 1, -1, -25, -15), (1800, -1, 1, 15, 25), (2200, -1, 1, 10, 30), (2200, 1, -1, -30, -10),
    (2700, 1, 1, 20, 20), (2700, -1, -1, -20, -20), (3400, 0, 0, 10, -15),
)
#: 36 more direct views for the "more views" setup (48 per camera with DIRECT_POSES): depths evenly over
#: 1.15-3.4 m, tilts of 10-30° in directions spread by the golden angle, the target pushed to the image's
#: corners, edges and centre in turn (generated once, written out so that cache keys stay stable).
#: Why: with 12 views the principal point is known to ~0.3-0.5 px, i.e. ~0.005-0.007° of camera rotation
#: that no mirror view can see; repro/intrinsics_design.py predicts 48 views halve it (docs/calibration.md).
EXTRA_DIRECT_POSES = (
    (1150, 1, 1, 10, 0), (1210, -1, 0, -17, 15), (1280, -1, -1, 1, -14), (1340, 0, 1, 16, 21), (1410, 1, -1, -17, -3),
    (1470, 0, -1, 25, -16), (1540, -1, 1, -5, 20), (1600, 0, 0, -5, -10), (1660, 1, 0, 23, 8), (1730, 1, 1, -14, 6),
    (1790, -1, 0, 12, -26), (1860, -1, -1, 6, 18), (1920, 0, 1, -9, -5), (1990, 1, -1, 22, -5), (2050, 0, -1, -8, 11),
    (2110, -1, 1, -3, -26), (2180, 0, 0, 13, 11), (2240, 1, 0, -30, 1), (2310, 1, 1, 15, -15), (2370, -1, 0, -1, 12),
    (2440, -1, -1, -16, -19), (2500, 0, 1, 15, 2), (2560, 1, -1, -23, 16), (2630, 0, -1, 4, -19), (2690, -1, 1, 5, 9),
    (2760, 0, 0, -22, -7), (2820, 1, 0, 12, -6), (2890, 1, 1, -10, 24), (2950, -1, 0, -6, -16), (3010, -1, -1, 27, 14),
    (3080, 0, 1, -20, 5), (3140, 1, -1, 6, -10), (3210, 0, -1, 4, 24), (3270, -1, 1, -12, -9), (3340, 0, 0, 28, -2),
    (3400, 1, 0, -13, 14),
)
#: Mirror-mount settings (about the mirror's vertical, horizontal axes; degrees). The first three are
#: the lab's (and the paper's) three tilts; the improved setup adds two more on the same 3° cone.
MIRROR_TILTS = ((3.0, 0.0), (-1.5, 2.6), (-1.5, -2.6), (1.5, 2.6), (1.5, -2.6))
#: Indices into DIRECT_POSES at which the improved setup also shows the 24x12 target directly (one
#: more render per pose and camera, ~1-3 min each at full resolution; ``--dense-poses`` picks a subset).
DENSE_DIRECT_POSES = tuple(range(12))


def paper_target(steps: int = 4) -> PhaseTarget:
    """The paper's target: 6 × 3 dots, 300 px pitch (93.3 mm), one fringe period per cell, coded."""
    return PhaseTarget(grid=(6, 3), pitch=300, steps=steps)


def dense_target(steps: int = 4, grid=(24, 12), pitch: float = 75) -> PhaseTarget:
    """A denser dot grid on the same monitor area (24 × 12 dots at 75 px = 23.3 mm by default).

    The code is searched with a 4 × 4 window (``make_cell_code``'s default search starts with a 2 × 3
    window, which takes minutes for grids this large)."""
    code, _ = make_cell_code(grid, window=(4, 4))
    return PhaseTarget(grid=grid, pitch=pitch, steps=steps, code=code)


def rot_xy(ax_deg: float, ay_deg: float) -> np.ndarray:
    return rotation_from_vector([np.radians(ax_deg), 0, 0]) @ rotation_from_vector([0, np.radians(ay_deg), 0])


def direct_pose(rig, camera: str, target: PhaseTarget, depth: float, u: float, v: float, ax: float, ay: float,
                margin: float = 0.03):
    """Monitor pose ``(R_world_screen, t_world_screen)`` for a direct view of ``camera``.

    The monitor faces the camera, turned by ``ax`` / ``ay`` degrees about the camera's x / y axes, its
    centre at ``depth`` mm along the viewing direction shifted by ``(u, v)`` times the room that keeps
    the target's lit area ``margin`` × width inside the image.
    """
    cam = rig.camera(camera)
    W, H = cam.size
    R_c_s = rot_xy(ax, ay)
    pitch = rig.monitor.pixel_pitch_mm[0]
    res = rig.monitor.resolution
    c_local = np.array([(res[0] - 1) / 2 * pitch, (res[1] - 1) / 2 * pitch, 0.0])
    lo, hi = target._lit_lo * target.pixel_pitch, target._lit_hi * target.pixel_pitch
    corners = np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0], [lo[0], hi[1], 0]])
    m = margin * W
    for s in np.linspace(1.0, 0.0, 41):
        p_c = np.array([u * s * (W / 2) / cam.camera.fx * depth, v * s * (H / 2) / cam.camera.fy * depth, depth])
        t_c = p_c - R_c_s @ c_local
        uv = cam.camera.project(corners @ R_c_s.T + t_c)
        if np.all(uv[:, 0] > m) and np.all(uv[:, 0] < W - 1 - m) and np.all(uv[:, 1] > m) and np.all(uv[:, 1] < H - 1 - m):
            break
    else:
        raise ValueError(f"direct pose depth={depth} ax={ax} ay={ay}: the target does not fit in the image")
    return cam.R_cam_world.T @ R_c_s, cam.R_cam_world.T @ (t_c - cam.t_cam_world)


def common_pose(rig, center, ax: float = 0.0, ay: float = 0.0):
    """Monitor pose facing the cameras (normal along −z of the world) at ``center`` (world mm), turned by ax/ay deg."""
    R = rot_xy(ax, ay)
    pitch = rig.monitor.pixel_pitch_mm[0]
    res = rig.monitor.resolution
    c_local = np.array([(res[0] - 1) / 2 * pitch, (res[1] - 1) / 2 * pitch, 0.0])
    return R, np.asarray(center, dtype=np.float64) - R @ c_local


def render_view_stack(scene, camera, images, *, samples: int, seed: int) -> np.ndarray:
    """Render the monitor showing each of ``images`` (K, 1080, 1920) uint8: (K, H, W) uint8."""
    from dic.lab import render, screens_window

    window = screens_window(scene, camera)  # direct views: background pixels get one sample (same image)
    return np.stack([render(scene.with_monitor_image(im), camera, samples=samples, seed=seed + 7919 * k, window=window)
                     for k, im in enumerate(images)])


def target_pose(scene, camera):
    """True ``(R_cam_target, t_cam_target)`` of the monitor (target frame = screen frame) in ``camera``."""
    cam = scene.camera(camera)
    return (cam.R_cam_world @ scene.monitor.R_world_screen,
            cam.R_cam_world @ scene.monitor.t_world_screen + cam.t_cam_world)


def true_rig(rig) -> StereoRig:
    L, R = rig.camera("left"), rig.camera("right")
    R_rl = R.R_cam_world @ L.R_cam_world.T
    return StereoRig(L.camera, R.camera, R_rl, R.t_cam_world - R_rl @ L.t_cam_world)


@dataclass
class Cache:
    """Rendered stacks on disk (``.npy`` per view), keyed by a hash of what was rendered."""

    directory: str | None

    def get(self, key: str, make):
        if self.directory is None:
            return make()
        os.makedirs(self.directory, exist_ok=True)
        path = os.path.join(self.directory, hashlib.sha1(key.encode()).hexdigest()[:16] + ".npy")
        if os.path.exists(path):
            return np.load(path)
        arr = make()
        with atomic_output(path) as tmp:
            np.save(tmp, arr)
        return arr


class LabSession:
    """Renders the views of one calibration session of the paper rig (see the module docstring)."""

    def __init__(self, *, scale: float = 1.0, samples: int = 16, seed: int = 2019, cache: str | None = None,
                 tilts=MIRROR_TILTS, log=print):
        from dic.lab import paper_rig

        self.scale, self.samples, self.seed = scale, samples, seed
        self.rig = paper_rig(scale=scale, mirror_tilts_deg=tilts, mirror_tilt=None)
        self.tilts = tuple(tilts)
        self.cache = Cache(cache)
        self.log = log
        self._images = {}

    def _key(self, *parts) -> str:
        return repr((self.scale, self.samples, self.seed) + parts)

    def images(self, target: PhaseTarget):
        key = repr(target)
        if key not in self._images:
            self._images[key] = target.images()
        return self._images[key]

    def _render(self, scene, camera, target, tag, seed, samples=None):
        t0 = time.time()
        samples = self.samples if samples is None else int(samples)
        key = self._key(tag, camera, repr(target), target.code.tolist(), seed) + ("" if samples == self.samples else f" s{samples}")
        stack = self.cache.get(key, lambda: render_view_stack(scene, camera, self.images(target),
                                                               samples=samples, seed=seed))
        dt = time.time() - t0
        if dt > 5 and self.log:
            self.log(f"    rendered {tag} ({camera}, {target.grid[0]}x{target.grid[1]} dots) in {dt:.0f} s")
        return stack

    def direct_view(self, camera: str, target: PhaseTarget, pose_index: int, poses=DIRECT_POSES):
        base = self.rig.without_mirrors()
        R, t = direct_pose(base, camera, target, *poses[pose_index])
        scene = base.with_monitor_pose(R, t)
        seed = self.seed + 1000 * pose_index + (0 if camera == "left" else 500)
        return scene, self._render(scene, camera, target, f"direct{pose_index} {poses[pose_index]}", seed)

    def mirror_view(self, camera: str, target: PhaseTarget, tilt: int):
        scene = self.rig.with_mirror_tilt(tilt)
        seed = self.seed + 50000 + 100 * tilt + (0 if camera == "left" else 50)
        return scene, self._render(scene, camera, target, f"mirror{tilt} {self.tilts[tilt]}", seed)

    def common_view(self, target: PhaseTarget, center, ax=0.0, ay=0.0, tag="common", samples=None):
        """The monitor where both cameras see it (mirrors removed): ``(scene, (left stack, right stack))``."""
        R, t = common_pose(self.rig, center, ax, ay)
        scene = self.rig.without_mirrors().with_monitor_pose(R, t)
        seed = self.seed + 90000 + int(abs(hash((tuple(np.round(center, 3)), ax, ay))) % 10000)
        tag = f"{tag} {tuple(np.round(center, 3))} {ax} {ay}"
        return scene, (self._render(scene, "left", target, tag, seed, samples),
                       self._render(scene, "right", target, tag, seed + 1, samples))

    def mirror_truth(self, camera: str):
        scene = self.rig.with_mirror_tilt(0)
        return target_pose(scene, camera)


def export_session(out_dir: str, *, scale: float = 1.0, samples: int = 16, cache: str | None = None,
                   n_tilts: int = 3, log=print) -> str:
    """Write a calibration session of the lab as image folders, laid out like a real one (for the CLI
    walk-through of docs/calibration.md)::

        OUT/fringes/fringes.json                   the target file ('specula target fringes' writes it)
        OUT/left/intrinsics/pose01 ... pose12/     direct views, 4 phase-shifted TIFFs each
        OUT/left/mirror/tilt1 ... tiltK/           the monitor behind the cameras, seen in the mirror
        OUT/right/...                              the same for the right camera
        OUT/far/left, OUT/far/right                the monitor at the axes' crossing (both cameras)
        OUT/check1/left, OUT/check1/right          another common view, for checking
        OUT/ground_truth.json                      the lab's cameras and rig (for comparison only)

    Stacks come from the render cache when present (``cache``), else they are rendered.
    Every file is written whole or not at all (``kernels._atomic``); ``specula lab session`` holds the
    folder's lock meanwhile (:func:`dic.store.files.output_lock`)."""
    from kernels.images import write_image

    S = LabSession(scale=scale, samples=samples, cache=cache, log=log)
    tgt = paper_target()
    os.makedirs(os.path.join(out_dir, "fringes"), exist_ok=True)
    tgt.save_json(os.path.join(out_dir, "fringes", "fringes.json"))

    def write(folder, stack):
        os.makedirs(folder, exist_ok=True)
        for k, img in enumerate(stack):
            write_image(os.path.join(folder, f"img_{k}.tif"), img)

    for cam in ("left", "right"):
        for i in range(len(DIRECT_POSES)):
            write(os.path.join(out_dir, cam, "intrinsics", f"pose{i + 1:02d}"), S.direct_view(cam, tgt, i)[1])
        for k in range(n_tilts):
            write(os.path.join(out_dir, cam, "mirror", f"tilt{k + 1}"), S.mirror_view(cam, tgt, k)[1])
    _, (l, r) = S.common_view(tgt, S.rig.crossing_point, tag="far")
    write(os.path.join(out_dir, "far", "left"), l)
    write(os.path.join(out_dir, "far", "right"), r)
    _, (l, r) = S.common_view(tgt, (1000.0, 780.0, 4500.0), 0, 0, tag="check1")
    write(os.path.join(out_dir, "check1", "left"), l)
    write(os.path.join(out_dir, "check1", "right"), r)
    truth = true_rig(S.rig)
    R_l, t_l = S.mirror_truth("left")
    R_r, t_r = S.mirror_truth("right")
    with atomic_output(os.path.join(out_dir, "ground_truth.json")) as tmp, open(tmp, "w") as f:
        json.dump({"rig": truth.to_dict(), "R_left_target": R_l.tolist(), "t_left_target": t_l.tolist(),
                   "R_right_target": R_r.tolist(), "t_right_target": t_r.tolist()}, f, indent=1)
    return out_dir
