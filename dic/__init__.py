"""Specula's user-facing DIC engine: grids, tracking, strain, stereo, results, CLI and the virtual lab.

``dic.track``, ``dic.strain``, ``dic.stereo`` and ``dic.triangulate`` are the functions; their modules
stay importable as ``from dic.track import Tracker`` etc. Importing compiles no kernel.

The names below are imported when first used (PEP 562), not by ``import dic``: the CLI's
post-processing verbs need none of Warp, the correlation or the plots, and importing them all
took 1.2-2.6 s of every command (issue 25). ``dic.<submodule>`` works as before.
"""
from __future__ import annotations

import importlib
import sys
import types
from typing import TYPE_CHECKING

# public name -> (module, attribute; None: the module itself)
_EXPORTS = {
    "synth": (".synth", None), "quality": (".quality", None),
    "write_vtk": (".export", "write_vtk"), "write_vtk_series": (".export", "write_vtk_series"),
    "Field3D": (".field3d", "Field3D"), "StereoStatus": (".field3d", "StereoStatus"),
    "read_image": (".io", "read_image"), "write_image": (".io", "write_image"),
    "write_figures": (".plots.fields", "write_figures"),
    "read_stereo": (".sequence", "read_stereo"), "stereo_sequence": (".sequence", "stereo_sequence"),
    "track_sequence": (".sequence", "track_sequence"),
    "StereoCorrelation": (".stereo", "StereoCorrelation"), "stereo": (".stereo", "stereo"),
    "ResultWriter": (".store", "ResultWriter"), "read_results": (".store", "read_results"),
    "StrainField": (".strain", "StrainField"), "strain": (".strain", "strain"),
    "Field2D": (".track", "Field2D"), "Tracker": (".track", "Tracker"), "grid": (".track", "grid"),
    "track": (".track", "track"),
    "Triangulation": (".triangulate", "Triangulation"), "triangulate": (".triangulate", "triangulate"),
    "undistort_points": (".triangulate", "undistort_points"),
}

__all__ = [
    "synth", "quality",
    "Field2D", "Tracker", "grid", "track",
    "StrainField", "strain",
    "ResultWriter", "read_results", "read_image", "write_image",
    "Triangulation", "triangulate", "undistort_points",
    "Field3D", "StereoStatus", "StereoCorrelation", "stereo", "read_stereo", "stereo_sequence", "track_sequence",
    "write_figures", "write_vtk", "write_vtk_series",
]


#: names that are functions of the submodule of the same name: ``dic.track`` is the function
#: :func:`dic.track.track`, whichever imported the submodule first
_FUNCTIONS_OF_SUBMODULES = ("track", "strain", "stereo", "triangulate")


class _Package(types.ModuleType):
    def __setattr__(self, name, value):
        # the import system binds a submodule to its name in the package when it loads it: keep the function
        if name in _FUNCTIONS_OF_SUBMODULES and isinstance(value, types.ModuleType):
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


def __getattr__(name: str):
    if name in _EXPORTS:
        module, attribute = _EXPORTS[name]
        value = importlib.import_module(module, __name__)
        if attribute is not None:
            value = getattr(value, attribute)
        globals()[name] = value  # once: later lookups do not come here
        return value
    if importlib.util.find_spec(f"{__name__}.{name}") is not None:  # a submodule, e.g. dic.sequence
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # the names for type checkers and IDEs
    from . import quality, synth  # noqa: F401
    from .export import write_vtk, write_vtk_series  # noqa: F401
    from .field3d import Field3D, StereoStatus  # noqa: F401
    from .io import read_image, write_image  # noqa: F401
    from .plots.fields import write_figures  # noqa: F401
    from .sequence import read_stereo, stereo_sequence, track_sequence  # noqa: F401
    from .stereo import StereoCorrelation, stereo  # noqa: F401
    from .store import ResultWriter, read_results  # noqa: F401
    from .strain import StrainField, strain  # noqa: F401
    from .track import Field2D, Tracker, grid, track  # noqa: F401
    from .triangulate import Triangulation, triangulate, undistort_points  # noqa: F401
