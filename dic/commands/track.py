"""``specula track``: 2-D DIC of a reference image against one or more current images.

Results go to an HDF5 file (layout: docs/results_format.md), one group per frame, flushed as
each frame finishes; rerunning the same command resumes after the last finished frame.
"""
from __future__ import annotations

import time
from pathlib import Path

import click
import numpy as np

from ._region import parse_region, region_options


def _fail(exc: Exception) -> click.ClickException:
    return click.ClickException(str(exc))


@click.command(name="track", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("reference")
@click.argument("current", nargs=-1)
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="HDF5 result file (.h5); an existing compatible file is resumed.")
@click.option("--subset", default=21, show_default=True, type=int, help="Square subset side in px (odd).")
@click.option("--step", default=5, show_default=True, type=click.IntRange(min=1), help="Grid spacing of the points of interest, px.")
@click.option("--order", default="1", show_default=True, type=click.Choice(["1", "2"]),
              help="Shape function: 1 (affine, 6 parameters) or 2 (quadratic, 12 parameters).")
@click.option("--search", default=None, type=click.IntRange(min=1, max=2**31 - 1),
              help="Find an integer-pixel initial guess first, for displacements up to this many px "
                   "(needed beyond about a third of the subset; a radius beyond the image is clamped to it).")
@click.option("--search-method", default="pyramid", show_default=True, type=click.Choice(["pyramid", "zncc", "fft", "rg"]),
              help="Initial-guess strategy used with --search: pyramid (coarse-to-fine), zncc (window search "
                   "per point), fft (one global shift), rg (reliability-guided propagation).")
@click.option("--max-iter", default=None, type=click.IntRange(min=1, max=10000),
              help="IC-GN iteration limit per point (at most 10000).")
@click.option("--tol", default=None, type=click.FloatRange(min=0, min_open=True), help="Convergence threshold on the parameter update norm.")
@click.option("--strain-window", default=5, show_default=True, type=click.IntRange(min=0),
              help="Strain fit window in grid points (odd, >= 3); 0 skips strain.")
