"""3-D stereo-DIC results: the :class:`Field3D` container, object frames and surface strains.

Frames and units follow docs/conventions.md: 3-D coordinates in millimetres, by default in the
**left camera frame** (x right, y down, z forward); a :class:`Field3D` can be expressed in any
object frame ``x_obj = R_obj_left @ x_left + t_obj_left`` (:func:`plane_frame` gives the frame of
the best-fit plane of a shape, as in Section 3 of the paper behind Specula). Image positions are
``(x, y)`` pixels of the **left reference image**.

Surface strain
--------------
The Green-Lagrange strain of the surface is computed pointwise (Pan, Asundi, Xie & Gao, "Digital
image correlation using iterative least squares and pointwise least squares for displacement
field and strain field measurements", Optics and Lasers in Engineering 47, 2009,
doi:10.1016/j.optlaseng.2008.10.014), extended to a surface in 3-D as in Sutton, Orteu & Schreier,
*Image Correlation for Shape, Motion and Deformation Measurements*, Springer 2009, Sec. 7.x:

1. the tangent plane at each point is the least-squares plane of the reference positions of its
   neighbours (the eigenvector of the smallest eigenvalue of their scatter matrix), with the
   unit normal ``n`` turned towards the left camera; the in-plane basis ``e1`` is the object
   frame's x axis projected onto the plane, ``e2 = ± n × e1`` on the side of the frame's y axis
   (:func:`tangent_basis`);
2. the 3-D displacement of the neighbours is fitted by least squares as an affine function of
   their tangent-plane coordinates ``(a, b)``: ``U ≈ U0 + G_a a + G_b b``;
3. the deformed tangent vectors are ``f_a = e1 + G_a``, ``f_b = e2 + G_b`` and the strain is
   ``E = ½ (Fᵀ F − I)`` in the ``(e1, e2)`` basis: ``exx = ½(f_a·f_a − 1)``,
   ``eyy = ½(f_b·f_b − 1)``, ``exy = ½ f_a·f_b`` (tensor component; the engineering shear is
   ``2 exy``).

Rigid-body motions give exactly zero strain in this formulation (it is the exact Green-Lagrange
strain of the fitted affine map, not a small-strain approximation).

Other strain types by name (``strain_type=``, the names of :data:`dic._strain.STRAIN_TYPES`), from the
same fit: ``"small"``, the symmetric in-plane part of the displacement gradient,
``exx = e1·G_a``, ``eyy = e2·G_b``, ``exy = ½(e1·G_b + e2·G_a)`` (on a plane deformed in its own plane
this is the 2-D small strain; it is not zero under a finite rotation); ``"euler-almansi"``,
``e = ½(I − F₂⁻ᵀF₂⁻¹)`` with ``F₂ = Q'ᵀ[f_a f_b]`` the in-plane deformation gradient expressed in the
deformed tangent basis ``Q' = (R e1, R e2)``, ``R`` the smallest rotation that turns the reference normal
``n`` into the deformed one ``n' ∝ f_a × f_b`` (on a plane deformed in its own plane ``R = I`` and this
is the 2-D Euler-Almansi strain in the same axes).
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from enum import IntEnum
from typing import ClassVar

import numpy as np

from kernels.checks import as_points, odd_int

from ._strain import DEFAULT_STRAIN_TYPE, check_strain_type

__all__ = ["StereoStatus", "Field3D", "plane_frame", "surface_strain", "surface_strain_grid", "SurfaceStrainPlan",
           "check_grid_window",
           "grid_neighbours", "scattered_neighbours",
           "as_frame", "tangent_axis", "tangent_basis"]


class StereoStatus(IntEnum):
    """Outcome of stereo DIC for one point (int8 in results); the first failing stage is reported.

    Stages run in the order of the codes from the top: the reference subset (left image), the
    initial guess of the stereo match, the stereo match, the temporal tracking in the left and
    right images, the epipolar check, the triangulation and the correlation threshold.
    """

    OK = 0                   #: matched, tracked, epipolar-consistent, triangulated, ZNCC above threshold
    NOT_COMPUTED = 1         #: outside the ROI, or the left reference subset leaves the image / is flat
    NO_GUESS = 2             #: no feature match nearby, no converged neighbour and no epipolar-search hit
    MATCH_FAILED = 3         #: left -> right IC-GN did not converge (out of bounds, diverged, singular...)
    TRACK_LEFT_FAILED = 4    #: left reference -> left current IC-GN failed
    TRACK_RIGHT_FAILED = 5   #: right reference -> right current IC-GN failed
    EPIPOLAR_VIOLATION = 6   #: the matched pair is farther than ``epipolar_tol_px`` from its epipolar line
    TRIANGULATION_FAILED = 7 #: a triangulation status other than OK (behind a camera, degenerate rays,
    #:                          outside an image, lens model not invertible, not converged)
    LOW_ZNCC = 8             #: a match or track has ZNCC below ``zncc_min``
    IMPLAUSIBLE_WARP = 9     #: a match or track converged to a warp its partly featureless subset cannot
    #:                          support (a specimen edge; dic.correlation.acceptance)
    COMPOSED_MISMATCH = 10   #: with a moved reference: a composed track (left or right) fails the check against that
    #:                          camera's reference image (``verify_zncc``; dic.correlation.stereo_verify)


# ------------------------------------------------------------------------------------------------
# frames


def as_frame(frame) -> tuple[np.ndarray, np.ndarray]:
    """Validate an object frame ``(R_obj_left (3, 3), t_obj_left (3,))`` and return it as float64."""
    try:
        R, t = frame
    except (TypeError, ValueError):
        raise ValueError(f"a frame must be a pair (R_obj_left (3, 3), t_obj_left (3,) mm), got {frame!r}") from None
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"R_obj_left must be a finite 3x3 rotation, got shape {R.shape}")
    if np.max(np.abs(R @ R.T - np.eye(3))) > 1e-6 or np.linalg.det(R) < 0:
        raise ValueError("R_obj_left must be a proper rotation (orthonormal, det +1)")
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise ValueError(f"t_obj_left must be a finite 3-vector (mm), got shape {t.shape}")
    return R, t


def plane_frame(points, valid=None) -> tuple[np.ndarray, np.ndarray]:
    """Frame of the least-squares plane of 3-D points (left camera frame, mm).

    Returns ``(R_obj_left, t_obj_left)`` with ``x_obj = R_obj_left @ x_left + t_obj_left``: origin
    at the centroid of the points, z along the plane normal turned towards the left camera (so
    positive out-of-plane displacements move towards the cameras), x along the left camera's x
    axis projected onto the plane, y = z × x. ``points`` (N, 3); ``valid`` (N,) bool selects the
    points used (at least 3, not collinear).
    """
    P = as_points(points, ncols=3, allow_empty=True, finite=False)  # non-finite points are left out below
    m = np.all(np.isfinite(P), axis=1)
    if valid is not None:
        m &= np.asarray(valid, dtype=bool)
    P = P[m]
    if P.shape[0] < 3:
        raise ValueError(f"plane_frame needs at least 3 valid points, got {P.shape[0]}")
    c = P.mean(axis=0)
    _, s, Vt = np.linalg.svd(P - c, full_matrices=False)
    if s[1] <= 1e-9 * max(s[0], 1e-300):
        raise ValueError("plane_frame: the points are collinear; the plane is undetermined")
    n = Vt[2]
    if n @ (-c) < 0:  # towards the camera centre (origin of the left frame)
        n = -n
    x = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 1.0, 0.0]) - n[1] * n
    x /= np.linalg.norm(x)
    y = np.cross(n, x)
    R = np.stack([x, y, n])
    return R, -R @ c


# ------------------------------------------------------------------------------------------------
# neighbourhoods and strain


def check_grid_window(window, grid_shape) -> int:
    """The strain window (odd int >= 3, grid points per side) checked against a grid of ``(ny, nx)`` points.

    A window of ``2·max(ny, nx) − 1`` already reaches the whole grid from every point; a larger
    one is refused (``ValueError`` naming the largest useful window) rather than silently fitting
    one plane to the whole surface.
    """
    window = odd_int(window, "strain window", detail=" (grid points)", integral_float=True)
    ny, nx = (int(v) for v in grid_shape)
    most = max(3, 2 * max(ny, nx) - 1)
    if window > most:
        raise ValueError(f"strain window {window} (grid points per side) is larger than the {ny} x {nx} grid of points: "
                         f"a window of {most} already reaches every point of it; use a window of at most {most}")
    return window


def grid_neighbours(grid_shape, window: int) -> np.ndarray:
    """Indices (N, window²) of the ``window × window`` grid neighbours of each point of a grid.

    Points are numbered row-major over ``grid_shape = (ny, nx)``; neighbours outside the grid
    are -1. ``window`` is odd (the point itself is the centre) and at most ``2·max(ny, nx) − 1``
    (:func:`check_grid_window`).
    """
    ny, nx = (int(v) for v in grid_shape)
    window = check_grid_window(window, (ny, nx))
    h = int(window) // 2
    jj, ii = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    off = np.arange(-h, h + 1)
    dj, di = np.meshgrid(off, off, indexing="ij")
    J = jj.reshape(-1, 1) + dj.reshape(1, -1)
    I = ii.reshape(-1, 1) + di.reshape(1, -1)
    inside = (J >= 0) & (J < ny) & (I >= 0) & (I < nx)
    return np.where(inside, J * nx + I, -1)


def scattered_neighbours(points, k: int, max_distance: float = np.inf) -> np.ndarray:
    """Indices (N, k) of the k nearest points (itself included) of scattered 2-D or 3-D points; -1 beyond ``max_distance``."""
    from scipy.spatial import cKDTree

    P = np.asarray(points, dtype=np.float64)
    k = int(min(k, P.shape[0]))
    _, idx = cKDTree(P).query(P, k=k, distance_upper_bound=max_distance)
    idx = np.asarray(idx).reshape(P.shape[0], k)
    return np.where(idx >= P.shape[0], -1, idx)


def tangent_axis(normals, x_axis, y_axis=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Unit in-plane axes ``e1`` (N, 3): ``x_axis`` projected onto the planes of unit ``normals`` (N, 3).

    Where ``x_axis`` is (nearly) normal to the plane, ``y_axis`` is projected instead.
    """
    nrm = np.asarray(normals, dtype=np.float64)
    ax = np.asarray(x_axis, dtype=np.float64)
    e1 = ax[None, :] - (nrm @ ax)[:, None] * nrm
    alt = np.asarray(y_axis, dtype=np.float64)
    weak = np.linalg.norm(e1, axis=1) < 1e-6
    e1[weak] = alt - (nrm[weak] @ alt)[:, None] * nrm[weak]
    with np.errstate(invalid="ignore", divide="ignore"):
        return e1 / np.linalg.norm(e1, axis=1, keepdims=True)


