"""The one image reader and writer, and the array check every kernel launcher uses.

Files: TIFF (8/16-bit or float, tifffile), PNG and BMP (imageio/Pillow; 8/16-bit grey PNGs through
OpenCV, which decodes them with less CPU into the same pixels). Every package reads
images through :func:`read_image`, so the same rules hold in DIC, calibration and the virtual lab:

- grey levels keep their scale and dtype (0-255 for 8-bit, 0-65535 for 16-bit files);
- grey stored as RGB(A) with three identical colour channels is grey (alpha ignored);
- a true colour image needs ``as_grey=True`` (BT.601 luma), else ``ValueError`` naming the file;
- missing, empty, unsupported, truncated/corrupt and multi-page files raise ``ValueError``
  naming the file; a symbolic link that leads nowhere (a loop) or a FIFO is named as such;
- the image size a file declares in its header is checked against :func:`max_image_pixels`
  (default :data:`DEFAULT_MAX_IMAGE_PIXELS`, 2**28 = 268 435 456 px, e.g. 16384 x 16384; raise it
  with the environment variable ``SPECULA_MAX_IMAGE_PIXELS`` or :func:`set_max_image_pixels`)
  *before* anything is decoded, so a small file declaring a huge image (a decompression bomb) is
  refused at once instead of filling the memory;
- compressed TIFFs (LZW, Deflate, PackBits, JPEG, ...) are decoded by tifffile with the
  ``imagecodecs`` package (a dependency), or else by Pillow; when neither can decode the
  compression, the ``ValueError`` names the missing package (never "corrupt").

Images are 2-D arrays indexed ``[row, col] = [y, x]`` (docs/conventions.md). The module itself
needs only NumPy (tifffile, imageio and OpenCV are imported on first use) and runs no kernel.
"""
from __future__ import annotations

import os
import re
import sys
from pathlib import Path

import numpy as np

from .checks import boolean

__all__ = ["DEFAULT_MAX_IMAGE_PIXELS", "IMAGE_SUFFIXES", "MAX_IMAGE_PIXELS_ENV", "as_float32_image", "as_float32_tensor",
           "check_image_size", "declared_image_shape", "describe_not_a_file", "grey_image", "is_torch_tensor",
           "max_image_pixels", "natural_key", "read_image", "read_tiff_page", "set_max_image_pixels", "write_image"]

#: file name suffixes read_image and write_image accept (case-insensitive)
IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".bmp")

#: default limit on the pixels (height x width) an image file may declare: 2**28 (16384 x 16384 px, 256 MiB as
#: 8-bit, 1 GiB as float32); the largest scientific cameras today have about 150 Mpx
DEFAULT_MAX_IMAGE_PIXELS = 1 << 28
#: environment variable that sets the limit (a positive integer, in pixels) for a whole run
MAX_IMAGE_PIXELS_ENV = "SPECULA_MAX_IMAGE_PIXELS"
_max_pixels_set: int | None = None  # set_max_image_pixels() (wins over the environment)

# ITU-R BT.601 luma weights, used only when a colour image is converted on request
_LUMA = np.array([0.299, 0.587, 0.114])


def natural_key(path) -> tuple:
    """Sort key of file names in natural order (``img_2`` before ``img_10``; case-insensitive).

    Compares the base names with their digit runs as numbers, then the whole path (so that equal
    base names in different folders keep a fixed order). Used for every folder or glob of images.
    """
    text = os.fspath(path)
    parts = re.split(r"(\d+)", os.path.basename(text))
    return [int(p) if p.isdigit() else p.lower() for p in parts], text


def max_image_pixels() -> int:
    """The largest image (height x width, in px) a file may declare before it is decoded.

    :func:`set_max_image_pixels` if it was called, else the environment variable
    ``SPECULA_MAX_IMAGE_PIXELS`` (a positive integer; a malformed value raises ``ValueError``), else
    :data:`DEFAULT_MAX_IMAGE_PIXELS`.
    """
    if _max_pixels_set is not None:
        return _max_pixels_set
    text = os.environ.get(MAX_IMAGE_PIXELS_ENV, "").strip()
    if not text:
        return DEFAULT_MAX_IMAGE_PIXELS
    try:
        value = int(float(text)) if re.fullmatch(r"[0-9]+(\.0*)?([eE]\+?[0-9]+)?", text) else -1
    except (ValueError, OverflowError):
        value = -1
    if value < 1:
        raise ValueError(f"{MAX_IMAGE_PIXELS_ENV} must be a positive whole number of pixels (e.g. 1000000000), "
                         f"got {text!r}")
    return value


