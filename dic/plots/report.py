"""The pictures of a run report (:mod:`dic.report`, ``specula report``), as PNG bytes to embed in HTML.

* :func:`colour_lut` — a colour map as a (256, 3) uint8 look-up table (the report's field maps are
  coloured through it, without a figure per frame).
* :func:`png_bytes` — an (H, W, 3) uint8 array as PNG bytes.
* :func:`quality_png` — per-frame quality curves (valid fraction, ZNCC, sigma, iterations, seconds),
  one panel each, against the frame index.
* :func:`history_png`, :func:`extensometer_png` — :mod:`dic.plots.postprocess` figures as PNG bytes.
* :func:`shape3d_png` — a rendered 3-D view of a stereo state's shape (X, Y, Z in mm, coloured by Z).
"""
from __future__ import annotations

import io

import numpy as np

from ._common import colormap, new_figure

__all__ = ["colour_lut", "png_bytes", "quality_png", "history_png", "extensometer_png", "shape3d_png",
           "SHAPE_MAX_POINTS"]

#: the most points drawn in the 3-D shape view (an even subsample of the valid points beyond it)
SHAPE_MAX_POINTS = 20_000


def colour_lut(name: str) -> np.ndarray:
    """The Matplotlib colour map ``name`` as a (256, 3) uint8 table: Matplotlib's own 256-entry table in the
    8-bit form Matplotlib draws with (``cmap(k, bytes=True)``)."""
    cmap = colormap(name)
    if cmap.N != 256:
        cmap = cmap.resampled(256)
    return np.ascontiguousarray(cmap(np.arange(256), bytes=True)[:, :3])


def png_bytes(rgb) -> bytes:
    """An (H, W, 3) uint8 array (or (H, W) grey) encoded as PNG (Pillow, no gamma or colour profile chunk:
    a browser shows the stored values as sRGB)."""
    from PIL import Image

    arr = np.asarray(rgb)
    if arr.dtype != np.uint8 or arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3):
        raise ValueError(f"expected an (H, W, 3) or (H, W) uint8 image, got {arr.dtype} {arr.shape}")
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG", optimize=False, compress_level=4)
    return buf.getvalue()


def _figure_png(fig, dpi: float) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def quality_png(frames, series: dict, *, dpi: float = 80) -> bytes:
    """Per-frame quality curves as one PNG: ``frames`` (F,) frame indices, ``series`` an ordered dict
    ``label -> (F,) values`` (NaN: no value in that frame), one panel per label, sharing the frame axis."""
    frames = np.asarray(frames, dtype=np.float64)
    if not series:
        raise ValueError("quality_png needs at least one series")
    n = len(series)
    height = 1.45 * n + 0.5
    fig = new_figure((6.4, height))  # fixed margins: constrained layout costs a second per figure
    fig.subplots_adjust(left=0.16, right=0.97, top=1 - 0.15 / height, bottom=0.45 / height, hspace=0.12)
    axes = np.atleast_1d(fig.subplots(n, 1, sharex=True))
    for k, (ax, (label, values)) in enumerate(zip(axes, series.items())):
        vals = np.asarray(values, dtype=np.float64)
        if vals.shape != frames.shape:
            raise ValueError(f"series {label!r} has {vals.shape} values for {frames.shape[0]} frames")
        ax.plot(frames, vals, "o-", ms=3, color=f"C{k % 10}")
        ax.set_ylabel(label, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("frame", fontsize=8)
    from matplotlib.ticker import MaxNLocator

    axes[-1].xaxis.set_major_locator(MaxNLocator(integer=True))
    if frames.size == 1:  # one frame: its index as the only tick, not a fractional axis about it
        axes[-1].set_xlim(frames[0] - 1, frames[0] + 1)
        axes[-1].set_xticks([frames[0]])
    return _figure_png(fig, dpi)


def history_png(histories, *, dpi: float = 80) -> bytes:
    """:func:`dic.plots.postprocess.history_figure` of ``histories`` as PNG bytes."""
    from .postprocess import history_figure

    return _figure_png(history_figure(histories), dpi)


def extensometer_png(ext, *, dpi: float = 80) -> bytes:
    """:func:`dic.plots.postprocess.extensometer_figure` of ``ext`` as PNG bytes."""
    from .postprocess import extensometer_figure

    return _figure_png(extensometer_figure(ext), dpi)


def shape3d_png(X, Y, Z, *, title: str = "", dpi: float = 80) -> bytes:
    """A rendered 3-D view of the points (X, Y, Z) (N,) mm, coloured by Z (NaN points left out; at most
    :data:`SHAPE_MAX_POINTS`, evenly subsampled), axes labelled in mm, as PNG bytes."""
    X, Y, Z = (np.asarray(a, dtype=np.float64).ravel() for a in (X, Y, Z))
    if not (X.shape == Y.shape == Z.shape):
        raise ValueError(f"X, Y, Z must have one length, got {X.shape}, {Y.shape}, {Z.shape}")
    ok = np.isfinite(X) & np.isfinite(Y) & np.isfinite(Z)
    if not ok.any():
        raise ValueError("no point has a 3-D position; nothing to draw")
    idx = np.flatnonzero(ok)
    if idx.size > SHAPE_MAX_POINTS:
        idx = idx[np.linspace(0, idx.size - 1, SHAPE_MAX_POINTS).astype(np.int64)]
    fig = new_figure((6.0, 4.8), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    sc = ax.scatter(X[idx], Y[idx], Z[idx], c=Z[idx], cmap="viridis", s=2, linewidths=0)
    ax.set_xlabel("X (mm)", fontsize=8)
    ax.set_ylabel("Y (mm)", fontsize=8)
    ax.set_zlabel("Z (mm)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.view_init(elev=30, azim=-60)
    fig.colorbar(sc, ax=ax, shrink=0.7, label="Z (mm)")
    if title:
        ax.set_title(title, fontsize=9)
    return _figure_png(fig, dpi)
