"""The stereo payload of a result file (format ``specula-stereo``): one Field3D per state, plus the reference match.

Beyond the common layout a stereo file has::

    /rig                   attrs: json (the StereoRig file content)
    /reference/match       points_left, points_right, params, zncc, iterations, icgn_status,
                           epipolar_px, guess_source, status; attrs n_features, order
    /frames/<index>        one group per state ("000000" = the reference shape)
        attrs: grid_shape, frame_name, R_frame_left, t_frame_left, strain_type (what exx, eyy, exy are; absent in
               files before it: "green-lagrange") (besides the common ones); reference_index
               (written by dic.sequence.stereo_sequence; read as Field3D.reference_index, 0 when absent)
        datasets: every per-point array of the Field3D (points, X ... W, exx, eyy, exy, normal,
                  zncc_*, epipolar_*, reprojection_*, status, strain_valid) and its details
                  (match_status, track_left_status, ..., params_left, params_right, ...);
                  compressed with the file's setting (root attr ``compression``; dic.store.layout.Compression)

The frame protocol (``.partial`` -> complete, flush, resume) is :class:`dic.store.ResultWriter`'s.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .layout import DEFAULT_COMPRESSION, Compression, StoreKind, parse_compression, write_dataset

__all__ = ["FORMAT_NAME", "KIND", "StereoResults", "table_attrs", "write_field3d", "read_field3d", "write_match", "read_match"]

FORMAT_NAME = "specula-stereo"
MATCH_DATASETS = ("points_left", "points_right", "params", "zncc", "iterations", "icgn_status", "epipolar_px",
                  "guess_source", "status")
FIELD_DATASETS = ("points", "X", "Y", "Z", "U", "V", "W", "exx", "eyy", "exy", "normal", "zncc_stereo", "zncc_left",
                  "zncc_right", "epipolar_ref_px", "epipolar_px", "reprojection_ref_px", "reprojection_px", "status",
                  "strain_valid")


@dataclass
class StereoResults:
    """A stereo result file read back (:func:`dic.store.read_stereo`).

    ``fields`` maps state index -> :class:`dic.field3d.Field3D` (0 = the reference shape);
    ``match`` is the reference :class:`dic.StereoMatch`; ``rig`` the
    :class:`calibration.stereo.StereoRig`; ``settings`` the correlation settings; ``paths`` maps
    index -> (left, right) file names; ``reference_shape`` is (H, W) px.
    """

    fields: dict
    match: object | None
    rig: object
    settings: dict
    paths: dict = field(default_factory=dict)
    reference_shape: tuple = ()

    @property
    def indices(self) -> list[int]:
        return sorted(self.fields)

    def __repr__(self) -> str:
        idx = self.indices
        span = "no finished state" if not idx else f"{len(idx)} ({idx[0]}..{idx[-1]})" if len(idx) > 1 else f"1 ({idx[0]})"
        parts = [f"StereoResults: states {span}"]
        if idx:
            f0 = self.fields[idx[0]]
            grid = f" on a {f0.grid_shape[0]} x {f0.grid_shape[1]} grid" if f0.grid_shape is not None else ""
            parts[0] += f", {len(f0)} points{grid}, {f0.frame_name} frame (mm)"
            shares = [100.0 * np.count_nonzero(f.valid) / max(len(f), 1) for f in self.fields.values()]
            lo, hi = min(shares), max(shares)
            parts.append(f"OK {lo:.1f} %" if hi - lo < 0.05 else f"OK {lo:.1f}-{hi:.1f} % per state")
        if self.match is not None:
            parts.append(f"reference match {int(np.count_nonzero(self.match.valid))}/{len(self.match.status)} OK")
        if len(self.reference_shape) == 2:
            parts.append(f"images {self.reference_shape[1]} x {self.reference_shape[0]} px")
        s = self.settings or {}
        parts.append(", ".join(f"{k} {s[k]}" for k in ("subset", "step", "order") if s.get(k) is not None))
        return "<" + "; ".join(p for p in parts if p) + ">"

    def _field(self, index):
        if not self.fields:
            raise ValueError("the stereo result file has no finished state")
        if index is None:
            return self.fields[self.indices[-1]]
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or int(index) not in self.fields:
            raise ValueError(f"no state {index!r} in the stereo results; states: {self.indices}")
        return self.fields[int(index)]

    def to_xarray(self):
        """The file as an :class:`xarray.Dataset` over ``frame`` (the states) x ``point``: coordinates
        ``frame``, ``x``, ``y`` (left reference image, px), ``X``, ``Y``, ``Z`` (frame, point; mm),
        ``left_path``, ``right_path``; the columns of :meth:`dic.field3d.Field3D.to_xarray` with
        units; the rig and settings (JSON) as attributes."""
        from ..field3d import StereoStatus
        from ..tabular import columns_3d, frame_dataset

        idx = self.indices
        attrs = table_attrs(self.settings, self.rig, self.reference_shape, self.fields[idx[0]] if idx else None)
        paths = [tuple(self.paths.get(i, ("", ""))) for i in idx]
        return frame_dataset([(i, columns_3d(self.fields[i])) for i in idx], kind="stereo", attrs=attrs,
                             status_codes=StereoStatus,
                             frame_coords={"left_path": [str(p[0]) for p in paths],
                                           "right_path": [str(p[1]) for p in paths]})

    def to_dataframe(self):
        """The file as a :class:`pandas.DataFrame` indexed by (``frame``, ``point``)."""
        from ..tabular import dataframe

        return dataframe(self.to_xarray())

    def plot(self, index: int | None = None, quantity: str = "W", *, image=None, limits="frame", **kwargs):
        """A Matplotlib Figure of one quantity of one state (default: the last) over ``image`` (the
        left reference image, optional): :func:`dic.plots.fields.field3d_figure`.

        ``limits``: ``"frame"`` (the state's own values), ``"sequence"`` (one range over every
        state of the file) or ``(vmin, vmax)``. Other keywords go to ``field3d_figure``.
        """
        f = self._field(index)
        if isinstance(limits, str):
            if limits not in ("frame", "sequence"):
                raise ValueError(f"limits must be 'frame', 'sequence' or (vmin, vmax), got {limits!r}")
            if limits == "sequence" and quantity != "status":
                from ..plots.fields import sequence_limits

                kwargs["vmin"], kwargs["vmax"] = sequence_limits([self.fields[i] for i in self.indices],
                                                                 [quantity])[quantity]
        else:
            try:
                kwargs["vmin"], kwargs["vmax"] = limits
            except (TypeError, ValueError):
                raise ValueError(f"limits must be 'frame', 'sequence' or (vmin, vmax), got {limits!r}") from None
        return f.plot(quantity, image, **kwargs)


def table_attrs(settings: dict, rig, reference_shape, first) -> dict:
    """The attributes of a stereo result file's frame x point table (:meth:`StereoResults.to_xarray`, the
    exports): ``rig`` a StereoRig or its dict, ``first`` the first state's Field3D (or None)."""
    rig = rig.to_dict() if hasattr(rig, "to_dict") else rig
    return {"title": "Specula stereo-DIC results", "source_format": FORMAT_NAME, "settings": settings,
            "rig": rig, "reference_shape": [int(v) for v in reference_shape],
            "frame_name": first.frame_name if first is not None else None,
            "grid_shape": list(first.grid_shape) if first is not None and first.grid_shape is not None else None,
            "strain_type": getattr(first, "strain_type", "green-lagrange") if first is not None else None}


