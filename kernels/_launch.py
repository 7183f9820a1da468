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

#: CUDA launch shape of the kernels that set it (key: the kernel's name): ``(threads per block,
#: minimum resident blocks per SM)``, the kernel's ``__launch_bounds__`` (its
#: ``@wp.kernel(launch_bounds=...)``); a minimum of 0 leaves the register budget to the compiler,
#: a minimum ``m`` caps it at ``65536 / (block * m)`` registers. Every other kernel runs at its Warp
#: module's block size (Warp's default: 256; :func:`kernel_block_dim`). Every kernel of one Warp
#: module uses the module's block size
#: (``wp.set_module_options({"block_dim": ...})``) so that a module is compiled once and the
#: ahead-of-time cache (``bench/gpu.py --prebuild-cache``) holds exactly what is launched.
#: Occupancy on sm_90 (65536 registers and at most 64 warps per SM, registers allocated per warp in
#: units of 256), registers read from the compiled cubins (docs/dic2d.md, "GPU";
#: tests/kernels/test_kernel_resources.py holds them):
#:
#: ======================  ======  ========================================================
#: kernel                  bounds  reason
#: ======================  ======  ========================================================
#: _icgn_2nd               128     168 registers, no stack: 12 warps per SM in blocks of 4
#:                                 warps, 8 in blocks of 8 (a 2nd 256-thread block does not
#:                                 fit). Capping at 128 registers (128, 4) would give 16 warps
#:                                 but spills 112 bytes per thread: not taken
#: _icgn_1st               128, 8  capped at 64 registers (80 uncapped) with no spill: 32
#:                                 warps per SM instead of 24
#: _prepare_subsets_1st    128     once per reference; the module's block size
#: _prepare_subsets_2nd    128     idem (255 registers and a 3480-byte stack: 8 warps)
#: _reference_gradients    128     40 registers: 48 warps per SM at 128 or 256
#: _reference_gradients_window 128 the same over a window of the image (prepare_reference(window=))
#: _prefilter_rows         256, 6  capped at 40 registers (56 uncapped), no spill: 48 warps
#:                                 instead of 32 for a latency-bound recursive filter
#:                                 (capping at 32, (256, 8), spills 32 bytes)
#: _prefilter_cols         256, 8  capped at 32 registers (48 uncapped), no spill: 64 warps
#: _prefilter_entries_*    256     32 registers: 64 warps
#: _icgn_frames_2nd        128     as _icgn_2nd (kernels/frames.py: frames x POIs, the same body)
#: _icgn_frames_1st        128, 6  capped at 80 registers (96 uncapped), no spill: 24 warps
#:                                 instead of 20; at 64 (128, 8) it spills 72 bytes, at 72
#:                                 (128, 7) 8 bytes (the frame indexing costs registers)
#: _prefilter_rows_frames  256, 5  48 registers, no spill: 40 warps ((256, 6) spills 8 bytes)
#: _prefilter_cols_frames  256, 6  40 registers, no spill: 48 warps ((256, 8) spills 24 bytes)
#: _icgn_counted_2nd       128     as _icgn_2nd (kernels/rg_device.py: a wave's IC-GN sized by a
#:                                 device count, the same body)
#: _icgn_counted_1st       128, 8  as _icgn_1st
#: _icgn_robust_1st/_2nd   128     opt-in Tukey-weighted refinement (kernels/icgn_robust.py):
#:                                 the module's block size, registers left to the compiler
#:                                 (214 and 255, stack 112 and 944 bytes: 8 warps per SM)
#: _residual_outliers_1st/_2nd 128 the residual test of adaptive robust IC-GN (same module; 96 and 149
#:                                 registers, stack 112 bytes)
#: ======================  ======  ========================================================
CUDA_LAUNCH = {
    "_icgn_2nd": (128, 0),
    "_icgn_1st": (128, 8),
    "_prepare_subsets_1st": (128, 0),
    "_prepare_subsets_2nd": (128, 0),
    "_reference_gradients": (128, 0),
    "_reference_gradients_window": (128, 0),
    "_prefilter_rows": (256, 6),
    "_prefilter_cols": (256, 8),
    "_prefilter_entries_rows": (256, 0),
    "_prefilter_entries_cols": (256, 0),
    "_prefilter_rows_frames": (256, 5),
    "_prefilter_cols_frames": (256, 6),
    "_icgn_frames_2nd": (128, 0),
    "_icgn_frames_1st": (128, 6),
    "_icgn_counted_2nd": (128, 0),
    "_icgn_counted_1st": (128, 8),
    "_icgn_robust_1st": (128, 0),
    "_icgn_robust_2nd": (128, 0),
    "_residual_outliers_1st": (128, 0),
    "_residual_outliers_2nd": (128, 0),
}

#: Warp's default threads per block on CUDA
DEFAULT_CUDA_BLOCK_DIM = 256


def _check_name(name) -> str:
    if not isinstance(name, str):
        raise ValueError(f"name must be a kernel name (str), got {type(name).__name__}")
    return name


def cuda_block_dim(name: str) -> int:
    """CUDA threads per block of the kernel called ``name`` (:data:`CUDA_LAUNCH`, else 256)."""
    return CUDA_LAUNCH.get(_check_name(name), (DEFAULT_CUDA_BLOCK_DIM, 0))[0]


def cuda_launch_bounds(name: str) -> int | tuple[int, int]:
    """``launch_bounds`` of ``@wp.kernel`` for the kernel called ``name``: the block size, or
    ``(block size, minimum blocks per SM)`` where :data:`CUDA_LAUNCH` sets a minimum."""
    block, min_blocks = CUDA_LAUNCH.get(_check_name(name), (DEFAULT_CUDA_BLOCK_DIM, 0))
    return (block, min_blocks) if min_blocks else block


def kernel_block_dim(kernel) -> int:
    """CUDA threads per block that ``launch_1d`` uses for ``kernel``: its :data:`CUDA_LAUNCH` entry,
    else its Warp module's block size (so a kernel added to a module runs with the module's
    compiled variant, and needs a table entry only to set launch bounds)."""
    if not isinstance(kernel, wp.Kernel):
        raise ValueError(f"kernel must be a Warp kernel, got {type(kernel).__name__}")
    name = kernel.func.__name__
    if name in CUDA_LAUNCH:
        return CUDA_LAUNCH[name][0]
    return int(kernel.module.options.get("block_dim", DEFAULT_CUDA_BLOCK_DIM))


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
    covers all ``n`` items (offset 0), with the kernel's block size (:func:`kernel_block_dim`).
    """
    if n <= 0:
        return
    inputs = list(inputs)
    threads = cpu_threads()
    if not str(device).startswith("cpu"):
        inputs[offset_index] = 0
        wp.launch(kernel, dim=n, inputs=inputs, device=device, block_dim=kernel_block_dim(kernel))
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
