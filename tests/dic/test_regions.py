"""Regions for real specimens (issue 25, item 5): shapes excluded from a region of interest (circle, box,
polygon) in the library (dic.correlation.points) and on the command line (--exclude on track, stereo and
speckle, speckle --roi), stored in the result file's run record, resumed, and drawn in the field figures."""
import json
import re

import numpy as np
import pytest
from click.testing import CliRunner

from dic.cli import main
from dic.correlation.points import Region, exclusion, grid, grid_points, lattice, region, roi_mask
from dic.io import write_image
from dic.sequence.options import StereoOptions, TrackOptions

SHAPE = (80, 100)  # (H, W) px


def _lattice_truth(shape, step, margin, keep):
    """The lattice points (row-major, x fastest) for which ``keep(x, y)`` is true, by a plain loop."""
    h, w = shape
    return np.array([(x, y) for y in range(margin, h - margin, step) for x in range(margin, w - margin, step)
                     if keep(x, y)], dtype=np.float64).reshape(-1, 2)


def _in_triangle(x, y, a, b, c):
    """Inside or on the edge of triangle abc (signs of the three edge cross products agree)."""
    def cross(p, q):
        return (q[0] - p[0]) * (y - p[1]) - (q[1] - p[1]) * (x - p[0])
    d = (cross(a, b), cross(b, c), cross(c, a))
    return all(v >= 0 for v in d) or all(v <= 0 for v in d)


# -- the library: one rule for every shape ------------------------------------------------------------------
def test_each_excluded_shape_takes_exactly_its_points_out():
    box = (10.0, 10.0, 89.0, 69.0)
    hole_box = (20, 20, 30, 28)
    tri = ((70, 20), (85, 20), (85, 35))
    cases = {
        "circle": ({"box": list(box), "exclude": ["circle:50,40,12"]},
                   lambda x, y: (x - 50) ** 2 + (y - 40) ** 2 > 144),
        "box": ({"box": list(box), "exclude": [{"box": list(hole_box)}]},
                lambda x, y: not (20 <= x <= 30 and 20 <= y <= 28)),
        "polygon": ({"box": list(box), "exclude": ["polygon:70,20,85,20,85,35"]},
                    lambda x, y: not _in_triangle(x, y, *tri)),
    }
    for name, (roi, outside_shape) in cases.items():
        def keep(x, y, outside_shape=outside_shape):
            return box[0] <= x <= box[2] and box[1] <= y <= box[3] and outside_shape(x, y)
        expected = _lattice_truth(SHAPE, 2, 5, keep)
        got = grid(SHAPE, 2, margin=5, roi=roi)
        assert np.array_equal(got, expected), name
        assert len(got) < len(grid(SHAPE, 2, margin=5, roi=box)), name
        # stereo keeps the lattice and flags the same points: one rule for 2-D and stereo
        pts, _, in_roi = grid_points(SHAPE, 2, 11, roi)
        assert np.array_equal(pts[in_roi], got), name
    # the points exactly on the circle are excluded, those one px further out are kept
    reg = region(cases["circle"][0], SHAPE)
    on = np.array([[38.0, 40.0], [62.0, 40.0], [50.0, 28.0], [50.0, 52.0]])
    assert not roi_mask(on, reg, SHAPE).any()
    assert roi_mask(on + [[-1, 0], [1, 0], [0, -1], [0, 1]], reg, SHAPE).all()


def test_exclusions_without_a_region_and_with_a_polygon_or_a_mask(tmp_path):
    # the whole image less a circle: the Gauss count of lattice points in a radius-10 disc is 317
    reg = region({"exclude": ["circle:50,40,10"]}, SHAPE)
    assert reg.kind == "image"
    assert np.count_nonzero(~reg.pixel_mask(SHAPE)) == 317
    # a polygon region less a box
    poly = [[5, 5], [95, 5], [95, 75], [5, 75]]
    got = grid(SHAPE, 5, roi={"polygon": poly, "exclude": ["box:40,30,60,50"]})
    assert np.array_equal(got, _lattice_truth(SHAPE, 5, 0, lambda x, y: 5 <= x <= 95 and 5 <= y <= 75
                                              and not (40 <= x <= 60 and 30 <= y <= 50)))
    # a mask file less a circle; the mask's digest is checked when the stored form names the file again
    mask = np.zeros(SHAPE, np.uint8)
    mask[10:70, 10:90] = 1
    write_image(tmp_path / "mask.png", mask, bits=8)
    reg = region({"mask": str(tmp_path / "mask.png"), "exclude": [{"circle": [50, 40, 10]}]}, SHAPE)
    yy, xx = np.mgrid[0:SHAPE[0], 0:SHAPE[1]]
    truth = (mask != 0) & ((xx - 50) ** 2 + (yy - 40) ** 2 > 100)
    assert np.array_equal(reg.pixel_mask(SHAPE), truth)
    assert np.array_equal(region(reg.settings(), SHAPE).pixel_mask(SHAPE), truth)
    write_image(tmp_path / "mask.png", 1 - mask, bits=8)
    with pytest.raises(ValueError, match="differs from the mask the region was made with"):
        region(reg.settings(), SHAPE)


