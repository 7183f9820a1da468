"""Post-processing of result files: strain re-computation, derived strains, extensometers, histories.

Works on 2-D results (``specula track``, :func:`dic.store.read_results`) and stereo results
(``specula stereo``, :func:`dic.store.read_stereo`), given as a path or as the object read back.
docs/postprocessing.md has worked examples; the CLI verbs are ``specula strain``, ``extensometer``,
``history`` and ``profile`` (dic/commands/postprocess.py).

* :func:`principal_strains` — principal strains ``e1 >= e2``, the angle of ``e1``, the maximum
  shear and the von Mises equivalent strain of an in-plane strain tensor (definitions below).
* :func:`recompute_strain` — the strain of a 2-D result file with another fit window (grid
  points or px), written through the results store (:class:`dic.store.ResultWriter`).
* :func:`extensometer` — a virtual extensometer: a gauge between two reference points, its
  length, length change and engineering strain per frame.
* :func:`point_history`, :func:`line_profile` — a quantity at a point over the frames, and
  along a line per frame.

Values at arbitrary points come from the grid cell of the points that contains them
(:mod:`dic.gridinterp`): bilinear in the cell when every corner it depends on is a point of the
result and valid in the frame, exact for fields linear in the position; otherwise NaN, with a
:class:`~dic.gridinterp.QueryStatus` saying why (outside the grid, in a hole or an excluded
region, among invalid points). Nothing is interpolated across a hole, an excluded region or
invalid points. Points on no grid (given by hand) use a Delaunay triangulation without the
triangles longer than 1.5 point spacings.

Derived strains (tensor shear ``exy``, as everywhere in Specula; the engineering shear strain is
``γxy = 2 exy``)::

    e1, e2     = (exx + eyy)/2 ± sqrt(((exx - eyy)/2)² + exy²)     (e1 >= e2)
    angle      = ½ atan2(2 exy, exx - eyy)   in (-π/2, π/2], rad, from the x axis to e1's direction
                 (towards +y; image y points down, so positive angles turn clockwise on screen)
    max_shear  = (e1 - e2)/2                 tensor; the engineering maximum shear is e1 - e2
    von_mises  = (2/√3) sqrt(e1² + e1 e2 + e2²) = (2/√3) sqrt(exx² + exx eyy + eyy² + exy²)

``von_mises`` is the equivalent strain ``sqrt(2/3 ε:ε)`` of the in-plane tensor completed with
the incompressible out-of-plane strain ``e3 = -(e1 + e2)`` (the convention of VIC-3D and of
plasticity): it equals ``e`` for an incompressible uniaxial strain ``(e, -e/2)`` and ``γ/√3``
for a pure engineering shear ``γ``.

Units: 2-D positions and displacements are px, or mm with a scale (``scale=`` mm/px, or the
``scale_mm_per_px`` a file stores in its settings, see :func:`results_scale`); strains are
dimensionless and unchanged by a scale. Stereo results are in mm (docs/stereo.md).
"""
from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .gridinterp import QueryStatus

__all__ = ["QueryStatus", "PrincipalStrains", "principal_strains", "recompute_strain", "window_points", "results_scale",
           "SCALE_KEY", "Extensometer", "extensometer", "History", "point_history", "Profile", "line_profile",
           "quantities", "load_results", "results_crack_opening"]

#: the settings key of a result file that holds its mm/px scale (2-D; absent: pixels)
SCALE_KEY = "scale_mm_per_px"

_DERIVED = ("e1", "e2", "angle", "max_shear", "von_mises")
_Q2D_DISP = ("u", "v", "magnitude")
_Q2D_STRAIN = ("dudx", "dudy", "dvdx", "dvdy", "exx", "eyy", "exy", "Exx", "Eyy", "Exy") + _DERIVED
_Q3D_DISP = ("U", "V", "W", "magnitude", "X", "Y", "Z")
_Q3D_STRAIN = ("exx", "eyy", "exy") + _DERIVED
_Q3D_OTHER = ("zncc_stereo", "zncc_left", "zncc_right")


# ------------------------------------------------------------------------------------------------
# derived strains


@dataclass
class PrincipalStrains:
    """Principal strains and derived measures of an in-plane strain tensor (module docstring).

    Every attribute is a float64 array of the shape of the input components (NaN where an input
    is NaN): ``e1 >= e2`` the principal strains, ``angle`` (rad, of ``e1``'s direction from the
    x axis, in (-π/2, π/2]), ``max_shear`` the tensor maximum shear ``(e1 - e2)/2``,
    ``von_mises`` the equivalent strain.
    """

    e1: np.ndarray
    e2: np.ndarray
    angle: np.ndarray
    max_shear: np.ndarray
    von_mises: np.ndarray


def _components_of(source):
    if isinstance(source, dict):
        missing = [k for k in ("exx", "eyy", "exy") if k not in source]
        if missing:
            raise ValueError(f"the strain dict has no {', '.join(missing)}")
        return source["exx"], source["eyy"], source["exy"]
    try:
        return source.exx, source.eyy, source.exy
    except AttributeError:
        raise ValueError("principal_strains takes exx, eyy, exy arrays, or one object with them (a "
                         f"dic._strain.StrainField, a dic.field3d.Field3D, a strain dict); got {type(source).__name__}"
                         ) from None


