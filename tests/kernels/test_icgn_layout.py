"""IC-GN on the plain padded coefficients (``layout="plain"``) gives the bits of the row-expanded
layout ("rows4"), for both shape-function orders, and skips the 4x expanded buffer."""
import numpy as np
import pytest
import warp as wp

from dic.synth import speckle_pair
from kernels.icgn import (
    LAYOUTS,
    CurrentImage,
    check_layout,
    default_layout,
    icgn,
    prepare_current,
    prepare_reference,
    prepare_subsets,
)
from kernels.interp import bspline_coefficients, rows4_view


def _field(x, y):
    # a shift plus a gentle strain and curvature: 2nd-order terms are exercised, and some POIs
    # near the border leave the image (OUT_OF_BOUNDS) so that every status path is compared
    return 2.3 + 0.004 * (x - 48) + 2e-5 * (y - 40) ** 2, -1.7 + 0.003 * (y - 40) - 0.002 * (x - 48)


@pytest.fixture(scope="module")
def pair():
    ref, cur = speckle_pair((88, 104), _field, seed=7, noise_sigma=1.0)
    ys, xs = np.mgrid[3:86:5, 4:101:5]
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    pts[::3] += 0.37  # sub-pixel POIs (deltas not zero)
    return ref, cur, pts


@pytest.mark.parametrize("order", [1, 2])
def test_plain_layout_is_bitwise_rows4(pair, order):
    ref, cur, pts = pair
    subsets = prepare_subsets(prepare_reference(ref, device="cpu"), pts, subset=15, order=order)
    k = 6 if order == 1 else 12
    guess = np.zeros((len(pts), k))
    guess[:, 0], guess[:, k // 2] = 2.0, -2.0
    rows4 = prepare_current(cur, device="cpu", layout="rows4")
    plain = prepare_current(cur, device="cpu", layout="plain")
    assert rows4.layout == "rows4" and plain.layout == "plain" and plain.rows4 is None
    a = icgn(subsets, rows4, guess, max_iter=40).numpy()
    b = icgn(subsets, plain, guess, max_iter=40).numpy()
    # the rows4 current also holds its plain coefficients: either kernel runs on it
    c = icgn(subsets, rows4, guess, max_iter=40, layout="plain").numpy()
    st = a["status"]
    assert (st == 0).sum() > len(pts) // 2, "too few converged POIs to compare"
    assert len(np.unique(st)) >= 2, "the pair should exercise more than one status"
    for other in (b, c):
        np.testing.assert_array_equal(other["status"], a["status"])
        np.testing.assert_array_equal(other["iterations"], a["iterations"])
        # bitwise: compare the raw bits (NaN-safe)
        np.testing.assert_array_equal(other["params"].view(np.int32), a["params"].view(np.int32))
        np.testing.assert_array_equal(other["zncc"].view(np.int32), a["zncc"].view(np.int32))


def test_plain_layout_from_image_and_padded(pair):
    ref, cur, pts = pair
    subsets = prepare_subsets(prepare_reference(ref, device="cpu"), pts, subset=15, order=1)
    a = icgn(subsets, cur).numpy()  # an image: the device's default layout
    b = icgn(subsets, cur, layout="plain").numpy()
    c = icgn(subsets, prepare_current(bspline_coefficients(cur, device="cpu"), layout="plain")).numpy()
    for other in (b, c):
        np.testing.assert_array_equal(other["params"].view(np.int32), a["params"].view(np.int32))
        np.testing.assert_array_equal(other["status"], a["status"])


def test_plain_layout_skips_the_expanded_buffer(pair):
    _, cur, _ = pair
    plain = prepare_current(cur, device="cpu", layout="plain")
    rows4 = prepare_current(cur, device="cpu", layout="rows4")
    h, w = cur.shape
    n = (h + 4) * (w + 4)
    assert plain.rows4 is None
    assert rows4.rows4.shape == (n,) and rows4.rows4.dtype == wp.vec4 and rows4.rows4.strides == (16,)
    # the plain layout reads the coefficients in place: a vec4 view with a 4-byte stride, entry k
    # starting at float k-1 of the padded coefficients (no 4x copy)
    assert plain.plain.dtype == wp.vec4 and plain.plain.strides == (4,) and plain.plain.shape == (n - 2,)
    assert plain.plain.ptr == plain.coef.ptr - 4
    # reuse: a plain out keeps its coefficient buffer and builds no expanded one
    again = prepare_current(cur, device="cpu", out=plain, layout="plain")
    assert again.coef.ptr == plain.coef.ptr and again.rows4 is None
    # a rows4 out reused for rows4 keeps both buffers
    again4 = prepare_current(cur, device="cpu", out=rows4)
    assert again4.rows4.ptr == rows4.rows4.ptr and again4.coef.ptr == rows4.coef.ptr


def test_rows4_view_matches_expand_rows4_and_keeps_coefficients_alive(pair):
    import gc

    ref, cur, pts = pair
    subsets = prepare_subsets(prepare_reference(ref, device="cpu"), pts, subset=15, order=2)
    a = icgn(subsets, prepare_current(cur, device="cpu")).numpy()
    view = rows4_view(bspline_coefficients(cur, device="cpu"))  # the PaddedImage is dropped here
    gc.collect()
    junk = [wp.array(np.full(view.shape[0] + 2, 7.0, np.float32), device="cpu") for _ in range(4)]
    b = icgn(subsets, CurrentImage(None, cur.shape, "cpu", None, view)).numpy()
    del junk
    np.testing.assert_array_equal(b["params"].view(np.int32), a["params"].view(np.int32))
    np.testing.assert_array_equal(b["iterations"], a["iterations"])
    with pytest.raises(ValueError, match="PaddedImage"):
        rows4_view(np.zeros((8, 8), np.float32))


def test_layout_defaults_and_checks(pair):
    ref, cur, pts = pair
    assert LAYOUTS == ("rows4", "plain")
    assert default_layout("cpu") == "rows4"
    assert check_layout(None, "cpu") == "rows4" and check_layout("plain") == "plain"
    for bad in ("vec4", 4, "", "Plain"):
        with pytest.raises(ValueError, match="layout must be one of"):
            check_layout(bad)
        with pytest.raises(ValueError, match="layout must be one of"):
            prepare_current(cur, device="cpu", layout=bad)
    subsets = prepare_subsets(prepare_reference(ref, device="cpu"), pts, subset=15, order=1)
    plain = prepare_current(cur, device="cpu", layout="plain")
    with pytest.raises(ValueError, match='layout="rows4" needs'):
        icgn(subsets, plain, layout="rows4")
    with pytest.raises(ValueError, match="layout must be one of"):
        icgn(subsets, plain, layout="tiles")
    bare = CurrentImage(None, plain.shape, "cpu")
    with pytest.raises(ValueError, match='layout="plain" needs'):
        icgn(subsets, bare)


def test_rows4_only_readers_refuse_a_plain_current(pair):
    from bench.icgn_tiled import icgn_tiled
    from kernels.frames import icgn_batch

    ref, cur, pts = pair
    subsets = prepare_subsets(prepare_reference(ref, device="cpu"), pts, subset=15, order=1)
    plain = prepare_current(cur, device="cpu", layout="plain")
    with pytest.raises(ValueError, match='layout="plain"'):
        icgn_batch(subsets, [plain])
    with pytest.raises(ValueError, match='layout="plain"'):
        icgn_tiled(subsets, plain)
