"""Exports of DIC results that other tools open: CSV, MATLAB, netCDF/xarray, VTK (ParaView) and PLY.

Every export is written by the library that owns the format and starts from the one table of
:mod:`dic.tabular` (same names and units everywhere; docs/exports.md):

* :func:`to_xarray` / :func:`to_dataframe` — a field (:class:`~dic.field2d.Field2D`,
  :class:`~dic.field3d.Field3D`, a result file's frame) or a whole result file
  (:class:`~dic.store.TrackResults`, :class:`~dic.store.StereoResults`, or its path) as an xarray
  Dataset (``frame`` x ``point``, coordinates ``x``, ``y`` and for stereo ``X``, ``Y``, ``Z``,
  units and attributes) or a pandas DataFrame;
* :func:`write_csv` — one CSV file per frame (pandas);
* :func:`write_mat` — one MATLAB ``.mat`` file, a (frames x points) matrix per quantity (scipy.io);
* :func:`write_netcdf` — the xarray Dataset as netCDF-4 (xarray, engine h5netcdf);
* :func:`write_vtk` — one field as a VTK unstructured grid (meshio): ``kind="grid"`` a quad
  surface over the POI grid (a quad wherever its four corners are written), ``kind="points"`` a
  point cloud. By default only valid points are written (``invalid="drop"``); ``invalid="nan"``
  writes every point that has a position, with NaN data where it is invalid. 3-D fields: positions
  in mm in the field's frame (``deformed=True``: reference + displacement), every per-point field
  as point data (``displacement``, ``normal`` as 3-vectors). 2-D fields: positions ``(x, y, 0)``
  in px, point data ``u``, ``v``, ``displacement`` (u, v, 0), ``sigma_u``, ``sigma_v``, ``zncc``,
  ``iterations``, ``status``, ``valid`` and the strains when there are any (the uncertainty columns,
  ``sigma_u``, ``sigma_v`` px or ``sigma_X`` ... ``sigma_W`` mm, are in every export, NaN where a
  point is not valid or the field has none);
* :func:`write_vtk_series` — a sequence (2-D or 3-D) as one ``.vtu`` per frame plus a ParaView
  collection (``.pvd``): **the same points and cells at every time step**, NaN where a point is
  invalid in that step, so ParaView's filters and probes follow each point through the sequence;
* :func:`write_ply` — stereo states as PLY point clouds (x, y, z and U, V, W in mm, valid), one file
  per state;
* :func:`export_results` — any of these from a result file (``specula export``).

PNG maps of the same fields are drawn by :mod:`dic.plots.fields`.

Every export holds its output's lock while it writes (:func:`dic.store.files.output_lock`: a second
process exporting to the same file or folder, or a run writing its VTK files there, is refused
with one message naming it), reads a result file only when no run is writing it, and writes each
file whole or not at all (:func:`dic.store.files.atomic_output`: a temporary name, fsync, rename; a
full disk leaves no truncated CSV, MAT, netCDF, VTU or PVD file, and a previous file of that name
untouched).
"""
from __future__ import annotations

import os
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from kernels.conventions import Status

from .field2d import Field2D
from .field3d import SCALAR_FIELDS, Field3D
from .store import FrameResult, ResultFrames, ResultReader, StereoResults, TrackResults, read_results, read_stereo
from .store.files import atomic_output, output_lock

__all__ = ["write_vtk", "write_vtk_series", "write_pvd", "write_csv", "write_mat", "write_netcdf", "to_xarray", "to_dataframe",
           "read_any", "export_results", "restore_vtk_files", "vtk_file_complete", "write_ply", "PLY_PROPERTIES",
           "EXPORT_FORMATS", "NETCDF_ENGINE",
           "MAT_MAX_BYTES"]

#: formats of :func:`export_results` (``specula export --format``)
EXPORT_FORMATS = ("csv", "mat", "netcdf", "vtk", "ply")
#: the xarray engine of :func:`write_netcdf` (netCDF-4 on h5py, which Specula already uses)
NETCDF_ENGINE = "h5netcdf"
#: points per HDF5 chunk of a (frame, point) netCDF variable (one frame per chunk; 8 MiB of float64)
NETCDF_CHUNK_POINTS = 1 << 20
#: default ``max_bytes`` of :func:`write_mat`: the matrices a MATLAB v5 file is built from, in memory at once
MAT_MAX_BYTES = 1 << 30
#: the most bytes one variable of a MATLAB v5/v7 file can hold (MATLAB needs -v7.3 above 2 GiB)
MAT_VARIABLE_LIMIT = 2**31

#: per-point scalars of a Field3D exported as VTK point data (besides the vectors)
_VTK_SCALARS = SCALAR_FIELDS
_STRAIN_2D = ("dudx", "dudy", "dvdx", "dvdy", "exx", "eyy", "exy", "Exx", "Eyy", "Exy")
_FIELDS = (Field2D, FrameResult, Field3D)
#: point data that say where a point is (kept for invalid points in a series; the rest becomes NaN)
_POSITION_DATA = frozenset({"X", "Y", "Z", "image_x", "image_y"})
_RESULTS = (TrackResults, StereoResults)


# ------------------------------------------------------------------------------------------------
# results and tables


def read_any(source):
    """A result file's contents, whichever its kind: :class:`~dic.store.TrackResults` (2-D) or
    :class:`~dic.store.StereoResults`; ``source`` is a path or already one of them. Every frame is
    read into memory: to go through a long file one frame at a time use :class:`dic.store.ResultFrames`
    (the exports do)."""
    if isinstance(source, _RESULTS):
        return source
    if not isinstance(source, (str, os.PathLike)):
        raise ValueError("expected a result file (path), dic.store.TrackResults or dic.store.StereoResults, "
                         f"got {type(source).__name__}")
    with ResultReader(source) as r:
        kind = r.kind.name
    return read_results(source) if kind == "dic2d" else read_stereo(source)


