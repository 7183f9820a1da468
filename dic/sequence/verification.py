"""Re-verification of composed results against the original reference image (``verify_composed``).

With a moved reference (``reference="incremental"``, ``"every:N"``, ``"auto"``) a frame's reported warp
is a composition of several correlations (:class:`dic.correlation.lagrangian.MovedReference`): a wrong
match that anchored a reference update is carried into every frame tracked from it, and each
correlation of the chain can look good. :class:`ComposedVerifier` checks every valid point of such a
frame against the ORIGINAL reference image: the ZNCC between the point's reference subset and the frame
sampled at the composed warp (1st order: displacement and gradient; 2nd order: with the second
derivatives; :class:`kernels.verify.ComposedCheck`, one launch per frame). A point whose ZNCC is below
the threshold is not valid and gets the status
:attr:`kernels.conventions.Status.COMPOSED_MISMATCH`; a point whose subset (or its warped copy) leaves
the image, or has no texture, cannot be checked and keeps its result. Frames correlated against the
reference image itself (``reference_index`` 0) are not composed and are not checked.

The threshold defaults to :data:`VERIFY_ZNCC` (0.95), chosen by measurement (docs/dic2d.md,
"Re-verification of composed results"; speckle of radius 2 px, blur 0.7, subset 21, 8-bit): a correct composed
warp scored at least 0.9993 at 1 grey level of noise and 0.9942 at 4, a warp 1 px off at most 0.921, 0.5 px off
at most 0.980. The run's ``zncc_min`` (0.8) would pass a whole-pixel wrong match (median 0.86).

On a texture that changes during the test (an evolving speckle: paint that flakes, glints) every correct point
loses correlation with the reference image as the sequence goes on, and a fixed 0.95 refuses them all within a
few frames. The threshold of a frame is therefore ``min(verify_zncc, median - verify_spread * 1.4826 * MAD)``
of its checked points' ZNCCs (:func:`kernels.verify.composed_threshold`; ``verify_spread`` default
:data:`VERIFY_SPREAD`): ``verify_zncc`` wherever the texture still matches the reference (correct points close
to 1 with a small spread: the results of the fixed threshold), and the frame's typical value less
``verify_spread`` robust standard deviations where it does not; there a point between the two also fails when
the ZNCC at its composed warp moved by 1 px along x or y beats its own (the peak test of
:func:`kernels.verify.composed_failures`: a wrong match is off the peak of what is left of the reference
texture, however decorrelated). Measured on the evolving texture of
docs/dic2d.md (512², 2 % of the speckles replaced per frame, 60 frames), see "Re-verification of composed
results" there for what it keeps and what it still catches.
"""
from __future__ import annotations

import numpy as np

from kernels.conventions import Status
from kernels.verify import VERIFY_SPREAD, check_verify_spread

from ..correlation.masked_check import MaskedComposedCheck, masked_rows

__all__ = ["ComposedVerifier", "composed_mismatches", "VERIFY_ZNCC", "VERIFY_SPREAD", "check_verify_spread"]

#: the default ZNCC below which a composed point fails (``verify_zncc``), by measurement (module docstring)
VERIFY_ZNCC = 0.95


def composed_mismatches(field) -> int:
    """The points of a 2-D frame ``field`` (a :class:`dic.field2d.Field2D`) that failed the check."""
    return int(np.count_nonzero(np.asarray(field.status) == int(Status.COMPOSED_MISMATCH)))


class ComposedVerifier:
    """The check of composed 2-D results: the reference image and the POIs held on the device once.

    ``reference`` (H, W) grey levels: the original reference image; ``points`` (N, 2) px: the POIs;
    ``subset`` px (odd): the run's; ``threshold``: the ZNCC in [-1, 1] below which a point fails (``verify_zncc``);
    ``spread``: robust standard deviations below each frame's median ZNCC (``verify_spread``;
    :func:`kernels.verify.composed_threshold`), None: ``threshold`` alone; ``device``: the run's Warp device
    (None: the default). ``last_threshold``: the threshold of the last frame checked (None before any).
    """

    def __init__(self, reference, points, subset: int, threshold: float, device=None, pixel_mask=None,
                 spread: float | None = None):
        from kernels.checks import in_range
        from kernels.verify import ComposedCheck

        self.threshold = in_range(threshold, -1.0, 1.0, "verify_zncc")
        self.spread = check_verify_spread(spread)
        self.last_threshold: float | None = None
        self._check = ComposedCheck(reference, points, subset, device=device)
        # ``pixel_mask`` (N, subset²) bool, optional: the pixels each reference subset keeps (holes, edges, cracks:
        # dic.correlation.subset_masks); the masked points are checked on their kept pixels (_masked_zncc)
        found = masked_rows(pixel_mask, self._check.n_points, subset)
        self._masked = None if found is None else MaskedComposedCheck(reference, points, int(subset), *found)

    def apply(self, field, image) -> tuple[int, int]:
        """Check the valid points of ``field`` (a frame's composed :class:`dic.field2d.Field2D`, changed in
        place) in ``image`` (the frame, (H, W)); returns (points checked, points that failed). A field
        correlated against the reference image (``reference_index`` 0) is left alone: (0, 0)."""
        if int(field.reference_index) == 0:
            return 0, 0
        from kernels.verify import CHECKED, composed_failures, shifted_params

        valid = np.asarray(field.valid, bool)
        params = field.params
        if params is None:  # translation only (a custom tracker's result)
            params = np.zeros((len(field.u), 6))
            params[:, 0], params[:, 3] = field.u, field.v
        frame = self._check.coefficients(_on_device(image, self._check.device))  # prefiltered once per frame

        def zncc_at(p, which):
            ask = which if self._masked is None else which & ~self._masked.flags
            z, outcome = self._check.zncc(frame, p, ask)
            if self._masked is not None and np.any(which & self._masked.flags):
                self._masked.fill(image, p, which, z, outcome)
            return z, outcome

        zncc, outcome = zncc_at(params, valid)
        checked = outcome == CHECKED

        def probe(du, dv, which):  # the peak test (kernels.verify.composed_failures)
            z, oc = zncc_at(shifted_params(params, du, dv), which)
            return np.where(oc == CHECKED, z, np.nan)

        failed, self.last_threshold = composed_failures(zncc, checked & valid, self.threshold, self.spread, probe)
        if np.any(failed):
            field.valid = valid & ~failed
            status = np.asarray(field.status, np.int32).copy()
            status[failed] = int(Status.COMPOSED_MISMATCH)
            field.status = status
            if field.reference_interpolated is not None:
                field.reference_interpolated = np.asarray(field.reference_interpolated, bool) & ~failed
            for name in ("sigma_u", "sigma_v"):  # NaN where not valid (dic.field2d.Field2D)
                sigma = getattr(field, name)
                if sigma is not None:
                    sigma = np.asarray(sigma, np.float64).copy()
                    sigma[failed] = np.nan
                    setattr(field, name, sigma)
        return int(np.count_nonzero(checked)), int(np.count_nonzero(failed))


def _on_device(image, device):
    """A torch tensor frame as a float32 ``wp.array`` on ``device``, converted there by torch (no copy through
    the host, as the tracker reads it: kernels.images.as_float32_tensor); any other frame as it is."""
    from kernels.images import as_float32_tensor, is_torch_tensor

    if not is_torch_tensor(image):
        return image
    import warp as wp

    return wp.from_torch(as_float32_tensor(image, str(device), "frame"))
