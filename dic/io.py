"""Reading and writing grey-level images: TIFF (8/16-bit, tifffile), PNG and BMP (imageio/Pillow).

Images are 2-D arrays indexed ``[row, col] = [y, x]`` (docs/conventions.md). Grey levels keep
their original scale (0-255 for 8-bit, 0-65535 for 16-bit files).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["read_image", "write_image", "IMAGE_SUFFIXES"]

#: file name suffixes read_image accepts (case-insensitive)
IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".bmp")

# ITU-R BT.601 luma weights, used only when a colour image is converted on request
_LUMA = np.array([0.299, 0.587, 0.114])


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
        Convert colour (RGB/RGBA) images to grey with BT.601 luma weights (result float32).
        Without it a colour image raises ``ValueError``.

    Returns
    -------
    ndarray (H, W)
        In the file's own dtype (uint8, uint16, float32, ...) unless converted from colour.

    Raises
    ------
    ValueError
        Missing, unreadable, truncated or empty files, unsupported formats, multi-page stacks,
        and colour images without ``as_grey``; the message names the file.
    """
    p = Path(os.fspath(path))
    if not p.exists():
        raise ValueError(f"image file not found: {p}")
    if not p.is_file():
        raise ValueError(f"not an image file (it is a directory or special file): {p}")
    suffix = p.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise ValueError(f"unsupported image format {p.suffix!r} for {p}; expected one of {', '.join(IMAGE_SUFFIXES)}")
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
                arr = tif.asarray()
        else:
            import imageio.v3 as iio

            arr = np.asarray(iio.imread(p, plugin="pillow"))
    except ValueError as exc:
        if str(p) in str(exc):
            raise
        raise ValueError(f"cannot read image {p} (truncated or corrupt file?): {exc}") from exc
    except Exception as exc:  # tifffile.TiffFileError, OSError from Pillow, ...
        raise ValueError(f"cannot read image {p} (truncated or corrupt file?): {exc}") from exc
    if arr.ndim == 3:
        if arr.shape[2] == 1:
            arr = arr[:, :, 0]
        elif as_grey:
            arr = _to_grey(arr, p)
        else:
            raise ValueError(
                f"{p} is a colour image of shape {arr.shape}; DIC needs grey levels. Convert it "
                "(read_image(path, as_grey=True) uses BT.601 luma) or save it as grey")
    if arr.ndim != 2 or arr.size == 0:
        raise ValueError(f"{p}: expected a 2-D grey image, got shape {arr.shape}")
    if arr.dtype == bool:
        arr = arr.astype(np.uint8)
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise ValueError(f"{p}: unsupported pixel type {arr.dtype}")
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
    p = Path(os.fspath(path))
    suffix = p.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise ValueError(f"unsupported image format {p.suffix!r} for {p}; expected one of {', '.join(IMAGE_SUFFIXES)}")
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
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits!r}")
    if suffix == ".bmp" and bits != 8:
        raise ValueError("BMP files hold 8-bit grey images only; use .tif or .png for 16 bits")
    if not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"image must be numeric, got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("image contains NaN or infinite values")
    dtype = np.uint8 if bits == 8 else np.uint16
    out = np.clip(np.rint(arr.astype(np.float64)), 0, 2**bits - 1).astype(dtype)
    p.parent.mkdir(parents=True, exist_ok=True)
    if suffix in (".tif", ".tiff"):
        import tifffile

        tifffile.imwrite(p, out)
    else:
        import imageio.v3 as iio

        iio.imwrite(p, out, plugin="pillow")
    return p
