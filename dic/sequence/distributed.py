"""Sequences beyond one machine, on Dask (``client=`` of :func:`dic.sequence.track_sequence`; docs/dic2d.md,
"Sequences on several machines (Dask)").

The client reads the frames and writes the results (the one writer, in frame order); the workers
correlate. Each worker prepares a reference once and keeps it in :data:`_CACHE` (a per-process dict
keyed by the run's settings digest, the reference frame and its image digest), so a frame costs one
task: the frame travels with its task and the reference image with a task of its own, fetched once by
each worker (so a task whose worker dies is retried on another worker with its frame, distributed
reschedules it; data scattered with ``client.scatter`` would be lost with the last worker holding it).

Distributed frames cannot wait for their predecessor's result, so a distributed run starts every
frame from the tracker's own start (its ``search``, or zero against the reference, which for
``every:N`` is the block's key frame moved to where the points are): ``guess="none"`` of the
single-process engine, which gives identical results.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict

__all__ = ["LOST", "connect", "local_client", "n_workers", "track_on_worker", "held", "forget", "release", "ReferenceBuilder", "CarriedMasks",
           "CONNECT_TIMEOUT",
           "WORKER_TIMEOUT", "worker_timeout"]

CONNECT_TIMEOUT = 5.0  # seconds to reach a scheduler
WORKER_TIMEOUT = 60.0  # seconds to wait for a first worker of a scheduler that has none (SPECULA_DASK_WORKER_TIMEOUT)
_CACHE_SIZE = 2  # references kept per worker process (the current block's and the one before)
_CACHE: OrderedDict = OrderedDict()
_LOCK = threading.Lock()


def _distributed():
    try:
        import distributed
    except ImportError:
        raise ValueError("client= needs dask.distributed: pip install 'specula-dic[dask]'") from None
    return distributed


def LOST() -> tuple:
    """The exception types of a frame the cluster lost (not of the frame itself): a worker that kept
    dying on it (``KilledWorker`` after ``distributed.scheduler.allowed-failures`` retries), a cancelled
    future (a scheduler gone), a connection closed or timed out."""
    import asyncio
    import concurrent.futures

    _distributed()
    from distributed.scheduler import KilledWorker

    try:
        from distributed.client import FutureCancelledError
    except ImportError:  # older distributed: a plain CancelledError
        FutureCancelledError = asyncio.CancelledError
    # (distributed's CommClosedError is an OSError)
    return (KilledWorker, FutureCancelledError, asyncio.CancelledError, concurrent.futures.CancelledError,
            OSError, TimeoutError)


def connect(client, *, timeout: float = CONNECT_TIMEOUT):
    """A :class:`distributed.Client` from ``client``: a Client as it is, or a scheduler address
    (``"tcp://host:8786"``) connected within ``timeout`` seconds (ValueError when it cannot be reached).

    A scheduler without workers is reported at once (a ``UserWarning``) and waited for up to
    :func:`worker_timeout` seconds (``SPECULA_DASK_WORKER_TIMEOUT``, default 60), then refused with
    ``ValueError``; a ``Client`` given as it is gets the warning only (an adaptive cluster starts its
    workers when work arrives)."""
    distributed = _distributed()
    if isinstance(client, distributed.Client):
        if not client.nthreads():  # reported at once; not waited for (an adaptive cluster starts workers on demand)
            import warnings

            warnings.warn("the Dask client's cluster has no workers yet: the frames wait until one joins",
                          UserWarning, stacklevel=3)
        return client
    if isinstance(client, str) and client.strip():
        address = client.strip()
        try:  # a handshake first: a Client that fails half-way leaves a client object that complains when collected
            _probe(address, timeout)
            connected = distributed.Client(address, timeout=timeout, set_as_default=False)
        except Exception as exc:  # refused, timed out, not a Dask scheduler (any reply it cannot read), a bad address
            reason = f"{type(exc).__name__}: {exc}"
            if not isinstance(exc, (OSError, TimeoutError, ValueError)):  # something answered, not in Dask's protocol
                reason = f"something answered there, but not a Dask scheduler: {type(exc).__name__}"
            if len(reason) > 200:
                reason = reason[:200] + "..."
            raise ValueError(f"cannot reach the Dask scheduler at {address} within {timeout:g} s ({reason})") from None
        _wait_for_a_worker(connected, address, worker_timeout())
        return connected
    raise ValueError(f"client must be a distributed.Client or a scheduler address such as 'tcp://host:8786', "
                     f"got {client!r}")


def worker_timeout() -> float:
    """Seconds to wait for a first worker of a scheduler that has none: the environment variable
    ``SPECULA_DASK_WORKER_TIMEOUT`` (a positive number), else :data:`WORKER_TIMEOUT`."""
    import math
    import os

    text = os.environ.get("SPECULA_DASK_WORKER_TIMEOUT", "").strip()
    if not text:
        return WORKER_TIMEOUT
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"SPECULA_DASK_WORKER_TIMEOUT must be a positive number of seconds, got {text!r}")
    return value


def _wait_for_a_worker(client, address: str, timeout: float) -> None:
    """Return once the scheduler of ``client`` has a worker. When it has none: a warning at once, then up to
    ``timeout`` s of waiting; ``ValueError`` (the client closed) when none joins: work sent to a scheduler
    without workers would wait forever at 0 %."""
    import warnings

    if client.nthreads():
        return
    warnings.warn(f"the Dask scheduler at {address} has no workers; waiting up to {timeout:g} s for one (start them "
                  f"with 'dask worker {address}')", UserWarning, stacklevel=3)
    try:
        client.wait_for_workers(1, timeout=timeout)
    except Exception as exc:  # TimeoutError (distributed's own type in some versions), a scheduler gone
        client.close()
        raise ValueError(f"no Dask worker joined the scheduler at {address} within {timeout:g} s "
                         f"({type(exc).__name__}); start workers with 'dask worker {address}', or wait longer with "
                         "the environment variable SPECULA_DASK_WORKER_TIMEOUT (seconds)") from None


def call_connected(function, arguments: dict):
    """Call ``function(**arguments)`` with ``arguments["client"]``, a scheduler address, connected for the call.

    ``arguments``: the caller's ``locals()`` (its keyword ``options`` spread out); the connection is
    closed when the call returns, so a run given an address leaves nothing open.
    """
    given = dict(arguments)
    given.pop("call_connected", None)  # the caller's import of this function, not an argument
    options = given.pop("options", {})
    with connect(given["client"]) as given["client"]:
        return function(**given, **options)


def local_client(n_workers: int):
    """A client of a new local cluster of ``n_workers`` worker processes (one thread each; closed with
    the client's ``_specula_cluster``)."""
    from kernels.checks import positive_int

    n_workers = positive_int(n_workers, "n_workers")
    distributed = _distributed()
    cluster = distributed.LocalCluster(n_workers=n_workers, processes=True, threads_per_worker=1,
                                       dashboard_address=None)
    client = distributed.Client(cluster, set_as_default=False)
    client._specula_cluster = cluster
    return client


def _probe(address: str, timeout: float) -> None:
    """Open and close one connection to ``address`` (distributed's handshake), on a thread of its own (the
    caller may be running an event loop)."""
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    from distributed.comm import connect as comm_connect

    async def probe():
        comm = await comm_connect(address, timeout=timeout)
        await comm.close()

    with ThreadPoolExecutor(1) as pool:
        pool.submit(asyncio.run, asyncio.wait_for(probe(), timeout + 1.0)).result()


def n_workers(client) -> int:
    """The number of worker threads of ``client``'s cluster (at least 1)."""
    try:
        return max(1, sum(client.nthreads().values()))
    except Exception:
        return 1


def held(obj):
    """``obj`` itself: a task whose result is ``obj`` puts it on the cluster and can be computed again."""
    return obj


def forget(prefix: str) -> int:
    """Drop this process's cached references whose key starts with ``prefix`` (a finished run's); the count."""
    with _LOCK:
        keys = [k for k in _CACHE if k.startswith(prefix)]
        for k in keys:
            del _CACHE[k]
    return len(keys)


def release(client, prefix: str) -> None:
    """:func:`forget` on every worker (a run's references are not kept once it ends); best effort."""
    try:
        client.run(forget, prefix)
    except Exception:  # a cluster gone or a worker lost: its cache went with it
        pass


def track_on_worker(key: str, build, ref_image, points, image, carried=None):
    """(raw field, seconds): ``image`` tracked against the reference ``key``, prepared once per worker
    process by ``build(ref_image, points)`` (``build(ref_image, points, carried.keywords())`` with
    ``carried``, a moved reference's :class:`CarriedMasks`) and kept for the next frames."""
    with _LOCK:  # one frame at a time per process (a worker's threads would share a tracker)
        tracker = _CACHE.get(key)
        if tracker is None:
            tracker = build(ref_image, points) if carried is None else build(ref_image, points, carried.keywords())
            _CACHE[key] = tracker
            while len(_CACHE) > _CACHE_SIZE:
                _CACHE.popitem(last=False)
        else:
            _CACHE.move_to_end(key)
        t0 = time.perf_counter()
        raw = tracker.track(image, guess=None)
        return raw, time.perf_counter() - t0


class CarriedMasks:
    """What a moved reference's tracker is cut by, as a Dask run ships it to its workers: the :class:`dic.Tracker`
    keywords ``carried`` (``pixel_region``: the run's region carried into the moved reference's image, (H, W)
    bool; ``blocked_pixels``: the carried cracks' callable; ``cracks``: None), built once in the client by
    :func:`dic.sequence.track2d._carry_for` as a single-process run builds them. The region travels packed 8 px a
    byte (``np.packbits``: an eighth of a bool image, a thirty-second of the float32 frame that goes with it), the
    cracks' callable as the moved points, their sub-pixel positions and the carried polylines
    (:meth:`dic.correlation.lagrangian.MovedReference.crack_blocked_pixels`). :meth:`keywords` gives back the same
    keywords on the worker (the region bit for bit)."""

    def __init__(self, carried: dict):
        import numpy as np

        kw = dict(carried)
        region = kw.pop("pixel_region", None)
        self.shape = None
        self.bits = None
        if region is not None:
            region = np.asarray(region, dtype=bool)
            self.shape = tuple(region.shape)
            self.bits = np.packbits(region.ravel())
        self.rest = kw

    @property
    def nbytes(self) -> int:
        """Bytes of the packed region (0 without one)."""
        return 0 if self.bits is None else int(self.bits.nbytes)

    def keywords(self) -> dict:
        """The tracker keywords (a new dict; ``pixel_region`` unpacked to (H, W) bool)."""
        import numpy as np

        kw = dict(self.rest)
        if self.bits is not None:
            h, w = self.shape
            kw["pixel_region"] = np.unpackbits(self.bits, count=h * w).reshape(h, w).astype(bool)
        return kw


class ReferenceBuilder:
    """Builds the tracker of a reference on a worker: ``make_tracker(image, points)`` (a moved reference's with
    ``carried``: ``make_tracker(image, points, carried=carried)``), in chunks of the memory budget when over it
    (as :func:`dic.sequence.track_sequence` does on one machine)."""

    def __init__(self, make_tracker, budget: int, order: int, search=None):
        self.make_tracker, self.budget, self.order, self.search = make_tracker, int(budget), int(order), search

    def over_budget(self, n_points: int) -> bool:
        from .chunks import bytes_per_poi

        return n_points * bytes_per_poi(self.order) > self.budget

    def __call__(self, image, points, carried: dict | None = None):
        import functools

        from .chunks import ChunkedTracker, bytes_per_poi

        make = self.make_tracker if carried is None else functools.partial(self.make_tracker, carried=carried)
        if points is not None and self.over_budget(len(points)):
            return ChunkedTracker(make, image, points, order=self.order,
                                  chunk=self.budget // bytes_per_poi(self.order), search=self.search)
        return make(image, points)
