"""Scene files: load a virtual-lab :class:`~dic.lab.scene.Scene` from TOML, and write one.

The format (docs/lab.md has a full example) is one array of tables per object kind::

    background = 0.02            # radiance of rays that hit nothing
    max_bounces = 4

    [[camera]]
    name = "left"
    size = [2352, 1728]
    pixel_pitch_mm = 0.0074
    focal_length_mm = 28.0
    f_number = 2.8               # inf: pinhole
    focus_distance_mm = 5462.7
    dist = [-0.09, 0.12, 0.0002, -0.00015, 0.0]
    position = [-825.0, 0.0, 0.0]   # or R_cam_world = [[...], ...] and t_cam_world = [...]
    look_at = [0.0, 0.0, 5400.0]
    # K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]   optional: default from the lens, principal_point or the centre

    [[mirror]]
    center = [...]; normal = [...]; size = [185.0, 115.0]; up = [0.0, -1.0, 0.0]; reflectance = 0.9

    [[screen]]
    resolution = [1920, 1080]; pixel_pitch_mm = 0.311
    center = [...]; normal = [...]      # or R_world_screen / t_world_screen
    image = "fringes.png"               # path relative to this file (.png, .tif, .npy), or fill = 0.5

    [[plane]]
    size = [300.0, 200.0]; center = [...]; normal = [...]
    speckle = { radius = 1.0, density = 0.5, seed = 1 }   # dic.synth.make_speckle over the plane, in mm
    displacement = "bulge.npz"          # optional: arrays values (ny, nx, 3), origin (2,), step (2,)

    [[cylinder]]
    radius = 80.0; length = 300.0; center = [...]; axis = [0.0, 1.0, 0.0]; front = [0.0, 0.0, -1.0]

Unknown keys, missing keys and bad values raise ``ValueError`` naming the file, the object and the
field.
"""
from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np

from calibration.camera import Camera
from calibration.targets import MONITOR_PIXEL_PITCH_MM
from kernels._atomic import atomic_output
from kernels.images import read_image

from .camera import LabCamera, look_at
from .scene import Displacement, Mirror, Scene, Screen, SpeckleCylinder, SpeckleDisks, SpecklePlane

TOP_KEYS = {"background", "max_bounces", "camera", "mirror", "screen", "plane", "cylinder"}
CAMERA_KEYS = {"name", "size", "pixel_pitch_mm", "focal_length_mm", "f_number", "focus_distance_mm", "K", "principal_point",
               "dist", "R_cam_world", "t_cam_world", "position", "look_at", "up", "bit_depth", "exposure_dn",
               "black_level_dn", "read_noise_dn", "electrons_per_dn"}
MIRROR_KEYS = {"name", "center", "normal", "size", "up", "reflectance"}
SCREEN_KEYS = {"name", "resolution", "pixel_pitch_mm", "image", "fill", "brightness", "black_level", "nonuniformity",
               "bezel_mm", "R_world_screen", "t_world_screen", "center", "normal", "up"}
PLANE_KEYS = {"name", "size", "albedo", "speckle", "speckle_file", "displacement", "R_world_surface", "t_world_surface",
              "center", "normal", "up"}
CYLINDER_KEYS = {"name", "radius", "length", "arc", "albedo", "speckle", "speckle_file", "displacement",
                 "R_world_surface", "t_world_surface", "center", "axis", "front"}
SPECKLE_KEYS = {"radius", "density", "radius_spread", "seed"}