def set_max_image_pixels(pixels: int | None) -> None:
    """Set the limit of :func:`max_image_pixels` for this process (``None``: back to the environment / default).

    ``pixels``: a positive int (height x width). Raise it to read images larger than the default.
    """
    global _max_pixels_set
    if pixels is not None:
        if isinstance(pixels, bool) or not isinstance(pixels, (int, np.integer)) or pixels < 1:
            raise ValueError(f"the image-size limit must be a positive whole number of pixels, got {pixels!r}")
        pixels = int(pixels)
    _max_pixels_set = pixels


def check_image_size(height: int, width: int, name) -> None:
    """Refuse (``ValueError`` naming ``name`` and the bound) an image whose declared ``height x width`` px
    exceeds :func:`max_image_pixels`; called before any decoding."""
    limit = max_image_pixels()
    if int(height) * int(width) > limit:
        raise ValueError(
            f"{name} declares an image of {int(width)} x {int(height)} px = {int(height) * int(width):,} pixels, "
            f"more than the limit of {limit:,} pixels (a damaged header or a decompression bomb?); if the image is "
            f"real, raise the limit with the environment variable {MAX_IMAGE_PIXELS_ENV} (or "
            "kernels.images.set_max_image_pixels)")


def describe_not_a_file(path) -> str | None:
    """What ``path`` is when it is not a regular file that can be opened, in words, or None when it is one
    (or does not exist at all): a symbolic link that leads nowhere (a loop or a missing target), a FIFO
    (named pipe), a socket, a device, a folder."""
    import stat

    text = os.fspath(path)
    try:
        lst = os.lstat(text)
    except OSError:
        return None  # not there at all
    if stat.S_ISLNK(lst.st_mode):
        try:
            os.stat(text)
        except OSError as exc:
            import errno

            if exc.errno == errno.ELOOP:
                return f"{text} is a symbolic link in a loop (it leads back to itself), not an image file"
            return f"{text} is a symbolic link whose target does not exist ({os.readlink(text)})"
        lst = os.stat(text)
    if stat.S_ISREG(lst.st_mode):
        return None
    kind = ("a folder" if stat.S_ISDIR(lst.st_mode) else "a FIFO (named pipe)" if stat.S_ISFIFO(lst.st_mode)
            else "a socket" if stat.S_ISSOCK(lst.st_mode) else "a device" if stat.S_ISCHR(lst.st_mode)
            or stat.S_ISBLK(lst.st_mode) else "a special file")
    return f"{text} is {kind}, not an image file"


def declared_image_shape(path) -> tuple[int, int] | None:
    """``(height, width)`` an image file declares in its header (TIFF: the first page; PNG: IHDR; BMP and
    others: Pillow's header parser), read without decoding pixels; None when the header does not tell
    (the decoder then says what is wrong)."""
    p = Path(os.fspath(path))
    suffix = p.suffix.lower()
    try:
        if suffix in (".tif", ".tiff"):
            import tifffile

            with tifffile.TiffFile(p) as tif:
                page = tif.pages.first
                return int(page.imagelength), int(page.imagewidth)
        if suffix == ".png":
            with open(p, "rb") as fh:
                head = fh.read(24)
            if head[:8] == _PNG_SIGNATURE and head[12:16] == b"IHDR":
                return int.from_bytes(head[20:24], "big"), int.from_bytes(head[16:20], "big")
            return None
        from PIL import Image

        with Image.open(p) as im:
            return int(im.size[1]), int(im.size[0])
    except Exception:
        return None


def _missing_codec(exc: BaseException) -> str | None:
    """The package tifffile asked for when it lacks a decoder (its message "... requires the 'imagecodecs'
    package"), else None."""
    m = re.search(r"requires the '([A-Za-z0-9_.-]+)' package", str(exc))
    return m.group(1) if m else None


def _tiff_compression(page) -> str:
    try:
        return page.compression.name
    except AttributeError:
        return str(getattr(page, "compression", "unknown"))


def _pillow_tiff(p: Path, k: int) -> np.ndarray:
    """Page ``k`` of a TIFF decoded by Pillow (the fallback when tifffile lacks the codec)."""
    from PIL import Image

    with Image.open(p) as im:
        im.seek(k)
        return np.asarray(im)


