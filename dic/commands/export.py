"""``specula export``: a result file as CSV, MATLAB, netCDF, VTK or PLY files that other tools open.

The formats are written by :func:`dic.export.export_results` (pandas, scipy.io, xarray, meshio);
docs/exports.md describes each one.
"""
from __future__ import annotations

from pathlib import Path

import click

_WHAT = {"csv": "CSV file(s), one per frame,", "mat": "MATLAB file", "netcdf": "netCDF file",
         "vtk": "VTK file(s), one per frame, and a ParaView collection",
         "ply": "PLY point cloud(s), one per state,"}


@click.command(name="export", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("results", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-f", "--format", "fmt", required=True, type=click.Choice(["csv", "mat", "netcdf", "vtk", "ply"]),
              help="csv: one CSV per frame (folder); mat: one MATLAB .mat file; netcdf: one netCDF-4 .nc file "
                   "(xarray); vtk: one .vtu per frame and a .pvd collection for ParaView (folder); ply (stereo): one "
                   "binary PLY point cloud per state, valid points only (folder).")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path),
              help="The output: a folder (csv, vtk) or a file (.mat, .nc).")
@click.option("--vtk-kind", default="grid", show_default=True, type=click.Choice(["grid", "points"]),
              help="VTK only: a quad surface over the point grid, or a point cloud.")
@click.option("--deformed", is_flag=True,
              help="VTK and PLY only: place the valid points at their current (deformed) positions.")
@click.option("-q", "--quiet", is_flag=True, help="No summary.")
def export(results, fmt, output, vtk_kind, deformed, quiet):
    """Export RESULTS (a 2-D or stereo result file of specula track / specula stereo).

    Every frame has the same points in every format (NaN where a point is invalid), with the
    names and units of docs/exports.md.

    \b
    specula export run.h5 --format csv -o run_csv/
    specula export run.h5 --format mat -o run.mat
    specula export run.h5 --format netcdf -o run.nc
    specula export run.h5 --format vtk -o run_vtk/
    specula export stereo.h5 --format ply -o stereo_ply/
    """
    from dic.export import export_results

    if vtk_kind != "grid" and fmt != "vtk":
        raise click.UsageError("--vtk-kind applies to --format vtk only")
    if deformed and fmt not in ("vtk", "ply"):
        raise click.UsageError("--deformed applies to --format vtk and ply only")
    try:
        written = export_results(results, fmt, output, kind=vtk_kind, deformed=deformed)
    except (ValueError, OSError) as exc:
        raise click.ClickException(str(exc)) from None
    if not quiet:
        n = len(written) - 1 if fmt == "vtk" else len(written)  # the .pvd is the collection
        click.echo(f"wrote {n} {_WHAT[fmt]} to {output}")
        if fmt == "vtk":
            click.echo(f"ParaView: open {written[-1]}")