def principal_strains(exx, eyy=None, exy=None) -> PrincipalStrains:
    """Principal strains, angle, maximum shear and von Mises strain of ``(exx, eyy, exy)``.

    Parameters
    ----------
    exx, eyy, exy : array-like of one shape (or scalars)
        Normal strains and the **tensor** shear (``exy = γxy / 2``), e.g. a
        :class:`dic.StrainField`'s small strain or a :class:`dic.field3d.Field3D`'s
        Green-Lagrange surface strain. Alternatively pass one object with attributes or keys
        ``exx``, ``eyy``, ``exy`` as ``exx`` alone (then the Green-Lagrange ``Exx``... of a
        StrainField are not used: call with ``s.Exx, s.Eyy, s.Exy`` for those).

    Returns
    -------
    PrincipalStrains
    """
    if eyy is None and exy is None:
        exx, eyy, exy = _components_of(exx)
    elif eyy is None or exy is None:
        raise ValueError("principal_strains needs all three components exx, eyy, exy (or one object holding them)")
    try:
        a, b, c = (np.asarray(x, dtype=np.float64) for x in (exx, eyy, exy))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"exx, eyy, exy must be numeric arrays: {exc}") from None
    if not (a.shape == b.shape == c.shape):
        raise ValueError(f"exx, eyy, exy must have one shape, got {a.shape}, {b.shape}, {c.shape}")
    mean = 0.5 * (a + b)
    radius = np.hypot(0.5 * (a - b), c)
    e1, e2 = mean + radius, mean - radius
    angle = 0.5 * np.arctan2(2.0 * c, a - b)
    von_mises = 2.0 / math.sqrt(3.0) * np.sqrt(a * a + a * b + b * b + c * c)
    return PrincipalStrains(e1=e1, e2=e2, angle=angle, max_shear=radius, von_mises=von_mises)


# ------------------------------------------------------------------------------------------------
# scale and loading


def _scale_value(scale, what="scale") -> float:
    from kernels.checks import positive_float

    return positive_float(scale, what, detail=" (mm per px)")


def results_scale(results) -> float | None:
    """The mm/px scale a 2-D result stores (settings key :data:`SCALE_KEY`), or None (pixels)."""
    settings = getattr(results, "settings", None) or {}
    value = settings.get(SCALE_KEY)
    return None if value is None else _scale_value(value, f"the stored {SCALE_KEY}")


def load_results(results):
    """A result file (path) read back, or ``results`` itself when already read.

    Returns a :class:`dic.store.TrackResults` (2-D) or a :class:`dic.store.StereoResults`.
    """
    from .store import ResultReader, StereoResults, TrackResults, read_results, read_stereo

    if isinstance(results, (TrackResults, StereoResults)):
        return results
    if isinstance(results, (str, os.PathLike)):
        with ResultReader(results) as r:
            kind = r.kind.name
        return read_results(results) if kind == "dic2d" else read_stereo(results)
    raise ValueError("results must be a result file (path) or what dic.store.read_results / read_stereo return, "
                     f"got {type(results).__name__}")


