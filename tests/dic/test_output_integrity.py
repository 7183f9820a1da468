"""Issue 24, defects 1, 2 and 8: every writer takes its output's lock; side files are written whole or
not at all; side outputs of finished frames are checked and rewritten on resume."""
from __future__ import annotations

import errno
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_store import SETTINGS, STEREO_KW, fake_field, fake_field3d, fake_match, fake_rig
from test_store_robust import ENV, TESTS, WRITER_SCRIPT, _assert_frames

from dic.store import ResultFileInUse, ResultWriter, read_results

KW2 = dict(reference_path="r.tif", reference_shape=(60, 60), reference_sha256="abc", settings=SETTINGS)


def _finished(path: Path, indices=(0, 1, 2)) -> Path:
    with ResultWriter(path, **KW2, mode="overwrite") as w:
        for k in indices:
            w.write_frame(k, fake_field(k), path=f"c{k}.tif")
    return path


def _cli(*args, env=None):
    return subprocess.run([sys.executable, "-m", "dic.cli", *map(str, args)], capture_output=True, text=True,
                          env={**ENV, **(env or {})}, timeout=300)


class _Running:
    """A run writing ``out`` in another process (frame 0 written, frames 1 and 2 once released)."""

    def __init__(self, tmp_path: Path, out: Path, env=None):
        self.go = tmp_path / "go"
        script = WRITER_SCRIPT.format(tests=str(TESTS), out=str(out), kind="dic2d", go=str(self.go))
        self.proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, env={**ENV, **(env or {})}, cwd=str(tmp_path))
        line = self.proc.stdout.readline().strip()
        assert line == "ready", self.proc.stderr.read()

    def finish(self):
        self.go.touch()
        stdout, stderr = self.proc.communicate(timeout=120)
        assert self.proc.returncode == 0 and "done" in stdout, stderr


# ------------------------------------------------------------------------------------------------
# defect 1: strain recomputation (and every other writer) takes the output's lock


@pytest.mark.parametrize("hdf5_locking", ["TRUE", "FALSE"])
def test_strain_refuses_a_file_that_a_running_track_writes(tmp_path, monkeypatch, hdf5_locking):
    """Before: ``recompute_strain(other, output=run.h5)`` renamed its file over the one a running job
    wrote (both exit 0, the job's frames gone); with HDF5_USE_FILE_LOCKING=FALSE an in-place
    ``specula strain run.h5`` during the run read a half-written file (RuntimeError traceback)."""
    from dic.postprocess import recompute_strain

    monkeypatch.setenv("HDF5_USE_FILE_LOCKING", hdf5_locking)
    env = {"HDF5_USE_FILE_LOCKING": hdf5_locking}
    other = _finished(tmp_path / "other.h5")
    out = tmp_path / "run.h5"
    run = _Running(tmp_path, out, env)
    try:
        with pytest.raises(ResultFileInUse, match=rf"{out.name} is in use by another process \(pid \d+"):
            recompute_strain(other, out, window=3)  # onto the running job's output
        with pytest.raises(ResultFileInUse, match=rf"{out.name} is in use by another process"):
            recompute_strain(out, window=3)  # in place
        with pytest.raises(ResultFileInUse, match="in use by another process"):
            recompute_strain(out, tmp_path / "copy.h5", window=3)  # from the file being written
        for args in ([out, "--window", 3], [other, "--window", 3, "-o", out]):
            proc = _cli("strain", *args, env=env)
            assert proc.returncode == 1, proc.stdout + proc.stderr
            assert "Traceback" not in proc.stderr and "in use by another process" in proc.stderr, proc.stderr
            assert proc.stderr.strip().startswith("Error:") and len(proc.stderr.strip().splitlines()) == 1
    finally:
        run.finish()
    _assert_frames(out, "dic2d", [0, 1, 2])  # the running job's file is whole
    assert not (tmp_path / "copy.h5").exists()
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no temporary left
    recompute_strain(out, window=3)  # once the run is over
    assert read_results(out).frames[2].strain is not None


