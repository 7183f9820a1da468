"""Uncertainty of calibration results, and exact synthetic setups to predict it.

* :func:`covariance_from_jacobian` — Gauss–Newton covariance ``σ² (JᵀJ)⁻¹`` of a least-squares
  estimate, with ``σ²`` the residual variance (or a given image noise).
* :func:`propagate` — first-order propagation of a covariance through a function (numerical Jacobian).
* :class:`MirrorSetup`, :func:`paper_mirror_setup`, :func:`simulate_mirror_observations` — the
  exact geometry of the mirror-assisted rig calibration of the paper behind Specula (Optics Express
  2019: two cameras 1.65 m apart converging at 5.4 m, a monitor behind the cameras, one mirror about
  0.4 m ahead of each camera tilted to K poses), with every parameter open, so that a planned setup
  (number of points, tilts, noise) can be evaluated before going to the lab; used by the tests and
  by the accuracy figures of docs/calibration.md.
* :func:`checkerboard_far_views` — views of a checkerboard that both cameras see, for comparing with
  ``cv2.stereoCalibrate``.

Conventions: docs/conventions.md (mm, camera frame x right / y down / z forward, ``R_a_b``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .camera import Camera, rotation_angle_deg, rotation_from_vector, transform_points, vector_from_rotation


# -- covariance ----------------------------------------------------------------------------------
def covariance_from_jacobian(jac, residuals, sigma: float | None = None) -> np.ndarray:
    """Covariance of a least-squares estimate from its Jacobian at the solution.

    jac : (m, p) float64, residuals : (m,) float64. ``sigma`` is the standard deviation of one
    residual; when None it is estimated as ``sqrt(Σr² / (m − p))``. Raises ``ValueError`` when
    ``JᵀJ`` is singular (a parameter is not determined by the data).
    """
    J = np.asarray(jac, dtype=np.float64)
    r = np.asarray(residuals, dtype=np.float64).ravel()
    m, p = J.shape
    if r.size != m:
        raise ValueError(f"jacobian has {m} rows but there are {r.size} residuals")
    if m <= p:
        raise ValueError(f"{m} residuals cannot determine the covariance of {p} parameters")
    if sigma is None:
        s2 = float(r @ r) / (m - p)
    else:
        s2 = float(sigma) ** 2
    # scale columns for conditioning, invert, unscale
    scale = np.sqrt(np.sum(J * J, axis=0))
    if np.any(scale == 0):
        bad = np.flatnonzero(scale == 0).tolist()
        raise ValueError(f"parameters {bad} do not influence any residual; they are not determined")
    Js = J / scale
    JtJ = Js.T @ Js
    w, V = np.linalg.eigh(JtJ)
    if not np.all(np.isfinite(w)) or w[0] <= 1e-14 * w[-1]:
        raise ValueError(f"the normal matrix is singular (condition number {w[-1] / max(w[0], 1e-300):.3g}); "
                         "some parameters are not determined by the data")
    inv = (V / w) @ V.T
    return s2 * inv / np.outer(scale, scale)


def propagate(func, x0, cov, step: float = 1e-7) -> np.ndarray:
    """First-order propagation ``J cov Jᵀ`` of ``cov`` through ``func`` (central differences).

    func : callable (p,) -> (q,); x0 : (p,); cov : (p, p). ``step`` is relative to ``max(1, |x|)``.
    """
    x0 = np.asarray(x0, dtype=np.float64).ravel()
    f0 = np.asarray(func(x0), dtype=np.float64).ravel()
    J = np.empty((f0.size, x0.size))
    for k in range(x0.size):
        h = step * max(1.0, abs(x0[k]))
        xp, xm = x0.copy(), x0.copy()
        xp[k] += h
        xm[k] -= h
        J[:, k] = (np.asarray(func(xp)).ravel() - np.asarray(func(xm)).ravel()) / (2 * h)
    return J @ np.asarray(cov, dtype=np.float64) @ J.T


# -- synthetic geometry --------------------------------------------------------------------------
def rig_covariance_from_intrinsics(solve, left: Camera, right: Camera, R_right_left, t_right_left) -> np.ndarray:
    """6×6 covariance of a rig ``[δρ (rad), δt (mm)]`` due to the uncertainty of both cameras' intrinsics.

    ``solve(left_camera, right_camera) -> (R_right_left, t_right_left)`` re-computes the rig from
    the same observations with other intrinsics (e.g. the joint mirror adjustment). Each camera's
    intrinsics are moved by ±1 σ along every principal axis of its ``covariance`` and the rig is
    re-solved: the central differences ``d_k`` give ``Σ_k d_k d_kᵀ`` (first-order propagation,
    ``J C Jᵀ``, without forming J; 4 × P solves for P intrinsics per camera). The two cameras'
    intrinsics are taken as independent of each other and of the rig's own observation noise (the
    extrinsic covariance, added by the caller). A camera without a covariance is taken as exact.
    Why: a principal-point error δ rotates a camera by δ / f, which no extrinsic view can see; the
    rig adjustments hold intrinsics fixed, so without this term their rotation σ is a lower bound.

    Raises ``ValueError`` when neither camera has a covariance.
    """
    if not callable(solve):
        raise ValueError("solve must be a function (left_camera, right_camera) -> (R_right_left, t_right_left)")
    for nm, cam in (("left", left), ("right", right)):
        if not isinstance(cam, Camera):
            raise ValueError(f"{nm} must be a calibration.camera.Camera, got {type(cam).__name__}")
    R0 = np.asarray(R_right_left, dtype=np.float64)
    t0 = np.asarray(t_right_left, dtype=np.float64).ravel()
    if R0.shape != (3, 3) or t0.shape != (3,) or not (np.all(np.isfinite(R0)) and np.all(np.isfinite(t0))):
        raise ValueError(f"R_right_left must be a finite 3x3 rotation and t_right_left a finite 3-vector, got shapes "
                         f"{np.shape(R_right_left)} and {np.shape(t_right_left)}")
    C = np.zeros((6, 6))
    if left.covariance is None and right.covariance is None:
        raise ValueError("neither camera carries an intrinsic covariance (calibrate them with "
                         "calibration.calibrate_intrinsics, or load camera files that have one)")
    for side, cam in (("left", left), ("right", right)):
        if cam.covariance is None:
            continue
        names = cam.covariance_names
        values = np.array([cam.parameter(n) for n in names])
        lam, E = np.linalg.eigh(cam.covariance)
        for k in np.flatnonzero(lam > 1e-12 * max(lam.max(), 1e-300)):
            step = np.sqrt(lam[k]) * E[:, k]
            out = []
            for sgn in (1.0, -1.0):
                moved = cam.with_parameters(**dict(zip(names, values + sgn * step)))
                pair = (moved, right) if side == "left" else (left, moved)
                R, t = solve(*pair)
                out.append(np.concatenate([vector_from_rotation(np.asarray(R) @ R0.T), np.asarray(t) - t0]))
            d = 0.5 * (out[0] - out[1])
            C += np.outer(d, d)
    return 0.5 * (C + C.T)


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


def paper_mirror_setup(*, grid=(6, 3), pitch: float = 93.3, n_tilts: int = 3, tilt_deg: float = 3.0,
                       baseline: float = 1650.0, working_distance: float = 5400.0, mirror_distance: float = 400.0,
                       target_behind: float = 650.0, focal_px: float = 4050.0, size=(2352, 1728),
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


# -- accuracy study (python -m calibration.uncertainty) -------------------------------------------
def accuracy_study(draws: int = 30, noise_px: float = 0.03, seed: int = 2019, configs=None) -> list[dict]:
    """Monte Carlo comparison of rig calibrations on the exact paper geometry (docs/calibration.md).

    For each configuration and noise draw: calibrate, compare with the true rig (rotation error,
    baseline error, translation error) and reconstruct an independent far view of the 6×3-dot
    target (neighbour-distance error). Intrinsics are exact in every configuration, so the figures
    isolate the extrinsic calibration. Returns one dict of RMS figures per configuration.
    """
    from .mirror import joint_mirror_stereo, mirror_closed_form, mirror_extrinsics
    from .stereo import StereoRig, reconstruct_target, rig_from_mirror, stereo_calibrate

    if configs is None:
        configs = [
            ("paper: 6x3 dots, 3 tilts of 3 deg, closed form", dict(), "closed"),
            ("paper: 6x3 dots, 3 tilts of 3 deg, closed form + BA per camera", dict(), "mirror"),
            ("paper + joint BA with the far view", dict(), "joint"),
            ("24x12 dots, 5 tilts of 3 deg, BA per camera", dict(grid=(24, 12), pitch=93.3 / 4, n_tilts=5), "mirror"),
            ("24x12 dots, 5 tilts of 3 deg, joint BA + far view",
             dict(grid=(24, 12), pitch=93.3 / 4, n_tilts=5), "joint"),
            ("48x24 dots, 5 tilts of 4 deg, joint BA + far view",
             dict(grid=(48, 24), pitch=93.3 / 8, n_tilts=5, tilt_deg=4.0), "joint"),
            ("cv2.stereoCalibrate, 15 views of a 9x6 checkerboard (40 mm) at 5.4 m", dict(), "checkerboard"),
            ("same, intrinsics refined from the same 15 views (started at the truth)", dict(), "checkerboard_free"),
        ]
    rng = np.random.default_rng(seed)
    rows = []
    for label, kw, method in configs:
        setup = paper_mirror_setup(**kw)
        check = paper_mirror_setup()  # independent far view: 6x3 dots at 5.4 m, shifted and turned
        check.R_world_far = rotation_from_vector(np.radians([8.0, -15.0, 3.0]))
        check.t_world_far = np.array([180.0, -120.0, 5200.0])
        truth = StereoRig(setup.left, setup.right, setup.R_right_left, setup.t_right_left)
        errs = []
        for _ in range(draws):
            obs = simulate_mirror_observations(setup, noise_px, rng)
            if method.startswith("checkerboard"):
                objs, ql, qr = checkerboard_far_views(setup, noise_px=noise_px, rng=rng)
                rig = stereo_calibrate(setup.left, setup.right, objs, ql, qr,
                                       fix_intrinsics=(method == "checkerboard")).rig
                pose_err = (np.nan, np.nan)
            else:
                X = setup.object_points
                if method == "closed":
                    L = mirror_closed_form(setup.left, obs["left_mirrored"], X)
                    R = mirror_closed_form(setup.right, obs["right_mirrored"], X)
                    rig = rig_from_mirror(L, R, setup.left, setup.right)
                    est = L
                else:
                    L = mirror_extrinsics(setup.left, obs["left_mirrored"], X)
                    R = mirror_extrinsics(setup.right, obs["right_mirrored"], X)
                    est = L
                    if method == "mirror":
                        rig = rig_from_mirror(L, R)
                    else:
                        far = [(setup.far_object_points, obs["far_left"], obs["far_right"])]
                        rig = joint_mirror_stereo(setup.left, setup.right, obs["left_mirrored"], obs["right_mirrored"],
                                                  X, far_views=far, left_result=L, right_result=R).rig
                R_true, t_true = setup.pose_cam_target("left")
                pose_err = (rotation_angle_deg(est.R_cam_target, R_true), float(np.linalg.norm(est.t_cam_target - t_true)))
            e = rig.errors_to(truth)
            cobs = simulate_mirror_observations(check, noise_px, rng)
            rec = reconstruct_target(rig, cobs["far_left"], cobs["far_right"], check.far_object_points)
            sb = rig.std_baseline_mm if rig.covariance is not None else np.nan
            sr = float(np.degrees(np.sqrt(np.trace(rig.covariance[:3, :3])))) if rig.covariance is not None else np.nan
            errs.append([e["rotation_deg"], e["baseline_percent"], e["translation_mm"], *pose_err,
                         100 * sb / truth.baseline, sr, np.mean(rec.neighbour_errors), rec.mean_relative_error * 100])
        a = np.asarray(errs)
        def rms(v):
            return float(np.sqrt(np.mean(v[np.isfinite(v)] ** 2))) if np.any(np.isfinite(v)) else float("nan")

        def mean(v):
            return float(np.mean(v[np.isfinite(v)])) if np.any(np.isfinite(v)) else float("nan")

        rows.append({"config": label, "draws": draws, "rig_rotation_deg": rms(a[:, 0]), "baseline_percent": rms(a[:, 1]),
                     "rig_translation_mm": rms(a[:, 2]), "left_pose_rotation_deg": rms(a[:, 3]),
                     "left_pose_translation_mm": rms(a[:, 4]), "reported_sigma_baseline_percent": mean(a[:, 5]),
                     "reported_sigma_rotation_deg": mean(a[:, 6]),
                     "check_neighbour_error_mm": rms(a[:, 7]), "check_scale_error_percent": rms(a[:, 8]),
                     "max_rig_rotation_deg": float(np.max(a[:, 0])), "max_baseline_percent": float(np.max(np.abs(a[:, 1])))})
    return rows


def _main(argv=None):  # pragma: no cover - documentation tool
    import argparse
    import json
    import time

    ap = argparse.ArgumentParser(description="Monte Carlo accuracy of mirror vs checkerboard rig calibration")
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--noise", type=float, default=0.03)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    t0 = time.time()
    rows = accuracy_study(args.draws, args.noise)
    print("| configuration | rig rotation error (deg, RMS) | baseline error (%, RMS) | rig translation error (mm, RMS) "
          "| left pose rot. (deg) / transl. (mm) | reported σ baseline (%) | check: neighbour error (mm, RMS) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['config']} | {r['rig_rotation_deg']:.4f} | {r['baseline_percent']:.4f} | {r['rig_translation_mm']:.3f} "
              f"| {r['left_pose_rotation_deg']:.4f} / {r['left_pose_translation_mm']:.2f} "
              f"| {r['reported_sigma_baseline_percent']:.4f} | {r['check_neighbour_error_mm']:.4f} |")
    print(f"({args.draws} draws per configuration, noise {args.noise} px, {time.time() - t0:.0f} s)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"noise_px": args.noise, "rows": rows}, f, indent=2)


if __name__ == "__main__":  # pragma: no cover
    _main()
