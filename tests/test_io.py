"""Image reading/writing (dic/io.py) against tifffile / imageio round trips and broken files."""
import numpy as np
import pytest
import tifffile

from dic.io import read_image, write_image


@pytest.mark.parametrize("suffix,bits", [(".tif", 8), (".tif", 16), (".png", 8), (".png", 16), (".bmp", 8)])
def test_round_trip_is_lossless(tmp_path, rng, suffix, bits):
    top = 2**bits - 1
    img = rng.integers(0, top + 1, size=(37, 53)).astype(np.uint8 if bits == 8 else np.uint16)
    path = write_image(tmp_path / f"img{suffix}", img)
    back = read_image(path)
    assert back.shape == (37, 53) and back.dtype == img.dtype
    assert np.array_equal(back, img)


def test_float_images_are_rounded_and_clipped(tmp_path):
    img = np.array([[-3.0, 0.4, 0.6], [254.5, 255.7, 1000.0]])
    back = read_image(write_image(tmp_path / "f.png", img, bits=8))
    assert np.array_equal(back, [[0, 0, 1], [254, 255, 255]])  # rint rounds half to even
    with pytest.raises(ValueError, match="give bits=8 or bits=16"):
        write_image(tmp_path / "g.png", img)
    with pytest.raises(ValueError, match="BMP files hold 8-bit"):
        write_image(tmp_path / "g.bmp", img, bits=16)
    with pytest.raises(ValueError, match="NaN"):
        write_image(tmp_path / "g.tif", img * np.nan, bits=8)


def test_float_tiff_is_read_as_is(tmp_path, rng):
    img = rng.random((10, 12)).astype(np.float32)
    tifffile.imwrite(tmp_path / "f.tif", img)
    assert np.array_equal(read_image(tmp_path / "f.tif"), img)


def test_colour_images(tmp_path, rng):
    rgb = rng.integers(0, 256, size=(20, 30, 3)).astype(np.uint8)
    import imageio.v3 as iio

    iio.imwrite(tmp_path / "c.png", rgb)
    with pytest.raises(ValueError, match="colour image"):
        read_image(tmp_path / "c.png")
    grey = read_image(tmp_path / "c.png", as_grey=True)
    expected = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]  # BT.601
    assert grey.shape == (20, 30) and np.max(np.abs(grey - expected)) < 1e-3


def test_missing_truncated_and_unsupported_files(tmp_path, rng):
    with pytest.raises(ValueError, match="image file not found"):
        read_image(tmp_path / "nope.tif")
    img = rng.integers(0, 65536, size=(64, 80)).astype(np.uint16)
    data = (tmp_path / "full.tif")
    tifffile.imwrite(data, img)
    raw = data.read_bytes()
    for name, cut in [("half.tif", len(raw) // 2), ("head.tif", 20)]:
        (tmp_path / name).write_bytes(raw[:cut])
        with pytest.raises(ValueError, match=f"cannot read image .*{name}"):
            read_image(tmp_path / name)
    write_image(tmp_path / "full.png", img)
    raw = (tmp_path / "full.png").read_bytes()
    (tmp_path / "half.png").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match="cannot read image .*half.png"):
        read_image(tmp_path / "half.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(ValueError, match="image file is empty"):
        read_image(tmp_path / "empty.png")
    (tmp_path / "text.bmp").write_text("not an image")
    with pytest.raises(ValueError, match="cannot read image"):
        read_image(tmp_path / "text.bmp")
    (tmp_path / "img.jpg").write_bytes(b"x")
    with pytest.raises(ValueError, match="unsupported image format"):
        read_image(tmp_path / "img.jpg")
    tifffile.imwrite(tmp_path / "stack.tif", np.zeros((3, 8, 8), np.uint8), photometric="minisblack")
    with pytest.raises(ValueError, match="multi-page"):
        read_image(tmp_path / "stack.tif")
    with pytest.raises(ValueError, match="not an image file"):
        read_image(tmp_path)
