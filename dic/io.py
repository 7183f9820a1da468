"""Reading and writing grey-level images: TIFF (8/16-bit, tifffile), PNG and BMP (imageio/Pillow).

The reader and writer live in the bottom layer, :mod:`kernels.images`, so that DIC, calibration
and the virtual lab read images by the same rules; this module keeps ``dic.io.read_image``
importable. Images are 2-D arrays indexed ``[row, col] = [y, x]`` (docs/conventions.md). Grey
levels keep their original scale (0-255 for 8-bit, 0-65535 for 16-bit files). An image file may declare
at most :func:`max_image_pixels` pixels (default 2**28; ``SPECULA_MAX_IMAGE_PIXELS`` or
:func:`set_max_image_pixels` raise it), checked from its header before decoding.
"""
from __future__ import annotations

from kernels.images import IMAGE_SUFFIXES, max_image_pixels, read_image, set_max_image_pixels, write_image

__all__ = ["read_image", "write_image", "IMAGE_SUFFIXES", "max_image_pixels", "set_max_image_pixels"]
