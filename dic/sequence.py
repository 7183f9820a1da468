"""Stereo-DIC sequences: match the reference pair once, track every later pair, write as you go.

:func:`stereo_sequence` runs :class:`dic.stereo.StereoCorrelation` over a list of image pairs
(arrays or image files; the first pair is the reference) and writes one HDF5 group per state as
soon as it is finished, so that an interrupted run keeps every finished state and a rerun with
the same output, images and settings resumes after the last one (the reference match is read
back, not recomputed). :func:`read_stereo` reads a file back into :class:`~dic.field3d.Field3D`
objects.

File layout (format ``specula-stereo``, schema version 1; docs/stereo.md, "Result file")::

    /                      attrs: format, schema_version, specula_version, created, updated
    /rig                   attrs: json (the StereoRig file content)
    /settings              attrs: json (the StereoCorrelation settings)
    /reference             attrs: left_path, right_path, shape (H, W), left_sha256, right_sha256
    /reference/match       points_left, points_right, params, zncc, iterations, icgn_status,
                           epipolar_px, guess_source, status; attrs n_features, order
    /frames/<index>        one group per state, zero-padded ("000000" = the reference shape)
        attrs: index, left_path, right_path, complete, written, seconds, grid_shape,
               frame_name, R_frame_left, t_frame_left
        datasets: every per-point array of the Field3D (points, X ... W, exx, eyy, exy, normal,
                  zncc_*, epipolar_*, reprojection_*, status, strain_valid) and its details
                  (match_status, track_left_status, ..., params_left, params_right, ...)

A state is written into ``/frames/<index>.partial`` and renamed when whole; the file is flushed
after every state.
"""
from __future__ import annotations

import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .field3d import Field3D
from .stereo import StereoCorrelation, StereoMatch
from .store import _now, _specula_version

__all__ = ["stereo_sequence", "read_stereo", "read_field", "StereoResults", "FORMAT_NAME", "SCHEMA_VERSION"]

FORMAT_NAME = "specula-stereo"
SCHEMA_VERSION = 1
_MATCH_KEYS = ("points_left", "points_right", "params", "zncc", "iterations", "icgn_status", "epipolar_px",
               "guess_source", "status")




def _digest(image: np.ndarray) -> str:
    import hashlib

    arr = np.ascontiguousarray(image, dtype=np.float32)
    h = hashlib.sha256()
    h.update(str(arr.shape).encode())
    h.update(arr.tobytes())
    return h.hexdigest()


def _load(item, what: str) -> tuple[np.ndarray, str]:
    """An image given as an array or a file path -> (array, path or '')."""
    if isinstance(item, (str, os.PathLike)):
        from .io import read_image

        return read_image(item), os.fspath(item)
    if item is None:
        raise ValueError(f"{what} is missing")
    return np.asarray(item), ""


def _settings_json(settings: dict) -> str:
    return json.dumps(settings, sort_keys=True, default=lambda o: np.asarray(o).tolist())


def _frame_name(index: int) -> str:
    return f"{int(index):06d}"


# ------------------------------------------------------------------------------------------------
# writing


def _write_field(h5, index: int, f: Field3D, *, left_path: str, right_path: str, seconds: float) -> None:
    frames = h5.require_group("frames")
    name = _frame_name(index)
    partial = name + ".partial"
    if partial in frames:
        del frames[partial]
    g = frames.create_group(partial)
    for key, arr in f.arrays().items():
        arr = np.asarray(arr)
        if arr.dtype == bool or arr.size < 64:
            g.create_dataset(key, data=arr)
        else:
            g.create_dataset(key, data=arr, compression="gzip", compression_opts=4, shuffle=True)
    g.attrs.update({"index": int(index), "left_path": left_path, "right_path": right_path, "seconds": float(seconds),
                    "written": _now(), "grid_shape": list(f.grid_shape) if f.grid_shape is not None else [],
                    "frame_name": f.frame_name, "R_frame_left": np.asarray(f.R_frame_left),
                    "t_frame_left": np.asarray(f.t_frame_left), "complete": 0})
    if name in frames:
        del frames[name]
    frames.move(partial, name)
    frames[name].attrs["complete"] = 1
    h5.attrs["updated"] = _now()
    h5.flush()


def _done_frames(h5) -> list[int]:
    if "frames" not in h5:
        return []
    return sorted(int(k) for k, g in h5["frames"].items() if not k.endswith(".partial") and g.attrs.get("complete", 0) == 1)


