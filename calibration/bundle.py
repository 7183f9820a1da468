"""Rig bundle adjustment: one camera or a stereo pair, fixed intrinsics, analytic Jacobian.

:class:`RigBundle` is the least-squares core shared by the mirror calibration
(:func:`calibration.mirror.mirror_extrinsics`, :func:`calibration.mirror.joint_mirror_stereo`) and
the conventional stereo calibration (:func:`calibration.stereo.stereo_calibrate`). Its unknowns are
any of: the pose of a target seen in mirrors, the rig pose ``R_right_left, t_right_left``, the
mirror planes of each camera and the poses of views that both cameras see directly; its residuals
are reprojection errors (px) through the full camera model, distortion included
(``scipy.optimize.least_squares``, Levenberg–Marquardt), and its Jacobian at the solution gives the
covariance (:func:`calibration.uncertainty.covariance_from_jacobian`).

Rotations are parametrised as left perturbations ``R = exp([ω]×) R0`` of a reference rotation;
planes ``n·x + d = 0`` (``|n| = 1``) as ``n = normalise(n0 + a u + b v)`` with ``(u, v)`` a tangent
basis of the reference normal ``n0``. Conventions: docs/conventions.md (mm, camera frame, ``R_a_b``).
"""
from __future__ import annotations

import numpy as np

from .camera import Camera, distort_normalized, rotation_from_vector
from .uncertainty import covariance_from_jacobian


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


def _check_inputs(left, right, X, left_obs, right_obs, far, target0, rig0, mirrors_left, mirrors_right, far0):
    """Shapes, types and counts of :class:`RigBundle`'s inputs (values are the caller's to check)."""
    if not isinstance(left, Camera):
        raise ValueError(f"left must be a calibration.camera.Camera, got {type(left).__name__}")
    if right is not None and not isinstance(right, Camera):
        raise ValueError(f"right must be a calibration.camera.Camera or None, got {type(right).__name__}")
    if not isinstance(X, np.ndarray) or X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"X must be an (N, 3) float64 array of target points (mm), got {getattr(X, 'shape', type(X))}")
    for what, obs, planes in (("left_obs", left_obs, mirrors_left), ("right_obs", right_obs, mirrors_right)):
        if len(obs) != len(planes):
            raise ValueError(f"{what} has {len(obs)} mirrored views but {len(planes)} start planes were given")
        for j, q in enumerate(obs):
            if np.shape(q) != (X.shape[0], 2):
                raise ValueError(f"{what}[{j}] must have shape ({X.shape[0]}, 2) (rows aligned with X), got {np.shape(q)}")
    if right_obs and right is None:
        raise ValueError("right_obs needs the right camera")
    if (left_obs or right_obs) and target0 is None:
        raise ValueError("mirrored views need a start target pose target0 = (R, t)")
    if right is not None and rig0 is None:
        raise ValueError("a right camera needs a start rig pose rig0 = (R_right_left, t_right_left)")
    if len(far) != len(far0):
        raise ValueError(f"{len(far)} far views but {len(far0)} start poses far0")
    for i, fv in enumerate(far):
        if len(fv) != 3:
            raise ValueError(f"far[{i}] must be (object_points, left_points, right_points)")
        Xf, ql, qr = fv
        m = np.shape(Xf)[0] if np.ndim(Xf) == 2 else -1
        if np.shape(Xf) != (m, 3) or np.shape(ql) != (m, 2) or np.shape(qr) != (m, 2):
            raise ValueError(f"far[{i}]: expected (M, 3), (M, 2), (M, 2) arrays with equal M, got "
                             f"{np.shape(Xf)}, {np.shape(ql)}, {np.shape(qr)}")


