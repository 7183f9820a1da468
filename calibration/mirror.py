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

from .camera import (
    Camera,
    distort_normalized,
    nearest_rotation,
    rigid_fit,
    rotation_angle_deg,
    rotation_from_vector,
    transform_points,
)
from .intrinsics import MIRROR_FLIP
from .uncertainty import covariance_from_jacobian

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


# -- bundle adjustment -----------------------------------------------------------------------------
def _tangent_basis(n):
    a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def _skew(v):
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    v = np.asarray(v, dtype=np.float64)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def _left_jacobian(w):
    """Left Jacobian of SO(3): d exp(w) = [J_l(w) dw]× exp(w)."""
    th = float(np.linalg.norm(w))
    W = _skew(w)
    if th < 1e-8:
        return np.eye(3) + 0.5 * W
    return np.eye(3) + (1 - np.cos(th)) / th ** 2 * W + (th - np.sin(th)) / th ** 3 * W @ W


def _reflect(P, n, d):
    return P - 2.0 * (P @ n + d)[:, None] * n[None, :]


def _project(camera, P, jacobian: bool = False):
    """Pinhole + OpenCV distortion of camera-frame points (N, 3) -> pixels (N, 2), no input checks
    (the inner loop of the bundle adjustments; same model as :meth:`Camera.project`). With
    ``jacobian``, also returns d(pixels)/d(P), shape (N, 2, 3)."""
    Z = P[:, 2]
    x = P[:, 0] / Z
    y = P[:, 1] / Z
    xy = np.column_stack([x, y])
    if jacobian:
        distorted, D = distort_normalized(xy, camera.dist8, jacobian=True)  # D: d(xd, yd)/d(x, y)
    else:
        distorted = distort_normalized(xy, camera.dist8)
    xd, yd = distorted[:, 0], distorted[:, 1]
    K = camera.K
    out = np.empty((P.shape[0], 2))
    out[:, 0] = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    out[:, 1] = K[1, 1] * yd + K[1, 2]
    if not jacobian:
        return out
    A = np.array([[K[0, 0], K[0, 1]], [0.0, K[1, 1]]])
    G2 = np.einsum("ij,njk->nik", A, D)  # (N, 2, 2)
    Pi = np.zeros((P.shape[0], 2, 3))  # d(x, y)/dP
    Pi[:, 0, 0] = 1 / Z
    Pi[:, 0, 2] = -x / Z
    Pi[:, 1, 1] = 1 / Z
    Pi[:, 1, 2] = -y / Z
    return out, np.einsum("nij,njk->nik", G2, Pi)


