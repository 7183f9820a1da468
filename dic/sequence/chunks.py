"""POIs in chunks under a memory budget (``max_memory`` of :func:`dic.sequence.track_sequence`).

A :class:`dic.Tracker` keeps its per-POI reference data (the packed ``H^-1`` table, subset
centres, IC-GN buffers: :func:`bytes_per_poi`) for the whole sequence. When that would exceed the
budget, :class:`ChunkedTracker` stands in for it: for each frame it prepares the POIs a chunk at a
time (at most ``chunk`` POIs' data alive at once) and frees each chunk before the next, so the
per-POI working memory is bounded whatever the POI count, at the cost of preparing the reference
subsets again for every frame. IC-GN, acceptance and the implausible-warp check are per POI, and the
uncertainty's noise estimate is taken over all POIs at the end, so the results are identical to an
unchunked run. Reliability-guided propagation (``search="rg"``) follows neighbours across the whole
grid and cannot run in chunks. The chunks' results are copied into the frame's arrays as each
chunk finishes (no second copy of the whole frame's results). The arrays of a frame's result (host,
about 0.11 KB per POI) are not chunked; its strain is computed a band of grid rows at a time
(:func:`strain_in_bands`, identical to :func:`dic.strain`), so that the strain's working
arrays (about 0.5 KB per POI at once) stay bounded too.
"""
from __future__ import annotations

import os
import warnings
from types import SimpleNamespace

import numpy as np

__all__ = ["bytes_per_poi", "result_bytes_per_poi", "write_depth", "default_max_memory", "ChunkedTracker", "strain_in_bands", "STRAIN_BAND_POINTS"]

#: the most POIs whose strain :func:`strain_in_bands` computes at once (about 0.5 GB of working arrays)
STRAIN_BAND_POINTS = 1 << 20


#: the fewest points per chunk a memory budget must allow (unless the run has fewer)
MIN_CHUNK_POINTS = 1024


def check_budget(budget: int, n_points: int, order: int, shape, *, name: str = "max_memory") -> str | None:
    """A memory budget (bytes) against a run's working set: ``ValueError`` below one point's data
    (:func:`bytes_per_poi`); the text of a warning below the working set (all the points' data when that is
    less, else the larger of the reference image as float32, 4 x H x W bytes, and ``MIN_CHUNK_POINTS``
    points), None above it. Below the working set the points are tracked in small chunks, each preparing
    the whole image again: the same results, but a 2-frame run of 2 s took over a minute with 1 KiB."""
    per_point = bytes_per_poi(order)
    if budget < per_point:
        raise ValueError(f"{name} ({budget:,} bytes) cannot hold the data of one point ({per_point} bytes at "
                         f"order {order}); give at least {per_point} bytes")
    floor = min(n_points * per_point, max(4 * int(shape[0]) * int(shape[1]), MIN_CHUNK_POINTS * per_point))
    if budget >= floor:
        return None
    return (f"{name} ({budget:,} bytes) is below the working set of this run, {floor:,} bytes (the reference "
            f"image as float32, {shape[1]} x {shape[0]} px x 4 bytes, or {MIN_CHUNK_POINTS} points x {per_point} "
            f"bytes, whichever is larger, or all {n_points:,} points if that is less); the {n_points:,} points "
            f"are tracked in chunks of {budget // per_point:,}, each preparing the whole image again: the same "
            "results, much more slowly")


def bytes_per_poi(order: int) -> int:
    """Bytes per POI that tracking a frame needs at its peak: the tracker's reference table, centres
    and IC-GN buffers, and the host arrays at the end of one ``track`` call (the results read back as
    float32, their float64 copies, the acceptance and implausible-warp checks, the uncertainty, the
    chunk's Field2D).

    Measured (bench/scale.py, 8192 x 8192 at step 2, chunks of 5.57 M POIs, 1st order): +1.3 GB
    while a chunk's tracker is prepared, +2.3 GB more at the end of its ``track`` call, 650 B per POI;
    this gives 652 (1st order) and 1144 (2nd order: the per-parameter parts scaled).
    """
    from kernels.icgn import n_params, refdata_width

    k = n_params(order)
    return 4 * (refdata_width(order) + 3 * k + 12) + 32 + 24 * k + 216


def result_bytes_per_poi(order: int) -> int:
    """Bytes of one frame's result per POI on the host: the Field2D's arrays (points, u, v, parameters,
    ZNCC, iterations, status, valid, sigma_u, sigma_v) and its strain (10 components, valid, n_fit,
    grid index)."""
    from kernels.icgn import n_params

    return 8 * n_params(order) + 77 + 105


def write_depth(n_points: int, order: int, budget: int) -> int:
    """How many finished frames may wait for the writer (:class:`dic.sequence.pipeline.WriteBehind`):
    2 while three frames' results fit in a quarter of ``budget``, else 0 (one frame written while the
    next is computed, none waiting: frames of many millions of POIs)."""
    return 2 if 3 * int(n_points) * result_bytes_per_poi(order) <= int(budget) // 4 else 0


