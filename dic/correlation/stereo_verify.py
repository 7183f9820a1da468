"""Re-verification of a stereo state's composed temporal tracks against the reference pair (issue 26).

With a moved reference (``reference="incremental"``, ``"every:N"``, ``"auto"`` of
:func:`dic.sequence.stereo_sequence`), a state's left and right track parameters are compositions of
several correlations (:class:`dic.correlation.lagrangian.MovedReference`, one per camera): a wrong match
that anchored a reference update is carried into every later state. :class:`StereoComposedCheck` checks
each camera's composed warps against that camera's ORIGINAL reference image, the 2-D check
(:mod:`dic.sequence.verification`) done per camera with the same kernel (:class:`kernels.verify.ComposedCheck`):

- left: the ZNCC between the left reference subset at each POI and the state's left image at the composed
  left warp (``params_left``, at the POIs of the reference pair);
- right: the ZNCC between the right reference subset at each matched point (``match.points_right``) and the
  state's right image at the composed right warp (``params_right``).

A point whose accepted track scores below the threshold in either camera fails (each camera's threshold of a
state: ``min(verify_zncc, median - spread * 1.4826 * MAD)`` of that camera's checked ZNCCs, the 2-D rule of
:func:`kernels.verify.composed_threshold`; ``spread`` None: ``verify_zncc`` alone) (the stereo status
:attr:`dic.field3d.StereoStatus.COMPOSED_MISMATCH`, set by :class:`dic.StereoCorrelation`); a subset that
leaves the image (in the reference or the state) or has no texture cannot be checked and keeps its result.
A subset masked to a region or cut by a crack (the tracks' pixel masks) is checked on its kept pixels, as in 2-D
(:class:`dic.correlation.masked_check.MaskedComposedCheck`).
"""
from __future__ import annotations

import numpy as np

__all__ = ["StereoComposedCheck"]


class StereoComposedCheck:
    """The reference pair and its subsets held on the device once, to check composed stereo tracks.

    ``left_ref``, ``right_ref`` (H, W) grey levels: the reference pair; ``points_left`` (N, 2) px: the POIs
    in the left reference; ``points_right`` (M, 2) px: the matched points in the right reference (the rows
    ``matched`` of the POIs); ``matched`` (M,) int: their POI indices; ``subset`` px (odd): the run's;
    ``threshold``: the ZNCC in [-1, 1] below which a track fails (``verify_zncc``); ``spread``: robust standard
    deviations below each camera's median ZNCC of a state that can lower it (``verify_spread``; None: the threshold
    alone); ``device``: the run's Warp device. ``pixel_mask_left`` (N, subset²) and ``pixel_mask_right``
    (M, subset²) bool, optional: the pixels each camera's reference subsets keep (the tracks' masks: a region,
    a free edge, a crack); those points are checked on their kept pixels
    (:class:`dic.correlation.masked_check.MaskedComposedCheck`), as in 2-D. ``last_thresholds``: (left, right)
    thresholds of the last state checked (None before any; right None without a right track).
    """

    def __init__(self, left_ref, right_ref, points_left, points_right, matched, subset: int, threshold: float,
                 device=None, spread: float | None = None, pixel_mask_left=None, pixel_mask_right=None):
        from kernels.checks import in_range
        from kernels.verify import ComposedCheck, check_verify_spread

        from .masked_check import MaskedComposedCheck, masked_rows

        self.threshold = in_range(threshold, -1.0, 1.0, "verify_zncc")
        self.spread = check_verify_spread(spread)
        self.last_thresholds: tuple | None = None
        self.matched = np.asarray(matched, dtype=np.int64)
        self.n_points = len(points_left)
        self._left = ComposedCheck(left_ref, points_left, subset, device=device)
        self._right = ComposedCheck(right_ref, points_right, subset, device=device) if len(self.matched) else None

        def masked(ref, points, mask):
            found = masked_rows(mask, len(points), subset)
            return None if found is None else MaskedComposedCheck(ref, points, int(subset), *found)

        self._masked_left = masked(left_ref, points_left, pixel_mask_left)
        self._masked_right = masked(right_ref, points_right, pixel_mask_right) if self._right is not None else None

    def check(self, params_left, accepted_left, image_left, params_right, accepted_right, image_right):
        """ZNCC of each camera's composed tracks against its reference image.

        ``params_left`` (N, 6 or 12), ``accepted_left`` (N,) bool: the left track at the POIs; ``params_right``
        (M, 6 or 12), ``accepted_right`` (M,) bool: the right track at the matched points (None: no right track);
        ``image_left``, ``image_right`` (H, W): the state's pair.

        Returns ``(failed, zncc_left, zncc_right)``: (N,) bool, the POIs whose accepted track fails in either
        camera; (N,) float32 ZNCC per camera, NaN where not checked (not accepted, or the subset leaves the
        image or is flat), the right one at the POIs (NaN where not matched).
        """
        n = self.n_points
        failed = np.zeros(n, bool)
        zncc_left, fail_l, limit_l = self._camera(self._left, self._masked_left, image_left, params_left,
                                                  accepted_left)
        failed |= fail_l
        zncc_right = np.full(n, np.nan, np.float32)
        limit_r = None
        if self._right is not None and params_right is not None:
            z, fail_r, limit_r = self._camera(self._right, self._masked_right, image_right, params_right,
                                              accepted_right)
            zncc_right[self.matched] = z
            failed[self.matched] |= fail_r
        self.last_thresholds = (limit_l, limit_r)
        return failed, zncc_left, zncc_right

    def _camera(self, check, masked, image, params, accepted):
        """One camera's check: (ZNCC (float32, NaN where not checked), failed (bool), the threshold), per point of
        ``check`` (:func:`kernels.verify.composed_failures`, the 2-D rule with its peak test); the points of
        ``masked`` (a MaskedComposedCheck or None) on their kept pixels."""
        from kernels.verify import CHECKED, composed_failures, shifted_params

        accepted = np.asarray(accepted, bool)
        frame = check.coefficients(image)  # prefiltered once for the check and its probes

        def zncc_at(p, which):
            ask = which if masked is None else which & ~masked.flags
            z, oc = check.zncc(frame, p, ask)
            if masked is not None and np.any(which & masked.flags):
                masked.fill(image, p, which, z, oc)
            return z, oc

        z, outcome = zncc_at(params, accepted)
        zncc = np.where(outcome == CHECKED, z, np.nan).astype(np.float32)

        def probe(du, dv, which):
            zp, oc = zncc_at(shifted_params(params, du, dv), which)
            return np.where(oc == CHECKED, zp, np.nan)

        failed, limit = composed_failures(zncc, np.isfinite(zncc), self.threshold, self.spread, probe)
        return zncc, failed, limit
