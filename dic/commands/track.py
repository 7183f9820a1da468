"""``specula track``: 2-D DIC of a reference image against one or more current images.

Results go to an HDF5 file (layout: docs/results_format.md), one group per frame, flushed as
each frame finishes; rerunning the same command resumes after the last finished frame.
"""
from __future__ import annotations

from pathlib import Path

import click

from ._compression import compression_option
from ._dask import check as check_dask
from ._dask import dask_client, dask_options
from ._interrupt import report_interrupt
from ._region import parse_region, region_options
from ._robust import robust_mode_option, robust_value
from ._verify import parse_verify_spread


def _fail(exc: Exception) -> click.ClickException:
    return click.ClickException(str(exc))


@click.command(name="track", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("reference")
@click.argument("current", nargs=-1)
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="HDF5 result file (.h5); an existing compatible file is resumed.")
@click.option("--subset", default=21, show_default=True, type=int, help="Square subset side in px (odd).")
@click.option("--step", default=None, type=click.IntRange(min=1),
              help="Grid spacing of the points of interest, px  [default: subset // 2, 10 for --subset 21].")
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
@click.option("--tol", default=None, type=click.FloatRange(min=0, min_open=True, max=0.1),
              help="Convergence threshold on the parameter update norm, px (default 0.001; at most 0.1: a larger one "
                   "stops the iterations before they converge).")
@click.option("--strain-window", default=5, show_default=True, type=click.IntRange(min=0),
              help="Strain fit window in grid points (odd, >= 3); 0 skips strain.")
