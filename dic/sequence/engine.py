"""The one sequence loop of 2-D (:func:`dic.sequence.track_sequence`) and stereo (:func:`dic.sequence.stereo_sequence`).

:func:`run_sequence` drives a *kind* of sequence through one small protocol (:class:`FrameMeasure`,
after OpenCorr's ``DIC`` interface: the reference is prepared once, then each frame is computed):

- ``measure(k, image)``: frame ``k`` against the current reference, from the kind's own initial
  guess (the previous frame's result, or none);
- ``move_reference(r, image, state)``: track the next frames from frame ``r`` (``r = 0``: the
  reference image or pair), :class:`CannotServe` when frame ``r`` has no valid point;
- ``quality(result)``: valid fraction among the points the reference can track, median ZNCC;
- ``accept(k, result, image)``, ``stored_state(r)``: the next frame's guess starts from a result (2-D with
  ``verify_composed``: checked against the reference image first, :mod:`dic.sequence.verification`); what
  a moved reference is built from (a frame computed in this call, or one read back from the file);
- ``counts(result)``, ``mismatches(result)``: valid points and points of the region; points that failed the
  check of composed results;
- ``check_done``, ``resume``: the resume check of a finished frame and the initial guess after it;
- ``write(k, result, item, seconds)``: the result file, side outputs and callback (writer thread).

The loop owns what is the same for every kind: the resume check of finished frames, the reference
policy (``fixed``, ``incremental``, ``every:N`` and ``auto`` with its one retry; a frame that cannot
serve as a reference leaves the previous reference in place), the images that may serve as a
reference (at most three frames held), the reader thread ahead and the writer thread behind
(:mod:`dic.sequence.pipeline`), memory trimming, the progress bar and the :class:`SequenceSummary`.
Results are never held after they are written: the summary keeps a few numbers per frame.
The Dask window of either kind is :func:`run_on_dask`.
"""
from __future__ import annotations

import time
from array import array
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np

from .pipeline import Loaded, WriteBehind, trim_memory
from .reference import ReferencePolicy

__all__ = ["SequenceSummary", "FrameMeasure", "CannotServe", "run_sequence", "run_on_dask", "dask_window",
           "TRIM_EVERY"]

TRIM_EVERY = 10  # frames between two malloc_trim calls


class CannotServe(ValueError):
    """Raised by a kind's ``move_reference``: the frame cannot serve as a reference (no valid point, or none
    that is no false match); the engine keeps the previous reference."""