def _read_match(h5) -> StereoMatch:
    g = h5["reference/match"]
    arrays = {k: g[k][()] for k in _MATCH_KEYS}
    return StereoMatch(**arrays, n_features=int(g.attrs.get("n_features", 0)), order=int(g.attrs.get("order", 2)))


def _open_output(path: Path, *, rig, settings: dict, shape, digests, paths, mode: str):
    import h5py

    if mode not in ("resume", "overwrite"):
        raise ValueError(f"mode must be 'resume' or 'overwrite', got {mode!r}")
    if path.suffix.lower() not in (".h5", ".hdf5"):
        raise ValueError(f"the output must be an HDF5 file ending in .h5, got {path.name}")
    if path.exists() and mode == "resume":
        try:
            h5 = h5py.File(path, "r+")
        except OSError as exc:
            raise ValueError(f"{path} exists but cannot be opened as HDF5 ({exc}); delete it or pass overwrite") from None
        try:
            fmt = h5.attrs.get("format")
            if fmt != FORMAT_NAME:
                raise ValueError(f"{path} is not a Specula stereo result file (format {fmt!r}); choose another output "
                                 "or overwrite it")
            if int(h5.attrs.get("schema_version", -1)) != SCHEMA_VERSION:
                raise ValueError(f"{path} has schema version {h5.attrs.get('schema_version')!r}, this Specula writes "
                                 f"version {SCHEMA_VERSION}; choose another output or overwrite it")
            old = json.loads(h5["settings"].attrs["json"])
            new = json.loads(_settings_json(settings))
            if old != new:
                diff = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
                raise ValueError(f"{path} holds results computed with other settings ({', '.join(diff)}); "
                                 "choose another output or overwrite it")
            ref = h5["reference"].attrs
            if tuple(ref["shape"]) != tuple(shape) or (ref["left_sha256"], ref["right_sha256"]) != digests:
                raise ValueError(f"{path} holds results for another reference image pair; choose another output "
                                 "or overwrite it")
            old_rig = json.loads(h5["rig"].attrs["json"])
            if old_rig != json.loads(json.dumps(rig.to_dict())):
                raise ValueError(f"{path} holds results computed with another rig; choose another output or overwrite it")
        except Exception:
            h5.close()
            raise
        return h5
    path.parent.mkdir(parents=True, exist_ok=True)
    h5 = h5py.File(path, "w")
    h5.attrs.update({"format": FORMAT_NAME, "schema_version": SCHEMA_VERSION, "specula_version": _specula_version(),
                     "created": _now(), "updated": _now()})
    h5.create_group("rig").attrs["json"] = json.dumps(rig.to_dict())
    h5.create_group("settings").attrs["json"] = _settings_json(settings)
    ref = h5.create_group("reference")
    ref.attrs.update({"left_path": paths[0], "right_path": paths[1], "shape": list(shape),
                      "left_sha256": digests[0], "right_sha256": digests[1]})
    h5.flush()
    return h5


@dataclass
class StereoResults:
    """A stereo result file read back (:func:`read_stereo`).

    ``fields`` maps state index -> :class:`Field3D` (0 = the reference shape); ``match`` is the
    reference :class:`StereoMatch`; ``rig`` the :class:`calibration.stereo.StereoRig`;
    ``settings`` the correlation settings; ``paths`` maps index -> (left, right) file names.
    """

    fields: dict
    match: StereoMatch | None
    rig: object
    settings: dict
    paths: dict = field(default_factory=dict)
    reference_shape: tuple = ()

    @property
    def indices(self) -> list[int]:
        return sorted(self.fields)