class _Section:
    """One TOML table, with key checks that name the file and object in every error."""

    def __init__(self, table, where: str, known: set[str]):
        if not isinstance(table, dict):
            raise ValueError(f"{where}: expected a table, got {type(table).__name__}")
        self.table, self.where = table, where
        unknown = sorted(set(table) - known)
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {unknown}; known keys: {sorted(known)}")

    def get(self, key, default=None):
        return self.table.get(key, default)

    def has(self, key) -> bool:
        return key in self.table

    def require(self, key):
        if key not in self.table:
            raise ValueError(f"{self.where}: missing required key '{key}'")
        return self.table[key]

    def number(self, key, default=None, positive=False):
        if key not in self.table:
            if default is None:
                raise ValueError(f"{self.where}: missing required key '{key}'")
            return default
        v = self.table[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v):
            raise ValueError(f"{self.where}: '{key}' must be a number, got {v!r}")
        if positive and not v > 0:
            raise ValueError(f"{self.where}: '{key}' must be positive, got {v!r}")
        return float(v)

    def array(self, key, shape, default=None):
        if key not in self.table:
            if default is None:
                raise ValueError(f"{self.where}: missing required key '{key}'")
            return np.asarray(default, dtype=np.float64)
        try:
            a = np.asarray(self.table[key], dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{self.where}: '{key}' must be an array of numbers of shape {shape}, got {self.table[key]!r}") from None
        if shape is not None and a.shape != tuple(shape):
            raise ValueError(f"{self.where}: '{key}' must have shape {tuple(shape)}, got {a.shape}")
        return a

    def pose(self, R_key, t_key, alt: tuple[str, ...]):
        """Either the explicit pose pair or the alternative keys, never both or neither."""
        explicit = self.has(R_key) or self.has(t_key)
        other = any(self.has(k) for k in alt)
        if explicit and other:
            raise ValueError(f"{self.where}: give either {R_key}/{t_key} or {'/'.join(alt)}, not both")
        if explicit:
            return self.array(R_key, (3, 3)), self.array(t_key, (3,))
        if not other:
            raise ValueError(f"{self.where}: missing pose; give {R_key} and {t_key}, or {' and '.join(alt)}")
        return None


def _resolve(base: Path, name: str, where: str) -> Path:
    if not isinstance(name, str):
        raise ValueError(f"{where}: expected a file name (string), got {name!r}")
    p = Path(name)
    p = p if p.is_absolute() else base / p
    if not p.is_file():
        raise ValueError(f"{where}: file {str(p)!r} not found")
    return p


def _read_image(path: Path, where: str) -> np.ndarray:
    """A screen image: ``.npy`` as stored, image files by the rules of :func:`kernels.images.read_image`."""
    if path.suffix.lower() == ".npy":
        try:
            return np.load(path)
        except Exception as exc:  # unreadable file: say which and why
            raise ValueError(f"{where}: cannot read image {str(path)!r}: {exc}") from None
    try:
        return read_image(path)
    except ValueError as exc:  # the message names the file; add the scene field
        raise ValueError(f"{where}: {exc}") from None


def _camera(sec: _Section) -> LabCamera:
    name = sec.get("name", "")
    size = sec.require("size")
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(s, int) and s > 0 for s in size)):
        raise ValueError(f"{sec.where}: 'size' must be [width, height] positive integers, got {size!r}")
    pitch = sec.number("pixel_pitch_mm", positive=True)
    f = sec.number("focal_length_mm", positive=True)
    N = sec.number("f_number", positive=True)
    s = sec.number("focus_distance_mm", positive=True)
    if s <= f:
        raise ValueError(f"{sec.where}: 'focus_distance_mm' ({s}) must exceed 'focal_length_mm' ({f})")
    dist = sec.array("dist", None, default=np.zeros(5)).ravel()
    pose = sec.pose("R_cam_world", "t_cam_world", ("position", "look_at"))
    if pose is None:
        R, t = look_at(sec.array("position", (3,)), sec.array("look_at", (3,)), sec.array("up", (3,), default=[0.0, -1.0, 0.0]))
    else:
        R, t = pose
    if sec.has("K"):
        if sec.has("principal_point"):
            raise ValueError(f"{sec.where}: give either 'K' or 'principal_point', not both")
        K = sec.array("K", (3, 3))
    else:
        f_px = f * s / (s - f) / pitch
        cx, cy = sec.array("principal_point", (2,), default=[(size[0] - 1) / 2, (size[1] - 1) / 2])
        K = np.array([[f_px, 0.0, cx], [0.0, f_px, cy], [0.0, 0.0, 1.0]])
    bits = sec.get("bit_depth", 8)
    if isinstance(bits, bool) or not isinstance(bits, int):
        raise ValueError(f"{sec.where}: 'bit_depth' must be an integer, got {bits!r}")
    return LabCamera(camera=Camera(K=K, dist=dist, size=tuple(size), name=name), R_cam_world=R, t_cam_world=t,
                     pixel_pitch_mm=pitch, focal_length_mm=f, f_number=N, focus_distance_mm=s, bit_depth=bits,
                     exposure_dn=sec.number("exposure_dn", 220.0, positive=True),
                     black_level_dn=sec.number("black_level_dn", 0.0), read_noise_dn=sec.number("read_noise_dn", 0.0),
                     electrons_per_dn=sec.number("electrons_per_dn", 0.0))


