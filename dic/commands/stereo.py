"""``specula stereo``: stereo DIC of a reference image pair and any number of later pairs.

Results go to an HDF5 file (layout: docs/results_format.md), one group per state,
flushed as each state finishes; rerunning the same command resumes after the last finished one.
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
from .track import _parse_cracks


def _single_image(path) -> bool:
    """Whether a command-line input names one image file (not a folder, pattern, video or multi-page TIFF)."""
    from dic.sources import is_single_image

    return is_single_image(path)


#: name parts that tell a left view from a right one, tried in this order (case-insensitive)
_SIDE_TOKENS = (("left", "right"), ("cam0", "cam1"), ("cam1", "cam2"), ("_l", "_r"), ("l_", "r_"))


def _one_input_hint(path) -> str:
    """For a single IMAGES input that holds one sequence (a folder, a pattern, a video): how to give the two views.
    A folder whose image names tell left from right (``left``/``right``, ``cam0``/``cam1``, ``_L``/``_R``, ...)
    gets the --left/--right glob patterns that split it."""
    import os

    from dic.sources import IMAGE_SUFFIXES

    if _single_image(path):
        return ": one image; give its right partner after it"
    generic = ("; a folder, pattern or video holds one view's sequence: give the left and right sequences as two "
               "inputs, or with --left and --right")
    if not os.path.isdir(path):
        return generic
    names = [n for n in sorted(os.listdir(path)) if n.lower().endswith(IMAGE_SUFFIXES)]
    for left, right in _SIDE_TOKENS:
        n_left = sum(left in n.lower() and right not in n.lower() for n in names)
        n_right = sum(right in n.lower() and left not in n.lower() for n in names)
        if n_left and n_right:
            def pattern(token):  # the token as the first name that has it spells it
                name = next(n for n in names if token in n.lower())
                at = name.lower().index(token)
                return "'" + os.path.join(path, f"*{name[at:at + len(token)]}*") + "'"
            return (f"; {path} holds both views ({n_left} image(s) named with {left!r}, {n_right} with {right!r}): "
                    f"give them with --left {pattern(left)} --right {pattern(right)} (quoted glob patterns)")
    return generic


class _LazyImage:
    """One frame of a source, read when the engine asks for its pixels (``np.asarray``)."""

    def __init__(self, source, index: int):
        self.source, self.index = source, index

    def __array__(self, dtype=None, copy=None):
        import numpy as np

        image = self.source[self.index].image
        return image if dtype is None else np.asarray(image, dtype=dtype)


def _engine_pairs(pairs) -> list:
    """The (left, right) items of every state for stereo_sequence: the image files when the frames are files
    (as before), else frames read on demand."""
    sides = []
    for src in (pairs.left, pairs.right):
        files = src.files
        sides.append(files if files is not None else [_LazyImage(src, k) for k in range(len(src))])
    return list(zip(*sides))


@click.command(name="stereo", context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--rig", "rig_path", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Stereo rig file: Specula JSON (from 'specula calibrate'), OpenCV YAML/XML, VIC-3D XML or DICe XML "
                   "(the format is read from the content).")
@click.argument("images", nargs=-1)
@click.option("--left", "left_inputs", multiple=True,
              help="Left images instead of IMAGES: a folder, a quoted glob pattern, a multi-page TIFF, a video or an "
                   "image file (repeat the option to join several); needs --right with as many frames.")
@click.option("--right", "right_inputs", multiple=True, help="Right images, as --left.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="HDF5 result file (.h5); an existing compatible file is resumed.")
@click.option("--step", default=None, type=click.IntRange(min=1),
              help="Grid spacing of the points of interest, px  [default: subset // 2, 10 for --subset 21].")
@click.option("--subset", default=21, show_default=True, type=int, help="Square subset side in px (odd).")
@click.option("--order", default="1", show_default=True, type=click.Choice(["1", "2"]),
              help="Shape function: 1 (affine; the more accurate on measured stereo data, docs/stereo.md "
                   "'Defaults') or 2 (quadratic: large subsets on strongly curved or non-uniform fields).")
@region_options
@click.option("--frame", default="left", show_default=True, type=click.Choice(["left", "plane"]),
              help="Output coordinates: left camera frame, or the best-fit plane of the reference shape.")
@click.option("--epipolar-tol", default=1.0, show_default=True, type=click.FloatRange(min=0, min_open=True),
              help="Matches farther than this from their epipolar line (px) are flagged.")
@click.option("--zncc-min", default=0.8, show_default=True, type=click.FloatRange(-1, 1),
              help="Matches and tracks with a lower ZNCC are flagged.")
@click.option("--strain-window", default=5, show_default=True, type=click.IntRange(min=3),
              help="Strain fit window in grid points (odd).")
@click.option("--noise-sigma", default=None, type=click.FloatRange(min=0, min_open=True, max=1e6),
              help="Image noise std in grey levels (at most 1e6), for the per-point uncertainty of the match and the "
                   "tracks and its propagation to X, Y, Z and U, V, W (sigma_X ... sigma_W, mm; default: estimated "
                   "from the correlation residuals of each stage).")
@click.option("--robust", is_flag=True,
              help="Outlier-robust correlation (Tukey-weighted IC-GN) of every match and track: pixels whose texture "
                   "changed or differs between the views (glints, flaking paint) do not bias them; several times slower "
                   "(= --robust-mode on).")
@click.option("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present).")
@click.option("--vtk", "vtk_dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Also write ParaView files into this folder as each state finishes: <output>_<index>.vtu per "
                   "state (every point at its reference position, NaN where invalid) and the <output>.pvd collection.")
@click.option("--figures", "figure_dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Also write PNG maps (depth, displacements, strains, status) per state into this folder, as each "
                   "state finishes.")
@click.option("--figure-limits", default="frame", show_default=True, type=click.Choice(["frame", "sequence"]),
              help="Colour range of the figures: per state, or one range per quantity over the whole sequence "
                   "(figures drawn once the run ends; signed quantities are centred on zero either way).")
@click.option("--figure-every", default=1, show_default=True, type=click.IntRange(min=1),
              help="With --figures: draw every Nth state only (state 0, N, 2N, ...).")
@click.option("--reference", "reference_strategy", default="fixed", show_default=True,
              metavar="fixed|incremental|every:N|auto",
              help="What the left and right tracks of each state start from: the reference pair (fixed), the previous "
                   "pair (incremental), a new pair every N states (every:N), or a new one when the valid fraction or "
                   "the median track ZNCC drops below 0.95 (auto). The left-right match is done once; results are "
                   "always relative to the reference state.")
@dask_options("state")
@compression_option("array")
@click.option("--overwrite", is_flag=True, help="Start the output afresh instead of resuming it.")
@click.option("--allow-empty", is_flag=True,
              help="Exit with status 0 even when no state of the run has a valid point (by default that is an error: "
                   "a swapped or foreign rig, or images that do not match).")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar or summary.")
@click.option("--subset-mask", default="region", show_default=True, type=click.Choice(["region", "none"]),
              help="region: with --mask or --roi-polygon, the left reference's subsets are correlated on the pixels "
                   "inside the region only (the match and the left track; holes, free edges); none: on all pixels.")
@click.option("--min-kept-fraction", default=0.5, show_default=True, type=click.FloatRange(min=0, min_open=True, max=1),
              help="A masked subset keeping fewer than this fraction of its pixels is not correlated (TOO_FEW_PIXELS).")
@click.option("--strain-type", default="green-lagrange", show_default=True,
              type=click.Choice(["green-lagrange", "small", "euler-almansi"], case_sensitive=False),
              help="What the surface strain exx, eyy, exy is: Green-Lagrange (zero for rigid motions; VIC-3D's "
                   "default), small (engineering) or Euler-Almansi; stored in the file.")
@robust_mode_option("matches and tracks", default="off")
@click.option("--verify-composed/--no-verify-composed", default=None,
              help="With a moved --reference: check each state's composed left and right tracks against the reference "
                   "pair (ZNCC of each camera's reference subset and the state's image at the composed warp); points "
                   "below --verify-zncc in either camera are not valid (status COMPOSED_MISMATCH) and are counted per "
                   "state. Default: on with a moved reference.")
@click.option("--verify-zncc", default=None, type=click.FloatRange(min=-1.0, max=1.0),
              help="With --verify-composed: the ZNCC below which a composed track fails (default 0.95, as 2-D).")
@click.option("--right-track-mask/--no-right-track-mask", default=True, show_default=True,
              help="With --subset-mask region and --mask or --roi-polygon: the right camera's temporal track "
                   "correlates the pixels of its subsets that the region maps to through the stereo match.")
@click.option("--crack", "cracks", multiple=True, metavar="x1,y1,x2,y2,...",
              help="A declared crack: a polyline in LEFT reference-image px (repeat for several). No subset (left, or "
                   "right through the stereo match) or surface-strain window reaches across it; stored in the file.")
@click.option("--verify-spread", default=None, metavar="K|off",
              help="With --verify-composed: each camera's threshold of a state is the lower of --verify-zncc and its "
                   "checked tracks' median ZNCC less K robust standard deviations (1.4826 MAD), as 2-D; 'off': "
                   "--verify-zncc alone. Default 4.")
@click.option("--motion-prediction", type=click.Choice(["velocity", "none"]), default=None,
              help="How each state's temporal tracks start: 'velocity' extrapolates the two states before at constant "
                   "velocity (fewer IC-GN iterations on smooth motion; when that start accepts under 95 % of the "
                   "points the state before had - a jump - it starts again from the previous state plus the global "
                   "shift); 'none': the previous state plus the global shift. Default: 'velocity' for a new file; a "
                   "resumed file keeps its own (files written before this option: 'none').")
def stereo(rig_path, images, left_inputs, right_inputs, output, step, subset, order, roi, roi_polygon, mask, exclude, frame, epipolar_tol, zncc_min,
           strain_window, noise_sigma, robust, device, vtk_dir, figure_dir, figure_limits, figure_every, reference_strategy, scheduler, workers,
           compression, overwrite, allow_empty, quiet, subset_mask, min_kept_fraction, strain_type, robust_mode,
           verify_composed, verify_zncc, right_track_mask, cracks, verify_spread, motion_prediction):
    """Stereo DIC of image pairs: IMAGES are LEFT RIGHT [LEFT RIGHT ...] (TIFF, PNG or BMP).

    The left and right sequences can also be given as two inputs, IMAGES = LEFT_SEQUENCE
    RIGHT_SEQUENCE, or with --left and --right: each a folder (natural order), a quoted glob
    pattern ('left/*.tif'), a multi-page TIFF or a video, with as many frames on each side.

    The first pair is the reference state (state 0: the shape); later pairs are states 1, 2, ...
    (shape, 3-D displacement and surface strain). Coordinates are in mm. A region of interest
    (--roi, --roi-polygon or --mask, less any --exclude shapes) is given in the left reference image:
    the grid points outside it are kept in the file and flagged NOT_COMPUTED.
    """

    check_dask(scheduler, workers)
    from dic.sequence import parse_reference, read_stereo, stereo_sequence
    from dic.sources import open_inputs, open_pairs

    try:
        parse_reference(reference_strategy)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--reference") from None
    if left_inputs or right_inputs:
        if images:
            raise click.UsageError("give the images either as IMAGES or with --left and --right, not both")
        if not (left_inputs and right_inputs):
            raise click.UsageError("--left and --right go together: give both")
    elif not images:
        raise click.UsageError("give the images: LEFT RIGHT [LEFT RIGHT ...], two sequences (folders, patterns, "
                               "videos, multi-page TIFFs) or --left and --right")
    elif len(images) == 2 and not all(_single_image(p) for p in images):
        left_inputs, right_inputs = (images[0],), (images[1],)  # two sequences
    elif len(images) < 2 or len(images) % 2:
        hint = _one_input_hint(images[0]) if len(images) == 1 else ""
        raise click.BadParameter(f"give the images as LEFT RIGHT pairs (an even number, at least 2); got {len(images)}"
                                 + hint, param_hint="IMAGES")
    if verify_zncc is not None and verify_composed is False:
        raise click.BadParameter("--verify-zncc cannot act with --no-verify-composed", param_hint="--verify-zncc")
    if verify_spread is not None and verify_composed is False:
        raise click.BadParameter("--verify-spread cannot act with --no-verify-composed", param_hint="--verify-spread")
    verify_spread = parse_verify_spread(verify_spread)
    if subset < 5 or subset % 2 == 0:
        raise click.BadParameter(f"the subset must be an odd number of px >= 5, got {subset}", param_hint="--subset")
    if strain_window % 2 == 0:
        raise click.BadParameter(f"must be an odd number >= 3, got {strain_window}", param_hint="--strain-window")
    if output.suffix.lower() not in (".h5", ".hdf5"):
        raise click.BadParameter(f"the output must be an HDF5 file ending in .h5, got {output.name}", param_hint="--output")
    region = parse_region(roi, roi_polygon, mask, exclude)
    try:
        if left_inputs:
            sources = open_pairs(open_inputs(left_inputs), open_inputs(right_inputs))
        else:
            sources = open_pairs([(images[i], images[i + 1]) for i in range(0, len(images), 2)])
        # every frame's size before any work (headers only): a long run should not stop at its last pair
        sources.check_shapes()
        first_left = sources.left[0]
        size = first_left.image.shape
        sources.right[0]  # a missing or unreadable right reference image: one clear error now
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    from dic._stereo import as_rig, check_rig_images
    from dic.correlation.points import region as check_region

    try:  # any calibration format; the images' size stands in where the file records none
        rig = as_rig(rig_path, image_size=(size[1], size[0]))
    except ValueError as exc:
        msg = str(exc)  # name the file once
        raise click.ClickException(msg if str(rig_path) in msg else f"rig file {rig_path}: {msg}") from None
    try:
        check_rig_images(rig, size)
    except ValueError as exc:
        raise click.ClickException(f"{rig_path} does not fit {first_left.name}: {exc}") from None
    pairs = _engine_pairs(sources)
    # the run record (dic.sequence.options): the same as stereo_sequence builds from the same keywords
    from dic.sequence.options import OptionError, StereoOptions

    try:
        region = None if region is None else check_region(region, size)
        record = StereoOptions(step=step, subset=subset, order=int(order), frame=frame, epipolar_tol_px=epipolar_tol,
                               zncc_min=zncc_min, strain_window=strain_window, roi=region,
                               robust=robust_value(robust, robust_mode, default="off"),
                               noise_sigma=noise_sigma,
                               reference=reference_strategy, subset_mask=subset_mask,
                               min_kept_fraction=min_kept_fraction, strain_type=strain_type,
                               verify_composed=verify_composed, verify_zncc=verify_zncc,
                               right_track_mask=right_track_mask, cracks=_parse_cracks(cracks),
                               verify_spread=verify_spread, motion_prediction=motion_prediction)
    except OptionError as exc:
        raise click.BadParameter(str(exc), param_hint=StereoOptions.CLI_NAMES.get(exc.option, exc.option)) from None
    except ValueError as exc:  # the region does not fit the images
        raise click.ClickException(str(exc)) from None
    options = {**record.correlation_kwargs(), "verify_composed": record.verify_composed}
    written = []  # a state finished (the callback): finished states are in the file

    def after(index, field, strain):
        written[:] = [index]

    streamed_figures = figure_dir if figure_limits == "frame" else None  # "sequence": drawn at the end
    try:
        with report_interrupt(output, "state"), dask_client(scheduler, workers) as client:
            summary = stereo_sequence(rig, pairs, output, reference=reference_strategy,
                                      mode="overwrite" if overwrite else "resume", progress=not quiet,
                                      callback=after, vtk_dir=vtk_dir, vtk_stem=output.stem,
                                      figure_dir=streamed_figures, figure_every=figure_every, device=device,
                                      client=client, compression=compression, **options)
    except ValueError as exc:
        raise click.ClickException(f"{exc}" + (f"; finished states are saved in {output}" if written else "")) from None
    if figure_dir is not None and figure_limits == "sequence":
        from dic.plots.fields import FIGURE_QUANTITIES, sequence_limits, write_figures

        results = read_stereo(output)
        fields = [results.fields[i] for i in results.indices]
        moving = [q for q in FIGURE_QUANTITIES if q not in ("X", "Y", "Z", "status")]
        limits = sequence_limits([f for f in fields if f.index > 0], moving)
        for f in fields:
            if f.index % figure_every == 0:
                write_figures(f, first_left.image, figure_dir, prefix=f"state_{f.index:06d}_", limits=limits,
                              region=region, cracks=_parse_cracks(cracks))
    if not quiet:
        if vtk_dir is not None and (vtk_dir / f"{output.stem}.pvd").exists():
            click.echo(f"ParaView: {vtk_dir / f'{output.stem}.pvd'}")
        if figure_dir is not None:
            click.echo(f"figures: {figure_dir}")
        for index, n_valid, n, ref_index, n_mismatch in zip(summary.indices, summary.n_valid, summary.n_points,
                                                            summary.reference_indices, summary.n_mismatch):
            ref_note = f" (reference: state {ref_index})" if ref_index else ""
            if record.verify_composed and ref_index:
                ref_note += f", {n_mismatch} failed the check against the reference pair"
            click.echo(f"state {index}: {n_valid}/{n} valid points in the region{ref_note}")
        if record.verify_composed:
            checked = sum(1 for r in summary.reference_indices if r)
            click.echo(f"composed tracks checked against the reference pair in {checked} state(s): "
                       f"{int(summary.n_mismatch.sum())} point(s) failed (ZNCC < {record.verify_zncc:g})")
        skipped = len(pairs) - len(summary)
        if skipped:
            click.echo(f"{skipped} state(s) were already in {output} and were skipped")
        from dic._strain import strain_type_label

        click.echo(f"strain: {strain_type_label(strain_type)} surface strain, window {strain_window} grid points")
        click.echo(f"results: {output}")
    if len(summary) and not allow_empty and not any(summary.n_valid):
        raise click.ClickException(
            f"no state of this run has a valid point ({len(summary)} state(s) written to {output}): are the left and "
            f"right images swapped, or is {rig_path} the rig of another setup? (--allow-empty accepts such a run)")
