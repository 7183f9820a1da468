"""``specula calibrate``: intrinsics, mirror extrinsics and the stereo rig from images of a phase target.

Walk-through and accuracy: docs/calibration.md. Each subcommand prints a readable report (RMS per
view, parameters ± σ, dropped views and why) and writes its file:

* ``specula calibrate intrinsics --target target.json VIEW... -o camera.json``
* ``specula calibrate mirror --camera camera.json --target target.json VIEW VIEW VIEW... -o pose.json``
* ``specula calibrate stereo --left pose_left.json --right pose_right.json [--far L R] [--check L R] -o rig.json``
* ``specula calibrate stereo --checkerboard --target board.json --left 'L/*.png' --right 'R/*.png' -o rig.json``

A VIEW is one pose of the monitor: a folder holding the N phase-shifted images it recorded (in
display order, natural sort of the file names), or a quoted glob pattern (``'view03/*.tif'``).
"""
from __future__ import annotations

import os
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
@click.option("--figures", "figure_dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Write PNG figures (detected centres per view, a close-up with dot ids, residuals, RMS per view) "
                   "into this folder.")
@click.option("--device", default=None, help="Warp device for the phase demodulation: cpu, cuda, cuda:N.")
@click.option("-q", "--quiet", is_flag=True, help="No per-view progress lines.")
def intrinsics_cmd(views, target_path, output, name, model, dense, dense_spacing, reject, max_view_rms, max_misfit,
                   reject_points, correct_blur,
                   min_modulation, weighting, figure_dir, device, quiet):
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
            max_view_rms=max_view_rms, reject_points=reject_points or None, max_misfit=max_misfit or None,
            dense_spacing=dense_spacing,
            correct_blur=correct_blur, min_modulation=min_modulation, weighting=weighting,
            name=name if name is not None else output.stem, progress=_progress(quiet), device=device)
    except ValueError as exc:
        _fail(exc)
    click.echo(ic.report())
    meta = ic.metadata()
    meta["target"] = os.fspath(target_path)
    ic.camera.save(output, metadata=meta)
    click.echo(f"wrote {output}")
    if figure_dir is not None:
        for p in _intrinsics_figures(ic, figure_dir):
            click.echo(f"wrote {p}")


# -- mirror --------------------------------------------------------------------------------------------
@calibrate.command(name="mirror", epilog=_view_help)
@click.argument("views", nargs=-1, required=True)
@click.option("--camera", "camera_path", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Camera file of this camera (from 'specula calibrate intrinsics').")
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
    from calibration.camera import Camera
    from calibration.pipeline import calibrate_mirror_from_images

    _check_output(output)
    if len(views) < 3:
        raise click.UsageError(f"the mirror calibration needs at least 3 views (mirror tilts), got {len(views)}")
    try:
        cam = Camera.load(camera_path)
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
        for p in _mirror_figures(mc, figure_dir):
            click.echo(f"wrote {p}")


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
              help="With --checkerboard: left camera file (intrinsics held fixed); default: calibrate from the boards.")
@click.option("--right-camera", default=None, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="With --checkerboard: right camera file.")
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
@click.option("--device", default=None, help="Warp device for the phase demodulation.")
def stereo_cmd(left, right, output, far, check, target_path, no_joint, checkerboard, left_camera, right_camera, sigma_px,
               intrinsic_uncertainty, export_opencv, export_dice, export_vic3d, allow_lossy, figure_dir, correct_blur, device):
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
            rig, report, rc = _stereo_checkerboard(left, right, target_path, left_camera, right_camera)
        else:
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
        for p in _stereo_figures(rc, figure_dir):
            click.echo(f"wrote {p}")
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


def _expand(source):
    from calibration.pipeline import list_view_files

    return list_view_files(source)


def _stereo_checkerboard(left, right, target_path, left_camera, right_camera):
    from calibration.camera import Camera
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
    cl = Camera.load(left_camera) if left_camera else None
    cr = Camera.load(right_camera) if right_camera else None
    cs = stereo_from_checkerboards(lf, rf, board, left_camera=cl, right_camera=cr)
    return cs.rig, cs.report(), None


# -- figures ---------------------------------------------------------------------------------------------
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _label(name: str) -> str:
    """Short label of a view: its folder name (``pose03``), or the last two parts when that is ambiguous (``left``)."""
    parts = [p for p in str(name).replace("\\", "/").rstrip("/").split("/") if p and p != "*" and "*" not in p]
    if not parts:
        return str(name)
    if len(parts) >= 2 and parts[-1] in ("left", "right", "L", "R"):
        return "/".join(parts[-2:])
    return parts[-1]


