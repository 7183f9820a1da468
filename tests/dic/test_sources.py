"""Frame sources (dic/sources.py): every kind, laziness, the faults, natural order, the CLI inputs."""
import warnings

import numpy as np
import pytest
import tifffile
from click.testing import CliRunner

import dic.sources as sources
from dic.cli import main
from dic.io import write_image
from dic.sources import Frame, FrameError, open_frames, open_inputs, open_pairs
from kernels.images import natural_key

H, W = 24, 32


def _frames(n, seed=0, shape=(H, W), dtype=np.uint8):
    rng = np.random.default_rng(seed)
    top = 255 if dtype == np.uint8 else 65535
    return (rng.random((n,) + shape) * top).astype(dtype)


@pytest.fixture
def folder(tmp_path):
    """img_0 .. img_11 as PNG (natural order differs from the lexical one), plus a text file."""
    d = tmp_path / "run"
    d.mkdir()
    ims = _frames(12)
    for i, im in enumerate(ims):
        write_image(d / f"img_{i}.png", im)
    return d, ims


def _write_video(path, frames, fps=10):
    import imageio.v3 as iio

    iio.imwrite(path, frames, plugin="FFMPEG", fps=fps, macro_block_size=8)
    return path


# -- every kind of source ------------------------------------------------------------------------
def test_list_of_files_and_arrays(tmp_path):
    ims = _frames(3)
    p = write_image(tmp_path / "a.tif", ims[0])
    wide = _frames(1, dtype=np.uint16)[0]
    src = open_frames([p, ims[1], ims[2].astype(np.float64), wide])
    assert len(src) == 4 and src.shape == (H, W)
    frames = list(src)
    assert [f.index for f in frames] == [0, 1, 2, 3] and isinstance(frames[0], Frame)
    assert [f.name for f in frames] == [str(p), "array[1]", "array[2]", "array[3]"]
    assert frames[0].image.dtype == np.uint8 and np.array_equal(frames[0].image, ims[0])
    assert frames[2].image.dtype == np.float32 and np.array_equal(frames[2].image, ims[2])  # float: float32
    assert frames[3].image.dtype == np.uint16 and np.array_equal(frames[3].image, wide)  # 16-bit kept
    assert src.files is None and open_frames([p]).files == [str(p)]
    assert np.array_equal(src[1].image, ims[1]) and src[-1].name == "array[3]"


def test_folder_in_natural_order_non_images_ignored_with_a_warning(folder):
    d, ims = folder
    (d / "notes.txt").write_text("log")
    (d / ".DS_Store").write_bytes(b"x")  # hidden files are not counted
    (d / "sub").mkdir()
    with pytest.warns(UserWarning, match=r"ignored 1 file\(s\) that are not images \(notes.txt\)"):
        src = open_frames(d)
    assert len(src) == 12 and src.shape == (H, W)
    names = [f.name for f in src]
    assert [n.rsplit("/", 1)[1] for n in names[:3]] == ["img_0.png", "img_1.png", "img_2.png"]
    assert names[10].endswith("img_10.png") and src.files == names
    assert all(np.array_equal(f.image, ims[f.index]) for f in src)


def test_natural_key_is_shared_with_calibration():
    import calibration.pipeline as pipeline

    names = ["b10.tif", "b2.tif", "B1.tif", "a.tif"]
    assert sorted(names, key=natural_key) == ["a.tif", "B1.tif", "b2.tif", "b10.tif"]
    assert pipeline.natural_key is natural_key


def test_glob_pattern(folder):
    d, ims = folder
    src = open_frames(str(d / "img_1*.png"))
    assert [f.name.rsplit("/", 1)[1] for f in src] == ["img_1.png", "img_10.png", "img_11.png"]
    assert np.array_equal(src[1].image, ims[10])
    (d / "img_1.txt").write_text("x")
    with pytest.warns(UserWarning, match="ignored 1 file"):
        assert len(open_frames(str(d / "img_1*"))) == 3
    with pytest.raises(ValueError, match="matches no files"):
        open_frames(str(d / "nothing*.png"))
    with pytest.raises(ValueError, match=r"matches 1 file\(s\) but no image file"):
        open_frames(str(d / "*.txt"))