def _tabular(obj):
    if isinstance(obj, _FIELDS) or isinstance(obj, _RESULTS):
        return obj
    if isinstance(obj, (str, os.PathLike)):
        return read_any(obj)
    raise ValueError("expected a Field2D, Field3D, a result file's frame, TrackResults, StereoResults or a result "
                     f"file path, got {type(obj).__name__}")


def to_xarray(obj):
    """An :class:`xarray.Dataset` of a field (over ``point``) or of a result file (over ``frame`` x
    ``point``); ``obj`` is a field, a results object or the path of a result file. The Dataset is in
    memory (every frame of a file); a long file is better exported with :func:`write_netcdf` (written one
    frame at a time) and opened with ``xarray.open_dataset(path, chunks={"frame": 1})``."""
    return _tabular(obj).to_xarray()


def to_dataframe(obj):
    """A :class:`pandas.DataFrame` of a field (index ``point``) or of a result file (index
    ``frame``, ``point``); ``obj`` as for :func:`to_xarray` (in memory: a long file is better written
    with :func:`write_csv`, one file per frame)."""
    return _tabular(obj).to_dataframe()


def _out_path(path, suffixes: tuple[str, ...], what: str) -> Path:
    p = Path(os.fspath(path))
    if p.suffix.lower() not in suffixes:
        raise ValueError(f"{what} output must end in {' or '.join(suffixes)}, got {p.name}")
    if p.exists() and p.is_dir():
        raise ValueError(f"{p} is a folder; give a file name ending in {' or '.join(suffixes)}")
    p.parent.mkdir(parents=True, exist_ok=True)
    return p


class _FrameTable:
    """The frame x point table of a result (the Dataset of its ``to_xarray()``), one frame at a time: the one
    reading helper of the CSV, MATLAB and netCDF exports.

    A first pass over the frames gathers the columns (:class:`dic.tabular.FrameSchema`: names, dtypes,
    the same points everywhere); :meth:`datasets` then yields each frame as a one-frame Dataset built
    exactly as ``to_xarray()`` builds that frame's row. Each frame is read from the file when it is
    reached (:class:`dic.store.ResultFrames`), so memory does not grow with the number of frames.
    """

    def __init__(self, frames: ResultFrames):
        from .field3d import StereoStatus
        from .tabular import FrameSchema

        if not frames.indices:
            raise ValueError("the result file has no finished frame to export")
        self.frames = frames
        self.kind = frames.kind
        self.status_codes = StereoStatus if self.kind == "stereo" else Status
        self.schema = FrameSchema()
        self.attrs = None
        for index, f in frames:  # first pass: the columns, one frame at a time
            if self.attrs is None:
                self.attrs = frames.table_attrs(f)
            self.schema.add(index, _frame_columns(self.kind, f))
        self.n_frames, self.n_points = len(frames.indices), self.schema.n_points

    def _coords(self, index, f) -> dict:
        paths = self.frames.frame_paths(index, f)
        if self.kind == "stereo":
            return {"left_path": [str(paths[0])], "right_path": [str(paths[1])]}
        return {"path": [str(paths[0])]}

    def rows(self):
        """Yield ``(index, row)`` per frame: ``row`` maps ``frame``, the per-frame coordinates (image
        paths) and every column of the table to its values in that frame, in the table's dtypes."""
        for index, f in self.frames:
            row = {"frame": np.int64(index)}
            row.update({k: v[0] for k, v in self._coords(index, f).items()})
            row.update(self.schema.align(index, _frame_columns(self.kind, f)))
            yield index, row

    def dataset(self, index: int, row: dict):
        """One frame's row as a Dataset (dims ``frame`` (1) x ``point``), built exactly as ``to_xarray()``
        builds the table: the names, order, dtypes, coordinates and attributes of every export."""
        from .tabular import frame_dataset

        coords = {k: [row[k]] for k in ("path", "left_path", "right_path") if k in row}
        cols = {k: v for k, v in row.items() if k != "frame" and k not in coords}
        return frame_dataset([(index, cols)], kind=self.kind, attrs=self.attrs, frame_coords=coords,
                             status_codes=self.status_codes)

    def datasets(self):
        """Yield ``(index, Dataset)`` per frame: :meth:`dataset` of each row."""
        for index, row in self.rows():
            yield index, self.dataset(index, row)

    def frame_bytes(self) -> dict[str, int]:
        """Bytes of each (frame x point) column over the whole table (bool as 1 byte, as MATLAB stores it)."""
        return {name: self.n_frames * self.n_points * max(self.schema.dtype(name).itemsize, 1)
                for name in self.schema.names if name not in ("x", "y")}


def _frame_columns(kind: str, f) -> dict:
    """The table columns of one frame of a result file (2-D FrameResult or stereo Field3D)."""
    from .tabular import columns_3d

    return columns_3d(f) if kind == "stereo" else f._columns()


def _stem(kind: str) -> str:
    return "stereo" if kind == "stereo" else "frame"


def _check_stem(stem) -> str:
    stem = str(stem)
    if not stem or os.sep in stem or "/" in stem:
        raise ValueError(f"stem must be a plain file name prefix, got {stem!r}")
    return stem


