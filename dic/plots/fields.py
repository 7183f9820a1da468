"""Maps of DIC results over the reference image: 2-D fields (displacement, strain) and 3-D stereo fields.

* :func:`field_figure` / :func:`write_field_figure` — a :class:`~dic.track.Field2D` (and optionally
  its :class:`~dic.strain.StrainField`), one panel per component, on the POI grid (one cell per
  point, ``step`` px wide) over the grey reference image; invalid points are transparent.
* :func:`write_figures` — one PNG per quantity of a :class:`~dic.field3d.Field3D` over the left
  reference image: depth (Z), displacements U, V, W, strains exx, eyy, exy, ZNCC and status
  (:data:`FIGURE_QUANTITIES`).

Colour limits are the 1st-99th percentiles of the drawn values (:mod:`dic.plots._common`).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..field3d import Field3D, StereoStatus
from ._common import colormap, new_figure, padded_limits, percentile_limits, save_figure

__all__ = ["field_figure", "write_field_figure", "write_figures", "FIGURE_QUANTITIES"]

#: component of a 2-D field -> panel title of :func:`field_figure`
_LABELS = {
    "u": "u (px)", "v": "v (px)", "magnitude": "|d| (px)",
    "exx": "εxx", "eyy": "εyy", "exy": "εxy", "Exx": "Exx", "Eyy": "Eyy", "Exy": "Exy",
}

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


# -- 2-D fields ------------------------------------------------------------------------------------------
def _component_values(field, strain, name) -> np.ndarray:
    """(N,) values of one component; displacements of invalid points are NaN."""
    if name in ("u", "v"):
        vals = np.asarray(getattr(field, name), dtype=np.float64).copy()
    elif name == "magnitude":
        vals = np.hypot(np.asarray(field.u, float), np.asarray(field.v, float))
    else:
        return np.asarray(getattr(strain, name), dtype=np.float64)
    valid = np.asarray(getattr(field, "valid", np.ones(len(vals), bool)), dtype=bool)
    vals[~valid] = np.nan
    return vals


def _grid_maps(field, strain, names):
    """Per-name (rows, cols) maps and the image extent of the grid, or (None, None) if not a grid."""
    from ..strain import grid_layout

    pts = np.asarray(field.points, dtype=np.float64)
    try:
        index, shape, step = grid_layout(pts)
    except ValueError:
        return None, None
    maps = {}
    for name in names:
        grid = np.full(shape, np.nan)
        grid[index[:, 1], index[:, 0]] = _component_values(field, strain, name)
        maps[name] = grid
    x0 = pts[:, 0].min() - index[:, 0].min() * step[0]
    y0 = pts[:, 1].min() - index[:, 1].min() * step[1]
    extent = (x0 - step[0] / 2, x0 + (shape[1] - 0.5) * step[0], y0 + (shape[0] - 0.5) * step[1], y0 - step[1] / 2)
    return maps, extent


def field_figure(reference, field, strain=None, *, components=None, title: str | None = None,
                 cmap: str = "viridis", alpha: float = 0.75, panel_size: float = 4.0):
    """A Matplotlib Figure with one panel per component over the reference image.

    Parameters
    ----------
    reference : (H, W) array
        The reference image (grey levels), drawn in grey beneath the maps.
    field : Field2D-like
        ``points`` (N, 2) px, ``u``, ``v`` (N,) px, optional ``valid`` (N,) bool.
    strain : StrainField, optional
        Adds strain panels (default components ``exx``, ``eyy``, ``exy``).
    components : sequence of str, optional
        Any of ``u``, ``v``, ``magnitude``, ``exx``, ``eyy``, ``exy``, ``Exx``, ``Eyy``, ``Exy``.
        Default ``u``, ``v`` plus the small strains when ``strain`` is given.
    title : str, optional
        Figure title.
    cmap, alpha : colour map and opacity of the maps.
    panel_size : float
        Width of one panel's image in inches.

    POIs on a regular grid are drawn as cells, scattered POIs as dots.
    """
    ref = np.asarray(reference, dtype=np.float64)
    if ref.ndim != 2:
        raise ValueError(f"reference must be a 2-D grey image, got shape {ref.shape}")
    if not hasattr(field, "points") or not hasattr(field, "u") or not hasattr(field, "v"):
        raise ValueError(f"field must have points, u and v (a dic.track.Field2D), got {type(field).__name__}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha!r}")
    if not panel_size > 0:
        raise ValueError(f"panel_size must be positive (inches), got {panel_size!r}")
    if components is None:
        components = ["u", "v"] + (["exx", "eyy", "exy"] if strain is not None else [])
    components = list(components)
    if not components:
        raise ValueError("components is empty; name at least one of " + ", ".join(_LABELS))
    for c in components:
        if c not in _LABELS:
            raise ValueError(f"unknown component {c!r}; choose from {', '.join(_LABELS)}")
        if c not in ("u", "v", "magnitude") and strain is None:
            raise ValueError(f"component {c!r} needs a strain field (strain=dic.strain.strain(field))")
    maps, extent = _grid_maps(field, strain, components)
    n = len(components)
    ncols = min(n, 3)
    nrows = -(-n // ncols)
    H, W = ref.shape
    aspect = H / W
    fig = new_figure((panel_size * ncols * 1.25, (panel_size * aspect + 0.7) * nrows + 0.5))
    fig.subplots_adjust(left=0.06, right=0.97, bottom=0.08, top=0.9, wspace=0.35, hspace=0.35)
    pts = np.asarray(field.points, dtype=np.float64)
    for k, name in enumerate(components):
        ax = fig.add_subplot(nrows, ncols, k + 1)
        ax.imshow(ref, cmap="gray", extent=(-0.5, W - 0.5, H - 0.5, -0.5), interpolation="nearest")
        if maps is not None:
            vmin, vmax = padded_limits(maps[name])
            im = ax.imshow(maps[name], extent=extent, cmap=cmap, vmin=vmin, vmax=vmax, alpha=alpha,
                           interpolation="nearest")
        else:  # scattered points: colour the points themselves (invalid ones included, as drawn before)
            if name in ("u", "v"):
                vals = np.asarray(getattr(field, name), float)
            elif name == "magnitude":
                vals = np.hypot(np.asarray(field.u, float), np.asarray(field.v, float))
            else:
                vals = np.asarray(getattr(strain, name), float)
            vmin, vmax = padded_limits(vals)
            im = ax.scatter(pts[:, 0], pts[:, 1], c=vals, s=4, cmap=cmap, vmin=vmin, vmax=vmax)
        ax.set_xlim(-0.5, W - 0.5)
        ax.set_ylim(H - 0.5, -0.5)
        ax.set_title(_LABELS[name])
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
        cb = fig.colorbar(im, ax=ax, shrink=0.85)
        cb.formatter.set_useOffset(False)
        cb.update_ticks()
    if title:
        fig.suptitle(title)
    return fig


def write_field_figure(path, reference, field, strain=None, *, dpi: int = 110, **kwargs) -> Path:
    """Draw :func:`field_figure` and save it (format from the suffix, e.g. ``.png``, ``.pdf``); returns the path."""
    fig = field_figure(reference, field, strain, **kwargs)
    return save_figure(fig, path, dpi=dpi)


# -- 3-D (stereo) fields ---------------------------------------------------------------------------------
def _check_field3d(f) -> Field3D:
    if not isinstance(f, Field3D):
        raise ValueError(f"expected a dic.field3d.Field3D, got {type(f).__name__}")
    return f


def _map(f: Field3D, values: np.ndarray):
    """Values on the POI grid (masked where not finite) and the image extent of the grid cells."""
    ny, nx = f.grid_shape
    g = np.asarray(values, dtype=np.float64).reshape(ny, nx)
    pts = f.points.reshape(ny, nx, 2)
    dx = (pts[0, -1, 0] - pts[0, 0, 0]) / max(nx - 1, 1) if nx > 1 else 1.0
    dy = (pts[-1, 0, 1] - pts[0, 0, 1]) / max(ny - 1, 1) if ny > 1 else 1.0
    extent = (pts[0, 0, 0] - dx / 2, pts[0, -1, 0] + dx / 2, pts[-1, 0, 1] + dy / 2, pts[0, 0, 1] - dy / 2)
    return np.ma.masked_invalid(g), extent


def _status_colours(n: int):
    """Status colour map and norm: OK green; failures in colours without green (tab10 minus its green,
    then tab20b when there are more than ten statuses)."""
    from matplotlib.colors import BoundaryNorm, ListedColormap

    tab10 = colormap("tab10")
    colours = np.vstack([tab10([2]), tab10([7, 1, 3, 4, 5, 6, 9, 8, 0]), colormap("tab20b")(np.arange(20))])[:n]
    return ListedColormap(colours), BoundaryNorm(np.arange(n + 1) - 0.5, n)


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
    prefix : file name prefix, e.g. ``"state_000003_"``; files are ``<prefix><quantity>.png``.
    dpi, alpha : resolution of the PNGs and opacity of the maps.

    Only points with status OK are coloured; colour limits are the 1st-99th percentiles
    (symmetric about 0 for displacements and strains).
    """
    f = _check_field3d(field)
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must be the (H, W) left reference image, got shape {img.shape}")
    if quantities is None:
        quantities = ["Z", "zncc_stereo", "status"] if f.index == 0 else list(FIGURE_QUANTITIES)
    unknown = [q for q in quantities if q not in FIGURE_QUANTITIES]
    if unknown:
        raise ValueError(f"unknown figure quantities {unknown}; choose from {list(FIGURE_QUANTITIES)}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha!r}")
    directory = Path(os.fspath(directory))
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    valid = f.valid
    names = [s.name for s in StereoStatus]
    for q in quantities:
        label, unit, cmap = FIGURE_QUANTITIES[q]
        fig = new_figure((7.5, 7.5 * img.shape[0] / img.shape[1] + 0.6))
        ax = fig.subplots()
        ax.imshow(img, cmap="gray", interpolation="nearest")
        if q == "status":
            vals = f.status.astype(np.float64)
            cm, norm = _status_colours(len(names))
            kw = {"cmap": cm, "norm": norm}
        else:
            vals = np.where(valid, np.asarray(getattr(f, q), dtype=np.float64), np.nan)
            kw = {"cmap": cmap}
            limits = percentile_limits(vals, symmetric=cmap == "RdBu_r")
            if limits is not None:
                kw.update(vmin=limits[0], vmax=limits[1])
        if f.grid_shape is not None:
            data, extent = _map(f, vals)
            im = ax.imshow(data, extent=extent, alpha=alpha, interpolation="nearest", **kw)
        else:
            fin = np.isfinite(vals)
            im = ax.scatter(f.points[fin, 0], f.points[fin, 1], c=vals[fin], s=6, alpha=alpha, **kw)
        cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
        if q == "status":
            cb.set_ticks(np.arange(len(names)))
            cb.set_ticklabels(names, fontsize=7)
        cb.set_label(f"{label} ({unit})" if unit else label)
        frame = {"left": "left camera frame", "plane": "best-fit plane frame"}.get(f.frame_name, f"{f.frame_name} frame")
        ax.set_title(f"state {f.index}: {label}" + (f" ({frame})" if q in ("Z", "U", "V", "W") else ""))
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
        fig.tight_layout()
        written.append(save_figure(fig, directory / f"{prefix}{q}.png", dpi=dpi))
    return written
