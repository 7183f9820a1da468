"""Grid linking of dot candidates (calibration.detect.lattice._grow_lattice): robust to a spurious candidate."""
import numpy as np

from calibration.detect.lattice import _grow_lattice


def _grid(nx=8, ny=4, pitch=110.0, angle_deg=7.0):
    a = np.radians(angle_deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    ij = np.array([(i, j) for j in range(ny) for i in range(nx)], float)
    return ij, (ij * pitch) @ R.T + (600.0, 400.0)


def _labels_match_grid(labels, ij):
    """Labels are the grid indices up to a rotation/reflection and an offset: check through the
    affine map between them (exact integers for a correct linking)."""
    X = np.c_[labels, np.ones(len(labels))]
    coef, *_ = np.linalg.lstsq(X, ij, rcond=None)
    return np.allclose(X @ coef, ij, atol=1e-9) and np.allclose(np.abs(np.linalg.det(coef[:2])), 1.0)


def test_every_dot_linked_with_a_spurious_candidate_at_the_middle():
    ij, pts = _grid()
    # a phase defect 25 px from a dot, placed where the median of the candidates falls: it is the
    # first seed tried, and its nearest neighbour is not a lattice step
    centre = np.median(pts, axis=0)
    spurious = centre + (3.0, 2.0)
    cands = np.vstack([pts, spurious])
    labels, done = _grow_lattice(cands, 4 * len(pts))
    assert done[: len(pts)].all(), f"only {done[: len(pts)].sum()} of {len(pts)} dots linked"
    assert not done[-1]
    assert _labels_match_grid(labels[: len(pts)], ij)


def test_clean_grid_linked():
    ij, pts = _grid(angle_deg=-20.0)
    labels, done = _grow_lattice(pts, 4 * len(pts))
    assert done.all() and _labels_match_grid(labels, ij)


def test_code_placement_rule():
    """The code decides ids only when the best placement is clearly unique (see _placement_is_unique)."""
    from calibration.detect.lattice import _placement_is_unique

    assert _placement_is_unique(0, 2, 18)          # a full code window: unique
    assert _placement_is_unique(1, 3, 18)          # one misread dot, next placement 3 cells off
    assert not _placement_is_unique(1, 2, 18)      # one misread dot, next placement 2 cells off: ambiguous
    assert _placement_is_unique(2, 28, 32)         # two misread of 32 (heavy defocus), next 28: unique
    assert not _placement_is_unique(2, 28, 18)     # two misread of 18 is more than 10 %
    assert not _placement_is_unique(3, 5, 32)      # margin below 2 x best
    assert not _placement_is_unique(13, 13, 22)


def test_spurious_row_trimmed():
    """A candidate one pitch beyond the last row is linked as a 5th row of an 8 x 4 grid: trimmed."""
    from calibration.detect.lattice import _trim_spurious_lines

    ij, pts = _grid()
    extra_ij = np.array([[3, 4]])
    labels = np.vstack([ij.astype(int), extra_ij])
    points = np.vstack([pts, pts[3] + 4 * (pts[8] - pts[0])])
    kept_labels, kept_points = _trim_spurious_lines(labels, points, (8, 4))
    assert len(kept_labels) == 32 and not np.any(np.all(kept_labels == (3, 4), axis=1))
    # a genuine grid is left alone, also when seen rotated (labels transposed)
    same, _ = _trim_spurious_lines(ij.astype(int)[:, ::-1], pts, (8, 4))
    assert len(same) == 32
