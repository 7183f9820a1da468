"""Subsets that keep only the specimen's pixels (issue 26, item 1): a hole and free edges, exact truth.

The cases of bench/holes.py (dic.synth renders: a 0.8 % stretch ``u = 0.008 x``, 1 GL noise, 8 bits,
subset 21, step 4; a 30 px hole; a band with two slanted free edges), the specimen's region given as a
mask (``roi=``). Edge points: those whose subset overlaps the hole / the background. Bounds (issue 26):
the kept edge points' RMS error within 2 x the interior points' RMS, and at least 80 % of the edge points
kept, for both orders. Where the background seen through the hole or beyond the edge is textured (and
still), correlating every pixel pulls the edge points by up to 0.5-0.9 px (tens of times the interior's
error); the masked subsets stay within the bound there too.
"""
import numpy as np
import pytest

from bench import holes
from dic import Tracker
from dic.correlation.subset_masks import subset_pixel_masks
from kernels.conventions import Status


@pytest.fixture(scope="module", params=holes.CASES)
def case(request):
    return request.param, holes.case(request.param)


@pytest.mark.parametrize("order", [1, 2])
def test_edge_points_are_kept_and_as_accurate_as_the_interior(case, order):
    name, _ = case
    r = holes.measure(name, order, "region")
    assert r["edge_points"] >= 60 and r["interior_points"] >= 1000  # the measurement has points to speak of
    assert r["edge_kept"] >= 0.80, r
    assert r["edge_rms_px"] <= 2.0 * r["interior_rms_px"], r


@pytest.mark.parametrize("order", [1, 2])
def test_without_masks_a_textured_background_pulls_the_edge_points(order):
    r = holes.measure("hole-textured", order, "none")  # plain IC-GN (robust=False)
    assert r["edge_rms_px"] > 10 * r["interior_rms_px"], r  # measured 41 x (1st order), 19 x (2nd)
    # the 2-D default, adaptive robust IC-GN, refines the pulled subsets and takes back part of it, not all at
    # 2nd order (measured 1.8 x and 9.1 x); the masks bring both within 2 x (the bounds of the other tests)
    default = holes.measure("hole-textured", order, "region", robust="adaptive")
    assert default["edge_rms_px"] < 2 * default["interior_rms_px"], default


def test_box_roi_masks_no_pixel_and_none_reproduces_the_unmasked_tracker():
    ref, cur, region = holes.case("hole")
    box = (20, 20, 300, 180)
    a = Tracker(ref, step=8, roi=box, subset=21, device="cpu")
    assert a.pixel_mask is None  # a box chooses the POIs, it does not describe the specimen
    b = Tracker(ref, step=8, roi=region, subset=21, subset_mask="none", device="cpu")
    assert b.pixel_mask is None and b.correlator.subsets.mask is None
    c = Tracker(ref, step=8, roi=region, subset=21, device="cpu")
    assert np.array_equal(b.points, c.points)  # the region chooses the same POIs either way
    assert c.pixel_mask is not None and c.pixel_mask.shape == (len(c.points), 441)
    fa, fb = b.track(cur), Tracker(ref, points=b.points, subset=21, device="cpu").track(cur)
    assert np.array_equal(fa.params, fb.params) and np.array_equal(fa.status, fb.status)


def test_points_whose_centre_is_outside_stay_out_and_too_few_pixels_are_flagged():
    ref, cur, region = holes.case("edges")
    tracker = Tracker(ref, step=4, roi=region, subset=21, min_kept_fraction=0.75, device="cpu")
    pts = tracker.points
    assert np.all(region[pts[:, 1].astype(int), pts[:, 0].astype(int)])
    field = tracker.track(cur)
    kept = tracker.pixel_mask.mean(axis=1)
    few = field.status == int(Status.TOO_FEW_PIXELS)
    assert np.any(few) and np.all(kept[few] < 0.75) and not np.any(field.valid[few])
    # the masks are those of the region less its 1 px rim, for every POI
    from dic.correlation.subset_masks import REGION_MARGIN_PX, shrink_region

    assert REGION_MARGIN_PX == 1
    assert np.array_equal(tracker.pixel_mask, subset_pixel_masks(pts, 21, shrink_region(region, 1)))


def test_option_checks():
    ref, _, region = holes.case("hole")
    with pytest.raises(ValueError, match="subset_mask must be one of"):
        Tracker(ref, step=8, roi=region, subset_mask="yes", device="cpu")
    with pytest.raises(ValueError, match="min_kept_fraction must be a number in"):
        Tracker(ref, step=8, roi=region, min_kept_fraction=1.5, device="cpu")
    with pytest.raises(ValueError, match="pixel_region goes with points"):
        Tracker(ref, step=8, pixel_region=region, device="cpu")