class _RigBundle:
    """Bundle adjustment of a (stereo) camera system with fixed intrinsics, analytic Jacobian.

    Parameter vector, in order (blocks present only when used):

    * ``target``: ``[ω (3), t (3)]`` pose of the mirror target in the left (first) camera frame,
      ``R = exp([ω]×) R0``;
    * ``rig``: ``[ρ (3), t (3)]`` pose of the right camera in the left frame, ``R = exp([ρ]×) R0``;
    * ``mirrors_left`` / ``mirrors_right``: ``[a, b, d]`` per plane, ``n = normalise(n0 + a u + b v)``
      in that camera's frame;
    * ``far``: ``[ω (3), t (3)]`` per directly seen view, its pose in the left frame.

    Residuals (px, observed subtracted): left mirrored views, right mirrored views, then per far
    view its left and right image points.
    """

    def __init__(self, left, right, X, left_obs, right_obs, far, target0, rig0, mirrors_left, mirrors_right, far0):
        self.left, self.right, self.X = left, right, X
        self.left_obs, self.right_obs, self.far = left_obs, right_obs, far
        self.has_target = bool(left_obs) or bool(right_obs)
        self.has_rig = right is not None
        self.R_target0, self.R_rig0 = (target0[0] if target0 else None), (rig0[0] if rig0 else None)
        self.mirror_bases = [[(m.normal.copy(), *_tangent_basis(m.normal)) for m in ms] for ms in (mirrors_left, mirrors_right)]
        self.R_far0 = [R for R, _ in far0]
        o = 0
        self.sl = {}

        def add(name, size):
            nonlocal o
            self.sl[name] = slice(o, o + size)
            o += size

        x0 = []
        if self.has_target:
            add("target", 6)
            x0.append(np.concatenate([np.zeros(3), target0[1]]))
        if self.has_rig:
            add("rig", 6)
            x0.append(np.concatenate([np.zeros(3), rig0[1]]))
        for side, ms in (("L", mirrors_left), ("R", mirrors_right)):
            for j, m in enumerate(ms):
                add(f"m{side}{j}", 3)
                x0.append(np.array([0.0, 0.0, m.d]))
        for i, (_, t) in enumerate(far0):
            add(f"far{i}", 6)
            x0.append(np.concatenate([np.zeros(3), t]))
        self.n_params = o
        self.x0 = np.concatenate(x0) if x0 else np.zeros(0)
        obs = np.concatenate([q.ravel() for q in left_obs] + [q.ravel() for q in right_obs]
                             + [np.concatenate([ql.ravel(), qr.ravel()]) for _, ql, qr in far])
        # points not seen in a view (NaN rows) have no residual: their rows are left out
        self.seen = np.isfinite(obs)
        self.obs = np.where(self.seen, obs, 0.0)
        self._cache_x = None

    # -- parameter access -------------------------------------------------------------------------
    def _pose(self, x, name, R0):
        p = x[self.sl[name]]
        return rotation_from_vector(p[:3]) @ R0, p[3:6].copy(), p[:3]

    def _plane(self, x, side, j):
        n0, u, v = self.mirror_bases[0 if side == "L" else 1][j]
        a, b, d = x[self.sl[f"m{side}{j}"]]
        m = n0 + a * u + b * v
        norm = np.linalg.norm(m)
        n = m / norm
        T = (np.eye(3) - np.outer(n, n)) / norm
        return n, d, np.stack([T @ u, T @ v], axis=1)  # dn/d(a, b): (3, 2)

    def unpack(self, x):
        out = {}
        if self.has_target:
            out["target"] = self._pose(x, "target", self.R_target0)[:2]
        if self.has_rig:
            out["rig"] = self._pose(x, "rig", self.R_rig0)[:2]
        out["mirrors_left"] = [self._plane(x, "L", j)[:2] for j in range(len(self.left_obs))]
        out["mirrors_right"] = [self._plane(x, "R", j)[:2] for j in range(len(self.right_obs))]
        out["far"] = [self._pose(x, f"far{i}", self.R_far0[i])[:2] for i in range(len(self.far))]
        return out

    def recenter(self, x):
        """Move rotations into the reference matrices so that the rotation parameters are 0 at ``x``
        (the covariance then refers to perturbations ``exp([δ]×) R̂`` of the estimate)."""
        x = x.copy()
        if self.has_target:
            self.R_target0 = self._pose(x, "target", self.R_target0)[0]
            x[self.sl["target"]][:3] = 0
        if self.has_rig:
            self.R_rig0 = self._pose(x, "rig", self.R_rig0)[0]
            x[self.sl["rig"]][:3] = 0
        for i in range(len(self.far)):
            self.R_far0[i] = self._pose(x, f"far{i}", self.R_far0[i])[0]
            x[self.sl[f"far{i}"]][:3] = 0
        for side, n_obs in (("L", len(self.left_obs)), ("R", len(self.right_obs))):
            for j in range(n_obs):
                n, d, _ = self._plane(x, side, j)
                self.mirror_bases[0 if side == "L" else 1][j] = (n, *_tangent_basis(n))
                x[self.sl[f"m{side}{j}"]] = [0.0, 0.0, d]
        self._cache_x = None
        return x

    # -- residuals and Jacobian -------------------------------------------------------------------
    def evaluate(self, x):
        if self._cache_x is not None and np.array_equal(x, self._cache_x):
            return self._cache
        rows_r, rows_J = [], []
        N = self.X.shape[0]
        if self.has_target:
            R_t, t_t, w_t = self._pose(x, "target", self.R_target0)
            RX = self.X @ R_t.T
            PL = RX + t_t
            dPL = np.zeros((N, 3, 6))  # dPL / d(target)
            dPL[:, :, :3] = -_skew(RX) @ _left_jacobian(w_t)
            dPL[:, :, 3:] = np.eye(3)
        if self.has_rig:
            R_r, t_r, w_r = self._pose(x, "rig", self.R_rig0)
            Jl_r = _left_jacobian(w_r)

        def block(J_full, name, J_part):
            J_full[:, self.sl[name]] = J_part

        def mirror_rows(camera, P, dP_dtarget, side, j, extra):
            n, d, dn = self._plane(x, side, j)
            Pm = _reflect(P, n, d)
            q, G = _project(camera, Pm, jacobian=True)
            H = np.eye(3) - 2 * np.outer(n, n)
            J = np.zeros((2 * N, self.n_params))
            GH = G @ H  # (N, 2, 3)
            block(J, "target", (GH @ dP_dtarget).reshape(2 * N, 6))
            s_ = P @ n + d
            dPm_dn = -2 * (s_[:, None, None] * np.eye(3) + n[None, :, None] * P[:, None, :])  # (N, 3, 3)
            dm = np.concatenate([dPm_dn @ dn, (-2 * n)[None, :, None].repeat(N, 0)], axis=2)  # (N, 3, 3)
            block(J, f"m{side}{j}", (G @ dm).reshape(2 * N, 3))
            for name, dP in extra:
                block(J, name, (GH @ dP).reshape(2 * N, dP.shape[2]))
            rows_r.append(q.ravel())
            rows_J.append(J)

        for j in range(len(self.left_obs)):
            mirror_rows(self.left, PL, dPL, "L", j, [])
        if self.right_obs:
            PR = PL @ R_r.T + t_r
            dPR_dt = np.einsum("ij,njk->nik", R_r, dPL)
            dPR_drig = np.zeros((N, 3, 6))
            dPR_drig[:, :, :3] = -_skew(PL @ R_r.T) @ Jl_r
            dPR_drig[:, :, 3:] = np.eye(3)
            for j in range(len(self.right_obs)):
                mirror_rows(self.right, PR, dPR_dt, "R", j, [("rig", dPR_drig)])
        for i, (Xf, _, _) in enumerate(self.far):
            M = Xf.shape[0]
            R_f, t_f, w_f = self._pose(x, f"far{i}", self.R_far0[i])
            RXf = Xf @ R_f.T
            P = RXf + t_f
            dP = np.zeros((M, 3, 6))
            dP[:, :, :3] = -_skew(RXf) @ _left_jacobian(w_f)
            dP[:, :, 3:] = np.eye(3)
            q, G = _project(self.left, P, jacobian=True)
            J = np.zeros((2 * M, self.n_params))
            block(J, f"far{i}", (G @ dP).reshape(2 * M, 6))
            rows_r.append(q.ravel())
            rows_J.append(J)
            if self.has_rig:
                PRf = P @ R_r.T + t_r
                q, G = _project(self.right, PRf, jacobian=True)
                J = np.zeros((2 * M, self.n_params))
                block(J, f"far{i}", (G @ np.einsum("ij,njk->nik", R_r, dP)).reshape(2 * M, 6))
                drig = np.zeros((M, 3, 6))
                drig[:, :, :3] = -_skew(P @ R_r.T) @ Jl_r
                drig[:, :, 3:] = np.eye(3)
                block(J, "rig", (G @ drig).reshape(2 * M, 6))
                rows_r.append(q.ravel())
                rows_J.append(J)
        r = np.concatenate(rows_r) - self.obs
        J = np.concatenate(rows_J, axis=0)
        self._cache_x, self._cache = x.copy(), (r[self.seen], J[self.seen])
        self._full_r = np.where(self.seen, r, np.nan)
        return self._cache

    def full_residuals(self, x):
        """Residuals (px) of every observation slot, NaN where the point was not seen."""
        self.evaluate(x)
        return self._full_r.copy()

    def residuals(self, x):
        return self.evaluate(x)[0]

    def jacobian(self, x):
        return self.evaluate(x)[1]

    def solve(self, sigma_px=None, refine=True):
        """Levenberg–Marquardt from ``x0``, then recentre and return ``(x, r, covariance)``."""
        from scipy.optimize import least_squares

        x = self.x0
        if refine:
            sol = least_squares(self.residuals, x, jac=self.jacobian, method="lm", x_scale="jac",
                                xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100 * (x.size + 1))
            x = sol.x
        x = self.recenter(x)
        r, J = self.evaluate(x)
        return x, r, covariance_from_jacobian(J, r, sigma_px)


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
    model = _RigBundle(camera, None, X, views, [], [], (cf.R_cam_target, cf.t_cam_target), None, cf.mirrors, [], [])
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
    from .stereo import StereoRig

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
    model = _RigBundle(left, right, X, lv, rv, far, (R_lt0, t_lt0), (R_rl0, t_rl0), left_result.mirrors,
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
