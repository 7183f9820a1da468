"""Scene model of the virtual lab: cameras, planar mirrors, screens (monitors) and speckled surfaces.

Every object is a plain dataclass in the **world frame** (mm; docs/lab.md draws it: any
right-handed frame works, the paper rig uses x right, y down, z forward from the cameras, so a
camera at the origin with ``R_cam_world = I`` looks along +z). Objects with an image or a texture
carry a local frame named after the frames it maps, ``x_world = R_world_obj @ x_obj +
t_world_obj``:

* :class:`Screen` (a monitor): origin at the **centre of screen pixel (0, 0)**, x along the
  pixel columns, y along the rows, z into the screen; it emits towards −z. A feature displayed at
  screen pixel ``(c, r)`` sits at ``(c · pitch_x, r · pitch_y, 0)`` mm in the screen frame.
* :class:`SpecklePlane`: material coordinates ``(X, Y)`` mm = surface-frame ``(x, y)``, over
  ``[0, w] × [0, h]``; both faces are textured.
* :class:`SpeckleCylinder`: axis along the local y; material coordinates ``(S, Y)`` with ``S``
  the arc length (mm) from the local −z direction towards +x and ``Y`` along the axis.
* :class:`Mirror`: a rectangle given by ``center``, unit ``normal`` (pointing out of the
  reflecting face) and ``size``; its plane is ``n · x + d = 0``. Rays reflect off the front face
  inside the rectangle (Householder: ``d' = d − 2 (n · d) n``); the back face is opaque (black);
  outside the rectangle rays pass.

Surfaces may carry a :class:`Displacement` (3-D, mm) of their material points: the deformed
state renders with the exact same speckle at the displaced material points.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from calibration.targets import MONITOR_PIXEL_PITCH_MM
from kernels.checks import in_range, positive_float

from .camera import LabCamera, _vec3, check_rotation

# ---------------------------------------------------------------------------------------------
# helpers


def _pair(value, what: str, positive: bool = True) -> tuple[float, float]:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be two numbers, got {value!r}") from None
    if arr.shape != (2,) or not np.all(np.isfinite(arr)) or (positive and np.any(arr <= 0)):
        kind = "positive finite numbers" if positive else "finite numbers"
        raise ValueError(f"{what} must be two {kind}, got {value!r}")
    return float(arr[0]), float(arr[1])


def _unit(value, what: str) -> np.ndarray:
    v = _vec3(value, what)
    n = np.linalg.norm(v)
    if n < 1e-12:
        raise ValueError(f"{what} must be a non-zero vector, got {v.tolist()}")
    return v / n


def frame_from_normal(normal, up, what: str) -> np.ndarray:
    """Rotation ``R_world_obj`` of an object whose visible face looks along ``normal``.

    Object frame: z = −normal (into the object), y = −``up`` projected onto the object's plane
    (rows/“down”), x = y × z (columns/“right” as seen from the front).
    """
    n = _unit(normal, f"{what}: normal")
    u = _unit(up, f"{what}: up")
    y = -(u - np.dot(u, n) * n)
    if np.linalg.norm(y) < 1e-9:
        raise ValueError(f"{what}: up {u.tolist()} is parallel to the normal {n.tolist()}; give an up direction in the plane")
    y /= np.linalg.norm(y)
    z = -n
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=1)


def rotation_about(axis, angle_rad: float) -> np.ndarray:
    """Rotation matrix (3, 3) of ``angle_rad`` about unit ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * K + (1 - math.cos(angle_rad)) * (K @ K)


def reflect_points(points, normal, d) -> np.ndarray:
    """Householder reflection of points (N, 3) about the plane ``n · x + d = 0`` (unit ``n``)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normal, dtype=np.float64)
    return p - 2.0 * (p @ n + d)[:, None] * n[None, :]


# ---------------------------------------------------------------------------------------------
# displacement fields


def _keys_weights(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keys (a = −1/2, Catmull-Rom) weights and derivatives for taps −1, 0, 1, 2; t in [0, 1)."""
    t2 = t * t
    w = np.stack([((-0.5 * t + 1.0) * t - 0.5) * t,
                  (1.5 * t - 2.5) * t2 + 1.0,
                  ((-1.5 * t + 2.0) * t + 0.5) * t,
                  (0.5 * t - 0.5) * t2], axis=-1)
    dw = np.stack([-1.5 * t2 + 2.0 * t - 0.5,
                   4.5 * t2 - 5.0 * t,
                   -4.5 * t2 + 4.0 * t + 0.5,
                   1.5 * t2 - t], axis=-1)
    return w, dw


