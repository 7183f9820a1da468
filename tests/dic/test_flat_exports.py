"""CSV, MATLAB and netCDF exports and the post-processing time series of long result files (issue 13, "memory
bounded by design"): read one frame at a time (dic.store.ResultFrames), the same output as the eager path that
tabulated the whole file at once (Dataset of to_xarray()), and bad input refused."""
import tracemalloc

import numpy as np
import pytest
from test_export_formats import field2d, results3d  # noqa: F401 (a fixture)
from test_store_compression import KW, long_result_file

from dic._strain import strain
from dic.export import export_results, write_csv, write_mat, write_netcdf
from dic.postprocess import extensometer, line_profile, point_history, recompute_strain
from dic.store import ResultFrames, ResultReader, ResultWriter, read_results, read_stereo
from dic.tabular import FrameSchema, dataframe

# ------------------------------------------------------------------------------------------------
# the eager path of before (the whole file as one Dataset), as it wrote each format


def eager_csv(res, directory, stem):
    ds = res.to_xarray()
    directory.mkdir()
    per_frame = [c for c in ds.coords if ds.coords[c].dims == ("frame",)]
    for k, index in enumerate(ds["frame"].values):
        one = ds.isel(frame=k).drop_vars(["frame", *[c for c in per_frame if c != "frame"]])
        dataframe(one).to_csv(directory / f"{stem}_{int(index):06d}.csv")


def eager_mat(res, path):
    import scipy.io

    from dic.export import _grid_index

    ds = res.to_xarray()
    out, units, long_names = {"frame": ds["frame"].values.astype(np.float64)}, {}, {}
    for name in list(ds.coords) + list(ds.data_vars):
        if name in ("frame", "point"):
            continue
        arr = ds[name].values
        if arr.dtype == bool:
            arr = arr.astype(np.uint8)
        elif arr.dtype.kind in "USO":
            arr = np.asarray([str(v) for v in arr.ravel()], dtype=object).reshape(arr.shape)
        out[name] = arr
        if ds[name].attrs.get("units"):
            units[name] = ds[name].attrs["units"]
        if ds[name].attrs.get("long_name"):
            long_names[name] = ds[name].attrs["long_name"]
    grid = _grid_index(ds["x"].values, ds["y"].values)
    if grid is not None:
        out["grid_row"], out["grid_col"] = grid[0].astype(np.float64), grid[1].astype(np.float64)
        out["grid_shape"] = np.asarray(grid[2], dtype=np.float64)
    out["units"] = units
    out["long_names"] = long_names
    out["info"] = {str(k): (v if isinstance(v, str) else np.asarray(v)) for k, v in ds.attrs.items()}
    scipy.io.savemat(path, out, do_compression=True, oned_as="row")


def mixed2d(tmp_path, order=1):
    """A 2-D file whose frame 2 has no strain (its strain columns: NaN / False in the table)."""
    path = tmp_path / f"mixed{order}.h5"
    with ResultWriter(path, reference_path="ref.tif", reference_shape=(60, 70), settings={"subset": 15, "step": 8}) as w:
        for k in (1, 2, 3, 4):
            f = field2d(k, order=order)
            w.write_frame(k, f, strain=strain(f, window=3) if k != 2 else None, path=f"cur{k}.tif",
                          attrs={"seconds": 0.1})
    return path


def _mat(path):
    import scipy.io

    return {k: v for k, v in scipy.io.loadmat(path).items() if not k.startswith("__")}


@pytest.mark.parametrize("which", ["2d1", "2d2", "stereo"])
def test_streamed_exports_equal_the_eager_ones(tmp_path, results3d, which):  # noqa: F811
    import xarray as xr

    path = results3d if which == "stereo" else mixed2d(tmp_path, order=int(which[-1]))
    res = read_stereo(path) if which == "stereo" else read_results(path)
    stem = "stereo" if which == "stereo" else "frame"
    # CSV: byte for byte
    eager_csv(res, tmp_path / "eager_csv", stem)
    written = export_results(path, "csv", tmp_path / "csv")
    assert [p.name for p in written] == sorted(p.name for p in (tmp_path / "eager_csv").iterdir())
    for p in written:
        assert p.read_bytes() == (tmp_path / "eager_csv" / p.name).read_bytes(), p.name
    if which == "2d1":  # the frame without strain: empty strain cells, False strain_valid
        text = (tmp_path / "csv" / "frame_000002.csv").read_text().splitlines()
        head, row = text[0].split(","), text[1].split(",")
        assert row[head.index("exx")] == "" and row[head.index("strain_valid")] == "False"
    # MATLAB: the same variables, in the same order, with the same values
    eager_mat(res, tmp_path / "eager.mat")
    export_results(path, "mat", tmp_path / "out.mat")
    a, b = _mat(tmp_path / "eager.mat"), _mat(tmp_path / "out.mat")
    assert list(a) == list(b)
    for k in a:
        assert repr(a[k]) == repr(b[k]), k
    # netCDF: the same Dataset read back, the same variables and attributes on disk
    res.to_xarray().to_netcdf(tmp_path / "eager.nc", engine="h5netcdf")
    export_results(path, "netcdf", tmp_path / "out.nc")
    for decode in (True, False):
        with xr.open_dataset(tmp_path / "eager.nc", decode_cf=decode) as x, \
                xr.open_dataset(tmp_path / "out.nc", decode_cf=decode) as y:
            x, y = x.load(), y.load()
            assert x.identical(y)
            for name in x.variables:
                assert x[name].dtype == y[name].dtype and repr(x[name].attrs) == repr(y[name].attrs), name
    # an in-memory results object gives the same files as its path
    write_csv(res, tmp_path / "csv_obj")
    for p in written:
        assert p.read_bytes() == (tmp_path / "csv_obj" / p.name).read_bytes()


