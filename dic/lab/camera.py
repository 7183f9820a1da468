"""A camera placed in the virtual lab: intrinsics, pose, thin-lens optics and sensor noise.

Frames and units (docs/conventions.md): world and camera frames in millimetres, camera frame
x right, y down, z forward (OpenCV); ``x_cam = R_cam_world @ x_world + t_cam_world``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from calibration.camera import Camera
from kernels.checks import positive_float


def _vec3(value, what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64).reshape(-1) if value is not None else None
    if arr is None or arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be 3 finite numbers (x, y, z), got {value!r}")
    return arr


def check_rotation(R, what: str) -> np.ndarray:
    """Return ``R`` as a float64 proper rotation (3, 3), or raise ``ValueError`` naming ``what``."""
    try:
        R = np.asarray(R, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a 3x3 rotation matrix of numbers, got {R!r}") from None
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"{what} must be a finite 3x3 rotation matrix, got shape {R.shape}")
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > 1e-6 or np.linalg.det(R) < 0:
        raise ValueError(
            f"{what} must be a proper rotation (R Rᵀ = I, det R = +1); got |R Rᵀ - I| = {err:.2e}, "
            f"det = {np.linalg.det(R):.6f}"
        )
    return R


def look_at(position, target, up=(0.0, -1.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Pose ``(R_cam_world, t_cam_world)`` of a camera at ``position`` looking at ``target`` (world, mm).

    The camera's z axis points at ``target``; its y axis (image down) is opposite to ``up``
    projected onto the image plane. The default ``up = (0, -1, 0)`` suits the lab's world frame
    (x right, y down, z forward, like a camera at the origin with R = I).
    """
    position = _vec3(position, "camera position")
    target = _vec3(target, "look-at target")
    up = _vec3(up, "up direction")
    z = target - position
    if np.linalg.norm(z) == 0:
        raise ValueError("look_at: position and target coincide; the viewing direction is undefined")
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"look_at: up {up.tolist()} is parallel to the viewing direction {z.tolist()}")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ position