def _nice_step(x: float) -> float:
    """A round number (1, 2 or 5 × 10^k) close to ``x`` (for arrow keys)."""
    import math

    if not x > 0:
        return 1.0
    e = math.floor(math.log10(x))
    m = x / 10 ** e
    return (1 if m < 1.5 else 2 if m < 3.5 else 5 if m < 7.5 else 10) * 10 ** e


def _residual_arrows(ax, points, residuals, colors, labels, size, title):
    """Residual vectors drawn at their points, magnified so that the 95th percentile is ~5 % of the width,
    with a key arrow of a round length in px."""
    import numpy as np

    w, h = size
    # points not seen in a view are NaN rows: leave them out
    pairs = []
    for pts, r in zip(points, residuals):
        pts, r = np.asarray(pts, dtype=float).reshape(-1, 2), np.asarray(r, dtype=float).reshape(-1, 2)
        ok = np.all(np.isfinite(pts), axis=1) & np.all(np.isfinite(r), axis=1)
        pairs.append((pts[ok], r[ok]))
    allr = np.concatenate([r for _, r in pairs]) if pairs else np.zeros((0, 2))
    p95 = float(np.percentile(np.linalg.norm(allr, axis=1), 95)) if len(allr) else 0.0
    key = _nice_step(p95) if p95 > 0 else 1.0
    scale = 0.05 * w / key
    q = None
    for (pts, r), c, lab in zip(pairs, colors, labels):
        ax.plot(pts[:, 0], pts[:, 1], ".", ms=2, color=c, label=lab)
        q = ax.quiver(pts[:, 0], pts[:, 1], r[:, 0] * scale, r[:, 1] * scale, color=c, angles="xy", scale_units="xy",
                      scale=1, width=0.0025)
    if q is not None:
        ax.quiverkey(q, 0.04, 0.04, key * scale, f"{key:g} px", labelpos="E", coordinates="axes", color="k",
                     fontproperties={"size": 7})
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)
    ax.set_title(title, fontsize=8, loc="left")
    return scale


def view_mosaic(views, path: Path, max_views: int = 16, title: str = "") -> Path:
    """Wrapped phase of each view (subsampled) with the detected dot centres; up to ``max_views`` panels."""
    import math

    import numpy as np

    plt = _plt()
    shown = [v for v in views if v.preview is not None][:max_views]
    if not shown:
        return None
    n = len(shown)
    cols = min(4, n)
    rows = math.ceil(n / cols)
    h, w = shown[0].preview.shape
    fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols, (2.6 * h / w + 0.3) * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, v in zip(axes.ravel(), shown):
        ax.imshow(v.preview, cmap="twilight", interpolation="nearest", vmin=-np.pi, vmax=np.pi)
        ax.add_patch(plt.Rectangle((-0.5, -0.5), w, h, fill=False, lw=0.5, color="0.6"))
        if v.detection is not None:
            q = v.detection.image_points / v.preview_step
            ax.plot(q[:, 0], q[:, 1], "+", color="red", ms=4, mew=0.8)
        state = ("mirrored" if v.mirrored else "direct") if v.ok else "dropped"
        blur = f", blur {v.detection.blur_sigma:.1f} px" if v.detection is not None else ""
        ax.set_title(f"{_label(v.name)} ({state}, {v.n_points} pts{blur})", fontsize=6)
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _first_image(view):
    """The first recorded image of a view given as a folder or glob (None when it cannot be read)."""
    from calibration.pipeline import read_stack

    try:
        return read_stack(view.name)[0]
    except (ValueError, OSError, IndexError):
        return None


