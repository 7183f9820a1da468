"""HDF5 result store (dic/store.py): round trip, per-frame flush, interruption and resume."""
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from dic.store import FORMAT_NAME, SCHEMA_VERSION, ResultWriter, image_digest, read_results
from dic.strain import strain


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
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])}
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
