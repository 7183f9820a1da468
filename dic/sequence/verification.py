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
"""
from __future__ import annotations

import numpy as np

from kernels.conventions import Status

__all__ = ["ComposedVerifier", "composed_mismatches", "VERIFY_ZNCC"]

#: the default ZNCC below which a composed point fails (``verify_zncc``), by measurement (module docstring)
VERIFY_ZNCC = 0.95


def composed_mismatches(field) -> int:
    """The points of a 2-D frame ``field`` (a :class:`dic.field2d.Field2D`) that failed the check."""
    return int(np.count_nonzero(np.asarray(field.status) == int(Status.COMPOSED_MISMATCH)))


class ComposedVerifier:
    """The check of composed 2-D results: the reference image and the POIs held on the device once.

    ``reference`` (H, W) grey levels: the original reference image; ``points`` (N, 2) px: the POIs;
    ``subset`` px (odd): the run's; ``threshold``: the ZNCC in [-1, 1] below which a point fails;
    ``device``: the run's Warp device (None: the default).
    """

    def __init__(self, reference, points, subset: int, threshold: float, device=None):
        from kernels.checks import in_range
        from kernels.verify import ComposedCheck

        self.threshold = in_range(threshold, -1.0, 1.0, "verify_zncc")
        self._check = ComposedCheck(reference, points, subset, device=device)

    def apply(self, field, image) -> tuple[int, int]:
        """Check the valid points of ``field`` (a frame's composed :class:`dic.field2d.Field2D`, changed in
        place) in ``image`` (the frame, (H, W)); returns (points checked, points that failed). A field
        correlated against the reference image (``reference_index`` 0) is left alone: (0, 0)."""
        if int(field.reference_index) == 0:
            return 0, 0
        from kernels.verify import CHECKED

        valid = np.asarray(field.valid, bool)
        params = field.params
        if params is None:  # translation only (a custom tracker's result)
            params = np.zeros((len(field.u), 6))
            params[:, 0], params[:, 3] = field.u, field.v
        zncc, outcome = self._check.zncc(_on_device(image, self._check.device), params, valid)
        checked = outcome == CHECKED
        failed = checked & valid & ~(zncc >= self.threshold)
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
