"""A run report: one self-contained HTML file about a 2-D or stereo result file (``specula report``).

:func:`write_report` writes one HTML file that needs nothing else (no network, no other file): every
picture is inline (base64 PNG), the few lines of JavaScript too. It holds

* a summary (file, kind, frames, reference image, Specula version) and the run settings (``/settings``);
* **field maps** of one quantity over the reference image, one pre-rendered picture per shown frame with
  **one colour range** for all (the rule of ``specula animate``: the 1st-99th percentiles of every shown
  frame's valid values, symmetric about zero on a diverging map for a signed quantity whose range spans
  zero, else a sequential map), a frame slider, and ``#frame=K`` in the address to open frame K; above
  :data:`MAX_MAP_FRAMES` finished frames, an evenly spaced selection of that many is shown (the first
  and the last included);
* **per-frame quality** over every finished frame: the valid fraction over the region (2-D: the
  stored points, which are the region's; stereo: the points with a status other than NOT_COMPUTED),
  the median ZNCC of the valid points, the median predicted sigma when the file holds it, the mean
  number of IC-GN iterations (2-D) or the median reprojection error (stereo), and the seconds per frame;
* point **histories** and virtual **extensometers** when asked (:func:`dic.postprocess.point_history`,
  :func:`dic.postprocess.extensometer`), as a figure and a table;
* for stereo files, the **3-D shape** of the reference state (a rendered view of X, Y, Z in mm).

The maps are drawn without a figure per frame: each point's grid cell (the grid of its points,
:func:`dic.grid_layout`; points on no grid: the nearest point within half the point spacing) is
coloured through the colour map's 256-entry table as Matplotlib colours a value (entry ``min(255,
floor(256 t))`` for ``t = (value - vmin) / (vmax - vmin)`` clipped to [0, 1]), blended at :data:`MAP_ALPHA` over the grey reference image (when
given; the grey backdrop of every Specula map, :func:`dic.plots._common.backdrop`), at most ``map_width``
pixels wide (a smaller reference image is enlarged by a whole factor).
"""
from __future__ import annotations

import base64
import html
import json
import os
from pathlib import Path

import numpy as np

__all__ = ["write_report", "report_frames", "render_map", "map_geometry", "frame_quality", "default_quantity", "MAX_MAP_FRAMES",
           "MAP_WIDTH", "MAP_ALPHA"]

#: the most frames whose map a report carries; longer runs show an evenly spaced selection of this many
MAX_MAP_FRAMES = 40
#: default width (px) of a map picture (a wider reference image is shrunk to it, a narrower one enlarged by a whole factor)
MAP_WIDTH = 640
#: opacity of the colours over the grey reference image
MAP_ALPHA = 0.8
#: grey level of the map's background where there is no reference image
_PAPER = 235

#: units of the quantities of 2-D files (px or strain), by quantity
_UNITS_2D = {"u": "px", "v": "px", "magnitude": "px"}


def report_frames(indices, max_frames: int = MAX_MAP_FRAMES) -> list[int]:
    """The frames whose map a report shows: all of ``indices`` up to ``max_frames``, else ``max_frames`` of
    them evenly spaced over the list (the first and the last included), ascending."""
    from kernels.checks import positive_int

    max_frames = positive_int(max_frames, "max_frames")
    idx = sorted(int(i) for i in indices)
    if len(idx) <= max_frames:
        return idx
    if max_frames == 1:
        return [idx[-1]]
    pos = np.unique(np.rint(np.linspace(0, len(idx) - 1, max_frames)).astype(np.int64))
    return [idx[p] for p in pos]


def default_quantity(kind: str) -> str:
    """The quantity a report maps when none is named: ``magnitude`` (2-D, px) or ``W`` (stereo, mm)."""
    return "W" if kind == "stereo" else "magnitude"


