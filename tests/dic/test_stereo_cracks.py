"""Declared cracks in stereo DIC (``StereoCorrelation(cracks=)``, ``stereo_sequence(cracks=)``, ``specula stereo
--crack``; dic.stereo_cracks; issue 26 item 2 on the stereo path), against exact truth.

Scene (the virtual lab, dic.lab): the 320 x 240 px rig of tests/dic/test_stereo_dic.py looking at two speckled
plates 150 x 250 mm side by side at 1000 mm, abutting along the world line x = 0 (a vertical line near the left
image's column 159.5); between the two states the right-hand plate slides by 0.5 mm along y (about 0.8 px in
the images), the other stays: a displacement jump across the line, whose left-image projection is the
declared crack.
"""
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner

from dic._stereo import StereoCorrelation
from dic.lab import Displacement, LabCamera, Scene, SpecklePlane, render, stereo_rig
from dic.synth import make_speckle

T_WORLD = np.array([0.0, 0.5, 0.0])  # mm, the right-hand plate's slide
SUBSET = 21


@pytest.fixture(scope="module")
def jump_lab():
    cams = [LabCamera.from_lens(name=n, size=(320, 240), focal_length_mm=12.0, f_number=float("inf"),
                                focus_distance_mm=1000.0, position=(x, 0.0, 0.0), look_at_point=(0.0, 0.0, 1000.0),
                                exposure_dn=200.0, bit_depth=8)
            for n, x in (("left", -150.0), ("right", 150.0))]

    def plate(cx, seed):
        return SpecklePlane.facing(center=(cx, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=(150.0, 250.0),
                                   speckle=make_speckle(region=(-5, -5, 155, 255), radius=1.2, density=0.5, bits=None,
                                                        seed=seed))

    fixed, sliding = plate(-75.0, 3), plate(75.0, 4)
    t_local = sliding.R_world_surface.T @ T_WORLD
    slid = replace(sliding, displacement=Displacement(np.broadcast_to(t_local, (2, 2, 3)).copy(), (0.0, 0.0),
                                                      (150.0, 250.0)))
    ref = tuple(render(Scene(cameras=cams, planes=[fixed, sliding]), i, samples=16, seed=i) for i in range(2))
    cur = tuple(render(Scene(cameras=cams, planes=[fixed, slid]), i, samples=16, seed=10 + i) for i in range(2))
    left, right = cams
    rig = stereo_rig(left, right)
    crack = left.project(np.array([[0.0, -125.0, 1000.0], [0.0, 125.0, 1000.0]]))  # the line x = 0, left px
    return {"rig": rig, "ref": ref, "cur": cur, "crack": crack, "left": left}


def _measure(lab, cracks):
    sc = StereoCorrelation(lab["rig"], *lab["ref"], step=5, subset=SUBSET, device="cpu", cracks=cracks)
    f = sc.measure(*lab["cur"])
    left = lab["left"]
    world = (np.nan_to_num(f.xyz) - left.t_cam_world) @ left.R_cam_world
    on_sliding = world[:, 0] > 0.0
    exact = np.where(on_sliding[:, None], left.R_cam_world @ T_WORLD, 0.0)  # left camera frame, mm
    a, b = lab["crack"]
    dist_px = np.abs((b - a)[0] * (f.points - a)[:, 1] - (b - a)[1] * (f.points - a)[:, 0]) / np.linalg.norm(b - a)
    return sc, f, np.linalg.norm(f.uvw - exact, axis=1), on_sliding, dist_px


def _rms(e, m):
    return float(np.sqrt(np.mean(e[m] ** 2)))


def test_a_displacement_jump_is_measured_without_smearing(jump_lab):
    """With the crack declared, the points within one subset of it (left image) have the interior's 3-D error
    (RMS within 1.5 x that of the points farther than 1.5 subsets: measured 0.0052 against 0.0057 mm) and the jump
    across it is recovered within 0.01 mm; no surface-strain window reaches across (the strain of these rigid
    motions stays at the interior's level next to it, measured 6.8e-4 against 6.3e-4). Without it the subsets and
    windows straddling the line smear the jump (RMS 0.10 mm near it, strain up to 0.02, measured)."""
    sc, f, err, on_sliding, dist = _measure(jump_lab, [jump_lab["crack"]])
    near, far = f.valid & (dist <= SUBSET), f.valid & (dist > 1.5 * SUBSET)
    assert np.count_nonzero(near) >= 300 and np.count_nonzero(far) >= 1500
    assert np.count_nonzero(near) >= 0.8 * np.count_nonzero(dist <= SUBSET)  # (points on the crack keep one side)
    assert _rms(err, near) <= 1.5 * _rms(err, far), (_rms(err, near), _rms(err, far))
    exact_jump = jump_lab["left"].R_cam_world @ T_WORLD
    jump = f.uvw[near & on_sliding].mean(axis=0) - f.uvw[near & ~on_sliding].mean(axis=0)
    assert np.all(np.abs(jump - exact_jump) < 0.01), (jump, exact_jump)
    strain = np.nanmax(np.abs(np.stack([f.exx, f.eyy, f.exy])), axis=0)
    sv = f.strain_valid
    assert np.count_nonzero(sv & (dist <= SUBSET)) >= 300
    assert np.nanmax(strain[sv & (dist <= SUBSET)]) < 2 * np.nanmax(strain[sv & (dist > 1.5 * SUBSET)])
    assert sc._crack_strain is not None and sc._crack_strain.rows.size > 0
    assert sc.right_pixel_mask is not None  # the right subsets near the crack keep their own side

    sc0, f0, err0, _, _ = _measure(jump_lab, None)  # the problem, shown
    near0 = f0.valid & (dist <= SUBSET)
    assert _rms(err0, near0) > 5 * _rms(err0, f0.valid & (dist > 1.5 * SUBSET))
    strain0 = np.nanmax(np.abs(np.stack([f0.exx, f0.eyy, f0.exy])), axis=0)
    assert np.nanmax(strain0[f0.strain_valid & (dist <= SUBSET)]) > 10 * np.nanmax(strain[sv & (dist > 1.5 * SUBSET)])


def test_cracks_are_stored_and_given_on_the_command_line(jump_lab, tmp_path):
    from dic.cli import main
    from dic.io import write_image
    from dic.sequence import read_stereo, stereo_sequence
    from dic.sequence.options import StereoOptions

    crack = jump_lab["crack"]
    pairs = [jump_lab["ref"], jump_lab["cur"]]
    stereo_sequence(jump_lab["rig"], pairs, tmp_path / "lib.h5", step=10, device="cpu", cracks=[crack])
    res = read_stereo(tmp_path / "lib.h5")
    assert np.allclose(res.settings["cracks"], [crack.tolist()])
    assert StereoOptions.ADDED_OPTIONS["cracks"] is None and StereoOptions().cracks is None
    paths = []
    for k, (a, b) in enumerate(pairs):
        for side, img in (("L", a), ("R", b)):
            paths.append(str(tmp_path / f"{side}{k}.png"))
            write_image(paths[-1], img)
    jump_lab["rig"].save(tmp_path / "rig.json")
    text = ",".join(f"{v:.6f}" for v in crack.ravel())
    r = CliRunner().invoke(main, ["stereo", "--rig", str(tmp_path / "rig.json"), *paths, "--step", "10", "--device",
                                  "cpu", "-q", "-o", str(tmp_path / "cli.h5"), "--crack", text])
    assert r.exit_code == 0, r.output
    stored = read_stereo(tmp_path / "cli.h5").settings["cracks"]
    assert np.allclose(stored, [crack.tolist()], atol=1e-6)
    # resuming the library's file without the crack is refused, naming the option
    with pytest.raises(ValueError, match=r"--crack \(cracks\)"):
        stereo_sequence(jump_lab["rig"], pairs, tmp_path / "lib.h5", step=10, device="cpu")
    r = CliRunner().invoke(main, ["stereo", "--rig", str(tmp_path / "rig.json"), *paths, "-o", str(tmp_path / "x.h5"),
                                  "--crack", "1,2,3"])
    assert r.exit_code == 2 and "--crack" in r.output
