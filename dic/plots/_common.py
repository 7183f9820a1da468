"""Shared plumbing of :mod:`dic.plots`: Agg figures, colour limits and maps, map panels and saving.

Every figure is a :class:`matplotlib.figure.Figure` with its own Agg canvas (Matplotlib's object
API, no pyplot): nothing changes the global backend of the user's session, figures are not kept in
pyplot's registry (no ``close`` needed), and drawing works headless and from threads. Matplotlib is
imported on first use, so importing :mod:`dic.plots` stays cheap.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: percentiles of the finite values that set the colour limits of a map (outliers do not stretch it)
LIMIT_PERCENTILES = (1, 99)

#: colour map of a signed quantity whose range spans zero (limits symmetric about zero, white at zero)
DIVERGING_CMAP = "RdBu_r"
#: colour map of a one-signed range (e.g. v from -12 to -5 px) and of unsigned quantities
SEQUENTIAL_CMAP = "viridis"


def new_figure(figsize, **kwargs):
    """A Matplotlib ``Figure`` of ``figsize`` (width, height) inches, drawn by its own Agg canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    width, height = (float(s) for s in figsize)
    if not (width > 0 and height > 0 and np.isfinite(width) and np.isfinite(height)):
        raise ValueError(f"figsize must be two positive finite sizes in inches, got {figsize!r}")
    fig = Figure(figsize=(width, height), **kwargs)
    FigureCanvasAgg(fig)
    return fig


def colormap(name: str):
    """The registered Matplotlib colour map ``name`` (e.g. ``"tab10"``)."""
    import matplotlib

    return matplotlib.colormaps[name]


def save_figure(fig, path, *, dpi: float) -> Path:
    """Save ``fig`` to ``path`` (format from the suffix, e.g. ``.png``, ``.pdf``; parent folders created).

    Returns the path as a :class:`~pathlib.Path`.
    """
    p = Path(os.fspath(path))
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi!r}")
    from kernels._atomic import atomic_output

    if not p.suffix:  # what Matplotlib does with a name without a suffix
        p = p.with_name(p.name + ".png")
    with atomic_output(p) as tmp:  # whole or not at all
        fig.savefig(tmp, dpi=dpi, format=p.suffix.lstrip(".").lower())
    return p


def save_map_png(fig, path, *, dpi: float) -> Path:
    """Save a map figure as a compact PNG: its ticks frozen (:func:`freeze_ticks`; the figure is
    changed), drawn once by Agg at ``dpi`` with its plain tick labels drawn by Pillow instead
    (:data:`RASTER_TEXT_GIDS`), stored as 8-bit RGB (no alpha channel, white background) with zlib
    level 1 (the 1.3 MP figure below: 382 KB in 0.045 s of CPU; level 3 is 361 KB in 0.064 s, level 6
    9 % smaller again at twice the time). Other suffixes go to :func:`save_figure`.

    Returns the path. A 1 MP frame's 5-panel figure (:func:`dic.plots.fields.field_figure`) stays under
    500 KB this way (bench/figures.py).
    """
    p = Path(os.fspath(path))
    if p.suffix.lower() != ".png":
        return save_figure(fig, p, dpi=dpi)
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi!r}")
    from PIL import Image

    p.parent.mkdir(parents=True, exist_ok=True)
    fig.set_dpi(dpi)
    # the plain tick labels are drawn into the raster by Pillow: Matplotlib's Text costs about 1 ms a
    # label to build and draw, a 5-panel map has about 100 of them, Pillow's text is about 20x cheaper
    labels: list = []
    freeze_ticks(fig, raster_labels=labels)
    family = _default_family()
    raster = [t for ax in fig.axes for t in ax.texts if _rasterisable(t, family)]  # e.g. the colourbars' tick labels
    for t in raster:
        x, y = t.get_transform().transform(t.get_position())
        labels.append((x, y, t.get_text(), t.get_ha(), t.get_va(), t.get_fontsize(), t.get_color()))
        t.set_visible(False)
    try:
        canvas = fig.canvas
        canvas.draw()
        width, height = canvas.get_width_height(physical=True)
        image = Image.frombuffer("RGBA", (width, height), canvas.buffer_rgba(), "raw", "RGBA", 0, 1).convert("RGB")
    finally:
        for t in raster:
            t.set_visible(True)
    _draw_texts(image, labels, fontfile=_font_file(), dpi=dpi)
    from kernels._atomic import atomic_output

    with atomic_output(p) as tmp:  # whole or not at all, as save_figure
        image.save(tmp, format="PNG", compress_level=1)
    return p


