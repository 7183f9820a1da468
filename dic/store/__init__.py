"""One results store for 2-D and stereo DIC: one file family, one writer, one reader.

Every result file (HDF5, docs/results_format.md) has the same root layout and the same
frame-by-frame protocol (``/frames/<index>.partial`` -> complete -> flush; resume skips complete
frames), written by :class:`ResultWriter` and read by :class:`ResultReader`. What differs per kind
is the payload of a frame, written and read by small per-kind functions:

==========  =================  ==============================================  ===========================
kind        format attr        frame payload                                   module
==========  =================  ==============================================  ===========================
``dic2d``   ``specula-dic2d``  :class:`dic.Field2D` (+ strain)           :mod:`dic.store.dic2d`
``stereo``  ``specula-stereo`` :class:`dic.field3d.Field3D`; + rig, match      :mod:`dic.store.stereo`
==========  =================  ==============================================  ===========================

Modules, lowest first: :mod:`~dic.store.layout` (shared names, digests, JSON),
:mod:`~dic.store.dic2d` and :mod:`~dic.store.stereo` (payloads), :mod:`~dic.store.files` (lock,
temporary file, space reservation, fsync, the in-use and write errors), :mod:`~dic.store.results`
(writer, reader, whole-file readers).
"""
from .dic2d import FORMAT_NAME, FrameResult, TrackResults
from .files import ResultFileDamaged, ResultFileInUse, ResultWriteError
from .layout import DEVICE_CHECKSUM_PREFIX, SCHEMA_VERSION, device_checksum, image_digest
from .results import (
    KINDS,
    ResultFrames,
    ResultReader,
    ResultWriter,
    read_field,
    read_results,
    read_stereo,
    repair_results,
)
from .stereo import FORMAT_NAME as STEREO_FORMAT_NAME
from .stereo import StereoResults

__all__ = ["ResultWriter", "ResultReader", "ResultFrames", "read_results", "read_stereo", "read_field", "TrackResults",
           "FrameResult", "StereoResults", "SCHEMA_VERSION", "FORMAT_NAME", "STEREO_FORMAT_NAME", "KINDS",
           "image_digest", "device_checksum", "DEVICE_CHECKSUM_PREFIX", "ResultFileInUse", "ResultWriteError",
           "ResultFileDamaged", "repair_results"]
