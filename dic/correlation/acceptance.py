"""Acceptance of IC-GN results, in one place for 2-D tracking and stereo DIC.

A POI's result is *accepted* when IC-GN ended CONVERGED or MAX_ITERATIONS and its ZNCC is at least
``zncc_min`` (:func:`accepted_mask`). On top of that:

* **Second opinion** (:func:`second_opinion_candidates`): an accepted POI whose ZNCC is clearly
  below its accepted neighbours' converged to a wrong local minimum more often than not (measured:
  a 2nd-order track started 2 px away ended at ZNCC 0.86 with spurious curvature, its neighbours at
  0.99); the engine retries it from its best neighbour and keeps whichever result correlates better.
* **Implausible warps** (:func:`flag_implausible`): on a subset that is partly featureless (a
  specimen edge against a dark background) the featureless part does not constrain the warp, and
  2nd-order IC-GN can converge with a high ZNCC to a wrong warp. Such POIs get their own status,
  :attr:`kernels.conventions.Status.IMPLAUSIBLE_WARP` (rules in :mod:`.plausibility`).
* **Runs with (almost) nothing valid** (:func:`warn_if_mostly_invalid`) end with a warning that
  says why and what to try, rather than a silent all-invalid field.
"""
from __future__ import annotations

import warnings

import numpy as np

from kernels._launch import cpu_threads
from kernels.conventions import Status

__all__ = ["GOOD", "accepted_mask", "second_opinion_candidates", "flag_implausible", "stage_status", "status_counts",
           "warn_if_mostly_invalid", "MOSTLY_INVALID_FRACTION"]

#: IC-GN outcomes that count as a result (docs/conventions.md: "valid"), subject to the ZNCC threshold
GOOD = (int(Status.CONVERGED), int(Status.MAX_ITERATIONS))

#: a run whose valid POIs are fewer than this fraction of its POIs ends with a warning
MOSTLY_INVALID_FRACTION = 0.05


def accepted_mask(status: np.ndarray, zncc: np.ndarray, zncc_min: float) -> np.ndarray:
    """(N,) bool: IC-GN status CONVERGED or MAX_ITERATIONS and ``zncc >= zncc_min`` (NaN: False)."""
    return np.isin(status, GOOD) & (zncc >= zncc_min)


