"""``specula animate``: a movie (MP4 or GIF) of one quantity over the frames of a result file.

The movie is written by :func:`dic.animate.write_animation` with one colour range for the whole
movie; docs/cli.md describes the verb.
"""
from __future__ import annotations

from pathlib import Path

import click

from dic.animate import MAX_FPS

CONTEXT = {"help_option_names": ["-h", "--help"]}


def _reference_image(results: Path, quiet: bool):
    """The stored reference image (the left one for stereo) when its file can be read, else None (with a note)."""
    from dic.io import read_image
    from dic.store import ResultReader

    with ResultReader(results) as r:
        ref = r.reference
    stored = ref.get("path") or ref.get("left_path") or ""
    if not stored:
        return None
    candidates = [Path(stored)]
    if not Path(stored).is_absolute():
        candidates.append(results.parent / stored)
    for p in candidates:
        if p.is_file():
            try:
                return read_image(p)
            except (ValueError, OSError) as exc:
                if not quiet:
                    click.echo(f"note: reference image {p} not drawn ({exc})", err=True)
                return None
    if not quiet:
        click.echo(f"note: reference image {stored} not found; drawing the maps without it", err=True)
    return None


@click.command(name="animate", context_settings=CONTEXT)
@click.argument("results", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--quantity", "-Q", required=True, type=click.STRING,
              help="What to show: 2-D u, v, magnitude or a stored strain (exx, eyy, exy, Exx, ...); stereo Z, U, V, "
                   "W, exx, eyy, exy or zncc_stereo.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The movie: .mp4 (H.264) or .gif.")
@click.option("--fps", default=5.0, show_default=True, type=click.FloatRange(min=0, max=MAX_FPS, min_open=True),
              help="Frames per second of the movie.")
@click.option("--frames", default=None, type=click.STRING,
              help="Frame indices to show, e.g. 1,2,5 or 2-6 (default: every finished frame).")
@click.option("--dpi", default=80, show_default=True, type=click.IntRange(20, 300),
              help="Resolution of the frames (a 5-inch map at 80 dpi is 400 px wide).")
@click.option("--no-image", is_flag=True, help="Do not draw the reference image beneath the maps.")
@click.option("-q", "--quiet", is_flag=True, help="No summary.")
def animate(results, quantity, output, fps, frames, dpi, no_image, quiet):
    """A movie of one QUANTITY over the frames of RESULTS (a 2-D or stereo result file).

    Every frame is drawn with one colour range, the 1st-99th percentiles of the quantity over all the
    shown frames, so a colour means the same value throughout. The movie appears under its name only
    when it is complete.

    \b
    specula animate run.h5 --quantity exx -o exx.mp4
    specula animate stereo.h5 --quantity W -o w.gif --fps 2 --frames 1-10
    """
    from dic.animate import write_animation
    from dic.commands.postprocess import _frames

    wanted = _frames(frames)
    image = None if no_image else _reference_image(results, quiet)  # errors: one line by the specula group
    path = write_animation(results, output, quantity=quantity, fps=fps, frames=wanted, image=image, dpi=dpi)
    if not quiet:
        click.echo(f"wrote {path} ({quantity}, {fps:g} frames per second)")