def write_csv(results, directory, *, stem: str | None = None) -> list[Path]:
    """One CSV file per frame of a result file: ``<directory>/<stem>_<index>.csv`` (index 6 digits).

    Columns: ``point`` (the row index), ``x``, ``y`` (px) (stereo: ``X``, ``Y``, ``Z`` mm), then
    every quantity of :mod:`dic.tabular` (units in docs/exports.md); ``True``/``False`` flags,
    empty cells for NaN. ``stem`` defaults to ``frame`` (2-D) or ``stereo``. Returns the paths
    (the CSV files; :func:`csv_metadata_path` names the description beside them).

    Beside the CSV files, ``<directory>/<stem>.csv-metadata.json`` describes them in the W3C "CSV on the
    Web" metadata vocabulary (a table group listing the files, one schema): each column's name, its
    description (``dc:description``: the quantity by name, e.g. "Green-Lagrange strain xx" for
    ``exx`` — the strain's type, which a CSV cell cannot carry) and its unit (``schema:unitText``), and
    the run's strain type in the group's description.
    A result file (path) is read one frame at a time (twice: the columns, then the files) and each
    CSV is written as its frame is read, so memory does not grow with the number of frames.
    For one field use ``field.to_dataframe().to_csv(path)``.
    """
    from .tabular import dataframe

    directory = Path(os.fspath(directory))
    if directory.exists() and not directory.is_dir():
        raise ValueError(f"the CSV output must be a folder, but {directory} is a file")
    stem = None if stem is None else _check_stem(stem)
    with ResultFrames(results) as frames, output_lock(directory, "CSV folder"):
        table = _FrameTable(frames)
        stem = _stem(table.kind) if stem is None else stem
        directory.mkdir(parents=True, exist_ok=True)
        written = []
        for index, ds in table.datasets():
            per_frame = [c for c in ds.coords if ds.coords[c].dims == ("frame",) and c != "frame"]
            one = ds.isel(frame=0).drop_vars(["frame", *per_frame])
            path = directory / f"{stem}_{int(index):06d}.csv"
            df = dataframe(one)
            with atomic_output(path) as tmp:  # whole or not at all
                df.to_csv(tmp)
            if not written:
                columns = _csv_columns(df, one)
            written.append(path)
        _write_csv_metadata(csv_metadata_path(directory, stem), written, columns, table.kind, table.attrs)
    return written


def csv_metadata_path(directory, stem: str) -> Path:
    """The CSV-on-the-Web metadata file :func:`write_csv` writes beside ``<stem>_<index>.csv``."""
    return Path(os.fspath(directory)) / f"{_check_stem(stem)}.csv-metadata.json"


def _csv_columns(df, ds) -> list[dict]:
    """CSVW column descriptions of a frame's DataFrame ``df`` (index ``point`` first) from the Dataset ``ds``
    it was made from: name, description (the variable's long name) and unit."""
    columns = []
    for name in [df.index.name or "point", *df.columns]:
        col = {"name": str(name), "titles": str(name)}
        var = ds[name] if name in ds.variables else None
        attrs = {} if var is None else var.attrs
        description = attrs.get("long_name") or ("the point's index in the result's point list" if name == "point"
                                                 else None)
        if description:
            col["dc:description"] = str(description)
        if attrs.get("units"):
            col["schema:unitText"] = str(attrs["units"])
        columns.append(col)
    return columns


def _write_csv_metadata(path: Path, files: list[Path], columns: list[dict], kind: str, attrs) -> None:
    """The W3C CSVW metadata (https://www.w3.org/TR/tabular-metadata/) of the CSV ``files``."""
    import json

    from ._strain import strain_type_label

    strain_type = (attrs or {}).get("strain_type")
    what = "stereo states" if kind == "stereo" else "2-D frames"
    description = f"Specula results, one CSV file per frame ({what})"
    if strain_type:
        description += f"; exx, eyy, exy are {strain_type_label(strain_type)} strains ({strain_type})"
    meta = {"@context": "http://www.w3.org/ns/csvw", "dc:description": description,
            "tables": [{"url": p.name} for p in files], "tableSchema": {"columns": columns}}
    with atomic_output(path) as tmp:
        Path(tmp).write_text(json.dumps(meta, indent=1) + "\n")


def _grid_index(x, y):
    """1-based (row, col) of each point and the grid shape, or None when the points are not a grid."""
    from ._strain import grid_layout

    try:
        index, shape, _ = grid_layout(np.column_stack([x, y]))
    except ValueError:
        return None
    return index[:, 1] + 1, index[:, 0] + 1, shape


def write_mat(results, path, *, max_bytes: int = MAT_MAX_BYTES) -> Path:
    """A MATLAB ``.mat`` file (v5, compressed; scipy.io.savemat) of a whole result file.

    Variables: ``frame`` (1 x F) frame indices; ``x``, ``y`` (1 x N) px; each quantity as an
    (F x N) matrix (row k = frame ``frame(k)``; stereo ``X``, ``Y``, ``Z`` too); flags as uint8;
    ``grid_shape`` [rows cols], ``grid_row``, ``grid_col`` (1 x N, 1-based) when the points are a
    grid (``M = nan(grid_shape); M(sub2ind(grid_shape, grid_row, grid_col)) = u(k, :)``); image
    paths per frame as cell arrays; ``units``, ``long_names`` (each quantity by name, e.g.
    ``long_names.exx`` "Green-Lagrange strain xx": the strain's type) and ``info`` (the file's
    attributes: settings, reference, rig as text, ``strain_type``) as structs.

    A v5 file is written whole, each matrix column by column (a point over every frame), so it
    cannot be streamed frame by frame: the matrices are filled one frame at a time into arrays of
    exactly their final size (no other copy of the file is held), and an export that needs more
    than ``max_bytes`` (default :data:`MAT_MAX_BYTES`) of them, or a matrix over the 2 GiB a v5/v7
    variable can hold, is refused with a ``ValueError`` before anything is written. Long files:
    :func:`write_netcdf` (MATLAB reads it with ``ncread``), :func:`write_csv` or
    :func:`write_vtk_series`, which are written one frame at a time.
    """
    from kernels.checks import positive_int

    max_bytes = positive_int(max_bytes, "max_bytes", detail=" (bytes)")
    p = _out_path(path, (".mat",), "the MATLAB")
    with output_lock(p, "MATLAB file"):
        return _write_mat(results, p, max_bytes)


