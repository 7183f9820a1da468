"""Stereo-DIC sequences: match the reference pair once, track every later pair, write as you go.

On the sequence engine's pipeline (:mod:`dic.sequence.pipeline`): the next pairs are read on a
thread ahead of the correlation, the finished states written on a thread behind it.

:func:`stereo_sequence` runs :class:`dic.stereo.StereoCorrelation` over a list of image pairs
(arrays or image files; the first pair is the reference) and writes each state through the
results store (:class:`dic.store.ResultWriter`, kind ``stereo``) as soon as it is finished, so
that an interrupted run keeps every finished state and a rerun with the same output, images and
settings resumes after the last one (the reference match is read back, not recomputed).
:func:`read_stereo` and :func:`read_field` (from :mod:`dic.store`) read a file back into
:class:`~dic.field3d.Field3D` objects. File layout: docs/results_format.md (format
``specula-stereo``), docs/stereo.md ("Sequences and the result file").
"""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..correlation.points import Region, region
from ..field3d import Field3D
from ..stereo import StereoCorrelation, as_rig
from ..store import SCHEMA_VERSION, ResultWriter, StereoResults, image_digest, read_field, read_stereo
from ..store import STEREO_FORMAT_NAME as FORMAT_NAME
from .pipeline import Loaded, WriteBehind, load_image, read_ahead, trim_memory

__all__ = ["stereo_sequence", "read_stereo", "read_field", "StereoResults", "FORMAT_NAME", "SCHEMA_VERSION"]


_load = load_image
_TRIM_EVERY = 10  # states between two malloc_trim calls


