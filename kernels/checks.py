"""Argument checks shared by every layer: point arrays and scalar settings.

Each check returns the value in its canonical type (float64 arrays, ``int``, ``float``) or raises
``ValueError`` with a message that names the argument and shows what was given, e.g.
``"step must be a positive integer number of pixels, got 0"``. ``name`` is the argument's name
as the caller should see it (it may carry a prefix such as ``"scene.camera[0]: focal_length_mm"``);
``detail`` is appended to the requirement (``" number of pixels"``, ``" (e.g. 21)"``).

Booleans are refused wherever a number is expected (``True`` is an ``int`` in Python). The module
itself needs only NumPy.
"""
from __future__ import annotations

import math
import numbers

import numpy as np

__all__ = [
    "as_points",
    "boolean",
    "in_range",
    "non_negative_int",
    "odd_int",
    "positive_float",
    "positive_int",
    "unit_interval",
]

_COLUMNS = {2: "(x, y)", 3: "(x, y, z)"}


def as_points(points, name: str = "points", *, ncols: int = 2, shape=None, image_name: str = "image",
              allow_empty: bool = False, finite: bool = True) -> np.ndarray:
    """Validate an array of points and return it as a C-contiguous float64 array (N, ncols).

    Parameters
    ----------
    points : array-like (N, ncols), torch tensor or ``wp.array``
        Point coordinates: ``(x, y)`` px for ``ncols=2``, ``(x, y, z)`` (e.g. mm) for ``ncols=3``.
    name : str
        The argument's name in messages.
    ncols : int >= 1
        Number of coordinates per point.
    shape : (H, W), optional
        Image shape (px): every point must lie on the image, i.e. within
        ``[-0.5, W - 0.5] x [-0.5, H - 0.5]`` (pixel centres at integers, docs/conventions.md).
        Needs ``ncols=2``.
    image_name : str
        How messages name the image of ``shape`` (e.g. ``"left image"``).
    allow_empty : bool
        Accept N = 0 (default: at least one point is needed).
    finite : bool
        Require finite coordinates (default). ``False`` lets NaN through (e.g. "no point here").

    Returns
    -------
    ndarray (N, ncols) float64, C-contiguous; the input itself when it already is one.
    """
    if isinstance(ncols, bool) or not isinstance(ncols, (int, np.integer)) or ncols < 1:
        raise ValueError(f"ncols must be a positive integer, got {ncols!r}")
    if hasattr(points, "numpy") and not isinstance(points, np.ndarray):  # torch tensor / warp array
        points = points.detach().cpu().numpy() if hasattr(points, "detach") else points.numpy()
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != ncols:
        cols = _COLUMNS.get(int(ncols), f"{ncols} coordinates")
        raise ValueError(f"{name} must have shape (N, {ncols}), an array of {cols}, got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    if arr.shape[0] == 0 and not allow_empty:
        raise ValueError(f"{name} is empty: at least one point is needed")
    out = np.ascontiguousarray(arr, dtype=np.float64)
    if finite and not np.all(np.isfinite(out)):
        raise ValueError(f"{name} contains NaN or infinite values")
    if shape is not None:
        if ncols != 2:
            raise ValueError(f"an image shape can only check (x, y) points, not ncols={ncols}")
        h, w = _image_shape(shape)
        x, y = out[:, 0], out[:, 1]
        outside = (x < -0.5) | (x > w - 0.5) | (y < -0.5) | (y > h - 0.5)
        if np.any(outside):
            i = int(np.argmax(outside))
            raise ValueError(f"{int(outside.sum())} point(s) lie outside the {w}x{h} px {image_name}, e.g. point {i} "
                             f"at ({out[i, 0]:.6g}, {out[i, 1]:.6g})")
    return out


def _image_shape(shape) -> tuple[int, int]:
    try:
        h, w = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise ValueError(f"shape must be an image shape (H, W), got {shape!r}") from None
    if h < 1 or w < 1:
        raise ValueError(f"shape must be an image shape (H, W) of positive sizes, got {shape!r}")
    return h, w


def _integer(value, integral_float: bool) -> int | None:
    """``value`` as an int when it is one (not a bool); integral floats too when allowed; else None."""
    if isinstance(value, (bool, np.bool_)):
        return None
    if isinstance(value, (int, np.integer)):
        return int(value)
    if integral_float and isinstance(value, (float, np.floating)) and math.isfinite(value) and value == int(value):
        return int(value)
    return None


def positive_int(value, name: str, *, minimum: int = 1, maximum: int | None = None, detail: str = "",
                 integral_float: bool = False) -> int:
    """``value`` as an ``int`` >= ``minimum`` (default 1) and, when given, <= ``maximum``.

    Message: ``"{name} must be a positive integer{detail}, got {value!r}"`` (``"an integer >= m"``
    for another minimum, ``"an integer in [m, M]"`` with a maximum). ``integral_float=True`` also
    accepts floats such as ``4.0``.
    """
    v = _integer(value, integral_float)
    if v is None or v < minimum or (maximum is not None and v > maximum):
        if maximum is not None:
            need = f"an integer in [{minimum}, {maximum}]"
        else:
            need = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
        raise ValueError(f"{name} must be {need}{detail}, got {value!r}")
    return v


def non_negative_int(value, name: str, *, detail: str = "", integral_float: bool = False) -> int:
    """``value`` as an ``int`` >= 0. Message: ``"{name} must be a non-negative integer{detail}, got ..."``."""
    v = _integer(value, integral_float)
    if v is None or v < 0:
        raise ValueError(f"{name} must be a non-negative integer{detail}, got {value!r}")
    return v


def odd_int(value, name: str, *, minimum: int = 3, detail: str = "", integral_float: bool = False) -> int:
    """``value`` as an odd ``int`` >= ``minimum`` (subset sizes, fit windows).

    Message: ``"{name} must be an odd integer >= {minimum}{detail}, got {value!r}"``.
    """
    v = _integer(value, integral_float)
    if v is None or v < minimum or v % 2 == 0:
        raise ValueError(f"{name} must be an odd integer >= {minimum}{detail}, got {value!r}")
    return v


def _real(value) -> float | None:
    """``value`` as a float when it is a real number (not a bool, nor a string); else None."""
    if isinstance(value, (bool, np.bool_)):
        return None
    if isinstance(value, numbers.Real):
        return float(value)
    if isinstance(value, np.ndarray) and value.ndim == 0 and (
            np.issubdtype(value.dtype, np.integer) or np.issubdtype(value.dtype, np.floating)):
        return float(value)
    return None


def positive_float(value, name: str, *, detail: str = "", allow_inf: bool = False) -> float:
    """``value`` as a ``float`` > 0 and finite (``allow_inf``: +inf accepted, e.g. a pinhole's f-number).

    Message: ``"{name} must be a positive finite number{detail}, got {value!r}"``.
    """
    v = _real(value)
    if v is None or not v > 0 or math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise ValueError(f"{name} must be a positive finite number{detail}, got {value!r}")
    return v


def in_range(value, lo: float, hi: float, name: str, *, detail: str = "") -> float:
    """``value`` as a ``float`` in the closed interval ``[lo, hi]``.

    Message: ``"{name} must be in [{lo}, {hi}]{detail}, got {value!r}"`` (``"a number in ..."``
    when it is not a number).
    """
    v = _real(value)
    if v is None:
        raise ValueError(f"{name} must be a number in [{lo}, {hi}]{detail}, got {value!r}")
    if not lo <= v <= hi:
        raise ValueError(f"{name} must be in [{lo}, {hi}]{detail}, got {value!r}")
    return v


def unit_interval(value, name: str, *, detail: str = "") -> float:
    """``value`` as a ``float`` in ``[0, 1]`` (fractions, coverages, reflectances)."""
    return in_range(value, 0, 1, name, detail=detail)


def boolean(value, name: str) -> bool:
    """``value`` as a ``bool`` when it is one (Python or NumPy); anything else (1, "yes", None) is a
    ``ValueError``: a switch given a truthy non-boolean is usually a misplaced argument."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)
