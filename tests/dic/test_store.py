"""HDF5 result store (dic/store.py): round trip, per-frame flush, interruption and resume."""
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from dic._strain import strain
from dic.store import FORMAT_NAME, SCHEMA_VERSION, ResultWriter, image_digest, read_results


def fake_field(seed, n_side=6):
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(20.0 + 4 * np.arange(n_side), 30.0 + 4 * np.arange(n_side))
    pts = np.stack([xs.ravel(), ys.ravel()], 1)
    n = len(pts)
    return SimpleNamespace(points=pts, u=rng.normal(size=n).astype(np.float32), v=rng.normal(size=n).astype(np.float32),
                           params=rng.normal(size=(n, 6)).astype(np.float32), zncc=rng.random(n).astype(np.float32),
                           iterations=rng.integers(1, 20, n).astype(np.int32), status=rng.integers(0, 7, n),
                           valid=rng.random(n) > 0.2)


SETTINGS = {"subset": 21, "step": 4, "order": 1}


def test_round_trip(tmp_path):
    ref = np.arange(100.0).reshape(10, 10)
    out = tmp_path / "res.h5"
    fields = [fake_field(i) for i in range(3)]
    with ResultWriter(out, reference_path="ref.tif", reference_shape=ref.shape, reference_sha256=image_digest(ref),
                      settings=SETTINGS) as w:
        for i, f in enumerate(fields):
            w.write_frame(i + 1, f, strain=strain(f, window=3), path=f"cur{i}.tif", attrs={"seconds": 0.5})
    res = read_results(out)
    assert res.attrs["format"] == FORMAT_NAME and res.attrs["schema_version"] == SCHEMA_VERSION
    assert res.reference == {"path": "ref.tif", "shape": (10, 10), "sha256": image_digest(ref)}
    assert res.settings == SETTINGS and sorted(res.frames) == [1, 2, 3]
    for i, f in enumerate(fields):
        fr = res.frames[i + 1]
        assert fr.path == f"cur{i}.tif" and fr.attrs["seconds"] == 0.5
        for key in ("points", "u", "v", "params", "zncc", "iterations", "valid"):
            assert np.array_equal(getattr(fr, key), getattr(f, key))
        assert np.array_equal(fr.status, f.status.astype(np.int8))
        s = strain(f, window=3)
        assert np.array_equal(fr.strain["exx"], s.exx, equal_nan=True) and fr.strain["window"] == 3


def test_resume_skips_finished_frames_and_checks_compatibility(tmp_path):
    out = tmp_path / "res.h5"
    kw = dict(reference_path="r.tif", reference_shape=(10, 10), reference_sha256="abc", settings=SETTINGS)
    with ResultWriter(out, **kw) as w:
        w.write_frame(0, fake_field(0))
        w.write_frame(1, fake_field(1))
    with ResultWriter(out, **kw) as w:
        assert w.done_frames() == [0, 1] and w.is_done(1) and not w.is_done(2)
        w.write_frame(2, fake_field(2))
    assert sorted(read_results(out).frames) == [0, 1, 2]
    with pytest.raises(ValueError, match="different settings"):
        ResultWriter(out, **{**kw, "settings": {**SETTINGS, "order": 2}})
    with pytest.raises(ValueError, match="different reference image"):
        ResultWriter(out, **{**kw, "reference_sha256": "xyz"})
    with pytest.raises(ValueError, match="already exists"):
        ResultWriter(out, mode="new", **kw)
    with ResultWriter(out, mode="overwrite", **kw) as w:
        assert w.done_frames() == []


def test_interrupted_run_keeps_finished_frames(tmp_path):
    """A process killed while writing frame 2 leaves frames 0 and 1 readable; a rerun resumes."""
    out = tmp_path / "res.h5"
    script = textwrap.dedent(f"""
        import os, sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_store import fake_field, SETTINGS
        from dic.store import ResultWriter
        w = ResultWriter({str(out)!r}, reference_path="r.tif", reference_shape=(10, 10), settings=SETTINGS)
        w.write_frame(0, fake_field(0))
        w.write_frame(1, fake_field(1))
        g = w._h5["frames"].create_group("000002.partial")   # frame 2 half written ...
        g.create_dataset("u", data=[1.0, 2.0])
        os._exit(1)                                          # ... when the process dies (no close)
    """)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[2])}
    proc = subprocess.run([sys.executable, "-c", script], cwd=str(tmp_path), capture_output=True, text=True, env=env)
    assert proc.returncode == 1, proc.stderr
    assert sorted(read_results(out).frames) == [0, 1]
    with ResultWriter(out, reference_path="r.tif", reference_shape=(10, 10), settings=SETTINGS) as w:
        assert w.done_frames() == [0, 1]
        assert "000002.partial" not in w._h5["frames"]  # the leftover was dropped
        w.write_frame(2, fake_field(2))
    assert sorted(read_results(out).frames) == [0, 1, 2]


