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
@click.option("--figures", "figure_dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Write PNG figures (detected centres per view, residuals) into this folder.")
@click.option("--device", default=None, help="Warp device for the phase demodulation: cpu, cuda, cuda:N.")
@click.option("-q", "--quiet", is_flag=True, help="No per-view progress lines.")
def intrinsics_cmd(views, target_path, output, name, model, dense, dense_spacing, reject, max_view_rms, max_misfit,
                   reject_points, correct_blur,
                   min_modulation, figure_dir, device, quiet):
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
            correct_blur=correct_blur, min_modulation=min_modulation,
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
              help="Write PNG figures (residuals per mirror tilt) into this folder.")
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
@click.option("--export-opencv", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the rig as OpenCV FileStorage (.yml/.yaml/.xml).")
@click.option("--export-dice", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the rig as a DICe camera-system XML.")
@click.option("--export-vic3d", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the rig as a VIC-3D calibration XML (radial k1 k2 k3 only).")
@click.option("--figures", "figure_dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Write PNG figures (check reconstruction errors) into this folder.")
@click.option("--blur-correction/--no-blur-correction", "correct_blur", default=None,
              help="Run (or skip) the dot detector's defocus-bias correction on --far/--check views.")
@click.option("--device", default=None, help="Warp device for the phase demodulation.")
def stereo_cmd(left, right, output, far, check, target_path, no_joint, checkerboard, left_camera, right_camera, sigma_px,
               export_opencv, export_dice, export_vic3d, figure_dir, correct_blur, device):
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
            rig, report, checks = _stereo_checkerboard(left, right, target_path, left_camera, right_camera)
        else:
            if left_camera or right_camera:
                raise click.UsageError("--left-camera/--right-camera go with --checkerboard; pose files carry their camera")
            rig, report, checks = _stereo_mirror(left, right, far, check, target_path, no_joint, sigma_px, correct_blur, device)
    except ValueError as exc:
        _fail(exc)
    click.echo(report)
    rig.save(output)
    click.echo(f"wrote {output}")
    try:
        from calibration import formats

        if export_opencv is not None:
            formats.save_opencv(export_opencv, rig)
            click.echo(f"wrote {export_opencv}")
        if export_dice is not None:
            formats.save_dice_xml(export_dice, rig)
            click.echo(f"wrote {export_dice}")
        if export_vic3d is not None:
            formats.save_vic3d_xml(export_vic3d, rig)
            click.echo(f"wrote {export_vic3d}")
    except ValueError as exc:
        _fail(exc)
    if figure_dir is not None and checks:
        for p in _check_figures(checks, figure_dir):
            click.echo(f"wrote {p}")


def _stereo_mirror(left, right, far, check, target_path, no_joint, sigma_px, correct_blur, device):
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
                                    joint=not no_joint, sigma_px=sigma_px)
    report = "\n".join([ml.report(), mr.report(), rc.report()])
    return rc.rig, report, list(zip(check_views, rc.checks))


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
    return cs.rig, cs.report(), []


# -- figures ---------------------------------------------------------------------------------------------
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


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
        if v.detection is not None:
            q = v.detection.image_points / v.preview_step
            ax.plot(q[:, 0], q[:, 1], "+", color="red", ms=4, mew=0.8)
        label = os.path.basename(v.name.rstrip("/")) or v.name
        state = ("mirrored" if v.mirrored else "direct") if v.ok else "dropped"
        ax.set_title(f"{label} ({state}, {v.n_points})", fontsize=6)
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _intrinsics_figures(ic, folder: Path) -> list[Path]:
    """Detected centres on the phase maps, residual vectors of every kept view in the image, RMS per view."""
    import numpy as np

    plt = _plt()
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    mosaic = view_mosaic(ic.views, folder / "intrinsics_views.png", title="wrapped phase and detected dot centres")
    if mosaic is not None:
        out.append(mosaic)
    res = ic.result
    w, h = res.camera.size
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 3.6), gridspec_kw={"width_ratios": [1.5, 1]})
    allr = np.concatenate(res.residuals)
    scale = 0.25 * w / max(np.percentile(np.linalg.norm(allr, axis=1), 95), 1e-6)
    for u, r in zip(res.view_indices, res.residuals):
        q = ic.image_points[u]
        c = "tab:orange" if ic.views[ic.used[u]].mirrored else "tab:blue"
        ax.quiver(q[:, 0], q[:, 1], r[:, 0] * scale, r[:, 1] * scale, color=c, angles="xy", scale_units="xy", scale=1,
                  width=0.002)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    ax.set_title(f"residuals × {scale:.0f} (blue direct, orange mirrored)", fontsize=9)
    names = [ic.views[ic.used[u]].name for u in res.view_indices]
    colors = ["tab:orange" if m else "tab:blue" for m in res.mirrored]
    bx.bar(range(len(names)), res.per_view_rms, color=colors)
    bx.set_xticks(range(len(names)))
    bx.set_xticklabels([os.path.basename(n.rstrip("/")) for n in names], rotation=90, fontsize=6)
    bx.set_ylabel("RMS (px)")
    bx.set_title(f"RMS per view (all: {res.rms:.4f} px)", fontsize=9)
    fig.tight_layout()
    p = folder / "intrinsics_residuals.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return out + [p]


def _mirror_figures(mc, folder: Path) -> list[Path]:
    import numpy as np

    plt = _plt()
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    mosaic = view_mosaic(mc.views, folder / "mirror_views.png", title="mirrored views: wrapped phase and dot centres")
    if mosaic is not None:
        out.append(mosaic)
    r = mc.result
    w, h = r.camera.size
    fig, ax = plt.subplots(figsize=(6, 4.4))
    allr = np.concatenate(r.residuals)
    scale = 0.2 * w / max(np.percentile(np.linalg.norm(allr, axis=1), 95), 1e-6)
    for j, (q, res) in enumerate(zip(mc.mirrored_points, r.residuals)):
        ax.plot(q[:, 0], q[:, 1], ".", ms=3, color=f"C{j}", label=f"{os.path.basename(mc.names[j].rstrip('/'))}: "
                                                                   f"{r.per_mirror_rms[j]:.4f} px")
        ax.quiver(q[:, 0], q[:, 1], res[:, 0] * scale, res[:, 1] * scale, color=f"C{j}", angles="xy", scale_units="xy",
                  scale=1, width=0.003)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title(f"mirrored dots and residuals × {scale:.0f} after the bundle adjustment", fontsize=9)
    fig.tight_layout()
    p = folder / "mirror_residuals.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return out + [p]


def _check_figures(checks, folder: Path) -> list[Path]:
    import numpy as np

    plt = _plt()
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    fig, ax = plt.subplots(figsize=(6, 3.2))
    for k, (view, rec) in enumerate(checks):
        ax.plot(np.full(len(rec.neighbour_errors), k) + np.linspace(-0.2, 0.2, len(rec.neighbour_errors)),
                rec.neighbour_errors, "o", ms=3)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xticks(range(len(checks)))
    ax.set_xticklabels([v.name for v, _ in checks], fontsize=7)
    ax.set_ylabel("neighbour distance error (mm)")
    ax.set_title("check views: measured − true distance between adjacent dots", fontsize=9)
    fig.tight_layout()
    p = folder / "stereo_check.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths
