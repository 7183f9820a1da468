"""Reliability-guided propagation on the device: the waves of :func:`dic.correlation.reliability_guided`.

Reliability-guided tracking (Pan 2009, doi:10.1364/AO.48.001535) processes POIs in waves: the
pending POIs (tracked, accepted, not yet expanded) whose ZNCC is within ``band`` (0.05) of the best
pending one form a wave; every untracked POI next to a wave member is tracked next, from the affine
prediction of its best-ZNCC wave neighbour (ties: the lowest index). This module runs one wave's
bookkeeping in one launch (:func:`rg_wave`): each pending POI decides whether it belongs to the
wave, each untracked POI finds its source among its wave neighbours, writes its guess into the
full-size guess array and appends itself to the candidate list (an atomic counter). IC-GN of the
candidates then runs over that list (:func:`kernels.icgn.icgn_indexed`), marking the accepted ones
pending and raising the next wave's best ZNCC. Only two counts per wave come back to the host.

State per POI (device arrays the caller allocates once):

* ``pop`` int32: 0 = not pending; :data:`PENDING` = accepted and waiting; ``w`` >= 1 = expanded in
  wave ``w``. A POI is a member of wave ``w`` when ``pop >= w`` and its ZNCC is within ``band`` of
  ``best[w]``: the test reads the same whether or not the member has already written ``w``.
* ``best`` float32 (>= waves + 2): ``best[w]`` is the best pending ZNCC at the start of wave ``w``
  (filled with -inf, raised by atomic max: the remaining pending POIs of wave ``w - 1`` and its
  newly accepted ones).
* ``counts`` int32 (>= waves + 1, 2): ``counts[w, 0]`` candidates of wave ``w``, ``counts[w, 1]``
  pending POIs left after wave ``w``.

The guesses are computed in float64 without FMA contraction (``fuse_fp`` off for this module), in
the host code's operation order, so that they are bitwise those of the host implementation.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from ._common import ST_CONVERGED, ST_MAX_ITERATIONS, ST_NOT_COMPUTED
from ._launch import launch_1d
from .icgn import IcgnOutputs, SubsetTable, copy_subset_row

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

#: ``pop`` value of an accepted POI that has not been expanded yet
PENDING = 1 << 30
_PENDING = wp.constant(PENDING)


@wp.func
def rg_wave_point(
    j: int, w: int, band: wp.float64, nb_start: wp.array(dtype=wp.int32), nb: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec2d), src: SubsetTable, full: IcgnOutputs, pop: wp.array(dtype=wp.int32),
    best: wp.array(dtype=float), counts: wp.array2d(dtype=wp.int32), cand: wp.array(dtype=wp.int32),
    gathered: SubsetTable, guess: wp.array2d(dtype=float),
):
    """Wave ``w``'s bookkeeping of POI ``j`` (:func:`rg_wave`)."""
    thr = wp.float64(best[w]) - band
    zncc = full.zncc
    params = full.params
    if pop[j] == _PENDING:  # an accepted POI: a member of this wave, or still pending after it
        if wp.float64(zncc[j]) >= thr:
            pop[j] = w
        else:
            wp.atomic_add(counts, w, 1, 1)
            wp.atomic_max(best, w + 1, zncc[j])
        return
    if full.status[j] != ST_NOT_COMPUTED:
        return
    src_poi = int(-1)
    zs = float(0.0)
    for e in range(nb_start[j], nb_start[j + 1]):
        i = nb[e]
        if pop[i] >= w:  # pending before this wave (PENDING or w)
            zi = zncc[i]
            if wp.float64(zi) >= thr:
                if src_poi < 0 or zi > zs or (zi == zs and i < src_poi):
                    src_poi = i
                    zs = zi
    if src_poi < 0:
        return
    t = wp.atomic_add(counts, w, 0, 1)
    cand[t] = j
    # the candidate's prepared reference quantities, gathered for IC-GN (kernels.icgn.gather_subsets)
    copy_subset_row(src, j, gathered, t)
    # its guess: the affine prediction of the source (float64, the host code's operation order)
    pj = points[j]
    pi = points[src_poi]
    d0 = pj[0] - pi[0]
    d1 = pj[1] - pi[1]
    k = params.shape[1]
    h = k // 2  # column of v
    u = wp.float64(params[src_poi, 0])
    ux = wp.float64(params[src_poi, 1])
    uy = wp.float64(params[src_poi, 2])
    v = wp.float64(params[src_poi, h])
    vx = wp.float64(params[src_poi, h + 1])
    vy = wp.float64(params[src_poi, h + 2])
    guess[t, 0] = wp.float32(u + ux * d0 + uy * d1)
    guess[t, 1] = params[src_poi, 1]
    guess[t, 2] = params[src_poi, 2]
    guess[t, h] = wp.float32(v + vx * d0 + vy * d1)
    guess[t, h + 1] = params[src_poi, h + 1]
    guess[t, h + 2] = params[src_poi, h + 2]
    if k == 12:  # 2nd derivatives carried over from the source
        for c in range(3, 6):
            guess[t, c] = params[src_poi, c]
            guess[t, 6 + c] = params[src_poi, 6 + c]


