"""The shared argument checks (kernels/checks.py): accepted values, canonical types and messages."""
import numpy as np
import pytest

from kernels.checks import (
    as_points,
    in_range,
    non_negative_int,
    odd_int,
    positive_float,
    positive_int,
    unit_interval,
)


def test_as_points_returns_contiguous_float64():
    pts = as_points([[1, 2], [3, 4]])
    assert pts.dtype == np.float64 and pts.flags.c_contiguous and pts.shape == (2, 2)
    same = np.ascontiguousarray([[1.5, 2.5]])
    assert as_points(same) is same  # no copy when nothing changes
    assert as_points(np.zeros((0, 3)), ncols=3, allow_empty=True).shape == (0, 3)
    assert np.isnan(as_points([[np.nan, 1.0]], finite=False)[0, 0])


@pytest.mark.parametrize("points, kw, message", [
    ([1.0, 2.0, 3.0], {}, r"points must have shape \(N, 2\), an array of \(x, y\), got shape \(3,\)"),
    (np.zeros((4, 2)), {"ncols": 3, "name": "points_world"}, r"points_world must have shape \(N, 3\)"),
    (np.zeros((0, 2)), {}, "points is empty"),
    ([[1.0, np.inf]], {}, "points contains NaN or infinite values"),
    ([["a", "b"]], {}, "must be numeric"),
    (np.zeros((2, 2), bool), {}, "must be numeric"),
    ([[0.0, 0.0], [10.0, 2.0]], {"shape": (5, 8), "image_name": "left image"},
     r"1 point\(s\) lie outside the 8x5 px left image, e.g. point 1 at \(10, 2\)"),
])
def test_as_points_rejects(points, kw, message):
    with pytest.raises(ValueError, match=message):
        as_points(points, **kw)


def test_as_points_inside_image_uses_pixel_edges():
    as_points([[-0.5, -0.5], [7.5, 4.5]], shape=(5, 8))  # the outer edges of the corner pixels


def test_integers():
    assert positive_int(np.int64(3), "n") == 3 and type(positive_int(np.int64(3), "n")) is int
    assert positive_int(4.0, "samples", integral_float=True) == 4
    assert non_negative_int(0, "levels") == 0
    assert odd_int(21, "subset") == 21
    for bad in (0, -1, True, 2.0, "3", None):
        with pytest.raises(ValueError, match=r"step must be a positive integer number of pixels, got"):
            positive_int(bad, "step", detail=" number of pixels")
    with pytest.raises(ValueError, match="samples must be a positive integer, got 2.5"):
        positive_int(2.5, "samples", integral_float=True)
    with pytest.raises(ValueError, match="steps must be an integer >= 3, got 2"):
        positive_int(2, "steps", minimum=3)
    with pytest.raises(ValueError, match=r"radius must be a non-negative integer \(pixels\), got -1"):
        non_negative_int(-1, "radius", detail=" (pixels)")
    for bad in (20, 1, 21.0, False):
        with pytest.raises(ValueError, match=r"subset must be an odd integer >= 3 \(e.g. 21\)"):
            odd_int(bad, "subset", detail=" (e.g. 21)")
    assert odd_int(5.0, "strain window", integral_float=True) == 5


def test_reals():
    assert positive_float(np.float32(0.5), "tol") == 0.5 and positive_float(np.array(2.0), "x") == 2.0
    assert positive_float(np.inf, "f_number", allow_inf=True) == np.inf
    for bad in (0.0, -1.0, np.nan, np.inf, True, "1", None, [1.0]):
        with pytest.raises(ValueError, match="tol must be a positive finite number of pixels, got"):
            positive_float(bad, "tol", detail=" of pixels")
    assert in_range(0.5, 0.0, 1.0, "reflectance") == 0.5 and unit_interval(1, "coverage") == 1.0
    with pytest.raises(ValueError, match=r"reflectance must be in \[0.0, 1.0\], got 1.5"):
        in_range(1.5, 0.0, 1.0, "reflectance")
    with pytest.raises(ValueError, match=r"min_coverage must be in \[0, 1\], got -0.1"):
        unit_interval(-0.1, "min_coverage")
    with pytest.raises(ValueError, match=r"x must be a number in \[0, 1\], got 'a'"):
        unit_interval("a", "x")
    with pytest.raises(ValueError, match="must be in"):
        unit_interval(np.nan, "x")
