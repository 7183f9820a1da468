"""What the Warp modules of the IC-GN family share: their module options and the status codes as Warp constants.

One definition each, imported by :mod:`kernels.icgn`, :mod:`kernels.frames`, :mod:`kernels.rg_device`,
:mod:`kernels.icgn_robust`, :mod:`kernels.propagation` (and the prototype ``bench/icgn_tiled.py``):

* :func:`icgn_module_options`: the options every module that compiles the IC-GN per-POI bodies sets
  with ``wp.set_module_options`` (FMA contraction across statements on the CPU, no backward pass, the
  module's CUDA block size). The per-POI bodies give the same bits in every kernel only when every
  module compiles them with the same options.
* ``ST_*``: :class:`kernels.conventions.Status` as ``wp.constant`` (a kernel cannot read an ``IntEnum``).
"""
from __future__ import annotations

import warp as wp

from ._launch import cuda_block_dim
from .conventions import Status

#: the Warp module options of every module that compiles the IC-GN per-POI bodies, less the block size
#: (:func:`icgn_module_options` adds it). FMA contraction across statements: ~15 % faster CPU passes,
#: and FMA only improves rounding.
ICGN_MODULE_OPTIONS = {"enable_backward": False, "cpu_compiler_flags": "-march=native -ffp-contract=fast"}


def struct_of(struct_type, **fields):
    """An instance of the ``wp.struct`` type ``struct_type`` with ``fields`` set (every field of a
    kernel argument must be set: an unset array field is a null array)."""
    s = struct_type()
    for name, value in fields.items():
        setattr(s, name, value)
    return s


def icgn_module_options(kernel_name: str) -> dict:
    """:data:`ICGN_MODULE_OPTIONS` with the CUDA block size of the kernel ``kernel_name``
    (:data:`kernels._launch.CUDA_LAUNCH`; one block size per Warp module)."""
    return {**ICGN_MODULE_OPTIONS, "block_dim": cuda_block_dim(kernel_name)}


ST_CONVERGED = wp.constant(int(Status.CONVERGED))
ST_MAX_ITERATIONS = wp.constant(int(Status.MAX_ITERATIONS))
ST_OUT_OF_BOUNDS = wp.constant(int(Status.OUT_OF_BOUNDS))
ST_FLAT = wp.constant(int(Status.FLAT_SUBSET))
ST_SINGULAR = wp.constant(int(Status.SINGULAR_HESSIAN))
ST_DIVERGED = wp.constant(int(Status.DIVERGED))
ST_NOT_COMPUTED = wp.constant(int(Status.NOT_COMPUTED))
ST_TOO_FEW_PIXELS = wp.constant(int(Status.TOO_FEW_PIXELS))
ST_COMPOSED_MISMATCH = wp.constant(int(Status.COMPOSED_MISMATCH))
