"""``specula crack``: opening and sliding of declared cracks along their polylines (a 2-D result file)."""
from __future__ import annotations

import csv
from pathlib import Path

import click
import numpy as np


@click.command(name="crack", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("results", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--frame", "frame", default=None, type=click.IntRange(min=0),
              help="Frame to measure  [default: the last finished frame].")
@click.option("--crack", "cracks", multiple=True, metavar="x1,y1,x2,y2,...",
              help="A crack to measure (reference px; repeatable)  [default: the cracks the run declared with --crack].")
@click.option("--spacing", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Distance between stations along the crack, px  [default: the run's grid step].")
@click.option("--radius", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Radius of each side's linear fit around a station, px  [default: 3 x the run's subset].")
@click.option("--gap", default=None, type=click.FloatRange(min=0),
              help="Points closer than this to the crack are left out of the fits, px  [default: half the run's "
                   "subset: the points whose subsets lie wholly on one side].")
@click.option("-o", "--output", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="CSV file: one row per station (crack, arclength, x, y, opening, sliding and their sigmas, px; "
                   "the points in each side's fit).")
@click.option("-q", "--quiet", is_flag=True, help="No table on the terminal.")
def crack(results, frame, cracks, spacing, radius, gap, output, quiet):
    """Opening (normal jump) and sliding (tangential jump) of the displacement across each crack of RESULTS.

    At stations along the polyline, the valid points within --radius on each side (and no nearer the
    crack than --gap) are fitted by a linear field, evaluated on the crack; the jump U+ - U- (positive
    side: the normal (-t_y, t_x) of the direction from the first vertex to the last) projected on the
    normal is the opening, on the tangent the sliding. Sigmas come from the points' sigma_u, sigma_v.
    """
    from dic.cracks import parse_crack
    from dic.postprocess import results_crack_opening

    try:
        given = [parse_crack(t) for t in cracks] or None
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--crack") from None
    try:
        measured = results_crack_opening(results, frame, cracks=given, spacing=spacing, radius=radius, gap=gap)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    names = ["crack"] + [f"{n}_{u}" if u else n for n, u in measured[0].COLUMNS]
    rows = [[k, *row] for k, m in enumerate(measured) for row in m.table()]
    if output is not None:
        from dic.store.files import atomic_output, output_lock

        with output_lock(output, "CSV file"), atomic_output(output) as tmp, open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(names)
            for row in rows:
                w.writerow([int(row[0])] + [repr(float(v)) for v in row[1:-2]] + [int(row[-2]), int(row[-1])])
    if not quiet:
        for k, m in enumerate(measured):
            ok = m.valid
            if ok.any():
                click.echo(f"crack {k}: {int(ok.sum())}/{ok.size} stations, opening {np.mean(m.opening[ok]):.4f} px "
                           f"(range {np.min(m.opening[ok]):.4f} to {np.max(m.opening[ok]):.4f}), sliding "
                           f"{np.mean(m.sliding[ok]):.4f} px (mean), median sigma {np.median(m.sigma_opening[ok]):.4f} px")
            else:
                click.echo(f"crack {k}: no station with enough valid points on both sides within {m.radius:g} px")
        if output is not None:
            click.echo(f"results: {output}")
