"""The file-system side of the results store: the lock, the temporary file of a new run, space
reservation, fsync, and the errors a user can meet (file in use, disk full, unwritable folder).

:class:`dic.store.ResultWriter` uses these so that

- a result file is never opened, truncated or replaced while another process writes it: a writer
  first takes an exclusive ``flock`` on ``<file>.lock`` (a second writer gets
  :class:`ResultFileInUse`); HDF5's own lock, held by any other program that has the file open,
  is reported the same way;
- a new run (a new file or ``mode="overwrite"``) is written to ``<file>.tmp`` in the same folder
  and renamed over ``<file>`` (``os.replace``) only once it holds its reference data, so a run that
  fails before that leaves the previous file untouched;
- before each frame the space it needs is reserved in the file (``posix_fallocate`` past HDF5's
  end of allocation), so a full disk stops the run *between* frames with
  :class:`ResultWriteError` instead of in the middle of an HDF5 flush, which corrupts the file;
- every frame ends with a flush and an ``fsync`` of the file.

The same lock guards every other output Specula writes (:func:`output_lock`: exports, strain
recomputation, a run's VTK and figure folders, lab sessions), and readers of a result file refuse
one that a writer holds (:func:`check_not_in_use`), before HDF5 opens it: whatever
``HDF5_USE_FILE_LOCKING`` says, a file being written is never read half-way. Every side file is
written whole or not at all (:func:`atomic_output`, from :mod:`kernels._atomic`).
"""
from __future__ import annotations

import errno
import os
import re
from contextlib import contextmanager
from pathlib import Path

from kernels._atomic import atomic_output, fsync_folder

try:  # POSIX only; elsewhere the store runs without the cross-process lock
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

__all__ = ["ResultFileInUse", "ResultWriteError", "FileLock", "lock_path", "temp_path", "check_output_path",
           "write_error", "fsync_folder", "reserve", "abandon", "is_lock_error", "os_errno", "output_lock",
           "check_not_in_use", "atomic_output", "OutputInUse", "ResultFileDamaged"]

_DISK_FULL = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC), errno.EFBIG}


class ResultFileInUse(ValueError):
    """The result file is held by another process (a running Specula job or any HDF5 program)."""


#: an output (an export, a VTK folder, a lab session) held by another process: the same error as a result file's
OutputInUse = ResultFileInUse


class ResultFileDamaged(ValueError):
    """A result file whose content is damaged or not Specula's layout: a frame whose checksum does not
    match (a flipped bit, a zeroed block), a frame without its ``index`` or a required dataset, a
    header group missing or of the wrong type. The message names the file, the frame and what is
    wrong, and says what to do (``specula repair`` for a damaged frame)."""


class ResultWriteError(OSError, ValueError):
    """Writing a result file failed (disk full, I/O error); ``errno`` is the OS error number.

    Both an ``OSError`` and a ``ValueError``: the run ends with one message, and every frame
    finished before it stays in the file, readable and resumable.
    """

    def __init__(self, message: str, err: int | None = None):
        super().__init__(err, message)
        self.message = message

    def __str__(self) -> str:
        return self.message


def lock_path(path: Path) -> Path:
    """``<file>.lock``: the lock file next to a result file."""
    return path.with_name(path.name + ".lock")


def temp_path(path: Path) -> Path:
    """``<file>.tmp``: where a new run is written until it holds its reference data."""
    return path.with_name(path.name + ".tmp")


def os_errno(exc: BaseException) -> int | None:
    """The OS error number of an exception: ``errno``, or the ``errno = N`` HDF5 writes in its messages."""
    err = getattr(exc, "errno", None)
    if isinstance(err, int) and err > 0:
        return err
    m = re.search(r"errno = (\d+)", str(exc))
    return int(m.group(1)) if m else None


def is_lock_error(exc: BaseException) -> bool:
    """True when h5py could not open a file because another process holds HDF5's lock on it."""
    return os_errno(exc) in (errno.EAGAIN, errno.EWOULDBLOCK) or "unable to lock file" in str(exc)


def reason(exc: BaseException) -> str:
    """A short reason for an OS/HDF5 error: "disk full (...)" for ENOSPC/EDQUOT/EFBIG, else the OS text."""
    err = os_errno(exc)
    if err in _DISK_FULL:
        return f"disk full ({os.strerror(err)})"
    if err:
        return os.strerror(err)
    first = str(exc).split("\n")[0].strip()
    return first or type(exc).__name__


def write_error(path: Path, what: str, exc: BaseException, kept: str) -> ResultWriteError:
    """The one message of a failed write: the file, what was being written, why, and what is kept."""
    return ResultWriteError(f"could not write {what} to {path}: {reason(exc)}. {kept}", os_errno(exc))


def check_output_path(path: Path) -> None:
    """Refuse, with a ValueError naming the path and the reason, an output that cannot be written:
    a folder in the way, a parent that is a file, a folder that cannot be created."""
    if path.is_dir():
        raise ValueError(f"cannot write the result file {path}: it is a folder")
    for p in (path.parent, *path.parent.parents):
        if p.exists():
            if not p.is_dir():
                raise ValueError(f"cannot write the result file {path}: {p} is a file, not a folder")
            break
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"cannot write the result file {path}: cannot create the folder {path.parent} "
                         f"({exc.strerror or exc})") from None


