"""Import/export of cameras and rigs: OpenCV FileStorage, DICe camera-system XML, VIC-3D calibration XML."""
import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.camera import Camera, rotation_angle_deg, rotation_from_vector
from calibration.formats import (
    euler_from_rotation,
    load_dice_xml,
    load_opencv,
    load_vic3d_xml,
    rotation_from_euler,
    save_dice_xml,
    save_opencv,
    save_vic3d_xml,
)
from calibration.stereo import StereoRig


@pytest.fixture
def rig():
    left = Camera([[4050.0, 0, 1172.8], [0, 4050.8, 868.1], [0, 0, 1]], [-0.06, 0.09, 2e-4, -1e-4, 0.003],
                  (2352, 1728), "left")
    right = Camera([[4041.9, 0, 1181.5], [0, 4042.3, 861.3], [0, 0, 1]], [-0.055, 0.08, -1e-4, 2e-4, 0.0],
                   (2352, 1728), "right")
    return StereoRig(left, right, rotation_from_vector(np.radians([0.4, -17.4, 0.2])), [-1631.07, 2.5, 249.19])


@pytest.fixture
def radial_rig(rig):
    cams = [Camera(c.K, [c.dist[0], c.dist[1], 0, 0, c.dist[4]], c.size, c.name) for c in (rig.left, rig.right)]
    return StereoRig(cams[0], cams[1], rig.R_right_left, rig.t_right_left)


def _same(a: StereoRig, b: StereoRig, tol=1e-9):
    assert rotation_angle_deg(a.R_right_left, b.R_right_left) < tol
    assert np.max(np.abs(a.t_right_left - b.t_right_left)) < tol * 1e3
    for ca, cb in ((a.left, b.left), (a.right, b.right)):
        assert np.max(np.abs(ca.K - cb.K)) < tol * 1e3 and np.max(np.abs(ca.dist8 - cb.dist8)) < tol
        assert ca.size == cb.size


def test_euler_convention_matches_scipy(rng):
    for _ in range(10):
        a, b, g = rng.uniform(-170, 170), rng.uniform(-80, 80), rng.uniform(-170, 170)
        # DICe / VIC-3D: R = Rz(γ) Ry(β) Rx(α) = scipy's extrinsic "xyz" sequence
        R = Rotation.from_euler("xyz", [a, b, g], degrees=True).as_matrix()
        assert np.allclose(rotation_from_euler(a, b, g), R, atol=1e-14)
        assert np.allclose(euler_from_rotation(R), (a, b, g), atol=1e-9)


@pytest.mark.parametrize("ext", ["yml", "xml", "json"])
def test_opencv_round_trip(rig, tmp_path, ext):
    path = tmp_path / f"rig.{ext}"
    save_opencv(path, rig)
    _same(load_opencv(path), rig, tol=1e-12)
    cam_path = tmp_path / f"cam.{ext}"
    save_opencv(cam_path, rig.left)
    cam = load_opencv(cam_path)
    assert np.array_equal(cam.K, rig.left.K) and np.array_equal(cam.dist, rig.left.dist) and cam.name == "left"


def test_opencv_reads_a_file_written_by_plain_filestorage(rig, tmp_path):
    """Keys as OpenCV's calibration sample writes them, by cv2.FileStorage directly (independent writer)."""
    path = str(tmp_path / "out_camera_data.yml")
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 2352)
    fs.write("image_height", 1728)
    fs.write("camera_matrix", rig.left.K)
    fs.write("distortion_coefficients", rig.left.dist.reshape(-1, 1))
    fs.write("avg_reprojection_error", 0.04)
    fs.release()
    cam = load_opencv(path)
    assert np.array_equal(cam.K, rig.left.K) and np.array_equal(cam.dist, rig.left.dist)
    assert cam.size == (2352, 1728)


