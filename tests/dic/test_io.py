"""Image reading/writing (kernels/images.py, re-exported by dic/io.py) against tifffile / imageio round trips
and broken files; the same rules in the DIC, calibration and virtual-lab readers."""
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


def test_one_reader_everywhere():
    import calibration.pipeline
    import kernels.images
    from kernels._device import as_float32_image

    assert read_image is kernels.images.read_image and write_image is kernels.images.write_image
    assert calibration.pipeline.IMAGE_SUFFIXES is kernels.images.IMAGE_SUFFIXES
    assert as_float32_image is kernels.images.as_float32_image


@pytest.mark.parametrize("suffix,channels", [(".png", 3), (".png", 4), (".tif", 3), (".bmp", 3)])
def test_grey_stored_as_rgb_is_grey_in_dic_and_calibration(tmp_path, rng, suffix, channels):
    from calibration.pipeline import read_stack

    grey = rng.integers(0, 256, size=(20, 30)).astype(np.uint8)
    rgb = np.repeat(grey[:, :, None], channels, axis=2)
    if channels == 4:
        rgb[:, :, 3] = 255 - grey  # alpha is ignored
    path = tmp_path / f"g{suffix}"
    if suffix == ".tif":
        tifffile.imwrite(path, rgb, photometric="rgb")
    else:
        import imageio.v3 as iio

        iio.imwrite(path, rgb)
    for as_grey in (False, True):  # grey stays exact (and in its dtype) with or without the conversion
        back = read_image(path, as_grey=as_grey)
        assert back.dtype == np.uint8 and np.array_equal(back, grey)
    stack = read_stack([path, path])
    assert stack.shape == (2, 20, 30) and stack.dtype == np.uint8 and np.array_equal(stack[1], grey)


def test_true_colour_is_refused_in_dic_calibration_and_lab(tmp_path, rng):
    import imageio.v3 as iio

    from calibration.pipeline import read_stack
    from dic.lab.io import _read_image as lab_read_image

    rgb = rng.integers(0, 256, size=(20, 30, 3)).astype(np.uint8)
    rgb[0, 0] = (10, 20, 30)  # at least one pixel whose channels differ
    iio.imwrite(tmp_path / "c.png", rgb)
    with pytest.raises(ValueError, match=r"c\.png is a colour image"):
        read_image(tmp_path / "c.png")
    with pytest.raises(ValueError, match=r"c\.png is a colour image"):
        read_stack([tmp_path / "c.png"])
    with pytest.raises(ValueError, match=r"screen\[0\]: 'image': .*c\.png is a colour image"):
        lab_read_image(tmp_path / "c.png", "screen[0]: 'image'")
    grey = rng.integers(0, 256, size=(20, 30)).astype(np.uint8)
    iio.imwrite(tmp_path / "g.png", np.repeat(grey[:, :, None], 3, axis=2))
    assert np.array_equal(lab_read_image(tmp_path / "g.png", "screen"), grey)


def test_calibration_reader_messages(tmp_path):
    from calibration.pipeline import read_stack

    with pytest.raises(ValueError, match="image file not found"):
        read_stack([tmp_path / "nope.png"])
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(ValueError, match="image file is empty"):
        read_stack([tmp_path / "empty.png"])
    (tmp_path / "text.png").write_text("not an image")
    with pytest.raises(ValueError, match="cannot read image .*text.png"):
        read_stack([tmp_path / "text.png"])
    tifffile.imwrite(tmp_path / "stack.tif", np.zeros((3, 8, 8), np.uint8), photometric="minisblack")
    with pytest.raises(ValueError, match="multi-page"):
        read_stack([tmp_path / "stack.tif"])


def test_reader_arguments_are_checked(tmp_path):
    with pytest.raises(ValueError, match="path must be a file name"):
        read_image(3)
    write_image(tmp_path / "a.png", np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError, match="as_grey must be True or False"):
        read_image(tmp_path / "a.png", as_grey="yes")
    with pytest.raises(ValueError, match="bits must be 8 or 16"):
        write_image(tmp_path / "b.png", np.zeros((4, 4)), bits=12)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    import struct
    import zlib

    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _pillow_pixels(path):
    """The PNG reader before the OpenCV path (imageio/Pillow): the pixels read_image must give."""
    import imageio.v3 as iio

    return np.asarray(iio.imread(path, plugin="pillow"))


