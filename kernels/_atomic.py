"""Atomic file output: every file Specula writes appears whole or not at all.

The one helper behind every writer of every layer (images, calibration and rig files, VTK, CSV,
MAT, figures, JSON; :mod:`dic.store.files` re-exports it): the file is written under a temporary,
hidden name in its own folder, flushed and fsynced, then renamed over the final name
(``os.replace``, atomic on POSIX file systems) and the folder fsynced. A writer that fails half-way
(a full disk, an exception, Ctrl-C) leaves no truncated file: the temporary file is removed, and a
previous file of that name is untouched. It lives in ``kernels/`` because ``calibration/`` may not
import ``dic`` (docs/architecture.md, layers).
"""
from __future__ import annotations

import os
import secrets
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_output", "atomic_temp_name", "fsync_path", "fsync_folder", "TEMP_MARK"]

#: what every temporary name contains (``.<stem>.tmp-<hex><suffix>``); hidden, so globs such as
#: ``frame_*.vtu`` never see a temporary file
TEMP_MARK = ".tmp-"


def atomic_temp_name(path: Path) -> Path:
    """A fresh temporary name next to ``path``: ``.<stem>.tmp-<8 hex><suffix>`` (the suffix kept, so that
    writers that choose the format from it, e.g. meshio, Matplotlib, imageio, scipy.io, still do)."""
    return path.with_name(f".{path.stem}{TEMP_MARK}{secrets.token_hex(4)}{path.suffix}")


def fsync_path(path) -> None:
    """fsync a file by name (its data reach the disk before it is renamed into place)."""
    fd = os.open(os.fspath(path), os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_folder(folder) -> None:
    """fsync a folder (makes a rename in it durable); best effort (some file systems refuse it)."""
    try:
        fd = os.open(os.fspath(folder), os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextmanager
def atomic_output(path, *, mkdir: bool = True):
    """Write ``path`` atomically: yields a temporary path in the same folder to write instead.

    On leaving the block without an exception the temporary file is fsynced and renamed over
    ``path``; on an exception it is removed and ``path`` is left as it was (absent, or the previous
    file). A block that writes nothing to the temporary path raises ``OSError`` (a writer that
    silently wrote elsewhere). ``mkdir``: create the parent folders first. Yields a
    :class:`~pathlib.Path`.

    >>> with atomic_output("out/frame_000001.vtu") as tmp:  # doctest: +SKIP
    ...     mesh.write(tmp)
    """
    final = Path(os.fspath(path))
    if mkdir:
        final.parent.mkdir(parents=True, exist_ok=True)
    tmp = atomic_temp_name(final)
    try:
        yield tmp
        if not tmp.exists():
            raise OSError(f"the writer of {final} wrote no file to {tmp}")
        fsync_path(tmp)
        os.replace(tmp, final)
    except BaseException:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise
    fsync_folder(final.parent)
