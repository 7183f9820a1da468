"""One writer and one reader for every Specula result file (2-D DIC and stereo DIC).

Both kinds share one root layout (docs/results_format.md)::

    /                     attrs: format ("specula-dic2d" | "specula-stereo"), schema_version,
                                 specula_version, created, updated, compression ("none", "lzf",
                                 "gzip:N"; absent in files written before it: gzip level 4)
    /reference            attrs: shape (H, W) and, per reference image, its path and sha256
                          (2-D: path, sha256; stereo: left_path, left_sha256, right_path, right_sha256)
    /settings             attrs: json (the run's settings, a JSON object)
    /rig                  stereo only: attrs json (the StereoRig file content)
    /frames/<index>       one group per frame (state), zero-padded ("000001")
        attrs: index, path (2-D) or left_path/right_path (stereo), complete, written, and the
               caller's extras (seconds); datasets: the kind's payload (dic.store.dic2d, dic.store.stereo)

The frame protocol is the same for both: a frame is written into ``/frames/<index>.partial``,
renamed to ``/frames/<index>`` and marked ``complete`` only when it is whole; the file is
flushed and fsynced after every frame. An interrupted run therefore keeps every finished frame,
and a rerun with the same output, reference image(s), settings (and rig) skips them
(:meth:`ResultWriter.is_done`; :meth:`ResultWriter.check_frame` refuses a frame whose image
differs) and drops leftovers of the frame that was cut short. The lock, the temporary file of a
new run and the space reservation that keeps a full disk from corrupting a file are
:mod:`dic.store.files`.
"""
from __future__ import annotations

import errno
import json
import os
import warnings
from pathlib import Path

import numpy as np

from . import dic2d, files, stereo
from .layout import (
    LEGACY_COMPRESSION,
    SCHEMA_VERSION,
    Compression,
    StoreKind,
    frame_name,
    now,
    parse_compression,
    plain,
    role_attr,
    settings_json,
    specula_version,
)

__all__ = ["ResultWriter", "ResultReader", "ResultFrames", "KINDS", "read_results", "read_stereo", "read_field",
           "repair_results", "ResultFileInUse", "ResultWriteError", "ResultFileDamaged"]

ResultFileInUse = files.ResultFileInUse
ResultWriteError = files.ResultWriteError
ResultFileDamaged = files.ResultFileDamaged
#: what h5py's errors say when a dataset's Fletcher-32 checksum (or another filter) fails on read
_CHECKSUM_WORDS = ("fletcher32", "checksum", "filter returned failure")
#: the exceptions h5py and the payload readers raise on a damaged or foreign frame
_READ_ERRORS = (OSError, KeyError, TypeError, ValueError, RuntimeError, AttributeError, IndexError)

KINDS: dict[str, StoreKind] = {dic2d.KIND.name: dic2d.KIND, stereo.KIND.name: stereo.KIND}
_BY_FORMAT = {k.format: k for k in KINDS.values()}
_MODES = ("resume", "overwrite", "new")
#: how a refusal to resume says to start afresh, for the CLI and for Python
_START_AFRESH = "start afresh with --overwrite (mode='overwrite' in Python)"
_RESERVE_MARGIN = 1 << 20  # bytes reserved beyond a frame's arrays: its metadata, the groups' growth
_METADATA_CACHE = 4 << 20  # bytes: HDF5's metadata cache of a file being written (its default grows to 32 MiB)


def _kind(kind) -> StoreKind:
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {sorted(KINDS)}, got {kind!r}")
    return KINDS[kind]


def _per_image(kind: StoreKind, value, what: str) -> tuple[str, ...]:
    """A path or digest given for each reference/current image of ``kind``: one text, or one per image."""
    roles = kind.image_roles
    if len(roles) == 1:
        if isinstance(value, (tuple, list)):
            raise ValueError(f"a {kind.label} file has one image per frame; {what} must be a single text, got {value!r}")
        return (os.fspath(value) if isinstance(value, os.PathLike) else str(value),)
    if isinstance(value, (str, os.PathLike)) and not value:
        return ("",) * len(roles)
    if not isinstance(value, (tuple, list)) or len(value) != len(roles):
        raise ValueError(f"a {kind.label} file has {len(roles)} images per frame ({', '.join(roles)}); "
                         f"{what} must be a ({', '.join(roles)}) pair, got {value!r}")
    return tuple(os.fspath(v) if isinstance(v, os.PathLike) else str(v) for v in value)


def _is_group(obj) -> bool:
    import h5py

    return isinstance(obj, h5py.Group)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().split("\n")[0].strip(" '\"")
    return text or type(exc).__name__


def _header_damage(path, what: str) -> files.ResultFileDamaged:
    return files.ResultFileDamaged(f"{path} is damaged or not a Specula result file: {what}; recompute it, or restore "
                                   "it from a copy")


def _check_header(h5, path, kind: StoreKind) -> None:
    """Refuse, with one :class:`ResultFileDamaged` line, a file whose header is not the store's layout: a
    missing ``/reference`` or ``/settings`` (a header-only or cut file), one of them or ``/frames``
    stored as a dataset, settings that are not a JSON object, a stereo file without its rig."""
    try:
        for name in ("reference", "settings") + (("rig",) if kind.needs_rig else ()):
            if name not in h5:
                raise _header_damage(path, f"it has no '/{name}' group (a header-only or cut file?)")
            if not _is_group(h5[name]):
                raise _header_damage(path, f"'/{name}' is a dataset, not a group")
        if "frames" in h5 and not _is_group(h5["frames"]):
            raise _header_damage(path, "'/frames' is a dataset, not a group")
        for name in ("settings",) + (("rig",) if kind.needs_rig else ()):
            text = h5[name].attrs.get("json", "{}")
            if not isinstance(json.loads(plain(text)), dict):
                raise _header_damage(path, f"'/{name}' holds no JSON object")
    except files.ResultFileDamaged:
        raise
    except _READ_ERRORS as exc:  # unreadable metadata, JSON that does not parse
        raise _header_damage(path, f"its header does not read ({_first_line(exc)})") from None