class FileLock:
    """An exclusive, non-blocking ``flock`` on ``<file>.lock``, held while a writer has the file open.

    The lock file holds the owner's process id (for the message a second writer gets) and is
    removed on release; a lock file left by a killed process is stale (the kernel released its
    lock) and is simply taken over.
    """

    def __init__(self, target: Path, what: str = "result file"):
        self.target = target
        self.what = what
        self.path = lock_path(target)
        self.fd: int | None = None

    def acquire(self) -> None:
        if fcntl is None:  # pragma: no cover - no flock on this platform
            return
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                if exc.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)):
                    raise ResultWriteError(f"cannot write the {self.what} {self.target}: cannot create its lock file "
                                           f"{self.path}: {reason(exc)}", exc.errno) from None
                raise ValueError(f"cannot write the {self.what} {self.target}: the folder {self.target.parent} "
                                 f"does not take new files ({exc.strerror or exc})") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                owner = _read_owner(fd)
                os.close(fd)
                raise ResultFileInUse(
                    f"{self.what} {self.target} is in use by another process ({owner}lock {self.path}); "
                    "wait for that run to finish, or write to another file") from None
            except OSError:  # no flock on this file system (some network mounts): go on without it
                os.close(fd)
                return
            try:  # the file we locked must still be the lock file (not one a releasing owner just removed)
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        self.fd = fd
        try:
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
        except OSError:  # a full disk: the lock holds all the same
            pass

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            os.unlink(self.path)  # while still holding the lock (see acquire)
        except OSError:
            pass
        os.close(self.fd)
        self.fd = None


@contextmanager
def output_lock(path, what: str = "output"):
    """Hold the lock of an output (a file or a folder) while it is written: ``<path>.lock`` next to it.

    The one file protocol of every Specula writer: a second process writing the same output gets
    :class:`OutputInUse` (a ``ValueError``) naming it, and the output is left as the first process
    writes it. ``what`` names the output in that message ("CSV folder", "MATLAB file", ...).
    Re-entrant in one process only through separate outputs: the same output locked twice, even by
    one process, is refused (two writers of one file).
    """
    target = Path(os.path.abspath(os.fspath(path)))
    try:
        target.parent.mkdir(parents=True, exist_ok=True)  # the lock file lives next to the output
    except OSError as exc:
        raise ValueError(f"cannot write the {what} {path}: cannot create the folder {target.parent} "
                         f"({exc.strerror or exc})") from None
    lock = FileLock(target, what)
    lock.acquire()
    try:
        yield target
    finally:
        lock.release()


def check_not_in_use(path, what: str = "result file") -> None:
    """Refuse to read a file that another process is writing (it holds ``<path>.lock``).

    Readers call this before HDF5 opens the file, so the refusal is the same with or without HDF5's
    own file locking (``HDF5_USE_FILE_LOCKING=FALSE``, common on NFS/Lustre, lets HDF5 read a file in
    the middle of a write). A lock held by this very process (a reader of the file a run of this
    process writes) is no refusal. Raises :class:`ResultFileInUse` naming the file and the lock.
    """
    if fcntl is None:  # pragma: no cover - no flock on this platform
        return
    lock = lock_path(Path(os.path.abspath(os.fspath(path))))
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:  # no lock file: nobody writes it (a writer creates it before opening the file)
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = _read_owner(fd)
            if owner == f"pid {os.getpid()}, ":
                return
            raise ResultFileInUse(
                f"{what} {path} is in use by another process ({owner}lock {lock}): a run is still writing it; "
                "read it when that run has finished") from None
        except OSError:  # no flock on this file system
            return
        fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


def _read_owner(fd: int) -> str:
    try:
        pid = os.pread(fd, 32, 0).decode().strip()
    except (OSError, UnicodeDecodeError):
        return ""
    return f"pid {pid}, " if pid.isdigit() else ""


def reserve(fd: int, start: int, nbytes: int) -> None:
    """Allocate ``nbytes`` of disk space in the file from offset ``start`` (HDF5's end of allocation).

    HDF5 writes a frame's new objects from its end of allocation on; with those blocks allocated
    beforehand, the frame and its flush cannot meet a full disk half-way. Raises OSError
    (ENOSPC, EDQUOT, EFBIG) when the space is not there, with the file's size restored; file
    systems without ``fallocate`` support are written without a reservation.
    """
    size = os.fstat(fd).st_size
    if size >= start + nbytes:
        return
    try:
        os.posix_fallocate(fd, start, nbytes)
    except OSError as exc:
        try:
            if os.fstat(fd).st_size > size:
                os.ftruncate(fd, size)
        except OSError:
            pass
        if exc.errno in _DISK_FULL:
            raise
    except AttributeError:  # pragma: no cover - no posix_fallocate on this platform
        pass


def abandon(h5) -> None:
    """Close an h5py file after a failed write without letting HDF5 write anything more to it.

    After a write error HDF5's cache may hold half of a frame; flushing it (which ``close`` does)
    is what corrupts files on a full disk. The file's descriptor is pointed at ``/dev/null``
    first, so the file on disk stays as it was at the last finished frame.
    """
    try:
        fd = h5.id.get_vfd_handle()
        null = os.open(os.devnull, os.O_RDWR)
        os.dup2(null, fd)
        os.close(null)
    except Exception:  # noqa: BLE001 - nothing more can be done; close as well as possible
        pass
    try:
        h5.close()
    except Exception:  # noqa: BLE001
        pass