class _Source:
    """The frames of a 2-D or stereo result, with quantities, validity and positions per frame.

    A result file is read one frame at a time, and of each frame only the datasets a quantity
    needs (``u``, ``v`` and ``valid`` for a 2-D displacement, ``strain/eyy`` and ``strain/valid``
    for a strain ...: :meth:`dic.store.ResultReader.frame_arrays`); the arrays of the last frame
    read are kept. A time series over a 10 000-frame file holds one frame's arrays, whatever the
    file's length. A results object already read (:class:`dic.store.TrackResults`,
    :class:`~dic.store.StereoResults`) is used as it is. Use as a context manager (it closes the file).
    """

    def __init__(self, results, scale=None):
        from .store import ResultFrames, ResultReader, StereoResults, TrackResults

        if not isinstance(results, (str, os.PathLike, TrackResults, StereoResults)):
            raise ValueError("results must be a result file (path) or what dic.store.read_results / read_stereo "
                             f"return, got {type(results).__name__}")
        if isinstance(results, (str, os.PathLike)):
            self._reader, self._frames = ResultReader(results), None
        else:
            self._reader, self._frames = None, ResultFrames(results)
        try:
            if self._reader is not None:
                kind, self.indices, self.settings = self._reader.kind.name, self._reader.done_frames(), self._reader.settings
            else:
                kind, self.indices, self.settings = self._frames.kind, list(self._frames.indices), self._frames.settings
            self.is_2d = kind == "dic2d"
            if self.is_2d:
                self.scale = _scale_value(scale) if scale is not None else results_scale(self)
                self.length_unit = "mm" if self.scale is not None else "px"
            else:
                if scale is not None:
                    raise ValueError("a scale applies to 2-D results only; stereo results are in mm already")
                self.scale = None
                self.length_unit = "mm"
            if not self.indices:
                raise ValueError("the results hold no finished frame")
        except BaseException:
            self.close()
            raise
        self._cells: dict = {}  # "px" / "mm" -> the cells of the points (dic.gridinterp)
        self._located: dict = {}  # (units, query bytes) -> where the queries fall in those cells
        self._held: tuple[int, dict] | None = None  # (index, {dataset: array}): the arrays of one frame

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        for source in (self._reader, self._frames):
            if source is not None:
                source.close()
        self._held = None
        self._cells, self._located = {}, {}

    def strain_type(self, quantity: str) -> str | None:
        """The strain type behind ``quantity`` (``exx``..., the principal and von Mises strains: the file's
        type, :func:`dic._strain.stored_strain_type`; 2-D ``Exx``...: Green-Lagrange), None for others."""
        from ._strain import stored_strain_type

        if self.is_2d and quantity in ("Exx", "Eyy", "Exy"):
            return "green-lagrange"
        if quantity not in ("exx", "eyy", "exy") + _DERIVED:
            return None
        first = None
        if self.settings.get("strain_type") is None:  # a file that records it per frame only (or not at all)
            first = self._reader.read_frame(self.indices[0]) if self._reader is not None else \
                self._frames.read(self.indices[0])
        return stored_strain_type("dic2d" if self.is_2d else "stereo", self.settings, first)

    def arrays(self, index: int, names) -> dict:
        """Datasets ``names`` of frame ``index`` (``"u"``, ``"strain/exx"``, ``"status"`` ...) by name;
        a name the frame lacks is absent from the result. Read from the file unless held already."""
        if self._held is None or self._held[0] != index:
            self._held = (index, {})
        held = self._held[1]
        wanted = [n for n in names if n not in held]
        if wanted:
            if self._reader is not None:
                got = self._reader.frame_arrays(index, wanted)
                if got is None:  # one of them is missing: read those present
                    got = [(self._reader.frame_arrays(index, [n]) or (None,))[0] for n in wanted]
                for n, a in zip(wanted, got):
                    # a finished frame always has its displacements and statuses; strain may be absent
                    if a is None and not n.startswith("strain/") and self._reader.is_done(index):
                        raise self._reader._damaged(index, f"has no {n!r} dataset")
                held.update((n, a) for n, a in zip(wanted, got) if a is not None)
            else:
                held.update(_object_arrays(self._frames.read(index), wanted))
        return {n: held[n] for n in names if n in held}

    @property
    def kind(self) -> str:
        return "2-D" if self.is_2d else "stereo"

    def names(self) -> tuple[str, ...]:
        if self.is_2d:
            return _Q2D_DISP + _Q2D_STRAIN + ("zncc",)
        return _Q3D_DISP + _Q3D_STRAIN + _Q3D_OTHER

    def unit(self, name: str) -> str:
        if name == "angle":
            return "rad"
        if name in ("u", "v", "magnitude", "U", "V", "W", "X", "Y", "Z"):
            return self.length_unit
        return ""

    def select(self, frames) -> list[int]:
        available = list(self.indices)
        if frames is None:
            return available
        if isinstance(frames, (int, np.integer)) and not isinstance(frames, bool):
            frames = [frames]
        try:
            wanted = [int(f) for f in frames]
        except (TypeError, ValueError):
            raise ValueError(f"frames must be frame indices, got {frames!r}") from None
        known = set(self.indices)
        missing = [f for f in wanted if f not in known]
        if missing:
            raise ValueError(f"no finished frame {', '.join(map(str, missing))} in the results; "
                             f"available: {available}")
        if not wanted:
            raise ValueError("frames is empty")
        return wanted

    def check_at(self, at: str) -> str:
        if at not in ("px", "mm"):
            raise ValueError(f"at must be 'px' (reference image pixels) or 'mm', got {at!r}")
        if at == "mm" and self.is_2d and self.scale is None:
            raise ValueError("positions in mm need a scale: pass scale= (mm per px; --scale) or store one with "
                             "specula track --scale / recompute_strain(scale=)")
        return at

    def check_quantity(self, name: str) -> str:
        if name not in self.names():
            raise ValueError(f"unknown quantity {name!r} for {self.kind} results; choose one of "
                             f"{', '.join(self.names())}")
        return name

    # -- per frame
    def values(self, index: int, name: str):
        """(values (N,), valid (N,)) of a quantity in frame ``index`` (displacements scaled)."""
        if self.is_2d:
            s = self.scale or 1.0
            if name in _Q2D_DISP or name == "zncc":
                needed = ("u", "v") if name in _Q2D_DISP else ("zncc",)
                a = self.arrays(index, needed + ("valid",))
                if name == "zncc" and "zncc" not in a:
                    raise ValueError(f"frame {index} has no zncc")
                if name in _Q2D_DISP:
                    u, v = np.asarray(a["u"], np.float64) * s, np.asarray(a["v"], np.float64) * s
                    vals = {"u": u, "v": v}.get(name)
                    vals = np.hypot(u, v) if vals is None else vals
                else:
                    vals = np.asarray(a["zncc"], np.float64)
                valid = np.asarray(a["valid"], bool) if "valid" in a else np.ones(vals.shape[0], bool)
            else:
                comps = ("exx", "eyy", "exy") if name in _DERIVED else (name,)
                a = self.arrays(index, ["strain/valid"] + [f"strain/{c}" for c in comps])
                if len(a) != len(comps) + 1:
                    raise ValueError(f"frame {index} has no strain; recompute it with `specula strain` "
                                     "(dic.postprocess.recompute_strain)")
                valid = np.asarray(a["strain/valid"], bool)
                if name in _DERIVED:
                    vals = getattr(principal_strains(*(a[f"strain/{c}"] for c in comps)), name)
                else:
                    vals = np.asarray(a[f"strain/{name}"], np.float64)
        else:
            if name in _Q3D_STRAIN:
                comps = ("exx", "eyy", "exy") if name in _DERIVED else (name,)
                a = self.arrays(index, ("strain_valid",) + comps)
                valid = np.asarray(a["strain_valid"], bool)
                vals = getattr(principal_strains(*(a[c] for c in comps)), name) if name in _DERIVED else a[name]
            else:
                comps = ("U", "V", "W") if name == "magnitude" else (name,)
                a = self.arrays(index, ("status",) + comps)
                valid = self._stereo_valid(a["status"])
                vals = np.sqrt(sum(np.asarray(a[c], np.float64) ** 2 for c in comps)) if name == "magnitude" else a[name]
        vals = np.asarray(vals, np.float64)
        return vals, valid & np.isfinite(vals)

    @staticmethod
    def _stereo_valid(status) -> np.ndarray:
        from .field3d import StereoStatus

        return np.asarray(status) == StereoStatus.OK

    def stereo_positions(self, index: int):
        """Stereo: the (N, 3) reference positions and (N, 3) displacements (mm) and their validity (N,)."""
        a = self.arrays(index, ("status", "X", "Y", "Z", "U", "V", "W"))
        xyz = np.column_stack([a["X"], a["Y"], a["Z"]]).astype(np.float64)
        uvw = np.column_stack([a["U"], a["V"], a["W"]]).astype(np.float64)
        valid = self._stereo_valid(a["status"]) & np.all(np.isfinite(xyz), 1) & np.all(np.isfinite(uvw), 1)
        return xyz, uvw, valid

    def domain(self, index: int, at: str) -> np.ndarray:
        """(N, 2) positions of the points in the units of ``at`` (where queries are given)."""
        pts = np.asarray(self.arrays(index, ("points",))["points"], np.float64)
        if at == "px":
            return pts
        if self.is_2d:
            return pts * self.scale
        a = self.arrays(index, ("X", "Y"))
        return np.column_stack([a["X"], a["Y"]]).astype(np.float64)

    def cells(self, index: int, at: str):
        """The cells of frame ``index``'s points in the units of ``at`` (:mod:`dic.gridinterp`).

        2-D (either unit) and stereo px: :class:`~dic.gridinterp.GridCells` of the points (px), or the
        scattered-points fallback when they are on no grid; stereo mm: the grid's cells over the
        points' ``(X, Y)`` (:meth:`~dic.gridinterp.TriangleCells.from_grid`). Every frame of a file
        has the same points, so the cells are built once (and again only if a frame's differ).
        """
        from .gridinterp import GridCells, TriangleCells, cells_for

        pts = self.domain(index, "px")
        grid = self._cells.get("px")
        if grid is None or not grid.matches(pts):
            # 2-D runs with declared cracks (settings "cracks", reference px): no cell across one (dic.cracks)
            grid = cells_for(pts, cracks=(self.settings or {}).get("cracks") if self.is_2d else None)
            self._cells = {"px": grid}
            self._located = {}
        if at == "px" or self.is_2d:
            return grid
        xy = self.domain(index, "mm")
        cells = self._cells.get("mm")
        if cells is None or not cells.matches(xy):
            cells = TriangleCells.from_grid(grid, xy) if isinstance(grid, GridCells) else TriangleCells.scattered(xy)
            self._cells["mm"] = cells
            self._located = {k: v for k, v in self._located.items() if k[0] != "mm"}
        return cells

    def interpolate(self, index: int, at: str, values, valid, query) -> tuple[np.ndarray, np.ndarray]:
        """``values`` (N, k) of frame ``index`` at the reference positions ``query`` (M, 2), units ``at``.

        Interpolated in the grid cell containing each query, from its corners only, when they are
        valid (:mod:`dic.gridinterp`). Returns the (M, k) values (NaN where there is none) and the
        (M,) :class:`~dic.gridinterp.QueryStatus` codes saying why.
        """
        query = np.asarray(query, np.float64).reshape(-1, 2)
        if self.is_2d and at == "mm":
            query = query / self.scale  # 2-D mm positions are px times the scale
            at = "px"
        cells = self.cells(index, at)
        key = ("px" if at == "px" or self.is_2d else "mm", query.tobytes())
        located = self._located.get(key)
        if located is None:
            located = self._located[key] = cells.locate(query)
        return located.evaluate(values, valid, present=self.present(index))

    def present(self, index: int) -> np.ndarray | None:
        """Stereo: the points that were computed at all (status not NOT_COMPUTED: inside the region, a
        reference subset with texture inside the image); a cell with a corner that was not counts as
        no points (a hole, an excluded region). 2-D: None (a region drops the points outside it, and
        NOT_COMPUTED there may be a frame's failed guess)."""
        if self.is_2d:
            return None
        from .field3d import StereoStatus

        return np.asarray(self.arrays(index, ("status",))["status"]) != StereoStatus.NOT_COMPUTED

    def check_inside(self, query, at: str, what: str, every: bool = True) -> None:
        """Refuse (``ValueError`` with the extent) query positions (M, 2) outside the measured points of the
        first frame (their bounding box, widened by one grid spacing): every one of them (``every``), or all of
        them. Values there would be NaN in every frame."""
        dom = self.domain(self.indices[0], at)
        dom = dom[np.all(np.isfinite(dom), axis=1)]
        if dom.shape[0] == 0:
            return
        pad = self.grid_spacing(at)
        lo, hi = dom.min(axis=0) - pad, dom.max(axis=0) + pad
        q = np.asarray(query, np.float64).reshape(-1, 2)
        inside = np.all((q >= lo) & (q <= hi), axis=1)
        if (not inside.all()) if every else (not inside.any()):
            where = f"({q[0, 0]:g}, {q[0, 1]:g})" if q.shape[0] == 1 else \
                f"from ({q[0, 0]:g}, {q[0, 1]:g}) to ({q[-1, 0]:g}, {q[-1, 1]:g})"
            raise ValueError(f"{what} {where} {at} lies outside the measured points (x {lo[0] + pad:g} to "
                             f"{hi[0] - pad:g}, y {lo[1] + pad:g} to {hi[1] - pad:g} {at}); its values would be "
                             "NaN in every frame")

    def grid_spacing(self, at: str) -> float:
        """Spacing of the points (in ``at`` units): the grid step (the smaller one), else the median
        nearest-neighbour distance."""
        from .gridinterp import GridCells

        grid = self.cells(self.indices[0], "px")
        if isinstance(grid, GridCells) and (at == "px" or self.is_2d) and grid.points.shape[0] > 1:
            # the step along each axis with more than one node
            steps = [d for d, n in zip(grid.step, (grid.shape[1], grid.shape[0])) if n > 1]
            return min(steps) * (self.scale if at == "mm" else 1.0)
        from scipy.spatial import cKDTree  # here: scipy.spatial takes 0.3-1 s to import, and the grid needs none

        dom = self.domain(self.indices[0], at)
        dom = dom[np.all(np.isfinite(dom), axis=1)]
        if dom.shape[0] < 2:
            return 1.0
        d, _ = cKDTree(dom).query(dom, k=2)
        return float(np.median(d[:, 1])) or 1.0


