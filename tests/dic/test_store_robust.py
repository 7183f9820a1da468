"""Result files that survive (issue 15, defects 1-4): the lock, a full disk, resume with other images, fsync.

Both kinds of result file go through the same writer, so most cases run for 2-D and stereo files.
"""
import errno
import os
import shutil
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
from test_store import SETTINGS, STEREO_KW, fake_field, fake_field3d, fake_match, fake_rig

from dic.store import ResultFileInUse, ResultReader, ResultWriteError, ResultWriter, read_results, read_stereo

TESTS = Path(__file__).parent
ENV = {**os.environ, "PYTHONPATH": str(TESTS.parents[1])}
KW2 = dict(reference_path="r.tif", reference_shape=(10, 10), reference_sha256="abc", settings=SETTINGS)


def _writer(out, kind, **kw):
    if kind == "stereo":
        w = ResultWriter(out, rig=fake_rig(), **STEREO_KW, **kw)
        if w.read_match() is None:
            w.write_match(fake_match(35))
        return w
    return ResultWriter(out, **KW2, **kw)


def _field(kind, k):
    return fake_field3d(k, k) if kind == "stereo" else fake_field(k)


def _path(kind, k):
    return (f"l{k}.tif", f"r{k}.tif") if kind == "stereo" else f"c{k}.tif"


def _indices(out, kind):
    return read_stereo(out).indices if kind == "stereo" else sorted(read_results(out).frames)


def _assert_frames(out, kind, indices):
    """The file holds exactly ``indices``, each equal to the field written for it."""
    assert _indices(out, kind) == list(indices)
    if kind == "stereo":
        back = read_stereo(out)
        for k in indices:
            for key, arr in fake_field3d(k, k).arrays().items():
                assert np.array_equal(back.fields[k].arrays()[key], arr, equal_nan=True), (k, key)
    else:
        back = read_results(out)
        for k in indices:
            for key in ("points", "u", "v", "params", "zncc", "iterations", "valid"):
                assert np.array_equal(getattr(back.frames[k], key), getattr(fake_field(k), key)), (k, key)


# ------------------------------------------------------------------------------------------------
# defects 1 and 4: a file held by another process


WRITER_SCRIPT = """
import sys, time
from pathlib import Path
sys.path.insert(0, {tests!r})
from test_store_robust import _writer, _field, _path
w = _writer({out!r}, {kind!r}, mode="overwrite")
w.write_frame(0, _field({kind!r}, 0), path=_path({kind!r}, 0))
print("ready", flush=True)
go = Path({go!r})
t0 = time.time()
while not go.exists() and time.time() - t0 < 60:
    time.sleep(0.02)
for k in (1, 2):
    w.write_frame(k, _field({kind!r}, k), path=_path({kind!r}, k))
w.close()
print("done", flush=True)
"""


@pytest.mark.parametrize("kind", ["dic2d", "stereo"])
def test_second_writer_is_told_in_use_and_the_first_run_survives(tmp_path, kind):
    """Before: the second writer's "w" truncated the running job's file (unreadable afterwards)
    and the resume writer was told "it may be corrupt: delete it"."""
    out, go = tmp_path / "run.h5", tmp_path / "go"
    script = WRITER_SCRIPT.format(tests=str(TESTS), out=str(out), kind=kind, go=str(go))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=ENV, cwd=str(tmp_path))
    try:
        assert proc.stdout.readline().strip() == "ready", proc.stderr.read()
        for mode in ("overwrite", "resume", "new"):
            with pytest.raises(ResultFileInUse, match=r"is in use by another process \(pid \d+") as info:
                _writer(out, kind, mode=mode)
            assert "corrupt" not in str(info.value) and "delete" not in str(info.value)
        with pytest.raises(ResultFileInUse, match="in use by another process"):
            ResultReader(out)  # HDF5's own lock, held by the running writer
    finally:
        go.touch()
        stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 0 and "done" in stdout, stderr
    _assert_frames(out, kind, [0, 1, 2])  # whole: nothing was truncated
    assert not (tmp_path / "run.h5.lock").exists() and not (tmp_path / "run.h5.tmp").exists()