def view_detail(views, path: Path, title: str = "") -> Path | None:
    """Close-up of the most blurred direct view and of the first mirrored view: the recorded image
    and the wrapped phase with the detected centres and their ids (the mirrored view's ids follow the
    reflected target). Dots removed for a poor phase fit are listed in the panel title."""
    import numpy as np

    plt = _plt()
    ok = [v for v in views if v.ok and v.detection is not None and v.preview is not None]
    direct = [v for v in ok if not v.mirrored]
    mirrored = [v for v in ok if v.mirrored]
    picks = []
    if direct:
        picks.append(max(direct, key=lambda v: v.detection.blur_sigma))
    if mirrored:  # the one with the most dots removed (it shows why), else the first
        picks.append(max(mirrored, key=lambda v: (len(v.removed) + len(v.vignetted), -mirrored.index(v))))
    if not picks:
        return None
    fig, axes = plt.subplots(len(picks), 2, figsize=(10, 2.9 * len(picks) + 0.4), squeeze=False)
    for (ax_img, ax_ph), v in zip(axes, picks):
        d = v.detection
        q = d.image_points
        # crop: the lit target area (robust bounds of the valid phase, so that dots removed near an edge show too)
        s = v.preview_step
        yy, xx = np.nonzero(np.isfinite(v.preview))
        if len(xx) > 100:
            lo = np.array([np.percentile(xx, 0.5), np.percentile(yy, 0.5)]) * s
            hi = np.array([np.percentile(xx, 99.5), np.percentile(yy, 99.5)]) * s
            pad = 0.03 * (hi - lo)
            (x0, y0), (x1, y1) = np.minimum(lo, q.min(axis=0)) - pad, np.maximum(hi, q.max(axis=0)) + pad
        else:
            (x0, y0), (x1, y1) = q.min(axis=0) - 50, q.max(axis=0) + 50
        W, H = v.image_size
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W - 1), min(y1, H - 1)
        img = _first_image(v)
        if img is not None:
            ax_img.imshow(img, cmap="gray", interpolation="antialiased")
            ax_img.set_title(f"{_label(v.name)}: first recorded image (of the N phase steps)", fontsize=8, loc="left")
        else:
            ax_img.set_title(f"{_label(v.name)}: (image not readable)", fontsize=8, loc="left")
        hp, wp = v.preview.shape
        ax_ph.imshow(v.preview, cmap="twilight", interpolation="nearest", vmin=-np.pi, vmax=np.pi,
                     extent=(-0.5 * s, (wp - 0.5) * s, (hp - 0.5) * s, -0.5 * s))
        ax_ph.plot(q[:, 0], q[:, 1], "+", color="red", ms=7, mew=1.2)
        if len(q) <= 80:
            for (x, y), i in zip(q, d.ids):
                ax_ph.annotate(str(int(i)), (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7,
                               color="k", bbox=dict(boxstyle="round,pad=0.1", fc="white", ec="none", alpha=0.8))
        kind = "mirrored: ids follow the reflected target" if v.mirrored else "direct"
        extra = []
        if v.removed:
            extra.append(f"poor phase fit: {', '.join(str(i) for i, _ in v.removed)}")
        if v.vignetted:
            extra.append(f"vignetted: {', '.join(str(i) for i, _ in v.vignetted)}")
        extra = f"; removed ids ({'; '.join(extra)})" if extra else ""
        ax_ph.set_title(f"wrapped phase, {len(q)} centres ({kind})\nblur σ ≈ {d.blur_sigma:.1f} px{extra}",
                        fontsize=8, loc="left")
        for ax in (ax_img, ax_ph):
            ax.set_xlim(x0, x1)
            ax.set_ylim(y1, y0)
            ax.set_aspect("equal")
            ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _intrinsics_figures(ic, folder: Path) -> list[Path]:
    """Detected centres on the phase maps (all views, and a close-up with ids), residual vectors of
    every kept view in the image, their distribution, and the RMS per view (dropped views in grey)."""
    import numpy as np

    plt = _plt()
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    mosaic = view_mosaic(ic.views, folder / "intrinsics_views.png", title="wrapped phase and detected dot centres")
    if mosaic is not None:
        out.append(mosaic)
    detail = view_detail(ic.views, folder / "intrinsics_detail.png",
                         title="dot centres found in the wrapped phase (defocus-insensitive), with their ids")
    if detail is not None:
        out.append(detail)
    res = ic.result
    size = res.camera.size
    fig, (ax, cx, bx) = plt.subplots(1, 3, figsize=(12, 3.8), gridspec_kw={"width_ratios": [1.45, 0.75, 1.1]})
    colors = ["tab:orange" if ic.views[ic.used[u]].mirrored else "tab:blue" for u in res.view_indices]
    _residual_arrows(ax, [ic.image_points[u] for u in res.view_indices], res.residuals, colors,
                     [None] * len(colors), size, "residual vectors, magnified (blue: direct, orange: mirrored)")
    allr = np.concatenate(res.residuals)
    for r, c in zip(res.residuals, colors):
        cx.plot(r[:, 0], r[:, 1], ".", ms=2.5, color=c)
    lim = 1.15 * float(np.max(np.abs(allr))) if len(allr) else 1.0
    rms1 = float(np.sqrt(np.mean(allr ** 2)))  # per axis
    cx.add_patch(plt.Circle((0, 0), rms1, fill=False, ls="--", color="k", lw=0.8))
    cx.axhline(0, color="0.7", lw=0.5)
    cx.axvline(0, color="0.7", lw=0.5)
    cx.set_xlim(-lim, lim)
    cx.set_ylim(lim, -lim)
    cx.set_aspect("equal")
    cx.tick_params(labelsize=7)
    cx.set_xlabel("residual x (px)", fontsize=7)
    cx.set_ylabel("residual y (px)", fontsize=7)
    cx.set_title(f"residuals; circle: RMS per axis {rms1:.4f} px", fontsize=8, loc="left")
    # RMS per view in input order; views dropped by the outlier rejection in grey
    rms_of = {int(u): float(r) for u, r in zip(res.view_indices, res.per_view_rms)}
    drop_of = {int(d.index): d for d in res.dropped}
    names, vals, cols, hatches = [], [], [], []
    for u, vi in enumerate(ic.used):
        v = ic.views[vi]
        names.append(_label(v.name))
        if u in rms_of:
            vals.append(rms_of[u])
            cols.append("tab:orange" if v.mirrored else "tab:blue")
            hatches.append("")
        else:
            vals.append(drop_of[u].rms if u in drop_of else 0.0)
            cols.append("0.75")
            hatches.append("//")
    bars = bx.bar(range(len(names)), vals, color=cols)
    for b, hh in zip(bars, hatches):
        b.set_hatch(hh)
    med = float(np.median(res.per_view_rms))
    bx.axhline(med, color="k", ls="--", lw=0.7)
    bx.text(len(names) - 0.5, med, f" median {med:.4f}", fontsize=6, va="bottom", ha="right")
    bx.set_xticks(range(len(names)))
    bx.set_xticklabels(names, rotation=90, fontsize=6)
    bx.tick_params(axis="y", labelsize=7)
    bx.set_ylabel("RMS (px)", fontsize=7)
    nd = len(drop_of)
    bx.set_title(f"RMS per view (all {res.rms:.4f} px" + (f"; {nd} dropped, grey)" if nd else ")"), fontsize=8,
                 loc="left")
    fig.tight_layout()
    p = folder / "intrinsics_residuals.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return out + [p]


def _mirror_figures(mc, folder: Path) -> list[Path]:
    """Mirrored views with their centres, and the residuals of the bundle adjustment per mirror tilt."""
    plt = _plt()
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    mosaic = view_mosaic(mc.views, folder / "mirror_views.png", title="mirrored views: wrapped phase and dot centres")
    if mosaic is not None:
        out.append(mosaic)
    r = mc.result
    fig, ax = plt.subplots(figsize=(6.4, 4.9))
    labels = [f"{_label(mc.names[j])}: RMS {r.per_mirror_rms[j]:.4f} px" for j in range(len(mc.names))]
    _residual_arrows(ax, mc.mirrored_points, r.residuals, [f"C{j}" for j in range(len(mc.names))], labels,
                     r.camera.size, f"{r.camera.name or 'camera'}: mirrored dots and residuals (magnified) after the "
                                    f"bundle adjustment;\nRMS {r.rms:.4f} px (closed form alone {r.closed_form_rms:.4f} px)")
    ax.legend(fontsize=7, loc="lower right", markerscale=3)
    fig.tight_layout()
    p = folder / "mirror_residuals.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return out + [p]


def _joint_residuals(rc):
    """Per-point residuals (px) of the joint adjustment, recomputed from its solution:
    ``{"left": [(label, points, residuals)...], "right": [...]}`` (mirror tilts, then far views)."""
    import numpy as np

    j = rc.joint
    rig = j.rig
    out = {"left": [], "right": []}
    common = np.intersect1d(rc.left.point_ids, rc.right.point_ids)
    for side, mc, mirrors in (("left", rc.left, j.mirrors_left), ("right", rc.right, j.mirrors_right)):
        pos = {int(d): n for n, d in enumerate(mc.point_ids)}
        idx = [pos[int(i)] for i in common]
        X = mc.object_points[idx]
        P = X @ j.R_left_target.T + j.t_left_target
        if side == "right":
            P = P @ rig.R_right_left.T + rig.t_right_left
        for nm, q, m in zip(mc.names, mc.mirrored_points, mirrors):
            qo = q[idx]
            out[side].append((_label(nm), qo, mc.camera.project(m.reflect(P)) - qo))
    for fv, (R, t) in zip(rc.far_views, j.far_poses_left):
        P = fv.object_points @ np.asarray(R).T + t
        out["left"].append((fv.name or "far", fv.left_points, rig.left.project(P) - fv.left_points))
        Pr = P @ rig.R_right_left.T + rig.t_right_left
        out["right"].append((fv.name or "far", fv.right_points, rig.right.project(Pr) - fv.right_points))
    return out


def _stereo_figures(rc, folder: Path) -> list[Path]:
    """Residuals of the joint adjustment in both cameras (mirror tilts and far views), and the check views'
    triangulation: reprojection residuals and the errors of the distances between adjacent dots."""
    import numpy as np

    plt = _plt()
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    groups = _joint_residuals(rc) if rc.joint is not None else None
    if groups is not None:
        # the residuals are recomputed here: draw them only if they reproduce the adjustment's RMS
        for side in ("left", "right"):
            r = np.concatenate([r for _, _, r in groups[side][:len(rc.left.names if side == "left" else rc.right.names)]])
            want = rc.joint.rms_groups.get(f"{side}_mirrored")
            got = float(np.sqrt(np.nanmean(np.sum(r ** 2, axis=1))))
            if want is None or not abs(got - want) <= 1e-3 * want + 1e-9:
                click.echo(f"note: no stereo_residuals.png (recomputed {side} RMS {got:.4g} px differs from the "
                           f"adjustment's {want})", err=True)
                groups = None
                break
    if groups is not None:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.3))
        for ax, side in zip(axes, ("left", "right")):
            items = groups[side]
            labels = [f"{nm}: {np.sqrt(np.nanmean(np.sum(r ** 2, axis=1))):.4f} px" for nm, _, r in items]
            cols = [f"C{k}" for k in range(len(items))]
            cam = rc.rig.left if side == "left" else rc.rig.right
            _residual_arrows(ax, [p for _, p, _ in items], [r for _, _, r in items], cols, labels, cam.size,
                             f"{side} camera: residuals (magnified) of the joint adjustment")
            ax.legend(fontsize=6.5, loc="lower right", markerscale=3)
        fig.tight_layout()
        p = folder / "stereo_residuals.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        out.append(p)
    if rc.checks:
        out.extend(_check_figures(list(zip(rc.check_views, rc.checks)), folder, rig=rc.rig))
    return out