def stereo_sequence(rig, pairs: Sequence, out, *, mode: str = "resume", progress: bool = False,
                    callback: Callable[[Field3D], None] | None = None, vtk_dir=None, guess: str | None = None,
                    client=None, **options) -> list[Field3D]:
    """Stereo DIC of an image-pair sequence, written state by state to an HDF5 file.

    Parameters
    ----------
    rig : calibration.stereo.StereoRig, or a rig file in any format Specula reads (Specula JSON,
        OpenCV YAML/XML/JSON, VIC-3D XML, DICe XML; :func:`dic.stereo.as_rig`)
    pairs : sequence of (left, right)
        Images (arrays or file paths: TIFF, PNG, BMP). ``pairs[0]`` is the reference state;
        state ``k`` is ``pairs[k]``. Each state is tracked from the reference with the previous
        state's parameters as initial guess (the reference match is done once).
    out : str or Path
        The ``.h5`` file (layout: docs/results_format.md). An existing file with the same rig,
        reference images and settings is resumed (finished states are skipped) unless
        ``mode="overwrite"`` (``"new"`` refuses an existing file); an incompatible one, or one
        whose finished states were computed from other image pairs than those given now, raises
        ``ValueError``; a file another process is writing raises
        :class:`dic.store.ResultFileInUse`, a full disk :class:`dic.store.ResultWriteError`
        (both ``ValueError``; finished states stay in the file).
    progress : bool
        Show a tqdm progress bar.
    callback : callable(Field3D), optional
        Called with each state's result after it is written (not for skipped states; later states
        are called on the writer thread, in order).
    vtk_dir : folder, optional
        Write ``stereo_<index>.vtu`` per later state as it finishes (every point with a position, NaN
        where invalid).
    guess : "previous" | "none", optional
        ``"previous"`` (default without ``client``): each state starts from the previous state's
        parameters; ``"none"`` (default, and the only choice, with ``client``): from zero and the
        global shift, so states are independent (stored in the settings).
    client : distributed.Client or scheduler address, optional
        Measure the states on a Dask cluster (docs/dic2d.md, "Sequences on several machines"): the
        reference match is done here once, each worker prepares the reference pair once and keeps it,
        the states are written here in order; results identical to ``guess="none"`` on one process.
    options
        :class:`dic.stereo.StereoCorrelation` keywords (``step``, ``subset``, ``order``,
        ``frame``, ``roi``, ``points``, ``epipolar_tol_px``, ``zncc_min``, ``strain_window``,
        ``max_iter``, ``tol``, ``triangulation``, ``device``).

    Returns
    -------
    list of Field3D
        The states computed in this call (skipped states are not read back; use :func:`read_stereo`).
    """
    if isinstance(client, str):  # a scheduler address: connected here, closed when the run ends
        from .distributed import connect

        given = dict(locals())
        given.pop("connect")
        opts = given.pop("options")
        with connect(client) as given["client"]:
            return stereo_sequence(**given, **opts)
    from tqdm import tqdm

    pairs = list(pairs)
    if not pairs:
        raise ValueError("pairs is empty: give at least the reference (left, right) pair")
    for k, p in enumerate(pairs):
        if not isinstance(p, (tuple, list)) or len(p) != 2:
            raise ValueError(f"pairs[{k}] must be a (left, right) pair, got {type(p).__name__}")
    out = Path(os.fspath(out))
    left_ref, lp = _load(pairs[0][0], "reference left image")
    right_ref, rp = _load(pairs[0][1], "reference right image")
    device = options.pop("device", None)
    rig = as_rig(rig, image_size=(np.shape(left_ref)[1], np.shape(left_ref)[0]))
    if options.get("roi") is not None:  # checked once (a mask file is read once); stored in its JSON form
        options["roi"] = region(options["roi"], np.shape(left_ref))
    settings = {k: (v.settings() if isinstance(v, Region) else np.asarray(v).tolist() if isinstance(v, np.ndarray)
                    else v) for k, v in sorted(options.items())}
    if out.suffix.lower() not in (".h5", ".hdf5"):
        raise ValueError(f"the output must be an HDF5 file ending in .h5, got {out.name}")
    if guess is None:
        guess = "previous" if client is None else "none"
    if guess not in ("previous", "none"):
        raise ValueError(f"guess must be 'previous' or 'none', got {guess!r}")
    if client is not None:
        if guess != "none":
            raise ValueError("guess='previous' chains each state to the one before it and cannot be distributed: "
                             "with client= every state starts from guess='none' (leave guess out)")
        from .distributed import connect

        client = connect(client)
    if guess == "none":  # only when not chained: files of earlier runs resume as before
        settings["guess"] = "none"
    ref_digests = (image_digest(left_ref), image_digest(right_ref))
    writer = ResultWriter(out, kind="stereo", reference_path=(lp, rp), reference_shape=np.shape(left_ref),
                          reference_sha256=ref_digests, settings=settings, rig=rig, mode=mode)
    results = []
    with writer:
        done = set(writer.done_frames())
        # resuming: every finished state must have been computed from the pair given for it now (the later
        # states are checked as they are read, below)
        if 0 in done:
            writer.check_frame(0, (lp, rp), ref_digests)
        match = writer.read_match()
        t0 = time.perf_counter()
        sc = StereoCorrelation(rig, left_ref, right_ref, match=match, device=device, **options)
        if match is None:
            writer.write_match(sc.match)
        if 0 not in done:
            writer.write_frame(0, sc.reference, path=(lp, rp), sha256=ref_digests,
                               attrs={"seconds": float(time.perf_counter() - t0)})
            results.append(sc.reference)
            if callback:
                callback(sc.reference)
        # the later states: the next pairs are read on a thread ahead, the finished ones written on one behind
        wb = WriteBehind(depth=2)

        def finish(k, f, lpath, rpath, digests, seconds):
            writer.write_frame(k, f, path=(lpath, rpath), sha256=digests, attrs={"seconds": seconds})
            if vtk_dir is not None:
                from ..export import write_vtk

                write_vtk(f, Path(vtk_dir) / f"stereo_{k:06d}.vtu", invalid="nan")
            if callback:
                callback(f)

        def load(k, pair) -> Loaded:
            (L, lpath), (R, rpath) = _load(pair[0], f"left image of pair {k}"), _load(pair[1], f"right image of pair {k}")
            return Loaded(k, (L, R), (lpath, rpath), (image_digest(L), image_digest(R)))

        if vtk_dir is not None:
            Path(vtk_dir).mkdir(parents=True, exist_ok=True)
        last_images = None  # the pair of the last state skipped (resuming starts from it)
        computed = 0
        reader = read_ahead(pairs[1:], load, first=1)
        if client is not None:
            with tqdm(total=len(pairs), initial=1 if 0 in done or results else 0, unit="pair", desc="stereo",
                      disable=not progress) as bar:
                try:
                    _stereo_on_dask(client, reader, writer, wb, done, results, bar, finish, out,
                                    _StereoBuilder(rig, left_ref, right_ref, sc.match, device, options))
                finally:
                    reader.close()
                    wb.close(raise_error=False)
            trim_memory()
            return results
        with tqdm(total=len(pairs), initial=1 if 0 in done or results else 0, unit="pair", desc="stereo",
                  disable=not progress) as bar:
            try:
                for item in reader:
                    k = item.index
                    if item.error is not None:
                        wb.close()
                        raise item.error
                    (L, R), (lpath, rpath) = item.image, item.path
                    if k in done:  # resuming: the finished state must come from the pair given for it now
                        with wb.lock:
                            writer.check_frame(k, (lpath, rpath), item.digest)
                        last_images = (L, R)
                        bar.update(1)
                        continue
                    prev = max((d for d in done if d < k and d > 0), default=None)
                    if sc._previous is None and prev is not None:  # resuming: start from the last stored state
                        with wb.lock:
                            params_left, params_right = writer.frame_arrays(prev, ("params_left", "params_right"))
                        sc.set_previous(params_left, params_right, images=last_images if prev == k - 1 else None)
                    t1 = time.perf_counter()
                    try:
                        f = sc.measure(L, R, index=k, use_previous=guess == "previous")
                    except ValueError as exc:
                        wb.close()
                        raise ValueError(f"pair {k} ({lpath or 'array'}, {rpath or 'array'}): {exc}") from None
                    wb.submit(lambda k=k, f=f, lp=lpath, rp=rpath, d=item.digest, s=float(time.perf_counter() - t1):
                              finish(k, f, lp, rp, d, s))
                    done.add(k)
                    results.append(f)
                    computed += 1
                    if computed % _TRIM_EVERY == 0:
                        trim_memory()
                    bar.update(1)
                wb.close()
            finally:
                reader.close()
                wb.close(raise_error=False)
        trim_memory()
    return results


