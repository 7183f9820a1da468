"""Virtual-lab renderer (kernels/render.py through dic.lab.render) against independent references.

References: cv2.projectPoints for where things land, an explicit Householder reflection for mirror
images, the thin-lens circle of confusion (A f |z - s| / (z (s - f))) with the analytic edge-spread
function of a uniform blur disk for defocus, and rigidly moved copies of surfaces for displacement
fields.
"""
import cv2
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from calibration.camera import Camera
from dic.lab.camera import LabCamera
from dic.lab.rendering import project, render
from dic.lab.scene import (
    Displacement,
    Mirror,
    Scene,
    Screen,
    SpeckleCylinder,
    SpeckleDisks,
    SpecklePlane,
    rotation_about,
)
from kernels import available_devices

# a small camera with strong distortion (k1 = -0.25: ~4 px at the corners of 128 x 96 px)
K_SMALL = np.array([[320.0, 0.0, 63.7], [0.0, 320.0, 48.2], [0.0, 0.0, 1.0]])
DIST_SMALL = np.array([-0.25, 0.12, 1.5e-3, -1.0e-3, -0.02])


def _small_camera(focus=1000.0, f_number=4.0, pose=(np.eye(3), np.zeros(3))):
    # focal length chosen so that the thin lens focused at `focus` has fx = 320 px with 25 µm pixels
    f_px, pitch = 320.0, 0.025
    v = f_px * pitch
    f = v * focus / (focus + v)
    return LabCamera(camera=Camera(K=K_SMALL, dist=DIST_SMALL, size=(128, 96), name="cam"), R_cam_world=pose[0],
                     t_cam_world=pose[1], pixel_pitch_mm=pitch, focal_length_mm=f, f_number=f_number,
                     focus_distance_mm=focus, exposure_dn=200.0)


def _centroid(img, uv, half=9):
    ys, xs = np.mgrid[: img.shape[0], : img.shape[1]]
    w = img * ((np.abs(xs - uv[0]) < half) & (np.abs(ys - uv[1]) < half))
    return np.array([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()])


def _cv2_project(cam: LabCamera, points_world):
    rvec, _ = cv2.Rodrigues(cam.R_cam_world)
    uv, _ = cv2.projectPoints(np.asarray(points_world, dtype=np.float64).reshape(-1, 1, 3), rvec, cam.t_cam_world,
                              cam.camera.K, cam.camera.dist)
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("material_xy", [(350.0, 595.3), (620.4, 429.3), (500.3, 500.2)])
def test_disk_centroid_matches_cv2_projectpoints(device, material_xy):
    # A bright disk (radius 12 mm, ~4 px in the image) on a black plane perpendicular to the optical axis
    # at the focus distance: in focus and, before distortion, a similarity image ("symmetric case").
    # Error budget: pixelisation bias of the centroid of a box-sampled 4 px disk <= 0.006 px, distortion
    # curvature over the disk (Heikkilä-type bias) ~0.002 px, quadrature error of the 8 x 8 anti-aliased
    # sub-cells per pixel ~0.001 px (measured max 0.007 px over 6 positions): < 0.02 px (the bound).
    cam = _small_camera()
    centre = np.array([material_xy])
    plane = SpecklePlane(R_world_surface=np.eye(3), t_world_surface=np.array([-500.0, -500.0, 1000.0]), size=(1000.0, 1000.0),
                         speckle=SpeckleDisks(centres=centre, radii=np.array([12.0])), albedo=(0.0, 1.0))
    scene = Scene(cameras=[cam], planes=[plane])
    uv_ref = _cv2_project(cam, plane.to_world(centre))[0]
    img = render(scene, 0, samples=64, seed=3, noise=False, quantize=False, device=device).astype(np.float64)
    err = _centroid(img, uv_ref) - uv_ref
    assert np.all(np.abs(err) < 0.02), f"centroid - projectPoints = {err} px"
    # project() is the same model as OpenCV, in float64
    np.testing.assert_allclose(project(scene, 0, plane.to_world(centre))[0], uv_ref, atol=1e-9)


