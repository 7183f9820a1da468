"""Rendering and exact projection for the virtual lab.

:func:`render` turns a :class:`~dic.lab.scene.Scene` into the image one camera records (the ray
caster is ``kernels/render.py``); :func:`project` gives the exact (noise-free, float64) pixel
positions of 3-D points, seen directly or through a mirror, for ground truth.
"""
from __future__ import annotations

from collections import OrderedDict

import numpy as np

from kernels import render as _k
from kernels._device import resolve_device
from kernels.checks import as_points
from kernels.speckle import build_speckle_model

from .scene import Scene

# speckle models are binned once per (pattern, device); a small cache keeps repeated renders fast
_SPECKLE_CACHE: "OrderedDict[tuple[int, str], tuple[object, object]]" = OrderedDict()
_CACHE_SIZE = 16


def _speckle_model(speckle, device):
    if hasattr(speckle, "device_model"):  # dic.synth.BooleanSpeckle caches its own
        return speckle.device_model(device)
    key = (id(speckle), device)
    hit = _SPECKLE_CACHE.get(key)
    if hit is not None and hit[0] is speckle:
        _SPECKLE_CACHE.move_to_end(key)
        return hit[1]
    model = build_speckle_model(np.asarray(speckle.centres, dtype=np.float64), np.asarray(speckle.radii, dtype=np.float64), device=device)
    _SPECKLE_CACHE[key] = (speckle, model)
    while len(_SPECKLE_CACHE) > _CACHE_SIZE:
        _SPECKLE_CACHE.popitem(last=False)
    return model


def build_scene_geometry(scene: Scene, device=None):
    """Device form of ``scene``: ``(SceneGeom, keep_alive)``; keep ``keep_alive`` while rendering."""
    device = resolve_device(device)
    keep = []
    mirrors = []
    for m in scene.mirrors:
        R = m.R_world_mirror
        mirrors.append(_k.make_mirror(m.center, R[:, 0], R[:, 1], m.normal, m.size, m.reflectance))
    screens, texels, offset = [], [], 0
    for s in scene.screens:
        screens.append(_k.make_screen(s.R_world_screen, s.t_world_screen, s.resolution, s.pixel_pitch_mm, offset,
                                      s.brightness, s.black_level, s.nonuniformity, s.bezel_mm))
        texels.append(np.ascontiguousarray(s.image, dtype=np.float32).ravel())
        offset += s.image.size
    speckles, speckle_index = [], {}
    disps = []
    surfaces = []

    def tex(obj):
        spk = obj.speckle
        if spk is None:
            return -1
        if id(spk) not in speckle_index:
            speckle_index[id(spk)] = len(speckles)
            speckles.append(_speckle_model(spk, device))
        return speckle_index[id(spk)]

    def disp(obj):
        if obj.displacement is None:
            return -1
        d = obj.displacement
        disps.append(_k.make_disp_grid(d.values, d.origin, d.step, device))
        return len(disps) - 1

    for p in scene.planes:
        surfaces.append(_k.make_surface(_k.SURFACE_PLANE, p.R_world_surface, p.t_world_surface, size_x=p.size[0],
                                        size_y=p.size[1], albedo=p.albedo, speckle=tex(p), disp=disp(p)))
    for c in scene.cylinders:
        surfaces.append(_k.make_surface(_k.SURFACE_CYLINDER, c.R_world_surface, c.t_world_surface, size_y=c.length,
                                        radius=c.radius, arc=c.arc, albedo=c.albedo, speckle=tex(c), disp=disp(c)))
    keep.extend(speckles)
    keep.extend(disps)
    geom = _k.make_scene(mirrors=mirrors, screens=screens, texels=np.concatenate(texels) if texels else None,
                         surfaces=surfaces, speckles=speckles, disps=disps, background=scene.background,
                         max_bounces=scene.max_bounces, device=device)
    keep.append(geom)
    return geom, keep