class _StereoBuilder:
    """A worker's :class:`dic.stereo.StereoCorrelation` of the reference pair with the client's match
    (the builder interface of :func:`dic.sequence.distributed.track_on_worker`)."""

    def __init__(self, rig, left, right, match, device, options):
        self.rig, self.left, self.right, self.match, self.device, self.options = rig, left, right, match, device, options

    def __call__(self, _image, _points):
        return _StereoMeasure(StereoCorrelation(self.rig, self.left, self.right, match=self.match, device=self.device,
                                                **self.options))


class _StereoMeasure:
    def __init__(self, sc):
        self.sc = sc

    def track(self, item, guess=None):
        k, L, R = item
        return self.sc.measure(L, R, index=k, use_previous=False)


def _stereo_on_dask(client, reader, writer, wb, done, results, bar, finish, out, builder):
    """The later states of :func:`stereo_sequence` measured on a Dask cluster, written here in order."""
    import uuid
    from collections import OrderedDict

    import cloudpickle

    from .distributed import LOST, held, n_workers, release, track_on_worker

    lost = LOST()
    token = uuid.uuid4().hex[:16]
    try:
        cloudpickle.dumps(builder)
    except Exception as exc:
        raise ValueError(f"the stereo settings cannot be sent to the Dask workers ({type(exc).__name__}: {exc})") from None
    build = client.submit(held, builder, key=f"specula-{token}-stereo-builder", pure=False)
    window = 2 * n_workers(client) + 1
    pending: OrderedDict = OrderedDict()  # state -> (future, Loaded)

    def fail(k, item, exc):
        (lpath, rpath) = item.path if item.path else (None, None)
        raise ValueError(f"pair {k} ({lpath or 'array'}, {rpath or 'array'}): {exc}") from None

    def drain_one():
        k, (fut, item) = pending.popitem(last=False)
        try:
            f, seconds = fut.result()
        except ValueError as exc:
            wb.close()
            fail(k, item, exc)
        except lost as exc:
            wb.close()
            fail(k, item, f"the Dask cluster could not compute it ({type(exc).__name__}: {exc})")
        lpath, rpath = item.path
        wb.submit(lambda k=k, f=f, lp=lpath, rp=rpath, d=item.digest, s=float(seconds): finish(k, f, lp, rp, d, s))
        done.add(k)
        results.append(f)
        if len(results) % _TRIM_EVERY == 0:
            trim_memory()
        bar.update(1)

    try:
        for item in reader:
            k = item.index
            if item.error is not None:
                while pending:
                    drain_one()
                wb.close()
                raise item.error
            if k in done:  # resuming: the finished state must come from the pair given for it now
                with wb.lock:
                    writer.check_frame(k, item.path, item.digest)
                bar.update(1)
                continue
            while len(pending) >= window:
                drain_one()
            L, R = item.image
            pending[k] = (client.submit(track_on_worker, f"{token}:stereo", build, None, None, (k, L, R),
                                        key=f"specula-{token}-pair-{k}", pure=False), item)
        while pending:
            drain_one()
        wb.close()
    finally:
        if pending:
            client.cancel([f for f, _ in pending.values()])
        release(client, token + ":")
