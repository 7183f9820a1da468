"""Ray-cast rendering for the virtual lab: thin-lens cameras, planar mirrors, screens, speckled surfaces.

One thread renders one camera pixel (``launch_1d`` over pixels, chunked on the CPU):

1. **Sampling.** ``samples`` sub-samples per pixel, each a point in the pixel's area and a point
   on the lens aperture. Pixel area: the ``s × s`` grid of sub-cell centres when ``samples = s²``
   (else the first two dimensions of a 4-D Kronecker sequence), the same in every pixel, with the
   texture at each sub-sample area-filtered over the sub-cell's footprint (anti-aliased speckle
   coverage, box-filtered monitor pixels) — the midpoint rule of ``kernels/speckle.py``, exact for
   straight edges and shift-covariant. Aperture: the last two dimensions of the 4-D Kronecker
   sequence with increments ``1/g^k``, ``g^5 = g + 1`` (M. Roberts' R-sequence, "The unreasonable
   effectiveness of quasirandom sequences", 2018), shifted per pixel by a random offset drawn from
   ``(seed, pixel index)`` (Cranley–Patterson rotation; ``jitter=False`` uses the same pattern
   everywhere), mapped onto the disk with Shirley and Chiu's concentric map ("A low distortion map
   between disk and square", J. Graphics Tools 2(3), 1997, doi:10.1080/10867651.1997.10487479),
   which keeps the stratification. Deterministic for a given seed.
2. **Lens.** The sub-sample's sensor position ``(u, v)`` (distorted pixels) is undistorted with
   Newton's method on the OpenCV model (:mod:`kernels.distortion`: k1 k2 p1 p2 k3 k4 k5 k6, analytic Jacobian; 12 steps at
   the pixel centre, then 1 per sub-sample from there) into the ideal normalised ray ``(x, y, 1)``
   of the chief ray. A thin lens focused at distance ``s`` sends every ray from the aperture
   point ``A`` through the point ``s (x, y, 1)`` where the chief ray meets the plane of focus, so a
   point at depth ``z`` blurs into a disk of diameter ``f_x (f/N) |1/s − 1/z|`` px: physically correct
   defocus, zero at the focus plane.
3. **Scene.** Up to ``max_bounces`` reflections on planar rectangular mirrors (Householder
   ``d' = d − 2 (n·d) n``, scaled by the reflectance; the back face is black), then the nearest
   hit of a screen (the monitor's square pixels box-filtered over the footprint, optional emission
   non-uniformity and bezel) or a speckled surface (Boolean-model coverage at the hit's material
   coordinates: :func:`kernels.speckle.speckle_coverage_smooth`; Sur, Blaysat & Grédiac, J. Math.
   Imaging Vis. 60, 2018, doi:10.1007/s10851-018-0834-x). A surface with a displacement field
   ``u(X)`` is hit on its deformed geometry ``x(X) = S(X) + u(X)``: Newton's method solves
   ``x(X) = o + t d`` for ``(X, t)`` from the undeformed hit, so the speckle is evaluated exactly at
   the material point that moved there (no texture resampling).
   The filter footprint is the sub-cell's angular size times the path length, isotropic (it
   ignores the obliquity of the surface).
4. **Sensor.** The mean radiance ``L`` over the sub-samples becomes ``black + exposure · L`` grey
   levels, with optional Poisson shot noise (``gain`` e⁻/DN), Gaussian read noise and quantisation
   to ``2^bits − 1``.

Conventions: docs/conventions.md (pixel (0, 0) is the centre of the top-left pixel; camera x right,
y down, z forward; mm). The lab's scene model and frames are in ``dic/lab/scene.py``.
"""
from __future__ import annotations

import sys

import numpy as np
import warp as wp

from ._device import host_copy, resolve_device
from ._launch import launch_1d
from .checks import positive_int
from .distortion import distort_normalized, distortion_coefficients, undistort_step, vec8f
from .interp import keys_dweights, keys_weights
from .speckle import SpeckleModel, build_speckle_model, speckle_coverage_smooth

wp.set_module_options({"enable_backward": False})

KIND_NONE = wp.constant(0)
KIND_MIRROR = wp.constant(1)
KIND_SCREEN = wp.constant(2)
KIND_SURFACE = wp.constant(3)
SURFACE_PLANE = wp.constant(0)
SURFACE_CYLINDER = wp.constant(1)
T_MIN = wp.constant(1.0e-3)  # mm: hits closer than this along the ray are ignored (self-intersection)
BIG = wp.constant(1.0e30)
# generalised golden ratio for 4-D (root of x^5 = x + 1): R-sequence increments 1/g^k
_G4 = 1.1673039782614187
R4_ALPHA = wp.constant(wp.vec4(1.0 / _G4, 1.0 / _G4**2, 1.0 / _G4**3, 1.0 / _G4**4))


# ---------------------------------------------------------------------------------------------
# structs