@dataclass
class Displacement:
    """A 3-D displacement field on a surface's material coordinates, sampled on a regular grid.

    ``values[j, i]`` (mm) is the displacement of the material point ``origin + (i·step_x,
    j·step_y)``; between samples it is interpolated with Keys' cubic convolution (Catmull-Rom,
    a = −1/2; clamped taps at the border), identically on the device and in
    :meth:`evaluate`, so the rendered deformation and the ground truth are the same function.

    Components are in the surface frame: ``(u_x, u_y, u_z)`` along the plane's local axes for a
    :class:`SpecklePlane`; ``(u_S, u_Y, u_R)`` tangential (increasing S), axial and radial
    (outwards) for a :class:`SpeckleCylinder`.
    """

    values: np.ndarray
    origin: tuple[float, float] = (0.0, 0.0)
    step: tuple[float, float] = (1.0, 1.0)

    def __post_init__(self):
        v = np.asarray(self.values, dtype=np.float64)
        if v.ndim != 3 or v.shape[2] != 3 or v.shape[0] < 2 or v.shape[1] < 2:
            raise ValueError(f"displacement values must have shape (ny >= 2, nx >= 2, 3), got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError("displacement values contain NaN or infinite entries")
        self.values = v
        self.origin = _pair(self.origin, "displacement origin", positive=False)
        self.step = _pair(self.step, "displacement step")

    @classmethod
    def from_function(cls, func, extent, step: float) -> "Displacement":
        """Sample ``func(X, Y) -> (ux, uy, uz)`` (arrays, mm) on a grid covering ``extent``.

        ``extent = (x0, x1, y0, y1)`` in material mm; the grid extends one step beyond it on
        every side so that the interpolation inside ``extent`` never uses clamped taps.
        """
        x0, x1, y0, y1 = (float(e) for e in extent)
        step = positive_float(step, "displacement step")
        xs = np.arange(x0 - step, x1 + 2 * step, step)
        ys = np.arange(y0 - step, y1 + 2 * step, step)
        X, Y = np.meshgrid(xs, ys)
        u = func(X, Y)
        values = np.stack([np.broadcast_to(np.asarray(c, dtype=np.float64), X.shape) for c in u], axis=-1)
        return cls(values=values, origin=(xs[0], ys[0]), step=(step, step))

    def evaluate(self, XY, derivatives: bool = False):
        """Displacement (N, 3) mm at material points ``XY`` (N, 2) (float64, same interpolant as the renderer).

        With ``derivatives=True`` also returns the derivatives along X and Y, each (N, 3).
        """
        XY = np.asarray(XY, dtype=np.float64).reshape(-1, 2)
        ny, nx, _ = self.values.shape
        fx = (XY[:, 0] - self.origin[0]) / self.step[0]
        fy = (XY[:, 1] - self.origin[1]) / self.step[1]
        ix = np.floor(fx).astype(np.int64)
        iy = np.floor(fy).astype(np.int64)
        wx, dwx = _keys_weights(fx - ix)
        wy, dwy = _keys_weights(fy - iy)
        cols = np.clip(ix[:, None] + np.arange(-1, 3)[None, :], 0, nx - 1)  # (N, 4)
        rows = np.clip(iy[:, None] + np.arange(-1, 3)[None, :], 0, ny - 1)
        patch = self.values[rows[:, :, None], cols[:, None, :]]  # (N, 4, 4, 3)
        u = np.einsum("nj,ni,njic->nc", wy, wx, patch)
        if not derivatives:
            return u
        du_x = np.einsum("nj,ni,njic->nc", wy, dwx, patch) / self.step[0]
        du_y = np.einsum("nj,ni,njic->nc", dwy, wx, patch) / self.step[1]
        return u, du_x, du_y


def _check_speckle(speckle, what: str, extent=None):
    """Accept an object with ``centres`` (M, 2) and ``radii`` (M,) in mm (e.g. dic.synth.BooleanSpeckle).

    When the pattern declares the ``region`` it is complete in (``dic.synth.BooleanSpeckle``), the
    surface's material ``extent = (x0, y0, x1, y1)`` must lie inside it.
    """
    if speckle is None:
        return None
    if not (hasattr(speckle, "centres") and hasattr(speckle, "radii")):
        raise ValueError(
            f"{what}: speckle must have 'centres' (M, 2) and 'radii' (M,) in mm (e.g. dic.synth.make_speckle(...)), "
            f"got {type(speckle).__name__}"
        )
    c = np.asarray(speckle.centres, dtype=np.float64)
    r = np.asarray(speckle.radii, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 2 or r.shape != (c.shape[0],):
        raise ValueError(f"{what}: speckle centres must be (M, 2) and radii (M,), got {c.shape} and {r.shape}")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(r)) and np.all(r > 0)):
        raise ValueError(f"{what}: speckle centres must be finite and radii finite and > 0")
    region = getattr(speckle, "region", None)
    if region is not None and extent is not None:
        r = [float(v) for v in region]
        if extent[0] < r[0] - 1e-9 or extent[1] < r[1] - 1e-9 or extent[2] > r[2] + 1e-9 or extent[3] > r[3] + 1e-9:
            raise ValueError(
                f"{what}: the speckle pattern is complete only in region {tuple(r)} (mm) but the surface's material "
                f"extent is {tuple(extent)}; draw it with dic.synth.make_speckle(region={tuple(extent)}, radius=..., ...)"
            )
    return speckle