def test_file_open_in_another_program_is_in_use_and_only_unreadable_files_are_corrupt(tmp_path):
    out = tmp_path / "run.h5"
    with ResultWriter(out, **KW2) as w:
        w.write_frame(1, fake_field(1))
    holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import h5py, sys
        f = h5py.File({str(out)!r}, "r")   # e.g. HDFView or a notebook holding the file
        print("open", flush=True)
        sys.stdin.read()
    """)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=ENV)
    try:
        assert holder.stdout.readline().strip() == "open"
        with pytest.raises(ResultFileInUse, match="is in use by another process") as info:
            ResultWriter(out, **KW2)
        assert "corrupt" not in str(info.value)
    finally:
        holder.communicate("", timeout=60)
    with ResultWriter(out, **KW2) as w:  # released: resumes
        assert w.done_frames() == [1]
    (tmp_path / "junk.h5").write_bytes(b"not an HDF5 file at all")
    with pytest.raises(ValueError, match="may be corrupt") as info:
        ResultWriter(tmp_path / "junk.h5", **KW2)
    assert not isinstance(info.value, ResultFileInUse)


def test_stale_lock_and_temporary_files_of_a_killed_run_do_not_block(tmp_path):
    out = tmp_path / "run.h5"
    script = textwrap.dedent(f"""
        import os, sys
        sys.path.insert(0, {str(TESTS)!r})
        from test_store_robust import _writer, _field
        w = _writer({str(out)!r}, "dic2d")
        os._exit(3)   # killed before its first frame: {out.name}.tmp and {out.name}.lock stay behind
    """)
    assert subprocess.run([sys.executable, "-c", script], env=ENV).returncode == 3
    assert (tmp_path / "run.h5.lock").exists() and (tmp_path / "run.h5.tmp").exists() and not out.exists()
    with ResultWriter(out, **KW2) as w:
        w.write_frame(1, fake_field(1))
        assert not (tmp_path / "run.h5.tmp").exists()  # renamed into place with the first frame
    assert sorted(read_results(out).frames) == [1] and not (tmp_path / "run.h5.lock").exists()


@pytest.mark.parametrize("kind", ["dic2d", "stereo"])
def test_overwrite_replaces_the_file_only_once_the_new_run_has_written(tmp_path, kind):
    out = tmp_path / "run.h5"
    with _writer(out, kind) as w:
        for k in (0, 1):
            w.write_frame(k, _field(kind, k), path=_path(kind, k))
    # a new run that fails before writing anything leaves the old file as it was
    with pytest.raises(RuntimeError, match="boom"):
        with ResultWriter(out, mode="overwrite", **(dict(rig=fake_rig(), **STEREO_KW) if kind == "stereo" else KW2)):
            _assert_frames(out, kind, [0, 1])  # readable meanwhile: the new run writes <file>.tmp
            raise RuntimeError("boom")
    _assert_frames(out, kind, [0, 1])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]
    with _writer(out, kind, mode="overwrite") as w:  # stereo: the match is the new run's first data
        w.write_frame(2, _field(kind, 2), path=_path(kind, 2))
    _assert_frames(out, kind, [2])


# ------------------------------------------------------------------------------------------------
# defect 2: a full disk


def _fail_at(monkeypatch, marker):
    """h5py's create_dataset raises ENOSPC inside the group whose name contains ``marker``."""
    original = h5py.Group.create_dataset

    def create_dataset(self, name, *args, **kw):
        if marker in self.name:
            raise OSError(errno.ENOSPC, "No space left on device")
        return original(self, name, *args, **kw)

    monkeypatch.setattr(h5py.Group, "create_dataset", create_dataset)


@pytest.mark.parametrize("kind", ["dic2d", "stereo"])
def test_injected_disk_full_keeps_every_finished_frame_readable_and_resumable(tmp_path, monkeypatch, kind):
    out = tmp_path / "run.h5"
    _fail_at(monkeypatch, "000003.partial")
    w = _writer(out, kind)
    for k in range(3):
        w.write_frame(k, _field(kind, k), path=_path(kind, k))
    noun = "state" if kind == "stereo" else "frame"
    with pytest.raises(ResultWriteError) as info:
        w.write_frame(3, _field(kind, 3), path=_path(kind, 3))
    err = info.value
    assert isinstance(err, ValueError) and isinstance(err, OSError) and err.errno == errno.ENOSPC
    assert str(err).startswith(f"could not write {noun} 3 to {out}: disk full (No space left on device).")
    assert f"keeps its 3 finished {noun}s (last: 2)" in str(err) and "rerun" in str(err)
    with pytest.raises(ValueError, match="is closed"):
        w.write_frame(4, _field(kind, 4), path=_path(kind, 4))
    w.close()  # harmless
    monkeypatch.undo()
    _assert_frames(out, kind, [0, 1, 2])  # the half-written frame was dropped
    with _writer(out, kind) as w:  # resume
        assert w.done_frames() == [0, 1, 2] and not any(n.endswith(".partial") for n in w._h5["frames"])
        for k in (3, 4):
            w.write_frame(k, _field(kind, k), path=_path(kind, k))
    _assert_frames(out, kind, [0, 1, 2, 3, 4])