@wp.struct
class LensCamera:
    """A thin-lens camera with OpenCV distortion (world frame, mm; px)."""

    R_world_cam: wp.mat33  # camera -> world rotation (R_cam_worldᵀ)
    center: wp.vec3  # optical centre in the world
    fx: float
    fy: float
    cx: float
    cy: float
    skew: float
    dist: vec8f  # OpenCV k1 k2 p1 p2 k3 k4 k5 k6 (kernels.distortion)
    aperture_radius: float  # mm (0: pinhole)
    focus_distance: float  # mm along the optical axis
    width: int
    height: int


@wp.struct
class MirrorGeom:
    center: wp.vec3
    ex: wp.vec3  # unit, along the width
    ey: wp.vec3  # unit, along the height
    n: wp.vec3  # unit, out of the reflecting face
    half_w: float
    half_h: float
    reflectance: float


@wp.struct
class ScreenGeom:
    origin: wp.vec3  # centre of screen pixel (0, 0)
    ex: wp.vec3  # unit, along columns
    ey: wp.vec3  # unit, along rows
    ez: wp.vec3  # unit, into the screen (emission towards -ez)
    pitch_x: float
    pitch_y: float
    width: int
    height: int
    offset: int  # first texel of this screen in SceneGeom.texels
    brightness: float
    black_level: float
    nonuniformity: float
    bezel: float  # mm


@wp.struct
class DispGrid:
    """Displacement samples ``values[j, i]`` at material ``origin + (i, j) * step`` (surface-frame components, mm)."""

    values: wp.array2d(dtype=wp.vec3)
    origin: wp.vec2
    inv_step: wp.vec2
    reach: float  # largest |u| over the samples (mm): bounds how far the deformed surface strays


@wp.struct
class SurfaceGeom:
    kind: int  # SURFACE_PLANE or SURFACE_CYLINDER
    R: wp.mat33  # R_world_surface
    t: wp.vec3  # t_world_surface
    size_x: float  # plane: material width (mm)
    size_y: float  # plane: material height; cylinder: length
    radius: float  # cylinder
    arc_min: float  # cylinder: S range (mm)
    arc_max: float
    albedo_bg: float
    albedo_sp: float
    speckle: int  # index into SceneGeom.speckles, -1: uniform albedo_bg
    disp: int  # index into SceneGeom.disps, -1: undeformed


@wp.struct
class SceneGeom:
    mirrors: wp.array(dtype=MirrorGeom)
    n_mirrors: int
    screens: wp.array(dtype=ScreenGeom)
    n_screens: int
    texels: wp.array(dtype=float)
    surfaces: wp.array(dtype=SurfaceGeom)
    n_surfaces: int
    speckles: wp.array(dtype=SpeckleModel)
    disps: wp.array(dtype=DispGrid)
    background: float
    max_bounces: int


@wp.struct
class SensorModel:
    exposure: float  # DN per unit radiance
    black: float  # DN
    gain: float  # e-/DN, 0: no shot noise
    read_noise: float  # DN
    max_dn: float  # 2^bits - 1
    noise: int  # 0/1
    quantize: int  # 0/1


# ---------------------------------------------------------------------------------------------
# lens


@wp.func
def pixel_to_distorted(cam: LensCamera, u: float, v: float) -> wp.vec2:
    yd = (v - cam.cy) / cam.fy
    return wp.vec2((u - cam.cx - cam.skew * yd) / cam.fx, yd)


@wp.func
def concentric_disk(a: float, b: float) -> wp.vec2:
    """Shirley–Chiu concentric map of [0, 1)² onto the unit disk.

    The angle within each octant is at most π/4, where Taylor polynomials of degree 8 (cos) and 9
    (sin) are accurate to 3e-8: no library calls in the per-sample loop.
    """
    sx = 2.0 * a - 1.0
    sy = 2.0 * b - 1.0
    if sx == 0.0 and sy == 0.0:
        return wp.vec2(0.0, 0.0)
    r = float(0.0)
    alpha = float(0.0)
    swap = bool(False)
    if wp.abs(sx) > wp.abs(sy):
        r = sx
        alpha = 0.25 * wp.pi * (sy / sx)
    else:
        r = sy
        alpha = 0.25 * wp.pi * (sx / sy)  # phi = pi/2 - alpha: cos and sin swap
        swap = True
    a2 = alpha * alpha
    c = 1.0 + a2 * (-0.5 + a2 * (1.0 / 24.0 + a2 * (-1.0 / 720.0 + a2 * (1.0 / 40320.0))))
    sn = alpha * (1.0 + a2 * (-1.0 / 6.0 + a2 * (1.0 / 120.0 + a2 * (-1.0 / 5040.0 + a2 * (1.0 / 362880.0)))))
    if swap:
        return wp.vec2(r * sn, r * c)
    return wp.vec2(r * c, r * sn)


# ---------------------------------------------------------------------------------------------
# intersections


@wp.func
def hit_plane(o: wp.vec3, d: wp.vec3, point: wp.vec3, n: wp.vec3) -> float:
    """Ray parameter of the hit with the plane through ``point`` with normal ``n`` (BIG if none ahead)."""
    den = wp.dot(d, n)
    if wp.abs(den) < 1.0e-12:
        return BIG
    t = wp.dot(point - o, n) / den
    if t < T_MIN:
        return BIG
    return t


