"""Limits before work and readers that read what cameras write (issue 24, defects 4-6, 9-14, 16 and the
"also seen" list): each test failed before its fix.

Image-size limit (kernels.images.max_image_pixels), compressed TIFFs (imagecodecs, or Pillow), empty
strings for path/text options, --tol / --max-memory / screen / frame / sample bounds, a moved
``speckle --second``, lab camera names that collide, camera files without a size, DICe's identity
rotation of camera 0, a Dask scheduler without workers, a cut-short AVI, a bow-tie ROI polygon,
symlink loops and FIFOs, a history point outside the measured points, stereo runs without a valid point.
"""
import json
import os
import re
import struct
import time
import warnings
import zlib

import numpy as np
import pytest
from click.testing import CliRunner

from dic.cli import main
from kernels.images import read_image

MAX_IMAGE_PIXELS_ENV = "SPECULA_MAX_IMAGE_PIXELS"


def bomb_tiff(path, side: int = 40000, tile: int = 1024) -> None:
    """A tiled, Deflate-compressed 8-bit TIFF declaring ``side`` x ``side`` px, written by hand: every tile
    entry points at one compressed all-zero tile (about 14 KB for 40000 x 40000 px)."""
    n = (-(-side // tile)) ** 2
    data = zlib.compress(bytes(tile * tile), 9)
    entries = [(256, 4, 1, side), (257, 4, 1, side), (258, 3, 1, 8), (259, 3, 1, 8), (262, 3, 1, 1),
               (277, 3, 1, 1), (322, 4, 1, tile), (323, 4, 1, tile), (324, 4, n, None), (325, 4, n, None)]
    offsets_at = 8 + 2 + 12 * len(entries) + 4
    counts_at = offsets_at + 4 * n
    data_at = counts_at + 4 * n
    out = bytearray(b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", len(entries)))
    for tag, kind, count, value in entries:
        value = {324: offsets_at, 325: counts_at}.get(tag, value)
        out += struct.pack("<HHI", tag, kind, count)
        out += struct.pack("<HH", value, 0) if kind == 3 else struct.pack("<I", value)
    out += struct.pack("<I", 0)
    out += struct.pack(f"<{n}I", *([data_at] * n)) + struct.pack(f"<{n}I", *([len(data)] * n)) + data
    with open(path, "wb") as fh:
        fh.write(out)


def _speckle(shape=(64, 80), seed=3):
    from dic.synth import speckle_pair

    return speckle_pair(shape, None, seed=seed)[0]


def _clean(res) -> None:
    """No traceback: a refusal is a message (click's exit 1 or 2), never an exception of the code."""
    assert res.exception is None or isinstance(res.exception, SystemExit), res.output
    assert "Traceback" not in res.output


# ---------------------------------------------------------------------------------------------
# 5: declared image size before decoding
def test_a_decompression_bomb_tiff_is_refused_at_once(tmp_path):
    bomb = tmp_path / "bomb.tif"
    bomb_tiff(bomb)
    assert os.path.getsize(bomb) < 30_000
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=r"40000 x 40000 px .* more than the limit of 268,435,456 pixels") as err:
        read_image(bomb)
    assert time.perf_counter() - t0 < 2.0
    assert MAX_IMAGE_PIXELS_ENV in str(err.value) and str(bomb) in str(err.value)
    ok = tmp_path / "ok.tif"
    from dic.io import write_image

    write_image(ok, _speckle(), bits=8)
    bomb_tiff(tmp_path / "bomb2.tif")
    for args in (["track", str(bomb), str(tmp_path / "bomb2.tif"), "-o", str(tmp_path / "r.h5")], ["speckle", str(bomb)],
                 ["speckle", str(ok), "--second", str(bomb)]):
        t0 = time.perf_counter()
        res = CliRunner().invoke(main, args)
        assert res.exit_code == 1 and "40000 x 40000" in res.output, res.output
        assert time.perf_counter() - t0 < 30.0
        _clean(res)


def test_the_size_limit_covers_every_format_and_can_be_raised(tmp_path, monkeypatch):
    from dic.io import write_image
    from kernels.images import DEFAULT_MAX_IMAGE_PIXELS, max_image_pixels, set_max_image_pixels

    image = _speckle((40, 50))
    paths = [write_image(tmp_path / f"a{ext}", image, bits=8) for ext in (".tif", ".png", ".bmp")]
    assert max_image_pixels() == DEFAULT_MAX_IMAGE_PIXELS == 1 << 28
    monkeypatch.setenv(MAX_IMAGE_PIXELS_ENV, "1999")  # 40 x 50 = 2000 px: one too many
    for p in paths:
        with pytest.raises(ValueError, match="50 x 40 px = 2,000 pixels, more than the limit of 1,999"):
            read_image(p)
    monkeypatch.setenv(MAX_IMAGE_PIXELS_ENV, "2000")
    for p in paths:
        assert np.array_equal(read_image(p), np.clip(np.rint(image), 0, 255).astype(np.uint8))
    set_max_image_pixels(1000)  # the function wins over the environment
    try:
        with pytest.raises(ValueError, match="limit of 1,000"):
            read_image(paths[0])
    finally:
        set_max_image_pixels(None)
    for bad in ("lots", "0", "-5"):
        monkeypatch.setenv(MAX_IMAGE_PIXELS_ENV, bad)
        with pytest.raises(ValueError, match=MAX_IMAGE_PIXELS_ENV):
            max_image_pixels()
    monkeypatch.setenv(MAX_IMAGE_PIXELS_ENV, str(2048 * 2048))  # a bomb under a raised limit is read
    bomb_tiff(tmp_path / "small.tif", side=2048)
    assert read_image(tmp_path / "small.tif").shape == (2048, 2048)


def test_the_size_limit_covers_multi_page_tiffs(tmp_path, monkeypatch):
    import tifffile

    from dic.sources import open_frames

    stack = np.stack([np.clip(_speckle((40, 50), seed=k), 0, 255).astype(np.uint8) for k in range(3)])
    tifffile.imwrite(tmp_path / "stack.tif", stack, photometric="minisblack")
    monkeypatch.setenv(MAX_IMAGE_PIXELS_ENV, "1999")
    with pytest.raises(ValueError, match="more than the limit of 1,999"):
        list(open_frames(str(tmp_path / "stack.tif")))


# ---------------------------------------------------------------------------------------------
# 6: compressed TIFFs
COMPRESSIONS = ["tiff_lzw", "tiff_adobe_deflate", "packbits"]


def _pillow_tiff(path, image, compression):
    from PIL import Image

    Image.fromarray(image).save(path, compression=compression)


@pytest.fixture
def no_imagecodecs(monkeypatch):
    """tifffile as it is without the imagecodecs package: its pure-Python codecs only (no LZW, no JPEG)."""
    import tifffile.tifffile as tt

    pure = pytest.importorskip("tifffile._imagecodecs")
    monkeypatch.setattr(tt, "imagecodecs", pure)
    monkeypatch.setattr(tt.TIFF.DECOMPRESSORS, "_codecs", {1: tt.identityfunc})
    yield
    tt.TIFF.DECOMPRESSORS._codecs = {1: tt.identityfunc}  # forget the pure codecs picked up meanwhile


@pytest.mark.parametrize("fallback", [False, True], ids=["imagecodecs", "pillow"])
def test_lzw_deflate_packbits_and_jpeg_tiffs_are_read(tmp_path, request, fallback):
    import cv2

    if fallback:
        request.getfixturevalue("no_imagecodecs")
    image = np.clip(np.rint(_speckle((48, 64))), 0, 255).astype(np.uint8)
    image16 = image.astype(np.uint16) * 257
    for c in COMPRESSIONS:
        _pillow_tiff(tmp_path / f"{c}.tif", image, c)
        assert np.array_equal(read_image(tmp_path / f"{c}.tif"), image), c
    cv2.imwrite(str(tmp_path / "opencv.tif"), image16)  # OpenCV writes LZW by default
    assert np.array_equal(read_image(tmp_path / "opencv.tif"), image16)
    smooth = (100 + 50 * np.sin(np.arange(64)[None, :] / 9.0) * np.cos(np.arange(48)[:, None] / 7.0)).astype(np.uint8)
    _pillow_tiff(tmp_path / "jpeg.tif", smooth, "jpeg")
    got = read_image(tmp_path / "jpeg.tif")
    assert got.shape == smooth.shape and got.dtype == np.uint8
    assert np.abs(got.astype(int) - smooth).mean() < 2.0  # JPEG is lossy: close, not equal


def test_a_missing_codec_is_named_and_never_called_corruption(tmp_path, no_imagecodecs, monkeypatch):
    import kernels.images as images

    image = np.clip(np.rint(_speckle((48, 64))), 0, 255).astype(np.uint8)
    _pillow_tiff(tmp_path / "lzw.tif", image, "tiff_lzw")

    def pillow_cannot(path, k):
        raise OSError("decoder tiff_lzw not available")

    monkeypatch.setattr(images, "_pillow_tiff", pillow_cannot)
    with pytest.raises(ValueError) as err:
        read_image(tmp_path / "lzw.tif")
    text = str(err.value)
    assert "'imagecodecs' package" in text and "pip install imagecodecs" in text and "LZW" in text
    assert "corrupt" not in text and "truncated" not in text


# ---------------------------------------------------------------------------------------------
# 9: empty strings
@pytest.fixture(scope="module")
def two_images(tmp_path_factory):
    from dic.io import write_image
    from dic.synth import speckle_pair

    folder = tmp_path_factory.mktemp("two")
    ref, cur = speckle_pair((64, 80), (0.5, 0.0), seed=4)
    return [str(write_image(folder / "ref.tif", ref, bits=8)), str(write_image(folder / "cur.tif", cur, bits=8))]


@pytest.mark.parametrize("option", ["--roi-polygon", "--vtk", "--figures", "--mask", "--device", "--output",
                                    "--reference", "--max-memory", "--scheduler"])
def test_empty_strings_are_refused_for_track(two_images, tmp_path, option):
    args = ["track", *two_images, "-o", str(tmp_path / "r.h5"), "-q", "--step", "16", option, ""]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 2 and "must not be empty" in res.output and option in res.output, res.output
    assert not (tmp_path / "r.h5").exists()
    _clean(res)


@pytest.mark.parametrize("args", [
    ["stereo", "--rig", "r.json", "a.tif", "b.tif", "-o", "x.h5", "--vtk", ""],
    ["stereo", "--rig", "r.json", "a.tif", "b.tif", "-o", "x.h5", "--figures", ""],
    ["stereo", "--rig", "", "a.tif", "b.tif", "-o", "x.h5"],
    ["track", "", "b.tif", "-o", "x.h5"],
    ["export", "x.h5", "-f", "csv", "-o", ""],
    ["history", "", "--point", "1,1", "--csv", "t.csv"],
    ["profile", "x.h5", "--from", "1,1", "--to", "2,2", "--plot", ""],
    ["target", "fringes", "-o", "", "--screen", "100x100"],
    ["target", "checkerboard", "-o", "out", "--screen", ""],
    ["speckle", "", "--second", "b.tif"],
    ["speckle", "a.tif", "--second", ""],
    ["lab", "render", "scene.toml", "-o", ""],
])
def test_empty_strings_are_refused_everywhere(args, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(main, args)
    _clean(res)
    assert res.exit_code == 2 and "must not be empty" in res.output, res.output
    assert list(tmp_path.iterdir()) == []  # nothing written into the current folder


# ---------------------------------------------------------------------------------------------
# 10: --tol
def test_tol_is_at_most_a_tenth_of_a_pixel(two_images, tmp_path):
    from dic._track import Tracker
    from dic.correlation.params import MAX_TOL_PX, check_tol

    assert MAX_TOL_PX == 0.1 and check_tol(0.1) == 0.1 and check_tol(1e-3) == 1e-3
    res = CliRunner().invoke(main, ["track", *two_images, "-o", str(tmp_path / "r.h5"), "--tol", "1e300"])
    assert res.exit_code == 2 and "--tol" in res.output and "0.1" in res.output, res.output
    _clean(res)
    with pytest.raises(ValueError, match=r"tol must be at most 0.1 px"):
        Tracker(np.zeros((40, 40)) + np.arange(40), tol=0.5)
    with pytest.raises(ValueError, match="tol must be at most 0.1 px"):
        check_tol(1e300)


# ---------------------------------------------------------------------------------------------
# 13 and 14: memory budget, screen, frames, samples, positions
def test_a_max_memory_below_the_working_set_says_the_bound(two_images, tmp_path):
    from dic.sequence.chunks import bytes_per_poi

    base = ["track", *two_images, "--step", "16", "--device", "cpu", "-q"]
    res = CliRunner().invoke(main, [*base, "-o", str(tmp_path / "a.h5"), "--max-memory", "100"])
    assert res.exit_code == 2 and f"cannot hold the data of one point ({bytes_per_poi(1)} bytes" in res.output
    _clean(res)
    res = CliRunner().invoke(main, [*base, "-o", str(tmp_path / "b.h5"), "--max-memory", "1K"])
    assert res.exit_code == 0, res.output
    n_points = 12  # 64 x 80 px at step 16, 10 px from the borders: 3 x 4
    floor = n_points * bytes_per_poi(1)  # all the points' data is less than the image as float32 (20 480 bytes)
    assert f"below the working set of this run, {floor:,} bytes" in res.output
    assert "chunks of 1," in res.output



def test_the_library_says_the_bound_of_max_memory_too(two_images, tmp_path):
    """Before: track_sequence(max_memory=1024) crawled without a word (only the CLI checked the budget)."""
    from dic.io import read_image
    from dic.sequence import track_sequence
    from dic.sequence.chunks import bytes_per_poi

    ref, cur = (read_image(p) for p in two_images)
    with pytest.raises(ValueError, match=f"cannot hold the data of one point \\({bytes_per_poi(1)} bytes"):
        track_sequence(ref, [cur], tmp_path / "a.h5", step=16, max_memory=100)
    with pytest.warns(UserWarning, match="below the working set of this run") as caught:
        summary = track_sequence(ref, [cur], tmp_path / "b.h5", step=16, max_memory=1024)
    assert "chunks of 1," in str(caught[0].message) and len(summary) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a budget above the working set: no word
        track_sequence(ref, [cur], tmp_path / "c.h5", step=16, max_memory=2**30)

@pytest.fixture(scope="module")
def result_file(two_images, tmp_path_factory):
    out = tmp_path_factory.mktemp("res") / "r.h5"
    res = CliRunner().invoke(main, ["track", *two_images, "-o", str(out), "--step", "8", "--device", "cpu", "-q"])
    assert res.exit_code == 0, res.output
    return str(out)


@pytest.mark.parametrize("args, exit_code, message", [
    (["target", "fringes", "--screen", "100000x100000", "-o", "{tmp}/t"], 1, "at most 16384"),
    (["target", "checkerboard", "--screen", "20000x100", "-o", "{tmp}/t"], 1, "at most 16384"),
    (["target", "fringes", "--steps", "100000000", "-o", "{tmp}/t"], 1, "at most 64"),
    (["history", "{res}", "--point", "30,30", "--frames", "1-100000000000"], 2, "more than 1,000,000 frames"),
    (["profile", "{res}", "--from", "20,20", "--to", "50,40", "--samples", "100000000"], 2, "100000"),
    (["profile", "{res}", "--from", "20,20", "--to", "1e300,1e300"], 1, "more than 100,000"),
    (["profile", "{res}", "--from", "-1e308,-1e308", "--to", "1e308,1e308", "--samples", "3"], 1,
     "outside the measured points"),
    (["history", "{res}", "--point", "5000,5000"], 1, "outside the measured points"),
    (["history", "{res}", "--point", "-40,30"], 1, "outside the measured points"),
])
def test_huge_values_are_refused_with_their_bound(result_file, tmp_path, args, exit_code, message):
    args = [a.format(tmp=tmp_path, res=result_file) for a in args]
    t0 = time.perf_counter()
    res = CliRunner().invoke(main, args)
    assert res.exit_code == exit_code and message in res.output, res.output
    assert time.perf_counter() - t0 < 20.0
    _clean(res)
    assert not (tmp_path / "t").exists() or not any((tmp_path / "t").iterdir())


def test_history_and_profile_inside_still_work(result_file):
    res = CliRunner().invoke(main, ["history", result_file, "--point", "30,30"])
    assert res.exit_code == 0 and "nan" not in res.output.split("\n", 1)[1], res.output
    res = CliRunner().invoke(main, ["profile", result_file, "--from", "0,30", "--to", "80,30", "--samples", "5"])
    assert res.exit_code == 0, res.output  # a line across the image: its ends may lie beyond the points


# ---------------------------------------------------------------------------------------------
# 11: speckle --second moved
def test_speckle_refuses_a_moved_second_image(tmp_path):
    from dic.io import write_image
    from dic.quality import estimate_noise
    from dic.synth import speckle_pair

    ref, still = speckle_pair((128, 128), None, noise_sigma=2.0, seed=7)
    _, moved = speckle_pair((128, 128), (2.0, 0.0), noise_sigma=2.0, seed=7)
    _, nudged = speckle_pair((128, 128), (0.1, 0.0), noise_sigma=2.0, seed=7)
    assert abs(estimate_noise(ref, still) - 2.0) < 0.15
    for image in (moved, nudged):
        with pytest.raises(ValueError, match="second image is moved by about"):
            estimate_noise(ref, image)
        assert estimate_noise(ref, image, check_motion=False) > 2.5  # what the check prevents
    paths = {n: str(write_image(tmp_path / f"{n}.tif", img, bits=8)) for n, img in
             (("ref", ref), ("still", still), ("moved", moved))}
    res = CliRunner().invoke(main, ["speckle", paths["ref"], "--second", paths["moved"], "--device", "cpu"])
    assert res.exit_code == 1, res.output
    dx, dy = (float(v) for v in re.search(r"second image is moved by about \(([-0-9.e]+), ([-0-9.e]+)\) px",
                                          res.output).groups())
    assert abs(dx - 2.0) < 0.05 and abs(dy) < 0.05, res.output  # the shift it was given
    _clean(res)
    res = CliRunner().invoke(main, ["speckle", paths["ref"], "--second", paths["still"], "--device", "cpu"])
    assert res.exit_code == 0 and "measured from the difference" in res.output, res.output


# ---------------------------------------------------------------------------------------------
# 12: lab camera names
SCENE = """
background = 0.1

[[camera]]
name = "{a}"
size = [16, 12]
pixel_pitch_mm = 0.08
focal_length_mm = 12.0
f_number = inf
focus_distance_mm = 1000.0
position = [0.0, 0.0, 0.0]
look_at = [0.0, 0.0, 1000.0]

[[camera]]
name = "{b}"
size = [16, 12]
pixel_pitch_mm = 0.08
focal_length_mm = 12.0
f_number = inf
focus_distance_mm = 1000.0
position = [10.0, 0.0, 0.0]
look_at = [0.0, 0.0, 1000.0]

[[plane]]
size = [200.0, 200.0]
center = [0.0, 0.0, 1000.0]
normal = [0.0, 0.0, -1.0]
speckle = {{ radius = 3.0, density = 0.4, seed = 2 }}
"""


@pytest.mark.parametrize("a, b", [("cam/1", "cam_1"), ("Left", "left"), ("a b", "a_b")])
def test_lab_camera_names_that_give_one_file_name_are_refused(tmp_path, a, b):
    (tmp_path / "scene.toml").write_text(SCENE.format(a=a, b=b))
    res = CliRunner().invoke(main, ["lab", "render", str(tmp_path / "scene.toml"), "-o", str(tmp_path / "out"),
                                    "--samples", "1", "--device", "cpu"])
    assert res.exit_code == 1 and "give the same file name" in res.output and a in res.output, res.output
    _clean(res)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").glob("*.tif"))


def test_lab_distinct_camera_names_render(tmp_path):
    (tmp_path / "scene.toml").write_text(SCENE.format(a="cam/1", b="cam/2"))
    res = CliRunner().invoke(main, ["lab", "render", str(tmp_path / "scene.toml"), "-o", str(tmp_path / "out"),
                                    "--samples", "1", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (tmp_path / "out").glob("*.tif")) == ["cam_1.tif", "cam_2.tif"]


# ---------------------------------------------------------------------------------------------
# 16: camera files
def _camera(size=(640, 480)):
    from calibration.camera import Camera

    return Camera(K=[[800.0, 0, 320.0], [0, 800.0, 240.0], [0, 0, 1]], dist=[0.01, 0, 0, 0, 0], size=size, name="left")


def test_camera_files_with_size_zero_are_refused(tmp_path):
    from calibration.camera import Camera
    from calibration.formats import load_rig
    from calibration.stereo import StereoRig

    cam = _camera()
    cam.save(tmp_path / "cam.json")
    data = json.loads((tmp_path / "cam.json").read_text())
    data["size"] = [0, 0]
    (tmp_path / "zero.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"zero.json.*image size of camera 'left' is unknown \(size \[0, 0\]\)"):
        Camera.load(tmp_path / "zero.json")
    with pytest.raises(ValueError, match=r"size \[0, 0\]"):
        load_rig(tmp_path / "zero.json")
    with pytest.raises(ValueError, match="cannot save the camera"):
        _camera(size=(0, 0)).save(tmp_path / "x.json")
    rig = StereoRig(cam, _camera(), np.eye(3), [100.0, 0, 0])
    rig.save(tmp_path / "rig.json")
    data = json.loads((tmp_path / "rig.json").read_text())
    data["right"]["size"] = [0, 0]
    (tmp_path / "rig0.json").write_text(json.dumps(data))
    for load in (StereoRig.load, load_rig):
        with pytest.raises(ValueError, match=r"right camera: .*size \[0, 0\]"):
            load(tmp_path / "rig0.json")
    assert not (tmp_path / "x.json").exists()
    assert Camera.load(tmp_path / "cam.json").size == (640, 480)


DICE_IDENTITY = """<?xml version="1.0"?>
<ParameterList>
<Parameter name="xml_file_format" type="string" value="DICe_xml_camera_system_file" />
<Parameter name="system_type_3D" type="string" value="OPENCV" />
<Parameter name="extrinsics_relative_camera_to_camera" type="bool" value="true" />
<ParameterList name="CAMERA 0">
<Parameter name="CX" type="double" value="3.200000000000e+02" />
<Parameter name="CY" type="double" value="2.400000000000e+02" />
<Parameter name="FX" type="double" value="8.000000000000e+02" />
<Parameter name="FY" type="double" value="8.010000000000e+02" />
<Parameter name="K1" type="double" value="1.000000000000e-02" />
<Parameter name="LENS_DISTORTION_MODEL" type="string" value="OPENCV_LENS_DISTORTION" />
<Parameter name="TX" type="double" value="0.000000000000e+00" />
<Parameter name="TY" type="double" value="0.000000000000e+00" />
<Parameter name="TZ" type="double" value="0.000000000000e+00" />
<ParameterList name="rotation_3x3_matrix">
<Parameter name="ROW 0" type="string" value="{ 1.000000000000e+00, 0.000000000000e+00, 0.000000000000e+00 }" />
<Parameter name="ROW 1" type="string" value="{ 0.000000000000e+00, 1.000000000000e+00, 0.000000000000e+00 }" />
<Parameter name="ROW 2" type="string" value="{ 0.000000000000e+00, 0.000000000000e+00, %s }" />
</ParameterList>
<Parameter name="IMAGE_HEIGHT_WIDTH" type="string" value="{ 480, 640 }" />
</ParameterList>
<ParameterList name="CAMERA 1">
<Parameter name="CX" type="double" value="3.100000000000e+02" />
<Parameter name="CY" type="double" value="2.500000000000e+02" />
<Parameter name="FX" type="double" value="8.050000000000e+02" />
<Parameter name="FY" type="double" value="8.040000000000e+02" />
<Parameter name="LENS_DISTORTION_MODEL" type="string" value="OPENCV_LENS_DISTORTION" />
<Parameter name="TX" type="double" value="-1.000000000000e+02" />
<Parameter name="TY" type="double" value="0.000000000000e+00" />
<Parameter name="TZ" type="double" value="5.000000000000e+00" />
<ParameterList name="rotation_3x3_matrix">
<Parameter name="ROW 0" type="string" value="{ 0.98480775301, 0.0, -0.17364817767 }" />
<Parameter name="ROW 1" type="string" value="{ 0.0, 1.0, 0.0 }" />
<Parameter name="ROW 2" type="string" value="{ 0.17364817767, 0.0, 0.98480775301 }" />
</ParameterList>
<Parameter name="IMAGE_HEIGHT_WIDTH" type="string" value="{ 480, 640 }" />
</ParameterList>
</ParameterList>
"""


def test_dice_files_with_camera_0_identity_rotation_load(tmp_path):
    """DICe's writer (and writers following it) gives camera 0 of a camera-to-camera file zero TX TY TZ and
    an identity rotation_3x3_matrix: that is no pose, and the rig is camera 1's extrinsics."""
    from calibration.formats import load_dice_xml, load_rig

    (tmp_path / "cal.xml").write_text(DICE_IDENTITY % "1.000000000000e+00")
    for load in (load_dice_xml, load_rig):
        rig = load(tmp_path / "cal.xml")
        np.testing.assert_allclose(rig.t_right_left, [-100.0, 0.0, 5.0])
        c, s = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))
        np.testing.assert_allclose(rig.R_right_left, [[c, 0, -s], [0, 1, 0], [s, 0, c]], atol=1e-10)
        assert rig.left.size == (640, 480) and rig.left.K[1, 1] == 801.0
    (tmp_path / "bad.xml").write_text(DICE_IDENTITY % "-1.000000000000e+00")  # not the identity: still refused
    with pytest.raises(ValueError, match="camera 0 is the reference; its extrinsics must be absent or zero"):
        load_dice_xml(tmp_path / "bad.xml")


# ---------------------------------------------------------------------------------------------
# 4: a Dask scheduler without workers
def test_a_scheduler_without_workers_is_reported_and_waited_for_with_a_timeout(monkeypatch):
    distributed = pytest.importorskip("distributed")
    from dic.sequence.distributed import WORKER_TIMEOUT, connect, worker_timeout

    assert worker_timeout() == WORKER_TIMEOUT == 60.0
    monkeypatch.setenv("SPECULA_DASK_WORKER_TIMEOUT", "2")
    cluster = distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=None)
    try:
        t0 = time.perf_counter()
        with pytest.warns(UserWarning, match="has no workers; waiting up to 2 s"):
            with pytest.raises(ValueError, match=r"no Dask worker joined the scheduler at .* within 2 s"):
                connect(cluster.scheduler_address)
        assert time.perf_counter() - t0 < 15.0
        with distributed.Client(cluster, set_as_default=False) as client:  # a client given: reported, not waited for
            with pytest.warns(UserWarning, match="cluster has no workers yet"):
                assert connect(client) is client
    finally:
        cluster.close()
    monkeypatch.setenv("SPECULA_DASK_WORKER_TIMEOUT", "soon")
    with pytest.raises(ValueError, match="SPECULA_DASK_WORKER_TIMEOUT must be a positive number"):
        worker_timeout()


# ---------------------------------------------------------------------------------------------
# also seen
def test_a_cut_short_avi_is_refused(tmp_path):
    import imageio.v3 as iio

    from dic.sources import open_frames

    rng = np.random.default_rng(0)
    frames = (rng.random((10, 48, 64)) * 255).astype(np.uint8)
    iio.imwrite(tmp_path / "v.avi", frames, plugin="FFMPEG", fps=10, codec="ffv1")
    assert len(open_frames(str(tmp_path / "v.avi"))) == 10
    data = (tmp_path / "v.avi").read_bytes()
    (tmp_path / "cut.avi").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"cut\.avi is cut short: its header declares 10 frames"):
        len(open_frames(str(tmp_path / "cut.avi")))
    res = CliRunner().invoke(main, ["track", str(tmp_path / "cut.avi"), "-o", str(tmp_path / "r.h5")])
    assert res.exit_code == 1 and "cut short" in res.output, res.output
    _clean(res)


def test_a_bow_tie_polygon_is_accepted_and_a_line_refused():
    from dic.correlation.points import grid, region

    bow_tie = [(0, 0), (20, 20), (20, 0), (0, 20)]  # signed area 0, but two triangles
    pts = grid((30, 30), 1, roi=region(bow_tie, (30, 30)))
    x, y = pts[:, 0], pts[:, 1]
    assert np.all((x <= 20) & (y <= 20)) and np.all(np.abs(x - 10) >= np.abs(y - 10) - 1e-9)  # the left/right loops
    assert len(pts) == 2 * sum(2 * k + 1 for k in range(11)) - 1  # 11 rows per loop; the centre (10, 10) once
    with pytest.raises(ValueError, match="lie on one line"):
        region([(0, 0), (5, 5), (10, 10)], (30, 30))
    with pytest.raises(ValueError, match="encloses no area"):
        region([(0, 0), (10, 0), (10, 10), (10, 0)], (30, 30))


def test_symlink_loops_and_fifos_are_named(tmp_path, two_images):
    from dic.sources import open_frames

    loop = tmp_path / "loop.tif"
    os.symlink(loop, loop)
    dangling = tmp_path / "dangling.tif"
    os.symlink(tmp_path / "gone.tif", dangling)
    fifo = tmp_path / "pipe.tif"
    os.mkfifo(fifo)
    for path, what in ((loop, "symbolic link in a loop"), (dangling, "symbolic link whose target does not exist"),
                       (fifo, "FIFO")):
        with pytest.raises(ValueError, match=what):
            read_image(path)
        with pytest.raises(ValueError, match=what):
            open_frames(str(path))
        res = CliRunner().invoke(main, ["track", two_images[0], str(path), "-o", str(tmp_path / "r.h5")])
        assert res.exit_code == 1 and what in res.output and "not found" not in res.output, res.output
        _clean(res)


def test_stereo_exits_non_zero_when_no_state_has_a_valid_point(tmp_path, monkeypatch):
    """A swapped or foreign rig: every state of the run without a valid point is an error unless --allow-empty."""
    from dataclasses import replace
    from types import SimpleNamespace

    import dic.sequence
    from calibration.stereo import StereoRig
    from dic.io import write_image

    cam = replace(_camera(size=(80, 64)), K=[[100.0, 0, 40.0], [0, 100.0, 32.0], [0, 0, 1]])
    StereoRig(cam, cam, np.eye(3), [100.0, 0, 0]).save(tmp_path / "rig.json")
    paths = [str(write_image(tmp_path / f"{n}.tif", _speckle((64, 80), seed=k), bits=8))
             for k, n in enumerate(("l0", "r0", "l1", "r1"))]
    valid_counts = {}

    class Field(SimpleNamespace):
        def __len__(self):
            return len(self.valid)

    def fake(rig, pairs, output, *, callback, **kw):
        summary = dic.sequence.SequenceSummary(path=output)
        for index in range(len(pairs)):
            valid = np.zeros(10, bool)
            valid[: valid_counts.get(index, 0)] = True
            callback(index, Field(index=index, valid=valid, reference_index=0), None)
            summary.add(index, int(valid.sum()), len(valid), 0.0, 0)
        return summary

    monkeypatch.setattr(dic.sequence, "stereo_sequence", fake)
    base = ["stereo", "--rig", str(tmp_path / "rig.json"), *paths, "-o", str(tmp_path / "s.h5"), "-q"]
    res = CliRunner().invoke(main, base)
    assert res.exit_code == 1 and "no state of this run has a valid point (2 state(s)" in res.output, res.output
    assert "swapped" in res.output
    _clean(res)
    assert CliRunner().invoke(main, [*base, "--allow-empty"]).exit_code == 0
    valid_counts[1] = 3  # one state with valid points: no error
    assert CliRunner().invoke(main, base).exit_code == 0


def test_a_png_with_fewer_rows_than_its_header_declares_is_refused(tmp_path):
    """Found by the CLI fuzz pass: a PNG header edited to 65536 rows over 48 rows of data was read by Pillow with
    the missing rows zero (OpenCV's libpng refuses it: "Not enough image data")."""
    from dic.io import write_image

    image = np.clip(np.rint(_speckle((48, 64))), 0, 255).astype(np.uint8)
    write_image(tmp_path / "ok.png", image, bits=8)
    data = bytearray((tmp_path / "ok.png").read_bytes())
    for rows in (49, 65536):
        data[20:24] = struct.pack(">I", rows)
        data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
        (tmp_path / "tall.png").write_bytes(bytes(data))
        with pytest.raises(ValueError, match=rf"tall.png holds image data for fewer pixels than its header declares "
                                             rf"\(64 x {rows} px"):
            read_image(tmp_path / "tall.png")
    assert np.array_equal(read_image(tmp_path / "ok.png"), image)
