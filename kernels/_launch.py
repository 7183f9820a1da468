"""Launch helpers.

Warp's CPU backend runs one launch on one thread but releases the GIL, so on the CPU a large
1-D launch is split into per-core chunks run from a thread pool (measured: 2 chunks on 2 cores
take 0.56x the time of one launch). Kernels that use this take an ``offset: int`` input and
compute their index as ``wp.tid() + offset``; the launcher passes ``offset`` at ``offset_index``.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import warp as wp

_POOL: ThreadPoolExecutor | None = None

#: CUDA threads per block of the kernels that set it (key: the kernel's name); every other kernel
#: runs at Warp's default of 256. Each entry is also the kernel's ``__launch_bounds__`` (its
#: ``@wp.kernel(launch_bounds=...)``), and every kernel of one Warp module uses the module's value
#: (``wp.set_module_options({"block_dim": ...})``) so that a module is compiled once, and the
#: ahead-of-time cache (``bench/gpu.py --prebuild-cache``) holds exactly what is launched.
#: Occupancy on sm_90 (65536 registers and at most 64 warps per SM; registers allocated per warp
#: in units of 256) for the registers read from the compiled cubins (docs/dic2d.md, "GPU"):
#:
#: ======================  =====  ==========================================================
#: kernel                  block  reason
#: ======================  =====  ==========================================================
#: _icgn_2nd               128    168 registers: 12 warps per SM in blocks of 4 warps, only
#:                                 8 in blocks of 8 (a 2nd 256-thread block does not fit)
#: _icgn_1st               128    80 registers: 24 warps per SM at 128 or 256; 128 keeps the
#:                                 module at one block size
#: _prepare_subsets_1st    128    per-reference; the module's block size
#: _prepare_subsets_2nd    128    idem (254 registers: 8 warps at 128 or 256)
#: _reference_gradients    128    40 registers: 48 warps at 128 or 256
#: ======================  =====  ==========================================================
CUDA_BLOCK_DIM = {
    "_icgn_2nd": 128,
    "_icgn_1st": 128,
    "_prepare_subsets_1st": 128,
    "_prepare_subsets_2nd": 128,
    "_reference_gradients": 128,
}

#: Warp's default threads per block on CUDA
DEFAULT_CUDA_BLOCK_DIM = 256


def cuda_block_dim(name: str) -> int:
    """CUDA threads per block of the kernel called ``name`` (:data:`CUDA_BLOCK_DIM`, else 256)."""
    if not isinstance(name, str):
        raise ValueError(f"name must be a kernel name (str), got {type(name).__name__}")
    return CUDA_BLOCK_DIM.get(name, DEFAULT_CUDA_BLOCK_DIM)


def _kernel_name(kernel) -> str:
    return kernel.func.__name__


def cpu_threads() -> int:
    """Number of CPU threads to split launches over (``SPECULA_THREADS`` overrides)."""
    env = os.environ.get("SPECULA_THREADS")
    if env:
        return max(1, int(env))
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=cpu_threads(), thread_name_prefix="specula-cpu")
    return _POOL


def launch_1d(kernel, n: int, inputs: list, device: str, offset_index: int, min_chunk: int = 256) -> None:
    """Launch ``kernel`` over ``n`` items, chunked across CPU threads when on the CPU.

    ``inputs[offset_index]`` is replaced by each chunk's start index. On CUDA a single launch
    covers all ``n`` items (offset 0), with the kernel's block size (:func:`cuda_block_dim`).
    """
    if n <= 0:
        return
    inputs = list(inputs)
    threads = cpu_threads()
    if not str(device).startswith("cpu"):
        inputs[offset_index] = 0
        wp.launch(kernel, dim=n, inputs=inputs, device=device, block_dim=cuda_block_dim(_kernel_name(kernel)))
        return
    if threads == 1 or n < 2 * min_chunk:
        inputs[offset_index] = 0
        wp.launch(kernel, dim=n, inputs=inputs, device=device)
        return
    # Compile/load the module once here: otherwise every pool thread races to build it.
    wp.load_module(kernel.module, device=device)
    # a few chunks per thread balance uneven per-item cost (e.g. POIs that iterate longer)
    n_chunks = min(threads * 4, max(1, n // min_chunk))
    bounds = [round(k * n / n_chunks) for k in range(n_chunks + 1)]

    def run(k: int) -> None:
        args = list(inputs)
        args[offset_index] = bounds[k]
        wp.launch(kernel, dim=bounds[k + 1] - bounds[k], inputs=args, device=device)

    list(_pool().map(run, range(n_chunks)))