@wp.func
def hit_mirror(m: MirrorGeom, o: wp.vec3, d: wp.vec3) -> float:
    t = hit_plane(o, d, m.center, m.n)
    if t < BIG:
        q = o + t * d - m.center
        if wp.abs(wp.dot(q, m.ex)) > m.half_w or wp.abs(wp.dot(q, m.ey)) > m.half_h:
            return BIG
    return t


@wp.func
def hit_screen(s: ScreenGeom, o: wp.vec3, d: wp.vec3) -> float:
    t = hit_plane(o, d, s.origin, s.ez)
    if t < BIG:
        q = o + t * d - s.origin
        col = wp.dot(q, s.ex) / s.pitch_x
        row = wp.dot(q, s.ey) / s.pitch_y
        bx = s.bezel / s.pitch_x
        by = s.bezel / s.pitch_y
        if col < -0.5 - bx or col > float(s.width) - 0.5 + bx or row < -0.5 - by or row > float(s.height) - 0.5 + by:
            return BIG
    return t


@wp.func
def box_weight(x: float, half: float) -> wp.vec2:
    """Nearest texel offset (-1 or +1) and its weight when the box [x - half, x + half] (texel units,
    texel centres at integers, half <= 1/2) straddles the boundary between the nearest texel and it."""
    c = wp.floor(x + 0.5)
    if half <= 0.0:
        return wp.vec2(1.0, 0.0)
    if x >= c:
        return wp.vec2(1.0, wp.clamp((x + half - (c + 0.5)) / (2.0 * half), 0.0, 1.0))
    return wp.vec2(-1.0, wp.clamp(((c - 0.5) - (x - half)) / (2.0 * half), 0.0, 1.0))


@wp.func
def screen_radiance(scene: SceneGeom, s: ScreenGeom, p: wp.vec3, d: wp.vec3, width: float) -> float:
    """Radiance of the screen at world point p: the displayed image box-filtered over a footprint of
    ``width`` mm (the sub-sample's size there, at most one texel), pixels emitting uniformly."""
    if wp.dot(d, s.ez) <= 0.0:
        return 0.0  # back of the monitor
    q = p - s.origin
    col = wp.dot(q, s.ex) / s.pitch_x
    row = wp.dot(q, s.ey) / s.pitch_y
    c = int(wp.floor(col + 0.5))
    r = int(wp.floor(row + 0.5))
    if c < 0 or c >= s.width or r < 0 or r >= s.height:
        return 0.0  # bezel
    bx = box_weight(col, wp.min(0.5 * width / s.pitch_x, 0.5))
    by = box_weight(row, wp.min(0.5 * width / s.pitch_y, 0.5))
    c1 = wp.clamp(c + int(bx[0]), 0, s.width - 1)
    r1 = wp.clamp(r + int(by[0]), 0, s.height - 1)
    base = s.offset
    v00 = scene.texels[base + r * s.width + c]
    v01 = scene.texels[base + r * s.width + c1]
    v10 = scene.texels[base + r1 * s.width + c]
    v11 = scene.texels[base + r1 * s.width + c1]
    value = (1.0 - by[1]) * ((1.0 - bx[1]) * v00 + bx[1] * v01) + by[1] * ((1.0 - bx[1]) * v10 + bx[1] * v11)
    hw = 0.5 * float(s.width - 1)
    hh = 0.5 * float(s.height - 1)
    rx = (col - hw) / wp.max(hw, 0.5)
    ry = (row - hh) / wp.max(hh, 0.5)
    falloff = 1.0 - s.nonuniformity * 0.5 * (rx * rx + ry * ry)
    return (s.black_level + (s.brightness - s.black_level) * value) * falloff


@wp.func
def disp_eval(g: DispGrid, X: float, Y: float) -> wp.mat33:
    """Columns: u, du/dX, du/dY (surface-frame components) by Keys bicubic interpolation (clamped taps)."""
    fx = (X - g.origin[0]) * g.inv_step[0]
    fy = (Y - g.origin[1]) * g.inv_step[1]
    ix = int(wp.floor(fx))
    iy = int(wp.floor(fy))
    wx = keys_weights(fx - float(ix))
    dwx = keys_dweights(fx - float(ix))
    wy = keys_weights(fy - float(iy))
    dwy = keys_dweights(fy - float(iy))
    ny = g.values.shape[0]
    nx = g.values.shape[1]
    u = wp.vec3(0.0)
    ux = wp.vec3(0.0)
    uy = wp.vec3(0.0)
    for j in range(4):
        row = wp.clamp(iy + j - 1, 0, ny - 1)
        r = wp.vec3(0.0)
        rx = wp.vec3(0.0)
        for i in range(4):
            val = g.values[row, wp.clamp(ix + i - 1, 0, nx - 1)]
            r += wx[i] * val
            rx += dwx[i] * val
        u += wy[j] * r
        ux += wy[j] * rx
        uy += dwy[j] * r
    return wp.matrix_from_cols(u, ux * g.inv_step[0], uy * g.inv_step[1])