def _damage_reason(group, exc: BaseException | None = None) -> str:
    """Why a frame's group does not read: the first dataset whose data fail (a checksum mismatch, named as
    such), else the reader's error (a missing dataset or attribute)."""
    import h5py

    failed = []

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset) and not failed:
            try:
                obj[()]
            except Exception as err:  # noqa: BLE001 - any read failure is the damage to report
                failed.append((name, err))
    try:
        group.visititems(visit)
    except Exception as err:  # noqa: BLE001 - the group's own metadata are damaged
        return f"does not read ({_first_line(err)})"
    if failed:
        name, err = failed[0]
        if any(w in str(err).lower() for w in _CHECKSUM_WORDS):
            return f"fails its checksum in dataset '{name}' (a flipped bit or a damaged block)"
        return f"cannot read its dataset '{name}' ({_first_line(err)})"
    return _first_line(exc) if exc is not None else ""


def _frame_problem(kind: StoreKind, name: str, obj) -> str:
    """What is wrong with a complete frame's group ("" when it reads whole, every checksum verified)."""
    if not _is_group(obj):
        return "is a dataset, not a group"
    index = obj.attrs.get("index")
    try:
        if index is None or int(index) < 0:
            return "has no 'index' attribute"
    except (TypeError, ValueError):
        return f"has an 'index' attribute that is no frame index ({index!r})"
    reason = _damage_reason(obj)
    if reason:
        return reason
    try:
        kind.read_payload(obj)
    except _READ_ERRORS as exc:
        return _first_line(exc)
    return ""


def _rig_dict(rig) -> dict:
    if isinstance(rig, dict):
        return rig
    if not hasattr(rig, "to_dict"):
        raise ValueError(f"rig must be a calibration.stereo.StereoRig (or its dict), got {type(rig).__name__}")
    return rig.to_dict()


class _ResultFile:
    """What the writer and the reader share: the open h5py file, its kind and its frames."""

    _h5 = None
    path: Path
    kind: StoreKind

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        """Flush (when writable) and close the file; closing twice is harmless."""
        if self._h5 is not None and self._h5.id.valid:
            if self._h5.mode != "r":
                self._h5.flush()
            self._h5.close()

    # -- header
    @property
    def attrs(self) -> dict:
        """The root attributes (format, schema_version, specula_version, created, updated)."""
        return {k: plain(v) for k, v in self._h5.attrs.items()}

    @property
    def reference(self) -> dict:
        """``shape`` (H, W) and each reference image's path and sha256 (2-D: ``path``, ``sha256``;
        stereo: ``left_path``, ``left_sha256``, ``right_path``, ``right_sha256``)."""
        ref = self._h5["reference"].attrs
        out = {}
        for role in self.kind.image_roles:
            out[role_attr(role, "path")] = str(ref.get(role_attr(role, "path"), ""))
        out["shape"] = tuple(int(n) for n in ref.get("shape", ()))
        for role in self.kind.image_roles:
            out[role_attr(role, "sha256")] = str(ref.get(role_attr(role, "sha256"), ""))
        return out

    @property
    def settings(self) -> dict:
        return json.loads(self._h5["settings"].attrs.get("json", "{}"))

    @property
    def compression(self) -> Compression:
        """The file's compression setting (root attribute ``compression``; files written before it
        existed: gzip level 4) with its checksum setting (root attribute ``checksum``: "none" turns
        checksums off; absent in files written before checksums: frames appended to them get them).
        Readers need it for nothing: HDF5 filters are self-describing."""
        text = self._h5.attrs.get("compression")
        try:
            comp = LEGACY_COMPRESSION if text is None else parse_compression(str(plain(text)))
        except ValueError:
            raise ValueError(f"{self.path} has an unknown compression setting {text!r}") from None
        checksum = str(plain(self._h5.attrs.get("checksum", "fletcher32"))) != "none"
        return Compression(comp.filter, comp.level, checksum)

    @property
    def rig(self) -> dict | None:
        """The stored rig (the StereoRig file content) or None (2-D files)."""
        return json.loads(self._h5["rig"].attrs["json"]) if "rig" in self._h5 else None

    # -- frames
    def _frames(self):
        if "frames" not in self._h5:
            return {}
        g = self._h5["frames"]
        if not _is_group(g):
            raise _header_damage(self.path, "'/frames' is a dataset, not a group")
        return g

    def _damaged(self, frame, reason: str) -> files.ResultFileDamaged:
        """The one message of a damaged frame: the file, the frame, what is wrong, what to do."""
        return files.ResultFileDamaged(
            f"{self.path} is damaged: {self.kind.frame_noun} {frame} {reason}; 'specula repair {self.path}' drops "
            "it (dic.store.repair_results), and rerunning the same command then recomputes it")

    def done_frames(self) -> list[int]:
        """Indices of the complete frames in the file, ascending (:class:`ResultFileDamaged` for a complete
        frame without its ``index``)."""
        g = self._frames()
        done = []
        for n in g:
            if n.endswith(".partial") or not g[n].attrs.get("complete", 0):
                continue
            index = g[n].attrs.get("index")
            try:
                done.append(int(index))
            except (TypeError, ValueError):
                raise self._damaged(repr(n), "has no 'index' attribute" if index is None else
                                    f"has an 'index' attribute that is no frame index ({index!r})") from None
        return sorted(done)

    def is_done(self, index: int) -> bool:
        """True when frame ``index`` is already complete in the file."""
        g = self._frames()
        name = frame_name(index)
        return name in g and bool(g[name].attrs.get("complete", 0))

    def _complete_group(self, index: int):
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0:
            raise ValueError(f"frame index must be a non-negative integer, got {index!r}")
        if not self.is_done(index):
            raise ValueError(f"{self.path} has no finished {self.kind.frame_noun} {index}; "
                             f"finished: {self.done_frames()}")
        return self._frames()[frame_name(index)]

    def read_frame(self, index: int):
        """A complete frame: :class:`dic.store.FrameResult` (2-D) or :class:`dic.field3d.Field3D` (stereo).

        Every dataset's checksum is verified as it is read (files with checksums); a frame that does not
        read (a checksum mismatch, a missing dataset) raises :class:`ResultFileDamaged` naming it."""
        g = self._complete_group(index)
        try:
            if not _is_group(g):
                raise ValueError("is a dataset, not a group")
            return self.kind.read_payload(g)
        except _READ_ERRORS as exc:
            raise self._damaged(index, _damage_reason(g, exc) if _is_group(g) else _first_line(exc)) from None

    def iter_frames(self, indices=None):
        """Yield ``(index, frame)`` for the complete frames (``indices``: those, in that order; default all,
        ascending), each read from the file when it is reached: a consumer that keeps none of them holds
        one frame at a time, whatever the file's length (a 10 000-frame file included)."""
        wanted = self.done_frames() if indices is None else [int(i) for i in indices]
        for index in wanted:
            yield index, self.read_frame(index)

    def frame_paths(self, index: int) -> tuple[str, ...]:
        """The image path(s) recorded for a complete frame: (path,) or (left, right)."""
        g = self._complete_group(index)
        return tuple(str(g.attrs.get(role_attr(r, "path"), "")) for r in self.kind.image_roles)

    def frame_attrs(self, index: int) -> dict:
        """The attributes of a complete frame (index, path(s), written, seconds, reference_index, ...)."""
        return {k: plain(v) for k, v in self._complete_group(index).attrs.items()}

    def frame_arrays(self, index: int, names) -> tuple | None:
        """Datasets ``names`` of a complete frame (e.g. the parameters to resume from), or None
        when the frame is not complete or lacks one of them."""
        if not self.is_done(index):
            return None
        g = self._frames()[frame_name(index)]
        if not _is_group(g) or any(n not in g for n in names):
            return None
        try:
            return tuple(g[n][()] for n in names)
        except _READ_ERRORS as exc:
            raise self._damaged(index, _damage_reason(g, exc)) from None

    def read_match(self):
        """The stored reference :class:`dic.StereoMatch` (stereo files), or None."""
        if "reference/match" not in self._h5:
            return None
        g = self._h5["reference/match"]
        try:
            return stereo.read_match(g)
        except _READ_ERRORS as exc:
            reason = _damage_reason(g, exc) if _is_group(g) else _first_line(exc)
            raise files.ResultFileDamaged(f"{self.path} is damaged: its reference match {reason}; recompute it "
                                          "(--overwrite), or restore it from a copy") from None