def test_result_frames_reads_a_file_like_the_object_read_back(tmp_path, results3d):  # noqa: F811
    path = mixed2d(tmp_path)
    with ResultFrames(path) as lazy:
        eager = ResultFrames(read_results(path))
        assert lazy.kind == eager.kind == "dic2d" and lazy.indices == eager.indices == [1, 2, 3, 4] and len(lazy) == 4
        assert lazy.settings == eager.settings and lazy.table_attrs() == eager.table_attrs()
        for (i, a), (j, b) in zip(lazy, eager):
            assert i == j and np.array_equal(a.u, b.u) and lazy.frame_paths(i) == eager.frame_paths(j) == (b.path,)
    with ResultFrames(results3d) as lazy:
        eager = ResultFrames(read_stereo(results3d))
        assert lazy.kind == "stereo" and lazy.table_attrs() == eager.table_attrs()
        assert lazy.frame_paths(1) == eager.frame_paths(1) == ("l1.tif", "r1.tif")
        with pytest.raises(ValueError, match="has no finished state 7"):
            lazy.read(7)
    with pytest.raises(ValueError, match="no finished frame 7"):
        eager.read(7)
    with pytest.raises(ValueError, match="expected a result file"):
        ResultFrames(np.zeros(3))
    with pytest.raises(ValueError, match="not found"):
        ResultFrames(tmp_path / "missing.h5")


def test_frame_schema_refuses_other_points_and_a_table_without_frames():
    a = {"x": np.array([0.0, 1.0]), "y": np.array([0.0, 0.0]), "u": np.array([1.0, 2.0])}
    b = {"x": np.array([0.0, 2.0]), "y": np.array([0.0, 0.0]), "u": np.array([1.0, 2.0])}
    schema = FrameSchema()
    with pytest.raises(ValueError, match="no frame"):
        schema.align(1, a)
    schema.add(1, a)
    with pytest.raises(ValueError, match="frame 2 has other points than frame 1"):
        schema.add(2, b)
    with pytest.raises(ValueError, match="frame 3 has other points than frame 1"):
        schema.align(3, b)


def test_exports_refuse_bad_input(tmp_path):
    path = mixed2d(tmp_path)
    for fn, out in ((write_csv, tmp_path / "c"), (write_mat, tmp_path / "m.mat"), (write_netcdf, tmp_path / "n.nc")):
        with pytest.raises(ValueError, match="expected a"):
            fn(42, out)
    for bad in (0, -5, 1.5, "1G", True):
        with pytest.raises(ValueError, match="max_bytes"):
            write_mat(path, tmp_path / "m.mat", max_bytes=bad)
    with pytest.raises(ValueError, match="must end in .mat"):
        write_mat(path, tmp_path / "m.txt")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="must be a folder"):
        write_csv(path, tmp_path / "file")
    with pytest.raises(ValueError, match="stem must be a plain file name"):
        write_csv(path, tmp_path / "c", stem="a/b")
    empty = tmp_path / "empty.h5"
    ResultWriter(empty, **KW).close()
    for fmt, out in (("csv", "c"), ("mat", "e.mat"), ("netcdf", "e.nc")):
        with pytest.raises(ValueError, match="no finished frame"):
            export_results(empty, fmt, tmp_path / out)
    assert not (tmp_path / "e.mat").exists() and not (tmp_path / "e.nc").exists()


