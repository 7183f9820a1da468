"""Import and export of cameras and stereo rigs in other tools' formats, so rigs move between tools.

* **OpenCV YAML/XML** (``cv2.FileStorage``): a single camera as in OpenCV's ``calibration.cpp``
  sample (``image_width``, ``image_height``, ``camera_matrix``, ``distortion_coefficients``), a rig as
  in its ``stereo_calib.cpp`` sample (``M1 D1 M2 D2 R T`` plus the image sizes). ``R, T`` are
  OpenCV's stereo extrinsics ``x_2 = R x_1 + T`` = Specula's ``R_right_left, t_right_left`` (mm).
* **DICe camera-system XML** (Teuchos ``ParameterList``), as read by DICe's
  ``Camera_System::read_camera_system_file`` (src/core/DICe_CameraSystem.cpp): ``xml_file_format =
  DICe_xml_camera_system_file``, sublists ``CAMERA 0`` / ``CAMERA 1`` with ``CX CY FX FY FS K1..K6
  P1 P2``, ``LENS_DISTORTION_MODEL = OPENCV_LENS_DISTORTION``, ``IMAGE_HEIGHT_WIDTH = { h, w }``,
  world→camera extrinsics ``TX TY TZ`` and a ``rotation_3x3_matrix`` sublist (rows ``ROW 0..2``) or
  Euler angles ``ALPHA BETA GAMMA`` (degrees, ``R = Rz(γ) Ry(β) Rx(α)``, DICe_Camera.cpp).
  Specula writes the left camera frame as the world frame (camera 0 identity).
* **VIC-3D project calibration** (``<calibration><camera id="0">CX CY FX FY FS κ1 κ2 κ3
  <orientation>α β γ tx ty tz</orientation></camera>…``), the layout DICe's VIC-3D reader parses
  (same source file): 8 intrinsics per camera, world→camera orientation with the same Euler
  convention, image size from ``<polygonmask width= height=>``. Assumptions we could not verify
  against Correlated Solutions' documentation, stated so they can be checked: κ1..κ3 act on
  r², r⁴, r⁶ of normalised coordinates (= OpenCV k1, k2, k3; DICe itself marks its VIC-3D model
  as unconfirmed), FS is ``K[0, 1]`` in pixels (as DICe's projection uses it), lengths in mm.
  The format has no tangential or rational terms: exporting a camera that has them raises
  ``ValueError`` unless ``allow_lossy=True``. VIC-3D's own world frame sits between the cameras;
  Specula exports the left camera frame as world, which any reader handles since only
  ``R_1 R_0ᵀ`` and ``t_1 − R_1 R_0ᵀ t_0`` matter.
"""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET

import numpy as np

from .camera import Camera, nearest_rotation
from .stereo import StereoRig


# -- helpers ---------------------------------------------------------------------------------------
def euler_from_rotation(R) -> tuple[float, float, float]:
    """(α, β, γ) in degrees with ``R = Rz(γ) Ry(β) Rx(α)`` (DICe / VIC-3D convention)."""
    R = np.asarray(R, dtype=np.float64)
    sy = np.hypot(R[0, 0], R[1, 0])
    if sy > 1e-9:
        a, b, g = np.arctan2(R[2, 1], R[2, 2]), np.arctan2(-R[2, 0], sy), np.arctan2(R[1, 0], R[0, 0])
    else:
        a, b, g = np.arctan2(-R[1, 2], R[1, 1]), np.arctan2(-R[2, 0], sy), 0.0
    return float(np.degrees(a)), float(np.degrees(b)), float(np.degrees(g))


