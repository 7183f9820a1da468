"""Device selection shared by every kernel launcher (and ``as_float32_image``, from :mod:`kernels.images`).

Conventions (see docs/conventions.md): device arrays are float32, images are indexed
``[row, col] = [y, x]``. ``device=None`` means ``"cuda:0"`` when a CUDA device exists, else ``"cpu"``.
"""
from __future__ import annotations

import os
from contextlib import contextmanager

import numpy as np
import warp as wp

# array validation lives with the image reader; re-exported for the launchers that import it from here
from .images import as_float32_image  # noqa: F401

_initialised = False


def _cuda_driver_present() -> bool:
    """Whether the NVIDIA CUDA driver library can be loaded here (without initialising it)."""
    import ctypes
    import sys

    names = ("nvcuda.dll",) if sys.platform == "win32" else ("libcuda.so", "libcuda.so.1")
    for name in names:
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


@contextmanager
def _native_stderr_silenced():
    """Silence file descriptor 2 (what native code prints with fprintf) inside the block."""
    import sys

    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def _ensure_init(wants_cuda: bool = False) -> None:
    """Initialise Warp once, quietly (importing our packages does not do this).

    On a machine without the NVIDIA driver, Warp's native start-up prints "Warp CUDA warning: Could
    not find or load the NVIDIA CUDA driver" on every run; that says nothing to a CPU user, so it is
    silenced unless CUDA was asked for (``device="cuda..."``, which then fails with our own message).
    """
    global _initialised
    if not _initialised:
        import logging

        # Warp >= 1.10 replaced ``config.quiet`` with ``config.log_level``; silence the banner
        # either way (errors still print).
        if hasattr(wp.config, "log_level"):
            wp.config.log_level = max(wp.config.log_level, logging.WARNING)
        else:  # pragma: no cover - older Warp
            wp.config.quiet = True
        # Specula never differentiates through its kernels: skipping adjoint code generation
        # cuts CPU compile time about threefold.
        wp.config.enable_backward = False
        if wants_cuda or _cuda_driver_present():
            wp.init()
        else:
            with _native_stderr_silenced():
                wp.init()
        _initialised = True


def available_devices() -> list[str]:
    """Names of the Warp devices usable here: ``["cpu"]`` plus ``"cuda:0"`` when present."""
    _ensure_init()
    names = ["cpu"]
    if wp.is_cuda_available():
        names.append("cuda:0")
    return names


def resolve_device(device=None) -> str:
    """Return the Warp device name to run on.

    Parameters
    ----------
    device : None, str or warp.context.Device
        ``None`` picks ``"cuda:0"`` when a CUDA device is available, else ``"cpu"``.
    """
    name = None if device is None else (str(device.alias) if hasattr(device, "alias") else str(device))
    _ensure_init(wants_cuda=name is not None and name.startswith("cuda"))
    if name is None:
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if name == "cuda":
        name = "cuda:0"
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise ValueError(
            f"device={name!r} was requested but no CUDA device is available here; "
            "use device='cpu' or leave device=None to pick automatically"
        )
    if name != "cpu" and not name.startswith("cuda"):
        raise ValueError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {name!r}")
    return name


def host_copy(array) -> np.ndarray:
    """An owned NumPy copy of a ``wp.array`` on any device (the one way launchers return host arrays).

    ``wp.array.numpy()`` differs by device: on CUDA it copies to the host, on the CPU it returns a
    *view* of the device buffer, which a later launch writing the same buffer (a reused ``out=``, the
    next frame) overwrites under the caller's feet. This copies on the CPU and not twice on CUDA, so
    results the caller keeps are the caller's on every device.
    """
    if not isinstance(array, wp.array):
        raise ValueError(f"host_copy needs a wp.array, got {type(array).__name__}")
    a = array.numpy()
    if array.device.is_cpu:
        return np.array(a, copy=True)
    return a