#: gids of the plain one-line texts :func:`save_map_png` draws into the raster with Pillow (the frozen
#: tick labels of :func:`freeze_ticks` and the colourbar tick labels of :func:`draw_colourbar`)
RASTER_TEXT_GIDS = frozenset({"tick-label", "colourbar-tick-label"})

#: Matplotlib's text alignment -> Pillow's anchor letters (horizontal; vertical)
_PIL_HORIZONTAL = {"left": "l", "center": "m", "right": "r"}
_PIL_VERTICAL = {"top": "t", "bottom": "d", "center": "m", "center_baseline": "m", "baseline": "s"}


def _plain(s: str) -> bool:
    """A one-line label without mathtext."""
    return bool(s) and "\n" not in s and "$" not in s


def _rasterisable(text, family) -> bool:
    """Whether ``text`` is a plain, upright, one-line label in the font ``family`` (Matplotlib's default,
    :func:`_default_family`, worked out once per figure) that Pillow can draw as Matplotlib would."""
    return (text.get_gid() in RASTER_TEXT_GIDS and text.get_visible() and _plain(text.get_text())
            and text.get_rotation() == 0 and text.get_ha() in _PIL_HORIZONTAL and text.get_va() in _PIL_VERTICAL
            and text.get_fontproperties().get_family() == family)


def _default_family():
    import matplotlib as mpl
    from matplotlib.font_manager import FontProperties

    return FontProperties(family=mpl.rcParams["font.family"]).get_family()


def _font_file() -> str:
    """The file of Matplotlib's default font (what its texts are drawn in)."""
    import matplotlib as mpl
    from matplotlib.font_manager import FontProperties, findfont

    return findfont(FontProperties(family=mpl.rcParams["font.family"]))


def _pil_font(path: str, size_px: int):
    from PIL import ImageFont

    key = (path, size_px)
    if key not in _FONTS:
        _FONTS[key] = ImageFont.truetype(path, size_px)
    return _FONTS[key]


_FONTS: dict = {}


def _draw_texts(image, labels, *, fontfile: str, dpi: float) -> None:
    """Draw ``labels`` ``(x, y, text, ha, va, fontsize, colour)`` (display px from the bottom left,
    Matplotlib's alignment names, points, a Matplotlib colour) into the Pillow ``image`` in the font
    file ``fontfile``, as Matplotlib would draw them."""
    if not labels:
        return
    from matplotlib.colors import to_rgb
    from PIL import ImageDraw

    draw = ImageDraw.Draw(image)
    height = image.height
    for x, y, text, ha, va, size, colour in labels:
        font = _pil_font(fontfile, max(1, int(round(size * dpi / 72.0))))
        rgb = tuple(int(round(255 * c)) for c in to_rgb(colour))
        draw.text((float(x), height - float(y)), text, fill=rgb, font=font, anchor=_PIL_HORIZONTAL[ha] + _PIL_VERTICAL[va])


