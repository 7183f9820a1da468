"""Ctrl-C during a long run (``specula track``, ``specula stereo``): say what is saved and how to go on.

Finished frames are flushed to the result file as they end (dic/store), so an interrupted run
keeps them and the same command resumes after the last one. Click alone would print "Aborted!".
"""
from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import click

#: the exit status of a run stopped by Ctrl-C (SIGINT), as shells report it: 128 + 2
INTERRUPTED_EXIT = 130


def saved_frames(output: Path) -> int | None:
    """The finished frames (states) in the result file ``output``; None when it cannot be read (no file yet,
    nothing written, or a file that another process holds)."""
    from dic.store import ResultReader

    if not Path(output).exists():
        return 0
    try:
        with ResultReader(output) as reader:
            return len(reader.done_frames())
    except (ValueError, OSError):
        return None


def interrupted_message(output: Path, noun: str) -> str:
    """``N frames saved in FILE; run the same command again to resume`` (``noun``: "frame" or "state")."""
    n = saved_frames(output)
    if n is None:
        return f"Interrupted: finished {noun}s are kept in {output}; run the same command again to resume"
    if n == 0:
        return f"Interrupted: no {noun} was saved in {output} yet; run the same command again to start over"
    return f"Interrupted: {n} {noun}{'s' if n != 1 else ''} saved in {output}; run the same command again to resume"


@contextmanager
def report_interrupt(output: Path, noun: str):
    """Turn Ctrl-C (KeyboardInterrupt) inside the block into :func:`interrupted_message` on stderr and exit
    status :data:`INTERRUPTED_EXIT`."""
    try:
        yield
    except KeyboardInterrupt:
        click.echo(interrupted_message(output, noun), err=True)
        raise SystemExit(INTERRUPTED_EXIT) from None
