"""POIs in chunks under a memory budget (``max_memory`` of :func:`dic.sequence.track_sequence`).

A :class:`dic.track.Tracker` keeps its per-POI reference data (the packed ``H^-1`` table, subset
centres, IC-GN buffers: :func:`bytes_per_poi`) for the whole sequence. When that would exceed the
budget, :class:`ChunkedTracker` stands in for it: for each frame it prepares the POIs a chunk at a
time (at most ``chunk`` POIs' data alive at once) and frees each chunk before the next, so the
per-POI working memory is bounded whatever the POI count, at the cost of preparing the reference
subsets again for every frame. IC-GN, acceptance and the implausible-warp check are per POI, and the
uncertainty's noise estimate is taken over all POIs at the end, so the results are identical to an
unchunked run. Reliability-guided propagation (``search="rg"``) follows neighbours across the whole
grid and cannot run in chunks. The arrays of a frame's result (host, about 0.3 KB per POI) are not
chunked.
"""
from __future__ import annotations

import os
import warnings

import numpy as np

__all__ = ["bytes_per_poi", "default_max_memory", "ChunkedTracker"]


def bytes_per_poi(order: int) -> int:
    """Bytes of per-POI working data a tracker holds: the reference table, centres, IC-GN buffers."""
    from kernels.icgn import n_params, refdata_width

    k = n_params(order)
    return 4 * (refdata_width(order) + 3 * k + 12) + 32


def default_max_memory() -> int:
    """A quarter of the machine's physical memory (bytes); 2 GiB when it cannot be read."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")) // 4
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
        self.chunk = max(1, int(chunk))
        self.search = search

    @property
    def n_chunks(self) -> int:
        return -(-len(self.points) // self.chunk)

    def track(self, current, guess=None):
        from kernels.conventions import Status

        from ..correlation.acceptance import status_counts, warn_if_mostly_invalid
        from ..field2d import Field2D
        from ..quality import SigmaBasis, displacement_sigma

        parts, bases, tracker = [], [], None
        n = len(self.points)
        for s in range(0, n, self.chunk):
            tracker = self.make_tracker(self.image, self.points[s:s + self.chunk])
            g = None if guess is None else np.asarray(guess)[s:s + self.chunk]
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                parts.append(tracker.track(current, guess=g))
            for w in caught:  # the "mostly invalid" warning is issued once, for all POIs, below
                if "2-D tracking" not in str(w.message):
                    warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
            bases.append(tracker._sigma_basis)
            del tracker  # this chunk's reference data are freed before the next chunk's are prepared
        cat = {name: np.concatenate([getattr(p, name) for p in parts]) for name in
               ("points", "u", "v", "params", "zncc", "iterations", "status", "valid")}
        first = parts[0]
        sigma_u = sigma_v = None
        noise, source = first.noise_sigma, first.noise_source
        if all(b is not None for b in bases):
            basis = SigmaBasis(np.concatenate([b.hinv_uv for b in bases]), np.concatenate([b.fnorm for b in bases]),
                               bases[0].subset, bases[0].order)
            given = first.noise_sigma if first.noise_source == "given" else None
            sigma, noise, source = displacement_sigma(basis, cat["zncc"], cat["valid"], given)
            sigma_u, sigma_v = sigma[:, 0].copy(), sigma[:, 1].copy()
        field = Field2D(cat["points"], cat["u"], cat["v"], cat["params"], cat["zncc"], cat["iterations"], cat["status"],
                        cat["valid"], first.subset, first.order, first.step, first.zncc_min, {}, sigma_u=sigma_u,
                        sigma_v=sigma_v, noise_sigma=noise, noise_source=source)
        counts = status_counts(field.status[~field.valid], Status)
        from ..track import _no_valid_hint

        warn_if_mostly_invalid(int(np.count_nonzero(field.valid)), n, counts, _no_valid_hint(self.search, counts),
                               what="2-D tracking")
        return field