@dataclass
class LabCamera:
    """A camera in the virtual lab.

    Attributes
    ----------
    camera : calibration.camera.Camera
        Pinhole + OpenCV distortion model (``K`` px, ``dist``, ``size = (W, H)``, ``name``).
        ``K``'s focal length is the lens-to-sensor distance over the pixel pitch; for a thin lens
        focused at ``s`` that is ``f s / (s - f) / pitch`` (see :meth:`from_lens`).
    R_cam_world, t_cam_world : (3, 3), (3,) float64
        Pose: ``x_cam = R_cam_world @ x_world + t_cam_world`` (mm).
    pixel_pitch_mm : float
        Sensor pixel pitch (mm), e.g. 0.0074 for 7.4 µm pixels.
    focal_length_mm : float
        Focal length of the thin lens (mm); sets the aperture diameter ``f / N``.
    f_number : float
        Aperture f-number ``N``; ``math.inf`` gives a pinhole (no defocus).
    focus_distance_mm : float
        Distance (mm, along the optical axis) from the lens to the plane of sharp focus.
    bit_depth : int
        Bits per pixel of the output (1..16): uint8 images up to 8 bits, uint16 above.
    exposure_dn : float
        Mean grey level (DN) recorded for radiance 1 (a white Lambertian surface or a white
        monitor pixel at full brightness), before noise; the lab's radiance unit is relative.
    black_level_dn : float
        Grey level added to every pixel (dark offset).
    read_noise_dn : float
        Standard deviation (DN) of the Gaussian read noise.
    electrons_per_dn : float
        Conversion gain (e⁻ per DN) for photon shot noise: a pixel with mean signal ``S`` DN
        collects Poisson(``S · gain``) electrons. ``0`` switches shot noise off.
    """

    camera: Camera
    R_cam_world: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_cam_world: np.ndarray = field(default_factory=lambda: np.zeros(3))
    pixel_pitch_mm: float = 0.0074
    focal_length_mm: float = 30.0
    f_number: float = 2.8
    focus_distance_mm: float = 5000.0
    bit_depth: int = 8
    exposure_dn: float = 220.0
    black_level_dn: float = 0.0
    read_noise_dn: float = 0.0
    electrons_per_dn: float = 0.0

    def __post_init__(self):
        if not isinstance(self.camera, Camera):
            raise ValueError(f"LabCamera.camera must be a calibration.camera.Camera, got {type(self.camera).__name__}")
        who = f"camera {self.camera.name!r}" if self.camera.name else "camera"
        if self.camera.size[0] < 1 or self.camera.size[1] < 1:
            raise ValueError(f"{who}: size must be (width, height) >= 1 px, got {self.camera.size}")
        self.R_cam_world = check_rotation(self.R_cam_world, f"{who}: R_cam_world")
        self.t_cam_world = _vec3(self.t_cam_world, f"{who}: t_cam_world")
        for name in ("pixel_pitch_mm", "focal_length_mm", "f_number", "focus_distance_mm", "exposure_dn"):
            # f_number = inf is a pinhole
            setattr(self, name, positive_float(getattr(self, name), f"{who}: {name}", allow_inf=name == "f_number"))
        if self.focus_distance_mm <= self.focal_length_mm:
            raise ValueError(
                f"{who}: focus_distance_mm ({self.focus_distance_mm}) must exceed focal_length_mm "
                f"({self.focal_length_mm}); a thin lens cannot focus closer than its focal length"
            )
        for name in ("black_level_dn", "read_noise_dn", "electrons_per_dn"):
            value = float(getattr(self, name))
            if not (value >= 0 and math.isfinite(value)):
                raise ValueError(f"{who}: {name} must be a finite number >= 0, got {getattr(self, name)!r}")
            setattr(self, name, value)
        if int(self.bit_depth) != self.bit_depth or not 1 <= int(self.bit_depth) <= 16:
            raise ValueError(f"{who}: bit_depth must be an integer in 1..16, got {self.bit_depth!r}")
        self.bit_depth = int(self.bit_depth)
        # K and the lens must describe the same camera (catches px/mm mix-ups)
        v = self.image_distance_mm
        f_px_expected = v / self.pixel_pitch_mm
        rel = abs(self.camera.fx - f_px_expected) / f_px_expected
        if rel > 0.1:
            raise ValueError(
                f"{who}: K's focal length fx = {self.camera.fx:.6g} px disagrees with the lens: a "
                f"{self.focal_length_mm:g} mm lens focused at {self.focus_distance_mm:g} mm with "
                f"{self.pixel_pitch_mm:g} mm pixels has fx = {f_px_expected:.6g} px ({100 * rel:.0f} % off); "
                "check the units (focal length and pixel pitch in mm) or use LabCamera.from_lens"
            )

    # -- construction --------------------------------------------------------------------------
    @classmethod
    def from_lens(
        cls,
        *,
        name: str = "",
        size=(2352, 1728),
        pixel_pitch_mm: float = 0.0074,
        focal_length_mm: float = 30.0,
        f_number: float = 2.8,
        focus_distance_mm: float = 5000.0,
        position=(0.0, 0.0, 0.0),
        look_at_point=(0.0, 0.0, 1000.0),
        up=(0.0, -1.0, 0.0),
        principal_point=None,
        dist=None,
        **sensor,
    ) -> "LabCamera":
        """Build a camera from lens and sensor data, placed at ``position`` looking at ``look_at_point``.

        ``K`` gets ``fx = fy = f s / (s - f) / pitch`` (thin-lens image distance over pixel pitch,
        ``s = focus_distance_mm``) and the principal point ``principal_point`` (px; default the
        image centre ``((W - 1) / 2, (H - 1) / 2)``). ``sensor`` takes the remaining
        :class:`LabCamera` fields (``bit_depth``, ``exposure_dn``, ``read_noise_dn``...).
        """
        W, H = (int(s) for s in size)
        f = float(focal_length_mm)
        s = float(focus_distance_mm)
        if not (f > 0 and pixel_pitch_mm > 0 and s > f):
            raise ValueError(
                "from_lens needs focal_length_mm > 0, pixel_pitch_mm > 0 and focus_distance_mm > focal_length_mm; "
                f"got {focal_length_mm}, {pixel_pitch_mm}, {focus_distance_mm}"
            )
        f_px = f * s / (s - f) / pixel_pitch_mm
        cx, cy = ((W - 1) / 2.0, (H - 1) / 2.0) if principal_point is None else principal_point
        K = np.array([[f_px, 0.0, cx], [0.0, f_px, cy], [0.0, 0.0, 1.0]])
        cam = Camera(K=K, dist=np.zeros(5) if dist is None else dist, size=(W, H), name=name)
        R, t = look_at(position, look_at_point, up)
        return cls(camera=cam, R_cam_world=R, t_cam_world=t, pixel_pitch_mm=pixel_pitch_mm,
                   focal_length_mm=f, f_number=f_number, focus_distance_mm=s, **sensor)

    # -- derived quantities ------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.camera.name

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.camera.size

    @property
    def center_world(self) -> np.ndarray:
        """Optical centre (lens centre) in world coordinates (mm)."""
        return -self.R_cam_world.T @ self.t_cam_world

    @property
    def axis_world(self) -> np.ndarray:
        """Unit optical axis (the camera's +z) in world coordinates."""
        return self.R_cam_world[2].copy()

    @property
    def aperture_diameter_mm(self) -> float:
        """Entrance pupil diameter ``f / N`` (mm); 0 for a pinhole."""
        return 0.0 if math.isinf(self.f_number) else self.focal_length_mm / self.f_number

    @property
    def image_distance_mm(self) -> float:
        """Lens-to-sensor distance of the thin lens focused at ``focus_distance_mm`` (mm)."""
        f, s = self.focal_length_mm, self.focus_distance_mm
        return f * s / (s - f)

    def blur_diameter_px(self, depth_mm) -> np.ndarray:
        """Thin-lens circle-of-confusion diameter (px) for points at camera-frame depth ``depth_mm``.

        ``c = A v |1/s - 1/z| / pitch`` with aperture ``A = f/N``, image distance ``v`` and focus
        distance ``s``; equivalently ``A f |z - s| / (z (s - f)) / pitch``.
        """
        z = np.asarray(depth_mm, dtype=np.float64)
        return self.aperture_diameter_mm * self.camera.fx * np.abs(1.0 / self.focus_distance_mm - 1.0 / z)

    def world_to_camera(self, points_world) -> np.ndarray:
        """(N, 3) world points (mm) -> (N, 3) camera-frame points (mm)."""
        p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        return p @ self.R_cam_world.T + self.t_cam_world

    def scaled(self, scale: float) -> "LabCamera":
        """The same camera with a sensor of ``scale`` times the pixel count per side.

        The sensor keeps its physical size (the pixel pitch grows by ``1/scale``), so the
        geometry, the field of view and the blur in mm on the sensor are unchanged; ``K`` is scaled
        with the pixel-centre convention ``c' = (c + 1/2) s - 1/2``. ``W·scale`` and ``H·scale``
        must be integers.
        """
        scale = float(scale)
        W, H = self.camera.size
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"scale must be a positive finite number, got {scale}")
        Ws, Hs = W * scale, H * scale
        if abs(Ws - round(Ws)) > 1e-9 or abs(Hs - round(Hs)) > 1e-9 or round(Ws) < 1 or round(Hs) < 1:
            raise ValueError(f"scale {scale} must give an integer image size; {W}x{H} -> {Ws}x{Hs}")
        K = self.camera.K.copy()
        K[0, 0] *= scale
        K[0, 1] *= scale
        K[1, 1] *= scale
        K[0, 2] = (K[0, 2] + 0.5) * scale - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * scale - 0.5
        cam = Camera(K=K, dist=self.camera.dist.copy(), size=(int(round(Ws)), int(round(Hs))), name=self.camera.name)
        return replace(self, camera=cam, pixel_pitch_mm=self.pixel_pitch_mm / scale)

    def project(self, points_world) -> np.ndarray:
        """Distorted pixel positions (N, 2) of world points (N, 3); raises for points behind the camera."""
        return self.camera.project(self.world_to_camera(points_world))


def stereo_rig(left: LabCamera, right: LabCamera):
    """The exact calibration of two lab cameras as a :class:`calibration.stereo.StereoRig`: their camera models and
    the right camera's pose in the left camera frame, ``R_right_left = R_right_world R_left_world^T``,
    ``t_right_left = t_right_world - R_right_left t_left_world`` (mm): the rig a perfect calibration of the two
    would give, for measuring with images rendered from them."""
    from calibration.stereo import StereoRig

    for name, cam in (("left", left), ("right", right)):
        if not isinstance(cam, LabCamera):
            raise ValueError(f"{name} must be a dic.lab.LabCamera, got {type(cam).__name__}")
    if left is right:
        raise ValueError("left and right must be two cameras, got the same LabCamera twice")
    R = right.R_cam_world @ left.R_cam_world.T
    return StereoRig(left.camera, right.camera, R, right.t_cam_world - R @ left.t_cam_world)