def test_grey_png_read_through_opencv_has_pillows_pixels(tmp_path, rng):
    """8/16-bit grey PNGs are decoded by OpenCV (less CPU); the pixels and dtype are Pillow's, with
    ancillary chunks too (gamma, significant bits, transparency), and every other PNG is still Pillow's."""
    import io

    from PIL import Image

    import kernels.images as images

    a8 = rng.integers(0, 256, (37, 53), dtype=np.uint8)
    a16 = rng.integers(0, 65536, (37, 53), dtype=np.uint16)
    write_image(tmp_path / "g8.png", a8)
    write_image(tmp_path / "g16.png", a16)
    raw8 = (tmp_path / "g8.png").read_bytes()
    raw16 = (tmp_path / "g16.png").read_bytes()
    variants = {"gamma.png": raw8[:33] + _png_chunk(b"gAMA", (45455).to_bytes(4, "big")) + raw8[33:],
                "sbit.png": raw8[:33] + _png_chunk(b"sBIT", bytes([5])) + raw8[33:],
                "sbit16.png": raw16[:33] + _png_chunk(b"sBIT", bytes([12])) + raw16[33:],
                "trns.png": raw8[:33] + _png_chunk(b"tRNS", (7).to_bytes(2, "big")) + raw8[33:],
                "tail.png": raw8 + b"bytes after the end"}
    for name, data in variants.items():
        (tmp_path / name).write_bytes(data)
    for name, want in [("g8.png", a8), ("g16.png", a16), ("gamma.png", a8), ("sbit.png", a8), ("sbit16.png", a16),
                       ("trns.png", a8), ("tail.png", a8)]:
        got = read_image(tmp_path / name)
        pil = _pillow_pixels(tmp_path / name)
        assert got.dtype == pil.dtype == want.dtype and np.array_equal(got, pil) and np.array_equal(got, want), name
        fast = images._read_plain_grey_png(tmp_path / name)  # the OpenCV path: taken, the same pixels
        assert fast is not None and fast.dtype == want.dtype and np.array_equal(fast, want), name
    # other PNGs are not for OpenCV: 1-bit, palette, grey + alpha, RGB, interlaced (header flag)
    buf = io.BytesIO()
    Image.fromarray(a8 > 128).save(buf, format="PNG")
    one_bit = buf.getvalue()
    buf = io.BytesIO()
    Image.fromarray(a8).convert("P").save(buf, format="PNG")
    palette = buf.getvalue()
    interlaced = bytearray(raw8)
    interlaced[28] = 1
    for k, data in enumerate((one_bit, palette, bytes(interlaced))):
        assert images._plain_grey_png(data) is None
        (tmp_path / f"other{k}.png").write_bytes(data)
        assert images._read_plain_grey_png(tmp_path / f"other{k}.png") is None
    (tmp_path / "bits.png").write_bytes(one_bit)
    assert read_image(tmp_path / "bits.png").dtype == np.uint8 and np.array_equal(read_image(tmp_path / "bits.png"),
                                                                                   (a8 > 128).astype(np.uint8))
    # a file whose chunks stop short is left to Pillow (which says it is truncated), and so is one OpenCV
    # refuses (a damaged checksum): what Pillow makes of it, as before
    for cut in (len(raw8) // 2, len(raw8) - 6):
        assert images._plain_grey_png(raw8[:cut]) is None
    bad = bytearray(raw8)
    bad[len(raw8) // 2] ^= 0xFF
    (tmp_path / "crc.png").write_bytes(bytes(bad))
    assert images._read_plain_grey_png(tmp_path / "crc.png") is None
    try:
        pil = _pillow_pixels(tmp_path / "crc.png")
    except Exception:  # noqa: BLE001 - Pillow refuses it: so must read_image
        with pytest.raises(ValueError, match="cannot read image .*crc.png"):
            read_image(tmp_path / "crc.png")
    else:
        assert np.array_equal(read_image(tmp_path / "crc.png"), pil)


def test_png_headers_that_promise_more_pixels_than_the_file_holds_go_to_pillow(tmp_path):
    """A PNG whose header claims huge dimensions is not handed to OpenCV (which would allocate them
    first): Pillow reads it, with its decompression-bomb guard, and read_image says it cannot read it."""
    import struct
    import zlib

    import kernels.images as images

    def png(width, height, idat=b""):
        ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
        return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", idat)
                + _png_chunk(b"IEND", b""))

    small = png(4, 3, zlib.compress(b"".join(b"\x00" + bytes([10 * r + c for c in range(4)]) for r in range(3))))
    assert images._plain_grey_png(small) == (3, 4)
    (tmp_path / "small.png").write_bytes(small)
    assert np.array_equal(read_image(tmp_path / "small.png"), [[0, 1, 2, 3], [10, 11, 12, 13], [20, 21, 22, 23]])
    for w, h in [(30000, 30000), (5000, 5000)]:  # beyond Pillow's pixel limit; more than 1100 x the file's bytes
        data = png(w, h, zlib.compress(b"\x00" * 100))
        assert images._plain_grey_png(data) is None
        (tmp_path / "big.png").write_bytes(data)
        message = "big.png declares an image of 30000 x 30000 px" if w == 30000 else "cannot read image .*big.png"
        with pytest.raises(ValueError, match=message):  # beyond the image-size limit: refused from its header
            read_image(tmp_path / "big.png")