def test_mat_over_its_budget_is_refused_before_anything_is_written(tmp_path):
    path = mixed2d(tmp_path)
    with pytest.raises(ValueError, match=r"written whole.*over max_bytes.*netcdf \(MATLAB reads it with ncread"):
        write_mat(path, tmp_path / "m.mat", max_bytes=1000)
    assert not (tmp_path / "m.mat").exists()
    write_mat(path, tmp_path / "m.mat", max_bytes=10**6)  # 4 frames x 30 points: well within
    assert _mat(tmp_path / "m.mat")["u"].shape == (4, 30)


def test_mat_refuses_a_variable_over_what_a_v5_file_holds(monkeypatch, tmp_path):
    import dic.export as export

    path = mixed2d(tmp_path)
    monkeypatch.setattr(export, "MAT_VARIABLE_LIMIT", 4 * 30 * 8)  # a float64 (frame x point) matrix is this big
    with pytest.raises(ValueError, match="at most 2 GiB per variable"):
        write_mat(path, tmp_path / "m.mat", max_bytes=10**9)
    assert not (tmp_path / "m.mat").exists()


# ------------------------------------------------------------------------------------------------
# memory: flat over the file's length


SHORT, LONG = 12, 120  # frames


@pytest.fixture(scope="module")
def long_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("long")
    return tuple(long_result_file(d / name, n, n_side=30) for name, n in (("warm.h5", 2), ("short.h5", SHORT),
                                                                           ("long.h5", LONG)))


def _peak(fn) -> int:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def _frame_bytes(path) -> int:
    with ResultReader(path) as r:
        f = r.read_frame(1)
    return sum(np.asarray(v).nbytes for v in vars(f).values() if isinstance(v, np.ndarray)) + \
        sum(np.asarray(v).nbytes for v in f.strain.values() if isinstance(v, np.ndarray))


FLAT = {
    "csv": lambda src, out: export_results(src, "csv", out / "csv"),
    "netcdf": lambda src, out: export_results(src, "netcdf", out / "run.nc"),
    "extensometer": lambda src, out: extensometer(src, (30, 30), (100, 60)),
    "point_history": lambda src, out: point_history(src, (50, 50), "exx"),
    "line_profile": lambda src, out: line_profile(src, (20, 20), (100, 100), "u", samples=5),
    "recompute_strain": lambda src, out: recompute_strain(src, out / "strain.h5", window=5),
}


@pytest.mark.parametrize("what", list(FLAT))
def test_memory_does_not_grow_with_the_number_of_frames(long_files, tmp_path, what):
    warm, short, long = long_files
    run = FLAT[what]
    run(warm, tmp_path / "warm")  # imports and caches outside the measurement
    peaks = [_peak(lambda: run(src, tmp_path / name)) for src, name in ((short, "a"), (long, "b"))]
    frame = _frame_bytes(long)
    # 10x the frames: the eager path held every frame (at least LONG x frame, in several copies);
    # streamed, the peak is that of a few frames (and the library's own buffers), whatever the length
    assert peaks[1] < 1.25 * peaks[0] + 2 * frame, (what, peaks, frame)
    assert peaks[1] < 0.4 * LONG * frame, (what, peaks, frame)  # far from holding every frame


def test_mat_holds_its_matrices_and_no_other_copy_of_the_file(long_files, tmp_path):
    warm, _, long = long_files
    write_mat(warm, tmp_path / "warm.mat")
    peak = _peak(lambda: write_mat(long, tmp_path / "run.mat"))
    mats = _mat(tmp_path / "run.mat")
    matrices = sum(v.nbytes for v in mats.values() if isinstance(v, np.ndarray) and v.shape[:1] == (LONG,))
    assert matrices > 0.5 * LONG * _frame_bytes(long)  # (what a v5 file needs at once)
    assert peak < 1.5 * matrices, (peak, matrices)


def test_streamed_time_series_equal_those_of_the_object_read_back(long_files, tmp_path):
    _, short, _ = long_files
    res = read_results(short)
    for fn, args in ((extensometer, ((30, 30), (100, 60))), (point_history, ((50, 50), "exx")),
                     (line_profile, ((20, 20), (100, 100), "von_mises"))):
        a, b = fn(short, *args), fn(res, *args)
        for name, value in vars(a).items():
            if isinstance(value, np.ndarray):
                assert np.array_equal(value, getattr(b, name), equal_nan=True), (fn.__name__, name)
    recompute_strain(short, tmp_path / "s.h5", window=5)
    again = read_results(tmp_path / "s.h5")
    for i, f in res.frames.items():
        expected = strain(f, window=5)
        assert np.array_equal(again.frames[i].strain["exx"], expected.exx, equal_nan=True)
        assert np.array_equal(again.frames[i].u, f.u)
    with pytest.raises(ValueError, match="results must be a result file"):
        point_history([1, 2], (50, 50), "u")
