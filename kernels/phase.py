"""N-step phase-shifting demodulation: wrapped phase, modulation and background per pixel.

A pixel that sees a fringe pattern displayed with phase shifts ``delta_k`` records

    I_k = B + A sin(phi + delta_k),            k = 0 .. N-1,  N >= 3

which is linear in ``(B, a, b) = (B, A sin(phi), A cos(phi))``:
``I_k = B + a cos(delta_k) + b sin(delta_k)``. The least-squares solution is a fixed 3 x N matrix
``P = pinv(D)`` (``D`` the N x 3 design matrix) applied to the N samples, so the kernel only forms
three dot products per pixel; for equal steps ``delta_k = 2 pi k / N`` it reduces to the classic
N-step formula ``phi = atan2(sum I_k cos delta_k, sum I_k sin delta_k)``.

Outputs (float32, same (H, W) shape as one image):

- ``phase`` wrapped to (-pi, pi] (rad), the ``phi`` of the equation above;
- ``modulation`` ``A = sqrt(a^2 + b^2)`` in grey levels (the fringe amplitude);
- ``background`` ``B`` in grey levels;
- ``valid`` (uint8) 1 where ``A >= min_modulation`` and no sample reaches ``saturation``.

Phase noise for white intensity noise ``sigma`` is ``sigma * sqrt(2 / N) / A`` rad (equal steps).
Reference: Greivenkamp, "Generalized data reduction for heterodyne interferometry", Optical
Engineering 23(4), 1984, doi:10.1117/12.7973298 (least squares for arbitrary phase shifts). The
phase targets built on it follow the paper behind Specula ("Stereo-camera calibration for
large-scale DIC measurements with active phase targets and planar mirrors", Optics Express 27(6),
9040, 2019, doi:10.1364/OE.27.009040).

Conventions: docs/conventions.md (images indexed ``[row, col] = [y, x]``, float32 on device).
"""
from __future__ import annotations

import numpy as np
import warp as wp

from ._device import resolve_device
from ._launch import launch_1d
from .checks import positive_int

__all__ = ["demodulate", "equal_phase_shifts", "demodulation_matrix"]


@wp.func
def _wrap_pi(a: float):
    """Wrap an angle to (-pi, pi]."""
    two_pi = 6.283185307179586
    w = a - two_pi * wp.floor((a + 3.141592653589793) / two_pi)
    if w <= -3.141592653589793:
        w = w + two_pi
    return w


@wp.kernel
def _demodulate_kernel(
    images: wp.array3d(dtype=wp.float32),      # (N, H, W) grey levels
    coeffs: wp.array2d(dtype=wp.float32),      # (3, N) least-squares rows for B, a, b
    min_modulation: float,
    saturation: float,
    width: int,
    n_pixels: int,
    offset: int,
    phase: wp.array2d(dtype=wp.float32),
    modulation: wp.array2d(dtype=wp.float32),
    background: wp.array2d(dtype=wp.float32),
    valid: wp.array2d(dtype=wp.uint8),
):
    idx = wp.tid() + offset
    if idx >= n_pixels:
        return
    row = idx / width
    col = idx - row * width
    n = images.shape[0]
    bg = float(0.0)
    a = float(0.0)
    b = float(0.0)
    saturated = int(0)
    for k in range(n):
        v = images[k, row, col]
        bg += coeffs[0, k] * v
        a += coeffs[1, k] * v
        b += coeffs[2, k] * v
        if v >= saturation:
            saturated = 1
    amp = wp.sqrt(a * a + b * b)
    phase[row, col] = _wrap_pi(wp.atan2(a, b))
    modulation[row, col] = amp
    background[row, col] = bg
    ok = wp.uint8(0)
    if amp >= min_modulation and saturated == 0:
        ok = wp.uint8(1)
    valid[row, col] = ok


def equal_phase_shifts(steps: int) -> np.ndarray:
    """The equal phase shifts ``delta_k = 2 pi k / N`` (rad, float64, shape (N,)), N >= 3."""
    steps = positive_int(steps, "the number of phase steps", minimum=3)
    return 2.0 * np.pi * np.arange(steps) / steps


def demodulation_matrix(phase_shifts) -> np.ndarray:
    """Least-squares matrix (3, N) float64 mapping N samples to ``(B, A sin phi, A cos phi)``.

    ``phase_shifts`` (N,) rad, N >= 3, must not be degenerate (at least three distinct shifts
    modulo 2 pi).
    """
    d = np.asarray(phase_shifts, dtype=np.float64)
    if d.ndim != 1 or d.size < 3 or not np.all(np.isfinite(d)):
        raise ValueError(f"phase_shifts must be a finite 1-D array of N >= 3 shifts (rad), got shape {d.shape}")
    design = np.stack([np.ones_like(d), np.cos(d), np.sin(d)], axis=1)
    if np.linalg.matrix_rank(design, tol=1e-9) < 3:
        raise ValueError(
            f"phase_shifts {np.round(d, 4).tolist()} are degenerate (fewer than three distinct shifts modulo 2 pi); "
            "the background, amplitude and phase cannot be separated"
        )
    return np.linalg.pinv(design)


