"""Per-point uncertainty in every table and export (issue 25 item 4): ``sigma_u``, ``sigma_v`` (px) of 2-D
fields and ``sigma_X`` ... ``sigma_W`` (mm) of stereo fields in the DataFrame, the xarray Dataset, CSV
(pandas), netCDF (xarray), MATLAB (scipy.io) and VTK (meshio), NaN where a point is not valid or the
field has no sigma (files written before the columns existed)."""
import meshio
import numpy as np
import pandas as pd
import pytest
import scipy.io
import xarray as xr
from test_export_formats import NX, NY, field2d, field3d

from dic.export import write_csv, write_mat, write_netcdf, write_vtk, write_vtk_series
from dic.field3d import Field3D
from dic.store import ResultWriter, read_results, read_stereo
from dic.tabular import SIGMA_3D, UNITS

SIGMA_2D = ("sigma_u", "sigma_v")


def sigma_field2d(k):
    """:func:`field2d` with a sigma at every point, invalid ones included (the table must blank those)."""
    f = field2d(k)
    n = len(f.u)
    f.sigma_u = 0.01 + 1e-4 * np.arange(n) + 1e-3 * k
    f.sigma_v = 0.02 + 2e-4 * np.arange(n) + 1e-3 * k
    f.noise_sigma, f.noise_source = 1.5, "given"
    return f


def sigma_field3d(k):
    """:func:`field3d` with ``details["sigma_xyz_mm"]``, ``["sigma_uvw_mm"]`` (N, 3) mm, finite everywhere."""
    f = field3d(k)
    n = len(f)
    ramp = np.arange(n, dtype=np.float64)[:, None]
    f.details = {"sigma_xyz_mm": 0.001 * (1 + ramp) * np.array([1.0, 2.0, 10.0]),
                 "sigma_uvw_mm": 0.0005 * (1 + ramp + k) * np.array([1.0, 1.5, 6.0])}
    return f


def expected_2d(f, name):
    return np.where(f.valid, getattr(f, name), np.nan)


def expected_3d(f, name):
    key, j = SIGMA_3D[name]
    return np.where(f.valid, f.details[key][:, j], np.nan)


@pytest.fixture
def run2d(tmp_path):
    path = tmp_path / "sigma2d.h5"
    with ResultWriter(path, reference_path="ref.tif", reference_shape=(60, 70), settings={"subset": 15, "step": 8}) as w:
        for k in (1, 2):
            w.write_frame(k, sigma_field2d(k), path=f"cur{k}.tif")
    return path


@pytest.fixture
def run3d(tmp_path):
    from calibration.camera import Camera
    from calibration.stereo import StereoRig

    K = np.array([[1641.0, 0, 160], [0, 1641.0, 120], [0, 0, 1]])
    rig = StereoRig(Camera(K=K, size=(320, 240), name="left"), Camera(K=K, size=(320, 240), name="right"),
                    np.eye(3), np.array([-300.0, 0.0, 0.0]))
    path = tmp_path / "sigma3d.h5"
    with ResultWriter(path, kind="stereo", rig=rig, reference_path=("l0.tif", "r0.tif"), reference_shape=(240, 320),
                      settings={"step": 10, "subset": 21}) as w:
        for k in (0, 1, 2):
            w.write_frame(k, sigma_field3d(k), path=(f"l{k}.tif", f"r{k}.tif"))
    return path


def test_units_of_the_sigma_columns():
    assert all(UNITS[name] == "px" for name in SIGMA_2D)
    assert all(UNITS[name] == "mm" for name in SIGMA_3D)


def test_2d_field_and_file_tables_hold_sigma(run2d):
    f = sigma_field2d(1)
    assert not f.valid.all()  # some points are invalid: their sigma must be blanked
    df = f.to_dataframe()
    ds = f.to_xarray()
    for name in SIGMA_2D:
        assert ds[name].attrs["units"] == "px"
        assert np.array_equal(df[name].to_numpy(), expected_2d(f, name), equal_nan=True)
        assert np.isnan(df[name].to_numpy()[~f.valid]).all() and np.isfinite(df[name].to_numpy()[f.valid]).all()
    res = read_results(run2d)
    ds = res.to_xarray()
    df = res.to_dataframe()
    for k in (1, 2):
        fr = res.frames[k]
        for name in SIGMA_2D:
            assert np.array_equal(ds[name].sel(frame=k).values, expected_2d(fr, name), equal_nan=True)
            assert np.array_equal(df.loc[k][name].to_numpy(), expected_2d(sigma_field2d(k), name), equal_nan=True)
    assert ds["sigma_u"].attrs["units"] == "px" and ds["sigma_u"].dims == ("frame", "point")


