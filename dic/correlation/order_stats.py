"""Percentiles of large images, bit for bit those of :func:`numpy.percentile`, without sorting the whole image.

``np.percentile`` copies its input and partitions all of it (and at its minimum and maximum); on a
1920 x 1200 image that is mostly one grey level (a dark background around a specimen) the partition takes
0.1-0.3 s, ten times its time on varied data. :func:`percentile` finds the two order statistics it needs among
the few values near them (the rest are only counted), then interpolates them as NumPy does ("linear", the
default method): the same values, in a few milliseconds. Used for the texture threshold of
:mod:`.plausibility` and the 8-bit scaling of :mod:`.features`.
"""
from __future__ import annotations

import numpy as np

__all__ = ["percentile"]

#: about this many values are drawn to bracket the wanted order statistics
_SAMPLE = 20_000
#: the bracket's half width, as a fraction of the sample (wide enough that it holds the order statistic
#: nearly always; when it does not, the whole array is partitioned, as NumPy does)
_BRACKET = 0.01


def _order_stats(a: np.ndarray, ks: list[int]) -> np.ndarray:
    """The values of sorted ``a`` (1-D, finite) at the indices ``ks``: each run of neighbouring indices is found
    among the values of a bracket around it, drawn from a sample (the values below it only counted)."""
    n = a.size
    if n <= 4 * _SAMPLE:
        return np.partition(a, ks)[ks]
    sample = np.sort(a[:: max(1, n // _SAMPLE)])
    m = sample.size
    out = {}
    groups = [[ks[0]]]
    for k in ks[1:]:
        if k - groups[-1][-1] <= 1:
            groups[-1].append(k)
        else:
            groups.append([k])
    for group in groups:
        lo = sample[max(0, int(np.floor((group[0] / (n - 1) - _BRACKET) * (m - 1))))]
        hi = sample[min(m - 1, int(np.ceil((group[-1] / (n - 1) + _BRACKET) * (m - 1))))]
        below = int(np.count_nonzero(a < lo))
        inside = a[(a >= lo) & (a <= hi)]
        if below <= group[0] and below + inside.size > group[-1]:
            local = [k - below for k in group]
            values = np.partition(inside, local)[local]
        else:  # the bracket missed (a sample unlike the whole): partition everything, as NumPy does
            values = np.partition(a, group)[group]
        out.update(zip(group, values))
    return np.array([out[k] for k in ks], dtype=a.dtype)


def percentile(values, q):
    """``np.percentile(values, q)`` (method "linear") of a finite float32 or float64 array, the same bits and dtype.

    ``values``: any shape (all of it is used); ``q``: a number or a sequence of numbers in [0, 100].
    Arrays of another dtype, small arrays and arrays holding NaN or infinities go to ``np.percentile`` itself.
    """
    a = np.asarray(values)
    if a.dtype.kind not in "biuf" or a.size == 0:
        raise ValueError(f"values must be a non-empty array of real numbers, got dtype {a.dtype} and size {a.size}")
    if a.dtype not in (np.float32, np.float64) or a.size <= 4 * _SAMPLE:
        return np.percentile(a, q)
    flat = a.reshape(-1)
    if not (np.isfinite(flat.min()) and np.isfinite(flat.max())):
        return np.percentile(a, q)
    # NumPy's steps (numpy/lib/_function_base_impl.py: percentile, _quantile, _get_indexes, _lerp), method "linear"
    weak_q = type(q) in (int, float)  # a Python number: the result keeps the values' dtype
    quantiles = np.true_divide(q, 100)
    if np.ndim(quantiles) > 1 or not np.all((quantiles >= 0) & (quantiles <= 1)):
        return np.percentile(a, q)
    n = flat.size
    virtual = np.asanyarray((n - 1) * quantiles)
    previous = np.asanyarray(np.floor(virtual))
    nxt = np.asanyarray(previous + 1)
    above = virtual >= n - 1
    if above.any():
        previous[above] = -1
        nxt[above] = -1
    below = virtual < 0
    if below.any():
        previous[below] = 0
        nxt[below] = 0
    previous, nxt = previous.astype(np.intp), nxt.astype(np.intp)
    gamma = np.asanyarray(virtual - previous, dtype=virtual.dtype)
    previous, nxt = previous % n, nxt % n
    ks = sorted(set(previous.ravel().tolist()) | set(nxt.ravel().tolist()))
    stats = dict(zip(ks, _order_stats(flat, ks)))
    lo = np.array([stats[k] for k in previous.ravel()], dtype=flat.dtype).reshape(previous.shape)
    hi = np.array([stats[k] for k in nxt.ravel()], dtype=flat.dtype).reshape(nxt.shape)
    if weak_q:  # Python-float weight: the arithmetic in the values' dtype
        g, lo, hi = float(gamma), lo[()], hi[()]
        diff = hi - lo
        return hi - diff * (1 - g) if g >= 0.5 else lo + diff * g
    diff = hi - lo
    result = np.add(lo, diff * gamma, out=...)
    np.subtract(hi, diff * (1 - gamma), out=result, where=gamma >= 0.5, casting="unsafe", dtype=type(result.dtype))
    return result[()] if result.ndim == 0 else result
