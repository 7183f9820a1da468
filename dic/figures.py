"""Figures of 2-D DIC results: displacement and strain maps over the reference image.

Uses Matplotlib's object API with the Agg canvas (no pyplot, no global backend change), so it
works headless and from threads. Maps are drawn on the POI grid (one cell per point, ``step`` px
wide) over the grey reference image; invalid points are transparent.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["field_figure", "write_field_figure"]

_LABELS = {
    "u": "u (px)", "v": "v (px)", "magnitude": "|d| (px)",
    "exx": "εxx", "eyy": "εyy", "exy": "εxy", "Exx": "Exx", "Eyy": "Eyy", "Exy": "Exy",
}


def _grid_maps(field, strain, names):
    """Per-name (rows, cols) maps and the image extent of the grid, or None if not a grid."""
    from .strain import grid_layout

    pts = np.asarray(field.points, dtype=np.float64)
    valid = np.asarray(getattr(field, "valid", np.ones(len(pts), bool)), dtype=bool)
    try:
        index, shape, step = grid_layout(pts)
    except ValueError:
        return None, None
    maps = {}
    for name in names:
        if name in ("u", "v"):
            vals = np.asarray(getattr(field, name), dtype=np.float64).copy()
            vals[~valid] = np.nan
        elif name == "magnitude":
            vals = np.hypot(np.asarray(field.u, float), np.asarray(field.v, float))
            vals[~valid] = np.nan
        else:
            vals = np.asarray(getattr(strain, name), dtype=np.float64)
        grid = np.full(shape, np.nan)
        grid[index[:, 1], index[:, 0]] = vals
        maps[name] = grid
    x0 = pts[:, 0].min() - index[:, 0].min() * step[0]
    y0 = pts[:, 1].min() - index[:, 1].min() * step[1]
    extent = (x0 - step[0] / 2, x0 + (shape[1] - 0.5) * step[0], y0 + (shape[0] - 0.5) * step[1], y0 - step[1] / 2)
    return maps, extent


def _limits(values):
    v = values[np.isfinite(values)]
    if v.size == 0:
        return -1.0, 1.0
    lo, hi = np.percentile(v, [1, 99])
    pad = 0.01 * max(abs(lo), abs(hi)) or 1e-6
    if hi - lo < pad:  # (nearly) uniform: centre a +-1 % range on it
        mid = 0.5 * (lo + hi)
        lo, hi = mid - pad, mid + pad
    return float(lo), float(hi)


def field_figure(reference, field, strain=None, *, components=None, title: str | None = None,
                 cmap: str = "viridis", alpha: float = 0.75, panel_size: float = 4.0):
    """A Matplotlib Figure with one panel per component over the reference image.

    Parameters
    ----------
    reference : (H, W) array
        The reference image (grey levels), drawn in grey beneath the maps.
    field : Field2D-like
        ``points`` (N, 2), ``u``, ``v`` (N,), optional ``valid``.
    strain : StrainField, optional
        Adds strain panels (default components ``exx``, ``eyy``, ``exy``).
    components : sequence of str, optional
        Any of ``u``, ``v``, ``magnitude``, ``exx``, ``eyy``, ``exy``, ``Exx``, ``Eyy``, ``Exy``.
        Default ``u``, ``v`` plus the small strains when ``strain`` is given.
    """
    from matplotlib.figure import Figure

    ref = np.asarray(reference, dtype=np.float64)
    if ref.ndim != 2:
        raise ValueError(f"reference must be a 2-D grey image, got shape {ref.shape}")
    if components is None:
        components = ["u", "v"] + (["exx", "eyy", "exy"] if strain is not None else [])
    components = list(components)
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
    fig = Figure(figsize=(panel_size * ncols * 1.25, (panel_size * aspect + 0.7) * nrows + 0.5))
    fig.subplots_adjust(left=0.06, right=0.97, bottom=0.08, top=0.9, wspace=0.35, hspace=0.35)
    pts = np.asarray(field.points, dtype=np.float64)
    for k, name in enumerate(components):
        ax = fig.add_subplot(nrows, ncols, k + 1)
        ax.imshow(ref, cmap="gray", extent=(-0.5, W - 0.5, H - 0.5, -0.5), interpolation="nearest")
        if maps is not None:
            vmin, vmax = _limits(maps[name])
            im = ax.imshow(maps[name], extent=extent, cmap=cmap, vmin=vmin, vmax=vmax, alpha=alpha,
                           interpolation="nearest")
        else:  # scattered points: colour the points themselves
            if name in ("u", "v"):
                vals = np.asarray(getattr(field, name), float)
            elif name == "magnitude":
                vals = np.hypot(np.asarray(field.u, float), np.asarray(field.v, float))
            else:
                vals = np.asarray(getattr(strain, name), float)
            vmin, vmax = _limits(vals)
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
    """Draw :func:`field_figure` and save it (format from the suffix, e.g. ``.png``, ``.pdf``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    p = Path(os.fspath(path))
    fig = field_figure(reference, field, strain, **kwargs)
    FigureCanvasAgg(fig)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=dpi)
    return p