def _write_mat(results, p: Path, max_bytes: int) -> Path:
    """:func:`write_mat` with the output's lock held."""
    import scipy.io

    with ResultFrames(results) as frames:
        if frames.indices:  # refused early from the first frame's columns, before the pass over the whole file
            cols = _frame_columns(frames.kind, frames.read(frames.indices[0]))
            _check_mat_size({k: len(frames) * v.nbytes for k, v in cols.items() if k not in ("x", "y")},
                            len(frames), max_bytes)
            del cols
        table = _FrameTable(frames)
        _check_mat_size(table.frame_bytes(), table.n_frames, max_bytes)
        out, units, long_names, matrices = {"frame": np.asarray(frames.indices, dtype=np.float64)}, {}, {}, {}
        for k, (index, row) in enumerate(table.rows()):
            if k == 0:  # the variables, in the order and with the units of the table (its first frame's Dataset)
                ds = table.dataset(index, row)
                for name in list(ds.coords) + list(ds.data_vars):
                    if name in ("frame", "point"):
                        continue
                    var = ds[name]
                    if "frame" not in var.dims:
                        out[name] = _mat_array(var.values)
                    else:
                        dtype = (object if var.dtype.kind in "USO" else np.uint8 if var.dtype == bool else var.dtype)
                        out[name] = matrices[name] = np.empty((table.n_frames,) + var.shape[1:], dtype=dtype)
                    unit = var.attrs.get("units")
                    if unit:
                        units[name] = unit
                    if var.attrs.get("long_name"):  # e.g. exx: "Green-Lagrange strain xx"
                        long_names[name] = var.attrs["long_name"]
                attrs = ds.attrs
                del ds
            for name, arr in matrices.items():
                arr[k] = _mat_array(np.asarray(row[name])[None])[0]
    grid = _grid_index(out["x"], out["y"])
    if grid is not None:
        out["grid_row"], out["grid_col"] = grid[0].astype(np.float64), grid[1].astype(np.float64)
        out["grid_shape"] = np.asarray(grid[2], dtype=np.float64)
    out["units"] = units
    out["long_names"] = long_names
    out["info"] = {str(k): (v if isinstance(v, str) else np.asarray(v)) for k, v in attrs.items()}
    with atomic_output(p) as tmp:  # whole or not at all
        scipy.io.savemat(tmp, out, do_compression=True, oned_as="row")
    return p


def _mat_array(arr):
    """A column as MATLAB gets it: flags as uint8, text as cells (object arrays of str)."""
    arr = np.asarray(arr)
    if arr.dtype == bool:
        return arr.astype(np.uint8)
    if arr.dtype.kind in "USO":
        return np.asarray([str(v) for v in arr.ravel()], dtype=object).reshape(arr.shape)
    return arr


def _check_mat_size(nbytes: dict[str, int], n_frames: int, max_bytes: int) -> None:
    streaming = ("export as netcdf (MATLAB reads it with ncread/ncinfo), csv or vtk instead: those are written one "
                 "frame at a time")
    big = {k: v for k, v in nbytes.items() if v >= MAT_VARIABLE_LIMIT}
    if big:
        name = max(big, key=big.get)
        raise ValueError(f"a MATLAB v5 .mat file holds at most 2 GiB per variable, and {name} over {n_frames} frames "
                         f"needs {big[name] / 2**30:.1f} GiB; {streaming}")
    total = sum(nbytes.values())
    if total > max_bytes:
        raise ValueError(f"a MATLAB v5 .mat file is written whole, and this one needs {total / 2**20:.0f} MiB of "
                         f"matrices for {n_frames} frames, over max_bytes ({max_bytes / 2**20:.0f} MiB); {streaming}, "
                         "or raise max_bytes")


def write_netcdf(results, path) -> Path:
    """The xarray Dataset of a result file (:func:`to_xarray`) as netCDF-4 (``.nc``), through
    xarray with the h5netcdf engine; ``xarray.open_dataset(path)`` reads it back (flags as booleans,
    units and attributes kept). ``results`` may also be one field.

    A result file is written one frame at a time: its first frame through xarray's ``to_netcdf``
    (which fixes every variable's encoding), with ``frame`` an unlimited dimension and each
    (frame, point) variable chunked by frame, then every other frame written into the file's
    datasets (h5py) as it is read, so memory does not grow with the number of frames.
    """
    import h5py

    if not isinstance(results, (str, os.PathLike)) and not isinstance(results, _RESULTS):
        field = _tabular(results)  # a field (or a clear error)
        p = _out_path(path, (".nc", ".nc4", ".netcdf"), "the netCDF")
        with output_lock(p, "netCDF file"), atomic_output(p) as tmp:
            field.to_xarray().to_netcdf(tmp, engine=NETCDF_ENGINE)
        return p
    p = _out_path(path, (".nc", ".nc4", ".netcdf"), "the netCDF")
    with ResultFrames(results) as frames, output_lock(p, "netCDF file"):
        table = _FrameTable(frames)
        with atomic_output(p) as tmp:  # whole or not at all (the previous file kept until the new one is)
            rows = table.rows()
            index, row = next(rows)
            ds = table.dataset(index, row)
            chunks = (1, max(1, min(table.n_points, NETCDF_CHUNK_POINTS)))
            encoding = {name: {"chunksizes": chunks} for name, var in ds.variables.items()
                        if var.dims == ("frame", "point")}
            ds.to_netcdf(tmp, engine=NETCDF_ENGINE, unlimited_dims=["frame"], encoding=encoding)
            del ds
            # the netCDF-4 variables are HDF5 datasets and `frame` is unlimited: each frame's row of a variable is
            # whole chunks, written straight to the file (a chunk cache held 220 MB more over 1000 frames)
            with h5py.File(tmp, "a", rdcc_nbytes=0) as h5:
                targets = {name: h5[name] for name in row if name in h5 and h5[name].maxshape[:1] == (None,)}
                for target in targets.values():
                    target.resize(table.n_frames, axis=0)
                for k, (_, row) in enumerate(rows, start=1):
                    for name, target in targets.items():
                        target[k] = _nc_row(row[name], target.dtype)
    return p