@wp.func
def surface_local(s: SurfaceGeom, X: float, Y: float, u: wp.mat33) -> wp.mat33:
    """Columns: local position, d/dX, d/dY of material point (X, Y) displaced by u (cols u, u_X, u_Y)."""
    if s.kind == SURFACE_PLANE:
        return wp.matrix_from_cols(
            wp.vec3(X, Y, 0.0) + wp.vec3(u[0, 0], u[1, 0], u[2, 0]),
            wp.vec3(1.0 + u[0, 1], u[1, 1], u[2, 1]),
            wp.vec3(u[0, 2], 1.0 + u[1, 2], u[2, 2]),
        )
    rho = s.radius
    th = X / rho
    sn = wp.sin(th)
    cs = wp.cos(th)
    e_r = wp.vec3(sn, 0.0, -cs)
    e_t = wp.vec3(cs, 0.0, sn)
    e_y = wp.vec3(0.0, 1.0, 0.0)
    pos = rho * e_r + Y * e_y + u[0, 0] * e_t + u[1, 0] * e_y + u[2, 0] * e_r
    # d e_t / dS = -e_r / rho, d e_r / dS = e_t / rho
    dX = e_t + u[0, 1] * e_t + u[1, 1] * e_y + u[2, 1] * e_r + (u[2, 0] * e_t - u[0, 0] * e_r) / rho
    dY = e_y + u[0, 2] * e_t + u[1, 2] * e_y + u[2, 2] * e_r
    return wp.matrix_from_cols(pos, dX, dY)


@wp.func
def in_extent(s: SurfaceGeom, X: float, Y: float) -> bool:
    if s.kind == SURFACE_PLANE:
        return X >= 0.0 and X <= s.size_x and Y >= 0.0 and Y <= s.size_y
    return X >= s.arc_min and X <= s.arc_max and Y >= 0.0 and Y <= s.size_y


@wp.func
def deformed_hit(scene: SceneGeom, s: SurfaceGeom, ol: wp.vec3, dl: wp.vec3, guess: wp.vec3) -> wp.vec3:
    """Newton on x(X, Y) = ol + t dl (surface frame) from guess (t, X, Y); returns (t, X, Y), t = BIG on failure."""
    g = scene.disps[s.disp]
    t = guess[0]
    X = guess[1]
    Y = guess[2]
    for it in range(12):
        P = surface_local(s, X, Y, disp_eval(g, X, Y))
        F = wp.vec3(P[0, 0], P[1, 0], P[2, 0]) - ol - t * dl
        J = wp.matrix_from_cols(wp.vec3(P[0, 1], P[1, 1], P[2, 1]), wp.vec3(P[0, 2], P[1, 2], P[2, 2]), -dl)
        if wp.abs(wp.determinant(J)) < 1.0e-20:
            return wp.vec3(BIG, 0.0, 0.0)
        step = wp.inverse(J) * F
        X = X - step[0]
        Y = Y - step[1]
        t = t - step[2]
        if wp.abs(step[0]) + wp.abs(step[1]) < 1.0e-5 * (1.0 + wp.abs(X) + wp.abs(Y)):
            break  # material point converged to float32 resolution
    if t < T_MIN or not in_extent(s, X, Y):
        return wp.vec3(BIG, 0.0, 0.0)
    return wp.vec3(t, X, Y)


@wp.func
def material_of(s: SurfaceGeom, p: wp.vec3) -> wp.vec2:
    """Material coordinates of an undeformed local point."""
    if s.kind == SURFACE_PLANE:
        return wp.vec2(p[0], p[1])
    return wp.vec2(s.radius * wp.atan2(p[0], -p[2]), p[1])


@wp.func
def hit_surface(scene: SceneGeom, s: SurfaceGeom, o: wp.vec3, d: wp.vec3) -> wp.vec3:
    """Nearest hit (t, X, Y) of the ray with a (possibly deformed) surface; t = BIG if none."""
    Rt = wp.transpose(s.R)
    ol = Rt * (o - s.t)
    dl = Rt * d
    if s.kind == SURFACE_PLANE:
        if wp.abs(dl[2]) < 1.0e-12:
            return wp.vec3(BIG, 0.0, 0.0)
        t = -ol[2] / dl[2]
        m = material_of(s, ol + t * dl)
        if s.disp >= 0:
            # skip rays that pass farther from the extent than the displacement can reach
            reach = scene.disps[s.disp].reach * (1.0 + wp.sqrt(dl[0] * dl[0] + dl[1] * dl[1]) / wp.abs(dl[2]))
            if m[0] < -reach or m[0] > s.size_x + reach or m[1] < -reach or m[1] > s.size_y + reach:
                return wp.vec3(BIG, 0.0, 0.0)
            return deformed_hit(scene, s, ol, dl, wp.vec3(t, m[0], m[1]))
        if t < T_MIN or not in_extent(s, m[0], m[1]):
            return wp.vec3(BIG, 0.0, 0.0)
        return wp.vec3(t, m[0], m[1])
    # cylinder x^2 + z^2 = rho^2 (local), two roots
    a = dl[0] * dl[0] + dl[2] * dl[2]
    b = 2.0 * (ol[0] * dl[0] + ol[2] * dl[2])
    c = ol[0] * ol[0] + ol[2] * ol[2] - s.radius * s.radius
    disc = b * b - 4.0 * a * c
    if a < 1.0e-12 or disc < 0.0:
        return wp.vec3(BIG, 0.0, 0.0)
    sq = wp.sqrt(disc)
    if b < 0.0:
        sq = -sq
    q = -0.5 * (b + sq)  # numerically stable roots t0 = q / a, t1 = c / q
    if q == 0.0:
        return wp.vec3(BIG, 0.0, 0.0)
    t0 = q / a
    t1 = c / q
    if t0 > t1:
        tmp = t0
        t0 = t1
        t1 = tmp
    for k in range(2):
        t = t0
        if k == 1:
            t = t1
        m = material_of(s, ol + t * dl)
        if s.disp >= 0:
            h = deformed_hit(scene, s, ol, dl, wp.vec3(t, m[0], m[1]))
            if h[0] < BIG:
                return h
        elif t >= T_MIN and in_extent(s, m[0], m[1]):
            return wp.vec3(t, m[0], m[1])
    return wp.vec3(BIG, 0.0, 0.0)