def test_2d_exports_hold_sigma(run2d, tmp_path):
    res = read_results(run2d)
    csv = write_csv(run2d, tmp_path / "csv")
    for path, k in zip(csv, (1, 2)):
        table = pd.read_csv(path, index_col="point")
        for name in SIGMA_2D:
            assert np.allclose(table[name].to_numpy(), expected_2d(res.frames[k], name), rtol=1e-15, atol=0,
                               equal_nan=True)
    nc = xr.open_dataset(write_netcdf(run2d, tmp_path / "run.nc"))
    mat = scipy.io.loadmat(write_mat(run2d, tmp_path / "run.mat"))
    for name in SIGMA_2D:
        assert nc[name].attrs["units"] == "px"
        assert str(mat["units"][name][0, 0][0]) == "px"
        for row, k in enumerate((1, 2)):
            want = expected_2d(res.frames[k], name)
            assert np.array_equal(nc[name].sel(frame=k).values, want, equal_nan=True)
            assert np.array_equal(mat[name][row], want, equal_nan=True)
    nc.close()
    pvd = write_vtk_series(run2d, tmp_path / "vtk")
    for k in (1, 2):
        mesh = meshio.read(pvd.parent / f"frame_{k:06d}.vtu")  # every point of the grid, in order
        for name in SIGMA_2D:
            assert np.array_equal(mesh.point_data[name], expected_2d(res.frames[k], name), equal_nan=True)
    one = meshio.read(write_vtk(res.frames[1], tmp_path / "one.vtu"))  # valid points only
    keep = res.frames[1].valid
    assert np.array_equal(one.point_data["sigma_u"], res.frames[1].sigma_u[keep])


def test_files_without_sigma_export_nan_columns(tmp_path):
    """A file written without sigma (before it was stored, or by another writer) exports NaN sigma columns."""
    path = tmp_path / "old.h5"
    with ResultWriter(path, reference_path="ref.tif", reference_shape=(60, 70), settings={"subset": 15}) as w:
        w.write_frame(1, field2d(1), path="cur1.tif")
    res = read_results(path)
    assert res.frames[1].sigma_u is None
    ds = res.to_xarray()
    assert np.isnan(ds["sigma_u"].values).all() and np.isnan(ds["sigma_v"].values).all()
    table = pd.read_csv(write_csv(path, tmp_path / "csv")[0], index_col="point")
    assert table["sigma_u"].isna().all() and len(table) == NY * NX
    mesh = meshio.read(write_vtk_series(path, tmp_path / "vtk").parent / "frame_000001.vtu")
    assert np.isnan(mesh.point_data["sigma_v"]).all()
    st = field3d(1)
    assert st.details == {} and np.isnan(st.to_dataframe()["sigma_W"].to_numpy()).all()


def test_stereo_tables_and_exports_hold_sigma(run3d, tmp_path):
    st = read_stereo(run3d)
    assert set(st.fields[1].details) >= {"sigma_xyz_mm", "sigma_uvw_mm"}  # stored in the file, read back
    ds = st.to_xarray()
    df = st.to_dataframe()
    nc = xr.open_dataset(write_netcdf(run3d, tmp_path / "run.nc"))
    mat = scipy.io.loadmat(write_mat(run3d, tmp_path / "run.mat"))
    csv = write_csv(run3d, tmp_path / "csv")
    pvd = write_vtk_series(run3d, tmp_path / "vtk")
    for row, k in enumerate((0, 1, 2)):
        f = st.fields[k]
        assert not f.valid.all()
        table = pd.read_csv(csv[row], index_col="point")
        mesh = meshio.read(pvd.parent / f"stereo_{k:06d}.vtu")
        # the series drops the point without a position (its reference match failed): match by image position
        order = [int(np.flatnonzero((f.points[:, 0] == x) & (f.points[:, 1] == y))[0])
                 for x, y in zip(mesh.point_data["image_x"], mesh.point_data["image_y"])]
        for name in SIGMA_3D:
            want = expected_3d(f, name)
            assert np.isnan(want[~f.valid]).all() and np.isfinite(want[f.valid]).all()
            assert np.array_equal(ds[name].sel(frame=k).values, want, equal_nan=True)
            assert np.array_equal(df.loc[k][name].to_numpy(), want, equal_nan=True)
            assert np.array_equal(nc[name].sel(frame=k).values, want, equal_nan=True)
            assert np.array_equal(mat[name][row], want, equal_nan=True)
            assert np.allclose(table[name].to_numpy(), want, rtol=1e-15, atol=0, equal_nan=True)
            assert np.array_equal(mesh.point_data[name], want[order], equal_nan=True)
    for name in SIGMA_3D:
        assert ds[name].attrs["units"] == "mm" and nc[name].attrs["units"] == "mm"
    nc.close()


def test_stereo_field_table_refuses_a_misshapen_sigma():
    f = sigma_field3d(1)
    f.details["sigma_uvw_mm"] = f.details["sigma_uvw_mm"][:, :2]
    with pytest.raises(ValueError, match="sigma_uvw_mm"):
        f.to_dataframe()


def test_in_frame_drops_the_sigma_it_cannot_rotate():
    """Only the std per axis is stored, not the covariance: another frame cannot be computed from it."""
    f = sigma_field3d(1)
    assert isinstance(f, Field3D)
    same = f.in_frame((f.R_frame_left, f.t_frame_left))
    assert np.array_equal(same.to_dataframe()["sigma_W"].to_numpy(), expected_3d(f, "sigma_W"), equal_nan=True)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    turned = f.in_frame((R, np.zeros(3)))
    assert "sigma_uvw_mm" not in turned.details and "sigma_xyz_mm" not in turned.details
    assert np.isnan(turned.to_dataframe()["sigma_U"].to_numpy()).all()
