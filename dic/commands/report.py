"""``specula report``: one self-contained HTML run report of a result file (:func:`dic.report.write_report`).

docs/cli.md describes the verb.
"""
from __future__ import annotations

import time
from pathlib import Path

import click

from dic.commands.postprocess import POINT, NumbersType
from dic.report import MAP_WIDTH, MAX_MAP_FRAMES

CONTEXT = {"help_option_names": ["-h", "--help"]}


GAUGE = NumbersType(4, "x1,y1,x2,y2", "gauge ends x1,y1,x2,y2 (four finite numbers separated by commas)")


@click.command(name="report", context_settings=CONTEXT)
@click.argument("results", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The report: an .html file (self-contained: open it in any browser, offline).")
@click.option("--quantity", "-Q", default=None, type=click.STRING,
              help="What the maps show: 2-D u, v, magnitude or a stored strain (exx, eyy, exy, Exx, ...); stereo Z, "
                   "U, V, W, exx, eyy, exy or zncc_stereo. [default: magnitude (2-D), W (stereo)]")
@click.option("--history", "history", multiple=True, type=POINT,
              help="A reference point X,Y (image px) whose quantity is shown over the frames; repeatable.")
@click.option("--extensometer", "extensometer", multiple=True, type=GAUGE,
              help="A virtual extensometer between X1,Y1 and X2,Y2 (reference image px); repeatable.")
@click.option("--max-frames", default=MAX_MAP_FRAMES, show_default=True, type=click.IntRange(min=1),
              help="The most frames with a map; longer runs show this many, evenly spaced.")
@click.option("--map-width", default=MAP_WIDTH, show_default=True, type=click.IntRange(64, 4096),
              help="The most pixels across a map (a wider reference image is shrunk to it, a narrower one enlarged by a whole factor).")
@click.option("--no-image", is_flag=True, help="Do not draw the reference image beneath the maps.")
@click.option("-q", "--quiet", is_flag=True, help="No summary.")
def report(results, output, quantity, history, extensometer, max_frames, map_width, no_image, quiet):
    """One self-contained HTML report of RESULTS (a 2-D or stereo result file).

    The report holds the run settings, quality per frame (valid fraction over the region, median ZNCC,
    sigma, iterations, seconds), maps of one quantity over the reference image with a frame slider
    (one colour range; open frame K with #frame=K in the address), histories and extensometers when
    asked, and the 3-D shape of a stereo result.

    \b
    specula report run.h5 -o report.html
    specula report run.h5 -o report.html --quantity exx --history 194,543 --extensometer 50,300,340,300
    """
    from dic.commands.animate import _reference_image
    from dic.report import write_report

    started = time.perf_counter()
    image = None if no_image else _reference_image(results, quiet)
    path = write_report(results, output, quantity=quantity, image=image, history=history, extensometer=extensometer,
                        max_frames=max_frames, map_width=map_width)
    if not quiet:
        size = path.stat().st_size / 1e6
        click.echo(f"wrote {path} ({size:.2f} MB) in {time.perf_counter() - started:.1f} s")