def _nc_row(values, dtype):
    """One frame's values encoded as xarray encodes them on disk (flags as int8, text as strings)."""
    values = np.asarray(values)
    if values.dtype.kind in "USO":
        return np.asarray(values, dtype=object)
    return values.astype(dtype, copy=False)


# ------------------------------------------------------------------------------------------------
# VTK (meshio)


def _check_field(f):
    if not isinstance(f, _FIELDS):
        raise ValueError(f"expected a dic.field3d.Field3D, a dic.field2d.Field2D or a result file's frame, "
                         f"got {type(f).__name__}")
    return f


class _Geometry:
    """Positions, validity, grid and point data of one field, for VTK."""

    def __init__(self, f, strain=None):
        if isinstance(f, Field3D):
            self.ref = f.xyz
            self.cur = f.xyz_current
            self.valid = f.valid & np.all(np.isfinite(self.ref), axis=1)
            self.lattice = (np.arange(len(f)).reshape(f.grid_shape) if f.grid_shape is not None else None)
            self.grid_hint = "grid_shape is None"
            data = {name: np.asarray(getattr(f, name), dtype=np.float64) for name in _VTK_SCALARS}
            data["displacement"] = f.uvw
            data["normal"] = np.nan_to_num(f.normal)
            data["strain_valid"] = f.strain_valid.astype(np.uint8)
            data["status"] = f.status.astype(np.int32)
            data.update(_sigma_data(f))  # sigma_X ... sigma_W (mm), NaN where not valid or not computed
            data["image_x"] = f.points[:, 0]
            data["image_y"] = f.points[:, 1]
            self.vectors_3d = True
        else:
            pts = np.asarray(f.points, dtype=np.float64)
            n = pts.shape[0]
            u = np.asarray(f.u, dtype=np.float64)
            v = np.asarray(f.v, dtype=np.float64)
            self.ref = np.column_stack([pts, np.zeros(n)])
            self.cur = self.ref + np.column_stack([u, v, np.zeros(n)])
            valid = np.ones(n, bool) if f.valid is None else np.asarray(f.valid, dtype=bool)
            self.valid = valid & np.all(np.isfinite(pts), axis=1)
            self.lattice = None
            self.grid_hint = "the points are not on a regular grid"
            try:
                from ._strain import grid_layout

                index, shape, _ = grid_layout(pts)
                lat = np.full(shape, -1, dtype=np.int64)
                lat[index[:, 1], index[:, 0]] = np.arange(n)
                self.lattice = lat
            except ValueError:
                pass
            data = {"u": u, "v": v, "displacement": np.column_stack([u, v, np.zeros(n)])}
            data.update(_sigma_data(f))  # sigma_u, sigma_v (px), NaN where not valid or not computed
            if f.zncc is not None:  # a Field2D (a result file's frame included; arrays a file lacks are None)
                data["zncc"] = np.asarray(f.zncc, dtype=np.float64)
            if f.iterations is not None:
                data["iterations"] = np.asarray(f.iterations).astype(np.int32)
            if f.status is not None:
                data["status"] = np.asarray(f.status).astype(np.int32)
            data["valid"] = valid.astype(np.uint8)
            strain = f.strain if strain is None else strain
            if strain is not None:
                get = strain.get if isinstance(strain, dict) else lambda k: getattr(strain, k)
                for name in _STRAIN_2D:
                    data[name] = np.asarray(get(name), dtype=np.float64)
                data["strain_valid"] = np.asarray(get("valid")).astype(np.uint8)
            self.vectors_3d = False
        self.data = data
        self.has_position = np.all(np.isfinite(self.ref), axis=1)


def _sigma_data(f) -> dict[str, np.ndarray]:
    """The uncertainty columns of one field as VTK point data, as in every table (:mod:`dic.tabular`):
    ``sigma_u``, ``sigma_v`` (px) of a 2-D field, ``sigma_X`` ... ``sigma_W`` (mm) of a Field3D."""
    from .tabular import SIGMA_3D, columns_2d, columns_3d

    if isinstance(f, Field3D):
        cols = columns_3d(f)
        return {name: cols[name] for name in SIGMA_3D}
    cols = columns_2d(f.points, f.u, f.v, valid=f.valid, sigma_u=getattr(f, "sigma_u", None),
                      sigma_v=getattr(f, "sigma_v", None))
    return {"sigma_u": cols["sigma_u"], "sigma_v": cols["sigma_v"]}


def _cells(geo: _Geometry, keep: np.ndarray, new_index: np.ndarray, kind: str):
    n_keep = int(np.count_nonzero(keep))
    vertices = [("vertex", np.arange(n_keep, dtype=np.int64)[:, None])]
    if kind == "points":
        return vertices
    if kind != "grid":
        raise ValueError(f"kind must be 'grid' or 'points', got {kind!r}")
    if geo.lattice is None:
        raise ValueError(f"kind='grid' needs POIs on a regular grid ({geo.grid_hint}); use kind='points'")
    idx = geo.lattice
    quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], axis=-1).reshape(-1, 4)
    quads = quads[np.all(quads >= 0, axis=1)]
    quads = quads[np.all(keep[quads], axis=1)]
    quads = new_index[quads]
    return [("quad", quads)] if quads.size else vertices