@click.option("--scale", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Image scale in mm per px, stored with the results (post-processing then gives positions "
                   "and displacements in mm).")
@click.option("--noise-sigma", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Image noise std in grey levels, for the per-point uncertainty sigma_u, sigma_v "
                   "(default: estimated from the correlation residuals of each frame).")
@region_options
@click.option("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present).")
@click.option("--figures", "--figure", "figure_dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Also write a displacement/strain figure per frame (PNG) into this folder.")
@click.option("--figure-limits", default="frame", show_default=True, type=click.Choice(["frame", "sequence"]),
              help="Colour range of the --figure maps: per frame, or one range per quantity over every frame of "
                   "the output (figures drawn once the run ends), so frames compare at a glance.")
@click.option("--overwrite", is_flag=True, help="Start the output afresh instead of resuming it.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar or summary.")
def track(reference, current, output, subset, step, order, search, search_method, max_iter, tol, strain_window,
          scale, noise_sigma, roi, roi_polygon, mask, device, figure_dir, figure_limits, overwrite, quiet):
    """Track REFERENCE into each CURRENT image (TIFF, PNG or BMP; grey levels).

    Each argument may also be a folder (its images in natural order), a quoted glob pattern
    ('run/*.tif'), a multi-page TIFF or a video: the arguments, expanded in order, make one
    sequence whose first frame is the reference (so 'specula track film.mp4' tracks every frame
    of the video against its first). Frames are numbered 1, 2, ... in that order; each frame starts from the previous frame's
    result (or from --search). Per point the file holds u, v, the shape-function parameters, ZNCC,
    iterations, a status code and a validity flag, plus strain. A region of interest (--roi,
    --roi-polygon or --mask, in the reference image) keeps only the grid points inside it.
    """
    from tqdm import tqdm

    from dic.sources import open_inputs
    from dic.store import ResultWriter, image_digest

    order = int(order)
    if subset < 5 or subset % 2 == 0:
        raise click.BadParameter(f"the subset must be an odd number of px >= 5, got {subset}", param_hint="--subset")
    if strain_window and (strain_window < 3 or strain_window % 2 == 0):
        raise click.BadParameter(f"must be 0 or an odd number >= 3, got {strain_window}", param_hint="--strain-window")
    if output.suffix.lower() not in (".h5", ".hdf5"):
        raise click.BadParameter(f"the output must be an HDF5 file ending in .h5, got {output.name}", param_hint="--output")
    region = parse_region(roi, roi_polygon, mask)
    try:
        source = open_inputs([reference, *current])
        n_frames = len(source)
    except ValueError as exc:
        raise _fail(exc) from None
    if n_frames < 2:
        raise click.UsageError(f"{reference} is a single image: give CURRENT images after it (or a folder, quoted "
                               "pattern, multi-page TIFF or video holding the reference and the frames)")
    try:
        source.check_shapes()  # file headers only: a mixed-size sequence is refused before any work
        ref_frame = source[0]
        ref = ref_frame.image
        if region is not None:
            from dic.correlation.points import region as check_region

            region = check_region(region, ref.shape)
    except ValueError as exc:
        raise _fail(exc) from None
    settings = {"subset": subset, "step": step, "order": order, "search": search,
                "search_method": search_method if search else None, "max_iter": max_iter, "tol": tol,
                "strain_window": strain_window}
    if scale is not None:  # only when given, so files written without it still resume
        from dic.postprocess import SCALE_KEY
        from kernels.checks import positive_float

        try:
            settings[SCALE_KEY] = positive_float(scale, "the scale", detail=" (mm per px)")
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="--scale") from None
    if noise_sigma is not None:  # (the key is absent by default, so files of earlier runs still resume)
        settings["noise_sigma"] = noise_sigma
    if region is not None:  # only when given: files written without a region resume as before
        settings["roi"] = region.settings()
    try:
        tracker = _make_tracker(ref, subset=subset, step=step, order=order, search=search,
                                search_method=search_method, max_iter=max_iter, tol=tol, device=device,
                                noise_sigma=noise_sigma, roi=region)
    except ValueError as exc:
        raise _fail(exc) from None
    if strain_window:
        from dic.strain import check_strain_window, grid_layout

        try:
            check_strain_window(strain_window, grid_layout(tracker.points)[1])
        except ValueError as exc:
            raise click.BadParameter(f"{exc} (0 skips strain)", param_hint="--strain-window") from None
    try:
        writer = ResultWriter(output, reference_path=ref_frame.name, reference_shape=ref.shape,
                              reference_sha256=image_digest(ref), settings=settings,
                              mode="overwrite" if overwrite else "resume")
    except ValueError as exc:
        raise _fail(exc) from None

    done_before = 0
    summary = []
    previous = None  # (params, valid) of the last frame: the next frame's initial guess
    with writer, tqdm(total=n_frames - 1, unit="frame", disable=quiet, desc="track") as bar:
        # resuming: every finished frame must have been computed from the image given for it now
        done = [index for index in range(1, n_frames) if writer.is_done(index)]
        if done:
            done_set = set(done)
            try:
                for frame in source:
                    if frame.index in done_set:
                        writer.check_frame(frame.index, frame.name, image_digest(frame.image))
                    if frame.index >= done[-1]:
                        break
            except ValueError as exc:
                raise _fail(exc) from None
        frames = iter(source)
        while True:
            try:
                frame = next(frames)
            except StopIteration:
                break
            except ValueError as exc:  # an unreadable frame (dic.sources.FrameError names it)
                saved = any(writer.is_done(i) for i in range(1, n_frames))
                raise click.ClickException(f"{exc}" + (f"; frames before it are saved in {output}" if saved else "")) \
                    from None
            index, cur_path = frame.index, frame.name
            if index == 0:
                continue
            if writer.is_done(index):
                done_before += 1
                previous = None
                bar.update(1)
                continue
            if previous is None and index > 1 and writer.is_done(index - 1):
                previous = _stored_guess(writer, index - 1)
            t0 = time.perf_counter()
            try:
                cur = frame.image
                field = tracker.track(cur, guess=_guess(previous))
                strain = None
                if strain_window:
                    from dic.strain import strain as compute_strain

                    strain = compute_strain(field, window=strain_window)
            except ValueError as exc:
                raise click.ClickException(
                    f"frame {index} ({cur_path}): {exc}" + (f"; frames before it are saved in {output}" if index > 1 else "")
                ) from None
            seconds = time.perf_counter() - t0
            try:
                writer.write_frame(index, field, strain=strain, path=str(cur_path), sha256=image_digest(cur),
                                   attrs={"seconds": seconds})
            except ValueError as exc:  # dic.store.ResultWriteError (a full disk): says what the file keeps
                raise _fail(exc) from None
            if figure_dir is not None and figure_limits == "frame":
                from dic.plots.fields import write_field_figure

                write_field_figure(figure_dir / f"frame_{index:06d}.png", ref, field, strain,
                                   title=f"frame {index}: {Path(cur_path).name}")
            valid = np.asarray(field.valid, bool)
            previous = (np.asarray(field.params, np.float64), valid)
            summary.append((index, int(valid.sum()), valid.size, seconds))
            bar.update(1)
    if figure_dir is not None and figure_limits == "sequence":
        _sequence_figures(output, ref, figure_dir)
    if not quiet:
        for index, n_valid, n, seconds in summary:
            click.echo(f"frame {index}: {n_valid}/{n} valid points, {seconds:.2f} s")
        if done_before:
            click.echo(f"{done_before} frame(s) were already in {output} and were skipped")
        click.echo(f"results: {output}")