def _mirror_scene(focus=600.0):
    # camera at the origin looking along +z; a 45° mirror at z = 300 sends the view to +x, where a
    # black plane facing -x carries a bright disk. Its virtual image lies on the plane z = 600,
    # perpendicular to the optical axis (symmetric case), in focus.
    cam = _small_camera(focus=focus)
    mirror = Mirror(center=np.array([0.0, 0.0, 300.0]), normal=np.array([1.0, 0.0, -1.0]), size=(400.0, 100.0),
                    up=np.array([0.0, -1.0, 0.0]), reflectance=0.9, name="m")
    plane = SpecklePlane.facing(center=(300.0, 0.0, 300.0), normal=(-1.0, 0.0, 0.0), size=(400.0, 400.0),
                                speckle=SpeckleDisks(centres=np.array([[230.7, 162.4]]), radii=np.array([7.0])),
                                albedo=(0.0, 1.0))
    return Scene(cameras=[cam], mirrors=[mirror], planes=[plane]), plane, mirror


def test_point_seen_through_mirror_lands_on_householder_projection(device):
    scene, plane, mirror = _mirror_scene()
    X = np.array([[230.7, 162.4]])
    P = plane.to_world(X)
    # independent Householder reflection x' = x - 2 (n.x + d) n of the disk centre
    n = np.array([1.0, 0.0, -1.0]) / np.sqrt(2.0)
    d = -n @ np.array([0.0, 0.0, 300.0])
    P_virtual = P - 2.0 * (P @ n + d)[:, None] * n
    uv_ref = _cv2_project(scene.cameras[0], P_virtual)[0]
    np.testing.assert_allclose(project(scene, 0, P, mirror=0)[0], uv_ref, atol=1e-9)
    img = render(scene, 0, samples=64, seed=5, noise=False, quantize=False, device=device).astype(np.float64)
    err = _centroid(img, uv_ref) - uv_ref
    # same error budget as the direct disk test (the virtual disk is a fronto-parallel 3 px disk in focus)
    assert np.all(np.abs(err) < 0.02), f"centroid - reflected projection = {err} px"
    # the reflectance scales the radiance: the disk's total signal is 0.9 x its direct-view value
    # (area of a radius-7 mm disk at 600 mm, in px^2, times 200 DN), to the 2 % of pixelisation + distortion
    area_px = np.pi * (7.0 * 320.0 / 600.0) ** 2
    ratio = img.sum() / (0.9 * 200.0 * area_px)
    assert abs(ratio - 1.0) < 0.02, ratio


def test_mirror_extent_and_back_face():
    scene, plane, mirror = _mirror_scene()
    # a point far up on the plane: its chief ray crosses the mirror plane above the mirror's top edge
    far = plane.to_world([[200.0, 10.0]])
    uv, visible = project(scene, 0, far, mirror=0, return_mask=True)
    assert not visible[0] and np.all(np.isfinite(uv))
    assert np.all(np.isnan(project(scene, 0, far, mirror=0)))
    # a point behind the mirror (on the side its normal points away from) has no mirror image
    behind = np.array([[-50.0, 0.0, 400.0]])
    assert not project(scene, 0, behind, mirror=0, return_mask=True)[1][0]


