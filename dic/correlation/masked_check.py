"""The check of composed warps on the kept pixels of masked reference subsets (issue 26), on the host.

:class:`kernels.verify.ComposedCheck` compares whole reference subsets; a subset masked to a region (a hole,
a free edge, a declared crack: :mod:`dic.correlation.subset_masks`) would be compared with what lies beyond
the specimen there and fail correct points. :class:`MaskedComposedCheck` gives those points' ZNCC on their
kept pixels; the 2-D check (:class:`dic.sequence.verification.ComposedVerifier`) and the stereo check of
each camera (:class:`dic.correlation.stereo_verify.StereoComposedCheck`) use it for their masked points.
"""
from __future__ import annotations

import numpy as np

__all__ = ["MaskedComposedCheck", "masked_rows"]


def masked_rows(pixel_mask, n_points: int, subset: int):
    """``(rows, kept)`` of an (N, subset²) bool ``pixel_mask``: the points that keep only part of their subset
    and their masks, or None when every subset is whole (or no mask is given)."""
    if pixel_mask is None:
        return None
    m = np.asarray(pixel_mask, bool)
    if m.shape != (int(n_points), int(subset) ** 2):
        raise ValueError(f"pixel_mask must be (N, subset**2) = {(int(n_points), int(subset) ** 2)}, got {m.shape}")
    rows = np.flatnonzero(~m.all(axis=1))
    return (rows, m[rows]) if rows.size else None


class MaskedComposedCheck:
    """The check of the points whose reference subsets keep part of their pixels (a hole, an edge, a crack), on
    the host: the ZNCC between the kept pixels of the reference subset (whole pixels around the POI rounded half
    away from zero) and the frame at the composed warp of those pixels (the warp of :mod:`kernels.verify`; the
    frame's cubic B-spline through ``scipy.ndimage.map_coordinates``). A whole-subset ZNCC there would compare
    what lies beyond the specimen (a background that does not move with it, the other face of a crack) and fail
    correct points. ``rows`` (M,): those points; ``kept`` (M, subset²) bool: their masks."""

    def __init__(self, reference, points, subset: int, rows: np.ndarray, kept: np.ndarray):
        from kernels.conventions import round_half_away

        from .subset_masks import subset_offsets

        ref = np.asarray(reference, np.float64)
        self.shape = ref.shape
        self.rows, self.kept = rows, kept
        self.flags = np.zeros(np.asarray(points).shape[0], bool)
        self.flags[rows] = True
        di, dj = subset_offsets(subset)
        self.dx, self.dy = di.astype(np.float64), dj.astype(np.float64)
        self.centres = round_half_away(np.asarray(points, np.float64)[rows])
        xs = self.centres[:, :1].astype(np.int64) + di[None]
        ys = self.centres[:, 1:].astype(np.int64) + dj[None]
        h, w = ref.shape
        self.inside = np.all((xs >= 0) & (xs < w) & (ys >= 0) & (ys < h), axis=1)
        self.f = np.where(self.inside[:, None], ref[np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)], np.nan)

    def fill(self, image, params, valid, zncc, outcome) -> None:
        """Write the masked points' ZNCC and outcome into ``zncc``, ``outcome`` (N,), for the ``valid`` ones."""
        from scipy.ndimage import map_coordinates

        from kernels.verify import CHECKED, FLAT, OUTSIDE

        p = np.asarray(params, np.float64)
        sel = valid[self.rows] & np.all(np.isfinite(p[self.rows]), axis=1)
        if not np.any(sel):
            return
        rows, kept, c = self.rows[sel], self.kept[sel], self.centres[sel]
        q = p[rows]
        h = q.shape[1] // 2
        dx, dy = self.dx[None], self.dy[None]
        xw = c[:, :1] + dx + q[:, :1] + q[:, 1:2] * dx + q[:, 2:3] * dy
        yw = c[:, 1:] + dy + q[:, h:h + 1] + q[:, h + 1:h + 2] * dx + q[:, h + 2:h + 3] * dy
        if h == 6:
            xw = xw + 0.5 * q[:, 3:4] * dx ** 2 + q[:, 4:5] * dx * dy + 0.5 * q[:, 5:6] * dy ** 2
            yw = yw + 0.5 * q[:, 9:10] * dx ** 2 + q[:, 10:11] * dx * dy + 0.5 * q[:, 11:12] * dy ** 2
        H, W = self.shape
        frame = image.detach().cpu().numpy() if hasattr(image, "detach") else image
        frame = np.asarray(frame, np.float64)
        out_x = np.where(kept, (xw < 0) | (xw > W - 1), False).any(axis=1)
        out_y = np.where(kept, (yw < 0) | (yw > H - 1), False).any(axis=1)
        outside = ~self.inside[sel] | out_x | out_y
        g = map_coordinates(frame, [yw.ravel(), xw.ravel()], order=3, mode="mirror").reshape(xw.shape)
        f = self.f[sel]
        n = kept.sum(axis=1)
        with np.errstate(all="ignore"):
            fm = np.where(kept, f, 0.0).sum(axis=1) / n
            gm = np.where(kept, g, 0.0).sum(axis=1) / n
            fc = np.where(kept, f - fm[:, None], 0.0)
            gc = np.where(kept, g - gm[:, None], 0.0)
            sff, sgg, sfg = (fc * fc).sum(axis=1), (gc * gc).sum(axis=1), (fc * gc).sum(axis=1)
            value = sfg / np.sqrt(sff * sgg)
        flat = ~outside & ((sff <= 0) | (sgg <= 0) | (n == 0))
        done = ~outside & ~flat
        zncc[rows] = np.where(done, value, np.nan).astype(zncc.dtype)
        outcome[rows] = np.where(outside, OUTSIDE, np.where(flat, FLAT, CHECKED)).astype(outcome.dtype)