@wp.func
def surface_radiance(scene: SceneGeom, s: SurfaceGeom, X: float, Y: float, width: float) -> float:
    """Albedo at material point (X, Y): speckle coverage anti-aliased over a footprint of ``width`` mm."""
    if s.speckle < 0:
        return s.albedo_bg
    cov = speckle_coverage_smooth(scene.speckles[s.speckle], wp.vec2(X, Y), width)
    return s.albedo_bg + (s.albedo_sp - s.albedo_bg) * cov


@wp.func
def trace(scene: SceneGeom, o_in: wp.vec3, d_in: wp.vec3, footprint: float) -> float:
    """Radiance arriving along the ray (world frame) after up to max_bounces mirror reflections.

    ``footprint`` (rad) is the angular size of one sub-sample: textures are area-filtered over
    ``path length x footprint`` mm where the ray lands (planar mirrors keep the footprint).
    """
    o = o_in
    d = d_in
    throughput = float(1.0)
    travelled = float(0.0)
    last_mirror = int(-1)
    for bounce in range(scene.max_bounces + 1):
        best_t = float(BIG)
        kind = int(KIND_NONE)
        idx = int(-1)
        mat = wp.vec2(0.0, 0.0)
        for k in range(scene.n_mirrors):
            if k != last_mirror:
                t = hit_mirror(scene.mirrors[k], o, d)
                if t < best_t:
                    best_t = t
                    kind = KIND_MIRROR
                    idx = k
        for k in range(scene.n_screens):
            t = hit_screen(scene.screens[k], o, d)
            if t < best_t:
                best_t = t
                kind = KIND_SCREEN
                idx = k
        for k in range(scene.n_surfaces):
            h = hit_surface(scene, scene.surfaces[k], o, d)
            if h[0] < best_t:
                best_t = h[0]
                kind = KIND_SURFACE
                idx = k
                mat = wp.vec2(h[1], h[2])
        if kind == KIND_NONE:
            return throughput * scene.background
        if kind == KIND_SCREEN:
            width = (travelled + best_t) * footprint
            return throughput * screen_radiance(scene, scene.screens[idx], o + best_t * d, d, width)
        if kind == KIND_SURFACE:
            width = (travelled + best_t) * footprint
            return throughput * surface_radiance(scene, scene.surfaces[idx], mat[0], mat[1], width)
        m = scene.mirrors[idx]
        den = wp.dot(d, m.n)
        if den >= 0.0:
            return 0.0  # back of the mirror
        o = o + best_t * d
        d = d - (2.0 * den) * m.n
        throughput = throughput * m.reflectance
        travelled = travelled + best_t
        last_mirror = idx
    return 0.0


# ---------------------------------------------------------------------------------------------
# kernel


@wp.func
def camera_ray_radiance(cam: LensCamera, scene: SceneGeom, u: float, v: float, centre: wp.vec2, lens: wp.vec2,
                        footprint: float) -> float:
    """Radiance of the ray from sensor position (u, v) px through aperture point ``lens`` (unit disk)."""
    target = pixel_to_distorted(cam, u, v)
    # from the pixel centre's solution, shifted by the sub-pixel offset: one Newton step is exact to
    # float32 (the start is off by ~|J - I| * 0.5 px, the step leaves the square of that)
    p = undistort_step(centre + (target - distort_normalized(centre, cam.dist)), target, cam.dist)
    s = cam.focus_distance
    a = cam.aperture_radius * lens
    o_cam = wp.vec3(a[0], a[1], 0.0)
    d_cam = wp.normalize(wp.vec3(p[0] * s, p[1] * s, s) - o_cam)
    return trace(scene, cam.center + cam.R_world_cam * o_cam, cam.R_world_cam * d_cam, footprint)


