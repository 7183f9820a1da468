"""The 2-D DIC payload of a result file (format ``specula-dic2d``): one Field2D (+ strain) per frame.

Per frame ``/frames/<index>``::

    points (N, 2) f8, u (N,), v (N,), params (N, 6|12), zncc (N,), iterations (N,), status (N,) i1,
    valid (N,) bool                  compressed with the file's setting (root attr ``compression``;
                                     dic.store.layout.Compression: where it pays, with byte shuffle)
    sigma_u, sigma_v (N,) f8         optional: predicted displacement std (px, NaN where not valid);
                                     attrs noise_sigma (grey levels), noise_source ("given" | "residual")
    strain/                          optional: dudx, dudy, dvdx, dvdy, exx, eyy, exy, Exx, Eyy, Exy (N,) f8,
                                     valid (N,) bool; attrs window, step (dx, dy) px, strain_type (what exx,
                                     eyy, exy are; absent before strain types: the settings' strain_type, else small)

The frame protocol (``.partial`` -> complete, flush, resume) is :class:`dic.store.ResultWriter`'s.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..field2d import Field2D
from .layout import DEFAULT_COMPRESSION, Compression, StoreKind, parse_compression, plain, write_dataset

__all__ = ["FORMAT_NAME", "KIND", "FrameResult", "TrackResults", "table_attrs", "write_field2d", "read_field2d"]

FORMAT_NAME = "specula-dic2d"
FIELD_DATASETS = ("points", "u", "v", "params", "zncc", "iterations", "status", "valid", "sigma_u", "sigma_v")
#: frame attributes taken from the field when it has them (dic.quality: the noise behind sigma_u, sigma_v)
FIELD_ATTRS = ("noise_sigma", "noise_source")
STRAIN_DATASETS = ("dudx", "dudy", "dvdx", "dvdy", "exx", "eyy", "exy", "Exx", "Eyy", "Exy", "valid")


@dataclass(repr=False)
class FrameResult(Field2D):
    """One frame of a 2-D result file: a :class:`dic.field2d.Field2D` read back (arrays aligned with
    ``points``, (N, 2) px), the one 2-D result type.

    What the file holds per frame fills the :class:`Field2D` fields: the arrays, ``index``,
    ``reference_index``, ``sigma_u``, ``sigma_v``, ``noise_sigma``, ``noise_source`` and ``strain``
    (the stored strain as a dict of (N,) arrays with ``window`` and ``step``, or None); ``order``
    follows from ``params``. A file holds no per-frame ``subset`` (``subset`` is 0: see the file's
    settings) and no mask of the points placed by interpolation at a moved reference
    (``reference_interpolated`` is None; their count is ``attrs["reference_interpolated"]``). Arrays a
    file of another writer lacks are None. Added: ``path`` (the frame's image, '' for an array) and
    ``attrs`` (the frame's stored attributes: ``seconds``, ``sha256``, ``reference_index``, ..., and
    ``strain_type``, the type of its strain, where the file records it).
    """

    path: str = ""
    attrs: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        n = int(np.asarray(self.points).shape[0])
        text = f"FrameResult: frame {self.index}, {n} points"
        if self.valid is not None and n:
            n_valid = int(np.count_nonzero(self.valid))
            text += f", {n_valid} valid ({100.0 * n_valid / n:.1f} %)"
        text += ", strain" if self.strain is not None else ", no strain"
        if self.path:
            text += f", image {Path(self.path).name}"
        return f"<{text}>"

    def _columns(self) -> dict:
        from ..tabular import columns_2d

        return columns_2d(self.points, self.u, self.v, params=self.params, zncc=self.zncc,
                          iterations=self.iterations, status=self.status, valid=self.valid, strain=self.strain,
                          sigma_u=self.sigma_u, sigma_v=self.sigma_v)

    def to_xarray(self):
        """This frame as an :class:`xarray.Dataset` over ``point`` (the columns of
        :meth:`dic.field2d.Field2D.to_xarray`, with the stored strain)."""
        from ..tabular import point_dataset

        strain_type = self.attrs.get("strain_type") if self.strain is not None else None
        return point_dataset(self._columns(), kind="dic2d",
                             attrs={"title": "Specula 2-D DIC frame", "frame": int(self.index), "image_path": self.path,
                                    "strain_type": strain_type})

    def to_dataframe(self):
        """This frame as a :class:`pandas.DataFrame`, one row per point."""
        from ..tabular import dataframe

        return dataframe(self.to_xarray())

    def plot(self, reference=None, **kwargs):
        """A Matplotlib Figure of this frame (:func:`dic.plots.fields.field_figure`): u, v and the
        stored strains over ``reference`` (the reference image, optional). Keywords go to
        ``field_figure`` (``components``, ``vmin``, ``vmax``, ``limits``, ``cmap``, ``title``, ...)."""
        from ..plots.fields import field_figure

        kwargs.setdefault("title", f"frame {self.index}" + (f": {Path(self.path).name}" if self.path else ""))
        return field_figure(reference, self, self.strain, **kwargs)


def _range_text(values, unit="") -> str:
    lo, hi = min(values), max(values)
    return f"{lo:.1f}{unit}" if abs(hi - lo) < 0.05 else f"{lo:.1f}-{hi:.1f}{unit}"


def frames_text(indices) -> str:
    """``"3 frames (1..3)"``-like summary of frame indices (for reprs)."""
    indices = list(indices)
    if not indices:
        return "no finished frame"
    span = f"{indices[0]}" if len(indices) == 1 else f"{indices[0]}..{indices[-1]}"
    return f"{len(indices)} ({span})"


@dataclass
class TrackResults:
    """Contents of a 2-D DIC result file (:func:`dic.store.read_results`); ``frames`` maps index -> FrameResult.

    ``to_xarray()`` / ``to_dataframe()`` give the whole file as a frame x point table,
    ``plot(index)`` draws a frame (with one colour scale over the file on request).
    """

    path: Path
    attrs: dict
    reference: dict
    settings: dict
    frames: dict[int, FrameResult]

    @property
    def indices(self) -> list[int]:
        """The frame indices, ascending."""
        return sorted(self.frames)

    def __repr__(self) -> str:
        idx = self.indices
        parts = [f"TrackResults {str(self.path)!r}: 2-D DIC, frames {frames_text(idx)}"]
        if idx:
            n = int(np.asarray(self.frames[idx[0]].points).shape[0])
            parts[0] += f", {n} points"
            shares = [100.0 * np.count_nonzero(f.valid) / max(len(f.valid), 1)
                      for f in self.frames.values() if f.valid is not None]
            if shares:
                parts.append(f"valid {_range_text(shares, ' %')} per frame")
        shape = self.reference.get("shape") or ()
        ref = Path(self.reference.get("path", "") or "?").name
        parts.append(f"reference {ref}" + (f" ({shape[1]} x {shape[0]} px)" if len(shape) == 2 else ""))
        s = self.settings
        parts.append(", ".join(f"{k} {s[k]}" for k in ("subset", "step", "order") if s.get(k) is not None))
        return "<" + "; ".join(p for p in parts if p) + ">"

    def _frame(self, index):
        if not self.frames:
            raise ValueError(f"{self.path} has no finished frame")
        if index is None:
            return self.frames[self.indices[-1]]
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or int(index) not in self.frames:
            raise ValueError(f"{self.path} has no frame {index!r}; frames: {self.indices}")
        return self.frames[int(index)]

    def to_xarray(self):
        """The file as an :class:`xarray.Dataset` over ``frame`` x ``point``: coordinates ``frame``,
        ``x``, ``y`` (px) and ``path`` (each frame's image); the columns of
        :meth:`dic.field2d.Field2D.to_xarray` (strain included) with units; the file's reference,
        settings (JSON) and version as attributes."""
        from ..tabular import frame_dataset

        idx = self.indices
        attrs = table_attrs(self.path, self.attrs, self.reference, self.settings, self.frames[idx[0]] if idx else None)
        return frame_dataset([(i, self.frames[i]._columns()) for i in idx], kind="dic2d", attrs=attrs,
                             frame_coords={"path": [str(self.frames[i].path) for i in idx]})

    def to_dataframe(self):
        """The file as a :class:`pandas.DataFrame` indexed by (``frame``, ``point``)."""
        from ..tabular import dataframe

        return dataframe(self.to_xarray())

    def plot(self, index: int | None = None, *, reference=None, limits="frame", **kwargs):
        """A Matplotlib Figure of one frame (default: the last) over ``reference`` (optional image).

        ``limits``: ``"frame"`` (each map spans its own values), ``"sequence"`` (one colour range
        per component over every frame of the file: frames drawn this way compare at a glance),
        or ``{component: (vmin, vmax)}``. Other keywords go to :func:`dic.plots.fields.field_figure`.
        """
        frame = self._frame(index)
        if isinstance(limits, str):
            if limits not in ("frame", "sequence"):
                raise ValueError(f"limits must be 'frame', 'sequence' or {{component: (vmin, vmax)}}, got {limits!r}")
            if limits == "sequence":
                from ..plots.fields import sequence_limits

                components = kwargs.get("components") or (["u", "v"] + (["exx", "eyy", "exy"] if frame.strain else []))
                frames = [self.frames[i] for i in self.indices]
                limits = sequence_limits(frames, components)
            else:
                limits = None
        return frame.plot(reference, limits=limits, **kwargs)


def table_attrs(path, attrs: dict, reference: dict, settings: dict, first=None) -> dict:
    """The attributes of a 2-D result file's frame x point table (:meth:`TrackResults.to_xarray`, the exports);
    ``first``: the first frame (its strain's type where the settings name none)."""
    from .._strain import stored_strain_type

    shape = reference.get("shape") or ()
    has_strain = first is None or getattr(first, "strain", None) is not None
    return {"title": "Specula 2-D DIC results", "source": str(path), "source_format": FORMAT_NAME,
            "specula_version": attrs.get("specula_version"), "reference_path": reference.get("path", ""),
            "reference_shape": [int(v) for v in shape], "settings": settings,
            "strain_type": stored_strain_type("dic2d", settings, first) if has_strain else None}


def write_field2d(group, field2d, strain=None, compression: Compression | str | None = DEFAULT_COMPRESSION) -> None:
    """Write one frame's displacement field (and optional strain) into an empty h5py ``group``.

    ``field2d`` has ``points`` (N, 2), ``u``, ``v`` (N,) px and optionally ``params``, ``zncc``,
    ``iterations``, ``status``, ``valid``, ``sigma_u``, ``sigma_v``, ``noise_sigma``, ``noise_source``
    (a :class:`dic.Field2D`); ``strain`` is a
    :class:`dic.StrainField` or None. ``compression``: :func:`dic.store.layout.parse_compression`.
    """
    compression = parse_compression(compression)
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
        write_dataset(group, key, arr, compression)
    for key in FIELD_ATTRS:
        val = getattr(field2d, key, None)
        if val is not None:
            group.attrs[key] = val
    if strain is not None:
        sg = group.create_group("strain")
        for key in STRAIN_DATASETS:
            write_dataset(sg, key, np.asarray(getattr(strain, key)), compression)
        sg.attrs["window"] = int(strain.window)
        sg.attrs["step"] = np.asarray(strain.step, dtype=np.float64)
        sg.attrs["strain_type"] = str(getattr(strain, "strain_type", "green-lagrange"))  # what exx, eyy, exy are


def read_field2d(group) -> FrameResult:
    """A complete ``/frames/<index>`` group of a 2-D file as a :class:`FrameResult` (``ValueError`` naming
    a missing dataset)."""
    for key in ("points", "u", "v"):
        if key not in group:
            raise ValueError(f"has no '{key}' dataset")
    data = {k: group[k][()] for k in FIELD_DATASETS if k in group}
    strain = None
    if "strain" in group:
        strain = {k: group["strain"][k][()] for k in group["strain"]}
        strain["window"] = int(group["strain"].attrs["window"])
        strain["step"] = tuple(group["strain"].attrs["step"])
    extra = {k: plain(v) for k, v in group.attrs.items() if k not in ("index", "path")}
    if strain is not None and "strain_type" in group["strain"].attrs:  # absent before strain types: the settings'
        extra["strain_type"] = str(group["strain"].attrs["strain_type"])  # with the frame's attrs (the dict: arrays)
    params = data.get("params")
    return FrameResult(points=data["points"], u=data["u"], v=data["v"], params=params, zncc=data.get("zncc"),
                       iterations=data.get("iterations"), status=data.get("status"), valid=data.get("valid"),
                       subset=0, order=2 if params is not None and params.shape[1] == 12 else 1,
                       sigma_u=data.get("sigma_u"), sigma_v=data.get("sigma_v"), noise_sigma=extra.get("noise_sigma"),
                       noise_source=extra.get("noise_source"), index=int(group.attrs["index"]),
                       reference_index=int(extra.get("reference_index", 0)), strain=strain,
                       path=str(group.attrs.get("path", "")), attrs=extra)


KIND = StoreKind(name="dic2d", format=FORMAT_NAME, label="2-D DIC", image_roles=("",),
                 reference_noun="reference image", frame_noun="frame", needs_rig=False,
                 write_payload=write_field2d, read_payload=read_field2d)
