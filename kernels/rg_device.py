"""Counted IC-GN: the IC-GN launch of a reliability-guided wave sized without reading the count back.

A wave's candidates (:func:`kernels.propagation.rg_wave`) are counted on the device
(``counts[w, 0]``, ``w = ctl[0]``). :func:`icgn_counted` launches IC-GN over the capacity of the
gathered buffers (N rows, the most candidates a wave can have) and every thread ``t >= counts[w, 0]``
returns at once: the launch needs no host value, so a whole frame's waves can be captured as one CUDA
graph (``wp.capture_while``, :func:`dic.correlation.reliability_guided`).

The per-POI bodies are :func:`kernels.icgn.icgn_point_1st` / :func:`kernels.icgn.icgn_point_2nd`
compiled with kernels.icgn's module options (FMA contraction on the CPU, its CUDA block size) and
its launch bounds: each candidate gets bitwise the result of :func:`kernels.icgn.icgn` on the same
gathered rows.
"""
from __future__ import annotations

import warp as wp

from ._common import icgn_module_options
from ._launch import cuda_launch_bounds, launch_1d
from .checks import positive_float
from .icgn import (
    CurrentCoefficients,
    CurrentImage,
    IcgnOutputs,
    IcgnResult,
    ReferenceSubsets,
    SubsetTable,
    check_max_iter,
    icgn_point_1st,
    icgn_point_2nd,
)

# the same options as kernels.icgn: the same code for the same body (bitwise), one block size per module
wp.set_module_options(icgn_module_options("_icgn_2nd"))


def _make_icgn_counted(order: int):
    """The counted IC-GN kernel of one order: rows ``0 .. counts[ctl[0], 0] - 1`` with the per-POI body."""
    icgn_point = icgn_point_1st if order == 1 else icgn_point_2nd

    def icgn_counted_kernel(offset: int, ctl: wp.array(dtype=wp.int32), counts: wp.array2d(dtype=wp.int32),
                            sub: SubsetTable, cur: CurrentCoefficients, guess: wp.array2d(dtype=float), max_iter: int,
                            tol: float, out: IcgnOutputs):
        t = wp.tid() + offset
        if t >= counts[ctl[0], 0]:
            return
        icgn_point(t, sub, cur, guess, max_iter, tol, out)

    name = "_icgn_counted_1st" if order == 1 else "_icgn_counted_2nd"
    icgn_counted_kernel.__name__ = icgn_counted_kernel.__qualname__ = name
    return wp.kernel(icgn_counted_kernel, launch_bounds=cuda_launch_bounds(name))


_icgn_counted_1st = _make_icgn_counted(1)
_icgn_counted_2nd = _make_icgn_counted(2)


def icgn_counted(gathered: ReferenceSubsets, current: CurrentImage, guess: wp.array, max_iter: int, tol: float,
                 out: IcgnResult, ctl: wp.array, counts: wp.array) -> None:
    """IC-GN of rows ``0 .. counts[ctl[0], 0] - 1`` of ``gathered`` (:func:`kernels.icgn.subset_buffers`,
    filled by the wave's bookkeeping) from ``guess`` into the same rows of ``out``, in one launch over
    all ``gathered.n_points`` rows (threads past the count return): no host value of the count is needed.
    ``ctl`` (int32, >= 1) holds the wave index, ``counts`` (int32, (W, 2)) the per-wave counts."""
    if not isinstance(gathered, ReferenceSubsets) or not isinstance(current, CurrentImage):
        raise ValueError("gathered must be ReferenceSubsets (subset_buffers()) and current a CurrentImage")
    dev = gathered.device
    if current.device != dev:
        raise ValueError(f"current is on {current.device} but the subsets are on {dev}")
    if current.shape != gathered.reference.shape:
        raise ValueError(f"current image has shape {current.shape} but the reference has shape "
                         f"{gathered.reference.shape}")
    n, k = gathered.n_points, 6 * gathered.order
    if guess.shape[0] < n or guess.shape[1] != k or out.params.shape[0] < n or out.params.shape[1] != k:
        raise ValueError(f"guess and out need at least {n} rows of {k} parameters")
    for name, a in (("ctl", ctl), ("counts", counts)):
        if not isinstance(a, wp.array) or a.dtype != wp.int32 or str(a.device) != dev:
            raise ValueError(f"{name} must be an int32 Warp array on {dev}")
    if counts.ndim != 2 or counts.shape[1] != 2:
        raise ValueError(f"counts must have shape (waves, 2), got {counts.shape}")
    max_iter = check_max_iter(max_iter)
    tol = positive_float(tol, "tol", detail=" of pixels")
    kernel = _icgn_counted_1st if gathered.order == 1 else _icgn_counted_2nd
    launch_1d(kernel, n, [0, ctl, counts, gathered.table, current.coefficients(), guess, int(max_iter),
                          float(tol), out.outputs], dev, offset_index=0, min_chunk=64)