@wp.func
def sensor_response(sensor: SensorModel, radiance: float, state: wp.uint32) -> float:
    rng = state
    signal = sensor.exposure * radiance
    if sensor.noise != 0:
        if sensor.gain > 0.0 and signal > 0.0:
            signal = float(wp.poisson(rng, signal * sensor.gain)) / sensor.gain
        signal = signal + sensor.read_noise * wp.randn(rng)
    value = sensor.black + signal
    if sensor.quantize != 0:
        value = wp.clamp(wp.floor(value + 0.5), 0.0, sensor.max_dn)
    return value


@wp.kernel
def _render_kernel(
    cam: LensCamera,
    scene: SceneGeom,
    sensor: SensorModel,
    samples: int,
    seed: int,
    jitter: int,
    window: wp.vec4i,
    window_only: int,
    out: wp.array(dtype=float),
    offset: int,
):
    # window = (x0, y0, width, height); width 0 = no window. window_only = 1: the launch runs over
    # the window's pixels with ``samples``; 0: over the whole image, skipping the window's pixels
    # when there is one and rendering the others with a single sample (they see uniform background).
    j = wp.tid() + offset
    row = j / cam.width
    col = j - row * cam.width
    n_samples = samples
    if window_only == 1:
        row = window[1] + j / window[2]
        col = window[0] + j - (j / window[2]) * window[2]
    elif window[2] > 0:
        if col >= window[0] and col < window[0] + window[2] and row >= window[1] and row < window[1] + window[3]:
            return
        n_samples = 1
    i = row * cam.width + col
    state = wp.rand_init(seed, i)
    # aperture pattern: shifted per pixel (jitter) or the same in every pixel
    shift = wp.vec2(wp.randf(state), wp.randf(state))
    if jitter == 0:
        shift = wp.vec2(0.5, 0.5)
    # pixel-area pattern, the same in every pixel: an s x s grid of sub-cell centres when samples = s^2
    grid = int(wp.sqrt(float(n_samples)) + 0.5)
    if grid * grid != n_samples:
        grid = 0
    cell = 1.0 / wp.sqrt(float(n_samples))
    # ideal normalised coordinates of the pixel centre (Newton from the distorted position)
    target = pixel_to_distorted(cam, float(col), float(row))
    centre = target
    for it in range(12):
        centre = undistort_step(centre, target, cam.dist)
    # angular size of one sub-cell: the texture filter width per mm of path
    footprint = cell / wp.sqrt(cam.fx * cam.fy)
    acc = float(0.0)
    for k in range(n_samples):
        q = float(k + 1) * R4_ALPHA
        px = q[0] + 0.5 - wp.floor(q[0] + 0.5)
        py = q[1] + 0.5 - wp.floor(q[1] + 0.5)
        if grid > 0:
            px = (float(k % grid) + 0.5) * cell
            py = (float(k / grid) + 0.5) * cell
        ax = q[2] + shift[0] - wp.floor(q[2] + shift[0])
        ay = q[3] + shift[1] - wp.floor(q[3] + shift[1])
        acc += camera_ray_radiance(cam, scene, float(col) + px - 0.5, float(row) + py - 0.5, centre,
                                   concentric_disk(ax, ay), footprint)
    out[i] = sensor_response(sensor, acc / float(n_samples), state)


# ---------------------------------------------------------------------------------------------
# host side: building the structs from plain arrays


def _v3(a) -> wp.vec3:
    a = np.asarray(a, dtype=np.float64).reshape(3)
    return wp.vec3(float(a[0]), float(a[1]), float(a[2]))


def _m33(a) -> wp.mat33:
    a = np.asarray(a, dtype=np.float64).reshape(3, 3)
    return wp.mat33(*[float(x) for x in a.ravel()])


def make_camera(K, dist, size, R_cam_world, t_cam_world, aperture_diameter_mm: float, focus_distance_mm: float) -> LensCamera:
    """Build a :class:`LensCamera` (``K`` 3×3 px, ``dist`` OpenCV coefficients (≤ 8), ``size = (W, H)``,
    pose ``x_cam = R_cam_world x_world + t_cam_world`` in mm)."""
    K = np.asarray(K, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64).ravel()
    if K.shape != (3, 3) or dist.size > 8 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"make_camera: K must be 3x3 with positive focal lengths and dist <= 8 coefficients, got {K.shape}, {dist.size}")
    dist8 = distortion_coefficients(dist, "make_camera: dist", sizes=tuple(range(9)))
    R = np.asarray(R_cam_world, dtype=np.float64)
    t = np.asarray(t_cam_world, dtype=np.float64).reshape(3)
    W, H = (int(s) for s in size)
    if W < 1 or H < 1:
        raise ValueError(f"make_camera: size must be positive (W, H), got {size}")
    if not (aperture_diameter_mm >= 0 and focus_distance_mm > 0):
        raise ValueError(f"make_camera: aperture >= 0 and focus distance > 0 expected, got {aperture_diameter_mm}, {focus_distance_mm}")
    cam = LensCamera()
    cam.R_world_cam = _m33(R.T)
    cam.center = _v3(-R.T @ t)
    cam.fx, cam.fy, cam.cx, cam.cy, cam.skew = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), float(K[0, 1])
    cam.dist = vec8f(*(float(c) for c in dist8))
    cam.aperture_radius = 0.5 * float(aperture_diameter_mm)
    cam.focus_distance = float(focus_distance_mm)
    cam.width, cam.height = W, H
    return cam


