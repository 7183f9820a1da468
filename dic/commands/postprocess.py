"""Post-processing verbs: ``specula strain``, ``extensometer``, ``history`` and ``profile``.

They read a result file (2-D or stereo), call :mod:`dic.postprocess` and write a result file,
a CSV table and/or a figure (:mod:`dic.plots.postprocess`). docs/postprocessing.md has examples.
"""
from __future__ import annotations

import csv
from pathlib import Path

import click
import numpy as np

CONTEXT = {"help_option_names": ["-h", "--help"]}


class NumbersType(click.ParamType):
    """``count`` finite numbers separated by commas (``x,y`` for a point; the message names ``what``)."""

    def __init__(self, count: int, name: str, what: str):
        self.count, self.name, self.what = int(count), name, what

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        parts = str(value).replace(" ", "").split(",")
        try:
            if len(parts) != self.count:
                raise ValueError
            vals = tuple(float(p) for p in parts)
            if not np.all(np.isfinite(vals)):
                raise ValueError
        except ValueError:
            self.fail(f"expected {self.what}, got {value!r}", param, ctx)
        return vals


POINT = NumbersType(2, "x,y", "a point x,y (two finite numbers separated by a comma)")
RESULTS = click.Path(dir_okay=False, path_type=Path)
_AT = click.option("--at", default="px", show_default=True, type=click.Choice(["px", "mm"]),
                   help="Units of the given positions: reference image px, or mm (2-D: with a scale; stereo: "
                        "the X, Y coordinates of the result's frame).")
_SCALE = click.option("--scale", default=None, type=click.FloatRange(min=0, min_open=True),
                      help="mm per px of a 2-D result (default: the one stored in the file, else px).")
_FRAMES = click.option("--frames", default=None,
                       help="Frame indices to use, e.g. 1,2,5 or 2-6 (default: every finished frame).")
_CSV = click.option("--csv", "csv_path", default=None, type=click.Path(dir_okay=False, path_type=Path),
                    help="Write the table to this CSV file.")
_PLOT = click.option("--plot", "plot_path", default=None, type=click.Path(dir_okay=False, path_type=Path),
                     help="Write a figure (PNG, PDF, SVG: from the suffix).")


#: the most frame indices ``--frames`` may name (ranges included): far more than any result file holds
MAX_FRAME_SELECTION = 1_000_000


def _frames(text):
    """``"1,2,5"`` / ``"2-6"`` / ``"1,3-4"`` -> [indices], or None; at most MAX_FRAME_SELECTION indices."""
    if text is None:
        return None
    out = []
    try:
        for part in str(text).replace(" ", "").split(","):
            if "-" in part:
                lo, hi = (int(v) for v in part.split("-"))
                if hi < lo:
                    raise ValueError
                if hi - lo + 1 + len(out) > MAX_FRAME_SELECTION:
                    raise click.BadParameter(f"{text!r} names more than {MAX_FRAME_SELECTION:,} frames; give the "
                                             "frames of the result file", param_hint="--frames")
                out.extend(range(lo, hi + 1))
            else:
                out.append(int(part))
    except ValueError:
        raise click.BadParameter(f"expected frame indices such as 1,2,5 or 2-6, got {text!r}",
                                 param_hint="--frames") from None
    return out


def _fmt(x) -> str:
    return "nan" if not np.isfinite(x) else f"{x:.6g}"


