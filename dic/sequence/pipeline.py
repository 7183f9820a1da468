"""The pipeline of a sequence run: a reader thread ahead, a writer thread behind, bounded queues.

The correlation runs on the caller's thread; :func:`read_ahead` reads and decodes the next frames
(and computes their digests) on a background thread while it works, and :class:`WriteBehind`
writes finished frames (strain, result file, VTK, figures) on another one. Both queues are bounded,
so at most ``depth`` frames wait on either side: memory does not grow with the sequence length.
:func:`trim_memory` hands freed heap pages back to the system (glibc keeps them otherwise: the
issue measured +1-4 MB per frame without it).
"""
from __future__ import annotations

import ctypes
import os
import queue
import threading
from dataclasses import dataclass
from typing import Any, Callable, Iterable

import numpy as np

__all__ = ["Loaded", "read_ahead", "WriteBehind", "trim_memory", "load_image"]

_DONE = object()


@dataclass
class Loaded:
    """One frame read ahead: its index, image(s), path(s) ('' for arrays) and digest(s); or the error reading it."""

    index: int
    image: Any = None
    path: Any = ""
    digest: Any = ""
    error: BaseException | None = None


def load_image(item, what: str, *, keep_tensors: bool = False) -> tuple[Any, str]:
    """An image given as an array, a torch tensor or a file path -> (array, path or '').

    A torch tensor is passed through untouched with ``keep_tensors`` (frames a tracker reads in place
    on its device: no host copy); otherwise it is copied to the host once (a NumPy array).
    """
    from kernels.images import is_torch_tensor

    if isinstance(item, (str, os.PathLike)):
        from kernels.images import read_image

        return read_image(item), os.fspath(item)
    if item is None:
        raise ValueError(f"{what} is missing")
    name = ""
    if hasattr(item, "image") and hasattr(item, "name"):  # a dic.sources.Frame: its image and its name
        item, name = item.image, str(item.name)
    if is_torch_tensor(item):
        return (item if keep_tensors else item.detach().cpu().numpy()), name
    return np.asarray(item), name


def read_ahead(items: Iterable, load: Callable[[int, Any], Loaded], *, first: int = 1, depth: int = 2):
    """Yield ``load(index, item)`` for the items in order (indices from ``first``), read on a thread.

    At most ``depth`` loaded frames wait in the queue. An error while iterating or loading is yielded
    as a :class:`Loaded` with ``error`` set (the frame's index is known), and reading stops there.
    Closing the generator stops the thread.
    """
    q: queue.Queue = queue.Queue(maxsize=max(1, int(depth)))
    stop = threading.Event()

    def put(obj) -> bool:
        while not stop.is_set():
            try:
                q.put(obj, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work():
        index = first
        try:
            it = iter(items)
            while not stop.is_set():
                try:
                    item = next(it)
                except StopIteration:
                    break
                except Exception as exc:  # noqa: BLE001 - a source that fails mid-sequence: reported with its index
                    put(Loaded(index, error=exc))
                    return
                try:
                    loaded = load(index, item)
                except Exception as exc:  # noqa: BLE001 - reported to the caller's thread
                    loaded = Loaded(index, path=item if isinstance(item, (str, os.PathLike)) else "", error=exc)
                if not put(loaded) or loaded.error is not None:
                    return
                index += 1
        finally:
            put(_DONE)

    thread = threading.Thread(target=work, name="specula-reader", daemon=True)
    thread.start()
    try:
        while True:
            obj = q.get()
            if obj is _DONE:
                break
            yield obj
    finally:
        stop.set()
        while True:  # unblock a reader waiting on a full queue
            try:
                q.get_nowait()
            except queue.Empty:
                break
        thread.join()


class WriteBehind:
    """Run jobs (writing finished frames) in order on one thread, at most ``depth`` waiting.

    ``depth`` 0: none waits, :meth:`submit` returns once the job before has finished (one frame is
    written while the next is computed, no more frames are held: for frames whose results take
    gigabytes). :meth:`submit` raises the first error a job raised (later jobs are dropped, the
    frames written before stay in the file); :meth:`close` waits for every submitted job and raises
    that error too.
    """

    def __init__(self, depth: int = 2):
        depth = max(0, int(depth))
        self._q: queue.Queue = queue.Queue()
        self._slots = threading.Semaphore(depth + 1)  # jobs submitted and not finished: the one running + depth
        self.error: BaseException | None = None
        self.lock = threading.RLock()  # taken by every job and by the caller's own reads of the result file
        self._thread = threading.Thread(target=self._work, name="specula-writer", daemon=True)
        self._thread.start()

    def _work(self):
        while True:
            job = self._q.get()
            if job is _DONE:
                return
            try:
                if self.error is None:
                    with self.lock:
                        job()
            except BaseException as exc:  # noqa: BLE001 - re-raised on the caller's thread
                self.error = exc
            finally:
                del job  # the finished frame is freed before the next one is waited for
                self._slots.release()

    def check(self) -> None:
        if self.error is not None:
            raise self.error

    def submit(self, job: Callable[[], None]) -> None:
        self.check()
        while not self._slots.acquire(timeout=0.1):
            self.check()
        self._q.put(job)

    def close(self, *, raise_error: bool = True) -> None:
        if self._thread.is_alive():
            self._q.put(_DONE)
            self._thread.join()
        if raise_error:
            self.check()


_LIBC = None


def trim_memory() -> None:
    """Give freed heap memory back to the system (glibc's ``malloc_trim(0)``; a no-op elsewhere)."""
    global _LIBC
    if _LIBC is None:
        try:
            _LIBC = ctypes.CDLL("libc.so.6")
            _LIBC.malloc_trim.argtypes = [ctypes.c_size_t]
        except (OSError, AttributeError):
            _LIBC = False
    if _LIBC:
        _LIBC.malloc_trim(0)