def test_pixel_mask_is_roi_mask_at_every_pixel():
    """The boolean (H, W) mask of the region (what a subset's pixels are masked by) and the POI rule agree."""
    reg = region({"polygon": [[3, 4], [96, 8], [90, 77], [6, 70]],
                  "exclude": ["circle:50,40,9.5", "box:10,10,20,15", "polygon:60,60,80,60,70,75"]}, SHAPE)
    pts, _ = lattice(SHAPE, 1)
    m = reg.pixel_mask(SHAPE)
    assert m.shape == SHAPE and m.dtype == bool
    assert np.array_equal(m.ravel(), roi_mask(pts, reg, SHAPE))
    assert not m[40, 50] and not m[12, 15] and not m[65, 70] and m[40, 30]


def test_pixel_mask_scanlines_match_the_point_rule_on_random_polygons():
    """Region.pixel_mask fills polygons by scanlines (fast: a 2048 x 2048 px mask in about 0.1 s): the same
    pixels as roi_mask's point test for random polygons (whole, half-pixel and arbitrary vertices, horizontal
    edges, self-intersecting outlines, vertices outside the image), as a region and as an exclusion."""
    shape = (60, 75)
    pts, _ = lattice(shape, 1)
    rng = np.random.default_rng(0)
    checked = 0
    for k in range(120):
        v = rng.uniform(-10, 85, (int(rng.integers(3, 9)), 2))
        if k % 3 == 0:
            v = np.round(v * 2) / 2  # half pixels: vertices and edges through pixel centres
        if k % 4 == 0:
            v[:, 1] = np.round(v[:, 1])
            v[1, 1] = v[0, 1]  # a horizontal edge on a pixel row
        for roi in ({"polygon": v.tolist()}, {"exclude": [{"polygon": v.tolist()}]}):
            try:
                reg = region(roi, shape)
            except ValueError:  # a degenerate random polygon
                continue
            assert np.array_equal(reg.pixel_mask(shape).ravel(), roi_mask(pts, reg, shape)), v.tolist()
            checked += 1
    assert checked > 200


def test_the_json_form_is_the_region_and_without_exclusions_it_is_what_it_was():
    forms = [
        ({"box": [1.0, 2.0, 90.0, 70.0], "exclude": [{"circle": [50.0, 40.0, 10.0]}]}, "box"),
        ({"polygon": [[5.0, 5.0], [95.0, 5.0], [50.0, 75.0]], "exclude": [{"box": [40.0, 20.0, 60.0, 30.0]}]},
         "polygon"),
        ({"exclude": [{"polygon": [[10.0, 10.0], [20.0, 10.0], [15.0, 20.0]]}]}, "image"),
    ]
    for form, kind in forms:
        reg = region(form, SHAPE)
        assert reg.kind == kind and reg.settings() == form
        assert region(reg.settings(), SHAPE).settings() == form
    # the text form of the command line is the same shape as the JSON form
    assert exclusion("circle:50,40,10").settings() == {"circle": [50.0, 40.0, 10.0]}
    assert exclusion("box: 1, 2, 3, 4").settings() == {"box": [1.0, 2.0, 3.0, 4.0]}
    assert exclusion("polygon:1,2;9,2;5,8").settings() == {"polygon": [[1.0, 2.0], [9.0, 2.0], [5.0, 8.0]]}
    # regions without exclusions keep the JSON form files written before exclusions existed hold
    assert region((1, 2, 90, 70), SHAPE).settings() == [1.0, 2.0, 90.0, 70.0]
    assert region([(5, 5), (95, 5), (50, 75)], SHAPE).settings() == {"polygon": [[5.0, 5.0], [95.0, 5.0], [50.0, 75.0]]}
    assert region({"exclude": []}, SHAPE) is None


