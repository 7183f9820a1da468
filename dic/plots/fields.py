"""Maps of DIC results over the reference image: 2-D fields (displacement, strain) and 3-D stereo fields.

* :func:`field_figure` / :func:`write_field_figure` — a :class:`~dic.track.Field2D` (and optionally
  its :class:`~dic.strain.StrainField`), one panel per component, on the POI grid (one cell per
  point, ``step`` px wide) over the grey reference image; invalid points are transparent.
* :func:`write_figures` — one PNG per quantity of a :class:`~dic.field3d.Field3D` over the left
  reference image: depth (Z), displacements U, V, W, strains exx, eyy, exy, ZNCC and status
  (:data:`FIGURE_QUANTITIES`).

* :func:`field3d_figure` — one quantity of a Field3D as a Figure (what :func:`write_figures` saves).
* :func:`sequence_limits` — colour limits over a whole sequence, for maps that keep one colour scale
  from frame to frame (``limits=`` of :func:`field_figure`, ``vmin=``/``vmax=`` of :func:`field3d_figure`).

Signed quantities (displacements u, v, U, V, W and strains) are drawn on a diverging colour map
(:data:`DIVERGING_CMAP`) centred on zero (symmetric limits); the others (|d|, depth, ZNCC) on a
sequential one. Colour limits are the 1st-99th percentiles of the drawn values
(:mod:`dic.plots._common`) unless fixed by the caller.

The ``.plot()`` methods of :class:`~dic.field2d.Field2D`, :class:`~dic.field3d.Field3D` and of
the result files (:mod:`dic.store`) call these functions and return the Figure.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._common import colormap, new_figure, padded_limits, percentile_limits, save_figure

__all__ = ["field_figure", "write_field_figure", "field3d_figure", "write_figures", "sequence_limits",
           "FIGURE_QUANTITIES", "SIGNED", "DIVERGING_CMAP", "SEQUENTIAL_CMAP"]

#: colour map of signed quantities (centred on zero) and of the others
DIVERGING_CMAP = "RdBu_r"
SEQUENTIAL_CMAP = "viridis"

#: signed quantities: drawn on :data:`DIVERGING_CMAP` with limits symmetric about zero
SIGNED = frozenset({"u", "v", "exx", "eyy", "exy", "Exx", "Eyy", "Exy", "U", "V", "W"})

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


# -- colour scales -----------------------------------------------------------------------------------------
def _check_limits(pair, what: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in pair)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a (vmin, vmax) pair of numbers, got {pair!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise ValueError(f"{what} must be finite with vmin < vmax, got ({lo:g}, {hi:g})")
    return lo, hi


def _auto_limits(values, signed: bool) -> tuple[float, float]:
    """Limits of one map: symmetric about zero for signed quantities, padded percentiles otherwise."""
    if signed:
        lim = percentile_limits(values, symmetric=True)
        return lim if lim is not None else (-1.0, 1.0)
    return padded_limits(values)


def _resolve_limits(name, values, *, vmin, vmax, limits) -> tuple[float, float]:
    """The (vmin, vmax) of component ``name``: ``limits[name]``, else the data's (signed: centred
    on 0), with ``vmin`` / ``vmax`` replacing either end when given."""
    if limits is not None and name in limits:
        return _check_limits(limits[name], f"limits[{name!r}]")
    lo, hi = _auto_limits(values, name in SIGNED)
    lo = lo if vmin is None else float(vmin)
    hi = hi if vmax is None else float(vmax)
    return _check_limits((lo, hi), f"the colour range of {name!r} (vmin, vmax)")


def _strain_view(strain):
    """A strain given as a dict (a result file's frame) viewed with attributes like a StrainField."""
    if isinstance(strain, dict):
        from types import SimpleNamespace

        return SimpleNamespace(**strain)
    return strain


def _is_field3d(f) -> bool:
    return all(hasattr(f, a) for a in ("points", "grid_shape", "status", "valid", "X", "U", "status_codes"))


def sequence_limits(fields, components, *, strains=None) -> dict[str, tuple[float, float]]:
    """One colour range per component over a whole sequence (the 1st-99th percentiles of every
    frame's valid values together; symmetric about zero for signed quantities).

    Parameters
    ----------
    fields : sequence of Field2D / result-file frames (``points``, ``u``, ``v``, ``valid``) or of Field3D
    components : names to draw (2-D: :func:`field_figure`'s components; 3-D: :data:`FIGURE_QUANTITIES`)
    strains : sequence of StrainField (or strain dicts), one per 2-D field; by default the fields'
        own ``strain`` attribute where they have one (result-file frames)

    Returns ``{component: (vmin, vmax)}``, for ``field_figure(..., limits=)`` (2-D) or
    ``field3d_figure(..., vmin=, vmax=)`` (3-D), so every frame of a sequence shares one scale.
    """
    fields = list(fields)
    if not fields:
        raise ValueError("sequence_limits needs at least one field")
    components = [components] if isinstance(components, str) else list(components)
    if strains is not None:
        strains = list(strains)
        if len(strains) != len(fields):
            raise ValueError(f"strains must have one entry per field ({len(fields)}), got {len(strains)}")
    out = {}
    for name in components:
        chunks = []
        for k, f in enumerate(fields):
            if _is_field3d(f):
                if name not in FIGURE_QUANTITIES or name == "status":
                    raise ValueError(f"unknown 3-D quantity {name!r}; choose from {list(FIGURE_QUANTITIES)[:-1]}")
                chunks.append(np.where(f.valid, np.asarray(getattr(f, name), dtype=np.float64), np.nan))
            else:
                if name not in _LABELS:
                    raise ValueError(f"unknown component {name!r}; choose from {', '.join(_LABELS)}")
                strain = strains[k] if strains is not None else getattr(f, "strain", None)
                if name not in ("u", "v", "magnitude") and strain is None:
                    raise ValueError(f"component {name!r} needs strain for every field (frame {k} has none)")
                chunks.append(_component_values(f, _strain_view(strain), name))
        values = np.concatenate(chunks)
        if _is_field3d(fields[0]):
            cmap = FIGURE_QUANTITIES[name][2]
            lim = percentile_limits(values, symmetric=cmap == DIVERGING_CMAP)
            out[name] = lim if lim is not None else (-1.0, 1.0)
        else:
            out[name] = _auto_limits(values, name in SIGNED)
    return out


# -- 2-D fields ------------------------------------------------------------------------------------------
def _component_values(field, strain, name) -> np.ndarray:
    """(N,) values of one component; displacements of invalid points are NaN."""
    if name in ("u", "v"):
        vals = np.asarray(getattr(field, name), dtype=np.float64).copy()
    elif name == "magnitude":
        vals = np.hypot(np.asarray(field.u, float), np.asarray(field.v, float))
    else:
        return np.asarray(getattr(strain, name), dtype=np.float64)
    valid = getattr(field, "valid", None)
    valid = np.ones(len(vals), bool) if valid is None else np.asarray(valid, dtype=bool)
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


def _view_box(ref, pts, extent):
    """(x0, x1, y0, y1) of the axes: the image when there is one, else the grid cells or the points."""
    if ref is not None:
        H, W = ref.shape
        return -0.5, W - 0.5, -0.5, H - 0.5
    if extent is not None:
        return extent[0], extent[1], extent[3], extent[2]
    fin = pts[np.all(np.isfinite(pts), axis=1)]
    if fin.size == 0:
        return -0.5, 0.5, -0.5, 0.5
    pad = 0.02 * max(np.ptp(fin[:, 0]), np.ptp(fin[:, 1]), 1.0)
    return fin[:, 0].min() - pad, fin[:, 0].max() + pad, fin[:, 1].min() - pad, fin[:, 1].max() + pad


def field_figure(reference, field, strain=None, *, components=None, title: str | None = None,
                 cmap: str | None = None, alpha: float = 0.75, panel_size: float = 4.0, vmin: float | None = None,
                 vmax: float | None = None, limits: dict | None = None):
    """A Matplotlib Figure with one panel per component over the reference image.

    Parameters
    ----------
    reference : (H, W) array or None
        The reference image (grey levels), drawn in grey beneath the maps; None draws the maps alone.
    field : Field2D-like
        ``points`` (N, 2) px, ``u``, ``v`` (N,) px, optional ``valid`` (N,) bool.
    strain : StrainField or dict, optional
        Adds strain panels (default components ``exx``, ``eyy``, ``exy``); a result file's frame
        gives its strain as a dict.
    components : sequence of str, optional
        Any of ``u``, ``v``, ``magnitude``, ``exx``, ``eyy``, ``exy``, ``Exx``, ``Eyy``, ``Exy``.
        Default ``u``, ``v`` plus the small strains when ``strain`` is given.
    title : str, optional
        Figure title.
    cmap : str, optional
        One colour map for every panel. Default: signed components (u, v, strains; :data:`SIGNED`)
        on :data:`DIVERGING_CMAP` with limits symmetric about zero, ``magnitude`` on
        :data:`SEQUENTIAL_CMAP`.
    alpha : opacity of the maps.
    panel_size : float
        Width of one panel's image in inches.
    vmin, vmax : float, optional
        Fixed colour limits for every panel (either may be given alone).
    limits : dict, optional
        ``{component: (vmin, vmax)}``, fixed limits per component, e.g. from :func:`sequence_limits`
        so that every frame of a sequence has the same colour scale; takes precedence over ``vmin``/``vmax``.

    Without fixed limits each panel spans the 1st-99th percentiles of its own values. POIs on a
    regular grid are drawn as cells, scattered POIs as dots.
    """
    ref = None
    if reference is not None:
        ref = np.asarray(reference, dtype=np.float64)
        if ref.ndim != 2:
            raise ValueError(f"reference must be a 2-D grey image, got shape {ref.shape}")
    if not hasattr(field, "points") or not hasattr(field, "u") or not hasattr(field, "v"):
        raise ValueError(f"field must have points, u and v (a dic.track.Field2D), got {type(field).__name__}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha!r}")
    if not panel_size > 0:
        raise ValueError(f"panel_size must be positive (inches), got {panel_size!r}")
    if limits is not None and not isinstance(limits, dict):
        raise ValueError(f"limits must be a dict {{component: (vmin, vmax)}}, got {type(limits).__name__}")
    strain = _strain_view(strain)
    if components is None:
        components = ["u", "v"] + (["exx", "eyy", "exy"] if strain is not None else [])
    components = [components] if isinstance(components, str) else list(components)
    if not components:
        raise ValueError("components is empty; name at least one of " + ", ".join(_LABELS))
    for c in components:
        if c not in _LABELS:
            raise ValueError(f"unknown component {c!r}; choose from {', '.join(_LABELS)}")
        if c not in ("u", "v", "magnitude") and strain is None:
            raise ValueError(f"component {c!r} needs a strain field (strain=dic.strain.strain(field))")
    maps, extent = _grid_maps(field, strain, components)
    pts = np.asarray(field.points, dtype=np.float64)
    x0, x1, y0, y1 = _view_box(ref, pts, extent)
    n = len(components)
    ncols = min(n, 3)
    nrows = -(-n // ncols)
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    fig = new_figure((panel_size * ncols * 1.25, (panel_size * aspect + 0.7) * nrows + 0.5))
    fig.subplots_adjust(left=0.06, right=0.97, bottom=0.08, top=0.9, wspace=0.35, hspace=0.35)
    for k, name in enumerate(components):
        ax = fig.add_subplot(nrows, ncols, k + 1)
        if ref is not None:
            H, W = ref.shape
            ax.imshow(ref, cmap="gray", extent=(-0.5, W - 0.5, H - 0.5, -0.5), interpolation="nearest")
        map_cmap = cmap or (DIVERGING_CMAP if name in SIGNED else SEQUENTIAL_CMAP)
        if maps is not None:
            lo, hi = _resolve_limits(name, maps[name], vmin=vmin, vmax=vmax, limits=limits)
            im = ax.imshow(maps[name], extent=extent, cmap=map_cmap, vmin=lo, vmax=hi, alpha=alpha,
                           interpolation="nearest")
        else:  # scattered points: colour the points themselves (invalid ones included, as drawn before)
            if name in ("u", "v"):
                vals = np.asarray(getattr(field, name), float)
            elif name == "magnitude":
                vals = np.hypot(np.asarray(field.u, float), np.asarray(field.v, float))
            else:
                vals = np.asarray(getattr(strain, name), float)
            lo, hi = _resolve_limits(name, vals, vmin=vmin, vmax=vmax, limits=limits)
            im = ax.scatter(pts[:, 0], pts[:, 1], c=vals, s=4, cmap=map_cmap, vmin=lo, vmax=hi)
        ax.set_xlim(x0, x1)
        ax.set_ylim(y1, y0)
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
def _check_field3d(f):
    if not _is_field3d(f):
        raise ValueError(f"expected a dic.field3d.Field3D, got {type(f).__name__}")
    return f


def _map(f, values: np.ndarray):
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


def field3d_figure(field, quantity: str = "W", image=None, *, vmin: float | None = None, vmax: float | None = None,
                   cmap: str | None = None, alpha: float = 0.75):
    """One quantity of a Field3D as a Matplotlib Figure, over the left reference image when given.

    Parameters
    ----------
    field : Field3D
    quantity : a name of :data:`FIGURE_QUANTITIES` (``Z``, ``U``, ``V``, ``W``, ``exx``, ``eyy``,
        ``exy``, ``zncc_stereo``, ``status``)
    image : (H, W) the left reference image (grey levels) drawn underneath, or None
    vmin, vmax : fixed colour limits (e.g. from :func:`sequence_limits` for one scale over a
        sequence); by default the 1st-99th percentiles of the valid points, symmetric about zero
        for displacements and strains
    cmap : colour map instead of the quantity's own (:data:`FIGURE_QUANTITIES`)
    alpha : opacity of the map

    Only points with status OK are coloured (the status map shows every point).
    """
    f = _check_field3d(field)
    img = None
    if image is not None:
        img = np.asarray(image, dtype=np.float64)
        if img.ndim != 2:
            raise ValueError(f"image must be the (H, W) left reference image, got shape {img.shape}")
    if quantity not in FIGURE_QUANTITIES:
        raise ValueError(f"unknown figure quantity {quantity!r}; choose from {list(FIGURE_QUANTITIES)}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha!r}")
    label, unit, q_cmap = FIGURE_QUANTITIES[quantity]
    names = [s.name for s in f.status_codes]
    pts = np.asarray(f.points, dtype=np.float64)
    if img is not None:
        aspect = img.shape[0] / img.shape[1]
    else:
        fin = pts[np.all(np.isfinite(pts), axis=1)]
        aspect = (np.ptp(fin[:, 1]) + 1) / (np.ptp(fin[:, 0]) + 1) if fin.size else 1.0
    fig = new_figure((7.5, 7.5 * aspect + 0.6))
    ax = fig.subplots()
    if img is not None:
        ax.imshow(img, cmap="gray", interpolation="nearest")
    if quantity == "status":
        vals = f.status.astype(np.float64)
        cm, norm = _status_colours(len(names))
        kw = {"cmap": cm, "norm": norm}
    else:
        vals = np.where(f.valid, np.asarray(getattr(f, quantity), dtype=np.float64), np.nan)
        use = cmap or q_cmap
        kw = {"cmap": use}
        limits = percentile_limits(vals, symmetric=q_cmap == DIVERGING_CMAP)
        if vmin is not None or vmax is not None:
            lo, hi = limits if limits is not None else (-1.0, 1.0)
            limits = _check_limits((lo if vmin is None else vmin, hi if vmax is None else vmax),
                                   f"the colour range of {quantity!r} (vmin, vmax)")
        if limits is not None:
            kw.update(vmin=limits[0], vmax=limits[1])
    if f.grid_shape is not None:
        data, extent = _map(f, vals)
        im = ax.imshow(data, extent=extent, alpha=alpha, interpolation="nearest", **kw)
    else:
        fin = np.isfinite(vals)
        im = ax.scatter(f.points[fin, 0], f.points[fin, 1], c=vals[fin], s=6, alpha=alpha, **kw)
        if img is None:
            ax.invert_yaxis()
    cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
    if quantity == "status":
        cb.set_ticks(np.arange(len(names)))
        cb.set_ticklabels(names, fontsize=7)
    cb.set_label(f"{label} ({unit})" if unit else label)
    frame = {"left": "left camera frame", "plane": "best-fit plane frame"}.get(f.frame_name, f"{f.frame_name} frame")
    ax.set_title(f"state {f.index}: {label}" + (f" ({frame})" if quantity in ("Z", "U", "V", "W") else ""))
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    fig.tight_layout()
    return fig


def write_figures(field, image, directory, *, quantities=None, prefix: str = "", dpi: int = 110,
                  alpha: float = 0.75, limits: dict | None = None) -> list[Path]:
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
    limits : ``{quantity: (vmin, vmax)}``, fixed colour limits (e.g. :func:`sequence_limits` over
        every state of a sequence); the others are per figure.

    Each PNG is :func:`field3d_figure`: only points with status OK are coloured; colour limits
    are the 1st-99th percentiles (symmetric about 0 for displacements and strains).
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
    if limits is not None and not isinstance(limits, dict):
        raise ValueError(f"limits must be a dict {{quantity: (vmin, vmax)}}, got {type(limits).__name__}")
    directory = Path(os.fspath(directory))
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for q in quantities:
        lo, hi = (limits or {}).get(q, (None, None))
        fig = field3d_figure(f, q, img, vmin=lo, vmax=hi, alpha=alpha)
        written.append(save_figure(fig, directory / f"{prefix}{q}.png", dpi=dpi))
    return written