def read_tiff_page(tif, k: int, name) -> np.ndarray:
    """Page ``k`` of an open ``tifffile.TiffFile`` as an array, with the size check of :func:`check_image_size`
    before decoding and the Pillow fallback for a compression tifffile cannot decode (``imagecodecs``
    missing). ``ValueError`` naming ``name`` (and the missing package) when neither decodes it."""
    page = tif.pages[k]
    check_image_size(page.imagelength, page.imagewidth, name)
    return _decode_tiff(page.asarray, tif, k, name)


def _decode_tiff(decode, tif, k: int, name) -> np.ndarray:
    """``decode()``, or page ``k`` decoded by Pillow when tifffile lacks the codec (see :func:`read_tiff_page`)."""
    page = tif.pages[k]
    try:
        return decode()
    except Exception as exc:
        package = _missing_codec(exc)
        if package is None:
            raise
        try:
            return _pillow_tiff(Path(tif.filehandle.path), k)
        except Exception as pil_exc:
            raise ValueError(
                f"cannot decode {name}: its {_tiff_compression(page)} compression needs the '{package}' package "
                f"(pip install {package}), and Pillow could not decode it either ({type(pil_exc).__name__}: "
                f"{pil_exc}); the file itself was not found damaged") from None


def _unsupported_suffix(p: Path) -> str:
    return f"unsupported image format {p.suffix!r} for {p}; expected one of {', '.join(IMAGE_SUFFIXES)}"


def _grey_channels(arr: np.ndarray) -> np.ndarray | None:
    """Channel 0 of an (H, W, 3|4) image whose R, G and B are identical (grey stored as RGB(A)), else None."""
    if arr.ndim == 3 and arr.shape[2] in (3, 4) and np.array_equal(arr[:, :, 0], arr[:, :, 1]) \
            and np.array_equal(arr[:, :, 1], arr[:, :, 2]):
        return np.ascontiguousarray(arr[:, :, 0])
    return None


def _to_grey(arr: np.ndarray, path) -> np.ndarray:
    """Convert an RGB(A) image (H, W, 3|4) to float32 BT.601 luma (alpha ignored)."""
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        return (arr[:, :, :3].astype(np.float64) @ _LUMA).astype(np.float32)
    raise ValueError(f"{path}: cannot convert an image of shape {arr.shape} to grey")


