"""Pixel masks of the right camera's temporal track (``right_track_mask``, dic.correlation.right_masks; issue 26
item 1 on the stereo path), against exact truth.

Scene (the virtual lab, dic.lab): the 320 x 240 px rig of tests/dic/test_stereo_dic.py looking at a speckled
plate 120 mm wide (free edges left and right, inside both images) 150 mm in front of a static speckled
background; between the two states the plate translates rigidly by (0.8, -0.5, 1.0) mm (world), the
background stays. Region: the plate's outline projected into the left reference image (a polygon ROI), so the
match and the left track correlate the plate's pixels only (the left subsets' masks); the right track's
subsets either keep every pixel (``right_track_mask=False``: the behaviour before) or the pixels the region
maps to through the match.
"""
from dataclasses import replace

import numpy as np
import pytest

from dic._stereo import StereoCorrelation
from dic.correlation.right_masks import mapped_pixel_masks
from dic.lab import Displacement, LabCamera, Scene, SpecklePlane, render, stereo_rig
from dic.synth import make_speckle

PLATE_MM = (120.0, 250.0)
T_WORLD = np.array([0.8, -0.5, 1.0])


@pytest.fixture(scope="module")
def edge_lab():
    cams = [LabCamera.from_lens(name=n, size=(320, 240), focal_length_mm=12.0, f_number=float("inf"),
                                focus_distance_mm=1000.0, position=(x, 0.0, 0.0), look_at_point=(0.0, 0.0, 1000.0),
                                exposure_dn=200.0, bit_depth=8)
            for n, x in (("left", -150.0), ("right", 150.0))]
    w, h = PLATE_MM
    plate = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=PLATE_MM,
                                speckle=make_speckle(region=(-5, -5, w + 5, h + 5), radius=1.2, density=0.5, bits=None,
                                                     seed=3))
    background = SpecklePlane.facing(center=(0.0, 0.0, 1150.0), normal=(0.0, 0.0, -1.0), size=(700.0, 500.0),
                                     speckle=make_speckle(region=(-5, -5, 705, 505), radius=1.4, density=0.5,
                                                          bits=None, seed=8))
    t_local = plate.R_world_surface.T @ T_WORLD
    moved = replace(plate, displacement=Displacement(np.broadcast_to(t_local, (2, 2, 3)).copy(), (0.0, 0.0), PLATE_MM))
    ref = tuple(render(Scene(cameras=cams, planes=[plate, background]), i, samples=16, seed=i) for i in range(2))
    cur = tuple(render(Scene(cameras=cams, planes=[moved, background]), i, samples=16, seed=10 + i) for i in range(2))
    left, right = cams
    rig = stereo_rig(left, right)
    outline = left.project(plate.to_world(np.array([[0, 0], [w, 0], [w, h], [0, h]], float), deformed=False))
    return {"rig": rig, "ref": ref, "cur": cur, "outline": outline, "left": left, "right": right}


def _run(lab, right_track_mask):
    sc = StereoCorrelation(lab["rig"], *lab["ref"], step=5, subset=21, roi=lab["outline"], device="cpu",
                           right_track_mask=right_track_mask)
    f = sc.measure(*lab["cur"])
    left, right = lab["left"], lab["right"]
    exact = left.R_cam_world @ T_WORLD  # a rigid translation: the same displacement at every plate point
    err_mm = np.linalg.norm(f.uvw - exact, axis=1)
    # the right track's image-plane error: its measured point against the exact projection of the material point
    world = (np.nan_to_num(f.xyz) - left.t_cam_world) @ left.R_cam_world
    err_right_px = np.linalg.norm(f.details["points_right_cur"] - right.project(world + T_WORLD), axis=1)
    return sc, f, err_mm, err_right_px


def _rms(e, m):
    return float(np.sqrt(np.mean(e[m] ** 2)))


