"""Figures of post-processing results (:mod:`dic.postprocess`): extensometers, point histories, line profiles.

* :func:`extensometer_figure` / :func:`write_extensometer_figure` — strain and length change of a
  virtual extensometer against the frame index.
* :func:`history_figure` / :func:`write_history_figure` — one or more point histories against the
  frame index.
* :func:`profile_figure` / :func:`write_profile_figure` — a quantity along a line, one curve per
  frame (coloured from the first frame to the last).

Frames without a value (a gauge end or point outside the valid points) are gaps in the curves.
"""
from __future__ import annotations

import numpy as np

from ._common import colormap, new_figure, save_figure

__all__ = ["extensometer_figure", "write_extensometer_figure", "history_figure", "write_history_figure",
           "profile_figure", "write_profile_figure"]


def _check(obj, cls_name: str, fields: tuple[str, ...]):
    if not all(hasattr(obj, f) for f in fields):
        raise ValueError(f"expected a dic.postprocess.{cls_name}, got {type(obj).__name__}")
    return obj


def _label(name: str, unit: str) -> str:
    return f"{name} ({unit})" if unit else name


def _integer_frames(ax) -> None:
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))


def _pt(p, at: str) -> str:
    return f"({p[0]:g}, {p[1]:g}) {at}"


def _named(result) -> str:
    """A History's or Profile's quantity with its strain type, e.g. ``exx (Green-Lagrange)``."""
    kind = getattr(result, "strain_type", None)
    if not kind:
        return result.quantity
    from .._strain import strain_type_label

    return f"{result.quantity} ({strain_type_label(kind)})"


def extensometer_figure(ext, *, title: str | None = None, figsize=(6.4, 5.6)):
    """Strain (top) and elongation (bottom) of a :class:`dic.postprocess.Extensometer` against the frame."""
    _check(ext, "Extensometer", ("frames", "strain", "elongation", "length0", "unit", "start", "end", "at"))
    fig = new_figure(figsize, layout="constrained")
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ax1.plot(ext.frames, ext.strain, "o-", color="C0")
    ax1.set_ylabel("strain (engineering)")
    ax1.axhline(0.0, color="0.6", lw=0.8)
    ax2.plot(ext.frames, ext.elongation, "o-", color="C1")
    ax2.set_ylabel(_label("length change", ext.unit))
    ax2.set_xlabel("frame")
    _integer_frames(ax2)
    ax2.axhline(0.0, color="0.6", lw=0.8)
    l0 = ext.length0[np.isfinite(ext.length0)]
    gauge = f"gauge {_pt(ext.start, ext.at)} -> {_pt(ext.end, ext.at)}"
    if l0.size:
        gauge += f", L0 = {l0[0]:.4g} {ext.unit}"
    fig.suptitle(title or f"virtual extensometer: {gauge}", fontsize="medium")
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
    return fig


def write_extensometer_figure(path, ext, *, dpi: float = 120, **kwargs):
    """Save :func:`extensometer_figure` to ``path`` (format from the suffix); returns the path."""
    return save_figure(extensometer_figure(ext, **kwargs), path, dpi=dpi)


def history_figure(histories, *, title: str | None = None, figsize=(6.4, 4.0)):
    """One curve per :class:`dic.postprocess.History` (a single one or a list) against the frame."""
    items = list(histories) if isinstance(histories, (list, tuple)) else [histories]
    if not items:
        raise ValueError("history_figure needs at least one History")
    for h in items:
        _check(h, "History", ("frames", "values", "quantity", "unit", "point", "at"))
    fig = new_figure(figsize, layout="constrained")
    ax = fig.subplots()
    for k, h in enumerate(items):
        ax.plot(h.frames, h.values, "o-", color=f"C{k % 10}", label=f"{_named(h)} at {_pt(h.point, h.at)}")
    units = {h.unit for h in items}
    names = {_named(h) for h in items}
    ax.set_ylabel(_label(", ".join(sorted(names)), units.pop() if len(units) == 1 else ""))
    ax.set_xlabel("frame")
    _integer_frames(ax)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    if title:
        ax.set_title(title)
    return fig


def write_history_figure(path, histories, *, dpi: float = 120, **kwargs):
    """Save :func:`history_figure` to ``path``; returns the path."""
    return save_figure(history_figure(histories, **kwargs), path, dpi=dpi)


def profile_figure(profile, *, title: str | None = None, cmap: str = "viridis", figsize=(6.4, 4.0)):
    """A :class:`dic.postprocess.Profile`: the quantity against the distance along the line, one curve per frame."""
    _check(profile, "Profile", ("frames", "values", "distance", "quantity", "unit", "start", "end", "at"))
    fig = new_figure(figsize, layout="constrained")
    ax = fig.subplots()
    cm = colormap(cmap)
    F = len(profile.frames)
    for k, (i, row) in enumerate(zip(profile.frames, profile.values)):
        ax.plot(profile.distance, row, "-", color=cm(k / max(F - 1, 1)), label=f"frame {int(i)}")
    ax.set_xlabel(f"distance along the line ({profile.at})")
    ax.set_ylabel(_label(_named(profile), profile.unit))
    ax.grid(True, alpha=0.3)
    if F <= 12:
        ax.legend(fontsize="small")
    ax.set_title(title or f"{profile.quantity} from {_pt(profile.start, profile.at)} to {_pt(profile.end, profile.at)}",
                 fontsize="medium")
    return fig


def write_profile_figure(path, profile, *, dpi: float = 120, **kwargs):
    """Save :func:`profile_figure` to ``path``; returns the path."""
    return save_figure(profile_figure(profile, **kwargs), path, dpi=dpi)