def render(scene: Scene, camera=0, *, samples: int = 16, seed: int = 0, noise: bool = True, quantize: bool = True,
           jitter: bool = True, window=None, device=None) -> np.ndarray:
    """Render the image that ``camera`` (index, name or LabCamera of ``scene``) records.

    Parameters
    ----------
    samples : int
        Sub-samples per pixel, spread over the pixel area and the lens aperture. A perfect square
        ``s²`` puts them on an ``s × s`` grid of anti-aliased sub-cells (exact for straight edges;
        16 gives ~0.6 DN rms on 2 px speckle); defocused scenes want more (the aperture is sampled
        by the same number of points).
    seed : int
        Seed of the sample pattern and of the noise: the same seed gives the same image.
    noise : bool
        Apply the camera's shot and read noise (``electrons_per_dn``, ``read_noise_dn``).
    quantize : bool
        Round to integers in ``[0, 2^bit_depth − 1]`` and return uint8 (bit_depth ≤ 8) or uint16;
        ``False`` returns float32 grey levels.
    jitter : bool
        ``True`` (default): the aperture points are shifted randomly in every pixel, so the
        defocus blur is unbiased and its sampling error is per-pixel noise. ``False``: the same
        aperture points in every pixel — with strong defocus the blur disk is then a fixed set of
        ``samples`` points, which shows as overlapping copies. In-focus content does not depend
        on it (the pixel-area pattern is always the same in every pixel).
    window : (x0, y0, x1, y1), optional
        Pixel bounds (columns ``x0..x1``, rows ``y0..y1``, exclusive ends) that get ``samples``
        sub-samples; all other pixels get one. The image is the same as without a window as long
        as the pixels outside see only uniform background (their radiance does not depend on
        where the ray crosses the pixel or the lens): take it from :func:`window_around`, which
        adds the defocus blur. A monitor filling 2 % of the frame then renders more than 10x faster
        at 64 samples (docs/lab.md).
    device : str, optional
        Warp device (``None``: CUDA when present, else CPU).

    Returns
    -------
    ndarray (H, W)
        The image, indexed ``[row, col]``.
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a dic.lab.Scene, got {type(scene).__name__}")
    cam = scene.camera(camera)
    device = resolve_device(device)
    geom, keep = build_scene_geometry(scene, device)
    lens = _k.make_camera(cam.camera.K, cam.camera.dist, cam.size, cam.R_cam_world, cam.t_cam_world,
                          cam.aperture_diameter_mm, cam.focus_distance_mm)
    sensor = _k.make_sensor(exposure=cam.exposure_dn, black=cam.black_level_dn, gain=cam.electrons_per_dn,
                            read_noise=cam.read_noise_dn, bit_depth=cam.bit_depth, noise=noise, quantize=quantize)
    img = _k.render_image(lens, geom, sensor, samples=samples, seed=seed, jitter=jitter, window=window, device=device)
    del keep
    if not quantize:
        return img
    return img.astype(np.uint8 if cam.bit_depth <= 8 else np.uint16)


def window_around(scene: Scene, camera, points_world, *, margin_px: float = 4.0) -> tuple[int, int, int, int]:
    """Pixel window ``(x0, y0, x1, y1)`` that holds the direct image of a convex object, blur included.

    ``points_world`` (N, 3) mm are the object's outline (e.g. a monitor's four corners with
    its bezel, :meth:`Screen.outer_corners`); the window is the bounding box of their projections, grown at each
    point by half its defocus blur diameter (:meth:`LabCamera.blur_diameter_px`) plus
    ``margin_px`` (pixel-area filtering, distortion between the corners). Use it as
    ``render(..., window=...)`` for a scene in which nothing else than that object is in view;
    objects seen through mirrors are not covered. Raises ``ValueError`` when a point lies
    behind the camera (the image of the object is then unbounded).
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a dic.lab.Scene, got {type(scene).__name__}")
    if not (np.isfinite(margin_px) and margin_px >= 0):
        raise ValueError(f"margin_px must be a finite number >= 0, got {margin_px!r}")
    cam = scene.camera(camera)
    pts = np.asarray(points_world)
    if pts.shape == (3,):
        pts = pts[None]
    pts = as_points(pts, "points_world", ncols=3)
    # the segments between all pairs of points span the outline: their images bound the object's
    # image even where lens distortion bends its straight edges outwards
    t = np.linspace(0.0, 1.0, 33)[:, None]
    pairs = [pts[a] + t * (pts[b] - pts[a]) for a in range(len(pts)) for b in range(a + 1, len(pts))]
    pts = np.vstack([pts, *pairs])
    depth = cam.world_to_camera(pts)[:, 2]
    if not np.all(depth > 0):
        raise ValueError("window_around: a point lies behind the camera; its image has no bounded window")
    uv = project(scene, cam, pts)
    reach = 0.5 * cam.blur_diameter_px(depth) + float(margin_px)
    lo = np.min(uv - reach[:, None], axis=0)
    hi = np.max(uv + reach[:, None], axis=0)
    return (int(np.floor(lo[0])), int(np.floor(lo[1])), int(np.ceil(hi[0])) + 1, int(np.ceil(hi[1])) + 1)