def write_field3d(group, field3d, strain=None, compression: Compression | str | None = DEFAULT_COMPRESSION) -> None:
    """Write one state's :class:`dic.field3d.Field3D` (arrays and details) into an empty h5py ``group``.

    ``compression``: :func:`dic.store.layout.parse_compression` (booleans are not compressed)."""
    compression = parse_compression(compression)
    if strain is not None:
        raise ValueError("a stereo frame carries its strain in the Field3D; pass strain=None")
    if not hasattr(field3d, "arrays") or not hasattr(field3d, "R_frame_left"):
        raise ValueError(f"a stereo frame must be a dic.field3d.Field3D, got {type(field3d).__name__}")
    flags = Compression(None, checksum=compression.checksum)
    for key, arr in field3d.arrays().items():
        arr = np.asarray(arr)
        if arr.dtype == bool:  # flags: not compressed (checksummed all the same)
            write_dataset(group, key, arr, flags)
        else:
            write_dataset(group, key, arr, compression)
    group.attrs.update({"grid_shape": list(field3d.grid_shape) if field3d.grid_shape is not None else [],
                        "frame_name": field3d.frame_name, "R_frame_left": np.asarray(field3d.R_frame_left),
                        "t_frame_left": np.asarray(field3d.t_frame_left),
                        "strain_type": str(getattr(field3d, "strain_type", "green-lagrange"))})


def read_field3d(group):
    """A complete ``/frames/<index>`` group of a stereo file as a :class:`dic.field3d.Field3D`."""
    from ..field3d import Field3D

    for key in FIELD_DATASETS:
        if key not in group:
            raise ValueError(f"has no '{key}' dataset")
    arrays = {k: group[k][()] for k in FIELD_DATASETS}
    details = {k: group[k][()] for k in group.keys() if k not in FIELD_DATASETS}
    gs = [int(v) for v in group.attrs.get("grid_shape", [])]
    return Field3D(**arrays, grid_shape=tuple(gs) if gs else None,
                   R_frame_left=np.asarray(group.attrs["R_frame_left"]),
                   t_frame_left=np.asarray(group.attrs["t_frame_left"]), frame_name=str(group.attrs["frame_name"]),
                   index=int(group.attrs["index"]), details=details,
                   reference_index=int(group.attrs.get("reference_index", 0)),
                   strain_type=str(group.attrs.get("strain_type", "green-lagrange")))  # files before it: Green-Lagrange


def write_match(group, match, compression: Compression | str | None = None) -> None:
    """Write the reference :class:`dic.StereoMatch` into an empty h5py ``group`` (``/reference/match``).

    Stored without compression unless ``compression`` is given (written once per file)."""
    if not hasattr(match, "arrays"):
        raise ValueError(f"match must be a dic.StereoMatch, got {type(match).__name__}")
    comp = Compression(None) if compression is None else parse_compression(compression)
    for key, arr in match.arrays().items():
        write_dataset(group, key, arr, comp)
    group.attrs.update({"n_features": match.n_features, "order": match.order})


def read_match(group):
    """``/reference/match`` as a :class:`dic.StereoMatch`."""
    from .._stereo import StereoMatch

    arrays = {k: group[k][()] for k in MATCH_DATASETS}
    return StereoMatch(**arrays, n_features=int(group.attrs.get("n_features", 0)),
                       order=int(group.attrs.get("order", 2)))


KIND = StoreKind(name="stereo", format=FORMAT_NAME, label="stereo", image_roles=("left", "right"),
                 reference_noun="reference image pair", frame_noun="state", needs_rig=True,
                 write_payload=write_field3d, read_payload=read_field3d)
