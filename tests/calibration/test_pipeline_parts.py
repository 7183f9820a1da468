"""The parts of the calibration pipeline (calibration.views, .stages, .reports, .posefiles): what each
checks, and that the pipeline's entry points are the same objects as the parts'."""
import numpy as np
import pytest

import calibration.pipeline as pipeline
from calibration import posefiles, reports, stages, views
from calibration.camera import Camera
from calibration.targets import PhaseTarget, render_view

CAM = Camera(K=[[1000, 0, 399.5], [0, 1000, 299.5], [0, 0, 1]], size=(800, 600))
TARGET = PhaseTarget()


def test_pipeline_reexports_the_parts():
    assert pipeline.ViewResult is views.ViewResult and pipeline.StereoView is views.StereoView
    assert pipeline.filter_detection is views.filter_detection
    assert pipeline.MirrorCalibration is stages.MirrorCalibration
    assert pipeline.calibrate_rig_from_mirrors is stages.calibrate_rig_from_mirrors
    assert pipeline.MIRROR_POSE_SCHEMA == posefiles.MIRROR_POSE_SCHEMA == "specula.mirror_calibration"
    for name in pipeline.__all__:
        assert getattr(pipeline, name) is not None


def test_detect_view_stack_is_detect_view_on_an_array():
    centre = np.array([(TARGET.screen[0] - 1) / 2, (TARGET.screen[1] - 1) / 2, 0.0]) * TARGET.pixel_pitch
    R, t = np.eye(3), np.array([0.0, 0.0, 850.0]) - centre
    imgs = render_view(TARGET, CAM, R, t, noise_sigma=1.0, seed=1, supersample=1)
    a = views.detect_view_stack(imgs, TARGET, name="v", device="cpu")
    b = pipeline.detect_view(imgs, TARGET, name="v", device="cpu")
    assert a.ok and len(a.detection) == 18
    np.testing.assert_array_equal(a.detection.image_points, b.detection.image_points)
    with pytest.raises(ValueError, match=r"\(N, H, W\)"):
        views.detect_view_stack(imgs[0], TARGET)
    with pytest.raises(ValueError, match="the target needs 4"):
        views.detect_view_stack(imgs[:3], TARGET)
    with pytest.raises(ValueError, match="PhaseTarget"):
        views.detect_view_stack(imgs, "target")
    with pytest.raises(ValueError, match="mode"):
        views.detect_view_stack(imgs, TARGET, mode="lines")


@pytest.mark.parametrize("report", [reports.intrinsics_report, reports.mirror_report, reports.rig_report,
                                    reports.checkerboard_stereo_report])
def test_reports_refuse_other_objects(report):
    with pytest.raises(ValueError, match="expected a calibration.stages"):
        report(object())


def test_pose_files_refuse_other_objects(tmp_path):
    with pytest.raises(ValueError, match="MirrorCalibration"):
        posefiles.mirror_pose_dict({"result": None})
    with pytest.raises(ValueError, match="must be a dict"):
        posefiles.mirror_pose_fields([1, 2])
    with pytest.raises(ValueError, match="schema"):
        posefiles.mirror_pose_fields({"schema": "specula.stereo_rig", "schema_version": 1})