def test_multi_page_tiff_page_by_page(tmp_path, monkeypatch):
    ims = _frames(5, dtype=np.uint16)
    p = tmp_path / "stack.tif"
    tifffile.imwrite(p, ims, photometric="minisblack")
    src = open_frames(p)
    assert len(src) == 5 and src.shape == (H, W)
    frames = list(src)
    assert [f.name for f in frames] == [f"{p}[page {k}]" for k in range(5)]
    assert all(f.image.dtype == np.uint16 and np.array_equal(f.image, ims[f.index]) for f in frames)
    assert np.array_equal(src[3].image, ims[3])
    # a one-page TIFF is one frame, read by read_image
    q = write_image(tmp_path / "one.tif", ims[0])
    assert len(open_frames(q)) == 1 and open_frames(q).files == [str(q)]
    # pages of different sizes: refused at the first page that differs, naming both
    r = tmp_path / "mixed.tif"
    with tifffile.TiffWriter(r) as tw:
        for im in (ims[0], ims[1], ims[2][:20]):
            tw.write(im)
    src = open_frames(r)
    got = []
    with pytest.raises(FrameError, match=r"frame 2 \(.*mixed.tif\[page 2\]\) is 32x20 px but frame 0 "
                                         r"\(.*mixed.tif\[page 0\]\) is 32x24 px") as err:
        for f in src:
            got.append(f.index)
    assert got == [0, 1] and err.value.index == 2
    with pytest.raises(FrameError, match="page 2"):
        src.check_shapes()


def test_video_grey_colour_and_undecodable(tmp_path):
    ims = _frames(6)
    ims[:, :, :] = np.clip(ims.astype(int) // 2 + 64, 0, 255).astype(np.uint8)
    p = _write_video(tmp_path / "film.mp4", ims)
    src = open_frames(p)
    assert src.shape == (H, W) and len(src) == 6
    frames = list(src)
    assert [f.name for f in frames] == [f"{p}[frame {k}]" for k in range(6)]
    assert all(f.image.dtype == np.uint8 and f.image.shape == (H, W) for f in frames)
    # lossy coding: the frames are close to what was written, and in order
    errors = np.array([[np.abs(f.image.astype(float) - im).mean() for im in ims] for f in frames])
    assert np.array_equal(errors.argmin(1), np.arange(6)) and errors.diagonal().max() < 20
    assert np.array_equal(src[2].image, frames[2].image)
    # colour video: refused without as_grey (naming the frame), BT.601 luma with it
    rgb = _frames(3, shape=(H, W, 3))
    c = _write_video(tmp_path / "colour.mp4", rgb)
    with pytest.raises(FrameError, match=r"frame 0: .*colour.mp4\[frame 0\] is a colour image.*as_grey=True"):
        list(open_frames(c))
    grey = list(open_frames(c, as_grey=True))
    assert len(grey) == 3 and grey[0].image.dtype == np.float32 and grey[0].image.shape == (H, W)
    # a file the decoder cannot read
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"not a video" * 100)
    with pytest.raises(ValueError, match=r"cannot decode video .*broken.mp4"):
        open_frames(bad)


def test_array_stack_is_read_frame_by_frame():
    ims = _frames(4)

    class Counting:
        """An array-like (T, H, W) that counts the frames taken from it."""

        shape = ims.shape
        taken = 0

        def __getitem__(self, k):
            Counting.taken += 1
            return ims[k]

    src = open_frames(Counting())
    assert len(src) == 4 and src.shape == (H, W) and Counting.taken == 0
    it = iter(src)
    first = next(it)
    assert first.name == "array[0]" and Counting.taken == 1
    assert np.array_equal(open_frames(ims)[3].image, ims[3])
    with pytest.raises(ValueError, match=r"is one image; a sequence is \(T, H, W\)"):
        open_frames(ims[0])
    with pytest.raises(ValueError, match="looks like one colour image"):
        open_frames(np.zeros((24, 32, 3)))
    with pytest.raises(ValueError, match="empty"):
        open_frames(np.zeros((0, 24, 32)))


def test_generator_is_not_materialised_and_read_once():
    ims = _frames(5)
    made = []

    def gen():
        for k, im in enumerate(ims):
            made.append(k)
            yield im

    src = open_frames(gen())
    assert made == [] and src.length is None
    with pytest.raises(TypeError, match="not known"):
        len(src)
    assert src.shape == (H, W) and made == [0]  # the first frame is peeked, not lost
    it = iter(src)
    assert [next(it).index, next(it).index] == [0, 1] and made == [0, 1]
    assert [f.index for f in it] == [2, 3, 4]
    with pytest.raises(ValueError, match="already been read"):
        list(src)


def test_file_list_is_read_on_demand(folder, monkeypatch):
    d, ims = folder
    reads = []
    real = sources.read_image
    monkeypatch.setattr(sources, "read_image", lambda p, **kw: reads.append(p) or real(p, **kw))
    src = open_frames(sorted(d.glob("*.png"), key=natural_key))
    assert len(src) == 12 and src.shape == (H, W) and reads == []  # the shape comes from the header
    for f in src:
        if f.index == 2:
            break
    assert len(reads) == 3


