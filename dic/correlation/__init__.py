"""The one correlation core of 2-D tracking (:mod:`dic.track`) and stereo DIC (:mod:`dic.stereo`).

* :mod:`.points` - POI grids and ROIs (one rule: an inclusive box or a mask);
* :mod:`.params` - shape-function parameter arrays (order conversion, user guesses, extrapolation);
* :mod:`.guesses` - initial-guess strategies behind one interface, chosen by name (``"zncc"``,
  ``"fft"``, ``"pyramid"``, ``"rg"``, ``"shift"``, ``"features"``, ``"epipolar"``, ...), extensible
  with :func:`~.guesses.register_guess`;
* :mod:`.features` - SIFT correspondences and per-POI affine fits (the ``"features"`` strategy);
* :mod:`.engine` - :class:`~.engine.Correlator` (reference work once, IC-GN for all or some POIs),
  :func:`~.engine.correlate` (propagation, fallback, second opinion), reliability-guided propagation;
* :mod:`.acceptance` - status and ZNCC acceptance, second opinion, implausible warps, the warning
  when a run ends with (almost) nothing valid;
* :mod:`.plausibility` - the textured fraction of subsets and the implausible-warp rule.

Importing the package compiles no kernel.
"""
from .acceptance import accepted_mask, flag_implausible, warn_if_mostly_invalid
from .engine import CorrelationResult, Correlator, correlate, reliability_guided
from .guesses import GuessContext, GuessStrategy, available_guesses, get_guess, register_guess
from .points import grid, grid_points, roi_mask

__all__ = [
    "Correlator", "CorrelationResult", "correlate", "reliability_guided",
    "GuessContext", "GuessStrategy", "register_guess", "get_guess", "available_guesses",
    "grid", "grid_points", "roi_mask",
    "accepted_mask", "flag_implausible", "warn_if_mostly_invalid",
]