def test_bad_files(tmp_path):
    with pytest.raises(ValueError, match="result file not found"):
        read_results(tmp_path / "none.h5")
    with pytest.raises(ValueError, match="image_digest needs an"):
        image_digest(np.zeros(5))
    with pytest.raises(ValueError, match="mode must be"):
        ResultWriter(tmp_path / "m.h5", mode="append")
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    with pytest.raises(ValueError, match="cannot open"):
        read_results(tmp_path / "junk.h5")
    with pytest.raises(ValueError, match="may be corrupt"):
        ResultWriter(tmp_path / "junk.h5")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.attrs["format"] = "something-else"
    with pytest.raises(ValueError, match="not a Specula 2-D DIC result file"):
        read_results(tmp_path / "other.h5")
    with pytest.raises(ValueError, match="not a Specula 2-D DIC result file"):
        ResultWriter(tmp_path / "other.h5")
    with ResultWriter(tmp_path / "ok.h5") as w:
        with pytest.raises(ValueError, match="needs points, u and v"):
            w.write_frame(0, SimpleNamespace(points=np.zeros((2, 2)), u=np.zeros(2)))
        with pytest.raises(ValueError, match="non-negative integer"):
            w.write_frame(-1, fake_field(0))


# ------------------------------------------------------------------------------------------------
# one file family: stereo results go through the same writer, reader and frame protocol


def fake_field3d(seed, index, ny=5, nx=7):
    """A Field3D with random values (NaN where failed) and the details a sequence resumes from."""
    from dic.field3d import Field3D

    rng = np.random.default_rng(seed)
    n = ny * nx
    gy, gx = np.meshgrid(np.arange(ny) * 10.0 + 20, np.arange(nx) * 10.0 + 20, indexing="ij")
    ok = rng.random(n) > 0.1
    val = lambda *shape: np.where(ok.reshape((n,) + (1,) * (len(shape))), rng.normal(size=(n, *shape)), np.nan)
    return Field3D(points=np.column_stack([gx.ravel(), gy.ravel()]), grid_shape=(ny, nx),
                   **{k: val() for k in ("X", "Y", "Z", "U", "V", "W", "exx", "eyy", "exy", "zncc_stereo",
                                         "zncc_left", "zncc_right", "epipolar_ref_px", "epipolar_px",
                                         "reprojection_ref_px", "reprojection_px")},
                   normal=val(3), status=np.where(ok, 0, 2).astype(np.int8), strain_valid=ok.copy(), index=index,
                   details={"params_left": rng.normal(size=(n, 12)), "params_right": rng.normal(size=(n, 12)),
                            "track_left_status": rng.integers(0, 7, n).astype(np.int32)})


def fake_match(n, seed=0):
    from dic._stereo import StereoMatch

    rng = np.random.default_rng(seed)
    return StereoMatch(points_left=rng.normal(size=(n, 2)), points_right=rng.normal(size=(n, 2)),
                       params=rng.normal(size=(n, 12)), zncc=rng.random(n), iterations=np.arange(n, dtype=np.int32),
                       icgn_status=np.zeros(n, np.int32), epipolar_px=rng.random(n),
                       guess_source=np.ones(n, np.int8), status=np.zeros(n, np.int8), n_features=7, order=2)


def fake_rig(baseline=300.0):
    from calibration.camera import Camera
    from calibration.stereo import StereoRig

    K = np.array([[1641.0, 0, 160], [0, 1641.0, 120], [0, 0, 1]])
    return StereoRig(Camera(K=K, size=(320, 240), name="left"), Camera(K=K, size=(320, 240), name="right"),
                     np.eye(3), np.array([-baseline, 0.0, 0.0]))


STEREO_KW = dict(kind="stereo", reference_path=("l0.tif", "r0.tif"), reference_shape=(240, 320),
                 reference_sha256=("aa", "bb"), settings={"step": 20, "roi": [1, 2, 3, 4]})


def _layout(path):
    """Root attribute names, top-level groups and the attribute names of a frame group."""
    with h5py.File(path, "r") as f:
        frame = f["frames"][sorted(f["frames"])[0]]
        return set(f.attrs), set(f), set(frame.attrs), f.attrs["format"], int(f.attrs["schema_version"])


