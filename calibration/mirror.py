"""Mirror-based extrinsic calibration: the pose of a camera relative to a target it only sees in a mirror.

Method (the paper behind Specula — "Stereo-camera calibration for large-scale DIC measurements
with active phase targets and planar mirrors", Optics Express 2019, Eqs. (1)–(6) — which follows
Takahashi, Nobuhara, Matsuyama, "A new mirror-based extrinsic camera calibration using an
orthogonality constraint", CVPR 2012, doi:10.1109/CVPR.2012.6247854):

1. Each mirrored view j is a view of the *virtual* (reflected, left-handed) target. PnP with the
   flipped object points (x → −x, see :mod:`calibration.intrinsics`) gives the virtual points
   ``p'_ji`` in the camera frame.
2. For mirror poses j, k the differences ``p'_ji − p'_ki`` are orthogonal to the axis
   ``m_jk = n_j × n_k`` (Eq. 3). ``m_jk`` is the eigenvector of the smallest eigenvalue of
   ``M_jk = Q_jkᵀ Q_jk`` (Eq. 5), ``Q_jk`` stacking the differences of *all* points (the
   least-squares form of the paper's search over point triples).
3. Each normal ``n_j`` is orthogonal to every axis ``m_jk`` (Eq. 6: ``n_1 ∝ m_12 × m_31``; for
   K > 3 poses, the smallest eigenvector of ``Σ_k m_jk m_jkᵀ``).
4. The real point ``p_i`` is the least-squares intersection of the lines through ``p'_ji`` along
   ``n_j``; a rigid fit (Kabsch) of the target points onto them gives ``R_cam_target, t_cam_target``
   (Eq. 1), and each mirror distance is ``d_j = −n_j·(p_i + p'_ji)/2`` averaged over i.
5. Bundle adjustment (``scipy.optimize.least_squares``) over the camera–target pose and all mirror
   planes, minimising the reprojection error of the mirrored points: reflect the true target
   points in each mirror (Householder, Eq. 2: ``x' = x − 2(n·x + d) n``) and project them with
   the camera, distortion included. Its Jacobian gives the covariance of the pose.

:func:`joint_mirror_stereo` adjusts both cameras at once, with the rig pose as a parameter, the
mirror views of both cameras (the target stays put) and optionally views of a target that both
cameras see directly (the paper's "last frame").

Planes: ``n·x + d = 0`` in the camera frame, ``|n| = 1``, ``d > 0`` (the normal points to the
camera's side). Poses: docs/conventions.md.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bundle import RigBundle
from .camera import Camera, nearest_rotation, rigid_fit, rotation_angle_deg, rotation_from_vector, transform_points
from .intrinsics import MIRROR_FLIP
from .stereo import StereoRig

#: Smallest angle (deg) allowed between the mirror axes m_jk that define one normal.
MIN_AXIS_ANGLE_DEG = 3.0
#: Smallest rotation (deg) between two virtual targets (twice the mirror tilt between two poses).
MIN_VIRTUAL_ROTATION_DEG = 0.5
#: Fewest points a mirror pose must show (its virtual target pose comes from a PnP on them).
MIN_POINTS_PER_VIEW = 4


@dataclass
class MirrorPlane:
    """A plane ``normal · x + d = 0`` (camera frame, mm), ``|normal| = 1``, ``d > 0``."""

    normal: np.ndarray
    d: float

    def __post_init__(self):
        n = np.asarray(self.normal, dtype=np.float64).ravel()
        if n.shape != (3,) or not np.all(np.isfinite(n)) or not np.isfinite(self.d):
            raise ValueError(f"MirrorPlane needs a finite 3-vector normal and a finite d, got {self.normal!r}, {self.d!r}")
        norm = np.linalg.norm(n)
        if norm == 0:
            raise ValueError("MirrorPlane normal must not be zero")
        n = n / norm
        d = float(self.d) / norm
        if d < 0:
            n, d = -n, -d
        self.normal, self.d = n, d

    def reflect(self, points) -> np.ndarray:
        """Householder reflection ``x − 2(n·x + d) n`` of points (N, 3)."""
        p = np.asarray(points, dtype=np.float64)
        return p - 2.0 * (p @ self.normal + self.d)[:, None] * self.normal[None, :]

    def angle_deg(self, other: "MirrorPlane") -> float:
        return float(np.degrees(np.arccos(np.clip(abs(self.normal @ other.normal), -1.0, 1.0))))


@dataclass
class MirrorClosedForm:
    """The closed-form solution (steps 1–4 of the module docstring), before bundle adjustment."""

    R_cam_target: np.ndarray
    t_cam_target: np.ndarray
    mirrors: list
    axes: dict                       # (j, k) -> unit axis m_jk
    virtual_poses: list              # (R', t') per mirror view, proper rotation of the flipped target
    points_cam: np.ndarray           # (N, 3) least-squares line intersections
    axis_angles_deg: np.ndarray      # per normal: angle between its defining axes (conditioning)


@dataclass
class MirrorExtrinsicsResult:
    """Result of :func:`mirror_extrinsics` (mm, rad, camera frame).

    ``pose_covariance`` is 6×6 for ``[δω (rad), δt (mm)]`` with ``R = exp([δω]×) R_cam_target``;
    ``covariance`` covers all parameters ``[δω, δt, (a_j, b_j, d_j) per mirror]`` (normal
    perturbation in the plane's tangent basis, rad; d in mm). ``rms`` and ``per_mirror_rms`` are
    reprojection RMS (px) of the image points, ``sqrt(mean |q_obs − q_proj|²)``.
    """

    R_cam_target: np.ndarray
    t_cam_target: np.ndarray
    mirrors: list
    closed_form: MirrorClosedForm
    rms: float
    per_mirror_rms: np.ndarray
    closed_form_rms: float
    residuals: list
    pose_covariance: np.ndarray
    covariance: np.ndarray
    camera: Camera
    n_points: int = 0

    @property
    def std_rotation_deg(self) -> np.ndarray:
        return np.degrees(np.sqrt(np.diag(self.pose_covariance)[:3]))

    @property
    def std_translation_mm(self) -> np.ndarray:
        return np.sqrt(np.diag(self.pose_covariance)[3:])

    def report(self) -> str:
        t = self.t_cam_target
        lines = [f"mirror extrinsics: {len(self.mirrors)} mirror poses x {self.n_points} points, "
                 f"RMS {self.rms:.4f} px (closed form {self.closed_form_rms:.4f} px)",
                 f"  t_cam_target = {np.array2string(t, precision=3)} mm ± {np.array2string(self.std_translation_mm, precision=3)}",
                 f"  rotation σ = {np.array2string(self.std_rotation_deg, precision=4)} deg",
                 f"  camera–target distance {np.linalg.norm(t):.1f} mm"]
        for j, (m, rms) in enumerate(zip(self.mirrors, self.per_mirror_rms)):
            lines.append(f"  mirror {j}: n = {np.array2string(m.normal, precision=5)}, d = {m.d:.2f} mm, RMS {rms:.4f} px")
        return "\n".join(lines)


# -- validation ------------------------------------------------------------------------------------
def _validate(camera, mirrored_points, object_points, what="mirrored_points"):
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a calibration.camera.Camera, got {type(camera).__name__}")
    X = np.asarray(object_points, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"object_points must have shape (N, 3) in mm (target frame), got {X.shape}")
    if not np.all(np.isfinite(X)):
        raise ValueError("object_points contains NaN or infinite values")
    if X.shape[0] < 4:
        raise ValueError(f"mirror calibration needs at least 4 target points per view, got {X.shape[0]}")
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if s[1] < 1e-3 * s[0]:
        raise ValueError("object_points are (nearly) collinear: the pose about their line is undetermined; "
                         "use a target whose points span two dimensions (a grid, not a row of dots)")
    if isinstance(mirrored_points, np.ndarray) and mirrored_points.ndim == 3:
        mirrored_points = list(mirrored_points)
    if not isinstance(mirrored_points, (list, tuple)):
        raise ValueError(f"{what} must be a list of K (N, 2) arrays (or a (K, N, 2) array), one per mirror pose")
    if len(mirrored_points) < 3:
        raise ValueError(f"{what}: mirror calibration needs at least 3 mirror poses, got {len(mirrored_points)}; "
                         "tilt the mirror to 3 or more orientations about two different axes")
    views = []
    for j, q in enumerate(mirrored_points):
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (X.shape[0], 2):
            raise ValueError(f"{what}[{j}] must have shape ({X.shape[0]}, 2) (rows aligned with object_points), got {q.shape}")
        if np.any(np.isinf(q)) or np.any(np.isnan(q[:, 0]) != np.isnan(q[:, 1])):
            raise ValueError(f"{what}[{j}] contains infinite values or rows with one NaN coordinate; mark a point "
                             "not seen in a view by a row of two NaN")
        n_seen = int(np.isfinite(q[:, 0]).sum())
        if n_seen < MIN_POINTS_PER_VIEW:
            raise ValueError(f"{what}[{j}] has only {n_seen} points (NaN rows are not seen); every mirror pose needs "
                             f"at least {MIN_POINTS_PER_VIEW}: keep more of the target inside the mirror")
        views.append(q)
    return views, X


# -- closed form -----------------------------------------------------------------------------------
def _pnp(camera: Camera, obj, img):
    import cv2

    dist = camera.dist if camera.dist.size else np.zeros(5)
    planar = np.linalg.svd(obj - obj.mean(axis=0), compute_uv=False)[2] < 1e-9 * max(1.0, np.abs(obj).max())
    method = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_SQPNP
    ok, rvec, tvec = cv2.solvePnP(obj.reshape(-1, 1, 3), img.reshape(-1, 1, 2), camera.K, dist, flags=method)
    if not ok:
        raise ValueError("PnP failed for a view; check that image points and object points correspond")
    rvec, tvec = cv2.solvePnPRefineLM(obj.reshape(-1, 1, 3), img.reshape(-1, 1, 2), camera.K, dist, rvec, tvec,
                                      criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-14))
    return rotation_from_vector(np.asarray(rvec).ravel()), np.asarray(tvec, dtype=np.float64).ravel()


def mirror_closed_form(camera: Camera, mirrored_points, object_points) -> MirrorClosedForm:
    """Closed-form pose of the camera relative to a target seen in K ≥ 3 mirror poses (steps 1–4).

    Same inputs as :func:`mirror_extrinsics`. Raises ``ValueError`` for degenerate setups (fewer
    than 3 poses, nearly identical mirror poses, mirror tilted about one axis only, collinear points).
    """
    views, X = _validate(camera, mirrored_points, object_points)
    K = len(views)
    Xf = X @ MIRROR_FLIP.T
    virt_poses, virt = [], []
    for q in views:
        seen = np.isfinite(q[:, 0])
        R, t = _pnp(camera, Xf[seen], q[seen])
        virt_poses.append((R, t))
        virt.append(transform_points(R, t, Xf))
    for j in range(K):
        for k in range(j + 1, K):
            ang = rotation_angle_deg(virt_poses[j][0], virt_poses[k][0])
            if ang < MIN_VIRTUAL_ROTATION_DEG:
                raise ValueError(
                    f"mirror poses {j} and {k} are nearly the same (virtual targets rotated by only {ang:.3f} deg, "
                    f"need ≥ {MIN_VIRTUAL_ROTATION_DEG} deg): tilt the mirror by at least a degree between poses")
    axes = {}
    for j in range(K):
        for k in range(j + 1, K):
            Q = virt[j] - virt[k]
            w, V = np.linalg.eigh(Q.T @ Q)
            axes[(j, k)] = axes[(k, j)] = V[:, 0]
    centroid = np.mean([v.mean(axis=0) for v in virt], axis=0)
    normals, axis_angles = [], []
    for j in range(K):
        A = sum(np.outer(axes[(j, k)], axes[(j, k)]) for k in range(K) if k != j)
        w, V = np.linalg.eigh(A)
        # two unit axes at angle φ give eigenvalues 1 ± cos φ: φ = 2 atan(sqrt(λ_mid / λ_max))
        phi = np.degrees(2 * np.arctan(np.sqrt(max(w[1], 0.0) / w[2])))
        axis_angles.append(phi)
        if phi < MIN_AXIS_ANGLE_DEG:
            raise ValueError(
                f"the mirror axes m_jk defining the normal of pose {j} are nearly parallel ({phi:.2f} deg apart, "
                f"need ≥ {MIN_AXIS_ANGLE_DEG} deg): the mirror was tilted about a single axis; tilt it about two "
                "different axes (e.g. once about the horizontal, once about the vertical)")
        n = V[:, 0]
        if n @ centroid > 0:  # the normal faces the camera, the virtual target lies behind the mirror
            n = -n
        normals.append(n)
    # least-squares intersection of the lines through p'_ji along n_j
    projs = [np.eye(3) - np.outer(n, n) for n in normals]
    A = sum(projs)
    b = sum(virt[j] @ projs[j].T for j in range(K))
    P = np.linalg.solve(A, b.T).T
    R, t = rigid_fit(X, P)
    Pfit = transform_points(R, t, X)
    mirrors = [MirrorPlane(normals[j], float(np.mean(-(Pfit + virt[j]) @ normals[j] / 2))) for j in range(K)]
    return MirrorClosedForm(R_cam_target=R, t_cam_target=t, mirrors=mirrors, axes=axes, virtual_poses=virt_poses,
                            points_cam=P, axis_angles_deg=np.asarray(axis_angles))


def mirror_extrinsics(camera: Camera, mirrored_points, object_points, *, sigma_px: float | None = None,
                      refine: bool = True) -> MirrorExtrinsicsResult:
    """Pose of ``camera`` relative to a target it sees in K ≥ 3 mirror poses (closed form + bundle adjustment).

    Parameters
    ----------
    camera : Camera
        Calibrated intrinsics (distortion included in the projection).
    mirrored_points : list of K arrays (N, 2) float64
        Image points (px) of the mirrored target for each mirror pose; rows aligned with
        ``object_points`` (row i is the image of the reflection of target point i). A point not
        seen (or rejected, e.g. vignetted by the mirror's edge) in a pose is a row of two NaN: the
        closed form takes each pose's virtual target from its own points, the adjustment leaves
        the missing observations out. Each pose needs at least ``MIN_POINTS_PER_VIEW`` points.
    object_points : (N, 3) float64
        Target points in the target frame (mm); N ≥ 4, not collinear.
    sigma_px : float, optional
        Image noise (px, per coordinate) for the covariance; default: estimated from the residuals.
    refine : bool
        Run the bundle adjustment (True) or return the closed form only (its covariance is then
        the one the bundle adjustment would have at that point).

    Returns
    -------
    MirrorExtrinsicsResult
        ``R_cam_target, t_cam_target`` (``x_cam = R @ x_target + t``), mirror planes, the
        closed-form solution, reprojection RMS (overall and per mirror) and covariances.

    Raises
    ------
    ValueError
        Invalid inputs or a degenerate setup (see :func:`mirror_closed_form`).
    """
    views, X = _validate(camera, mirrored_points, object_points)
    cf = mirror_closed_form(camera, views, X)
    K = len(views)
    model = RigBundle(camera, None, X, views, [], [], (cf.R_cam_target, cf.t_cam_target), None, cf.mirrors, [], [])
    r0 = model.residuals(model.x0)  # seen points only
    cf_rms = float(np.sqrt(np.mean(np.sum(r0.reshape(-1, 2) ** 2, axis=1))))
    x, r, cov = model.solve(sigma_px, refine)
    p = model.unpack(x)
    R, t = p["target"]
    per = model.full_residuals(x).reshape(K, -1, 2)
    per_rms = np.sqrt(np.nanmean(np.sum(per ** 2, axis=2), axis=1))
    return MirrorExtrinsicsResult(
        R_cam_target=nearest_rotation(R), t_cam_target=t,
        mirrors=[MirrorPlane(n, d) for n, d in p["mirrors_left"]], closed_form=cf,
        rms=float(np.sqrt(np.mean(np.sum(r.reshape(-1, 2) ** 2, axis=1)))), per_mirror_rms=per_rms,
        closed_form_rms=cf_rms, residuals=[-q for q in per], pose_covariance=cov[:6, :6], covariance=cov,
        camera=camera, n_points=X.shape[0])


# -- joint adjustment of both cameras ----------------------------------------------------------------
@dataclass
class JointMirrorResult:
    """Result of :func:`joint_mirror_stereo`.

    ``rig`` carries ``R_right_left, t_right_left`` and their 6×6 covariance (``[δρ (rad), δt (mm)]``,
    ``R_right_left = exp([δρ]×) R̂``). ``rms_groups`` gives the reprojection RMS (px) of each group
    of observations (left mirrored, right mirrored, far views left / right).
    """

    rig: object
    R_left_target: np.ndarray
    t_left_target: np.ndarray
    mirrors_left: list
    mirrors_right: list
    far_poses_left: list
    rms: float
    rms_groups: dict
    covariance: np.ndarray
    initial_rig: object = None

    def report(self) -> str:
        g = ", ".join(f"{k} {v:.4f}" for k, v in self.rms_groups.items())
        return f"joint mirror adjustment: RMS {self.rms:.4f} px ({g})\n" + self.rig.report()


def _validate_far(far_views):
    far = []
    for i, fv in enumerate(far_views or []):
        if len(fv) != 3:
            raise ValueError(f"far_views[{i}] must be (object_points, left_points, right_points)")
        Xf, ql, qr = (np.asarray(z, dtype=np.float64) for z in fv)
        if Xf.ndim != 2 or Xf.shape[1] != 3 or ql.shape != (Xf.shape[0], 2) or qr.shape != (Xf.shape[0], 2):
            raise ValueError(f"far_views[{i}]: expected (M, 3), (M, 2), (M, 2) arrays with equal M, got "
                             f"{Xf.shape}, {ql.shape}, {qr.shape}")
        if Xf.shape[0] < 4 or not (np.all(np.isfinite(Xf)) and np.all(np.isfinite(ql)) and np.all(np.isfinite(qr))):
            raise ValueError(f"far_views[{i}] needs at least 4 finite points")
        far.append((Xf, ql, qr))
    return far


def joint_mirror_stereo(left: Camera, right: Camera, left_mirrored, right_mirrored, object_points, *,
                        far_views=None, left_result: MirrorExtrinsicsResult | None = None,
                        right_result: MirrorExtrinsicsResult | None = None,
                        sigma_px: float | None = None) -> JointMirrorResult:
    """Joint bundle adjustment of a stereo rig from both cameras' mirror views (and direct far views).

    The target (monitor) stays put while each camera sees it in its own mirror at K ≥ 3 poses.
    Unknowns: the target pose in the left camera frame, the rig pose ``R_right_left, t_right_left``,
    every mirror plane of both cameras and the pose of each far view. Residuals: reprojection of
    the mirrored points in both cameras and, for each far view, of its points in both cameras.
    Intrinsics are held fixed (their uncertainty is not in the covariance).

    Parameters
    ----------
    left, right : Camera
    left_mirrored, right_mirrored : list of (N, 2)
        Mirrored image points per mirror pose, rows aligned with ``object_points`` (N, 3) mm.
    far_views : list of (object_points (M, 3), left_points (M, 2), right_points (M, 2)), optional
        Views of a target that both cameras see directly (e.g. the monitor at the far working
        distance — the paper's last frame).
    left_result, right_result : MirrorExtrinsicsResult, optional
        Per-camera solutions to start from (computed when omitted).
    sigma_px : float, optional
        Image noise for the covariance (default: from the residuals).
    """
    lv, X = _validate(left, left_mirrored, object_points, "left_mirrored")
    rv, _ = _validate(right, right_mirrored, object_points, "right_mirrored")
    far = _validate_far(far_views)
    if left_result is None:
        left_result = mirror_extrinsics(left, lv, X)
    if right_result is None:
        right_result = mirror_extrinsics(right, rv, X)
    R_lt0, t_lt0 = left_result.R_cam_target, left_result.t_cam_target
    R_rl0 = right_result.R_cam_target @ R_lt0.T
    t_rl0 = right_result.t_cam_target - R_rl0 @ t_lt0
    initial_rig = StereoRig(left, right, R_rl0, t_rl0)
    far0 = [_pnp(left, Xf, ql) for Xf, ql, _ in far]
    model = RigBundle(left, right, X, lv, rv, far, (R_lt0, t_lt0), (R_rl0, t_rl0), left_result.mirrors,
                       right_result.mirrors, far0)
    x, r, cov = model.solve(sigma_px)
    p = model.unpack(x)
    r = model.full_residuals(x)  # NaN where a point was not seen
    n = X.shape[0]
    sizes = {"left_mirrored": 2 * n * len(lv), "right_mirrored": 2 * n * len(rv)}
    for i, (Xf, _, _) in enumerate(far):
        sizes[f"far{i}_left"] = 2 * Xf.shape[0]
        sizes[f"far{i}_right"] = 2 * Xf.shape[0]
    groups, o = {}, 0
    for name, s in sizes.items():
        rr = r[o:o + s].reshape(-1, 2)
        groups[name] = float(np.sqrt(np.nanmean(np.sum(rr ** 2, axis=1))))
        o += s
    R_rl, t_rl = p["rig"]
    rig = StereoRig(left, right, nearest_rotation(R_rl), t_rl, covariance=cov[model.sl["rig"], model.sl["rig"]],
                    metadata={"method": "joint mirror bundle adjustment", "mirror_poses": [len(lv), len(rv)],
                              "points": n, "far_views": len(far)})
    R_lt, t_lt = p["target"]
    return JointMirrorResult(rig=rig, R_left_target=nearest_rotation(R_lt), t_left_target=t_lt,
                             mirrors_left=[MirrorPlane(nn, dd) for nn, dd in p["mirrors_left"]],
                             mirrors_right=[MirrorPlane(nn, dd) for nn, dd in p["mirrors_right"]],
                             far_poses_left=p["far"], rms=float(np.sqrt(np.nanmean(np.sum(r.reshape(-1, 2) ** 2, axis=1)))),
                             rms_groups=groups, covariance=cov, initial_rig=initial_rig)
