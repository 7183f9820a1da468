"""``specula repair``: drop the damaged frames of a result file so that a rerun recomputes them."""
from __future__ import annotations

from pathlib import Path

import click


@click.command(name="repair", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("results", type=click.Path(dir_okay=False, path_type=Path))
def repair(results):
    """Check every finished frame of RESULTS (a .h5 of specula track or stereo) and drop the damaged ones.

    A frame whose checksum does not match (a flipped bit, a zeroed block), or that lacks a dataset or
    its index, is deleted; every other frame is kept. Rerun the command that wrote the file (same
    output, same images and options) to recompute the dropped frames.
    """
    from dic.store import repair_results

    dropped = repair_results(results)
    for label, reason in dropped:
        click.echo(f"dropped frame {label}: {reason}")
    if dropped:
        click.echo(f"{results}: {len(dropped)} damaged frame{'s' if len(dropped) != 1 else ''} dropped; rerun the "
                   "command that wrote it (same output, images and options) to recompute "
                   f"{'them' if len(dropped) != 1 else 'it'}")
    else:
        click.echo(f"{results}: every finished frame reads whole; nothing to repair")
