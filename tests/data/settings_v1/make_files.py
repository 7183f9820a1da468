"""Make the result files of tests/test_run_options.py with Specula 8d9f975 (settings before the run record).

Run from a checkout of 8d9f975 (not this one): ``PYTHONPATH=<checkout> python make_files.py <out folder>``.
The images are written as PNGs next to the files (8-bit, so they read back identically); the files
hold the first frame/state only, so a test can resume them with one more.

- ``track_cli_v1.h5``: ``specula track ref.png f1.png --step 8 --search 4 --search-method zncc --roi 8 8 90 70``
  (settings of the old command-line form: ``search`` the radius, ``search_method`` the method).
- ``track_lib_v1.h5``: ``track_sequence(ref, [f1], step=8, search="zncc", search_radius=4, roi=(8, 8, 90, 70))``
  (the old library form: only the keywords given, ``search`` the method).
- ``stereo_cli_v1.h5``: ``specula stereo --rig rig.json L0 R0 L1 R1 --step 20``.
- ``stereo_lib_v1.h5``: ``stereo_sequence(rig, [(L0, R0), (L1, R1)], step=20, max_iter=50, reference="incremental")``.
"""
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibration.stereo import StereoRig
from dic.io import write_image
from dic.lab import Displacement, LabCamera, Scene, SpecklePlane, render
from dic.synth import deformed_image, make_speckle

OUT = Path(sys.argv[1])
OUT.mkdir(parents=True, exist_ok=True)
SHAPE = (80, 100)  # 2-D images (H, W) px

# 2-D: a speckle reference and two translated frames
model = make_speckle(SHAPE, radius=2.0, seed=7)
for name, shift in (("ref", None), ("f1", (0.6, -0.3)), ("f2", (1.2, -0.6))):
    write_image(OUT / f"{name}.png", deformed_image(model, SHAPE, shift, seed=1).astype(np.uint8))

# stereo: the virtual lab of tests/test_stereo_dic.py with 128 x 96 px cameras, a plane moved by 0.5 mm per state
W, H = 128, 96
cams = [LabCamera.from_lens(name=n, size=(W, H), focal_length_mm=12.0, f_number=float("inf"), focus_distance_mm=1000.0,
                            position=(x, 0.0, 0.0), look_at_point=(0.0, 0.0, 1000.0), exposure_dn=200.0, bit_depth=8)
        for n, x in (("left", -150.0), ("right", 150.0))]
speckle = make_speckle(region=(-5, -5, 105, 85), radius=0.5, density=0.5, bits=None, seed=3)
plane = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=(100.0, 80.0), speckle=speckle)
for k in range(3):
    t = np.array([0.5 * k, -0.25 * k, 0.0])
    moved = replace(plane, displacement=Displacement(np.broadcast_to(t, (2, 2, 3)).copy(), (0.0, 0.0), (100.0, 80.0)))
    for i, side in enumerate("LR"):
        img = render(Scene(cameras=cams, planes=[moved]), i, samples=4, seed=10 * k + i)
        write_image(OUT / f"{side}{k}.png", np.clip(np.round(img), 0, 255).astype(np.uint8))
left, right = cams
R = right.R_cam_world @ left.R_cam_world.T
StereoRig(left.camera, right.camera, R, right.t_cam_world - R @ left.t_cam_world).save(OUT / "rig.json")

cli = [sys.executable, "-m", "dic.cli"]
p = {k: str(OUT / f"{k}.png") for k in ("ref", "f1", "L0", "R0", "L1", "R1")}
subprocess.run([*cli, "track", p["ref"], p["f1"], "-o", str(OUT / "track_cli_v1.h5"), "--step", "8", "--search", "4",
                "--search-method", "zncc", "--roi", "8", "8", "90", "70", "--device", "cpu", "-q"], check=True)
subprocess.run([*cli, "stereo", "--rig", str(OUT / "rig.json"), p["L0"], p["R0"], p["L1"], p["R1"],
                "-o", str(OUT / "stereo_cli_v1.h5"), "--step", "20", "--device", "cpu", "-q"], check=True)

from dic.sequence import stereo_sequence, track_sequence  # noqa: E402

track_sequence(p["ref"], [p["f1"]], OUT / "track_lib_v1.h5", step=8, search="zncc", search_radius=4,
               roi=(8, 8, 90, 70), device="cpu")
stereo_sequence(OUT / "rig.json", [(p["L0"], p["R0"]), (p["L1"], p["R1"])], OUT / "stereo_lib_v1.h5", step=20,
                max_iter=50, reference="incremental", device="cpu")