@dataclass
class SpeckleDisks:
    """A plain Boolean-model speckle: disk centres (M, 2) and radii (M,) in material mm."""

    centres: np.ndarray
    radii: np.ndarray


# ---------------------------------------------------------------------------------------------
# scene objects


@dataclass
class Mirror:
    """A planar rectangular mirror (world frame, mm).

    ``normal`` points out of the reflecting face; ``up`` fixes the rectangle's height axis (its
    component in the plane); ``size = (width, height)`` mm. ``reflectance`` in (0, 1] scales the
    radiance of what is seen in it.
    """

    center: np.ndarray
    normal: np.ndarray
    size: tuple[float, float] = (185.0, 115.0)
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, -1.0, 0.0]))
    reflectance: float = 1.0
    name: str = ""

    def __post_init__(self):
        who = f"mirror {self.name!r}" if self.name else "mirror"
        self.center = _vec3(self.center, f"{who}: center")
        raw = _vec3(self.normal, f"{who}: normal")
        if np.linalg.norm(raw) < 1e-12:
            raise ValueError(f"{who}: normal must be a non-zero vector, got {raw.tolist()}")
        self.normal = raw / np.linalg.norm(raw)
        self.size = _pair(self.size, f"{who}: size (width, height) mm")
        self.up = _unit(self.up, f"{who}: up")
        frame_from_normal(self.normal, self.up, who)  # checks up is not parallel to the normal
        self.reflectance = in_range(self.reflectance, 0.0, 1.0, f"{who}: reflectance")

    @property
    def plane(self) -> tuple[np.ndarray, float]:
        """``(n, d)`` with ``n · x + d = 0`` in the world frame, ``n`` out of the reflecting face."""
        return self.normal.copy(), float(-self.normal @ self.center)

    @property
    def R_world_mirror(self) -> np.ndarray:
        """Mirror frame: x along the width, y along the height (down), z into the mirror."""
        return frame_from_normal(self.normal, self.up, "mirror")

    def plane_in(self, camera: LabCamera) -> tuple[np.ndarray, float]:
        """``(n, d)`` of the mirror plane in ``camera``'s frame (``d > 0`` when the camera faces the reflecting side)."""
        n, d = self.plane
        n_c = camera.R_cam_world @ n
        return n_c, float(d - n_c @ camera.t_cam_world)

    def corners(self) -> np.ndarray:
        """(4, 3) world corners, in order (−x −y), (+x −y), (+x +y), (−x +y) of the mirror frame."""
        R = self.R_world_mirror
        w, h = self.size
        local = np.array([[-w / 2, -h / 2, 0], [w / 2, -h / 2, 0], [w / 2, h / 2, 0], [-w / 2, h / 2, 0]])
        return local @ R.T + self.center

    def reflect(self, points_world) -> np.ndarray:
        """Householder reflection of world points (N, 3) about the mirror's plane."""
        n, d = self.plane
        return reflect_points(points_world, n, d)