@wp.kernel
def _rg_wave(
    offset: int, w: int, band: wp.float64, nb_start: wp.array(dtype=wp.int32), nb: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec2d), src: SubsetTable, full: IcgnOutputs, pop: wp.array(dtype=wp.int32),
    best: wp.array(dtype=float), counts: wp.array2d(dtype=wp.int32), cand: wp.array(dtype=wp.int32),
    gathered: SubsetTable, guess: wp.array2d(dtype=float),
):
    rg_wave_point(wp.tid() + offset, w, band, nb_start, nb, points, src, full, pop, best, counts, cand, gathered,
                  guess)


@wp.kernel
def _rg_wave_counted(
    offset: int, ctl: wp.array(dtype=wp.int32), band: wp.float64, nb_start: wp.array(dtype=wp.int32),
    nb: wp.array(dtype=wp.int32), points: wp.array(dtype=wp.vec2d), src: SubsetTable, full: IcgnOutputs,
    pop: wp.array(dtype=wp.int32), best: wp.array(dtype=float), counts: wp.array2d(dtype=wp.int32),
    cand: wp.array(dtype=wp.int32), gathered: SubsetTable, guess: wp.array2d(dtype=float),
):
    rg_wave_point(wp.tid() + offset, ctl[0] + 1, band, nb_start, nb, points, src, full, pop, best, counts, cand,
                  gathered, guess)


@wp.func
def scatter_point(t: int, idx: wp.array(dtype=wp.int32), compact: IcgnOutputs, full: IcgnOutputs, zncc_min: wp.float64,
                  pop: wp.array(dtype=wp.int32), best: wp.array(dtype=float), slot: int):
    """Row ``t`` of the IC-GN results into row ``idx[t]`` (:func:`scatter_accept`)."""
    n = idx[t]
    for c in range(full.params.shape[1]):
        full.params[n, c] = compact.params[t, c]
    z = compact.zncc[t]
    st = compact.status[t]
    full.zncc[n] = z
    full.iterations[n] = compact.iterations[t]
    full.status[n] = st
    if st == ST_CONVERGED or st == ST_MAX_ITERATIONS:  # accepted (dic.correlation.acceptance.accepted_mask)
        if wp.float64(z) >= zncc_min:
            pop[n] = _PENDING
            wp.atomic_max(best, slot, z)


@wp.kernel
def _scatter_accept(offset: int, idx: wp.array(dtype=wp.int32), compact: IcgnOutputs, full: IcgnOutputs,
                    zncc_min: wp.float64, pop: wp.array(dtype=wp.int32), best: wp.array(dtype=float), slot: int):
    scatter_point(wp.tid() + offset, idx, compact, full, zncc_min, pop, best, slot)


@wp.kernel
def _scatter_counted(offset: int, ctl: wp.array(dtype=wp.int32), counts: wp.array2d(dtype=wp.int32),
                     idx: wp.array(dtype=wp.int32), compact: IcgnOutputs, full: IcgnOutputs, zncc_min: wp.float64,
                     pop: wp.array(dtype=wp.int32), best: wp.array(dtype=float)):
    t = wp.tid() + offset
    w = ctl[0]
    if t < counts[w, 0]:
        scatter_point(t, idx, compact, full, zncc_min, pop, best, w + 1)


@wp.kernel
def _start_loop(ctl: wp.array(dtype=wp.int32), cond: wp.array(dtype=wp.int32), counts: wp.array2d(dtype=wp.int32),
                m: int):
    ctl[0] = 0  # the seeds' batch is "wave" 0
    ctl[1] = 0
    counts[0, 0] = m
    cond[0] = wp.where(m > 0, 1, 0)


