"""Peak memory of a long stereo sequence (issue 23): ``stereo_sequence`` over 100 and 1000 states.

Run from the repository root::

    .venv/bin/python -m bench.stereo_memory [--states 100 1000] [--before /path/to/old/checkout]

Scene: the virtual lab of tests/dic/test_stereo_sequence.py (two 320 x 240 px cameras 300 mm apart,
toed in on a speckled plane 1 m away; 4 samples per pixel, no noise), rendered once: the
reference pair and one pair with the plane translated by (0.5, -0.3, 1.0) mm. The sequence is the
reference pair followed by the moved pair repeated (the same two arrays: the input holds no
memory per state), 2nd-order 21 px subsets on a 16 px grid, ``reference="fixed"``, on the CPU.

Each run is a fresh child process (``--child N``) that reports its peak RSS (``ru_maxrss``), the
RSS it had just before the run (imports, images, Warp modules loaded) and the wall time; the
result file goes to a temporary folder. Target: peak RSS at 1000 states <= 1.1 x at 100 (the 2-D
engine's figure, bench/sequence.py). ``--before PATH`` runs the same children with ``PATH`` first
on ``PYTHONPATH`` (another checkout: the code before the change) and records both.
Writes bench/results/stereo_memory_cpu.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone

import numpy as np

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SIZE = (320, 240)
STEP = 16
SHIFT_MM = (0.5, -0.3, 1.0)


def render_pairs(path: str) -> None:
    """The reference pair and the moved pair of the scene, and the rig, saved to ``path`` (.npz)."""
    from dataclasses import replace

    from dic.lab import Displacement, LabCamera, Scene, SpecklePlane, render, stereo_rig
    from dic.synth import make_speckle

    cams = [LabCamera.from_lens(name=name, size=SIZE, focal_length_mm=12.0, f_number=float("inf"),
                                focus_distance_mm=1000.0, position=(x, 0.0, 0.0), look_at_point=(0.0, 0.0, 1000.0),
                                exposure_dn=200.0, bit_depth=8)
            for name, x in (("left", -150.0), ("right", 150.0))]
    speckle = make_speckle(region=(-5, -5, 305, 255), radius=1.2, density=0.5, bits=None, seed=3)
    plane = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=(300.0, 250.0),
                                speckle=speckle)
    t_local = plane.R_world_surface.T @ np.asarray(SHIFT_MM)
    moved = replace(plane, displacement=Displacement(np.broadcast_to(t_local, (2, 2, 3)).copy(), (0.0, 0.0),
                                                     (300.0, 250.0)))
    pairs = [tuple(render(Scene(cameras=cams, planes=[p]), i, samples=4, seed=7 + i) for i in range(2))
             for p in (plane, moved)]
    left, right = cams
    rig = stereo_rig(left, right)
    rig.save(path + ".rig.json")
    np.savez(path, l0=pairs[0][0], r0=pairs[0][1], l1=pairs[1][0], r1=pairs[1][1])


def child(n_states: int, images: str, folder: str) -> dict:
    """One run of ``n_states`` states in this (fresh) process."""
    import warnings

    from dic.sequence import stereo_sequence

    warnings.simplefilter("ignore")
    data = np.load(images)
    ref, cur = (data["l0"], data["r0"]), (data["l1"], data["r1"])
    pairs = [ref] + [cur] * (n_states - 1)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    out = os.path.join(folder, f"run_{n_states}.h5")
    t0 = time.perf_counter()
    stereo_sequence(images + ".rig.json", pairs, out, step=STEP, device="cpu", mode="overwrite")
    wall = time.perf_counter() - t0
    size = os.path.getsize(out)
    os.remove(out)
    return {"states": n_states, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "rss_before_run_mb": before, "seconds": wall, "seconds_per_state": wall / n_states,
            "results_file_mb": size / 2**20}


def measure(states, images: str, folder: str, code: str | None) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (code or ROOT, env.get("PYTHONPATH", "")) if p)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    env.setdefault("OMP_NUM_THREADS", "1")
    rows = []
    for n in states:
        cmd = [sys.executable, os.path.abspath(__file__), "--child", str(n), "--images", images, "--folder", folder]
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=code or ROOT, env=env)
        if proc.returncode != 0:
            raise RuntimeError(f"the run of {n} states failed:\n{proc.stderr[-3000:]}")
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        print(f"  {n:5d} states: peak RSS {rows[-1]['peak_rss_mb']:.0f} MB (before the run "
              f"{rows[-1]['rss_before_run_mb']:.0f} MB), {rows[-1]['seconds']:.0f} s", flush=True)
    return {"code": code or ROOT, "runs": rows, "peak_ratio": rows[-1]["peak_rss_mb"] / rows[0]["peak_rss_mb"]}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--states", type=int, nargs="+", default=[100, 1000])
    parser.add_argument("--before", default=None, help="another checkout to measure too (the code before)")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--images", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--folder", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child is not None:
        print(json.dumps(child(args.child, args.images, args.folder)))
        return
    with tempfile.TemporaryDirectory(prefix="specula-stereo-memory-") as folder:
        images = os.path.join(folder, "pairs.npz")
        render_pairs(images)
        report = {"benchmark": "stereo_memory", "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                  "machine": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version(),
                  "conditions": {"image_px": list(SIZE), "step_px": STEP, "subset_px": 21, "order": 2,
                                 "reference": "fixed", "device": "cpu", "samples_per_px": 4},
                  "target_peak_ratio": 1.1}
        print("after (this checkout):")
        report["after"] = measure(args.states, images, folder, None)
        if args.before:
            print(f"before ({args.before}):")
            report["before"] = measure(args.states, images, folder, os.path.abspath(args.before))
    os.makedirs(RESULTS, exist_ok=True)
    path = os.path.join(RESULTS, "stereo_memory_cpu.json")
    with open(path, "w") as fh:
        json.dump(report, fh, indent=2)
    for name in ("before", "after"):
        if name in report:
            print(f"{name}: peak ratio {report[name]['peak_ratio']:.3f} (target <= 1.1)")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
