"""Compiled resources of the GPU kernels: registers and stack read from the sm_90 cubins.

The IC-GN, reference-preparation and interpolation modules are compiled ahead of time for sm_90
(:func:`warp.compile_aot_module` runs NVRTC from inside Warp: no GPU, no CUDA toolkit), once per
test session, and :mod:`bench.cubin` reads each kernel's registers and stack from the ELF. The
bounds are the figures measured after issue 16's changes (docs/dic2d.md, "GPU"); a change that
makes a kernel need more registers or any stack where it had none fails here. A Warp upgrade
(another NVRTC) may move the figures by a few registers: re-measure and update the table then.
"""
import struct

import pytest
import warp as wp

from bench import cubin
from kernels._launch import CUDA_LAUNCH, DEFAULT_CUDA_BLOCK_DIM, cuda_block_dim, cuda_launch_bounds, kernel_block_dim

#: kernel -> (max registers, max stack bytes) on sm_90; before issue 16 in the comment
BOUNDS = {
    "_icgn_1st": (64, 0),  # 80, 0 (capped by launch bounds (128, 8), no spill)
    "_icgn_2nd": (168, 0),
    "_icgn_1st_tiled": (64, 0),  # prototype (bench/icgn_tiled.py)
    "_icgn_frames_1st": (80, 0),  # kernels/frames.py (frames x POIs)
    "_icgn_frames_2nd": (168, 0),
    "_icgn_counted_1st": (64, 0),  # kernels/rg_device.py (a wave's IC-GN sized by a device count)
    "_icgn_counted_2nd": (168, 0),
    "_propagate_guess": (32, 0),  # 40 before issue 23 (the frames' arrays as one struct)
    "_pack_results": (32, 0),
    "_prefilter_rows_frames": (48, 0),  # every frame dtype (uint8, uint16, float32)
    "_prefilter_cols_frames": (40, 0),
    "_prefilter_entries_rows_frames": (32, 0),
    "_prefilter_entries_cols_frames": (32, 0),
    "_expand_rows4_frames": (28, 0),  # 166, 168 (pivot swap of the 6x6 solve)
    "_prepare_subsets_1st": (177, 0),  # one kernel for both orders: 255, 7232; 183 before issue 23 (named columns)
    "_prepare_subsets_2nd": (255, 3472),  # 12x12 float64 Cholesky in run-time loops (1256 B unrolled); 3480 B before issue 23
    "_reference_gradients": (40, 0),
    "_reference_gradients_window": (40, 0),  # prepare_reference(window=) (issue 23, measured)
    "_gather_subsets": (32, 0),  # indexed IC-GN's gather (kernels.icgn, issue 16 search on the device)
    "_scatter_subsets": (32, 0),  # prepare_subsets(active=): the prepared rows into every POI's (issue 23, measured)
    "_expand_rows4": (30, 0),
    "_interp_kernel": (64, 0),
    "_prefilter_rows": (40, 0),  # whole lines: 32, 0; segments: 56 uncapped, 40 with bounds (256, 6)
    "_prefilter_cols": (32, 0),  # whole lines: 40, 0; segments: 48 uncapped, 32 with bounds (256, 8)
    "_prefilter_entries_rows": (32, 0),  # new: segment entry values
    "_prefilter_entries_cols": (32, 0),
    # opt-in Tukey-weighted refinement (kernels/icgn_robust.py): weights change every iteration, so the weighted
    # Hessian is assembled from float64 moments in the kernel (no precomputed H^-1 as in _icgn_*)
    "_icgn_robust_1st": (210, 112),  # the stack: the |residual| histogram, indexed at run time; 214 before issue 23
    "_icgn_robust_2nd": (255, 944),
    # per-POI pixel masks (kernels/icgn_masked.py, issue 26): separate kernels, the unmasked ones above unchanged;
    # module block size 256, no launch-bounds cap (measured at their introduction)
    "_icgn_masked_1st": (80, 0),
    "_icgn_masked_2nd": (227, 0),
    "_icgn_frames_masked_1st": (112, 0),
    "_icgn_frames_masked_2nd": (238, 0),
    "_prepare_masked_1st": (181, 0),
    "_prepare_masked_2nd": (255, 3488),  # the 12x12 float64 Cholesky of _prepare_subsets_2nd (3472 B)
    "_gather_masks": (32, 0),
    # the residual test of adaptive robust IC-GN (same module; 256 bytes of stack: the two rows of horizontal 3-sums
    # of the box pass, 2 x BOX_STRIP floats, which also hold the |residual| histogram of the optional MAD pass):
    # measured 96 and 153 registers, 256 bytes, issue 26 (before the box pass: 96 and 149, 112 bytes)
    "_residual_outliers_1st": (100, 256),
    "_residual_outliers_2nd": (156, 256),
}
MODULES = ("kernels.icgn", "kernels.interp", "bench.icgn_tiled", "kernels.frames", "kernels.rg_device",
           "kernels.icgn_robust", "kernels.icgn_masked")


