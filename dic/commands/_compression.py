"""``--compression`` of the commands that write a result file (``specula track``, ``specula stereo``)."""
from __future__ import annotations

import click


def _parse(ctx, param, value):
    if value is None:
        return None
    from dic.store.layout import parse_compression

    try:
        return parse_compression(value).text
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


def compression_option(noun: str):
    """The ``--compression none|lzf|gzip[:LEVEL]`` option (a checked text, or None for the default)."""
    return click.option(
        "--compression", default=None, metavar="none|lzf|gzip[:LEVEL]", callback=_parse,
        help=f"How the result file's arrays are compressed: none (default: the fastest, about 1.6x the size), "
             f"gzip (level 4, or gzip:0-9: smaller, slower to write; read by any HDF5 tool), lzf (between the two; "
             f"h5py's own filter, other HDF5 tools need its plugin). A resumed file keeps "
             f"the setting it was written with. Each {noun} is compressed only where it pays (docs/results_format.md).")
