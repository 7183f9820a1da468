"""The 2-D DIC payload of a result file (format ``specula-dic2d``): one Field2D (+ strain) per frame.

Per frame ``/frames/<index>``::

    points (N, 2) f8, u (N,), v (N,), params (N, 6|12), zncc (N,), iterations (N,), status (N,) i1,
    valid (N,) bool                  every dataset gzip level 4 + byte shuffle
    sigma_u, sigma_v (N,) f8         optional: predicted displacement std (px, NaN where not valid);
                                     attrs noise_sigma (grey levels), noise_source ("given" | "residual")
    strain/                          optional: dudx, dudy, dvdx, dvdy, exx, eyy, exy, Exx, Eyy, Exy (N,) f8,
                                     valid (N,) bool; attrs window, step (dx, dy) px

The frame protocol (``.partial`` -> complete, flush, resume) is :class:`dic.store.ResultWriter`'s.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .layout import StoreKind, plain

__all__ = ["FORMAT_NAME", "KIND", "FrameResult", "TrackResults", "write_field2d", "read_field2d"]

FORMAT_NAME = "specula-dic2d"
FIELD_DATASETS = ("points", "u", "v", "params", "zncc", "iterations", "status", "valid", "sigma_u", "sigma_v")
#: frame attributes taken from the field when it has them (dic.quality: the noise behind sigma_u, sigma_v)
FIELD_ATTRS = ("noise_sigma", "noise_source")
STRAIN_DATASETS = ("dudx", "dudy", "dvdx", "dvdy", "exx", "eyy", "exy", "Exx", "Eyy", "Exy", "valid")


@dataclass
class FrameResult:
    """One frame of a 2-D result file (arrays aligned with ``points``, (N, 2) px)."""

    index: int
    path: str
    points: np.ndarray
    u: np.ndarray
    v: np.ndarray
    params: np.ndarray | None = None
    zncc: np.ndarray | None = None
    iterations: np.ndarray | None = None
    status: np.ndarray | None = None
    valid: np.ndarray | None = None
    strain: dict | None = None
    attrs: dict = field(default_factory=dict)
    sigma_u: np.ndarray | None = None
    sigma_v: np.ndarray | None = None


@dataclass
class TrackResults:
    """Contents of a 2-D DIC result file (:func:`dic.store.read_results`); ``frames`` maps index -> FrameResult."""

    path: Path
    attrs: dict
    reference: dict
    settings: dict
    frames: dict[int, FrameResult]


def _compressed(group, key, data) -> None:
    group.create_dataset(key, data=data, compression="gzip", compression_opts=4, shuffle=True)


def write_field2d(group, field2d, strain=None) -> None:
    """Write one frame's displacement field (and optional strain) into an empty h5py ``group``.

    ``field2d`` has ``points`` (N, 2), ``u``, ``v`` (N,) px and optionally ``params``, ``zncc``,
    ``iterations``, ``status``, ``valid``, ``sigma_u``, ``sigma_v``, ``noise_sigma``, ``noise_source``
    (a :class:`dic.track.Field2D`); ``strain`` is a
    :class:`dic.strain.StrainField` or None.
    """
    n = None
    for key in FIELD_DATASETS:
        val = getattr(field2d, key, None)
        if val is None:
            if key in ("points", "u", "v"):
                raise ValueError(f"the field has no {key!r}; write_frame needs points, u and v")
            continue
        arr = np.asarray(val)
        if key == "status":
            arr = arr.astype(np.int8)
        elif key == "valid":
            arr = arr.astype(bool)
        n = arr.shape[0] if n is None else n
        if arr.shape[0] != n:
            raise ValueError(f"field arrays disagree in length: {key} has {arr.shape[0]}, expected {n}")
        _compressed(group, key, arr)
    for key in FIELD_ATTRS:
        val = getattr(field2d, key, None)
        if val is not None:
            group.attrs[key] = val
    if strain is not None:
        sg = group.create_group("strain")
        for key in STRAIN_DATASETS:
            _compressed(sg, key, np.asarray(getattr(strain, key)))
        sg.attrs["window"] = int(strain.window)
        sg.attrs["step"] = np.asarray(strain.step, dtype=np.float64)


def read_field2d(group) -> FrameResult:
    """A complete ``/frames/<index>`` group of a 2-D file as a :class:`FrameResult`."""
    data = {k: group[k][()] for k in FIELD_DATASETS if k in group}
    strain = None
    if "strain" in group:
        strain = {k: group["strain"][k][()] for k in group["strain"]}
        strain["window"] = int(group["strain"].attrs["window"])
        strain["step"] = tuple(group["strain"].attrs["step"])
    extra = {k: plain(v) for k, v in group.attrs.items() if k not in ("index", "path")}
    return FrameResult(index=int(group.attrs["index"]), path=str(group.attrs.get("path", "")), strain=strain,
                       attrs=extra, **data)


KIND = StoreKind(name="dic2d", format=FORMAT_NAME, label="2-D DIC", image_roles=("",),
                 reference_noun="reference image", frame_noun="frame", needs_rig=False,
                 write_payload=write_field2d, read_payload=read_field2d)
