"""The calibration stages on detected views (the paper behind Specula, Optics Express 27(6), 9040,
2019, Section 2): intrinsics (:mod:`.intrinsics`), the mirror pose of each camera (:mod:`.mirror`)
and the stereo rig (:mod:`.stereo`). :mod:`calibration.pipeline` runs them from image files.
"""
from .intrinsics import IntrinsicsCalibration, calibrate_intrinsics_from_detections
from .mirror import MirrorCalibration, calibrate_mirror_from_detections
from .stereo import CheckerboardStereo, RigCalibration, calibrate_rig_from_mirrors

__all__ = ["IntrinsicsCalibration", "calibrate_intrinsics_from_detections", "MirrorCalibration",
           "calibrate_mirror_from_detections", "RigCalibration", "CheckerboardStereo", "calibrate_rig_from_mirrors"]
