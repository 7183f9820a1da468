"""``specula calibrate``: intrinsics, mirror extrinsics and the stereo rig from images of a phase target.

Walk-through and accuracy: docs/calibration.md. Each subcommand prints a readable report (RMS per
view, parameters ± σ, dropped views and why) and writes its file:

* ``specula calibrate intrinsics --target target.json VIEW... -o camera.json``
* ``specula calibrate mirror --camera camera.json --target target.json VIEW VIEW VIEW... -o pose.json``
* ``specula calibrate stereo --left pose_left.json --right pose_right.json [--far L R] [--check L R] -o rig.json``
* ``specula calibrate stereo --checkerboard --target board.json --left 'L/*.png' --right 'R/*.png' -o rig.json``
* ``specula calibrate verify --rig rig.json --target target.json LEFT_VIEW RIGHT_VIEW [--ids A,B] [--distance MM]``

A VIEW is one pose of the monitor: a folder holding the N phase-shifted images it recorded (in
display order, natural sort of the file names), or a quoted glob pattern (``'view03/*.tif'``).
``--figures DIR`` figures are drawn by :mod:`dic.plots.calibration`.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import click

_MODELS = ("none", "radial1", "radial2", "radial3", "radial2+tangential", "opencv5", "rational")


@click.group(name="calibrate", context_settings={"help_option_names": ["-h", "--help"]})
def calibrate():
    """Calibrate intrinsics, mirror extrinsics or a stereo rig from images of a phase target (docs/calibration.md)."""


# -- helpers -----------------------------------------------------------------------------------------
def _load_phase_target(path):
    from calibration.targets import PhaseTarget, load_target

    tgt = load_target(os.fspath(path))
    if not isinstance(tgt, PhaseTarget):
        raise ValueError(f"{path} describes a {type(tgt).__name__}; this command needs a phase target "
                         "(written by 'specula target fringes')")
    return tgt


def _progress(quiet):
    if quiet:
        return None

    def show(i, res):
        click.echo(f"  [{i + 1}] {res.summary()}", err=True)

    return show


def _fail(exc):
    raise click.ClickException(str(exc)) from None


def _echo_written(paths):
    for p in paths:
        click.echo(f"wrote {p}")


def _check_output(path: Path, suffixes=(".json",)):
    if path.suffix.lower() not in suffixes:
        raise click.BadParameter(f"the output must be a {' or '.join(suffixes)} file, got {path.name!r}",
                                 param_hint="'-o'")
    if path.parent and not path.parent.exists():
        raise click.BadParameter(f"the folder {str(path.parent)!r} does not exist", param_hint="'-o'")


_view_help = "VIEW: a folder of the N phase-shifted images of one pose, or a quoted glob ('v3/*.png')."


# -- intrinsics --------------------------------------------------------------------------------------
@calibrate.command(name="intrinsics", epilog=_view_help)
@click.argument("views", nargs=-1, required=True)
@click.option("--target", "target_path", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Target file (target.json from 'specula target fringes').")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Camera file to write (.json).")
@click.option("--name", default=None, help="Camera name stored in the file (default: the output file's stem).")
@click.option("--model", default="opencv5", show_default=True, type=click.Choice(_MODELS),
              help="Distortion model: opencv5 = k1 k2 p1 p2 k3; radial3 for VIC-3D export.")
@click.option("--dense", is_flag=True, help="The views hold the dense sequence (linear fringes), not the dots.")
@click.option("--dense-spacing", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Dense mode: spacing of the screen-point grid located in each view, screen px (default: pitch / 4).")
@click.option("--reject", default=3.0, show_default=True, type=click.FloatRange(min=0),
              help="Drop views whose RMS exceeds this multiple of the median view RMS (0: keep all).")
@click.option("--max-view-rms", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Also drop views whose RMS exceeds this many px.")
@click.option("--reject-mad", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Also drop views whose RMS exceeds median + K x 1.4826 x MAD of the view RMS (robust z-score K, e.g. 5).")
@click.option("--max-misfit", default=1.5, show_default=True, type=click.FloatRange(min=0),
              help="Remove dots whose phase-fit residual x modulation exceeds this multiple of the view's median (0: keep all).")
@click.option("--reject-points", default=4.0, show_default=True, type=click.FloatRange(min=0),
              help="Remove points whose residual exceeds this multiple of the robust RMS, then recalibrate (0: keep all).")
@click.option("--blur-correction/--no-blur-correction", "correct_blur", default=None,
              help="Run (or skip) the dot detector's defocus-bias correction (default: the detector's default).")
@click.option("--min-modulation", default=3.0, show_default=True, type=click.FloatRange(min=0),
              help="Ignore pixels whose fringe modulation is below this (grey levels).")
@click.option("--weighting", default="equal", show_default=True, type=click.Choice(["equal", "per_view"]),
              help="per_view: weight each view by its estimated point noise (views blurred to different degrees).")
@click.option("--leave-out", "leave_out", default=None, type=click.IntRange(min=1),
              help="Leave-p-out stability test: re-solve with P views left out (every subset, or random ones) and "
                   "report the spread (std, max deviation) of each parameter.")
@click.option("--leave-out-subsets", default=50, show_default=True, type=click.IntRange(min=2),
              help="With --leave-out: at most this many subsets; above, random subsets drawn with --seed.")
@click.option("--seed", default=0, show_default=True, type=int, help="With --leave-out: seed of the random subsets.")
@click.option("--figures", "figure_dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Write PNG figures (detected centres per view, a close-up with dot ids, residuals, RMS per view) "
                   "into this folder.")
@click.option("--device", default=None, help="Warp device for the phase demodulation: cpu, cuda, cuda:N.")
@click.option("-q", "--quiet", is_flag=True, help="No per-view progress lines.")
def intrinsics_cmd(views, target_path, output, name, model, dense, dense_spacing, reject, max_view_rms, reject_mad,
                   max_misfit,
                   reject_points, correct_blur,
                   min_modulation, weighting, leave_out, leave_out_subsets, seed, figure_dir, device, quiet):
    """Intrinsics of one camera from VIEWS of the phase target (direct and mirrored views together).

    Show the target's images on the monitor at many poses through the camera's depth of field (near
    and blurred is fine; tilt it up to ~30-40 degrees) and through the mirror(s); record the N images
    of each pose into one folder per pose. Writes the camera file with the report in its metadata.
    """
    from calibration.pipeline import calibrate_intrinsics_from_images

    _check_output(output)
    try:
        target = _load_phase_target(target_path)
        if not quiet:
            click.echo(f"{len(views)} views of {target!r}", err=True)
        ic = calibrate_intrinsics_from_images(
            list(views), target, mode="dense" if dense else "dots", model=model, reject=reject or None,
            max_view_rms=max_view_rms, reject_mad=reject_mad, reject_points=reject_points or None, max_misfit=max_misfit or None,
            dense_spacing=dense_spacing,
            correct_blur=correct_blur, min_modulation=min_modulation, weighting=weighting,
            name=name if name is not None else output.stem, progress=_progress(quiet), device=device)
        stability = None
        if leave_out is not None:
            from calibration.stability import intrinsics_stability

            res = ic.result
            stability = intrinsics_stability([ic.object_points[u] for u in res.view_indices],
                                             [ic.image_points[u] for u in res.view_indices], ic.camera.size,
                                             mirrored=list(res.mirrored), p=leave_out, model=model,
                                             weighting=weighting, max_subsets=leave_out_subsets, seed=seed,
                                             view_names=[ic.views[ic.used[u]].name for u in res.view_indices])
    except ValueError as exc:
        _fail(exc)
    click.echo(ic.report())
    meta = ic.metadata()
    if stability is not None:
        click.echo(stability.report())
        meta["stability"] = stability.to_dict()
    meta["target"] = os.fspath(target_path)
    ic.camera.save(output, metadata=meta)
    click.echo(f"wrote {output}")
    if figure_dir is not None:
        from dic.plots.calibration import write_intrinsics_figures

        _echo_written(write_intrinsics_figures(ic, figure_dir))


# -- mirror --------------------------------------------------------------------------------------------
@calibrate.command(name="mirror", epilog=_view_help)
@click.argument("views", nargs=-1, required=True)
@click.option("--camera", "camera_path", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Camera file of this camera (from 'specula calibrate intrinsics', or OpenCV YAML/XML; "
                   "the format is read from the content).")
@click.option("--target", "target_path", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Target file (target.json).")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Pose file to write (.json): camera pose relative to the monitor, mirror planes, observations.")
@click.option("--dense", is_flag=True, help="The views hold the dense sequence (linear fringes).")
@click.option("--dense-spacing", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Dense mode: spacing of the common screen-point grid, screen px (default: half the dot pitch).")
@click.option("--sigma-px", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Image noise (px) for the covariance (default: from the residuals).")
@click.option("--max-misfit", default=1.5, show_default=True, type=click.FloatRange(min=0),
              help="Remove dots whose phase-fit residual x modulation exceeds this multiple of the view's median (0: keep all).")
@click.option("--reject-points", default=4.0, show_default=True, type=click.FloatRange(min=0),
              help="Remove target points whose residual in any view exceeds this multiple of the robust RMS (0: keep all).")
@click.option("--blur-correction/--no-blur-correction", "correct_blur", default=None,
              help="Run (or skip) the dot detector's defocus-bias correction (default: the detector's default).")
@click.option("--min-modulation", default=3.0, show_default=True, type=click.FloatRange(min=0),
              help="Ignore pixels whose fringe modulation is below this (grey levels).")
@click.option("--figures", "figure_dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Write PNG figures (mirrored views with their centres, residuals per mirror tilt) into this folder.")
@click.option("--device", default=None, help="Warp device for the phase demodulation.")
@click.option("-q", "--quiet", is_flag=True, help="No per-view progress lines.")
def mirror_cmd(views, camera_path, target_path, output, dense, dense_spacing, sigma_px, max_misfit, reject_points,
               correct_blur, min_modulation, figure_dir, device, quiet):
    """Pose of a camera relative to the monitor from VIEWS of it in a mirror at 3 or more tilts.

    The monitor stays put behind the cameras; the mirror in front of the camera is tilted about two
    different axes between the views (paper Step 2). Run it once per camera with the monitor in the
    same place, then 'specula calibrate stereo --left ... --right ...'.
    """
    from calibration.formats import load_camera
    from calibration.pipeline import calibrate_mirror_from_images

    _check_output(output)
    if len(views) < 3:
        raise click.UsageError(f"the mirror calibration needs at least 3 views (mirror tilts), got {len(views)}")
    try:
        cam = load_camera(camera_path)
        target = _load_phase_target(target_path)
        mc = calibrate_mirror_from_images(cam, list(views), target, mode="dense" if dense else "dots",
                                          dense_spacing=dense_spacing, sigma_px=sigma_px, correct_blur=correct_blur,
                                          reject_points=reject_points or None, max_misfit=max_misfit or None,
                                          min_modulation=min_modulation,
                                          progress=_progress(quiet), device=device)
    except ValueError as exc:
        _fail(exc)
    click.echo(mc.report())
    mc.save(output)
    click.echo(f"wrote {output}")
    if figure_dir is not None:
        from dic.plots.calibration import write_mirror_figures

        _echo_written(write_mirror_figures(mc, figure_dir))


# -- stereo ----------------------------------------------------------------------------------------------
@calibrate.command(name="stereo")
@click.option("--left", "left", required=True,
              help="Left pose file (from 'calibrate mirror'); with --checkerboard: folder or quoted glob of left images.")
@click.option("--right", "right", required=True,
              help="Right pose file; with --checkerboard: folder or quoted glob of right images (paired in sorted order).")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path), help="Rig file to write (.json).")
@click.option("--far", "far", nargs=2, multiple=True, metavar="LEFT_VIEW RIGHT_VIEW",
              help="A view of the target both cameras see directly (repeatable); joins the joint adjustment.")
@click.option("--check", "check", nargs=2, multiple=True, metavar="LEFT_VIEW RIGHT_VIEW",
              help="A view both cameras see, reconstructed as a check of the result (repeatable, not used to fit).")
@click.option("--target", "target_path", default=None, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Target of the --far/--check views (default: the target stored in the left pose file); "
                   "with --checkerboard, the checkerboard file.")
@click.option("--no-joint", is_flag=True, help="Only compose the two mirror calibrations (the paper's method); "
                                               "--far views are then ignored.")
@click.option("--checkerboard", is_flag=True, help="Conventional calibration (cv2.stereoCalibrate) from checkerboard pairs.")
@click.option("--left-camera", default=None, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="With --checkerboard: left camera file (intrinsics held fixed; any calibration format, a rig file "
                   "gives its left camera); default: calibrate from the boards.")
@click.option("--right-camera", default=None, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="With --checkerboard: right camera file (a rig file gives its right camera).")
@click.option("--sigma-px", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Image noise (px) for the rig covariance (default: from the residuals).")
@click.option("--intrinsic-uncertainty/--no-intrinsic-uncertainty", default=True,
              help="Mirror mode: add both cameras' intrinsic uncertainty (stored in the pose files' cameras) to the "
                   "rig covariance by re-solving the rig with the intrinsics moved by ±1σ (default: on; it "
                   "dominates the rotation σ when the far view pins the rig).")
@click.option("--export-opencv", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the rig as OpenCV FileStorage (.yml/.yaml/.xml).")
@click.option("--export-dice", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the rig as a DICe camera-system XML.")
@click.option("--export-vic3d", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the rig as a VIC-3D calibration XML (radial k1 k2 k3 only: calibrate the intrinsics "
                   "with --model radial3, or pass --allow-lossy).")
@click.option("--allow-lossy", is_flag=True,
              help="VIC-3D export: drop the tangential/rational distortion terms VIC-3D cannot hold instead of refusing.")
@click.option("--figures", "figure_dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Write PNG figures (residuals of the joint adjustment in both cameras; check views: "
                   "dot-distance errors and reprojection residuals) into this folder.")
@click.option("--blur-correction/--no-blur-correction", "correct_blur", default=None,
              help="Run (or skip) the dot detector's defocus-bias correction on --far/--check views.")
@click.option("--leave-out", "leave_out", default=None, type=click.IntRange(min=1),
              help="With --checkerboard: leave-p-out stability test of the rig (intrinsics held): re-solve with P "
                   "pairs left out and report the spread of the rotation angles, translation and baseline.")
@click.option("--leave-out-subsets", default=50, show_default=True, type=click.IntRange(min=2),
              help="With --leave-out: at most this many subsets; above, random subsets drawn with --seed.")
@click.option("--seed", default=0, show_default=True, type=int, help="With --leave-out: seed of the random subsets.")
@click.option("--device", default=None, help="Warp device for the phase demodulation.")
def stereo_cmd(left, right, output, far, check, target_path, no_joint, checkerboard, left_camera, right_camera, sigma_px,
               intrinsic_uncertainty, export_opencv, export_dice, export_vic3d, allow_lossy, figure_dir, correct_blur, device,
               leave_out, leave_out_subsets, seed):
    """The stereo rig, from the two cameras' mirror calibrations (pose files) or from checkerboard pairs.

    Mirror mode: the rig is R_right_left = R_right_target R_left_target^T (paper Section 2); with
    --far views (the monitor where both cameras see it, e.g. at the working distance) both cameras'
    mirror views and the far views are adjusted jointly, which pins the rig rotation. --check views
    are triangulated with the result and their dot distances compared with the target's.
    """
    _check_output(output)
    try:
        if checkerboard:
            if far or check:
                raise click.UsageError("--far/--check are for the mirror mode; with --checkerboard every pair is used")
            rig, report, rc = _stereo_checkerboard(left, right, target_path, left_camera, right_camera,
                                                   leave_out, leave_out_subsets, seed)
        else:
            if leave_out is not None:
                raise click.UsageError("--leave-out goes with --checkerboard (the pairs it leaves out); for the "
                                       "intrinsics use 'calibrate intrinsics --leave-out'")
            if left_camera or right_camera:
                raise click.UsageError("--left-camera/--right-camera go with --checkerboard; pose files carry their camera")
            rig, report, rc = _stereo_mirror(left, right, far, check, target_path, no_joint, sigma_px, correct_blur, device,
                                             intrinsic_uncertainty)
    except ValueError as exc:
        _fail(exc)
    click.echo(report)
    rig.save(output)
    click.echo(f"wrote {output}")
    from calibration import formats

    failed = []  # an export that cannot be written does not stop the others, nor the figures
    for path, save in ((export_opencv, formats.save_opencv), (export_dice, formats.save_dice_xml),
                       (export_vic3d, lambda p, r: formats.save_vic3d_xml(p, r, allow_lossy=allow_lossy))):
        if path is None:
            continue
        try:
            save(path, rig)
            click.echo(f"wrote {path}")
        except (ValueError, OSError) as exc:
            hint = (" (on the command line: 'specula calibrate intrinsics --model radial3', or --allow-lossy here)"
                    if "allow_lossy" in str(exc) else "")
            failed.append(f"{path}: {exc}{hint}")
    if figure_dir is not None and rc is not None:
        from dic.plots.calibration import FigureSkipped, write_rig_figures

        with warnings.catch_warnings(record=True) as caught:  # a figure left out is a note, not a failure
            warnings.simplefilter("always")
            paths = write_rig_figures(rc, figure_dir)
        for w in caught:
            if issubclass(w.category, FigureSkipped):
                click.echo(f"note: {w.message}", err=True)
            else:  # any other warning goes on as it would have
                warnings.showwarning(w.message, w.category, w.filename, w.lineno)
        _echo_written(paths)
    if failed:
        raise click.ClickException("not written: " + "; ".join(failed))


def _stereo_mirror(left, right, far, check, target_path, no_joint, sigma_px, correct_blur, device,
                   intrinsic_uncertainty=True):
    from calibration.pipeline import MirrorCalibration, calibrate_rig_from_mirrors, detect_stereo_view
    from calibration.targets import PhaseTarget

    for nm, p in (("--left", left), ("--right", right)):
        if not os.path.isfile(p):
            raise ValueError(f"{nm} {p!r} is not a file; give the pose files written by 'specula calibrate mirror' "
                             "(or add --checkerboard for image folders)")
    ml = MirrorCalibration.load(left)
    mr = MirrorCalibration.load(right)
    target = None
    if far or check:
        if target_path is not None:
            target = _load_phase_target(target_path)
        elif ml.target is not None:
            target = PhaseTarget.from_dict(ml.target)
        else:
            raise ValueError("--far/--check views need the target: pass --target target.json")
    far_views = [detect_stereo_view(a, b, target, name=f"far {i + 1}", correct_blur=correct_blur, device=device)
                 for i, (a, b) in enumerate(far)]
    check_views = [detect_stereo_view(a, b, target, name=f"check {i + 1}", correct_blur=correct_blur, device=device)
                   for i, (a, b) in enumerate(check)]
    rc = calibrate_rig_from_mirrors(ml, mr, far_views=[] if no_joint else far_views, check_views=check_views,
                                    joint=not no_joint, sigma_px=sigma_px, intrinsic_uncertainty=intrinsic_uncertainty)
    report = "\n".join([ml.report(), mr.report(), rc.report()])
    return rc.rig, report, rc


# -- verify ----------------------------------------------------------------------------------------------
@calibrate.command(name="verify")
@click.argument("views", nargs=-1)
@click.option("--rig", "rig_path", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Rig file (from 'calibrate stereo', or OpenCV/VIC-3D/DICe; the format is read from the content).")
@click.option("--target", "target_path", default=None, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Target file of the views (target.json); needed with LEFT_VIEW RIGHT_VIEW.")
@click.option("--ids", default=None, metavar="A,B",
              help="The two target point ids to measure (default: the two common points farthest apart).")
@click.option("--distance", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Known distance between the two points, mm (default with views: from the target file).")
@click.option("--point", "points", nargs=4, type=float, multiple=True, metavar="XL YL XR YR",
              help="Instead of views: one point in the left and the right image, px (give it twice; needs --distance).")
@click.option("--max-error", default=None, type=click.FloatRange(min=0, min_open=True),
              help="Exit with status 1 when the scale error exceeds this many percent (for scripted checks).")
@click.option("--json", "json_path", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the result as JSON.")
@click.option("--blur-correction/--no-blur-correction", "correct_blur", default=None,
              help="Run (or skip) the dot detector's defocus-bias correction.")
@click.option("--device", default=None, help="Warp device for the phase demodulation.")
def verify_cmd(views, rig_path, target_path, ids, distance, points, max_error, json_path, correct_blur, device):
    """Check a rig's scale with a known distance between two target points seen by both cameras.

    LEFT_VIEW RIGHT_VIEW: the target (phase target, e.g. the monitor) where both cameras see it, away
    from the calibration views; the two points are triangulated with the rig and their distance compared
    with the known one (the target's own pitch, or --distance). Or give the two points' image
    coordinates with --point XL YL XR YR (twice) and --distance. Prints measured, known and the scale
    error in %.
    """
    import json

    from calibration.formats import load_rig
    from calibration.verify import verify_distance, verify_view_distance

    pair = None
    if ids is not None:
        parts = ids.replace(" ", "").split(",")
        try:
            pair = tuple(int(p) for p in parts)
        except ValueError:
            pair = ()
        if len(pair) != 2:
            raise click.BadParameter(f"must be two point ids 'A,B', got {ids!r}", param_hint="'--ids'")
    if points:
        if views:
            raise click.UsageError("give either LEFT_VIEW RIGHT_VIEW or --point (twice), not both")
        if len(points) != 2:
            raise click.UsageError(f"--point must be given twice (the two points), got {len(points)}")
        if distance is None:
            raise click.UsageError("--point needs --distance (the known distance between the two points, mm)")
        if pair is not None:
            raise click.UsageError("--ids goes with views; --point gives the points themselves")
    elif len(views) != 2:
        raise click.UsageError(f"give LEFT_VIEW RIGHT_VIEW (2 views, got {len(views)}) or --point XL YL XR YR twice")
    try:
        rig = load_rig(rig_path)
        if points:
            res = verify_distance(rig, [p[:2] for p in points], [p[2:] for p in points], distance)
        else:
            if target_path is None:
                raise ValueError("LEFT_VIEW RIGHT_VIEW need the target: pass --target target.json")
            from calibration.pipeline import detect_stereo_view

            target = _load_phase_target(target_path)
            sv = detect_stereo_view(views[0], views[1], target, name=f"{views[0]} + {views[1]}",
                                    correct_blur=correct_blur, device=device, min_points=2)
            res = verify_view_distance(rig, sv, ids=pair, known_distance=distance)
    except ValueError as exc:
        _fail(exc)
    click.echo(res.report())
    if json_path is not None:
        json_path.write_text(json.dumps(res.to_dict(), indent=1))
        click.echo(f"wrote {json_path}")
    if max_error is not None and abs(res.scale_error_percent) > max_error:
        raise click.ClickException(f"the scale error {res.scale_error_percent:+.4f} % exceeds --max-error {max_error:g} %")


def _expand(source):
    from calibration.pipeline import list_view_files

    return list_view_files(source)


def _stereo_checkerboard(left, right, target_path, left_camera, right_camera, leave_out=None, leave_out_subsets=50,
                         seed=0):
    from calibration.formats import load_camera
    from calibration.pipeline import stereo_from_checkerboards
    from calibration.targets import CheckerboardTarget, load_target

    if target_path is None:
        raise ValueError("--checkerboard needs --target board.json (a checkerboard target file)")
    board = load_target(os.fspath(target_path))
    if not isinstance(board, CheckerboardTarget):
        raise ValueError(f"{target_path} describes a {type(board).__name__}, not a checkerboard")
    lf, rf = _expand(left), _expand(right)
    if len(lf) != len(rf):
        raise ValueError(f"{len(lf)} left images but {len(rf)} right images; they are paired in sorted order")
    # any calibration format; a rig file gives its left / right camera
    cl = load_camera(left_camera, which="left") if left_camera else None
    cr = load_camera(right_camera, which="right") if right_camera else None
    cs = stereo_from_checkerboards(lf, rf, board, left_camera=cl, right_camera=cr)
    report = cs.report()
    if leave_out is not None:
        from calibration.stability import rig_stability

        st = rig_stability(cs.rig.left, cs.rig.right, cs.object_points, cs.left_points, cs.right_points, p=leave_out,
                           max_subsets=leave_out_subsets, seed=seed, view_names=cs.names)
        report += "\n" + st.report()
        cs.rig.metadata["stability"] = st.to_dict()
    return cs.rig, report, None