def test_rays_past_the_mirror_edge_see_the_scene_behind(device):
    # a 40 x 40 mm mirror in front of a uniformly lit wall: only the mirror's image is dark (it shows
    # the empty side of the room), everything around it shows the wall (albedo 0.5 -> 100 DN)
    cam = _small_camera(f_number=float("inf"))
    wall = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=(3000.0, 3000.0), albedo=(0.5, 0.5))
    mirror = Mirror(center=np.array([0.0, 0.0, 500.0]), normal=np.array([1.0, 0.0, -1.0]), size=(40.0, 40.0))
    scene = Scene(cameras=[cam], mirrors=[mirror], planes=[wall])
    img = render(scene, 0, samples=4, noise=False, quantize=False, device=device)
    corners = project(scene, 0, mirror.corners())
    inside = cv2.pointPolygonTest(corners.astype(np.float32), (float(K_SMALL[0, 2]), float(K_SMALL[1, 2])), False) > 0
    assert inside
    assert img[48, 64] == pytest.approx(0.0, abs=1e-3)  # the mirror shows the empty +x side
    assert img[5, 5] == pytest.approx(100.0, abs=1e-3) and img[90, 120] == pytest.approx(100.0, abs=1e-3)


def _esf_disk(x, c):
    """Edge-spread function of a uniform disk of diameter c: the fraction of the disk left of x."""
    r = c / 2.0
    t = np.clip(x / r, -1.0, 1.0)
    return 0.5 + (t * np.sqrt(1.0 - t * t) + np.arcsin(t)) / np.pi


def _esf_pixels(cols, edge, c):
    sub = (np.arange(400) + 0.5) / 400 - 0.5  # pixel-area average
    return _esf_disk(cols[:, None] + sub[None, :] - edge, c).mean(axis=1)


@pytest.mark.parametrize("depth", [850.0, 700.0, 1300.0, 2000.0])
def test_edge_blur_follows_thin_lens_circle_of_confusion(device, depth):
    # Thin lens f = 25 mm, f/1.4, focused at s = 1000 mm, 10 µm pixels. A black/white edge on a screen
    # at depth z is blurred by a uniform disk of diameter c = (f/N) f |z - s| / (z (s - f)) / pitch,
    # 8-23 px here. We fit c to the row-averaged profile with the analytic disk edge-spread function
    # (pixel-integrated), the edge position fixed by the exact projection. 64 aperture samples per pixel
    # (randomly shifted per pixel) averaged over 48 rows leave profile noise ~1e-3 of the step (measured
    # rms 0.0015): c fits to 0.3 %; we allow 2 %.
    f, N, pitch, s = 25.0, 1.4, 0.01, 1000.0
    cam = LabCamera.from_lens(name="c", size=(64, 48), pixel_pitch_mm=pitch, focal_length_mm=f, f_number=N,
                              focus_distance_mm=s, principal_point=(31.73, 23.5), exposure_dn=200.0)
    W, H = 400, 300
    image = np.zeros((H, W), np.float32)
    image[:, W // 2:] = 1.0
    p = 0.1 * depth / 1000.0
    screen = Screen.facing(center=(0.5 * p, 0.0, depth), normal=(0.0, 0.0, -1.0), resolution=(W, H), pixel_pitch_mm=p, image=image)
    scene = Scene(cameras=[cam], screens=[screen])
    edge_u = project(scene, 0, screen.to_world([[W / 2 - 0.5, 0.0]]))[0, 0]
    img = render(scene, 0, samples=64, seed=1, noise=False, quantize=False, device=device).astype(np.float64) / 200.0
    profile = img.mean(axis=0)
    cols = np.arange(64.0)
    c_lens = (f / N) * f * abs(depth - s) / (depth * (s - f)) / pitch
    fit = minimize_scalar(lambda c: np.sum((_esf_pixels(cols, edge_u, c) - profile) ** 2), bounds=(0.5, 40.0), method="bounded")
    assert abs(fit.x / c_lens - 1.0) < 0.02, f"fitted blur {fit.x:.3f} px, thin lens {c_lens:.3f} px"
    assert np.sqrt(fit.fun / cols.size) < 0.005  # the profile has the uniform-disk shape


def test_focus_plane_is_sharp(device):
    # at the focus distance the edge spreads over the pixel only: the profile is the pixel-integrated step
    cam = LabCamera.from_lens(name="c", size=(64, 48), pixel_pitch_mm=0.01, focal_length_mm=25.0, f_number=1.4,
                              focus_distance_mm=1000.0, principal_point=(31.73, 23.5), exposure_dn=200.0)
    image = np.zeros((300, 400), np.float32)
    image[:, 200:] = 1.0
    screen = Screen.facing(center=(0.05, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), resolution=(400, 300), pixel_pitch_mm=0.1, image=image)
    img = render(Scene(cameras=[cam], screens=[screen]), 0, samples=64, noise=False, quantize=False, device=device)
    profile = img.mean(axis=0) / 200.0
    edge_u = project(Scene(cameras=[cam], screens=[screen]), 0, screen.to_world([[199.5, 0.0]]))[0, 0]
    sharp = _esf_pixels(np.arange(64.0), edge_u, 1e-9)  # a step integrated over the pixel, no blur
    # 8 x 8 anti-aliased sub-cells per pixel: the straight edge integrates to ~1e-3 of the step
    assert np.abs(profile - sharp).max() < 0.01


def _speckle_plane(**kw):
    rng = np.random.default_rng(7)
    centres = rng.uniform(0, 300, size=(4000, 2))
    disks = SpeckleDisks(centres=centres, radii=rng.uniform(1.5, 3.0, size=4000))
    return SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.2, -0.1, -1.0), size=(300.0, 300.0), speckle=disks, **kw)


