"""Maps of DIC results over the reference image: 2-D fields (displacement, strain) and 3-D stereo fields.

* :func:`field_figure` / :func:`write_field_figure` — a :class:`~dic.Field2D` (and optionally
  its :class:`~dic.StrainField`), one panel per component, on the POI grid (one cell per
  point, ``step`` px wide) over the grey reference image; invalid points are transparent.
* :func:`write_figures` — one PNG per quantity of a :class:`~dic.field3d.Field3D` over the left
  reference image: depth (Z), displacements U, V, W, strains exx, eyy, exy, ZNCC and status
  (:data:`FIGURE_QUANTITIES`).

* :func:`field3d_figure` — one quantity of a Field3D as a Figure (what :func:`write_figures` saves).
* :func:`sequence_limits` — colour limits over a whole sequence, for maps that keep one colour scale
  from frame to frame (``limits=`` of :func:`field_figure`, ``vmin=``/``vmax=`` of :func:`field3d_figure`).

Colour maps (:func:`dic.plots._common.colour_scale`): a signed quantity (displacements u, v, U, V, W
and strains) whose range spans zero is drawn on a diverging map (:data:`DIVERGING_CMAP`) centred on zero
(symmetric limits); a one-signed range (an offset field such as v from -12 to -5 px) and the unsigned
quantities (|d|, depth, ZNCC) on a sequential one over their own range. Colour limits are the 1st-99th
percentiles of the drawn values (:mod:`dic.plots._common`) unless fixed by the caller. Every panel has
its axes labelled in image px, a title with the quantity and its unit, and a colourbar as tall as the
panel; the grey reference image is drawn beneath the map (which has opacity ``alpha``) when it is given.

The region of interest of a run (``region=``: a :class:`dic.correlation.points.Region` or the JSON form a
result file stores) is drawn over the maps: its outline as a solid line (:data:`REGION_STYLE`; a box or
a polygon, and a mask's boundary when the mask itself is given) and each excluded shape (circle, box,
polygon) as a dashed one (:data:`EXCLUDED_STYLE`); the artists carry the gids ``"region"`` and
``"excluded"``.

The ``.plot()`` methods of :class:`~dic.field2d.Field2D`, :class:`~dic.field3d.Field3D` and of
the result files (:mod:`dic.store`) call these functions and return the Figure.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._common import (
    DIVERGING_CMAP,
    SEQUENTIAL_CMAP,
    backdrop,
    colormap,
    colour_scale,
    draw_colourbar,
    map_panels,
    save_map_png,
)

__all__ = ["field_figure", "write_field_figure", "field3d_figure", "write_figures", "sequence_limits",
           "FIGURE_QUANTITIES", "SIGNED", "DIVERGING_CMAP", "SEQUENTIAL_CMAP", "REGION_STYLE", "EXCLUDED_STYLE"]

#: the region of interest's outline (a box, a polygon or a mask's boundary) over the maps
REGION_STYLE = {"color": "black", "linewidth": 1.2, "linestyle": "-"}
#: the outline of each excluded shape
EXCLUDED_STYLE = {"color": "black", "linewidth": 1.2, "linestyle": "--"}

#: signed quantities: drawn on :data:`DIVERGING_CMAP` with limits symmetric about zero when their range
#: spans zero, else on :data:`SEQUENTIAL_CMAP` over their own range
SIGNED = frozenset({"u", "v", "exx", "eyy", "exy", "Exx", "Eyy", "Exy", "U", "V", "W"})

#: component of a 2-D field -> panel title of :func:`field_figure` (quantity and unit)
_LABELS = {
    "u": "displacement u (px)", "v": "displacement v (px)", "magnitude": "displacement magnitude |d| (px)",
    "exx": "strain exx (1)", "eyy": "strain eyy (1)", "exy": "strain exy (1)",  # with the strain's type in front
    "Exx": "Green-Lagrange strain Exx (1)", "Eyy": "Green-Lagrange strain Eyy (1)", "Exy": "Green-Lagrange strain Exy (1)",
}
#: component of a 2-D field -> colourbar label
_UNITS = {"u": "u (px)", "v": "v (px)", "magnitude": "|d| (px)", "exx": "exx", "eyy": "eyy", "exy": "exy",
          "Exx": "Exx", "Eyy": "Eyy", "Exy": "Exy"}

#: quantity -> (label, unit, colour map) of :func:`write_figures`; the signed quantities' map is
#: :data:`DIVERGING_CMAP` when their range spans zero, else :data:`SEQUENTIAL_CMAP`
FIGURE_QUANTITIES = {
    "Z": ("depth Z", "mm", "viridis"),
    "U": ("displacement U", "mm", "RdBu_r"),
    "V": ("displacement V", "mm", "RdBu_r"),
    "W": ("displacement W", "mm", "RdBu_r"),
    "exx": ("Green-Lagrange strain exx", "1", "RdBu_r"),
    "eyy": ("Green-Lagrange strain eyy", "1", "RdBu_r"),
    "exy": ("Green-Lagrange strain exy", "1", "RdBu_r"),
    "zncc_stereo": ("ZNCC of the stereo match", "1", "magma"),
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


def _resolve_scale(name, values, *, vmin, vmax, limits, cmap=None) -> tuple[float, float, str]:
    """(vmin, vmax, colour map) of component ``name``: ``limits[name]``, else the data's range
    (:func:`dic.plots._common.colour_scale`: centred on 0 when a signed range spans zero), with
    ``vmin`` / ``vmax`` replacing either end when given; ``cmap`` replaces the map."""
    fixed = None
    if limits is not None and name in limits:
        fixed = _check_limits(limits[name], f"limits[{name!r}]")
        vmin = vmax = None
    use, lo, hi = colour_scale(values, signed=name in SIGNED, fixed=fixed, vmin=vmin, vmax=vmax)
    lo, hi = _check_limits((lo, hi), f"the colour range of {name!r} (vmin, vmax)")
    return lo, hi, cmap or use


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
        _, lo, hi = colour_scale(np.concatenate(chunks), signed=name in SIGNED)
        out[name] = (lo, hi)
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


def _grid_maps(field, strain, names, cracks=None):
    """Per-name (rows, cols) maps and the image extent of the grid, or (None, None) if not a grid; the
    cells (a node's square, one step wide) that a declared crack enters are NaN (not drawn)."""
    from .._strain import grid_layout
    from ..gridinterp import _cut_cells

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
    # a node's cell is the cell of the grid shifted by half a step, one node larger each way
    cut = _cut_cells((x0 - step[0] / 2, y0 - step[1] / 2), step, (shape[0] + 1, shape[1] + 1), cracks)
    if cut is not None:
        for grid in maps.values():
            grid[cut] = np.nan
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


class _Region:
    """A region to draw: ``kind``, ``data`` and ``exclude`` as :class:`dic.correlation.points.Region` has them."""

    def __init__(self, kind, data, exclude):
        self.kind, self.data, self.exclude = kind, data, exclude


class _Shape:
    """A shape to draw: ``kind`` and ``data`` as :class:`dic.correlation.points.Exclusion` has them."""

    def __init__(self, kind, data):
        self.kind, self.data = kind, data


def _shape_from_form(form) -> _Shape:
    """An excluded shape from its JSON form (``{"circle": [cx, cy, r]}``, ...), its text form
    (``"circle:CX,CY,R"``, ...) or an object with ``kind`` and ``data`` (an ``Exclusion``)."""
    if hasattr(form, "kind") and hasattr(form, "data"):
        return _Shape(form.kind, form.data)
    if isinstance(form, str) and ":" in form:
        kind, _, rest = form.partition(":")
        try:
            nums = [float(c) for c in rest.replace(";", ",").split(",") if c.strip()]
        except ValueError:
            nums = []
        form = {kind.strip().lower(): np.reshape(nums, (-1, 2)) if kind.strip().lower() == "polygon" and
                len(nums) % 2 == 0 else nums}
    if isinstance(form, dict) and len(form) == 1:
        kind, data = next(iter(form.items()))
        size = {"circle": 3, "box": 4}.get(kind)
        arr = np.asarray(data, dtype=np.float64) if kind in ("circle", "box", "polygon") else None
        if arr is not None and ((size and arr.shape == (size,)) or
                                (kind == "polygon" and arr.ndim == 2 and arr.shape[1] == 2 and len(arr) >= 3)):
            return _Shape(kind, tuple(arr) if size else arr)
    raise ValueError(f"region: excluded shape {form!r} is not a circle [cx, cy, r], box [x0, y0, x1, y1] or "
                     "polygon [[x, y], ...] (px)")


def _region_parts(value):
    """(kind, data, excluded shapes) of a region to draw. ``value``: a
    :class:`dic.correlation.points.Region` (any object with ``kind``, ``data``, ``exclude``), the JSON
    form a result file stores (a box ``[x0, y0, x1, y1]``, ``{"box" | "polygon" | "mask": ...,
    "exclude": [...]}``), a polygon ``[(x, y), ...]`` or an (H, W) bool mask. Drawn as given: checking
    a region is :func:`dic.correlation.points.region`'s job (done when the run was made); a stored
    mask form holds only a digest of the mask, so its exclusions are drawn, not its outline."""
    if all(hasattr(value, a) for a in ("kind", "data", "exclude")):
        return value.kind, value.data, tuple(_shape_from_form(e) for e in value.exclude)
    if isinstance(value, dict):
        shapes = value.get("exclude", [])
        if isinstance(shapes, (str, dict)) or not isinstance(shapes, (list, tuple)):
            raise ValueError(f"region 'exclude' must be a list of shapes, got {shapes!r}")
        exclude = tuple(_shape_from_form(e) for e in shapes)
        if "box" in value:
            return ("box",) + _region_parts(value["box"])[1:2] + (exclude,)
        if "polygon" in value:
            return ("polygon",) + _region_parts(np.asarray(value["polygon"], dtype=np.float64))[1:2] + (exclude,)
        if "mask" in value:
            mask = value["mask"]
            return "mask", (np.asarray(mask, bool) if isinstance(mask, np.ndarray) else None), exclude
        return "image", None, exclude
    arr = value if isinstance(value, np.ndarray) else np.asarray(value, dtype=np.float64) \
        if isinstance(value, (list, tuple)) else None
    if arr is not None and arr.dtype != bool and arr.shape == (4,):
        return "box", tuple(float(c) for c in arr), ()
    if arr is not None and arr.ndim == 2 and arr.dtype != bool and arr.shape[1] == 2 and len(arr) >= 3:
        return "polygon", np.asarray(arr, dtype=np.float64), ()
    if arr is not None and arr.ndim == 2:
        return "mask", arr != 0, ()
    raise ValueError(f"region must be a Region (dic.correlation.points.region), the stored JSON form, a box "
                     f"(x0, y0, x1, y1), a polygon [(x, y), ...] or an (H, W) mask; got {type(value).__name__}")


def _draw_region(ax, parts) -> None:
    """The region's outline (gid ``"region"``) and its excluded shapes (gid ``"excluded"``) on ``ax``; px."""
    from matplotlib.patches import Circle, Polygon, Rectangle

    kind, data, exclude = parts
    if kind == "box":
        x0, y0, x1, y1 = data
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, gid="region", **REGION_STYLE))
    elif kind == "polygon":
        ax.add_patch(Polygon(np.asarray(data), closed=True, fill=False, gid="region", **REGION_STYLE))
    elif kind == "mask" and data is not None and np.any(data) and not np.all(data):
        cs = ax.contour(np.asarray(data, dtype=np.float32), levels=[0.5], colors=[REGION_STYLE["color"]],
                        linewidths=REGION_STYLE["linewidth"])
        cs.set_gid("region")
    for shape in exclude:
        if shape.kind == "circle":
            cx, cy, r = shape.data
            patch = Circle((cx, cy), r, fill=False, gid="excluded", **EXCLUDED_STYLE)
        elif shape.kind == "box":
            x0, y0, x1, y1 = shape.data
            patch = Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, gid="excluded", **EXCLUDED_STYLE)
        else:
            patch = Polygon(np.asarray(shape.data), closed=True, fill=False, gid="excluded", **EXCLUDED_STYLE)
        ax.add_patch(patch)


