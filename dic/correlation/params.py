"""Shape-function parameter arrays: order conversion, user guesses, extrapolation to a neighbour.

Parameters are stored in :data:`kernels.conventions.PARAMS_1ST` order ``(u, ux, uy, v, vx, vy)``
(6 per POI) or ``PARAMS_2ND`` order ``(u, ux, uy, uxx, uxy, uyy, v, vx, vy, vxx, vxy, vyy)`` (12 per
POI); ``u`` is at column 0 and ``v`` at column ``k // 2``. Displacements in px, gradients
dimensionless, second derivatives in 1/px.
"""
from __future__ import annotations

import numpy as np

from kernels.checks import positive_float
from kernels.icgn import n_params

__all__ = ["MAX_TOL_PX", "check_tol", "n_params", "convert_order", "embed_first_order", "extrapolate", "displacement",
           "guess_params"]

#: the largest IC-GN convergence threshold accepted (px, on the norm of the parameter update): beyond it
#: iterations stop while the displacement is still tenths of a pixel off (``tol=1e300`` on a 1.0 px shift
#: stopped after one iteration at u = 0.83 px with the points marked valid); the default is 0.001 px
MAX_TOL_PX = 0.1


def check_tol(tol) -> float:
    """The IC-GN convergence threshold ``tol`` (px) as a float, positive and at most :data:`MAX_TOL_PX`;
    ``ValueError`` that says the bound otherwise."""
    value = positive_float(tol, "tol", detail=" of pixels")
    if value > MAX_TOL_PX:
        raise ValueError(f"tol must be at most {MAX_TOL_PX} px (the convergence threshold on the parameter update; "
                         f"a larger one stops the iterations before they converge), got {tol!r}")
    return value


def convert_order(params: np.ndarray, order: int) -> np.ndarray:
    """(N, 6|12) parameters -> (N, k) for ``order`` (2nd -> 1st drops the 2nd derivatives).

    Returns the input itself when it already has the order's width.
    """
    k = n_params(order)
    if params.shape[1] == k:
        return params
    if k == 6:  # 2nd -> 1st: drop second derivatives
        return params[:, [0, 1, 2, 6, 7, 8]]
    out = np.zeros((params.shape[0], 12))
    out[:, [0, 1, 2, 6, 7, 8]] = params
    return out


def embed_first_order(params6: np.ndarray, order: int) -> np.ndarray:
    """(N, 6) first-order parameters -> a new (N, 6|12) array in the order's layout."""
    if order == 1:
        return params6.copy()
    out = np.zeros((params6.shape[0], 12))
    out[:, 0:3] = params6[:, 0:3]
    out[:, 6:9] = params6[:, 3:6]
    return out


def extrapolate(params: np.ndarray, d: np.ndarray, order: int) -> np.ndarray:
    """Shape-function parameters of a neighbour (N, k) moved to a POI offset by ``d`` (N, 2) px."""
    dx, dy = d[:, 0], d[:, 1]
    out = params.copy()
    if order == 1:
        for b in (0, 3):
            out[:, b] = params[:, b] + params[:, b + 1] * dx + params[:, b + 2] * dy
        return out
    for b in (0, 6):
        u, ux, uy, uxx, uxy, uyy = (params[:, b + i] for i in range(6))
        out[:, b] = u + ux * dx + uy * dy + 0.5 * uxx * dx * dx + uxy * dx * dy + 0.5 * uyy * dy * dy
        out[:, b + 1] = ux + uxx * dx + uxy * dy
        out[:, b + 2] = uy + uxy * dx + uyy * dy
    return out


def displacement(params: np.ndarray, order: int) -> np.ndarray:
    """(N, 2) displacement ``(u, v)`` px at the POIs from parameters (N, 6|12)."""
    j = 3 if order == 1 else 6
    return np.stack([params[:, 0], params[:, j]], axis=1).astype(np.float64)


def guess_params(guess, n: int, order: int) -> np.ndarray | None:
    """Normalise a user's guess to (N, K) float64 parameters (None stays None).

    ``guess``: ``(u, v)``, an (N, 2) array of ``(u, v)``, an (N, 6|12) parameter array, or an object
    with ``params`` and ``n_points`` (a :class:`dic.Field2D`, e.g. the previous frame; its
    NaNs become 0).
    """
    if guess is None:
        return None
    k = n_params(order)
    if hasattr(guess, "params") and hasattr(guess, "n_points"):
        if guess.n_points != n:
            raise ValueError(f"guess field has {guess.n_points} points, expected {n}")
        g = convert_order(np.asarray(guess.params, dtype=np.float64), order)
        return np.where(np.isfinite(g), g, 0.0)
    g = np.asarray(guess, dtype=np.float64)
    if g.shape == (2,):
        g = np.broadcast_to(g, (n, 2))
    if g.shape == (n, 2):
        out = np.zeros((n, k))
        out[:, 0] = g[:, 0]
        out[:, k // 2] = g[:, 1]
        g = out
    elif g.shape in ((n, 6), (n, 12)):
        g = convert_order(g, order)
    else:
        raise ValueError(f"guess must be (u, v), an (N, 2) array of (u, v), an (N, {k}) parameter array or a "
                         f"Field2D, with N = {n}; got shape {g.shape}")
    if not np.all(np.isfinite(g)):
        raise ValueError("guess contains NaN or infinite values")
    return np.ascontiguousarray(g)
