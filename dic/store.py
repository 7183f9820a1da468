"""HDF5 result files for 2-D DIC runs, written frame by frame so that a run can resume.

The layout is documented in docs/results_format.md. In short::

    /                     attrs: format="specula-dic2d", schema_version, specula_version, created, updated
    /reference            attrs: path, shape (H, W), sha256 (of the float32 grey levels)
    /settings             attrs: json (the tracking settings, a JSON object)
    /frames/<index>       one group per current image, named by its zero-padded index ("000001")
        attrs: index, path, complete (1 once every dataset is written), written (ISO time)
        points (N, 2) f8, u (N,), v (N,), params (N, 6|12), zncc (N,), iterations (N,),
        status (N,) i1, valid (N,) bool
        strain/           optional: dudx, dudy, dvdx, dvdy, exx, eyy, exy, Exx, Eyy, Exy (N,) f8,
                          valid (N,) bool, attrs window, step

A frame is written into ``/frames/<index>.partial``, renamed to ``/frames/<index>`` and marked
``complete`` only when it is whole; the file is flushed after every frame. An interrupted run
therefore keeps every finished frame, and a rerun with the same output and settings skips them
(:meth:`ResultWriter.is_done`) and drops leftovers of the frame that was cut short.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from kernels.checks import non_negative_int

__all__ = ["ResultWriter", "read_results", "TrackResults", "FrameResult", "SCHEMA_VERSION", "FORMAT_NAME",
           "image_digest"]

FORMAT_NAME = "specula-dic2d"
SCHEMA_VERSION = 1
_FIELD_DATASETS = ("points", "u", "v", "params", "zncc", "iterations", "status", "valid")
_STRAIN_DATASETS = ("dudx", "dudy", "dvdx", "dvdy", "exx", "eyy", "exy", "Exx", "Eyy", "Exy", "valid")


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _specula_version() -> str:
    try:
        from importlib.metadata import version

        return version("specula")
    except Exception:  # pragma: no cover - not installed
        return "unknown"


def image_digest(image) -> str:
    """SHA-256 of an image's grey levels as C-contiguous float32 (identifies a reference image)."""
    arr = np.ascontiguousarray(np.asarray(image), dtype=np.float32)
    h = hashlib.sha256()
    h.update(str(arr.shape).encode())
    h.update(arr.tobytes())
    return h.hexdigest()


def _frame_name(index: int) -> str:
    return f"{int(index):06d}"


def _canonical(settings) -> str:
    try:
        return json.dumps(settings if settings is not None else {}, sort_keys=True, default=str)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"settings must be JSON-serialisable: {exc}") from None