def field_figure(reference, field, strain=None, *, components=None, title: str | None = None,
                 cmap: str | None = None, alpha: float = 0.75, panel_size: float = 3.0, vmin: float | None = None,
                 vmax: float | None = None, limits: dict | None = None, dpi: float = 100, region=None, cracks=None):
    """A Matplotlib Figure with one panel per component over the reference image.

    Parameters
    ----------
    reference : (H, W) array or None
        The reference image (grey levels), drawn in grey beneath the maps (as block means at about
        the panel's resolution, :func:`dic.plots._common.backdrop`); None draws the maps alone.
    field : Field2D-like
        ``points`` (N, 2) px, ``u``, ``v`` (N,) px, optional ``valid`` (N,) bool.
    strain : StrainField or dict, optional
        Adds strain panels (default components ``exx``, ``eyy``, ``exy``); a result file's frame
        gives its strain as a dict.
    components : sequence of str, optional
        Any of ``u``, ``v``, ``magnitude``, ``exx``, ``eyy``, ``exy``, ``Exx``, ``Eyy``, ``Exy``.
        Default ``u``, ``v`` plus the strains ``exx``, ``eyy``, ``exy`` (of the strain's type, named in the
        panel titles) when ``strain`` is given.
    title : str, optional
        Figure title.
    cmap : str, optional
        One colour map for every panel. Default (:func:`dic.plots._common.colour_scale`): a signed
        component (u, v, strains; :data:`SIGNED`) whose range spans zero on :data:`DIVERGING_CMAP`
        with limits symmetric about zero; a one-signed range (e.g. v from -12 to -5 px) and
        ``magnitude`` on :data:`SEQUENTIAL_CMAP` over their own range.
    alpha : opacity of the maps over the grey reference.
    panel_size : float
        Width of one panel in inches (its height follows the image's aspect ratio).
    vmin, vmax : float, optional
        Fixed colour limits for every panel (either may be given alone).
    limits : dict, optional
        ``{component: (vmin, vmax)}``, fixed limits per component, e.g. from :func:`sequence_limits`
        so that every frame of a sequence has the same colour scale; takes precedence over ``vmin``/``vmax``.
    dpi : float
        Resolution the figure is drawn at (:func:`write_field_figure` saves at its own dpi).
    region : optional
        The run's region of interest (a :class:`dic.correlation.points.Region`, the JSON form a result
        file stores, a box, a polygon or an (H, W) mask), drawn on every panel: its outline solid, its
        excluded shapes dashed (module docstring).
    cracks : optional
        Declared cracks (:mod:`dic.cracks`, reference px): the grid cells they cut are not drawn, and
        each crack is drawn as a black line.

    Without fixed limits each panel spans the 1st-99th percentiles of its own values. POIs on a
    regular grid are drawn as cells, scattered POIs as dots. Every panel has x and y axes in image
    px, a title naming the quantity and its unit, and a colourbar exactly as tall as the panel.
    """
    ref = None
    if reference is not None:
        ref = np.asarray(reference, dtype=np.float64)
        if ref.ndim != 2:
            raise ValueError(f"reference must be a 2-D grey image, got shape {ref.shape}")
    if not hasattr(field, "points") or not hasattr(field, "u") or not hasattr(field, "v"):
        raise ValueError(f"field must have points, u and v (a dic.Field2D), got {type(field).__name__}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha!r}")
    if not panel_size > 0:
        raise ValueError(f"panel_size must be positive (inches), got {panel_size!r}")
    if not (isinstance(dpi, (int, float)) and np.isfinite(dpi) and dpi > 0):
        raise ValueError(f"dpi must be a positive number, got {dpi!r}")
    if limits is not None and not isinstance(limits, dict):
        raise ValueError(f"limits must be a dict {{component: (vmin, vmax)}}, got {type(limits).__name__}")
    strain = _strain_view(strain)
    outline = None if region is None else _region_parts(region)
    from .._strain import strain_type_label

    if components is None:
        components = ["u", "v"] + (["exx", "eyy", "exy"] if strain is not None else [])
    components = [components] if isinstance(components, str) else list(components)
    if not components:
        raise ValueError("components is empty; name at least one of " + ", ".join(_LABELS))
    for c in components:
        if c not in _LABELS:
            raise ValueError(f"unknown component {c!r}; choose from {', '.join(_LABELS)}")
        if c not in ("u", "v", "magnitude") and strain is None:
            raise ValueError(f"component {c!r} needs a strain field (strain=dic.strain(field))")
    from ..cracks import as_cracks

    cracks = as_cracks(cracks)
    maps, extent = _grid_maps(field, strain, components, cracks)
    pts = np.asarray(field.points, dtype=np.float64)
    x0, x1, y0, y1 = _view_box(ref, pts, extent)
    n = len(components)
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    fig, panels = map_panels(n, ncols=min(n, 3), panel_w=panel_size, aspect=aspect, suptitle=bool(title), dpi=dpi)
    back = None if ref is None else _grey_backdrop(ref, panel_size * dpi)  # once for every panel
    for (ax, bar), name in zip(panels, components):
        if back is not None:
            _draw_backdrop(ax, back)
        values = maps[name] if maps is not None else _scatter_values(field, strain, name)
        lo, hi, map_cmap = _resolve_scale(name, values, vmin=vmin, vmax=vmax, limits=limits, cmap=cmap)
        if maps is not None:
            im = ax.imshow(maps[name], extent=extent, cmap=map_cmap, vmin=lo, vmax=hi, alpha=alpha,
                           interpolation="nearest", aspect="auto", gid="map")
        else:  # scattered points: colour the points themselves (invalid ones included, as drawn before)
            im = ax.scatter(pts[:, 0], pts[:, 1], c=values, s=4, cmap=map_cmap, vmin=lo, vmax=hi, gid="map")
        if outline is not None:
            _draw_region(ax, outline)
        for crack in cracks:
            ax.plot(crack.vertices[:, 0], crack.vertices[:, 1], color="k", linewidth=1.5, gid="crack")
        ax.set_xlim(x0, x1)
        ax.set_ylim(y1, y0)
        panel_title, unit_label = _LABELS[name], _UNITS[name]
        if name in ("exx", "eyy", "exy"):  # the strain's type by name
            kind = strain_type_label(getattr(strain, "strain_type", None)  # a StrainField; a file's frame: its attrs
                                     or getattr(field, "attrs", {}).get("strain_type") or "small")  # before: small
            panel_title, unit_label = f"{kind} strain {name} (1)", f"{name}, {kind}"
        ax.set_title(panel_title, fontsize=10)
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
        draw_colourbar(ax, im, bar, label=unit_label)
    if title:
        fig.suptitle(title, y=1.0 - 0.12 / fig.get_figheight(), va="top")
    return fig


