"""dic.correlation.order_stats.percentile: the bits and dtype of np.percentile, on the data it is used for."""
import numpy as np
import pytest

from dic.correlation.order_stats import percentile


def _arrays(rng):
    n = 250_000
    yield "uniform", rng.random(n)
    yield "mostly zero (background)", np.where(rng.random(n) < 0.8, 0.0, rng.random(n) * 60.0)
    yield "few levels (ties)", rng.integers(0, 5, n).astype(float)
    yield "normal", rng.normal(size=n) * 1e3
    yield "constant", np.full(n, 3.0)
    image = np.zeros((600, 700))
    image[100:400, 200:600] = rng.random((300, 400)) * 60.0
    yield "image with a dark border (2-D)", image
    yield "sorted", np.sort(rng.random(n))
    # a sample unlike the whole (every value the strided sample draws is large): the bracket misses, and the
    # whole array is partitioned
    odd = rng.random(n)
    odd[:: n // 20_000] = 100.0
    yield "unrepresentative sample", odd


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("q", [95.0, 0.0, 100.0, 50.0, 37.3, np.float64(95.0), 7, [0.5, 99.5], [5, 95], (50.0,)])
def test_percentile_equals_numpy_bitwise(dtype, q):
    rng = np.random.default_rng(1)
    for name, a in _arrays(rng):
        a = a.astype(dtype)
        expected, got = np.percentile(a, q), percentile(a, q)
        assert np.asarray(got).dtype == np.asarray(expected).dtype, name
        assert np.shape(got) == np.shape(expected), name
        assert type(got) is type(expected), name
        np.testing.assert_array_equal(np.asarray(got), np.asarray(expected), err_msg=name)


def test_percentile_hands_other_inputs_to_numpy():
    rng = np.random.default_rng(2)
    small = rng.random(50)
    assert percentile(small, 95.0) == np.percentile(small, 95.0)
    ints = rng.integers(0, 255, 200_000)
    assert percentile(ints, 95.0) == np.percentile(ints, 95.0)
    with_nan = rng.random(200_000)
    with_nan[7] = np.nan
    assert np.isnan(percentile(with_nan, 95.0))
    with pytest.raises(ValueError):
        percentile(rng.random(200_000), 101.0)


def test_percentile_refuses_what_is_not_numbers():
    with pytest.raises(ValueError, match="non-empty array of real numbers"):
        percentile(np.array(["a", "b"]), 50.0)
    with pytest.raises(ValueError, match="non-empty array of real numbers"):
        percentile(np.zeros(0), 50.0)
