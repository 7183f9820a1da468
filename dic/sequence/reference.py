"""Reference strategies of a 2-D sequence and the composition of displacements across reference updates.

Strategies (``reference=`` of :func:`dic.sequence.track_sequence`, ``--reference`` of ``specula track``):

``"fixed"``
    every frame against the original reference image (frame 0).
``"incremental"``
    frame ``k`` against frame ``k - 1``.
``"every:N"``
    frame ``k`` against frame ``N * floor((k - 1) / N)`` (the reference moves every N frames).
``"auto"``
    frame ``k`` against the previous frame's reference; when the result's valid fraction (among the
    points the reference can track: valid in it or placed by local interpolation, below) falls
    below ``auto_valid`` (default 0.95) or the median ZNCC of its valid points below ``auto_zncc``
    (default 0.95), the reference moves to frame ``k - 1`` (the newest frame there is) and frame
    ``k`` is tracked again against it.

Results are always Lagrangian, at the original POIs ``X0`` of the reference image: a new reference
``r`` tracks the points where the original POIs are in frame ``r`` (``X_r = X0 + d_r(X0)``; invalid
points get the displacement interpolated from their valid neighbours so that the point set stays
the same), so a displacement ``w`` measured against ``r`` composes exactly as
``d_k(X0) = d_r(X0) + w(X_r)``, and the shape-function gradients by the chain rule
(:func:`compose_params`).

Validity across an update (:func:`fill_reference`): a point is valid in frame ``k`` when it is valid
against its reference ``r`` and its place in ``r`` is known: either it is valid in ``r``, or it was
not but its parameters in ``r`` were interpolated (all of them, linearly) from a Delaunay triangle of
valid points whose corners are all within 4 POI spacings of it. Such a point is tracked again against
the new reference and comes back (its composed displacement is as good as the local interpolation of
a smooth field); a frame's ``reference_interpolated`` attribute counts them (per point: valid in ``k``
and not valid in frame ``reference_index``). Points outside the valid points' hull or in a wider hole
stay invalid, with the status they had in ``r``. (Before, a point invalid at an update stayed invalid
for good, so the valid set only shrank with every update.)
"""
from __future__ import annotations

from dataclasses import dataclass

from ..correlation.lagrangian import (
    compose_params,
    displacement_outliers,
    fill_reference,
    moved_points,
    relative_params,
    shift_params,
)

__all__ = ["ReferencePolicy", "parse_reference", "compose_params", "displacement_outliers", "fill_reference",
           "moved_points", "relative_params",
           "shift_params"]

AUTO_VALID = 0.95
AUTO_ZNCC = 0.95


@dataclass(frozen=True)
class ReferencePolicy:
    """A parsed reference strategy: ``kind`` "fixed" | "incremental" | "every" | "auto", ``every`` N,
    and the ``auto`` thresholds."""

    kind: str = "fixed"
    every: int = 0
    auto_valid: float = AUTO_VALID
    auto_zncc: float = AUTO_ZNCC

    @property
    def text(self) -> str:
        return f"every:{self.every}" if self.kind == "every" else self.kind

    def start(self, k: int, previous_reference: int) -> int:
        """The reference frame that frame ``k`` is tracked against first (``previous_reference``: frame k-1's)."""
        if self.kind == "fixed":
            return 0
        if self.kind == "incremental":
            return k - 1
        if self.kind == "every":
            return self.every * ((k - 1) // self.every)
        return previous_reference

    def needs_update(self, valid_fraction: float, median_zncc: float) -> bool:
        """``auto``: does a result this good call for a newer reference?"""
        return self.kind == "auto" and (not valid_fraction >= self.auto_valid or not median_zncc >= self.auto_zncc)


def parse_reference(reference, *, auto_valid: float = AUTO_VALID, auto_zncc: float = AUTO_ZNCC) -> ReferencePolicy:
    """``"fixed"``, ``"incremental"``, ``"every:N"`` (N >= 1) or ``"auto"`` -> :class:`ReferencePolicy`."""
    from kernels.checks import unit_interval

    auto_valid = unit_interval(auto_valid, "auto_valid")
    auto_zncc = unit_interval(auto_zncc, "auto_zncc")
    if isinstance(reference, ReferencePolicy):
        return reference
    if not isinstance(reference, str):
        raise ValueError(f"reference must be 'fixed', 'incremental', 'every:N' or 'auto', got {reference!r}")
    text = reference.strip().lower()
    if text in ("fixed", "incremental", "auto"):
        return ReferencePolicy(text, 0, auto_valid, auto_zncc)
    if text.startswith("every:"):
        n = text[len("every:"):].strip()
        if n.isdigit() and int(n) >= 1:
            return ReferencePolicy("every", int(n), auto_valid, auto_zncc)
        raise ValueError(f"reference 'every:N' needs a whole number N >= 1 of frames, got {reference!r}")
    raise ValueError(f"reference must be 'fixed', 'incremental', 'every:N' or 'auto', got {reference!r}")