def stereo_sequence(rig, pairs: Sequence, out, *, mode: str = "resume", progress: bool = False,
                    callback: Callable[[Field3D], None] | None = None, **options) -> list[Field3D]:
    """Stereo DIC of an image-pair sequence, written state by state to an HDF5 file.

    Parameters
    ----------
    rig : calibration.stereo.StereoRig
    pairs : sequence of (left, right)
        Images (arrays or file paths: TIFF, PNG, BMP). ``pairs[0]`` is the reference state;
        state ``k`` is ``pairs[k]``. Each state is tracked from the reference with the previous
        state's parameters as initial guess (the reference match is done once).
    out : str or Path
        The ``.h5`` file (layout in the module docstring). An existing file with the same rig,
        reference images and settings is resumed (finished states are skipped) unless
        ``mode="overwrite"``; an incompatible one raises ``ValueError``.
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
    settings = {k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in sorted(options.items())}
    h5 = _open_output(out, rig=rig, settings=settings, shape=np.shape(left_ref),
                      digests=(_digest(left_ref), _digest(right_ref)), paths=(lp, rp), mode=mode)
    results = []
    try:
        match = _read_match(h5) if "reference/match" in h5 else None
        t0 = time.perf_counter()
        sc = StereoCorrelation(rig, left_ref, right_ref, match=match, device=device, **options)
        if match is None:
            g = h5.require_group("reference").create_group("match")
            for k, v in sc.match.arrays().items():
                g.create_dataset(k, data=v)
            g.attrs.update({"n_features": sc.match.n_features, "order": sc.match.order})
            h5.flush()
        done = set(_done_frames(h5))
        if 0 not in done:
            _write_field(h5, 0, sc.reference, left_path=lp, right_path=rp, seconds=time.perf_counter() - t0)
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
                if sc._previous is None and prev is not None:
                    grp = h5["frames"][_frame_name(prev)]
                    imgs = (_load(pairs[prev][0], "left image")[0], _load(pairs[prev][1], "right image")[0]) \
                        if prev < len(pairs) else None
                    sc.set_previous(grp["params_left"][()], grp["params_right"][()], images=imgs)
                t1 = time.perf_counter()
                try:
                    f = sc.measure(L, R, index=k)
                except ValueError as exc:
                    raise ValueError(f"pair {k} ({lpath or 'array'}, {rpath or 'array'}): {exc}") from None
                _write_field(h5, k, f, left_path=lpath, right_path=rpath, seconds=time.perf_counter() - t1)
                done.add(k)
                results.append(f)
                if callback:
                    callback(f)
                bar.update(1)
    finally:
        h5.close()
    return results


# ------------------------------------------------------------------------------------------------
# reading

_FIELD_KEYS = ("points", "X", "Y", "Z", "U", "V", "W", "exx", "eyy", "exy", "normal", "zncc_stereo", "zncc_left",
               "zncc_right", "epipolar_ref_px", "epipolar_px", "reprojection_ref_px", "reprojection_px", "status",
               "strain_valid")


def _read_field_group(g) -> Field3D:
    arrays = {k: g[k][()] for k in _FIELD_KEYS}
    details = {k: g[k][()] for k in g.keys() if k not in _FIELD_KEYS}
    gs = [int(v) for v in g.attrs.get("grid_shape", [])]
    return Field3D(**arrays, grid_shape=tuple(gs) if gs else None, R_frame_left=np.asarray(g.attrs["R_frame_left"]),
                   t_frame_left=np.asarray(g.attrs["t_frame_left"]), frame_name=str(g.attrs["frame_name"]),
                   index=int(g.attrs["index"]), details=details)


def _open_read(path):
    import h5py

    path = Path(os.fspath(path))
    if not path.exists():
        raise ValueError(f"result file not found: {path}")
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        raise ValueError(f"{path} is not a readable HDF5 file ({exc})") from None
    fmt = h5.attrs.get("format")
    if fmt != FORMAT_NAME:
        h5.close()
        raise ValueError(f"{path} is not a Specula stereo result file (format {fmt!r})")
    if int(h5.attrs.get("schema_version", -1)) != SCHEMA_VERSION:
        v = h5.attrs.get("schema_version")
        h5.close()
        raise ValueError(f"{path} has schema version {v!r}; this Specula reads version {SCHEMA_VERSION}")
    return h5


def read_field(path, index: int) -> Field3D:
    """One state of a stereo result file as a :class:`Field3D` (``ValueError`` if it is not there)."""
    with _open_read(path) as h5:
        name = _frame_name(index)
        if "frames" not in h5 or name not in h5["frames"] or h5["frames"][name].attrs.get("complete", 0) != 1:
            raise ValueError(f"{path} has no finished state {index}; finished: {_done_frames(h5)}")
        return _read_field_group(h5["frames"][name])


def read_stereo(path) -> StereoResults:
    """Read every finished state of a stereo result file (see the module docstring)."""
    from calibration.stereo import StereoRig

    with _open_read(path) as h5:
        fields = {}
        paths = {}
        for i in _done_frames(h5):
            g = h5["frames"][_frame_name(i)]
            fields[i] = _read_field_group(g)
            paths[i] = (str(g.attrs.get("left_path", "")), str(g.attrs.get("right_path", "")))
        match = _read_match(h5) if "reference/match" in h5 else None
        rig = StereoRig.from_dict(json.loads(h5["rig"].attrs["json"]))
        settings = json.loads(h5["settings"].attrs["json"])
        shape = tuple(int(v) for v in h5["reference"].attrs["shape"])
    return StereoResults(fields, match, rig, settings, paths, shape)
