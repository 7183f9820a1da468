"""Dot detector, steps 1, 2 and 4 (:mod:`calibration.detect.dots`): dot candidates from the
divergence of the unit phase gradient, their linking into a lattice of grid neighbours, and the
dots' ids read from the target's cell code.

Conventions: docs/conventions.md (pixel (0, 0) is the centre of the top-left pixel, points are
(x, y)); target frame: :mod:`calibration.targets`.
"""
from __future__ import annotations

import numpy as np

from ..targets import PhaseTarget
from .common import DetectionError, _homography, _jacobian_h


def _phase_gradient(phase, modulation, mask):
    """Wrapped central-difference phase gradient (rad/px) and a weight map."""
    z = modulation * np.exp(1j * phase) * mask
    gx = np.zeros(phase.shape)
    gy = np.zeros(phase.shape)
    gx[:, 1:-1] = np.angle(z[:, 2:] * np.conj(z[:, :-2])) / 2
    gy[1:-1, :] = np.angle(z[2:, :] * np.conj(z[:-2, :])) / 2
    ok = mask.copy()
    ok[:, 1:-1] &= mask[:, 2:] & mask[:, :-2]
    ok[1:-1, :] &= mask[2:, :] & mask[:-2, :]
    ok[:, [0, -1]] = False
    ok[[0, -1], :] = False
    return gx, gy, ok


def _find_candidates(phase, modulation, mask, period_img: float):
    """Dot-centre candidates (K, 2) from the divergence of the unit phase-gradient field."""
    from scipy import ndimage

    gx, gy, ok = _phase_gradient(phase, modulation, mask)
    norm = np.hypot(gx, gy)
    ok &= norm > 1e-6
    w = np.where(ok, np.minimum(modulation / (np.median(modulation[ok]) + 1e-9), 1.0), 0.0)
    nx = np.where(ok, gx / np.maximum(norm, 1e-12), 0.0) * w
    ny = np.where(ok, gy / np.maximum(norm, 1e-12), 0.0) * w
    div = np.zeros(phase.shape)
    div[:, 1:-1] += (nx[:, 2:] - nx[:, :-2]) / 2
    div[1:-1, :] += (ny[2:, :] - ny[:-2, :]) / 2
    s = max(1.0, period_img / 12)
    div = ndimage.gaussian_filter(div, s)
    cover = ndimage.gaussian_filter(w, s)
    size = int(max(3, round(period_img / 3))) | 1
    peaks = (div == ndimage.maximum_filter(div, size=size)) & (cover > 0.5)
    # a dot's divergence integrates to ~2 pi over a disk: peak height ~ 1 / s
    peaks &= div > 0.15 / s
    ys, xs = np.nonzero(peaks)
    strength = div[ys, xs]
    order = np.argsort(-strength)
    return np.stack([xs[order], ys[order]], axis=1).astype(np.float64), strength[order]


_STEPS = ((1, 0), (-1, 0), (0, 1), (0, -1))


def _grow_lattice(points: np.ndarray, max_points: int):
    """Assign integer lattice indices to candidate points by 4-neighbour growth.

    Growth starts from each of the (up to 12) candidates nearest the middle that has two
    independent neighbour directions, and the largest labelling wins: a spurious candidate (a
    phase defect near a mirror's edge, a glint) as the seed, or as the seed's nearest neighbour,
    would otherwise set a wrong basis and link only a line of dots.

    Returns (labels (K, 2) int, labelled bool mask)."""
    from scipy.spatial import cKDTree

    k = len(points)
    if k < 4:
        raise DetectionError(f"found {k} dot candidates; at least 4 are needed to set up the grid")
    tree = cKDTree(points)
    centre = np.median(points, axis=0)
    seed_order = np.argsort(np.linalg.norm(points - centre, axis=1))
    best = None
    for seed in seed_order[: min(k, 12)]:
        d, nb = tree.query(points[seed], k=min(k, 9))
        vecs = points[nb[1:]] - points[seed]
        if len(vecs) < 2:
            continue
        e1 = vecs[0]
        # second axis: the nearest vector far from parallel to e1
        cosang = np.abs(vecs @ e1) / (np.linalg.norm(vecs, axis=1) * np.linalg.norm(e1) + 1e-12)
        cand = np.flatnonzero(cosang < 0.5)
        if cand.size == 0:
            continue
        labels, done = _grow_from(points, tree, int(seed), e1, vecs[cand[0]], max_points)
        span = labels[done].max(axis=0) - labels[done].min(axis=0)
        score = (int(np.all(span > 0)), int(done.sum()))   # a 2-D grid beats a line, then more dots
        if best is None or score > best[0]:
            best = (score, labels, done)
        if score[1] >= 0.9 * k:   # (nearly) every candidate linked: no better labelling exists
            break
    if best is None:
        raise DetectionError("the dot candidates do not form a 2-D grid (no two independent neighbour directions)")
    return best[1], best[2]


