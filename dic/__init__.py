"""Specula's user-facing DIC engine: grids, tracking, strain, stereo, results, CLI and the virtual lab.

``dic.track``, ``dic.strain``, ``dic.stereo`` and ``dic.triangulate`` are the functions; their modules
stay importable as ``from dic.track import Tracker`` etc. Importing compiles no kernel.
"""
from . import quality, synth
from .export import write_vtk, write_vtk_series
from .field3d import Field3D, StereoStatus
from .io import read_image, write_image
from .plots.fields import write_figures
from .sequence import read_stereo, stereo_sequence, track_sequence
from .stereo import StereoCorrelation, stereo
from .store import ResultWriter, read_results
from .strain import StrainField, strain
from .track import Field2D, Tracker, grid, track
from .triangulate import Triangulation, triangulate, undistort_points

__all__ = [
    "synth", "quality",
    "Field2D", "Tracker", "grid", "track",
    "StrainField", "strain",
    "ResultWriter", "read_results", "read_image", "write_image",
    "Triangulation", "triangulate", "undistort_points",
    "Field3D", "StereoStatus", "StereoCorrelation", "stereo", "read_stereo", "stereo_sequence", "track_sequence",
    "write_figures", "write_vtk", "write_vtk_series",
]