def test_cli_and_sequence_record_the_option_and_mask_the_subsets(tmp_path):
    from click.testing import CliRunner

    from dic.cli import main
    from dic.sequence import track_sequence
    from dic.store import read_results
    from kernels.images import write_image

    ref, cur, region = holes.case("hole-textured")
    paths = {}
    for name, img in (("ref", ref), ("cur", cur), ("mask", region.astype(np.uint8) * 255)):
        paths[name] = str(tmp_path / f"{name}.png")
        write_image(paths[name], np.clip(np.rint(img), 0, 255).astype(np.uint8))
    errors = {}
    for mode in ("region", "none"):
        out = tmp_path / f"{mode}.h5"
        res = CliRunner().invoke(main, ["track", paths["ref"], paths["cur"], "--mask", paths["mask"], "--step", "4",
                                        "--subset-mask", mode, "--robust-mode", "off", "-o", str(out), "--device",
                                        "cpu", "-q"])  # plain IC-GN: what the masks alone do
        assert res.exit_code == 0, res.output
        results = read_results(out)
        assert results.settings["subset_mask"] == mode and results.settings["min_kept_fraction"] == 0.5
        f = results.frames[max(results.frames)]
        edge = ~subset_pixel_masks(f.points, 21, region).all(axis=1)
        u, v = holes.displacement(f.points[:, 0], f.points[:, 1])
        err = np.hypot(f.u - u, f.v - v)
        errors[mode] = float(np.sqrt(np.mean(err[f.valid & edge] ** 2)))
    assert errors["region"] < 0.02 and errors["none"] > 0.1, errors  # bench/holes.py: 0.006 and 0.14 px
    # the library's sequence writes the same record
    out = tmp_path / "lib.h5"
    track_sequence(ref, [cur], out, roi=region, step=4, device="cpu")
    assert read_results(out).settings["subset_mask"] == "region"