def tangent_basis(normals, x_axis, y_axis=(0.0, 1.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """In-plane unit axes ``(e1, e2)``, each (N, 3), of planes with unit ``normals`` (N, 3).

    ``e1`` is ``x_axis`` projected onto the plane (``y_axis`` where ``x_axis`` is normal to it);
    ``e2 = ± n × e1``, the sign chosen so that ``e2 · y_axis >= 0`` — so in the left camera frame
    ``e2`` points down the image like ``y``, in the best-fit-plane frame along its ``y``.
    """
    nrm = np.asarray(normals, dtype=np.float64)
    e1 = tangent_axis(nrm, x_axis, y_axis)
    e2 = np.cross(nrm, e1)
    flip = (e2 @ np.asarray(y_axis, dtype=np.float64)) < 0
    e2[flip] = -e2[flip]
    return e1, e2


def _surface_components(e1, e2, nrm, ga, gb, strain_type: str):
    """``(exx, eyy, exy)`` (each (n,)) of the chosen type from the tangent basis ``e1``, ``e2``, the
    reference normal ``nrm`` and the fitted surface gradients ``ga``, ``gb`` (each (n, 3); module docstring)."""
    if strain_type == "small":
        return (np.sum(e1 * ga, axis=1), np.sum(e2 * gb, axis=1),
                0.5 * (np.sum(e1 * gb, axis=1) + np.sum(e2 * ga, axis=1)))
    fa = e1 + ga
    fb = e2 + gb
    if strain_type == "green-lagrange":
        return 0.5 * (np.sum(fa * fa, axis=1) - 1.0), 0.5 * (np.sum(fb * fb, axis=1) - 1.0), 0.5 * np.sum(fa * fb, axis=1)
    # Euler-Almansi: the deformed tangent basis is the reference one turned by the rotation n -> n'
    # (Rodrigues: R v = v c + (k × v) + k (k·v) / (1 + c), k = n × n', c = n·n')
    with np.errstate(invalid="ignore", divide="ignore"):
        n2 = np.cross(fa, fb)  # oriented as e1 x e2 is against n (e2 = ± n x e1): the deformed n' on n's side
        side = np.sign(np.sum(np.cross(e1, e2) * nrm, axis=1))[:, None]
        n2 = side * n2 / np.linalg.norm(n2, axis=1, keepdims=True)
        k = np.cross(nrm, n2)
        c = np.sum(nrm * n2, axis=1)[:, None]

        def turn(v):
            return v * c + np.cross(k, v) + k * (np.sum(k * v, axis=1)[:, None] / (1.0 + c))

        q1, q2 = turn(e1), turn(e2)
        f11, f12 = np.sum(q1 * fa, axis=1), np.sum(q1 * fb, axis=1)
        f21, f22 = np.sum(q2 * fa, axis=1), np.sum(q2 * fb, axis=1)
        b11 = f11 * f11 + f12 * f12
        b22 = f21 * f21 + f22 * f22
        b12 = f11 * f21 + f12 * f22
        det = f11 * f22 - f12 * f21
        det2 = np.where((det > 0) & (c[:, 0] > -1.0 + 1e-12), det * det, np.nan)
        return 0.5 * (1.0 - b22 / det2), 0.5 * (1.0 - b11 / det2), 0.5 * (b12 / det2)


def surface_strain(X, U, valid, neighbours, *, camera_center=(0.0, 0.0, 0.0), x_axis=(1.0, 0.0, 0.0),
                   y_axis=(0.0, 1.0, 0.0), min_neighbours: int = 6, strain_type: str = DEFAULT_STRAIN_TYPE):
    """Strain in the local tangent plane by pointwise least squares (module docstring), Green-Lagrange by default.

    Parameters
    ----------
    X : (N, 3) float64
        Reference positions (mm) in some frame.
    U : (N, 3) float64
        Displacements (mm) in the same frame.
    valid : (N,) bool
        Points that may be used (as centres and as neighbours).
    neighbours : (N, k) int
        Neighbour indices per point (-1 = none), e.g. from :func:`grid_neighbours`.
    camera_center : (3,)
        Position of the (left) camera in the same frame; normals are turned towards it.
    x_axis, y_axis : (3,)
        ``e1`` is ``x_axis`` projected onto the tangent plane, ``e2`` the perpendicular in-plane
        direction on the side of ``y_axis`` (:func:`tangent_basis`).
    min_neighbours : int
        A point needs this many valid neighbours (itself included), not all on a line.
    strain_type : "green-lagrange" | "small" | "euler-almansi"
        What ``exx``, ``eyy``, ``exy`` are (module docstring).

    Returns
    -------
    dict of (N,) float64 ``exx``, ``eyy``, ``exy`` (tensor components in ``(e1, e2)``),
    ``normal`` (N, 3), and ``strain_valid`` (N,) bool. Strains and normals are NaN exactly where
    ``strain_valid`` is False.
    """
    strain_type = check_strain_type(strain_type)
    X = np.asarray(X, dtype=np.float64)
    U = np.asarray(U, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool) & np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(U), axis=1)
    nb = np.asarray(neighbours, dtype=np.int64)
    n_pts = X.shape[0]
    if X.shape != (n_pts, 3) or U.shape != (n_pts, 3) or valid.shape != (n_pts,) or nb.ndim != 2 or nb.shape[0] != n_pts:
        raise ValueError(f"surface_strain: X, U must be (N, 3), valid (N,), neighbours (N, k); got {X.shape}, "
                         f"{U.shape}, {valid.shape}, {nb.shape}")
    out = {k: np.full(n_pts, np.nan) for k in ("exx", "eyy", "exy")}
    out["normal"] = np.full((n_pts, 3), np.nan)
    out["strain_valid"] = np.zeros(n_pts, dtype=bool)
    if n_pts == 0:
        return out
    safe = np.where(nb >= 0, nb, 0)
    w = ((nb >= 0) & valid[safe]).astype(np.float64)            # (N, k)
    w[~valid] = 0.0
    count = w.sum(axis=1)
    Xn = X[safe]                                                  # (N, k, 3)
    Un = U[safe]
    Xn = np.where(w[..., None] > 0, Xn, 0.0)
    Un = np.where(w[..., None] > 0, Un, 0.0)
    cnt = np.maximum(count, 1.0)[:, None]
    mean = (w[..., None] * Xn).sum(axis=1) / cnt
    d = (Xn - mean[:, None, :]) * w[..., None]
    scatter = np.einsum("nki,nkj->nij", d, Xn - mean[:, None, :])
    ok = valid & (count >= min_neighbours)
    normal = np.full((n_pts, 3), np.nan)
    if not np.any(ok):
        return out
    evals, evecs = np.linalg.eigh(scatter[ok])
    nrm = evecs[:, :, 0]
    # in-plane spread: the two largest eigenvalues must both be significant (not collinear)
    planar = evals[:, 1] > 1e-6 * np.maximum(evals[:, 2], 1e-300)
    to_cam = np.asarray(camera_center, dtype=np.float64) - X[ok]
    nrm = np.where((np.sum(nrm * to_cam, axis=1) < 0)[:, None], -nrm, nrm)
    e1, e2 = tangent_basis(nrm, x_axis, y_axis)
    idx = np.flatnonzero(ok)
    rel = Xn[idx] - X[idx][:, None, :]                            # about the point itself
    a = np.einsum("nki,ni->nk", rel, e1)
    b = np.einsum("nki,ni->nk", rel, e2)
    ww = w[idx]
    # weighted LS for U = c0 + ga a + gb b, per component (same design for x, y, z)
    A = np.stack([np.ones_like(a), a, b], axis=2)                 # (n, k, 3)
    AtA = np.einsum("nk,nki,nkj->nij", ww, A, A)
    AtU = np.einsum("nk,nki,nkc->nic", ww, A, Un[idx])            # (n, 3 coeffs, 3 comps)
    det = np.linalg.det(AtA)
    scale = np.einsum("nii->n", AtA) ** 3
    solvable = planar & (np.abs(det) > 1e-12 * np.maximum(scale, 1e-300))
    coef = np.full_like(AtU, np.nan)
    if np.any(solvable):
        coef[solvable] = np.linalg.solve(AtA[solvable], AtU[solvable])
    ga, gb = coef[:, 1, :], coef[:, 2, :]
    exx, eyy, exy = _surface_components(e1, e2, nrm, ga, gb, strain_type)
    good = solvable & np.isfinite(exx) & np.isfinite(eyy) & np.isfinite(exy)
    sel = idx[good]
    out["exx"][sel], out["eyy"][sel], out["exy"][sel] = exx[good], eyy[good], exy[good]
    normal[sel] = nrm[good]
    out["normal"] = normal
    out["strain_valid"][sel] = True
    return out


def surface_strain_grid(X, U, valid, grid_shape, window: int, *, camera_center=(0.0, 0.0, 0.0),
                        x_axis=(1.0, 0.0, 0.0), y_axis=(0.0, 1.0, 0.0), min_neighbours: int = 6,
                        strain_type: str = DEFAULT_STRAIN_TYPE):
    """:func:`surface_strain` for points on a regular grid with ``window × window`` neighbourhoods, in O(N).

    Same result as ``surface_strain(X, U, valid, grid_neighbours(grid_shape, window), ...)`` (to
    rounding), but the neighbourhood sums (weights, first and second moments of the positions,
    position-displacement cross moments) come from box filters over the grid instead of gathering
    ``window²`` neighbours per point: ~20x less memory traffic at 200 000 points. For the states of a
    sequence on the same reference positions use :class:`SurfaceStrainPlan` (bit for bit this).
    """
    plan = SurfaceStrainPlan(X, grid_shape, window, camera_center=camera_center, x_axis=x_axis, y_axis=y_axis,
                             min_neighbours=min_neighbours, strain_type=strain_type)
    return plan(U, valid)


class SurfaceStrainPlan:
    """:func:`surface_strain_grid` for many displacement fields on the same reference positions (a sequence).

    The positions' part - the box sums of the weights and of the first and second position moments, the
    local tangent planes (one 3x3 eigen-decomposition per point), the tangent bases and the fit's normal
    matrix - depends on ``X`` and on the valid points only; it is worked out on the first call and kept
    while the next calls have the same valid points (most states of a sequence), so a state costs the
    displacement moments (12 box filters) and a 2x2 solve per point. Bit for bit
    ``surface_strain_grid(X, U, valid, grid_shape, window, ...)`` (the same operations on the same values;
    tested); :class:`dic.StrainPlan` does the same for 2-D strain.

    Parameters
    ----------
    X : (ny*nx, 3) float64, reference positions (mm), row-major over ``grid_shape``.
    grid_shape : (ny, nx); window : odd int, grid points per side of the neighbourhood.
    camera_center, x_axis, y_axis, min_neighbours, strain_type : as :func:`surface_strain`.
    """

    def __init__(self, X, grid_shape, window: int, *, camera_center=(0.0, 0.0, 0.0), x_axis=(1.0, 0.0, 0.0),
                 y_axis=(0.0, 1.0, 0.0), min_neighbours: int = 6, strain_type: str = DEFAULT_STRAIN_TYPE):
        self.strain_type = check_strain_type(strain_type)
        self.ny, self.nx = (int(v) for v in grid_shape)
        self.X = np.asarray(X, dtype=np.float64)
        n_pts = self.ny * self.nx
        if self.X.shape != (n_pts, 3):
            raise ValueError(f"X must be (ny*nx, 3) = ({n_pts}, 3), got {self.X.shape}")
        self.window = check_grid_window(window, (self.ny, self.nx))
        self.camera_center = np.asarray(camera_center, dtype=np.float64)
        self.x_axis, self.y_axis = x_axis, y_axis
        self.min_neighbours = min_neighbours
        self._finite_x = np.all(np.isfinite(self.X), axis=1)
        self._geometry = None  # (valid mask, its geometry) of the last call
        #: calls that reused the positions' part (tests, benchmarks)
        self.reused = 0

    def _box(self, v):
        from scipy.ndimage import uniform_filter

        size = float(self.window * self.window)
        return uniform_filter(v.reshape(self.ny, self.nx), size=int(self.window), mode="constant",
                              cval=0.0).ravel() * size

    def _positions(self, valid: np.ndarray) -> dict | None:
        if self._geometry is not None and np.array_equal(self._geometry[0], valid):
            self.reused += 1
            return self._geometry[1]
        geo = None
        if np.any(valid):
            X, box = self.X, self._box
            w = valid.astype(np.float64)
            origin = X[valid].mean(axis=0)           # moments about a global origin: no cancellation at 1e3 mm
            Xc = np.where(valid[:, None], X - origin, 0.0)
            sw = box(w)
            ok = valid & (np.rint(sw) >= self.min_neighbours)
            idx = np.flatnonzero(ok)
            if idx.size:
                inv = 1.0 / sw[idx]
                mX = np.stack([box(Xc[:, i])[idx] for i in range(3)], axis=1) * inv[:, None]
                C = np.empty((idx.size, 3, 3))
                for i in range(3):
                    for j in range(i, 3):
                        C[:, i, j] = C[:, j, i] = box(Xc[:, i] * Xc[:, j])[idx] * inv - mX[:, i] * mX[:, j]
                evals, evecs = np.linalg.eigh(C)
                nrm = evecs[:, :, 0]
                planar = evals[:, 1] > 1e-6 * np.maximum(evals[:, 2], 1e-300)
                to_cam = self.camera_center - X[idx]
                nrm = np.where((np.sum(nrm * to_cam, axis=1) < 0)[:, None], -nrm, nrm)
                e1, e2 = tangent_basis(nrm, self.x_axis, self.y_axis)
                saa = np.einsum("ni,nij,nj->n", e1, C, e1)
                sab = np.einsum("ni,nij,nj->n", e1, C, e2)
                sbb = np.einsum("ni,nij,nj->n", e2, C, e2)
                det = saa * sbb - sab * sab
                solvable = planar & (det > 1e-12 * (saa + sbb) ** 2)
                geo = {"Xc": Xc, "idx": idx, "inv": inv, "mX": mX, "nrm": nrm, "e1": e1, "e2": e2, "saa": saa,
                       "sab": sab, "sbb": sbb, "det": det, "solvable": solvable}
        self._geometry = (valid.copy(), geo)
        return geo

    def __call__(self, U, valid) -> dict:
        """The strain of displacements ``U`` (N, 3) mm at the ``valid`` (N,) points: the dict of
        :func:`surface_strain`."""
        U = np.asarray(U, dtype=np.float64)
        n_pts = self.ny * self.nx
        if U.shape != (n_pts, 3):
            raise ValueError(f"X and U must be (ny*nx, 3) = ({n_pts}, 3), got {self.X.shape} and {U.shape}")
        valid = np.asarray(valid, dtype=bool) & self._finite_x & np.all(np.isfinite(U), axis=1)
        out = {k: np.full(n_pts, np.nan) for k in ("exx", "eyy", "exy")}
        out["normal"] = np.full((n_pts, 3), np.nan)
        out["strain_valid"] = np.zeros(n_pts, dtype=bool)
        geo = self._positions(valid)
        if geo is None:
            return out
        box, idx, inv, mX, Xc = self._box, geo["idx"], geo["inv"], geo["mX"], geo["Xc"]
        Uc = np.where(valid[:, None], U, 0.0)
        mU = np.stack([box(Uc[:, c])[idx] for c in range(3)], axis=1) * inv[:, None]
        CXU = np.empty((idx.size, 3, 3))                                  # [i, c] = cov(X_i, U_c)
        for i in range(3):
            for c in range(3):
                CXU[:, i, c] = box(Xc[:, i] * Uc[:, c])[idx] * inv - mX[:, i] * mU[:, c]
        e1, e2, saa, sab, sbb, det = (geo[k] for k in ("e1", "e2", "saa", "sab", "sbb", "det"))
        sat = np.einsum("ni,nic->nc", e1, CXU)
        sbt = np.einsum("ni,nic->nc", e2, CXU)
        with np.errstate(invalid="ignore", divide="ignore"):
            ga = (sbb[:, None] * sat - sab[:, None] * sbt) / det[:, None]
            gb = (saa[:, None] * sbt - sab[:, None] * sat) / det[:, None]
        exx, eyy, exy = _surface_components(e1, e2, geo["nrm"], ga, gb, self.strain_type)
        good = geo["solvable"] & np.isfinite(exx) & np.isfinite(eyy) & np.isfinite(exy)
        sel = idx[good]
        out["exx"][sel], out["eyy"][sel], out["exy"][sel] = exx[good], eyy[good], exy[good]
        out["normal"][sel] = geo["nrm"][good]
        out["strain_valid"][sel] = True
        return out


# ------------------------------------------------------------------------------------------------
# the result container

#: (N,) per-point float fields of a Field3D, in export order
SCALAR_FIELDS = ("X", "Y", "Z", "U", "V", "W", "exx", "eyy", "exy", "zncc_stereo", "zncc_left", "zncc_right",
                 "epipolar_ref_px", "epipolar_px", "reprojection_ref_px", "reprojection_px")


@dataclass
class Field3D:
    """Stereo-DIC result for one state: shape, 3-D displacement and surface strain at every point.

    All per-point arrays have length N and follow the order of ``points`` (row-major over
    ``grid_shape`` when the points form a grid). Coordinates are in mm in the frame
    ``x_frame = R_frame_left @ x_left + t_frame_left`` (identity: the left camera frame).

    Attributes
    ----------
    points : (N, 2) float64
        POIs ``(x, y)`` in the left reference image (px).
    grid_shape : (ny, nx) or None
        Set when ``points`` is a regular grid, row-major.
    X, Y, Z : (N,) float64
        Reference (undeformed) positions, mm.
    U, V, W : (N,) float64
        Displacements from the reference to the current state, mm (0 for the reference itself).
    exx, eyy, exy : (N,) float64
        Green-Lagrange surface strain in the local tangent basis ``(e1, e2)``: ``e1`` the frame's
        x axis projected onto the surface, ``e2`` perpendicular to it on the side of the frame's
        y axis (dimensionless, tensor shear). NaN exactly where ``strain_valid`` is False.
    normal : (N, 3) float64
        Unit surface normal (towards the left camera), NaN where ``strain_valid`` is False.
    zncc_stereo, zncc_left, zncc_right : (N,) float64
        ZNCC of the left -> right reference match and of the temporal tracks (1 for the reference state).
    epipolar_ref_px, epipolar_px : (N,) float64
        Distance (px, undistorted right image) of the right point from the epipolar line of the
        left point, reference and current state.
    reprojection_ref_px, reprojection_px : (N,) float64
        RMS reprojection residual of the triangulation (px), reference and current.
    status : (N,) int8
        :class:`StereoStatus`. Quantities of points whose status is not OK may be NaN.
    strain_valid : (N,) bool
    R_frame_left, t_frame_left : (3, 3), (3,)
        The frame of the coordinates.
    frame_name : str
        ``"left"`` (left camera), ``"plane"`` (best-fit plane of the reference shape) or ``"custom"``.
    index : int
        State index in a sequence (0 = reference).
    reference_index : int
        The state whose images the temporal tracks used as their reference (0: the reference pair;
        a later state with ``reference="incremental"``, ``"every:N"`` or ``"auto"`` of
        :func:`dic.sequence.stereo_sequence`). Whatever it is, every quantity is relative to the
        reference state (Lagrangian).
    reference_interpolated : (N,) bool or None
        Measured from a moved reference: the valid points whose place in that state was interpolated
        from their neighbours (not valid there; :meth:`dic.StereoCorrelation.move_reference`).
        None otherwise (and for states read back from a file, which store only their count, the
        ``reference_interpolated`` attribute).
    details : dict
        Stage-by-stage codes: ``match_status``, ``track_left_status``, ``track_right_status``
        (:class:`kernels.conventions.Status`), ``triangulation_ref_status``,
        ``triangulation_status`` (:class:`dic._triangulate.TriangulationStatus`), ``guess_source``
        (0 features, 1 neighbour propagation, 2 epipolar search, -1 none), and the matched
        image positions ``points_right_ref``, ``points_left_cur``, ``points_right_cur`` (N, 2) float64.
    """

    points: np.ndarray
    grid_shape: tuple[int, int] | None
    X: np.ndarray
    Y: np.ndarray
    Z: np.ndarray
    U: np.ndarray
    V: np.ndarray
    W: np.ndarray
    exx: np.ndarray
    eyy: np.ndarray
    exy: np.ndarray
    normal: np.ndarray
    zncc_stereo: np.ndarray
    zncc_left: np.ndarray
    zncc_right: np.ndarray
    epipolar_ref_px: np.ndarray
    epipolar_px: np.ndarray
    reprojection_ref_px: np.ndarray
    reprojection_px: np.ndarray
    status: np.ndarray
    strain_valid: np.ndarray
    R_frame_left: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_frame_left: np.ndarray = field(default_factory=lambda: np.zeros(3))
    frame_name: str = "left"
    index: int = 0
    details: dict = field(default_factory=dict)
    reference_index: int = 0
    reference_interpolated: np.ndarray | None = None
    #: what ``exx``, ``eyy``, ``exy`` are: "green-lagrange", "small" or "euler-almansi" (module docstring)
    strain_type: str = DEFAULT_STRAIN_TYPE

    #: the codes of ``status``
    status_codes: ClassVar[type] = StereoStatus

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def __repr__(self) -> str:
        n = len(self)
        ok = self.valid
        n_ok = int(np.count_nonzero(ok))
        grid = f" on a {self.grid_shape[0]} x {self.grid_shape[1]} grid" if self.grid_shape is not None else ""
        share = f" ({100.0 * n_ok / n:.1f} %)" if n else ""
        text = (f"Field3D: state {self.index}, {n} points{grid}, {n_ok} OK{share}, "
                f"strain at {int(np.count_nonzero(self.strain_valid))}, {self.frame_name} frame (mm)")
        if n_ok and self.index != 0:
            w = np.asarray(self.W)[ok]
            d = np.linalg.norm(self.uvw[ok], axis=1)
            if np.any(np.isfinite(d)):
                text += f"; |U| max {np.nanmax(d):.4g} mm, W {np.nanmin(w):.4g}..{np.nanmax(w):.4g} mm"
        return f"<{text}>"

    def to_xarray(self):
        """An :class:`xarray.Dataset` over ``point``: coordinates ``x``, ``y`` (left reference image,
        px) and ``X``, ``Y``, ``Z`` (mm); ``U``, ``V``, ``W`` (mm), ``exx``, ``eyy``, ``exy``, their
        predicted std ``sigma_X`` ... ``sigma_W`` (mm; from ``details``, NaN where not valid or not computed),
        ``normal_x|y|z``, the ZNCCs, epipolar and reprojection residuals (px), ``status``,
        ``strain_valid``, ``valid``; units and descriptions as attributes (:mod:`dic.tabular`)."""
        from .tabular import columns_3d, point_dataset

        return point_dataset(columns_3d(self), kind="stereo", status_codes=StereoStatus,
                             attrs={"title": "Specula stereo-DIC field", "state": int(self.index),
                                    "frame_name": self.frame_name, "strain_type": self.strain_type,
                                    "R_frame_left": np.asarray(self.R_frame_left, np.float64).ravel(),
                                    "t_frame_left": np.asarray(self.t_frame_left, np.float64)})

    def to_dataframe(self):
        """A :class:`pandas.DataFrame`, one row per point (index ``point``): the columns of :meth:`to_xarray`."""
        from .tabular import dataframe

        return dataframe(self.to_xarray())

    def plot(self, quantity: str = "W", image=None, **kwargs):
        """A Matplotlib Figure of one quantity (:func:`dic.plots.fields.field3d_figure`): ``Z``, ``U``,
        ``V``, ``W``, ``exx``, ``eyy``, ``exy``, ``zncc_stereo`` or ``status``, over ``image`` (the
        left reference image, optional); keywords ``vmin``, ``vmax``, ``cmap``, ``alpha``."""
        from .plots.fields import field3d_figure

        return field3d_figure(self, quantity, image, **kwargs)

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: ``status == OK``."""
        return self.status == StereoStatus.OK

    @property
    def xyz(self) -> np.ndarray:
        """(N, 3) reference positions (mm)."""
        return np.stack([self.X, self.Y, self.Z], axis=1)

    @property
    def uvw(self) -> np.ndarray:
        """(N, 3) displacements (mm)."""
        return np.stack([self.U, self.V, self.W], axis=1)

    @property
    def xyz_current(self) -> np.ndarray:
        """(N, 3) current (deformed) positions ``xyz + uvw`` (mm)."""
        return self.xyz + self.uvw

    def grid(self, name: str) -> np.ndarray:
        """A per-point field reshaped to ``grid_shape`` (``ValueError`` when the points are not a grid)."""
        if self.grid_shape is None:
            raise ValueError("this Field3D's points are not a regular grid (grid_shape is None)")
        arr = np.asarray(getattr(self, name))
        return arr.reshape(tuple(self.grid_shape) + arr.shape[1:])

    def counts(self) -> dict[str, int]:
        """Number of points per :class:`StereoStatus` name."""
        codes, counts = np.unique(self.status, return_counts=True)
        return {StereoStatus(int(c)).name: int(n) for c, n in zip(codes, counts)}

    def in_frame(self, frame, name: str = "custom") -> "Field3D":
        """The same result with coordinates in another frame.

        ``frame`` is ``"left"``, ``"plane"`` (best-fit plane of the valid reference points, see
        :func:`plane_frame`) or ``(R_obj_left, t_obj_left)``. Strains are frame-independent
        except for the in-plane axis ``e1`` (the new frame's x axis projected on the surface), so
        the tensor is rotated about each point's normal into the new basis (exact). The predicted std
        ``details["sigma_xyz_mm"]``, ``["sigma_uvw_mm"]`` are per axis of the old frame (their
        covariance is not kept), so they are dropped when the axes turn (NaN ``sigma_X`` ...
        ``sigma_W`` in the tables).
        """
        if isinstance(frame, str):
            if frame == "left":
                R, t = np.eye(3), np.zeros(3)
            elif frame == "plane":
                R, t = plane_frame(self._xyz_left(), self.valid)
            else:
                raise ValueError(f"frame must be 'left', 'plane' or (R_obj_left, t_obj_left), got {frame!r}")
            name = frame
        else:
            R, t = as_frame(frame)
        xyz_left = self._xyz_left()
        uvw_left = self.uvw @ self.R_frame_left  # R_frame_left.T @ u
        n_left = self.normal @ self.R_frame_left
        xyz = xyz_left @ R.T + t
        uvw = uvw_left @ R.T
        # express the strain tensor in the new in-plane basis: E' = Q E Q^T, Q_ij = e_i' . e_j
        e1_old, e2_old = tangent_basis(n_left, self.R_frame_left[0], self.R_frame_left[1])
        e1_new, e2_new = tangent_basis(n_left, R[0], R[1])
        q11, q12 = np.sum(e1_new * e1_old, axis=1), np.sum(e1_new * e2_old, axis=1)
        q21, q22 = np.sum(e2_new * e1_old, axis=1), np.sum(e2_new * e2_old, axis=1)
        exx, eyy, exy = self.exx, self.eyy, self.exy
        new_exx = q11 * q11 * exx + 2 * q11 * q12 * exy + q12 * q12 * eyy
        new_eyy = q21 * q21 * exx + 2 * q21 * q22 * exy + q22 * q22 * eyy
        new_exy = q11 * q21 * exx + (q11 * q22 + q12 * q21) * exy + q12 * q22 * eyy
        details = self.details
        if not np.allclose(R, self.R_frame_left, rtol=0.0, atol=1e-12):
            # only the std per axis is kept, not the covariance: it has no value along other axes
            details = {k: v for k, v in details.items() if k not in ("sigma_xyz_mm", "sigma_uvw_mm")}
        return replace(self, X=xyz[:, 0], Y=xyz[:, 1], Z=xyz[:, 2], U=uvw[:, 0], V=uvw[:, 1], W=uvw[:, 2],
                       exx=new_exx, eyy=new_eyy, exy=new_exy, normal=n_left @ R.T,
                       R_frame_left=R, t_frame_left=t, frame_name=name, details=details)

    def _xyz_left(self) -> np.ndarray:
        return (self.xyz - self.t_frame_left) @ self.R_frame_left

    def arrays(self) -> dict[str, np.ndarray]:
        """Every per-point array by name (for stores and exports; ``reference_interpolated`` is stored as its count)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)
               if isinstance(getattr(self, f.name), np.ndarray)
               and f.name not in ("R_frame_left", "t_frame_left", "reference_interpolated")}
        for k, v in self.details.items():
            if isinstance(v, np.ndarray):
                out[k] = v
        return out