@dataclass
class Screen:
    """A monitor: a planar grid of emitting square pixels showing ``image``.

    Attributes
    ----------
    R_world_screen, t_world_screen :
        Pose of the screen frame (origin at the centre of pixel (0, 0), x along columns, y along
        rows, z into the screen; emission towards −z).
    resolution : (W, H)
        Pixels per row and per column.
    pixel_pitch_mm : float or (px, py)
        Pixel pitch (mm); each pixel is a uniformly emitting rectangle (fill factor 1).
    image : (H, W) array or None
        Displayed image: floats in [0, 1], or uint8/uint16 (scaled by 255/65535). ``None``: black.
    brightness : float
        Radiance of a full-white pixel (relative units; 1 = white paper under the lab light).
    black_level : float
        Radiance of a black pixel (LCD leakage), < brightness.
    nonuniformity : float
        Relative emission drop at the corners: radiance × (1 − a (ρx² + ρy²) / 2) with ρ in
        [−1, 1] across the active area (0 = uniform).
    bezel_mm : float
        Width of the dark frame around the active area (radiance 0); 0 = no frame.
    """

    R_world_screen: np.ndarray
    t_world_screen: np.ndarray
    resolution: tuple[int, int] = (1920, 1080)
    pixel_pitch_mm: float | tuple[float, float] = MONITOR_PIXEL_PITCH_MM
    image: np.ndarray | None = None
    brightness: float = 1.0
    black_level: float = 0.0
    nonuniformity: float = 0.0
    bezel_mm: float = 0.0
    name: str = ""

    def __post_init__(self):
        who = f"screen {self.name!r}" if self.name else "screen"
        self.R_world_screen = check_rotation(self.R_world_screen, f"{who}: R_world_screen")
        self.t_world_screen = _vec3(self.t_world_screen, f"{who}: t_world_screen")
        try:
            W, H = (int(r) for r in self.resolution)
            if (W, H) != tuple(self.resolution) or W < 1 or H < 1:
                raise ValueError
        except (TypeError, ValueError):
            raise ValueError(f"{who}: resolution must be two positive integers (width, height), got {self.resolution!r}") from None
        self.resolution = (W, H)
        pitch = self.pixel_pitch_mm
        self.pixel_pitch_mm = _pair(pitch if np.ndim(pitch) else (pitch, pitch), f"{who}: pixel_pitch_mm")
        self.image = self._check_image(self.image, who)
        self.brightness = positive_float(self.brightness, f"{who}: brightness")
        self.black_level = in_range(self.black_level, 0.0, self.brightness, f"{who}: black_level")
        self.nonuniformity = in_range(self.nonuniformity, 0.0, 1.0, f"{who}: nonuniformity")
        self.bezel_mm = in_range(self.bezel_mm, 0.0, 1e6, f"{who}: bezel_mm")

    def _check_image(self, image, who):
        W, H = self.resolution
        if image is None:
            return np.zeros((H, W), dtype=np.float32)
        arr = np.asarray(image)
        if arr.shape != (H, W):
            raise ValueError(
                f"{who}: image must have shape (H, W) = ({H}, {W}) to match resolution {W}x{H}, got {arr.shape}"
                + ("; colour images are not supported, convert to grey" if arr.ndim == 3 else "")
            )
        if arr.dtype == np.uint8:
            return arr.astype(np.float32) / 255.0
        if arr.dtype == np.uint16:
            return arr.astype(np.float32) / 65535.0
        if arr.dtype == bool:
            return arr.astype(np.float32)
        if not np.issubdtype(arr.dtype, np.floating):
            raise ValueError(f"{who}: image must be float in [0, 1], uint8 or uint16, got dtype {arr.dtype}")
        arr = arr.astype(np.float32)
        if not np.all(np.isfinite(arr)) or arr.min() < 0 or arr.max() > 1:
            raise ValueError(f"{who}: float image values must be finite and in [0, 1], got range "
                             f"[{np.nanmin(arr):.4g}, {np.nanmax(arr):.4g}]")
        return arr

    def with_image(self, image) -> "Screen":
        """A copy of this screen displaying ``image`` (same checks as the constructor)."""
        return replace(self, image=image)

    @property
    def size_mm(self) -> tuple[float, float]:
        """Active area (width, height) in mm."""
        return self.resolution[0] * self.pixel_pitch_mm[0], self.resolution[1] * self.pixel_pitch_mm[1]

    @property
    def normal(self) -> np.ndarray:
        """Unit world normal of the emitting face (towards the viewer)."""
        return -self.R_world_screen[:, 2]

    @property
    def center_world(self) -> np.ndarray:
        """World position (mm) of the centre of the active area."""
        W, H = self.resolution
        return self.to_world([[(W - 1) / 2.0, (H - 1) / 2.0]])[0]

    def to_world(self, pixels) -> np.ndarray:
        """World points (N, 3) mm of screen pixel positions ``pixels`` (N, 2) = (col, row), (0, 0) = centre of the first pixel."""
        pix = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        local = np.column_stack([pix[:, 0] * self.pixel_pitch_mm[0], pix[:, 1] * self.pixel_pitch_mm[1], np.zeros(len(pix))])
        return local @ self.R_world_screen.T + self.t_world_screen

    def corners(self) -> np.ndarray:
        """(4, 3) world corners of the active area: top-left, top-right, bottom-right, bottom-left."""
        W, H = self.resolution
        return self.to_world([[-0.5, -0.5], [W - 0.5, -0.5], [W - 0.5, H - 0.5], [-0.5, H - 0.5]])

    def outer_corners(self) -> np.ndarray:
        """(4, 3) world corners of the screen with its bezel (same order as :meth:`corners`)."""
        W, H = self.resolution
        bx, by = self.bezel_mm / self.pixel_pitch_mm[0], self.bezel_mm / self.pixel_pitch_mm[1]
        return self.to_world([[-0.5 - bx, -0.5 - by], [W - 0.5 + bx, -0.5 - by], [W - 0.5 + bx, H - 0.5 + by],
                              [-0.5 - bx, H - 0.5 + by]])

    @classmethod
    def facing(cls, center, normal, up=(0.0, -1.0, 0.0), **kw) -> "Screen":
        """A screen whose active area is centred at ``center`` (world mm), emitting along ``normal``, top edge towards ``up``."""
        tmp = cls(R_world_screen=np.eye(3), t_world_screen=np.zeros(3), **kw)
        R = frame_from_normal(normal, up, f"screen {tmp.name!r}" if tmp.name else "screen")
        W, H = tmp.resolution
        px, py = tmp.pixel_pitch_mm
        c_local = np.array([(W - 1) / 2.0 * px, (H - 1) / 2.0 * py, 0.0])
        return replace(tmp, R_world_screen=R, t_world_screen=_vec3(center, "screen center") - R @ c_local)

    def placed(self, R_world_screen, t_world_screen) -> "Screen":
        """A copy of this screen at another pose."""
        return replace(self, R_world_screen=R_world_screen, t_world_screen=t_world_screen)