def _backdrop(image, xs, ys, map_width: int) -> np.ndarray:
    """The grey reference image beneath a map, at the map's pixel centres ``xs`` (w,), ``ys`` (h,) (image px):
    the backdrop of every Specula map (:func:`dic.plots._common.backdrop`: block means of ``f x f`` image px,
    stretched over their 1st-99th percentiles, 8 grey levels; it shows the specimen, not the speckle, and
    keeps the picture small), (h, w) float64 in [0, 255]."""
    from .plots._common import BACKDROP_COARSENESS, backdrop

    grey, _ = backdrop(image, map_width)
    f = min(max(1, int(round(BACKDROP_COARSENESS * image.shape[1] / max(float(map_width), 1.0)))), *image.shape)
    rows = np.clip(np.rint(ys).astype(np.int64) // f, 0, grey.shape[0] - 1)
    cols = np.clip(np.rint(xs).astype(np.int64) // f, 0, grey.shape[1] - 1)
    return grey[rows[:, None], cols[None, :]] * 255.0


def _pixel_index(points, xs, ys) -> np.ndarray:
    """For each map pixel (centres ``xs`` (w,), ``ys`` (h,), image px), the index of the point whose grid cell
    (``step`` wide, centred on the point; :func:`dic.grid_layout`) contains it, -1 where none, (h, w) int64.
    Points on no grid: the nearest point within half the median point spacing."""
    from ._strain import grid_layout

    has = np.flatnonzero(np.all(np.isfinite(points), axis=1))
    out = np.full((ys.size, xs.size), -1, dtype=np.int64)
    if has.size == 0:
        return out
    pts = points[has]
    try:
        index, (ny, nx), (dx, dy) = grid_layout(pts)
    except ValueError:  # points on no grid
        from scipy.spatial import cKDTree

        tree = cKDTree(pts)
        spacing = np.median(tree.query(pts, k=2)[0][:, 1]) if pts.shape[0] > 1 else 1.0
        gx, gy = np.meshgrid(xs, ys)
        dist, nearest = tree.query(np.column_stack([gx.ravel(), gy.ravel()]), distance_upper_bound=0.5 * spacing)
        found = np.isfinite(dist)
        flat = out.reshape(-1)
        flat[found] = has[nearest[found]]
        return out
    cell = np.full(ny * nx, -1, dtype=np.int64)
    cell[index[:, 1] * nx + index[:, 0]] = has
    cols = np.rint((xs - pts[:, 0].min()) / dx).astype(np.int64)
    rows = np.rint((ys - pts[:, 1].min()) / dy).astype(np.int64)
    col_ok, row_ok = (cols >= 0) & (cols < nx), (rows >= 0) & (rows < ny)
    out[np.ix_(row_ok, col_ok)] = cell[rows[row_ok][:, None] * nx + cols[col_ok][None, :]]
    return out


def render_map(points, values, image_shape, limits, lut, *, image=None, width: int = MAP_WIDTH,
               alpha: float = MAP_ALPHA, pixel_index=None) -> np.ndarray:
    """One field map as (h, w, 3) uint8 pixels (module docstring).

    ``points`` (N, 2) reference image px (NaN rows: no position), ``values`` (N,) (NaN: not valid),
    ``image_shape`` (H, W) of the reference image, ``limits`` (vmin, vmax), ``lut`` (256, 3) uint8
    (:func:`dic.plots.report.colour_lut`), ``image`` the (H, W) grey reference image or None, ``width``
    the most pixels across (the map is ``round(W s)`` x ``round(H s)`` with ``s = width / W`` for an
    image wider than ``width``, else the largest whole enlargement ``s = width // W``, each image pixel
    then drawn as an s x s block). Map pixel (i, j) stands for image point ``((j + 0.5) / s - 0.5,
    (i + 0.5) / s - 0.5)``. ``pixel_index``: the cells of these points worked out before
    (:func:`map_geometry`), for the frames of one file.
    """
    pts = np.asarray(points, dtype=np.float64)
    vals = np.asarray(values, dtype=np.float64).reshape(-1)
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] != vals.size:
        raise ValueError(f"points must be (N, 2) and values (N,), got {pts.shape} and {vals.shape}")
    lo, hi = (float(v) for v in limits)
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise ValueError(f"limits must be two finite numbers vmin < vmax, got {limits!r}")
    lut = np.asarray(lut)
    if lut.shape != (256, 3) or lut.dtype != np.uint8:
        raise ValueError(f"lut must be a (256, 3) uint8 table, got {lut.dtype} {lut.shape}")
    xs, ys = map_geometry(image_shape, width)
    H, W = (int(n) for n in image_shape)
    if image is not None and np.asarray(image).shape != (H, W):
        raise ValueError(f"image has shape {np.asarray(image).shape}, the result's reference image is {(H, W)}")
    cell = _pixel_index(pts, xs, ys) if pixel_index is None else pixel_index
    # colours per point (Matplotlib's rule: entry min(255, floor(256 t))), then one gather per pixel
    t = np.clip((np.where(np.isfinite(vals), vals, lo) - lo) / (hi - lo), 0.0, 1.0)
    colour = np.concatenate([lut[np.minimum(np.floor(t * 256.0), 255).astype(np.int64)],
                             np.zeros((1, 3), np.uint8)])
    valid = np.concatenate([np.isfinite(vals), [False]])
    cell = np.where(cell >= 0, cell, vals.size)  # no cell: the extra entry, not valid
    has = valid[cell]
    if image is None:
        out = np.full((ys.size, xs.size, 3), _PAPER, dtype=np.uint8)
        out[has] = colour[cell[has]]
        return out
    grey = _backdrop(np.asarray(image, dtype=np.float64), xs, ys, xs.size).astype(np.float32)
    blend = alpha * colour[cell].astype(np.float32) + (1.0 - alpha) * grey[:, :, None]
    out = np.where(has[:, :, None], blend, grey[:, :, None])
    return np.rint(out).astype(np.uint8)


def map_geometry(image_shape, width: int = MAP_WIDTH) -> tuple[np.ndarray, np.ndarray]:
    """The image points (px) that the map pixels stand for: ``xs`` (w,) and ``ys`` (h,) (:func:`render_map`)."""
    H, W = (int(n) for n in image_shape)
    if H < 1 or W < 1:
        raise ValueError(f"image_shape must be (H, W) with H, W >= 1, got {image_shape!r}")
    s = float(width) / W if W > width else float(max(1, int(width) // W))
    w, h = max(1, int(round(W * s))), max(1, int(round(H * s)))
    return (np.arange(w) + 0.5) / s - 0.5, (np.arange(h) + 0.5) / s - 0.5


def frame_quality(reader, index: int) -> dict[str, float]:
    """Quality numbers of one finished frame of an open :class:`dic.store.ResultReader` (module docstring):
    ``valid_fraction``, ``region_points``, ``valid_points``, ``zncc_median``, and when the file holds them
    ``sigma_u_median`` / ``sigma_v_median`` (px), ``iterations_mean`` (2-D), ``zncc_left_median``,
    ``zncc_right_median``, ``reprojection_median_px``, ``sigma_W_median_mm`` (stereo), ``seconds``."""
    def arr(name):
        got = reader.frame_arrays(index, [name])
        return None if got is None else np.asarray(got[0])

    def median(a, mask):
        if a is None:
            return np.nan
        a = np.asarray(a, dtype=np.float64)
        sel = a[mask] if a.ndim == 1 else a[mask].reshape(-1)
        sel = sel[np.isfinite(sel)]
        return float(np.median(sel)) if sel.size else np.nan

    out: dict[str, float] = {}
    if reader.kind.name == "stereo":
        from .field3d import StereoStatus

        status = arr("status")
        region = status != StereoStatus.NOT_COMPUTED
        valid = status == StereoStatus.OK
        out["zncc_median"] = median(arr("zncc_stereo"), valid)
        out["zncc_left_median"] = median(arr("zncc_left"), valid)
        out["zncc_right_median"] = median(arr("zncc_right"), valid)
        out["reprojection_median_px"] = median(arr("reprojection_px"), valid)
        sig = arr("sigma_uvw_mm")
        if sig is not None and sig.ndim == 2 and sig.shape[1] == 3:
            out["sigma_W_median_mm"] = median(sig[:, 2], valid)
    else:
        valid = arr("valid")
        if valid is None:
            status = arr("status")
            valid = status == 0 if status is not None else np.isfinite(arr("u"))
        valid = valid.astype(bool)
        region = np.ones(valid.shape, bool)  # a 2-D file stores the points of its region only
        out["zncc_median"] = median(arr("zncc"), valid)
        for name in ("sigma_u", "sigma_v"):
            a = arr(name)
            if a is not None:
                out[f"{name}_median"] = median(a, valid)
        it = arr("iterations")
        if it is not None and valid.any():
            out["iterations_mean"] = float(np.mean(it[valid]))
    n_region, n_valid = int(region.sum()), int((valid & region).sum())
    out["region_points"], out["valid_points"] = n_region, n_valid
    out["valid_fraction"] = n_valid / n_region if n_region else np.nan
    seconds = reader.frame_attrs(index).get("seconds")
    out["seconds"] = float(seconds) if seconds is not None else np.nan
    return out


#: per-frame quality curves of the report: key of :func:`frame_quality` -> axis label
_QUALITY_LABELS = {
    "valid_fraction": "valid fraction\n(of the region)",
    "zncc_median": "median ZNCC",
    "zncc_left_median": "median ZNCC\nleft track",
    "zncc_right_median": "median ZNCC\nright track",
    "sigma_u_median": "median σu (px)",
    "sigma_v_median": "median σv (px)",
    "sigma_W_median_mm": "median σW (mm)",
    "iterations_mean": "mean IC-GN\niterations",
    "reprojection_median_px": "median reproj.\nerror (px)",
    "seconds": "seconds\nper frame",
}


def _unit(kind: str, quantity: str) -> str:
    if kind == "stereo":
        from .plots.fields import FIGURE_QUANTITIES

        unit = FIGURE_QUANTITIES.get(quantity, ("", "", None))[1]
        return "" if unit == "1" else unit
    return _UNITS_2D.get(quantity, "")


def _points(values: list[tuple[float, float]] | None, what: str, n: int) -> list[tuple[float, ...]]:
    out = []
    for item in values or ():
        try:
            vals = tuple(float(v) for v in item)
        except (TypeError, ValueError):
            raise ValueError(f"each {what} must be {n} numbers, got {item!r}") from None
        if len(vals) != n or not all(np.isfinite(vals)):
            raise ValueError(f"each {what} must be {n} finite numbers, got {item!r}")
        out.append(vals)
    return out


def _data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _fmt(value) -> str:
    if isinstance(value, float):
        return "–" if not np.isfinite(value) else f"{value:.6g}"
    if isinstance(value, (dict, list, tuple)):
        return json.dumps(value, default=str)
    return str(value)


def _table(rows, header=None) -> str:
    esc = html.escape
    head = "" if header is None else "<tr>" + "".join(f"<th>{esc(str(h))}</th>" for h in header) + "</tr>"
    body = "".join("<tr>" + "".join(f"<td>{esc(_fmt(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table>{head}{body}</table>"


_STYLE = """
body{font-family:sans-serif;margin:16px;color:#222;max-width:1100px}
h1{font-size:1.4em}h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;font-size:0.85em}td,th{border:1px solid #ddd;padding:2px 6px;text-align:left}
#mapbox img{display:none;image-rendering:pixelated}
#mapbox img.shown{display:block}
.bar{display:flex;align-items:center;gap:8px;font-size:0.85em;margin:6px 0}
.bar img{width:256px;height:14px;image-rendering:pixelated}
.note{font-size:0.85em;color:#555}
"""

_SCRIPT = """
(function () {
  var imgs = Array.prototype.slice.call(document.querySelectorAll('#mapbox img'));
  var slider = document.getElementById('slider');
  var label = document.getElementById('frame-label');
  function show(pos, note) {
    imgs.forEach(function (im, k) { im.className = (k === pos) ? 'shown' : ''; });
    slider.value = String(pos);
    var frame = imgs[pos].getAttribute('data-frame');
    label.textContent = 'frame ' + frame + ' (' + (pos + 1) + ' of ' + imgs.length + ' shown)' + (note || '');
    document.body.setAttribute('data-shown-frame', frame);
    var r = imgs[pos].getBoundingClientRect();
    document.body.setAttribute('data-map-rect', [Math.round(r.left + window.scrollX), Math.round(r.top + window.scrollY),
      Math.round(r.width), Math.round(r.height)].join(','));
  }
  function fromHash() {
    var m = /(?:^#|&)frame=(\\d+)/.exec(window.location.hash);
    if (!m) { return null; }
    for (var k = 0; k < imgs.length; k++) {
      if (imgs[k].getAttribute('data-frame') === m[1]) { return [k, '']; }
    }
    return [imgs.length - 1, ' (frame ' + m[1] + ' is not in this report)'];
  }
  slider.addEventListener('input', function () {
    var pos = parseInt(slider.value, 10);
    show(pos, '');
    window.history.replaceState(null, '', '#frame=' + imgs[pos].getAttribute('data-frame'));
  });
  window.addEventListener('hashchange', function () { var h = fromHash(); if (h) { show(h[0], h[1]); } });
  var start = fromHash();
  if (start) { show(start[0], start[1]); } else { show(imgs.length - 1, ''); }
  document.body.setAttribute('data-report-ready', '1');
})();
"""


def write_report(results, path, *, quantity: str | None = None, image=None, history=(), extensometer=(),
                 max_frames: int = MAX_MAP_FRAMES, map_width: int = MAP_WIDTH) -> Path:
    """Write the HTML run report of a result file to ``path``; returns the path (module docstring).

    Parameters
    ----------
    results : str or path-like
        A 2-D or stereo result file.
    path : str or path-like
        The HTML file to write (``.html`` or ``.htm``); written whole or not at all.
    quantity : str, optional
        What the maps show (:func:`dic.animate.animation_quantities`: 2-D ``u``, ``v``, ``magnitude``
        and the stored strains; stereo ``Z``, ``U``, ``V``, ``W``, ``exx``, ``eyy``, ``exy``,
        ``zncc_stereo``); default :func:`default_quantity`.
    image : (H, W) array, optional
        The grey reference image (stereo: the left one) beneath the maps.
    history : sequence of (x, y)
        Reference points (image px; stereo: left image px) whose ``quantity`` is shown over the frames.
    extensometer : sequence of (x1, y1, x2, y2)
        Gauge ends (reference image px) of virtual extensometers.
    max_frames : int
        The most frames with a map (:data:`MAX_MAP_FRAMES`); more are decimated evenly.
    map_width : int
        The most pixels across a map, 64 to 4096.
    """
    from kernels._atomic import atomic_output
    from kernels.checks import positive_int

    from . import postprocess
    from .plots import report as pictures
    from .plots._common import colour_scale
    from .plots.animate import frame_quantities, frame_values, movie_limits
    from .plots.fields import SIGNED
    from .store import ResultReader

    if not isinstance(results, (str, os.PathLike)):
        raise ValueError(f"results must be a result file (path), got {type(results).__name__}")
    out = Path(os.fspath(path))
    if out.suffix.lower() not in (".html", ".htm"):
        raise ValueError(f"the report file must end in .html or .htm, got {out.name!r}")
    if out.is_dir():
        raise ValueError(f"{out} is a folder; give the report's file name")
    map_width = positive_int(map_width, "map_width", minimum=64, maximum=4096)
    max_frames = positive_int(max_frames, "max_frames")
    points_h = _points(history, "history point (x, y)", 2)
    gauges = _points(extensometer, "extensometer (x1, y1, x2, y2)", 4)
    img = None
    if image is not None:
        img = np.asarray(image, dtype=np.float64)
        if img.ndim != 2:
            raise ValueError(f"image must be the (H, W) grey reference image, got shape {img.shape}")

    esc = html.escape
    results = Path(os.fspath(results))
    with ResultReader(results) as reader:
        kind = reader.kind.name
        indices = reader.done_frames()
        if not indices:
            raise ValueError(f"{results} has no finished frame; nothing to report")
        ref = reader.reference
        shape = tuple(ref["shape"]) if len(ref.get("shape", ())) == 2 else None
        settings, attrs = reader.settings, reader.attrs
        shown = report_frames(indices, max_frames)
        first = reader.read_frame(shown[0])
        known = frame_quantities(first)
        quantity = default_quantity(kind) if quantity is None else str(quantity)
        if quantity not in known:
            raise ValueError(f"unknown quantity {quantity!r} for this {'stereo' if kind == 'stereo' else '2-D'} "
                             f"result file; choose from {', '.join(known)}")
        if shape is None:
            pts = np.asarray(first.points, dtype=np.float64)
            shape = (int(np.nanmax(pts[:, 1])) + 1, int(np.nanmax(pts[:, 0])) + 1)
        if img is not None and img.shape != shape:
            raise ValueError(f"image has shape {img.shape}, the result's reference image is {shape}")
        # the maps: one colour range over the shown frames
        per_frame = []
        for i in shown:
            frame = first if i == shown[0] else reader.read_frame(i)
            per_frame.append((i, np.asarray(frame.points, dtype=np.float64), frame_values(frame, quantity)))
        finite = np.concatenate([v[np.isfinite(v)] for _, _, v in per_frame])
        if finite.size == 0:
            raise ValueError(f"{quantity} has no valid value in the frames of {results}; choose another quantity")
        lo, hi = movie_limits(finite, quantity)
        cmap, lo, hi = colour_scale(finite, signed=quantity in SIGNED, fixed=(lo, hi))
        lut = pictures.colour_lut(cmap)
        maps, cells = [], {}
        xs, ys = map_geometry(shape, map_width)
        for i, p, v in per_frame:  # the cells of the points once per set of points (2-D: the same every frame)
            key = p.tobytes()
            if key not in cells:
                cells = {key: _pixel_index(p, xs, ys)}
            maps.append((i, pictures.png_bytes(render_map(p, v, shape, (lo, hi), lut, image=img, width=map_width,
                                                          pixel_index=cells[key]))))
        bar = pictures.png_bytes(lut[None, :, :])
        # quality over every finished frame
        quality = [frame_quality(reader, i) for i in indices]
        shape_png = None
        if kind == "stereo":
            ref_state = reader.read_frame(0) if 0 in indices else first
            try:
                shape_png = pictures.shape3d_png(ref_state.X, ref_state.Y, ref_state.Z,
                                                 title=f"state {ref_state.index}, {ref_state.frame_name} frame")
            except ValueError:
                shape_png = None

    unit = _unit(kind, quantity)
    unit_txt = f" {unit}" if unit else ""
    keys = [k for k in _QUALITY_LABELS if any(k in q for q in quality)]
    series = {_QUALITY_LABELS[k]: np.array([q.get(k, np.nan) for q in quality], dtype=np.float64) for k in keys
              if np.isfinite([q.get(k, np.nan) for q in quality]).any()}
    quality_png = pictures.quality_png(indices, series)

    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>Specula report: "
             f"{esc(results.name)}</title><style>{_STYLE}</style></head><body>"]
    label = "stereo DIC" if kind == "stereo" else "2-D DIC"
    parts.append(f"<h1>Specula run report: {esc(results.name)}</h1>")
    ref_paths = [ref.get(k, "") for k in ("path", "left_path", "right_path") if ref.get(k)]
    summary = [("file", str(results)), ("kind", label), ("finished frames", f"{len(indices)} ({indices[0]} to {indices[-1]})"),
               ("reference image(s)", ", ".join(ref_paths) or "–"), ("reference size (H x W px)", f"{shape[0]} x {shape[1]}"),
               ("Specula version", attrs.get("specula_version", "–")), ("created", attrs.get("created", "–")),
               ("updated", attrs.get("updated", "–"))]
    parts.append(_table(summary))

    # maps
    parts.append(f"<h2 id='maps'>{esc(quantity)}{esc(unit_txt and ' (' + unit + ')')} over the reference image</h2>")
    note = (f"{len(shown)} of {len(indices)} frames shown, evenly spaced (at most {max_frames} maps per report)"
            if len(shown) < len(indices) else f"all {len(indices)} finished frames")
    parts.append(f"<p class='note'>{esc(note)}; one colour range for every frame ({esc(cmap)}); grey: no valid "
                 f"value; open a frame with <code>#frame=K</code> in the address.</p>")
    parts.append(f"<div><input type='range' id='slider' min='0' max='{len(maps) - 1}' step='1' value='{len(maps) - 1}' "
                 "aria-label='frame' style='width:320px'> <span id='frame-label'></span></div>")
    parts.append(f"<div class='bar'><span>{esc(f'{lo:.4g}')}</span><img alt='colour scale' src='{_data_uri(bar)}'>"
                 f"<span>{esc(f'{hi:.4g}')}{esc(unit_txt)}</span></div>")
    parts.append("<div id='mapbox'>")
    for k, (i, png) in enumerate(maps):
        h, w = _png_size(png)
        cls = " class='shown'" if k == len(maps) - 1 else ""
        parts.append(f"<img{cls} data-frame='{i}' id='map-{i}' width='{w}' height='{h}' alt='{esc(quantity)} frame {i}' "
                     f"src='{_data_uri(png)}'>")
    parts.append("</div>")

    # quality
    parts.append("<h2 id='quality'>Quality per frame</h2>")
    parts.append("<p class='note'>Valid fraction over the region "
                 + ("(points with a status other than NOT_COMPUTED); " if kind == "stereo" else "(the stored points); ")
                 + "medians over the valid points.</p>")
    parts.append(f"<img alt='quality per frame' src='{_data_uri(quality_png)}'>")
    header = ["frame", "valid points", "region points"] + [_QUALITY_LABELS[k].replace("\n", " ") for k in keys
                                                           if k != "valid_fraction"]
    rows = [[i, q["valid_points"], q["region_points"]] + [q.get(k, np.nan) for k in keys if k != "valid_fraction"]
            for i, q in zip(indices, quality)]
    parts.append(f"<details><summary>table</summary>{_table(rows, header)}</details>")

    # histories and extensometers
    if points_h:
        hists = [postprocess.point_history(results, p, quantity) for p in points_h]
        parts.append("<h2 id='history'>Point histories</h2>")
        parts.append(f"<img alt='point histories' src='{_data_uri(pictures.history_png(hists))}'>")
        rows = [[int(f)] + [h.values[k] for h in hists] for k, f in enumerate(hists[0].frames)]
        header = ["frame"] + [f"{h.quantity} at ({h.point[0]:g}, {h.point[1]:g}) px" + (f" ({h.unit})" if h.unit else "")
                              for h in hists]
        parts.append(f"<details><summary>table</summary>{_table(rows, header)}</details>")
    if gauges:
        parts.append("<h2 id='extensometers'>Virtual extensometers</h2>")
        for g in gauges:
            ext = postprocess.extensometer(results, g[:2], g[2:])
            parts.append(f"<img alt='extensometer' src='{_data_uri(pictures.extensometer_png(ext))}'>")
            names, table = ext.table()
            parts.append(f"<details><summary>table ({esc(f'({g[0]:g}, {g[1]:g}) -> ({g[2]:g}, {g[3]:g}) px')})"
                         f"</summary>{_table([[int(r[0])] + list(r[1:]) for r in table], names)}</details>")

    if shape_png is not None:
        parts.append("<h2 id='shape'>3-D shape of the reference state</h2>")
        parts.append(f"<img alt='3-D shape' src='{_data_uri(shape_png)}'>")

    parts.append("<h2 id='settings'>Run settings</h2>")
    parts.append(_table(sorted(settings.items())) if settings else "<p class='note'>none stored</p>")
    parts.append(f"<script>{_SCRIPT}</script></body></html>")
    with atomic_output(out) as tmp:
        tmp.write_text("\n".join(parts), encoding="utf-8")
    return out


def _png_size(png: bytes) -> tuple[int, int]:
    """(height, width) of a PNG from its IHDR chunk."""
    width = int.from_bytes(png[16:20], "big")
    height = int.from_bytes(png[20:24], "big")
    return height, width