class ResultWriter:
    """Write (or resume) a 2-D DIC result file, one frame at a time.

    Parameters
    ----------
    path : str or Path
        The ``.h5`` file.
    reference_path : str
        Where the reference image came from (recorded only).
    reference_shape : (H, W)
    reference_sha256 : str, optional
        :func:`image_digest` of the reference; a resumed file must match it.
    settings : dict
        Tracking settings (subset, step, order, ...), stored as JSON; a resumed file must match.
    mode : "resume" | "overwrite" | "new"
        ``resume`` (default) opens an existing compatible file and keeps its complete frames;
        ``overwrite`` starts afresh; ``new`` refuses an existing file.

    Use as a context manager; :meth:`write_frame` flushes the file after each frame.
    """

    def __init__(self, path, *, reference_path: str = "", reference_shape=None, reference_sha256: str = "",
                 settings: dict | None = None, mode: str = "resume"):
        import h5py

        if mode not in ("resume", "overwrite", "new"):
            raise ValueError(f"mode must be 'resume', 'overwrite' or 'new', got {mode!r}")
        self.path = Path(os.fspath(path))
        self._settings_json = _canonical(settings)
        shape = tuple(int(n) for n in reference_shape) if reference_shape is not None else ()
        exists = self.path.exists()
        if exists and mode == "new":
            raise ValueError(f"result file {self.path} already exists; choose another output or allow overwriting")
        if exists and mode == "resume":
            try:
                self._h5 = h5py.File(self.path, "a")
            except OSError as exc:
                raise ValueError(
                    f"cannot open the existing result file {self.path} to resume ({exc}); it may be corrupt: "
                    "delete it or write to another file") from None
            try:
                self._check_compatible(reference_sha256, shape)
            except ValueError:
                self._h5.close()
                raise
            for name in list(self._h5["frames"].keys()):  # leftovers of an interrupted frame
                if name.endswith(".partial") or not self._h5["frames"][name].attrs.get("complete", 0):
                    del self._h5["frames"][name]
            self._h5.attrs["updated"] = _now()
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._h5 = h5py.File(self.path, "w")
            f = self._h5
            f.attrs["format"] = FORMAT_NAME
            f.attrs["schema_version"] = SCHEMA_VERSION
            f.attrs["specula_version"] = _specula_version()
            f.attrs["created"] = _now()
            f.attrs["updated"] = f.attrs["created"]
            ref = f.create_group("reference")
            ref.attrs["path"] = str(reference_path)
            ref.attrs["shape"] = np.asarray(shape, dtype=np.int64)
            ref.attrs["sha256"] = str(reference_sha256)
            f.create_group("settings").attrs["json"] = self._settings_json
            f.create_group("frames")
        self._h5.flush()

    def _check_compatible(self, sha, shape):
        f = self._h5
        if f.attrs.get("format") != FORMAT_NAME or "frames" not in f:
            raise ValueError(f"{self.path} is not a Specula 2-D DIC result file; write to another file")
        version = int(f.attrs.get("schema_version", -1))
        if version != SCHEMA_VERSION:
            raise ValueError(
                f"{self.path} uses result schema version {version}, this Specula writes version {SCHEMA_VERSION}; "
                "write to another file")
        stored = f["reference"].attrs
        if sha and stored.get("sha256", "") and stored["sha256"] != sha:
            raise ValueError(
                f"{self.path} holds results for a different reference image ({stored.get('path', '?')}); "
                "write to another file or overwrite it")
        if shape and tuple(stored.get("shape", ())) != shape:
            raise ValueError(f"{self.path} holds results for a reference of shape {tuple(stored['shape'])}, not {shape}")
        old = f["settings"].attrs.get("json", "{}")
        if old != self._settings_json:
            raise ValueError(
                f"{self.path} was written with different settings ({old}); resuming needs the same settings "
                f"({self._settings_json}). Write to another file or overwrite it")

    # -- context manager
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        if getattr(self, "_h5", None) is not None and self._h5.id.valid:
            self._h5.flush()
            self._h5.close()

    # -- frames
    def done_frames(self) -> list[int]:
        """Indices of the complete frames in the file."""
        g = self._h5["frames"]
        return sorted(int(g[n].attrs["index"]) for n in g if g[n].attrs.get("complete", 0))

    def is_done(self, index: int) -> bool:
        """True when frame ``index`` is already complete in the file."""
        g = self._h5["frames"]
        name = _frame_name(index)
        return name in g and bool(g[name].attrs.get("complete", 0))

    def write_frame(self, index: int, field2d, *, strain=None, path: str = "", attrs: dict | None = None) -> None:
        """Write one frame's displacement field (and optional strain), then flush.

        ``field2d`` has ``points``, ``u``, ``v`` and optionally ``params``, ``zncc``, ``iterations``,
        ``status``, ``valid`` (a :class:`dic.track.Field2D`); ``strain`` is a
        :class:`dic.strain.StrainField` or None.
        """
        index = non_negative_int(index, "frame index")
        frames = self._h5["frames"]
        name = _frame_name(index)
        if name in frames:
            del frames[name]
        tmp = name + ".partial"
        if tmp in frames:
            del frames[tmp]
        g = frames.create_group(tmp)
        n = None
        for key in _FIELD_DATASETS:
            val = getattr(field2d, key, None)
            if val is None:
                if key in ("points", "u", "v"):
                    raise ValueError(f"the field has no {key!r}; write_frame needs points, u and v")
                continue
            arr = np.asarray(val)
            if key == "status":
                arr = arr.astype(np.int8)
            elif key == "valid":
                arr = arr.astype(bool)
            n = arr.shape[0] if n is None else n
            if arr.shape[0] != n:
                del frames[tmp]
                raise ValueError(f"field arrays disagree in length: {key} has {arr.shape[0]}, expected {n}")
            g.create_dataset(key, data=arr, compression="gzip", compression_opts=4, shuffle=True)
        if strain is not None:
            sg = g.create_group("strain")
            for key in _STRAIN_DATASETS:
                sg.create_dataset(key, data=np.asarray(getattr(strain, key)), compression="gzip",
                                  compression_opts=4, shuffle=True)
            sg.attrs["window"] = int(strain.window)
            sg.attrs["step"] = np.asarray(strain.step, dtype=np.float64)
        g.attrs["index"] = int(index)
        g.attrs["path"] = str(path)
        g.attrs["written"] = _now()
        for k, v in (attrs or {}).items():
            g.attrs[k] = v
        frames.move(tmp, name)
        frames[name].attrs["complete"] = 1
        self._h5.attrs["updated"] = _now()
        self._h5.flush()