class ResultWriter(_ResultFile):
    """Write (or resume) a result file, one frame at a time: 2-D DIC or stereo DIC.

    Parameters
    ----------
    path : str or Path
        The ``.h5`` file.
    kind : "dic2d" | "stereo"
        ``dic2d`` (format ``specula-dic2d``): frames are :class:`dic.Field2D` (+ strain).
        ``stereo`` (format ``specula-stereo``): frames are :class:`dic.field3d.Field3D`, and the
        file also holds the rig and the reference match (:meth:`write_match`).
    reference_path : str, or (left, right) for stereo
        Where the reference image(s) came from (recorded only).
    reference_shape : (H, W) px
    reference_sha256 : str, or (left, right) for stereo, optional
        :func:`dic.store.image_digest` of the reference image(s); a resumed file must match.
    settings : dict
        The run's settings, stored as JSON; a resumed file must hold the same.
    settings_check : callable(stored settings dict) -> str or None, optional
        Compares a resumed file's settings instead of requiring the same JSON: None when they describe
        this run (e.g. :meth:`dic.sequence.options.TrackOptions.resume_check`, which reads every form
        of the run record), else the text of the refusal. The file keeps the settings it holds.
    rig : calibration.stereo.StereoRig or its dict
        Stereo only (required there); a resumed file must hold the same rig.
    mode : "resume" | "overwrite" | "new"
        ``resume`` (default) opens an existing compatible file and keeps its complete frames;
        ``overwrite`` starts afresh; ``new`` refuses an existing file.
    compression : "none" | "lzf" | "gzip" | "gzip:N", optional
        How a new file's datasets are compressed (:func:`dic.store.layout.parse_compression`; default
        :data:`dic.store.layout.DEFAULT_COMPRESSION`), recorded as the root attribute ``compression``.
        A resumed file keeps its own setting (frames appended to a gzip-4 file are gzip-4), whatever
        is given here: :attr:`compression` says which one is used. Every dataset also carries HDF5's
        Fletcher-32 checksum, verified on every read (a :class:`dic.store.layout.Compression` with
        ``checksum=False`` writes without; root attribute ``checksum``).

    The writer holds an exclusive lock (``<file>.lock``) while it is open: a second writer on the
    same file gets :class:`dic.store.ResultFileInUse`. A new run (a new file, or ``overwrite``) is
    written to ``<file>.tmp`` and renamed over ``<file>`` with its first frame (stereo: the
    reference match), so a run that fails before that leaves an existing file untouched.
    :meth:`write_frame` reserves the frame's space first, then flushes and fsyncs the file; a
    write that fails (a full disk) raises :class:`dic.store.ResultWriteError` and closes the
    writer, leaving every finished frame readable and resumable. :meth:`hold_outputs` holds the locks
    of a run's side folders (VTK, figures) with the file's. Use as a context manager.
    """

    def __init__(self, path, *, reference_path="", reference_shape=None, reference_sha256="",
                 settings: dict | None = None, mode: str = "resume", kind: str = "dic2d", rig=None,
                 compression=None, settings_check=None):
        import h5py

        self.kind = _kind(kind)
        self._compression = parse_compression(compression)
        if mode not in _MODES:
            raise ValueError(f"mode must be 'resume', 'overwrite' or 'new', got {mode!r}")
        self.path = Path(os.fspath(path))
        self._settings_json = settings_json(settings)
        self._settings_check = settings_check
        paths = _per_image(self.kind, reference_path, "reference_path")
        digests = _per_image(self.kind, reference_sha256, "reference_sha256")
        shape = tuple(int(n) for n in reference_shape) if reference_shape is not None else ()
        if self.kind.needs_rig and rig is None:
            raise ValueError(f"a {self.kind.label} result file needs the rig (rig=)")
        if not self.kind.needs_rig and rig is not None:
            raise ValueError(f"a {self.kind.label} result file has no rig; pass rig=None")
        rig_json = json.dumps(_rig_dict(rig)) if rig is not None else None
        self._tmp: Path | None = None  # the temporary file of a new run, until it is renamed into place
        self._warned_paths_only = False
        files.check_output_path(self.path)
        self._lock = files.FileLock(Path(os.path.abspath(self.path)))
        self._lock.acquire()  # before anything is opened, truncated or replaced
        try:
            self._open(h5py, mode, paths, digests, shape, rig_json)
        except BaseException:
            self._release()
            raise

    def _open(self, h5py, mode, paths, digests, shape, rig_json) -> None:
        tmp = files.temp_path(Path(os.path.abspath(self.path)))
        if tmp.exists():  # left by a run killed before its first frame (we hold the lock: nobody writes it)
            tmp.unlink()
        exists = self.path.exists()
        if exists and mode == "new":
            raise ValueError(f"result file {self.path} already exists; choose another output or allow overwriting")
        if exists and mode == "resume":
            try:
                self._h5 = h5py.File(self.path, "a")
            except OSError as exc:
                if files.is_lock_error(exc):
                    raise files.ResultFileInUse(
                        f"result file {self.path} is in use by another process (HDF5 could not lock it); wait for "
                        "that process to finish or close it, or write to another file") from None
                if files.os_errno(exc) in (errno.EACCES, errno.EPERM, errno.EROFS):
                    raise ValueError(f"cannot open the result file {self.path} for writing to resume: "
                                     f"{files.reason(exc)}") from None
                raise ValueError(
                    f"cannot open the existing result file {self.path} to resume ({exc}); it may be corrupt: "
                    "delete it or write to another file") from None
            try:
                self._check_compatible(paths, digests, shape, rig_json)
                self._compression = self.compression  # the file's own setting, kept for the frames added
                _bound_metadata_cache(self._h5)
            except BaseException:
                self._h5.close()
                raise
            try:
                frames = self._h5.require_group("frames")  # stereo files of v1 create it with the first state
                for name in list(frames.keys()):  # leftovers of an interrupted frame
                    if name.endswith(".partial") or not frames[name].attrs.get("complete", 0):
                        del frames[name]
                self._h5.attrs["updated"] = now()
                self._sync()
            except (OSError, RuntimeError) as exc:
                raise self._fail(exc, "the resumed file's header") from None
            return
        self._tmp = tmp
        try:
            self._h5 = h5py.File(tmp, "w")
            _bound_metadata_cache(self._h5)
            f = self._h5
            f.attrs["format"] = self.kind.format
            f.attrs["schema_version"] = SCHEMA_VERSION
            f.attrs["specula_version"] = specula_version()
            f.attrs["created"] = now()
            f.attrs["updated"] = f.attrs["created"]
            f.attrs["compression"] = self._compression.text
            f.attrs["checksum"] = self._compression.checksum_text
            if rig_json is not None:
                f.create_group("rig").attrs["json"] = rig_json
            ref = f.create_group("reference")
            for role, p in zip(self.kind.image_roles, paths):
                ref.attrs[role_attr(role, "path")] = p
            ref.attrs["shape"] = np.asarray(shape, dtype=np.int64)
            for role, d in zip(self.kind.image_roles, digests):
                ref.attrs[role_attr(role, "sha256")] = d
            f.create_group("settings").attrs["json"] = self._settings_json
            f.create_group("frames")
            self._sync()
        except (OSError, RuntimeError) as exc:
            raise self._fail(exc, "a new result file") from None

    # -- the file on disk
    def _fd(self) -> int | None:
        try:
            fd = self._h5.id.get_vfd_handle()
        except Exception:  # noqa: BLE001 - a driver without a file descriptor
            return None
        return fd if isinstance(fd, int) else None

    def _sync(self) -> None:
        """Flush HDF5's buffers and fsync the file: what is written now survives a crash or a power cut."""
        self._h5.flush()
        fd = self._fd()
        if fd is not None:
            os.fsync(fd)
        self._synced_size = int(self._h5.id.get_filesize())  # all the file needs as of now (>= HDF5's end)

    def _reserve(self, nbytes: int) -> None:
        fd = self._fd()
        if fd is not None:
            files.reserve(fd, int(self._h5.id.get_filesize()), int(nbytes * 1.25) + _RESERVE_MARGIN)

    def _commit(self) -> None:
        """Rename a new run's temporary file into place (once it holds its reference data)."""
        if self._tmp is not None:
            os.replace(self._tmp, self._tmp.with_name(self.path.name))
            files.fsync_folder(self._tmp.parent)
            self._tmp = None

    def _release(self) -> None:
        """Give up the lock; a new run that never reached :meth:`_commit` is discarded."""
        if self._h5 is not None and self._h5.id.valid:
            try:
                self._h5.close()
            except Exception:  # noqa: BLE001 - discarded anyway
                files.abandon(self._h5)
        if self._tmp is not None:
            try:
                self._tmp.unlink()
            except OSError:
                pass
            self._tmp = None
        if getattr(self, "_lock", None) is not None:
            self._lock.release()
        for lock in getattr(self, "_side_locks", ()):
            lock.release()
        self._side_locks = []

    def hold_outputs(self, *folders) -> None:
        """Take the locks of this run's side outputs (its VTK and figure folders; None is skipped), creating
        the folders, and hold them until the writer is closed: an export or another run writing into one
        of them meanwhile is refused (:func:`dic.store.files.output_lock`), and so is this call when
        another process holds one (:class:`ResultFileInUse`, the writer closed)."""
        held = {lock.target for lock in getattr(self, "_side_locks", ())}
        for folder in folders:
            if folder is None:
                continue
            target = Path(os.path.abspath(os.fspath(folder)))
            if target in held:  # one folder for VTK and figures: one lock
                continue
            held.add(target)
            try:
                target.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                self._release()
                raise ValueError(f"cannot write into the folder {folder}: {exc.strerror or exc}") from None
            lock = files.FileLock(target, "output folder")
            try:
                lock.acquire()
            except BaseException:
                self._release()
                raise
            self._side_locks = [*getattr(self, "_side_locks", ()), lock]

    def _fail(self, exc: BaseException, what: str) -> files.ResultWriteError:
        """After a failed write: close without writing anything more, and the message to raise."""
        done: list[int] = []
        try:
            done = self.done_frames()
        except Exception:  # noqa: BLE001 - only for the message
            pass
        new = self._tmp is not None
        if self._h5 is not None:
            files.abandon(self._h5)
            size = getattr(self, "_synced_size", None)
            if not new and size is not None:  # give the space of the frame that failed back to the disk
                try:
                    if self.path.stat().st_size > size:
                        os.truncate(self.path, size)
                except OSError:
                    pass
        self._release()
        noun = self.kind.frame_noun
        if new:
            kept = "Nothing was written" + (f"; the previous {self.path.name} is unchanged" if self.path.exists() else "")
        elif done:
            kept = (f"{self.path} keeps its {len(done)} finished {noun}{'s' if len(done) != 1 else ''} (last: {done[-1]}); "
                    "make room and rerun the same command to resume")
        else:
            kept = f"{self.path} is as it was; make room and rerun the same command to resume"
        return files.write_error(self.path, what, exc, kept)

    def _writable(self):
        if self._h5 is None or not self._h5.id.valid:
            raise ValueError(f"the result writer of {self.path} is closed")
        return self._h5

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        elif self._tmp is not None:  # a new run that failed before its first frame: keep any previous file
            self._release()
        else:
            try:
                self.close()
            except files.ResultWriteError:
                pass  # the error that ended the run is the one to report

    def close(self) -> None:
        """Flush, fsync and close the file, and release its lock; closing twice is harmless."""
        h5 = self._h5
        if h5 is not None and h5.id.valid:
            try:
                self._sync()
                fd, end = self._fd(), int(h5.id.get_filesize())
                if fd is not None and os.fstat(fd).st_size > end:  # the unused part of the last reservation
                    os.ftruncate(fd, end)
                h5.close()
                self._commit()
            except (OSError, RuntimeError) as exc:
                raise self._fail(exc, "the end of the run") from None
        self._release()

    def _check_compatible(self, paths, digests, shape, rig_json) -> None:
        f, kind = self._h5, self.kind
        fmt = f.attrs.get("format")
        if fmt != kind.format:
            raise ValueError(f"{self.path} is not a Specula {kind.label} result file (format {fmt!r}); "
                             f"write to another file or {_START_AFRESH}")
        version = int(f.attrs.get("schema_version", -1))
        if version != SCHEMA_VERSION:
            raise ValueError(
                f"{self.path} uses result schema version {version}, this Specula writes version {SCHEMA_VERSION}; "
                f"write to another file or {_START_AFRESH}")
        _check_header(f, self.path, kind)
        stored = f["reference"].attrs
        for role, d in zip(kind.image_roles, digests):
            old = str(stored.get(role_attr(role, "sha256"), ""))
            if d and old and old != d:
                were = ", ".join(str(stored.get(role_attr(r, "path"), "?")) for r in kind.image_roles)
                raise ValueError(f"{self.path} holds results for a different {kind.reference_noun} ({were}); "
                                 f"write to another file or {_START_AFRESH}")
        if shape and tuple(stored.get("shape", ())) != shape:
            raise ValueError(f"{self.path} holds results for a reference of shape {tuple(int(v) for v in stored['shape'])}, "
                             f"not {tuple(int(v) for v in shape)}; "
                             f"write to another file or {_START_AFRESH}")
        old_json = f["settings"].attrs.get("json", "{}")
        old, new = json.loads(old_json), json.loads(self._settings_json)
        if self._settings_check is not None:
            refusal = self._settings_check(old)
            if refusal is not None:
                raise ValueError(f"{self.path} was written with different settings: {refusal}")
        elif old != new:
            differ = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
            raise ValueError(
                f"{self.path} was written with different settings ({', '.join(differ)} differ; stored: {old_json}); "
                f"resuming needs the same settings ({self._settings_json}). Write to another file or {_START_AFRESH}")
        if rig_json is not None:
            if "rig" not in f or json.loads(f["rig"].attrs["json"]) != json.loads(rig_json):
                raise ValueError(f"{self.path} holds results computed with another rig; write to another file "
                                 f"or {_START_AFRESH}")

    # -- writing
    def write_frame(self, index: int, field, *, strain=None, path="", sha256="", attrs: dict | None = None) -> None:
        """Write one frame, mark it complete, then flush and fsync the file.

        ``field``: a :class:`dic.Field2D`-like object (``points``, ``u``, ``v`` and optionally
        ``params``, ``zncc``, ``iterations``, ``status``, ``valid``) for 2-D, with ``strain`` a
        :class:`dic.StrainField` or None; a :class:`dic.field3d.Field3D` for stereo.
        ``path``: the current image file (2-D) or (left, right) files (stereo). ``sha256``: the
        :func:`dic.store.image_digest` of that image (or pair), stored so that a resumed run can
        check it is given the same images (:meth:`check_frame`). ``attrs``: extra frame
        attributes (e.g. ``seconds``).

        Raises :class:`dic.store.ResultWriteError` (and closes the writer) when the file cannot
        be written, e.g. on a full disk; the frames finished before stay readable and resumable.
        """
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0:
            raise ValueError(f"frame index must be a non-negative integer, got {index!r}")
        paths = _per_image(self.kind, path, "path")
        digests = _per_image(self.kind, sha256, "sha256")
        frames = self._writable()["frames"]
        name = frame_name(index)
        tmp = name + ".partial"
        what = f"{self.kind.frame_noun} {index}"
        try:
            self._reserve(_nbytes(field) + _nbytes(strain))
            if name in frames:  # rewriting a finished frame: it is gone from the file first
                del frames[name]
                self._sync()
            if tmp in frames:
                del frames[tmp]
            g = frames.create_group(tmp)
            try:
                self.kind.write_payload(g, field, strain, self._compression)
            except (OSError, RuntimeError):
                raise
            except BaseException:  # a field the payload refuses (ValueError), Ctrl-C: the writer stays usable
                del frames[tmp]
                raise
            g.attrs["index"] = int(index)
            for role, p in zip(self.kind.image_roles, paths):
                g.attrs[role_attr(role, "path")] = p
            for role, d in zip(self.kind.image_roles, digests):
                if d:
                    g.attrs[role_attr(role, "sha256")] = d
            g.attrs["written"] = now()
            for k, v in (attrs or {}).items():
                g.attrs[k] = v
            frames.move(tmp, name)
            frames[name].attrs["complete"] = 1
            self._h5.attrs["updated"] = now()
            self._sync()
        except (OSError, RuntimeError) as exc:
            raise self._fail(exc, what) from None
        self._commit()

    def write_match(self, match) -> None:
        """Store the reference :class:`dic.StereoMatch` (stereo files, once), then flush and fsync."""
        if self.kind is not stereo.KIND:
            raise ValueError(f"a {self.kind.label} result file has no reference match")
        h5 = self._writable()
        if "reference/match" in h5:
            raise ValueError(f"{self.path} already holds a reference match")
        try:
            self._reserve(_nbytes(match))
            g = h5["reference"].create_group("match")
            try:
                stereo.write_match(g, match, self._compression)
            except (OSError, RuntimeError):
                raise
            except BaseException:
                del h5["reference/match"]
                raise
            self._sync()
        except (OSError, RuntimeError) as exc:
            raise self._fail(exc, "the reference match") from None
        self._commit()

    def check_frame(self, index: int, path="", sha256="") -> None:
        """Refuse to resume past a finished frame that was computed from other image(s).

        ``path`` and ``sha256`` are the image file(s) given for frame ``index`` now and their
        :func:`dic.store.image_digest` (a pair for stereo). Nothing is checked when the frame is
        not finished yet. When the frame and the caller both have digests, the digests decide (the
        same image under another path is accepted); a frame without digests (files of older
        Specula versions) is compared by path, and a warning says so once. Raises ValueError
        naming the frame and both paths.
        """
        if not self.is_done(index):
            return
        roles = self.kind.image_roles
        given = _per_image(self.kind, path, "path")
        given_d = _per_image(self.kind, sha256, "sha256")
        g = self._frames()[frame_name(index)]
        stored = tuple(str(g.attrs.get(role_attr(r, "path"), "")) for r in roles)
        stored_d = tuple(str(g.attrs.get(role_attr(r, "sha256"), "")) for r in roles)
        if all(stored_d) and all(given_d):
            same, how = stored_d == given_d, "the images differ"
        else:
            if not all(stored_d) and not self._warned_paths_only:
                self._warned_paths_only = True
                warnings.warn(f"{self.path} holds no image digests for its finished {self.kind.frame_noun}s (written "
                              "by an older Specula): resuming compares their image paths only", stacklevel=2)
            same, how = all(_same_path(a, b) for a, b in zip(stored, given)), "the image paths differ"
        if not same:
            raise ValueError(
                f"{self.path} holds {self.kind.frame_noun} {index} computed from {_show(stored)}, but this run gives "
                f"{_show(given)} for it ({how}); resume with the same images, write to another file, or start "
                "afresh (--overwrite, mode='overwrite')")