def read_image(path, *, as_grey: bool = False) -> np.ndarray:
    """Read a grey-level image file into a 2-D NumPy array.

    Parameters
    ----------
    path : str or Path
        A ``.tif``/``.tiff`` (8-, 16-bit or float; first and only page), ``.png`` or ``.bmp`` file.
    as_grey : bool
        Convert true colour (RGB/RGBA) images to grey with BT.601 luma weights (result float32).
        Without it a true colour image raises ``ValueError``. Grey stored as RGB(A) (identical
        R, G, B) is read as grey either way, in the file's dtype.

    Returns
    -------
    ndarray (H, W)
        In the file's own dtype (uint8, uint16, float32, ...; 1-bit files as uint8 0/1) unless
        converted from colour.

    Raises
    ------
    ValueError
        Missing, unreadable, truncated or empty files, unsupported formats, multi-page stacks,
        and colour images without ``as_grey``; the message names the file.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path must be a file name (str or Path), got {type(path).__name__}")
    boolean(as_grey, "as_grey")
    p = Path(os.fspath(path))
    special = describe_not_a_file(p)
    if special is not None:
        raise ValueError(special)
    if not p.exists():
        raise ValueError(f"image file not found: {p}")
    if not p.is_file():
        raise ValueError(f"not an image file (it is a directory or special file): {p}")
    suffix = p.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise ValueError(_unsupported_suffix(p))
    if p.stat().st_size == 0:
        raise ValueError(f"image file is empty: {p}")
    try:
        if suffix in (".tif", ".tiff"):
            import tifffile

            with tifffile.TiffFile(p) as tif:
                if len(tif.series) != 1 or len(tif.series[0].shape) > 3 or (
                        len(tif.series[0].shape) == 3 and tif.series[0].shape[-1] not in (1, 3, 4)):
                    raise ValueError(
                        f"{p} holds a multi-page or multi-image TIFF (series shapes "
                        f"{[s.shape for s in tif.series]}); give one image per file")
                shape = tif.series[0].shape
                if len(shape) == 2 or shape[-1] in (1, 3, 4):
                    check_image_size(shape[0], shape[1], p)
                else:  # pages of one series: all of them count
                    check_image_size(shape[0] * shape[1], shape[2], p)
                arr = _decode_tiff(tif.asarray, tif, 0, p)
        else:
            shape = declared_image_shape(p)
            if shape is not None:
                check_image_size(*shape, p)
            arr = _read_plain_grey_png(p) if suffix == ".png" else None
            if arr is None:
                import imageio.v3 as iio
                from PIL import Image

                if Image.MAX_IMAGE_PIXELS is not None and max_image_pixels() > Image.MAX_IMAGE_PIXELS:
                    Image.MAX_IMAGE_PIXELS = max_image_pixels()  # a raised limit holds for Pillow's own check too
                arr = np.asarray(iio.imread(p, plugin="pillow"))
                if suffix == ".png":
                    _check_png_data_complete(p)
    except ValueError as exc:
        if str(p) in str(exc):
            raise
        raise ValueError(f"cannot read image {p} (truncated or corrupt file?): {exc}") from exc
    except Exception as exc:  # tifffile.TiffFileError, OSError from Pillow, ...
        raise ValueError(f"cannot read image {p} (truncated or corrupt file?): {exc}") from exc
    return grey_image(arr, p, as_grey=as_grey,
                      hint="(read_image(path, as_grey=True) uses BT.601 luma) or save it as grey")


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_FAST_MAX_PIXELS = 89_478_485  # Pillow's MAX_IMAGE_PIXELS: larger images go to Pillow, which guards them
_PNG_MAX_RATIO = 1100  # deflate holds at most about 1032 bytes per byte it stores


def _grey_png_header(head: bytes) -> tuple[int, int, int] | None:
    """``(height, width, bytes per pixel)`` from a PNG file's first 29 bytes when it is 8- or 16-bit grey and
    not interlaced; None otherwise."""
    if len(head) < 29 or head[:8] != _PNG_SIGNATURE or head[8:16] != b"\x00\x00\x00\rIHDR":
        return None
    width = int.from_bytes(head[16:20], "big")
    height = int.from_bytes(head[20:24], "big")
    depth, colour, compression, filtering, interlace = head[24:29]
    if width == 0 or height == 0 or depth not in (8, 16) or (colour, compression, filtering, interlace) != (0, 0, 0, 0):
        return None
    return height, width, depth // 8


_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # by colour type


def _png_raw_bytes(width: int, height: int, depth: int, colour: int, interlace: int) -> int:
    """Bytes of a PNG's filtered image data (a filter byte per row), per its header; Adam7 passes when
    interlaced."""
    bits = _PNG_CHANNELS[colour] * depth
    if not interlace:
        return height * (1 + (width * bits + 7) // 8)
    total = 0
    for x0, y0, dx, dy in ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2),
                           (0, 1, 1, 2)):
        w, h = (width - x0 + dx - 1) // dx, (height - y0 + dy - 1) // dy
        if w and h:
            total += h * (1 + (w * bits + 7) // 8)
    return total


def _check_png_data_complete(p: Path) -> None:
    """Refuse (``ValueError``) a PNG whose compressed data holds fewer pixel rows than its header declares:
    Pillow decodes such a file without a word, the missing rows zero (a header edited or damaged, or a
    file cut short before its data was written: OpenCV's libpng says "Not enough image data"). The
    data is inflated once more, without keeping it."""
    import zlib

    with open(p, "rb") as fh:
        data = fh.read()
    if data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR" or len(data) < 33:
        return
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    depth, colour, interlace = data[24], data[25], data[28]
    if colour not in _PNG_CHANNELS:
        return
    expected = _png_raw_bytes(width, height, depth, colour, interlace)
    inflate, got, pos = zlib.decompressobj(), 0, 8
    try:
        while pos + 12 <= len(data) and got < expected:
            length = int.from_bytes(data[pos:pos + 4], "big")
            kind = data[pos + 4:pos + 8]
            if kind == b"IDAT":
                chunk = data[pos + 8:pos + 8 + length]
                while chunk and got < expected:
                    got += len(inflate.decompress(chunk, 1 << 22))
                    chunk = inflate.unconsumed_tail
            elif kind == b"IEND":
                break
            pos += 12 + length
    except zlib.error:
        return  # Pillow decoded it: its own reading stands
    if got < expected:
        raise ValueError(f"{p} holds image data for fewer pixels than its header declares ({width} x {height} px: "
                         f"{got:,} of {expected:,} bytes); the file is damaged or cut short")


def _plain_grey_png(data: bytes) -> tuple[int, int] | None:
    """``(height, width)`` of a PNG file's bytes when it is 8- or 16-bit grey, not interlaced, and its
    chunks run whole from the header to the end chunk (checksums not checked here); None otherwise."""
    header = _grey_png_header(data[:29])
    if header is None:
        return None
    height, width, depth = header
    if width * height > _PNG_FAST_MAX_PIXELS or width * height * depth > _PNG_MAX_RATIO * len(data):
        return None  # what Pillow's decompression-bomb check is there for, or pixels these bytes cannot hold
    pos, n, image_data = 8, len(data), False
    while pos + 12 <= n:
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind = data[pos + 4:pos + 8]
        pos += 12 + length
        if pos > n:
            return None
        image_data |= kind == b"IDAT"
        if kind == b"IEND":
            return (height, width) if image_data else None
    return None


def _read_plain_grey_png(p: Path) -> np.ndarray | None:
    """The pixels of an 8- or 16-bit grey, non-interlaced PNG decoded by OpenCV (about 20 % less CPU than
    Pillow; the same pixels, tests/dic/test_io.py), or None (then Pillow reads it, as for every other PNG):
    another kind of PNG, a file whose chunks do not run whole to the end, anything OpenCV does not decode."""
    with open(p, "rb") as fh:
        head = fh.read(29)
        if _grey_png_header(head) is None:  # another kind of PNG: not read any further here
            return None
        data = head + fh.read()
    shape = _plain_grey_png(data)
    if shape is None:
        return None
    try:
        import cv2
    except ImportError:  # pragma: no cover - OpenCV is a dependency
        return None
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None or arr.shape != shape or arr.dtype not in (np.uint8, np.uint16):
        return None
    return arr


def grey_image(arr, name, *, as_grey: bool = False, hint: str = "(as_grey=True uses BT.601 luma)") -> np.ndarray:
    """The grey levels of a decoded image array, by the rules of :func:`read_image`.

    ``arr``: (H, W), (H, W, 1) or (H, W, 3|4) as a decoder returns it (a file, a TIFF page, a video
    frame). Grey stored as RGB(A) (identical R, G, B) is grey in its own dtype; true colour is
    converted to float32 BT.601 luma with ``as_grey=True`` and refused otherwise (``ValueError``
    naming ``name``, followed by ``hint``). Boolean images become uint8 0/1.
    """
    arr = np.asarray(arr)
    if arr.ndim == 3:
        grey = arr[:, :, 0] if arr.shape[2] == 1 else _grey_channels(arr)
        if grey is not None:
            arr = grey
        elif as_grey:
            arr = _to_grey(arr, name)
        else:
            raise ValueError(
                f"{name} is a colour image of shape {arr.shape}; DIC needs grey levels. Convert it {hint}")
    if arr.ndim != 2 or arr.size == 0:
        raise ValueError(f"{name}: expected a 2-D grey image, got shape {arr.shape}")
    if arr.dtype == bool:
        arr = arr.astype(np.uint8)
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise ValueError(f"{name}: unsupported pixel type {arr.dtype}")
    return arr


def write_image(path, array, *, bits: int | None = None) -> Path:
    """Write a 2-D grey image as TIFF, PNG (8 or 16 bit) or BMP (8 bit).

    Parameters
    ----------
    path : str or Path
        Output file; the suffix picks the format (``.tif``/``.tiff``, ``.png``, ``.bmp``).
    array : array_like (H, W)
        Grey levels on the target scale (0-255 for 8 bits, 0-65535 for 16 bits); values are
        rounded and clipped to that range.
    bits : 8, 16 or None
        None keeps uint8/uint16 arrays as they are and asks for ``bits`` otherwise.

    Returns the path written.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path must be a file name (str or Path), got {type(path).__name__}")
    p = Path(os.fspath(path))
    suffix = p.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise ValueError(_unsupported_suffix(p))
    arr = np.asarray(array)
    if arr.ndim != 2 or arr.size == 0:
        raise ValueError(f"write_image needs a non-empty 2-D grey image (H, W), got shape {arr.shape}")
    if bits is None:
        if arr.dtype == np.uint8:
            bits = 8
        elif arr.dtype == np.uint16:
            bits = 16
        else:
            raise ValueError(f"give bits=8 or bits=16 to write a {arr.dtype} image")
    if isinstance(bits, bool) or bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits!r}")
    if suffix == ".bmp" and bits != 8:
        raise ValueError("BMP files hold 8-bit grey images only; use .tif or .png for 16 bits")
    if not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"image must be numeric, got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("image contains NaN or infinite values")
    dtype = np.uint8 if bits == 8 else np.uint16
    out = np.clip(np.rint(arr.astype(np.float64)), 0, 2**bits - 1).astype(dtype)
    from ._atomic import atomic_output

    with atomic_output(p) as tmp:  # whole or not at all (a full disk leaves no truncated image)
        if suffix in (".tif", ".tiff"):
            import tifffile

            tifffile.imwrite(tmp, out)
        else:
            import imageio.v3 as iio

            iio.imwrite(tmp, out, plugin="pillow")
    return p