@dataclass
class FrameResult:
    """One frame of a result file (arrays aligned with ``points``)."""

    index: int
    path: str
    points: np.ndarray
    u: np.ndarray
    v: np.ndarray
    params: np.ndarray | None = None
    zncc: np.ndarray | None = None
    iterations: np.ndarray | None = None
    status: np.ndarray | None = None
    valid: np.ndarray | None = None
    strain: dict | None = None
    attrs: dict = field(default_factory=dict)


@dataclass
class TrackResults:
    """Contents of a 2-D DIC result file."""

    path: Path
    attrs: dict
    reference: dict
    settings: dict
    frames: dict[int, FrameResult]


def read_results(path) -> TrackResults:
    """Read a result file written by :class:`ResultWriter` (complete frames only)."""
    import h5py

    p = Path(os.fspath(path))
    if not p.exists():
        raise ValueError(f"result file not found: {p}")
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise ValueError(f"cannot open result file {p}: {exc}") from None
    with f:
        if f.attrs.get("format") != FORMAT_NAME:
            raise ValueError(f"{p} is not a Specula 2-D DIC result file")
        version = int(f.attrs.get("schema_version", -1))
        if version > SCHEMA_VERSION:
            raise ValueError(f"{p} uses result schema version {version}; this Specula reads up to {SCHEMA_VERSION}")
        attrs = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in f.attrs.items()}
        ref = f["reference"].attrs
        reference = {"path": str(ref.get("path", "")), "shape": tuple(int(n) for n in ref.get("shape", ())),
                     "sha256": str(ref.get("sha256", ""))}
        settings = json.loads(f["settings"].attrs.get("json", "{}"))
        frames = {}
        for name, g in f["frames"].items():
            if not g.attrs.get("complete", 0):
                continue
            data = {k: g[k][()] for k in _FIELD_DATASETS if k in g}
            strain = None
            if "strain" in g:
                strain = {k: g["strain"][k][()] for k in g["strain"]}
                strain["window"] = int(g["strain"].attrs["window"])
                strain["step"] = tuple(g["strain"].attrs["step"])
            index = int(g.attrs["index"])
            extra = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in g.attrs.items()
                     if k not in ("index", "path")}
            frames[index] = FrameResult(index=index, path=str(g.attrs.get("path", "")), strain=strain,
                                        attrs=extra, **data)
    return TrackResults(path=p, attrs=attrs, reference=reference, settings=settings,
                        frames=dict(sorted(frames.items())))
