"""``specula target``: write calibration target images to show on a monitor (or to print), with a
JSON file of the target (parameters, orientation code, object points in mm).

Examples::

    specula target fringes --screen 1920x1080 --pixel-pitch 0.311 --grid 6x3 --pitch 300 --steps 4 -o fringes/
    specula target fringes --grid 4x2 --pitch 450 --period 300 --dense -o section3/
    specula target checkerboard --corners 9x6 --square 120 -o board/
    specula target circles --grid 6x3 --pitch 300 --diameter 150 -o circles/
    specula target checkerboard --screen fit --pixel-pitch 1 --corners 9x6 --square 25 --printable -o print/

``--printable`` also writes ``{name}.svg`` and ``{name}.pdf``, vector files whose page is the target's
physical size (``screen × pixel_pitch`` mm; :mod:`calibration.printable`): print them at 100 %.

See docs/targets.md for the designs and the target frame (origin at the centre of screen pixel
(0, 0), x right, y down, z into the screen, mm).
"""
from __future__ import annotations

import os
import re

import click

from calibration.targets import MONITOR_PIXEL_PITCH_MM


def _pair(text: str, name: str, integer: bool):
    parts = str(text).lower().replace(",", "x").split("x")
    try:
        vals = [int(p) if integer else float(p) for p in parts]
    except ValueError:
        raise click.BadParameter(f"{name} must look like 'AxB' ({'integers' if integer else 'numbers'}), got {text!r}") from None
    if len(vals) != 2:
        raise click.BadParameter(f"{name} must look like 'AxB', got {text!r}")
    return tuple(vals)


def _screen(text: str):
    """``--screen``: 'WxH' px, or 'fit' (the board plus a margin of one square / one circle pitch)."""
    return None if str(text).strip().lower() == "fit" else _pair(text, "--screen", True)


def _write_printable(target, out: str, prefix: str) -> None:
    from calibration.printable import page_size_mm, write_pdf, write_svg

    paths = [write_svg(target, os.path.join(out, f"{prefix}.svg")), write_pdf(target, os.path.join(out, f"{prefix}.pdf"))]
    w, h = page_size_mm(target)
    click.echo(f"wrote {paths[0]} and {paths[1]}: {w:g} x {h:g} mm; print at 100 % (actual size, no fit to page) "
               "and measure a square or the pitch before use")


def _write(target, out: str, prefix: str, dense: bool = False) -> None:
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as exc:
        raise click.ClickException(f"cannot create output folder {out}: {exc}") from exc
    paths = target.save_images(out, prefix=prefix)
    if dense:
        import imageio.v3 as iio

        from kernels._atomic import atomic_output

        for k, img in enumerate(target.dense_images()):
            path = os.path.join(out, f"{prefix}_dense_{k:02d}.png")
            with atomic_output(path) as tmp:  # whole or not at all
                iio.imwrite(tmp, img)
            paths.append(path)
    json_path = os.path.join(out, f"{prefix}.json")
    target.save_json(json_path)
    names = [os.path.basename(p) for p in paths]
    listed = names[0] if len(names) == 1 else f"{names[0]} … {names[-1]}"
    click.echo(f"wrote {len(paths)} image(s) {target.screen[0]}x{target.screen[1]} ({listed}) in {out}, and {json_path}")


def _common(f):
    f = click.option("--screen", default="1920x1080", show_default=True, help="Monitor resolution WxH (px); checkerboard and circles also take 'fit' "
                                                            "(the pattern plus one square / pitch of margin).")(f)
    f = click.option("--pixel-pitch", type=float, default=MONITOR_PIXEL_PITCH_MM, show_default=True,
                     help="Monitor pixel pitch (mm).")(f)
    f = click.option("-o", "--out", required=True, type=click.Path(file_okay=False), help="Output folder.")(f)
    return f


@click.group(name="target")
def target():
    """Write calibration target images (PNG, shown full-screen, unscaled) and their JSON; show them (target show)."""


@target.command()
@_common
@click.option("--grid", default="6x3", show_default=True, help="Dots along x and y.")
@click.option("--pitch", type=float, default=300, show_default=True, help="Dot spacing (screen px).")
@click.option("--steps", type=int, default=4, show_default=True, help="Phase steps N >= 3.")
@click.option("--period", type=float, default=None, help="Fringe period (screen px); default: the pitch.")
@click.option("--guard", type=float, default=None, help="Fringe band beyond the outer cells (screen px).")
@click.option("--no-code", is_flag=True, help="Plain target as in the paper (no orientation code).")
@click.option("--gamma", type=float, default=1.0, show_default=True, help="Monitor gamma to pre-compensate.")
@click.option("--dense", is_flag=True, help="Also write the dense-mode linear fringe sequence.")
def fringes(screen, pixel_pitch, out, grid, pitch, steps, period, guard, no_code, gamma, dense):
    """Phase-shifted circular fringes (coded dot grid) and optionally the dense sequence."""
    from calibration.targets import PhaseTarget

    try:
        tg = PhaseTarget(_pair(screen, "--screen", True), pixel_pitch, _pair(grid, "--grid", True), pitch, steps,
                         period=period, guard=guard, code=not no_code, gamma=gamma)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from exc
    _write(tg, out, "fringes", dense=dense)
    click.echo(f"{tg.n_dots} dots, spacing {tg.spacing_mm:.3f} mm; show each image full screen and unscaled (1 screen "
               f"px = 1 image px), in order, one capture each; give {os.path.join(out, 'fringes.json')} to "
               "'specula calibrate' as --target")