#: the most samples of a line profile (a line across a 16384-px image at several samples per px)
MAX_PROFILE_SAMPLES = 100_000


def _object_arrays(frame, names) -> dict:
    """Datasets ``names`` of a frame object read already (a :class:`dic.store.FrameResult` or a
    :class:`dic.field3d.Field3D`), by their names in the file; missing ones are left out."""
    out = {}
    for name in names:
        if name.startswith("strain/"):
            strain = getattr(frame, "strain", None)
            value = None if strain is None else strain.get(name[len("strain/"):])
        else:
            value = getattr(frame, name, None)
        if value is not None:
            out[name] = np.asarray(value)
    return out


def quantities(results) -> tuple[str, ...]:
    """Names of the quantities :func:`point_history` and :func:`line_profile` accept for ``results``."""
    with _Source(results) as src:
        return src.names()


def _xy(value, what: str) -> np.ndarray:
    try:
        p = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a point (x, y), got {value!r}") from None
    if p.shape != (2,) or not np.all(np.isfinite(p)):
        raise ValueError(f"{what} must be a finite point (x, y), got {value!r}")
    return p


# ------------------------------------------------------------------------------------------------
# strain with another window


def window_points(window, step, unit: str = "grid") -> int:
    """The strain fit window in grid points for a window given in grid points or in px.

    ``unit="grid"``: ``window`` is the number of grid points per side (odd, >= 3), returned as is.
    ``unit="px"``: ``window`` is a side length in px; the window is the largest odd number of grid
    points ``n`` whose span ``(n - 1) · step`` does not exceed it (at least 3: a window narrower
    than two grid steps is refused). ``step`` is the grid spacing in px (a number, or the
    ``(dx, dy)`` of :func:`dic.grid_layout`, which must then be equal).
    """
    from kernels.checks import odd_int

    if unit == "grid":
        return odd_int(window, "window", detail=" (grid points per side)")
    if unit != "px":
        raise ValueError(f"unit must be 'grid' (grid points) or 'px', got {unit!r}")
    steps = np.atleast_1d(np.asarray(step, dtype=np.float64))
    if steps.size not in (1, 2) or not np.all(np.isfinite(steps) & (steps > 0)):
        raise ValueError(f"step must be a positive grid spacing in px, got {step!r}")
    if steps.size == 2 and abs(steps[0] - steps[1]) > 1e-9 * steps.max():
        raise ValueError(f"a window in px needs equal grid steps along x and y, got {steps[0]:g} and {steps[1]:g} px; "
                         "give the window in grid points")
    d = float(steps[0])
    try:
        w = float(window)
    except (TypeError, ValueError):
        raise ValueError(f"window must be a length in px, got {window!r}") from None
    if not (math.isfinite(w) and w > 0):
        raise ValueError(f"window must be a positive length in px, got {window!r}")
    n = 2 * int(math.floor(w / (2 * d) + 1e-9)) + 1
    if n < 3:
        raise ValueError(f"a strain window of {w:g} px spans fewer than 3 grid points at a step of {d:g} px; "
                         f"give at least {2 * d:g} px")
    return n