def test_disk_full_while_creating_a_new_file_writes_nothing(tmp_path, monkeypatch):
    out = tmp_path / "run.h5"
    with ResultWriter(out, **KW2) as w:
        w.write_frame(1, fake_field(1))
    _fail_at(monkeypatch, "000001.partial")
    w = ResultWriter(out, mode="overwrite", **KW2)
    with pytest.raises(ResultWriteError, match="could not write frame 1 .* disk full .* Nothing was written; the previous"):
        w.write_frame(1, fake_field(2))
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]
    assert np.array_equal(read_results(out).frames[1].u, fake_field(1).u)  # the previous file, unchanged


FILL_SCRIPT = """
import sys
sys.path.insert(0, {tests!r})
from test_store import fake_field, SETTINGS
from dic.store import ResultWriter, ResultWriteError
w = ResultWriter({out!r}, reference_path="r.tif", reference_shape=(10, 10), settings=SETTINGS)
try:
    for k in range(10000):
        w.write_frame(k, fake_field(k, n_side=60))
except ResultWriteError as exc:
    print(k, exc, flush=True)
    sys.exit(1)
"""


@pytest.fixture
def small_fs(tmp_path):
    """A 4 MiB tmpfs (root only; skipped where mounting is not allowed)."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    if shutil.which("mount") is None or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mnt)],
                                                       capture_output=True).returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_a_real_full_disk_ends_the_run_with_one_message(small_fs):
    """Before: ~34 h5py tracebacks, a segfault, and a file neither the reader nor resume could open."""
    out = small_fs / "run.h5"
    proc = subprocess.run([sys.executable, "-c", FILL_SCRIPT.format(tests=str(TESTS), out=str(out))],
                          capture_output=True, text=True, env=ENV, timeout=300)
    assert proc.returncode == 1, (proc.returncode, proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr and "Error" not in proc.stderr, proc.stderr[-2000:]
    k, message = proc.stdout.strip().split(" ", 1)
    k = int(k)
    assert k >= 3 and message.startswith(f"could not write frame {k} to {out}: disk full")
    assert f"keeps its {k} finished frames (last: {k - 1})" in message
    same = small_fs.parent / "same.h5"  # the same frames written where there is room, and closed
    with ResultWriter(same, reference_path="r.tif", reference_shape=(10, 10), settings=SETTINGS) as w:
        for i in range(k):
            w.write_frame(i, fake_field(i, n_side=60))
    assert out.stat().st_size <= same.stat().st_size + 65536  # the space reserved for frame k was given back
    res = read_results(out)
    assert sorted(res.frames) == list(range(k))
    for i in range(k):
        assert np.array_equal(res.frames[i].params, fake_field(i, n_side=60).params)
    subprocess.run(["mount", "-o", "remount,size=64m", str(small_fs)], check=True)
    with ResultWriter(out, reference_path="r.tif", reference_shape=(10, 10), settings=SETTINGS) as w:
        assert w.done_frames() == list(range(k))
        w.write_frame(k, fake_field(k, n_side=60))
    assert sorted(read_results(out).frames) == list(range(k + 1))
    assert out.stat().st_size < 4 << 20  # the unused reservation is given back on close


# ------------------------------------------------------------------------------------------------
# defect 3: resume checks the images it is given; fsync at frame boundaries


def test_resume_refuses_frames_of_other_images(tmp_path):
    out = tmp_path / "run.h5"
    with ResultWriter(out, **KW2) as w:
        for k in (1, 2):
            w.write_frame(k, fake_field(k), path=f"c{k}.tif", sha256=f"d{k}")
    with ResultWriter(out, **KW2) as w:
        w.check_frame(1, "c1.tif", "d1")
        w.check_frame(2, "moved/c2.tif", "d2")  # the same image under another path
        w.check_frame(3, "anything.tif", "zz")  # not finished: nothing to compare
        with pytest.raises(ValueError, match=r"holds frame 2 computed from c2\.tif, but this run gives x\.tif for it "
                                             r"\(the images differ\).*--overwrite"):
            w.check_frame(2, "x.tif", "other")
    assert read_results(out).frames[1].attrs["sha256"] == "d1"
    # stereo: both images of the pair
    s = tmp_path / "s.h5"
    with _writer(s, "stereo") as w:
        w.write_frame(1, fake_field3d(1, 1), path=("l1.tif", "r1.tif"), sha256=("a1", "b1"))
    with _writer(s, "stereo") as w:
        w.check_frame(1, ("l1.tif", "r1.tif"), ("a1", "b1"))
        with pytest.raises(ValueError, match=r"holds state 1 computed from \(l1\.tif, r1\.tif\), but this run gives "
                                             r"\(l1\.tif, r9\.tif\)"):
            w.check_frame(1, ("l1.tif", "r9.tif"), ("a1", "b9"))


def test_files_without_digests_resume_by_path_and_say_so_once(tmp_path):
    out = tmp_path / "old.h5"
    with ResultWriter(out, **KW2) as w:
        for k in (1, 2):
            w.write_frame(k, fake_field(k), path=f"c{k}.tif")  # what schema-1 files of older versions hold
    with h5py.File(out, "r") as f:
        assert "sha256" not in f["frames/000001"].attrs
    with ResultWriter(out, **KW2) as w:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            w.check_frame(1, "c1.tif", "d1")
            w.check_frame(2, "c2.tif", "d2")
        assert len(caught) == 1 and "compares their image paths only" in str(caught[0].message)
        with pytest.raises(ValueError, match=r"frame 2 computed from c2\.tif, but this run gives c9\.tif for it "
                                             r"\(the image paths differ\)"):
            w.check_frame(2, "c9.tif", "d2")


def test_fsync_once_per_frame(tmp_path, monkeypatch):
    out = tmp_path / "run.h5"
    with ResultWriter(out, **KW2) as w:
        w.write_frame(0, fake_field(0))
    synced = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real(fd))[1])
    with ResultWriter(out, **KW2) as w:
        fd = w._h5.id.get_vfd_handle()
        synced.clear()
        for k in (1, 2, 3):
            w.write_frame(k, fake_field(k))
            assert synced == [fd] * k  # flushed and fsynced once at the end of every frame
    assert len(synced) == 4  # and once more on close


# ------------------------------------------------------------------------------------------------
# outputs that cannot be written (issue 15, defect 7)


def test_unwritable_outputs_get_one_clear_message(tmp_path):
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ValueError, match=r"cannot write the result file .*afile/sub/run\.h5: .*afile is a file, not a folder"):
        ResultWriter(tmp_path / "afile" / "sub" / "run.h5", **KW2)
    with pytest.raises(ValueError, match=r"cannot write the result file .*afile/run\.h5: .*afile is a file"):
        ResultWriter(tmp_path / "afile" / "run.h5", **KW2)
    (tmp_path / "dir.h5").mkdir()
    with pytest.raises(ValueError, match=r"cannot write the result file .*dir\.h5: it is a folder"):
        ResultWriter(tmp_path / "dir.h5", **KW2)
    if Path("/proc/self").exists():
        with pytest.raises(ValueError, match=r"cannot write the result file /proc/specula/run\.h5: cannot create the folder"):
            ResultWriter("/proc/specula/run.h5", **KW2)
        with pytest.raises(ValueError, match=r"cannot write the result file /proc/run\.h5: the folder /proc does not take new files"):
            ResultWriter("/proc/run.h5", **KW2)


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_folder_and_file(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    with ResultWriter(ro / "run.h5", **KW2) as w:
        w.write_frame(1, fake_field(1))
    (ro / "run.h5").chmod(0o444)
    with pytest.raises(ValueError, match=r"cannot open the result file .*run\.h5 for writing to resume: Permission denied"):
        ResultWriter(ro / "run.h5", **KW2)
    ro.chmod(0o555)
    try:
        with pytest.raises(ValueError, match=r"cannot write the result file .*new\.h5: the folder .*ro does not take new "
                                             r"files \(Permission denied\)"):
            ResultWriter(ro / "new.h5", **KW2)
    finally:
        ro.chmod(0o755)