@pytest.mark.parametrize("roi, message", [
    ({"exclude": ["hexagon:1,2,3"]}, "exclude: 'hexagon:1,2,3' is not a shape; give circle:CX,CY,R"),
    ({"exclude": ["circle:1,2"]}, "exclude circle needs 3 numbers cx, cy, r"),
    ({"exclude": ["circle:10,10,0"]}, "exclude circle radius must be > 0 px"),
    ({"exclude": ["circle:10,10,nan"]}, "must be finite numbers"),
    ({"exclude": ["circle:a,b,c"]}, "exclude circle 'circle:a,b,c': the coordinates must be numbers"),
    ({"exclude": ["box:5,5,1,9"]}, "exclude box (x0, y0, x1, y1) = 'box:5,5,1,9' is empty"),
    ({"exclude": ["box:1,2,3"]}, "exclude box needs 4 numbers"),
    ({"exclude": ["polygon:1,2,3,4"]}, "exclude polygon needs at least 3 vertices"),
    ({"exclude": ["polygon:1,2,3,4,5"]}, "give x,y pairs"),
    ({"exclude": ["polygon:0,0,5,5,10,10"]}, "exclude polygon [[0.0, 0.0], [5.0, 5.0], [10.0, 10.0]] has zero area"),
    ({"exclude": [{"circle": [1, 2, 3], "box": [1, 2, 3, 4]}]}, "is not a shape"),
    ({"exclude": "circle:1,2,3"}, "roi 'exclude' must be a list of shapes"),
    ({"box": [1, 2, 3, 4], "polygon": [[1, 2], [3, 4], [5, 7]]}, "one of box, polygon, mask"),
    ({"mask": "array", "sha256": "0" * 64, "shape": [80, 100]}, "give the (H, W) mask array or its image file"),
    ({"box": [0, 0, 99, 79], "exclude": ["box:0,0,99,79"]}, "contains no grid point (empty ROI)"),
])
def test_bad_regions_say_what_is_wrong(roi, message):
    with pytest.raises(ValueError) as err:
        grid(SHAPE, 5, roi=roi)
    assert message in str(err.value)


# -- the run record: stored, compared, resumed ---------------------------------------------------------------
def test_the_run_record_stores_the_exclusions_and_compares_them():
    roi = {"box": [10.0, 10.0, 89.0, 69.0], "exclude": [{"circle": [50.0, 40.0, 12.0]}]}
    for cls in (TrackOptions, StereoOptions):
        rec = cls.from_keywords({"roi": roi}, shape=SHAPE)
        assert isinstance(rec.region, Region) and rec.region.exclude
        stored = json.loads(json.dumps(rec.to_settings()))  # through JSON, as the file holds it
        assert stored["roi"] == roi
        assert rec.resume_check(stored) is None  # the same run resumes
        read = cls.from_settings(stored)
        assert read.roi == roi and read.region is None
        other = cls.from_keywords({"roi": {**roi, "exclude": [{"circle": [50.0, 40.0, 13.0]}]}}, shape=SHAPE)
        refusal = other.resume_check(stored)
        assert refusal is not None and "--exclude" in refusal and "roi" in refusal
        # a run without the exclusion is another run too
        plain = cls.from_keywords({"roi": roi["box"]}, shape=SHAPE)
        assert plain.resume_check(stored) is not None
        assert plain.to_settings()["roi"] == [10.0, 10.0, 89.0, 69.0]  # the form files written before hold


# -- the command line -------------------------------------------------------------------------------------------
@pytest.fixture
def pair(tmp_path):
    from dic.synth import speckle_pair

    ref, cur = speckle_pair((96, 112), (0.4, -0.3), seed=21)
    return [str(write_image(tmp_path / n, im, bits=8)) for n, im in (("ref.tif", ref), ("cur.tif", cur))]


