"""Target detectors, one per module: phase-target dot centres (:mod:`.dots`, with its lattice and
code reading in :mod:`.lattice` and its per-dot model fit in :mod:`.dot_model`), dense phase
decoding (:mod:`.dense`), and the OpenCV detectors of conventional targets (:mod:`.checkerboard`,
:mod:`.circle_grid`); :mod:`.common` holds what they share.

The dot detector and the dense decoder follow the paper behind Specula (Optics Express 27(6), 9040,
2019, doi:10.1364/OE.27.009040). Conventions: docs/conventions.md.
"""
from .checkerboard import detect_checkerboard
from .circle_grid import detect_circle_grid
from .common import DetectionError, demodulate_images
from .dense import DenseDecoding, decode_dense, dense_correspondences
from .dots import DotDetection, detect_dots, detect_dots_in_images

__all__ = [
    "DotDetection",
    "DenseDecoding",
    "DetectionError",
    "demodulate_images",
    "detect_dots",
    "detect_dots_in_images",
    "decode_dense",
    "dense_correspondences",
    "detect_checkerboard",
    "detect_circle_grid",
]