def _write_csv(path: Path, names, table) -> None:
    from dic.store.files import atomic_output, output_lock

    with output_lock(path, "CSV file"), atomic_output(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(names)
        for row in table:
            w.writerow([int(v) if i == 0 else repr(float(v)) for i, v in enumerate(row)])


def _echo_table(names, table) -> None:
    click.echo("  ".join(f"{n:>14}" for n in names))
    for row in table:
        click.echo("  ".join(f"{int(row[0]):>14}" if i == 0 else f"{_fmt(v):>14}" for i, v in enumerate(row)))


def _run(fn, *args, **kwargs):
    """Call a library function; every ValueError (bad file, quantity, point ...) as one message."""
    try:
        return fn(*args, **kwargs)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None


def _load(results, quantity=None):
    """The result file (left on disk: the library reads it one frame at a time) and the quantity
    (default: u for 2-D, U for stereo)."""
    from dic.store import ResultReader

    if quantity is None:
        with _run(ResultReader, results) as r:
            quantity = "u" if r.kind.name == "dic2d" else "U"
    return results, quantity


def _outputs(csv_path, plot_path, names, table, plot, obj, quiet) -> None:
    """Write the CSV and the figure (``plot``: the name of a writer of dic.plots.postprocess, imported only
    when a figure is asked for: Matplotlib takes 0.3-1 s to import) and print the table."""
    if csv_path is not None:
        _write_csv_checked(csv_path, names, table)
    if plot_path is not None:
        from dic.plots import postprocess as figures

        try:
            _run(getattr(figures, plot), plot_path, obj)
        except OSError as exc:
            raise click.ClickException(f"cannot write {plot_path}: {exc.strerror or exc}") from None
    if not quiet:
        if csv_path is None:
            _echo_table(names, table)
        else:
            click.echo(f"table: {csv_path}")
        if plot_path is not None:
            click.echo(f"figure: {plot_path}")


def _ranges(values) -> str:
    """``[1, 2, 3, 5, 7, 8]`` -> ``"1-3, 5, 7-8"``."""
    values = sorted(int(v) for v in values)
    parts, lo = [], None
    for k, v in enumerate(values):
        if lo is None:
            lo = v
        if k + 1 == len(values) or values[k + 1] != v + 1:
            parts.append(f"{lo}" if lo == v else f"{lo}-{v}")
            lo = None
    return ", ".join(parts)


def _frames_text(frames) -> str:
    """``[3]`` -> ``"frame 3"``, ``[1, 2, 5]`` -> ``"frames 1-2, 5"``."""
    return f"frame{'s' if len(frames) > 1 else ''} {_ranges(frames)}"


def _why(frames, status) -> str:
    """Why a query has no value in ``frames``: its reason, or the reason in each group of frames."""
    from dic.gridinterp import QueryStatus

    frames, status = np.asarray(frames), np.asarray(status)
    codes = [c for c in dict.fromkeys(int(c) for c in status) if c != QueryStatus.OK]
    if len(codes) == 1:
        return f"it is {QueryStatus(codes[0]).reason}"
    return "; ".join(f"in {_frames_text(frames[status == c])} it is {QueryStatus(c).reason}" for c in codes)


def _where(point, at) -> str:
    return f"({point[0]:g}, {point[1]:g}) {at}"


def _check_point(what, point, at, frames, status) -> None:
    """A point with no value in any frame is an error (exit status 1) that says why; a point with
    no value in some frames a warning on stderr."""
    from dic.gridinterp import QueryStatus

    missing = np.asarray(status) != QueryStatus.OK
    if missing.all():
        raise click.ClickException(f"no value at the {what} {_where(point, at)} in any frame: {_why(frames, status)}")
    if missing.any():
        click.echo(f"Warning: no value at the {what} {_where(point, at)} in {_frames_text(np.asarray(frames)[missing])}: "
                   f"{_why(np.asarray(frames)[missing], np.asarray(status)[missing])}", err=True)


def _write_csv_checked(path, names, table) -> None:
    try:
        _write_csv(path, names, table)
    except OSError as exc:
        raise click.ClickException(f"cannot write {path}: {exc.strerror or exc}") from None


#: library keywords of dic.postprocess.recompute_strain and the checks it calls -> this command's options
_STRAIN_OPTIONS = {"min_points": "--min-points", "min_neighbours": "--min-points", "strain_type": "--strain-type",
                   "strain_window": "--window", "strain window": "--window"}


def _with_options(text: str) -> str:
    """A library message with its keywords named as this command's options (``min_points`` -> ``--min-points``)."""
    import re

    pattern = "|".join(re.escape(k) for k in sorted(_STRAIN_OPTIONS, key=len, reverse=True))
    return re.sub(rf"(?<![\w-])({pattern})(?![\w-])", lambda m: _STRAIN_OPTIONS[m.group(1)], text)


@click.command(name="strain", context_settings=CONTEXT)
@click.argument("results", type=RESULTS)
@click.option("--window", required=True, type=float,
              help="Strain fit window: grid points per side (odd >= 3), or its side in px with --px.")
@click.option("--px", "in_px", is_flag=True, help="--window is the window's side in px.")
@click.option("--grid-points", "in_grid", is_flag=True, help="--window is in grid points (the default).")
@click.option("--strain-type", default=None, type=click.Choice(["green-lagrange", "small", "euler-almansi"],
                                                               case_sensitive=False),
              help="What exx, eyy, exy are (default: the file's; files without one: 2-D small, stereo "
                   "green-lagrange).")
@click.option("-o", "--output", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="New result file (.h5); default: rewrite RESULTS in place.")
@click.option("--min-points", default=None, type=click.IntRange(min=3),
              help="Fewest valid points per fit (2-D default: a quarter window; stereo default 6).")
@click.option("--scale", default=None, type=click.FloatRange(min=0, min_open=True),
              help="2-D: also store this scale, mm per px (positions and displacements of post-processing in mm).")
@click.option("-q", "--quiet", is_flag=True, help="No summary.")
def strain(results, window, in_px, in_grid, strain_type, output, min_points, scale, quiet):
    """Recompute the strain of a 2-D (specula track) or stereo (specula stereo) result file with
    another window or strain type.

    Everything but the strain is copied unchanged; the new window (grid points) and strain type
    are recorded in the settings as strain_window and strain_type.
    """
    from dic._strain import strain_type_label
    from dic.postprocess import recompute_strain
    from dic.store import ResultReader

    if in_px and in_grid:  # one unit for one number: the last one given must not silently win
        raise click.UsageError("--px and --grid-points exclude each other: give the unit of --window once")
    if not np.isfinite(window):
        raise click.BadParameter(f"must be a finite number, got {window}", param_hint="--window")
    if not in_px:
        if window != int(window):
            raise click.BadParameter(f"a window in grid points must be an odd integer >= 3, got {window:g}",
                                     param_hint="--window")
        window = int(window)
    try:
        path = recompute_strain(results, output, window=window, unit="px" if in_px else "grid",
                                min_points=min_points, scale=scale, strain_type=strain_type)
    except ValueError as exc:
        raise click.ClickException(_with_options(str(exc))) from None
    if not quiet:
        with ResultReader(path) as r:  # one frame at a time
            n = r.settings.get("strain_window")
            label = strain_type_label(r.settings.get("strain_type"))
            names = ("strain_valid", "exx") if r.kind.name == "stereo" else ("strain/valid", "strain/exx")
            for i in r.done_frames():  # only the two datasets the line needs
                valid, exx = r.frame_arrays(i, names)
                ok = np.asarray(valid, bool)
                exx = np.asarray(exx)[ok]
                click.echo(f"{r.kind.frame_noun} {i}: strain at {int(ok.sum())}/{ok.size} points, "
                           f"{label} exx mean {_fmt(exx.mean()) if exx.size else 'nan'}")
        click.echo(f"strain window {n} grid points, {label} strain; results: {path}")


@click.command(name="extensometer", context_settings=CONTEXT)
@click.argument("results", type=RESULTS)
@click.option("--from", "start", required=True, type=POINT, help="First gauge end x,y (reference position).")
@click.option("--to", "end", required=True, type=POINT, help="Second gauge end x,y (reference position).")
@_AT
@_SCALE
@_FRAMES
@_CSV
@_PLOT
@click.option("-q", "--quiet", is_flag=True, help="Do not print the table.")
def extensometer(results, start, end, at, scale, frames, csv_path, plot_path, quiet):
    """A virtual extensometer: gauge length, length change and strain per frame.

    The displacement at each gauge end is interpolated in the grid cell of points that contains
    it, from the cell's corners when they are valid in the frame (never across a hole, an
    excluded region or invalid points); strain = (length - length0) / length0. A gauge end with
    no value in any frame (outside the grid, in a hole, among invalid points) is an error that
    says why; frames with no value are NaN, with a warning.
    """
    from dic.postprocess import extensometer as run

    ext = _run(run, results, start, end, at=at, frames=_frames(frames), scale=scale)
    for what, point, status in (("gauge start", ext.start, ext.start_status), ("gauge end", ext.end, ext.end_status)):
        if np.all(status != 0):
            _check_point(what, point, at, ext.frames, status)
    names, table = ext.table()
    _outputs(csv_path, plot_path, names, table, "write_extensometer_figure", ext, quiet)
    for what, point, status in (("gauge start", ext.start, ext.start_status), ("gauge end", ext.end, ext.end_status)):
        _check_point(what, point, at, ext.frames, status)


@click.command(name="history", context_settings=CONTEXT)
@click.argument("results", type=RESULTS)
@click.option("--point", required=True, type=POINT, help="Reference position x,y.")
@click.option("--quantity", default=None,
              help="u, v, magnitude, exx, eyy, exy, Exx, Eyy, Exy, e1, e2, angle, max_shear, von_mises, zncc "
                   "(stereo: U, V, W, magnitude, X, Y, Z, exx, eyy, exy, e1, ...). Default: u (stereo: U).")
@_AT
@_SCALE
@_FRAMES
@_CSV
@_PLOT
@click.option("-q", "--quiet", is_flag=True, help="Do not print the table.")
def history(results, point, quantity, at, scale, frames, csv_path, plot_path, quiet):
    """A quantity at one point over the frames.

    Interpolated in the grid cell of points that contains the point, from the cell's corners
    when they are valid in the frame (never across a hole, an excluded region or invalid
    points). A point with no value in any frame (outside the grid, in a hole, among invalid
    points) is an error that says why; frames with no value are NaN, with a warning.
    """
    from dic.postprocess import point_history

    res, quantity = _load(results, quantity)
    h = _run(point_history, res, point, quantity, at=at, frames=_frames(frames), scale=scale)
    if np.all(h.status != 0):
        _check_point("point", h.point, at, h.frames, h.status)
    names, table = h.table()
    _outputs(csv_path, plot_path, names, table, "write_history_figure", h, quiet)
    _check_point("point", h.point, at, h.frames, h.status)


@click.command(name="profile", context_settings=CONTEXT)
@click.argument("results", type=RESULTS)
@click.option("--from", "start", required=True, type=POINT, help="Start of the line x,y (reference position).")
@click.option("--to", "end", required=True, type=POINT, help="End of the line x,y (reference position).")
@click.option("--quantity", default=None, help="As for specula history. Default: u (stereo: U).")
@click.option("--samples", default=None, type=click.IntRange(min=2, max=100_000),
              help="Points along the line, 2 to 100000 (default: about one per grid step).")
@_AT
@_SCALE
@_FRAMES
@_CSV
@_PLOT
@click.option("-q", "--quiet", is_flag=True, help="Do not print the table.")
def profile(results, start, end, quantity, samples, at, scale, frames, csv_path, plot_path, quiet):
    """A quantity along a line, per frame (one row per frame and sample).

    Samples are interpolated as for specula history; those with no value (in a hole, an excluded
    region, among invalid points, outside the grid) are NaN, with a warning that says where and
    why. A line with no value anywhere in any frame is an error.
    """
    from dic.postprocess import line_profile

    res, quantity = _load(results, quantity)
    p = _run(line_profile, res, start, end, quantity, samples=samples, at=at, frames=_frames(frames),
             scale=scale)
    if np.all(p.status != 0):
        raise click.ClickException(f"no value along the line from {_where(p.start, at)} to {_where(p.end, at)} in "
                                   f"any frame: {'; '.join(_profile_gaps(p, at))}")
    names, table = p.table()
    _outputs(csv_path, plot_path, names, table, "write_profile_figure", p, quiet)
    for clause in _profile_gaps(p, at):
        click.echo(f"Warning: no value {clause}", err=True)


def _profile_gaps(p, at) -> list[str]:
    """Where and why samples of a profile have no value: one clause per reason."""
    from dic.gridinterp import QueryStatus

    clauses = []
    for code in list(QueryStatus)[1:]:
        mask = p.status == code  # (F, n)
        if mask.any():
            cols, rows = np.flatnonzero(mask.any(axis=0)), mask.any(axis=1)
            d = p.distance[cols]
            frames = "every frame" if rows.all() else _frames_text(p.frames[rows])
            clauses.append(f"at {cols.size} of {p.distance.size} samples ({d.min():.4g} to {d.max():.4g} {at} along "
                           f"the line) in {frames}: {code.reason}")
    return clauses
