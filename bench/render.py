"""Rendering throughput of the virtual lab (rays per second) on each available device.

    python -m bench.render                    # every device, full resolution, 16 samples per pixel
    python -m bench.render --device cpu --scale 0.5 --samples 16

Scenes (all from ``dic.lab.paper_rig``, left camera, 2352 x 1728 px at scale 1):

* ``mirror``: the calibration view, monitor seen through the tilted mirror (defocused).
* ``direct``: the monitor at the crossing point (position (2, 2, 2)), mirrors removed.
* ``speckle``: a 1.2 m x 0.9 m Boolean-speckle plate (0.5 mm disks, ~1.2 M disks) at the crossing
  point with a 3-D displacement field (bulge + shear), so every ray runs the deformed-surface
  Newton solve and the speckle look-up.

A "ray" is one sub-sample (pixel area x lens aperture); rays/s = W·H·samples / wall time. Kernel
compilation is excluded (a small warm-up render first). Writes bench/results/render_<device>.json.
The development machine is shared (2 cores, several users): CPU figures there are noisy.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np


def _scenes(scale: float):
    from dic.lab import Displacement, SpecklePlane, paper_rig
    from dic.synth import make_speckle

    rig = paper_rig(scale=scale)
    size = (1200.0, 900.0)
    speckle = make_speckle(region=(0.0, 0.0, *size), radius=0.5, density=0.5, radius_spread=0.2, seed=1, blur=0.0)

    def field(X, Y):
        r2 = (X - 600.0) ** 2 + (Y - 450.0) ** 2
        return 1e-3 * (Y - 450.0), 5e-4 * (X - 600.0), -8.0 * np.exp(-r2 / (2 * 250.0**2))

    plate = SpecklePlane.facing(center=rig.crossing_point, normal=(0.0, 0.0, -1.0), size=size, speckle=speckle,
                                displacement=Displacement.from_function(field, (0.0, size[0], 0.0, size[1]), 20.0), name="plate")
    return {
        "mirror": rig.with_mirror_tilt(0),
        "direct": rig.with_monitor_at((2, 2, 2)),
        "speckle": rig.without_mirrors().replace(screens=[], planes=[plate]),
    }


def run(device: str, scale: float, samples: int, repeats: int) -> dict:
    import warp as wp

    from dic.lab import render
    from kernels._launch import cpu_threads

    scenes = _scenes(scale)
    # warm-up: compilation and speckle binning, excluded from the timings
    for scene in scenes.values():
        render(scene.replace(cameras=[scene.cameras[0].scaled(0.125 / scale if scale >= 0.125 else 1.0)]), 0, samples=1, device=device)
    results = {}
    for name, scene in scenes.items():
        cam = scene.cameras[0]
        W, H = cam.size
        walls, cpus = [], []
        for r in range(repeats):
            wp.synchronize_device(device)
            t0, c0 = time.perf_counter(), time.process_time()
            render(scene, 0, samples=samples, seed=r, device=device)
            wp.synchronize_device(device)
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        best = min(walls)
        rays = W * H * samples
        results[name] = {"width": W, "height": H, "samples": samples, "rays": rays, "wall_s": walls, "cpu_s": cpus,
                         "best_wall_s": best, "rays_per_s": rays / best}
        print(f"{device:8s} {name:8s} {W}x{H} x {samples} spp: {best:7.2f} s wall (cpu {min(cpus):.1f} s), "
              f"{rays / best / 1e6:7.2f} Mrays/s", flush=True)
    return {
        "device": device,
        "device_name": str(wp.get_device(device).name) if hasattr(wp.get_device(device), "name") else device,
        "cpu_threads": cpu_threads() if device == "cpu" else None,
        "machine": platform.processor() or platform.machine(),
        "os_cpu_count": os.cpu_count(),
        "versions": {"warp": wp.config.version, "numpy": np.__version__, "python": platform.python_version()},
        "parameters": {"scale": scale, "samples": samples, "repeats": repeats, "camera": "paper_rig left"},
        "note": "wall time excludes kernel compilation; the CPU figures come from a shared 2-core machine "
                "(several users at once), so they are noisy and pessimistic",
        "scenes": results,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", action="append", help="cpu, cuda:0 (repeatable; default: every available device)")
    parser.add_argument("--scale", type=float, default=1.0, help="camera resolution factor (1 = 2352 x 1728)")
    parser.add_argument("--samples", type=int, default=16, help="sub-samples per pixel")
    parser.add_argument("--repeats", type=int, default=1, help="timed renders per scene (best kept)")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    args = parser.parse_args(argv)
    from kernels import available_devices

    devices = args.device or available_devices()
    args.out.mkdir(parents=True, exist_ok=True)
    for device in devices:
        result = run(device, args.scale, args.samples, args.repeats)
        tag = device.replace(":", "")
        path = args.out / f"render_{tag}.json"
        path.write_text(json.dumps(result, indent=2))
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
