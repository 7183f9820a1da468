"""``specula track`` (dic/commands/track.py) with click's CliRunner on small images."""
import importlib.util
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from dic.cli import main
from dic.io import write_image
from dic.store import read_results
from dic.synth import speckle_pair

HAVE_TRACK = importlib.util.find_spec("dic._track") is not None


@pytest.fixture
def images(tmp_path):
    """A reference and two current images (rigid shifts of 0.4 and 0.8 px along x), 8-bit TIFF."""
    ref, cur1 = speckle_pair((96, 112), (0.4, -0.3), seed=21)
    _, cur2 = speckle_pair((96, 112), (0.8, -0.6), seed=21)
    paths = [write_image(tmp_path / name, img, bits=8) for name, img in
             [("ref.tif", ref), ("cur1.tif", cur1), ("cur2.tif", cur2)]]
    return [str(p) for p in paths]


class FakeTracker:
    """Stands in for dic.track so the CLI mechanics are tested on their own: returns a grid
    field whose u is the frame's mean grey level (so frames are distinguishable)."""

    calls = 0
    guesses = []

    def __init__(self, reference, *, subset, step, order, **kw):
        h, w = reference.shape
        r = subset // 2
        xs, ys = np.meshgrid(np.arange(r, w - r, step, dtype=float), np.arange(r, h - r, step, dtype=float))
        self.points = np.stack([xs.ravel(), ys.ravel()], 1)
        self.order = order

    def track(self, current, guess=None):
        FakeTracker.calls += 1
        FakeTracker.guesses.append(None if guess is None else np.array(guess))
        n = len(self.points)
        k = 6 if self.order == 1 else 12
        u = np.full(n, float(np.mean(current)))
        params = np.zeros((n, k))
        params[:, 0] = u
        valid = np.ones(n, bool)
        valid[0] = False
        return SimpleNamespace(points=self.points, u=u, v=0.001 * self.points[:, 0], params=params,
                               zncc=np.ones(n, np.float32), iterations=np.ones(n, np.int32),
                               status=np.zeros(n, np.int8), valid=valid)


@pytest.fixture
def fake(monkeypatch):
    import dic.commands.track as cmd

    FakeTracker.calls = 0
    FakeTracker.guesses = []
    monkeypatch.setattr(cmd, "_make_tracker", lambda ref, **kw: FakeTracker(ref, **kw))
    return FakeTracker


def run(args):
    return CliRunner().invoke(main, ["track", *args], catch_exceptions=False)


def test_writes_frames_strain_and_figures(images, tmp_path, fake):
    out = tmp_path / "res.h5"
    r = run([*images, "-o", str(out), "--step", "8", "--figure", str(tmp_path / "figs")])
    assert r.exit_code == 0, r.output
    res = read_results(out)
    assert sorted(res.frames) == [1, 2] and res.reference["shape"] == (96, 112)
    assert res.settings["subset"] == 21 and res.settings["step"] == 8
    assert res.frames[2].path == images[2]
    # v = 0.001 x exactly -> dv/dx = 0.001 from the plane fits (float64 rounding only)
    s = res.frames[1].strain
    assert np.nanmax(np.abs(s["dvdx"] - 0.001)) < 1e-9 and s["valid"].sum() == len(s["valid"]) - 1
    # frame 2 started from frame 1's result: its parameters, with the invalid point at the mean
    g = fake.guesses[1]
    assert fake.guesses[0] is None and np.allclose(g[:, 0], res.frames[1].u[1])
    assert (tmp_path / "figs" / "frame_000001.png").stat().st_size > 1000
    assert "frame 2:" in r.output and "valid points" in r.output


