"""What every Specula result file shares: root attributes, names, JSON and image digests.

The lowest module of :mod:`dic.store`; the per-kind payload modules (:mod:`dic.store.dic2d`,
:mod:`dic.store.stereo`) and the writer/reader (:mod:`dic.store.results`) build on it. The
layout itself is documented in docs/results_format.md.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Callable

import numpy as np

__all__ = ["SCHEMA_VERSION", "StoreKind", "image_digest", "frame_name", "role_attr", "settings_json"]

# One schema version for the whole family: both kinds have been at version 1 since their first
# release, and the unified store writes exactly the version-1 layout.
SCHEMA_VERSION = 1


@dataclass(frozen=True)
class StoreKind:
    """One kind of result file: its format name and how its per-frame payload is written and read.

    name : "dic2d" or "stereo" (the ``kind=`` of :class:`dic.store.ResultWriter`)
    format : the root ``format`` attribute ("specula-dic2d", "specula-stereo")
    label : how messages name the file ("2-D DIC", "stereo")
    image_roles : the images of one state; "" for one image (attrs ``path``, ``sha256``),
        ("left", "right") for a pair (attrs ``left_path``, ``left_sha256``, ...)
    reference_noun, frame_noun : words for messages ("reference image pair", "state", ...)
    needs_rig : the file stores a ``/rig`` (stereo) checked on resume
    write_payload : (h5py group, field, strain) -> None, writes the frame's datasets and attrs
    read_payload : (h5py group) -> the frame's result object
    """

    name: str
    format: str
    label: str
    image_roles: tuple[str, ...]
    reference_noun: str
    frame_noun: str
    needs_rig: bool
    write_payload: Callable
    read_payload: Callable


def now() -> str:
    """The current UTC time, ISO 8601 to the second (the ``created``/``updated``/``written`` attrs)."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def specula_version() -> str:
    try:
        from importlib.metadata import version

        from kernels.conventions import DISTRIBUTION_NAME

        return version(DISTRIBUTION_NAME)
    except Exception:  # pragma: no cover - not installed
        return "unknown"


def image_digest(image) -> str:
    """SHA-256 (hex) of an image's grey levels as C-contiguous float32, shape included.

    Identifies the reference image(s) of a result file, so that a resumed run cannot mix
    results of different references. ``image``: (H, W) or (H, W, C) numeric array.
    """
    arr = np.asarray(image)
    if arr.ndim not in (2, 3) or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise ValueError(f"image_digest needs an (H, W) or (H, W, C) numeric image, got shape {arr.shape} "
                         f"and dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    h = hashlib.sha256()
    h.update(str(arr.shape).encode())
    h.update(arr.tobytes())
    return h.hexdigest()


def frame_name(index: int) -> str:
    """The group name of frame ``index`` under ``/frames``: zero-padded to 6 digits."""
    return f"{int(index):06d}"


def role_attr(role: str, name: str) -> str:
    """Attribute name of an image's ``path``/``sha256``: ``path`` for a single image, ``left_path`` for a pair."""
    return f"{role}_{name}" if role else name


def _json_default(obj):
    # NumPy arrays and scalars as their values (stereo ROIs, POIs); anything else as its text.
    if isinstance(obj, (np.ndarray, np.generic)):
        return obj.tolist()
    return str(obj)


def settings_json(settings) -> str:
    """The canonical JSON text of a settings dict (sorted keys), as stored in ``/settings``."""
    if settings is not None and not isinstance(settings, dict):
        raise ValueError(f"settings must be a dict, got {type(settings).__name__}")
    try:
        return json.dumps(settings if settings is not None else {}, sort_keys=True, default=_json_default)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"settings must be JSON-serialisable: {exc}") from None


def plain(value):
    """An HDF5 attribute value as a Python value (NumPy scalars unwrapped)."""
    return value.item() if isinstance(value, np.generic) else value
