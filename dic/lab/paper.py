"""The experiment of the paper behind Specula, as a ready virtual-lab scene.

Paper: "Stereo-camera calibration for large-scale DIC measurements with active phase targets and
planar mirrors", Optics Express 27 (2019) — setup in Section 2 (Fig. 1, 2, 4) and the test layout
of Section 3 (Fig. 7). The numbers the paper gives, and the choices made here to make the layout
physically consistent (docs/lab.md has the figures):

* World frame: origin midway between the two lens centres, x from the left camera to the right
  one, y down, z forward (towards the scene), mm.
* Two Dalsa Falcon 4M30 cameras, 2352 × 1728 px of 7.4 µm, 8 bit, with 28–105 mm zooms at f/2.8
  "and ~30 mm focal length"; here **28 mm** (the zoom's wide end) so that the 3 × 3 × 3 grid of
  monitor positions fits both fields of view. Baseline 1650 mm; both axes cross at
  ``(0, 0, 5400)`` (working distance 5.4 m) and both cameras focus there (5463 mm along the axis).
  The paper's magnifications (1.32 / 1.59 / 1.84 mm/px at the front / middle / rear planes) imply
  about 25 mm; pass ``focal_length_mm=25`` to match them (the grid then spans 3.0 m × 2.1 m).
* Two 185 × 115 mm mirrors, each 400 mm in front of its camera on the optical axis (filling about
  70 % × 60 % of the view), on a kinematic mount tilted so that the camera looks back at the
  27-inch monitor (1920 × 1080 px, 0.311 mm pitch, 597 × 336 mm) standing 650 mm behind the
  cameras, centred between them and facing the scene. The optical path camera → mirror →
  monitor is about 1.7 m, so the monitor is strongly defocused (blur disk ≈ 16 px at full
  resolution). ``mirror_tilts_deg`` lists the mount's settings (rotations about the mirror's
  vertical and horizontal axes from the nominal aim); the default three tilts of 3° move the
  monitor's image by 300–600 px and push part of it past the mirror's edge.
* Section 3's test layout: the monitor at 27 positions of a 3 × 3 × 3 grid centred on the axes'
  crossing point, parallel to the baseline and facing the cameras, spaced 1000 mm (x), 780 mm
  (y) and 900 mm (z): 2.6 m × 1.9 m × 1.8 m including the monitor (paper: about 3 m × 2 m × 1.8 m),
  all fully inside both images. Position labels ``(i, j, k)`` are 1-based as in the paper's
  Fig. 7: i along x (1 = left), j along y (1 = top), k along z (1 = front); ``(2, 2, 2)`` is the
  crossing point. Mirrors are removed for these views, as in the paper.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from calibration.targets import MONITOR_PIXEL_PITCH_MM, MONITOR_RESOLUTION_PX

from .camera import LabCamera
from .scene import Mirror, Scene, Screen, rotation_about

#: Default mirror-mount settings per camera: (about the mirror's vertical axis, about its horizontal axis), degrees.
MIRROR_TILTS_DEG: tuple[tuple[float, float], ...] = ((3.0, 0.0), (-1.5, 2.6), (-1.5, -2.6))

BASELINE_MM = 1650.0
WORKING_DISTANCE_MM = 5400.0
MIRROR_DISTANCE_MM = 400.0
MONITOR_BEHIND_MM = 650.0
MONITOR_RESOLUTION = MONITOR_RESOLUTION_PX
MONITOR_PITCH_MM = MONITOR_PIXEL_PITCH_MM
GRID_SPACING_MM = (1000.0, 780.0, 900.0)
#: The cameras' sensor (Dalsa Falcon 4M30): (width, height) px and pixel pitch, mm.
IMAGE_SIZE_PX = (2352, 1728)
PIXEL_PITCH_MM = 0.0074


@dataclass(frozen=True)
class MonitorPose:
    """One of the 27 monitor positions: ``label = (i, j, k)`` 1-based, and the screen pose."""

    index: int
    label: tuple[int, int, int]
    R_world_screen: np.ndarray
    t_world_screen: np.ndarray


def paper_fringe_image(phase: float = 0.0, resolution=MONITOR_RESOLUTION, cell: int = 300, grid=(6, 3),
                       background: float = 0.5, amplitude: float = 0.45) -> np.ndarray:
    """The paper's circular fringes (Fig. 3): ``grid`` cells of ``cell`` px, ``I = B + A sin(2π r / cell + phase)``.

    ``r`` is the distance (monitor px) from each cell's centre; the 1800 × 900 px pattern is centred
    on a black screen. Returns float32 (H, W) in [0, 1]. (calibration/targets.py builds the full
    phase-shifted target sets; this is the display content of the demo scenes.)
    """
    W, H = resolution
    gx, gy = grid
    img = np.zeros((H, W), dtype=np.float32)
    x0 = (W - gx * cell) // 2
    y0 = (H - gy * cell) // 2
    yy, xx = np.mgrid[0:gy * cell, 0:gx * cell].astype(np.float64)
    cx = (np.floor(xx / cell) + 0.5) * cell - 0.5
    cy = (np.floor(yy / cell) + 0.5) * cell - 0.5
    r = np.hypot(xx - cx, yy - cy)
    img[y0:y0 + gy * cell, x0:x0 + gx * cell] = background + amplitude * np.sin(2 * np.pi * r / cell + phase)
    return img


def _cameras(focal_length_mm: float, f_number: float) -> list[LabCamera]:
    crossing = np.array([0.0, 0.0, WORKING_DISTANCE_MM])
    specs = (
        ("left", (-BASELINE_MM / 2, 0.0, 0.0), (1181.3, 858.2), [-0.090, 0.120, 2.0e-4, -1.5e-4, 0.0]),
        ("right", (BASELINE_MM / 2, 0.0, 0.0), (1170.6, 867.9), [-0.085, 0.100, -1.0e-4, 2.0e-4, 0.0]),
    )
    cams = []
    for name, pos, pp, dist in specs:
        focus = float(np.linalg.norm(crossing - np.asarray(pos)))
        cams.append(LabCamera.from_lens(
            name=name, size=IMAGE_SIZE_PX, pixel_pitch_mm=PIXEL_PITCH_MM, focal_length_mm=focal_length_mm, f_number=f_number,
            focus_distance_mm=focus, position=pos, look_at_point=crossing, principal_point=pp, dist=dist,
            bit_depth=8, exposure_dn=200.0, black_level_dn=2.0, read_noise_dn=1.0, electrons_per_dn=80.0,
        ))
    return cams


def _nominal_mirror(cam: LabCamera, monitor_center: np.ndarray, name: str) -> Mirror:
    center = cam.center_world + MIRROR_DISTANCE_MM * cam.axis_world
    to_monitor = monitor_center - center
    to_monitor /= np.linalg.norm(to_monitor)
    normal = -cam.axis_world + to_monitor  # bisector: the chief ray reflects onto the monitor's centre
    return Mirror(center=center, normal=normal / np.linalg.norm(normal), size=(185.0, 115.0),
                  up=(0.0, -1.0, 0.0), reflectance=0.9, name=name)


def tilt_mirror(mirror: Mirror, about_vertical_deg: float, about_horizontal_deg: float) -> Mirror:
    """The mirror turned about its centre: first about its own vertical (height) axis, then its horizontal (width) axis."""
    R = mirror.R_world_mirror
    rot = rotation_about(R[:, 0], np.radians(about_horizontal_deg)) @ rotation_about(R[:, 1], np.radians(about_vertical_deg))
    return replace(mirror, normal=rot @ mirror.normal, up=rot @ mirror.up)


def _monitor_positions(spacing) -> list[MonitorPose]:
    dx, dy, dz = spacing
    out = []
    for k in range(3):
        for j in range(3):
            for i in range(3):
                center = np.array([(i - 1) * dx, (j - 1) * dy, WORKING_DISTANCE_MM + (k - 1) * dz])
                R = np.eye(3)  # columns along +x, rows along +y (down), facing the cameras (-z)
                W, H = MONITOR_RESOLUTION
                c_local = np.array([(W - 1) / 2 * MONITOR_PITCH_MM, (H - 1) / 2 * MONITOR_PITCH_MM, 0.0])
                out.append(MonitorPose(index=len(out), label=(i + 1, j + 1, k + 1), R_world_screen=R, t_world_screen=center - R @ c_local))
    return out


@dataclass
class PaperRig(Scene):
    """A :class:`Scene` of the paper's rig, plus what is needed to move its parts like in the lab.

    Attributes
    ----------
    monitor_positions : list[MonitorPose]
        The 27 test positions (Section 3), ``monitor_positions[i].label = (i, j, k)``.
    mirror_tilts_deg : tuple of (about_vertical, about_horizontal) degrees
        The mirror-mount settings, the same list for both cameras.
    mirror_tilt : int or None
        Index of the current setting (``None``: no mirrors in the scene).
    nominal_mirrors : list[Mirror]
        The untilted mirrors (left, right).
    calibration_pose : (R_world_screen, t_world_screen)
        The monitor's place behind the cameras for the mirror-based extrinsic calibration.
    crossing_point : (3,)
        Where the optical axes cross (world, mm).
    """

    monitor_positions: list = field(default_factory=list)
    mirror_tilts_deg: tuple = MIRROR_TILTS_DEG
    mirror_tilt: int | None = None
    nominal_mirrors: list = field(default_factory=list)
    calibration_pose: tuple = (np.eye(3), np.zeros(3))
    crossing_point: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, WORKING_DISTANCE_MM]))

    @property
    def monitor(self) -> Screen:
        """The monitor (the scene's only screen)."""
        return self.screens[0]

    def with_mirror_tilt(self, left: int, right: int | None = None) -> "PaperRig":
        """Mirrors in place (monitor behind the cameras), at settings ``left`` and ``right`` (default: same)."""
        right = left if right is None else right
        mirrors = []
        for cam_idx, k in enumerate((left, right)):
            if not (isinstance(k, (int, np.integer)) and 0 <= k < len(self.mirror_tilts_deg)):
                raise ValueError(f"mirror tilt must be an index in 0..{len(self.mirror_tilts_deg) - 1}, got {k!r}")
            a, b = self.mirror_tilts_deg[k]
            mirrors.append(tilt_mirror(self.nominal_mirrors[cam_idx], a, b))
        R, t = self.calibration_pose
        return replace(self, mirrors=mirrors, mirror_tilt=int(left) if left == right else None,
                       screens=[self.monitor.placed(R, t)])

    def without_mirrors(self) -> "PaperRig":
        """The mirrors taken away (monitor where it is)."""
        return replace(self, mirrors=[], mirror_tilt=None)

    def with_monitor_at(self, position) -> "PaperRig":
        """Mirrors removed and the monitor at test position ``position`` (index 0..26 or label ``(i, j, k)``)."""
        if isinstance(position, (tuple, list)):
            labels = {p.label: p for p in self.monitor_positions}
            key = tuple(int(v) for v in position)
            if key not in labels:
                raise ValueError(f"monitor position label must be (i, j, k) with entries in 1..3, got {position!r}")
            pose = labels[key]
        elif isinstance(position, (int, np.integer)) and 0 <= position < len(self.monitor_positions):
            pose = self.monitor_positions[position]
        else:
            raise ValueError(f"monitor position must be an index 0..{len(self.monitor_positions) - 1} or a label (i, j, k), got {position!r}")
        return replace(self, mirrors=[], mirror_tilt=None, screens=[self.monitor.placed(pose.R_world_screen, pose.t_world_screen)])

    def with_monitor_pose(self, R_world_screen, t_world_screen) -> "PaperRig":
        """The monitor at any pose (e.g. the intrinsic-calibration views); mirrors unchanged."""
        return replace(self, screens=[self.monitor.placed(R_world_screen, t_world_screen)])

    def with_monitor_image(self, image) -> "PaperRig":
        """The monitor showing ``image`` ((1080, 1920) float in [0, 1], uint8 or uint16)."""
        return replace(self, screens=[self.monitor.with_image(image)])

    def scene(self) -> Scene:
        """A plain :class:`Scene` with the same content (for saving or editing)."""
        return Scene(cameras=list(self.cameras), mirrors=list(self.mirrors), screens=list(self.screens),
                     planes=list(self.planes), cylinders=list(self.cylinders), background=self.background,
                     max_bounces=self.max_bounces)


def paper_rig(*, scale: float = 1.0, mirror_tilt: int | None = 0, monitor_position=None, image=None,
              mirror_tilts_deg=MIRROR_TILTS_DEG, focal_length_mm: float = 28.0, f_number: float = 2.8,
              grid_spacing_mm=GRID_SPACING_MM, noise: bool = True) -> PaperRig:
    """The paper's stereo rig in the virtual lab (see the module docstring for the layout).

    Parameters
    ----------
    scale : float
        Camera resolution factor (0.25 → 588 × 432 px); geometry, optics and field of view are
        unchanged (``LabCamera.scaled``).
    mirror_tilt : int or None
        Mirror setting for both cameras (index into ``mirror_tilts_deg``), monitor behind the
        cameras. ``None``: no mirrors (monitor behind the cameras unless ``monitor_position``).
    monitor_position : int or (i, j, k), optional
        Put the monitor at one of the 27 test positions (mirrors removed).
    image : (1080, 1920) array, optional
        What the monitor shows; default :func:`paper_fringe_image` (phase 0).
    mirror_tilts_deg : sequence of (about_vertical, about_horizontal) degrees
        The mirror-mount settings (three or more for the mirror calibration).
    focal_length_mm, f_number : float
        Lens settings (28 mm, f/2.8).
    grid_spacing_mm : (dx, dy, dz)
        Spacing of the 3 × 3 × 3 monitor grid.
    noise : bool
        ``False`` zeroes the cameras' read and shot noise (the scene stays 8-bit).
    """
    tilts = tuple((float(a), float(b)) for a, b in mirror_tilts_deg)
    if len(tilts) < 1:
        raise ValueError("mirror_tilts_deg must list at least one (about_vertical, about_horizontal) setting")
    cams = _cameras(float(focal_length_mm), float(f_number))
    if scale != 1.0:
        cams = [c.scaled(scale) for c in cams]
    if not noise:
        cams = [replace(c, read_noise_dn=0.0, electrons_per_dn=0.0) for c in cams]
    monitor_center = np.array([0.0, 0.0, -MONITOR_BEHIND_MM])
    monitor = Screen.facing(center=monitor_center, normal=(0.0, 0.0, 1.0), up=(0.0, -1.0, 0.0),
                            resolution=MONITOR_RESOLUTION, pixel_pitch_mm=MONITOR_PITCH_MM,
                            image=paper_fringe_image() if image is None else image,
                            brightness=1.0, black_level=0.01, nonuniformity=0.05, bezel_mm=15.0, name="monitor")
    nominal = [_nominal_mirror(c, monitor_center, f"mirror_{c.name}") for c in cams]
    rig = PaperRig(cameras=cams, mirrors=[], screens=[monitor], background=0.02,
                   monitor_positions=_monitor_positions(grid_spacing_mm), mirror_tilts_deg=tilts,
                   mirror_tilt=None, nominal_mirrors=nominal,
                   calibration_pose=(monitor.R_world_screen.copy(), monitor.t_world_screen.copy()))
    if monitor_position is not None:
        return rig.with_monitor_at(monitor_position)
    if mirror_tilt is not None:
        return rig.with_mirror_tilt(mirror_tilt)
    return rig


__all__ = ["PaperRig", "MonitorPose", "paper_rig", "paper_fringe_image", "tilt_mirror", "MIRROR_TILTS_DEG",
           "BASELINE_MM", "WORKING_DISTANCE_MM", "MIRROR_DISTANCE_MM", "MONITOR_BEHIND_MM", "MONITOR_RESOLUTION",
           "MONITOR_PITCH_MM", "GRID_SPACING_MM", "IMAGE_SIZE_PX", "PIXEL_PITCH_MM"]