class RigBundle:
    """Bundle adjustment of a (stereo) camera system with fixed intrinsics, analytic Jacobian.

    Parameter vector, in order (blocks present only when used):

    * ``target``: ``[ω (3), t (3)]`` pose of the mirror target in the left (first) camera frame,
      ``R = exp([ω]×) R0``;
    * ``rig``: ``[ρ (3), t (3)]`` pose of the right camera in the left frame, ``R = exp([ρ]×) R0``;
    * ``mirrors_left`` / ``mirrors_right``: ``[a, b, d]`` per plane, ``n = normalise(n0 + a u + b v)``
      in that camera's frame;
    * ``far``: ``[ω (3), t (3)]`` per directly seen view, its pose in the left frame.

    Residuals (px, observed subtracted): left mirrored views, right mirrored views, then per far
    view its left and right image points. ``sl[name]`` is the slice of a block in the parameter
    vector (names ``"target"``, ``"rig"``, ``"mL{j}"``, ``"mR{j}"``, ``"far{i}"``).

    Parameters
    ----------
    left : Camera
        The first camera (its frame is the frame of every pose).
    right : Camera or None
        The second camera; ``None`` for a single camera (no rig block).
    X : (N, 3) float64
        Target points of the mirrored views (mm, target frame); ``(0, 3)`` when there are none.
    left_obs, right_obs : lists of (N, 2) float64
        Image points (px) of the mirrored target per mirror pose of each camera, rows aligned with
        ``X``; a point not seen is a row of two NaN.
    far : list of (object_points (M, 3), left_points (M, 2), right_points (M, 2))
        Views that both cameras see directly (``right_points`` unused without ``right``).
    target0 : (R (3, 3), t (3,)) or None
        Start pose of the mirror target in the left frame (required with mirrored views).
    rig0 : (R_right_left, t_right_left) or None
        Start rig pose (required with ``right``).
    mirrors_left, mirrors_right : lists of planes
        Start planes, one per mirrored view (objects with ``normal`` (3,) and ``d``, e.g.
        :class:`calibration.mirror.MirrorPlane`).
    far0 : list of (R (3, 3), t (3,))
        Start pose of each far view in the left frame.

    Raises
    ------
    ValueError
        Inputs of the wrong type, shape or count (e.g. a mirror plane missing for a view).
    """

    def __init__(self, left, right, X, left_obs, right_obs, far, target0, rig0, mirrors_left, mirrors_right, far0):
        _check_inputs(left, right, X, left_obs, right_obs, far, target0, rig0, mirrors_left, mirrors_right, far0)
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
        """Parameters ``x`` (n_params,) as a dict: ``target`` and ``rig`` ``(R, t)``, ``mirrors_left`` /
        ``mirrors_right`` lists of ``(n (3,), d)``, ``far`` list of ``(R, t)`` (mm, left camera frame)."""
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
        """Residuals (px) of the seen observations (m,) and their Jacobian (m, n_params) at ``x``."""
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
        """Residuals (px) of the seen observations, shape (m,)."""
        return self.evaluate(x)[0]

    def jacobian(self, x):
        """Jacobian of :meth:`residuals`, shape (m, n_params)."""
        return self.evaluate(x)[1]

    def solve(self, sigma_px=None, refine=True):
        """Levenberg–Marquardt from ``x0``, then recentre and return ``(x, r, covariance)``.

        ``x`` (n_params,) the recentred solution (rotation parameters 0, see :meth:`recenter`),
        ``r`` (m,) px its residuals, ``covariance`` (n_params, n_params) from the Jacobian with image
        noise ``sigma_px`` (px per coordinate; default: estimated from the residuals). ``refine=False``
        evaluates the start point without iterating.
        """
        from scipy.optimize import least_squares

        x = self.x0
        if refine:
            sol = least_squares(self.residuals, x, jac=self.jacobian, method="lm", x_scale="jac",
                                xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100 * (x.size + 1))
            x = sol.x
        x = self.recenter(x)
        r, J = self.evaluate(x)
        return x, r, covariance_from_jacobian(J, r, sigma_px)

