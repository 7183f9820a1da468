"""Device selection and array conversion shared by every kernel launcher.

Conventions (see docs/conventions.md): device arrays are float32, images are indexed
``[row, col] = [y, x]``. ``device=None`` means ``"cuda:0"`` when a CUDA device exists, else ``"cpu"``.
"""
from __future__ import annotations

import numpy as np
import warp as wp

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


def as_float32_image(image, name: str = "image") -> np.ndarray:
    """Validate a 2-D grey image and return it as a C-contiguous float32 NumPy array.

    Raises ``ValueError`` for non-2-D input (colour images included), empty images and
    non-finite values.
    """
    if hasattr(image, "numpy") and not isinstance(image, np.ndarray):  # torch tensor / warp array
        image = image.detach().cpu().numpy() if hasattr(image, "detach") else image.numpy()
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        raise ValueError(
            f"{name} is a colour image of shape {arr.shape}; a grey image (H, W) is expected. "
            "Convert it first, e.g. with cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)"
        )
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array (H, W), got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} is empty (shape {arr.shape})")
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    out = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name} contains NaN or infinite values; DIC needs finite grey levels")
    return out
