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

__all__ = ["SCHEMA_VERSION", "StoreKind", "Compression", "DEFAULT_COMPRESSION", "LEGACY_COMPRESSION",
           "parse_compression", "write_dataset", "image_digest", "device_checksum", "DEVICE_CHECKSUM_PREFIX", "frame_name",
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
    write_payload : (h5py group, field, strain, compression) -> None, writes the frame's datasets and attrs
        (``compression`` a :class:`Compression`; datasets through :func:`write_dataset`)
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


@dataclass(frozen=True)
class Compression:
    """How a result file's datasets are compressed (an HDF5 filter, or none) and checksummed.

    filter : None (stored as they are), "lzf" (h5py's built-in LZF: fast) or "gzip" (zlib, any HDF5 reader)
    level : the gzip level 0-9 (None otherwise)
    checksum : HDF5's Fletcher-32 filter on every dataset (default True): each chunk's checksum is
        stored with it and verified by HDF5 on every read, so a flipped bit or a zeroed block in a
        frame's data is an error naming the frame, not a silently wrong value (root attribute
        ``checksum``: "fletcher32" or "none"; files without it were written without checksums)

    Compressed datasets also get HDF5's byte shuffle (measured: smaller and faster on these
    arrays). A dataset of fewer than 64 values, or one whose bytes do not compress (a probe of up
    to 1024 values spread over it, shuffled and deflated at level 1, shrinks by less than
    :attr:`MIN_GAIN`: float64 strains and uncertainties are mostly noise in their low bits), is
    stored without a filter, so the filter's CPU time is spent only where it saves space. HDF5
    filters are self-describing: readers need nothing to read any setting.
    """

    filter: str | None = None
    level: int | None = None
    checksum: bool = True

    MIN_GAIN = 0.15  # a dataset is compressed when the probe shrinks by at least this fraction
    MIN_SIZE = 64  # values; smaller datasets are stored as they are

    @property
    def text(self) -> str:
        """The setting as written (``"none"``, ``"lzf"``, ``"gzip:4"``): the ``compression`` root attribute."""
        if self.filter is None:
            return "none"
        return self.filter if self.level is None else f"{self.filter}:{self.level}"

    @property
    def checksum_text(self) -> str:
        """The checksum setting as written: the ``checksum`` root attribute ("fletcher32" or "none")."""
        return "fletcher32" if self.checksum else "none"

    def dataset_options(self, arr: np.ndarray) -> dict:
        """The ``create_dataset`` keywords of an array: its filter and shuffle, or none (chunked storage
        all the same for arrays of ``MIN_SIZE`` values or more: files of contiguous datasets only made
        the writing process's memory grow with the number of frames written, +20 MB over 800 frames),
        and the Fletcher-32 checksum (:attr:`checksum`; small arrays then are one chunk: HDF5's filters
        need chunked storage). Empty and 0-d arrays are stored as they are (nothing to checksum)."""
        small = arr.size < self.MIN_SIZE
        if small and not (self.checksum and arr.size and arr.ndim):
            return {}
        check = {"fletcher32": True} if self.checksum else {}
        if small or self.filter is None or not _compresses(arr, self.MIN_GAIN):
            return {"chunks": arr.shape if small else _chunks(arr), **check}
        opts = {"compression": self.filter, "shuffle": arr.dtype.itemsize > 1, **check}
        if self.level is not None:
            opts["compression_opts"] = self.level
        return opts


def _chunks(arr: np.ndarray, nbytes: int = 4 << 20) -> tuple:
    """Chunks of whole rows of at most ``nbytes`` (the whole array when smaller): few chunks to index."""
    row = max(1, arr[:1].nbytes) if arr.shape[0] else 1
    return (max(1, min(arr.shape[0], nbytes // row)),) + arr.shape[1:]


def _compresses(arr: np.ndarray, min_gain: float) -> bool:
    """Whether ``arr`` (shuffled, deflated at level 1) shrinks by ``min_gain``: a probe of <= 1024 values."""
    import zlib

    flat = arr.reshape(arr.shape[0], -1) if arr.ndim > 1 else arr.reshape(-1)
    rows = flat.shape[0]
    sample = np.ascontiguousarray(flat[:: max(1, rows // 1024)][:1024])
    raw = sample.view(np.uint8).reshape(-1, sample.dtype.itemsize).T.tobytes()  # byte shuffle
    return len(zlib.compress(raw, 1)) <= (1.0 - min_gain) * len(raw)


#: the compression of new result files when none is chosen: none, the fastest to write and readable by
#: every HDF5 tool (docs/results_format.md: measured against lzf and gzip on sequence throughput)
DEFAULT_COMPRESSION = Compression(None)
#: the compression of files written before the setting existed (they hold no ``compression`` attribute)
LEGACY_COMPRESSION = Compression("gzip", 4)


def parse_compression(value) -> Compression:
    """A compression setting: ``"none"``, ``"lzf"``, ``"gzip"`` (level 4) or ``"gzip:N"`` (N in 0-9),
    a :class:`Compression`, or None (:data:`DEFAULT_COMPRESSION`)."""
    if value is None:
        return DEFAULT_COMPRESSION
    if isinstance(value, Compression):
        return value
    if not isinstance(value, str):
        raise ValueError(f"compression must be 'none', 'lzf', 'gzip' or 'gzip:LEVEL', got {value!r}")
    text = value.strip().lower()
    if text in ("none", "off", ""):
        return Compression(None)
    if text == "lzf":
        return Compression("lzf")
    if text == "gzip":
        return Compression("gzip", 4)
    if text.startswith("gzip:"):
        level = text[5:]
        if level.isdigit() and 0 <= int(level) <= 9:
            return Compression("gzip", int(level))
        raise ValueError(f"compression {value!r}: the gzip level must be an integer from 0 to 9")
    raise ValueError(f"compression must be 'none', 'lzf', 'gzip' or 'gzip:LEVEL' (0-9), got {value!r}")


def write_dataset(group, key: str, arr, compression: Compression):
    """``group[key] = arr`` with ``compression``'s filter where it pays (:meth:`Compression.dataset_options`)."""
    arr = np.asarray(arr)
    return group.create_dataset(key, data=arr, **compression.dataset_options(arr))


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
    h.update(arr)  # the array's own buffer (C-contiguous): no copy of its bytes
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