def _grey_backdrop(image, panel_px: float):
    """:func:`dic.plots._common.backdrop` of ``image`` as ``(rgb, extent)``: the grey levels as (h, w, 3)
    8-bit RGB (what the ``gray`` colour map makes of them), so that Agg only resamples it per panel."""
    grey, extent = backdrop(image, panel_px)
    grey8 = np.round(np.clip(grey, 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.repeat(grey8[..., None], 3, axis=2), extent


def _draw_backdrop(ax, back):
    """The grey reference image beneath a map panel; ``back`` is :func:`_grey_backdrop`'s ``(rgb, extent)``."""
    rgb, extent = back
    ax.imshow(rgb, interpolation="nearest", aspect="auto", extent=extent, gid="backdrop")


def _scatter_values(field, strain, name) -> np.ndarray:
    if name in ("u", "v"):
        return np.asarray(getattr(field, name), float)
    if name == "magnitude":
        return np.hypot(np.asarray(field.u, float), np.asarray(field.v, float))
    return np.asarray(getattr(strain, name), float)


def write_field_figure(path, reference, field, strain=None, *, dpi: int = 100, **kwargs) -> Path:
    """Draw :func:`field_figure` and save it (format from the suffix, e.g. ``.png``, ``.pdf``); returns the path.

    PNGs are stored as 8-bit RGB (:func:`dic.plots._common.save_map_png`): the 5-panel figure of a
    1 MP frame is 1.3 MP and about 360 KB (bench/figures.py).
    """
    fig = field_figure(reference, field, strain, dpi=dpi, **kwargs)
    return save_map_png(fig, path, dpi=dpi)


# -- 3-D (stereo) fields ---------------------------------------------------------------------------------
def _check_field3d(f):
    if not _is_field3d(f):
        raise ValueError(f"expected a dic.field3d.Field3D, got {type(f).__name__}")
    return f


def _map(f, values: np.ndarray, cracks=()):
    """Values on the POI grid (masked where not finite, and in the cells a declared crack enters) and the
    image extent of the grid cells."""
    from ..gridinterp import _cut_cells

    ny, nx = f.grid_shape
    g = np.asarray(values, dtype=np.float64).reshape(ny, nx)
    pts = f.points.reshape(ny, nx, 2)
    dx = (pts[0, -1, 0] - pts[0, 0, 0]) / max(nx - 1, 1) if nx > 1 else 1.0
    dy = (pts[-1, 0, 1] - pts[0, 0, 1]) / max(ny - 1, 1) if ny > 1 else 1.0
    extent = (pts[0, 0, 0] - dx / 2, pts[0, -1, 0] + dx / 2, pts[-1, 0, 1] + dy / 2, pts[0, 0, 1] - dy / 2)
    # a node's cell is the cell of the grid shifted by half a step, one node larger each way (as 2-D)
    cut = _cut_cells((extent[0], extent[3]), (dx, dy), (ny + 1, nx + 1), cracks)
    if cut is not None:
        g = np.where(cut, np.nan, g)
    return np.ma.masked_invalid(g), extent


def _status_colours(n: int):
    """Status colour map and norm: OK green; failures in colours without green (tab10 minus its green,
    then tab20b when there are more than ten statuses)."""
    from matplotlib.colors import BoundaryNorm, ListedColormap

    tab10 = colormap("tab10")
    colours = np.vstack([tab10([2]), tab10([7, 1, 3, 4, 5, 6, 9, 8, 0]), colormap("tab20b")(np.arange(20))])[:n]
    return ListedColormap(colours), BoundaryNorm(np.arange(n + 1) - 0.5, n)


def field3d_figure(field, quantity: str = "W", image=None, *, vmin: float | None = None, vmax: float | None = None,
                   cmap: str | None = None, alpha: float = 0.75, panel_size: float = 5.0, dpi: float = 110,
                   region=None, cracks=None):
    """One quantity of a Field3D as a Matplotlib Figure, over the left reference image when given.

    Parameters
    ----------
    field : Field3D
    quantity : a name of :data:`FIGURE_QUANTITIES` (``Z``, ``U``, ``V``, ``W``, ``exx``, ``eyy``,
        ``exy``, ``zncc_stereo``, ``status``)
    image : (H, W) the left reference image (grey levels) drawn underneath, or None
    vmin, vmax : fixed colour limits (e.g. from :func:`sequence_limits` for one scale over a
        sequence); by default the 1st-99th percentiles of the valid points, symmetric about zero
        for displacements and strains whose range spans zero (then on :data:`DIVERGING_CMAP`; a
        one-signed range, e.g. W from 0.011 to 0.022 mm, is on :data:`SEQUENTIAL_CMAP`)
    cmap : colour map instead of the quantity's own (:data:`FIGURE_QUANTITIES`)
    alpha : opacity of the map
    panel_size : width of the map in inches (its height follows the image's aspect ratio)
    dpi : resolution the figure is drawn at
    region : the run's region of interest in the left reference image (a Region, the JSON form a
        result file stores, a box, a polygon or an (H, W) mask): outline solid, excluded shapes dashed
    cracks : declared cracks in left reference px (:mod:`dic.cracks`, as ``stereo_sequence(cracks=)``):
        the grid cells they enter are not drawn, and each crack is drawn as a black line

    Only points with status OK are coloured (the status map shows every point). The map is drawn
    where the points are in the left reference image: axes x, y in left-image px; the colourbar,
    as tall as the map, carries the quantity and its unit (mm for Z, U, V, W).
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
    if not panel_size > 0:
        raise ValueError(f"panel_size must be positive (inches), got {panel_size!r}")
    label, unit, q_cmap = FIGURE_QUANTITIES[quantity]
    outline = None if region is None else _region_parts(region)
    from ..cracks import as_cracks

    cracks = as_cracks(cracks)
    if quantity in ("exx", "eyy", "exy"):  # the field's strain type (Green-Lagrange unless chosen otherwise)
        from .._strain import strain_type_label

        label = f"{strain_type_label(getattr(f, 'strain_type', 'green-lagrange'))} strain {quantity}"
    names = [s.name for s in f.status_codes]
    pts = np.asarray(f.points, dtype=np.float64)
    if quantity == "status":
        vals = f.status.astype(np.float64)
        cm, norm = _status_colours(len(names))
        kw = {"cmap": cm, "norm": norm}
    else:
        vals = np.where(f.valid, np.asarray(getattr(f, quantity), dtype=np.float64), np.nan)
        if vmin is not None or vmax is not None:
            lo, hi = colour_scale(vals, signed=quantity in SIGNED)[1:]
            _check_limits((lo if vmin is None else vmin, hi if vmax is None else vmax),
                          f"the colour range of {quantity!r} (vmin, vmax)")
        use, lo, hi = colour_scale(vals, signed=quantity in SIGNED, vmin=vmin, vmax=vmax)
        if quantity not in SIGNED:
            use = q_cmap
        kw = {"cmap": cmap or use, "vmin": lo, "vmax": hi}
    data = extent = None
    if f.grid_shape is not None:
        data, extent = _map(f, vals, cracks)
    x0, x1, y0, y1 = _view_box(img, pts if data is None else pts[np.isfinite(vals)] if np.isfinite(vals).any() else pts,
                               extent)
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    right = 0.3 + 0.6 * 10 * max(len(nm) for nm in names) / 72.0 if quantity == "status" else None  # names at 10 pt
    fig, [(ax, bar)] = map_panels(1, ncols=1, panel_w=panel_size, aspect=aspect, suptitle=False, dpi=dpi, right=right)
    if img is not None:
        _draw_backdrop(ax, _grey_backdrop(img, panel_size * dpi))
    if data is not None:
        im = ax.imshow(data, extent=extent, alpha=alpha, interpolation="nearest", aspect="auto", gid="map", **kw)
    else:
        fin = np.isfinite(vals)
        im = ax.scatter(f.points[fin, 0], f.points[fin, 1], c=vals[fin], s=6, alpha=alpha, gid="map", **kw)
    if outline is not None:
        _draw_region(ax, outline)
    for crack in cracks:
        ax.plot(crack.vertices[:, 0], crack.vertices[:, 1], color="k", linewidth=1.5, gid="crack")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1, y0)
    if quantity == "status":
        draw_colourbar(ax, im, bar, ticks=np.arange(len(names)), ticklabels=names)
    else:
        draw_colourbar(ax, im, bar, label=f"{label} ({unit})" if unit else label)
    frame = {"left": "left camera frame", "plane": "best-fit plane frame"}.get(f.frame_name, f"{f.frame_name} frame")
    title = f"state {f.index}: {label}" + (f" ({unit})" if unit else "")
    ax.set_title(title + (f", {frame}" if quantity in ("Z", "U", "V", "W") else ""), fontsize=10)
    ax.set_xlabel("x, left image (px)")
    ax.set_ylabel("y, left image (px)")
    return fig


def write_figures(field, image, directory, *, quantities=None, prefix: str = "", dpi: int = 100,
                  alpha: float = 0.75, limits: dict | None = None, region=None, cracks=None) -> list[Path]:
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
    region : the run's region of interest (:func:`field3d_figure`), drawn on every map.
    cracks : declared cracks in left reference px (:func:`field3d_figure`), drawn on every map.

    Each PNG is :func:`field3d_figure` stored as 8-bit RGB (:func:`dic.plots._common.save_map_png`):
    only points with status OK are coloured; colour limits are the 1st-99th percentiles (symmetric
    about 0 for displacements and strains whose range spans zero, else a sequential map).
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
    if region is not None:
        region = _Region(*_region_parts(region))  # read once for every quantity
    directory = Path(os.fspath(directory))
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for q in quantities:
        lo, hi = (limits or {}).get(q, (None, None))
        fig = field3d_figure(f, q, img, vmin=lo, vmax=hi, alpha=alpha, dpi=dpi, region=region, cracks=cracks)
        written.append(save_map_png(fig, directory / f"{prefix}{q}.png", dpi=dpi))
    return written
