"""Named constants shared by all layers: shape-function parameter order and per-POI status.

See docs/conventions.md.
"""
from __future__ import annotations

from enum import IntEnum

import numpy as np

#: 1st-order shape function parameters, in storage order (u, v in px; gradients dimensionless).
PARAMS_1ST: tuple[str, ...] = ("u", "ux", "uy", "v", "vx", "vy")
#: 2nd-order shape function parameters, in storage order (second derivatives in 1/px).
PARAMS_2ND: tuple[str, ...] = (
    "u", "ux", "uy", "uxx", "uxy", "uyy",
    "v", "vx", "vy", "vxx", "vxy", "vyy",
)


def param_names(order: int) -> tuple[str, ...]:
    """Parameter names for shape-function ``order`` 1 or 2."""
    if order == 1:
        return PARAMS_1ST
    if order == 2:
        return PARAMS_2ND
    raise ValueError(f"shape-function order must be 1 or 2, got {order!r}")


def round_half_away(x) -> np.ndarray:
    """Round to the nearest integer, halfway cases away from zero (float64 array of whole numbers).

    The one rounding rule of POI positions: the kernels centre a subset on ``wp.round(x)`` (C
    ``round``: half away from zero), so every host-side rounding of a POI position (the integer
    search, plausibility, quality) must use the same rule; ``np.rint``/``np.round`` round half to
    even (10.5 -> 10, not 11) and ``np.floor(x + 0.5)`` is wrong for negative halves (-10.5 -> -10)
    and for 0.49999999999999994 (-> 1). Exact for every float64: ``s - floor(s)`` has no rounding.
    """
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"round_half_away needs real numbers (a scalar or an array), got {type(x).__name__}") from None
    s = np.abs(a)
    f = np.floor(s)
    return np.copysign(f + (s - f >= 0.5), a)


class Status(IntEnum):
    """Outcome of subset tracking for one point of interest (stored as int8/int32)."""

    CONVERGED = 0        #: norm of the parameter update fell below tol
    MAX_ITERATIONS = 1   #: max_iter reached without convergence (result still usable, check ZNCC)
    OUT_OF_BOUNDS = 2    #: the subset (reference or warped) leaves the image
    FLAT_SUBSET = 3      #: no texture: subset grey-level standard deviation ~ 0
    SINGULAR_HESSIAN = 4 #: the Gauss-Newton Hessian cannot be inverted
    DIVERGED = 5         #: the update grew without bound or the correlation collapsed
    NOT_COMPUTED = 6     #: not processed (e.g. masked out, or its guess failed)
    IMPLAUSIBLE_WARP = 7 #: converged, but to a warp its partly featureless subset cannot support
    #:                      (set by dic.correlation.acceptance, never by the kernels)
    NEIGHBOUR_OUTLIER = 8  #: converged, but its displacement disagrees with its neighbours' (a false
    #:                      match; the normalised median test, dic.correlation.lagrangian; 2-D robust mode)
    TOO_FEW_PIXELS = 9   #: a masked subset (holes, free edges, cracks: kernels.icgn_masked) keeps fewer
    #:                      of its pixels than the minimum kept fraction
    COMPOSED_MISMATCH = 10  #: valid against a moved reference, but its composed warp fails the check against the
    #:                      original reference image (ZNCC below the threshold; kernels.verify, 2-D sequences
    #:                      with verify_composed; set by dic.sequence.verification, never by the IC-GN kernels)


#: the distribution name on PyPI (``pip install specula-dic``); the command and the packages keep the
#: name Specula (``specula``, ``import dic``); "specula" on PyPI is an unrelated project
DISTRIBUTION_NAME = "specula-dic"