@wp.kernel
def _advance(ctl: wp.array(dtype=wp.int32), cond: wp.array(dtype=wp.int32), counts: wp.array2d(dtype=wp.int32),
             last: int):
    w = ctl[0] + 1  # the wave _rg_wave_counted just ran
    ctl[0] = w
    go = counts[w, 0] > 0 or counts[w, 1] > 0  # candidates to track, or pending POIs for the next wave
    if go and w >= last:  # the next wave would pass the state arrays' rows: the host takes over
        ctl[1] = 1
        go = False
    cond[0] = wp.where(go, 1, 0)


@wp.kernel
def _init_state(offset: int, ready_status: wp.array(dtype=wp.int32), status: wp.array(dtype=wp.int32),
                zncc: wp.array(dtype=float), iterations: wp.array(dtype=wp.int32), pop: wp.array(dtype=wp.int32),
                best: wp.array(dtype=float), counts: wp.array2d(dtype=wp.int32)):
    n = wp.tid() + offset
    if n < status.shape[0]:
        status[n] = ready_status[n]
        zncc[n] = wp.nan
        iterations[n] = 0
        pop[n] = 0
    best[n] = -wp.inf
    counts[n, 0] = 0
    counts[n, 1] = 0


def neighbour_lists(points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """CSR neighbour lists ``(start (N+1,), flat (E,))`` int32 of every point within ``radius``
    (itself included), from a k-d tree."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] == 0:
        raise ValueError(f"points must be a non-empty (N, 2) array, got shape {pts.shape}")
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be a positive number of pixels, got {radius!r}")
    lists = cKDTree(pts).query_ball_point(pts, r=radius)
    start = np.zeros(pts.shape[0] + 1, dtype=np.int64)
    start[1:] = np.cumsum([len(x) for x in lists])
    if start[-1] >= 2 ** 31:
        raise ValueError("too many neighbour pairs for int32 indices; use a larger grid step")
    flat = np.fromiter((j for x in lists for j in x), dtype=np.int32, count=int(start[-1]))
    return start.astype(np.int32), flat


def init_state(ready_status: wp.array, status: wp.array, zncc: wp.array, iterations: wp.array, pop: wp.array,
               best: wp.array, counts: wp.array) -> None:
    """Reset the per-frame state in one launch: ``status = ready_status`` (NOT_COMPUTED where the POI is
    trackable, else the reference status), ``zncc`` NaN, ``iterations`` 0, ``pop`` 0, ``best`` -inf,
    ``counts`` 0 (``best`` and ``counts`` have the same number of rows, at least N + 2)."""
    n = ready_status.shape[0]
    rows = best.shape[0]
    if rows < n + 2 or counts.shape[0] != rows:
        raise ValueError(f"best and counts need the same number of rows, at least {n + 2} (waves + 2)")
    launch_1d(_init_state, rows, [0, ready_status, status, zncc, iterations, pop, best, counts], str(status.device),
              offset_index=0, min_chunk=1 << 14)


def rg_wave(w: int, band: float, nb_start: wp.array, nb: wp.array, points: wp.array, subsets, full, pop: wp.array,
            best: wp.array, counts: wp.array, cand: wp.array, gathered, guess: wp.array) -> None:
    """Wave ``w`` (>= 1) of the reliability-guided propagation, in one launch over the N POIs (module doc).

    Marks the members (``pop = w``); appends the candidates to ``cand`` (``counts[w, 0]`` of them, in
    any order) with, in the same rows, their prepared reference quantities gathered from ``subsets``
    into ``gathered`` (:func:`kernels.icgn.subset_buffers`) and their guesses in ``guess``; counts the
    POIs still pending (``counts[w, 1]``), whose best ZNCC goes to ``best[w + 1]``. ``full`` is the
    frame's :class:`kernels.icgn.IcgnResult` (N rows), ``points`` the POIs as ``wp.vec2d``.
    """
    n = full.status.shape[0]
    if not 1 <= w < best.shape[0] - 1:
        raise ValueError(f"wave {w} is outside the state arrays ({best.shape[0]} rows)")
    launch_1d(_rg_wave, n, [0, int(w), float(band), nb_start, nb, points, subsets.table, full.outputs, pop, best,
                            counts, cand, gathered.table, guess],
              str(full.status.device), offset_index=0, min_chunk=1 << 12)


def scatter_accept(idx: wp.array, compact, full, count: int, zncc_min: float, pop: wp.array, best: wp.array,
                   slot: int) -> None:
    """Rows ``0..count-1`` of the IC-GN results ``compact`` into the rows ``idx[:count]`` of ``full``;
    an accepted POI (CONVERGED or MAX_ITERATIONS, ZNCC >= ``zncc_min`` in float64 as on the host)
    becomes pending (``pop = PENDING``) and raises ``best[slot]`` to its ZNCC."""
    launch_1d(_scatter_accept, int(count), [0, idx, compact.outputs, full.outputs, float(zncc_min), pop, best, int(slot)],
              str(full.status.device), offset_index=0, min_chunk=1024)


def _check_loop_arrays(ctl, cond, counts) -> None:
    for name, a, shape in (("ctl", ctl, (2,)), ("cond", cond, (1,)), ("counts", counts, None)):
        if not isinstance(a, wp.array) or a.dtype != wp.int32:
            raise ValueError(f"{name} must be an int32 Warp array")
        if shape is not None and tuple(a.shape) != shape:
            raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    if counts.ndim != 2 or counts.shape[1] != 2:
        raise ValueError(f"counts must have shape (waves, 2), got {counts.shape}")
    if not (ctl.device == cond.device == counts.device):
        raise ValueError("ctl, cond and counts must be on one device")


def start_loop(ctl: wp.array, cond: wp.array, counts: wp.array, m: int) -> None:
    """Start a frame's device loop: the seeds' batch (``m`` gathered POIs) is batch 0 (``ctl[0] = 0``,
    ``counts[0, 0] = m``), ``cond[0] = m > 0``, the bound flag ``ctl[1]`` cleared. One launch.
    ``ctl`` int32 (2,), ``cond`` int32 (1,), ``counts`` int32 (W, 2) on one device."""
    _check_loop_arrays(ctl, cond, counts)
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 0:
        raise ValueError(f"m must be a non-negative int (the seeds' count), got {m!r}")
    wp.launch(_start_loop, dim=1, inputs=[ctl, cond, counts, int(m)], device=str(ctl.device))


def scatter_counted(ctl: wp.array, counts: wp.array, idx: wp.array, compact, full, zncc_min: float, pop: wp.array,
                    best: wp.array) -> None:
    """:func:`scatter_accept` of the ``counts[ctl[0], 0]`` rows of batch ``ctl[0]`` (slot ``ctl[0] + 1``), in
    one launch over the N rows (threads past the count return): no host value needed."""
    n = full.status.shape[0]
    launch_1d(_scatter_counted, n, [0, ctl, counts, idx, compact.outputs, full.outputs, float(zncc_min), pop, best],
              str(full.status.device), offset_index=0, min_chunk=1 << 12)


def rg_wave_counted(ctl: wp.array, band: float, nb_start: wp.array, nb: wp.array, points: wp.array, subsets, full,
                    pop: wp.array, best: wp.array, counts: wp.array, cand: wp.array, gathered, guess: wp.array) -> None:
    """:func:`rg_wave` of wave ``ctl[0] + 1``, read on the device (the same per-POI body)."""
    n = full.status.shape[0]
    launch_1d(_rg_wave_counted, n, [0, ctl, float(band), nb_start, nb, points, subsets.table, full.outputs, pop, best,
                                    counts, cand, gathered.table, guess],
              str(full.status.device), offset_index=0, min_chunk=1 << 12)


def advance(ctl: wp.array, cond: wp.array, counts: wp.array, last: int) -> None:
    """After :func:`rg_wave_counted`: ``ctl[0] += 1`` (the wave just run) and ``cond[0]`` = whether the loop
    goes on (candidates, or POIs still pending); at wave ``last`` (the state arrays' last usable wave, or a
    smaller bound) the loop stops with ``ctl[1] = 1`` and the host loop finishes the frame. One thread."""
    _check_loop_arrays(ctl, cond, counts)
    if isinstance(last, bool) or not isinstance(last, (int, np.integer)) or not 1 <= last <= counts.shape[0] - 2:
        raise ValueError(f"last must be a wave in [1, {counts.shape[0] - 2}] (counts' rows - 2), got {last!r}")
    wp.launch(_advance, dim=1, inputs=[ctl, cond, counts, int(last)], device=str(ctl.device))