@dataclass
class SequenceSummary:
    """What a sequence run did (:func:`dic.sequence.track_sequence`, :func:`dic.sequence.stereo_sequence`).

    ``path``: the result file (read it with :func:`dic.store.read_results`); ``skipped``: finished
    frames already in the file; ``seconds``: the whole call; per frame computed in this call, in
    order, compact columns: ``indices``, ``n_valid``, ``n_points``, ``frame_seconds``,
    ``reference_indices``, ``n_mismatch`` (NumPy arrays), and ``frames``, the same as one dict per frame
    (``index``, ``n_valid``, ``n_points``, ``seconds``, ``reference_index``, ``n_mismatch``) built on request.
    ``n_mismatch``: the points of a composed frame (correlated against a moved reference) that failed the
    check against the reference image (2-D ``verify_composed``, :mod:`dic.sequence.verification`; they are
    not in ``n_valid``); 0 where nothing was checked. A stereo run
    counts the reference state 0 as a computed frame when it wrote it. ``n_points`` counts the points of the
    region, not the whole grid: 2-D, the tracked points (the region's grid); stereo, the grid points that were
    computed (status not ``NOT_COMPUTED``: inside the region, a reference subset with texture in the image).
    """

    path: Path
    skipped: int = 0
    seconds: float = 0.0
    _index: array = field(default_factory=lambda: array("q"), repr=False)
    _valid: array = field(default_factory=lambda: array("q"), repr=False)
    _points: array = field(default_factory=lambda: array("q"), repr=False)
    _seconds: array = field(default_factory=lambda: array("d"), repr=False)
    _reference: array = field(default_factory=lambda: array("q"), repr=False)
    _mismatch: array = field(default_factory=lambda: array("q"), repr=False)

    def add(self, index: int, n_valid: int, n_points: int, seconds: float, reference_index: int,
            n_mismatch: int = 0) -> None:
        """Record one computed frame."""
        self._index.append(int(index))
        self._valid.append(int(n_valid))
        self._points.append(int(n_points))
        self._seconds.append(float(seconds))
        self._reference.append(int(reference_index))
        self._mismatch.append(int(n_mismatch))

    def __len__(self) -> int:
        return len(self._index)

    @property
    def indices(self) -> np.ndarray:
        return np.asarray(self._index, dtype=np.int64)

    @property
    def n_valid(self) -> np.ndarray:
        return np.asarray(self._valid, dtype=np.int64)

    @property
    def n_points(self) -> np.ndarray:
        return np.asarray(self._points, dtype=np.int64)

    @property
    def frame_seconds(self) -> np.ndarray:
        return np.asarray(self._seconds, dtype=np.float64)

    @property
    def reference_indices(self) -> np.ndarray:
        return np.asarray(self._reference, dtype=np.int64)

    @property
    def n_mismatch(self) -> np.ndarray:
        return np.asarray(self._mismatch, dtype=np.int64)

    @property
    def frames(self) -> list[dict]:
        """One dict per computed frame (``index``, ``n_valid``, ``n_points``, ``seconds``, ``reference_index``,
        ``n_mismatch``)."""
        return [{"index": k, "n_valid": v, "n_points": n, "seconds": s, "reference_index": r, "n_mismatch": m}
                for k, v, n, s, r, m in zip(self._index, self._valid, self._points, self._seconds, self._reference,
                                            self._mismatch)]

    @property
    def frames_per_second(self) -> float:
        return len(self) / self.seconds if self.seconds > 0 else float("nan")

    def __repr__(self) -> str:
        n = len(self)
        text = f"SequenceSummary: {n} computed"
        if n:
            text += f" ({self._index[0]}..{self._index[-1]})" if n > 1 else f" ({self._index[0]})"
        text += f", {self.skipped} skipped, {self.seconds:.1f} s"
        if n and self.seconds > 0:
            text += f" ({self.frames_per_second:.3g}/s)"
        pts = self.n_points
        if n and pts.min() > 0:
            share = 100.0 * self.n_valid / pts
            text += f", valid {share.min():.1f}-{share.max():.1f} %"
        if n and any(self._mismatch):
            text += f", {sum(self._mismatch)} composed mismatches"
        return f"<{text}; {self.path}>"


class FrameMeasure(Protocol):
    """What :func:`run_sequence` needs of a kind of sequence (2-D: ``dic.sequence.track2d``; stereo:
    ``dic.sequence.stereo``). ``result`` is the kind's own result (a :class:`dic.field2d.Field2D`, a
    :class:`dic.field3d.Field3D`); ``item`` the :class:`dic.sequence.pipeline.Loaded` frame."""

    noun: str  # "frame" | "state": in messages
    images_noun: str  # "the image" | "the images": in messages
    inputs_noun: str  # "frames" | "pairs": in messages

    @property
    def reference_index(self) -> int: ...

    def measure(self, k: int, image, *, final: bool = True) -> Any:
        """Frame k against the current reference (``final`` False: it may be measured again from a newer
        reference, so no warning about it yet)."""

    def kept(self, result) -> None:
        """A result measured with ``final=False`` is kept (the warnings ``measure`` held back)."""

    def accept(self, k: int, result, image) -> Any:
        """Frame k's result is final: the next frame's initial guess starts from it. Returns its state
        (what :meth:`move_reference` builds a reference from)."""

    def quality(self, result) -> tuple[float, float]: ...

    def stored_state(self, r: int) -> Any: ...

    def move_reference(self, r: int, image, state) -> None:
        """Track the next frames from frame r (``image``, ``state``); r = 0: back to the reference.
        :class:`CannotServe` when frame r has no valid point."""

    def check_done(self, k: int, item: Loaded) -> int:
        """Check a finished frame against the image given for it now; its reference index."""

    def resume(self, k: int, image, *, next_done: bool) -> None:
        """Frame k is finished (skipped): when the next is not, start its guess from k."""

    def counts(self, result) -> tuple[int, int]:
        """(valid points, points of the region: see :class:`SequenceSummary`) of a result."""

    def mismatches(self, result) -> int:
        """Points of an accepted result that failed the check against the reference image (0: none or no check)."""

    def write(self, k: int, result, item: Loaded, seconds: float) -> None: ...

    def failed(self, item: Loaded, exc: BaseException) -> BaseException:
        """The error to raise for a frame that could not be read or measured."""