def _check_figures(checks, folder: Path, rig=None) -> list[Path]:
    """Check views: errors of the distances between adjacent dots (and, with ``rig``, the reprojection
    residuals of the triangulated dots in both cameras)."""
    import numpy as np

    plt = _plt()
    folder.mkdir(parents=True, exist_ok=True)
    ncol = 3 if rig is not None else 1
    fig, axes = plt.subplots(1, ncol, figsize=(4.2 * ncol, 3.4), squeeze=False,
                             gridspec_kw={"width_ratios": [1.0] + [1.2] * (ncol - 1)})
    ax = axes[0, 0]
    for k, (view, rec) in enumerate(checks):
        e = np.asarray(rec.neighbour_errors)
        ax.plot(np.full(len(e), k) + np.linspace(-0.2, 0.2, len(e)), e, "o", ms=3)
        ax.annotate(f"RMS {np.sqrt(np.mean(e ** 2)):.3f} mm\nscale {rec.mean_relative_error * 100:+.3f} %", (k, 0.97),
                    xycoords=("data", "axes fraction"), fontsize=6, va="top", ha="center")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xticks(range(len(checks)))
    ax.set_xticklabels([v.name for v, _ in checks], fontsize=7)
    ax.tick_params(axis="y", labelsize=7)
    ax.set_xlim(-0.7, len(checks) - 0.3)
    lo, hi = ax.get_ylim()
    ax.set_ylim(lo, hi + 0.35 * (hi - lo))
    ax.set_ylabel("measured − true distance (mm)", fontsize=7)
    ax.set_title("check views: distance between adjacent dots", fontsize=8, loc="left")
    if rig is not None:
        for ax, side in zip(axes[0, 1:], ("left", "right")):
            pts, res, labels = [], [], []
            for view, rec in checks:
                pl, pr = rig.project(rec.points)
                q = view.left_points if side == "left" else view.right_points
                r = (pl if side == "left" else pr) - q
                pts.append(q)
                res.append(r)
                labels.append(f"{view.name}: {np.sqrt(np.nanmean(np.sum(r ** 2, axis=1))):.4f} px")
            cam = rig.left if side == "left" else rig.right
            _residual_arrows(ax, pts, res, [f"C{k}" for k in range(len(pts))], labels, cam.size,
                             f"{side}: reprojection of the triangulated dots")
            ax.legend(fontsize=6.5, loc="best", markerscale=3)
    fig.tight_layout()
    p = folder / "stereo_check.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return [p]