def freeze_ticks(fig, *, raster_labels: list | None = None) -> None:
    """Replace the live ticks of every axes of ``fig`` by fixed tick marks and labels, for a figure
    that is only saved (never zoomed or panned).

    The positions and texts are Matplotlib's own (each axis's locator and formatter at the current
    view limits), drawn as one line of tick markers and plain texts per axis (gid ``"tick-label"``); the
    axis label is placed beyond the tick labels. Ticks are taken on the side of the axis label (the map
    figures keep Matplotlib's default sides; asking Matplotlib for the ticks' side would build the tick
    objects this avoids). Matplotlib's tick objects cost more to build and draw than the rest of a map
    figure: freezing them about halves the time of a 5-panel map (bench/figures.py).

    ``raster_labels``: a list to receive the tick labels as ``(x, y, text, ha, va, fontsize, colour)``
    (display px from the bottom left, as :func:`save_map_png` draws them with Pillow) instead of Text
    artists in the figure.
    """
    import matplotlib as mpl
    from matplotlib.markers import TICKDOWN, TICKLEFT, TICKRIGHT, TICKUP
    from matplotlib.transforms import ScaledTranslation

    fontsize = mpl.font_manager.FontProperties(size=mpl.rcParams["xtick.labelsize"]).get_size_in_points()
    length, pad = mpl.rcParams["xtick.major.size"], mpl.rcParams["xtick.major.pad"]
    width = mpl.rcParams["xtick.major.width"]
    markers = {"bottom": TICKDOWN, "top": TICKUP, "left": TICKLEFT, "right": TICKRIGHT}
    for ax in fig.axes:
        box = ax.get_position()
        w_in, h_in = box.width * fig.get_figwidth(), box.height * fig.get_figheight()
        for axis, name in ((ax.xaxis, "x"), (ax.yaxis, "y")):
            side = axis.get_label_position()
            if not axis.get_visible() or side not in markers:
                continue
            lo, hi = sorted(axis.get_view_interval())
            tol = 1e-9 * max(abs(hi - lo), 1e-300)
            locs = [float(v) for v in axis.get_majorticklocs() if lo - tol <= v <= hi + tol]
            labels = axis.get_major_formatter().format_ticks(locs) if locs else []
            axis.set_ticks([])
            sign = -1.0 if side in ("bottom", "left") else 1.0
            edge = 0.0 if sign < 0 else 1.0
            base = ax.get_xaxis_transform() if name == "x" else ax.get_yaxis_transform()
            d = sign * (length + pad) / 72.0
            # tick labels: `length + pad` points out of the axes edge
            shift = ScaledTranslation(0.0, d, fig.dpi_scale_trans) if name == "x" else \
                ScaledTranslation(d, 0.0, fig.dpi_scale_trans)
            text_t = base + shift
            xy = (locs, [edge] * len(locs)) if name == "x" else ([edge] * len(locs), locs)
            ax.plot(*xy, linestyle="none", marker=markers[side], markersize=length, markeredgewidth=width,
                    color="k", transform=base, clip_on=False, scalex=False, scaley=False)
            for v, lab in zip(locs, labels):
                if name == "x":
                    at, ha, va = (v, edge), "center", "top" if sign < 0 else "bottom"
                else:
                    at, ha, va = (edge, v), "right" if sign < 0 else "left", "center_baseline"
                if raster_labels is not None and _plain(lab):
                    x, y = text_t.transform(at)
                    raster_labels.append((x, y, lab, ha, va, fontsize, "k"))
                else:
                    ax.text(*at, lab, transform=text_t, fontsize=fontsize, ha=ha, va=va, clip_on=False,
                            gid="tick-label")
            # the axis label beyond the tick labels (their size estimated from the font size)
            if name == "x":
                off_in = (length + pad + 1.2 * fontsize + 3.0) / 72.0
                axis.set_label_coords(0.5, edge + sign * off_in / h_in)
            else:
                widest = max((len(t) for t in labels), default=0)
                off_in = (length + pad + 0.6 * fontsize * widest + 4.0) / 72.0
                axis.set_label_coords(edge + sign * off_in / w_in, 0.5)


def spans_zero(lo: float, hi: float) -> bool:
    """Whether the colour range ``(lo, hi)`` has values on both sides of zero."""
    return lo < 0.0 < hi