def as_float32_image(image, name: str = "image") -> np.ndarray:
    """Validate a 2-D grey image array and return it as a C-contiguous float32 NumPy array (H, W).

    ``image``: NumPy array (any real dtype or bool), torch tensor or ``wp.array``. Grey levels keep
    their scale. Raises ``ValueError`` for non-2-D input (colour arrays included: unlike files,
    arrays are not inspected for grey stored as RGB), empty images, non-finite values, complex
    arrays (the imaginary part would be dropped silently: pass ``image.real`` or ``abs(image)``)
    and masked arrays with masked pixels (the mask would be ignored: pass the mask as a region of
    interest, ``roi=``, and the image as ``image.filled(...)``); a masked array with nothing masked
    is its data.
    """
    if hasattr(image, "numpy") and not isinstance(image, np.ndarray):  # torch tensor / warp array
        image = image.detach().cpu().numpy() if hasattr(image, "detach") else image.numpy()
    if isinstance(image, np.ma.MaskedArray):
        if np.ma.is_masked(image):
            raise ValueError(
                f"{name} is a masked array with {int(np.ma.count_masked(image))} masked pixel(s); the mask would be "
                "ignored. Pass the image as an ordinary array (e.g. image.filled(0)) and the pixels to measure as "
                "a region of interest (roi=~image.mask)")
        image = np.ma.getdata(image)
    arr = np.asarray(image)
    if np.iscomplexobj(arr):
        raise ValueError(f"{name} is complex (dtype {arr.dtype}); DIC needs real grey levels. Pass image.real "
                         "or abs(image) explicitly")
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        raise ValueError(
            f"{name} is a colour image of shape {arr.shape}; a grey image (H, W) is expected. "
            "Convert it first, e.g. with cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)"
        )
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array (H, W), got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} is empty (shape {arr.shape})")
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    out = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name} contains NaN or infinite values; DIC needs finite grey levels")
    return out