def _grow_from(points, tree, seed: int, e1, e2, max_points: int):
    """Breadth-first growth of the lattice labelling from ``seed`` with basis (e1, e2)."""
    k = len(points)
    labels = np.zeros((k, 2), dtype=np.int64)
    done = np.zeros(k, dtype=bool)
    where: dict[tuple[int, int], int] = {(0, 0): seed}
    done[seed] = True
    queue = [(0, 0)]
    basis = {(1, 0): e1, (-1, 0): -e1, (0, 1): e2, (0, -1): -e2}
    while queue:
        ij = queue.pop(0)
        p = points[where[ij]]
        for step in _STEPS:
            nij = (ij[0] + step[0], ij[1] + step[1])
            if nij in where:
                continue
            back = (ij[0] - step[0], ij[1] - step[1])
            if back in where:
                v = p - points[where[back]]
            else:
                # the step along the same axis seen from a labelled side neighbour, else the seed basis
                v = basis[step]
                for side in ((step[1], step[0]), (-step[1], -step[0])):
                    a = (ij[0] + side[0], ij[1] + side[1])
                    b = (a[0] + step[0], a[1] + step[1])
                    if a in where and b in where:
                        v = points[where[b]] - points[where[a]]
                        break
            pred = p + v
            d, nb = tree.query(pred)
            if d < 0.3 * np.linalg.norm(v) and not done[nb]:
                where[nij] = int(nb)
                done[nb] = True
                labels[nb] = nij
                queue.append(nij)
        if len(where) > max_points:
            break
    return labels, done


_DIHEDRAL = [np.array(m) for m in (
    [[1, 0], [0, 1]], [[0, -1], [1, 0]], [[-1, 0], [0, -1]], [[0, 1], [-1, 0]],
    [[-1, 0], [0, 1]], [[1, 0], [0, -1]], [[0, 1], [1, 0]], [[0, -1], [-1, 0]],
)]


def _match_code(labels: np.ndarray, symbols: np.ndarray, target: PhaseTarget):
    """All placements (mismatches, T, offset) of the lattice labels on the target grid, best first:
    lattice index ``l`` goes to cell ``T l + offset`` (T one of the 8 rotations/reflections)."""
    nx, ny = target.grid
    out = []
    for T in _DIHEDRAL:
        L = labels @ T.T
        lo = L.min(axis=0)
        hi = L.max(axis=0)
        for ox in range(-lo[0], nx - hi[0]):
            for oy in range(-lo[1], ny - hi[1]):
                ij = L + (ox, oy)
                out.append((int(np.sum(target.code[ij[:, 1], ij[:, 0]] != symbols)), T, (ox, oy)))
    out.sort(key=lambda r: r[0])
    return out


def _trim_spurious_lines(labels: np.ndarray, points: np.ndarray, grid):
    """Drop outer lattice rows/columns that make the linked grid larger than the target's.

    A spurious candidate just outside the grid (a phase defect at the monitor's edge, a reflection)
    sits one pitch beyond the last row and gets linked as a row of its own. While the linked grid
    spans more lines than the target has (in either orientation) and has more points than the
    target, the outermost line with the fewest points is removed if it holds at most a quarter of a
    full line; otherwise nothing is trimmed and the size check reports the mismatch.

    labels : (K, 2) int lattice indices; points : (K, 2) px. Returns the kept (labels, points)."""
    big, small = max(grid), min(grid)
    n_dots = grid[0] * grid[1]
    while len(labels) > n_dots:
        span = np.sort(labels.max(axis=0) - labels.min(axis=0) + 1)
        if span[0] <= small and span[1] <= big:
            break
        span = labels.max(axis=0) - labels.min(axis=0) + 1
        lines = []
        for axis in (0, 1):
            for end in (labels[:, axis].min(), labels[:, axis].max()):
                members = labels[:, axis] == end
                lines.append((int(members.sum()), axis, members))
        count, axis, members = min(lines, key=lambda t: t[0])
        if count > max(1, span[1 - axis] // 4):   # a line across the grid holds span[1 - axis] dots
            break
        labels, points = labels[~members], points[~members]
    return labels, points


def _placement_is_unique(best: int, second: int, n_dots: int) -> bool:
    """Whether the best code placement (``best`` misread symbols) identifies the dots safely.

    A full code window differs from any other placement in >= 2 cells, so with no misread dot a
    margin of 2 suffices. Heavy defocus can misread a few dots' symbols (their phase offset is
    shifted unevenly); up to 10 % of the dots (at least 1) may disagree with the code, provided
    the next placement is at least twice as bad (margin >= 2 and >= 2 x best). The disagreeing
    dots are then dropped, never relabelled."""
    return best <= max(1, n_dots // 10) and second - best >= max(2, 2 * best)


def _uncoded_ids(lab, centres, target, mirrored):
    """Cell indices (K, 2) for a plain (uncoded), fully visible grid: the placement whose
    handedness matches ``mirrored`` and whose target x axis points closest to the image +x axis."""
    nx, ny = target.grid
    want_mirror = bool(mirrored)
    best = None
    for T in _DIHEDRAL:
        L = lab @ T.T
        L = L - L.min(axis=0)
        if L[:, 0].max() != nx - 1 or L[:, 1].max() != ny - 1:
            continue
        ids = L[:, 1] * nx + L[:, 0]
        H = _homography(target.dot_centres_px[ids], centres)
        J = _jacobian_h(H, target.dot_centres_px.mean(axis=0))
        if (np.linalg.det(J) < 0) != want_mirror:
            continue
        score = J[0, 0] / np.linalg.norm(J[:, 0])
        if best is None or score > best[0]:
            best = (score, L)
    if best is None:
        raise DetectionError(f"no placement of the plain grid matches the requested handedness (mirrored={want_mirror})")
    return best[1]
