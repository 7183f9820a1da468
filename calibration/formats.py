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

from kernels._atomic import atomic_output

from .camera import Camera, nearest_rotation, require_image_size
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


#: Largest deviation ``max |R Rᵀ − I|`` accepted for a rotation matrix read from a file (the entries
#: of a rotation written with 5 significant digits); beyond it the file is refused, never repaired.
ROTATION_TOLERANCE = 1e-4

#: Largest image side (px) accepted from a file.
MAX_IMAGE_SIDE = 1 << 20


def _rig_from_world_poses(cam0, cam1, R0, t0, R1, t1, metadata):
    R = R1 @ R0.T
    return StereoRig(cam0, cam1, nearest_rotation(R), t1 - R @ t0, metadata=metadata)


def _exists(path, what):
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"{what} file {path!r} " + ("is not a file (a folder?)" if os.path.exists(path)
                                                     else "does not exist"))
    return path


def _guarded(what, path, load, *args):
    """Run ``load(path, *args)``; any error about the file's content becomes one ``ValueError`` that
    names the file (the inner messages name the field)."""
    path = _exists(path, what)
    try:
        return load(path, *args)
    except (ValueError, TypeError, KeyError, IndexError, OverflowError, AttributeError, UnicodeError) as exc:
        msg = str(exc) if isinstance(exc, ValueError) else f"malformed content ({type(exc).__name__}: {exc})"
        raise ValueError(f"{what} file {path!r}: {msg}") from None


def _number(text, field):
    """A finite float from a file's text (``field`` names it in the error)."""
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise ValueError(f"{field} must be a number, got {text!r}") from None
    if not np.isfinite(v):
        raise ValueError(f"{field} must be finite, got {text!r}")
    return v


def _side(value, field):
    """A positive integral image side in pixels."""
    v = _number(value, field)
    if v != int(v) or not 0 < v <= MAX_IMAGE_SIDE:
        raise ValueError(f"{field} must be a positive whole number of pixels (<= {MAX_IMAGE_SIDE}), got {value!r}")
    return int(v)


def _image_size_arg(image_size) -> tuple[int, int]:
    """The ``image_size=(width, height)`` argument of a reader, checked."""
    if isinstance(image_size, (str, bytes)) or not hasattr(image_size, "__len__") or len(image_size) != 2:
        raise ValueError(f"image_size must be (width, height) in pixels, got {image_size!r}")
    return _side(image_size[0], "image_size width"), _side(image_size[1], "image_size height")