def _bound_metadata_cache(h5) -> None:
    """Cap HDF5's metadata cache of a file being written at 4 MiB: the objects of the frames written so
    far otherwise fill it up to 32 MiB over the first few hundred frames (measured with uncompressed
    datasets: +20 MB of RSS between frames 50 and 800), a growth with the sequence's length."""
    try:
        config = h5.id.get_mdc_config()
        config.set_initial_size = True
        config.initial_size = min(int(config.initial_size), _METADATA_CACHE)
        config.min_size = min(int(config.min_size), _METADATA_CACHE)
        config.max_size = _METADATA_CACHE
        h5.id.set_mdc_config(config)
    except (AttributeError, ValueError, RuntimeError):  # a driver or build without it: the default cache
        pass


def _same_path(a: str, b: str) -> bool:
    if a == b:
        return True
    try:
        return bool(a and b) and os.path.samefile(a, b)
    except OSError:
        return False


def _show(paths: tuple[str, ...]) -> str:
    shown = [p or "an array" for p in paths]
    return shown[0] if len(shown) == 1 else "(" + ", ".join(shown) + ")"


def _nbytes(obj) -> int:
    """Bytes of the arrays of a field, strain or match (the space a frame may need, uncompressed)."""
    if obj is None:
        return 0
    try:
        values = obj.arrays().values() if callable(getattr(obj, "arrays", None)) else vars(obj).values()
    except Exception:  # noqa: BLE001 - only an estimate; the payload writer checks the object
        return 0
    return sum(int(v.nbytes) for v in values if isinstance(v, np.ndarray))