def test_output_lock_names_the_output_and_the_holder(tmp_path):
    from dic.store.files import output_lock

    target = tmp_path / "export"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys; from dic.store.files import output_lock\n"
        f"with output_lock({str(target)!r}, 'CSV folder'):\n"
        "    print('held', flush=True); sys.stdin.read()\n")], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        text=True, env=ENV)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(ResultFileInUse, match=rf"output {target} is in use by another process \(pid \d+"):
            with output_lock(target):
                pass
    finally:
        holder.communicate("", timeout=60)
    with output_lock(target) as held:  # released
        assert held == target
    assert not (tmp_path / "export.lock").exists()



class _Holder:
    """Another process holding the lock of ``target`` (as an export or a run writing there does)."""

    def __init__(self, target: Path):
        self.proc = subprocess.Popen([sys.executable, "-c", (
            "import sys; from dic.store.files import output_lock\n"
            f"with output_lock({str(target)!r}):\n"
            "    print('held', flush=True); sys.stdin.read()\n")], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            text=True, env=ENV)
        assert self.proc.stdout.readline().strip() == "held"

    def release(self):
        self.proc.communicate("", timeout=60)


def test_exports_and_side_outputs_refuse_an_output_another_process_writes(tmp_path):
    """Before: two exports into one folder, or an export into the VTK folder of a running track, wrote
    over each other's files."""
    from dic.export import export_results

    src = _finished(tmp_path / "run.h5")
    for fmt, name in (("csv", "out_csv"), ("mat", "out.mat"), ("netcdf", "out.nc"), ("vtk", "out_vtk")):
        out = tmp_path / name
        holder = _Holder(out)
        try:
            with pytest.raises(ResultFileInUse, match=rf"{name} is in use by another process \(pid \d+"):
                export_results(src, fmt, out)
        finally:
            holder.release()
        assert not out.exists()
        export_results(src, fmt, out)  # released
    vtk = tmp_path / "vtk"
    holder = _Holder(vtk)
    try:
        w = ResultWriter(tmp_path / "new.h5", **KW2)
        with pytest.raises(ResultFileInUse, match="vtk is in use by another process"):
            w.hold_outputs(vtk, tmp_path / "figures")
    finally:
        holder.release()
    assert not (tmp_path / "new.h5").exists() and not (tmp_path / "new.h5.lock").exists()
    with ResultWriter(tmp_path / "new.h5", **KW2) as w:  # one folder for both: one lock
        w.hold_outputs(vtk, vtk, None)
        w.write_frame(0, fake_field(0))
    assert not (tmp_path / "vtk.lock").exists()

# ------------------------------------------------------------------------------------------------
# defect 2: side files of finished frames are checked on resume and rewritten when cut short or gone


def _vtu_data(path):
    import meshio

    mesh = meshio.read(path)
    return mesh.points, {k: np.asarray(v) for k, v in mesh.point_data.items()}


def _same_vtu(a, b):
    pa, da = _vtu_data(a)
    pb, db = _vtu_data(b)
    assert np.array_equal(pa, pb) and sorted(da) == sorted(db)
    for k in da:
        assert np.array_equal(da[k], db[k], equal_nan=True), k


