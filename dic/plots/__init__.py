"""All of Specula's plotting (Matplotlib): the one place in kernels/, calibration/ and dic/ that draws.

* :mod:`dic.plots.fields` — maps of 2-D fields (:func:`field_figure`, :func:`write_field_figure`)
  and of 3-D stereo fields (:func:`field3d_figure`, :func:`write_figures`, :data:`FIGURE_QUANTITIES`)
  over the reference image; :func:`sequence_limits` for one colour scale over a sequence.
* :mod:`dic.plots.calibration` — the figures of ``specula calibrate ... --figures``
  (:func:`write_intrinsics_figures`, :func:`write_mirror_figures`, :func:`write_rig_figures`,
  :func:`write_check_figures`, :func:`view_mosaic`, :func:`view_detail`, :class:`FigureSkipped`).
* :mod:`dic.plots.lab` — the layout of a virtual-lab scene (:func:`plot_layout`).
* :mod:`dic.plots.postprocess` — virtual extensometers, point histories and line profiles
  (:func:`extensometer_figure`, :func:`history_figure`, :func:`profile_figure` and their ``write_*``).
* :mod:`dic.plots.animate` — the pictures of a movie (:mod:`dic.animate`): one frame as RGB pixels with a
  given colour range (:func:`frame_rgb`, :func:`movie_limits`, :func:`frame_values`, :func:`frame_quantities`).
* :mod:`dic.plots._common` — shared plumbing: figures on their own Agg canvas (no pyplot, no global
  backend change), colour limits, saving.

The names above are importable from ``dic.plots`` too; each submodule is imported on first use of one
of its names, so ``import dic.plots`` imports neither Matplotlib nor the calibration or lab packages.
CLI commands call these functions; no module outside this package imports Matplotlib
(tests/project/test_plots.py checks it).
"""
from __future__ import annotations

import importlib

#: public name -> submodule that defines it
_EXPORTS = {
    "field_figure": "fields", "write_field_figure": "fields", "write_figures": "fields", "FIGURE_QUANTITIES": "fields",
    "field3d_figure": "fields", "sequence_limits": "fields",
    "write_intrinsics_figures": "calibration", "write_mirror_figures": "calibration",
    "write_rig_figures": "calibration", "write_check_figures": "calibration",
    "view_mosaic": "calibration", "view_detail": "calibration", "FigureSkipped": "calibration",
    "plot_layout": "lab",
    "extensometer_figure": "postprocess", "write_extensometer_figure": "postprocess",
    "history_figure": "postprocess", "write_history_figure": "postprocess",
    "profile_figure": "postprocess", "write_profile_figure": "postprocess",
    "frame_quantities": "animate", "frame_values": "animate", "movie_limits": "animate", "frame_rgb": "animate",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