@click.option("--scale", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Image scale in mm per px, stored with the results (post-processing then gives positions "
                   "and displacements in mm).")
@click.option("--noise-sigma", default=None, type=click.FloatRange(min=0, min_open=True, max=1e6),
              help="Image noise std in grey levels (at most 1e6), for the per-point uncertainty sigma_u, sigma_v "
                   "(default: estimated from the correlation residuals of each frame).")
@click.option("--robust", is_flag=True,
              help="Outlier-robust correlation (Tukey-weighted IC-GN) of every point: subset pixels whose texture changed "
                   "(speckles flaking off or appearing, dust, glints) do not bias the displacement; several times "
                   "slower (= --robust-mode on; the default, adaptive, refines only the subsets that need it).")
@region_options
@click.option("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present).")
@click.option("--figures", "--figure", "figure_dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Also write a displacement/strain figure per frame (PNG) into this folder.")
@click.option("--figure-limits", default="frame", show_default=True, type=click.Choice(["frame", "sequence"]),
              help="Colour range of the --figure maps: per frame, or one range per quantity over every frame of "
                   "the output (figures drawn once the run ends), so frames compare at a glance.")
@click.option("--figure-every", default=1, show_default=True, type=click.IntRange(min=1),
              help="With --figure (per-frame limits): draw every Nth frame only.")
@click.option("--vtk", "vtk_dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Also write frame_<index>.vtu per frame into this folder as it finishes (ParaView; every point "
                   "at its reference position, NaN where invalid).")
@click.option("--reference", "reference_strategy", default="fixed", show_default=True, metavar="fixed|incremental|every:N|auto",
              help="What each frame is correlated against: the reference image (fixed), the previous frame "
                   "(incremental), a new reference every N frames (every:N), or a new one when the valid fraction or "
                   "the median ZNCC drops below 0.95 (auto). Results are always relative to the reference image.")
@click.option("--max-memory", default=None, metavar="SIZE",
              help="Budget for the per-point working data of the correlation: bytes, or with a unit K, M, G (binary, "
                   "e.g. 512M; default: a twelfth of the machine's memory); beyond it the points are prepared and "
                   "tracked in chunks, with the same results.")
@dask_options("frame")
@compression_option("array")
@click.option("--overwrite", is_flag=True, help="Start the output afresh instead of resuming it.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar or summary.")
@click.option("--subset-mask", default="region", show_default=True, type=click.Choice(["region", "none"]),
              help="region: with --mask or --roi-polygon, each subset is correlated on the pixels inside the region "
                   "only (holes, free edges; a box --roi masks no pixel); none: on all its pixels.")
@click.option("--min-kept-fraction", default=0.5, show_default=True, type=click.FloatRange(min=0, min_open=True, max=1),
              help="A masked subset keeping fewer than this fraction of its pixels is not tracked (TOO_FEW_PIXELS).")
# -- crack26: declared cracks
@click.option("--crack", "cracks", multiple=True, metavar="x1,y1,x2,y2,...",
              help="A declared crack: a polyline in reference-image px (repeat for several). No subset, strain window, "
                   "interpolation or figure cell reaches across it; stored in the result file (specula crack measures "
                   "its opening and sliding).")
@click.option("--verify-composed/--no-verify-composed", default=None,
              help="With a moved --reference: check every point of a frame correlated against a moved reference "
                   "against the reference image itself (ZNCC of its reference subset and the frame at the composed "
                   "warp); points below --verify-zncc are not valid (status COMPOSED_MISMATCH) and are counted per "
                   "frame. Default: on (with --scheduler/--workers too).")
@click.option("--verify-zncc", default=None, type=click.FloatRange(min=-1.0, max=1.0),
              help="With --verify-composed: the ZNCC below which a composed point fails (default 0.95: a whole-pixel "
                   "wrong match scores at most 0.92 on a 2 px speckle, a correct warp at least 0.994 at 4 grey levels "
                   "of noise).")
@click.option("--strain-type", default="green-lagrange", show_default=True,
              type=click.Choice(["green-lagrange", "small", "euler-almansi"], case_sensitive=False),
              help="What the strain exx, eyy, exy is: Green-Lagrange (zero for rigid motions; VIC-3D's and DICe's "
                   "default, and stereo's), small (engineering) or Euler-Almansi; stored in the file.")
@click.option("--verify-spread", default=None, metavar="K|off",
              help="With --verify-composed: a frame's threshold is the lower of --verify-zncc and its checked points' "
                   "median ZNCC less K robust standard deviations (1.4826 MAD), so that a texture that changes during "
                   "the test (an evolving speckle) keeps its correct points; 'off': --verify-zncc alone. Default 4.")
@robust_mode_option("the subsets", default="adaptive")
def track(reference, current, output, subset, step, order, search, search_method, max_iter, tol, strain_window,
          scale, noise_sigma, robust, roi, roi_polygon, mask, exclude, device, figure_dir, figure_limits, figure_every, vtk_dir,
          reference_strategy, max_memory, scheduler, workers, compression, overwrite, quiet, subset_mask,
          min_kept_fraction, cracks, verify_composed, verify_zncc, strain_type, verify_spread, robust_mode):
    """Track REFERENCE into each CURRENT image (TIFF, PNG or BMP; grey levels).

    Each argument may also be a folder (its images in natural order), a quoted glob pattern
    ('run/*.tif'), a multi-page TIFF or a video: the arguments, expanded in order, make one
    sequence whose first frame is the reference (so 'specula track film.mp4' tracks every frame
    of the video against its first). Frames are numbered 1, 2, ... in that order; each frame starts from the previous frame's
    result (or from --search). The next frames are read while one is correlated, and finished
    frames are written (with --vtk and --figures files) while the next one is; --reference chooses
    what each frame is correlated against (results are always relative to the reference). Per point the file holds u, v, the shape-function parameters, ZNCC,
    iterations, a status code and a validity flag, plus strain. A region of interest (--roi,
    --roi-polygon or --mask, in the reference image; less any --exclude shapes) keeps only the
    grid points inside it.
    """
    from dic.sequence import parse_reference
    from dic.sources import open_inputs

    budget = _size(max_memory) if max_memory is not None else None
    order = int(order)
    try:
        policy = parse_reference(reference_strategy)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--reference") from None
    if check_dask(scheduler, workers) and policy.kind not in ("fixed", "every"):
        raise click.BadParameter(f"{policy.text!r} cannot be distributed (each frame waits for the one before it); "
                                 "use fixed or every:N with --scheduler/--workers", param_hint="--reference")
    if verify_zncc is not None and verify_composed is False:
        raise click.BadParameter("--verify-zncc cannot act with --no-verify-composed", param_hint="--verify-zncc")
    if verify_spread is not None and verify_composed is False:
        raise click.BadParameter("--verify-spread cannot act with --no-verify-composed", param_hint="--verify-spread")
    verify_spread = parse_verify_spread(verify_spread)
    if verify_composed is None:
        verify_composed = policy.kind != "fixed"  # nothing is composed with the fixed reference
    if subset < 5 or subset % 2 == 0:
        raise click.BadParameter(f"the subset must be an odd number of px >= 5, got {subset}", param_hint="--subset")
    if strain_window and (strain_window < 3 or strain_window % 2 == 0):
        raise click.BadParameter(f"must be 0 or an odd number >= 3, got {strain_window}", param_hint="--strain-window")
    if output.suffix.lower() not in (".h5", ".hdf5"):
        raise click.BadParameter(f"the output must be an HDF5 file ending in .h5, got {output.name}", param_hint="--output")
    region = parse_region(roi, roi_polygon, mask, exclude)
    cracks = _parse_cracks(cracks)
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
    # the run record: the options the library's track_sequence takes (an option left out is the library's default)
    given = {"max_iter": max_iter, "tol": tol, "search_radius": search}
    record = _record(subset=subset, step=step, order=order, search=search_method if search else None,
                     noise_sigma=noise_sigma, robust=robust_value(robust, robust_mode, default="adaptive"), roi=region,
                     strain_window=strain_window,
                     scale_mm_per_px=scale, subset_mask=subset_mask, min_kept_fraction=min_kept_fraction, cracks=cracks,
                     verify_composed=verify_composed, verify_zncc=verify_zncc, strain_type=strain_type,
                     verify_spread=verify_spread, **{k: v for k, v in given.items() if v is not None})
    try:  # the POIs, planned without preparing them (a run over --max-memory prepares them in chunks)
        from dic.correlation.points import grid

        planned = grid(ref.shape, record.step, margin=subset // 2, roi=region)
    except ValueError as exc:
        raise _fail(exc) from None
    if budget is not None:
        _check_budget(budget, max_memory, len(planned), order, ref.shape)
    if strain_window:
        from dic._strain import check_strain_window, grid_layout

        try:
            check_strain_window(strain_window, grid_layout(planned)[1])
        except ValueError as exc:
            raise click.BadParameter(f"{exc} (0 skips strain)", param_hint="--strain-window") from None
    from dic.sequence import track_sequence
    from dic.sequence.track2d import _same_image

    def make_tracker(image, points, carried=None):
        kwargs = record.tracker_kwargs()
        if points is not None:  # a moved reference or a chunk (dic.sequence): these POIs, not the region's grid
            region = kwargs.pop("roi", None)
            kwargs["points"] = points
            if carried is not None:  # a moved reference: its region and cracks carried into its image
                kwargs.pop("cracks", None)
                kwargs.update(carried)
            elif region is not None and _same_image(image, ref):  # a chunk of the reference: its subsets masked
                kwargs["pixel_region"] = region
        return _make_tracker(image, device=device, **kwargs)

    try:
        with report_interrupt(output, "frame"), dask_client(scheduler, workers) as client:
            result = track_sequence(
                ref_frame, _Frames(source), output, reference=reference_strategy,
                mode="overwrite" if overwrite else "resume", progress=not quiet, strain_window=strain_window,
                vtk_dir=vtk_dir, figure_dir=figure_dir if figure_limits == "frame" else None, figure_every=figure_every,
                settings=record, make_tracker=make_tracker, points=planned, order=order,
                max_memory=budget, search=search_method if search else None, client=client, compression=compression,
                verify_composed=verify_composed, verify_zncc=verify_zncc, strain_type=strain_type, device=device,
                verify_spread=verify_spread)
    except ValueError as exc:
        raise _fail(exc) from None
    if figure_dir is not None and figure_limits == "sequence":
        _sequence_figures(output, ref, figure_dir, region, cracks)
    if not quiet:
        for f in result.frames:
            ref_note = f" (reference: frame {f['reference_index']})" if f["reference_index"] else ""
            mismatch = f", {f['n_mismatch']} failed the check against the reference" if verify_composed and \
                f["reference_index"] else ""
            click.echo(f"frame {f['index']}: {f['n_valid']}/{f['n_points']} valid points in the region{mismatch}, "
                       f"{f['seconds']:.2f} s{ref_note}")
        if result.skipped:
            click.echo(f"{result.skipped} frame(s) were already in {output} and were skipped")
        if result.frames:
            click.echo(f"{len(result.frames)} frame(s) in {result.seconds:.1f} s ({result.frames_per_second:.2f} frames/s)")
            if verify_composed:
                from dic.sequence.verification import VERIFY_ZNCC

                verify_threshold = VERIFY_ZNCC if verify_zncc is None else verify_zncc
                checked = int((result.reference_indices != 0).sum())
                click.echo(f"composed results checked against the reference image in {checked} frame(s): "
                           f"{int(result.n_mismatch.sum())} point(s) failed (ZNCC < {verify_threshold:g})")
        if strain_window:
            from dic._strain import strain_type_label

            click.echo(f"strain: {strain_type_label(strain_type)}, window {strain_window} grid points")
        click.echo(f"results: {output}")


class _Frames:
    """The frames after the reference of a :class:`dic.sources.FrameSource`, read lazily (sized)."""

    def __init__(self, source):
        self.source = source

    def __len__(self) -> int:
        return len(self.source) - 1

    def __iter__(self):
        return (frame for frame in self.source if frame.index > 0)


def _size(text: str) -> int:
    """``--max-memory``: bytes, or a number with a binary unit K, M, G (``512M``)."""
    t = str(text).strip().upper().removesuffix("B").removesuffix("I")
    units = {"K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}
    scale = units.get(t[-1:], 1)
    number = t[:-1] if t[-1:] in units else t
    try:
        value = float(number)
    except ValueError:
        value = float("nan")
    if not (value * scale >= 1):
        raise click.BadParameter(f"must be a size in bytes (e.g. 2000000, 512K, 512M, 2G), got {text!r}",
                                 param_hint="--max-memory")
    return int(value * scale)


def _check_budget(budget: int, text: str, n_points: int, order: int, shape) -> None:
    """``--max-memory`` refused below one point's data (:func:`dic.sequence.chunks.check_budget`); below the
    run's working set the library warns (``track_sequence``), printed as a ``Warning:`` line."""
    from dic.sequence.chunks import check_budget

    try:
        check_budget(budget, n_points, order, shape, name=f"--max-memory {text}")
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--max-memory") from None


def _parse_cracks(texts):
    """``--crack`` values -> the cracks (:func:`dic.cracks.parse_crack`), or None without any."""
    from dic.cracks import parse_crack

    out = []
    for text in texts:
        try:
            out.append(parse_crack(text))
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="--crack") from None
    return out or None


def _sequence_figures(output, ref, figure_dir, region=None, cracks=None) -> None:
    """One figure per frame of the result file, with one colour range per quantity over all frames (and
    the region of interest drawn: ``region``, a checked Region or None; declared ``cracks`` drawn)."""
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
                           limits=limits, cracks=cracks, title=f"frame {f.index}: {Path(f.path).name}", region=region)


def _make_tracker(reference, *, device, **options):
    """A :class:`dic.Tracker` of the run record's tracker ``options`` (the reference-side work is done once
    for all frames)."""
    from dic._track import Tracker

    return Tracker(reference, device=device, **options)


def _record(**options):
    """The run record (:class:`dic.sequence.options.TrackOptions`) of the command's options, the same as
    :func:`dic.sequence.track_sequence` builds from the same keywords; a bad value names its option."""
    from dic.sequence.options import OptionError, TrackOptions

    try:
        return TrackOptions(**options)
    except OptionError as exc:
        raise click.BadParameter(str(exc), param_hint=TrackOptions.CLI_NAMES.get(exc.option, exc.option)) from None