def test_resume_rewrites_vtk_files_cut_short_or_deleted(tmp_path):
    """Before: a .vtu truncated by a full disk (invalid XML) or deleted after a kill was skipped by the
    rerun (its frame is done in the .h5) and never repaired."""
    from dic.sequence import track_sequence
    from dic.synth import speckle_pair

    ref, _ = speckle_pair((64, 72), (0, 0), seed=3)
    frames = [speckle_pair((64, 72), (0.4 * k, -0.3 * k), seed=3)[1] for k in range(1, 4)]
    out, vtk = tmp_path / "r.h5", tmp_path / "vtk"
    track_sequence(ref, frames, out, step=8, strain_window=3, device="cpu", vtk_dir=vtk)
    originals = tmp_path / "originals"
    originals.mkdir()
    for k in (1, 2, 3):
        (originals / f"frame_{k:06d}.vtu").write_bytes((vtk / f"frame_{k:06d}.vtu").read_bytes())
    whole = (vtk / "frame_000002.vtu").read_bytes()
    (vtk / "frame_000002.vtu").write_bytes(whole[: len(whole) // 2])  # cut short by a full disk
    (vtk / "frame_000003.vtu").unlink()  # deleted after a kill
    (vtk / ".frame_000003.tmp-0123abcd.vtu").write_bytes(b"<?xml")  # a writer killed before its rename
    with pytest.raises((Exception, SystemExit)):  # whatever the XML parser (or meshio: sys.exit) says of half a file
        _vtu_data(vtk / "frame_000002.vtu")
    before = (vtk / "frame_000001.vtu").stat().st_mtime_ns
    s = track_sequence(ref, frames, out, step=8, strain_window=3, device="cpu", vtk_dir=vtk)
    assert s.skipped == 3  # nothing recomputed: the side files come from the result file
    for k in (1, 2, 3):
        _same_vtu(vtk / f"frame_{k:06d}.vtu", originals / f"frame_{k:06d}.vtu")  # as the run wrote them
    assert (vtk / "frame_000001.vtu").stat().st_mtime_ns == before  # a whole file is left alone
    assert sorted(p.name for p in vtk.iterdir()) == [f"frame_{k:06d}.vtu" for k in (1, 2, 3)]


def test_restore_vtk_files_of_stereo_states(tmp_path):
    from dic.export import restore_vtk_files, write_pvd, write_vtk

    out, vtk = tmp_path / "s.h5", tmp_path / "vtk"
    with ResultWriter(out, rig=fake_rig(), **STEREO_KW) as w:
        w.write_match(fake_match(35))
        for k in range(3):
            w.write_frame(k, fake_field3d(k, k), path=(f"l{k}.tif", f"r{k}.tif"))
        for k in range(3):
            write_vtk(w.read_frame(k), vtk / f"run_{k:06d}.vtu", invalid="nan")
        write_pvd(vtk, [(k, f"run_{k:06d}.vtu") for k in range(3)], stem="run")
        whole = (vtk / "run_000001.vtu").read_bytes()
        (vtk / "run_000001.vtu").write_bytes(whole[:100])
        (vtk / "run_000002.vtu").unlink()
        assert restore_vtk_files(w, vtk, "run", w.done_frames()) == [1, 2]
        assert (vtk / "run_000001.vtu").read_bytes() == whole
        assert restore_vtk_files(w, vtk, "run", w.done_frames()) == []


# ------------------------------------------------------------------------------------------------
# defect 8: an export that fails half-way (a full disk) leaves no truncated file


def _disk_full_after_half(write_bytes):
    """A writer that writes half of its output to the path it is given, then fails as a full disk does."""
    def fail(path, data: bytes):
        Path(path).write_bytes(data[: len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")
    return fail


def _no_temporaries(folder: Path):
    assert [p.name for p in folder.rglob(".*")] == []


@pytest.mark.parametrize("fmt", ["csv", "mat", "netcdf", "vtk"])
def test_export_on_a_full_disk_leaves_no_truncated_file(tmp_path, monkeypatch, fmt):
    """Before: a CSV whose last row had 9 of 24 fields, 0-byte or partial .mat and .vtu files."""
    import meshio
    import pandas
    import scipy.io

    from dic.cli import main
    from dic.export import export_results

    src = _finished(tmp_path / "run.h5")
    out = tmp_path / ("out.mat" if fmt == "mat" else "out.nc" if fmt == "netcdf" else "out")
    export_results(src, fmt, out)  # a previous, whole export
    before = {p: p.read_bytes() for p in sorted(tmp_path.rglob("*")) if p.is_file() and p.suffix != ".h5"}
    calls = []
    if fmt == "csv":
        real = pandas.DataFrame.to_csv

        def to_csv(self, path, *a, **k):
            calls.append(path)
            if len(calls) == 2:  # the second frame's file fails half-way
                _disk_full_after_half(None)(path, real(self, None, *a, **k).encode())
            return real(self, path, *a, **k)
        monkeypatch.setattr(pandas.DataFrame, "to_csv", to_csv)
    elif fmt == "mat":
        def savemat(path, *a, **k):
            _disk_full_after_half(None)(path, b"MATLAB 5.0 MAT-file" + bytes(1000))
        monkeypatch.setattr(scipy.io, "savemat", savemat)
    elif fmt == "netcdf":
        import xarray

        def to_netcdf(self, path, *a, **k):
            _disk_full_after_half(None)(path, b"\x89HDF\r\n\x1a\n" + bytes(1000))
        monkeypatch.setattr(xarray.Dataset, "to_netcdf", to_netcdf)
    else:
        real = meshio.Mesh.write

        def write(self, path, *a, **k):
            calls.append(path)
            if len(calls) == 2:
                _disk_full_after_half(None)(path, b"<?xml version" + bytes(1000))
            return real(self, path, *a, **k)
        monkeypatch.setattr(meshio.Mesh, "write", write)
    with pytest.raises(OSError, match="No space left"):
        export_results(src, fmt, out)
    after = {p: p.read_bytes() for p in sorted(tmp_path.rglob("*")) if p.is_file() and p.suffix != ".h5"}
    assert after == before  # every file whole: the previous ones kept, nothing half-written
    _no_temporaries(tmp_path)
    # through the CLI: one line, exit 1
    from click.testing import CliRunner

    calls.clear()
    res = CliRunner().invoke(main, ["export", str(src), "-f", fmt, "-o", str(out)])
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert res.output.strip().startswith("Error:") and "No space left" in res.output
    _no_temporaries(tmp_path)


def test_side_writers_leave_no_truncated_file(tmp_path, monkeypatch):
    """Images, figures and camera files: whole or not at all (a failure half-way keeps the previous file)."""
    import json

    import tifffile

    from calibration.camera import Camera
    from dic.plots._common import new_figure, save_figure
    from kernels.images import write_image

    img = tmp_path / "a.tif"
    write_image(img, np.full((8, 8), 7, np.uint8))
    cam_path = tmp_path / "cam.json"
    Camera(K=[[1500.0, 0, 640], [0, 1500, 480], [0, 0, 1]], size=(1280, 960)).save(cam_path)
    fig = new_figure((2, 2))
    png = save_figure(fig, tmp_path / "f.png", dpi=50)
    before = {p.name: p.read_bytes() for p in (img, cam_path, png)}

    def half_then_full(path, *a, **k):
        _disk_full_after_half(None)(path, b"0123456789" * 50)
    monkeypatch.setattr(tifffile, "imwrite", half_then_full)
    monkeypatch.setattr(json, "dump", lambda obj, fh, **k: (fh.write('{"K": [[1'), half_then_full(fh.name)))
    monkeypatch.setattr(type(fig), "savefig", lambda self, path, **k: half_then_full(path))
    with pytest.raises(OSError, match="No space left"):
        write_image(img, np.full((8, 8), 9, np.uint8))
    with pytest.raises(OSError, match="No space left"):
        Camera(K=[[1000.0, 0, 640], [0, 1000, 480], [0, 0, 1]], size=(1280, 960)).save(cam_path)
    with pytest.raises(OSError, match="No space left"):
        save_figure(fig, png, dpi=50)
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in (img, cam_path, png)} == before
    assert np.all(tifffile.imread(img) == 7)
    _no_temporaries(tmp_path)
