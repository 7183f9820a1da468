"""``specula lab``: render virtual-lab scenes and write the paper's rig as a scene file."""
from __future__ import annotations

import json
from pathlib import Path

import click


@click.group(name="lab", context_settings={"help_option_names": ["-h", "--help"]})
def lab():
    """Virtual lab: render scenes of cameras, mirrors, monitors and speckle (see docs/lab.md)."""


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name) or "camera"


@lab.command(name="render")
@click.argument("scene", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output folder (created): one TIFF per camera and ground_truth.json.")
@click.option("--camera", "cameras", multiple=True, help="Render only these cameras (name or index; repeatable).")
@click.option("--samples", default=16, show_default=True, type=click.IntRange(1, 4096), help="Sub-samples per pixel (pixel area x lens aperture).")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2**31 - 1), help="Seed of the sampling pattern and the noise.")
@click.option("--no-noise", is_flag=True, help="Switch off shot and read noise.")
@click.option("--float", "as_float", is_flag=True, help="Write float32 grey levels (no quantisation).")
@click.option("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present).")
def render_cmd(scene, out_dir, cameras, samples, seed, no_noise, as_float, device):
    """Render every camera of SCENE (a .toml scene file) into OUT.

    Writes OUT/<camera>.tif (8- or 16-bit, or float32 with --float) and OUT/ground_truth.json with the
    camera models (K, distortion, size), poses, mirror planes (world and each camera's frame) and
    screen poses.
    """
    import tifffile

    from dic.lab import load_scene, render
    from dic.lab.io import file_names
    from kernels._atomic import atomic_output

    try:
        sc = load_scene(scene)
        chosen = [sc.camera(int(c) if c.lstrip("-").isdigit() else c) for c in cameras] if cameras else sc.cameras
        # every camera of the scene, not only the chosen ones: a later run must not overwrite this one's images
        stems = dict(zip((id(c) for c in sc.cameras),
                         file_names([c.name or f"camera{k}" for k, c in enumerate(sc.cameras)], "camera", _safe)))
        if len({id(c) for c in chosen}) != len(chosen):
            raise ValueError("a camera is chosen twice with --camera")
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for i, cam in enumerate(chosen):
        try:
            img = render(sc, cam, samples=samples, seed=seed, noise=not no_noise, quantize=not as_float, device=device)
        except ValueError as exc:
            raise click.ClickException(str(exc)) from None
        path = out_dir / f"{stems[id(cam)]}.tif"
        with atomic_output(path) as tmp:  # whole or not at all
            tifffile.imwrite(tmp, img)
        written.append(path)
        click.echo(f"{path}  {img.shape[1]}x{img.shape[0]} {img.dtype}  mean {float(img.mean()):.2f}")
    truth = sc.ground_truth()
    truth["render"] = {"samples": samples, "seed": seed, "noise": not no_noise, "quantized": not as_float,
                       "images": {(c.name or f"camera{sc.cameras.index(c)}"): p.name for c, p in zip(chosen, written)}}
    with atomic_output(out_dir / "ground_truth.json") as tmp:
        tmp.write_text(json.dumps(truth, indent=2))
    click.echo(f"{out_dir / 'ground_truth.json'}")


@lab.command(name="paper-rig")
@click.option("-o", "--out", "out_path", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Scene file to write (.toml); the monitor image goes beside it.")
@click.option("--scale", default=1.0, show_default=True, type=float, help="Camera resolution factor (0.25: 588x432 px).")
@click.option("--tilt", default="0", show_default=True,
              help="Mirror setting index (see docs/lab.md), or 'none' for no mirrors.")
@click.option("--position", default=None, help="Monitor at test position: index 0..26 or i,j,k (1-based); removes the mirrors.")
@click.option("--no-noise", is_flag=True, help="Cameras without read and shot noise.")
def paper_rig_cmd(out_path, scale, tilt, position, no_noise):
    """Write the paper's stereo rig (two cameras, two mirrors, a monitor) as a scene file."""
    from dic.lab import paper_rig, save_scene

    try:
        mirror_tilt = None if tilt.lower() == "none" else int(tilt)
        pos = None
        if position is not None:
            parts = [int(p) for p in position.replace(" ", "").split(",")]
            pos = parts[0] if len(parts) == 1 else tuple(parts)
        rig = paper_rig(scale=scale, mirror_tilt=mirror_tilt, monitor_position=pos, noise=not no_noise)
        files = save_scene(rig.scene(), out_path)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    for f in files:
        click.echo(str(f))


@lab.command(name="session")
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--scale", default=1.0, show_default=True, type=click.FloatRange(0.05, 1.0),
              help="Camera resolution factor (1: 2352x1728 px; 0.25: 588x432 px, minutes instead of an hour).")
@click.option("--samples", default=16, show_default=True, type=click.IntRange(1, 4096),
              help="Render sub-samples per pixel (pixel area x lens aperture).")
@click.option("--tilts", default=3, show_default=True, type=click.IntRange(3, 5), help="Mirror tilts per camera.")
@click.option("--cache", default=None, type=click.Path(file_okay=False),
              help="Folder for rendered stacks: an interrupted run resumes from it.")
def session_cmd(out_dir, scale, samples, tilts, cache):
    """Render a calibration session of the paper's rig into OUT_DIR (the image folders of a lab session).

    OUT_DIR/fringes/fringes.json (the target), OUT_DIR/{left,right}/intrinsics/pose01..pose12 (direct
    views), OUT_DIR/{left,right}/mirror/tilt1..tiltK (views in the mirror), OUT_DIR/far/{left,right},
    OUT_DIR/check1/{left,right}, OUT_DIR/ground_truth.json (the lab's rig, for comparison): what the
    walk-through of docs/calibration.md calibrates with 'specula calibrate'.
    """
    from dic.lab.session import export_session
    from dic.store.files import output_lock

    try:
        with output_lock(out_dir, "lab session folder"):  # a second session into the same folder is refused
            export_session(str(out_dir), scale=scale, samples=samples, cache=cache, n_tilts=tilts, log=click.echo)
    except (ValueError, OSError) as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"wrote the session to {out_dir}")