def _mirror(sec: _Section) -> Mirror:
    return Mirror(center=sec.array("center", (3,)), normal=sec.array("normal", (3,)),
                  size=tuple(sec.array("size", (2,), default=[185.0, 115.0])),
                  up=sec.array("up", (3,), default=[0.0, -1.0, 0.0]), reflectance=sec.number("reflectance", 1.0),
                  name=sec.get("name", ""))


def _screen(sec: _Section, base: Path) -> Screen:
    res = sec.require("resolution")
    if not (isinstance(res, list) and len(res) == 2 and all(isinstance(r, int) and r > 0 for r in res)):
        raise ValueError(f"{sec.where}: 'resolution' must be [width, height] positive integers, got {res!r}")
    pitch = sec.get("pixel_pitch_mm", MONITOR_PIXEL_PITCH_MM)
    if sec.has("image") and sec.has("fill"):
        raise ValueError(f"{sec.where}: give either 'image' (a file) or 'fill' (a constant in [0, 1]), not both")
    if sec.has("image"):
        image = _read_image(_resolve(base, sec.get("image"), f"{sec.where}: 'image'"), f"{sec.where}: 'image'")
    else:
        image = np.full((res[1], res[0]), sec.number("fill", 0.0), dtype=np.float32)
    kw = dict(resolution=tuple(res), pixel_pitch_mm=pitch, image=image, brightness=sec.number("brightness", 1.0),
              black_level=sec.number("black_level", 0.0), nonuniformity=sec.number("nonuniformity", 0.0),
              bezel_mm=sec.number("bezel_mm", 0.0), name=sec.get("name", ""))
    pose = sec.pose("R_world_screen", "t_world_screen", ("center", "normal"))
    if pose is None:
        return Screen.facing(sec.array("center", (3,)), sec.array("normal", (3,)), sec.array("up", (3,), default=[0.0, -1.0, 0.0]), **kw)
    return Screen(R_world_screen=pose[0], t_world_screen=pose[1], **kw)


def _speckle(sec: _Section, base: Path, region):
    if sec.has("speckle") and sec.has("speckle_file"):
        raise ValueError(f"{sec.where}: give either 'speckle' (parameters) or 'speckle_file', not both")
    if sec.has("speckle_file"):
        path = _resolve(base, sec.get("speckle_file"), f"{sec.where}: 'speckle_file'")
        with np.load(path) as z:
            if "centres" not in z or "radii" not in z:
                raise ValueError(f"{sec.where}: speckle_file {str(path)!r} must hold arrays 'centres' (M, 2) and 'radii' (M,)")
            return SpeckleDisks(centres=z["centres"], radii=z["radii"])
    if not sec.has("speckle"):
        return None
    spk = _Section(sec.get("speckle"), f"{sec.where}: speckle", SPECKLE_KEYS)
    from dic.synth import make_speckle

    return make_speckle(region=region, radius=spk.number("radius", 1.0, positive=True),
                        density=spk.number("density", 0.5), radius_spread=spk.number("radius_spread", 0.2),
                        seed=int(spk.number("seed", 0.0)), blur=0.0)


def _displacement(sec: _Section, base: Path):
    if not sec.has("displacement"):
        return None
    path = _resolve(base, sec.get("displacement"), f"{sec.where}: 'displacement'")
    with np.load(path) as z:
        missing = {"values", "origin", "step"} - set(z.files)
        if missing:
            raise ValueError(f"{sec.where}: displacement file {str(path)!r} lacks arrays {sorted(missing)}")
        try:
            return Displacement(values=z["values"], origin=tuple(z["origin"]), step=tuple(z["step"]))
        except ValueError as exc:
            raise ValueError(f"{sec.where}: displacement file {str(path)!r}: {exc}") from None


def _plane(sec: _Section, base: Path) -> SpecklePlane:
    size = tuple(sec.array("size", (2,)))
    kw = dict(size=size, albedo=tuple(sec.array("albedo", (2,), default=[0.9, 0.1])),
              speckle=_speckle(sec, base, (0.0, 0.0, size[0], size[1])), displacement=_displacement(sec, base),
              name=sec.get("name", ""))
    pose = sec.pose("R_world_surface", "t_world_surface", ("center", "normal"))
    if pose is None:
        return SpecklePlane.facing(sec.array("center", (3,)), sec.array("normal", (3,)), sec.array("up", (3,), default=[0.0, -1.0, 0.0]), **kw)
    return SpecklePlane(R_world_surface=pose[0], t_world_surface=pose[1], **kw)