def test_right_track_edge_points_are_kept_with_interior_accuracy(edge_lab):
    """The points whose right subsets reach beyond the plate's edge (the static background): without right masks
    they follow the background half-way (3-D error RMS 36 x the interior's, measured); with them they are kept
    (at least 95 % of those matched) with a 3-D error RMS and a right-track image error RMS within 2 x the
    interior's (measured: all 156 kept, 1.64 x and 1.74 x)."""
    sc, f, err_mm, err_px = _run(edge_lab, True)
    assert sc.right_pixel_mask is not None
    right_edge = np.zeros(len(f.points), bool)
    right_edge[sc._matched] = ~sc.right_pixel_mask.all(axis=1)
    # (the plate's free edges; not the image's top and bottom, which the plate reaches: there a subset loses pixels
    # beyond the image, and the left track fails once the plate moves out)
    x, y = f.points[:, 0], f.points[:, 1]
    right_edge &= (y >= 21) & (y <= 240 - 1 - 21) & (x >= 21) & (x <= 320 - 1 - 21)
    left_edge = ~sc.pixel_mask.all(axis=1)
    interior = f.valid & ~right_edge & ~left_edge
    edge = sc.match.valid & right_edge
    assert interior.sum() >= 1000 and edge.sum() >= 150
    assert np.count_nonzero(f.valid[edge]) >= 0.95 * edge.sum()
    kept = f.valid & right_edge
    assert _rms(err_mm, kept) <= 2.0 * _rms(err_mm, interior), (_rms(err_mm, kept), _rms(err_mm, interior))
    assert _rms(err_px, kept) <= 2.0 * _rms(err_px, interior), (_rms(err_px, kept), _rms(err_px, interior))

    sc0, f0, err0_mm, _ = _run(edge_lab, False)  # the behaviour before: the right subsets on every pixel
    assert sc0.right_pixel_mask is None
    assert np.array_equal(sc0.match.status, sc.match.status)  # the match is the same (masked on the left)
    kept0 = f0.valid & right_edge
    assert _rms(err0_mm, kept0) > 10 * _rms(err0_mm, interior)  # the problem, shown
    # interior points are correlated on every pixel either way: the same results
    assert np.array_equal(f0.uvw[interior], f.uvw[interior])


def test_mapped_masks_follow_the_match():
    """A pure shift of the match carries the region's edge by that shift; a stretch of 2 in x spreads the kept
    right pixels over twice the width; a subset beyond the right image keeps nothing; a singular warp nothing."""
    region = np.zeros((60, 80), bool)
    region[:, :34] = True  # the specimen: x < 34 (left image)
    pl = np.full((4, 2), 30.0)
    pr = pl + [[5.0, 0.0], [5.0, 0.0], [5.0, 0.0], [75.0, 0.0]]
    params = np.array([[5.0, 0, 0, 0, 0, 0], [5.0, 1.0, 0, 0, 0, 0], [5.0, -1.0, 0, 0, 0, -1.0],
                       [75.0, 0, 0, 0, 0, 0]])
    m = mapped_pixel_masks(region, (60, 80), pl, pr, params, 11).reshape(4, 11, 11)
    i = np.arange(-5, 6)
    # shift 5: right pixel 35 + i sees left 30 + i, kept when both left pixels 30 + i and 31 + i are < 34: i <= 2
    assert np.array_equal(m[0], np.broadcast_to(i <= 2, (11, 11)))
    # (I + G) = diag(2, 1): right pixel 35 + i sees left 30 + i / 2, kept when floor(30 + i / 2) + 1 < 34: every i
    assert m[1].all()
    assert not m[2].any()  # singular (I + G): nothing kept
    assert not m[3].any()  # the right subset at x = 100..110, beyond the 80 px right image: nothing kept


def test_the_option_is_compared_only_where_it_can_act():
    """A run record without the option (ADDED_OPTIONS: False) resumes unless a side masks its subsets."""
    from dic.sequence.options import StereoOptions

    polygon = np.array([(20.0, 20.0), (200.0, 20.0), (200.0, 150.0), (20.0, 150.0)])

    def record(**kw):
        return StereoOptions.from_keywords(kw, shape=(240, 320))

    masked = record(roi=polygon)
    assert masked.right_track_mask is True and StereoOptions.ADDED_OPTIONS["right_track_mask"] is False
    assert [d[0] for d in masked.differences(record(roi=polygon, right_track_mask=False))] == ["right_track_mask"]
    assert not record(roi=polygon, subset_mask="none").differences(
        record(roi=polygon, subset_mask="none", right_track_mask=False))
    assert not record(roi=(20, 20, 200, 150)).differences(record(roi=(20, 20, 200, 150), right_track_mask=False))
