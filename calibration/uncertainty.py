"""Uncertainty of calibration results.

* :func:`covariance_from_jacobian` — Gauss–Newton covariance ``σ² (JᵀJ)⁻¹`` of a least-squares
  estimate, with ``σ²`` the residual variance (or a given image noise).
* :func:`propagate` — first-order propagation of a covariance through a function (numerical Jacobian).
* :func:`rig_covariance_from_intrinsics` — a stereo rig's covariance due to its cameras' intrinsic
  covariances (the rig re-solved with the intrinsics moved ±1σ).

The exact synthetic geometry of the paper's rig that predicts these figures (``paper_mirror_setup``
and its Monte Carlo study) is research code: ``repro/mirror_setup.py``, ``repro/mirror_accuracy.py``.

Conventions: docs/conventions.md (mm, camera frame x right / y down / z forward, ``R_a_b``).
"""
from __future__ import annotations

import numpy as np

from .camera import Camera, vector_from_rotation


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


# -- intrinsics' share of a rig's covariance ------------------------------------------------------
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


__all__ = ["covariance_from_jacobian", "propagate", "rig_covariance_from_intrinsics"]