@pytest.fixture(scope="session")
def sm90_resources(tmp_path_factory):
    import importlib

    wp.config.quiet = True
    wp.init()
    found = {}
    for name in MODULES:
        out = tmp_path_factory.mktemp(name.replace(".", "_"))
        wp.compile_aot_module(importlib.import_module(name), arch=90, module_dir=str(out), use_ptx=False)
        cubins = sorted(out.rglob("*.cubin"))
        assert cubins, f"no cubin for {name}"
        for path in cubins:
            for mangled, res in cubin.kernel_resources(path).items():
                if mangled.endswith("_cuda_kernel_forward"):
                    name = mangled.split("_cuda_kernel_forward")[0].rsplit("_", 1)[0]
                    found.setdefault(name, []).append(res)  # overloads (one per dtype) share a name
    # the most demanding overload of each kernel
    return {k: max(v, key=lambda r: (r.registers, r.stack)) for k, v in found.items()}


@pytest.mark.slow
@pytest.mark.parametrize("kernel", sorted(BOUNDS))
def test_kernel_registers_and_stack_within_bounds(sm90_resources, kernel):
    assert kernel in sm90_resources, f"{kernel} not found in the cubins: {sorted(sm90_resources)}"
    res = sm90_resources[kernel]
    max_regs, max_stack = BOUNDS[kernel]
    assert 0 < res.registers <= max_regs, f"{kernel}: {res.registers} registers (bound {max_regs})"
    assert res.stack <= max_stack, f"{kernel}: {res.stack} bytes of stack (bound {max_stack})"


@pytest.mark.slow
def test_every_compiled_kernel_has_a_bound(sm90_resources):
    assert set(sm90_resources) == set(BOUNDS)


def test_block_size_table_matches_kernels_and_modules():
    from kernels import frames, icgn, icgn_robust, interp, rg_device

    kernels = {k.func.__name__: k for mod in (icgn, interp, frames, rg_device) for k in vars(mod).values() if isinstance(k, wp.Kernel)}
    kernels.update({k.func.__name__: k for k in icgn._prepare_subsets.values()})
    kernels.update({k.func.__name__: k for k in icgn_robust._icgn_robust.values()})
    kernels.update({k.func.__name__: k for k in icgn_robust._residual_outliers.values()})
    assert set(CUDA_LAUNCH) <= set(kernels)
    for name, kernel in kernels.items():
        # one block size per Warp module: the module is compiled (and AOT-cached) once
        assert kernel.module.options["block_dim"] == kernel_block_dim(kernel), name
        if name in CUDA_LAUNCH:
            assert cuda_block_dim(name) == kernel_block_dim(kernel), name
            assert kernel.options.get("launch_bounds") == cuda_launch_bounds(name), name
    assert cuda_block_dim("not_a_kernel") == DEFAULT_CUDA_BLOCK_DIM
    with pytest.raises(ValueError, match="kernel name"):
        cuda_block_dim(3)
    with pytest.raises(ValueError, match="Warp kernel"):
        kernel_block_dim("_icgn_2nd")


def test_occupancy_from_registers():
    # sm_90: 65536 registers per SM, warps take registers in units of 256, at most 64 warps
    assert cubin.occupancy_warps(166, 256) == 8  # 168 x 32 = 5376 per warp: 12 fit, in blocks of 8 -> 8
    assert cubin.occupancy_warps(166, 128) == 12
    assert cubin.occupancy_warps(80, 256) == 24
    assert cubin.occupancy_warps(255, 128) == 8
    assert cubin.occupancy_warps(32, 256) == 64
    with pytest.raises(ValueError):
        cubin.occupancy_warps(0, 128)


