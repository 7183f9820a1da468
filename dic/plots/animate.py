"""The pictures of a movie (:mod:`dic.animate`, ``specula animate``): one frame of a result drawn as an RGB
array with a given colour range.

* :func:`frame_quantities` — the quantities a frame can be drawn with.
* :func:`frame_values` — one quantity of a frame, NaN where the point is not valid.
* :func:`movie_limits` — the one colour range of a movie from the values of all its frames.
* :func:`frame_rgb` — one frame as (H, W, 3) uint8 pixels.

A 2-D frame is drawn by :func:`dic.plots.fields.field_figure`, a stereo state by
:func:`dic.plots.fields.field3d_figure`, each with the range given, so a colour means the same value in
every frame of a movie.
"""
from __future__ import annotations

import numpy as np

from ._common import colour_scale

__all__ = ["frame_quantities", "frame_values", "movie_limits", "frame_rgb"]

#: 2-D quantities that need no strain
_DISPLACEMENTS_2D = ("u", "v", "magnitude")
_STRAINS_2D = ("exx", "eyy", "exy", "Exx", "Eyy", "Exy")


def frame_quantities(frame) -> list[str]:
    """The quantities ``frame`` can be drawn with: a 2-D frame ``u``, ``v``, ``magnitude`` and the strains it
    holds; a stereo state (Field3D) those of :data:`dic.plots.fields.FIGURE_QUANTITIES` but ``status``
    (``Z``, ``U``, ``V``, ``W``, ``exx``, ``eyy``, ``exy``, ``zncc_stereo``)."""
    from .fields import FIGURE_QUANTITIES, _is_field3d

    if _is_field3d(frame):
        return [q for q in FIGURE_QUANTITIES if q != "status"]
    strain = getattr(frame, "strain", None) or {}
    has = (lambda q: q in strain) if isinstance(strain, dict) else (lambda q: getattr(strain, q, None) is not None)
    return list(_DISPLACEMENTS_2D) + [q for q in _STRAINS_2D if has(q)]


def frame_values(frame, quantity: str) -> np.ndarray:
    """(N,) float64 values of ``quantity`` in ``frame`` (2-D frame or Field3D), NaN where the point is not valid."""
    from .fields import _component_values, _is_field3d, _strain_view

    if _is_field3d(frame):
        return np.where(frame.valid, np.asarray(getattr(frame, quantity), dtype=np.float64), np.nan)
    return _component_values(frame, _strain_view(getattr(frame, "strain", None)), quantity)


def movie_limits(values, quantity: str) -> tuple[float, float]:
    """``(vmin, vmax)`` of ``quantity`` from ``values`` (every frame's values together): the 1st-99th
    percentiles of the finite ones, symmetric about zero for a signed quantity whose range spans zero
    (:func:`dic.plots._common.colour_scale`; nearly uniform values get +-1 % about their middle)."""
    from .fields import SIGNED

    v = np.asarray(values, dtype=np.float64)
    if not np.isfinite(v).any():
        raise ValueError(f"{quantity} has no valid value in the selected frames; nothing to animate")
    _, lo, hi = colour_scale(v, signed=quantity in SIGNED)
    return float(lo), float(hi)


def frame_rgb(frame, quantity: str, limits: tuple[float, float], *, index=None, image=None, dpi: float = 80,
              alpha: float = 0.75) -> np.ndarray:
    """One frame drawn with the colour range ``limits`` as (H, W, 3) uint8 pixels (a 5-inch map at ``dpi``).

    ``frame``: a 2-D frame (titled ``frame <index>``) or a Field3D (titled with its state); ``image``: the
    (H, W) grey reference image beneath the map (the left one for stereo), or None."""
    from .fields import _is_field3d, field3d_figure, field_figure

    lo, hi = limits
    if _is_field3d(frame):
        fig = field3d_figure(frame, quantity, image, vmin=lo, vmax=hi, alpha=alpha, dpi=dpi)
    else:
        fig = field_figure(image, frame, getattr(frame, "strain", None), components=[quantity],
                           limits={quantity: (lo, hi)}, title=None if index is None else f"frame {index}",
                           alpha=alpha, dpi=dpi, panel_size=5.0)
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