def second_opinion_candidates(points: np.ndarray, zncc: np.ndarray, accepted: np.ndarray, radius: float,
                              zncc_drop: float, cache: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Accepted POIs whose ZNCC is more than ``zncc_drop`` below their neighbours' median, and a donor each.

    Neighbours: up to 8 accepted POIs within ``2 radius`` px; a POI needs at least 3 of them.
    Returns ``(idx (m,), donor (m,))``: the suspect POIs and, for each, the neighbour with the best
    ZNCC, whose parameters (extrapolated) seed the retry.
    ``cache``: optional dict kept with ``points`` (a correlator's): the neighbours found for one set of accepted
    POIs are reused while the next call has the same set (a sequence's states usually do; the same answers as a
    new search, which a k-d tree of the same points gives bit for bit).
    """
    from scipy.spatial import cKDTree

    empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    acc = np.flatnonzero(accepted)
    if acc.size < 3:
        return empty
    kk = min(9, acc.size)
    kept = None if cache is None else cache.get("second_opinion_neighbours")
    if kept is not None and kept[0] == radius and np.array_equal(kept[1], acc):
        d, j = kept[2], kept[3]
    else:
        # the queries split over the CPU threads: each point's answer is the one-thread answer
        d, j = cKDTree(points[acc]).query(points[acc], k=kk, distance_upper_bound=2.0 * radius,
                                          workers=cpu_threads())
        if cache is not None:
            cache["second_opinion_neighbours"] = (radius, acc, d, j)
    have = np.isfinite(d[:, 1:])
    nb = np.where(have, acc[np.minimum(j[:, 1:], acc.size - 1)], -1)
    z_nb = np.where(have, zncc[np.maximum(nb, 0)], np.nan)
    # the neighbours' median ZNCC, for the POIs that have at least 3 neighbours (NaN for the others)
    enough = np.sum(have, axis=1) >= 3
    med = np.full(acc.size, np.nan)
    if np.any(enough):
        med[enough] = _row_nanmedian(z_nb[enough])
    suspect = np.isfinite(med) & (zncc[acc] < med - zncc_drop)
    if not np.any(suspect):
        return empty
    idx = acc[suspect]
    best = nb[suspect][np.arange(idx.size), np.nanargmax(np.where(nb[suspect] >= 0, z_nb[suspect], -np.inf), axis=1)]
    return idx, best


def _row_nanmedian(values: np.ndarray) -> np.ndarray:
    """``np.nanmedian(values, axis=1)`` of an (M, K) array with at least one finite value per row, bit for bit
    (NumPy takes the mean of the two middle values of the sorted finite ones, ``(low + high) / 2``, the same
    value twice for an odd count) without its masked-array path, several times slower on small rows."""
    ordered = np.sort(values, axis=1)  # NaN last
    count = np.count_nonzero(~np.isnan(values), axis=1)
    high = count // 2
    low = np.where(count % 2 == 1, high, high - 1)
    rows = np.arange(values.shape[0])
    return (ordered[rows, low] + ordered[rows, high]) / 2.0


def flag_implausible(correlator, params: np.ndarray, accepted: np.ndarray, order: int) -> np.ndarray:
    """(N,) bool: accepted POIs whose warp is implausible (see :mod:`.plausibility`).

    ``correlator``: the :class:`.engine.Correlator` whose reference subsets produced ``params``
    (N, k) - its textured fractions are computed once and cached.
    """
    from .plausibility import implausible_warps

    if not np.any(accepted):
        return np.zeros(accepted.shape, dtype=bool)
    return implausible_warps(correlator.points, params, order, accepted, correlator.textured_fraction())


def status_counts(status: np.ndarray, names) -> dict[str, int]:
    """``{name: count}`` of the status codes present, with ``names(code) -> str`` (an IntEnum)."""
    codes, counts = np.unique(np.asarray(status), return_counts=True)
    return {names(int(c)).name: int(n) for c, n in zip(codes, counts)}


def warn_if_mostly_invalid(n_valid: int, n_total: int, counts: dict[str, int], hint: str, *, what: str,
                           fraction: float = MOSTLY_INVALID_FRACTION, stacklevel: int = 3) -> str | None:
    """Warn (RuntimeWarning) when fewer than ``fraction`` of ``n_total`` POIs are valid; return the message.

    ``counts``: status name -> count (why the others failed); ``hint``: what to try, in words.
    """
    if n_total == 0 or n_valid >= fraction * n_total:
        return None
    why = ", ".join(f"{k} {v}" for k, v in sorted(counts.items(), key=lambda kv: -kv[1]))
    msg = f"{what}: only {n_valid} of {n_total} points are valid ({why}). {hint}"
    warnings.warn(msg, RuntimeWarning, stacklevel=stacklevel)
    return msg


def stage_status(res, eligible: np.ndarray, failed_code, extra_code, zncc_min: float) -> np.ndarray:
    """Per-POI :class:`dic.field3d.StereoStatus` (int8) of one stereo correlation stage.

    ``res``: a :class:`.engine.CorrelationResult`; ``eligible`` (N,) bool: POIs the stage was meant
    to correlate (the others are NOT_COMPUTED); ``failed_code``: the status of an IC-GN failure in
    this stage (MATCH_FAILED, TRACK_LEFT_FAILED, ...); ``extra_code``: the status of a result
    rejected by the stage's extra check (EPIPOLAR_VIOLATION). NO_GUESS where IC-GN never ran,
    LOW_ZNCC below ``zncc_min``, IMPLAUSIBLE_WARP for implausible warps, OK when accepted.
    """
    from dic.field3d import StereoStatus

    out = np.full(res.accepted.shape, int(StereoStatus.OK), dtype=np.int8)
    ran = res.icgn_status != int(Status.NOT_COMPUTED)
    out[~ran] = StereoStatus.NO_GUESS
    bad = ran & ~np.isin(res.icgn_status, GOOD)
    out[bad] = failed_code
    low = ran & np.isin(res.icgn_status, GOOD) & ~(res.zncc >= zncc_min)
    out[low] = StereoStatus.LOW_ZNCC
    out[res.extra_failed & ~res.accepted] = extra_code
    out[res.implausible & ~res.accepted] = StereoStatus.IMPLAUSIBLE_WARP
    out[res.accepted] = StereoStatus.OK
    out[~eligible] = StereoStatus.NOT_COMPUTED
    return out