def _rotation(R, field):
    """A proper rotation read from a file: finite 3x3, orthonormal within :data:`ROTATION_TOLERANCE`,
    det +1; returned re-orthonormalised (the deviation is rounding only)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"{field} must be a 3x3 rotation matrix, got shape {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError(f"{field} holds non-finite numbers")
    if np.max(np.abs(R)) > 1.0 + ROTATION_TOLERANCE:
        raise ValueError(f"{field} is not a rotation matrix (an entry of magnitude {np.max(np.abs(R)):.6g} > 1)")
    dev = float(np.max(np.abs(R @ R.T - np.eye(3))))
    if dev > ROTATION_TOLERANCE:
        raise ValueError(f"{field} is not a rotation matrix (max |R R^T - I| = {dev:.3g} > {ROTATION_TOLERANCE:g})")
    if np.linalg.det(R) < 0:
        raise ValueError(f"{field} is a reflection (det = {np.linalg.det(R):.6g}), not a proper rotation")
    return nearest_rotation(R)


def _vector3(t, field):
    t = np.asarray(t, dtype=np.float64).ravel()
    if t.shape != (3,):
        raise ValueError(f"{field} must hold 3 numbers, got {t.size}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{field} holds non-finite numbers")
    return t


def _camera(K, dist, size, name, field):
    """A :class:`Camera` from a file: positive size, positive focal lengths, finite numbers, principal
    point inside the image; errors name ``field``."""
    try:
        cam = Camera(K, dist, size, name)
    except ValueError as exc:
        raise ValueError(f"{field}: {exc}") from None
    w, h = cam.size
    if w <= 0 or h <= 0:
        raise ValueError(f"{field}: the image size must be positive, got {cam.size}")
    if not (-0.5 <= cam.cx <= w - 0.5 and -0.5 <= cam.cy <= h - 0.5):
        raise ValueError(f"{field}: the principal point ({cam.cx:.6g}, {cam.cy:.6g}) px lies outside the "
                         f"{w}x{h} image")
    return cam


# -- OpenCV ----------------------------------------------------------------------------------------
def save_opencv(path, obj) -> None:
    """Write a :class:`Camera` or :class:`StereoRig` with ``cv2.FileStorage`` (.yml/.yaml/.xml/.json)."""
    import cv2

    if not isinstance(obj, (Camera, StereoRig)):
        raise ValueError(f"save_opencv writes a Camera or a StereoRig, got {type(obj).__name__}")
    with atomic_output(path, mkdir=False) as tmp:  # whole or not at all
        _save_opencv(tmp, path, obj, cv2)


def _save_opencv(tmp, path, obj, cv2) -> None:
    fs = cv2.FileStorage(os.fspath(tmp), cv2.FILE_STORAGE_WRITE)
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


def load_opencv(path, image_size=None):
    """Read a camera or a rig written by OpenCV tools or :func:`save_opencv`.

    Returns a :class:`StereoRig` when ``R`` and ``T`` are present, else a :class:`Camera`. Accepts
    the key sets ``camera_matrix``/``distortion_coefficients`` and ``M1 D1 M2 D2`` (also
    ``K1``/``cameraMatrix1``-style aliases). ``image_size`` (width, height) is needed when the file
    has no ``image_width``/``image_height`` (OpenCV's stereo sample writes none); the right camera
    takes ``right_image_width``/``right_image_height`` when present, else the same size.

    Nothing missing is filled in: the camera matrices, the distortion coefficients, the image size
    and, for a rig, ``R`` (a proper rotation within :data:`ROTATION_TOLERANCE`) and ``T`` (3 finite
    numbers) must be present and valid, else ``ValueError`` names the file and the field.
    """
    return _guarded("OpenCV calibration", path, _load_opencv, image_size)


def _load_opencv(path, image_size):
    import cv2

    try:
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise ValueError(f"not a readable OpenCV FileStorage file ({exc.err})") from None
    except SystemError as exc:  # OpenCV's binding reports some parse errors so, with the cv2.error as the cause
        cause = getattr(exc.__cause__, "err", None) or exc.__cause__ or exc
        raise ValueError(f"not a readable OpenCV FileStorage file ({cause})") from None
    if not fs.isOpened():
        raise ValueError("not a readable OpenCV FileStorage file")
    try:
        root = fs.root()
        if not root.isMap():
            raise ValueError("not an OpenCV FileStorage map of named entries")

        def node(*names):
            for n in names:
                nd = fs.getNode(n)
                if not nd.empty() and not nd.isNone():
                    return n, nd
            return None, None

        def mat(*names, required=True):
            n, nd = node(*names)
            if nd is None:
                if required:
                    raise ValueError(f"{names[0]} is missing")
                return None
            m = _read_matrix(nd, n)
            if not np.all(np.isfinite(m)):
                raise ValueError(f"{n} holds non-finite numbers")
            return m

        def num(*names):
            n, nd = node(*names)
            if nd is None:
                return None
            if not (nd.isInt() or nd.isReal()):
                raise ValueError(f"{n} must be a number")
            return _side(nd.real(), n)

        if node("R", "T")[1] is None and node("camera_matrix", "cameraMatrix", "K")[1] is None:
            raise ValueError("has neither camera_matrix nor M1/M2 with R/T")
        w, h = num("image_width", "imageWidth", "width"), num("image_height", "imageHeight", "height")
        given = None if image_size is None else _image_size_arg(image_size)
        if w is None or h is None:
            if given is None:
                missing = "image_width" if w is None else "image_height"
                raise ValueError(f"{missing} is missing (the image size is required); pass image_size=(width, height)")
            w, h = given
        elif given is not None and given != (w, h):
            raise ValueError(f"image_size={given} differs from the file's image_width x image_height {(w, h)}")
        size = (w, h)
        R, T = mat("R", required=False), mat("T", required=False)
        if (R is None) != (T is None):
            raise ValueError(f"{'T' if T is None else 'R'} is missing (a rig needs both R and T)")
        if R is not None:
            K1 = mat("M1", "K1", "cameraMatrix1", "camera_matrix_1")
            D1 = mat("D1", "distCoeffs1", "distortion_coefficients_1")
            K2 = mat("M2", "K2", "cameraMatrix2", "camera_matrix_2")
            D2 = mat("D2", "distCoeffs2", "distortion_coefficients_2")
            w2, h2 = num("right_image_width"), num("right_image_height")
            if (w2 is None) != (h2 is None):
                raise ValueError("right_image_width and right_image_height must be given together")
            left = _camera(K1, _dist(D1, "D1"), size, "left", "M1/D1")
            right = _camera(K2, _dist(D2, "D2"), (w2, h2) if w2 is not None else size, "right", "M2/D2")
            return StereoRig(left, right, _rotation(R, "R"), _vector3(T, "T"), metadata={"imported_from": path})
        K = mat("camera_matrix", "cameraMatrix", "K")
        D = mat("distortion_coefficients", "distCoeffs", "D")
        n, name = node("camera_name")
        if name is not None and not name.isString():
            raise ValueError("camera_name must be a string")
        return _camera(K, _dist(D, "distortion_coefficients"), size, name.string() if name is not None else "",
                       "camera_matrix/distortion_coefficients")
    except cv2.error as exc:
        raise ValueError(f"unreadable entry ({exc.err})") from None
    finally:
        fs.release()


#: Element types of a one-channel ``opencv-matrix`` (``dt``).
_MATRIX_TYPES = ("u", "c", "w", "s", "i", "f", "d", "h")


def _read_matrix(node, name) -> np.ndarray:
    """An ``!!opencv-matrix`` node as a float64 array, read element by element after checking that
    ``rows x cols`` matches the data: ``FileNode.mat()`` trusts the header and corrupts memory (a
    crash) when it does not."""
    if not node.isMap():
        raise ValueError(f"{name} is not an OpenCV matrix")
    rows, cols, dt, data = (node.getNode(k) for k in ("rows", "cols", "dt", "data"))
    for k, nd in (("rows", rows), ("cols", cols)):
        if nd.empty() or not nd.isInt() or not 0 <= nd.real() <= 1000:
            raise ValueError(f"{name} is not an OpenCV matrix ({k} is missing or not a count)")
    if dt.empty() or not dt.isString() or dt.string() not in _MATRIX_TYPES:
        raise ValueError(f"{name} is not a one-channel OpenCV matrix (dt = {dt.string() if dt.isString() else None!r})")
    r, c = int(rows.real()), int(cols.real())
    if not data.isSeq() or data.size() != r * c:
        n = data.size() if data.isSeq() else None
        raise ValueError(f"{name}: the matrix is {r}x{c} but its data holds {n} numbers")
    vals = []
    for i in range(r * c):
        el = data.at(i)
        if not (el.isInt() or el.isReal()):
            raise ValueError(f"{name}: data element {i} is not a number")
        vals.append(el.real())
    return np.asarray(vals, dtype=np.float64).reshape(r, c)


def _dist(D, field="distortion"):
    d = np.asarray(D, dtype=np.float64).ravel()
    if d.size in (0, 4, 5, 8):
        return d
    if d.size > 8 and np.allclose(d[8:], 0):
        return d[:8]
    raise ValueError(f"{field}: unsupported number of distortion coefficients {d.size} (Specula supports 4, 5 or 8)")


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
    with atomic_output(path, mkdir=False) as tmp:  # whole or not at all
        ET.ElementTree(root).write(os.fspath(tmp), encoding="utf-8", xml_declaration=True)


def _parse_xml(path):
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ValueError(f"not well-formed XML ({exc}); is it truncated?") from None
    except RecursionError:
        raise ValueError("XML nested too deeply") from None
    except LookupError as exc:  # an unknown encoding in the XML declaration
        raise ValueError(f"not readable XML ({exc})") from None


def _brace_numbers(text, n, what):
    if text is None:
        raise ValueError(f"{what} has no value")
    vals = [_number(v, what) for v in text.replace("{", " ").replace("}", " ").replace(",", " ").split()]
    if len(vals) != n:
        raise ValueError(f"{what}: expected {n} numbers, got {text!r}")
    return vals


def load_dice_xml(path) -> StereoRig:
    """Read a two-camera DICe camera-system XML file (OpenCV or no distortion model).

    Required in each ``CAMERA i`` sublist: ``CX CY FX FY``, ``IMAGE_HEIGHT_WIDTH``, and the
    extrinsics ``TX TY TZ`` with a rotation (``rotation_3x3_matrix`` with ``ROW 0..2``, a proper
    rotation within :data:`ROTATION_TOLERANCE`, or ``ALPHA BETA GAMMA``), as DICe always writes them
    (with ``extrinsics_relative_camera_to_camera = true`` camera 0 is the reference and has none).
    ``FS``, ``K1..K6``, ``P1 P2`` may be omitted when 0 (DICe's format: DICe writes only the non-zero
    intrinsics). A missing or malformed value raises ``ValueError`` naming the file and the field.
    """
    return _guarded("DICe camera system", path, _load_dice_xml)


def _is_identity(rot_list, params, where: str) -> bool:
    """Whether a DICe ``rotation_3x3_matrix`` sublist holds the identity (rows ``ROW 0..2``; 1e-12 tolerance)."""
    rp = params(rot_list, f"{where}: rotation_3x3_matrix")
    rows = []
    for r in range(3):
        if f"ROW {r}" not in rp:
            raise ValueError(f"{where}: rotation_3x3_matrix: ROW {r} is missing")
        rows.append(_brace_numbers(rp[f"ROW {r}"][1], 3, f"{where}: rotation_3x3_matrix: ROW {r}"))
    return bool(np.allclose(np.asarray(rows, np.float64), np.eye(3), rtol=0.0, atol=1e-12))


def _load_dice_xml(path) -> StereoRig:
    root = _parse_xml(path)
    if root.tag != "ParameterList":
        raise ValueError(f"not a DICe ParameterList file (root <{root.tag}>)")

    def params(el, where):
        out = {}
        for p in el.findall("Parameter"):
            name = p.get("name")
            if name is None:
                raise ValueError(f"{where}: a <Parameter> has no name")
            if name in out:
                raise ValueError(f"{where}: parameter {name!r} appears twice")
            out[name] = (p.get("type"), p.get("value"))
        return out

    top = params(root, "top level")
    fmt = top.get("xml_file_format", top.get("cal_file_ID", (None, None)))[1]
    if fmt not in ("DICe_xml_camera_system_file", "DICe_XML_Calibration_File"):
        raise ValueError(f"not a DICe camera-system file (xml_file_format = {fmt!r})")
    rel = top.get("extrinsics_relative_camera_to_camera", ("bool", "false"))[1]
    if rel is None or rel.strip().lower() not in ("true", "false"):
        raise ValueError(f"extrinsics_relative_camera_to_camera must be true or false, got {rel!r}")
    relative = rel.strip().lower() == "true"
    cams, poses = [], []
    for i in range(2):
        where = f"CAMERA {i}"
        found = root.findall(f"ParameterList[@name='CAMERA {i}']")
        if not found:
            raise ValueError(f"lacks the sublist 'CAMERA {i}' (a stereo rig needs two cameras)")
        if len(found) > 1:
            raise ValueError(f"the sublist 'CAMERA {i}' appears {len(found)} times")
        pl = found[0]
        p = params(pl, where)

        def value(k, required=True):
            if k not in p:
                if required:
                    raise ValueError(f"{where}: {k} is missing")
                return None
            return _number(p[k][1], f"{where}: {k}")

        model = p.get("LENS_DISTORTION_MODEL", p.get("LD_MODEL", ("string", None)))[1]
        opencv = model in ("OPENCV_LENS_DISTORTION", "OPENCV_DIS")
        if model is None:
            present = [k for k in ("K1", "K2", "K3", "K4", "K5", "K6", "P1", "P2") if value(k, False)]
            if present:
                raise ValueError(f"{where}: LENS_DISTORTION_MODEL is missing but distortion terms {present} are given")
        elif not opencv and model not in ("NO_LENS_DISTORTION", "NONE"):
            raise ValueError(f"{where}: lens distortion model {model!r} is not supported (OpenCV or none only)")
        for k in ("S1", "S2", "S3", "S4", "T1", "T2"):
            if value(k, False):
                raise ValueError(f"{where}: thin-prism / tilted-sensor term {k} is not supported by Specula")
        fx, fy, cx, cy = (value(k) for k in ("FX", "FY", "CX", "CY"))
        fs = value("FS", False) or 0.0
        if "IMAGE_HEIGHT_WIDTH" not in p:
            raise ValueError(f"{where}: IMAGE_HEIGHT_WIDTH is missing")
        h, w = (_side(x, f"{where}: IMAGE_HEIGHT_WIDTH")
                for x in _brace_numbers(p["IMAGE_HEIGHT_WIDTH"][1], 2, f"{where}: IMAGE_HEIGHT_WIDTH"))
        K = [[fx, fs, cx], [0, fy, cy], [0, 0, 1]]
        if opencv:  # DICe's format: a distortion term with the value 0 may be omitted (DICe writes only the others)
            k1, k2, k3, p1, p2, k4, k5, k6 = (value(k, False) or 0.0 for k in ("K1", "K2", "K3", "P1", "P2", "K4", "K5", "K6"))
            dist = [k1, k2, p1, p2, k3] + ([k4, k5, k6] if any((k4, k5, k6)) else [])
        else:
            dist = [0.0] * 5
        name = p.get("CAMERA_ID", ("string", ""))[1] or ""
        cams.append(_camera(K, dist, (w, h), name, where))
        rots = pl.findall("ParameterList[@name='rotation_3x3_matrix']")
        if len(rots) > 1:
            raise ValueError(f"{where}: rotation_3x3_matrix appears {len(rots)} times")
        eulers = [k for k in ("ALPHA", "BETA", "GAMMA") if k in p]
        if rots and eulers:
            raise ValueError(f"{where}: both rotation_3x3_matrix and {' '.join(eulers)} are given (DICe allows one)")
        if relative and i == 0:  # the reference camera: its pose is the identity, if given at all
            given = [value(k) for k in ("TX", "TY", "TZ") if k in p]
            # DICe's own writer always gives camera 0 a rotation_3x3_matrix: the identity is no pose
            if any(given) or any(value(k) for k in eulers) or (rots and not _is_identity(rots[0], params, where)):
                raise ValueError(f"{where}: with extrinsics_relative_camera_to_camera = true, camera 0 is the "
                                 "reference; its extrinsics must be absent or zero")
            poses.append((np.eye(3), np.zeros(3)))
            continue
        t = np.array([value(k) for k in ("TX", "TY", "TZ")])
        if rots:
            rp = params(rots[0], f"{where}: rotation_3x3_matrix")
            rows = []
            for r in range(3):
                if f"ROW {r}" not in rp:
                    raise ValueError(f"{where}: rotation_3x3_matrix: ROW {r} is missing")
                rows.append(_brace_numbers(rp[f"ROW {r}"][1], 3, f"{where}: rotation_3x3_matrix: ROW {r}"))
            R = _rotation(rows, f"{where}: rotation_3x3_matrix")
        else:
            if not eulers:
                raise ValueError(f"{where}: the rotation is missing (rotation_3x3_matrix or ALPHA BETA GAMMA)")
            R = rotation_from_euler(*(value(k) for k in ("ALPHA", "BETA", "GAMMA")))
        poses.append((R, t))
    meta = {"imported_from": path, "format": "DICe camera system"}
    if relative:  # camera 1 extrinsics are already camera 0 -> camera 1
        return StereoRig(cams[0], cams[1], poses[1][0], poses[1][1], metadata=meta)
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
    with atomic_output(path, mkdir=False) as tmp, open(tmp, "w", encoding="iso-8859-1") as f:
        f.write("\n".join(lines))


def load_vic3d_xml(path, image_size=None) -> StereoRig:
    """Read the calibration of a VIC-3D project / calibration XML (two cameras, ids 0 and 1), in either layout:
    ``<camera id="i">CX CY FX FY FS κ1 κ2 κ3<orientation>…</orientation></camera>`` or
    ``<camera id="i"><intrinsics>CX CY FX FY FS</intrinsics><orientation>α β γ tx ty tz</orientation>
    <distortion>κ1 κ2 κ3</distortion></camera>`` (see :func:`_vic3d_split_camera`).

    ``image_size`` (width, height) is needed when the file has no ``<polygonmask>`` with the size
    (``width`` and ``height``). A missing or malformed value raises ``ValueError`` naming the file
    and the field.
    """
    return _guarded("VIC-3D calibration", path, _load_vic3d_xml, image_size)


def _load_vic3d_xml(path, image_size) -> StereoRig:
    root = _parse_xml(path)
    cal = root if root.tag == "calibration" else root.find(".//calibration")
    if cal is None:
        raise ValueError("has no <calibration> element (is it a VIC-3D project file?)")
    cam_els = cal.findall("camera")
    if len(cam_els) != 2:
        raise ValueError(f"expected two <camera> elements, found {len(cam_els)}")
    ids = [el.get("id") for el in cam_els]
    if sorted(str(i).strip() for i in ids) != ["0", "1"]:
        raise ValueError(f"the <camera> ids must be 0 and 1, got {ids}")
    cam_els = sorted(cam_els, key=lambda e: int(e.get("id")))
    if image_size is None:
        pm = root.find(".//polygonmask")
        if pm is None or pm.get("width") is None or pm.get("height") is None:
            raise ValueError("does not record the image size (<polygonmask width= height=>); "
                             "pass image_size=(width, height)")
        image_size = (_side(pm.get("width"), "polygonmask width"), _side(pm.get("height"), "polygonmask height"))
    else:
        image_size = _image_size_arg(image_size)
    cams, poses = [], []
    for el in cam_els:
        where = f"camera {el.get('id')}"
        if el.find("intrinsics") is not None:  # the <intrinsics>/<orientation>/<distortion> layout
            cam, pose = _vic3d_split_camera(el, image_size, where)
            cams.append(cam)
            poses.append(pose)
            continue
        vals = (el.text or "").split()
        orient = el.findall("orientation")
        if len(vals) != 8 or len(orient) != 1:
            raise ValueError(f"{where}: expected 8 intrinsics (CX CY FX FY FS κ1 κ2 κ3) and one <orientation>, "
                             f"got {len(vals)} values and {len(orient)} <orientation>")
        cx, cy, fx, fy, fs, k1, k2, k3 = (_number(v, f"{where}: intrinsic {j}") for j, v in enumerate(vals))
        o = [_number(v, f"{where}: <orientation>") for v in (orient[0].text or "").split()]
        if len(o) != 6:
            raise ValueError(f"{where}: <orientation> must hold α β γ tx ty tz, got {len(o)} values")
        cams.append(_camera([[fx, fs, cx], [0, fy, cy], [0, 0, 1]], [k1, k2, 0.0, 0.0, k3], image_size, where, where))
        poses.append((rotation_from_euler(*o[:3]), np.array(o[3:])))
    return _rig_from_world_poses(cams[0], cams[1], *poses[0], *poses[1],
                                 {"imported_from": path, "format": "VIC-3D"})


def _vic3d_numbers(el, what: str, where: str) -> list[float]:
    return [_number(v, f"{where}: <{what}>") for v in (el.text or "").split()]


def _vic3d_split_camera(el, image_size, where: str):
    """One camera of the ``<intrinsics>/<orientation>/<distortion>`` layout of VIC-3D project files.

    ``<intrinsics>``: CX CY FX FY FS (5 numbers, FS = ``K[0, 1]``); ``<orientation>``: α β γ (degrees,
    ``R = Rz(γ) Ry(β) Rx(α)``, world→camera) tx ty tz (mm), as in the other layout; ``<distortion>``
    (optional): κ1 [κ2 [κ3]] on r², r⁴, r⁶ of normalised coordinates (= OpenCV k1 k2 k3; the same
    assumption as the other layout). Further distortion terms are refused unless they are zero: we
    could not verify what VIC-3D means by them. Returns ``(Camera, (R, t))``; errors name ``where``.
    """
    intr = _vic3d_numbers(el.find("intrinsics"), "intrinsics", where)
    if len(intr) != 5:
        raise ValueError(f"{where}: <intrinsics> must hold CX CY FX FY FS (5 numbers), got {len(intr)}")
    orient = el.findall("orientation")
    if len(orient) != 1:
        raise ValueError(f"{where} has <intrinsics> but " + ("no <orientation>" if not orient else
                                                             f"{len(orient)} <orientation> elements (needs one)"))
    o = _vic3d_numbers(orient[0], "orientation", where)
    if len(o) != 6:
        raise ValueError(f"{where}: <orientation> must hold α β γ tx ty tz, got {len(o)} values")
    dist_el = el.find("distortion")
    kappa = _vic3d_numbers(dist_el, "distortion", where) if dist_el is not None else []
    if any(k != 0.0 for k in kappa[3:]):
        raise ValueError(f"{where}: <distortion> holds {len(kappa)} terms; Specula reads κ1 κ2 κ3 (radial) only "
                         "and the further terms are not zero")
    k1, k2, k3 = (kappa + [0.0, 0.0, 0.0])[:3]
    cx, cy, fx, fy, fs = intr
    cam = _camera([[fx, fs, cx], [0, fy, cy], [0, 0, 1]], [k1, k2, 0.0, 0.0, k3], image_size, where, where)
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
        try:
            root = _parse_xml(path)
        except ValueError as exc:
            raise ValueError(f"calibration file {path!r}: {exc}") from None
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
        return require_image_size(Camera.from_dict(data), ""), fmt
    if fmt == "specula-rig":
        rig = StereoRig.from_dict(data)
        for side, cam in (("left", rig.left), ("right", rig.right)):
            require_image_size(cam, f"{side} camera")
        return rig, fmt
    if fmt == "opencv":
        obj = _opencv_sized(path, image_size)
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


def _opencv_sized(path, image_size):
    """An OpenCV camera or rig with the image size the file records, else ``image_size``."""
    try:
        return load_opencv(path)
    except ValueError as exc:
        if "pass image_size" not in str(exc) or image_size is None:
            raise
    return load_opencv(path, image_size=image_size)


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

    Every function that takes a rig calls this (``dic.StereoCorrelation``, ``stereo``,
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
