"""Stereo-DIC sequences: match the reference pair once, track every later pair, write as you go.

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
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..correlation.points import Region, region
from ..field3d import Field3D
from ..stereo import StereoCorrelation, as_rig
from ..store import SCHEMA_VERSION, ResultWriter, StereoResults, image_digest, read_field, read_stereo
from ..store import STEREO_FORMAT_NAME as FORMAT_NAME

__all__ = ["stereo_sequence", "read_stereo", "read_field", "StereoResults", "FORMAT_NAME", "SCHEMA_VERSION"]


def _load(item, what: str) -> tuple[np.ndarray, str]:
    """An image given as an array or a file path -> (array, path or '')."""
    if isinstance(item, (str, os.PathLike)):
        from ..io import read_image

        return read_image(item), os.fspath(item)
    if item is None:
        raise ValueError(f"{what} is missing")
    return np.asarray(item), ""


def stereo_sequence(rig, pairs: Sequence, out, *, mode: str = "resume", progress: bool = False,
                    callback: Callable[[Field3D], None] | None = None, **options) -> list[Field3D]:
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
        Called with each state's result after it is written (not for skipped states).
    options
        :class:`dic.stereo.StereoCorrelation` keywords (``step``, ``subset``, ``order``,
        ``frame``, ``roi``, ``points``, ``epipolar_tol_px``, ``zncc_min``, ``strain_window``,
        ``max_iter``, ``tol``, ``triangulation``, ``device``).

    Returns
    -------
    list of Field3D
        The states computed in this call (skipped states are not read back; use :func:`read_stereo`).
    """
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
    ref_digests = (image_digest(left_ref), image_digest(right_ref))
    writer = ResultWriter(out, kind="stereo", reference_path=(lp, rp), reference_shape=np.shape(left_ref),
                          reference_sha256=ref_digests, settings=settings, rig=rig, mode=mode)
    results = []
    with writer:
        done = set(writer.done_frames())
        # resuming: every finished state must have been computed from the pair given for it now
        for k in sorted(d for d in done if d < len(pairs)):
            if k == 0:
                writer.check_frame(0, (lp, rp), ref_digests)
                continue
            (L, lpath), (R, rpath) = (_load(pairs[k][0], f"left image of pair {k}"),
                                      _load(pairs[k][1], f"right image of pair {k}"))
            writer.check_frame(k, (lpath, rpath), (image_digest(L), image_digest(R)))
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
        todo = [k for k in range(1, len(pairs)) if k not in done]
        with ThreadPoolExecutor(max_workers=1) as io_pool, \
                tqdm(total=len(pairs), initial=len(pairs) - len(todo), unit="pair", desc="stereo",
                     disable=not progress) as bar:
            def load(k):
                return _load(pairs[k][0], f"left image of pair {k}"), _load(pairs[k][1], f"right image of pair {k}")

            pending = io_pool.submit(load, todo[0]) if todo else None
            for j, k in enumerate(todo):
                (L, lpath), (R, rpath) = pending.result()
                pending = io_pool.submit(load, todo[j + 1]) if j + 1 < len(todo) else None  # overlap I/O
                prev = max((d for d in done if d < k and d > 0), default=None)
                if sc._previous is None and prev is not None:  # resuming: start from the last stored state
                    params_left, params_right = writer.frame_arrays(prev, ("params_left", "params_right"))
                    imgs = (_load(pairs[prev][0], "left image")[0], _load(pairs[prev][1], "right image")[0]) \
                        if prev < len(pairs) else None
                    sc.set_previous(params_left, params_right, images=imgs)
                t1 = time.perf_counter()
                try:
                    f = sc.measure(L, R, index=k)
                except ValueError as exc:
                    raise ValueError(f"pair {k} ({lpath or 'array'}, {rpath or 'array'}): {exc}") from None
                writer.write_frame(k, f, path=(lpath, rpath), sha256=(image_digest(L), image_digest(R)),
                                   attrs={"seconds": float(time.perf_counter() - t1)})
                done.add(k)
                results.append(f)
                if callback:
                    callback(f)
                bar.update(1)
    return results
