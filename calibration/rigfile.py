"""A stereo rig from a file of any format Specula reads, detected from the file, or the rig itself.

:func:`as_rig` is what every function that takes a rig calls (``dic.stereo.StereoCorrelation``,
``dic.stereo.stereo``, ``dic.sequence.stereo_sequence``, ``specula stereo --rig``), so a rig may be
given as a :class:`~calibration.stereo.StereoRig` or as the path of its file:

==========================  ======================================================================
Specula JSON (``.json``)    :meth:`StereoRig.load` (a JSON object with a ``schema`` key)
OpenCV FileStorage          :func:`calibration.formats.load_opencv` (``.yml``/``.yaml``, ``.xml``
                            with root ``<opencv_storage>``, ``.json`` without a ``schema`` key)
DICe camera system          :func:`calibration.formats.load_dice_xml` (``.xml``, root ``<ParameterList>``)
VIC-3D calibration          :func:`calibration.formats.load_vic3d_xml` (any other ``.xml``)
==========================  ======================================================================

Lives apart from :mod:`calibration.stereo` because it needs :mod:`calibration.formats`, which
itself builds on :mod:`calibration.stereo`.
"""
from __future__ import annotations

import json
import os
import xml.etree.ElementTree as ET
from pathlib import Path

from .formats import load_dice_xml, load_opencv, load_vic3d_xml
from .stereo import StereoRig

__all__ = ["as_rig", "load_rig", "RIG_SUFFIXES"]

#: file name suffixes :func:`load_rig` reads (case-insensitive)
RIG_SUFFIXES = (".json", ".yml", ".yaml", ".xml")

_RIG_ATTRIBUTES = ("left", "right", "R_right_left", "t_right_left")


def _xml_root_tag(path: Path) -> str:
    try:
        for _, element in ET.iterparse(os.fspath(path), events=("start",)):
            return element.tag
    except ET.ParseError as exc:
        raise ValueError(f"rig file {os.fspath(path)!r} is not well-formed XML ({exc}); is it truncated?") from None
    raise ValueError(f"rig file {os.fspath(path)!r} is empty")


def _json_has_schema(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError):
        return True  # let the Specula loader report what is wrong with it
    return not isinstance(data, dict) or "schema" in data


def load_rig(path, *, image_size=None) -> StereoRig:
    """Read a stereo rig from a Specula, OpenCV, DICe or VIC-3D file, the format detected from the file.

    Parameters
    ----------
    path : str or Path
        ``.json`` (Specula rig file, or OpenCV FileStorage JSON), ``.yml``/``.yaml`` (OpenCV),
        ``.xml`` (OpenCV, DICe camera system or VIC-3D calibration, told apart by the root element).
    image_size : (width, height), optional
        Only for VIC-3D files that do not record the image size.

    Raises
    ------
    ValueError
        Missing file, unknown suffix, a file of one camera instead of a rig, or whatever the
        format's loader finds wrong (the message names the file).
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"a rig file must be given as a path (str or Path), got {type(path).__name__}")
    p = Path(os.fspath(path))
    if not p.is_file():
        raise ValueError(f"rig file {os.fspath(p)!r} does not exist" if not p.exists()
                         else f"rig file {os.fspath(p)!r} is not a file")
    suffix = p.suffix.lower()
    if suffix not in RIG_SUFFIXES:
        raise ValueError(f"rig file {os.fspath(p)!r}: unknown format {p.suffix!r}; expected a Specula rig (.json) "
                         "or an OpenCV (.yml, .yaml, .xml, .json), DICe (.xml) or VIC-3D (.xml) calibration")
    if image_size is not None and suffix != ".xml":
        raise ValueError("image_size is only used for VIC-3D .xml files")
    if suffix == ".json" and _json_has_schema(p):
        return StereoRig.load(p)
    if suffix == ".xml":
        tag = _xml_root_tag(p)
        if tag == "ParameterList":
            rig = load_dice_xml(p)
        elif tag == "opencv_storage":
            rig = load_opencv(p)
        else:
            rig = load_vic3d_xml(p, image_size=image_size)
    else:
        rig = load_opencv(p)
    if not isinstance(rig, StereoRig):
        raise ValueError(f"rig file {os.fspath(p)!r} holds one camera ({type(rig).__name__}), not a stereo rig "
                         "(it needs both cameras and R, T)")
    return rig


def as_rig(rig_or_path, *, image_size=None):
    """``rig_or_path`` as a rig: a :class:`StereoRig` (or an object with its attributes) as it is, a path
    read with :func:`load_rig`; anything else raises ``ValueError``."""
    if isinstance(rig_or_path, (str, os.PathLike)):
        return load_rig(rig_or_path, image_size=image_size)
    if isinstance(rig_or_path, StereoRig) or all(hasattr(rig_or_path, a) for a in _RIG_ATTRIBUTES):
        return rig_or_path
    raise ValueError("rig must be a calibration.stereo.StereoRig or the path of a rig file (Specula .json, "
                     f"OpenCV, DICe or VIC-3D), got {type(rig_or_path).__name__}")
