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

__all__ = ["SCHEMA_VERSION", "StoreKind", "image_digest", "device_checksum", "DEVICE_CHECKSUM_PREFIX", "frame_name",
           "role_attr", "settings_json"]

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


#: how a frame's stored digest says it is a :func:`device_checksum` rather than a SHA-256 (64 hex digits)
DEVICE_CHECKSUM_PREFIX = "devsum1-"
_P = 2147483647  # 2^31 - 1: the checksum's terms stay below 2^31 and their sums below 2^63
_MULTIPLIERS = ((1103515245, 12345, 2654435761, 97), (1664525, 1013904223, 3266489917, 31))


def device_checksum(image) -> str:
    """A checksum of an image's float32 grey levels computed where the image is: a torch tensor on its
    device (CUDA or CPU) or a NumPy array, the same value for the same image either way.

    The resume check of a sequence (:meth:`dic.store.ResultWriter.check_frame`) needs a digest of
    every frame; :func:`image_digest` (SHA-256) needs the bytes on the host, which for a frame kept on
    the GPU would be a device-to-host copy of the whole image per frame. This checksum reduces the
    image on the device instead (exact integer arithmetic: two position-weighted sums modulo
    2^31 - 1 of the two 16-bit halves of each float32 word), and only those two numbers come back;
    they are hashed with the shape. It tells a different image apart (any changed pixel, swapped
    pixels, another shape); it is not a cryptographic hash. Returns ``"devsum1-"`` + 40 hex digits.
    """
    from kernels.images import is_torch_tensor

    if is_torch_tensor(image):
        import torch

        x = image.detach()
        if x.ndim not in (2, 3) or x.is_complex():
            raise ValueError(f"device_checksum needs an (H, W) or (H, W, C) real image, got shape {tuple(x.shape)} "
                             f"and dtype {x.dtype}")
        shape = tuple(int(n) for n in x.shape)
        words = x.to(torch.float32).contiguous().reshape(-1).view(torch.int32).to(torch.int64) & 0xFFFFFFFF
        i = torch.arange(1, words.numel() + 1, dtype=torch.int64, device=words.device) % _P
    else:
        arr = np.asarray(image)
        if arr.ndim not in (2, 3) or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool) \
                or np.iscomplexobj(arr):
            raise ValueError(f"device_checksum needs an (H, W) or (H, W, C) real image, got shape {arr.shape} "
                             f"and dtype {arr.dtype}")
        shape = tuple(int(n) for n in arr.shape)
        words = np.ascontiguousarray(arr, dtype=np.float32).reshape(-1).view(np.int32).astype(np.int64) & 0xFFFFFFFF
        i = np.arange(1, words.size + 1, dtype=np.int64) % _P
    lo, hi = words & 0xFFFF, words >> 16
    sums = []
    for a, b, c, d in _MULTIPLIERS:
        w1 = (i * a + b) % _P  # < 2^31 each; i * a < 2^63
        w2 = (i * (c % _P) + d) % _P
        sums.append(((lo * w1 + hi * w2) % _P).sum())  # terms < 2^31: the sum of < 2^32 of them fits int64
    if is_torch_tensor(sums[0]):  # the two sums are the only values read back from the device
        sums = torch.stack(sums).tolist()
    values = [int(v) for v in sums]
    h = hashlib.sha256(repr((shape, values)).encode())
    return DEVICE_CHECKSUM_PREFIX + h.hexdigest()[:40]


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