def test_2d_and_stereo_files_share_the_layout(tmp_path):
    from dic.store import STEREO_FORMAT_NAME, ResultReader

    with ResultWriter(tmp_path / "a.h5", reference_path="r.tif", reference_shape=(10, 10), reference_sha256="abc",
                      settings=SETTINGS) as w:
        w.write_frame(1, fake_field(1), path="c.tif", attrs={"seconds": 0.5})
    with ResultWriter(tmp_path / "b.h5", rig=fake_rig(), **STEREO_KW) as w:
        w.write_match(fake_match(35))
        w.write_frame(0, fake_field3d(0, 0), path=("l0.tif", "r0.tif"), attrs={"seconds": 0.5})
    root2, groups2, frame2, fmt2, v2 = _layout(tmp_path / "a.h5")
    root3, groups3, frame3, fmt3, v3 = _layout(tmp_path / "b.h5")
    assert root2 == root3 == {"format", "schema_version", "specula_version", "created", "updated", "compression",
                                  "checksum"}
    assert (fmt2, fmt3) == (FORMAT_NAME, STEREO_FORMAT_NAME) and v2 == v3 == SCHEMA_VERSION
    assert groups2 == {"reference", "settings", "frames"} and groups3 == groups2 | {"rig"}
    common = {"index", "complete", "written", "seconds"}
    assert frame2 == common | {"path"}
    assert frame3 == common | {"left_path", "right_path", "grid_shape", "frame_name", "R_frame_left", "t_frame_left",
                               "strain_type"}  # a state's strain type (issue 25; a 2-D frame's: in its strain group)
    # one reader for both kinds
    for name, kind in (("a.h5", "dic2d"), ("b.h5", "stereo")):
        with ResultReader(tmp_path / name) as r:
            assert r.kind.name == kind and r.done_frames() == ([1] if kind == "dic2d" else [0])
    with ResultReader(tmp_path / "b.h5") as r:
        assert r.reference == {"left_path": "l0.tif", "right_path": "r0.tif", "shape": (240, 320),
                               "left_sha256": "aa", "right_sha256": "bb"}
        assert r.frame_paths(0) == ("l0.tif", "r0.tif") and r.read_match().n_features == 7
    with pytest.raises(ValueError, match="not a Specula 2-D DIC result file"):
        read_results(tmp_path / "b.h5")
    with pytest.raises(ValueError, match="not a Specula stereo result file"):
        ResultReader(tmp_path / "a.h5", kind="stereo")
    with pytest.raises(ValueError, match="not a Specula stereo result file"):
        ResultWriter(tmp_path / "a.h5", rig=fake_rig(), **STEREO_KW)


def test_stereo_round_trip_resume_and_checks(tmp_path):
    from dic.store import read_field, read_stereo

    out = tmp_path / "s.h5"
    fields = [fake_field3d(k, k) for k in range(3)]
    with ResultWriter(out, rig=fake_rig(), **STEREO_KW) as w:
        w.write_match(fake_match(35))
        for k in (0, 1):
            w.write_frame(k, fields[k], path=(f"l{k}.tif", f"r{k}.tif"))
    with ResultWriter(out, rig=fake_rig(), **STEREO_KW) as w:
        assert w.done_frames() == [0, 1] and w.read_match().n_features == 7
        assert np.array_equal(w.frame_arrays(1, ("params_left",))[0], fields[1].details["params_left"])
        w.write_frame(2, fields[2], path=("l2.tif", "r2.tif"))
    back = read_stereo(out)
    assert back.indices == [0, 1, 2] and back.paths[2] == ("l2.tif", "r2.tif") and back.reference_shape == (240, 320)
    assert back.settings == STEREO_KW["settings"] and back.rig.baseline == pytest.approx(300.0)
    for k, f in enumerate(fields):
        got = back.fields[k]
        assert got.index == k and got.grid_shape == f.grid_shape and got.frame_name == f.frame_name
        for key, arr in f.arrays().items():
            assert np.array_equal(got.arrays()[key], arr, equal_nan=True), key
    assert read_field(out, 1).index == 1
    with pytest.raises(ValueError, match="no finished state 5"):
        read_field(out, 5)
    with pytest.raises(ValueError, match="another rig"):
        ResultWriter(out, rig=fake_rig(200.0), **STEREO_KW)
    with pytest.raises(ValueError, match="different settings"):
        ResultWriter(out, rig=fake_rig(), **{**STEREO_KW, "settings": {"step": 10}})
    with pytest.raises(ValueError, match="different reference image pair"):
        ResultWriter(out, rig=fake_rig(), **{**STEREO_KW, "reference_sha256": ("aa", "cc")})
    with pytest.raises(ValueError, match="needs the rig"):
        ResultWriter(tmp_path / "x.h5", **STEREO_KW)
    with pytest.raises(ValueError, match=r"must be a \(left, right\) pair"):
        ResultWriter(tmp_path / "x.h5", rig=fake_rig(), **{**STEREO_KW, "reference_path": "l0.tif"})
    with pytest.raises(ValueError, match="kind must be one of"):
        ResultWriter(tmp_path / "x.h5", kind="3d")
    with ResultWriter(tmp_path / "y.h5") as w:
        with pytest.raises(ValueError, match="has no reference match"):
            w.write_match(fake_match(3))
        with pytest.raises(ValueError, match="has no rig"):
            ResultWriter(tmp_path / "z.h5", rig=fake_rig())