@dataclass
class SpecklePlane:
    """A flat rectangle of material ``[0, w] × [0, h]`` mm painted with Boolean-model speckle.

    ``R_world_surface, t_world_surface`` place the surface frame (material ``(X, Y, 0)``). The
    radiance is ``albedo[0]`` on the background and ``albedo[1]`` inside speckle disks (uniform
    diffuse lighting). ``displacement`` (optional) moves material points by ``u(X, Y)`` (surface
    frame components).
    """

    R_world_surface: np.ndarray
    t_world_surface: np.ndarray
    size: tuple[float, float] = (200.0, 200.0)
    speckle: object | None = None
    albedo: tuple[float, float] = (0.9, 0.1)
    displacement: Displacement | None = None
    name: str = ""

    def __post_init__(self):
        who = f"plane {self.name!r}" if self.name else "plane"
        self.R_world_surface = check_rotation(self.R_world_surface, f"{who}: R_world_surface")
        self.t_world_surface = _vec3(self.t_world_surface, f"{who}: t_world_surface")
        self.size = _pair(self.size, f"{who}: size (width, height) mm")
        self.albedo = _albedo(self.albedo, who)
        self.speckle = _check_speckle(self.speckle, who, (0.0, 0.0, self.size[0], self.size[1]))
        if self.displacement is not None and not isinstance(self.displacement, Displacement):
            raise ValueError(f"{who}: displacement must be a dic.lab.Displacement, got {type(self.displacement).__name__}")

    @classmethod
    def facing(cls, center, normal, up=(0.0, -1.0, 0.0), **kw) -> "SpecklePlane":
        """A plane centred at ``center``, material x along the viewer's right, y down, front face along ``normal``."""
        tmp = cls(R_world_surface=np.eye(3), t_world_surface=np.zeros(3), **kw)
        R = frame_from_normal(normal, up, f"plane {tmp.name!r}" if tmp.name else "plane")
        w, h = tmp.size
        return replace(tmp, R_world_surface=R, t_world_surface=_vec3(center, "plane center") - R @ np.array([w / 2, h / 2, 0.0]))

    def to_world(self, XY, deformed: bool = True) -> np.ndarray:
        """World positions (N, 3) of material points ``XY`` (N, 2) mm, displaced when ``deformed``."""
        XY = np.asarray(XY, dtype=np.float64).reshape(-1, 2)
        local = np.column_stack([XY, np.zeros(len(XY))])
        if deformed and self.displacement is not None:
            local = local + self.displacement.evaluate(XY)
        return local @ self.R_world_surface.T + self.t_world_surface


