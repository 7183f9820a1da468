"""Exports of 3-D stereo-DIC results: VTK files for ParaView (meshio) and figures (matplotlib).

* :func:`write_vtk` — one :class:`~dic.field3d.Field3D` as a VTK XML unstructured grid (``.vtu``):
  ``kind="grid"`` gives a quad surface over the POI grid (a quad wherever its four corners are
  valid), ``kind="points"`` a point cloud (one vertex cell per point). Only points with status
  OK are written; every per-point field goes along as point data (``displacement`` and
  ``normal`` as 3-vectors, the rest as scalars). Coordinates are the reference positions
  (``deformed=True``: reference + displacement), in mm in the field's frame.
* :func:`write_vtk_series` — a sequence of fields as one ``.vtu`` per state plus a ParaView
  collection (``.pvd``) that plays them as time steps.
* :func:`write_figures` — PNG maps over the left reference image: depth (Z), displacements U, V,
  W, strains exx, eyy, exy, ZNCC and status.
"""
from __future__ import annotations

import os
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from .field3d import Field3D, StereoStatus

__all__ = ["write_vtk", "write_vtk_series", "write_figures", "FIGURE_QUANTITIES"]

#: per-point scalars exported as VTK point data (besides the vectors)
_VTK_SCALARS = ("X", "Y", "Z", "U", "V", "W", "exx", "eyy", "exy", "zncc_stereo", "zncc_left", "zncc_right",
                "epipolar_ref_px", "epipolar_px", "reprojection_ref_px", "reprojection_px")

#: quantity -> (label, unit, colour map) of :func:`write_figures`
FIGURE_QUANTITIES = {
    "Z": ("depth Z", "mm", "viridis"),
    "U": ("displacement U", "mm", "RdBu_r"),
    "V": ("displacement V", "mm", "RdBu_r"),
    "W": ("displacement W", "mm", "RdBu_r"),
    "exx": ("Green-Lagrange strain exx", "", "RdBu_r"),
    "eyy": ("Green-Lagrange strain eyy", "", "RdBu_r"),
    "exy": ("Green-Lagrange strain exy", "", "RdBu_r"),
    "zncc_stereo": ("ZNCC of the stereo match", "", "magma"),
    "status": ("status", "", None),
}


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


def _map(f: Field3D, values: np.ndarray):
    """Values on the POI grid (masked where not finite) and the image extent of the grid cells."""
    ny, nx = f.grid_shape
    g = np.asarray(values, dtype=np.float64).reshape(ny, nx)
    pts = f.points.reshape(ny, nx, 2)
    dx = (pts[0, -1, 0] - pts[0, 0, 0]) / max(nx - 1, 1) if nx > 1 else 1.0
    dy = (pts[-1, 0, 1] - pts[0, 0, 1]) / max(ny - 1, 1) if ny > 1 else 1.0
    extent = (pts[0, 0, 0] - dx / 2, pts[0, -1, 0] + dx / 2, pts[-1, 0, 1] + dy / 2, pts[0, 0, 1] - dy / 2)
    return np.ma.masked_invalid(g), extent


def write_figures(field: Field3D, image, directory, *, quantities=None, prefix: str = "", dpi: int = 110,
                  alpha: float = 0.75) -> list[Path]:
    """PNG maps of a Field3D over the left reference image; returns the written paths.

    Parameters
    ----------
    field : Field3D
    image : (H, W) the left reference image (grey levels), drawn underneath.
    directory : output folder (created).
    quantities : names from :data:`FIGURE_QUANTITIES` (default: all; strains and displacements are
        skipped for the reference state, where they are zero).
    prefix : file name prefix, e.g. ``"state_000003_"``.

    Only points with status OK are coloured; colour limits are the 1st-99th percentiles
    (symmetric about 0 for displacements and strains).
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm, ListedColormap

    f = _check_field(field)
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must be the (H, W) left reference image, got shape {img.shape}")
    if quantities is None:
        quantities = ["Z", "zncc_stereo", "status"] if f.index == 0 else list(FIGURE_QUANTITIES)
    unknown = [q for q in quantities if q not in FIGURE_QUANTITIES]
    if unknown:
        raise ValueError(f"unknown figure quantities {unknown}; choose from {list(FIGURE_QUANTITIES)}")
    directory = Path(os.fspath(directory))
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    valid = f.valid
    for q in quantities:
        label, unit, cmap = FIGURE_QUANTITIES[q]
        fig, ax = plt.subplots(figsize=(7.5, 7.5 * img.shape[0] / img.shape[1] + 0.6))
        ax.imshow(img, cmap="gray", interpolation="nearest")
        if q == "status":
            vals = f.status.astype(np.float64)
            names = [s.name for s in StereoStatus]
            # OK green; failures in colours without green (tab10 minus its green, then tab20b)
            tab = plt.get_cmap("tab10")
            colours = np.vstack([tab([2]), tab([7, 1, 3, 4, 5, 6, 9, 8, 0]),
                                 plt.get_cmap("tab20b")(np.arange(20))])[:len(names)]
            cm = ListedColormap(colours)
            norm = BoundaryNorm(np.arange(len(names) + 1) - 0.5, len(names))
            kw = {"cmap": cm, "norm": norm}
        else:
            vals = np.where(valid, np.asarray(getattr(f, q), dtype=np.float64), np.nan)
            fin = vals[np.isfinite(vals)]
            kw = {"cmap": cmap}
            if fin.size:
                lo, hi = np.percentile(fin, [1, 99])
                if cmap == "RdBu_r":
                    m = max(abs(lo), abs(hi), 1e-12)
                    lo, hi = -m, m
                if hi <= lo:
                    hi = lo + 1e-12
                kw.update(vmin=lo, vmax=hi)
        if f.grid_shape is not None:
            data, extent = _map(f, vals)
            im = ax.imshow(data, extent=extent, alpha=alpha, interpolation="nearest", **kw)
        else:
            fin = np.isfinite(vals)
            im = ax.scatter(f.points[fin, 0], f.points[fin, 1], c=vals[fin], s=6, alpha=alpha, **kw)
        cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
        if q == "status":
            cb.set_ticks(np.arange(len(StereoStatus)))
            cb.set_ticklabels([s.name for s in StereoStatus], fontsize=7)
        cb.set_label(f"{label} ({unit})" if unit else label)
        frame = {"left": "left camera frame", "plane": "best-fit plane frame"}.get(f.frame_name, f"{f.frame_name} frame")
        ax.set_title(f"state {f.index}: {label}" + (f" ({frame})" if q in ("Z", "U", "V", "W") else ""))
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
        fig.tight_layout()
        path = directory / f"{prefix}{q}.png"
        fig.savefig(path, dpi=dpi)
        plt.close(fig)
        written.append(path)
    return written
