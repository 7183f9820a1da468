"""Warp kernels and their thin launchers (the bottom layer; imports only warp and numpy).

Importing this package compiles nothing and initialises no device.
"""
from .conventions import PARAMS_1ST, PARAMS_2ND, Status, param_names
from ._device import available_devices, resolve_device

__all__ = ["PARAMS_1ST", "PARAMS_2ND", "Status", "param_names", "available_devices", "resolve_device"]
