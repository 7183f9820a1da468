"""Every kernel module must also build for the GPU (sm_90), even on a machine without one.

Warp compiles CUDA ahead of time through NVRTC, which ships with warp-lang and needs no driver,
so a kernel that would fail to build for CUDA fails CI here rather than on a user's GPU.
"""
import importlib
import pkgutil

import pytest
import warp as wp

import kernels

KERNEL_MODULES = sorted(
    name for _, name, _ in pkgutil.iter_modules(kernels.__path__) if not name.startswith("_") and name != "conventions"
)


def _has_kernels(module) -> bool:
    return any(isinstance(getattr(module, attr), wp.Kernel) for attr in dir(module))


@pytest.mark.parametrize("module_name", KERNEL_MODULES)
def test_module_compiles_for_cuda_sm90(module_name, tmp_path):
    wp.config.quiet = True
    wp.init()
    module = importlib.import_module(f"kernels.{module_name}")
    if not _has_kernels(module):
        pytest.skip(f"kernels.{module_name} defines no Warp kernel")
    outputs = wp.compile_aot_module(module, arch=90, module_dir=str(tmp_path))
    cubins = [p for p in tmp_path.iterdir() if p.suffix in (".cubin", ".ptx")]
    assert cubins, f"no CUDA binary was produced for kernels.{module_name}: {outputs}"