def _sequence_figures(output, ref, figure_dir) -> None:
    """One figure per frame of the result file, with one colour range per quantity over all frames."""
    from dic.plots.fields import sequence_limits, write_field_figure
    from dic.store import read_results

    res = read_results(output)
    frames = [res.frames[i] for i in res.indices]
    if not frames:
        return
    components = ["u", "v"] + (["exx", "eyy", "exy"] if all(f.strain is not None for f in frames) else [])
    limits = sequence_limits(frames, components)
    for f in frames:
        write_field_figure(figure_dir / f"frame_{f.index:06d}.png", ref, f, f.strain, components=components,
                           limits=limits, title=f"frame {f.index}: {Path(f.path).name}")


def _make_tracker(reference, *, subset, step, order, search, search_method, max_iter, tol, device, noise_sigma=None,
                  roi=None):
    """A :class:`dic.track.Tracker` (the reference-side work is done once for all frames)."""
    from dic.track import Tracker

    kwargs = {"step": step, "subset": subset, "order": order, "device": device, "noise_sigma": noise_sigma}
    if roi is not None:
        kwargs["roi"] = roi
    if search is not None:
        kwargs["search"] = search_method
        kwargs["search_radius"] = int(search)
    if max_iter is not None:
        kwargs["max_iter"] = max_iter
    if tol is not None:
        kwargs["tol"] = tol
    return Tracker(reference, **kwargs)


def _guess(previous):
    """Initial parameters from the previous frame: its valid points as they are, the others at
    the mean displacement of the valid ones (None for the first frame or when none is valid)."""
    if previous is None:
        return None
    params, valid = previous
    if not np.any(valid) or params.ndim != 2:
        return None
    guess = params.copy()
    k = params.shape[1]
    guess[~valid] = 0.0
    guess[~valid, 0] = params[valid, 0].mean()
    guess[~valid, k // 2] = params[valid, k // 2].mean()
    return guess


def _stored_guess(writer, index):
    """(params, valid) of a finished frame in the result file (resuming a sequence), or None."""
    stored = writer.frame_arrays(index, ("params", "valid"))
    if stored is None:
        return None
    return np.asarray(stored[0], np.float64), np.asarray(stored[1], bool)