def test_interrupted_stereo_file_resumes_with_identical_results(tmp_path):
    """The frame protocol of stereo files: a process killed while writing state 2 keeps 0 and 1."""
    out = tmp_path / "s.h5"
    script = textwrap.dedent(f"""
        import os, sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_store import fake_field3d, fake_match, fake_rig, STEREO_KW
        from dic.store import ResultWriter
        w = ResultWriter({str(out)!r}, rig=fake_rig(), **STEREO_KW)
        w.write_match(fake_match(35))
        for k in (0, 1):
            w.write_frame(k, fake_field3d(k, k), path=("l.tif", "r.tif"))
        g = w._h5["frames"].create_group("000002.partial")   # state 2 half written ...
        g.create_dataset("X", data=[1.0, 2.0])
        os._exit(1)                                          # ... when the process dies (no close)
    """)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[2])}
    proc = subprocess.run([sys.executable, "-c", script], cwd=str(tmp_path), capture_output=True, text=True, env=env)
    assert proc.returncode == 1, proc.stderr
    from dic.store import read_stereo

    assert read_stereo(out).indices == [0, 1]
    with ResultWriter(out, rig=fake_rig(), **STEREO_KW) as w:
        assert w.done_frames() == [0, 1] and "000002.partial" not in w._h5["frames"]
        w.write_frame(2, fake_field3d(2, 2), path=("l.tif", "r.tif"))
    back = read_stereo(out)
    assert back.indices == [0, 1, 2]
    for k in range(3):
        for key, arr in fake_field3d(k, k).arrays().items():
            assert np.array_equal(back.fields[k].arrays()[key], arr, equal_nan=True), key


def test_reads_and_resumes_v1_stereo_files_of_the_old_writer(tmp_path):
    """Stereo files written before the unified store (same layout, but no /frames group until the
    first state) are read and resumed."""
    from dic.store import read_stereo

    out = tmp_path / "old.h5"
    with h5py.File(out, "w") as h5:  # what dic.sequence wrote when a run stopped after the reference match
        h5.attrs.update({"format": "specula-stereo", "schema_version": 1, "specula_version": "0.1.0",
                         "created": "2026-01-01T00:00:00+00:00", "updated": "2026-01-01T00:00:00+00:00"})
        h5.create_group("rig").attrs["json"] = json.dumps(fake_rig().to_dict())
        h5.create_group("settings").attrs["json"] = json.dumps(STEREO_KW["settings"], sort_keys=True)
        h5.create_group("reference").attrs.update({"left_path": "l0.tif", "right_path": "r0.tif",
                                                   "shape": [240, 320], "left_sha256": "aa", "right_sha256": "bb"})
        g = h5["reference"].create_group("match")
        for k, v in fake_match(35).arrays().items():
            g.create_dataset(k, data=v)
        g.attrs.update({"n_features": 7, "order": 2})
    back = read_stereo(out)
    assert back.indices == [] and back.match.n_features == 7
    with ResultWriter(out, rig=fake_rig(), **STEREO_KW) as w:
        assert w.done_frames() == [] and w.read_match() is not None
        w.write_frame(0, fake_field3d(0, 0), path=("l0.tif", "r0.tif"))
    assert read_stereo(out).indices == [0]


def test_image_digest_is_the_sha256_of_the_float32_grey_levels():
    """The digest stored for each frame (and compared on resume): SHA-256 of the shape's text and the
    image's C-ordered float32 bytes, whatever the array's dtype and memory order."""
    import hashlib

    rng = np.random.default_rng(5)
    u8 = rng.integers(0, 256, (31, 47), dtype=np.uint8)
    for img in (u8, u8.astype(np.uint16) * 257, u8.T, u8[::2, 1::3], u8.astype(np.float64) / 3, u8 > 100):
        want = hashlib.sha256(str(img.shape).encode() + np.asarray(img, np.float32).tobytes(order="C")).hexdigest()
        assert image_digest(img) == want
    assert image_digest(u8) != image_digest(u8.T)