def _run(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def test_track_exclude_selects_stores_resumes_and_draws(pair, tmp_path):
    from dic.store import read_results

    out = tmp_path / "run.h5"
    opts = ["--step", "5", "--device", "cpu", "--roi", "12", "12", "99", "83", "--exclude", "circle:56,48,15",
            "--exclude", "box:12,12,30,25", "--exclude", "polygon:80,70,99,70,99,83"]
    r = _run("track", *pair, "-o", out, "-q", "--figures", tmp_path / "fig", *opts)
    assert r.exit_code == 0, r.output
    res = read_results(out)
    stored = {"box": [12.0, 12.0, 99.0, 83.0], "exclude": [{"circle": [56.0, 48.0, 15.0]},
                                                            {"box": [12.0, 12.0, 30.0, 25.0]},
                                                            {"polygon": [[80.0, 70.0], [99.0, 70.0], [99.0, 83.0]]}]}
    assert res.settings["roi"] == stored

    def keep(x, y):
        return (12 <= x <= 99 and 12 <= y <= 83 and (x - 56) ** 2 + (y - 48) ** 2 > 225
                and not (12 <= x <= 30 and 12 <= y <= 25) and not _in_triangle(x, y, (80, 70), (99, 70), (99, 83)))
    assert np.array_equal(res.frames[1].points, _lattice_truth((96, 112), 5, 10, keep))
    # the library takes the same region through roi= (the one way), and a library-written file stores the same form
    from dic._track import track
    from dic.sequence import track_sequence

    assert np.array_equal(track(pair[0], pair[1], step=5, roi=stored, device="cpu").points, res.frames[1].points)
    track_sequence(pair[0], [pair[1]], tmp_path / "lib.h5", step=5, roi=stored, device="cpu", progress=False)
    assert read_results(tmp_path / "lib.h5").settings["roi"] == stored
    assert (tmp_path / "fig" / "frame_000001.png").is_file()
    # the figures drawn once the run ends (one colour range over the sequence) draw the region too
    import dic.plots.fields as fields

    drawn = []
    real = fields.write_field_figure

    def spy(path, *args, **kwargs):
        drawn.append(kwargs.get("region"))
        return real(path, *args, **kwargs)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fields, "write_field_figure", spy)
        r = _run("track", *pair, "-o", tmp_path / "seq.h5", "-q", "--figures", tmp_path / "seqfig", "--figure-limits",
                 "sequence", *opts)
    assert r.exit_code == 0, r.output
    assert len(drawn) == 1 and drawn[0].settings() == stored
    assert (tmp_path / "seqfig" / "frame_000001.png").is_file()
    # the same command resumes (nothing to do); another exclusion is refused naming the option
    r = _run("track", *pair, "-o", out, *opts)
    assert r.exit_code == 0, r.output
    bad = [o if o != "circle:56,48,15" else "circle:56,48,16" for o in opts]
    r = _run("track", *pair, "-o", out, "-q", *bad)
    assert r.exit_code == 1 and "--exclude" in r.output and "--overwrite" in r.output, r.output


def test_a_file_written_before_exclusions_existed_still_resumes(pair, tmp_path):
    """The run records of b36e3a0 (tests/data/settings_v2: a box ROI stored as a plain list) resume with the same
    options given now, and a CLI run with a box ROI still stores that same form and resumes."""
    from pathlib import Path

    from dic.store import read_results

    v2 = Path(__file__).parents[1] / "data" / "settings_v2"
    for cls, name in ((TrackOptions, "track_b36e3a0.json"), (StereoOptions, "stereo_b36e3a0.json")):
        old = json.loads((v2 / name).read_text())
        same = cls.from_keywords({**{k: v for k, v in old.items() if k != "options_schema"}, **cls.ADDED_OPTIONS},
                                 shape=(100, 120))
        assert same.resume_check(old) is None and same.to_settings()["roi"] == old["roi"]
    assert old["roi"] is None and json.loads((v2 / "track_b36e3a0.json").read_text())["roi"] == [8.0, 8.0, 90.0, 70.0]
    out = tmp_path / "old.h5"
    opts = ["--step", "8", "--device", "cpu", "-q", "--roi", "8", "8", "90", "70"]
    assert _run("track", *pair, "-o", out, *opts).exit_code == 0
    assert read_results(out).settings["roi"] == [8.0, 8.0, 90.0, 70.0]
    r = _run("track", *pair, "-o", out, *opts)
    assert r.exit_code == 0, r.output


