"""Per-POI pixel masks (dic.correlation.subset_masks): pixel order, region, blocked pixels, validation."""
import numpy as np
import pytest

from dic.correlation.subset_masks import kept_fraction, region_pixel_mask, subset_offsets, subset_pixel_masks


def test_mask_row_order_is_row_major_about_the_rounded_poi():
    region = np.zeros((20, 30), dtype=bool)
    region[9, 12] = True  # one pixel: offset (+2, -1) from the POI (10, 10)
    m = subset_pixel_masks([[10.0, 10.0], [9.6, 10.4]], 5, region)
    assert m.shape == (2, 25) and m.dtype == bool
    # row-major about (X, Y) = (10, 10): entry (j + r) * S + (i + r) with i = 2, j = -1
    expected = np.zeros(25, bool)
    expected[(-1 + 2) * 5 + (2 + 2)] = True
    assert np.array_equal(m[0], expected)
    assert np.array_equal(m[1], expected)  # 9.6 -> 10, 10.4 -> 10
    di, dj = subset_offsets(5)
    assert (di[(1) * 5 + 4], dj[(1) * 5 + 4]) == (2, -1)


def test_half_pixel_positions_round_away_from_zero_like_the_kernels():
    region = np.zeros((10, 10), dtype=bool)
    region[5, 5] = True
    m = subset_pixel_masks([[4.5, 4.5]], 3, region)  # centre (5, 5): the middle entry
    assert m[0].nonzero()[0].tolist() == [4]


def test_outside_the_image_is_dropped_with_a_region_and_blocked_pixels_dropped():
    region = np.ones((8, 8), dtype=bool)
    m = subset_pixel_masks([[0.0, 0.0]], 3, region)
    assert m[0].reshape(3, 3).tolist() == [[False, False, False], [False, True, True], [False, True, True]]
    blocked = np.zeros((1, 9), bool)
    blocked[0, 4] = True
    m2 = subset_pixel_masks([[4.0, 4.0]], 3, region, blocked=blocked)
    assert m2[0].sum() == 8 and not m2[0, 4]
    assert np.all(subset_pixel_masks([[4.0, 4.0]], 3, None))
    assert subset_pixel_masks([[4.0, 4.0]], 3, None, blocked=blocked)[0].sum() == 8
    assert kept_fraction(m2)[0] == pytest.approx(8 / 9)


def test_region_pixel_mask_box_masks_nothing_polygon_rasterised():
    assert region_pixel_mask((1, 1, 5, 5), (10, 10)) is None
    assert region_pixel_mask(None, (10, 10)) is None
    poly = region_pixel_mask([(2, 2), (6, 2), (6, 5), (2, 5)], (10, 10))
    assert poly.shape == (10, 10) and poly.sum() == 5 * 4  # x 2..6, y 2..5 (edges inside)
    arr = np.zeros((10, 10), bool)
    arr[3, 4] = True
    assert np.array_equal(region_pixel_mask(arr, (10, 10)), arr)


def test_invalid_inputs_are_refused_with_clear_messages():
    with pytest.raises(ValueError, match="subset"):
        subset_pixel_masks([[1.0, 1.0]], 4, None)
    with pytest.raises(ValueError, match="region_mask"):
        subset_pixel_masks([[1.0, 1.0]], 3, np.ones(5, bool))
    with pytest.raises(ValueError, match="blocked must have shape"):
        subset_pixel_masks([[1.0, 1.0]], 3, None, blocked=np.zeros((1, 8), bool))
    with pytest.raises(ValueError, match="blocked must be a bool"):
        subset_pixel_masks([[1.0, 1.0]], 3, None, blocked=np.zeros((1, 9), int))