class ResultReader(_ResultFile):
    """Open a result file read-only: ``kind`` "dic2d", "stereo", or None for whichever it is.

    Offers :attr:`attrs`, :attr:`reference`, :attr:`settings`, :attr:`rig`, :attr:`compression`,
    :meth:`done_frames`, :meth:`read_frame`, :meth:`iter_frames` (one frame in memory at a time), :meth:`frame_paths`, :meth:`frame_attrs`, :meth:`frame_arrays` and :meth:`read_match`;
    incomplete frames are invisible. Files of a newer schema version are refused. Use as a
    context manager.
    """

    def __init__(self, path, kind: str | None = None):
        import h5py

        wanted = _kind(kind) if kind is not None else None
        self.path = Path(os.fspath(path))
        if not self.path.exists():
            raise ValueError(f"result file not found: {self.path}")
        files.check_not_in_use(self.path)  # a run still writing it: refused before HDF5 opens it (any HDF5 locking)
        try:
            self._h5 = h5py.File(self.path, "r")
        except OSError as exc:
            if files.is_lock_error(exc):
                raise files.ResultFileInUse(
                    f"result file {self.path} is in use by another process (a run still writing it); read it when "
                    "that run has finished") from None
            raise ValueError(f"cannot open result file {self.path}: {exc}") from None
        try:
            fmt = self._h5.attrs.get("format")
            found = _BY_FORMAT.get(fmt)
            if found is None or (wanted is not None and found is not wanted):
                label = wanted.label + " " if wanted is not None else ""
                raise ValueError(f"{self.path} is not a Specula {label}result file (format {fmt!r})")
            self.kind = found
            version = int(self._h5.attrs.get("schema_version", -1))
            if version > SCHEMA_VERSION:
                raise ValueError(f"{self.path} uses result schema version {version}; this Specula reads up to "
                                 f"{SCHEMA_VERSION}")
            _check_header(self._h5, self.path, found)
        except Exception:
            self._h5.close()
            raise


    def __repr__(self) -> str:
        return _short_repr("ResultReader", self.path, self.kind.label, self._h5 is not None and bool(self._h5),
                           lambda: (self.done_frames(), self.settings))


