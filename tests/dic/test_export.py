"""VTK (meshio, dic.export) and figure (dic.plots.fields) exports of 3-D fields, checked by reading the files back."""
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from dic.export import write_vtk, write_vtk_series
from dic.field3d import Field3D, StereoStatus
from dic.plots.fields import write_figures


def _field(rng, ny=6, nx=8, index=1, grid=True):
    n = ny * nx
    gy, gx = np.meshgrid(np.arange(ny) * 10.0 + 20, np.arange(nx) * 10.0 + 20, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    status = np.zeros(n, np.int8)
    status[[0, 13, 29]] = [StereoStatus.MATCH_FAILED, StereoStatus.EPIPOLAR_VIOLATION, StereoStatus.LOW_ZNCC]
    ok = status == 0
    X = np.where(ok, pts[:, 0] * 0.6 - 50, np.nan)
    Y = np.where(ok, pts[:, 1] * 0.6 - 40, np.nan)
    Z = np.where(ok, 1000 + 0.01 * pts[:, 0], np.nan)
    U, V, W = (np.where(ok, rng.normal(size=n), np.nan) for _ in range(3))
    e = {k: np.where(ok, rng.normal(scale=1e-3, size=n), np.nan) for k in ("exx", "eyy", "exy")}
    return Field3D(points=pts, grid_shape=(ny, nx) if grid else None, X=X, Y=Y, Z=Z, U=U, V=V, W=W, **e,
                   normal=np.where(ok[:, None], [0.0, 0.0, -1.0], np.nan), zncc_stereo=rng.uniform(0.9, 1, n),
                   zncc_left=rng.uniform(0.9, 1, n), zncc_right=rng.uniform(0.9, 1, n),
                   epipolar_ref_px=rng.uniform(0, 0.1, n), epipolar_px=rng.uniform(0, 0.1, n),
                   reprojection_ref_px=rng.uniform(0, 0.1, n), reprojection_px=rng.uniform(0, 0.1, n),
                   status=status, strain_valid=ok.copy(), index=index)


def test_vtk_grid_and_points_round_trip(rng, tmp_path):
    import meshio

    f = _field(rng)
    ok = f.valid
    path = write_vtk(f, tmp_path / "grid.vtu")
    mesh = meshio.read(path)
    assert np.allclose(mesh.points, f.xyz[ok])
    # quads: every grid cell whose 4 corners are valid (counted independently here)
    ny, nx = f.grid_shape
    v = ok.reshape(ny, nx)
    expected_quads = int(np.sum(v[:-1, :-1] & v[:-1, 1:] & v[1:, :-1] & v[1:, 1:]))
    assert mesh.cells_dict["quad"].shape == (expected_quads, 4)
    # each quad's corners are grid neighbours: their image positions form a 10 px square
    q = mesh.cells_dict["quad"]
    ix, iy = mesh.point_data["image_x"][q], mesh.point_data["image_y"][q]
    assert np.allclose(ix.max(1) - ix.min(1), 10) and np.allclose(iy.max(1) - iy.min(1), 10)
    for name in ("U", "W", "exx", "zncc_left", "epipolar_px"):
        assert np.allclose(mesh.point_data[name], getattr(f, name)[ok])
    assert np.allclose(mesh.point_data["displacement"], f.uvw[ok])
    deformed = meshio.read(write_vtk(f, tmp_path / "deformed.vtk", deformed=True))
    assert np.allclose(deformed.points, (f.xyz + f.uvw)[ok])
    cloud = meshio.read(write_vtk(f, tmp_path / "cloud.vtu", kind="points"))
    assert cloud.cells_dict["vertex"].shape == (ok.sum(), 1) and np.allclose(cloud.points, f.xyz[ok])


def test_vtk_series_and_errors(rng, tmp_path):
    fields = [_field(rng, index=i) for i in (0, 1, 2)]
    pvd = write_vtk_series(fields, tmp_path / "vtk", stem="run")
    root = ET.parse(pvd).getroot()
    sets = root.findall("./Collection/DataSet")
    assert [int(s.get("timestep")) for s in sets] == [0, 1, 2]
    assert all((tmp_path / "vtk" / s.get("file")).exists() for s in sets)
    with pytest.raises(ValueError, match="kind='grid' needs POIs on a regular grid"):
        write_vtk(_field(rng, grid=False), tmp_path / "x.vtu")
    with pytest.raises(ValueError, match=r"\.vtu or \.vtk"):
        write_vtk(fields[0], tmp_path / "x.csv")
    with pytest.raises(ValueError, match="kind must be"):
        write_vtk(fields[0], tmp_path / "x.vtu", kind="mesh")
    dead = _field(rng)
    dead.status[:] = StereoStatus.NO_GUESS
    with pytest.raises(ValueError, match="no valid point"):
        write_vtk(dead, tmp_path / "x.vtu")
    with pytest.raises(ValueError, match="Field3D"):
        write_vtk({"X": 1}, tmp_path / "x.vtu")


def test_figures(rng, tmp_path):
    import imageio.v3 as iio

    image = rng.uniform(0, 255, (90, 120))
    f = _field(rng)
    paths = write_figures(f, image, tmp_path / "fig", prefix="s1_", dpi=50)
    names = sorted(p.name for p in paths)
    assert names == sorted(f"s1_{q}.png" for q in ("Z", "U", "V", "W", "exx", "eyy", "exy", "zncc_stereo", "status"))
    for p in paths:
        img = iio.imread(p)
        assert img.ndim == 3 and img.shape[0] > 150 and img.shape[1] > 300  # 7.5 in wide at 50 dpi
    ref = write_figures(_field(rng, index=0), image, tmp_path / "fig0", dpi=40)
    assert sorted(p.name for p in ref) == ["Z.png", "status.png", "zncc_stereo.png"]
    scattered = write_figures(_field(rng, grid=False), image, tmp_path / "fig2", quantities=["W"], dpi=40)
    assert scattered[0].exists()
    with pytest.raises(ValueError, match="unknown figure quantities"):
        write_figures(f, image, tmp_path / "fig", quantities=["T"])
    with pytest.raises(ValueError, match=r"\(H, W\) left reference image"):
        write_figures(f, np.zeros((4, 4, 3)), tmp_path / "fig")
