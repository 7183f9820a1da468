"""The virtual lab: physically based images of cameras, mirrors, monitors and speckled surfaces.

Build a :class:`Scene` (or load one with :func:`load_scene`, or take the paper's rig with
:func:`paper_rig`), then :func:`render` what a camera records and :func:`project` where exact
3-D points land. Importing this package compiles no kernel. See docs/lab.md.
"""
from .camera import LabCamera, look_at, stereo_rig
from .io import load_scene, save_scene
from .paper import MIRROR_TILTS_DEG, MonitorPose, PaperRig, paper_fringe_image, paper_rig, tilt_mirror
from .rendering import project, render, screens_window, window_around
from .scene import (
    Displacement,
    Mirror,
    Scene,
    Screen,
    SpeckleCylinder,
    SpeckleDisks,
    SpecklePlane,
    frame_from_normal,
    reflect_points,
    rotation_about,
)

__all__ = [
    "Displacement", "LabCamera", "MIRROR_TILTS_DEG", "Mirror", "MonitorPose", "PaperRig", "Scene", "Screen",
    "SpeckleCylinder", "SpeckleDisks", "SpecklePlane", "frame_from_normal", "load_scene", "look_at",
    "paper_fringe_image", "paper_rig", "project", "reflect_points", "render", "rotation_about", "save_scene",
    "screens_window", "stereo_rig", "tilt_mirror", "window_around",
]