def _mesh(f, kind: str, deformed: bool, invalid: str = "drop", strain=None, keep=None, positions=None):
    """The meshio Mesh of one field. ``invalid="drop"``: valid points only; ``"nan"``: every point
    of ``keep`` (default: those with a position) at ``positions`` (default: the field's own),
    with NaN data where the point is not valid (its position data X, Y, Z, image_x, image_y kept)."""
    import meshio

    geo = _Geometry(f, strain)
    if invalid not in ("drop", "nan"):
        raise ValueError(f"invalid must be 'drop' or 'nan', got {invalid!r}")
    good = geo.valid.copy()
    if deformed:
        good &= np.all(np.isfinite(geo.cur), axis=1)
    if invalid == "drop":
        keep = good
        if not np.any(keep):
            counts = f.counts() if isinstance(f, Field3D) else f"{int(np.count_nonzero(geo.valid))} valid"
            raise ValueError("the field has no valid point to export (every status is an error); "
                             f"status counts: {counts}")
        pts_all = geo.cur if deformed else geo.ref
    else:
        keep = geo.has_position if keep is None else keep
        if not np.any(keep):
            raise ValueError("the field has no point with a position to export")
        base = geo.ref if positions is None else positions
        pts_all = np.where(good[:, None], geo.cur, base) if deformed else base
    if kind not in ("grid", "points"):
        raise ValueError(f"kind must be 'grid' or 'points', got {kind!r}")
    sel = np.flatnonzero(keep)
    new_index = np.full(keep.shape[0], -1, dtype=np.int64)
    new_index[sel] = np.arange(sel.size)
    cells = _cells(geo, keep, new_index, kind)
    data = {}
    for name, arr in geo.data.items():
        arr = np.asarray(arr)[sel]
        if invalid == "nan" and arr.dtype.kind == "f" and name not in _POSITION_DATA:
            arr = np.where((good[sel] if arr.ndim == 1 else good[sel][:, None]), arr, np.nan)
        data[name] = arr
    return meshio.Mesh(points=np.asarray(pts_all[sel], dtype=np.float64), cells=cells, point_data=data)


def write_vtk(field, path, *, kind: str = "grid", deformed: bool = False, invalid: str = "drop",
              strain=None) -> Path:
    """Write one field as a VTK file for ParaView (module docstring); returns the path.

    ``field``: a :class:`~dic.field3d.Field3D` (mm), a :class:`~dic.field2d.Field2D` or a result
    file's frame (px, z = 0). ``path`` ends in ``.vtu`` (XML, compressed) or ``.vtk`` (legacy).
    ``invalid``: ``"drop"`` writes the valid points only, ``"nan"`` every point with a position
    (NaN data where invalid). ``strain``: a :class:`dic.StrainField` to add to a Field2D.
    NaN strains (too few neighbours) stay NaN, which ParaView shows as blank.
    """
    f = _check_field(field)
    p = _out_path(path, (".vtu", ".vtk"), "VTK")
    mesh = _mesh(f, kind, deformed, invalid=invalid, strain=strain)
    with atomic_output(p) as tmp:  # whole or not at all (a full disk leaves no truncated .vtu)
        mesh.write(tmp, file_format="vtu" if p.suffix.lower() == ".vtu" else "vtk")
    return p


def write_vtk_series(fields, directory, *, stem: str | None = None, kind: str = "grid",
                     deformed: bool = False) -> Path:
    """Write a sequence of fields as ``<stem>_<index>.vtu`` files and a ``<stem>.pvd`` collection; returns the .pvd path.

    ``fields``: Field3D, Field2D or result-file frames (all of one kind, with the same points), or a
    :class:`~dic.store.TrackResults` / :class:`~dic.store.StereoResults` / result file path. Every
    step holds the same points (each point that has a position in any step, at its reference
    position; ``deformed=True`` moves the valid ones) and the same cells; data are NaN where a
    point is invalid in that step. Each field's ``index`` (a Field2D: its place in the sequence,
    from 1) is its time step in ParaView. ``stem`` defaults to ``stereo`` (3-D) or ``frame`` (2-D).
    A result file path is read one frame at a time, twice (the point set, then the files): memory
    stays flat over the file's length.
    """
    series = _field_series(fields)
    first = is3d = keep = positions = None
    for k, f in enumerate(series()):  # first pass: the kind, the points and the positions (one field at a time)
        f = _check_field(f)
        if first is None:
            is3d = isinstance(f, Field3D)
            stem = ("stereo" if is3d else "frame") if stem is None else str(stem)
            if not stem or os.sep in stem or "/" in stem:
                raise ValueError(f"stem must be a plain file name prefix, got {stem!r}")
            first = np.asarray(f.points, dtype=np.float64)
            # the one point set of the series: every point with a position in some step, at its first known one
            keep = np.zeros(first.shape[0], dtype=bool)
            positions = np.full((first.shape[0], 3), np.nan)
        elif isinstance(f, Field3D) != is3d:
            raise ValueError("a VTK series holds fields of one kind: all Field3D or all 2-D fields")
        pts = np.asarray(f.points, dtype=np.float64)
        if pts.shape != first.shape or not np.array_equal(pts, first, equal_nan=True):
            raise ValueError(f"field {k} of the series has other points than the first; a VTK series needs the same "
                             "points in every step")
        geo = _Geometry(f)
        new = geo.has_position & ~keep
        positions[new] = geo.ref[new]
        keep |= geo.has_position
        del geo
    if first is None:
        raise ValueError("no field to export")
    if not np.any(keep):
        raise ValueError("no point of the series has a position (every state failed); nothing to export")
    directory = Path(os.fspath(directory))
    if directory.exists() and not directory.is_dir():
        raise ValueError(f"the VTK output must be a folder, but {directory} is a file")
    with output_lock(directory, "VTK folder"):
        directory.mkdir(parents=True, exist_ok=True)
        entries = []
        for k, f in enumerate(series()):  # second pass: one file per field, as it is read
            index = int(f.index) if f.index is not None else k + 1  # a lone Field2D has no index
            name = f"{stem}_{index:06d}.vtu"
            with atomic_output(directory / name) as tmp:  # whole or not at all
                _mesh(f, kind, deformed, invalid="nan", keep=keep, positions=positions).write(tmp, file_format="vtu")
            entries.append((index, name))
        return write_pvd(directory, entries, stem=stem)