@pytest.mark.parametrize("args, message", [
    (["--exclude", "circle:1,2"], "Invalid value for --exclude: exclude circle needs 3 numbers"),
    (["--exclude", "ring:1,2,3"], "Invalid value for --exclude: exclude: 'ring:1,2,3' is not a shape"),
    (["--exclude", "box:9,9,1,1"], "Invalid value for --exclude"),
    (["--exclude", "polygon:1,1,5,5"], "Invalid value for --exclude: exclude polygon needs at least 3 vertices"),
    (["--exclude", "circle:56,48,200"], "empty ROI"),
])
@pytest.mark.parametrize("verb", ["track", "speckle"])
def test_cli_bad_exclusions_name_the_option(pair, tmp_path, verb, args, message):
    inputs = pair if verb == "track" else pair[:1]
    extra = ["-o", tmp_path / "bad.h5", "-q"] if verb == "track" else ["--noise-sigma", "2"]
    r = _run(verb, *inputs, *extra, "--device", "cpu", *args)
    assert r.exit_code in (1, 2) and message in r.output and "Traceback" not in r.output, r.output


def test_stereo_has_the_exclude_option():
    r = _run("stereo", "--help")
    assert r.exit_code == 0 and "--exclude SHAPE" in r.output and "circle:CX,CY,R" in r.output


def test_cli_polygon_exclusion_from_a_file(tmp_path):
    from dic.commands._region import parse_region

    (tmp_path / "notch.json").write_text(json.dumps([[70, 20], [85, 20], [85, 35]]))
    roi = parse_region(None, None, None, (f"polygon:{tmp_path / 'notch.json'}",))
    assert roi == {"exclude": [{"polygon": [[70.0, 20.0], [85.0, 20.0], [85.0, 35.0]]}]}


# -- speckle: the suggestion on the specimen only -------------------------------------------------------------
def _suggested(output: str) -> int:
    m = re.search(r"suggested subset: (\d+) px", output)
    assert m, output
    return int(m.group(1))


def test_speckle_suggestion_on_the_specimen_only(tmp_path):
    """A speckled specimen with black borders (14 px) and a dark hole (r 18 px): without a region the
    featureless pixels push the suggestion up; with --roi on the specimen and --exclude around the hole it
    is the suggestion of the image of the specimen alone (the same speckle and noise everywhere) within one
    step of the odd subset sizes (2 px)."""
    from dic.synth import specimen_on_background

    H = W = 200
    B, CX, CY, R = 14, 100, 100, 18

    def inside(x, y):
        return (x >= B) & (x <= W - 1 - B) & (y >= B) & (y <= H - 1 - B) & ((x - CX) ** 2 + (y - CY) ** 2 > R * R)

    holed, _, frac = specimen_on_background((H, W), specimen=inside, noise_sigma=2.0, seed=3, background_level=10.0)
    alone, _, _ = specimen_on_background((H, W), specimen=lambda x, y: np.ones_like(x, bool), noise_sigma=2.0, seed=3)
    assert np.array_equal(holed[frac == 1], alone[frac == 1])  # the same specimen
    for name, img in (("holed.png", holed), ("alone.png", alone)):
        write_image(tmp_path / name, np.clip(np.round(img), 0, 255).astype(np.uint8), bits=8)
    common = ["--noise-sigma", "2", "--target", "0.01", "--device", "cpu"]
    r_full = _run("speckle", tmp_path / "holed.png", *common)
    r_roi = _run("speckle", tmp_path / "holed.png", *common, "--roi", B + 2, B + 2, W - 3 - B, H - 3 - B,
                 "--exclude", f"circle:{CX},{CY},{R + 3}")
    r_alone = _run("speckle", tmp_path / "alone.png", *common)
    for r in (r_full, r_roi, r_alone):
        assert r.exit_code == 0, r.output
    full, roi, spec = _suggested(r_full.output), _suggested(r_roi.output), _suggested(r_alone.output)
    assert roi < full
    assert abs(roi - spec) <= 2
    assert "region: box (16.0, 16.0, 183.0, 183.0) less circle (100.0, 100.0, 21.0)" in r_roi.output
    assert "region: whole image" in r_full.output
    # the other region forms are there too; one region at a time
    r = _run("speckle", tmp_path / "holed.png", *common, "--roi-polygon", "16,16;183,16;183,183;16,183")
    assert r.exit_code == 0 and _suggested(r.output) < full, r.output
    r = _run("speckle", tmp_path / "holed.png", *common, "--roi", 1, 1, 5, 5, "--mask", tmp_path / "alone.png")
    assert r.exit_code == 2 and "give one region of interest, not --roi and --mask" in r.output