def test_same_seed_same_image_and_noise_statistics(device):
    cam = _small_camera()
    cam.read_noise_dn, cam.electrons_per_dn = 2.0, 50.0
    scene = Scene(cameras=[cam], planes=[_speckle_plane()])
    a = render(scene, 0, samples=4, seed=11, device=device)
    b = render(scene, 0, samples=4, seed=11, device=device)
    c = render(scene, 0, samples=4, seed=12, device=device)
    assert a.dtype == np.uint8 and np.array_equal(a, b)
    assert not np.array_equal(a, c)
    # noise: on a uniform grey wall (albedo 0.5 -> S = 100 DN) the std is sqrt(S / gain + read^2) = 2.45 DN
    wall = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=(3000.0, 3000.0), albedo=(0.5, 0.5))
    flat = render(Scene(cameras=[cam], planes=[wall]), 0, samples=1, seed=1, quantize=False, device=device)
    expected = np.sqrt(100.0 / 50.0 + 2.0**2)
    # 12288 pixels: the sample std is within 3 % of the truth with > 99.9 % probability
    assert abs(flat.std() / expected - 1.0) < 0.03 and abs(flat.mean() - 100.0) < 0.1


@pytest.mark.skipif("cuda:0" not in available_devices(), reason="needs a CUDA device")
def test_cpu_and_cuda_render_the_same():
    scene, _, _ = _mirror_scene()
    scene = scene.replace(planes=scene.planes + [_speckle_plane()])
    a = render(scene, 0, samples=16, seed=2, noise=False, quantize=False, device="cpu")
    b = render(scene, 0, samples=16, seed=2, noise=False, quantize=False, device="cuda:0")
    # same sample pattern and RNG; only float rounding differs (FMA contraction), which can flip the
    # coverage of a sub-sample lying within ~1e-6 mm of a disk edge: 1/16 of 200 DN in rare pixels
    diff = np.abs(a.astype(np.float64) - b)
    assert diff.mean() < 0.01 and np.quantile(diff, 0.999) <= 12.5 + 1e-3


