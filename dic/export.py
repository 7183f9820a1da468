"""Exports of 3-D stereo-DIC results: VTK files for ParaView (meshio).

* :func:`write_vtk` — one :class:`~dic.field3d.Field3D` as a VTK XML unstructured grid (``.vtu``):
  ``kind="grid"`` gives a quad surface over the POI grid (a quad wherever its four corners are
  valid), ``kind="points"`` a point cloud (one vertex cell per point). Only points with status
  OK are written; every per-point field goes along as point data (``displacement`` and
  ``normal`` as 3-vectors, the rest as scalars). Coordinates are the reference positions
  (``deformed=True``: reference + displacement), in mm in the field's frame.
* :func:`write_vtk_series` — a sequence of fields as one ``.vtu`` per state plus a ParaView
  collection (``.pvd``) that plays them as time steps.

PNG maps of the same fields are drawn by :func:`dic.plots.fields.write_figures`.
"""
from __future__ import annotations

import os
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from .field3d import Field3D

__all__ = ["write_vtk", "write_vtk_series"]

#: per-point scalars exported as VTK point data (besides the vectors)
_VTK_SCALARS = ("X", "Y", "Z", "U", "V", "W", "exx", "eyy", "exy", "zncc_stereo", "zncc_left", "zncc_right",
                "epipolar_ref_px", "epipolar_px", "reprojection_ref_px", "reprojection_px")

def _check_field(f) -> Field3D:
    if not isinstance(f, Field3D):
        raise ValueError(f"expected a dic.field3d.Field3D, got {type(f).__name__}")
    return f


def _mesh(f: Field3D, kind: str, deformed: bool):
    import meshio

    valid = f.valid & np.all(np.isfinite(f.xyz), axis=1)
    if deformed:
        valid &= np.all(np.isfinite(f.uvw), axis=1)
    if not np.any(valid):
        raise ValueError("the field has no valid point to export (every status is an error); "
                         f"status counts: {f.counts()}")
    keep = np.flatnonzero(valid)
    new_index = np.full(len(f), -1, dtype=np.int64)
    new_index[keep] = np.arange(keep.size)
    pts = (f.xyz_current if deformed else f.xyz)[keep]
    if kind == "points":
        cells = [("vertex", np.arange(keep.size, dtype=np.int64)[:, None])]
    elif kind == "grid":
        if f.grid_shape is None:
            raise ValueError("kind='grid' needs POIs on a regular grid (grid_shape is None); use kind='points'")
        ny, nx = f.grid_shape
        idx = np.arange(ny * nx).reshape(ny, nx)
        quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], axis=-1).reshape(-1, 4)
        quads = quads[np.all(valid[quads], axis=1)]
        quads = new_index[quads]
        cells = [("quad", quads)] if quads.size else [("vertex", np.arange(keep.size, dtype=np.int64)[:, None])]
    else:
        raise ValueError(f"kind must be 'grid' or 'points', got {kind!r}")
    data = {name: np.asarray(getattr(f, name), dtype=np.float64)[keep] for name in _VTK_SCALARS}
    data["displacement"] = f.uvw[keep]
    data["normal"] = np.nan_to_num(f.normal[keep])
    data["strain_valid"] = f.strain_valid[keep].astype(np.uint8)
    data["status"] = f.status[keep].astype(np.int32)
    data["image_x"] = f.points[keep, 0]
    data["image_y"] = f.points[keep, 1]
    return meshio.Mesh(points=pts, cells=cells, point_data=data)


def write_vtk(field: Field3D, path, *, kind: str = "grid", deformed: bool = False) -> Path:
    """Write one Field3D as a VTK file for ParaView (module docstring); returns the path.

    ``path`` ends in ``.vtu`` (XML, compressed) or ``.vtk`` (legacy). NaN strains (points with
    too few neighbours, ``strain_valid == 0``) are kept as NaN, which ParaView shows as blank.
    """
    f = _check_field(field)
    path = Path(os.fspath(path))
    if path.suffix.lower() not in (".vtu", ".vtk"):
        raise ValueError(f"VTK output must end in .vtu or .vtk, got {path.name}")
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh = _mesh(f, kind, deformed)
    mesh.write(path)
    return path


def write_vtk_series(fields, directory, *, stem: str = "stereo", kind: str = "grid", deformed: bool = False) -> Path:
    """Write a sequence of Field3D as ``<stem>_<index>.vtu`` files and a ``<stem>.pvd`` collection; returns the .pvd path.

    Each state's ``index`` is its time step in ParaView. States without any valid point are skipped.
    """
    directory = Path(os.fspath(directory))
    directory.mkdir(parents=True, exist_ok=True)
    entries = []
    for f in fields:
        f = _check_field(f)
        if not np.any(f.valid):
            continue
        name = f"{stem}_{f.index:06d}.vtu"
        write_vtk(f, directory / name, kind=kind, deformed=deformed)
        entries.append((f.index, name))
    if not entries:
        raise ValueError("no state with a valid point to export")
    lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1">', "  <Collection>"]
    for index, name in entries:
        lines.append(f'    <DataSet timestep="{index}" group="" part="0" file={quoteattr(name)}/>')
    lines += ["  </Collection>", "</VTKFile>", ""]
    pvd = directory / f"{stem}.pvd"
    pvd.write_text("\n".join(lines), encoding="utf-8")
    return pvd