# -- figures ----------------------------------------------------------------------------------------------------
def _dark_at(fig, ax, x, y, rgb) -> bool:
    """Whether the saved PNG ``rgb`` (H, W, 3) is dark (an outline) within 1 px of data point (x, y) of ``ax``."""
    dx, dy = ax.transData.transform((x, y))
    col, row = int(round(dx)), int(round(rgb.shape[0] - dy))
    patch = rgb[row - 1:row + 2, col - 1:col + 2].astype(int).sum(axis=2)
    return bool(patch.min() < 150)


def test_field_figure_draws_the_region_and_the_excluded_shapes(tmp_path):
    from types import SimpleNamespace

    from PIL import Image

    from dic.plots._common import save_map_png
    from dic.plots.fields import field_figure

    roi = {"box": [10.0, 10.0, 89.0, 69.0], "exclude": [{"circle": [50.0, 40.0, 12.0]}, {"box": [15, 15, 25, 25]},
                                                          {"polygon": [[70, 20], [85, 20], [85, 35]]}]}
    pts = grid(SHAPE, 2, roi=roi)
    field = SimpleNamespace(points=pts, u=0.01 * pts[:, 0], v=0.02 * pts[:, 1] - 1.0, valid=np.ones(len(pts), bool))
    fig = field_figure(None, field, region=roi, dpi=100)
    for ax in fig.axes:  # the map panels (each with its colourbar beside it)
        outlines = [p for p in ax.patches if p.get_gid() == "region"]
        excluded = [p for p in ax.patches if p.get_gid() == "excluded"]
        assert len(outlines) == 1 and outlines[0].get_linestyle() == "-"
        assert len(excluded) == 3 and all(p.get_linestyle() == "--" for p in excluded)
        assert sorted(type(p).__name__ for p in excluded) == ["Circle", "Polygon", "Rectangle"]
    # in the saved PNG: the region's left (x = 10) and top (y = 10) edges and the circle's top (50, 28) and left
    # (38, 40) are dark outline pixels, the circle's centre is not; the figure without a region is light there
    on_outline = [(10, 60), (30, 10), (50, 28), (38, 40)]
    rgb = np.asarray(Image.open(save_map_png(fig, tmp_path / "fig.png", dpi=100)).convert("RGB"))
    assert all(_dark_at(fig, fig.axes[0], x, y, rgb) for x, y in on_outline)
    assert not _dark_at(fig, fig.axes[0], 50, 40, rgb)
    plain = field_figure(None, field, dpi=100)
    assert not [p for p in plain.axes[0].patches if p.get_gid() in ("region", "excluded")]
    rgb = np.asarray(Image.open(save_map_png(plain, tmp_path / "plain.png", dpi=100)).convert("RGB"))
    assert not any(_dark_at(plain, plain.axes[0], x, y, rgb) for x, y in on_outline)


def test_stereo_figures_draw_the_region(tmp_path):
    from dic.field3d import Field3D
    from dic.plots.fields import field3d_figure, write_figures

    pts, grid_shape, in_roi = grid_points(SHAPE, 4, 11, {"exclude": ["circle:50,40,12"]})
    n = len(pts)
    ok = in_roi
    nan = np.where(ok, 1.0, np.nan)
    status = np.where(ok, 0, 1).astype(np.int8)
    f = Field3D(points=pts, grid_shape=grid_shape, X=nan * pts[:, 0], Y=nan * pts[:, 1], Z=500 * nan, U=0.01 * nan,
                V=0.02 * nan, W=nan * pts[:, 0] * 1e-3, exx=nan * 0, eyy=nan * 0, exy=nan * 0,
                normal=np.tile([0.0, 0.0, -1.0], (n, 1)), zncc_stereo=nan, zncc_left=np.ones(n), zncc_right=np.ones(n),
                epipolar_ref_px=np.zeros(n), epipolar_px=np.zeros(n), reprojection_ref_px=np.zeros(n),
                reprojection_px=np.zeros(n), status=status, strain_valid=ok.copy(), index=1)
    fig = field3d_figure(f, "W", np.zeros(SHAPE), region={"exclude": [{"circle": [50.0, 40.0, 12.0]}]})
    excluded = [p for p in fig.axes[0].patches if p.get_gid() == "excluded"]
    assert len(excluded) == 1 and tuple(excluded[0].center) == (50.0, 40.0) and excluded[0].radius == 12.0
    written = write_figures(f, np.zeros(SHAPE), tmp_path, quantities=["W"], region={"exclude": ["circle:50,40,12"]})
    assert [p.name for p in written] == ["W.png"]
    # a mask region draws the mask's boundary
    mask = np.zeros(SHAPE, bool)
    mask[10:70, 20:80] = True
    fig = field3d_figure(f, "W", np.zeros(SHAPE), region=mask)
    assert [c for c in fig.axes[0].get_children() if c.get_gid() == "region"]