def vtk_file_complete(path) -> bool:
    """Whether a VTK XML file (``.vtu``, ``.pvd``) is whole: present, and its last bytes the closing
    ``</VTKFile>`` tag (a file cut short by a full disk or a kill before atomic writes is not)."""
    try:
        with open(os.fspath(path), "rb") as fh:
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - 64))
            tail = fh.read()
    except OSError:
        return False
    return tail.rstrip().endswith(b"</VTKFile>")


def restore_vtk_files(writer, directory, stem: str, indices) -> list[int]:
    """On resume: the VTK file ``<directory>/<stem>_<index>.vtu`` of every finished frame ``indices`` of the
    result ``writer`` (a :class:`dic.store.ResultWriter` or reader) checked (:func:`vtk_file_complete`)
    and rewritten from the stored frame when it is missing or cut short; temporary files left by a
    killed writer are removed. Returns the indices rewritten, ascending.

    The sequence runs call it when they resume with a VTK folder (``vtk_dir=``, ``--vtk``), so that a
    file deleted, or truncated by a full disk in an earlier run, is regenerated rather than skipped
    with its frame; the files are written as the run writes them (``invalid="nan"``; a 2-D frame with
    its stored strain).
    """
    from kernels._atomic import TEMP_MARK

    directory = Path(os.fspath(directory))
    for leftover in directory.glob(f".{stem}_*{TEMP_MARK}*"):  # a writer killed between write and rename
        try:
            leftover.unlink()
        except OSError:
            pass
    rewritten = []
    for k in sorted(int(i) for i in indices):
        path = directory / f"{stem}_{k:06d}.vtu"
        if not vtk_file_complete(path):
            write_vtk(writer.read_frame(k), path, invalid="nan")
            rewritten.append(k)
    return rewritten


def _field_series(fields):
    """A function giving a fresh iterator over the fields of a series: a result file is read one frame at a
    time (:class:`dic.store.ResultFrames`), so that a long file's export holds one frame at once."""
    if isinstance(fields, (str, os.PathLike)) or isinstance(fields, _RESULTS):
        ResultFrames(fields).close()  # a missing or foreign file is refused now, not on the first pass

        def frames():
            with ResultFrames(fields) as src:
                for _, f in src:
                    yield f
        return frames
    fields = list(fields)
    return lambda: iter(fields)


def write_pvd(directory, entries, *, stem: str) -> Path:
    """Write the ParaView collection ``<directory>/<stem>.pvd`` of ``entries`` ``[(time step, file name), ...]``
    (VTK files in ``directory``); returns its path. Rewritten as a whole (a sequence run refreshes it after
    every state, so ParaView can open the states written so far)."""
    stem = str(stem)
    if not stem or os.sep in stem or "/" in stem:
        raise ValueError(f"stem must be a plain file name prefix, got {stem!r}")
    lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1">', "  <Collection>"]
    for index, name in entries:
        lines.append(f'    <DataSet timestep="{int(index)}" group="" part="0" file={quoteattr(str(name))}/>')
    lines += ["  </Collection>", "</VTKFile>", ""]
    pvd = Path(os.fspath(directory)) / f"{stem}.pvd"
    with atomic_output(pvd) as tmp:  # a reader never sees half a file
        tmp.write_text("\n".join(lines), encoding="utf-8")
    return pvd


# ------------------------------------------------------------------------------------------------
# one entry point for the CLI


def export_results(source, fmt: str, out, *, kind: str = "grid", deformed: bool = False) -> list[Path]:
    """Export a result file (path or results object) as ``fmt`` into ``out``; returns the written paths.

    A result file is read one frame at a time for every format; csv, netcdf and vtk are written one
    frame at a time too (memory independent of the number of frames), mat is written whole and
    refused above :data:`MAT_MAX_BYTES` (:func:`write_mat`).

    ``csv``: one file per frame in the folder ``out``; ``mat``: the file ``out`` (``.mat``);
    ``netcdf``: the file ``out`` (``.nc``); ``vtk``: a series (``.vtu`` per frame + ``.pvd``) in the
    folder ``out`` (``kind``, ``deformed`` as in :func:`write_vtk_series`); ``ply`` (stereo only): one
    ``.ply`` point cloud per state in the folder ``out`` (:func:`write_ply`, valid points only, ``deformed``
    as there).
    """
    if fmt not in EXPORT_FORMATS:
        raise ValueError(f"format must be one of {', '.join(EXPORT_FORMATS)}, got {fmt!r}")
    if kind not in ("grid", "points"):
        raise ValueError(f"kind must be 'grid' or 'points', got {kind!r}")
    out = Path(os.fspath(out))
    suffixes = {"mat": (".mat",), "netcdf": (".nc", ".nc4", ".netcdf")}.get(fmt)
    if suffixes is not None and out.suffix.lower() not in suffixes:
        raise ValueError(f"a {fmt} export is one file ending in {' or '.join(suffixes)}, got {out.name}")
    if suffixes is None and out.exists() and not out.is_dir():
        raise ValueError(f"a {fmt} export is a folder of files, but {out} is a file")
    if fmt == "csv":
        return write_csv(source, out)
    if fmt == "mat":
        return [write_mat(source, out)]
    if fmt == "netcdf":
        return [write_netcdf(source, out)]
    if fmt == "ply":
        return write_ply(source, out, deformed=deformed)
    with ResultFrames(source) as frames:  # read one frame at a time, twice (the point set, then the files)
        if not frames.indices:
            raise ValueError("the result file has no finished frame to export")
    pvd = write_vtk_series(source, out, kind=kind, deformed=deformed)
    return sorted(pvd.parent.glob(f"{pvd.stem}_*.vtu")) + [pvd]


