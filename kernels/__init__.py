"""Warp kernels and their thin launchers (the bottom layer; imports only warp and numpy).

Importing this package compiles nothing and initialises no device. Kernel modules: ``interp``,
``icgn``, ``search``, ``speckle``, ``phase``, ``triangulate``, ``render``; ``distortion`` holds the
lens model (device functions) that ``triangulate`` and ``render`` share. Shared by every layer
(NumPy only): ``images`` (the one image reader/writer) and ``checks`` (argument checks).
"""
from .conventions import PARAMS_1ST, PARAMS_2ND, Status, param_names

__all__ = ["PARAMS_1ST", "PARAMS_2ND", "Status", "param_names", "available_devices", "resolve_device"]


def __getattr__(name):
    # available_devices and resolve_device import warp (0.7-1.6 s): only when asked for, so that the NumPy-only
    # modules (checks, conventions, images) import without it
    if name in ("available_devices", "resolve_device"):
        from . import _device

        return getattr(_device, name)
    raise AttributeError(f"module 'kernels' has no attribute {name!r}")