def test_rigid_displacement_renders_like_a_moved_surface(device):
    # a constant displacement (3.7, -1.2, 5.0) mm in the plane's frame must render exactly like the plane
    # moved by R u: Newton finds the same material point for every ray (differences only from float
    # rounding flipping sub-samples on disk edges)
    plane = _speckle_plane()
    u = np.array([3.7, -1.2, 5.0])
    disp = Displacement(values=np.broadcast_to(u, (4, 4, 3)).copy(), origin=(-10.0, -10.0), step=(110.0, 110.0))
    deformed = SpecklePlane(R_world_surface=plane.R_world_surface, t_world_surface=plane.t_world_surface, size=plane.size,
                            speckle=plane.speckle, displacement=disp)
    moved = SpecklePlane(R_world_surface=plane.R_world_surface, t_world_surface=plane.t_world_surface + plane.R_world_surface @ u,
                         size=plane.size, speckle=plane.speckle)
    cam = _small_camera()
    a = render(Scene(cameras=[cam], planes=[deformed]), 0, samples=16, seed=4, noise=False, quantize=False, device=device)
    b = render(Scene(cameras=[cam], planes=[moved]), 0, samples=16, seed=4, noise=False, quantize=False, device=device)
    diff = np.abs(a.astype(np.float64) - b)
    assert diff.mean() < 0.01 and diff.max() <= 2 * 200.0 * 0.8 / 16 + 1e-3


def test_cylinder_displacement_of_a_rigid_rotation_renders_like_a_rotated_cylinder(device):
    # on a cylinder of radius R, the constant field u_S = R sin(phi), u_R = R (cos(phi) - 1), u_Y = a moves
    # every material point by a rotation phi about the axis plus a shift a along it (exercises the
    # cylinder's Newton solve with tangential, radial and axial components)
    rng = np.random.default_rng(3)
    R_cyl, L = 80.0, 200.0
    disks = SpeckleDisks(centres=np.column_stack([rng.uniform(-np.pi * R_cyl, np.pi * R_cyl, 3000), rng.uniform(0, L, 3000)]),
                         radii=rng.uniform(1.5, 3.0, 3000))
    base = SpeckleCylinder.facing(center=(10.0, 5.0, 1000.0), axis=(0.1, 1.0, 0.0), front=(0.0, 0.0, -1.0), radius=R_cyl,
                                  length=L, speckle=disks)
    phi, a = 0.075, 2.5
    u = [R_cyl * np.sin(phi), a, R_cyl * (np.cos(phi) - 1.0)]
    disp = Displacement(values=np.broadcast_to(u, (4, 4, 3)).copy(), origin=(-300.0, -20.0), step=(200.0, 100.0))
    deformed = SpeckleCylinder(R_world_surface=base.R_world_surface, t_world_surface=base.t_world_surface, radius=R_cyl,
                               length=L, speckle=disks, displacement=disp)
    # theta -> theta + phi: the local point (R sin, y, -R cos) rotates about local y by -phi
    Rloc = rotation_about([0.0, 1.0, 0.0], -phi)
    moved = SpeckleCylinder(R_world_surface=base.R_world_surface @ Rloc,
                            t_world_surface=base.t_world_surface + base.R_world_surface @ np.array([0.0, a, 0.0]),
                            radius=R_cyl, length=L, speckle=disks)
    cam = _small_camera(f_number=float("inf"))
    img_d = render(Scene(cameras=[cam], cylinders=[deformed]), 0, samples=16, seed=4, noise=False, quantize=False, device=device)
    img_m = render(Scene(cameras=[cam], cylinders=[moved]), 0, samples=16, seed=4, noise=False, quantize=False, device=device)
    assert img_m.std() > 20  # the speckle is visible
    diff = np.abs(img_d.astype(np.float64) - img_m)
    assert diff.mean() < 0.05 and np.quantile(diff, 0.999) <= 200.0 * 0.8 / 16 * 2 + 1e-3


