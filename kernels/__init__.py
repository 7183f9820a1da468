"""Warp kernels and their thin launchers (the bottom layer; imports only warp and numpy).

Importing this package compiles nothing and initialises no device. Kernel modules: ``interp``,
``icgn``, ``search``, ``speckle``, ``phase``, ``triangulate``, ``render``; ``distortion`` holds the
lens model (device functions) that ``triangulate`` and ``render`` share. Shared by every layer
(NumPy only): ``images`` (the one image reader/writer) and ``checks`` (argument checks).
"""
from ._device import available_devices, resolve_device
from .conventions import PARAMS_1ST, PARAMS_2ND, Status, param_names

__all__ = ["PARAMS_1ST", "PARAMS_2ND", "Status", "param_names", "available_devices", "resolve_device"]