def test_stereo_masks_the_left_subsets_by_a_mask_region(tmp_path):
    """The match left -> right and the left track use the left reference's mask; "none" and a box do not."""
    from pathlib import Path

    from dic import StereoCorrelation
    from dic.correlation.subset_masks import shrink_region
    from kernels.images import read_image

    data = Path(__file__).parents[1] / "data" / "settings_v1"
    left, right = read_image(str(data / "L0.png")), read_image(str(data / "R0.png"))
    h, w = left.shape
    region = np.ones((h, w), bool)
    region[h // 2 - 6:h // 2 + 6, w // 2 - 6:w // 2 + 6] = False  # a 12 px hole
    kw = dict(step=10, subset=21, order=1, device="cpu")
    masked = StereoCorrelation(str(data / "rig.json"), left, right, roi=region, **kw)
    assert masked.pixel_mask is not None and masked.left.subsets.mask is not None
    assert np.array_equal(masked.pixel_mask, subset_pixel_masks(masked.points, 21, shrink_region(region, 1)))
    plain = StereoCorrelation(str(data / "rig.json"), left, right, roi=region, subset_mask="none", **kw)
    assert plain.pixel_mask is None and plain.left.subsets.mask is None
    boxed = StereoCorrelation(str(data / "rig.json"), left, right, roi=(10, 10, w - 11, h - 11), **kw)
    assert boxed.pixel_mask is None


def test_the_options_cannot_refuse_a_resume_where_nothing_is_masked():
    from dic.sequence.options import StereoOptions, TrackOptions

    poly = {"polygon": [[0.0, 0.0], [40.0, 0.0], [40.0, 30.0]]}
    for record in (TrackOptions, StereoOptions):
        for roi in (None, (1, 1, 50, 50)):  # nothing to mask: a file written before the options resumes
            stored = {k: v for k, v in record(roi=roi).to_settings().items()
                      if k not in ("subset_mask", "min_kept_fraction")}
            assert record(roi=roi).resume_check(stored) is None
            assert record(roi=roi, min_kept_fraction=0.9).resume_check(stored) is None
        # a file written before the options with a polygon ROI: every pixel was correlated, a run now differs
        stored = {k: v for k, v in record(roi=poly).to_settings().items()
                  if k not in ("subset_mask", "min_kept_fraction")}
        refusal = record(roi=poly).resume_check(stored)
        assert "--subset-mask (subset_mask): 'none' in the file, 'region' now" in refusal
        assert "min_kept_fraction" not in refusal  # "none" there: the fraction did not act
        assert record(roi=poly, subset_mask="none").resume_check(stored) is None
        assert "--min-kept-fraction" in record(roi=poly, min_kept_fraction=0.9).resume_check(
            record(roi=poly).to_settings())


def test_reliability_guided_waves_on_masked_subsets_agree_and_measure_the_edges():
    from dic.correlation.engine import reliability_guided
    from kernels.icgn import prepare_current

    ref, cur, region = holes.case("hole-textured")
    tracker = Tracker(ref, step=6, roi=region, subset=21, device="cpu")
    corr = tracker.correlator
    current = prepare_current(cur, device="cpu")
    base = np.zeros((corr.n_points, 6))
    runs = {w: reliability_guided(corr, current, base, lambda idx: np.zeros((len(idx), 6)), zncc_min=0.8, step=6.0,
                                  waves=w) for w in ("host", "device")}
    for key in ("params", "zncc", "status", "iterations"):
        assert np.array_equal(runs["host"][key], runs["device"][key], equal_nan=key == "zncc"), key
    field = Tracker(ref, step=6, roi=region, subset=21, search="rg", device="cpu").track(cur)
    pts = field.points
    u, v = holes.displacement(pts[:, 0], pts[:, 1])
    err = np.hypot(field.u - u, field.v - v)
    edge = ~subset_pixel_masks(pts, 21, region).all(axis=1)
    assert np.count_nonzero(field.valid & edge) >= 0.8 * np.count_nonzero(edge)
    assert np.sqrt(np.mean(err[field.valid & edge] ** 2)) <= 2 * np.sqrt(np.mean(err[field.valid & ~edge] ** 2))


def test_excluded_shapes_mask_the_subsets_even_in_a_box():
    """Excluded shapes (a hole given as a circle, regions25's ``exclude``) describe the specimen: they mask the
    subsets whatever the region they are taken out of; a plain box does not."""
    from dic.correlation import points as points_module

    if not hasattr(points_module, "exclusion"):
        pytest.skip("regions without excluded shapes in this tree (regions25 not merged)")
    ref, cur, region = holes.case("hole-textured")
    cx, cy = holes.HOLE_CENTRE
    hole = {"circle": [cx, cy, holes.HOLE_RADIUS]}
    for roi in ({"exclude": [hole]}, {"box": [20.0, 20.0, 300.0, 180.0], "exclude": [hole]}):
        tracker = Tracker(ref, step=4, roi=points_module.region(roi, ref.shape), subset=21, search="zncc",
                          search_radius=4, device="cpu")
        assert tracker.pixel_mask is not None
        field = tracker.track(cur)
        pts = field.points
        u, v = holes.displacement(pts[:, 0], pts[:, 1])
        err = np.hypot(field.u - u, field.v - v)
        edge = ~subset_pixel_masks(pts, 21, region).all(axis=1)
        assert np.count_nonzero(field.valid & edge) >= 0.8 * np.count_nonzero(edge)
        assert np.sqrt(np.mean(err[field.valid & edge] ** 2)) <= 2 * np.sqrt(np.mean(err[field.valid & ~edge] ** 2))


def test_robust_refinement_leaves_masked_subsets_at_their_masked_result():
    ref, cur, region = holes.case("hole-textured")
    plain = Tracker(ref, step=6, roi=region, subset=21, search="zncc", search_radius=4, device="cpu")
    robust = Tracker(ref, step=6, roi=region, subset=21, search="zncc", search_radius=4, robust=True,
                     check_outliers=False, device="cpu")
    fp, fr = plain.track(cur), robust.track(cur)
    masked = ~plain.pixel_mask.all(axis=1)
    assert np.any(masked)
    assert np.array_equal(fp.params[masked], fr.params[masked])  # not refined on whole subsets
    u, v = holes.displacement(fr.points[:, 0], fr.points[:, 1])
    err = np.hypot(fr.u - u, fr.v - v)
    assert np.sqrt(np.mean(err[fr.valid & masked] ** 2)) < 0.02  # bench/holes.py: 0.006 px


def test_chunks_of_the_reference_grid_are_masked_alike(tmp_path):
    from dic.sequence import track_sequence
    from dic.sequence.chunks import bytes_per_poi
    from dic.store import read_results

    ref, cur, region = holes.case("hole-textured")
    whole, chunked = tmp_path / "whole.h5", tmp_path / "chunked.h5"
    track_sequence(ref, [cur], whole, roi=region, step=6, device="cpu")
    n = len(read_results(whole).frames[1].points)
    track_sequence(ref, [cur], chunked, roi=region, step=6, device="cpu", max_memory=bytes_per_poi(1) * (n // 3 + 1))
    a, b = read_results(whole).frames[1], read_results(chunked).frames[1]
    assert np.array_equal(a.params, b.params) and np.array_equal(a.status, b.status)