def test_opencv_bad_files(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        load_opencv(tmp_path / "missing.yml")
    path = str(tmp_path / "empty.yml")
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    fs.write("something", 1)
    fs.release()
    with pytest.raises(ValueError, match="neither camera_matrix"):
        load_opencv(path)
    with pytest.raises(ValueError, match="Camera or a StereoRig"):
        save_opencv(tmp_path / "x.yml", "rig")


def test_dice_round_trip(rig, tmp_path):
    path = tmp_path / "cam_sys.xml"
    save_dice_xml(path, rig)
    text = path.read_text()
    assert 'value="DICe_xml_camera_system_file"' in text and 'name="rotation_3x3_matrix"' in text
    assert 'name="IMAGE_HEIGHT_WIDTH" type="string" value="{ 1728, 2352 }"' in text
    _same(load_dice_xml(path), rig, tol=1e-12)


def test_dice_relative_extrinsics_with_euler_angles(tmp_path):
    """A hand-written DICe file in the layout of DICe's own test data: camera-to-camera extrinsics
    given as TX TY TZ and ALPHA BETA GAMMA (degrees), OpenCV distortion."""
    path = tmp_path / "cam_sys.xml"
    path.write_text("""<ParameterList>
<Parameter name="xml_file_format" type="string" value="DICe_xml_camera_system_file" />
<Parameter name="system_type_3D" type="string" value="OPENCV" />
<Parameter name="extrinsics_relative_camera_to_camera" type="bool" value="true" />
<ParameterList name="CAMERA 0">
<Parameter name="CAMERA_ID" type="string" value="left" />
<Parameter name="CX" type="double" value="640.5" /><Parameter name="CY" type="double" value="400.25" />
<Parameter name="FX" type="double" value="2400.0" /><Parameter name="FY" type="double" value="2399.0" />
<Parameter name="K1" type="double" value="0.05" />
<Parameter name="LENS_DISTORTION_MODEL" type="string" value="OPENCV_LENS_DISTORTION" />
<Parameter name="IMAGE_HEIGHT_WIDTH" type="string" value="{ 800, 1280 }" />
</ParameterList>
<ParameterList name="CAMERA 1">
<Parameter name="CAMERA_ID" type="string" value="right" />
<Parameter name="CX" type="double" value="630.0" /><Parameter name="CY" type="double" value="395.0" />
<Parameter name="FX" type="double" value="2380.0" /><Parameter name="FY" type="double" value="2381.0" />
<Parameter name="P2" type="double" value="0.001" />
<Parameter name="LENS_DISTORTION_MODEL" type="string" value="OPENCV_LENS_DISTORTION" />
<Parameter name="TX" type="double" value="130.5" /><Parameter name="TY" type="double" value="-0.6" />
<Parameter name="TZ" type="double" value="17.0" />
<Parameter name="ALPHA" type="double" value="0.09" /><Parameter name="BETA" type="double" value="-18.0" />
<Parameter name="GAMMA" type="double" value="-0.08" />
<Parameter name="IMAGE_HEIGHT_WIDTH" type="string" value="{ 800, 1280 }" />
</ParameterList>
</ParameterList>
""")
    rig = load_dice_xml(path)
    R = Rotation.from_euler("xyz", [0.09, -18.0, -0.08], degrees=True).as_matrix()
    assert np.allclose(rig.R_right_left, R, atol=1e-12) and np.allclose(rig.t_right_left, [130.5, -0.6, 17.0])
    assert rig.left.size == (1280, 800) and rig.left.dist[0] == 0.05 and rig.right.dist[3] == 0.001
    assert rig.right.fx == 2380.0 and rig.left.cy == 400.25


def test_dice_bad_files(tmp_path):
    path = tmp_path / "bad.xml"
    path.write_text("<ParameterList><Parameter name=\"xml_file_format\" type=\"string\" value=\"other\" /></ParameterList>")
    with pytest.raises(ValueError, match="not a DICe camera-system file"):
        load_dice_xml(path)
    path.write_text("<ParameterList><Parameter name=")
    with pytest.raises(ValueError, match="not well-formed XML"):
        load_dice_xml(path)


def test_vic3d_round_trip(radial_rig, tmp_path):
    path = tmp_path / "cal.xml"
    save_vic3d_xml(path, radial_rig)
    text = path.read_text(encoding="iso-8859-1")
    # one camera per line, as DICe's line-tokenising VIC-3D reader expects: 3 + 8 + 1 + 6 + 1 tokens
    line = next(ln for ln in text.splitlines() if "<camera id=\"1\">" in ln)
    tokens = [t for t in line.replace("<", " ").replace(">", " ").replace('"', " ").split() if t]
    assert tokens[0] == "camera" and tokens[11] == "orientation" and len(tokens) == 19
    _same(load_vic3d_xml(path), radial_rig, tol=1e-9)  # written with 13 significant digits


def test_vic3d_hand_written_file(tmp_path):
    """VIC-3D layout with a world frame between the cameras (both cameras have orientations)."""
    path = tmp_path / "project.z3d.xml"
    path.write_text("""<?xml version="1.0" encoding="ISO-8859-1"?>
<!DOCTYPE vpml>
<project dir="C:/data">
 <calibration lri="calibration">
  <camera id="0">6.4e+02 4.0e+02 2.4e+03 2.4e+03 0.0e+00 -0.1 0.05 0.0<orientation>180.0 9.0 0.0 -63.0 0.0 18.0</orientation>
  </camera>
  <camera id="1">6.3e+02 3.9e+02 2.38e+03 2.38e+03 0.0e+00 -0.09 0.0 0.0<orientation>-180.0 -9.0 0.0 65.0 -0.5 15.0</orientation>
  </camera>
 </calibration>
 <projectaois lri="projectaois"><aoinode><polygonmask width="1280" height="800" lri="polygonmask"/></aoinode></projectaois>
</project>
""", encoding="iso-8859-1")
    rig = load_vic3d_xml(path)
    R0 = Rotation.from_euler("xyz", [180.0, 9.0, 0.0], degrees=True).as_matrix()
    R1 = Rotation.from_euler("xyz", [-180.0, -9.0, 0.0], degrees=True).as_matrix()
    R = R1 @ R0.T
    assert np.allclose(rig.R_right_left, R, atol=1e-12)
    assert np.allclose(rig.t_right_left, np.array([65.0, -0.5, 15.0]) - R @ [-63.0, 0.0, 18.0], atol=1e-9)
    assert rig.left.size == (1280, 800) and np.allclose(rig.left.dist, [-0.1, 0.05, 0, 0, 0])
    # the baseline is the distance between the two camera centres in the world frame
    C0, C1 = -R0.T @ [-63.0, 0.0, 18.0], -R1.T @ [65.0, -0.5, 15.0]
    assert rig.baseline == pytest.approx(np.linalg.norm(C1 - C0), rel=1e-12)


def test_vic3d_refuses_what_it_cannot_hold(rig, radial_rig, tmp_path):
    with pytest.raises(ValueError, match="tangential/rational distortion"):
        save_vic3d_xml(tmp_path / "cal.xml", rig)
    save_vic3d_xml(tmp_path / "cal.xml", rig, allow_lossy=True)
    assert np.all(load_vic3d_xml(tmp_path / "cal.xml").left.dist[2:4] == 0)
    path = tmp_path / "nosize.xml"
    path.write_text("<calibration><camera id=\"0\">1 2 3 4 0 0 0 0<orientation>0 0 0 0 0 0</orientation></camera>"
                    "<camera id=\"1\">1 2 3 4 0 0 0 0<orientation>0 0 0 1 0 0</orientation></camera></calibration>")
    with pytest.raises(ValueError, match="pass image_size"):
        load_vic3d_xml(path)
    assert load_vic3d_xml(path, image_size=(100, 80)).baseline == pytest.approx(1.0)
    path.write_text("<calibration><camera id=\"0\">1 2 3<orientation>0 0 0 0 0 0</orientation></camera>"
                    "<camera id=\"1\">1 2 3<orientation>0 0 0 1 0 0</orientation></camera></calibration>")
    with pytest.raises(ValueError, match="expected 8 intrinsics"):
        load_vic3d_xml(path, image_size=(100, 80))


VIC_SPLIT = """<?xml version="1.0" encoding="ISO-8859-1"?>
<!DOCTYPE vpml>
<project>
 <calibration lri="calibration">
  <camera id="0"><intrinsics>640.0 400.0 2400.0 2401.0 0.5</intrinsics><orientation>180.0 9.0 0.0 -63.0 0.0 18.0</orientation><distortion>-0.1 0.05 0.002</distortion></camera>
  <camera id="1">
   <intrinsics>630.0 390.0 2380.0 2380.0 0.0</intrinsics>
   <orientation>-180.0 -9.0 0.0 65.0 -0.5 15.0</orientation>
   <distortion>-0.09</distortion>
  </camera>
 </calibration>
 <projectaois lri="projectaois"><aoinode><polygonmask width="1280" height="800" lri="polygonmask"/></aoinode></projectaois>
</project>
"""


def test_vic3d_intrinsics_orientation_distortion_layout(tmp_path):
    """The <intrinsics>/<orientation>/<distortion> layout of VIC-3D project files (before: refused with
    'expected 8 intrinsics'); the same rig as the one-line layout with the same numbers."""
    path = tmp_path / "project.xml"
    path.write_text(VIC_SPLIT, encoding="iso-8859-1")
    rig = load_vic3d_xml(path)
    R0 = Rotation.from_euler("xyz", [180.0, 9.0, 0.0], degrees=True).as_matrix()
    R1 = Rotation.from_euler("xyz", [-180.0, -9.0, 0.0], degrees=True).as_matrix()
    assert np.allclose(rig.R_right_left, R1 @ R0.T, atol=1e-12)
    assert np.allclose(rig.t_right_left, np.array([65.0, -0.5, 15.0]) - R1 @ R0.T @ [-63.0, 0.0, 18.0], atol=1e-9)
    assert np.allclose(rig.left.K, [[2400.0, 0.5, 640.0], [0, 2401.0, 400.0], [0, 0, 1]])
    assert np.allclose(rig.left.dist, [-0.1, 0.05, 0, 0, 0.002]) and np.allclose(rig.right.dist, [-0.09, 0, 0, 0, 0])
    assert rig.left.size == (1280, 800)
    one_line = tmp_path / "one_line.xml"
    one_line.write_text(VIC_SPLIT.replace(
        '<intrinsics>640.0 400.0 2400.0 2401.0 0.5</intrinsics><orientation>180.0 9.0 0.0 -63.0 0.0 18.0</orientation>'
        '<distortion>-0.1 0.05 0.002</distortion>',
        '640.0 400.0 2400.0 2401.0 0.5 -0.1 0.05 0.002<orientation>180.0 9.0 0.0 -63.0 0.0 18.0</orientation>'))
    assert np.array_equal(load_vic3d_xml(one_line).left.K, rig.left.K)
    assert np.array_equal(load_vic3d_xml(one_line).left.dist, rig.left.dist)
    for old, new, msg in [("<distortion>-0.09</distortion>", "<distortion>-0.09 0 0 0.01</distortion>", "not zero"),
                          ("630.0 390.0 2380.0 2380.0 0.0", "630.0 390.0 2380.0", "CX CY FX FY FS"),
                          ("<orientation>-180.0 -9.0 0.0 65.0 -0.5 15.0</orientation>", "", "no <orientation>"),
                          ("630.0 390.0", "630.0 abc", "<intrinsics> must be a number")]:
        path.write_text(VIC_SPLIT.replace(old, new))
        with pytest.raises(ValueError, match=msg):
            load_vic3d_xml(path)
    path.write_text(VIC_SPLIT.replace("<distortion>-0.09 0 0 0.01</distortion>", "").replace(
        "<distortion>-0.09</distortion>", "<distortion>-0.09 0 0 0</distortion>"))
    assert np.allclose(load_vic3d_xml(path).right.dist, [-0.09, 0, 0, 0, 0])  # further terms that are zero


def test_load_rig_detects_every_format_from_the_content(rig, radial_rig, tmp_path):
    """One entry point for every format, whatever the file is called (before: 'specula stereo --rig' read
    only Specula's JSON and refused a VIC-3D, OpenCV or DICe file as 'not valid JSON')."""
    from calibration.formats import CALIBRATION_FORMATS, detect_calibration_format, load_camera, load_rig

    writers = {"specula-rig": lambda p: radial_rig.save(p), "opencv": lambda p: save_opencv(p, radial_rig),
               "dice": lambda p: save_dice_xml(p, radial_rig), "vic3d": lambda p: save_vic3d_xml(p, radial_rig)}
    for fmt, write in writers.items():
        for name in ("rig.json", "rig.yml", "rig.xml", "rig.cal"):  # the suffix says nothing
            path = tmp_path / f"{fmt}_{name}"
            write(path)
            assert detect_calibration_format(path) == fmt
            _same(load_rig(path), radial_rig, tol=1e-9)
            assert np.array_equal(load_camera(path, which="right").K, load_rig(path).right.K)
    for ext in ("yml", "xml", "json"):  # OpenCV's three syntaxes (its JSON has // comments)
        save_opencv(tmp_path / f"cv.{ext}", rig)
        _same(load_rig(tmp_path / f"cv.{ext}"), rig, tol=1e-12)
    (tmp_path / "split.txt").write_text(VIC_SPLIT)
    assert detect_calibration_format(tmp_path / "split.txt") == "vic3d"
    # cameras
    rig.left.save(tmp_path / "cam.yml")
    save_opencv(tmp_path / "cam.json", rig.left)
    for p in ("cam.yml", "cam.json"):
        cam = load_camera(tmp_path / p)
        assert np.array_equal(cam.K, rig.left.K) and np.array_equal(cam.dist, rig.left.dist)
    with pytest.raises(ValueError, match="holds a stereo rig .*which='left' or 'right'"):
        load_camera(tmp_path / "dice_rig.xml")
    with pytest.raises(ValueError, match="holds one camera .*not a stereo rig"):
        load_rig(tmp_path / "cam.yml")
    # a file that fits no format names them all
    for text in ("hello", "<foo/>", '{"a": 1}', '{"schema": "specula.mirror_pose", "schema_version": 1}', ""):
        (tmp_path / "other.txt").write_text(text)
        with pytest.raises(ValueError, match="not a calibration file Specula reads") as err:
            load_rig(tmp_path / "other.txt")
        assert all(f.split(" (")[0] in str(err.value) for f in CALIBRATION_FORMATS)
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_rig(tmp_path / "broken.json")
    with pytest.raises(ValueError, match="does not exist"):
        load_rig(tmp_path / "missing.xml")
    # the image size: from the file, else from image_size (DIC passes its images' size)
    nosize = tmp_path / "nosize.xml"
    nosize.write_text(VIC_SPLIT.replace('<polygonmask width="1280" height="800" lri="polygonmask"/>', ""))
    with pytest.raises(ValueError, match=r"does not record the image size; pass image_size"):
        load_rig(nosize)
    assert load_rig(nosize, image_size=(1280, 800)).right.size == (1280, 800)
    assert load_rig(tmp_path / "split.txt", image_size=(64, 48)).left.size == (1280, 800)  # the file's size wins
    with pytest.raises(ValueError, match="image_size must be"):
        load_rig(nosize, image_size=(0, 5))