def test_figures_share_one_colour_range_over_the_sequence(images, tmp_path, fake, monkeypatch):
    """The --figure maps rescaled their colours per frame (and drew signed strain on a sequential map)."""
    import dic.plots.fields as plots

    drawn = []
    real = plots.write_field_figure

    def spy(path, reference, field, strain=None, **kw):
        fig = plots.field_figure(reference, field, strain, **{k: v for k, v in kw.items() if k != "dpi"})
        drawn.append({ax.get_title(): (im.get_clim(), im.get_cmap().name) for ax in fig.axes for im in ax.images
                      if im.get_gid() == "map"})
        return real(path, reference, field, strain, **kw)

    monkeypatch.setattr(plots, "write_field_figure", spy)
    out = tmp_path / "res.h5"
    r = run([*images, "-o", str(out), "--step", "8", "--figure", str(tmp_path / "figs"), "--figure-limits", "frame"])
    assert r.exit_code == 0, r.output
    u_title = "displacement u (px)"
    assert drawn[0][u_title][0] != drawn[1][u_title][0]  # per frame: u (the frame's mean grey level) differs
    # diverging (centred on zero) exactly where the range spans zero, else sequential
    assert all(cmap == ("RdBu_r" if lo < 0 < hi else "viridis") and (lo == -hi or not lo < 0 < hi)
               for d in drawn for (lo, hi), cmap in d.values())
    drawn.clear()
    r = run([*images, "-o", str(out), "--step", "8", "--figure", str(tmp_path / "figs2"), "--figure-limits", "sequence"])
    assert r.exit_code == 0, r.output
    assert len(drawn) == 2 and drawn[0] == drawn[1]  # resumed frames are drawn too, on one scale
    lo, hi = drawn[0][u_title][0]
    us = [read_results(out).frames[k].u[1] for k in (1, 2)]
    assert lo <= min(us) + 1e-9 and hi >= max(us) - 1e-9 and (lo == -hi or not lo < 0 < hi)
    assert sorted(p.name for p in (tmp_path / "figs2").iterdir()) == ["frame_000001.png", "frame_000002.png"]
    r = run([*images, "-o", str(out), "--figure-limits", "global"])
    assert r.exit_code == 2 and "--figure-limits" in r.output


def test_resume_skips_finished_frames(images, tmp_path, fake):
    out = tmp_path / "res.h5"
    assert run([images[0], images[1], "-o", str(out), "-q"]).exit_code == 0
    assert fake.calls == 1
    r = run([*images, "-o", str(out)])
    assert r.exit_code == 0 and fake.calls == 2  # frame 1 skipped, frame 2 computed
    assert np.allclose(fake.guesses[1][:, 0], read_results(out).frames[1].u[1])  # guess read back from the file
    assert "1 frame(s) were already" in r.output
    assert sorted(read_results(out).frames) == [1, 2]
    r = run([*images, "-o", str(out), "--step", "6"])
    assert r.exit_code == 1 and "different settings" in r.output
    r = run([*images, "-o", str(out), "--step", "6", "--overwrite", "-q"])
    assert r.exit_code == 0 and fake.calls == 4


