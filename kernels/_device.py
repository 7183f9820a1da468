"""Device selection shared by every kernel launcher (and ``as_float32_image``, from :mod:`kernels.images`).

Conventions (see docs/conventions.md): device arrays are float32, images are indexed
``[row, col] = [y, x]``. ``device=None`` means ``"cuda:0"`` when a CUDA device exists, else ``"cpu"``.
"""
from __future__ import annotations

import warp as wp

# array validation lives with the image reader; re-exported for the launchers that import it from here
from .images import as_float32_image  # noqa: F401

_initialised = False


def _ensure_init() -> None:
    """Initialise Warp once, quietly (importing our packages does not do this)."""
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
    _ensure_init()
    if device is None:
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    name = str(device.alias) if hasattr(device, "alias") else str(device)
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
