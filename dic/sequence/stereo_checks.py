"""The stereo sequence's counts of the check of composed tracks (``verify_composed``; issue 26).

:func:`composed_mismatches` counts a state's points with the status
:attr:`dic.field3d.StereoStatus.COMPOSED_MISMATCH` (the count of :attr:`SequenceSummary.n_mismatch`);
:func:`composed_mismatch_attrs` the attributes a checked state gets in the result file: ``composed_mismatch``
(that count) and, per camera, ``composed_mismatch_left`` / ``composed_mismatch_right``: the points whose
composed track in that camera scored below ``verify_zncc`` (a point can fail in both; one that failed an
earlier stage keeps that stage's status and is not in ``composed_mismatch``).
"""
from __future__ import annotations

import numpy as np

from ..field3d import StereoStatus

__all__ = ["composed_mismatches", "composed_mismatch_attrs"]


def composed_mismatches(field) -> int:
    """The points of a stereo state ``field`` (:class:`dic.field3d.Field3D`) that failed the check."""
    return int(np.count_nonzero(np.asarray(field.status) == int(StereoStatus.COMPOSED_MISMATCH)))


def composed_mismatch_attrs(field, threshold: float) -> dict:
    """The file attributes of a state checked against the reference pair (``threshold``: ``verify_zncc``)."""
    attrs = {"composed_mismatch": composed_mismatches(field)}
    for side in ("left", "right"):
        z = (field.details or {}).get(f"composed_zncc_{side}")
        if z is not None:
            z = np.asarray(z, np.float64)
            attrs[f"composed_mismatch_{side}"] = int(np.count_nonzero(np.isfinite(z) & ~(z >= threshold)))
    return attrs