def recompute_strain(results, output=None, *, window, unit: str = "grid", min_points: int | None = None,
                     scale=None, strain_type: str | None = None) -> Path:
    """Recompute the strain of a result file (2-D or stereo) with another fit window or strain type.

    Parameters
    ----------
    results : path of a result file (``specula track`` or ``specula stereo``)
    output : path, optional
        The new ``.h5`` file (overwritten if it exists). None: replace ``results`` in place (a new
        file is written next to it and renamed over it only when complete).
    window : int or float
        The fit window: grid points per side (``unit="grid"``) or its side in px (``unit="px"``,
        see :func:`window_points`; the grid of the (left) reference image's points).
    min_points : int, optional
        Fewest valid points per fit: 2-D, :func:`dic.strain`'s ``min_points`` (default a quarter
        window); stereo, :class:`dic.field3d.SurfaceStrainPlan`'s ``min_neighbours`` (default 6, as
        the run).
    scale : float, optional
        2-D: also store this mm/px scale (settings key :data:`SCALE_KEY`); None keeps the stored one.
    strain_type : "green-lagrange" | "small" | "euler-almansi", optional
        What ``exx``, ``eyy``, ``exy`` are; None keeps the file's (:func:`dic._strain.stored_strain_type`:
        a file written before strain types holds 2-D small strain, stereo Green-Lagrange).

    Everything but the strain is copied unchanged (points, displacements, parameters, statuses,
    frame attributes; stereo: the rig, the reference match, shapes and normals' positions); the
    settings record the new ``strain_window`` (grid points) and ``strain_type``. The strain is
    computed exactly as the run computes it (2-D: one :class:`dic.StrainPlan` for the file, whose
    frames share their points; stereo: one :class:`dic.field3d.SurfaceStrainPlan` per reference
    shape, with the left camera centre of the state's frame), so a recomputation with a run's
    window and type gives that run's strain bit for bit. Returns the path written. Frames are
    read, strained and written one at a time (memory independent of the number of frames).

    The output's lock is held throughout (:func:`dic.store.files.output_lock`, the one protocol of
    every writer): an output, or a ``results`` file, that another process is writing (a running
    ``specula track``) is refused with :class:`dic.store.ResultFileInUse` and left untouched.
    """
    from ._strain import check_strain_type, grid_layout, stored_strain_type
    from .store import ResultReader, ResultWriter, files
    from .store.layout import role_attr

    if not isinstance(results, (str, os.PathLike)):
        raise ValueError(f"results must be the path of a result file, got {type(results).__name__}")
    if strain_type is not None:
        strain_type = check_strain_type(strain_type)
    src = Path(os.fspath(results))
    dst = Path(os.fspath(output)) if output is not None else src
    if dst.suffix.lower() not in (".h5", ".hdf5"):
        raise ValueError(f"the output must be an HDF5 file ending in .h5, got {dst.name}")
    files.check_output_path(dst)
    tmp = None
    with files.output_lock(dst, "result file"), ResultReader(src) as r:  # read, strained and written one frame at a time
        kind = r.kind.name
        if kind not in ("dic2d", "stereo"):
            raise ValueError(f"{src} is a {r.kind.label} result file; the strain of 2-D and stereo results can be "
                             "recomputed")
        if kind == "stereo" and scale is not None:
            raise ValueError("a stereo result file is in mm already; a scale (mm per px) is for 2-D results")
        indices = r.done_frames()
        if not indices:
            raise ValueError(f"{src} holds no finished frame")
        settings = dict(r.settings)
        first = r.read_frame(indices[0])
        kind_type = strain_type if strain_type is not None else stored_strain_type(kind, settings, first)
        # the grid step only for a window in px (a stereo run given scattered points has no grid)
        n = window_points(window, grid_layout(first.points)[2] if unit == "px" else None, unit)
        settings["strain_window"] = n
        settings["strain_type"] = kind_type
        if scale is not None:
            settings[SCALE_KEY] = _scale_value(scale)
        ref = r.reference
        strain_of = _strain_2d(first.points, n, min_points, kind_type) if kind == "dic2d" else \
            _strain_3d(first, n, min_points, kind_type)
        del first
        roles = r.kind.image_roles
        extra = {}
        if kind == "stereo":
            extra = {"kind": "stereo", "rig": r.rig}
        try:
            fd, tmp = tempfile.mkstemp(suffix=".h5", prefix=f".{dst.stem}.", dir=dst.parent)
            os.close(fd)
            ref_paths = tuple(ref.get(role_attr(x, "path"), "") for x in roles)
            ref_digests = tuple(ref.get(role_attr(x, "sha256"), "") for x in roles)
            one = len(roles) == 1
            with ResultWriter(tmp, reference_path=ref_paths[0] if one else ref_paths,
                              reference_shape=ref.get("shape") or None,
                              reference_sha256=ref_digests[0] if one else ref_digests, settings=settings,
                              mode="overwrite", compression=r.compression, **extra) as w:
                if kind == "stereo":
                    match = r.read_match()
                    if match is not None:
                        w.write_match(match)
                for i, f in r.iter_frames(indices):
                    # the frame's attributes as they were, less those the writer sets and the strain's own
                    attrs = {k: v for k, v in r.frame_attrs(i).items() if k not in ("complete", "written", "strain_type")}
                    field, strain = strain_of(f)
                    w.write_frame(i, field, strain=strain, path=r.frame_paths(i)[0] if one else r.frame_paths(i),
                                  attrs=attrs)
            r.close()  # before the new file replaces it (in place)
            os.replace(tmp, dst)
            files.fsync_folder(dst.parent)
        except files.ResultWriteError:
            raise
        except OSError as exc:
            raise ValueError(f"cannot write {dst}: {exc.strerror or exc}") from None
        finally:
            if tmp is not None and os.path.exists(tmp):
                os.unlink(tmp)
    return dst