@dataclass
class SpeckleCylinder:
    """A speckled cylinder (or part of one) of radius ``radius`` mm.

    Surface frame: the axis is the local y axis, material ``Y`` in ``[0, length]``; the arc
    coordinate ``S`` (mm) runs from the local −z direction (``S = 0``, facing a viewer on the −z
    side) towards +x, over ``arc = (S_min, S_max)`` (default the full circumference). Material
    point ``(S, Y)`` is at ``(R sin θ, Y, −R cos θ)`` with ``θ = S / R``. Both faces are textured.
    """

    R_world_surface: np.ndarray
    t_world_surface: np.ndarray
    radius: float = 100.0
    length: float = 300.0
    arc: tuple[float, float] | None = None
    speckle: object | None = None
    albedo: tuple[float, float] = (0.9, 0.1)
    displacement: Displacement | None = None
    name: str = ""

    def __post_init__(self):
        who = f"cylinder {self.name!r}" if self.name else "cylinder"
        self.R_world_surface = check_rotation(self.R_world_surface, f"{who}: R_world_surface")
        self.t_world_surface = _vec3(self.t_world_surface, f"{who}: t_world_surface")
        self.radius = positive_float(self.radius, f"{who}: radius")
        self.length = positive_float(self.length, f"{who}: length")
        half = math.pi * self.radius
        arc = (-half, half) if self.arc is None else _pair(self.arc, f"{who}: arc (S_min, S_max) mm", positive=False)
        if not (-half - 1e-9 <= arc[0] < arc[1] <= half + 1e-9):
            raise ValueError(f"{who}: arc must satisfy -pi*R <= S_min < S_max <= pi*R (= {half:.6g} mm), got {arc}")
        self.arc = arc
        self.albedo = _albedo(self.albedo, who)
        self.speckle = _check_speckle(self.speckle, who, (self.arc[0], 0.0, self.arc[1], self.length))
        if self.displacement is not None and not isinstance(self.displacement, Displacement):
            raise ValueError(f"{who}: displacement must be a dic.lab.Displacement, got {type(self.displacement).__name__}")

    @classmethod
    def facing(cls, center, axis, front, **kw) -> "SpeckleCylinder":
        """A cylinder with its axis through ``center`` (mid-length) along ``axis``; ``S = 0`` faces ``front``."""
        tmp = cls(R_world_surface=np.eye(3), t_world_surface=np.zeros(3), **kw)
        who = f"cylinder {tmp.name!r}" if tmp.name else "cylinder"
        y = _unit(axis, f"{who}: axis")
        f = _unit(front, f"{who}: front")
        z = -(f - np.dot(f, y) * y)
        if np.linalg.norm(z) < 1e-9:
            raise ValueError(f"{who}: front {f.tolist()} is parallel to the axis")
        z /= np.linalg.norm(z)
        R = np.stack([np.cross(y, z), y, z], axis=1)
        return replace(tmp, R_world_surface=R, t_world_surface=_vec3(center, "cylinder center") - R @ np.array([0.0, tmp.length / 2, 0.0]))

    def to_world(self, SY, deformed: bool = True) -> np.ndarray:
        """World positions (N, 3) of material points ``(S, Y)`` (N, 2) mm, displaced when ``deformed``."""
        SY = np.asarray(SY, dtype=np.float64).reshape(-1, 2)
        th = SY[:, 0] / self.radius
        s, c = np.sin(th), np.cos(th)
        zeros = np.zeros_like(th)
        e_r = np.column_stack([s, zeros, -c])
        e_t = np.column_stack([c, zeros, s])
        e_y = np.column_stack([zeros, np.ones_like(th), zeros])
        local = self.radius * e_r + SY[:, 1:2] * e_y
        if deformed and self.displacement is not None:
            u = self.displacement.evaluate(SY)
            local = local + u[:, 0:1] * e_t + u[:, 1:2] * e_y + u[:, 2:3] * e_r
        return local @ self.R_world_surface.T + self.t_world_surface