def _tiny_elf(regcount: int, frame: int) -> bytes:
    """A minimal ELF64 built independently of the parser: one function ``k`` with .text.k and a
    module-wide .nv.info holding EIATTR_REGCOUNT and EIATTR_FRAME_SIZE (SVAL records), plus an
    HVAL, a BVAL with its padding byte and an NVAL record the parser must step over."""
    shstr = b"\0.shstrtab\0.strtab\0.symtab\0.text.k\0.nv.info\0"
    strtab = b"\0k\0"
    sym = bytes(24) + struct.pack("<IBBHQQ", 1, 0x12, 0, 4, 0, 0)  # symbol 1: k, FUNC
    text = b"\0" * 16
    info = (struct.pack("<BBH", 0x03, 0x1B, 255)  # HVAL EIATTR_MAXREG_COUNT
            + struct.pack("<BBBB", 0x02, 0x4C, 7, 0)  # BVAL and its padding byte
            + struct.pack("<BB", 0x01, 0x21)  # NVAL
            + struct.pack("<BBHII", 0x04, 0x2F, 8, 1, regcount)
            + struct.pack("<BBHII", 0x04, 0x11, 8, 1, frame))
    bodies = [b"", shstr, strtab, sym, text, info]
    names = [0, shstr.index(b".shstrtab"), shstr.index(b".strtab"), shstr.index(b".symtab"),
             shstr.index(b".text.k"), shstr.index(b".nv.info")]
    types = [0, 3, 3, 2, 1, 0x70000000]
    links = [0, 0, 0, 2, 0, 3]
    data = bytearray(64)
    offs = []
    for b in bodies:
        offs.append(len(data))
        data += b
    shoff = len(data)
    for i, b in enumerate(bodies):
        data += struct.pack("<IIQQQQIIQQ", names[i], types[i], 0, 0, offs[i], len(b), links[i], 0, 1,
                            24 if types[i] == 2 else 0)
    hdr = b"\x7fELF" + bytes([2, 1, 1]) + bytes(9)
    hdr += struct.pack("<HHIQQQIHHHHHH", 2, 190, 1, 0, 0, shoff, 0, 64, 0, 0, 64, len(bodies), 1)
    data[:64] = hdr
    return bytes(data)


def test_cubin_parser_on_a_handmade_elf():
    res = cubin.kernel_resources(_tiny_elf(42, 16))
    assert set(res) == {"k"}
    assert res["k"].registers == 42 and res["k"].frame == 16 and res["k"].stack == 16
    with pytest.raises(ValueError, match="not an ELF"):
        cubin.kernel_resources(b"not a cubin at all")
    with pytest.raises(ValueError, match="bytes or a path"):
        cubin.kernel_resources(3.0)


def test_launch_1d_passes_the_kernel_block_size_on_cuda_only(monkeypatch):
    """A kernel compiled with __launch_bounds__(128) fails to launch with Warp's default 256
    threads: launch_1d must pass the table's block size on CUDA (and nothing on the CPU)."""
    from kernels import _launch, icgn, interp

    calls = []
    monkeypatch.setattr(wp, "launch", lambda kernel, dim, inputs, device, **kw: calls.append((kernel, device, kw)))
    for kernel in (icgn._icgn_2nd, icgn._icgn_1st, icgn._prepare_subsets[2], interp._prefilter_rows,
                   interp._expand_rows4):
        _launch.launch_1d(kernel, 1000, [0], "cuda:0", offset_index=0)
    assert [kw["block_dim"] for _, _, kw in calls] == [128, 128, 128, 256, 256]
    calls.clear()
    _launch.launch_1d(icgn._gather_subsets, 10, [0], "cuda:0", offset_index=0)  # no entry: the module's 128
    assert calls[0][2]["block_dim"] == 128
    calls.clear()
    monkeypatch.setenv("SPECULA_THREADS", "1")
    _launch.launch_1d(icgn._icgn_2nd, 10, [0], "cpu", offset_index=0)
    assert calls and "block_dim" not in calls[0][2]


@pytest.mark.slow
def test_icgn_kernels_load_coefficients_as_scalars_on_sm90(tmp_path):
    """``layout="plain"`` hands the IC-GN kernels a vec4 view with a 4-byte stride
    (:func:`kernels.interp.rows4_view`): valid only while a ``wp.vec4`` load needs 4-byte alignment.
    If the compiler ever emitted 8/16-byte vector loads for them (e.g. a Warp with an aligned
    ``vec_t``), the plain layout would fault on CUDA: the sm_90 PTX must hold scalar loads only."""
    import importlib
    import re

    wp.config.quiet = True
    wp.init()
    wp.compile_aot_module(importlib.import_module("kernels.icgn"), arch=90, module_dir=str(tmp_path), use_ptx=True)
    ptx = "".join(p.read_text() for p in tmp_path.rglob("*.ptx"))
    for name in ("_icgn_1st", "_icgn_2nd"):
        m = re.search(r"\.entry \S*%s_[0-9a-f]+_cuda_kernel_forward\((.*?)\n\}\n" % name, ptx, re.S)
        assert m, f"{name} not in the PTX"
        loads = re.findall(r"\bld\.global(?:\.nc)?(\.v[248])?\.\w+", m.group(1))
        assert loads and not any(loads), f"{name}: vector loads {sorted(set(loads) - {''})}"