def _strain_2d(points, window: int, min_points, strain_type: str):
    """``frame -> (frame, StrainField)`` of a 2-D file: one :class:`dic.StrainPlan` for the file (a
    frame on other points, which no run writes, gets a plan of its own)."""
    from ._strain import StrainPlan

    plan = StrainPlan(points, window=window, min_points=min_points, strain_type=strain_type)

    def strain_of(frame):
        own = plan if plan.matches(frame.points) else StrainPlan(frame.points, window=window, min_points=min_points,
                                                                 strain_type=strain_type)
        return frame, own.strain(frame)

    return strain_of


def _strain_3d(first, window: int, min_points, strain_type: str):
    """``state -> (Field3D with the new strain, None)`` of a stereo file: the run's computation
    (:meth:`dic.StereoCorrelation.measure`): a :class:`dic.field3d.SurfaceStrainPlan` of the state's reference
    positions ``X, Y, Z`` (kept while they stay the same, as the run keeps it), the left camera centre
    ``t_frame_left`` of the state's frame, the displacements of the valid points (status OK); points given
    to the run (no grid): :func:`dic.field3d.surface_strain` over the ``window²`` nearest points within
    ``window`` typical spacings, as the run."""
    from dataclasses import replace

    from .field3d import SurfaceStrainPlan, check_grid_window, scattered_neighbours, surface_strain

    min_neighbours = 6 if min_points is None else int(min_points)
    neighbours = None
    if first.grid_shape is None:  # a run given points: the window² nearest within window spacings, as the run
        from .correlation.points import typical_spacing

        points = np.asarray(first.points, np.float64)
        neighbours = scattered_neighbours(points, window ** 2, max_distance=window * typical_spacing(points))
    else:
        check_grid_window(window, first.grid_shape)
    held = [None]

    def strain_of(state):
        X = np.stack([state.X, state.Y, state.Z], axis=1)
        t = np.asarray(state.t_frame_left, np.float64)
        if neighbours is not None:
            s = surface_strain(X, np.nan_to_num(np.stack([state.U, state.V, state.W], axis=1)),
                               np.asarray(state.status) == 0, neighbours, camera_center=t,
                               min_neighbours=min_neighbours, strain_type=strain_type)
            return replace(state, exx=s["exx"], eyy=s["eyy"], exy=s["exy"], normal=s["normal"],
                           strain_valid=s["strain_valid"], strain_type=strain_type), None
        plan = held[0]
        if plan is None or not (np.array_equal(plan.X, X, equal_nan=True) and np.array_equal(plan.camera_center, t)):
            plan = held[0] = SurfaceStrainPlan(X, state.grid_shape, window, camera_center=t,
                                               min_neighbours=min_neighbours, strain_type=strain_type)
        uvw = np.stack([state.U, state.V, state.W], axis=1)
        valid = np.asarray(state.status) == 0  # StereoStatus.OK: the points the run strained
        s = plan(np.nan_to_num(uvw), valid)
        return replace(state, exx=s["exx"], eyy=s["eyy"], exy=s["exy"], normal=s["normal"],
                       strain_valid=s["strain_valid"], strain_type=strain_type), None

    return strain_of


# ------------------------------------------------------------------------------------------------
# extensometers, histories, profiles


