"""IC-GN over the kept pixels of each subset (kernels.icgn_masked): exact truth and agreement of its paths."""
import numpy as np
import pytest
import warp as wp

from dic.synth import speckle_pair
from kernels.conventions import Status
from kernels.frames import FrameTracker
from kernels.icgn import (
    REFDATA_1ST,
    gather_subsets,
    icgn,
    prepare_current,
    prepare_reference,
    prepare_subsets,
    subset_buffers,
)
from kernels.icgn_masked import prepare_subsets_masked

SHAPE = (96, 128)
SUBSET = 21
SHIFT = (0.4, -0.3)  # the specimen's exact translation (px)


@pytest.fixture(scope="module")
def half_moving():
    """A speckle translated by SHIFT on the left of x = 64 and a *stationary* speckle on the right: the right
    part of a straddling subset pulls its warp towards zero unless it is masked out."""
    ref, cur = speckle_pair(SHAPE, SHIFT, noise_sigma=0.5, seed=5, device="cpu")
    still_ref, still_cur = speckle_pair(SHAPE, (0.0, 0.0), noise_sigma=0.5, seed=9, radius=3.0, device="cpu")
    ref, cur = ref.copy(), cur.copy()
    ref[:, 64:] = still_ref[:, 64:]
    cur[:, 64:] = still_cur[:, 64:]
    pts = np.array([[x, y] for y in (40.0, 48.0, 56.0) for x in (52.0, 56.0, 58.0)])  # subsets reach x = 62..68
    yy, xx = np.mgrid[0:SUBSET, 0:SUBSET] - SUBSET // 2
    # the left side up to x = 60: the cubic B-spline values and gradients of a kept pixel reach 2 px (plus the
    # shift, plus the prefilter's decaying ringing) towards the seam at x = 63.5, whose right side does not move
    masks = np.stack([(p[0] + xx <= 60).ravel() for p in pts])
    return ref, cur, pts, masks


def test_masked_subsets_recover_the_translation_the_unmasked_miss(half_moving):
    ref, cur, pts, masks = half_moving
    reference = prepare_reference(ref, device="cpu")
    for order in (1, 2):
        k = 6 * order
        v_col = k // 2
        plain = icgn(prepare_subsets(reference, pts, SUBSET, order), cur).numpy()
        masked = icgn(prepare_subsets_masked(reference, pts, SUBSET, order, pixel_mask=masks, min_kept_fraction=0.3),
                      cur).numpy()
        assert np.all(masked["status"] == int(Status.CONVERGED))
        err_masked = np.hypot(masked["params"][:, 0] - SHIFT[0], masked["params"][:, v_col] - SHIFT[1])
        err_plain = np.hypot(plain["params"][:, 0] - SHIFT[0], plain["params"][:, v_col] - SHIFT[1])
        # bounds: 0.5 GL noise, >= 30 % of a 21 px subset kept: well under 0.02 px; the stationary speckle
        # pulls the unmasked subsets towards zero motion (a few hundredths to a tenth of a px)
        assert err_masked.max() < 0.02, (order, err_masked)
        rms_masked, rms_plain = np.sqrt(np.mean(err_masked ** 2)), np.sqrt(np.mean(err_plain ** 2))
        assert err_plain.max() > 0.05 and rms_masked < rms_plain / 3, (order, err_plain, err_masked)


def test_reference_mean_and_norm_are_those_of_the_kept_pixels(half_moving):
    ref, _, pts, masks = half_moving
    subsets = prepare_subsets_masked(prepare_reference(ref, device="cpu"), pts, SUBSET, 1, pixel_mask=masks,
                                     min_kept_fraction=0.3)
    table = subsets.refdata.numpy()
    r = SUBSET // 2
    for n, (x, y) in enumerate(pts.astype(int)):
        f = ref[y - r:y + r + 1, x - r:x + r + 1].astype(np.float64).ravel()[masks[n]]
        assert table[n, REFDATA_1ST.fmean] == pytest.approx(f.mean(), rel=1e-6)
        assert table[n, REFDATA_1ST.fnorm] == pytest.approx(np.sqrt(np.sum((f - f.mean()) ** 2)), rel=1e-5)
    assert np.array_equal(subsets.mask.kept.numpy(), masks.sum(axis=1))


def test_a_full_mask_gives_the_unmasked_results(half_moving):
    ref, cur, pts, masks = half_moving
    reference = prepare_reference(ref, device="cpu")
    full = np.ones_like(masks)
    for order in (1, 2):
        plain = icgn(prepare_subsets(reference, pts, SUBSET, order), cur).numpy()
        masked = icgn(prepare_subsets_masked(reference, pts, SUBSET, order, pixel_mask=full), cur).numpy()
        assert np.array_equal(plain["status"], masked["status"])
        assert np.abs(plain["params"] - masked["params"]).max() < 1e-5  # the same sums; float32 rounding only


def test_too_few_pixels_has_its_own_status_and_bad_masks_are_refused(half_moving):
    ref, cur, pts, masks = half_moving
    reference = prepare_reference(ref, device="cpu")
    few = np.zeros_like(masks)
    few[:, : SUBSET * SUBSET // 2] = True  # 220 of 441 pixels: below half
    sub = prepare_subsets_masked(reference, pts, SUBSET, 1, pixel_mask=few, min_kept_fraction=0.5)
    assert np.all(sub.status.numpy() == int(Status.TOO_FEW_PIXELS))
    assert np.all(icgn(sub, cur).numpy()["status"] == int(Status.TOO_FEW_PIXELS))
    sub = prepare_subsets_masked(reference, pts, SUBSET, 1, pixel_mask=few, min_kept_fraction=0.49)
    assert np.all(sub.status.numpy() == int(Status.CONVERGED))
    with pytest.raises(ValueError, match="pixel_mask must have shape"):
        prepare_subsets_masked(reference, pts, SUBSET, 1, pixel_mask=masks[:, :-1])
    with pytest.raises(ValueError, match="min_kept_fraction must be a number in"):
        prepare_subsets_masked(reference, pts, SUBSET, 1, pixel_mask=masks, min_kept_fraction=0.0)
    with pytest.raises(ValueError, match="0/1 integers"):
        prepare_subsets_masked(reference, pts, SUBSET, 1, pixel_mask=masks.astype(np.int32) * 2)


@pytest.mark.parametrize("order", [1, 2])
def test_indexed_and_frame_paths_give_the_same_bits(half_moving, order):
    ref, cur, pts, masks = half_moving
    reference = prepare_reference(ref, device="cpu")
    subsets = prepare_subsets_masked(reference, pts, SUBSET, order, pixel_mask=masks, min_kept_fraction=0.3)
    current = prepare_current(cur, device="cpu")
    whole = icgn(subsets, current).numpy()
    idx = np.array([7, 2, 5], dtype=np.int32)
    sub = gather_subsets(subsets, wp.array(idx, dtype=wp.int32, device="cpu"), idx.size, subset_buffers(subsets))
    part = icgn(sub, current).numpy()
    for key in ("params", "zncc", "status", "iterations"):
        assert np.array_equal(part[key], whole[key][idx]), key
    framed = FrameTracker(subsets, np.float32).track(cur.astype(np.float32))
    for key in ("params", "zncc", "status", "iterations"):
        assert np.array_equal(framed[key], whole[key]), key