def make_mirror(center, ex, ey, normal, size, reflectance: float) -> MirrorGeom:
    m = MirrorGeom()
    m.center, m.ex, m.ey, m.n = _v3(center), _v3(ex), _v3(ey), _v3(normal)
    m.half_w, m.half_h = 0.5 * float(size[0]), 0.5 * float(size[1])
    m.reflectance = float(reflectance)
    return m


def make_screen(R_world_screen, t_world_screen, resolution, pitch, offset: int, brightness: float,
                black_level: float, nonuniformity: float, bezel_mm: float) -> ScreenGeom:
    R = np.asarray(R_world_screen, dtype=np.float64)
    s = ScreenGeom()
    s.origin = _v3(t_world_screen)
    s.ex, s.ey, s.ez = _v3(R[:, 0]), _v3(R[:, 1]), _v3(R[:, 2])
    s.pitch_x, s.pitch_y = float(pitch[0]), float(pitch[1])
    s.width, s.height = int(resolution[0]), int(resolution[1])
    s.offset = int(offset)
    s.brightness, s.black_level, s.nonuniformity, s.bezel = float(brightness), float(black_level), float(nonuniformity), float(bezel_mm)
    return s


def make_surface(kind: int, R_world_surface, t_world_surface, *, size_x=0.0, size_y=0.0, radius=0.0,
                 arc=(0.0, 0.0), albedo=(1.0, 0.0), speckle: int = -1, disp: int = -1) -> SurfaceGeom:
    s = SurfaceGeom()
    s.kind = int(kind)
    s.R, s.t = _m33(R_world_surface), _v3(t_world_surface)
    s.size_x, s.size_y, s.radius = float(size_x), float(size_y), float(radius)
    s.arc_min, s.arc_max = float(arc[0]), float(arc[1])
    s.albedo_bg, s.albedo_sp = float(albedo[0]), float(albedo[1])
    s.speckle, s.disp = int(speckle), int(disp)
    return s


def make_disp_grid(values, origin, step, device) -> DispGrid:
    v = np.ascontiguousarray(values, dtype=np.float32)
    if v.ndim != 3 or v.shape[2] != 3:
        raise ValueError(f"displacement grid must be (ny, nx, 3), got {v.shape}")
    g = DispGrid()
    g.values = wp.array(v, dtype=wp.vec3, device=device)
    g.origin = wp.vec2(float(origin[0]), float(origin[1]))
    g.inv_step = wp.vec2(1.0 / float(step[0]), 1.0 / float(step[1]))
    g.reach = float(np.linalg.norm(np.asarray(values, dtype=np.float64), axis=-1).max()) * 1.01 + 1e-3
    return g


def make_scene(*, mirrors=(), screens=(), texels=None, surfaces=(), speckles=(), disps=(),
               background: float = 0.0, max_bounces: int = 4, device=None) -> SceneGeom:
    """Assemble a :class:`SceneGeom` on ``device`` from lists of built structs.

    ``texels`` is the float32 concatenation of all screens' images (row-major, in the order of the
    screens' ``offset``); ``speckles`` are :class:`kernels.speckle.SpeckleModel` s (mm) on the same
    device; ``disps`` :class:`DispGrid` s. Empty lists get a dummy element (never indexed).
    """
    device = resolve_device(device)
    sc = SceneGeom()
    sc.mirrors = wp.array(list(mirrors) or [MirrorGeom()], dtype=MirrorGeom, device=device)
    sc.n_mirrors = len(mirrors)
    sc.screens = wp.array(list(screens) or [ScreenGeom()], dtype=ScreenGeom, device=device)
    sc.n_screens = len(screens)
    tex = np.zeros(1, np.float32) if texels is None or len(texels) == 0 else np.ascontiguousarray(texels, dtype=np.float32)
    sc.texels = wp.array(tex, dtype=float, device=device)
    sc.surfaces = wp.array(list(surfaces) or [SurfaceGeom()], dtype=SurfaceGeom, device=device)
    sc.n_surfaces = len(surfaces)
    if not speckles:
        speckles = [build_speckle_model(np.zeros((0, 2)), np.zeros(0), device=device)]
    sc.speckles = wp.array(list(speckles), dtype=SpeckleModel, device=device)
    if not disps:
        disps = [make_disp_grid(np.zeros((2, 2, 3)), (0.0, 0.0), (1.0, 1.0), device)]
    sc.disps = wp.array(list(disps), dtype=DispGrid, device=device)
    sc.background = float(background)
    sc.max_bounces = int(max_bounces)
    return sc


def make_sensor(*, exposure: float, black: float = 0.0, gain: float = 0.0, read_noise: float = 0.0,
                bit_depth: int = 8, noise: bool = True, quantize: bool = True) -> SensorModel:
    s = SensorModel()
    s.exposure, s.black, s.gain, s.read_noise = float(exposure), float(black), float(gain), float(read_noise)
    s.max_dn = float(2 ** int(bit_depth) - 1)
    s.noise, s.quantize = int(bool(noise)), int(bool(quantize))
    return s