def run_sequence(kind: FrameMeasure, reader, policy: ReferencePolicy, *, done: set, wb: WriteBehind,
                 summary: SequenceSummary, bar, out: Path, lock) -> None:
    """The frames of ``reader`` (:func:`dic.sequence.pipeline.read_ahead`) measured by ``kind`` in order.

    ``done``: the frames finished in the file (checked, skipped); ``wb``: the writer thread
    (``kind.write`` runs there); ``lock``: taken around reads of the result file; ``bar``: a tqdm
    bar. Raises what ``kind.failed`` makes of a frame that cannot be read or measured, after the
    frames before it are written.
    """
    images: dict[int, Any] = {}  # images of frames that may serve as a reference: bounded (<= 3)
    states: dict[int, Any] = {}  # the states of those computed in this call (what a moved reference is built from)
    prev_ref = 0  # the reference index of the frame before the next one
    computed = 0

    def use_reference(r: int, fallback: int | None) -> int:
        """Move to frame r (a frame with no valid point cannot serve: ``fallback`` then); the reference used."""
        if r == kind.reference_index:
            return r
        if r == 0:
            kind.move_reference(0, None, None)
            return 0
        if r not in images:
            raise ValueError(f"cannot resume {out}: {kind.images_noun} of {kind.noun} {r}, the reference of the next "
                             f"{kind.noun}, {'was' if kind.images_noun == 'the image' else 'were'} not given again; "
                             f"give the same {kind.inputs_noun} as the run that wrote the file")
        state = states.get(r)
        if state is None:
            with lock:
                state = kind.stored_state(r)
        try:
            kind.move_reference(r, images[r], state)
        except CannotServe:  # no valid point (or none that is no false match): the previous reference stays
            if fallback is None or fallback == r:
                raise ValueError(f"{kind.noun} {r} has no valid point and cannot serve as a reference") from None
            return use_reference(fallback, fallback)
        return r

    def hold(k: int, image, state) -> None:
        """Keep frame k's image (and state) while it may serve as a reference: the next frame's first
        reference (every:N: the key frame, kept although it could not serve), k itself, the current one."""
        images[k] = image
        if state is not None:
            states[k] = state
        keep = {policy.start(k + 1, prev_ref), k, kind.reference_index}
        for i in [i for i in images if i not in keep]:
            del images[i]
        for i in [i for i in states if i not in keep]:
            del states[i]

    for item in reader:
        k = item.index
        if item.error is not None:
            wb.close(raise_error=True)  # the frames before it are written first
            err = kind.failed(item, item.error)
            if err is item.error:
                raise err
            raise err from None
        if k in done:  # resuming: the finished frame must come from the image given for it now
            with lock:
                prev_ref = kind.check_done(k, item)
                kind.resume(k, item.image, next_done=k + 1 in done)
            hold(k, item.image, None)
            summary.skipped += 1
            bar.update(1)
            continue
        t0 = time.perf_counter()
        try:
            r = use_reference(policy.start(k, prev_ref), prev_ref)
            if policy.kind == "auto" and r != k - 1 and k > 1:
                result = kind.measure(k, item.image, final=False)
                if policy.needs_update(*kind.quality(result)) and use_reference(k - 1, r) != r:
                    result = kind.measure(k, item.image)
                else:
                    kind.kept(result)
            else:
                result = kind.measure(k, item.image)
        except ValueError as exc:
            wb.close(raise_error=True)
            raise kind.failed(item, exc) from None
        seconds = time.perf_counter() - t0
        state = kind.accept(k, result, item.image)
        wb.submit(_job(kind, k, result, item, seconds))
        prev_ref = kind.reference_index
        n_valid, n_points = kind.counts(result)
        summary.add(k, n_valid, n_points, seconds, prev_ref, kind.mismatches(result))
        hold(k, item.image, state if policy.kind != "fixed" else None)
        del result, state
        computed += 1
        if computed % TRIM_EVERY == 0:
            trim_memory()
        bar.update(1)
    wb.close(raise_error=True)