def default_max_memory() -> int:
    """A twelfth of the machine's physical memory (bytes); 2 GiB when it cannot be read.

    The budget covers tracking's per-POI needs (:func:`bytes_per_poi`); the frame's result arrays
    (about 0.11 KB per POI, :func:`result_bytes_per_poi` with the strain), the strain bands, the
    images and the writer's frame come on top: about 5 GB for an 8192 x 8192 pair at step 2 (16.7 M
    POIs; bench/scale.py), so that such a pair stays within 8 GB on a 24 GB machine.
    """
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")) // 12
    except (ValueError, OSError, AttributeError):
        return 2 << 30


class ChunkedTracker:
    """Tracker-like (``points``, ``order``, ``track(current, guess=)``): ``make_tracker(image, points)``
    built for ``chunk`` POIs at a time, for every frame; results concatenated in POI order."""

    def __init__(self, make_tracker, image, points, *, order: int, chunk: int, search=None):
        if search == "rg":
            raise ValueError("search='rg' (reliability-guided propagation) follows neighbours over the whole grid and "
                             "cannot run on POIs in chunks; raise max_memory or choose another search")
        self.make_tracker, self.image = make_tracker, image
        self.points = np.asarray(points, np.float64)
        self.order = int(order)
        n, chunk = len(self.points), max(1, int(chunk))
        self.chunk = -(-n // -(-n // chunk)) if n else chunk  # chunks of even size, as many as ``chunk`` needs
        self.search = search
        self._textured = None  # textured fraction of every POI's reference subset (computed once)

    def _share_textured(self, tracker, start: int) -> None:
        """Give a chunk's correlator its slice of the reference's textured fractions (the implausible-warp
        check), computed once for every POI: each correlator would otherwise filter the whole reference
        image again (about 3.5 GB of image-sized arrays at 8192 x 8192) for its own POIs. The fraction
        of a POI depends on the image and that POI only, so the values are the same."""
        corr = getattr(tracker, "correlator", None)
        if corr is None or not hasattr(corr, "_textured") or not getattr(tracker, "check_warps", True):
            return
        if self._textured is None:
            from ..correlation.plausibility import textured_fraction

            self._textured = textured_fraction(corr.image, self.points, corr.subset)
        corr._textured = self._textured[start:start + len(corr.points)]

    @property
    def n_chunks(self) -> int:
        return -(-len(self.points) // self.chunk)

    def track(self, current, guess=None):
        """The frame's :class:`dic.field2d.Field2D` over every POI, tracked a chunk at a time."""
        from kernels.conventions import Status

        from ..correlation.acceptance import status_counts, warn_if_mostly_invalid
        from ..field2d import Field2D
        from ..quality import SigmaBasis, displacement_sigma
        from .pipeline import trim_memory

        bases, first, out, extra = [], None, {}, {}
        check_outliers = False
        n = len(self.points)
        for s in range(0, n, self.chunk):
            tracker = self.make_tracker(self.image, self.points[s:s + self.chunk])
            self._share_textured(tracker, s)
            if getattr(tracker, "check_outliers", False):  # the neighbour test needs every POI: run below, once
                check_outliers = True
                tracker.check_outliers = False
            g = None if guess is None else np.asarray(guess)[s:s + self.chunk]
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                part = tracker.track(current, guess=g)
            for w in caught:  # the "mostly invalid" warning is issued once, for all POIs, below
                if "2-D tracking" not in str(w.message):
                    warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
            bases.append(tracker._sigma_basis)
            refined = (getattr(part, "extra", None) or {}).get("robust_refined")
            if refined is not None:  # points refined by robust IC-GN, summed over the chunks
                extra["robust_refined"] = extra.get("robust_refined", 0) + int(refined)
            del tracker  # this chunk's reference data are freed before the next chunk's are prepared
            if first is None:  # what every chunk shares (not its arrays: they are freed with the chunk)
                first = SimpleNamespace(**{k: getattr(part, k) for k in ("subset", "order", "step", "zncc_min",
                                                                         "noise_sigma", "noise_source")})
            for name in _FIELD_ARRAYS:  # into the frame's arrays now: no list of parts to concatenate later
                a = np.asarray(getattr(part, name))
                if name not in out:
                    out[name] = np.empty((n,) + a.shape[1:], a.dtype)
                out[name][s:s + len(a)] = a
            del part
            trim_memory()  # the chunk's freed buffers go back to the system before the next chunk's are made
        cat = out
        if check_outliers:  # as dic.Tracker does, over the whole frame (a chunk's edge would cut neighbourhoods)
            from ..correlation.lagrangian import displacement_outliers

            h = cat["params"].shape[1] // 2
            outliers = displacement_outliers(cat["points"], cat["params"][:, 0], cat["params"][:, h], cat["valid"])
            cat["status"][outliers] = int(Status.NEIGHBOUR_OUTLIER)
            cat["valid"] &= ~outliers
        sigma_u = sigma_v = None
        noise, source = first.noise_sigma, first.noise_source
        if all(b is not None for b in bases):
            basis = SigmaBasis(np.concatenate([b.hinv_uv for b in bases]), np.concatenate([b.fnorm for b in bases]),
                               bases[0].subset, bases[0].order)
            given = first.noise_sigma if first.noise_source == "given" else None
            sigma, noise, source = displacement_sigma(basis, cat["zncc"], cat["valid"], given)
            sigma_u, sigma_v = sigma[:, 0].copy(), sigma[:, 1].copy()
        field = Field2D(cat["points"], cat["u"], cat["v"], cat["params"], cat["zncc"], cat["iterations"], cat["status"],
                        cat["valid"], first.subset, first.order, first.step, first.zncc_min, extra, sigma_u=sigma_u,
                        sigma_v=sigma_v, noise_sigma=noise, noise_source=source)
        counts = status_counts(field.status[~field.valid], Status)
        from .._track import _no_valid_hint

        warn_if_mostly_invalid(int(np.count_nonzero(field.valid)), n, counts, _no_valid_hint(self.search, counts),
                               what="2-D tracking")
        return field


_FIELD_ARRAYS = ("points", "u", "v", "params", "zncc", "iterations", "status", "valid")


def strain_in_bands(field, window: int, *, max_points: int = STRAIN_BAND_POINTS, cracks=None,
                    strain_type: str = "green-lagrange"):
    """:func:`dic.strain` of ``field`` (``window`` grid points) computed a band of grid rows at a time.

    Each band holds at most about ``max_points`` POIs plus ``window // 2`` grid rows on either
    side, whose points enter the fits of the band's own rows and nothing else: every fit sees the
    same points, in the same places, as in one call over the whole grid, so the result is
    identical (tested), while the strain's working arrays are those of one band. A field of at
    most ``max_points`` POIs is one call of :func:`dic.strain`; so is a field whose bands
    do not make grids of their own that a window fits (a region of interest only a few points
    wide in places). ``cracks``: declared cracks no fit reaches across (:mod:`dic.cracks`). ``strain_type``
    as for :func:`dic.strain`.
    """
    from kernels.checks import positive_int

    from .._strain import StrainField, check_strain_type, grid_layout, strain

    max_points = positive_int(max_points, "max_points")
    # declared cracks (no fit across them) and the strain type, passed on to every strain() below
    crack_kw = {"strain_type": strain_type} if cracks is None else {"cracks": cracks, "strain_type": strain_type}
    if not all(hasattr(field, name) for name in ("points", "u", "v", "valid")):
        raise ValueError(f"strain_in_bands needs a 2-D field (points, u, v, valid), got {type(field).__name__}")
    points = np.asarray(field.points, np.float64)
    n = len(points)
    if n <= max_points:
        return strain(field, window=window, **crack_kw)
    index, shape, step = grid_layout(points)
    h = int(window) // 2
    rows = index[:, 1]
    per_row = max(1, n // max(1, shape[0]))
    band = max(2 * h + 1, max_points // per_row)
    u, v = np.asarray(field.u, np.float64), np.asarray(field.v, np.float64)
    valid = getattr(field, "valid", None)
    valid = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    order = np.argsort(rows, kind="stable")  # POIs grouped by grid row, in their own order within a row
    starts = np.searchsorted(rows[order], np.arange(shape[0] + 1))
    out = None
    for r0 in range(0, shape[0], band):
        r1 = min(shape[0], r0 + band)
        sel = np.sort(order[starts[max(0, r0 - h)]:starts[min(shape[0], r1 + h)]])
        part = _Field(points[sel], u[sel], v[sel], valid[sel])
        try:
            s = strain(part, window=window, **crack_kw)
        except ValueError:  # a band that is no grid a window fits on its own: the whole field at once
            return strain(field, window=window, **crack_kw)
        if tuple(s.step) != tuple(step):
            return strain(field, window=window, **crack_kw)
        keep = (rows[sel] >= r0) & (rows[sel] < r1)
        if out is None:
            out = {name: np.empty(n, getattr(s, name).dtype) for name in StrainField.COMPONENTS + ("valid", "n_fit")}
        for name, arr in out.items():
            arr[sel[keep]] = getattr(s, name)[keep]
        del s, part
    return StrainField(points=points.copy(), **out, window=int(window), step=step, grid_index=index,
                       grid_shape=shape, strain_type=check_strain_type(strain_type))


class _Field:
    """The points, displacements and flags of a band (what :func:`dic.strain` reads)."""

    def __init__(self, points, u, v, valid):
        self.points, self.u, self.v, self.valid = points, u, v, valid
