"""Declared cracks in stereo DIC (``StereoCorrelation(cracks=)``, ``stereo_sequence(cracks=)``, ``specula stereo
--crack``; issue 26).

The cracks are polylines in LEFT reference-image px (:mod:`dic.cracks`, its crossing rule). They act on

* the left subsets (the stereo match and the left temporal track): the pixels across a crack from the POI,
  and those within :data:`dic.cracks.CRACK_MARGIN_PX` of one, are not correlated
  (:func:`dic.cracks.blocked_pixels`, as 2-D);
* the right subsets (the right temporal track): each right subset pixel is mapped back into the left
  reference image through the POI's stereo match (:mod:`dic.correlation.right_masks`) and dropped when the
  segment from the POI to the mapped position crosses a crack or the position lies within the margin of one;
* the surface strain: a point's fit window leaves out the neighbours whose straight segment from the point
  (left reference px) crosses a crack (:class:`CrackCutStrain`).

A moved reference (``reference="incremental"``, ...) cuts its subsets at the cracks carried into its images by
the state's measured tracks (:meth:`dic.StereoCorrelation._moved_pixel_masks`; docs/stereo.md, "Masks and cracks
carried to a moved reference").
"""
from __future__ import annotations

import numpy as np

__all__ = ["crack_blocked_pixels", "CrackCutStrain"]


def crack_blocked_pixels(cracks):
    """The ``blocked_pixels`` callable of :func:`dic.correlation.subset_masks.tracking_pixel_masks` for ``cracks``
    (a tuple of :class:`dic.cracks.Crack`), or None without any."""
    if not cracks:
        return None

    def blocked(points, subset):
        from .cracks import blocked_pixels

        return blocked_pixels(points, subset, cracks)

    return blocked


class CrackCutStrain:
    """Surface-strain windows that do not reach across a crack.

    ``points`` (N, 2) left reference px; ``neighbours`` (N, k) int (-1: none): the fit neighbourhoods (a grid's
    ``window x window``, :func:`dic.field3d.grid_neighbours`, or a scattered set's); ``cracks``: the declared
    cracks. :attr:`rows` are the points whose neighbourhood a crack cuts, :attr:`neighbours` their neighbours
    with those across set to -1 (None when no window is cut). :meth:`apply` recomputes those points' strain
    with :func:`dic.field3d.surface_strain` on the cut neighbourhoods and writes it into a strain dict computed
    on the whole windows (the other points keep theirs, bit for bit).
    """

    def __init__(self, points, neighbours, cracks):
        from .cracks import segments_cross

        pts = np.asarray(points, np.float64)
        nb = np.asarray(neighbours, np.int64)
        across = (nb >= 0) & segments_cross(pts[:, None, :], pts[np.maximum(nb, 0)], cracks)
        self.rows = np.flatnonzero(across.any(axis=1))
        self.neighbours = None
        if self.rows.size:
            cut = np.full_like(nb, -1)  # only the cut rows are fitted again: every other row without neighbours
            cut[self.rows] = np.where(across[self.rows], -1, nb[self.rows])
            self.neighbours = cut

    def apply(self, strain: dict, X, U, valid, *, camera_center, strain_type: str) -> dict:
        """``strain`` (the dict of :func:`dic.field3d.surface_strain`) with the cut rows fitted again, in place."""
        if self.neighbours is None:
            return strain
        from .field3d import surface_strain

        again = surface_strain(X, U, valid, self.neighbours, camera_center=camera_center, strain_type=strain_type)
        r = self.rows
        for key in ("exx", "eyy", "exy", "normal", "strain_valid"):
            strain[key] = np.array(strain[key], copy=True)
            strain[key][r] = again[key][r]
        return strain