def _as_stack(images, device: str):
    """Validate an (N, H, W) stack and return it as a float32 Warp array on ``device``."""
    if isinstance(images, wp.array):
        if images.ndim != 3:
            raise ValueError(f"images must be a 3-D stack (N, H, W), got a {images.ndim}-D warp array of shape {images.shape}")
        if images.dtype != wp.float32:
            raise ValueError(f"a warp array of images must be float32, got {images.dtype}")
        if str(images.device) != device:
            images = images.to(device)
        return images
    if isinstance(images, (list, tuple)):
        shapes = {np.shape(im) for im in images}
        if len(shapes) > 1:
            raise ValueError(f"all phase-shifted images must have the same shape, got {sorted(shapes)}")
        images = np.stack([np.asarray(im) for im in images])
    arr = np.asarray(images)
    if arr.ndim != 3:
        raise ValueError(f"images must be a stack (N, H, W) of N phase-shifted grey images, got shape {arr.shape}")
    if arr.shape[1] == 0 or arr.shape[2] == 0:
        raise ValueError(f"images are empty (shape {arr.shape})")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"images must be real grey levels, got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.all(np.isfinite(arr)):
        raise ValueError("images contain NaN or infinite values")
    return wp.array(arr, dtype=wp.float32, device=device)


def demodulate(
    images,
    phase_shifts=None,
    *,
    min_modulation: float = 0.0,
    saturation: float | None = None,
    out=None,
    device=None,
):
    """Least-squares N-step demodulation of a stack of phase-shifted images.

    Parameters
    ----------
    images : (N, H, W) array-like or float32 ``wp.array3d``
        The N >= 3 recorded images, in display order, grey levels (any real dtype; 8/16-bit kept
        on their scale). A list of N (H, W) images is accepted too.
    phase_shifts : (N,) float, optional
        Phase shift ``delta_k`` (rad) of each image, ``I_k = B + A sin(phi + delta_k)``. Default:
        equal steps ``2 pi k / N``.
    min_modulation : float
        Pixels whose modulation ``A`` (grey levels) is below this are marked invalid.
    saturation : float, optional
        Grey level at or above which a sample counts as saturated (its pixel is marked invalid);
        default: 255 for uint8 input, 65535 for uint16 input, no check otherwise.
    out : tuple of 4 warp arrays, optional
        Preallocated ``(phase, modulation, background, valid)``: three float32 (H, W) and one
        uint8 (H, W) array on ``device``.
    device : str, optional
        Warp device; ``None`` picks CUDA when available (docs/conventions.md).

    Returns
    -------
    phase, modulation, background : wp.array2d float32 (H, W)
        Wrapped phase (rad, (-pi, pi]), modulation ``A`` and background ``B`` (grey levels).
    valid : wp.array2d uint8 (H, W)
        1 where ``A >= min_modulation`` and nothing saturated, else 0.
    """
    device = resolve_device(device)
    if saturation is None:
        dtype = getattr(images, "dtype", None)
        if isinstance(images, (list, tuple)) and images:
            dtype = np.asarray(images[0]).dtype
        if dtype == np.uint8:
            saturation = 255.0
        elif dtype == np.uint16:
            saturation = 65535.0
        else:
            saturation = np.inf
    if not np.isfinite(min_modulation) or min_modulation < 0:
        raise ValueError(f"min_modulation must be a finite grey level >= 0, got {min_modulation!r}")
    if np.isnan(saturation):
        raise ValueError("saturation must be a grey level or inf, got NaN")
    stack = _as_stack(images, device)
    n, h, w = stack.shape
    if n < 3:
        raise ValueError(f"phase-shifting needs N >= 3 images, got {n}")
    shifts = equal_phase_shifts(n) if phase_shifts is None else np.asarray(phase_shifts, dtype=np.float64)
    if shifts.shape != (n,):
        raise ValueError(f"phase_shifts must have one shift per image, shape ({n},), got {shifts.shape}")
    coeffs = wp.array(demodulation_matrix(shifts).astype(np.float32), dtype=wp.float32, device=device)
    if out is None:
        out = (
            wp.empty((h, w), dtype=wp.float32, device=device),
            wp.empty((h, w), dtype=wp.float32, device=device),
            wp.empty((h, w), dtype=wp.float32, device=device),
            wp.empty((h, w), dtype=wp.uint8, device=device),
        )
    else:
        if len(out) != 4:
            raise ValueError(f"out must be a tuple (phase, modulation, background, valid), got {len(out)} items")
        for name, arr, dt in zip(("phase", "modulation", "background", "valid"), out,
                                 (wp.float32, wp.float32, wp.float32, wp.uint8)):
            if not isinstance(arr, wp.array) or arr.shape != (h, w) or arr.dtype != dt or str(arr.device) != device:
                got = (getattr(arr, "shape", None), getattr(arr, "dtype", None), str(getattr(arr, "device", None)))
                raise ValueError(f"out {name} must be a warp array of shape {(h, w)}, dtype {dt.__name__} on {device}, got {got}")
    sat = float(min(saturation, 3.0e38))
    launch_1d(
        _demodulate_kernel, h * w,
        [stack, coeffs, float(min_modulation), sat, w, h * w, 0, *out],
        device=device, offset_index=6, min_chunk=4096,
    )
    return tuple(out)