def test_figures_take_the_region_as_checked_or_as_stored():
    from types import SimpleNamespace

    from dic.plots.fields import field_figure

    form = {"polygon": [[5.0, 5.0], [95.0, 5.0], [50.0, 75.0]],
            "exclude": [{"circle": [50.0, 30.0, 8.0]}, {"box": [40.0, 10.0, 60.0, 14.0]}]}
    pts = grid(SHAPE, 4, roi=form)
    field = SimpleNamespace(points=pts, u=pts[:, 0] * 0.0 + 1.0, v=pts[:, 1] * 0.01, valid=np.ones(len(pts), bool))

    def drawn(fig):
        ax = fig.axes[0]
        return [(p.get_gid(), type(p).__name__, np.round(p.get_verts(), 6).tolist()) for p in ax.patches]
    from_region = drawn(field_figure(None, field, region=region(form, SHAPE)))
    assert drawn(field_figure(None, field, region=form)) == from_region  # the form a result file stores
    assert [g for g, *_ in from_region] == ["region", "excluded", "excluded"]
    # a stored mask form (a digest, no mask): the exclusions are drawn, not an outline
    stored_mask = {"mask": "specimen.png", "sha256": "0" * 64, "shape": [80, 100], "exclude": [{"circle": [50, 30, 8]}]}
    assert [p.get_gid() for p in field_figure(None, field, region=stored_mask).axes[0].patches] == ["excluded"]
    for bad, message in [({"exclude": [{"ring": [1, 2, 3]}]}, "excluded shape"), ({"exclude": "circle:1,2,3"},
                         "must be a list of shapes"), ("specimen.png", "region must be a Region")]:
        with pytest.raises(ValueError, match=message):
            field_figure(None, field, region=bad)


def test_stereo_exclude_flags_the_points_and_stores_the_region(tmp_path):
    """specula stereo --roi ... --exclude circle: the grid points in the circle are NOT_COMPUTED like those outside
    the box, the points computed are exactly the region's, the file stores the form, a figure is drawn."""
    from test_cli_messages import _stereo_scene
    from test_stereo_sequence import STEP

    from dic.field3d import StereoStatus
    from dic.store import read_stereo

    paths = _stereo_scene(tmp_path)
    out = tmp_path / "holed.h5"
    r = _run("stereo", "--rig", tmp_path / "rig.json", *paths, "--step", STEP, "--roi", 100, 80, 220, 160,
             "--exclude", "circle:160,120,20", "--figures", tmp_path / "figs", "-o", out, "-q")
    assert r.exit_code == 0, r.output
    res = read_stereo(out)
    assert res.settings["roi"] == {"box": [100.0, 80.0, 220.0, 160.0], "exclude": [{"circle": [160.0, 120.0, 20.0]}]}
    f = res.fields[0]
    x, y = f.points[:, 0], f.points[:, 1]
    in_region = (x >= 100) & (x <= 220) & (y >= 80) & (y <= 160) & ((x - 160) ** 2 + (y - 120) ** 2 > 400)
    computed = f.status != StereoStatus.NOT_COMPUTED
    assert np.any((x - 160) ** 2 + (y - 120) ** 2 <= 400)  # the circle holds grid points
    assert np.array_equal(computed, in_region)
    assert np.count_nonzero(f.valid) > 0.9 * np.count_nonzero(in_region)
    assert sorted(p.name for p in (tmp_path / "figs").iterdir())  # state 0's maps