def screens_window(scene: Scene, camera, *, margin_px: float = 4.0):
    """Window around every screen of a mirrorless scene (bezels and blur included), or None.

    For ``render(..., window=...)`` when the screens are all there is to see besides the uniform
    background (no speckled surfaces): None when the scene has mirrors or surfaces (what they show
    is not bounded by the screens' direct images) or a screen reaches behind the camera."""
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a dic.lab.Scene, got {type(scene).__name__}")
    if scene.mirrors or scene.planes or scene.cylinders or not scene.screens:
        return None
    try:
        return window_around(scene, camera, np.vstack([s.outer_corners() for s in scene.screens]), margin_px=margin_px)
    except ValueError:
        return None


def project(scene: Scene, camera, points_world, *, mirror=None, return_mask: bool = False):
    """Exact pixel positions (N, 2) of world points (N, 3) mm in ``camera``, directly or via a mirror.

    With ``mirror=k`` (index or name) the points are reflected about mirror ``k``'s plane
    (Householder, ``x' = x − 2 (n·x + d) n``) and the virtual points projected: the image of each
    point as seen in that mirror. Projection is float64 with the camera's full distortion model
    (identical to ``cv2.projectPoints``).

    A point **has no image** when it lies behind the camera, or, through a mirror, when the camera
    or the point is behind the mirror's reflecting face, or the chief ray (from the lens centre to
    the virtual point) crosses the mirror plane outside the mirror's rectangle. Such rows are NaN.
    With ``return_mask=True`` the call returns ``(uv, visible)`` instead: ``uv`` holds the
    projection of every point in front of the camera (as if the mirror were infinite; NaN only
    behind the camera) and ``visible`` (N,) bool says which have an image. Occlusion by other
    objects and the image borders are not checked (``uv`` may fall outside the image).
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a dic.lab.Scene, got {type(scene).__name__}")
    cam = scene.camera(camera)
    pts = np.asarray(points_world)
    if pts.shape == (3,):
        pts = pts[None]
    pts = as_points(pts, "points_world", ncols=3, allow_empty=True)
    visible = np.ones(len(pts), dtype=bool)
    if mirror is not None:
        m = _mirror(scene, mirror)
        n, d = m.plane
        C = cam.center_world
        side_cam = n @ C + d
        side_pts = pts @ n + d
        virtual = m.reflect(pts)
        visible &= (side_cam > 0) & (side_pts > 0)
        # chief ray C -> virtual point meets the plane at C + s (P' - C), s = side_cam / (side_cam - n·P' - d)
        den = side_cam - (virtual @ n + d)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(den > 0, side_cam / den, np.nan)
        hit = C + s[:, None] * (virtual - C)
        R = m.R_world_mirror
        local = (hit - m.center) @ R
        inside = (np.abs(local[:, 0]) <= m.size[0] / 2) & (np.abs(local[:, 1]) <= m.size[1] / 2)
        visible &= inside & np.isfinite(s)
        pts = virtual
    p_cam = cam.world_to_camera(pts)
    front = p_cam[:, 2] > 0
    visible &= front
    uv = np.full((len(pts), 2), np.nan)
    if np.any(front):
        uv[front] = cam.camera.project(p_cam[front])
    if return_mask:
        return uv, visible
    uv[~visible] = np.nan
    return uv


def _mirror(scene: Scene, key):
    if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
        if not 0 <= key < len(scene.mirrors):
            raise ValueError(f"mirror index {key} out of range; the scene has {len(scene.mirrors)} mirror(s)")
        return scene.mirrors[key]
    for m in scene.mirrors:
        if m.name == key:
            return m
    raise ValueError(f"no mirror named {key!r}; mirrors: {[m.name or i for i, m in enumerate(scene.mirrors)]}")


__all__ = ["render", "project", "build_scene_geometry"]