# ------------------------------------------------------------------------------------------------
# the frames of a result, one at a time


class ResultFrames:
    """The finished frames of one result, 2-D or stereo, read one at a time: the one way the exports and
    the post-processing go through a whole result (memory independent of the number of frames).

    ``source``: a result file (path; opened read-only until :meth:`close`), or a
    :class:`~dic.store.TrackResults` / :class:`~dic.store.StereoResults` already in memory. Offers
    :attr:`kind` (``"dic2d"`` | ``"stereo"``), :attr:`indices` (ascending), :attr:`settings`,
    :meth:`read` (one frame: a :class:`~dic.store.FrameResult` or a :class:`~dic.field3d.Field3D`),
    iteration over ``(index, frame)`` (each frame read when it is reached: a consumer that keeps none
    holds one at a time), :meth:`frame_paths` and :meth:`table_attrs` (the attributes of the file's
    table, as in ``to_xarray()``). Use as a context manager.
    """

    def __init__(self, source):
        self._reader = None
        if isinstance(source, dic2d.TrackResults):
            self._results, self.kind = source, "dic2d"
        elif isinstance(source, stereo.StereoResults):
            self._results, self.kind = source, "stereo"
        elif isinstance(source, (str, os.PathLike)):
            self._results = None
            self._reader = ResultReader(source)
            self.kind = self._reader.kind.name
        else:
            raise ValueError("expected a result file (path), dic.store.TrackResults or dic.store.StereoResults, "
                             f"got {type(source).__name__}")
        self.indices: list[int] = self._reader.done_frames() if self._reader else list(self._results.indices)
        self.settings: dict = self._reader.settings if self._reader else dict(self._results.settings or {})

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        """Close the file (a results object needs nothing); closing twice is harmless."""
        if self._reader is not None:
            self._reader.close()

    def __len__(self) -> int:
        return len(self.indices)

    def __repr__(self) -> str:
        if self._reader is not None:
            path, is_open = self._reader.path, self._reader._h5 is not None and bool(self._reader._h5)
        else:
            path, is_open = getattr(self._results, "path", None), None
        label = "2-D DIC" if self.kind == "dic2d" else "stereo"
        return _short_repr("ResultFrames", path, label, is_open, lambda: (self.indices, self.settings))

    def read(self, index: int):
        """Frame ``index`` (one of :attr:`indices`)."""
        if self._reader is not None:
            return self._reader.read_frame(index)
        table = self._results.frames if self.kind == "dic2d" else self._results.fields
        if index not in table:
            raise ValueError(f"no finished frame {index!r}; finished: {self.indices}")
        return table[index]

    def __iter__(self):
        for index in self.indices:
            yield index, self.read(index)

    def frame_paths(self, index: int, frame=None) -> tuple[str, ...]:
        """The image path(s) of frame ``index``: (path,) (2-D) or (left, right) (stereo)."""
        if self._reader is not None:
            return self._reader.frame_paths(index)
        if self.kind == "dic2d":
            return (str((frame if frame is not None else self.read(index)).path),)
        return tuple(self._results.paths.get(index, ("", "")))

    def table_attrs(self, first=None) -> dict:
        """The attributes of the file's frame x point table (``to_xarray()``); ``first``: the first frame,
        when the caller has it (stereo tables name its frame and grid)."""
        if self.kind == "dic2d":
            if first is None and self.indices:
                first = self.read(self.indices[0])
            if self._reader is not None:
                r = self._reader
                return dic2d.table_attrs(r.path, r.attrs, r.reference, self.settings, first)
            res = self._results
            return dic2d.table_attrs(res.path, res.attrs, res.reference, res.settings, first)
        if first is None and self.indices:
            first = self.read(self.indices[0])
        if self._reader is not None:  # the rig as read_stereo gives it (a StereoRig's dict)
            from calibration.stereo import StereoRig

            rig = StereoRig.from_dict(self._reader.rig)
            return stereo.table_attrs(self.settings, rig, self._reader.reference["shape"], first)
        res = self._results
        return stereo.table_attrs(res.settings, res.rig, res.reference_shape, first)