def _cylinder(sec: _Section, base: Path) -> SpeckleCylinder:
    radius = sec.number("radius", positive=True)
    length = sec.number("length", positive=True)
    arc = tuple(sec.array("arc", (2,), default=[-math.pi * radius, math.pi * radius]))
    kw = dict(radius=radius, length=length, arc=arc, albedo=tuple(sec.array("albedo", (2,), default=[0.9, 0.1])),
              speckle=_speckle(sec, base, (arc[0], 0.0, arc[1], length)), displacement=_displacement(sec, base),
              name=sec.get("name", ""))
    pose = sec.pose("R_world_surface", "t_world_surface", ("center", "axis", "front"))
    if pose is None:
        return SpeckleCylinder.facing(sec.array("center", (3,)), sec.array("axis", (3,)), sec.array("front", (3,)), **kw)
    return SpeckleCylinder(R_world_surface=pose[0], t_world_surface=pose[1], **kw)


def load_scene(path) -> Scene:
    """Read a scene TOML file (format in this module's docstring and docs/lab.md).

    Relative file names inside (screen images, speckle and displacement files) are resolved
    against the TOML file's folder. Errors name the file, the object and the field.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ValueError(f"scene file {str(path)!r} not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML: {exc}") from None
    unknown = sorted(set(data) - TOP_KEYS)
    if unknown:
        raise ValueError(f"{path}: unknown top-level key(s) {unknown}; known keys: {sorted(TOP_KEYS)} "
                         "(objects are arrays of tables: [[camera]], [[mirror]], [[screen]], [[plane]], [[cylinder]])")
    base = path.parent
    lists = {}
    for key, known, build in (("camera", CAMERA_KEYS, lambda s: _camera(s)), ("mirror", MIRROR_KEYS, lambda s: _mirror(s)),
                              ("screen", SCREEN_KEYS, lambda s: _screen(s, base)), ("plane", PLANE_KEYS, lambda s: _plane(s, base)),
                              ("cylinder", CYLINDER_KEYS, lambda s: _cylinder(s, base))):
        tables = data.get(key, [])
        if not isinstance(tables, list):
            raise ValueError(f"{path}: '{key}' must be an array of tables ([[{key}]]), got a {type(tables).__name__}")
        items = []
        for i, table in enumerate(tables):
            label = f"{key}[{i}]" + (f" ({table.get('name')!r})" if isinstance(table, dict) and table.get("name") else "")
            where = f"{path}: {label}"
            sec = _Section(table, where, known)
            try:
                items.append(build(sec))
            except ValueError as exc:
                msg = str(exc)
                raise ValueError(msg if msg.startswith(str(path)) else f"{where}: {msg}") from None
        lists[key] = items
    if not lists["camera"]:
        raise ValueError(f"{path}: the scene has no [[camera]]")
    try:
        return Scene(cameras=lists["camera"], mirrors=lists["mirror"], screens=lists["screen"], planes=lists["plane"],
                     cylinders=lists["cylinder"], background=data.get("background", 0.0),
                     max_bounces=data.get("max_bounces", 4))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


# ---------------------------------------------------------------------------------------------
# writing


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        if math.isnan(v):
            raise ValueError("NaN cannot be written to a scene file")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, np.ndarray):
        return _toml_value(v.tolist())
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise ValueError(f"cannot write {type(v).__name__} to TOML")


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name) or "obj"


def file_names(names, what: str, safe=_safe) -> list[str]:
    """The file-name forms (``safe(name)``) of object names, refused (``ValueError`` naming both) when two names
    give the same file name, letter case ignored (``cam/1`` and ``cam_1``; ``Cam`` and ``cam`` on a
    case-insensitive file system): one object's file would overwrite the other's."""
    out, seen = [], {}
    for name in names:
        tag = safe(name)
        other = seen.get(tag.casefold())
        if other is not None:
            raise ValueError(f"the {what} names {other!r} and {name!r} give the same file name {tag!r}; one file would "
                             f"overwrite the other: rename one of them")
        seen[tag.casefold()] = name
        out.append(tag)
    return out


def save_scene(scene: Scene, path) -> list[Path]:
    """Write ``scene`` as TOML at ``path``; screen images (.npy), speckle disks and displacement
    fields (.npz) go beside it as ``<stem>_<object>.*``. Returns the paths written.

    Poses are written as explicit ``R_*``/``t_*`` and ``K`` in full, so :func:`load_scene` gives
    back the same scene.
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a dic.lab.Scene, got {type(scene).__name__}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stem = path.stem
    written = []
    lines = ["# Specula virtual-lab scene (dic.lab.save_scene). Units: mm, px.",
             "# Poses: x_cam = R_cam_world x_world + t_cam_world; x_world = R_world_obj x_obj + t_world_obj.",
             f"background = {_toml_value(scene.background)}", f"max_bounces = {scene.max_bounces}", ""]

    def table(kind, entries):
        lines.append(f"[[{kind}]]")
        for k, v in entries.items():
            if v is not None:
                lines.append(f"{k} = {_toml_value(v)}")
        lines.append("")

    for cam in scene.cameras:
        table("camera", {"name": cam.name, "size": list(cam.size), "pixel_pitch_mm": cam.pixel_pitch_mm,
                         "focal_length_mm": cam.focal_length_mm, "f_number": cam.f_number,
                         "focus_distance_mm": cam.focus_distance_mm, "K": cam.camera.K, "dist": cam.camera.dist,
                         "R_cam_world": cam.R_cam_world, "t_cam_world": cam.t_cam_world, "bit_depth": cam.bit_depth,
                         "exposure_dn": cam.exposure_dn, "black_level_dn": cam.black_level_dn,
                         "read_noise_dn": cam.read_noise_dn, "electrons_per_dn": cam.electrons_per_dn})
    for m in scene.mirrors:
        table("mirror", {"name": m.name, "center": m.center, "normal": m.normal, "size": list(m.size), "up": m.up,
                         "reflectance": m.reflectance})
    screen_tags = file_names([s.name or f"screen{k}" for k, s in enumerate(scene.screens)], "screen")
    surfaces = [(kind, k, s) for kind, objs in (("plane", scene.planes), ("cylinder", scene.cylinders))
                for k, s in enumerate(objs)]
    file_names([s.name or f"{kind}{k}" for kind, k, s in surfaces], "surface")
    for k, s in enumerate(scene.screens):
        img_path = path.parent / f"{stem}_{screen_tags[k]}.npy"
        with atomic_output(img_path) as tmp:
            np.save(tmp, s.image.astype(np.float32))
        written.append(img_path)
        table("screen", {"name": s.name, "resolution": list(s.resolution), "pixel_pitch_mm": list(s.pixel_pitch_mm),
                         "image": img_path.name, "brightness": s.brightness, "black_level": s.black_level,
                         "nonuniformity": s.nonuniformity, "bezel_mm": s.bezel_mm,
                         "R_world_screen": s.R_world_screen, "t_world_screen": s.t_world_screen})
    for kind, objs in (("plane", scene.planes), ("cylinder", scene.cylinders)):
        for k, s in enumerate(objs):
            tag = _safe(s.name or f"{kind}{k}")
            entry = {"name": s.name}
            if kind == "plane":
                entry["size"] = list(s.size)
            else:
                entry.update(radius=s.radius, length=s.length, arc=list(s.arc))
            entry.update(albedo=list(s.albedo), R_world_surface=s.R_world_surface, t_world_surface=s.t_world_surface)
            if s.speckle is not None:
                p = path.parent / f"{stem}_{tag}_speckle.npz"
                with atomic_output(p) as tmp:
                    np.savez(tmp, centres=np.asarray(s.speckle.centres), radii=np.asarray(s.speckle.radii))
                written.append(p)
                entry["speckle_file"] = p.name
            if s.displacement is not None:
                p = path.parent / f"{stem}_{tag}_displacement.npz"
                d = s.displacement
                with atomic_output(p) as tmp:
                    np.savez(tmp, values=d.values, origin=np.asarray(d.origin), step=np.asarray(d.step))
                written.append(p)
                entry["displacement"] = p.name
            table(kind, entry)
    with atomic_output(path) as tmp:  # each file of the scene whole or not at all
        tmp.write_text("\n".join(lines))
    written.insert(0, path)
    return written


__all__ = ["load_scene", "save_scene"]
