"""Leave-p-out stability of a calibration: re-solve with p views left out, over many subsets, and
report how far each parameter moves.

A calibration whose parameters move by more than their reported σ when one view is left out depends
on that view: a view with corrupted detections, a missing orientation, too few views. The test
re-solves the intrinsics (:func:`intrinsics_stability`) or the stereo rig (:func:`rig_stability`, or
any rig solver through :func:`leave_p_out`) for every subset of ``p`` views left out when there are
at most ``max_subsets`` of them, otherwise for ``max_subsets`` distinct random subsets drawn with
``seed`` (repeatable). Per parameter it reports the standard deviation of the re-solved values
(``std``, ddof 1) and the largest deviation from the solve with every view (``max_deviation``), with
the subset that gave it. Units: px for ``fx fy cx cy``, none for distortion terms, deg for rotations,
mm for translations (docs/conventions.md).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from .camera import Camera, vector_from_rotation
from .intrinsics import STD_NAMES, calibrate_intrinsics

__all__ = ["StabilityResult", "leave_p_out_subsets", "leave_p_out", "intrinsics_stability", "rig_stability",
           "intrinsic_parameters", "rig_parameters"]

#: Default number of subsets above which random subsets replace the full enumeration.
MAX_SUBSETS = 50


@dataclass
class StabilityResult:
    """Result of a leave-p-out test.

    ``names``/``units`` (P,) the parameters; ``reference`` (P,) their values with every view;
    ``samples`` (S, P) their values in each re-solve; ``left_out`` the S subsets of view indices left
    out; ``exhaustive`` whether every subset of ``p`` views was tried; ``failed`` ``(subset, reason)``
    for re-solves that raised ``ValueError`` (e.g. the views left could not determine the intrinsics);
    ``view_names`` (optional) names the views in the report.
    """

    names: tuple
    units: tuple
    reference: np.ndarray
    samples: np.ndarray
    left_out: list
    p: int
    n_views: int
    exhaustive: bool
    seed: int | None = None
    failed: list = field(default_factory=list)
    kind: str = ""
    view_names: list | None = None

    @property
    def std(self) -> np.ndarray:
        """(P,) standard deviation of the re-solved values (ddof 1; NaN with fewer than 2 re-solves)."""
        if len(self.samples) < 2:
            return np.full(len(self.names), np.nan)
        return np.std(self.samples, axis=0, ddof=1)

    @property
    def max_deviation(self) -> np.ndarray:
        """(P,) largest |re-solved − reference| (NaN without re-solves)."""
        if len(self.samples) == 0:
            return np.full(len(self.names), np.nan)
        return np.max(np.abs(self.samples - self.reference), axis=0)

    def worst_subset(self, name: str) -> tuple:
        """The subset of views whose omission moved parameter ``name`` the most."""
        k = self.names.index(name)
        return self.left_out[int(np.argmax(np.abs(self.samples[:, k] - self.reference[k])))]

    def _subset_text(self, subset) -> str:
        if self.view_names is None:
            return ",".join(map(str, subset))
        return ", ".join(str(self.view_names[i]) for i in subset)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "p": self.p, "n_views": self.n_views, "subsets": len(self.left_out),
                "exhaustive": self.exhaustive, "seed": self.seed,
                "view_names": None if self.view_names is None else [str(v) for v in self.view_names],
                "parameters": {nm: {"unit": u, "value": float(v), "std": float(s), "max_deviation": float(d),
                                    "worst_left_out": list(self.worst_subset(nm)) if len(self.samples) else []}
                               for nm, u, v, s, d in zip(self.names, self.units, self.reference, self.std,
                                                         self.max_deviation)},
                "failed": [{"left_out": list(s), "reason": r} for s, r in self.failed]}

    def report(self) -> str:
        how = "every subset" if self.exhaustive else f"{len(self.left_out)} random subsets (seed {self.seed})"
        lines = [f"leave-{self.p}-out stability of the {self.kind or 'calibration'}: {self.n_views} views, {how}"
                 + (f", {len(self.failed)} re-solve(s) failed" if self.failed else ""),
                 "  parameter          value          std   max deviation  (views left out)"]
        dev = self.max_deviation
        for k, (nm, u, v, s) in enumerate(zip(self.names, self.units, self.reference, self.std)):
            worst = self._subset_text(self.worst_subset(nm)) if len(self.samples) else "-"
            lines.append(f"  {nm:>9} = {v: 14.8g} {s:12.4g} {dev[k]:12.4g} {u:3s} ({worst})")
        for s, r in self.failed:
            lines.append(f"  left out {self._subset_text(s)}: failed: {r}")
        return "\n".join(lines)


def leave_p_out_subsets(n_views: int, p: int, *, max_subsets: int = MAX_SUBSETS, seed: int = 0):
    """The subsets of view indices to leave out: all ``C(n_views, p)`` when there are at most
    ``max_subsets``, else ``max_subsets`` distinct ones drawn at random with ``seed`` (sorted tuples,
    in a repeatable order). Returns ``(subsets, exhaustive)``."""
    n_views, p, max_subsets = int(n_views), int(p), int(max_subsets)
    if p < 1 or p >= n_views:
        raise ValueError(f"p must be between 1 and the number of views - 1 ({n_views - 1}), got {p}")
    if max_subsets < 2:
        raise ValueError(f"max_subsets must be at least 2, got {max_subsets}")
    total = math.comb(n_views, p)
    if total <= max_subsets:
        return [tuple(c) for c in itertools.combinations(range(n_views), p)], True
    rng = np.random.default_rng(seed)
    chosen: set = set()
    out = []
    while len(out) < max_subsets:
        s = tuple(sorted(int(i) for i in rng.choice(n_views, size=p, replace=False)))
        if s not in chosen:
            chosen.add(s)
            out.append(s)
    return out, False


def leave_p_out(n_views: int, solve, *, p: int = 1, max_subsets: int = MAX_SUBSETS, seed: int = 0,
                kind: str = "", view_names=None) -> StabilityResult:
    """Generic leave-p-out test. ``solve(keep)`` takes the sorted list of view indices to use and returns
    ``(names, units, values)`` (values (P,)); it is called once with every view (the reference), then
    once per subset left out. A re-solve that raises ``ValueError`` is recorded in ``failed``.
    ``view_names`` (n_views,) names the views in the report."""
    if view_names is not None and len(view_names) != n_views:
        raise ValueError(f"view_names must name the {n_views} views, got {len(view_names)}")
    subsets, exhaustive = leave_p_out_subsets(n_views, p, max_subsets=max_subsets, seed=seed)
    names, units, ref = solve(list(range(n_views)))
    samples, left_out, failed = [], [], []
    for s in subsets:
        keep = [i for i in range(n_views) if i not in s]
        try:
            _, _, vals = solve(keep)
        except ValueError as exc:
            failed.append((s, str(exc)))
            continue
        samples.append(np.asarray(vals, dtype=np.float64))
        left_out.append(s)
    return StabilityResult(names=tuple(names), units=tuple(units), reference=np.asarray(ref, dtype=np.float64),
                           samples=np.asarray(samples, dtype=np.float64).reshape(len(samples), len(names)),
                           left_out=left_out, p=int(p), n_views=int(n_views), exhaustive=exhaustive,
                           seed=None if exhaustive else int(seed), failed=failed, kind=kind,
                           view_names=None if view_names is None else list(view_names))


def intrinsic_parameters(camera: Camera, estimated) -> tuple[list, list, np.ndarray]:
    """``(names, units, values)`` of a camera's estimated intrinsics, in the order of :data:`STD_NAMES`."""
    values = {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy}
    for i, nm in enumerate(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")):
        if i < camera.dist.size:
            values[nm] = float(camera.dist[i])
    names = [nm for nm in STD_NAMES if nm in estimated and nm in values]
    units = ["px" if nm in ("fx", "fy", "cx", "cy") else "" for nm in names]
    return names, units, np.array([values[nm] for nm in names])


def intrinsics_stability(object_points, image_points, image_size, *, p: int = 1, mirrored=None,
                         model: str = "opencv5", weighting: str = "equal", max_subsets: int = MAX_SUBSETS,
                         seed: int = 0, view_names=None) -> StabilityResult:
    """Leave-p-out stability of :func:`calibration.intrinsics.calibrate_intrinsics` (same view lists).

    Every solve runs without view rejection (``reject=None``): give the views the calibration kept.
    Parameters: ``fx fy cx cy`` (px) and the estimated distortion terms of ``model``.
    """
    if mirrored is None:
        mirrored = [False] * len(object_points)
    if len(object_points) - int(p) < 3:
        raise ValueError(f"leaving {p} of {len(object_points)} views out leaves fewer than 3 views")
    estimated: set = set()

    def solve(keep):
        res = calibrate_intrinsics([object_points[i] for i in keep], [image_points[i] for i in keep], image_size,
                                   mirrored=[mirrored[i] for i in keep], model=model, reject=None,
                                   weighting=weighting)
        if not estimated:
            estimated.update(res.std)
        return intrinsic_parameters(res.camera, estimated)

    return leave_p_out(len(object_points), solve, p=p, max_subsets=max_subsets, seed=seed, kind="intrinsics",
                       view_names=view_names)


def rig_parameters(R_right_left, t_right_left) -> tuple[list, list, np.ndarray]:
    """``(names, units, values)`` of a rig pose: the rotation vector of ``R_right_left`` (deg; for the small
    differences between re-solves its components are the rotation angles about x, y, z), the
    translation ``t_right_left`` (mm) and the baseline (mm)."""
    rv = np.degrees(vector_from_rotation(np.asarray(R_right_left, dtype=np.float64)))
    t = np.asarray(t_right_left, dtype=np.float64).reshape(3)
    return (["rot_x", "rot_y", "rot_z", "t_x", "t_y", "t_z", "baseline"], ["deg"] * 3 + ["mm"] * 4,
            np.concatenate([rv, t, [np.linalg.norm(t)]]))


def rig_stability(left: Camera, right: Camera, object_points, left_points, right_points, *, p: int = 1,
                  max_subsets: int = MAX_SUBSETS, seed: int = 0, view_names=None) -> StabilityResult:
    """Leave-p-out stability of :func:`calibration.stereo.stereo_calibrate` (intrinsics fixed) over its
    views (lists of (N_v, 3), (N_v, 2), (N_v, 2)): rig rotation angles (deg), translation and baseline (mm).
    For other rig solvers (the mirror calibration) call :func:`leave_p_out` with a ``solve`` that returns
    :func:`rig_parameters` of its rig."""
    from .stereo import stereo_calibrate

    def solve(keep):
        res = stereo_calibrate(left, right, [object_points[i] for i in keep], [left_points[i] for i in keep],
                               [right_points[i] for i in keep], uncertainty="none")
        return rig_parameters(res.rig.R_right_left, res.rig.t_right_left)

    return leave_p_out(len(object_points), solve, p=p, max_subsets=max_subsets, seed=seed, kind="stereo rig",
                       view_names=view_names)
