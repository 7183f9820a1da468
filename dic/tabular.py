"""Tables of DIC results: per-point columns with units, as pandas DataFrames and xarray Datasets.

The one place that turns results into tables. Each result type builds its columns here and the
exports of :mod:`dic.export` (CSV, MATLAB, netCDF) are written from these tables, so a quantity has
the same name and unit everywhere:

* :meth:`dic.field2d.Field2D.to_dataframe` / ``to_xarray`` and the 2-D result file
  (:meth:`dic.store.TrackResults.to_xarray`): ``x``, ``y`` (px), ``u``, ``v`` (px), the other
  shape-function parameters (``ux``, ``uy``, ...), ``zncc``, ``iterations``, ``status``, ``valid``
  and, with strain, ``dudx`` ... ``Exy`` and ``strain_valid``;
* :meth:`dic.field3d.Field3D.to_dataframe` / ``to_xarray`` and the stereo result file
  (:meth:`dic.store.StereoResults.to_xarray`): ``x``, ``y`` (left reference image, px), ``X``,
  ``Y``, ``Z``, ``U``, ``V``, ``W`` (mm), ``exx``, ``eyy``, ``exy``, ``normal_x|y|z``, the ZNCCs,
  epipolar and reprojection residuals (px), ``status``, ``strain_valid`` and ``valid``.

A single field is a table over ``point``; a result file over ``frame`` x ``point`` (every frame has
the same points; a state of a stereo file is a frame). pandas and xarray are imported on first use.
"""
from __future__ import annotations

import json

import numpy as np

from kernels.conventions import Status, param_names

__all__ = ["UNITS", "LONG_NAMES", "SIGMA_3D", "columns_2d", "columns_3d", "point_dataset", "frame_dataset", "FrameSchema",
           "dataframe", "clean_attrs"]

#: unit of each column ("1": dimensionless; "" for codes and flags)
UNITS = {
    "x": "px", "y": "px", "u": "px", "v": "px",
    "ux": "1", "uy": "1", "vx": "1", "vy": "1",
    "uxx": "1/px", "uxy": "1/px", "uyy": "1/px", "vxx": "1/px", "vxy": "1/px", "vyy": "1/px",
    "zncc": "1", "iterations": "1", "status": "", "valid": "",
    "dudx": "1", "dudy": "1", "dvdx": "1", "dvdy": "1",
    "exx": "1", "eyy": "1", "exy": "1", "Exx": "1", "Eyy": "1", "Exy": "1", "strain_valid": "",
    "X": "mm", "Y": "mm", "Z": "mm", "U": "mm", "V": "mm", "W": "mm",
    "normal_x": "1", "normal_y": "1", "normal_z": "1",
    "zncc_stereo": "1", "zncc_left": "1", "zncc_right": "1",
    "epipolar_ref_px": "px", "epipolar_px": "px", "reprojection_ref_px": "px", "reprojection_px": "px",
    "sigma_u": "px", "sigma_v": "px",
    "sigma_X": "mm", "sigma_Y": "mm", "sigma_Z": "mm", "sigma_U": "mm", "sigma_V": "mm", "sigma_W": "mm",
}

#: description of each column (netCDF ``long_name``)
LONG_NAMES = {
    "x": "reference position x (right)", "y": "reference position y (down)",
    "u": "displacement along x", "v": "displacement along y",
    "zncc": "zero-normalised cross-correlation", "iterations": "IC-GN iterations",
    "status": "status code", "valid": "valid point",
    "dudx": "displacement gradient du/dx", "dudy": "displacement gradient du/dy",
    "dvdx": "displacement gradient dv/dx", "dvdy": "displacement gradient dv/dy",
    "exx": "strain xx", "eyy": "strain yy", "exy": "strain xy (tensor shear)",
    "Exx": "Green-Lagrange strain xx", "Eyy": "Green-Lagrange strain yy",
    "Exy": "Green-Lagrange strain xy (tensor shear)", "strain_valid": "valid strain",
    "X": "reference position X", "Y": "reference position Y", "Z": "reference position Z",
    "U": "displacement U", "V": "displacement V", "W": "displacement W",
    "normal_x": "surface normal x", "normal_y": "surface normal y", "normal_z": "surface normal z",
    "zncc_stereo": "ZNCC of the stereo match", "zncc_left": "ZNCC of the left track",
    "zncc_right": "ZNCC of the right track",
    "epipolar_ref_px": "epipolar distance, reference", "epipolar_px": "epipolar distance, current",
    "reprojection_ref_px": "RMS reprojection residual, reference",
    "reprojection_px": "RMS reprojection residual, current",
    "sigma_u": "predicted standard deviation of u", "sigma_v": "predicted standard deviation of v",
    "sigma_X": "predicted standard deviation of X", "sigma_Y": "predicted standard deviation of Y",
    "sigma_Z": "predicted standard deviation of Z", "sigma_U": "predicted standard deviation of U",
    "sigma_V": "predicted standard deviation of V", "sigma_W": "predicted standard deviation of W",
}