def is_torch_tensor(obj) -> bool:
    """Whether ``obj`` is a torch tensor (without importing torch: a tensor exists only if torch is loaded)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(obj, torch.Tensor)


def as_float32_tensor(image, device: str, name: str = "image"):
    """Validate a 2-D grey torch tensor and return it as a contiguous float32 tensor on ``device``, on the device.

    The tensor counterpart of :func:`as_float32_image`, with the same rules and messages, for images
    that never go through the host: ``image`` already float32, contiguous and on ``device`` (a Warp
    device name, ``"cpu"`` or ``"cuda:N"``) is returned as it is (no copy); another dtype (8/16-bit,
    float64, bool) is converted on its device by torch; a tensor on another device is moved there
    first (one copy). The finiteness check reduces on the device to one scalar, which is the only
    value read back; reading it also waits for the work that produced the tensor on torch's stream,
    so a kernel launched afterwards on another stream sees the finished image.
    """
    import torch

    if not isinstance(image, torch.Tensor):
        raise ValueError(f"{name} must be a torch tensor, got {type(image).__name__}")
    if image.is_complex():
        raise ValueError(f"{name} is complex (dtype {image.dtype}); DIC needs real grey levels. Pass image.real "
                         "or abs(image) explicitly")
    if image.ndim == 3 and image.shape[2] in (3, 4):
        raise ValueError(f"{name} is a colour image of shape {tuple(image.shape)}; a grey image (H, W) is expected. "
                         "Convert it first (e.g. a weighted sum of the channels)")
    if image.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array (H, W), got shape {tuple(image.shape)}")
    if image.numel() == 0:
        raise ValueError(f"{name} is empty (shape {tuple(image.shape)})")
    target = torch.device("cpu") if str(device) == "cpu" else torch.device(str(device))
    out = image.detach().to(device=target, dtype=torch.float32).contiguous()
    if not bool(torch.isfinite(out).all()):
        raise ValueError(f"{name} contains NaN or infinite values; DIC needs finite grey levels")
    return out
