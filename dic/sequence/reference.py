"""Reference strategies of a 2-D sequence and the composition of displacements across reference updates.

Strategies (``reference=`` of :func:`dic.sequence.track_sequence`, ``--reference`` of ``specula track``):

``"fixed"``
    every frame against the original reference image (frame 0).
``"incremental"``
    frame ``k`` against frame ``k - 1``.
``"every:N"``
    frame ``k`` against frame ``N * floor((k - 1) / N)`` (the reference moves every N frames).
``"auto"``
    frame ``k`` against the previous frame's reference; when the result's valid fraction (among the
    points valid in the reference) falls below ``auto_valid`` (default 0.95) or the median ZNCC of its
    valid points below ``auto_zncc`` (default 0.95), the reference moves to frame ``k - 1`` and
    frame ``k`` is tracked again against it.

Results are always Lagrangian, at the original POIs ``X0`` of the reference image: a new reference
``r`` tracks the points where the original POIs are in frame ``r`` (``X_r = X0 + d_r(X0)``; invalid
points get the displacement interpolated from their valid neighbours so that the point set stays
the same), so a displacement ``w`` measured against ``r`` composes exactly as
``d_k(X0) = d_r(X0) + w(X_r)``, and the shape-function gradients by the chain rule
(:func:`compose_params`). A point is valid when it is valid in the reference and in the frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ReferencePolicy", "parse_reference", "compose_params", "moved_points", "relative_params"]

AUTO_VALID = 0.95
AUTO_ZNCC = 0.95


@dataclass(frozen=True)
class ReferencePolicy:
    """A parsed reference strategy: ``kind`` "fixed" | "incremental" | "every" | "auto", ``every`` N,
    and the ``auto`` thresholds."""

    kind: str = "fixed"
    every: int = 0
    auto_valid: float = AUTO_VALID
    auto_zncc: float = AUTO_ZNCC

    @property
    def text(self) -> str:
        return f"every:{self.every}" if self.kind == "every" else self.kind

    def start(self, k: int, previous_reference: int) -> int:
        """The reference frame that frame ``k`` is tracked against first (``previous_reference``: frame k-1's)."""
        if self.kind == "fixed":
            return 0
        if self.kind == "incremental":
            return k - 1
        if self.kind == "every":
            return self.every * ((k - 1) // self.every)
        return previous_reference

    def needs_update(self, valid_fraction: float, median_zncc: float) -> bool:
        """``auto``: does a result this good call for a newer reference?"""
        return self.kind == "auto" and (not valid_fraction >= self.auto_valid or not median_zncc >= self.auto_zncc)


def parse_reference(reference, *, auto_valid: float = AUTO_VALID, auto_zncc: float = AUTO_ZNCC) -> ReferencePolicy:
    """``"fixed"``, ``"incremental"``, ``"every:N"`` (N >= 1) or ``"auto"`` -> :class:`ReferencePolicy`."""
    from kernels.checks import unit_interval

    auto_valid = unit_interval(auto_valid, "auto_valid")
    auto_zncc = unit_interval(auto_zncc, "auto_zncc")
    if isinstance(reference, ReferencePolicy):
        return reference
    if not isinstance(reference, str):
        raise ValueError(f"reference must be 'fixed', 'incremental', 'every:N' or 'auto', got {reference!r}")
    text = reference.strip().lower()
    if text in ("fixed", "incremental", "auto"):
        return ReferencePolicy(text, 0, auto_valid, auto_zncc)
    if text.startswith("every:"):
        n = text[len("every:"):].strip()
        if n.isdigit() and int(n) >= 1:
            return ReferencePolicy("every", int(n), auto_valid, auto_zncc)
        raise ValueError(f"reference 'every:N' needs a whole number N >= 1 of frames, got {reference!r}")
    raise ValueError(f"reference must be 'fixed', 'incremental', 'every:N' or 'auto', got {reference!r}")


def _gradients(params: np.ndarray, order: int):
    """(N, 2) displacement, (N, 2, 2) gradient G[i, a] = d u_i / d x_a and, for order 2, (N, 2, 2, 2) Hessians."""
    h = params.shape[1] // 2
    d = np.stack([params[:, 0], params[:, h]], 1)
    G = np.stack([params[:, 1:3], params[:, h + 1:h + 3]], 1)
    H = None
    if order == 2:
        H = np.empty((params.shape[0], 2, 2, 2))
        for i, base in enumerate((0, h)):
            xx, xy, yy = params[:, base + 3], params[:, base + 4], params[:, base + 5]
            H[:, i] = np.stack([np.stack([xx, xy], -1), np.stack([xy, yy], -1)], -2)
    return d, G, H


def _pack(d, G, H, order: int) -> np.ndarray:
    n = d.shape[0]
    out = np.zeros((n, 6 if order == 1 else 12))
    h = out.shape[1] // 2
    for i, base in enumerate((0, h)):
        out[:, base] = d[:, i]
        out[:, base + 1:base + 3] = G[:, i]
        if order == 2:
            out[:, base + 3] = H[:, i, 0, 0]
            out[:, base + 4] = H[:, i, 0, 1]
            out[:, base + 5] = H[:, i, 1, 1]
    return out


def compose_params(ref_params: np.ndarray, inc_params: np.ndarray, order: int) -> np.ndarray:
    """Parameters of ``d(X) = d_r(X) + w(X + d_r(X))`` from those of ``d_r`` (at X) and ``w`` (at X + d_r(X)).

    Chain rule: gradient ``G = G_r + G_w F_r`` (``F_r = I + G_r``); second order
    ``H_i = H_r,i + F_r^T H_w,i F_r + sum_a G_w[i, a] H_r,a``.
    """
    dr, Gr, Hr = _gradients(np.asarray(ref_params, np.float64), order)
    dw, Gw, Hw = _gradients(np.asarray(inc_params, np.float64), order)
    F = np.eye(2)[None] + Gr
    G = Gr + np.einsum("nia,nab->nib", Gw, F)
    H = None
    if order == 2:
        H = Hr + np.einsum("nab,niac,ncd->nibd", F, Hw, F) + np.einsum("nia,nabc->nibc", Gw, Hr)
    return _pack(dr + dw, G, H, order)


def relative_params(ref_params: np.ndarray, params: np.ndarray, order: int) -> np.ndarray:
    """The inverse of :func:`compose_params` to first order: ``w`` with ``d = d_r ∘ w`` (translation and
    gradient; second-order terms zero), used as the initial guess against a moved reference."""
    dr, Gr, _ = _gradients(np.asarray(ref_params, np.float64), order)
    d, G, _ = _gradients(np.asarray(params, np.float64), order)
    F = np.eye(2)[None] + Gr
    with np.errstate(all="ignore"):
        Gw = np.einsum("nia,nab->nib", G - Gr, np.linalg.inv(F))
    return _pack(d - dr, Gw, np.zeros((d.shape[0], 2, 2, 2)), order)


def moved_points(points0: np.ndarray, u: np.ndarray, v: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Where the original POIs are in a frame: ``X0 + (u, v)``; points not valid there get the displacement
    interpolated linearly from the valid ones (nearest valid one outside their hull)."""
    pts = np.asarray(points0, np.float64)
    d = np.stack([u, v], 1).astype(np.float64)
    good = np.asarray(valid, bool) & np.all(np.isfinite(d), axis=1)
    if not np.any(good):
        raise ValueError("no valid point to move the reference with")
    bad = ~good
    if np.any(bad):
        from scipy.interpolate import griddata

        filled = None
        if np.count_nonzero(good) >= 3:
            try:
                filled = griddata(pts[good], d[good], pts[bad], method="linear")
            except Exception:  # noqa: BLE001 - collinear valid points (Qhull): nearest below
                filled = None
        near = griddata(pts[good], d[good], pts[bad], method="nearest")
        if filled is None:
            filled = near
        filled = np.where(np.isfinite(filled), filled, near)
        d = d.copy()
        d[bad] = filled
    return pts + d


def shift_params(params: np.ndarray, delta: np.ndarray, order: int) -> np.ndarray:
    """Shape-function parameters of the same warp seen from a point ``delta`` (N, 2) px away: the
    displacement and gradient evaluated there (exact for the affine and quadratic shape functions)."""
    d, G, H = _gradients(np.asarray(params, np.float64), order)
    delta = np.asarray(delta, np.float64)
    d2 = d + np.einsum("nia,na->ni", G, delta)
    G2 = G
    if order == 2:
        d2 = d2 + 0.5 * np.einsum("niab,na,nb->ni", H, delta, delta)
        G2 = G + np.einsum("niab,nb->nia", H, delta)
    return _pack(d2, G2, H, order)
