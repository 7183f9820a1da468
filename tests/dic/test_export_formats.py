"""Exports of result files (dic/export.py, ``specula export``), each read back by the library that owns
the format: pandas.read_csv, scipy.io.loadmat, xarray.open_dataset and meshio.read."""
import numpy as np
import pytest
from click.testing import CliRunner

from dic._strain import strain
from dic.cli import main
from dic.export import (
    export_results,
    to_dataframe,
    to_xarray,
    write_csv,
    write_mat,
    write_netcdf,
    write_vtk,
    write_vtk_series,
)
from dic.field2d import Field2D
from dic.field3d import Field3D, StereoStatus
from dic.store import ResultWriter, read_results, read_stereo

NY, NX = 5, 6


def field2d(k, *, order=1):
    """A 2-D field on a 5 x 6 grid (step 8 px) whose validity changes from frame to frame."""
    gy, gx = np.meshgrid(np.arange(NY) * 8.0 + 12, np.arange(NX) * 8.0 + 12, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    n = len(pts)
    u = 0.1 * k + 0.002 * pts[:, 0]
    v = -0.05 * k + 0.001 * pts[:, 1] ** 1.1
    params = np.zeros((n, 6 if order == 1 else 12))
    params[:, 0], params[:, 6 if order == 2 else 3] = u, v
    params[:, 1] = 0.002
    status = np.zeros(n, np.int32)
    status[[k, 7 + k]] = [2, 5]
    valid = status == 0
    return Field2D(points=pts, u=u, v=v, params=params, zncc=np.linspace(0.9, 1.0, n), iterations=np.full(n, 3 + k, np.int32),
                   status=status, valid=valid, subset=15, order=order, step=8, zncc_min=0.8)


@pytest.fixture
def results2d(tmp_path):
    path = tmp_path / "run2d.h5"
    with ResultWriter(path, reference_path="ref.tif", reference_shape=(60, 70), settings={"subset": 15, "step": 8}) as w:
        for k in (1, 2, 3):
            f = field2d(k)
            w.write_frame(k, f, strain=strain(f, window=3), path=f"cur{k}.tif", attrs={"seconds": 0.1})
    return path


def field3d(k, ny=4, nx=5):
    """A Field3D like a stereo sequence's: reference positions shared by every state (NaN where the
    reference match failed), per-state failures with NaN displacements."""
    n = ny * nx
    gy, gx = np.meshgrid(np.arange(ny) * 10.0 + 20, np.arange(nx) * 10.0 + 20, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    status = np.zeros(n, np.int8)
    status[2] = StereoStatus.MATCH_FAILED                        # every state: no position
    if k:
        status[[5 + k, 11 + k]] = StereoStatus.TRACK_LEFT_FAILED  # this state only
    has_pos = status != StereoStatus.MATCH_FAILED
    ok = status == StereoStatus.OK
    X = np.where(has_pos, 0.5 * pts[:, 0] - 20, np.nan)
    Y = np.where(has_pos, 0.5 * pts[:, 1] - 15, np.nan)
    Z = np.where(has_pos, 1000 + 0.01 * pts[:, 0], np.nan)
    U = np.where(ok, 0.1 * k + 0.001 * pts[:, 0], np.nan)
    V = np.where(ok, -0.05 * k, np.nan)
    W = np.where(ok, 0.02 * k * np.sin(pts[:, 1] / 10), np.nan)
    e = {name: np.where(ok, 1e-4 * k * (j + 1), np.nan) for j, name in enumerate(("exx", "eyy", "exy"))}
    q = {name: np.where(ok, 0.95, np.nan) for name in ("zncc_stereo", "zncc_left", "zncc_right")}
    r = {name: np.where(ok, 0.05, np.nan) for name in ("epipolar_ref_px", "epipolar_px", "reprojection_ref_px",
                                                        "reprojection_px")}
    return Field3D(points=pts, grid_shape=(ny, nx), X=X, Y=Y, Z=Z, U=U, V=V, W=W, **e, **q, **r,
                   normal=np.where(ok[:, None], [0.0, 0.0, -1.0], np.nan), status=status, strain_valid=ok.copy(),
                   index=k, frame_name="plane")


@pytest.fixture
def results3d(tmp_path):
    from calibration.camera import Camera
    from calibration.stereo import StereoRig

    K = np.array([[1641.0, 0, 160], [0, 1641.0, 120], [0, 0, 1]])
    rig = StereoRig(Camera(K=K, size=(320, 240), name="left"), Camera(K=K, size=(320, 240), name="right"),
                    np.eye(3), np.array([-300.0, 0.0, 0.0]))
    path = tmp_path / "run3d.h5"
    with ResultWriter(path, kind="stereo", rig=rig, reference_path=("l0.tif", "r0.tif"), reference_shape=(240, 320),
                      settings={"step": 10, "subset": 21}) as w:
        for k in (0, 1, 2):
            w.write_frame(k, field3d(k), path=(f"l{k}.tif", f"r{k}.tif"))
    return path


def test_xarray_and_dataframe_of_result_files(results2d, results3d):
    res = read_results(results2d)
    ds = res.to_xarray()
    assert dict(ds.sizes) == {"frame": 3, "point": NY * NX} and list(ds["frame"].values) == [1, 2, 3]
    assert ds["u"].attrs["units"] == "px" and ds["x"].attrs["units"] == "px" and ds["exx"].attrs["units"] == "1"
    assert ds["status"].attrs["flag_meanings"].split()[:2] == ["CONVERGED", "MAX_ITERATIONS"]
    assert list(ds["path"].values) == ["cur1.tif", "cur2.tif", "cur3.tif"]
    assert ds.attrs["reference_path"] == "ref.tif" and '"subset": 15' in ds.attrs["settings"]
    for k in (1, 2, 3):
        fr = res.frames[k]
        assert np.array_equal(ds["u"].sel(frame=k).values, fr.u)
        assert np.array_equal(ds["valid"].sel(frame=k).values, fr.valid)
        assert np.array_equal(ds["exx"].sel(frame=k).values, fr.strain["exx"], equal_nan=True)
        assert np.array_equal(ds["ux"].sel(frame=k).values, fr.params[:, 1])
    df = res.to_dataframe()
    assert df.index.names == ["frame", "point"] and len(df) == 3 * NY * NX and list(df.columns[:4]) == ["x", "y", "u", "v"]
    assert np.array_equal(df.loc[2]["u"].to_numpy(), res.frames[2].u)
    st = read_stereo(results3d)
    ds3 = st.to_xarray()
    assert dict(ds3.sizes) == {"frame": 3, "point": 20}
    assert {"x", "y", "X", "Y", "Z"} <= set(ds3.coords) and ds3["X"].dims == ("frame", "point")
    assert ds3["U"].attrs["units"] == "mm" and ds3["status"].attrs["flag_meanings"].split()[0] == "OK"
    assert np.array_equal(ds3["W"].sel(frame=2).values, st.fields[2].W, equal_nan=True)
    assert list(ds3["left_path"].values) == ["l0.tif", "l1.tif", "l2.tif"]
    assert '"baseline"' in ds3.attrs["rig"] or "R" in ds3.attrs["rig"]
    df3 = to_dataframe(results3d)  # the module-level helpers take a path too
    assert list(df3.columns[:5]) == ["x", "y", "X", "Y", "Z"] and len(df3) == 60
    assert to_xarray(results2d).equals(ds)


def test_field_tables():
    f = field2d(1, order=2)
    df = f.to_dataframe()
    assert df.index.name == "point" and len(df) == f.n_points
    assert {"uxx", "vyy", "zncc", "status", "valid"} <= set(df.columns) and "strain_valid" not in df.columns
    assert np.array_equal(df["u"].to_numpy(), f.u) and df["valid"].dtype == bool
    s = strain(f, window=3)
    ds = f.to_xarray(s)
    assert np.array_equal(ds["Exy"].values, s.Exy, equal_nan=True) and ds["uxx"].attrs["units"] == "1/px"
    f3 = field3d(1)
    ds3 = f3.to_xarray()
    assert ds3["X"].dims == ("point",) and np.array_equal(ds3["normal_z"].values, f3.normal[:, 2], equal_nan=True)
    assert np.array_equal(f3.to_dataframe()["valid"].to_numpy(), f3.valid)
    with pytest.raises(ValueError, match="expected a Field2D"):
        to_xarray(42)


def test_csv_per_frame_reads_back_with_pandas(results2d, results3d, tmp_path):
    import pandas as pd

    res = read_results(results2d)
    paths = write_csv(results2d, tmp_path / "csv")
    assert [p.name for p in paths] == ["frame_000001.csv", "frame_000002.csv", "frame_000003.csv"]
    for p, k in zip(paths, (1, 2, 3)):
        df = pd.read_csv(p, index_col="point")
        fr = res.frames[k]
        assert np.array_equal(df[["x", "y"]].to_numpy(), fr.points)
        assert np.array_equal(df["u"].to_numpy(), fr.u) and np.array_equal(df["v"].to_numpy(), fr.v)
        assert np.array_equal(df["valid"].to_numpy(), fr.valid) and np.array_equal(df["status"].to_numpy(), fr.status)
        assert np.array_equal(df["Exx"].to_numpy(), fr.strain["Exx"], equal_nan=True)
    st = read_stereo(results3d)
    paths3 = write_csv(st, tmp_path / "csv3")
    assert [p.name for p in paths3] == ["stereo_000000.csv", "stereo_000001.csv", "stereo_000002.csv"]
    df = pd.read_csv(paths3[2], index_col="point")
    f = st.fields[2]
    for name in ("X", "Z", "U", "W", "exy", "normal_z", "reprojection_px"):
        assert np.array_equal(df[name].to_numpy(), np.asarray(getattr(f, name) if name != "normal_z" else f.normal[:, 2]),
                              equal_nan=True), name
    assert np.array_equal(df["status"].to_numpy(), f.status)
    with pytest.raises(ValueError, match="must be a folder"):
        write_csv(results2d, paths[0])


def test_mat_reads_back_with_scipy(results2d, results3d, tmp_path):
    import scipy.io

    res = read_results(results2d)
    m = scipy.io.loadmat(write_mat(results2d, tmp_path / "run.mat"))
    assert m["frame"].ravel().tolist() == [1, 2, 3] and m["u"].shape == (3, NY * NX)
    for row, k in enumerate((1, 2, 3)):
        fr = res.frames[k]
        assert np.array_equal(m["u"][row], fr.u) and np.array_equal(m["valid"][row], fr.valid.astype(np.uint8))
        assert np.array_equal(m["exx"][row], fr.strain["exx"], equal_nan=True)
    assert np.array_equal(m["x"].ravel(), res.frames[1].points[:, 0])
    # 1-based grid indices rebuild the (rows, cols) map, as MATLAB's sub2ind would
    rows, cols = m["grid_row"].ravel().astype(int) - 1, m["grid_col"].ravel().astype(int) - 1
    grid = np.full(tuple(m["grid_shape"].ravel().astype(int)), np.nan)
    grid[rows, cols] = m["u"][1]
    assert grid.shape == (NY, NX) and np.array_equal(grid.ravel(), res.frames[2].u)
    assert str(m["units"]["u"][0, 0][0]) == "px" and "subset" in str(m["info"]["settings"][0, 0][0])
    assert [str(c[0]) for c in m["path"].ravel()] == ["cur1.tif", "cur2.tif", "cur3.tif"]
    st = read_stereo(results3d)
    m3 = scipy.io.loadmat(write_mat(st, tmp_path / "run3d.mat"))
    assert m3["X"].shape == (3, 20) and np.array_equal(m3["W"][2], st.fields[2].W, equal_nan=True)
    assert np.array_equal(m3["status"][1], st.fields[1].status) and str(m3["units"]["Z"][0, 0][0]) == "mm"
    with pytest.raises(ValueError, match=r"must end in \.mat"):
        write_mat(results2d, tmp_path / "run.txt")


def test_netcdf_reads_back_with_xarray(results2d, results3d, tmp_path):
    import xarray as xr

    for source in (results2d, results3d):
        expected = to_xarray(source)
        with xr.open_dataset(write_netcdf(source, tmp_path / (source.stem + ".nc"))) as back:
            back.load()
        assert dict(back.sizes) == dict(expected.sizes)
        for name in list(expected.data_vars) + ["x", "y"]:
            assert back[name].dtype == expected[name].dtype, name
            assert np.array_equal(back[name].values, expected[name].values, equal_nan=True), name
            assert back[name].attrs.get("units") == expected[name].attrs.get("units"), name
        assert back.attrs["settings"] == expected.attrs["settings"]
    assert back["X"].dims == ("frame", "point") and back["valid"].dtype == bool
    # one field too
    with xr.open_dataset(write_netcdf(field2d(1), tmp_path / "one.nc")) as one:
        assert np.array_equal(one["u"].values, field2d(1).u)
    with pytest.raises(ValueError, match=r"must end in \.nc"):
        write_netcdf(results2d, tmp_path / "run.h5")


def test_vtk_of_a_2d_field(tmp_path):
    """write_vtk(Field2D) used to raise ("expected a dic.field3d.Field3D")."""
    import meshio

    f = field2d(1)
    s = strain(f, window=3)
    mesh = meshio.read(write_vtk(f, tmp_path / "f.vtu", strain=s))
    ok = f.valid
    assert np.allclose(mesh.points, np.column_stack([f.points, np.zeros(len(f.points))])[ok])
    v = ok.reshape(NY, NX)
    assert len(mesh.cells_dict["quad"]) == int(np.sum(v[:-1, :-1] & v[:-1, 1:] & v[1:, :-1] & v[1:, 1:]))
    assert np.allclose(mesh.point_data["u"], f.u[ok]) and np.allclose(mesh.point_data["displacement"][:, 1], f.v[ok])
    assert np.array_equal(mesh.point_data["exx"], s.exx[ok], equal_nan=True)
    every = meshio.read(write_vtk(f, tmp_path / "all.vtk", invalid="nan", kind="points"))
    assert len(every.points) == f.n_points and np.isnan(every.point_data["u"][~ok]).all()
    with pytest.raises(ValueError, match="invalid must be"):
        write_vtk(f, tmp_path / "x.vtu", invalid="keep")


@pytest.mark.parametrize("kind3d", [True, False])
def test_vtk_series_has_the_same_points_at_every_step(tmp_path, kind3d):
    """The 3-D series used to write only each state's valid points, so the point set changed between steps."""
    import xml.etree.ElementTree as ET

    import meshio

    fields = [field3d(k) for k in (0, 1, 2)] if kind3d else [field2d(k) for k in (1, 2, 3)]
    pvd = write_vtk_series(fields, tmp_path / "vtk")
    files = [tmp_path / "vtk" / s.get("file") for s in ET.parse(pvd).getroot().findall("./Collection/DataSet")]
    meshes = [meshio.read(p) for p in files]
    assert len(meshes) == 3
    first = meshes[0]
    for mesh, f in zip(meshes, fields):
        assert np.array_equal(mesh.points, first.points)
        assert np.array_equal(mesh.cells_dict["quad"], first.cells_dict["quad"])
        name = "W" if kind3d else "u"
        ix = np.rint((mesh.point_data["image_x"] if kind3d else mesh.points[:, 0])).astype(int)
        iy = np.rint((mesh.point_data["image_y"] if kind3d else mesh.points[:, 1])).astype(int)
        pts = np.rint(f.points).astype(int)
        row = {(x, y): i for i, (x, y) in enumerate(pts)}
        idx = np.array([row[(x, y)] for x, y in zip(ix, iy)])
        valid = f.valid[idx]
        values = np.asarray(getattr(f, name))[idx]
        assert np.array_equal(mesh.point_data[name][valid], values[valid])
        assert np.isnan(mesh.point_data[name][~valid]).all()
    n_expected = 19 if kind3d else NY * NX  # 3-D: the point whose reference match failed has no position
    assert len(first.points) == n_expected
    with pytest.raises(ValueError, match="other points"):
        write_vtk_series([field2d(1), Field2D(**{**field2d(2).__dict__, "points": field2d(2).points + 1})],
                         tmp_path / "bad")
    with pytest.raises(ValueError, match="one kind"):
        write_vtk_series([field3d(0), field2d(1)], tmp_path / "bad")


def test_export_results_checks_its_arguments(results2d, tmp_path):
    with pytest.raises(ValueError, match="format must be one of"):
        export_results(results2d, "xlsx", tmp_path / "x")
    with pytest.raises(ValueError, match=r"ending in \.mat"):
        export_results(results2d, "mat", tmp_path / "x.csv")
    with pytest.raises(ValueError, match="result file not found"):
        export_results(tmp_path / "missing.h5", "csv", tmp_path / "x")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="is a file"):
        export_results(results2d, "vtk", tmp_path / "file")
    empty = tmp_path / "empty.h5"
    ResultWriter(empty, reference_path="r.tif", reference_shape=(10, 10)).close()
    with pytest.raises(ValueError, match="no finished frame"):
        export_results(empty, "csv", tmp_path / "y")


def run(args):
    return CliRunner().invoke(main, ["export", *args], catch_exceptions=False)


def test_cli_export_every_format(results2d, results3d, tmp_path):
    import meshio
    import pandas as pd
    import scipy.io
    import xarray as xr

    r = run([str(results2d), "--format", "csv", "-o", str(tmp_path / "csv")])
    assert r.exit_code == 0, r.output
    assert "wrote 3 CSV file(s), one per frame, to" in r.output
    assert np.array_equal(pd.read_csv(tmp_path / "csv" / "frame_000002.csv")["u"].to_numpy(), field2d(2).u)
    assert run([str(results3d), "-f", "mat", "-o", str(tmp_path / "r.mat"), "-q"]).exit_code == 0
    assert scipy.io.loadmat(tmp_path / "r.mat")["W"].shape == (3, 20)
    assert run([str(results2d), "-f", "netcdf", "-o", str(tmp_path / "r.nc")]).exit_code == 0
    with xr.open_dataset(tmp_path / "r.nc") as ds:
        assert ds.sizes["frame"] == 3
    r = run([str(results3d), "-f", "vtk", "-o", str(tmp_path / "vtk"), "--deformed"])
    assert r.exit_code == 0, r.output
    assert "wrote 3 VTK file(s), one per frame, and a ParaView collection" in r.output
    assert "ParaView: open" in r.output and (tmp_path / "vtk" / "stereo.pvd").exists()
    assert len(meshio.read(tmp_path / "vtk" / "stereo_000002.vtu").points) == 19
    assert "export" in CliRunner().invoke(main, ["--help"]).output


def test_cli_export_errors_are_one_line(results2d, tmp_path):
    bad = [
        ([str(tmp_path / "nope.h5"), "-f", "csv", "-o", str(tmp_path / "o")], 1, "result file not found"),
        ([str(results2d), "-f", "mat", "-o", str(tmp_path / "o.txt")], 1, "ending in .mat"),
        ([str(results2d), "-f", "csv", "-o", str(tmp_path / "o"), "--deformed"], 2, "--deformed applies to --format vtk and ply only"),
        ([str(results2d), "-f", "xlsx", "-o", str(tmp_path / "o")], 2, "Invalid value"),
    ]
    (tmp_path / "notes.h5").write_text("not hdf5")
    bad.append(([str(tmp_path / "notes.h5"), "-f", "csv", "-o", str(tmp_path / "o")], 1, "cannot open result file"))
    for args, code, text in bad:
        r = CliRunner().invoke(main, ["export", *args])
        assert r.exit_code == code, (args, r.output)
        assert text in r.output and "Traceback" not in r.output and isinstance(r.exception, SystemExit)