def _albedo(value, who):
    try:
        a = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{who}: albedo must be (background, speckle) in [0, 1], got {value!r}") from None
    if a.shape != (2,) or not np.all(np.isfinite(a)) or np.any(a < 0) or np.any(a > 1):
        raise ValueError(f"{who}: albedo must be two numbers (background, speckle) in [0, 1], got {value!r}")
    return float(a[0]), float(a[1])


# ---------------------------------------------------------------------------------------------
# the scene


@dataclass
class Scene:
    """Everything the renderer sees. ``background`` is the radiance of rays that hit nothing;
    ``max_bounces`` bounds mirror reflections per ray (a ray still bouncing after that is black)."""

    cameras: list = field(default_factory=list)
    mirrors: list = field(default_factory=list)
    screens: list = field(default_factory=list)
    planes: list = field(default_factory=list)
    cylinders: list = field(default_factory=list)
    background: float = 0.0
    max_bounces: int = 4

    def __post_init__(self):
        for attr, cls in (("cameras", LabCamera), ("mirrors", Mirror), ("screens", Screen),
                          ("planes", SpecklePlane), ("cylinders", SpeckleCylinder)):
            items = list(getattr(self, attr))
            for i, item in enumerate(items):
                if not isinstance(item, cls):
                    raise ValueError(f"scene.{attr}[{i}] must be a {cls.__name__}, got {type(item).__name__}")
            setattr(self, attr, items)
        names = [c.name for c in self.cameras if c.name]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"camera names must be unique, repeated: {sorted(dup)}")
        self.background = in_range(self.background, 0.0, 1e6, "scene background")
        if int(self.max_bounces) != self.max_bounces or not 0 <= int(self.max_bounces) <= 16:
            raise ValueError(f"scene max_bounces must be an integer in 0..16, got {self.max_bounces!r}")
        self.max_bounces = int(self.max_bounces)

    def camera(self, key) -> LabCamera:
        """The camera given by index or name (``ValueError`` listing the choices otherwise)."""
        if isinstance(key, LabCamera):
            return key
        if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
            if not -len(self.cameras) <= key < len(self.cameras):
                raise ValueError(f"camera index {key} out of range; the scene has {len(self.cameras)} camera(s)")
            return self.cameras[key]
        for cam in self.cameras:
            if cam.name == key:
                return cam
        raise ValueError(f"no camera named {key!r}; cameras: {[c.name or i for i, c in enumerate(self.cameras)]}")

    def replace(self, **changes) -> "Scene":
        """A copy with some fields changed (``dataclasses.replace``)."""
        return replace(self, **changes)

    def ground_truth(self) -> dict:
        """JSON-serialisable ground truth: camera models and poses, mirror planes, screen poses.

        Mirror planes are given in the world frame and in every camera's frame (``n · x + d = 0``,
        ``n`` out of the reflecting face).
        """
        out = {
            "units": "mm, px; x_cam = R_cam_world @ x_world + t_cam_world; pixel (0, 0) = centre of the top-left pixel",
            "cameras": [],
            "mirrors": [],
            "screens": [],
            "planes": [],
            "cylinders": [],
        }
        for i, cam in enumerate(self.cameras):
            out["cameras"].append({
                "name": cam.name or f"camera{i}",
                "K": cam.camera.K.tolist(),
                "dist": cam.camera.dist.tolist(),
                "size": list(cam.size),
                "R_cam_world": cam.R_cam_world.tolist(),
                "t_cam_world": cam.t_cam_world.tolist(),
                "center_world": cam.center_world.tolist(),
                "pixel_pitch_mm": cam.pixel_pitch_mm,
                "focal_length_mm": cam.focal_length_mm,
                "f_number": None if math.isinf(cam.f_number) else cam.f_number,
                "focus_distance_mm": cam.focus_distance_mm,
                "bit_depth": cam.bit_depth,
                "exposure_dn": cam.exposure_dn,
                "black_level_dn": cam.black_level_dn,
                "read_noise_dn": cam.read_noise_dn,
                "electrons_per_dn": cam.electrons_per_dn,
            })
        for k, m in enumerate(self.mirrors):
            n, d = m.plane
            entry = {"name": m.name or f"mirror{k}", "normal_world": n.tolist(), "d_world": d,
                     "center_world": m.center.tolist(), "size_mm": list(m.size), "corners_world": m.corners().tolist(),
                     "reflectance": m.reflectance, "plane_in_camera": {}}
            for i, cam in enumerate(self.cameras):
                nc, dc = m.plane_in(cam)
                entry["plane_in_camera"][cam.name or f"camera{i}"] = {"normal": nc.tolist(), "d": dc}
            out["mirrors"].append(entry)
        for k, s in enumerate(self.screens):
            out["screens"].append({"name": s.name or f"screen{k}", "R_world_screen": s.R_world_screen.tolist(),
                                   "t_world_screen": s.t_world_screen.tolist(), "resolution": list(s.resolution),
                                   "pixel_pitch_mm": list(s.pixel_pitch_mm), "corners_world": s.corners().tolist(),
                                   "frame": "origin at the centre of screen pixel (0, 0); x along columns, y along rows, z into the screen"})
        for attr in ("planes", "cylinders"):
            for k, s in enumerate(getattr(self, attr)):
                entry = {"name": s.name or f"{attr[:-1]}{k}", "R_world_surface": s.R_world_surface.tolist(),
                         "t_world_surface": s.t_world_surface.tolist(), "deformed": s.displacement is not None}
                entry.update({"size_mm": list(s.size)} if attr == "planes" else
                             {"radius_mm": s.radius, "length_mm": s.length, "arc_mm": list(s.arc)})
                out[attr].append(entry)
        return out


SCENE_OBJECTS = {"camera": LabCamera, "mirror": Mirror, "screen": Screen, "plane": SpecklePlane, "cylinder": SpeckleCylinder}

__all__ = [
    "Displacement", "Mirror", "Scene", "Screen", "SpeckleCylinder", "SpeckleDisks", "SpecklePlane",
    "frame_from_normal", "reflect_points", "rotation_about",
]