@dataclass
class Extensometer:
    """A virtual extensometer over the frames of a result (:func:`extensometer`).

    ``start``, ``end`` the gauge ends as given (reference positions, units ``at``); ``unit`` the
    length unit of the lengths ("px", or "mm" for scaled 2-D and stereo results). Per frame
    (arrays of length F, aligned with ``frames``): ``length0`` the reference gauge length,
    ``length`` the deformed one, ``elongation = length - length0``, ``strain = elongation /
    length0`` (engineering), ``start_displacement`` / ``end_displacement`` (F, 2 | 3) the
    displacement of each end, ``valid`` both ends have a value (lengths NaN otherwise), and
    ``start_status`` / ``end_status`` (F,) int8 the :class:`~dic.gridinterp.QueryStatus` of each
    end in each frame (why an end has no value: ``QueryStatus(code).reason``).
    """

    start: np.ndarray
    end: np.ndarray
    at: str
    unit: str
    frames: np.ndarray
    length0: np.ndarray
    length: np.ndarray
    elongation: np.ndarray
    strain: np.ndarray
    start_displacement: np.ndarray
    end_displacement: np.ndarray
    valid: np.ndarray
    start_status: np.ndarray
    end_status: np.ndarray

    def table(self) -> tuple[list[str], np.ndarray]:
        """Column names and an (F, k) table (frame, length0, length, elongation, strain, end displacements)."""
        d = self.start_displacement.shape[1]
        comps = "uv" if d == 2 else "UVW"
        names = ["frame", f"length0_{self.unit}", f"length_{self.unit}", f"elongation_{self.unit}", "strain"]
        names += [f"start_{c}_{self.unit}" for c in comps] + [f"end_{c}_{self.unit}" for c in comps]
        cols = [self.frames.astype(np.float64), self.length0, self.length, self.elongation, self.strain]
        cols += list(self.start_displacement.T) + list(self.end_displacement.T)
        return names, np.column_stack(cols)


def extensometer(results, start, end, *, at: str = "px", frames=None, scale=None) -> Extensometer:
    """A virtual extensometer between two reference points, over the frames of a result.

    Parameters
    ----------
    results : a result file (2-D or stereo) or what :func:`dic.store.read_results` /
        :func:`dic.store.read_stereo` return.
    start, end : (x, y)
        The gauge ends in the reference state: reference image px (``at="px"``; stereo: the left
        reference image), or mm (``at="mm"``; 2-D: px times the scale; stereo: the ``(X, Y)``
        coordinates of the result's frame, best with ``frame="plane"``).
    frames : frame indices, optional (default: every finished frame)
    scale : float, optional
        mm/px of a 2-D result (default: the stored one, else px).

    The displacement at each end is interpolated in its grid cell (module docstring; NaN, with
    ``start_status`` / ``end_status`` saying why, when the cell is not entirely valid); the
    gauge length is the distance between the ends (2-D in the image plane; stereo in 3-D).
    """
    with _Source(results, scale) as src:
        at = src.check_at(at)
        a, b = _xy(start, "start"), _xy(end, "end")
        if np.allclose(a, b):
            raise ValueError(f"the gauge ends coincide ({a[0]:g}, {a[1]:g}); give two distinct points")
        idx = src.select(frames)
        dim = 2 if src.is_2d else 3
        F = len(idx)
        L0, L = np.full(F, np.nan), np.full(F, np.nan)
        dA, dB = np.full((F, dim), np.nan), np.full((F, dim), np.nan)
        status = np.zeros((F, 2), np.int8)
        q = np.stack([a, b])
        for k, i in enumerate(idx):
            if src.is_2d:
                u, valid_u = src.values(i, "u")
                v, valid_v = src.values(i, "v")
                s = src.scale or 1.0
                q_px = q / s if at == "mm" else q
                disp, status[k] = src.interpolate(i, "px", np.column_stack([u, v]), valid_u & valid_v, q_px)
                ref = q_px * s
            else:
                xyz, uvw, valid = src.stereo_positions(i)
                both, status[k] = src.interpolate(i, at, np.column_stack([xyz, uvw]), valid, q)
                ref, disp = both[:, :3], both[:, 3:]
            dA[k], dB[k] = disp[0], disp[1]
            L0[k] = np.linalg.norm(ref[1] - ref[0])
            L[k] = np.linalg.norm(ref[1] + disp[1] - ref[0] - disp[0])
        ok = np.isfinite(L) & np.isfinite(L0) & np.all(status == QueryStatus.OK, axis=1)
        L[~ok] = np.nan
        elong = L - L0
        with np.errstate(invalid="ignore", divide="ignore"):
            eps = elong / L0
        return Extensometer(start=a, end=b, at=at, unit=src.length_unit, frames=np.asarray(idx, np.int64), length0=L0,
                            length=L, elongation=elong, strain=eps, start_displacement=dA, end_displacement=dB, valid=ok,
                            start_status=status[:, 0], end_status=status[:, 1])


@dataclass
class History:
    """A quantity at one reference point over the frames (:func:`point_history`).

    ``values`` (F,) aligned with ``frames``; NaN where the point has no value in a frame, and
    ``status`` (F,) int8 the :class:`~dic.gridinterp.QueryStatus` saying why
    (``QueryStatus(code).reason``: outside the grid, in a hole or an excluded region, among
    invalid points).
    """

    quantity: str
    unit: str
    point: np.ndarray
    at: str
    frames: np.ndarray
    values: np.ndarray
    status: np.ndarray
    #: the strain type of a strain quantity ("green-lagrange", "small", "euler-almansi"), else None
    strain_type: str | None = None

    def table(self) -> tuple[list[str], np.ndarray]:
        """Column names and the (F, 2) table (frame, value)."""
        name = self.quantity + (f"_{self.unit}" if self.unit else "")
        return ["frame", name], np.column_stack([self.frames.astype(np.float64), self.values])


def point_history(results, point, quantity: str, *, at: str = "px", frames=None, scale=None) -> History:
    """A quantity at one reference point over the frames of a result.

    ``point`` (x, y) in reference image px (``at="px"``) or mm (``at="mm"``, see :func:`extensometer`);
    ``quantity`` one of :func:`quantities` (2-D: u, v, magnitude, the strain components, e1, e2,
    angle, max_shear, von_mises, zncc; stereo: U, V, W, magnitude, X, Y, Z, exx, eyy, exy, e1 ...).
    Values are interpolated in the grid cell that contains the point, from its corners when they are
    valid (strain: strain-valid); else NaN with ``status`` saying why (module docstring).
    """
    with _Source(results, scale) as src:
        at = src.check_at(at)
        quantity = src.check_quantity(quantity)
        p = _xy(point, "point")
        src.check_inside(p[None, :], at, "the point")
        idx = src.select(frames)
        out = np.full(len(idx), np.nan)
        status = np.zeros(len(idx), np.int8)
        for k, i in enumerate(idx):
            vals, valid = src.values(i, quantity)
            value, code = src.interpolate(i, at, vals, valid, p)
            out[k], status[k] = value[0, 0], code[0]
        return History(quantity=quantity, unit=src.unit(quantity), point=p, at=at, frames=np.asarray(idx, np.int64),
                       values=out, status=status, strain_type=src.strain_type(quantity))


