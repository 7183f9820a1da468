"""Issue 24, defects 1, 2 and 8: every writer takes its output's lock; side files are written whole or
not at all; side outputs of finished frames are checked and rewritten on resume."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_store import SETTINGS, fake_field
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