def _short_repr(name: str, path, label: str, is_open: bool | None, contents) -> str:
    """``<ResultReader 'run.h5': 2-D DIC, frames 2 (1..2), order 1>`` (``", closed"`` once closed: then
    ``contents`` is not called); ``contents() -> (frame indices, settings)``."""
    where = f" {str(path)!r}" if path is not None else " (in memory)"
    text = f"<{name}{where}: {label}"
    if is_open is False:
        return text + ", closed>"
    indices, settings = contents()
    noun = "frames" if label != "stereo" else "states"
    text += f", {noun} {dic2d.frames_text(indices)}"
    details = ", ".join(f"{k} {settings[k]}" for k in ("order", "subset", "step") if (settings or {}).get(k) is not None)
    return text + (f", {details}" if details else "") + ">"

# ------------------------------------------------------------------------------------------------
# repair


def repair_results(path) -> list[tuple[int | str, str]]:
    """Drop the damaged frames of a result file, so that rerunning the command that wrote it recomputes them.

    Every complete frame is read whole, each dataset's checksum verified (files with checksums: every
    file written since they exist); a frame that does not read (a checksum mismatch from a flipped bit
    or a zeroed block, a missing dataset, no ``index`` attribute, a dataset where its group should be)
    is deleted, and so are leftovers of a frame cut short. The file keeps every other frame, and the
    same ``specula track``/``stereo`` command (or ``track_sequence``/``stereo_sequence`` with the same
    output) then resumes and recomputes the dropped ones. A damaged header (no ``/reference`` or
    ``/settings``, ...) cannot be repaired: :class:`ResultFileDamaged`. The file's lock is held (a file
    a run is writing is refused: :class:`ResultFileInUse`).

    Returns ``[(frame index or group name, what was wrong), ...]`` for the frames dropped (empty: the
    file was whole). Frames written without checksums (files of earlier versions) are checked for
    readability and layout only: a flipped bit in their data cannot be seen.
    """
    import h5py

    path = Path(os.fspath(path))
    if not path.is_file():
        raise ValueError(f"result file not found: {path}")
    lock = files.FileLock(Path(os.path.abspath(path)))
    lock.acquire()
    try:
        try:
            h5 = h5py.File(path, "a")
        except OSError as exc:
            if files.is_lock_error(exc):
                raise files.ResultFileInUse(f"result file {path} is in use by another process (HDF5 could not lock "
                                            "it); repair it when that process has finished") from None
            raise _header_damage(path, f"it does not open as HDF5 ({_first_line(exc)})") from None
        with h5:
            kind = _BY_FORMAT.get(h5.attrs.get("format"))
            if kind is None:
                raise ValueError(f"{path} is not a Specula result file (format {h5.attrs.get('format')!r}); "
                                 "nothing to repair")
            _check_header(h5, path, kind)
            if "frames" not in h5:
                return []
            frames = h5["frames"]
            dropped: list[tuple[int | str, str]] = []
            for name in list(frames.keys()):
                obj = frames[name]
                if name.endswith(".partial") or not obj.attrs.get("complete", 0):
                    reason = "was cut short (unfinished)"
                else:
                    reason = _frame_problem(kind, name, obj)
                    if not reason:
                        continue
                label = int(name) if name.isdigit() else name
                try:
                    del frames[name]
                except Exception as exc:  # noqa: BLE001 - metadata too damaged to unlink the group
                    raise _header_damage(path, f"{kind.frame_noun} {label} {reason} and cannot be dropped "
                                         f"({_first_line(exc)})") from None
                if reason != "was cut short (unfinished)":
                    dropped.append((label, reason))
            if dropped:
                h5.attrs["updated"] = now()
            h5.flush()
            fd = h5.id.get_vfd_handle()
            if isinstance(fd, int):
                os.fsync(fd)
            return dropped
    finally:
        lock.release()