@target.command()
@_common
@click.option("--corners", default="9x6", show_default=True, help="Inner corners along x and y.")
@click.option("--square", type=float, default=100, show_default=True, help="Square size (screen px).")
@click.option("--printable", is_flag=True,
              help="Also write checkerboard.svg and checkerboard.pdf at the physical size (screen x pixel pitch mm).")
def checkerboard(screen, pixel_pitch, out, corners, square, printable):
    """A checkerboard (for OpenCV's detectors and for comparison).

    To print one: --screen fit --pixel-pitch 1 --square SQUARE_MM --printable."""
    from calibration.targets import CheckerboardTarget

    try:
        tg = CheckerboardTarget(_screen(screen), pixel_pitch, _pair(corners, "--corners", True), square)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from exc
    _write(tg, out, "checkerboard")
    if printable:
        _write_printable(tg, out, "checkerboard")


@target.command()
@_common
@click.option("--grid", default="6x3", show_default=True, help="Circles along x and y.")
@click.option("--pitch", type=float, default=300, show_default=True, help="Circle spacing (screen px).")
@click.option("--diameter", type=float, default=None, help="Circle diameter (screen px); default pitch / 2.")
@click.option("--printable", is_flag=True,
              help="Also write circles.svg and circles.pdf at the physical size (screen x pixel pitch mm).")
def circles(screen, pixel_pitch, out, grid, pitch, diameter, printable):
    """A symmetric grid of dark circles (OpenCV's findCirclesGrid target).

    To print one: --screen fit --pixel-pitch 1 --pitch PITCH_MM --printable."""
    from calibration.targets import CircleGridTarget

    try:
        tg = CircleGridTarget(_screen(screen), pixel_pitch, _pair(grid, "--grid", True), pitch, diameter)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from exc
    _write(tg, out, "circles")
    if printable:
        _write_printable(tg, out, "circles")


def _geometry(text):
    """``--geometry WxH+X+Y`` -> (W, H, X, Y)."""
    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)x(\d+)([+-]\d+)([+-]\d+)\s*", str(text))
    if not m:
        raise click.BadParameter(f"expected WxH+X+Y (px, e.g. 1920x1080+1920+0), got {text!r}", param_hint="--geometry")
    w, h, x, y = (int(v) for v in m.groups())
    if w < 1 or h < 1:
        raise click.BadParameter(f"width and height must be at least 1 px, got {text!r}", param_hint="--geometry")
    return w, h, x, y


@target.command()
@click.argument("folder", type=click.Path(file_okay=False))
@click.option("--screen", "screen", default=0, show_default=True, type=click.IntRange(min=0),
              help="The monitor: K-th of 'xrandr --listmonitors' (without xrandr: 0, the whole screen).")
@click.option("--geometry", default=None, help="The monitor's area WxH+X+Y in px of the X screen (replaces --screen).")
@click.option("--interval", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Seconds per image; without it, a key press steps (Space/Right: next, Left: back, Escape: stop).")
@click.option("--after-each", default=None,
              help="A command run after each image is on the screen (e.g. a camera trigger); {index} (0-based) and "
                   "{path} are replaced. The next step waits for it; a failure stops the show.")
@click.option("--settle", default=0.2, show_default=True, type=click.FloatRange(min=0),
              help="Seconds between drawing an image and running --after-each.")
@click.option("--loop", is_flag=True, help="Start again after the last image (stop with Escape).")
def show(folder, screen, geometry, interval, after_each, settle, loop):
    """Show the images of FOLDER (written by 'specula target') full screen, unscaled (1 image px = 1 screen px).

    Images are shown in natural file order from the monitor's top-left pixel, on black. Step with a key
    (Space/Return/Right: next, Left/BackSpace: back, Escape/q: stop) or with --interval; --after-each runs
    a command after each image, e.g. to trigger a camera.

    \b
    specula target show fringes/ --screen 1
    specula target show fringes/ --interval 1.5 --after-each "gphoto2 --capture-image-and-download --filename cap_{index}.jpg"
    """
    from calibration.display import show_images, target_images

    files = target_images(folder)
    area = _geometry(geometry)
    click.echo(f"showing {len(files)} image(s) of {folder}: " + ("every " + f"{interval:g} s" if interval else
               "Space/Right: next, Left: back, Escape: stop"))
    result = show_images(files, screen=screen, geometry=area, interval=interval, after_each=after_each, settle=settle,
                         loop=loop)
    click.echo(f"{result.reason} ({len(result.shown)} step(s))")
    if not result.completed and result.reason.startswith("the command"):
        raise click.ClickException(result.reason)