# -- faults --------------------------------------------------------------------------------------
def test_mixed_sizes_in_a_folder_refused_at_the_first_frame_that_differs(folder):
    d, _ = folder
    write_image(d / "img_5.png", _frames(1, shape=(20, 32))[0])
    src = open_frames(d)
    got = []
    with pytest.raises(FrameError, match=r"frame 5 \(.*img_5.png\) is 32x20 px but frame 0 \(.*img_0.png\) is "
                                         r"32x24 px; every image must have the same size"):
        for f in src:
            got.append(f.index)
    assert got == [0, 1, 2, 3, 4]
    with pytest.raises(FrameError, match="frame 5"):  # from the headers, before any work
        src.check_shapes()


def test_unreadable_frame_in_the_middle_is_named_after_the_frames_before_it(folder):
    d, _ = folder
    raw = (d / "img_4.png").read_bytes()
    (d / "img_4.png").write_bytes(raw[: len(raw) // 2])
    src = open_frames(d)
    src.check_shapes()  # an unreadable header is left to the frame's own read
    got = []
    with pytest.raises(FrameError, match=r"frame 4: cannot read image .*img_4.png") as err:
        for f in src:
            got.append(f.index)
    assert got == [0, 1, 2, 3] and err.value.index == 4 and err.value.name.endswith("img_4.png")


def test_bad_sources(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="holds no image files"):
        open_frames(tmp_path / "empty")
    (tmp_path / "text").mkdir()
    (tmp_path / "text" / "a.txt").write_text("x")
    with pytest.raises(ValueError, match=r"holds no image files .*1 other file"):
        open_frames(tmp_path / "text")
    with pytest.raises(ValueError, match="image file not found"):
        open_frames(tmp_path / "missing.tif")
    with pytest.raises(ValueError, match="video file not found"):
        open_frames(tmp_path / "missing.mp4")
    (tmp_path / "data.csv").write_text("1,2")
    with pytest.raises(ValueError, match="unsupported file type '.csv'"):
        open_frames(tmp_path / "data.csv")
    with pytest.raises(ValueError, match="list of frames is empty"):
        open_frames([])
    with pytest.raises(ValueError, match="cannot read frames from a int"):
        open_frames(3)
    with pytest.raises(ValueError, match="as_grey must be True or False"):
        open_frames([np.zeros((4, 4))], as_grey="yes")
    # a colour file, a non-finite array, a pair in a list: named
    write_image(tmp_path / "c.png", np.zeros((4, 4)), bits=8)
    colour = np.zeros((8, 8, 3), np.uint8)
    colour[..., 0] = 200
    with pytest.raises(FrameError, match=r"frame 0: array\[0\] is a colour image"):
        list(open_frames([colour]))
    assert list(open_frames([colour], as_grey=True))[0].image.dtype == np.float32
    with pytest.raises(FrameError, match=r"frame 1: array\[1\] contains NaN"):
        list(open_frames([np.zeros((4, 4)), np.full((4, 4), np.nan)]))
    with pytest.raises(FrameError, match="open_pairs"):
        list(open_frames([(np.zeros((4, 4)), np.zeros((4, 4)))]))


# -- stereo, joined inputs -------------------------------------------------------------
def test_open_pairs(folder, tmp_path):
    d, ims = folder
    stack = tmp_path / "right.tif"
    tifffile.imwrite(stack, ims[::-1], photometric="minisblack")
    pairs = open_pairs(d, stack)
    assert len(pairs) == 12 and pairs.shape == (H, W)
    got = list(pairs)
    assert all(left.index == right.index == k for k, (left, right) in enumerate(got))
    assert np.array_equal(got[3][1].image, ims[8]) and got[3][1].name.endswith("right.tif[page 3]")
    with pytest.raises(ValueError, match=r"differ in length: 12 left frame\(s\) .* but 2 right"):
        open_pairs(d, ims[:2])
    # a list of (left, right) pairs, a (T, 2, H, W) array, a generator of pairs
    pl = open_pairs([(ims[0], ims[1]), (ims[2], ims[3])])
    assert [(a.name, b.name) for a, b in pl] == [("left[0]", "right[0]"), ("left[1]", "right[1]")]
    both = np.stack([ims[:3], ims[3:6]], 1)
    assert np.array_equal(open_pairs(both)[2][1].image, ims[5])
    gen = open_pairs((a, b) for a, b in zip(ims[:3], ims[3:6]))
    assert [a.index for a, _ in gen] == [0, 1, 2]
    # left and right of different sizes; a side that ends early
    with pytest.raises(FrameError, match="pair 0: the left frame .* is 32x24 px but the right frame .* is 32x20 px"):
        list(open_pairs([ims[0]], [ims[0][:20]]))

    def short():
        yield ims[0]

    with pytest.raises(FrameError, match=r"the right sequence ended after 1 frame\(s\)"):
        list(open_pairs(ims[:3], short()))
    with pytest.raises(ValueError, match="one side only"):
        open_pairs(d)
    with pytest.raises(ValueError, match=r"pairs\[1\] must be a \(left, right\) pair"):
        open_pairs([(ims[0], ims[1]), ims[2]])


def test_open_inputs_joins_and_renumbers(folder, tmp_path):
    d, ims = folder
    stack = tmp_path / "stack.tif"
    tifffile.imwrite(stack, ims[:3], photometric="minisblack")
    first = write_image(tmp_path / "ref.png", ims[5])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        src = open_inputs([first, stack, str(d / "img_1*.png")])
    assert len(src) == 7 and src.files is None
    assert [f.name.rsplit("/", 1)[1] for f in src] == ["ref.png", "stack.tif[page 0]", "stack.tif[page 1]",
                                                        "stack.tif[page 2]", "img_1.png", "img_10.png", "img_11.png"]
    assert np.array_equal(src[4].image, ims[1])
    write_image(d / "img_10.png", ims[0][:20])
    with pytest.raises(FrameError, match=r"frame 5 \(.*img_10.png\) is 32x20 px but frame 0 \(.*ref.png\)"):
        list(open_inputs([first, stack, str(d / "img_1*.png")]))


# -- the command line ----------------------------------------------------------------------------
@pytest.fixture
def fake_tracker(monkeypatch):
    from test_cli_track import FakeTracker

    import dic.commands.track as cmd

    FakeTracker.calls = 0
    monkeypatch.setattr(cmd, "_make_tracker", lambda ref, **kw: FakeTracker(ref, **kw))
    return FakeTracker


def _track(args):
    return CliRunner().invoke(main, ["track", *args, "-q"], catch_exceptions=False)


def test_cli_track_folder_glob_stack_and_video(folder, tmp_path, fake_tracker):
    from dic.store import read_results

    d, ims = folder
    files = [str(d / f"img_{k}.png") for k in range(12)]
    runs = {"files": files, "folder": [str(d)], "glob": [str(d / "img_*.png")], "ref+folder": [files[0], str(d)]}
    results = {}
    for key, args in runs.items():
        out = tmp_path / f"{key}.h5"
        r = _track([*args, "-o", str(out), "--step", "8"])
        assert r.exit_code == 0, r.output
        results[key] = read_results(out)
    assert sorted(results["files"].frames) == list(range(1, 12))
    for key in ("folder", "glob"):  # the folder and the pattern give the same frames as the files
        assert sorted(results[key].frames) == list(range(1, 12))
        for k in range(1, 12):
            assert np.array_equal(results[key].frames[k].u, results["files"].frames[k].u)
            assert results[key].frames[k].path == files[k]
    assert len(results["ref+folder"].frames) == 12  # the reference, then every image of the folder
    # a multi-page TIFF and a video: the first frame is the reference
    tifffile.imwrite(tmp_path / "stack.tif", ims[:4], photometric="minisblack")
    r = _track([str(tmp_path / "stack.tif"), "-o", str(tmp_path / "stack.h5")])
    assert r.exit_code == 0, r.output
    res = read_results(tmp_path / "stack.h5")
    assert sorted(res.frames) == [1, 2, 3] and res.frames[2].path.endswith("stack.tif[page 2]")
    _write_video(tmp_path / "film.mp4", ims[:4])
    r = _track([str(tmp_path / "film.mp4"), "-o", str(tmp_path / "film.h5")])
    assert r.exit_code == 0, r.output
    assert read_results(tmp_path / "film.h5").frames[3].path.endswith("film.mp4[frame 3]")


def test_cli_track_input_faults(folder, tmp_path, fake_tracker):
    d, ims = folder
    r = _track([str(d / "nothing_*.png"), "-o", str(tmp_path / "a.h5")])
    assert r.exit_code == 1 and "matches no files" in r.output and "Traceback" not in r.output
    r = _track([str(d / "img_0.png"), "-o", str(tmp_path / "a.h5")])
    assert r.exit_code == 2 and "single image" in r.output
    write_image(d / "img_7.png", ims[0][:20])
    r = _track([str(d), "-o", str(tmp_path / "b.h5")])
    assert r.exit_code == 1 and "frame 7" in r.output and "img_7.png" in r.output and "same size" in r.output
    write_image(d / "img_7.png", ims[7])
    raw = (d / "img_9.png").read_bytes()
    (d / "img_9.png").write_bytes(raw[: len(raw) // 2])
    out = tmp_path / "c.h5"
    r = _track([str(d), "-o", str(out)])
    assert r.exit_code == 1 and "frame 9: cannot read image" in r.output and "saved in" in r.output
    from dic.store import read_results

    assert sorted(read_results(out).frames) == list(range(1, 9))  # every finished frame stays


def test_cli_stereo_two_sequences(tmp_path, monkeypatch):
    """``specula stereo`` with --left/--right folders or two inputs: the engine gets the pairs in order."""
    from calibration.camera import Camera
    from calibration.stereo import StereoRig

    K = np.array([[400.0, 0, W / 2 - 0.5], [0, 400.0, H / 2 - 0.5], [0, 0, 1]])
    rig = StereoRig(Camera(K, np.zeros(5), (W, H), "left"), Camera(K, np.zeros(5), (W, H), "right"),
                    np.eye(3), [-100.0, 0.0, 0.0])
    rig.save(tmp_path / "rig.json")
    ims = _frames(6)
    for side, part in (("left", ims[:3]), ("right", ims[3:])):
        (tmp_path / side).mkdir()
        for k, im in enumerate(part):
            write_image(tmp_path / side / f"{side}_{k}.png", im)
    tifffile.imwrite(tmp_path / "right.tif", ims[3:], photometric="minisblack")
    seen = []

    def fake_sequence(rig, pairs, out, **kw):
        from dic.sequence import SequenceSummary

        seen.append([(np.asarray(a) if not isinstance(a, str) else a, np.asarray(b) if not isinstance(b, str) else b)
                     for a, b in pairs])
        return SequenceSummary(path=out)

    import dic.sequence

    monkeypatch.setattr(dic.sequence, "stereo_sequence", fake_sequence)
    base = ["stereo", "--rig", str(tmp_path / "rig.json"), "-o", str(tmp_path / "o.h5"), "-q"]
    r = CliRunner().invoke(main, [*base, "--left", str(tmp_path / "left"), "--right", str(tmp_path / "right")])
    assert r.exit_code == 0, r.output
    assert seen[-1] == [(str(tmp_path / "left" / f"left_{k}.png"), str(tmp_path / "right" / f"right_{k}.png"))
                        for k in range(3)]
    r = CliRunner().invoke(main, [*base, str(tmp_path / "left" / "left_*.png"), str(tmp_path / "right.tif")])
    assert r.exit_code == 0, r.output
    assert [a for a, _ in seen[-1]] == [str(tmp_path / "left" / f"left_{k}.png") for k in range(3)]
    assert all(np.array_equal(b, ims[3 + k]) for k, (_, b) in enumerate(seen[-1]))  # pages read on demand
    # faults: unequal lengths, one side only, both forms at once
    r = CliRunner().invoke(main, [*base, "--left", str(tmp_path / "left"), "--right", str(tmp_path / "right" /
                                                                                          "right_0.png")])
    assert r.exit_code == 1 and "differ in length: 3 left frame(s)" in r.output
    r = CliRunner().invoke(main, [*base, "--left", str(tmp_path / "left")])
    assert r.exit_code == 2 and "--left and --right go together" in r.output
    r = CliRunner().invoke(main, [*base, "a.png", "b.png", "--left", str(tmp_path / "left")])
    assert r.exit_code == 2 and "not both" in r.output


def test_a_failing_generator_and_a_bad_frame_of_joined_inputs_are_named(folder, tmp_path):
    def gen():
        yield np.zeros((H, W))
        raise OSError("camera disconnected")

    got = []
    with pytest.raises(FrameError, match=r"frame 1 \(array\[1\]\): the iterable failed: OSError: camera disconnected"):
        for f in open_frames(gen()):
            got.append(f.index)
    assert got == [0]
    d, ims = folder
    first = write_image(tmp_path / "ref.png", ims[0])
    (d / "img_2.png").write_bytes(b"broken")
    src = open_inputs([first, d])
    with pytest.raises(FrameError, match=r"frame 3: cannot read image .*img_2.png") as err:
        src[3]
    assert err.value.index == 3
    with pytest.raises(FrameError, match=r"frame 3: cannot read image .*img_2.png"):
        list(src)