_STRAIN_2D = ("dudx", "dudy", "dvdx", "dvdy", "exx", "eyy", "exy", "Exx", "Eyy", "Exy")
_SCALARS_3D = ("X", "Y", "Z", "U", "V", "W", "exx", "eyy", "exy")
#: the uncertainty columns of a stereo field and the Field3D.details array each is a column of (N, 3) mm
SIGMA_3D = {"sigma_X": ("sigma_xyz_mm", 0), "sigma_Y": ("sigma_xyz_mm", 1), "sigma_Z": ("sigma_xyz_mm", 2),
            "sigma_U": ("sigma_uvw_mm", 0), "sigma_V": ("sigma_uvw_mm", 1), "sigma_W": ("sigma_uvw_mm", 2)}
_QUALITY_3D = ("zncc_stereo", "zncc_left", "zncc_right", "epipolar_ref_px", "epipolar_px", "reprojection_ref_px",
               "reprojection_px")


def _strain_get(strain, name):
    if isinstance(strain, dict):
        return strain.get(name)
    return getattr(strain, name, None)


def columns_2d(points, u, v, *, params=None, order=None, zncc=None, iterations=None, status=None, valid=None,
               strain=None, sigma_u=None, sigma_v=None) -> dict[str, np.ndarray]:
    """Per-point columns of a 2-D field (any of the optional arrays may be None).

    ``strain`` is a :class:`dic.StrainField` or the strain dict of a result file's frame.
    ``sigma_u``, ``sigma_v`` (N,) px: the predicted displacement std (:mod:`dic.quality`); the two
    columns are always there, NaN where a point is not valid and everywhere when the field has none
    (a field built without them, a file written before they were stored).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must be (N, 2) px, got shape {pts.shape}")
    n = pts.shape[0]
    cols = {"x": pts[:, 0], "y": pts[:, 1], "u": np.asarray(u, np.float64), "v": np.asarray(v, np.float64)}
    if params is not None:
        p = np.asarray(params, np.float64)
        if order is None:
            order = {6: 1, 12: 2}.get(p.shape[1] if p.ndim == 2 else -1)
            if order is None:
                raise ValueError(f"params must be (N, 6) or (N, 12), got shape {p.shape}")
        for k, name in enumerate(param_names(order)):
            if name not in ("u", "v"):
                cols[name] = p[:, k]
    usable = None if valid is None else np.asarray(valid).astype(bool)
    for name, arr in (("sigma_u", sigma_u), ("sigma_v", sigma_v)):
        if arr is None:
            cols[name] = np.full(n, np.nan)
        else:
            arr = np.asarray(arr, np.float64)
            cols[name] = arr if usable is None or usable.shape != arr.shape else np.where(usable, arr, np.nan)
    for name, arr, dtype in (("zncc", zncc, np.float64), ("iterations", iterations, np.int32),
                             ("status", status, np.int8), ("valid", valid, bool)):
        if arr is not None:
            cols[name] = np.asarray(arr).astype(dtype)
    if strain is not None:
        for name in _STRAIN_2D:
            cols[name] = np.asarray(_strain_get(strain, name), np.float64)
        cols["strain_valid"] = np.asarray(_strain_get(strain, "valid")).astype(bool)
    for name, arr in cols.items():
        if arr.shape != (n,):
            raise ValueError(f"{name} must have one value per point ({n}), got shape {arr.shape}")
    return cols


def columns_3d(field) -> dict[str, np.ndarray]:
    """Per-point columns of a :class:`dic.field3d.Field3D` (its stage-by-stage details are left out, but
    for the predicted std of the positions and displacements: ``sigma_X`` ... ``sigma_W`` (mm), the
    columns of ``details["sigma_xyz_mm"]`` and ``details["sigma_uvw_mm"]``, always there, NaN where
    a point is not valid and everywhere when the field has none)."""
    pts = np.asarray(field.points, dtype=np.float64)
    n = pts.shape[0]
    cols = {"x": pts[:, 0], "y": pts[:, 1]}
    for name in _SCALARS_3D:
        cols[name] = np.asarray(getattr(field, name), np.float64)
    valid = np.asarray(field.valid).astype(bool)
    details = getattr(field, "details", None) or {}
    for name, (key, k) in SIGMA_3D.items():
        arr = details.get(key)
        if arr is None:
            cols[name] = np.full(n, np.nan)
            continue
        arr = np.asarray(arr, np.float64)
        if arr.shape != (n, 3):
            raise ValueError(f"details[{key!r}] must be ({n}, 3) mm, got shape {arr.shape}")
        cols[name] = np.where(valid, arr[:, k], np.nan)
    normal = np.asarray(field.normal, np.float64).reshape(-1, 3)
    for k, axis in enumerate("xyz"):
        cols[f"normal_{axis}"] = normal[:, k]
    for name in _QUALITY_3D:
        cols[name] = np.asarray(getattr(field, name), np.float64)
    cols["status"] = np.asarray(field.status).astype(np.int8)
    cols["strain_valid"] = np.asarray(field.strain_valid).astype(bool)
    cols["valid"] = valid
    for name, arr in cols.items():
        if arr.shape != (n,):
            raise ValueError(f"{name} must have one value per point ({n}), got shape {arr.shape}")
    return cols


def _status_attrs(codes) -> dict:
    return {"flag_values": np.array([int(c) for c in codes], dtype=np.int8),
            "flag_meanings": " ".join(c.name for c in codes)}


_TYPED = {"exx": "xx", "eyy": "yy", "exy": "xy (tensor shear)"}


def _var_attrs(name: str, codes, strain_type: str | None = None) -> dict:
    attrs = {}
    if name in LONG_NAMES:
        attrs["long_name"] = LONG_NAMES[name]
    if name in _TYPED and strain_type:  # the strain's type by name (dic._strain.STRAIN_TYPES)
        from ._strain import strain_type_label

        attrs["long_name"] = f"{strain_type_label(strain_type)} strain {_TYPED[name]}"
        attrs["strain_type"] = strain_type
    if UNITS.get(name):
        attrs["units"] = UNITS[name]
    if name == "status":
        attrs.update(_status_attrs(codes))
    return attrs


def _coord_names(kind: str) -> tuple[str, ...]:
    return ("x", "y", "X", "Y", "Z") if kind == "stereo" else ("x", "y")


def clean_attrs(attrs: dict) -> dict:
    """Dataset attributes that netCDF can hold: None dropped, dicts/lists of mixed types as JSON text."""
    out = {}
    for k, v in attrs.items():
        if v is None:
            continue
        if isinstance(v, (dict, list, tuple)) and not (isinstance(v, (list, tuple)) and v
                                                       and all(isinstance(e, (int, float)) for e in v)):
            v = json.dumps(v, sort_keys=True, default=str)
        elif isinstance(v, bool):
            v = int(v)
        out[str(k)] = v
    return out


def point_dataset(cols: dict[str, np.ndarray], *, kind: str, attrs: dict | None = None, status_codes=Status):
    """An xarray Dataset over ``point`` from the columns of one field (coordinates x, y; X, Y, Z for stereo).

    ``status_codes``: the IntEnum of the ``status`` column (its ``flag_values``, ``flag_meanings``).
    """
    import xarray as xr

    n = len(cols["x"])
    coords = {"point": ("point", np.arange(n))}
    data = {}
    strain_type = (attrs or {}).get("strain_type")
    for name, arr in cols.items():
        target = coords if name in _coord_names(kind) else data
        target[name] = ("point", arr, _var_attrs(name, status_codes, strain_type))
    return xr.Dataset(data, coords=coords, attrs=clean_attrs(attrs or {}))


def frame_dataset(frames: list[tuple[int, dict[str, np.ndarray]]], *, kind: str, attrs: dict | None = None,
                  frame_coords: dict | None = None, status_codes=Status):
    """An xarray Dataset over ``frame`` x ``point`` from ``[(index, columns), ...]`` of one result file.

    Every frame must have the same points (``x``, ``y``); the reference position coordinates of a
    stereo file (``X``, ``Y``, ``Z``) are (frame, point). ``frame_coords`` adds per-frame
    coordinates (e.g. the image paths). A column missing from some frames (strain) is NaN (False
    for flags) there.
    """
    import xarray as xr

    if not frames:
        raise ValueError("the result file has no finished frame to export")
    first = frames[0][1]
    n = len(first["x"])
    names: list[str] = []
    for _, cols in frames:
        for name in cols:
            if name not in names:
                names.append(name)
    for index, cols in frames:
        same = (len(cols["x"]) == n and np.array_equal(cols["x"], first["x"], equal_nan=True)
                and np.array_equal(cols["y"], first["y"], equal_nan=True))
        if not same:
            raise ValueError(f"frame {index} has other points than frame {frames[0][0]}; a frame x point table "
                             "needs the same points in every frame (export the frames one by one)")
    coords = {"frame": ("frame", np.array([i for i, _ in frames], dtype=np.int64)),
              "point": ("point", np.arange(n))}
    coords["x"] = ("point", first["x"], _var_attrs("x", status_codes))
    coords["y"] = ("point", first["y"], _var_attrs("y", status_codes))
    data = {}
    for name in names:
        if name in ("x", "y"):
            continue
        like = next(cols[name] for _, cols in frames if name in cols)
        rows = []
        for _, cols in frames:
            if name in cols:
                rows.append(cols[name])
            else:
                rows.append(np.zeros(n, bool) if like.dtype == bool else np.full(n, np.nan))
        stacked = np.stack(rows)
        if stacked.dtype != like.dtype and like.dtype != bool:
            stacked = stacked.astype(np.result_type(like.dtype, np.float64))
        target = coords if name in _coord_names(kind) else data
        target[name] = (("frame", "point"), stacked, _var_attrs(name, status_codes, (attrs or {}).get("strain_type")))
    for name, values in (frame_coords or {}).items():
        coords[name] = ("frame", np.asarray(values))
    return xr.Dataset(data, coords=coords, attrs=clean_attrs(attrs or {}))


class FrameSchema:
    """The columns of a frame x point table gathered one frame at a time, so that a long result file is
    tabulated (exported) frame by frame with the table :func:`frame_dataset` would build from all of
    its frames at once: the same column names in the same order, the same dtypes, and the same fill
    (NaN, False for flags) where a frame lacks a column (e.g. strain).

    :meth:`add` every frame's columns (first pass; only names, dtypes and the points are kept), then
    :meth:`align` each frame's columns to the table (second pass).
    """

    def __init__(self):
        self.names: list[str] = []
        self._like: dict[str, np.dtype] = {}
        self._present: dict[str, int] = {}
        self.n_frames = 0
        self._first = None  # (index, x, y) of the first frame

    def add(self, index: int, cols: dict[str, np.ndarray]) -> None:
        """Record one frame's columns; a frame with other points than the first is refused."""
        if self._first is None:
            self._first = (index, np.array(cols["x"]), np.array(cols["y"]))
        self._check_points(index, cols)
        for name, arr in cols.items():
            if name not in self._like:
                self.names.append(name)
                self._like[name] = np.asarray(arr).dtype
            self._present[name] = self._present.get(name, 0) + 1
        self.n_frames += 1

    def _check_points(self, index, cols) -> None:
        first_index, x, y = self._first
        same = (len(cols["x"]) == len(x) and np.array_equal(cols["x"], x, equal_nan=True)
                and np.array_equal(cols["y"], y, equal_nan=True))
        if not same:
            raise ValueError(f"frame {index} has other points than frame {first_index}; a frame x point table "
                             "needs the same points in every frame (export the frames one by one)")

    @property
    def n_points(self) -> int:
        return len(self._first[1]) if self._first is not None else 0

    def dtype(self, name: str) -> np.dtype:
        """The column's dtype in the table: its own, or float (NaN fill) where some frame lacks it."""
        like = self._like[name]
        if self._present[name] < self.n_frames and like.kind != "b":
            return np.result_type(like, np.float64)
        return like

    def align(self, index: int, cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """One frame's columns in the table's order and dtypes, with the fill where it lacks a column."""
        if self._first is None:
            raise ValueError("the table has no frame (add the frames first)")
        self._check_points(index, cols)
        out = {}
        for name in self.names:
            dtype = self.dtype(name)
            if name in cols:
                out[name] = np.asarray(cols[name]).astype(dtype, copy=False)
            else:
                out[name] = np.zeros(self.n_points, bool) if dtype.kind == "b" else np.full(self.n_points, np.nan, dtype)
        return out


def dataframe(dataset):
    """The Dataset as a pandas DataFrame: index ``point`` (one field) or (``frame``, ``point``); the
    coordinates x, y (X, Y, Z) first, then the quantities. A per-frame text coordinate (the image
    ``path``, stereo ``left_path``/``right_path``) is repeated on every row: it is a pandas categorical
    (one small code per row, each text once) instead of one Python string per row, which took 113 of
    the 246 MB of a long file's table."""
    import pandas as pd

    df = dataset.to_dataframe()
    for name, coord in dataset.coords.items():
        if coord.dims == ("frame",) and name in df.columns and not pd.api.types.is_numeric_dtype(df[name]):
            df[name] = pd.Categorical(df[name])
    first = [c for c in ("x", "y", "X", "Y", "Z") if c in df.columns]
    rest = [c for c in df.columns if c not in first]
    df = df[first + rest]
    if dataset.attrs.get("strain_type"):  # what exx, eyy, exy are (the columns' own attributes stay in xarray)
        df.attrs["strain_type"] = dataset.attrs["strain_type"]
    return df