# ------------------------------------------------------------------------------------------------
# PLY point clouds (stereo)

#: vertex properties of :func:`write_ply`: (name, PLY type, numpy little-endian type)
PLY_PROPERTIES = (("x", "double", "<f8"), ("y", "double", "<f8"), ("z", "double", "<f8"),
                  ("U", "double", "<f8"), ("V", "double", "<f8"), ("W", "double", "<f8"),
                  ("valid", "uchar", "u1"), ("point", "int", "<i4"))


def _ply_vertices(f: Field3D, *, invalid: str, deformed: bool) -> np.ndarray:
    """The vertex table of one state: a structured array with the fields of :data:`PLY_PROPERTIES`."""
    has_position = np.all(np.isfinite(f.xyz), axis=1)
    valid = f.valid & has_position
    keep = valid if invalid == "drop" else has_position
    xyz = f.xyz_current if deformed else f.xyz
    if deformed and invalid == "nan":  # an invalid point keeps its reference position (it has no current one)
        xyz = np.where(valid[:, None], xyz, f.xyz)
    uvw = np.where(valid[:, None], f.uvw, np.nan)
    table = np.empty(int(np.count_nonzero(keep)), dtype=[(name, np_type) for name, _, np_type in PLY_PROPERTIES])
    for j, name in enumerate("xyz"):
        table[name] = xyz[keep, j]
    for j, name in enumerate("UVW"):
        table[name] = uvw[keep, j]
    table["valid"] = valid[keep]
    table["point"] = np.flatnonzero(keep)
    return table


def _ply_bytes(f: Field3D, table: np.ndarray, *, binary: bool) -> bytes:
    head = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
            "comment Specula stereo state " + str(int(f.index) if f.index is not None else 0),
            f"comment x y z U V W in mm, {f.frame_name} frame; point: index in the result's point grid",
            f"element vertex {len(table)}"]
    head += [f"property {ply_type} {name}" for name, ply_type, _ in PLY_PROPERTIES]
    head.append("end_header")
    header = ("\n".join(head) + "\n").encode("ascii")
    if binary:
        return header + table.tobytes()
    columns = [np.char.mod("%.17g" if np_type == "<f8" else "%d", table[name]) for name, _, np_type in PLY_PROPERTIES]
    rows = "".join(" ".join(row) + "\n" for row in zip(*columns)) if len(table) else ""
    return header + rows.encode("ascii")


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)  # a reader never sees half a file
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_ply(source, out, *, binary: bool = True, invalid: str = "drop", deformed: bool = False,
              stem: str = "stereo") -> list[Path]:
    """Write stereo states as PLY point clouds (MeshLab, CloudCompare, Open3D, ParaView); returns the paths.

    ``source``: a :class:`~dic.field3d.Field3D` (``out`` is the ``.ply`` file) or a stereo result
    (file path or :class:`~dic.store.StereoResults`; ``out`` is a folder that receives
    ``<stem>_<state:06d>.ply`` per finished state, read one state at a time).

    Each vertex has ``x``, ``y``, ``z`` (double, mm, the field's frame: the reference position, or
    reference + displacement with ``deformed=True``), the displacement ``U``, ``V``, ``W`` (double, mm),
    ``valid`` (uchar, 1 where the point's status is OK) and ``point`` (int, the point's index in the
    result's point grid, to join with the other exports). ``invalid="drop"`` (default) writes the valid
    points only; ``invalid="nan"`` every point that has a reference position, with NaN displacements and
    ``valid`` 0 where the state failed (it stays at its reference position). Points without a reference
    position (the reference stereo match failed) are never written. ``binary``: binary little-endian
    (default) or ASCII. Each file is written under a temporary name and renamed into place.
    """
    if invalid not in ("drop", "nan"):
        raise ValueError(f"invalid must be 'drop' or 'nan', got {invalid!r}")
    out = Path(os.fspath(out))
    if isinstance(source, Field3D):
        p = _out_path(out, (".ply",), "PLY")
        _write_atomic(p, _ply_bytes(source, _ply_vertices(source, invalid=invalid, deformed=deformed), binary=binary))
        return [p]
    if isinstance(source, (Field2D, FrameResult, TrackResults)):
        raise ValueError("PLY export is for stereo results (3-D points); a 2-D result has no z: use csv, vtk or netcdf")
    stem = _check_stem(stem)
    written = []
    with ResultFrames(source) as frames:
        if frames.kind != "stereo":
            raise ValueError("PLY export is for stereo result files (3-D points); a 2-D result has no z: use "
                             "--format csv, vtk or netcdf")
        if not frames.indices:
            raise ValueError("the result file has no finished state to export")
        if out.exists() and not out.is_dir():
            raise ValueError(f"a PLY export of a result file is a folder of files, but {out} is a file")
        out.mkdir(parents=True, exist_ok=True)
        for index, f in frames:
            p = out / f"{stem}_{int(index):06d}.ply"
            _write_atomic(p, _ply_bytes(f, _ply_vertices(f, invalid=invalid, deformed=deformed), binary=binary))
            written.append(p)
    return written
