"""Camera and rig models, phase targets, feature extraction and calibration (float64, NumPy/SciPy/OpenCV).

See docs/calibration.md and docs/targets.md.
"""
from .camera import Camera
from .detect import (
    DenseDecoding,
    DetectionError,
    DotDetection,
    decode_dense,
    demodulate_images,
    dense_correspondences,
    detect_checkerboard,
    detect_circle_grid,
    detect_dots,
    detect_dots_in_images,
)
from .formats import (
    as_rig,
    load_camera,
    load_dice_xml,
    load_opencv,
    load_rig,
    load_vic3d_xml,
    save_dice_xml,
    save_opencv,
    save_vic3d_xml,
)
from .intrinsics import IntrinsicsResult, calibrate_intrinsics
from .mirror import MirrorPlane, joint_mirror_stereo, mirror_closed_form, mirror_extrinsics
from .stereo import StereoRig, reconstruct_target, rig_from_mirror, stereo_calibrate
from .targets import CheckerboardTarget, CircleGridTarget, PhaseTarget, load_target, make_cell_code, render_view

__all__ = [
    "Camera",
    "CheckerboardTarget", "CircleGridTarget", "PhaseTarget", "load_target", "make_cell_code", "render_view",
    "DenseDecoding", "DetectionError", "DotDetection", "decode_dense", "demodulate_images", "dense_correspondences",
    "detect_checkerboard", "detect_circle_grid", "detect_dots", "detect_dots_in_images",
    "IntrinsicsResult", "calibrate_intrinsics",
    "MirrorPlane", "joint_mirror_stereo", "mirror_closed_form", "mirror_extrinsics",
    "StereoRig", "reconstruct_target", "rig_from_mirror", "stereo_calibrate", "as_rig",
    "load_dice_xml", "load_opencv", "load_vic3d_xml", "save_dice_xml", "save_opencv", "save_vic3d_xml",
    "load_rig", "load_camera",
]