# ---------------------------------------------------------------------------------------------
# launcher

_LOADED: set[str] = set()


def render_image(camera: LensCamera, scene: SceneGeom, sensor: SensorModel, *, samples: int = 16, seed: int = 0,
                 jitter: bool = True, window=None, device=None, out=None) -> np.ndarray:
    """Render one camera image: float32 (H, W) grey levels (integers when the sensor quantises).

    Parameters
    ----------
    camera, scene, sensor : structs from :func:`make_camera`, :func:`make_scene`, :func:`make_sensor`
        (the scene's arrays must live on ``device``).
    samples : int
        Sub-samples per pixel (pixel area × aperture), ≥ 1.
    seed : int
        Seed of the per-pixel sample shifts and of the noise; same seed, same image.
    jitter : bool
        ``True``: the aperture pattern is shifted randomly in every pixel (defocus blur is
        unbiased; its quadrature error becomes a small per-pixel noise). ``False``: the same
        aperture pattern in every pixel. The pixel-area pattern is the same in every pixel anyway.
    window : (x0, y0, x1, y1) ints, optional
        Pixel columns ``x0 <= col < x1`` and rows ``y0 <= row < y1`` rendered with ``samples``;
        every other pixel gets a single sample. Exact (the same image as without a window) when
        the pixels outside see uniform radiance everywhere on the lens (background only, blur
        included); the caller chooses the window so (e.g. :func:`dic.lab.object_window`). Small
        objects in a large frame then cost a fraction of a full render. Clipped to the image.
    out : wp.array, optional
        float32 array of ``W·H`` elements on ``device`` to render into.
    """
    device = resolve_device(device)
    if not isinstance(camera, LensCamera.cls) or not isinstance(scene, SceneGeom.cls) or not isinstance(sensor, SensorModel.cls):
        raise ValueError("render_image expects LensCamera, SceneGeom and SensorModel structs (see make_camera, make_scene, make_sensor)")
    samples = positive_int(samples, "samples", integral_float=True)
    if int(seed) != seed or not 0 <= int(seed) < 2**31:
        raise ValueError(f"seed must be an integer in [0, 2**31), got {seed!r}")
    if str(scene.mirrors.device) != device:
        raise ValueError(f"scene arrays live on {scene.mirrors.device}, but device={device!r}; build the scene on the render device")
    n = camera.width * camera.height
    win = _pixel_window(window, camera.width, camera.height)
    if device not in _LOADED:  # compile once before the CPU chunks start (they would all compile it)
        wp.load_module(sys.modules[__name__], device=device)
        _LOADED.add(device)
    if out is None:
        out = wp.empty(n, dtype=float, device=device)
    elif out.shape != (n,) or out.dtype != wp.float32 or str(out.device) != device:
        raise ValueError(f"out must be a float32 warp array of {n} elements on {device}, got {out.shape} {out.dtype} on {out.device}")
    args = [camera, scene, sensor, int(samples), int(seed), int(bool(jitter)), wp.vec4i(*win), 0, out, 0]
    launch_1d(_render_kernel, n, args, device, 9, min_chunk=1024)
    if win[2] > 0 and win[2] * win[3] < n:
        args[7] = 1  # then the window alone, with every sample: a launch of its own balances the CPU chunks
        launch_1d(_render_kernel, win[2] * win[3], args, device, 9, min_chunk=256)
    return host_copy(out).reshape(camera.height, camera.width)


def _pixel_window(window, width: int, height: int) -> tuple[int, int, int, int]:
    """(x0, y0, w, h) of ``window`` = (x0, y0, x1, y1) clipped to the image; (0, 0, 0, 0) for None.

    A window that covers the whole image is returned as "no window" (every pixel gets every sample)."""
    if window is None:
        return (0, 0, 0, 0)
    try:
        x0, y0, x1, y1 = (float(v) for v in window)
    except (TypeError, ValueError):
        raise ValueError(f"window must be (x0, y0, x1, y1) pixel bounds, got {window!r}") from None
    if not all(np.isfinite([x0, y0, x1, y1])):
        raise ValueError(f"window bounds must be finite, got {window!r}")
    x0, y0 = max(0, int(np.floor(x0))), max(0, int(np.floor(y0)))
    x1, y1 = min(width, int(np.ceil(x1))), min(height, int(np.ceil(y1)))
    if x1 <= x0 or y1 <= y0:
        # nothing of interest in view: the whole image sees background, one sample per pixel is exact
        return (0, 0, 1, 1) if (width, height) != (1, 1) else (0, 0, 0, 0)
    if (x0, y0, x1, y1) == (0, 0, width, height):
        return (0, 0, 0, 0)
    return (x0, y0, x1 - x0, y1 - y0)


__all__ = [
    "LensCamera", "MirrorGeom", "ScreenGeom", "SurfaceGeom", "DispGrid", "SceneGeom", "SensorModel",
    "make_camera", "make_mirror", "make_screen", "make_surface", "make_disp_grid", "make_scene", "make_sensor",
    "render_image", "SURFACE_PLANE", "SURFACE_CYLINDER",
]

