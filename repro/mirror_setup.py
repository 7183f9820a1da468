"""The exact geometry of the paper's mirror-assisted rig calibration, for Monte Carlo studies.

* :class:`MirrorSetup`, :func:`paper_mirror_setup`, :func:`simulate_mirror_observations` — the
  exact geometry of the mirror-assisted rig calibration of the paper behind Specula (Optics Express
  2019: two cameras 1.65 m apart converging at 5.4 m, a monitor behind the cameras, one mirror about
  0.4 m ahead of each camera tilted to K poses), with every parameter open, so that a planned setup
  (number of points, tilts, noise) can be evaluated before going to the lab; used by the tests and
  by the accuracy figures of docs/calibration.md (:mod:`repro.mirror_accuracy`).
* :func:`checkerboard_far_views` — views of a checkerboard that both cameras see, for comparing with
  ``cv2.stereoCalibrate``.
* :func:`grid_points` — a centred planar grid of points (the dot targets).

The paper's numbers (baseline, working distance, mirror distance, monitor place and pitch) are
those of the virtual lab's paper rig, :mod:`dic.lab.paper`, defined there once. Moved here from
``calibration/uncertainty.py``, which keeps the generic covariance tools.

Conventions: docs/conventions.md (mm, camera frame x right / y down / z forward, ``R_a_b``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.camera import Camera, rotation_from_vector, transform_points
from dic.lab.paper import (
    BASELINE_MM,
    IMAGE_SIZE_PX,
    MIRROR_DISTANCE_MM,
    MONITOR_BEHIND_MM,
    MONITOR_PITCH_MM,
    WORKING_DISTANCE_MM,
)

#: The paper's calibration target: 6 × 3 dots, one per 300 monitor px cell (93.3 mm).
PAPER_DOT_GRID = (6, 3)
PAPER_DOT_PITCH_MM = 300 * MONITOR_PITCH_MM

__all__ = ["MirrorSetup", "PAPER_DOT_GRID", "PAPER_DOT_PITCH_MM", "checkerboard_far_views", "grid_points",
           "paper_mirror_setup", "simulate_mirror_observations"]


def _look_at(center, target) -> np.ndarray:
    """R_cam_world of a camera at ``center`` looking at ``target`` (x right, y down, world y down)."""
    z = np.asarray(target, float) - np.asarray(center, float)
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def grid_points(cols: int, rows: int, pitch: float) -> np.ndarray:
    """(cols·rows, 3) points of a centred planar grid (z = 0), row-major from the top-left, mm."""
    gx, gy = np.meshgrid((np.arange(cols) - (cols - 1) / 2) * pitch, (np.arange(rows) - (rows - 1) / 2) * pitch)
    return np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)


@dataclass
class MirrorSetup:
    """Exact geometry of a mirror-assisted stereo calibration (all poses in the world frame W).

    W: midpoint between the cameras, x right, y down, z toward the scene (mm).
    """

    left: Camera
    right: Camera
    R_left_world: np.ndarray
    t_left_world: np.ndarray
    R_right_world: np.ndarray
    t_right_world: np.ndarray
    object_points: np.ndarray            # (N, 3) target frame, mm
    R_world_target: np.ndarray           # monitor behind the cameras (mirror views)
    t_world_target: np.ndarray
    mirrors_left: list                   # [(n (3,), d)] planes in the LEFT camera frame
    mirrors_right: list                  # planes in the RIGHT camera frame
    far_object_points: np.ndarray        # (M, 3) target seen directly by both cameras
    R_world_far: np.ndarray
    t_world_far: np.ndarray
    notes: dict = field(default_factory=dict)

    # truth, in the conventions of the results
    def pose_cam_target(self, which: str):
        Rc, tc = (self.R_left_world, self.t_left_world) if which == "left" else (self.R_right_world, self.t_right_world)
        return Rc @ self.R_world_target, Rc @ self.t_world_target + tc

    @property
    def R_right_left(self):
        return self.R_right_world @ self.R_left_world.T

    @property
    def t_right_left(self):
        return self.t_right_world - self.R_right_left @ self.t_left_world


def _reflect(points, n, d):
    return points - 2.0 * (points @ n + d)[:, None] * n[None, :]


def paper_mirror_setup(*, grid=PAPER_DOT_GRID, pitch: float = PAPER_DOT_PITCH_MM, n_tilts: int = 3,
                       tilt_deg: float = 3.0, baseline: float = BASELINE_MM,
                       working_distance: float = WORKING_DISTANCE_MM, mirror_distance: float = MIRROR_DISTANCE_MM,
                       target_behind: float = MONITOR_BEHIND_MM, focal_px: float = 4050.0, size=IMAGE_SIZE_PX,
                       far_grid=None, far_pitch=None) -> MirrorSetup:
    """The paper's rig (Optics Express 2019, Section 2 and Fig. 7) as an exact geometry.

    Two cameras (``focal_px`` ≈ 30 mm lens on 7.4 µm pixels, ``size`` px, mild distortion)
    ``baseline`` mm apart, axes crossing at ``working_distance``; a monitor centred ``target_behind``
    mm behind the cameras facing the scene shows a ``grid`` of dots at ``pitch`` mm; one mirror per
    camera, ``mirror_distance`` mm along its axis, its nominal normal bisecting the directions to the
    camera and to the monitor, tilted about its centre to ``n_tilts`` poses spread on a cone of
    half-angle ``tilt_deg`` (n_tilts ≥ 3, non-coplanar normals). The far view is the same monitor at
    the axes' crossing point facing the cameras (grid ``far_grid`` at ``far_pitch``, default the
    mirror grid).
    """
    left = Camera(K=[[focal_px, 0, size[0] / 2 - 3.2], [0, focal_px * 1.0002, size[1] / 2 + 4.1], [0, 0, 1]],
                  dist=[-0.06, 0.09, 2e-4, -1e-4, 0.0], size=size, name="left")
    right = Camera(K=[[focal_px * 0.998, 0, size[0] / 2 + 5.5], [0, focal_px * 0.9981, size[1] / 2 - 2.7], [0, 0, 1]],
                   dist=[-0.055, 0.08, -1e-4, 2e-4, 0.0], size=size, name="right")
    cross = np.array([0.0, 0.0, working_distance])
    C = {"left": np.array([-baseline / 2, 0.0, 0.0]), "right": np.array([baseline / 2, 0.0, 0.0])}
    R_cw = {k: _look_at(c, cross) for k, c in C.items()}
    t_cw = {k: -R_cw[k] @ C[k] for k in C}
    X = grid_points(grid[0], grid[1], pitch)
    # monitor behind the cameras, facing +z (toward the mirrors); target x to the viewer's right
    R_wt = np.array([[-1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]])
    T = np.array([0.0, 0.0, -target_behind])
    mirrors = {}
    for k in ("left", "right"):
        axis = R_cw[k][2]
        M = C[k] + mirror_distance * axis
        to_cam = (C[k] - M) / np.linalg.norm(C[k] - M)
        to_mon = (T - M) / np.linalg.norm(T - M)
        n0 = to_cam + to_mon
        n0 /= np.linalg.norm(n0)
        u = np.cross(n0, [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(n0, u)
        planes = []
        for j in range(n_tilts):
            phi = 2 * np.pi * j / n_tilts + 0.3
            tilt = np.radians(tilt_deg)
            n = np.cos(tilt) * n0 + np.sin(tilt) * (np.cos(phi) * u + np.sin(phi) * v)
            n /= np.linalg.norm(n)
            # plane through M in world, then into the camera frame: n_c = R n, d_c = d - n_c·t
            d_w = -n @ M
            n_c = R_cw[k] @ n
            d_c = d_w - n_c @ t_cw[k]
            if d_c < 0:
                n_c, d_c = -n_c, -d_c
            planes.append((n_c, float(d_c)))
        mirrors[k] = planes
    Xf = X if far_grid is None else grid_points(far_grid[0], far_grid[1], far_pitch or pitch)
    return MirrorSetup(left=left, right=right, R_left_world=R_cw["left"], t_left_world=t_cw["left"],
                       R_right_world=R_cw["right"], t_right_world=t_cw["right"], object_points=X,
                       R_world_target=R_wt, t_world_target=T, mirrors_left=mirrors["left"],
                       mirrors_right=mirrors["right"], far_object_points=Xf, R_world_far=np.eye(3),
                       t_world_far=cross.copy(),
                       notes={"grid": grid, "pitch": pitch, "n_tilts": n_tilts, "tilt_deg": tilt_deg})


def simulate_mirror_observations(setup: MirrorSetup, noise_px: float, rng) -> dict:
    """Image points of the exact setup plus Gaussian noise (σ = ``noise_px`` per coordinate).

    Returns a dict with ``left_mirrored`` / ``right_mirrored`` (lists of (N, 2), rows aligned with
    ``setup.object_points``), ``far_left`` / ``far_right`` ((M, 2), rows aligned with
    ``setup.far_object_points``). Raises ``ValueError`` if a point falls outside an image.
    """
    out = {}
    for k, cam, planes in (("left", setup.left, setup.mirrors_left), ("right", setup.right, setup.mirrors_right)):
        R, t = setup.pose_cam_target(k)
        P = transform_points(R, t, setup.object_points)
        views = []
        for n, d in planes:
            q = cam.project(_reflect(P, np.asarray(n), d))
            _check_inside(q, cam, f"{k} mirrored view")
            views.append(q + rng.normal(0.0, noise_px, q.shape))
        out[f"{k}_mirrored"] = views
        Rc, tc = (setup.R_left_world, setup.t_left_world) if k == "left" else (setup.R_right_world, setup.t_right_world)
        Pf = transform_points(Rc @ setup.R_world_far, Rc @ setup.t_world_far + tc, setup.far_object_points)
        qf = cam.project(Pf)
        _check_inside(qf, cam, f"{k} far view")
        out[f"far_{k}"] = qf + rng.normal(0.0, noise_px, qf.shape)
    return out


def _check_inside(q, cam, what):
    w, h = cam.size
    if np.any(q < -0.5) or np.any(q[:, 0] > w - 0.5) or np.any(q[:, 1] > h - 0.5):
        raise ValueError(f"{what}: points fall outside the {w}x{h} image; change the synthetic setup")


def checkerboard_far_views(setup: MirrorSetup, *, n_views: int = 15, inner=(9, 6), square: float = 40.0,
                           max_tilt_deg: float = 30.0, spread: float = 0.3, noise_px: float = 0.03, rng=None):
    """Views of a checkerboard (``inner`` corners, ``square`` mm) seen by both cameras of ``setup``.

    The board is placed around the axes' crossing point (±``spread`` of the common field laterally,
    ±10 % in depth) with random tilts up to ``max_tilt_deg``. Returns ``(object_points, left_points,
    right_points)``, lists of (54, 3) / (54, 2) arrays, with Gaussian noise ``noise_px``.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    X = grid_points(inner[0], inner[1], square)
    objs, ql, qr = [], [], []
    wd = setup.t_world_far[2]
    half_w = wd * setup.left.size[0] / (2 * setup.left.fx)
    while len(objs) < n_views:
        ang = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 3))
        ang[2] = np.radians(rng.uniform(-15, 15))
        R_wb = rotation_from_vector(ang)
        t_wb = np.array([rng.uniform(-spread, spread) * half_w, rng.uniform(-spread, spread) * half_w * 0.7,
                         wd * rng.uniform(0.9, 1.1)])
        pts = []
        ok = True
        for cam, Rc, tc in ((setup.left, setup.R_left_world, setup.t_left_world),
                            (setup.right, setup.R_right_world, setup.t_right_world)):
            q = cam.project(transform_points(Rc @ R_wb, Rc @ t_wb + tc, X))
            w, h = cam.size
            if np.any(q < 0) or np.any(q[:, 0] > w - 1) or np.any(q[:, 1] > h - 1):
                ok = False
            pts.append(q + rng.normal(0.0, noise_px, q.shape))
        if ok:
            objs.append(X.copy())
            ql.append(pts[0])
            qr.append(pts[1])
    return objs, ql, qr