def test_clean_errors(images, tmp_path, fake):
    out = str(tmp_path / "res.h5")
    r = run([images[0], str(tmp_path / "missing.tif"), "-o", out])
    assert r.exit_code == 1 and "image file not found" in r.output and "Traceback" not in r.output
    raw = open(images[1], "rb").read()
    (tmp_path / "trunc.tif").write_bytes(raw[: len(raw) // 2])
    r = run([images[0], images[1], str(tmp_path / "trunc.tif"), "-o", out])
    assert r.exit_code == 1 and "frame 2" in r.output and "cannot read image" in r.output
    assert sorted(read_results(out).frames) == [1]  # the finished frame was kept
    write_image(tmp_path / "small.tif", np.zeros((50, 50)), bits=8)
    r = run([images[0], str(tmp_path / "small.tif"), "-o", str(tmp_path / "b.h5")])
    assert r.exit_code == 1 and "same size" in r.output
    r = run([*images, "-o", str(tmp_path / "c.h5"), "--subset", "20"])
    assert r.exit_code == 2 and "odd" in r.output
    r = run([*images, "-o", str(tmp_path / "c.txt")])
    assert r.exit_code == 2 and ".h5" in r.output
    import imageio.v3 as iio

    rgb = np.zeros((96, 112, 3), np.uint8)
    rgb[..., 0] = 200  # true colour (grey stored as RGB, with equal channels, would be read as grey)
    iio.imwrite(tmp_path / "rgb.png", rgb)
    r = run([str(tmp_path / "rgb.png"), images[1], "-o", str(tmp_path / "d.h5")])
    assert r.exit_code == 1 and "colour image" in r.output


@pytest.mark.skipif(not HAVE_TRACK, reason="dic.track is not in this checkout yet")
def test_end_to_end_with_the_real_tracker(images, tmp_path):
    out = tmp_path / "res.h5"
    r = run([*images, "-o", str(out), "--step", "8", "--device", "cpu", "-q"])
    assert r.exit_code == 0, r.output
    res = read_results(out)
    for index, (u, v) in [(1, (0.4, -0.3)), (2, (0.8, -0.6))]:
        f = res.frames[index]
        # the top row of subsets (y = 10, subset 21) moves out of the image with v < 0: those
        # points must be reported OUT_OF_BOUNDS, every other one is valid
        assert f.valid.mean() > 0.8 and np.all(f.status[~f.valid] == 2)
        # noise-free 8-bit Boolean speckle, 21 px subsets: IC-GN errors are ~0.01 px; 0.03 allows
        # the 8-bit quantisation and the few border subsets
        assert np.max(np.abs(f.u[f.valid] - u)) < 0.03 and np.max(np.abs(f.v[f.valid] - v)) < 0.03


@pytest.mark.skipif(not HAVE_TRACK, reason="dic.track is not in this checkout yet")
def test_search_option_finds_a_large_shift(tmp_path):
    """A 7.6 px shift is beyond IC-GN's reach from zero with 21 px subsets; --search finds it."""
    ref, cur = speckle_pair((96, 112), (7.6, -5.2), seed=5)
    paths = [str(write_image(tmp_path / n, im, bits=8)) for n, im in [("r.tif", ref), ("c.tif", cur)]]
    out = tmp_path / "res.h5"
    r = run([*paths, "-o", str(out), "--step", "10", "--search", "12", "--device", "cpu", "-q"])
    assert r.exit_code == 0, r.output
    f = read_results(out).frames[1]
    # the run record (dic.sequence.options): the method and the radius under the library's names
    assert res_settings(out)["search"] == "pyramid" and res_settings(out)["search_radius"] == 12
    assert f.valid.sum() >= 10
    # same bound as above: noise-free 8-bit speckle, IC-GN errors ~0.01 px
    assert np.max(np.abs(f.u[f.valid] - 7.6)) < 0.03 and np.max(np.abs(f.v[f.valid] + 5.2)) < 0.03


def res_settings(path):
    return read_results(path).settings


def test_no_valid_point_says_what_to_try(tmp_path):
    """A 23 px motion without --search: no point is valid; the command says so and names --search
    (before: 0 of 2304 valid, exit status 0 and no hint)."""
    ref, cur = speckle_pair((128, 144), (23.0, 0.0), seed=6)
    paths = [str(write_image(tmp_path / n, im, bits=8)) for n, im in [("r.tif", ref), ("c.tif", cur)]]
    out = tmp_path / "res.h5"
    r = run([*paths, "-o", str(out), "--step", "10", "--device", "cpu", "-q"])
    assert r.exit_code == 0, r.output
    assert "Warning: 2-D tracking: only" in r.output and "--search" in r.output
    r = run([*paths, "-o", str(tmp_path / "ok.h5"), "--step", "10", "--search", "30", "--device", "cpu", "-q"])
    assert r.exit_code == 0 and "Warning" not in r.output, r.output


def test_output_in_use_by_a_running_job_is_refused_not_truncated(images, tmp_path, fake):
    """Before: --overwrite truncated the running job's file (unreadable afterwards) and printed a
    BlockingIOError traceback."""
    from dic.store import ResultWriter

    out = tmp_path / "res.h5"
    assert run([*images, "-o", str(out), "-q"]).exit_code == 0
    with ResultWriter(out, reference_path="other.tif", reference_shape=(96, 112), mode="overwrite") as running:
        running.write_frame(1, fake_field_for_test())
        for extra in ([], ["--overwrite"]):
            r = run([*images, "-o", str(out), "-q", *extra])
            assert r.exit_code == 1 and "is in use by another process" in r.output, r.output
            assert "corrupt" not in r.output and "Traceback" not in r.output
        running.write_frame(2, fake_field_for_test())
    res = read_results(out)
    assert sorted(res.frames) == [1, 2] and res.reference["path"] == "other.tif"  # the running job's file, whole


def fake_field_for_test():
    pts = np.array([[10.0, 10.0], [20.0, 10.0]])
    return SimpleNamespace(points=pts, u=np.zeros(2), v=np.zeros(2))


def test_resume_with_other_images_is_refused(images, tmp_path, fake):
    """Before: rerunning into a file with a different image list exited 0 and skipped every frame."""
    out = tmp_path / "res.h5"
    assert run([*images, "-o", str(out), "-q"]).exit_code == 0
    r = run([images[0], images[2], images[1], "-o", str(out), "-q"])  # the current images swapped
    assert r.exit_code == 1 and "Traceback" not in r.output
    assert f"holds frame 1 computed from {images[1]}, but this run gives {images[2]} for it (the images differ)" \
        in r.output.replace("\n", " ")
    assert "--overwrite" in r.output
    # the same images under another name are the same frames: resumed
    import shutil

    copy = shutil.copy(images[1], tmp_path / "renamed.tif")
    r = run([images[0], str(copy), "-o", str(out)])
    assert r.exit_code == 0 and "1 frame(s) were already" in r.output
    r = run([images[0], images[2], images[1], "-o", str(out), "-q", "--overwrite"])
    assert r.exit_code == 0 and read_results(out).frames[1].path == images[2]


def test_full_disk_ends_the_run_with_one_message_and_resumes(images, tmp_path, fake, monkeypatch):
    import errno

    import h5py

    out = tmp_path / "res.h5"
    original = h5py.Group.create_dataset

    def full_at_frame_2(self, name, *args, **kw):
        if "000002.partial" in self.name:
            raise OSError(errno.ENOSPC, "No space left on device")
        return original(self, name, *args, **kw)

    monkeypatch.setattr(h5py.Group, "create_dataset", full_at_frame_2)
    r = run([*images, "-o", str(out), "-q"])
    assert r.exit_code == 1 and "Traceback" not in r.output
    assert f"could not write frame 2 to {out}: disk full (No space left on device)" in r.output.replace("\n", " ")
    monkeypatch.undo()
    assert sorted(read_results(out).frames) == [1]
    u1 = read_results(out).frames[1].u
    r = run([*images, "-o", str(out)])
    assert r.exit_code == 0 and "1 frame(s) were already" in r.output
    res = read_results(out)
    assert sorted(res.frames) == [1, 2] and np.array_equal(res.frames[1].u, u1)


def test_output_that_cannot_be_written(images, tmp_path, fake):
    (tmp_path / "afile").write_text("x")
    r = run([*images, "-o", str(tmp_path / "afile" / "res.h5")])
    assert r.exit_code == 1 and "Traceback" not in r.output
    assert "afile is a file, not a folder" in r.output


def test_regions_of_interest(images, tmp_path):
    """--roi, --roi-polygon (inline, JSON and CSV file) and --mask keep the grid points inside the region, the
    same as the library's roi= (dic.correlation.points), and are stored in the file's settings."""
    import json

    from dic._track import track
    from dic.correlation.points import grid

    shape = (96, 112)
    mask = np.zeros(shape, np.uint8)
    mask[20:70, 30:90] = 1
    write_image(tmp_path / "mask.png", mask, bits=8)
    (tmp_path / "poly.json").write_text(json.dumps({"polygon": [[15, 15], [95, 20], [60, 80]]}))
    (tmp_path / "poly.csv").write_text("x,y\n15,15\n95,20\n60,80\n")
    cases = [(["--roi", "20", "15", "70", "60"], (20.0, 15.0, 70.0, 60.0), [20.0, 15.0, 70.0, 60.0]),
             (["--roi-polygon", "15,15; 95,20; 60,80"], [(15, 15), (95, 20), (60, 80)],
              {"polygon": [[15.0, 15.0], [95.0, 20.0], [60.0, 80.0]]}),
             (["--roi-polygon", str(tmp_path / "poly.json")], [(15, 15), (95, 20), (60, 80)], None),
             (["--roi-polygon", str(tmp_path / "poly.csv")], [(15, 15), (95, 20), (60, 80)], None),
             (["--mask", str(tmp_path / "mask.png")], mask, None)]
    for k, (opts, roi, stored) in enumerate(cases):
        out = tmp_path / f"r{k}.h5"
        r = run([images[0], images[1], "-o", str(out), "--step", "5", "--device", "cpu", "-q", *opts])
        assert r.exit_code == 0, r.output
        res = read_results(out)
        expected = grid(shape, 5, margin=10, roi=roi)
        assert np.array_equal(res.frames[1].points, expected) and 0 < len(expected) < len(grid(shape, 5, margin=10))
        assert np.array_equal(track(images[0], images[1], step=5, roi=roi, device="cpu").points, expected)
        if stored is not None:
            assert res.settings["roi"] == stored
    assert read_results(tmp_path / "r4.h5").settings["roi"]["mask"] == str(tmp_path / "mask.png")
    # without a region the run record says so (every default is written out: docs/results_format.md)
    r = run([images[0], images[1], "-o", str(tmp_path / "all.h5"), "--step", "5", "--device", "cpu", "-q"])
    assert r.exit_code == 0 and read_results(tmp_path / "all.h5").settings["roi"] is None
    # clear errors, no traceback
    write_image(tmp_path / "small.png", mask[:50], bits=8)
    for opts, code, msg in [(["--roi", "1", "2", "3", "4", "--mask", str(tmp_path / "mask.png")], 2,
                             "give one region of interest, not --roi and --mask"),
                            (["--roi-polygon", "1,2;3"], 2, "x,y;x,y"),
                            (["--roi-polygon", "10,10;20,20"], 1, "at least 3 vertices"),
                            (["--mask", str(tmp_path / "small.png")], 1, "is 112x50 px but the images are 112x96 px"),
                            (["--mask", str(tmp_path / "none.png")], 1, "image file not found"),
                            (["--roi", "200", "200", "300", "300"], 1, "empty ROI")]:
        r = run([images[0], images[1], "-o", str(tmp_path / "bad.h5"), "--device", "cpu", "-q", *opts])
        assert r.exit_code == code and msg in r.output and "Traceback" not in r.output, (opts, r.output)
