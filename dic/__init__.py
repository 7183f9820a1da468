"""Specula's user-facing DIC engine: grids, tracking, strain, stereo, results, exports, CLI and the virtual lab.

The public surface is the list below (``__all__``): ``dic.track``, ``dic.strain``, ``dic.stereo`` and
``dic.triangulate`` are functions, and the classes that go with them are here too (``dic.Tracker``,
``dic.StrainPlan``, ``dic.StereoCorrelation``, ...). Their implementation modules are private
(``dic/_track.py``, ``dic/_strain.py``, ``dic/_stereo.py``, ``dic/_triangulate.py``), as in
scikit-image, so that each public name is one thing. Sub-packages with their own surface stay
modules: ``dic.sequence``, ``dic.store``, ``dic.export``, ``dic.postprocess``, ``dic.synth``,
``dic.quality``, ``dic.plots``, ``dic.lab``, ``dic.correlation``, ``dic.io``.

Every export is ``dic.write_<format>`` (``write_csv``, ``write_mat``, ``write_netcdf``, ``write_vtk``,
``write_vtk_series``, ``write_pvd``) or ``dic.export_results(source, format, out)``; tables are
``dic.to_dataframe`` / ``dic.to_xarray``.

The names are imported when first used (PEP 562), not by ``import dic``: the CLI's post-processing
verbs need none of Warp, the correlation or the plots (docs/architecture.md).
"""
from __future__ import annotations

import importlib
import importlib.util
from typing import TYPE_CHECKING

# public name -> (module, attribute; None: the module itself)
_EXPORTS = {
    # tracking (2-D)
    "Tracker": ("._track", "Tracker"), "track": ("._track", "track"), "grid": ("._track", "grid"),
    "Field2D": (".field2d", "Field2D"),
    # strain
    "strain": ("._strain", "strain"), "StrainField": ("._strain", "StrainField"),
    "StrainPlan": ("._strain", "StrainPlan"), "grid_layout": ("._strain", "grid_layout"),
    # stereo
    "StereoCorrelation": ("._stereo", "StereoCorrelation"), "stereo": ("._stereo", "stereo"),
    "StereoMatch": ("._stereo", "StereoMatch"),
    "Field3D": (".field3d", "Field3D"), "StereoStatus": (".field3d", "StereoStatus"),
    "Triangulation": ("._triangulate", "Triangulation"), "triangulate": ("._triangulate", "triangulate"),
    "undistort_points": ("._triangulate", "undistort_points"),
    # sequences and their run records
    "track_sequence": (".sequence", "track_sequence"), "stereo_sequence": (".sequence", "stereo_sequence"),
    "SequenceSummary": (".sequence", "SequenceSummary"),
    "TrackOptions": (".sequence", "TrackOptions"), "StereoOptions": (".sequence", "StereoOptions"),
    # result files
    "ResultWriter": (".store", "ResultWriter"), "ResultReader": (".store", "ResultReader"),
    "ResultFrames": (".store", "ResultFrames"), "read_results": (".store", "read_results"),
    "read_stereo": (".store", "read_stereo"), "read_field": (".store", "read_field"),
    "repair_results": (".store", "repair_results"),
    # exports: one naming scheme, write_<format>
    "write_csv": (".export", "write_csv"), "write_mat": (".export", "write_mat"),
    "write_netcdf": (".export", "write_netcdf"), "write_vtk": (".export", "write_vtk"),
    "write_vtk_series": (".export", "write_vtk_series"), "write_pvd": (".export", "write_pvd"),
    "export_results": (".export", "export_results"),
    "to_dataframe": (".export", "to_dataframe"), "to_xarray": (".export", "to_xarray"),
    # declared cracks (dic.cracks)
    "Crack": (".cracks", "Crack"), "crack_opening": (".cracks", "crack_opening"),
    # images, figures, synthetic data, speckle quality
    "read_image": (".io", "read_image"), "write_image": (".io", "write_image"),
    "write_figures": (".plots.fields", "write_figures"),
    "write_report": (".report", "write_report"),
    "synth": (".synth", None), "quality": (".quality", None),
}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        module, attribute = _EXPORTS[name]
        value = importlib.import_module(module, __name__)
        if attribute is not None:
            value = getattr(value, attribute)
        globals()[name] = value  # once: later lookups do not come here
        return value
    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        return importlib.import_module(f".{name}", __name__)  # a public sub-package, e.g. dic.sequence
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # the names for type checkers and IDEs
    from . import quality, synth  # noqa: F401
    from ._stereo import StereoCorrelation, StereoMatch, stereo  # noqa: F401
    from ._strain import StrainField, StrainPlan, grid_layout, strain  # noqa: F401
    from ._track import Tracker, grid, track  # noqa: F401
    from ._triangulate import Triangulation, triangulate, undistort_points  # noqa: F401
    from .cracks import Crack, crack_opening  # noqa: F401
    from .export import (  # noqa: F401
        export_results,
        to_dataframe,
        to_xarray,
        write_csv,
        write_mat,
        write_netcdf,
        write_pvd,
        write_vtk,
        write_vtk_series,
    )
    from .field2d import Field2D  # noqa: F401
    from .field3d import Field3D, StereoStatus  # noqa: F401
    from .io import read_image, write_image  # noqa: F401
    from .plots.fields import write_figures  # noqa: F401
    from .report import write_report  # noqa: F401
    from .sequence import SequenceSummary, StereoOptions, TrackOptions, stereo_sequence, track_sequence  # noqa: F401
    from .store import (  # noqa: F401
        ResultFrames,
        ResultReader,
        ResultWriter,
        read_field,
        read_results,
        read_stereo,
        repair_results,  # noqa: F401
    )