def colour_scale(values, *, signed: bool, fixed=None, vmin: float | None = None,
                 vmax: float | None = None) -> tuple[str, float, float]:
    """The colour map name and limits ``(cmap, vmin, vmax)`` of one map.

    The rule: the range is ``fixed`` when given, else the 1st-99th percentiles of the finite
    ``values`` (:data:`LIMIT_PERCENTILES`); a ``signed`` quantity (displacement, strain) whose range
    spans zero is drawn on :data:`DIVERGING_CMAP` with limits symmetric about zero (white = 0);
    any one-signed range (e.g. v from -12 to -5 px, W from 0.011 to 0.022 mm) and unsigned
    quantities are drawn on :data:`SEQUENTIAL_CMAP` over their own range (:func:`padded_limits`), so an
    offset field is not flattened into one shade. ``vmin`` / ``vmax`` replace either end (then
    used as given, not re-centred); the map is chosen on the final range.
    """
    if fixed is not None:
        lo, hi = (float(v) for v in fixed)
    else:
        lo, hi = padded_limits(values)
        if signed and spans_zero(lo, hi):
            m = max(abs(lo), abs(hi))
            lo, hi = -m, m
    lo = lo if vmin is None else float(vmin)
    hi = hi if vmax is None else float(vmax)
    return (DIVERGING_CMAP if signed and spans_zero(lo, hi) else SEQUENTIAL_CMAP), lo, hi


#: the grey backdrop of a map has one block mean per this many pixels of the drawn panel
BACKDROP_COARSENESS = 3.0
#: grey levels of the backdrop (between its 1st and 99th percentiles)
BACKDROP_LEVELS = 8