# ------------------------------------------------------------------------------------------------
# whole-file readers, one per kind


def read_results(path) -> dic2d.TrackResults:
    """Read a 2-D DIC result file (complete frames only) into a :class:`dic.store.TrackResults`.

    Every frame is held in memory; to go through a long file one frame at a time use
    :class:`ResultFrames` or :meth:`ResultReader.iter_frames` (the exports and post-processing do)."""
    with ResultReader(path, kind="dic2d") as r:
        frames = {i: r.read_frame(i) for i in r.done_frames()}
        return dic2d.TrackResults(path=r.path, attrs=r.attrs, reference=r.reference, settings=r.settings,
                                  frames=frames)


def read_field(path, index: int):
    """One finished state of a stereo result file as a :class:`dic.field3d.Field3D` (``ValueError`` if absent)."""
    with ResultReader(path, kind="stereo") as r:
        return r.read_frame(index)


def read_stereo(path) -> stereo.StereoResults:
    """Read every finished state of a stereo result file into a :class:`dic.store.StereoResults` (all in
    memory; :class:`ResultFrames` reads one state at a time)."""
    from calibration.stereo import StereoRig

    with ResultReader(path, kind="stereo") as r:
        indices = r.done_frames()
        fields = {i: r.read_frame(i) for i in indices}
        paths = {i: r.frame_paths(i) for i in indices}
        return stereo.StereoResults(fields, r.read_match(), StereoRig.from_dict(r.rig), r.settings, paths,
                                    r.reference["shape"])
