"""2-D displacement fields: :class:`Field2D`, the result of 2-D tracking (:mod:`dic.track`).

Conventions (docs/conventions.md): points ``(x, y)`` in reference pixels, displacements ``(u, v)``
in pixels, parameters in :data:`kernels.conventions.PARAMS_1ST` / ``PARAMS_2ND`` order, statuses
:class:`kernels.conventions.Status`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kernels.conventions import param_names

__all__ = ["Field2D", "as_field2d"]


@dataclass
class Field2D:
    """A 2-D displacement field at POIs of the reference image.

    Attributes
    ----------
    points : (N, 2) float64
        POIs ``(x, y)`` in reference pixels.
    u, v : (N,) float64
        Displacement at each POI (px), ``params[:, 0]`` and ``params[:, 3 | 6]``.
    params : (N, 6 | 12) float64
        Shape-function parameters in ``PARAMS_1ST`` / ``PARAMS_2ND`` order.
    zncc : (N,) float64
        Zero-normalised cross-correlation of the last iteration (NaN where not computed).
    iterations : (N,) int32
    status : (N,) int32
        :class:`kernels.conventions.Status` code per POI.
    valid : (N,) bool
        ``status`` in (CONVERGED, MAX_ITERATIONS) and ``zncc >= zncc_min`` (POIs whose warp is
        implausible get status IMPLAUSIBLE_WARP and are not valid; dic.correlation.acceptance).
    subset, order : int
        Subset size (px) and shape-function order.
    step : int or None
        Grid spacing when the points come from :func:`grid` (used by :meth:`to_grid`).
    zncc_min : float
        ZNCC threshold behind ``valid``.
    sigma_u, sigma_v : (N,) float64 or None
        Predicted standard deviation of ``u``, ``v`` (px) from the IC-GN Hessian and the image
        noise, ``sqrt(2 noise_sigma^2 diag H^-1)`` (:mod:`dic.quality`, docs/dic2d.md
        "Uncertainty"); NaN where not valid.
    noise_sigma : float or None
        The grey-level noise std of each image behind ``sigma_u``/``sigma_v``.
    noise_source : str or None
        ``"given"`` (the user's ``noise_sigma``) or ``"residual"`` (estimated from the valid
        subsets' ZNSSD residuals).
    index : int or None
        The frame of a sequence this field is (:func:`dic.sequence.track_sequence`; None for a lone pair).
    reference_index : int
        The frame it was correlated against (0: the reference image); the field itself is always
        relative to the reference image at its POIs (Lagrangian).
    reference_interpolated : (N,) bool or None
        Correlated against a moved reference: the valid points whose place in it was interpolated from
        their neighbours (:mod:`dic.sequence.reference`); None otherwise.
    strain : StrainField, dict or None
        The frame's strain when a sequence computed it (a :class:`dic.StrainField`; a result
        file's frame: the stored strain as a dict), used by :meth:`to_xarray` and :meth:`plot` when
        they are given none.
    """

    points: np.ndarray
    u: np.ndarray
    v: np.ndarray
    params: np.ndarray
    zncc: np.ndarray
    iterations: np.ndarray
    status: np.ndarray
    valid: np.ndarray
    subset: int
    order: int
    step: int | None = None
    zncc_min: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)
    sigma_u: np.ndarray | None = None
    sigma_v: np.ndarray | None = None
    noise_sigma: float | None = None
    noise_source: str | None = None
    index: int | None = None
    reference_index: int = 0
    reference_interpolated: np.ndarray | None = None
    strain: Any = None

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    def __repr__(self) -> str:
        n = self.n_points
        n_valid = int(np.count_nonzero(self.valid))
        share = f" ({100.0 * n_valid / n:.1f} %)" if n else ""
        text = f"Field2D: {n} points, {n_valid} valid{share}, subset {self.subset} px, order {self.order}"
        if self.step is not None:
            text += f", step {self.step} px"
        u, v = np.asarray(self.u, dtype=np.float64), np.asarray(self.v, dtype=np.float64)
        shown = np.asarray(self.valid, dtype=bool) & np.isfinite(u) & np.isfinite(v)
        if np.any(shown):
            u, v = u[shown], v[shown]
            text += f"; valid u {u.min():.4g}..{u.max():.4g} px, v {v.min():.4g}..{v.max():.4g} px"
        return f"<{text}>"

    def _columns(self, strain=None) -> dict:
        from .tabular import columns_2d

        strain = self.strain if strain is None else strain
        return columns_2d(self.points, self.u, self.v, params=self.params, order=self.order, zncc=self.zncc,
                          iterations=self.iterations, status=self.status, valid=self.valid, strain=strain,
                          sigma_u=self.sigma_u, sigma_v=self.sigma_v)

    def to_xarray(self, strain=None):
        """An :class:`xarray.Dataset` over ``point``: coordinates ``x``, ``y`` (px); ``u``, ``v`` (px),
        the other shape-function parameters, ``sigma_u``, ``sigma_v`` (px; NaN where not valid or not
        computed), ``zncc``, ``iterations``, ``status``, ``valid`` and, with ``strain`` (a :class:`dic.StrainField`), the strain columns; units and
        descriptions as attributes (:mod:`dic.tabular`)."""
        from .tabular import point_dataset

        strain = self.strain if strain is None else strain
        strain_type = None
        if strain is not None:
            strain_type = strain.get("strain_type") if isinstance(strain, dict) else getattr(strain, "strain_type", None)
        return point_dataset(self._columns(strain), kind="dic2d",
                             attrs={"title": "Specula 2-D DIC field", "subset_px": int(self.subset),
                                    "order": int(self.order), "step_px": self.step, "zncc_min": float(self.zncc_min),
                                    "strain_type": strain_type})

    def to_dataframe(self, strain=None):
        """A :class:`pandas.DataFrame`, one row per point (index ``point``): the columns of :meth:`to_xarray`."""
        from .tabular import dataframe

        return dataframe(self.to_xarray(strain))

    def plot(self, reference=None, strain=None, **kwargs):
        """A Matplotlib Figure of the field (:func:`dic.plots.fields.field_figure`): u, v (and the
        strains when ``strain`` is given) over ``reference`` (the reference image, optional).
        Keywords go to ``field_figure`` (``components``, ``vmin``, ``vmax``, ``limits``, ``cmap``, ...)."""
        from .plots.fields import field_figure

        return field_figure(reference, self, self.strain if strain is None else strain, **kwargs)

    @property
    def param_names(self) -> tuple[str, ...]:
        return param_names(self.order)

    def _lattice(self):
        pts = self.points
        if pts.shape[0] == 0:
            raise ValueError("the field has no points")
        out = []
        for axis in (0, 1):
            c = pts[:, axis]
            lo = c.min()
            step = self.step
            if step is None:
                d = np.diff(np.unique(c))
                step = float(d.min()) if d.size else 1.0
            k = (c - lo) / step
            if not np.allclose(k, np.rint(k), atol=1e-6):
                raise ValueError("the points are not on a regular grid (give step= or use grid())")
            out.append((lo, step, np.rint(k).astype(np.int64)))
        return out

    def grid_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """``(xs, ys)``: coordinates of the grid columns and rows spanned by the points."""
        (x0, sx, kx), (y0, sy, ky) = self._lattice()
        return x0 + sx * np.arange(kx.max() + 1), y0 + sy * np.arange(ky.max() + 1)

    def to_grid(self, values="u", fill=np.nan) -> np.ndarray:
        """A per-point quantity as a 2-D map on the points' grid.

        Parameters
        ----------
        values : str or array-like (N,) / (N, k)
            A field name (``"u"``, ``"v"``, ``"zncc"``, ``"status"``, ``"valid"``, ``"iterations"``
            or a parameter name such as ``"ux"``) or an array with one row per point.
        fill : value for grid nodes without a point (ROIs); NaN by default.

        Returns
        -------
        np.ndarray (ny, nx) or (ny, nx, k); row ``i`` is ``ys[i]``, column ``j`` is ``xs[j]``
        (:meth:`grid_axes`). Invalid points keep their value: mask with ``to_grid("valid")``.
        """
        if isinstance(values, str):
            if values in ("u", "v", "zncc", "status", "valid", "iterations"):
                arr = np.asarray(getattr(self, values))
            elif values in ("sigma_u", "sigma_v") and getattr(self, values) is not None:
                arr = np.asarray(getattr(self, values))
            elif values in self.param_names:
                arr = self.params[:, self.param_names.index(values)]
            else:
                raise ValueError(f"unknown quantity {values!r}; use u, v, zncc, status, valid, iterations, sigma_u, sigma_v or "
                                 f"one of {self.param_names}")
        else:
            arr = np.asarray(values)
        if arr.shape[0] != self.n_points:
            raise ValueError(f"values must have one row per point ({self.n_points}), got shape {arr.shape}")
        (_, _, kx), (_, _, ky) = self._lattice()
        nx, ny = int(kx.max()) + 1, int(ky.max()) + 1
        if arr.dtype == bool and isinstance(fill, float) and np.isnan(fill):
            fill = False  # boolean maps (valid) are False where there is no point
        dtype = np.result_type(arr.dtype, np.min_scalar_type(fill) if not isinstance(fill, float) else np.float64)
        if arr.dtype == bool and fill is False:
            dtype = bool
        out = np.full((ny, nx) + arr.shape[1:], fill, dtype=dtype)
        out[ky, kx] = arr
        return out


def as_field2d(result) -> Field2D:
    """A tracker's result as a :class:`Field2D` (the one 2-D result type of a sequence).

    A :class:`Field2D` is returned as it is. Anything else is the result of a custom tracker
    (``make_tracker`` of :func:`dic.sequence.track_sequence`): an object with ``points`` (N, 2),
    ``u``, ``v`` (N,) px and, optionally, ``params`` (N, 6|12; default: the translation ``u``, ``v``),
    ``zncc``, ``iterations``, ``status``, ``valid`` (default: every point), ``sigma_u``, ``sigma_v``,
    ``subset``; the arrays are taken as they are (those it lacks stay None and are not written).
    """
    if isinstance(result, Field2D):
        return result
    missing = [name for name in ("points", "u", "v") if getattr(result, name, None) is None]
    if missing:
        raise ValueError(f"a tracker's result must have points, u and v; {type(result).__name__} has no "
                         f"{', '.join(missing)}")
    u, v = result.u, result.v
    n = len(u)
    params = getattr(result, "params", None)
    if params is None:  # translation only
        params = np.zeros((n, 6))
        params[:, 0], params[:, 3] = u, v
    valid = getattr(result, "valid", None)
    return Field2D(points=result.points, u=u, v=v, params=params, zncc=getattr(result, "zncc", None),
                   iterations=getattr(result, "iterations", None), status=getattr(result, "status", None),
                   valid=np.ones(n, bool) if valid is None else valid, subset=int(getattr(result, "subset", 0) or 0),
                   order=1 if np.shape(params)[1] == 6 else 2, sigma_u=getattr(result, "sigma_u", None),
                   sigma_v=getattr(result, "sigma_v", None))