def _job(kind, k, result, item, seconds) -> Callable[[], None]:
    return lambda: kind.write(k, result, item, seconds)


def dask_window(client) -> int:
    """Frames in flight at once on a Dask cluster: two per worker thread, plus one."""
    from .distributed import n_workers

    return 2 * n_workers(client) + 1


def run_on_dask(client, reader, *, done: set, wb: WriteBehind, summary: SequenceSummary, bar, token: str,
                submit: Callable, collect: Callable, check_done: Callable, failed: Callable,
                before: Callable | None = None) -> None:
    """The frames of ``reader`` computed on a Dask cluster and collected here in frame order: the one Dask
    window of 2-D and stereo sequences (:func:`dask_window` frames in flight; the oldest is collected first).

    ``submit(k, item) -> (future, context)`` sends frame k out (the future gives ``(result, seconds)``);
    ``collect(k, item, context, result, seconds) -> (n_valid, n_points, reference_index[, n_mismatch])``
    hands the result to the writer thread (``n_mismatch``: its points that failed the check of composed
    results, 0 when not given); ``check_done(k, item)``: the resume check of a finished frame (under
    ``wb.lock``); ``failed(item, exc)``: the error naming the frame; ``before(k, item, wait)``, optional:
    called first for every frame (2-D every:N: a new reference, whose key frame it waits for with
    ``wait(r)``, which collects the frames up to r). Cancels what is in flight on the way out and
    releases the data held under ``token`` on the workers.
    """
    from collections import OrderedDict

    from .distributed import LOST, release

    lost = LOST()
    window = dask_window(client)
    pending: OrderedDict = OrderedDict()  # frame -> (future, Loaded, context)

    def collect_one():
        k, (fut, item, context) = pending.popitem(last=False)
        try:
            result, seconds = fut.result()
        except ValueError as exc:
            wb.close(raise_error=True)  # the frames before it are written first
            raise failed(item, exc) from None
        except lost as exc:  # workers that kept dying on this frame, a scheduler gone, a cancelled run
            wb.close(raise_error=True)
            raise failed(item, ValueError(f"the Dask cluster could not compute it ({type(exc).__name__}: {exc})")) \
                from None
        n_valid, n_points, reference_index, *n_mismatch = collect(k, item, context, result, seconds)
        del result
        summary.add(k, n_valid, n_points, seconds, reference_index, *n_mismatch)
        if len(summary) % TRIM_EVERY == 0:
            trim_memory()
        bar.update(1)

    def wait(r: int) -> None:
        while r in pending:
            collect_one()

    try:
        for item in reader:
            k = item.index
            if item.error is not None:
                while pending:
                    collect_one()
                wb.close(raise_error=True)
                err = failed(item, item.error)
                if err is item.error:
                    raise err
                raise err from None
            if before is not None:
                before(k, item, wait)
            if k in done:  # resuming: the finished frame must come from the image given for it now
                with wb.lock:
                    check_done(k, item)
                summary.skipped += 1
                bar.update(1)
                continue
            while len(pending) >= window:
                collect_one()
            fut, context = submit(k, item)
            pending[k] = (fut, item, context)
        while pending:
            collect_one()
        wb.close(raise_error=True)
    finally:
        if pending:
            client.cancel([f for f, _, _ in pending.values()])
        release(client, token + ":")