@dataclass
class Profile:
    """A quantity along a line, per frame (:func:`line_profile`).

    ``positions`` (n, 2) the sample points (units ``at``), ``distance`` (n,) their distance from
    ``start`` (units ``at``), ``values`` (F, n): row ``k`` is frame ``frames[k]``, NaN where a
    sample has no value, and ``status`` (F, n) int8 the :class:`~dic.gridinterp.QueryStatus` of
    each sample saying why.
    """

    quantity: str
    unit: str
    start: np.ndarray
    end: np.ndarray
    at: str
    positions: np.ndarray
    distance: np.ndarray
    frames: np.ndarray
    values: np.ndarray
    status: np.ndarray
    #: the strain type of a strain quantity ("green-lagrange", "small", "euler-almansi"), else None
    strain_type: str | None = None

    def table(self) -> tuple[list[str], np.ndarray]:
        """Long-format column names and table: one row per (frame, sample): frame, distance, x, y, value."""
        name = self.quantity + (f"_{self.unit}" if self.unit else "")
        F, n = self.values.shape
        cols = [np.repeat(self.frames.astype(np.float64), n), np.tile(self.distance, F),
                np.tile(self.positions[:, 0], F), np.tile(self.positions[:, 1], F), self.values.reshape(-1)]
        return ["frame", f"distance_{self.at}", f"x_{self.at}", f"y_{self.at}", name], np.column_stack(cols)


def line_profile(results, start, end, quantity: str, *, samples: int | None = None, at: str = "px", frames=None,
                 scale=None) -> Profile:
    """A quantity along the segment ``start`` -> ``end`` (reference positions), per frame.

    ``samples`` points evenly spaced from ``start`` to ``end`` (default: about one per grid step,
    at least 2); the rest as :func:`point_history`.
    """
    from kernels.checks import positive_int

    with _Source(results, scale) as src:
        at = src.check_at(at)
        quantity = src.check_quantity(quantity)
        a, b = _xy(start, "start"), _xy(end, "end")
        length = float(np.hypot(*(b - a)))
        if length == 0:
            raise ValueError(f"the line's ends coincide ({a[0]:g}, {a[1]:g}); give two distinct points")
        if samples is None:
            needed = length / src.grid_spacing(at) + 1
            if not needed <= MAX_PROFILE_SAMPLES:
                raise ValueError(f"the line from ({a[0]:g}, {a[1]:g}) to ({b[0]:g}, {b[1]:g}) {at} would need {needed:.3g} "
                                 f"samples at one per grid step, more than {MAX_PROFILE_SAMPLES:,}; give a shorter line "
                                 "(inside the measured points) or fewer samples")
            samples = max(2, int(round(needed)))
        samples = positive_int(samples, "samples", minimum=2)
        if samples > MAX_PROFILE_SAMPLES:
            raise ValueError(f"samples must be at most {MAX_PROFILE_SAMPLES:,} (a line across the largest image at "
                             f"several samples per px), got {samples:,}")
        t = np.linspace(0.0, 1.0, samples)
        pos = a[None, :] + t[:, None] * (b - a)[None, :]
        src.check_inside(pos, at, "the line", every=False)
        idx = src.select(frames)
        vals = np.full((len(idx), samples), np.nan)
        status = np.zeros((len(idx), samples), np.int8)
        for k, i in enumerate(idx):
            v, valid = src.values(i, quantity)
            value, status[k] = src.interpolate(i, at, v, valid, pos)
            vals[k] = value[:, 0]
        return Profile(quantity=quantity, unit=src.unit(quantity), start=a, end=b, at=at, positions=pos,
                       distance=t * length, frames=np.asarray(idx, np.int64), values=vals, status=status,
                       strain_type=src.strain_type(quantity))


# -- crack26: opening and sliding of declared cracks (dic.cracks) in a 2-D result file
def results_crack_opening(results, frame: int | None = None, *, cracks=None, spacing: float | None = None,
                          radius: float | None = None, min_points: int = 6, gap: float | None = None) -> list:
    """:func:`dic.cracks.crack_opening` of every crack of a 2-D result file's frame.

    Parameters
    ----------
    results : str or Path
        A 2-D result file (``specula track`` / :func:`dic.sequence.track_sequence`).
    frame : int, optional
        The frame (default: the last finished one).
    cracks : optional
        The cracks to measure (any form :func:`dic.cracks.as_cracks` takes). Default: those the run declared
        (its settings' ``cracks``); a file without any needs them given.
    spacing, radius, min_points, gap :
        As for :func:`dic.cracks.crack_opening` (defaults from the run's ``step`` and ``subset`` in the file's settings).

    Returns
    -------
    list of dic.cracks.CrackOpening, one per crack, in order.
    """
    from .cracks import as_cracks, crack_opening
    from .store import ResultReader

    with ResultReader(results) as reader:
        if reader.kind.name != "dic2d":
            raise ValueError(f"{results} holds {reader.kind.label} results; crack opening is measured on 2-D results "
                             "(declared cracks are reference-image px)")
        settings = reader.settings or {}
        done = reader.done_frames()
        if not done:
            raise ValueError(f"{results} has no finished frame")
        index = done[-1] if frame is None else frame
        field = reader.read_frame(index)
    measured = as_cracks(cracks if cracks is not None else settings.get("cracks"))
    if not measured:
        raise ValueError(f"{results} declares no crack (its run had no --crack); give the crack to measure")
    def recorded(name):
        value = settings.get(name)
        return value if isinstance(value, int) and not isinstance(value, bool) and value > 0 else None

    if spacing is None:
        spacing = recorded("step")
    return [crack_opening(field, c, spacing=spacing, radius=radius, min_points=min_points, subset=recorded("subset"),
                          gap=gap) for c in measured]