def rotation_from_euler(alpha: float, beta: float, gamma: float) -> np.ndarray:
    """``Rz(γ) Ry(β) Rx(α)`` from angles in degrees (DICe ``eulers_to_rotation_matrix``)."""
    a, b, g = np.radians([alpha, beta, gamma])
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rz = np.array([[np.cos(g), -np.sin(g), 0], [np.sin(g), np.cos(g), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _rig_from_world_poses(cam0, cam1, R0, t0, R1, t1, metadata):
    R = R1 @ R0.T
    return StereoRig(cam0, cam1, nearest_rotation(R), t1 - R @ t0, metadata=metadata)


def _exists(path, what):
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"{what} file {path!r} " + ("is not a file (a folder?)" if os.path.exists(path)
                                                     else "does not exist"))
    return path


# -- OpenCV ----------------------------------------------------------------------------------------
def save_opencv(path, obj) -> None:
    """Write a :class:`Camera` or :class:`StereoRig` with ``cv2.FileStorage`` (.yml/.yaml/.xml/.json)."""
    import cv2

    if not isinstance(obj, (Camera, StereoRig)):
        raise ValueError(f"save_opencv writes a Camera or a StereoRig, got {type(obj).__name__}")
    fs = cv2.FileStorage(os.fspath(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise ValueError(f"cannot open {os.fspath(path)!r} for writing")
    try:
        fs.writeComment("Specula export; lengths in mm, pixels with (0,0) at the centre of the top-left pixel")
        if isinstance(obj, Camera):
            fs.write("image_width", int(obj.size[0]))
            fs.write("image_height", int(obj.size[1]))
            fs.write("camera_name", obj.name or "camera")
            fs.write("camera_matrix", obj.K)
            fs.write("distortion_coefficients", obj.dist.reshape(1, -1) if obj.dist.size else np.zeros((1, 5)))
        else:
            fs.writeComment("x_right = R @ x_left + T (OpenCV stereoCalibrate convention)")
            fs.write("image_width", int(obj.left.size[0]))
            fs.write("image_height", int(obj.left.size[1]))
            fs.write("right_image_width", int(obj.right.size[0]))
            fs.write("right_image_height", int(obj.right.size[1]))
            fs.write("M1", obj.left.K)
            fs.write("D1", obj.left.dist.reshape(1, -1) if obj.left.dist.size else np.zeros((1, 5)))
            fs.write("M2", obj.right.K)
            fs.write("D2", obj.right.dist.reshape(1, -1) if obj.right.dist.size else np.zeros((1, 5)))
            fs.write("R", obj.R_right_left)
            fs.write("T", obj.t_right_left.reshape(3, 1))
    finally:
        fs.release()


def load_opencv(path):
    """Read a camera or a rig written by OpenCV tools or :func:`save_opencv`.

    Returns a :class:`StereoRig` when ``R`` and ``T`` are present, else a :class:`Camera`. Accepts
    the key sets ``camera_matrix``/``distortion_coefficients`` and ``M1 D1 M2 D2`` (also
    ``K1``/``cameraMatrix1``-style aliases).
    """
    import cv2

    path = _exists(path, "OpenCV calibration")
    try:
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise ValueError(f"{path!r} is not a readable OpenCV FileStorage file ({exc.err})") from None
    if not fs.isOpened():
        raise ValueError(f"{path!r} is not a readable OpenCV FileStorage file")
    try:
        def mat(*names):
            for n in names:
                node = fs.getNode(n)
                if not node.empty():
                    m = node.mat()
                    if m is not None:
                        return np.asarray(m, dtype=np.float64)
            return None

        def num(*names):
            for n in names:
                node = fs.getNode(n)
                if not node.empty():
                    return int(node.real())
            return None

        w, h = num("image_width", "imageWidth", "width"), num("image_height", "imageHeight", "height")
        size = (w or 0, h or 0)
        R, T = mat("R"), mat("T")
        if R is not None and T is not None:
            K1, D1 = mat("M1", "K1", "cameraMatrix1", "camera_matrix_1"), mat("D1", "distCoeffs1", "distortion_coefficients_1")
            K2, D2 = mat("M2", "K2", "cameraMatrix2", "camera_matrix_2"), mat("D2", "distCoeffs2", "distortion_coefficients_2")
            if K1 is None or K2 is None:
                raise ValueError(f"{path!r} has R and T but no camera matrices (M1/M2)")
            w2, h2 = num("right_image_width"), num("right_image_height")
            left = Camera(K1, _dist(D1), size, "left")
            right = Camera(K2, _dist(D2), (w2 or size[0], h2 or size[1]), "right")
            return StereoRig(left, right, nearest_rotation(R), T.ravel(), metadata={"imported_from": path})
        K = mat("camera_matrix", "cameraMatrix", "K")
        if K is None:
            raise ValueError(f"{path!r} has neither camera_matrix nor M1/M2 with R/T")
        name = fs.getNode("camera_name")
        return Camera(K, _dist(mat("distortion_coefficients", "distCoeffs", "D")), size,
                      name.string() if not name.empty() else "")
    finally:
        fs.release()


def _dist(D):
    if D is None:
        return np.zeros(5)
    d = np.asarray(D, dtype=np.float64).ravel()
    if d.size in (0, 4, 5, 8):
        return d
    if d.size > 8 and np.allclose(d[8:], 0):
        return d[:8]
    raise ValueError(f"unsupported number of distortion coefficients {d.size} (Specula supports 4, 5 or 8)")


# -- DICe ------------------------------------------------------------------------------------------
_DICE_INTRINSICS = ("CX", "CY", "FX", "FY", "FS", "K1", "K2", "K3", "K4", "K5", "K6", "P1", "P2")


def _dice_values(cam: Camera) -> dict:
    k1, k2, p1, p2, k3, k4, k5, k6 = cam.dist8
    return {"CX": cam.cx, "CY": cam.cy, "FX": cam.fx, "FY": cam.fy, "FS": cam.skew, "K1": k1, "K2": k2, "K3": k3,
            "K4": k4, "K5": k5, "K6": k6, "P1": p1, "P2": p2}


def save_dice_xml(path, rig: StereoRig) -> None:
    """Write a rig as a DICe camera-system XML file (world frame = left camera frame)."""
    if not isinstance(rig, StereoRig):
        raise ValueError(f"save_dice_xml writes a StereoRig, got {type(rig).__name__}")
    root = ET.Element("ParameterList")
    root.append(ET.Comment(" DICe formatted camera system file, written by Specula (lengths in mm) "))

    def param(parent, name, typ, value):
        ET.SubElement(parent, "Parameter", name=name, type=typ, value=value)

    param(root, "xml_file_format", "string", "DICe_xml_camera_system_file")
    param(root, "system_type_3D", "string", "OPENCV")
    param(root, "extrinsics_relative_camera_to_camera", "bool", "false")
    poses = [(np.eye(3), np.zeros(3)), (rig.R_right_left, rig.t_right_left)]
    for i, (cam, (R, t)) in enumerate(zip((rig.left, rig.right), poses)):
        pl = ET.SubElement(root, "ParameterList", name=f"CAMERA {i}")
        param(pl, "CAMERA_ID", "string", cam.name or ("left" if i == 0 else "right"))
        for k, v in _dice_values(cam).items():
            param(pl, k, "double", repr(float(v)))
        param(pl, "LENS_DISTORTION_MODEL", "string", "OPENCV_LENS_DISTORTION")
        for k, v in zip(("TX", "TY", "TZ"), t):
            param(pl, k, "double", repr(float(v)))
        rot = ET.SubElement(pl, "ParameterList", name="rotation_3x3_matrix")
        for r in range(3):
            param(rot, f"ROW {r}", "string", "{ " + ", ".join(repr(float(v)) for v in R[r]) + " }")
        param(pl, "IMAGE_HEIGHT_WIDTH", "string", f"{{ {int(cam.size[1])}, {int(cam.size[0])} }}")
    ET.indent(root)
    ET.ElementTree(root).write(os.fspath(path), encoding="utf-8", xml_declaration=True)


def _parse_xml(path, what):
    path = _exists(path, what)
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ValueError(f"{path!r} is not well-formed XML ({exc}); is it truncated?") from None


def _brace_numbers(text, n, what):
    vals = [float(v) for v in text.replace("{", " ").replace("}", " ").replace(",", " ").split()]
    if len(vals) != n:
        raise ValueError(f"{what}: expected {n} numbers, got {text!r}")
    return vals


def load_dice_xml(path) -> StereoRig:
    """Read a two-camera DICe camera-system XML file (OpenCV or no distortion model)."""
    root = _parse_xml(path, "DICe camera system")
    if root.tag != "ParameterList":
        raise ValueError(f"{os.fspath(path)!r} is not a DICe ParameterList file (root <{root.tag}>)")

    def params(el):
        return {p.get("name"): (p.get("type"), p.get("value")) for p in el.findall("Parameter")}

    top = params(root)
    fmt = top.get("xml_file_format", top.get("cal_file_ID", (None, None)))[1]
    if fmt not in ("DICe_xml_camera_system_file", "DICe_XML_Calibration_File"):
        raise ValueError(f"{os.fspath(path)!r} is not a DICe camera-system file (xml_file_format = {fmt!r})")
    relative = top.get("extrinsics_relative_camera_to_camera", ("bool", "false"))[1].strip().lower() == "true"
    cams, poses = [], []
    for i in range(2):
        pl = root.find(f"ParameterList[@name='CAMERA {i}']")
        if pl is None:
            raise ValueError(f"{os.fspath(path)!r} lacks the sublist 'CAMERA {i}' (a stereo rig needs two cameras)")
        p = params(pl)
        model = p.get("LENS_DISTORTION_MODEL", p.get("LD_MODEL", ("string", "NO_LENS_DISTORTION")))[1]
        if model not in ("OPENCV_LENS_DISTORTION", "OPENCV_DIS", "NO_LENS_DISTORTION", "NONE"):
            raise ValueError(f"CAMERA {i}: lens distortion model {model!r} is not supported (OpenCV or none only)")
        v = {k: float(p[k][1]) if k in p else 0.0 for k in _DICE_INTRINSICS}
        for k in ("S1", "S2", "S3", "S4", "T1", "T2"):
            if k in p and float(p[k][1]) != 0.0:
                raise ValueError(f"CAMERA {i}: thin-prism / tilted-sensor term {k} is not supported by Specula")
        if "IMAGE_HEIGHT_WIDTH" not in p:
            raise ValueError(f"CAMERA {i} lacks IMAGE_HEIGHT_WIDTH")
        h, w = (int(x) for x in _brace_numbers(p["IMAGE_HEIGHT_WIDTH"][1], 2, "IMAGE_HEIGHT_WIDTH"))
        K = [[v["FX"], v["FS"], v["CX"]], [0, v["FY"], v["CY"]], [0, 0, 1]]
        rational = any(v[k] for k in ("K4", "K5", "K6"))
        dist = [v["K1"], v["K2"], v["P1"], v["P2"], v["K3"]] + ([v["K4"], v["K5"], v["K6"]] if rational else [])
        if model in ("NO_LENS_DISTORTION", "NONE"):
            dist = [0.0] * 5
        name = p.get("CAMERA_ID", ("string", ""))[1]
        cams.append(Camera(K, dist, (w, h), name))
        t = np.array([float(p[k][1]) if k in p else 0.0 for k in ("TX", "TY", "TZ")])
        rot = pl.find("ParameterList[@name='rotation_3x3_matrix']")
        if rot is not None:
            rp = params(rot)
            R = np.array([_brace_numbers(rp[f"ROW {r}"][1], 3, f"ROW {r}") for r in range(3)])
        else:
            R = rotation_from_euler(*(float(p[k][1]) if k in p else 0.0 for k in ("ALPHA", "BETA", "GAMMA")))
        poses.append((R, t))
    meta = {"imported_from": os.fspath(path), "format": "DICe camera system"}
    if relative:  # camera 1 extrinsics are already camera 0 -> camera 1
        return StereoRig(cams[0], cams[1], nearest_rotation(poses[1][0]), poses[1][1], metadata=meta)
    return _rig_from_world_poses(cams[0], cams[1], *poses[0], *poses[1], meta)


# -- VIC-3D ----------------------------------------------------------------------------------------
def save_vic3d_xml(path, rig: StereoRig, *, allow_lossy: bool = False) -> None:
    """Write a rig in the VIC-3D project calibration layout (see module docstring for the assumptions).

    Raises ``ValueError`` when a camera has tangential or rational distortion terms (the format
    holds only κ1..κ3) unless ``allow_lossy`` (they are then dropped), or when the two image sizes
    differ (the format stores one).
    """
    if not isinstance(rig, StereoRig):
        raise ValueError(f"save_vic3d_xml writes a StereoRig, got {type(rig).__name__}")
    for side, cam in (("left", rig.left), ("right", rig.right)):
        d = cam.dist8
        extra = np.abs(np.r_[d[2:4], d[5:8]])
        if np.any(extra > 0) and not allow_lossy:
            raise ValueError(f"the {side} camera has tangential/rational distortion (p1 p2 k4 k5 k6 = "
                             f"{np.r_[d[2:4], d[5:8]]}) that the VIC-3D calibration cannot hold; recalibrate with "
                             "model='radial3' or pass allow_lossy=True to drop them")
    if rig.left.size != rig.right.size:
        raise ValueError(f"VIC-3D stores one image size; the cameras differ ({rig.left.size} vs {rig.right.size})")
    lines = ['<?xml version="1.0" encoding="ISO-8859-1"?>', "<!DOCTYPE vpml>", "<project>",
             " <!-- written by Specula; lengths in mm, world frame = left camera frame -->",
             ' <calibration lri="calibration">']
    for i, (cam, R, t) in enumerate(((rig.left, np.eye(3), np.zeros(3)),
                                     (rig.right, rig.R_right_left, rig.t_right_left))):
        k1, k2, _, _, k3 = cam.dist8[:5]
        intr = [cam.cx, cam.cy, cam.fx, cam.fy, cam.skew, k1, k2, k3]
        orient = list(euler_from_rotation(R)) + list(t)
        lines.append(f'  <camera id="{i}">' + " ".join(f"{v:.12e}" for v in intr) + "<orientation>"
                     + " ".join(f"{v:.12e}" for v in orient) + "</orientation>")
        lines.append("  </camera>")
    w, h = rig.left.size
    lines += [" </calibration>", ' <projectaois lri="projectaois">', '  <aoinode lri="aoinode">',
              f'   <polygonmask width="{w}" height="{h}" lri="polygonmask">', "   </polygonmask>",
              "  </aoinode>", " </projectaois>", "</project>", ""]
    with open(os.fspath(path), "w", encoding="iso-8859-1") as f:
        f.write("\n".join(lines))


def load_vic3d_xml(path, image_size=None) -> StereoRig:
    """Read the calibration of a VIC-3D project / calibration XML (two cameras), in either layout:
    ``<camera id="i">CX CY FX FY FS κ1 κ2 κ3<orientation>…</orientation></camera>`` or
    ``<camera id="i"><intrinsics>CX CY FX FY FS</intrinsics><orientation>α β γ tx ty tz</orientation>
    <distortion>κ1 κ2 κ3</distortion></camera>`` (see :func:`_vic3d_split_camera`).

    ``image_size`` (width, height) is needed when the file has no ``<polygonmask>`` with the size.
    """
    root = _parse_xml(path, "VIC-3D calibration")
    cal = root if root.tag == "calibration" else root.find(".//calibration")
    if cal is None:
        raise ValueError(f"{os.fspath(path)!r} has no <calibration> element (is it a VIC-3D project file?)")
    cam_els = sorted(cal.findall("camera"), key=lambda e: int(e.get("id", "0")))
    if len(cam_els) != 2:
        raise ValueError(f"{os.fspath(path)!r}: expected two <camera> elements, found {len(cam_els)}")
    if image_size is None:
        pm = root.find(".//polygonmask")
        if pm is None or pm.get("width") is None:
            raise ValueError(f"{os.fspath(path)!r} does not record the image size; pass image_size=(width, height)")
        image_size = (int(pm.get("width")), int(pm.get("height")))
    cams, poses = [], []
    for el in cam_els:
        if el.find("intrinsics") is not None:  # the <intrinsics>/<orientation>/<distortion> layout
            cam, pose = _vic3d_split_camera(el, image_size, path)
            cams.append(cam)
            poses.append(pose)
            continue
        vals = (el.text or "").split()
        orient = el.find("orientation")
        if len(vals) != 8 or orient is None:
            raise ValueError(f"camera {el.get('id')}: expected 8 intrinsics (CX CY FX FY FS κ1 κ2 κ3) and an "
                             f"<orientation>, got {len(vals)} values")
        cx, cy, fx, fy, fs, k1, k2, k3 = (float(v) for v in vals)
        o = [float(v) for v in (orient.text or "").split()]
        if len(o) != 6:
            raise ValueError(f"camera {el.get('id')}: <orientation> must hold α β γ tx ty tz, got {len(o)} values")
        cams.append(Camera([[fx, fs, cx], [0, fy, cy], [0, 0, 1]], [k1, k2, 0.0, 0.0, k3], image_size,
                           f"camera {el.get('id')}"))
        poses.append((rotation_from_euler(*o[:3]), np.array(o[3:])))
    return _rig_from_world_poses(cams[0], cams[1], *poses[0], *poses[1],
                                 {"imported_from": os.fspath(path), "format": "VIC-3D"})


def _vic3d_numbers(el, what: str, path) -> list[float]:
    try:
        return [float(v) for v in (el.text or "").split()]
    except ValueError:
        raise ValueError(f"{os.fspath(path)!r}: <{what}> must hold numbers, got {(el.text or '').strip()!r}") from None


def _vic3d_split_camera(el, image_size, path):
    """One camera of the ``<intrinsics>/<orientation>/<distortion>`` layout of VIC-3D project files.

    ``<intrinsics>``: CX CY FX FY FS (5 numbers, FS = ``K[0, 1]``); ``<orientation>``: α β γ (degrees,
    ``R = Rz(γ) Ry(β) Rx(α)``, world→camera) tx ty tz (mm), as in the other layout; ``<distortion>``
    (optional): κ1 [κ2 [κ3]] on r², r⁴, r⁶ of normalised coordinates (= OpenCV k1 k2 k3; the same
    assumption as the other layout). Further distortion terms are refused unless they are zero: we
    could not verify what VIC-3D means by them. Returns ``(Camera, (R, t))``.
    """
    cid = el.get("id")
    intr = _vic3d_numbers(el.find("intrinsics"), "intrinsics", path)
    if len(intr) != 5:
        raise ValueError(f"{os.fspath(path)!r}: camera {cid}: <intrinsics> must hold CX CY FX FY FS (5 numbers), "
                         f"got {len(intr)}")
    orient = el.find("orientation")
    if orient is None:
        raise ValueError(f"{os.fspath(path)!r}: camera {cid} has <intrinsics> but no <orientation>")
    o = _vic3d_numbers(orient, "orientation", path)
    if len(o) != 6:
        raise ValueError(f"{os.fspath(path)!r}: camera {cid}: <orientation> must hold α β γ tx ty tz, got {len(o)} values")
    dist_el = el.find("distortion")
    kappa = _vic3d_numbers(dist_el, "distortion", path) if dist_el is not None else []
    if any(k != 0.0 for k in kappa[3:]):
        raise ValueError(f"{os.fspath(path)!r}: camera {cid}: <distortion> holds {len(kappa)} terms; Specula reads "
                         "κ1 κ2 κ3 (radial) only and the further terms are not zero")
    k1, k2, k3 = (kappa + [0.0, 0.0, 0.0])[:3]
    cx, cy, fx, fy, fs = intr
    cam = Camera([[fx, fs, cx], [0, fy, cy], [0, 0, 1]], [k1, k2, 0.0, 0.0, k3], image_size, f"camera {cid}")
    return cam, (rotation_from_euler(*o[:3]), np.array(o[3:]))


# -- one entry point: the format detected from the content ------------------------------------------
#: the calibration formats :func:`load_rig` and :func:`load_camera` recognise, as named in messages
CALIBRATION_FORMATS = (
    "Specula JSON (camera or stereo rig, from 'specula calibrate')",
    "OpenCV FileStorage YAML/XML/JSON (camera_matrix/distortion_coefficients, or M1 D1 M2 D2 R T)",
    "VIC-3D calibration or project XML (<camera> with 8 numbers + <orientation>, or "
    "<intrinsics>/<orientation>/<distortion>)",
    "DICe camera-system XML (<ParameterList> with xml_file_format = DICe_xml_camera_system_file)",
)

_OPENCV_KEYS = ("camera_matrix", "cameraMatrix", "K", "M1", "K1", "cameraMatrix1", "camera_matrix_1")


def _opencv_has_camera(path) -> bool:
    """Whether cv2.FileStorage reads ``path`` and finds a camera matrix in it."""
    import cv2

    try:
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except Exception:  # cv2.error, or SystemError from the binding when parsing fails
        return False
    try:
        return fs.isOpened() and any(not fs.getNode(k).empty() for k in _OPENCV_KEYS)
    except cv2.error:
        return False
    finally:
        fs.release()


def _unknown_format(path, why: str) -> ValueError:
    return ValueError(f"{path!r} is not a calibration file Specula reads ({why}); the formats recognised from the "
                      "content are: " + "; ".join(CALIBRATION_FORMATS))


def detect_calibration_format(path) -> str:
    """The format of a camera or rig file, from its content (never its suffix).

    Returns ``"specula-camera"``, ``"specula-rig"``, ``"opencv"``, ``"vic3d"`` or ``"dice"``. Raises
    ``ValueError`` for a missing file, malformed JSON/XML, or content that fits none of
    :data:`CALIBRATION_FORMATS` (the message names them).
    """
    return _detect(path)[0]


def _detect(path):
    """(format, parsed JSON dict or None)."""
    from .camera import CAMERA_SCHEMA
    from .stereo import RIG_SCHEMA

    path = _exists(path, "calibration")
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise ValueError(f"cannot read {path!r} ({exc.strerror})") from None
    text = raw.decode("utf-8", errors="replace").lstrip("\ufeff \t\r\n")
    if not text:
        raise _unknown_format(path, "the file is empty")
    if text.startswith("{"):
        import json

        try:
            data = json.loads(raw.decode("utf-8-sig"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            if _opencv_has_camera(path):  # OpenCV writes JSON with // comments
                return "opencv", None
            raise ValueError(f"calibration file {path!r} is not valid JSON ({exc}); is it truncated?") from None
        if not isinstance(data, dict):
            raise _unknown_format(path, "a JSON file that is not an object")
        schema = data.get("schema")
        if schema == CAMERA_SCHEMA:
            return "specula-camera", data
        if schema == RIG_SCHEMA:
            return "specula-rig", data
        if schema is not None:
            raise _unknown_format(path, f"a JSON file of schema {schema!r}, neither {CAMERA_SCHEMA!r} nor {RIG_SCHEMA!r}")
        if any(k in data for k in _OPENCV_KEYS):
            return "opencv", None
        raise _unknown_format(path, "a JSON file without a Specula schema or OpenCV camera matrices")
    if text.startswith("%YAML"):
        return "opencv", None
    if text.startswith("<"):
        root = _parse_xml(path, "calibration")
        if root.tag == "opencv_storage":
            return "opencv", None
        if root.tag == "ParameterList":
            return "dice", None
        cal = root if root.tag == "calibration" else root.find(".//calibration")
        if cal is not None and cal.find("camera") is not None:
            return "vic3d", None
        raise _unknown_format(path, f"an XML file with root <{root.tag}> and no <calibration><camera>")
    if _opencv_has_camera(path):  # YAML without its %YAML header
        return "opencv", None
    raise _unknown_format(path, "neither JSON, YAML nor XML with camera parameters")


def _fill_size(cam: Camera, image_size) -> Camera:
    if image_size is None or tuple(cam.size) != (0, 0):
        return cam
    import dataclasses

    return dataclasses.replace(cam, size=tuple(int(s) for s in image_size))


def _check_image_size(image_size):
    if image_size is None:
        return None
    try:
        w, h = (int(s) for s in image_size)
    except (TypeError, ValueError):
        raise ValueError(f"image_size must be (width, height) in px, got {image_size!r}") from None
    if w <= 0 or h <= 0:
        raise ValueError(f"image_size must be positive (width, height) in px, got {image_size!r}")
    return w, h


def _load_any(path, image_size):
    """Camera or StereoRig from any format (see :func:`load_rig`) and the format's name."""
    image_size = _check_image_size(image_size)
    fmt, data = _detect(path)
    if fmt == "specula-camera":
        return Camera.from_dict(data), fmt
    if fmt == "specula-rig":
        return StereoRig.from_dict(data), fmt
    if fmt == "opencv":
        obj = load_opencv(path)
    elif fmt == "dice":
        obj = load_dice_xml(path)
    else:
        obj = _vic3d_sized(path, image_size)
    if isinstance(obj, Camera):
        return _fill_size(obj, image_size), fmt
    left, right = _fill_size(obj.left, image_size), _fill_size(obj.right, image_size)
    if left is not obj.left or right is not obj.right:
        obj = StereoRig(left, right, obj.R_right_left, obj.t_right_left, covariance=obj.covariance,
                        metadata={**obj.metadata, "image_size": "not in the file; taken from the images"})
    return obj, fmt


def _vic3d_sized(path, image_size):
    """A VIC-3D rig with the image size the file records, else ``image_size``."""
    try:
        return load_vic3d_xml(path)
    except ValueError as exc:
        if "pass image_size" not in str(exc):
            raise
        if image_size is None:
            raise ValueError(f"{os.fspath(path)!r} (VIC-3D) does not record the image size; pass "
                             "image_size=(width, height)") from None
    rig = load_vic3d_xml(path, image_size=image_size)
    rig.metadata["image_size"] = "not in the file; taken from the images"
    return rig


def load_rig(path, *, image_size=None) -> StereoRig:
    """Read a stereo rig from a file in any format Specula reads, detected from the content.

    Formats (:data:`CALIBRATION_FORMATS`): Specula's rig JSON, OpenCV FileStorage (YAML/XML/JSON as
    ``stereo_calib.cpp`` writes it), VIC-3D calibration/project XML (both layouts) and DICe
    camera-system XML. ``image_size`` (width, height) is used only where the file records no image
    size (VIC-3D files without ``<polygonmask>``, OpenCV files without ``image_width``): DIC passes
    its images' size. Raises ``ValueError`` naming the formats when none fits, or saying that the
    file holds one camera, not a rig.
    """
    obj, fmt = _load_any(path, image_size)
    if not isinstance(obj, StereoRig):
        raise ValueError(f"{os.fspath(path)!r} holds one camera ({fmt}), not a stereo rig; a rig file comes from "
                         "'specula calibrate stereo' (or another tool's two-camera calibration)")
    return obj


def as_rig(rig_or_path, *, image_size=None):
    """``rig_or_path`` as a rig: a :class:`StereoRig` (or an object with its attributes) as it is, a file
    path read with :func:`load_rig` (any format, detected from the content; ``image_size`` (width,
    height) stands in where the file records no size). Anything else raises ``ValueError``.

    Every function that takes a rig calls this (``dic.stereo.StereoCorrelation``, ``stereo``,
    ``dic.sequence.stereo_sequence``, ``specula stereo --rig``), so a rig may be given as an object
    or as the path of its file.
    """
    if isinstance(rig_or_path, (str, os.PathLike)):
        return load_rig(rig_or_path, image_size=image_size)
    if isinstance(rig_or_path, StereoRig) or all(
            hasattr(rig_or_path, a) for a in ("left", "right", "R_right_left", "t_right_left")):
        return rig_or_path
    raise ValueError("rig must be a calibration.stereo.StereoRig or the path of a rig file (Specula JSON, "
                     f"OpenCV YAML/XML/JSON, VIC-3D XML or DICe XML), got {type(rig_or_path).__name__}")


def load_camera(path, *, which: str | None = None, image_size=None) -> Camera:
    """Read one camera from a file in any format Specula reads, detected from the content.

    A camera file (Specula camera JSON, OpenCV ``calibration.cpp`` keys) gives its camera; a rig
    file (any format of :func:`load_rig`) gives its ``which`` camera (``"left"`` or ``"right"``) and
    is refused without ``which``. ``image_size`` as in :func:`load_rig`.
    """
    if which not in (None, "left", "right"):
        raise ValueError(f"which must be None, 'left' or 'right', got {which!r}")
    obj, fmt = _load_any(path, image_size)
    if isinstance(obj, Camera):
        return obj
    if which is None:
        raise ValueError(f"{os.fspath(path)!r} holds a stereo rig ({fmt}), not one camera; give a camera file "
                         "(from 'specula calibrate intrinsics') or choose the rig's camera (which='left' or 'right')")
    return getattr(obj, which)