def backdrop(image, panel_px: float) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The grey image to draw beneath a map panel ``panel_px`` pixels wide, in [0, 1], and its
    extent ``(left, right, bottom, top)`` in image px (Matplotlib's ``imshow(extent=)``).

    Block means of the image over ``f x f`` pixels, ``f`` the integer nearest to
    :data:`BACKDROP_COARSENESS` x width / ``panel_px``, stretched between their 1st and 99th
    percentiles and rounded to :data:`BACKDROP_LEVELS` grey levels. The backdrop shows the specimen
    (edges, holes, the region) rather than the speckle: a speckle resampled to a panel's few hundred
    pixels is noise that hides the colours and triples the size of a PNG, and Agg then need not
    resample a megapixel for every panel. The grey image is (H // f, W // f) float64.
    """
    img = np.asarray(image, dtype=np.float64)
    f = max(1, int(round(BACKDROP_COARSENESS * img.shape[1] / max(float(panel_px), 1.0))))
    f = min(f, *img.shape)
    H, W = (img.shape[0] // f) * f, (img.shape[1] // f) * f
    if f > 1:
        img = img[:H, :W].reshape(H // f, f, W // f, f).mean(axis=(1, 3))
    extent = (-0.5, W - 0.5, H - 0.5, -0.5)
    fin = np.isfinite(img)
    if not fin.any():
        return np.full(img.shape, 0.5), extent
    lo, hi = np.percentile(img[fin], LIMIT_PERCENTILES)
    scaled = np.clip((np.where(fin, img, lo) - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return np.round(scaled * (BACKDROP_LEVELS - 1)) / (BACKDROP_LEVELS - 1), extent


#: panel layout of the map figures (inches): room left of a panel (y ticks and label), below it
#: (x ticks and label), above it (title), between panel and colourbar, the colourbar's width, and
#: right of the colourbar (its ticks and label)
MARGINS_IN = {"left": 0.75, "bottom": 0.55, "top": 0.38, "gap": 0.08, "bar": 0.16, "right": 1.2}


def map_panels(n: int, *, ncols: int, panel_w: float, aspect: float, suptitle: bool, dpi: float,
               right: float | None = None):
    """A figure of ``n`` map panels in rows of ``ncols``, each ``panel_w`` inches wide and ``panel_w *
    aspect`` high, with room for a colourbar beside each one exactly as tall as the panel.

    Returns ``(fig, [(ax, bar), ...])``: one Axes per panel and the colourbar's place right of it,
    ``bar = (x0, x1)`` in the panel's axes fraction (:func:`draw_colourbar` draws it there, inside the
    panel's Axes: an Axes costs Matplotlib about 15 ms to build, a third of a 5-panel map). The figure's
    size is the panels plus :data:`MARGINS_IN`, so there is no empty band above or below the maps;
    ``right`` replaces the room right of each colourbar (inches), e.g. for long tick names.
    """
    m = MARGINS_IN if right is None else {**MARGINS_IN, "right": float(right)}
    nrows = -(-n // ncols)
    panel_h = panel_w * aspect
    cell_w = m["left"] + panel_w + m["gap"] + m["bar"] + m["right"]
    cell_h = m["top"] + panel_h + m["bottom"]
    head = 0.4 if suptitle else 0.0
    fig_w, fig_h = cell_w * ncols, cell_h * nrows + head
    from matplotlib.ticker import MaxNLocator

    fig = new_figure((fig_w, fig_h), dpi=dpi)
    bar = (1.0 + m["gap"] / panel_w, 1.0 + (m["gap"] + m["bar"]) / panel_w)
    pairs = []
    for k in range(n):
        r, c = divmod(k, ncols)
        x0 = c * cell_w + m["left"]
        y0 = fig_h - head - r * cell_h - m["top"] - panel_h
        ax = fig.add_axes((x0 / fig_w, y0 / fig_h, panel_w / fig_w, panel_h / fig_h))
        for axis in (ax.xaxis, ax.yaxis):  # few ticks: each costs Matplotlib a copy of its properties
            axis.set_major_locator(MaxNLocator(nbins=4))
        pairs.append((ax, bar))
    return fig, pairs


@dataclass(frozen=True)
class Colourbar:
    """A colourbar drawn by :func:`draw_colourbar`: its gradient image (an ``AxesImage`` with the map's
    colour map and norm), the tick values and their labels (in the map's units), and the bar's label."""

    image: object
    ticks: tuple
    labels: tuple
    label: str | None


def draw_colourbar(ax, mappable, bar, *, label: str | None = None, ticks=None, ticklabels=None,
                   nbins: int = 5) -> Colourbar:
    """Draw the colourbar of ``mappable`` (a map image or scatter of ``ax``) beside the panel, in the
    place ``bar = (x0, x1)`` (axes fraction) that :func:`map_panels` keeps for it, as tall as the panel.

    The bar is a gradient image with the mappable's colour map, norm and opacity, framed like the axes,
    with tick marks and labels on its right (``ticks``/``ticklabels``, else at most ``nbins`` + 1
    round values of a :class:`~matplotlib.ticker.MaxNLocator`, formatted without an offset) and
    ``label`` beyond them. A :class:`~matplotlib.colors.BoundaryNorm` (classes such as the status
    map) gets one cell per class. The artists carry gids: ``"colourbar"`` (the gradient image),
    ``"colourbar-frame"``, ``"colourbar-ticks"``, ``"colourbar-tick-label"`` and ``"colourbar-label"``.
    Returns a :class:`Colourbar`.
    """
    import matplotlib as mpl
    from matplotlib.colors import BoundaryNorm
    from matplotlib.image import AxesImage
    from matplotlib.lines import Line2D
    from matplotlib.markers import TICKRIGHT
    from matplotlib.ticker import MaxNLocator, ScalarFormatter
    from matplotlib.transforms import ScaledTranslation

    x0, x1 = (float(v) for v in bar)
    norm, cmap = mappable.norm, mappable.get_cmap()
    if isinstance(norm, BoundaryNorm):  # classes: one cell each, ticks at the cells' centres
        edges = np.asarray(norm.boundaries, dtype=np.float64)
        values = 0.5 * (edges[:-1] + edges[1:])
        gradient = values[:, None]
        locs = values if ticks is None else np.asarray(ticks, dtype=np.float64)

        def position(v):
            return (np.searchsorted(edges, v) - 0.5) / len(values)
    else:
        lo, hi = float(norm.vmin), float(norm.vmax)
        gradient = np.linspace(lo, hi, 256)[:, None]
        if ticks is None:
            locs = MaxNLocator(nbins=nbins).tick_values(lo, hi)
            tol = 1e-9 * max(abs(hi - lo), 1e-300)
            locs = locs[(locs >= lo - tol) & (locs <= hi + tol)]
        else:
            locs = np.asarray(ticks, dtype=np.float64)

        def position(v):
            return (np.asarray(v, dtype=np.float64) - lo) / max(hi - lo, 1e-300)
    if ticklabels is None:
        formatter = ScalarFormatter(useOffset=False)
        formatter.create_dummy_axis()
        formatter.axis.set_view_interval(float(gradient.min()), float(gradient.max()))
        ticklabels = formatter.format_ticks(list(locs))
    ticklabels = [str(t) for t in ticklabels]
    # the gradient: constructed directly (not ax.imshow) so that it changes neither the data limits nor
    # the autoscaling of the map's axes
    image = AxesImage(ax, cmap=cmap, norm=norm, interpolation="nearest", origin="lower", extent=(x0, x1, 0.0, 1.0))
    image.set_data(gradient)
    image.set_transform(ax.transAxes)
    image.set_alpha(mappable.get_alpha())
    image.set_clip_on(False)
    image.set_gid("colourbar")
    ax.add_artist(image)
    # the frame as a line, not a patch: ``ax.patches`` keeps only what is drawn on the map
    ax.add_artist(Line2D([x0, x1, x1, x0, x0], [0.0, 0.0, 1.0, 1.0, 0.0], transform=ax.transAxes, clip_on=False,
                         linewidth=mpl.rcParams["axes.linewidth"], color=mpl.rcParams["axes.edgecolor"],
                         gid="colourbar-frame"))
    fontsize = mpl.font_manager.FontProperties(size=mpl.rcParams["ytick.labelsize"]).get_size_in_points()
    length, pad = mpl.rcParams["ytick.major.size"], mpl.rcParams["ytick.major.pad"]
    ys = position(locs) if len(locs) else np.zeros(0)
    ax.add_artist(Line2D(np.full(len(ys), x1), ys, linestyle="none", marker=TICKRIGHT, markersize=length,
                         markeredgewidth=mpl.rcParams["ytick.major.width"], color="k", transform=ax.transAxes,
                         clip_on=False, gid="colourbar-ticks"))
    fig = ax.get_figure()
    text_t = ax.transAxes + ScaledTranslation((length + pad) / 72.0, 0.0, fig.dpi_scale_trans)
    for y, lab in zip(ys, ticklabels):
        ax.text(x1, y, lab, transform=text_t, fontsize=fontsize, ha="left", va="center_baseline", clip_on=False,
                gid="colourbar-tick-label")
    if label:
        widest = max((len(t) for t in ticklabels), default=0)
        off = (length + pad + 0.6 * fontsize * widest + 4.0) / 72.0
        ax.text(x1, 0.5, label, transform=ax.transAxes + ScaledTranslation(off, 0.0, fig.dpi_scale_trans),
                rotation=90, ha="left", va="center", fontsize=mpl.rcParams["axes.labelsize"], clip_on=False,
                gid="colourbar-label")
    return Colourbar(image, tuple(float(v) for v in locs), tuple(ticklabels), label or None)


def percentile_limits(values, *, symmetric: bool = False) -> tuple[float, float] | None:
    """Colour limits ``(vmin, vmax)``: the 1st and 99th percentiles of the finite ``values``.

    ``symmetric=True`` centres them on 0 (``±max(|lo|, |hi|)``, for signed quantities drawn with a
    diverging map). A zero range is widened to 1e-12. Returns None when no value is finite (then
    Matplotlib's own scaling applies).
    """
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None
    lo, hi = np.percentile(v, LIMIT_PERCENTILES)
    if symmetric:
        m = max(abs(lo), abs(hi), 1e-12)
        lo, hi = -m, m
    if hi <= lo:
        hi = lo + 1e-12
    return float(lo), float(hi)


def padded_limits(values) -> tuple[float, float]:
    """Colour limits ``(vmin, vmax)``: the 1st and 99th percentiles of the finite ``values``,
    widened to ±1 % of their magnitude about their middle when the values are (nearly) uniform,
    so that a uniform map shows one colour rather than noise; ``(-1, 1)`` when none is finite.
    """
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return -1.0, 1.0
    lo, hi = np.percentile(v, LIMIT_PERCENTILES)
    pad = 0.01 * max(abs(lo), abs(hi)) or 1e-6
    if hi - lo < pad:  # (nearly) uniform: centre a +-1 % range on it
        mid = 0.5 * (lo + hi)
        lo, hi = mid - pad, mid + pad
    return float(lo), float(hi)