def test_deformed_marker_lands_where_its_displaced_point_projects(device):
    # a non-uniform displacement (bulge out of plane + in-plane shear): a small disk painted at material
    # point X lands where plane.to_world(X, deformed=True) projects. Over the disk (radius 6 mm, ~2 px)
    # the field is affine to within 0.05 mm (bulge curvature 60 / 150^2 per mm), and an affine map keeps
    # the centroid on the image of the centre, so the 0.02 px budget of the undeformed disk test holds.
    def field(X, Y):
        r2 = (X - 250.0) ** 2 + (Y - 250.0) ** 2
        return 0.1 * (Y - 250.0), 0.05 * (X - 250.0), -60.0 * np.exp(-r2 / (2 * 150.0**2))

    disp = Displacement.from_function(field, (0.0, 500.0, 0.0, 500.0), 10.0)
    X = np.array([[330.0, 290.0]])
    plane = SpecklePlane(R_world_surface=np.eye(3), t_world_surface=np.array([-250.0, -250.0, 1000.0]), size=(500.0, 500.0),
                         speckle=SpeckleDisks(centres=X, radii=np.array([6.0])), albedo=(0.0, 1.0), displacement=disp)
    cam = _small_camera(f_number=float("inf"))
    scene = Scene(cameras=[cam], planes=[plane])
    uv_ref = _cv2_project(cam, plane.to_world(X, deformed=True))[0]
    uv_undeformed = _cv2_project(cam, plane.to_world(X, deformed=False))[0]
    assert np.linalg.norm(uv_ref - uv_undeformed) > 2.0  # the deformation moves it by pixels
    img = render(scene, 0, samples=64, seed=9, noise=False, quantize=False, device=device).astype(np.float64)
    err = _centroid(img, uv_ref, half=6) - uv_ref
    assert np.all(np.abs(err) < 0.02), err


@pytest.mark.parametrize("position", [0, 26])  # a near and a far corner of the volume: strong defocus
def test_window_render_is_the_full_render(device, position):
    """Pixels outside window_around(...) see only background: rendering them with one sample
    changes nothing (bit for bit, noise and quantisation included); a window cut into the monitor does."""
    from dic.lab import paper_rig, window_around
    from repro.experiments import speckle_monitor_image

    lab = paper_rig(scale=0.5)
    scene = lab.with_monitor_at(position).with_monitor_image(speckle_monitor_image(3.0, 5))
    for cam in ("left", "right"):
        win = window_around(scene, cam, scene.monitor.outer_corners())
        blur = scene.camera(cam).blur_diameter_px(scene.camera(cam).world_to_camera(scene.monitor.center_world[None])[:, 2])
        assert blur[0] > 0.4  # out of focus (0.4-0.8 px at half scale): the window needs its blur margin
        full = render(scene, cam, samples=4, seed=4, device=device)
        assert np.array_equal(render(scene, cam, samples=4, seed=4, window=win, device=device), full)
        x0, y0, x1, y1 = win
        cut = (x0 + 12, y0 + 12, x1 - 12, y1 - 12)
        assert not np.array_equal(render(scene, cam, samples=4, seed=4, window=cut, device=device), full)


def test_window_bad_input():
    from dic.lab import paper_rig, window_around

    scene = paper_rig(scale=0.25).with_monitor_at(13)
    with pytest.raises(ValueError, match="window must be"):
        render(scene, "left", samples=1, window=(1, 2, 3))
    with pytest.raises(ValueError, match="finite"):
        render(scene, "left", samples=1, window=(0, 0, np.nan, 10))
    with pytest.raises(ValueError, match="points_world"):
        window_around(scene, "left", np.zeros((2, 2)))
    with pytest.raises(ValueError, match="points_world"):
        window_around(scene, "left", np.zeros((3, 2)))  # 6 numbers, but not (N, 3)
    behind = scene.camera("left").center_world - 100.0 * scene.camera("left").axis_world
    with pytest.raises(ValueError, match="behind the camera"):
        window_around(scene, "left", behind[None])


def test_screens_window_only_for_mirrorless_screen_scenes():
    from dic.lab import paper_rig, screens_window, window_around

    rig = paper_rig(scale=0.25)
    direct = rig.with_monitor_at(13)
    assert screens_window(direct, "left") == window_around(direct, "left", direct.monitor.outer_corners())
    assert screens_window(rig.with_mirror_tilt(0), "left") is None  # monitor seen through a mirror
    with pytest.raises(ValueError, match="dic.lab.Scene"):
        screens_window("scene", "left")
