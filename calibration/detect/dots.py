"""Dot centres of a phase target (:func:`detect_dots`, :func:`detect_dots_in_images`).

Dot centres (:func:`detect_dots`). The recorded phase-shifted images are demodulated
(:func:`kernels.phase.demodulate`) into a wrapped phase ``phi`` and a modulation ``M``. Defocus
attenuates the fringes but leaves the phase of slowly curved fringes nearly in place, so the phase
map stays sharp where the intensity images are a blur (the paper behind Specula, Optics Express
27(6), 9040, 2019, doi:10.1364/OE.27.009040; Bell, Xu, Zhang, "Method for out-of-focus camera
calibration", Applied Optics 55(9), 2016, doi:10.1364/AO.55.002346).

1. Candidates: the phase gradient of a dot points away from its centre; the divergence of the
   unit gradient field peaks at dot centres (and is negative on cell borders).
2. Lattice: candidates are linked to their grid neighbours (4-neighbour growth with
   extrapolated steps, so perspective is followed), giving each a lattice index.
3. Centre (pass 1): around each dot the projectively mapped radial phase model
   ``phi(x) = 2 pi |s(x)| / period + phi0``, ``s = H^-1 x`` (``H`` a local homography from the
   dot's cell, centred on the dot, to the image) is fitted to the wrapped phase by Gauss-Newton on
   the wrapped residual, weighted by the modulation, on a smooth window of the cell that leaves out
   the cone tip and the cell border. The image point is ``H (0, 0)``: the image of the dot centre
   itself, free of the eccentricity bias of ellipse or intensity centroids (Heikkilä, "Geometric
   camera calibration using circular control points", IEEE TPAMI 22(10), 2000,
   doi:10.1109/34.879788).
4. Ids: each dot's fitted ``phi0`` reads its code symbol; the lattice is matched to the target's
   code over all 8 rotations/reflections and translations. A view whose target-to-image mapping
   reverses orientation (a mirror view) is flagged ``mirrored``; ids follow the reflected target,
   so ``target.object_points[ids]`` stay the right correspondences.
5. Defocus (pass 2): a Gaussian blur bends the phase of curved fringes near the cone tip and
   where cells meet, and moves the pass-1 centres (by up to ~1 px at sigma = 10 px). The blur of
   each dot is measured by matching a simulated modulation map to the measured one, and the bias
   is measured by running the identical pass-1 fit (same pixels, same weights) on a simulated view
   of the dot: the target's exact fringe field (all cells, codes, the edge of the fringe area,
   pixel-area integration at the code jumps) mapped through the current homography and blurred.
   The bias is subtracted, three rounds (the homography and blur are refined in between).

Steps 1, 2 and 4 live in :mod:`calibration.detect.lattice`, steps 3 and 5 in
:mod:`calibration.detect.dot_model`.

Conventions: docs/conventions.md (pixel (0, 0) is the centre of the top-left pixel, points are
(x, y)); target frame: :mod:`calibration.targets`. Accuracy measured in docs/targets.md.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..targets import PhaseTarget
from .common import (
    TWO_PI,
    DetectionError,
    _check_maps,
    _check_target,
    _estimate_blur,
    _homography,
    _jacobian_h,
    demodulate_images,
)
from .dot_model import _fit_dot, _remove_blur_bias
from .lattice import (
    _find_candidates,
    _grow_lattice,
    _match_code,
    _phase_gradient,
    _placement_is_unique,
    _trim_spurious_lines,
    _uncoded_ids,
)


@dataclass
class DotDetection:
    """Dot centres found in one view of a :class:`~calibration.targets.PhaseTarget`.

    Attributes
    ----------
    image_points : (N, 2) float64
        Sub-pixel image position (x, y) of each found dot centre (px).
    ids : (N,) int64
        Target dot id of each point (``target.object_points[ids]`` are the matching object points).
    object_points : (N, 3) float64
        Target-frame dot centres (mm) matching ``image_points``.
    residual_rms : (N,) float64
        RMS of the wrapped-phase residual of each dot's fit (rad).
    sigma_px : (N,) float64
        Standard deviation of each centre from the fit covariance (px, noise only).
    modulation : (N,) float64
        Median fringe modulation around each dot (grey levels).
    modulation_slope : (N,) float64
        Relative change of the modulation across each dot's fit window (plane fit, centre to
        window edge). Near 0 for a fully lit dot; large where part of the window is vignetted
        (e.g. by a mirror's edge), which biases the centre (see :func:`detect_dots`).
    n_pixels : (N,) int64
        Pixels used in each dot's fit.
    mirrored : bool
        True when the target appears left-handed (seen through a mirror).
    blur_sigma : float
        Gaussian blur estimated from the fringe modulation (px); 0 when sharp.
    """

    image_points: np.ndarray
    ids: np.ndarray
    object_points: np.ndarray
    residual_rms: np.ndarray
    sigma_px: np.ndarray
    modulation: np.ndarray
    n_pixels: np.ndarray
    mirrored: bool
    blur_sigma: float = 0.0
    modulation_slope: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def quality(self) -> np.ndarray:
        """Per-point quality figure: the centre standard deviation (px) from the fit."""
        return self.sigma_px


def _estimate_period(phase, modulation, mask):
    gx, gy, ok = _phase_gradient(phase, modulation, mask)
    g = np.hypot(gx, gy)[ok]
    if g.size < 100:
        raise DetectionError(f"only {g.size} pixels show fringes with enough modulation; is the target in view?")
    return float(TWO_PI / np.median(g))


def detect_dots(
    phase,
    modulation,
    target: PhaseTarget,
    *,
    mask=None,
    min_modulation: float = 3.0,
    blur_sigma: float | None = None,
    correct_blur: bool = True,
    min_coverage: float = 0.8,
    mirrored: bool | None = None,
) -> DotDetection:
    """Find the dots of a phase target in a demodulated view and their centres.

    Parameters
    ----------
    phase, modulation : (H, W) float
        Wrapped phase (rad) and modulation (grey levels) from :func:`kernels.phase.demodulate`.
    target : PhaseTarget
        The displayed target (grid, pitch, period, code).
    mask : (H, W) bool, optional
        Pixels to use (e.g. the ``valid`` output of the demodulation); combined with
        ``modulation >= min_modulation``.
    blur_sigma : float, optional
        Gaussian blur of the camera (px) if known. By default it is measured: first from the
        width of the modulation drop at the edge of the fringe area, then per dot from its
        modulation map, smoothed by a plane over the image.
    correct_blur : bool
        Run pass 2 (defocus bias removal by simulation) when the blur exceeds 0.3 px.
    min_coverage : float
        Dots whose fit window is less than this share on usable pixels (cut by the image edge,
        the mask, or a mirror's edge) are dropped.
    mirrored : bool, optional
        Only for targets without a code: whether the view is through a mirror (a plain grid
        cannot tell). Coded targets report it.

    Returns
    -------
    DotDetection
        Raises :class:`DetectionError` when no grid can be found or identified.
    """
    _check_target(target)
    phase, modulation, mask = _check_maps(phase, modulation, mask)
    if blur_sigma is not None and (not np.isfinite(blur_sigma) or blur_sigma < 0):
        raise ValueError(f"blur_sigma must be a finite number of px >= 0 or None, got {blur_sigma!r}")
    if not 0 <= min_coverage <= 1:
        raise ValueError(f"min_coverage must be in [0, 1], got {min_coverage!r}")
    mask = mask & (modulation >= min_modulation)
    period_img = _estimate_period(phase, modulation, mask)
    cands, _ = _find_candidates(phase, modulation, mask, period_img * target.pitch / target.period)
    labels, found = _grow_lattice(cands, 4 * target.n_dots)
    pts = cands[found]
    lab = labels[found]
    lab, pts = _trim_spurious_lines(lab, pts, target.grid)
    if len(pts) < 4:
        raise DetectionError(f"only {len(pts)} dots could be linked into a grid; at least 4 are needed")
    where = {tuple(l): n for n, l in enumerate(lab)}
    ncell = np.array(target.grid)
    span = lab.max(axis=0) - lab.min(axis=0) + 1
    if np.any(span > ncell.max()) or len(pts) > target.n_dots:
        raise DetectionError(
            f"found a grid of {span[0]}x{span[1]} dots ({len(pts)} dots) but the target has {ncell[0]}x{ncell[1]}; "
            "check grid/pitch/period of the target"
        )
    pitch = target.pitch
    given_blur = blur_sigma is not None
    if blur_sigma is None:
        blur_sigma = _estimate_blur(modulation, mask)
    # pass 1: radial phase model on the wrapped phase, window margins a fixed fraction of the cell
    rho_in, border = 0.1 * target.period, 0.1 * pitch
    fits = []
    for n, ij in enumerate(lab):
        src, dst = [], []
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                m = where.get((ij[0] + di, ij[1] + dj))
                if m is not None:
                    src.append((di * pitch, dj * pitch))
                    dst.append(pts[m])
        src, dst = np.array(src), np.array(dst)
        if len(src) < 4 or np.linalg.matrix_rank(src - src.mean(axis=0)) < 2:
            fits.append(None)
            continue
        try:
            A0 = np.linalg.inv(_homography(src, dst))
            fit = _fit_dot(phase, modulation, mask, A0, target.period, pitch, rho_in, border)
        except np.linalg.LinAlgError:
            fit = None  # degenerate neighbourhood homography (dots a few pixels apart): this dot has no fit
        fits.append(fit if fit is not None and fit.coverage >= min_coverage else None)
    keep = np.array([f is not None for f in fits])
    if keep.sum() < 4:
        raise DetectionError(f"only {int(keep.sum())} dots are fully in view with a successful fit; at least 4 are needed")
    fits = [f for f in fits if f is not None]
    lab = lab[keep]
    centres = np.array([f.centre for f in fits])
    # ids
    phi0 = np.array([f.phi0 for f in fits])
    step = TWO_PI / target.levels
    # defocus shifts every dot's phi0 by about the same amount: remove the common offset
    # (circular mean of the deviations from the nearest symbol) before reading the symbols
    dev = phi0 - step * np.rint(phi0 / step)
    common = float(np.angle(np.mean(np.exp(1j * dev * target.levels)))) / target.levels
    sym = np.mod(np.rint((phi0 - common) / step), target.levels).astype(np.int64)
    if target.coded:
        placements = _match_code(lab, sym, target)
        if not placements:
            raise DetectionError(
                f"the {len(lab)} linked dots span more rows or columns than the {target.grid[0]} x {target.grid[1]} "
                "target in every orientation (spurious or mislinked dots); check the target file and the view")
        best = placements[0]
        second = placements[1][0] if len(placements) > 1 else 10 ** 6
        if not _placement_is_unique(best[0], second, len(lab)):
            raise DetectionError(
                f"the dot code is ambiguous in this view (best placement {best[0]} mismatches, next {second}); "
                f"{len(lab)} dots seen - show more of the target"
            )
        T, off = best[1], np.array(best[2])
        ij = lab @ T.T + off
        good = target.code[ij[:, 1], ij[:, 0]] == sym  # drops a single misread dot
    else:
        if len(lab) != target.n_dots:
            raise DetectionError(
                f"a target without code must be fully visible: found {len(lab)} of {target.n_dots} dots"
            )
        ij = _uncoded_ids(lab, centres, target, mirrored)
        good = np.ones(len(ij), dtype=bool)
    ids = ij[:, 1] * target.grid[0] + ij[:, 0]
    sigmas = np.full(len(ids), float(blur_sigma))
    if correct_blur and blur_sigma > 0.3:
        centres, good, sigmas = _remove_blur_bias(target, phase.shape, modulation, mask, fits, ids, centres,
                                                  good, float(blur_sigma), given_blur, rho_in, border)
    gsel = np.flatnonzero(good)
    if gsel.size < 4:
        raise DetectionError(f"only {gsel.size} dots were identified; at least 4 are needed")
    # handedness of the target -> image mapping
    screen_c = target.dot_centres_px
    Hg = _homography(screen_c[ids[gsel]], centres[gsel])
    is_mirrored = bool(np.linalg.det(_jacobian_h(Hg, screen_c[ids[gsel]].mean(axis=0))) < 0)
    sel = gsel[np.argsort(ids[gsel])]
    return DotDetection(
        image_points=centres[sel],
        ids=ids[sel].astype(np.int64),
        object_points=target.object_points[ids[sel]],
        residual_rms=np.array([fits[i].rms for i in sel]),
        sigma_px=np.array([fits[i].sigma for i in sel]),
        modulation=np.array([fits[i].modulation for i in sel]),
        n_pixels=np.array([fits[i].n for i in sel], dtype=np.int64),
        mirrored=is_mirrored,
        blur_sigma=float(np.median(sigmas[sel])),
        modulation_slope=np.array([fits[i].modulation_slope for i in sel]),
    )


def detect_dots_in_images(images, target: PhaseTarget, *, min_modulation: float = 3.0, device=None, **kwargs) -> DotDetection:
    """Demodulate a recorded (steps, H, W) stack and run :func:`detect_dots` on it."""
    _check_target(target)
    phase, mod, _, valid = demodulate_images(images, target, min_modulation=min_modulation, device=device)
    return detect_dots(phase, mod, target, mask=valid, min_modulation=min_modulation, **kwargs)
