"""Shared plumbing of :mod:`dic.plots`: Agg figures, colour limits and saving.

Every figure is a :class:`matplotlib.figure.Figure` with its own Agg canvas (Matplotlib's object
API, no pyplot): nothing changes the global backend of the user's session, figures are not kept in
pyplot's registry (no ``close`` needed), and drawing works headless and from threads. Matplotlib is
imported on first use, so importing :mod:`dic.plots` stays cheap.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

#: percentiles of the finite values that set the colour limits of a map (outliers do not stretch it)
LIMIT_PERCENTILES = (1, 99)


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
